"""Run-time specular lobes of the PTT method (Sun et al. 2007 §4.1): prefiltered environment maps ×
fractional visibility, and the remainder BRDF basis that goes through the transport factorization.

Split (Sun §4.1). Every basis BRDF b_p (``transport.BRDFBasis``; isotropic) is split as

    b_p(ωi, ωo) = Σ_k a_k^p(θo) G_k(ωi; R(ωo)) + r_p(ωi, ωo),     k ∈ lobe degrees (paper 0/7/14/21°)

with R(ωo) the mirror direction, G_k the unit-mass Gaussian of ``methods.ptt.lobes`` (3σ_k = k°,
∫_{S²} G_k dω = 1; the 0° lobe is the Dirac delta at R), a_k^p(θo) ≥ 0 in BRDF·sr units tabulated
over θo (`fit_lobe_table`), and r_p the remainder given to ``transport.factor_basis`` through the
wrapper `RemainderBasis`. A region's BRDF has coordinates H(r, p, c), so its lobe weights are
a_k(r, θo, c) = Σ_p H(r, p, c) a_k^p(θo): tables per basis function mixed by H at run time keep
dynamic BRDFs working (no refit when a material changes).

Fit (ours; the paper fits by EM with fixed centres and widths). For each θo on `n_theta` nodes the
samples of b_p over the upper hemisphere (a spherical-Fibonacci set of ``fit_samples`` directions,
uniform in solid angle: the orthographic disk grid of ``brdf_tensor`` is ~1/cos θ coarser near the
horizon, where a 0°/7° lobe about a grazing R then falls between samples and its NNLS weight is
unbounded — measured a_0 ≈ 2·10⁴ for Cook–Torrance at θo = 88°) are fitted by
non-negative least squares (`lobes.fit_lobe_weights`, exact active-set NNLS) with solid-angle
weights (the continuous L² norm on the hemisphere) by

    b_p(ωi) ≈ c_p + Σ_k a_k^p G_k(ωi; R),      c_p ≥ 0, a_k^p ≥ 0,

where the constant c_p is only a regressor: it *stays* in the remainder. Without it the NNLS puts a
narrow bump of weight ≈ ⟨f, G⟩/⟨G, G⟩ into a Lambert term (carving a sharp dip into a diffuse
remainder, which is harder to factor than no separation); with it a diffuse basis function gets
lobe weights ≈ 0 and a glossy one gives its broad part to c_p. Then the weights of each (p, θo) are
scaled by one factor ≤ 1 so that f_s ≤ f + τ·max f at every fit sample (τ = NEG_REMAINDER): an L²
fit of a lobe *narrower* than the BRDF peaks at ~2× the BRDF (a = ⟨f, G⟩/⟨G, G⟩ ≈ f(R)·4πσ²,
G(R) = 1/(2πσ²)), and the negative remainder spikes it leaves (worst at grazing θo for
Cook–Torrance) take over the rank-K factorization (measured on `chess` without the bound: the
image went black). With the bound f_r ≥ −τ·max f, so the factorization never sees much larger
values than without separation.

The 0° lobe (a Dirac at run time) is, in the fit *and* in `RemainderBasis.eval`, the unit-mass
Gaussian of σ_δ = the fit sample spacing √(2π/fit_samples): the narrowest lobe the fit resolves,
and the same function on both sides so its energy is not counted twice (a pointwise Dirac would be
invisible in f_r). r_p is 0 below either horizon (like every BRDF). The fit assumes non-negative
lobes (true for `transport.LobeBasis`; a PCA basis function with a negative lobe keeps it in r_p).

Direct term (per lighting, per vertex, per sample). With L the env map and V_x the binary
visibility of vertex x,

    ∫ G_k(ω; R) L(ω) V_x(ω) max(0, n·ω) dω ≈ E^(k)(R) · V_c^(k)(x, R),
    E^(k)(R)       = ∫ G_k(ω; R) L(ω) dω / ∫ G_k(ω; R) dω           (prefiltered env map, stage 1)
    V_c^(k)(x, R)  = ∫ G_k(ω; R) V_x(ω) max(0, n·ω) dω / ∫ G_k dω   (cosine-weighted fractional
                                                                     visibility, precompute)

Normalisation choices: (1) lobes have unit mass, so E^(k) is a weighted *mean* of radiance (a
constant env map stays exactly constant, whatever the discretisation); (2) the cosine is taken
*inside* the visibility integral instead of as max(0, R·n) at the lobe centre: exact for constant
lighting (the furnace test) and equal to max(0, R·n)·V^(k) in the narrow-lobe limit; directions
below the vertex's horizon count as occluded (direct transport's ``below_horizon="hide"``), which
clips lobes that straddle the horizon; (3) both integrals are normalised by the *discrete* mass of
the lobe on their own sampling (so a lobe narrower than the sampling is a nearest-sample look-up,
not a loss of energy).

Storage. E^(k), k > 0: a lat-long map (EnvMap convention, bilinear) of height 2·res_k and width
4·res_k, computed from a 6×res_k×res_k cube-map resampling of the env map by a sparse truncated
(3.5σ) kernel; res_k = the smallest power of two whose texel (≈ 90°/res_k) is ≤ σ_k, capped at
``env_res`` (wide lobes are filtered at lower resolution; the texel box adds ≲ σ/2 of blur; the
paper's narrow 7° lobe, σ = 2.3°, is limited by ``env_res``: 32 → 2.8° texels). The 0° lobe reads
the unfiltered env map at R. V_c^(k)(x, ·): per vertex a T×T table over the *local* hemisphere of
R (the azimuthal-equidistant table of ``transport.table_grid``, bilinear), computed from the
vertex's world-cube visibility of the direct transport (nearest texel, so its resolution is
``cube_res``) resampled at a fixed local spherical-Fibonacci set of ``samples`` directions, so the
lobe kernels are one sparse matrix shared by every vertex: (V, L, T, T) floats per scene.

Run time (stage 3). The maps E^(k) are resampled onto the env map's own grid and frame
(`on_env_grid`) and read at the per-sample mirror direction R = reflect(ωo, n) of the
interpolated shading normal n; with shading="vertex" every lobe with one bilinear look-up
(`latlong_cells`, Mitsuba's convention, at `mirror_dirs`; both shared by the reference and the
fast path, so they look the maps up at the same bits). With shading="vertex"
(Sun's run time: the fractional visibility "is computed from the visibility maps of each vertex")
the factors are per vertex x at its own view direction, R_x = reflect(ωo_x, n_x), and
interpolated with the barycentrics β:

    L_s = Σ_k E^(k)(R) · Σ_v β_v a_k(H, θo_v) V_c^(k)(v, R_v);

with shading="pixel" a_k is taken at the sample's θo = acos(n·ωo) and each vertex's table is
read at the sample's R in that vertex's frame:

    L_s = Σ_k a_k(H, θo) · E^(k)(R) · Σ_v β_v V_c^(k)(v, R).

Indirect term (bounces ≥ 1, Sun §4.1 "computed with respect to transferred incident radiance from
one-bounce interreflection ... using prefiltered SH basis functions"): the one-bounce incident
radiance of vertex v in SH (I1_v(s), order 4, local frame; from the BRDF stage) convolved with each
unit-mass lobe's zonal kernel (Funk–Hecke factors Λ_l k_l, `lobe_sh_kernels`) is evaluated at R and multiplied by
max(0, n·R) (no visibility: it *is* the occluded part); vertices interpolated as above, clamped at 0
(with shading="vertex" evaluated per vertex at R_x and interpolated).
The two-bounce uniform radiance is disregarded for the lobes (as the paper). The bounce tensors
themselves are built from the remainder basis, so light reflected by a *hit point's* separated lobe
is missing from the interreflections (see ``methods.ptt.method``).
"""
from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass
from typing import Any, Sequence

