"""Drift-corrected speed-ups between perf runs (issue 14): how much faster each method
configuration's frames got, with the host's run-to-run drift divided out.

    python -m benchmarks.perf_speedup --before RUN [RUN ...] --after RUN [RUN ...]
                                      [--unchanged GROUP ...] [--by-kind]

This shared machine drifts: two perf runs of one clone, back to back, have differed by 1.14× in the
geometric mean of all their cells' frame times (session 33), more than most changes gain. So a
before / after comparison divides by the cells whose code did not change. For every pair of a
"before" and an "after" run:

- raw speed-up of a group (a method configuration) = the geometric mean, over the group's cells
  present in both runs, of before / after median frame time;
- drift = the same geometric mean over the reference cells (the unchanged groups' cells);
- drift-corrected speed-up = raw / drift.

The table gives each group's median over the pairs and the range. Reference groups: ``--unchanged``
(a method name, e.g. ``ptt``, or a method and its config JSON, e.g. ``'inout {"shading":"vertex"}'``),
else every group whose code key (``provenance.json``'s ``code``: the method module's import closure,
as the precompute cache keys it; recorded since session 34) is the same in every run. A group that
is its own reference reads 1.00× corrected by construction; with one reference group, that is all
its line says.
"""
from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from benchmarks.perf_table import frame_ms
from reports import store
from reports.html import _method_label

Group = tuple[str, str]  # (method, config)


def group_codes(run: str | Path) -> dict[Group, set[str]]:
    """(method, config) → the code keys its timed cells recorded in ``run``'s provenance.json (empty
    set for a run from before the key was recorded)."""
    run = Path(run)
    p = run / "provenance.json"
    prov = json.loads(p.read_text()) if p.is_file() else []
    code = {r["cell"]: r.get("code", "") for r in prov}
    df = store.read_table(run)
    out: dict[Group, set[str]] = {}
    for (m, c, cell), _ in df[df["method"] != ""].groupby(["method", "config", "cell"]):
        out.setdefault((m, c), set())
        if code.get(cell):
            out[(m, c)].add(code[cell])
    return out


def unchanged_groups(runs: list[str | Path]) -> list[Group]:
    """Groups with one and the same recorded code key in every run."""
    codes = [group_codes(r) for r in runs]
    common = set.intersection(*(set(c) for c in codes)) if codes else set()
    out = []
    for g in sorted(common):
        keys = set().union(*(c[g] for c in codes))
        if len(keys) == 1 and all(c[g] for c in codes):
            out.append(g)
    return out


def _matches(g: Group, spec: str) -> bool:
    m, c = g
    return spec == m or spec == f"{m} {c}"


def _geomean(x: list[float]) -> float:
    return float(np.exp(np.mean(np.log(x)))) if x else float("nan")


def speedups(before: list[dict], after: list[dict], reference: list[Group], by_kind: bool = False) -> dict:
    """``before`` / ``after``: `frame_ms` dicts of runs ((method, config, scene, kind) → ms).
    → {group (or (group, kind) with ``by_kind``): {"cells": n, "raw": [..], "corrected": [..]}}, one
    value per (before, after) pair; ``"drift"`` holds the reference's ratio per pair."""
    ref = set(reference)
    res: dict = {"drift": []}
    for a in before:
        for b in after:
            keys = [k for k in b if k in a and a[k] > 0 and b[k] > 0]
            drift = _geomean([a[k] / b[k] for k in keys if (k[0], k[1]) in ref])
            if not math.isfinite(drift):
                raise ValueError("no reference cell is in both runs: pass --unchanged with groups both runs timed")
            res["drift"].append(drift)
            groups: dict = {}
            for k in keys:
                gk = ((k[0], k[1]), k[3]) if by_kind else (k[0], k[1])
                groups.setdefault(gk, []).append(a[k] / b[k])
            for gk, r in groups.items():
                e = res.setdefault(gk, {"cells": len(r), "raw": [], "corrected": []})
                e["raw"].append(_geomean(r))
                e["corrected"].append(_geomean(r) / drift)
    return res


def _fmt(v: list[float]) -> str:
    if len(v) == 1:
        return f"{v[0]:.2f}×"
    return f"{np.median(v):.2f}× ({min(v):.2f}–{max(v):.2f})"


def table(res: dict, reference: list[Group]) -> str:
    rows = ["| method (config) | cells | raw speed-up | drift-corrected | reference |", "|---|---|---|---|---|"]
    for gk in sorted(k for k in res if k != "drift"):
        g, kind = (gk[0], gk[1]) if isinstance(gk[0], tuple) else (gk, "")
        label = _method_label(*g) + (f" {kind}" if kind else "")
        e = res[gk]
        rows.append(f"| {label} | {e['cells']} | {_fmt(e['raw'])} | {_fmt(e['corrected'])} | "
                    f"{'yes' if g in set(reference) else ''} |")
    rows.append(f"\nDrift (reference cells' before / after): {_fmt(res['drift'])}; "
                f"{len(res['drift'])} pair(s) of runs; reference: "
                + ", ".join(_method_label(*g) for g in reference))
    return "\n".join(rows)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--before", nargs="+", required=True, help="perf run directories of the old code")
    ap.add_argument("--after", nargs="+", required=True, help="perf run directories of the new code")
    ap.add_argument("--unchanged", nargs="+", default=None, metavar="GROUP",
                    help="reference groups: a method name or 'method {config}' (default: equal code keys)")
    ap.add_argument("--by-kind", action="store_true", help="one line per method configuration and frame kind")
    a = ap.parse_args(argv)
    runs = a.before + a.after
    tables = [frame_ms(store.read_table(r)) for r in runs]
    groups = sorted({(k[0], k[1]) for t in tables for k in t})
    if a.unchanged:
        bad = [s for s in a.unchanged if not any(_matches(g, s) for g in groups)]
        if bad:
            raise SystemExit(f"--unchanged {bad}: no such method (config) in the runs; groups: "
                             + ", ".join(f"{m} {c}" for m, c in groups))
        reference = [g for g in groups if any(_matches(g, s) for s in a.unchanged)]
    else:
        reference = unchanged_groups(runs)
        if not reference:
            raise SystemExit("no method configuration has the same recorded code key in every run "
                             "(runs before session 34 record none): pass --unchanged GROUP ...")
    try:
        res = speedups(tables[:len(a.before)], tables[len(a.before):], reference, a.by_kind)
    except ValueError as e:
        raise SystemExit(str(e))
    print(table(res, reference))


if __name__ == "__main__":
    main()
