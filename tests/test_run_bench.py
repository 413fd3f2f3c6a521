"""run_bench.py command line, on the fake backend (testing.fakes): run → resume → compare, study
wiring, errors."""
import re
import sys
import types

import pandas as pd
import pytest

import run_bench
from reports import pipeline

FAKE = ["--backend", "testing.fakes", "--plugin", "testing.fakes", "--scenes", "fake_plane"]


@pytest.fixture(autouse=True)
def small_triad(monkeypatch):
    monkeypatch.setattr(pipeline, "TRIAD_ELEMENTS", 1 << 16)  # bandwidth measurement cost, not its value


def _run(capsys, out, hist, *extra):
    code = run_bench.main(["run", "--suite", "smoke", *FAKE, "--methods", "fake", "fake_gi", "--out", str(out),
                           "--history", str(hist), "--no-isolate", "--no-vertex-renders", "--quiet", *extra])
    return code, capsys.readouterr().out


def test_run_resume_and_compare(tmp_path, capsys, monkeypatch):
    # The fakes' frames take ~70 µs, so one scheduler hiccup of a loaded machine (2 ms, seen) is a
    # "+3000 %" frame-time change: their times say nothing, and this test checks the plumbing of
    # resume and compare, not timing (the time rule has its own planted tests in tests/reports).
    from reports import regress
    monkeypatch.setattr(regress, "TIME_ABS_FLOOR", 1.0)
    hist = tmp_path / "history.parquet"
    code, out = _run(capsys, tmp_path / "a", hist)
    assert code == 0, out
    run_id = re.search(r"run (\S+):", out).group(1)
    # smoke kinds V, VBL, L, E: fake runs V, L, E (VBL n/a: fixed BRDFs), fake_gi all four
    assert "7 cells ok, 0 suspect, 1 n/a, 0 failed" in out
    report = re.search(r"report:\s+(\S+)", out).group(1)
    assert report.endswith("a/report.html") and (tmp_path / "a" / "report.html").exists()

    stamps = {p.name: p.stat().st_mtime_ns for p in (tmp_path / "a" / "cells").iterdir()}
    code, out2 = _run(capsys, tmp_path / "a", hist)  # resume: same run, nothing recomputed
    assert code == 0 and f"run {run_id}:" in out2
    assert {p.name: p.stat().st_mtime_ns for p in (tmp_path / "a" / "cells").iterdir()} == stamps
    assert pd.read_parquet(hist)["run_id"].nunique() == 1

    code, out_f = _run(capsys, tmp_path / "c", hist)
    code, out_f2 = _run(capsys, tmp_path / "c", hist, "--fresh")  # --fresh: a new run, not a resume
    assert code == 0 and re.search(r"run (\S+):", out_f).group(1) != re.search(r"run (\S+):", out_f2).group(1)

    code, out3 = _run(capsys, tmp_path / "b", hist)  # a new run compares against the history
    assert code == 0 and "no regressions since the last run" in out3
    assert pd.read_parquet(hist)["run_id"].nunique() == 4

    # plant a 30 % error rise in run b (the fake references are noisy: 5 % is below their floor)
    t = pd.read_parquet(tmp_path / "b" / "results.parquet")
    t.loc[t.metric == "rmse", "value"] *= 1.3
    t.to_parquet(tmp_path / "b" / "results.parquet")
    code = run_bench.main(["compare", str(tmp_path / "a"), str(tmp_path / "b")])
    out4 = capsys.readouterr().out
    assert code == 1 and "!!" in out4 and "rmse" in out4
    assert run_bench.main(["compare", str(tmp_path / "a"), str(tmp_path / "a")]) == 0
    assert "no changes" in capsys.readouterr().out


def test_references_subcommand(capsys):
    assert run_bench.main(["references", "--suite", "smoke", *FAKE, "--methods", "fake", "--quiet"]) == 0
    # smoke: V, L, E for "fake" (VBL is n/a) → 3 × (3 frames + the equal-error ladder's other spp (16))
    assert "12 references ready" in capsys.readouterr().out


def test_study_subcommand_is_wired(tmp_path, monkeypatch, capsys):
    calls = []

    def run_study(name, out_dir, *, quick=False):
        calls.append((name, out_dir, quick))
        return [out_dir / "plot.png"]

    fake = types.ModuleType("reports.studies")
    fake.STUDIES = {"terms": None}
    fake.run_study = run_study
    monkeypatch.setitem(sys.modules, "reports.studies", fake)
    import reports

    monkeypatch.setattr(reports, "studies", fake, raising=False)
    assert run_bench.main(["study", "terms", "--out", str(tmp_path), "--quick"]) == 0
    assert calls == [("terms", tmp_path, True)]
    assert str(tmp_path / "plot.png") in capsys.readouterr().out
    assert run_bench.main(["study", "nope"]) == 2


