"""reports.executors + the parallel paths of reports.cells.run_cells (issue #9), on the fake backend
(testing.fakes): the same error table from local / processes / dask (LocalCluster, 2 workers ×
1 thread, 127.0.0.1), timing parts never overlapping, failing cells recorded, killed workers losing
no finished cell, a re-run redoing only what failed. Every cluster and pool is shut down."""

import json
import os
import signal
import threading
import time
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import replace
from concurrent.futures.process import BrokenProcessPool

import pandas as pd
import pytest

from reports import cells as C
from reports import measure_cell as MC
from reports import runner as R
from reports import executors as X
from reports.pipeline import collect, provenance

FAKE = dict(backend="testing.fakes", plugins=("testing.fakes",))
ERROR_METRICS = ["rmse", "psnr", "rel_mse"]  # what testing.fakes.all_metrics returns


def _cell(**kw):
    d = dict(scene="fake_plane", size="test", kind="V", method="fake", n_frames=3, ref_spp=64, spp_side=1,
             eq_err_spp=(8, 32), **FAKE)
    d.update(kw)
    return C.Cell(**d)


def _sweep():
    """A small smoke-like sweep: two biases × two sequences, a failing cell and an n/a cell."""
    cells = [_cell(config=C.canonical_config({"bias": b}), seed=s) for b in (0.05, 0.2) for s in (0, 1)]
    return cells + [_cell(method="fake_fail"), _cell(kind="VBL", na="BRDFs fixed at precompute")]


def _error_table(results):
    meta = {"run_id": "t", "time": "", "git_sha": "", "versions": {}, "machine": "", "threads": 1,
            "triad_bandwidth": 1e9}
    df = collect(results, meta)
    df = df[df["metric"].isin(ERROR_METRICS)][["cell", "frame", "metric", "value", "noise_floor"]]
    return df.sort_values(["cell", "frame", "metric"]).reset_index(drop=True)


def _files(d):
    """Files of a results folder without in-flight atomic writes (`scenes.io`: a dot-file
    temporary, renamed away a moment later — a snapshot that caught one cannot find it after)."""
    return [p for p in d.iterdir() if p.is_file() and not p.name.startswith(".")]


def _mtimes(d):
    return {p.name: p.stat().st_mtime_ns for p in _files(d)}


class _ThreadsParallel(X.BenchExecutor):
    """A parallel BenchExecutor on threads (in-process, fast): exercises the split/merge runner."""

    name, parallel, workers, slots, timing_in_flight = "threads", True, 3, 3, 1

    def __init__(self):
        self._pool = ThreadPoolExecutor(3)

    def submit(self, fn, /, *args, **kwargs):
        return self._pool.submit(fn, *args, **kwargs)

    def shutdown(self, wait=True, **kw):
        self._pool.shutdown(wait=wait)


def test_share_of_cores_and_bad_input():
    assert X.share_of_cores(8, 3) == 2 and X.share_of_cores(2, 2) == 1 and X.share_of_cores(2, 4) == 1
    assert X.share_of_cores(16, 1) == 16
    with pytest.raises(ValueError):
        X.share_of_cores(0, 1)
    with pytest.raises(ValueError):
        X.make_executor("slurm")
    with pytest.raises(ValueError):
        X.make_executor("processes", scheduler="tcp://127.0.0.1:1")
    with pytest.raises(ValueError):
        X.make_executor("processes", workers=0)
    assert X.make_executor("local").describe() == {"executor": "local", "workers": 1}


def test_worker_thread_share_reaches_torch_and_drjit(monkeypatch):
    """A task applies ``PRTBENCH_THREADS`` (the worker's share, set by the executors) to torch and to
    Dr.Jit's pool (Mitsuba references, G-buffers and visibility run there)."""
    import drjit as dr
    import torch

    from reports import backend

    before = torch.get_num_threads(), dr.thread_count()
    monkeypatch.setenv(C.THREADS_ENV, "3")
    try:
        assert MC.task_threads(_cell()) == 3
        assert MC.task_threads(_cell(threads=2)) == 2  # a cell's own count wins
        assert MC._set_threads(MC.task_threads(_cell()), backend) == 3
        assert (torch.get_num_threads(), dr.thread_count()) == (3, 3)
    finally:
        torch.set_num_threads(before[0])
        dr.set_thread_count(before[1])


