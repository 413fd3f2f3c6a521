"""Cells — the unit of work of a benchmark run — and the loop that runs them.

A *cell* is (scene, size, sequence kind, method, config, bounces) plus the measuring settings:
a small frozen, picklable dataclass, independent of every other cell, executed by
``run_cell(cell, out_dir) -> CellResult``. ``run_cells`` drives any ``concurrent.futures``-like
executor (``submit(fn, *args) -> future``; ``future.result()``): in process, a spawn-based process
pool or a Dask cluster (``reports/executors.py``). Parallel executors run each cell as two tasks —
image errors (in parallel) and timings (one at a time per machine) — merged into one result
(``run_part``, ``merge_parts``).

Resuming: each finished cell writes ``<out>/cells/<key>.json`` atomically (temp + ``os.replace``);
``run_cell`` returns that file's result without recomputing. Cells that failed are retried.

Measuring (DESIGN.md "Measuring"): precompute time; per-frame render time (``perf_counter``, first
frame = warm-up excluded from median/IQR; all frames stored); ``Method.memory()``; peak RSS of the
cell's process (``ru_maxrss``) — the cell's own when ``isolate`` runs it in a spawned child;
``bytes_per_frame``; error metrics against the reference of the cell's bounce count on the
``score_frames``; the equal-error speedup (``reports.measure.fit_convergence``).
"""
from __future__ import annotations

import hashlib
import importlib
import json
import multiprocessing as mp
import os
import sys
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import torch

from reports import measure, precompute_cache
from reports.store import atomic_save, atomic_write_json

FULL = -1  # bounces = −1: full global illumination (Mitsuba max_depth = −1)
STATUS_OK, STATUS_NA, STATUS_ERROR = "ok", "na", "error"

# Units of the values the harness stores (metric name → unit).
UNITS = {
    "rmse": "radiance", "rel_mse": "1", "psnr": "dB", "ssim": "1", "flip": "1", "delta_e2000": "dE00",
    "nonfinite_frac": "1", "render_time": "s", "render_time_median": "s", "render_time_iqr": "s",
    "fps": "1/s", "precompute_time": "s", "memory_bytes": "B", "peak_rss_bytes": "B",
    "harness_peak_rss_bytes": "B", "bytes_per_frame": "B", "roofline_efficiency": "1",
    "eq_error_speedup": "x", "mitsuba_time_eq_error": "s", "timed_frames": "1",
    "rmse_full_gi": "radiance", "precompute_cached": "1", "precompute_load_time": "s",
}


def canonical_config(config: dict | str | None) -> str:
    """A method config as canonical JSON (sorted keys), the form cells and tables store."""
    if config is None:
        config = {}
    if isinstance(config, str):
        config = json.loads(config)
    if not isinstance(config, dict):
        raise ValueError(f"method config must be a dict, got {type(config).__name__}")
    return json.dumps(config, sort_keys=True, separators=(",", ":"))


def bounces_label(b: int) -> str:
    return "full" if b == FULL else str(b)


def capability_bounces(b: int) -> int:
    """Bounce count as ``Capabilities.why_not`` compares it (full GI exceeds every finite max)."""
    return 10**6 if b == FULL else b


