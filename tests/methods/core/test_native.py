"""`methods.core.native`'s host-ISA flags: one lookup shared by every library built for the host."""
from __future__ import annotations

import pathlib

import pytest
import torch

from methods.core import native


@pytest.mark.parametrize("cap, flags", [("AVX2", ("-mavx2", "-mfma")), ("AVX512", ("-mavx2", "-mfma")),
                                        ("DEFAULT", ()), ("ZVECTOR", ())])
def test_isa_flags_follow_torchs_cpu_capability(cap, flags, monkeypatch):
    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", lambda: cap)
    native.cpu_capability.cache_clear()
    try:
        assert native.cpu_capability() == cap
        assert native.isa_flags() == flags
    finally:
        native.cpu_capability.cache_clear()


def test_cpu_capability_without_the_query_is_unknown(monkeypatch):
    def broken():
        raise AttributeError("no get_cpu_capability")

    monkeypatch.setattr(torch.backends.cpu, "get_cpu_capability", broken)
    native.cpu_capability.cache_clear()
    try:
        assert native.cpu_capability() == "unknown" and native.isa_flags() == ()
    finally:
        native.cpu_capability.cache_clear()


def test_every_host_built_library_takes_the_shared_flags():
    """The libraries that add the host's ISA take it from here (one lookup, one cache key rule)."""
    from methods.ptt import native as ptt_native
    from methods.sh_prt import native as sh_native
    from methods.triple_product import native as tp_native
    from methods.triple_product import native_light

    isa = native.isa_flags()
    for flags in (tp_native._flags(), native_light._flags(), sh_native._flags()):
        assert flags[len(flags) - len(isa):] == isa
    assert f"-DPRTBENCH_CPU_{native.cpu_capability()}" in ptt_native._EXTRA_FLAGS


def test_the_capability_is_looked_up_in_one_place():
    """No method module asks torch for the CPU capability itself (three copies of the lookup grew
    in sessions 27-29): `cpu_capability` / `isa_flags` are the one place."""
    root = pathlib.Path(native.__file__).parents[1]
    askers = sorted(str(p.relative_to(root)) for p in root.rglob("*.py") if "get_cpu_capability" in p.read_text())
    assert askers == ["core/native.py"]
