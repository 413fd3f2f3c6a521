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

Layout and batching (`shade`): points are processed in chunks in the point-minor layout (rows =
components), a point's visibility Σ_k b_k v[vi_k] is one fused gather (`interpolate`), and the
monomials come from three broadcast products per degree (`_monomial_levels`). Two exact
shortcuts, both from the linearity of the terms in v and in l:

* planes (`planar_groups`): points whose normals are bitwise equal share T¹(n), so their diffuse
  term Σ_k b_k (v[vi_k] · T¹(n)) is a 3-vector per vertex, interpolated — no per-point GEMM;
* lighting-only frames (`relight_cache`, `relight`): with the tables of the identity lighting
  (n² channels) the same GEMMs give each point's lighting-free transfer t (term = t · l); kept,
  a frame with new lighting is one (3, n²) @ (n², Q) product per region and term.
* per-vertex tables (`vertex_table`, `sample_terms`; ``shade(tables="vertex")``): U_i = v_i ·
  [W¹ ⊙ kd; W^α ⊙ ks] per vertex (N, 3, K), so a point's terms are Σ_k b_k features(r) · U[vi_k]
  — 2·(9 + 3)·K flops per point instead of the GEMM's 2·3n²·K and the n²-term dot (1,920 vs
  7,680 at order 4), gathers of contiguous rows in one compiled pass. U costs 2·n²·3K per vertex
  (on the bench creature: N = 13.4 K vertices for 36 K off-plane samples, as much as the GEMMs it
  replaces), so `ZHShadow` builds it on a view-only frame and keeps it while the pose, lighting and
  materials stay (not for ``cosine``: w = cos-weighted v is not interpolated linearly).
