"""Specular lobe separation (Sun et al. 2007 §4.1, Fig. 4, Fig. 6).

    f(h, ωo, ωi) = f_s(h, ωo, ωi) + f_r(h, ωo, ωi),
    f_s = Σ_{k ∈ {0°, 7°, 14°, 21°}} f_s^(k),   f_s^(k)(h, ωo, ωi) = a_k(h, ωo) G_k(ωi; R(ωo)),

with R(ωo) the mirror direction of ωo about the normal and G_k a univariate Gaussian in the angle
θ between ωi and R(ωo), "of which three standard deviations covers a k-degree" neighbourhood:
σ_k = k/3 degrees (we read "k-degree solid angle" as the cone of half-angle k about R; the paper
does not say whether k is the half-angle or the apex angle). 0° is the perfect mirror.

Normalisation (ours; the paper does not give one): every lobe has unit mass on the sphere,
∫ G_k dω = 1, so a_k(h, ωo) is the lobe's integral in BRDF·sr units and the run-time direct term is
a_k · E^(k)(R) · (R·n) · V^(k) with E^(k) the env map prefiltered by the same unit-mass Gaussian
(§4.1) and V^(k) the fractional visibility over the cone. The 0° lobe is a Dirac delta at R; on a
discrete ωi sampling it is represented by its interpolation weights at R divided by the sample
solid angles (`delta` argument of `lobe_basis`, built by `brdf_tensor.DiskGrid.delta`), so that
Σ_j Ω_j δ_j = 1 and ∫ δ g ≈ the interpolated g(R).

Fitting: the paper uses EM with the centres and widths fixed. We solve the equivalent constrained
fit directly: for every (h, ωo) the non-negative least-squares problem
    min_{a ≥ 0} Σ_j w_j (f(ωi_j) − Σ_k a_k G_k(ωi_j))²
exactly (K = 4 unknowns: all 2^K active sets are solved in closed form and the best feasible one
kept — the NNLS optimum is the least-squares solution on its support, and every feasible
support-restricted solution is a feasible point, so the minimum over them is the optimum).
The default w_j = 1 minimises the same discrete Frobenius norm the tensor approximation of f_r is
scored in (Fig. 5).
"""
from __future__ import annotations

import itertools
import math
from typing import Sequence

import numpy as np
import torch
from torch import Tensor

from methods.core.threads import torch_threads

__all__ = [
    "LOBE_DEGREES",
    "lobe_sigma",
    "gaussian_lobe_mass",
    "gaussian_lobe",
    "lobe_basis",
    "fit_lobe_weights",
    "lobe_values",
    "separate_lobes",
]

# Sun 2007 §4.1: "k = 0°, 7°, 14°, 21°", sampled from the 64×64×6 visibility cube map resolution.
LOBE_DEGREES: tuple[float, ...] = (0.0, 7.0, 14.0, 21.0)

# Relative slack when testing an active-set solution for non-negativity (float64 round-off of a
# 4×4 solve is ~1e-13 relative; 1e-9 leaves margin without accepting genuinely negative weights).
_FEAS_TOL = 1e-9


def lobe_sigma(k_deg: float) -> float:
    """σ_k in radians: 3σ_k = k degrees (Sun 2007 §4.1)."""
    if not k_deg > 0:
        raise ValueError(f"a Gaussian lobe needs k > 0 degrees, got {k_deg}")
    return math.radians(k_deg) / 3.0


def gaussian_lobe_mass(sigma: float) -> float:
    """Z(σ) = ∫_{S²} exp(−θ²/(2σ²)) dω = 2π ∫_0^π exp(−θ²/(2σ²)) sinθ dθ (Gauss–Legendre, 256
    nodes on [0, min(π, 12σ)], float64; the integrand is < e^−72 beyond 12σ)."""
    if not sigma > 0:
        raise ValueError(f"sigma must be > 0, got {sigma}")
    hi = min(math.pi, 12.0 * sigma)
    x, w = np.polynomial.legendre.leggauss(256)
    t = 0.5 * hi * (x + 1.0)
    return float(2.0 * math.pi * 0.5 * hi * np.sum(w * np.exp(-t * t / (2 * sigma * sigma)) * np.sin(t)))


def gaussian_lobe(cos_theta: Tensor, sigma: float) -> Tensor:
    """Unit-mass Gaussian lobe exp(−θ²/(2σ²))/Z(σ), θ = acos(cos_theta); (...) → (...)."""
    th = torch.acos(cos_theta.clamp(-1.0, 1.0))
    return torch.exp(-th * th / (2.0 * sigma * sigma)) / gaussian_lobe_mass(sigma)


