"""Where an oracle frame's time goes (issue 14): process CPU ms per stage of `Oracle.render`, median
over timed frames, frames 0-1 untimed (frame 0 inside ``methods.core.fused.warming``).

    python -m benchmarks.oracle_stages [--scene chess] [--kind V] [--frames 6] [--threads 1]
        [--config '{"light_samples":4,"brdf_samples":4}']

Each stage function is wrapped (its own time, nested calls included in their callers'): the
env-map cell search (`_light_cells` / `_guide_stage`), the geometric normals, the sample blocks'
layout (`_soa_blocks`), the pre-trace graph (`_pretrace_stage`), the shadow rays (``occluded``, the
tracer alone) and their gathers (`_trace_soa`), the radiance look-up (`_shade_block_stage`), the
resolve; on the C loops' path (``methods.oracle.native_rays``) their cell search + per-ray work
(``native.pretrace``), the trace (``native.trace``: Mitsuba's ``ray_test`` on the rays as they are,
or with ``--time-occluded`` the live rays gathered for the tracer's ``occluded``, timed alone) and
radiance sum (``native.shade``); on the oracle's own tracer (``methods.oracle.embree_rays``, session 34)
its trace (``own.trace``) and a new pose's refit (``own.repose``). The rest of a frame (random numbers, index arithmetic, copies) is the frame minus them.
"""
from __future__ import annotations

import argparse
import collections
import json
import statistics
import time


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--kind", default="V")
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--config", default='{"light_samples":4,"brdf_samples":4}')
    ap.add_argument("--time-occluded", action="store_true",
                    help="time the tracer's occluded alone (the C loops' path then gathers the live rays for it)")
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(a.threads)
    import methods.base as base
    import methods.oracle as O
    from benchmarks.common import setup
    from methods.core.fused import warming

    scene, frames, gbs, _ = setup(a.scene, a.size, kind=a.kind, n_frames=max(a.frames, 3))
    m = O.Oracle(**json.loads(a.config))
    m.precompute(scene)
    T: dict = collections.defaultdict(float)

    def timed(f, label):
        def g(*args, **kw):
            t0 = time.process_time()
            try:
                return f(*args, **kw)
            finally:
                T[label] += time.process_time() - t0
        if hasattr(f, "eager"):
            g.eager = f.eager
        return g

    for name in ("_pretrace_stage", "_shade_block_stage", "_guide_stage", "_soa_blocks", "geometric_normals"):
        setattr(O, name, timed(getattr(O, name), name))
    for name in ("_light_cells", "_trace_soa"):
        setattr(O.Oracle, name, staticmethod(timed(O.Oracle.__dict__[name].__func__, name)))
    base.GBuffer.resolve = timed(base.GBuffer.resolve, "resolve")
    import methods.oracle.native_rays as N  # the C loops' path (`Oracle._shade_native`)

    for name in ("pretrace", "trace", "shade"):
        setattr(N, name, timed(getattr(N, name), f"native.{name}"))
    import methods.oracle.embree_rays as E  # the oracle's own tracer (session 34)

    for name in ("trace", "repose"):
        setattr(E.EmbreeTracer, name, timed(getattr(E.EmbreeTracer, name), f"own.{name}"))
    if a.time_occluded:  # Mitsuba's tracer's ``occluded``: the oracle's own tracer off
        O.OWN_TRACER = False
    with warming():
        m.render(frames[0], gbs[0])
    m.render(frames[1], gbs[1])
    if a.time_occluded:  # replacing ``occluded`` turns `native_rays.trace`'s direct hand-off to Mitsuba off
        vis = m._vis[1]
        type(vis).occluded = timed(type(vis).occluded, "occluded (in _trace_soa)")
    runs = []
    for i in range(2, len(frames)):
        T.clear()
        t0 = time.process_time()
        m.render(frames[i], gbs[i])
        runs.append((time.process_time() - t0, dict(T)))
    out = {"scene": a.scene, "kind": a.kind, "threads": a.threads,
           "frame_ms": 1e3 * statistics.median(r[0] for r in runs),
           "stages_ms": {k: 1e3 * statistics.median(r[1].get(k, 0.0) for r in runs) for k in runs[0][1]},
           "rays": (m.n_light + m.n_brdf) * m._last[1], "live_rays": m._last[2]}
    print(f"oracle {a.scene} {a.kind} ({a.size}), {a.threads} threads: frame {out['frame_ms']:.1f} ms CPU, "
          f"{out['rays']} rays, {out['live_rays']} live")
    for k, v in out["stages_ms"].items():
        print(f"  {k:28s} {v:8.1f} ms")
    return out


if __name__ == "__main__":
    main()
