"""Direction sets on the sphere and hemisphere: deterministic grids, quasi-random and random samples.

Every generator returns `(dirs (D, 3), weights (D,))` where `Σ_d weights_d g(dirs_d)` estimates
∫ g(ω) dω over the sphere (or the upper hemisphere z ≥ 0). Hemisphere sets are around +z (the local
shading frame of `methods/core/frames.py`, z = normal). The random samplers (`sample_*`) return the
pdf w.r.t. solid angle instead of a weight.

- `equal_area_sphere/hemisphere`: n_theta × n_phi cells uniform in (cos θ, φ) (Archimedes: equal
  area), cell centres, equal weights 4π/D (2π/D). Mahajan et al. 2008 §3 sample 40×40 per
  direction this way.
- `fibonacci_sphere/hemisphere`: spherical Fibonacci points (golden-angle spiral in φ, uniform in
  cos θ; González 2010), equal weights.
- `gauss_legendre_sphere`: Gauss–Legendre in cos θ × uniform φ, exact for band-limited
  products (reference quadrature).
- `stratified_sphere/hemisphere`: one jittered sample per equal-area cell (torch.Generator).
- `sample_uniform_sphere`, `sample_uniform_hemisphere`, `sample_cosine_hemisphere`: warps of
  uniforms u ∈ [0,1)² to directions, with their pdf (Pharr et al., PBRT 3 §13.6).
- `latlong_grid`: the texel directions of a lat-long env map in the Mitsuba 3.9 `envmap`
  convention (docs/ARCHITECTURE.md) with per-texel solid-angle quadrature weights (see there).
"""
from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor

from methods.core.frames import to_world

GOLDEN_ANGLE = math.pi * (3.0 - math.sqrt(5.0))  # 2π(1 − 1/φ), φ the golden ratio


def _opts(dtype, device):
    return dict(dtype=dtype or torch.get_default_dtype(), device=device)


def _check_pos(**kw):
    for k, v in kw.items():
        if not isinstance(v, int) or v < 1:
            raise ValueError(f"{k} must be an int >= 1, got {v!r}")


def from_cos_phi(z: Tensor, phi: Tensor) -> Tensor:
    """Directions (..., 3) from cos θ (...) and φ (...), z-polar."""
    r = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], dim=-1)


_from_cos_phi = from_cos_phi


def _cells(n_theta: int, n_phi: int, z_lo: float, ju: Tensor | None, jv: Tensor | None,
           dtype, device) -> tuple[Tensor, Tensor]:
    o = _opts(dtype, device)
    i = torch.arange(n_theta, **o)[:, None]
    j = torch.arange(n_phi, **o)[None, :]
    fu = 0.5 if ju is None else ju
    fv = 0.5 if jv is None else jv
    z = 1.0 - (i + fu) * ((1.0 - z_lo) / n_theta)          # uniform in cos θ from 1 down to z_lo
    phi = (j + fv) * (2.0 * math.pi / n_phi)
    z, phi = torch.broadcast_tensors(z, phi)
    d = _from_cos_phi(z, phi).reshape(-1, 3)
    area = 2.0 * math.pi * (1.0 - z_lo)
    w = torch.full((n_theta * n_phi,), area / (n_theta * n_phi), **o)
    return d, w


def equal_area_sphere(n_theta: int, n_phi: int, *, dtype=None, device=None) -> tuple[Tensor, Tensor]:
    """Cell centres of an n_theta × n_phi grid uniform in (cos θ ∈ [−1, 1], φ ∈ [0, 2π)).

    Returns:
        dirs (n_theta·n_phi, 3) (row-major: θ index slowest), weights (n_theta·n_phi,) = 4π/D.
    """
    _check_pos(n_theta=n_theta, n_phi=n_phi)
    return _cells(n_theta, n_phi, -1.0, None, None, dtype, device)


def equal_area_hemisphere(n_theta: int, n_phi: int, *, dtype=None, device=None) -> tuple[Tensor, Tensor]:
    """Cell centres of an n_theta × n_phi grid uniform in (cos θ ∈ [0, 1], φ ∈ [0, 2π)), around +z.

    Returns:
        dirs (D, 3), weights (D,) = 2π/D.
    """
    _check_pos(n_theta=n_theta, n_phi=n_phi)
    return _cells(n_theta, n_phi, 0.0, None, None, dtype, device)


