"""Where a paper-configuration (``{}``) P frame's time goes (session 37, zh37p): the frame's steps timed in place
(process CPU, 1 thread by default, each frame after ``--settle`` seconds idle), by wrapping the functions it
calls — skinning (`ZHShadow._posed_geometry`), the pose's visibility (`ZHShadow._pose_visibility`), the plane
term (`ZHShadow._plane_term`), the per-vertex table (`ZHShadow._vertex_table`), the fused pass
(`native.fused_pixels`) and the whole frame — medians over the frames.

    python -m benchmarks.zh_paper_pose_split [--frames 12] [--threads 1] [--settle 0.2] [--config '{}']

Session 37 (zh37p), 1 thread, host load 6-8 on 2 cores, before the referenced visibility: skinning 0.41, visibility
1.11 (`pose_sh` over every vertex 0.86), plane term 0.39, vertex table 1.05, plane mask 0.59, `fused_pixels` 4.44,
frame 9.37 ms; after it: `referenced_ids` ~0.65 and `pose_sh` (4.4 K of 13.4 K vertices) ~0.7 ms right after the
settle — the face scan costs about what the skipped rows saved (the rows' reads are scattered).
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

from benchmarks.common import apply_ab_options, precomputed, setup


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--settle", type=float, default=0.2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--config", default="{}")
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
        if not hasattr(obj, name):
            return
        fn = getattr(obj, name)

        def timed(*args, **kw):
            c = time.process_time()
            out = fn(*args, **kw)
            times.setdefault(label, []).append(time.process_time() - c)
            return out
        setattr(obj, name, timed)

    names = [n for n in ("fused_pixels", "pose_sh", "referenced_lut", "plane_u", "screen8", "plane_mask",
                         "rest_screen", "skin", "referenced_ids") if hasattr(zn, n)]
    originals = {n: getattr(zn, n) for n in names}
    for obj, name, label in ((m, "_posed_geometry", "skinning"), (m, "_pose_visibility", "visibility"),
                             (m, "_plane_term", "plane term"), (m, "_vertex_table", "vertex table"),
                             (m, "_fused_planes", "fused planes (all)"), (m, "_pose_state", "pose state"),
                             (m, "_referenced_rows", "referenced rows (ids + pose_sh)"),
                             *((zn, n, "native." + n) for n in names)):
        wrap(obj, name, label)
    frame = []
    for f, g in zip(frames[2:], gbs[2:]):
        time.sleep(a.settle)
        c = time.process_time()
        m.render(f, g)
        frame.append(time.process_time() - c)
    for n, fn in originals.items():
        setattr(zn, n, fn)
    times["frame"] = frame
    out = {k: 1e3 * statistics.median(v) for k, v in times.items()}
    for k, v in out.items():
        print(f"{k:40s} {v:7.3f} ms  ({len(times[k])} calls)")
    print(json.dumps({"threads": a.threads, "ms": out}))
    return out


if __name__ == "__main__":
    main()
