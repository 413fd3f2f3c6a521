"""Measurements the harness makes (DESIGN.md "Measuring"): timing statistics, peak RSS, the
machine's triad bandwidth, roofline efficiency and the equal-error speedup against Mitsuba.

Pure functions; the harness (``reports/cells.py``) calls them.
"""
from __future__ import annotations

import math
import os
import resource
import sys
import time
from dataclasses import dataclass

import numpy as np
import torch


# -- timing -----------------------------------------------------------------------------------


def frame_time_stats(times: list[float], *, warmup: int = 1) -> dict[str, float]:
    """Median and IQR (seconds) of per-frame times, the first ``warmup`` frames excluded.

    With fewer than ``warmup + 1`` frames the warm-up frames are used (and ``n`` says so).
    """
    t = np.asarray(times, dtype=np.float64)
    if t.ndim != 1 or len(t) == 0:
        raise ValueError("need at least one frame time")
    s = t[warmup:] if len(t) > warmup else t
    q1, med, q3 = np.percentile(s, [25, 50, 75])
    return {"median": float(med), "iqr": float(q3 - q1), "n": int(len(s))}


# Below this many seconds of wall time the jiffy counters (10 ms) make `other_cpu_cores` too coarse
# to say anything: it is NaN then.
CONTENTION_MIN_SECONDS = 0.5


def cpu_snapshot() -> tuple[float, float, float] | None:
    """(wall seconds, CPU seconds every core of the machine spent busy, CPU seconds of this process)
    now — the counters `other_cpu_cores` differences. "Busy" is user + nice + system + irq + softirq +
    steal of ``/proc/stat``'s ``cpu`` line: steal is time the hypervisor gave this VM's vCPUs to
    someone else, contention as much as another process here. None where there is no /proc/stat."""
    try:
        with open("/proc/stat") as f:
            parts = f.readline().split()
    except OSError:
        return None
    if not parts or parts[0] != "cpu" or len(parts) < 9:
        return None
    user, nice, system, _idle, _iowait, irq, softirq, steal = (int(x) for x in parts[1:9])
    hz = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    ru = resource.getrusage(resource.RUSAGE_SELF)   # every thread of this process (Mitsuba's, OpenMP's)
    return (time.perf_counter(), (user + nice + system + irq + softirq + steal) / hz, ru.ru_utime + ru.ru_stime)


def other_cpu_cores(start: tuple | None, end: tuple | None) -> float:
    """Cores' worth of CPU that everything but this process used, on average, between two
    `cpu_snapshot` s (0 on a machine reserved for the run; 1 = another process kept one core busy the
    whole time). Frame times measured beside such work are slower by an amount no within-run
    statistic shows (every frame slows alike), so the harness records this for every timed cell
    (``other_cpu_cores``) and the report and the regression check say where it was not ~0. NaN when
    either snapshot is None or the interval is shorter than ``CONTENTION_MIN_SECONDS``."""
    if start is None or end is None:
        return float("nan")
    wall = end[0] - start[0]
    if not wall >= CONTENTION_MIN_SECONDS:
        return float("nan")
    return max(0.0, ((end[1] - start[1]) - (end[2] - start[2])) / wall)


def peak_rss_bytes() -> int:
    """Peak resident set size of this process (``ru_maxrss``; KiB on Linux, bytes on macOS)."""
    r = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(r if sys.platform == "darwin" else r * 1024)


# -- bandwidth / roofline ---------------------------------------------------------------------


def triad_bandwidth(n: int = 1 << 24, *, repeats: int = 5, dtype=torch.float32, device="cpu") -> float:
    """STREAM-triad bandwidth in bytes/s: ``a = b + s·c`` on arrays of ``n`` elements.

    Counts 3 arrays × n × itemsize bytes per pass (reads of b, c and the write of a; write-allocate
    traffic is not counted, as in STREAM). Best of ``repeats`` passes after one warm-up.
    """
    if n < 1 or repeats < 1:
        raise ValueError("n and repeats must be >= 1")
    b = torch.rand(n, dtype=dtype, device=device)
    c = torch.rand(n, dtype=dtype, device=device)
    a = torch.empty_like(b)
    torch.add(b, c, alpha=3.0, out=a)  # warm-up (page faults)
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        torch.add(b, c, alpha=3.0, out=a)
        best = min(best, time.perf_counter() - t0)
    return 3.0 * n * b.element_size() / max(best, 1e-12)


def matmul_peak(n: int = 1024, *, repeats: int = 5, dtype=torch.float32, device="cpu") -> float:
    """Dense matmul (sgemm) throughput in FLOP/s: 2·n³ per (n × n) @ (n × n), best of ``repeats``
    after one warm-up — the machine's compute roof for the threads torch uses."""
    if n < 1 or repeats < 1:
        raise ValueError("n and repeats must be >= 1")
    a = torch.rand(n, n, dtype=dtype, device=device)
    b = torch.rand(n, n, dtype=dtype, device=device)
    c = a @ b
    best = math.inf
    for _ in range(repeats):
        t0 = time.perf_counter()
        torch.matmul(a, b, out=c)
        best = min(best, time.perf_counter() - t0)
    return 2.0 * n**3 / max(best, 1e-12)


