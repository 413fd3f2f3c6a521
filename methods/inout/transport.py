"""Pure functions behind the in-out renderer (Mahajan, Tseng & Ramamoorthi 2008 §2 eq. 2–4, §6).

1. **BRDF factorization** (eq. 2), in the norm the image sees. The BRDF of one material is
   sampled on the equal-area (cos θ, φ) grid of the visible hemisphere
   (``methods.inout.analysis.direction_grid``; n × n cells of solid angle Δ = 2π/n² for each of
   ω_i and ω_o). The three colour channels are stacked along the *outgoing* axis and the matrix is
   weighted by a(ω_o) b(ω_i), ``A[(c, o), i] = a(ω_o) ρ_c(ω_i, ω_o) b(ω_i)`` (3n², n²); one SVD
   ``A = U S Vᵀ`` gives

       ρ_c(ω_i, ω_o) b(ω_i) = Σ_k σ_k h_{k,c}(ω_o) g_k(ω_i),
       σ_k = Δ S_k,  h_{k,c}(ω_o) = U[(c, o), k]/(√Δ a(ω_o)),  g_k(ω_i) = V[i, k]/√Δ,

   with h_k (jointly over channels) orthonormal in L²(a² dω_o) and g_k in L²(dω_i) of the
   hemisphere (the analysis module's scaling). By Eckart–Young the K-term truncation is the best
   rank-K approximation in ∫∫ a² |ρ b − Σ_k…|² dω_i dω_o, and K(99 %) (Fig. 3A) is counted in it.

   *Which norm.* ``norm="brdf"`` (a = b = 1) is eq. 2 as written, the matrix the paper analyses
   (§3–4; ``analysis`` keeps it for Fig. 3A/5/7). The paper itself says the image accuracy
   "ultimately depends on equation 4" (§2) and uses ρ as a proxy, which is sound for the BRDFs it
   analyses — Phong f(R·ω_i) (§3) and half-angle lobes "for exitant angles far from grazing" (§4;
   its measured curves omit grazing angles, Fig. 7) — whose matrix energy sits in the lobe. A
   microfacet BRDF D F G/(4 cos θ_i cos θ_o) (Cook–Torrance) breaks the proxy: ρ grows like
   1/cos² towards grazing mirror pairs, Σ σ_k² is dominated by them (and grows as the grid
   refines), and the 99 % rule spends every term there — on directions that eq. 1 multiplies by
   n·ω_i ≈ 0 and that reach few pixels (a surface seen at θ_o covers ∝ cos θ_o of the image) — so
   away from grazing the K-term BRDF is almost entirely wrong and the render comes out nearly
   black. ``norm="cosine"`` (the default of ``InOut``) factorizes ρ̃ = cos θ_o ρ cos θ_i
   (a = cos θ_o, b = cos θ_i): cos θ_i is eq. 1's own factor (the kernel that multiplies L·V in
   eq. 4 is ρ cos θ_i) and cos θ_o weights each exitant direction by the projected area through
   which it reaches the image. ρ̃ is symmetric (reciprocity) and bounded for every family (for
   Cook–Torrance it is D F G/4 ≤ 1/(4π m²)), so its energy is finite and converged in n and the
   99 % rule measures the lobe again, as in §3–4. For Phong and half-angle lobes the weights only
   damp the grazing tail (the paper's rules stay a floor on K: ``method``). (A √cos θ_o weight —
   the plain pixel measure — still leaves ρ cos θ_i √cos θ_o ∝ 1/√cos θ_o at grazing mirror
   pairs; measured, its 99 % K under-resolves a pure Cook–Torrance lobe.)

   Rendering is eq. 3–4 unchanged: with ĝ_k = g_k / b, T_k(x, ω_i) = V(x, ω_i) ĝ_k(ω_i) (n·ω_i)
   and B = Σ_k σ_k h_k(ω_o) T_k · L (for "brdf", ĝ_k = g_k). The incident factor is shared by the
   three channels, so the transport T_k is colour-free and costs K (not 3K) vectors per vertex;
   the material's colours live in h_k. The diffuse part kd/π is in ρ, hence in the factorization
   (for a Lambert material the stacked matrix has rank 1 in either norm).

2. **Off-grid factors by the SVD identity (Nyström extension).** Run time needs g_k at cube-map
   texel directions (in each vertex's local frame) and h_k at every G-buffer sample's ω_o. Instead
   of interpolating the coarse SVD grid we evaluate the exact identities of the SVD,

       ĝ_k(ω_i) = (1/σ_k) Σ_c ∫ ρ_c(ω_i, ω_o) a(ω_o)² h_{k,c}(ω_o) dω_o ≈ (Δ/σ_k) Σ_{c,o} ρ_c(ω_i, ω_o^j) a² h_{k,c}(ω_o^j)
       h_{k,c}(ω_o) = (1/σ_k) ∫ ρ_c(ω_i, ω_o) b(ω_i) g_k(ω_i) dω_i ≈ (Δ/σ_k) Σ_i ρ_c(ω_i^j, ω_o) b g_k(ω_i^j),

   (neither divides by a weight, so both stay finite at grazing angles), which reproduce the grid values exactly at grid directions (Aᵀu_k = S_k v_k, A v_k = S_k u_k)
   and between them inherit the smoothness of ρ itself (the BRDF is evaluated analytically in the
   free direction; only the integral over the other direction is a grid quadrature). Evaluating
   this per (vertex, texel) costs n² BRDF evaluations each, too much for 10⁴ vertices, so we
   tabulate it once per material on a fine look-up table (``lut_res`` × ``lut_res`` nodes,
   default 64, much finer than the SVD grid) and interpolate that bilinearly.

   The look-up table is parametrised by the *hemi-octahedral* map (Cigolle et al. 2014, JCGT 3(2),
   "A Survey of Efficient Representations for Independent Unit Vectors"): local direction
   d (z ≥ 0) ↦ p = (d_x, d_y)/(|d_x|+|d_y|+d_z), (u, v) = (p_x + p_y, p_x − p_y) ∈ [−1, 1]².
   Unlike a (cos θ, φ) table it has no pole (near the normal a uniform cos θ table has a θ spacing
   of ~√(2/R) rad — 10° at R = 64 — exactly where glossy h_k vary most) and no φ seam; nodes are
   corner-aligned so the horizon is on the table's boundary. Nodes on the horizon (z = 0) are
   evaluated at z = ``HORIZON_Z`` (the limit from above: the materials return 0 *at* z = 0).

3. **Transport in the cube-map Haar basis** (eq. 3–4, Ng 2003). For vertex x with normal n and
   world texel direction ω_t, T_k(x, ω_t) = V(x, ω_t) ĝ_k(to_local(ω_t)) max(0, n·ω_t). The dot
   product T_k · L must equal ∫ T_k L dω. On the cube map this integral is Σ_t T_k(ω_t) Ω_t L_t,
   with Ω_t the exact texel solid angle and L_t the texel-averaged radiance. The Haar transform
   of ``methods.core.cubemap`` is orthonormal in the texel-count measure (Parseval), so we fold the
   solid angle into the transport, T̃_t = T_k(ω_t) Ω_t, leave the lighting as plain texel
   radiance, and then ``Haar(T̃) · Haar(L) = Σ_t T̃_t L_t = ∫ T_k L dω`` exactly (before
   truncation). Keeping the largest |Haar(T̃)| coefficients is then the L²-optimal non-linear
   approximation of the kernel of that integral.

4. **Which coefficients a vertex keeps** (``budget``). The paper says only that T_k · L is "a
   simple dot product in a wavelet representation" (§2); how many coefficients, and for which k,
   is ours to choose. A vertex's exit radiance is B(ω_o) = Σ_k σ_k h_k(ω_o) c_k with the h_k
   orthonormal in L²(a² dω_o) (item 1), so truncating T̃ costs, for any lighting,

       ‖ΔB‖² = Σ_k σ_k² (ΔT̃_k · L)² ≤ ‖L‖² Σ_k σ_k² ‖ΔT̃_k‖²,

   and a fixed number of coefficients per vertex minimizes that bound by keeping the largest
   σ_k |Haar(T̃_k)| over *all* (k, t) of the vertex — ``budget="vertex"``, the default, with
   ``n_coeffs`` × K coefficients per vertex (the same memory as before). ``budget="term"`` keeps
   ``n_coeffs`` per (vertex, k) whatever σ_k is (the first implementation): glossy materials
   need K ≈ 100 terms whose g_k oscillate, the high-k rows then spend as many coefficients as the
   dominant low-k ones while the low-k rows lose energy near the sun, and with 10⁴ vertices
   choosing their coefficients independently the errors show as blotches — measured on
   sphere_plane at bench size (Phong s = 40, K = 100, 128 coefficients): 0.6–1.2 % negative
   pixels and a mottled sphere (the nightly's sanity gate marked it ``suspect``); at test size the
   same bytes give relative RMSE 0.097 ("term"), 0.091 ("vertex") and 0.087 with all 6N²
   coefficients kept, against a 1024-spp reference.

   The budget has a floor of ``MIN_BUDGET_TERMS`` terms' worth: a vertex keeps
   ``n_coeffs`` × max(K, MIN_BUDGET_TERMS). A one-term (Lambert) vertex's V·cos is smooth except at
   the horizon and at shadow edges, but that is exactly where a low sun sits, and the sun's
   radiance multiplies whatever the truncation lost there: on the bench bunny under the sunrise
   probe (sun 8° above the horizon, 54 % of the probe's energy) 128 coefficients left the Lambert
   ground at 0.82 of the reference's mean with a faint, streaky shadow, 384 at 1.02. The floor costs
   little memory: the glossy vertices, K ≈ 100, hold almost all of it.

   How many: ``n_coeffs`` = 256 per term on average (``InOut``'s default; 17 % of the 6N² = 1536
   coefficients of a term at N = 16). Any lighting-independent truncation fails for some probe —
   the coefficients it drops are small in T̃ but may face a sun — and 128 (8 %) did on the project's
   example scene (``scenes/examples/two_boxes.toml``, test size, every frame of V, L and E against
   1024-spp references): the red Phong s = 30 box (K = 75) came out at 0.874 of the reference's
   mean on E frame 2 and 0.897 on V frame 2, the Cook–Torrance box at 0.922 (E 2); with 256 every
   region of the nine frames lies in [0.964, 1.025] (all coefficients: red box 1.053 on E 2, the
   remaining error being the N = 16 cube map's), at 1.65× the memory (31 → 52 MiB there). Ng
   2003's area-weighted selection (``select="area"``) at 128 reached 0.905 / 0.932: better, not
   enough. At bench size the transport is the method's largest array and a lighting change reads
   all of it, so the bytes of an L or E frame double with n_coeffs (``frame_cost`` counts them).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import warnings

import torch
from torch import Tensor

from methods.core import cubemap
from methods.core.frames import frame_matrix
from methods.core.stable import canonical_svd
from methods.core.visibility import DEFAULT_OFFSET_EPS, offset_origins

# The materials return 0 for z <= 0; look-up-table nodes on the horizon are evaluated this far
# above it (the one-sided limit), so bilinear weights near the horizon see the true values.
HORIZON_Z = 1e-4
# Terms with S_k below this fraction of S_1 are numerically zero: the stacked matrix has lower rank
# than K (e.g. a Lambert material has rank 1) and their Nyström extension would divide by ~0.
RANK_RTOL = 1e-7
# Singular values this close (relative) are one degenerate group (`factorize`'s ``complete``); the
# (cos θ, φ) grid is exactly symmetric under φ → φ + 2π/n, so pairs agree to round-off.
DEGENERATE_RTOL = 1e-6
# Fraction of the way towards its faces' centroid at which a vertex's visibility is sampled
# (`visibility_points`): far above float32 error, far below the size of a face.
INWARD_PULL = 1e-2


# -- the BRDF factorization (eq. 2) -------------------------------------------------------------


NORMS = ("brdf", "cosine")
# Mahajan 2008 Fig. 3A: K captures 99 % of the energy Σ σ_k² (of the matrix that is factorized).
ENERGY_FRACTION = 0.99


@dataclass
class Factorization:
    """In-out factorization of one material on the hemisphere grid (Mahajan 2008 eq. 2), in a norm.

    The factorized kernel is ρ_c(ω_i, ω_o) b(ω_i) ≈ Σ_k σ_k h_{k,c}(ω_o) g_k(ω_i), the SVD in
    L²(a² dω_o) × L²(dω_i) (module docstring, item 1): norm "brdf" has a = b = 1 (eq. 2 as
    written), norm "cosine" has a = cos θ_o, b = cos θ_i.

    sigma: (K,) σ_k of the continuous operator (Δ·S_k), descending.
    g: (K, n²) g_k at the grid directions; h: (K, 3, n²) h_{k,c} at the grid directions.
    dirs: (n², 3) local grid directions (both ω_i and ω_o); delta: cell solid angle Δ.
    w_out: (n²,) a(ω_o); w_in: (n²,) b(ω_i) at the grid directions.
    energy: (r,) all singular values σ (for the captured-energy fraction).
    norm: "brdf" or "cosine".
    """

    sigma: Tensor
    g: Tensor
    h: Tensor
    dirs: Tensor
    delta: float
    energy: Tensor
    w_out: Tensor | None = None
    w_in: Tensor | None = None
    norm: str = "brdf"

    def __post_init__(self) -> None:
        n2 = self.dirs.shape[0]
        if self.w_out is None:
            self.w_out = torch.ones(n2, dtype=self.dirs.dtype)
        if self.w_in is None:
            self.w_in = torch.ones(n2, dtype=self.dirs.dtype)

    @property
    def K(self) -> int:
        return int(self.sigma.numel())

    @property
    def g_hat(self) -> Tensor:
        """(K, n²) ĝ_k = g_k / b at the grid: the factor eq. 3 multiplies by V(ω_i)(n·ω_i)."""
        return self.g / self.w_in

    def captured_energy(self) -> float:
        """Σ_{k≤K} σ_k² / Σ_k σ_k² in the factorization's norm (Mahajan 2008 Fig. 3A's measure)."""
        e = self.energy.square()
        return float(e[: self.K].sum() / e.sum().clamp_min(1e-300))


def _rgb_eval(material: Any, wi: Tensor, wo: Tensor) -> Tensor:
    """ρ_c(ω_i, ω_o) as (..., 3), broadcasting scalar BRDF outputs to RGB."""
    v = material.eval(wi, wo)
    if v.shape == wi.shape[:-1]:
        v = v.unsqueeze(-1).expand(*v.shape, 3)
    if v.shape != (*wi.shape[:-1], 3):
        raise ValueError(f"material.eval returned {tuple(v.shape)} for directions {tuple(wi.shape)}")
    return v


def brdf_rgb_matrix(material: Any, n: int, *, dtype=torch.float64, chunk: int = 256) -> tuple[Tensor, Tensor, float]:
    """The stacked hemisphere BRDF matrix A[(c, o), i] = ρ_c(ω_i^i, ω_o^o), (3n², n²).

    Returns A, the grid directions (n², 3) (``analysis.direction_grid``) and Δ = 2π/n².
    """
    from methods.inout.analysis import cell_solid_angle, direction_grid  # noqa: PLC0415

    d = direction_grid(n, domain="hemisphere", dtype=dtype)
    N = d.shape[0]
    A = torch.empty(3, N, N, dtype=dtype)
    for a in range(0, N, chunk):
        wo = d[a:a + chunk, None, :].expand(-1, N, 3)
        wi = d[None, :, :].expand(wo.shape[0], N, 3)
        A[:, a:a + chunk] = _rgb_eval(material, wi, wo).to(dtype).permute(2, 0, 1)
    return A.reshape(3 * N, N), d, cell_solid_angle(n, "hemisphere")


def norm_weights(dirs: Tensor, norm: str) -> tuple[Tensor, Tensor]:
    """Grid weights (a(ω_o), b(ω_i)), each (n²,), of the factorization norm (module docstring 1)."""
    if norm not in NORMS:
        raise ValueError(f"norm must be one of {NORMS}, got {norm!r}")
    if norm == "brdf":
        one = torch.ones(dirs.shape[0], dtype=dirs.dtype)
        return one, one
    c = dirs[:, 2].clamp_min(0.0)
    return c, c


def factorize(material: Any, n: int, K: int | None, *, norm: str = "brdf",
              frac: float = ENERGY_FRACTION, complete: bool = False) -> Factorization:
    """SVD of the stacked RGB BRDF matrix in ``norm``, truncated to K terms (capped at the rank).

    Mahajan 2008 eq. 2 with the scaling of ``methods.inout.analysis`` (σ_k = Δ·S_k). norm "brdf":
    the matrix of ρ itself (the paper's); "cosine": of cos θ_o ρ cos θ_i (module docstring, item 1).
    K None: the smallest K capturing ``frac`` of Σ σ_k² of that matrix (Fig. 3A's 99 % rule).
    complete (always for K None): raise K to the end of a group of equal singular values. An
    isotropic BRDF's singular values come in equal pairs (cos mφ, sin mφ: the Y_l,±m of eq. 9);
    cutting a pair keeps an arbitrary, round-off-dependent direction of its 2-D singular space —
    an azimuthally anisotropic reflection that changes with the thread count of the SVD.
    """
    if K is not None and (isinstance(K, bool) or not isinstance(K, int) or K < 1):
        raise ValueError(f"K must be a positive int or None, got {K!r}")
    if not 0.0 < frac <= 1.0:
        raise ValueError(f"frac must be in (0, 1], got {frac!r}")
    A, d, delta = brdf_rgb_matrix(material, n)
    a, b = norm_weights(d, norm)
    N = d.shape[0]
    A = A * a.repeat(3)[:, None] * b[None, :]
    # The singular vectors of (near-)equal singular values depend on the reduction order, i.e. on
    # the thread count (issue 17: local vs process-pool runs must agree) and on the machine's
    # instruction set (the same code read 1e-3 different RMSEs with torch's and MKL's vector kernels
    # off); `canonical_svd` runs one LAPACK thread and fixes each cluster's basis from its space
    # (methods.core.stable), so the per-term transport truncation sees the same factors everywhere.
    U, S, Vh = canonical_svd(A)
    if not S[0] > 0:
        raise ValueError(f"the BRDF {material!r} is zero on the hemisphere grid")
    rank = int((S > RANK_RTOL * S[0]).sum())
    if K is None:
        c = torch.cumsum(S.square(), 0)
        K = int(torch.searchsorted(c, frac * c[-1]).item()) + 1
        complete = True
    K = min(K, rank)
    while complete and K < rank and S[K] >= (1.0 - DEGENERATE_RTOL) * S[K - 1]:
        K += 1
    sq = math.sqrt(delta)
    h = (U[:, :K] / sq).T.reshape(K, 3, N) / a  # h_{k,c}(ω_o^o), orthonormal in L²(a² dω_o)
    g = Vh[:K] / sq                              # g_k(ω_i^i), orthonormal in L²(dω_i)
    return Factorization(sigma=S[:K] * delta, g=g, h=h, dirs=d, delta=delta, energy=S * delta,
                         w_out=a, w_in=b, norm=norm)


# -- hemi-octahedral look-up tables -------------------------------------------------------------


def hemioct_encode(d: Tensor) -> Tensor:
    """Local directions (..., 3) with z >= 0 → hemi-octahedral coordinates (..., 2) in [−1, 1]².

    Cigolle et al. 2014 (JCGT 3(2)) hemisphere octahedral map; z < 0 is folded onto z = 0.
    """
    x, y, z = d.unbind(-1)
    s = (x.abs() + y.abs() + z.clamp_min(0.0)).clamp_min(1e-30)
    px, py = x / s, y / s
    return torch.stack([px + py, px - py], -1)


def hemioct_decode(uv: Tensor) -> Tensor:
    """Inverse of `hemioct_encode`: (..., 2) in [−1, 1]² → unit local directions (..., 3)."""
    u, v = uv.unbind(-1)
    px, py = 0.5 * (u + v), 0.5 * (u - v)
    z = 1.0 - px.abs() - py.abs()
    d = torch.stack([px, py, z], -1)
    return d / d.norm(dim=-1, keepdim=True)


def lut_directions(R: int, *, dtype=torch.float64) -> Tensor:
    """(R·R, 3) local directions of the corner-aligned R × R hemi-octahedral nodes, row-major
    (row = v index, col = u index); horizon nodes lifted to z = HORIZON_Z."""
    if R < 2:
        raise ValueError(f"lut_res must be >= 2, got {R}")
    c = torch.linspace(-1.0, 1.0, R, dtype=dtype)
    vv, uu = torch.meshgrid(c, c, indexing="ij")
    d = hemioct_decode(torch.stack([uu, vv], -1)).reshape(-1, 3)
    # lift horizon nodes to z = HORIZON_Z, keeping their azimuth
    xy = d[:, :2]
    lifted = torch.cat([xy * (math.sqrt(1.0 - HORIZON_Z**2) / xy.norm(dim=-1, keepdim=True).clamp_min(1e-30)),
                        torch.full_like(d[:, 2:], HORIZON_Z)], -1)
    return torch.where(d[:, 2:] < HORIZON_Z, lifted, d)


def lut_cell(d: Tensor, R: int) -> tuple[Tensor, Tensor]:
    """The bilinear cell of local directions d (M, 3) on a corner-aligned R × R hemi-octahedral
    table: the flat index (M,) int64 of its first node (row-major, row = v) and the fractions
    (M, 2) (f_u, f_v) in d's dtype. The cell's nodes are base, base + 1, base + R, base + R + 1
    with weights (1−f_u)(1−f_v), f_u(1−f_v), (1−f_u)f_v, f_u f_v (`lut_lookup`)."""
    iu, iv, fu, fv = lut_cell_xyz(*d.unbind(-1), R)
    return iv * R + iu, torch.stack([fu, fv], -1)


def lut_cell_xyz(x: Tensor, y: Tensor, z: Tensor, R: int, *,
                 index_dtype: torch.dtype = torch.int64) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """`lut_cell` of directions given by their components (M,) each: the cell's first column and
    row (M,) of ``index_dtype`` and the fractions f_u, f_v (M,) (the arithmetic of `hemioct_encode`)."""
    s = (x.abs() + y.abs() + z.clamp_min(0.0)).clamp_min(1e-30)
    px, py = x / s, y / s
    h = 0.5 * (R - 1)
    u = ((px + py + 1.0) * h).clamp_(0.0, R - 1)  # continuous node coordinates
    v = ((px - py + 1.0) * h).clamp_(0.0, R - 1)
    iu, iv = u.floor().clamp_(max=R - 2), v.floor().clamp_(max=R - 2)
    return iu.to(index_dtype), iv.to(index_dtype), u - iu, v - iv


def lut_lookup(lut: Tensor, d: Tensor) -> Tensor:
    """Bilinear look-up of an (R·R, C) hemi-octahedral table at local directions d (M, 3) → (M, C).

    Directions below the horizon are folded onto it (callers mask them).
    """
    RR, C = lut.shape
    R = int(round(math.sqrt(RR)))
    if R * R != RR:
        raise ValueError(f"lut must be (R·R, C), got {tuple(lut.shape)}")
    base, f = lut_cell(d.to(lut.dtype), R)
    fu, fv = f[:, :1], f[:, 1:]
    v00 = lut.index_select(0, base)
    v01 = lut.index_select(0, base + 1)
    v10 = lut.index_select(0, base + R)
    v11 = lut.index_select(0, base + R + 1)
    return (v00 * (1 - fu) + v01 * fu) * (1 - fv) + (v10 * (1 - fu) + v11 * fu) * fv


def nystrom_tables(material: Any, fac: Factorization, R: int, *, chunk: int = 512) -> tuple[Tensor, Tensor]:
    """Look-up tables of ĝ_k and σ_k h_{k,c} by the SVD identities (module docstring, item 2).

    Returns:
        g_lut (R·R, K) — ĝ_k = g_k/b at the nodes (the factor T_k multiplies by V (n·ω_i));
        sh_lut (R·R, K·3) — σ_k h_{k,c} at the nodes (index k·3 + c), both float64.
    """
    nodes = lut_directions(R, dtype=torch.float64)
    grid = fac.dirs
    Ng, K = grid.shape[0], fac.K
    M = nodes.shape[0]
    g_lut = torch.empty(M, K, dtype=torch.float64)
    sh_lut = torch.empty(M, K * 3, dtype=torch.float64)
    # (o,c) × k: Δ a(ω_o)² h_{k,c}(ω_o^o); (i, k): Δ b(ω_i) g_k(ω_i^i)
    hw = (fac.h * fac.w_out.square()).permute(2, 1, 0).reshape(Ng * 3, K) * fac.delta
    gw = (fac.g * fac.w_in).T * fac.delta
    for a in range(0, M, chunk):
        x = nodes[a:a + chunk]
        m = x.shape[0]
        # ĝ_k(x) = (1/σ_k) Σ_{o,c} Δ ρ_c(x, ω_o) a(ω_o)² h_{k,c}(ω_o)
        rho = _rgb_eval(material, x[:, None, :].expand(m, Ng, 3), grid[None].expand(m, Ng, 3)).double()
        g_lut[a:a + m] = (rho.reshape(m, Ng * 3) @ hw) / fac.sigma
        # σ_k h_{k,c}(x) = Σ_i Δ ρ_c(ω_i, x) b(ω_i) g_k(ω_i)   (σ_k cancels the 1/σ_k of the identity)
        rho = _rgb_eval(material, grid[None].expand(m, Ng, 3), x[:, None, :].expand(m, Ng, 3)).double()
        sh_lut[a:a + m] = torch.einsum("mic,ik->mkc", rho, gw).reshape(m, K * 3)
    return g_lut, sh_lut


# -- per-vertex transport in the Haar basis (eq. 3) ---------------------------------------------


BUDGETS = ("vertex", "term")
# Floor of the per-vertex budget in terms (module docstring, item 4): n_coeffs × max(K, this).
MIN_BUDGET_TERMS = 4


def transport_haar(g_lut: Tensor, vis, points: Tensor, normals: Tensor, N: int, *,
                   n_coeffs: int | None, supersample: int = 1, select_weights: Tensor | None = None,
                   term_weights: Tensor | None = None, budget: str = "vertex",
                   eps: float = DEFAULT_OFFSET_EPS, progress: bool = False, chunk: int = 64,
                   desc: str = "inout transport") -> Tensor:
    """Sparse Haar coefficients of T̃_k(x, ω_t) = V(x, ω_t) ĝ_k(to_local(ω_t)) max(0, n·ω_t) Ω_t.

    Mahajan 2008 eq. 3 with the solid angle folded in (module docstring, item 3), projected on the
    cube-map Haar basis and truncated (item 4): ``budget="vertex"`` keeps the
    ``n_coeffs``·max(K, MIN_BUDGET_TERMS) largest |c|·σ_k·w of each vertex over all its terms,
    ``"term"`` the ``n_coeffs`` largest |c|·w of every (vertex, k) (Ng 2003).

    Args:
        g_lut: (R·R, K) float table of ĝ_k (`nystrom_tables`).
        vis: ``methods.core.visibility.Visibility`` of the scene.
        points, normals: (V, 3) vertex positions and unit normals (world).
        N: cube face resolution (power of two); supersample: s → s×s sub-directions per texel
            (T averaged with their exact solid angles).
        n_coeffs: kept per (vertex, k), on average over k for ``budget="vertex"``; None keeps all 6N².
        select_weights: optional (6N²,) selection weights (e.g. Haar support areas).
        term_weights: (K,) σ_k, the weight of term k in the image (``budget="vertex"``; None = 1).
        budget: "vertex" or "term" (above).
        eps: shadow-ray origin offset along the normal, relative to the scene size
            (``methods.core.visibility.offset_origins``).
    Returns:
        CSR (V·K, 6N²) float32, row v·K + k the kept coefficients of T̃_k at vertex v (columns
        ascending; int32 indices while they fit).
    """
    from tqdm.auto import tqdm  # noqa: PLC0415

    if points.ndim != 2 or points.shape[1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points, normals must be (V, 3), got {tuple(points.shape)}, {tuple(normals.shape)}")
    if budget not in BUDGETS:
        raise ValueError(f"budget must be one of {BUDGETS}, got {budget!r}")
    K = g_lut.shape[1]
    D = 6 * N * N
    n_keep = D if n_coeffs is None else min(int(n_coeffs), D)
    n_vertex = min(n_keep * max(K, MIN_BUDGET_TERMS), K * D)   # budget="vertex" (item 4, its floor)
    keep_all = n_vertex >= K * D if budget == "vertex" else n_keep >= D
    if term_weights is not None and term_weights.shape != (K,):
        raise ValueError(f"term_weights must be ({K},), got {tuple(term_weights.shape)}")
    s = int(supersample)
    dirs = cubemap.texel_directions_supersampled(N, s, dtype=torch.float32).reshape(-1, 3)  # (D·s², 3)
    w_sub = cubemap.texel_solid_angles(N * s, dtype=torch.float64)
    w_sub = w_sub.reshape(6, N, s, N, s).permute(0, 1, 3, 2, 4).reshape(-1).float()        # (D·s²,) Ω
    g_lut = g_lut.float()
    P = points.detach().cpu().float()
    Nn = normals.detach().cpu().float()
    nV = P.shape[0]
    score_w = torch.ones(K, D)
    if select_weights is not None:
        score_w = score_w * torch.as_tensor(select_weights, dtype=torch.float32).reshape(1, D)
    if budget == "vertex" and term_weights is not None:
        score_w = score_w * term_weights.float().abs().reshape(K, 1)
    counts, cols, vals = [], [], []
    for a in tqdm(range(0, nV, chunk), disable=not progress, desc=desc, unit="chunk"):
        b = min(nV, a + chunk)
        n_ = Nn[a:b]
        cos = n_ @ dirs.T                                   # (v, D·s²) n·ω
        live = cos > 0
        vi, ti = live.nonzero(as_tuple=True)
        w = dirs[ti]                                        # (M, 3) world directions
        o = offset_origins(P[a:b][vi], n_[vi], eps, scale=vis.scale)
        free = ~torch.from_numpy(vis.occluded(o.numpy(), w.numpy())).bool()
        keep = free.nonzero(as_tuple=True)[0]
        vi, ti, w = vi[keep], ti[keep], w[keep]
        wl = (frame_matrix(n_[vi]) @ w.unsqueeze(-1)).squeeze(-1)  # to_local
        gk = lut_lookup(g_lut, wl)                                   # (M, K)
        # T̃ = V g_k cos Ω (sub-texel solid angles sum to the texel's: supersampled average)
        gk = gk * (cos[vi, ti] * w_sub[ti]).unsqueeze(-1)
        T = torch.zeros(b - a, D, K, dtype=torch.float32)
        T.index_put_((vi, ti // (s * s)), gk, accumulate=True)
        T = T.permute(0, 2, 1).reshape(b - a, K, 6, N, N)
        C = cubemap.haar_forward(T).reshape(b - a, K, D)
        if keep_all:
            mask = torch.ones(b - a, K, D, dtype=torch.bool)
        elif budget == "vertex":
            score = (C.abs() * score_w).reshape(b - a, K * D)
            top = torch.topk(score, n_vertex, dim=-1, sorted=False).indices
            mask = torch.zeros(b - a, K * D, dtype=torch.bool).scatter_(1, top, True).view(b - a, K, D)
        else:
            top = torch.topk(C.abs() * score_w, n_keep, dim=-1, sorted=False).indices
            mask = torch.zeros(b - a, K, D, dtype=torch.bool).scatter_(2, top, True)
        counts.append(mask.sum(-1).reshape(-1))
        r, t = mask.reshape((b - a) * K, D).nonzero(as_tuple=True)   # row-major: columns ascend per row
        cols.append(t.to(torch.int32))
        vals.append(C.reshape((b - a) * K, D)[r, t])
    rows = nV * K
    cnt = torch.cat(counts) if counts else torch.zeros(0, dtype=torch.int64)
    crow = torch.zeros(rows + 1, dtype=torch.int64)
    torch.cumsum(cnt, 0, out=crow[1:])
    col = torch.cat(cols) if cols else torch.zeros(0, dtype=torch.int32)
    val = torch.cat(vals) if vals else torch.zeros(0, dtype=torch.float32)
    if int(crow[-1]) < 2**31:
        crow = crow.to(torch.int32)
    else:
        col = col.long()
    with warnings.catch_warnings():  # torch flags sparse CSR as "beta"; the product we use is stable
        warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta state")
        return torch.sparse_csr_tensor(crow, col, val, size=(rows, D), check_invariants=False)


def visibility_points(V: Tensor, F: Tensor, normals: Tensor, frac: float = INWARD_PULL) -> Tensor:
    """Points (Nv, 3) at which eq. 3's V(x, ω) of each vertex is sampled: the vertex moved by
    ``frac`` of the tangential part of (c − x), c the mean centroid of its incident faces.

    A vertex on a contact line (a box standing on the ground: its bottom vertices lie *in* the
    ground plane) is a degenerate visibility sample — every shadow ray starts on the other surface
    and is reported occluded, although the surface a hair above it sees the whole upper sky — and
    per-vertex transport interpolated across a large face carries that darkness over the face.
    Sampling a hair inside the vertex's own faces is the usual cure; the pull is tangential (it
    never moves the point under a curved surface) and 0 for a vertex at the centre of a regular
    one-ring (smooth meshes are unchanged). V (Nv, 3), F (M, 3) int64, normals (Nv, 3) unit.
    """
    if not 0.0 <= frac < 1.0:
        raise ValueError(f"frac must be in [0, 1), got {frac!r}")
    Vd = V.double()
    cen = Vd[F].mean(1)                                              # (M, 3) face centroids
    acc = torch.zeros_like(Vd).index_add_(0, F.reshape(-1), cen.repeat_interleave(3, 0))
    cnt = torch.zeros(V.shape[0], dtype=Vd.dtype).index_add_(0, F.reshape(-1), torch.ones(F.numel(), dtype=Vd.dtype))
    d = torch.where(cnt[:, None] > 0, acc / cnt.clamp_min(1)[:, None] - Vd, torch.zeros_like(Vd))
    n = normals.double()
    d = d - (d * n).sum(-1, keepdim=True) * n                        # tangential part
    return (Vd + frac * d).to(V.dtype)


def _spread_bits(x: Tensor) -> Tensor:
    """Insert two zero bits after each of the 10 low bits of x (int64): the Morton-code spread."""
    x = x & 0x3FF
    x = (x | (x << 16)) & 0x030000FF
    x = (x | (x << 8)) & 0x0300F00F
    x = (x | (x << 4)) & 0x030C30C3
    return (x | (x << 2)) & 0x09249249


def locality_order(points: Tensor) -> Tensor:
    """Permutation (N,) int64 sorting points (N, 3) along a Z-order (Morton) curve of their bounding
    box (10 bits per axis): points close in space get close indices, so the vertices one view sees
    are few runs of consecutive rows (the run time computes c_k per run, ``methods.inout.fast``)."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {tuple(points.shape)}")
    if points.shape[0] == 0:
        return torch.zeros(0, dtype=torch.int64, device=points.device)
    p = points.double()
    lo, hi = p.min(0).values, p.max(0).values
    q = ((p - lo) / (hi - lo).clamp_min(1e-30) * 1023.0).round().long().clamp(0, 1023)
    code = _spread_bits(q[:, 0]) | (_spread_bits(q[:, 1]) << 1) | (_spread_bits(q[:, 2]) << 2)
    return torch.sort(code, stable=True).indices
