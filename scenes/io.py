"""The one place generated files are written: the cache root and atomic writes.

* ``cache_dir(*parts)`` — root of generated data (git-ignored): ``$PRTBENCH_CACHE`` or
  ``<project>/.cache``; references, precomputations and studies live under it.
* ``atomic_save(path, writer)`` and the ``atomic_write_{bytes,text,json}`` wrappers — a temp file in
  the target's directory, then ``os.replace``: a killed process never leaves a half-written result,
  reference, cache entry or report behind. Every writer in the project goes through them. The file
  gets the permissions a plain ``open(path, "w")`` gives (0o666 minus the umask; ``tempfile.mkstemp``
  would make it 0o600, so a report written by a nightly job could not be served by a web server
  running as another user).

This module sits in the lowest layer that touches the file system (``scenes``), so references,
methods and reports can all use it without importing upwards.
"""
from __future__ import annotations

import json
import os
import secrets
from pathlib import Path
from typing import Any

PROJECT_ROOT = Path(__file__).resolve().parent.parent


def cache_dir(*parts: str) -> Path:
    """Root of generated data (git-ignored): ``$PRTBENCH_CACHE`` or ``<project>/.cache``; created."""
    root = Path(os.environ.get("PRTBENCH_CACHE", PROJECT_ROOT / ".cache"))
    p = root.joinpath(*parts)
    p.mkdir(parents=True, exist_ok=True)
    return p


_TMP_TRIES = 100


def _create_temp(path: Path) -> str:
    """Create an empty, exclusive temp file next to ``path`` (mode 0o666 & ~umask, as ``open`` does)."""
    for _ in range(_TMP_TRIES):
        tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}.tmp{path.suffix}"
        try:
            fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_CLOEXEC", 0), 0o666)
        except FileExistsError:
            continue
        os.close(fd)
        return str(tmp)
    raise FileExistsError(f"could not create a temporary file next to {path}")


def atomic_save(path: str | os.PathLike, writer) -> Path:
    """Atomically create ``path`` with ``writer(tmp_path)`` (for writers that need a file name).

    The file gets the permissions a plain ``open()`` would give it (0o666 minus the umask)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _create_temp(path)
    try:
        writer(tmp)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except FileNotFoundError:
            pass
        raise
    return path


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically (temp file in the same directory + ``os.replace``)."""

    def write(tmp: str) -> None:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())

    return atomic_save(path, write)


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    return atomic_write_bytes(path, text.encode("utf-8"))


def atomic_write_json(path: str | os.PathLike, obj: Any) -> Path:
    """JSON with sorted keys; numpy/torch scalars, sets, tuples and paths are converted."""
    return atomic_write_text(path, json.dumps(obj, indent=1, sort_keys=True, default=_json_default))


def _json_default(o):
    if hasattr(o, "item"):
        return o.item()
    if isinstance(o, (set, frozenset, tuple)):
        return list(o)
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-serialisable: {type(o).__name__}")
