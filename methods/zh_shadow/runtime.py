"""The fast run-time path of Nowrouzezahrai et al. 2008 §4.3: the per-point shade as one batched
polynomial in the shading direction (GEMMs), with the per-point frame rotations folded into tables
built once per lighting.

What is computed (the same number as `methods.zh_shadow.method.shade`, the slow reference path):
per point with world-space order-n SH visibility v (eq. 1, lobes taken to world space) and the
world-space SH lighting l, a 1D-BRDF term about the direction r (r = n, α = 1 for the diffuse term;
r = R = reflect(ωo, n), α = the Phong exponent for the specular one) is

    ((α+1)/(2π)) v_rᵀ M^α l_r = ∫ V_n(ω) L_n(ω) (α+1)/(2π) max(0, r·ω)^α dω          (eq. 2, §4.3 #2–#5)

(v_r, l_r: v and l rotated into a frame with z = r; M^α is invariant about z, so the tangent does
not matter; V_n, L_n the band-limited functions). The product of two order-n SH is band-limited to
order B = 2n−1: y_j y_i = Σ_a G[a, j, i] y_a (`product_tensor`, the SH triple products), and the
Funk–Hecke theorem turns the lobe integral of y_a into F_l(α) y_a(r) with F_l the exact Phong
factors (`methods.core.zh.phong_factors`; F(1) is the clamped cosine / π). Hence

    term_c = Σ_j v_j T^α_jc(r),   T^α_jc(r) = Σ_a y_a(r) F_{l(a)}(α) Σ_i G[a, j, i] l_ic,

an order-B SH polynomial in r whose coefficient table W^α (B², n²·3) is built once per lighting and
exponent. Per point this is one row of a GEMM (features(r) @ W^α) and a 16-term dot per channel,
instead of two per-point SH rotations of the lighting. The features are the monomials of degree
2n−2 (even bands) and 2n−3 (odd bands) of r — on the unit sphere exactly a basis of the order-B SH
(`monomial_basis`; cheaper to evaluate than the SH recurrence) — for order ≤ `MONOMIAL_MAX_ORDER`,
the SH themselves above. The diffuse factors F_l(1) vanish for odd l ≥ 3, so the diffuse term only
needs the even-degree monomials and r itself.
"""
from __future__ import annotations

import functools
import itertools
import math

import torch
from torch import Tensor

from methods.core.sampling import gauss_legendre_sphere
from methods.core.sh import sh_eval
from methods.core.threads import torch_threads
from methods.core.zh import expand_bands, phong_factors

# Largest SH order whose features are monomials: the monomial basis of degree 2n−2 ⊕ 2n−3 has
# condition number 37 (n = 4), 167 (n = 5), 844 (n = 6), 2.3e4 (n = 8) on the sphere (measured
# on 4000 random directions); above 5 float32 round-off would grow past ~1e-5, so the SH are used.
MONOMIAL_MAX_ORDER = 5
# Points per batch of the per-point kernel (bounds the (Q, n²·3) GEMM outputs; small enough that
# a batch's temporaries stay in the last-level cache).
CHUNK = 1 << 14


def _monos(deg: int) -> list[tuple[int, int, int]]:
    return [e for e in itertools.product(range(deg, -1, -1), repeat=3) if sum(e) == deg]


@functools.lru_cache(maxsize=None)
def product_tensor(order: int) -> Tensor:
    """G[a, j, i] = ∫ y_a y_j y_i dω (float64, (B², n², n²), B = 2n−1): y_j y_i = Σ_a G[a, j, i] y_a.

    Gauss–Legendre × uniform quadrature with n_θ = 2n, n_φ = 4n: exact for the degree ≤ 4n−4
    polynomial integrand (entries below 1e-12 are set to 0)."""
    B = 2 * order - 1
    d, w = gauss_legendre_sphere(2 * order + 2, 4 * order + 4, dtype=torch.float64)
    YB, Yn = sh_eval(d, B), sh_eval(d, order)
    G = torch.einsum("da,dj,di,d->aji", YB, Yn, Yn, w)
    return torch.where(G.abs() < 1e-12, torch.zeros_like(G), G)


