"""README's run-time table from a perf run (issue 14): frame ms per method × scene × frame kind, the
roofline efficiency's range, the equal-error speedup's range and which cells reach 10 % of the
roofline, with an earlier run's frame times in brackets.

    python -m benchmarks.perf_table RUN_DIR [--before OLD_RUN_DIR] [--threshold 0.10]

``RUN_DIR`` is a finished ``run_bench.py run --suite perf --out RUN_DIR`` (its ``results.parquet``).
The roofline efficiency is the run's own (``reports.pipeline.collect``: the best triad / matmul of
the run), so two runs' percentages are comparable only as far as their limits are; the frame times
in brackets are the earlier run's medians.
"""
from __future__ import annotations

import argparse
import math

import pandas as pd

from reports import store
from reports.html import _method_label

COLUMNS = (("chess", ("V", "L", "E")), ("creature", ("V", "L", "E")), ("creature", ("P",)))


def _metric(df: pd.DataFrame, metric: str) -> pd.DataFrame:
    d = df[(df["metric"] == metric) & (df["frame"] == -1) & df["status"].isin(("ok", "suspect"))]
    return d[["scene", "method", "config", "sequence", "value"]]


def frame_ms(df: pd.DataFrame) -> dict:
    """(method, config, scene, kind) → median frame time in ms."""
    d = _metric(df, "render_time_median")
    return {(r.method, r.config, r.scene, r.sequence): 1e3 * r.value for r in d.itertuples()}


def _ms(v: float | None) -> str:
    if v is None or not math.isfinite(v):
        return "–"
    return f"{v:.2g}" if v < 10 else f"{v:.0f}"


def table(df: pd.DataFrame, before: pd.DataFrame | None = None, threshold: float = 0.10) -> tuple[str, list[str]]:
    """The markdown table and the summary lines (cells at or above ``threshold``, per method, and
    the cells below it)."""
    ms, old = frame_ms(df), frame_ms(before) if before is not None else {}
    roof, sp = _metric(df, "roofline_efficiency"), _metric(df, "eq_error_speedup")
    rows = ["| method (config) | chess V / L / E | creature V / L / E | creature P | roofline | eq.-error speedup |",
            "|---|---|---|---|---|---|"]
    keys = sorted({(m, c) for m, c, _, _ in ms})
    for m, c in keys:
        cols = []
        for scene, kinds in COLUMNS:
            parts = []
            for k in kinds:
                v, o = ms.get((m, c, scene, k)), old.get((m, c, scene, k))
                parts.append(_ms(v) + (f" ({_ms(o)})" if v is not None and o is not None else ""))
            cols.append(" / ".join(parts) if any(p != "–" for p in parts) else "–")
        r = roof[(roof.method == m) & (roof.config == c)]["value"]
        s = sp[(sp.method == m) & (sp.config == c)]["value"]
        s = s[s.map(math.isfinite)]
        rr = f"{100 * r.min():.1f}–{100 * r.max():.1f} %" if len(r) else "–"
        ss = f"{s.min():.2g}–{s.max():.3g}×" if len(s) else "–"
        rows.append(f"| {_method_label(m, c)} | {' | '.join(cols)} | {rr} | {ss} |")
    lines = [f"Roofline ≥ {100 * threshold:.0f} %: {int((roof.value >= threshold).sum())} of {len(roof)} cells"]
    for (m, c), g in roof.groupby(["method", "config"]):
        lines.append(f"  {_method_label(m, c)}: {int((g.value >= threshold).sum())} of {len(g)}")
    below = roof[roof.value < threshold].sort_values(["method", "config", "scene", "sequence"])
    lines.append("Below:")
    lines += [f"  {_method_label(r.method, r.config)} {r.scene} {r.sequence}: {100 * r.value:.1f} %"
              for r in below.itertuples()]
    return "\n".join(rows), lines


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("--before", default=None, help="an earlier perf run: its frame times go in brackets")
    ap.add_argument("--threshold", type=float, default=0.10)
    a = ap.parse_args(argv)
    df = store.read_table(a.run)
    before = store.read_table(a.before) if a.before else None
    bw = df[df["metric"] == "triad_bandwidth"]["value"]
    tab, lines = table(df, before, a.threshold)
    if len(bw):
        print(f"run triad bandwidth: {bw.iloc[0] / 1e9:.1f} GB/s")
    print(tab)
    print()
    print("\n".join(lines))


if __name__ == "__main__":
    main()
