"""ZH's frame count (`ZHShadow.frame_cost`) of each perf-suite cell, this checkout against another
(issue 14, session 27: the count over the vertices the samples reference).

    python -m benchmarks.zh_referenced_count --baseline /work/base [--precompute-code /work/base]
        [--configs '{}' '{"order":8,"shading":"vertex","specular":"cosine"}'] [--kinds V VB VL VBL P L E]
        [--frames 5] [--seed 0] [--scene creature] [--size bench]

As the harness (`reports.measure_cell`): the sequence of ``--frames`` frames rendered in order, the
count read after the last one; both checkouts render the same frames (their own instances, one
precomputed model). Prints bytes and flops, old / new, per cell."""
from __future__ import annotations

import argparse
import copy
import json

import torch

from benchmarks.common import apply_ab_options, precomputed, setup
from benchmarks.zh_pose_ab import PHYSICAL, base_modules, baseline_class


def main(argv: list[str] | None = None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", required=True)
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--configs", nargs="+", default=["{}", PHYSICAL])
    ap.add_argument("--kinds", nargs="+", default=["V", "VB", "VL", "VBL", "P", "L", "E"])
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    apply_ab_options(a)
    from methods.zh_shadow.method import ZHShadow as New

    Base = baseline_class(a.baseline)
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1)
    rows = []
    for cfg in a.configs:
        m, _ = precomputed(New, scene, json.loads(cfg))
        for kind in a.kinds:
            _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=a.seed)
            new = m.with_render_config()
            base = copy.copy(m.with_render_config())
            base.__class__ = Base
            err = 0.0
            with torch.no_grad():
                for f, g in zip(frames, gbs):
                    x = new.render(f, g)
                    with base_modules(a.baseline, "base"):
                        y = base.render(f, g)
                    err = max(err, float((x - y).abs().max() / y.abs().max().clamp_min(1e-12)))
            P = gbs[-1].num_samples
            cn = new.frame_cost(kind, P)
            with base_modules(a.baseline, "base"):
                cb = base.frame_cost(kind, P)
            r = {"config": cfg, "kind": kind, "old_bytes": cb.bytes, "new_bytes": cn.bytes, "old_flops": cb.flops,
                 "new_flops": cn.flops, "rel_diff": err}
            rows.append(r)
            print(f"{cfg:52} {kind:4} bytes {cb.bytes:>11,} -> {cn.bytes:>11,} ({cn.bytes / cb.bytes:.3f})  "
                  f"flops {cb.flops:>13,} -> {cn.flops:>13,} ({cn.flops / cb.flops:.3f})  rel_diff {err:.1e}",
                  flush=True)
    return rows


if __name__ == "__main__":
    main()
