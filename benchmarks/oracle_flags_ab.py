"""Same-process A/B of the oracle's module switches (issue 14, session 35): frames rendered with the named
switches of ``methods.oracle`` on (new) and off (old), alternating which goes first, process CPU and wall,
medians, and whether every image and `frame_cost` count is the same bit for bit.

    python -m benchmarks.oracle_flags_ab [--scene creature] [--kind V] [--frames 16] [--threads 1]
        [--flags DIRECT FRAME_ROWS FACE_CACHE]

Each side is its own `Oracle` (its own work arrays), frame 0 untimed (inside ``methods.core.fused.warming``),
each timed frame after ``benchmarks.common.settle``. `benchmarks.oracle_ab` compares whole checkouts; this
compares a change's fast path with the slow path kept beside it, in one tree.
"""
from __future__ import annotations

import argparse
import statistics
import time


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--kind", default="V")
    ap.add_argument("--frames", type=int, default=16)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--flags", nargs="+", default=["DIRECT", "FRAME_ROWS", "FACE_CACHE"])
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(a.threads)
    import methods.oracle as O
    from benchmarks.common import settle, setup
    from methods.core.fused import warming

    scene, frames, gbs, _ = setup(a.scene, a.size, kind=a.kind, n_frames=a.frames)

    def switch(v: bool) -> None:
        for f in a.flags:
            if not hasattr(O, f):
                raise SystemExit(f"methods.oracle has no switch {f}")
            setattr(O, f, v)

    saved = {f: getattr(O, f) for f in a.flags}
    m = {v: O.Oracle(light_samples=4, brdf_samples=4) for v in (True, False)}
    try:
        for v in (True, False):
            m[v].precompute(scene)
            switch(v)
            with warming():
                m[v].render(frames[0], gbs[0])
        cpu, wall, same = {True: [], False: []}, {True: [], False: []}, True
        for i in range(1, len(frames)):
            img = {}
            for v in ((True, False) if i % 2 else (False, True)):
                switch(v)
                settle()
                t0, w0 = time.process_time(), time.perf_counter()
                img[v] = m[v].render(frames[i], gbs[i])
                cpu[v].append(time.process_time() - t0)
                wall[v].append(time.perf_counter() - w0)
            same &= torch.equal(img[True], img[False]) and m[True]._last == m[False]._last
    finally:
        for f, v in saved.items():
            setattr(O, f, v)
    c = {v: 1e3 * statistics.median(x) for v, x in cpu.items()}
    w = {v: 1e3 * statistics.median(x) for v, x in wall.items()}
    out = {"scene": a.scene, "kind": a.kind, "threads": a.threads, "flags": a.flags, "cpu_ms": c, "wall_ms": w,
           "cpu_ratio": c[False] / c[True], "wall_ratio": w[False] / w[True], "same": same}
    print(f"oracle {a.scene} {a.kind} ({a.size}), {a.threads} threads, {' '.join(a.flags)} off → on: "
          f"cpu {c[False]:.1f} → {c[True]:.1f} ms ({out['cpu_ratio']:.3f}x), wall {w[False]:.1f} → {w[True]:.1f} ms "
          f"({out['wall_ratio']:.3f}x), images and counts {'bit-identical' if same else 'DIFFER'}")
    return out


if __name__ == "__main__":
    main()
