"""Content-hash cache of reference renders under ``cache_dir("references")``.

An entry is two files named by its key: ``<key>.npz`` (the arrays) and ``<key>.json`` (the sidecar:
the key fields, the meta data, each array's shape/dtype and the sha256 of the ``.npz`` bytes).
The key is the sha256 of the canonical JSON of the key fields (``reference_fields``): scene content
hash, frame key, max_depth, spp, seed, sub-pixel side S of the coverage, Mitsuba version and variant,
``CACHE_VERSION`` and a hash of the source files that define what Mitsuba renders (the export and the
plugins — editing them must never leave stale references in use).

Writes are atomic: each file goes to a temporary file in the same directory and is moved into place
with ``os.replace``; the ``.npz`` first, the sidecar last (the sidecar is the commit record). On
load, an entry whose sidecar is unreadable or disagrees with the key fields, whose ``.npz`` is
missing, has other bytes than the sidecar's hash, or does not hold the recorded arrays, is reported
stale (a warning), deleted, and treated as a miss, so the caller re-renders — never reuses it.
``PRTBENCH_CACHE`` relocates the cache root (see ``scenes.io.cache_dir``).
"""
from __future__ import annotations

import hashlib
import io
import json

import warnings
from pathlib import Path

import numpy as np

from scenes.io import atomic_write_bytes, cache_dir

# Bump when the meaning of a cached reference changes in a way the key does not see.
CACHE_VERSION = 1
# Source files whose content defines the rendered image (hashed into the key).
_SOURCES = ("references/export.py", "references/plugins.py", "scenes/materials.py", "scenes/envmap.py")
_ROOT = Path(__file__).resolve().parent.parent


def source_hash() -> str:
    """sha256 over the sources that define what a reference render computes (missing files count)."""
    h = hashlib.sha256()
    for rel in _SOURCES:
        p = _ROOT / rel
        h.update(rel.encode() + b"\0")
        h.update(p.read_bytes() if p.is_file() else b"<missing>")
        h.update(b"\0")
    return h.hexdigest()


def reference_fields(scene, frame, *, max_depth: int, spp: int, seed: int, spp_side: int) -> dict:
    """The key fields of a reference render (JSON-able)."""
    import mitsuba as mi

    from references.mitsuba_setup import ensure_variant

    variant = ensure_variant()
    return {
        "scene": scene.content_hash(),
        "frame": frame.key(),
        "max_depth": int(max_depth),
        "spp": int(spp),
        "seed": int(seed),
        "spp_side": int(spp_side),
        "mitsuba": mi.__version__,
        "variant": variant,
        "cache_version": CACHE_VERSION,
        "sources": source_hash(),
    }


def key_of(fields: dict) -> str:
    """sha256 hex of the canonical JSON of ``fields``."""
    return hashlib.sha256(json.dumps(fields, sort_keys=True, separators=(",", ":")).encode()).hexdigest()


def root() -> Path:
    return cache_dir("references")


def paths(key: str) -> tuple[Path, Path]:
    d = root()
    return d / f"{key}.npz", d / f"{key}.json"


def store(key: str, fields: dict, arrays: dict[str, np.ndarray], meta: dict) -> Path:
    """Write an entry atomically (``.npz`` then the sidecar). Returns the ``.npz`` path."""
    npz, side = paths(key)
    buf = io.BytesIO()
    arrays = {k: np.ascontiguousarray(v) for k, v in arrays.items()}
    np.savez(buf, **arrays)
    data = buf.getvalue()
    atomic_write_bytes(npz, data)
    sidecar = {
        "key": key,
        "fields": fields,
        "meta": meta,
        "arrays": {k: {"shape": list(v.shape), "dtype": v.dtype.str} for k, v in arrays.items()},
        "npz_sha256": hashlib.sha256(data).hexdigest(),
    }
    atomic_write_bytes(side, json.dumps(sidecar, sort_keys=True, indent=1, default=str).encode())
    return npz


def _discard(key: str, why: str) -> None:
    warnings.warn(f"reference cache entry {key[:12]}… is stale or corrupt ({why}); re-rendering", RuntimeWarning)
    for p in paths(key):
        try:
            p.unlink()
        except OSError:
            pass


def load(key: str, fields: dict) -> tuple[dict[str, np.ndarray], dict] | None:
    """(arrays, meta) of a valid entry, or None (a miss; stale/corrupt entries are deleted)."""
    npz, side = paths(key)
    if not side.exists():
        return None
    try:
        sidecar = json.loads(side.read_text())
    except (OSError, ValueError) as e:
        _discard(key, f"unreadable sidecar: {e}")
        return None
    if not isinstance(sidecar, dict) or sidecar.get("key") != key or sidecar.get("fields") != fields:
        _discard(key, "sidecar does not match the key fields")
        return None
    try:
        data = npz.read_bytes()
    except OSError as e:
        _discard(key, f"missing/unreadable .npz: {e}")
        return None
    if hashlib.sha256(data).hexdigest() != sidecar.get("npz_sha256"):
        _discard(key, ".npz bytes differ from the sidecar's hash")
        return None
    try:
        with np.load(io.BytesIO(data), allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception as e:  # zipfile/np errors of many kinds on a damaged file
        _discard(key, f"unreadable .npz: {type(e).__name__}: {e}")
        return None
    spec = sidecar.get("arrays", {})
    if set(spec) != set(arrays) or any(list(arrays[k].shape) != spec[k]["shape"] or arrays[k].dtype.str != spec[k]["dtype"]
                                       for k in spec):
        _discard(key, "arrays differ from the sidecar")
        return None
    return arrays, dict(sidecar.get("meta", {}))
