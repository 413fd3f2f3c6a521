"""Measuring one cell: precompute, render its sequence, score it against the references.

``run_cell(cell, out_dir) -> CellResult`` measures a cell (or returns its stored result) and
writes ``<out>/cells/<key>.json`` atomically; a cell that failed is measured again. A parallel
executor runs each cell as two tasks (``run_part``): image errors (in parallel) and timings (one at
a time per machine), joined by ``merge_parts`` into the same result.

Measuring (DESIGN.md "Measuring"): precompute time; per-frame render time (``perf_counter``, first
frame = warm-up excluded from median/IQR, rendered inside ``methods.core.fused.warming``; all frames
stored; Python's garbage collector paused while a frame renders, `gc_paused`); ``Method.memory()``; peak RSS of the
cell's process (``ru_maxrss``) — the cell's own when ``isolate=True`` runs it in a spawned child
(with ``isolate="method"``, the process of its method configuration's cells);
``bytes_per_frame``; error metrics against the reference of the cell's bounce count on the
``score_frames``; the equal-error speedup (``reports.measure.fit_convergence``).
"""
from __future__ import annotations

import contextlib
import gc
import hashlib
import importlib
import inspect
import json
import multiprocessing as mp
import os
import socket
import time
import traceback
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm.auto import tqdm

from methods.core.fused import warming
from methods.registry import get_method
from reports import gate, measure, precompute_cache
from reports.backend import load_backend
from reports.cells import (FULL, MEASURED, PARTS, STATUS_ERROR, STATUS_NA, STATUS_OK, STATUS_SUSPECT, THREADS_ENV,
                           UNITS, Cell, CellResult, load_part, load_result, part_path, result_path)
from scenes.io import atomic_save, atomic_write_json


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
    elif cell.isolate is True:
        try:
            res = _run_isolated(cell, out_dir, progress)
        except Exception as e:  # the child died (BrokenProcessPool, OOM kill, …)
            res = CellResult(cell.key(), cell.to_dict(), STATUS_ERROR, reason=f"child process failed: {e!r}",
                             info={"traceback": traceback.format_exc()})
    else:
        res = execute_cell(cell, out_dir, progress=progress)
        if cell.isolate == "method":
            res.info["isolate"] = _method_isolation()
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


def _method_isolation() -> str:
    """What ``isolate="method"`` did for a cell run in this process (``info["isolate"]``)."""
    from reports.executors import METHOD_PROCESS_ENV

    if os.environ.get(METHOD_PROCESS_ENV) == "1":
        return "method: this method configuration's process"
    return "method: not applied (this executor runs cells in its own processes)"


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


def where() -> dict[str, Any]:
    """Where this code runs: host, pid and (inside a Dask worker) the worker's address."""
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
    if cell.isolate is True and part == "timing":
        try:
            res = _run_isolated(cell, out_dir, progress, part=part)
        except Exception as e:
            res = CellResult(cell.key(), cell.to_dict(), STATUS_ERROR, reason=f"child process failed: {e!r}",
                             info={"traceback": traceback.format_exc()})
    else:
        res = execute_cell(replace(cell, isolate=False), out_dir, progress=progress, part=part)
        res.cell = cell.to_dict()
        if cell.isolate == "method":
            res.info["isolate"] = _method_isolation()
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
    bad = [(p, r) for p, r in (("errors", errors), ("timing", timing)) if r.status not in MEASURED]
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
    return CellResult(cell.key(), cell.to_dict(), errors.status, reason=errors.reason, rows=rows,
                      artifacts={**timing.artifacts, **errors.artifacts}, info=info)  # the gate judges the errors part


WARM_ENV = "PRTBENCH_WARM"


def warm_up_compiles() -> bool:
    """Whether the untimed warm-up frame runs inside ``warming`` (``PRTBENCH_WARM``, default ``1``).
    Warming compiles the block sizes later frames may meet, on dummy blocks, so that no timed frame
    compiles; it changes no value (``tests/reports/test_executors.py`` checks bit identity between a
    warmed and an unwarmed run). The test session turns it off (``tests/conftest.py``): tests time
    nothing, and it cost ~20 % of a small cell's CPU time (in-out 26.9 vs 22.0 s, PTT 28.0 vs 22.4 s)."""
    v = os.environ.get(WARM_ENV, "1").strip()
    if v not in ("0", "1"):
        raise ValueError(f"{WARM_ENV} must be 0 or 1, got {v!r}")
    return v == "1"


