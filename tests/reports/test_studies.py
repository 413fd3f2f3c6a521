"""methods.studies (the registries, loaded through methods.registry) and reports.studies (the quick
terms-vs-exponent study)."""
from __future__ import annotations

import csv
from pathlib import Path

import pytest
import torch

from methods import studies as MS
from reports import studies  # noqa: F401  (registers terms-vs-exponent and loads every method's studies)


@pytest.fixture
def one_torch_thread():
    # Small eigen-decompositions: 2 torch threads per xdist worker on 2 shared cores
    # oversubscribe the machine (measured 10× slower); restored afterwards.
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture
def clean_registries():
    saved = (dict(MS.STUDIES), dict(MS.TERMS_CONTRIBUTORS), dict(MS.ERROR_VS_TERMS))
    yield
    for reg, old in zip((MS.STUDIES, MS.TERMS_CONTRIBUTORS, MS.ERROR_VS_TERMS), saved):
        reg.clear()
        reg.update(old)


def test_builtin_registrations():
    assert "terms-vs-exponent" in MS.STUDIES
    c = MS.TERMS_CONTRIBUTORS["inout"]
    assert c.target == 0.99 and callable(c.fn)
    for name in ("triple_product", "zh_shadow", "ptt", "ptt_separated"):  # every method has a row
        assert callable(MS.TERMS_CONTRIBUTORS[name].fn), name
    assert "ptt-figures" in MS.STUDIES


# Every paper figure/table the project reproduces, by paper (`run_bench.py study --list`).
PAPER_STUDIES = {
    "Mahajan 2008": {"mahajan-fig3a", "mahajan-fig2-5", "mahajan-fig7c", "mahajan-fig6"},
    "Sun 2007": {"sun-fig5", "sun-fig6", "sun-fig8", "sun-fig9", "sun-fig10", "ptt-terms", "ptt-figures"},
    "Ma 2006": {"ma-fig7-8", "ma-tables"},
    "Nowrouzezahrai 2008": {"nowrouzezahrai-fig3-5"},
}
# Studies whose quick run takes a few seconds (measured by hand, 1 thread: ma-tables 0.0 s,
# mahajan-fig3a 2.0 s, mahajan-fig2-5 0.7 s, mahajan-fig7c 1.3 s). The others run in their
# method's tests through the same functions (tests/methods/*/test_*study*.py) or by hand.
CHEAP_STUDIES = ("ma-tables", "mahajan-fig3a", "mahajan-fig2-5", "mahajan-fig7c")


def test_every_paper_figure_is_a_registered_study():
    for paper, names in PAPER_STUDIES.items():
        missing = names - set(MS.STUDIES)
        assert not missing, f"{paper}: {sorted(missing)} not registered"
        for n in names:
            assert MS.STUDIES[n].paper == paper, n
    assert MS.STUDIES["terms-vs-exponent"].paper == ""  # the cross-method sweeps
    assert MS.STUDIES["terms-own-criteria"].paper == ""


@pytest.mark.parametrize("name", CHEAP_STUDIES)
def test_cheap_studies_run_quick(name, tmp_path, one_torch_thread):
    files = MS.run_study(name, tmp_path, quick=True)
    assert files, name
    for f in files:
        assert f.parent == tmp_path and f.stat().st_size > 0, f


def test_no_entry_points_left_in_methods():
    """Paper figures run through `run_bench.py study`, benchmarks through `python -m benchmarks.*`:
    no module under methods/ is a script."""
    root = Path(__file__).resolve().parents[2] / "methods"
    scripts = [str(p.relative_to(root.parent)) for p in root.rglob("*.py") if "__main__" in p.read_text()]
    assert not scripts, scripts


def test_register_and_run_study(tmp_path, clean_registries):
    def run(out, *, quick):
        p = out / "x.txt"
        p.write_text(str(quick))
        return [p]

    MS.register_study(MS.Study("dummy", "test", run))
    with pytest.raises(ValueError):
        MS.register_study(MS.Study("dummy", "again", run))
    files = MS.run_study("dummy", tmp_path / "o", quick=True)
    assert files[0].read_text() == "True"
    with pytest.raises(ValueError):
        MS.run_study("no-such-study", tmp_path)


def test_terms_contributors(clean_registries):
    MS.register_terms_contributor("fake", lambda s, t: int(3 * s), target=0.5, target_kind="x")
    MS.register_terms_contributor(
        "rich", lambda s, t: MS.TermsRecord("rich", s, t, 7, "y", "note"), target=0.1)
    with pytest.raises(ValueError):
        MS.register_terms_contributor("fake", lambda s, t: 1)
    with pytest.raises(ValueError):
        MS.register_terms_contributor("bad", 42)
    rows = MS.terms_table([2.0, 4.0], ["fake", "rich"])
    assert [(r.method, r.exponent, r.terms, r.target) for r in rows] == [
        ("fake", 2.0, 6, 0.5), ("fake", 4.0, 12, 0.5), ("rich", 2.0, 7, 0.1), ("rich", 4.0, 7, 0.1)]
    MS.register_terms_contributor("neg", lambda s, t: -1)
    with pytest.raises(ValueError):
        MS.terms_table([1.0], ["neg"])
    with pytest.raises(ValueError):
        MS.terms_table([1.0], ["unknown"])


def test_contributors_are_callables_not_module_strings(clean_registries):
    """Registration takes a callable (a method's study module registers its own function at
    import); a "module:function" string — a hidden import by name — is refused."""
    with pytest.raises(ValueError):
        MS.register_terms_contributor("lazy", "builtins:max")


def test_quick_terms_own_criteria(tmp_path, clean_registries, one_torch_thread):
    # The real contributors are tested with their methods (tests/methods/*); cheap stand-ins here.
    MS.TERMS_CONTRIBUTORS.clear()
    MS.ERROR_VS_TERMS.clear()
    MS.register_terms_contributor("inout", lambda s, t: int(2.5 * s), replace=True)
    MS.register_error_vs_terms("fake", lambda s, k: 1.0 / (k + s))
    files = MS.run_study("terms-own-criteria", tmp_path, quick=True)
    names = {f.name for f in files}
    for n in ("terms_by_method.csv", "terms_by_method.png", "error_vs_terms.csv"):
        assert n in names and (tmp_path / n).stat().st_size > 0
    t = list(csv.DictReader(open(tmp_path / "terms_by_method.csv")))
    assert {r["method"] for r in t} == {"inout"}
    assert [int(r["terms"]) for r in t] == [int(2.5 * s) for s in studies.OWN_CRITERIA_EXPONENTS_QUICK]
    e = list(csv.DictReader(open(tmp_path / "error_vs_terms.csv")))
    assert e and all(abs(float(r["error"]) - 1.0 / (int(r["K"]) + float(r["s"]))) < 1e-12 for r in e)
