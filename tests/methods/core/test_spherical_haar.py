"""Tests for methods.core.spherical_haar (Ma 2006 §3.1 spherical Haar wavelets, tripling rules)."""
from __future__ import annotations

import math

import pytest
import torch

from methods.core import spherical_haar as sh

# float64 transforms/sums of O(1) numbers over ≤ 5120 terms: a few hundred ulps at most.
F64_EXACT = 1e-11


def _rand(shape, seed):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, generator=g, dtype=torch.float64)


def test_geodesic_geometry():
    G = sh.Geodesic(3)
    assert [t.shape[0] for t in G.triangles] == [20, 80, 320, 1280]
    for l in range(4):
        om = G.solid_angles(l, dtype=torch.float64)
        assert abs(om.sum().item() - 4 * math.pi) < 1e-12
        assert (om > 0).all()
    # children partition their parent: the 4 children's solid angles sum to the parent's
    om2, om3 = G.solid_angles(2, dtype=torch.float64), G.solid_angles(3, dtype=torch.float64)
    torch.testing.assert_close(om3.reshape(-1, 4).sum(-1), om2, atol=1e-14, rtol=0)
    # documented child order: b, c, d share the parent's corners p0, p1, p2; a is the centre
    P, C = G.triangles[2], G.triangles[3].reshape(-1, 4, 3, 3)
    torch.testing.assert_close(C[:, 1, 0], P[:, 0])
    torch.testing.assert_close(C[:, 2, 1], P[:, 1])
    torch.testing.assert_close(C[:, 3, 2], P[:, 2])
    # outward counter-clockwise orientation
    T = G.triangles[3]
    assert ((T[:, 0] * torch.cross(T[:, 1], T[:, 2], dim=-1)).sum(-1) > 0).all()
    # centres are unit and inside their triangle (locate round trip)
    c = G.centres(dtype=torch.float64)
    assert torch.equal(G.locate(c), torch.arange(G.n))


def test_locate_random_directions_inside():
    G = sh.Geodesic(2)
    d = _rand((3000, 3), 0)
    d = d / d.norm(dim=-1, keepdim=True)
    T = G.triangles[2][G.locate(d)]
    vol = torch.stack([(d * torch.cross(T[:, i], T[:, (i + 1) % 3], dim=-1)).sum(-1) for i in range(3)], -1)
    assert (vol > -1e-12).all()


@pytest.mark.parametrize("level", [0, 1, 3])
def test_round_trip_exact(level):
    x = _rand((4, 20 * 4 ** level), 1)
    torch.testing.assert_close(sh.inverse(sh.forward(x)), x, atol=F64_EXACT, rtol=0)
    c = _rand((4, 20 * 4 ** level), 2)
    torch.testing.assert_close(sh.forward(sh.inverse(c)), c, atol=F64_EXACT, rtol=0)


@pytest.mark.parametrize("level", [0, 1, 3])
def test_forward_butterfly_equals_forward(level):
    """The unrolled forward transform (sums and differences of the children) = `forward` (float64 to
    summation-order rounding, float32 to float32 round-off)."""
    g = torch.Generator().manual_seed(level)
    f = torch.randn(5, 3, sh.n_triangles(level), generator=g, dtype=torch.float64)
    assert torch.allclose(sh.forward_butterfly(f), sh.forward(f), rtol=0, atol=1e-14)
    f32 = f.float()
    assert (sh.forward_butterfly(f32) - sh.forward(f32)).abs().max() <= 1e-6 * f32.abs().max()


def test_orthogonality_gram_matrix():
    """Gram matrix in the equal-area measure (fine triangle area A_L) is diagonal with A_l."""
    L = 2
    B = sh.basis_matrix(L)  # (K, K) basis function values on fine triangles
    gram = B @ B.T * 0.25 ** L
    expected = torch.diag(sh.support_areas(L, dtype=torch.float64))
    torch.testing.assert_close(gram, expected, atol=F64_EXACT, rtol=0)
    # basis values: scaling 0/1, wavelets of level l are ±1 on exactly 4^(L-l) fine triangles
    lv = sh.coefficient_levels(L)
    assert set(B.unique().tolist()) == {-1.0, 0.0, 1.0}
    nz = (B != 0).sum(-1)
    assert torch.equal(nz, 4 ** (L - lv.clamp_min(0)))
    # the coefficient = ⟨f,Ψ⟩/⟨Ψ,Ψ⟩ (projection definition)
    f = _rand((20 * 16,), 3)
    proj = (B @ f) * 0.25 ** L / sh.support_areas(L, dtype=torch.float64)
    torch.testing.assert_close(sh.forward(f), proj, atol=F64_EXACT, rtol=0)


