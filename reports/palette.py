"""One colour per method for every figure the project draws (reports, studies).

``METHOD_COLORS``: method name → hex colour (Okabe–Ito, distinguishable with the common colour
vision deficiencies). ``method_color(name)``: that colour; a config-qualified label such as
``"inout (terms=8)"`` or ``"ptt_separated"`` takes its method's colour; an unknown name gets a
fixed grey-free colour from its name (the same in every figure and every run).
"""
from __future__ import annotations

import zlib

METHOD_COLORS: dict[str, str] = {
    "inout": "#0072B2",           # blue
    "zh_shadow": "#009E73",       # bluish green
    "triple_product": "#D55E00",  # vermilion
    "ptt": "#CC79A7",             # reddish purple
    "sh_prt": "#E69F00",          # orange
    "oracle": "#000000",          # black (the brute-force reference renderer)
}
# Colours for methods not listed above (picked by a hash of the name).
_EXTRA = ("#56B4E9", "#F0E442", "#882255", "#117733", "#44AA99", "#999933", "#AA4499", "#332288")


def method_color(name: str) -> str:
    """The hex colour of method ``name`` (or of a label that starts with a method's name)."""
    if not isinstance(name, str) or not name:
        raise ValueError(f"name must be a non-empty string, got {name!r}")
    if name in METHOD_COLORS:
        return METHOD_COLORS[name]
    base = max((m for m in METHOD_COLORS if name.startswith(m)), key=len, default=None)
    if base is not None:
        return METHOD_COLORS[base]
    return _EXTRA[zlib.crc32(name.encode()) % len(_EXTRA)]
