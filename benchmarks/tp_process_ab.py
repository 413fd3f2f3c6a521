"""Process A/B of the per-pixel (or per-vertex) triple product: this tree and a baseline checkout, each in
processes of its own with its own precomputation (its own cache key: the precomputation's format is part of
what is compared), alternating process by process (A B B A ...), every process timing a fresh instance's
frames the way the perf suite does (`reports.measure_cell`: frame 0 untimed under `warming`, frames 1.. each
right after `make_gbuffer`). Prints each process's median process-CPU (and wall) ms per kind, and the ratio
of the medians of those per-process medians (baseline / this tree: > 1 = this tree faster).

    python -m benchmarks.tp_process_ab --baseline OTHER_CHECKOUT [--scene creature] [--config '{}']
        [--kinds V] [--frames 8] [--processes 4] [--threads 1]

What a same-process A/B (`benchmarks.tp_frames_ab`) cannot see: the two codes there share one process and
one precomputation (``--precompute-code``), so a precomputation stored in another format (tp36's broadcast
index row), or a process-level state (heap layout, the compiled kernels' first frame) is not compared.
Written for session 37's check of the per-pixel V frames that read 0.85x in session 36's runs (tp37): the
host's process-to-process spread is large (loaded: +-15 %), so use several processes and quote the ratio with
the per-process spread. The child runs with the checkout's own ``benchmarks.common`` (``setup``,
``precomputed``): both trees need them.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parents[1]


def child(a) -> dict:
    """One process: per kind, a fresh instance from the cache, frame 0 untimed, frames 1.. timed."""
    import resource

    import torch

    torch.set_num_threads(a.threads)
    from benchmarks.common import precomputed, setup
    from methods.core.fused import warming
    from methods.triple_product import TripleProduct
    from references.gbuffer import make_gbuffer

    config = json.loads(a.config)
    out = {}
    for kind in a.kinds:
        scene, frames, _, _ = setup(a.scene, a.size, kind=kind, n_frames=a.frames + 1, seed=a.seed, spp_side=a.spp_side)
        m, _ = precomputed(TripleProduct, scene, config)
        wall, cpu, flt = [], [], []
        for i, f in enumerate(frames):
            gb = make_gbuffer(scene, f, a.spp_side)
            r0 = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
            t0, c0 = time.perf_counter(), time.process_time()
            with warming(i == 0):
                m.render(f, gb)
            if i:
                wall.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
                flt.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - r0)
        out[kind] = {"cpu_ms": [1e3 * t for t in cpu], "wall_ms": [1e3 * t for t in wall], "minflt": flt}
        del m
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", required=False)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--config", default="{}")
    ap.add_argument("--kinds", nargs="+", default=["V"])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--processes", type=int, default=4, help="processes per tree")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--spp-side", type=int, default=2)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print("RESULT " + json.dumps(child(a)), flush=True)
        return {}
    if not a.baseline:
        raise SystemExit("--baseline is required")
    trees = {"new": HERE, "old": Path(a.baseline).resolve()}
    args = ["--child", "--scene", a.scene, "--size", a.size, "--config", a.config, "--kinds", *a.kinds,
            "--frames", str(a.frames), "--threads", str(a.threads), "--seed", str(a.seed), "--spp-side", str(a.spp_side)]
    runs: dict[str, list[dict]] = {"new": [], "old": []}
    for i in range(a.processes):
        for name in (("old", "new") if i % 2 == 0 else ("new", "old")):
            tree = trees[name]
            env = {**os.environ, "PYTHONPATH": str(tree)}
            p = subprocess.run([sys.executable, str(HERE / "benchmarks" / "tp_process_ab.py"), *args], cwd=tree, env=env,
                               capture_output=True, text=True)
            line = [x for x in p.stdout.splitlines() if x.startswith("RESULT ")]
            if p.returncode or not line:
                raise SystemExit(f"{name} process failed:\n{p.stderr[-2000:]}")
            r = json.loads(line[-1][7:])
            runs[name].append(r)
            print(name, " ".join(f"{k}: cpu {statistics.median(v['cpu_ms']):.2f} wall {statistics.median(v['wall_ms']):.2f} "
                                 f"minflt {statistics.median(v['minflt']):.0f}" for k, v in r.items()), flush=True)
    out = {"scene": a.scene, "config": a.config, "threads": a.threads, "processes": a.processes, "kinds": {}}
    for kind in a.kinds:
        per = {n: [statistics.median(r[kind]["cpu_ms"]) for r in runs[n]] for n in runs}
        pw = {n: [statistics.median(r[kind]["wall_ms"]) for r in runs[n]] for n in runs}
        res = {"old_cpu_ms": per["old"], "new_cpu_ms": per["new"],
               "ratio_cpu": statistics.median(per["old"]) / statistics.median(per["new"]),
               "ratio_wall": statistics.median(pw["old"]) / statistics.median(pw["new"])}
        out["kinds"][kind] = res
        print(f"{kind}: per-process median CPU ms old {sorted(round(x, 1) for x in per['old'])} new "
              f"{sorted(round(x, 1) for x in per['new'])}; ratio (old/new, median of medians) CPU "
              f"{res['ratio_cpu']:.3f}, wall {res['ratio_wall']:.3f}", flush=True)
    return out


if __name__ == "__main__":
    main()