@dataclass(frozen=True)
class Cell:
    """One independent unit of a run (picklable; ``key()`` identifies its result file).

    scene: library name, or ``"file:<path>"`` for a TOML scene file. size: "test" | "bench".
    kind: sequence kind "V" | "VB" | "VBL" | "P". method: registry name; config: canonical JSON.
    bounces: 0 = direct lighting, k = k indirect bounces, −1 = full GI.
    n_frames, seed: the sequence. score_frames: frame indices scored against references (empty =
    all). ref_spp: reference samples per pixel. spp_side: G-buffer S (S×S sub-samples).
    eq_err_spp: reference spp ladder for the equal-error speedup (empty = skip).
    threads: torch / Dr.Jit threads (None = leave the defaults). isolate: run in a spawned child.
    na: the n/a reason from the capability matrix (None = in scope); the cell is then not run.
    score_full_gi: also score every scored frame against the full-GI reference (metric
    ``rmse_full_gi``; Sun 2007 Fig. 11: a method that renders k bounces is also judged by how far it
    is from the real image) — set by the suites for methods with ``max_bounces > 0``.
    backend: module providing scenes/references/metrics (see ``reports.backend``).
    plugins: modules imported before the method is looked up (e.g. tests registering a method).
    """

    scene: str
    size: str
    kind: str
    method: str
    config: str = "{}"
    bounces: int = 0
    n_frames: int = 3
    seed: int = 0
    score_frames: tuple[int, ...] = ()
    ref_spp: int = 64
    spp_side: int = 2
    eq_err_spp: tuple[int, ...] = ()
    threads: int | None = None
    isolate: bool = False
    save_images: bool = True
    na: str | None = None
    score_full_gi: bool = False
    backend: str = "reports.backend"
    plugins: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.kind not in ("V", "VB", "VBL", "P"):
            raise ValueError(f"unknown sequence kind {self.kind!r}")
        if self.n_frames < 1:
            raise ValueError("n_frames must be >= 1")
        if self.bounces < FULL:
            raise ValueError("bounces must be >= 0 or -1 (full)")
        if any(not 0 <= f < self.n_frames for f in self.score_frames):
            raise ValueError(f"score_frames {self.score_frames} outside 0..{self.n_frames - 1}")
        canonical_config(self.config)

    def key(self) -> str:
        """Readable, unique, filesystem-safe id (``isolate`` does not change what is measured)."""
        d = asdict(self)
        d.pop("isolate")
        h = hashlib.sha1(json.dumps(d, sort_keys=True, default=list).encode()).hexdigest()[:12]
        scene = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in Path(self.scene).stem)
        return f"{scene}-{self.size}-{self.kind}-{self.method}-b{bounces_label(self.bounces)}-{h}"

    def scored(self) -> list[int]:
        return sorted(self.score_frames) if self.score_frames else list(range(self.n_frames))

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "Cell":
        names = {f.name for f in fields(cls)}
        d = {k: v for k, v in d.items() if k in names}
        for k in ("score_frames", "eq_err_spp", "plugins"):
            if k in d:
                d[k] = tuple(d[k])
        return cls(**d)


@dataclass
class CellResult:
    """What a cell produced: long-format rows (frame, metric, value, unit, noise_floor), the
    artifacts written (name → path relative to the run dir) and run facts (threads, …)."""

    key: str
    cell: dict
    status: str
    reason: str = ""
    rows: list[dict] = field(default_factory=list)
    artifacts: dict[str, str] = field(default_factory=dict)
    info: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> "CellResult":
        return cls(**d)


def result_path(out_dir: str | os.PathLike, cell: Cell) -> Path:
    return Path(out_dir) / "cells" / f"{cell.key()}.json"


def load_result(out_dir: str | os.PathLike, cell: Cell) -> CellResult | None:
    p = result_path(out_dir, cell)
    if not p.exists():
        return None
    try:
        return CellResult.from_dict(json.loads(p.read_text()))
    except (json.JSONDecodeError, TypeError):
        return None  # cannot happen with atomic writes; recompute if it does


def is_finished(out_dir, cell: Cell) -> bool:
    r = load_result(out_dir, cell)
    return r is not None and r.status != STATUS_ERROR


# -- running one cell -------------------------------------------------------------------------


THREADS_ENV = "PRTBENCH_THREADS"  # a worker's share of its machine's cores (set by reports.executors)
PARTS = ("errors", "timing")  # how a parallel executor splits a cell (see ``run_part``)


def run_cell(cell: Cell, out_dir: str | os.PathLike, *, progress: bool = True,
             context: dict | None = None) -> CellResult:
    """Run ``cell`` (or return its stored result) and store the result atomically.

    context: the executor's description (``executor``, ``workers``, …), recorded in ``info``."""
    out_dir = Path(out_dir)
    old = load_result(out_dir, cell)
    if old is not None and old.status != STATUS_ERROR:
        return old
    if cell.na is not None:
        res = CellResult(cell.key(), cell.to_dict(), STATUS_NA, reason=cell.na)
    elif cell.isolate:
        try:
            res = _run_isolated(cell, out_dir, progress)
        except Exception as e:  # the child died (BrokenProcessPool, OOM kill, …)
            res = CellResult(cell.key(), cell.to_dict(), STATUS_ERROR, reason=f"child process failed: {e!r}",
                             info={"traceback": traceback.format_exc()})
    else:
        res = execute_cell(cell, out_dir, progress=progress)
    if cell.na is None:
        res.info.update({**(context or {}), **{k: v for k, v in where().items() if k not in res.info}})
    atomic_write_json(result_path(out_dir, cell), res.to_dict())
    return res


