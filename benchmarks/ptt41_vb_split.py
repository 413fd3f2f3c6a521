"""Where a PTT VB frame's time goes beyond a V frame's (issue 14, session 41, pt41): chess / creature bench,
the perf suite's frames (seed 1, 2×2 samples), each frame after a 64 MB write and ``PRTBENCH_SETTLE``
idle (the harness's G-buffer and scoring between timed frames), V and VB sequences interleaved frame by
frame; every call of the frame's parts wrapped in a timer (wall and process CPU).

    python -m benchmarks.ptt41_vb_split [--scene chess] [--frames 9] [--threads 2] [--rounds 2]
                                        [--precompute-of BASE_CHECKOUT]

Prints per kind the median ms (wall / cpu) of the frame and of each part: `PTT.coords` (the run-time
fit; ``native_fit.fit_materials`` inside it), `fast.region_tables` (``native.region_tables`` — W_r —
and the a_r einsum or ``native_fit.ar_table`` inside it), ``native.referenced_sel``,
``native.vertex_rows``, ``native.shade_mirror``. At 2 threads the wall
time of a serial part is what the frame waits for it."""
from __future__ import annotations

import argparse
import collections
import json
import statistics
import time

import torch

from benchmarks.common import frame_args, precomputed, settle, setup
from methods.ptt import fast as _fast
from methods.ptt import native as _native
from methods.ptt import native_fit as _nf
from methods.ptt.method import PTT

T = collections.defaultdict(lambda: [0.0, 0.0])


def wrap(mod, name, label):
    f = getattr(mod, name)

    def g(*a, **k):
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            return f(*a, **k)
        finally:
            T[label][0] += time.perf_counter() - t0
            T[label][1] += time.process_time() - c0

    setattr(mod, name, g)


def flush(buf):
    buf.add_(1.0)  # 64 MB read + written: the harness's G-buffer / scoring between frames


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    frame_args(ap, scene="chess", config='{"light_res_1":4}', frames=9, kinds=("V", "VB"))
    ap.add_argument("--precompute-of", default="",
                    help="look the precomputation up under this checkout's code fingerprint ('' = this one's; "
                         "benchmarks.ptt_ab.base_fingerprint)")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--flags-ab", action="store_true",
                    help="each kind twice, alternating frame by frame: 'off' = session 40's BRDF stage "
                         "(method.FIT_BATCH and native_fit.FAST_FIT off) and 'on' (both on)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    if a.precompute_of:
        from benchmarks.ptt_ab import base_fingerprint
        from reports import precompute_cache

        fp = base_fingerprint(a.precompute_of)
        precompute_cache._process_fingerprint = lambda module: fp
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1, spp_side=a.spp_side)
    m, _ = precomputed(PTT, scene, json.loads(a.config))
    m = m.with_bounces(0)
    m._fast_static()
    import methods.ptt.method as _mm

    def flags(on):
        _mm.FIT_BATCH = _nf.FAST_FIT = on

    seqs = {}
    kinds = [f"{k} {w}" for k in a.kinds for w in ("off", "on")] if a.flags_ab else list(a.kinds)
    for kind in kinds:
        _, frames, gbs, _ = setup(scene, a.size, kind=kind.split()[0], n_frames=a.frames, seed=1, spp_side=a.spp_side)
        r = m.with_shading("vertex")
        if a.flags_ab:
            flags(kind.endswith("on"))
        r.render(frames[0], gbs[0])
        seqs[kind] = (r, frames, gbs)
    wrap(PTT, "coords", "coords")
    wrap(_native, "region_tables", "W_r native")
    wrap(torch, "einsum", "a_r einsum")
    wrap(_nf, "ar_table", "a_r native")
    wrap(_fast, "region_tables", "region_tables (all)")
    wrap(_nf, "fit_materials", "fit_materials")
    wrap(type(m), "_fast_static", "_fast_static")
    wrap(_native, "referenced_sel", "referenced_sel")
    wrap(_native, "vertex_rows", "vertex_rows")
    wrap(_native, "shade_mirror", "shade_mirror")
    wrap(_native, "view_frame", "view_frame (one call)")  # session 42: the three above in one C call

    wrap(torch, "set_num_threads", "set_num_threads")
    buf = torch.zeros(16 << 20)
    per = {k: collections.defaultdict(list) for k in kinds}
    for rnd in range(a.rounds):
        for i in range(1, a.frames):
            for kind in (kinds if (i + rnd) % 2 == 0 else kinds[::-1]):
                r, frames, gbs = seqs[kind]
                if a.flags_ab:
                    flags(kind.endswith("on"))
                if i == 1:
                    r._reset_cache()
                    r.render(frames[0], gbs[0])
                flush(buf)
                settle()
                T.clear()
                t0, c0 = time.perf_counter(), time.process_time()
                r.render(frames[i], gbs[i])
                w, c = time.perf_counter() - t0, time.process_time() - c0
                per[kind]["frame"].append((w, c))
                for k, v in T.items():
                    per[kind][k].append(tuple(v))
    for kind in kinds:
        n = len(per[kind]["frame"])
        print(f"\n{a.scene} {kind}, {a.threads} thread(s), median of {n} frames (ms wall / cpu):")
        for k, v in per[kind].items():
            v = v + [(0.0, 0.0)] * (n - len(v))
            print(f"  {k:22s} {1e3 * statistics.median(x[0] for x in v):7.3f} {1e3 * statistics.median(x[1] for x in v):7.3f}"
                  f"   frames wall: {' '.join(f'{1e3 * x[0]:.2f}' for x in v)}" if k == "frame" else
                  f"  {k:22s} {1e3 * statistics.median(x[0] for x in v):7.3f} {1e3 * statistics.median(x[1] for x in v):7.3f}")


if __name__ == "__main__":
    main()
