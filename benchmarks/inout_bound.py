"""What bounds in-out's per-sample C loop (``methods.inout.native_sample``): the loop against copies
of itself whose data loads are redirected into L1, alternating in one process (issue 14).

    python -m benchmarks.inout_bound --scene chess|creature [--frames 15] [--threads 1] [--warm]

Each variant is the loop's C source with a few lines replaced (string replacement, built under its own
name by ``methods.core.native.load``; the module itself is not touched), run with ``FAST`` as the module
has it but for the tiles' bits (256 | 512 | 1024, session 37: the per-sample loop is what these variants
edit; `benchmarks.inout_tiles` splits the tile passes). Variants (each adds to the one before, but the last):

- ``base``: the loop as it is;
- ``L1 table``: ``cell_x`` reads a 4 KB table (four rows of 3K floats) and a 1 KB c that stay in L1 instead
  of the frame's table rows and its vertices' c (the same calls, the same arithmetic, wrong values);
- ``+ c``: and the vertices' c from L1 as well;
- ``+ memo``: and the memo's rows read and written in a 16 KB block (their stamps still the real ones,
  so the same fills and exact entries as ``base``: the control flow is unchanged);
- ``no cell_x``: (from ``base``) no ``cell_x`` (its four X zeros): the look-ups (vertex records, stamps,
  memo rows, the (face, cell) cache) and everything else as in ``base``;
- ``no X``: every sample takes the last shaded sample's 12 X (no vertex record, stamp, memo row or
  ``cell_x`` at all: the G-buffer reads, ``frame_cells``, the checks, the (face, cell) cache look-ups
  and B's 36 multiply-adds only): the per-sample floor of this loop's structure.

Timed as ``benchmarks.inout_loop_ab``: the process CPU time of the ``shade`` call, each call right after
a fresh ``make_gbuffer`` of its frame (the perf suite's protocol; ``--warm``: without it), the variants'
order alternating per frame, medians over frames 1.. . The values of every variant but ``base`` are wrong
by design (only its time counts).

Session 36 (ip36), 1 thread, cold, 13 frames, host at load ~5 (ms; base/this per frame):

    variant     chess bench V        creature bench V
    base        14.79                 8.77
    L1 table    14.43 (1.19x)         8.45 (1.03x)
    + c         11.51 (1.27x)         8.45 (1.03x)
    + memo      10.85 (1.36x)         7.79 (1.13x)
    no cell_x    9.10 (1.66x)         7.25 (1.21x)
    no X         5.08 (2.91x)         4.51 (1.95x)

Issue 14's targets (55 GB/s) need the loop 1.45x (chess V <= 4.66 ms at 2 threads) and 1.67x (creature
V <= 3.54 ms): more than the loop gains with every table, c and memo-row load an L1 hit (1.36x / 1.13x).
Chess splits into the per-sample floor ~5.1 ms (the front end ~2.0 ms, then ~11.5 ns per sample: the
checks, the (face, cell) cache and B's 36 multiply-adds), the look-ups ~4.0 ms (94·10³ samples whose
(face, cell) differs from the last one's: cache entry, vertex records, stamps, memo rows) and `cell_x`
~5.7 ms (70.5·10³ calls, ~81 ns each: ~34 ns its arithmetic with every operand in L1 — 72 16-lane FMAs
and 90 loads at K = 88, near the core's throughput — and ~47 ns reaching its table rows in L2 / L3).
The work against the minimum (chess bench, frame 1: 262,144 shaded samples, 4,305 referenced vertices):
69.0·10³ distinct (vertex, cell) pairs (24.6·10³ outside their vertex's 8 x 8 window, on 1,744 vertices
whose samples' cells span more than the window: a better-placed window would not hold them), 124.5·10³
distinct (vertex, node) pairs, 7,260 distinct table nodes (5.9 MB of rows); the loop calls `cell_x`
1.02x per distinct (vertex, cell) pair, i.e. 282·10³ (vertex, node) products, 2.3x the distinct ones.

Tried in session 36 and dropped (chess bench V, 1 thread, cold, same process alternating, the same
bits): the next block's front end computed a block ahead (double buffers) 0.95x, and with it the table
rows of the next block's cells requested into L2 (a per-(slot, node) recency filter, 4 / 16 / 64 blocks)
0.81-0.86x / 0.90-0.93x / 0.79-0.83x; every table swept (prefetched or read) once before the loop
0.99-1.03x (noise): the table rows cost ~3 ms as L2 / L3 latency per `cell_x`, not as first touches.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.common import inout_loop_state, settle
from methods.core import native
from methods.inout import native_sample as ns
from references.gbuffer import make_gbuffer

_DUMMY = ("static float l1t[16384] __attribute__((aligned(64))); static float l1c[4096] __attribute__((aligned(64)));"
          " static float l1m[4096] __attribute__((aligned(64)));\n")
_ANCHOR = "typedef struct {\n    const float *nrm;"
_CALL = "cell_x(t, R * 3 * K, cv, K, x, (int)(A->fast >> 5 & 1));"
_TABLE = (_CALL, "cell_x(l1t, 6 * K, cv, K, x, (int)(A->fast >> 5 & 1));")
_TABLE_C = (_CALL, "cell_x(l1t, 6 * K, l1c, K, x, (int)(A->fast >> 5 & 1));")
_MEMO = ("                                float *m = A->memo + 4 * row;",
         "                                float *m = l1m + 4 * (row & 1023);")
# no `cell_x` (its four X zeros; the look-ups, stamps and memo rows as they are)
_NO_CELL = (_CALL, "memset(x, 0, 4 * sizeof(v4));")
# the X of a sample never computed: its entry's (or the last sample's) values taken as they are
_NO_X = ("                        if (!(have >> j & 1)) {\n                            have |= 1 << j;",
         "                        if (0) {\n                            have |= 1 << j;")


def variants() -> dict[str, list[tuple[str, str]]]:
    return {"base": [], "L1 table": [_TABLE], "+ c": [_TABLE_C], "+ memo": [_TABLE_C, _MEMO], "no cell_x": [_NO_CELL],
            "no X": [_NO_X]}


def _build(name: str, reps: list[tuple[str, str]]):
    src = ns._SOURCE
    if reps:
        src = src.replace(_ANCHOR, _DUMMY + _ANCHOR)
    for old, new in reps:
        if old not in src:
            raise SystemExit(f"the loop's source changed: {old!r} not found")
        src = src.replace(old, new)
    return native.load("inout_bound_" + "".join(c for c in name if c.isalnum()), src, ns._SIGNATURES,
                       extra_flags=ns._flags())


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--frames", type=int, default=15)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--warm", action="store_true", help="no fresh G-buffer before each call")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    libs = {k: _build(k, r) for k, r in variants().items()}
    if any(lib is None for lib in libs.values()):
        raise SystemExit("the C loop is not available (no compiler or PRTBENCH_COMPILE=0)")
    scene, frames, gbs, m, st, cs = inout_loop_state(a.scene, a.size, a.frames)
    names = list(libs)
    mems = {k: ns.memo(st.voff[-1], ns.WINDOW) for k in names}
    T: dict[str, list[float]] = {k: [] for k in names}
    stats = {}
    saved, fast = ns._lib, ns.FAST
    ns.FAST = fast & 255   # the per-sample loop (not the tiles)
    try:
        for i, (f, g) in enumerate(zip(frames, gbs)):
            cam = torch.tensor(f.camera.origin, dtype=torch.float32)
            for k in (names if i % 2 == 0 else names[::-1]):
                lib = libs[k]
                ns._lib = lambda lib=lib: lib
                settle()
                if not a.warm:
                    make_gbuffer(scene, f, 2)
                c0 = time.process_time()
                _, s = ns.shade(st, cs, g.normal, g.wo, g.bary, g.face, g.region, g.hit, 4, cam, mems[k], i + 1,
                                ns.WINDOW)
                T[k].append(time.process_time() - c0)
                stats[k] = s
    finally:
        ns._lib, ns.FAST = saved, fast
    print(f"{a.scene} {a.size} V, {a.threads} thread(s), {a.frames} frames{'' if a.warm else ' (cold)'}, FAST {fast & 255}")
    res = {}
    for k in names:
        med = 1e3 * statistics.median(T[k][1:])
        paired = statistics.median(x / y for x, y in zip(T["base"][1:], T[k][1:]))
        res[k] = {"median_ms": med, "paired": paired, "stats": stats[k]}
        print(f"{k:>10}  median {med:7.3f} ms  base/this per frame {paired:5.3f}  stats {stats[k]}")
    return res


if __name__ == "__main__":
    main()
