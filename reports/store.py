"""Results store: one long-format parquet table per run, plus a history table every run appends to.

Every file is written atomically (write a temporary file in the same directory, then
``os.replace``), so a killed run never leaves a half-written file behind; files get the permissions
a plain ``open()`` gives (0o666 minus the umask). The history is appended under a file lock
(``<history>.lock``), so runs finishing together cannot drop each other's rows.

Columns of the long table (``COLUMNS``; one row per measured value):
run_id, time (UTC ISO), git_sha, versions (JSON), machine, threads, scene, size, sequence, frame
(−1 = summary over the sequence), method, config (canonical JSON), bounces (−1 = full), metric,
value, unit, noise_floor (RMSE of the reference the value was measured against; NaN if none),
status ("ok" | "na" | "error"), reason (n/a reason or error message), cell (cell key).
"""
from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path
from typing import Iterable

import pandas as pd

from scenes.io import atomic_save, atomic_write_bytes, atomic_write_json, atomic_write_text  # noqa: F401  (re-exported)

COLUMNS = [
    "run_id", "time", "git_sha", "versions", "machine", "threads",
    "scene", "size", "sequence", "frame", "method", "config", "bounces",
    "metric", "value", "unit", "noise_floor", "status", "reason", "cell",
]
_DTYPES = {
    "threads": "int64", "frame": "int64", "bounces": "int64",
    "value": "float64", "noise_floor": "float64",
}
DEFAULT_HISTORY = Path("out") / "history.parquet"


# -- tables -----------------------------------------------------------------------------------


def to_frame(rows: Iterable[dict]) -> pd.DataFrame:
    """Rows (dicts with ``COLUMNS`` keys; missing ones become NA) → a typed long table."""
    return normalize(pd.DataFrame(list(rows)))


def normalize(df: pd.DataFrame) -> pd.DataFrame:
    """A table with (at least) some of ``COLUMNS`` → exactly ``COLUMNS``, typed (missing → NA)."""
    df = df.copy()
    for c in COLUMNS:
        if c not in df.columns:
            df[c] = float("nan") if c in ("value", "noise_floor") else ("" if c not in _DTYPES else -1)
    df = df[COLUMNS].copy()
    for c, t in _DTYPES.items():
        df[c] = pd.to_numeric(df[c], errors="coerce")
        if t == "int64":
            df[c] = df[c].fillna(-1).astype("int64")
        else:
            df[c] = df[c].astype("float64")
    for c in set(COLUMNS) - set(_DTYPES):
        df[c] = df[c].fillna("").astype(str)
    return df


def write_table(df: pd.DataFrame, path: str | os.PathLike) -> Path:
    """Write a long table as parquet, atomically."""
    missing = set(COLUMNS) - set(df.columns)
    if missing:
        raise ValueError(f"results table lacks columns {sorted(missing)}")
    return atomic_save(path, lambda tmp: df.to_parquet(tmp, index=False))


def read_table(path: str | os.PathLike) -> pd.DataFrame:
    """Read a run table: a parquet file or a run directory holding ``results.parquet``."""
    p = Path(path)
    if p.is_dir():
        p = p / "results.parquet"
    if not p.exists():
        raise FileNotFoundError(f"no results table at {p}")
    return pd.read_parquet(p)


HISTORY_LOCK_TIMEOUT = 600.0  # seconds a run waits for another run's history append


def history_lock(history: str | os.PathLike, timeout: float = HISTORY_LOCK_TIMEOUT):
    """The inter-process lock of a history file (``<history>.lock``, a ``filelock.FileLock``)."""
    from filelock import FileLock

    history = Path(history)
    history.parent.mkdir(parents=True, exist_ok=True)
    return FileLock(str(history) + ".lock", timeout=timeout)


def merge_rows(old: pd.DataFrame, new: pd.DataFrame) -> pd.DataFrame:
    """``old`` plus ``new``, where ``new``'s rows replace the rows of the same (run_id, cell) in
    ``old``: re-finishing a resumed run does not duplicate it, and a re-run of the same run with
    fewer methods adds its cells without dropping the others. (The run-level rows have cell "".)"""
    if len(old) == 0:
        return normalize(new)
    if len(new) == 0:
        return normalize(old)
    pair_old = old["run_id"].astype(str) + "\0" + old["cell"].astype(str)
    pair_new = set(new["run_id"].astype(str) + "\0" + new["cell"].astype(str))
    kept = old[~pair_old.isin(pair_new)]
    return normalize(pd.concat([normalize(kept), normalize(new)], ignore_index=True))


