"""Regression detection: a run against a named earlier run (``compare_runs``) or against the history
(``compare_with_history``).

Cell identity: ``CELL_ID`` = (scene, size, sequence, method, config, bounces) — no code version in
it, so a code change is compared with the numbers of the code before it.

Baseline (``baseline_rows``): for every cell of a new run, the most recent *earlier* run in the
history (by run time, same suite, the new run itself excluded) in which that same cell was measured
— not "the latest run of the suite", which may not contain the cell (a ``--methods oracle`` run
must not hide an inout regression). A run's suite is the first part of its id (``suite_of``):
``smoke``, ``nightly``, … and ``smoke+files`` for a run that includes scene files. Scene files are
shown by their TOML ``name``, which may equal a library scene's, so ``+files`` runs are compared
only with ``+files`` runs: a scene-file run is never mistaken for a smoke run, nor the reverse.

Rules (each value of a cell compared with the same cell's baseline):

* Error metrics are deterministic (fixed seeds, cached references): a change is flagged when it is
  worse by more than ``max(REL_TOL·|old|, absolute floor)``; the absolute floor of radiance-unit
  metrics (RMSE) is ``NOISE_FLOOR_FRAC`` × the reference noise floor when the reference was
  re-rendered (its floor differs), so a new noise realisation cannot raise false alarms on its
  own — against the same cached reference it is 0 and a 5 % RMSE rise is flagged; other metrics have a fixed floor (``ABS_FLOOR``).
* Frame times (per-frame render times, warm-up frame excluded; 2 per cell in smoke, 4 in nightly).
  A rank test cannot fire with so few samples (one-sided Mann–Whitney with 2 vs 2 frames: p ≥ 1/6),
  so the decision is a threshold on the ratio of the medians across the two runs, guarded by the
  within-run spread (``time_change``): slower is flagged when

      median_new / median_old − 1  ≥  max(TIME_REL, TIME_SPREAD_K · spread)
      and  median_new − median_old  ≥  TIME_ABS_FLOOR,

  where ``spread`` = the larger relative IQR (IQR / median) of the two runs' frame times. The guard
  keeps cells whose frames scatter within a run from raising alarms; with ``TIME_SPREAD_K`` = 2 a
  single slow outlier frame (an interrupt, another job) in a 2-frame cell is not flagged, while two
  uniformly slower frames are. Changes of a fraction of a millisecond (timer and scheduler jitter)
  are ignored. Faster by the mirror rule. Frame times are compared only when both runs used the
  same number of threads on the same machine kind (CPU model and core count of the ``machine``
  column; the host name may differ), and when neither run's cell was timed beside other work (the
  rest of the machine used at most ``CONTENTION_MAX`` cores while its frames ran, the cell's
  ``other_cpu_cores``); otherwise the row says why they were not compared.

  Decision (false alarms vs power; measured rates are pinned in tests/reports/test_regress.py for
  synthetic noise and were measured on repeated unchanged runs when the rule was introduced):
  ``TIME_REL`` sits between the run-to-run scatter of a machine reserved for the benchmark and the
  10 % slowdown the nightly must catch. Wall-clock frame times cannot separate a slower build from
  a machine that other jobs slowed down between the two runs — every frame of the run slows alike,
  so no within-run statistic helps. What the harness can see is the other work itself: the CPU the
  rest of the machine used while a cell's frames were timed (``other_cpu_cores``, including the
  hypervisor's steal time), and cells timed beside more than ``CONTENTION_MAX`` cores of it are not
  compared. Rows from before it was recorded have none and compare as before.
* Memory (``memory_bytes``) is deterministic: flagged above ``MEMORY_REL``.
* A cell that finished in its baseline run and now fails is flagged, and so is one that was ``ok``
  and is now ``suspect`` (its images failed the sanity gate, ``reports/gate.py``); suspect cells'
  numbers are compared like ok ones.
Improvements by the same rules are reported as ``improvement``.
"""
from __future__ import annotations

import math

