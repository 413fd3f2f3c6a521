"""Timing and error of ZHShadow on the creature: `python -m benchmarks.zh_shadow --size test`.

Prints precompute time, model size, per-frame render time (median and IQR of `--repeats` renders
after one warm-up, torch thread count recorded) for both shading modes, and the RMSE against the
oracle on a held-out pose (`--oracle` samples per strategy; 0 skips it).
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", default="test", choices=["test", "bench"])
    ap.add_argument("--spp-side", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--oracle", type=int, default=0)
    ap.add_argument("--train-poses", type=int, default=32)
    ap.add_argument("--n-dirs", type=int, default=1024)
    ap.add_argument("--lobes", type=int, default=2)
    ap.add_argument("--order", type=int, default=4)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    a = ap.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)

    from benchmarks.common import setup
    from methods.zh_shadow import ZHShadow

    scene, frames, gbs, _ = setup("creature", a.size, kind="P", n_frames=4, seed=5, spp_side=a.spp_side)
    m = ZHShadow(train_poses=a.train_poses, n_dirs=a.n_dirs, lobes=a.lobes, order=a.order)
    t0 = time.perf_counter()
    m.precompute(scene)
    out = {"size": a.size, "threads": torch.get_num_threads(), "precompute_s": time.perf_counter() - t0,
           "stats": m.stats, "config": m.config}
    precomputed = m
    for mode in ("sample", "vertex"):
        m = precomputed.with_render_config(shading=mode)  # the same precomputation, another shading mode
        m.render(frames[0], gbs[0])                                   # warm-up (lighting SH, operators)
        ts = []
        for r in range(a.repeats):
            f, g = frames[1 + r % 3], gbs[1 + r % 3]
            t = time.perf_counter()
            m.render(f, g)
            ts.append(time.perf_counter() - t)
        q = statistics.quantiles(ts, n=4) if len(ts) >= 2 else [ts[0]] * 3
        out[f"frame_s_{mode}"] = {"median": statistics.median(ts), "iqr": q[2] - q[0]}
    out["memory"] = m.memory()
    if a.oracle:
        from methods.oracle import Oracle
        from references.metrics import rmse

        o = Oracle(light_samples=a.oracle, brdf_samples=a.oracle)
        o.precompute(scene)
        ref = o.render(frames[1], gbs[1]).numpy()
        mask = gbs[1].coverage.numpy()
        for mode in ("sample", "vertex"):
            for sp in ("published", "cosine"):
                mm = precomputed.with_render_config(shading=mode, specular=sp)
                out[f"rmse_{mode}_{sp}"] = rmse(mm.render(frames[1], gbs[1]).numpy(), ref, mask)
    print(json.dumps(out, indent=1, default=str))
    return out


if __name__ == "__main__":
    main()
