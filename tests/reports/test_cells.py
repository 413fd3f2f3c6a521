"""reports.cells / reports.suites with the fake backend (testing.fakes): measuring, n/a and failed
cells, resume after a kill, process isolation, per-vertex error splatting, the capability matrix."""
import dataclasses
import json
import math
import pickle

import numpy as np
import pytest
import torch

from reports import cells as C
from reports import measure_cell as MC
from reports import runner as R
from testing import fakes
from reports.suites import NIGHTLY, SMOKE, Suite, plan_cells

FAKE = dict(backend="testing.fakes", plugins=("testing.fakes",))
# Fake method error: truth·(1+bias) vs a noisy reference → RMSE² ≈ bias²·mean(truth²) + floor².
# The floor term has a few % sampling error on 63 pixels × 3 channels → 15 % tolerance.
RMSE_RTOL = 0.15


def _cell(**kw):
    d = dict(scene="fake_plane", size="test", kind="V", method="fake", n_frames=4, ref_spp=64, spp_side=1,
             eq_err_spp=(8, 32), **FAKE)
    d.update(kw)
    return C.Cell(**d)


def test_cell_is_picklable_and_key_identifies_it():
    c = _cell(config=C.canonical_config({"bias": 0.1}))
    assert pickle.loads(pickle.dumps(c)) == c
    assert C.Cell.from_dict(json.loads(json.dumps(c.to_dict()))) == c
    assert c.key() == _cell(config='{"bias":0.1}').key()
    assert c.key() != _cell(config='{"bias":0.2}').key()
    assert c.key() == _cell(config='{"bias":0.1}', isolate=True).key()  # isolation measures the same thing
    with pytest.raises(ValueError):
        _cell(kind="X")
    with pytest.raises(ValueError):
        _cell(score_frames=(9,))


def test_run_cell_measures_everything(tmp_path):
    bias = 0.1
    r = MC.run_cell(_cell(config=C.canonical_config({"bias": bias})), tmp_path, progress=False)
    assert r.status == "ok", r.reason
    summ = {row["metric"]: row for row in r.rows if row["frame"] == -1}
    for m in ("precompute_time", "render_time_median", "render_time_iqr", "fps", "rmse", "psnr", "memory_bytes",
              "bytes_per_frame", "harness_peak_rss_bytes", "eq_error_speedup", "mitsuba_time_eq_error"):
        assert m in summ, m
    assert summ["memory_bytes"]["value"] == 1024  # 256 float32 coefficients
    assert summ["timed_frames"]["value"] == 3  # 4 frames, warm-up excluded
    assert len([row for row in r.rows if row["metric"] == "render_time"]) == 4
    # process CPU per frame beside the wall times, and the load at the cell's start and end
    assert len(r.info["frame_cpu_times"]) == len(r.info["frame_times"]) == 4
    assert all(c >= 0 for c in r.info["frame_cpu_times"]) and len(r.info["loadavg_1min"]) == 2
    # RMSE vs the closed form; every score carries the reference's noise floor
    per_frame = [row for row in r.rows if row["metric"] == "rmse" and row["frame"] >= 0]
    frames = fakes.make_sequence(fakes.get_scene("fake_plane"), "V", 4, 0)
    cov = fakes._coverage()
    for row, fr in zip(per_frame, frames):
        t = fakes.truth(fr)[cov]
        expect = math.sqrt(bias**2 * float((t**2).mean()) + row["noise_floor"] ** 2)
        assert row["value"] == pytest.approx(expect, rel=RMSE_RTOL)
        assert row["noise_floor"] == pytest.approx(fakes.SIGMA / 8, rel=0.2)  # σ/sqrt(spp), spp = 64
    # calibration fit: the fake renderer converges exactly as σ/sqrt(spp) → c ≈ σ
    fit = r.info["convergence_fit"]
    assert fit["c"] == pytest.approx(fakes.SIGMA, rel=0.2)
    with np.load(tmp_path / r.artifacts["images"]) as z:
        assert z["reference"].shape == (8, 8, 3) and z["method"].shape == (8, 8, 3)
        assert z["vertex_sq_error"].shape == (4,) and np.isfinite(z["vertex_sq_error"]).any()


def test_na_and_failing_cells_are_recorded(tmp_path):
    na = MC.run_cell(_cell(kind="VBL", na="BRDFs fixed at precompute"), tmp_path)
    assert na.status == "na" and na.reason == "BRDFs fixed at precompute" and na.rows == []
    bad = MC.run_cell(_cell(method="fake_fail"), tmp_path, progress=False)
    assert bad.status == "error" and "planted failure" in bad.reason and "Traceback" in bad.info["traceback"]
    assert C.result_path(tmp_path, _cell(method="fake_fail")).exists()
    assert not C.is_finished(tmp_path, _cell(method="fake_fail"))  # failed cells are retried on resume


