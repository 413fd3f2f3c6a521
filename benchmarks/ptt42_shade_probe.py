"""What bounds the shading pass of a PTT shading="vertex" frame (issue 14, session 42, pt42): the very
``native.shade_mirror`` calls of real frames (chess / creature bench, the perf suite's V frames, seed 1, 2×2
samples), replayed through probe builds of this checkout's C source that each remove one part of the work:

    python -m benchmarks.ptt42_shade_probe [--scene chess] [--frames 5] [--rounds 9] [--flush-mb 64]

* ``real``: the source as it is;
* ``env_hot``: every sample's env cell replaced by its run's first (the four env rows in L1; cells still
  computed) — what the env rows' cache misses cost;
* ``face_hot``: every sample reads face 0's three pair rows (pair rows and face corners in L1) — what the
  per-sample gather of the pair (W_r / transfer) rows costs;
* ``both_hot``: both;
* ``no_cells``: the cells of the first run of each thread reused for every run (no acos / atan2 / G-buffer
  normal and wo reads after the first run; env rows then hot too) — ``env_hot`` minus this is the cells;
* ``cells_only``: the cells without the pixel loop.

Before every call ``--flush-mb`` MB are written (the harness's G-buffer and scoring between timed frames:
cold caches) and ``PRTBENCH_SETTLE`` idled; 1 thread; the variants alternate in rotating order. Prints the
median process-CPU ms of each and per sample ns.

Measured (session 42, host at load 2-7; ms, 262 144 samples a call): chess real 2.79-2.82 (10.7 ns a
sample), env_hot 2.29-2.34, face_hot 2.46-2.58, both_hot 1.84-1.88, no_cells 1.57, cells_only 0.74;
creature real 2.70 (10.3 ns), env_hot 2.43, face_hot 2.37, both_hot 1.86, no_cells 1.71, cells_only 0.75.
So of a cold pass: the env rows' misses 10-18 %, the pair-row gather (face corners + 3 rows a sample)
8-12 %, both ~33 %; the cells (acos / atan2 polynomials, the normal / wo reads) ~27 %; the rest (~1.1 ms,
~4 ns or ~14 cycles a sample with every row in L1) the pixel loop's arithmetic and loads. The W_r /
transfer rows are not gathered per sample (``vertex_rows`` reads them per referenced pair, ~0.5 ms a
frame); the pass streams ~41 bytes a sample (face 8, barycentrics 8, normal 12, wo 12, hit 1) plus the
gathers: latency / instruction bound, far from the bandwidth. ``frame_cost`` counts ~75 bytes a sample for
the whole chess V frame (19.8 MB; 60.8 MFLOP, the bound: 0.29 ms at 211 GFLOP/s)."""
from __future__ import annotations

import argparse
import collections
import statistics
import time

import torch

from benchmarks.common import precomputed, settle, setup
from methods.core import native as _core
from methods.ptt import native as N
from methods.ptt.method import PTT

PROBES = {
    "real": "",
    "env_hot": "#define PROBE_ENV_HOT 1\n",
    "face_hot": "#define PROBE_FACE_HOT 1\n",
    "both_hot": "#define PROBE_ENV_HOT 1\n#define PROBE_FACE_HOT 1\n",
    "no_cells": "#define PROBE_NO_CELLS 1\n",
    "cells_only": "#define PROBE_CELLS_ONLY 1\n",
}


def probe_source(defs: str) -> str:
    src = N._SOURCE
    a = "        cells(nrm, ns, nc, wo, ws, wc, mm, H, W, vacos, vatan2, w16, i0, (m + 7) / 8 * 8, r, fx, fy);\n"
    assert src.count(a) == 1
    b = ("#ifdef PROBE_NO_CELLS\n        if (a == p0)\n#endif\n" + a +
         "#ifdef PROBE_ENV_HOT\n        for (int64_t k = 1; k < m; ++k) r[k] = r[0];\n#endif\n"
         "#ifdef PROBE_CELLS_ONLY\n        out[3 * a] += r[0] + fx[m - 1];\n        continue;\n#endif\n")
    src = src.replace(a, b)
    f = "                int64_t f = face[i];\n"
    assert src.count(f) == 1
    src = src.replace(f, "#ifdef PROBE_FACE_HOT\n                int64_t f = face[0];\n#else\n" + f + "#endif\n")
    return defs + src


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--flush-mb", type=int, default=64)
    ap.add_argument("--precompute-of", default=None)   # another checkout whose precomputation to reuse
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    if a.precompute_of:
        from benchmarks.ptt_ab import base_fingerprint
        from reports import precompute_cache

        fp = base_fingerprint(a.precompute_of)
        precompute_cache._process_fingerprint = lambda module: fp
    scene, _, _, _ = setup(a.scene, "bench", kind="V", n_frames=1, spp_side=2)
    m, _ = precomputed(PTT, scene, {"light_res_1": 4})
    r = m.with_bounces(0).with_shading("vertex")
    _, frames, gbs, _ = setup(scene, "bench", kind="V", n_frames=a.frames, seed=1, spp_side=2)
    calls = []
    orig = N.shade_mirror

    def spy(*args):
        calls.append(args)
        return orig(*args)

    N.shade_mirror = spy
    import methods.ptt.method as _pm

    _pm.VIEW_FRAME = False  # the frames' shade_mirror calls as separate calls, to record them
    for i in range(a.frames):
        r.render(frames[i], gbs[i])
    N.shade_mirror = orig
    calls = calls[1:]
    libs = {k: N._functions(_core.load("ptt_probe", probe_source(d), N._SIGNATURES, extra_flags=N._EXTRA_FLAGS))
            for k, d in PROBES.items()}
    buf = torch.zeros(a.flush_mb << 18)
    res = collections.defaultdict(list)
    names = list(PROBES)
    ref = None
    for rnd in range(a.rounds):
        for j, name in enumerate(names[rnd % len(names):] + names[:rnd % len(names)]):
            for args in calls:
                N._kernel = lambda fn=libs[name]: fn
                buf.add_(1.0)
                settle()
                c0 = time.process_time()
                out = N.shade_mirror(*args)
                res[name].append(time.process_time() - c0)
                if name == "real":
                    ref = out if ref is None else ref
    n = int(calls[0][4].shape[0])
    print(f"{a.scene}: {len(calls)} calls x {a.rounds} rounds, {n} samples a call, 1 thread, flush {a.flush_mb} MB, "
          f"process CPU median:")
    base = statistics.median(res["real"])
    for k in names:
        t = statistics.median(res[k])
        print(f"  {k:10s} {1e3 * t:7.3f} ms  {1e9 * t / n:6.2f} ns/sample  ({t / base:5.2f} of real)")


if __name__ == "__main__":
    main()
