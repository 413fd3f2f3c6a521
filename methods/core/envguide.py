"""Env-map CDF search by a guide table (Pharr et al., PBRT 3 §13.3: the "guide"/cut-point method of
Chen and Asau 1974), for the oracle's env-map sampling (issue 14).

``scenes.envmap.count_le(cdf, x)`` (the number of CDF entries <= x, i.e. the sampled cell) is a
branchless binary search of ⌊log₂ C⌋ + 1 dependent loads (18 on a 256-row map). The guide table
``guide[b] = count_le(cdf, b / G)``, b = 0 … G, with G a power of two ≥ C, brackets the answer of any
x ∈ [b/G, (b+1)/G] (b = ⌊x·G⌋, exact in float64) between ``guide[b]`` and ``guide[b + 1]``; the
search then takes `GUIDE_STEPS` bisection steps inside the bracket (one load for the bracket, the
others within a few cache lines). A bracket wider than 2^GUIDE_STEPS − 1 cells (many near-empty
cells within 1/G of u: ≤ 1.3 % of u on the library maps), or an x outside [0, 1], is flagged and
searched again by ``count_le`` itself (`fix_unguided`): the result is exactly ``count_le``'s for
every x, so the samples stay bit-identical (``tests/methods/core/test_envguide.py``).

This module is core math (layer 0) and imports nothing from ``scenes``: the table is built by
``torch.searchsorted(cdf, edges, right=True)`` (``count_le``'s definition; the edges lie in [0, 1]),
and `fix_unguided` takes the caller's search. `sample_cells_at` repeats ``scenes.envmap.sample_cells`` after its search; making
``sample_cells`` call it would edit ``scenes/envmap.py``, whose bytes key every Mitsuba reference
(``references/cache.py``), so it waits for the next deliberate re-render.
"""
from __future__ import annotations

import math
import weakref

import torch
from torch import Tensor


# Bisection steps inside a guide bucket: brackets of up to 2^4 − 1 = 15 cells are searched in place.
GUIDE_STEPS = 4

_TABLES: dict[int, tuple] = {}  # id(cdf) → (weakref to cdf, guide table)


def guide_buckets(C: int) -> int:
    """Buckets G of the guide table of a C-entry CDF: the power of two ≥ C (≥ 2)."""
    return 1 << max(int(C) - 1, 1).bit_length()


def guide_table(cdf: Tensor) -> Tensor:
    """(G + 1,) int32 ``count_le(cdf, b / G)`` for b = 0 … G (`guide_buckets`), on cdf's device;
    cached per cdf tensor (``EnvMap._tables`` builds one per map, shared by its rotated copies)."""
    key = id(cdf)
    hit = _TABLES.get(key)
    if hit is not None and hit[0]() is cdf:
        return hit[1]
    G = guide_buckets(cdf.shape[0])
    edges = torch.arange(G + 1, dtype=torch.float64, device=cdf.device) / G  # exact: G a power of 2
    table = torch.searchsorted(cdf, edges, right=True).to(torch.int32)   # = count_le(cdf, edges)
    _TABLES[key] = (weakref.ref(cdf), table)
    weakref.finalize(cdf, _TABLES.pop, key, None)
    return table


def guided_count_le(x: Tensor, cdf: Tensor, guide: Tensor, steps: int = GUIDE_STEPS) -> tuple[Tensor, Tensor]:
    """``count_le(cdf, x)`` where ``ok``, by the guide table (`guide_table` of ``cdf``) and ``steps``
    bisection steps (a pure tensor function, compiled by its callers): → (k int64, ok bool), x's
    shape. Not ok (k then meaningless, in [0, C]): x outside [0, 1] (or NaN), or its bucket wider
    than 2^steps − 1 cells — `fix_unguided` searches those."""
    C, G = cdf.shape[0], guide.shape[0] - 1
    inside = (x >= 0) & (x <= 1)
    xs = torch.where(inside, x, torch.zeros_like(x))
    b = torch.floor(xs * G).to(torch.int64).clamp(0, G - 1)  # x = 1: the last bucket
    lo, hi = guide[b].to(torch.int64), guide[b + 1].to(torch.int64)
    k = lo  # count_le(cdf, x) ∈ [lo, hi]: cdf[hi] > (b + 1)/G ≥ x and cdf[lo − 1] ≤ b/G ≤ x
    step = 1 << (steps - 1)
    while step:
        j = (k + (step - 1)).clamp(max=C - 1)
        k = torch.where((k + step <= hi) & (cdf[j] <= xs), k + step, k)
        step >>= 1
    return k, inside & (hi - lo < (1 << steps))


def fix_unguided(k: Tensor, ok: Tensor, x: Tensor, cdf: Tensor, search) -> int:
    """Entries of k (contiguous) where not ``ok`` set to ``search(cdf, x.double())`` in place — the
    caller's CDF search, ``scenes.envmap.count_le`` for the oracle (passed in: the core imports
    nothing from ``scenes``), so that out-of-range and NaN x get exactly its answer (x: the same
    number of elements, any strides and float dtype: only the entries not ok are read and
    converted); → how many."""
    bad = torch.nonzero(~ok.reshape(-1)).squeeze(-1)
    if bad.numel():
        k.view(-1)[bad] = search(cdf, x.reshape(-1)[bad].double()).to(k.dtype)
    return int(bad.numel())


def sample_cells_at(k: Tensor, u: Tensor, cdf: Tensor, p_flat: Tensor, omega: Tensor, R: Tensor, H: int,
                    W: int) -> tuple[Tensor, Tensor]:
    """``scenes.envmap.sample_cells`` given its CDF search's result ``k`` (``count_le(cdf, u[..., 0])``,
    e.g. `guided_count_le` + `fix_unguided`): the same operations after the search, so the same
    directions and densities (float64)."""
    u0, u1 = u[..., 0].double(), u[..., 1].double()
    k = k.to(torch.int64).clamp(max=cdf.numel() - 1)
    lo = torch.where(k > 0, cdf[(k - 1).clamp_min(0)], torch.zeros_like(u0))
    pk = p_flat[k]
    r = ((u0 - lo) / pk.clamp_min(1e-300)).clamp(0.0, 1.0)
    iy, ix = k // W, k % W
    phi = 2 * math.pi * (ix.double() + 0.5 + r) / W
    z_top = torch.cos(math.pi * iy.double() / (H - 1))
    z_bot = torch.cos(math.pi * (iy.double() + 1) / (H - 1))
    zc = z_top - u1 * (z_top - z_bot)
    st = (1 - zc * zc).clamp_min(0).sqrt()
    d_local = torch.stack([torch.sin(phi) * st, zc, -torch.cos(phi) * st], -1)
    pdf = pk / omega[iy]
    return d_local @ R.T, pdf
