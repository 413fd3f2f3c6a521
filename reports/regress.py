"""Regression detection between two runs (or the last two runs of the history).

A cell is identified across runs by (scene, size, sequence, method, config, bounces).

* Error metrics are deterministic (fixed seeds, cached references): a change is flagged when it is
  worse by more than ``max(REL_TOL·|old|, absolute floor)``; the absolute floor of radiance-unit
  metrics (RMSE) is ``NOISE_FLOOR_FRAC`` × the reference noise floor, so re-rendered references
  cannot raise false alarms on their own; other metrics have a fixed floor (``ABS_FLOOR``).
* Times (per-frame render times, warm-up frame excluded) are noisy: flagged when the median is
  ≥ ``TIME_REL`` slower AND a one-sided Mann–Whitney U test on the frame samples gives
  p < ``TIME_P``. Both conditions: the test alone flags tiny but significant changes, the
  threshold alone flags noise.
* Memory (``memory_bytes``) is deterministic: flagged above ``MEMORY_REL``.
* A cell that ran before and now fails is flagged.
Improvements by the same rules are reported as ``improvement``.
"""
from __future__ import annotations

import math

import numpy as np
import pandas as pd
from scipy.stats import mannwhitneyu

CELL_ID = ["scene", "size", "sequence", "method", "config", "bounces"]
# metric → +1 if larger is worse, −1 if larger is better
ERROR_METRICS = {"rmse": +1, "rel_mse": +1, "flip": +1, "delta_e2000": +1, "nonfinite_frac": +1,
                 "psnr": -1, "ssim": -1}
# Deterministic scores: 1 % relative tolerance absorbs float reordering across torch versions/threads.
REL_TOL = 0.01
# RMSE's absolute floor: a tenth of the reference noise floor (below anything the reference resolves).
NOISE_FLOOR_FRAC = 0.1
# Fixed absolute floors of metrics not in radiance units (about their printing precision).
ABS_FLOOR = {"rel_mse": 1e-6, "psnr": 0.05, "ssim": 1e-3, "flip": 1e-4, "delta_e2000": 1e-3, "nonfinite_frac": 0.0}
# Times: ≥ 5 % slower (median) and one-sided Mann–Whitney p < 0.01.
TIME_REL = 0.05
TIME_P = 0.01
# Memory of run-time arrays is deterministic; 1 % guards against metadata-sized differences.
MEMORY_REL = 0.01

CHANGE_COLUMNS = CELL_ID + ["metric", "old", "new", "rel_change", "p_value", "threshold", "flag", "test"]


def _key(df: pd.DataFrame) -> pd.Series:
    k = df[CELL_ID[0]].astype(str)
    for c in CELL_ID[1:]:
        k = k + "|" + df[c].astype(str)
    return k


def _rel(old: float, new: float) -> float:
    return (new - old) / abs(old) if old not in (0.0,) and math.isfinite(old) else float("nan")


def compare_runs(old: pd.DataFrame, new: pd.DataFrame) -> pd.DataFrame:
    """All compared values of cells present (status ok) in both runs, with ``flag`` in
    {"regression", "improvement", ""} (``CHANGE_COLUMNS``)."""
    out: list[dict] = []
    if len(old) == 0 or len(new) == 0:
        return pd.DataFrame(columns=CHANGE_COLUMNS)
    old = old.assign(_k=_key(old))
    new = new.assign(_k=_key(new))
    ok_old = set(old.loc[old["status"] == "ok", "_k"])
    old_groups = {k: g for k, g in old.groupby("_k", sort=False)}
    for k, g_new in new.groupby("_k", sort=True):
        ident = {c: g_new.iloc[0][c] for c in CELL_ID}
        if k not in ok_old:
            continue
        status = g_new.iloc[0]["status"]
        if status == "error":
            out.append({**ident, "metric": "status", "old": float("nan"), "new": float("nan"), "rel_change": float("nan"),
                        "p_value": float("nan"), "threshold": float("nan"), "flag": "regression",
                        "test": f"cell failed: {g_new.iloc[0]['reason']}"})
            continue
        if status != "ok":
            continue
        g_old = old_groups[k]
        out += _compare_errors(ident, g_old, g_new)
        out += _compare_times(ident, g_old, g_new)
        out += _compare_memory(ident, g_old, g_new)
    return pd.DataFrame(out, columns=CHANGE_COLUMNS)


def _summary(g: pd.DataFrame, metric: str) -> tuple[float, float] | None:
    r = g[(g["metric"] == metric) & (g["frame"] == -1)]
    if len(r) == 0:
        return None
    return float(r.iloc[0]["value"]), float(r.iloc[0]["noise_floor"])


def _compare_errors(ident: dict, g_old: pd.DataFrame, g_new: pd.DataFrame) -> list[dict]:
    rows = []
    for metric, sign in ERROR_METRICS.items():
        a, b = _summary(g_old, metric), _summary(g_new, metric)
        if a is None or b is None:
            continue
        (vo, fo), (vn, fn) = a, b
        if metric == "rmse":
            floors = [f for f in (fo, fn) if math.isfinite(f)]
            absf = NOISE_FLOOR_FRAC * max(floors) if floors else 0.0
        else:
            absf = ABS_FLOOR.get(metric, 0.0)
        tol = max(REL_TOL * abs(vo), absf) if math.isfinite(vo) else 0.0
        if math.isfinite(vo) and not math.isfinite(vn) and not (metric == "psnr" and vn == math.inf):
            flag = "regression"
        elif math.isfinite(vo) and math.isfinite(vn):
            d = (vn - vo) * sign
            flag = "regression" if d > tol else ("improvement" if d < -tol else "")
        else:
            flag = ""
        rows.append({**ident, "metric": metric, "old": vo, "new": vn, "rel_change": _rel(vo, vn), "p_value": float("nan"),
                     "threshold": tol, "flag": flag, "test": "tolerance"})
    return rows


