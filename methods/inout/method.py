"""The in-out BRDF factorization renderer (Mahajan, Tseng & Ramamoorthi 2008 §2 eq. 2–4, §6).

Precompute (static geometry, static BRDFs):
  * per region's material, the SVD factorization ρ_c(ω_i, ω_o) cos θ_i ≈ Σ_k σ_k h_{k,c}(ω_o) g_k(ω_i)
    on the hemisphere equal-area grid (eq. 2; ``brdf_res`` × ``brdf_res`` per direction) in the
    cosine-weighted norm of ``methods.inout.transport`` (docstring item 1: why), with K capturing
    99 % of that norm's energy and at least the paper's rule ``analysis.k_rule`` (eq. 13, §4) for
    the families it covers, unless ``terms`` overrides it (``InOut._factorize``; K per region and
    how it was chosen are in ``stats["regions"]``), and the off-grid factors by the SVD identities
    tabulated on a fine hemi-octahedral table (``methods.inout.transport``, docstring item 2);
  * per vertex of the region, T̃_k(x, ω_t) = V(x', ω_t) ĝ_k(to_local(ω_t)) max(0, n·ω_t) Ω_t on a
    ``cube_res`` cube map (eq. 3, texel solid angle Ω_t folded in), Haar-transformed, keeping the
    ``n_coeffs`` largest coefficients per (vertex, k) (Ng 2003), stored as a CSR matrix (V·K, 6N²);
    x' is the vertex moved a hair into its faces (``transport.visibility_points``: a vertex on a
    contact line would otherwise see every shadow ray blocked).

Render (dynamic lighting and view):
  * L = frame.envmap resampled on the cube map (``light_supersample``² sub-samples per texel, exact
    sub-texel solid angles) → Haar (all coefficients, or the ``light_coeffs`` largest
    area-weighted ones, Ng 2003 §5);
  * per vertex c_k = T̃_k · L = ∫ T_k L dω (eq. 4's dot product; one sparse-dense product);
    cached between frames whose ``changed`` does not contain "light" (c_k is view-independent, so
    V-only frames skip it entirely);
  * per G-buffer sample: c_k interpolated barycentrically from the vertices, h_k evaluated at the
    sample's *own* ω_o in its own shading frame (better than evaluating eq. 4 per vertex and
    interpolating radiance, which would blur highlights across triangles, and as cheap: h_k is a
    table look-up), B = Σ_k σ_k h_k(ω_o) c_k (eq. 4).

Direct lighting only. Materials are the scene's (``frame.materials`` are not read: the BRDF is
baked into T_k; sequences that change BRDFs are outside ``capabilities``). Isotropic families only
(the tables are in the local frame of ``methods.core.frames.coordinate_system``, which is not a
tangent frame a Ward BRDF could be authored in).
"""
from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from methods.base import Capabilities, Frame, GBuffer, Method, register, tensor_bytes
from methods.core import cubemap
from methods.core.frames import frame_matrix
from references.visibility import make_visibility
from methods.inout import transport as tp

# Families with a closed-form K rule of the paper (analysis.k_rule: eq. 13 and §4).
PAPER_RULE_KINDS = frozenset({"lambert", "phong", "blinnphong", "torrancesparrow"})
# Floats per (Q, K, 3) temporary in render(): samples per batch = RENDER_FLOATS / (3K) (~16 MB).
RENDER_FLOATS = 1 << 22


@dataclass
class _Region:
    """Run-time data of one region (one material)."""

    name: str
    K: int                 # terms used (after capping at the numerical rank)
    K_requested: int       # k_rule / `terms` before capping
    captured: float        # Σ_{k≤K} σ_k² / Σ σ_k² of the BRDF matrix
    verts: Tensor          # (Vr,) int64 global vertex ids this region's faces touch
    local_of: Tensor       # (Nv,) int64 global vertex id → row in verts (−1 if absent)
    T: Tensor              # CSR (Vr·K, 6N²) float32 Haar coefficients of T̃_k (eq. 3)
    sh_lut: Tensor         # (R·R, K·3) float32 σ_k h_{k,c} on the hemi-octahedral table
    sigma: Tensor          # (K,) float32 (reporting only; σ is folded into sh_lut)
    c: Tensor | None = None  # (Vr, K, 3) float32 cached T̃_k · L of the current lighting