def _quadrature_triple(f, g, h):
    L = sh.level_of_size(f.shape[-1])
    return (sh.inverse(f) * sh.inverse(g) * sh.inverse(h)).sum(-1) * 0.25 ** L


def test_tripling_rules_equal_quadrature_tensor():
    """C_ijk from the three rules == brute-force ∫ΨiΨjΨk on the finest grid, for all ijk (L = 3)."""
    L = 3
    B = sh.basis_matrix(L)  # (K, T)
    K = B.shape[0]
    ijk, val = sh.tripling_coefficients(L)
    # C = Σ_t A_L B[:, t]⊗B[:, t]⊗B[:, t]; exactly 1 + 3L basis functions are non-zero on each t
    nz = (B.T != 0).nonzero()[:, 1].reshape(B.shape[1], 1 + 3 * L)  # (T, 1 + 3L)
    bt = B.T.gather(1, nz)  # (T, 1 + 3L)
    I = torch.stack(torch.broadcast_tensors(nz[:, :, None, None], nz[:, None, :, None], nz[:, None, None, :]), 0)
    v = bt[:, :, None, None] * bt[:, None, :, None] * bt[:, None, None, :] * 0.25 ** L
    C = torch.sparse_coo_tensor(I.reshape(3, -1), v.reshape(-1), (K, K, K), check_invariants=True).coalesce()
    keep = C.values().abs() > F64_EXACT  # structural zeros cancel (e.g. ∫ψ³ = 0)
    Ci, Cv = C.indices()[:, keep], C.values()[keep]
    R = torch.sparse_coo_tensor(ijk.T, val, (K, K, K), check_invariants=True).coalesce()
    assert torch.equal(R.indices(), Ci)
    torch.testing.assert_close(R.values(), Cv, atol=F64_EXACT, rtol=0)


@pytest.mark.parametrize("level", [1, 4])
def test_triple_integral_dense_matches_quadrature(level):
    K = 20 * 4 ** level
    f, g, h = _rand((3, K), 4), _rand((3, K), 5), _rand((1, K), 6)
    torch.testing.assert_close(sh.triple_integral(f, g, h), _quadrature_triple(f, g, h),
                               atol=F64_EXACT * K, rtol=F64_EXACT)


@pytest.mark.parametrize("n_a,n_b", [(20, 80), (320, 5), (0, 10), (5120, 5120)])
def test_triple_integral_sparse_matches_quadrature(n_a, n_b):
    """Truncated (sparse) V and ρ, dense L, level 4 (the paper's 5120 directions)."""
    L = 4
    K = 20 * 4 ** L
    a, b, c = _rand((5, K), 7), _rand((5, K), 8), _rand((5, K), 9)
    ai, av = sh.keep_largest(a, n_a, weights=sh.support_areas(L, dtype=torch.float64))
    bi, bv = sh.keep_top(b, n_b)
    ad = torch.zeros_like(a).scatter(-1, ai, av)
    bd = sh.keep_top_dense(b, n_b)
    got = sh.triple_integral_sparse(ai, av, bi, bv, c)
    torch.testing.assert_close(got, _quadrature_triple(ad, bd, c), atol=F64_EXACT * K, rtol=F64_EXACT)
    # row chunking does not change the result
    torch.testing.assert_close(sh.triple_integral_sparse(ai, av, bi, bv, c, chunk_elems=2 * K), got,
                               atol=F64_EXACT * K, rtol=F64_EXACT)
    # shared dense third function (K,)
    got1 = sh.triple_integral_sparse(ai, av, bi, bv, c[0])
    torch.testing.assert_close(got1, _quadrature_triple(ad, bd, c[:1]), atol=F64_EXACT * K, rtol=F64_EXACT)