def forget_warm_up_calls() -> None:
    """Before a cell's warm-up frame: forget which warm-up calls earlier cells of this process made
    (``methods.core.fused.warm_blocks`` makes each once per process), so that this cell makes its
    own. `warm_blocks`' key is a call's signature as far as it can be read — an argument that is
    neither a tensor nor hashable counts by its type — and misses shapes a kernel specialises on
    inside such arguments. Measured (session 22, perf suite, in one process as the suite runs): the
    triple product's creature L cell after the chess cells found its warm-up calls "made" already
    and compiled 6 Inductor graphs in its first timed frame (1.8-2.3 s against 70 ms; the cell
    alone compiled nothing there). Done here, not in `methods.core.fused`, whose source is part of
    every precomputation's cache key."""
    from methods.core import fused

    fused._warmed.clear()


CELL_LIMITS_ENV = "PRTBENCH_CELL_LIMITS"


def cell_limits() -> bool:
    """Whether each timed cell measures the machine's limits once more right after its timed frames
    (``PRTBENCH_CELL_LIMITS``, default ``1``): rows ``host_triad_bandwidth`` / ``host_matmul_peak``.

    Why: on this VM the triad read 22.4 and 40.5 GB/s at the start and end of one perf run (session
    23), so two measurements per run leave the roof — the best of them — to chance, and nothing said
    what the machine could do while a given cell was timed. One measurement per cell (~0.2 s: three
    64 MiB arrays and a 1024² sgemm) makes the run's roof the best of ~75–200 (`pipeline.collect`)
    and shows each cell's host next to its frame times. The test session turns it off
    (``tests/conftest.py``; tests time nothing); ``tests/reports/test_machine_limits.py`` runs it."""
    v = os.environ.get(CELL_LIMITS_ENV, "1").strip()
    if v not in ("0", "1"):
        raise ValueError(f"{CELL_LIMITS_ENV} must be 0 or 1, got {v!r}")
    return v == "1"


def _ray_rate(scene, frame, gb) -> tuple[float, str]:
    """``measure.ray_rate`` on ``frame``'s geometry (posed, for an articulated scene) from the hit
    points of its G-buffer ``gb``: the roof of ``FrameCost.rays`` for this cell (~0.2–0.5 s)."""
    g = scene.geometry(getattr(frame, "pose", None))
    hit = gb.hit.cpu()
    if not bool(hit.any()):  # nothing in view: no points to trace from, no roof (the rays bound nothing)
        return float("nan"), "no hit points"
    return measure.ray_rate(g.V.cpu(), g.F.cpu(), gb.position.cpu()[hit], gb.normal.cpu()[hit])


def _row(metric: str, value, frame: int = -1, noise_floor: float = float("nan")) -> dict:
    v = float("nan") if value is None else float(value)
    return {"frame": frame, "metric": metric, "value": v, "unit": UNITS.get(metric, ""), "noise_floor": noise_floor}


def _finite_float(x) -> float:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return float("nan")
    return x


def _loadavg() -> float | None:
    """The machine's 1-minute load average (None where the OS has none)."""
    try:
        return float(os.getloadavg()[0])
    except (OSError, AttributeError):
        return None


@contextlib.contextmanager
def gc_paused():
    """Python's cyclic garbage collector off while a frame renders, back on after (timeit's convention,
    session 40). A collection's pause scales with every object the PROCESS holds (the harness's scenes,
    Mitsuba, pandas: ~417 k objects in a bench cell's process, a full collection 207 ms; pt40), not with
    the frame's work, and a young-generation one fires whenever allocations cross a threshold — inside
    whichever frame that happens to be. The frames' own garbage is reference-counted tensors and is freed
    at once either way; what a frame leaves in cycles is collected after it, outside the timed region."""
    was = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if was:
            gc.enable()


