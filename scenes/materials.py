"""Analytic BRDFs in torch — one formula each, mirrored by the Mitsuba plugins in
`references/plugins.py` (docs/ARCHITECTURE.md, "scenes/materials.py").

Conventions (docs/ARCHITECTURE.md "Conventions"):
* Directions are unit vectors in the local shading frame (z = normal), both pointing *away* from
  the surface: ``wi`` towards the light, ``wo`` towards the viewer.
* ``eval(wi, wo)`` is the BRDF f(wi, wo) *without* the cosine; it is 0 when either direction is
  at or below the horizon (z <= 0).
* ``sample(wo, u)`` draws ``wi`` from a mixture: a cosine-weighted hemisphere for the diffuse part
  and a lobe sampler for the specular part, chosen with probability proportional to the
  luminance of kd resp. ks. ``pdf(wi, wo)`` is the exact solid-angle density of ``sample``
  over the whole sphere (it integrates to 1; samples can fall below the horizon, where
  ``eval`` is 0).
* Colours kd, ks are linear-RGB 3-tuples (a scalar is broadcast).

Half-vector samplers draw h in the upper hemisphere with density p_h(h) and reflect
wo about it, wi = 2(wo·h)h − wo; the solid-angle density of wi is p_h(h)/(4|wo·h|)
(Walter et al. 2007 eq. 14/17), with h = ±normalize(wi + wo) chosen in the upper hemisphere.
This map from the upper hemisphere of h onto the sphere of wi is one-to-one, so the density
integrates to exactly 1.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import torch
from torch import Tensor

from methods.core.frames import coordinate_system
from methods.core.sampling import cosine_hemisphere_pdf, from_cos_phi, sample_cosine_hemisphere

# Rec.709 luminance weights (also Mitsuba's `luminance()` for RGB variants).
LUMINANCE_WEIGHTS = (0.212671, 0.715160, 0.072169)

# Guard for divisions by |wo·h| and normalisations of nearly-opposite vectors.
_TINY = 1e-12

# -- float32 limits of the lobe parameters (the Mitsuba references and the methods run in float32) --
# Rule: a lobe's peak normalisation must stay 2²⁴ below FLT_MAX (headroom for the 1/cos factors
# and the radiance it multiplies).
# Beckmann (1/(πm²cos⁴θh)), Torrance–Sparrow (1/(4πσ²)) and Ward (1/(4π ax ay √(cosθi cosθo)))
# peak as 1/(π w²) in the lobe width w: 1/(π w²) ≤ FLT_MAX/2²⁴ ⇔ w ≥ √(2²⁴/(π·FLT_MAX)) ≈ 1.25e-16
# (Ward: w = √(ax·ay)). The references overflow from m ≈ 1e-19, σ ≈ 1e-21, a ≈ 1e-25 on.
# Blinn-Phong's (s+2)/(8π) gives s ≤ 8π·FLT_MAX/2²⁴ ≈ 5.1e32 (n·h of a normalised h stays ≤ 1 in
# float32; its reference is finite up to s = 1e12).
# Phong is different: its normalisation (s+1)/(2π) is harmless, but R·wi of float32 unit vectors
# rounds up to δ = 2 ulp = 2·2⁻²³ above 1, and (1+δ)^s = e^{sδ} multiplies the peak: it overflows
# float32 (ln FLT_MAX = 88.7) at s ≈ (88.7 − ln((s+1)/2π))/δ ≈ 3.0e8, where the Mitsuba reference
# turns NaN/Inf (pixels of ~1e9 already at s = 1e8). We stop where that factor reaches e (sδ = 1):
# s ≤ 2²², above any lobe the float32 sphere resolves.
FLT32_MAX = float(torch.finfo(torch.float32).max)
_HEADROOM = 2.0**24
MIN_LOBE_WIDTH = math.sqrt(_HEADROOM / (math.pi * FLT32_MAX))
MAX_BLINN_EXPONENT = 8.0 * math.pi * FLT32_MAX / _HEADROOM
MAX_PHONG_EXPONENT = 2.0**22


def _max_exponent(s: float, name: str, bound: float, why: str) -> float:
    if s > bound:
        raise ValueError(f"{name} = {s!r} exceeds {bound:.3g}: {why}")
    return s


def _min_width(w: float, name: str) -> float:
    if w < MIN_LOBE_WIDTH:
        raise ValueError(f"{name} = {w!r} is below {MIN_LOBE_WIDTH:.3g}: the lobe's peak 1/(π·{name}²) overflows "
                         f"float32 in the Mitsuba reference")
    return w


# -- validation helpers ---------------------------------------------------------------------


def _positive_float(x: Any, name: str, *, allow_zero: bool = False) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real number, got {x!r}") from None
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{name} must be finite and {bound}, got {x!r}")
    return v


def _rgb(x: Any, name: str) -> tuple[float, float, float]:
    """A non-negative finite RGB triple from a scalar or a length-3 sequence."""
    if isinstance(x, Tensor):
        x = x.detach().cpu().tolist()
    if hasattr(x, "tolist") and not isinstance(x, (list, tuple)):  # numpy
        x = x.tolist()
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        x = (x, x, x)
    if not isinstance(x, (list, tuple)) or len(x) != 3:
        raise ValueError(f"{name} must be a scalar or an RGB 3-tuple, got {x!r}")
    return tuple(_positive_float(c, f"{name}[{i}]", allow_zero=True) for i, c in enumerate(x))  # type: ignore[return-value]


def luminance(rgb: tuple[float, float, float]) -> float:
    """Rec.709 luminance of an RGB triple."""
    return sum(w * c for w, c in zip(LUMINANCE_WEIGHTS, rgb))


# -- pure sampling functions ----------------------------------------------------------------


def _dot(a: Tensor, b: Tensor) -> Tensor:
    return (a * b).sum(-1)


def power_cosine_sample(u: Tensor, s: float) -> Tensor:
    """Directions about +z with density (s+1)/(2π) cos^s θ on the hemisphere (..., 2) → (..., 3)."""
    cos_t = (1.0 - u[..., 0]).clamp_min(0.0).pow(1.0 / (s + 1.0))
    return from_cos_phi(cos_t, 2.0 * math.pi * u[..., 1])


def power_cosine_pdf(cos_t: Tensor, s: float) -> Tensor:
    """Density (s+1)/(2π) max(0, cosθ)^s of `power_cosine_sample`."""
    return (s + 1.0) / (2.0 * math.pi) * cos_t.clamp_min(0.0).pow(s) * (cos_t > 0)


def reflect_z(w: Tensor) -> Tensor:
    """Mirror direction about the local normal z: R = 2(n·w)n − w = (−x, −y, z)."""
    return torch.stack([-w[..., 0], -w[..., 1], w[..., 2]], dim=-1)


def reflect_about(wo: Tensor, h: Tensor) -> Tensor:
    """wi = 2(wo·h)h − wo."""
    return 2.0 * _dot(wo, h)[..., None] * h - wo


def half_vector(wi: Tensor, wo: Tensor) -> tuple[Tensor, Tensor]:
    """Unit half vector flipped into the upper hemisphere, and a validity mask (wi ≠ −wo)."""
    h = wi + wo
    n = h.norm(dim=-1, keepdim=True)
    valid = n[..., 0] > 1e-6
    h = h / n.clamp_min(_TINY)
    h = torch.where((h[..., 2] < 0)[..., None], -h, h)
    return h, valid


def half_to_wi_pdf(p_h: Tensor, wo: Tensor, h: Tensor, valid: Tensor) -> Tensor:
    """Solid-angle density of wi = reflect(wo, h): p_h/(4|wo·h|) (Walter 2007 eq. 14)."""
    woh = _dot(wo, h).abs()
    out = p_h / (4.0 * woh.clamp_min(_TINY))
    return torch.where(valid & (woh > 0), out, torch.zeros_like(out))


def beckmann_sample(u: Tensor, m: float) -> Tensor:
    """Half vectors with density D(h)cosθh, D Beckmann of roughness m; (..., 2) → (..., 3)."""
    tan2 = -(m * m) * torch.log1p(-u[..., 0].clamp(max=1.0 - 1e-7))
    cos_t = torch.rsqrt(1.0 + tan2)
    return from_cos_phi(cos_t, 2.0 * math.pi * u[..., 1])


def beckmann_D(cos_t: Tensor, m: float) -> Tensor:
    """Beckmann distribution D(h) = exp(−tan²θh/m²)/(π m² cos⁴θh) (Cook & Torrance 1982 eq. 4)."""
    c = cos_t.clamp_min(_TINY)
    c2 = c * c
    tan2 = (1.0 - c2).clamp_min(0.0) / c2
    d = torch.exp(-tan2 / (m * m)) / (math.pi * m * m * c2 * c2)
    return torch.where(cos_t > 0, d, torch.zeros_like(d))


def phong_lobe(wi: Tensor, wo: Tensor, s) -> Tensor:
    """Phong specular lobe (s+1)/(2π) max(0, R·wi)^s, R = reflect(wo) (Mahajan 2008 eq. 5), no ks.
    ``s`` a float or a tensor broadcasting against the (...) result (a family of exponents)."""
    return power_cosine_pdf(_dot(reflect_z(wo), wi), s)


def blinn_phong_lobe(wi: Tensor, wo: Tensor, s) -> Tensor:
    """Blinn-Phong specular lobe (s+2)/(8π) (n·h)^s, no ks; ``s`` as in `phong_lobe`."""
    h, valid = half_vector(wi, wo)
    return (s + 2.0) / (8.0 * math.pi) * h[..., 2].clamp_min(0.0).pow(s) * valid


def cook_torrance_lobe(wi: Tensor, wo: Tensor, m, F0) -> Tensor:
    """Cook–Torrance specular lobe D·F·G/(4 cosθi cosθo) (see `CookTorrance`), no ks; ``m`` and
    ``F0`` floats or tensors broadcasting against the (...) result (h and G are computed once)."""
    h, valid = half_vector(wi, wo)
    nh, ni, no = h[..., 2], wi[..., 2], wo[..., 2]
    oh = _dot(wo, h).clamp_min(_TINY)
    G = torch.minimum(torch.ones_like(nh), torch.minimum(2 * nh * no / oh, 2 * nh * ni / oh))
    F = F0 + (1.0 - F0) * (1.0 - oh).clamp_min(0.0) ** 5  # Schlick 1994
    return beckmann_D(nh, m) * F * (G / (4.0 * ni * no).clamp_min(_TINY) * valid)


def ts_sample(u: Tensor, sigma: float) -> Tensor:
    """Half vectors for the Torrance–Sparrow lobe exp(−(θh/σ)²): θh has density
    ∝ θ exp(−θ²/σ²) on [0, π/2] (a 2-D Gaussian in polar coordinates, truncated), φ uniform."""
    E = 1.0 - math.exp(-((math.pi / 2) / sigma) ** 2)
    theta = sigma * torch.sqrt(-torch.log1p(-u[..., 0] * E))
    theta = theta.clamp(max=math.pi / 2)
    return from_cos_phi(torch.cos(theta), 2.0 * math.pi * u[..., 1])


def ts_half_pdf(cos_t: Tensor, sigma: float) -> Tensor:
    """Solid-angle density of `ts_sample`: θ exp(−θ²/σ²)/(πσ²(1−e^{−(π/2σ)²}) sinθ)."""
    E = 1.0 - math.exp(-((math.pi / 2) / sigma) ** 2)
    c = cos_t.clamp(-1.0, 1.0)
    theta = torch.acos(c)
    sin_t = (1.0 - c * c).clamp_min(0.0).sqrt()
    # θ/sinθ → 1 at θ = 0; its series 1 + θ²/6 is exact to float precision for θ < 1e-3
    ratio = torch.where(theta > 1e-3, theta / sin_t.clamp_min(_TINY), 1.0 + theta * theta / 6.0)
    p = ratio * torch.exp(-(theta / sigma) ** 2) / (math.pi * sigma * sigma * E)
    return torch.where(cos_t > 0, p, torch.zeros_like(p))


def ward_sample(u: Tensor, ax: float, ay: float) -> Tensor:
    """Half vectors for the anisotropic Ward/Beckmann lobe (Walter 2005, "Notes on the Ward
    BRDF", eq. 6–7), written in slope space: slope = sqrt(−ln(1−u0))·(ax cos2πu1, ay sin2πu1)."""
    r = torch.sqrt(-torch.log1p(-u[..., 0].clamp(max=1.0 - 1e-7)))
    phi = 2.0 * math.pi * u[..., 1]
    sx, sy = ax * r * torch.cos(phi), ay * r * torch.sin(phi)
    h = torch.stack([sx, sy, torch.ones_like(sx)], dim=-1)
    return h / h.norm(dim=-1, keepdim=True)


def ward_half_pdf(h: Tensor, ax: float, ay: float) -> Tensor:
    """Solid-angle density of `ward_sample`: exp(−(hx²/ax² + hy²/ay²)/hz²)/(π ax ay hz³)."""
    hz = h[..., 2].clamp_min(_TINY)
    e = ((h[..., 0] / ax) ** 2 + (h[..., 1] / ay) ** 2) / (hz * hz)
    p = torch.exp(-e) / (math.pi * ax * ay * hz**3)
    return torch.where(h[..., 2] > 0, p, torch.zeros_like(p))


# -- the materials ---------------------------------------------------------------------------


def _check_dirs(wi: Tensor, wo: Tensor) -> None:
    if wi.shape[-1] != 3 or wo.shape[-1] != 3:
        raise ValueError(f"wi, wo must have shape (..., 3), got {tuple(wi.shape)} and {tuple(wo.shape)}")


_KINDS: dict[str, type["Material"]] = {}


@dataclass(frozen=True)
class Material:
    """Base of every BRDF: a frozen dataclass of validated parameters.

    Subclasses implement the specular part (`_spec_eval`, `_spec_sample`, `_spec_pdf`); the
    Lambertian kd/π term, the horizon test, the mixture sampling and (de)serialisation live here.
    """

    kd: tuple[float, float, float] = (0.5, 0.5, 0.5)

    def __init_subclass__(cls, **kw):
        super().__init_subclass__(**kw)
        _KINDS[cls.__name__.lower()] = cls

    def __post_init__(self) -> None:
        object.__setattr__(self, "kd", _rgb(self.kd, "kd"))
        if hasattr(self, "ks"):
            object.__setattr__(self, "ks", _rgb(self.ks, "ks"))

    # -- identity / serialisation
    @property
    def kind(self) -> str:
        return type(self).__name__.lower()

    def params(self) -> dict:
        """JSON-able parameters including "kind"; `Material.from_params` inverts it."""
        d: dict[str, Any] = {"kind": self.kind}
        for f in fields(self):
            v = getattr(self, f.name)
            d[f.name] = list(v) if isinstance(v, tuple) else v
        return d

    @staticmethod
    def from_params(d: dict) -> "Material":
        if not isinstance(d, dict) or "kind" not in d:
            raise ValueError(f"material parameters must be a dict with a 'kind', got {d!r}")
        kind = d["kind"]
        if kind not in _KINDS:
            raise ValueError(f"unknown material kind {kind!r}; known: {', '.join(sorted(_KINDS))}")
        cls = _KINDS[kind]
        names = {f.name for f in fields(cls)}
        extra = set(d) - names - {"kind"}
        if extra:
            raise ValueError(f"unknown parameter(s) for {kind}: {', '.join(sorted(extra))}")
        return cls(**{k: v for k, v in d.items() if k != "kind"})

    # -- mixture weights
    @property
    def ks_rgb(self) -> tuple[float, float, float]:
        return getattr(self, "ks", (0.0, 0.0, 0.0))

    @property
    def spec_weight(self) -> float:
        """Probability of sampling the specular lobe: lum(ks)/(lum(kd)+lum(ks)) (0 if both 0)."""
        ld, ls = luminance(self.kd), luminance(self.ks_rgb)
        return ls / (ld + ls) if ld + ls > 0 else 0.0

    # -- the three operations
    def eval(self, wi: Tensor, wo: Tensor) -> Tensor:
        """BRDF f(wi, wo) without the cosine.

        Args:
            wi, wo: (..., 3) local-frame unit directions (broadcastable), away from the surface.
        Returns:
            (..., 3) RGB values, 0 where wi.z <= 0 or wo.z <= 0.
        """
        _check_dirs(wi, wo)
        wi, wo = torch.broadcast_tensors(wi, wo)
        kd = torch.tensor(self.kd, dtype=wi.dtype, device=wi.device)
        f = kd / math.pi + self._spec_eval(wi, wo)
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        return torch.where(up[..., None], f, torch.zeros_like(f))

    def pdf(self, wi: Tensor, wo: Tensor) -> Tensor:
        """Solid-angle density of `sample(wo, ·)` at wi; (..., 3), (..., 3) → (...)."""
        _check_dirs(wi, wo)
        wi, wo = torch.broadcast_tensors(wi, wo)
        ps = self.spec_weight
        p = (1.0 - ps) * cosine_hemisphere_pdf(wi)
        if ps > 0:
            p = p + ps * self._spec_pdf(wi, wo)
        return p

    def sample(self, wo: Tensor, u: Tensor) -> tuple[Tensor, Tensor]:
        """Importance-sample wi for the view direction wo.

        Args:
            wo: (..., 3) local-frame unit view directions; u: (..., 2) uniforms in [0, 1).
        Returns:
            wi (..., 3) unit directions (may lie below the horizon for specular samples) and
            pdf (...) their solid-angle density (= `pdf(wi, wo)`).
        """
        if wo.shape[-1] != 3 or u.shape[-1] != 2:
            raise ValueError(f"wo must be (..., 3) and u (..., 2), got {tuple(wo.shape)}, {tuple(u.shape)}")
        u = u.to(wo.dtype)
        batch = torch.broadcast_shapes(wo.shape[:-1], u.shape[:-1])
        wo = wo.expand(*batch, 3)
        u = u.expand(*batch, 2)
        ps = self.spec_weight
        pd = 1.0 - ps
        u0, u1 = u[..., 0], u[..., 1]
        one_minus = 1.0 - torch.finfo(u.dtype).eps
        wi = sample_cosine_hemisphere(torch.stack([(u0 / max(pd, _TINY)).clamp(0, one_minus), u1], -1))[0]
        if ps > 0:
            us = torch.stack([((u0 - pd) / ps).clamp(0, one_minus), u1], -1)
            wi_s = self._spec_sample(wo, us)
            wi = torch.where((u0 >= pd)[..., None], wi_s, wi)
        return wi, self.pdf(wi, wo)

    # -- specular part (overridden)
    def _spec_eval(self, wi: Tensor, wo: Tensor) -> Tensor:
        return torch.zeros(*wi.shape[:-1], 3, dtype=wi.dtype, device=wi.device)

    def _spec_sample(self, wo: Tensor, u: Tensor) -> Tensor:
        raise NotImplementedError

    def _spec_pdf(self, wi: Tensor, wo: Tensor) -> Tensor:
        return torch.zeros_like(wi[..., 0])

    def _ks(self, like: Tensor) -> Tensor:
        return torch.tensor(self.ks_rgb, dtype=like.dtype, device=like.device)


@dataclass(frozen=True)
class Lambert(Material):
    """f = kd/π."""


@dataclass(frozen=True)
class Phong(Material):
    """Normalised Phong, Mahajan 2008 eq. 5: f = kd/π + ks (s+1)/(2π) max(0, R·wi)^s,
    R = reflect(wo) about n. Specular sampling: the cos^s lobe about R (density (s+1)/(2π)(R·wi)^s
    on the hemisphere around R), so the specular pdf equals the lobe."""

    ks: tuple[float, float, float] = (0.5, 0.5, 0.5)
    s: float = 10.0

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "s", _max_exponent(
            _positive_float(self.s, "s"), "s", MAX_PHONG_EXPONENT,
            "float32 rounding of cos^s overflows the lobe (the Mitsuba reference turns NaN/Inf near s = 3e8)"))

    def _spec_eval(self, wi, wo):
        return self._ks(wi) * phong_lobe(wi, wo, self.s)[..., None]  # Mahajan eq. 5

    def _spec_sample(self, wo, u):
        R = reflect_z(wo)
        R = R / R.norm(dim=-1, keepdim=True).clamp_min(_TINY)
        s_, t_ = coordinate_system(R)
        l = power_cosine_sample(u, self.s)
        return l[..., :1] * s_ + l[..., 1:2] * t_ + l[..., 2:] * R

    def _spec_pdf(self, wi, wo):
        R = reflect_z(wo)
        return power_cosine_pdf(_dot(R, wi) / R.norm(dim=-1).clamp_min(_TINY), self.s)


