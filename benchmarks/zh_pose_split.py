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

    python -m benchmarks.zh_pose_split [--frames 12] [--threads 1] [--settle 0.2] [--precompute-code DIR]
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
    ap.add_argument("--precompute-code", default=None)
    a = ap.parse_args(argv)
    apply_ab_options(a)
    from methods.zh_shadow import native as zn
    from methods.zh_shadow.method import ZHShadow

    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(ZHShadow, scene, CONFIG)
    _, frames, gbs, _ = setup(scene, "bench", kind="P", n_frames=a.frames + 2, seed=a.seed)
    m = m.with_render_config()
    for f, g in zip(frames[:2], gbs[:2]):
        m.render(f, g)
    times: dict[str, list[float]] = {}

    def wrap(obj, name: str, label: str) -> None:
        fn = getattr(obj, name)

        def timed(*args, **kw):
            c = time.process_time()
            out = fn(*args, **kw)
            times.setdefault(label, []).append(time.process_time() - c)
            return out
        setattr(obj, name, timed)

    originals = {n: getattr(zn, n) for n in ("referenced_mask", "front_columns", "pose_columns", "pose_radiance",
                                              "resolve_table", "pose_sh")}
    for obj, name, label in ((m, "_posed_geometry", "skinning"), (zn, "referenced_mask", "referenced"),
                             (zn, "front_columns", "front"), (zn, "pose_columns", "pose product"),
                             (zn, "pose_sh", "pose product + eq. 1 (one C call, zh36o)"),
                             (m, "_pose_visibility", "visibility (product + eq. 1)"),
                             (zn, "pose_radiance", "pose pass"), (zn, "resolve_table", "resolve"),
                             (m, "_front_radiance", "front radiance (front, visibility, pose pass, glue)")):
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
