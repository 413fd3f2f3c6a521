"""BRDF spaces navigated at run time (Sun et al. 2007 §4.2 "BRDF Navigation").

A BRDF space is a finite family of *sampled* specular BRDFs f_h, h = 0..N_h−1, plus a rule that
maps a point of the space's parameter domain to interpolation weights w (N_h,) over the family:

    f_spec(point; ωi, ωo) = Σ_h w_h(point) f_h(ωi, ωo).

The full BRDF of a region is  kd/π + ks · f_spec  with *adjustable* diffuse and specular weights
kd, ks (RGB) — "we also utilize adjustable weighting coefficients for the specular and diffuse
components in the navigation" (§4.2). The sampled f_h are the specular parts of the project's
analytic materials (`scenes.materials`) with kd = 0, ks = 1 (values without the cosine).

* `BlinnPhongSpace` — shininess sampled at the integers 1..200; any shininess in [1, 200] is the
  linear interpolation of its two neighbouring samples (§4.2).
* `PhongSpace` — the same for Phong lobes (s+1)/(2π) cos^s α. Not in the paper (its spaces are
  Blinn-Phong and Cook-Torrance); our library scenes also use Phong regions (chess board, alcove
  vase), and this space lets the PCA-basis mode of the PTT method navigate them the same way.
* `CookTorranceSpace` — materials scattered over the (Fresnel F0, roughness m) plane, triangulated
  (scipy.spatial.Delaunay); a point inside the convex hull gets the barycentric weights of its
  triangle (§4.2, Fig. 7). The paper's points are Cook–Torrance fits to the 100 measured MERL
  materials (Ngan et al. 2005); their values are not published in the paper, so
  `cook_torrance_samples` generates a comparable deterministic set (see its docstring).
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from scenes.materials import (BlinnPhong, CookTorrance, Material, Phong, blinn_phong_lobe, cook_torrance_lobe,
                              phong_lobe)

__all__ = [
    "BRDFSpace",
    "BlinnPhongSpace",
    "PhongSpace",
    "CookTorranceSpace",
    "cook_torrance_samples",
    "get_space",
    "BP_SHININESS",
    "CT_F0_RANGE",
    "CT_M_RANGE",
]

# Sun 2007 §4.2: "sampling the shininess parameter at integer values from 1 to 200".
BP_SHININESS: tuple[float, ...] = tuple(float(s) for s in range(1, 201))

# Ranges of the generated Cook–Torrance set (see `cook_torrance_samples`).
CT_F0_RANGE = (0.02, 1.0)
CT_M_RANGE = (0.05, 0.5)

# Barycentric coordinates may come out at −1e-12 for points on an edge; accept that much.
_BARY_EPS = 1e-9


class BRDFSpace:
    """A family of N_h sampled specular BRDFs and a point → weights rule (thin base class).

    Subclasses define `materials` (the N_h sampled BRDFs, kd = 0, ks = 1), `weights(point)` and
    `point_of(material)`.
    """

    kind: str = ""
    materials: tuple[Material, ...] = ()

    @property
    def n_h(self) -> int:
        """N_h, the number of sampled BRDFs."""
        return len(self.materials)

    def weights(self, point) -> Tensor:  # pragma: no cover - abstract
        raise NotImplementedError

    def point_of(self, material: Material):  # pragma: no cover - abstract
        raise NotImplementedError

    def eval_samples(self, wi: Tensor, wo: Tensor) -> Tensor:
        """The sampled specular BRDFs f_h(ωi, ωo) (no cosine, ks = 1).

        Args:
            wi, wo: (..., 3) broadcastable local-frame unit directions.
        Returns:
            (N_h, ...) values, 0 below the horizon.
        """
        return torch.stack([m.eval(wi, wo)[..., 0] for m in self.materials], dim=0)

    def eval_spec(self, weights: Tensor, wi: Tensor, wo: Tensor) -> Tensor:
        """Interpolated specular BRDF Σ_h w_h f_h(ωi, ωo).

        Args:
            weights: (N_h,) interpolation weights (from `weights`); wi, wo: (..., 3).
        Returns:
            (...) values.
        """
        w = _check_weights(weights, self.n_h)
        nz = torch.nonzero(w).flatten().tolist()
        wi, wo = torch.broadcast_tensors(wi, wo)
        out = torch.zeros(wi.shape[:-1], dtype=wi.dtype, device=wi.device)
        for h in nz:  # at most 2 (BP) or 3 (CT) non-zero weights
            out = out + float(w[h]) * self.materials[h].eval(wi, wo)[..., 0]
        return out

    def eval(self, point, wi: Tensor, wo: Tensor, *, kd=0.0, ks=1.0) -> Tensor:
        """Full navigated BRDF kd/π + ks Σ_h w_h(point) f_h (Sun 2007 §4.2, adjustable weights).

        Args:
            point: a point of the space (see `weights`); wi, wo: (..., 3); kd, ks: scalar or RGB.
        Returns:
            (..., 3) RGB values (no cosine), 0 below the horizon.
        """
        spec = self.eval_spec(self.weights(point).to(wi.dtype), wi, wo)
        kd_t = torch.as_tensor(kd, dtype=wi.dtype, device=wi.device).expand(3)
        ks_t = torch.as_tensor(ks, dtype=wi.dtype, device=wi.device).expand(3)
        up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
        f = kd_t / math.pi * up[..., None] + ks_t * spec[..., None]
        return f

    def material_weights(self, material: Material) -> tuple[Tensor, tuple, tuple]:
        """(w (N_h,), kd, ks) for a project material of this space's kind."""
        return self.weights(self.point_of(material)), tuple(material.kd), tuple(material.ks_rgb)


