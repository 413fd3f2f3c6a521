"""Disk cache of precomputations shared by the cells of one (scene, method, config) — the one
precompute cache of the project (methods keep no caches of their own).

A nightly suite runs one method on one scene in many cells (sequence kinds × bounce counts: 15
cells per scene for PTT); the precomputation is the same in all of them. Methods that opt in
(``Method.cache_precompute = True``) are precomputed once: the harness stores the method's state
(its ``__dict__``) after ``precompute`` and later cells load it.

Honesty of the numbers: a cell that loads a cached precomputation reports the *original*
precompute seconds (recorded when it was computed, with the thread count it ran with) as
``precompute_time`` and says so with ``precompute_cached = 1`` and ``precompute_load_time``; peak
RSS of such a cell is that of loading, not computing (the report's memory column is
``Method.memory()``, unaffected).

Key: sha256 over the scene's content hash, the method name, its canonical config without the keys
only its render reads (``Method.render_config_keys``; `precompute_config`: the perf suite's per-vertex
and per-pixel cells of one method and scene share one entry, loaded with each cell's own values of
those keys), the fingerprint
of the code the method runs — its module and every project module it imports, transitively
(``reports.store.code_closure_fingerprint``) — and the torch version: a change of that code
recomputes, a change elsewhere (the report, another method) keeps the night's precomputations. ``PRTBENCH_NO_PRECOMPUTE_CACHE=1`` turns it off.

Storage that cannot run code (the folder may be shared between machines, so a file in it is
untrusted input): an entry is two files in ``<cache>/precompute/`` (``scenes.io.cache_dir``),

* ``<method>-<key>.json`` (`cache_path`) — the sidecar: sha256 and size of the data file, the
  original precompute seconds and thread count, created / last-used times, method, config, scene;
* ``<method>-<key>.<sha256[:16]>.pt`` — the data file it names: ``torch.save`` of
  ``{"format", "version", "tree", "tensors"}``, the state encoded by `encode_state` into a JSON
  string (``tree``) and a list of plain tensors; read back with ``torch.load(weights_only=True)``,
  which unpickles nothing but tensors and primitive containers. Content-addressed, so a reader
  never pairs a sidecar with the data file of a concurrent write of the same key.

`encode_state` accepts tensors (dense, sparse COO, sparse CSR), numpy arrays (not of object dtype),
python scalars, strings, containers, torch dtypes/devices, and instances of classes defined in the
project's own packages (`ALLOWED_PACKAGES`), stored as their class name plus encoded ``__dict__``
/ slots; the precompute's scene is stored as a reference to the scene passed in, never copied.
`decode_state` resolves such a class name only inside the allowed packages and rebuilds the
instance with ``cls.__new__(cls)`` + its attributes — no constructor, ``__setstate__`` or any
other callable named by the file runs. State that cannot be encoded (a function, a lock, a class
from elsewhere) makes the method uncached, with one warning naming the attribute.

On load the sha256 is checked; a corrupt, truncated, zeroed, mismatching or unreadable entry is
deleted, reported in one warning line and recomputed. Size cap: after each write, entries are
pruned least-recently-used first until the folder holds at most ``PRTBENCH_CACHE_MAX_GB``
(default 20) GB (`prune`); `info`, `prune` and `clear` back ``run_bench.py cache {info,prune,clear}``.
Files are written atomically (temp file + ``os.replace``; sidecars through ``scenes.io``, the data
file by `_save` itself, which names it only once its hash is known), so parallel workers and
killed runs never see half a file.
"""
from __future__ import annotations

import abc
import functools
import hashlib
import importlib
import json
import math
import os
import pickle  # only for its exception type: nothing here unpickles
import re
import tempfile
import time
import typing
import warnings
from pathlib import Path, PurePath
from typing import Any

import numpy as np
import torch

from references.visibility import backend_id

