"""Analysis of the in-out BRDF factorization (Mahajan, Tseng & Ramamoorthi 2008).

The BRDF, sampled on a grid of incident and outgoing directions, is a matrix
``M[o, i] = ρ(ω_i, ω_o)`` (rows: outgoing ω_o, columns: incident ω_i). Its SVD is the in-out
factorization ``ρ = Σ_k σ_k h_k(ω_o) g_k(ω_i)`` (Mahajan 2008 eq. 2). This module builds that
matrix, turns its singular values into those of the continuous operator (comparable with the
Phong F_l of eq. 9), counts the terms for a given energy fraction (Fig. 3A, 5, 7C) and implements
the paper's rules for choosing the number of terms K per material (eq. 10–14).

Grid (paper §3.2): directions sampled *uniformly in (cos θ, φ)* — n values of cos θ times n values
of φ at cell centres, so every cell has the same solid angle Δ and no quadrature weights are
needed. ``domain="sphere"``: cos θ ∈ [−1, 1], Δ = 4π/n²; ``domain="hemisphere"``: both ω_i and ω_o
restricted to the visible hemisphere cos θ ∈ [0, 1] (paper §3.4), Δ = 2π/n². The paper uses
n = 40 (its "40⁴" matrix is 1600 × 1600).

Scaling of the singular values (derivation). Let T be the integral operator
``(T f)(ω_o) = ∫ ρ(ω_i, ω_o) f(ω_i) dω_i`` with SVD ``ρ = Σ σ_k h_k(ω_o) g_k(ω_i)``, the h_k and g_k
orthonormal in L²(S²) (or L² of the hemisphere). On the equal-area grid, the vectors
``u_k[a] = √Δ h_k(ω_a)`` and ``v_k[b] = √Δ g_k(ω_b)`` are orthonormal up to the quadrature error
(``Σ_a Δ h_k(ω_a)² ≈ ∫ h_k² = 1``), and ``M[a, b] = Σ_k σ_k h_k(ω_a) g_k(ω_b) =
Σ_k (σ_k/Δ) u_k[a] v_k[b]``. So the matrix singular values are σ_k/Δ, and ``σ_k = Δ · svd(M)``.
With this scaling the full-sphere Phong singular values are F_l, F_0 = 1 (eq. 9), and
``Σ_k σ_k² ≈ ∫∫ ρ² dω_i dω_o`` (a closed form for Phong: 2(s+1)²/(2s+1)).
The 99 % term count is scale-free, so the scaling matters only for comparisons with F_l.

BRDF callables: ``brdf_fn(wi (..., 3), wo (..., 3)) -> (...)`` or ``(..., 3)`` (local frame,
z = normal, both directions pointing away from the surface — docs/ARCHITECTURE.md). A
``scenes.materials.Material`` may be passed directly (its ``eval`` is used). RGB outputs are
averaged over the three channels (as the paper does for measured data, §4 footnote).

Two idealised full-sphere lobes are defined here because the paper's full-sphere analysis (§3.1–3.3)
uses the lobe *without* the horizon cut, while the physical materials in ``scenes.materials``
(``Phong``, ``TorranceSparrow``) return 0 when either direction is below the horizon. The
hemisphere analysis (§3.4, §4) uses the materials themselves.
"""
from __future__ import annotations

import math
from functools import lru_cache
from typing import Any, Callable

import numpy as np
import torch
from torch import Tensor

from methods.core.frames import reflect
from methods.core.sampling import equal_area_hemisphere, equal_area_sphere
from methods.core.threads import torch_threads
from methods.core.zh import gauss_legendre, legendre, phong_factors

__all__ = [
    "DOMAINS", "ENERGY_FRACTION", "DECAY_THRESHOLD",
    "direction_grid", "cell_solid_angle", "phong_lobe_sphere", "torrance_sparrow_sphere",
    "brdf_matrix", "singular_values", "terms_for_energy", "band_multiplicity", "repeat_bands",
    "phong_F", "phong_F_approx", "phong_energy_sphere", "phong_terms_sphere_exact",
    "zonal_transform", "l_star", "half_angle_curve", "k_rule", "terms_needed",
    "phong_hemisphere_terms", "torrance_sparrow_hemisphere_terms",
]

