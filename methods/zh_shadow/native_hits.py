"""Whether every sample of a G-buffer hits, by one serial C scan of its hit bytes (session 46, zh46;
`ZHShadow.bound_glue`'s `_render` step).

`method._all` asks torch for the minimum of the (P,) bool bytes: at bench size a threaded reduction of 262 K bytes,
~0.045 ms of a ~2.5 ms P frame at 2 threads with the caches cold (the pool woken for a few microseconds of work).
`all_hit` reads the same bytes once, 64 at a time, and stops at the first zero byte: the same answer for any bool
array (a bool byte is 0 or 1, so "the minimum is 1" is "no byte is 0").
"""
from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from methods.zh_shadow import native as zn

_SOURCE = r"""
#include <stdint.h>

/* 1 when none of the n bytes of m is 0, else 0 (the blocks of 64 and-ed, the first block holding a 0 ends the scan) */
int64_t zh46_all(const uint8_t *m, int64_t n) {
    int64_t i = 0;
    for (; i + 64 <= n; i += 64) {
        uint8_t z = 0;
        for (int j = 0; j < 64; ++j) z |= (uint8_t)(m[i + j] == 0);
        if (z) return 0;
    }
    for (; i < n; ++i)
        if (m[i] == 0) return 0;
    return 1;
}
"""
_SIGNATURES = {"zh46_all": [ctypes.c_void_p, ctypes.c_int64]}


def _lib():
    """The library or None (`native.switched_load`: no compiler, ``PRTBENCH_COMPILE=0``, ``PRTBENCH_ZH_NATIVE=0``)."""
    lib = zn.switched_load("zh46_all", _SOURCE, _SIGNATURES)
    if lib is not None:
        lib.zh46_all.restype = ctypes.c_int64
    return lib


def all_hit(mask: Tensor, fn=None) -> bool | None:
    """``bool(mask.all())`` of a (P,) contiguous CPU bool tensor by `zh46_all` (``fn``: that C function, resolved by
    the caller; else looked up), or None where it does not run (no library, another dtype, layout or device)."""
    if mask.dtype != torch.bool or mask.device.type != "cpu" or not mask.is_contiguous():
        return None
    if fn is None:
        lib = _lib()
        if lib is None:
            return None
        fn = lib.zh46_all
    n = mask.numel()
    return True if n == 0 else bool(fn(mask.data_ptr(), n))
