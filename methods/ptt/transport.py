"""Direct-lighting wavelet transport of the PTT method (Sun et al. 2007 §3.1, §3.3 "Direct
Lighting", §4.3) and the BRDF-side plumbing it needs.

The BRDF side is *pluggable*. Everything here takes a region's BRDF as RGB coordinates H(r, p, c)
over a small basis of scalar BRDFs b_p(ωi, ωo), p = 1..n_P (Sun §3.1: "we represent these BRDFs in
terms of n_P basis functions computed by PCA"):

    f_r(ωi, ωo)[c] = Σ_p H(r, p, c) b_p(ωi, ωo).                                   (Sun §3.1)

Any object with the `BRDFBasis` protocol (``n_P``, ``eval(wi, wo) -> (..., n_P)``,
``coords(material) -> (n_P, 3)``) can be used, e.g. the PCA basis of ``methods.ptt.pca``.
`LobeBasis` is the analytic stand-in: a Lambert term plus unit-weight specular lobes of given
materials (exact coordinates for materials built from those lobes, least squares otherwise).

Shading factorization. Eq. 3 needs the BRDF factored into an incident-direction factor U^{ωi}(ω, k)
shared by *all* BRDFs and a per-BRDF view factor. Until the Tucker factors of
``methods.ptt.brdf_tensor`` (eq. 2) are plugged in, `factor_basis` builds them from the basis
itself, like Mahajan 2008 / Kautz–McCool but with the ωi factor shared over all (p, ωo):
the matrix M[(p, ωo_j), ωi_i] = b_p(ωi_i, ωo_j) on an orthographic hemisphere→disk grid
(Sun §4.3, Wang 2004) is weighted by √dω·cos^γ θ on both sides (γ = COS_POWER = 0.5) and SVD'd,
A = a M c = U S Vᵀ. Without the cosines the grazing 1/(cos θi cos θo) growth of Cook–Torrance
dominates the fit (measured on `chess`: the image goes black); γ = 1 costs the `alcove` direct
image 2 % of its mean, γ = 0.5 nothing. Then

    b_p(ωi, ωo) ≈ Σ_k W(p, ωo, k) U^{ωi}(ωi, k),                               (Sun eq. 2 with h ≡ p)
    U^{ωi}(ω, k) = Σ_r U[r, k] a_r M[r, ω] / S_k     (the SVD identity: defined at *any* ω),
    W(p, ωo, k)  = ∫ b_p(ωi, ωo) U^{ωi}(ωi, k) dωi   (= U S / a on the grid rows),

U^{ωi}(ω, k)·cos θ (bounded up to the horizon) and W are tabulated on a fine azimuthal-equidistant
table ((x, y) = θ/(π/2)·(cos φ, sin φ), smooth through the horizon, unlike the orthographic disk
whose √(1 − r²) rim bilinear interpolation gets wrong) and looked up bilinearly; every consumer (T̃⁰, C^{ωi}) needs U^{ωi} only times the cosine.
The view factor of a region is then
Σ_p H(r, p, c) W(p, ωo, k) (the role of D ×_h U^h ×_ωo U^{ωo} in eq. 3).

Direct transport (§3.3, §4.3). Per vertex x, on a world-frame cube map (6×N×N, Haar basis of
``methods.core.cubemap``):

    T̃⁰_x(ω, k) = U^{ωi}(ω_local, k) (ω·n_x) V_x(ω),       U^{I0}_x(l, k) = ∫ L_l T̃⁰_x dω,

texel values ∫_texel T̃⁰ dω ≈ T̃⁰(centre)·Ω_texel Haar-transformed; the n_L largest area-weighted
coefficients per k are kept (Ng 2003; paper n_L = 96 at 6×64×64). Because the Haar basis is
orthonormal in the texel-count measure, Σ_l C^L_l U^{I0}(l, k) with C^L the Haar coefficients of the
texel-mean radiance equals Σ_texels L̄ ∫_texel T̃⁰ dω exactly.

Coarse lighting for the bounces (§4.3: 6×8×8 for one bounce, 6×2×2 for two). The coarse wavelets
are the top-left n×n block of every face in the in-place Haar layout of the fine map: keeping only
them is the orthogonal projection onto per-face n×n piecewise constants, so a coarse PTT and the
run-time lighting both use the *same fine-layout coefficients* of that block (`block_index`) and
no rescaling is needed. `direct_transport` also returns the untruncated block of T̃⁰ per vertex
(the input of the one-bounce PTT, ``methods.ptt.bounce``).

Local frames. All local quantities use the frame of ``methods.core.frames`` at a *vertex*. Values
that live in a vertex's frame (U^{I}, SH of incident radiance) are never interpolated across
vertices; per-vertex results are evaluated in each vertex's own frame and the scalar results are
interpolated (see ``methods.ptt.method``), which stays right where the frame flips (n.z = 0).
"""
from __future__ import annotations

import dataclasses
import math
import sys
from dataclasses import dataclass
from typing import Any, Protocol, Sequence, runtime_checkable

import torch
import torch.nn.functional as Fnn
from torch import Tensor