@dataclass(frozen=True)
class BlinnPhong(Material):
    """f = kd/π + ks (s+2)/(8π) (n·h)^s. Half vector sampled with density (s+1)/(2π)(n·h)^s."""

    ks: tuple[float, float, float] = (0.5, 0.5, 0.5)
    s: float = 10.0

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "s", _max_exponent(
            _positive_float(self.s, "s"), "s", MAX_BLINN_EXPONENT, "the normalisation (s+2)/(8π) overflows float32"))

    def _spec_eval(self, wi, wo):
        return self._ks(wi) * blinn_phong_lobe(wi, wo, self.s)[..., None]

    def _spec_sample(self, wo, u):
        return reflect_about(wo, power_cosine_sample(u, self.s))

    def _spec_pdf(self, wi, wo):
        h, valid = half_vector(wi, wo)
        return half_to_wi_pdf(power_cosine_pdf(h[..., 2], self.s), wo, h, valid)


@dataclass(frozen=True)
class CookTorrance(Material):
    """Cook & Torrance 1982: f = kd/π + ks·D·F·G/(4 cosθi cosθo) with Beckmann D (roughness m),
    Schlick F = F0 + (1−F0)(1 − wo·h)^5 and G = min(1, 2(n·h)(n·wo)/(wo·h), 2(n·h)(n·wi)/(wo·h)).
    F0 is a scalar in [0, 1]. Half vector sampled with density D(h) cosθh."""

    ks: tuple[float, float, float] = (0.5, 0.5, 0.5)
    m: float = 0.3
    F0: float = 0.04

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "m", _min_width(_positive_float(self.m, "m"), "m"))
        F0 = _positive_float(self.F0, "F0", allow_zero=True)
        if F0 > 1:
            raise ValueError(f"F0 must lie in [0, 1], got {self.F0!r}")
        object.__setattr__(self, "F0", F0)

    def _spec_eval(self, wi, wo):
        return self._ks(wi) * cook_torrance_lobe(wi, wo, self.m, self.F0)[..., None]

    def _spec_sample(self, wo, u):
        return reflect_about(wo, beckmann_sample(u, self.m))

    def _spec_pdf(self, wi, wo):
        h, valid = half_vector(wi, wo)
        return half_to_wi_pdf(beckmann_D(h[..., 2], self.m) * h[..., 2], wo, h, valid)


