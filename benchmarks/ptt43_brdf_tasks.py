"""A PTT VB frame's BRDF stage at 2 threads (issue 14, session 43, pt43): the route's three C calls one after
the other — ``native_fit.fit_materials`` (materials dealt round-robin to the threads), ``native.region_tables``
(W_r's rows split in halves), ``native_fit.ar_table`` (one thread) — against ``native_fit.frame_call``'s task
team (the fits, W_r's row chunks and a_r taken from one counter, a chunk once its region's fit is done), on the
perf suite's VB frames (chess / creature bench, seed 1):

    python -m benchmarks.ptt43_brdf_tasks [--scene chess] [--frames 12] [--rounds 5] [--threads 2]
                                          [--precompute-code CHECKOUT]

The frame call's view slot points at a C function that does nothing (``frame_call_count``), so only the
BRDF part runs; each variant's Python (arguments, H) is made before its timer. Before each call 64 MB are written (cold caches) and a small 2-thread torch op wakes the
team (the frame's earlier work would have). Wall time (perf_counter) per call, the variants alternating;
prints the median, minimum, 10th and 30th percentile ms of each and checks that both wrote the same H, W_r and a_r bits. On a shared
machine the wall medians carry other processes' preemption: compare the minima too.

Measured (session 43, chess bench, 22 frames x 4 rounds, host load 6-8 on 2 cores): 1 thread route median
0.217 ms (10th percentile 0.196), tasks 0.203 (0.183); 2 threads route 0.228 (0.150, min 0.134), tasks 0.197
(0.136, min 0.126): the BRDF part's C work is ~0.2 ms a VB frame, and at 2 threads the tasks take ~0.01-0.03
ms off it. Bits equal."""
from __future__ import annotations

import argparse
import ctypes
import statistics
import time

import torch

from benchmarks.common import precomputed, setup
from methods.ptt import method as PM
from methods.ptt import native as N
from methods.ptt import native_fit as NF
from methods.ptt.method import _FRAME_PLANS, PTT


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--precompute-code", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    if a.precompute_code:
        from benchmarks.ptt_ab import base_fingerprint
        from reports import precompute_cache

        fp = base_fingerprint(a.precompute_code)
        precompute_cache._process_fingerprint = lambda module: fp
    scene, _, _, _ = setup(a.scene, "bench", kind="V", n_frames=1, spp_side=2)
    m, _ = precomputed(PTT, scene, {"light_res_1": 4})
    r = m.with_bounces(0).with_shading("vertex")
    _, frames, gbs, _ = setup(scene, "bench", kind="VB", n_frames=a.frames, seed=1, spp_side=2)
    PM.FRAME_CALL = True
    r.render(frames[0], gbs[0])
    r.render(frames[1], gbs[1])
    fpl = _FRAME_PLANS[r]
    lib = NF._library()[0]
    args = (ctypes.c_int64 * len(NF.FC))()
    args[:] = fpl.args[:]
    args[NF._FC["view"]] = ctypes.cast(lib.frame_call_count, ctypes.c_void_p).value
    Wr, ar = r._f_tabs
    W_rows, lobe_a = r._f_wrows[1], r.lobe_table.a
    mats = [[f.materials[g] for g in r.regions] for f in frames[2:]]
    buf, small = torch.zeros(16 << 20), torch.zeros(1 << 16)
    t = {"route": [], "tasks": []}
    outs = {}
    for rnd in range(a.rounds):
        for j, ms in enumerate(mats):
            for v in (("route", "tasks") if (j + rnd) % 2 else ("tasks", "route")):
                buf.add_(1.0)
                small.mul_(1.0)  # the team awake, as after the frame's earlier parallel work
                if v == "route":  # the three C calls with the route's arguments, made before the timer
                    fa = NF.fit_args(r.basis, ms, a.threads)
                    H = torch.empty(fa[1][0], fa[1][8], 3)
                    fa[1][18] = H.data_ptr()
                    fn, Wp, P, R, T2, K, out, nt = N.region_tables_args(W_rows, H, a.threads, Wr)
                    Lb, R_, P_, n, L, hl, c, aout = NF.ar_args(H, lobe_a, ar)
                    t0 = time.perf_counter()
                    Lb[0].fit_materials(*fa[1])
                    fn.region_tables(Wp.data_ptr(), H.data_ptr(), P, R, T2, K, out.data_ptr(), nt)
                    Lb[0].ar_table(H.data_ptr(), lobe_a.data_ptr(), R_, P_, n, L, Lb[5], Lb[6], hl.data_ptr(),
                                   c.data_ptr(), aout.data_ptr())
                    dt = time.perf_counter() - t0
                else:
                    fa = NF.fit_args(r.basis, ms, a.threads, fpl.lib, team=a.threads)
                    H = torch.empty(fa[1][0], fa[1][8], 3)
                    fa[1][18] = H.data_ptr()
                    args[0:20] = fa[1]
                    args[NF._FC["hold"]] = 0
                    t0 = time.perf_counter()
                    fpl.fn(args)
                    dt = time.perf_counter() - t0
                t[v].append(dt)
                if rnd == 0:
                    outs.setdefault(j, {})[v] = (H.clone(), Wr.clone(), ar.clone())
    same = all(all(torch.equal(x, y) for x, y in zip(o["route"], o["tasks"])) for o in outs.values())
    for v, x in t.items():
        q = statistics.quantiles(x, n=10)
        print(f"{a.scene} {a.threads} threads {v:5s}: median {1e3 * statistics.median(x):.3f} ms, "
              f"min {1e3 * min(x):.3f}, 10th / 30th percentile {1e3 * q[0]:.3f} / {1e3 * q[2]:.3f} ms (n={len(x)})")
    print("same H / W_r / a_r bits:", same)


if __name__ == "__main__":
    main()
