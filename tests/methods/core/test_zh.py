"""Tests for methods/core/zh.py: clamped-cosine Â_l, exact Phong factors, ZH→SH, convolution."""
import math
from fractions import Fraction

import numpy as np
import pytest
import torch
from scipy import integrate, special

from methods.core import sh, zh
from methods.core.frames import to_world
from methods.core.sampling import gauss_legendre_sphere

F64 = torch.float64
EXACT = 1e-12        # float64 round-off on O(1) quantities
GL_REF_TOL = 1e-14    # float64 GL sum of 600 terms, then × (s+1): the reference's own round-off
QUAD_TOL = 1e-11     # scipy.integrate.quad on smooth 1-D integrands (epsabs 1e-13)


def _dirs(n, seed=0):
    d = torch.randn(n, 3, generator=torch.Generator().manual_seed(seed), dtype=F64)
    return d / d.norm(dim=-1, keepdim=True)


def test_clamped_cosine_factors_are_ramamoorthi_hanrahan():
    A = zh.clamped_cosine_factors(7)
    ref = [math.pi, 2 * math.pi / 3, math.pi / 4, 0.0, -math.pi / 24, 0.0, math.pi / 64]
    assert np.abs(A.numpy() - ref).max() < EXACT
    # definition Â_l = 2π ∫₀¹ t P_l(t) dt, to l = 20
    A = zh.clamped_cosine_factors(21)
    for l in range(21):
        q = integrate.quad(lambda t: t * special.eval_legendre(l, t), 0, 1, epsabs=1e-13)[0]
        assert abs(A[l].item() - 2 * math.pi * q) < QUAD_TOL, l
    # ZH coefficients by projection of max(0, t) (GL on [0, 1] only: the kink is at t = 0)
    t, w = zh.gauss_legendre(40)
    t, w = 0.5 * (t + 1), 0.5 * w
    k = (zh.zh_basis(t, 21) * (2 * math.pi * w * t)[:, None]).sum(0)
    assert torch.allclose(zh.clamped_cosine_kernel(21), k, atol=EXACT)


def _phong_literal(s: int, l: int) -> Fraction:
    """The closed forms of the method card, as written (exact rationals)."""
    num, den = Fraction(1), Fraction(1)
    if l % 2:  # (s+1)(s−1)…(s−l+2) / ((s+2)(s+4)…(s+l+1))
        for a in range(s + 1, s - l + 1, -2):
            num *= a
        for b in range(s + 2, s + l + 2, 2):
            den *= b
    else:      # s(s−2)…(s−l+2) / ((s+3)(s+5)…(s+l+1))
        for a in range(s, s - l + 1, -2):
            num *= a
        for b in range(s + 3, s + l + 2, 2):
            den *= b
    return num / den


@pytest.mark.parametrize("s", [0, 1, 2, 5, 30, 101, 1000])
def test_phong_factors_closed_forms_and_quadrature(s):
    order = 61
    F = zh.phong_factors(s, order)
    for l in range(order):
        assert abs(F[l].item() - float(_phong_literal(s, l))) < EXACT, l
    # (s+1) ∫₀¹ t^s P_l(t) dt by Gauss–Legendre on [0, 1]: polynomial degree s + l ≤ 1060 → exact
    t, w = np.polynomial.legendre.leggauss(600)
    t, w = 0.5 * (t + 1), 0.5 * w
    P = np.stack([special.eval_legendre(l, t) for l in range(order)])
    ref = (s + 1) * (P * (w * t ** s)).sum(1)
    assert np.abs(F.numpy() - ref).max() < GL_REF_TOL * (s + 1) + EXACT


@pytest.mark.parametrize("s", [0.5, 7.3, 250.75])
def test_phong_factors_non_integer_exponent(s):
    F = zh.phong_factors(s, 12)
    for l in range(12):
        q = integrate.quad(lambda t: t ** s * special.eval_legendre(l, t), 0, 1, epsabs=1e-14,
                           epsrel=1e-13, limit=200)[0]
        assert abs(F[l].item() - (s + 1) * q) < QUAD_TOL, l


def test_phong_kernel_is_projection_of_the_lobe():
    s, order = 12, 10
    lobe = lambda t: (s + 1) / (2 * math.pi) * t.clamp_min(0) ** s
    # split at the kink: integrate on [0, 1] with GL mapped there
    t, w = zh.gauss_legendre(40)
    t, w = 0.5 * (t + 1), 0.5 * w
    k = (zh.zh_basis(t, order) * (2 * math.pi * w * lobe(t))[:, None]).sum(0)
    assert torch.allclose(zh.phong_kernel(s, order), k, atol=EXACT)
    with pytest.raises(ValueError):
        zh.phong_factors(-1.0, 4)