def test_split_cells_give_the_same_rows_as_whole_cells(tmp_path, monkeypatch):
    """errors part + timing part, merged == run_cell: bit-identical errors, the same metric set,
    timing parts one at a time while error parts overlap."""
    cells = _sweep()
    whole = R.run_cells(cells, tmp_path / "whole", progress=False)
    intervals = {"timing": [], "errors": []}
    real = MC.run_part

    def spy(cell, part, out_dir, **kw):
        t0 = time.monotonic()
        r = real(cell, part, out_dir, **kw)
        intervals[part].append((t0, time.monotonic()))
        return r

    monkeypatch.setattr(R, "run_part", spy)
    slow = [C.Cell.from_dict({**c.to_dict(), "config": C.canonical_config({**json.loads(c.config), "delay": 0.02})})
            if c.method == "fake" else c for c in cells]
    with _ThreadsParallel() as ex:
        split = R.run_cells(cells, tmp_path / "split", executor=ex, progress=False)
        R.run_cells(slow, tmp_path / "slow", executor=ex, progress=False)
    assert [r.status for r in split] == [r.status for r in whole] == ["ok"] * 4 + ["error", "na"]
    pd.testing.assert_frame_equal(_error_table(split), _error_table(whole))  # seeded: bit-identical
    for a, b in zip(whole[:4], split[:4]):
        metrics = [sorted({(r["metric"], r["frame"]) for r in x.rows}) for x in (a, b)]
        assert metrics[0] == metrics[1]
        assert set(b.info["parts"]) == {"errors", "timing"} and b.info["parts"]["timing"]["executor"] == "threads"
    assert "errors part: RuntimeError: planted failure" in split[4].reason
    t = sorted(intervals["timing"])
    assert len(t) >= 4 and all(t0 >= t1 for (_, t1), (t0, _) in zip(t, t[1:]))  # never two timing parts at once
    e = sorted(intervals["errors"])
    assert any(b0 < a1 for (_, a1), (b0, _) in zip(e, e[1:]))  # error parts do run in parallel
    prov = provenance(split)
    assert {(p["part"], p["executor"]) for p in prov} == {("errors", "threads"), ("timing", "threads")}


class _Dying(_ThreadsParallel):
    """Every timing task of the cells with seed 1 "loses its worker" (the future raises)."""

    def submit_timing(self, fn, /, *args, **kwargs):
        if args[0].seed == 1:
            f = Future()
            f.set_exception(BrokenProcessPool("worker died"))
            return f
        return self.submit(fn, *args, **kwargs)


def test_lost_worker_is_recorded_and_rerun_redoes_only_that(tmp_path):
    cells = _sweep()
    with _Dying() as ex:
        res = R.run_cells(cells, tmp_path, executor=ex, progress=False)
    assert [r.status for r in res] == ["ok", "error", "ok", "error", "error", "na"]
    for r in (res[1], res[3]):  # retried once alone, then recorded with the error
        assert "timing part: worker lost: BrokenProcessPool: worker died" in r.reason
    assert C.load_part(tmp_path, cells[1], "errors").status == "ok"
    before = _mtimes(tmp_path / "cells" / "parts")
    with _ThreadsParallel() as ex:
        res2 = R.run_cells(cells, tmp_path, executor=ex, progress=False)
    assert [r.status for r in res2] == ["ok"] * 4 + ["error", "na"]
    after = _mtimes(tmp_path / "cells" / "parts")
    redone = {k for k in after if after[k] != before.get(k)}
    assert redone == {f"{c.key()}.{p}.json" for c in cells[1:4:2] for p in ["timing"]} | {
        f"{cells[4].key()}.{p}.json" for p in C.PARTS}