def _run_isolated(cell: Cell, out_dir: Path, progress: bool, part: str = "all") -> CellResult:
    """Run the cell in a fresh spawned process, so its ``ru_maxrss`` is the cell's alone.

    A daemonic process (e.g. a Dask worker with ``distributed.worker.daemon: true``) may not have
    children: the cell then runs here, without isolation, and says so in ``info["isolate"]``."""
    if mp.current_process().daemon:
        res = execute_cell(replace(cell, isolate=False), out_dir, progress=progress, part=part)
        res.info["isolate"] = "skipped: daemonic worker process"
        return res
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=ctx) as ex:
        return ex.submit(execute_cell, cell, out_dir, progress=progress, part=part).result()


def task_threads(cell: Cell) -> int | None:
    """Threads a cell's task uses: the cell's own ``threads`` if set, else the worker's share of its
    machine's cores (``PRTBENCH_THREADS``, set by ``reports.executors``), else None (defaults)."""
    if cell.threads is not None:
        return cell.threads
    v = os.environ.get(THREADS_ENV)
    return int(v) if v else None


def _set_threads(n: int | None, backend) -> int:
    if n is not None:
        if n < 1:
            raise ValueError("threads must be >= 1")
        torch.set_num_threads(n)
        if hasattr(backend, "set_threads"):
            backend.set_threads(n)
    return torch.get_num_threads()


def execute_cell(cell: Cell, out_dir: str | os.PathLike, *, progress: bool = True, part: str = "all") -> CellResult:
    """Measure ``cell`` in this process (no result file; ``run_cell`` writes it). Never raises:
    a failure becomes an ``error`` result carrying the traceback.

    part: ``"all"`` (everything), ``"errors"`` (image errors only) or ``"timing"`` (times, memory and
    the reference convergence fit only) — see ``run_part``."""
    try:
        if part == "all":
            return _measure(cell, Path(out_dir), progress)
        if part not in PARTS:
            raise ValueError(f"unknown cell part {part!r}")
        return _measure(cell, Path(out_dir), progress, part=part)
    except Exception as e:
        return CellResult(cell.key(), cell.to_dict(), STATUS_ERROR, reason=f"{type(e).__name__}: {e}",
                          info={"traceback": traceback.format_exc(), "threads": torch.get_num_threads()})


# -- a cell in two parts (parallel executors) -------------------------------------------------


def part_path(out_dir: str | os.PathLike, cell: Cell, part: str) -> Path:
    return Path(out_dir) / "cells" / "parts" / f"{cell.key()}.{part}.json"


def load_part(out_dir: str | os.PathLike, cell: Cell, part: str) -> CellResult | None:
    p = part_path(out_dir, cell, part)
    if not p.exists():
        return None
    try:
        return CellResult.from_dict(json.loads(p.read_text()))
    except (json.JSONDecodeError, TypeError):
        return None


def where() -> dict[str, Any]:
    """Where this code runs: host, pid and (inside a Dask worker) the worker's address."""
    import socket

    d: dict[str, Any] = {"host": socket.gethostname(), "pid": os.getpid()}
    try:
        from distributed import get_worker

        d["worker"] = get_worker().address
    except (ImportError, ValueError):
        pass
    return d


def run_part(cell: Cell, part: str, out_dir: str | os.PathLike, *, progress: bool = False,
             context: dict | None = None) -> CellResult:
    """Run one part of ``cell`` (or return its stored result) and store it in
    ``<out>/cells/parts/<key>.<part>.json``.

    A parallel executor splits every cell in two so timings stay honest (issue #9):
    ``"errors"`` — precompute, render the whole sequence, score the ``score_frames`` against the
    references, save the images; runs on any worker, in parallel. ``"timing"`` — precompute (timed),
    render the whole sequence (timed), memory, bytes per frame, peak RSS and the reference
    convergence fit; runs one at a time per machine (``reports.executors``). ``merge_parts`` joins
    them into the same ``CellResult`` as ``run_cell``. ``context``: the executor's description,
    recorded in ``info``. The errors part never runs isolated (it measures no memory)."""
    out_dir = Path(out_dir)
    old = load_part(out_dir, cell, part)
    if old is not None and old.status != STATUS_ERROR:
        return old
    if part not in PARTS:
        raise ValueError(f"unknown cell part {part!r}")
    t_start = time.time()
    if cell.isolate and part == "timing":
        try:
            res = _run_isolated(cell, out_dir, progress, part=part)
        except Exception as e:
            res = CellResult(cell.key(), cell.to_dict(), STATUS_ERROR, reason=f"child process failed: {e!r}",
                             info={"traceback": traceback.format_exc()})
    else:
        res = execute_cell(replace(cell, isolate=False), out_dir, progress=progress, part=part)
        res.cell = cell.to_dict()
    res.info.update({**(context or {}), **{k: v for k, v in where().items() if k not in res.info}, "part": part,
                     "wall": [t_start, time.time()]})
    atomic_write_json(part_path(out_dir, cell, part), res.to_dict())
    return res


