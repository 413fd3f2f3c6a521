"""Tests for methods.ptt.brdf_tensor (Sun 2007 §3.2 eq. 2, §4.3 parameterisation, Fig. 5)."""
from __future__ import annotations

import math

import pytest
import torch

from methods.core import tensors as T
from methods.ptt.brdf_space import BlinnPhongSpace
from methods.ptt.brdf_tensor import DiskGrid, brdf_tensor, build_tensor_brdf, hosvd_error_grid, separate_tensor

# float64 interpolation / reconstruction of O(1)–O(1e3) values.
F64_RTOL = 1e-10
# Pythagoras shortcut vs explicit reconstruction: both float64, cancellation in ‖X‖² − ‖G‖².
GRID_RTOL = 1e-8


def test_disk_grid_geometry():
    g = DiskGrid(16)
    assert g.N == int(((torch.arange(16) + 0.5) / 8 - 1).pow(2).add(
        ((torch.arange(16) + 0.5) / 8 - 1).pow(2)[:, None]).lt(1).sum())
    torch.testing.assert_close(g.dirs.norm(dim=-1), torch.ones(g.N, dtype=torch.float64))
    assert (g.dirs[:, 2] > 0).all()
    # the mirror map is the involution (x, y) → (−x, −y)
    torch.testing.assert_close(g.xy[g.mirror], -g.xy)
    assert (g.mirror[g.mirror] == torch.arange(g.N)).all()
    # orthographic solid angles Δ²/z approximate the hemisphere (the 1/z rim singularity makes the
    # midpoint rule converge slowly: 5% at n = 64)
    assert float(DiskGrid(64).solid_angle.sum()) == pytest.approx(2 * math.pi, rel=0.05)


def test_disk_grid_interpolation():
    g = DiskGrid(16)
    vals = torch.stack([torch.ones(g.N), g.xy[:, 0], g.xy[:, 1]], -1).to(torch.float64)
    # node values are reproduced at the nodes
    torch.testing.assert_close(g.interpolate(vals, g.dirs), vals, rtol=F64_RTOL, atol=1e-14)
    # bilinear interpolation reproduces affine functions where all 4 neighbours are inside
    gen = torch.Generator().manual_seed(0)
    xy = (torch.rand(200, 2, generator=gen, dtype=torch.float64) - 0.5) * 1.2
    d = torch.cat([xy, (1 - xy.square().sum(-1, keepdim=True)).sqrt()], -1)
    torch.testing.assert_close(g.interpolate(vals, d), torch.cat([torch.ones(200, 1), xy], -1).to(torch.float64),
                               rtol=F64_RTOL, atol=1e-14)
    # weights form a partition of unity everywhere on the hemisphere, 0 below it
    idx, w = g.locate(torch.tensor([[0.0, 0.999, 0.0447], [0.3, 0.1, -0.9]], dtype=torch.float64))
    assert float(w[0].sum()) == pytest.approx(1.0) and float(w[1].sum()) == 0.0


def test_brdf_tensor_entries_are_material_values():
    space = BlinnPhongSpace(shininess=(2.0, 30.0, 90.0))
    g = DiskGrid(8)
    F = brdf_tensor(space, g)
    assert F.shape == (3, g.N, g.N)
    h, o, i = 1, 5, 17
    ref = space.materials[h].eval(g.dirs[i], g.dirs[o])[0]
    assert float(F[h, o, i]) == pytest.approx(float(ref), rel=F64_RTOL)


def test_hosvd_error_grid_matches_explicit_truncation():
    gen = torch.Generator().manual_seed(0)
    X = torch.randn(7, 20, 20, generator=gen, dtype=torch.float64).cumsum(1)
    grid = hosvd_error_grid(X, (1, 3, 7), (2, 5, 20))
    for a, b in [(1, 2), (3, 5), (7, 20)]:
        direct = float((X - T.tucker_reconstruct(*T.hosvd(X, (a, b, b)))).square().sum())
        assert grid[(a, b)] == pytest.approx(direct, rel=GRID_RTOL, abs=1e-9)
    assert grid[(7, 20)] < 1e-18 * float(X.square().sum()) + 1e-9  # full ranks: exact


def test_tensor_brdf_full_rank_reproduces_remainder_and_lobes():
    space = BlinnPhongSpace(shininess=(5.0, 40.0, 150.0))
    g = DiskGrid(8)
    tb = build_tensor_brdf(space, grid_n=8, ranks=(3, g.N, g.N), method="hosvd", dtype=torch.float64)
    F_r, a, _ = separate_tensor(brdf_tensor(space, g), g)
    torch.testing.assert_close(tb.reconstruct(), F_r, rtol=1e-8, atol=1e-9 * float(F_r.abs().max()))
    w = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    o = torch.arange(0, g.N, 5)
    got = tb.eval(w, g.dirs[None, :, :], g.dirs[o][:, None, :])           # (O, N) at nodes
    torch.testing.assert_close(got, F_r[1][o], rtol=1e-8, atol=1e-9 * float(F_r.abs().max()))
    torch.testing.assert_close(tb.lobe_weights(w, g.dirs[o]), a[1][o])
    assert set(tb.memory()) == {"D", "U_h", "U_o", "U_i", "lobe_a"}


def test_default_ranks_and_bad_input():
    tb = build_tensor_brdf(BlinnPhongSpace(shininess=(5.0, 20.0, 60.0, 150.0)), grid_n=10, method="hosvd")
    assert tb.D.shape == (3, 8, 8) and tb.D.dtype == torch.float32  # Sun 2007 §4.3 (BP)
    with pytest.raises(ValueError):
        DiskGrid(1)