"""
from __future__ import annotations

import contextlib
import functools
import itertools
import math

import numpy as np
import torch
from torch import Tensor

from methods.core.frames import _coordinate_components
from methods.core.fused import fused
from methods.core.sampling import gauss_legendre_sphere
from methods.core.threads import torch_threads
from methods.core.sh import sh_eval, sh_terms
from methods.core.zh import band_norms, expand_bands, phong_factors
from methods.zh_shadow import native as zn
from methods.zh_shadow.convolution import phong_operator
from methods.zh_shadow.precompute import CHART_RMAX

# Largest SH order whose features are monomials: the monomial basis of degree 2n−2 ⊕ 2n−3 has
# condition number 37 (n = 4), 167 (n = 5), 844 (n = 6), 2.3e4 (n = 8) on the sphere (measured
# on 4000 random directions); above 5 float32 round-off would grow past ~1e-5, so the SH are used.
MONOMIAL_MAX_ORDER = 5
# Points per batch of the per-point kernel (bounds the (Q, n²·3) GEMM outputs; small enough that
# a batch's temporaries stay in the last-level cache).
CHUNK = 1 << 13
# Planar groups (`planar_groups`): a plane's diffuse term costs one (N, n²) @ (n², 3) product and a
# gather per point; below this many points the feature GEMM is as cheap as the group's fixed cost.
PLANAR_MIN_POINTS = 1024
PLANAR_MAX_GROUPS = 16
# Vertices from which `world_visibility` runs `_vertex_sh` compiled (one kernel, the vertex count
# symbolic: a bench-size mesh compiles it in the harness's warm-up frame); fewer run it eagerly, so
# tests meeting many orders and dtypes on small meshes pay no compilations (`scenes.skeleton`'s
# BLEND_COMPILE_MIN; the compiled kernel is checked against the eager one in tests)
VERTEX_COMPILE_MIN = 4096


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


def _fit_monomials(degrees: tuple[int, int], B: int, rows: Tensor) -> tuple[Tensor, Tensor]:
    """Exponents (K, 3) of the monomials of the two ``degrees`` (`_monos` order) and C (K, |rows|)
    float64 with y_rows(d) = mono(d) @ C for unit d, y the order-B SH (least squares on random
    directions; exact to round-off when the monomials span those SH on the sphere)."""
    ex = _monos(degrees[0]) + _monos(degrees[1])
    g = torch.Generator().manual_seed(0)
    d = torch.randn(8 * len(ex), 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=-1, keepdim=True)
    et = torch.tensor(ex)
    M = (d[:, None, :] ** et[None]).prod(-1)
    # gelsd (SVD) on one thread: the default gelsy's answer varies from call to call in the last
    # bits, and LAPACK's with the thread count (methods.core.threads)
    with torch_threads(1):
        return et, torch.linalg.lstsq(M, sh_eval(d, B)[:, rows], driver="gelsd").solution


@functools.lru_cache(maxsize=None)
def monomial_basis(order: int, diffuse: bool) -> tuple[Tensor, Tensor, Tensor]:
    """The per-point features of `features` and their map to the order-B SH.

    Returns:
        ex (K, 3) int64 monomial exponents (degree 2n−2, then 2n−3 — or 1 for ``diffuse``);
        rows (K,) int64: the order-B SH indices the features span (all B², or the bands with
            F_l(1) ≠ 0 for ``diffuse``: l = 1 and even l);
        C (K, K) float64 with y_rows(d) = mono(d) @ C on the unit sphere (exact to round-off).
    """
    D = 2 * order - 2
    rows = _table_rows(order, diffuse)
    et, C = _fit_monomials((D, 1 if diffuse else D - 1), 2 * order - 1, rows)
    return et, rows, C


@functools.lru_cache(maxsize=None)
def sh_monomials(order: int) -> Tensor:
    """C (n², n²) float64 with y(d) = mono(d) @ C on the unit sphere: the order-n SH from the
    monomials of degree n−1 and n−2 (`sh_features`), which span them there exactly."""
    return _fit_monomials((order - 1, order - 2), order, torch.arange(order * order))[1]


def sh_features(dT: Tensor, order: int) -> Tensor:
    """(n², Q) monomials of degree n−1 and n−2 of unit directions dT (3, Q) (`sh_monomials`)."""
    dT = dT.contiguous()
    out = torch.empty(order * order, dT.shape[1], dtype=dT.dtype, device=dT.device)
    _monomial_levels(dT, (order - 1, order - 2), out)
    return out


def _monomial_levels(dT: Tensor, degrees: tuple[int, ...], out: Tensor) -> None:
    """Write the monomials of each degree in ``degrees`` (each ≥ 0, `_monos` order) of the
    directions dT (3, Q) into consecutive row blocks of ``out``.

    Degree k from degree k−1 with three broadcast products and no gathers: in `_monos` order
    (exponents descending) the degree-k monomials are x·(every degree-(k−1) one), then y·(the last
    k of them, those without x), then z·(the last one, z^(k−1)) — in that order."""
    top = max(max(degrees), 1)
    blocks, r = {}, 0
    for k in degrees:
        m = (k + 1) * (k + 2) // 2
        blocks[k] = out[r:r + m]
        r += m
    prev = dT
    for k in range(2, top + 1):
        m = (k + 1) * (k + 2) // 2
        cur = blocks[k] if k in blocks else torch.empty(m, dT.shape[1], dtype=dT.dtype, device=dT.device)
        p = prev.shape[0]
        torch.mul(prev, dT[0:1], out=cur[:p])
        torch.mul(prev[p - k:], dT[1:2], out=cur[p:p + k])
        torch.mul(prev[p - 1:], dT[2:3], out=cur[p + k:])
        prev = cur
    if 1 in blocks:
        blocks[1].copy_(dT)
    if 0 in blocks:
        blocks[0].fill_(1.0)


def features(dT: Tensor, order: int, diffuse: bool, *, out: Tensor | None = None) -> Tensor:
    """(K, Q) per-point features of unit directions dT (3, Q) (coordinates as rows): monomials
    (order ≤ `MONOMIAL_MAX_ORDER`, `monomial_basis`) or the order-B SH themselves (rows of `table`);
    written into ``out`` (K, Q) when given."""
    if order > MONOMIAL_MAX_ORDER:
        Y = sh_eval(dT.T, 2 * order - 1).T
        Y = Y.index_select(0, _table_rows(order, diffuse).to(dT.device)) if diffuse else Y
        return Y if out is None else out.copy_(Y)
    D = 2 * order - 2
    degrees = (D, 1) if diffuse else (D, D - 1)
    dT = dT.contiguous()
    if out is None:
        out = torch.empty(sum((k + 1) * (k + 2) // 2 for k in degrees), dT.shape[1], dtype=dT.dtype, device=dT.device)
    _monomial_levels(dT, degrees, out)
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
    # (a new exponent's operator from its band parts at orders ≤ `MONOMIAL_MAX_ORDER`: `_table_operator_b`)
    A = _table_operator_b(n, float(alpha), bool(diffuse)) if TABLE_BANDS and n <= MONOMIAL_MAX_ORDER \
        else _table_operator(n, float(alpha), bool(diffuse))                          # (K·n², n²)
    W = (A @ light.detach().double().cpu()).view(-1, n2 * C)
    return W.to(dtype=light.dtype, device=light.device)


# `table`'s operator by `_table_operator_b` (from its band parts: float64 round-off against the direct
# operator, the tables equal to float32 round-off) at orders ≤ `MONOMIAL_MAX_ORDER` (above: the band parts
# grow as B·K·n⁴, 110 MB at order 8); False: `_table_operator` (the tests' oracle)
TABLE_BANDS = True


@functools.lru_cache(maxsize=8)
def _band_operators(n: int, diffuse: bool) -> Tensor:
    """(B, K·n²·n²) float64: the parts A_b of `_table_operator`(n, α, diffuse) = Σ_b F_b(α) A_b (F the
    exact Phong factors per band b < B = 2n − 1), each flattened: that operator is linear in the factors,
    A_b its part of band b (the same rows, triple products and monomial map with f = 1 on band b's
    coefficients, 0 elsewhere). 0.7 MB at order 4."""
    B = 2 * n - 1
    n2 = n * n
    band = torch.repeat_interleave(torch.arange(B), torch.arange(B) * 2 + 1)
    rows = _table_rows(n, diffuse)
    G = product_tensor(n)
    out = []
    for b in range(B):
        Wy = ((band == b).to(G.dtype)[:, None, None] * G)[rows].reshape(rows.shape[0], n2 * n2)
        if n <= MONOMIAL_MAX_ORDER:
            Wy = monomial_basis(n, diffuse)[2] @ Wy
        out.append(Wy.reshape(-1))
    return torch.stack(out).contiguous()


@functools.lru_cache(maxsize=64)
def _table_operator_b(n: int, alpha: float, diffuse: bool) -> Tensor:
    """`_table_operator`(n, α, diffuse) (K·n², n²) float64 as Σ_b F_b(α) A_b (`_band_operators`): a new
    exponent — every material frame's — costs B·K·n⁴ multiply-adds (~0.03 ms at order 4, 1 thread) instead
    of the operator from the triple products (~0.4-0.6 ms: `expand_bands`, the (B², n², n²) product and the
    monomial map)."""
    B = 2 * n - 1
    return (phong_factors(alpha, B) @ _band_operators(n, diffuse)).view(-1, n * n)


@functools.lru_cache(maxsize=64)
def _table_operator(n: int, alpha: float, diffuse: bool) -> Tensor:
    """A (K·n², n²) float64 with `table`(light, α) = (A @ light) viewed (K, n²·C): the table is
    linear in the lighting, A[(k, j), i] = Σ_a C[k, a] F_{l(a)}(α) G[a, j, i] (the SH triple
    products, the Phong factors and the monomial map of `table`), built once per order and exponent
    so that a new lighting costs one small product (a lighting frame built two tables from G each:
    0.3 ms apiece on the bench machine)."""
    B = 2 * n - 1
    n2 = n * n
    f = expand_bands(phong_factors(alpha, B))
    rows = _table_rows(n, diffuse)
    Wy = (f[:, None, None] * product_tensor(n))[rows].reshape(rows.shape[0], n2 * n2)
    if n <= MONOMIAL_MAX_ORDER:
        Wy = monomial_basis(n, diffuse)[2] @ Wy
    return Wy.view(-1, n2, n2).reshape(-1, n2).contiguous()


def _term(vT: Tensor, dT: Tensor, W: Tensor, diffuse: bool) -> Tensor:
    """(C, Q) = Σ_j v_j T_jc(d): the feature GEMM W_ᵀ features(d) (n²·C, Q) and the n²-term dot."""
    n2, Q = vT.shape
    T = (W.T @ features(dT, math.isqrt(n2), diffuse)).view(n2, -1, Q)
    return (T * vT[:, None]).sum(0)


# Points per block of the per-vertex-table kernels of `sample_terms` with SH features (orders above
# `MONOMIAL_MAX_ORDER`; the monomial features go in one call with a symbolic point count): one static
# shape; a block's features stay in the L2 cache (measured: 4096 fastest of 1024–8192 on the bench
# creature, session 17, when every order took blocks).
SAMPLE_BLOCK = 1 << 12


def vertex_table(v: Tensor, vertex_region: Tensor, mats: list[tuple[Tensor, Tensor, Tensor, Tensor | None]], *,
                 diffuse: bool = True) -> Tensor:
    """U (N, 3, K) with U[i, c, :] = Σ_j v[i, j] W_c[:, j] — the per-vertex contraction of the
    visibility with the (albedo-folded) tables of its region, so that a point's terms are
    Σ_k b_k features(r)·U[vi_k] (`sample_terms`): the terms are linear in v, and a point's v is
    Σ_k b_k v[vi_k] (a face's vertices share its region: `Scene` concatenates one mesh per region).

    The per-point work becomes the interpolation of U (3·3K multiply-adds for a face's three
    vertices) and a K-term dot per channel (3K) instead of the feature GEMM (K·3n²) and the n²-term
    dot (`_term`): 4× fewer flops per point at order 4 (2·(3·3 + 3)·K = 1,920 vs 2·(3n² + n²)·K …
    7,680 with K = 31 + 49), for N·2·n²·3K flops per vertex table (built once per pose, lighting and
    material; `ZHShadow` keeps it between view-only frames).

    Args:
        v: (N, n²) per-vertex world-space SH visibility; vertex_region: (N,) int64;
        mats: per region (kd (3,), ks (3,), Wd `table`(·, 1, diffuse=True), Ws `table`(·, α) or
            None: no specular term) — one Wd for all regions, as `shade`;
        diffuse: include the diffuse columns (False: the specular ones alone, for the planes'
            specular term whose diffuse part goes through the plane's per-vertex factor).
    Returns:
        (N, 3, K) in the dtype/device of v: K = K_d + K_s columns ([diffuse; specular] features,
        `sample_features` order), K_s = 0 when no region has a specular term; rows of a region
        without one have zero specular columns.
    """
    N, n2 = v.shape
    dev, dt = v.device, v.dtype
    K, tables = region_tables(mats, n2, dev, dt, diffuse=diffuse)
    # uninitialised when every row is written below (each vertex's region has its product)
    covered = len(mats) == 1 or int(((vertex_region >= 0) & (vertex_region < len(mats))).sum()) == N
    U = (torch.empty if covered else torch.zeros)(N, 3, K, dtype=dt, device=dev)
    single = len(mats) == 1
    for r, Wr in enumerate(tables):
        if single:
            torch.matmul(v, Wr, out=U.view(N, 3 * K))
        else:
            ids = (vertex_region == r).nonzero().squeeze(-1)
            if not ids.shape[0]:
                continue
            a0, a1 = int(ids[0]), int(ids[-1]) + 1
            if a1 - a0 == ids.shape[0]:
                # the region's vertices are one range (a mesh's: `Scene` concatenates one per region):
                # the product written into its rows, no gather, temporary or scatter (bench creature,
                # 2 regions, 1 thread: 7.5 → 3.2 ms; the same products)
                torch.matmul(v[a0:a1], Wr, out=U.view(N, 3 * K)[a0:a1])
            else:
                U.index_copy_(0, ids, (v.index_select(0, ids) @ Wr).view(-1, 3, K))
    return U


def region_tables(mats: list[tuple[Tensor, Tensor, Tensor, Tensor | None]], n2: int, dev, dt, *,
                  diffuse: bool = True, out: Tensor | None = None) -> tuple[int, list[Tensor]]:
    """(K, [Wr (n², 3K) per region]) of `vertex_table`: region r's rows are v @ Wr, column c·K + k the
    albedo-folded coefficient of feature k for channel c ([diffuse; specular] features; zero specular
    columns for a region without a specular term when another has one). ``out`` (R, n², 3K): written
    there (each product into its columns, the same values), Wr its rows."""
    spec = any(m[3] is not None for m in mats)
    Wd = mats[0][2]
    Kd = Wd.shape[0] if diffuse else 0
    Ks = next(m[3].shape[0] for m in mats if m[3] is not None) if spec else 0
    K = Kd + Ks
    if K == 0:
        raise ValueError("vertex_table: no columns (diffuse=False and no specular term)")
    if out is not None:
        if out.shape != (len(mats), n2, 3 * K) or out.dtype != dt or not out.is_contiguous():
            raise ValueError("region_tables: out must be a contiguous (R, n², 3K) tensor")
        o4 = out.view(len(mats), n2, 3, K)
        for r, (kd, ks, _, Ws) in enumerate(mats):   # (K_, n², 3) ⊙ albedo, permuted into its columns
            if diffuse:
                torch.mul(Wd.view(Kd, n2, 3).permute(1, 2, 0), kd.to(dev, dt).view(3, 1), out=o4[r, :, :, :Kd])
            if Ws is not None:
                torch.mul(Ws.view(Ks, n2, 3).permute(1, 2, 0), ks.to(dev, dt).view(3, 1), out=o4[r, :, :, Kd:])
            elif spec:
                o4[r, :, :, Kd:].zero_()
        return K, list(out.unbind(0))

    def fold(W: Tensor, k: Tensor) -> Tensor:   # (K_, n², 3) ⊙ albedo → (n², 3·K_) with column c·K_ + f
        Wk = W.view(W.shape[0], n2, 3) * k.to(dev, dt)
        return Wk.permute(1, 2, 0).reshape(n2, 3 * W.shape[0])

    tables = []
    for kd, ks, _, Ws in mats:
        parts = ([fold(Wd, kd).view(n2, 3, Kd)] if diffuse else []) + \
                ([fold(Ws, ks).view(n2, 3, Ks)] if Ws is not None else
                 [torch.zeros(n2, 3, Ks, dtype=dt, device=dev)] if spec else [])
        tables.append(torch.cat(parts, 2).reshape(n2, 3 * K))
    return K, tables


def referenced_vertices(vi: Tensor, N: int) -> tuple[Tensor, Tensor]:
    """The vertices (of N) that the vertex ids vi (Q, k) int32 / int64 reference, ascending (M,)
    int64, and vi renumbered over them (same shape and dtype): row vi[q, j] of a per-vertex table
    is row vi_r[q, j] of its rows ``idx`` (`ZHShadow._vertex_table`: a table of those rows alone)."""
    flat = vi.reshape(-1)
    idx = (torch.bincount(flat, minlength=N) > 0).nonzero().squeeze(-1)
    lut = torch.empty(N, dtype=vi.dtype, device=vi.device)
    lut.index_copy_(0, idx, torch.arange(idx.shape[0], dtype=vi.dtype, device=vi.device))
    return idx, lut.index_select(0, flat).view(vi.shape)


def _monomial_rows(d: tuple[Tensor, Tensor, Tensor], degrees: tuple[int, ...]) -> list[Tensor]:
    """The monomials of each degree in ``degrees`` of the direction rows d = (x, y, z) (each (C,)),
    as a list of rows in `_monos` order: the recurrence of `_monomial_levels` (the same products),
    unrolled for a compiled kernel."""
    levels = {0: [torch.ones_like(d[0])], 1: list(d)}
    prev = levels[1]
    for k in range(2, max(max(degrees), 1) + 1):
        p = len(prev)
        prev = [t * d[0] for t in prev] + [t * d[1] for t in prev[p - k:]] + [prev[-1] * d[2]]
        levels[k] = prev
    return [t for k in degrees for t in levels[k]]


@fused
def _monomial_features(nT: Tensor, woT: Tensor, D: int, diffuse: bool, specular: bool) -> Tensor:
    """(C, K) point-major features of C points (nT, woT (3, C) unit normals / directions to the
    viewer): [monomials of n of degrees (D, 1)] if ``diffuse``, then [monomials of R = reflect(ωo, n)
    of degrees (D, D−1)] if ``specular`` (R as `reflect_T`) — the rows of `features`, one compiled
    pass."""
    return torch.stack(_feature_rows(nT, woT, D, diffuse, specular), 1)


def sample_features(nT: Tensor, woT: Tensor, order: int, *, diffuse: bool, specular: bool) -> Tensor:
    """(C, K) the point-major features of `vertex_table`'s columns: `features`(n, diffuse) rows
    (if ``diffuse``) then `features`(R, specular) rows (if ``specular``), R = `reflect_T`(n, ωo)."""
    if order <= MONOMIAL_MAX_ORDER:
        return _monomial_features(nT, woT, 2 * order - 2, diffuse, specular)
    parts = ([features(nT, order, True)] if diffuse else []) + \
        ([features(reflect_T(nT, woT), order, False)] if specular else [])
    return torch.cat(parts).T.contiguous()


@fused
def _interpolated_dot(U: Tensor, vi: Tensor, b: Tensor, f: Tensor) -> Tensor:
    """(C, 3) Σ_k b[q, k] Σ_f U[vi[q, k], c, f] f[q, f] (U (N, 3, K), vi (C, k) int64, b (C, k),
    f (C, K)): the rows of U interpolated and dotted with the features, one compiled pass (the
    gathers read contiguous rows of U: vectorised over K)."""
    acc = U[vi[:, 0]] * b[:, 0, None, None]
    for j in range(1, vi.shape[1]):
        acc = acc + U[vi[:, j]] * b[:, j, None, None]
    return (acc * f[:, None, :]).sum(-1)


def _feature_rows(nT: Tensor, woT: Tensor, D: int, diffuse: bool, specular: bool) -> list[Tensor]:
    """The rows of `_monomial_features` (each (C,)): monomials of n, then of R = reflect(ωo, n)."""
    rows = []
    if diffuse:
        rows += _monomial_rows((nT[0], nT[1], nT[2]), (D, 1))
    if specular:
        dn = nT[0] * woT[0] + nT[1] * woT[1] + nT[2] * woT[2]
        R = [2.0 * dn * nT[i] - woT[i] for i in range(3)]
        norm = (R[0] * R[0] + R[1] * R[1] + R[2] * R[2]).sqrt().clamp_min(1e-12)
        rows += _monomial_rows((R[0] / norm, R[1] / norm, R[2] / norm), (D, D - 1))
    return rows


# `_sample_block`: Inductor would inline the features (a stack of 80 computed rows) into the
# dot's reduction over them — 80 candidate expressions per element, 1.4x slower than the two
# calls; realised (a buffer read once), the block is one call with the same two loops
_REALIZE = {"realize_reads_threshold": 1}


@functools.partial(fused, options=_REALIZE)
def _sample_block(U: Tensor, vi: Tensor, b: Tensor, nT: Tensor, woT: Tensor, D: int, diffuse: bool,
                  specular: bool) -> Tensor:
    """`_interpolated_dot`(U, vi, b, `_monomial_features`(nT, woT, …)) as one compiled call: the
    same two loops (point-major features, then the interpolated dot) and numbers, without a second
    call's overhead per block (guards, wrapper: ~0.1 ms of a block of 4096 points on the bench
    machine) — bench creature V frame, 36 K object samples, 1 thread: 10.5 → 8.0 ms, bit-identical."""
    return _interpolated_dot.eager(U, vi, b, torch.stack(_feature_rows(nT, woT, D, diffuse, specular), 1))


def sample_terms(U: Tensor, vi: Tensor, b: Tensor, nT: Tensor, woT: Tensor, order: int, *, diffuse: bool,
                 specular: bool, block: int = SAMPLE_BLOCK) -> Tensor:
    """(3, Q) the terms of Q points from the per-vertex table U (`vertex_table`, same ``diffuse``;
    ``specular``: U has specular columns): Σ_k b_k features(r)·U[vi_k] — equal to `_term`'s
    Σ_j v_j T_jc(r) summed over the terms, albedos applied (same math, summed in another order).

    Monomial features (order ≤ `MONOMIAL_MAX_ORDER`): every point in one compiled call
    (`_sample_block`) with the point count and the table's vertex count symbolic
    (``maybe_mark_dynamic``: one kernel for every frame and mesh) — the same loops and numbers as
    static blocks, without a call (guards, wrapper, padding) per block: bench creature V frame,
    36 K object samples, 1 thread, same process, load ~7-10: sample stage 1.06-1.09x (1.25x on random
    points), bit-identical (as `methods.triple_product.fast_eval` since session 18). What bounds it is
    the kernel itself (~150 ns per point: the point-major features are computed in scalar loops with
    strided stores, ~half the time; the interpolated dot gathers 3 × 960 bytes of U per point) — so where
    `native.sample_terms` applies (float32, order 4 with both terms or order 5 diffuse alone, Inductor
    on AVX2 or AVX-512) its C loop computes the same bits in one pass per point (session 28: paper setting, bench
    creature, 1 thread, same process: P 1.23x, V 1.13x, VB 1.23x, VL / VBL 1.17x). Above it (SH features): blocks of exactly
    ``block`` points (the last padded by repeating its last point), one static shape.

    Args:
        U: (N, 3, K); vi, b: (Q, k) vertex ids / weights; nT, woT: (3, Q) unit normals / directions
        to the viewer; order: the SH order n of the visibility.
    """
    Q, n = nT.shape[1], order
    torch._dynamo.maybe_mark_dynamic(U, 0)
    vi, b = vi.long().contiguous(), b.to(U.dtype).contiguous()   # (once, not per block)
    if n <= MONOMIAL_MAX_ORDER:
        if Q == 0:
            return torch.empty(3, 0, dtype=U.dtype, device=U.device)
        nT, woT = nT.contiguous(), woT.contiguous()
        out = zn.sample_terms(U, vi, b, nT, woT, 2 * n - 2, diffuse, specular)   # the C loop: the same bits
        if out is not None:
            return out
        for t, d in ((vi, 0), (b, 0), (nT, 1), (woT, 1)):
            torch._dynamo.maybe_mark_dynamic(t, d)
        return rows(_sample_block(U, vi, b, nT, woT, 2 * n - 2, diffuse, specular))
    out = torch.empty(Q, 3, dtype=U.dtype, device=U.device)
    for a in range(0, Q, block):
        m = min(block, Q - a)
        if m == block:
            vi_c, b_c, n_c, wo_c = vi[a:a + m], b[a:a + m], nT[:, a:a + m], woT[:, a:a + m]
        else:
            idx = torch.arange(a, a + block, device=U.device).clamp_max_(Q - 1)
            vi_c, b_c = vi.index_select(0, idx), b.index_select(0, idx)
            n_c, wo_c = nT.index_select(1, idx), woT.index_select(1, idx)
        f = sample_features(n_c.contiguous(), wo_c.contiguous(), n, diffuse=diffuse, specular=specular)
        out[a:a + m] = _interpolated_dot(U, vi_c, b_c, f)[:m]
    return rows(out)


@functools.lru_cache(maxsize=None)
def _zyz_tables(order: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Constants of `zonal_conjugate` (float64): perm (n²,) the index of (l, −m) for (l, m); absm
    (n²,) |m|; sgn (n²,) with M(R_z(φ))[(l, m), (l, −m)] = sgn·sin(|m|φ) (and cos(mφ) on the
    diagonal: a z rotation mixes only the pairs ±m); X = M(R_x(90°)) (n², n²), so that
    M(R_y(θ)) = Xᵀ M(R_z(θ)) X (`methods.core.sh_rotation` semantics)."""
    from methods.core.sh_rotation import sh_rotation_matrix

    n2 = order * order
    l = torch.repeat_interleave(torch.arange(order), torch.arange(order) * 2 + 1)
    m = torch.arange(n2) - l * (l + 1)
    perm = l * (l + 1) - m
    phi = 0.1
    c, s = math.cos(phi), math.sin(phi)
    Mz = sh_rotation_matrix(torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64), order)
    sin_m = torch.sin(m.abs().double() * phi)
    sgn = torch.where(m == 0, torch.zeros((), dtype=torch.float64), (Mz[torch.arange(n2), perm] / sin_m).round())
    X = sh_rotation_matrix(torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=torch.float64), order)
    return perm, m.abs(), sgn, X


