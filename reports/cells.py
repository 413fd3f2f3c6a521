"""Cells — the unit of work of a benchmark run — and their result files.

A *cell* is (scene, size, sequence kind, method, config, bounces) plus the measuring settings: a
small frozen, picklable dataclass, independent of every other cell. Its result (``CellResult``:
long-format rows, artifacts, run facts) is stored in ``<out>/cells/<key>.json``; a parallel
executor stores the two halves of a cell (``PARTS``) in ``<out>/cells/parts/``.

Where the rest lives: measuring one cell — ``reports.measure_cell`` (``run_cell``, ``run_part``);
running many cells on an executor — ``reports.runner.run_cells``; the executors —
``reports.executors``.
"""
from __future__ import annotations

import hashlib
import json
import os
import sys
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field, fields
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

from scenes.sequences import KINDS

SCENE_FILE_PREFIX = "file:"  # a TOML scene file given as a scene name (``reports.backend.get_scene``)
FULL = -1  # bounces = −1: full global illumination (Mitsuba max_depth = −1)
STATUS_OK, STATUS_NA, STATUS_ERROR = "ok", "na", "error"
# Measured, but the sanity gate (reports.gate) found the image plainly wrong; its numbers are kept.
STATUS_SUSPECT = "suspect"
MEASURED = (STATUS_OK, STATUS_SUSPECT)  # statuses whose rows hold measurements


UNITS = {
    "rmse": "radiance", "rel_mse": "1", "psnr": "dB", "ssim": "1", "flip": "1", "delta_e2000": "dE00",
    "nonfinite_frac": "1", "render_time": "s", "render_time_median": "s", "render_time_iqr": "s",
    "fps": "1/s", "precompute_time": "s", "memory_bytes": "B", "peak_rss_bytes": "B",
    "harness_peak_rss_bytes": "B", "bytes_per_frame": "B", "flops_per_frame": "flop", "roofline_efficiency": "1",
    "eq_error_speedup": "x", "mitsuba_time_eq_error": "s", "timed_frames": "1", "other_cpu_cores": "cores",
    "host_triad_bandwidth": "B/s", "host_matmul_peak": "flop/s",
    "rays_per_frame": "1", "host_ray_rate": "1/s", "roofline_compute_bound": "1", "roofline_traversal_bound": "1",
    "rmse_full_gi": "radiance", "precompute_cached": "1", "precompute_load_time": "s",
    "negative_frac": "1", "mean_ratio": "1", "region_mean_ratio_min": "1", "region_mean_ratio_max": "1",
}


def canonical_config(config: dict | str | None) -> str:
    """A method config as canonical JSON (sorted keys), the form cells and tables store."""
    if config is None:
        config = {}
    if isinstance(config, str):
        config = json.loads(config)
    if isinstance(config, Mapping):
        config = dict(config)
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

    scene: the scene's name — a library name, or a TOML scene file's ``name`` (default its stem); it
    is what results, the report and file names show. scene_file: the TOML file's path for a
    file scene ("" for library scenes; internal: loads the scene, never shown in tables, not part of
    the key). scene_hash: the scene's content hash (``Scene.content_hash``: geometry, materials,
    env map, camera, skeleton) filled by the planner, so an edited scene gets new keys and is
    re-run. size: "test" | "bench".
    kind: sequence kind (``scenes.sequences.KINDS``: V, VB, VBL, P, L, E, VL). method: registry name; config: canonical JSON.
    bounces: 0 = direct lighting, k = k indirect bounces, −1 = full GI.
    n_frames, seed: the sequence. score_frames: frame indices scored against references (empty =
    all). ref_spp: reference samples per pixel. spp_side: G-buffer S (S×S sub-samples).
    eq_err_spp: reference spp ladder for the equal-error speedup (empty = skip).
    fresh_calibration: time that ladder's Mitsuba renders in this run, beside the method's frames,
    instead of taking the render times the reference cache recorded (which may have been rendered
    while other jobs shared the machine: a perf run on 2026-12-03 got Mitsuba 7–20× slower than in
    the run before from cached entries rendered at load 15–20, and so equal-error speedups 10–20×
    too high). Part of the key only when set.
    threads: torch / Dr.Jit threads (None = leave the defaults). isolate: ``False`` run in the
    executor's process, ``True`` in a spawned child of its own (its peak RSS is the cell's),
    ``"method"`` in one spawned process per method configuration (``MethodProcessExecutor``; with
    the local executor).
    na: the n/a reason from the capability matrix (None = in scope); the cell is then not run.
    score_full_gi: also score every scored frame against the full-GI reference (metric
    ``rmse_full_gi``; Sun 2007 Fig. 11: a method that renders k bounces is also judged by how far it
    is from the real image) — set by the suites for methods with ``max_bounces > 0``.
    backend: module providing scenes/references/metrics (see ``reports.backend``).
    plugins: modules imported before the method is looked up (e.g. tests registering a method).
    device: torch device the method renders on ("cpu", "cuda"): after ``precompute`` the method and
    every G-buffer are moved there (``Method.to``, ``GBuffer.to``); metrics are computed on the CPU.
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
    fresh_calibration: bool = False
    threads: int | None = None
    isolate: bool | str = False
    save_images: bool = True
    na: str | None = None
    score_full_gi: bool = False
    backend: str = "reports.backend"
    plugins: tuple[str, ...] = ()
    device: str = "cpu"
    scene_file: str = ""
    scene_hash: str = ""

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"unknown sequence kind {self.kind!r}")
        if self.n_frames < 1:
            raise ValueError("n_frames must be >= 1")
        if self.bounces < FULL:
            raise ValueError("bounces must be >= 0 or -1 (full)")
        if any(not 0 <= f < self.n_frames for f in self.score_frames):
            raise ValueError(f"score_frames {self.score_frames} outside 0..{self.n_frames - 1}")
        canonical_config(self.config)
        if self.isolate not in (False, True, "method"):
            raise ValueError(f"isolate must be False, True or 'method', got {self.isolate!r}")

    def key(self) -> str:
        """Readable, unique, filesystem-safe id (``isolate`` does not change what is measured)."""
        d = asdict(self)
        d.pop("isolate")
        d.pop("scene_file")  # where the file lives is not what is measured; scene_hash is
        if not d["scene_hash"]:
            d.pop("scene_hash")  # keys of cells planned without a hash stay as they were
        if not d["fresh_calibration"]:
            d.pop("fresh_calibration")  # nor do the keys of cells that take the recorded times
        h = hashlib.sha1(json.dumps(d, sort_keys=True, default=list).encode()).hexdigest()[:12]
        scene = "".join(ch if ch.isalnum() or ch in "-_" else "_" for ch in self.scene)[:64]
        return f"{scene}-{self.size}-{self.kind}-{self.method}-b{bounces_label(self.bounces)}-{h}"

    @property
    def scene_ref(self) -> str:
        """What the backend's ``get_scene`` loads: ``"file:<path>"`` for a file scene, else ``scene``."""
        return f"{SCENE_FILE_PREFIX}{self.scene_file}" if self.scene_file else self.scene

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
    """The stored result of ``cell``, or None (not run yet, or its file was corrupt: moved aside
    with one line on stderr, see `read_result_file`, so the cell is re-run)."""
    return read_result_file(result_path(out_dir, cell), cell)


