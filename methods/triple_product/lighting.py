"""Local frames and the pre-rotated lighting grid (Ma 2006 §3.2, §4.1–4.2).

Ma 2006 eq. 7 integrates in the local frame of the shading point x (normal n(x), tangent t(x)):

    B^{x,ωo} = ∫ L^x(ω) V^x(ω) ρ̃^{ωo}(ω) dω,   L^x(ω) = L(R_x^T ω)                  (Ma 2006 eq. 7)

with R_x the world→local rotation (rows s, t, n). Spherical wavelets cannot be rotated, so the
global lighting is resampled into a *grid of local frames* (the paper: 32 × 16 normals × 32 tangent
angles = 16384 rotations, §4.1) and each shading point looks up nearby ones by (n, t) (§4.2).

Frame grid (`FrameGrid(n_theta, n_phi, n_psi)`)
-----------------------------------------------
World is +Y up. A normal is parameterised by θ ∈ [0, π] from +Y and φ ∈ [0, 2π):
    n(θ, φ) = (sin θ cos φ, cos θ, sin θ sin φ).
Its *reference tangent* is s0 = ∂n/∂θ = (cos θ cos φ, −sin θ, cos θ sin φ), t0 = n × s0 (a smooth
field except at the poles ±Y, where φ = atan2(n_z, n_x) = 0 for an exact pole normal, so every
exactly-vertical normal — e.g. a floor — gets the same frame). A frame of the grid is
(θ_i, φ_j, ψ_k) with tangent s = cos ψ s0 + sin ψ t0:
    θ_i = i·π/(n_theta − 1)  (poles included, so a floor hits a node exactly),
    φ_j = 2πj/n_phi,  ψ_k = 2πk/n_psi.
Grid frame index = (i·n_phi + j)·n_psi + k.

Tangent fields (`tangent` argument)
-----------------------------------
* ``"grid"``: the shading point's tangent is the reference tangent s0(n) (ψ = 0): one tangent angle
  suffices (n_psi = 1, the paper's isotropic 32 × 16 layout, Table 1's 170 MB). Valid for isotropic
  BRDFs only (the BRDF then does not care which tangent the frame has).
* ``"duff"``: the tangent of `methods.core.frames.coordinate_system` (Mitsuba's, Duff et al. 2017),
  the frame an anisotropic BRDF (Ward) is authored in by the references; needs the ψ dimension.

Look-up (`lookup_weights`)
--------------------------
* ``"nearest"``: the nearest node in (θ, φ, ψ) index space (one frame);
* ``"trilinear"``: linear weights in θ (clamped), φ and ψ (periodic): 8 frames (the paper
  "interpolat[es] coefficients of nearby lighting functions", §4.2). Linear in the coefficients =
  linear in the functions, so this blends rotated copies of the lighting (it blurs sharp lights
  by up to half a grid step instead of displacing them by up to half a step as nearest does).
The ``"exact"`` alternative (project the lighting per shading point) lives in `project_lighting`
called on the points' own frames.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from methods.core.frames import coordinate_system
from methods.core.fused import fused, map_rows, warm_blocks
from methods.core.latlong import quad_lane_weights, quad_lanes, quad_taps, quad_texels
from methods.core.spherical_haar import Geodesic, forward_butterfly
from methods.core.threads import torch_threads

TANGENTS = ("grid", "duff")
LOOKUPS = ("nearest", "trilinear", "exact")

# Paper preset (Ma 2006 §4.1: 32 × 16 normals × 32 tangent angles = 16384 rotations; with our
# pole-inclusive θ nodes "16 elevations" is n_theta = 16).
PAPER_FRAME_GRID = (16, 32, 32)


@dataclass(frozen=True)
class FrameGrid:
    """Sizes of the pre-rotated lighting grid: n_theta (≥ 2, poles included), n_phi, n_psi (≥ 1)."""

    n_theta: int = 9
    n_phi: int = 16
    n_psi: int = 1

    def __post_init__(self) -> None:
        for k, lo in (("n_theta", 2), ("n_phi", 1), ("n_psi", 1)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"frame grid {k} must be an int >= {lo}, got {v!r}")

    @property
    def size(self) -> int:
        return self.n_theta * self.n_phi * self.n_psi


def _spherical(n: Tensor) -> tuple[Tensor, Tensor]:
    """θ ∈ [0, π] from +Y and φ ∈ [0, 2π) of unit normals (..., 3)."""
    theta = torch.acos(n[..., 1].clamp(-1.0, 1.0))
    phi = torch.remainder(torch.atan2(n[..., 2], n[..., 0]), 2 * math.pi)
    return theta, phi


def reference_tangent(theta: Tensor, phi: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """n, s0 = ∂n/∂θ, t0 = n × s0 (each (..., 3)) of the module docstring's parameterisation."""
    st, ct, sp, cp = torch.sin(theta), torch.cos(theta), torch.sin(phi), torch.cos(phi)
    n = torch.stack([st * cp, ct, st * sp], -1)
    s0 = torch.stack([ct * cp, -st, ct * sp], -1)
    t0 = torch.cross(n, s0, dim=-1)
    return n, s0, t0


def local_frames(n: Tensor, tangent: str = "grid") -> Tensor:
    """World→local rotations (..., 3, 3), rows (s, t, n), of unit normals n (..., 3).

    ``tangent``: "grid" (s = reference tangent s0(n)) or "duff" (Mitsuba's coordinate_system).
    The normal row is n itself (not re-derived from θ, φ).
    """
    if n.shape[-1] != 3:
        raise ValueError(f"normals must be (..., 3), got {tuple(n.shape)}")
    if tangent == "duff":
        s, t = coordinate_system(n)
    elif tangent == "grid":
        theta, phi = _spherical(n)
        _, s0, _ = reference_tangent(theta, phi)
        s = s0 - (s0 * n).sum(-1, keepdim=True) * n  # exact orthogonality to the given n
        s = s / s.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        t = torch.cross(n, s, dim=-1)
    else:
        raise ValueError(f"tangent must be one of {TANGENTS}, got {tangent!r}")
    return torch.stack([s, t, n], -2)


def grid_frames(grid: FrameGrid, *, dtype=torch.float64) -> Tensor:
    """(F, 3, 3) world→local rotations of every grid frame, F = grid.size (index order above)."""
    th = torch.arange(grid.n_theta, dtype=torch.float64) * (math.pi / (grid.n_theta - 1))
    ph = torch.arange(grid.n_phi, dtype=torch.float64) * (2 * math.pi / grid.n_phi)
    ps = torch.arange(grid.n_psi, dtype=torch.float64) * (2 * math.pi / grid.n_psi)
    T, P, S = torch.meshgrid(th, ph, ps, indexing="ij")
    n, s0, t0 = reference_tangent(T, P)
    s = torch.cos(S)[..., None] * s0 + torch.sin(S)[..., None] * t0
    t = torch.cross(n, s, dim=-1)
    return torch.stack([s, t, n], -2).reshape(-1, 3, 3).to(dtype)


def _normal_coordinates(theta: Tensor, phi: Tensor, grid: FrameGrid) -> tuple[Tensor, Tensor]:
    """Fractional grid coordinates (fi, fj) of normals at (θ, φ) (`_spherical`)."""
    fi = (theta / (math.pi / (grid.n_theta - 1))).clamp(0, grid.n_theta - 1)
    fj = phi / (2 * math.pi / grid.n_phi)
    return fi, fj


