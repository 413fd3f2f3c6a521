"""The shading frame (`methods.core.frames`): Duff et al.'s tangents are orthonormal and
right-handed, and the point-minor variant returns the same numbers bit for bit."""
from __future__ import annotations

import pytest
import torch

from methods.core.frames import coordinate_system, coordinate_system_rows

# Orthonormality in float32 (a handful of ulps of 1).
ORTHO_TOL = 1e-6


def _normals() -> torch.Tensor:
    g = torch.Generator().manual_seed(3)
    n = torch.randn(2000, 3, generator=g)
    n = torch.cat([n, torch.eye(3), -torch.eye(3), torch.tensor([[0.0, 0.0, -1.0 + 1e-7]])])  # poles, axes
    return n / n.norm(dim=-1, keepdim=True)


def test_coordinate_system_orthonormal_right_handed():
    n = _normals()
    s, t = coordinate_system(n)
    for a, b in ((s, t), (s, n), (t, n)):
        assert (a * b).sum(-1).abs().max() <= ORTHO_TOL
    for a in (s, t):
        assert ((a * a).sum(-1) - 1).abs().max() <= ORTHO_TOL
    assert (torch.linalg.cross(s, t) - n).abs().max() <= 4 * ORTHO_TOL


def test_coordinate_system_rows_bitwise():
    n = _normals()
    s, t = coordinate_system(n)
    sT, tT = coordinate_system_rows(n.T.contiguous())
    assert torch.equal(sT, s.T) and torch.equal(tT, t.T)
    with pytest.raises(ValueError, match="shape"):
        coordinate_system_rows(n)
