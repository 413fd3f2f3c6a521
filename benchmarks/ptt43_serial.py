"""The serial part of a PTT shading="vertex" frame (issue 14, session 43, pt43): a frame's process-CPU time
outside its C calls — the Python a 2-thread frame runs on one thread besides the C calls' own serial parts —
with ``method.FRAME_CALL`` on and off, alternating frame by frame on two instances sharing one precomputation:

    python -m benchmarks.ptt43_serial [--scene chess] [--kind VB] [--frames 30] [--precompute-code CHECKOUT]

1 thread; before every timed frame 64 MB are written (the harness's G-buffer and scoring: cold caches) and
``PRTBENCH_SETTLE`` idled; frames 0 and 1 of each instance make its plans and are not counted. The C calls
timed are the route's (``fit_materials``, ``region_tables``, ``ar_table``, ``view_frame``) and the frame call's
(``frame_call``). Prints per setting the median frame CPU ms, the median of its C calls and of the rest.

Measured (session 43; chess / creature bench VB, 28 frames each): outside the C calls 0.494 -> 0.284 ms
(chess), 0.475 -> 0.276 ms (creature); the C calls 3.58 / 3.55 and 3.27 / 3.28 ms."""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.common import precomputed, settle, setup
from methods.ptt import method as PM
from methods.ptt import native as N
from methods.ptt import native_fit as NF
from methods.ptt.method import _FRAME_PLANS, PTT


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--kind", default="VB")
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--precompute-code", default=None, help="look the precomputation up under this checkout's code")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    if a.precompute_code:
        from benchmarks.ptt_ab import base_fingerprint
        from reports import precompute_cache

        fp = base_fingerprint(a.precompute_code)
        precompute_cache._process_fingerprint = lambda module: fp
    scene, _, _, _ = setup(a.scene, "bench", kind="V", n_frames=1, spp_side=2)
    m, _ = precomputed(PTT, scene, {"light_res_1": 4})
    m = m.with_bounces(0)
    m._fast_static()
    _, frames, gbs, _ = setup(scene, "bench", kind=a.kind, n_frames=a.frames, seed=1, spp_side=2)
    acc = [0.0]

    def timed(f):
        def w(*args):
            c0 = time.process_time()
            try:
                return f(*args)
            finally:
                acc[0] += time.process_time() - c0
        return w

    insts = {}
    for on in (False, True):
        PM.FRAME_CALL = on
        r = m.with_shading("vertex")
        r.render(frames[0], gbs[0])
        r.render(frames[1], gbs[1])
        insts[on] = r
    # wrapped after the plans are made (the frame call's plan holds view_frame's C address)
    lib, fn = NF._library()[0], N._kernel()
    lib.fit_materials, lib.ar_table = timed(lib.fit_materials), timed(lib.ar_table)
    fn.region_tables, fn.view_frame = timed(fn.region_tables), timed(fn.view_frame)
    buf = torch.zeros(16 << 20)
    res = {False: [], True: []}
    try:
        for i in range(2, a.frames):
            for on in ((False, True) if i % 2 else (True, False)):
                r = insts[on]
                PM.FRAME_CALL = on
                fpl = _FRAME_PLANS.get(r)
                real = None
                if fpl is not None:
                    real, fpl.fn = fpl.fn, timed(fpl.fn)
                acc[0] = 0.0
                buf.add_(1.0)
                settle()
                c0 = time.process_time()
                r.render(frames[i], gbs[i])
                c = time.process_time() - c0
                if real is not None:
                    fpl.fn = real
                res[on].append((c, acc[0]))
    finally:
        PM.FRAME_CALL = True
    med = statistics.median
    for on in (False, True):
        v = res[on]
        print(f"{a.scene} {a.kind} FRAME_CALL {'on ' if on else 'off'}: frame {1e3 * med(x[0] for x in v):.3f} ms cpu, "
              f"C calls {1e3 * med(x[1] for x in v):.3f}, outside {1e3 * med(x[0] - x[1] for x in v):.3f} (n={len(v)})")


if __name__ == "__main__":
    main()
