"""ZH's C libraries follow PRTBENCH_COMPILE at each call (as in-out's, SH PRT's and the oracle's since
b541a75, tests/methods/test_native_off_switch.py): one first asked for while compilation was off (a
test's monkeypatch) loads once it is back on. Until session 31 ZH lru-cached them, so a None met while
PRTBENCH_COMPILE=0 stuck for the pytest worker and later tests ran the fallbacks."""
from methods.core import native as core_native
from methods.zh_shadow import native as Z

_GETTERS = ("_kernel", "_split_lib", "_csr_lib", "_face_pixels_lib", "_plane_pixels_lib", "_relight_lib",
            "_screen_lib", "_terms_lib", "_project_lib", "_conj_lib")


def test_zh_libraries_asked_for_while_compilation_was_off_load_when_it_is_back_on(monkeypatch):
    if core_native.compiler() is None:   # pragma: no cover - no C compiler here
        import pytest
        pytest.skip("no C compiler")
    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    assert all(getattr(Z, g)() is None for g in _GETTERS)
    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    on = {g: getattr(Z, g)() is not None for g in _GETTERS}
    if Z._inductor_lanes() not in Z.TERMS_LANES:   # sample_terms' kernel needs Inductor's AVX2 / AVX-512
        on.pop("_terms_lib")
    assert all(on.values()), on
