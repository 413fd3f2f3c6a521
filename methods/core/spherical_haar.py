"""Spherical triangular Haar wavelets on an icosahedral geodesic sphere and their tripling
coefficients (Ma, Hsiao, Lee, Chuang, Chen 2006 §3.1; the triple product of Ng, Ramamoorthi,
Hanrahan 2004). The method card is ``shared/methods/triple_product.md``.

Geodesic sphere
---------------
Level 0 is the icosahedron (20 triangles, outward counter-clockwise). Every level splits each
triangle (p0, p1, p2) at its geodesic edge midpoints m01, m12, m20 (normalised chord midpoints)
into four children, stored at indices 4i .. 4i+3 of the next level in the order

    4i+0 = a = centre  (m01, m12, m20)
    4i+1 = b = corner at p0 (p0, m01, m20)
    4i+2 = c = corner at p1 (m01, p1, m12)
    4i+3 = d = corner at p2 (m20, m12, p2)

Level L has 20·4^L triangles; the paper's 5120 directions are level 4.

Basis (Ma 2006 §3.1) — *equal-area measure*
---------------------------------------------
Areas are taken equal by construction: A_0 = 1 per level-0 triangle, A_l = 4^−l. In this measure
(total area 20) the basis {φ_i^0} ∪ {ψ_{i,t}^l : l < L, t = 0,1,2} with

    ψ_{i,0} = φa + φb − φc − φd,  ψ_{i,1} = φa − φb + φc − φd,  ψ_{i,2} = φa − φb − φc + φd

(a..d = children 4i..4i+3 of T_i^l at level l+1) is orthogonal, not normalised: ∫φ^0 φ^0 = A_0,
∫ψ^l ψ^l = A_l. Coefficients are ⟨f, Ψ⟩ / ⟨Ψ, Ψ⟩.

Coefficient layout of a vector (..., K), K = 20·4^L, coarse to fine:
    [0, 20)                          level-0 scaling coefficients φ_i^0
    [20·4^l, 20·4^(l+1)) for l<L      wavelets of level l: index 20·4^l + 3i + t
(so the wavelet block of level l starts at 20 + 20(4^l − 1) = 20·4^l). "Top-only" truncation keeps
a prefix of this vector.

Real solid angles
-----------------
The fine triangles' real solid angles Ω_t are not equal (max/min ≈ 1.3 at level 3). The transform
and the tripling coefficients live in the equal-area measure (that is what makes the basis
orthogonal). To get real integrals ∫ f g h dω ≈ Σ_t Ω_t f_t g_t h_t, fold the density Ω_t/A_L into
exactly ONE factor before projecting (``project(..., solid_angle_weight=True)`` or
`Geodesic.density`), e.g. into the BRDF·cosine table ρ̃ of Ma 2006 eq. 7. Without it, Σ C L V ρ is
the equal-area integral.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Callable

import torch
from torch import Tensor

from methods.core.cubemap import keep_largest, keep_largest_dense  # noqa: F401  (re-exported)

__all__ = [
    "Geodesic",
    "icosahedron",
    "forward",
    "inverse",
    "scaling_pyramid",
    "triple_integral",
    "triple_integral_sparse",
    "product_project",
    "tripling_coefficients",
    "basis_matrix",
    "support_areas",
    "basis_norms",
    "coefficient_levels",
    "n_triangles",
    "keep_largest",
    "keep_largest_dense",
    "keep_top",
    "keep_top_dense",
]

# 2-D Haar sign pattern S[t, p]: value of ψ_t on child p = (a, b, c, d) (Ma 2006 §3.1)
_SIGNS = ((1, 1, -1, -1), (1, -1, 1, -1), (1, -1, -1, 1))


def _signs(dtype, device) -> Tensor:
    return torch.tensor(_SIGNS, dtype=dtype, device=device)  # (3, 4)


def n_triangles(level: int) -> int:
    return 20 * 4 ** level


def _check_level(level: int) -> int:
    if int(level) != level or level < 0:
        raise ValueError(f"level must be a non-negative integer, got {level}")
    return int(level)


def level_of_size(K: int) -> int:
    """Level L of a coefficient vector of length K = 20·4^L (ValueError otherwise)."""
    L = 0
    while n_triangles(L) < K:
        L += 1
    if n_triangles(L) != K:
        raise ValueError(f"coefficient count {K} is not 20·4^L")
    return L


def icosahedron(dtype=torch.float64) -> tuple[Tensor, Tensor]:
    """Unit icosahedron: vertices (12, 3), faces (20, 3) int64, outward counter-clockwise."""
    p = (1.0 + math.sqrt(5.0)) / 2.0
    V = torch.tensor([[-1, p, 0], [1, p, 0], [-1, -p, 0], [1, -p, 0],
                      [0, -1, p], [0, 1, p], [0, -1, -p], [0, 1, -p],
                      [p, 0, -1], [p, 0, 1], [-p, 0, -1], [-p, 0, 1]], dtype=torch.float64)
    V = V / V.norm(dim=-1, keepdim=True)
    F = torch.tensor([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
                      [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
                      [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
                      [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], dtype=torch.int64)
    return V.to(dtype), F


def _subdivide(T: Tensor) -> Tensor:
    """(n, 3, 3) spherical triangles → (4n, 3, 3) children in the order a, b, c, d."""
    p0, p1, p2 = T[:, 0], T[:, 1], T[:, 2]

    def mid(x, y):
        m = x + y
        return m / m.norm(dim=-1, keepdim=True)

    m01, m12, m20 = mid(p0, p1), mid(p1, p2), mid(p2, p0)
    a = torch.stack([m01, m12, m20], 1)
    b = torch.stack([p0, m01, m20], 1)
    c = torch.stack([m01, p1, m12], 1)
    d = torch.stack([m20, m12, p2], 1)
    return torch.stack([a, b, c, d], 1).reshape(-1, 3, 3)


def _spherical_triangle_area(T: Tensor) -> Tensor:
    # Van Oosterom & Strackee 1983: tan(Ω/2) = |a·(b×c)| / (1 + a·b + b·c + c·a)
    a, b, c = T[:, 0], T[:, 1], T[:, 2]
    num = (a * torch.cross(b, c, dim=-1)).sum(-1).abs()
    den = 1.0 + (a * b).sum(-1) + (b * c).sum(-1) + (c * a).sum(-1)
    return 2.0 * torch.atan2(num, den)


class Geodesic:
    """The geodesic subdivision up to `level` (geometry only; transforms are free functions).

    Attributes (float64, CPU):
        level: L.
        triangles[l]: (20·4^l, 3, 3) vertex directions of level-l triangles, l = 0..L.
    """

    def __init__(self, level: int):
        self.level = _check_level(level)
        V, F = icosahedron()
        T = [V[F]]
        for _ in range(self.level):
            T.append(_subdivide(T[-1]))
        self.triangles = T

    @property
    def n(self) -> int:
        """Number of fine triangles = number of coefficients, 20·4^L."""
        return n_triangles(self.level)

    def centres(self, level: int | None = None, *, dtype=torch.float32) -> Tensor:
        """(20·4^l, 3) unit directions of the triangles' (normalised) vertex centroids."""
        T = self.triangles[self.level if level is None else level]
        c = T.mean(1)
        return (c / c.norm(dim=-1, keepdim=True)).to(dtype)

    def solid_angles(self, level: int | None = None, *, dtype=torch.float32) -> Tensor:
        """(20·4^l,) real solid angles of the level's spherical triangles (sum 4π)."""
        return _spherical_triangle_area(self.triangles[self.level if level is None else level]).to(dtype)

    def density(self, *, dtype=torch.float32) -> Tensor:
        """(20·4^L,) Ω_t / A_L: multiply ONE factor's fine values by it to turn equal-area
        integrals into real solid-angle integrals (see module docstring)."""
        return (self.solid_angles(dtype=torch.float64) * 4.0 ** self.level).to(dtype)

    def locate(self, d: Tensor) -> Tensor:
        """Index of the level-L triangle containing each direction.

        Args:
            d: (..., 3) directions (need not be unit).
        Returns:
            (...,) int64 fine-triangle indices (boundary points go to one of the neighbours).
        """
        d = torch.as_tensor(d)
        if d.shape[-1] != 3:
            raise ValueError(f"directions must be (..., 3), got {tuple(d.shape)}")
        shp = d.shape[:-1]
        x = d.reshape(-1, 3).to(torch.float64)

        def inside_score(T: Tensor, x: Tensor) -> Tensor:
            # min over edges of the signed volume x·(vi × vj) (>= 0 inside a CCW triangle)
            e = [torch.cross(T[..., i, :], T[..., (i + 1) % 3, :], dim=-1) for i in range(3)]
            return torch.stack([(x.unsqueeze(-2) * ei).sum(-1) for ei in e], -1).amin(-1)

        idx = inside_score(self.triangles[0].unsqueeze(0), x).argmax(-1)  # (R,)
        for l in range(1, self.level + 1):
            cand = idx.unsqueeze(-1) * 4 + torch.arange(4)  # (R, 4)
            sc = inside_score(self.triangles[l][cand], x)
            idx = cand.gather(-1, sc.argmax(-1, keepdim=True)).squeeze(-1)
        return idx.reshape(shp)

    def subsamples(self, supersample: int) -> tuple[Tensor, Tensor]:
        """The sample points of `project`: c (n·4^s, 3) float64 unit centres of the 4^s
        sub-triangles of every fine triangle (fine triangle-major), w (n, 4^s) their solid angles."""
        T = self.triangles[-1]
        for _ in range(_check_level(supersample)):
            T = _subdivide(T)
        c = T.mean(1)
        return c / c.norm(dim=-1, keepdim=True), _spherical_triangle_area(T).reshape(self.n, 4 ** supersample)

    def project(self, fn: Callable[[Tensor], Tensor], *, supersample: int = 2,
                solid_angle_weight: bool = False, dtype=torch.float32) -> Tensor:
        """Wavelet coefficients of a spherical function.

        Each fine triangle gets the mean of ``fn`` over it, estimated from the centres of its
        4^supersample sub-triangles weighted by their real solid angles; then `forward`.

        Args:
            fn: callable (P, 3) unit directions → (P,) or (P, C).
            solid_angle_weight: multiply the fine values by `density` (do this for exactly one
                factor of a triple product to get real solid-angle integrals).
        Returns:
            (K,) or (C, K) coefficients, K = 20·4^L (channels first, transform on the last dim).
        """
        s = _check_level(supersample)
        c, w = self.subsamples(s)
        vals = torch.as_tensor(fn(c.to(dtype))).to(torch.float64)
        chan = vals.ndim == 2
        vals = vals.reshape(self.n, 4 ** s, -1)
        fine = (vals * w[..., None]).sum(1) / w.sum(1)[:, None]  # (n, C)
        if solid_angle_weight:
            fine = fine * self.density(dtype=torch.float64)[:, None]
        out = forward(fine.T.contiguous()).to(dtype)
        return out if chan else out[0]


