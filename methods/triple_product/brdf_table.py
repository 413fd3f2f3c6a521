"""One BRDF table per material in the local frame (Ma 2006 §3.2, eq. 7).

    ρ̃^{ωo}(ωi) = f(ωi, ωo) · max(0, cos θi)                                   (Ma 2006 eq. 2/7)

is tabulated for a grid of outgoing directions ωo and projected on the spherical Haar basis of
`methods.core.spherical_haar` (local frame: z = normal, x = tangent). The paper samples 64
outgoing directions per material (§4.1) and interpolates.

Outgoing grid (`OutgoingGrid(n_theta, n_phi)`): θo_a = (a + ½)·(π/2)/n_theta (cell centres: the
exactly grazing ωo, where Ward and Cook–Torrance divide by cos θo, is never tabulated),
φo_b = 2πb/n_phi; index a·n_phi + b; ωo = (sin θ cos φ, sin θ sin φ, cos θ).
Run-time look-up (`outgoing_weights`): **bilinear in (θo, φo)** (θo clamped to [θo_0, θo_last], φo
periodic) over the four surrounding tabulated ωo — linear in coefficients, i.e. a blend of four
BRDF slices. Outgoing directions below the horizon are clamped to the horizon (f = 0 there in the
references anyway, the result is multiplied by nothing else).

Real solid angles: the fine triangles of the geodesic grid differ in solid angle; the density
Ω_t / A_L (`Geodesic.density`) is folded into ρ̃ here — and only here — so that Σ C L V ρ̃ (equal
-area tripling coefficients) is the real ∫ L V ρ̃ dω.

Material editing (§5, "2 to 3 seconds to resample the edited BRDF") = calling `brdf_table` again.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from methods.core.spherical_haar import Geodesic
from methods.triple_product.lighting import periodic_index


@dataclass(frozen=True)
class OutgoingGrid:
    """Tabulated outgoing directions: n_theta ≥ 1 elevations (cell centres of 0..90°), n_phi ≥ 1 azimuths."""

    n_theta: int = 8
    n_phi: int = 16

    def __post_init__(self) -> None:
        for k, lo in (("n_theta", 1), ("n_phi", 1)):
            v = getattr(self, k)
            if isinstance(v, bool) or not isinstance(v, int) or v < lo:
                raise ValueError(f"brdf_dirs {k} must be an int >= {lo}, got {v!r}")

    @property
    def size(self) -> int:
        return self.n_theta * self.n_phi

    def directions(self, *, dtype=torch.float64) -> Tensor:
        """(n_theta·n_phi, 3) local unit outgoing directions in table order."""
        th = (torch.arange(self.n_theta, dtype=torch.float64) + 0.5) * (0.5 * math.pi / self.n_theta)
        ph = torch.arange(self.n_phi, dtype=torch.float64) * (2 * math.pi / self.n_phi)
        T, P = torch.meshgrid(th, ph, indexing="ij")
        d = torch.stack([torch.sin(T) * torch.cos(P), torch.sin(T) * torch.sin(P), torch.cos(T)], -1)
        return d.reshape(-1, 3).to(dtype)


# The paper's 64 outgoing directions (§4.1) as an 8 × 8 (θo, φo) grid.
PAPER_BRDF_DIRS = (8, 8)


def brdf_table(material, geo: Geodesic, grid: OutgoingGrid, *, supersample: int = 2,
               dirs_per_chunk: int = 64) -> Tensor:
    """Wavelet coefficients of ρ̃^{ωo}(ωi) = f(ωi, ωo) max(0, cos θi) · Ω_t/A_L for every tabulated ωo.

    Args:
        material: a `scenes.materials.Material` (local-frame ``eval``, no cosine).
        geo: geodesic grid (level L); supersample: 4^s sub-samples per fine triangle.
    Returns:
        (n_o, 3, K) float32, n_o = grid.size, K = 20·4^L.
    """
    wo_all = grid.directions(dtype=torch.float32)
    out = []
    for a in range(0, wo_all.shape[0], dirs_per_chunk):
        wo = wo_all[a:a + dirs_per_chunk]  # (o, 3)

        def fn(c: Tensor, wo=wo) -> Tensor:
            wi = c.float()[:, None, :].expand(-1, wo.shape[0], 3)
            f = material.eval(wi, wo[None].expand_as(wi))  # (P, o, 3)
            cos = wi[..., 2].clamp_min(0.0)[..., None]
            return (f * cos).reshape(c.shape[0], -1)  # (P, o·3)

        co = geo.project(fn, supersample=supersample, solid_angle_weight=True, dtype=torch.float32)
        out.append(co.reshape(wo.shape[0], 3, -1))
    return torch.cat(out, 0)


def outgoing_weights(wo: Tensor, grid: OutgoingGrid) -> tuple[Tensor, Tensor]:
    """Bilinear (θo, φo) weights of local outgoing directions wo (B, 3) over the table.

    Returns idx (B, 4) int64 table rows and w (B, 4) weights (sum 1).
    """
    idx, w = outgoing_terms(wo, grid)
    return torch.stack(idx, -1), torch.stack(w, -1)


def outgoing_terms(wo: Tensor, grid: OutgoingGrid) -> tuple[list[Tensor], list[Tensor]]:
    """`outgoing_weights` as 4 (B,) row tensors and 4 (B,) weight tensors (wo's dtype), unstacked
    (a compiled caller keeps every output a 1-D plane: `fast_eval.grid_lookups`)."""
    if wo.ndim != 2 or wo.shape[1] != 3:
        raise ValueError(f"wo must be (B, 3), got {tuple(wo.shape)}")
    w64 = wo.double()
    theta = torch.acos((w64[:, 2] / w64.norm(dim=-1).clamp_min(1e-30)).clamp(0.0, 1.0))  # clamp at horizon
    phi = torch.remainder(torch.atan2(w64[:, 1], w64[:, 0]), 2 * math.pi)
    fi = (theta / (0.5 * math.pi / grid.n_theta) - 0.5).clamp(0, grid.n_theta - 1)
    fj = phi / (2 * math.pi / grid.n_phi)
    i0 = fi.floor().long().clamp(0, max(grid.n_theta - 2, 0))
    ai = (fi - i0).clamp(0, 1)
    i1 = (i0 + 1).clamp(max=grid.n_theta - 1)
    j0 = fj.floor().long()
    aj = fj - j0
    idx, w = [], []
    for di, wi in ((0, 1 - ai), (1, ai)):
        for dj, wj in ((0, 1 - aj), (1, aj)):
            idx.append((i1 if di else i0) * grid.n_phi + periodic_index(j0 + dj, grid.n_phi))
            w.append((wi * wj).to(wo.dtype))
    return idx, w
