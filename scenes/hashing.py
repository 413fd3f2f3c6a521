"""Stable content hashes (sha256 hex), identical across processes and machines of one endianness.

* tensors/arrays: dtype, shape and the C-contiguous little-endian bytes;
* parameters: canonical JSON (sorted keys, no spaces, floats as `repr` — shortest round-trip —
  tuples as lists); tensors/arrays inside parameters are replaced by their `hash_tensor`;
* frames: env map (data + rotation), camera, per-region material parameters and pose. The frame's
  `index` and `changed` are bookkeeping, not content, and are excluded.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
from typing import Any

import numpy as np
import torch


def _to_numpy(t) -> np.ndarray:
    if isinstance(t, torch.Tensor):
        t = t.detach().cpu()
        if t.dtype == torch.bfloat16:
            t = t.float()
        return t.contiguous().numpy()
    return np.asarray(t)


def hash_tensor(t) -> str:
    """sha256 of a tensor/array: dtype, shape and bytes (C order, little-endian)."""
    a = np.ascontiguousarray(_to_numpy(t))
    if a.dtype.byteorder == ">":
        a = a.astype(a.dtype.newbyteorder("<"))
    h = hashlib.sha256()
    h.update(f"{a.dtype.str}|{a.shape}|".encode())
    h.update(a.tobytes())
    return h.hexdigest()


def canonical(obj: Any) -> Any:
    """A JSON-able canonical form (floats repr'd as strings, tensors by hash)."""
    if obj is None or isinstance(obj, (bool, str)):
        return obj
    if isinstance(obj, (int, np.integer)) and not isinstance(obj, bool):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        f = float(obj)
        if math.isnan(f):
            return "f:nan"
        return "f:" + repr(f + 0.0)  # + 0.0 folds -0.0 onto 0.0
    if isinstance(obj, (torch.Tensor, np.ndarray)):
        return {"__tensor__": hash_tensor(obj)}
    if isinstance(obj, dict):
        return {str(k): canonical(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [canonical(v) for v in obj]
    if isinstance(obj, (set, frozenset)):
        return sorted(canonical(v) for v in obj)
    if hasattr(obj, "params") and callable(obj.params):
        return {"__type__": type(obj).__name__, "params": canonical(obj.params())}
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {"__type__": type(obj).__name__,
                **{f.name: canonical(getattr(obj, f.name)) for f in dataclasses.fields(obj)}}
    raise TypeError(f"cannot hash object of type {type(obj).__name__}")


def hash_params(obj: Any) -> str:
    """sha256 of the canonical JSON of `obj` (dicts, lists, numbers, tensors, objects with params())."""
    s = json.dumps(canonical(obj), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(s.encode()).hexdigest()


def hash_envmap(env) -> str:
    """Env map content: texel data and the `to_world` rotation (and any `params()` it offers)."""
    if env is None:
        return hash_params(None)
    parts = {"data": hash_tensor(env.data), "to_world": hash_tensor(torch.as_tensor(np.asarray(_to_numpy(env.to_world), np.float64)))}
    return hash_params(parts)


def hash_materials(materials: dict) -> str:
    return hash_params({str(k): (m.params() if hasattr(m, "params") else m) for k, m in materials.items()})


def hash_frame(frame) -> str:
    """Content hash of a `methods.base.Frame` (env map, camera, materials, pose)."""
    cam = frame.camera
    pose = frame.pose
    parts = {
        "envmap": hash_envmap(frame.envmap),
        "camera": cam.params() if hasattr(cam, "params") else canonical(cam),
        "materials": hash_materials(frame.materials),
        "pose": None if pose is None else hash_tensor(torch.as_tensor(pose).to(torch.float64)),
    }
    return hash_params(parts)