from methods.core import cubemap
from methods.core import sh as _sh
from methods.core.frames import to_local
from methods.core.sampling import fibonacci_hemisphere
from methods.core.stable import canonical_svd, keep_largest
from methods.core.threads import torch_threads
from methods.core.visibility import Visibility, vertex_visibility
from scenes import materials as _mat

__all__ = [
    "BRDFBasis", "LobeBasis", "scene_basis", "BasisFactors", "factor_basis", "disk_grid",
    "sh_light_matrix", "uniform_light_vector", "block_index", "env_cube", "env_haar", "DirectTransport",
    "direct_transport", "direct_incidence", "ray_points",
]

# Smallest cos θ used for grid cells on / outside the disk rim (their directions are put just
# above the horizon so that bilinear look-ups near the rim see sensible values).
RIM_Z = 1e-3
# Sub-samples per side used to integrate dω = dx dy / z over one disk-grid cell (the 1/z
# singularity at the rim is integrable; 8×8 gets each cell's solid angle to < 1 % except the rim).
CELL_SUB = 8


# -- the BRDF basis ------------------------------------------------------------------------------


@runtime_checkable
class BRDFBasis(Protocol):
    """A small linear basis of scalar BRDFs b_p (Sun 2007 §3.1, H(r, p) its coordinates).

    n_P: number of basis BRDFs.
    eval(wi, wo): wi, wo (..., 3) local unit directions → (..., n_P) values b_p(wi, wo), no cosine,
        0 below either horizon.
    coords(material): (n_P, 3) RGB coordinates H(·, c) of a ``scenes.materials.Material``.
    """

    n_P: int

    def eval(self, wi: Tensor, wo: Tensor) -> Tensor: ...

    def coords(self, material: Any) -> Tensor: ...


def _lobe_key(material: Any) -> tuple:
    """(type, the lobe parameters) of a material of a `lobe_grid.FAMILIES` type: (s,) or (m, F0) — the
    fields of ``_spec_lobe(material)`` beside kd and ks, so two such materials' unit lobes are equal
    (``==``) exactly when their keys are."""
    if type(material) is _mat.CookTorrance:
        return (_mat.CookTorrance, (material.m, material.F0))
    return (type(material), (material.s,))


def _spec_lobe(material: Any) -> Any | None:
    """The material's specular lobe with unit weight and no diffuse term (None for Lambert)."""
    p = dict(material.params())
    if "ks" not in p:
        return None
    p["kd"] = [0.0, 0.0, 0.0]
    p["ks"] = [1.0, 1.0, 1.0]
    return type(material).from_params(p)