# -- transforms ----------------------------------------------------------------------------------


def forward(f_fine: Tensor) -> Tensor:
    """Fine piecewise-constant values → wavelet coefficients (the layout of the module doc).

    Args:
        f_fine: (..., 20·4^L) values on the level-L triangles (coefficients of φ^L).
    Returns:
        (..., 20·4^L) coefficients; exact inverse `inverse`.
    """
    f_fine = torch.as_tensor(f_fine)
    L = level_of_size(f_fine.shape[-1])
    S = _signs(f_fine.dtype, f_fine.device)
    s = f_fine
    blocks = []
    for l in range(L - 1, -1, -1):
        ch = s.reshape(*s.shape[:-1], n_triangles(l), 4)  # children a, b, c, d
        w = ch @ S.T * 0.25  # (..., n_l, 3): ⟨f,ψ⟩/⟨ψ,ψ⟩ = (±a ± b ± c ± d)/4
        s = ch.mean(-1)  # scaling coefficient of φ^l = average of its children
        blocks.append(w.reshape(*w.shape[:-2], -1))
    return torch.cat([s] + blocks[::-1], -1)


def forward_butterfly(f_fine: Tensor) -> Tensor:
    """`forward` with the sign matrix unrolled into sums and differences of the four children
    (a + b ± (c + d), a − b ± (c − d), then × 1/4): the same coefficients to float32 round-off, as
    element-wise passes that a compiled caller fuses (`triple_product.lighting.project_env`; the
    eager `forward` is a (n, 4) @ (4, 3) product and a mean per level)."""
    L = level_of_size(f_fine.shape[-1])
    s = f_fine
    blocks = []
    for l in range(L - 1, -1, -1):
        a, b, c, d = s.unflatten(-1, (n_triangles(l), 4)).unbind(-1)       # children a, b, c, d
        p, q, r, t = a + b, c + d, a - b, c - d
        # rows of `_SIGNS`: (a + b − c − d), (a − b + c − d), (a − b − c + d)
        blocks.append(torch.stack(((p - q) * 0.25, (r + t) * 0.25, (r - t) * 0.25), -1).flatten(-2))
        s = (p + q) * 0.25
    return torch.cat([s] + blocks[::-1], -1)


