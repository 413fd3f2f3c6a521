"""Real orthonormal spherical harmonics (SH): evaluation, projection, reconstruction.

Convention (docs/ARCHITECTURE.md, "Conventions"):
- Real, orthonormal on the unit sphere: ∫ y_i y_j dω = δ_ij.
- Flat index i = l(l+1) + m; "order n" means bands l = 0..n−1, i.e. n² coefficients.
- Polar axis is +z of whatever frame the directions are given in (θ = acos z, φ = atan2(y, x)), so
  in a local shading frame (z = normal) band 1 is (y_{1,−1}, y_{1,0}, y_{1,1}) = c·(y, z, x),
  c = √(3/(4π)).
- The Condon–Shortley phase (−1)^m is NOT included:
      y_{l,0}  = K_l^0 P_l^0(cos θ)
      y_{l,m}  = √2 K_l^m P_l^m(cos θ) cos(mφ),        m > 0
      y_{l,−m} = √2 K_l^m P_l^m(cos θ) sin(mφ),        m > 0
  with K_l^m = √((2l+1)/(4π) (l−m)!/(l+m)!) and P_l^m the associated Legendre function WITHOUT
  (−1)^m (so P_l^l(z) = (2l−1)!! (1−z²)^{l/2} ≥ 0). This is the convention of Sloan, "Stupid SH
  Tricks" (2008) with the (−1)^m dropped, i.e. every y_{l,±m} with odd m has the opposite sign of a
  Condon–Shortley basis. scipy's `sph_harm_y` includes the phase; `tests/methods/core/test_sh.py`
  converts and compares.

Evaluation is a polynomial in (x, y, z): P_l^m(z) = (1−z²)^{m/2} Q_l^m(z) and
(1−z²)^{m/2} (cos mφ, sin mφ) = (Re, Im)(x + iy)^m, so no trigonometric functions are needed and
directions are taken as given (pass unit vectors). Q is computed with the standard fully
normalised forward-column recurrence (sectoral seed, then three-term in l; stable to high order,
cf. Holmes & Featherstone 2002, "A unified approach to the Clenshaw summation and the recursive
computation of very high degree and order normalised associated Legendre functions"); orders ≤ 6
use hard-coded polynomials generated symbolically (sympy) from the same recurrence (tested equal).

API: `sh_eval(dirs, order)`, `project(values, dirs, weights, order)`, `reconstruct(coeffs, dirs)`,
`project_latlong(image_or_envmap, order)` (exact projection of the bilinear lat-long map Mitsuba
renders; coefficients in the frame of the map, or in world space for an EnvMap with `to_world`).
Coefficient arrays are (n², C): coefficient index first, channels last.
"""
from __future__ import annotations

import functools
import math

import numpy as np
import torch
from torch import Tensor

from methods.core.fused import fused
from methods.core.sampling import latlong_grid
from methods.core.sh_rotation import rotate_coeffs

FAST_MAX_ORDER = 6


def n_coeffs(order: int) -> int:
    """Number of SH coefficients of order n (bands 0..n−1): n²."""
    return order * order


def sh_index(l: int, m: int) -> int:
    """Flat index of (l, m): l(l+1) + m."""
    if abs(m) > l:
        raise ValueError(f"|m| must be <= l, got l={l}, m={m}")
    return l * (l + 1) + m


def _check(dirs: Tensor, order: int) -> None:
    if not isinstance(order, int) or order < 1:
        raise ValueError(f"order must be an int >= 1, got {order!r}")
    if dirs.ndim < 1 or dirs.shape[-1] != 3:
        raise ValueError(f"dirs must have shape (..., 3), got {tuple(dirs.shape)}")


def sh_eval(dirs: Tensor, order: int, *, fast: bool = True) -> Tensor:
    """Real SH basis y_i(d) for i < order².

    Args:
        dirs: (..., 3) unit directions (any float dtype/device).
        order: n ≥ 1, bands 0..n−1.
        fast: use the hard-coded polynomials when order ≤ 6 (else the recurrence).
    Returns:
        (..., order²) basis values, dtype/device of `dirs`.
    """
    _check(dirs, order)
    if not dirs.is_floating_point():
        dirs = dirs.float()
    if fast and order <= FAST_MAX_ORDER:
        return _sh_eval_fast(dirs, order)
    return sh_eval_recurrence(dirs, order)


