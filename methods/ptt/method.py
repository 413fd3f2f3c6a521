"""Precomputed transfer tensors for relighting with dynamic BRDFs (Sun, Zhou, Chen, Lin, Shi, Guo
2007) behind the common `methods.base.Method` interface.

Precompute (static geometry): the BRDF basis b_p and its shared factorization
(``methods.ptt.transport``); per vertex the direct transport T̃⁰ (Haar, n_L kept per k), the
one-bounce PTT T¹(r, p, s, l) on the coarse 6×n₁×n₁ lighting and the two-bounce PTT
T²(l, r1, p1, r2, p2) on 6×n₂×n₂ (``methods.ptt.bounce``).

Run time (Sun eq. 3–4), per frame, three cached stages keyed on ``frame.changed``:

1. lighting (only when "light" changed): C^L = Haar of the env map on the cube map;
   E⁰_x(k) = Σ_l C^L_l U^{I0}_x(l, k); T¹L_x(r, p, s) = Σ_l C^L_l T¹_x(r, p, s, l);
   T²L_x(r1, p1, r2, p2) = Σ_l C^L_l T²_x(l, r1, p1, r2, p2)                        (eq. 4 terms)
2. BRDFs (when "brdf" or "light" changed): H(r, p, c) = basis coordinates of frame.materials;
   E_x(k) = E⁰_x(k) + Σ_s C^{ωi}(s, k) Σ_{r,p} H(r,p) T¹L_x(r,p,s)
            + C^{ωi}(k) Σ H(r1,p1) H(r2,p2) T²L_x(r1,p1,r2,p2)            (U^{I0} + U^{I1} + U^{I2})
3. view (every frame), the view factor g_x(k) = Σ_p H(r, p) W(p, ωo in x's frame, k) (the
   D ×_h U^h ×_ωo U^{ωo} part of eq. 3) and B_x = Σ_k g_x(k) E_x(k), where (config ``shading``):
   * "vertex" (default; Sun's run time — §3: eq. 1 is evaluated "for determining the exit
     radiance at each point toward the viewer", the points being the vertices that carry the
     transfer; §4.1: the fractional visibility "is computed from the visibility maps of each
     vertex"; §4.3: "for direct lighting, performance is linearly dependent on the number of
     vertices"; §5: "the computation of the transferred incident radiance is performed on the
     CPU, and the final shading is done on the GPU"): x is a vertex
     and ωo its own direction to the camera; a sample's radiance is max(0, Σ_v β_v B_v) with its
     barycentrics β (Gouraud). The separated lobes' per-vertex factors (a_k(θo_x), the fractional
     visibility V_c^(k)(x, R_x) from the vertex's visibility table, the one-bounce term) are
     interpolated the same way; only the prefiltered maps E^(k) are read per sample, at the
     mirror direction of the interpolated normal (the GPU's final shading with prefiltered
     environment textures), so mirror-like reflections stay sharp.
   * "pixel": per G-buffer sample, for each vertex v of its triangle, B_v with the *sample's* ωo
     in v's frame and the lobes at the sample's mirror direction in each vertex's frame; the
     sample's radiance is the barycentric mix of B_v (values living in a vertex's local frame are
     never interpolated across frames), clamped at 0. Per-sample look-ups make it ≈ 10× slower
     per V frame; it is more accurate on coarse meshes (test-size alcove direct RMSE vs Mitsuba
     0.0092 vs 0.0109 "vertex", shadow_detail 0.075 vs 0.085; chess 0.0528 vs 0.0533; chess
     bench 0.0355 vs 0.0358).

So V-only frames do only stage 3, V&B frames skip the lighting wavelet products (stage 1), V,B&L
frames do all three (Sun Table 1). `render` runs these stages batched (``methods.ptt.fast``: the
same sums, regrouped); `_render_reference` is the stage-by-stage code above, kept as the test
oracle of the fast path (equal to float32 round-off). `frame_cost` / `cost_terms` state the minimum
bytes and flops of each frame kind (the roofline's numerators).

Specular lobe separation (§4.1, ``separate=True``; all formulas and normalisations in
``methods.ptt.specular``): the lobe weights a_k^p(θo) of every basis function are fitted at
precompute and the factorization, direct transport and PTTs see only the remainder basis
f_r = f − f_s. Per vertex, the direct transport's visibility rays also give the cosine-weighted
fractional visibility V_c^(k)(x, R) on a T×T local table per lobe; stage 1 prefilters the env map
with each unit-mass Gaussian (E^(k), resampled onto the env map's own grid:
``specular.on_env_grid``); stage 2 prefilters the one-bounce SH radiance per lobe; stage 3 adds
Σ_k a_k(H, θo)[E^(k)(R) V_c^(k)(x, R) + max(0, n·R) L1^(k)(R)] (per vertex but E^(k)(R) per sample
with shading="vertex", `_vertex_terms`; per sample with "pixel", `_specular_lobes`).
Light reflected by a *hit point's* separated lobe is missing from the bounce tensors (they are built
from f_r), and the two-bounce radiance is not applied to the lobes (as the paper).

BRDF factorization (eq. 2–3): the shading factors come from the BRDF basis itself
(`transport.factor_basis`): a Tucker factorization whose h mode is the basis (H = the region's
coordinates, the role of U^h(H, ·)), ωi mode of rank ``n_wi`` and ωo mode of rank ``n_wo`` (None =
untruncated table). The sampled-BRDF-space tensor of ``methods.ptt.brdf_tensor`` (Fig. 5, the n_h
study) is not what renders: its h mode indexes BRDF samples that H maps onto only through the
PCA basis, which is the basis here;
compression (§4.3 CPCA + clustered tensor approximation) is ``methods.ptt.compress`` (optional,
``compress=``; T² is kept dense).
"""
from __future__ import annotations

import ctypes
import weakref
from typing import Any

import torch
from torch import Tensor

from methods.base import (GBUFFER_BYTES_PER_SAMPLE, GBUFFER_HIT_BYTES, Capabilities, Frame, FrameCost, GBuffer, Method,
                          geometry_key, output_bytes, precompute_memo, register, tensor_bytes)
from methods.core import zh as _zh
from methods.core.frames import reflect, to_local
from methods.core.fused import compile_enabled
from methods.core.threads import torch_threads
from references.visibility import make_visibility
from methods.ptt import bounce as _bounce
from methods.ptt import compress as _cmp
from methods.ptt import fast as _fast
from methods.ptt import lobes as _lobes
from methods.ptt import native as _pn
from methods.ptt import native_fit as _pnf
from methods.ptt import pca as _pca
from methods.ptt import specular as _spec
from methods.ptt import transport as _tp
from methods.ptt.transport import table_coords
from scenes.envmap import extend_periodic
from scenes.hashing import hash_materials

# G-buffer samples shaded per batch by the reference path (a batch holds (Q, 3, n_P, K) view factors)
# and by the fast path (a batch holds a few hundred bytes per sample).
RENDER_CHUNK = 1 << 15
FAST_CHUNK = 1 << 18
# shading="vertex": the per-sample view stage through the compiled ``fast.shade_samples_fused`` (True) or
# the eager ``fast.shade_samples`` (False; the same numbers to float32 round-off).
FUSED_VIEW = True

# Paper settings (Sun 2007 §4.3): 6×64×64 cube map, n_L = 96, n_ωi = 8, one-bounce lighting 6×8×8,
# two-bounce 6×2×2, 4th-order SH.
PAPER = dict(cube_res=64, n_L=96, n_wi=8, n_wo=8, light_res_1=8, light_res_2=2, sh_order=4, separate=True,
             lobe_degrees=[0.0, 7.0, 14.0, 21.0])

# Where the view stage evaluates Sun eq. 3 (the `shading` config, class docstring): "vertex" (Sun's
# run time, the default) or "pixel" (per G-buffer sample; slower, sharper on coarse meshes).
SHADINGS = ("vertex", "pixel")
SHADING_DEFAULT = "vertex"

# REFERENCED_PAIRS: a shading="vertex" frame whose samples the native loop shades computes the rows
# of `fast.vertex_view` for the (vertex, region) pairs of the faces its samples lie on only
# (`fast.referenced_pairs`, ~40 % of the pairs on the chess bench, ~31 % on the creature; what
# `cost_terms` counts), and the sample stage reads them through the faces' corners remapped onto
# that compact table. The same bits as the full table (tested). Off: every pair's row (the path
# without the native loop, whose compiled sample stage would recompile for every table size).
REFERENCED_PAIRS = True

# FULL_TABLE (session 38, pt38): with REFERENCED_PAIRS and the native loops, the referenced pairs' rows
# are written at the pairs' own positions of an (n_pairs + 1)-row table (`fast.referenced_view`) and the
# sample stage reads them through the static face corners (`fast.miss_face_pairs`) — the same rows, the
# same bits — instead of a compact table read through the faces' corners remapped each frame
# (`fast.referenced_pairs`' fpc: M + 1 corner triples and the pairs' positions built per frame, serial
# after the faces' marking at 2 threads). The bench's pair tables are 0.7 MB (chess) full against 0.3
# compact; the rows read are the same cache lines (one 64-byte row a pair). Measured (1 thread, process
# CPU, same process, 64 MB touched before each call as the rasteriser would): the pair selection alone
# 0.52 -> 0.44 ms chess, 0.64 -> 0.52 ms creature; whole V / VB frames with FULL_TABLE on / off
# alternating chess 1.004-1.012 / 0.964, creature 1.067 / 1.042 (the sample stage then reads the static
# corners, cache-cold, instead of the freshly written remapped ones: on chess that takes back the gain);
# against 43313b4 (`benchmarks.ptt_ab ... --frames 17 --threads 1`) chess V 0.98 VB 1.02, creature V 1.04
# VB 1.06. Images bit-identical (tested).
FULL_TABLE = True

# VIEW_FRAME (session 42, pt42): a shading="vertex" frame that takes the FULL_TABLE route runs its native
# view stage — `fast.referenced_view`'s ``native.referenced_sel`` and ``native.vertex_rows`` (rows_at), then
# ``native.shade_mirror`` — as ONE C call (``native.view_frame``) on a packed argument array made once per
# (region tables, E, lighting, static arrays, thread count, switches) and G-buffer layout (`_VIEW_PLANS`),
# with the G-buffer's hit / face -1 check (the `pixels` condition) in its marking pass. The same loops, the
# same arguments, the same order: the same bits (tested). What it removes is the Python between them, cold
# after the harness's G-buffer and serial at 2 threads: a chess bench V frame's time outside its C calls
# (1 thread, after a 64 MB write and 50 ms idle, median of 32 frames) 0.64 -> 0.21 ms, VB 0.98 -> 0.62 ms
# (`all_true`'s torch reduction, `torch.as_tensor` of the camera — 82 µs cold —, the wrappers' checks,
# contiguous / to / empty calls, six library look-ups). Same process, 1 thread, process CPU, 21 frames
# (``python -m benchmarks.ptt_ab --base B --precompute-code B --threads 1 --kinds V VB --frames 21 --scene S``,
# B = ce67f85): chess V 1.12 / 1.09, VB 1.06 / 1.07; creature V 1.12, VB 1.08; A/A chess 0.99 / 1.00.
# Off, or where the plan declines (`native.view_plan`) or the call returns None: the path below, as before.
VIEW_FRAME = True
# method → its `native.ViewPlan` (outside the instance: not pickled, not part of the state the thread test
# compares, not shared by `with_shading` copies)
_VIEW_PLANS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()

