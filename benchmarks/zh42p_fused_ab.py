"""Kernel A/B of the paper configuration's fused pass with the object samples' dot in 16-float vectors and the
plane samples grouped by face (`native_fused16`'s `zh42p_fused_wide`, session 42, zh42p, `ZHShadow.wide_dot`)
against the pass it replaces (`zh40p_fused_fma`), same process, the same call's arguments. Session 42, bench
creature P, 1 thread, 64 MB flush: 2.99 → 2.46 ms median (1.22×, A/A 0.995).

    python -m benchmarks.zh42p_fused_ab [--kind P] [--precompute-code DIR] [--threads 1] [--repeat 60] [--flush 64]

Renders three frames of a ``--kind`` sequence (bench creature, config ``{}``), keeps the last fused call's
arguments (`benchmarks.zh_fused_ab.fused_call`), prints the max |wide − 8-float| / max |8-float| of the image and
whether the specular counts agree, then times, alternating, process CPU per call (the collector off; ``--flush``
MB written and read before each call: the frame's cold caches; 0: back to back): the 8-float pass ("base"), the
wide one ("wide") and the 8-float pass again ("base2": the A/A). Prints min / p25 / median ms and the median ratios.
"""
from __future__ import annotations

import argparse
import json
import statistics


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kind", default="P")
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=60)
    ap.add_argument("--flush", type=int, default=64)
    a = ap.parse_args(argv)
    import torch

    from benchmarks.common import apply_ab_options
    from benchmarks.zh_fused_ab import alternate, fused_call, report

    apply_ab_options(a)
    orig, args, kw = fused_call(a.kind, {})
    kw = {k: v for k, v in kw.items() if k not in ("fma", "vector", "wide")}
    base = orig(*args, **kw, fma=True, vector=True, wide=False)
    wide = orig(*args, **kw, fma=True, vector=True, wide=True)
    out = {"kind": a.kind, "threads": a.threads, "object samples": int((~args[4]).sum()),
           "max |diff| / max": float((wide[0] - base[0]).abs().max() / base[0].abs().max()),
           "same specular count": wide[1] == base[1]}
    print(json.dumps(out))
    junk = torch.empty(a.flush * (1 << 18), dtype=torch.float32) if a.flush else None

    def flush():
        if junk is not None:
            junk.fill_(1.0)
            float(junk[::4096].sum())

    ts = alternate({"base": lambda: orig(*args, **kw, fma=True, vector=True, wide=False),
                    "wide": lambda: orig(*args, **kw, fma=True, vector=True, wide=True),
                    "base2": lambda: orig(*args, **kw, fma=True, vector=True, wide=False)}, a.repeat, flush)
    report(ts, out)
    md = {k: statistics.median(v) for k, v in ts.items()}
    out["ratio"], out["A/A"] = md["base"] / md["wide"], md["base"] / md["base2"]
    print(f"ratio base / wide {out['ratio']:.3f}   A/A base / base2 {out['A/A']:.3f}")
    return out


if __name__ == "__main__":
    main()
