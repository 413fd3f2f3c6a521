"""reports.regress: planted regressions are flagged, noise-only resamples are not."""
import numpy as np
import pandas as pd

from reports import regress, store

N_FRAMES = 30  # timed frames per cell in the synthetic history
TIME_NOISE = 0.03  # 3 % lognormal frame-time jitter, typical of a quiet machine
N_RESAMPLES = 20  # noise-only re-runs that must raise no alarm


def _run(run_id, day, rng, *, slow=1.0, err=1.0, mem=1000.0):
    rows = []
    base = {"run_id": run_id, "time": f"2026-01-{day:02d}T00:00:00+00:00", "git_sha": "x", "versions": "{}",
            "machine": "m", "threads": 2, "size": "test", "config": "{}", "bounces": 0, "status": "ok", "reason": ""}
    for scene in ("sphere_plane", "chess"):
        for method in ("a", "b"):
            ident = {**base, "scene": scene, "sequence": "V", "method": method, "cell": f"{scene}-{method}"}
            f = slow if (scene, method) == ("chess", "a") else 1.0
            e = err if (scene, method) == ("sphere_plane", "b") else 1.0
            t = 0.01 * f * np.exp(TIME_NOISE * rng.standard_normal(N_FRAMES + 1))
            rows += [{**ident, "frame": i, "metric": "render_time", "value": v, "unit": "s"} for i, v in enumerate(t)]
            rows += [{**ident, "frame": -1, "metric": "rmse", "value": 0.05 * e, "unit": "radiance", "noise_floor": 0.004},
                     {**ident, "frame": -1, "metric": "psnr", "value": 30.0 - 20 * np.log10(e), "unit": "dB",
                      "noise_floor": 0.004},
                     {**ident, "frame": -1, "metric": "memory_bytes", "value": mem, "unit": "B"}]
    return store.to_frame(rows)


def test_planted_slowdown_and_error_rise_are_flagged():
    rng = np.random.default_rng(0)
    hist = pd.concat([_run("r1", 1, rng), _run("r2", 2, rng, slow=1.10, err=1.05)])
    prev = regress.previous_run(hist, "r2")
    assert prev["run_id"].unique().tolist() == ["r1"]
    ch = regress.compare_runs(prev, hist[hist.run_id == "r2"])
    fl = regress.flagged(ch)
    got = {(r.scene, r.method, r.metric, r.flag) for r in fl.itertuples()}
    assert got == {("chess", "a", "render_time", "regression"),
                   ("sphere_plane", "b", "rmse", "regression"), ("sphere_plane", "b", "psnr", "regression")}
    assert "!!" in regress.format_changes(ch, only_flagged=True)


def test_no_false_alarm_on_noise_only_resamples():
    rng = np.random.default_rng(1)
    old = _run("r1", 1, rng)
    for k in range(N_RESAMPLES):
        new = _run(f"n{k}", 2, rng)
        fl = regress.flagged(regress.compare_runs(old, new))
        assert len(fl) == 0, fl


def test_improvement_and_small_error_change_within_tolerance():
    rng = np.random.default_rng(2)
    old = _run("r1", 1, rng)
    ch = regress.compare_runs(old, _run("r2", 2, rng, slow=0.8, err=1.005))  # 0.5 % < 1 % tolerance
    fl = regress.flagged(ch)
    assert {(r.metric, r.flag) for r in fl.itertuples()} == {("render_time", "improvement")}


def test_memory_growth_and_failed_cell_are_flagged():
    rng = np.random.default_rng(3)
    old = _run("r1", 1, rng)
    new = _run("r2", 2, rng, mem=1100.0)
    new.loc[(new.scene == "chess") & (new.method == "b"), "status"] = "error"
    fl = regress.flagged(regress.compare_runs(old, new))
    assert set(fl[fl.metric == "memory_bytes"]["method"]) == {"a", "b"}
    assert ((fl.metric == "status") & (fl.scene == "chess") & (fl.method == "b")).sum() == 1


def test_time_change_needs_both_threshold_and_significance():
    rng = np.random.default_rng(4)
    a = 1 + 0.001 * rng.standard_normal(200)
    # 2 % slower with tiny noise: significant but under the 5 % threshold
    assert regress.time_change(a, 1.02 * a)[0] == ""
    # 10 % slower but only 2 samples each: not significant
    assert regress.time_change(a[:2], 1.1 * a[:2])[0] == ""
    assert regress.time_change(a, 1.1 * a)[0] == "regression"
