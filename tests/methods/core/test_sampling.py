"""Tests for methods/core/sampling.py: weights, exactness, cell membership, sampler moments."""
import math

import pytest
import torch
from scipy import integrate

from methods.core import sampling as S

F64 = torch.float64
EXACT = 1e-12        # float64 round-off for sums of O(1e4) terms
GRID_TOL = 1e-2     # deterministic 32-row / 2048-point sets: midpoint error 2π·n·h³/12 = 4.1e-3 for z²
STRAT_TOL = 3e-2    # one jittered sample per cell: standard error of Σ w z² ≈ 5.7e-3, ×5 sigma
MC_SIGMAS = 5.0      # Monte-Carlo checks at 5 standard errors (false alarm ~ 6e-7)


def _unit(d):
    return torch.allclose(d.norm(dim=-1), torch.ones(d.shape[0], dtype=d.dtype), atol=1e-12)


@pytest.mark.parametrize("fn,area,hemi,tol", [
    (lambda: S.equal_area_sphere(32, 64, dtype=F64), 4 * math.pi, False, GRID_TOL),
    (lambda: S.equal_area_hemisphere(32, 64, dtype=F64), 2 * math.pi, True, GRID_TOL),
    (lambda: S.fibonacci_sphere(2048, dtype=F64), 4 * math.pi, False, GRID_TOL),
    (lambda: S.fibonacci_hemisphere(2048, dtype=F64), 2 * math.pi, True, GRID_TOL),
    (lambda: S.stratified_sphere(32, 64, torch.Generator().manual_seed(1), dtype=F64), 4 * math.pi, False,
     STRAT_TOL),
    (lambda: S.stratified_hemisphere(32, 64, torch.Generator().manual_seed(1), dtype=F64), 2 * math.pi, True,
     STRAT_TOL),
    (lambda: S.gauss_legendre_sphere(16, 32, dtype=F64), 4 * math.pi, False, EXACT),
    (lambda: S.gauss_legendre_sphere(16, 32, hemisphere=True, dtype=F64), 2 * math.pi, True, EXACT),
])
def test_direction_sets_integrate_low_moments(fn, area, hemi, tol):
    d, w = fn()
    assert d.ndim == 2 and d.shape[1] == 3 and w.shape == (d.shape[0],)
    assert _unit(d)
    assert abs(w.sum().item() - area) < EXACT
    if hemi:
        assert (d[:, 2] >= 0).all()
        # ∫_H z dω = π, ∫_H z² dω = 2π/3
        assert abs((w * d[:, 2]).sum().item() - math.pi) < tol
        assert abs((w * d[:, 2] ** 2).sum().item() - 2 * math.pi / 3) < tol
    else:
        # ∫ z² dω = 4π/3, ∫ x y dω = 0, ∫ x² dω = 4π/3
        assert abs((w * d[:, 2] ** 2).sum().item() - 4 * math.pi / 3) < tol
        assert abs((w * d[:, 0] ** 2).sum().item() - 4 * math.pi / 3) < tol
        assert abs((w * d[:, 0] * d[:, 1]).sum().item()) < tol


def test_equal_area_cell_centres():
    nt, npf = 5, 7
    d, w = S.equal_area_sphere(nt, npf, dtype=F64)
    z = d[:, 2].reshape(nt, npf)
    expect = 1 - (torch.arange(nt, dtype=F64) + 0.5) * 2 / nt
    assert torch.allclose(z, expect[:, None].expand(nt, npf), atol=EXACT)
    phi = torch.atan2(d[:, 1], d[:, 0]).remainder(2 * math.pi).reshape(nt, npf)
    assert torch.allclose(phi[0], (torch.arange(npf, dtype=F64) + 0.5) * 2 * math.pi / npf, atol=EXACT)
    assert torch.allclose(w, torch.full_like(w, 4 * math.pi / (nt * npf)))
    # midpoint rule in cos θ: ∫ z² dω − Σ w z² = 2π · n_theta · h³/12 exactly (h = 2/n_theta)
    d, w = S.equal_area_sphere(32, 3, dtype=F64)
    err = 4 * math.pi / 3 - (w * d[:, 2] ** 2).sum().item()
    assert abs(err - 2 * math.pi * 32 * (2 / 32) ** 3 / 12) < EXACT


def test_stratified_one_sample_per_cell_and_reproducible():
    nt, npf = 8, 12
    d, _ = S.stratified_hemisphere(nt, npf, torch.Generator().manual_seed(3), dtype=F64)
    z = d[:, 2].reshape(nt, npf)
    phi = torch.atan2(d[:, 1], d[:, 0]).remainder(2 * math.pi).reshape(nt, npf)
    i = torch.arange(nt, dtype=F64)[:, None]
    j = torch.arange(npf, dtype=F64)[None, :]
    assert ((z <= 1 - i / nt + EXACT) & (z >= 1 - (i + 1) / nt - EXACT)).all()
    assert ((phi >= j * 2 * math.pi / npf - EXACT) & (phi <= (j + 1) * 2 * math.pi / npf + EXACT)).all()
    d2, _ = S.stratified_hemisphere(nt, npf, torch.Generator().manual_seed(3), dtype=F64)
    d3, _ = S.stratified_hemisphere(nt, npf, torch.Generator().manual_seed(4), dtype=F64)
    assert torch.equal(d, d2) and not torch.equal(d, d3)