class _Killed(BaseException):
    """Stands in for SIGINT/SIGKILL in the middle of a cell."""


def test_killed_run_resumes_without_recomputing(tmp_path, monkeypatch):
    cells = [_cell(seed=s, eq_err_spp=()) for s in range(4)]
    calls = []
    real = MC._measure

    def counting(cell, out_dir, progress):
        calls.append(cell.seed)
        if cell.seed == 2 and len(calls) == 3:
            raise _Killed()
        return real(cell, out_dir, progress)

    monkeypatch.setattr(MC, "_measure", counting)
    with pytest.raises(_Killed):
        R.run_cells(cells, tmp_path, progress=False)
    assert calls == [0, 1, 2]
    done = sorted(p.name for p in (tmp_path / "cells").iterdir())
    assert done == sorted(f"{c.key()}.json" for c in cells[:2])  # no partial file for the killed cell
    res = R.run_cells(cells, tmp_path, progress=False)
    assert calls == [0, 1, 2, 2, 3]  # only the unfinished cells ran again
    assert [r.status for r in res] == ["ok"] * 4
    assert [r.key for r in res] == [c.key() for c in cells]


def test_run_cells_with_a_process_pool_like_executor(tmp_path):
    from concurrent.futures import ThreadPoolExecutor

    cells = [_cell(seed=s, eq_err_spp=()) for s in range(3)]
    with ThreadPoolExecutor(2) as ex:
        res = R.run_cells(cells, tmp_path, executor=ex, max_in_flight=2, progress=False)
    assert [r.key for r in res] == [c.key() for c in cells] and all(r.status == "ok" for r in res)


def test_isolated_cell_runs_in_a_spawned_child(tmp_path):
    import os

    r = MC.run_cell(_cell(isolate=True, eq_err_spp=()), tmp_path, progress=False)
    assert r.status == "ok", r.reason
    assert r.info["pid"] != os.getpid()
    rss = [row["value"] for row in r.rows if row["metric"] == "peak_rss_bytes"]
    assert len(rss) == 1 and rss[0] > 10 * 2**20  # a python + torch process holds > 10 MiB


def test_splat_vertex_error_constant_and_hand_example():
    gb = fakes.make_gbuffer(None, None, 2)
    V, F = fakes.geometry(None, None)
    mask = gb.coverage
    const = MC.splat_vertex_error(torch.full((8, 8), 0.25), gb, F, len(V), mask)
    seen = torch.isfinite(const)
    assert seen.any() and torch.allclose(const[seen], torch.tensor(0.25, dtype=torch.float64))
    # one scored pixel only: its error lands (normalised) on exactly its triangle's vertices
    m1 = torch.zeros(8, 8, dtype=torch.bool)
    m1[3, 5] = True
    e = torch.zeros(8, 8)
    e[3, 5] = 2.0
    v = MC.splat_vertex_error(e, gb, F, len(V), m1)
    tri = set(F[gb.face.view(8, 8, 4)[3, 5, 0]].tolist())
    assert set(torch.nonzero(torch.isfinite(v)).flatten().tolist()) == tri
    assert torch.allclose(v[list(tri)], torch.tensor(2.0, dtype=torch.float64))
    with pytest.raises(ValueError):
        MC.splat_vertex_error(torch.zeros(4, 4), gb, F, len(V), mask)


