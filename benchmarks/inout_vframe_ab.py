"""In-out shading "vertex": the view frame's one C loop (``methods.inout.native_vframe``) against the split
path it replaces (`InOut._render_vertex` with the loop off), in one process on one precomputation.

    python -m benchmarks.inout_vframe_ab [--scene chess] [--threads 1] [--frames 21]

Two copies of one precomputation (the harness's cache), V frames (seed 1, 2×2 samples) rendered by both,
alternating which goes first, each after `benchmarks.common.settle` (the suite's idle); frame 0 untimed.
Prints the median process-CPU and wall ms of each, their ratios, and whether every image was the same bits.
"""
from __future__ import annotations

import argparse
import copy
import statistics
import time

import torch

from benchmarks.common import precomputed, settle, setup
from methods.inout.method import InOut


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--frames", type=int, default=21)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    scene, frames, gbs, _ = setup(a.scene, a.size, kind="V", n_frames=a.frames, seed=1, spp_side=2)
    m, _ = precomputed(InOut, scene, {"shading": "vertex"})
    m._fast = None
    new, old = copy.copy(m), copy.copy(m)
    new._reset_cache()
    old._reset_cache()
    old._render_vertex_native = lambda frame, gbuffer: None
    cpu = {"new": [], "old": []}
    wall = {"new": [], "old": []}
    same = True
    for i, (f, g) in enumerate(zip(frames, gbs)):
        imgs = {}
        for which in (("new", "old") if i % 2 else ("old", "new")):
            r = new if which == "new" else old
            settle()
            t0, c0 = time.perf_counter(), time.process_time()
            imgs[which] = r.render(f, g)
            if i:
                cpu[which].append(time.process_time() - c0)
                wall[which].append(time.perf_counter() - t0)
        same = same and torch.equal(imgs["new"], imgs["old"])
    out = {k: {w: statistics.median(v[w]) for w in v} for k, v in (("cpu", cpu), ("wall", wall))}
    print(f"{a.scene} {a.size}, {a.threads} threads, {a.frames - 1} timed frames each: "
          f"cpu old {1e3 * out['cpu']['old']:.2f} new {1e3 * out['cpu']['new']:.2f} ms "
          f"({out['cpu']['old'] / out['cpu']['new']:.3f}x), wall old {1e3 * out['wall']['old']:.2f} "
          f"new {1e3 * out['wall']['new']:.2f} ms ({out['wall']['old'] / out['wall']['new']:.3f}x), same bits: {same}")
    out["same"] = same
    return out


if __name__ == "__main__":
    main()