# FRAME_CALL (session 43, pt43): a frame that would take VIEW_FRAME's route on the plan made by an earlier frame,
# with the lighting unchanged and no bounce terms (E does not depend on H), runs as ONE C call
# (``native_fit.frame_call``) from the top of `render`: where a region's material object changed (a VB
# frame) the batched fit's materials, W_r's rows (``native.region_rows_range``, in place) and a_r
# (``native_fit.ar_table``, in place) as tasks of one OpenMP team (a row chunk starts once its region's fit is
# done, a_r once every fit is: at 2 threads the fits, rows and a_r overlap instead of three regions in turn,
# a_r serial), then ``native.view_frame`` on the view plan — the functions and arguments of the route it
# replaces (`_check_frame` → `coords` → `fast.region_tables` → `_view_frame`): the same bits (tested). What
# it removes is that route's Python, serial at 2 threads and cold after the harness's G-buffer: each
# wrapper's checks, `torch.equal` (done in C), the tables' new views and the plan's re-keying, two library
# look-ups. Measured (`benchmarks.ptt43_serial`, 1 thread, process CPU, 64 MB written + settle before each
# frame, 28 frames, on / off alternating): a VB frame's time outside its C calls chess 0.494 -> 0.284 ms,
# creature 0.475 -> 0.276 ms (all of it serial at 2 threads: ~0.2 ms of the perf suite's 2.46 / 2.15 ms VB
# frames). ``benchmarks.ptt_ab --base B --precompute-code B --threads 1 --frames 21`` (B = 0a8e785): chess
# VB 1.04-1.07, creature VB 1.04-1.07 (process CPU; A/A chess 0.98-0.99), V 0.98-1.01 (a V frame's Python is
# about the route's: outside its C calls 0.262 -> 0.243 ms, chess). The BRDF part's C work itself is ~0.2 ms
# (`benchmarks.ptt43_brdf_tasks`, chess: 1 thread route 0.217 / tasks 0.203 ms; 2 threads 0.228 / 0.197 ms
# median, 0.150 / 0.136 ms 10th percentile, on a loaded host). Off, or where it declines (no plan yet, another switch, layout
# or lighting, a decline of any call's checks): the route below, as before.
FRAME_CALL = True
# W_r rows a task of the frame call (its threads take the fits, then chunks of the rows, a_r among them)
FRAME_CHUNK = 256
# method → its `_FramePlan` (as _VIEW_PLANS: outside the instance)
_FRAME_PLANS: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


class _FramePlan:
    """``native_fit.frame_call``'s packed arguments: ``args`` (ctypes int64, the tables' and view's slots
    written once), ``key`` what they were made from (compared by identity / value), ``keep`` the tensors
    whose addresses they hold."""

    __slots__ = ("args", "key", "keep", "fn", "lib", "hold")

    def __init__(self, args, key, keep, fn, lib):
        self.args, self.key, self.keep, self.fn, self.lib = args, key, keep, fn, lib
        self.hold = (None, 0)  # (the H this route made last, its address)

# Default of the `separate` config (Sun §4.1 lobe separation): on, it lowers the Fig. 11 RMSEs of
# chess and alcove (numbers in the class docstring).
SEPARATE_DEFAULT = True


# BRDF_STAGE_THREADS: a VB frame's BRDF stage — the run-time fit of each changed material
# (`PTT.coords`: a few dozen eager ops on the 25 200 fit pairs and a 4×4 solve) and the region
# tables (`fast.region_tables`: Σ_p of lane-wise products over every region) — runs on one torch
# thread. Its ops are small, and with 2 threads on a loaded machine each one's OpenMP region spent
# ~10x its work waiting: chess bench, 2 threads, load ~10 on 2 cores, process CPU time, same
# process, alternating: one material's fit 14.1 ms vs 1.38 ms under torch_threads(1), the region
# tables 12.8 ms vs 1.0 ms (so the perf run's chess VB frame, 2.5x the V frame, paid ~3 fits and
# the tables at ~10x; the creature fits one material on 2 basis functions). One thread also makes
# these results independent of the thread count by construction (``methods.core.threads``).
# On an idle machine (load ~2) it is neutral: chess VB 2 threads 9.2 vs 9.2 ms wall, 1 thread 15.3 vs
# 15.0 ms; creature VB 2 threads 7.9 vs 8.0 ms. The same for the view stage's pair rows
# (`fast.vertex_view`) was 1.5-1.6x under load but 0.86x idle (chess V, 2 threads): not adopted.


# FAST_COORDS (session 40, pt40): `coords` takes `transport.LobeBasis.coords_rows` (the fit's float64
# values as Python floats, without the unit-lobe material and most small tensor ops; the same bits,
# tested) and hands back the last H when every region's material is the very object of the last call
# (V / L / E frames: no hashing of the materials each frame). Off: the per-material `basis.coords`.
# Measured in frames (chess bench, 1 thread, process CPU, settled, medians of 7–9 frames): a VB frame's
# coords (three fits) 0.75 -> 0.55 ms, a V frame's 0.12 -> 0.03 ms; serial also at 2 threads.
FAST_COORDS = True

# TABLE_THREADS (session 40, pt40): a VB frame's W_r (`fast.region_tables`, 3 × 2304 rows of 48 lanes
# on the chess bench, 1.3 MB) by ``native.region_tables``: its rows split over the frame's threads and
# written into the previous frame's table (no fresh pages), the lanes read from H directly; the rest of
# the BRDF stage stays on one thread (BRDF_STAGE_THREADS). The same bits at any thread count (each row
# one thread's; tested). Measured (`benchmarks.ptt_region_tables`, chess bench shapes, after a 64 MB
# pass, the threads awake): 0.51 -> 0.18 ms at 2 threads; 0.52 -> 0.34 ms process CPU at 1 thread.
TABLE_THREADS = True


# FIT_BATCH (session 41, pt41): when a region's material object changed, every region's material fitted in
# ONE C call (``native_fit.fit_materials``: coords_rows' float64 operations — the torch ops' own pow / exp /
# dgemv, MKL set to one thread by ``MKL_Set_Num_Threads_Local`` instead of ``torch_threads(1)`` — and
# float32 rounding, the materials dealt to the frame's threads; the same bits, tested) instead of the memo
# look-ups and coords_rows per new material (a few torch ops each, run cold after the harness's G-buffer).
# Off, or where it declines (a basis lobe's own material, another type, no compiler): the memoised path.
FIT_BATCH = True


def _check_int(name: str, v: Any, lo: int) -> int:
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise ValueError(f"{name} must be an int >= {lo}, got {v!r}")
    return v


def _check_pow2(name: str, v: Any) -> int:
    _check_int(name, v, 1)
    if v & (v - 1):
        raise ValueError(f"{name} must be a power of two, got {v}")
    return v