def _upper(wi: Tensor, wo: Tensor) -> Tensor:
    """1 where both directions are above the horizon (every BRDF is 0 elsewhere), else 0."""
    return ((wi[..., 2] > 0) & (wo[..., 2] > 0)).to(wi.dtype)


def _column(x: Sequence[float], like: Tensor) -> Tensor:
    """(N_h, 1, …, 1) tensor of per-sample parameters broadcasting against ``like``."""
    return torch.tensor(x, dtype=like.dtype, device=like.device).reshape(-1, *([1] * like.ndim))


def _check_weights(w: Tensor, n: int) -> Tensor:
    w = torch.as_tensor(w)
    if w.shape != (n,):
        raise ValueError(f"weights must have shape ({n},), got {tuple(w.shape)}")
    return w


# -- Blinn-Phong -----------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class BlinnPhongSpace(BRDFSpace):
    """Blinn–Phong specular lobes (s+2)/(8π)(n·h)^s sampled at shininess values (Sun 2007 §4.2).

    shininess: strictly increasing sample values (default the integers 1..200).
    """

    shininess: tuple[float, ...] = BP_SHININESS
    kind: str = "bp"
    materials: tuple[Material, ...] = field(init=False, repr=False)

    def __post_init__(self) -> None:
        s = np.asarray(self.shininess, dtype=np.float64)
        if s.ndim != 1 or s.size < 2 or not np.all(np.diff(s) > 0) or s[0] <= 0:
            raise ValueError("shininess must be >= 2 strictly increasing positive values")
        object.__setattr__(self, "shininess", tuple(float(x) for x in s))
        object.__setattr__(self, "materials", tuple(BlinnPhong(kd=0.0, ks=1.0, s=x) for x in s))

    def weights(self, point) -> Tensor:
        """Linear-interpolation weights over the shininess samples (Sun 2007 §4.2).

        Args:
            point: shininess s (scalar) or a (B,) tensor, within [s_0, s_{N−1}].
        Returns:
            (N_h,) float64 weights (or (B, N_h)); two neighbouring entries are non-zero, exactly
            one at a sample value.
        """
        s = torch.as_tensor(point, dtype=torch.float64)
        grid = torch.tensor(self.shininess, dtype=torch.float64)
        if not torch.isfinite(s).all() or (s < grid[0]).any() or (s > grid[-1]).any():
            raise ValueError(f"shininess must lie in [{grid[0]:g}, {grid[-1]:g}], got {point!r}")
        flat = s.reshape(-1)
        j = torch.searchsorted(grid, flat, right=True).clamp(1, len(grid) - 1)  # grid[j-1] <= s
        t = (flat - grid[j - 1]) / (grid[j] - grid[j - 1])
        W = torch.zeros(flat.shape[0], len(grid), dtype=torch.float64)
        W.scatter_(1, (j - 1)[:, None], (1.0 - t)[:, None])
        W.scatter_add_(1, j[:, None], t[:, None])
        return W.reshape(*s.shape, len(grid))

    def eval_samples(self, wi: Tensor, wo: Tensor) -> Tensor:
        """`BRDFSpace.eval_samples` for all shininess samples at once (`scenes.materials.blinn_phong_lobe`
        with a column of exponents: the half vector is computed once)."""
        wi, wo = torch.broadcast_tensors(wi, wo)
        return blinn_phong_lobe(wi, wo, _column(self.shininess, wi[..., 0])) * _upper(wi, wo)

    def point_of(self, material: Material) -> float:
        if not isinstance(material, BlinnPhong):
            raise ValueError(f"the Blinn-Phong space needs a BlinnPhong material, got {material.kind}")
        return float(material.s)


