"""A whole benchmark run: plan cells → run them (resumable) → long table → history → regressions
→ HTML report. ``run_bench.py`` is a thin command line over these functions.

Run directory layout (``--out``):
``run.json`` (run id, time, git sha, versions, machine, bandwidth — written once, kept on resume),
``plan.json`` (the cells), ``cells/<key>.json`` (one result per finished cell), ``images/<key>.npz``,
``calib/*.json`` (reference convergence fits), ``results.parquet``, ``changes.csv``, ``report.html``,
``provenance.json`` (executor, workers, host and threads behind each cell's numbers);
``cells/parts/<key>.{errors,timing}.json`` when a parallel executor split the cells.

Re-running into the same ``--out`` adds to the run there: cells already finished are kept (also
those of methods/scenes not selected this time), so the results table, the report and the history
cover every cell of the run. A run that cannot be resumed (other code, package versions or suite,
or a corrupt ``run.json``) is moved aside to ``<out>.prev-<UTC time>`` (``preserve_run``), never
deleted.
"""
from __future__ import annotations

import json
import math
import os
import time
import uuid
from dataclasses import dataclass
from datetime import datetime, timezone
from pathlib import Path

import pandas as pd
import torch

from reports import measure, regress, store
from reports.cells import MEASURED, Cell, CellResult, load_result, move_aside
from reports.executors import LocalExecutor, MethodProcessExecutor
from reports.html import wall_time_text
from reports.runner import run_cells
from reports.suites import Suite, plan_cells, reference_jobs

TRIAD_ELEMENTS = measure.TRIAD_ELEMENTS


@dataclass
class RunOutput:
    run_id: str
    out_dir: Path
    table: Path
    report: Path | None
    history: Path | None
    n_ok: int
    n_na: int
    n_error: int
    changes: pd.DataFrame | None
    n_suspect: int = 0
    wall_time: str | None = None   # `html.wall_time_text` of the run's invocations


def suite_label(suite_name: str, scenes=None) -> str:
    """How a run names its suite (the first part of its id, ``regress.suite_of``): the suite's name,
    plus ``+files`` when the run includes scene files — such a run is not a run of the suite's own
    scenes and must not pass for one."""
    return suite_name + ("+files" if any(str(s).startswith("file:") for s in (scenes or ())) else "")