TRIAD_ELEMENTS = 1 << 24  # 64 MiB per float32 array: far beyond the caches of this machine kind


def machine_limits(bandwidth_elements: int = TRIAD_ELEMENTS) -> dict[str, float]:
    """One measurement of both machine limits: ``triad_bandwidth`` (B/s) and ``matmul_peak``
    (FLOP/s; a 1024² sgemm, 256² when ``bandwidth_elements`` is below `TRIAD_ELEMENTS`: tests)."""
    return {"triad_bandwidth": triad_bandwidth(bandwidth_elements),
            "matmul_peak": matmul_peak(256 if bandwidth_elements < TRIAD_ELEMENTS else 1024)}


def roofline(cost_bytes: float | None, cost_flops: float | None, bandwidth: float, peak_flops: float,
             frame_time: float) -> tuple[float, str] | None:
    """(efficiency, bound): max(bytes / bandwidth, flops / peak) / frame time and which term is the
    larger ("memory" | "compute"); None when the method reports no cost or a time is not positive."""
    if cost_bytes is None or not (bandwidth > 0) or not (frame_time > 0):
        return None
    tb = float(cost_bytes) / float(bandwidth)
    tf = float(cost_flops or 0.0) / float(peak_flops) if peak_flops and peak_flops > 0 else 0.0
    return (max(tb, tf) / float(frame_time), "memory" if tb >= tf else "compute")


def roofline_efficiency(bytes_per_frame: float | None, bandwidth: float, frame_time: float) -> float | None:
    """Fraction of the bandwidth roofline a method reaches: (bytes / bandwidth) / frame time.

    1.0 means the frame took as long as streaming its bytes once at triad bandwidth; None when the
    method does not report bytes or a time is not positive.
    """
    if bytes_per_frame is None or not (bandwidth > 0) or not (frame_time > 0):
        return None
    return float(bytes_per_frame) / float(bandwidth) / float(frame_time)


# -- equal-error speedup ----------------------------------------------------------------------


@dataclass(frozen=True)
class ConvergenceFit:
    """Monte Carlo convergence of the reference renderer on one frame.

    RMSE(spp) ≈ c · spp^(−1/2) (fitted with the exponent fixed at −1/2 from the noise floors);
    time(spp) ≈ t0 + t_spp · spp (least squares, clamped to non-negative).
    ``slope`` is the freely fitted log-log exponent, recorded as a sanity check (≈ −0.5).
    """

    c: float
    t0: float
    t_spp: float
    slope: float

    def spp_for_rmse(self, rmse: float) -> float:
        return (self.c / rmse) ** 2

    def time_for_rmse(self, rmse: float) -> float:
        return self.t0 + self.t_spp * self.spp_for_rmse(rmse)

    def to_dict(self) -> dict:
        return {"c": self.c, "t0": self.t0, "t_spp": self.t_spp, "slope": self.slope}


def fit_convergence(spp: list[float], rmse: list[float], seconds: list[float]) -> ConvergenceFit:
    """Fit ``ConvergenceFit`` from references rendered at several spp.

    spp, rmse (noise floors), seconds: (K,) with K ≥ 2 distinct spp, positive values.
    """
    s = np.asarray(spp, dtype=np.float64)
    e = np.asarray(rmse, dtype=np.float64)
    t = np.asarray(seconds, dtype=np.float64)
    if not (s.shape == e.shape == t.shape) or s.ndim != 1:
        raise ValueError("spp, rmse and seconds must be 1-D of equal length")
    if len(np.unique(s)) < 2:
        raise ValueError("need references at >= 2 distinct spp")
    if np.any(s <= 0) or np.any(e <= 0) or np.any(t < 0) or not np.all(np.isfinite(np.r_[s, e, t])):
        raise ValueError("spp and rmse must be positive and finite, seconds non-negative")
    # RMSE = c / sqrt(spp)  →  log c = mean(log e + ½ log s)
    c = float(np.exp(np.mean(np.log(e) + 0.5 * np.log(s))))
    slope = float(np.polyfit(np.log(s), np.log(e), 1)[0])
    A = np.stack([np.ones_like(s), s], 1)
    (t0, t_spp), *_ = np.linalg.lstsq(A, t, rcond=None)
    t_spp = max(float(t_spp), 1e-12)
    t0 = max(float(t0), 0.0)
    return ConvergenceFit(c=c, t0=t0, t_spp=t_spp, slope=slope)


def equal_error_speedup(fit: ConvergenceFit, method_rmse: float, method_frame_time: float) -> float | None:
    """Mitsuba time to reach the method's RMSE ÷ the method's frame time (None if undefined).

    The method's RMSE is measured against a noisy reference, so it is an upper bound of its true
    error and the speedup is a lower bound when the method is near the noise floor.
    """
    if not (method_rmse > 0) or not (method_frame_time > 0) or not math.isfinite(method_rmse):
        return None
    return fit.time_for_rmse(method_rmse) / method_frame_time
