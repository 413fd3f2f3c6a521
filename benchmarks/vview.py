"""Same-process A/B of the SH PRT and in-out run time against another checkout's code (issue 14).

    python -m benchmarks.vview --method sh_prt --scene creature [--kinds V L] [--frames 9]
    python -m benchmarks.vview --method inout --config '{"shading":"vertex"}' --scene chess
    options: --baseline OTHER_CHECKOUT (the checkout whose method modules are the "before"),
             --threads 1 (1: process CPU time per frame, the load-robust measure; 2: wall time),
             --precompute-code DIR (take the precomputation from the harness cache entry of the code
             in DIR: this branch changes only run-time code, so the cached state is the same)

Loads one precomputation, gives it to the method class of this tree and to the baseline's (its whole
``methods`` package, `benchmarks.common.checkout_class`; the baseline's frames render inside
`checkout_modules`, so its lazy imports are the baseline's too), renders each kind's frames
alternating which goes first, frame 0–1 untimed. Prints
per kind the medians (process CPU and wall), their ratio, the roofline efficiency of the new code
with its ``frame_cost`` and the machine limits measured in the run, and max |new − reference| /
max |reference| (``render_reference``/``_render_reference``, this tree's oracle).
"""
from __future__ import annotations

import argparse
import copy
import json
import os


from benchmarks.common import (ab_frames, ab_options, ab_report, apply_ab_options, checkout_class, machine_limits,
                               precomputed, setup)
from reports import measure


def baseline_class(method: str, root: str):
    """The method class of the checkout ``root``, imported with its whole ``methods`` package
    (`benchmarks.common.checkout_class`; until session 29 only its method module, and in-out's
    ``fast``, were loaded by path, so every other module — native loops, core — was this tree's and a
    change there read ~1.0x). Render its frames with ``ab_frames(..., base_root=root)``."""
    if method == "sh_prt":
        return checkout_class(root, "methods.sh_prt.method", "SHPRT")
    return checkout_class(root, "methods.inout.method", "InOut")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--method", choices=("sh_prt", "inout"), required=True)
    ab_options(ap)
    ap.add_argument("--micro", action="store_true", help="sh_prt: time the frame's stages alone")
    a = ap.parse_args(argv)
    apply_ab_options(a)
    cfg = json.loads(a.config)
    if a.method == "sh_prt":
        from methods.sh_prt.method import SHPRT as New
    else:
        from methods.inout.method import InOut as New
    Base = baseline_class(a.method, a.baseline)
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1)
    m, _ = precomputed(New, scene, cfg)
    out: dict = {"method": a.method, "scene": a.scene, "config": cfg, "threads": a.threads,
                 "load": os.getloadavg()}
    bw, peak = [measure.triad_bandwidth()], [measure.matmul_peak()]
    kinds = {}
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=1)
        new = copy.copy(m)
        new._reset_cache()
        if a.method == "inout":
            new._fast = None
        base = copy.copy(new)
        base.__class__ = Base
        ref = copy.copy(new)
        r = ab_frames(new, base, ref.render_reference if a.method == "sh_prt" else ref._render_reference, frames, gbs, kind,
                      base_root=a.baseline)
        kinds[kind] = r
    B, Pk = machine_limits(out, bw, peak)
    if a.micro and a.method == "sh_prt":
        out["micro"] = micro_sh_prt(new, frames[-1], gbs[-1], B, Pk)
    ab_report(out, kinds, B, Pk, f"{a.method} {a.config} {a.scene} {a.size}, {a.threads} thread(s)")
    return out


def micro_sh_prt(m, frame, gb, B: float, Pk: float) -> dict:
    """The SH PRT frame's stages alone on the frame's real sizes, each with its achieved GB/s or
    GFLOP/s next to the machine's (`benchmarks.sh_prt.micro`, which this defers to)."""
    from benchmarks.sh_prt import micro

    return micro(m, [frame], gb, B, Pk)


if __name__ == "__main__":
    main()
