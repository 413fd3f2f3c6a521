"""reports.regress: planted regressions are flagged, unchanged re-runs are not (at the frame counts
the suites time: 2 frames in smoke, 4 in nightly); each cell is compared with the most recent
earlier run that has it."""
import numpy as np
import pandas as pd
import pytest

from reports import regress, store

# Noise of unchanged re-runs on a machine reserved for the benchmark (synthetic): every frame time
# scatters log-normally by FRAME_NOISE, and each run as a whole by RUN_NOISE (load, clocks).
FRAME_NOISE = 0.02
RUN_NOISE = 0.01
TIMED = {"smoke": 2, "nightly": 4}  # timed frames per cell (warm-up frame excluded)
N_PAIRS = 2000  # simulated run pairs per rate estimate
MAX_FALSE_ALARM = 0.02  # flags (either way) per cell and unchanged re-run, at the noise above
MIN_POWER = 0.9  # share of 10 % slowdowns caught, at the noise above
CELLS = [("sphere_plane", "a"), ("sphere_plane", "b"), ("chess", "a"), ("chess", "b")]


def _run(run_id, day, rng, *, n_timed=2, slow=1.0, err=1.0, mem=1000.0, cells=CELLS, threads=2, machine=None,
         frame_noise=FRAME_NOISE, run_noise=RUN_NOISE, other_cpu=None):
    """One synthetic run: cell (chess, a) is ``slow`` × slower, (sphere_plane, b) has ``err`` × the RMSE."""
    rows = []
    base = {"run_id": run_id, "time": f"2026-01-{day:02d}T00:00:00+00:00", "git_sha": "x", "versions": "{}",
            "machine": machine or "host | Some CPU | 2 cpu | Linux", "threads": threads, "size": "test",
            "config": "{}", "bounces": 0, "status": "ok", "reason": ""}
    shift = np.exp(run_noise * rng.standard_normal())
    for scene, method in cells:
        ident = {**base, "scene": scene, "sequence": "V", "method": method, "cell": f"{scene}-{method}"}
        f = slow if (scene, method) == ("chess", "a") else 1.0
        e = err if (scene, method) == ("sphere_plane", "b") else 1.0
        t = 0.01 * f * shift * np.exp(frame_noise * rng.standard_normal(n_timed + 1))
        t[0] *= 3  # warm-up frame: never compared
        rows += [{**ident, "frame": i, "metric": "render_time", "value": v, "unit": "s"} for i, v in enumerate(t)]
        rows += [{**ident, "frame": -1, "metric": "rmse", "value": 0.05 * e, "unit": "radiance", "noise_floor": 0.004},
                 {**ident, "frame": -1, "metric": "psnr", "value": 30.0 - 20 * np.log10(e), "unit": "dB",
                  "noise_floor": 0.004},
                 {**ident, "frame": -1, "metric": "memory_bytes", "value": mem, "unit": "B"}]
        if other_cpu is not None:  # the CPU the rest of the machine used while the cell was timed
            rows.append({**ident, "frame": -1, "metric": "other_cpu_cores", "value": other_cpu, "unit": "cores"})
    rows.append({**base, "scene": "", "size": "", "config": "", "status": "run", "frame": -1,
                 "metric": "triad_bandwidth", "value": 1e10, "cell": ""})
    return store.to_frame(rows)


def _flags(changes):
    return {(r.scene, r.method, r.metric, r.flag) for r in regress.flagged(changes).itertuples()}


@pytest.mark.parametrize("suite", sorted(TIMED))
def test_planted_slowdown_and_error_rise_are_flagged(suite):
    rng = np.random.default_rng(0)
    n = TIMED[suite]
    hist = pd.concat([_run(f"{suite}-r1", 1, rng, n_timed=n), _run(f"{suite}-r2", 2, rng, n_timed=n)])
    new = _run(f"{suite}-r3", 3, rng, n_timed=n, slow=1.10, err=1.05)
    ch = regress.compare_with_history(hist, new)
    assert set(ch["baseline"]) == {f"{suite}-r2"}
    assert _flags(ch) == {("chess", "a", "render_time", "regression"),
                          ("sphere_plane", "b", "rmse", "regression"), ("sphere_plane", "b", "psnr", "regression")}
    assert "!!" in regress.format_changes(ch, only_flagged=True)


