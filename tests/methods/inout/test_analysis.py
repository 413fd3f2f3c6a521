"""Mahajan, Tseng & Ramamoorthi 2008 — the in-out BRDF factorization analysis, pinned to the paper.

Matrices are built at the paper's 40 × 40 per direction (1600 × 1600, §3.2) and cached per module
(a handful of 1600² eigen-decompositions, a few seconds each on a loaded 2-core machine).
"""
from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import pytest
import torch

from methods.inout import analysis as A
from scenes.materials import CookTorrance, Lambert, Phong, TorranceSparrow

PAPER_N = 40  # Mahajan 2008 §3.2: 40⁴ BRDF matrix

# Sphere SVD vs exact F_l (eq. 9). The (cos θ, φ) grid is not rotation invariant, so the 2l+1
# degenerate singular values of a band split slightly, and the midpoint rule has O(1/n²) error.
# Measured at 40×40: band means agree with F_l to 1e-4 (s=10) / 1e-3 (s=32); individual values
# deviate by ≤ 0.009 (s=10) / 0.03 (s=32) from the band splitting.
BAND_MEAN_TOL = 2e-3
SV_TOL = 0.04
# ∫∫ρ² (Frobenius energy × Δ²) vs the closed form 2(s+1)²/(2s+1): midpoint-rule error of the grid
# (measured 2e-4 at s=10, 2.4e-3 at s=30).
ENERGY_RTOL = 1e-2
# Paper's claims, tolerances from the issue: slopes ±15 %, K(s=30) ±15 %, TS σ=0.2 ±25 %.
SLOPE_RTOL = 0.15
K30_RTOL = 0.15
TS_RTOL = 0.25
# Sphere K at 40×40 vs the grid-free K from exact F_l: the grid must not cap K (measured equal
# for s ≤ 32; 1 term apart at s = 32/48 in the study).
GRID_K_TOL = 2
# Fig. 5: hemisphere σ_k ≈ F_l with l+1 per band. "Approximately": the horizon cuts off part of
# the physical lobe, lowering every σ_k (measured ≤ 0.082 below at s = 30, 0.127 at s = 10).
HEMI_SV_TOL = 0.1
# Eq. 12: l* ≈ √(6s) from the e⁻³ decay of the exact F_l (eq. 11 is approximate: measured l* is
# 3–5 % below √(6s)).
LSTAR_RTOL = 0.1

SLOPE_S = (4.0, 8.0, 16.0, 32.0)


@pytest.fixture(autouse=True, scope="module")
def _one_torch_thread():
    # 1600² eigen-decompositions: with 2 pytest-xdist workers on 2 shared cores, 2 torch threads
    # per worker oversubscribe the machine (measured 10× slower); restored afterwards.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@lru_cache(maxsize=None)
def sphere_sv(s: float, n: int = PAPER_N) -> torch.Tensor:
    M = A.brdf_matrix(lambda wi, wo: A.phong_lobe_sphere(wi, wo, s), n, "sphere")
    return A.singular_values(M, "sphere")


@lru_cache(maxsize=None)
def hemi_sv(s: float, n: int = PAPER_N) -> torch.Tensor:
    M = A.brdf_matrix(Phong(kd=0.0, ks=1.0, s=s), n, "hemisphere")
    return A.singular_values(M, "hemisphere")


# -- building blocks --------------------------------------------------------------------------


def test_grid_is_equal_area_and_on_domain():
    d = A.direction_grid(8, domain="hemisphere")
    assert d.shape == (64, 3)
    assert torch.allclose(d.norm(dim=-1), torch.ones(64, dtype=d.dtype), atol=1e-12)
    assert (d[:, 2] > 0).all()
    z = torch.sort(torch.unique(d[:, 2].round(decimals=12))).values
    assert torch.allclose(z, (torch.arange(8, dtype=d.dtype) + 0.5) / 8, atol=1e-12)
    assert A.cell_solid_angle(8, "hemisphere") == pytest.approx(2 * math.pi / 64)
    assert A.cell_solid_angle(8, "sphere") == pytest.approx(4 * math.pi / 64)


def test_constant_brdf_has_one_operator_singular_value_equal_to_area():
    # ρ = c: T f = c ∫ f, rank one, h = g = 1/√area, σ = c · area — checks the Δ scaling exactly.
    c = 0.3
    for domain, area in (("sphere", 4 * math.pi), ("hemisphere", 2 * math.pi)):
        M = A.brdf_matrix(lambda wi, wo: torch.full(wi.shape[:-1], c, dtype=wi.dtype), 6, domain)
        sv = A.singular_values(M, domain)
        assert sv[0].item() == pytest.approx(c * area, rel=1e-12)
        assert sv[1:].abs().max().item() < 1e-6
        assert A.terms_for_energy(sv) == 1


def test_gram_singular_values_match_svd():
    M = A.brdf_matrix(lambda wi, wo: A.phong_lobe_sphere(wi, wo, 10.0), 10, "sphere")
    a = A.singular_values(M, "sphere")
    b = A.singular_values(M, "sphere", method="svd")
    assert torch.allclose(a, b, atol=1e-7)  # gram: ~1e-8·σ_1 absolute (docstring)