class LobeBasis:
    """Analytic BRDF basis: b_0 = 1/π (Lambert) and b_p = unit-weight specular lobe p.

    Args:
        lobes: specular-lobe materials (their kd is ignored, ks set to 1), e.g.
            ``[BlinnPhong(0, 1, 8), BlinnPhong(0, 1, 32)]``.
        diffuse: include the Lambert basis function (index 0).
        fit_res: disk-grid resolution of the least-squares fit used by `coords` for materials that
            are not an exact combination of the basis.
    """

    def __init__(self, lobes: Sequence[Any], *, diffuse: bool = True, fit_res: int = 16) -> None:
        self.lobes = [_spec_lobe(m) for m in lobes]
        if any(l is None for l in self.lobes):
            raise ValueError("every lobe must be a material with a specular term (ks)")
        self.diffuse = bool(diffuse)
        self.n_P = len(self.lobes) + int(self.diffuse)
        if self.n_P == 0:
            raise ValueError("the basis is empty")
        self.fit_res = int(fit_res)
        self._fold = None  # `_fit`'s grid, lobe evaluator and normal equations, built on first use

    def __repr__(self) -> str:
        return f"LobeBasis(diffuse={self.diffuse}, lobes={[l.params() for l in self.lobes]})"

    def eval(self, wi: Tensor, wo: Tensor) -> Tensor:
        """b_p(wi, wo): wi, wo (..., 3) → (..., n_P)."""
        if wi.shape[-1] != 3 or wo.shape[-1] != 3:
            raise ValueError(f"wi, wo must be (..., 3), got {tuple(wi.shape)}, {tuple(wo.shape)}")
        wi, wo = torch.broadcast_tensors(wi, wo)
        out = []
        if self.diffuse:
            up = (wi[..., 2] > 0) & (wo[..., 2] > 0)
            out.append(torch.where(up, torch.full_like(wi[..., 2], 1.0 / math.pi), torch.zeros_like(wi[..., 2])))
        for l in self.lobes:
            out.append(l.eval(wi, wo)[..., 0])
        return torch.stack(out, -1)

    def coords(self, material: Any) -> Tensor:
        """(n_P, 3) float64 H(·, c): exact for Lambert + one of the lobes, else a least-squares fit."""
        H = torch.zeros(self.n_P, 3, dtype=torch.float64)
        kd = torch.tensor(material.kd, dtype=torch.float64)
        lobe = _spec_lobe(material)
        if not self.diffuse and bool((kd != 0).any()):
            return self._fit(material, lobe)
        if lobe is not None:
            j = next((i for i, l in enumerate(self.lobes) if l == lobe), None)
            if j is None:
                return self._fit(material, lobe)
            H[int(self.diffuse) + j] = torch.tensor(material.ks_rgb, dtype=torch.float64)
        if self.diffuse:
            H[0] = kd
        return H

    def coords_rows(self, material: Any) -> list[list[float]] | None:
        """`coords` (material) as (n_P, 3) nested Python floats — the same float64 values (tested bit for
        bit) — or None where it does not apply (no diffuse function; a material whose type is not exactly
        Lambert or a `lobe_grid.FAMILIES` one: call `coords`).

        Session 40 (pt40): a chess bench VB frame fits three changed materials on one thread, serial in
        a 2-thread frame, and `coords` spent most of its time around the lobe projection (building the
        unit lobe material with its validation, comparing it with the basis lobes, a dozen small
        float64 tensor ops per material, then the float32 conversion and the stack). Here the unit
        lobe is the material's own parameters (its type and the fields beside kd / ks: what
        ``_spec_lobe``'s copy holds, validated already), the lobe is projected by
        `GridLobes.project_family` (the same ops) and H = g_d kd + g_s ks is formed in Python floats
        (IEEE float64 products and sums, no fused multiply-add: the tensor ops' roundings)."""
        kind = type(material)
        if not self.diffuse:
            return None
        from methods.ptt import lobe_grid as _lg

        kd = material.kd
        if kind is _mat.Lambert:
            return [list(kd)] + [[0.0, 0.0, 0.0] for _ in range(self.n_P - 1)]
        fam = _lg.FAMILIES.get(kind)
        if fam is None:
            return None
        key = _lobe_key(material)
        keys = self.__dict__.get("_lobe_keys")
        if keys is None:
            keys = self._lobe_keys = [_lobe_key(l) for l in self.lobes]
        ks = material.ks_rgb
        if key in keys:  # the exact lobe: H = kd on b_0, ks on its function
            j = keys.index(key)
            rows = [list(kd)] + [[0.0, 0.0, 0.0] for _ in range(self.n_P - 1)]
            rows[1 + j] = list(ks)
            return rows
        grid, A, g_d = self.prepare()
        gd = self.__dict__.get("_gd_rows")
        if gd is None or gd[0] is not g_d:
            gd = self._gd_rows = (g_d, g_d[:, 0].tolist())
        gs = grid.project_family(fam, A, *key[1], as_list=True)
        return [[a * kd[0] + b * ks[0], a * kd[1] + b * ks[1], a * kd[2] + b * ks[2]] for a, b in zip(gd[1], gs)]

    def _fit(self, material: Any, lobe: Any = False) -> Tensor:
        """Least squares over disk-grid pairs, weight cosθi dωi dωo (error in reflected radiance).
        Every material is kd/π + ks·lobe (``scenes.materials.Material.eval``) and the fit is
        linear, so H = g_d ⊗ kd + g_s ⊗ ks with g_d = G⁻¹Bᵀ(1/π) fitted once and g_s = G⁻¹Bᵀ lobe
        from one evaluation of the unit-weight lobe (`_spec_lobe`): a changed material costs
        one scalar lobe evaluation on the grid (the run time's BRDF navigation, Sun §3.1).

        The lobe is evaluated on the pairs o <= i only and mirrored: every family a LobeBasis takes
        (Phong in Mahajan's normalised form, Blinn-Phong, Cook-Torrance, ... — physically based
        BRDFs) is reciprocal, f(ωi, ωo) = f(ωo, ωi), and both directions of a pair come from the
        same grid. Half the evaluations: a chess bench VB frame fits three changed materials, 8.9
        → 4.6 ms (1 thread, CPU time); the mirrored values equal the evaluated ones to float64
        round-off (Cook-Torrance's ωo·h vs ωi·h). The mirroring is folded into the normal
        equations' right-hand side: Bᵀ(f·wt) = M f_u with M[:, (o, i)] = B(o, i) wt(o, i) +
        B(i, o) wt(i, o) (once on the diagonal), built once — no n×n scatter per material.

        The lobe itself is evaluated by ``methods.ptt.lobe_grid.GridLobes`` (its direction-only
        factors cached on the pairs; bit-identical to the material's own ``eval``). Together,
        same process against the material's ``eval`` + n×n scatter (1 thread, CPU time, median of 11
        frames of perturbed materials, loaded 2-core machine; ``python -m benchmarks.ptt_fit``): one
        frame's fits chess bench 9.7 → 1.9 ms (×5.2), creature 3.0 → 0.8 ms (×3.9); the
        coordinates differ from the unfolded fit by float64 round-off (≤ 5e-14 relative).

        A f_u is `GridLobes.project` (session 22): the lobe evaluated once per distinct value of its
        direction factor (2.5–3.5 K of the 25 200 pairs) against A's columns summed per value
        (built in `prepare`); the coordinates equal A @ eval to float64 round-off."""
        grid, A, g_d = self.prepare()
        H = g_d * torch.tensor(material.kd, dtype=torch.float64)[None, :]
        if lobe is False:  # not passed by `coords`
            lobe = _spec_lobe(material)
        if lobe is not None:
            g_s = grid.project(lobe, A)[:, None]  # G⁻¹ M f_u (`prepare`), f_u the unit-ks lobe on the pairs o <= i
            H = H + g_s * torch.tensor(material.ks_rgb, dtype=torch.float64)[None, :]
        return H

    def prepare(self) -> tuple:
        """The fit's static part (`_fit`): the lobe evaluator on the grid pairs o <= i, the folded
        normal equations' operator A = G⁻¹ M (P, pairs) (M the folded matrix, G the Gram matrix) and
        g_d; built once (the first `_fit`, or a renderer's warm-up frame: ``PTT.render`` calls it on
        its first frame so that the first changed material of a timed frame does not pay it).

        G⁻¹ is applied to M once here (`_solve` with the P·pairs right-hand sides), so a changed
        material's fit is one matrix-vector product A f_u instead of a gelsd solve of G per material
        (~0.1–0.25 ms each, three per chess bench VB frame): the same coordinates up to float64
        round-off times G's condition (G⁻¹(M f) vs (G⁻¹M) f). Same process, alternating, 1 thread,
        process CPU time, load 10–17 (``python -m benchmarks.ptt_fit --base OTHER_CHECKOUT --frames
        15``): one frame's fits chess bench 1.58 → 1.15 ms (×1.37), creature 0.49 → 0.41 ms (×1.20);
        max relative |old − new| of the coordinates 2.3e-14 (the float32 H, and so the images,
        bit-identical on the bench VB frames)."""
        fold = getattr(self, "_fold", None)
        if fold is None:
            from methods.ptt.lobe_grid import GridLobes

            dirs, w = disk_grid(self.fit_res)
            inside = w > 0
            d, w = dirs[inside], w[inside]
            wi, wo = d[None, :, :], d[:, None, :]
            wt = (w[None, :] * d[None, :, 2] * w[:, None]).sqrt()  # (o, i)
            B = self.eval(wi, wo) * wt[..., None]  # (o, i, P)
            Bf = B.reshape(-1, self.n_P)
            with torch_threads(1):  # float64 products with a long reduction: MKL splits it over the
                G = Bf.T @ Bf       # threads on AVX-512 machines (methods.core.threads); built once
                g_d = _solve(G, Bf.T @ (wt.reshape(-1, 1) / math.pi))  # (P, 1)
            o, i = torch.triu_indices(d.shape[0], d.shape[0])  # the pairs o <= i
            Bw = B * wt[..., None]
            M = Bw[o, i] + torch.where((o != i)[:, None], Bw[i, o], torch.zeros_like(Bw[i, o]))  # (pairs, P)
            grid = GridLobes(d[i], d[o])
            with torch_threads(1):
                A = _solve(G, M.T.contiguous()).contiguous()  # (P, pairs)
            for lobe in self.lobes:  # the direction-only factors of the basis's families and A summed per
                grid.project(lobe, A)  # factor value (a changed material keeps its family:
                #                        scenes.sequences.perturb_material)
            fold = self._fold = (grid, A, g_d)
        return fold