def test_plan_capability_matrix_and_bounces():
    suite = Suite(name="t", size="test", kinds=("V", "VBL"), n_frames=3, ref_spp=16,
                  scenes=("fake_plane", "fake_creature"), extra_bounces=(1, 2, C.FULL), isolate=False)
    cells = plan_cells(suite, methods=["fake", "fake_gi"], **FAKE)
    by = {(c.scene, c.method, c.kind, c.bounces): c.na for c in cells}
    assert by[("fake_plane", "fake", "V", 0)] is None
    assert by[("fake_plane", "fake", "VBL", 0)] == "BRDFs fixed at precompute"
    assert ("fake_plane", "fake", "V", 1) not in by  # extra bounces only for methods with max_bounces > 0
    assert by[("fake_plane", "fake_gi", "VBL", 1)] is None
    assert by[("fake_plane", "fake_gi", "V", 2)] == "at most 1 bounce(s)"
    assert by[("fake_plane", "fake_gi", "V", C.FULL)] == "at most 1 bounce(s)"
    assert by[("fake_creature", "fake", "P", 0)] == "static geometry only"  # dynamic scene gets P
    assert ("fake_plane", "fake", "P", 0) not in by
    # a method that renders interreflection is also scored against full GI (Sun 2007 Fig. 11)
    full = {(c.method, c.bounces): c.score_full_gi for c in cells if c.scene == "fake_plane" and c.kind == "VBL"}
    assert full == {("fake", 0): False, ("fake_gi", 0): True, ("fake_gi", 1): True, ("fake_gi", 2): True,
                    ("fake_gi", C.FULL): False}
    from reports.suites import reference_jobs
    jobs = {(j[0], j[2], j[5]) for j in reference_jobs(cells)}
    assert ("fake_plane", "VBL", C.FULL) in jobs  # no in-scope FULL cell, but the full-GI scores need it
    with pytest.raises(ValueError):
        plan_cells(suite, methods=["no_such_method"], **FAKE)
    # bounce_kinds: the extra bounce counts only on those kinds (not planned at all elsewhere)
    cut = plan_cells(dataclasses.replace(suite, bounce_kinds=("V",)), methods=["fake", "fake_gi"], **FAKE)
    cut_by = {(c.scene, c.method, c.kind, c.bounces): c.na for c in cut}
    assert {k for k in cut_by if k[3] != 0} == {k for k in by if k[3] != 0 and k[2] == "V"}
    assert {k: v for k, v in cut_by.items() if k[3] == 0} == {k: v for k, v in by.items() if k[3] == 0}


def test_cell_scored_against_full_gi(tmp_path):
    c = _cell(method="fake_gi", bounces=1, kind="V", score_full_gi=True, eq_err_spp=())
    fakes.WITH_BOUNCES_CALLS.clear()
    r = MC.run_cell(c, tmp_path, progress=False)
    assert r.status == "ok", r.reason
    assert fakes.WITH_BOUNCES_CALLS == [1]  # the method was told how many bounces to render
    same = {row["frame"]: row["value"] for row in r.rows if row["metric"] == "rmse"}
    full = {row["frame"]: row["value"] for row in r.rows if row["metric"] == "rmse_full_gi"}
    assert set(full) == set(same) and -1 in full
    # the fake backend's truth does not depend on the bounce count and references are seeded per
    # frame, so the full-GI reference is the same image: the two scores must agree exactly
    for f in same:
        assert full[f] == pytest.approx(same[f], rel=1e-6)
    plain = MC.run_cell(_cell(method="fake_gi", bounces=1, kind="V", eq_err_spp=()), tmp_path / "b", progress=False)
    assert not [row for row in plain.rows if row["metric"] == "rmse_full_gi"]


def test_suite_definitions_follow_the_issue():
    assert SMOKE.size == "test" and set(SMOKE.kinds) == {"V", "VBL", "L", "E"} and 2 <= SMOKE.n_frames <= 3
    assert 64 <= SMOKE.ref_spp <= 256 and len(SMOKE.scenes) <= 2 and SMOKE.isolate
    assert "bunny" in SMOKE.scenes  # a real scan under a captured probe (issue 15)
    assert NIGHTLY.size == "bench" and {"V", "VB", "VBL", "L", "E", "VL"} <= set(NIGHTLY.kinds)
    assert "P" in NIGHTLY.dynamic_kinds and set(NIGHTLY.extra_bounces) == {1, 2, C.FULL}
    assert set(NIGHTLY.bounce_kinds) == {"V", "L"}  # Sun 2007 Fig. 11 (V) and relighting with interreflection (L)
    assert "bunny" in NIGHTLY.scenes and "creature" in NIGHTLY.scenes  # a real scan; an articulated scene


