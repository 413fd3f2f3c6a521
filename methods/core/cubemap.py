"""Cube maps and their 2-D Haar wavelet basis (Ng, Ramamoorthi, Hanrahan 2003, "All-Frequency
Shadows Using Non-linear Wavelet Lighting Approximation").

Face order and orientation (defined ONCE here; OpenGL's cube-map table, which Mitsuba's and most
tools' cube maps follow). Faces are indexed 0..5 = +X, −X, +Y, −Y, +Z, −Z. A cube map is a tensor
``(..., 6, N, N)`` (or ``(..., 6, N, N, C)`` for colour) indexed ``[face, row, col]``. Texel
(row, col) has face coordinates

    u = 2 (col + 0.5) / N − 1   (columns, left → right)
    v = 2 (row + 0.5) / N − 1   (rows, top → bottom)

and the (unnormalised) direction on face f is

    +X: ( 1, −v, −u)    −X: (−1, −v,  u)
    +Y: ( u,  1,  v)    −Y: ( u, −1, −v)
    +Z: ( u, −v,  1)    −Z: (−u, −v, −1)

i.e. OpenGL's (s, t) = ((u+1)/2, (v+1)/2) with sc/tc/ma from the GL spec's major-axis table. The
directions are in whatever frame the caller uses (world +Y up, or a local frame z = normal).

Haar basis: per face, the orthonormal 2-D *non-standard* Haar decomposition (Ng 2003 §4; Stollnitz,
DeRose, Salesin 1995 "Wavelets for computer graphics" §3.2): repeatedly replace every 2×2 block
(p00 p01 / p10 p11) by

    s  = (p00 + p01 + p10 + p11)/2      (scaling, moved to the coarser quadrant [0:n/2, 0:n/2])
    dh = (p00 − p01 + p10 − p11)/2      → [0:n/2, n/2:n]   (varies along columns)
    dv = (p00 + p01 − p10 − p11)/2      → [n/2:n, 0:n/2]   (varies along rows)
    dd = (p00 − p01 − p10 + p11)/2      → [n/2:n, n/2:n]   (diagonal)

until one scaling coefficient per face remains at [0, 0]. The transform is orthonormal in the
texel-count measure (Parseval: Σ pixel² = Σ coefficient²), so each face carries N² coefficients.
"""
from __future__ import annotations

import functools
import math

from typing import Any, Callable

import torch
from torch import Tensor

from methods.core.fused import fused, map_rows
from methods.core.latlong import planar_radiance

__all__ = [
    "FACE_NAMES",
    "face_uv",
    "texel_directions",
    "texel_directions_supersampled",
    "texel_solid_angles",
    "dir_to_texel",
    "dir_to_face_uv",
    "haar_forward",
    "haar_inverse",
    "haar_support_area",
    "keep_largest",
    "keep_largest_dense",
    "from_radiance",
    "from_envmap",
    "min_supersample",
    "lookup",
    "integrate",
]

FACE_NAMES = ("+X", "-X", "+Y", "-Y", "+Z", "-Z")


def _check_n(N: int) -> int:
    if int(N) != N or N < 1:
        raise ValueError(f"face resolution N must be a positive integer, got {N}")
    return int(N)


def _face_dirs_from_uv(u: Tensor, v: Tensor) -> Tensor:
    """(…,) face coordinates → (6, …, 3) unnormalised directions (the table in the module doc)."""
    one = torch.ones_like(u)
    return torch.stack([
        torch.stack([one, -v, -u], -1),   # +X
        torch.stack([-one, -v, u], -1),   # −X
        torch.stack([u, one, v], -1),     # +Y
        torch.stack([u, -one, -v], -1),   # −Y
        torch.stack([u, -v, one], -1),    # +Z
        torch.stack([-u, -v, -one], -1),  # −Z
    ])


def face_uv(N: int, *, dtype=torch.float64, device=None) -> tuple[Tensor, Tensor]:
    """Texel-centre face coordinates u (N, N) (varies along col), v (N, N) (varies along row)."""
    N = _check_n(N)
    c = (torch.arange(N, dtype=dtype, device=device) + 0.5) * (2.0 / N) - 1.0
    v, u = torch.meshgrid(c, c, indexing="ij")
    return u, v