def _check_int(name: str, v: Any, lo: int, *, none_ok: bool = False) -> None:
    if v is None and none_ok:
        return
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise ValueError(f"{name} must be an int >= {lo}{' or None' if none_ok else ''}, got {v!r}")


@register
class InOut(Method):
    """In-out BRDF factorization PRT with Haar cube-map transport (Mahajan 2008 eq. 2–4)."""

    name = "inout"
    cache_precompute = True  # the cells of one scene/config share one stored precomputation
    capabilities = Capabilities(
        dynamic_lighting=True, dynamic_brdf=False, dynamic_geometry=False,
        max_bounces=0,
        brdfs=frozenset({"lambert", "phong", "blinnphong", "cooktorrance", "torrancesparrow"}))

    def __init__(self, *, terms: int | dict[str, int] | None = None, brdf_res: int = 24,
                 cube_res: int = 16, n_coeffs: int | None = 128, light_coeffs: int | None = None,
                 lut_res: int = 64, supersample: int = 1, light_supersample: int = 4,
                 select: str = "magnitude", norm: str = "cosine", progress: bool | None = None) -> None:
        """
        terms: K for every region (int), per region name (dict; missing regions use the rule),
            or None = ``analysis.k_rule(material)`` (Mahajan 2008 eq. 13 / §4).
        brdf_res: n of the n × n (cos θ, φ) hemisphere grid per direction of the SVD (paper: 40).
        cube_res: cube-map face resolution N (power of two) of T and L.
        n_coeffs: Haar coefficients kept per (vertex, k) (None = all 6N²).
        light_coeffs: Haar coefficients of L kept per frame (None = all).
        lut_res: nodes per side of the hemi-octahedral tables of g_k and σ_k h_k.
        supersample: s×s sub-directions per cube texel when building T (visibility, g, cosine).
        light_supersample: sub-samples per texel side when resampling the env map.
        select: "magnitude" (plain |c| of the solid-angle-weighted T̃: L²-optimal) or "area"
            (|c| × Haar support solid angle, Ng 2003's area-weighted selection) for T.
        norm: the norm of the factorization and of its 99 %-energy term count (``transport``
            docstring, item 1): "cosine" (default) factorizes cos θ_o ρ cos θ_i, "brdf" factorizes
            ρ as eq. 2 is written (renders BRDFs with a 1/(cos θ_i cos θ_o) factor, such as
            Cook–Torrance, nearly black: kept for comparison).
        progress: tqdm bars (default: when stderr is a TTY).
        """
        if terms is not None and not isinstance(terms, dict):
            _check_int("terms", terms, 1)
        if isinstance(terms, dict):
            for k, v in terms.items():
                _check_int(f"terms[{k!r}]", v, 1)
        _check_int("brdf_res", brdf_res, 2)
        _check_int("cube_res", cube_res, 1)
        if cube_res & (cube_res - 1):
            raise ValueError(f"cube_res must be a power of two, got {cube_res}")
        _check_int("n_coeffs", n_coeffs, 1, none_ok=True)
        _check_int("light_coeffs", light_coeffs, 1, none_ok=True)
        _check_int("lut_res", lut_res, 2)
        _check_int("supersample", supersample, 1)
        _check_int("light_supersample", light_supersample, 1)
        if select not in ("magnitude", "area"):
            raise ValueError(f"select must be 'magnitude' or 'area', got {select!r}")
        if norm not in tp.NORMS:
            raise ValueError(f"norm must be one of {tp.NORMS}, got {norm!r}")
        super().__init__(terms=terms, brdf_res=brdf_res, cube_res=cube_res, n_coeffs=n_coeffs,
                         light_coeffs=light_coeffs, lut_res=lut_res, supersample=supersample,
                         light_supersample=light_supersample, select=select, norm=norm)
        self.progress = sys.stderr.isatty() if progress is None else bool(progress)
        self.scene = None
        self.F: Tensor | None = None           # (M, 3) int64 faces of the static geometry
        self.regions: list[_Region] = []
        self.L: Tensor | None = None           # (6N², 3) float32 Haar coefficients of the lighting
        self.stats: dict[str, Any] = {}        # precompute timings and per-region K
        self._last_samples = 0

    # -- precompute ---------------------------------------------------------------------------
    def _terms_for(self, region: str, material) -> int | None:
        """K from ``terms`` for this region, or None (choose by rule, `precompute`)."""
        t = self.config["terms"]
        if isinstance(t, int):
            return t
        if isinstance(t, dict) and region in t:
            return int(t[region])
        return None

    def _factorize(self, region: str, material) -> tuple[tp.Factorization, dict[str, Any]]:
        """The region's factorization and how its K was chosen (the ``stats`` entry).

        Explicit ``terms``: that K. norm "brdf": ``analysis.k_rule`` (Mahajan 2008 eq. 13, §4), the
        paper's rules, in the BRDF's own norm. norm "cosine" (default): the paper's 99 %-energy
        criterion (Fig. 3A) applied to the matrix the renderer factorizes, cos θ_o ρ cos θ_i
        (``transport`` docstring, item 1, for why this norm); for the families with a closed-form
        rule of the paper (Lambert, Phong eq. 13, half-angle §4) K is never below that rule, so
        they keep the paper's K (or more).
        """
        from methods.inout.analysis import k_rule  # noqa: PLC0415

        cfg = self.config
        n, norm = cfg["brdf_res"], cfg["norm"]
        K_req = self._terms_for(region, material)
        info: dict[str, Any] = {"norm": norm, "K_requested": K_req}
        if K_req is not None:
            info["K_source"] = "terms"
            return tp.factorize(material, n, K_req, norm=norm), info
        if norm == "brdf":  # the pre-cosine behaviour, kept as it was (no group completion)
            K_req = int(k_rule(material))
            info.update(K_requested=K_req, K_source="k_rule")
            return tp.factorize(material, n, K_req, norm=norm), info
        fac = tp.factorize(material, n, None, norm=norm)          # K(99 %) in the cosine norm
        info.update(K_requested=fac.K, K_energy=fac.K, K_source="energy99_cosine")
        if getattr(material, "kind", "") in PAPER_RULE_KINDS:
            rule = int(k_rule(material))
            info["K_rule"] = rule
            if rule > fac.K:
                fac = tp.factorize(material, n, rule, norm=norm, complete=True)
                info.update(K_requested=rule, K_source="k_rule")
        return fac, info

    def precompute(self, scene) -> None:
        cfg = self.config
        N = cfg["cube_res"]
        D = 6 * N * N
        geom = scene.geometry()
        V = torch.as_tensor(geom.V).float().cpu()
        F = torch.as_tensor(geom.F).long().cpu()
        Nrm = torch.nn.functional.normalize(torch.as_tensor(geom.N).float().cpu(), dim=-1)
        face_region = torch.as_tensor(geom.face_region).long().cpu()
        if V.ndim != 2 or V.shape[1] != 3 or F.ndim != 2 or F.shape[1] != 3 or Nrm.shape != V.shape:
            raise ValueError(f"bad geometry: V {tuple(V.shape)}, F {tuple(F.shape)}, N {tuple(Nrm.shape)}")
        vis = make_visibility(V, F)
        Vs = tp.visibility_points(V, F, Nrm)  # V(x, ω) sampled a hair inside the vertex's faces
        weights = None
        if cfg["select"] == "area":
            weights = cubemap.haar_support_area(N, solid_angle=True).reshape(-1)
        t0 = time.perf_counter()
        self.regions = []
        self.stats = {"regions": {}}
        for r, name in enumerate(scene.regions):
            faces = (face_region == r).nonzero(as_tuple=True)[0]
            if faces.numel() == 0:
                continue
            mat = scene.materials[name]
            if getattr(mat, "kind", "") not in self.capabilities.brdfs:
                raise ValueError(f"region {name!r}: BRDF family {getattr(mat, 'kind', type(mat).__name__)!r}"
                                 " is not supported by inout (isotropic families only)")
            ta = time.perf_counter()
            fac, kinfo = self._factorize(name, mat)                      # Mahajan 2008 eq. 2
            K_req = int(kinfo["K_requested"])
            g_lut, sh_lut = tp.nystrom_tables(mat, fac, cfg["lut_res"])
            tb = time.perf_counter()
            verts = torch.unique(F[faces].reshape(-1))
            local_of = torch.full((V.shape[0],), -1, dtype=torch.int64)
            local_of[verts] = torch.arange(verts.numel())
            idx, val = tp.transport_haar(g_lut, vis, Vs[verts], Nrm[verts], N,  # eq. 3 + Haar
                                         n_coeffs=cfg["n_coeffs"], supersample=cfg["supersample"],
                                         select_weights=weights, progress=self.progress,
                                         desc=f"inout T[{name}]")
            tc = time.perf_counter()
            self.regions.append(_Region(
                name=name, K=fac.K, K_requested=K_req, captured=fac.captured_energy(), verts=verts,
                local_of=local_of, T=tp.sparse_rows(idx, val, D), sh_lut=sh_lut.float(),
                sigma=fac.sigma.float()))
            self.stats["regions"][name] = {**kinfo, "K": fac.K, "K_requested": K_req,
                                           "captured_energy": fac.captured_energy(),
                                           "vertices": int(verts.numel()),
                                           "brdf_seconds": tb - ta, "transport_seconds": tc - tb}
        self.stats["precompute_seconds"] = time.perf_counter() - t0
        self.scene = scene
        self.F = F
        self.L = None

    # -- render -------------------------------------------------------------------------------
    def _lighting(self, envmap) -> Tensor:
        """(6N², 3) Haar coefficients of the env map's texel radiance (module docstring)."""
        cfg = self.config
        N = cfg["cube_res"]
        Lt = cubemap.from_radiance(envmap.radiance, N, supersample=cfg["light_supersample"])  # (6,N,N,3)
        C = cubemap.haar_forward(Lt.permute(3, 0, 1, 2)).reshape(3, -1)                        # (3, 6N²)
        if cfg["light_coeffs"] is not None:
            # Ng 2003 §5: keep the largest area-weighted coefficients, selected on the channel sum
            w = cubemap.haar_support_area(N, solid_angle=True).reshape(-1)
            idx, _ = cubemap.keep_largest(C.abs().sum(0), cfg["light_coeffs"], weights=w)
            C = torch.zeros_like(C).index_copy_(1, idx, C.index_select(1, idx))
        return C.T.contiguous().float()

    def render(self, frame: Frame, gbuffer: GBuffer) -> Tensor:
        if self.scene is None:
            raise RuntimeError("call precompute(scene) before render()")
        relight = self.L is None or "light" in frame.changed
        if relight:
            self.L = self._lighting(frame.envmap)
            for reg in self.regions:
                # c_k = T̃_k · L = ∫ T_k L dω (Mahajan 2008 eq. 4), per vertex and colour
                reg.c = (reg.T @ self.L).view(reg.verts.numel(), reg.K, 3)
        P = gbuffer.num_samples
        self._last_samples = P
        out = torch.zeros(P, 3, dtype=torch.float32)
        vidx, bw = gbuffer.vertex_weights(self.F)  # (P, 3) global vertex ids, barycentric weights
        for r_index, name in enumerate(self.scene.regions):
            reg = next((x for x in self.regions if x.name == name), None)
            if reg is None:
                continue
            sel = (gbuffer.hit & (gbuffer.region == r_index)).nonzero(as_tuple=True)[0]
            chunk = max(256, RENDER_FLOATS // (3 * reg.K))
            for a in range(0, sel.numel(), chunk):
                s = sel[a:a + chunk]
                out[s] = self._shade(reg, vidx[s], bw[s].float(), gbuffer.normal[s].float(),
                                     gbuffer.wo[s].float())
        return gbuffer.resolve(out)

    @staticmethod
    def _shade(reg: _Region, vidx: Tensor, bw: Tensor, n: Tensor, wo: Tensor) -> Tensor:
        """B = Σ_k σ_k h_k(ω_o) c_k for samples (Q,) (Mahajan 2008 eq. 4) → (Q, 3)."""
        loc = reg.local_of[vidx]                                   # (Q, 3)
        if (loc < 0).any():
            raise ValueError(f"G-buffer samples of region {reg.name!r} lie on faces of another region")
        c = reg.c[loc[:, 0]] * bw[:, 0, None, None]                # (Q, K, 3) barycentric c_k
        c += reg.c[loc[:, 1]] * bw[:, 1, None, None]
        c += reg.c[loc[:, 2]] * bw[:, 2, None, None]
        n = torch.nn.functional.normalize(n, dim=-1)
        wl = (frame_matrix(n) @ wo.unsqueeze(-1)).squeeze(-1)      # ω_o in the sample's frame
        sh = tp.lut_lookup(reg.sh_lut, wl).view(-1, reg.K, 3)      # σ_k h_{k,c}(ω_o)
        B = (sh * c).sum(1)
        return torch.where(wl[:, 2:] > 0, B, torch.zeros_like(B))  # ρ = 0 for ω_o below the horizon

    # -- accounting ---------------------------------------------------------------------------
    def memory(self) -> dict[str, int]:
        m: dict[str, int] = {}
        for reg in self.regions:
            T = reg.T
            m[f"{reg.name}/T_values"] = tensor_bytes(T.values())
            m[f"{reg.name}/T_columns"] = tensor_bytes(T.col_indices())
            m[f"{reg.name}/T_rows"] = tensor_bytes(T.crow_indices())
            m[f"{reg.name}/sh_lut"] = tensor_bytes(reg.sh_lut)
            m[f"{reg.name}/vertex_map"] = tensor_bytes(reg.verts, reg.local_of)
            m[f"{reg.name}/c"] = tensor_bytes(reg.c) if reg.c is not None else 4 * reg.verts.numel() * reg.K * 3
        m["faces"] = tensor_bytes(self.F)
        N = self.config["cube_res"]
        m["L"] = tensor_bytes(self.L) if self.L is not None else 4 * 6 * N * N * 3
        return m

    def bytes_per_frame(self, frame_kind: str = "VBL") -> int | None:
        """Bytes read/written by one frame: the G-buffer inputs and c_k/h_k tables per sample
        (every frame), plus T, L and the c_k write when the lighting changes ("L" in the kind)."""
        if self.scene is None:
            return None
        N = self.config["cube_res"]
        P = self._last_samples
        total = P * (8 + 8 + 12 + 12 + 8 + 1 + 12)  # face, bary, normal, wo, region, hit, output
        for reg in self.regions:
            cb = 4 * reg.verts.numel() * reg.K * 3
            total += tensor_bytes(reg.sh_lut) + cb
            if "L" in frame_kind:
                T = reg.T
                total += tensor_bytes(T.values(), T.col_indices(), T.crow_indices()) + cb
        if "L" in frame_kind:
            total += 4 * 6 * N * N * 3
        return int(total)