@dataclass(frozen=True)
class TorranceSparrow(Material):
    """Mahajan 2008 eq. 14, a Gaussian in the half angle:
    f = kd/π + ks · exp(−(acos(n·h)/σ)²)/(4πσ²).

    The 1/(4πσ²) factor is Mahajan's: ∫ exp(−θh²/σ²) dωh ≈ πσ² for small σ, and dωi = 4(wo·h)dωh
    ≈ 4dωh near normal incidence, so ∫ f_spec dωi ≈ ks for small σ (the same normalisation
    as eq. 5's Phong lobe: the lobe integrates to 1 without the cosine). No Fresnel, shadowing
    or 1/cos factors are added. Half vector sampled with density ∝ θh exp(−θh²/σ²)/sinθh
    (see `ts_sample`).
    """

    ks: tuple[float, float, float] = (0.5, 0.5, 0.5)
    sigma: float = 0.2

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "sigma", _min_width(_positive_float(self.sigma, "sigma"), "sigma"))

    def _spec_eval(self, wi, wo):
        h, valid = half_vector(wi, wo)
        th = torch.acos(h[..., 2].clamp(-1.0, 1.0))
        v = torch.exp(-(th / self.sigma) ** 2) / (4.0 * math.pi * self.sigma**2) * valid  # Mahajan eq. 14
        return self._ks(wi) * v[..., None]

    def _spec_sample(self, wo, u):
        return reflect_about(wo, ts_sample(u, self.sigma))

    def _spec_pdf(self, wi, wo):
        h, valid = half_vector(wi, wo)
        return half_to_wi_pdf(ts_half_pdf(h[..., 2], self.sigma), wo, h, valid)