DOMAINS = ("sphere", "hemisphere")
# Mahajan 2008 §3.3 / Fig. 3A: K is the number of terms that capture 99 % of the energy
# Σ_k σ_k² ("99 % accuracy").
ENERGY_FRACTION = 0.99
# Mahajan 2008 §3.3 (above eq. 12): "a common very conservative threshold is for the SH
# coefficients to decay so that F_l ≈ exp[−3]", giving l* ≈ √(6s) for Phong.
DECAY_THRESHOLD = math.exp(-3.0)
# Mahajan 2008 eq. 13: K ≈ 2.5 s for Phong on the hemisphere.
PHONG_HEMISPHERE_SLOPE = 2.5
# Mahajan 2008 §4: K ≈ (l*)²/4 for half-angle BRDFs.
HALF_ANGLE_DIVISOR = 4.0
# Resolution (n × n per direction) of the hemisphere SVD used for BRDF families without a rule.
FALLBACK_SVD_N = 24
# Resolution of the paper's matrix (§3.2: 40⁴).
PAPER_N = 40

_DOMAIN_AREA = {"sphere": 4.0 * math.pi, "hemisphere": 2.0 * math.pi}


def _check_domain(domain: str) -> None:
    if domain not in _DOMAIN_AREA:
        raise ValueError(f"domain must be one of {DOMAINS}, got {domain!r}")


def _check_n(n: int) -> None:
    if not isinstance(n, (int, np.integer)) or isinstance(n, bool) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")


# -- grid -------------------------------------------------------------------------------------


def direction_grid(n: int, *, domain: str = "sphere", dtype: torch.dtype = torch.float64,
                   device=None) -> Tensor:
    """(n·n, 3) unit directions, uniform in (cos θ, φ) at cell centres (Mahajan 2008 §3.2).

    ``methods.core.sampling.equal_area_sphere/hemisphere(n, n)``; every direction stands for a
    cell of solid angle ``cell_solid_angle(n, domain)``.
    """
    _check_n(n)
    _check_domain(domain)
    grid = equal_area_sphere if domain == "sphere" else equal_area_hemisphere
    d, _ = grid(int(n), int(n), dtype=dtype, device=device)
    return d


def cell_solid_angle(n: int, domain: str = "sphere") -> float:
    """Solid angle Δ of one grid cell: 4π/n² (sphere) or 2π/n² (hemisphere)."""
    _check_n(n)
    _check_domain(domain)
    return _DOMAIN_AREA[domain] / (n * n)


# -- idealised full-sphere lobes (no horizon) ------------------------------------------------


def phong_lobe_sphere(wi: Tensor, wo: Tensor, s: float) -> Tensor:
    """The paper's idealised Phong lobe on the whole sphere, (...) from wi, wo (..., 3).

    Mahajan 2008 eq. 5, ρ = (s+1)/(2π) max(0, R·ω_i)^s with R = reflect(ω_o) about n = +z, defined
    for *all* ω_i, ω_o on the sphere: §3.1 analyses the lobe over the full sphere, which is what
    makes eq. 9 (singular values F_l, singular vectors real SH) exact. ``scenes.materials.Phong``
    is the physical BRDF and is 0 below the horizon; use it for the hemisphere analysis.
    """
    if wi.shape[-1] != 3 or wo.shape[-1] != 3:
        raise ValueError(f"wi, wo must be (..., 3), got {tuple(wi.shape)}, {tuple(wo.shape)}")
    if s < 0:
        raise ValueError(f"Phong exponent s must be >= 0, got {s}")
    nrm = torch.zeros_like(wo)
    nrm[..., 2] = 1.0
    R = reflect(wo, nrm)
    c = torch.clamp((R * wi).sum(-1), min=0.0)
    return (s + 1.0) / (2.0 * math.pi) * c.pow(s)  # Mahajan 2008 eq. 5


