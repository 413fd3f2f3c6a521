"""What bounds the oracle's targets, from a perf run (issue 14):

    python -m benchmarks.oracle_bound runs/<perf run>    (the folder, or its results.parquet)

The oracle is the same estimator as Mitsuba's ``path`` integrator at ``max_depth = 2`` (MIS of the
env map's and the BRDF's samples, `methods.oracle`). Its equal-error speedup is Mitsuba's time to
reach the oracle's RMSE ÷ the oracle's frame time, so for one cell

    Mitsuba's efficiency under the oracle's count = (roofline time of the oracle's `frame_cost`)
                                                     ÷ (Mitsuba's time at the oracle's error)
                                                  = oracle efficiency ÷ equal-error speedup.

That is how close a JIT-compiled, vectorised production renderer running the same estimator comes
to the roofline of the oracle's honest count (bytes of the G-buffer, env-map tables and output;
flops of the shading; since session 38 the live shadow rays at the scene's measured ray rate,
``FrameCost.rays`` — before, the traversal, most of the work, was not counted and both sat near 1 %).
The oracle reaches an equal-error speedup ≥ 1 only by out-running Mitsuba on Mitsuba's own estimator.
Prints one row per oracle cell (frame kind) and the range.
"""
from __future__ import annotations

import argparse
import glob
import os

import pandas as pd


def table(path: str) -> pd.DataFrame:
    if os.path.isdir(path):
        hits = sorted(glob.glob(os.path.join(path, "**", "results.parquet"), recursive=True))
        if not hits:
            raise SystemExit(f"no results.parquet under {path}")
        path = hits[0]
    d = pd.read_parquet(path)
    d = d[(d.method == "oracle") & (d.frame == -1) & (d.bounces == 0)]
    want = ["render_time_median", "mitsuba_time_eq_error", "eq_error_speedup", "roofline_efficiency"]
    p = d[d.metric.isin(want)].pivot_table(index=["scene", "sequence"], columns="metric", values="value",
                                           aggfunc="first")
    missing = [w for w in want if w not in p.columns]
    if missing or p.empty:
        raise SystemExit(f"{path}: no oracle cells with {', '.join(missing or want)} (run the perf suite)")
    out = pd.DataFrame({
        "oracle ms": p.render_time_median * 1e3,
        "Mitsuba ms at equal error": p.mitsuba_time_eq_error * 1e3,
        "eq.-error speedup": p.eq_error_speedup,
        "oracle roofline %": p.roofline_efficiency * 100,
        "Mitsuba roofline % (same count)": p.roofline_efficiency * p.render_time_median / p.mitsuba_time_eq_error * 100,
    })
    return out


def main(argv: list[str] | None = None) -> pd.DataFrame:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", help="a perf run's folder or its results.parquet")
    t = table(ap.parse_args(argv).run)
    print(t.round(3).to_string())
    m = t["Mitsuba roofline % (same count)"]
    print(f"Mitsuba under the oracle's count: {m.min():.2f}–{m.max():.2f} % of the roofline "
          f"(the oracle: {t['oracle roofline %'].min():.2f}–{t['oracle roofline %'].max():.2f} %)")
    return t


if __name__ == "__main__":
    main()
