"""reports.measure: closed forms of the timing statistics, convergence fit and speedup."""
import math

import numpy as np
import pytest

from reports import measure

# The fit is exact for noiseless synthetic data up to float64 round-off in log/exp and lstsq.
FIT_RTOL = 1e-9


def test_frame_time_stats_excludes_warmup():
    s = measure.frame_time_stats([100.0, 1.0, 2.0, 3.0, 4.0, 5.0], warmup=1)
    assert s["median"] == 3.0
    assert s["iqr"] == 2.0  # percentiles 25/75 of 1..5 = 2, 4
    assert s["n"] == 5


def test_frame_time_stats_single_frame_and_bad_input():
    assert measure.frame_time_stats([0.5])["median"] == 0.5
    with pytest.raises(ValueError):
        measure.frame_time_stats([])


def test_fit_convergence_recovers_closed_form():
    spp = np.array([4.0, 16.0, 64.0, 256.0])
    c, t0, t_spp = 0.8, 0.3, 0.002
    fit = measure.fit_convergence(spp, c / np.sqrt(spp), t0 + t_spp * spp)
    assert fit.c == pytest.approx(c, rel=FIT_RTOL)
    assert fit.t0 == pytest.approx(t0, rel=FIT_RTOL)
    assert fit.t_spp == pytest.approx(t_spp, rel=FIT_RTOL)
    assert fit.slope == pytest.approx(-0.5, rel=FIT_RTOL)
    # RMSE 0.1 needs (0.8/0.1)^2 = 64 spp → 0.3 + 0.128 s; method at 1 ms → 428x
    assert fit.spp_for_rmse(0.1) == pytest.approx(64.0, rel=FIT_RTOL)
    assert measure.equal_error_speedup(fit, 0.1, 1e-3) == pytest.approx((0.3 + 0.128) / 1e-3, rel=FIT_RTOL)


def test_fit_convergence_rejects_bad_input():
    with pytest.raises(ValueError):
        measure.fit_convergence([16, 16], [0.1, 0.1], [1, 1])
    with pytest.raises(ValueError):
        measure.fit_convergence([4, 16], [0.1, -0.1], [1, 1])
    fit = measure.fit_convergence([4, 16], [0.2, 0.1], [1, 2])
    assert measure.equal_error_speedup(fit, 0.0, 1.0) is None
    assert measure.equal_error_speedup(fit, float("nan"), 1.0) is None


def test_roofline_efficiency_closed_form():
    # 1 GB at 10 GB/s = 0.1 s; a 0.4 s frame reaches 25 % of the roofline
    assert measure.roofline_efficiency(1e9, 1e10, 0.4) == pytest.approx(0.25)
    assert measure.roofline_efficiency(None, 1e10, 0.4) is None
    assert measure.roofline_efficiency(1e9, 1e10, 0.0) is None


def test_triad_bandwidth_is_a_plausible_rate():
    bw = measure.triad_bandwidth(1 << 16, repeats=2)
    assert math.isfinite(bw) and 1e7 < bw < 1e13  # between 10 MB/s and 10 TB/s
    with pytest.raises(ValueError):
        measure.triad_bandwidth(0)


def test_other_cpu_cores_closed_form_and_unknowns():
    """(Δ machine busy − Δ own CPU) / Δ wall; NaN when unknown or too short to resolve 10 ms jiffies."""
    assert measure.other_cpu_cores((0.0, 100.0, 5.0), (2.0, 103.0, 6.0)) == pytest.approx(1.0)
    assert measure.other_cpu_cores((0.0, 100.0, 5.0), (2.0, 101.0, 6.0)) == 0.0   # jiffy rounding: never < 0
    assert math.isnan(measure.other_cpu_cores(None, (2.0, 101.0, 6.0)))
    assert math.isnan(measure.other_cpu_cores((0.0, 100.0, 5.0), None))
    short = measure.CONTENTION_MIN_SECONDS / 2
    assert math.isnan(measure.other_cpu_cores((0.0, 100.0, 5.0), (short, 101.0, 5.0)))


@pytest.mark.skipif(measure.cpu_snapshot() is None, reason="no /proc/stat")
def test_other_cpu_cores_sees_another_busy_process():
    """A child process spinning for 1.5 s while this one waits: the rest of the machine used about one
    core (more if other work runs too; a child is not this process's own CPU)."""
    import subprocess
    import sys

    a = measure.cpu_snapshot()
    subprocess.run([sys.executable, "-c", "import time\nt = time.perf_counter()\nwhile time.perf_counter() - t < 1.5: pass"],
                   check=True)
    b = measure.cpu_snapshot()
    assert measure.other_cpu_cores(a, b) > 0.6
