"""The hemispherical 1D-BRDF convolution operator M^α (Nowrouzezahrai et al. 2008 §4.2, Appendix A).

    M^α[l'm', lm] = ∫_{H²} cos^α θ · y_{l'm'}(s) · y_{lm}(s) ds        (eq. 2, z-up hemisphere)
    t = ((α+1)/(2π)) · M^α · v                                          (eq. 2)

t is the SH projection of v(s)·(α+1)/(2π)·max(0, cos θ)^α, i.e. of the visibility times the
normalised Phong lobe about +z (the reflection vector, or the normal for α = 1 = the clamped
cosine: (2/(2π)) M¹ = (1/π) M¹ is the Lambert operator). Real SH of `methods.core.sh` (no
Condon–Shortley phase, index l(l+1)+m).

Closed form (any order, `phong_operator`). The φ integral of two real SH vanishes unless m = m'
(same cos/sin type), and gives π K_l^m K_l'^m·2 (m ≠ 0, from the √2 factors) or 2π K K' (m = 0):

    M^α[l'm, lm] = 2π K_l^|m| K_l'^|m| ∫₀¹ t^α (1−t²)^|m| Q_l^|m|(t) Q_l'^|m|(t) dt,
    Q_l^m = d^m P_l / dt^m,   K_l^m = √((2l+1)/(4π) (l−m)!/(l+m)!).

The polynomial p(t) = (1−t²)^m Q_l^m Q_l'^m is re-expanded in u = 1 − t, p = Σ_k d_k u^k, and
∫₀¹ t^α u^k dt = B(α+1, k+1) = k!/((α+1)(α+2)…(α+k+1)) — a sum of positive, rapidly decreasing
rational functions of α (no cancellation for large α, unlike the monomial moments 1/(α+k+1)).

Appendix A of the paper (`appendix_a`, order 4) lists the same entries factorised. The OCR'd text
has three wrong entries and one missing, found by the sympy derivation in
`tests/methods/zh_shadow/test_convolution.py` and the quadrature (`phong_operator_quadrature`):
  * "M_0B = √7 α₋₁ /(2α₂α₄)": index typo — (0,0)×(3,−1) is zero (m ≠ m'); the entry is M_0C.
  * "M_BB = 21(2α²+4α+5)/(2α₁α₃α₄α₇)": α₄ must be α₅ (the second copy in the text is right).
  * "M_6C = √35(α²+2α+6)/(2α₁α₂α₆)": the denominator is 2α₂α₄α₆.
  * M_66 = 5(α²+2α+3)/(2α₁α₃α₅) is missing from the list.
Non-zeros: 44 of 256 (17.19 %, the paper's "17.1 %"); unique values 20 (7.8 %; the paper's 5.9 %
= 15/256 counts "simple multiples" as not unique).
"""
from __future__ import annotations

import functools
import math

import numpy as np
import torch
from numpy.polynomial import legendre as npleg
from numpy.polynomial import polynomial as nppoly
from torch import Tensor

from methods.core.sampling import gauss_legendre_sphere


def _check(alpha: float, order: int) -> float:
    if not isinstance(order, int) or order < 1:
        raise ValueError(f"order must be an int >= 1, got {order!r}")
    a = float(alpha)
    if not math.isfinite(a) or a < 0:
        raise ValueError(f"Phong exponent alpha must be finite and >= 0, got {alpha!r}")
    return a


def _K(l: int, m: int) -> float:
    return math.sqrt((2 * l + 1) / (4 * math.pi) * math.factorial(l - m) / math.factorial(l + m))


@functools.lru_cache(maxsize=None)
def _u_moments(order: int) -> tuple[tuple[int, int, np.ndarray], ...]:
    """For every (i, j) with m_i = m_j: coefficients d_k (in u = 1 − t) of 2π K K' (1−t²)^m Q Q'."""
    out = []
    for l1 in range(order):
        for m1 in range(-l1, l1 + 1):
            for l2 in range(order):
                m = abs(m1)
                if l2 < m:
                    continue
                q1 = npleg.leg2poly(npleg.Legendre.basis(l1).deriv(m).coef)   # power series in t
                q2 = npleg.leg2poly(npleg.Legendre.basis(l2).deriv(m).coef)
                p = nppoly.polymul(nppoly.polymul(q1, q2), nppoly.polypow([1.0, 0.0, -1.0], m))
                # t = 1 − u: p(1 − u) as a power series in u
                d = np.zeros(1)
                for k, c in enumerate(p):
                    d = nppoly.polyadd(d, c * nppoly.polypow([1.0, -1.0], k))
                d = d * 2.0 * math.pi * _K(l1, m) * _K(l2, m)
                out.append((l1 * (l1 + 1) + m1, l2 * (l2 + 1) + m1, np.asarray(d, dtype=np.float64)))
    return tuple(out)