import torch
from torch import Tensor

from methods.core import cubemap
from methods.core import sh as _sh
from methods.core import zh as _zh
from methods.core.fused import fused
from methods.core.frames import to_world
from methods.core.sampling import fibonacci_hemisphere, fibonacci_sphere
from methods.ptt import lobes as _lobes
from methods.ptt.transport import table_coords, table_grid

__all__ = [
    "LobeTable", "fit_lobe_table", "lobe_weights", "lobe_shape", "RemainderBasis",
    "LobeVisibility", "lobe_visibility", "vertex_lobe_tables", "lookup_vertex_tables",
    "EnvFilter", "env_filters", "prefilter_env", "lobe_sh_kernels", "sh_at", "check_lobe_degrees",
]

# Truncation of the Gaussian prefilter kernels, in σ (beyond 3.5σ the 2-D Gaussian holds
# e^{-6.1} ≈ 0.2 % of its mass; rows are renormalised, so a constant map stays constant).
KERNEL_SIGMAS = 3.5
# Lower bound of the remainder, as a fraction τ of the basis function's maximum at that θo:
# f_r ≥ −τ·max f (`fit_lobe_table`). τ = 0 (f_r ≥ 0) is too strict: a Gaussian in the angle to R
# never fits under a Blinn–Phong / Cook–Torrance lobe's tails (an exact QP gave the lobes ≤ 25 % of
# the Blinn–Phong s = 60 energy). Measured on chess/test, direct, 1 spp G-buffer, RMSE vs a 32+32
# sample oracle image: no separation 0.0743; τ = 0 → 0.0742, 0.1 → 0.0654, 0.3 → 0.0646 (the board's
# remainder is the sensitive part: its mean goes 0.170 → 0.203 → 0.202, oracle 0.214). 0.1 keeps
# the remainder closest to non-negative for nearly all of the gain.
NEG_REMAINDER = 0.1
# Coarsest face resolution of a prefiltered lobe (res_k rule in the module docstring).
MIN_ENV_RES = 4