def _measure(cell: Cell, out_dir: Path, progress: bool, part: str = "all") -> CellResult:
    """Measure ``cell`` here. part ``"all"``: everything; ``"errors"``: only the image errors (and
    images); ``"timing"``: only times, memory, peak RSS and the convergence fit (``run_part``)."""
    score, timed = part in ("all", "errors"), part in ("all", "timing")
    be = load_backend(cell.backend)
    for mod in cell.plugins:
        importlib.import_module(mod)
    threads = _set_threads(task_threads(cell), be)
    scene = be.get_scene(cell.scene_ref, cell.size)
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
    if cell.device != "cpu":
        method = method.to(cell.device)
    scored = set(cell.scored())
    times: list[float] = []
    cpu_times: list[float] = []  # process CPU per frame, beside the wall times: tells a transient
    load = [_loadavg()]          # (other work on the machine) from a cause inside the process
    errors: dict[str, list[tuple[float, float]]] = {}
    exposure = None
    last = None
    strip: list[tuple] = []
    warm = warm_up_compiles()
    if warm:
        forget_warm_up_calls()
    bar = tqdm(frames, desc=cell.key()[:48], leave=False, disable=None if progress else True, unit="frame")
    contention = None  # CPU the rest of the machine used while the timed frames ran (measure.other_cpu_cores)
    gb = img = None
    for i, frame in enumerate(bar):
        if i == min(1, len(frames) - 1):
            contention = measure.cpu_snapshot()
        # the previous frame's G-buffer and image stay referenced here until this frame's timer stops
        # (`held`), so they are freed after it: a method that keeps a reference to its last G-buffer
        # (frame state, `frame_cost`'s statistics) drops it inside its next render, and freeing those
        # harness-made tensors took 4-6 ms (munmap) in 5 of 90 of SH PRT's 1.3 ms steady E frames, 0 of 90
        # held (session 42, a stage timer in the suite's loop: the time sat in the reference drop) — the
        # harness's memory, not the method's work; only the perf suite's unscored frames showed it (a
        # scored frame's G-buffer and image stay in ``last`` until the next scoring anyway)
        held = (gb, img)
        gb = be.make_gbuffer(scene, frame, cell.spp_side)
        if cell.device != "cpu":
            gb = gb.to(cell.device)
        t0, c0 = time.perf_counter(), time.process_time()
        with warming(warm and i == 0), gc_paused():  # the untimed warm-up frame also compiles the block sizes later frames meet
            img = method.render(frame, gb)
        if img.device.type == "cuda":
            torch.cuda.synchronize(img.device)  # the frame is done when its image is
        dt = time.perf_counter() - t0
        del held
        times.append(dt)
        cpu_times.append(time.process_time() - c0)
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
        ref_img = torch.as_tensor(ref.image).float()
        m = be.all_metrics(img.detach().cpu().float(), ref_img, mask, exposure=exposure)
        regions = gate.pixel_regions(gb.region.cpu(), gb.height, gb.width) if getattr(gb, "region", None) is not None else None
        m.update(gate.frame_sanity(img.detach().cpu().float(), ref_img, mask, regions))  # the sanity gate
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
        last = (i, frame, gb.to("cpu"), img.detach().cpu().float(), ref, mask)
        if cell.kind == "E":  # every probe's image, for the report's strip (reports.html.probe_strip)
            strip.append((i, last[3], ref_img, mask))

    other = measure.other_cpu_cores(contention, measure.cpu_snapshot())
    stats = measure.frame_time_stats(times, warmup=1)
    if timed:
        rows += [_row("render_time_median", stats["median"]), _row("render_time_iqr", stats["iqr"]),
                 _row("timed_frames", stats["n"]), _row("other_cpu_cores", other),
                 _row("fps", 1.0 / stats["median"] if stats["median"] > 0 else float("inf"))]
        if cell_limits():  # after the snapshot above: its own CPU is not "other" work anyway
            host = measure.machine_limits()
            rows += [_row("host_triad_bandwidth", host["triad_bandwidth"]),
                     _row("host_matmul_peak", host["matmul_peak"])]
    for k, vals in errors.items():
        v = np.array([a for a, _ in vals])
        f = np.array([b for _, b in vals])
        agg = np.min if k == "region_mean_ratio_min" else np.max if k in ("region_mean_ratio_max", "negative_frac") else np.mean
        rows.append(_row(k, float(agg(v)), noise_floor=float(np.mean(f))))

    info: dict[str, Any] = {"threads": threads, "pid": os.getpid()}
    if timed:
        # the method's code key (its import closure, as the precompute cache keys it): two runs'
        # cells of one method compare as "unchanged code" when it is equal (benchmarks.perf_speedup)
        info["code"] = precompute_cache._process_fingerprint(type(method).__module__)
        mem = method.memory()
        rows.append(_row("memory_bytes", sum(int(b) for b in mem.values())))
        cost = method.frame_cost(cell.kind, gb.num_samples, pixels=gb.height * gb.width)  # the roofline numerators
        bpf = cost.bytes if cost is not None else method.bytes_per_frame(cell.kind)
        if bpf is not None:
            rows.append(_row("bytes_per_frame", bpf))
        if cost is not None:
            rows.append(_row("flops_per_frame", cost.flops))
        if cost is not None and cost.rays:  # shadow rays the frame must trace: their roof (`FrameCost.rays`)
            rows.append(_row("rays_per_frame", cost.rays))
            if cell_limits():  # the ray rate of this scene, from the last frame's G-buffer points
                rate, tracer = _ray_rate(scene, frame, gb)
                rows.append(_row("host_ray_rate", rate))
                info["ray_rate_tracer"] = tracer
        rows.append(_row("peak_rss_bytes" if cell.isolate is True else "harness_peak_rss_bytes", measure.peak_rss_bytes()))
        load.append(_loadavg())
        info.update({"memory": {k: int(b) for k, b in mem.items()}, "frame_times": times,
                     "frame_cpu_times": cpu_times, "loadavg_1min": load})
        # terms per material region, for methods that choose them per region (in-out's K)
        for region, st in (getattr(method, "stats", {}) or {}).get("regions", {}).items():
            if isinstance(st, dict) and isinstance(st.get("K"), (int, float)):
                rows.append(_row(f"terms[{region}]", st["K"]))
    artifacts: dict[str, str] = {}
    if timed and cell.eq_err_spp and (part == "timing" or ("rmse" in errors and last is not None)):
        i0 = cell.scored()[0]
        fit = calibrate(cell, out_dir, be, scene, frames[i0], fresh=part == "timing" or cell.fresh_calibration)
        if fit is not None:
            info["convergence_fit"] = fit.to_dict()
            if part == "all":
                rows += _eq_error_rows(fit.to_dict(), errors["rmse"][0][0], errors["rmse"][0][1], stats["median"])
    if score and cell.save_images and last is not None:
        artifacts["images"] = _save_images(cell, out_dir, be, scene, *last)
        if strip:
            rel = Path("images") / f"{cell.key()}.frames.npz"
            arrays = {f"{name}_{i}": a.numpy() for i, img, ref_img, mask in strip
                      for name, a in (("method", img), ("reference", ref_img), ("mask", mask))}
            atomic_save(out_dir / rel, lambda tmp: np.savez_compressed(tmp, frames=np.array([i for i, *_ in strip]), **arrays))
            artifacts["frames"] = str(rel)
    suspect = gate.verdict(rows) if score else None
    return CellResult(cell.key(), cell.to_dict(), STATUS_SUSPECT if suspect else STATUS_OK, reason=suspect or "",
                      rows=rows, artifacts=artifacts, info=info)


