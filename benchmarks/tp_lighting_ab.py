"""Same-process A/B of TripleProduct's lighting change (`lighting.project_env`, the default grid at
bench size): a baseline checkout's `methods/triple_product/lighting.py` (``--baseline``, e.g. a
git worktree of main) against this tree's, alternating call by call on the same prefiltered maps of a scene's
"E" (probes turned about +Y: `lighting.env_block_azimuthal` here) and "L" (tilted axis: the general
kernel in both) frames; median process-CPU ms per lighting change (``--threads 1``) or wall ms, and
max |new − old| relative to the largest coefficient.

    python -m benchmarks.tp_lighting_ab [--scene chess] [--threads 1] [--reps 7] [--wall]
"""
from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
import sys
import time
from pathlib import Path

import torch


def _baseline(root: str):
    spec = importlib.util.spec_from_file_location("_baseline_tp_lighting", Path(root) / "methods/triple_product/lighting.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--kinds", default="E,L")
    ap.add_argument("--wall", action="store_true", help="wall time (perf_counter) instead of process CPU")
    ap.add_argument("--baseline", required=True)
    a = ap.parse_args(argv)

    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt
    from methods.triple_product import TripleProduct
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    torch.set_num_threads(a.threads)
    old = _baseline(a.baseline)
    cfg = TripleProduct()
    geo, grid, s = Geodesic(cfg.level), cfg.grid, cfg.config["light_supersample"]
    R = lt.grid_frames(grid)
    scene = get_scene(a.scene, a.size)
    clock = time.perf_counter if a.wall else time.process_time
    out = {"scene": a.scene, "threads": a.threads, "clock": "wall" if a.wall else "process_cpu"}
    for kind in a.kinds.split(","):
        envs = [lt.prefiltered(f.envmap, geo, s) for f in make_sequence(scene, kind, n_frames=4, seed=0)[1:]]
        st = {}
        new_c, _ = lt.project_env(envs[0], R, geo, supersample=s, grid=grid, stats=st)   # compile / warm up
        old_c, _ = old.project_env(envs[0], R, geo, supersample=s)
        err = float((new_c - old_c).abs().max() / old_c.abs().max())
        t_old, t_new = [], []
        for r in range(a.reps):
            env = envs[r % len(envs)]
            t = clock(); old.project_env(env, R, geo, supersample=s); t_old.append(clock() - t)
            t = clock(); lt.project_env(env, R, geo, supersample=s, grid=grid); t_new.append(clock() - t)
        mo, mn = statistics.median(t_old), statistics.median(t_new)
        out[kind] = {"path": st["lighting_path"], "old_ms": 1e3 * mo, "new_ms": 1e3 * mn, "ratio": mo / mn,
                     "max_rel_diff": err}
        print(kind, json.dumps(out[kind]), flush=True)
    return out


if __name__ == "__main__":
    main()