def _csr(x: Tensor) -> Tensor:
    """x (dense or COO) → sparse CSR, without torch's "beta" warning."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*[Ss]parse CSR tensor support is in beta.*")
        return x.to_sparse_csr()


# -- lobe weights per basis function ------------------------------------------------------------


@dataclass
class LobeTable:
    """Lobe weights a_k^p(θo) of every basis function (module docstring).

    degrees: (L,) lobe sizes k in degrees (0 = mirror delta).
    theta: (n,) θo nodes in radians (ascending, inside (0, π/2)).
    a: (n_P, n, L) float32 weights (BRDF·sr) ≥ 0.
    sigma_delta: σ (radians) with which the 0° lobe is subtracted pointwise in `RemainderBasis`.
    """

    degrees: tuple[float, ...]
    theta: Tensor
    a: Tensor
    sigma_delta: float

    @property
    def n_P(self) -> int:
        return int(self.a.shape[0])

    @property
    def L(self) -> int:
        return len(self.degrees)


@functools.lru_cache(maxsize=64)
def _mass(sigma: float) -> float:
    """`lobes.gaussian_lobe_mass`, memoised (it builds a 256-node Gauss–Legendre rule per call)."""
    return _lobes.gaussian_lobe_mass(sigma)


def _sigmas(degrees: Sequence[float], sigma_delta: float) -> list[float]:
    return [sigma_delta if k == 0 else _lobes.lobe_sigma(float(k)) for k in degrees]


def check_lobe_degrees(degrees: Sequence[float]) -> tuple[float, ...]:
    """Validated lobe sizes (distinct numbers in [0, 180) degrees) as a tuple; ValueError otherwise."""
    try:
        degs = tuple(float(k) for k in degrees)
    except TypeError:
        raise ValueError(f"lobe degrees must be a sequence of numbers, got {degrees!r}") from None
    if not degs or any(not (0.0 <= k < 180.0) for k in degs) or len(set(degs)) != len(degs):
        raise ValueError(f"lobe degrees must be distinct numbers in [0, 180), got {degrees!r}")
    return degs


def fit_lobe_table(basis: Any, degrees: Sequence[float] = _lobes.LOBE_DEGREES, *, n_theta: int = 32,
                   fit_samples: int = 16384) -> LobeTable:
    """Fit a_k^p(θo) for every basis function of an isotropic `transport.BRDFBasis`.

    Args:
        basis: n_P basis BRDFs (``eval(wi, wo) -> (..., n_P)``).
        degrees: lobe sizes (Sun §4.1: 0, 7, 14, 21).
        n_theta: θo nodes, θ_j = (j + ½)/n_theta · π/2.
        fit_samples: ωi samples, a spherical-Fibonacci hemisphere (16384 → spacing ≈ 1.1°).
    Returns:
        `LobeTable`.
    """
    degs = check_lobe_degrees(degrees)
    for name, v in (("n_theta", n_theta), ("fit_samples", fit_samples)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 2:
            raise ValueError(f"{name} must be an int >= 2, got {v!r}")
    wi, sw = fibonacci_hemisphere(fit_samples, dtype=torch.float64)  # (Ni, 3), (Ni,) = 2π/Ni
    th = (torch.arange(n_theta, dtype=torch.float64) + 0.5) * (math.pi / 2 / n_theta)
    wo = torch.stack([torch.sin(th), torch.zeros_like(th), torch.cos(th)], -1)  # (n, 3)
    R = torch.stack([-wo[:, 0], wo[:, 1], wo[:, 2]], -1)  # mirror about z
    sigma_delta = math.sqrt(2.0 * math.pi / fit_samples)  # the sample spacing, radians
    G = lobe_shape(R @ wi.T, degs, sigma_delta).permute(0, 2, 1)  # (n, L, Ni)
    B = torch.cat([G, torch.ones_like(G[:, :1])], 1)  # + the constant regressor c_p (stays in r_p)
    f = basis.eval(wi[None].expand(n_theta, -1, 3), wo[:, None].expand(-1, wi.shape[0], 3)).double()
    f = f.permute(2, 0, 1)  # (P, n, Ni)
    a = _lobes.fit_lobe_weights(f, B, weights=sw)[..., :-1]  # (P, n, L)
    # bound the remainder from below: scale the lobes down until f_s <= f + τ max f at every sample
    fs = _lobes.lobe_values(a, G)  # (P, n, Ni)
    cap = f + NEG_REMAINDER * f.amax(-1, keepdim=True)
    ratio = torch.where(fs > 1e-12 * fs.amax(-1, keepdim=True).clamp_min(1e-300), cap / fs.clamp_min(1e-300),
                        torch.full_like(fs, math.inf))
    a = a * ratio.amin(-1, keepdim=True).clamp(0.0, 1.0)
    return LobeTable(degs, th.float(), a.float().contiguous(), float(sigma_delta))


def lobe_weights(table: LobeTable, cos_o: Tensor) -> Tensor:
    """a_k^p at cos θo (...) by linear interpolation in θo (clamped at the end nodes) → (..., P, L)."""
    th = torch.acos(cos_o.clamp(-1.0, 1.0)).to(table.a.dtype)
    n = table.theta.shape[0]
    x = (th / (math.pi / 2) * n - 0.5).clamp(0.0, n - 1.0)
    i0 = x.floor().long().clamp(max=n - 2) if n > 1 else torch.zeros_like(x, dtype=torch.long)
    t = (x - i0.to(x.dtype))[..., None]
    a = table.a.to(cos_o.device).transpose(0, 1).reshape(n, -1)  # (n, P·L)
    out = torch.lerp(a[i0], a[(i0 + 1).clamp(max=n - 1)], t) * (cos_o > 0).to(a.dtype)[..., None]
    return out.unflatten(-1, (table.n_P, table.L))


def lobe_shape(cos_t: Tensor, degrees: Sequence[float], sigma_delta: float) -> Tensor:
    """Unit-mass lobe values G_k(cos θ) (...) → (..., L) (the 0° lobe as a Gaussian of σ_δ);
    the formula of `lobes.gaussian_lobe` with θ computed once."""
    th2 = torch.acos(cos_t.clamp(-1.0, 1.0)).square()
    return torch.stack([torch.exp(th2 * (-0.5 / (s * s))) / _mass(s)
                        for s in _sigmas(degrees, sigma_delta)], -1)


class RemainderBasis:
    """The BRDFBasis r_p = b_p − Σ_k a_k^p(θo) G_k(ωi; R(ωo)) (module docstring); coordinates are
    those of the wrapped basis (same H)."""

    def __init__(self, basis: Any, table: LobeTable) -> None:
        if int(basis.n_P) != table.n_P:
            raise ValueError(f"lobe table has n_P={table.n_P}, basis {basis.n_P}")
        self.basis, self.table, self.n_P = basis, table, int(basis.n_P)

    def __repr__(self) -> str:
        return f"RemainderBasis({self.basis!r}, degrees={self.table.degrees})"

    def eval(self, wi: Tensor, wo: Tensor) -> Tensor:
        """r_p(wi, wo): wi, wo (..., 3) local → (..., n_P); 0 below either horizon."""
        if wi.shape[-1] != 3 or wo.shape[-1] != 3:
            raise ValueError(f"wi, wo must be (..., 3), got {tuple(wi.shape)}, {tuple(wo.shape)}")
        wi, wo = torch.broadcast_tensors(wi, wo)
        f = self.basis.eval(wi, wo)
        a = lobe_weights(self.table, wo[..., 2]).to(f.dtype)  # (..., P, L)
        R = torch.stack([-wo[..., 0], -wo[..., 1], wo[..., 2]], -1)
        G = lobe_shape((wi * R).sum(-1), self.table.degrees, self.table.sigma_delta).to(f.dtype)  # (..., L)
        fs = (a * G[..., None, :]).sum(-1)
        up = ((wi[..., 2] > 0) & (wo[..., 2] > 0))[..., None]
        return torch.where(up, f - fs, torch.zeros_like(f))

    def coords(self, material: Any) -> Tensor:
        return self.basis.coords(material)


# -- fractional visibility ----------------------------------------------------------------------


@dataclass
class LobeVisibility:
    """Kernels turning a vertex's local visibility samples into V_c^(k) tables.

    dirs: (S, 3) local upper-hemisphere sample directions; kernel: (L·T², S) sparse CSR of the
    normalised lobe weights × cos θ (truncated at KERNEL_SIGMAS σ; the 0° lobe as a nearest-sample
    pick); L: number of lobes; T: table resolution.
    """

    dirs: Tensor
    kernel: Tensor
    L: int
    T: int


def lobe_visibility(degrees: Sequence[float], *, T: int = 16, samples: int = 4096) -> LobeVisibility:
    """Kernels of V_c^(k)(R_t) = Σ_s G_k(R_t·s) w_s V(s) max(0, s_z) / Σ_{s ∈ S²} G_k(R_t·s) w_s
    (module docstring) on a spherical-Fibonacci set of ``samples`` local directions, R_t the
    `table_grid(T)` directions. The 0° lobe picks the sample nearest R_t."""
    degs = check_lobe_degrees(degrees)
    if isinstance(T, bool) or not isinstance(T, int) or T < 2:
        raise ValueError(f"T must be an int >= 2, got {T!r}")
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 16:
        raise ValueError(f"samples must be an int >= 16, got {samples!r}")
    d, w = fibonacci_sphere(samples, dtype=torch.float64)
    Rt = table_grid(T).reshape(-1, 3)  # (T², 3)
    cos = Rt @ d.T  # (T², S_all)
    up = d[:, 2] > 0
    rows = []
    for k in degs:
        if k == 0:
            K = torch.zeros_like(cos)
            K[torch.arange(cos.shape[0]), cos.argmax(-1)] = 1.0
        else:
            s = _lobes.lobe_sigma(k)
            G = lobe_shape(cos, (k,), 0.0)[..., 0] * w
            G = torch.where(cos >= math.cos(min(math.pi, KERNEL_SIGMAS * s)), G, torch.zeros_like(G))
            K = G / G.sum(-1, keepdim=True).clamp_min(1e-300)
        rows.append((K * d[:, 2].clamp_min(0.0))[:, up])
    K = _csr(torch.cat(rows).float())  # (L·T², S_up)
    return LobeVisibility(d[up].float(), K, len(degs), T)


def vertex_lobe_tables(lv: LobeVisibility, vis_world: Tensor, normals: Tensor, N: int) -> Tensor:
    """V_c^(k) tables of a chunk of vertices from their world cube-map visibility.

    vis_world: (c, 6N²) bool (flat (face, row, col), as `transport.direct_transport` traces it);
    normals: (c, 3). Returns (c, L, T, T) float32.
    """
    c = normals.shape[0]
    if normals.ndim != 2 or normals.shape[1] != 3:
        raise ValueError(f"normals must be (c, 3), got {tuple(normals.shape)}")
    if vis_world.shape != (c, 6 * N * N):
        raise ValueError(f"vis_world must be ({c}, {6 * N * N}), got {tuple(vis_world.shape)}")
    S = lv.dirs.shape[0]
    wd = to_world(lv.dirs[None].expand(c, S, 3), normals[:, None, :].float().expand(c, S, 3))
    f, r, col = cubemap.dir_to_texel(wd, N)
    V = torch.gather(vis_world, 1, (f * N * N + r * N + col).long()).float()  # (c, S)
    out = (lv.kernel @ V.T).T  # (c, L·T²)
    return out.reshape(c, lv.L, lv.T, lv.T)


def lookup_vertex_tables(tab: Tensor, v: Tensor, d: Tensor) -> Tensor:
    """Bilinear look-up of per-vertex tables tab (V, C, T, T) (`table_grid` layout) for vertices
    v (Q,) at local directions d (Q, 3) → (Q, C); 0 where d_z <= 0 (border-clamped like
    ``grid_sample(padding_mode="border", align_corners=False)``)."""
    if tab.ndim != 4 or v.ndim != 1 or d.shape != (v.shape[0], 3):
        raise ValueError(f"need tab (V, C, T, T), v (Q,), d (Q, 3); "
                         f"got {tuple(tab.shape)}, {tuple(v.shape)}, {tuple(d.shape)}")
    T = tab.shape[-1]
    uv = table_coords(d.to(tab.dtype))
    x = ((uv + 1.0) * (T / 2.0) - 0.5).clamp(0.0, T - 1.0)  # (Q, 2) continuous (col, row)
    i0 = x.floor().long().clamp(max=T - 2)
    t = x - i0.to(x.dtype)
    ix, iy = i0[:, 0], i0[:, 1]
    tx, ty = t[:, 0:1], t[:, 1:2]
    out = (tab[v, :, iy, ix] * (1 - tx) * (1 - ty) + tab[v, :, iy, ix + 1] * tx * (1 - ty)
           + tab[v, :, iy + 1, ix] * (1 - tx) * ty + tab[v, :, iy + 1, ix + 1] * tx * ty)
    return out * (d[:, 2:3] > 0).to(out.dtype)


# -- prefiltered environment maps -----------------------------------------------------------------


@dataclass
class EnvFilter:
    """Sparse prefilter of one lobe: cube resolution res (input 6·res² texel means), output a
    lat-long of (2·res, 4·res) texels; kernel (H·W, 6·res²) CSR, rows sum to 1."""

    degrees: float
    res: int
    kernel: Tensor

    @property
    def shape(self) -> tuple[int, int]:
        return 2 * self.res, 4 * self.res


def _filter_res(sigma: float, env_res: int) -> int:
    """Smallest power of two whose cube texel (≈ (π/2)/res) is <= σ, within [MIN_ENV_RES, env_res]."""
    res = MIN_ENV_RES
    while res < env_res and (math.pi / 2) / res > sigma:
        res *= 2
    return res


def env_filters(degrees: Sequence[float], env_res: int = 32) -> list[EnvFilter | None]:
    """Sparse Gaussian prefilters, one per lobe (None for the 0° lobe: the unfiltered map)."""
    from scenes.envmap import texel_directions as latlong_dirs

    degs = check_lobe_degrees(degrees)
    if isinstance(env_res, bool) or not isinstance(env_res, int) or env_res < MIN_ENV_RES or env_res & (env_res - 1):
        raise ValueError(f"env_res must be a power of two >= {MIN_ENV_RES}, got {env_res!r}")
    out: list[EnvFilter | None] = []
    for k in degs:
        if k == 0:
            out.append(None)
            continue
        s = _lobes.lobe_sigma(k)
        res = _filter_res(s, env_res)
        din = cubemap.texel_directions(res, dtype=torch.float64).reshape(-1, 3)
        om = cubemap.texel_solid_angles(res, dtype=torch.float64).reshape(-1)
        H, W = 2 * res, 4 * res
        dout = latlong_dirs(H, W).reshape(-1, 3)  # EnvMap to_world = I: local = world
        cmin = math.cos(min(math.pi, KERNEL_SIGMAS * s))
        rows, cols, vals = [], [], []
        for a in range(0, dout.shape[0], 512):
            cos = dout[a:a + 512] @ din.T
            r, c = torch.nonzero(cos >= cmin, as_tuple=True)
            G = torch.exp(torch.acos(cos[r, c].clamp(-1, 1)).square() * (-0.5 / (s * s))) * om[c]
            tot = torch.zeros(cos.shape[0], dtype=G.dtype).index_add_(0, r, G)
            rows.append(r + a)
            cols.append(c)
            vals.append(G / tot[r])
        K = _csr(torch.sparse_coo_tensor(torch.stack([torch.cat(rows), torch.cat(cols)]), torch.cat(vals).float(),
                                         (H * W, din.shape[0]), check_invariants=True).coalesce())
        out.append(EnvFilter(k, res, K))
    return out


def prefilter_env(envmap: Any, filters: Sequence[EnvFilter | None], *, supersample: int = 2,
                  cubes: dict | None = None) -> list[Any]:
    """E^(k) per lobe as ``scenes.envmap.EnvMap`` (world frame, to_world = I); the 0° lobe is the
    env map itself. cubes: the lighting stage's memo of resampled cube maps
    (``transport.env_cube``; lobes of one resolution, and the Haar transform of that resolution,
    share one resampling)."""
    from methods.ptt.transport import env_cube

    cubes = {} if cubes is None else cubes
    out = []
    for flt in filters:
        if flt is None:
            out.append(envmap)
            continue
        cube = env_cube(envmap, flt.res, supersample, cubes)
        E = (flt.kernel @ cube.reshape(-1, 3)).clamp_min(0.0).reshape(*flt.shape, 3)
        out.append(_envmap(E, None))
    return out


def _envmap(data: Tensor, to_world: Tensor | None) -> Any:
    """``EnvMap(data, to_world)`` without the input checks (finite, non-negative (H, W, 3) data, a
    rotation), for maps this module builds from checked ones: a prefiltered or resampled map is a
    non-negative combination of the env map's texels (clamped at 0) and its frame is the env map's.
    The checks cost 1.6 ms per 256×512 map, three maps per lighting change (chess bench)."""
    from scenes.envmap import EnvMap

    out = EnvMap.__new__(EnvMap)
    out.data = data
    out.to_world = torch.eye(3, dtype=torch.float64) if to_world is None else to_world
    out._table, out._ext = None, {}
    return out


def on_env_grid(maps: Sequence[Any], envmap: Any) -> list[Any]:
    """The prefiltered maps E^(k) (`prefilter_env`) resampled onto ``envmap``'s own lat-long grid and
    frame: E^(k) at each texel's world direction by the bilinear look-up of ``EnvMap.radiance``
    (as `latlong_cells`), as an EnvMap with ``envmap``'s to_world (the 0° lobe is ``envmap``
    itself). Every lobe then has the same grid and frame, so the run time reads all of them with
    one bilinear look-up per shading point (``fast.EnvStack``). The resampling adds a bilinear
    interpolation of the (coarser, smooth) prefiltered map; the env map is never resampled.

    One compiled loop over the texels (`_grid_resample`: direction, (u, v), the cell in each map and
    its four corners; ``methods.core.fused``), shared by the fast path and the reference. Measured on
    the chess bench (256×512 env map, three lobe maps of 64×128, 64×128, 32×64; 1 thread, CPU time,
    same process, 11 rotated maps, load ~5): 11.1 ms for the eager passes (`_on_env_grid_eager`, kept
    as its test oracle: the same look-ups to float32 round-off, ≤ 2e-6 relative) → 4.7 ms (×2.4;
    creature the same)."""
    from scenes.envmap import extend_periodic

    H, W = envmap.data.shape[:2]
    todo = [m for m in maps if m is not envmap]
    if not todo:
        return list(maps)
    if any(not torch.equal(m.to_world, todo[0].to_world) for m in todo):
        raise ValueError("the prefiltered maps must share one frame")
    # local direction of each env texel in the maps' frame: A d with A = M_mapsᵀ R_env (float64, then float32)
    A = (todo[0].to_world.to(torch.float64).T @ envmap.to_world.to(torch.float64)).to(torch.float32).contiguous()
    exts = [extend_periodic(m.data.to(torch.float32)) for m in todo]
    dims = tuple((int(m.height), int(m.width)) for m in todo)
    res = iter(_grid_resample(_texel_dirs(H, W), A, exts, dims))
    return [m if m is envmap else _envmap(next(res).view(H, W, 3), envmap.to_world) for m in maps]


def _grid_resample_fn(d: Tensor, A: Tensor, exts: list[Tensor], dims: tuple) -> list[Tensor]:
    """For ``core.fused``: maps of resolutions ``dims`` ((H_k, W_k), periodic-extended texels
    ``exts`` (H_k·(W_k + 1), 3)) looked up bilinearly (``scenes.envmap.bilinear_lookup``, the cells
    of `_uv_cells`) at the directions A d (d (3, n) local texel directions, A (3, 3)) → one (n, 3)
    per map."""
    x = A[0, 0] * d[0] + A[0, 1] * d[1] + A[0, 2] * d[2]
    y = A[1, 0] * d[0] + A[1, 1] * d[1] + A[1, 2] * d[2]
    z = A[2, 0] * d[0] + A[2, 1] * d[1] + A[2, 2] * d[2]
    u = torch.atan2(x, -z) * (0.5 / math.pi)
    v = torch.acos(y.clamp(-1.0, 1.0)) * (1.0 / math.pi)
    out = []
    for ext, (Hm, Wm) in zip(exts, dims):
        uu = u - 0.5 / Wm
        px = (uu - torch.floor(uu)) * Wm
        py = (v - torch.floor(v)) * (Hm - 1)
        ix = px.to(torch.int64).clamp(0, Wm - 1)
        iy = py.to(torch.int64).clamp(0, Hm - 2)
        fx, fy = px - ix, py - iy
        gx, gy = 1.0 - fx, 1.0 - fy
        r = iy * (Wm + 1) + ix
        out.append(ext[r] * (gx * gy)[:, None] + ext[r + 1] * (fx * gy)[:, None]
                   + ext[r + (Wm + 1)] * (gx * fy)[:, None] + ext[r + (Wm + 2)] * (fx * fy)[:, None])
    return out


_grid_resample = fused(_grid_resample_fn)


def _on_env_grid_eager(maps: Sequence[Any], envmap: Any) -> list[Any]:
    """`on_env_grid` as eager passes (the previous implementation; its test oracle)."""
    from scenes.envmap import extend_periodic

    H, W = envmap.data.shape[:2]
    uv = None
    cells: dict = {}  # the bilinear cells of the texels' (u, v), once per map resolution
    out = []
    for m in maps:
        if m is envmap:
            out.append(m)
            continue
        if uv is None:  # world directions of the env texels in the maps' frame, (u, v) once
            d = envmap.to_world.to(torch.float32) @ _texel_dirs(H, W)  # (3, H·W)
            uv = _latlong_uv(d, m.to_world)
        elif not torch.equal(m.to_world, maps[-1].to_world):
            raise ValueError("the prefiltered maps must share one frame")
        if (m.height, m.width) not in cells:
            cells[m.height, m.width] = _uv_cells(*uv, m.height, m.width)
        idx, w = cells[m.height, m.width]
        E = torch.nn.functional.embedding_bag(idx, extend_periodic(m.data), per_sample_weights=w, mode="sum")
        out.append(_envmap(E.reshape(H, W, 3), envmap.to_world))
    return out


def mirror_dirs(normal: Tensor, wo: Tensor) -> Tensor:
    """Unit mirror directions R = reflect(ωo, n̂)/|·| (``core.frames.reflect``, n̂ = n/|n|) of G-buffer
    samples: normal, wo (Q, 3) → (3, Q), the components as contiguous rows (what `latlong_cells`
    reads; the reference and the fast path share it, so both look the maps up at the same bits)."""
    nx, ny, nz = normal.unbind(-1)
    wx, wy, wz = wo.unbind(-1)
    s = (nx * wx).add_(ny * wy).add_(nz * wz)
    n2 = (nx * nx).add_(ny * ny).add_(nz * nz).clamp_min_(1e-24)
    s = s.div_(n2).mul_(2.0)  # 2 (n̂·ωo) / |n|, so R = s n − ωo
    R = torch.empty(3, normal.shape[0], dtype=normal.dtype, device=normal.device)
    torch.mul(s, nx, out=R[0]).sub_(wx)
    torch.mul(s, ny, out=R[1]).sub_(wy)
    torch.mul(s, nz, out=R[2]).sub_(wz)
    inv = (R[0] * R[0]).add_(R[1] * R[1]).add_(R[2] * R[2]).clamp_min_(1e-24).rsqrt_()
    for i in range(3):  # row by row: the same products as R.mul_(inv), in passes of Q elements
        R[i].mul_(inv)
    return R


@functools.lru_cache(maxsize=8)
def _texel_dirs(H: int, W: int) -> Tensor:
    """(3, H·W) float32 local directions of an H×W lat-long map's texels (``scenes.envmap.texel_directions``)."""
    from scenes.envmap import texel_directions

    return texel_directions(H, W).reshape(-1, 3).T.to(torch.float32).contiguous()


