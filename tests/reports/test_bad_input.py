"""Bad input to the harness (issue 17): an unknown scene is one error line like an unknown method;
corrupt cell / part / run.json files are named in one line, moved aside and recomputed; cell keys
follow the scene's content; a scene file is identified by its TOML name, not its path."""
import json
import re
import shutil
from pathlib import Path

import pytest

import run_bench
from reports import cells as C
from reports import pipeline
from reports import runner as R
from reports.suites import SMOKE, plan_cells

FAKE = dict(backend="testing.fakes", plugins=("testing.fakes",))
EXAMPLES = Path(__file__).resolve().parents[2] / "scenes" / "examples"


@pytest.fixture(autouse=True)
def small_triad(monkeypatch):
    monkeypatch.setattr(pipeline, "TRIAD_ELEMENTS", 1 << 16)  # bandwidth measurement cost, not its value


def _cell(**kw):
    d = dict(scene="fake_plane", size="test", kind="V", method="fake", n_frames=3, ref_spp=8, spp_side=1, **FAKE)
    d.update(kw)
    return C.Cell(**d)


# -- 6. unknown scene ---------------------------------------------------------------------------


def _cli(capsys, tmp_path, *args):
    code = run_bench.main(["run", "--suite", "smoke", "--backend", "testing.fakes", "--plugin", "testing.fakes",
                           "--out", str(tmp_path / "out"), "--no-history", "--no-isolate", "--no-vertex-renders", "--quiet", *args])
    cap = capsys.readouterr()
    return code, cap.err.strip()


def test_unknown_scene_is_one_line_like_unknown_method(tmp_path, capsys):
    code, err = _cli(capsys, tmp_path, "--scenes", "nope", "--methods", "fake")
    assert code == 2 and err == "prtbench: error: unknown scene 'nope'; available: fake_plane, fake_creature"
    assert not (tmp_path / "out").exists()  # nothing written
    code_m, err_m = _cli(capsys, tmp_path, "--scenes", "fake_plane", "--methods", "nope")
    assert code_m == 2 and re.fullmatch(r"prtbench: error: unknown method 'nope'; available: .+", err_m)
    code, err = _cli(capsys, tmp_path, "--scene-file", str(tmp_path / "missing.toml"), "--methods", "fake")
    assert code == 2 and err == f"prtbench: error: {tmp_path / 'missing.toml'}: scene file not found"


def test_bad_scene_file_is_one_line_and_writes_nothing(tmp_path, capsys):
    p = _scene_dir(tmp_path)
    p.write_text(p.read_text().replace("fov_deg = 45.0", "fov_deg = 179.99"))
    code = run_bench.main(["run", "--suite", "smoke", "--scene-file", str(p), "--methods", "oracle",
                           "--out", str(tmp_path / "out"), "--no-history", "--quiet", "--fresh"])
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.startswith("prtbench: error: my_scene_file.toml: [camera] fov_deg/origin/target: ")
    assert "\n" not in err and not (tmp_path / "out").exists()


def test_unknown_library_scene_in_the_real_backend_is_a_value_error():
    from reports.backend import get_scene

    with pytest.raises(ValueError, match=r"^unknown scene 'nope'; available: sphere_plane, "):
        get_scene("nope")
    with pytest.raises(ValueError, match=r"^unknown scene 'nope'; available: "):
        plan_cells(SMOKE, methods=["oracle"], scenes=["nope"])


# -- 7. corrupt cell / part / run files ----------------------------------------------------------


CORRUPTIONS = {
    "not_utf8": lambda p: p.write_bytes(b"\xff\xfe\x00garbage"),
    "empty_object": lambda p: p.write_text("{}"),
    "garbage": lambda p: p.write_text("this is not json"),
    "list": lambda p: p.write_text("[1, 2]"),
    "folder": lambda p: (p.unlink(), p.mkdir(), (p / "x").write_text("x")),
}


@pytest.mark.parametrize("how", sorted(CORRUPTIONS))
def test_corrupt_cell_file_is_named_moved_aside_and_rerun(tmp_path, capsys, how):
    cells = [_cell(), _cell(kind="VBL")]
    first = R.run_cells(cells, tmp_path, progress=False)
    assert [r.status for r in first] == ["ok", "ok"]
    p = C.result_path(tmp_path, cells[0])
    intact = C.result_path(tmp_path, cells[1]).stat().st_mtime_ns
    CORRUPTIONS[how](p)
    capsys.readouterr()
    again = R.run_cells(cells, tmp_path, progress=False)
    assert [r.status for r in again] == ["ok", "ok"]
    err = [l for l in capsys.readouterr().err.splitlines() if "corrupt" in l or "moved to" in l]
    assert len(err) == 1 and str(p) in err[0] and "moved to" in err[0], err
    aside = list(p.parent.glob(p.name + ".corrupt-*"))
    assert len(aside) == 1
    assert C.load_result(tmp_path, cells[0]).status == "ok"  # re-run and stored again
    assert C.result_path(tmp_path, cells[1]).stat().st_mtime_ns == intact  # the intact cell was not re-run


def test_cell_file_of_another_cell_is_moved_aside(tmp_path, capsys):
    a, b = _cell(), _cell(kind="VBL")
    R.run_cells([a, b], tmp_path, progress=False)
    shutil.copy(C.result_path(tmp_path, b), C.result_path(tmp_path, a))
    assert C.load_result(tmp_path, a) is None
    assert f"holds cell {b.key()!r}" in capsys.readouterr().err