def test_processes_executor_same_errors_and_killed_worker(tmp_path):
    cells = _sweep()
    local = R.run_cells(cells, tmp_path / "local", progress=False)
    with X.make_executor("processes", workers=2) as ex:
        assert ex.threads == X.share_of_cores(X.machine_cores(), 2)
        res = R.run_cells(cells, tmp_path / "proc", executor=ex, progress=False)
        pd.testing.assert_frame_equal(_error_table(res), _error_table(local))
        assert [r.status for r in res] == ["ok"] * 4 + ["error", "na"]
        assert {r.info["threads"] for r in res[:4]} == {ex.threads}  # the worker's share, recorded
        assert {r.info["parts"]["errors"]["workers"] for r in res[:4]} == {2}

        # a worker killed mid-sweep: finished cells stay, the lost tasks run again (alone), all finish
        slow = [_cell(config='{"delay":0.4}', seed=s, eq_err_spp=()) for s in range(4)]
        out = tmp_path / "kill"
        box = {}
        th = threading.Thread(target=lambda: box.update(r=R.run_cells(slow, out, executor=ex, progress=False)))
        th.start()
        before = _wait_for_finished(out, th)
        victim = ex.pids()[0]
        os.kill(victim, signal.SIGKILL)
        th.join(60)
        assert victim not in ex.pids()  # a fresh pool took over
    assert not th.is_alive() and [r.status for r in box["r"]] == ["ok"] * 4
    after = _mtimes(out / "cells")
    assert all(after[k] == v for k, v in before.items())  # finished cells were not redone


def test_method_processes_one_process_per_configuration(tmp_path):
    """isolate="method" (the perf suite): each method configuration's cells run in one spawned
    process of their own, after one another, whatever the plan's order (interleaved here, as the
    perf suite's scene-major plan is); results in the plan's order; the same errors as in-process."""
    a, b = (C.canonical_config({"bias": x}) for x in (0.05, 0.2))
    cells = [_cell(config=c, seed=s, eq_err_spp=(), isolate="method") for s in (0, 1) for c in (a, b)]
    cells.append(_cell(kind="VBL", na="BRDFs fixed at precompute", isolate="method"))
    local = R.run_cells([replace(c, isolate=False) for c in cells], tmp_path / "local", progress=False)
    ex = X.MethodProcessExecutor()
    try:
        res = R.run_cells(cells, tmp_path / "m", executor=ex, progress=False)
    finally:
        ex.shutdown()
    assert [r.status for r in res] == ["ok"] * 4 + ["na"]
    assert [r.key for r in res] == [c.key() for c in cells]
    pids = [r.info["pid"] for r in res[:4]]
    assert pids[0] == pids[2] and pids[1] == pids[3] and pids[0] != pids[1] and os.getpid() not in pids
    assert ex.processes == 2  # grouped: not one process per alternation of the plan
    assert {r.info["isolate"] for r in res[:4]} == {"method: this method configuration's process"}
    assert {r.info["executor"] for r in res[:4]} == {"method-processes"}
    pd.testing.assert_frame_equal(_error_table(res), _error_table(local))
    with pytest.raises(ValueError, match="isolate must be"):
        _cell(isolate="cell")


def test_run_suite_uses_method_processes_for_isolate_method(tmp_path):
    """`run --isolate-method` (the perf suite's default) replaces the local executor by one process
    per method configuration; a run of the same cells with `--no-isolate` stays in this process."""
    import run_bench
    from reports import pipeline

    pipeline.TRIAD_ELEMENTS, triad = 1 << 16, pipeline.TRIAD_ELEMENTS
    try:
        for flag, out in (("--isolate-method", "m"), ("--no-isolate", "in")):
            code = run_bench.main(["run", "--suite", "smoke", "--backend", "testing.fakes", "--plugin", "testing.fakes",
                                   "--scenes", "fake_plane", "--methods", "fake", "--out", str(tmp_path / out),
                                   "--no-history", flag, "--no-vertex-renders", "--quiet"])
            assert code == 0
    finally:
        pipeline.TRIAD_ELEMENTS = triad
    prov = {o: json.loads((tmp_path / o / "provenance.json").read_text()) for o in ("m", "in")}
    assert prov["m"] and {p["executor"] for p in prov["m"]} == {"method-processes"}
    assert prov["in"] and {p["executor"] for p in prov["in"]} == {"local"}
    # each timed cell records its method's code key (benchmarks.perf_speedup's "unchanged" test):
    # one code, one key, whichever process ran the cell
    codes = {o: {p["code"] for p in prov[o] if p["status"] != "na"} for o in prov}
    assert codes["m"] == codes["in"] and len(codes["m"]) == 1 and "" not in codes["m"]
    info = {o: [json.loads(f.read_text())["info"] for f in _files(tmp_path / o / "cells")] for o in ("m", "in")}
    pids = {o: {i["pid"] for i in info[o] if "pid" in i} for o in info}
    assert len(pids["m"]) == 1 and os.getpid() not in pids["m"]  # one configuration: one child
    assert pids["in"] == {os.getpid()}


