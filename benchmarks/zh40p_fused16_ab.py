"""Kernel A/B of the paper configuration's fused pass with its plane samples 16 at a time (`native_fused16`,
session 40, zh40p) against the scalar plane lines (`native.fused_pixels` with ``vector`` False), same process.

    python -m benchmarks.zh40p_fused16_ab [--kind P] [--precompute-code DIR] [--threads 1] [--repeat 150]
        [--flush 0]

Renders three frames of a ``--kind`` sequence (bench creature, config ``{}``), keeps the last fused call's
arguments, checks both passes' images bit for bit (``fma`` on and off, the object samples with and without
the plane mask as ``hit``), then times, alternating, process CPU per call (the collector off): the whole pass
scalar / vector (``fma``, as the frames run it) and its plane part alone (``hit`` = the plane mask: no object
samples). ``--flush MB``: write and read that many MB before each call (the settled frame's cold caches).
Prints min / p25 / median ms.
"""
from __future__ import annotations

import argparse
import gc
import json
import statistics
import time


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kind", default="P")
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=150)
    ap.add_argument("--flush", type=int, default=0)
    a = ap.parse_args(argv)
    import torch

    from benchmarks.common import apply_ab_options, precomputed, setup
    from methods.zh_shadow import native as zn
    from methods.zh_shadow.method import ZHShadow

    apply_ab_options(a)
    scene, _, _, _ = setup("creature", "bench", kind=a.kind, n_frames=1)
    m, _ = precomputed(ZHShadow, scene, {})
    _, frames, gbs, _ = setup(scene, "bench", kind=a.kind, n_frames=3, seed=0)
    cap: list = []
    orig = zn.fused_pixels

    def spy(*args, **kw):
        cap.append((args, kw))
        return orig(*args, **kw)

    zn.fused_pixels = spy
    mm = m.with_render_config()
    for f, g in zip(frames, gbs):
        mm.render(f, g)
    zn.fused_pixels = orig
    if not cap:
        raise SystemExit("no fused pass ran")
    args, kw = cap[-1]
    args, kw = list(args), {k: v for k, v in kw.items() if k not in ("fma", "vector")}
    plane_only = list(args)
    plane_only[5] = args[4].clone()   # hit = the plane mask: no object samples
    same = {}
    for fma in (False, True):
        for nm, ar in (("whole", args), ("plane", plane_only)):
            x, y = orig(*ar, **kw, fma=fma, vector=False), orig(*ar, **kw, fma=fma, vector=True)
            same[f"{nm} fma={fma}"] = x is not None and y is not None and torch.equal(x[0], y[0]) and x[1] == y[1]
    junk = torch.empty(a.flush * (1 << 18), dtype=torch.float32) if a.flush else None

    def flush():
        if junk is not None:
            junk.fill_(1.0)
            float(junk.sum())

    cases = {
        "whole scalar": lambda: orig(*args, **kw, fma=True, vector=False),
        "whole vector": lambda: orig(*args, **kw, fma=True, vector=True),
        "plane scalar": lambda: orig(*plane_only, **kw, fma=True, vector=False),
        "plane vector": lambda: orig(*plane_only, **kw, fma=True, vector=True),
    }
    ts: dict = {k: [] for k in cases}
    gc.disable()
    try:
        names = list(cases)
        for it in range(a.repeat):
            for k in (names if it % 2 == 0 else names[::-1]):
                flush()
                c = time.process_time()
                cases[k]()
                ts[k].append(time.process_time() - c)
    finally:
        gc.enable()
    out = {"kind": a.kind, "threads": a.threads, "object samples": int((~args[4]).sum()), "bit-equal": same}
    print(json.dumps(out))
    for k, v in ts.items():
        v = sorted(v)
        out[k] = (v[0] * 1e3, v[len(v) // 4] * 1e3, statistics.median(v) * 1e3)
        print(f"{k:20s} min {out[k][0]:.3f}  p25 {out[k][1]:.3f}  median {out[k][2]:.3f} ms")
    return out


if __name__ == "__main__":
    main()
