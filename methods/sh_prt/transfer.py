"""Precomputed radiance transfer (Sloan, Kautz & Snyder 2002): per-vertex diffuse transfer vectors
and glossy transfer matrices over real SH of order n (n² coefficients, `methods.core.sh`).

Notation (the method card /work/shared/methods/sh_prt.md; Sloan 2002 §4–§6). Everything is in the
*global* (world) SH frame, like the paper's transfer vectors: the lighting l is projected once per
frame and every vertex dots it with its own vector/matrix. t is kept WITHOUT the receiver's albedo ρ
(ρ multiplies at run time, so diffuse colour is a run-time parameter).

Diffuse transfer (Sloan 2002 §5, the three transfer functions T_DU, T_DS, T_DI):
    unshadowed   t⁰_i(x) = (1/π) ∫ y_i(s) H_N(s) ds,                 H_N(s) = max(N·s, 0)
    shadowed     t⁰_i(x) = (1/π) ∫ y_i(s) V_x(s) H_N(s) ds
    bounce b ≥ 1 t^b_i(x) = (1/π) ∫ (1 − V_x(s)) T^{b−1}_i(y_s, −s) H_N(s) ds,    y_s = hit(x, s)
    with T^{b−1}_i(y, ω) the transfer of the radiance y sends towards ω after the previous pass
    (`hit_radiance_transfer`): ρ(y) t^{b−1}_i(y), plus on glossy regions
    k_s(y) Σ_k G_k(y) y_k(R_y) (M^{b−1}_y)_{ki} with R_y = reflect(ω, N_y) (the run-time formula of
    `methods.sh_prt.method`); barycentric at the hit, 0 from the back side of one-sided surfaces
    (as Mitsuba's BSDFs). t = Σ_b t^b (§5: the paper iterates until the added energy is small;
    here a fixed number of passes, config `bounces`).
    The unshadowed vector is the clamped cosine ZH rotated to N, in closed form:
    t_lm = Â_l y_lm(N)/π (Ramamoorthi–Hanrahan Â_l, `zh.clamped_cosine_factors`).

Glossy transfer (Sloan 2002 §6, T_GU / T_GS / T_GI): a matrix per vertex mapping source radiance
to *transferred incident radiance*, l' = M_x l, here WITH the cosine H_N folded in (the method
card's M has none; like the diffuse vectors):
    (M⁰_x)_ij = ∫ y_i(s) V_x(s) H_N(s) y_j(s) ds
    (M^b_x)_ij = ∫ y_i(s) (1 − V_x(s)) H_N(s) T^{b−1}_j(y_s, −s) ds             (b ≥ 1)
At run time the exit radiance towards v of a lobe circularly symmetric about R = reflect(v, N) is
Σ_lm G_l (M_x l)_lm y_lm(R) (§6, Funk–Hecke; `methods.sh_prt.method`). Folding H_N into M makes the
run time the exact rendering-equation integral ∫ L V H_N lobe(R·s) ds up to the order-n truncation
of the transferred radiance and of the lobe (a transfer matrix without H_N would need the cosine
applied per direction, which a zonal kernel about R cannot do). Bounces carry both the diffuse and
the glossy reflection of the hit points, with the scene's materials at precompute time.

Quadrature: every vertex traces J rays over its upper hemisphere (a spherical-Fibonacci set,
rotated about the normal by a seeded random azimuth per vertex, as `methods.ptt.bounce`); closest
hits give both V and the bounce points. The shadowed transfer is computed as the closed-form
unshadowed transfer MINUS the quadrature of the blocked part (a control variate: exact for fully
visible vertices, quadrature error only where rays are blocked).
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import torch
from torch import Tensor

from methods.core import sh as _sh
from methods.core import zh as _zh
from methods.core.frames import frame_matrix, reflect
from methods.core.sampling import gauss_legendre_sphere, rotated_hemisphere_dirs
from methods.core.sh_rotation import sh_rotation_matrix
from methods.core.visibility import Visibility, interpolate_at_hits, offset_origins

MIN_ORDER, MAX_ORDER = 2, 10
# Vertices per batch of the (v, J, n²) quadrature temporaries.
CHUNK = 64


def check_order(order) -> int:
    """n in [MIN_ORDER, MAX_ORDER] (ValueError naming ``order`` otherwise)."""
    if isinstance(order, bool) or not isinstance(order, int) or not MIN_ORDER <= order <= MAX_ORDER:
        raise ValueError(f"order must be an int in [{MIN_ORDER}, {MAX_ORDER}], got {order!r}")
    return order


# -- unshadowed transfer (closed form) ---------------------------------------------------------


def unshadowed_diffuse(normals: Tensor, order: int) -> Tensor:
    """Sloan 2002 §5 T_DU without ρ: t_lm = Â_l y_lm(N)/π (the clamped cosine ZH rotated to N).

    Args:
        normals: (V, 3) unit normals.
    Returns:
        (V, n²) float32.
    """
    check_order(order)
    k = _zh.clamped_cosine_kernel(order)                      # (n,) ZH coefficients of H
    return (_zh.zh_to_sh(k, normals.double()) / math.pi).float()


def unshadowed_glossy_local(order: int, *, dtype=torch.float64) -> Tensor:
    """(M_loc)_ij = ∫ y_i(s) y_j(s) max(s_z, 0) ds in the frame z = N → (n², n²).

    Gauss–Legendre in s_z ∈ [0, 1] × uniform φ: the integrand is a polynomial of degree ≤ 2n−1 in
    (x, y, z) on the hemisphere, so n+2 nodes in z and 2n+2 in φ integrate it exactly.
    """
    check_order(order)
    d, w = gauss_legendre_sphere(order + 2, 2 * order + 2, hemisphere=True, dtype=torch.float64)
    Y = _sh.sh_eval(d, order)                                  # (D, n²)
    return ((Y * (w * d[:, 2])[:, None]).T @ Y).to(dtype)


def unshadowed_glossy(normals: Tensor, order: int) -> Tensor:
    """Sloan 2002 §6 unshadowed glossy transfer with H_N: M_U(N) = D(R) M_loc D(R)ᵀ, R the
    local→world rotation of N's frame (`frames.frame_matrix`ᵀ), D its SH rotation
    (`sh_rotation.sh_rotation_matrix`: y(R u) = D(R) y(u)).

    Args:
        normals: (V, 3) unit normals.
    Returns:
        (V, n², n²) float32.
    """
    check_order(order)
    M_loc = unshadowed_glossy_local(order)
    D = sh_rotation_matrix(frame_matrix(normals.double()).transpose(-1, -2), order)  # (V, n², n²)
    return (D @ M_loc @ D.transpose(-1, -2)).float()


# -- rays ---------------------------------------------------------------------------------------


@dataclass
class Rays:
    """Closest hits of every vertex's hemisphere rays (Sloan 2002 §5 "shadowed"/"interreflected").

    dirs: (V, J, 3) unit world directions; weight: (J,) solid-angle weights (2π/J);
    cos: (V, J) N·s (> 0); face: (V, J) int64 hit face (−1 = the ray escapes, V_x(s) = 1);
    u, v: (V, J) barycentrics of the hit (Mitsuba prim_uv).
    """

    dirs: Tensor
    weight: Tensor
    cos: Tensor
    face: Tensor
    u: Tensor
    v: Tensor

    @property
    def blocked(self) -> Tensor:
        """(V, J) bool: 1 − V_x(s)."""
        return self.face >= 0


def trace_rays(vis: Visibility, points: Tensor, normals: Tensor, n_rays: int, *, seed: int = 0) -> Rays:
    """Trace ``n_rays`` hemisphere rays from every vertex.

    Args:
        vis: Embree scene of the static geometry; points, normals: (V, 3) vertices and unit normals
            (origins offset along N by `visibility.offset_origins(scale=vis.scale)`).
        n_rays: J ≥ 1; seed: the per-vertex azimuth rotation.
    """
    P = torch.as_tensor(points, dtype=torch.float32)
    N = torch.as_tensor(normals, dtype=torch.float32)
    nv = P.shape[0]
    loc, world, w = rotated_hemisphere_dirs(N, n_rays, seed=seed)
    o = offset_origins(P, N, scale=vis.scale)[:, None, :].expand(nv, n_rays, 3)
    _, face, u, v = vis.intersect(o.reshape(-1, 3).contiguous(), world.reshape(-1, 3).contiguous())
    return Rays(world, w, loc[..., 2].clamp_min(0.0), face.reshape(nv, n_rays),
                u.reshape(nv, n_rays), v.reshape(nv, n_rays))


# -- shadowed transfer ---------------------------------------------------------------------------


def shadowed_diffuse(rays: Rays, normals: Tensor, order: int) -> Tensor:
    """Sloan 2002 §5 T_DS without ρ: t = t_U − (1/π) Σ_k w_k (1 − V_k) H_N(s_k) y(s_k) → (V, n²)."""
    t = unshadowed_diffuse(normals, order)
    wb = rays.weight[None] * rays.cos * rays.blocked.float() / math.pi     # (V, J)
    for a in range(0, t.shape[0], CHUNK):
        b = min(a + CHUNK, t.shape[0])
        Y = _sh.sh_eval(rays.dirs[a:b], order)                             # (v, J, n²)
        t[a:b] -= torch.einsum("vj,vji->vi", wb[a:b], Y)
    return t


def shadowed_glossy(rays: Rays, normals: Tensor, order: int, verts: Tensor) -> Tensor:
    """Sloan 2002 §6 shadowed glossy transfer with H_N (module docstring) for vertices ``verts``:
    M = M_U − Σ_k w_k (1 − V_k) H_N(s_k) y(s_k) y(s_k)ᵀ.

    Args:
        verts: (Vg,) vertex indices (the glossy regions' vertices).
    Returns:
        (Vg, n², n²) float32.
    """
    M = unshadowed_glossy(normals[verts], order)
    wb = (rays.weight[None] * rays.cos * rays.blocked.float())[verts]      # (Vg, J)
    dirs = rays.dirs[verts]
    for a in range(0, M.shape[0], CHUNK):
        b = min(a + CHUNK, M.shape[0])
        Y = _sh.sh_eval(dirs[a:b], order)                                  # (v, J, n²)
        M[a:b] -= (Y * wb[a:b, :, None]).transpose(1, 2) @ Y
    return M


# -- interreflections ------------------------------------------------------------------------------


@dataclass
class GlossyHits:
    """What a pass needs to send the glossy reflection of hit points y back towards x:
    M_prev (Vg, n², n², C) the previous pass's glossy transfer, gpos (V,) vertex → row of M_prev
    (−1 if none), face_ks (M, 3) specular albedo and face_G (M, n²) lobe factors G_l of each face's
    region (0 for Lambert faces), face_vcos (M,) bool: the lobe carries an extra factor N·ωo
    (Blinn-Phong approximated about R, `methods.sh_prt.method`)."""

    M_prev: Tensor
    gpos: Tensor
    face_ks: Tensor
    face_G: Tensor
    face_vcos: Tensor


# Floats of the (segments, n², K) gathers of per-vertex matrices per batch (`segment_vecmat`).
GATHER_FLOATS = 1 << 23
# Rows per padded segment of `segment_vecmat` (a vertex hit by more rows gets several segments).
SEGMENT_CAP = 32


def segment_vecmat(a: Tensor, idx: Tensor, M: Tensor) -> Tensor:
    """out_p = a_p · M[idx_p] for many rows sharing few matrices, gathering each matrix once per
    segment of ≤ SEGMENT_CAP rows with the same idx (rows grouped and zero-padded, one bmm)
    instead of once per row.

    Args:
        a: (P, D) rows; idx: (P,) int64 matrix index per row; M: (U, D, K) matrices.
    Returns:
        (P, K).
    """
    P, D = a.shape
    K = M.shape[-1]
    out = torch.zeros(P, K, dtype=a.dtype, device=a.device)
    if P == 0:
        return out
    order = torch.argsort(idx, stable=True)
    si = idx[order]
    new = torch.ones(P, dtype=torch.bool, device=a.device)
    new[1:] = si[1:] != si[:-1]
    start = torch.cummax(torch.where(new, torch.arange(P, device=a.device), 0), 0).values
    rank = torch.arange(P, device=a.device) - start                    # position within its idx run
    seg_new = new | (rank % SEGMENT_CAP == 0)
    seg = torch.cumsum(seg_new.long(), 0) - 1                           # (P,) segment of each sorted row
    col = rank % SEGMENT_CAP
    seg_mat = si[seg_new]                                               # (S,) matrix of each segment
    n_seg = int(seg_mat.numel())
    step = max(1, GATHER_FLOATS // (D * K))
    for s0 in range(0, n_seg, step):
        s1 = min(n_seg, s0 + step)
        rows = ((seg >= s0) & (seg < s1)).nonzero().squeeze(-1)         # sorted rows of these segments
        A = torch.zeros(s1 - s0, SEGMENT_CAP, D, dtype=a.dtype, device=a.device)
        A[seg[rows] - s0, col[rows]] = a[order[rows]]
        Y = torch.bmm(A, M[seg_mat[s0:s1]])                             # (s, CAP, K)
        out[order[rows]] = Y[seg[rows] - s0, col[rows]]
    return out



def hit_radiance_transfer(rays: Rays, a: int, b: int, F: Tensor, normals: Tensor, face_albedo: Tensor,
                          t_prev: Tensor, glossy: GlossyHits | None = None) -> Tensor:
    """Transfer of the radiance the hit points y of vertices a:b send back along −s, as a linear
    function of the source lighting (row j ↔ source coefficient j):
        ρ(y) t^{b−1}(y) + k_s(y) Σ_i G_i(y) y_i(R_y) (M^{b−1}_y)_{ij},   R_y = reflect(−s, N_y),
    (the glossy term only with ``glossy``), barycentric at the hit, 0 on misses and from back
    faces (one-sided BSDFs, as Mitsuba's).

    Args:
        F: (M, 3) faces; normals: (V, 3) unit vertex normals; face_albedo: (M, 3) diffuse albedo of
        each face's region; t_prev: (V, n², C) previous-pass diffuse transfer (C = 1 or 3).
    Returns:
        (b−a, J, n², 3).
    """
    face = rays.face[a:b].reshape(-1)
    u, v = rays.u[a:b].reshape(-1), rays.v[a:b].reshape(-1)
    s = rays.dirs[a:b].reshape(-1, 3)
    tp = interpolate_at_hits(t_prev, F, face, u, v)                     # (h, n², C), 0 on misses
    n_hit = interpolate_at_hits(normals, F, face, u, v)                 # (h, 3) shading normal at y
    live = ((n_hit * s).sum(-1) < 0) & (face >= 0)                      # x is on y's front side
    fc = face.clamp_min(0)
    rho = face_albedo[fc] * live.float()[:, None]                       # (h, 3)
    out = tp * rho[:, None, :]                                          # (h, n², 3)
    if glossy is not None:
        gl = (live & (glossy.face_G[fc].abs().sum(-1) > 0)).nonzero().squeeze(-1)
        if gl.numel():
            n2 = glossy.face_G.shape[1]
            order = math.isqrt(n2)
            C = glossy.M_prev.shape[-1]
            ny = torch.nn.functional.normalize(n_hit[gl], dim=-1)
            R = reflect(-s[gl], ny)
            wR = _sh.sh_eval(torch.nn.functional.normalize(R, dim=-1), order) * glossy.face_G[fc[gl]]  # (g, n²)
            c = (ny * -s[gl]).sum(-1, keepdim=True).clamp_min(0.0)          # N_y·ωo, ωo = −s towards x
            wR = torch.where(glossy.face_vcos[fc[gl]][:, None], wR * c, wR)
            tri = F[fc[gl]]                                                 # (g, 3)
            bw = torch.stack([1.0 - u[gl] - v[gl], u[gl], v[gl]], -1)       # (g, 3)
            a_p = (bw[..., None] * wR[:, None, :]).reshape(-1, n2)          # (3g, n²) per (hit, vertex)
            Mf = glossy.M_prev.reshape(glossy.M_prev.shape[0], n2, n2 * C)
            g_p = segment_vecmat(a_p, glossy.gpos[tri.reshape(-1)], Mf)     # (3g, n² C)
            acc = g_p.reshape(-1, 3, n2, C).sum(1)                           # barycentric sum
            out[gl] += acc * glossy.face_ks[fc[gl]][:, None, :]
    return out.reshape(b - a, -1, out.shape[1], 3)


def bounce(rays: Rays, F: Tensor, normals: Tensor, face_albedo: Tensor, t_prev: Tensor, order: int,
           glossy_verts: Tensor, glossy: GlossyHits | None = None, *,
           progress: bool | None = None) -> tuple[Tensor, Tensor]:
    """One interreflection pass (Sloan 2002 §5 T_DI, §6; module docstring).

    Args:
        rays, F, normals, face_albedo, glossy: as `hit_radiance_transfer`; t_prev: (V, n², C).
        glossy_verts: (Vg,) vertices that also get a glossy matrix.
    Returns:
        t^b (V, n², 3) and M^b (Vg, n², n², 3), float32.
    """
    from tqdm.auto import tqdm

    nv, n2 = normals.shape[0], order * order
    t = torch.zeros(nv, n2, 3)
    gpos = torch.full((nv,), -1, dtype=torch.int64)
    gpos[glossy_verts] = torch.arange(glossy_verts.numel())
    M = torch.zeros(glossy_verts.numel(), n2, n2, 3)
    wc = rays.weight[None] * rays.cos                                    # (V, J) w_k H_N(s_k)
    if progress is None:
        progress = sys.stderr.isatty()
    for a in tqdm(range(0, nv, CHUNK), disable=not progress, desc="sh_prt bounce", unit="chunk"):
        b = min(a + CHUNK, nv)
        Lt = hit_radiance_transfer(rays, a, b, F, normals, face_albedo, t_prev, glossy)  # (v, J, n², 3)
        t[a:b] = torch.einsum("vj,vjic->vic", wc[a:b], Lt) / math.pi
        g = gpos[a:b]
        sel = (g >= 0).nonzero().squeeze(-1)
        if sel.numel():
            Y = _sh.sh_eval(rays.dirs[a:b][sel], order) * wc[a:b][sel][..., None]   # (s, J, n²)
            M[g[sel]] = torch.einsum("sji,sjkc->sikc", Y, Lt[sel])
    return t, M
