"""Pick the Mitsuba 3 variant once for the whole process.

`llvm_ad_rgb` is the fast variant (and the only one in which Python BSDF plugins are fast). Dr.Jit's
LLVM backend needs libLLVM >= 17 in practice (Debian's libllvm15 crashes with
"Cannot select ... fminimum"), so we point Dr.Jit at the newest libLLVM on the machine and fall back
to `scalar_rgb` with a warning when none is usable. `PRTBENCH_MI_VARIANT` forces a variant.
"""
from __future__ import annotations

import glob
import os
import re
import warnings

_VARIANT: str | None = None


def _newest_libllvm() -> str | None:
    best, best_v = None, -1
    for p in glob.glob("/usr/lib/x86_64-linux-gnu/libLLVM*.so*") + glob.glob("/usr/lib/aarch64-linux-gnu/libLLVM*.so*"):
        m = re.search(r"libLLVM(?:-|\.so\.)(\d+)", os.path.basename(p))
        if m and int(m.group(1)) > best_v:
            best, best_v = p, int(m.group(1))
    return best if best_v >= 17 else None


def ensure_variant(preferred: str | None = None) -> str:
    """Set (once) and return the active Mitsuba variant."""
    global _VARIANT
    import mitsuba as mi

    if _VARIANT is not None:
        return _VARIANT
    want = preferred or os.environ.get("PRTBENCH_MI_VARIANT")
    candidates = [want] if want else []
    if not want:
        lib = _newest_libllvm()
        if lib:
            os.environ.setdefault("DRJIT_LIBLLVM_PATH", lib)
            candidates.append("llvm_ad_rgb")
        else:
            warnings.warn("no libLLVM >= 17 found: Mitsuba falls back to scalar_rgb (slow); "
                          "run `make setup` as root to install libllvm19", RuntimeWarning)
        candidates.append("scalar_rgb")
    last_err = None
    for v in candidates:
        try:
            mi.set_variant(v)
            if v.startswith("llvm"):
                import drjit as dr
                dr.eval(dr.ones(mi.Float, 4) * 2)  # smoke: a broken libLLVM fails here, not later
            _VARIANT = v
            return v
        except Exception as e:  # pragma: no cover - depends on the machine
            last_err = e
            warnings.warn(f"Mitsuba variant {v} unusable ({e}); trying the next", RuntimeWarning)
    raise RuntimeError(f"no usable Mitsuba variant among {candidates}: {last_err}")


def variant() -> str:
    return ensure_variant()