def _solve(G: Tensor, rhs: Tensor) -> Tensor:
    """G⁻¹ rhs by gelsd (SVD) on one thread: the default gelsy's answer varies from call to call in
    the last bits, and LAPACK's with the thread count (methods.core.threads)."""
    with torch_threads(1):
        return torch.linalg.lstsq(G, rhs, driver="gelsd").solution


def scene_basis(materials: dict[str, Any] | Sequence[Any]) -> LobeBasis:
    """Lambert + the distinct unit-weight specular lobes of the given materials (exact coordinates
    for those materials; perturbed ones are fitted by least squares)."""
    mats = list(materials.values()) if isinstance(materials, dict) else list(materials)
    lobes = []
    for m in mats:
        l = _spec_lobe(m)
        if l is not None and l not in lobes:
            lobes.append(l)
    return LobeBasis(lobes, diffuse=True)


# -- the shared incident-direction factorization ----------------------------------------------

# γ of the SVD weights √dω·cos^γ θ on both directions (module docstring).
COS_POWER = 0.5


def disk_grid(G: int, *, dtype=torch.float64) -> tuple[Tensor, Tensor]:
    """Orthographic hemisphere→unit-disk grid (Sun §4.3, Wang 2004): G×G cells on [−1, 1]².

    Returns:
        dirs (G, G, 3) local unit directions of the cell centres (cells whose centre lies outside
        the disk get the rim direction at their azimuth, z = RIM_Z), indexed [row = y, col = x];
        weights (G, G) solid angle of the part of the cell inside the disk (0 outside), Σ = 2π.
    """
    if int(G) != G or G < 2:
        raise ValueError(f"grid resolution must be an int >= 2, got {G}")
    G = int(G)
    c = (torch.arange(G, dtype=torch.float64) + 0.5) * (2.0 / G) - 1.0
    y, x = torch.meshgrid(c, c, indexing="ij")
    r = torch.sqrt(x * x + y * y)
    scale = torch.where(r > 1.0 - RIM_Z, (1.0 - RIM_Z) / r.clamp_min(1e-12), torch.ones_like(r))
    x2, y2 = x * scale, y * scale
    z = torch.sqrt((1.0 - x2 * x2 - y2 * y2).clamp_min(RIM_Z * RIM_Z))
    dirs = torch.stack([x2, y2, z], -1)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    # cell solid angle: ∫∫ dx dy / z over the sub-samples inside the disk
    s = (torch.arange(CELL_SUB, dtype=torch.float64) + 0.5) / CELL_SUB * (2.0 / G) - 1.0 / G
    sy, sx = torch.meshgrid(s, s, indexing="ij")
    px, py = x[..., None, None] + sx, y[..., None, None] + sy
    rr = px * px + py * py
    zz = torch.sqrt((1.0 - rr).clamp_min(0.0))
    inside = rr < 1.0
    dA = (2.0 / G / CELL_SUB) ** 2
    w = torch.where(inside, dA / zz.clamp_min(1e-2 / G), torch.zeros_like(zz)).sum((-1, -2))
    w = w * (2.0 * math.pi / w.sum())
    return dirs.to(dtype), w.to(dtype)


