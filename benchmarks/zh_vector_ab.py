"""Kernel A/B of session 38's (zh38p) vector loops against the loops they replace, same process, alternating,
process CPU, 1 thread by default, medians: the vertex-shaded frames' resolve (`native.resolve_vector` against
`native.resolve_table`, on each frame's own G-buffer and random vertex colours) and a P frame's skinning
(`native.skin_vector` against `native.skin`, on each frame's pose); each pair's outputs compared bit for bit.
``--cold``: a 64 MB buffer written before each call (the G-buffer and tables out of the caches).

    python -m benchmarks.zh_vector_ab [--frames 12] [--repeat 20] [--threads 1] [--cold]

Session 38, 1 thread, load ~9 on 2 cores, warm: resolve 0.73 -> 0.46 ms, skinning 0.162 -> 0.045 ms.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--repeat", type=int, default=20)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cold", action="store_true")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    from benchmarks.common import setup
    from methods.zh_shadow import native as zn

    scene, frames, gbs, _ = setup("creature", "bench", kind="P", n_frames=a.frames)
    geom = scene.rest_geometry()
    N, F = int(geom.num_vertices), geom.F
    st = zn.skin_setup(scene)
    vs = zn.skin_vector_setup(st)
    g = torch.Generator().manual_seed(0)
    vals = [torch.rand(N, 3, generator=g) for _ in frames]
    big = torch.zeros(64 << 20, dtype=torch.uint8) if a.cold else None
    calls = {
        "resolve": (lambda i: zn.resolve_table(vals[i], F, gbs[i].face, gbs[i].bary, gbs[i].hit, gbs[i].height,
                                               gbs[i].width, gbs[i].spp_side),
                    lambda i: zn.resolve_vector(vals[i], F, gbs[i].face, gbs[i].bary, gbs[i].hit, gbs[i].height,
                                                gbs[i].width, gbs[i].spp_side)),
        "skin": (lambda i: zn.skin(st, torch.as_tensor(frames[i].pose).float()),
                 lambda i: zn.skin_vector(st, vs, torch.as_tensor(frames[i].pose).float())),
    }
    out = {}
    for name, (old, new) in calls.items():
        ts: dict[str, list[float]] = {"old": [], "new": []}
        for i in range(len(frames)):   # (the same outputs: the new loop's bits are the old one's)
            x, y = old(i), new(i)
            assert y is not None, f"{name}: the vector loop does not run here"
            x, y = (x, y) if isinstance(x, tuple) else ((x,), (y,))
            assert all(torch.equal(p, q) for p, q in zip(x, y)), name
        for r in range(a.repeat):
            for i in range(len(frames)):
                for label, fn in ((("old", old), ("new", new)) if (r + i) % 2 == 0 else (("new", new), ("old", old))):
                    if big is not None:
                        big.add_(1)
                    c = time.process_time()
                    fn(i)
                    ts[label].append(time.process_time() - c)
        o, n = statistics.median(ts["old"]), statistics.median(ts["new"])
        out[name] = {"old_ms": 1e3 * o, "new_ms": 1e3 * n, "ratio": o / n}
        print(f"{name:8s} old {1e3 * o:7.3f} ms  new {1e3 * n:7.3f} ms  ratio {o / n:5.2f}  (bits equal)")
    print(json.dumps({"threads": a.threads, "cold": a.cold, **out}))
    return out


if __name__ == "__main__":
    main()
