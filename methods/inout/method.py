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
    largest σ_k-weighted coefficients of each vertex over all its terms, ``n_coeffs`` × K of them
    (``budget="vertex"``; ``transport`` docstring item 4: why not ``n_coeffs`` per (vertex, k), Ng
    2003's per-function rule, ``budget="term"``), stored as a CSR matrix (V·K, 6N²)
    with the region's vertices in Morton order (``transport.locality_order``: the vertices one view
    sees are few runs of rows, for the run time's lazy c_k); x' is the vertex moved a hair into its
    faces (``transport.visibility_points``: a vertex on a contact line would otherwise see every
    shadow ray blocked).

Render (dynamic lighting and view):
  * L = frame.envmap resampled on the cube map (``light_supersample``² sub-samples per texel, exact
    sub-texel solid angles) → Haar (all coefficients, or the ``light_coeffs`` largest
    area-weighted ones, Ng 2003 §5);
  * per vertex c_k = T̃_k · L = ∫ T_k L dω (eq. 4's dot product; one sparse-dense product);
    cached between frames whose ``changed`` does not contain "light" (c_k is view-independent, so
    V-only frames skip it entirely); the fast path computes it for every vertex under the first
    lighting (the start-up lighting an application sets once), lazily for the referenced vertices
    under later lighting changes (`InOut._ensure_c`);
  * per G-buffer sample: c_k interpolated barycentrically from the vertices, h_k evaluated at the
    sample's *own* ω_o in its own shading frame (better than evaluating eq. 4 per vertex and
    interpolating radiance, which would blur highlights across triangles), B = Σ_k σ_k h_k(ω_o) c_k
    (eq. 4).

  * or, with ``shading="vertex"``, eq. 4 per vertex as the paper renders (§6, "interactive at 17K
    vertices"): B_v = Σ_k σ_k h_k(ω_o) c_k with ω_o towards the camera from the vertex in the
    vertex's frame (0 below its horizon), Gouraud-interpolated to the samples with the G-buffer's
    barycentrics (``methods.core.gouraud``). Only the vertices of the faces the hit samples lie on
    are shaded, and the view part (those vertices and their table cells) is kept while the camera
    and the G-buffer's hits are unchanged, so a lighting-only frame recomputes c_k and B_v only.
    A view frame under the first lighting (every c_k computed) is one C loop over the pixels
    (``methods.inout.native_vframe``: the referenced faces, their vertices, eq. 4 at those vertices and
    the Gouraud resolve in one OpenMP region; the split path's image bit for bit).
    Its cost is per vertex, not per sample; its error follows the mesh density (a highlight or a
    shadow edge narrower than a triangle is blurred): RMSE against the references 1.00–1.11× the
    per-sample shading's at bench size (perf suite: chess, creature; sphere_plane V 1.03×, E
    1.00×), 1.0–1.9× at test size (coarse meshes: sphere_plane, shadow_detail, dragon, character
    the worst); no region mean ratio leaves [0.9, 1.1] where the per-sample one stays inside
    (measured 2026-12-03 on V and E frames; the table is in the commit message that added this).

`_render_reference` does exactly this, step by step (the test oracle); `render` computes the same
image to float32 round-off with the sums regrouped (``methods.inout.fast``): c_k, after the first
lighting, only for the vertices the samples reference, and eq. 4 reassociated through per-vertex products with the
σ_k h_k table — per sample as one C loop over the samples when it builds (``methods.inout.native_sample``,
`_render_native`: the products formed at the (vertex, node) pairs the samples read, while they are
shaded), else by the compiled passes of ``fast`` (its fallback and test oracle). `frame_cost` states the compulsory bytes and flops of each frame kind.

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

from methods.base import (GBUFFER_BYTES_PER_SAMPLE, GBUFFER_HIT_BYTES, Capabilities, Frame, FrameCost, GBuffer, Method,
                          geometry_key, output_bytes, precompute_memo, register, tensor_bytes)
from methods.core import cubemap, gouraud
from methods.core.fused import map_rows, warm_blocks
from methods.core.frames import frame_matrix
from references.visibility import make_visibility
from scenes.hashing import hash_materials
from methods.inout import csr as _csr
from methods.inout import fast as _fast
from methods.inout import native as _native
from methods.inout import native_sample as _nsample
from methods.inout import native_vframe as _nvframe
from methods.inout import transport as tp

# Families with a closed-form K rule of the paper (analysis.k_rule: eq. 13 and §4).
PAPER_RULE_KINDS = frozenset({"lambert", "phong", "blinnphong", "torrancesparrow"})
# Floats per (Q, K, 3) temporary in `_render_reference`: samples per batch = RENDER_FLOATS / (3K) (~16 MB).
RENDER_FLOATS = 1 << 22
# `render` shades every G-buffer sample (misses with weight 0) when at least this fraction hits,
# else gathers the hits first (a gather of every per-sample array costs more than a few misses).
DENSE_HIT_FRACTION = 0.75
# Relative margin of `_view_setup`'s shaded-sample test (a superset of the per-sample stage's).
SHADED_MARGIN = 1e-4
# Where eq. 4 is evaluated (``shading``): per G-buffer sample, or per vertex and Gouraud-interpolated.
SHADINGS = ("sample", "vertex")


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


@dataclass
class _View:
    """One frame's fast-path set-up (`InOut._view_setup`): the shaded samples — all P (misses with
    weight 0) when ``sel`` is None, else the hits ``sel`` (Q,) —, the c of each
    region (``cs``) and the windows' products (``wins``)."""

    gbuffer: GBuffer
    st: Any
    sel: Tensor | None
    Q: int
    cs: list = None
    wins: Any = None
    ref: Any = None


def _face_mask(face: Tensor, M: int) -> Tensor:
    """(M,) bool: which of the M faces occur in ``face`` (q,) int32 or int64, values in [0, M] (M: none, dropped).
    A histogram (``torch.bincount``) rather than ``mask[face] = True``: the q ≈ 2.6·10⁵ bench samples
    index ~6·10³ faces, and the indexed store with that many repeats took 2.4× the histogram (chess
    bench G-buffer, 1 thread, process CPU time, load ~11: 1.2 vs 0.5 ms)."""
    return torch.bincount(face, minlength=M + 1)[:M] > 0


def _check_int(name: str, v: Any, lo: int, *, none_ok: bool = False) -> None:
    if v is None and none_ok:
        return
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise ValueError(f"{name} must be an int >= {lo}{' or None' if none_ok else ''}, got {v!r}")


def _shaded_faces_inputs(gbuffer: GBuffer, st, sel: Tensor | None) -> tuple[list[Tensor], tuple]:
    """The row tensors and arguments of ``fast.shaded_faces_cols`` (`InOut._view_refs`'s referenced-face
    pass) for every sample (``sel`` None) or the samples ``sel``: ω_o as columns (no transposing copy of a
    column-major ω_o), the face-region table with its length marked dynamic (one variant per scene)."""
    if sel is None:
        rows = [gbuffer.normal, *gbuffer.wo.unbind(1), gbuffer.face, gbuffer.region, gbuffer.hit]
    else:
        rows = [_fast.take_rows(gbuffer.normal, sel), *gbuffer.wo.T.index_select(1, sel).unbind(0),
                gbuffer.face.index_select(0, sel), gbuffer.region.index_select(0, sel),
                torch.ones(sel.numel(), dtype=torch.bool, device=sel.device)]
    torch._dynamo.maybe_mark_dynamic(st.face_region, 0)       # the scene's face count: one variant
    return [r.float() if r.is_floating_point() else r for r in rows], (st.face_region, SHADED_MARGIN)


@register
class InOut(Method):
    """In-out BRDF factorization PRT with Haar cube-map transport (Mahajan 2008 eq. 2–4)."""

    name = "inout"
    cache_precompute = True  # the cells of one scene/config share one stored precomputation
    render_config_keys = ("shading",)  # where eq. 4 is evaluated: run time only
    # lightings set since the last `_reset_cache` (a class default: a state stored by older code has
    # no such attribute); `_ensure_c` computes every vertex's c under the first one
    _lightings: int = 0
    _vmemo = None   # (as `_lightings`: a state stored by older code has none)
    _vstamp: int = 0
    _vcall = None   # `native_vframe.bind`'s bound call (state of older code: none)
    _xcall = None   # `native_sample.bind`'s
    capabilities = Capabilities(
        dynamic_lighting=True, dynamic_brdf=False, dynamic_geometry=False,
        max_bounces=0,
        brdfs=frozenset({"lambert", "phong", "blinnphong", "cooktorrance", "torrancesparrow"}))

    def __init__(self, *, terms: int | dict[str, int] | None = None, brdf_res: int = 24,
                 cube_res: int = 16, n_coeffs: int | None = 256, light_coeffs: int | None = None,
                 lut_res: int = 64, supersample: int = 1, light_supersample: int = 4,
                 select: str = "magnitude", norm: str = "cosine", budget: str = "vertex",
                 shading: str = "sample", progress: bool | None = None) -> None:
        """
        terms: K for every region (int), per region name (dict; missing regions use the rule),
            or None = ``analysis.k_rule(material)`` (Mahajan 2008 eq. 13 / §4).
        brdf_res: n of the n × n (cos θ, φ) hemisphere grid per direction of the SVD (paper: 40).
        cube_res: cube-map face resolution N (power of two) of T and L.
        n_coeffs: Haar coefficients kept per (vertex, k) — on average over k with
            ``budget="vertex"`` (None = all 6N²); 256 (``transport`` docstring, item 4: 128 left a
            Phong box of the example scene at 0.87 of the reference under one captured probe).
        budget: "vertex" (default): each vertex keeps its n_coeffs·K largest σ_k-weighted
            coefficients over all terms; "term": n_coeffs per (vertex, k) (``transport``
            docstring, item 4).
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
        shading: "sample" (default): eq. 4 per G-buffer sample, each at its own ω_o (module
            docstring); "vertex": eq. 4 per vertex with ω_o towards the camera from the vertex,
            the radiance Gouraud-interpolated to the samples (the paper's run time, §6:
            "interactive at 17K vertices"; ``methods.core.gouraud``).
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
        if budget not in tp.BUDGETS:
            raise ValueError(f"budget must be one of {tp.BUDGETS}, got {budget!r}")
        if shading not in SHADINGS:
            raise ValueError(f"shading must be one of {SHADINGS}, got {shading!r}")
        super().__init__(terms=terms, brdf_res=brdf_res, cube_res=cube_res, n_coeffs=n_coeffs,
                         light_coeffs=light_coeffs, lut_res=lut_res, supersample=supersample,
                         light_supersample=light_supersample, select=select, norm=norm, budget=budget,
                         shading=shading)
        self.progress = sys.stderr.isatty() if progress is None else bool(progress)
        self.scene = None
        self.F: Tensor | None = None           # (M, 3) int64 faces of the static geometry
        self.regions: list[_Region] = []
        self.L: Tensor | None = None           # (6N², 3) float32 Haar coefficients of the lighting
        self.stats: dict[str, Any] = {}        # precompute timings and per-region K
        self._c: dict[str, Tensor] = {}        # region → (Vr, K, 3) c_k = T̃_k · L (reference path)
        self._cf: dict[str, Tensor] = {}       # region → (Vr, 3, K) the same for the fast path, filled lazily:
        self._cf_valid: dict[str, Tensor] = {}  # region → (Vr,) bool, which rows of _cf are computed
        self._cf_full: dict[str, Tensor] = {}   # region → its _cf_valid tensor when every row was computed at once
        self._fast = None                      # the fast path's static arrays (`_fast_static`), built on first use
        self._last_view = None                 # (P, what `frame_cost` counts) of the last fast render
        self._env_shape = None                 # (H, W) of the env map of the current lighting
        self._vview = None                     # shading "vertex": the view's referenced vertices (`_vertex_view`)
        self._xmemo = None                     # shading "sample", the C loop: its memo of X (`native_sample.memo`)
        self._xstamp = 0                       # frames shaded on that memo
        self._xcall = None                     # and the loop's bound call (`native_sample.bind`)
        self._vmemo = None                     # shading "vertex", the C loop: its memo of B_v (`native_vframe.memo`)
        self._vstamp = 0                       # frames shaded on that memo
        self._vcall = None                     # and the loop's bound call (`native_vframe.bind`)

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
        memo = precompute_memo()
        gkey = geometry_key(V, F, Nrm, face_region) if memo is not None else None
        for r, name in enumerate(scene.regions):
            faces = (face_region == r).nonzero(as_tuple=True)[0]
            if faces.numel() == 0:
                continue
            mat = scene.materials[name]
            if getattr(mat, "kind", "") not in self.capabilities.brdfs:
                raise ValueError(f"region {name!r}: BRDF family {getattr(mat, 'kind', type(mat).__name__)!r}"
                                 " is not supported by inout (isotropic families only)")
            # shared precompute (methods.base.shared_precompute): a region is a function of the
            # geometry, its faces, its material, its K setting and every other config value. Only
            # regions whose K is chosen by rule are shared: a region with an explicit ``terms`` K
            # is the one a term ladder varies (sharing it would keep every rung's T alive for
            # nothing)
            mkey = None
            if memo is not None and self._terms_for(name, mat) is None:
                mkey = ("inout.region", gkey, r, name, hash_materials({name: mat}), self._terms_for(name, mat),
                        tuple(sorted((k, v) for k, v in cfg.items() if k not in ("terms", "shading"))))
                if mkey in memo:
                    region, rstats = memo[mkey]
                    self.regions.append(region)
                    self.stats["regions"][name] = {**rstats, "shared": True}
                    continue
            ta = time.perf_counter()
            fac, kinfo = self._factorize(name, mat)                      # Mahajan 2008 eq. 2
            K_req = int(kinfo["K_requested"])
            g_lut, sh_lut = tp.nystrom_tables(mat, fac, cfg["lut_res"])
            tb = time.perf_counter()
            verts = torch.unique(F[faces].reshape(-1))
            verts = verts[tp.locality_order(V[verts])]  # Morton order: a view's vertices are few runs of rows
            local_of = torch.full((V.shape[0],), -1, dtype=torch.int64)
            local_of[verts] = torch.arange(verts.numel())
            T = tp.transport_haar(g_lut, vis, Vs[verts], Nrm[verts], N,  # eq. 3 + Haar
                                  n_coeffs=cfg["n_coeffs"], supersample=cfg["supersample"],
                                  select_weights=weights, term_weights=fac.sigma[:fac.K].float(),
                                  budget=cfg["budget"], progress=self.progress, desc=f"inout T[{name}]")
            tc = time.perf_counter()
            self.regions.append(_Region(
                name=name, K=fac.K, K_requested=K_req, captured=fac.captured_energy(), verts=verts,
                local_of=local_of, T=T, sh_lut=sh_lut.float(),
                sigma=fac.sigma.float()))
            self.stats["regions"][name] = {**kinfo, "K": fac.K, "K_requested": K_req,
                                           "captured_energy": fac.captured_energy(),
                                           "vertices": int(verts.numel()),
                                           "brdf_seconds": tb - ta, "transport_seconds": tc - tb}
            if mkey is not None:
                memo[mkey] = (self.regions[-1], dict(self.stats["regions"][name]))
        self.stats["precompute_seconds"] = time.perf_counter() - t0
        self.scene = scene
        self.F = F
        self._fast = None
        self._reset_cache()

    # -- render -------------------------------------------------------------------------------
    def _lighting(self, envmap) -> Tensor:
        """(6N², 3) Haar coefficients of the env map's texel radiance (module docstring)."""
        cfg = self.config
        N = cfg["cube_res"]
        Lt = cubemap.from_envmap(envmap, N, supersample=cfg["light_supersample"])  # (6,N,N,3)
        C = cubemap.haar_forward(Lt.permute(3, 0, 1, 2)).reshape(3, -1)                        # (3, 6N²)
        if cfg["light_coeffs"] is not None:
            # Ng 2003 §5: keep the largest area-weighted coefficients, selected on the channel sum
            w = cubemap.haar_support_area(N, solid_angle=True).reshape(-1)
            idx, _ = cubemap.keep_largest(C.abs().sum(0), cfg["light_coeffs"], weights=w)
            C = torch.zeros_like(C).index_copy_(1, idx, C.index_select(1, idx))
        return C.T.contiguous().float()

    def _reset_cache(self) -> None:
        """Forget the lighting and every per-vertex c_k (the next frame recomputes them): gives a
        copy of a precomputed method caches of its own."""
        self.L = None
        self._c, self._cf, self._cf_valid, self._cf_full = {}, {}, {}, {}
        self._lightings = 0
        self._last_view = None
        self._vview = None
        self._xmemo, self._xstamp = None, 0
        self._vmemo, self._vstamp = None, 0
        self._vcall = None
        self._xcall = None

    def _relight(self, frame: Frame) -> None:
        """New lighting when the frame changed it (or none is cached): L, and c_k invalidated."""
        if self.L is not None and "light" not in frame.changed:
            return
        self.L = self._lighting(frame.envmap).to(self.regions[0].T.device if self.regions else "cpu")
        self._env_shape = tuple(int(x) for x in frame.envmap.data.shape[:2])
        self._c, self._cf, self._cf_valid, self._cf_full = {}, {}, {}, {}  # c_k of the new lighting: none computed yet
        self._lightings += 1

    def _region_samples(self, gbuffer: GBuffer):
        """(region, sample indices (Q,)) of the hit samples of every precomputed region."""
        for r_index, name in enumerate(self.scene.regions):
            reg = next((x for x in self.regions if x.name == name), None)
            if reg is not None:
                yield reg, (gbuffer.hit & (gbuffer.region == r_index)).nonzero(as_tuple=True)[0]

    def _render_reference(self, frame: Frame, gbuffer: GBuffer) -> Tensor:
        """The per-sample reference path (the test oracle of `render`): c_k = T̃_k · L for every
        vertex by one sparse-dense product when the lighting changes, then per sample the
        barycentric c̄_k, the bilinear σ_k h_k(ω_o) and their dot product (`_shade`)."""
        if self.scene is None:
            raise RuntimeError("call precompute(scene) before render()")
        self._relight(frame)
        self._ensure_c_reference()
        if self.config["shading"] == "vertex":
            return self._render_vertex_reference(frame, gbuffer)
        P = gbuffer.num_samples
        out = torch.zeros(P, 3, dtype=torch.float32, device=gbuffer.hit.device)
        vidx, bw = gbuffer.vertex_weights(self.F)  # (P, 3) global vertex ids, barycentric weights
        for reg, sel in self._region_samples(gbuffer):
            chunk = max(256, RENDER_FLOATS // (3 * reg.K))
            for a in range(0, sel.numel(), chunk):
                s = sel[a:a + chunk]
                out[s] = self._shade(reg, self._c[reg.name], vidx[s], bw[s].float(), gbuffer.normal[s].float(),
                                     gbuffer.wo[s].float())
        return gbuffer.resolve(out)

    def _ensure_c_reference(self) -> None:
        """The reference paths' c_k of every vertex of every region (one product per lighting)."""
        for reg in self.regions:
            if reg.name not in self._c:
                # c_k = T̃_k · L = ∫ T_k L dω (Mahajan 2008 eq. 4), per vertex and colour
                self._c[reg.name] = (reg.T @ self.L).view(reg.verts.numel(), reg.K, 3)

    def _render_vertex_reference(self, frame: Frame, gbuffer: GBuffer) -> Tensor:
        """Shading "vertex" step by step (the test oracle of `_render_vertex`): eq. 4 at every vertex
        of every region by the per-sample code (`_shade`) evaluated at the vertex — its normal, ω_o
        towards the camera from its position, its own c_k (barycentric weights (1, 0, 0)) — then
        each hit sample's radiance the barycentric mix of its face's three vertex radiances of the
        sample's region (Gouraud, Mahajan 2008 §6), box-filtered (``GBuffer.resolve``)."""
        dev = gbuffer.hit.device
        geom = self.scene.geometry()
        V = torch.as_tensor(geom.V).float().to(dev)
        Nrm = torch.nn.functional.normalize(torch.as_tensor(geom.N).float().to(dev), dim=-1)
        cam = torch.tensor(frame.camera.origin, dtype=torch.float32, device=dev)
        out = torch.zeros(gbuffer.num_samples, 3, dtype=torch.float32, device=dev)
        vidx, bw = gbuffer.vertex_weights(self.F)
        for reg, sel in self._region_samples(gbuffer):
            if bool((reg.local_of[vidx[sel]] < 0).any()):
                raise ValueError(f"G-buffer samples of region {reg.name!r} lie on faces of another region")
            Bv = torch.zeros(V.shape[0], 3, dtype=torch.float32, device=dev)   # radiance of the region's vertices
            chunk = max(256, RENDER_FLOATS // (3 * reg.K))
            for a in range(0, reg.verts.numel(), chunk):
                v = reg.verts[a:a + chunk]
                one = torch.tensor([1.0, 0.0, 0.0], device=dev).expand(v.numel(), 3)
                wo = torch.nn.functional.normalize(cam - V[v], dim=-1)
                Bv[v] = self._shade(reg, self._c[reg.name], v[:, None].expand(-1, 3), one, Nrm[v], wo)
            out[sel] = (Bv[vidx[sel]] * bw[sel].float()[..., None]).sum(1)
        return gbuffer.resolve(out)

    @staticmethod
    def _shade(reg: _Region, c: Tensor, vidx: Tensor, bw: Tensor, n: Tensor, wo: Tensor) -> Tensor:
        """B = Σ_k σ_k h_k(ω_o) c_k for samples (Q,) (Mahajan 2008 eq. 4) → (Q, 3); c (Vr, K, 3)."""
        loc = reg.local_of[vidx]                                   # (Q, 3)
        if (loc < 0).any():
            raise ValueError(f"G-buffer samples of region {reg.name!r} lie on faces of another region")
        cb = c[loc[:, 0]] * bw[:, 0, None, None]                   # (Q, K, 3) barycentric c_k
        cb += c[loc[:, 1]] * bw[:, 1, None, None]
        cb += c[loc[:, 2]] * bw[:, 2, None, None]
        n = torch.nn.functional.normalize(n, dim=-1)
        wl = (frame_matrix(n) @ wo.unsqueeze(-1)).squeeze(-1)      # ω_o in the sample's frame
        sh = tp.lut_lookup(reg.sh_lut, wl).view(-1, reg.K, 3)      # σ_k h_{k,c}(ω_o)
        B = (sh * cb).sum(1)
        return torch.where(wl[:, 2:] > 0, B, torch.zeros_like(B))  # ρ = 0 for ω_o below the horizon

    def _fast_static(self) -> _fast.FastStatic:
        """The fast path's static arrays (``fast.FastStatic``), built on first use from the
        precomputed regions and the scene's geometry (not stored by the precompute cache: views,
        regroupings and per-vertex geometry)."""
        if self._fast is None:
            dev = self.F.device
            geom = self.scene.geometry()
            V = torch.as_tensor(geom.V).float().to(dev)
            Nrm = torch.nn.functional.normalize(torch.as_tensor(geom.N).float().to(dev), dim=-1)
            face_region = torch.as_tensor(geom.face_region).long().to(dev)
            regions = [_fast.build_region(reg.T, reg.sh_lut) for reg in self.regions]
            Rs = {fr.R for fr in regions}
            if len(Rs) > 1:
                raise ValueError(f"regions have tables of different sizes {sorted(Rs)}")
            voff = [0]
            face_gl = torch.full(self.F.shape, -1, dtype=torch.int32, device=dev)
            for reg in self.regions:
                faces = (face_region == list(self.scene.regions).index(reg.name)).nonzero(as_tuple=True)[0]
                face_gl[faces] = (reg.local_of[self.F[faces]] + voff[-1]).to(torch.int32)
                voff.append(voff[-1] + int(reg.verts.numel()))
            if bool((face_gl < 0).any()):
                raise ValueError("faces whose region has no precomputation")
            verts = torch.cat([reg.verts for reg in self.regions]) if self.regions else self.F.new_zeros(0)
            K = torch.cat([torch.full((int(reg.verts.numel()),), reg.K, dtype=torch.int64, device=dev)
                           for reg in self.regions]) if self.regions else self.F.new_zeros(0)
            self._fast = _fast.FastStatic(regions=regions, voff=voff, face_gl=face_gl.T.contiguous(),
                                          face_rows=face_gl.contiguous(),
                                          face_region=face_region,
                                          pos=V[verts].contiguous(), frames=frame_matrix(Nrm[verts]).contiguous(),
                                          K=K, R=Rs.pop() if Rs else 2)
        return self._fast

    def _ensure_c(self, s: int, ref: Tensor) -> Tensor:
        """The fast path's c (Vr, 3, K) of slot ``s`` with the rows of its referenced vertices
        ``ref`` (ascending local ids) valid.

        Under the first lighting since the precompute (`_reset_cache`) every vertex of every region
        is computed at once, by whole blocks (`_ensure_c_all`): an application sets its start-up
        lighting once, and a view-only sequence's frames then do no lighting work, as `frame_cost`
        counts them (a V frame reads c, it does not compute it). Under a later lighting change only
        the missing rows of ``ref`` are computed, lazily — exactly those by the native loop
        (``fast.light_vertices``), else by whole blocks (`fast.light_runs`) — so an L / E / VL frame
        computes no c its view does not reference."""
        reg, fr = self.regions[s], self._fast.regions[s]
        full = self._cf_full.get(reg.name)
        if full is not None and full is self._cf_valid.get(reg.name):  # every row valid: no check (~0.07 ms a region)
            return self._cf[reg.name]
        if reg.name not in self._cf:
            if self._lightings == 1:
                self._ensure_c_all()
                return self._cf[reg.name]
            self._cf[reg.name] = torch.zeros(reg.verts.numel(), 3, reg.K, device=self.L.device)  # no stale memory in the state
            self._cf_valid[reg.name] = torch.zeros(reg.verts.numel(), dtype=torch.bool, device=self.L.device)
        c, valid = self._cf[reg.name], self._cf_valid[reg.name]
        todo = ref[~valid[ref]]
        if todo.numel() and _fast.native(fr, self.L):
            c[todo] = _fast.light_vertices(fr, self.L, todo).transpose(1, 2)
            valid[todo] = True
            return c
        for v0, v1 in _fast.light_runs(todo, reg.verts.numel()):
            c[v0:v1] = _fast.light_rows(fr, self.L, v0, v1).transpose(1, 2)
            valid[v0:v1] = True
        return c

    def _ensure_c_all(self) -> None:
        """c (Vr, 3, K) of every vertex of every region not yet computed under the current lighting,
        each region by one whole-block product (``fast.light_rows`` over all its rows)."""
        st = self._fast_static()
        for reg, fr in zip(self.regions, st.regions):
            full = self._cf_full.get(reg.name)
            if full is not None and full is self._cf_valid.get(reg.name):   # computed whole: no reduction
                continue
            if reg.name in self._cf and bool(self._cf_valid[reg.name].all()):
                continue
            nv = int(reg.verts.numel())
            self._cf[reg.name] = _fast.light_rows(fr, self.L, 0, nv).transpose(1, 2).contiguous()
            self._cf_valid[reg.name] = torch.ones(nv, dtype=torch.bool, device=self.L.device)
            self._cf_full[reg.name] = self._cf_valid[reg.name]

    def _view_refs(self, frame: Frame, gbuffer: GBuffer) -> "_View":
        """The first part of `_view_setup`: which samples are shaded, the referenced vertices
        (``ref``, ascending concatenated ids) and their c_k (`_ensure_c`)."""
        self._relight(frame)
        st = self._fast_static()
        dev = gbuffer.hit.device
        P = gbuffer.num_samples
        hit = gbuffer.hit
        M = st.face_region.numel()
        # every sample is shaded (misses with weight 0) unless many miss: then only the hits
        sel = None if int(torch.count_nonzero(hit)) >= DENSE_HIT_FRACTION * P else hit.nonzero(as_tuple=True)[0]
        view = _View(gbuffer=gbuffer, st=st, sel=sel, Q=P if sel is None else sel.numel())
        # referenced vertices: those of the faces of the shaded samples (the region check on every
        # hit), one compiled pass (``fast.shaded_faces``: its shaded test is a superset of the
        # per-sample stage's, so every vertex a shaded entry reads has its c and its window); the faces
        # of hits below their horizon only (ρ = 0) need neither. Creature bench: 3.4·10³ of the
        # 4.9·10³ vertices of hit faces (chess: 4.3 of 6.9·10³), c's bytes −30–38 %.
        rows, args = _shaded_faces_inputs(gbuffer, st, sel)
        fsh, bad = map_rows(_fast.shaded_faces_cols, rows, args, chunk=(B := _fast.sample_block(view.Q)),
                            warm=_fast.warm_sizes(B))
        if bool(bad.any()):
            name = self.scene.regions[int(rows[5][bad][0])]
            raise ValueError(f"G-buffer samples of region {name!r} lie on faces of another region")
        # the referenced-face mask as a histogram of the samples' faces (`_face_mask`)
        faces = _face_mask(fsh, M).nonzero(as_tuple=True)[0]
        vmask = torch.zeros(st.voff[-1], dtype=torch.bool, device=dev)
        vmask[st.face_gl.index_select(1, faces).reshape(-1)] = True
        ref = vmask.nonzero(as_tuple=True)[0]                                 # ascending
        view.cs = [self._ensure_c(s, ref[(ref >= st.voff[s]) & (ref < st.voff[s + 1])] - st.voff[s])
                   for s in range(len(self.regions))]
        view.ref = ref
        return view

    def _view_setup(self, frame: Frame, gbuffer: GBuffer) -> "_View":
        """The per-frame part of the fast path before the per-sample stage: which samples are shaded,
        the referenced vertices and their c_k (`_view_refs`), and the windows' products X
        (``fast.prepare``, each vertex's window chosen on every ``fast.WINDOW_SUBSAMPLE``-th sample)."""
        view = self._view_refs(frame, gbuffer)
        st, sel, ref, hit, dev = view.st, view.sel, view.ref, gbuffer.hit, gbuffer.hit.device
        k = _fast.WINDOW_SUBSAMPLE
        if sel is None:                       # strided views: the G-buffer's arrays need not be row-major
            sub = (gbuffer.normal[::k], gbuffer.wo[::k], gbuffer.bary[::k], gbuffer.face[::k], hit[::k])
        else:
            i = sel[::k]
            sub = (_fast.take_rows(gbuffer.normal, i), _fast.take_rows(gbuffer.wo, i), _fast.take_rows(gbuffer.bary, i),
                   gbuffer.face.index_select(0, i), torch.ones(i.numel(), dtype=torch.bool, device=dev))
        cam = torch.tensor(frame.camera.origin, dtype=torch.float32, device=dev)
        view.wins = _fast.prepare(st, view.cs, ref, cam, sub)
        return view

    def render(self, frame: Frame, gbuffer: GBuffer) -> Tensor:
        """The fast path (``methods.inout.fast``): the image of `_render_reference` to float32
        round-off; c_k computed only for the vertices the samples reference (`_view_setup`), the
        per-sample stage one compiled pass over static blocks of samples (``fast.shade_pixels``)."""
        if self.scene is None:
            raise RuntimeError("call precompute(scene) before render()")
        if self.config["shading"] == "vertex":
            return self._render_vertex(frame, gbuffer)
        img = self._render_native(frame, gbuffer)
        if img is not None:
            return img
        view = self._view_setup(frame, gbuffer)
        g, st, sel = gbuffer, view.st, view.sel
        P, S2 = g.num_samples, g.spp_side ** 2
        if sel is None:                                      # every sample, box-filtered per block
            img = _fast.shade_pixels(st, view.cs, view.wins, g.normal, g.wo, g.bary, g.face, g.hit, S2)
        else:                                                # the hits only, then the box filter
            B = _fast.shade_pixels(st, view.cs, view.wins, _fast.take_rows(g.normal, sel), _fast.take_rows(g.wo, sel),
                                   _fast.take_rows(g.bary, sel), g.face.index_select(0, sel),
                                   torch.ones(sel.numel(), dtype=torch.bool, device=sel.device), 1)
            img = torch.zeros(P, 3, dtype=B.dtype, device=B.device).index_copy_(0, sel, B).view(-1, S2, 3).mean(1)
        self._last_view = (P, {"gbuffer": g, "sel": sel, "window": view.wins.W})
        return img.view(g.height, g.width, 3)

    def _render_native(self, frame: Frame, gbuffer: GBuffer) -> Tensor | None:
        """The per-sample fast path as one C loop over the samples (``native_sample.shade``: X formed
        at the (vertex, node) pairs the samples read, while they are shaded; the compiled set-up and
        stage of `render` are its fallback and test oracle), or None when the loop is not available.
        c_k: under the first lighting every vertex's at once (`_ensure_c_all`), so a view frame runs
        no pass before the loop; under a later one the referenced vertices' (`_view_refs`)."""
        lib = _nsample._lib()                    # looked up once a frame (`shade` takes it)
        if lib is None:
            return None
        self._relight(frame)
        st = self._fast_static()
        if self._lightings == 1:
            if not self._cf_full:
                # the first lighting's first frame: the referenced-vertex pass (`_view_refs`) runs from the
                # second lighting on, so its kernel is compiled here, in the harness's untimed warm-up frame
                # (``core.fused.warm_blocks``, a no-op outside it), not in the first timed lighting frame (~110 ms
                # there: chess bench L, session 44); once a lighting (the inputs cost ~0.23 ms: not every frame)
                rows, args = _shaded_faces_inputs(gbuffer, st, None)
                B = _fast.sample_block(gbuffer.num_samples)
                warm_blocks(_fast.shaded_faces_cols, rows, args, (B, *_fast.warm_sizes(B)))
            self._ensure_c_all()
        if all(self._cf_full.get(r.name) is not None and self._cf_full[r.name] is self._cf_valid.get(r.name)
               for r in self.regions):
            cs = [self._cf[r.name] for r in self.regions]
        else:
            cs = self._view_refs(frame, gbuffer).cs
        g = gbuffer
        W = min(_nsample.WINDOW, st.R)
        b = self._xcall                          # the loop's static arguments, bound once (`native_sample.bind`)
        if b is None or self._xstamp >= 2 ** 31 - 2 or not b.fits(st, cs, self._xmemo, W, lib):
            nv = st.voff[-1]
            if (self._xmemo is None or self._xmemo[0].shape[0] != nv or self._xmemo[2].shape[0] != nv * W * W
                    or self._xstamp >= 2 ** 31 - 2):
                self._xmemo, self._xstamp = _nsample.memo(nv, W), 0
            b = self._xcall = _nsample.bind(st, cs, self._xmemo, W, lib)
            if b is None:
                return None
        self._xstamp += 1
        got = b.frame(g.normal, g.wo, g.bary, g.face, g.region, g.hit, g.spp_side ** 2, frame.camera.origin,
                      self._xstamp, (g.height, g.width, 3))
        if got is None:
            return None
        img, (_, _, bad) = got
        if bad >= 0:
            name = self.scene.regions[int(g.region[bad])]
            raise ValueError(f"G-buffer samples of region {name!r} lie on faces of another region")
        self._last_view = (g.num_samples, {"gbuffer": g, "sel": None, "window": W})
        return img

    def _view_counts(self, last: dict) -> dict:
        """What `frame_cost` counts of the last per-sample render (``last`` = its `_last_view` entry),
        computed on first use (not in the timed frame): the hit count and, per shaded sample
        (all P, or the hits ``sel``), whether ω_o is above its horizon (``front``), its table cell
        (``cell``, first node) and its face."""
        if "front" not in last:
            g, sel, st = last["gbuffer"], last["sel"], self._fast_static()
            idx = torch.arange(g.num_samples, device=g.hit.device) if sel is None else sel
            face = g.face.index_select(0, idx)
            _, _, (iu, iv, _, _), front = _fast.sample_inputs(
                st, g.normal.index_select(0, idx), g.wo.index_select(0, idx), g.bary.index_select(0, idx),
                face.clamp_min(0), g.hit.index_select(0, idx))
            last.update(hit=int(g.hit.sum()), front=front, cell=iv * st.R + iu, face=face)
        return last

    def _vertex_view(self, frame: Frame, gbuffer: GBuffer) -> dict[str, Any]:
        """Shading "vertex": what the view decides — the referenced vertices (those of the faces
        the hit samples lie on) and, for those above their horizon as seen from the camera, the
        table cell of ω_o in the vertex's frame and its bilinear weights, per slot. The slots are a
        function of the camera position and the referenced vertices alone, so they are kept while
        both are unchanged (a lighting change keeps them: L and E frames recompute only c_k and
        B_v): every frame finds its referenced vertices (one pass over the samples, which also
        checks the regions), and compares them with the kept ones — not the G-buffer's faces and
        hits, whose copies and comparison cost a view frame 0.35 ms and a lighting frame ~1 ms
        (chess bench, 1 thread, after the suite's idle; session 28)."""
        st = self._fast_static()
        key = (gbuffer.num_samples, tuple(float(x) for x in frame.camera.origin))
        dev, hit, face = gbuffer.hit.device, gbuffer.hit, gbuffer.face
        M, R, P = st.face_region.numel(), st.R, gbuffer.num_samples
        # the referenced vertices, the referenced-face count, the miss count and the region check: one
        # pass of the native loop over the samples, one over the faces (``csr.hit_face_mask``; chess
        # bench, 1 thread, after the suite's idle: 0.7 against 3.0 ms), else the compiled pass and
        # one histogram of the hits' faces (bin M: the misses, ``fast.hit_face_counts``), the
        # vertices of its faces marked
        got = _csr.hit_face_mask(face, gbuffer.region, hit, st.face_region, st.face_gl, st.voff[-1])
        if got is None:
            counts, bad = _fast.hit_face_counts(face, gbuffer.region, hit, st.face_region)
            faces = (counts[:M] > 0).nonzero(as_tuple=True)[0]
            vmask = torch.zeros(st.voff[-1], dtype=torch.bool, device=dev)
            vmask[st.face_gl.index_select(1, faces).reshape(-1).long()] = True
            nfaces, misses = int(faces.numel()), int(counts[M])
        else:
            vmask, nfaces, misses, bad = got
        if bad:
            f = face.clamp_min(0)
            sel = hit & (st.face_region.index_select(0, f) != gbuffer.region)
            name = self.scene.regions[int(gbuffer.region[sel][0])]
            raise ValueError(f"G-buffer samples of region {name!r} lie on faces of another region")
        vv = self._vview
        if vv is not None and vv["key"] == key and vv["hits"] == P - misses and torch.equal(vv["vmask"], vmask):
            vv["faces"] = nfaces
            return vv
        cam = torch.tensor(frame.camera.origin, dtype=torch.float32, device=dev)
        # towards the camera, in each vertex's frame: ρ = 0 below the horizon; its cell and weights,
        # per slot (region) — one pass of the native loop over the marked vertices (``native.vertex_cells``;
        # chess bench, 1 thread: the compiled pass and the slots' index arithmetic took ~1 ms), else
        # the compiled pass over the referenced ids (``fast.vertex_cells``) and the slots cut from it
        got = _native.vertex_cells(vmask, st.voff, st.pos, st.frames, cam, R)
        if got is not None:
            slots, nref = got
        else:
            ref = vmask.nonzero(as_tuple=True)[0]                              # ascending concatenated ids
            for t in (st.pos, st.frames):
                torch._dynamo.maybe_mark_dynamic(t, 0)                          # the scene's vertex count
            front, first, wc = _fast.vertex_cells_of(ref, st.pos, st.frames, cam, R)
            b = torch.searchsorted(ref, torch.tensor(st.voff, device=dev)).tolist()  # ref ascending: slots are runs
            slots = []
            for s in range(len(self.regions)):
                sel = front[b[s]:b[s + 1]].nonzero(as_tuple=True)[0] + b[s]
                slots.append((ref.index_select(0, sel) - st.voff[s], first.index_select(0, sel),
                              wc.index_select(0, sel)))
            nref = int(ref.numel())
        self._vview = {"key": key, "vmask": vmask, "slots": slots, "faces": nfaces, "ref": nref, "hits": P - misses}
        return self._vview

    def _render_vertex(self, frame: Frame, gbuffer: GBuffer) -> Tensor:
        """Shading "vertex", the fast path (`_render_vertex_reference` to float32 round-off): c_k of
        the referenced vertices above their horizon (`_ensure_c`, lazily as the per-sample path),
        B_v = Σ_n w_n Σ_k σ_k h_k(n) c_{v,k} at each one's own cell (a C loop per region,
        ``native.vertex_radiance``; else ``fast.vertex_radiance``, one compiled sampled product per
        region), then the Gouraud resolve (``core.gouraud.resolve``) — or, when every c is computed
        (a view frame under the first lighting), all of it as one C loop (`_render_vertex_native`).

        Session 43: a view frame whose loop is bound to the current c, statics and memo (`_vcall_current`:
        the same conditions as `_render_vertex_native`'s checks, fewer Python calls) goes to the bound call
        first (`_vertex_frame_bound`); each cold Python call costs ~5-30 us here, serial at 2 threads."""
        b, tried = self._vcall, False
        if b is not None and self.L is not None and "light" not in frame.changed and self._vcall_current(b):
            img = self._vertex_frame_bound(b, frame, gbuffer)
            if img is not None:
                return img
            tried = True                         # `_render_vertex_native` would run the same call: the split path
        self._relight(frame)
        st = self._fast_static()
        img = None if tried else self._render_vertex_native(frame, gbuffer)
        if img is not None:
            return img
        vv = self._vertex_view(frame, gbuffer)
        Bv = torch.zeros(st.voff[-1], 3, dtype=torch.float32, device=gbuffer.hit.device)
        for s, (loc, first, wc) in enumerate(vv["slots"]):
            if loc.numel():
                c, fr = self._ensure_c(s, loc), st.regions[s]
                # the native loop writes the rows itself (``native.vertex_radiance``), else the compiled pass
                if not _native.vertex_radiance(fr.sh_nc, fr.R, c, loc, first, wc, Bv, st.voff[s]):
                    Bv[st.voff[s] + loc] = _fast.vertex_radiance(fr, c, loc, first, wc)
        self._last_view = (gbuffer.num_samples, {"vertex": vv})
        return gouraud.resolve(Bv, st.face_gl, gbuffer.face, gbuffer.bary, gbuffer.hit, gbuffer.height,
                               gbuffer.width, gbuffer.spp_side)

    def _render_vertex_native(self, frame: Frame, gbuffer: GBuffer) -> Tensor | None:
        """Shading "vertex" as one C loop over the pixels (``native_vframe``: each referenced vertex's
        B_v computed at the first sample that reads it, then the Gouraud mix and box filter; the image
        of the split path of `_render_vertex`, bit for bit), when every region's c is computed (a view
        frame under the first lighting, `_ensure_c_all`; under a later lighting c is computed lazily
        for the view's vertices, which the split path finds first). None (the split path runs, and
        raises the G-buffer's errors) when the loop is not available, c is incomplete or the
        G-buffer fails a check. What `frame_cost` counts of the view (referenced faces and vertices,
        their cells) is found from the kept frame and G-buffer when it is asked (`_frame_cost_vertex`),
        not in the frame."""
        lib = _nvframe._lib()                    # looked up once a frame (`vertex_frame` takes it)
        if lib is None:
            return None
        if self._lightings == 1:
            self._ensure_c_all()
        if not all(self._cf_full.get(r.name) is not None and self._cf_full[r.name] is self._cf_valid.get(r.name)
                   for r in self.regions):
            return None
        st = self._fast_static()
        cs = [self._cf[r.name] for r in self.regions]
        b = self._vcall                          # the loop's static arguments, bound once (`native_vframe.bind`)
        if b is None or self._vstamp >= _nvframe.STAMP_MAX - 1 or not b.fits(st, cs, self._vmemo, lib):
            nv, M = st.voff[-1], int(st.face_region.shape[0])
            if (self._vmemo is None or len(self._vmemo) != 4 or self._vmemo[0].shape[0] != nv
                    or self._vmemo[1].shape[0] != M or self._vstamp >= _nvframe.STAMP_MAX - 1):
                self._vmemo, self._vstamp = _nvframe.memo(nv, M), 0
            b = self._vcall = _nvframe.bind(st, cs, self._vmemo, lib)
            if b is None:
                return None
            b.regions, b.names = self.regions, tuple(r.name for r in self.regions)   # for `_vcall_current`
        return self._vertex_frame_bound(b, frame, gbuffer)

    def _vcall_current(self, b: _nvframe.Bound) -> bool:
        """True when `_render_vertex_native` would run the bound call ``b`` as it is (no lighting work, no
        rebind): ``b`` bound to this object's statics, memo, regions and library, every region's c computed
        whole (`_ensure_c_all`'s mark) and the very tensors ``b`` holds, the stamps not exhausted. The
        caller checks that the lighting is kept (`_relight` would do nothing)."""
        if (b.st is not self._fast or b.mem is not self._vmemo or b.regions is not self.regions
                or self._vstamp >= _nvframe.STAMP_MAX - 1 or _nvframe._lib() is not b.lib):
            return False
        cf, full, valid = self._cf, self._cf_full, self._cf_valid
        for name, c in zip(b.names, b.cs):
            f = full.get(name)
            if f is None or f is not valid.get(name) or cf.get(name) is not c:
                return False
        return True

    def _vertex_frame_bound(self, b: _nvframe.Bound, frame: Frame, g: GBuffer) -> Tensor | None:
        """One frame of the bound call ``b`` (the next stamp), or None when the G-buffer fails its checks."""
        self._vstamp += 1
        got = b.frame(g.face, g.bary, g.region, g.hit, g.height * g.width, g.spp_side ** 2, frame.camera.origin,
                      self._vstamp, (g.height, g.width, 3))
        if got is None or got[2]:
            return None
        self._last_view = (g.num_samples, {"vertex_of": (frame, g)})
        return got[0]

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
            m[f"{reg.name}/c"] = (4 * 3 * reg.K + 1) * reg.verts.numel()   # c_k and its validity flag
            m[f"{reg.name}/sh_table_fast"] = tensor_bytes(reg.sh_lut)       # σ_k h_k regrouped (fast path)
        m["faces"] = tensor_bytes(self.F)
        nv = sum(int(reg.verts.numel()) for reg in self.regions)
        # fast path (`fast.FastStatic`): per face its concatenated vertex ids (3 int32) and region
        # (int64); per vertex position (3 float32), frame (9 float32) and K (int64)
        m["fast_static"] = int(self.F.shape[0]) * (3 * 4 + 8) + nv * (12 * 4 + 8) if self.F is not None else 0
        # the per-sample C loop's memo of X (``native_sample.memo``: per vertex W² rows and stamps),
        # allocated at its first frame
        m["sample_memo"] = tensor_bytes(*self._xmemo) if self._xmemo is not None else 0
        # the vertex-shaded frame's C loop's memo of B_v (``native_vframe.memo``: 16 bytes a vertex)
        m["vertex_memo"] = tensor_bytes(*self._vmemo) if self._vmemo is not None else 0
        N = self.config["cube_res"]
        m["L"] = tensor_bytes(self.L) if self.L is not None else 4 * 6 * N * N * 3
        return m

    FRAME_KINDS = ("V", "L", "E", "VL")  # the sequence kinds in scope (static geometry and BRDFs)

    def frame_cost(self, frame_kind: str, num_samples: int, *, pixels: int | None = None) -> FrameCost | None:
        """Compulsory work of one frame (Mahajan 2008 eq. 4 at run time; ``methods.base.FrameCost``),
        whatever our implementation does. Multiply-add = 2 flops; transcendentals (the normalising
        square roots, hemi-octahedral division, the env map's atan2/acos) are not counted.

        Every frame (view part): per hit sample the G-buffer inputs (`GBUFFER_BYTES_PER_SAMPLE`) and
        its int64 region, per missed sample its hit flag (1 B), the (H, W, 3) float32 image (``pixels``). A *shaded*
        sample is a hit whose ω_o is above its horizon (eq. 4 is 0 below); per region with K terms:
        the faces of the shaded samples (3 int64 each), the c_k (K·3 float32) of their vertices
        (*referenced* vertices) and the σ_k h_k rows (3K float32) of every table node their bilinear
        cells touch. Flops: per hit sample ω_o into its frame (9 MACs); per shaded sample the 12
        vertex × node weights β_j w_n (4 + 12 products) and B = Σ 12 weights × X (12·3 MACs); per
        referenced vertex at least one cell of X(v, n) = Σ_k σ_k h_k(n) c_{v,k} (4 nodes × 3K MACs;
        the reassociated form of eq. 4, ``methods.inout.fast``: no implementation does less).

        A lighting change ("L" or "E" in the kind: L, E, VL) adds: the env map resampled on the
        cube map (6N²s² sub-samples, s = ``light_supersample``: the texels they touch, at most H·W
        float32 RGB, read; per sub-sample the rotation into the map's frame (9 MACs), the bilinear
        texel mix (4·3 MACs) and the weighted mean (3 MACs)), its Haar transform (4 flops per
        texel and channel over all levels) and the (6N², 3) float32 L written; the kept coefficients
        of T̃ of every referenced vertex (their count varies per vertex) read once (values float32 + column indices at their stored
        width) and c_k = T̃_k · L computed for them (2·3 flops per kept coefficient; the c write is
        the c read counted above, once). Vertices no sample references need no c (the fast path
        computes c lazily per vertex, ``methods.inout.fast``).

        Hit and shaded samples, referenced vertices, faces and table nodes come from the last
        `render` on a G-buffer of ``num_samples`` samples; without one, every sample is taken as
        shaded and every vertex, face and node as referenced (an upper bound of those terms). None
        before `precompute`.
        """
        if frame_kind not in self.FRAME_KINDS:
            raise ValueError(f"frame_kind must be one of {self.FRAME_KINDS} (inout: static geometry and BRDFs), "
                             f"got {frame_kind!r}")
        if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 0:
            raise ValueError(f"num_samples must be an int >= 0, got {num_samples!r}")
        if self.scene is None:
            return None
        cfg, f4 = self.config, 4
        P = num_samples
        light = "L" in frame_kind or "E" in frame_kind
        if cfg["shading"] == "vertex":
            return self._frame_cost_vertex(P, light, pixels)
        last = self._last_view[1] if self._last_view is not None and self._last_view[0] == P else None
        if last is not None:
            last = self._view_counts(last)
        b = output_bytes(P, pixels)                                      # the image
        f = 0
        if last is not None:
            st = self._fast_static()
            faces = last["face"][last["front"]]
            verts = torch.unique(st.face_gl.index_select(1, faces).reshape(-1).long())      # concatenated ids
            cells, face_region = last["cell"][last["front"]].long(), st.face_region.index_select(0, faces)
        for s, reg in enumerate(self.regions):
            K, R = reg.K, int(round(reg.sh_lut.shape[0] ** 0.5))
            crow = reg.T.crow_indices()
            if last is None:
                nref, nodes = int(reg.verts.numel()), R * R
                nnz = int(crow[-1])                                       # kept coefficients of every vertex
            else:
                loc = verts[(verts >= st.voff[s]) & (verts < st.voff[s + 1])] - st.voff[s]
                nref = int(loc.numel())
                nnz = int((crow[(loc + 1) * K].long() - crow[loc * K].long()).sum())
                cell = cells[face_region == list(self.scene.regions).index(reg.name)]
                nodes = int(torch.unique(cell[:, None] + torch.tensor([0, 1, R, R + 1], device=cell.device)).numel())
            b += nref * K * 3 * f4 + nodes * 3 * K * f4                  # c rows, σ_k h_k rows
            f += nref * 4 * 3 * K * 2                                     # one cell of X per vertex
            if light:
                b += nnz * (reg.T.values().element_size() + reg.T.col_indices().element_size())
                f += 2 * 3 * nnz                                          # c_k = T̃_k · L
        if last is None:
            hit = Q = P
            nfaces = int(self.F.shape[0])
        else:
            hit, Q = last["hit"], int(last["front"].sum())
            nfaces = int(torch.unique(faces).numel())
        b += hit * (GBUFFER_BYTES_PER_SAMPLE + 8) + (P - hit) * GBUFFER_HIT_BYTES + nfaces * 3 * self.F.element_size()
        f += hit * 2 * 9 + Q * (16 + 2 * 12 * 3)
        if light:
            lb, lf = self._lighting_cost()
            b, f = b + lb, f + lf
        return FrameCost(int(b), int(f))

    def _lighting_cost(self) -> tuple[int, int]:
        """(bytes, flops) of a lighting change before the per-vertex products (`frame_cost`): the
        env map resampled on the cube map, its Haar transform, L written."""
        cfg, f4 = self.config, 4
        N, s = cfg["cube_res"], cfg["light_supersample"]
        D, sub = 6 * N * N, 6 * N * N * s * s
        H, W = self._env_shape or tuple(int(x) for x in self.scene.envmap.data.shape[:2])
        return (min(H * W, 4 * sub) * 3 * f4 + D * 3 * f4,                # texels read, L written
                sub * 2 * (9 + 4 * 3 + 3) + D * 3 * 4)                      # resampling, Haar

    def _frame_cost_vertex(self, P: int, light: bool, pixels: int | None = None) -> FrameCost:
        """`frame_cost` of shading "vertex" (eq. 4 per vertex, Gouraud to the samples).

        Every frame: per hit sample its face index (int64), barycentrics (2 float32) and hit flag
        (1 B) — not its normal or ω_o —, per missed sample its hit flag, the (H, W, 3) float32 image
        (as the per-sample path); per *referenced* face (a hit sample lies on it)
        its 3 vertex ids; per referenced vertex its position and normal (6 float32); per *shaded*
        vertex (referenced, and the camera above its horizon: eq. 4 is 0 below) its c_k (3K
        float32) and the σ_k h_k rows (3K float32) of every table node the shaded vertices' cells
        touch. Flops: per hit sample the Gouraud mix (3 vertices × 3 MACs); per referenced vertex
        the direction to the camera (3) into its frame (9 MACs; the hemi-octahedral cell needs
        no unit vector); per shaded vertex the 4 bilinear weights (4), B_v = Σ_n w_n Σ_k σ_k
        h_k(n) c_{v,k} (4 nodes × 3K MACs + 4 × 3 MACs).

        A lighting change adds the env map's resampling, Haar transform and L (as the per-sample
        path) and, per shaded vertex, its kept coefficients of T̃ read and c_k = T̃_k · L (2·3 flops
        per coefficient). Without a render on ``P`` samples: every sample hit, every face and
        vertex referenced and shaded, every node touched (an upper bound of those terms)."""
        f4 = 4
        lv = self._last_view[1] if self._last_view is not None and self._last_view[0] == P else None
        if lv is not None and "vertex" not in lv and "vertex_of" in lv:   # the C loop's frame: its view, found now
            lv["vertex"] = self._vertex_view(*lv["vertex_of"])
        last = lv.get("vertex") if lv is not None else None
        b = output_bytes(P, pixels)
        f = 0
        if last is None:
            hit, nfaces = P, int(self.F.shape[0])
            nref = sum(int(reg.verts.numel()) for reg in self.regions)
        else:
            hit, nfaces, nref = last["hits"], last["faces"], last["ref"]
        b += hit * (8 + 8 + GBUFFER_HIT_BYTES) + (P - hit) * GBUFFER_HIT_BYTES + nfaces * 3 * self.F.element_size() + nref * 6 * f4
        f += hit * 2 * 9 + nref * (3 + 2 * 9)
        for s, reg in enumerate(self.regions):
            K, R = reg.K, int(round(reg.sh_lut.shape[0] ** 0.5))
            crow = reg.T.crow_indices()
            if last is None:
                loc = torch.arange(reg.verts.numel(), device=crow.device)
                nodes = R * R
            else:
                loc, first, _ = last["slots"][s]
                nodes = int(torch.unique(first[:, None] + torch.tensor([0, 1, R, R + 1], device=first.device)).numel())
            nv = int(loc.numel())
            b += nv * K * 3 * f4 + nodes * 3 * K * f4                     # c rows, σ_k h_k rows
            f += nv * (4 + 2 * 4 * 3 * K + 2 * 4 * 3)
            if light:
                nnz = int((crow[(loc + 1) * K].long() - crow[loc * K].long()).sum())
                b += nnz * (reg.T.values().element_size() + reg.T.col_indices().element_size())
                f += 2 * 3 * nnz
        if light:
            lb, lf = self._lighting_cost()
            b, f = b + lb, f + lf
        return FrameCost(int(b), int(f))