@dataclass(frozen=True)
class Ward(Material):
    """Anisotropic Ward 1992 (eq. 5a): f = kd/π + ks exp(−(hx²/ax² + hy²/ay²)/hz²)
    / (4π ax ay sqrt(cosθi cosθo)), tangent = local x. Half vector sampled from the anisotropic
    Beckmann-like density exp(−…)/(π ax ay hz³) (Walter 2005)."""

    ks: tuple[float, float, float] = (0.5, 0.5, 0.5)
    ax: float = 0.2
    ay: float = 0.2

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "ax", _positive_float(self.ax, "ax"))
        object.__setattr__(self, "ay", _positive_float(self.ay, "ay"))
        _min_width(math.sqrt(self.ax * self.ay), "sqrt(ax·ay)")

    def _spec_eval(self, wi, wo):
        h = wi + wo  # unnormalised: only ratios hx/hz, hy/hz enter
        hz = h[..., 2].clamp_min(_TINY)
        e = ((h[..., 0] / self.ax) ** 2 + (h[..., 1] / self.ay) ** 2) / (hz * hz)
        c = (wi[..., 2] * wo[..., 2]).clamp_min(_TINY).sqrt()
        v = torch.exp(-e) / (4.0 * math.pi * self.ax * self.ay * c)  # Ward 1992 eq. 5a
        return self._ks(wi) * v[..., None]

    def _spec_sample(self, wo, u):
        return reflect_about(wo, ward_sample(u, self.ax, self.ay))

    def _spec_pdf(self, wi, wo):
        h, valid = half_vector(wi, wo)
        return half_to_wi_pdf(ward_half_pdf(h, self.ax, self.ay), wo, h, valid)


MATERIAL_KINDS: tuple[str, ...] = ("lambert", "phong", "blinnphong", "cooktorrance", "torrancesparrow", "ward")

__all__ = ["MAX_PHONG_EXPONENT", "MAX_BLINN_EXPONENT", "MIN_LOBE_WIDTH", "Material", "Lambert", "Phong", "BlinnPhong", "CookTorrance", "TorranceSparrow", "Ward",
           "MATERIAL_KINDS", "luminance"]
