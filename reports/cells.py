"""Cells — the unit of work of a benchmark run — and the loop that runs them.

A *cell* is (scene, size, sequence kind, method, config, bounces) plus the measuring settings:
a small frozen, picklable dataclass, independent of every other cell, executed by
``run_cell(cell, out_dir) -> CellResult``. ``run_cells`` drives any ``concurrent.futures``-like
executor (``submit(fn, *args) -> future``; ``future.result()``): in-process now, a process pool
or a Dask ``Client`` later (their futures have the same two methods).

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
import time
import traceback
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Iterable

import numpy as np
import torch

from reports import measure
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


def run_cell(cell: Cell, out_dir: str | os.PathLike, *, progress: bool = True) -> CellResult:
    """Run ``cell`` (or return its stored result) and store the result atomically."""
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
    atomic_write_json(result_path(out_dir, cell), res.to_dict())
    return res


def _run_isolated(cell: Cell, out_dir: Path, progress: bool) -> CellResult:
    """Run the cell in a fresh spawned process, so its ``ru_maxrss`` is the cell's alone."""
    ctx = mp.get_context("spawn")
    with ProcessPoolExecutor(max_workers=1, mp_context=ctx) as ex:
        return ex.submit(execute_cell, cell, out_dir, progress=progress).result()


def _set_threads(n: int | None, backend) -> int:
    if n is not None:
        if n < 1:
            raise ValueError("threads must be >= 1")
        torch.set_num_threads(n)
        if hasattr(backend, "set_threads"):
            backend.set_threads(n)
    return torch.get_num_threads()


def execute_cell(cell: Cell, out_dir: str | os.PathLike, *, progress: bool = True) -> CellResult:
    """Measure ``cell`` in this process (no result file; ``run_cell`` writes it). Never raises:
    a failure becomes an ``error`` result carrying the traceback."""
    try:
        return _measure(cell, Path(out_dir), progress)
    except Exception as e:
        return CellResult(cell.key(), cell.to_dict(), STATUS_ERROR, reason=f"{type(e).__name__}: {e}",
                          info={"traceback": traceback.format_exc()})


def _row(metric: str, value, frame: int = -1, noise_floor: float = float("nan")) -> dict:
    v = float("nan") if value is None else float(value)
    return {"frame": frame, "metric": metric, "value": v, "unit": UNITS.get(metric, ""), "noise_floor": noise_floor}


def _finite_float(x) -> float:
    try:
        x = float(x)
    except (TypeError, ValueError):
        return float("nan")
    return x


def _measure(cell: Cell, out_dir: Path, progress: bool) -> CellResult:
    from tqdm.auto import tqdm

    from methods.base import get_method
    from reports.backend import load_backend

    be = load_backend(cell.backend)
    for mod in cell.plugins:
        importlib.import_module(mod)
    threads = _set_threads(cell.threads, be)
    scene = be.get_scene(cell.scene, cell.size)
    frames = be.make_sequence(scene, cell.kind, cell.n_frames, cell.seed)
    if len(frames) != cell.n_frames:
        raise ValueError(f"sequence has {len(frames)} frames, expected {cell.n_frames}")
    method = get_method(cell.method)(**json.loads(cell.config))

    rows: list[dict] = []
    t0 = time.perf_counter()
    method.precompute(scene)
    rows.append(_row("precompute_time", time.perf_counter() - t0))

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
        rows.append(_row("render_time", dt, frame=i))
        if tuple(img.shape) != (gb.height, gb.width, 3):
            raise ValueError(f"{cell.method}.render returned {tuple(img.shape)}, expected ({gb.height}, {gb.width}, 3)")
        if i not in scored:
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
        last = (i, frame, gb, img.detach().cpu().float(), ref, mask)

    stats = measure.frame_time_stats(times, warmup=1)
    rows += [_row("render_time_median", stats["median"]), _row("render_time_iqr", stats["iqr"]),
             _row("timed_frames", stats["n"]),
             _row("fps", 1.0 / stats["median"] if stats["median"] > 0 else float("inf"))]
    for k, vals in errors.items():
        v = np.array([a for a, _ in vals])
        f = np.array([b for _, b in vals])
        rows.append(_row(k, float(np.mean(v)), noise_floor=float(np.mean(f))))

    mem = method.memory()
    rows.append(_row("memory_bytes", sum(int(b) for b in mem.values())))
    bpf = method.bytes_per_frame(cell.kind)
    if bpf is not None:
        rows.append(_row("bytes_per_frame", bpf))
    rows.append(_row("peak_rss_bytes" if cell.isolate else "harness_peak_rss_bytes", measure.peak_rss_bytes()))

    info: dict[str, Any] = {"threads": threads, "memory": {k: int(b) for k, b in mem.items()},
                            "frame_times": times, "pid": os.getpid()}
    artifacts: dict[str, str] = {}
    if cell.eq_err_spp and "rmse" in errors and last is not None:
        i0 = cell.scored()[0]
        fit = calibrate(cell, out_dir, be, scene, frames[i0])
        if fit is not None:
            rmse0 = errors["rmse"][0][0]
            sp = measure.equal_error_speedup(fit, rmse0, stats["median"])
            rows.append(_row("eq_error_speedup", sp, noise_floor=errors["rmse"][0][1]))
            if sp is not None:
                rows.append(_row("mitsuba_time_eq_error", fit.time_for_rmse(rmse0)))
            info["convergence_fit"] = fit.to_dict()
    if cell.save_images and last is not None:
        artifacts["images"] = _save_images(cell, out_dir, be, scene, *last)
    return CellResult(cell.key(), cell.to_dict(), STATUS_OK, rows=rows, artifacts=artifacts, info=info)