def frame_samples(g: pd.DataFrame, metric: str = "render_time", warmup: int = 1) -> np.ndarray:
    r = g[(g["metric"] == metric) & (g["frame"] >= warmup)]
    return r["value"].to_numpy(dtype=np.float64)


def time_change(old: np.ndarray, new: np.ndarray, *, rel: float = TIME_REL, p: float = TIME_P) -> tuple[str, float, float]:
    """(flag, median ratio − 1, p-value) of frame-time samples ``old`` (n,) vs ``new`` (m,)."""
    old = np.asarray(old, dtype=np.float64)
    new = np.asarray(new, dtype=np.float64)
    if len(old) == 0 or len(new) == 0:
        raise ValueError("need at least one sample in each run")
    mo, mn = float(np.median(old)), float(np.median(new))
    change = mn / mo - 1.0 if mo > 0 else float("nan")
    p_slower = float(mannwhitneyu(new, old, alternative="greater").pvalue)
    p_faster = float(mannwhitneyu(new, old, alternative="less").pvalue)
    if change >= rel and p_slower < p:
        return "regression", change, p_slower
    if change <= 1.0 / (1.0 + rel) - 1.0 and p_faster < p:
        return "improvement", change, p_faster
    return "", change, min(p_slower, p_faster)


def _compare_times(ident: dict, g_old: pd.DataFrame, g_new: pd.DataFrame) -> list[dict]:
    a, b = frame_samples(g_old), frame_samples(g_new)
    if len(a) == 0 or len(b) == 0:
        return []
    flag, change, pv = time_change(a, b)
    return [{**ident, "metric": "render_time", "old": float(np.median(a)), "new": float(np.median(b)),
             "rel_change": change, "p_value": pv, "threshold": TIME_REL, "flag": flag,
             "test": f"Mann-Whitney U (n={len(a)},{len(b)})"}]


def _compare_memory(ident: dict, g_old: pd.DataFrame, g_new: pd.DataFrame) -> list[dict]:
    a, b = _summary(g_old, "memory_bytes"), _summary(g_new, "memory_bytes")
    if a is None or b is None:
        return []
    vo, vn = a[0], b[0]
    ch = _rel(vo, vn)
    flag = ""
    if math.isfinite(ch):
        flag = "regression" if ch > MEMORY_REL else ("improvement" if ch < -MEMORY_REL else "")
    return [{**ident, "metric": "memory_bytes", "old": vo, "new": vn, "rel_change": ch, "p_value": float("nan"),
             "threshold": MEMORY_REL, "flag": flag, "test": "tolerance"}]


def flagged(changes: pd.DataFrame) -> pd.DataFrame:
    return changes[changes["flag"] != ""].reset_index(drop=True)


def run_ids(history: pd.DataFrame) -> list[str]:
    """Run ids of ``history`` oldest first (by run time)."""
    if len(history) == 0:
        return []
    t = pd.to_datetime(history["time"], utc=True, format="ISO8601").groupby(history["run_id"]).min().sort_values()
    return list(t.index)


def previous_run(history: pd.DataFrame, run_id: str) -> pd.DataFrame | None:
    """The rows of the run recorded just before ``run_id`` in ``history`` (None if none)."""
    ids = run_ids(history)
    if run_id in ids:
        i = ids.index(run_id)
        prev = ids[i - 1] if i > 0 else None
    else:
        prev = ids[-1] if ids else None
    return None if prev is None else history[history["run_id"] == prev]


def format_changes(changes: pd.DataFrame, *, only_flagged: bool = False) -> str:
    """A plain-text table of changes (flags: ``!!`` regression, ``++`` improvement)."""
    ch = flagged(changes) if only_flagged else changes
    if len(ch) == 0:
        return "no changes" if only_flagged else "no comparable cells"
    lines = [f"{'':2} {'scene':14} {'seq':4} {'method':16} {'b':4} {'metric':14} {'old':>11} {'new':>11} {'change':>8} {'p':>8}"]
    for _, r in ch.iterrows():
        mark = {"regression": "!!", "improvement": "++"}.get(r["flag"], "  ")
        b = "full" if int(r["bounces"]) == -1 else str(r["bounces"])
        rc = f"{100 * r['rel_change']:+.1f}%" if math.isfinite(r["rel_change"]) else "-"
        pv = f"{r['p_value']:.1e}" if math.isfinite(r["p_value"]) else "-"
        lines.append(f"{mark:2} {str(r['scene'])[:14]:14} {r['sequence']:4} {str(r['method'])[:16]:16} {b:4} "
                     f"{r['metric'][:14]:14} {r['old']:11.4g} {r['new']:11.4g} {rc:>8} {pv:>8}")
    n_reg = int((ch["flag"] == "regression").sum())
    n_imp = int((ch["flag"] == "improvement").sum())
    lines.append(f"{n_reg} regression(s), {n_imp} improvement(s)")
    return "\n".join(lines)
