"""The run's machine limits (issue 14): measured at the start and again at the end of every
invocation, the roofline using the best of each — a measurement taken under load reads low, and a
low roof would inflate every cell's efficiency."""
from __future__ import annotations

import itertools
import json

import pytest

from reports import measure, pipeline
from reports.cells import Cell, CellResult


@pytest.fixture
def limits(monkeypatch):
    """Deterministic stand-ins for the two measurements: the n-th call returns the n-th value."""
    bw = itertools.chain([10e9, 30e9, 20e9], itertools.repeat(5e9))
    pk = itertools.chain([100e9, 50e9, 80e9], itertools.repeat(1e9))
    monkeypatch.setattr(measure, "triad_bandwidth", lambda *a, **k: next(bw))
    monkeypatch.setattr(measure, "matmul_peak", lambda *a, **k: next(pk))


def test_best_of_start_and_each_invocation(tmp_path, limits):
    meta = pipeline.run_meta(tmp_path, "smoke", bandwidth_elements=1 << 10)
    assert (meta["triad_bandwidth"], meta["matmul_peak"]) == (10e9, 100e9)
    meta = pipeline.record_invocation(tmp_path, meta, started="t", seconds=1.0, cells=1, bandwidth_elements=1 << 10)
    # the best of each limit, which need not come from the same measurement
    assert (meta["triad_bandwidth"], meta["matmul_peak"]) == (30e9, 100e9)
    meta = pipeline.record_invocation(tmp_path, meta, started="t", seconds=1.0, cells=1, bandwidth_elements=1 << 10)
    assert (meta["triad_bandwidth"], meta["matmul_peak"]) == (30e9, 100e9)
    assert [s["when"] for s in meta["limit_samples"]] == ["start", "end of invocation 1", "end of invocation 2"]
    assert [s["triad_bandwidth"] for s in meta["limit_samples"]] == [10e9, 30e9, 20e9]
    # what a resumed run reads back is what was used
    assert pipeline.read_run_json(tmp_path) == meta


def test_no_remeasurement_when_asked(tmp_path, limits):
    meta = pipeline.run_meta(tmp_path, "smoke", bandwidth_elements=1 << 10)
    meta = pipeline.record_invocation(tmp_path, meta, started="t", seconds=1.0, cells=1, bandwidth_elements=None)
    assert meta["triad_bandwidth"] == 10e9 and len(meta["limit_samples"]) == 1


def test_run_json_from_before_the_rule_counts_its_value(tmp_path, limits):
    old = {"run_id": "r", "suite": "smoke", "time": "t", "git_sha": "x", "versions": {}, "machine": "m",
           "threads": 2, "triad_bandwidth": 40e9, "matmul_peak": 60e9}
    meta = pipeline.with_limits(old, pipeline.measure_limits(1 << 10, "end of invocation 1"))
    assert (meta["triad_bandwidth"], meta["matmul_peak"]) == (40e9, 100e9)
    assert meta["limit_samples"][0] == {"when": "start", "triad_bandwidth": 40e9, "matmul_peak": 60e9}


def test_roofline_rows_use_the_best_limits(tmp_path, limits):
    meta = pipeline.run_meta(tmp_path, "smoke", bandwidth_elements=1 << 10)
    meta = pipeline.record_invocation(tmp_path, meta, started="t", seconds=1.0, cells=1, bandwidth_elements=1 << 10)
    cell = Cell(scene="s", size="test", kind="V", method="m", config="{}", bounces=0)
    rows = [{"frame": -1, "metric": "bytes_per_frame", "value": 3e7, "unit": "B", "noise_floor": float("nan")},
            {"frame": -1, "metric": "flops_per_frame", "value": 1e6, "unit": "flop", "noise_floor": float("nan")},
            {"frame": -1, "metric": "render_time_median", "value": 0.01, "unit": "s", "noise_floor": float("nan")}]
    r = CellResult(key=cell.key(), cell=cell.to_dict(), status="ok", rows=rows)
    df = pipeline.collect([r], meta)
    eff = df[df.metric == "roofline_efficiency"].value.iloc[0]
    assert eff == pytest.approx(3e7 / 30e9 / 0.01)  # 10 %: the 30 GB/s measurement, not the first 10
    bw = df[df.metric == "triad_bandwidth"].value.iloc[0]
    assert bw == 30e9
    json.dumps(meta)  # run.json stays plain JSON