def _eq_error_rows(fit: dict | None, rmse0: float, noise_floor0: float, median: float) -> list[dict]:
    """Equal-error speedup rows from the convergence fit and the first scored frame's RMSE."""
    if fit is None:
        return []
    f = measure.ConvergenceFit(**fit)
    sp = measure.equal_error_speedup(f, rmse0, median)
    rows = [_row("eq_error_speedup", sp, noise_floor=noise_floor0)]
    if sp is not None:
        rows.append(_row("mitsuba_time_eq_error", f.time_for_rmse(rmse0)))
    return rows


PROVENANCE_KEYS = ("executor", "workers", "scheduler", "host", "worker", "threads", "pid", "isolate", "wall")


def merge_parts(cell: Cell, errors: CellResult, timing: CellResult) -> CellResult:
    """The cell's result from its two parts (``run_part``): the same rows as ``run_cell`` gives;
    ``info["parts"]`` says where (executor, workers, host, threads) each part ran."""
    parts = {p: {k: r.info[k] for k in PROVENANCE_KEYS if k in r.info} for p, r in (("errors", errors),
                                                                                    ("timing", timing))}
    bad = [(p, r) for p, r in (("errors", errors), ("timing", timing)) if r.status != STATUS_OK]
    if bad:
        return CellResult(cell.key(), cell.to_dict(), STATUS_ERROR,
                          reason="; ".join(f"{p} part: {r.reason}" for p, r in bad),
                          info={"parts": parts, "traceback": "\n".join(r.info.get("traceback", "") for _, r in bad)})
    rows = list(timing.rows) + list(errors.rows)
    first = cell.scored()[0]
    rmse0 = [r for r in errors.rows if r["metric"] == "rmse" and r["frame"] == first]
    median = [r["value"] for r in timing.rows if r["metric"] == "render_time_median"]
    if rmse0 and median:
        rows += _eq_error_rows(timing.info.get("convergence_fit"), rmse0[0]["value"], rmse0[0]["noise_floor"],
                               median[0])
    info = {**timing.info, "parts": parts}
    info.pop("part", None)
    return CellResult(cell.key(), cell.to_dict(), STATUS_OK, rows=rows, artifacts={**timing.artifacts,
                      **errors.artifacts}, info=info)


def _row(metric: str, value, frame: int = -1, noise_floor: float = float("nan")) -> dict:
    v = float("nan") if value is None else float(value)
    return {"frame": frame, "metric": metric, "value": v, "unit": UNITS.get(metric, ""), "noise_floor": noise_floor}


def _finite_float(x) -> float:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return float("nan")
    return x