def append_history(df: pd.DataFrame, history: str | os.PathLike = DEFAULT_HISTORY, *,
                   timeout: float = HISTORY_LOCK_TIMEOUT) -> Path:
    """Append one run's table to the history parquet: read, merge (``merge_rows``) and atomically
    replace, all under the history's file lock, so concurrent runs cannot lose each other's rows."""
    history = Path(history)
    with history_lock(history, timeout):
        old = pd.read_parquet(history) if history.exists() else to_frame([])
        return write_table(merge_rows(old, df), history)


def read_history(history: str | os.PathLike = DEFAULT_HISTORY) -> pd.DataFrame:
    history = Path(history)
    if not history.exists():
        return to_frame([])
    return pd.read_parquet(history)


# -- run metadata -----------------------------------------------------------------------------


def git_sha(root: str | os.PathLike | None = None) -> str:
    root = Path(root) if root else Path(__file__).resolve().parent.parent
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, timeout=10)
        sha = out.stdout.strip()
        if out.returncode != 0 or not sha:
            return "unknown"
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=root,
                               capture_output=True, text=True, timeout=10).stdout.strip()
        return sha + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


CODE_PACKAGES = ("scenes", "references", "methods", "reports")


def code_fingerprint(root: str | os.PathLike | None = None) -> str:
    """sha256 over the source of every package whose code can change a number (and run_bench.py).

    Unlike ``git_sha`` ("+dirty" says nothing about *what* changed), two checkouts with the same
    fingerprint run the same code; a resumed run uses it to refuse mixing results of different code.
    """
    import hashlib

    root = Path(root) if root else Path(__file__).resolve().parent.parent
    h = hashlib.sha256()
    files = [root / "run_bench.py"] + sorted(p for pkg in CODE_PACKAGES for p in (root / pkg).rglob("*.py"))
    for f in files:
        if f.is_file():
            h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def module_closure(module: str, root: str | os.PathLike | None = None) -> list[Path]:
    """The project source files ``module`` runs: its own file and, transitively, every project
    module it imports (module level or inside functions, read from the AST — the same reading as
    tests/test_layers.py), with the ``__init__.py`` of every package on the way. Sorted paths.

    ``from pkg import name`` counts ``pkg/name.py`` when that file exists (a submodule) and
    ``pkg/__init__.py`` otherwise. Imports outside the project (torch, mitsuba, ...) are not
    followed; their versions are part of the keys that use this (``package_versions``)."""
    import ast

    root = Path(root) if root else Path(__file__).resolve().parent.parent
    tops = set(CODE_PACKAGES)

    def files_of(name: str) -> list[Path]:
        parts = name.split(".")
        if parts[0] not in tops:
            return []
        out = [root.joinpath(*parts[:i], "__init__.py") for i in range(1, len(parts) + 1)]
        out.append(root.joinpath(*parts).with_suffix(".py"))
        return [f for f in out if f.is_file()]

    todo, seen = list(files_of(module)), set()
    if not todo:
        raise ValueError(f"{module!r} is not a module of the project under {root}")
    while todo:
        f = todo.pop()
        if f in seen:
            continue
        seen.add(f)
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"), filename=str(f))):
            names: list[str] = []
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            for n in names:
                todo.extend(x for x in files_of(n) if x not in seen)
    return sorted(seen)


# Packages whose every file is part of `code_closure_fingerprint`: a method receives a
# ``scenes.scene.Scene`` and runs scene code through it (geometry, posing, materials' evaluation)
# without importing the module that defines it.
CLOSURE_ALWAYS = ("scenes",)


def code_closure_fingerprint(module: str, root: str | os.PathLike | None = None) -> str:
    """sha256 over the sources of `module_closure` and of every package in `CLOSURE_ALWAYS`
    (paths and bytes): equal as long as no file ``module`` can run changed — an edit of the report
    code or of another method keeps it."""
    import hashlib

    root = Path(root) if root else Path(__file__).resolve().parent.parent
    files = set(module_closure(module, root))
    for pkg in CLOSURE_ALWAYS:
        files.update(p for p in (root / pkg).rglob("*.py") if p.is_file())
    h = hashlib.sha256()
    for f in sorted(files):
        h.update(str(f.relative_to(root)).encode() + b"\0" + f.read_bytes() + b"\0")
    return h.hexdigest()[:16]


def package_versions() -> dict[str, str]:
    from importlib import metadata

    out = {"python": platform.python_version()}
    for name in ("prtbench", "torch", "mitsuba", "drjit", "numpy", "scipy", "pandas", "embreex"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            pass
    return out


def machine_description() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return f"{platform.node()} | {cpu} | {os.cpu_count()} cpu | {platform.system()} {platform.release()}"