def scaling_pyramid(coeffs: Tensor) -> list[Tensor]:
    """Scaling coefficients (= averages over each triangle) of every level 0..L.

    Args:
        coeffs: (..., 20·4^L).
    Returns:
        list of L+1 tensors (..., 20·4^l); the last one equals `inverse(coeffs)`.
    """
    coeffs = torch.as_tensor(coeffs)
    L = level_of_size(coeffs.shape[-1])
    S = _signs(coeffs.dtype, coeffs.device)
    s = coeffs[..., :20]
    out = [s]
    for l in range(L):
        lo = n_triangles(l)
        w = coeffs[..., lo:4 * lo].reshape(*coeffs.shape[:-1], lo, 3)
        s = (s.unsqueeze(-1) + w @ S).reshape(*coeffs.shape[:-1], 4 * lo)  # child = s + Σ_t S[t,p] w_t
        out.append(s)
    return out


def inverse(coeffs: Tensor) -> Tensor:
    """Wavelet coefficients (..., 20·4^L) → fine values (..., 20·4^L)."""
    return scaling_pyramid(coeffs)[-1]


def coefficient_levels(level: int, *, device=None) -> Tensor:
    """(K,) int64: −1 for level-0 scaling functions, l for wavelets of level l."""
    L = _check_level(level)
    parts = [torch.full((20,), -1, dtype=torch.int64, device=device)]
    for l in range(L):
        parts.append(torch.full((3 * n_triangles(l),), l, dtype=torch.int64, device=device))
    return torch.cat(parts)


