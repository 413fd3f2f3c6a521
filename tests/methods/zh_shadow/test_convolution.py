"""Phong convolution operator M^α (Nowrouzezahrai 2008 §4.2, Appendix A): closed form vs
quadrature vs sympy vs the core ZH kernels."""
from __future__ import annotations

import math

import pytest
import torch

from methods.core.zh import clamped_cosine_kernel, phong_kernel
from methods.zh_shadow.convolution import (appendix_a, phong_operator, phong_operator_quadrature,
                                           phong_transfer_operator, sparsity)

# The card's requirement: closed form and quadrature agree to 1e-6 (measured: ≤ 2e-14 at order 4).
AGREE = 1e-6
# float64 round-off of sums of ~10 terms of size ≤ 1.
EXACT = 1e-12
ALPHAS = [1.0, 1.5, 2.0, 3.7, 10.0, 33.3, 100.0, 200.0]


@pytest.mark.parametrize("alpha", ALPHAS)
def test_closed_form_equals_quadrature(alpha):
    C = phong_operator(alpha, 4, dtype=torch.float64)
    Q = phong_operator_quadrature(alpha, 4)
    assert (C - Q).abs().max().item() <= AGREE
    assert (appendix_a(alpha) - C).abs().max().item() <= EXACT


@pytest.mark.parametrize("alpha", [1.0, 7.5, 200.0])
def test_higher_order_closed_form(alpha):
    """Orders beyond the paper's 4 (the method's `order` config)."""
    C = phong_operator(alpha, 6, dtype=torch.float64)
    assert (C - phong_operator_quadrature(alpha, 6)).abs().max().item() <= AGREE


def _phong_operator_per_entry(alpha: float, order: int) -> torch.Tensor:
    """`phong_operator` entry by entry (one sum of the u-moments times B(α+1, k+1) each, in k order,
    in plain float64 arithmetic): the oracle of its one-product form. Not ``np.dot``: its summation
    order is the BLAS kernel's and differs between hosts (an AVX-512 host left −6.0e-16 where the k-order
    sum cancels to 0 exactly, at order 5, α = 0), and the non-zero pattern is compared exactly."""
    import numpy as np

    from methods.zh_shadow.convolution import _u_moments

    n2, kmax = order * order, 4 * order
    beta = np.empty(kmax)
    beta[0] = 1.0 / (alpha + 1.0)
    for k in range(1, kmax):
        beta[k] = beta[k - 1] * k / (alpha + k + 1.0)
    M = np.zeros((n2, n2))
    for i, j, d in _u_moments(order):
        if i <= j:
            acc = float(d[0]) * float(beta[0])
            for k in range(1, d.shape[0]):
                acc = acc + float(d[k]) * float(beta[k])
            M[i, j] = M[j, i] = acc
    return torch.as_tensor(M)


@pytest.mark.parametrize("order", [1, 2, 4, 5, 8, 9])
def test_phong_operator_equals_per_entry_sums(order):
    """`phong_operator` (every entry's sum k by k over zero-padded coefficients, all entries at
    once) = the per-entry dot products to float64 round-off of the sums' terms (Σ_k |d_k| B_k: at
    high orders and small α the terms cancel), with the same non-zero pattern (the run-time block
    plans are keyed on it)."""
    import numpy as np

    from methods.zh_shadow.convolution import _u_moments

    n2 = order * order
    for alpha in ALPHAS + [0.0, 0.37, 12.0, 57.3]:
        got = phong_operator(alpha, order, dtype=torch.float64)
        want = _phong_operator_per_entry(alpha, order)
        beta = [1.0 / (alpha + 1.0)]
        for k in range(1, 4 * order):
            beta.append(beta[-1] * k / (alpha + k + 1.0))
        scale = torch.zeros(n2, n2, dtype=torch.float64)
        for i, j, d in _u_moments(order):
            scale[i, j] = scale[j, i] = float(np.dot(np.abs(d), beta[: d.shape[0]]))
        assert torch.equal(got != 0, want != 0), (order, alpha)
        assert ((got - want).abs() <= 1e-14 * scale).all(), (order, alpha)
        assert torch.equal(got, got.T)


