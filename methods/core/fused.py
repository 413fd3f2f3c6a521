"""Fused run-time kernels (issue 14): a chain of elementwise and gather passes over a frame's
samples compiled into one loop by ``torch.compile`` (Inductor), eager torch where that is not
possible.

Why: an eager torch op makes one pass over its (Q, ...) operands and allocates its result, so a
per-sample stage of n ops over a 256² × 4 frame streams ~n × Q × 12 bytes and pays n kernel launches;
the Gouraud resolve alone (gather 3 vertex colours, weight, sum) takes 3.6 ms eager on this 2-core
machine against 0.32 ms of compulsory bytes at triad bandwidth (9 %), 0.55-0.7 ms compiled
(``benchmarks/fused.py``). The compiled kernel computes the same arithmetic in the same order per
output element (sums over a handful of terms are unrolled, not split over threads), so it equals
the eager function to float32 round-off; methods keep their eager reference paths as the test
oracle and tests compare the two.

Decisions (measured with ``benchmarks/fused.py``):

* Shapes: the sample count of a frame varies; Inductor's kernels with a *symbolic* row count ran
  20-30× slower than with a static one (16 ms vs 0.55 ms for the resolve above), so `map_rows` calls
  the compiled function on blocks of exactly ``chunk`` rows (the last block padded by repeating its
  last row, the padding dropped) — one static shape per function. This holds for memory-bound
  kernels like that resolve; it is not a rule for every kernel: the triple product's per-pixel
  look-ups and eq. 7 products (compute-bound, `methods/triple_product/fast_eval.py`, session 18) run
  faster as one call with a symbolic row count (``maybe_mark_dynamic``) than as static blocks whose
  results are copied and concatenated (1.08-1.12× per frame), so measure per kernel. Other dimensions (vertex or
  table counts) are NOT made symbolic by themselves with ``dynamic=False``: every new size
  recompiles (up to `RECOMPILE_LIMIT` variants per function; past it `fused` warns and runs that
  function eagerly). A caller whose tables take many sizes marks those dimensions with
  ``torch._dynamo.maybe_mark_dynamic`` (found by the helpers who fused PTT, in-out and triple
  product: with Dynamo's default limit of 8 the fallback was silent, and a study's worker and its
  parent process differed in round-off).
* Threads: ``cpp.dynamic_threads`` — a kernel uses the thread count at the call, not at the
  compilation (otherwise a kernel compiled under ``torch_threads(1)`` would stay on one thread).
  Each output element is computed by one thread, so results do not depend on the count
  (``tests/methods/test_threads.py`` checks every method).
* Off switch: ``PRTBENCH_COMPILE=0`` runs every fused function eagerly (same numbers to round-off);
  a compilation that fails (no C++ compiler, an unsupported op) warns once and falls back to eager
  for that function. The first call of each function compiles (seconds; Inductor caches the code on
  disk, keyed by the thread count) — it lands in a method's warm-up frame, which the harness
  excludes from the frame-time median, and tests see it as test time.
* Block sizes met later (`warming`, `warm_blocks`): a caller whose block follows a per-frame count
  (`pow2_block`: the count rounded up to a power of two) compiles a new variant the first time a
  frame's count lands in a new size class — a re-trace (0.2-0.8 s with Inductor's disk cache warm,
  seconds cold) inside a *timed* frame. Measured in session 13's perf run: in-out per sample creature
  V frames 2-3 at 264 / 270 ms against 65-75 ms, PTT chess V frame 4 at 783 ms against 13 ms. The
  harness renders its untimed warm-up frame inside ``warming()``; there `warm_blocks` also compiles
  the neighbouring size classes (×4 either way, `neighbour_blocks`) of every kernel call it sees, on
  dummy blocks made of the call's first row, so later frames find their variant compiled — as an
  interactive application compiles its kernels at load time. Outside ``warming()`` it does nothing
  (tests and studies pay no extra compilations). Rows are made contiguous first (`map_rows`), so
  a strided row tensor does not compile a second, padded-block variant (in-out's window columns
  did: ``ax`` stride 3 in full blocks, 1 in the padded last one).
"""
from __future__ import annotations

import contextlib
import functools
import warnings
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

from methods.core import switches

__all__ = ["CHUNK", "call_rows", "compile_enabled", "fused", "map_rows", "neighbour_blocks", "pow2_block", "warm_blocks", "warming"]

# Rows per block of `map_rows`: large enough that a block's launch overhead (~20 µs) is small against
# its work, small enough that its temporaries stay in the L2 cache of one core.
CHUNK = 1 << 15


def compile_enabled() -> bool:
    """False when ``PRTBENCH_COMPILE`` is 0 / false / no / off (`switches.on`: read at each call, so tests
    can switch it; any case since session 43)."""
    return switches.on("PRTBENCH_COMPILE")


