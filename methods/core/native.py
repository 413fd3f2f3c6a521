"""Small C loops compiled on first use and called through ctypes (issue 14): the one place the suite
builds and loads native code.

A kernel that Inductor cannot express well (a reduction over data-dependent extents, a gather-bound
pass where the compiled graph's guards and wrapper cost more than its loop) is written as a short C
source in its module and loaded with `load`. Every such kernel has a torch path beside it that is
its fallback and its test oracle: `load` returns None when there is no C compiler (``$CC``, ``cc``
or ``gcc``), when ``PRTBENCH_COMPILE=0`` (``methods.core.fused``'s off switch) or when the build
fails (with one warning), and the caller then runs the torch path.

A library is compiled once per source text, compiler and flags into a per-user cache directory in
the temp folder (atomic rename, so concurrent processes are safe) and loaded only from a directory
this user owns and nobody else can write: a file planted there by another user is never loaded (as
Inductor's own per-user cache). Built at the x86-64 baseline by default (`FLAGS`); a library may add
ISA flags for the host that runs it (``extra_flags``, part of its cache key).
"""
from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import shutil
import stat
import subprocess
import sys
import tempfile
import warnings

from methods.core.fused import compile_enabled

__all__ = ["FLAGS", "cache_clear", "compiler", "cpu_capability", "isa_flags", "load"]

FLAGS = ("-O3", "-shared", "-fPIC", "-fno-math-errno")


@functools.lru_cache(maxsize=None)
def cpu_capability() -> str:
    """The CPU capability torch found ("DEFAULT", "AVX2", "AVX512", ...; "unknown" on a torch without
    the query). A library built for the host (``-march=native``) puts it in a define, so that its
    cache key differs between hosts that share a temp folder."""
    import torch

    try:
        return str(torch.backends.cpu.get_cpu_capability())
    except Exception:  # pragma: no cover - older torch
        return "unknown"


def isa_flags() -> tuple[str, ...]:
    """``-mavx2 -mfma`` when torch found the CPU to have AVX2 (or AVX-512), else none: the ISA flags
    of a library built on the machine that runs it (part of its cache key through `load`'s flags).
    Whether products may be fused into multiply-adds is each library's own ``-ffp-contract``."""
    return ("-mavx2", "-mfma") if cpu_capability() in ("AVX2", "AVX512") else ()


def _private_dir(root: str) -> bool:
    """Whether ``root`` is a real directory owned by this user that nobody else can write: the loaded
    library comes from there, so a file planted by another user must not be."""
    st = os.lstat(root)
    uid = os.getuid() if hasattr(os, "getuid") else st.st_uid
    return stat.S_ISDIR(st.st_mode) and st.st_uid == uid and not (st.st_mode & 0o022)


@functools.lru_cache(maxsize=None)
def compiler() -> str | None:
    """The C compiler's path (looked up once per process: a PATH search costs ~0.25 ms)."""
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    return shutil.which(cc) if cc else None


@functools.lru_cache(maxsize=None)
def _build(name: str, source: str, cc: str, signatures: tuple, flags: tuple) -> ctypes.CDLL | None:
    key = hashlib.sha256("\0".join((source, cc, *flags, sys.platform)).encode()).hexdigest()[:20]
    root = os.path.join(tempfile.gettempdir(), f"prtbench-native-{os.getuid() if hasattr(os, 'getuid') else 0}")
    path = os.path.join(root, f"{name}_{key}.so")
    try:
        os.makedirs(root, mode=0o700, exist_ok=True)
        if not _private_dir(root):
            raise OSError(f"{root} is not a directory only this user can write; not loading code from it")
        if not os.path.exists(path):
            with tempfile.TemporaryDirectory(dir=root) as tmp:
                src, so = os.path.join(tmp, f"{name}.c"), os.path.join(tmp, f"{name}.so")
                with open(src, "w") as f:
                    f.write(source)
                subprocess.run([cc, *flags, src, "-o", so], check=True, capture_output=True)
                os.replace(so, path)                           # atomic: a concurrent build finds a whole file
        lib = ctypes.CDLL(path)
        for fn, argtypes in signatures:
            f = getattr(lib, fn)
            f.restype, f.argtypes = None, list(argtypes)
        return lib
    except (OSError, AttributeError, subprocess.CalledProcessError) as e:
        warnings.warn(f"{name}: the native kernel did not build ({e}); using the torch path")
        return None


def load(name: str, source: str, signatures: dict[str, list], extra_flags: tuple[str, ...] = ()) -> ctypes.CDLL | None:
    """The library of C ``source`` (compiled once per source, compiler and flags, module docstring)
    with each function of ``signatures`` given its ctypes argument types (and no return value), or
    None: no compiler, ``PRTBENCH_COMPILE=0``, or the build failed (warned once per process).
    ``extra_flags`` follow `FLAGS` (e.g. ISA flags of the host that runs the library; they are part
    of its cache key)."""
    if not compile_enabled():
        return None
    cc = compiler()
    if cc is None:
        return None
    return _build(name, source, cc, tuple((fn, tuple(a)) for fn, a in signatures.items()), (*FLAGS, *extra_flags))


def cache_clear() -> None:
    """Forget the built libraries of this process (tests: a later `load` builds or loads again)."""
    _build.cache_clear()