def texel_directions(N: int, *, dtype=torch.float32, device=None) -> Tensor:
    """Unit directions through texel centres, (6, N, N, 3)."""
    u, v = face_uv(N, dtype=torch.float64, device=device)
    d = _face_dirs_from_uv(u, v)
    return (d / d.norm(dim=-1, keepdim=True)).to(dtype)


def texel_directions_supersampled(N: int, s: int, *, dtype=torch.float32, device=None) -> Tensor:
    """Directions through the centres of an s×s sub-grid of every texel, (6, N, N, s*s, 3).

    Sub-sample k = a*s + b is sub-row a, sub-column b (the texel (row, col) of resolution N·s at
    (row*s + a, col*s + b)).
    """
    N, s = _check_n(N), _check_n(s)
    d = texel_directions(N * s, dtype=dtype, device=device)  # (6, Ns, Ns, 3)
    return d.reshape(6, N, s, N, s, 3).permute(0, 1, 3, 2, 4, 5).reshape(6, N, N, s * s, 3)


def _area_element(x: Tensor, y: Tensor) -> Tensor:
    # Solid angle of the face rectangle [0,x]×[0,y] at distance 1 (signed):
    # Ω(x, y) = atan2(x y, sqrt(x² + y² + 1))  (e.g. Driscoll, "Cubemap texel solid angle").
    return torch.atan2(x * y, torch.sqrt(x * x + y * y + 1.0))


def texel_solid_angles(N: int, *, dtype=torch.float32, device=None) -> Tensor:
    """Exact solid angle of every texel, (6, N, N); sums to 4π. Identical on all faces."""
    N = _check_n(N)
    e = torch.arange(N + 1, dtype=torch.float64, device=device) * (2.0 / N) - 1.0  # texel edges
    y0, x0 = torch.meshgrid(e[:-1], e[:-1], indexing="ij")
    y1, x1 = torch.meshgrid(e[1:], e[1:], indexing="ij")
    w = _area_element(x1, y1) - _area_element(x0, y1) - _area_element(x1, y0) + _area_element(x0, y0)
    return w.expand(6, N, N).to(dtype).contiguous()


def dir_to_texel(d: Tensor, N: int) -> tuple[Tensor, Tensor, Tensor]:
    """Texel containing each direction.

    Args:
        d: (..., 3) directions (need not be unit). Ties between major axes go to x, then y, then z.
        N: face resolution.
    Returns:
        face, row, col: (...,) int64.
    """
    face, u, v = dir_to_face_uv(d)
    col = ((u + 1.0) * (0.5 * N)).floor().long().clamp(0, N - 1)
    row = ((v + 1.0) * (0.5 * N)).floor().long().clamp(0, N - 1)
    return face, row, col


