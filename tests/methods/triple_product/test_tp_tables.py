"""Frame grid, lighting projection and BRDF tables of the local-frame triple product."""
from __future__ import annotations

import math

import pytest
import torch

from methods.core.spherical_haar import Geodesic, triple_integral
from methods.triple_product import brdf_table as bt
from methods.triple_product import lighting as lt
from scenes.materials import Lambert, Phong

# float32 rotation matrices / weights
F32 = 1e-5
# Grid-quadrature error of ∫ f cos dω on the level-3 geodesic grid with 4^2 sub-samples per
# triangle (horizon-straddling triangles, piecewise-constant cosine): measured ≈ 2e-3 relative.
QUAD_REL = 1e-2


def test_grid_frames_orthonormal_and_lookup_hits_nodes():
    g = lt.FrameGrid(5, 8, 4)
    R = lt.grid_frames(g)
    assert R.shape == (g.size, 3, 3)
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    assert torch.allclose(R @ R.transpose(-1, -2), eye, atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(g.size, dtype=R.dtype), atol=1e-12)
    # skip the poles (φ is degenerate there: every φ node is the same normal)
    keep = torch.arange(g.size).reshape(5, 8, 4)[1:-1].reshape(-1)
    for mode in ("nearest", "trilinear"):
        idx, w = lt.lookup_weights(R[keep], g, mode)
        assert torch.allclose(w.sum(-1), torch.ones(keep.numel(), dtype=w.dtype), atol=1e-9)
        best = idx.gather(1, w.argmax(-1, keepdim=True)).squeeze(-1)
        assert torch.equal(best, keep)
        assert torch.allclose(w.amax(-1), torch.ones(keep.numel(), dtype=w.dtype), atol=1e-9)


def test_cell_weights_are_the_merged_trilinear_lookup():
    """`lighting.cell_weights` (n_psi = 1: each (θ, φ) node once, no ψ) = `lookup_weights`'
    trilinear look-up with each node's two ψ entries merged: its even columns' rows, the column
    pairs' summed weights to round-off — at random normals, the poles, and φ a hair below 2π (the
    cell index rounds up to n_phi: `periodic_index`); and `periodic_index` = remainder on [0, 3n)."""
    gen = torch.Generator().manual_seed(5)
    n = torch.nn.functional.normalize(torch.randn(500, 3, generator=gen), dim=-1)
    n = torch.cat([n, torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [0.6, 0.0, -1e-9], [1.0, 0.0, 0.0]])])
    for g in (lt.FrameGrid(5, 8, 1), lt.FrameGrid(17, 32, 1), lt.FrameGrid(3, 1, 1)):
        for R in (lt.local_frames(n, "grid"), lt.local_frames(n, "grid").double()):
            idx, w = lt.lookup_weights(R, g, "trilinear")
            ci, cw = lt.cell_weights(R, g)
            assert ci.shape == (n.shape[0], 4) and cw.dtype == R.dtype
            assert torch.equal(ci, idx[:, 0::2]) and torch.equal(idx[:, 0::2], idx[:, 1::2])
            assert (cw - (w[:, 0::2] + w[:, 1::2])).abs().max() <= 4 * torch.finfo(R.dtype).eps
            assert int(ci.min()) >= 0 and int(ci.max()) < g.size
    with pytest.raises(ValueError):
        lt.cell_weights(lt.local_frames(n, "grid"), lt.FrameGrid(5, 8, 2))
    for m in (1, 2, 7, 32):
        j = torch.arange(3 * m)
        assert torch.equal(lt.periodic_index(j, m), torch.remainder(j, m))


def test_local_frames_tangents():
    n = torch.nn.functional.normalize(torch.randn(200, 3, generator=torch.Generator().manual_seed(0)), dim=-1)
    for tangent in lt.TANGENTS:
        R = lt.local_frames(n, tangent)
        assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3).expand_as(R), atol=F32)
        assert torch.allclose(R[:, 2], n)
    # a floor normal (+Y exactly) maps to grid node (θ = 0, φ = 0, ψ = 0)
    R = lt.local_frames(torch.tensor([[0.0, 1.0, 0.0]]), "grid")
    idx, w = lt.lookup_weights(R, lt.FrameGrid(9, 16, 1), "trilinear")
    assert idx[0, w[0].argmax()] == 0 and w[0].max() == pytest.approx(1.0)
    with pytest.raises(ValueError):
        lt.local_frames(n, "bogus")


def _ulp32(x: torch.Tensor) -> torch.Tensor:
    """The float32 ulp at |x| (float64 in, float64 out; the smallest normal's ulp at 0)."""
    e = torch.frexp(x.abs().float().clamp_min(torch.finfo(torch.float32).tiny))[1].double()
    return torch.ldexp(torch.ones_like(x), (e - 24).to(torch.int32))


