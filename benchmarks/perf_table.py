"""README's run-time table from a perf run (issue 14): frame ms per method × scene × frame kind, the
roofline efficiency's range, the equal-error speedup's range and which cells reach 10 % of the
roofline, with an earlier run's frame times in brackets.

    python -m benchmarks.perf_table RUN_DIR [--before OLD_RUN_DIR] [--threshold 0.10] [--triad GBPS]

``RUN_DIR`` is a finished ``run_bench.py run --suite perf --out RUN_DIR`` (its ``results.parquet``).
The roofline efficiency is the run's own (``reports.pipeline.collect``: the best triad / matmul of
the run), so two runs' percentages are comparable only as far as their limits are; the frame times
in brackets are the earlier run's medians. ``--triad GBPS`` recomputes every cell's efficiency at
that bandwidth instead (the run's matmul peak kept): each run divides by its own best triad, which
has read 40-55 GB/s on one host, so a memory-bound cell's efficiency moves up to 1.37x between runs
of the same code; at one fixed bandwidth (e.g. the highest this host has measured) two runs' tallies
compare.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

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


def at_bandwidth(df: pd.DataFrame, bandwidth: float, peak: float) -> pd.DataFrame:
    """``df`` with every cell's ``roofline_efficiency`` recomputed at ``bandwidth`` B/s and ``peak``
    flop/s (``reports.measure.roofline``: max(bytes / bandwidth, flops / peak, rays / the run's ray rate of
    the cell's scene) / median frame time)."""
    from reports import measure

    vals = df[(df["frame"] == -1) & df["metric"].isin(("bytes_per_frame", "flops_per_frame", "render_time_median",
                                                       "rays_per_frame"))]
    v = vals.pivot_table(index="cell", columns="metric", values="value", aggfunc="first")
    hr = df[(df["frame"] == -1) & (df["metric"] == "host_ray_rate")]  # the run's ray roof per scene (pipeline.ray_rates)
    rates = hr.groupby(["scene", "size"])["value"].max().to_dict() if len(hr) else {}
    where = df.drop_duplicates("cell").set_index("cell")[["scene", "size"]]
    out = df.copy()
    is_roof = (out["metric"] == "roofline_efficiency") & (out["frame"] == -1)
    for i in out.index[is_roof]:
        c = out.at[i, "cell"]
        if c not in v.index:
            continue
        r = v.loc[c]
        rate = rates.get(tuple(where.loc[c])) if c in where.index else None
        roof = measure.roofline(r.get("bytes_per_frame"), r.get("flops_per_frame"), bandwidth, peak,
                                r.get("render_time_median", float("nan")), r.get("rays_per_frame"), rate)
        out.at[i, "value"] = roof[0] if roof is not None else float("nan")
    return out


def run_peak(run: str, df: pd.DataFrame) -> float:
    """The matmul peak the run divided by: the best of run.json's and the cells' measurements."""
    vals = list(df[(df["metric"] == "host_matmul_peak") & (df["frame"] == -1)]["value"])
    p = Path(run) / "run.json"
    if p.is_file():
        vals.append(float(json.loads(p.read_text()).get("matmul_peak", float("nan"))))
    vals = [x for x in vals if math.isfinite(x)]
    return max(vals) if vals else float("nan")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run")
    ap.add_argument("--before", default=None, help="an earlier perf run: its frame times go in brackets")
    ap.add_argument("--threshold", type=float, default=0.10)
    ap.add_argument("--triad", type=float, default=None, metavar="GBPS",
                    help="recompute the roofline efficiencies at this triad bandwidth (GB/s) instead of the run's own")
    a = ap.parse_args(argv)
    df = store.read_table(a.run)
    before = store.read_table(a.before) if a.before else None
    bw = df[df["metric"] == "triad_bandwidth"]["value"]
    if len(bw):
        print(f"run triad bandwidth: {bw.iloc[0] / 1e9:.1f} GB/s")
    if a.triad is not None:
        if not a.triad > 0:
            raise SystemExit("--triad must be a positive bandwidth in GB/s")
        df = at_bandwidth(df, a.triad * 1e9, run_peak(a.run, df))
        print(f"roofline efficiencies below at {a.triad:.1f} GB/s (not the run's own)")
    tab, lines = table(df, before, a.threshold)
    print(tab)
    print()
    print("\n".join(lines))


if __name__ == "__main__":
    main()