def _frame_times(rng, n_timed, slow=1.0):
    """(N_PAIRS, n_timed) timed frames of one cell in N_PAIRS runs, noise as in ``_run``."""
    shift = np.exp(RUN_NOISE * rng.standard_normal((N_PAIRS, 1)))
    return 0.01 * slow * shift * np.exp(FRAME_NOISE * rng.standard_normal((N_PAIRS, n_timed)))


@pytest.mark.parametrize("suite", sorted(TIMED))
def test_ten_percent_slowdowns_are_caught_and_unchanged_reruns_are_not(suite):
    """Rates of the frame-time rule over many simulated run pairs at the noise of a reserved
    machine (FRAME_NOISE, RUN_NOISE)."""
    rng = np.random.default_rng(1)
    n = TIMED[suite]
    old, same, slow = _frame_times(rng, n), _frame_times(rng, n), _frame_times(rng, n, slow=1.10)
    alarms = sum(regress.time_change(a, b)[0] != "" for a, b in zip(old, same))  # regressions or improvements
    caught = sum(regress.time_change(a, b)[0] == "regression" for a, b in zip(old, slow))
    assert alarms / N_PAIRS <= MAX_FALSE_ALARM
    assert caught / N_PAIRS >= MIN_POWER


def test_the_old_rank_test_could_not_fire():
    """Why the rule changed (issue 17): a one-sided Mann-Whitney U with 2 vs 2 frames has p >= 1/6
    even when every new frame is 27x slower; the ratio rule flags it."""
    from scipy.stats import mannwhitneyu

    old, new = np.array([0.010, 0.011]), np.array([0.27, 0.28])
    assert mannwhitneyu(new, old, alternative="greater").pvalue == pytest.approx(1 / 6)
    assert regress.time_change(old, new)[0] == "regression"


def test_time_rule():
    a = np.array([0.0100, 0.0101, 0.0099, 0.0100])
    assert regress.time_change(a, 1.10 * a)[0] == "regression"
    assert regress.time_change(a, a / 1.10)[0] == "improvement"
    assert regress.time_change(a, 1.03 * a)[0] == ""  # under TIME_REL
    # frames of one run scattering by ±25 %: a 10 % change of the median is inside that spread
    wide = np.array([0.0080, 0.0120])
    flag, change, thr = regress.time_change(wide, 1.10 * wide)
    assert flag == "" and change == pytest.approx(0.10) and thr == pytest.approx(regress.TIME_SPREAD_K * 0.2)
    # one slow outlier frame in a 2-frame cell (an interrupt, another job) is not a regression...
    assert regress.time_change(np.array([0.0100, 0.0101]), np.array([0.0100, 0.0150]))[0] == ""
    # ... but two slow frames are
    assert regress.time_change(np.array([0.0100, 0.0101]), np.array([0.0111, 0.0112]))[0] == "regression"
    # microseconds: a 50 % change of 20 µs is timer jitter, not a regression
    assert regress.time_change(np.array([2e-5, 2e-5]), np.array([3e-5, 3e-5]))[0] == ""
    with pytest.raises(ValueError, match="at least one"):
        regress.time_change(a, np.array([]))
    with pytest.raises(ValueError, match="finite"):
        regress.time_change(a, np.array([np.nan, 1.0]))