def frame_coordinates(R: Tensor, grid: FrameGrid) -> tuple[Tensor, Tensor, Tensor]:
    """Fractional grid coordinates (fi, fj, fk) (each (B,)) of frames R (B, 3, 3) (rows s, t, n)."""
    n, s = R[:, 2], R[:, 0]
    theta, phi = _spherical(n)
    _, s0, t0 = reference_tangent(theta, phi)
    psi = torch.remainder(torch.atan2((s * t0).sum(-1), (s * s0).sum(-1)), 2 * math.pi)
    fi, fj = _normal_coordinates(theta, phi, grid)
    fk = psi / (2 * math.pi / grid.n_psi)
    return fi, fj, fk


def periodic_index(j: Tensor, n: int) -> Tensor:
    """j mod n of integer indices 0 ≤ j < 3n (a look-up's cell index, ⌊f⌋ of f ∈ [0, n] — n itself
    when an angle rounds up to its period — plus 0 or 1) by two compare-and-subtracts: = torch.remainder
    (j, n) there, without the per-lane integer division that kept the compiled look-ups slow
    (`fast_eval.grid_lookups`: 2x per point, same results). A negative j (⌊f⌋ of a non-finite
    angle) gives 0, so that every index names a row of the table (as the remainder did)."""
    j = torch.where(j >= n, j - n, j)
    return torch.where(j >= n, j - n, torch.where(j < 0, 0, j))


def _bilinear_cell(fi: Tensor, fj: Tensor, grid: FrameGrid) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The trilinear look-up's (θ, φ) cell: i0, ai (θ clamped), j0, aj (φ periodic)."""
    i0 = fi.floor().long().clamp(0, grid.n_theta - 2)
    ai = (fi - i0).clamp(0, 1)
    j0 = fj.floor().long()
    aj = fj - j0
    return i0, ai, j0, aj


def cell_weights(R: Tensor, grid: FrameGrid) -> tuple[Tensor, Tensor]:
    """`lookup_weights` (R, grid, "trilinear") of a grid with one tangent angle (n_psi = 1), each
    (θ, φ) node once: there every node's two ψ entries (dk = 0, 1) are the same grid frame, with
    weights w_ij·(1 − a_k) and w_ij·a_k, so the look-up is the 4 nodes of the (θ, φ) cell with
    weights w_ij — no tangent angle ψ (its sin / cos / atan2) to compute. Returns idx (B, 4)
    int64 (the even columns of `lookup_weights`' idx, same order) and w (B, 4) (the column pairs'
    sums, to round-off)."""
    idx, w = cell_terms(R, grid)
    return torch.stack(idx, -1), torch.stack(w, -1)


def cell_terms(R: Tensor, grid: FrameGrid) -> tuple[list[Tensor], list[Tensor]]:
    """`cell_weights` as 4 (B,) row tensors and 4 (B,) weight tensors (R's dtype), unstacked (a
    compiled caller keeps every output a 1-D plane: `fast_eval.grid_lookups`)."""
    if grid.n_psi != 1:
        raise ValueError(f"cell_weights needs a grid with n_psi = 1, got {grid}")
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise ValueError(f"R must be (B, 3, 3), got {tuple(R.shape)}")
    theta, phi = _spherical(R.double()[:, 2])
    i0, ai, j0, aj = _bilinear_cell(*_normal_coordinates(theta, phi, grid), grid)
    idx, w = [], []
    for di, wi in ((0, 1 - ai), (1, ai)):
        for dj, wj in ((0, 1 - aj), (1, aj)):
            idx.append((i0 + di) * grid.n_phi + periodic_index(j0 + dj, grid.n_phi))
            w.append((wi * wj).to(R.dtype))
    return idx, w


def lookup_weights(R: Tensor, grid: FrameGrid, mode: str = "trilinear") -> tuple[Tensor, Tensor]:
    """Grid frames and weights approximating the frames R (B, 3, 3).

    Returns idx (B, k) int64 and w (B, k) (k = 1 nearest, 8 trilinear; weights sum to 1).
    """
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise ValueError(f"R must be (B, 3, 3), got {tuple(R.shape)}")
    fi, fj, fk = frame_coordinates(R.double(), grid)
    if mode == "nearest":
        i = fi.round().long().clamp(0, grid.n_theta - 1)
        j = torch.remainder(fj.round().long(), grid.n_phi)
        k = torch.remainder(fk.round().long(), grid.n_psi)
        idx = ((i * grid.n_phi + j) * grid.n_psi + k)[:, None]
        return idx, torch.ones_like(fi, dtype=R.dtype)[:, None]
    if mode != "trilinear":
        raise ValueError(f"lookup must be 'nearest' or 'trilinear', got {mode!r}")
    i0, ai, j0, aj = _bilinear_cell(fi, fj, grid)
    k0 = fk.floor().long()
    ak = fk - k0
    idx, w = [], []
    for di, wi in ((0, 1 - ai), (1, ai)):
        for dj, wj in ((0, 1 - aj), (1, aj)):
            for dk, wk in ((0, 1 - ak), (1, ak)):
                i = i0 + di
                j = periodic_index(j0 + dj, grid.n_phi)
                k = periodic_index(k0 + dk, grid.n_psi)
                idx.append((i * grid.n_phi + j) * grid.n_psi + k)
                w.append(wi * wj * wk)
    return torch.stack(idx, -1), torch.stack(w, -1).to(R.dtype)


def sample_spacing(geo: Geodesic, supersample: int) -> float:
    """Mean angular spacing (radians) of the point samples a projection takes: one per sub-triangle,
    geo.n · 4^supersample of them over 4π."""
    return math.sqrt(4.0 * math.pi / (geo.n * 4 ** int(supersample)))


def prefiltered(envmap, geo: Geodesic, supersample: int):
    """The env map box-downsampled so that the projection's point samples (`sample_spacing`) put
    two in every texel (``EnvMap.prefiltered_for_spacing``). Sampled at full resolution a sun of a
    few texels aliases: at level 3 with 4 samples per fine triangle (2.8° apart) the bench bunny's
    ground came out at 0.63 of the reference under its 256 × 512 sunrise probe (1.10 with 64 samples
    per triangle, and with this prefilter — see README). The blur is the fine triangles' own scale
    (5.7° at level 3 with 4 samples per triangle), which the level's Haar basis cannot resolve
    below anyway — but the blur reaches across a triangle's edges: a sun 10° below the ground's
    horizon leaked into the triangles above it (1.51× vs 1.30× converged on the smoke bunny's L frame
    1), hence the method's default of 16 samples per triangle, prefiltered to 2.7° texels at most.

    The box filter does not depend on the rotation: the last filtered map per spacing is kept and
    reused for every rotated copy of the same data (an L / VL frame rotates the map only; the
    float64 box filter of a 256 × 512 probe was ~5 ms of such a frame), each copy a shallow copy of it
    with the frame's rotation (as ``EnvMap.rotated`` makes one: the data's checks and its periodic
    texels made once). The filter itself is `box_filtered` (the same texels as
    ``prefiltered_for_spacing``, ~6x faster: an E frame filters a new probe)."""
    import copy

    sp = sample_spacing(geo, supersample)
    hit = _PREFILTERED.get(sp)
    if hit is None or hit[0] is not envmap.data:
        k = prefilter_factor(envmap.height, envmap.width, sp)
        hit = (envmap.data, None if k == 1 else filtered_map(envmap, box_filtered(envmap.data, k)))
        _PREFILTERED[sp] = hit
    if hit[1] is None:
        return envmap
    out = copy.copy(hit[1])                    # shares the filtered data, its tables and periodic copies
    out.to_world = envmap.to_world             # (validated when ``envmap`` was made)
    return out


