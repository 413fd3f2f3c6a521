"""Zonal harmonics (ZH): axially symmetric functions, their rotation into SH and SH convolution.

Conventions (same basis as `methods/core/sh.py`: real orthonormal SH, index l(l+1)+m, no
Condon–Shortley phase):
- A ZH expansion of order n is k = (k_0 … k_{n−1}) with g(d) = Σ_l k_l y_{l,0}(a·d) around a unit
  axis a, y_{l,0}(t) = √((2l+1)/(4π)) P_l(t). k_l are the ZH *coefficients* ("kernel").
- Λ_l = √(4π/(2l+1)).
- Rotating a ZH to axis a (Sloan et al. 2005 "Local, deformable PRT" §4; Nowrouzezahrai et al. 2008
  eq. 1): f_lm = Λ_l k_l y_lm(a).
- Convolution with a zonal kernel (Funk–Hecke theorem; Ramamoorthi & Hanrahan 2001 §2):
  (k ⋆ f)_lm = Λ_l k_l f_lm. The per-band numbers Λ_l k_l are the *convolution factors*
  (`*_factors`); `*_kernel` functions return the ZH coefficients k_l.
- Clamped cosine max(0, cos θ): factors Â_l = Λ_l k_l = 2π ∫₀¹ t P_l(t) dt, i.e.
  Ramamoorthi–Hanrahan 2001 ("An efficient representation for irradiance environment maps",
  §2) Â_0 = π, Â_1 = 2π/3, Â_2 = π/4, Â_3 = 0, Â_4 = −π/24, Â_5 = 0, Â_6 = π/64, so that the
  irradiance E_lm = Â_l L_lm.
- Normalised Phong lobe (s+1)/(2π) max(0, t)^s (Mahajan et al. 2008 eq. 5, method card
  /work/shared/methods/inout.md): factors F_l = Λ_l f_l = (s+1) ∫₀¹ t^s P_l(t) dt, exactly
  F_0 = 1, F_1 = (s+1)/(s+2), F_l = F_{l−2} (s−l+2)/(s+l+1) — the recurrence form of the
  Ramamoorthi–Hanrahan closed forms (odd l: (s+1)(s−1)…(s−l+2)/((s+2)(s+4)…(s+l+1)); even l:
  s(s−2)…(s−l+2)/((s+3)(s+5)…(s+l+1))); a product of ratios, stable for large s and l.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np
import torch
from torch import Tensor

from methods.core.sh import sh_eval


def _check_order(order: int) -> None:
    if not isinstance(order, int) or order < 1:
        raise ValueError(f"order must be an int >= 1, got {order!r}")


def band_norms(order: int, *, dtype=torch.float64, device=None) -> Tensor:
    """Λ_l = √(4π/(2l+1)), l = 0..n−1 → (n,)."""
    _check_order(order)
    l = torch.arange(order, dtype=torch.float64, device=device)
    return torch.sqrt(4.0 * math.pi / (2.0 * l + 1.0)).to(dtype)


def expand_bands(per_band: Tensor) -> Tensor:
    """Repeat a per-band vector (..., n) 2l+1 times along the last dim → (..., n²)."""
    n = per_band.shape[-1]
    reps = torch.arange(n, device=per_band.device) * 2 + 1
    return torch.repeat_interleave(per_band, reps, dim=-1)


def legendre(t: Tensor, order: int) -> Tensor:
    """Legendre polynomials P_0..P_{n−1} at t (...) → (..., n) (Bonnet recurrence)."""
    _check_order(order)
    out = [torch.ones_like(t)]
    if order > 1:
        out.append(t)
    for l in range(2, order):
        out.append(((2 * l - 1) * t * out[-1] - (l - 1) * out[-2]) / l)
    return torch.stack(out, dim=-1)


def zh_basis(t: Tensor, order: int) -> Tensor:
    """y_{l,0} as a function of t = cos θ: √((2l+1)/(4π)) P_l(t) → (..., n)."""
    l = torch.arange(order, dtype=t.dtype, device=t.device)
    return legendre(t, order) * torch.sqrt((2.0 * l + 1.0) / (4.0 * math.pi))


def zh_eval(k: Tensor, axis: Tensor, dirs: Tensor) -> Tensor:
    """Evaluate g(d) = Σ_l k_l y_{l,0}(a·d).

    Args:
        k: (..., n) ZH coefficients; axis: (..., 3) unit axes; dirs: (..., 3) directions
            (all broadcast together).
    Returns:
        (...) values.
    """
    t = (axis * dirs).sum(-1)
    return (zh_basis(t, k.shape[-1]) * k).sum(-1)


def zh_to_sh(k: Tensor, axis: Tensor) -> Tensor:
    """Rotate ZH lobes to axes: f_lm = Λ_l k_l y_lm(a) (Nowrouzezahrai 2008 eq. 1, Sloan 2005).

    Args:
        k: (..., n) ZH coefficients (e.g. (V, L, n) for V points × L lobes).
        axis: (..., 3) unit axes, broadcastable against k's batch dims (e.g. (V, L, 3)).
    Returns:
        (..., n²) SH coefficients per lobe; sum over the lobe dim for a sum of lobes.
    """
    if axis.shape[-1] != 3:
        raise ValueError(f"axis must have shape (..., 3), got {tuple(axis.shape)}")
    n = k.shape[-1]
    _check_order(n)
    Y = sh_eval(axis.to(k.dtype), n)                                     # (..., n²)
    lam = band_norms(n, dtype=k.dtype, device=k.device)
    return Y * expand_bands(k * lam)


def zh_lobes_to_sh(k: Tensor, axis: Tensor) -> Tensor:
    """Sum of ZH lobes as one SH vector: v_lm = Λ_l Σ_x k^x_l y_lm(s^x) (Nowrouzezahrai 2008 eq. 1).

    Args:
        k: (..., L, n) ZH coefficients of L lobes; axis: (..., L, 3) unit lobe axes.
    Returns:
        (..., n²).
    """
    if k.ndim < 2 or axis.ndim < 2:
        raise ValueError(f"k must be (..., L, n) and axis (..., L, 3), got {tuple(k.shape)}, {tuple(axis.shape)}")
    return zh_to_sh(k, axis).sum(-2)


def convolve(coeffs: Tensor, kernel: Tensor, *, dim: int = 0) -> Tensor:
    """Convolve an SH expansion with a zonal kernel given by ZH coefficients k_l (Funk–Hecke).

    (k ⋆ f)_lm = Λ_l k_l f_lm.

    Args:
        coeffs: SH coefficients with n² entries along `dim` (default 0: (n², C) as from `project`).
        kernel: (n,) ZH coefficients (at least n entries; extra are ignored).
    Returns:
        same shape as `coeffs`.
    """
    K = coeffs.shape[dim]
    n = math.isqrt(K)
    if n * n != K or n == 0:
        raise ValueError(f"coeffs must have n² entries along dim {dim}, got {K}")
    if kernel.ndim != 1 or kernel.shape[0] < n:
        raise ValueError(f"kernel must have shape (>= {n},), got {tuple(kernel.shape)}")
    lam = band_norms(n, dtype=coeffs.dtype, device=coeffs.device)
    return convolve_factors(coeffs, kernel[:n].to(coeffs) * lam, dim=dim)


def convolve_factors(coeffs: Tensor, factors: Tensor, *, dim: int = 0) -> Tensor:
    """Multiply band l of `coeffs` (n² entries along `dim`) by factors[l] (n,)."""
    K = coeffs.shape[dim]
    n = math.isqrt(K)
    if n * n != K or n == 0:
        raise ValueError(f"coeffs must have n² entries along dim {dim}, got {K}")
    if factors.ndim != 1 or factors.shape[0] < n:
        raise ValueError(f"factors must have shape (>= {n},), got {tuple(factors.shape)}")
    f = expand_bands(factors[:n].to(coeffs))
    shape = [1] * coeffs.ndim
    shape[dim] = K
    return coeffs * f.reshape(shape)


def clamped_cosine_factors(order: int, *, dtype=torch.float64, device=None) -> Tensor:
    """Ramamoorthi–Hanrahan Â_l = 2π ∫₀¹ t P_l(t) dt for max(0, cos θ), l < n → (n,).

    Â_0 = π, Â_1 = 2π/3, odd l > 1: 0, even l ≥ 2:
    Â_l = 2π (−1)^{l/2−1} / ((l+2)(l−1)) · l!/(2^l (l/2)!²) (R–H 2001 §2); the last factor is
    accumulated as a product of ratios (no factorials).
    """
    _check_order(order)
    out = np.zeros(order)
    out[0] = math.pi
    if order > 1:
        out[1] = 2.0 * math.pi / 3.0
    c = 1.0  # C(l, l/2)/2^l for l = 0
    for l in range(2, order, 2):
        c *= (l - 1) / l   # C(l, l/2)/2^l = C(l−2, l/2−1)/2^{l−2} · (l−1)/l
        out[l] = 2.0 * math.pi * (-1) ** (l // 2 - 1) / ((l + 2) * (l - 1)) * c
    return torch.as_tensor(out, dtype=dtype, device=device)


def clamped_cosine_kernel(order: int, *, dtype=torch.float64, device=None) -> Tensor:
    """ZH coefficients k_l = Â_l/Λ_l of max(0, cos θ) → (n,)."""
    return (clamped_cosine_factors(order) / band_norms(order)).to(dtype=dtype, device=device)


def phong_factors(s: float, order: int, *, dtype=torch.float64, device=None) -> Tensor:
    """Exact Phong convolution factors F_l = Λ_l f_l = (s+1) ∫₀¹ t^s P_l(t) dt → (n,).

    For the normalised lobe (s+1)/(2π) max(0, t)^s (Mahajan 2008 eq. 5; R–H 2001 closed form,
    see the module docstring). Computed in float64 by F_l = F_{l−2}(s−l+2)/(s+l+1); exact zeros
    for even s and even l > s (and odd/odd) come out exactly. Requires s ≥ 0.
    """
    _check_order(order)
    s = float(s)
    if not math.isfinite(s) or s < 0:
        raise ValueError(f"Phong exponent s must be finite and >= 0, got {s}")
    out = np.zeros(order)
    out[0] = 1.0
    if order > 1:
        out[1] = (s + 1.0) / (s + 2.0)
    for l in range(2, order):
        out[l] = out[l - 2] * (s - l + 2.0) / (s + l + 1.0)
    return torch.as_tensor(out, dtype=dtype, device=device)


def phong_kernel(s: float, order: int, *, dtype=torch.float64, device=None) -> Tensor:
    """ZH coefficients f_l = F_l/Λ_l of the normalised Phong lobe (s+1)/(2π) max(0, t)^s → (n,)."""
    return (phong_factors(s, order) / band_norms(order)).to(dtype=dtype, device=device)


WINDOWS = ("none", "hanning", "lanczos")


def window_factors(kind: str, order: int, width: float | None = None, *, dtype=torch.float64, device=None) -> Tensor:
    """Per-band SH windowing ("σ-factors") that damp Gibbs ringing (Sloan 2008, "Stupid Spherical
    Harmonics (SH) Tricks", §"Windowing"): multiply band l of an SH expansion by σ_l (a zonal
    convolution, so it commutes with rotation; apply with `convolve_factors`).

        none:     σ_l = 1
        hanning:  σ_l = (1 + cos(π l / w)) / 2   for l ≤ w, else 0
        lanczos:  σ_l = sin(π l / w) / (π l / w)  (σ_0 = 1), for l ≤ w, else 0

    Args:
        kind: one of `WINDOWS`; order: n ≥ 1 (bands 0..n−1).
        width: window width w > 0 (default n: the band n, one past the last kept, would get σ = 0
            for Hanning and Lanczos); larger w = weaker damping.
    Returns:
        (n,) factors, σ_0 = 1 (the mean is kept).
    """
    _check_order(order)
    if kind not in WINDOWS:
        raise ValueError(f"window kind must be one of {WINDOWS}, got {kind!r}")
    w = float(order if width is None else width)
    if not math.isfinite(w) or w <= 0:
        raise ValueError(f"window width must be a finite number > 0, got {width!r}")
    l = torch.arange(order, dtype=torch.float64)
    x = l / w
    if kind == "none":
        s = torch.ones(order, dtype=torch.float64)
    elif kind == "hanning":
        s = 0.5 * (1.0 + torch.cos(math.pi * x))
    else:
        px = math.pi * x
        s = torch.where(l == 0, torch.ones_like(x), torch.sin(px) / torch.where(l == 0, torch.ones_like(px), px))
    if kind != "none":
        s = torch.where(x <= 1.0, s, torch.zeros_like(s))
    return s.to(dtype=dtype, device=device)


def gauss_legendre(n: int, *, dtype=torch.float64, device=None) -> tuple[Tensor, Tensor]:
    """Gauss–Legendre nodes t (n,) in (−1, 1) (ascending) and weights (n,)."""
    if not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be an int >= 1, got {n!r}")
    t, w = np.polynomial.legendre.leggauss(n)
    return (torch.as_tensor(t, dtype=dtype, device=device),
            torch.as_tensor(w, dtype=dtype, device=device))


def zh_project(f: Callable[[Tensor], Tensor] | Tensor, order: int, *, n_quad: int | None = None
               ) -> Tensor:
    """ZH coefficients of an axially symmetric g(θ): k_l = 2π ∫_{−1}^{1} g(t) y_{l,0}(t) dt.

    1-D Gauss–Legendre quadrature in t = cos θ (exact for polynomial g of degree < 2Q − n + 1).

    Args:
        f: a callable t (Q,) float64 → (Q,) or (Q, C); or samples (Q,) / (Q, C) taken at the nodes
            of `gauss_legendre(Q)` (ascending t).
        order: n ≥ 1.
        n_quad: number of nodes Q for a callable (default max(4n, 64)).
    Returns:
        (n,) or (n, C) ZH coefficients (float64 for a callable, else the samples' dtype).
    """
    _check_order(order)
    if callable(f):
        Q = n_quad if n_quad is not None else max(4 * order, 64)
        t, w = gauss_legendre(Q)
        g = torch.as_tensor(f(t))
    else:
        g = torch.as_tensor(f)
        if not g.is_floating_point():
            g = g.double()
        Q = g.shape[0] if g.ndim >= 1 else 0
        if g.ndim not in (1, 2) or Q == 0:
            raise ValueError(f"samples must have shape (Q,) or (Q, C), got {tuple(g.shape)}")
        t, w = gauss_legendre(Q, dtype=g.dtype, device=g.device)
    if g.shape[0] != t.shape[0] or g.ndim not in (1, 2):
        raise ValueError(f"f must give shape ({t.shape[0]},) or ({t.shape[0]}, C), got {tuple(g.shape)}")
    B = zh_basis(t.to(g.dtype), order) * (2.0 * math.pi * w.to(g.dtype))[:, None]  # (Q, n)
    return B.transpose(0, 1) @ g


# -- how much of a Phong lobe order n keeps (the terms-vs-exponent rows of SH/ZH methods) ----------

PHONG_MAX_ORDER = 200  # orders searched (n² ≤ 40 000 terms: enough for s ≈ 10⁵ at 99 %)


def phong_lobe_energy(exponent: float) -> float:
    """∫ lobe² dω of the normalised Phong lobe (s+1)/(2π) max(0, cos)^s: (s+1)² / (2π (2s+1));
    by Parseval (the lobe is zonal) also Σ_l f_l² over all bands of `phong_kernel`."""
    s = float(exponent)
    return (s + 1.0) ** 2 / (2.0 * math.pi * (2.0 * s + 1.0))


def phong_energy_fraction(exponent: float, order: int) -> float:
    """Fraction of the Phong lobe's energy ∫ lobe² held by SH bands l < order."""
    k = phong_kernel(float(exponent), order)
    return float((k * k).sum()) / phong_lobe_energy(exponent)


def phong_order_needed(exponent: float, target: float = 0.99) -> int:
    """Smallest SH order n whose bands l < n hold ``target`` of the Phong lobe's energy."""
    s = float(exponent)
    if not math.isfinite(s) or s < 0:
        raise ValueError(f"exponent must be finite and >= 0, got {exponent!r}")
    if not 0 < target < 1:
        raise ValueError(f"target must be in (0, 1), got {target!r}")
    k = phong_kernel(s, PHONG_MAX_ORDER)
    cum = (k.double() ** 2).cumsum(0) / phong_lobe_energy(s)
    hit = (cum >= target).nonzero()
    if hit.numel() == 0:
        raise ValueError(f"exponent {s} needs more than order {PHONG_MAX_ORDER} for {target:.3%}")
    return int(hit[0, 0]) + 1