def test_times_of_other_threads_or_machines_are_not_compared():
    rng = np.random.default_rng(5)
    old = _run("r1", 1, rng)
    for new in (_run("r2", 2, rng, slow=2.0, threads=1),
                _run("r2", 2, rng, slow=2.0, machine="host | Other CPU | 64 cpu | Linux")):
        ch = regress.compare_runs(old, new)
        t = ch[(ch.metric == "render_time") & (ch.scene == "chess") & (ch.method == "a")]
        assert len(t) == 1 and t.iloc[0]["flag"] == "" and t.iloc[0]["test"].startswith("not compared")
    # another host of the same machine kind is compared
    ch = regress.compare_runs(old, _run("r2", 2, rng, slow=2.0, machine="other-host | Some CPU | 2 cpu | Linux"))
    assert ("chess", "a", "render_time", "regression") in _flags(ch)


def test_times_measured_beside_other_work_are_not_compared():
    """A run whose cells were timed while other processes kept the machine busy (``other_cpu_cores``
    above CONTENTION_MAX, in either run) does not flag its frame times — neither the slowdown the load
    caused nor an improvement against a loaded baseline; errors are still compared. Below the bound,
    or where a run predates the measurement (no row, or NaN), times compare as before."""
    rng = np.random.default_rng(7)
    quiet = _run("r1", 1, rng, other_cpu=0.02)
    loaded = _run("r2", 2, rng, slow=2.0, err=1.05, other_cpu=1.1)
    for old, new in ((quiet, loaded), (loaded, _run("r3", 3, rng, other_cpu=0.0))):
        ch = regress.compare_runs(old, new)
        t = ch[(ch.metric == "render_time") & (ch.scene == "chess") & (ch.method == "a")]
        assert len(t) == 1 and t.iloc[0]["flag"] == "", t
        assert t.iloc[0]["test"].startswith("not compared: other processes used 1.10 cores")
    assert ("sphere_plane", "b", "rmse", "regression") in _flags(regress.compare_runs(quiet, loaded))
    for other in (regress.CONTENTION_MAX * 0.9, float("nan"), None):
        ch = regress.compare_runs(quiet, _run("r4", 4, rng, slow=2.0, other_cpu=other))
        assert ("chess", "a", "render_time", "regression") in _flags(ch), other


def test_improvement_and_small_error_change_within_tolerance():
    rng = np.random.default_rng(2)
    old = _run("r1", 1, rng)
    ch = regress.compare_runs(old, _run("r2", 2, rng, slow=0.8, err=1.005))  # 0.5 % < 1 % tolerance
    assert {(m, f) for _, _, m, f in _flags(ch)} == {("render_time", "improvement")}


def test_memory_growth_and_failed_cell_are_flagged():
    rng = np.random.default_rng(3)
    old = _run("r1", 1, rng)
    new = _run("r2", 2, rng, mem=1100.0)
    new.loc[(new.scene == "chess") & (new.method == "b"), "status"] = "error"
    fl = regress.flagged(regress.compare_runs(old, new))
    assert set(fl[fl.metric == "memory_bytes"]["method"]) == {"a", "b"}
    assert ((fl.metric == "status") & (fl.scene == "chess") & (fl.method == "b")).sum() == 1


def test_suspect_cells_are_compared_and_becoming_suspect_is_flagged():
    rng = np.random.default_rng(7)
    old = _run("r1", 1, rng)
    new = _run("r2", 2, rng, err=1.05)
    sus = (new.scene == "sphere_plane") & (new.method == "b")
    new.loc[sus, "status"], new.loc[sus, "reason"] = "suspect", "frame 1: 9 % negative pixels"
    fl = regress.flagged(regress.compare_runs(old, new))
    got = {(r.metric, r.flag) for r in fl.itertuples() if (r.scene, r.method) == ("sphere_plane", "b")}
    assert got == {("status", "regression"), ("rmse", "regression"), ("psnr", "regression")}
    assert "became suspect: frame 1" in fl[fl.metric == "status"].iloc[0]["test"]
    # suspect → suspect: numbers compared, no status flag
    fl2 = regress.flagged(regress.compare_runs(new, new))
    assert len(fl2) == 0


