"""Where in-out's per-tile pass (``methods.inout.native_sample``, `FAST` bit 256) spends a V frame: the
loop's C source with a thread-CPU clock read around its passes, and copies whose table rows or c are
redirected into L1 (issue 14, session 37).

    python -m benchmarks.inout_tiles --scene chess|creature [--frames 9] [--tile 2048] [--warm]
                                     [--variants base table table+c] [--precompute-code DIR]

Each variant is the loop's source with a few lines replaced (string replacement, built under its own
name by ``methods.core.native.load``; the module itself is not touched), run at 1 thread with ``FAST``
as the module has it (bit 256 must be set):

- ``base``: the passes as they are, timed: resolve (the front end, the samples' (face, cell) entries),
  group (the entries' vertex needs, counting sort), fill (per vertex its distinct nodes by ``rows_x``,
  the entries' X written), shade (each sample's B from its entry);
- ``table``: ``rows_x`` reads four table rows that stay in L1 instead of the vertex's nodes' rows (the
  same calls, wrong values);
- ``table+c``: and the vertex's c from L1 as well;
- ``norows``: no ``rows_x`` call (the fill's book-keeping alone: node tags, the entries' X written);
- ``front``: every sample dead after the front end (the G-buffer read along its layouts and ``frame_cells``).

``--fast N`` runs the loop with those ``FAST`` bits (default the module's).

Each frame's call is timed right after a fresh ``make_gbuffer`` (the perf suite's protocol; ``--warm``:
without it), variants alternating per frame; medians over frames 1.. of the call's process CPU and of
each pass's thread CPU (the clock reads, ~4 a tile, cost a little). The values of every variant but
``base`` are wrong by design.

Session 37 (ip37), chess bench V, 1 thread, cold, tiles of 2048 pixels, host at load ~7 (ms): base call
~11.6 (resolve 3.7, group 0.55, fill 5.5, shade 1.4; ~40·10³ ``rows_x`` calls, 155·10³ (vertex, node)
products); table: fill ~3.5; table+c: fill ~3.3, call ~9.2. So the fill's table rows cost ~2 ms as L2 → L1
traffic (1 KB a product), c ~0.2 ms (read once a tile, prefetched), and ~1.9 ms of the fill is its
per-vertex book-keeping (the nodes' tags, the entries' X written).

Session 41 (ip41), the same, FAST 4095, host at load 5-8 (ms): base call ~8.1-8.9 (resolve 2.7-2.9, group
0.45, fill 3.6-4.2, shade 1.0); table: fill ~2.1-2.3; norows: fill ~1.2-1.4; front: resolve ~0.87. So of the
resolve ~1.9 ms is its per-sample loop after the front end (face / region / live reads, the region check,
the (face, cell) hash, the weights written), the fill's table rows' traffic ~1.9 ms, ``rows_x``'s arithmetic
with rows in L1 ~0.9 ms, its book-keeping ~1.3 ms.
"""
from __future__ import annotations

import argparse
import ctypes
import statistics
import time

import torch

from benchmarks.common import inout_loop_state, settle
from methods.core import native
from methods.inout import native_sample as ns
from references.gbuffer import make_gbuffer

_CLOCK = ("static __thread tws tw;",
          "static __thread tws tw;\n#include <time.h>\nstatic __thread uint64_t tp[4];\n"
          "static inline uint64_t rdc(void) { struct timespec t; clock_gettime(CLOCK_THREAD_CPUTIME_ID, &t);"
          " return (uint64_t)t.tv_sec * 1000000000ull + (uint64_t)t.tv_nsec; }\n"
          "void tprof(int64_t *o) { for (int i = 0; i < 4; ++i) { o[i] = (int64_t)tp[i]; tp[i] = 0; } }\n"
          "static float l1t[16384] __attribute__((aligned(64))); static float l1c[4096] __attribute__((aligned(64)));\n")
_PASSES = [
    ("    /* (1) resolve */", "    uint64_t T0 = rdc();"),
    ("    for (int32_t e = 0; e < nE; ++e)\n        ht[ent[e].slot] = 0;",
     "    for (int32_t e = 0; e < nE; ++e)\n        ht[ent[e].slot] = 0;\n    uint64_t T1 = rdc(); tp[0] += T1 - T0;"),
    ("    for (int32_t it = 0; it < nI; ++it)\n        sorted[vcnt[item_lv[it]]++] = item_e[it];",
     "    for (int32_t it = 0; it < nI; ++it)\n        sorted[vcnt[item_lv[it]]++] = item_e[it];\n"
     "    uint64_t T1b = rdc(); tp[1] += T1b - T1;"),
    ("    /* (3) shade */", "    uint64_t T2 = rdc(); tp[2] += T2 - T1b;"),
    ("    *made_ += made;\n    *bad_ = bad;", "    *made_ += made;\n    *bad_ = bad; tp[3] += rdc() - T2;"),
]
_CALL = ("rows_x(sh + nodes[b] * K3, sh + nodes[b + 1] * K3, sh + nodes[b + 2] * K3, sh + nodes[b + 3] * K3, cv, K,\n"
         "                       xs + b, tree);")
