"""reports.pipeline: re-running into a finished run directory adds to it (never drops cells),
a run that cannot be resumed is moved aside (never deleted), failed cells say why on the console;
run_bench compare exits 2 on runs without a common cell. Fake backend (testing.fakes)."""
import json
import re

import pandas as pd
import pytest

import run_bench
from reports import pipeline, store
from reports.suites import Suite

SUITE = Suite(name="smoke", size="test", kinds=("V",), n_frames=3, ref_spp=16, spp_side=1, scenes=("fake_plane",),
              isolate=False)
KW = dict(backend="testing.fakes", plugins=("testing.fakes",), progress=False, report=False, bandwidth_elements=1 << 12)


def _methods(df):
    return sorted(set(df.loc[df.status != "run", "method"]))


def test_rerun_with_fewer_methods_adds_to_the_run(tmp_path):
    out, hist = tmp_path / "run", tmp_path / "hist.parquet"
    a = pipeline.run_suite(SUITE, out, methods=["fake", "fake_gi"], history=hist, **KW)
    b = pipeline.run_suite(SUITE, out, methods=["fake"], history=hist, **KW)
    assert a.run_id == b.run_id
    table = store.read_table(out)
    assert _methods(table) == ["fake", "fake_gi"]
    assert (table.status == "run").sum() == 1
    h = store.read_history(hist)
    assert _methods(h) == ["fake", "fake_gi"] and set(h.run_id) == {a.run_id}
    assert len(h) == len(table)  # nothing duplicated
    plan = json.loads((out / "plan.json").read_text())
    assert sorted({c["method"] for c in plan}) == ["fake", "fake_gi"]
    # a third invocation adding a method keeps both earlier ones
    pipeline.run_suite(SUITE, out, methods=["fake_fail"], history=hist, **KW)
    assert _methods(store.read_table(out)) == ["fake", "fake_fail", "fake_gi"]
    assert _methods(store.read_history(hist)) == ["fake", "fake_fail", "fake_gi"]


def test_run_that_cannot_resume_is_moved_aside(tmp_path, monkeypatch, capsys):
    out, hist = tmp_path / "run", tmp_path / "hist.parquet"
    (tmp_path / "keep.txt").write_text("not a run file")
    a = pipeline.run_suite(SUITE, out, methods=["fake"], history=hist, **KW)
    before = store.read_table(out)
    cells = sorted(p.name for p in (out / "cells").iterdir())
    monkeypatch.setattr(store, "code_fingerprint", lambda root=None: "someotherversion")
    b = pipeline.run_suite(SUITE, out, methods=["fake"], history=hist, **KW)
    assert b.run_id != a.run_id
    msg = capsys.readouterr().out
    assert "the code changed since this run started" in msg
    dest = tmp_path / re.search(r"moved to \S*?(run\.prev-\S+?);", msg).group(1)
    assert dest.is_dir() and dest.name.startswith("run.prev-")
    assert json.loads((dest / "run.json").read_text())["run_id"] == a.run_id
    pd.testing.assert_frame_equal(store.read_table(dest), before)
    assert sorted(p.name for p in (dest / "cells").iterdir()) == cells
    assert json.loads((out / "run.json").read_text())["run_id"] == b.run_id
    assert (tmp_path / "keep.txt").read_text() == "not a run file"
    assert set(store.read_history(hist).run_id) == {a.run_id, b.run_id}


def test_preserve_run_never_overwrites_an_earlier_copy(tmp_path):
    out = tmp_path / "run"
    dests = []
    for i in range(2):
        (out / "cells").mkdir(parents=True)
        (out / "run.json").write_text(json.dumps({"i": i}))
        dests.append(pipeline.preserve_run(out))
    assert dests[0] != dests[1]
    assert [json.loads((d / "run.json").read_text())["i"] for d in dests] == [0, 1]
    assert not (out / "run.json").exists() and pipeline.preserve_run(out) is None


def test_failed_cell_prints_its_reason(tmp_path, capsys):
    res = pipeline.run_suite(SUITE, tmp_path / "run", methods=["fake", "fake_fail"], history=None, **KW)
    assert res.n_error == 1
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if "FAILED" in ln]
    assert lines == ["[prtbench] FAILED fake_fail/fake_plane/V/b0: RuntimeError: planted failure"]


def test_scene_file_runs_are_labelled(tmp_path):
    assert pipeline.suite_label("smoke", ["sphere_plane"]) == "smoke"
    assert pipeline.suite_label("smoke", None) == "smoke"
    assert pipeline.suite_label("smoke", ["file:/x/two_boxes.toml"]) == "smoke+files"


def test_compare_runs_without_common_cells_exits_2(tmp_path, capsys):
    hist = tmp_path / "hist.parquet"
    pipeline.run_suite(SUITE, tmp_path / "a", methods=["fake"], history=hist, **KW)
    pipeline.run_suite(SUITE, tmp_path / "b", methods=["fake_gi"], history=hist, **KW)
    capsys.readouterr()
    assert run_bench.main(["compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 2
    assert "share no cell" in capsys.readouterr().err
    assert run_bench.main(["compare", str(tmp_path / "a"), str(tmp_path / "a")]) == 0
    assert "no changes" in capsys.readouterr().out


def test_wall_time_of_every_invocation_in_run_json_console_and_report(tmp_path):
    """Issue 14 item 6: the suite's wall time is in the report header; a resumed run lists each
    invocation (planning, references and cells) and their sum."""
    out = tmp_path / "run"
    a = pipeline.run_suite(SUITE, out, methods=["fake"], history=None, **KW)
    inv = json.loads((out / "run.json").read_text())["invocations"]
    assert len(inv) == 1 and inv[0]["cells"] == 1 and inv[0]["seconds"] >= 0
    assert a.wall_time is not None and "invocations" not in a.wall_time
    b = pipeline.run_suite(SUITE, out, methods=["fake_gi"], history=None, **{**KW, "report": True})
    inv = json.loads((out / "run.json").read_text())["invocations"]
    assert [i["cells"] for i in inv] == [1, 1] and b.run_id == a.run_id
    assert "(2 invocations:" in b.wall_time
    html = b.report.read_text()
    assert "wall time" in html and "2 invocations" in html