ENV_OFF = "PRTBENCH_NO_PRECOMPUTE_CACHE"
ENV_MAX_GB = "PRTBENCH_CACHE_MAX_GB"
# The perf suite's entries take 4.1 GB and the nightly's more than 5 GB (a 5 GB cap evicted entries
# within one run, so a re-run recomputed them): 20 GB holds both on a machine of this kind.
DEFAULT_MAX_GB = 20.0
VERSION = 2
FORMAT = "prtbench-precompute"
# Packages whose classes an entry may name (module == name or module starts with name + ".").
ALLOWED_PACKAGES = ("methods", "scenes")
# Sidecars larger than this are not ours (a sidecar is a few hundred bytes).
MAX_SIDECAR_BYTES = 1 << 20
# Orphaned files (a data file without its sidecar, an atomic writer's temporary) younger than
# this may belong to a write in progress in another process: prune leaves them alone.
ORPHAN_GRACE_S = 600.0


class NotCacheable(TypeError):
    """The method's state holds something `encode_state` does not store (names the attribute)."""


class CorruptEntry(ValueError):
    """A cache entry failed its checks (hash, size, format, decoding)."""


# -- the state codec -------------------------------------------------------------------------


def _allowed_module(module: str) -> bool:
    return any(module == p or module.startswith(p + ".") for p in ALLOWED_PACKAGES)


def _class_name(cls: type, where: str) -> str:
    module, qual = cls.__module__, cls.__qualname__
    if not _allowed_module(module) or "<locals>" in qual:
        raise NotCacheable(f"{where}: instance of {module}.{qual} (only classes defined at module level in "
                           f"{', '.join(p + '.*' for p in ALLOWED_PACKAGES)} are stored)")
    return f"{module}:{qual}"


def _resolve_class(name: Any) -> type:
    """The class named ``"module:qualname"`` — only inside `ALLOWED_PACKAGES`, only a class defined
    there (not a name imported into such a module)."""
    if not isinstance(name, str) or name.count(":") != 1:
        raise CorruptEntry(f"bad class name {name!r}")
    module, qual = name.split(":")
    if not _allowed_module(module) or not qual or "<" in qual or any(not p.isidentifier() for p in qual.split(".")):
        raise CorruptEntry(f"class {name!r} is outside the allowed packages {ALLOWED_PACKAGES}")
    obj: Any = importlib.import_module(module)
    for part in qual.split("."):
        obj = getattr(obj, part, None)
    if not isinstance(obj, type) or obj.__module__ != module or obj.__qualname__ != qual:
        raise CorruptEntry(f"{name!r} is not a class defined in {module}")
    return obj


_ATOMS = (type(None), bool, int, str)