def sh_eval_recurrence(dirs: Tensor, order: int) -> Tensor:
    """Real SH via the normalised associated-Legendre recurrence, any order.

    Args:
        dirs: (..., 3) unit directions.
        order: n ≥ 1.
    Returns:
        (..., order²).
    """
    _check(dirs, order)
    return torch.stack(_terms_recurrence(*dirs.unbind(-1), order), dim=-1)


def sh_terms(x: Tensor, y: Tensor, z: Tensor, order: int, *, fast: bool = True) -> list[Tensor]:
    """`sh_eval` as a list of the n² basis values, each of the shape of the direction components
    x, y, z (unit directions): for kernels that keep the coefficient index outside the points'
    (``torch.stack(sh_terms(...))`` is the point-minor (n², ...) layout)."""
    if not isinstance(order, int) or order < 1:
        raise ValueError(f"order must be an int >= 1, got {order!r}")
    if fast and order <= FAST_MAX_ORDER:
        return _terms_fast(x, y, z, order)
    return _terms_recurrence(x, y, z, order)


def _terms_recurrence(x: Tensor, y: Tensor, z: Tensor, order: int) -> list[Tensor]:
    out = [None] * (order * order)
    sqrt2 = math.sqrt(2.0)
    # Sectoral start q_m^m = K_m^m (2m−1)!!, q_m^m = q_{m−1}^{m−1} √((2m+1)/(2m)); q_0^0 = 1/√(4π).
    qmm = 1.0 / math.sqrt(4.0 * math.pi)
    c = torch.ones_like(x)   # Re (x+iy)^m
    s = torch.zeros_like(x)  # Im (x+iy)^m
    for m in range(order):
        if m > 0:
            qmm *= math.sqrt((2 * m + 1) / (2 * m))
            c, s = x * c - y * s, x * s + y * c
        # Q along l for this m (normalised three-term recurrence, Holmes & Featherstone 2002):
        # q_{m+1}^m = √(2m+3) z q_m^m;
        # q_l^m = a_lm (z q_{l−1}^m − b_lm q_{l−2}^m),
        # a_lm = √((4l²−1)/(l²−m²)), b_lm = √(((l−1)²−m²)/(4(l−1)²−1)).
        q_prev2 = None
        q_prev = torch.full_like(z, qmm)
        for l in range(m, order):
            if l == m + 1:
                q = math.sqrt(2 * m + 3) * z * q_prev
            elif l > m + 1:
                a = math.sqrt((4 * l * l - 1) / (l * l - m * m))
                b = math.sqrt(((l - 1) ** 2 - m * m) / (4 * (l - 1) ** 2 - 1))
                q = a * (z * q_prev - b * q_prev2)
            else:
                q = q_prev
            if m == 0:
                out[l * (l + 1)] = q
            else:
                out[l * (l + 1) + m] = sqrt2 * q * c
                out[l * (l + 1) - m] = sqrt2 * q * s
            if l > m:
                q_prev2, q_prev = q_prev, q
    return out


def _sh_eval_fast(dirs: Tensor, order: int) -> Tensor:
    """Hard-coded polynomials for order ≤ 6 (generated symbolically from `sh_eval_recurrence`)."""
    return torch.stack(_terms_fast(*dirs.unbind(-1), order), dim=-1)