import numpy as np
import pandas as pd

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
# Frame times (``time_change``, module docstring): ratio of medians ≥ 1 + TIME_REL, beyond
# TIME_SPREAD_K × the within-run relative IQR, and at least TIME_ABS_FLOOR seconds per frame.
TIME_REL = 0.06
TIME_SPREAD_K = 2.0
TIME_ABS_FLOOR = 2e-4
# Frame times of a cell are not compared when, in either run, the rest of the machine used more than
# this many cores on average while the cell's frames were timed (``other_cpu_cores``, from
# ``/proc/stat``: `reports.measure.other_cpu_cores`). One other busy process adds ~1
# (tests/reports/test_measure.py); a quarter core is 12 % of a 2-core machine.
CONTENTION_MAX = 0.25
# Memory of run-time arrays is deterministic; 1 % guards against metadata-sized differences.
MEMORY_REL = 0.01

# Cell statuses that carry numbers: "suspect" = measured, but its images failed the sanity gate
# (reports/gate.py).
MEASURED = ("ok", "suspect")

CHANGE_COLUMNS = CELL_ID + ["metric", "old", "new", "rel_change", "p_value", "threshold", "flag", "test", "baseline"]


class NoCommonCells(ValueError):
    """Two runs that share no cell (``compare_runs(..., require_common=True)``)."""


def _key(df: pd.DataFrame) -> pd.Series:
    k = df[CELL_ID[0]].astype(str)
    for c in CELL_ID[1:]:
        k = k + "|" + df[c].astype(str)
    return k


def _rel(old: float, new: float) -> float:
    return (new - old) / abs(old) if old not in (0.0,) and math.isfinite(old) else float("nan")


def suite_of(run_id: str) -> str:
    """The suite a run id names (``<suite>-<UTC time>-<sha>-<nonce>``), e.g. ``smoke``, ``smoke+files``."""
    return str(run_id).split("-", 1)[0]


def _run_times(df: pd.DataFrame) -> pd.Series:
    """run_id → the run's start time (UTC)."""
    return pd.to_datetime(df["time"], utc=True, format="ISO8601").groupby(df["run_id"]).min()


def baseline_rows(history: pd.DataFrame, new: pd.DataFrame, *, same_suite: bool = True) -> pd.DataFrame:
    """For every cell of ``new`` (one run), that cell's rows from the most recent earlier run of
    ``history`` in which it was measured (``MEASURED``) (``CELL_ID``; see the module docstring). Runs of ``new``'s
    own id(s) and runs that started at or after it are not candidates; with ``same_suite`` only runs
    of the same suite (``suite_of``) are. The rows of several earlier runs may be returned
    (each cell from its own baseline run)."""
    if len(history) == 0 or len(new) == 0:
        return history.iloc[0:0]
    new_ids = set(new["run_id"].astype(str))
    t_new = _run_times(new).min()
    h = history[~history["run_id"].astype(str).isin(new_ids)]
    if same_suite:
        suites = {suite_of(r) for r in new_ids}
        h = h[h["run_id"].astype(str).map(suite_of).isin(suites)]
    if len(h) == 0:
        return h
    t = _run_times(h)
    h = h[h["run_id"].map(t) < t_new]
    keys = _key(h)
    h = h.assign(_k=keys, _t=h["run_id"].map(t))
    want = set(_key(new[new["status"].isin(MEASURED + ("error",))]))
    ok = h[h["status"].isin(MEASURED) & h["_k"].isin(want)]
    if len(ok) == 0:
        return history.iloc[0:0]
    latest = ok.groupby("_k")["_t"].transform("max")
    return ok[ok["_t"] == latest].drop(columns=["_k", "_t"])


def compare_with_history(history: pd.DataFrame, new: pd.DataFrame) -> pd.DataFrame:
    """Every cell of the run ``new`` against its own baseline in ``history`` (``baseline_rows``)."""
    return compare_runs(baseline_rows(history, new), new)


