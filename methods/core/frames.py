"""The local shading frame, shared with the references (docs/ARCHITECTURE.md, "Conventions").

z = normal n; tangent s and bitangent t from Mitsuba's `coordinate_system` (Duff et al. 2017,
"Building an Orthonormal Basis, Revisited"), so a BRDF evaluated here and in a Mitsuba plugin sees
the same local directions.
"""
from __future__ import annotations

import torch
from torch import Tensor


def _coordinate_components(x: Tensor, y: Tensor, z: Tensor) -> tuple[list[Tensor], list[Tensor]]:
    """The components of s and t (Duff et al. 2017) from those of the unit normal."""
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))  # copysign(1, z)
    a = -1.0 / (sign + z)
    b = x * y * a
    return [1.0 + sign * x * x * a, sign * b, -sign * x], [b, sign + y * y * a, -y]


def coordinate_system(n: Tensor) -> tuple[Tensor, Tensor]:
    """Tangent frame for unit normals.

    Args:
        n: (..., 3) unit normals.
    Returns:
        s, t: (..., 3) unit tangent and bitangent; (s, t, n) is right-handed and orthonormal.
    """
    if n.shape[-1] != 3:
        raise ValueError(f"normals must have shape (..., 3), got {tuple(n.shape)}")
    s, t = _coordinate_components(*n.unbind(-1))
    return torch.stack(s, dim=-1), torch.stack(t, dim=-1)


def coordinate_system_rows(nT: Tensor) -> tuple[Tensor, Tensor]:
    """`coordinate_system` in the point-minor layout (the same numbers, bit for bit).

    Args:
        nT: (3, ...) unit normals, components first.
    Returns:
        s, t: (3, ...) each.
    """
    if nT.shape[0] != 3:
        raise ValueError(f"normals must have shape (3, ...), got {tuple(nT.shape)}")
    s, t = _coordinate_components(*nT.unbind(0))
    return torch.stack(s), torch.stack(t)


def frame_matrix(n: Tensor, s: Tensor | None = None) -> Tensor:
    """World→local rotation matrices with rows (s, t, n).

    Args:
        n: (..., 3) unit normals; s: optional (..., 3) tangents (else `coordinate_system`).
    Returns:
        (..., 3, 3) R with R @ v_world = v_local.
    """
    if s is None:
        s, t = coordinate_system(n)
    else:
        s = s - (s * n).sum(-1, keepdim=True) * n
        s = s / s.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        t = torch.cross(n, s, dim=-1)
    return torch.stack([s, t, n], dim=-2)


def to_local(v: Tensor, n: Tensor, s: Tensor | None = None) -> Tensor:
    """World vectors (..., 3) → local frame (..., 3) of normals n (..., 3)."""
    return (frame_matrix(n, s) @ v.unsqueeze(-1)).squeeze(-1)


def to_world(v: Tensor, n: Tensor, s: Tensor | None = None) -> Tensor:
    """Local vectors (..., 3) → world, inverse of `to_local`."""
    return (frame_matrix(n, s).transpose(-1, -2) @ v.unsqueeze(-1)).squeeze(-1)


def reflect(wo: Tensor, n: Tensor) -> Tensor:
    """Mirror direction of wo (..., 3) about n (..., 3): R = 2(n·wo)n − wo."""
    return 2.0 * (wo * n).sum(-1, keepdim=True) * n - wo
