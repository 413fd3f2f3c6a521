"""One- and two-bounce precomputed transfer tensors (Sun et al. 2007 §3.1, §3.3, §4.3).

One bounce (§3.1, §4.3 "Precomputation"): rays are traced over the hemisphere of every vertex x
(embreex closest hits). A ray hitting the scene at y (region r_y) brings the radiance y reflects
towards x of its *direct* lighting, per lighting wavelet l (coarse 6×n×n, paper 6×8×8) and BRDF
basis function p:

    D_y(l, p) = ∫ L_l(ω) V_y(ω) b_p(ω, ωo_y) (ω·n_y) dω ≈ Σ_k W(p, ωo_y, k) U^{I0}_y(l, k),

and T¹_x(l, r, p, s) = Σ_rays w_j Y_s(ω_j) [r_y = r] D_y(l, p)      (4-D PTT, SH order 4 at x).

The paper interpolates y's *visibility* barycentrically from its triangle's vertices (§4.3); here
the per-vertex visibility-weighted coarse transport U^{I0}_v (`transport.direct_transport`,
``coarse``) is evaluated at each vertex of y's triangle in that vertex's own frame and the three
results are interpolated with y's barycentrics — the same interpolation of visibility, with the
BRDF applied through the shared factorization (rank K) instead of pointwise.

Two bounces (§3.1, §3.3 "Two-Bounce"): from the one-bounce PTTs at the hit points z (lighting
reduced to the coarser 6×2×2 block), reflected at z with basis p2 of z's region r2:

    T²_x(l, r1, p1, r2, p2) = (1/π) Σ_rays w_j cos θ_j [r_z = r2]
                               Σ_s T¹_z(l, r1, p1, s) Σ_k C^{ωi}(s, k) W(p2, ωo_z, k),

i.e. the cosine-weighted mean incident radiance (irradiance/π), the uniform radiance that
U^{I2} = C^{ωi}(k) ΣΣ H H T² assumes. T¹_z is again interpolated over z's triangle with every
vertex evaluated in its own frame.

Ray directions: a spherical-Fibonacci hemisphere set, rotated about the normal by a seeded random
azimuth per vertex (decorrelates neighbouring vertices' quadrature error).
"""
from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import torch
from torch import Tensor

from methods.core import sh as _sh
from methods.core.frames import to_local
from methods.core.sampling import rotated_hemisphere_dirs
from methods.core.threads import bmm
from methods.core.visibility import Visibility, offset_origins
from methods.ptt.transport import BasisFactors

__all__ = ["Hits", "trace_hemispheres", "one_bounce_ptt", "two_bounce_ptt"]


@dataclass
class Hits:
    """Closest hits of every vertex's hemisphere rays.

    local: (Nv, J, 3) ray directions in the vertex's local frame; weight: (J,) quadrature weights.
    wo: (Nv, J, 3) world directions from the hit point back to the vertex (−ray direction).
    face: (Nv, J) int64 hit face (−1 = miss: the ray sees the env map, i.e. direct lighting).
    u, v: (Nv, J) barycentrics (Mitsuba prim_uv).
    """

    local: Tensor
    weight: Tensor
    wo: Tensor
    face: Tensor
    u: Tensor
    v: Tensor


def trace_hemispheres(vis: Visibility, V: Tensor, normals: Tensor, n_rays: int, *, seed: int = 0) -> Hits:
    """Trace ``n_rays`` hemisphere rays from every vertex: V (Nv, 3) ray origins
    (`transport.ray_points`), normals (Nv, 3)."""
    V = torch.as_tensor(V, dtype=torch.float32)
    normals = torch.as_tensor(normals, dtype=torch.float32)
    nv = V.shape[0]
    loc, world, w = rotated_hemisphere_dirs(normals, n_rays, seed=seed)
    o = offset_origins(V, normals, scale=vis.scale)[:, None, :].expand(nv, n_rays, 3)
    _, face, u, v = vis.intersect(o.reshape(-1, 3).contiguous(), world.reshape(-1, 3).contiguous())
    return Hits(loc, w, -world, face.reshape(nv, n_rays), u.reshape(nv, n_rays), v.reshape(nv, n_rays))


def _tri(F: Tensor, face: Tensor, u: Tensor, v: Tensor) -> tuple[Tensor, Tensor]:
    """Vertex ids (H, 3) and barycentric weights (H, 3) of hits."""
    return F[face], torch.stack([1.0 - u - v, u, v], -1)


def _chunk_hits(hits: Hits, F: Tensor, a: int, b: int):
    """The rays of vertices a:b that hit something: flat indices sel (H,) into the chunk's
    (b−a)·J rays, their faces f (H,), triangle vertices tri (H, 3), barycentric weights bw (H, 3)
    and directions back towards the shading vertex wo (H, 3); None if no ray hit."""
    face = hits.face[a:b].reshape(-1)
    sel = torch.nonzero(face >= 0).squeeze(-1)
    if sel.numel() == 0:
        return None
    f = face[sel]
    tri, bw = _tri(F, f, hits.u[a:b].reshape(-1)[sel], hits.v[a:b].reshape(-1)[sel])
    return sel, f, tri, bw, hits.wo[a:b].reshape(-1, 3)[sel]