def table_grid(T: int, *, dtype=torch.float64) -> Tensor:
    """Directions (T, T, 3) of the cell centres of the azimuthal-equidistant look-up table:
    cell (row, col) ↦ (u, v) = texel centre in [−1, 1]², θ = min(|(u, v)|, 1)·π/2 (cells beyond the
    unit circle repeat the horizon, θ → π/2), φ = atan2(v, u)."""
    c = (torch.arange(T, dtype=torch.float64) + 0.5) * (2.0 / T) - 1.0
    v, u = torch.meshgrid(c, c, indexing="ij")
    r = torch.sqrt(u * u + v * v)
    theta = r.clamp_max(1.0 - RIM_Z) * (math.pi / 2)
    s = torch.sin(theta) / r.clamp_min(1e-12)
    return torch.stack([u * s, v * s, torch.cos(theta)], -1).to(dtype)


def table_coords(d: Tensor) -> Tensor:
    """Inverse of `table_grid`: directions (..., 3) → table coordinates (..., 2) in [−1, 1]²."""
    rho = torch.sqrt(d[..., 0] ** 2 + d[..., 1] ** 2)
    theta = torch.atan2(rho, d[..., 2])
    s = theta / (math.pi / 2) / rho.clamp_min(1e-12)
    s = torch.where(rho > 1e-12, s, torch.full_like(s, 2.0 / math.pi))  # θ/ρ → 1 at the pole
    return torch.stack([d[..., 0] * s, d[..., 1] * s], -1)


@dataclass
class BasisFactors:
    """Shared incident factor and per-basis view factors of a BRDF basis (Sun eq. 2, h ≡ p).

    U_tab: (K, T, T) U^{ωi}·cos θ on the T×T disk table ([k, row = y, col = x]).
    W_tab: (n_P·K, T, T) W(p, ωo, k) on the same table (channel p·K + k).
    sigma: (K,) singular values (reporting). captured: Σ_{k≤K} S_k² / Σ S_k².
    """

    U_tab: Tensor
    W_tab: Tensor
    sigma: Tensor
    captured: float
    n_P: int

    @property
    def K(self) -> int:
        return int(self.U_tab.shape[0])

    @staticmethod
    def _lookup(tab: Tensor, d: Tensor) -> Tensor:
        """Bilinear look-up of (C, T, T) (`table_grid` layout) at local directions d (..., 3) →
        (..., C); 0 for z <= 0."""
        shp = d.shape[:-1]
        g = table_coords(d.reshape(1, 1, -1, 3)).to(tab.dtype)
        out = Fnn.grid_sample(tab[None], g, mode="bilinear", padding_mode="border", align_corners=False)
        # contiguous rows: ``torch.bmm`` of batches with a batch stride of 1 (the transposed view)
        # rounds differently with 1 and 2 threads (methods.core.threads)
        out = out[0, :, 0, :].T.contiguous().reshape(*shp, tab.shape[0])
        return out * (d[..., 2:3] > 0).to(out.dtype)

    def Ucos(self, wi: Tensor) -> Tensor:
        """U^{ωi}(wi, k)·cos θi: wi (..., 3) local → (..., K) (0 below the horizon)."""
        return self._lookup(self.U_tab, wi)

    def U(self, wi: Tensor) -> Tensor:
        """U^{ωi}(wi, k) = `Ucos` / cos θi: (..., 3) → (..., K) (ill-conditioned at the horizon)."""
        return self.Ucos(wi) / wi[..., 2:3].clamp_min(RIM_Z).to(self.U_tab.dtype)

    def W(self, wo: Tensor) -> Tensor:
        """W(p, wo, k): wo (..., 3) local → (..., n_P, K)."""
        return self._lookup(self.W_tab, wo).unflatten(-1, (self.n_P, self.K))

    def brdf(self, wi: Tensor, wo: Tensor) -> Tensor:
        """Reconstructed basis BRDFs Σ_k W(p, wo, k) U(wi, k): (..., 3) each → (..., n_P)."""
        return (self.W(wo) * self.U(wi)[..., None, :]).sum(-1)

    def to(self, dtype=None, device=None) -> "BasisFactors":
        return dataclasses.replace(self, U_tab=self.U_tab.to(dtype=dtype, device=device),
                                   W_tab=self.W_tab.to(dtype=dtype, device=device))


