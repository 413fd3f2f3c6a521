"""Atomic file writes: a temp file in the target's directory, then ``os.replace``.

A killed process never leaves a half-written result, reference or report behind. Used by the
reference cache (``references/cache.py``) and the results store (``reports/store.py``).
"""
from __future__ import annotations

import os
import tempfile
from pathlib import Path


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
