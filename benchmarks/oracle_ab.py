"""Same-process A/B of oracle frames (`Oracle.render`) against another checkout's oracle (`methods/oracle.py`,
`methods/oracle/` since session 30)
(issue 14; `benchmarks.oracle` compares the two paths of one checkout).

    python -m benchmarks.oracle_ab --baseline /work/base [--scene chess] [--kinds V L]
        [--config '{"light_samples":4,"brdf_samples":4}'] [--frames 7] [--threads 1] [--check-frames 1]

The baseline's `Oracle` is imported with its whole ``methods`` package
(`benchmarks.common.checkout_class`; its precompute and frames run inside `checkout_modules`, its
warm-up frame inside its own ``warming``); both classes render each kind's frames, alternating which goes first, frames 0-1
untimed (frame 0 inside ``methods.core.fused.warming``, as the harness's warm-up frame); medians of
process CPU and wall time and their ratio (`benchmarks.common.ab_frames`), and max |new − reference|
/ max |reference| against this tree's eager `Oracle.render_reference` on the first ``--check-frames``
frames (the eager estimator takes ~10× a frame).
"""
from __future__ import annotations

import argparse
import json
import os

from benchmarks.common import (ab_frames, ab_options, ab_report, apply_ab_options, checkout_class, checkout_modules,
                               machine_limits, setup)
from reports import measure

CONFIG = '{"light_samples":4,"brdf_samples":4}'


def baseline_class(root: str):
    """`Oracle` of the checkout ``root`` with its whole ``methods`` package (until session 29 only its
    ``methods/oracle.py``, by path, with this tree's core)."""
    return checkout_class(root, "methods.oracle", "Oracle")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ab_options(ap, config=CONFIG, kinds=("V", "L"))
    ap.add_argument("--check-frames", type=int, default=1, help="frames checked against render_reference")
    ap.set_defaults(scene="chess", frames=7)
    a = ap.parse_args(argv)
    apply_ab_options(a)
    from methods.core.fused import warming
    from methods.oracle import Oracle as New

    Base = baseline_class(a.baseline)
    cfg = json.loads(a.config)
    out: dict = {"method": "oracle", "scene": a.scene, "config": cfg, "threads": a.threads, "load": os.getloadavg()}
    bw, peak = [measure.triad_bandwidth()], [measure.matmul_peak()]
    kinds = {}
    for kind in a.kinds:
        scene, frames, gbs, _ = setup(a.scene, a.size, kind=kind, n_frames=a.frames)
        new, base = New(**cfg), Base(**cfg)
        new.precompute(scene)
        with warming():
            new.render(frames[0], gbs[0])
        with checkout_modules(a.baseline):
            from methods.core.fused import warming as base_warming

            base.precompute(scene)
            with base_warming():
                base.render(frames[0], gbs[0])
        checked, last, render = [0], {}, new.render

        def keep(f, g, render=render, last=last):
            last["img"] = render(f, g)
            return last["img"]

        def reference(f, g, new=new, checked=checked, last=last):
            checked[0] += 1  # frames 0-1 are untimed
            return new.render_reference(f, g) if 2 < checked[0] <= 2 + a.check_frames else last["img"]

        new.render = keep  # the instance's: the image `ab_frames` checks is the one just timed

        kinds[kind] = ab_frames(new, base, reference, frames, gbs, kind, base_root=a.baseline)
    B, Pk = machine_limits(out, bw, peak)
    ab_report(out, kinds, max(B, 1.0), max(Pk, 1.0), f"oracle {a.scene} ({a.size}) {cfg}, {a.threads} threads")
    return out


if __name__ == "__main__":
    main()