def _measure(cell: Cell, out_dir: Path, progress: bool, part: str = "all") -> CellResult:
    """Measure ``cell`` here. part ``"all"``: everything; ``"errors"``: only the image errors (and
    images); ``"timing"``: only times, memory, peak RSS and the convergence fit (``run_part``)."""
    from tqdm.auto import tqdm

    from methods.base import get_method
    from reports.backend import load_backend

    score, timed = part in ("all", "errors"), part in ("all", "timing")
    be = load_backend(cell.backend)
    for mod in cell.plugins:
        importlib.import_module(mod)
    threads = _set_threads(task_threads(cell), be)
    scene = be.get_scene(cell.scene, cell.size)
    frames = be.make_sequence(scene, cell.kind, cell.n_frames, cell.seed)
    if len(frames) != cell.n_frames:
        raise ValueError(f"sequence has {len(frames)} frames, expected {cell.n_frames}")
    method = get_method(cell.method)(**json.loads(cell.config))

    rows: list[dict] = []
    pre = precompute_cache.precompute(method, scene, cell.config)  # opt-in disk cache (its docstring)
    if timed:
        rows.append(_row("precompute_time", pre["seconds"]))
        if pre["cached"]:
            rows += [_row("precompute_cached", 1), _row("precompute_load_time", pre["load_seconds"])]

    if method.capabilities.max_bounces > 0 and cell.bounces != FULL:
        # one precomputation for every bounce count; the cell renders exactly cell.bounces
        # (`Method.with_bounces`, e.g. Sun 2007 Fig. 11's direct / +1 / +2 columns)
        method = method.with_bounces(cell.bounces)
    scored = set(cell.scored())
    times: list[float] = []
    errors: dict[str, list[tuple[float, float]]] = {}
    exposure = None
    last = None
    bar = tqdm(frames, desc=cell.key()[:48], leave=False, disable=None if progress else True, unit="frame")
    for i, frame in enumerate(bar):
        gb = be.make_gbuffer(scene, frame, cell.spp_side)
        t0 = time.perf_counter()
        img = method.render(frame, gb)
        dt = time.perf_counter() - t0
        times.append(dt)
        if timed:
            rows.append(_row("render_time", dt, frame=i))
        if tuple(img.shape) != (gb.height, gb.width, 3):
            raise ValueError(f"{cell.method}.render returned {tuple(img.shape)}, expected ({gb.height}, {gb.width}, 3)")
        if not score or i not in scored:
            continue
        ref = be.render_reference(scene, frame, bounces=cell.bounces, spp=cell.ref_spp, seed=cell.seed,
                                  spp_side=cell.spp_side)
        mask = torch.as_tensor(ref.coverage, dtype=torch.bool) & gb.coverage.cpu().bool()
        if exposure is None:  # fixed per (scene, sequence): from the first scored reference
            exposure = be.make_exposure(ref.image, mask)
        m = be.all_metrics(img.detach().cpu().float(), torch.as_tensor(ref.image).float(), mask, exposure=exposure)
        floor = _finite_float(ref.noise_floor)
        for k, v in m.items():
            rows.append(_row(k, _finite_float(v), frame=i, noise_floor=floor))
            errors.setdefault(k, []).append((_finite_float(v), floor))
        if cell.score_full_gi and cell.bounces != FULL:  # Sun 2007 Fig. 11: distance to the real image
            full = be.render_reference(scene, frame, bounces=FULL, spp=cell.ref_spp, seed=cell.seed,
                                       spp_side=cell.spp_side)
            fmask = mask & torch.as_tensor(full.coverage, dtype=torch.bool)
            v = _finite_float(be.all_metrics(img.detach().cpu().float(), torch.as_tensor(full.image).float(), fmask,
                                             exposure=exposure)["rmse"])
            ffloor = _finite_float(full.noise_floor)
            rows.append(_row("rmse_full_gi", v, frame=i, noise_floor=ffloor))
            errors.setdefault("rmse_full_gi", []).append((v, ffloor))
        last = (i, frame, gb, img.detach().cpu().float(), ref, mask)

    stats = measure.frame_time_stats(times, warmup=1)
    if timed:
        rows += [_row("render_time_median", stats["median"]), _row("render_time_iqr", stats["iqr"]),
                 _row("timed_frames", stats["n"]),
                 _row("fps", 1.0 / stats["median"] if stats["median"] > 0 else float("inf"))]
    for k, vals in errors.items():
        v = np.array([a for a, _ in vals])
        f = np.array([b for _, b in vals])
        rows.append(_row(k, float(np.mean(v)), noise_floor=float(np.mean(f))))

    info: dict[str, Any] = {"threads": threads, "pid": os.getpid()}
    if timed:
        mem = method.memory()
        rows.append(_row("memory_bytes", sum(int(b) for b in mem.values())))
        bpf = method.bytes_per_frame(cell.kind)
        if bpf is not None:
            rows.append(_row("bytes_per_frame", bpf))
        rows.append(_row("peak_rss_bytes" if cell.isolate else "harness_peak_rss_bytes", measure.peak_rss_bytes()))
        info.update({"memory": {k: int(b) for k, b in mem.items()}, "frame_times": times})
    artifacts: dict[str, str] = {}
    if timed and cell.eq_err_spp and (part == "timing" or ("rmse" in errors and last is not None)):
        i0 = cell.scored()[0]
        fit = calibrate(cell, out_dir, be, scene, frames[i0], fresh=part == "timing")
        if fit is not None:
            info["convergence_fit"] = fit.to_dict()
            if part == "all":
                rows += _eq_error_rows(fit.to_dict(), errors["rmse"][0][0], errors["rmse"][0][1], stats["median"])
    if score and cell.save_images and last is not None:
        artifacts["images"] = _save_images(cell, out_dir, be, scene, *last)
    return CellResult(cell.key(), cell.to_dict(), STATUS_OK, rows=rows, artifacts=artifacts, info=info)


