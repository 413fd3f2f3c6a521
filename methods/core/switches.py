"""On/off switches read from the environment at each call (``PRTBENCH_COMPILE``, a method's own
``PRTBENCH_*_NATIVE``): tests and A/B tools flip them with ``monkeypatch.setenv`` between calls, so a
switch is never cached; frames read them, so a read must be cheap.

`on` reads ``os.environ``'s own mapping (POSIX: a dict of bytes keys and values that
``os.environ.__setitem__`` / ``__delitem__`` keep in step with the process environment) by one
look-up: ``os.environ.get`` runs ~5 Python frames (the key encoded, the value decoded) — measured
~14 µs more per call with the caches a benchmark frame starts with (a 64 MB buffer written between
calls; ~0.7 µs this way), and a ZH paper frame read its switches 26 times, a triple-product frame 31
(session 43, ``/work/scratch/envcount.py``-style count of ``os.environ`` reads inside ``render``).
Where the mapping is not such a dict (another OS, a test that replaced ``os.environ``),
``os.environ.get``: the same answers (but for non-ASCII spaces around a value, which only the
latter strips).
"""
from __future__ import annotations

import os

__all__ = ["OFF", "on"]

# Values that switch a flag off (after surrounding ASCII spaces are stripped, ASCII letters in any case).
OFF = ("0", "false", "no", "off")
_OFF_BYTES = tuple(v.encode() for v in OFF)

_ENV = os.environ
_DATA = getattr(_ENV, "_data", None) if os.name == "posix" else None
_DATA = _DATA if type(_DATA) is dict else None
_KEYS: dict[str, bytes] = {}


def on(name: str) -> bool:
    """False when the environment variable ``name`` is one of `OFF` (surrounding spaces stripped, any
    case), True when it is unset or anything else."""
    data = _DATA
    if data is not None and os.environ is _ENV:
        key = _KEYS.get(name)
        if key is None:
            key = _KEYS[name] = os.fsencode(name)
        raw = data.get(key)
        return raw is None or raw.strip().lower() not in _OFF_BYTES
    value = os.environ.get(name)
    return value is None or value.strip().lower() not in OFF