def test_polynomial_atan2_acos_within_float32_round_off():
    """`lighting.atan2_f32` / `acos_f32` (the general footprint kernel's angles): within 3e-7 rad of
    the float64 angle of the float32 input on random unit directions, the axes and the octant /
    half-angle switch points (ATen's float32 atan2 / acos: 1.4e-7 / 1.9e-7 there), and through the
    compiled kernel (`methods.core.fused`) as eagerly. acos within 2 ulps of the float32 result
    (ATen's: 0.79): a fixed 3e-7 rad failed at 3.05e-7 (1.28 ulps at acos = 2.11) on a host without
    AVX-512, where ATen's eager float32 kernels round the polynomial's steps differently; in ulps the
    bound is also far tighter than 3e-7 for small angles."""
    from methods.core.fused import fused

    g = torch.Generator().manual_seed(0)
    d = torch.randn(3, 200_000, generator=g, dtype=torch.float64)
    d = (d / d.norm(dim=0)).float()
    t8 = math.tan(math.pi / 8)
    ys = torch.tensor([0.0, -0.0, 1.0, -1.0, 0.0, 1e-30, -1e-30, t8, -t8, 1.0, 1.0, 3.0, -2.0, 0.0])
    xs = torch.tensor([1.0, 1.0, 0.0, 0.0, -1.0, -1.0, -1.0, 1.0, -1.0, t8, 1.0, -3.0, -2.0, 0.0])
    y, x = torch.cat([d[0], ys]), torch.cat([d[2], xs])
    ref = torch.atan2(y.double(), x.double())
    ref = torch.where((y == 0) & (x < 0), math.pi, ref)     # atan2(-0, x < 0): +π here (the same u mod 1)
    c = torch.cat([d[1], torch.linspace(-1.0, 1.0, 20001), torch.tensor([0.5, -0.5, 1.0, -1.0, 0.0])])
    for f_atan2, f_acos in ((lt.atan2_f32, lt.acos_f32), (fused(lt.atan2_f32), fused(lt.acos_f32))):
        assert (f_atan2(y, x).double() - ref).abs().max() <= 3e-7
        ref_c = torch.acos(c.double())
        assert ((f_acos(c).double() - ref_c).abs() / _ulp32(ref_c)).max() <= 2.0


def test_project_lighting_rotates_the_env_map():
    geo = Geodesic(2)
    g = lt.FrameGrid(3, 4, 2)
    R = lt.grid_frames(g)

    def radiance(d):  # a smooth RGB "env map": L(d) = (1 + d_x, 1 + d_y, 1 + d_z)
        return 1.0 + d

    L = lt.project_lighting(radiance, R, geo, supersample=2)  # (F, 3, K)
    assert L.shape == (g.size, 3, geo.n)
    # constant part: the level-0 averages of 1 + (R^T ω) average to ≈ 1
    from methods.core.spherical_haar import inverse
    fine = inverse(L.double())  # (F, 3, K) per-triangle means
    c = geo.centres(dtype=torch.float64)
    expect = 1.0 + torch.einsum("pj,fji->fip", c, R)  # 1 + (R^T c)_i
    # triangle-mean vs centre value of a linear function: differs by O(triangle size²)
    assert (fine - expect).abs().max() < 0.05


def test_brdf_table_albedo_closed_forms():
    geo = Geodesic(3)
    grid = bt.OutgoingGrid(3, 4)
    L1 = torch.zeros(geo.n, dtype=torch.float64)
    L1[:20] = 1.0  # L ≡ 1, V ≡ 1
    lam = bt.brdf_table(Lambert(kd=(0.2, 0.5, 0.8)), geo, grid).double()  # (n_o, 3, K)
    alb = triple_integral(L1, L1, lam)  # ∫ kd/π cos dω = kd
    assert torch.allclose(alb, torch.tensor([0.2, 0.5, 0.8], dtype=torch.float64).expand_as(alb), rtol=QUAD_REL)
    s = 20.0
    # ωo = normal: ∫ (s+1)/(2π) cos^s θ cos θ dω = (s+1)/(s+2)
    class AtNormal(bt.OutgoingGrid):
        def directions(self, *, dtype=torch.float64):
            return torch.tensor([[0.0, 0.0, 1.0]], dtype=dtype)

    ph = bt.brdf_table(Phong(kd=0.0, ks=1.0, s=s), geo, AtNormal(1, 1)).double()
    assert triple_integral(L1, L1, ph[0]) == pytest.approx(torch.full((3,), (s + 1) / (s + 2), dtype=torch.float64),
                                                           rel=3 * QUAD_REL)


def test_outgoing_weights_nodes_and_horizon():
    grid = bt.OutgoingGrid(4, 6)
    d = grid.directions()
    idx, w = bt.outgoing_weights(d, grid)
    best = idx.gather(1, w.argmax(-1, keepdim=True)).squeeze(-1)
    assert torch.equal(best, torch.arange(grid.size))
    assert torch.allclose(w.amax(-1), torch.ones(grid.size, dtype=w.dtype), atol=1e-9)
    idx, w = bt.outgoing_weights(torch.tensor([[1.0, 0.0, -0.5]]), grid)  # below horizon → θ = 90°
    assert (idx[w > 1e-9] // grid.n_phi == grid.n_theta - 1).all()
    with pytest.raises(ValueError):
        bt.OutgoingGrid(0, 4)