def calibrate(cell: Cell, out_dir: Path, be, scene, frame) -> measure.ConvergenceFit | None:
    """Fit the reference renderer's convergence on ``frame`` (cached per run in
    ``<out>/calib/``, shared by every method of the same scene/sequence/bounces)."""
    spec = {"scene": cell.scene, "size": cell.size, "kind": cell.kind, "seed": cell.seed, "bounces": cell.bounces,
            "spp": list(cell.eq_err_spp), "threads": cell.threads, "frame": int(getattr(frame, "index", 0)),
            "backend": cell.backend, "n_frames": cell.n_frames}
    key = hashlib.sha1(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:16]
    path = out_dir / "calib" / f"{key}.json"
    if path.exists():
        d = json.loads(path.read_text())
        return measure.ConvergenceFit(**d["fit"]) if d.get("fit") else None
    spp, floors, secs = [], [], []
    for s in cell.eq_err_spp:
        ref, sec = be.timed_reference(scene, frame, bounces=cell.bounces, spp=int(s), seed=cell.seed,
                                      spp_side=cell.spp_side)
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


def make_executor(name: str = "local", workers: int = 1):
    """``local`` → in-process. (A process pool or Dask client can be passed to ``run_cells``.)"""
    if name == "local":
        return InlineExecutor()
    raise ValueError(f"unknown executor {name!r} (available: local)")


def run_cells(cells: Iterable[Cell], out_dir: str | os.PathLike, *, executor=None, max_in_flight: int = 1,
              progress: bool = True) -> list[CellResult]:
    """Run every cell not finished yet in ``out_dir``; results in the order of ``cells``.

    ``executor``: anything with ``submit(fn, *args, **kw) -> future`` whose futures have
    ``result()`` (and ``done()``); at most ``max_in_flight`` cells are submitted at once.
    """
    from tqdm.auto import tqdm

    cells = list(cells)
    out_dir = Path(out_dir)
    ex = executor or InlineExecutor()
    results: dict[int, CellResult] = {}
    todo = []
    for j, c in enumerate(cells):
        r = load_result(out_dir, c)
        if r is not None and r.status != STATUS_ERROR:
            results[j] = r
        else:
            todo.append(j)
    bar = tqdm(total=len(cells), initial=len(results), desc="run", unit="cell", disable=None if progress else True)
    pending: dict[Any, int] = {}
    queue = list(todo)
    try:
        while queue or pending:
            while queue and len(pending) < max(1, max_in_flight):
                j = queue.pop(0)
                pending[ex.submit(run_cell, cells[j], str(out_dir), progress=progress)] = j
            done = [f for f in pending if f.done()]
            if not done:
                if all(isinstance(f, Future) for f in pending):
                    done, _ = wait(list(pending), return_when=FIRST_COMPLETED)
                else:  # foreign futures (e.g. Dask): poll
                    time.sleep(0.05)
                    continue
            for f in done:
                j = pending.pop(f)
                results[j] = f.result()
                bar.set_postfix_str(f"{cells[j].method}/{cells[j].scene}/{cells[j].kind}: {results[j].status}")
                bar.update(1)
    finally:
        bar.close()
    return [results[j] for j in range(len(cells))]
