"""reports.store: atomic writes and the long-format table / history."""
import json
import os

import pandas as pd
import pytest

from reports import store


def _rows(run_id, n=3, value=1.0):
    return [{"run_id": run_id, "time": f"2026-01-0{1 + (run_id == 'b')}T00:00:00+00:00", "git_sha": "x",
             "versions": "{}", "machine": "m", "threads": 2, "scene": "s", "size": "test", "sequence": "V",
             "frame": i, "method": "fake", "config": "{}", "bounces": 0, "metric": "render_time",
             "value": value, "unit": "s", "noise_floor": float("nan"), "status": "ok", "reason": "", "cell": "k"}
            for i in range(n)]


def test_atomic_write_failure_leaves_nothing(tmp_path):
    target = tmp_path / "a.parquet"

    def bad_writer(tmp):
        with open(tmp, "wb") as f:
            f.write(b"half")
        raise RuntimeError("killed mid-write")

    with pytest.raises(RuntimeError):
        store.atomic_save(target, bad_writer)
    assert os.listdir(tmp_path) == []  # neither the target nor a temp file


def test_atomic_write_replaces_whole_file(tmp_path):
    p = tmp_path / "x.json"
    store.atomic_write_json(p, {"a": 1})
    store.atomic_write_json(p, {"b": 2})
    assert json.loads(p.read_text()) == {"b": 2}
    assert os.listdir(tmp_path) == ["x.json"]


def test_table_roundtrip_has_columns_and_types(tmp_path):
    df = store.to_frame(_rows("a"))
    assert list(df.columns) == store.COLUMNS
    store.write_table(df, tmp_path / "r.parquet")
    back = store.read_table(tmp_path / "r.parquet")
    pd.testing.assert_frame_equal(back, df)
    assert back["frame"].dtype == "int64" and back["value"].dtype == "float64"
    with pytest.raises(ValueError):
        store.write_table(df.drop(columns=["metric"]), tmp_path / "bad.parquet")


def test_history_appends_and_replaces_same_run(tmp_path):
    h = tmp_path / "hist.parquet"
    store.append_history(store.to_frame(_rows("a")), h)
    store.append_history(store.to_frame(_rows("b")), h)
    store.append_history(store.to_frame(_rows("b", value=2.0)), h)  # a resumed run re-finished
    hist = store.read_history(h)
    assert sorted(hist["run_id"].value_counts().items()) == [("a", 3), ("b", 3)]
    assert set(hist[hist.run_id == "b"]["value"]) == {2.0}
