"""Texel addressing of a lat-long env map (Mitsuba's ``envmap`` convention), shared by the look-ups
that must agree bit for bit: `scenes.envmap.bilinear_lookup` (the reference), triple product's projection,
`methods.core.cubemap.from_envmap` (compiled resampling) and `methods.ptt.fast.latlong_lookup`."""
from __future__ import annotations

import math

import torch
from torch import Tensor

__all__ = ["bilinear_taps", "planar_bilinear", "planar_radiance"]


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