class _Encoder:
    """State → (JSON-able tree, list of plain tensors). Objects met twice are stored once and
    referenced ({"$": "ref"}), so aliasing and cycles through lists, dicts and objects survive."""

    def __init__(self, scene: Any) -> None:
        self.scene = scene
        self.tensors: list[torch.Tensor] = []
        self.memo: dict[int, int] = {}    # id(obj) → node id
        self.keep: list[Any] = []         # keeps memoised objects alive (ids stay unique)
        self.active: set[int] = set()     # tuples being encoded (a cycle through them is refused)

    def _tensor(self, t: torch.Tensor) -> int:
        self.tensors.append(t)
        return len(self.tensors) - 1

    def _new_id(self, x: Any) -> int:
        self.memo[id(x)] = n = len(self.keep)
        self.keep.append(x)
        return n

    def enc(self, x: Any, where: str) -> Any:
        t = type(x)
        if t in _ATOMS:
            return x
        if t is float:
            return x if math.isfinite(x) else {"$": "float", "v": repr(x)}
        if x is self.scene and x is not None:
            return {"$": "scene"}
        if id(x) in self.memo:
            return {"$": "ref", "id": self.memo[id(x)]}
        if isinstance(x, torch.Tensor):
            return self._enc_tensor(x, where)
        if t is list:
            n = self._new_id(x)
            return {"$": "list", "id": n, "items": [self.enc(v, f"{where}[{i}]") for i, v in enumerate(x)]}
        if t is dict:
            n = self._new_id(x)
            return {"$": "dict", "id": n,
                    "items": [[self.enc(k, f"{where} key"), self.enc(v, f"{where}[{k!r}]")] for k, v in x.items()]}
        if t in (tuple, set, frozenset, torch.Size):
            if id(x) in self.active:
                raise NotCacheable(f"{where}: a cycle through a {t.__name__}")
            self.active.add(id(x))
            items = [self.enc(v, f"{where}[{i}]") for i, v in enumerate(x)]
            self.active.discard(id(x))
            return {"$": t.__name__ if t is not torch.Size else "size", "id": self._new_id(x), "items": items}
        if t is complex:
            return {"$": "complex", "re": self.enc(x.real, where), "im": self.enc(x.imag, where)}
        if t is bytes:
            return {"$": "bytes", "hex": x.hex()}
        if t is torch.dtype:
            return {"$": "dtype", "v": str(x).removeprefix("torch.")}
        if t is torch.device:
            return {"$": "device", "v": str(x)}
        if isinstance(x, PurePath):
            return {"$": "path", "v": str(x)}
        if t is np.ndarray:
            return self._enc_ndarray(x, where)
        if isinstance(x, np.generic):
            if x.dtype.kind not in "biuf":
                raise NotCacheable(f"{where}: numpy scalar of dtype {x.dtype}")
            return {"$": "npscalar", "dtype": x.dtype.str, "v": self.enc(x.item(), where)}
        if t is np.dtype or isinstance(x, np.dtype):
            if x.kind not in "biufc?":
                raise NotCacheable(f"{where}: numpy dtype {x}")
            return {"$": "npdtype", "v": x.str}
        return self._enc_object(x, where)

    def _enc_tensor(self, x: torch.Tensor, where: str) -> dict:
        if type(x) not in (torch.Tensor, torch.nn.Parameter):
            raise NotCacheable(f"{where}: tensor subclass {type(x).__name__}")
        n = self._new_id(x)
        rg = bool(x.requires_grad)
        x = x.detach()
        if x.layout == torch.strided:
            node = {"$": "tensor", "id": n, "i": self._tensor(x)}
        elif x.layout == torch.sparse_coo:
            node = {"$": "sparse_coo", "id": n, "size": list(x.shape), "coalesced": bool(x.is_coalesced()),
                    "indices": self._tensor(x._indices()), "values": self._tensor(x._values())}
        elif x.layout == torch.sparse_csr:
            node = {"$": "sparse_csr", "id": n, "size": list(x.shape), "crow": self._tensor(x.crow_indices()),
                    "col": self._tensor(x.col_indices()), "values": self._tensor(x.values())}
        else:
            raise NotCacheable(f"{where}: tensor layout {x.layout}")
        if rg:
            node["requires_grad"] = True
        return node

    def _enc_ndarray(self, x: np.ndarray, where: str) -> dict:
        if x.dtype.kind not in "biufc" or x.dtype.byteorder not in "=|" + ("<" if np.little_endian else ">"):
            raise NotCacheable(f"{where}: numpy array of dtype {x.dtype}")
        n = self._new_id(x)
        data = torch.from_numpy(np.array(x, copy=True, order="C"))
        return {"$": "ndarray", "id": n, "i": self._tensor(data), "writeable": bool(x.flags.writeable)}

    def _enc_object(self, x: Any, where: str) -> dict:
        """An instance of a plain class of ours: all its state is in ``__dict__``."""
        t = type(x)
        cls = _class_name(t, where)  # functions, classes, locks, modules, ...: not ours, refused
        if not _plain_class(t) or not isinstance(getattr(x, "__dict__", None), dict):
            raise NotCacheable(f"{where}: {cls} is not a plain class (a base from elsewhere, __slots__ or "
                               "__new__: its state is not all in __dict__)")
        n = self._new_id(x)
        state = vars(x)
        if any(type(k) is not str for k in state):
            raise NotCacheable(f"{where}: non-string attribute names")
        return {"$": "obj", "cls": cls, "id": n,
                "state": [[k, self.enc(v, f"{where}.{k}")] for k, v in state.items()]}


