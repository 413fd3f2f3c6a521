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
  last row, the padding dropped) — one static shape per function. Other dimensions (vertex or
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
"""
from __future__ import annotations

import functools
import os
import warnings
from collections.abc import Callable, Sequence

import torch
from torch import Tensor

__all__ = ["CHUNK", "compile_enabled", "fused", "map_rows"]

# Rows per block of `map_rows`: large enough that a block's launch overhead (~20 µs) is small against
# its work, small enough that its temporaries stay in the L2 cache of one core.
CHUNK = 1 << 15


def compile_enabled() -> bool:
    """False when ``PRTBENCH_COMPILE=0`` (read at each call, so tests can switch it)."""
    return os.environ.get("PRTBENCH_COMPILE", "1").strip() not in ("0", "false", "no", "off")


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


def map_rows(fn: Callable, rows: Sequence[Tensor], args: Sequence = (), *, chunk: int = CHUNK):
    """``fn(*row_blocks, *args)`` over blocks of exactly ``chunk`` rows of the ``rows`` tensors
    (all with the same leading size Q), results (a tensor or a tuple of tensors with leading size
    equal to the block's) concatenated and trimmed to Q rows. The last block is padded by repeating
    the last row, so a compiled ``fn`` sees one shape (module docstring). Q = 0 calls ``fn`` once on
    the empty tensors (eagerly when ``fn`` is `fused`)."""
    if not rows:
        raise ValueError("map_rows needs at least one row tensor")
    q = int(rows[0].shape[0])
    if any(int(r.shape[0]) != q for r in rows):
        raise ValueError(f"row tensors differ in length: {[tuple(r.shape) for r in rows]}")
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    if q == 0:
        return getattr(fn, "eager", fn)(*rows, *args)
    outs = []
    for s in range(0, q, chunk):
        blk = [r[s:s + chunk] for r in rows]
        n = blk[0].shape[0]
        if n < chunk:
            blk = [torch.cat([b, b[-1:].expand(chunk - n, *b.shape[1:])]) for b in blk]
        o = fn(*blk, *args)
        outs.append(o[:n] if isinstance(o, Tensor) else tuple(x[:n] for x in o))
    if isinstance(outs[0], Tensor):
        return outs[0] if len(outs) == 1 else torch.cat(outs)
    return tuple(torch.cat(parts) if len(parts) > 1 else parts[0] for parts in zip(*outs))