@functools.lru_cache(maxsize=None)
def _conjugated(op_key: tuple, order: int) -> Tensor:
    """X · M · Xᵀ (float64) of the zonal operator M named by ``op_key`` (("phong", α): M^α of
    `convolution.phong_operator`), the fixed middle factor of `zonal_conjugate`."""
    X = _zyz_tables(order)[3]
    M = phong_operator(op_key[1], order, dtype=torch.float64)
    return X @ M @ X.T


@functools.lru_cache(maxsize=None)
def _conjugate_tables(order: int, dtype: torch.dtype, device) -> tuple:
    """Tables of the compiled `zonal_conjugate` kernels: perm, |m| (n²,) int64 and sgn (n², 1) of
    `_zyz_tables`; X = M(R_x(90°)) and Xᵀ each as k gathered terms per row — idx (n², k) int64
    columns, w (n², k) values (zero-padded) with (X a)_r = Σ_j w[r, j] a[idx[r, j]] — k = 4 at
    order 8: X has 176 non-zeros of 4096 (block-diagonal by band, and zero between the cos/sin
    and odd/even-m parts of a band), so 4·n² multiply-adds per point instead of Σ(2l+1)²."""
    perm, absm, sgn, X = _zyz_tables(order)
    n2 = order * order

    def gathered(A: Tensor) -> tuple[Tensor, Tensor]:
        nz = A.abs() > 1e-12
        k = int(nz.sum(1).max())
        idx = torch.zeros(n2, k, dtype=torch.int64)
        w = torch.zeros(n2, k, dtype=torch.float64)
        for r in range(n2):
            c = nz[r].nonzero().squeeze(-1)
            idx[r, :c.shape[0]], w[r, :c.shape[0]] = c, A[r, c]
        return idx.to(device), w.to(dtype).to(device)

    return (perm.to(device), absm.to(device), sgn.to(dtype).to(device)[:, None], *gathered(X), *gathered(X.T))


def _angle_rows(cT: Tensor, sT: Tensor, order: int) -> tuple[list[Tensor], list[Tensor]]:
    """cos(mφ), sin(mφ) (n × (Q,) each), m = 0..n−1, of the per-point angles with cos φ = cT,
    sin φ = sT (Q,) (the Chebyshev recurrence of the angle sums)."""
    cs, ss = [torch.ones_like(cT), cT], [torch.zeros_like(sT), sT]
    for _ in range(2, order):
        c, s = cs[-1], ss[-1]
        cs.append(c * cT - s * sT)
        ss.append(s * cT + c * sT)
    return cs[:order], ss[:order]


# (gather indices in range by construction — `_conjugate_tables` — so no per-load bounds check:
# 5-10 % of the two passes of a half, 1.65 → 1.5 ms at 13.4 K points, 1 thread)
_NO_ASSERT = {"assert_indirect_indexing": False}


@functools.partial(fused, options=_NO_ASSERT)
def _rz(aT: Tensor, C: Tensor, S: Tensor, perm: Tensor, absm: Tensor, sgn: Tensor) -> Tensor:
    """M(R_z(±angle)) a per point (a (n², Q)): a·cos(|m|φ) + a[(l, −m)]·sgn·sin(|m|φ) (C, S (n, Q)
    the cos/sin of `_angle_rows`, sgn (n², 1) carrying the sign of the rotation), one compiled pass."""
    return aT * C.index_select(0, absm) + aT.index_select(0, perm) * (S.index_select(0, absm) * sgn)


@functools.partial(fused, options=_NO_ASSERT)
def _gathered_rz(aT: Tensor, idx: Tensor, w: Tensor, C: Tensor, S: Tensor, perm: Tensor, absm: Tensor,
                 sgn: Tensor) -> Tensor:
    """`_rz` of A a, A given by its gathered terms (`_conjugate_tables`: (A a)_r = Σ_j w[r, j]
    a[idx[r, j]], unrolled over j), one compiled pass."""
    out = aT.index_select(0, idx[:, 0]) * w[:, 0:1]
    for j in range(1, idx.shape[1]):
        out = out + aT.index_select(0, idx[:, j]) * w[:, j:j + 1]
    return out * C.index_select(0, absm) + _gathered_perm(aT, idx, w, perm) * (S.index_select(0, absm) * sgn)


def _gathered_perm(aT: Tensor, idx: Tensor, w: Tensor, perm: Tensor) -> Tensor:
    """(A a)[(l, −m)] from A's gathered terms (rows permuted: no gather of a computed value)."""
    ip, wp = idx.index_select(0, perm), w.index_select(0, perm)
    out = aT.index_select(0, ip[:, 0]) * wp[:, 0:1]
    for j in range(1, idx.shape[1]):
        out = out + aT.index_select(0, ip[:, j]) * wp[:, j:j + 1]
    return out


def zonal_conjugate(vT: Tensor, nT: Tensor, op_key: tuple, scale: float = 1.0) -> Tensor:
    """(n², Q) M(R_n) · M · M(R_n)ᵀ v per point: the world-space SH of the function whose
    coefficients in a frame with z = n are M times those of v — for a zonal (z-symmetric) operator
    M such as the hemispherical M^α (`convolution.phong_operator`), so the tangent of the frame
    does not matter. With R_n = R_z(φ) R_y(θ) (n = (sin θ cos φ, sin θ sin φ, cos θ)) and
    M(R_y(θ)) = Xᵀ M(R_z(θ)) X (X = M(R_x(90°)), `_zyz_tables`):

        M(R_n) M M(R_n)ᵀ = R_z(φ) Xᵀ R_z(θ) · (X M Xᵀ) · R_z(−θ) X R_z(−φ),

    three fixed products — X and Xᵀ by their non-zeros (`_conjugate_tables`: 4 per row at order 8),
    the middle X M Xᵀ one (n², n²) product, block by block (`_operator_blocks`, `_blocked_product`: M couples
    only equal m, X only one band's parts, so X M Xᵀ is 4 dense blocks, 1,056 of 4,096 entries at order 8)
    — and four per-point z rotations (cos/sin of |m| times the
    angle on the ±m pairs), instead of building each point's SH rotation
    (`methods.core.sh_rotation`). Each half around the GEMM is one compiled pass over all Q points
    (`_zyz_half`: the z rotation `_rz`, X or Xᵀ by its non-zeros and the next z rotation,
    `_gathered_rz`), the point count marked dynamic so one kernel serves every Q (eager, the z
    rotations' gathers and temporaries took 85 % of the time; a variant over static blocks of 1024
    points was 0.70× as fast, session 11; a block-major (blocks, n², 1024–2048) layout, each block's
    rows in L2, gained only 1.1x over the flat one — the passes are bound by the instructions per
    gathered row, not by the cache, session 14).

    Args:
        vT: (n², Q) world-space SH (point-minor); nT: (3, Q) unit normals; op_key: ("phong", α).
        scale: a factor on the operator (folded into the middle product's blocks: no pass over
            the result; `specular_transfer`'s (α+1)/(2π)).
    """
    n = math.isqrt(vT.shape[0])
    ang = _zyz_angles(nT, n)
    plan = _block_plan(op_key, n, False, vT.dtype, vT.device, float(scale))
    return _zyz_up(_blocked_product(plan, _zyz_down(vT, ang, plan[0])), ang, plan[1])