def _wait_for_finished(out, th, timeout=60.0):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout and th.is_alive():
        if (out / "cells").is_dir() and any(p.suffix == ".json" for p in _files(out / "cells")):
            return _mtimes(out / "cells")
        time.sleep(0.05)
    raise AssertionError("no cell finished")


def test_dask_local_cluster_same_errors_failures_kill_and_rerun(tmp_path, monkeypatch):
    monkeypatch.setenv(X.LOCK_DIR_ENV, str(tmp_path))  # the lock file of the --scheduler run below
    cells = _sweep()
    local = R.run_cells(cells, tmp_path / "local", progress=False)
    with X.make_executor("dask", workers=2) as ex:
        info = ex.client.scheduler_info(n_workers=-1)["workers"]
        assert len(info) == 2 and all(a.startswith("tcp://127.0.0.1:") for a in info)
        assert sum(w["resources"].get(X.TIMING_RESOURCE, 0) for w in info.values()) == 1  # one slot per machine
        assert ex.client.scheduler.address.startswith("tcp://127.0.0.1:")
        out = tmp_path / "dask"
        res = R.run_cells(cells, out, executor=ex, progress=False)
        pd.testing.assert_frame_equal(_error_table(res), _error_table(local))  # bit-identical (seeded)
        assert [r.status for r in res] == ["ok"] * 4 + ["error", "na"]
        assert "planted failure" in res[4].reason
        parts = [r.info["parts"] for r in res[:4]]
        assert {p["timing"]["worker"] for p in parts} == {_timing_worker(ex)}  # timing on the slot holder
        assert {p["errors"]["threads"] for p in parts} == {1} and {p["errors"]["workers"] for p in parts} == {2}
        walls = sorted(p["timing"]["wall"] for p in parts)
        assert all(b[0] >= a[1] for a, b in zip(walls, walls[1:]))  # timing parts one at a time

        # re-run: only the failed cell's parts run again
        before = _mtimes(out / "cells" / "parts")
        res2 = R.run_cells(cells, out, executor=ex, progress=False)
        after = _mtimes(out / "cells" / "parts")
        redone = {k for k in after if after[k] != before.get(k)}
        assert redone == {f"{cells[4].key()}.errors.json", f"{cells[4].key()}.timing.json"}
        assert [r.status for r in res2] == [r.status for r in res]

        # a worker killed mid-sweep: finished cells stay, the scheduler re-runs the lost task
        slow = [_cell(config='{"delay":0.4}', seed=s, eq_err_spp=()) for s in range(4)]
        out = tmp_path / "kill"
        box = {}
        th = threading.Thread(target=lambda: box.update(r=R.run_cells(slow, out, executor=ex, progress=False)))
        th.start()
        before = _wait_for_finished(out, th)
        busy = [a for a, ts in ex.client.processing().items() if ts] or list(ex.worker_pids())
        victim = ex.worker_pids()[busy[0]]
        os.kill(victim, signal.SIGKILL)
        th.join(90)
        assert victim not in ex.worker_pids().values()
        assert not th.is_alive() and [r.status for r in box["r"]] == ["ok"] * 4
        after = _mtimes(out / "cells")
        assert all(after[k] == v for k, v in before.items())

        # the command line against an existing scheduler (this cluster's)
        import run_bench
        from reports import pipeline

        pipeline.TRIAD_ELEMENTS, triad = 1 << 16, pipeline.TRIAD_ELEMENTS
        try:
            code = run_bench.main(["run", "--suite", "smoke", "--backend", "testing.fakes", "--plugin", "testing.fakes",
                                   "--scenes", "fake_plane", "--methods", "fake", "--out", str(tmp_path / "cli"),
                                   "--no-history", "--no-isolate", "--no-vertex-renders", "--quiet",
                                   "--executor", "dask", "--scheduler", ex.scheduler])
        finally:
            pipeline.TRIAD_ELEMENTS = triad
        assert code == 0
        prov = json.loads((tmp_path / "cli" / "provenance.json").read_text())
        assert {(p["part"], p["scheduler"], p["workers"]) for p in prov} == {("errors", ex.scheduler, 2),
                                                                              ("timing", ex.scheduler, 2)}
        assert "Where the numbers come from" in (tmp_path / "cli" / "report.html").read_text()
    assert ex.cluster is None  # shut down


