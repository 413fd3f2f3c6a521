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


def test_atomic_writes_respect_the_umask(tmp_path):
    """Reports are served by web servers running as another user: an atomically written file gets
    the permissions a plain open() gives it (0o666 minus the umask), not mkstemp's 0o600."""
    for umask, mode in ((0o022, 0o644), (0o002, 0o664), (0o077, 0o600)):
        old = os.umask(umask)
        try:
            p = store.atomic_write_text(tmp_path / f"r{umask:o}.html", "<p>")
            q = store.write_table(store.to_frame(_rows("a")), tmp_path / f"r{umask:o}.parquet")
            with open(tmp_path / f"plain{umask:o}", "w"):
                pass
        finally:
            os.umask(old)
        plain = os.stat(tmp_path / f"plain{umask:o}").st_mode & 0o777
        assert plain == mode
        assert os.stat(p).st_mode & 0o777 == mode and os.stat(q).st_mode & 0o777 == mode


def _cell_rows(run_id, cell, method, value=1.0, day=1):
    return [{"run_id": run_id, "time": f"2026-01-{day:02d}T00:00:00+00:00", "scene": "s", "size": "test",
             "sequence": "V", "frame": -1, "method": method, "config": "{}", "bounces": 0, "metric": "rmse",
             "value": value, "unit": "radiance", "status": "ok", "cell": cell},
            {"run_id": run_id, "time": f"2026-01-{day:02d}T00:00:00+00:00", "frame": -1, "metric": "triad_bandwidth",
             "value": 1e10, "status": "run", "cell": ""}]


def test_history_rerun_of_part_of_a_run_keeps_its_other_cells(tmp_path):
    h = tmp_path / "hist.parquet"
    store.append_history(store.to_frame(_cell_rows("r", "k1", "m1") + _cell_rows("r", "k2", "m2")[:1]), h)
    store.append_history(store.to_frame(_cell_rows("r", "k1", "m1", value=3.0)), h)  # re-run with fewer methods
    hist = store.read_history(h)
    got = {(r.cell, r.value) for r in hist[hist.status != "run"].itertuples()}
    assert got == {("k1", 3.0), ("k2", 1.0)}
    assert (hist.status == "run").sum() == 1  # the run-level row is replaced, not duplicated


N_APPENDS = 6  # appends per process and trial
N_TRIALS = 3


def _append_runs(path, prefix, go):
    go.wait(60)
    for i in range(N_APPENDS):
        store.append_history(store.to_frame(_rows(f"{prefix}{i}")), path)


def test_concurrent_appends_lose_no_run(tmp_path):
    """Two processes appending to one history at the same moment (issue 17: without a lock one
    run's rows vanished): every run of both is in the history afterwards."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    for trial in range(N_TRIALS):
        h = tmp_path / f"hist{trial}.parquet"
        go = ctx.Event()
        procs = [ctx.Process(target=_append_runs, args=(h, p, go)) for p in ("a", "b")]
        for p in procs:
            p.start()
        go.set()
        for p in procs:
            p.join(120)
            assert p.exitcode == 0
        runs = store.read_history(h)["run_id"].value_counts()
        assert sorted(runs.index) == sorted(f"{p}{i}" for p in "ab" for i in range(N_APPENDS)), trial
        assert set(runs) == {3}
