"""Micro-benchmark of the paper config's lighting-only pass (zh40l): `native.relight_pixels_setup` with the object
entries read from their blocked copies (``blocked=True``: ``zh40l_relight_pixels``) against zh35p's pass
(``blocked=False``), on the arguments of a bench creature L / E frame (`ZHShadow._relight_planes`), alternating,
after ``--idle`` seconds of sleep (the suite's settle) or after a 32 MB pass (``--idle 0``: caches flushed);
checks the two images are equal bit for bit.

    python -m benchmarks.zh_blocked_relight [--precompute-code DIR] [--kind L] [--threads 1] [--repeat 40] [--idle 0.2]
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
    ap.add_argument("--kind", default="L")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=40)
    ap.add_argument("--idle", type=float, default=0.2)
    a = ap.parse_args(argv)
    if a.precompute_code:
        from reports import precompute_cache
        from reports.store import code_closure_fingerprint

        precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, a.precompute_code)
    from methods.zh_shadow import native as zn
    from methods.zh_shadow.method import ZHShadow

    torch.set_num_threads(a.threads)
    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(ZHShadow, scene, {})
    _, frames, gbs, _ = setup(scene, "bench", kind=a.kind, n_frames=3, seed=0)
    r = m.with_render_config()
    got = []
    rs = zn.relight_pixels_setup
    zn.relight_pixels_setup = lambda *x, **k: got.append((x, k)) or rs(*x, **k)
    for f, g in zip(frames, gbs):
        r.render(f, g)
    zn.relight_pixels_setup = rs
    x, _ = got[-1]
    face, bary, clamp, ents, inv, planes = x
    sts = {"zh35p": rs(*x, blocked=False), "blocked": rs(*x, blocked=True)}
    lds, lss, T = [e[2] for e in ents], [e[3] for e in ents], planes[3]
    imgs = {k: zn.relight_pixels_run(st, lds, lss, T) for k, st in sts.items()}
    print(f"entries {[tuple(e[0].shape) for e in ents]}, equal {torch.equal(imgs['zh35p'], imgs['blocked'])}")
    junk = torch.randn(8 << 20)
    t = {k: [] for k in sts}
    for i in range(a.repeat):
        for k in (list(sts) if i % 2 == 0 else list(sts)[::-1]):
            if a.idle > 0:
                time.sleep(a.idle)
            else:
                junk.mul_(1.0001)
            c = time.perf_counter()
            zn.relight_pixels_run(sts[k], lds, lss, T)
            t[k].append(time.perf_counter() - c)
    b, n = statistics.median(t["zh35p"]), statistics.median(t["blocked"])
    print(f"{a.threads} thread(s), idle {a.idle}: zh35p {b * 1e3:.3f} ms, blocked {n * 1e3:.3f} ms (wall medians), "
          f"ratio {b / n:.2f}")


if __name__ == "__main__":
    main()