def stratified_sphere(n_theta: int, n_phi: int, generator: torch.Generator | None = None, *,
                      dtype=None, device=None) -> tuple[Tensor, Tensor]:
    """One uniformly jittered sample per equal-area (cos θ, φ) cell of the sphere.

    Returns:
        dirs (D, 3), weights (D,) = 4π/D.
    """
    _check_pos(n_theta=n_theta, n_phi=n_phi)
    o = _opts(dtype, device)
    u = torch.rand((2, n_theta, n_phi), generator=generator, dtype=o["dtype"],
                   device=generator.device if generator is not None else device).to(device=device)
    return _cells(n_theta, n_phi, -1.0, u[0], u[1], dtype, device)


def stratified_hemisphere(n_theta: int, n_phi: int, generator: torch.Generator | None = None, *,
                          dtype=None, device=None) -> tuple[Tensor, Tensor]:
    """One uniformly jittered sample per equal-area cell of the upper (z ≥ 0) hemisphere.

    Returns:
        dirs (D, 3), weights (D,) = 2π/D.
    """
    _check_pos(n_theta=n_theta, n_phi=n_phi)
    o = _opts(dtype, device)
    u = torch.rand((2, n_theta, n_phi), generator=generator, dtype=o["dtype"],
                   device=generator.device if generator is not None else device).to(device=device)
    return _cells(n_theta, n_phi, 0.0, u[0], u[1], dtype, device)


def fibonacci_sphere(n: int, *, dtype=None, device=None) -> tuple[Tensor, Tensor]:
    """Spherical Fibonacci points: z_i = 1 − (2i+1)/n, φ_i = i·golden angle.

    Returns:
        dirs (n, 3), weights (n,) = 4π/n.
    """
    _check_pos(n=n)
    o = _opts(dtype, device)
    i = torch.arange(n, dtype=torch.float64, device=device)
    z = 1.0 - (2.0 * i + 1.0) / n
    phi = torch.remainder(i * GOLDEN_ANGLE, 2.0 * math.pi)
    return _from_cos_phi(z, phi).to(o["dtype"]), torch.full((n,), 4.0 * math.pi / n, **o)


def fibonacci_hemisphere(n: int, *, dtype=None, device=None) -> tuple[Tensor, Tensor]:
    """Fibonacci points on the upper hemisphere: z_i = 1 − (i+½)/n, φ_i = i·golden angle.

    Returns:
        dirs (n, 3), weights (n,) = 2π/n.
    """
    _check_pos(n=n)
    o = _opts(dtype, device)
    i = torch.arange(n, dtype=torch.float64, device=device)
    z = 1.0 - (i + 0.5) / n
    phi = torch.remainder(i * GOLDEN_ANGLE, 2.0 * math.pi)
    return _from_cos_phi(z, phi).to(o["dtype"]), torch.full((n,), 2.0 * math.pi / n, **o)


def gauss_legendre_sphere(n_theta: int, n_phi: int, *, hemisphere: bool = False, dtype=None,
                          device=None) -> tuple[Tensor, Tensor]:
    """Product rule: Gauss–Legendre nodes in cos θ × n_phi uniform φ (offset by half a step).

    Exact for spherical polynomials of degree ≤ min(2·n_theta − 1, n_phi − 1), i.e. SH products
    up to band sums l₁ + l₂ < n_phi; the reference quadrature of the tests. With
    `hemisphere=True` the cos θ nodes are mapped to [0, 1] (exact for polynomials in z there).

    Returns:
        dirs (n_theta·n_phi, 3), weights (n_theta·n_phi,) summing to 4π (2π).
    """
    _check_pos(n_theta=n_theta, n_phi=n_phi)
    o = _opts(dtype, device)
    x, wx = np.polynomial.legendre.leggauss(n_theta)
    z = torch.as_tensor(x, dtype=torch.float64, device=device).flip(0)
    wz = torch.as_tensor(wx, dtype=torch.float64, device=device).flip(0)
    if hemisphere:
        z, wz = 0.5 * (z + 1.0), 0.5 * wz
    phi = (torch.arange(n_phi, dtype=torch.float64, device=device) + 0.5) * (2.0 * math.pi / n_phi)
    zz, pp = torch.broadcast_tensors(z[:, None], phi[None, :])
    d = _from_cos_phi(zz, pp).reshape(-1, 3)
    w = (wz[:, None] * (2.0 * math.pi / n_phi)).expand(n_theta, n_phi).reshape(-1)
    return d.to(o["dtype"]), w.to(o["dtype"])