def one_bounce_ptt(hits: Hits, F: Tensor, normals: Tensor, face_region: Tensor, n_regions: int,
                   factors: BasisFactors, coarse: Tensor, *, order: int = 4, chunk: int = 8,
                   progress: bool | None = None) -> Tensor:
    """T¹_x(r, p, s, l) for every vertex (module docstring).

    Args:
        hits: `trace_hemispheres` result; F (M, 3) faces; normals (Nv, 3); face_region (M,).
        n_regions: R; factors: the basis factorization (n_P basis BRDFs, K factors).
        coarse: (Nv, K, L1) coarse direct transport per vertex (`DirectTransport.coarse`).
        order: SH order of the transferred incident radiance (paper 4 → 16 coefficients).
        chunk: vertices per batch.
    Returns:
        (Nv, R, n_P, S, L1) float32.
    """
    from tqdm.auto import tqdm

    nv, J = hits.face.shape
    K, L1 = coarse.shape[1], coarse.shape[2]
    P, S = factors.n_P, order * order
    if coarse.shape[0] != nv or K != factors.K:
        raise ValueError(f"coarse must be (Nv={nv}, K={factors.K}, L1), got {tuple(coarse.shape)}")
    Y = _sh.sh_eval(hits.local, order) * hits.weight[None, :, None]  # (Nv, J, S) w_j Y_s(ω_j)
    out = torch.zeros(nv, n_regions, P, S, L1, dtype=torch.float32)
    if progress is None:
        progress = sys.stderr.isatty()
    for a in tqdm(range(0, nv, chunk), disable=not progress, desc="one-bounce PTT", unit="chunk"):
        b = min(nv, a + chunk)
        chunk_hits = _chunk_hits(hits, F, a, b)
        if chunk_hits is None:
            continue
        sel, f, tri, bw, wo = chunk_hits
        D = torch.zeros(sel.numel(), P, L1)
        for j in range(3):
            vid = tri[:, j]
            Wv = factors.W(to_local(wo, normals[vid])) * bw[:, j, None, None]  # (H, P, K)
            D += bmm(Wv, coarse[vid])  # (H, P, L1); a batch of one hit on one thread (methods.core.threads)
        Dfull = torch.zeros((b - a) * J, P, L1)
        Dfull[sel] = D
        reg = torch.full(((b - a) * J,), -1, dtype=torch.int64)
        reg[sel] = face_region[f]
        onehot = (reg[:, None] == torch.arange(n_regions)[None]).float()  # (cJ, R), misses all 0
        A = onehot.reshape(b - a, J, n_regions, 1) * Y[a:b, :, None, :]  # (c, J, R, S)
        out[a:b] = torch.einsum("cjrs,cjpl->crpsl", A, Dfull.reshape(b - a, J, P, L1))
    return out


def two_bounce_ptt(hits: Hits, F: Tensor, normals: Tensor, face_region: Tensor, n_regions: int,
                   factors: BasisFactors, C: Tensor, T1: Tensor, *, chunk: int = 16,
                   progress: bool | None = None) -> Tensor:
    """T²_x(l, r1, p1, r2, p2) for every vertex (module docstring).

    Args:
        hits, F, normals, face_region, n_regions, factors: as `one_bounce_ptt`.
        C: (S, K) C^{ωi}(s, k) (`transport.sh_light_matrix`).
        T1: (Nv, R, P, S, L2) one-bounce PTTs restricted to the two-bounce lighting block.
    Returns:
        (Nv, L2, R, P, R, P) float32.
    """
    from tqdm.auto import tqdm

    nv, J = hits.face.shape
    R, P, S, L2 = T1.shape[1:]
    if T1.shape[0] != nv or R != n_regions or P != factors.n_P or C.shape != (S, factors.K):
        raise ValueError(f"T1 {tuple(T1.shape)} / C {tuple(C.shape)} do not match the scene and basis")
    wcos = hits.weight[None, :] * hits.local[..., 2] / math.pi  # (Nv, J) w_j cos θ_j / π
    out = torch.zeros(nv, L2, R, P, R, P, dtype=torch.float32)
    if progress is None:
        progress = sys.stderr.isatty()
    for a in tqdm(range(0, nv, chunk), disable=not progress, desc="two-bounce PTT", unit="chunk"):
        b = min(nv, a + chunk)
        chunk_hits = _chunk_hits(hits, F, a, b)
        if chunk_hits is None:
            continue
        sel, f, tri, bw, wo = chunk_hits
        X = torch.zeros(sel.numel(), R, P, P, L2)
        for j in range(3):
            vid = tri[:, j]
            G = torch.einsum("sk,hqk->hsq", C, factors.W(to_local(wo, normals[vid]))) * bw[:, j, None, None]
            X += torch.einsum("hrpsl,hsq->hrpql", T1[vid], G)
        Xfull = torch.zeros((b - a) * J, R, P, P, L2)
        Xfull[sel] = X
        reg = torch.full(((b - a) * J,), -1, dtype=torch.int64)
        reg[sel] = face_region[f]
        onehot = (reg[:, None] == torch.arange(n_regions)[None]).float()  # (cJ, R2)
        A = onehot.reshape(b - a, J, n_regions) * wcos[a:b, :, None]
        out[a:b] = torch.einsum("cjt,cjrpql->clrptq", A, Xfull.reshape(b - a, J, R, P, P, L2))
    return out
