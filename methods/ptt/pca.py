"""The PCA BRDF basis of the PTTs (Sun et al. 2007 §3.1, §4.3 "Indirect-lighting BRDFs").

"we represent these BRDFs in terms of n_P basis functions computed by PCA on a given BRDF
dataset. The BRDF of a surface region r can then be dynamically changed by adjusting the
coefficients H(r, p)" (§3.1); "five basis functions (four specular and one diffuse) for both the
Cook-Torrance and Blinn-Phong BRDFs, which give a squared reconstruction error of 6.23e-4 and
1.61e-7, respectively ... even though the PCA basis includes specular lobe components" (§4.3).

So the PCA runs on the full specular BRDFs f_h of a BRDF space (no lobe separation), each a
vector over the direction pairs (ωo, ωi) of a `DiskGrid`. We do it through the N_h × N_h Gram
matrix G[h, h'] = Σ_{o,i} W_oi f_h f_h' (never forming the N_h × N² data matrix):

    G = V Λ Vᵀ,  b_p = Σ_h V[h,p] f_h / √λ_p  (orthonormal),  c(h, p) = ⟨f_h, b_p⟩ = √λ_p V[h,p],

(uncentred PCA = SVD of the data matrix; with `center=True` the first specular basis function is
the mean BRDF with coefficient 1 and the others are the leading PCs of the centred data). Every
basis function is a combination Σ_h M[h,p] f_h of the analytic sampled BRDFs, so it can be
evaluated exactly at any direction pair (what the PTT precomputation needs at ray hits).

A region's BRDF kd/π + ks Σ_h w_h f_h (`brdf_space`) is, in this basis,
    H(r, p) = ks · Σ_h w_h c(h, p)   (p < n_spec),      H(r, n_spec) = kd   (b_{n_spec} = 1/π),
per RGB channel — linear in the navigation weights w, which is what makes PTTs work.

Error: `rel_sq_err` = Σ_h ‖f_h − f̂_h‖² / Σ_h ‖f_h‖² over the whole sampled space (the diffuse part
is exact); also `sse`, and `mse` = sse / (N_h · N²). W_oi = 1 ("samples", the discrete norm of the
sampled table, as for Fig. 5) or Ω_o Ω_i ("solid_angle", the L² norm over the hemisphere pair).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from methods.core.threads import torch_threads
from methods.ptt.brdf_space import BRDFSpace, get_space
from methods.ptt.brdf_tensor import DiskGrid

__all__ = ["brdf_gram", "BRDFBasis", "pca_basis", "FamilyPCABasis", "family_pca_basis", "SPACE_OF_KIND",
           "PAPER_PCA_ERROR", "N_SPEC"]

# Sun 2007 §4.3: n_P = 5 = 4 specular + 1 diffuse.
N_SPEC = 4
# Sun 2007 §4.3: squared reconstruction error of the 5-term basis.
PAPER_PCA_ERROR = {"ct": 6.23e-4, "bp": 1.61e-7}


def brdf_gram(space: BRDFSpace, grid: DiskGrid, *, weighting: str = "samples",
              block: int = 16) -> Tensor:
    """G[h, h'] = Σ_{o,i} W_oi f_h(ωi, ωo) f_h'(ωi, ωo) over the grid's direction pairs.

    Args:
        weighting: "samples" (W = 1) or "solid_angle" (W = Ω_o Ω_i); block: ωo per batch.
    Returns:
        (N_h, N_h) float64.
    """
    if weighting not in ("samples", "solid_angle"):
        raise ValueError(f"weighting must be 'samples' or 'solid_angle', got {weighting!r}")
    d, om = grid.dirs, grid.solid_angle
    G = torch.zeros(space.n_h, space.n_h, dtype=torch.float64)
    for s in range(0, grid.N, block):
        wo = d[s:s + block, None, :]
        X = space.eval_samples(d[None, :, :], wo).to(torch.float64)      # (N_h, b, N)
        if weighting == "solid_angle":
            X = X * torch.sqrt(om[s:s + block, None] * om[None, :])
        X = X.reshape(space.n_h, -1)
        with torch_threads(1):  # a long float64 reduction: MKL splits it over the threads on AVX-512
            G += X @ X.T        # machines, and eigh's vectors in near-degenerate spaces follow the bits
    return G


@dataclass(eq=False)
class BRDFBasis:
    """n_P = n_spec + 1 BRDF basis functions for the PTTs (Sun 2007 §3.1/§4.3).

    M (N_h, n_spec): b_p = Σ_h M[h, p] f_h (specular basis over the space's sampled BRDFs);
    C (N_h, n_spec): c(h, p), the coordinates of sampled BRDF h; eigvals (N_h,) of the
    (centred if `center`) Gram matrix, descending; norm2 = Σ_h ‖f_h‖²; basis n_spec is 1/π.

    Implements the `methods.ptt.transport.BRDFBasis` protocol: `n_P`, `eval(wi, wo) -> (..., n_P)`,
    `coords(material) -> (n_P, 3)`.
    """

    space: BRDFSpace
    M: Tensor
    C: Tensor
    eigvals: Tensor
    norm2: float
    n_pairs: int
    center: bool
    weighting: str

    @property
    def n_spec(self) -> int:
        return self.M.shape[1]

    @property
    def n_P(self) -> int:
        return self.n_spec + 1

    def sq_error(self) -> dict[str, float]:
        """Squared reconstruction error of the sampled specular BRDFs in this basis."""
        k = self.n_spec - 1 if self.center else self.n_spec
        sse = float(self.eigvals[k:].clamp_min(0).sum())
        return dict(rel_sq_err=sse / self.norm2, sse=sse, mse=sse / (self.M.shape[0] * self.n_pairs))

    def spec_coords(self, w: Tensor) -> Tensor:
        """Σ_h w_h c(h, ·): w (..., N_h) navigation weights → (..., n_spec)."""
        return w.to(self.C) @ self.C

    def H(self, w: Tensor, *, kd=(0.0, 0.0, 0.0), ks=(1.0, 1.0, 1.0)) -> Tensor:
        """H(r, ·) of one region: w (N_h,) weights, kd, ks RGB (or scalars) → (n_P, 3)."""
        c = self.spec_coords(w)
        ks_t = torch.as_tensor(ks, dtype=c.dtype).expand(3)
        kd_t = torch.as_tensor(kd, dtype=c.dtype).expand(3)
        return torch.cat([c[:, None] * ks_t[None, :], kd_t[None, :]], dim=0)

    def coords(self, material) -> Tensor:
        """H(r, ·) (n_P, 3) float64 for a project material of the space's kind (`scenes.materials`)
        or a `Lambert` (specular coordinates 0)."""
        if not hasattr(material, "ks"):
            return self.H(torch.zeros(self.C.shape[0], dtype=self.C.dtype), kd=material.kd, ks=0.0)
        w, kd, ks = self.space.material_weights(material)
        return self.H(w, kd=kd, ks=ks)

    def eval(self, wi: Tensor, wo: Tensor) -> Tensor:
        """All n_P basis functions b_p(ωi, ωo) (no cosine, 0 below either horizon); the last is 1/π.

        Args:
            wi, wo: (..., 3) broadcastable local directions. Returns: (..., n_P).
        """
        f = self.space.eval_samples(wi, wo)                               # (N_h, ...)
        with torch_threads(1):  # the N_h-long reduction: MKL splits it over the threads on AVX-512
            spec = torch.einsum("hp,h...->...p", self.M.to(f), f)   # machines (factor_basis's SVD follows)
        wi, wo = torch.broadcast_tensors(wi, wo)
        up = ((wi[..., 2] > 0) & (wo[..., 2] > 0)).to(f.dtype)
        return torch.cat([spec, (up / math.pi)[..., None]], dim=-1)

    def reconstruct(self, H: Tensor, wi: Tensor, wo: Tensor) -> Tensor:
        """Σ_p H(p, c) b_p(ωi, ωo): H (n_P, 3), wi, wo (..., 3) → (..., 3)."""
        b = self.eval(wi, wo)
        return b @ H.to(b)


def pca_basis(space: BRDFSpace | str, *, grid_n: int = 16, n_spec: int = N_SPEC,
              center: bool = False, weighting: str = "samples") -> BRDFBasis:
    """PCA of a BRDF space's sampled specular BRDFs over DiskGrid(grid_n)² direction pairs."""
    space = get_space(space) if isinstance(space, str) else space
    if not 1 <= n_spec <= space.n_h:
        raise ValueError(f"n_spec must be in [1, {space.n_h}], got {n_spec}")
    grid = DiskGrid(grid_n)
    G = brdf_gram(space, grid, weighting=weighting)
    norm2 = float(torch.diagonal(G).sum())
    N = space.n_h
    with torch_threads(1):  # MKL's eigh rounds differently with other thread counts (methods.core.threads)
        if center:
            C = torch.eye(N, dtype=G.dtype) - 1.0 / N
            lam, V = torch.linalg.eigh(C @ G @ C)
        else:
            lam, V = torch.linalg.eigh(G)
    lam, V = lam.flip(0), V.flip(1)                                       # descending
    k = n_spec - 1 if center else n_spec
    lam_k = lam[:k].clamp_min(torch.finfo(lam.dtype).tiny)
    M = V[:, :k] / lam_k.sqrt()                                           # b_p = Σ_h M[h,p] f_h
    coords = V[:, :k] * lam_k.sqrt()                                      # c(h,p) = √λ_p V[h,p]
    if center:
        C = torch.eye(N, dtype=G.dtype) - 1.0 / N
        M = torch.cat([torch.full((N, 1), 1.0 / N, dtype=G.dtype), C @ M], dim=1)
        coords = torch.cat([torch.ones(N, 1, dtype=G.dtype), coords], dim=1)
    return BRDFBasis(space, M, coords, lam, norm2, grid.N * grid.N, center, weighting)


# Which BRDF space (`brdf_space.get_space`) navigates which material family (`Material.kind`).
SPACE_OF_KIND = {"blinnphong": "bp", "cooktorrance": "ct", "phong": "phong"}


class FamilyPCABasis:
    """The PCA bases of several BRDF families behind one diffuse function: the PTT basis of a scene
    whose regions use more than one family (Sun 2007 uses one space per scene — Blinn-Phong *or*
    Cook-Torrance; `chess` has Blinn-Phong, Cook-Torrance and Phong regions).

    b = [b^(f1)_0 .. b^(f1)_{n1−1}, b^(f2)_0 .., …, 1/π]: the specular functions of each family's
    `BRDFBasis` in the order of ``bases``, then the shared Lambert function (last, as in
    `BRDFBasis`). A material of family f gets H = its own basis' coordinates in f's block and kd
    in the last row, 0 elsewhere — linear in the navigation weights, so any point of the space
    (shininess 1..200, a Cook-Torrance point in the hull) is a run-time change of H only.
    Implements the `transport.BRDFBasis` protocol.
    """

    def __init__(self, bases: dict[str, BRDFBasis]) -> None:
        if not bases:
            raise ValueError("FamilyPCABasis needs at least one family basis")
        self.bases = dict(bases)
        self.offsets: dict[str, int] = {}
        o = 0
        for kind, b in self.bases.items():
            if not isinstance(b, BRDFBasis):
                raise ValueError(f"basis of {kind!r} must be a pca.BRDFBasis, got {b!r}")
            self.offsets[kind] = o
            o += b.n_spec
        self.n_P = o + 1

    def __repr__(self) -> str:
        return ("FamilyPCABasis(" + ", ".join(f"{k}: {b.space.kind} n_spec={b.n_spec}" for k, b in self.bases.items())
                + ")")

    def sq_error(self) -> dict[str, float]:
        """Relative squared PCA reconstruction error of each family's sampled space."""
        return {k: b.sq_error()["rel_sq_err"] for k, b in self.bases.items()}

    def eval(self, wi: Tensor, wo: Tensor) -> Tensor:
        """b_p(wi, wo): (..., 3) local directions → (..., n_P); no cosine, 0 below either horizon."""
        parts = [b.eval(wi, wo) for b in self.bases.values()]
        return torch.cat([p[..., :-1] for p in parts] + [parts[0][..., -1:]], dim=-1)

    def coords(self, material) -> Tensor:
        """H (n_P, 3) float64 of a Lambert or a material of one of the families (ValueError else,
        and for a point outside its space: shininess outside the samples, CT outside the hull)."""
        H = torch.zeros(self.n_P, 3, dtype=torch.float64)
        if not hasattr(material, "ks"):
            H[-1] = torch.as_tensor(material.kd, dtype=torch.float64)
            return H
        kind = material.kind
        if kind not in self.bases:
            raise ValueError(f"the PCA basis covers the families {sorted(self.bases)}, not {kind!r}")
        h = self.bases[kind].coords(material)
        o = self.offsets[kind]
        H[o:o + h.shape[0] - 1] = h[:-1]
        H[-1] = h[-1]
        return H


def family_pca_basis(materials, *, n_spec: int = N_SPEC, grid_n: int = 16, center: bool = False,
                     weighting: str = "samples") -> FamilyPCABasis:
    """A `FamilyPCABasis` with one n_spec-term PCA basis (`pca_basis`, default spaces of
    `brdf_space.get_space`) per specular family among ``materials`` (a dict or a sequence;
    Lambert needs none). ValueError for a family without a BRDF space (see `SPACE_OF_KIND`)."""
    mats = list(materials.values()) if isinstance(materials, dict) else list(materials)
    kinds = []
    for m in mats:
        if not hasattr(m, "ks"):
            continue
        if m.kind not in SPACE_OF_KIND:
            raise ValueError(f"no BRDF space for the {m.kind!r} family (PCA basis families: "
                             f"{', '.join(sorted(SPACE_OF_KIND))})")
        if m.kind not in kinds:
            kinds.append(m.kind)
    if not kinds:  # an all-Lambert scene: keep one specular family so the basis is not empty
        kinds = ["blinnphong"]
    return FamilyPCABasis({k: pca_basis(SPACE_OF_KIND[k], grid_n=grid_n, n_spec=n_spec, center=center,
                                        weighting=weighting) for k in kinds})