def support_areas(level: int, *, dtype=torch.float32, device=None) -> Tensor:
    """(K,) equal-measure support area of each basis function: 1 for φ^0, A_l = 4^−l for ψ^l
    (the weights of "area-weighted" selection, Ma 2006 §4 / Ng 2003)."""
    lv = coefficient_levels(level, device=device).clamp_min(0)
    return (0.25 ** lv.to(torch.float64)).to(dtype)


def basis_norms(level: int, *, dtype=torch.float32, device=None) -> Tensor:
    """(K,) ⟨Ψ, Ψ⟩ in the equal-area measure (= `support_areas`)."""
    return support_areas(level, dtype=dtype, device=device)


def basis_matrix(level: int, *, dtype=torch.float64) -> Tensor:
    """(K, K) values of every basis function (rows) on every fine triangle (columns)."""
    K = n_triangles(level)
    eye = torch.eye(K, dtype=dtype)
    # Ψ_k as fine values = inverse of the unit coefficient vector e_k
    return inverse(eye)


# -- truncation ------------------------------------------------------------------------------------


def keep_top(coeffs: Tensor, n: int) -> tuple[Tensor, Tensor]:
    """"Top-only" (coarsest-first) selection: the first n coefficients of the layout.

    Returns indices (..., n) int64 and values (..., n)."""
    K = coeffs.shape[-1]
    n = min(int(n), K)
    idx = torch.arange(n, device=coeffs.device).expand(*coeffs.shape[:-1], n)
    return idx, coeffs[..., :n]


def keep_top_dense(coeffs: Tensor, n: int) -> Tensor:
    """`keep_top` as a dense (..., K) vector."""
    out = torch.zeros_like(coeffs)
    out[..., :n] = coeffs[..., :n]
    return out


# -- triple products ---------------------------------------------------------------------------------


def _wavelets(c: Tensor, l: int) -> Tensor:
    lo = n_triangles(l)
    return c[..., lo:4 * lo].reshape(*c.shape[:-1], lo, 3)