@register
class PTT(Method):
    """Sun 2007 precomputed transfer tensors: dynamic lighting, view and BRDFs; 0–2 bounces.

    Config (keyword-only; everything that changes a score):
        bounces: 0 (direct), 1 or 2 interreflections.
        basis: "scene" / None: `transport.scene_basis` (Lambert + the scene's own specular lobes,
            exact for them; a changed material — another exponent or roughness — is least-squares
            fitted onto those lobes). "pca": the paper's basis (Sun §3.1, §4.3): per specular family
            of the scene (Blinn-Phong, Cook-Torrance, Phong) the ``pca_terms``-term PCA of its BRDF
            space (``methods.ptt.pca.family_pca_basis``; paper: 4 specular + 1 diffuse), so any
            point of the space is exact navigation weights → H. Or a `transport.BRDFBasis` object.
        pca_terms, pca_grid: specular PCA terms per family and the disk-grid resolution of the PCA
            (only with basis="pca").
        n_wi: K incident factors of the shading factorization (paper 8).
        n_wo: rank of its view mode (paper 8; None = full table resolution): the Tucker form of
            Sun eq. 2–3 with the h mode = the basis (`transport.factor_basis`).
        brdf_grid, brdf_table: disk-grid resolutions of the factorization SVD and its look-up tables.
        cube_res: N of the 6×N×N direct-lighting cube map (paper 64); n_L: kept coefficients per k
            (paper 96); area_weighted: Ng 2003 area-weighted selection (paper).
        light_res_1, light_res_2: coarse lighting of the one-/two-bounce PTTs (paper 8, 2).
        sh_order: SH order of the one-bounce incident radiance (paper 4).
        rays: hemisphere rays per vertex for the PTTs; light_supersample: env → cube sub-samples.
        seed: ray-rotation seed.
        compress: None (dense T¹) or dict(clusters=, eigenvectors=, light_dim=) for the CPCA +
            clustered tensor approximation of T¹ (``methods.ptt.compress``; paper 32 / 64, about
            one cluster per 1000 vertices).
        separate: Sun §4.1 run-time specular lobes (``methods.ptt.specular``): the factorization
            and transport see only the remainder f_r = f − f_s; f_s is rendered per sample from
            prefiltered env maps × per-vertex fractional visibility (+ the one-bounce SH radiance).
            Default True (SEPARATE_DEFAULT), measured with ``python -m benchmarks.ptt --size
            test`` (rays 64, cube 16; RMSE vs Mitsuba of the same bounce count, direct / +1 / +2):
            chess 0.0616 / 0.0654 / 0.0665 → 0.0528 / 0.0563 / 0.0576 (direct mean 0.201 → 0.214,
            reference 0.224); alcove 0.0109 / 0.0121 / 0.0124 → 0.0092 / 0.0104 / 0.0110. Costs
            precompute (lobe fit, remainder factorization, prefilter kernels: alcove 3.9 → 5.3 s,
            chess 8.6 → 16.5 s on a loaded 2-core machine), 4 KiB per vertex of lobe visibility,
            ~16 MB of prefilter kernels, and ≈ 2× the V-frame time at test size.
        lobe_degrees: the lobe sizes k (paper 0, 7, 14, 21; 3σ_k = k°, 0 = mirror).
        lobe_theta, lobe_fit_samples: θo nodes of the lobe-weight tables and ωi samples of their fit.
        lobe_vis_res, lobe_vis_samples: T of the per-vertex T×T fractional-visibility tables and
            the local sample count they are filtered from.
        env_res: finest cube resolution of the prefiltered env maps.
        shading: "vertex" (default: Sun's per-vertex run time, module docstring) or "pixel" (the
            view stage per G-buffer sample). The precomputation does not depend on it
            (`with_shading` shares it).
    """

    name = "ptt"
    cache_precompute = True  # the nightly's 15 cells per scene share one precomputation (reports.precompute_cache)
    capabilities = Capabilities(dynamic_lighting=True, dynamic_brdf=True,
                                dynamic_geometry=False, max_bounces=2,
                                brdfs=frozenset({"lambert", "phong", "blinnphong", "cooktorrance"}))

    def __init__(self, *, bounces: int = 2, basis: Any = None, n_wi: int = 16, brdf_grid: int = 24,
                 brdf_table: int = 48, cube_res: int = 32, n_L: int = 96, area_weighted: bool = True,
                 light_res_1: int = 8, light_res_2: int = 2, sh_order: int = 4, rays: int = 128,
                 light_supersample: int = 2, seed: int = 0, compress: dict | None = None, n_wo: int | None = None,
                 separate: bool = SEPARATE_DEFAULT, lobe_degrees: Any = _lobes.LOBE_DEGREES,
                 lobe_theta: int = 32, lobe_fit_samples: int = 16384, lobe_vis_res: int = 16,
                 lobe_vis_samples: int = 4096, env_res: int = 32, pca_terms: int = _pca.N_SPEC,
                 pca_grid: int = 16, shading: str = SHADING_DEFAULT) -> None:
        if isinstance(bounces, bool) or bounces not in (0, 1, 2):
            raise ValueError(f"bounces must be 0, 1 or 2, got {bounces!r}")
        if basis == "scene":
            basis = None
        if basis is not None and basis != "pca" and not isinstance(basis, _tp.BRDFBasis):
            raise ValueError(f"basis must be 'scene' (or None), 'pca' or implement BRDFBasis (n_P, eval, coords), "
                             f"got {basis!r}")
        _check_int("pca_terms", pca_terms, 1)
        _check_int("pca_grid", pca_grid, 2)
        _check_int("n_wi", n_wi, 1)
        _check_int("brdf_grid", brdf_grid, 2)
        _check_int("brdf_table", brdf_table, 2)
        _check_pow2("cube_res", cube_res)
        _check_int("n_L", n_L, 1)
        _check_pow2("light_res_1", light_res_1)
        _check_pow2("light_res_2", light_res_2)
        if light_res_1 > cube_res or light_res_2 > light_res_1:
            raise ValueError(f"need light_res_2 <= light_res_1 <= cube_res, got {light_res_2}, {light_res_1}, {cube_res}")
        _check_int("sh_order", sh_order, 1)
        _check_int("rays", rays, 1)
        _check_int("light_supersample", light_supersample, 1)
        if compress is not None:
            if not isinstance(compress, dict) or set(compress) != {"clusters", "eigenvectors", "light_dim"}:
                raise ValueError("compress must be None or a dict with keys clusters, eigenvectors, light_dim")
            for k, v in compress.items():
                _check_int(f"compress[{k!r}]", v, 1)
            compress = dict(compress)
        if n_wo is not None:
            _check_int("n_wo", n_wo, 1)
        if not isinstance(separate, bool):
            raise ValueError(f"separate must be a bool, got {separate!r}")
        lobe_degrees = list(_spec.check_lobe_degrees(lobe_degrees))
        _check_int("lobe_theta", lobe_theta, 2)
        _check_int("lobe_fit_samples", lobe_fit_samples, 16)
        _check_int("lobe_vis_res", lobe_vis_res, 2)
        _check_int("lobe_vis_samples", lobe_vis_samples, 16)
        if shading not in SHADINGS:
            raise ValueError(f"shading must be one of {SHADINGS}, got {shading!r}")
        _check_pow2("env_res", env_res)
        if env_res < _spec.MIN_ENV_RES:
            raise ValueError(f"env_res must be >= {_spec.MIN_ENV_RES}, got {env_res}")
        basis_name = (basis if basis is None or basis == "pca"
                      else f"{type(basis).__module__}.{type(basis).__name__}(n_P={basis.n_P})")
        super().__init__(bounces=bounces, basis=basis_name, n_wi=n_wi,
                         brdf_grid=brdf_grid, brdf_table=brdf_table, cube_res=cube_res, n_L=n_L,
                         area_weighted=bool(area_weighted), light_res_1=light_res_1,
                         light_res_2=light_res_2, sh_order=sh_order, rays=rays,
                         light_supersample=light_supersample, seed=seed, compress=compress, n_wo=n_wo,
                         separate=separate, lobe_degrees=lobe_degrees, lobe_theta=lobe_theta,
                         lobe_fit_samples=lobe_fit_samples, lobe_vis_res=lobe_vis_res,
                         lobe_vis_samples=lobe_vis_samples, env_res=env_res, shading=shading,
                         **({"pca_terms": pca_terms, "pca_grid": pca_grid} if basis == "pca" else {}))
        self.separate = separate
        self.bounces = bounces
        self._basis_arg = basis
        self.scene = None
        self.timings: dict[str, float] = {}
        self._reset_cache()

    def _reset_cache(self) -> None:
        self._env = None     # env map object of the cached lighting stage
        self._light = None   # (E0 (V,K,3), T1L (V,R,P,S,3) | None, T2L (V,R,P,R,P,3) | None)
        self._H = None       # (R, P, 3) coordinates of the cached BRDF stage
        self._E = None       # (V, K, 3) Σ_l C^L_l U^I_x(l, k, H)
        self._Ek = None      # separated lobes: prefiltered env maps E^(k) (EnvMap per lobe)
        self._I1k = None     # separated lobes: (V, L, S, 3) lobe-prefiltered one-bounce SH radiance
        self._coords: dict[Any, Any] = {}  # material -> its H row block (float32 tensor, or FAST_COORDS' floats)
        self._coords_last = None  # (the regions' material objects, H) of the last `coords` call
        self.stats = {"light": 0, "brdf": 0, "view": 0}  # how often each stage ran
        # fast path (`render`, ``methods.ptt.fast``): its own caches, same stages
        self._f_env = None    # env map object of the cached lighting products
        self._f_light = None  # (E0 (V,K,3), T1L (V,RP,S,3) | None, T2L (V,(RP)²,3) | None,
        #                       (E^(k) maps, their fast.LatLongStack) | None)
        self._f_H = None      # (R, P, 3) coordinates of the cached region tables
        self._f_tabs = None   # (W_r (R·T², K·3), a_r (R·n_θ, L·3) | None)
        self._f_wrows = None  # (W_tab, its fast.view_table_rows (P, T², K·3)): kept while W_tab is
        self._f_E = None      # (E (V, K·3), I1 | None) for the cached (lighting, H): the one-bounce SH
        # radiance, (V, S, 3) local frame (shading="vertex") or (V, 3·S) world frame (shading="pixel")
        self._last_view = None  # (num_samples, G-buffer, camera origin (3,)) of the last render (cost_terms)

    # -- precompute ------------------------------------------------------------------------------
    def precompute(self, scene) -> None:
        import time

        c = self.config
        t0 = time.perf_counter()
        geom = scene.geometry()
        self.scene = scene
        self.regions = list(scene.regions)
        self.V, self.F, self.N = geom.V.float(), geom.F.long(), geom.N.float()
        self.face_region = geom.face_region.long()
        if self._basis_arg == "pca":  # Sun §4.3: n_P = pca_terms + 1 per family's BRDF space
            self.basis = _pca.family_pca_basis(scene.materials, n_spec=c["pca_terms"], grid_n=c["pca_grid"])
        elif self._basis_arg is not None:
            self.basis = self._basis_arg
        else:
            self.basis = _tp.scene_basis(scene.materials)
        factored = self.basis
        self.lobe_table = self.lobe_vis = self.env_filters = self.lobe_sh = None
        # shared precompute (methods.base.shared_precompute): the lobe fit is a function of the
        # materials (scene_basis) and its settings; the lobe visibility tables of the geometry,
        # the cube-map rays and their settings; the env filters of their settings only
        memo = precompute_memo()
        gkey = geometry_key(self.V, self.F, self.N) if memo is not None else None
        if self.separate:  # Sun §4.1: only the remainder goes through the factorization
            lkey = None
            if memo is not None and self._basis_arg is None:
                lkey = ("ptt.lobe_table", hash_materials(scene.materials), tuple(self.regions),
                        tuple(c["lobe_degrees"]), c["lobe_theta"], c["lobe_fit_samples"])
            if lkey is not None and lkey in memo:
                self.lobe_table = memo[lkey]
            else:
                self.lobe_table = _spec.fit_lobe_table(self.basis, c["lobe_degrees"], n_theta=c["lobe_theta"],
                                                       fit_samples=c["lobe_fit_samples"])
                if lkey is not None:
                    memo[lkey] = self.lobe_table
            factored = _spec.RemainderBasis(self.basis, self.lobe_table)
        self.factors = _tp.factor_basis(factored, n_wi=c["n_wi"], grid=c["brdf_grid"], table=c["brdf_table"],
                                        n_wo=c["n_wo"])
        t1 = time.perf_counter()
        vis = make_visibility(self.V, self.F)
        N = c["cube_res"]
        P0 = _tp.ray_points(self.V, self.F)  # ray origins just inside each vertex's faces
        hook = None
        vkey = None
        if self.separate:
            degs = tuple(c["lobe_degrees"])
            vkey = ("ptt.lobe_vis", gkey, N, degs, c["lobe_vis_res"], c["lobe_vis_samples"]) if memo is not None else None
            if vkey is not None and vkey in memo:
                self.lobe_vis = memo[vkey]
                vkey = None  # nothing to store
            else:
                lv = _spec.lobe_visibility(c["lobe_degrees"], T=c["lobe_vis_res"], samples=c["lobe_vis_samples"])
                T = c["lobe_vis_res"]
                self.lobe_vis = torch.empty(self.V.shape[0], len(c["lobe_degrees"]), T, T)

                def hook(a, b, vb):  # reuse the direct transport's visibility rays
                    self.lobe_vis[a:b] = _spec.vertex_lobe_tables(lv, vb, self.N[a:b], N)

            fkey = ("ptt.env_filters", degs, c["env_res"])
            if memo is not None and fkey in memo:
                self.env_filters = memo[fkey]
            else:
                self.env_filters = _spec.env_filters(c["lobe_degrees"], c["env_res"])
                if memo is not None:
                    memo[fkey] = self.env_filters
            if self.bounces >= 1:
                self.lobe_sh = _spec.lobe_sh_kernels(c["lobe_degrees"], c["sh_order"])  # (L, order)
        self.dt = _tp.direct_transport(vis, P0, self.N, self.factors, N=N, n_L=c["n_L"],
                                       area_weighted=c["area_weighted"],
                                       coarse=c["light_res_1"] if self.bounces >= 1 else 0,
                                       visibility_hook=hook)
        self.dt.idx = self.dt.idx.to(torch.int32)  # run-time storage
        if vkey is not None:
            memo[vkey] = self.lobe_vis
        t2 = time.perf_counter()
        self.C = self.Cu = self.T1 = self.T2 = self.T1c = None
        R = len(self.regions)
        if self.bounces >= 1:
            self.blk1 = _tp.block_index(N, c["light_res_1"])
            self.C = _tp.sh_light_matrix(self.factors, c["sh_order"])  # (S, K)
            hits = _bounce.trace_hemispheres(vis, P0, self.N, c["rays"], seed=c["seed"])
            self.T1 = _bounce.one_bounce_ptt(hits, self.F, self.N, self.face_region, R, self.factors,
                                             self.dt.coarse, order=c["sh_order"])
            self.dt.coarse = None  # precompute-only
            if self.bounces >= 2:
                self.blk2 = _tp.block_index(N, c["light_res_2"])
                sub = _tp.block_index(c["light_res_1"], c["light_res_2"])  # 6n₂² block inside 6n₁²
                self.Cu = _tp.uniform_light_vector(self.factors)  # (K,)
                self.T2 = _bounce.two_bounce_ptt(hits, self.F, self.N, self.face_region, R, self.factors,
                                                 self.C, self.T1[..., sub].contiguous())
        t3 = time.perf_counter()
        self.T1c = None
        if self.T1 is not None and c["compress"] is not None:
            nv, R_, P_, S_, L1 = self.T1.shape
            self.T1c = _cmp.compress_ptt(self.T1.reshape(nv, R_ * P_ * S_, L1), seed=c["seed"], **c["compress"])
            self.T1 = None
        t4 = time.perf_counter()
        self._fs = None
        self._fast_static()  # run-time layouts and per-vertex frames of the fast path
        t5 = time.perf_counter()
        self.timings = {"brdf_factorization": t1 - t0, "direct": t2 - t1, "bounces": t3 - t2,
                        "compress": t4 - t3, "fast_layout": t5 - t4, "total": t5 - t0}
        self._reset_cache()

    def _fast_static(self) -> _fast.FastStatic:
        """The fast path's static arrays (``fast.FastStatic``), built once (also for a method
        unpickled from before they existed); T² and the lobe-visibility tables are re-laid out
        lighting-last / texel-major and T¹ (vertex, SH)-major in place (the reference path reads views
        of the same storage).
        The per-vertex SH rotations are built only when shading="pixel" needs them."""
        need_sh = self.separate and self.bounces >= 1 and self.config["shading"] == "pixel"
        fs = getattr(self, "_fs", None)
        if fs is None or fs.pair_pos is None or (need_sh and fs.sh_rot is None):
            if self.T2 is not None and not self.T2.permute(0, 2, 3, 4, 5, 1).is_contiguous():
                self.T2 = _fast.relayout_t2(self.T2)
            if self.T1 is not None and not self.T1.permute(0, 3, 1, 2, 4).is_contiguous():
                self.T1 = _fast.relayout_t1(self.T1)
            if self.lobe_vis is not None and not self.lobe_vis.permute(0, 2, 3, 1).is_contiguous():
                self.lobe_vis = self.lobe_vis.permute(0, 2, 3, 1).contiguous().permute(0, 3, 1, 2)
            self._fs = _fast.build_static(self.V, self.N, self.F, self.face_region, len(self.regions),
                                          self.config["sh_order"] if need_sh else None)
        return self._fs

    def with_shading(self, shading: str) -> "PTT":
        """A copy sharing this precomputation whose view stage shades per ``shading`` ("vertex" |
        "pixel"; the precomputation does not depend on it)."""
        import copy

        if shading not in SHADINGS:
            raise ValueError(f"shading must be one of {SHADINGS}, got {shading!r}")
        m = copy.copy(self)
        m._config = {**self._config, "shading": shading}
        m._reset_cache()
        return m

    def with_bounces(self, bounces: int) -> "PTT":
        """A copy sharing this precomputation that renders only ``bounces`` (<= self.bounces)
        interreflections (Fig. 11's direct / +1 / +2 columns from one precompute)."""
        import copy

        if isinstance(bounces, bool) or bounces not in (0, 1, 2) or bounces > self.bounces:
            raise ValueError(f"bounces must be 0..{self.bounces}, got {bounces!r}")
        m = copy.copy(self)
        m._config = {**self._config, "bounces": bounces}  # a new method: its config says what it renders
        m.bounces = bounces
        if bounces < 2:
            m.T2 = m.Cu = None
        if bounces < 1:
            m.T1 = m.T1c = m.C = m.lobe_sh = None
        m._reset_cache()
        return m

    # -- run time ---------------------------------------------------------------------------------
    def coords(self, materials: dict[str, Any]) -> Tensor:
        """H (R, n_P, 3) float32 of a frame's materials (memoised per material)."""
        mats = [materials[r] for r in self.regions]
        last = getattr(self, "_coords_last", None)  # (absent on a method unpickled from before it existed)
        if FAST_COORDS and last is not None and all(a is b for a, b in zip(last[0], mats)):
            return last[1]  # the same material objects as the last call (a V / L frame): the same H
        if FIT_BATCH and FAST_COORDS and hasattr(self.basis, "coords_rows"):
            # every region's material in one C call (no memo look-ups: the same bits as a memoised H), MKL's
            # products on one thread (BRDF_STAGE_THREADS), the materials dealt to the frame's threads
            from methods.ptt import native_fit

            H = native_fit.fit_materials(self.basis, mats, torch.get_num_threads())
            if H is not None:
                self._coords_last = (mats, H)
                return H
        rows = []
        for m in mats:
            h = self._coords.get(m) if FAST_COORDS else None
            if h is None and m not in self._coords:
                # one thread (BRDF_STAGE_THREADS): the fit's ops are small
                with torch_threads(1):
                    fast = self.basis.coords_rows(m) if FAST_COORDS and hasattr(self.basis, "coords_rows") else None
                    self._coords[m] = fast if fast is not None else torch.as_tensor(self.basis.coords(m),
                                                                                    dtype=torch.float32)
            rows.append(self._coords[m])
        if all(isinstance(h, list) for h in rows):  # float64 values rounded to float32 once (as_tensor's rounding)
            H = torch.tensor(rows, dtype=torch.float32)
        else:
            H = torch.stack([h if isinstance(h, Tensor) else torch.tensor(h, dtype=torch.float32) for h in rows])
        self._coords_last = (mats, H)
        return H

    def _lighting_stage(self, envmap) -> None:
        c = self.config
        cubes: dict = {}  # resampled cube maps, shared by the Haar transform and the lobe prefilters
        CL = _tp.env_haar(envmap, c["cube_res"], supersample=c["light_supersample"], cubes=cubes)  # (6N², 3)
        E0 = _tp.direct_incidence(self.dt, CL)  # (V, K, 3)
        T1L = T2L = None
        if self.T1 is not None:
            T1L = torch.einsum("vrpsl,lc->vrpsc", self.T1, CL[self.blk1])
        elif self.T1c is not None:
            R_, P_, S_ = len(self.regions), self.factors.n_P, self.C.shape[0]
            T1L = self.T1c.contract_light(CL[self.blk1]).reshape(-1, R_, P_, S_, 3)
        if self.T2 is not None:
            T2L = torch.einsum("vlrptq,lc->vrptqc", self.T2, CL[self.blk2])
        self._light = (E0, T1L, T2L)
        if self.separate:  # Sun §4.1 E^(k), on the env map's grid
            self._Ek = _spec.on_env_grid(_spec.prefilter_env(envmap, self.env_filters, supersample=c["light_supersample"],
                                                              cubes=cubes), envmap)
        self._env = envmap
        self.stats["light"] += 1

    def _brdf_stage(self, H: Tensor) -> None:
        E0, T1L, T2L = self._light
        E = E0.clone()
        self._I1k = None
        if T1L is not None:  # Sun §3.3 U^{I1}
            I1 = torch.einsum("rpc,vrpsc->vsc", H, T1L)
            E += torch.einsum("sk,vsc->vkc", self.C, I1)
            if self.lobe_sh is not None:  # Sun §4.1: lobes × one-bounce radiance, SH prefiltered per lobe
                f = _zh.expand_bands(self.lobe_sh)  # (L, S)
                self._I1k = f[None, :, :, None] * I1[:, None]  # (V, L, S, 3)
        if T2L is not None:  # Sun §3.3 U^{I2}
            I2 = torch.einsum("rpc,tqc,vrptqc->vc", H, H, T2L)
            E += self.Cu[None, :, None] * I2[:, None, :]
        self._E, self._H = E, H
        self.stats["brdf"] += 1

    def _check_frame(self, frame: Frame) -> Tensor:
        """H (R, P, 3) of the frame's materials; RuntimeError before precompute, ValueError for
        missing regions."""
        if self.scene is None:
            raise RuntimeError("call precompute(scene) before render()")
        missing = [r for r in self.regions if r not in frame.materials]
        if missing:
            raise ValueError(f"frame.materials lacks regions {missing}")
        return self.coords(frame.materials)

    # -- fast path (``methods.ptt.fast``; equals `_render_reference` to float32 round-off) --------
    def render(self, frame: Frame, gbuffer: GBuffer) -> Tensor:
        """Sun eq. 3–4 with the three cached stages (module docstring), batched (``methods.ptt.fast``)."""
        if FRAME_CALL and VIEW_FRAME:
            img = self._frame_call(frame, gbuffer)
            if img is not None:
                return img
        H = self._check_frame(frame)
        st = self._fast_static()
        if self._f_H is None and isinstance(self.basis, _tp.LobeBasis):
            # the run-time fit's static tables (transport.LobeBasis.prepare) in the first frame (the
            # harness's warm-up), not in the first timed VB frame (chess bench VB frame 1: 142 ms vs ~60)
            self.basis.prepare()
        light = self._f_light is None or "light" in frame.changed or frame.envmap is not self._f_env
        if light:
            self._fast_lighting(frame.envmap)
        brdf = self._f_H is None or "brdf" in frame.changed or not (H is self._f_H or torch.equal(H, self._f_H))
        if brdf:
            W_tab = self.factors.W_tab
            wr = self._f_wrows
            if wr is None or wr[0] is not W_tab:
                wr = self._f_wrows = (W_tab, _fast.view_table_rows(W_tab, self.factors.K))
            nt = torch.get_num_threads() if TABLE_THREADS else 1
            lobe_a = self.lobe_table.a if self.separate else None
            if FIT_BATCH:  # no threads switch: the native tables take nt, a_r one MKL thread, the rest 1 thread
                self._f_tabs = _fast.region_tables(H, W_tab, self.factors.K, lobe_a, wr[1], nt=nt, out=self._f_tabs,
                                                   one_thread=True)
            else:
                with torch_threads(1):  # BRDF_STAGE_THREADS (the native tables take their own nt: TABLE_THREADS)
                    self._f_tabs = _fast.region_tables(H, W_tab, self.factors.K, lobe_a, wr[1], nt=nt,
                                                       out=self._f_tabs)
            self._f_H = H
            if self._f_light[1] is not None or self._f_light[2] is not None:
                # E = E⁰ + the bounce terms, which depend on H (Sun eq. 4); without bounces E = E⁰
                # (and no I1) is the lighting's alone, so the cached rows stay valid: a VB frame of
                # the perf suite (bounces 0) does not copy E⁰ into them again (10 701 × 48 floats, chess:
                # 0.68 ms, 1 thread, process CPU time, load ~17; the same bits)
                self._f_E = None
        if self._f_E is None:  # Sun eq. 4 for (lighting, H)
            E0, T1L, T2L, _ = self._f_light
            E, I1 = _fast.brdf_products(H, E0, T1L, self.C, T2L, self.Cu)
            if I1 is None or self.lobe_sh is None:
                I1 = None
            elif self.config["shading"] == "pixel":  # world-frame SH, interpolated before evaluation
                I1 = torch.bmm(st.sh_rot, I1).transpose(1, 2).reshape(I1.shape[0], -1)  # (V, 3·S)
            self._f_E = (E.reshape(E.shape[0], -1).contiguous(), I1)
            self.stats["brdf"] += 1
        elif brdf:
            self.stats["brdf"] += 1
        self.stats["view"] += 1
        if self.config["shading"] == "pixel":
            return self._fast_view_pixel(frame, gbuffer, st)
        return self._fast_view_vertex(frame, gbuffer, st)

    def _fast_lighting(self, envmap) -> None:
        """Stage 1 (lighting products of Sun eq. 4) for ``envmap``."""
        c = self.config
        cubes: dict = {}  # resampled cube maps, shared by the Haar transform and the lobe prefilters
        CL = _tp.env_haar(envmap, c["cube_res"], supersample=c["light_supersample"], cubes=cubes)  # (6N², 3)
        E0 = _fast.direct_incidence(self.dt.idx, self.dt.val, CL)  # (V, K, 3)
        bounce = self.T1 is not None or self.T1c is not None
        T1L, T2L = _fast.lighting_products(self.T1, self.T1c, CL[self.blk1] if bounce else None, self.T2,
                                           CL[self.blk2] if self.T2 is not None else None,
                                           len(self.regions) * self.factors.n_P)
        Ek = None
        if self.separate:  # Sun §4.1 E^(k) on the env map's grid, stacked for the per-sample look-ups
            Ek = _spec.on_env_grid(_spec.prefilter_env(envmap, self.env_filters, supersample=c["light_supersample"],
                                                       cubes=cubes), envmap)
            # the texels written straight onto the lanes the compiled sample stage reads (fast.env_stack)
            L = len(Ek)
            C = 3 + 3 * L + (3 if bounce and self.lobe_sh is not None else 0)  # as _fast_view_vertex's
            vertex = FUSED_VIEW and c["shading"] == "vertex"
            Ek = (Ek, _fast.env_stack(Ek, _fast.table_width(C) if vertex else 0))
        self._f_light, self._f_env, self._f_E = (E0, T1L, T2L, Ek), envmap, None
        self.stats["light"] += 1

    def _fast_view_vertex(self, frame: Frame, gbuffer: GBuffer, st: _fast.FastStatic) -> Tensor:
        """Stage 3, shading="vertex": the pair rows of `fast.vertex_view`, then per hit sample one
        interpolation and the prefiltered maps at R (`fast.shade_samples`)."""
        c = self.config
        E, I1 = self._f_E
        Wr, ar = self._f_tabs
        if VIEW_FRAME and I1 is None and self.separate:
            img = self._view_frame(frame, gbuffer, st)
            if img is not None:
                return img
        cam = torch.as_tensor(frame.camera.origin, dtype=torch.float32, device=self.V.device)
        T, K = self.factors.W_tab.shape[-1], self.factors.K
        lobes = env = None
        L = 0
        if self.separate:
            L = len(c["lobe_degrees"])
            lobes = dict(ar=ar, n_theta=self.lobe_table.theta.shape[0], Tv=self.lobe_vis.shape[-1],
                         vis=self.lobe_vis.permute(0, 2, 3, 1).reshape(-1, L),  # a view (`_fast_static`)
                         I1=I1, f=None if I1 is None else _zh.expand_bands(self.lobe_sh), order=c["sh_order"])
            env = self._f_light[3][1]
        C = 3 + 3 * L + (3 if I1 is not None and self.separate else 0)  # columns B | s | u of the pair rows
        width = _fast.table_width(C) if FUSED_VIEW and env is not None else 0
        gb, B = gbuffer, _fast.SAMPLE_CHUNK
        self._last_view = (gb.num_samples, gb, cam)
        pixels = FUSED_VIEW and env is not None and (_fast.all_true(gb.hit) or bool(((gb.face == -1) != gb.hit).all()))
        if pixels and REFERENCED_PAIRS and _fast.native_shading():
            # the rows of the pairs the samples read only (REFERENCED_PAIRS), the faces remapped onto them
            full = _fast.referenced_view(st, gb.face, cam, Wr, E, T, K, lobes, width) if FULL_TABLE else None
            if full is not None:  # FULL_TABLE: the rows at the pairs' own positions
                fpc, table = full
            else:
                sel, fpc = _fast.referenced_pairs(st, gb.face)
                table = _fast.vertex_view(st, cam, Wr, E, T, K, lobes, width, pairs=sel)
            img = _fast.shade_pixels_fused(fpc, table, gb.face, gb.bary, gb.normal, gb.wo, env, L, gb.spp_side ** 2, C)
            if img is not None:
                return img.view(gb.height, gb.width, 3)
        table = _fast.vertex_view(st, cam, Wr, E, T, K, lobes, width)
        if FUSED_VIEW:  # compiled blocks of samples (fast.shade_samples_fused)
            # samples shaded and resolved per block (fast.shade_pixels_fused); a miss (face −1, the
            # G-buffer's contract, checked) reads the zero face of `fast.miss_face_pairs`: 0, as
            # GBuffer.resolve counts it
            if pixels:
                img = _fast.shade_pixels_fused(_fast.miss_face_pairs(st), table, gb.face, gb.bary, gb.normal, gb.wo,
                                               env, L, gb.spp_side ** 2, C)
                if img is not None:
                    return img.view(gb.height, gb.width, 3)
            if _fast.all_true(gb.hit):  # no gathers of the G-buffer
                S2 = gb.spp_side ** 2
                out = _fast.shade_samples_fused(st.face_pairs, table, gb.face, gb.bary, gb.normal, gb.wo, env, L, C)
                return _fast.box_filter(out, gb.height, gb.width, S2)
            out = torch.zeros(gb.num_samples, 3, dtype=torch.float32, device=self.V.device)
            hit = torch.nonzero(gb.hit).squeeze(-1)
            out[hit] = _fast.shade_samples_fused(st.face_pairs, table, gb.face[hit], gb.bary[hit],
                                                 gb.normal[hit] if env is not None else None,
                                                 gb.wo[hit] if env is not None else None, env, L, C)
            return gb.resolve(out)
        if _fast.all_true(gb.hit):  # no gathers of the G-buffer
            out = torch.empty(gb.num_samples, 3, dtype=torch.float32, device=self.V.device)
            for a in range(0, gb.num_samples, B):
                _fast.shade_samples(st.face_pairs, table, gb.face[a:a + B], gb.bary[a:a + B], gb.normal[a:a + B],
                                    gb.wo[a:a + B], env, L, out=out[a:a + B])
            return _fast.box_filter(out, gb.height, gb.width, gb.spp_side ** 2)
        out = torch.zeros(gb.num_samples, 3, dtype=torch.float32, device=self.V.device)
        hit = torch.nonzero(gb.hit).squeeze(-1)
        for a in range(0, hit.numel(), B):
            sel = hit[a:a + B]
            out[sel] = _fast.shade_samples(st.face_pairs, table, gb.face[sel], gb.bary[sel],
                                           gb.normal[sel] if env is not None else None,
                                           gb.wo[sel] if env is not None else None, env, L)
        return gb.resolve(out)

    def _frame_call(self, frame: Frame, gb: GBuffer) -> Tensor | None:
        """`FRAME_CALL`: the frame's image by ``native_fit.frame_call``, or None where the route of `render` below
        is to run (nothing changed then, except — the view call declining after a fit — the new H and tables,
        which that route then finds current, as it would have made them)."""
        vplan = _VIEW_PLANS.get(self)
        H0, E, light = self._f_H, self._f_E, self._f_light
        if vplan is None or H0 is None or E is None or E[1] is not None or light is None or not self.separate:
            return None
        changed = frame.changed
        if "light" in changed or frame.envmap is not self._f_env or self._config["shading"] != "vertex":
            return None
        tabs, st = self._f_tabs, getattr(self, "_fs", None)
        objs, vals = vplan.key
        if objs[0] is not tabs or objs[1] is not E or objs[2] is not light or objs[3] is not st or st.pair_pos is None:
            return None
        threads = torch.get_num_threads()
        if vals != (threads, _fast.USE_NATIVE, compile_enabled(), _pn.LEAN, FUSED_VIEW, REFERENCED_PAIRS, FULL_TABLE):
            return None
        face, bary, normal, wo, hit = gb.face, gb.bary, gb.normal, gb.wo, gb.hit
        if vplan.layout != _pn.gbuffer_layout(face, bary, normal, wo, hit, gb.spp_side, gb.height, gb.width):
            return None
        last = self._coords_last
        if not FAST_COORDS or last is None:
            return None
        fm = frame.materials
        try:
            mats = [fm[r] for r in self.regions]
        except KeyError:
            return None
        if len(mats) == len(last[0]) and all(a is b for a, b in zip(last[0], mats)):  # a V frame: `coords`' memo
            if last[1] is not H0 or "brdf" in changed:
                return None
            H, fa = H0, None
        else:  # a VB frame (bounce terms: E would depend on H)
            if not FIT_BATCH or light[1] is not None or light[2] is not None or not hasattr(self.basis, "coords_rows"):
                return None
            fa = True  # (the fit's arguments below, with the plan's library)
        fplan = self._frame_plan(vplan, tabs, threads, H0)
        if fplan is None:
            return None
        a = fplan.args
        if fa is not None:
            fa = _pnf.fit_args(self.basis, mats, threads, fplan.lib, team=threads)
            if fa is None:
                return None
            fargs = fa[1]
            H = torch.empty(fargs[0], fargs[8], 3, dtype=torch.float32)
            fargs[18] = H.data_ptr()
            a[0:20] = fargs
            # the last H's values (the equality test): its address where it is one of this route's own H, else
            # where it is laid out as H
            hold = fplan.hold
            a[20] = hold[1] if hold[0] is H0 else (
                H0.data_ptr() if H0.shape == H.shape and H0.is_contiguous() and H0.dtype == H.dtype else 0)
        else:
            a[0] = 0
        # the view call's per-frame slots, as `native.view_frame`
        va = vplan.args
        out = torch.empty(gb.height, gb.width, 3, dtype=torch.float32)
        p = bary.data_ptr()
        va[0], va[1], va[31], va[34], va[39], va[40], va[51] = (face.data_ptr(), hit.data_ptr(), normal.data_ptr(),
                                                                wo.data_ptr(), p, p + 4 * bary.stride(1), out.data_ptr())
        vplan.cam_c[0], vplan.cam_c[1], vplan.cam_c[2] = frame.camera.origin
        r = fplan.fn(a)
        if fa is not None:
            self._coords_last = (mats, H)
            self._f_H = H
            fplan.hold = (H, fargs[18])
            # the BRDF stage as the route counts it (H changed, or the frame says so); declined, the route runs
            # next and counts a frame that says so itself
            if (a[38] or "brdf" in changed) if r > 0 else (a[38] and "brdf" not in changed):
                self.stats["brdf"] += 1
        if r <= 0:
            return None
        self.stats["view"] += 1
        self._last_view = (gb.num_samples, gb, vplan.cam)
        return out

    def _frame_plan(self, vplan, tabs, threads: int, H0: Tensor) -> "_FramePlan | None":
        """The `_FramePlan` of this view plan and these region tables (made here where missing or made for
        others), or None where the route of `render` would not take the native tables in place
        (`fast.region_tables`' one-thread route: ``native.region_tables`` and ``native_fit.ar_table`` into
        the tables' own memory) or ``frame_call`` is not available."""
        _native, _nf = _pn, _pnf
        wr, lobe_a = self._f_wrows, self.lobe_table.a
        nt = threads if TABLE_THREADS else 1
        key = (vplan, tabs, wr, lobe_a, nt, _fast.USE_NATIVE, _fast.NATIVE_TABLES, _nf.FAST_FIT, FRAME_CHUNK)
        fplan = _FRAME_PLANS.get(self)
        if fplan is not None and len(fplan.key) == len(key) and all(x is y or (type(x) in (int, bool) and x == y) for x, y in zip(fplan.key, key)):
            return fplan
        _FRAME_PLANS.pop(self, None)
        fc = _nf.frame_call_fn()
        if fc is None or wr is None or wr[0] is not self.factors.W_tab or not (_fast.USE_NATIVE and _fast.NATIVE_TABLES):
            return None
        Wr, ar = tabs
        ta = _native.region_tables_args(wr[1], H0, nt, Wr)
        aa = _nf.ar_args(H0, lobe_a, ar)
        if ta is None or aa is None or ta[6] is not Wr or aa[-1] is not ar or ta[1].data_ptr() != wr[1].data_ptr():
            return None
        fn, W_rows, P, R, T2, K, _, ntt = ta
        _, Ra, Pa, n, L, hl, c, _ = aa
        if (Ra, Pa) != (R, P) or tuple(H0.shape) != (R, P, 3):
            return None
        args = (ctypes.c_int64 * fc[1])()
        v = dict(rows=ctypes.cast(fn.region_rows_range, ctypes.c_void_p).value, wrows=W_rows.data_ptr(), R=R, T2=T2,
                 K=K, wr=Wr.data_ptr(), team=max(1, threads), chunk=FRAME_CHUNK, la=lobe_a.data_ptr(), n=n, L=L, sgemm=_nf._library()[5], hl=hl.data_ptr(),
                 c=c.data_ptr(), ar=ar.data_ptr(), view=ctypes.cast(vplan.fn.view_frame, ctypes.c_void_p).value,
                 vargs=ctypes.addressof(vplan.args))
        for k, x in v.items():
            args[_nf._FC[k]] = int(x)
        fplan = _FRAME_PLANS[self] = _FramePlan(args, key, (W_rows, lobe_a, hl, c, Wr, ar), fc[0], _nf._library())
        return fplan

    def _view_frame(self, frame: Frame, gb: GBuffer, st: _fast.FastStatic) -> Tensor | None:
        """`VIEW_FRAME`: the frame's image by ``native.view_frame`` on this method's plan (made or remade here
        when its key or the G-buffer layout changed), or None (no plan here, or the call declined: nothing
        shaded). The camera origin is written into the plan's (3,) float32 tensor (the float32 rounding of
        ``torch.as_tensor``), which `_last_view` holds as the last frame's camera (`cost_terms`)."""
        from methods.ptt import native as _native

        tabs = self._f_tabs
        objs = (tabs, self._f_E, self._f_light, st)  # compared by identity
        vals = (torch.get_num_threads(), _fast.USE_NATIVE, compile_enabled(), _native.LEAN, FUSED_VIEW,
                REFERENCED_PAIRS, FULL_TABLE)
        face, bary, normal, wo, hit = gb.face, gb.bary, gb.normal, gb.wo, gb.hit
        layout = _native.gbuffer_layout(face, bary, normal, wo, hit, gb.spp_side, gb.height, gb.width)
        plan = _VIEW_PLANS.get(self)
        if plan is None or plan.layout != layout or plan.key[1] != vals or not all(
                x is y for x, y in zip(plan.key[0], objs)):
            if plan is not None and plan.layout == layout and plan.key[1] == vals and all(
                    x is y for x, y in zip(plan.key[0][1:], objs[1:])) and plan.same_tables(*tabs):
                plan.key = (objs, vals)  # a VB frame's tables rewritten in place (``native.region_tables``' out)
            else:
                plan = self._make_view_plan(gb, st, (objs, vals), layout)
                if plan is None:
                    _VIEW_PLANS.pop(self, None)
                    return None
                _VIEW_PLANS[self] = plan
        plan.cam_c[0], plan.cam_c[1], plan.cam_c[2] = frame.camera.origin
        img = _native.view_frame(plan, face, bary, normal, wo, hit, gb.height, gb.width)
        if img is not None:
            self._last_view = (gb.num_samples, gb, plan.cam)
        return img

    def _make_view_plan(self, gb: GBuffer, st: _fast.FastStatic, key: tuple, layout: tuple):
        """``native.view_plan`` for the route `_fast_view_vertex` takes with FULL_TABLE and the native
        sample stage on a whole-block frame, or None where that route would not be taken."""
        from methods.ptt import native as _native

        if not (FUSED_VIEW and REFERENCED_PAIRS and FULL_TABLE and self.separate and _fast.USE_NATIVE
                and _fast.native_shading() and self.config["shading"] == "vertex"):
            return None
        E, I1 = self._f_E
        Wr, ar = self._f_tabs
        if I1 is not None or ar is None:
            return None
        T, K = self.factors.W_tab.shape[-1], self.factors.K
        L = len(self.config["lobe_degrees"])
        Tv = self.lobe_vis.shape[-1]
        vis = self.lobe_vis.permute(0, 2, 3, 1).reshape(-1, L)
        if max(int(Wr.shape[0]), int(vis.shape[0])) >= 2 ** 31 - Tv * Tv - T * T:
            return None
        C = 3 + 3 * L
        width = _fast.table_width(C)
        q, S2 = int(gb.face.shape[0]), gb.spp_side ** 2
        if q % S2 or q == 0:  # (any block size: each pixel's result is its own samples' alone, as the blocks')
            return None
        env = self._f_light[3][1]
        _, erows, lanes = _fast._fused_inputs(torch.empty(0, width), env, L, C)
        ri, vi = _fast.pair_indices32(st)
        return _native.view_plan(st.face_pairs, _fast.miss_face_pairs(st), st.pair_pos, st.pair_frame, ri, vi, T, Tv,
                                 self.lobe_table.theta.shape[0], Wr, E, K, ar, vis, width, env.to_world, env.H, erows,
                                 lanes, env.W, S2, gb.face, gb.bary, gb.normal, gb.wo, gb.hit, key, layout)

    def _fast_view_pixel(self, frame: Frame, gbuffer: GBuffer, st: _fast.FastStatic) -> Tensor:
        """Stage 3, shading="pixel", at the G-buffer's hit samples, FAST_CHUNK samples at a time."""
        c = self.config
        E, I1w = self._f_E
        Wr, ar = self._f_tabs
        T, K = self.factors.W_tab.shape[-1], self.factors.K
        cam = torch.as_tensor(frame.camera.origin, dtype=torch.float32, device=self.V.device)
        window = min(_fast.WINDOW, T)
        win = _fast.view_windows(st, self.V, cam, Wr, E, T, K, window)
        out = torch.zeros(gbuffer.num_samples, 3, dtype=torch.float32, device=self.V.device)
        hit = torch.nonzero(gbuffer.hit).squeeze(-1)
        if self.separate:
            Tv = self.lobe_vis.shape[-1]
            vis_rows = self.lobe_vis.permute(0, 2, 3, 1).reshape(-1, self.lobe_vis.shape[1])  # a view
        for a in range(0, hit.numel(), FAST_CHUNK):
            sel = hit[a:a + FAST_CHUNK]
            face = gbuffer.face[sel]
            vidx = _fast.rows(self.F, face)
            u, v = gbuffer.bary[sel].float().unbind(-1)
            bw = torch.stack([1.0 - u - v, u, v], -1)
            wo = gbuffer.wo[sel].float()
            region = gbuffer.region[sel]
            fq = _fast.rows(st.frames, vidx)  # (Q, 3, 3, 3)
            if self.separate:
                n, R = _fast.reflection(gbuffer.normal[sel].float(), wo)
                loc = _fast.to_vertex_frames(fq, torch.stack([wo, R], -1))  # (Q, 3, 3, 2): ωo, R per vertex
            else:
                loc = _fast.to_vertex_frames(fq, wo[:, :, None])
            res = _fast.shade(st, win, Wr, E, T, K, vidx, bw, region, loc[..., 0], window)
            if self.separate:
                res = res + _fast.specular_lobes(self.lobe_table.theta.shape[0], ar, self._f_light[3][0], vis_rows, Tv,
                                                 I1w, self.lobe_sh, c["sh_order"], n, R, wo, region, vidx, bw,
                                                 loc[..., 1])
            out[sel] = res
        self._last_view = (gbuffer.num_samples, gbuffer, cam)
        return gbuffer.resolve(out)

    # -- reference path: the stages as written in Sun's notation (the test oracle of the fast path) --
    def _render_reference(self, frame: Frame, gbuffer: GBuffer) -> Tensor:
        """The per-stage reference implementation (slow; kept as the fast path's test oracle)."""
        H = self._check_frame(frame)
        if self._light is None or "light" in frame.changed or frame.envmap is not self._env:
            self._lighting_stage(frame.envmap)
            self._E = None
        if self._E is None or "brdf" in frame.changed or not torch.equal(H, self._H):
            self._brdf_stage(H)
        self.stats["view"] += 1
        out = torch.zeros(gbuffer.num_samples, 3, dtype=torch.float32)
        hit = torch.nonzero(gbuffer.hit).squeeze(-1)
        vidx, bw = gbuffer.vertex_weights(self.F)
        if self.config["shading"] == "vertex":
            keys, B, s, u = self._vertex_terms(torch.as_tensor(frame.camera.origin, dtype=torch.float32), H)
            for a in range(0, hit.numel(), RENDER_CHUNK):
                sel = hit[a:a + RENDER_CHUNK]
                out[sel] = self._shade_vertex(keys, B, s, u, vidx[sel], bw[sel], gbuffer.region[sel],
                                              gbuffer.normal[sel].float(), gbuffer.wo[sel].float())
            return gbuffer.resolve(out)
        for a in range(0, hit.numel(), RENDER_CHUNK):
            sel = hit[a:a + RENDER_CHUNK]
            out[sel] = self._shade(vidx[sel], bw[sel], gbuffer.wo[sel].float(), H[gbuffer.region[sel]])
        lobes = self._specular_lobes(gbuffer, H, hit, vidx, bw)
        if lobes is not None:
            out = out + lobes
        return gbuffer.resolve(out)

    def _vertex_terms(self, cam: Tensor, H: Tensor) -> tuple[Tensor, Tensor, Tensor | None, Tensor | None]:
        """shading="vertex": the per-vertex part of Sun eq. 3 at each vertex x's own view direction
        ωo_x = (cam − x)/|cam − x|, for every (vertex, region) pair of the mesh (a vertex shading one
        region's faces uses that region's BRDF H(r)):
        B_x = Σ_k g_x(k) E_x(k), g_x(k) = Σ_p H(r, p) W(p, ωo_x, k) (the glossy remainder);
        with lobes (§4.1), at the mirror direction R_x of ωo_x about n_x:
        s_x(k) = a_k(H, θo_x) V_c^(k)(x, R_x) and u_x = Σ_k a_k(H, θo_x) max(0, n_x·R_x) L1^(k)_x(R_x).
        cam (3,); H (R, P, 3). Returns keys (n,) = v·R + r sorted, B (n, 3), s (n, L, 3) | None,
        u (n, 3) | None."""
        R = len(self.regions)
        keys = torch.unique(self.F * R + self.face_region[:, None])
        v, r = keys // R, keys % R
        n = self.N[v]
        wo = cam[None, :] - self.V[v]
        wo = wo / wo.norm(dim=-1, keepdim=True)
        g = torch.einsum("npk,npc->nkc", self.factors.W(to_local(wo, n)), H[r])  # Sun eq. 3: D ×_h U^h ×_ωo U^ωo
        B = (g * self._E[v]).sum(1)
        if not self.separate:
            return keys, B, None, None
        Rw = reflect(wo, n)
        Rw = Rw / Rw.norm(dim=-1, keepdim=True)
        Rl = to_local(Rw, n)
        ak = torch.einsum("npl,npc->nlc", _spec.lobe_weights(self.lobe_table, (n * wo).sum(-1)), H[r])
        s = ak * _spec.lookup_vertex_tables(self.lobe_vis, v, Rl)[..., None]
        u = None
        if self._I1k is not None:
            Li = _spec.sh_at(self._I1k[v], Rl[:, None, :], self.config["sh_order"])  # (n, L, 3)
            u = (ak * Li.clamp_min(0.0)).sum(1) * (n * Rw).sum(-1).clamp_min(0.0)[:, None]
        return keys, B, s, u

    def _shade_vertex(self, keys: Tensor, B: Tensor, s: Tensor | None, u: Tensor | None, vidx: Tensor, bw: Tensor,
                      region: Tensor, normal: Tensor, wo: Tensor) -> Tensor:
        """shading="vertex" at samples: the `_vertex_terms` of the sample's triangle interpolated with
        its barycentrics β, max(0, Σ_v β_v B_v) + Σ_v β_v u_v + Σ_k E^(k)(R) Σ_v β_v s_v(k), R the
        mirror direction of ωo about the interpolated shading normal. vidx, bw (Q, 3); region (Q,);
        normal, wo (Q, 3) → (Q, 3)."""
        j = torch.searchsorted(keys, vidx * len(self.regions) + region[:, None])  # (Q, 3) pair of each vertex
        out = (bw[..., None] * B[j]).sum(1).clamp_min(0.0)
        if s is None:
            return out
        if u is not None:
            out = out + (bw[..., None] * u[j]).sum(1)
        E = []
        for e in self._Ek:  # E^(k)(R): each map by Mitsuba's bilinear look-up
            # (u, v) of R: the one compiled formula the fast path reads the maps with (fast.mirror_uv)
            idx, w = _spec._uv_cells(*_fast.mirror_uv(normal, wo, e.to_world), e.height, e.width)
            E.append((extend_periodic(e.data)[idx] * w[..., None]).sum(1))
        return out + ((bw[..., None, None] * s[j]).sum(1) * torch.stack(E, 1)).sum(1)

    def _shade(self, vidx: Tensor, bw: Tensor, wo: Tensor, Hs: Tensor) -> Tensor:
        """shading="pixel": eq. 3 at samples: vidx, bw (Q, 3); wo (Q, 3) world; Hs (Q, P, 3) → (Q, 3)."""
        B = torch.zeros(wo.shape[0], 3)
        for j in range(3):
            v = vidx[:, j]
            W = self.factors.W(to_local(wo, self.N[v]))  # (Q, P, K)
            g = torch.einsum("qpk,qpc->qkc", W, Hs)
            B += bw[:, j, None] * (g * self._E[v]).sum(1)
        return B.clamp_min(0.0)

    def _specular_lobes(self, gbuffer: GBuffer, H: Tensor, hit: Tensor, vidx: Tensor, bw: Tensor) -> Tensor | None:
        """Sun §4.1 separated lobes at the hit samples (``methods.ptt.specular`` docstring):
        Σ_k a_k(H, θo) [E^(k)(R) Σ_v β_v V_c^(k)(v, R) + max(0, n·R) Σ_v β_v L1^(k)_v(R)].
        H (R, P, 3); hit (Q,) sample indices; vidx, bw (P, 3). Returns (P, 3) or None (no separation)."""
        if not self.separate:
            return None
        out = torch.zeros(gbuffer.num_samples, 3, dtype=torch.float32)
        for a in range(0, hit.numel(), RENDER_CHUNK):
            sel = hit[a:a + RENDER_CHUNK]
            n = gbuffer.normal[sel].float()
            n = n / n.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            wo = gbuffer.wo[sel].float()
            R = reflect(wo, n)
            R = R / R.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            A = _spec.lobe_weights(self.lobe_table, (n * wo).sum(-1))  # (Q, P, L)
            ak = torch.einsum("qpl,qpc->qlc", A, H[gbuffer.region[sel]])  # Σ_p H(r, p) a_k^p(θo)
            E = torch.stack([e.radiance(R) for e in self._Ek], 1)  # (Q, L, 3)
            Vc = torch.zeros(sel.numel(), ak.shape[1])
            Li = torch.zeros_like(ak) if self._I1k is not None else None
            for j in range(3):
                v = vidx[sel, j]
                Rl = to_local(R, self.N[v])
                Vc += bw[sel, j, None] * _spec.lookup_vertex_tables(self.lobe_vis, v, Rl)
                if Li is not None:
                    Li += bw[sel, j, None, None] * _spec.sh_at(self._I1k[v], Rl[:, None, :], self.config["sh_order"])
            L = E * Vc[..., None]
            if Li is not None:
                L = L + Li.clamp_min(0.0) * (n * R).sum(-1).clamp_min(0.0)[:, None, None]
            out[sel] = (ak * L).sum(1)
        return out

    def frame_cost(self, frame_kind: str, num_samples: int, *, pixels: int | None = None) -> FrameCost | None:
        """Compulsory work of one frame of ``frame_kind`` on ``num_samples`` G-buffer samples and an image
        of ``pixels`` pixels (the roofline numerators, ``methods.base.FrameCost``): the sums of `cost_terms`."""
        terms = self.cost_terms(frame_kind, num_samples, pixels=pixels)
        if terms is None:
            return None
        nbytes, flops = terms
        return FrameCost(int(sum(nbytes.values())), int(sum(flops.values())))

    def bytes_per_frame(self, frame_kind: str = "VBL") -> int | None:
        """Deprecated (``benchmarks/ptt.py`` still prints it): `frame_cost` bytes on the last
        rendered G-buffer's sample count."""
        cost = self.frame_cost(frame_kind, self._last_view[0] if self._last_view is not None else 0)
        return None if cost is None else cost.bytes

    def cost_terms(self, frame_kind: str, num_samples: int, *, pixels: int | None = None
                   ) -> tuple[dict[str, int], dict[str, int]] | None:
        """(bytes by array, flops by equation) of one frame; None before `precompute`.

        Stages (Sun Table 1): "V" runs the view stage only; "VB" also the BRDF stage (H products);
        "VBL" and the lighting kinds "L", "E", "VL" also the lighting stage (L, E, VL keep H, so the
        per-region tables are not rebuilt). Each array is counted once per frame (a perfect cache):
        a cache the frame rebuilds counts as its write, one it reuses as the read of the rows (or
        texels) the frame references.

        Minimum arithmetic (multiply-add = 2 flops; direction transforms and the interpolations
        counted, transcendentals / SH polynomials / the env-map cube resampling and Haar transform
        not — a lower bound):
        * view, shading="vertex", per referenced (vertex, region) pair: ωo_x in x's frame (9 + 3),
          the glossy term Σ_k W_r(ωo_x, k) E_x(k) (bilinear 4·K·3 + K·3); with lobes (§4.1) a_k by
          2 θ nodes (2·L·3), V_c^(k) bilinear (4·L), s = a_k V_c (L·3), with bounces the SH term
          (Y·I S·3, lobe factors L·order·3, Σ_k a_k L1 L·3 + 3); per hit sample the interpolation
          of the C pair columns (3·C), with lobes R (6), E^(k) bilinear (4·L·3) and Σ_k s E (L·3);
        * view, shading="pixel", per hit sample: the glossy term in the reassociated form
          X(v, r, texel) = Σ_k W_r(texel, k) E_v(k) — at least one bilinear cell (4 texels) per
          referenced (vertex, region) pair, K·3 MACs each — then 3 vertices × 4 corners × 3 MACs per
          sample, and ωo in 3 vertex frames (27 MACs); with lobes (§4.1) R in 3 frames (27), a_k by 2
          θ nodes (2·L·3), E^(k) bilinear (4·L·3), V_c^(k) (3·4·L), and with bounces the SH term
          (interpolation 3·S·3, Y·I S·3, lobe factors L·order·3), E·V_c + Li·cos (2·L·3), Σ_k (L·3);
        * BRDF stage (eq. 4), per vertex: Σ_{r,p} H T¹L (R·P·S·3), C^{ωi} (S·K·3), Σ H H T²L
          ((R·P)²·3), C^{ωi}(k) (K·3), with shading="pixel" the world-frame rotation of the SH
          radiance for the lobes (Σ_b (2b+1)²·3); when H changed, the per-region tables
          D ×_h U^h(H) (K·P·3 per texel: every texel with "pixel", the texels the view reads with
          "vertex") and lobe weights (R·n_θ·L·P·3);
        * lighting stage, per vertex: Σ_l C^L U^{I0} (K·n_L·3), T¹ (R·P·S·L1·3; compressed: the
          per-cluster contractions of ``compress``), T² (L2·(R·P)²·3); the lobe prefilters (nnz·3).

        Referenced rows, pairs, texels and the hit count come from the last `render` on a G-buffer
        of ``num_samples`` samples; without one, every sample is taken as a hit and every vertex,
        (vertex, region) pair and table texel as referenced (an upper bound of those terms)."""
        kinds = ("V", "VB", "VBL", "L", "E", "VL")
        if frame_kind not in kinds:
            raise ValueError(f"frame_kind must be one of {kinds}, got {frame_kind!r}")
        if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 0:
            raise ValueError(f"num_samples must be an int >= 0, got {num_samples!r}")
        if self.scene is None:
            return None
        st = self._fast_static()
        c, f4 = self.config, 4
        vertex = c["shading"] == "vertex"
        nv, nf = int(self.V.shape[0]), int(self.F.shape[0])
        K, P, R, S, order = self.factors.K, self.factors.n_P, len(self.regions), c["sh_order"] ** 2, c["sh_order"]
        T = self.factors.W_tab.shape[-1]
        light = frame_kind in ("VBL", "L", "E", "VL")
        brdf = "B" in frame_kind
        lobes = self.separate
        sh = lobes and self.lobe_sh is not None and (self.T1 is not None or self.T1c is not None)
        Lb = len(c["lobe_degrees"]) if lobes else 0
        n_theta = self.lobe_table.theta.shape[0] if lobes else 0
        env = self._f_env if self._f_env is not None else self.scene.envmap
        maps = [env.data.shape[:2]] * Lb  # E^(k) on the env map's grid (specular.on_env_grid)
        last = self._last_view if self._last_view is not None and self._last_view[0] == num_samples else None
        if last is not None:
            gb, cam = last[1], last[2]
            hit = torch.nonzero(gb.hit).squeeze(-1)
            faces = gb.face[hit]
            Q = int(faces.numel())
            ref_faces = int(torch.unique(faces).numel())
            ref_verts = int(torch.unique(self.F[faces]).numel())
            pairs = torch.unique(st.face_pairs[faces] if vertex
                                 else st.pair_of[self.F[faces] * R + gb.region[hit][:, None]])
        else:
            Q, ref_faces, ref_verts, pairs = num_samples, nf, nv, None
        ref_pairs = int(st.pair_v.numel()) if pairs is None else int(pairs.numel())
        # texels of the view tables (W_r, a_r) and lat-long maps (E^(k)) the view stage reads
        # (vertex mode: those of the last render; else every one): W_r texels (r, t) and texels t,
        # a_r rows (r, θ node) and θ nodes, texels of each map
        tex_W, tex_t, rows_a, nodes_a = R * T * T, T * T, R * n_theta, n_theta
        tex_maps = [h * w for h, w in maps]
        if vertex and last is not None:
            _, r, loc = _fast.pair_view_dirs(st, self.V, cam, pairs)
            ix, iy, _, _ = _fast._bilinear(table_coords(loc), T)
            cell = torch.stack([iy * T + ix, iy * T + ix + 1, (iy + 1) * T + ix, (iy + 1) * T + ix + 1])
            tex_W = int(torch.unique(r * (T * T) + cell).numel())
            tex_t = int(torch.unique(cell).numel())
            if lobes:
                i0, _ = _fast.theta_nodes(loc[:, 2], n_theta)
                node = torch.stack([i0, (i0 + 1).clamp(max=n_theta - 1)])
                rows_a = int(torch.unique(r * n_theta + node).numel())
                nodes_a = int(torch.unique(node).numel())
                uv = _fast.mirror_uv(gb.normal[hit].float(), gb.wo[hit].float(), env.to_world)
                idx, _ = _spec._uv_cells(*uv, env.height, env.width)
                tex_maps = [int(torch.unique(idx).numel())] * Lb  # one grid for every lobe (specular.on_env_grid)
        B, Fl = {}, {}
        # -- view stage (every frame)
        B["output"] = output_bytes(num_samples, pixels)  # the (H, W, 3) image
        B["faces"] = ref_faces * 3 * (8 if vertex else self.F.element_size())  # face_pairs (int64) / F
        if vertex:
            # G-buffer: face (int64), barycentrics, the hit flag; with lobes the shading normal and ωo
            B["gbuffer"] = Q * (8 + 8 + GBUFFER_HIT_BYTES + (24 if lobes else 0)) + (num_samples - Q) * GBUFFER_HIT_BYTES
            B["vertices"] = ref_verts * 6 * f4  # position + normal
            rows = {"E": ref_verts * K * 3 * f4, "W_r": tex_W * K * 3 * f4}
            if lobes:
                rows["lobe_visibility"] = min(ref_verts * 4 * Lb * f4, tensor_bytes(self.lobe_vis))  # >= one cell each
                rows["a_r"] = rows_a * Lb * 3 * f4
                B["env_maps"] = sum(tex_maps) * 3 * f4
            if sh:
                rows["I1"] = ref_verts * S * 3 * f4
            C = 3 + (3 * Lb if lobes else 0) + (3 if sh else 0)
            Fl["view_glossy"] = 2 * (ref_pairs * (12 + 4 * K * 3 + K * 3) + Q * 3 * C)
            if lobes:
                Fl["view_lobes"] = 2 * (ref_pairs * (2 * Lb * 3 + 4 * Lb + Lb * 3) + Q * (6 + 4 * Lb * 3 + Lb * 3))
                if sh:
                    Fl["view_lobes_sh"] = 2 * ref_pairs * (S * 3 + Lb * order * 3 + Lb * 3 + 3)
        else:
            # + region (int64); misses: hit flag
            B["gbuffer"] = Q * (GBUFFER_BYTES_PER_SAMPLE + 8) + (num_samples - Q) * GBUFFER_HIT_BYTES
            B["normals"] = ref_verts * 3 * f4
            rows = {"E": ref_verts * K * 3 * f4, "W_r": tex_W * K * 3 * f4}
            if lobes:
                rows["lobe_visibility"] = min(ref_verts * 4 * Lb * f4, tensor_bytes(self.lobe_vis))  # >= one cell each
                rows["a_r"] = rows_a * Lb * 3 * f4
                B["env_maps"] = sum(min(t, Q * 4) for t in tex_maps) * 3 * f4  # >= a bilinear cell per sample
            if sh:
                rows["I1w"] = ref_verts * S * 3 * f4
            Fl["view_glossy"] = 2 * (ref_pairs * 4 * K * 3 + Q * 3 * 4 * 3 + Q * 27)
            if lobes:
                Fl["view_lobes"] = 2 * Q * (27 + 2 * Lb * 3 + 4 * Lb * 3 + 3 * 4 * Lb + 2 * Lb * 3 + Lb * 3)
                if sh:
                    Fl["view_lobes_sh"] = 2 * Q * (3 * S * 3 + S * 3 + Lb * order * 3)
        # -- BRDF stage (H or lighting changed): caches it rebuilds count as their full write.
        # Without bounce terms E = E⁰ (Sun eq. 4 with U^{I1} = U^{I2} = 0): a lighting change writes
        # it once (the lighting stage's E⁰, nothing added, no second read), and a BRDF change leaves it
        # as it was (a VB frame reads E's referenced rows, as V does; `render` keeps them).
        bounce_terms = self.T1 is not None or self.T1c is not None or self.T2 is not None
        if light or (brdf and bounce_terms):
            rows["E"] = nv * K * 3 * f4
            if sh:
                rows["I1" if vertex else "I1w"] = nv * S * 3 * f4
            if sh and not vertex:
                B["sh_rotation"] = nv * sum((2 * b + 1) ** 2 for b in range(order)) * f4
                Fl["brdf_sh_rotation"] = 2 * nv * sum((2 * b + 1) ** 2 for b in range(order)) * 3
            if bounce_terms:
                B["E0"] = nv * K * 3 * f4
                Fl["brdf_E"] = 2 * nv * K * 3
            if self.T1 is not None or self.T1c is not None:
                B["T1L"] = nv * R * P * S * 3 * f4
                B["C"] = tensor_bytes(self.C)
                Fl["brdf_I1"] = 2 * nv * (R * P * S * 3 + S * K * 3)
            if self.T2 is not None:
                B["T2L"] = nv * (R * P) ** 2 * 3 * f4
                B["Cu"] = tensor_bytes(self.Cu)
                Fl["brdf_I2"] = 2 * nv * ((R * P) ** 2 * 3 + K * 3) + (R * P) ** 2 * 3
        if brdf:  # the per-region tables at the texels / θ nodes the view stage reads
            B["W_tables"] = tex_t * P * K * f4
            Fl["brdf_W_r"] = 2 * tex_W * K * P * 3
            if lobes:
                B["lobe_weights"] = nodes_a * P * Lb * f4
                Fl["brdf_a_r"] = 2 * rows_a * Lb * P * 3
        B.update(rows)
        # -- lighting stage
        if light:
            B["env_map"] = tensor_bytes(env.data)
            B["direct_transport"] = tensor_bytes(self.dt.idx, self.dt.val)
            Fl["light_E0"] = 2 * nv * K * self.dt.val.shape[-1] * 3
            if self.T1 is not None:
                B["T1"] = tensor_bytes(self.T1)
                Fl["light_T1"] = 2 * self.T1.numel() * 3
            elif self.T1c is not None:
                B["T1_compressed"] = tensor_bytes(*self.T1c.tensors())
                D = R * P * S
                Fl["light_T1"] = 2 * 3 * sum(Bc.shape[0] * Bc.shape[1] + A.shape[1] * D * Bc.shape[1] + A.numel() * D
                                             for A, Bc in zip(self.T1c.A, self.T1c.B))
            if self.T2 is not None:
                B["T2"] = tensor_bytes(self.T2)
                Fl["light_T2"] = 2 * self.T2.numel() * 3
            if lobes:
                kern = [flt.kernel for flt in self.env_filters if flt is not None]
                B["lobe_prefilters"] = sum(tensor_bytes(k.values(), k.col_indices(), k.crow_indices()) for k in kern)
                Fl["light_prefilter"] = 2 * sum(k.values().numel() for k in kern) * 3
                # the prefiltered maps resampled onto the env grid (specular.on_env_grid): written once
                # each, a bilinear cell (4 texels · 3) per texel
                B["lobe_maps"] = len(kern) * env.data.shape[0] * env.data.shape[1] * 3 * f4
                Fl["light_resample"] = 2 * len(kern) * env.data.shape[0] * env.data.shape[1] * 4 * 3
        return {k: int(v) for k, v in B.items()}, {k: int(v) for k, v in Fl.items()}

    def memory(self) -> dict[str, int]:
        if self.scene is None:
            return {}
        m = {"direct_idx": tensor_bytes(self.dt.idx), "direct_val": tensor_bytes(self.dt.val),
             "brdf_tables": tensor_bytes(self.factors.U_tab, self.factors.W_tab),
             "normals_faces": tensor_bytes(self.N, self.F)}
        if self.T1 is not None:
            m["T1"] = tensor_bytes(self.T1)
        if self.T1c is not None:
            m["T1_compressed"] = tensor_bytes(*self.T1c.tensors())
        if self.C is not None:
            m["C"] = tensor_bytes(self.C)
        if self.T2 is not None:
            m["T2"] = tensor_bytes(self.T2)
            m["Cu"] = tensor_bytes(self.Cu)
        if self.separate:
            m["lobe_visibility"] = tensor_bytes(self.lobe_vis)
            m["lobe_weights"] = tensor_bytes(self.lobe_table.a)
            m["env_filters"] = sum(tensor_bytes(f.kernel.values(), f.kernel.col_indices(), f.kernel.crow_indices())
                                   for f in self.env_filters if f is not None)
            if self.lobe_sh is not None:
                m["lobe_sh"] = tensor_bytes(self.lobe_sh)
        st = self._fast_static()
        m["fast_frames_pairs"] = tensor_bytes(st.frames, st.pair_of, st.pair_v, st.pair_r)
        if st.sh_rot is not None:
            m["sh_rotation"] = tensor_bytes(st.sh_rot)
        if self._f_wrows is not None:  # the view tables texel-major (fast.view_table_rows)
            m["fast_view_rows"] = tensor_bytes(self._f_wrows[1])
        return m