def test_baseline_is_the_latest_earlier_run_with_that_cell():
    """Issue 17: the latest run of the suite (here an ``--methods a`` run) is not every cell's
    baseline; each cell is compared with the most recent earlier run that has it ok."""
    rng = np.random.default_rng(4)
    only_a = [c for c in CELLS if c[1] == "a"]
    r1 = _run("smoke-r1", 1, rng)  # every cell
    r2 = _run("smoke-r2", 2, rng, cells=only_a)  # a later run of the same suite without the b cells
    r3 = _run("smoke-r3", 3, rng, cells=[("sphere_plane", "b")])
    r3["status"] = np.where(r3["status"] == "run", "run", "error")  # ... and one where b failed
    other_suite = _run("nightly-r4", 4, rng, err=3.0)  # same cells, other suite
    files = _run("smoke+files-r5", 5, rng)  # a scene-file run: its scenes may be named like library ones
    later = _run("smoke-r9", 9, rng)  # after the new run: never its baseline
    hist = pd.concat([r1, r2, r3, other_suite, files, later])
    new = _run("smoke-r6", 6, rng, err=1.05)  # 5 % RMSE rise of (sphere_plane, b)
    base = regress.baseline_rows(hist, new)
    got = base[base.status != "run"].groupby(["scene", "method"])["run_id"].unique().map(list).to_dict()
    assert got == {("sphere_plane", "a"): ["smoke-r2"], ("chess", "a"): ["smoke-r2"],
                   ("sphere_plane", "b"): ["smoke-r1"], ("chess", "b"): ["smoke-r1"]}
    ch = regress.compare_with_history(hist, new)
    assert ("sphere_plane", "b", "rmse", "regression") in _flags(ch)
    assert regress.cells_compared(ch) == 4
    assert regress.baseline_runs(ch) == "smoke-r1 (2 cells), smoke-r2 (2 cells)"
    # a scene-file run is compared with scene-file runs only; a re-finished run is not its own baseline
    again = _run("smoke+files-r7", 7, rng)
    assert set(regress.baseline_rows(pd.concat([hist, again]), again)["run_id"]) == {"smoke+files-r5"}
    assert regress.suite_of("smoke+files-20261202T061103Z-a5177110-4bed") == "smoke+files"
    # nothing earlier has these cells: no baseline, nothing compared
    assert len(regress.compare_with_history(r2, _run("smoke-r8", 8, rng, cells=[("chess", "b")]))) == 0


def test_compare_requires_a_common_cell():
    rng = np.random.default_rng(6)
    a = _run("r1", 1, rng, cells=[("chess", "a")])
    b = _run("r2", 2, rng, cells=[("chess", "b")])
    with pytest.raises(regress.NoCommonCells, match="share no cell"):
        regress.compare_runs(a, b, require_common=True)
    assert len(regress.compare_runs(a, b)) == 0
    assert regress.cells_compared(regress.compare_runs(a, a, require_common=True)) == 1


def test_five_percent_rmse_rise_flagged_even_below_the_noise_floor():
    """The smoke case: RMSE 0.153 against a floor 0.105 (0.1 × floor = 6.9 % of the RMSE). Against
    the same cached reference (identical floor) a deterministic method repeats its RMSE exactly, so a
    5 % rise is flagged; against a re-rendered reference (another floor) the floor slack applies."""
    def one(rid, rmse, floor):
        r = _run(rid, 1, np.random.default_rng(1))
        sel = (r["metric"] == "rmse") & (r["scene"] == "sphere_plane") & (r["method"] == "b")
        r.loc[sel, "value"], r.loc[r["metric"] == "rmse", "noise_floor"] = rmse, floor
        return r

    old = one("smoke-r1", 0.153, 0.105)
    same_ref = regress.compare_runs(old, one("smoke-r2", 0.153 * 1.05, 0.105))
    assert ("sphere_plane", "b", "rmse", "regression") in _flags(same_ref)
    new_ref = regress.compare_runs(old, one("smoke-r2", 0.153 * 1.05, 0.1051))
    assert ("sphere_plane", "b", "rmse", "regression") not in _flags(new_ref)
