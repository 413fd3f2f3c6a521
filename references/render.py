"""Path-traced Mitsuba 3 references: two independent halves → image + noise floor + coverage.

``render_reference(scene, frame, bounces=..., spp=...)`` renders the frame twice with ``spp/2``
samples per pixel each, with different seeds (``2·seed`` and ``2·seed + 1``), and returns their
mean as the image. Path integrator ``max_depth = bounces + 2`` (0 bounces = direct lighting only →
2; None = full global illumination → −1), ``hide_emitters=True``, box reconstruction filter.

Noise floor. Let σ² be the per-pixel variance of the full image I = (A + B)/2. Each half A, B has
half the samples, so variance 2σ²; they are independent, so Var(A − B) = 4σ² and
E[(A − B)²] = 4σ² (both are unbiased: the mean difference is 0). Hence
``RMSE(A, B) / 2 = sqrt(mean 4σ²) / 2 = sqrt(mean σ²)``: an estimate of the RMSE of the full
image against the noise-free truth. A method's RMSE against the reference cannot be trusted below
this floor (its expected value is sqrt(method error² + floor²)). Computed over the coverage mask.

Coverage: pixels all of whose S×S G-buffer sub-samples hit geometry (``make_gbuffer``), the
pixels every score is computed on. Results are cached by content hash (``references.cache``).
"""
from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from references import cache as _cache


@dataclass
class Reference:
    """A reference render.

    image: (H, W, 3) float32 linear RGB = (half_a + half_b) / 2.
    half_a, half_b: (H, W, 3) float32 independent renders with spp/2 samples each.
    noise_floor: RMSE(half_a, half_b) / 2 over ``coverage`` (≈ the image's own RMSE; NaN if no
        pixel is covered).
    coverage: (H, W) bool — pixels fully covered by geometry (scored pixels).
    meta: mitsuba version, variant, spp, seeds, max_depth, bounces, scene hash, frame key, render
        seconds, threads, spp_side, cache key, from_cache.
    """

    image: Tensor
    half_a: Tensor
    half_b: Tensor
    noise_floor: float
    coverage: Tensor
    meta: dict = field(default_factory=dict)


def max_depth_for(bounces: int | None) -> int:
    """Mitsuba ``max_depth`` of a bounce count: 0 → 2 (direct), 1 → 3, 2 → 4, None → −1 (full)."""
    if bounces is None:
        return -1
    if isinstance(bounces, bool) or int(bounces) != bounces or bounces < 0:
        raise ValueError(f"bounces must be a non-negative integer or None (full GI), got {bounces!r}")
    return int(bounces) + 2


def half_seeds(seed: int) -> tuple[int, int]:
    """Seeds of the two halves: distinct for every seed and between the halves."""
    return 2 * int(seed), 2 * int(seed) + 1


def noise_floor(half_a, half_b, mask) -> float:
    """RMSE(half_a, half_b) / 2 over ``mask`` (see the module doc). half_*: (H, W, 3); mask (H, W)."""
    from references.metrics import rmse

    m = mask.detach().cpu().numpy() if isinstance(mask, Tensor) else np.asarray(mask)
    if not m.any():
        return math.nan
    return rmse(half_a, half_b, m) / 2.0


@contextlib.contextmanager
def _jit_compile_seconds():
    """Collects, into the yielded list, the seconds Dr.Jit's backend spent compiling kernels (LLVM,
    ``backend_time`` of ``dr.kernel_history``: zero for a kernel found in its memory or disk cache)
    inside the block; the kernel history is switched on for the block and left as it was."""
    import drjit as dr

    out: list[float] = []
    was = dr.flag(dr.JitFlag.KernelHistory)
    dr.kernel_history_clear()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        yield out
    finally:
        hist = dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, was)
        out.append(sum(float(h.get("backend_time", 0.0) or 0.0) for h in hist) / 1e3)


