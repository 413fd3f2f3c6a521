"""Where an order-8 vertex-shaded ZH frame's time goes between its C calls and the Python / torch glue around them
(session 43, zh43o): bench creature, ``--threads`` torch threads (default 1), a 64 MB write and ``--sleep`` seconds
idle before every frame (the perf harness's cold caches), GC off, the frames 1..4 of a 5-frame ``--kind`` sequence
cycled ``--repeat`` times after frames 0-2 untimed. Every ctypes function of every loaded library (and the bound
calls' kept function pointers) is wrapped by a timer: per frame the wall time inside C calls, per C function, and
the rest ("non-C": what a 2-thread frame runs serially, plus the serial C loops). Medians over the frames.

    PYTHONPATH=. python -m benchmarks.zh43o_serial [--kind P] [--repeat 60] [--root /work/wt/base43]

``--root``: that checkout's ``methods`` imported instead (before anything imports it). Separate processes: absolute
times under whatever load there is; compare two roots in alternating runs (zh43o, 1 thread, load ~8: base43 P frame
2.37 ms, C 1.56, non-C 0.80; zh43o 1.70 ms, C 1.23, non-C 0.47).
"""
from __future__ import annotations

import argparse
import collections
import ctypes
import gc
import statistics
import sys
import time
from types import SimpleNamespace


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kind", default="P")
    ap.add_argument("--repeat", type=int, default=60)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--sleep", type=float, default=0.01)
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--root", default=None, help="import ``methods`` from this checkout (before anything imports it)")
    a = ap.parse_args(argv)
    if a.root:
        sys.path.insert(0, a.root)
    from benchmarks.common import apply_ab_options, precomputed, setup

    apply_ab_options(SimpleNamespace(threads=a.threads, precompute_code=a.precompute_code))
    import torch

    from methods.zh_shadow.method import ZHShadow

    print("methods from", ZHShadow.__module__, sys.modules[ZHShadow.__module__].__file__)
    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(ZHShadow, scene, {"order": 8, "shading": "vertex", "specular": "cosine"})
    _, frames, gbs, _ = setup(scene, "bench", kind=a.kind, n_frames=5, seed=0)
    m = m.with_render_config()
    for f, g in zip(frames[:3], gbs[:3]):
        m.render(f, g)
    acc: dict = collections.defaultdict(float)

    def timed(name, fn):
        def w(*args):
            c = time.perf_counter()
            r = fn(*args)
            acc[name] += time.perf_counter() - c
            return r
        return w

    gc.collect()
    for lib in [o for o in gc.get_objects() if isinstance(o, ctypes.CDLL)]:
        for name, fp in list(vars(lib).items()):
            if isinstance(fp, ctypes._CFuncPtr):
                setattr(lib, name, timed(name, fp))
    for attr in ("_pose_bound", "_pose_cols_bound", "_skin"):   # (the bound calls keep their function pointers)
        b = getattr(m, attr, None)
        b = b[-1] if isinstance(b, tuple) else b
        if b is not None and hasattr(b, "fn"):
            b.fn = timed(attr, b.fn)
    buf = torch.empty(16 * 1024 * 1024)
    ts, cs = [], []
    gc.disable()
    try:
        for _ in range(a.repeat):
            for i, (f, g) in enumerate(zip(frames[1:], gbs[1:])):
                buf.fill_(float(i))
                time.sleep(a.sleep)
                acc.clear()
                c = time.perf_counter()
                m.render(f, g)
                ts.append(time.perf_counter() - c)
                cs.append(dict(acc))
    finally:
        gc.enable()
    out = {"frame": 1e3 * statistics.median(ts), "C": 1e3 * statistics.median([sum(d.values()) for d in cs]),
           "non-C": 1e3 * statistics.median([t - sum(d.values()) for t, d in zip(ts, cs)])}
    for k in sorted({k for d in cs for k in d}):
        out["C " + k] = 1e3 * statistics.median([d.get(k, 0.0) for d in cs])
    for k, v in out.items():
        print(f"{k:34s} {v:7.3f} ms")
    return out


if __name__ == "__main__":
    main()
