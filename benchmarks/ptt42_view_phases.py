"""The phases of a PTT shading="vertex" frame's one-call view stage (``native.view_frame``, session 42, pt42)
and which of them run serial at 2 threads: the very calls of real frames (chess / creature bench, the perf
suite's V or VB frames, seed 1, 2×2 samples) replayed at 1 thread through probe builds of this checkout's C
source that stop after each phase:

    python -m benchmarks.ptt42_view_phases [--scene chess] [--kind V] [--frames 5] [--rounds 9]

* ``mark``: the parallel pass over the samples (face marks, the hit / face -1 contract);
* ``+sel``: the serial merge of the threads' marks, the pairs' marks and the sorted pair list;
* ``+rows``: the referenced pairs' rows (``vrows``, parallel over the pairs);
* ``+shade`` (the whole call): the cells and pixels (``shade_mirror``, parallel over the pixels).

Before every call 64 MB are written (the harness's G-buffer and scoring: cold caches) and
``PRTBENCH_SETTLE`` idled; the variants alternate. Prints the median process-CPU ms of each cumulative stop
and the differences (each phase's own time). With the frame's time outside C (`benchmarks.ptt42_glue`-style:
``--glue`` wraps the C call and reports the frame's wall time minus it) the serial part of a 2-thread frame is
glue + ``+sel`` − ``mark``."""
from __future__ import annotations

import argparse
import collections
import ctypes
import statistics
import time

import torch

from benchmarks.common import precomputed, settle, setup
from methods.core import native as _core
from methods.ptt import native as N
from methods.ptt.method import PTT

STOPS = {"mark": "    if (!(allhit | cons))\n        return -1;\n",
         "+sel": "    if (m == 0)\n        return 0;\n",
         "+rows": "          (const void*)a[VF_ACOS], (const void*)a[VF_ATAN2], a[VF_W16], nth, 1, (float*)a[VF_TABLE]);\n"}


def probe_source(stop: str | None) -> str:
    src = N._SOURCE
    if stop is None:
        return src
    anchor = STOPS[stop]
    assert src.count(anchor) == 1, stop
    return src.replace(anchor, anchor + "    return 1;\n")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--kind", default="V")
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=9)
    ap.add_argument("--precompute-of", default=None)   # another checkout whose precomputation to reuse
    ap.add_argument("--glue", action="store_true", help="also the frames' wall time outside the C call")
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
    _, frames, gbs, _ = setup(scene, "bench", kind=a.kind, n_frames=a.frames, seed=1, spp_side=2)
    fn = N._kernel()
    real = fn.view_frame
    calls, glue, outs, plans = [], [], [], []
    import methods.ptt.method as _pm

    buf = torch.zeros(16 << 20)

    class Spy:
        t = 0.0

        def __call__(self, args):
            c = type(args)()  # a copy of the packed arguments (the plan's array is rewritten each frame)
            c[:] = args[:]
            calls.append(c)
            plans.append(_pm._VIEW_PLANS.get(r))  # its buffers stay alive for the replays
            t0 = time.perf_counter()
            out = real(args)
            Spy.t = time.perf_counter() - t0
            return out

    fn.view_frame = Spy()
    for rnd in range(2 if a.glue else 1):
        for i in range(a.frames):
            buf.add_(1.0)
            settle()
            t0 = time.perf_counter()
            outs.append(r.render(frames[i], gbs[i]))  # (kept: the replays write into them)
            if i:
                glue.append(time.perf_counter() - t0 - Spy.t)
    fn.view_frame = real
    calls = calls[1:a.frames]
    if not calls:
        raise SystemExit("no native.view_frame call (VIEW_FRAME off, no compiler / AVX-512, or not this route)")
    libs = {k: _core.load("ptt_phase", probe_source(None if k == "+shade" else k), N._SIGNATURES,
                          extra_flags=N._EXTRA_FLAGS) for k in ("mark", "+sel", "+rows", "+shade")}
    for lib in libs.values():
        lib.view_frame.restype = ctypes.c_int64
        lib.view_frame.argtypes = [ctypes.c_void_p]
    res = collections.defaultdict(list)
    names = list(libs)
    for rnd in range(a.rounds):
        for name in names[rnd % 4:] + names[:rnd % 4]:
            for args in calls:
                buf.add_(1.0)
                settle()
                c0 = time.process_time()
                libs[name].view_frame(args)
                res[name].append(time.process_time() - c0)
    med = {k: statistics.median(v) for k, v in res.items()}
    print(f"{a.scene} {a.kind}: {len(calls)} calls x {a.rounds} rounds, 1 thread, cold (64 MB written before each), "
          f"process CPU median (cumulative | phase):")
    prev = 0.0
    for k in names:
        print(f"  {k:7s} {1e3 * med[k]:7.3f} ms | {1e3 * (med[k] - prev):7.3f} ms")
        prev = med[k]
    if glue:
        print(f"  frame outside the C call (wall, 1 thread): {1e3 * statistics.median(glue):.3f} ms")


if __name__ == "__main__":
    main()