def torrance_sparrow_sphere(wi: Tensor, wo: Tensor, sigma: float) -> Tensor:
    """The paper's simplified Torrance–Sparrow lobe on the whole sphere, (...) from (..., 3).

    Mahajan 2008 eq. 14, ρ = exp(−(acos(N·H)/σ)²)/(4πσ²), H = (ω_i+ω_o)/|ω_i+ω_o|, N = +z, with no
    horizon cut (``scenes.materials.TorranceSparrow`` is the physical BRDF, 0 below the horizon —
    use it on the hemisphere). H is undefined for ω_i = −ω_o (a set of measure zero, but antipodal
    cell centres do occur on an even grid); there N·H is taken as 0 (θ_h = π/2).
    """
    if wi.shape[-1] != 3 or wo.shape[-1] != 3:
        raise ValueError(f"wi, wo must be (..., 3), got {tuple(wi.shape)}, {tuple(wo.shape)}")
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    h = wi + wo
    norm = h.norm(dim=-1)
    cos_h = torch.where(norm > 1e-12, h[..., 2] / norm.clamp(min=1e-12), torch.zeros_like(norm))
    theta_h = torch.acos(cos_h.clamp(-1.0, 1.0))
    return torch.exp(-(theta_h / sigma) ** 2) / (4.0 * math.pi * sigma**2)  # Mahajan 2008 eq. 14


# -- the BRDF matrix and its SVD -------------------------------------------------------------


def _as_callable(brdf_fn: Any) -> Callable[[Tensor, Tensor], Tensor]:
    if hasattr(brdf_fn, "eval") and callable(brdf_fn.eval):
        return brdf_fn.eval
    if callable(brdf_fn):
        return brdf_fn
    raise ValueError(f"brdf_fn must be callable or a Material with .eval, got {type(brdf_fn)}")


def brdf_matrix(brdf_fn: Any, n: int, domain: str = "sphere", *,
                dtype: torch.dtype = torch.float64, device=None, chunk: int = 400) -> Tensor:
    """The BRDF matrix M (N, N), N = n², ``M[o, i] = ρ(ω_i, ω_o)`` (Mahajan 2008 eq. 2, §3.2).

    brdf_fn: ``f(wi (..., 3), wo (..., 3)) -> (...)`` or ``(..., 3)`` (RGB is averaged), or a
        ``Material`` (``.eval``). Both directions come from ``direction_grid(n, domain=domain)``.
    chunk: rows (outgoing directions) evaluated per call, to bound memory.
    Rows index ω_o (the h_k, left singular vectors), columns ω_i (the g_k).
    """
    f = _as_callable(brdf_fn)
    d = direction_grid(n, domain=domain, dtype=dtype, device=device)  # (N, 3)
    N = d.shape[0]
    if chunk < 1:
        raise ValueError(f"chunk must be >= 1, got {chunk}")
    M = torch.empty(N, N, dtype=dtype, device=d.device)
    for a in range(0, N, chunk):
        wo = d[a:a + chunk, None, :].expand(-1, N, 3)
        wi = d[None, :, :].expand(wo.shape[0], N, 3)
        v = f(wi, wo)
        if v.dim() == 3 and v.shape[-1] == 3:
            v = v.mean(-1)
        if v.shape != wo.shape[:2]:
            raise ValueError(f"brdf_fn returned shape {tuple(v.shape)}, expected {tuple(wo.shape[:2])}"
                             " or with a trailing RGB axis")
        M[a:a + chunk] = v.to(dtype)
    return M