def _terms_fast(x: Tensor, y: Tensor, z: Tensor, order: int) -> list[Tensor]:
    out = []
    x2, y2, z2 = x * x, y * y, z * z
    x3, y3, z3 = x2 * x, y2 * y, z2 * z
    x4, y4, z4 = x2 * x2, y2 * y2, z2 * z2
    x5, y5, z5 = x4 * x, y4 * y, z4 * z
    out.append(torch.full_like(x, 0.28209479177387814))  # l=0, m=0
    if order == 1:
        return out
    out.append(0.4886025119029199*y)  # l=1, m=-1
    out.append(0.4886025119029199*z)  # l=1, m=0
    out.append(0.4886025119029199*x)  # l=1, m=1
    if order == 2:
        return out
    out.append(1.0925484305920792*x*y)  # l=2, m=-2
    out.append(1.0925484305920792*y*z)  # l=2, m=-1
    out.append(0.94617469575756*z2 - 0.31539156525252)  # l=2, m=0
    out.append(1.0925484305920792*x*z)  # l=2, m=1
    out.append(0.5462742152960396*x2 - 0.5462742152960396*y2)  # l=2, m=2
    if order == 3:
        return out
    out.append(1.7701307697799304*x2*y - 0.5900435899266435*y3)  # l=3, m=-3
    out.append(2.8906114426405543*x*y*z)  # l=3, m=-2
    out.append(2.2852289973223288*y*z2 - 0.4570457994644657*y)  # l=3, m=-1
    out.append(1.865881662950577*z3 - 1.1195289977703462*z)  # l=3, m=0
    out.append(2.2852289973223288*x*z2 - 0.4570457994644657*x)  # l=3, m=1
    out.append(1.4453057213202771*x2*z - 1.4453057213202771*y2*z)  # l=3, m=2
    out.append(0.5900435899266435*x3 - 1.7701307697799304*x*y2)  # l=3, m=3
    if order == 4:
        return out
    out.append(2.5033429417967046*x3*y - 2.5033429417967046*x*y3)  # l=4, m=-4
    out.append(5.310392309339791*x2*y*z - 1.7701307697799304*y3*z)  # l=4, m=-3
    out.append(6.623222870302921*x*y*z2 - 0.94617469575756*x*y)  # l=4, m=-2
    out.append(4.683325804901024*y*z3 - 2.0071396306718676*y*z)  # l=4, m=-1
    out.append(3.7024941420321507*z4 - 3.173566407456129*z2 + 0.31735664074561293)  # l=4, m=0
    out.append(4.683325804901024*x*z3 - 2.0071396306718676*x*z)  # l=4, m=1
    out.append(3.3116114351514603*x2*z2 - 0.47308734787878*x2 - 3.3116114351514603*y2*z2 + 0.47308734787878*y2)  # l=4, m=2
    out.append(1.7701307697799304*x3*z - 5.310392309339791*x*y2*z)  # l=4, m=3
    out.append(0.6258357354491761*x4 - 3.755014412695057*x2*y2 + 0.6258357354491761*y4)  # l=4, m=4
    if order == 5:
        return out
    out.append(3.2819102842008507*x4*y - 6.5638205684017015*x2*y3 + 0.6563820568401701*y5)  # l=5, m=-5
    out.append(8.302649259524165*x3*y*z - 8.302649259524165*x*y3*z)  # l=5, m=-4
    out.append(13.209434084751761*x2*y*z2 - 1.467714898305751*x2*y - 4.403144694917254*y3*z2 + 0.4892382994352504*y3)  # l=5, m=-3
    out.append(14.380610354919972*x*y*z3 - 4.793536784973324*x*y*z)  # l=5, m=-2
    out.append(9.511879675109636*y*z4 - 6.341253116739757*y*z2 + 0.45294665119569694*y)  # l=5, m=-1
    out.append(7.367870314565686*z5 - 8.186522571739651*z3 + 1.754254836801354*z)  # l=5, m=0
    out.append(9.511879675109636*x*z4 - 6.341253116739757*x*z2 + 0.45294665119569694*x)  # l=5, m=1
    out.append(7.190305177459986*x2*z3 - 2.396768392486662*x2*z - 7.190305177459986*y2*z3 + 2.396768392486662*y2*z)  # l=5, m=2
    out.append(4.403144694917254*x3*z2 - 0.4892382994352504*x3 - 13.209434084751761*x*y2*z2 + 1.467714898305751*x*y2)  # l=5, m=3
    out.append(2.075662314881041*x4*z - 12.453973889286248*x2*y2*z + 2.075662314881041*y4*z)  # l=5, m=4
    out.append(0.6563820568401701*x5 - 6.5638205684017015*x3*y2 + 3.2819102842008507*x*y4)  # l=5, m=5
    return out


def project(values: Tensor, dirs: Tensor, weights: Tensor, order: int) -> Tensor:
    """SH coefficients by quadrature: c_i = Σ_d w_d f(d) y_i(d).

    Args:
        values: (D, C) or (D,) function samples.
        dirs: (D, 3) unit directions.
        weights: (D,) quadrature weights (solid angle per sample).
        order: n ≥ 1.
    Returns:
        (order², C) (or (order²,) if `values` was 1-D).
    """
    _check(dirs, order)
    if dirs.ndim != 2:
        raise ValueError(f"dirs must have shape (D, 3), got {tuple(dirs.shape)}")
    D = dirs.shape[0]
    squeeze = values.ndim == 1
    v = values.unsqueeze(-1) if squeeze else values
    if v.ndim != 2 or v.shape[0] != D:
        raise ValueError(f"values must have shape (D, C) or (D,) with D={D}, got {tuple(values.shape)}")
    if weights.shape != (D,):
        raise ValueError(f"weights must have shape ({D},), got {tuple(weights.shape)}")
    Y = sh_eval(dirs.to(v.dtype), order)  # (D, n²)
    c = Y.transpose(0, 1) @ (v * weights.to(v.dtype).unsqueeze(-1))
    return c.squeeze(-1) if squeeze else c