# Compiled variants kept per function (one per distinct static shape signature; see the module
# docstring). Dynamo's default (8) is reached by a study's ladder of table sizes; past the limit
# Dynamo raises here (``fail_on_recompile_limit_hit``) instead of silently running eagerly, so
# `fused` warns and falls back for that function in this process — never a silent mix of compiled
# and eager round-off between processes of one run.
RECOMPILE_LIMIT = 64


def _configure_inductor() -> None:
    import torch._dynamo.config as dc
    import torch._inductor.config as ic

    ic.cpp.dynamic_threads = True
    dc.recompile_limit = max(int(dc.recompile_limit), RECOMPILE_LIMIT)
    dc.fail_on_recompile_limit_hit = True


def fused(fn: Callable, *, options: dict | None = None) -> Callable:
    """``fn`` compiled with ``torch.compile`` on first use (module docstring); ``.eager`` is ``fn``.

    ``fn`` must be a pure tensor function (no Python side effects, no data-dependent Python control
    flow) so that it compiles as one graph (``fullgraph=True``). ``options``: Inductor settings for
    this function only (``torch.compile(options=...)``), e.g. ``{"cpp.enable_tiling_heuristics":
    False}``: Inductor's heuristics otherwise leave a loop whose loads are all strided (the
    components of (Q, 3) arrays) scalar, with scalar libm transcendentals (measured 8x slower for
    ``ptt.fast.mirror_uv``); or ``{"assert_indirect_indexing": False}`` for a kernel whose gather
    indices are clamped into range by construction."""
    state: dict = {"compiled": None, "failed": False}

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        if state["failed"] or not compile_enabled():
            return fn(*args, **kwargs)
        if state["compiled"] is None:
            _configure_inductor()
            state["compiled"] = torch.compile(fn, fullgraph=True, dynamic=False, options=options)
        try:
            return state["compiled"](*args, **kwargs)
        except Exception as e:  # noqa: BLE001 — decided below: a compilation problem or bad input
            out = fn(*args, **kwargs)   # bad input raises here, with the eager function's message
            state["failed"] = True
            warnings.warn(f"prtbench: could not compile {fn.__qualname__} ({type(e).__name__}: {e}); "
                          "running it eagerly", RuntimeWarning, stacklevel=2)
            return out

    wrapper.eager = fn  # type: ignore[attr-defined]
    return wrapper