def test_terms_for_energy():
    sv = torch.tensor([3.0, 2.0, 1.0, 0.0], dtype=torch.float64)  # energies 9, 4, 1 of 14
    assert A.terms_for_energy(sv, 0.5) == 1
    assert A.terms_for_energy(sv, 13 / 14) == 2
    assert A.terms_for_energy(sv, 0.99) == 3
    assert A.terms_for_energy(sv.flip(0), 0.5) == 1  # sorted internally
    with pytest.raises(ValueError):
        A.terms_for_energy(sv, 1.5)
    with pytest.raises(ValueError):
        A.terms_for_energy(torch.zeros(3))


def test_bad_input_raises():
    with pytest.raises(ValueError):
        A.direction_grid(8, domain="disk")
    with pytest.raises(ValueError):
        A.direction_grid(0)
    with pytest.raises(ValueError):
        A.singular_values(torch.zeros(3, 4))
    with pytest.raises(ValueError):
        A.brdf_matrix(lambda wi, wo: wi[..., :2], 4)
    with pytest.raises(ValueError):
        A.phong_lobe_sphere(torch.zeros(2, 2), torch.zeros(2, 3), 4.0)


def test_idealised_lobes_equal_materials_above_horizon():
    g = torch.Generator().manual_seed(0)
    v = torch.randn(2, 500, 3, generator=g, dtype=torch.float64)
    v = v / v.norm(dim=-1, keepdim=True)
    v[..., 2] = v[..., 2].abs() + 1e-3
    v = v / v.norm(dim=-1, keepdim=True)
    wi, wo = v[0], v[1]
    p = Phong(kd=0.0, ks=1.0, s=12.0).eval(wi, wo)[..., 0]
    assert torch.allclose(A.phong_lobe_sphere(wi, wo, 12.0), p, rtol=1e-10, atol=1e-12)
    t = TorranceSparrow(kd=0.0, ks=1.0, sigma=0.25).eval(wi, wo)[..., 0]
    assert torch.allclose(A.torrance_sparrow_sphere(wi, wo, 0.25), t, rtol=1e-9, atol=1e-12)
    # ... and the idealised Phong lobe does not vanish below the horizon (that is the point).
    assert A.phong_lobe_sphere(torch.tensor([0.0, 0.0, -1.0]), torch.tensor([0.0, 0.0, -1.0]),
                               4.0).item() == pytest.approx(5 / (2 * math.pi))


def test_zonal_transform_of_phong_curve_is_exact_F_l():
    # quadrature (zonal_transform) vs closed form (methods.core.zh.phong_factors)
    for s in (3.0, 10.0, 37.5):
        curve = lambda th, s=s: (s + 1) / (2 * math.pi) * torch.cos(th).clamp(min=0) ** s  # noqa: E731
        assert torch.allclose(A.zonal_transform(curve, 20), A.phong_F(s, 20), atol=1e-9)


# -- Mahajan 2008 §3.2, eq. 9, Fig. 2: sphere SVD = exact F_l ---------------------------------


@pytest.mark.parametrize("s", [10.0, 32.0])
def test_sphere_singular_values_are_exact_F_l(s):
    sv = sphere_sv(s)
    K = A.terms_for_energy(sv)
    L = math.isqrt(K) - 1  # complete bands inside the 99 % energy
    F = A.phong_F(s, L)
    for l in range(L + 1):  # each F_l repeated 2l+1 times (eq. 9)
        band = sv[l * l:(l + 1) ** 2]
        assert abs(band.mean().item() - F[l].item()) < BAND_MEAN_TOL, (l, band, F[l])
    pred = A.repeat_bands(A.phong_F(s, 4 * L + 8), "sphere")
    assert (sv[:K] - pred[:K]).abs().max().item() < SV_TOL
    # The approximation exp(−l²/2s) (eq. 11) is visibly worse than the SVD's agreement with F_l.
    approx_err = (A.phong_F_approx(s, L) - F).abs().max().item()
    assert approx_err > 5 * BAND_MEAN_TOL


@pytest.mark.parametrize("s", [4.0, 32.0])
def test_sphere_energy_is_closed_form(s):
    assert (sphere_sv(s) ** 2).sum().item() == pytest.approx(A.phong_energy_sphere(s), rel=ENERGY_RTOL)


# -- Fig. 3A: K(99 %) linear in s, 5s on the sphere and 2.5s on the hemisphere ----------------


def test_sphere_slope_is_5():
    K = [A.terms_for_energy(sphere_sv(s)) for s in SLOPE_S]
    for s, k in zip(SLOPE_S, K):  # the 40×40 grid does not cap K
        assert abs(k - A.phong_terms_sphere_exact(s)) <= GRID_K_TOL, (s, k)
    slope = np.polyfit(SLOPE_S, K, 1)[0]  # measured 4.55 (K = 23, 40, 77, 150)
    assert slope == pytest.approx(5.0, rel=SLOPE_RTOL), (slope, K)