def _fresh_timed_reference(be, scene, frame, **kw):
    """(reference, seconds) rendered here and now, bypassing the reference cache when the backend
    allows it: a cached reference may have been rendered while other work shared the machine."""
    import inspect

    if "use_cache" not in inspect.signature(be.render_reference).parameters:
        return be.timed_reference(scene, frame, **kw)
    t0 = time.perf_counter()
    ref = be.render_reference(scene, frame, use_cache=False, **kw)
    wall = time.perf_counter() - t0
    sec = be.reference_seconds(ref) if hasattr(be, "reference_seconds") else None
    return ref, sec or wall


def calibrate(cell: Cell, out_dir: Path, be, scene, frame, *, fresh: bool = False) -> measure.ConvergenceFit | None:
    """Fit the reference renderer's convergence on ``frame`` (cached per run in
    ``<out>/calib/``, shared by every method of the same scene/sequence/bounces).

    fresh: time renders made now (not the reference cache's recorded times) — the timing part of a
    parallel run, where the cached references were rendered next to other work."""
    spec = {"scene": cell.scene, "size": cell.size, "kind": cell.kind, "seed": cell.seed, "bounces": cell.bounces,
            "spp": list(cell.eq_err_spp), "threads": task_threads(cell), "frame": int(getattr(frame, "index", 0)),
            "backend": cell.backend, "n_frames": cell.n_frames}
    key = hashlib.sha1(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]
    path = out_dir / "calib" / f"{key}.json"
    if path.exists():
        d = json.loads(path.read_text())
        return measure.ConvergenceFit(**d["fit"]) if d.get("fit") else None
    spp, floors, secs = [], [], []
    for s in cell.eq_err_spp:
        kw = dict(bounces=cell.bounces, spp=int(s), seed=cell.seed, spp_side=cell.spp_side)
        ref, sec = _fresh_timed_reference(be, scene, frame, **kw) if fresh else be.timed_reference(scene, frame, **kw)
        if sec is None:
            atomic_write_json(path, {"spec": spec, "fit": None, "why": "renderer reports no time"})
            return None
        spp.append(s), floors.append(float(ref.noise_floor)), secs.append(sec)
    try:
        fit = measure.fit_convergence(spp, floors, secs)
    except ValueError as e:
        atomic_write_json(path, {"spec": spec, "fit": None, "why": str(e)})
        return None
    atomic_write_json(path, {"spec": spec, "fit": fit.to_dict(), "spp": spp, "noise_floor": floors, "seconds": secs})
    return fit


def splat_vertex_error(e_pix: torch.Tensor, gb, F: torch.Tensor, n_vertices: int, mask: torch.Tensor) -> torch.Tensor:
    """Per-vertex error from per-pixel error.

    e_pix: (H, W) per-pixel error (e.g. squared error); mask: (H, W) bool scored pixels;
    F: (M, 3) faces of the frame's geometry; returns (N,) float64.
    Each G-buffer sample carries its pixel's error; it is splatted onto its triangle's three
    vertices with the sample's barycentric weights and normalised by the splatted weight
    (vertices no scored sample sees get NaN).
    """
    H, W, S2 = gb.height, gb.width, gb.spp_side**2
    if tuple(e_pix.shape) != (H, W) or tuple(mask.shape) != (H, W):
        raise ValueError(f"e_pix and mask must be ({H}, {W}), got {tuple(e_pix.shape)}, {tuple(mask.shape)}")
    e_smp = e_pix.reshape(-1).double().cpu().repeat_interleave(S2)  # (P,) pixel-major (y, x, s)
    ok = gb.hit.cpu() & mask.cpu().reshape(-1).repeat_interleave(S2)
    idx, w = gb.vertex_weights(F.cpu())
    w = w.cpu().double() * ok[:, None]
    flat = idx.reshape(-1).cpu()
    num = torch.zeros(n_vertices, dtype=torch.float64).index_add_(0, flat, (w * e_smp[:, None]).reshape(-1))
    den = torch.zeros(n_vertices, dtype=torch.float64).index_add_(0, flat, w.reshape(-1))
    return torch.where(den > 0, num / den.clamp_min(1e-300), torch.full_like(num, float("nan")))


