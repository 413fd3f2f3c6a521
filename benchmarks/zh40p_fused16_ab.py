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
import json


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kind", default="P")
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=150)
    ap.add_argument("--flush", type=int, default=0)
    a = ap.parse_args(argv)
    import torch

    from benchmarks.common import apply_ab_options
    from benchmarks.zh_fused_ab import alternate, fused_call, report

    apply_ab_options(a)
    orig, args, kw = fused_call(a.kind, {})
    kw = {k: v for k, v in kw.items() if k not in ("fma", "vector", "wide")}   # (wide: zh42p's dot, off here)
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
    ts = alternate(cases, a.repeat, flush)
    out = {"kind": a.kind, "threads": a.threads, "object samples": int((~args[4]).sum()), "bit-equal": same}
    print(json.dumps(out))
    return report(ts, out)


if __name__ == "__main__":
    main()