@dataclass(frozen=True, eq=False)
class PhongSpace(BlinnPhongSpace):
    """Phong specular lobes (s+1)/(2π) max(0, R·ωi)^s sampled at exponents (default the integers
    1..200), linearly interpolated like `BlinnPhongSpace` (an extension: the paper's spaces are
    Blinn-Phong and Cook-Torrance)."""

    kind: str = "phong"

    def __post_init__(self) -> None:
        super().__post_init__()
        object.__setattr__(self, "materials", tuple(Phong(kd=0.0, ks=1.0, s=x) for x in self.shininess))

    def eval_samples(self, wi: Tensor, wo: Tensor) -> Tensor:
        """All exponent samples at once (`scenes.materials.phong_lobe`)."""
        wi, wo = torch.broadcast_tensors(wi, wo)
        return phong_lobe(wi, wo, _column(self.shininess, wi[..., 0])) * _upper(wi, wo)

    def point_of(self, material: Material) -> float:
        if not isinstance(material, Phong):
            raise ValueError(f"the Phong space needs a Phong material, got {material.kind}")
        return float(material.s)


# -- Cook-Torrance ---------------------------------------------------------------------------


def cook_torrance_samples(n: int = 100, *, seed: int = 2007, f0_range=CT_F0_RANGE,
                          m_range=CT_M_RANGE) -> np.ndarray:
    """A deterministic stand-in for the 100 fitted MERL materials of Sun 2007 Fig. 7.

    The paper's (F0, m) values (Cook–Torrance fits of Ngan et al. 2005) are not published, so we
    spread `n` points over the Fresnel–roughness rectangle: its 4 corners (so the convex hull
    — the navigable region — is the whole rectangle) plus n − 4 points of a scrambled 2-D Halton
    sequence (scipy.stats.qmc, `seed`), F0 uniform in `f0_range`, m log-uniform in `m_range`
    (roughness spans an order of magnitude, and a log scale spreads the shiny materials that
    dominate the tensor error as densely as the rough ones).

    Returns:
        (n, 2) float64 array of (F0, m).
    """
    from scipy.stats import qmc

    if n < 4:
        raise ValueError(f"n must be >= 4, got {n}")
    (f_lo, f_hi), (m_lo, m_hi) = f0_range, m_range
    if not (0 <= f_lo < f_hi <= 1 and 0 < m_lo < m_hi):
        raise ValueError(f"bad ranges F0 {f0_range}, m {m_range}")
    u = qmc.Halton(d=2, scramble=True, seed=seed).random(n - 4)
    corners = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]])
    u = np.concatenate([corners, u], axis=0)
    F0 = f_lo + (f_hi - f_lo) * u[:, 0]
    m = np.exp(np.log(m_lo) + (np.log(m_hi) - np.log(m_lo)) * u[:, 1])
    return np.stack([F0, m], axis=1)


