"""UV-space textures for the local-frame triple product (Ma 2006 §3.3, §5): the pure functions
behind visibility textures, spatially varying BRDFs (SBRDF weight maps) and bump maps.

Texture convention (stated once)
--------------------------------
A texture is a tensor (H, W[, C]) over the UV square [0, 1]²: **row i ↔ v, column j ↔ u**, texel
(i, j) centred at (u, v) = ((j + ½)/W, (i + ½)/H). Look-ups are bilinear between texel centres
with clamp-to-edge (a UV outside [0, 1]² reads the border texels). The flat texel index is i·W + j.

Barycentrics follow the G-buffer (Mitsuba ``prim_uv``): p = (1−b1−b2)·p0 + b1·p1 + b2·p2.

UV Jacobian of a triangle (the tangent frame of the parameterisation, Blinn 1978):
    [p1 − p0, p2 − p0] = [∂p/∂u, ∂p/∂v] · [[u1 − u0, u2 − u0], [v1 − v0, v2 − v0]].

Bump mapping (Blinn 1978; Ma 2006 §5 "rotate the lighting by the perturbed normal"):
the displaced surface p' = p + s·h(u, v)·n has, dropping the ∂n/∂u terms,
    ∂p'/∂u × ∂p'/∂v = ∂p/∂u × ∂p/∂v + s h_u (n × ∂p/∂v) − s h_v (n × ∂p/∂u),
and with ∂p/∂u × ∂p/∂v = σ |∂p/∂u × ∂p/∂v| n (σ = ±1, the orientation of the UV map on the side of
the shading normal n)
    n' = normalize(n + σ s (h_u (n × ∂p/∂v) − h_v (n × ∂p/∂u)) / |∂p/∂u × ∂p/∂v|).
"""
from __future__ import annotations

import torch
from torch import Tensor

# UV triangles with |det| below this (in UV² units) have no usable parameterisation: no texels are
# rasterised in them and bump mapping leaves their normals alone.
UV_DET_EPS = 1e-12
# Texel centres on a triangle edge count as inside (barycentric slack; float32 UVs ~1e-7).
RASTER_EPS = 1e-6


def _check_uv(uv: Tensor, name: str = "uv") -> None:
    if uv.ndim != 2 or uv.shape[1] != 2:
        raise ValueError(f"{name} must be (B, 2), got {tuple(uv.shape)}")


def texel_centres(height: int, width: int, *, dtype=torch.float32, device=None) -> Tensor:
    """(H·W, 2) UV of every texel centre in flat order i·W + j (module convention)."""
    v = (torch.arange(height, dtype=dtype, device=device) + 0.5) / height
    u = (torch.arange(width, dtype=dtype, device=device) + 0.5) / width
    V, U = torch.meshgrid(v, u, indexing="ij")
    return torch.stack([U.reshape(-1), V.reshape(-1)], -1)


