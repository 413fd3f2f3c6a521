"""Disk cache of precomputations shared by the cells of one (scene, method, config).

A nightly suite runs one method on one scene in many cells (sequence kinds × bounce counts: 15
cells per scene for PTT); the precomputation is the same in all of them. Methods that opt in
(``Method.cache_precompute = True``) are precomputed once: the harness pickles the method's state
after ``precompute`` and later cells load it.

Honesty of the numbers: a cell that loads a cached precomputation reports the *original*
precompute seconds (recorded when it was computed, with the thread count it ran with) as
``precompute_time`` and says so with ``precompute_cached = 1`` and ``precompute_load_time``; peak
RSS of such a cell is that of loading, not computing (the report's memory column is
``Method.memory()``, unaffected).

Key: sha256 over the scene's content hash, the method name, its canonical config, the code
fingerprint of every package that can change a number (``reports.store.code_fingerprint``) and the
torch version — any code change recomputes. ``PRTBENCH_NO_PRECOMPUTE_CACHE=1`` turns it off.
A method with a cache of its own sets ``cached_precompute_seconds`` (the original seconds) after a
``precompute`` that loaded from it (None otherwise); it is reported the same way.
Files live in ``<cache>/precompute/`` (``methods.base.cache_dir``) and are written atomically, so
parallel workers and killed runs never see half a file.
"""
from __future__ import annotations

import functools
import hashlib
import os
import pickle
import time
import warnings
from pathlib import Path
from typing import Any

import torch

ENV_OFF = "PRTBENCH_NO_PRECOMPUTE_CACHE"
VERSION = 1


def enabled(method: Any) -> bool:
    return bool(getattr(type(method), "cache_precompute", False)) and os.environ.get(ENV_OFF, "") in ("", "0")


@functools.lru_cache(maxsize=1)
def _process_fingerprint() -> str:
    """The code fingerprint once per process: the code a process runs is what it imported, so an
    edit of the working tree during a run must not split one run's cells over two keys."""
    from reports.store import code_fingerprint

    return code_fingerprint()


def cache_key(scene: Any, method: Any, config: str) -> str:
    h = hashlib.sha256()
    for part in (str(VERSION), scene.content_hash(), type(method).name, config, _process_fingerprint(),
                 torch.__version__):
        h.update(part.encode() + b"\0")
    return h.hexdigest()[:24]


def cache_path(scene: Any, method: Any, config: str) -> Path:
    from methods.base import cache_dir

    return cache_dir("precompute") / f"{type(method).name}-{cache_key(scene, method, config)}.pkl"


def precompute(method: Any, scene: Any, config: str) -> dict[str, Any]:
    """``method.precompute(scene)``, or its cached result. Returns {"seconds": original precompute
    seconds, "cached": bool, "load_seconds": seconds spent loading (0 when computed)}."""
    if not enabled(method):
        t0 = time.perf_counter()
        method.precompute(scene)
        dt = time.perf_counter() - t0
        own = getattr(method, "cached_precompute_seconds", None)  # a method's own cache (e.g. zh_shadow)
        if own is not None:
            return {"seconds": float(own), "cached": True, "load_seconds": dt}
        return {"seconds": dt, "cached": False, "load_seconds": 0.0}
    path = cache_path(scene, method, config)
    if path.exists():
        t0 = time.perf_counter()
        try:
            with open(path, "rb") as f:
                blob = pickle.load(f)
            if blob.get("version") != VERSION or blob.get("class") != type(method).__qualname__:
                raise ValueError("stale cache entry")
            method.__dict__.update(blob["state"])
            return {"seconds": float(blob["seconds"]), "cached": True, "load_seconds": time.perf_counter() - t0}
        except Exception as e:  # corrupt/stale entry: recompute and overwrite
            warnings.warn(f"ignoring precompute cache {path.name}: {e!r}", stacklevel=2)
    t0 = time.perf_counter()
    method.precompute(scene)
    seconds = time.perf_counter() - t0
    try:
        data = pickle.dumps({"version": VERSION, "class": type(method).__qualname__, "seconds": seconds,
                             "state": method.__dict__}, protocol=pickle.HIGHEST_PROTOCOL)
    except Exception as e:  # an unpicklable attribute: run uncached, say so once
        warnings.warn(f"{type(method).name}: precompute not cacheable ({e!r})", stacklevel=2)
        return {"seconds": seconds, "cached": False, "load_seconds": 0.0}
    from scenes.io import atomic_write_bytes

    atomic_write_bytes(path, data)
    return {"seconds": seconds, "cached": False, "load_seconds": 0.0}