def _save_images(cell: Cell, out_dir: Path, be, scene, i, frame, gb, img, ref, mask) -> str:
    """Reference, method image, mask and the per-vertex squared error (``splat_vertex_error``)
    of the last scored frame → ``<out>/images/<key>.npz``."""
    ref_img = torch.as_tensor(ref.image).float()
    e_pix = ((img - ref_img) ** 2).mean(-1) * mask  # (H, W)
    V, F = be.geometry(scene, frame)
    V = torch.as_tensor(V).float().cpu()
    F = torch.as_tensor(F).long().cpu()
    verr = splat_vertex_error(e_pix, gb, F, len(V), mask)
    rel = Path("images") / f"{cell.key()}.npz"
    arrays = dict(reference=ref_img.numpy().astype(np.float32), method=img.numpy().astype(np.float32),
                  mask=mask.numpy(), frame=np.int64(i), V=V.numpy(), F=F.numpy(), vertex_sq_error=verr.numpy())
    cam = getattr(frame, "camera", None)
    if cam is not None and all(hasattr(cam, a) for a in ("origin", "target", "up", "fov_deg", "width", "height")):
        arrays["camera"] = np.array([*np.asarray(cam.origin, float), *np.asarray(cam.target, float),
                                     *np.asarray(cam.up, float), float(cam.fov_deg), cam.width, cam.height])
    atomic_save(out_dir / rel, lambda tmp: np.savez_compressed(tmp, **arrays))
    return str(rel)


# -- running many cells -----------------------------------------------------------------------


class InlineExecutor:
    """The in-process executor: ``submit`` runs the call at once and returns a finished future."""

    def submit(self, fn, *args, **kwargs) -> Future:
        f: Future = Future()
        try:
            f.set_result(fn(*args, **kwargs))
        except BaseException as e:  # noqa: BLE001 — delivered through the future like a pool would
            f.set_exception(e)
        return f

    def shutdown(self, wait: bool = True) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.shutdown()


def make_executor(name: str = "local", workers: int | None = None, scheduler: str | None = None):
    """An executor by name (``reports.executors.make_executor``): ``local``, ``processes``, ``dask``."""
    from reports.executors import make_executor as _mk

    return _mk(name, workers=workers, scheduler=scheduler)


RETRIES_AFTER_WORKER_LOSS = 1  # a task whose worker died runs once more, alone (see ``run_cells``)


def _lost(cell: Cell, e: BaseException, part: str) -> CellResult:
    what = "" if part == "all" else f"{part} part: "
    return CellResult(cell.key(), cell.to_dict(), STATUS_ERROR, reason=f"{what}worker lost: {type(e).__name__}: {e}",
                      info={"traceback": "".join(traceback.format_exception(e)), "part": part})


