"""Micro-benchmark of `_fused_planes`' helpers (zh39s): the serial `native.screen8` + `native.rest_screen` +
`native.referenced_lut` against the threaded `native_threaded.screen8` + `native_threaded.rest_lut` on a real frame's
arrays (bench creature, the paper configuration, a VL frame's G-buffer and plane mask), alternating, medians of
wall and process CPU time per call set, at each of ``--threads``.

    python -m benchmarks.zh39s_helpers [--config '{}'] [--kind VL] [--repeat 400] [--threads 1 2] [--flush 64]
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="{}")
    ap.add_argument("--kind", default="VL")
    ap.add_argument("--repeat", type=int, default=400)
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--flush", type=int, default=0,
                    help="MB of memory written before each call set (0: warm, back to back): the settled frame's "
                         "cold caches")
    a = ap.parse_args(argv)
    from benchmarks.common import precomputed, setup
    from methods.zh_shadow import native as zn, native_threaded as z39
    from methods.zh_shadow.method import ZHShadow

    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(ZHShadow, scene, json.loads(a.config))
    _, frames, gbs, _ = setup(scene, "bench", kind=a.kind, n_frames=3, seed=0)
    r = m.with_render_config()
    cap = {}
    orig = z39.rest_lut

    def spy(*args):
        cap["a"] = args
        return orig(*args)
    z39.rest_lut = spy
    for f, g in zip(frames, gbs):
        r.render(f, g)
    z39.rest_lut = orig
    mask, hit, nrm, face, F32, N, mm, _, _ = cap["a"]
    gb = gbs[-1]

    def old():
        zn.screen8(gb.normal.T)
        zn.rest_screen(mask, nrm, mm)
        zn.referenced_lut(mask, hit, face, F32, N)

    def new():
        z39.screen8(gb.normal.T)
        z39.rest_lut(mask, hit, nrm, face, F32, N, mm, True, True)
    buf = torch.empty(max(a.flush, 1) << 18, dtype=torch.float32) if a.flush else None
    out = {}
    for nt in a.threads:
        torch.set_num_threads(nt)
        t = {"old": [], "new": []}
        c = {"old": [], "new": []}
        for i in range(a.repeat):
            for w, fn in ((("old", old), ("new", new)) if i % 2 == 0 else (("new", new), ("old", old))):
                if buf is not None:
                    buf.fill_(float(i))
                c0, t0 = time.process_time(), time.perf_counter()
                fn()
                t[w].append(time.perf_counter() - t0)
                c[w].append(time.process_time() - c0)
        md = {k: 1e3 * statistics.median(v[10:]) for k, v in t.items()}
        mc = {k: 1e3 * statistics.median(v[10:]) for k, v in c.items()}
        p10 = {k: 1e3 * sorted(v[10:])[len(v[10:]) // 10] for k, v in t.items()}   # (load only adds: the low tail)
        out[nt] = (md, mc, p10)
        print(f"threads {nt}: wall median old {md['old']:.3f} new {md['new']:.3f} ms ({md['old'] / md['new']:.2f}x), "
              f"10th percentile old {p10['old']:.3f} new {p10['new']:.3f} ms ({p10['old'] / p10['new']:.2f}x); "
              f"cpu old {mc['old']:.3f} new {mc['new']:.3f} ms", flush=True)
    return out


if __name__ == "__main__":
    main()
