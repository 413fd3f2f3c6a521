"""Micro-benchmark of the order-8 vertex config's lighting-only frame kernel (`native.relight_resolve`, zh39o):
the arguments captured from a bench creature L frame, then the call timed alone (process CPU and wall, medians
and minima) at 1 and 2 threads, and its radiance half alone (an empty matrix: R = 0) — what bounds the frame.

    python -m benchmarks.zh_relight_vertex [--precompute-code DIR] [--repeat 200]
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.common import precomputed, setup


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--repeat", type=int, default=200)
    a = ap.parse_args(argv)
    if a.precompute_code:
        from reports import precompute_cache
        from reports.store import code_closure_fingerprint

        precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, a.precompute_code)
    from methods.zh_shadow import native as zn
    from methods.zh_shadow.method import ZHShadow

    torch.set_num_threads(1)
    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(ZHShadow, scene, {"order": 8, "shading": "vertex", "specular": "cosine"})
    _, frames, gbs, _ = setup(scene, "bench", kind="L", n_frames=3, seed=0)
    r = m.with_render_config()
    got, runs = [], []
    rs, rr = zn.relight_setup, zn.relight_run   # (zh40l: `relight_resolve` = setup + run, the method calls both)
    zn.relight_setup = lambda *x: got.append(x) or rs(*x)
    zn.relight_run = lambda *x: runs.append(x) or rr(*x)
    for f, g in zip(frames, gbs):
        r.render(f, g)
    zn.relight_setup, zn.relight_run = rs, rr
    spans, wf, tsc, packed = got[-1]
    _, light, kd, ks, clamp = runs[-1]
    empty = (0, *packed[1:4], packed[4][:0], packed[5][:1], packed[6], packed[7])
    print(f"compact columns {wf.shape[1]}, specular parts {[tuple(t.shape) for _, t in tsc.values()]}, "
          f"rows {packed[0]}, tails {packed[4].numel()}")
    for th in (1, 2):
        torch.set_num_threads(th)
        for name, pk in (("radiance + resolve", packed), ("radiance alone", empty)):
            c, w = [], []
            for _ in range(a.repeat):
                t0, t1 = time.process_time(), time.perf_counter()
                zn.relight_resolve(light, kd, ks, spans, wf, tsc, clamp, pk)
                c.append(time.process_time() - t0)
                w.append(time.perf_counter() - t1)
            print(f"{th} thread(s) {name}: cpu median {statistics.median(c) * 1e3:.3f} ms, "
                  f"wall median {statistics.median(w) * 1e3:.3f} min {min(w) * 1e3:.3f} ms")


if __name__ == "__main__":
    main()