def run_meta(out_dir: Path, suite_name: str, *, bandwidth_elements: int = TRIAD_ELEMENTS) -> dict:
    """The run's facts; created (with one triad-bandwidth measurement) on the first call and
    re-read on resume, so a resumed run keeps its id. ``suite_name``: the ``suite_label``."""
    p = out_dir / "run.json"
    old, why = _read_run_json(p)
    if old is not None:
        return old
    if why is not None:
        move_aside(p, why)
    now = datetime.now(timezone.utc)
    sha = store.git_sha()
    meta = {
        "run_id": f"{suite_name}-{now.strftime('%Y%m%dT%H%M%SZ')}-{sha[:8]}-{uuid.uuid4().hex[:4]}",
        "suite": suite_name,
        "time": now.isoformat(timespec="microseconds"),
        "git_sha": sha,
        "code": store.code_fingerprint(),
        "versions": store.package_versions(),
        "machine": store.machine_description(),
        "threads": torch.get_num_threads(),
        # `run_bench.openmp_env`: the OpenMP settings the run's processes ran under
        "openmp": " ".join(f"{k}={os.environ[k]}" for k in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT") if k in os.environ),
    }
    meta = with_limits(meta, measure_limits(bandwidth_elements, "start"))
    store.atomic_write_json(p, meta)
    return meta


def measure_limits(bandwidth_elements: int = TRIAD_ELEMENTS, when: str = "") -> dict:
    """One measurement of both machine limits (triad bandwidth in B/s, dense-matmul peak in FLOP/s)."""
    return {"when": when, **measure.machine_limits(bandwidth_elements)}


def with_limits(meta: dict, sample: dict) -> dict:
    """``meta`` with ``sample`` added to its limit measurements and ``triad_bandwidth`` /
    ``matmul_peak`` set to the best of them.

    The roofline's denominators are what the machine can do; a measurement taken while something
    else loads this shared machine reads low, and a low roof inflates every cell's efficiency.
    The run therefore measures at its start and again at the end of each invocation and keeps the
    highest of each (a run.json from before this rule counts its one value as a measurement).
    """
    samples = list(meta.get("limit_samples") or [])
    if not samples and "triad_bandwidth" in meta:
        samples.append({"when": "start", "triad_bandwidth": meta["triad_bandwidth"],
                        "matmul_peak": meta.get("matmul_peak", float("nan"))})
    samples.append(sample)
    best = {k: max((float(s[k]) for s in samples if s.get(k) is not None and math.isfinite(float(s[k]))),
                   default=float("nan")) for k in ("triad_bandwidth", "matmul_peak")}
    return {**meta, **best, "limit_samples": samples}


def record_invocation(out_dir: Path, meta: dict, *, started: str, seconds: float, cells: int,
                      bandwidth_elements: int | None = TRIAD_ELEMENTS) -> dict:
    """Append this invocation's wall time (planning, references and cells; not the report) to the
    run's facts in run.json, so a resumed run's report gives every invocation and their sum; and,
    unless ``bandwidth_elements`` is None, measure the machine's limits once more (`with_limits`)."""
    meta = {**meta, "invocations": [*meta.get("invocations", []),
                                    {"started": started, "seconds": round(float(seconds), 1), "cells": int(cells)}]}
    if bandwidth_elements is not None:
        meta = with_limits(meta, measure_limits(bandwidth_elements, f"end of invocation {len(meta['invocations'])}"))
    store.atomic_write_json(out_dir / "run.json", meta)
    return meta


RUN_META_KEYS = ("run_id", "suite", "time", "git_sha", "versions", "machine", "threads", "triad_bandwidth")


def _read_run_json(p: Path) -> tuple[dict | None, str | None]:
    """(meta, None) from a valid run.json; (None, None) if there is none; (None, why) if it is
    corrupt (a folder, not UTF-8, not JSON, not a run's facts). No side effects."""
    if not p.exists() and not p.is_symlink():
        return None, None
    if p.is_dir():
        return None, "a folder in place of run.json"
    try:
        d = json.loads(p.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as e:
        return None, f"not UTF-8 text ({e.reason} at byte {e.start})"
    except json.JSONDecodeError as e:
        return None, f"not JSON ({e.msg} at line {e.lineno} column {e.colno})"
    except OSError as e:
        return None, f"unreadable ({e.strerror or e})"
    if not isinstance(d, dict) or any(k not in d for k in RUN_META_KEYS) or not isinstance(d["run_id"], str):
        return None, "not a run's facts (needs " + ", ".join(RUN_META_KEYS) + ")"
    return d, None


def read_run_json(out_dir: str | os.PathLike) -> dict | None:
    """The run facts in ``<out_dir>/run.json``, or None if it is missing or corrupt (no side
    effects: ``run_suite`` moves a corrupt one aside and starts afresh)."""
    return _read_run_json(Path(out_dir) / "run.json")[0]


def cell_limits(results: list[CellResult]) -> dict[str, list[float]]:
    """The limits each measured cell found right after its timed frames (``host_triad_bandwidth``,
    ``host_matmul_peak``: `reports.measure_cell.cell_limits`), finite values only, in cell order."""
    out: dict[str, list[float]] = {"triad_bandwidth": [], "matmul_peak": []}
    for r in results:
        if r.status not in MEASURED:
            continue
        for row in r.rows:
            k = {"host_triad_bandwidth": "triad_bandwidth", "host_matmul_peak": "matmul_peak"}.get(row["metric"])
            if k is not None and row["frame"] == -1 and math.isfinite(float(row["value"])):
                out[k].append(float(row["value"]))
    return out


def run_limits(results: list[CellResult], meta: dict) -> tuple[float, float]:
    """(triad bandwidth, matmul peak) the run's roofline divides by: the best of the run's own
    measurements (``meta``, `with_limits`) and the cells' (`cell_limits`). The best, not a typical
    value: the roof is what the machine can do, and a reading taken while the host was slowed would
    inflate every efficiency."""
    per_cell = cell_limits(results)
    bw = max([float(meta["triad_bandwidth"])] + per_cell["triad_bandwidth"],
             key=lambda v: v if math.isfinite(v) else -math.inf)
    pk = max([float(meta.get("matmul_peak", float("nan")))] + per_cell["matmul_peak"],
             key=lambda v: v if math.isfinite(v) else -math.inf)
    return bw, pk


def ray_rates(results: list[CellResult]) -> dict[tuple[str, str], float]:
    """(scene, size) → the ray rate the run's roofline divides ``rays_per_frame`` by: the best of the
    ``host_ray_rate`` readings of the run's cells on that scene at that size (`reports.measure.ray_rate`;
    per scene because a traversal's speed depends on the mesh; the best, as `run_limits`)."""
    out: dict[tuple[str, str], float] = {}
    for r in results:
        if r.status not in MEASURED:
            continue
        c = Cell.from_dict(r.cell)
        for row in r.rows:
            v = float(row["value"])
            if row["metric"] == "host_ray_rate" and row["frame"] == -1 and math.isfinite(v) and v > 0:
                out[(c.scene, c.size)] = max(out.get((c.scene, c.size), 0.0), v)
    return out


def collect(results: list[CellResult], meta: dict) -> pd.DataFrame:
    """Cell results + run facts → the run's long table (``store.COLUMNS``), with the roofline
    efficiency computed from the run's limits (`run_limits`), and one ``status="run"`` row for the
    bandwidth."""
    base = {"run_id": meta["run_id"], "time": meta["time"], "git_sha": meta["git_sha"],
            "versions": json.dumps(meta["versions"], sort_keys=True), "machine": meta["machine"]}
    bandwidth, peak = run_limits(results, meta)
    rates = ray_rates(results)
    rows = [{**base, "threads": meta["threads"], "scene": "", "size": "", "sequence": "", "frame": -1, "method": "",
             "config": "", "bounces": -1, "metric": "triad_bandwidth", "value": bandwidth, "unit": "B/s",
             "noise_floor": float("nan"), "status": "run", "reason": "", "cell": ""}]
    for r in results:
        c = Cell.from_dict(r.cell)
        ident = {**base, "threads": r.info.get("threads", c.threads or meta["threads"]), "scene": c.scene,
                 "size": c.size, "sequence": c.kind, "method": c.method, "config": c.config, "bounces": c.bounces,
                 "status": r.status, "reason": r.reason, "cell": r.key}
        if r.status not in MEASURED:
            rows.append({**ident, "frame": -1, "metric": "status", "value": float("nan"), "unit": "",
                         "noise_floor": float("nan")})
            continue
        vals = {row["metric"]: row["value"] for row in r.rows if row["frame"] == -1}
        rows += [{**ident, **row} for row in r.rows]
        # roofline: max(bytes / bandwidth, flops / peak) / frame time, and which bound applies
        roof = measure.roofline(vals.get("bytes_per_frame"), vals.get("flops_per_frame"), bandwidth, peak,
                                vals.get("render_time_median", float("nan")), vals.get("rays_per_frame"),
                                rates.get((c.scene, c.size)))
        if roof is not None:
            rows.append({**ident, "frame": -1, "metric": "roofline_efficiency", "value": roof[0], "unit": "1",
                         "noise_floor": float("nan")})
            for bound in ("compute", "traversal"):
                rows.append({**ident, "frame": -1, "metric": f"roofline_{bound}_bound", "value": float(roof[1] == bound),
                             "unit": "1", "noise_floor": float("nan")})
    return store.to_frame(rows)


RUN_FILES = ("run.json", "plan.json", "results.parquet", "changes.csv", "report.html", "provenance.json")


def provenance(results: list[CellResult]) -> list[dict]:
    """Which executor, how many workers, which host and how many threads produced each cell's
    numbers (one dict per run cell; the errors and timing parts separately when a parallel
    executor split the cell)."""
    out = []
    for r in results:
        if r.status == "na":
            continue
        c = Cell.from_dict(r.cell)
        base = {"cell": r.key, "method": c.method, "scene": c.scene, "sequence": c.kind, "bounces": c.bounces,
                "status": r.status}
        parts = r.info.get("parts") or {"all": r.info}
        for part, i in parts.items():
            out.append({**base, "part": part, "executor": i.get("executor", "?"), "workers": i.get("workers", "?"),
                        "scheduler": i.get("scheduler", ""), "host": i.get("host", ""),
                        "worker": i.get("worker", ""), "threads": i.get("threads", "?"),
                        "code": i.get("code", r.info.get("code", ""))})
    return out
RUN_DIRS = ("cells", "images", "calib")


def clear_run(out_dir: str | os.PathLike) -> None:
    """Remove a previous run's files from ``out_dir`` (only the files a run writes)."""
    import shutil

    out_dir = Path(out_dir)
    for f in RUN_FILES:
        (out_dir / f).unlink(missing_ok=True)
    for d in RUN_DIRS:
        if (out_dir / d).is_dir():
            shutil.rmtree(out_dir / d)


def preserve_run(out_dir: str | os.PathLike) -> Path | None:
    """Move a previous run's files (``RUN_FILES``, ``RUN_DIRS``) out of ``out_dir`` into a new
    sibling folder ``<out>.prev-<UTC time>``; returns it (None if there was nothing to move).
    ``run.json`` moves last, so an interrupted move is still recognised (and finished) next time."""
    out_dir = Path(out_dir)
    names = [n for n in RUN_DIRS + RUN_FILES if n != "run.json" and (out_dir / n).exists()]
    if (out_dir / "run.json").exists():
        names.append("run.json")
    if not names:
        return None
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%SZ")
    dest = out_dir.parent / f"{out_dir.name}.prev-{stamp}"
    n = 1
    while True:
        try:
            dest.mkdir(parents=True)
            break
        except FileExistsError:
            n += 1
            dest = out_dir.parent / f"{out_dir.name}.prev-{stamp}-{n}"
    for name in names:
        os.replace(out_dir / name, dest / name)
    return dest


def earlier_cells(out_dir: Path) -> list[Cell]:
    """The cells of the run already in ``out_dir`` (its ``plan.json``; empty if none/unreadable)."""
    p = out_dir / "plan.json"
    if not p.exists():
        return []
    try:
        return [Cell.from_dict(d) for d in json.loads(p.read_text())]
    except (OSError, ValueError, TypeError, AttributeError) as e:
        print(f"[prtbench] {p}: unreadable ({type(e).__name__}: {e}); earlier cells of this run are not "
              f"added to its table", flush=True)
        return []


def _merge_plans(earlier: list[Cell], cells: list[Cell]) -> tuple[list[Cell], list[Cell]]:
    """(every cell of the run — earlier ones in their order, replaced by this selection's cell of the
    same key, then this selection's new cells; the earlier cells not in this selection)."""
    mine = {c.key(): c for c in cells}
    others = [c for c in earlier if c.key() not in mine]
    order = list(dict.fromkeys([c.key() for c in earlier] + list(mine)))
    by_key = {**{c.key(): c for c in others}, **mine}
    return [by_key[k] for k in order], others


def run_suite(suite: Suite, out_dir: str | os.PathLike, *, methods=None, scenes=None, executor=None,
              history: str | os.PathLike | None = store.DEFAULT_HISTORY, backend: str = "reports.backend",
              plugins: tuple[str, ...] = (), isolate: bool | str | None = None, progress: bool = True,
              report: bool = True, vertex_renders: bool = True, bandwidth_elements: int | None = None,
              device: str = "cpu") -> RunOutput:
    """Run ``suite`` into ``out_dir``: resume the run there, adding this selection's cells to it;
    a run there that cannot be resumed (``stale_reason``) is moved aside (``preserve_run``) first."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    label = suite_label(suite.name, scenes)
    stale = stale_reason(out_dir, label)
    if stale:
        dest = preserve_run(out_dir)
        kept = f"its results were moved to {dest}" if dest is not None else "it had no results to keep"
        print(f"[prtbench] {out_dir}: {stale}; {kept}; starting a fresh run there", flush=True)
    cells = plan_cells(suite, methods=methods, scenes=scenes, backend=backend, plugins=plugins, isolate=isolate,
                       device=device)
    everything, others = _merge_plans(earlier_cells(out_dir), cells)
    store.atomic_write_json(out_dir / "plan.json", [c.to_dict() for c in everything])
    started = datetime.now(timezone.utc).isoformat(timespec="seconds")
    t0 = time.perf_counter()
    meta = run_meta(out_dir, label, bandwidth_elements=bandwidth_elements or TRIAD_ELEMENTS)
    own = None
    if (executor is None or type(executor) is LocalExecutor) and any(c.isolate == "method" and c.na is None
                                                                      for c in cells):
        executor = own = MethodProcessExecutor()  # one process per method configuration (the perf suite)
    try:
        results = run_cells(cells, out_dir, executor=executor, progress=progress)
    finally:
        if own is not None:
            own.shutdown()
    meta = record_invocation(out_dir, meta, started=started, seconds=time.perf_counter() - t0,
                             cells=sum(c.na is None for c in cells),
                             bandwidth_elements=bandwidth_elements or TRIAD_ELEMENTS)
    report_failures(results)
    kept = {}
    for c in others:  # finished cells of earlier invocations of this run, not selected this time
        r = load_result(out_dir, c)
        if r is not None:
            kept[c.key()] = r
    mine = {r.key: r for r in results}
    results = [mine.get(c.key()) or kept[c.key()] for c in everything if c.key() in mine or c.key() in kept]
    return finish_run(out_dir, results, meta, history=history, report=report, vertex_renders=vertex_renders)


def report_failures(results: list[CellResult], file=None) -> int:
    """Print one line per failed or suspect cell (method/scene/sequence/bounces: its reason — the
    exception, or what the sanity gate found — on one line) on stderr; returns how many failed."""
    import sys

    n = 0
    for r in results:
        if r.status not in ("error", "suspect"):
            continue
        n += r.status == "error"
        c = r.cell
        reason = " ".join(str(r.reason).split()) or "no reason recorded"
        what = "FAILED" if r.status == "error" else "SUSPECT"
        print(f"[prtbench] {what} {c.get('method')}/{c.get('scene')}/{c.get('kind')}/b{c.get('bounces')}: "
              f"{reason[:500]}", file=file or sys.stderr, flush=True)
    return n


def stale_reason(out_dir: Path, label: str | None = None) -> str | None:
    """Why the run in ``out_dir`` must not be resumed (its code, package versions or suite label
    differ from this one's, or its run.json is corrupt — that file is then moved aside), or None.
    Resuming it would mix numbers of different code in one table."""
    p = out_dir / "run.json"
    old, why = _read_run_json(p)
    if why is not None:
        move_aside(p, why)
        return "its run.json was corrupt, so its cells' code is unknown"
    if old is None:
        return None
    if old.get("code") != store.code_fingerprint():
        return "the code changed since this run started"
    if old.get("versions") != store.package_versions():
        return "package versions changed since this run started"
    if label is not None and old.get("suite") != label:
        return f"it is a run of suite {old.get('suite')!r}, not {label!r}"
    return None


def finish_run(out_dir: Path, results: list[CellResult], meta: dict, *, history=store.DEFAULT_HISTORY,
               report: bool = True, vertex_renders: bool = True) -> RunOutput:
    df = collect(results, meta)
    prov = provenance(results)
    store.atomic_write_json(out_dir / "provenance.json", prov)
    table = store.write_table(df, out_dir / "results.parquet")
    changes, prev_id = None, None
    hist_path = None
    if history is not None:
        changes = regress.compare_with_history(store.read_history(history), df)
        prev_id = regress.baseline_runs(changes)
        if prev_id is None:
            changes = None
        else:
            store.atomic_save(out_dir / "changes.csv", lambda tmp: changes.to_csv(tmp, index=False))
        hist_path = store.append_history(df, history)
    rep = None
    if report:
        from reports.html import build_report

        bw, pk = run_limits(results, meta)  # what `collect` divided by
        rep = build_report(df, out_dir / "report.html", run_dir=out_dir,
                           meta={**meta, "triad_bandwidth": bw, "matmul_peak": pk, "provenance": prov},
                           changes=changes, prev_run=prev_id,
                           vertex_renders=vertex_renders)
    st = df.drop_duplicates("cell")
    st = st[st["status"] != "run"]["status"]
    return RunOutput(meta["run_id"], out_dir, table, rep, hist_path, int((st == "ok").sum()), int((st == "na").sum()),
                     int((st == "error").sum()), changes, n_suspect=int((st == "suspect").sum()),
                     wall_time=wall_time_text(meta))


def build_references(suite: Suite, *, methods=None, scenes=None, backend: str = "reports.backend",
                     plugins: tuple[str, ...] = (), progress: bool = True) -> int:
    """Render (into the reference cache) every reference the suite's in-scope cells need,
    including the equal-error spp ladder. Returns the number of references requested."""
    from tqdm.auto import tqdm

    from reports.backend import load_backend

    be = load_backend(backend)
    cells = plan_cells(suite, methods=methods, scenes=scenes, backend=backend, plugins=plugins)
    jobs = reference_jobs(cells)
    todo = []
    for scene_name, size, kind, n_frames, seed, bounces, spp, frames, ladder in jobs:
        todo += [(scene_name, size, kind, n_frames, seed, bounces, spp, i) for i in frames]
        if ladder:
            todo += [(scene_name, size, kind, n_frames, seed, bounces, s, frames[0]) for s in ladder if s != spp]
    todo = list(dict.fromkeys(todo))
    seqs: dict = {}
    for scene_name, size, kind, n_frames, seed, bounces, spp, i in tqdm(todo, desc="references", disable=None if progress else True):
        k = (scene_name, size, kind, n_frames, seed)
        if k not in seqs:
            sc = be.get_scene(scene_name, size)
            seqs[k] = (sc, be.make_sequence(sc, kind, n_frames, seed))
        sc, frames = seqs[k]
        be.render_reference(sc, frames[i], bounces=bounces, spp=spp, seed=seed, spp_side=suite.spp_side)
    return len(todo)