class _Decoder:
    def __init__(self, tensors: list, scene: Any) -> None:
        self.tensors = tensors
        self.scene = scene
        self.memo: dict[int, Any] = {}

    def _t(self, i: Any) -> torch.Tensor:
        if type(i) is not int or not 0 <= i < len(self.tensors):
            raise CorruptEntry(f"bad tensor index {i!r}")
        return self.tensors[i]

    def _reg(self, node: dict, x: Any) -> Any:
        n = node.get("id")
        if type(n) is not int or n in self.memo:
            raise CorruptEntry(f"bad node id {n!r}")
        self.memo[n] = x
        return x

    def dec(self, x: Any) -> Any:
        if type(x) in _ATOMS or type(x) is float:
            return x
        if type(x) is not dict or "$" not in x:
            raise CorruptEntry(f"bad node {str(x)[:80]}")
        tag = x["$"]
        if tag == "scene":
            return self.scene
        if tag == "ref":
            if x.get("id") not in self.memo:
                raise CorruptEntry(f"dangling reference {x.get('id')!r}")
            return self.memo[x["id"]]
        if tag == "float":
            if x.get("v") not in ("nan", "inf", "-inf"):
                raise CorruptEntry(f"bad float {x.get('v')!r}")
            return float(x["v"])
        if tag == "list":
            out: list = self._reg(x, [])
            out.extend(self.dec(v) for v in x["items"])
            return out
        if tag == "dict":
            d: dict = self._reg(x, {})
            for k, v in x["items"]:
                d[self.dec(k)] = self.dec(v)
            return d
        if tag in ("tuple", "set", "frozenset", "size"):
            items = [self.dec(v) for v in x["items"]]
            kind = {"tuple": tuple, "set": set, "frozenset": frozenset, "size": torch.Size}[tag]
            return self._reg(x, kind(items))
        if tag == "complex":
            return complex(self.dec(x["re"]), self.dec(x["im"]))
        if tag == "bytes":
            return bytes.fromhex(x["hex"])
        if tag == "dtype":
            dt = getattr(torch, str(x["v"]), None)
            if not isinstance(dt, torch.dtype):
                raise CorruptEntry(f"bad dtype {x['v']!r}")
            return dt
        if tag == "device":
            return torch.device(str(x["v"]))
        if tag == "path":
            return Path(str(x["v"]))
        if tag == "npdtype":
            dt = np.dtype(str(x["v"]))
            if dt.kind not in "biufc?":
                raise CorruptEntry(f"bad numpy dtype {x['v']!r}")
            return dt
        if tag == "npscalar":
            dt = np.dtype(str(x["dtype"]))
            if dt.kind not in "biuf":
                raise CorruptEntry(f"bad numpy scalar dtype {x['dtype']!r}")
            return dt.type(self.dec(x["v"]))
        if tag == "tensor":
            t = self._t(x["i"])
            return self._reg(x, t.requires_grad_() if x.get("requires_grad") else t)
        if tag == "sparse_coo":
            # invariants checked: out-of-range indices in a file must not reach a kernel
            t = torch.sparse_coo_tensor(self._t(x["indices"]), self._t(x["values"]), tuple(x["size"]),
                                        is_coalesced=bool(x["coalesced"]), check_invariants=True)
            return self._reg(x, t.requires_grad_() if x.get("requires_grad") else t)
        if tag == "sparse_csr":
            with warnings.catch_warnings():  # torch flags sparse CSR "beta" once a process: once a cell in a run's log
                warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
                t = torch.sparse_csr_tensor(self._t(x["crow"]), self._t(x["col"]), self._t(x["values"]),
                                            tuple(x["size"]), check_invariants=True)
            return self._reg(x, t.requires_grad_() if x.get("requires_grad") else t)
        if tag == "ndarray":
            a = self._t(x["i"]).numpy()
            if not x.get("writeable", True):
                a.flags.writeable = False
            return self._reg(x, a)
        if tag == "obj":
            cls = _resolve_class(x["cls"])
            if not _plain_class(cls):
                raise CorruptEntry(f"{x['cls']!r} is not a plain class")
            obj = self._reg(x, cls.__new__(cls))  # object.__new__: no constructor runs
            for k, v in x["state"]:
                if type(k) is not str:
                    raise CorruptEntry("bad attribute name")
                obj.__dict__[k] = self.dec(v)  # not setattr: frozen dataclasses, no __setattr__ hooks
            return obj
        raise CorruptEntry(f"unknown node tag {tag!r}")