def latlong_cells(R: Tensor, to_world: Tensor, H: int, W: int) -> tuple[Tensor, Tensor]:
    """Mitsuba's bilinear lat-long look-up (``scenes.envmap.bilinear_lookup``; the ARCHITECTURE.md
    env-map convention) of an H×W map with frame ``to_world`` at world directions R (3, Q)
    (`mirror_dirs`): rows (Q, 4) int64 into its periodic-extended texels
    (``scenes.envmap.extend_periodic``, H·(W+1) rows) and their weights (Q, 4), corners
    (x, y), (x+1, y), (x, y+1), (x+1, y+1)."""
    return _uv_cells(*_latlong_uv(R, to_world), H, W)


def _latlong_uv(R: Tensor, to_world: Tensor) -> tuple[Tensor, Tensor]:
    """(u, v) ∈ [−½, ½] × [0, 1] of world directions R (3, Q) in a map of frame ``to_world``
    (``scenes.envmap.direction_to_uv``)."""
    m = to_world.to(torch.float64).tolist()  # local = to_worldᵀ d (EnvMap.to_local), component by component:

    def comp(i: int) -> Tensor:  # Σ_j to_world[j, i] R[j] (a 3×3 matmul over Q columns is a slow GEMM shape)
        return torch.mul(R[0], m[0][i]).add_(R[1], alpha=m[1][i]).add_(R[2], alpha=m[2][i])

    u = torch.atan2(comp(0), comp(2).neg_()).mul_(0.5 / math.pi)
    v = torch.acos(comp(1).clamp_(-1.0, 1.0)).mul_(1.0 / math.pi)
    return u, v