def _axis_taps(x: Tensor, n: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Lower tap, upper tap, fraction and 'inside' mask (derivative non-zero) along one axis of n
    texels, for continuous texel coordinates x = uv·n − ½ (clamp-to-edge)."""
    if n == 1:
        z = torch.zeros_like(x, dtype=torch.long)
        return z, z, torch.zeros_like(x), torch.zeros_like(x, dtype=torch.bool)
    i0 = x.floor().long().clamp(0, n - 2)
    a = (x - i0).clamp(0, 1)
    inside = (x >= 0) & (x <= n - 1)
    return i0, i0 + 1, a, inside


def bilinear_taps(uv: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
    """Bilinear look-up stencil of UVs (B, 2) on an H×W texture.

    Returns flat texel indices (B, 4) int64 and weights (B, 4) (sum 1), taps ordered
    (i0, j0), (i0, j1), (i1, j0), (i1, j1).
    """
    _check_uv(uv)
    uv = uv.double()
    j0, j1, a, _ = _axis_taps(uv[:, 0] * width - 0.5, width)
    i0, i1, b, _ = _axis_taps(uv[:, 1] * height - 0.5, height)
    idx = torch.stack([i0 * width + j0, i0 * width + j1, i1 * width + j0, i1 * width + j1], -1)
    w = torch.stack([(1 - b) * (1 - a), (1 - b) * a, b * (1 - a), b * a], -1)
    return idx, w


def bilinear(tex: Tensor, uv: Tensor) -> Tensor:
    """Bilinear texture look-up: tex (H, W) or (H, W, C), uv (B, 2) → (B,) or (B, C) (tex dtype)."""
    if tex.ndim not in (2, 3):
        raise ValueError(f"texture must be (H, W) or (H, W, C), got {tuple(tex.shape)}")
    H, W = tex.shape[:2]
    idx, w = bilinear_taps(uv, H, W)
    flat = tex.reshape(H * W, -1)
    out = (flat[idx] * w.to(tex.dtype)[..., None]).sum(1)
    return out[:, 0] if tex.ndim == 2 else out


def bilinear_gradient(tex: Tensor, uv: Tensor) -> Tensor:
    """(∂h/∂u, ∂h/∂v) (B, 2) of the bilinear interpolant of a scalar texture tex (H, W) at uv (B, 2).

    Exact derivative of `bilinear` inside the texel-centre lattice; 0 along an axis where the
    look-up is clamped (outside the outermost texel centres) or the texture is 1 texel wide.
    """
    if tex.ndim != 2:
        raise ValueError(f"height texture must be (H, W), got {tuple(tex.shape)}")
    _check_uv(uv)
    H, W = tex.shape
    u64 = uv.double()
    j0, j1, a, in_u = _axis_taps(u64[:, 0] * W - 0.5, W)
    i0, i1, b, in_v = _axis_taps(u64[:, 1] * H - 0.5, H)
    h = tex.double()
    h00, h01, h10, h11 = h[i0, j0], h[i0, j1], h[i1, j0], h[i1, j1]
    du = ((1 - b) * (h01 - h00) + b * (h11 - h10)) * W * in_u
    dv = ((1 - a) * (h10 - h00) + a * (h11 - h01)) * H * in_v
    return torch.stack([du, dv], -1).to(tex.dtype)


def uv_jacobian(V: Tensor, F: Tensor, uv: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """∂p/∂u, ∂p/∂v (M, 3) of every triangle and ok (M,) bool (non-degenerate UV triangle).

    Args: V (N, 3) positions, F (M, 3) faces, uv (N, 2) vertex UVs. Degenerate UV triangles get
    zero Jacobians and ok = False.
    """
    if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3 or uv.shape != (V.shape[0], 2):
        raise ValueError(f"V (N, 3), F (M, 3), uv (N, 2) expected, got {tuple(V.shape)}, {tuple(F.shape)}, "
                         f"{tuple(uv.shape)}")
    p, t = V.double()[F], uv.double()[F]                 # (M, 3, 3), (M, 3, 2)
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    du1, dv1 = t[:, 1, 0] - t[:, 0, 0], t[:, 1, 1] - t[:, 0, 1]
    du2, dv2 = t[:, 2, 0] - t[:, 0, 0], t[:, 2, 1] - t[:, 0, 1]
    det = du1 * dv2 - du2 * dv1
    ok = det.abs() > UV_DET_EPS
    inv = torch.where(ok, 1.0 / torch.where(ok, det, torch.ones_like(det)), torch.zeros_like(det))[:, None]
    # [e1 e2] = [Pu Pv] [[du1 du2], [dv1 dv2]]  ⇒  [Pu Pv] = [e1 e2] · inverse
    dpdu = (e1 * dv2[:, None] - e2 * dv1[:, None]) * inv
    dpdv = (e2 * du1[:, None] - e1 * du2[:, None]) * inv
    return dpdu.to(V.dtype), dpdv.to(V.dtype), ok


def rasterize_uv(uv: Tensor, F: Tensor, height: int, width: int) -> tuple[Tensor, Tensor]:
    """Which triangle covers each texel centre of an H×W texture, in UV space.

    Args: uv (N, 2) vertex UVs; F (M, 3) faces (indices into uv).
    Returns: face (H·W,) int64 (−1 where no triangle covers the centre) and bary (H·W, 2) (b1, b2)
        of the centre in that face (module convention). A centre covered by several triangles (a
        shared edge, or overlapping UV charts) takes the one it is deepest inside (largest minimum
        barycentric).
    """
    _check_uv(uv)
    if F.ndim != 2 or F.shape[1] != 3:
        raise ValueError(f"F must be (M, 3), got {tuple(F.shape)}")
    dev = uv.device
    T = uv.double()[F]                                            # (M, 3, 2)
    a0, e1, e2 = T[:, 0], T[:, 1] - T[:, 0], T[:, 2] - T[:, 0]
    det = e1[:, 0] * e2[:, 1] - e2[:, 0] * e1[:, 1]
    good = det.abs() > UV_DET_EPS
    lo, hi = T.amin(1), T.amax(1)                                 # (M, 2) UV bounding boxes
    # texel index range whose centres lie in the box: (j + ½)/W ∈ [lo, hi]
    j_lo = (lo[:, 0] * width - 0.5).ceil().long().clamp(0, width)
    j_hi = (hi[:, 0] * width - 0.5).floor().long().clamp(-1, width - 1)
    i_lo = (lo[:, 1] * height - 0.5).ceil().long().clamp(0, height)
    i_hi = (hi[:, 1] * height - 0.5).floor().long().clamp(-1, height - 1)
    nj = (j_hi - j_lo + 1).clamp_min(0)
    ni = (i_hi - i_lo + 1).clamp_min(0)
    cnt = torch.where(good, nj * ni, torch.zeros_like(nj))
    face = torch.full((height * width,), -1, dtype=torch.int64, device=dev)
    bary = torch.zeros(height * width, 2, dtype=uv.dtype, device=dev)
    total = int(cnt.sum())
    if total == 0:
        return face, bary
    f = torch.repeat_interleave(torch.arange(F.shape[0], device=dev), cnt)        # (C,)
    start = torch.cumsum(cnt, 0) - cnt
    k = torch.arange(total, device=dev) - start[f]                # rank inside the face's box
    i = i_lo[f] + k // nj[f]
    j = j_lo[f] + k % nj[f]
    cu, cv = (j.double() + 0.5) / width, (i.double() + 0.5) / height
    du, dv = cu - a0[f, 0], cv - a0[f, 1]
    b1 = (du * e2[f, 1] - dv * e2[f, 0]) / det[f]
    b2 = (dv * e1[f, 0] - du * e1[f, 1]) / det[f]
    score = torch.minimum(torch.minimum(1 - b1 - b2, b1), b2)
    inside = score >= -RASTER_EPS
    f, b1, b2, score, t = f[inside], b1[inside], b2[inside], score[inside], (i * width + j)[inside]
    if t.numel() == 0:
        return face, bary
    # per texel keep the candidate with the largest score: sort by score, then stably by texel
    o = torch.argsort(score, descending=True, stable=True)
    o = o[torch.argsort(t[o], stable=True)]
    t, f, b1, b2 = t[o], f[o], b1[o], b2[o]
    first = torch.ones_like(t, dtype=torch.bool)
    first[1:] = t[1:] != t[:-1]
    face[t[first]] = f[first]
    bary[t[first]] = torch.stack([b1[first], b2[first]], -1).to(uv.dtype)
    return face, bary


def perturb_normals(n: Tensor, dpdu: Tensor, dpdv: Tensor, grad: Tensor, scale: float | Tensor) -> Tensor:
    """Bump-mapped unit normals (B, 3) (module docstring; Blinn 1978).

    Args: n (B, 3) unit shading normals; dpdu, dpdv (B, 3) the UV Jacobian of each point's triangle
        (zero for triangles without a usable UV map: the normal is returned unchanged);
        grad (B, 2) (∂h/∂u, ∂h/∂v) of the height map; scale: height scale s (world units per unit h).
    """
    B = n.shape[0]
    for name, x, c in (("n", n, 3), ("dpdu", dpdu, 3), ("dpdv", dpdv, 3), ("grad", grad, 2)):
        if x.shape != (B, c):
            raise ValueError(f"{name} must be ({B}, {c}), got {tuple(x.shape)}")
    cr = torch.cross(dpdu, dpdv, dim=-1)
    area = cr.norm(dim=-1, keepdim=True)
    sigma = torch.where((cr * n).sum(-1, keepdim=True) < 0, -torch.ones_like(area), torch.ones_like(area))
    ok = area > 0
    s = torch.as_tensor(scale, dtype=n.dtype, device=n.device)
    d = grad[:, :1] * torch.cross(n, dpdv, dim=-1) - grad[:, 1:] * torch.cross(n, dpdu, dim=-1)
    d = torch.where(ok, sigma * s * d / torch.where(ok, area, torch.ones_like(area)), torch.zeros_like(d))
    return torch.nn.functional.normalize(n + d, dim=-1)
