"""Texel addressing of a lat-long env map (Mitsuba's ``envmap`` convention), shared by the look-ups
that must agree bit for bit: `scenes.envmap.bilinear_lookup` (the reference),
`methods.core.cubemap.from_envmap` (compiled resampling) and `methods.ptt.fast.latlong_lookup`."""
from __future__ import annotations

import torch
from torch import Tensor

__all__ = ["bilinear_taps"]


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