# Bases that add no instance state (a class of ours may derive from them).
_STATELESS_BASES = (object, abc.ABC, typing.Generic)


@functools.lru_cache(maxsize=None)
def _plain_class(cls: type) -> bool:
    """Every base is ours or stateless, none has __slots__ (beyond __dict__/__weakref__) or
    __new__: ``object.__new__(cls)`` + ``__dict__`` rebuilds an instance completely."""
    for c in cls.__mro__:
        if c in _STATELESS_BASES:
            continue
        if not _allowed_module(c.__module__):
            return False
        if "__new__" in c.__dict__ or set(c.__dict__.get("__slots__", ())) - {"__dict__", "__weakref__"}:
            return False
    return cls.__new__ is object.__new__


def encode_state(state: dict[str, Any], scene: Any = None) -> tuple[str, list[torch.Tensor]]:
    """A method's ``__dict__`` → (JSON tree, plain tensors); ``scene`` is stored as a reference.
    Raises NotCacheable naming the first attribute that cannot be stored."""
    e = _Encoder(scene)
    try:
        tree = e.enc(dict(state), "state")
    except RecursionError:
        raise NotCacheable("state nested too deeply") from None
    return json.dumps(tree, separators=(",", ":")), e.tensors


def decode_state(tree: str, tensors: list[torch.Tensor], scene: Any = None) -> dict[str, Any]:
    """Inverse of `encode_state` (``scene`` is put where the precompute's scene was)."""
    try:
        out = _Decoder(list(tensors), scene).dec(json.loads(tree))
    except CorruptEntry:
        raise
    except Exception as e:  # whatever a damaged tree makes the decoder trip over
        raise CorruptEntry(f"cannot decode the state: {e!r}") from e
    if type(out) is not dict or any(type(k) is not str for k in out):
        raise CorruptEntry("the state is not a dict of attributes")
    return out


# -- the cache -------------------------------------------------------------------------------


def enabled(method: Any) -> bool:
    return bool(getattr(type(method), "cache_precompute", False)) and os.environ.get(ENV_OFF, "") in ("", "0")


@functools.lru_cache(maxsize=None)
def _process_fingerprint(module: str) -> str:
    """The fingerprint of the code ``module`` runs (`reports.store.code_closure_fingerprint`), once
    per process and module: the code a process runs is what it imported, so an edit of the working
    tree during a run must not split one run's cells over two keys. A method defined outside the
    project's packages (a plugin, a test double) gets the whole tree's `code_fingerprint`, as before."""
    from reports.store import CODE_PACKAGES, code_closure_fingerprint, code_fingerprint

    if module.split(".")[0] not in CODE_PACKAGES:
        return code_fingerprint()
    return code_closure_fingerprint(module)


def precompute_config(method: Any, config: str) -> str:
    """``config`` (canonical JSON) without the method's ``render_config_keys``: what its precomputation
    depends on. Cells that differ only in those keys (e.g. in-out's ``shading``) share an entry."""
    drop = tuple(getattr(type(method), "render_config_keys", ()) or ())
    if not drop:
        return config
    cfg = json.loads(config) if config else {}
    return json.dumps({k: v for k, v in cfg.items() if k not in drop}, sort_keys=True, separators=(",", ":"))


def _keep_render_config(method: Any, live: dict) -> None:
    """After a load: the method renders with its own ``render_config_keys`` values (``live``, its config
    before the load), not those of the instance that computed the entry."""
    drop = tuple(getattr(type(method), "render_config_keys", ()) or ())
    cfg = getattr(method, "_config", None)
    if drop and isinstance(cfg, dict):
        method._config = {**{k: v for k, v in cfg.items() if k not in drop},
                          **{k: live[k] for k in drop if k in live}}