def render_halves(scene, frame, *, max_depth: int, spp: int, seed: int, progress: bool = False,
                  times: dict | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Render the two halves with Mitsuba. Returns (half_a, half_b) (H, W, 3) float32 and seconds
    (scene export and load, both renders, any kernel compilation).

    times: filled with that total split — ``load_seconds`` (our scene exported and loaded: plugins,
    emitter tables, BVH), ``compile_seconds`` (Dr.Jit compiling kernels it had not cached: new
    literal parameters, e.g. a VB frame's materials, compile new kernels) and ``frame_seconds``, the
    two renders without the compilation: what the equal-error speedup charges Mitsuba
    (`reference_seconds`), as a method's frame time excludes its compilation and precomputation."""
    import mitsuba as mi
    from tqdm import tqdm

    from references.export import load

    t0 = time.perf_counter()
    mi_scene = load(scene, frame, max_depth=max_depth, spp=spp // 2, seed=seed)
    t1 = time.perf_counter()
    halves = []
    with _jit_compile_seconds() as compiled:
        for s in tqdm(half_seeds(seed), desc="reference halves", disable=not progress, leave=False):
            img = mi.render(mi_scene, spp=spp // 2, seed=s)
            halves.append(np.array(img, dtype=np.float32).reshape(frame.camera.height, frame.camera.width, -1)[..., :3])
    t2 = time.perf_counter()
    if times is not None:
        times.update(load_seconds=t1 - t0, compile_seconds=compiled[0],
                     frame_seconds=max(t2 - t1 - compiled[0], 0.0))
    return halves[0], halves[1], t2 - t0


def _threads() -> int:
    import drjit as dr

    try:
        return int(dr.thread_count())
    except Exception:  # pragma: no cover - older drjit
        return -1


def render_reference(scene, frame, *, bounces: int | None, spp: int, seed: int = 0, use_cache: bool = True,
                     progress: bool = False, spp_side: int = 2) -> Reference:
    """Path-traced reference of ``scene`` in ``frame`` (cached by content hash).

    bounces: 0 (direct lighting), 1, 2, … or None (full global illumination).
    spp: total samples per pixel (even, >= 2): two halves of spp/2. seed: >= 0.
    spp_side: S of the G-buffer whose coverage mask is stored (S×S sub-samples per pixel).
    """
    from references.gbuffer import make_gbuffer
    from references.mitsuba_setup import ensure_variant

    max_depth = max_depth_for(bounces)
    if isinstance(spp, bool) or int(spp) != spp or spp < 2 or spp % 2:
        raise ValueError(f"spp must be an even integer >= 2 (two halves), got {spp!r}")
    if isinstance(seed, bool) or int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    if int(spp_side) != spp_side or spp_side < 1:
        raise ValueError(f"spp_side must be a positive integer, got {spp_side!r}")
    spp, seed, spp_side = int(spp), int(seed), int(spp_side)
    variant = ensure_variant()
    fields = _cache.reference_fields(scene, frame, max_depth=max_depth, spp=spp, seed=seed, spp_side=spp_side)
    key = _cache.key_of(fields)
    if use_cache:
        hit = _cache.load(key, fields)
        if hit is not None:
            arrays, meta = hit
            meta["from_cache"] = True
            return _make(arrays, meta)

    split: dict = {}
    a, b, seconds = render_halves(scene, frame, max_depth=max_depth, spp=spp, seed=seed, progress=progress, times=split)
    H, W = frame.camera.height, frame.camera.width
    if a.shape != (H, W, 3) or b.shape != (H, W, 3):
        raise RuntimeError(f"Mitsuba returned {a.shape}/{b.shape}, expected {(H, W, 3)}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise RuntimeError("Mitsuba reference contains NaN/Inf (a plugin or the env map is broken)")
    coverage = make_gbuffer(scene, frame, spp_side).coverage.numpy()
    import mitsuba as mi

    meta = {
        "mitsuba": mi.__version__,
        "variant": variant,
        "spp": spp,
        "seed": seed,
        "half_seeds": list(half_seeds(seed)),
        "max_depth": max_depth,
        "bounces": bounces,
        "scene": getattr(scene, "name", None),
        "scene_hash": fields["scene"],
        "frame_key": fields["frame"],
        "render_seconds": seconds,
        **split,  # load_seconds, compile_seconds, frame_seconds (`render_halves`)
        "threads": _threads(),
        "spp_side": spp_side,
        "width": W,
        "height": H,
        "cache_key": key,
        "cache_version": _cache.CACHE_VERSION,
    }
    arrays = {"half_a": a.astype(np.float32), "half_b": b.astype(np.float32), "coverage": coverage.astype(bool)}
    if use_cache:
        _cache.store(key, fields, arrays, meta)
    meta["from_cache"] = False
    return _make(arrays, meta)


def _make(arrays: dict, meta: dict) -> Reference:
    a = torch.from_numpy(np.asarray(arrays["half_a"], np.float32))
    b = torch.from_numpy(np.asarray(arrays["half_b"], np.float32))
    cov = torch.from_numpy(np.asarray(arrays["coverage"], bool))
    image = 0.5 * (a + b)
    return Reference(image=image, half_a=a, half_b=b, noise_floor=noise_floor(a, b, cov), coverage=cov, meta=meta)