def reconstruct(coeffs: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate an SH expansion f(d) = Σ_i c_i y_i(d).

    Args:
        coeffs: (n², C) or (n²,) coefficients (n² must be a perfect square).
        dirs: (..., 3) unit directions.
    Returns:
        (..., C) (or (...) if `coeffs` was 1-D).
    """
    K = coeffs.shape[0] if coeffs.ndim >= 1 else 0
    order = math.isqrt(K)
    if coeffs.ndim not in (1, 2) or order * order != K or K == 0:
        raise ValueError(f"coeffs must have shape (n², C) or (n²,), got {tuple(coeffs.shape)}")
    _check(dirs, order)
    Y = sh_eval(dirs.to(coeffs.dtype), order)
    return Y @ coeffs


# Proper rotation taking a Mitsuba env-map local direction d to a z-polar frame e = Q d whose polar
# angle is θ = acos(d.y) and whose azimuth is ψ = −φ', φ' = atan2(d.x, −d.z) = 2πu:
# e = (−d.z, −d.x, d.y) = (sin θ cos ψ, sin θ sin ψ, cos θ); det Q = +1.
_LATLONG_Q = ((0.0, 0.0, -1.0), (-1.0, 0.0, 0.0), (0.0, 1.0, 0.0))


def project_latlong(image, order: int, *, method: str = "exact", supersample: int = 4) -> Tensor:
    """Project a lat-long environment map (Mitsuba 3.9 `envmap` convention) onto SH.

    The map seen by Mitsuba is the bilinear interpolant L̃ of the texels: corner-aligned rows at
    θ_y = πy/(H−1), texel-centred periodic columns at φ'_x = 2π(x+½)/W (docs/ARCHITECTURE.md).
    Methods:
    - "exact" (default): ∫ L̃(ω) y_i(ω) dω exactly (to float64 round-off). L̃ = Σ img[y,x]
      hat_y(θ) hat_x(φ') is separable in the env map's own polar frame, so the φ' integrals of a
      periodic hat against cos/sin(mφ') are closed form (Δφ·sinc²(mΔφ/2)·cos/sin(mφ'_x), the
      Fourier transform of a triangle) and the θ integrals ∫ hat_y(θ) y_{l|m|}(θ, 0) sin θ dθ are
      taken with Gauss–Legendre per row interval (n+8 nodes; the integrand is analytic there).
      The result is computed in that polar frame and rotated to the requested frame exactly with
      `sh_rotation` (Ivanic–Ruedenberg). Cost O(H·W·n + H·n² + n³).
    - "hat": texel directions with their hat-function solid angles (`sampling.latlong_grid`), a
      product trapezoid rule: exact for the constant band, O(Δθ² l²) relative error otherwise.
    - "supersample": midpoint rule on `supersample`² sub-samples per cell of L̃ (cross-check).

    Args:
        image: (H, W, C) tensor, or an EnvMap-like object with `.data (H, W, C)` and
            `.to_world (3, 3)`; with the latter the coefficients are in WORLD space (the texel
            direction d_local maps to to_world @ d_local). A bare tensor gives coefficients in
            the env map's local frame.
        order: n ≥ 1.
        method: "exact", "hat" or "supersample".
        supersample: k ≥ 1 sub-samples per cell side for method="supersample".
    Returns:
        (order², C) coefficients, dtype/device of the image.
    """
    to_world = None
    if hasattr(image, "data") and not isinstance(image, Tensor):
        to_world = getattr(image, "to_world", None)
        image = image.data
    image = torch.as_tensor(image)
    if image.ndim != 3 or image.shape[0] < 2 or image.shape[1] < 1:
        raise ValueError(f"image must have shape (H>=2, W, C), got {tuple(image.shape)}")
    if not image.is_floating_point():
        image = image.float()
    if not isinstance(order, int) or order < 1:
        raise ValueError(f"order must be an int >= 1, got {order!r}")
    H, W, C = image.shape
    R = None
    if to_world is not None:
        R = torch.as_tensor(to_world, dtype=image.dtype, device=image.device)
        if R.shape != (3, 3):
            raise ValueError(f"to_world must be (3, 3), got {tuple(R.shape)}")
    if method == "exact":
        return _project_latlong_exact(image, order, R)
    if method == "hat":
        dirs, w = latlong_grid(H, W, dtype=image.dtype, device=image.device)
        if R is not None:
            dirs = dirs @ R.T
        return project(image.reshape(H * W, C), dirs, w, order)
    if method == "supersample":
        if not isinstance(supersample, int) or supersample < 1:
            raise ValueError(f"supersample must be an int >= 1, got {supersample!r}")
        return _project_latlong_supersampled(image, order, supersample, R)
    raise ValueError(f"method must be 'exact', 'hat' or 'supersample', got {method!r}")


def _latlong_theta_weights(H: int, order: int, device) -> Tensor:
    """T[y, i] = ∫ hat_y(θ) y_{l,|m|}(θ, φ=0) sin θ dθ (float64) for every flat index i → (H, n²).

    hat_y is the piecewise-linear row hat on θ_y = πy/(H−1); Gauss–Legendre with n+8 nodes per
    interval [θ_j, θ_{j+1}] (analytic integrand, so the rule is exact to round-off). Cached per
    (H, order, device): a map swap reprojects with the same weights; read-only.
    """
    return _latlong_theta_weights_cached(int(H), int(order), None if device is None else torch.device(device))


@functools.lru_cache(maxsize=16)
def _latlong_theta_weights_cached(H: int, order: int, device) -> Tensor:
    n = order
    dl = math.pi / (H - 1)
    t, wt = np.polynomial.legendre.leggauss(n + 8)
    t = torch.as_tensor(t, dtype=torch.float64, device=device)
    wt = torch.as_tensor(wt, dtype=torch.float64, device=device)
    j = torch.arange(H - 1, dtype=torch.float64, device=device)[:, None]
    frac = 0.5 * (t + 1.0)                                   # (K,) position inside an interval
    th = (j + frac) * dl                                     # (H−1, K)
    d = torch.stack([torch.sin(th), torch.zeros_like(th), torch.cos(th)], dim=-1)
    idx = [l * (l + 1) + abs(m) for l in range(n) for m in range(-l, l + 1)]
    Y0 = sh_eval(d, n)[..., idx]                             # (H−1, K, n²): y_{l,|m|}(θ, 0)
    base = (wt * 0.5 * dl)[None, :, None] * torch.sin(th)[..., None] * Y0
    rising = torch.einsum("k,jki->ji", frac, base)            # weight of row j+1 on interval j
    falling = torch.einsum("k,jki->ji", 1.0 - frac, base)     # weight of row j on interval j
    T = torch.zeros(H, n * n, dtype=torch.float64, device=device)
    T[1:] += rising
    T[:-1] += falling
    return T


def _project_latlong_exact(image: Tensor, order: int, R: Tensor | None) -> Tensor:
    """Exact SH projection of the bilinear lat-long interpolant (see `project_latlong`)."""
    H, W, C = image.shape
    dev = image.device
    n = order
    img = image.to(torch.float64)
    dph = 2.0 * math.pi / W
    phi = (torch.arange(W, dtype=torch.float64, device=dev) + 0.5) * dph        # φ'_x
    m = torch.arange(n, dtype=torch.float64, device=dev)
    half = 0.5 * m * dph
    sinc2 = torch.where(m == 0, torch.ones_like(m), (torch.sin(half) / half.clamp_min(1e-300)) ** 2)
    # ∫ hat_x(φ') cos(mφ') dφ' = Δφ sinc²(mΔφ/2) cos(mφ'_x) (and sin); ψ = −φ' flips the sine.
    cos_m = torch.cos(phi[:, None] * m[None, :]) * (dph * sinc2)                 # (W, n)
    sin_m = torch.sin(phi[:, None] * m[None, :]) * (dph * sinc2)
    Fc = torch.einsum("hwc,wm->hmc", img, cos_m)                                 # (H, n, C)
    Fs = -torch.einsum("hwc,wm->hmc", img, sin_m)
    ms = [mm for l in range(n) for mm in range(-l, l + 1)]
    am = torch.tensor([abs(mm) for mm in ms], device=dev)
    neg = torch.tensor([mm < 0 for mm in ms], device=dev)
    F = torch.where(neg[None, :, None], Fs[:, am], Fc[:, am])                    # (H, n², C)
    T = _latlong_theta_weights(H, n, dev)                                        # (H, n²)
    c = torch.einsum("hi,hic->ic", T, F)                                         # polar frame
    Q = torch.tensor(_LATLONG_Q, dtype=torch.float64, device=dev)
    Rw = Q.T if R is None else R.to(torch.float64) @ Q.T
    return rotate_coeffs(c, Rw).to(image.dtype)


# Qᵀ: the lat-long map's polar frame → its own frame (`project_latlong_polar`).
_LATLONG_QT = torch.tensor(_LATLONG_Q, dtype=torch.float64).T


@functools.lru_cache(maxsize=16)
def _latlong_polar_factors(H: int, W: int, order: int, device) -> tuple[Tensor, Tensor, Tensor]:
    """The map-independent factors of `project_latlong_polar` (float64, read-only): B (W, 2n) the
    columns' φ'-integrals [cos | −sin](mφ'_x)·Δφ sinc²(mΔφ/2), k (n²,) the column of B that each flat
    index i = (l, m) takes (|m| for m ≥ 0, n + |m| for m < 0) and T (H, n²) the rows' θ-weights."""
    n = order
    dph = 2.0 * math.pi / W
    phi = (torch.arange(W, dtype=torch.float64, device=device) + 0.5) * dph
    m = torch.arange(n, dtype=torch.float64, device=device)
    half = 0.5 * m * dph
    sinc2 = torch.where(m == 0, torch.ones_like(m), (torch.sin(half) / half.clamp_min(1e-300)) ** 2)
    B = torch.cat([torch.cos(phi[:, None] * m[None, :]), -torch.sin(phi[:, None] * m[None, :])], 1) * (dph * sinc2.repeat(2))
    k = torch.tensor([abs(mm) + (n if mm < 0 else 0) for l in range(n) for mm in range(-l, l + 1)], device=device)
    return B, k, _latlong_theta_weights(H, n, device)


def project_latlong_polar(image: Tensor, order: int) -> Tensor:
    """`sh.project_latlong`'s exact projection of the (H, W, C) map in the map's POLAR frame, before
    its final rotation: ``sh.project_latlong(image, order)`` = ``rotate_coeffs(c, Qᵀ)`` and, for an
    env map with ``to_world`` R, ``rotate_coeffs(c, R Qᵀ)`` (Q = ``sh._LATLONG_Q``; float64
    round-off). `SHPRT.lighting` / `ZHShadow._lighting` rotate the coefficients anyway (`rotate_sampled`), so one rotation
    by the product replaces two. → (n², C) float64.

    The same integrals as ``sh._project_latlong_exact`` (Fourier of the column hats, Gauss–Legendre
    row weights) with the column sums as ONE float64 GEMM of the (H·C, W) channel-major texels
    against the (W, 2n) cos/sin factors (`_latlong_polar_factors`, cached per size) instead of two
    einsums over (H, W, C): creature bench map 256 × 512, 1 thread, same process: the einsums
    2 × 1.17 ms, the whole of `sh.project_latlong` 4.8 ms (1.2 of it the band-recursion rotation).
    Used by SH PRT's and zh_shadow's lighting (E frames: a new map)."""
    H, W, C = image.shape
    B, k, T = _latlong_polar_factors(int(H), int(W), int(order), image.device)
    # (H·C, W) float64 channel-major texels in ONE strided copy-convert (`.to` of the permuted view
    # kept its strides, so the reshape copied a second time: 256 × 512 × 3, 1 thread, 0.75 → 0.50 ms)
    A = torch.empty(H, C, W, dtype=torch.float64, device=image.device)
    A.copy_(image.permute(0, 2, 1))
    F = (A.view(H * C, W) @ B).view(H, C, 2 * order).index_select(2, k)           # (H, C, n²)
    return torch.einsum("hi,hci->ic", T, F)


@functools.lru_cache(maxsize=None)
def _rotation_samples(order: int, device: str = "cpu") -> tuple[Tensor, Tensor]:
    """D (K, 3) float64 unit directions (a Fibonacci sphere of K = 4n² points) and P (n², K) the
    pseudo-inverse of their SH matrix Y(D) (K, n²) — full column rank, so P Y(D) = I (`rotate_sampled`);
    built on the CPU (the same numbers on every device), kept per device."""
    if device != "cpu":
        return tuple(t.to(device) for t in _rotation_samples(order))
    K = 4 * order * order
    k = torch.arange(K, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * k / K
    phi = math.pi * (3.0 - math.sqrt(5.0)) * k
    r = (1.0 - z * z).sqrt()
    D = torch.stack([r * phi.cos(), r * phi.sin(), z], -1)
    return D, torch.linalg.pinv(sh_eval(D, order))


def _rotate_sampled_impl(c: Tensor, R: Tensor, D: Tensor, P: Tensor) -> Tensor:
    X = D @ R                                                       # rows (Rᵀ d_j)ᵀ
    Y = torch.stack(sh_terms(X[:, 0], X[:, 1], X[:, 2], math.isqrt(P.shape[0])), -1)   # (K, n²)
    return P @ (Y @ c)


_rotate_sampled = fused(_rotate_sampled_impl)


def rotate_sampled(c: Tensor, R: Tensor) -> Tensor:
    """`sh_rotation.rotate_coeffs(c, R)` for one rotation R (3, 3) and c (n², C) float64: the
    coefficients of f'(d) = f(Rᵀd) from its values at K = 4n² fixed directions d_j, c' = P Y(Rᵀ D) c
    with P = Y(D)⁺ (`_rotation_samples`). Exact up to float64 round-off: f' is band-limited to the
    same order (rotations preserve each band), so it lies in the span of Y's columns and the
    least-squares fit P reproduces it (the same coefficients as Ivanic–Ruedenberg; Sloan 2002 §7
    rotates the lighting SH the same way; SH PRT's and zh_shadow's lighting). One compiled call (two small GEMMs and the n² polynomials)
    instead of the band recursion's ~120 eager ops on (2l+1)² blocks: order 5, 1 thread, same
    process: 0.44 ms against 1.48 ms (3.4×; equal to 7e-15), one per lighting frame."""
    D, P = _rotation_samples(math.isqrt(c.shape[0]), str(c.device))
    return _rotate_sampled(c, R, D, P)


def _project_latlong_supersampled(image: Tensor, order: int, k: int, R: Tensor | None) -> Tensor:
    """∫ bilinear(image)(ω) y(ω) dω with k×k midpoint samples per (θ, φ) cell (solid-angle weighted).

    Cells are between consecutive rows (θ_y = πy/(H−1)) and consecutive column centres
    (u_x = (x+0.5)/W, periodic). Sub-sample weight = sinθ dθ dφ (midpoint rule in θ and φ).
    """
    H, W, C = image.shape
    dt, dev = image.dtype, image.device
    dth = math.pi / (H - 1)
    dph = 2.0 * math.pi / W
    f = (torch.arange(k, dtype=dt, device=dev) + 0.5) / k  # fractional positions in a cell
    out = torch.zeros(order * order, C, dtype=dt, device=dev)
    # Columns: u = (x + 0.5 + fx)/W between column x and x+1 (wrapping).
    ucol = (torch.arange(W, dtype=dt, device=dev)[:, None] + 0.5 + f[None, :]).reshape(-1) / W
    phi = 2.0 * math.pi * ucol                      # (W k)
    x0 = torch.arange(W, device=dev).repeat_interleave(k)
    x1 = (x0 + 1) % W
    fx = f.repeat(W)
    for y in range(H - 1):
        th = (y + f) * dth                           # (k)
        wth = torch.sin(th) * dth / k                # midpoint weights in θ
        st, ct = torch.sin(th), torch.cos(th)
        # d = (sinθ sin φ', cosθ, −sinθ cos φ') for u = φ'/(2π) (Mitsuba envmap).
        d = torch.stack([st[:, None] * torch.sin(phi)[None, :],
                         ct[:, None].expand(k, phi.shape[0]),
                         -st[:, None] * torch.cos(phi)[None, :]], dim=-1).reshape(-1, 3)
        w = (wth[:, None] * (dph / k)).expand(k, phi.shape[0]).reshape(-1)
        top = image[y][x0] * (1 - fx)[:, None] + image[y][x1] * fx[:, None]      # (W k, C)
        bot = image[y + 1][x0] * (1 - fx)[:, None] + image[y + 1][x1] * fx[:, None]
        vals = top[None] * (1 - f)[:, None, None] + bot[None] * f[:, None, None]  # (k, W k, C)
        if R is not None:
            d = d @ R.T
        out = out + project(vals.reshape(-1, C), d, w, order)
    return out
