"""The shared Gouraud resolve (`methods.core.gouraud.resolve`) alone: the compiled kernel against the
native loop on one thread and split over a pool, in one process, alternating (issue 14, session 26).

    python -m benchmarks.gouraud_resolve [--scene chess] [--size bench] [--threads 2] [--reps 60]
                                         [--idle 0.01]

Each call follows ``--idle`` seconds of sleep and one parallel torch pass over 16 MB (as a frame's
resolve follows its other kernels), random per-vertex radiance on the scene's default-frame G-buffer
(2 × 2 samples per pixel). Prints the median and minimum wall ms of each mode and checks that the
three images are the same bits."""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.common import setup
from methods.core import gouraud


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=60)
    ap.add_argument("--idle", type=float, default=0.01)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    scene, _, gbs, _ = setup(a.scene, a.size, kind="V", n_frames=1, spp_side=2)
    g, F = gbs[0], scene.geometry().F
    vals = torch.rand(int(F.max()) + 1, 3, generator=torch.Generator().manual_seed(0))
    big = torch.rand(4_000_000)
    args = (vals, F.T, g.face, g.bary, g.hit, g.height, g.width, g.spp_side)
    split = gouraud._NATIVE_MIN_PIXELS

    def run(mode: str) -> torch.Tensor:
        if mode == "compiled":
            return gouraud.resolve(*args, native_resolve=False)
        gouraud._NATIVE_MIN_PIXELS = 1 << 30 if mode == "native, 1 thread" else 1
        try:
            return gouraud.resolve(*args)
        finally:
            gouraud._NATIVE_MIN_PIXELS = split

    modes = ("compiled", "native, 1 thread", "native, split")
    imgs = {m: run(m) for m in modes}                                      # warm-up (compiles)
    same = all(torch.equal(imgs["compiled"], imgs[m]) for m in modes)
    ts: dict[str, list[float]] = {m: [] for m in modes}
    for _ in range(a.reps):
        for m in modes:
            time.sleep(a.idle)
            big.mul_(1.0000001)
            t0 = time.perf_counter()
            run(m)
            ts[m].append(time.perf_counter() - t0)
    out = {m: {"median_ms": 1e3 * statistics.median(v), "min_ms": 1e3 * min(v)} for m, v in ts.items()}
    print(f"{a.scene} {a.size}, {g.height}x{g.width}x{g.spp_side}^2, {a.threads} threads, same bits: {same}")
    for m, r in out.items():
        print(f"  {m:18} median {r['median_ms']:7.3f} ms   min {r['min_ms']:7.3f} ms")
    return {"same_bits": same, **out}


if __name__ == "__main__":
    main()