def triple_integral(f: Tensor, g: Tensor, h: Tensor) -> Tensor:
    """∫ f g h = Σ_ijk C_ijk f_i g_j h_k in the equal-area measure, O(K) per row (the
    parent-summation form of the three tripling rules, Ng 2004 §5 / Ma 2006 §3.1):

        A_0 Σ_i f⁰_i g⁰_i h⁰_i                                              (rule 1)
      + Σ_{l,i} A_l Σ_{σ ∈ perm(0,1,2)} f_{i,σ0} g_{i,σ1} h_{i,σ2}           (rule 2)
      + Σ_{l,i,t} A_l (f_{i,t} g_{i,t} s^h_{i,l} + f_{i,t} h_{i,t} s^g_{i,l}
                       + g_{i,t} h_{i,t} s^f_{i,l})                           (rule 3)

    where s^h_{i,l} = Σ over h's basis functions coarser than level l of coef·sign on T_i^l,
    i.e. h's level-l scaling coefficient (its average over T_i^l, `scaling_pyramid`).

    Args:
        f, g, h: (..., K) coefficient vectors, broadcastable against each other.
    Returns:
        (...,) integrals.
    """
    f, g, h = torch.broadcast_tensors(torch.as_tensor(f), torch.as_tensor(g), torch.as_tensor(h))
    L = level_of_size(f.shape[-1])
    pf, pg, ph = scaling_pyramid(f), scaling_pyramid(g), scaling_pyramid(h)
    out = (f[..., :20] * g[..., :20] * h[..., :20]).sum(-1)  # rule 1, A_0 = 1
    perms = ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))
    for l in range(L):
        A = 0.25 ** l
        wf, wg, wh = _wavelets(f, l), _wavelets(g, l), _wavelets(h, l)  # (..., n_l, 3)
        r2 = sum(wf[..., a] * wg[..., b] * wh[..., c] for a, b, c in perms)
        r3 = ((wf * wg).sum(-1) * ph[l] + (wf * wh).sum(-1) * pg[l] + (wg * wh).sum(-1) * pf[l])
        out = out + A * (r2 + r3).sum(-1)
    return out