def map_rows(fn: Callable, rows: Sequence[Tensor], args: Sequence = (), *, chunk: int = CHUNK,
             warm: Sequence[int] = (), out=None):
    """``fn(*row_blocks, *args)`` over blocks of exactly ``chunk`` rows of the ``rows`` tensors
    (all with the same leading size Q), results (a tensor or a tuple of tensors with leading size
    equal to the block's) concatenated and trimmed to Q rows. The last block is padded by repeating
    the last row, so a compiled ``fn`` sees one shape (module docstring). Q = 0 calls ``fn`` once on
    the empty tensors (eagerly when ``fn`` is `fused`). ``warm``: other block sizes this call's
    kernels may meet in later frames (`neighbour_blocks`), compiled now when the harness is
    `warming` (`warm_blocks`). ``out``: a tensor (or a tuple matching ``fn``'s results) with Q
    leading rows; each block's results are written into its rows instead of concatenated (no copy
    of the whole result), and ``out`` is returned."""
    if not rows:
        raise ValueError("map_rows needs at least one row tensor")
    rows = [r.contiguous() for r in rows]  # one stride pattern for full and padded blocks (module docstring)
    q = int(rows[0].shape[0])
    if any(int(r.shape[0]) != q for r in rows):
        raise ValueError(f"row tensors differ in length: {[tuple(r.shape) for r in rows]}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    if q == 0:
        return out if out is not None else getattr(fn, "eager", fn)(*rows, *args)
    if warm:
        warm_blocks(fn, rows, args, [b for b in warm if b != chunk])
    outs = []
    for s in range(0, q, chunk):
        blk = [r[s:s + chunk] for r in rows]
        n = blk[0].shape[0]
        if n < chunk:
            blk = [torch.cat([b, b[-1:].expand(chunk - n, *b.shape[1:])]) for b in blk]
        o = fn(*blk, *args)
        if out is None:
            outs.append(o[:n] if isinstance(o, Tensor) else tuple(x[:n] for x in o))
        elif isinstance(out, Tensor):
            out[s:s + n] = o[:n]
        else:
            for dst, x in zip(out, o):
                dst[s:s + n] = x[:n]
    if out is not None:
        return out
    if isinstance(outs[0], Tensor):
        return outs[0] if len(outs) == 1 else torch.cat(outs)
    return tuple(torch.cat(parts) if len(parts) > 1 else parts[0] for parts in zip(*outs))


def call_rows(fn: Callable, rows: Sequence[Tensor], args: Sequence = ()):
    """``fn(*rows, *args)`` in ONE call over all Q rows of the ``rows`` tensors (same leading size),
    Q marked symbolic (``torch._dynamo.maybe_mark_dynamic``): one compiled variant serves every
    count — for compute-bound kernels, where a call per static block of `map_rows` costs more than
    the symbolic shape (module docstring, "Shapes"). Dynamo specialises sizes 0 and 1, which would
    compile a variant in a timed frame: Q = 1 is padded to 2 rows by repeating the row, and the
    results (a tensor or a tuple of tensors with Q leading rows) trimmed back; Q = 0 calls ``fn``
    on the empty tensors, eagerly when ``fn`` is `fused` (as `map_rows`)."""
    if not rows:
        raise ValueError("call_rows needs at least one row tensor")
    q = int(rows[0].shape[0])
    if any(int(r.shape[0]) != q for r in rows):
        raise ValueError(f"row tensors differ in length: {[tuple(r.shape) for r in rows]}")
    if q == 0:
        return getattr(fn, "eager", fn)(*rows, *args)
    rows = [(r if q >= 2 else r.expand(2, *r.shape[1:])).contiguous() for r in rows]
    for r in rows:
        torch._dynamo.maybe_mark_dynamic(r, 0)
    o = fn(*rows, *args)
    if q >= 2:
        return o
    return o[:q] if isinstance(o, Tensor) else tuple(x[:q] for x in o)


# -- block sizes that follow a per-frame count (module docstring) --------------------------------------

_warming = False
_warmed: set = set()


@contextlib.contextmanager
def warming(on: bool = True):
    """Within the block, `warm_blocks` compiles the block sizes it is given (the harness wraps its
    untimed warm-up frame in it, `reports.measure_cell`). Not thread-safe: one frame at a time."""
    global _warming
    prev, _warming = _warming, bool(on)
    try:
        yield
    finally:
        _warming = prev


def pow2_block(q: int, lo: int, hi: int) -> int:
    """Rows per static block for q rows: q rounded up to a power of two, clamped to [lo, hi]
    (powers of two themselves): few size classes, so few compiled variants."""
    return min(hi, max(lo, 1 << max(int(q) - 1, 0).bit_length()))


def neighbour_blocks(block: int, lo: int, hi: int, span: int = 4) -> tuple[int, ...]:
    """The power-of-two block sizes within ``span`` times ``block`` either way, clamped to [lo, hi]:
    what `warm_blocks` compiles besides ``block`` (a frame's count rarely moves 4× from the warm-up
    frame's within a sequence; each size costs a compilation in the warm-up frame)."""
    out, b = [], max(lo, block // span)
    while b <= min(hi, block * span):
        out.append(b)
        b *= 2
    return tuple(out)


def _signature(t) -> object:
    """What a compiled variant is specialised on, as far as `warm_blocks` needs: a tensor's dtype,
    device and sizes (None for dimensions marked dynamic), any other argument itself when hashable."""
    if isinstance(t, Tensor):
        dyn = getattr(t, "_dynamo_weak_dynamic_indices", set()) | getattr(t, "_dynamo_dynamic_indices", set())
        return (t.dtype, t.device.type, tuple(None if i in dyn else int(n) for i, n in enumerate(t.shape)))
    try:
        hash(t)
        return t
    except TypeError:
        return type(t).__name__


def warm_blocks(fn: Callable, rows: Sequence[Tensor], args: Sequence, sizes: Sequence[int]) -> int:
    """While `warming`: ``fn(*blocks, *args)`` once for each block size in ``sizes``, the blocks made
    of the first row of each of ``rows`` (valid input: a real row, repeated — as `map_rows` pads),
    the results dropped; once per (``fn``, argument signature) in the process. ``fn``: a `fused`
    function or a function of one block that calls such kernels (keyed by its code, so a closure
    made per call counts once; the same code in another file does not). Returns the number of
    warm-up calls made (0 outside `warming`)."""
    if not _warming or not sizes or not compile_enabled() or not rows or int(rows[0].shape[0]) == 0:
        return 0
    code = getattr(getattr(fn, "eager", fn), "__code__", None)
    # (the file name too: code objects compare equal across files, so in a same-process A/B the
    # baseline checkout's copy of a function would count as the new copy's warm-up — session 18)
    key = ((code, code.co_filename) if code is not None else id(fn), tuple(_signature(r[:0]) for r in rows),
           tuple(_signature(a) for a in args), tuple(sizes))
    if key in _warmed:
        return 0
    _warmed.add(key)
    for b in sizes:
        fn(*[r[:1].expand(b, *r.shape[1:]).contiguous() for r in rows], *args)
    return len(sizes)