def _fresh_timed_reference(be, scene, frame, **kw):
    """(reference, seconds) rendered here and now, bypassing the reference cache when the backend
    allows it: a cached reference may have been rendered while other work shared the machine."""
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
    spec = {"scene": cell.scene, "scene_hash": cell.scene_hash, "size": cell.size, "kind": cell.kind, "seed": cell.seed,
            "bounces": cell.bounces,
            "spp": list(cell.eq_err_spp), "threads": task_threads(cell), "frame": int(getattr(frame, "index", 0)),
            "backend": cell.backend, "n_frames": cell.n_frames}
    key = hashlib.sha1(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]
    path = out_dir / "calib" / f"{key}.json"
    if path.exists():
        d = json.loads(path.read_text())
        return measure.ConvergenceFit(**d["fit"]) if d.get("fit") else None
    spp, floors, secs, excluded = [], [], [], []
    for s in cell.eq_err_spp:
        kw = dict(bounces=cell.bounces, spp=int(s), seed=cell.seed, spp_side=cell.spp_side)
        ref, sec = _fresh_timed_reference(be, scene, frame, **kw) if fresh else be.timed_reference(scene, frame, **kw)
        if sec is None:
            atomic_write_json(path, {"spec": spec, "fit": None, "why": "renderer reports no time"})
            return None
        spp.append(s), floors.append(float(ref.noise_floor)), secs.append(sec)
        meta = getattr(ref, "meta", None) or {}   # what the renderer's time leaves out (`reference_seconds`)
        excluded.append({k: meta[k] for k in ("load_seconds", "compile_seconds") if k in meta})
    try:
        fit = measure.fit_convergence(spp, floors, secs)
    except ValueError as e:
        atomic_write_json(path, {"spec": spec, "fit": None, "why": str(e)})
        return None
    atomic_write_json(path, {"spec": spec, "fit": fit.to_dict(), "spp": spp, "noise_floor": floors, "seconds": secs,
                             "excluded": excluded})
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
