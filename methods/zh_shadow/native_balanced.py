"""`native_fused16`'s wide fused pass with its 64-pixel chunks handed out to the threads dynamically (session 46,
zh46; `ZHShadow.balanced_fused`).

`zh42p_fused_wide` splits its chunks of 64 pixels over the threads ``schedule(static, 1)``: at 2 threads thread 0
takes chunks 0, 2, 4, … — on a 256-pixel-wide image the same two 64-column stripes of every row — and thread 1 the
other two. The object samples (≈ 37 K of a bench frame's 262 K, the pass's costly part: a table dot each) sit where
the object is on screen, not evenly over the stripes: on the bench creature's P / VB / V frames (perf seeds) thread 1
took 56-59 % of them (e.g. 21,660 against 15,229), so the frame waited on it. Here the same loop with
``schedule(dynamic, CHUNKS)``: each pixel is still one thread's and computed by the same code (its samples summed in
the same order; the integer failure / specular counts summed), so the image is the same bits at any thread count and
any hand-out; only which thread takes which chunk changes.
"""
from __future__ import annotations

from methods.core import native
from methods.zh_shadow import native as zn
from methods.zh_shadow import native_fused16

# 64-pixel chunks a thread takes at a time (one 256-pixel row of the bench size: 256 hand-outs a frame)
CHUNKS = 4

_STATIC = "#pragma omp parallel for num_threads(nt) schedule(static, 1) reduction(+:nb, ns) if(nt > 1)"


def _source() -> str:
    src = native_fused16._WIDE_SOURCE
    assert src.count(_STATIC) == 1 and src.count("void zh42p_fused_wide(") == 1
    return src.replace(_STATIC, _STATIC.replace("schedule(static, 1)", f"schedule(dynamic, {CHUNKS})"), 1) \
        .replace("void zh42p_fused_wide(", "void zh46_fused_dyn(", 1)


_SOURCE = _source()
_SIGNATURES = {"zh46_fused_dyn": zn._FUSED_SIGNATURES["zh33p_fused"]}


def lib():
    """(library, `zh46_fused_dyn`) or None (no AVX-512, no compiler, switched off: `native_fused16.available`).
    Not cached here (`native.load` caches the build)."""
    if not native_fused16.available():
        return None
    flags = ("-ffp-contract=off", "-fopenmp", *native.isa_flags(), *zn._avx512_flags())
    lb = zn.load("zh46_fused_dyn", _SOURCE, _SIGNATURES, extra_flags=flags)
    return None if lb is None else (lb, lb.zh46_fused_dyn)