def phong_operator(alpha: float, order: int = 4, *, dtype=torch.float32, device=None) -> Tensor:
    """Closed-form M^α (see the module docstring), symmetric, (order², order²).

    Args:
        alpha: Phong exponent α ≥ 0 (α = 1: clamped cosine).
        order: SH order n (bands 0..n−1).
    Returns:
        (n², n²) M^α WITHOUT the (α+1)/(2π) factor (Nowrouzezahrai 2008 eq. 2).
    """
    a = _check(alpha, order)
    n2 = order * order
    I, J, D = _u_table(order)
    # B(α+1, k+1) = k!/((α+1)…(α+k+1)), accumulated as a product of ratios
    beta = np.empty(D.shape[1])
    beta[0] = 1.0 / (a + 1.0)
    for k in range(1, D.shape[1]):
        beta[k] = beta[k - 1] * k / (a + k + 1.0)
    M = np.zeros((n2, n2))
    # every entry's Σ_k d_k B(α+1, k+1) at once, k by k over the zero-padded d (0.31 → ~0.04 ms per
    # exponent at order 8: a VB / VBL frame meets a new one per region and frame). Summed in k order
    # as the per-entry dot products of short vectors are (bit for bit at orders ≤ 8 on the hosts
    # measured; to float64 round-off of the sum's terms otherwise, which at high orders and small α
    # cancel: `test_phong_operator_equals_per_entry_sums`)
    acc = D[:, 0] * beta[0]
    for k in range(1, D.shape[1]):
        acc = acc + D[:, k] * beta[k]
    M[I, J] = M[J, I] = acc
    return torch.as_tensor(M, dtype=dtype, device=device)