def singular_values(M: Tensor, domain: str | None = None, *, method: str = "gram") -> Tensor:
    """Singular values of the continuous operator, (N,) float64, descending.

    M: (N, N) from ``brdf_matrix`` with N = n². Returns Δ·svd(M), Δ = area(domain)/N (see the
    module docstring for the derivation), so that full-sphere Phong gives F_l (Mahajan 2008 eq. 9).
    With ``domain=None`` the raw matrix singular values are returned.
    method: "gram" (default) — σ_k = √λ_k(MᵀM) with ``torch.linalg.eigvalsh`` in float64: 3–10×
        faster than an SVD on this machine; σ_k is accurate to ~1e-8·σ_1 absolute, far below what
        the energy fractions and the F_l comparisons resolve (the smallest σ_k, which do not
        matter here, lose their relative accuracy). "svd" — ``torch.linalg.svdvals`` (LAPACK gesdd).
    """
    if M.dim() != 2 or M.shape[0] != M.shape[1]:
        raise ValueError(f"M must be square (N, N), got {tuple(M.shape)}")
    M = M.to(torch.float64)
    if method not in ("svd", "gram"):
        raise ValueError(f"method must be 'gram' or 'svd', got {method!r}")
    with torch_threads(1):  # LAPACK rounds differently with other thread counts (methods.core.threads)
        if method == "svd":
            sv = torch.linalg.svdvals(M)
        else:
            lam = torch.linalg.eigvalsh(M.T @ M)  # ascending
            sv = torch.sqrt(torch.flip(lam, (0,)).clamp(min=0.0))
    if domain is None:
        return sv
    _check_domain(domain)
    return sv * (_DOMAIN_AREA[domain] / M.shape[0])


def terms_for_energy(sv: Tensor, frac: float = ENERGY_FRACTION) -> int:
    """Smallest K with Σ_{k≤K} σ_k² ≥ frac · Σ_k σ_k² (Mahajan 2008 Fig. 3A "99 % of the energy").

    sv: (N,) singular values (any scale; sorted here, descending).
    """
    if sv.dim() != 1 or sv.numel() == 0:
        raise ValueError(f"sv must be a non-empty 1-D tensor, got {tuple(sv.shape)}")
    if not 0.0 < frac <= 1.0:
        raise ValueError(f"frac must be in (0, 1], got {frac}")
    e = torch.sort(sv.to(torch.float64).abs(), descending=True).values ** 2
    c = torch.cumsum(e, 0)
    total = c[-1]
    if total <= 0:
        raise ValueError("all singular values are zero")
    k = int(torch.searchsorted(c, frac * total).item()) + 1
    return min(k, sv.numel())


def band_multiplicity(l: int | Tensor, domain: str = "sphere"):
    """Number of singular values per SH band l: 2l+1 on the sphere (eq. 9), l+1 on the hemisphere
    (Mahajan 2008 §3.4, Fig. 5)."""
    _check_domain(domain)
    return 2 * l + 1 if domain == "sphere" else l + 1


def repeat_bands(F: Tensor, domain: str = "sphere") -> Tensor:
    """F_l (L,) repeated band_multiplicity(l) times, sorted by |value| descending, (Σ mult,)."""
    if F.dim() != 1:
        raise ValueError(f"F must be (L,), got {tuple(F.shape)}")
    mult = band_multiplicity(torch.arange(F.numel(), device=F.device), domain)
    r = torch.repeat_interleave(F.abs(), mult)
    return torch.sort(r, descending=True).values


# -- Phong: exact F_l ------------------------------------------------------------------------


def phong_F(s: float, l_max: int) -> Tensor:
    """Exact full-sphere Phong singular values F_l, l = 0..l_max, (l_max+1,) float64.

    F_l = Λ_l f_l = (s+1) ∫₀¹ t^s P_l(t) dt (Mahajan 2008 eq. 9 with Ramamoorthi–Hanrahan 2001's
    closed form), F_0 = 1. The math lives once, in ``methods.core.zh.phong_factors``
    (= Λ_l · ``phong_kernel``).
    """
    if l_max < 0:
        raise ValueError(f"l_max must be >= 0, got {l_max}")
    return phong_factors(float(s), l_max + 1)