def test_study_list_shows_every_paper_figure(capsys):
    assert run_bench.main(["study", "--list"]) == 0
    out = capsys.readouterr().out
    listed = {line.split()[0] for line in out.splitlines() if line.strip()}
    for name in ("terms-vs-exponent", "mahajan-fig3a", "mahajan-fig2-5", "mahajan-fig7c", "mahajan-fig6",
                 "sun-fig5", "sun-fig6", "sun-fig8", "sun-fig9", "sun-fig10", "ptt-terms", "ptt-figures",
                 "ma-fig7-8", "ma-tables", "nowrouzezahrai-fig3-5"):
        assert name in listed, name
    assert "Mahajan 2008" in out and "Sun 2007" in out and "Ma 2006" in out and "Nowrouzezahrai 2008" in out


def test_bad_input_is_reported(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        run_bench.main(["run", "--suite", "weekly"])
    assert e.value.code == 2
    code = run_bench.main(["run", *FAKE, "--methods", "no_such_method", "--out", str(tmp_path), "--no-history"])
    assert code == 2 and "unknown method" in capsys.readouterr().err
    assert run_bench.main(["compare", str(tmp_path / "x"), str(tmp_path / "y")]) == 2


def test_changed_code_is_not_resumed(tmp_path, capsys, monkeypatch):
    """Resuming a run made with other code would mix numbers of two versions in one table."""
    hist = tmp_path / "history.parquet"
    code, out = _run(capsys, tmp_path / "a", hist)
    run_id = re.search(r"run (\S+):", out).group(1)
    from reports import store

    monkeypatch.setattr(store, "code_fingerprint", lambda root=None: "someotherversion")
    code, out2 = _run(capsys, tmp_path / "a", hist)
    assert code == 0 and "the code changed since this run started" in out2
    assert re.search(r"run (\S+):", out2).group(1) != run_id


def test_list_shows_what_can_be_run(capsys):
    import run_bench
    from methods.registry import available_methods
    from scenes.library import SCENES
    from scenes.sequences import KINDS

    assert run_bench.main(["list", "--test-only"]) == 0
    out = capsys.readouterr().out
    for name in [*SCENES, *available_methods(), "smoke", "nightly", "terms-vs-exponent"]:
        assert f"\n{name} " in out or out.startswith(f"{name} "), name
    for k in KINDS:
        assert f"\n{k} " in out, k
    assert "bunny" in SCENES and "character" in SCENES  # the vendored real scenes are listed


def test_openmp_env_spins_a_while_for_the_perf_suite_only(tmp_path, capsys):
    """`run_bench.openmp_env`: PASSIVE for every run, plus a bounded spin (GOMP_SPINCOUNT) for ``--suite
    perf`` (run alone: every parallel region would otherwise first wake sleeping threads); a user's own
    setting wins (a fresh interpreter: the variables must be set before torch loads OpenMP); the run
    records what it ran under in run.json and the report's header."""
    import json
    import os
    import subprocess
    from pathlib import Path

    perf = {"OMP_WAIT_POLICY": "PASSIVE", "GOMP_SPINCOUNT": str(run_bench.PERF_SPINCOUNT)}
    assert run_bench.openmp_env(["run", "--suite", "perf"]) == perf
    assert run_bench.openmp_env(["run", "--out", "x", "--suite=perf"]) == perf
    for argv in (["run"], ["run", "--suite", "nightly"], ["run", "--suite", "smoke"], ["run", "--suite"],
                 ["compare", "a", "b"], ["run", "--out", "perf"]):
        assert run_bench.openmp_env(argv) == {"OMP_WAIT_POLICY": "PASSIVE"}, argv
    root = Path(run_bench.__file__).resolve().parent
    code = ("import sys; sys.argv = ['run_bench.py', 'run', '--suite', 'perf']; import run_bench, os; "
            "print(os.environ['OMP_WAIT_POLICY'], os.environ['GOMP_SPINCOUNT'])")
    env = {k: v for k, v in os.environ.items() if k not in ("OMP_WAIT_POLICY", "GOMP_SPINCOUNT")}
    got = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True, check=True)
    assert got.stdout.split() == ["PASSIVE", str(run_bench.PERF_SPINCOUNT)]
    got = subprocess.run([sys.executable, "-c", code], cwd=root, env={**env, "GOMP_SPINCOUNT": "7"},
                         capture_output=True, text=True, check=True)
    assert got.stdout.split() == ["PASSIVE", "7"]
    code, _ = _run(capsys, tmp_path / "run", tmp_path / "hist")
    assert code == 0
    meta = json.loads((tmp_path / "run" / "run.json").read_text())
    assert meta["openmp"].startswith(f"OMP_WAIT_POLICY={os.environ['OMP_WAIT_POLICY']}")
    assert f"OpenMP</th><td>{meta['openmp']}" in (tmp_path / "run" / "report.html").read_text()