def compare_runs(old: pd.DataFrame, new: pd.DataFrame, *, require_common: bool = False) -> pd.DataFrame:
    """All compared values of cells present in both tables — measured in ``old`` — with ``flag`` in
    {"regression", "improvement", ""} (``CHANGE_COLUMNS``; ``baseline`` = the run id the cell was
    compared with). ``old`` may hold rows of several runs, at most one per cell (``baseline_rows``).

    require_common: raise ``NoCommonCells`` when no cell of ``new`` is in ``old`` (ok or not)."""
    out: list[dict] = []
    old = old[old["status"] != "run"]  # the run-level rows (triad bandwidth) are no cell
    new = new[new["status"] != "run"]
    if require_common and (len(old) == 0 or len(new) == 0
                           or not set(_key(old)) & set(_key(new))):
        raise NoCommonCells("the two runs share no cell (scene, size, sequence, method, config, bounces): "
                            "nothing to compare")
    if len(old) == 0 or len(new) == 0:
        return pd.DataFrame(columns=CHANGE_COLUMNS)
    old = old.assign(_k=_key(old))
    new = new.assign(_k=_key(new))
    ok_old = set(old.loc[old["status"].isin(MEASURED), "_k"])
    old_groups = {k: g for k, g in old.groupby("_k", sort=False)}
    for k, g_new in new.groupby("_k", sort=True):
        ident = {c: g_new.iloc[0][c] for c in CELL_ID}
        if k not in ok_old:
            continue
        g_old = old_groups[k]
        ident["baseline"] = str(g_old.iloc[0]["run_id"])
        status = g_new.iloc[0]["status"]
        if status == "error":
            out.append({**ident, "metric": "status", "old": float("nan"), "new": float("nan"), "rel_change": float("nan"),
                        "p_value": float("nan"), "threshold": float("nan"), "flag": "regression",
                        "test": f"cell failed: {g_new.iloc[0]['reason']}"})
            continue
        if status not in MEASURED:
            continue
        if status == "suspect" and g_old.iloc[0]["status"] == "ok":
            out.append({**ident, "metric": "status", "old": float("nan"), "new": float("nan"), "rel_change": float("nan"),
                        "p_value": float("nan"), "threshold": float("nan"), "flag": "regression",
                        "test": f"cell became suspect: {g_new.iloc[0]['reason']}"})
        out += _compare_errors(ident, g_old, g_new)
        out += _compare_times(ident, g_old, g_new)
        out += _compare_memory(ident, g_old, g_new)
    return pd.DataFrame(out, columns=CHANGE_COLUMNS)


def cells_compared(changes: pd.DataFrame | None) -> int:
    """Number of distinct cells in a changes table."""
    if changes is None or len(changes) == 0:
        return 0
    return int(_key(changes).nunique())


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
        if metric == "rmse":  # the floor slack only when the reference was re-rendered (its floor moved):
            # against the same cached reference a deterministic method's RMSE repeats exactly
            floors = [f for f in (fo, fn) if math.isfinite(f)]
            same_ref = math.isfinite(fo) and math.isfinite(fn) and abs(fo - fn) <= 1e-12 * max(abs(fo), 1e-30)
            absf = NOISE_FLOOR_FRAC * max(floors) if floors and not same_ref else 0.0
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


def _rel_iqr(x: np.ndarray) -> float:
    q1, med, q3 = np.percentile(x, [25, 50, 75])
    return float((q3 - q1) / med) if med > 0 else float("inf")


def time_change(old: np.ndarray, new: np.ndarray, *, rel: float = TIME_REL, spread_k: float = TIME_SPREAD_K,
                abs_floor: float | None = None) -> tuple[str, float, float]:
    """(flag, median ratio − 1, threshold) of frame-time samples ``old`` (n,) vs ``new`` (m,), seconds.

    Flag ``"regression"`` when ``median(new)/median(old) − 1 ≥ threshold`` and the medians differ by
    at least ``abs_floor`` seconds; ``threshold = max(rel, spread_k · spread)`` with ``spread`` the
    larger relative IQR (IQR / median, numpy's linear percentiles) of the two samples.
    ``"improvement"`` by the mirror rule (``median(old)/median(new) − 1 ≥ threshold``)."""
    abs_floor = TIME_ABS_FLOOR if abs_floor is None else abs_floor  # read at call time (tests set it)
    old = np.asarray(old, dtype=np.float64)
    new = np.asarray(new, dtype=np.float64)
    if old.ndim != 1 or new.ndim != 1 or len(old) == 0 or len(new) == 0:
        raise ValueError("old and new must be 1-D with at least one frame time each")
    if not (np.all(np.isfinite(old)) and np.all(np.isfinite(new))) or old.min() < 0 or new.min() < 0:
        raise ValueError("frame times must be finite and >= 0")
    mo, mn = float(np.median(old)), float(np.median(new))
    if mo <= 0 or mn <= 0:
        return "", float("nan"), float("nan")
    thr = max(rel, spread_k * max(_rel_iqr(old), _rel_iqr(new)))
    change = mn / mo - 1.0
    if abs(mn - mo) < abs_floor:
        return "", change, thr
    if change >= thr:
        return "regression", change, thr
    if mo / mn - 1.0 >= thr:
        return "improvement", change, thr
    return "", change, thr