def phong_F_approx(s: float, l_max: int) -> Tensor:
    """Ramamoorthi–Hanrahan's approximation F_l ≈ exp(−l²/2s) (Mahajan 2008 eq. 11), (l_max+1,)."""
    if not s > 0:
        raise ValueError(f"s must be > 0, got {s}")
    l = torch.arange(l_max + 1, dtype=torch.float64)
    return torch.exp(-(l**2) / (2.0 * s))


def phong_energy_sphere(s: float) -> float:
    """∫∫ ρ² dω_i dω_o = Σ_l (2l+1) F_l² for the full-sphere Phong lobe: 2(s+1)²/(2s+1).

    (∫dω_o ∫dω_i ((s+1)/2π)² max(0, cos γ)^{2s} = 4π · (s+1)²/(4π²) · 2π/(2s+1).)
    """
    return 2.0 * (s + 1.0) ** 2 / (2.0 * s + 1.0)


def phong_terms_sphere_exact(s: float, frac: float = ENERGY_FRACTION) -> int:
    """K for ``frac`` of the energy of the continuous full-sphere Phong operator (no grid).

    Uses the exact F_l with multiplicity 2l+1 and the exact total energy ``phong_energy_sphere``:
    the n → ∞ limit of ``terms_for_energy(singular_values(brdf_matrix(phong_lobe_sphere, n)))``.
    """
    total = phong_energy_sphere(s)
    l_max = int(8 * math.sqrt(s + 1.0)) + 16
    F = phong_F(s, l_max)
    r = repeat_bands(F, "sphere")
    c = torch.cumsum(r**2, 0)
    if c[-1] < frac * total:
        raise ValueError(f"l_max={l_max} too small for s={s}")
    return int(torch.searchsorted(c, frac * total).item()) + 1


# -- frequency content l* of a 1-D curve (§3.3, §4, Fig. 7) ----------------------------------


@lru_cache(maxsize=8)
def _gauss_legendre(n_quad: int) -> tuple[Tensor, Tensor]:
    return gauss_legendre(n_quad)  # cached: numpy's leggauss costs seconds for n ~ 2000


def zonal_transform(curve: Callable[[Tensor], Tensor], l_max: int, *, n_quad: int = 512) -> Tensor:
    """F_l = Λ_l f_l = 2π ∫_{-1}^{1} f(acos t) P_l(t) dt of a zonal function, (l_max+1,) float64.

    curve: θ (M,) float64 in [0, π] → f(θ) (M,); return 0 where the curve is not defined
    (e.g. θ_h > π/2). This is the SH transform of Mahajan 2008 §4 ("we find l* by a spherical
    harmonic transform"); for the Phong curve (s+1)/(2π) max(0, cos θ)^s it gives eq. 9's F_l.
    Gauss–Legendre quadrature in t = cos θ with n_quad nodes (``methods.core.zh`` nodes and
    Legendre polynomials; the same sum as ``zh_project`` times Λ_l).
    """
    if l_max < 0:
        raise ValueError(f"l_max must be >= 0, got {l_max}")
    t, w = _gauss_legendre(int(n_quad))
    theta = torch.acos(t.clamp(-1.0, 1.0))
    f = torch.as_tensor(curve(theta), dtype=torch.float64).reshape(-1)
    if f.shape != theta.shape:
        raise ValueError(f"curve returned {tuple(f.shape)}, expected {tuple(theta.shape)}")
    P = legendre(t, l_max + 1)  # (Q, L)
    return 2.0 * math.pi * (w * f) @ P  # F_l = Λ_l f_l (Mahajan 2008 eq. 9)