def test_precompute_cache_reports_the_original_time(tmp_path, monkeypatch):
    """Cells of one (scene, method, config) share a precomputation (reports.precompute_cache): the
    second cell loads it, reports the original seconds and says it was cached; the image is the same."""
    monkeypatch.setenv("PRTBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("PRTBENCH_NO_PRECOMPUTE_CACHE", raising=False)
    fakes.PRECOMPUTE_CALLS.clear()
    cfg = C.canonical_config({"precompute_delay": 0.2})
    a = MC.run_cell(_cell(method="fake_cached", config=cfg, kind="V", eq_err_spp=()), tmp_path / "a")
    b = MC.run_cell(_cell(method="fake_cached", config=cfg, kind="VBL", eq_err_spp=()), tmp_path / "b")
    assert a.status == b.status == "ok", (a.reason, b.reason)
    assert fakes.PRECOMPUTE_CALLS == ["fake_plane"]  # computed once
    sa = {r["metric"]: r["value"] for r in a.rows if r["frame"] == -1}
    sb = {r["metric"]: r["value"] for r in b.rows if r["frame"] == -1}
    assert "precompute_cached" not in sa and sb["precompute_cached"] == 1
    assert sb["precompute_time"] == sa["precompute_time"] >= 0.2  # the original seconds, not the load
    assert sb["memory_bytes"] == sa["memory_bytes"] == 1024
    # another config is another precomputation; the switch turns the cache off
    MC.run_cell(_cell(method="fake_cached", config=C.canonical_config({"precompute_delay": 0.0}), eq_err_spp=()),
               tmp_path / "c")
    monkeypatch.setenv("PRTBENCH_NO_PRECOMPUTE_CACHE", "1")
    MC.run_cell(_cell(method="fake_cached", config=cfg, kind="VBL", eq_err_spp=()), tmp_path / "d")
    assert fakes.PRECOMPUTE_CALLS == ["fake_plane"] * 3


def test_corrupt_precompute_cache_entry_is_recomputed(tmp_path, monkeypatch):
    from reports import precompute_cache as PC

    monkeypatch.setenv("PRTBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("PRTBENCH_NO_PRECOMPUTE_CACHE", raising=False)
    fakes.PRECOMPUTE_CALLS.clear()
    m = fakes.FakeCachedMethod(precompute_delay=0.0)
    scene = fakes.get_scene("fake_plane")
    path = PC.cache_path(scene, m, C.canonical_config(m.config))
    path.write_bytes(b"not a pickle")
    with pytest.warns(UserWarning, match="ignoring precompute cache"):
        info = PC.precompute(m, scene, C.canonical_config(m.config))
    assert not info["cached"] and fakes.PRECOMPUTE_CALLS == ["fake_plane"]
    m2 = fakes.FakeCachedMethod(precompute_delay=0.0)
    assert PC.precompute(m2, scene, C.canonical_config(m.config))["cached"]
    assert torch.equal(m2.coeffs, torch.arange(256, dtype=torch.float32))


def test_progress_without_a_terminal_prints_one_line_per_cell(tmp_path, capsys):
    """A cron or CI log is not a terminal (tqdm stays silent): each finished cell gets one line."""
    cells = [_cell(seed=s, eq_err_spp=()) for s in (0, 1)] + [_cell(kind="P", na="static geometry only")]
    R.run_cells(cells, tmp_path, progress=True)
    lines = [l for l in capsys.readouterr().err.splitlines() if l.startswith("[prtbench] ")]
    assert len(lines) == 3, lines
    assert lines[0].startswith("[prtbench] 1/3 fake/fake_plane/V/b0: ok")
    assert lines[2].startswith("[prtbench] 3/3 fake/fake_plane/P/b0: na")
    R.run_cells(cells, tmp_path, progress=False)  # progress off: silent
    assert "[prtbench]" not in capsys.readouterr().err


def test_fresh_calibration_times_mitsuba_in_the_run_not_the_cache(tmp_path, monkeypatch):
    """A cell with ``fresh_calibration`` (the perf suite) fits Mitsuba's convergence on renders timed
    now (``use_cache=False``), not on the render times the reference cache recorded; other cells
    keep the recorded times and their keys. The recorded time here is 1000× the fresh one, as a
    cache entry rendered on a busy machine would be."""
    def render(scene, frame, *, bounces, spp, seed, spp_side=1, use_cache=True):
        ref = fakes_render(scene, frame, bounces=bounces, spp=spp, seed=seed, spp_side=spp_side)
        if use_cache:
            ref.meta["render_seconds"] *= 1000
        return ref

    fakes_render = fakes.render_reference
    monkeypatch.setattr(fakes, "render_reference", render)
    monkeypatch.setattr(fakes, "timed_reference", lambda scene, frame, **kw: (
        lambda r: (r, fakes.reference_seconds(r)))(render(scene, frame, **kw)))
    cfg = C.canonical_config({"bias": 0.1})
    cached = MC.run_cell(_cell(config=cfg), tmp_path / "cached", progress=False)
    fresh = MC.run_cell(_cell(config=cfg, fresh_calibration=True), tmp_path / "fresh", progress=False)
    assert cached.status == fresh.status == "ok"
    t_cached, t_fresh = (r.info["convergence_fit"]["t_spp"] for r in (cached, fresh))
    assert t_cached == pytest.approx(1000 * t_fresh, rel=1e-6)
    assert _cell(config=cfg).key() == _cell(config=cfg, fresh_calibration=False).key()
    assert _cell(config=cfg).key() != _cell(config=cfg, fresh_calibration=True).key()
    from reports.suites import PERF
    perf = dataclasses.replace(PERF, scenes=("fake_plane",), configs=())
    assert all(c.fresh_calibration for c in plan_cells(perf, backend="testing.fakes", plugins=("testing.fakes",)))


def test_each_cell_makes_its_own_warm_up_calls(tmp_path, monkeypatch):
    """A cell's warm-up frame starts with no record of earlier cells' warm-up calls
    (`measure_cell.forget_warm_up_calls`): `warm_blocks` makes each call once per process, keyed by a
    signature that misses shapes inside untyped arguments, so a later cell found its calls "made" and
    compiled in a timed frame (session 22, triple product creature L after chess)."""
    import contextlib

    from methods.core import fused

    monkeypatch.setenv("PRTBENCH_WARM", "1")
    fused._warmed.add("an earlier cell's call")
    seen = []
    real = MC.warming

    @contextlib.contextmanager
    def spy(on=True):
        if on:
            seen.append(set(fused._warmed))
        with real(on):
            yield

    monkeypatch.setattr(MC, "warming", spy)
    MC.run_cell(_cell(), tmp_path, progress=False)
    assert seen == [set()]                                 # one warm-up frame, and it started afresh


def test_previous_frame_freed_after_the_timer_stops(tmp_path, monkeypatch):
    """Session 42: a method that keeps its last G-buffer (frame state, `frame_cost`'s statistics) drops it
    inside its next render; the harness keeps the previous frame's G-buffer and image referenced until that
    frame's timer stops, so their memory is freed outside the timed region (SH PRT E: 4-6 ms munmap in 5 of
    90 steady frames before). Each render ends with the previous frame's G-buffer and image still alive, and
    they are gone once the next frame was timed."""
    import weakref

    alive_in_render, gone_after = [], []
    refs: list = []
    real = fakes.FakeMethod.render

    def keeping(self, frame, gbuffer):
        self._last = gbuffer                               # drops the previous frame's G-buffer here
        img = real(self, frame, gbuffer)
        alive_in_render.append([r() is not None for r in refs[-2:]])
        gone_after.append([r() is None for r in refs[2:-2]])   # (frame 0's: the scored frame, kept for its artifacts)
        refs.extend([weakref.ref(gbuffer), weakref.ref(img)])
        return img

    monkeypatch.setattr(fakes.FakeMethod, "render", keeping)
    MC.run_cell(_cell(n_frames=5, score_frames=(0,)), tmp_path, progress=False)   # the scoring keeps no frame
    assert len(alive_in_render) == 5
    assert alive_in_render[0] == [] and all(a == [True, True] for a in alive_in_render[1:])
    assert all(all(g) for g in gone_after), gone_after     # nothing older than the previous frame leaks
    assert sum(map(len, gone_after)) == 2 + 4              # frames 1 and 2 checked after frames 3 and 4


@pytest.mark.parametrize("enabled", [True, False])
def test_frames_render_with_the_garbage_collector_paused(tmp_path, monkeypatch, enabled):
    """Session 40 (`measure_cell.gc_paused`, timeit's convention): every frame — warm-up and timed —
    renders with Python's cyclic collector off, and the collector is back as it was after each frame
    (on between frames, where the harness rasterises the next G-buffer; left off when it was off)."""
    import gc

    seen, between = [], []
    real = fakes.FakeMethod.render

    def spy(self, frame, gbuffer):
        seen.append(gc.isenabled())
        return real(self, frame, gbuffer)

    real_gb = fakes.make_gbuffer

    def gb_spy(*a, **k):
        between.append(gc.isenabled())
        return real_gb(*a, **k)

    monkeypatch.setattr(fakes.FakeMethod, "render", spy)
    monkeypatch.setattr(fakes, "make_gbuffer", gb_spy)
    was = gc.isenabled()
    try:
        (gc.enable if enabled else gc.disable)()
        MC.run_cell(_cell(), tmp_path, progress=False)
        assert gc.isenabled() is enabled
    finally:
        (gc.enable if was else gc.disable)()
    assert seen == [False] * 4
    assert len(between) >= 4 and all(b is enabled for b in between)
