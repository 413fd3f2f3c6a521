"""Oracle frame times, the eager estimator (``Oracle.render_reference``) vs the compiled one
(``Oracle.render``) in one process, and the shadow-ray test that bounds a frame (issue 14).

    python -m benchmarks.oracle [--scene chess] [--size bench] [--config '{"brdf_samples":4,"light_samples":4}']
                                [--frames 5] [--threads 2] [--spp-side 2] [--kinds V VB]

Per sequence kind: frame 0 warms up both paths (compilation), then frames 1.. are rendered by both,
alternating which goes first; prints the median wall and process-CPU time of each, their ratio,
the roofline efficiency max(bytes / triad bandwidth, flops / matmul peak) / time with
``Oracle.frame_cost``'s bytes and flops (not its rays: the suite's roof for them, the scene's ray rate,
is measured by the harness, ``reports.measure.ray_rate``; nor the transcendentals) and
the largest |fast − reference| pixel difference. Then micro-benchmarks on the last frame's shadow
rays (the live rays the estimator traces): ``occluded`` as the oracle calls it (torch → numpy →
Dr.Jit and back) and Mitsuba's ``scene.ray_test`` alone on rays already in Dr.Jit arrays, in rays
per second — and the share of a frame the tracer takes.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from benchmarks.common import frame_args, machine_limits, setup, wall_cpu_time
from methods.oracle import Oracle
from reports import measure


def tracer(m: Oracle, frame, gb, repeats: int = 5) -> dict:
    """Seconds (wall, CPU) of the shadow-ray test of ``frame``'s rays: through ``occluded`` and
    Mitsuba's ``ray_test`` alone (rays already in Dr.Jit arrays; embreex: ``occluded`` only)."""
    import methods.oracle as O

    rays = {}
    own, O.OWN_TRACER = O.OWN_TRACER, False  # Mitsuba's tracer (the oracle's own: `benchmarks.oracle_stages`)
    try:
        m.render(frame, gb)
    finally:
        O.OWN_TRACER = own
    vis = m._vis[1]
    real = vis.occluded

    def grab(o, d):
        rays["o"], rays["d"] = o.clone(), d.clone()
        return real(o, d)

    vis.occluded = grab
    O.OWN_TRACER = False
    try:
        m.render(frame, gb)
    finally:
        vis.occluded = real
        O.OWN_TRACER = own
    o, d = rays["o"], rays["d"]
    out = {"rays": int(o.shape[0]), "backend": vis.backend, "occluded_s": wall_cpu_time(lambda: vis.occluded(o, d), repeats)}
    if vis.backend == "mitsuba":
        import drjit as dr

        out["ray_test_s"] = wall_cpu_time(measure.tracer_call(vis, o.numpy(), d.numpy()), repeats)
        out["drjit_threads"] = dr.thread_count()
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    frame_args(ap, scene="chess", config='{"brdf_samples":4,"light_samples":4}', frames=5, kinds=("V", "VB"))
    ap.add_argument("--json", default=None, help="write the results here")
    args = ap.parse_args(argv)
    torch.set_num_threads(args.threads)
    bw, peak = [measure.triad_bandwidth()], [measure.matmul_peak()]
    config = json.loads(args.config)
    res: dict = {"scene": args.scene, "size": args.size, "config": config, "threads": args.threads, "kinds": {}}
    last = None
    for kind in args.kinds:
        scene, frames, gbs, _ = setup(args.scene, args.size, kind=kind, n_frames=args.frames + 1,
                                      spp_side=args.spp_side)
        m = Oracle(**config)
        m.precompute(scene)
        m.render(frames[0], gbs[0])
        m.render_reference(frames[0], gbs[0])
        t = {"reference": ([], []), "fast": ([], [])}
        err = 0.0
        for i, (f, g) in enumerate(zip(frames[1:], gbs[1:])):
            imgs = {}
            for w in (("reference", "fast") if i % 2 else ("fast", "reference")):
                fn = m.render_reference if w == "reference" else m.render
                t0, c0 = time.perf_counter(), time.process_time()
                imgs[w] = fn(f, g)
                t[w][0].append(time.perf_counter() - t0)
                t[w][1].append(time.process_time() - c0)
            err = max(err, (imgs["fast"] - imgs["reference"]).abs().max().item())
        cost = m.frame_cost(kind, gbs[-1].num_samples, pixels=gbs[-1].height * gbs[-1].width)
        r = {"max_abs_diff": err, "bytes": cost.bytes, "flops": cost.flops}
        for w, (ws, cs) in t.items():
            r[f"{w}_median_s"], r[f"{w}_cpu_s"] = statistics.median(ws), statistics.median(cs)
            r[f"{w}_bytes"], r[f"{w}_flops"] = cost.bytes, cost.flops
        res["kinds"][kind] = r
        last = (m, frames[-1], gbs[-1])
    B, Pk = machine_limits(res, bw, peak)
    from benchmarks.common import roofline_columns

    roofline_columns(res["kinds"], ("reference", "fast"), B, Pk)
    res["tracer"] = tracer(*last)
    print(f"oracle {args.scene} ({args.size}) {config}, {args.threads} threads; triad {B / 1e9:.1f} GB/s, "
          f"matmul {Pk / 1e9:.1f} GFLOP/s")
    print(f"{'kind':5s} {'ref ms':>8s} {'fast ms':>8s} {'ratio':>6s} {'ref cpu':>8s} {'fast cpu':>8s} {'ratio':>6s} "
          f"{'eff ref':>8s} {'eff fast':>8s} {'max|d|':>9s}")
    for kind, r in res["kinds"].items():
        print(f"{kind:5s} {r['reference_median_s'] * 1e3:8.0f} {r['fast_median_s'] * 1e3:8.0f} "
              f"{r['reference_median_s'] / r['fast_median_s']:6.2f} {r['reference_cpu_s'] * 1e3:8.0f} "
              f"{r['fast_cpu_s'] * 1e3:8.0f} {r['reference_cpu_s'] / r['fast_cpu_s']:6.2f} "
              f"{100 * r['reference_efficiency']:7.2f}% {100 * r['fast_efficiency']:7.2f}% {r['max_abs_diff']:9.2e}")
    tr = res["tracer"]
    fast_cpu = statistics.median(r["fast_cpu_s"] for r in res["kinds"].values())
    print(f"shadow rays of the last frame: {tr['rays'] / 1e6:.2f} M ({tr['backend']})")
    for k in ("occluded_s", "ray_test_s"):
        if k in tr:
            w, c = tr[k]["wall"], tr[k]["cpu"]
            print(f"  {k[:-2]:9s} {w * 1e3:7.1f} ms wall ({tr['rays'] / w / 1e6:6.1f} Mrays/s), {c * 1e3:7.1f} ms CPU "
                  f"({tr['rays'] / c / 1e6:6.1f} Mrays/CPU-s) = {100 * c / fast_cpu:.0f} % of a fast frame's CPU")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=1)
    return res


if __name__ == "__main__":
    main()