def cache_key(scene: Any, method: Any, config: str) -> str:
    h = hashlib.sha256()
    for part in (str(VERSION), scene.content_hash(), type(method).name, precompute_config(method, config),
                 _process_fingerprint(type(method).__module__),
                 torch.__version__, backend_id()):  # the ray tracer that made the visibility
        h.update(part.encode() + b"\0")
    return h.hexdigest()[:24]


def cache_folder() -> Path:
    from scenes.io import cache_dir

    return cache_dir("precompute")


def cache_path(scene: Any, method: Any, config: str) -> Path:
    """The entry's sidecar ``<method>-<key>.json``; it names the data file
    ``<method>-<key>.<sha256[:16]>.pt`` (content-addressed, so a reader never pairs a sidecar with
    the data file of another write)."""
    return cache_folder() / f"{type(method).name}-{cache_key(scene, method, config)}.json"


def max_bytes() -> int:
    """The size cap in bytes from ``PRTBENCH_CACHE_MAX_GB`` (default `DEFAULT_MAX_GB`)."""
    raw = os.environ.get(ENV_MAX_GB, "").strip()
    try:
        gb = float(raw) if raw else DEFAULT_MAX_GB
    except ValueError:
        gb = float("nan")
    if not (gb >= 0 and math.isfinite(gb)):
        raise ValueError(f"{ENV_MAX_GB} must be a number of GB >= 0, got {raw!r}")
    return int(gb * 1e9)


def _sha256(f) -> str:
    h = hashlib.sha256()
    for chunk in iter(lambda: f.read(1 << 20), b""):
        h.update(chunk)
    return h.hexdigest()


def _read_sidecar(side: Path) -> tuple[dict, Path]:
    """The sidecar's metadata and the path of the data file it names (checked: a file of this
    entry in this folder — a planted sidecar cannot point elsewhere)."""
    if side.stat().st_size > MAX_SIDECAR_BYTES:
        raise CorruptEntry("sidecar too large")
    try:
        meta = json.loads(side.read_bytes())
    except (ValueError, RecursionError) as e:
        raise CorruptEntry(f"sidecar is not JSON ({e})") from e
    if type(meta) is not dict or meta.get("format") != FORMAT or meta.get("version") != VERSION:
        raise CorruptEntry("sidecar of another format or version")
    sha, size, name = meta.get("sha256"), meta.get("bytes"), meta.get("data")
    if type(sha) is not str or type(size) is not int or name != f"{side.stem}.{sha[:16]}.pt" \
            or not re.fullmatch(r"[0-9a-f]{64}", sha):
        raise CorruptEntry("sidecar lacks a valid sha256/bytes/data file name")
    return meta, side.with_name(name)


def _write_sidecar(side: Path, meta: dict) -> None:
    from scenes.io import atomic_write_bytes

    atomic_write_bytes(side, json.dumps(meta, indent=1, sort_keys=True).encode())


def _unlink(*paths: Path) -> int:
    """Delete files (gone already, or not deletable — e.g. a folder in a file's place: skipped);
    returns the bytes freed."""
    freed = 0
    for p in paths:
        try:
            size = p.stat().st_size
            p.unlink()
            freed += size
        except OSError:
            pass
    return freed


