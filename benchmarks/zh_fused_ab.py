"""Kernel A/B of a ZH paper-config plane frame's fused pass and plane search (session 37, zh37v), same process.

    python -m benchmarks.zh_fused_ab [--kind V] [--config '{}'] [--precompute-code DIR] [--threads 1] [--repeat 150]

Renders three frames of a ``--kind`` sequence (bench creature), keeps the last `native.fused_pixels` call's
arguments, then times, alternating, process CPU per call (Python's collector off: the loop's allocations
would otherwise trigger it): the exact pass (`zh33p_fused`, `sample_terms`' bits), the regrouped one
(``fma``, `zh37v_fused`), the exact pass with no object samples (``hit`` = the plane mask: the plane part
alone), and both with every table row read from L1 (one row, a lut of zeros: the object part without its
table misses) — and `native.plane_mask` by its loop and by `zh37v_plane_mask`. Prints min / p25 / median ms
and the max |difference| of the two passes' images.
"""
from __future__ import annotations

import argparse
import gc
import json
import statistics
import time


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kind", default="V")
    ap.add_argument("--config", default="{}")
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=150)
    a = ap.parse_args(argv)
    import torch

    from benchmarks.common import apply_ab_options
    from methods.zh_shadow import native as zn

    apply_ab_options(a)
    orig, args, kw = fused_call(a.kind, json.loads(a.config), fma_terms=False)
    kw = {k: v for k, v in kw.items() if k not in ("fma", "wide")}   # (wide: zh42p's dot, off here)
    plane_only = list(args)
    plane_only[5] = args[4].clone()                    # hit = the plane mask: no object samples
    l1 = list(args)
    l1[8], l1[9] = args[8][:1].contiguous(), torch.zeros(args[7].shape[0], dtype=torch.int32)
    nrm, region = args[2], args[10]
    n0 = nrm[int(args[4].nonzero()[0])].clone()
    spec = torch.tensor([bool(s) for s in args[11]])

    def pm(vec: bool):
        zn.VECTOR_PLANE_MASK = vec
        return zn.plane_mask(nrm, n0, region, spec)

    cases = {
        "fused exact": lambda: orig(*args, **kw),
        "fused fma": lambda: orig(*args, **kw, fma=True),
        "plane part alone": lambda: orig(*plane_only, **kw),
        "exact, table in L1": lambda: orig(*l1, **kw),
        "fma, table in L1": lambda: orig(*l1, **kw, fma=True),
        "plane_mask loop": lambda: pm(False),
        "plane_mask vector": lambda: pm(True),
    }
    x, y = cases["fused exact"](), cases["fused fma"]()
    diff = float((x[0] - y[0]).abs().max())
    p0, p1 = pm(False), pm(True)
    zn.VECTOR_PLANE_MASK = True
    same_mask = torch.equal(p0[0], p1[0]) and p0[1:] == p1[1:]
    try:
        ts = alternate(cases, a.repeat)
    finally:
        zn.VECTOR_PLANE_MASK = True
    out = {"kind": a.kind, "object samples": int((~args[4]).sum()), "fma max abs diff": diff,
           "image max": float(x[0].abs().max()), "plane_mask equal": same_mask}
    print(json.dumps(out))
    return report(ts, out)


def fused_call(kind: str, config: dict, **attrs) -> tuple:
    """(`native.fused_pixels` itself, the positional arguments as a list, the keywords) of the last fused call
    of three ``kind`` frames (bench creature, ``config``), the method's ``attrs`` set before they render;
    SystemExit when no fused pass ran. Imports here: the caller applied its A/B options first."""
    from benchmarks.common import precomputed, setup
    from methods.zh_shadow import native as zn
    from methods.zh_shadow.method import ZHShadow

    scene, _, _, _ = setup("creature", "bench", kind=kind, n_frames=1)
    m, _ = precomputed(ZHShadow, scene, config)
    _, frames, gbs, _ = setup(scene, "bench", kind=kind, n_frames=3, seed=0)
    cap: list = []
    orig = zn.fused_pixels

    def spy(*args, **kw):
        cap.append((args, kw))
        return orig(*args, **kw)

    zn.fused_pixels = spy
    try:
        mm = m.with_render_config()
        for k, v in attrs.items():
            setattr(mm, k, v)
        for f, g in zip(frames, gbs):
            mm.render(f, g)
    finally:
        zn.fused_pixels = orig
    if not cap:
        raise SystemExit("no fused pass ran")
    args, kw = cap[-1]
    return orig, list(args), dict(kw)


def alternate(cases: dict, repeat: int, before=None) -> dict:
    """Process CPU seconds per call of each of ``cases`` (name -> callable), ``repeat`` rounds alternating the
    order, ``before()`` (untimed) ahead of each call, Python's collector off (the loop's allocations would
    otherwise trigger it)."""
    ts: dict = {k: [] for k in cases}
    names = list(cases)
    gc.disable()
    try:
        for it in range(repeat):
            for k in (names if it % 2 == 0 else names[::-1]):
                if before is not None:
                    before()
                c = time.process_time()
                cases[k]()
                ts[k].append(time.process_time() - c)
    finally:
        gc.enable()
    return ts


def report(ts: dict, out: dict) -> dict:
    """Print and add to ``out`` each case's (min, p25, median) ms."""
    for k, v in ts.items():
        v = sorted(v)
        out[k] = (v[0] * 1e3, v[len(v) // 4] * 1e3, statistics.median(v) * 1e3)
        print(f"{k:20s} min {out[k][0]:.3f}  p25 {out[k][1]:.3f}  median {out[k][2]:.3f} ms")
    return out


if __name__ == "__main__":
    main()
