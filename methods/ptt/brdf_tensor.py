"""The BRDF tensor of Sun et al. 2007 §3.2 (eq. 2) and its Tucker factorisation.

    F[h, ωo, ωi] ≈ D ×_h U^h ×_ωo U^ωo ×_ωi U^ωi,
    f(h, ωo, ωi) ≈ Σ_{i,j,k} D(i,j,k) U^h(h,i) U^ωo(ωo,j) U^ωi(ωi,k)          (Sun 2007 eq. 2)

What F holds: the *specular* BRDF values f_h(ωi, ωo) of a BRDF space's sampled materials
(`brdf_space`, ks = 1), **without** the cosine — eq. 1 applies (ωi·n) outside f, and §3.3 puts
the cosine next to U^ωi (T̃⁰ = U^ωi (ω·n) T⁰; C^ωi = ∫ Y_s U^ωi (ω·n)); the diffuse part is
"handled independently of the tensor decomposition" (§4.3). With lobe separation (§4.1,
`lobes.py`) F holds the remainder f_r and the lobe weights a_k(h, ωo) are kept beside it.

Direction parameterisation (§4.3, "orthographic projection from the upper hemisphere onto the unit
disk as in [Wang et al. 2004]"): ω = (x, y, √(1 − x² − y²)) ↦ (x, y). `DiskGrid(n)` samples the
cell centres of an n × n grid on [−1, 1]² that fall inside the unit disk (≈ πn²/4 directions);
the same grid serves ωo and ωi (N_ωo = N_ωi). The grid is symmetric about the origin, so the
mirror direction (−x, −y, z) of a node is a node. Factors are evaluated off the grid by bilinear
interpolation in (x, y). The paper does not give its N_ω; Fig. 5 needs N_ω ≥ 32.

Tucker: `methods.core.tensors` (HOSVD; HOOI through tensorly). `hosvd_error_grid` — the error
grid over (n_h, n_ω) with n_ωo = n_ωi = n_ω (§4.3 "we set n_ωo to be equal to n_ωi") of Fig. 5
(drawn by `methods.ptt.study.fig5`) — is computed, for the truncated HOSVD, from one HOSVD at the
largest ranks: truncated-HOSVD factors of smaller ranks are leading columns
of the same mode-n singular vectors, and for orthonormal factors
‖X − X ×_n U_n U_nᵀ‖² = ‖X‖² − ‖X ×_n U_nᵀ‖² (Pythagoras), i.e. ‖X‖² minus the squared norm of a
leading sub-block of the big core.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import torch
from torch import Tensor

from methods.core import tensors as T
from methods.ptt.brdf_space import BRDFSpace, get_space
from methods.ptt.lobes import LOBE_DEGREES, lobe_basis, separate_lobes

__all__ = [
    "DiskGrid",
    "brdf_tensor",
    "separate_tensor",
    "fit_brdf_tensor",
    "TensorBRDF",
    "build_tensor_brdf",
    "hosvd_error_grid",
    "DEFAULT_RANKS",
]

# Sun 2007 §4.3: n_h = 4 (Cook–Torrance) or 3 (Blinn–Phong), n_ωo = n_ωi = 8.
DEFAULT_RANKS = {"ct": (4, 8, 8), "bp": (3, 8, 8)}


# -- the disk grid ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class DiskGrid:
    """Orthographic hemisphere→unit-disk sampling (Sun 2007 §4.3, Wang et al. 2004).

    n: cells per side of the square [−1, 1]²; nodes are the cell centres with x² + y² < 1,
    ordered row-major (y slowest). Attributes (float64, CPU):
        dirs (N, 3) unit directions; xy (N, 2); solid_angle (N,) = Δ²/z, Δ = 2/n (the orthographic
        Jacobian dω = dx dy / z); index (n, n) node index of cell (iy, ix), −1 outside the disk;
        mirror (N,) index of the node (−x, −y).
    """

    n: int
    dirs: Tensor = field(init=False, repr=False)
    xy: Tensor = field(init=False, repr=False)
    solid_angle: Tensor = field(init=False, repr=False)
    index: Tensor = field(init=False, repr=False)
    mirror: Tensor = field(init=False, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.n, int) or self.n < 2:
            raise ValueError(f"n must be an int >= 2, got {self.n!r}")
        n = self.n
        c = -1.0 + (torch.arange(n, dtype=torch.float64) + 0.5) * (2.0 / n)
        yy, xx = torch.meshgrid(c, c, indexing="ij")
        inside = xx * xx + yy * yy < 1.0
        index = torch.full((n, n), -1, dtype=torch.long)
        index[inside] = torch.arange(int(inside.sum()))
        xy = torch.stack([xx[inside], yy[inside]], dim=-1)
        z = torch.sqrt(1.0 - (xy * xy).sum(-1))
        iy, ix = torch.nonzero(inside, as_tuple=True)
        object.__setattr__(self, "xy", xy)
        object.__setattr__(self, "dirs", torch.cat([xy, z[:, None]], dim=-1))
        object.__setattr__(self, "solid_angle", (2.0 / n) ** 2 / z)
        object.__setattr__(self, "index", index)
        object.__setattr__(self, "mirror", index[n - 1 - iy, n - 1 - ix])  # symmetric grid

    @property
    def N(self) -> int:
        """Number of directions."""
        return self.dirs.shape[0]

    def locate(self, d: Tensor) -> tuple[Tensor, Tensor]:
        """Bilinear interpolation stencil in (x, y) for directions d.

        Args:
            d: (..., 3) unit directions (local frame).
        Returns:
            idx (..., 4) node indices, w (..., 4) weights (float64) summing to 1 — neighbours
            outside the disk are dropped and the rest renormalised; where none is inside (a thin
            band at the rim) the nearest node gets weight 1; directions with z <= 0 get weight 0.
        """
        if d.shape[-1] != 3:
            raise ValueError(f"d must be (..., 3), got {tuple(d.shape)}")
        n = self.n
        p = d.detach().to(torch.float64).cpu().reshape(-1, 3)
        u = (p[:, :2] + 1.0) * (n / 2.0) - 0.5                  # continuous cell coords (x, y)
        i0 = torch.floor(u).long()
        t = u - i0
        idx, w = [], []
        for dy in (0, 1):
            for dx in (0, 1):
                ix, iy = i0[:, 0] + dx, i0[:, 1] + dy
                ok = (ix >= 0) & (ix < n) & (iy >= 0) & (iy < n)
                node = torch.where(ok, self.index[iy.clamp(0, n - 1), ix.clamp(0, n - 1)], -1)
                wt = (t[:, 0] if dx else 1 - t[:, 0]) * (t[:, 1] if dy else 1 - t[:, 1])
                idx.append(node.clamp_min(0))
                w.append(torch.where(node >= 0, wt, torch.zeros_like(wt)))
        idx, w = torch.stack(idx, -1), torch.stack(w, -1)
        s = w.sum(-1, keepdim=True)
        lost = s[:, 0] <= 1e-12
        w = torch.where(lost[:, None], w, w / s.clamp_min(1e-300))
        if lost.any():
            nearest = torch.cdist(p[lost, :2], self.xy).argmin(-1)
            idx[lost] = nearest[:, None].expand(-1, 4)
            w[lost] = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=torch.float64)
        w = torch.where((p[:, 2] > 0)[:, None], w, torch.zeros_like(w))
        shape = d.shape[:-1]
        return idx.reshape(*shape, 4).to(d.device), w.reshape(*shape, 4).to(d.device)

    def interpolate(self, values: Tensor, d: Tensor) -> Tensor:
        """Bilinear interpolation of node values at directions d.

        Args:
            values: (N, C) node values (e.g. a factor U^ωi); d: (..., 3).
        Returns:
            (..., C) in the dtype of `values` (0 for directions below the horizon).
        """
        if values.ndim != 2 or values.shape[0] != self.N:
            raise ValueError(f"values must be ({self.N}, C), got {tuple(values.shape)}")
        idx, w = self.locate(d)
        idx, w = idx.to(values.device), w.to(device=values.device, dtype=values.dtype)
        return (values[idx] * w[..., None]).sum(-2)

    def delta(self, d: Tensor) -> Tensor:
        """Discrete unit-mass Dirac deltas at directions d on this grid (lobes.py, 0° lobe):
        δ_j = (bilinear weight of node j)/Ω_j, so Σ_j Ω_j δ_j = 1.

        Args:
            d: (M, 3). Returns: (M, N) float64.
        """
        idx, w = self.locate(d)
        out = torch.zeros(d.shape[0], self.N, dtype=torch.float64)
        out.scatter_add_(1, idx.cpu(), w.cpu())
        return out / self.solid_angle


# -- building and separating the tensor -------------------------------------------------------


def brdf_tensor(space: BRDFSpace, grid: DiskGrid, *, dtype=torch.float64) -> Tensor:
    """F[h, o, i] = f_h(ωi = grid.dirs[i], ωo = grid.dirs[o]), specular, no cosine (Sun 2007 §3.2).

    Returns:
        (N_h, N, N) tensor of `dtype` (CPU).
    """
    wi = grid.dirs[None, :, :]
    wo = grid.dirs[:, None, :]
    F = torch.empty(space.n_h, grid.N, grid.N, dtype=dtype)
    for h, mat in enumerate(space.materials):
        F[h] = mat.eval(wi, wo)[..., 0].to(dtype)
    return F


def mirror_dirs(grid: DiskGrid) -> Tensor:
    """R(ωo) = (−x, −y, z) for every grid direction ωo: (N, 3) float64."""
    return grid.dirs[grid.mirror]


def separate_tensor(F: Tensor, grid: DiskGrid, *, degrees: Sequence[float] = LOBE_DEGREES,
                    chunk: int = 8) -> tuple[Tensor, Tensor, Tensor]:
    """Lobe separation of a whole BRDF tensor (Sun 2007 §4.1).

    Args:
        F: (N_h, N, N) tensor from `brdf_tensor`; degrees: lobe sizes; chunk: BRDFs per batch.
    Returns:
        F_r (N_h, N, N) remainder (dtype of F), a (N_h, N, K) float64 lobe weights,
        B (N, K, N) float64 lobe basis (f_s = lobes.lobe_values(a, B)).
    """
    if F.ndim != 3 or F.shape[1:] != (grid.N, grid.N):
        raise ValueError(f"F must be (N_h, {grid.N}, {grid.N}), got {tuple(F.shape)}")
    R = mirror_dirs(grid)
    delta = grid.delta(R) if 0 in [float(k) for k in degrees] else None
    B = lobe_basis(grid.dirs, R, degrees=degrees, delta=delta)
    F_r = torch.empty_like(F)
    a = torch.empty(F.shape[0], grid.N, len(degrees), dtype=torch.float64)
    for s in range(0, F.shape[0], chunk):
        fr, ak = separate_lobes(F[s:s + chunk].to(torch.float64), B)
        F_r[s:s + chunk] = fr.to(F.dtype)
        a[s:s + chunk] = ak
    return F_r, a, B


def fit_brdf_tensor(F: Tensor, ranks: Sequence[int], *, method: str = "hooi",
                    n_iter_max: int = 50) -> tuple[Tensor, list[Tensor]]:
    """Tucker factorisation of a BRDF tensor (Sun 2007 eq. 2; De Lathauwer et al. 2000).

    Args:
        F: (N_h, N_ωo, N_ωi); ranks: (n_h, n_ωo, n_ωi); method: "hooi" (HOSVD-initialised HOOI,
        the best rank-(n_h, n_ωo, n_ωi) approximation the paper uses) or "hosvd" (truncated).
    Returns:
        core D (n_h, n_ωo, n_ωi), factors [U^h (N_h, n_h), U^ωo (N_ωo, n_ωo), U^ωi (N_ωi, n_ωi)].
    """
    if F.ndim != 3:
        raise ValueError(f"F must be (N_h, N_wo, N_wi), got {tuple(F.shape)}")
    if method == "hosvd":
        return T.hosvd(F, ranks)
    if method == "hooi":
        return T.tucker(F, ranks, n_iter_max=n_iter_max, tol=1e-9)
    raise ValueError(f"method must be 'hooi' or 'hosvd', got {method!r}")


@dataclass(eq=False)
class TensorBRDF:
    """A factorised BRDF space (Sun 2007 eq. 2) plus its separated lobes (§4.1).

    D (n_h, n_ωo, n_ωi) core; U_h (N_h, n_h); U_o (N, n_ωo); U_i (N, n_ωi) on `grid`;
    a (N_h, N, K) lobe weights per sampled BRDF and view node (None without separation);
    degrees: the lobe sizes k.
    """

    D: Tensor
    U_h: Tensor
    U_o: Tensor
    U_i: Tensor
    grid: DiskGrid
    a: Tensor | None = None
    degrees: tuple[float, ...] = ()

    def U_h_at(self, w: Tensor) -> Tensor:
        """U^h(H, ·) = Σ_h w_h U^h(h, ·): w (..., N_h) from `BRDFSpace.weights` → (..., n_h)."""
        return w.to(self.U_h) @ self.U_h

    def U_o_at(self, wo: Tensor) -> Tensor:
        """U^ωo at view directions: (..., 3) → (..., n_ωo) (bilinear on the disk grid)."""
        return self.grid.interpolate(self.U_o, wo)

    def U_i_at(self, wi: Tensor) -> Tensor:
        """U^ωi at incident directions: (..., 3) → (..., n_ωi) (0 below the horizon)."""
        return self.grid.interpolate(self.U_i, wi)

    def view_factor(self, w: Tensor, wo: Tensor) -> Tensor:
        """Σ_{i,j} D(i,j,k) U^h(H,i) U^ωo(ωo,j) — eq. 3's weights of the incidence components.

        Args:
            w: (N_h,) or (..., N_h) BRDF weights; wo: (..., 3). Returns: (..., n_ωi).
        """
        return torch.einsum("ijk,...i,...j->...k", self.D, self.U_h_at(w), self.U_o_at(wo))

    def eval(self, w: Tensor, wi: Tensor, wo: Tensor) -> Tensor:
        """Tensor part of the BRDF (f_r with separation, else f_spec), eq. 2 at any directions.

        Args:
            w: (N_h,) weights; wi, wo: (..., 3) broadcastable. Returns: (...).
        """
        wi, wo = torch.broadcast_tensors(wi, wo)
        return (self.view_factor(w, wo) * self.U_i_at(wi)).sum(-1)

    def lobe_weights(self, w: Tensor, wo: Tensor) -> Tensor:
        """a_k(H, ωo) = Σ_h w_h a_k(h, ωo), interpolated on the ωo grid: (..., 3) → (..., K)."""
        if self.a is None:
            raise ValueError("this TensorBRDF was built without lobe separation")
        aw = torch.einsum("h,hok->ok", w.to(self.a), self.a)
        return self.grid.interpolate(aw, wo)

    def reconstruct(self) -> Tensor:
        """F̂_r (N_h, N, N) = D ×_h U^h ×_ωo U^ωo ×_ωi U^ωi."""
        return T.tucker_reconstruct(self.D, [self.U_h, self.U_o, self.U_i])

    def memory(self) -> dict[str, int]:
        out = {k: v.numel() * v.element_size() for k, v in
               (("D", self.D), ("U_h", self.U_h), ("U_o", self.U_o), ("U_i", self.U_i))}
        if self.a is not None:
            out["lobe_a"] = self.a.numel() * self.a.element_size()
        return out


def build_tensor_brdf(space: BRDFSpace | str, *, grid_n: int = 24, ranks: Sequence[int] | None = None,
                      separate: bool = True, degrees: Sequence[float] = LOBE_DEGREES,
                      method: str = "hooi", dtype=torch.float32) -> TensorBRDF:
    """Sample a BRDF space on a `DiskGrid(grid_n)`, separate lobes, factorise (Sun 2007 §3.2/§4.1).

    ranks default to `DEFAULT_RANKS[space.kind]` ((4, 8, 8) CT, (3, 8, 8) BP). The result is
    stored in `dtype` (float32 at run time); the fit runs in float64.
    """
    space = get_space(space) if isinstance(space, str) else space
    grid = DiskGrid(grid_n)
    ranks = tuple(DEFAULT_RANKS[space.kind] if ranks is None else ranks)
    F = brdf_tensor(space, grid)
    a = None
    if separate:
        F, a, _ = separate_tensor(F, grid, degrees=degrees)
    D, (U_h, U_o, U_i) = fit_brdf_tensor(F, ranks, method=method)
    cast = lambda x: x.to(dtype)  # noqa: E731
    return TensorBRDF(cast(D), cast(U_h), cast(U_o), cast(U_i), grid,
                      None if a is None else cast(a), tuple(float(k) for k in degrees) if separate else ())


# -- truncation error grid (Fig. 5) -------------------------------------------------------------


def hosvd_error_grid(X: Tensor, n_h: Sequence[int], n_omega: Sequence[int]) -> dict[tuple[int, int], float]:
    """Squared truncated-HOSVD errors ‖X − X̂‖²_F for every (n_h, n_ω), n_ωo = n_ωi = n_ω, from one
    HOSVD at the largest ranks (see module docstring).

    Args:
        X: (N_h, N, N). Returns: {(n_h, n_ω): absolute squared error}.
    """
    X = X.to(torch.float64)
    rh, rw = max(n_h), max(n_omega)
    core, _ = T.hosvd(X, (rh, rw, rw))
    total = float(X.square().sum())
    c2 = core.square()
    return {(a, b): max(total - float(c2[:a, :b, :b].sum()), 0.0) for a in n_h for b in n_omega}