def _load(side: Path, method: Any, scene: Any) -> dict:
    """The entry's sidecar (its last-used time refreshed) after putting its state into ``method``.
    Raises FileNotFoundError (no entry, or pruned meanwhile) or CorruptEntry."""
    meta, data = _read_sidecar(side)
    with open(data, "rb") as f:
        size = os.fstat(f.fileno()).st_size
        if size != meta["bytes"]:
            raise CorruptEntry(f"data file has {size} B, the sidecar says {meta['bytes']} B (truncated or replaced?)")
        if _sha256(f) != meta["sha256"]:
            raise CorruptEntry("sha256 mismatch (corrupt or replaced data file)")
        f.seek(0)
        try:
            blob = torch.load(f, weights_only=True)
        except pickle.UnpicklingError as e:  # e.g. a planted __reduce__ payload
            raise CorruptEntry("refused by the weights-only unpickler (it holds pickled objects, not just "
                               "tensors)") from e
        except Exception as e:  # a damaged archive
            msg = (str(e).strip().splitlines() or [""])[0][:160]
            raise CorruptEntry(f"not a tensor archive ({type(e).__name__}: {msg})") from e
    if type(blob) is not dict or blob.get("format") != FORMAT or blob.get("version") != VERSION \
            or type(blob.get("tree")) is not str or type(blob.get("tensors")) is not list \
            or any(type(t) is not torch.Tensor or t.layout != torch.strided for t in blob["tensors"]):
        raise CorruptEntry("data file of another format or version, or not plain tensors")
    if meta.get("class") != type(method).__qualname__:
        raise CorruptEntry(f"entry of class {meta.get('class')!r}")
    state = decode_state(blob["tree"], blob["tensors"], scene)
    method.__dict__.update(state)
    meta["last_used"] = time.time()
    try:
        _write_sidecar(side, meta)
    except OSError:  # a read-only shared cache still serves hits
        pass
    return meta


def _save(side: Path, method: Any, scene: Any, config: str, seconds: float, threads: int) -> None:
    """Store ``method``'s state (raises NotCacheable before writing anything), then prune."""
    tree, tensors = encode_state(method.__dict__, scene)
    blob = {"format": FORMAT, "version": VERSION, "tree": tree, "tensors": tensors}
    fd, tmp = tempfile.mkstemp(prefix=f".{side.stem}.", suffix=".tmp", dir=side.parent)
    try:
        with os.fdopen(fd, "w+b") as f:
            torch.save(blob, f)
            f.flush()
            os.fsync(f.fileno())
            f.seek(0)
            sha, size = _sha256(f), os.fstat(f.fileno()).st_size
        data = side.with_name(f"{side.stem}.{sha[:16]}.pt")
        os.replace(tmp, data)
    except BaseException:
        _unlink(Path(tmp))
        raise
    try:
        old = _read_sidecar(side)[1]
    except (OSError, CorruptEntry):
        old = None
    now = time.time()
    _write_sidecar(side, {
        "format": FORMAT, "version": VERSION, "method": type(method).name, "class": type(method).__qualname__,
        "config": config, "scene": getattr(scene, "name", None), "scene_hash": scene.content_hash(),
        "seconds": seconds, "threads": threads, "torch": torch.__version__, "created": now, "last_used": now,
        "bytes": size, "sha256": sha, "data": data.name})
    if old is not None and old != data:  # the data file of the entry this write replaced
        _unlink(old)
    prune()


_WARNED: set[str] = set()


def precompute(method: Any, scene: Any, config: str) -> dict[str, Any]:
    """``method.precompute(scene)``, or its cached result. Returns {"seconds": original precompute
    seconds, "threads": the torch thread count it ran with, "cached": bool, "load_seconds": seconds
    spent loading (0 when computed)}."""
    if enabled(method):
        side = cache_path(scene, method, config)
        t0 = time.perf_counter()
        live = dict(getattr(method, "_config", None) or {})
        try:
            meta = _load(side, method, scene)
            _keep_render_config(method, live)
            return {"seconds": float(meta["seconds"]), "threads": meta.get("threads"), "cached": True,
                    "load_seconds": time.perf_counter() - t0}
        except FileNotFoundError:
            pass
        except (CorruptEntry, OSError) as e:
            _discard(side)
            warnings.warn(f"ignoring precompute cache {side.name}: {e}; deleted, recomputing", stacklevel=2)
    threads = torch.get_num_threads()
    t0 = time.perf_counter()
    method.precompute(scene)
    seconds = time.perf_counter() - t0
    out = {"seconds": seconds, "threads": threads, "cached": False, "load_seconds": 0.0}
    if enabled(method):
        try:
            _save(side, method, scene, precompute_config(method, config), seconds, threads)
        except NotCacheable as e:
            if type(method).name not in _WARNED:
                _WARNED.add(type(method).name)
                warnings.warn(f"{type(method).name}: precompute not cached, its state is not storable ({e})",
                              stacklevel=2)
        except OSError as e:  # a full or read-only disk: run uncached
            warnings.warn(f"precompute cache: cannot write {side.name}: {e}", stacklevel=2)
    return out