def test_product_project():
    L = 2
    f, g, h = _rand((2, 320), 10), _rand((2, 320), 11), _rand((2, 320), 12)
    p = sh.product_project(f, g)
    # ⟨Proj(fg), h⟩ = ∫ f g h  (Parseval in the unnormalised basis: Σ p_k h_k ⟨Ψk,Ψk⟩)
    torch.testing.assert_close((p * h * sh.support_areas(L, dtype=torch.float64)).sum(-1),
                               _quadrature_triple(f, g, h), atol=F64_EXACT, rtol=0)
    # and equals Σ_ij C_ijk f_i g_j / ⟨Ψk,Ψk⟩ from the rules
    ijk, val = sh.tripling_coefficients(L)
    K = 320
    C = torch.zeros(K, K, K, dtype=torch.float64)
    C[ijk[:, 0], ijk[:, 1], ijk[:, 2]] = val
    ref = torch.einsum("ijk,bi,bj->bk", C, f, g) / sh.support_areas(L, dtype=torch.float64)
    torch.testing.assert_close(p, ref, atol=F64_EXACT, rtol=0)


def test_truncation_strategies():
    """Adaptive (largest area-weighted) vs top-only on a function with a sharp feature: both
    errors fall with n, and adaptive beats top-only (Ma 2006 Fig. 7/8)."""
    G = sh.Geodesic(4)
    sun = torch.tensor([0.3, 0.8, 0.52], dtype=torch.float64)
    sun = sun / sun.norm()
    fn = lambda d: 0.2 + (((d * sun).sum(-1) > 0.97).double()) * 5.0  # noqa: E731
    c = G.project(fn, supersample=1, dtype=torch.float64)
    w = sh.support_areas(4, dtype=torch.float64)
    norm = lambda x: (x.square() * w).sum().sqrt()  # noqa: E731  (L2 in the equal-area measure)
    ea, et = [], []
    for n in (20, 80, 320, 1280):
        ea.append(norm(c - sh.keep_largest_dense(c, n, weights=w)).item())
        et.append(norm(c - sh.keep_top_dense(c, n)).item())
    assert all(x >= y for x, y in zip(ea, ea[1:])) and all(x >= y for x, y in zip(et, et[1:]))
    assert all(a <= t + 1e-12 for a, t in zip(ea, et))
    assert ea[2] < 0.7 * et[2]
    # keep everything → exact
    assert norm(c - sh.keep_largest_dense(c, c.numel(), weights=w)) == 0


def test_project_solid_angle_weight_integrates_real_measure():
    """With the density folded into one factor, the triple integral of (1, 1, f) is ∫ f dω."""
    G = sh.Geodesic(3)
    fn = lambda d: 1.0 + d[..., 1] ** 2  # ∫ = 4π + 4π/3   # noqa: E731
    fw = G.project(fn, supersample=2, solid_angle_weight=True, dtype=torch.float64)
    one = G.project(lambda d: torch.ones(d.shape[:-1], dtype=d.dtype), dtype=torch.float64)
    val = sh.triple_integral(one, one, fw).item()
    # piecewise-constant (level 3 + 2 supersample) quadrature of a smooth function: ~1e-4 rel.
    assert abs(val - (4 * math.pi + 4 * math.pi / 3)) < 1e-3 * 16.76
    # without the density it is the equal-area integral (total area 20)
    f0 = G.project(lambda d: torch.ones(d.shape[:-1], dtype=d.dtype), dtype=torch.float64)
    assert abs(sh.triple_integral(one, one, f0).item() - 20.0) < F64_EXACT


def test_bad_sizes():
    with pytest.raises(ValueError):
        sh.forward(torch.zeros(3, 50))
    with pytest.raises(ValueError):
        sh.triple_integral_sparse(torch.zeros(2, 3, dtype=torch.long), torch.zeros(2, 3),
                                  torch.zeros(3, 3, dtype=torch.long), torch.zeros(3, 3), torch.zeros(80))