def test_sparsity_and_structure():
    M = phong_operator(12.0, 4, dtype=torch.float64)
    nz, uniq = sparsity(M)
    assert nz == pytest.approx(44 / 256)            # the paper's "17.1 % non-zero"
    assert uniq == pytest.approx(20 / 256)          # 20 distinct values (the paper counts 15)
    assert torch.equal(M, M.T)
    assert torch.linalg.eigvalsh(M).min() >= -EXACT  # a Gram matrix of a positive weight
    # non-zero only where m = m'
    m_of = torch.tensor([i - math.isqrt(i) * (math.isqrt(i) + 1) for i in range(16)])
    assert (M[m_of[:, None] != m_of[None, :]] == 0).all()


@pytest.mark.parametrize("alpha", [1.0, 4.0, 37.0])
def test_constant_visibility_gives_the_zonal_lobe(alpha):
    """t = ((α+1)/(2π)) M^α v for V ≡ 1 is the SH of the normalised Phong lobe about z, whose m = 0
    coefficients are `methods.core.zh.phong_kernel` (α = 1: the clamped cosine / π)."""
    v = torch.zeros(16, dtype=torch.float64)
    v[0] = math.sqrt(4 * math.pi)
    t = phong_transfer_operator(alpha, 4, dtype=torch.float64) @ v
    zonal = [l * (l + 1) for l in range(4)]
    assert torch.allclose(t[zonal], phong_kernel(alpha, 4), atol=EXACT)
    assert t[[i for i in range(16) if i not in zonal]].abs().max() <= EXACT
    if alpha == 1.0:
        assert torch.allclose(t[zonal], clamped_cosine_kernel(4) / math.pi, atol=EXACT)


def test_sympy_derivation_of_the_corrected_entries():
    """Derive the entries the OCR'd appendix gets wrong (or omits) symbolically; show the printed
    forms are wrong and the corrected ones (`appendix_a`) right."""
    import sympy as sp
    a, t = sp.symbols("alpha t", positive=True)

    def entry(l1, l2, m):
        K = lambda l: sp.sqrt(sp.Rational(2 * l + 1) / (4 * sp.pi) * sp.factorial(l - m) / sp.factorial(l + m))  # noqa: E731
        P = lambda l: (1 - t**2) ** sp.Rational(m, 2) * sp.diff(sp.legendre(l, t), t, m)  # noqa: E731
        return 2 * sp.pi * K(l1) * K(l2) * sp.integrate(sp.expand(P(l1) * P(l2)) * t**a, (t, 0, 1), conds="none")

    A = lambda x: a + x  # noqa: E731
    printed = {  # as in the text
        (0xB, 0xB): 21 * (2 * a**2 + 4 * a + 5) / (2 * A(1) * A(3) * A(4) * A(7)),
        (0x6, 0xC): sp.sqrt(35) * (a**2 + 2 * a + 6) / (2 * A(1) * A(2) * A(6)),
    }
    derived = {(0xB, 0xB): entry(3, 3, 1), (0x6, 0xC): entry(2, 3, 0), (0x0, 0xC): entry(0, 3, 0),
               (0x6, 0x6): entry(2, 2, 0)}
    for alpha in (2.0, 5.5, 60.0):
        M = appendix_a(alpha)
        for (i, j), e in derived.items():
            assert float(e.subs(a, alpha)) == pytest.approx(M[i, j].item(), rel=1e-12)
        for (i, j), e in printed.items():
            assert abs(float(e.subs(a, alpha)) - M[i, j].item()) > 1e-4 * abs(M[i, j].item())
        assert M[0x0, 0xB] == 0 and M[0x0, 0xC] > 0       # printed "M_0B" is M_0C (∝ α − 1)
        assert M[0x6, 0x6] > 0                             # missing from the printed list


def test_bad_alpha():
    for bad in (-1.0, float("nan"), float("inf")):
        with pytest.raises(ValueError):
            phong_operator(bad)
    with pytest.raises(ValueError):
        phong_operator(2.0, 0)