def _timing_worker(ex):
    info = ex.client.scheduler_info(n_workers=-1)["workers"]
    (addr,) = [a for a, w in info.items() if w["resources"].get(X.TIMING_RESOURCE)]
    return addr


# -- one real scene -----------------------------------------------------------------------------

@pytest.mark.slow
def test_real_scene_errors_identical_local_and_dask(tmp_path):
    """The oracle on the test-size sphere_plane (2 frames of V): the same error metrics, bit for bit,
    in process (default threads) and on a 2-worker LocalCluster (1 thread per task)."""
    from reports.suites import Suite, plan_cells

    suite = Suite(name="e2e", size="test", scenes=("sphere_plane",), kinds=("V",), dynamic_kinds=(), n_frames=2,
                  ref_spp=16, configs=(("oracle", '{"brdf_samples":4,"light_samples":4}'),), isolate=False)
    cells = plan_cells(suite, methods=["oracle"])
    local = R.run_cells(cells, tmp_path / "local", progress=False)
    with X.make_executor("dask", workers=2) as ex:
        dask = R.run_cells(cells, tmp_path / "dask", executor=ex, progress=False)
    assert [r.status for r in local] == [r.status for r in dask] == ["ok"]
    assert len(_error_table(local)) > 0
    pd.testing.assert_frame_equal(_error_table(dask), _error_table(local))


@pytest.mark.slow
def test_every_method_bit_identical_local_two_threads_and_processes_one_thread(tmp_path, monkeypatch):
    """Issue 17: one small cell per registered method (``testing.small_configs``), run in process
    with 2 torch / Dr.Jit threads and in a 2-worker process pool with 1 thread per worker: every
    error value (rmse, psnr, rel_mse, ssim, flip, ΔE, the sanity gate's) is the same bit for bit.
    The in-process run warms its first frame as a real run does (``PRTBENCH_WARM=1``), the workers
    do not: warming (compiling block sizes on dummy blocks) must change no value either.
    No precompute cache, so both executors precompute; the references are the shared cache's."""
    import torch
    import drjit as dr

    from reports import precompute_cache
    from reports.cells import canonical_config
    from testing.small_configs import CASES, project_methods

    monkeypatch.setenv(precompute_cache.ENV_OFF, "1")
    cells = [C.Cell(scene=scene, size="test", kind="P" if scene == "creature" and method == "zh_shadow" else "L",
                    method=method, config=canonical_config(config), n_frames=2, ref_spp=16, spp_side=1,
                    save_images=False) for method, scene, config in CASES.values()]
    assert {c.method for c in cells} == project_methods()
    torch_before, dr_before = torch.get_num_threads(), dr.thread_count()
    monkeypatch.setenv(C.THREADS_ENV, "2")  # what a local run on a 2-core machine uses
    monkeypatch.setenv(MC.WARM_ENV, "1")  # as a real run: the warm-up frame compiles the neighbour blocks
    try:
        local = R.run_cells(cells, tmp_path / "local", progress=False)
    finally:
        torch.set_num_threads(torch_before)
        dr.set_thread_count(dr_before)
        monkeypatch.delenv(C.THREADS_ENV)
    monkeypatch.setenv(MC.WARM_ENV, "0")  # the workers do not: warming changes no value
    with X.ProcessesExecutor(2, threads=1) as ex:
        proc = R.run_cells(cells, tmp_path / "proc", executor=ex, progress=False)
    assert [r.status for r in local] == [r.status for r in proc] == ["ok"] * len(cells), \
        [r.reason for r in local + proc if r.status != "ok"]
    assert {r.info["threads"] for r in local} == {2}
    assert {r.info["parts"]["errors"]["threads"] for r in proc} == {1}
    a, b = _scores(local), _scores(proc)
    rmse = a[(a["metric"] == "rmse") & (a["frame"] >= 0)]
    assert len(rmse) == 2 * len(cells) and set(rmse["cell"]) == {c.key() for c in cells}  # both frames scored
    m = a.merge(b, on=["cell", "method", "frame", "metric"], how="outer", suffixes=("_local", "_proc"))
    same = (m["value_local"] == m["value_proc"]) | (m["value_local"].isna() & m["value_proc"].isna())
    bad = m[~same].assign(d=lambda t: (t["value_local"] - t["value_proc"]).abs())
    assert bad.empty, "error values differ: " + "; ".join(
        f"{k}: {len(g)} values ({', '.join(sorted(set(g['metric'])))}), max |Δrmse| "
        f"{g.loc[g['metric'] == 'rmse', 'd'].max():.3g}" for k, g in bad.groupby("method"))
    pd.testing.assert_frame_equal(a, b, check_exact=True)  # and the noise floors