_TABLE = (_CALL, _CALL.replace("sh + nodes[b] * K3, sh + nodes[b + 1] * K3, sh + nodes[b + 2] * K3, sh + nodes[b + 3] * K3",
                               "l1t, l1t + K3, l1t + 2 * K3, l1t + 3 * K3"))
_TABLE_C = (_CALL, _TABLE[1].replace("cv, K,", "l1c, K,"))


_NOROWS = (_CALL, ";")
_FRONT = ("            if (!A->live[q] || !(z_[i] > 0.0f)) {\n                sent[qi] = -1;",
          "            if (1) {\n                sent[qi] = -1;")


def variants() -> dict[str, list[tuple[str, str]]]:
    return {"base": [], "table": [_TABLE], "table+c": [_TABLE_C], "norows": [_NOROWS], "front": [_FRONT]}


def _build(name: str, reps: list[tuple[str, str]]):
    src = ns._SOURCE
    for old, new in [_CLOCK, *_PASSES, *reps]:
        if old not in src:
            raise SystemExit(f"the loop's source changed: {old!r} not found")
        src = src.replace(old, new)
    sig = dict(ns._SIGNATURES)
    sig["tprof"] = [ctypes.c_void_p]
    return native.load("inout_tiles_" + "".join(c for c in name if c.isalnum()), src, sig, extra_flags=ns._flags())


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--frames", type=int, default=9)
    ap.add_argument("--tile", type=int, default=ns.TILE)
    ap.add_argument("--fast", type=int, default=ns.FAST, help="the loop's FAST bits (default the module's)")
    ap.add_argument("--warm", action="store_true", help="no fresh G-buffer before each call")
    ap.add_argument("--variants", nargs="+", default=list(variants()))
    ap.add_argument("--precompute-code", default=None,
                    help="take the precomputation from the harness cache entry of the code in DIR")
    a = ap.parse_args(argv)
    if a.precompute_code:
        from reports import precompute_cache
        from reports.store import code_closure_fingerprint

        precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, a.precompute_code)
    if not a.fast & 256:
        raise SystemExit("native_sample.FAST has no bit 256 (the tiles)")
    torch.set_num_threads(1)
    table = variants()
    libs = {k: _build(k, table[k]) for k in a.variants}
    if any(lib is None for lib in libs.values()):
        raise SystemExit("the C loop is not available (no compiler or PRTBENCH_COMPILE=0)")
    scene, frames, gbs, m, st, cs = inout_loop_state(a.scene, a.size, a.frames)
    names = list(libs)
    mems = {k: ns.memo(st.voff[-1], ns.WINDOW) for k in names}
    T = {k: [] for k in names}
    P = {k: [] for k in names}
    stats = {}
    o = torch.zeros(4, dtype=torch.int64)
    saved = (ns._lib, ns.TILE, ns.FAST)
    try:
        ns.TILE, ns.FAST = a.tile, a.fast
        for i, (f, g) in enumerate(zip(frames, gbs)):
            cam = torch.tensor(f.camera.origin, dtype=torch.float32)
            for k in (names if i % 2 == 0 else names[::-1]):
                lib = libs[k]
                ns._lib = lambda lib=lib: lib
                settle()
                if not a.warm:
                    make_gbuffer(scene, f, 2)
                lib.tprof(o.data_ptr())
                c0 = time.process_time()
                _, s = ns.shade(st, cs, g.normal, g.wo, g.bary, g.face, g.region, g.hit, 4, cam, mems[k], i + 1,
                                ns.WINDOW)
                T[k].append(time.process_time() - c0)
                lib.tprof(o.data_ptr())
                P[k].append([float(x) / 1e6 for x in o.tolist()])
                stats[k] = s
    finally:
        ns._lib, ns.TILE, ns.FAST = saved
    print(f"{a.scene} {a.size} V, 1 thread, {a.frames} frames{'' if a.warm else ' (cold)'}, FAST {a.fast}, "
          f"tiles of {a.tile} pixels")
    res = {}
    for k in names:
        med = 1e3 * statistics.median(T[k][1:])
        parts = [statistics.median(p[j] for p in P[k][1:]) for j in range(4)]
        res[k] = {"median_ms": med, "resolve_ms": parts[0], "group_ms": parts[1], "fill_ms": parts[2],
                  "shade_ms": parts[3], "stats": stats[k]}
        print(f"{k:>8}  call {med:7.3f} ms  resolve {parts[0]:6.3f}  group {parts[1]:6.3f}  fill {parts[2]:6.3f}  "
              f"shade {parts[3]:6.3f}  (vertex, node) products {stats[k][0]}")
    return res


if __name__ == "__main__":
    main()