def _first(g: pd.DataFrame, col: str, metric: str = "render_time"):
    r = g[g["metric"] == metric]
    return r.iloc[0][col] if len(r) else None


def _machine_kind(machine) -> str:
    """CPU model and core count of a ``store.machine_description()`` ("host | cpu | N cpu | OS")."""
    parts = str(machine).split(" | ")
    return " | ".join(parts[1:3]) if len(parts) >= 3 else str(machine)


def _compare_times(ident: dict, g_old: pd.DataFrame, g_new: pd.DataFrame) -> list[dict]:
    a, b = frame_samples(g_old), frame_samples(g_new)
    if len(a) == 0 or len(b) == 0:
        return []
    row = {**ident, "metric": "render_time", "old": float(np.median(a)), "new": float(np.median(b)),
           "p_value": float("nan")}
    why = []
    if _first(g_old, "threads") != _first(g_new, "threads"):
        why.append(f"threads {_first(g_old, 'threads')} vs {_first(g_new, 'threads')}")
    if _machine_kind(_first(g_old, "machine")) != _machine_kind(_first(g_new, "machine")):
        why.append("another machine kind")
    for run, g in (("old", g_old), ("new", g_new)):
        other = _summary(g, "other_cpu_cores")
        if other is not None and other[0] > CONTENTION_MAX:  # NaN (unknown) compares
            why.append(f"other processes used {other[0]:.2f} cores while the {run} run timed it")
    if why:
        return [{**row, "rel_change": _rel(row["old"], row["new"]), "threshold": float("nan"), "flag": "",
                 "test": f"not compared: {', '.join(why)}"}]
    flag, change, thr = time_change(a, b)
    return [{**row, "rel_change": change, "threshold": thr, "flag": flag,
             "test": f"median ratio vs max({TIME_REL:g}, {TIME_SPREAD_K:g}·rel. IQR) (n={len(a)},{len(b)})"}]


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
    return list(_run_times(history).sort_values().index)


def baseline_runs(changes: pd.DataFrame | None) -> str | None:
    """The baseline run id(s) of a changes table, most cells first, as one line (None if empty)."""
    if changes is None or len(changes) == 0:
        return None
    per_cell = changes.assign(_k=_key(changes)).drop_duplicates("_k")
    counts = per_cell["baseline"].value_counts()
    counts = counts.iloc[sorted(range(len(counts)), key=lambda i: (-counts.iloc[i], str(counts.index[i])))]
    if len(counts) == 1:
        return str(counts.index[0])
    return ", ".join(f"{rid} ({n} cell{'s' if n > 1 else ''})" for rid, n in counts.items())


def format_changes(changes: pd.DataFrame, *, only_flagged: bool = False) -> str:
    """A plain-text table of changes (flags: ``!!`` regression, ``++`` improvement)."""
    ch = flagged(changes) if only_flagged else changes
    if len(ch) == 0:
        return "no changes" if only_flagged else "no comparable cells"
    lines = [f"{'':2} {'scene':14} {'seq':4} {'method':16} {'b':4} {'metric':14} {'old':>11} {'new':>11} {'change':>8} "
             f"{'thresh':>7}"]
    for _, r in ch.iterrows():
        mark = {"regression": "!!", "improvement": "++"}.get(r["flag"], "  ")
        b = "full" if int(r["bounces"]) == -1 else str(r["bounces"])
        rc = f"{100 * r['rel_change']:+.1f}%" if math.isfinite(r["rel_change"]) else "-"
        th = r["threshold"]
        ts = "-" if not math.isfinite(th) else (f"{100 * th:.1f}%" if r["metric"] in ("render_time", "memory_bytes")
                                                else f"{th:.2g}")
        lines.append(f"{mark:2} {str(r['scene'])[:14]:14} {r['sequence']:4} {str(r['method'])[:16]:16} {b:4} "
                     f"{r['metric'][:14]:14} {r['old']:11.4g} {r['new']:11.4g} {rc:>8} {ts:>7}")
    n_reg = int((ch["flag"] == "regression").sum())
    n_imp = int((ch["flag"] == "improvement").sum())
    lines.append(f"{n_reg} regression(s), {n_imp} improvement(s)")
    return "\n".join(lines)