def test_hemisphere_slope_is_2_5():
    K = [A.terms_for_energy(hemi_sv(s)) for s in SLOPE_S]
    slope = np.polyfit(SLOPE_S, K, 1)[0]  # measured 2.37 (K = 13, 22, 42, 79)
    assert slope == pytest.approx(2.5, rel=SLOPE_RTOL), (slope, K)


def test_hemisphere_s30_needs_75_terms():
    # Mahajan 2008 §3.4 / Fig. 6: K ≈ 2.5 s = 75 for s = 30 (measured 75 at 40×40 and at 80×80).
    K = A.terms_needed(30.0, 0.99)  # this paper's terms-vs-exponent contributor
    assert K == pytest.approx(75, rel=K30_RTOL)


def test_hemisphere_s20_needs_about_50_terms():
    # Mahajan 2008 §5: "a moderate Phong exponent of 20 would need about 50 BRDF factors"
    # (measured 51).
    assert A.terms_needed(20.0, 0.99) == pytest.approx(50, rel=K30_RTOL)


@pytest.mark.xfail(strict=True, reason="measured K(99%) = 6 for s = 1 on the hemisphere at 40x40 "
                   "vs the paper's 2-4 (§3.4, §5); 3 at 90 %, 4 at 95 % energy. The paper's small-s "
                   "numbers follow its K = 2.5s line (2.5 at s = 1); the measured line is "
                   "2.40s + 3.2")
def test_hemisphere_s1_needs_2_to_4_terms():
    assert 2 <= A.terms_needed(1.0, 0.99) <= 4


def test_hemisphere_singular_values_follow_F_l_with_l_plus_1_per_band():
    # Fig. 5: σ_k ≈ F_l, l+1 values per band (not 2l+1).
    s = 32.0
    sv = hemi_sv(s)
    K = A.terms_for_energy(sv)
    F = A.phong_F(s, 60)
    err_hemi = (sv[:K] - A.repeat_bands(F, "hemisphere")[:K]).abs().max().item()
    err_sph = (sv[:K] - A.repeat_bands(F, "sphere")[:K]).abs().max().item()
    assert err_hemi < HEMI_SV_TOL
    assert err_sph > HEMI_SV_TOL  # the multiplicity matters: 2l+1 per band does not fit


# -- eq. 12, §4 / Fig. 7C: l* and half-angle BRDFs -------------------------------------------


@pytest.mark.parametrize("s", [4.0, 16.0, 64.0])
def test_phong_l_star_is_sqrt_6s(s):
    ls = A.l_star(lambda th: torch.cos(th).clamp(min=0) ** s)
    assert ls == pytest.approx(math.sqrt(6 * s), rel=LSTAR_RTOL)


def test_torrance_sparrow_sigma_0_2_needs_about_60_terms():
    # Mahajan 2008 §4: "σ = .2 would need about 60 terms". Measured at the paper's 40×40: 64.
    # (Not converged in n: 79 at 60×60, 85 at 80×80 — the half-angle lobe narrows without bound
    # towards grazing exitant angles, see the report; the paper's number is at its 40⁴ grid.)
    M = A.brdf_matrix(TorranceSparrow(kd=0.0, ks=1.0, sigma=0.2), PAPER_N, "hemisphere")
    K = A.terms_for_energy(A.singular_values(M, "hemisphere"))
    assert K == pytest.approx(60, rel=TS_RTOL)


@pytest.mark.xfail(strict=True, reason="measured K(99%) = 23 for sigma = 0.4 at 40x40 (22 at 60x60, "
                   "21 at 80x80) vs the paper's 'about K = 10-20' (§4)")
def test_torrance_sparrow_sigma_0_4_needs_10_to_20_terms():
    M = A.brdf_matrix(TorranceSparrow(kd=0.0, ks=1.0, sigma=0.4), PAPER_N, "hemisphere")
    assert 10 <= A.terms_for_energy(A.singular_values(M, "hemisphere")) <= 20


def test_k_rule():
    assert A.k_rule(Lambert(kd=0.7)) == 1
    assert A.k_rule(Phong(kd=0.5, ks=0.0, s=50.0)) == 1
    assert A.k_rule(Phong(kd=0.1, ks=0.5, s=30.0)) == 75  # eq. 13
    sig = 0.2
    ts = TorranceSparrow(kd=0.2, ks=1.0, sigma=sig)
    ls = A.l_star(A.half_angle_curve(TorranceSparrow(kd=0.0, ks=1.0, sigma=sig)))
    # Half-angle curve exp(−(θ/σ)²) ≈ Gaussian: F_l ≈ exp(−l²σ²/4) → l* (e⁻³) ≈ √12/σ.
    assert ls == pytest.approx(math.sqrt(12) / sig, rel=0.05)
    assert A.k_rule(ts) == math.ceil(ls**2 / 4)
    k_ct = A.k_rule(CookTorrance(kd=0.0, ks=1.0, m=0.3), n_fallback=12)  # measured fallback
    assert 1 < k_ct < 12**2


def test_terms_needed_rejects_bad_exponent():
    with pytest.raises(ValueError):
        A.terms_needed(0.0, 0.99)
