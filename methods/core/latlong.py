"""Texel addressing of a lat-long env map (Mitsuba's ``envmap`` convention), shared by the look-ups
that must agree bit for bit: `scenes.envmap.bilinear_lookup` (the reference), triple product's projection,
`methods.core.cubemap.from_envmap` (compiled resampling) and `methods.ptt.fast.latlong_lookup`."""
from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["bilinear_taps", "planar_bilinear", "planar_radiance", "quad_taps", "quad_texels"]


def bilinear_taps(u: Tensor, v: Tensor, H: int, W: int) -> tuple[Tensor, Tensor, Tensor]:
    """The bilinear footprint of lat-long coordinates (u, v) (``scenes.envmap.direction_to_uv``) in
    an H × W map: texel columns are centred (half-texel shift in u), u wraps, rows span the poles.

    Returns:
        idx: flat index of the top-left tap in the periodic-extended (H, W + 1) table
            (``scenes.envmap.extend_periodic``); the other taps are idx + 1, idx + W + 1, idx + W + 2.
        fx, fy: the fractional weights of the right / lower taps.
    """
    u = u - 0.5 / W
    u = u - torch.floor(u)
    v = v - torch.floor(v)
    x, y = u * W, v * (H - 1)
    ix = x.to(torch.int64).clamp(max=W - 1)
    iy = y.to(torch.int64).clamp(max=H - 2)
    return iy * (W + 1) + ix, x - ix, y - iy


def planar_radiance(x: Tensor, y: Tensor, z: Tensor, planes: Tensor, H: int, W: int) -> list[Tensor]:
    """Mitsuba's bilinear env-map radiance at emitter-frame direction components (x, y, z) (any one
    shape), per channel: op for op `scenes.envmap.bilinear_lookup` (``direction_to_uv``,
    `bilinear_taps`, the same tap order), on channel planes so that a compiled loop runs over the
    directions (vectorised atan2 / acos). planes: (3, H·(W + 1)) the periodic-extended texels
    (``EnvMap.periodic_texels(planes=True)``). Returns three tensors of x's shape (R, G, B)."""
    u = torch.atan2(x, -z) * (0.5 / math.pi)
    v = torch.acos(y.clamp(-1.0, 1.0)) * (1.0 / math.pi)
    return planar_bilinear(u, v, planes, H, W)


def planar_bilinear(u: Tensor, v: Tensor, planes: Tensor, H: int, W: int) -> list[Tensor]:
    """The second half of `planar_radiance`: the bilinear look-up at lat-long coordinates (u, v) (any
    one shape; ``scenes.envmap.direction_to_uv``) on channel planes (3, H·(W + 1)). Returns (R, G, B)."""
    idx, fx, fy = bilinear_taps(u, v, H, W)
    w0x, w0y = 1.0 - fx, 1.0 - fy
    out = []
    for c in range(3):
        e = planes[c]
        v0 = w0x * e[idx] + fx * e[idx + 1]
        v1 = w0x * e[idx + W + 1] + fx * e[idx + W + 2]
        out.append(w0y * v0 + fy * v1)
    return out


# -- quad look-ups: the four taps of a footprint as one contiguous row ------------------------------
#
# A compiled loop vectorised over samples turns every texel load of `planar_bilinear` into 16 scalar
# loads (12 per sample: 4 taps × RGB). `quad_texels` stores, for every top-left tap, the 12 values
# its footprint reads in one 64-byte row, so a loop vectorised over that row loads them with one
# vector load per sample; `quad_taps` gives the footprint (int32, clamped on both sides so that the
# compiled code needs no negative-index wrap).


def quad_taps(u: Tensor, v: Tensor, H: int, W: int) -> tuple[Tensor, Tensor, Tensor]:
    """`bilinear_taps` with int32 indices clamped to the table on both sides (u − ⌊u⌋ ≥ 0, so the
    lower clamp changes no value): idx (a row of `quad_texels`), fx, fy."""
    u = u - 0.5 / W
    u = u - torch.floor(u)
    v = v - torch.floor(v)
    x, y = u * W, v * (H - 1)
    ix = x.to(torch.int32).clamp(0, W - 1)
    iy = y.to(torch.int32).clamp(0, H - 2)
    return iy * (W + 1) + ix, x - ix, y - iy


QUAD = 16  # values per `quad_texels` row: 4 taps × 3 channels, 4 zeros


def quad_texels(planes: Tensor, H: int, W: int) -> Tensor:
    """(H·(W + 1), 16) rows of the periodic-extended channel planes (3, H·(W + 1)): row i holds, at
    4c + t, channel c of tap t = (i, i + 1, i + W + 1, i + W + 2) (`bilinear_taps`' order: top-left,
    top-right, bottom-left, bottom-right), then 4 zeros. Rows past the last `quad_taps` index read
    zeros beyond the map (never used)."""
    n = planes.shape[1]
    pad = torch.cat([planes, planes.new_zeros(3, W + 2)], 1)
    out = planes.new_zeros(n, QUAD)
    for t, off in enumerate((0, 1, W + 1, W + 2)):
        out[:, t:12:4] = pad[:, off:off + n].T
    return out.contiguous()


def quad_lanes(device=None) -> Tensor:
    """(4, 16) lane constants of `quad_lane_weights`: rows 1 − dx, 2dx − 1, 1 − dy, 2dy − 1 of lane
    4c + t's tap offset (dx, dy) = (t % 2, t // 2). Passed to compiled loops as a tensor (an
    in-graph iota over the lanes kept Inductor from vectorising along them)."""
    lane = torch.arange(QUAD, device=device)
    dx, dy = (lane % 2).float(), (lane % 4 // 2).float()
    return torch.stack([1.0 - dx, 2.0 * dx - 1.0, 1.0 - dy, 2.0 * dy - 1.0])


def quad_lane_weights(fx: Tensor, fy: Tensor, lanes: Tensor) -> Tensor:
    """Bilinear weights (..., 16) of footprints (fx, fy) (...) laid out as a `quad_texels` row:
    lane 4c + t gets tap t's weight ((1 − fx)(1 − fy), fx(1 − fy), (1 − fx)fy, fx·fy); lanes 12-15
    a finite value (their texels are 0). lanes: `quad_lanes`."""
    wx = lanes[0] + lanes[1] * fx[..., None]                             # 1 − fx or fx
    wy = lanes[2] + lanes[3] * fy[..., None]
    return wx * wy