def _check_u(u: Tensor) -> None:
    if u.ndim < 1 or u.shape[-1] != 2:
        raise ValueError(f"u must have shape (..., 2), got {tuple(u.shape)}")


def sample_uniform_sphere(u: Tensor) -> tuple[Tensor, Tensor]:
    """Uniform sphere warp: z = 1 − 2u₀, φ = 2πu₁.

    Args:
        u: (..., 2) uniforms in [0, 1).
    Returns:
        dirs (..., 3), pdf (...) = 1/(4π).
    """
    _check_u(u)
    d = _from_cos_phi(1.0 - 2.0 * u[..., 0], 2.0 * math.pi * u[..., 1])
    return d, torch.full_like(u[..., 0], 1.0 / (4.0 * math.pi))


def sample_uniform_hemisphere(u: Tensor) -> tuple[Tensor, Tensor]:
    """Uniform upper-hemisphere warp: z = 1 − u₀, φ = 2πu₁.

    Args:
        u: (..., 2) uniforms in [0, 1).
    Returns:
        dirs (..., 3), pdf (...) = 1/(2π).
    """
    _check_u(u)
    d = _from_cos_phi(1.0 - u[..., 0], 2.0 * math.pi * u[..., 1])
    return d, torch.full_like(u[..., 0], 1.0 / (2.0 * math.pi))


def sample_cosine_hemisphere(u: Tensor) -> tuple[Tensor, Tensor]:
    """Cosine-weighted upper hemisphere (Malley's method: uniform disk, r = √u₀, lifted).

    Args:
        u: (..., 2) uniforms in [0, 1).
    Returns:
        dirs (..., 3), pdf (...) = cos θ / π.
    """
    _check_u(u)
    z = torch.sqrt((1.0 - u[..., 0]).clamp_min(0.0))  # cos θ; sin θ = √u₀
    d = _from_cos_phi(z, 2.0 * math.pi * u[..., 1])
    return d, z / math.pi


def cosine_hemisphere_pdf(d: Tensor) -> Tensor:
    """pdf (...) of `sample_cosine_hemisphere` at directions d (..., 3): max(0, z)/π."""
    return d[..., 2].clamp_min(0.0) / math.pi


def random_directions(n: int, kind: str = "sphere", generator: torch.Generator | None = None, *,
                      dtype=None, device=None) -> tuple[Tensor, Tensor]:
    """n i.i.d. Monte-Carlo directions with estimator weights 1/(n·pdf).

    Args:
        kind: "sphere", "hemisphere" or "cosine" (cosine-weighted hemisphere).
    Returns:
        dirs (n, 3), weights (n,).
    """
    _check_pos(n=n)
    warps = {"sphere": sample_uniform_sphere, "hemisphere": sample_uniform_hemisphere,
             "cosine": sample_cosine_hemisphere}
    if kind not in warps:
        raise ValueError(f"kind must be one of {sorted(warps)}, got {kind!r}")
    o = _opts(dtype, device)
    u = torch.rand((n, 2), generator=generator, dtype=o["dtype"],
                   device=generator.device if generator is not None else device).to(device=device)
    d, pdf = warps[kind](u)
    return d, 1.0 / (n * pdf.clamp_min(torch.finfo(pdf.dtype).tiny))


def latlong_row_weights(height: int, *, dtype=None, device=None) -> Tensor:
    """∫ hat_y(θ) sin θ dθ for the corner-aligned rows θ_y = πy/(H−1) of a lat-long map.

    Mitsuba's envmap interpolates bilinearly between rows whose centres sit at v = y/(H−1), i.e.
    the map is piecewise linear in θ with nodes θ_y. Row y's weight is the exact integral of its
    piecewise-linear hat function against sin θ (Δ = π/(H−1)):
        rising part on [a, b] = [θ_{y−1}, θ_y]:  −cos b + (sin b − sin a)/Δ
        falling part on [a, b] = [θ_y, θ_{y+1}]:  cos a − (sin b − sin a)/Δ
    The weights sum to 2 = ∫₀^π sin θ dθ exactly, and Σ_y w_y g(θ_y) is the trapezoid-type rule
    that is exact whenever g is itself piecewise linear on the row grid.

    Returns:
        (H,) weights (computed in float64).
    """
    if not isinstance(height, int) or height < 2:
        raise ValueError(f"height must be an int >= 2, got {height!r}")
    o = _opts(dtype, device)
    dl = math.pi / (height - 1)
    th = torch.arange(height, dtype=torch.float64, device=device) * dl
    a, b = th[:-1], th[1:]
    ds = (torch.sin(b) - torch.sin(a)) / dl
    rising = -torch.cos(b) + ds          # for rows 1..H−1
    falling = torch.cos(a) - ds          # for rows 0..H−2
    w = torch.zeros(height, dtype=torch.float64, device=device)
    w[1:] += rising
    w[:-1] += falling
    return w.to(o["dtype"])