def move_aside(p: Path, why: str) -> Path:
    """Rename a corrupt run file or folder to ``<name>.corrupt-<UTC timestamp>`` and say so on
    stderr in one line naming the file; returns the new path."""
    stamp = datetime.now(timezone.utc).strftime("%Y%m%dT%H%M%S%fZ")
    dest = p.with_name(f"{p.name}.corrupt-{stamp}")
    os.replace(p, dest)
    print(f"[prtbench] {p}: {why}; moved to {dest.name}, it will be recomputed", file=sys.stderr, flush=True)
    return dest


def _result_problem(d: Any, cell: Cell | None) -> str | None:
    """Why ``d`` (parsed JSON) is not a stored ``CellResult`` (of ``cell``), or None."""
    if not isinstance(d, dict):
        return f"not a cell result (a JSON {type(d).__name__})"
    need = {"key": str, "cell": dict, "status": str, "reason": str, "rows": list, "artifacts": dict, "info": dict}
    missing = [k for k in need if k not in d]
    if missing:
        return f"not a cell result (missing {', '.join(missing)})"
    bad = [k for k, t in need.items() if not isinstance(d[k], t)]
    if bad:
        return f"not a cell result (wrong type of {', '.join(bad)})"
    extra = set(d) - set(need)
    if extra:
        return f"not a cell result (unknown key(s) {', '.join(sorted(extra))})"
    if d["status"] not in (STATUS_OK, STATUS_NA, STATUS_ERROR, STATUS_SUSPECT):
        return f"unknown status {d['status']!r}"
    if cell is not None and d["key"] != cell.key():
        return f"holds cell {d['key']!r}, not {cell.key()!r}"
    if not all(isinstance(r, dict) for r in d["rows"]):
        return "rows are not all objects"
    return None


def read_result_file(p: Path, cell: Cell | None = None) -> CellResult | None:
    """A stored ``CellResult`` from ``p``; None if there is none. A corrupt entry — a folder in
    place of the file, unreadable bytes, not UTF-8, not JSON, not a cell result, another cell's
    result — is moved aside (`move_aside`, one line naming the file) and None returned."""
    p = Path(p)
    if not p.exists() and not p.is_symlink():
        return None
    if p.is_dir():
        move_aside(p, "a folder in place of a cell file")
        return None
    try:
        d = json.loads(p.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as e:
        why = f"not UTF-8 text ({e.reason} at byte {e.start})"
    except json.JSONDecodeError as e:
        why = f"not JSON ({e.msg} at line {e.lineno} column {e.colno})"
    except OSError as e:
        why = f"unreadable ({e.strerror or e})"
    else:
        why = _result_problem(d, cell)
        if why is None:
            return CellResult.from_dict(d)
    move_aside(p, why)
    return None


def is_finished(out_dir, cell: Cell) -> bool:
    r = load_result(out_dir, cell)
    return r is not None and r.status != STATUS_ERROR


THREADS_ENV = "PRTBENCH_THREADS"  # a worker's share of its machine's cores (set by reports.executors)


PARTS = ("errors", "timing")  # how a parallel executor splits a cell (see ``run_part``)


def part_path(out_dir: str | os.PathLike, cell: Cell, part: str) -> Path:
    return Path(out_dir) / "cells" / "parts" / f"{cell.key()}.{part}.json"


def load_part(out_dir: str | os.PathLike, cell: Cell, part: str) -> CellResult | None:
    """The stored ``part`` of ``cell``, or None (a corrupt file is moved aside, like `load_result`)."""
    return read_result_file(part_path(out_dir, cell, part), cell)