@functools.lru_cache(maxsize=None)
def monomial_basis(order: int, diffuse: bool) -> tuple[Tensor, Tensor, Tensor]:
    """The per-point features of `features` and their map to the order-B SH.

    Returns:
        ex (K, 3) int64 monomial exponents (degree 2n−2, then 2n−3 — or 1 for ``diffuse``);
        rows (K,) int64: the order-B SH indices the features span (all B², or the bands with
            F_l(1) ≠ 0 for ``diffuse``: l = 1 and even l);
        C (K, K) float64 with y_rows(d) = mono(d) @ C on the unit sphere (exact to round-off).
    """
    B = 2 * order - 1
    D = 2 * order - 2
    ex = _monos(D) + (_monos(1) if diffuse else _monos(D - 1))
    band = torch.repeat_interleave(torch.arange(B), torch.arange(B) * 2 + 1)
    rows = ((band % 2 == 0) | (band == 1)).nonzero().squeeze(-1) if diffuse else torch.arange(B * B)
    g = torch.Generator().manual_seed(0)
    d = torch.randn(8 * len(ex), 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    et = torch.tensor(ex)
    M = (d[:, None, :] ** et[None]).prod(-1)
    # gelsd (SVD) on one thread: the default gelsy's answer varies from call to call in the last
    # bits, and LAPACK's with the thread count (methods.core.threads)
    with torch_threads(1):
        C = torch.linalg.lstsq(M, sh_eval(d, B)[:, rows], driver="gelsd").solution
    return et, rows, C


@functools.lru_cache(maxsize=None)
def _plan(order: int, diffuse: bool) -> tuple[list[tuple[Tensor, Tensor]], list[tuple[int, int, Tensor, Tensor]]]:
    """How `features` builds the monomials of `monomial_basis` with few batched products.

    steps: degree k (2..h, h = n−1) from degree k−1 times one coordinate (row indices I, J);
    blocks: (deg_a, deg_b, I, J): the final rows, in `monomial_basis` order, as products of a
    degree-deg_a row I and a degree-deg_b row J (degree 2n−2 = h + h, 2n−3 = (h−1) + h; degree 1
    for the diffuse features is the direction itself, deg_b = 0).
    """
    h = order - 1
    levels = {1: _monos(1)}
    steps = []
    for deg in range(2, h + 1):
        I, J = [], []
        for e in _monos(deg):
            j = next(q for q in range(3) if e[q] > 0)
            f = list(e)
            f[j] -= 1
            I.append(levels[deg - 1].index(tuple(f)))
            J.append(j)
        steps.append((torch.tensor(I), torch.tensor(J)))
        levels[deg] = _monos(deg)

    def split(deg: int, da: int) -> tuple[int, int, Tensor, Tensor]:
        db = deg - da
        I, J = [], []
        for e in _monos(deg):
            for ea in levels[da]:
                rest = tuple(x - y for x, y in zip(e, ea))
                if min(rest) >= 0:
                    I.append(levels[da].index(ea))
                    J.append(levels[db].index(rest))
                    break
        return da, db, torch.tensor(I), torch.tensor(J)

    blocks = [split(2 * h, h)]
    blocks.append((1, 0, torch.arange(3), torch.zeros(3, dtype=torch.long)) if diffuse else split(2 * h - 1, h - 1))
    return steps, blocks


def features(dT: Tensor, order: int, diffuse: bool) -> Tensor:
    """(K, Q) per-point features of unit directions dT (3, Q) (coordinates as rows): monomials
    (order ≤ `MONOMIAL_MAX_ORDER`, `monomial_basis`) or the order-B SH themselves (rows of `table`)."""
    if order > MONOMIAL_MAX_ORDER:
        Y = sh_eval(dT.T, 2 * order - 1).T
        return Y.index_select(0, _table_rows(order, diffuse).to(dT.device)) if diffuse else Y
    if order < 3:   # degrees ≤ 2: the plan's split needs h ≥ 2
        et = monomial_basis(order, diffuse)[0].to(dT.device)
        return (dT.T[:, None, :] ** et[None]).prod(-1).T
    steps, blocks = _plan(order, diffuse)
    lv = {1: dT}
    for k, (I, J) in enumerate(steps, start=2):                  # degree k = degree k−1 · one coordinate
        lv[k] = lv[k - 1].index_select(0, I.to(dT.device)) * dT.index_select(0, J.to(dT.device))
    out = torch.empty(sum(b[2].shape[0] for b in blocks), dT.shape[1], dtype=dT.dtype, device=dT.device)
    r = 0
    for da, db, I, J in blocks:
        rows = out[r:r + I.shape[0]]
        if db == 0:
            rows.copy_(lv[da])
        else:
            torch.mul(lv[da].index_select(0, I.to(dT.device)), lv[db].index_select(0, J.to(dT.device)), out=rows)
        r += I.shape[0]
    return out


def _table_rows(order: int, diffuse: bool) -> Tensor:
    B = 2 * order - 1
    band = torch.repeat_interleave(torch.arange(B), torch.arange(B) * 2 + 1)
    return ((band % 2 == 0) | (band == 1)).nonzero().squeeze(-1) if diffuse else torch.arange(B * B)


def table(light: Tensor, alpha: float, *, diffuse: bool) -> Tensor:
    """W (K, n²·3) with T^α(r) = features(r)ᵀ @ W reshaped (Q, n², 3) (module docstring).

    Args:
        light: (n², 3) world-space SH lighting; alpha: Phong exponent (1 for ``diffuse``, whose
            features skip the bands where F_l(1) = 0).
    Returns:
        (K, n²·3) in the dtype/device of ``light`` (built in float64).
    """
    n2, C = light.shape
    n = math.isqrt(n2)
    B = 2 * n - 1
    G = product_tensor(n)
    H = torch.einsum("aji,ic->ajc", G, light.detach().double().cpu())           # (B², n², C)
    f = expand_bands(phong_factors(float(alpha), B))
    rows = _table_rows(n, diffuse)
    Wy = (f[:, None, None] * H)[rows].reshape(rows.shape[0], n2 * C)
    if n <= MONOMIAL_MAX_ORDER:
        Wy = monomial_basis(n, diffuse)[2] @ Wy
    return Wy.to(dtype=light.dtype, device=light.device)


def shade_terms(vT: Tensor, nT: Tensor, woT: Tensor, Wd: Tensor, Ws: Tensor | None) -> tuple[Tensor, Tensor | None]:
    """Diffuse and specular terms of Q points (before kd, ks; front-facing test not applied), in
    the point-minor layout the batched products want (rows = components, columns = points).

    Args:
        vT: (n², Q) world-space SH visibility; nT, woT: (3, Q) unit normals / directions to the viewer.
        Wd: `table`(·, 1, diffuse=True); Ws: `table`(·, α) or None (no specular term).
    Returns:
        diffuse (3, Q) = v · T¹(n); specular (3, Q) = v · T^α(R) or None.
    """
    n2, Q = vT.shape
    n = math.isqrt(n2)
    diff = ((Wd.T @ features(nT, n, True)).view(n2, -1, Q) * vT[:, None]).sum(0)
    if Ws is None:
        return diff, None
    R = 2.0 * (woT * nT).sum(0, keepdim=True) * nT - woT                         # reflect(ωo, n)
    R = R / R.norm(dim=0, keepdim=True).clamp_min(1e-12)
    spec = ((Ws.T @ features(R, n, False)).view(n2, -1, Q) * vT[:, None]).sum(0)
    return diff, spec
