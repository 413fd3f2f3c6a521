"""Time of a ZH paper-config frame's steps, inclusive, inside harness-like frames (session 45, zh45; zh44's
`zh44_sections` with two changes): ``--wall`` adds up wall time (``perf_counter``) instead of thread CPU — at 2
threads the thread CPU of the calling thread says nothing about the other — and each frame renders a fresh clone of
its G-buffer (`benchmarks.zh45_harness_ab.fresh`: written just before the frame, as the harness's) after the 64 MB
write. Set ``PRTBENCH_SETTLE=0``: the perf harness does not idle before a frame. With session 46's
``ZHShadow.bound_glue`` on (the default) the fused pass, the split and the vertex table are called through bound
objects: their time shows under ``zn._fused_run``, ``z44._run`` and ``zn._vtable_run``, not under the wrappers'
labels (``--set``-style: set ``bound_glue = False`` on the class to see those).

    PRTBENCH_SETTLE=0 python -m benchmarks.zh45_sections KIND [--repeat 6] [--seed 0] [--threads 2] [--wall]

Session 45, bench creature, P, 6 sequences (24 frames), median wall ms, 1 / 2 threads: FRAME 3.56 / 2.40,
`zn.fused_pixels` 1.95 / 1.14, `_fill_visibility` 0.29 / 0.19, `z39.rest_lut` 0.24 / 0.17, `zn.plane_mask` 0.22 /
0.14, `zn.vertex_table` 0.19 / 0.12, `_posed_geometry` 0.14 / 0.11, `_plane_term` 0.14 / 0.13 (`zn.plane_u` 0.055 /
0.056: one thread below 4096 rows), `z39.screen8` 0.06 / 0.04, `_all` 0.04 / 0.04; ~0.4 ms of Python between.

zh44's notes (1 thread, thread CPU):
    python -m benchmarks.zh44_sections KIND [--repeat 8] [--seed 0] [--threads 1] [--config '{}']

Session 44, bench creature, paper config, 1 thread, median of 24 frames (ms): VB frame 3.80 = `zn.fused_pixels`
1.75 + the plane search and rest walk (`rt.first_plane` with `zn.plane_mask`, `z39.screen8`, `z39.rest_lut`) 0.71 +
`_vertex_table` 0.35 (its C product 0.24) + `rt.table` 0.29 (the new exponent's table: zh43p's A/B, `--repeat 24`,
never timed it) + `_region_materials` 0.17 + `_plane_term` 0.08 + `_all` 0.06 + `_lighting` 0.06 + ~0.3 of glue;
P frame 4.29 = `fused_pixels` 2.07 + the search and walk 0.74 + `_fill_visibility` 0.28 + `_pose_state` 0.27 (the
skinning 0.21) + `_vertex_table` 0.24 + `_plane_term` 0.15 + `_all` 0.09 + `_lazy_ok` 0.07 + glue. Each step
made cheaper alone (branch zh44-tried: the table 0.29 -> 0.18, the search and walk as one call 0.71 -> 0.72)
left whole frames at 0.98-1.04x against an A/A of 0.99-1.02x.
"""
from __future__ import annotations

import argparse
import collections
import functools
import gc
import json
import statistics
import time

WALL = False


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("kind")
    ap.add_argument("--repeat", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--config", default="{}")
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--wall", action="store_true", help="wall time (perf_counter) instead of thread CPU")
    a = ap.parse_args(argv)
    global WALL
    WALL = a.wall
    import torch

    torch.set_num_threads(a.threads)
    from benchmarks.common import precomputed, settle, setup
    from benchmarks.zh45_harness_ab import fresh
    from methods.zh_shadow import method as M, native as zn, native_threaded as z39, runtime as rt
    try:   # (zh44-tried's module, where it exists)
        from methods.zh_shadow import native_split as z44
    except ImportError:
        z44 = None

    rec: dict = collections.defaultdict(float)

    def wrap(obj, name, label):
        f = getattr(obj, name)

        @functools.wraps(f)
        def g(*args, **kw):
            t = time.perf_counter() if WALL else time.thread_time()
            r = f(*args, **kw)
            rec[label] += (time.perf_counter() if WALL else time.thread_time()) - t
            return r
        setattr(obj, name, g)

    C = M.ZHShadow
    for n in ["_pose_state", "_lighting", "_region_materials", "_table", "_render_planes", "_fill_visibility",
              "_plane_term", "_vertex_table", "_native_table", "_credit_referenced", "_lazy_ok", "_posed_geometry",
              "_fused_planes"]:
        if hasattr(C, n):
            wrap(C, n, n)
    wrap(M, "_all", "_all")
    for n in ["fused_pixels", "plane_mask", "region_tables", "vertex_table", "plane_u", "skin", "light_world"]:
        if hasattr(zn, n):
            wrap(zn, n, "zn." + n)
    # (zh46's `bound_glue` calls the passes through bound objects that skip the wrappers above: these are the passes
    # themselves, under both settings — with it off a pass counts under its wrapper's label and this one)
    for n in ["_fused_run", "_vtable_run"]:
        if hasattr(zn, n):
            wrap(zn, n, "zn." + n)
    if z44 is not None and hasattr(z44, "_run"):
        wrap(z44, "_run", "z44._run")
    for n in ["screen8", "rest_lut"]:
        wrap(z39, n, "z39." + n)
    for n in ["split", "light_table"]:
        if z44 is not None and hasattr(z44, n):
            wrap(z44, n, "z44." + n)
    try:
        from methods.zh_shadow import native_plane_terms as z45
        wrap(z45, "plane_terms", "z45.plane_terms")
    except ImportError:
        pass
    for n in ["first_plane", "_plane_counts", "table", "diffuse_at"]:
        wrap(rt, n, "rt." + n)
    scene, _, _, _ = setup(a.scene, "bench", kind="V", n_frames=1)
    m0, _ = precomputed(C, scene, json.loads(a.config))
    junk = torch.empty(64 << 18)
    per: dict = collections.defaultdict(list)
    for r in range(a.repeat):
        _, frames, gbs, _ = setup(scene, "bench", kind=a.kind, n_frames=5, seed=a.seed + r)
        m = m0.with_render_config()
        for i, (f, gb) in enumerate(zip(frames, gbs)):
            junk.fill_(float(i))
            float(junk[::4096].sum())
            settle()
            gb = fresh(gb)   # (the harness's state: a G-buffer written just now, `zh45_harness_ab.fresh`)
            rec.clear()
            gc.disable()
            t = time.perf_counter() if WALL else time.thread_time()
            m.render(f, gb)
            dt = (time.perf_counter() if WALL else time.thread_time()) - t
            gc.enable()
            if i:
                per["FRAME"].append(dt)
                for k in set(rec) | set(per):
                    if k != "FRAME":
                        per[k].append(rec.get(k, 0.0))
    out = {k: 1e3 * statistics.median(v) for k, v in per.items()}
    for k, v in sorted(out.items(), key=lambda kv: -kv[1]):
        print(f"  {k:28s} {v:.3f} ms")
    return out


if __name__ == "__main__":
    main()