def test_zh_project_polynomial_exact_and_samples_path():
    order = 6
    k = torch.tensor([0.3, -1.0, 0.5, 0.2, -0.1, 0.05], dtype=F64)
    g = lambda t: (zh.zh_basis(t, order) * k).sum(-1)
    assert torch.allclose(zh.zh_project(g, order), k, atol=EXACT)
    t, _ = zh.gauss_legendre(20)
    samples = torch.stack([g(t), 2 * g(t)], dim=-1)
    assert torch.allclose(zh.zh_project(samples, order), torch.stack([k, 2 * k], -1), atol=EXACT)
    assert torch.allclose(zh.zh_project(samples[:, 0], 4), k[:4], atol=EXACT)


def test_zh_to_sh_matches_zh_eval_batched():
    order = 7
    V, L = 5, 3
    k = torch.randn(V, L, order, generator=torch.Generator().manual_seed(1), dtype=F64)
    axes = _dirs(V * L, seed=2).reshape(V, L, 3)
    f = zh.zh_to_sh(k, axes)
    assert f.shape == (V, L, order * order)
    d = _dirs(40, seed=3)
    summed = zh.zh_lobes_to_sh(k, axes)
    assert summed.shape == (V, order * order)
    for v in range(V):
        ref = sum(zh.zh_eval(k[v, j], axes[v, j], d) for j in range(L))
        assert torch.allclose(sh.reconstruct(summed[v], d), ref, atol=EXACT)
    # a ZH around +z is exactly the m = 0 coefficients
    fz = zh.zh_to_sh(k[0, 0], torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    m0 = [l * (l + 1) for l in range(order)]
    assert torch.allclose(fz[m0], k[0, 0], atol=EXACT)
    assert fz[[i for i in range(order * order) if i not in m0]].abs().max() < EXACT


def test_convolution_is_funk_hecke():
    order = 5
    c = torch.randn(order * order, 2, generator=torch.Generator().manual_seed(4), dtype=F64)
    kern = torch.tensor([1.0, 0.7, -0.3, 0.2, 0.4, 9.0], dtype=F64)  # extra band ignored
    conv = zh.convolve(c, kern)
    d, w = gauss_legendre_sphere(order + 1, 2 * order + 1, dtype=F64)  # exact for the product
    f = sh.reconstruct(c, d)
    for n in _dirs(4, seed=5):
        g = zh.zh_eval(kern[:order], n, d)         # kernel around n, band-limited
        ref = (w[:, None] * g[:, None] * f).sum(0)
        assert torch.allclose(sh.reconstruct(conv, n), ref, atol=EXACT)
    # convolve along another dim
    assert torch.allclose(zh.convolve(c.T.contiguous(), kern, dim=1), conv.T, atol=EXACT)


def test_irradiance_from_clamped_cosine_factors():
    """E(n) = ∫ L(ω) max(0, n·ω) dω = Σ Â_l L_lm y_lm(n) for L band-limited to order 3."""
    order = 3
    L = torch.randn(order * order, generator=torch.Generator().manual_seed(6), dtype=F64)
    E = zh.convolve_factors(L, zh.clamped_cosine_factors(order))
    dl, wl = gauss_legendre_sphere(4, 7, hemisphere=True, dtype=F64)  # exact on the hemisphere
    for n in _dirs(3, seed=7):
        dw = to_world(dl, n.expand_as(dl))
        ref = (wl * dl[:, 2] * sh.reconstruct(L, dw)).sum()
        assert abs(sh.reconstruct(E, n).item() - ref.item()) < EXACT


def test_float32_and_errors():
    c = torch.randn(16, 3)
    out = zh.convolve(c, zh.clamped_cosine_kernel(4))
    assert out.dtype == torch.float32
    f = zh.zh_to_sh(torch.ones(3, 4), torch.tensor([[0.0, 1.0, 0.0]] * 3))
    assert f.dtype == torch.float32 and f.shape == (3, 16)
    with pytest.raises(ValueError):
        zh.convolve(torch.zeros(8, 3), torch.ones(3))
    with pytest.raises(ValueError):
        zh.convolve(torch.zeros(16, 3), torch.ones(3))
    with pytest.raises(ValueError):
        zh.zh_to_sh(torch.ones(4), torch.ones(2))