def _decode(idx: Tensor, L: int):
    """Global coefficient index → (level l (−1 = scaling), node i, type t)."""
    lvl = torch.full_like(idx, -1)
    for l in range(L):  # the wavelet block of level l starts at 20·4^l
        lvl = torch.where(idx >= 20 * 4 ** l, torch.full_like(idx, l), lvl)
    r = idx - 20 * (4 ** lvl.clamp_min(0))
    node = torch.where(lvl < 0, idx, r // 3)
    t = torch.where(lvl < 0, torch.zeros_like(idx), r % 3)
    return lvl, node, t


def _ancestors(lvl: Tensor, node: Tensor, L: int, dtype) -> tuple[Tensor, Tensor]:
    """All basis functions strictly coarser than level `lvl` whose support contains T_node^lvl.

    Args: lvl, node (..., m) (lvl >= 0 where used).
    Returns: idx (..., m, 1 + 3L) global coefficient indices (0 where unused) and sign (..., m,
    1 + 3L), the function's value on T_node^lvl (0 where unused): a function's average over
    T_node^lvl is Σ coeff[idx] · sign (its level-lvl scaling coefficient).
    """
    S = _signs(dtype, node.device)  # (3, 4)
    lv = lvl.clamp_min(0)
    idx = [node >> (2 * lv)]  # level-0 scaling function of the root triangle
    sgn = [torch.ones(node.shape, dtype=dtype, device=node.device)]
    for lp in range(L):
        valid = lvl > lp
        sh = (2 * (lv - lp)).clamp_min(0)
        anc = node >> sh
        pos = (node >> (sh - 2).clamp_min(0)) & 3  # child position at level lp+1
        for t in range(3):
            idx.append(torch.where(valid, 20 * 4 ** lp + 3 * anc + t, torch.zeros_like(anc)))
            sgn.append(torch.where(valid, S[t][pos], torch.zeros((), dtype=dtype, device=node.device)))
    return torch.stack(idx, -1), torch.stack(sgn, -1)


@lru_cache(maxsize=16)
def coefficient_structure(L: int):
    """Per-coefficient tables for level L (CPU, cached): level (K,) (−1 = scaling), type (K,),
    ancestor indices (K, 1+3L) and their signs (K, 1+3L) (see `_ancestors`; all-zero rows for
    scaling functions, which have no coarser ancestors)."""
    idx = torch.arange(n_triangles(L))
    lvl, node, t = _decode(idx, L)
    anc_i, anc_s = _ancestors(lvl, node, L, torch.float64)
    anc_s = torch.where((lvl >= 0)[:, None], anc_s, torch.zeros_like(anc_s))
    return lvl, t, anc_i, anc_s


def _avg(dense: Tensor, anc_idx: Tensor, anc_sign: Tensor) -> Tensor:
    """dense (B, K); anc_idx/sign (B, m, P) → (B, m) averages Σ dense[idx]·sign."""
    B, m, P = anc_idx.shape
    return (dense.gather(-1, anc_idx.reshape(B, m * P)).reshape(B, m, P) * anc_sign).sum(-1)


def triple_integral_sparse(a_idx: Tensor, a_val: Tensor, b_idx: Tensor, b_val: Tensor, c: Tensor, *,
                           chunk_elems: int = 1 << 22) -> Tensor:
    """Σ C_ijk a_i b_j c_k for two sparse (truncated) functions and one dense one — Ma 2006 eq. 7
    B = Σ C L V ρ with V and ρ truncated (per vertex / per BRDF slice) and L dense.

    Only tripling coefficients touching a's and b's non-zeros are visited (the three rules; the
    coarser function of rule 3 enters through its average over the wavelets' support, gathered from
    its 1 + 3L ancestors): O(n·L) gathers per row. a and b are scattered into dense row buffers
    (chunks of ≈ `chunk_elems` elements) so every lookup is a gather.

    Args:
        a_idx, a_val: (B, n) coefficient indices (distinct within a row) and values of function a.
        b_idx, b_val: (B, m) the same for b.
        c: (B, K) or (K,) dense coefficients of the third function.
    Returns:
        (B,) integrals (equal-area measure; see the module docstring for real solid angles).
    """
    a_idx, b_idx = torch.as_tensor(a_idx).long(), torch.as_tensor(b_idx).long()
    a_val, b_val, c = torch.as_tensor(a_val), torch.as_tensor(b_val), torch.as_tensor(c)
    if a_idx.ndim != 2 or a_idx.shape != a_val.shape or b_idx.ndim != 2 or b_idx.shape != b_val.shape:
        raise ValueError("a_idx/a_val and b_idx/b_val must be matching (B, n) tensors")
    B = a_idx.shape[0]
    if b_idx.shape[0] != B:
        raise ValueError(f"batch sizes differ: {B} vs {b_idx.shape[0]}")
    K = c.shape[-1]
    L = level_of_size(K)
    if c.ndim == 1:
        c = c.unsqueeze(0)
    if c.ndim != 2 or c.shape[0] not in (1, B):
        raise ValueError(f"c must be (K,) or (B, K) = ({B}, {K}), got {tuple(c.shape)}")
    for name, ix in (("a_idx", a_idx), ("b_idx", b_idx)):
        if ix.numel() and (ix.min() < 0 or ix.max() >= K):
            raise ValueError(f"{name} must lie in [0, {K})")
    dt = torch.promote_types(torch.promote_types(a_val.dtype, b_val.dtype), c.dtype)
    a_val, b_val, c = a_val.to(dt), b_val.to(dt), c.to(dt)
    zero = torch.zeros((), dtype=dt, device=c.device)

    # per-coefficient structure (independent of the values; tables cached per level)
    lvl_t, typ_t, anc_t, sgn_t = (x.to(c.device) for x in coefficient_structure(L))
    sgn_t = sgn_t.to(dt)
    lva, ta = lvl_t[a_idx], typ_t[a_idx]
    lvb = lvl_t[b_idx]
    Aa = 0.25 ** lva.clamp_min(0).to(dt)  # A_l of a's basis functions
    Ab = 0.25 ** lvb.clamp_min(0).to(dt)
    wa, wb = lva >= 0, lvb >= 0
    out = torch.empty(B, dtype=dt, device=c.device)
    rows = max(1, chunk_elems // K)
    for r0 in range(0, B, rows):
        r1 = min(B, r0 + rows)
        n_r = r1 - r0
        ai, av, bi, bv = a_idx[r0:r1], a_val[r0:r1], b_idx[r0:r1], b_val[r0:r1]
        cc = c if c.shape[0] == 1 else c[r0:r1]
        cc = cc.expand(n_r, K)
        ad = torch.zeros(n_r, K, dtype=dt, device=c.device).scatter_(1, ai, av)
        bd = torch.zeros(n_r, K, dtype=dt, device=c.device).scatter_(1, bi, bv)
        tA, AA, wA = ta[r0:r1], Aa[r0:r1], wa[r0:r1]
        b_same = bd.gather(1, ai)
        c_same = cc.gather(1, ai)
        # rule 1: all three the same level-0 scaling function (A_0 = 1)
        tot = torch.where(wA, zero, av * b_same * c_same).sum(-1)
        # rule 3 over a's wavelets: (a, b identical; c coarser) + (a, c identical; b coarser)
        anc_i, anc_s = anc_t[ai], sgn_t[ai]
        t3 = b_same * _avg(cc, anc_i, anc_s) + c_same * _avg(bd, anc_i, anc_s)
        tot = tot + torch.where(wA, AA * av * t3, zero).sum(-1)
        # rule 2: the three wavelet types of one triangle (a type t, b type t', c the third)
        base = torch.where(wA, ai - tA, torch.zeros_like(ai))
        for d1 in (1, 2):
            t1 = (tA + d1) % 3
            t2 = 3 - tA - t1
            r2 = bd.gather(1, base + t1) * cc.gather(1, base + t2)
            tot = tot + torch.where(wA, AA * av * r2, zero).sum(-1)
        # rule 3 over b's wavelets: (b, c identical; a coarser)
        anc_i, anc_s = anc_t[bi], sgn_t[bi]
        r3b = bv * cc.gather(1, bi) * _avg(ad, anc_i, anc_s)
        tot = tot + torch.where(wb[r0:r1], Ab[r0:r1] * r3b, zero).sum(-1)
        out[r0:r1] = tot
    return out


def product_project(f: Tensor, g: Tensor) -> Tensor:
    """Coefficients of the product f·g projected onto the basis: (fg)_k = Σ_ij C_ijk f_i g_j / ⟨Ψ_k,Ψ_k⟩.

    Exact: f·g of two level-L piecewise-constant functions is level-L piecewise constant, so the
    projection equals the transform of the product of the reconstructions (O(K) per row).

    Args:
        f, g: (..., K) broadcastable.
    Returns:
        (..., K).
    """
    f, g = torch.broadcast_tensors(torch.as_tensor(f), torch.as_tensor(g))
    return forward(inverse(f) * inverse(g))


def tripling_coefficients(level: int, *, dtype=torch.float64) -> tuple[Tensor, Tensor]:
    """All non-zero tripling coefficients C_ijk = ∫ Ψ_i Ψ_j Ψ_k from the three rules (Ma 2006 §3.1).

    Meant for tests and small levels (the count grows like K·L).
    Returns:
        ijk (P, 3) int64 and values (P,), each unordered triple listed in all its orderings.
    """
    L = _check_level(level)
    S = _SIGNS
    trip: dict[tuple[int, int, int], float] = {}

    def add(i, j, k, v):
        for p in {(i, j, k), (i, k, j), (j, i, k), (j, k, i), (k, i, j), (k, j, i)}:
            trip[p] = v

    for i in range(20):  # rule 1
        add(i, i, i, 1.0)
    for l in range(L):
        A = 0.25 ** l
        for i in range(n_triangles(l)):
            base = 20 * 4 ** l + 3 * i
            add(base, base + 1, base + 2, A)  # rule 2
            for t in range(3):  # rule 3: the coarser function's sign on T_i^l
                w = base + t
                add(w, w, i >> (2 * l), A)  # level-0 scaling ancestor
                for lp in range(l):
                    anc = i >> (2 * (l - lp))
                    pos = (i >> (2 * (l - lp - 1))) & 3
                    for tp in range(3):
                        add(w, w, 20 * 4 ** lp + 3 * anc + tp, A * S[tp][pos])
    ijk = torch.tensor(list(trip.keys()), dtype=torch.int64).reshape(-1, 3)
    val = torch.tensor(list(trip.values()), dtype=dtype)
    return ijk, val
