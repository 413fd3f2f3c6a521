"""Session 39's thread changes of TripleProduct's per-vertex passes, each pass alone on the arguments
captured from real frames (creature bench, vertex shading), old and new alternating in one process,
median wall ms over ``--reps`` (order alternating):

* points (`native.POINTS_BLOCK`), comb (`native_light.COMB_BLOCK`, E frames) and project
  (`native_light.PROJECT_BLOCK`, VL frames) at ``--threads`` (2): static split (block 0) against
  dynamic blocks;
* hit_faces (`native.HIT_THREADS`) and box (`native_light.BOX_THREADS`, E frames): one thread (the
  switch off) against the threads.

On a host shared with other work the dynamic schedule's gain is larger than on a quiet one (a
thread whose core is busy takes fewer blocks); ``--threads 1`` times the 1-thread paths (CPU).

    python -m benchmarks.tp_passes_ab [--threads 2] [--reps 100] [--precompute-code DIR]
"""
from __future__ import annotations

import argparse
import statistics
import time


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=100)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--precompute-code", default=None)
    a = ap.parse_args(argv)
    from benchmarks.common import apply_ab_options, precomputed, setup
    apply_ab_options(a)
    import torch

    from methods.core.fused import warming
    from methods.triple_product import TripleProduct, native, native_light as nl
    from scenes.library import get_scene

    scene = get_scene(a.scene, "bench")
    m, _ = precomputed(TripleProduct, scene, {"shading": "vertex"})
    cap: dict[str, tuple] = {}
    orig = {"points": (native, "points"), "comb": (nl, "_comb_run"), "project": (nl, "project"),
            "hit_faces": (native, "hit_faces"), "box": (nl, "box")}
    fns = {k: getattr(mod, name) for k, (mod, name) in orig.items()}

    def rec(k):
        def g(*args, **kw):
            cap[k] = (args, kw)
            return fns[k](*args, **kw)
        return g
    for k, (mod, name) in orig.items():
        setattr(mod, name, rec(k))
    for kind in ("E", "VL"):
        _, frames, gbs, _ = setup(scene, kind=kind, n_frames=3, seed=0, spp_side=2)
        with warming():
            m.render(frames[0], gbs[0])
        for f, g in zip(frames[1:], gbs[1:]):
            m.render(f, g)
        if kind == "E":
            cap["points_E"] = cap["points"]
    for k, (mod, name) in orig.items():
        setattr(mod, name, fns[k])

    def call(k):
        args, kw = cap[k]
        if k == "comb":
            fn, name, pairs, head, tables, out = args
            return lambda: fns[k](fn, name, pairs, head, tables, out.clone())
        if k == "project":
            return lambda: fns[k](*args[:-1], args[-1].clone())
        if k == "points_E":
            return lambda: fns["points"](*args, **kw)
        return lambda: fns[k](*args, **kw)

    switch = {"points": (native, "POINTS_BLOCK"), "points_E": (native, "POINTS_BLOCK"), "comb": (nl, "COMB_BLOCK"),
              "project": (nl, "PROJECT_BLOCK"), "hit_faces": (native, "HIT_THREADS"), "box": (nl, "BOX_THREADS")}
    torch.set_num_threads(a.threads)
    res = {}
    for k in ("points_E", "points", "comb", "project", "hit_faces", "box"):
        mod, name = switch[k]
        new_val = getattr(mod, name)
        old_val = False if isinstance(new_val, bool) else 0
        run = call(k)
        t = {0: [], 1: []}
        outs = {}
        for r in range(a.reps):
            for s in ((0, 1) if r % 2 == 0 else (1, 0)):
                setattr(mod, name, new_val if s else old_val)
                t0 = time.perf_counter()
                o = run()
                t[s].append(time.perf_counter() - t0)
                outs[s] = o
        setattr(mod, name, new_val)
        o0, o1 = outs[0], outs[1]
        same = all((torch.equal(x, y) if isinstance(x, torch.Tensor) else x == y) for x, y in zip(o0, o1)) \
            if isinstance(o0, tuple) else torch.equal(o0, o1)
        old_ms, new_ms = 1e3 * statistics.median(t[0]), 1e3 * statistics.median(t[1])
        res[k] = {"old_ms": old_ms, "new_ms": new_ms, "ratio": old_ms / new_ms, "same": bool(same)}
        print(f"{k:10s} old {old_ms:.3f} ms  new {new_ms:.3f} ms  ratio {old_ms / new_ms:.2f}  same {same}", flush=True)
    return res


if __name__ == "__main__":
    main()