@dataclass(frozen=True, eq=False)
class CookTorranceSpace(BRDFSpace):
    """Cook–Torrance specular lobes at scattered (F0, m) points, navigated by Delaunay
    triangulation + barycentric interpolation (Sun 2007 §4.2, Fig. 7).

    points: (N_h, 2) array-like of (F0, m); default `cook_torrance_samples()` (100 points).
    """

    points: np.ndarray | None = None
    kind: str = "ct"
    materials: tuple[Material, ...] = field(init=False, repr=False)
    tri: object = field(init=False, repr=False)

    def __post_init__(self) -> None:
        from scipy.spatial import Delaunay

        P = cook_torrance_samples() if self.points is None else np.asarray(self.points, dtype=np.float64)
        if P.ndim != 2 or P.shape[1] != 2 or P.shape[0] < 3:
            raise ValueError(f"points must be (N >= 3, 2) (F0, m), got {P.shape}")
        if not np.isfinite(P).all() or (P[:, 0] < 0).any() or (P[:, 0] > 1).any() or (P[:, 1] <= 0).any():
            raise ValueError("points need F0 in [0, 1] and m > 0")
        P = P.copy()
        P.setflags(write=False)
        object.__setattr__(self, "points", P)
        object.__setattr__(self, "materials",
                           tuple(CookTorrance(kd=0.0, ks=1.0, F0=f, m=m) for f, m in P))
        object.__setattr__(self, "tri", Delaunay(P))

    def weights(self, point) -> Tensor:
        """Barycentric weights of the Delaunay triangle containing `point` (Sun 2007 §4.2).

        Args:
            point: (2,) (F0, m) or (B, 2) points inside the convex hull of `points`.
        Returns:
            (N_h,) float64 weights (or (B, N_h)), ≤ 3 non-zero, summing to 1; a sample point gets
            the unit vector of its index.
        Raises:
            ValueError: a point outside the convex hull.
        """
        q = (point.detach().cpu().to(torch.float64).numpy() if isinstance(point, Tensor)
             else np.asarray(point, dtype=np.float64))
        if q.shape[-1] != 2 or q.ndim > 2:
            raise ValueError(f"point must be (2,) or (B, 2) (F0, m), got {q.shape}")
        Q = q.reshape(-1, 2)
        simplex = self.tri.find_simplex(Q)
        if (simplex < 0).any():
            bad = Q[simplex < 0][0]
            raise ValueError(f"point (F0={bad[0]:g}, m={bad[1]:g}) is outside the convex hull of the "
                             "Cook-Torrance samples")
        T = self.tri.transform[simplex]                       # (B, 3, 2): affine map to barycentrics
        b = np.einsum("bij,bj->bi", T[:, :2], Q - T[:, 2])   # scipy Delaunay docs, `transform`
        bary = np.concatenate([b, 1.0 - b.sum(1, keepdims=True)], axis=1)
        bary = np.where(np.abs(bary) < _BARY_EPS, 0.0, bary)
        bary /= bary.sum(1, keepdims=True)
        W = np.zeros((Q.shape[0], self.n_h))
        np.put_along_axis(W, self.tri.simplices[simplex], bary, axis=1)
        W = torch.from_numpy(W)
        return W.reshape(*q.shape[:-1], self.n_h)

    def eval_samples(self, wi: Tensor, wo: Tensor) -> Tensor:
        """All (F0, m) samples at once (`scenes.materials.cook_torrance_lobe`: h, G and the
        denominator computed once, D and F per sample)."""
        wi, wo = torch.broadcast_tensors(wi, wo)
        x = wi[..., 0]
        return cook_torrance_lobe(wi, wo, _column(self.points[:, 1], x), _column(self.points[:, 0], x)) * _upper(wi, wo)

    def point_of(self, material: Material) -> tuple[float, float]:
        if not isinstance(material, CookTorrance):
            raise ValueError(f"the Cook-Torrance space needs a CookTorrance material, got {material.kind}")
        return (float(material.F0), float(material.m))


def get_space(kind: str, **kw) -> BRDFSpace:
    """'bp' → `BlinnPhongSpace(**kw)`, 'ct' → `CookTorranceSpace(**kw)`, 'phong' → `PhongSpace(**kw)`."""
    if kind == "bp":
        return BlinnPhongSpace(**kw)
    if kind == "phong":
        return PhongSpace(**kw)
    if kind == "ct":
        return CookTorranceSpace(**kw)
    raise ValueError(f"unknown BRDF space {kind!r}; use 'bp', 'ct' or 'phong'")