def l_star(curve: Callable[[Tensor], Tensor], *, criterion: str = "decay",
           threshold: float | None = None, l_max: int = 160) -> float:
    """Frequency content l* of a 1-D lobe (Mahajan 2008 §3.3 and §4 / Fig. 7).

    curve: θ (M,) → f(θ) (M,), see ``zonal_transform``; for a half-angle BRDF θ = θ_h
    (``half_angle_curve``), for Phong θ = γ (angle to the reflected direction).
    criterion:
      "decay" (the paper's, §3.3 above eq. 12): the band at which the normalised coefficients
          F_l/F_0 first fall to ``threshold`` (default e⁻³) — gives l* ≈ √(6s) for Phong. Returned
          as a real number: log F_l is interpolated linearly between the two bracketing bands.
      "energy": the smallest L with Σ_{l≤L} (2l+1) F_l² ≥ threshold (default 0.99) of the total
          (an integer, returned as float).
    """
    F = zonal_transform(curve, l_max)
    if not F[0] > 0:
        raise ValueError("curve has no positive mean (F_0 <= 0)")
    F = F / F[0]
    if criterion == "decay":
        thr = DECAY_THRESHOLD if threshold is None else threshold
        below = torch.nonzero(F.abs() <= thr)
        if below.numel() == 0:
            raise ValueError(f"F_l does not decay to {thr:g} by l_max={l_max}")
        l1 = int(below[0].item())
        if l1 == 0:
            return 0.0
        f0, f1 = math.log(abs(F[l1 - 1].item())), math.log(max(abs(F[l1].item()), 1e-300))
        lt = math.log(thr)
        return (l1 - 1) + (f0 - lt) / (f0 - f1) if f0 != f1 else float(l1)
    if criterion == "energy":
        thr = ENERGY_FRACTION if threshold is None else threshold
        e = torch.cumsum((2 * torch.arange(F.numel(), dtype=torch.float64) + 1) * F**2, 0)
        if e[-1] - e[-2] > 1e-6 * e[-1]:
            raise ValueError(f"F_l has not converged by l_max={l_max}")
        return float(torch.searchsorted(e, thr * e[-1]).item())
    raise ValueError(f"criterion must be 'decay' or 'energy', got {criterion!r}")


def half_angle_curve(brdf_fn: Any) -> Callable[[Tensor], Tensor]:
    """The 1-D half-angle curve θ_h ↦ ρ of a BRDF, at θ_d = 0 (ω_i = ω_o = H), 0 for θ_h > π/2.

    Mahajan 2008 §4 / Fig. 7A–B averages measured data over θ_d; for eq. 14 Torrance–Sparrow and
    Blinn–Phong, which depend on θ_h only, the θ_d = 0 slice is the whole curve.
    """
    f = _as_callable(brdf_fn)

    def curve(theta: Tensor) -> Tensor:
        th = theta.clamp(0.0, math.pi / 2)
        h = torch.stack([torch.sin(th), torch.zeros_like(th), torch.cos(th)], -1)
        v = f(h, h)
        if v.dim() == 2 and v.shape[-1] == 3:
            v = v.mean(-1)
        return torch.where(theta <= math.pi / 2, v.to(theta.dtype), torch.zeros_like(theta))

    return curve


# -- number of terms per material -------------------------------------------------------------


@lru_cache(maxsize=64)
def phong_hemisphere_terms(s: float, n: int = PAPER_N, frac: float = ENERGY_FRACTION) -> int:
    """Measured K(frac) of the physical Phong specular lobe (kd=0, ks=1) on the hemisphere, n×n."""
    from scenes.materials import Phong  # noqa: PLC0415

    M = brdf_matrix(Phong(kd=0.0, ks=1.0, s=float(s)), n, "hemisphere")
    return terms_for_energy(singular_values(M, "hemisphere"), frac)


@lru_cache(maxsize=64)
def torrance_sparrow_hemisphere_terms(sigma: float, n: int = PAPER_N,
                                      frac: float = ENERGY_FRACTION) -> int:
    """Measured K(frac) of eq. 14 Torrance–Sparrow (kd=0, ks=1) on the hemisphere, n×n (Fig. 7C).

    Not converged in n: a half-angle lobe narrows without bound towards grazing exitant angles
    (for ω_o at elevation α, rotating ω_i about the normal away from R moves H by ≈ ε cos α/(2 sin α),
    so the lobe's angular width there is ≈ 2σ sin α → 0), and a finer grid resolves more of that
    high-frequency sliver. Measured for σ = 0.2: K = 64 (n = 40, the paper's grid), 79 (60),
    85 (80); σ = 0.4: 23, 22, 21. Phong (a function of R·ω_i) has no such region (s = 30: 75 at
    n = 40 and n = 80).
    """
    from scenes.materials import TorranceSparrow  # noqa: PLC0415

    M = brdf_matrix(TorranceSparrow(kd=0.0, ks=1.0, sigma=float(sigma)), n, "hemisphere")
    return terms_for_energy(singular_values(M, "hemisphere"), frac)