def test_gauss_legendre_sphere_is_exact_for_polynomials():
    d, w = S.gauss_legendre_sphere(6, 11, dtype=F64)
    # ∫ z⁴ = 4π/5, ∫ x²y² = 4π/15, ∫ x⁴ = 4π/5
    assert abs((w * d[:, 2] ** 4).sum().item() - 4 * math.pi / 5) < EXACT
    assert abs((w * d[:, 0] ** 2 * d[:, 1] ** 2).sum().item() - 4 * math.pi / 15) < EXACT
    assert abs((w * d[:, 0] ** 4).sum().item() - 4 * math.pi / 5) < EXACT


@pytest.mark.parametrize("kind", ["sphere", "hemisphere", "cosine"])
def test_random_samplers_moments_and_pdf(kind):
    n = 200_000
    g = torch.Generator().manual_seed(11)
    u = torch.rand(n, 2, generator=g, dtype=F64)
    warp = {"sphere": S.sample_uniform_sphere, "hemisphere": S.sample_uniform_hemisphere,
            "cosine": S.sample_cosine_hemisphere}[kind]
    d, pdf = warp(u)
    assert _unit(d)
    if kind == "cosine":
        assert torch.allclose(pdf, d[:, 2] / math.pi) and torch.allclose(pdf, S.cosine_hemisphere_pdf(d))
        ez, ez2 = 2 / 3, 1 / 2          # E[cos θ], E[cos² θ] under pdf cos θ/π
    elif kind == "hemisphere":
        assert torch.allclose(pdf, torch.full_like(pdf, 1 / (2 * math.pi)))
        ez, ez2 = 1 / 2, 1 / 3
    else:
        assert torch.allclose(pdf, torch.full_like(pdf, 1 / (4 * math.pi)))
        ez, ez2 = 0.0, 1 / 3
    for val, ref in ((d[:, 2], ez), (d[:, 2] ** 2, ez2), (d[:, 0], 0.0), (d[:, 1], 0.0)):
        se = val.std().item() / math.sqrt(n)
        assert abs(val.mean().item() - ref) < MC_SIGMAS * se
    # the estimator weights integrate 1 over the domain
    dd, w = S.random_directions(n, kind, torch.Generator().manual_seed(5), dtype=F64)
    area = 4 * math.pi if kind == "sphere" else 2 * math.pi
    se = (w * n).std().item() / math.sqrt(n)
    assert abs(w.sum().item() - area) < MC_SIGMAS * se + EXACT


def test_latlong_directions_follow_mitsuba_convention():
    H, W = 9, 16
    d = S.latlong_directions(H, W, dtype=F64)
    assert d.shape == (H, W, 3)
    u = (torch.atan2(d[..., 0], -d[..., 2]) / (2 * math.pi)).remainder(1.0)
    v = torch.acos(d[..., 1].clamp(-1, 1)) / math.pi
    inner = slice(1, H - 1)  # u is undefined at the poles
    assert torch.allclose(u[inner], ((torch.arange(W, dtype=F64) + 0.5) / W).expand(H - 2, W), atol=1e-12)
    assert torch.allclose(v, (torch.arange(H, dtype=F64) / (H - 1))[:, None].expand(H, W), atol=1e-7)
    assert torch.allclose(d[0], torch.tensor([0.0, 1.0, 0.0], dtype=F64).expand(W, 3), atol=1e-12)


def test_latlong_row_weights_are_hat_integrals():
    H = 7
    w = S.latlong_row_weights(H, dtype=F64)
    dl = math.pi / (H - 1)
    for y in range(H):
        hat = lambda t: max(0.0, 1 - abs(t - y * dl) / dl) * math.sin(t)
        ref = integrate.quad(hat, max(0.0, (y - 1) * dl), min(math.pi, (y + 1) * dl), epsabs=1e-14)[0]
        assert abs(w[y].item() - ref) < 1e-12
    assert abs(w.sum().item() - 2.0) < EXACT


def test_latlong_grid_exact_for_piecewise_linear_in_theta_and_converges():
    H, W = 17, 8
    d, w = S.latlong_grid(H, W, dtype=F64)
    assert abs(w.sum().item() - 4 * math.pi) < EXACT
    theta = torch.acos(d[:, 1].clamp(-1, 1))
    # θ is linear on the row grid → integrated exactly: ∫ θ dω = 2π ∫ θ sin θ dθ = 2π²
    assert abs((w * theta).sum().item() - 2 * math.pi ** 2) < 1e-10
    # smooth integrand: second-order convergence of ∫ y⁴ dω = 4π/5
    errs = []
    for H in (17, 33, 65):
        d, w = S.latlong_grid(H, 8, dtype=F64)
        errs.append(abs((w * d[:, 1] ** 4).sum().item() - 4 * math.pi / 5))
    assert errs[1] < errs[0] / 3.5 and errs[2] < errs[1] / 3.5  # ratio → 4 for O(h²)


def test_dtype_and_errors():
    d, w = S.equal_area_sphere(4, 4)
    assert d.dtype == torch.float32 and w.dtype == torch.float32
    d, w = S.latlong_grid(4, 8)
    assert d.dtype == torch.float32
    with pytest.raises(ValueError):
        S.equal_area_sphere(0, 4)
    with pytest.raises(ValueError):
        S.latlong_grid(1, 4)
    with pytest.raises(ValueError):
        S.sample_cosine_hemisphere(torch.rand(5, 3))
    with pytest.raises(ValueError):
        S.random_directions(4, "cube")