@functools.lru_cache(maxsize=None)
def _u_table(order: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`_u_moments` with i ≤ j as arrays: rows I, columns J (E,) and the coefficients D (E, k)
    zero-padded to the longest (k = 2·order − 1: p has degree l + l' ≤ 2n − 2)."""
    ent = [(i, j, d) for i, j, d in _u_moments(order) if i <= j]
    D = np.zeros((len(ent), max(d.shape[0] for _, _, d in ent)))
    for e, (_, _, d) in enumerate(ent):
        D[e, :d.shape[0]] = d
    return np.array([i for i, _, _ in ent]), np.array([j for _, j, _ in ent]), D


def phong_transfer_operator(alpha: float, order: int = 4, *, dtype=torch.float32, device=None) -> Tensor:
    """((α+1)/(2π)) · M^α: maps visibility SH v to t, the SH of v · normalised Phong lobe (eq. 2)."""
    return phong_operator(alpha, order, dtype=torch.float64).mul((float(alpha) + 1.0) / (2.0 * math.pi)).to(
        dtype=dtype, device=device)


@functools.lru_cache(maxsize=8)
def _leggauss(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.polynomial.legendre.leggauss(n)   # O(n³) eigen-solve: cache it


def phong_operator_quadrature(alpha: float, order: int = 4, *, n_theta: int = 256, dtype=torch.float64,
                              device=None) -> Tensor:
    """M^α by direct quadrature with `methods.core.sh.sh_eval` (the independent check).

    Gauss–Legendre in t = cos θ on [0, 1] (n_theta nodes, after the substitution t = 1 − w², which
    makes t^α and the (1−t²)^{m/2} factors smooth) × 4n uniform φ nodes (exact for the products'
    trigonometric degree ≤ 2n − 2).
    """
    from methods.core.sh import sh_eval

    a = _check(alpha, order)
    x, wx = _leggauss(int(n_theta))
    w = 0.5 * (x + 1.0)                      # w ∈ (0, 1)
    t = 1.0 - w * w                          # dt = 2w dw
    wt = wx * 0.5 * 2.0 * w
    n_phi = 4 * order
    phi = (np.arange(n_phi) + 0.5) * (2.0 * math.pi / n_phi)
    st = np.sqrt(np.clip(1.0 - t * t, 0.0, None))
    d = np.stack([st[:, None] * np.cos(phi)[None], st[:, None] * np.sin(phi)[None],
                  np.broadcast_to(t[:, None], (t.shape[0], n_phi))], -1).reshape(-1, 3)
    q = (wt * t ** a)[:, None] * np.full(n_phi, 2.0 * math.pi / n_phi)[None]
    Y = sh_eval(torch.as_tensor(d, dtype=torch.float64), order)
    qw = torch.as_tensor(q.reshape(-1), dtype=torch.float64)
    M = Y.T @ (Y * qw[:, None])
    return M.to(dtype=dtype, device=device)


def appendix_a(alpha: float, *, dtype=torch.float64, device=None) -> Tensor:
    """Nowrouzezahrai 2008 Appendix A, order 4 (16 × 16), with the OCR errors corrected (module
    docstring); entries for m > 0 equal those for −m, the matrix is symmetric."""
    a = _check(alpha, 4)
    A = lambda x: a + x  # noqa: E731  α_x = α + x
    r2, r3, r5, r7 = math.sqrt(2), math.sqrt(3), math.sqrt(5), math.sqrt(7)
    e = {
        (0x0, 0x0): 0.5 / A(1),
        (0x0, 0x2): r3 / (2 * A(2)),
        (0x0, 0x6): r5 * a / (2 * A(1) * A(3)),
        (0x0, 0xC): r7 * A(-1) / (2 * A(2) * A(4)),                       # printed as "M_0B"
        (0x1, 0x1): 1.5 / (A(1) * A(3)),
        (0x1, 0x5): 3 * r5 / (2 * A(2) * A(4)),
        (0x1, 0xB): 3 * r7 * a / (r2 * A(1) * A(3) * A(5)),
        (0x2, 0x2): 1.5 / A(3),
        (0x2, 0x6): math.sqrt(15) * A(1) / (2 * A(2) * A(4)),
        (0x2, 0xC): math.sqrt(21) * a / (2 * A(3) * A(5)),
        (0x4, 0x4): 7.5 / (A(1) * A(3) * A(5)),
        (0x4, 0xA): 7.5 * r7 / (A(2) * A(4) * A(6)),
        (0x5, 0x5): 7.5 / (A(3) * A(5)),
        (0x5, 0xB): 3 * math.sqrt(35) * A(1) / (r2 * A(2) * A(4) * A(6)),
        (0x6, 0x6): 5 * (a * a + 2 * a + 3) / (2 * A(1) * A(3) * A(5)),   # missing in the text
        (0x6, 0xC): math.sqrt(35) * (a * a + 2 * a + 6) / (2 * A(2) * A(4) * A(6)),  # printed α₁α₂α₆
        (0x9, 0x9): 52.5 / (A(1) * A(3) * A(5) * A(7)),
        (0xA, 0xA): 52.5 / (A(3) * A(5) * A(7)),
        (0xB, 0xB): 21 * (2 * a * a + 4 * a + 5) / (2 * A(1) * A(3) * A(5) * A(7)),  # printed α₄
        (0xC, 0xC): 7 * (a * a + 2 * a + 15) / (2 * A(3) * A(5) * A(7)),
    }
    M = np.zeros((16, 16))

    def lm(i):
        l = math.isqrt(i)
        return l, i - l * (l + 1)

    for (i, j), v in e.items():
        (l1, m1), (l2, m2) = lm(i), lm(j)
        for s in ((1,) if m1 == 0 else (1, -1)):   # m ↔ −m (sin ↔ cos) give the same integral
            ii, jj = l1 * (l1 + 1) + s * m1, l2 * (l2 + 1) + s * m2
            M[ii, jj] = M[jj, ii] = v
    return torch.as_tensor(M, dtype=dtype, device=device)


def sparsity(M: Tensor, *, tol: float = 0.0) -> tuple[float, float]:
    """(fraction of non-zero entries, fraction of distinct non-zero |values| up to 1e-12 rel.)."""
    a = M.detach().double().abs().cpu().numpy()
    nz = a > tol
    vals = np.sort(a[nz])
    uniq = 0 if vals.size == 0 else 1 + int(np.sum(np.diff(vals) > 1e-12 * vals[1:]))
    return float(nz.mean()), uniq / a.size