def _ks_zero(material: Any) -> bool:
    ks = getattr(material, "ks", None)
    if ks is None:
        return False
    return all(float(c) == 0.0 for c in np.atleast_1d(np.asarray(ks, dtype=float)))


def k_rule(material: Any, *, frac: float = ENERGY_FRACTION, n_fallback: int = FALLBACK_SVD_N) -> int:
    """Number of in-out terms K for a material (Mahajan 2008 §3.4 eq. 13, §4), at least 1.

    - Lambert (or any material with ks = 0): 1 (the BRDF is a constant: rank one).
    - Phong: ⌈2.5 s⌉ (eq. 13, hemisphere); the diffuse part adds no term (a constant is the
      lobe's leading mode already, up to the mixing).
    - Half-angle BRDFs (Blinn–Phong, Torrance–Sparrow): ⌈(l*)²/4⌉ (§4), l* from the SH transform of
      the half-angle curve with the paper's e⁻³ decay criterion (``l_star``), diffuse removed.
    - Anything else (Cook–Torrance, Ward, ...): measured — K(frac) of the hemisphere BRDF matrix at
      ``n_fallback`` × ``n_fallback`` (24 by default: a few seconds; an estimate, capped by the grid
      for very sharp lobes).

    All in the BRDF's own norm (the paper's). The renderer's default (``InOut(norm="cosine")``)
    counts K(99 %) of cos θo ρ cos θi instead and uses this rule only as a floor for Lambert, Phong
    and the half-angle families: for a BRDF with a 1/(cos θi cos θo) factor the measured fallback
    here spends its terms on the grazing spike (``methods.inout.transport`` docstring, item 1).
    """
    kind = getattr(material, "kind", type(material).__name__).lower().replace("_", "")
    if kind == "lambert" or _ks_zero(material):
        return 1
    if kind == "phong":
        return max(1, math.ceil(PHONG_HEMISPHERE_SLOPE * float(material.s) - 1e-9))
    if kind in ("blinnphong", "torrancesparrow"):
        ls = l_star(half_angle_curve(_specular_only(material)))
        return max(1, math.ceil(ls**2 / HALF_ANGLE_DIVISOR - 1e-9))
    M = brdf_matrix(material, n_fallback, "hemisphere")
    return terms_for_energy(singular_values(M, "hemisphere"), frac)


def _specular_only(material: Any) -> Any:
    """The same material with kd = 0 (dataclasses.replace on the frozen dataclass)."""
    import dataclasses  # noqa: PLC0415

    if dataclasses.is_dataclass(material) and any(f.name == "kd" for f in dataclasses.fields(material)):
        return dataclasses.replace(material, kd=0.0)
    return material


def terms_needed(exponent: float, target: float = ENERGY_FRACTION) -> int:
    """This paper's row of the terms-vs-exponent study: measured K(target) for Phong exponent s on
    the visible hemisphere at the paper's 40 × 40 resolution (Mahajan 2008 Fig. 3A, hemisphere).

    The energy is that of the BRDF matrix ρ itself (the paper's norm, as in Fig. 3A), not of the
    cosine-weighted cos θo ρ cos θi in which the renderer (``InOut``, norm "cosine") counts its K.

    exponent: Phong s (> 0); target: captured energy fraction in (0, 1].
    """
    if not exponent > 0:
        raise ValueError(f"exponent must be > 0, got {exponent}")
    return phong_hemisphere_terms(float(exponent), PAPER_N, float(target))