def _scores(results):
    """Every error value of a run (the rows scored against a reference carry its noise floor)."""
    meta = {"run_id": "t", "time": "", "git_sha": "", "versions": {}, "machine": "", "threads": 1,
            "triad_bandwidth": 1e9}
    df = collect(results, meta)
    df = df[df["noise_floor"].notna()][["cell", "method", "frame", "metric", "value", "noise_floor"]]
    return df.sort_values(["cell", "frame", "metric"]).reset_index(drop=True)


def test_bad_warm_setting_is_one_clear_error_before_any_cell(tmp_path, monkeypatch):
    monkeypatch.setenv(MC.WARM_ENV, "yes")
    with pytest.raises(ValueError, match="PRTBENCH_WARM must be 0 or 1"):
        R.run_cells([], tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


_ORPHAN_PARENT = r"""
import os, sys, time
from reports import executors as X
ex = X.{cls}()
fut = ex.submit({submit})
for _ in range(200):
    if ex.pids():
        break
    time.sleep(0.05)
print(" ".join(str(p) for p in ex.pids()), flush=True)
time.sleep(600)
"""


@pytest.mark.parametrize("cls, submit", [("ProcessesExecutor", "time.sleep, 600"),
                                         ("MethodProcessExecutor", "time.sleep, 600")])
def test_pool_workers_end_with_a_killed_parent(cls, submit):
    """A run killed with SIGKILL cannot shut its pool down: its workers notice the parent is gone
    (`executors._exit_with_parent`) and exit within a few seconds instead of running on as orphans."""
    import subprocess
    import sys

    if cls == "MethodProcessExecutor":   # its submit groups by the cell's (method, config): a stand-in cell
        submit = "X._orphan_test_sleep, X._OrphanCell()"
    code = _ORPHAN_PARENT.format(cls=cls, submit=submit)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([os.getcwd(), os.environ.get("PYTHONPATH", "")])}
    p = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True, env=env)
    try:
        pids = [int(x) for x in p.stdout.readline().split()]
        assert pids, "the pool started no worker"
    finally:
        p.kill()
        p.wait()

    def alive(pid: int) -> bool:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return False
        with open(f"/proc/{pid}/stat") as f:          # a zombie has exited
            return f.read().split(")")[-1].split()[0] != "Z"

    deadline = time.monotonic() + 15 * X.ORPHAN_POLL_S + 10
    while any(alive(q) for q in pids) and time.monotonic() < deadline:
        time.sleep(0.2)
    left = [q for q in pids if alive(q)]
    for q in left:
        os.kill(q, signal.SIGKILL)
    assert not left, f"pool workers outlived their killed parent: {left}"
