"""Precomputation pieces of the local-frame triple product (Ma 2006 §3.2, §4.1): per-vertex
local-frame visibility V^x on the geodesic grid, coefficient truncation (§4.1, Figs. 7–8), and the
surface samples of visibility textures (§3.3, `texel_points`).

Truncation keeps n coefficients per function:
* ``"adaptive"``: the n largest *area-weighted* magnitudes |c_k|·A_k (A_k = support area of Ψ_k
  in the equal-area measure, `spherical_haar.support_areas`; Ng 2003 §5, Ma 2006 §4.1);
* ``"top"`` (top-only): the first n coefficients of the coarse-to-fine layout (level-0 scaling
  functions, then level-0 wavelets, …), the same index set for every function (GPU-friendly).
RGB functions select on the channel sum of magnitudes and keep the same indices for all channels.
Truncated functions are stored sparsely: indices (..., n) int32 and values (..., [C,] n).
"""
from __future__ import annotations

import torch
from torch import Tensor

from methods.core.spherical_haar import Geodesic, keep_largest, support_areas
from methods.core.visibility import Visibility, offset_origins

SELECTIONS = ("adaptive", "top")
# Interpolated normals shorter than this (opposite vertex normals) fall back to the face normal,
# as in `references.gbuffer`.
NORMAL_EPS = 1e-12


def visibility_coeffs(vis: Visibility, points: Tensor, normals: Tensor, R: Tensor, geo: Geodesic, *,
                      supersample: int = 0, vertices_per_chunk: int = 256,
                      progress: bool = False) -> Tensor:
    """Wavelet coefficients of binary local-frame visibility V^x(ω) (Ma 2006 eq. 7).

    V^x(ω) = 1 when the ray from x (offset along its normal) in world direction R_x^T ω escapes and
    n·(R_x^T ω) > 0 (directions below the horizon count as blocked: ρ̃ is 0 there anyway).
    Each fine triangle's value is the solid-angle-weighted fraction of its 4^supersample sub-rays
    that escape (`Geodesic.project`).

    Args:
        vis: Embree scene; points, normals: (V, 3); R: (V, 3, 3) world→local frames (rows s, t, n).
    Returns:
        (V, K) float32 coefficients.
    """
    from tqdm.auto import tqdm

    points, normals, R = points.float().cpu(), normals.float().cpu(), R.float().cpu()
    nV = points.shape[0]
    if points.shape != (nV, 3) or normals.shape != (nV, 3) or R.shape != (nV, 3, 3):
        raise ValueError(f"points, normals (V, 3) and R (V, 3, 3) expected, got {tuple(points.shape)}, "
                         f"{tuple(normals.shape)}, {tuple(R.shape)}")
    O = offset_origins(points, normals, scale=vis.scale)
    out = []
    for a in tqdm(range(0, nV, vertices_per_chunk), disable=not progress, desc="visibility", unit="chunk"):
        b = min(nV, a + vertices_per_chunk)

        def fn(c: Tensor, a=a, b=b) -> Tensor:
            d = torch.einsum("pj,vji->vpi", c.float(), R[a:b])  # world directions (v, P, 3)
            o = O[a:b, None, :].expand_as(d)
            free = ~torch.as_tensor(vis.occluded(o.reshape(-1, 3).numpy(), d.reshape(-1, 3).numpy()))
            free = free.reshape(d.shape[:2]) & ((d * normals[a:b, None, :]).sum(-1) > 0)
            return free.T.float()  # (P, v)

        out.append(geo.project(fn, supersample=supersample, dtype=torch.float32))  # (v, K)
    return torch.cat(out, 0) if out else torch.zeros(0, geo.n)