def factor_basis(basis: BRDFBasis, *, n_wi: int = 16, grid: int = 24, table: int = 48,
                 cos_power: float = COS_POWER, n_wo: int | None = None, dtype=torch.float32) -> BasisFactors:
    """Factor every basis BRDF with one shared incident factor (module docstring).

    Args:
        basis: a `BRDFBasis`.
        n_wi: K, number of incident factors (paper n_{ωi} = 8).
        grid: disk-grid resolution of the SVD (grid² directions for ωi and for ωo).
        table: resolution of the look-up tables of U^{ωi} and W.
        n_wo: None = the view mode at full table resolution; else the rank n_{ωo} of the view mode
            (paper 8): W(p, ωo, k) ≈ Σ_j D(p, k, j) U^{ωo}(ωo, j), the best weighted-L2 rank-n_{ωo}
            approximation over ωo of the (p, k) vectors (SVD on the grid with the same √dω·cos^γ
            row weights): the three-mode Tucker form D ×_h H ×_{ωo} U^{ωo} ×_{ωi} U^{ωi} of Sun eq. 2–3
            with the h mode = the basis. The truncated W is stored on the table (Q Qᵀ W).
    """
    for k, v in (("n_wi", n_wi), ("grid", grid), ("table", table)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"{k} must be a positive int, got {v!r}")
    if n_wo is not None and (isinstance(n_wo, bool) or not isinstance(n_wo, int) or n_wo < 1):
        raise ValueError(f"n_wo must be a positive int or None, got {n_wo!r}")
    P = int(basis.n_P)
    d, w = disk_grid(grid)
    inside = w > 0
    d, w = d[inside], w[inside]  # (D, 3), (D,)
    D = d.shape[0]
    M = basis.eval(d[None, :, :].expand(D, D, 3), d[:, None, :].expand(D, D, 3)).double()  # (o, i, P)
    M = M.permute(2, 0, 1).reshape(P * D, D)  # rows (p, ωo_j), cols ωi_i
    a = (w.sqrt() * d[:, 2] ** cos_power).repeat(P)  # row weights √dωo cos^γ θo
    c = w.sqrt() * d[:, 2] ** cos_power              # column weights √dωi cos^γ θi
    A = a[:, None] * M * c[None, :]
    # the singular vectors of the equal singular-value pairs of isotropic lobes (cos mφ, sin mφ)
    # are any basis of their pair's plane, chosen by round-off (thread count and the machine's
    # instruction set); the per-k Haar truncation of the transport (n_L per k) depends on which:
    # `canonical_svd` makes the vectors a function of the pair's plane (methods.core.stable)
    U, S, _ = canonical_svd(A)
    K = min(n_wi, int((S > S[0] * 1e-10).sum()))
    U, S_k = U[:, :K], S[:K]
    captured = float((S_k.square().sum() / S.square().sum()).item())
    coef = U * a[:, None] / S_k  # (P·D, K): U^{ωi}(ω, k) = Σ_r coef[r, k] M[r, ω]

    td = table_grid(table)
    T = table
    td_flat = td.reshape(-1, 3)
    # U^{ωi} on the table: M at (ωi = table dir, ωo = grid dir) for every row r = (p, j)
    d32, td32 = d.float(), td_flat.float()  # the two big evaluations in float32 (≈ 2× faster)
    Mt = basis.eval(td32[None, :, :].expand(D, -1, 3), d32[:, None, :].expand(D, td32.shape[0], 3)).double()
    Mt = Mt.permute(2, 0, 1).reshape(P * D, -1)  # (P·D, T²)
    U_tab = ((coef.T @ Mt) * td_flat[:, 2]).reshape(K, T, T)  # U^{ωi}·cos θ
    # W(p, ωo, k) = Σ_i b_p(ωi_i, ωo) c_i² U^{ωi}(ωi_i, k) with U^{ωi} on the SVD grid (= U S / a on rows)
    U_grid = coef.T @ M  # (K, D)
    Bt = basis.eval(d32[None, :, :].expand(td32.shape[0], D, 3), td32[:, None, :].expand(-1, D, 3)).double()  # (t, i, P)
    W_tab = torch.einsum("tip,i,ki->pkt", Bt, c * c, U_grid).reshape(P * K, T, T)
    if n_wo is not None and n_wo < P * K:  # Sun eq. 2: rank-n_ωo view mode (docstring)
        Wg = (U * S_k / a[:, None]).reshape(P, D, K).permute(1, 0, 2).reshape(D, P * K)  # W on the grid
        _, _, Vh = canonical_svd(Wg * (w.sqrt() * d[:, 2] ** cos_power)[:, None])  # as above
        Q = Vh[:n_wo].T  # (P·K, n_ωo): D(p, k, j)
        W_tab = (Q @ (Q.T @ W_tab.reshape(P * K, T * T))).reshape(P * K, T, T)
    return BasisFactors(U_tab.to(dtype), W_tab.to(dtype), S_k.to(dtype), captured, P)


