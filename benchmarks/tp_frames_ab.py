"""Same-process A/B of TripleProduct frames: a baseline checkout's `methods` package (``--baseline``,
e.g. a git worktree of main; `benchmarks.common.checkout_class`, the baseline copy of the method an
instance of the baseline's class, its frames rendered inside `benchmarks.common.checkout_modules` so
that every module it imports, lazily too, is the baseline's: native loops included) against this tree's, on
the same precomputed method (two copies), the same frames and G-buffers, alternating frame by frame; median
process-CPU ms per frame (``--threads 1``; ``--wall`` for wall time), the ratio, max |new − old|
relative to the image's maximum, and the roofline efficiency of the new frames with this run's
machine limits (`benchmarks.common.machine_limits`).

    python -m benchmarks.tp_frames_ab --baseline OTHER_CHECKOUT [--scene chess] [--shading vertex pixel]
        [--kinds V L E] [--frames 8] [--threads 1] [--wall] [--precompute-code OTHER_CHECKOUT]

``--precompute-code DIR``: take the precomputation from the cache entry of the code in DIR (a branch
that changes only run-time code has the same state; `benchmarks.common.apply_ab_options`).
"""
from __future__ import annotations

import argparse
import copy
import json
import statistics
import time


def main(argv=None) -> dict:
    from benchmarks.common import frame_args

    ap = frame_args(argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter),
                    scene="chess", frames=8)
    ap.add_argument("--shading", nargs="+", default=["vertex", "pixel"])
    ap.add_argument("--wall", action="store_true")
    ap.add_argument("--baseline", required=True)
    ap.add_argument("--precompute-code", default=None)
    ap.set_defaults(threads=1)
    a = ap.parse_args(argv)

    from benchmarks.common import precomputed, settle, setup
    from methods.core.fused import warming
    from methods.triple_product import TripleProduct
    from reports import measure
    from scenes.library import get_scene

    from benchmarks.common import apply_ab_options

    apply_ab_options(a)                                 # threads; --precompute-code
    from benchmarks.common import checkout_class, checkout_modules

    old_cls = checkout_class(a.baseline, "methods.triple_product.method", "TripleProduct")
    with checkout_modules(a.baseline):
        from methods.core.fused import warming as base_warming   # the baseline's own compile state
    scene = get_scene(a.scene, a.size)
    clock = time.perf_counter if a.wall else time.process_time
    B, P = measure.triad_bandwidth(), measure.matmul_peak()
    out = {"scene": a.scene, "threads": a.threads, "clock": "wall" if a.wall else "process_cpu",
           "triad_gbs": B / 1e9, "matmul_gflops": P / 1e9}
    for shading in a.shading:
        m, _ = precomputed(TripleProduct, scene, {} if shading == "pixel" else {"shading": "vertex"})
        base = copy.copy(m)
        base.__class__ = old_cls
        base.__dict__.pop("_perf_cache", None)
        base.stats = {}
        for kind in a.kinds:
            _, frames, gbs, _ = setup(scene, kind=kind, n_frames=a.frames, seed=0, spp_side=a.spp_side)
            with checkout_modules(a.baseline), base_warming():   # warm-up (compiles, builds tables), as the harness's
                base._light_key = None
                ref = base.render(frames[0], gbs[0])
            m._light_key = None
            with warming():
                img = m.render(frames[0], gbs[0])
            err = float((img - ref).abs().max() / ref.abs().max())
            t_old, t_new = [], []
            for f, g in zip(frames[1:], gbs[1:]):   # every timed frame's images compared too (the
                with checkout_modules(a.baseline):    # warm-up frame's lighting often takes another path)
                    settle(); t = clock(); ref = base.render(f, g); t_old.append(clock() - t)
                settle(); t = clock(); img = m.render(f, g); t_new.append(clock() - t)
                err = max(err, float((img - ref).abs().max() / ref.abs().max()))
            mo, mn = statistics.median(t_old), statistics.median(t_new)
            cost = m.frame_cost(kind, gbs[-1].num_samples, pixels=gbs[-1].height * gbs[-1].width)
            eff, bound = measure.roofline(cost.bytes, cost.flops, B, P, mn)
            r = {"old_ms": 1e3 * mo, "new_ms": 1e3 * mn, "ratio": mo / mn, "max_rel_diff": err,
                 "mflop": cost.flops / 1e6, "mbytes": cost.bytes / 1e6, "roofline_new": eff, "bound": bound}
            out[f"{shading}/{kind}"] = r
            print(shading, kind, json.dumps(r), flush=True)
    return out


if __name__ == "__main__":
    main()