def _discard(side: Path) -> None:
    """Delete an entry: its sidecar and every data file of its stem."""
    _unlink(side, *side.parent.glob(f"{side.stem}.*.pt"))


# -- maintenance: info / prune / clear --------------------------------------------------------


def _scan(folder: Path) -> tuple[list[dict], list[Path]]:
    """Readable entries (sidecar metadata + "paths" + "size") and the other files (data files no
    sidecar names, pickles of older versions, writers' temporaries, unreadable sidecars)."""
    files = {p.name: p for p in folder.iterdir() if p.is_file()} if folder.is_dir() else {}
    entries, claimed = [], set()
    for name, side in files.items():
        if not name.endswith(".json") or name.startswith("."):
            continue
        try:
            meta, data = _read_sidecar(side)
            size = data.stat().st_size + side.stat().st_size
        except (CorruptEntry, OSError):
            continue
        meta["paths"], meta["size"] = [side, data], size
        entries.append(meta)
        claimed.update({name, data.name})
    return entries, [p for n, p in files.items() if n not in claimed]


def _size(p: Path) -> int:
    try:
        return p.stat().st_size
    except FileNotFoundError:
        return 0


def info() -> dict[str, Any]:
    """What the cache holds: folder, cap, bytes, entries (least recently used first), per-method
    totals, and the other files (not entries) with their bytes."""
    folder = cache_folder()
    entries, other = _scan(folder)
    entries.sort(key=lambda m: m.get("last_used", 0))
    per: dict[str, dict[str, int]] = {}
    for m in entries:
        d = per.setdefault(str(m.get("method")), {"entries": 0, "bytes": 0})
        d["entries"] += 1
        d["bytes"] += m["size"]
    other_bytes = sum(_size(p) for p in other)
    return {"folder": str(folder), "max_bytes": max_bytes(), "entries": len(entries),
            "bytes": sum(m["size"] for m in entries) + other_bytes, "other_files": len(other),
            "other_bytes": other_bytes, "per_method": per,
            "list": [{k: m.get(k) for k in ("method", "scene", "config", "seconds", "threads", "created",
                                             "last_used", "size")} | {"file": m["paths"][0].name} for m in entries]}


def prune(limit: int | None = None) -> dict[str, int]:
    """Delete least-recently-used entries until the folder holds at most ``limit`` bytes (default
    `max_bytes`), after deleting the files that are not entries (pickles of older versions; other
    files once older than `ORPHAN_GRACE_S`, so a write in progress keeps its files).
    Returns {"removed": entries removed, "files": other files removed, "freed": bytes freed,
    "bytes": bytes left}."""
    limit = max_bytes() if limit is None else int(limit)
    if limit < 0:
        raise ValueError(f"limit must be >= 0 bytes, got {limit}")
    entries, other = _scan(cache_folder())
    now, freed, files, total = time.time(), 0, 0, 0
    for p in other:
        try:
            st = p.stat()
        except FileNotFoundError:
            continue
        if p.suffix == ".pkl" or now - st.st_mtime > ORPHAN_GRACE_S:
            freed += _unlink(p)
            files += 1
        else:
            total += st.st_size
    total += sum(m["size"] for m in entries)
    removed = 0
    for m in sorted(entries, key=lambda m: m.get("last_used", 0)):
        if total <= limit:
            break
        total -= m["size"]
        freed += _unlink(*m["paths"])
        removed += 1
    return {"removed": removed, "files": files, "freed": freed, "bytes": total}


def clear() -> dict[str, int]:
    """Delete every file in the cache folder. Returns {"files": files removed, "freed": bytes}."""
    files = [p for p in cache_folder().iterdir() if p.is_file()]
    return {"files": len(files), "freed": _unlink(*files)}
