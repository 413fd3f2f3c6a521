"""Sloan 2002 transfer (methods.sh_prt.transfer) proved against closed forms and Monte Carlo."""
from __future__ import annotations

import math

import pytest
import torch

from methods.core import sh as _sh
from methods.core.frames import to_world
from methods.core.sampling import gauss_legendre_sphere, sample_cosine_hemisphere
from methods.core.visibility import Visibility, offset_origins
from methods.sh_prt import transfer as T
from scenes import procedural as P

# Ramamoorthi & Hanrahan 2001 §2 clamped-cosine factors Â_l, l = 0..6, typed in from the paper
# (independent of `zh.clamped_cosine_factors`).
A_HAT = [math.pi, 2 * math.pi / 3, math.pi / 4, 0.0, -math.pi / 24, 0.0, math.pi / 64]
# float32 storage of t and M (values ≤ ~1): agreement of two exact computations.
EXACT_TOL = 2e-5


def _sphere():
    m = P.icosphere(2, 1.0)
    return m.V.float(), m.F.long(), m.N.float() / m.N.float().norm(dim=-1, keepdim=True)


@pytest.mark.parametrize("order", [2, 5, 7])
def test_unshadowed_diffuse_is_clamped_cosine_zh(order):
    """t_lm(x) = Â_l y_lm(N)/π for every vertex of a sphere, traced (shadowed path: a convex
    object blocks no ray) and in closed form."""
    V, F, N = _sphere()
    vis = Visibility(V, F)
    rays = T.trace_rays(vis, V, N, 64, seed=1)
    assert not rays.blocked.any()
    t = T.shadowed_diffuse(rays, N, order)
    lband = torch.cat([torch.full((2 * l + 1,), A_HAT[l]) for l in range(order)])
    expect = (lband * _sh.sh_eval(N.double(), order).float()) / math.pi
    assert (t - expect).abs().max() < EXACT_TOL
    assert (T.unshadowed_diffuse(N, order) - expect).abs().max() < EXACT_TOL


@pytest.mark.parametrize("order", [3, 5])
def test_unshadowed_glossy_matrix_is_the_hemisphere_product_integral(order):
    """M_U(N)_ij = ∫ y_i y_j max(N·s, 0) ds by a product Gauss rule on N's hemisphere in WORLD
    directions (exact: polynomial integrand) — checks the SH rotation of M_loc."""
    g = torch.Generator().manual_seed(3)
    N = torch.nn.functional.normalize(torch.randn(6, 3, generator=g, dtype=torch.float64), dim=-1)
    d, w = gauss_legendre_sphere(order + 2, 2 * order + 2, hemisphere=True, dtype=torch.float64)
    M = T.unshadowed_glossy(N, order)
    for x in range(N.shape[0]):
        s = to_world(d, N[x].expand_as(d))                            # hemisphere about N, world
        Y = _sh.sh_eval(s, order)
        ref = (Y * (w * d[:, 2])[:, None]).T @ Y
        assert (M[x].double() - ref).abs().max() < EXACT_TOL


def _plane_under_box():
    """A 4×4 plane (y = 0, normal +Y) under a 1.6×0.2×1.6 slab at height 0.5: the slab hides a
    cone of half-angle ≈ 55° above the plane's centre vertices."""
    plane = P.plane((4.0, 4.0), (8, 8))
    slab = P.box((1.6, 0.2, 1.6), (0.0, 0.5, 0.0))
    V = torch.cat([plane.V.float(), slab.V.float()])
    F = torch.cat([plane.F.long(), slab.F.long() + plane.V.shape[0]])
    Np = plane.N.float()
    assert torch.allclose(Np, torch.tensor([0.0, 1.0, 0.0]).expand_as(Np))
    return V, F, plane.V.float(), Np