def _polar(nT: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """cos θ, sin θ, cos φ, sin φ (Q,) each of unit directions nT (3, Q) = (sin θ cos φ, sin θ sin φ,
    cos θ), with φ = 0 on the pole (the ZYZ frame of `_zyz_angles` and `zyz_axes`)."""
    x, y, z = nT[0], nT[1], nT[2].clamp(-1.0, 1.0)
    rho = torch.sqrt(x * x + y * y)
    ok = rho > 1e-20
    safe = torch.where(ok, rho, torch.ones_like(rho))
    cp = torch.where(ok, x / safe, torch.ones_like(x))
    sp = torch.where(ok, y / safe, torch.zeros_like(y))
    return z, rho, cp, sp


@fused
def _zyz_angle_tables(nT: Tensor, order: int) -> Tensor:
    """(4, n, Q) the tables of `_zyz_angles` stacked, one compiled pass (eager, `_polar` and the two
    Chebyshev recurrences were ~40 small ops: 0.88 ms per call at 13.4 K points, 0.31 ms
    compiled, 1 thread). One stack of the 4n rows: stacks of stacks made Inductor write each table
    twice (its four (n, Q) stacks, then their copy into the result; 0.23 → 0.16 ms at 8.3 K
    points, 1 thread, bit-identical)."""
    z, rho, cp, sp = _polar(nT)
    Cp, Sp = _angle_rows(cp, sp, order)
    Ct, St = _angle_rows(z, rho, order)
    return torch.stack(Cp + Sp + Ct + St).view(4, order, -1)


def _zyz_angles(nT: Tensor, order: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """cos/sin (n, Q) of m·φ and m·θ (`_angle_rows`), n = (sin θ cos φ, sin θ sin φ, cos θ) the unit
    directions nT (3, Q) (φ = 0 on the pole: the operators conjugated are zonal), the point count
    marked dynamic (one compiled kernel for every count)."""
    nT = nT.contiguous()
    torch._dynamo.maybe_mark_dynamic(nT, 1)
    Cp, Sp, Ct, St = _zyz_angle_tables(nT, order).unbind(0)
    for t in (Cp, Sp, Ct, St):
        torch._dynamo.maybe_mark_dynamic(t, 1)
    return Cp, Sp, Ct, St


@functools.partial(fused, options=_NO_ASSERT)
def _zyz_half(aT: Tensor, C1: Tensor, S1: Tensor, C2: Tensor, S2: Tensor, perm: Tensor, absm: Tensor, sgn: Tensor,
              idx: Tensor, w: Tensor, src: Tensor | None = None, dst: Tensor | None = None) -> Tensor:
    """R_z(angle 2) A R_z(angle 1) a: `_rz` then `_gathered_rz` (A by its gathered terms) as one
    compiled function — Inductor makes it one pass, recomputing the first z rotation per gathered
    term instead of storing it (1.14x over the two compiled passes at 13.4 K points, 1 thread,
    load ~6 on 2 cores; equal numbers). ``src`` (n²,): a's rows are aT[src] (the rows of a blocked
    product in block order, `_block_plan`); ``dst`` (n²,): the result's rows returned in that order
    (the next product's column order) — both gathers folded into the pass's loads and stores."""
    if src is not None:
        aT = aT.index_select(0, src)
    out = _gathered_rz.eager(_rz.eager(aT, C1, S1, perm, absm, sgn), idx, w, C2, S2, perm, absm, sgn)
    return out if dst is None else out.index_select(0, dst)


def _zyz_down(vT: Tensor, ang: tuple, dst: Tensor | None = None) -> Tensor:
    """R_z(−θ) X R_z(−φ) v (n², Q): the first half of `zonal_conjugate` (X M(R_n)ᵀ v); ``dst``: its
    rows in that order (`_zyz_half`)."""
    n = len(ang[0])
    perm, absm, sgn, xi, xw, _, _ = _conjugate_tables(n, vT.dtype, vT.device)
    Cp, Sp, Ct, St = ang
    if vT.stride(1) != 1:   # (a column range of a wider array, `specular_parts`: read in place)
        vT = vT.contiguous()
    torch._dynamo.maybe_mark_dynamic(vT, 1)
    return _zyz_half(vT, Cp, Sp, Ct, St, perm, absm, -sgn, xi, xw, None, dst)


def _zyz_product(K: Tensor, aT: Tensor, blocks: tuple | None = None) -> Tensor:
    """K @ a, (n², n²) @ (n², Q) — on one thread below 16 rows: MKL splits such thin products over
    threads (methods.core.threads; `world_visibility`). ``blocks`` (`_operator_blocks` of K): the
    product block by block, K's structural zeros skipped — y[rows_b] = K[rows_b, cols_b] a[cols_b],
    a gathered and scattered by rows (4 blocks of 12–20 at order 8: 1,056 of K's 4,096 entries;
    1.17 vs 3.3 ms for the dense product at 13.4 K points, 1 thread, load ~2 on 2 cores; the
    physical setting's P frame 1.23x process CPU, `benchmarks.zh_pose_ab`, load ~5-9). The run-time
    paths take `_blocked_product` (the same block products without this function's row gathers and
    scatters, folded into the neighbouring `_zyz_half` passes); this one is its reference in tests."""
    with torch_threads(1) if K.shape[0] < 16 else contextlib.nullcontext():
        if blocks is None or len(blocks) == 1:
            return K @ aT
        out = torch.empty_like(aT)
        for rows_b, cols_b, K_b in blocks:
            out.index_copy_(0, rows_b, K_b @ aT.index_select(0, cols_b))
        return out


def _structure(op_key: tuple, order: int, lifted: bool, M: Tensor | None = None) -> Tensor:
    """(n², n²) bool: the entries of X M Xᵀ (`_conjugated`) or X M (`_lifted`, ``lifted``) that are
    not zero by structure — the boolean product of the non-zero patterns of X = M(R_x(90°)) (by band,
    and within a band between the cos/sin and odd/even-m parts) and of M (between equal m:
    `convolution.phong_operator` sets only those), so that an entry that is small but not zero is
    never dropped and one that is zero up to round-off always is. ``M``: the float64 operator
    already made (`_operator_blocks`)."""
    xs = (_zyz_tables(order)[3].abs() > 1e-12).double()
    if M is None:
        M = phong_operator(op_key[1], order, dtype=torch.float64)
    ms = (M != 0).double()
    S = xs @ ms
    return (S @ xs.T if not lifted else S) > 0


@functools.lru_cache(maxsize=None)
def _components(pattern: bytes, n2: int) -> tuple[tuple[tuple[int, ...], tuple[int, ...]], ...]:
    """The connected components of the bipartite graph rows ↔ columns of an (n², n²) structure
    (``pattern``: its bool array's bytes, row-major) as ((rows, cols), …), components without rows
    left out — kept per pattern: every Phong exponent but a few special ones has the same one, so a
    frame with a new exponent (VB / VBL) pays no union-find (~1 ms of Python per call, twice per
    exponent before)."""
    S = torch.frombuffer(bytearray(pattern), dtype=torch.bool).view(n2, n2)
    parent = list(range(2 * n2))                       # union-find over rows 0..n²−1, columns n²..2n²−1

    def find(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for r, c in S.nonzero().tolist():
        a, b = find(r), find(n2 + c)
        if a != b:
            parent[b] = a
    roots: dict[int, tuple[list[int], list[int]]] = {}
    for i in range(2 * n2):
        rows_b, cols_b = roots.setdefault(find(i), ([], []))
        (rows_b if i < n2 else cols_b).append(i % n2)
    return tuple((tuple(r), tuple(c)) for r, c in roots.values() if r)   # (an all-zero column: no output)


@functools.lru_cache(maxsize=None)
def _operator_blocks(op_key: tuple, order: int, lifted: bool, dtype: torch.dtype, device) -> tuple:
    """The dense blocks of X M Xᵀ (`_conjugated`) or X M (`_lifted`, ``lifted``) of the zonal
    operator named by ``op_key``: ((rows (r,) int64, cols (c,) int64, K[rows][:, cols] (r, c)), …)
    — the connected components of the bipartite graph rows ↔ columns of `_structure` (`_components`),
    so that K = Σ_b the blocks scattered to their rows and columns (`_zyz_product`); one block when K
    is not block-structured. M is made once (K = X M Xᵀ or X M as `_conjugated` / `_lifted` compute
    it: the same numbers)."""
    n2 = order * order
    M = phong_operator(op_key[1], order, dtype=torch.float64)
    S = _structure(op_key, order, lifted, M)
    X = _zyz_tables(order)[3]
    K = X @ M if lifted else X @ M @ X.T
    blocks = []
    for rows_b, cols_b in _components(S.contiguous().numpy().tobytes(), n2):
        r, c = torch.tensor(rows_b), torch.tensor(cols_b, dtype=torch.int64)
        blocks.append((r.to(device), c.to(device), K[r][:, c].to(dtype).to(device).contiguous()))
    return tuple(blocks)


def _zyz_up(aT: Tensor, ang: tuple, src: Tensor | None = None) -> Tensor:
    """R_z(φ) Xᵀ R_z(θ) a (n², Q): the second half of `zonal_conjugate` (M(R_n) Xᵀ a); ``src``: a's
    rows are aT[src] (`_zyz_half`)."""
    n = len(ang[0])
    perm, absm, sgn, _, _, ti, tw = _conjugate_tables(n, aT.dtype, aT.device)
    Cp, Sp, Ct, St = ang
    torch._dynamo.maybe_mark_dynamic(aT, 1)
    return _zyz_half(aT, Ct, St, Cp, Sp, perm, absm, sgn, ti, tw, src)


@functools.lru_cache(maxsize=None)
def _plan_layout(pattern: bytes, order: int, lifted: bool, device) -> tuple:
    """The exponent-free part of `_block_plan` for M's non-zero pattern (``pattern``: the bytes of
    the (n², n²) bool M != 0, row-major): cols, src (n²,) int64 on ``device``, per block (r0, r1, c0,
    c1) its spans, and the flat positions (Σ_b r_b·c_b,) int64 of the blocks' entries in K (row-major,
    block after block) — so a new exponent (every VB / VBL frame) costs M, K and one gather."""
    n2 = order * order
    ms = torch.frombuffer(bytearray(pattern), dtype=torch.bool).view(n2, n2)
    xs = (_zyz_tables(order)[3].abs() > 1e-12).double()
    S = xs @ ms.double()
    S = (S @ xs.T if not lifted else S) > 0          # `_structure`
    comps = _components(S.contiguous().numpy().tobytes(), n2)
    rows = torch.tensor([i for r, _ in comps for i in r], dtype=torch.int64)
    cols = torch.tensor([i for _, c in comps for i in c], dtype=torch.int64)
    src = torch.empty_like(rows)
    src[rows] = torch.arange(rows.shape[0])
    spans, flat, r0, c0 = [], [], 0, 0
    for r, c in comps:
        rt_, ct = torch.tensor(r, dtype=torch.int64), torch.tensor(c, dtype=torch.int64)
        flat.append((rt_[:, None] * n2 + ct[None, :]).flatten())
        spans.append((r0, r0 + len(r), c0, c0 + len(c)))
        r0, c0 = r0 + len(r), c0 + len(c)
    return cols.to(device), src.to(device), tuple(spans), torch.cat(flat)


@functools.lru_cache(maxsize=None)
def _block_plan(op_key: tuple, order: int, lifted: bool, dtype: torch.dtype, device, scale: float = 1.0) -> tuple:
    """`_operator_blocks` laid out for products on contiguous rows: cols (n²,) int64 the input rows
    in block order (the blocks' columns concatenated: each row once, tests), src (n²,) int64 with
    output row r at src[r] of the block-ordered result, and per block (r0, r1, c0, c1, K_b) its
    spans in the two orders — so that `_blocked_product` needs no gather or scatter of rows (the
    neighbouring `_zyz_half` passes do them in their loads and stores). ``scale``: the blocks
    times that factor (scaled in float64, then cast).

    Made from M (one `convolution.phong_operator`), K = X M Xᵀ or X M (as `_conjugated` /
    `_lifted`) and the layout of M's non-zero pattern (`_plan_layout`, kept: the same for every
    exponent but a few special ones) — the same tensors as from `_operator_blocks` bit for bit
    (tests), at ~0.4 ms per new exponent instead of ~2.4–6.7 (two `_operator_blocks` calls, each
    two more `phong_operator` calls and a Python union-find: the VB / VBL frames' extra cost)."""
    M = phong_operator(op_key[1], order, dtype=torch.float64)
    cols, src, spans, flat = _plan_layout((M != 0).numpy().tobytes(), order, lifted, device)
    X = _zyz_tables(order)[3]
    K = X @ M if lifted else X @ M @ X.T
    vals = K.view(-1).index_select(0, flat)
    if scale != 1.0:
        vals = vals * scale
    vals = vals.to(dtype)
    out, a = [], 0
    for r0, r1, c0, c1 in spans:
        n = (r1 - r0) * (c1 - c0)
        # (each block its own allocation, as `_operator_blocks`' blocks)
        out.append((r0, r1, c0, c1, vals[a:a + n].view(r1 - r0, c1 - c0).to(device).clone()))
        a += n
    return cols, src, tuple(out)


def _blocked_product(plan: tuple, aP: Tensor) -> Tensor:
    """K a in block order (`_block_plan`): aP (n², Q) a's rows in the plan's column order, result
    (n², Q) with row r of K a at plan's src[r] — each block one product of contiguous rows into
    contiguous rows (the products of `_zyz_product` with blocks, without its row gathers and
    scatters: the same numbers, bit for bit)."""
    _, _, spans = plan
    out = torch.empty(sum(r1 - r0 for r0, r1, _, _, _ in spans), aP.shape[1], dtype=aP.dtype, device=aP.device)
    with torch_threads(1) if aP.shape[0] < 16 else contextlib.nullcontext():
        for r0, r1, c0, c1, K_b in spans:
            torch.mm(K_b, aP[c0:c1], out=out[r0:r1])
    return out


@functools.lru_cache(maxsize=None)
def _lifted(op_key: tuple, order: int) -> Tensor:
    """X · M (float64) of the zonal operator M named by ``op_key`` (as `_conjugated`): the
    product that takes the SH of a function in the ZYZ frame of n (`world_visibility`'s
    ``frame="zyz"``) to the input of `_zyz_up` — X M Xᵀ (X M(R_n)ᵀ v) = X M v_zyz."""
    X = _zyz_tables(order)[3]
    return X @ phong_operator(op_key[1], order, dtype=torch.float64)


def zyz_rows(order: int, device=None) -> Tensor:
    """(n²,) int64: the order of the SH coefficients that `cosine_visibility_zyz`'s product reads
    its input rows in (`_block_plan` of X M¹, its blocks' columns) — `world_visibility`'s ``rows``
    for ``cosine_visibility_zyz(…, ordered=True)``."""
    return _block_plan(("phong", 1.0), order, True, torch.float32, torch.device("cpu"))[0].to(device)


def cosine_visibility_zyz(vzT: Tensor, nT: Tensor, *, ordered: bool = False) -> Tensor:
    """`cosine_visibility` from the visibility in the ZYZ frame of each point's normal (vzT (n², Q):
    `world_visibility` with ``frame="zyz"``, v_zyz = M(R_n)ᵀ v): M(R_n) M¹ v_zyz — the second half
    of `zonal_conjugate` alone, after one (n², n²) product by X M¹ (`_lifted`, block by block as `zonal_conjugate`): the lobes are taken to
    that frame as 3-vectors before eq. 1, so the first half (two z rotations and X per point) is not
    needed. Same numbers as `cosine_visibility` of the world-space v to round-off.

    Args:
        vzT: (n², Q) SH visibility in the frame (e1, e2, n) of `zyz_axes`; nT: (3, Q) unit normals.
        ordered: vzT's rows are already in the product's order (`zyz_rows`; `world_visibility`
            made them so), not the SH order: no gather of the rows (a 3.4 MB copy per pose at
            order 8 on the bench creature).
    """
    n = math.isqrt(vzT.shape[0])
    plan = _block_plan(("phong", 1.0), n, True, vzT.dtype, vzT.device)
    if native_conjugate and vzT.dtype == torch.float32 and vzT.device.type == "cpu" \
            and n <= zn.CONJ_MAX_ORDER and vzT.dim() == 2 and nT.dim() == 2:
        # (one C pass: the blocks of X M¹ and the second half per point; float32 round-off)
        w = zn.specular_conjugate(vzT if ordered else vzT.index_select(0, plan[0]), nT, None,
                                  (0, int(vzT.shape[1])), _conjugate_tables(n, vzT.dtype, vzT.device), plan, lifted=True)
        if w is not None:
            return w
    return _zyz_up(_blocked_product(plan, vzT if ordered else vzT.index_select(0, plan[0])), _zyz_angles(nT, n),
                   plan[1])


@functools.lru_cache(maxsize=64)
def plane_cosine_operator(n0: tuple[float, float, float], order: int) -> Tensor:
    """(n², n²) float64 K with `cosine_visibility_zyz`(vzT, n0 for every point, ordered=True) = K @ vzT:
    M(R_n0) M¹ with its columns in `zyz_rows` order — the same operator for every point sharing the
    normal n0 (a plane's vertices, `ZHShadow._front_radiance`), so their diffuse term is one
    (3, n²) row block ((l ⊙ kd / π)ᵀ K) times their visibility, without a w of their own. Made by
    the same factors applied to the identity (eager, float64: no kernel compiled), kept per normal."""
    n2 = order * order
    nT = torch.tensor(n0, dtype=torch.float64)[:, None].expand(3, n2).contiguous()
    plan = _block_plan(("phong", 1.0), order, True, torch.float64, torch.device("cpu"))
    Cp, Sp, Ct, St = _zyz_angle_tables.eager(nT, order).unbind(0)
    perm, absm, sgn, _, _, ti, tw = _conjugate_tables(order, torch.float64, torch.device("cpu"))
    aP = _blocked_product(plan, torch.eye(n2, dtype=torch.float64))
    return _zyz_half.eager(aP, Ct, St, Cp, Sp, perm, absm, sgn, ti, tw, plan[1])


def cosine_visibility(vT: Tensor, nT: Tensor) -> Tensor:
    """(n², Q) world-space SH of V(ω)·max(0, n·ω) (order-n projection; `method.shade`'s
    ``specular="cosine"``: M¹ v in the frame of n, taken back to world space) for the points'
    visibility vT (n², Q) and unit normals nT (3, Q) — `zonal_conjugate` with M¹."""
    return zonal_conjugate(vT, nT, ("phong", 1.0))


def point_transfer(vT: Tensor, nT: Tensor, woT: Tensor, vregion: Tensor, alphas: list[float | None], *,
                   cosine: bool = False) -> tuple[Tensor, Tensor | None]:
    """Lighting-free transfer vectors of Q points by frame rotations (`zonal_conjugate`): diffuse
    t_d = (1/π) M(R_n) M¹ M(R_n)ᵀ v and specular t_s = ((α+1)/(2π)) M(R_R) M^α M(R_R)ᵀ v' (v' = v,
    or for ``cosine`` the cos θ_i-weighted w = π t_d), so that the terms are t · l (§4.3 #2–#5:
    v_nᵀ M¹ L_n = vᵀ M(R_n) M¹ M(R_n)ᵀ l, the rotations being orthogonal). Per point 3 (n², n²)
    GEMMs per term — fewer flops than `_identity_table`'s K·n⁴, and at orders above
    `MONOMIAL_MAX_ORDER` fewer than the lighting tables' K·3n² (vertex shading: `ZHShadow.render`).

    Args:
        vT: (n², Q) world-space SH visibility; nT, woT: (3, Q) unit normals / directions to the
            viewer; vregion: (Q,) int64 region of each point; alphas: per region the Phong exponent,
            None for no specular term.
    Returns:
        t_d (n², Q) and t_s (n², Q) (zero where the region has no specular term; None if none has).
    """
    w = cosine_visibility(vT, nT)
    return w * (1.0 / math.pi), specular_transfer(w if cosine else vT, nT, woT, vregion, alphas)


def specular_parts(srcT: Tensor, nT: Tensor, woT: Tensor, vregion: Tensor,
                   alphas: list[float | None], keep: Tensor | None = None
                   ) -> list[tuple[int, tuple[int, int] | Tensor, Tensor]] | None:
    """The t_s of `specular_transfer` per region with a specular term, not assembled: [(region,
    span, t_s (n², Q_r) of the span's columns)] — span (a0, a1) when the region's points are one
    range of columns (a mesh's vertices: `Scene` concatenates one mesh per region; the creature's
    9,694 of 13,415), else their positions (Q_r,) int64; the columns of no part are zero. None when
    no region has a specular term. A range's columns are read as a strided view of srcT by the
    compiled first half (`_zyz_down`) and R is made for them alone, so a caller that consumes the
    parts region by region (`ZHShadow._render_vertex`) pays no copy of srcT's columns in and none
    of the result out (2 × 2.5 MB and a 1 MB zero fill per P frame at order 8 on the creature).

    ``keep`` (Q,) bool: only those columns' t_s are needed (vertex shading: the front-facing
    vertices, n·ωo > 0 — the others' radiance is zero); a part then holds the kept columns of its
    region alone, by position (the other columns, as a part's, zero when assembled). The columns
    are independent, so those made are the same numbers (to float32 round-off: the compiled passes'
    vector and tail loops) — about half of them on the bench creature's views."""
    if all(a is None for a in alphas):
        return None
    parts = []
    for r, a in enumerate(alphas):
        if a is None:
            continue
        p = ((vregion == r) if keep is None else (vregion == r) & keep).nonzero().squeeze(-1)
        if not p.shape[0]:
            continue
        a0, a1 = int(p[0]), int(p[-1]) + 1
        # (α+1)/(2π) goes into the operator (`zonal_conjugate`'s scale: no pass over the result)
        scale, key = (float(a) + 1.0) / (2.0 * math.pi), ("phong", float(a))
        span = (a0, a1) if a1 - a0 == p.shape[0] else p
        t = _native_conjugate(srcT, nT, woT, span, key, scale) if native_conjugate else None
        if t is not None:   # (one C pass: R, the angles, both halves and the blocks; float32 round-off)
            parts.append((r, span, t))
        elif a1 - a0 == p.shape[0]:
            parts.append((r, (a0, a1), zonal_conjugate(srcT[:, a0:a1], reflect_T(nT[:, a0:a1], woT[:, a0:a1]), key,
                                                       scale)))
        else:
            parts.append((r, p, zonal_conjugate(srcT.index_select(1, p),
                                                reflect_T(nT.index_select(1, p), woT.index_select(1, p)), key, scale)))
    return parts


# `specular_parts` conjugates each part by `native.specular_conjugate` (one C pass per part), and
# `cosine_visibility_zyz` (``ordered``) takes its second half by the same pass (``lifted``), where it
# runs; False: by `reflect_T` + `zonal_conjugate` / `_zyz_up` (the compiled passes and GEMMs: the
# tests' oracle)
native_conjugate = True


def _native_conjugate(srcT: Tensor, nT: Tensor, woT: Tensor, span, key: tuple, scale: float) -> Tensor | None:
    """`zonal_conjugate`(srcT[:, span], `reflect_T`(nT[:, span], woT[:, span]), key, scale) by
    `native.specular_conjugate`, or None where it does not run (float32 CPU arrays of rows with unit
    stride, order ≤ `native.CONJ_MAX_ORDER`)."""
    if srcT.dtype != torch.float32 or srcT.device.type != "cpu" or srcT.dim() != 2:
        return None
    n = math.isqrt(srcT.shape[0])
    if n * n != srcT.shape[0] or n > zn.CONJ_MAX_ORDER or nT.stride(0) != woT.stride(0):
        return None
    plan = _block_plan(key, n, False, srcT.dtype, srcT.device, float(scale))
    return zn.specular_conjugate(srcT, nT, woT, span, _conjugate_tables(n, srcT.dtype, srcT.device), plan)


def specular_transfer(srcT: Tensor, nT: Tensor, woT: Tensor | None, vregion: Tensor,
                      alphas: list[float | None], *, parts: list | None = None) -> Tensor | None:
    """The t_s of `point_transfer` from the visibility it rotates (srcT (n², Q): v, or w for the
    cosine variant) — apart, since only it depends on the view and the exponents: `specular_parts`
    assembled into one (n², Q) array (zero in the columns of no specular region); ``parts``: those
    already made (then nT and woT are not read)."""
    if parts is None:
        parts = specular_parts(srcT, nT, woT, vregion, alphas)
    if parts is None:
        return None
    Q = srcT.shape[1]
    if len(parts) == 1 and isinstance(parts[0][1], tuple) and parts[0][1] == (0, Q):
        return parts[0][2]
    ts = torch.zeros_like(srcT)
    for _, span, t in parts:
        if isinstance(span, tuple):
            ts[:, span[0]:span[1]] = t
        else:
            ts.index_copy_(1, span, t)
    return ts


def dot_T(aT: Tensor, bT: Tensor) -> Tensor:
    """(Q,) a·b of (3, Q) vectors (rows = components): two fused multiply-adds on rows, no
    reduction over the short leading dim."""
    return torch.addcmul(torch.addcmul(aT[0] * bT[0], aT[1], bT[1]), aT[2], bT[2])


def reflect_T(nT: Tensor, woT: Tensor) -> Tensor:
    """(3, Q) unit R = reflect(ωo, n) = 2(n·ωo)n − ωo of unit nT, woT (3, Q), renormalised as
    `methods.core.frames.reflect` + the reference path's normalisation."""
    R = torch.addcmul(-woT, 2.0 * dot_T(woT, nT), nT)
    return R / dot_T(R, R).sqrt().clamp_min(1e-12)


def shade_terms(vT: Tensor, nT: Tensor, woT: Tensor, Wd: Tensor, Ws: Tensor | None) -> tuple[Tensor, Tensor | None]:
    """Diffuse and specular terms of Q points (before kd, ks; front-facing test not applied), in
    the point-minor layout the batched products want (rows = components, columns = points).

    Args:
        vT: (n², Q) world-space SH visibility; nT, woT: (3, Q) unit normals / directions to the viewer.
        Wd: `table`(·, 1, diffuse=True); Ws: `table`(·, α) or None (no specular term).
    Returns:
        diffuse (3, Q) = v · T¹(n); specular (3, Q) = v · T^α(R) or None.
    """
    diff = _term(vT, nT, Wd, True)
    if Ws is None:
        return diff, None
    return diff, _term(vT, reflect_T(nT, woT), Ws, False)


def interpolate(values: Tensor, vi: Tensor, b: Tensor) -> Tensor:
    """(Q, C) = Σ_k b[q, k] · values[vi[q, k]]: barycentric interpolation of per-vertex rows
    (values (N, C); vi (Q, k) int32 or int64 vertex ids, b (Q, k) weights; k = 1 is a plain gather), as one
    fused gather-and-sum (``embedding_bag``, mode "sum" with per-sample weights)."""
    return torch.nn.functional.embedding_bag(vi, values, per_sample_weights=b.to(values.dtype), mode="sum")


def barycentrics(uv: Tensor) -> Tensor:
    """(Q, 3) weights (1 − u − v, u, v) of the G-buffer's (Q, 2) barycentrics (u, v)
    (`GBuffer.vertex_weights` without the miss mask)."""
    u, v = uv.unbind(-1)
    return torch.stack([1.0 - u - v, u, v], -1)


def rows(x: Tensor) -> Tensor:
    """(C, Q) contiguous copy of a (Q, C) tensor (one strided row copy per column: several times
    faster than ``x.T.contiguous()`` for small C)."""
    return torch.stack(x.unbind(-1))


def planar_groups(nT: Tensor, *, min_points: int | None = None, max_groups: int | None = None,
                  match=None) -> tuple[list[tuple[Tensor, Tensor | None]], Tensor | None, Tensor | None]:
    """Points whose normals are bitwise equal (a plane), as groups, and the rest.

    A group shares the diffuse factor T¹(n) (n², C), so its diffuse term v · T¹(n) is linear in v:
    per vertex, then interpolated, exactly (`shade`). Candidates are the normals of the first
    remaining point and of 7 evenly spaced ones; a candidate makes a group when at least
    ``min_points`` (default `PLANAR_MIN_POINTS`) points share it (a smaller group would not pay for
    its per-vertex pass; every 16th point screens a candidate first). Stops when no candidate
    qualifies or after ``max_groups`` (`PLANAR_MAX_GROUPS`) groups.

    Args:
        nT: (3, Q) unit normals (rows = components; a strided view, e.g. the transpose of the
            G-buffer's (Q, 3) normals, is read as it is).
        match: optional n0 → ((Q,) bool ``nT == n0`` column-wise, its count) for the first pass over
            all Q points (the same booleans, e.g. one compiled pass: `plane_match`).
    Returns:
        groups [(n0 (3,), positions (Q_g,) int64 ascending — None for a first group that holds
        more than half the points: its mask is returned instead)], that mask (Q,) bool or None,
        and the rest's positions (ascending; None when there is no group: every point).
    """
    min_points = PLANAR_MIN_POINTS if min_points is None else min_points
    max_groups = PLANAR_MAX_GROUPS if max_groups is None else max_groups
    Q = nT.shape[1]
    groups: list[tuple[Tensor, Tensor | None]] = []
    mask = rest = None
    cur = nT
    while len(groups) < max_groups and cur.shape[1] >= min_points:
        found = first_plane(cur, min_points, match if cur is nT else None)
        if found is None:
            break
        n0, eq, cnt = found
        keep = ~eq
        if rest is None:
            if 2 * cnt > Q:
                mask = eq
                groups.append((n0, None))
            else:
                groups.append((n0, eq.nonzero().squeeze(-1)))
            rest = keep.nonzero().squeeze(-1)
            # a transposed (Q, 3) view: gather its rows (a column gather of the strided view was
            # 1.6 ms at bench size, the row gather 0.06)
            cur = cur.T.index_select(0, rest).T if cur.stride(0) == 1 and cur.shape[0] > 1 else cur.index_select(1, rest)
        else:
            groups.append((n0, rest[eq]))
            rest, cur = rest[keep], cur[:, keep]
    return groups, mask, rest


def first_plane(cur: Tensor, min_points: int, match=None, screen: list[int] | None = None
                ) -> tuple[Tensor, Tensor, int] | None:
    """One step of `planar_groups`' search over the normals cur (3, m): (n0 (3,), (m,) bool ``cur ==
    n0`` column-wise, its count) for the first candidate — the normals of 8 evenly spaced points,
    screened on every 16th point — shared by at least ``min_points`` points, or None. ``match``: as
    `planar_groups`' (n0 → (that mask, its count)); ``screen``: the 8 screened counts, already made
    (`native.screen_counts`: the same counts)."""
    m = cur.shape[1]
    sub = cur[:, ::16].contiguous() if screen is None else None   # (screened every candidate: contiguous rows)
    for c in range(8):
        if screen is not None:
            if screen[c] * 32 < min_points:
                continue
            n0 = cur[:, c * m // 8].clone()
        else:
            n0 = cur[:, c * m // 8].clone()
            if int(((sub[0] == n0[0]) & (sub[1] == n0[1]) & (sub[2] == n0[2])).sum()) * 32 < min_points:
                continue                                               # under half the size, screened
        if match is not None:
            eq, cnt = match(n0)
            cnt = int(cnt)
        else:
            eq = (cur[0] == n0[0]) & (cur[1] == n0[1]) & (cur[2] == n0[2])
            cnt = int(eq.sum())
        if cnt >= min_points:
            return n0, eq, cnt
    return None


@fused
def _plane_match(normal: Tensor, n0: Tensor, region: Tensor, spec: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """(Q,) bool: normal (Q, 3) row-major equals n0 (3,) bitwise (as `planar_groups`), their count
    and the number of those points whose region (Q,) int64 has a specular term (``spec`` (regions,) bool),
    one compiled pass over the G-buffer's normals as they are stored."""
    eq = (normal[:, 0] == n0[0]) & (normal[:, 1] == n0[1]) & (normal[:, 2] == n0[2])
    return eq, eq.sum(), (eq & spec[region]).sum()


def plane_match(normal: Tensor, region: Tensor, spec: Tensor, specular: dict):
    """The ``match`` of `planar_groups` over the (Q, 3) row-major normals of a G-buffer (compiled:
    the three eager compares and two ands over all samples were 5 passes, and the (3, Q) copy of the
    normals one more); it also counts the matching points of a region with a specular term into
    ``specular``[n0 as a tuple] (`ZHShadow._render_planes` needs a plane without one)."""
    def match(n0: Tensor) -> tuple[Tensor, Tensor]:
        eq, cnt, ns = _plane_match(normal, n0, region, spec)
        specular[tuple(n0.tolist())] = ns
        return eq, cnt
    return match


def _plane_counts(groups: list, mask: Tensor | None, region: Tensor, vertex_normal: Tensor,
                  vertex_region: Tensor, planar: int | None = None) -> dict:
    """{"planar": points on the planes, "groups": planes, "plane_vertices": a zero-argument
    function (evaluated on demand, by `ZHShadow.frame_cost`) counting the vertices whose normal
    is a plane's and whose region has points on that plane — the per-vertex pass a plane needs at
    least; given ``keep`` (N,) bool, those among the kept vertices alone (the frame's referenced
    ones)}, and zeros for "specular", "planar_specular" (filled by the caller). ``planar``: the count of
    ``mask`` where the caller has it already (one group of it: no pass over the mask)."""
    out = {"planar": 0, "groups": len(groups), "planar_specular": 0, "specular": 0}
    for _, pos in groups:
        if pos is None:
            out["planar"] += int(torch.count_nonzero(mask)) if planar is None else planar   # (3x mask.sum())
        else:
            out["planar"] += int(pos.shape[0])

    def plane_vertices(keep: Tensor | None = None) -> int:
        nv, total = vertex_normal, 0
        for n0, pos in groups:
            regs = torch.unique(region[mask] if pos is None else region[pos])
            on = (nv[:, 0] == n0[0]) & (nv[:, 1] == n0[1]) & (nv[:, 2] == n0[2])
            on = on & torch.isin(vertex_region, regs)
            total += int((on if keep is None else on & keep).sum())
        return total

    out["plane_vertices"] = plane_vertices
    return out


def point_counts(nT: Tensor, region: Tensor, spec_regions: list[bool], vertex_normal: Tensor,
                 vertex_region: Tensor, min_points: int | None = None) -> dict:
    """The counts `shade` reports, without shading: planes (`planar_groups` of at least ``min_points``
    points, default `PLANAR_MIN_POINTS`; `_plane_counts`) and the points with a specular term
    (region in ``spec_regions``), on planes or not."""
    Q = nT.shape[1]
    mp = PLANAR_MIN_POINTS if min_points is None else min_points
    groups, mask, _ = planar_groups(nT, min_points=mp) if Q >= mp else ([], None, None)
    counts = _plane_counts(groups, mask, region, vertex_normal, vertex_region)
    spec = torch.tensor(spec_regions, dtype=torch.bool, device=region.device)[region.clamp_min(0)]
    counts["specular"] = int(spec.sum())
    on_plane = torch.zeros(Q, dtype=torch.bool, device=nT.device)
    for _, pos in groups:
        if pos is None:
            on_plane |= mask
        else:
            on_plane[pos] = True
    counts["planar_specular"] = int((spec & on_plane).sum())
    return counts


def diffuse_at(Wd: Tensor, n0: Tensor, C: int = 3) -> Tensor:
    """(n², C) T¹(n0): the diffuse factor of every SH visibility coefficient at one normal n0 (3,)
    (the features of n0 kept per normal: `_normal_features`)."""
    n2 = Wd.shape[1] // C
    # (the key: n0's values exactly — float32 → Python float is exact — converted once to Wd's dtype
    # as before, so the features are bit for bit those of ``n0.to(Wd.dtype)``)
    return (Wd.T @ _normal_features(tuple(n0.tolist()), math.isqrt(n2), Wd.dtype, Wd.device)).view(n2, C)


@functools.lru_cache(maxsize=64)
def _normal_features(n0: tuple, order: int, dtype: torch.dtype, device) -> Tensor:
    """(K, 1) diffuse `features` of one normal n0 (a plane's: the same every frame), made once — a
    lighting frame's plane term needed only the product by the new table (the features were ~15 eager
    ops of a single column, 0.3 ms of a settled L frame on the bench creature)."""
    return features(torch.tensor(n0, dtype=dtype, device=device).reshape(3, 1), order, True)


def shade(v: Tensor, vi: Tensor, b: Tensor, nT: Tensor, woT: Tensor, region: Tensor, vertex_region: Tensor,
          vertex_normal: Tensor, mats: list[tuple[Tensor, Tensor, Tensor, Tensor | None]], *, planar: bool = True,
          chunk: int = CHUNK, cosine: bool = False, tables: str = "vertex",
          U: Tensor | None = None) -> tuple[Tensor, dict[str, int]]:
    """Exit radiance of Q points (§4.3 steps 2–5 through the tables, module docstring).

    A point's visibility is Σ_k b[q, k] v[vi[q, k]] (a G-buffer sample: its face's three vertices
    and barycentrics; a vertex: itself with weight 1). Points on a plane (`planar_groups`, over all
    regions: the diffuse table does not depend on the material) get their diffuse term per vertex,
    u = kd(vertex) ⊙ v · T¹(n0), interpolated like v — exact, the term is linear in v and a face's
    vertices share its region. Every other diffuse term and every specular term goes through the
    feature GEMMs (`shade_terms`), per region, in chunks of ``chunk`` points.

    Args:
        v: (N, n²) per-vertex world-space SH visibility; vi, b: (Q, k) vertex ids / weights;
        nT, woT: (3, Q) unit normals / directions to the viewer; region: (Q,) int64 region of
        each point; vertex_region: (N,) int64; vertex_normal: (N, 3) (counts only);
        mats: per region (kd (3,), ks (3,), Wd, Ws or None: no specular term); one Wd for all.
        planar: use `planar_groups` (False: every point through the GEMMs).
        cosine: the specular term of ``specular="cosine"``: v · T^α(R) with v replaced by the
            cos θ_i-weighted visibility w = `cosine_visibility`(v, n) of the point (same tables:
            the term is linear in the visibility it dots).
        tables: how the points off the planes are shaded without ``cosine`` — "vertex": through
            the per-vertex table U (`vertex_table`, `sample_terms`: 4× fewer flops per point);
            "point": the feature GEMMs per point (`shade_terms`; also every ``cosine`` point, whose
            w is not interpolated linearly from the vertices). Both the same math.
        U: `vertex_table`(v, vertex_region, mats) when the caller kept it (tables="vertex").
    Returns:
        (3, Q) radiance (0 where n·ωo ≤ 0, as the BRDFs) and counts (`_plane_counts`, plus
        "specular": points with a specular term, "planar_specular": those of them on planes).
    """
    Q, dev, dt = nT.shape[1], v.device, v.dtype
    groups, mask, rest = planar_groups(nT) if planar and Q >= PLANAR_MIN_POINTS else ([], None, None)
    Wd = mats[0][2]
    counts = _plane_counts(groups, mask, region, vertex_normal, vertex_region)
    out = None
    if groups:
        kd_v = torch.stack([m[0] for m in mats]).to(dev, dt).index_select(0, vertex_region)   # (N, 3)
        for g, (n0, pos) in enumerate(groups):
            u = (v @ diffuse_at(Wd, n0)) * kd_v                                     # (N, 3) per vertex
            if pos is None:   # most points: interpolate everywhere, keep the group's (no gathers)
                out = rows(interpolate(u, vi, b)).mul_(mask)
            else:
                if out is None:
                    out = torch.zeros(3, Q, dtype=dt, device=dev)
                out.index_copy_(1, pos, interpolate(u, vi.index_select(0, pos), b.index_select(0, pos)).T)
    if out is None:
        out = torch.empty(3, Q, dtype=dt, device=dev)

    n = math.isqrt(v.shape[1])

    def general(p: Tensor | None, kd: Tensor, ks: Tensor, Wd_: Tensor | None, Ws: Tensor | None, add: bool) -> None:
        """out[:, p] (= or +=) kd ⊙ diffuse (unless Wd_ is None) + ks ⊙ specular (if Ws): one
        GEMM per chunk, the albedos folded into the stacked tables [Wd ⊙ kd; Ws ⊙ ks]."""
        Ws_ = [] if Ws is None else [(Ws.view(Ws.shape[0], -1, 3) * ks).view(Ws.shape[0], -1)]
        W = torch.cat(([] if Wd_ is None else [(Wd_.view(Wd_.shape[0], -1, 3) * kd).view(Wd_.shape[0], -1)]) + Ws_)
        Kd = 0 if Wd_ is None else Wd_.shape[0]
        split = cosine and Ws is not None            # the specular term dots w, not v: its own GEMM
        if split:
            WdT, WsT = W[:Kd].T.contiguous(), W[Kd:].T.contiguous()
        m = Q if p is None else p.shape[0]
        acc = None if p is None else torch.empty(3, m, dtype=dt, device=dev)   # scattered once, per row
        for a in range(0, m, chunk):
            s = slice(a, a + chunk)
            if p is None:
                vi_c, b_c, n_c, wo_c = vi[s], b[s], nT[:, s], woT[:, s]
            else:
                pc = p[a:a + chunk]
                vi_c, b_c = vi.index_select(0, pc), b.index_select(0, pc)
                n_c, wo_c = nT.index_select(1, pc), woT.index_select(1, pc)
            f = torch.empty(W.shape[0], n_c.shape[1], dtype=dt, device=dev)
            if Wd_ is not None:
                features(n_c, n, True, out=f[:Kd])
            if Ws is not None:
                features(reflect_T(n_c, wo_c), n, False, out=f[Kd:])
            vT = rows(interpolate(v, vi_c, b_c))                                    # (n², Q_c)
            if not split:
                rad = ((W.T @ f).view(n * n, 3, -1) * vT[:, None]).sum(0)            # (3, Q_c)
            else:
                wT = cosine_visibility(vT, n_c)
                rad = ((WsT @ f[Kd:]).view(n * n, 3, -1) * wT[:, None]).sum(0)
                if Kd:
                    rad += ((WdT @ f[:Kd]).view(n * n, 3, -1) * vT[:, None]).sum(0)
            if p is None:
                if add:
                    out[:, s] += rad
                else:
                    out[:, s] = rad
            else:
                acc[:, s] = rad
        if p is not None:   # row by row: a 1-D scatter is several times faster than one along dim 1
            for c in range(3):
                (out[c].index_add_ if add else out[c].index_copy_)(0, p, acc[c])

    single = len(mats) == 1
    if tables not in ("vertex", "point"):
        raise ValueError(f"tables must be 'vertex' or 'point', got {tables!r}")
    per_vertex = tables == "vertex" and not cosine
    if per_vertex:   # every point off the planes, all regions at once (U's rows carry the region's tables)
        spec = any(m[3] is not None for m in mats)
        U = vertex_table(v, vertex_region, mats) if U is None else U
        if not groups:
            out = sample_terms(U, vi, b, nT, woT, n, diffuse=True, specular=spec)
        elif rest.shape[0]:
            rad = sample_terms(U, vi.index_select(0, rest), b.index_select(0, rest), nT.index_select(1, rest),
                               woT.index_select(1, rest), n, diffuse=True, specular=spec)
            for c in range(3):   # row by row (as `general`)
                out[c].index_copy_(0, rest, rad[c])
    for r, (kd, ks, _, Ws) in enumerate(mats):
        kd, ks = kd.to(dev, dt), ks.to(dev, dt)
        if per_vertex and not groups:   # (shaded above: the region's points only counted, not gathered)
            if Ws is not None:
                counts["specular"] += Q if single else int((region == r).sum())
            continue
        if not groups and single:
            p = None                                                               # every point, in order
        else:
            ids = rest if groups else torch.arange(Q, device=dev)
            p = ids if single else ids[region.index_select(0, ids) == r]
        if not per_vertex and (p is None or p.shape[0]):
            general(p, kd, ks, Wd, Ws, add=False)
        if Ws is not None:
            counts["specular"] += Q if p is None else int(p.shape[0])
            for _, pos in groups:                                                  # the planes' specular term
                if pos is None:
                    pos = mask.nonzero().squeeze(-1)
                pg = pos if single else pos[region.index_select(0, pos) == r]
                if pg.shape[0]:
                    general(pg, kd, ks, None, Ws, add=True)
                    counts["specular"] += int(pg.shape[0])
                    counts["planar_specular"] += int(pg.shape[0])
    return out.mul_(dot_T(nT, woT) > 0), counts                                # 0 where n·ωo ≤ 0


@functools.lru_cache(maxsize=None)
def _identity_table(order: int, alpha: float, diffuse: bool) -> Tensor:
    """`table` of the identity lighting (n² channels, lighting coefficient i = e_i): W (K, n²·n²)
    with Σ_j v_j T_ji(r) the transfer vector t_i(r) of the lighting coefficient i (float32)."""
    n2 = order * order
    return table(torch.eye(n2, dtype=torch.float64), alpha, diffuse=diffuse).float()


def relight_cache(v: Tensor, vi: Tensor, b: Tensor, nT: Tensor, woT: Tensor, region: Tensor, vertex_region: Tensor,
                  vertex_normal: Tensor, alphas: list[float | None], *, planar: bool = True,
                  chunk: int = CHUNK, cosine: bool = False) -> dict:
    """What a frame that changes only the lighting needs of the points of `shade` (same args;
    ``alphas``: per region the Phong exponent, None for no specular term): their lighting-free
    transfer, so that the frame is one small product per region (`relight`).

    * planes (`planar_groups`): the vertex ids and barycentrics (front-facing test and group folded
      into the weights); the per-vertex diffuse factor v · T¹(n0) is the lighting's part;
    * every other point: t_d(q) = Σ_j v_j T¹_j·(n) ((n², Q), the diffuse transfer vector of the
      world-space lighting: term = t_d · l, linear in l) and, where there is a specular term,
      t_s(q) = Σ_j v_j T^α_j·(R) — `_term` with the tables of the identity lighting
      (`_identity_table`); the front-facing test folded in. ``cosine``: t_s from the cos θ_i-weighted
      visibility w (`cosine_visibility`) instead of v, as `shade`.

    Built once per view, pose and exponents (the first lighting-only frame after they changed):
    2·n²·K flops per point and term instead of 2·3·K, then reused by every lighting-only frame.
    """
    Q, dev, dt = nT.shape[1], v.device, v.dtype
    n = math.isqrt(v.shape[1])
    groups, mask, rest = planar_groups(nT) if planar and Q >= PLANAR_MIN_POINTS else ([], None, None)
    front = dot_T(nT, woT) > 0
    cache: dict = {"Q": Q, "vi": vi, "groups": [], "regions": [],
                   "counts": _plane_counts(groups, mask, region, vertex_normal, vertex_region)}
    counts = cache["counts"]
    cache["mask"] = mask   # (the first group's, when it holds most points: `ZHShadow._relight_planes`)
    for n0, pos in groups:
        if pos is None:
            cache["groups"].append((n0, None, None, b * (mask & front)[:, None]))
        else:
            cache["groups"].append((n0, pos, vi.index_select(0, pos), b.index_select(0, pos) * front[pos, None]))
    Wd = _identity_table(n, 1.0, True).to(dev, dt)

    def transfer(p: Tensor | None, Wd_: Tensor | None, Ws: Tensor | None) -> tuple[Tensor | None, Tensor | None]:
        m = Q if p is None else p.shape[0]
        td = torch.empty(v.shape[1], m, dtype=dt, device=dev) if Wd_ is not None else None
        ts = torch.empty(v.shape[1], m, dtype=dt, device=dev) if Ws is not None else None
        for a in range(0, m, chunk):
            s = slice(a, a + chunk)
            if p is None:
                vi_c, b_c, n_c, wo_c, f_c = vi[s], b[s], nT[:, s], woT[:, s], front[s]
            else:
                pc = p[s]
                vi_c, b_c = vi.index_select(0, pc), b.index_select(0, pc)
                n_c, wo_c, f_c = nT.index_select(1, pc), woT.index_select(1, pc), front.index_select(0, pc)
            vT = rows(interpolate(v, vi_c, b_c))
            if td is not None:
                torch.mul(_term(vT, n_c, Wd_, True), f_c, out=td[:, s])
            if ts is not None:
                wT = cosine_visibility(vT, n_c) if cosine else vT
                torch.mul(_term(wT, reflect_T(n_c, wo_c), Ws, False), f_c, out=ts[:, s])
        return td, ts

    single = len(alphas) == 1
    for r, al in enumerate(alphas):
        Ws = None if al is None else _identity_table(n, float(al), False).to(dev, dt)
        if not groups and single:
            p = None
        else:
            ids = rest if groups else torch.arange(Q, device=dev)
            p = ids if single else ids[region.index_select(0, ids) == r]
        entries = []
        if p is None or p.shape[0]:
            entries.append((p, *transfer(p, Wd, Ws)))
            if Ws is not None:
                counts["specular"] += Q if p is None else int(p.shape[0])
        if Ws is not None:
            for _, pos in groups:                                                  # the planes' specular term
                if pos is None:
                    pos = mask.nonzero().squeeze(-1)
                pg = pos if single else pos[region.index_select(0, pos) == r]
                if pg.shape[0]:
                    entries.append((pg, None, transfer(pg, None, Ws)[1]))
                    counts["specular"] += int(pg.shape[0])
                    counts["planar_specular"] += int(pg.shape[0])
        cache["regions"].append(entries)
    return cache


def relight_cache_bytes(cache: dict) -> int:
    """Bytes of the arrays a `relight_cache` holds (the vertex ids are the frame's, counted too)."""
    ts = [cache["vi"]] + [x for g in cache["groups"] for x in g[1:] if x is not None]
    ts += [x for entries in cache["regions"] for e in entries for x in e if x is not None]
    if cache.get("plane_pass") is not None:   # (`ZHShadow._relight_planes`: plane faces, object pixels, …)
        ts += [cache["plane_pass"][0]] + [x for pxs in cache["plane_pass"][1] for x in pxs] + \
            list(cache["plane_pass"][2:])   # (the plane faces' corner vertices and their regions)
    return sum(t.element_size() * t.nelement() for t in ts)


def relight(cache: dict, v: Tensor, Wd: Tensor, light: Tensor, vertex_region: Tensor,
            mats: list[tuple[Tensor, Tensor]]) -> Tensor:
    """(3, Q) radiance of a lighting-only frame from `relight_cache`: planes through their
    per-vertex diffuse factor (as `shade`), every other term t · (l ⊙ k) — one (3, n²) @ (n², Q_r)
    product per region and term.

    Args:
        v: (N, n²); Wd: `table`(light, 1, diffuse=True); light: (n², 3) world-space SH lighting;
        mats: per region (kd (3,), ks (3,)).
    """
    Q, dev, dt = cache["Q"], v.device, v.dtype
    out = None
    if cache["groups"]:
        kd_v = torch.stack([m[0] for m in mats]).to(dev, dt).index_select(0, vertex_region)
        for n0, pos, vi_g, b_g in cache["groups"]:
            u = (v @ diffuse_at(Wd, n0)) * kd_v
            if pos is None:
                out = rows(interpolate(u, cache["vi"], b_g))
            else:
                if out is None:
                    out = torch.zeros(3, Q, dtype=dt, device=dev)
                out.index_copy_(1, pos, interpolate(u, vi_g, b_g).T)
    if out is None:
        out = torch.empty(3, Q, dtype=dt, device=dev)
    light = light.to(dev, dt)
    for (kd, ks), entries in zip(mats, cache["regions"]):
        for p, td, ts in entries:
            rad = None
            if td is not None:
                rad = (light * kd.to(dev, dt)).T @ td                              # (3, Q_r)
            if ts is not None:
                sp = (light * ks.to(dev, dt)).T @ ts
                rad = sp if rad is None else rad + sp
            if p is None:
                out = rad
            elif td is None:
                out.index_add_(1, p, rad)
            else:
                out.index_copy_(1, p, rad)
    return out


def zyz_axes(nT: Tensor) -> tuple[list[Tensor], list[Tensor]]:
    """The components of e1, e2 (3 × (Q,) each) of the ZYZ frame (e1, e2, n) = R_n = R_z(φ) R_y(θ)
    of unit normals nT (3, Q) — the frame `zonal_conjugate` rotates through (e1 = (cos θ cos φ,
    cos θ sin φ, −sin θ), e2 = (−sin φ, cos φ, 0); φ = 0 on the pole, as `_zyz_angles`)."""
    z, rho, cp, sp = _polar(nT)
    return [z * cp, z * sp, -rho], [-sp, cp, torch.zeros_like(cp)]


@fused
def _vertex_sh(pT: Tensor, nT: Tensor, lam: tuple, lobes: int, order: int, dim: int, zyz: bool = False,
               perm: tuple | None = None) -> Tensor:
    """(n², Q) (``dim`` 0) or (Q, n²) (``dim`` 1) world-space SH visibility of Q vertices from their lobe parameters pT (c·(2+n), Q)
    ([X, Y, k_0..k_{n−1}] per lobe, `precompute.lobes_to_params`) and unit normals nT (3, Q), in
    the point-minor layout (every op a vector over the points): the chart → local axis
    (`precompute.chart_to_axis`), local → world through the frame (s, t, n) (`methods.core.frames`),
    y(axis) (`methods.core.sh.sh_eval`: a polynomial in the axis) scaled by Λ_l k_l (``lam`` the
    Λ_l) and summed over the lobes (eq. 1), unrolled; one compiled pass (`methods.core.fused`).
    ``zyz``: the SH in the ZYZ frame (e1, e2, n) of each normal (`zyz_axes`) instead of world space
    — the world axis's coordinates along e1, e2, n, i.e. M(R_n)ᵀ v (`cosine_visibility_zyz`).
    ``perm`` (n² ints): result row i is coefficient perm[i] (the order the next product reads its
    rows in, `world_visibility`'s ``rows``) — a free reordering of the stacked rows."""
    per = 2 + order
    s, t = _coordinate_components(nT[0], nT[1], nT[2])
    if zyz:
        e1, e2 = zyz_axes(nT)
    out = None
    for c in range(lobes):
        q = pT[c * per:(c + 1) * per]
        X, Y = q[0], q[1]                                                       # `chart_to_axis`
        r2 = X * X + Y * Y
        scale = torch.where(r2 > CHART_RMAX ** 2, CHART_RMAX / r2.clamp_min(1e-30).sqrt(), torch.ones_like(r2))
        X, Y = X * scale, Y * scale
        r2 = X * X + Y * Y
        z = 1.0 - 0.5 * r2
        f = (1.0 - 0.25 * r2).clamp_min(0.0).sqrt()
        ax = (f * X, f * Y, z)                                                  # local axis
        aw = [s[i] * ax[0] + t[i] * ax[1] + nT[i] * ax[2] for i in range(3)]    # world axis
        if zyz:                                                                 # → the frame (e1, e2, n)
            aw = [e[0] * aw[0] + e[1] * aw[1] + e[2] * aw[2] for e in (e1, e2, [nT[0], nT[1], nT[2]])]
        Yl = sh_terms(aw[0], aw[1], aw[2], order)                               # n² × (Q,)
        terms = [Yl[i] * (q[2 + l] * lam[l]) for l in range(order) for i in range(l * l, (l + 1) ** 2)]
        out = terms if out is None else [o + u for o, u in zip(out, terms)]
    if perm is not None:
        out = [out[i] for i in perm]
    return torch.stack(out, dim)


@functools.lru_cache(maxsize=None)
def _band_norms(order: int) -> tuple[float, ...]:
    """Λ_l (`methods.core.zh.band_norms`) as the Python floats `_vertex_sh` takes, once per order
    (0.2 ms a call otherwise, every pose)."""
    return tuple(band_norms(order).tolist())


@fused
def _pose_product(a: Tensor, Xf: Tensor) -> Tensor:
    """Σ_j a_j Xf_j (M,) of a (J1,) and Xf (J1, M) (contiguous rows): [pose, 1] · X. Compiled, every
    output's J1 terms are summed in the same order at any thread count, the outputs split over the
    threads (eagerly, torch's dim-0 sum does the same, through a (J1, M) temporary)."""
    return (a[:, None] * Xf).sum(0)


def world_visibility(X: Tensor, pose: Tensor, normal: Tensor, lobes: int, *, point_minor: bool = False,
                     frame: str = "world", rows: Tensor | None = None, cols: Tensor | None = None) -> Tensor:
    """(N, n²) world-space SH visibility of every vertex at one pose — (n², N) with
    ``point_minor`` — : §4.3 step 1 (the linear model [pose, 1] · X, one matrix-vector product: the
    frame's compulsory read of X), then per vertex the lobe axes from their chart
    (`precompute.chart_to_axis`) taken to world space through the vertex frame (s, t, n)
    (`methods.core.frames.coordinate_system`, the frame the visibility was fitted in) and eq. 1
    (y(s) by the SH polynomials, `methods.core.sh.sh_terms`), in one compiled pass over all the
    vertices (`_vertex_sh`, the vertex count symbolic). The same numbers as `ZHModel.lobes_at` + `frame_matrix` +
    `zh_lobes_to_sh` (the reference path) to round-off.

    Args:
        X: (J+1, N, c·(2+n)) linear model; pose: (J,) joint angles; normal: (N, 3) unit posed normals.
        frame: "world", or "zyz": each vertex's SH in the ZYZ frame of its normal (`zyz_axes`),
            the input of `cosine_visibility_zyz`.
        rows: (n²,) int64 or None: the coefficients in this order (result row / column i is
            coefficient rows[i]) — `zyz_rows`, the order `cosine_visibility_zyz(ordered=True)`
            reads them in, made by the compiled pass itself instead of a gather of the result.
        cols: (N',) int64 or None: those vertices alone (result column / row j is vertex cols[j]):
            the product over every vertex (X streamed once), then its columns and the normals
            gathered — c·(2+n) + 3 floats per vertex instead of the result's n² — and eq. 1 for
            them alone (a P frame's front-facing vertices, `ZHShadow._front_radiance`). The same
            numbers as those columns of the whole (each vertex's are its own).
    """
    if frame not in ("world", "zyz"):
        raise ValueError(f"frame must be 'world' or 'zyz', got {frame!r}")
    J1, N, d = X.shape
    per = d // lobes
    n = per - 2
    a = torch.cat([pose.to(X.dtype).reshape(-1), torch.ones(1, dtype=X.dtype, device=X.device)])
    if a.shape[0] != J1:
        raise ValueError(f"pose has {a.shape[0] - 1} joints, the model {J1 - 1}")
    # [pose, 1] · X as a compiled reduction over the J1 rows (`_pose_product`): each output sums its
    # J1 terms in one fixed order whatever the thread count (a one-row MKL product splits that
    # reduction over the threads on AVX-512 machines: methods.core.threads), so it runs on every
    # thread instead of switching torch to one — after such a switch the next parallel work paid
    # for it: a bench creature P frame (order 8, per vertex) at 2 threads, quiet, 1.42-1.54x wall
    # without the switch (session 24). It reads X once and is bandwidth-bound. With X laid out
    # (J+1, d, N) in memory (`point_minor_model`) it writes the point-minor pT (d, N) itself.
    point_major = not X.transpose(1, 2).is_contiguous()
    Xf = X.reshape(J1, N * d) if point_major else X.transpose(1, 2).reshape(J1, d * N)
    torch._dynamo.maybe_mark_dynamic(Xf, 1)              # one kernel for every model size
    pT = _pose_product(a, Xf)
    pT = pT.view(N, d).T.contiguous() if point_major else pT.view(d, N)
    nT = normal.T.contiguous()
    if cols is not None:
        pT, nT = pT.index_select(1, cols), nT.index_select(1, cols)
        N = int(cols.shape[0])
    lam = _band_norms(n)
    perm = None if rows is None else tuple(int(i) for i in rows.tolist())
    if perm is not None and sorted(perm) != list(range(n * n)):
        raise ValueError(f"rows must be a permutation of the {n * n} coefficients")
    # one compiled call over all N vertices, the vertex count marked dynamic (one kernel for every
    # count, as `_zyz_half`): no padded static blocks, no per-block copies of the result into place
    # (7 calls over blocks of 2,048 and their copies: 5.4 → 2.4 ms for the stage at 13.4 K vertices,
    # order 8, 1 thread, load ~7 on 2 cores)
    fn = _vertex_sh if N >= VERTEX_COMPILE_MIN else _vertex_sh.eager
    torch._dynamo.maybe_mark_dynamic(pT, 1)
    torch._dynamo.maybe_mark_dynamic(nT, 1)
    return fn(pT, nT, lam, lobes, n, 0 if point_minor else 1, frame == "zyz", perm)


def point_minor_model(X: Tensor) -> Tensor:
    """X (J+1, N, d) with its memory laid out (J+1, d, N) — the same values, the layout
    `world_visibility` reads without a copy (its product then writes the point-minor parameters
    directly); X itself if it already is."""
    return X if X.transpose(1, 2).is_contiguous() else X.transpose(1, 2).contiguous().transpose(1, 2)


# -- the lighting's rotation (L / VL / VBL frames rotate the env map; E projects a new one) -----------

def _axis_rotation(axis: int, t: float) -> "np.ndarray":
    c, s = math.cos(t), math.sin(t)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = np.eye(3)
    R[i, i] = R[j, j] = c
    R[j, i], R[i, j] = s, -s
    return R


@functools.lru_cache(maxsize=16)
def _lighting_zyz_tables(order: int) -> tuple:
    """The constants of `rotate_lighting` at SH order n, float64 numpy: |m| per flat index (n²,),
    the index of (l, −m) (n²,), the sign of the sin term of a z rotation (n²,) (read off
    `sh_rotation_matrix` of one z rotation: its (i, (l, −m)) entry over sin(|m|θ)), and
    X₋ = M(Rx(−π/2)), X₊ = M(Rx(π/2)) (n², n²), so that M(Ry(β)) = X₋ M(Rz(β)) X₊."""
    from methods.core.sh_rotation import sh_rotation_matrix

    lm = [(l, m) for l in range(order) for m in range(-l, l + 1)]
    mabs = np.array([abs(m) for _, m in lm], dtype=np.float64)
    perm = np.array([l * l + l - m for l, m in lm])
    t0 = 0.3
    Mz = sh_rotation_matrix(torch.from_numpy(_axis_rotation(2, t0)), order).numpy()
    sgn = np.array([Mz[i, perm[i]] / math.sin(mabs[i] * t0) if mabs[i] else 0.0 for i in range(len(lm))])
    sgn = np.round(sgn)
    Xm = sh_rotation_matrix(torch.from_numpy(_axis_rotation(0, -math.pi / 2)), order).numpy()
    Xp = np.ascontiguousarray(Xm.T)   # (orthogonal)
    return mabs, perm, sgn, Xm, Xp


@functools.lru_cache(maxsize=16)
def _lighting_zyz_tensors(order: int) -> tuple:
    """`_lighting_zyz_tables`(order) as contiguous CPU tensors (perm int64) for `native.rotate_zyz`."""
    mabs, perm, sgn, Xm, Xp = _lighting_zyz_tables(order)
    return tuple(torch.from_numpy(np.ascontiguousarray(x, dtype=np.int64 if i == 1 else np.float64))
                 for i, x in enumerate((mabs, perm, sgn, Xm, Xp)))


# `rotate_lighting`'s steps by one C call (`native.rotate_zyz`, zh38v: float64 round-off against the numpy
# steps) where it runs; False: the numpy steps (the tests' oracle)
NATIVE_ROTATE = True

# `rotate_lighting` takes R as a rotation when |R Rᵀ − I| ≤ this (float32 round-off of a composed one)
ROTATION_TOL = 1e-7


def rotate_lighting(c: Tensor, R: Tensor) -> Tensor:
    """`methods.core.sh.rotate_sampled(c, R)` (= `sh_rotation.rotate_coeffs`: the coefficients of
    f'(d) = f(Rᵀ d)) for the (n², C) float64 SH lighting and one rotation R (3, 3), as M(R) =
    M(Rz(a)) M(Ry(b)) M(Rz(g)) (R's ZYZ angles) with M(Ry(b)) = X₋ M(Rz(b)) X₊
    (`_lighting_zyz_tables`): three z rotations (cos / sin of |m|·angle per coefficient) and two
    fixed (n², n²) products, in numpy float64 — the same coefficients to float64 round-off (1e-14),
    in ~20 small numpy calls instead of the compiled call's guards and wrappers. After the suite's
    idle (`PRTBENCH_SETTLE`), 1 thread, alternating: order 8 0.67 → 0.40 ms, order 4 0.58 → 0.46 ms
    (of a 2.6–2.9 ms lighting-only frame). The scenes' ``to_world`` are rotations to float32
    round-off only (composed: |R Rᵀ − I| up to 6e-8 on the bench L sequence), and each of the three
    ways rotates a slightly non-orthonormal R differently (this one: the proper rotation with R's
    third column and the z rotation left over); they agree to ~l·|R Rᵀ − I| relative, float32
    round-off — R not a rotation to `ROTATION_TOL` (|R Rᵀ − I|, det), or c not float64 on the
    CPU: `rotate_sampled`."""
    if NATIVE_ROTATE and c.dim() == 2 and c.shape[0] <= 256:   # (the test, the angles and the steps in C: `native.rotate_lighting`)
        out = zn.rotate_lighting(c, R, ROTATION_TOL, _lighting_zyz_tensors(math.isqrt(c.shape[0])))
        if out is not None:
            return out
    r = R.tolist() if R.dim() == 2 and R.shape == (3, 3) else None
    ok = r is not None and c.device.type == "cpu" and c.dtype == torch.float64
    if ok:
        (r00, r01, r02), (r10, r11, r12), (r20, r21, r22) = r
        det = r00 * (r11 * r22 - r12 * r21) - r01 * (r10 * r22 - r12 * r20) + r02 * (r10 * r21 - r11 * r20)
        ok = det > 0 and max(abs(sum(r[i][k] * r[j][k] for k in range(3)) - (i == j))
                             for i in range(3) for j in range(i, 3)) <= ROTATION_TOL
    if not ok:
        from methods.core.sh import rotate_sampled

        return rotate_sampled(c, R)
    mabs, perm, sgn, Xm, Xp = _lighting_zyz_tables(math.isqrt(c.shape[0]))
    # R = Rz(a) Ry(b) Rz(g): a, b from R's third column (R e_z = (cos a sin b, sin a sin b, cos b)),
    # g from the z rotation left, T = (Rz(a) Ry(b))ᵀ R (its first column) — stable where sin b → 0
    # (a is then arbitrary and g takes up the rest)
    s = math.hypot(r02, r12)
    a = math.atan2(r12, r02) if s > 0 else 0.0
    b = math.atan2(s, r22)
    ca, sa, cb, sb = math.cos(a), math.sin(a), math.cos(b), math.sin(b)
    u0, u1 = ca * r00 + sa * r10, -sa * r00 + ca * r10
    g = math.atan2(u1, cb * u0 - sb * r20)
    A = np.multiply.outer(np.array([g, b, a]), mabs)
    C, S = np.cos(A)[..., None], (np.sin(A) * sgn)[..., None]
    x = c.numpy()
    x = C[0] * x + S[0] * x[perm]
    x = Xp @ x
    x = C[1] * x + S[1] * x[perm]
    x = Xm @ x
    x = C[2] * x + S[2] * x[perm]
    return torch.from_numpy(x)