def dir_to_face_uv(d: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Direction (..., 3) → face (...,) int64 and face coordinates u, v (...,) in [−1, 1]."""
    d = torch.as_tensor(d)
    if d.shape[-1] != 3:
        raise ValueError(f"directions must have shape (..., 3), got {tuple(d.shape)}")
    x, y, z = d.unbind(-1)
    ax, ay, az = x.abs(), y.abs(), z.abs()
    isx = (ax >= ay) & (ax >= az)
    isy = ~isx & (ay >= az)
    face = torch.where(isx, torch.where(x >= 0, 0, 1), torch.where(isy, torch.where(y >= 0, 2, 3),
                                                                      torch.where(z >= 0, 4, 5)))
    ma = torch.where(isx, ax, torch.where(isy, ay, az)).clamp_min(torch.finfo(d.dtype).tiny)
    # invert the table of the module docstring
    u = torch.where(isx, torch.where(x >= 0, -z, z), torch.where(isy, x, torch.where(z >= 0, x, -x))) / ma
    v = torch.where(isx, -y, torch.where(isy, torch.where(y >= 0, z, -z), -y)) / ma
    return face.long(), u, v


# -- 2-D non-standard Haar ----------------------------------------------------------------------


def _check_pow2(x: Tensor) -> int:
    if x.ndim < 2 or x.shape[-1] != x.shape[-2]:
        raise ValueError(f"expected (..., N, N) faces, got {tuple(x.shape)}")
    N = x.shape[-1]
    if N & (N - 1):
        raise ValueError(f"Haar transform needs a power-of-two face size, got N={N}")
    return N


def haar_forward(x: Tensor) -> Tensor:
    """Orthonormal 2-D non-standard Haar transform of each face (Ng 2003 §4).

    Args:
        x: (..., N, N) face data, N a power of two (typically (..., 6, N, N)); applied per
            trailing N×N face, batched over all leading dims.
    Returns:
        (..., N, N) coefficients in the in-place layout of the module docstring.
    """
    N = _check_pow2(x)
    c = x.clone()
    n = N
    while n > 1:
        h = n // 2
        blk = c[..., :n, :n]
        p00, p01 = blk[..., 0::2, 0::2], blk[..., 0::2, 1::2]
        p10, p11 = blk[..., 1::2, 0::2], blk[..., 1::2, 1::2]
        s = (p00 + p01 + p10 + p11) * 0.5
        dh = (p00 - p01 + p10 - p11) * 0.5
        dv = (p00 + p01 - p10 - p11) * 0.5
        dd = (p00 - p01 - p10 + p11) * 0.5
        c[..., :h, :h] = s
        c[..., :h, h:n] = dh
        c[..., h:n, :h] = dv
        c[..., h:n, h:n] = dd
        n = h
    return c


def haar_inverse(c: Tensor) -> Tensor:
    """Inverse of `haar_forward`: (..., N, N) coefficients → (..., N, N) face data."""
    N = _check_pow2(c)
    x = c.clone()
    n = 2
    while n <= N:
        h = n // 2
        s = x[..., :h, :h].clone()
        dh = x[..., :h, h:n].clone()
        dv = x[..., h:n, :h].clone()
        dd = x[..., h:n, h:n].clone()
        blk = x[..., :n, :n]
        blk[..., 0::2, 0::2] = (s + dh + dv + dd) * 0.5
        blk[..., 0::2, 1::2] = (s - dh + dv - dd) * 0.5
        blk[..., 1::2, 0::2] = (s + dh - dv - dd) * 0.5
        blk[..., 1::2, 1::2] = (s - dh - dv + dd) * 0.5
        n *= 2
    return x


def haar_support_area(N: int, *, solid_angle: bool = False, dtype=torch.float32, device=None) -> Tensor:
    """Area of the support of every Haar coefficient, (6, N, N) in the `haar_forward` layout.

    ``solid_angle=False``: fraction of the face covered (a level-j coefficient covers
    (N/2^j)² texels → 4^−j; the face scaling function covers 1). ``solid_angle=True``: the real
    solid angle of the support (sum of its texels' solid angles).
    Used as selection weights for `keep_largest` ("area-weighted" selection, Ng 2003 §5).
    """
    N = _check_n(N)
    if N & (N - 1):
        raise ValueError(f"N must be a power of two, got {N}")
    # support size (in texels per side) of each coefficient slot
    side = torch.full((N, N), float(N), dtype=torch.float64, device=device)
    n = N
    while n > 1:
        h = n // 2
        side[:h, h:n] = N / h
        side[h:n, :h] = N / h
        side[h:n, h:n] = N / h
        n = h
    if not solid_angle:
        return (side / N).square().expand(6, N, N).to(dtype).contiguous()
    # solid angle of the support of slot (r, c) at level with 2^j = N/side blocks per side:
    omega = texel_solid_angles(N, dtype=torch.float64, device=device)[0]
    out = torch.empty(N, N, dtype=torch.float64, device=device)
    out[0, 0] = omega.sum()
    n = N
    while n > 1:
        h = n // 2
        k = N // h  # texels per side of each support block at this level
        blocks = omega.reshape(h, k, h, k).sum((1, 3))  # (h, h)
        out[:h, h:n] = blocks
        out[h:n, :h] = blocks
        out[h:n, h:n] = blocks
        n = h
    return out.expand(6, N, N).to(dtype).contiguous()


# -- non-linear approximation -------------------------------------------------------------------


def keep_largest(coeffs: Tensor, n: int, *, weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Non-linear approximation: the n coefficients with the largest |c|·w in every row.

    Args:
        coeffs: (..., K) coefficient vectors (flatten a cube map's (6, N, N) to K = 6N² first;
            for colour, select on a luminance / channel-summed magnitude and gather).
        n: number kept per row (clamped to K).
        weights: optional (K,) or broadcastable (..., K) non-negative weights (e.g. support areas
            from `haar_support_area(...).flatten()`); None = plain magnitude (L2-optimal for an
            orthonormal basis).
    Returns:
        indices (..., n) int64 sorted by decreasing weighted magnitude, values (..., n) = coeffs at
        those indices.
    """
    if coeffs.ndim < 1:
        raise ValueError("coeffs must have a trailing coefficient dimension")
    K = coeffs.shape[-1]
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    n = min(int(n), K)
    score = coeffs.abs()
    if weights is not None:
        weights = torch.as_tensor(weights, dtype=coeffs.dtype, device=coeffs.device)
        if weights.shape[-1] != K:
            raise ValueError(f"weights must end in K={K}, got {tuple(weights.shape)}")
        score = score * weights
    idx = torch.topk(score, n, dim=-1, largest=True, sorted=True).indices
    return idx, torch.gather(coeffs, -1, idx)


def keep_largest_dense(coeffs: Tensor, n: int, *, weights: Tensor | None = None) -> Tensor:
    """`keep_largest` returned densely: (..., K) with all but the kept coefficients zeroed."""
    idx, val = keep_largest(coeffs, n, weights=weights)
    return torch.zeros_like(coeffs).scatter(-1, idx, val)


# -- resampling ----------------------------------------------------------------------------------


def min_supersample(N: int, source_res: int | None) -> int:
    """Sub-samples per texel side that put two sub-samples in every pixel of a lat-long source
    ``source_res`` rows high (rows span π): the sub-sample spacing (π/2)/(N·s) must not exceed
    half a pixel, π/(2·source_res), so s ≥ source_res / N (a power of two; 1 without a source)."""
    if source_res is None:
        return 1
    need = max(1, math.ceil(int(source_res) / int(N)))
    return 1 << (need - 1).bit_length()


def from_radiance(radiance: Callable[[Tensor], Tensor], N: int, *, supersample: int = 4,
                  source_res: int | None = None, dtype=torch.float32, device=None) -> Tensor:
    """Resample a spherical function (e.g. a lat-long env map) into a cube map.

    Every texel gets the solid-angle-weighted mean of s² sub-texel samples (exact sub-texel solid
    angles), i.e. an approximation of (1/Ω_texel) ∫_texel L dω, with s = max(``supersample``,
    `min_supersample` (N, ``source_res``)). Point sub-samples coarser than the source's pixels
    alias a small bright source: a sun of a few pixels is either missed or counted over a whole
    sub-sample's solid angle. Measured on a 256 × 512 captured probe (the bench creature's E frame
    2): at N = 16, s = 4 the cube's irradiance on an upward normal was 1.71× the converged value
    (s = 32) and in-out rendered the sunlit ground 1.78× too bright; at s = 16 (two sub-samples per
    pixel) it is within 1 %.

    Args:
        radiance: callable (..., 3) unit directions → (..., C) values, e.g.
            ``scenes.envmap.EnvMap.radiance`` (directions are in the env map's world frame).
        N: face resolution; supersample: sub-samples per texel side (at least).
        source_res: rows of the lat-long map ``radiance`` reads (``EnvMap.data.shape[0]``), or None.
    Returns:
        (6, N, N, C) texel values.
    """
    N, s = _check_n(N), _check_n(supersample)
    s = max(s, min_supersample(N, source_res))
    d = texel_directions_supersampled(N, s, dtype=dtype, device=device)  # (6, N, N, s², 3)
    w = texel_solid_angles(N * s, dtype=torch.float64, device=device)
    w = w.reshape(6, N, s, N, s).permute(0, 1, 3, 2, 4).reshape(6, N, N, s * s)
    L = radiance(d)
    if L.shape[:-1] != d.shape[:-1]:
        raise ValueError(f"radiance returned {tuple(L.shape)} for directions {tuple(d.shape)}")
    w = (w / w.sum(-1, keepdim=True)).to(L.dtype)
    return (L * w[..., None]).sum(-2).to(dtype)


@functools.lru_cache(maxsize=8)
def _subsample_table(N: int, s: int) -> tuple[Tensor, Tensor]:
    """`from_radiance`'s sub-sample directions as (3, 6N²s²) float32 (x, y, z rows: contiguous
    columns vectorise in the compiled loop, a (n, 3) layout's stride-3 loads made it ~10× slower)
    and their per-texel normalised solid-angle weights (6N²s²,) float32, samples ordered (face,
    row, col, sub-sample); cached: they depend on (N, s) only, never on the map or its rotation."""
    d = texel_directions_supersampled(N, s, dtype=torch.float32).reshape(-1, 3)
    w = texel_solid_angles(N * s, dtype=torch.float64)
    w = w.reshape(6, N, s, N, s).permute(0, 1, 3, 2, 4).reshape(6, N, N, s * s)
    w = (w / w.sum(-1, keepdim=True)).to(torch.float32).reshape(-1)
    return d.T.contiguous(), w.contiguous()


def _weighted_lookup(dx: Tensor, dy: Tensor, dz: Tensor, w: Tensor, R: Tensor, ext: Tensor,
                     H: int, W: int) -> tuple[Tensor, Tensor, Tensor]:
    """Sub-samples (world direction components dx, dy, dz (n,), weights w (n,)) → w · L per
    channel, three (n,): Mitsuba's bilinear env-map look-up at R^T d (R = to_world, (3, 3)), op for
    op `scenes.envmap.bilinear_lookup` (and ``EnvMap.to_local``'s d @ R) but per channel, so that the
    compiled loop runs over samples (vectorised atan2/acos; over an (n, 3) result Inductor
    vectorised the 3 channels and called scalar atan2/acos, 2× slower). ext: (3, H·(W+1)) channel
    planes of the periodic-extended texels (`scenes.envmap.extend_periodic`); H, W: map size."""
    x, y, z = (dx * R[0, j] + dy * R[1, j] + dz * R[2, j] for j in range(3))
    r, g, b = planar_radiance(x, y, z, ext, H, W)
    return r * w, g * w, b * w


def _texel_sums(dx: Tensor, dy: Tensor, dz: Tensor, w: Tensor, R: Tensor, ext: Tensor,
                H: int, W: int) -> Tensor:
    """Texels (n rows of s² sub-samples: dx, dy, dz, w (n, s²)) → (n, 3) Σ_sub w · L: `_weighted_lookup`
    and the per-texel sum in one compiled loop (each texel summed by one thread: the result does not
    depend on the thread count), so no per-sub-sample value is stored and read back."""
    r, g, b = _weighted_lookup(dx, dy, dz, w, R, ext, H, W)
    return torch.stack([r.sum(-1), g.sum(-1), b.sum(-1)], -1)


_texel_sums_fused = fused(_texel_sums)
# Sub-samples per compiled block of `from_envmap` (whole texels: ``TEXEL_BLOCK // s²`` of them, at most
# the 6N² of the cube): in-out's 16² cube at s = 16 is one block of 6·16²·16² = 393k sub-samples.
# One block against blocks of 128 texels (32k sub-samples): 1.3× (per-block launch and the
# reduction's start-up; ``benchmarks.cube_resample``).
TEXEL_BLOCK = 1 << 19


def from_envmap(envmap: Any, N: int, *, supersample: int = 4, dtype=torch.float32) -> Tensor:
    """`from_radiance` (``envmap.radiance``, N, supersample=..., source_res=envmap.height), fast.

    The same sub-samples, weights and bilinear look-ups as that (slow, test-oracle) path, so the
    same texels to float32 round-off: the sub-sample directions and weights are cached per (N, s)
    (`_subsample_table`), the rotation, look-up and weighting of each sub-sample and the per-texel
    sum over its s² sub-samples run as one compiled loop over blocks of whole texels
    (`_texel_sums`, `TEXEL_BLOCK`; `methods.core.fused.map_rows`). Costs (``python -m
    benchmarks.cube_resample``) are per call, nothing is kept between calls but the (N, s) table and
    the map's periodic texels (`EnvMap.periodic_texels`), so a rotated map (every L frame) costs the
    same as an unchanged one. Summing in the compiled loop instead of storing the s²·6N² weighted
    values and summing them eagerly: 1.45-1.6× per call at N = 16, s = 16 (1 thread, process CPU
    time, same process, load ~9: 10.0 → 6.4 ms); the loop is bound by its 12 scalar texel gathers
    per sub-sample (the rotation, atan2 and acos alone: ~2.5 ms; the texels as 64-byte quad rows,
    ``latlong.quad_texels``, one vector load per sub-sample: slower, 11 ms).

    Args:
        envmap: a ``scenes.envmap.EnvMap`` (lat-long texels ``data`` (H, W, 3), ``to_world``).
        N: face resolution; supersample: sub-samples per texel side (at least; raised to
            `min_supersample` (N, H) as in `from_radiance`).
    Returns:
        (6, N, N, 3) texel values in ``dtype`` (CPU).
    """
    N, s = _check_n(N), _check_n(supersample)
    s = max(s, min_supersample(N, envmap.height))
    d, w = _subsample_table(N, s)
    R = envmap.to_world.to(torch.float32).contiguous()
    ext = envmap.periodic_texels(None, torch.float32, planes=True)  # (3, H·(W+1))
    S2 = s * s
    rows = [t.view(6 * N * N, S2) for t in (d[0], d[1], d[2], w)]   # texel-major (face, row, col)
    Lt = map_rows(_texel_sums_fused, rows, (R, ext, envmap.height, envmap.width),
                  chunk=max(1, min(6 * N * N, TEXEL_BLOCK // S2)))
    return Lt.reshape(6, N, N, 3).to(dtype)


def pool_means(cube: Tensor) -> Tensor:
    """A (6, 2N, 2N, C) cube map of texel means → the (6, N, N, C) one: each texel the solid-angle
    weighted mean Σ_c Ω_c m_c / Σ_c Ω_c of its 2×2 children (Ω exact, `texel_solid_angles`).
    `from_envmap` (N, s) is this of `from_envmap` (2N, s/2) to float32 round-off — the same
    sub-samples (the N·s grid), a parent's Ω-weighted sum of them regrouped by child."""
    N2, C = int(cube.shape[1]), int(cube.shape[-1])
    if cube.ndim != 4 or cube.shape[0] != 6 or cube.shape[2] != N2 or N2 % 2:
        raise ValueError(f"need a (6, 2N, 2N, C) cube, got {tuple(cube.shape)}")
    N = N2 // 2
    w = texel_solid_angles(N2, dtype=torch.float64)[0].reshape(N, 2, N, 2).permute(0, 2, 1, 3).reshape(N, N, 4)
    w = (w / w.sum(-1, keepdim=True)).to(cube.dtype)
    c = cube.reshape(6, N, 2, N, 2, C).permute(0, 1, 3, 2, 4, 5).reshape(6, N, N, 4, C)
    return (c * w[None, :, :, :, None]).sum(3)


def lookup(cube: Tensor, d: Tensor) -> Tensor:
    """Nearest-texel lookup: cube (6, N, N, C) or (6, N, N), d (..., 3) → (..., C) or (...,)."""
    if cube.ndim < 3 or cube.shape[0] != 6 or cube.shape[1] != cube.shape[2]:
        raise ValueError(f"cube must be (6, N, N[, C]), got {tuple(cube.shape)}")
    f, r, c = dir_to_texel(d, cube.shape[1])
    return cube[f, r, c]


def integrate(cube: Tensor) -> Tensor:
    """∫ f dω of cube maps (..., 6, N, N) → (...,) using the exact texel solid angles."""
    N = cube.shape[-1]
    if cube.ndim < 3 or cube.shape[-3] != 6 or cube.shape[-2] != N:
        raise ValueError(f"cube must be (..., 6, N, N), got {tuple(cube.shape)}")
    w = texel_solid_angles(N, dtype=cube.dtype, device=cube.device)
    return (cube * w).sum((-3, -2, -1))
