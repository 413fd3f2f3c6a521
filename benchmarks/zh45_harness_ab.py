"""(zh45: zh44's `zh44_harness_ab` with the wall time of each frame printed beside the process CPU — at 2 threads
the process CPU counts the OpenMP worker's spinning, use the wall ratio — Python's GC paused around each frame as
the harness does, and ``--set ATTR=0|1`` to turn a switch of the new code's ZHShadow off or on.)

Same-process A/B of ZHShadow frames against another checkout (`benchmarks.zh_sample_ab`'s protocol: the baseline's
whole ``methods`` package, frames alternating which code goes first, frames 0-1 untimed, medians of process CPU time)
with the perf harness's cache state instead of a settle: before each frame 64 MB are written (everything cold, as
after the harness's Mitsuba call) and then the frame's G-buffer is made anew — every array cloned, strides kept,
as `make_gbuffer` writes it right before `reports.measure_cell` starts the timer — so the G-buffer the frame reads
sits in the last-level cache while code and kept state are cold, and every frame gets a new G-buffer object. No
idle before the frame (the harness renders right after making the G-buffer). One sequence of ``--frames`` frames
(each a new view / exponent / pose, as a perf cell's), ``--repeat`` times with seeds seed, seed + 1, ...

    python -m benchmarks.zh45_harness_ab --baseline DIR [--precompute-code DIR] [--config '{}'] [--kinds VB VBL P]
        [--frames 41] [--repeat 1] [--seed 0] [--threads 1] [--set ATTR=0 ...]
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import gc
import json
import statistics
import time

from benchmarks.common import apply_ab_options, precomputed, setup
from benchmarks.zh_pose_ab import base_modules, baseline_class


def fresh(gb):
    """``gb`` with every tensor cloned (the same strides): a new G-buffer written just now."""
    import torch

    return dataclasses.replace(gb, **{f.name: getattr(gb, f.name).clone() for f in dataclasses.fields(gb)
                                      if isinstance(getattr(gb, f.name), torch.Tensor)})


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", required=True)
    ap.add_argument("--config", default="{}")
    ap.add_argument("--kinds", nargs="+", default=["VB", "VBL", "P"])
    ap.add_argument("--frames", type=int, default=41)
    ap.add_argument("--repeat", type=int, default=1)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--mitsuba", action="store_true",
                    help="each frame's G-buffer rasterised anew right before it (`references.gbuffer.make_gbuffer`, "
                         "Mitsuba: the harness's own step) instead of the 64 MB write and a clone")
    ap.add_argument("--set", nargs="*", default=[], metavar="ATTR=0|1",
                    help="class switches of the new code's ZHShadow set for this run (e.g. one_split=0)")
    a = ap.parse_args(argv)
    apply_ab_options(a)
    import torch
    from methods.zh_shadow.method import ZHShadow as New

    for kv in a.set:
        k, v = kv.split("=")
        if not hasattr(New, k):
            raise SystemExit(f"ZHShadow has no switch {k!r}")
        setattr(New, k, bool(int(v)))
    from references.gbuffer import make_gbuffer

    Base = baseline_class(a.baseline)
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1)
    m, _ = precomputed(New, scene, json.loads(a.config))
    buf = torch.empty(16 * 1024 * 1024)
    out = {}
    for kind in a.kinds:
        t: dict = {"new": [], "base": []}
        tw: dict = {"new": [], "base": []}
        err = 0.0
        for r in range(a.repeat):
            _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=a.seed + r)
            new = m.with_render_config()
            base = copy.copy(m.with_render_config())
            base.__class__ = Base
            base.model = copy.copy(m.model)
            for i, (f, g) in enumerate(zip(frames, gbs)):
                imgs = {}
                for w in (("new", "base") if i % 2 == 0 else ("base", "new")):
                    with base_modules(a.baseline, w):
                        if a.mitsuba:
                            g2 = make_gbuffer(scene, f, g.spp_side)
                        else:
                            buf.fill_(float(i))
                            g2 = fresh(g)
                        gc.disable()
                        c, c0 = time.process_time(), time.perf_counter()
                        imgs[w] = (new if w == "new" else base).render(f, g2)
                        dc, dw = time.process_time() - c, time.perf_counter() - c0
                        gc.enable()
                        del g2
                    if i >= 2:
                        t[w].append(dc)
                        tw[w].append(dw)
                err = max(err, float((imgs["new"] - imgs["base"]).abs().max()
                                     / imgs["base"].abs().max().clamp_min(1e-12)))
        mb, mn = statistics.median(t["base"]), statistics.median(t["new"])
        wb, wn = statistics.median(tw["base"]), statistics.median(tw["new"])
        print(f"{kind}: WALL base {1e3 * wb:.3f} ms new {1e3 * wn:.3f} ms ratio {wb / wn:.3f} sum ratio "
              f"{sum(tw['base']) / sum(tw['new']):.3f}", flush=True)
        out[kind] = {"base_cpu_ms": 1e3 * mb, "new_cpu_ms": 1e3 * mn, "cpu_ratio": mb / mn, "rel_diff": err,
                     "base_wall_ms": 1e3 * wb, "new_wall_ms": 1e3 * wn, "wall_ratio": wb / wn,
                     "cpu_sum_ratio": sum(t["base"]) / sum(t["new"]), "frames": len(t["new"])}
        print(f"{kind}: base {1e3 * mb:.2f} ms new {1e3 * mn:.2f} ms ratio {mb / mn:.3f} sum ratio "
              f"{out[kind]['cpu_sum_ratio']:.3f} ({len(t['new'])} frames a side) rel_diff {err:.2e}", flush=True)
    return out


if __name__ == "__main__":
    main()
