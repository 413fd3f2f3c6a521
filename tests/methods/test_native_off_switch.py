"""The C libraries of the methods follow PRTBENCH_COMPILE at each call: one first asked for while it
was 0 (a test's monkeypatch) loads once it is back on. Until session 30 their `_lib` was lru-cached,
so the None stuck for the process and later tests in that pytest worker ran the fallbacks
(CI on an AVX-512 host: sh_prt's add_pixels test failed by test order)."""


def test_a_library_asked_for_while_compilation_was_off_loads_when_it_is_back_on(monkeypatch):
    from methods.sh_prt import native as S
    from methods.inout import native as I, native_sample as IS
    from methods.oracle import native_rays as O
    from methods.core import sh_native as C   # SH PRT's and ZH's projection of a new map (session 31)
    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    assert S._lib() is None and I._lib() is None and IS._lib() is None and O._lib() is None and C._lib() is None
    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    assert (S._lib() is not None and I._lib() is not None and IS._lib() is not None and O._lib() is not None
            and C._lib() is not None)
