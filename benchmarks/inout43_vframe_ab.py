"""In-out shading "vertex" V frames: a base checkout's method code (``--base``) against this checkout's, in one
process on one precomputation, each frame right after its G-buffer is made (the perf suite's protocol).

    python -m benchmarks.inout43_vframe_ab --base CHECKOUT [--precompute-code DIR] [--scene creature]
                                           [--threads 1] [--frames 41] [--aa]

The base's ``methods`` package is imported beside this one (`benchmarks.common.checkout_class`; its frames
render inside `checkout_modules`, entered before the clock starts), the precomputation is loaded once from the
harness cache under ``--precompute-code``'s code fingerprint (default: ``--base``'s; valid while this
checkout's edits leave the precompute alone), and both render every frame of the scene's bench V sequence
(seed 1, 2×2 samples) in alternating order. Before each timed render the frame's G-buffer is made afresh
(``make_gbuffer``, as ``reports.measure_cell`` does: the rasteriser's work cools the caches, no idle between
it and the render), the previous frame's G-buffer and image are held until the render returns, and Python's
GC is paused during it. Frame 0 (the lighting: every c computed) and frame 1 are not counted. Prints the
median process-CPU and wall ms of both, the ratio base / new of the medians and the median of the per-frame
ratios, and the largest |base − new| over the images (0: the same bits). ``--aa``: the base against itself
(two copies), the A/A noise of the same protocol.
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import gc
import statistics
import time

import torch

from benchmarks.common import checkout_class, checkout_fingerprint, checkout_modules, precomputed, setup
from methods.inout.method import InOut
from references.gbuffer import make_gbuffer


def _fresh(m: InOut, cls) -> InOut:
    """A copy of ``m`` of class ``cls`` with empty run-time caches and no fast-path statics of its own yet."""
    out = copy.copy(m)
    out.__class__ = cls
    out._reset_cache()
    out._fast = None
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True, help="a checkout of the code to compare against (e.g. a git worktree of the base commit)")
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--frames", type=int, default=41)
    ap.add_argument("--aa", action="store_true", help="the base against itself (the protocol's noise)")
    a = ap.parse_args(argv)
    from reports import precompute_cache

    fp = checkout_fingerprint(a.precompute_code or a.base, "methods.inout.method")
    precompute_cache._process_fingerprint = lambda module: fp
    torch.set_num_threads(a.threads)
    Base = checkout_class(a.base, "methods.inout.method", "InOut")
    scene, frames, _, _ = setup(a.scene, a.size, kind="V", n_frames=a.frames, seed=1, spp_side=2)
    m, _ = precomputed(InOut, scene, {"shading": "vertex"})
    runs = {"base": _fresh(m, Base), "new": _fresh(m, Base if a.aa else InOut)}
    roots = {"base": a.base, "new": a.base if a.aa else None}
    cpu = {k: [] for k in runs}
    wall = {k: [] for k in runs}
    diff, peak = 0.0, 0.0
    held = None
    for i, f in enumerate(frames):
        imgs = {}
        for which in (("base", "new") if i % 2 == 0 else ("new", "base")):
            with checkout_modules(roots[which]) if roots[which] else contextlib.nullcontext():
                g = make_gbuffer(scene, f, 2)
                gc.disable()
                t0, c0 = time.perf_counter(), time.process_time()
                img = runs[which].render(f, g)
                c1, t1 = time.process_time(), time.perf_counter()
                gc.enable()
                held = (g, img)
            imgs[which] = img
            if i >= 2:
                cpu[which].append(c1 - c0)
                wall[which].append(t1 - t0)
        diff = max(diff, float((imgs["base"] - imgs["new"]).abs().max()))
        peak = max(peak, float(imgs["base"].abs().max()))
    del held
    out = {}
    for name, d in (("cpu", cpu), ("wall", wall)):
        mb, mn = statistics.median(d["base"]), statistics.median(d["new"])
        pf = statistics.median(x / y for x, y in zip(d["base"], d["new"]))
        out[name] = {"base_ms": 1e3 * mb, "new_ms": 1e3 * mn, "ratio": mb / mn, "paired": pf}
    out["max_abs_diff"], out["peak"] = diff, peak
    print(f"{a.scene} {a.size} V, {a.threads} thread(s), {len(cpu['new'])} frames{' (A/A)' if a.aa else ''}: "
          + "; ".join(f"{k} base {v['base_ms']:.3f} new {v['new_ms']:.3f} ms ratio {v['ratio']:.3f} "
                      f"(per frame {v['paired']:.3f})" for k, v in out.items() if k in ("cpu", "wall"))
          + f"; max|base-new| {diff:.3g} (peak {peak:.3g})")
    return out


if __name__ == "__main__":
    main()
