"""Same-process A/B of the FIRST lighting-only frame of a sequence (the lazy work it carries: the resolve matrix
and the compact transfer), order-8 vertex config, against another checkout (zh39o). Per repeat: frame 0 (a full
change, untimed) then frame 1 after the suite's idle (`settle`), old and new alternating which goes first;
medians of process CPU time.

    python -m benchmarks.zh_first_light_ab --baseline DIR [--precompute-code DIR] [--kinds L E] [--repeat 10]
"""
from __future__ import annotations

import argparse
import copy
import statistics
import time

import torch

from benchmarks.common import apply_ab_options, precomputed, settle, setup
from benchmarks.zh_pose_ab import base_modules, baseline_class

CONFIG = {"order": 8, "shading": "vertex", "specular": "cosine"}


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--baseline", required=True)
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--kinds", nargs="+", default=["L", "E"])
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    apply_ab_options(a)
    from methods.zh_shadow.method import ZHShadow as New

    Base = baseline_class(a.baseline)
    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(New, scene, CONFIG)
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, "bench", kind=kind, n_frames=2, seed=0)
        t = {"new": [], "base": []}
        for i in range(a.repeat):
            for w in (("new", "base") if i % 2 == 0 else ("base", "new")):
                obj = m.with_render_config()
                if w == "base":
                    obj = copy.copy(obj)
                    obj.__class__ = Base
                    obj.model = copy.copy(m.model)
                with base_modules(a.baseline, w):
                    obj.render(frames[0], gbs[0])
                    settle()
                    c = time.process_time()
                    obj.render(frames[1], gbs[1])
                    t[w].append(time.process_time() - c)
        b, n = statistics.median(t["base"][1:]), statistics.median(t["new"][1:])
        print(f"{kind} first lighting frame: base {b * 1e3:.2f} ms new {n * 1e3:.2f} ms ratio {b / n:.2f}", flush=True)


if __name__ == "__main__":
    main()
