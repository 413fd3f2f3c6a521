"""In-out's per-sample C loop alone (``methods.inout.native_sample.shade``) under variants of its
switches, alternating in one process (issue 14: the V frames' run time).

    python -m benchmarks.inout_loop_ab --scene chess|creature [--frames 15] [--threads 1] [--cold]
                                       [--variants 63 15 63:10:12 ...] [--precompute-code DIR]

A variant is ``FAST[:YCACHE_LOG[:WINDOW[:TILE]]]`` (``native_sample``'s module constants; the ones
left out or empty default to the module's). The scene's bench V sequence (spp side 2) is precomputed under the
harness's cache (``benchmarks.common.precomputed``), frame 0 rendered once by ``InOut.render`` (c of
every vertex), then each frame's G-buffer is shaded by every variant, the order alternating per
frame, each with its own memo (``native_sample.memo``) and frame stamps, after ``settle()`` (the
host's idle) and, with ``--cold``, right after a fresh ``make_gbuffer`` of the frame (the perf
suite's protocol: caches cooled by the rasteriser). Timed: the process CPU time of the ``shade``
call (all threads; at 1 thread the loop's own time). Prints per variant the median and min ms over
frames 1.. (frame 0 fills the memo's pages), its stats (memo rows computed, entries summed exactly,
first sample of a foreign face), each variant's ratio against the first, and the largest pixel
difference against the first variant (0 when the variants are the same bits).

Written in session 34 (ip34, from ip33's scratch script) to take the loop apart. What it measured
(chess bench V, 1 thread, process CPU, host at load 5-6; the loop ~13.5 ms a frame there, FAST 63):
- the loop's front end alone (G-buffer read along its layouts, ``frame_cells``) ~1.8 ms; one more
  pass over the samples that only visits each shaded sample's 3 vertices (face row, vertex record,
  window test, a bit per (vertex, cell) in the record) ~5.3-5.9 ms: visiting the vertices per sample
  costs ~3.5-4 ms by itself, so any scheme with a second pass over the samples pays that again;
- the memo fills and the entries outside the window (``cell_x``, ~70·10³ calls) ~4 ms; computing
  instead only the distinct (vertex, node) X of the marked cells (82·10³ rows instead of 162·10³),
  vertex by vertex before the shading pass: 3.7 ms, i.e. per row ~1.9x the in-loop cost (so the
  fills are bound by reaching the table rows and c, not by their arithmetic); the same with the
  vertices sorted by window origin (the same table rows one after another) 1.06x slower;
- the whole two-pass loop (mark, per-vertex fill, a shading pass reading the filled memo without
  stamps, the same bits) 0.73-0.76x of FAST 63.
Also dropped (same bits, the same process): each (vertex, cell)'s 12 X and stamp in one cache line
(a cell-major memo, 34 MB on chess) 0.84x; the pixels in tiles of 8x8 / 16x4 instead of image rows
0.92x / 0.97x; the 4 table rows and c prefetched at the start of ``cell_x`` 0.87x; W = 10 / 12
0.99x / 0.97x (entries outside the window 30 -> 22 / 17·10³). perf (cpu-clock, FAST 63): ``cell_x``'s
loads ~25 % of the loop, the memo stamps' loads ~8 %, B's sum (the memo rows' loads) ~8 %, the
(face, cell) cache ~4 %, the region check (G-buffer face and region) ~3 %.
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.common import inout_loop_state, settle
from methods.inout import native_sample as ns
from references.gbuffer import make_gbuffer


# the module's constants as imported (a variant's left-out fields; not the last variant's values)
_DEFAULTS = (ns.YCACHE_LOG, ns.WINDOW, ns.TILE)


def _variant(spec: str) -> tuple[int, int, int, int]:
    parts = [int(x) if x else None for x in spec.split(":")]
    parts += [None] * (4 - len(parts))
    fast = parts[0]
    ylog, W, tile = (d if x is None else x for x, d in zip(parts[1:], _DEFAULTS))
    return fast, ylog, W, tile


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--frames", type=int, default=15)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cold", action="store_true", help="make the frame's G-buffer right before each call")
    ap.add_argument("--variants", nargs="+", default=[str(ns.FAST), "15"])
    ap.add_argument("--precompute-code", default=None,
                    help="take the precomputation from the harness cache entry of the code in DIR (a base checkout)")
    a = ap.parse_args(argv)
    if a.precompute_code:
        from reports import precompute_cache
        from reports.store import code_closure_fingerprint

        precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, a.precompute_code)
    torch.set_num_threads(a.threads)
    if not ns.available():
        raise SystemExit("the C loop is not available (no compiler or PRTBENCH_COMPILE=0)")
    scene, frames, gbs, m, st, cs = inout_loop_state(a.scene, a.size, a.frames)
    nv = st.voff[-1]
    saved = (ns.FAST, ns.YCACHE_LOG, ns.TILE)
    variants = list(dict.fromkeys(a.variants))
    mems = {v: ns.memo(nv, _variant(v)[2]) for v in variants}
    stamp = {v: 0 for v in variants}
    T: dict[str, list[float]] = {v: [] for v in variants}
    stats, imgs, diff = {}, {}, 0.0
    try:
        for i, (f, g) in enumerate(zip(frames, gbs)):
            cam = torch.tensor(f.camera.origin, dtype=torch.float32)
            for v in (variants if i % 2 == 0 else variants[::-1]):
                ns.FAST, ns.YCACHE_LOG, W, ns.TILE = _variant(v)
                stamp[v] += 1
                settle()
                if a.cold:
                    make_gbuffer(scene, f, 2)
                c0 = time.process_time()
                out, s = ns.shade(st, cs, g.normal, g.wo, g.bary, g.face, g.region, g.hit, 4, cam, mems[v], stamp[v], W)
                T[v].append(time.process_time() - c0)
                stats[v], imgs[v] = s, out
            diff = max(diff, *(float((imgs[v] - imgs[variants[0]]).abs().max()) for v in variants))
    finally:
        ns.FAST, ns.YCACHE_LOG, ns.TILE = saved
    peak = float(imgs[variants[0]].abs().max())
    print(f"{a.scene} {a.size} V, {a.threads} thread(s), {a.frames} frames{' (cold)' if a.cold else ''}; "
          f"max |d| against {variants[0]}: {diff:.3g} (peak {peak:.3g})")
    res = {}
    for v in variants:
        med, lo = 1e3 * statistics.median(T[v][1:]), 1e3 * min(T[v][1:])
        ratio = statistics.median(T[variants[0]][1:]) / statistics.median(T[v][1:])
        # the same frame's two calls (alternating order): drift between frames cancels
        paired = statistics.median(x / y for x, y in zip(T[variants[0]][1:], T[v][1:]))
        res[v] = {"median_ms": med, "min_ms": lo, "stats": stats[v], "ratio": ratio, "paired": paired}
        print(f"{v:>12}  median {med:7.3f} ms  min {lo:7.3f} ms  {variants[0]}/{v} {ratio:5.3f} "
              f"(per frame {paired:5.3f})  stats {stats[v]}")
    return {"variants": res, "max_diff": diff, "peak": peak}


if __name__ == "__main__":
    main()