def truncate(coeffs: Tensor, n: int | None, selection: str, level: int) -> tuple[Tensor, Tensor]:
    """Keep n coefficients per function.

    Args:
        coeffs: (B, K) scalar or (B, C, K) multi-channel coefficients.
        n: number kept (None or ≥ K = all); selection: "adaptive" | "top".
    Returns:
        idx (B, n) int32 and values (B, n) or (B, C, n).
    """
    if selection not in SELECTIONS:
        raise ValueError(f"selection must be one of {SELECTIONS}, got {selection!r}")
    K = coeffs.shape[-1]
    n = K if n is None else min(int(n), K)
    B = coeffs.shape[0]
    if coeffs.ndim not in (2, 3):
        raise ValueError(f"coeffs must be (B, K) or (B, C, K), got {tuple(coeffs.shape)}")
    if n == K:
        idx = torch.arange(K, device=coeffs.device).expand(B, K)
    elif selection == "top":
        idx = torch.arange(n, device=coeffs.device).expand(B, n)
    else:  # the magnitudes only where they select (a lighting change keeps all K: no pass over them)
        mag = coeffs.abs() if coeffs.ndim == 2 else coeffs.abs().sum(1)
        w = support_areas(level, dtype=mag.dtype, device=mag.device)
        idx, _ = keep_largest(mag, n, weights=w)
    if coeffs.ndim == 2:
        val = coeffs.gather(-1, idx)
    else:
        val = coeffs.gather(-1, idx[:, None, :].expand(B, coeffs.shape[1], idx.shape[-1]))
    return idx.to(torch.int32).contiguous(), val.contiguous()


def blend_sparse(idx: Tensor, val: Tensor, rows: Tensor, w: Tensor, K: int) -> Tensor:
    """Dense weighted blend Σ_r w_r f_{rows_r} of sparse stored functions.

    Args:
        idx: (N, n) int; val: (N, n) or (N, C, n) stored functions.
        rows: (B, k) int64 rows to blend; w: (B, k) weights.
    Returns:
        (B, K) or (B, C, K) dense coefficients.
    """
    B, k = rows.shape
    n = idx.shape[-1]
    ii = idx[rows].long().reshape(B, k * n)  # (B, k·n)
    if val.ndim == 2:
        vv = (val[rows] * w[..., None].to(val.dtype)).reshape(B, k * n)
        return torch.zeros(B, K, dtype=val.dtype, device=val.device).scatter_add_(1, ii, vv)
    C = val.shape[1]
    vv = (val[rows] * w[..., None, None].to(val.dtype)).permute(0, 2, 1, 3).reshape(B, C, k * n)
    return torch.zeros(B, C, K, dtype=val.dtype, device=val.device).scatter_add_(
        2, ii[:, None, :].expand(B, C, k * n), vv)


def texel_points(V: Tensor, N: Tensor, F: Tensor, uv: Tensor, res: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Surface samples of a res×res visibility texture over one shape's UV map (Ma 2006 §3.3:
    "for each texel of this map we find its corresponding position on the surface of the 3D mesh").

    The shape's triangles are rasterised in UV space (`textures.rasterize_uv`); every covered texel
    centre gives a 3-D point (barycentric interpolation of V) and a unit normal (normalised
    interpolation of N, the shading normal the G-buffer uses).

    Args:
        V (N, 3), N (N, 3) vertex positions and unit normals; F (M, 3) the shape's faces (indices
        into V); uv (N, 2) vertex UVs; res: texels per side.
    Returns:
        texel (T,) int64 flat texel indices (i·res + j) of the covered texels, face (T,) int64 local
        face index, points (T, 3) and normals (T, 3) float32.
    """
    from methods.triple_product.textures import rasterize_uv

    if V.ndim != 2 or V.shape[1] != 3 or N.shape != V.shape or uv.shape != (V.shape[0], 2):
        raise ValueError(f"V, N (N, 3) and uv (N, 2) expected, got {tuple(V.shape)}, {tuple(N.shape)}, "
                         f"{tuple(uv.shape)}")
    if isinstance(res, bool) or not isinstance(res, int) or res < 1:
        raise ValueError(f"res must be an int >= 1, got {res!r}")
    face, bary = rasterize_uv(uv, F, res, res)
    texel = torch.nonzero(face >= 0, as_tuple=False).squeeze(-1)
    f = face[texel]
    b = bary[texel].double()
    w = torch.stack([1 - b[:, 0] - b[:, 1], b[:, 0], b[:, 1]], -1)           # (T, 3)
    idx = F[f]
    pts = (V.double()[idx] * w[..., None]).sum(1)
    n = (N.double()[idx] * w[..., None]).sum(1)
    P = V.double()[idx]
    ng = torch.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0], dim=-1)  # fallback: geometric normal
    ng = torch.where(((ng * n).sum(-1, keepdim=True) < 0), -ng, ng)
    ln = n.norm(dim=-1, keepdim=True)
    ng = ng / ng.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    nrm = torch.where(ln > NORMAL_EPS, n / ln.clamp_min(NORMAL_EPS), ng)
    return texel, f, pts.float(), nrm.float()