@pytest.mark.parametrize("how", ["not_utf8", "empty_object", "folder"])
def test_corrupt_part_file_is_moved_aside(tmp_path, capsys, how):
    c = _cell()
    p = C.part_path(tmp_path, c, "errors")
    p.parent.mkdir(parents=True)
    p.write_text("x")
    CORRUPTIONS[how](p)
    assert C.load_part(tmp_path, c, "errors") is None
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(p) in err[0]
    assert not p.exists() and len(list(p.parent.glob(p.name + ".corrupt-*"))) == 1


@pytest.mark.parametrize("how", ["not_utf8", "empty_object", "list"])
def test_corrupt_run_json_is_moved_aside_by_run_meta(tmp_path, capsys, how):
    meta = pipeline.run_meta(tmp_path, "smoke", bandwidth_elements=1 << 10)
    p = tmp_path / "run.json"
    CORRUPTIONS[how](p)
    assert pipeline.read_run_json(tmp_path) is None  # no side effect
    assert p.exists()
    new = pipeline.run_meta(tmp_path, "smoke", bandwidth_elements=1 << 10)
    assert new["run_id"] != meta["run_id"] and pipeline.read_run_json(tmp_path) == new
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(p) in err[0] and "run.json.corrupt-" in err[0]


@pytest.mark.parametrize("how", ["garbage", "folder"])
def test_corrupt_run_json_is_named_moved_aside_and_the_run_redone(tmp_path, capsys, how):
    code, _ = _cli(capsys, tmp_path, "--scenes", "fake_plane", "--methods", "fake")
    assert code == 0
    p = tmp_path / "out" / "run.json"
    CORRUPTIONS[how](p)
    code, err = _cli(capsys, tmp_path, "--scenes", "fake_plane", "--methods", "fake")
    assert code == 0, err
    lines = [l for l in err.splitlines() if "run.json" in l]
    assert len(lines) == 1 and str(p) in lines[0] and "moved to run.json.corrupt-" in lines[0], err
    assert len(list(p.parent.glob("run.json.corrupt-*"))) == 1
    assert pipeline.read_run_json(tmp_path / "out")["run_id"]  # a fresh, valid run.json
    # `report` on a run whose run.json is garbage does not crash either
    p.write_text("garbage")
    assert run_bench.main(["report", str(tmp_path / "out"), "--history", str(tmp_path / "none.parquet")]) == 0


# -- 8./9. file scenes: keys follow the content; results show the TOML name ------------------------


def _scene_dir(tmp_path, text=None) -> Path:
    for f in ("box.obj", "ground.obj"):
        shutil.copy(EXAMPLES / f, tmp_path / f)
    p = tmp_path / "my_scene_file.toml"
    p.write_text(text if text is not None else (EXAMPLES / "two_boxes.toml").read_text())
    return p


def _plan(p):
    return plan_cells(SMOKE, methods=["oracle"], scenes=[f"file:{p}"])


def test_editing_a_scene_file_changes_the_cell_keys(tmp_path):
    p = _scene_dir(tmp_path)
    before = [c.key() for c in _plan(p)]
    assert before == [c.key() for c in _plan(p)]  # stable
    text = p.read_text()
    p.write_text(text.replace("kd = [0.5, 0.1, 0.08]", "kd = [0.1, 0.5, 0.08]"))  # a material colour
    after = [c.key() for c in _plan(p)]
    assert not set(before) & set(after)
    p.write_text(text.replace("fov_deg = 45.0", "fov_deg = 46.0"))  # the camera
    assert not set(before) & set(c.key() for c in _plan(p))
    (tmp_path / "box.obj").write_text((tmp_path / "box.obj").read_text().replace("v 0.5 ", "v 0.6 ", 1))  # mesh bytes
    p.write_text(text)
    assert not set(before) & set(c.key() for c in _plan(p))


def test_a_scene_file_is_identified_by_its_name_not_its_path(tmp_path):
    p = _scene_dir(tmp_path)
    cells = _plan(p)
    c = next(c for c in cells if c.na is None)
    assert c.scene == "two_boxes" and c.scene_file == str(p) and c.scene_ref == f"file:{p}"
    assert c.key().startswith("two_boxes-test-") and str(tmp_path) not in c.key()
    # the results table: name only, no path anywhere
    res = C.CellResult(c.key(), c.to_dict(), "ok", rows=[{"frame": -1, "metric": "rmse", "value": 0.1, "unit": "radiance",
                                                          "noise_floor": 0.01}])
    meta = {"run_id": "smoke-x", "time": "t", "git_sha": "g", "versions": {}, "machine": "m", "threads": 1,
            "triad_bandwidth": 1e9}
    df = pipeline.collect([res], meta)
    assert set(df[df.status != "run"]["scene"]) == {"two_boxes"}
    assert str(tmp_path) not in df.to_csv()
    prov = pipeline.provenance([res])
    assert prov[0]["scene"] == "two_boxes" and str(tmp_path) not in json.dumps(prov)
    # without a name key the file stem is the name
    p2 = tmp_path / "other.toml"
    p2.write_text(p.read_text().replace('name = "two_boxes"', ""))
    assert {c.scene for c in _plan(p2)} == {"other"}


def test_two_scenes_with_one_name_are_refused(tmp_path):
    p = _scene_dir(tmp_path)
    p2 = tmp_path / "copy.toml"
    p2.write_text(p.read_text())
    with pytest.raises(ValueError, match="scene name 'two_boxes' is used twice"):
        plan_cells(SMOKE, methods=["oracle"], scenes=[f"file:{p}", f"file:{p2}"])
    p2.write_text(p.read_text().replace('name = "two_boxes"', 'name = "chess"'))
    with pytest.raises(ValueError, match="copy.toml: scene name 'chess' is a library scene's name"):
        plan_cells(SMOKE, methods=["oracle"], scenes=[f"file:{p2}"])
