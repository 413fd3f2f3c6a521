"""Where an order-8 vertex-shaded P frame's time goes (session 35, zh35o): the frame's steps timed in place
(process CPU, 1 thread by default, each frame after ``--settle`` seconds idle as `benchmarks.common.settle`),
by wrapping the functions it calls — the skinning (`ZHShadow._posed_geometry`), the referenced vertices
(`native.referenced_mask`), the front-facing ones (`native.front_columns`), the pose product
(`native.pose_columns`), eq. 1 (`ZHShadow._pose_visibility` minus the product), the C pose pass
(`native.pose_radiance`), `ZHShadow._front_radiance` (front, visibility, pose pass and its glue), the resolve
(`native.resolve_table`) and the whole frame — medians over the frames. At 1 thread, 2026-12-06, load ~8 on 2
cores: skinning 0.40, referenced 0.27, front 0.15, pose product 0.46, visibility 1.20 (eq. 1 ~0.73), pose pass
0.68, front radiance 2.48, resolve 0.82, frame 4.47 ms. Session 36 (zh36o): the product and eq. 1 are one C call
(`native.pose_sh`; "pose product" then not called unless ``native_eq1`` is off).

``--config '{}'`` splits the paper configuration's P frame instead (session 37, zh37p): skinning, the pose's
visibility (`native.pose_sh` over every vertex), the plane term, the per-vertex table, the fused pass
(`native.fused_pixels`) and the plane search's kernels. Session 37, 1 thread, load 6-8 on 2 cores: skinning 0.41,
visibility 1.11 (`pose_sh` 0.86), plane term 0.39, vertex table 1.05, plane mask 0.59, `fused_pixels` 4.44, frame
9.37 ms. Computing only the referenced vertices' visibility (4.4 K of 13.4 K: `referenced_ids` ~0.65 ms, then
`pose_sh` on those ~0.7 ms right after the settle) was tried and dropped: the face scan costs about what the
skipped rows save (their reads are scattered).

    python -m benchmarks.zh_pose_split [--frames 12] [--threads 1] [--settle 0.2] [--config JSON] [--precompute-code DIR]
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

from benchmarks.common import apply_ab_options, precomputed, setup

CONFIG = {"order": 8, "shading": "vertex", "specular": "cosine"}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--settle", type=float, default=0.2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--config", default=json.dumps(CONFIG), help="the ZH configuration (default order 8)")
    ap.add_argument("--precompute-code", default=None)
    a = ap.parse_args(argv)
    apply_ab_options(a)
    from methods.zh_shadow import native as zn
    from methods.zh_shadow.method import ZHShadow

    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(ZHShadow, scene, json.loads(a.config))
    _, frames, gbs, _ = setup(scene, "bench", kind="P", n_frames=a.frames + 2, seed=a.seed)
    m = m.with_render_config()
    for f, g in zip(frames[:2], gbs[:2]):
        m.render(f, g)
    times: dict[str, list[float]] = {}

    def wrap(obj, name: str, label: str) -> None:
        if not hasattr(obj, name):   # (a stage of another configuration or code version)
            return
        fn = getattr(obj, name)

        def timed(*args, **kw):
            c = time.process_time()
            out = fn(*args, **kw)
            times.setdefault(label, []).append(time.process_time() - c)
            return out
        setattr(obj, name, timed)

    kernels = ("referenced_mask", "front_columns", "pose_columns", "pose_radiance", "resolve_table", "pose_sh",
               "resolve_vector", "skin_vector",   # (session 38's vector loops, where they run)
               # the paper configuration's (pixel-shaded planes)
               "fused_pixels", "referenced_lut", "plane_u", "screen8", "plane_mask", "rest_screen")
    originals = {n: getattr(zn, n) for n in kernels if hasattr(zn, n)}
    for obj, name, label in ((m, "_posed_geometry", "skinning"), (zn, "referenced_mask", "referenced"),
                             (zn, "front_columns", "front"), (zn, "pose_columns", "pose product"),
                             (zn, "pose_sh", "pose product + eq. 1 (one C call, zh36o)"),
                             (m, "_pose_visibility", "visibility (product + eq. 1)"),
                             (zn, "pose_radiance", "pose pass"), (zn, "resolve_table", "resolve"),
                             (zn, "resolve_vector", "resolve (vector, zh38p)"), (zn, "skin_vector", "skin (vector, zh38p)"),
                             (m, "_front_radiance", "front radiance (front, visibility, pose pass, glue)"),
                             (m, "_plane_term", "plane term"), (m, "_vertex_table", "vertex table"),
                             (m, "_fused_planes", "fused planes (all)"),
                             *((zn, n, "native." + n) for n in ("fused_pixels", "referenced_lut", "plane_u", "screen8",
                                                                 "plane_mask", "rest_screen"))):
        wrap(obj, name, label)
    frame = []
    for f, g in zip(frames[2:], gbs[2:]):
        time.sleep(a.settle)
        c = time.process_time()
        m.render(f, g)
        frame.append(time.process_time() - c)
    for n, fn in originals.items():   # (the module's functions back: the wrappers only for this run)
        setattr(zn, n, fn)
    times["frame"] = frame
    out = {k: 1e3 * statistics.median(v) for k, v in times.items()}
    for k, v in out.items():
        print(f"{k:58s} {v:7.3f} ms  ({len(times[k])} calls)")
    print(json.dumps({"threads": a.threads, "ms": out}))
    return out


if __name__ == "__main__":
    main()