def _uv_cells(u: Tensor, v: Tensor, H: int, W: int) -> tuple[Tensor, Tensor]:
    """The bilinear cell of `latlong_cells` from (u, v) of `_latlong_uv` (not modified)."""
    u = u - 0.5 / W  # half-texel shift: texel-centred columns
    x = u.sub_(torch.floor(u)).mul_(W)
    y = v - torch.floor(v)
    y = y.mul_(H - 1)
    ix = x.to(torch.int64).clamp_(max=W - 1)
    iy = y.to(torch.int64).clamp_(max=H - 2)
    fx, fy = x.sub_(ix), y.sub_(iy)
    gx, gy = 1.0 - fx, 1.0 - fy
    i0 = iy.mul_(W + 1).add_(ix)
    idx = i0[:, None] + torch.tensor([0, 1, W + 1, W + 2], dtype=i0.dtype, device=i0.device)
    w = torch.empty(idx.shape, dtype=fx.dtype, device=fx.device)
    torch.mul(gx, gy, out=w[:, 0])
    torch.mul(fx, gy, out=w[:, 1])
    torch.mul(gx, fy, out=w[:, 2])
    torch.mul(fx, fy, out=w[:, 3])
    return idx, w


def lobe_sh_kernels(degrees: Sequence[float], order: int) -> Tensor:
    """Funk–Hecke factors Λ_l k_l (L, order) of the unit-mass lobes (1 for the 0° delta), to
    prefilter SH radiance (``core.zh.convolve_factors``)."""
    degs = check_lobe_degrees(degrees)
    rows = []
    for k in degs:
        if k == 0:
            rows.append(torch.ones(order, dtype=torch.float64))
        else:  # Λ_l k_l = ∫ G_k P_l(cos θ) dω = 2π ∫_0^{min(π, 12σ)} G P_l sin θ dθ (Funk–Hecke)
            s = _lobes.lobe_sigma(k)
            hi = min(math.pi, 12.0 * s)
            n = 4096  # midpoint rule in θ: smooth integrand, error O((hi/n)²) ≈ 1e-9 relative
            th = (torch.arange(n, dtype=torch.float64) + 0.5) * (hi / n)
            g = torch.exp(-th * th / (2 * s * s)) * torch.sin(th) * (2 * math.pi * hi / n)
            rows.append((_zh.legendre(torch.cos(th), order) * g[:, None]).sum(0) / _mass(s))
    return torch.stack(rows).float()


def sh_at(coeffs: Tensor, d: Tensor, order: int) -> Tensor:
    """Σ_s coeffs(..., s, C) Y_s(d) for local directions d (..., 3) → (..., C)."""
    Y = _sh.sh_eval(d, order).to(coeffs.dtype)
    return (coeffs * Y[..., :, None]).sum(-2)