def run_cells(cells: Iterable[Cell], out_dir: str | os.PathLike, *, executor=None, max_in_flight: int | None = None,
              progress: bool = True) -> list[CellResult]:
    """Run every cell not finished yet in ``out_dir``; results in the order of ``cells``.

    ``executor``: a ``concurrent.futures.Executor`` (or anything with ``submit(fn, *args, **kw) ->
    future`` whose futures have ``result()`` and ``done()``). At most ``max_in_flight`` tasks are
    submitted at once (default: the executor's ``slots``, else 1).

    An executor from ``reports.executors`` with ``parallel = True`` gets every cell as two tasks
    (``run_part``): the ``errors`` part through ``submit`` and the ``timing`` part through
    ``submit_timing`` (at most ``timing_in_flight`` of them at once, when the executor sets it),
    so timings are taken one at a time per machine while error work runs in parallel.

    Failures: a cell that raises is an ``error`` result (``execute_cell``). A task whose future
    raises (its worker died, the pool broke, the scheduler gave up) is run once more *alone* — so a
    cell that kills its worker cannot take innocent cells down with it — and recorded as an
    ``error`` result if it fails again; the rest of the sweep goes on. Finished cells are on disk
    as soon as they finish, so a re-run redoes only what failed.
    """
    from tqdm.auto import tqdm

    cells = list(cells)
    out_dir = Path(out_dir)
    ex = executor or InlineExecutor()
    split = bool(getattr(ex, "parallel", False))
    context = ex.describe() if hasattr(ex, "describe") else {"executor": type(ex).__name__}
    slots = max(1, max_in_flight or getattr(ex, "slots", 1))
    timing_cap = getattr(ex, "timing_in_flight", None)
    results: dict[int, CellResult] = {}
    parts: dict[int, dict[str, CellResult]] = {}
    queue: list[tuple[int, str]] = []
    for j, c in enumerate(cells):
        r = load_result(out_dir, c)
        if r is not None and r.status != STATUS_ERROR:
            results[j] = r
        elif c.na is not None or not split:
            queue.append((j, "all"))
        else:
            parts[j] = {}
            for p in PARTS:
                old = load_part(out_dir, c, p)
                if old is not None and old.status != STATUS_ERROR:
                    parts[j][p] = old
                else:
                    queue.append((j, p))
            if len(parts[j]) == len(PARTS):  # both parts were done; the merge was not
                results[j] = _finish_merge(cells[j], parts.pop(j), out_dir)
    bar = tqdm(total=len(cells), initial=len(results), desc="run", unit="cell", disable=None if progress else True)
    t_start = time.perf_counter()
    pending: dict[Any, tuple[int, str]] = {}
    attempts: dict[tuple[int, str], int] = {}
    solo: list[tuple[int, str]] = []  # tasks whose worker died: re-run one at a time

    def submit(t: tuple[int, str]) -> None:
        j, p = t
        attempts[t] = attempts.get(t, 0) + 1
        if p == "all":
            f = ex.submit(run_cell, cells[j], str(out_dir), progress=progress, context=context)
        elif p == "timing":
            f = ex.submit_timing(run_part, cells[j], p, str(out_dir), progress=False, context=context)
        else:
            f = ex.submit(run_part, cells[j], p, str(out_dir), progress=False, context=context)
        pending[f] = t

    def finished(t: tuple[int, str], r: CellResult) -> None:
        j, p = t
        if p == "all":
            results[j] = r
        else:
            parts[j][p] = r
            if len(parts[j]) < len(PARTS):
                return
            results[j] = _finish_merge(cells[j], parts.pop(j), out_dir)
        bar.set_postfix_str(f"{cells[j].method}/{cells[j].scene}/{cells[j].kind}: {results[j].status}")
        bar.update(1)
        if progress and bar.disable:  # not a terminal (cron, CI logs): one line per finished cell
            c = cells[j]
            print(f"[prtbench] {len(results)}/{len(cells)} {c.method}/{c.scene}/{c.kind}/b{c.bounces}: {results[j].status} "
                  f"({time.perf_counter() - t_start:.0f} s)", file=sys.stderr, flush=True)

    try:
        while queue or pending or solo:
            if solo:
                if not pending:
                    submit(solo.pop(0))
            else:
                n_timing = sum(1 for t in pending.values() if t[1] == "timing")
                for t in list(queue):
                    if len(pending) >= slots:
                        break
                    if t[1] == "timing" and timing_cap is not None and n_timing >= timing_cap:
                        continue
                    queue.remove(t)
                    if t[1] == "all" and cells[t[0]].na is not None:
                        finished(t, run_cell(cells[t[0]], out_dir))  # n/a: nothing to run
                        continue
                    submit(t)
                    n_timing += t[1] == "timing"
            if not pending:
                continue
            done = [f for f in pending if f.done()]
            if not done:
                if all(isinstance(f, Future) for f in pending):
                    done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
                else:  # foreign futures: poll
                    time.sleep(0.05)
                    continue
            for f in done:
                t = pending.pop(f)
                try:
                    r = f.result()
                except Exception as e:  # the task did not return: its worker died / the pool broke
                    if attempts[t] <= RETRIES_AFTER_WORKER_LOSS:
                        solo.append(t)
                        continue
                    r = _lost(cells[t[0]], e, t[1])
                    atomic_write_json(result_path(out_dir, cells[t[0]]) if t[1] == "all"
                                      else part_path(out_dir, cells[t[0]], t[1]), r.to_dict())
                finished(t, r)
    finally:
        bar.close()
    return [results[j] for j in range(len(cells))]


def _finish_merge(cell: Cell, parts: dict[str, CellResult], out_dir: Path) -> CellResult:
    res = merge_parts(cell, parts["errors"], parts["timing"])
    atomic_write_json(result_path(out_dir, cell), res.to_dict())
    return res