def _cell_result(key_kind: str, host_bw: float | None, host_pk: float | None, status: str = "ok"):
    cell = Cell(scene="s", size="test", kind=key_kind, method="m", config="{}", bounces=0)
    rows = [{"frame": -1, "metric": "bytes_per_frame", "value": 3e7, "unit": "B", "noise_floor": float("nan")},
            {"frame": -1, "metric": "flops_per_frame", "value": 1e6, "unit": "flop", "noise_floor": float("nan")},
            {"frame": -1, "metric": "render_time_median", "value": 0.01, "unit": "s", "noise_floor": float("nan")}]
    if host_bw is not None:
        rows.append({"frame": -1, "metric": "host_triad_bandwidth", "value": host_bw, "unit": "B/s",
                     "noise_floor": float("nan")})
    if host_pk is not None:
        rows.append({"frame": -1, "metric": "host_matmul_peak", "value": host_pk, "unit": "flop/s",
                     "noise_floor": float("nan")})
    return CellResult(key=cell.key(), cell=cell.to_dict(), status=status, rows=rows)


def test_roof_is_the_best_of_run_and_cell_measurements(tmp_path, limits):
    meta = pipeline.run_meta(tmp_path, "smoke", bandwidth_elements=1 << 10)  # 10 GB/s, 100 GFLOP/s
    results = [_cell_result("V", 25e9, 40e9), _cell_result("L", float("nan"), 300e9),
               _cell_result("E", 1e12, 1e15, status="error"),  # a failed cell's numbers are not used
               _cell_result("VB", None, None)]  # a cell measured before per-cell limits existed
    assert pipeline.run_limits(results, meta) == (25e9, 300e9)
    df = pipeline.collect(results, meta)
    assert df[df.metric == "triad_bandwidth"].value.iloc[0] == 25e9
    eff = df[(df.metric == "roofline_efficiency") & (df.sequence == "VB")].value.iloc[0]
    assert eff == pytest.approx(3e7 / 25e9 / 0.01)  # every cell divides by the run's best, not its own
    # without any cell measurement the run's own measurements decide, as before
    assert pipeline.run_limits([_cell_result("V", None, None)], meta) == (10e9, 100e9)


def test_each_timed_cell_measures_the_limits(tmp_path, monkeypatch):
    from reports import measure_cell as MC
    from reports import cells as C

    calls = []
    monkeypatch.setattr(measure, "triad_bandwidth", lambda *a, **k: calls.append("bw") or 42e9)
    monkeypatch.setattr(measure, "matmul_peak", lambda *a, **k: calls.append("pk") or 77e9)
    cell = C.Cell(scene="fake_plane", size="test", kind="V", method="fake", n_frames=3, ref_spp=16, spp_side=1,
                  backend="testing.fakes", plugins=("testing.fakes",))
    monkeypatch.setenv("PRTBENCH_CELL_LIMITS", "1")
    r = MC.run_cell(cell, tmp_path / "on", progress=False)
    summ = {row["metric"]: row["value"] for row in r.rows if row["frame"] == -1}
    assert (summ["host_triad_bandwidth"], summ["host_matmul_peak"]) == (42e9, 77e9) and calls == ["bw", "pk"]
    monkeypatch.setenv("PRTBENCH_CELL_LIMITS", "0")  # the test session's setting
    r = MC.run_cell(cell, tmp_path / "off", progress=False)
    assert not any(row["metric"].startswith("host_") for row in r.rows) and calls == ["bw", "pk"]
    monkeypatch.setenv("PRTBENCH_CELL_LIMITS", "yes")
    with pytest.raises(ValueError, match="PRTBENCH_CELL_LIMITS"):
        MC.cell_limits()


def test_report_header_gives_the_cells_spread(tmp_path, limits):
    from reports.html import cell_limits_text

    meta = pipeline.run_meta(tmp_path, "smoke", bandwidth_elements=1 << 10)
    df = pipeline.collect([_cell_result("V", 20e9, 40e9), _cell_result("L", 30e9, 50e9),
                           _cell_result("E", 40e9, 60e9)], meta)
    assert cell_limits_text(df) == ("min / median / max over 3 cells: 20.0 / 30.0 / 40.0 GB/s, "
                                    "40.0 / 50.0 / 60.0 GFLOP/s")
    assert cell_limits_text(pipeline.collect([_cell_result("V", None, None)], meta)) is None