def filtered_map(envmap, data: Tensor):
    """``EnvMap(data, envmap.to_world)`` for texels ``data`` box-filtered from ``envmap``'s (finite and
    non-negative, as theirs, so ``EnvMap``'s checks hold already): a copy of ``envmap`` with the new
    data and its data-dependent caches empty, as ``EnvMap.rotated`` makes a copy (the checks and the
    rotation's validation were ~0.5 ms of an E frame, after the settle idle)."""
    import copy

    out = copy.copy(envmap)
    out.data = data
    out._table = None                          # the sampling tables and periodic copies of the new data
    out._ext = {}
    return out


# sample spacing → (source texels, their box-filtered map or None: no filter) of the last `prefiltered` call
_PREFILTERED: dict[float, tuple] = {}


def prefilter_factor(H: int, W: int, spacing: float) -> int:
    """The box size k of ``EnvMap.prefiltered_for_spacing(spacing)`` on an H × W map (its loop:
    powers of two until the texels are 1.9 spacings tall, k dividing H and W and leaving ≥ 3 rows)."""
    k = 1
    while math.pi / (H // k) < 1.9 * spacing:
        k2 = 2 * k
        if H % k2 or W % k2 or H // k2 < 3:
            break
        k = k2
    return k


def box_filtered(data: Tensor, k: int, *, native: bool = True) -> Tensor:
    """``EnvMap.box_downsampled(k).data`` (k ≥ 2) of texels data (H, W, 3) float32: each k × k block's mean
    in float64, rounded to float32 once. Summed as k row slabs, then k column slabs, each a
    contiguous pass (the reference's ``mean((1, 3))`` over a strided 5-d view: 3.2 ms for a 256 × 512
    probe at k = 4, this 0.35-0.45 ms, 1 thread). A block's k² float32 texels sum exactly in float64
    whenever they span less than 2^(29 − 2·log2 k) in magnitude, so then any order gives the same
    sum and the same float32 texel bit for bit (every bench probe and scene map: tested).
    `native_light.box` runs these operations in this order in one C pass when it is built (the same
    texels bit for bit whatever the data; ``native=False``: this torch path, its test oracle)."""
    if native:
        from methods.triple_product import native_light

        out = native_light.box(data, k)
        if out is not None:
            return out
    H, W, C = data.shape
    d = data.reshape(H // k, k, W * C)
    a = d[:, 0].double()
    for i in range(1, k):
        a += d[:, i]
    a = a.view(H // k, W // k, k, C)
    b = a[:, :, 0] + a[:, :, 1]
    for j in range(2, k):
        b += a[:, :, j]
    return b.mul_(1.0 / (k * k)).float()


def project_lighting(radiance, R: Tensor, geo: Geodesic, *, supersample: int = 1,
                     frames_per_chunk: int = 32, progress: bool = False) -> Tensor:
    """Wavelet coefficients of the lighting seen in local frames: L^R(ω) = L(R^T ω) (eq. 7).

    Args:
        radiance: callable world directions (..., 3) → (..., 3) radiance (``EnvMap.radiance``).
        R: (F, 3, 3) world→local rotations (rows s, t, n).
        geo: the geodesic grid (level L, K = 20·4^L); supersample: 4^s sub-triangle samples per
            fine triangle (`Geodesic.project`).
    Returns:
        (F, 3, K) float32 coefficients (equal-area measure; the real solid angle is folded into the
        BRDF table, see `brdf_table`).
    """
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise ValueError(f"R must be (F, 3, 3), got {tuple(R.shape)}")
    from tqdm.auto import tqdm

    Rf = R.float()
    out = []
    for a in tqdm(range(0, R.shape[0], frames_per_chunk), disable=not progress, desc="lighting", unit="chunk"):
        Rc = Rf[a:a + frames_per_chunk]  # (f, 3, 3)

        def fn(c: Tensor, Rc=Rc) -> Tensor:
            d = torch.einsum("pj,fji->fpi", c.float(), Rc)  # world = R^T c  (f, P, 3)
            L = radiance(d)  # (f, P, 3)
            return L.permute(1, 0, 2).reshape(c.shape[0], -1)  # (P, f·3)

        co = geo.project(fn, supersample=supersample, dtype=torch.float32)  # (f·3, K)
        out.append(co.reshape(Rc.shape[0], 3, -1))
    return torch.cat(out, 0)


# -- fast projection (run time) ----------------------------------------------------------------------

# Samples per compiled block of `project_env` (`methods.core.fused.map_rows`): the F grid frames are
# split into ceil(F·n·4^s / ENV_BLOCK_SAMPLES) equal blocks (one static shape per configuration; the
# default grid's 544 frames at level 3, s = 2: 8 blocks of 68 frames). Few large blocks, because
# every call is an OpenMP region with barriers, and on this shared 2-core machine (load 10-12) a
# barrier waits for a descheduled thread (2 threads, one kernel per block: 68 blocks of 8 frames
# 1347 ms wall, 17 of 32 614 ms, 8 of 68 486 ms); the two kernels of a block (`env_taps`,
# `quad_means`) pass 12 bytes per sample between them (16.7 MB per block of 68 frames; 1 thread,
# blocks of 8 / 16 / 68 frames: 77 / 82 / 78 ms CPU, the same within the noise).
ENV_BLOCK_SAMPLES = 3 << 19


def env_block_frames(F: int, samples_per_frame: int) -> int:
    """Frames per `project_env` block for F frames of ``samples_per_frame`` samples each."""
    blocks = max(1, -(-F * samples_per_frame // ENV_BLOCK_SAMPLES))
    return max(1, -(-F // blocks))


# Smallest tail block of `env_blocks`. A pixel / vertex frame after a lighting change projects only
# the grid frames it looks up (`TripleProduct.fill_lighting`: chess bench vertex L 347 of 544), and
# one padded block of 68 for the last 7 of them computed 61 frames for nothing (15 % of that
# frame's projection); tail blocks of 32 / 16 / 8 frames pad at most 7 (one compiled shape each,
# compiled in the warm-up frame). Same-process A/B, 1 thread, load 8-10: chess vertex L 1.11x / 1.09x
# (two runs), creature vertex L 1.03x, chess pixel L 1.02x (328 frames: 340 computed before).
ENV_TAIL_MIN = 8


def env_tail_sizes(chunk: int) -> tuple[int, ...]:
    """The tail block sizes of `env_blocks` for full blocks of ``chunk`` frames: the powers of two p
    with ENV_TAIL_MIN <= p and 2p <= chunk, largest first (none for small blocks)."""
    out, p = [], ENV_TAIL_MIN
    while 2 * p <= chunk:
        out.append(p)
        p *= 2
    return tuple(reversed(out))


def env_blocks(F: int, chunk: int) -> list[int]:
    """Block sizes (each padded when its frames run out) covering F frames: F // chunk full blocks,
    then the rest either in one padded full block or in tail blocks (`env_tail_sizes`, the binary
    digits of the rest rounded up to ENV_TAIL_MIN), whichever computes fewer frames (ties: one block)."""
    full, r = divmod(int(F), chunk)
    sizes = [chunk] * full
    if r:
        tails = env_tail_sizes(chunk)
        r8 = -(-r // ENV_TAIL_MIN) * ENV_TAIL_MIN
        if not tails or r8 >= chunk or r8 > sum(tails):
            sizes.append(chunk)
        else:
            sizes += [p for p in tails if r8 & p]
    return sizes


def _env_samples(geo: Geodesic, supersample: int) -> tuple[Tensor, Tensor]:
    """The sample directions and weights of `Geodesic.project`: c (n·4^s, 3) float32 unit centres of
    the 4^s sub-triangles of every fine triangle, wn (n, 4^s) float32 their solid angles divided by
    the fine triangle's sum (cached on ``geo``)."""
    cache = geo.__dict__.setdefault("_env_samples", {})
    if supersample not in cache:
        c, w = geo.subsamples(supersample)
        cache[supersample] = (c.float().contiguous(), (w / w.sum(1, keepdim=True)).float().contiguous())
    return cache[supersample]


def _env_sample_planes(geo: Geodesic, supersample: int) -> tuple[Tensor, Tensor]:
    """`_env_samples` laid out for `env_taps`: cp (3, n, 4^s) coordinate planes (a fine triangle's
    4^s sub-samples contiguous) and wT (n, 4^s) (cached on ``geo``). Triangle-major, so that
    `quad_means` reads a triangle's footprints as three contiguous runs: sample-major (3, 4^s, n),
    its 16 samples were 48 strided streams per triangle (1 thread, chess bench blocks of 68 frames:
    `quad_means` 1.40x / 1.45x faster in two same-process runs at load 10, `env_taps` the same,
    bit-identical results)."""
    cache = geo.__dict__.setdefault("_env_sample_planes_nS", {})     # (n, S) layout: its own key
    if supersample not in cache:
        c, wn = _env_samples(geo, supersample)
        n, S = wn.shape
        cache[supersample] = (c.view(n, S, 3).permute(2, 0, 1).contiguous(), wn.contiguous())
    return cache[supersample]


# -- float32 atan2 / acos as polynomials (the footprint kernel's lat-long angles) -------------------
#
# Inductor vectorises torch.atan2 / torch.acos with Sleef's 1-ulp (double-float) routines: 2.1-2.7 ns
# of the general footprint kernel's 3.75 ns per sample (session 16). Cephes' single-precision
# minimax polynomials (atanf on |t| <= tan π/8 after one reduction, asinf on |x| <= 1/2 with the
# half-angle identity above it) in plain float32 arithmetic — one division and one square root per
# sample, no tables — are within 2.6e-7 rad of the float64 angle of the float32 input (ATen's
# float32 atan2 / acos: 1.4e-7 / 1.9e-7; measured on 4·10^6 random unit directions, and tested),
# i.e. u, v to a few ulp: the same round-off class as the vectorised library calls, which already
# differ from ATen's by an ulp (tests' F32_LIGHT).


def atan2_f32(y: Tensor, x: Tensor) -> Tensor:
    """atan2(y, x) in (−π, π] by a polynomial (comment above): the octant reduction t = min/max of
    |x|, |y| (t → (t − 1)/(t + 1) + π/4 above tan π/8, the same one division), Cephes' atanf
    polynomial, then the quadrant. atan2(±0, x < 0) = +π (ATen: ±π; the same lat-long u mod 1);
    atan2(0, 0) = 0."""
    ax, ay = x.abs(), y.abs()
    mn, mx = torch.minimum(ax, ay), torch.maximum(ax, ay)
    c = mn > 0.41421356237309503 * mx                                       # t > tan(π/8)
    num = torch.where(c, mn - mx, mn)
    den = torch.where(c, mn + mx, mx)
    t = num / torch.where(den > 0, den, 1.0)
    z = t * t
    p = (((8.05374449538e-2 * z - 1.38776856032e-1) * z + 1.99777106478e-1) * z - 3.33329491539e-1) * z * t + t
    r = torch.where(c, p + math.pi / 4, p)
    r = torch.where(ay > ax, math.pi / 2 - r, r)
    r = torch.where(x < 0, math.pi - r, r)
    return torch.where(y < 0, -r, r)


def acos_f32(y: Tensor) -> Tensor:
    """acos(y) for y in [−1, 1] by a polynomial (comment above): Cephes' asinf polynomial on
    |y| <= 1/2 (acos = π/2 − asin), 2·asin(√((1 − |y|)/2)) above; acos(−y) = π − acos(y)."""
    a = y.abs()
    big = a > 0.5
    z = torch.where(big, 0.5 - 0.5 * a, a * a)
    s = torch.where(big, z.sqrt(), a)
    p = ((((4.2163199048e-2 * z + 2.4181311049e-2) * z + 4.5470025998e-2) * z + 7.4953002686e-2) * z
         + 1.6666752422e-1) * z * s + s
    r = torch.where(big, 2 * p, math.pi / 2 - p)
    return torch.where(y < 0, math.pi - r, r)


def env_taps(R: Tensor, cp: Tensor, T: Tensor, H: int, W: int) -> tuple[Tensor, Tensor, Tensor]:
    """The bilinear footprints (`methods.core.latlong.quad_taps`: idx int32, fx, fy, each (f, S, n))
    of the env map seen in f frames at the projection's samples (Ma 2006 eq. 7's L^x(ω) = L(R_x^T ω)):
    directions (R_f T)^T c in the emitter frame (T = to_world, as `EnvMap.to_local`; the two
    rotations folded into one per frame), then `direction_to_uv`'s atan2, acos as float32
    polynomials (`atan2_f32`, `acos_f32`).
    R (f, 3, 3); cp (3, n, S) sample coordinate planes (`_env_sample_planes`); T (3, 3); H, W the
    map's size; returns (f, n, S) each. Every operand is a plane over the samples: the compiled loop
    is vectorised along them. Compiled with `_TAPS_OPTIONS` (one loop: the directions stay in
    registers)."""
    M = (R @ T)[:, :, :, None, None]                                       # (f, 3, 3, 1, 1)
    cx, cy, cz = cp[0][None], cp[1][None], cp[2][None]                     # (1, n, S)
    d = [cx * M[:, 0, k] + cy * M[:, 1, k] + cz * M[:, 2, k] for k in range(3)]  # emitter frame
    u = atan2_f32(d[0], -d[2]) * (0.5 / math.pi)
    v = acos_f32(d[1].clamp(-1.0, 1.0)) * (1.0 / math.pi)
    return quad_taps(u, v, H, W)


def _tree_sum(xs: list[Tensor]) -> Tensor:
    """Σ xs pairwise ((x0 + x1) + (x2 + x3)) + …: a fixed order with independent adds (a running
    sum is one chain of dependent vector adds)."""
    while len(xs) > 1:
        xs = [xs[i] + xs[i + 1] if i + 1 < len(xs) else xs[i] for i in range(0, len(xs), 2)]
    return xs[0]


def quad_means(idx: Tensor, fx: Tensor, fy: Tensor, wT: Tensor, Q: Tensor, lanes: Tensor) -> Tensor:
    """Fine-triangle means of the map's bilinear radiance at footprints (idx, fx, fy) (f, n, S)
    (`env_taps`): Σ_s wT[:, s] · bilinear(s) per frame, triangle and channel, from the quad rows Q
    (H·(W + 1), 16) (`methods.core.latlong.quad_texels`; lanes: `quad_lanes`). Vectorised along each row (one vector
    load per sample instead of 12 scalar ones); the S-term sum in a fixed pairwise order per
    output (one thread each: thread-count independent). Returns (f, 3, n)."""
    terms = [Q[idx[:, :, s]] * (quad_lane_weights(fx[:, :, s], fy[:, :, s], lanes) * wT[:, s, None])  # (f, n, 16)
             for s in range(idx.shape[2])]
    acc = _tree_sum(terms)
    return torch.stack([(acc[..., 4 * c] + acc[..., 4 * c + 1]) + (acc[..., 4 * c + 2] + acc[..., 4 * c + 3])
                        for c in range(3)], 1)


# -- lighting that turns about +Y (E frames: probes swapped at a random azimuth) ------------------------
#
# The grid's frames at one (θ_i, ψ_k) are turned copies of each other about +Y: n, s0, t0 of
# (θ, φ) are Q_φ applied to those of (θ, 0), with Q_φ = [[cos φ, 0, −sin φ], [0, 1, 0], [sin φ, 0, cos φ]]
# (module docstring), so R_ijk = R_i0k Q_φj^T and the world direction of sample c is Q_φj e, e = R_i0k^T c.
# An emitter turned about +Y too (to_world T = Q_γ) sees it at Q_γ^T Q_φj e = Q_(φj − γ) e, whose
# lat-long coordinates are e's shifted in u: u = u(e) + (φ_j − γ)/2π, v = v(e) (atan2(x, −z) turns
# with Q). So the n_theta·n_psi base frames' (u, v) are computed once (float64, then float32) and a
# frame of such a map needs no rotation and no atan2 / acos: 31 flops per sample instead of 45.


def azimuth_of(T: Tensor) -> float | None:
    """γ when the emitter rotation T (3, 3) turns about +Y only (T = Q_γ, exact zeros and one in its
    Y row and column, as `scenes.sequences` "E" frames' ``rotation_y`` of an upright probe), else None."""
    t = T.detach().double().cpu().tolist()      # one conversion (element-wise tensor compares: ~10x the time)
    if t[1][1] != 1.0 or t[0][1] != 0.0 or t[2][1] != 0.0 or t[1][0] != 0.0 or t[1][2] != 0.0:
        return None
    return math.atan2(t[2][0], t[0][0])


def _azimuthal_samples(geo: Geodesic, supersample: int, grid: FrameGrid) -> tuple[Tensor, Tensor]:
    """u0 float64, v0 float32, each (n_theta·n_psi, n, 4^s): the lat-long coordinates
    (``direction_to_uv``) of every sample of the base frames (θ_i, φ = 0, ψ_k) in the world (row
    i·n_psi + k), computed in float64 from the float32 sample planes of `_env_sample_planes` (cached
    on ``geo``). u0 stays float64 so that u0 + shift is rounded once: a float32 sum added up to an ulp
    of u, 1.2e-5 of the largest coefficient on the bunny's sharp test map (measured; 8e-6 in float64)."""
    cache = geo.__dict__.setdefault("_azimuthal_samples_nS", {})     # (B, n, S) layout: its own key
    key = (supersample, grid)
    if key not in cache:
        cp, _ = _env_sample_planes(geo, supersample)
        R0 = grid_frames(FrameGrid(grid.n_theta, 1, grid.n_psi))          # (B, 3, 3) float64
        e = torch.einsum("cns,bci->ibns", cp.double(), R0)                  # world R0^T c (3, B, n, S)
        u0 = torch.atan2(e[0], -e[2]) * (0.5 / math.pi)
        v0 = torch.acos(e[1].clamp(-1.0, 1.0)) * (1.0 / math.pi)
        cache[key] = (u0.contiguous(), v0.float().contiguous())
    return cache[key]


def env_taps_azimuthal(shift: Tensor, base: Tensor, u0: Tensor, v0: Tensor, H: int, W: int
                       ) -> tuple[Tensor, Tensor, Tensor]:
    """`env_taps` of f grid frames for an emitter turned about +Y (comment above): u = u0 + shift,
    v = v0 of the frame's base row. shift (f,) float64 (φ_j − γ)/2π mod 1; base (f,) int64 base row;
    u0 float64, v0 float32 (B, n, S) (`_azimuthal_samples`). Returns idx, fx, fy (f, n, S)."""
    u = (u0[base] + shift[:, None, None]).float()                          # (f, n, S), rounded once
    return quad_taps(u, v0[base], H, W)


# -- the azimuthal projection on a comb table (E frames, the map's width a multiple of n_phi) ---------------
#
# With m = W / n_phi texel columns per grid step in φ, frame j of a base row sees every sample m·j
# columns further than frame 0 does (u = u0 + j/n_phi − γ/2π, comment above): the same fractional
# footprint (fx, fy) and rows, columns (ix + m·j) mod W. So the footprints are computed once per base
# row (`comb_taps`, in float64 and rounded once) and the n_phi frames of a base row are summed
# together, vectorised along j: per sample and channel 4 taps × n_phi frames read as contiguous runs
# of a comb table CT[r, p, c, e, k] = texel(r, (p + e + m·k) mod W, c) (`comb_table`: row r, phase
# p = ix mod m, side e = 0 / 1 for the tap at ix / ix + 1, k = ix div m + j < 2·n_phi) — no 16-lane
# quad row per (frame, sample), no per-frame footprints.


def comb_ok(grid: FrameGrid | None, W: int) -> bool:
    """`comb_means` applies: a frame grid whose n_phi divides the map's width."""
    return grid is not None and W % grid.n_phi == 0


def comb_table(planes: Tensor, H: int, W: int, n_phi: int) -> Tensor:
    """The comb table (flat, H·m·3·2·2n_phi floats, m = W / n_phi) of the channel planes (3, H·(W+1))
    (``EnvMap.periodic_texels(planes=True)``): CT[r, p, c, e, k] = texel(r, (p + e + m·k) mod W, c)."""
    m, J = W // n_phi, n_phi
    tex = planes.view(3, H, W + 1)[:, :, :W]
    # the column p + e + m·k (< 2W + 1) of the rows repeated twice and once more: a strided view of
    # (H, m, 3, 2, 2J) and one copy (the same texels as gathering the columns (p + e + m·k) mod W:
    # 64 x 128 map, n_phi = 32, 1 thread: 0.37 -> 0.12 ms)
    ext = torch.cat([tex, tex, tex[:, :, :1]], 2)                                  # (3, H, 2W + 1)
    We = 2 * W + 1
    return ext.as_strided((H, m, 3, 2, 2 * J), (We, 1, H * We, 1, m)).contiguous().reshape(-1)


def comb_taps(u0: Tensor, v0: Tensor, g: Tensor, wT: Tensor, H: int, W: int, n_phi: int) -> tuple[Tensor, Tensor]:
    """Frame j = 0's footprints of every base-row sample (`quad_taps` of u = u0 − γ/2π, v = v0, the
    u part in float64 and rounded once): o (B, n, S) int32 offset of the top-left tap's comb run in
    `comb_table`, w4 (B, n, S, 2, 2) float32 the bilinear weights of its taps (dy, dx) times the
    sample's wT (n, S). u0 float64, v0 float32 (B, n, S) (`_azimuthal_samples`); g float64 0-d: γ/2π
    (frame 0's shift, as `env_taps_azimuthal` rounds u0 + shift once, then the same float32 steps)."""
    m, J = W // n_phi, n_phi
    u = u0 - g                                                              # frame 0's u mod 1, rounded once:
    u = (u - torch.floor(u)).float()                                        # = torch.remainder(u, 1.0) (its
    # float64 floor division by 1 is ⌊u⌋ exactly), without the compiled remainder's fmod per lane
    u = u - 0.5 / W                                                         # then `quad_taps`' float32 steps
    x = (u - torch.floor(u)) * W
    ix = x.to(torch.int32).clamp(0, W - 1)
    fx = x - ix
    ix = ix.double()
    q = (ix / m).floor()                                                    # ix div m (exact: small ints)
    p = ix - q * m
    v = v0 - torch.floor(v0)
    y = v * (H - 1)
    iy = y.to(torch.int32).clamp(0, H - 2)
    fy = y - iy
    o = (iy * m + p.to(torch.int32)) * (3 * 2 * 2 * J) + q.to(torch.int32)
    w = wT[None]
    # one stack of the 4 taps, viewed (dy, e): nested stacks made the compiled loop write each inner
    # pair, then copy it into place in 2-lane partial vectors (1 thread, chess bench E, 17 base rows
    # of the 640 live triangles: 5.0 ms for 174 K samples); the same values, the same layout
    w4 = torch.stack([((1 - fx) * (1 - fy)) * w, (fx * (1 - fy)) * w,
                      ((1 - fx) * fy) * w, (fx * fy) * w], -1)
    return o, w4.view(*w4.shape[:-1], 2, 2)                                # (B, n, S, dy, e)


def comb_means(o: Tensor, w4: Tensor, CT: Tensor, J: int, m: int) -> Tensor:
    """Fine-triangle means (`quad_means`) of all n_phi = J frames of B base rows from their frame-0
    footprints (`comb_taps`: o (B, n, S) and the 4 taps' weights w4 (B, n, S, 2, 2), times the
    sample's weight), the comb table CT of J frames and m columns per step: (B, n, 3, J), frame j in
    the last dimension (vectorised along it: the table read through overlapping windows, so that
    every tap is one contiguous run of J). Each output sums its S·4 terms in one sequential loop.

    The J frames are summed as separate reductions of COMB_LANES frames each, which the compiled
    loop fuses into one pass with an accumulator per part: one reduction over all J kept a single
    vector accumulator per loop, whose 4·S dependent adds bounded it (1 thread, chess bench E, 17
    base rows of the 640 live triangles, J = 32: 6.3 -> 3.5 ms). Each output's terms are added in
    the same order as before: the same sums bit for bit."""
    es, cs = 2 * J, 4 * J                                                   # side, channel strides
    rs = m * 3 * cs                                                         # row stride
    # top-left offsets o: the window's last element (channel 2, dy = dx = 1, frame J - 1) lies
    # 2·cs + rs + es + J − 1 past o, so o < N − (2·cs + rs + es + J − 1) (the eager view is bounds-checked:
    # without the 2·cs it reached past the table and PRTBENCH_COMPILE=0 raised in every comb frame)
    win = CT.as_strided((CT.shape[0] - 2 * cs - rs - es - J + 1, 3, 2, 2, J), (1, cs, rs, es, 1))
    taps, w = win[o], w4[:, :, :, None, :, :, None]
    return torch.cat([(taps[..., a:a + COMB_LANES] * w).sum((2, 4, 5))    # (B, n, 3, J)
                      for a in range(0, J, COMB_LANES)], -1)


# frames per `comb_means` reduction: one float32 vector of an AVX2 host (the reductions of a block
# run side by side in one loop, each with its own accumulator)
COMB_LANES = 8


def comb_coeffs(fine: Tensor) -> tuple[Tensor, Tensor]:
    """(B, n, 3, J) `comb_means` → coefficients and fine values (B·J, 3, n), row b·J + j."""
    B, n, C, J = fine.shape
    f = fine.permute(0, 3, 2, 1).reshape(B * J, C, n)
    return forward_butterfly(f), f


def _comb_rows(grid: FrameGrid, frames: Tensor) -> Tensor:
    """Rows b·n_phi + j of `comb_coeffs` of grid frames f (base row b = i·n_psi + k, frame j)."""
    j = frames // grid.n_psi % grid.n_phi
    b = frames // (grid.n_phi * grid.n_psi) * grid.n_psi + frames % grid.n_psi
    return b * grid.n_phi + j


def _native_comb_scatter(means: Tensor, rows: Tensor, frames: Tensor, out: Tensor) -> bool:
    """`native_light.comb_scatter` (the live triangles' means into their frames' rows of ``out`` in one
    pass; False: not available, then the caller gathers with `_comb_select`)."""
    from methods.triple_product import native_light

    return native_light.comb_scatter(means, rows, frames, out)


def _comb_select(y: Tensor, rows: Tensor) -> Tensor:
    """Rows ``rows`` (b·J + j, `_comb_rows`) of (B·J, 3, n) `comb_coeffs` output, or of a (B, J, 3, n)
    view (the live triangles' means, permuted without a copy): (f, 3, n) contiguous."""
    if y.ndim == 3:
        return y.index_select(0, rows)
    J = y.shape[1]
    return y[rows // J, rows % J]


def quad_means_coeffs(idx: Tensor, fx: Tensor, fy: Tensor, wT: Tensor, Q: Tensor, lanes: Tensor
                      ) -> tuple[Tensor, Tensor]:
    """`quad_means` and their wavelet coefficients (`spherical_haar.forward_butterfly`), one compiled
    graph per block: coefficients (f, 3, n), fine values (f, 3, n)."""
    fine = quad_means(idx, fx, fy, wT, Q, lanes)
    return forward_butterfly(fine), fine


# E frames on the comb table (`comb_means`) where it applies; False: the per-frame azimuthal kernel
COMB = True

# compiled with the index checks off: `quad_taps` clamps every index into the table
_FUSE_OPTIONS = {"assert_indirect_indexing": False}
# `env_taps`: a direction component read by more than 4 loads (6 here) and used more than once (the
# polynomials read each several times) is stored by Inductor's default realize_reads_threshold (4) and
# read back in a second loop — 24 bytes per sample more, and the polynomial kernel was then slower than
# Sleef's (1 thread, chess bench block of 68 frames: 6.8-7.0 vs 5.4-5.9 ns per sample); kept in
# registers: 2.8-3.0 vs 4.1-4.5 ns (same process). (A much larger threshold together with
# realize_opcount_threshold made the lowering run for minutes.)
_TAPS_OPTIONS = {**_FUSE_OPTIONS, "realize_reads_threshold": 16}
_kernels: dict = {}


def _kernel(fn):
    """``fn`` through `methods.core.fused` (compiled on first use, `_FUSE_OPTIONS`; `env_taps`:
    `_TAPS_OPTIONS`)."""
    if fn.__name__ not in _kernels:
        _kernels[fn.__name__] = fused(fn, options=_TAPS_OPTIONS if fn.__name__ == "env_taps" else _FUSE_OPTIONS)
    return _kernels[fn.__name__]


def _general_block(R: Tensor, cp: Tensor, T: Tensor, H: int, W: int, wT: Tensor, Q: Tensor, lanes: Tensor
                   ) -> tuple[Tensor, Tensor]:
    """One block of `project_env`'s general path (`env_taps`, then `quad_means_coeffs`): what its
    comb path warms (`warm_blocks` keys on this function's code)."""
    return _kernel(quad_means_coeffs)(*_kernel(env_taps)(R, cp, T, H, W), wT, Q, lanes)


def _live_sample_planes(geo: Geodesic, supersample: int, tris: Tensor) -> tuple[Tensor, Tensor]:
    """`_env_sample_planes` of the fine triangles ``tris`` (n',) only: cp (3, n', 4^s), wT (n', 4^s)
    (cached on ``geo`` per index tensor, which the cache holds)."""
    cache = geo.__dict__.setdefault("_live_sample_planes", {})
    hit = cache.get(supersample)
    if hit is None or hit[0] is not tris:
        cp, wT = _env_sample_planes(geo, supersample)
        t = tris.to(cp.device)
        hit = cache[supersample] = (tris, cp[:, t].contiguous(), wT[t].contiguous())
    return hit[1], hit[2]


def _live_azimuthal_samples(geo: Geodesic, supersample: int, grid: FrameGrid, tris: Tensor, device
                            ) -> tuple[Tensor, Tensor]:
    """`_azimuthal_samples` (on ``device``) of the fine triangles ``tris`` (n',) only: u0, v0 (B, n', 4^s)
    contiguous, cached on ``geo`` per (supersample, grid, device) for the last index tensor (which the
    cache holds), as `_live_sample_planes`: an E frame gathered them anew (chess bench, 17 base rows of
    the 640 live triangles: ~0.5 ms of the frame, 1 thread)."""
    cache = geo.__dict__.setdefault("_live_azimuthal_samples", {})
    key = (supersample, grid, str(device))
    hit = cache.get(key)
    if hit is None or hit[0] is not tris:
        u0, v0 = _azimuthal_samples(geo, supersample, grid)
        t = tris.to(u0.device)
        u0, v0 = u0[:, t].contiguous().to(device), v0[:, t].contiguous().to(device)
        hit = cache[key] = (tris, u0, v0)
    return hit[1], hit[2]


def _quad_rows(envmap, device) -> Tensor:
    """`quad_texels` of the map's periodic texels (float32), kept for the last map data seen: an "L"
    frame rotates the same (prefiltered) texels, whose quad rows do not depend on the rotation
    (settled, 1 thread: ~0.5 ms of such a frame rebuilt them). Keyed on the data's storage, view and
    version counter (an in-place edit of the texels bumps it), holding the data tensor (no reuse of
    its address while cached). The comb path (E frames' live triangles) needs no quad rows."""
    t = envmap.data
    key = (t.untyped_storage().data_ptr(), t.storage_offset(), tuple(t.shape), tuple(t.stride()), t._version,
           t.dtype, str(device))
    hit = _QUAD_ROWS.get("last")
    if hit is None or hit[0] != key:
        Q = quad_texels(envmap.periodic_texels(device, torch.float32, planes=True), envmap.height, envmap.width)
        hit = _QUAD_ROWS["last"] = (key, t, Q)
    return hit[2]


# "last" → (key, the data tensor, its quad rows) of `_quad_rows`' last map
_QUAD_ROWS: dict = {}


def warm_live(envmap, R: Tensor, geo: Geodesic, *, supersample: int, grid: FrameGrid, tris: Tensor) -> int:
    """In the harness's warm-up frame (`methods.core.fused.warming`; elsewhere nothing): compile the
    kernels of `project_env` with ``tris`` — the live-triangle projection later lighting changes run
    (`TripleProduct.fill_lighting`) — on both paths (``envmap`` turned about +Y, the comb path, and
    tilted, the general one), full and tail blocks. Returns the warm-up calls made (0 or 1)."""
    return warm_blocks(_warm_live, [R[:1]], (envmap, R, geo, supersample, grid, tris), [1])


def _warm_live(_row: Tensor, envmap, R: Tensor, geo: Geodesic, supersample: int, grid: FrameGrid,
               tris: Tensor) -> None:
    """`warm_live`'s call (one projection of the whole grid per path; results dropped)."""
    from scenes.envmap import EnvMap

    c, s = math.cos(0.5), math.sin(0.5)
    about_y = torch.tensor([[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]], dtype=envmap.to_world.dtype)
    tilted = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]], dtype=envmap.to_world.dtype) @ about_y
    for T in (about_y, tilted):
        project_env(EnvMap(envmap.data, T), R, geo, supersample=supersample, grid=grid, tris=tris)


def pairs_ok(envmap) -> bool:
    """`project_pairs` applies: the native loop is available and the map is not turned about +Y only
    (that lighting takes the azimuthal / comb paths, whose values the loop does not reproduce)."""
    from methods.triple_product import native_light

    return azimuth_of(envmap.to_world) is None and native_light.available()


def comb_pairs_ok(envmap, grid: FrameGrid | None) -> bool:
    """`project_pairs` applies to a map turned about +Y only: `project_env` takes the comb path there
    (`comb_ok`, `COMB`) and the native loop is available (`native_light.comb_pairs`)."""
    from methods.triple_product import native_light

    return azimuth_of(envmap.to_world) is not None and COMB and comb_ok(grid, envmap.width) \
        and native_light.available()


# `project_pairs`' comb path makes each listed item's taps inside `native_light.comb_pairs_uv` (the
# same offsets and weights as the compiled `comb_taps`, bit for bit) instead of running `comb_taps` over
# every base row and live triangle first (creature bench vertex E: 11,152 items, 6,242 listed; the
# compiled pass ~0.9 ms of a ~12 ms frame, 1 thread). False: the compiled taps (the test oracle).
COMB_TAPS_NATIVE = True


def project_pairs(envmap, R: Tensor, geo: Geodesic, *, supersample: int, tris: Tensor, pairs: Tensor,
                  out: Tensor, grid: FrameGrid | None = None) -> Tensor:
    """`project_env`'s general path with ``tris`` for the (frame, live triangle) pairs ``pairs`` (P,)
    int64 (frame·n' + column of ``tris``) only, into ``out`` (F, 3, n') float32 (returned; the other
    entries untouched): the same fine values bit for bit (`native_light`: the compiled kernels'
    float32 operations in C). Needs `pairs_ok` (envmap) — or, for a map turned about +Y only,
    `comb_pairs_ok` (envmap, grid): then `project_env`'s comb path with ``tris`` (`comb_taps` of every
    base row, compiled, then `native_light.comb_pairs`: `comb_means`' sums on one thread bit for bit,
    for the 8-frame groups holding a listed pair only; other entries of those groups are written with
    their values too)."""
    from methods.triple_product import native_light

    gamma = azimuth_of(envmap.to_world)
    if gamma is not None and COMB and comb_ok(grid, envmap.width):      # `comb_pairs_ok`
        H, W = envmap.height, envmap.width
        _, wT = _live_sample_planes(geo, supersample, tris)
        u0, v0 = _live_azimuthal_samples(geo, supersample, grid, tris, R.device)
        CT = comb_table(envmap.periodic_texels(R.device, torch.float32, planes=True), H, W, grid.n_phi)
        if COMB_TAPS_NATIVE and u0.shape[2] <= native_light.MAX_SAMPLES:   # the listed items' taps in the loop
            return native_light.comb_pairs_uv(pairs, u0, v0, gamma / (2 * math.pi), wT, H, W, CT, grid.n_psi,
                                              grid.n_phi, out)
        g = torch.tensor(gamma / (2 * math.pi), dtype=torch.float64, device=R.device)
        o, w4 = _kernel(comb_taps)(u0, v0, g, wT, H, W, grid.n_phi)
        return native_light.comb_pairs(pairs, o, w4, CT, grid.n_psi, grid.n_phi, W // grid.n_phi, out)
    if gamma is not None:
        raise ValueError("a map turned about +Y only: project_pairs needs comb_pairs_ok (envmap, grid)")
    cp, wT = _live_sample_planes(geo, supersample, tris)
    T = envmap.to_world.float()
    M = torch.mm(R.float().reshape(-1, 3), T).view(-1, 3, 3)       # `env_taps`' R @ T (an extern mm there)
    return native_light.project(pairs, M, cp, wT, envmap.height, envmap.width, _quad_rows(envmap, R.device), out)


def project_env(envmap, R: Tensor, geo: Geodesic, *, supersample: int = 1,
                grid: FrameGrid | None = None, stats: dict | None = None,
                frames: Tensor | None = None, out: tuple[Tensor, Tensor] | None = None,
                tris: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """`project_lighting(envmap.radiance, R, geo, supersample)` at run time, per block of
    `env_block_frames` frames two compiled kernels (`methods.core.fused`): the samples' map
    footprints (`env_taps`), then the per-triangle means from the map's quad rows and their float32
    forward transform (`quad_means_coeffs`).

    Args: envmap (`scenes.envmap.EnvMap`); R (F, 3, 3) world→local rotations; geo; supersample;
        grid: the `FrameGrid` R was made from (``grid_frames(grid)``) or None — with it, a map turned
        about +Y only (`azimuth_of`) takes the shifted base coordinates (`env_taps_azimuthal`);
        stats: receives ``"lighting_path"``, "azimuthal" or "general" (for `fast_eval.frame_cost`).
        frames: (F',) int64 indices of the frames of R to project (None: all), in blocks of the
            same size as the whole projection's and tail blocks (`env_blocks`; a compiled shape
            each, the same values as any other blocking): a pixel frame projects only the grid
            frames its samples look up (`TripleProduct.fill_lighting`).
        out: (coefficients, fine values) tables (F, 3, K) float32 whose rows ``frames`` (all: None)
            receive the result (each block copied into its rows; returned), or None: new tensors.
        tris: (n',) int64 sorted fine triangles (`forward_butterfly`'s fine order) or None (all):
            project only their samples — the fine values of those triangles, no coefficients (a
            transform needs every triangle): returns (None, fine (F', 3, n')), and ``out`` is
            (None, fine table (F, 3, n')). Each triangle's mean is the same arithmetic as in the
            whole projection (the triangles the shading multiplies by an exact 0 need no samples:
            `fast_eval.live_triangles`).
    Returns: coefficients (F, 3, K) float32 (F' rows with ``frames``) (= `project_lighting` to float32 round-off) and the fine
        values (F, 3, K) they transform (the fine-value table of the full grid: no inverse needed).
    """
    if R.ndim != 3 or R.shape[1:] != (3, 3):
        raise ValueError(f"R must be (F, 3, 3), got {tuple(R.shape)}")
    if grid is not None and R.shape[0] != grid.size:
        raise ValueError(f"R has {R.shape[0]} frames, the grid {grid.size}")
    cp, wT = _env_sample_planes(geo, supersample)
    if tris is not None:
        cp, wT = _live_sample_planes(geo, supersample, tris)
    H, W = envmap.height, envmap.width
    lanes = quad_lanes(R.device)
    gamma = None if grid is None else azimuth_of(envmap.to_world)
    if stats is not None:
        stats["lighting_path"] = "general" if gamma is None else "azimuthal"
    chunk = env_block_frames(R.shape[0], cp.shape[1] * cp.shape[2])
    sel = slice(None) if frames is None else frames.to(R.device).long()
    if gamma is not None and comb_ok(grid, W) and COMB:   # turned about +Y, n_phi | W: the comb table
        u0, v0 = _azimuthal_samples(geo, supersample, grid)
        u0, v0 = u0.to(R.device), v0.to(R.device)
        planes = envmap.periodic_texels(R.device, torch.float32, planes=True)
        CT = comb_table(planes, H, W, grid.n_phi)
        g = torch.tensor(gamma / (2 * math.pi), dtype=torch.float64, device=R.device)
        # the general path's two kernels (comment below), the means too: no comb-path frame compiles
        # them, so a sequence whose warm-up lighting turns about +Y (chess / creature "L": the
        # scene's own map first) compiled `quad_means_coeffs` (full and tail blocks) in its first
        # timed frame (1 thread, chess vertex L: 1.2-1.3 s instead of ~70 ms; TORCH_LOGS=recompiles)
        if tris is None:
            warm_blocks(_general_block, [R.float()], (cp, envmap.to_world.float(), H, W, wT, _quad_rows(envmap, R.device), lanes),
                        [chunk, *env_tail_sizes(chunk)])
        else:                                  # the live triangles' samples only
            u0, v0 = _live_azimuthal_samples(geo, supersample, grid, tris, R.device)
        o, w4 = _kernel(comb_taps)(u0, v0, g, wT, H, W, grid.n_phi)
        # on one thread: the compiled loop's sums are split over the team where Inductor vectorises
        # for AVX-512 (an AMD EPYC host, session 30: comb means 3.8e-5 apart between 1 and 2 threads,
        # `test_bit_identical_with_one_and_two_threads[triple_product]`), and `native_light.comb_pairs`
        # reproduces the one-thread sums; this full-grid pass runs when a lighting is set, not per
        # E frame (those take the read pairs)
        with torch_threads(1):
            means = _kernel(comb_means)(o, w4, CT, grid.n_phi, W // grid.n_phi)
        if tris is None:
            coef, fine = _kernel(comb_coeffs)(means)
        else:                                  # (B, n', 3, J) → a (B, J, 3, n') view, frame (b, j): the
            coef, fine = None, means.permute(0, 3, 2, 1)   # rows gathered from it once (no copy of all B·J)
        if frames is None:
            frames = torch.arange(grid.size, device=R.device)
        frames = frames.to(R.device).long()
        rows = _comb_rows(grid, frames)
        if out is not None:
            for x, y in zip(out, (coef, fine)):
                if x is not None and not (y.ndim == 4 and _native_comb_scatter(means, rows, frames, x)):
                    x.index_copy_(0, frames, _comb_select(y, rows))
            return out
        return None if coef is None else coef[rows], _comb_select(fine, rows)
    if gamma is not None:                      # turned about +Y: shifted base coordinates, no trig
        u0, v0 = _azimuthal_samples(geo, supersample, grid)
        if tris is not None:                   # the live triangles' samples only
            u0, v0 = _live_azimuthal_samples(geo, supersample, grid, tris, u0.device)
        f = torch.arange(grid.size, device=R.device)
        j = f // grid.n_psi % grid.n_phi
        base = f // (grid.n_phi * grid.n_psi) * grid.n_psi + f % grid.n_psi
        shift = torch.remainder(j.double() / grid.n_phi - gamma / (2 * math.pi), 1.0)
        rows, taps, args = (shift[sel], base[sel]), _kernel(env_taps_azimuthal), (u0.to(R.device), v0.to(R.device), H, W)
        # the general kernel too, in the harness's warm-up frame (`core.fused.warming`): a sequence
        # whose first lighting turns about +Y only ("L": the scene's own map, then rotations about a
        # tilted axis) needs it first in a timed frame (chess L frame 1 compiled it: ~2x that frame)
        warm_blocks(_kernel(env_taps), [R.float()], (cp, envmap.to_world.float(), H, W),
                    [chunk, *env_tail_sizes(chunk)])
    else:
        rows, taps, args = (R.float()[sel],), _kernel(env_taps), (cp, envmap.to_world.float(), H, W)

    Q = _quad_rows(envmap, R.device)
    if tris is None:
        means = _kernel(quad_means_coeffs)

        def block(*r):  # two compiled kernels per block of frames (a static shape each)
            return means(*taps(*r, *args), wT, Q, lanes)
    else:
        means = _kernel(quad_means)

        def block(*r):  # the live triangles' fine values only (no transform)
            return None, means(*taps(*r, *args), wT, Q, lanes)

    # the tail block sizes too, in the warm-up frame (it projects the whole grid, often no tail)
    warm_blocks(block, rows, (), env_tail_sizes(chunk))
    q = int(rows[0].shape[0])
    if q == 0:
        return map_rows(block, rows, chunk=chunk) if out is None else out
    rows = [r.contiguous() for r in rows]
    dst = None if out is None else (torch.arange(q, device=R.device) if frames is None else sel)
    parts, a = [], 0
    for b in env_blocks(q, chunk):             # full blocks, then tail blocks; the last one padded
        n = min(b, q - a)
        blk = [r[a:a + n] for r in rows]
        if n < b:
            blk = [torch.cat([x, x[-1:].expand(b - n, *x.shape[1:])]) for x in blk]
        o = block(*blk)
        if out is None:
            parts.append(tuple(None if x is None else x[:n] for x in o))
        else:                                  # straight into the caller's rows (no concatenation)
            for x, y in zip(out, o):
                if x is not None:
                    x.index_copy_(0, dst[a:a + n], y[:n])
        a += n
    if out is not None:
        return out
    if len(parts) == 1:
        return parts[0]
    return tuple(None if x[0] is None else torch.cat(x) for x in zip(*parts))   # (F, 3, n) each