def sh_light_matrix(factors: BasisFactors, order: int = 4, *, n_quad: int = 8192) -> Tensor:
    """C^{ωi}(s, k) = ∫_{H+} Y_s(ω) U^{ωi}(ω, k) cos θ dω (Sun §3.3 "One-Bounce"), in the local
    frame (so one matrix serves every vertex). Fibonacci-hemisphere quadrature. Returns (S, K)."""
    d, w = fibonacci_hemisphere(n_quad, dtype=torch.float64)
    Y = _sh.sh_eval(d, order)  # (Q, S)
    Uc = factors.Ucos(d.to(factors.U_tab.dtype)).double()  # (Q, K)
    with torch_threads(1):  # an (S, Q)·(Q, K) product, Q = 8192: its sum order varies with the threads
        return ((Y * w[:, None]).T @ Uc).to(factors.U_tab.dtype)


def uniform_light_vector(factors: BasisFactors, *, n_quad: int = 8192) -> Tensor:
    """C^{ωi}(k) = ∫_{H+} U^{ωi}(ω, k) cos θ dω (Sun §3.3 "Two-Bounce"). Returns (K,)."""
    d, w = fibonacci_hemisphere(n_quad, dtype=torch.float64)
    Uc = factors.Ucos(d.to(factors.U_tab.dtype)).double()
    with torch_threads(1):  # as `sh_light_matrix`
        return (w @ Uc).to(factors.U_tab.dtype)


# -- lighting ------------------------------------------------------------------------------------


def block_index(N: int, n: int, *, device=None) -> Tensor:
    """Flat indices into a (6, N, N) Haar layout of the coarse block [face, 0:n, 0:n], ordered
    (face, row, col): the 6·n² wavelets of a 6×n×n lighting (module docstring). Returns (6n²,)."""
    if n < 1 or n > N or (n & (n - 1)) or (N & (N - 1)):
        raise ValueError(f"coarse resolution n={n} must be a power of two <= N={N}")
    f, r, c = torch.meshgrid(torch.arange(6, device=device), torch.arange(n, device=device),
                             torch.arange(n, device=device), indexing="ij")
    return (f * N * N + r * N + c).reshape(-1)


def env_cube(envmap: Any, N: int, supersample: int, cubes: dict | None = None) -> Tensor:
    """``cubemap.from_envmap(envmap, N, supersample=supersample)`` (6, N, N, 3) float32, kept in
    ``cubes`` (keyed by (N, supersample)) when given: a lighting stage resamples the env map once per
    cube resolution — the Haar transform (`env_haar`) and the lobe prefilters of the same resolution
    (``specular.prefilter_env``) read the same cube (the same call, so the same texels). Measured on
    the chess bench L frame (1 thread, CPU time): 8.2 ms per resampling, two of the four saved.
    A cube of half the resolution whose sub-samples are those of a kept one (the same N·s grid:
    `from_envmap` raises s to the map's resolution) is pooled from it (``cubemap.pool_means``:
    the same sums regrouped, float32 round-off; 0.2 ms instead of a third resampling — the 21°
    lobe's 16² cube from the 32² one)."""
    key = (int(N), int(supersample))
    if cubes is not None and key in cubes:
        return cubes[key]
    s_eff = max(int(supersample), cubemap.min_supersample(N, envmap.height))
    fine = None
    if cubes is not None:
        fine = next((c for (n2, s2), c in cubes.items()
                     if n2 == 2 * N and 2 * max(s2, cubemap.min_supersample(n2, envmap.height)) == s_eff), None)
    if fine is not None:
        cube = cubemap.pool_means(fine)
    else:
        cube = cubemap.from_envmap(envmap, N, supersample=supersample, dtype=torch.float32)
    if cubes is not None:
        cubes[key] = cube
    return cube


def env_haar(envmap: Any, N: int, *, supersample: int = 2, dtype=torch.float32, cubes: dict | None = None) -> Tensor:
    """Haar coefficients C^L of an env map on the 6×N×N cube map (texel means, world frame);
    cubes: the lighting stage's cube memo (`env_cube`).

    Returns (6N², 3): column c = haar_forward of channel c, flattened (face, row, col).
    """
    cube = env_cube(envmap, N, supersample, cubes)
    return cubemap.haar_forward(cube.permute(3, 0, 1, 2).double()).reshape(3, -1).T.to(dtype).contiguous()


# -- direct transport ------------------------------------------------------------------------

# Fraction of the way from a vertex towards the mean centroid of its faces by which ray origins
# are moved (`ray_points`). A vertex on the junction of two surfaces (a wall standing on a floor,
# the corners of a niche) lies *in* the other surface's plane; offsetting along its own normal only
# leaves every ray hitting that plane at t ≈ 0 (black corners). 1 % of the way into its own
# triangles puts it strictly on its own side while moving it far less than any shading detail.
INWARD_FRACTION = 1e-2


def ray_points(V: Tensor, F: Tensor) -> Tensor:
    """Ray origins of vertices, moved INWARD_FRACTION towards their faces' centroids.

    V (Nv, 3), F (M, 3) → (Nv, 3) (a vertex without faces stays where it is)."""
    V = torch.as_tensor(V, dtype=torch.float32)
    F = torch.as_tensor(F).long()
    cen = V[F].mean(1)  # (M, 3)
    acc = torch.zeros_like(V).index_add_(0, F.reshape(-1), cen.repeat_interleave(3, 0))
    cnt = torch.zeros(V.shape[0], dtype=V.dtype).index_add_(0, F.reshape(-1), torch.ones(F.numel(), dtype=V.dtype))
    mean = torch.where(cnt[:, None] > 0, acc / cnt.clamp_min(1)[:, None], V)
    return V + INWARD_FRACTION * (mean - V)