def latlong_directions(height: int, width: int, *, dtype=None, device=None) -> Tensor:
    """Texel directions (H, W, 3) of a lat-long map, Mitsuba 3.9 `envmap` convention (local frame).

    Row y ↦ θ = π·y/(H−1) (corner-aligned), column x ↦ u = (x+½)/W (texel-centred), φ' = 2πu, and
    d = (sin θ sin φ', cos θ, −sin θ cos φ'), the inverse of u = atan2(d.x, −d.z)/(2π),
    v = acos(d.y)/π. Rows 0 and H−1 are the poles ±y.
    """
    if not isinstance(height, int) or height < 2:
        raise ValueError(f"height must be an int >= 2, got {height!r}")
    _check_pos(width=width)
    o = _opts(dtype, device)
    th = torch.arange(height, dtype=torch.float64, device=device) * (math.pi / (height - 1))
    ph = (torch.arange(width, dtype=torch.float64, device=device) + 0.5) * (2.0 * math.pi / width)
    st, ct = torch.sin(th)[:, None], torch.cos(th)[:, None]
    d = torch.stack(torch.broadcast_tensors(st * torch.sin(ph), ct, -st * torch.cos(ph)), dim=-1)
    return d.to(o["dtype"])


def latlong_grid(height: int, width: int, *, dtype=None, device=None) -> tuple[Tensor, Tensor]:
    """Texel directions and solid-angle weights of an H × W lat-long map (Mitsuba convention).

    Quadrature: the map is bilinear between texel nodes (corner-aligned in θ, texel-centred and
    periodic in φ); texel (y, x) gets the exact integral of its bilinear hat function over the
    sphere, w = latlong_row_weights(H)[y] · 2π/W. Hence Σ w L(d) is exactly ∫ L̃ dω for the
    interpolated map L̃ and the rule is second-order accurate for smooth integrands (Σ w = 4π).

    Returns:
        dirs (H·W, 3) row-major (matches `image.reshape(H·W, C)`), weights (H·W,).
    """
    d = latlong_directions(height, width, dtype=dtype, device=device)
    w = latlong_row_weights(height, dtype=torch.float64, device=device)[:, None]
    w = (w * (2.0 * math.pi / width)).expand(height, width).reshape(-1)
    return d.reshape(-1, 3), w.to(d.dtype)


def rotated_hemisphere_dirs(normals: Tensor, n_rays: int, *, seed: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    """``n_rays`` Fibonacci hemisphere directions about every normal, each vertex's set turned by
    its own random azimuth (deterministic in ``seed``), for per-vertex hemisphere quadrature.

    normals: (V, 3) unit normals. Returns local (V, J, 3) directions in each normal's frame
    (z = normal; ``methods.core.frames.to_world`` convention), world (V, J, 3) unit directions and
    weights (J,) = 2π/J.
    """
    if isinstance(n_rays, bool) or not isinstance(n_rays, int) or n_rays < 1:
        raise ValueError(f"the number of rays must be a positive int, got {n_rays!r}")
    N = torch.as_tensor(normals, dtype=torch.float32)
    nv = N.shape[0]
    d, w = fibonacci_hemisphere(n_rays, dtype=torch.float32)            # (J, 3), (J,) = 2π/J
    gen = torch.Generator().manual_seed(int(seed))
    phi = torch.rand(nv, generator=gen) * (2.0 * math.pi)
    c, s = torch.cos(phi)[:, None], torch.sin(phi)[:, None]
    loc = torch.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], d[:, 2].expand(nv, -1)], -1)
    world = to_world(loc, N[:, None, :].expand(nv, n_rays, 3))
    return loc, world / world.norm(dim=-1, keepdim=True), w