def lobe_basis(wi: Tensor, R: Tensor, *, degrees: Sequence[float] = LOBE_DEGREES,
               delta: Tensor | None = None) -> Tensor:
    """The lobe functions G_k(ωi_j; R_o) sampled at the incident directions.

    Args:
        wi: (Ni, 3) unit incident directions (the ωi sampling of the BRDF tensor).
        R: (No, 3) unit mirror directions R(ωo) of the view samples.
        degrees: lobe sizes k (0 = mirror delta); Sun 2007 uses (0, 7, 14, 21).
        delta: (No, Ni) the discrete unit-mass delta at each R on the wi sampling (required when
            0 is in `degrees`; see `brdf_tensor.DiskGrid.delta`).
    Returns:
        B (No, K, Ni), K = len(degrees), in the dtype/device of `wi`.
    """
    if wi.ndim != 2 or wi.shape[1] != 3 or R.ndim != 2 or R.shape[1] != 3:
        raise ValueError(f"wi must be (Ni, 3) and R (No, 3), got {tuple(wi.shape)}, {tuple(R.shape)}")
    if len(degrees) == 0:
        raise ValueError("need at least one lobe")
    cos = R.to(wi) @ wi.T                                         # (No, Ni)
    rows = []
    for k in degrees:
        if k == 0:
            if delta is None or delta.shape != cos.shape:
                raise ValueError(f"the 0° (mirror) lobe needs delta of shape {tuple(cos.shape)}")
            rows.append(delta.to(wi))
        else:
            rows.append(gaussian_lobe(cos, lobe_sigma(float(k))))
    return torch.stack(rows, dim=1)


def fit_lobe_weights(f: Tensor, B: Tensor, *, weights: Tensor | None = None) -> Tensor:
    """Exact non-negative least-squares lobe weights for every (h, ωo) (see module docstring).

    Args:
        f: (..., No, Ni) BRDF samples (the specular part, no cosine).
        B: (No, K, Ni) lobe basis from `lobe_basis`.
        weights: optional (Ni,) non-negative sample weights w_j of the fit (default 1).
    Returns:
        a (..., No, K) ≥ 0.
    """
    if B.ndim != 3 or f.shape[-2:] != (B.shape[0], B.shape[2]):
        raise ValueError(f"f (..., No, Ni) and B (No, K, Ni) disagree: {tuple(f.shape)}, {tuple(B.shape)}")
    K = B.shape[1]
    Bw = B if weights is None else B * weights.to(B)
    A = torch.einsum("okj,olj->okl", Bw, B)                       # (No, K, K) normal matrix
    b = torch.einsum("...oj,okj->...ok", f.to(B), Bw)             # (..., No, K)
    best_gain = torch.zeros(b.shape[:-1], dtype=b.dtype, device=b.device)  # empty set: gain 0
    best = torch.zeros_like(b)
    for r in range(1, K + 1):
        for S in itertools.combinations(range(K), r):
            S = list(S)
            A_S = A[:, S][:, :, S]                                # (No, r, r)
            with torch_threads(1):  # LAPACK (eigh) rounds differently with other thread counts (methods.core.threads)
                A_inv = torch.linalg.pinv(A_S, hermitian=True)
            a_S = torch.einsum("ors,...os->...or", A_inv, b[..., S])
            scale = a_S.abs().amax(-1, keepdim=True).clamp_min(torch.finfo(a_S.dtype).tiny)
            feasible = (a_S >= -_FEAS_TOL * scale).all(-1)
            gain = (a_S * b[..., S]).sum(-1)                      # ‖f‖² − objective at the LS point
            take = feasible & (gain > best_gain)
            cand = torch.zeros_like(b)
            cand[..., S] = a_S.clamp_min(0.0)
            best = torch.where(take[..., None], cand, best)
            best_gain = torch.where(take, gain, best_gain)
    return best


def lobe_values(a: Tensor, B: Tensor) -> Tensor:
    """f_s = Σ_k a_k G_k: a (..., No, K), B (No, K, Ni) → (..., No, Ni)."""
    return torch.einsum("...ok,okj->...oj", a, B.to(a))


def separate_lobes(f: Tensor, B: Tensor, *, weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """Sun 2007 §4.1: split f = f_s + f_r with the fitted lobes.

    Args:
        f: (..., No, Ni); B: (No, K, Ni); weights: optional (Ni,).
    Returns:
        f_r (..., No, Ni) the remainder (may be slightly negative where a lobe overshoots),
        a (..., No, K) the non-negative lobe weights (BRDF·sr).
    """
    a = fit_lobe_weights(f, B, weights=weights)
    return f - lobe_values(a, B).to(f), a