@dataclass
class DirectTransport:
    """Per-vertex direct transport (Sun §3.3 "Direct Lighting", §4.3).

    idx, val: (V, K, n_L) kept Haar coefficients of ∫_texel T̃⁰_x(ω, k) dω (flat 6N² indices).
    coarse: (V, K, 6n²) all coefficients of the coarse block `block_index(N, n)` (untruncated).
    N: fine face resolution; n: coarse resolution (0 if no coarse block was requested).
    """

    idx: Tensor
    val: Tensor
    coarse: Tensor | None
    N: int
    n: int


def direct_transport(vis: Visibility, V: Tensor, normals: Tensor, factors: BasisFactors, *,
                     N: int = 32, n_L: int = 96, area_weighted: bool = True, coarse: int = 0,
                     chunk: int = 128, progress: bool | None = None,
                     visibility_hook: Any = None) -> DirectTransport:
    """T̃⁰_x(ω, k) = U^{ωi}(ω_local, k)(ω·n_x)V_x(ω) per vertex, Haar, keep n_L largest per k.

    Args:
        vis: Embree scene of the (static) geometry.
        V, normals: (Nv, 3) ray origins (`ray_points` of the vertices) and unit normals.
        factors: `factor_basis` result (K incident factors).
        N: cube-map face resolution (paper 64); n_L: coefficients kept per (vertex, k) (paper 96).
        area_weighted: select by |c|·support area (Ng 2003 §5, as the paper) instead of |c|.
        coarse: also return the untruncated coarse block 6×coarse×coarse (0 = none).
        visibility_hook: optional callable ``hook(a, b, vis)`` receiving each chunk's traced
            visibility, vertices a:b, vis (b − a, 6N²) bool (flat face, row, col; directions below
            the vertex's horizon False) — lets callers reuse the rays (``methods.ptt.specular``).
    Returns:
        `DirectTransport`.
    """
    from tqdm.auto import tqdm

    V = torch.as_tensor(V, dtype=torch.float32)
    normals = torch.as_tensor(normals, dtype=torch.float32)
    if V.ndim != 2 or V.shape[1] != 3 or normals.shape != V.shape:
        raise ValueError(f"V, normals must be (Nv, 3), got {tuple(V.shape)}, {tuple(normals.shape)}")
    if N & (N - 1) or N < 1:
        raise ValueError(f"N must be a power of two, got {N}")
    nv, K = V.shape[0], factors.K
    n_keep = min(int(n_L), 6 * N * N)
    dirs = cubemap.texel_directions(N).reshape(-1, 3)  # (T, 3) world
    omega = cubemap.texel_solid_angles(N).reshape(-1)  # (T,)
    wts = cubemap.haar_support_area(N).reshape(-1) if area_weighted else None
    bidx = block_index(N, coarse) if coarse else None
    idx = torch.empty(nv, K, n_keep, dtype=torch.int64)
    val = torch.empty(nv, K, n_keep, dtype=torch.float32)
    crs = torch.empty(nv, K, bidx.numel(), dtype=torch.float32) if coarse else None
    if progress is None:
        progress = sys.stderr.isatty()
    for a in tqdm(range(0, nv, chunk), disable=not progress, desc="direct transport", unit="chunk"):
        b = min(nv, a + chunk)
        vb = vertex_visibility(vis, V[a:b], normals[a:b], dirs, below_horizon="hide", progress=False)  # (c, T)
        if visibility_hook is not None:
            visibility_hook(a, b, vb)
        loc = to_local(dirs[None].expand(b - a, -1, 3), normals[a:b, None, :].expand(-1, dirs.shape[0], 3))
        Uc = factors.Ucos(loc)  # (c, T, K) U^{ωi}(ω_local, k)(ω·n_x)
        t = Uc * (vb.float() * omega)[..., None]  # ∫_texel T̃⁰ dω
        coef = cubemap.haar_forward(t.permute(0, 2, 1).reshape(b - a, K, 6, N, N)).reshape(b - a, K, -1)
        # the n_L largest, ties (equal by symmetry) decided the same on every machine (methods.core.stable)
        i, v = keep_largest(coef, n_keep, weights=wts)
        idx[a:b], val[a:b] = i, v
        if coarse:
            crs[a:b] = coef[..., bidx]
    return DirectTransport(idx, val, crs, N, int(coarse))


def direct_incidence(dt: DirectTransport, CL: Tensor) -> Tensor:
    """Σ_l C^L_l U^{I0}_x(l, k) (the direct part of eq. 3's inner sum). CL (6N², 3) → (V, K, 3)."""
    if CL.shape != (6 * dt.N * dt.N, 3):
        raise ValueError(f"lighting must be (6N², 3) = {(6 * dt.N * dt.N, 3)}, got {tuple(CL.shape)}")
    return torch.einsum("vkn,vknc->vkc", dt.val, CL[dt.idx])
