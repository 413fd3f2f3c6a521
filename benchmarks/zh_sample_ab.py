"""Same-process A/B of ZHShadow frames against another checkout, without the bench-size reference
render (`benchmarks.zh_pose_ab` checks every frame against `_render_reference`, which at bench size
on the loaded 2-core machine took > 20 min for two kinds): the new image is compared with the
baseline's instead (max |new − base| / max |base|), and the path the new code took is printed.

    python -m benchmarks.zh_sample_ab --baseline /work/base [--config '{}'] [--kinds V VB VBL VL L E]
        [--frames 11] [--scene creature] [--size bench] [--precompute-code /work/base] [--threads 1] [--repeat 1]

The baseline is the checkout's whole ``methods`` package (`benchmarks.zh_pose_ab.baseline_class`), its
frames rendered inside `benchmarks.common.checkout_modules`. Frames alternate which code goes first; frames 0–1 of each
repeat are untimed (zh42l: before, a repeat's frame 1 — after its frame 0's full change, a lighting-only sequence's
build frame — was timed from the second repeat on); before each frame a 64 MB buffer is written (zh42l; ``--no-flush``
off) and ``PRTBENCH_SETTLE`` idled, as the perf harness's G-buffer and idle leave the caches; medians of process CPU
time (and wall time), ``--threads`` torch threads (default 1; the perf suite runs 2). Use 1 thread for evidence:
at 2 threads an A/A run (this checkout as its own baseline, creature bench order-8 P frames, quiet
machine, session 24) read 1.03× and 1.70× wall — P frames came out either ~12 or ~20 ms on either
side — so a 2-thread ratio says nothing about the code.
For 2-thread wall-time evidence use `benchmarks.zh45_harness_ab` (session 45): no idle before a frame (the
harness renders right after making the G-buffer; here the settle's idle sends a 2-thread P frame to 9-12 ms and
an A/A read 1.42x), its A/A 0.99-1.02x.
"""
from __future__ import annotations

import argparse
import copy
import json
import statistics
import time

from benchmarks.common import apply_ab_options, precomputed, settle, setup
from benchmarks.zh_pose_ab import base_modules, baseline_class


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", required=True)
    ap.add_argument("--config", default="{}")
    ap.add_argument("--kinds", nargs="+", default=["V", "VB", "VBL", "VL", "L", "E"])
    ap.add_argument("--frames", type=int, default=11)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--precompute-code", default=None,
                    help="take the precomputation from the cache entry of the code in DIR (a run-time-only change)")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=1,
                    help="run the --frames sequence this many times over (the suite's spacing: --frames 5); "
                         "each repeat's frame 0 (a full change) untimed")
    ap.add_argument("--no-flush", action="store_true", help="no 64 MB write before each frame (warm caches)")
    a = ap.parse_args(argv)
    apply_ab_options(a)
    from methods.zh_shadow.method import ZHShadow as New

    Base = baseline_class(a.baseline)
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1)
    m, _ = precomputed(New, scene, json.loads(a.config))
    import torch

    buf = None if a.no_flush else torch.empty(16 * 1024 * 1024)
    out = {}
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=a.seed)
        new = m.with_render_config()
        base = copy.copy(m.with_render_config())
        base.__class__ = Base
        # its own model object (the same tensors): each code lays X out its own way once (`_visibility_args`;
        # session 35 keeps the order-8 model vertex-major), not back and forth every frame
        base.model = copy.copy(m.model)
        t: dict = {"new": [], "base": []}
        tw: dict = {"new": [], "base": []}
        err = 0.0
        for i, (f, g) in enumerate(zip(frames * a.repeat, gbs * a.repeat)):
            imgs = {}
            for w in (("new", "base") if i % 2 == 0 else ("base", "new")):
                with base_modules(a.baseline, w):   # the baseline's lazy imports its own (swap untimed)
                    if buf is not None:
                        buf.fill_(float(i))
                    settle()
                    c, c0 = time.process_time(), time.perf_counter()
                    imgs[w] = (new if w == "new" else base).render(f, g)
                    dc, dw = time.process_time() - c, time.perf_counter() - c0
                if i % len(frames) >= 2:
                    t[w].append(dc)
                    tw[w].append(dw)
            err = max(err, float((imgs["new"] - imgs["base"]).abs().max() / imgs["base"].abs().max().clamp_min(1e-12)))
        if kind == a.kinds[0]:   # which files the baseline's frames ran (its lazy imports included)
            with base_modules(a.baseline, "base"):
                import sys

                print("base frames ran: " + ", ".join(sys.modules[n].__file__ for n in
                      ("methods.zh_shadow.method", "methods.zh_shadow.runtime", "methods.zh_shadow.native",
                       "methods.core.gouraud", "methods.core.native") if n in sys.modules), flush=True)
        mb, mn = statistics.median(t["base"]), statistics.median(t["new"])
        wb, wn = statistics.median(tw["base"]), statistics.median(tw["new"])
        out[kind] = {"base_cpu_ms": 1e3 * mb, "new_cpu_ms": 1e3 * mn, "cpu_ratio": mb / mn, "rel_diff": err,
                     "base_wall_ms": 1e3 * wb, "new_wall_ms": 1e3 * wn, "wall_ratio": wb / wn,
                     "path": getattr(new, "last_path", "")}
        out[kind]["cpu_sum_ratio"] = sum(t["base"]) / sum(t["new"])   # (frames of two costs: the median hides one)
        print(f"{kind}: base {1e3 * mb:.2f} ms new {1e3 * mn:.2f} ms ratio {mb / mn:.2f} (wall {1e3 * wb:.2f} / "
              f"{1e3 * wn:.2f} ms, {wb / wn:.2f}) sum ratio {out[kind]['cpu_sum_ratio']:.2f} rel_diff {err:.2e} "
              f"path {out[kind]['path']}", flush=True)
    return out


if __name__ == "__main__":
    main()
