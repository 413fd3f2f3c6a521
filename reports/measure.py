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
             frame_time: float, cost_rays: float | None = None, ray_rate: float | None = None) -> tuple[float, str] | None:
    """(efficiency, bound): max(bytes / bandwidth, flops / peak, rays / ray rate) / frame time and which
    term is the largest ("memory" | "compute" | "traversal"); None when the method reports no cost or a
    time is not positive. Rays without a measured ``ray_rate`` bound nothing (``FrameCost.bound``)."""
    if cost_bytes is None or not (bandwidth > 0) or not (frame_time > 0):
        return None
    terms = [(float(cost_bytes) / float(bandwidth), "memory"),
             (float(cost_flops or 0.0) / float(peak_flops) if peak_flops and peak_flops > 0 else 0.0, "compute")]
    if cost_rays and ray_rate is not None and math.isfinite(ray_rate) and ray_rate > 0:
        terms.append((float(cost_rays) / float(ray_rate), "traversal"))
    t, bound = max(terms, key=lambda x: x[0])
    return (t / float(frame_time), bound)


RAY_SETS = ("cosine", "coherent")


def shadow_rays(points, normals, ray_set: str, *, seed: int = 0, offset: float = 1e-4) -> tuple[np.ndarray, np.ndarray]:
    """(origins, directions), (R, 3) float32 each: one shadow ray from each surface point, its origin
    moved ``offset`` along the normal. ``ray_set``: "cosine" — directions cosine-distributed about
    the normal (incoherent, an ambient-occlusion / Lambertian-sample ray: the kind of ray a Monte
    Carlo estimator traces); "coherent" — one fixed direction, flipped into each point's upper
    hemisphere (a directional light's shadow rays: the most coherent shadow rays from these points)."""
    p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if p.shape != n.shape:
        raise ValueError(f"points and normals must have the same shape, got {p.shape} and {n.shape}")
    if ray_set == "coherent":
        d0 = np.array([0.3, 0.8, 0.5]) / np.linalg.norm([0.3, 0.8, 0.5])
        d = np.where((n @ d0)[:, None] >= 0.0, d0, -d0)
    elif ray_set == "cosine":
        g = np.random.default_rng(seed)
        u1, u2 = g.random(len(p)), g.random(len(p))
        t = np.where(np.abs(n[:, :1]) > 0.9, np.array([[0.0, 1.0, 0.0]]), np.array([[1.0, 0.0, 0.0]]))
        b1 = np.cross(n, t)
        b1 /= np.maximum(np.linalg.norm(b1, axis=1, keepdims=True), 1e-30)
        b2 = np.cross(n, b1)
        r, phi = np.sqrt(u1)[:, None], 2.0 * np.pi * u2[:, None]
        d = r * np.cos(phi) * b1 + r * np.sin(phi) * b2 + np.sqrt(1.0 - u1)[:, None] * n
    else:
        raise ValueError(f"ray_set must be one of {RAY_SETS}, got {ray_set!r}")
    return (p + offset * n).astype(np.float32), d.astype(np.float32)


def ray_rate(V, F, points, normals, *, repeats: int = 3, seed: int = 0,
             backends: tuple[str, ...] | None = None) -> tuple[float, str]:
    """The roof of ``FrameCost.rays`` (session 38): shadow rays per second the fastest of the suite's
    tracers (``references.visibility``: Mitsuba's ``ray_test``, embreex; robust traversal, as the
    suite traces) answers on the mesh (V, F), from ``points`` along their ``normals`` — in the harness the
    cell's last G-buffer's hit points on its last frame's geometry. The best over tracers, both
    `RAY_SETS` and ``repeats`` passes (after a warm-up each): like the triad and the sgemm, the fastest
    the machine does this kind of work here, so a frame's traversal term is a lower bound. Mitsuba is
    timed on rays already in Dr.Jit arrays (its ``ray_test`` alone, no conversion), embreex through
    ``occluded`` on numpy arrays. Returns (rays / s, "tracer/ray set")."""
    from references.visibility import make_visibility, mitsuba_usable

    if repeats < 1:
        raise ValueError("repeats must be >= 1")
    p = np.asarray(points, dtype=np.float32).reshape(-1, 3)
    if len(p) == 0:
        raise ValueError("ray_rate needs at least one point")
    V = np.asarray(V, dtype=np.float32)
    scale = float(np.linalg.norm(V.max(0) - V.min(0))) if len(V) else 1.0
    if backends is None:
        backends = ("mitsuba", "embree") if mitsuba_usable() else ("embree",)
    best, which = 0.0, ""
    for b in backends:
        vis = make_visibility(V, F, backend=b)
        for rs in RAY_SETS:
            o, d = shadow_rays(p, normals, rs, seed=seed, offset=1e-4 * max(scale, 1e-12))
            trace = tracer_call(vis, o, d)
            trace()  # warm-up: Dr.Jit compiles its kernel, embreex its first pass
            for _ in range(repeats):
                t0 = time.perf_counter()
                trace()
                dt = time.perf_counter() - t0
                if len(o) / max(dt, 1e-12) > best:
                    best, which = len(o) / max(dt, 1e-12), f"{vis.backend}/{rs}"
    return best, which


def tracer_call(vis, o: np.ndarray, d: np.ndarray):
    """A call that traces (o, d) once with ``vis`` and waits for the answers."""
    if getattr(vis, "backend", "") == "mitsuba" and hasattr(vis, "_rays") and hasattr(vis, "_scene"):
        import drjit as dr

        ray = vis._rays(o, d, np.float32(np.inf))  # Dr.Jit arrays made once: time the traversal alone
        dr.eval(ray)
        dr.sync_thread()

        def trace():
            h = vis._scene.ray_test(ray)
            dr.eval(h)
            dr.sync_thread()
        return trace
    return lambda: vis.occluded(o, d)


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