# Monte Carlo: cosine-weighted directions, t_i = E[y_i V] and M_ij = π E[y_i y_j V]; the bound is
# MC_SIGMAS standard errors of the estimate plus the method's own quadrature error with RAYS
# spherical-Fibonacci rays (visibility is discontinuous). Measured against 2^19 MC samples: max
# coefficient error ≤ 7.7e-4 (t) and 1.6e-3 (M) at J = 2048 (≈ the MC noise itself), ≤ 5.5e-3 /
# 7.1e-3 at J = 256; coefficients are up to 0.33.
MC_SAMPLES = 1 << 17
MC_SIGMAS = 4.0
RAYS = 2048
QUAD_TOL = 2e-3


def test_shadowed_transfer_on_plane_under_box_equals_monte_carlo():
    order = 4
    V, F, Vp, Np = _plane_under_box()
    vis = Visibility(V, F)
    # plane vertices under the centre, under the edge, at the rim of and outside the shadow cone
    pts = [(0.0, 0.0), (0.5, 0.5), (1.0, 0.0), (1.0, 1.0), (1.5, 0.5), (2.0, 2.0)]
    sel = torch.tensor([int(((Vp[:, [0, 2]] - torch.tensor(p)).norm(dim=-1)).argmin()) for p in pts])
    rays = T.trace_rays(vis, Vp[sel], Np[sel], RAYS, seed=0)
    frac = rays.blocked.float().mean(1)
    assert frac.max() > 0.5 and frac.min() < 0.2  # the box really blocks a large part of some hemispheres
    t = T.shadowed_diffuse(rays, Np[sel], order)
    M = T.shadowed_glossy(rays, Np[sel], order, torch.arange(sel.numel()))
    g = torch.Generator().manual_seed(7)
    for k, x in enumerate(sel.tolist()):
        u = torch.rand(MC_SAMPLES, 2, generator=g)
        loc, _ = sample_cosine_hemisphere(u)
        s = to_world(loc, Np[x].expand_as(loc))
        o = offset_origins(Vp[x][None], Np[x][None], scale=vis.scale).expand_as(s)
        vis_ = (~vis.occluded(o.contiguous(), s.contiguous())).double()
        Y = _sh.sh_eval(s.double(), order)
        f = Y * vis_[:, None]                                              # (S, n²)
        ref_t, se_t = f.mean(0), f.std(0) / math.sqrt(MC_SAMPLES)
        ref_M = math.pi * f.T @ Y / MC_SAMPLES                            # π E[y_i y_j V]
        se_M = (math.pi**2 * (f * f).T @ (Y * Y) / MC_SAMPLES - ref_M**2).clamp_min(0).sqrt() / math.sqrt(MC_SAMPLES)
        assert ((t[k].double() - ref_t).abs() <= MC_SIGMAS * se_t + QUAD_TOL).all(), (x, t[k], ref_t)
        assert ((M[k].double() - ref_M).abs() <= MC_SIGMAS * se_M + QUAD_TOL).all(), x


def test_order_out_of_range_is_a_value_error():
    for bad in (1, 11, 5.0, True):
        with pytest.raises(ValueError, match="order"):
            T.check_order(bad)


def test_segment_vecmat_equals_per_row_products():
    """Grouped, padded rows (runs longer than SEGMENT_CAP, empty matrices, one batch split) give the
    per-row a_p · M[idx_p] exactly (float32 summation order aside)."""
    g = torch.Generator().manual_seed(0)
    M = torch.randn(50, 9, 12, generator=g)
    idx = torch.randint(0, 40, (1000,), generator=g)
    idx[:100] = 3                                              # one long run: several segments
    a = torch.randn(1000, 9, generator=g)
    ref = torch.einsum("pd,pdk->pk", a, M[idx])
    old = T.GATHER_FLOATS
    try:
        for floats in (old, 9 * 12 * 5):                       # one batch; five segments per batch
            T.GATHER_FLOATS = floats
            assert (T.segment_vecmat(a, idx, M) - ref).abs().max() < 1e-5
    finally:
        T.GATHER_FLOATS = old
    assert T.segment_vecmat(a[:0], idx[:0], M).shape == (0, 12)
