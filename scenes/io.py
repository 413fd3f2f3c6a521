"""The one place generated files are written: the cache root and atomic writes.

* ``cache_dir(*parts)`` — root of generated data (git-ignored): ``$PRTBENCH_CACHE`` or
  ``<project>/.cache``; references, precomputations and studies live under it.
* ``atomic_save(path, writer)`` and the ``atomic_write_{bytes,text,json}`` wrappers — a temp file in
  the target's directory, then ``os.replace``: a killed process never leaves a half-written result,
  reference, cache entry or report behind. Every writer in the project goes through them.

This module sits in the lowest layer that touches the file system (``scenes``), so references,
methods and reports can all use it without importing upwards.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any

PROJECT_ROOT = Path(__file__).resolve().parent.parent


def cache_dir(*parts: str) -> Path:
    """Root of generated data (git-ignored): ``$PRTBENCH_CACHE`` or ``<project>/.cache``; created."""
    root = Path(os.environ.get("PRTBENCH_CACHE", PROJECT_ROOT / ".cache"))
    p = root.joinpath(*parts)
    p.mkdir(parents=True, exist_ok=True)
    return p


def atomic_save(path: str | os.PathLike, writer) -> Path:
    """Atomically create ``path`` with ``writer(tmp_path)`` (for writers that need a file name)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp" + path.suffix, dir=path.parent)
    os.close(fd)
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
