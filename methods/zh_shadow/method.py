"""ZH-predicted shadowing with 1D BRDFs (Nowrouzezahrai, Kalogerakis, Simari & Fiume 2008) behind
the common `methods.base.Method` interface.

Precompute (`methods.zh_shadow.precompute`, §3): f training poses → per-vertex order-n SH of the
unweighted visibility in the skinned local frame → c ZH lobes per vertex → linear model
X (J+1, N, 6c) from joint angles (+ bias) to the lobe parameters.

Render (§4.3), per G-buffer sample (default, ``shading="sample"``) or per vertex + barycentric
interpolation of the radiance (``shading="vertex"``, the paper's GPU per-vertex shading):
  1. synthesize the lobes: [pose, 1] · X (CPU, per vertex), axes taken to world space through the
     posed vertex frame;
  2. rotate the lobe axes into the frame of the reflection vector R = reflect(ωo, n) (and of the
     normal n for the diffuse term) — a ZH lobe rotates by rotating its axis;
  3. ZH → SH (eq. 1);
  4. apply the operator: t = ((α+1)/(2π)) M^α v (eq. 2, `convolution.phong_operator`), α = the
     Phong exponent about R, α = 1 about n for the diffuse (Lambert) term;
  5. dot with the SH lighting rotated into that frame (`methods.core.sh_rotation`).
  Per sample, the three vertices' lobes are all kept (3c lobes with the barycentric weights folded
  into their ZH coefficients): that IS the barycentric interpolation of the SH visibility vector,
  evaluated without interpolating lobe axes (which would mix unrelated lobes).

Two implementations of these steps (issue 14). `ZHShadow.render` is the fast path
(`methods.zh_shadow.runtime`): step 1 and eq. 1 once per vertex and pose (cached while the pose
does not change), the world-space SH visibility interpolated per sample, and steps 2–5 as one
batched polynomial in n and R whose coefficient tables fold the per-point rotations, M^α and the
lighting (built once per lighting and exponent, cached). `ZHShadow._render_reference` is the slow
path, steps 2–5 per point with explicit rotations (`shade`); it is the test oracle of the fast one
(equal to float32 round-off) and renders the ``specular="cosine"`` variant, whose cos θ_i-weighted
visibility is not a sum of ZH lobes.

Radiance = kd · (1/π) v_nᵀ M¹ L_n + ks · ((α+1)/(2π)) v_Rᵀ M^α L_R, zero where n·ωo ≤ 0 (as the
BRDFs). ``specular="published"`` (default) is the paper's Phong convolution, which leaves out the
cos θ_i = max(0, n·ω) factor of the rendering equation; ``specular="cosine"`` puts it back: the
order-n SH of V(ω)·max(0, n·ω) is M¹ v_n (exact for the band-limited v), rotated to the R frame
by a full SH rotation (the lobes cannot carry it: it is no longer a sum of ZH lobes).

Negative radiance (issue 19). The order-4 SH projection of a probe whose energy sits in a small,
very bright source (a sun, a window) rings: the projected lighting is negative over a large part of
the sphere, by more than the probe's mean radiance. Against the whole lighting the negative lobes
are cancelled by the source's positive one, but where visibility removes the source (cast and self
shadows, thin parts) or the Phong lobe is narrow (the shade is then almost a point sample of the
lighting) they show as negative pixels. The lighting's truncation is the cause, not the lobe fit
or the pose model: exact ray-cast SH visibility in place of the fitted lobes gives as many negative
pixels, static scenes (no pose model) have them, and unshadowed shading (V ≡ 1) already goes
negative (tests/methods/zh_shadow/test_negative.py has the measurements). The paper says nothing
about it: §4.3 step 5 ends with shade = t · l, neither windowed nor clamped (a GPU render target
clamps at display). Windowing the lighting (Hanning / Lanczos σ-factors,
`methods.core.zh.window_factors`) removes the negative lobes only at widths that blur and darken
the lighting enough to raise the error against Mitsuba on most library scenes; a non-negative
least-squares fit of the lighting adds energy (images far too bright). Clamping each shade at 0
removes every negative pixel at no cost in error. Hence the defaults ``window="none"``,
``clamp=True``; the window stays a config (``window``, ``window_width``), applied once, to the SH
lighting, for every term and shading mode (a per-band scale: it commutes with the rotations and
equals windowing the transfer vector t).
"""
from __future__ import annotations

import math
import time
from typing import Any

import torch
from torch import Tensor

from methods.base import (GBUFFER_BYTES_PER_SAMPLE, Capabilities, Frame, FrameCost, GBuffer, Method, register,
                          tensor_bytes)
from methods.core.frames import frame_matrix, reflect
from methods.core.sh import project_latlong
from methods.core.sh_rotation import rotate_coeffs
from methods.core.zh import WINDOWS, convolve_factors, window_factors, zh_lobes_to_sh
from methods.zh_shadow import precompute as pc
from methods.zh_shadow import runtime as rt
from methods.zh_shadow.convolution import phong_operator

# Samples shaded per batch (bounds the (Q, n², 3) rotated-lighting temporaries).
SHADE_CHUNK = 1 << 15
SUPPORTED_BRDFS = frozenset({"lambert", "phong"})


def _choice(name: str, value: Any, options: tuple) -> Any:
    if value not in options:
        raise ValueError(f"{name} must be one of {options}, got {value!r}")
    return value


def _int(name: str, value: Any, lo: int, hi: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < lo or (hi is not None and value > hi):
        rng = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ValueError(f"{name} must be an int {rng}, got {value!r}")
    return value


def shade(k: Tensor, axes: Tensor, normal: Tensor, wo: Tensor, light: Tensor, kd: Tensor, ks: Tensor,
          alpha: Tensor, *, specular: str = "published", ops: dict | None = None) -> Tensor:
    """Run-time steps 2–5 of §4.3 for Q shading points, each with L weighted ZH lobes.

    Args:
        k: (Q, L, n) ZH coefficients (weights folded in); axes: (Q, L, 3) unit world-space axes.
        normal: (Q, 3) unit shading normals; wo: (Q, 3) unit directions towards the viewer.
        light: (n², 3) world-space SH of the env map.
        kd, ks: (Q, 3) diffuse / specular albedo; alpha: (Q,) Phong exponents (ignored where ks = 0).
        specular: "published" (no cos θ_i, the paper) or "cosine" (with it).
        ops: cache {α: M^α} (filled on demand).
    Returns:
        (Q, 3) exit radiance.
    """
    Q, Lb, n = k.shape
    n2 = n * n
    if axes.shape != (Q, Lb, 3) or normal.shape != (Q, 3) or wo.shape != (Q, 3) or light.shape != (n2, 3):
        raise ValueError("shade: inconsistent shapes "
                         f"k {tuple(k.shape)}, axes {tuple(axes.shape)}, normal {tuple(normal.shape)}, "
                         f"wo {tuple(wo.shape)}, light {tuple(light.shape)}")
    ops = {} if ops is None else ops
    dt, dev = k.dtype, k.device

    def op(a: float) -> Tensor:
        if a not in ops:
            ops[a] = phong_operator(a, n, dtype=dt, device=dev)
        return ops[a]

    light = light.to(dt)
    Fn = frame_matrix(normal)                                          # world → normal frame
    v_n = zh_lobes_to_sh(k, (Fn[:, None] @ axes[..., None]).squeeze(-1))   # (Q, n²) eq. 1
    L_n = rotate_coeffs(light, Fn)                                     # (Q, n², 3)
    M1 = op(1.0)
    out = kd * torch.einsum("qi,ij,qjc->qc", v_n, M1, L_n) / math.pi  # (2/(2π)) M¹: Lambert
    spec = (ks > 0).any(-1)
    if spec.any():
        idx = spec.nonzero().squeeze(-1)
        R = reflect(wo[idx], normal[idx])
        R = R / R.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        FR = frame_matrix(R)                                           # world → reflection frame
        if specular == "published":
            v_R = zh_lobes_to_sh(k[idx], (FR[:, None] @ axes[idx][..., None]).squeeze(-1))
        else:
            vcos_n = v_n[idx] @ M1                                     # SH of V·max(0, n·ω)
            v_R = rotate_coeffs(vcos_n[..., None], FR @ Fn[idx].transpose(-1, -2))[..., 0]
        L_R = rotate_coeffs(light, FR)                                 # (Qs, n², 3)
        a_s = alpha[idx]
        sp = torch.zeros(idx.shape[0], 3, dtype=dt, device=dev)
        for a in torch.unique(a_s).tolist():
            sel = a_s == a
            t = v_R[sel] @ op(float(a)) * ((a + 1.0) / (2.0 * math.pi))   # eq. 2 (M symmetric)
            sp[sel] = torch.einsum("qj,qjc->qc", t, L_R[sel])
        out[idx] = out[idx] + ks[idx] * sp
    front = (normal * wo).sum(-1, keepdim=True) > 0
    return torch.where(front, out, torch.zeros_like(out))


@register
class ZHShadow(Method):
    """Linear-model ZH visibility + Phong convolution operator (Nowrouzezahrai et al. 2008).

    Config (keyword-only): order (SH order, default 4), lobes (c ZH lobes, 1..4), train_poses (f),
    train_source ("animation" | "uniform"), train_seed, train_rest (fraction of the training frames
    easing in from the rest pose, `precompute.REST_FRACTION`), n_dirs (rays per vertex and pose),
    fit_iters (Adam steps of the lobe refinement), axis_anchor (pose-smoothness weight of the lobe
    axes, `precompute.AXIS_ANCHOR`), specular ("published" | "cosine"), shading
    ("sample" | "vertex"), below_horizon ("trace" | "hide"), window ("none" | "hanning" |
    "lanczos": σ-factors on the SH lighting) and window_width (w, default the order), clamp (shade
    clamped at 0). See the module docstring on negative radiance.
    """

    name = "zh_shadow"
    cache_precompute = True  # cells of one scene/config share the fitted model (reports.precompute_cache)
    capabilities = Capabilities(dynamic_lighting=True, dynamic_brdf=True,
                                dynamic_geometry=True, max_bounces=0, brdfs=SUPPORTED_BRDFS)

    def __init__(self, *, order: int = 4, lobes: int = 2, train_poses: int = 32, train_source: str = "animation",
                 train_seed: int = 1234, train_rest: float = pc.REST_FRACTION, n_dirs: int = 1024,
                 fit_iters: int = 60, specular: str = "published", shading: str = "sample",
                 below_horizon: str = "trace", axis_anchor: float = pc.AXIS_ANCHOR, window: str = "none",
                 window_width: float | None = None, clamp: bool = True) -> None:
        _int("order", order, 2, 8)
        _int("lobes", lobes, 1, 4)
        _int("train_poses", train_poses, 2)
        _int("n_dirs", n_dirs, 16)
        _int("fit_iters", fit_iters, 0)
        _int("train_seed", train_seed, 0)
        if isinstance(axis_anchor, bool) or not isinstance(axis_anchor, (int, float)) or not axis_anchor >= 0 \
                or not math.isfinite(axis_anchor):
            raise ValueError(f"axis_anchor must be a finite number >= 0, got {axis_anchor!r}")
        _choice("train_source", train_source, ("animation", "uniform"))
        _choice("specular", specular, ("published", "cosine"))
        _choice("shading", shading, ("sample", "vertex"))
        _choice("below_horizon", below_horizon, ("trace", "hide"))
        _choice("window", window, WINDOWS)
        if isinstance(train_rest, bool) or not isinstance(train_rest, (int, float)) or not 0 <= train_rest < 1:
            raise ValueError(f"train_rest must be a number in [0, 1), got {train_rest!r}")
        if window_width is not None:
            if isinstance(window_width, bool) or not isinstance(window_width, (int, float)) \
                    or not math.isfinite(window_width) or window_width <= 0:
                raise ValueError(f"window_width must be a finite number > 0 or None, got {window_width!r}")
            window_width = float(window_width)
        if not isinstance(clamp, bool):
            raise ValueError(f"clamp must be a bool, got {clamp!r}")
        super().__init__(order=order, lobes=lobes, train_poses=train_poses, train_source=train_source,
                         train_seed=train_seed, train_rest=float(train_rest), n_dirs=n_dirs, fit_iters=fit_iters,
                         specular=specular, shading=shading, below_horizon=below_horizon,
                         axis_anchor=float(axis_anchor), window=window, window_width=window_width, clamp=clamp)
        self.scene = None
        self.model: pc.ZHModel | None = None
        self.stats: dict[str, float] = {}
        self._ops: dict[float, Tensor] = {}          # α → M^α
        self._light: tuple[Any, Tensor] | None = None  # (env key, (n², 3) world SH)
        self._env_bytes = 0                             # bytes of the last projected env map
        self._env_local: tuple[Any, Tensor] | None = None  # (env data key, (n², 3) SH in the map's frame, float64)
        self._posed: tuple[Any, Any, Tensor] | None = None  # (pose key, geometry, (N, n²) world SH visibility)
        self._tables: tuple[Any, dict] | None = None      # (lighting key, {("d", 1) | ("s", α): W})
        self._last_counts: tuple[int, int, int] | None = None  # (G-buffer samples, shaded points, specular points)

    # -- precompute ---------------------------------------------------------------------------
    def precompute(self, scene) -> None:
        self.scene = scene
        self._light = self._env_local = self._posed = self._tables = None
        cfg = self.config
        t0 = time.perf_counter()
        if scene.skeleton is None:   # static scene: one "pose", the model is the bias row alone
            poses = torch.zeros(1, 0)
        else:
            poses = pc.training_poses(scene, cfg["train_poses"], source=cfg["train_source"],
                                      seed=cfg["train_seed"], rest=cfg["train_rest"])
        v, _ = pc.pose_visibility(_PoseAdapter(scene), poses, cfg["order"], n_dirs=cfg["n_dirs"],
                                  below_horizon=cfg["below_horizon"])
        t1 = time.perf_counter()
        # one thread: the lobe fit is a loop of small batched ops whose OpenMP synchronisation
        # dominates (on a loaded 2-core machine 14.5 s with 1 thread vs 188 s with 2), and its
        # lstsq / solves then do not depend on the caller's thread count (methods.core.threads)
        with pc.torch_threads(1):
            self.model, fitted = pc.build_model(v, poses, cfg["lobes"], iters=cfg["fit_iters"],
                                                anchor=cfg["axis_anchor"])
        t2 = time.perf_counter()
        # the training-set summaries on one thread too: whole-tensor means and a float32 product
        # with f rows would otherwise round with the thread count (methods.core.threads)
        with pc.torch_threads(1):
            train_pred = pc.synthesize(self.model.X, poses)                      # (f, N, d)
            kk, ax = pc.params_to_lobes(train_pred, self.model.lobes)
            e_lin = pc.sh_error(pc.lobes_sh(kk.flatten(0, 1), ax.flatten(0, 1)), v.flatten(0, 1), pc.NORM_V)
            e_fit = pc.sh_error(fitted, v, pc.NORM_V)
            self.stats = {"time_visibility_s": t1 - t0, "time_fit_s": t2 - t1,
                          "lobe_fit_err_mean": float(e_fit.mean()), "lobe_fit_err_std": float(e_fit.std()),
                          "train_model_err_mean": float(e_lin.mean()), "train_model_err_std": float(e_lin.std()),
                          "model_mb": self.model.nbytes / 1e6}

    # Config keys that only the render reads: a precomputed model serves every value of them.
    RENDER_KEYS = ("specular", "shading", "window", "window_width", "clamp")

    def with_render_config(self, **changes) -> "ZHShadow":
        """A new method with some render-time config keys (`RENDER_KEYS`) changed, sharing this
        one's precomputed model (its config records what it renders). ValueError for other keys."""
        bad = sorted(set(changes) - set(self.RENDER_KEYS))
        if bad:
            raise ValueError(f"with_render_config changes only {self.RENDER_KEYS}, got {bad}")
        m = type(self)(**{**self.config, **changes})
        m.scene, m.model, m.stats, m._ops = self.scene, self.model, self.stats, self._ops
        return m

    # -- render -------------------------------------------------------------------------------
    def _lighting(self, env) -> Tensor:
        """(n², 3) float32 world-space SH of ``env`` (cached): the exact projection in the map's
        own frame is kept per map, a new ``to_world`` (L/VL/VBL frames rotate the map) only
        rotates it (`methods.core.sh_rotation`, float64, then float32 as `project_latlong`)."""
        data = torch.as_tensor(env.data)
        dkey = (id(env.data), data.data_ptr(), tuple(data.shape))
        key = (dkey, tuple(torch.as_tensor(env.to_world).flatten().tolist()))
        if self._light is None or self._light[0] != key:
            if self._env_local is None or self._env_local[0] != dkey:
                self._env_local = (dkey, project_latlong(data.double(), self.config["order"]))
                self._env_bytes = int(data.numel() * data.element_size())
            R = torch.as_tensor(env.to_world, dtype=torch.float64, device=data.device)
            self._light = (key, rotate_coeffs(self._env_local[1], R).to(data.dtype).float())
        return self._light[1]

    def _window(self, light: Tensor) -> Tensor:
        if self.config["window"] != "none":   # once, on the lighting: every term and mode sees it
            light = convolve_factors(light, window_factors(self.config["window"], self.model.order,
                                                           self.config["window_width"], dtype=light.dtype))
        return light

    def _region_materials(self, frame: Frame) -> list[tuple[Tensor, Tensor, float]]:
        """Per region of the scene: kd (3,), ks (3,) float32 and α (1 for Lambert)."""
        out = []
        for name in self.scene.regions:
            mat = frame.materials[name]
            if mat.kind not in self.capabilities.brdfs:
                raise ValueError(f"zh_shadow supports {sorted(self.capabilities.brdfs)} BRDFs, region {name!r} is {mat.kind!r}")
            kd = torch.tensor(mat.kd, dtype=torch.float32)
            if mat.kind == "phong":
                out.append((kd, torch.tensor(mat.ks, dtype=torch.float32), float(mat.s)))
            else:
                out.append((kd, torch.zeros(3), 1.0))
        return out

    def _pose_state(self, frame: Frame):
        """(pose vector, posed geometry, (N, n²) world-space SH visibility), cached per pose:
        §4.3 #1 (lobes from the linear model), the local lobe axes taken to world space through the
        posed vertex frame, and eq. 1 (ZH → SH) once per vertex."""
        scene, m = self.scene, self.model
        if scene.skeleton is None:
            pose_vec = torch.zeros(0)
        else:
            pose_vec = torch.zeros(scene.skeleton.num_joints) if frame.pose is None else torch.as_tensor(frame.pose).float()
        key = tuple(pose_vec.tolist())
        if self._posed is None or self._posed[0] != key:
            geom = scene.geometry() if scene.skeleton is None else scene.geometry(pose_vec)
            k, ax = m.lobes_at(pose_vec)                                      # (N, c, n), (N, c, 3) local
            Fv = frame_matrix(geom.N.float())                                  # (N, 3, 3) world → local
            ax_w = (Fv.transpose(-1, -2)[:, None] @ ax[..., None]).squeeze(-1)
            self._posed = (key, geom, zh_lobes_to_sh(k, ax_w))                  # (N, n²) world SH, eq. 1
        return pose_vec, self._posed[1], self._posed[2]

    def _table(self, light: Tensor, light_key, alpha: float, diffuse: bool) -> Tensor:
        if self._tables is None or self._tables[0] != light_key:
            self._tables = (light_key, {})
        tkey = ("d", 1.0) if diffuse else ("s", float(alpha))
        tabs = self._tables[1]
        if tkey not in tabs:
            tabs[tkey] = rt.table(light, 1.0 if diffuse else alpha, diffuse=diffuse)
        return tabs[tkey]

    def render(self, frame: Frame, gbuffer: GBuffer) -> Tensor:
        """§4.3 for every covered sample (or vertex), batched (`methods.zh_shadow.runtime`); equal to
        `_render_reference` to float32 round-off. The per-pose visibility, the lighting SH and its
        tables are cached between frames (keyed on the pose / the env map and its rotation)."""
        if self.model is None or self.scene is None:
            raise RuntimeError("call precompute(scene) before render()")
        if self.config["specular"] != "published":   # the cos θ_i variant: not a ZH lobe sum (reference path)
            return self._render_reference(frame, gbuffer)
        _, geom, v = self._pose_state(frame)
        light = self._window(self._lighting(frame.envmap))
        lkey = self._light[0]
        mats = self._region_materials(frame)
        dev = gbuffer.hit.device
        v = v.to(dev)
        out = torch.zeros(gbuffer.num_samples, 3, device=dev)
        n_spec = 0
        if self.config["shading"] == "vertex":
            cam = torch.as_tensor(frame.camera.origin, dtype=torch.float32, device=dev)
            V, N = geom.V.to(dev), geom.N.to(dev).float()
            rad = torch.zeros(geom.num_vertices, 3, device=dev)
            reg = geom.vertex_region.to(dev)
            for r, (kd, ks, al) in enumerate(mats):
                sel = (reg == r).nonzero().squeeze(-1)
                wo = cam - V[sel]
                wo = wo / wo.norm(dim=-1, keepdim=True).clamp_min(1e-12)
                n_spec += self._shade_group(rad, sel, v[sel].T, N[sel].T, wo.T, light, lkey, kd, ks, al)
            if self.config["clamp"]:   # per vertex, before the interpolation (module docstring)
                rad = rad.clamp_min(0.0)
            out = gbuffer.interpolate(rad, geom.F.to(dev))
            self._last_counts = (gbuffer.num_samples, int(geom.num_vertices), n_spec)
        else:
            F = geom.F.to(dev)
            vT = v.T.contiguous()                                                 # (n², N)
            hits = gbuffer.hit.nonzero().squeeze(-1)
            reg = gbuffer.region.index_select(0, hits)
            for r, (kd, ks, al) in enumerate(mats):
                h = hits[reg == r]
                for a in range(0, h.shape[0], rt.CHUNK):
                    hq = h[a:a + rt.CHUNK]
                    vi = F.index_select(0, gbuffer.face.index_select(0, hq)).T         # (3, Q) vertex ids
                    u, w2 = gbuffer.bary.index_select(0, hq).T                         # barycentrics
                    vsT = vT.index_select(1, vi[0]) * (1.0 - u - w2) + vT.index_select(1, vi[1]) * u \
                        + vT.index_select(1, vi[2]) * w2                               # (n², Q) interpolated eq. 1
                    n_spec += self._shade_group(out, hq, vsT, gbuffer.normal.index_select(0, hq).T,
                                                gbuffer.wo.index_select(0, hq).T, light, lkey, kd, ks, al)
            if self.config["clamp"]:   # per shaded sample, before the pixel resolve
                out = out.clamp_min(0.0)
            self._last_counts = (gbuffer.num_samples, int(hits.numel()), n_spec)
        return gbuffer.resolve(out)

    def _shade_group(self, out: Tensor, idx: Tensor, vT: Tensor, nT: Tensor, woT: Tensor, light: Tensor, lkey,
                     kd: Tensor, ks: Tensor, alpha: float) -> int:
        """out[idx] = kd · diffuse + ks · specular (0 where n·ωo ≤ 0) for Q points of one material;
        returns the number of points with a specular term. vT (n², Q), nT/woT (3, Q) unit."""
        dev = out.device
        Wd = self._table(light, lkey, 1.0, True).to(dev)
        spec = bool((ks > 0).any())
        Ws = self._table(light, lkey, alpha, False).to(dev) if spec else None
        kd, ks = kd.to(dev)[:, None], ks.to(dev)[:, None]
        for a in range(0, idx.shape[0], rt.CHUNK):
            s = slice(a, a + rt.CHUNK)
            d, sp = rt.shade_terms(vT[:, s], nT[:, s], woT[:, s], Wd, Ws)
            rad = kd * d if sp is None else kd * d + ks * sp                       # (3, Q)
            front = (nT[:, s] * woT[:, s]).sum(0) > 0
            out.index_copy_(0, idx[s], torch.where(front, rad, torch.zeros_like(rad)).T)
        return int(idx.shape[0]) if spec else 0

    def _material_arrays(self, frame: Frame, region: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """kd, ks (Q, 3) and α (Q,) from the frame's per-region materials."""
        Q = region.shape[0]
        kd = torch.zeros(Q, 3)
        ks = torch.zeros(Q, 3)
        al = torch.ones(Q)
        for r, name in enumerate(self.scene.regions):
            mat = frame.materials[name]
            if mat.kind not in self.capabilities.brdfs:
                raise ValueError(f"zh_shadow supports {sorted(self.capabilities.brdfs)} BRDFs, region {name!r} is {mat.kind!r}")
            sel = region == r
            kd[sel] = torch.tensor(mat.kd, dtype=torch.float32)
            if mat.kind == "phong":
                ks[sel] = torch.tensor(mat.ks, dtype=torch.float32)
                al[sel] = float(mat.s)
        return kd, ks, al

    def _render_reference(self, frame: Frame, gbuffer: GBuffer) -> Tensor:
        """The slow reference path (the test oracle of `render`): per shaded point, the lobes of the
        three vertices rotated into the normal / reflection frame, ZH → SH, M^α, and the lighting
        rotated into that frame (`shade`), exactly as §4.3 lists the steps."""
        if self.model is None or self.scene is None:
            raise RuntimeError("call precompute(scene) before render()")
        scene, m = self.scene, self.model
        pose = frame.pose
        if scene.skeleton is None:
            pose_vec = torch.zeros(0)
            geom = scene.geometry()
        else:
            pose_vec = torch.zeros(scene.skeleton.num_joints) if pose is None else torch.as_tensor(pose).float()
            geom = scene.geometry(pose_vec)
        light = project_latlong(frame.envmap, m.order).float()   # direct, uncached (the oracle of `_lighting`)
        if self.config["window"] != "none":   # once, on the lighting: every term and mode sees it
            light = convolve_factors(light, window_factors(self.config["window"], m.order,
                                                           self.config["window_width"], dtype=light.dtype))
        clamp = self.config["clamp"]
        k, ax = m.lobes_at(pose_vec)                                          # (N, c, n), (N, c, 3) local
        Fv = frame_matrix(geom.N.float())                                      # (N, 3, 3) world → local
        ax_w = (Fv.transpose(-1, -2)[:, None] @ ax[..., None]).squeeze(-1)     # (N, c, 3) world
        out = torch.zeros(gbuffer.num_samples, 3)
        if self.config["shading"] == "vertex":
            cam = torch.as_tensor(frame.camera.origin, dtype=torch.float32)
            wo = cam - geom.V
            wo = wo / wo.norm(dim=-1, keepdim=True).clamp_min(1e-12)
            rad = torch.zeros(geom.num_vertices, 3)
            kd, ks, al = self._material_arrays(frame, geom.vertex_region)
            for a in range(0, geom.num_vertices, SHADE_CHUNK):
                s = slice(a, a + SHADE_CHUNK)
                rad[s] = shade(k[s], ax_w[s], geom.N[s], wo[s], light, kd[s], ks[s], al[s],
                               specular=self.config["specular"], ops=self._ops)
            if clamp:   # per vertex, before the interpolation (module docstring: negative radiance)
                rad = rad.clamp_min(0.0)
            out = gbuffer.interpolate(rad, geom.F)
            self._last_counts = (gbuffer.num_samples, int(geom.num_vertices), int((ks > 0).any(-1).sum()))
        else:
            n_spec = 0
            idx, w = gbuffer.vertex_weights(geom.F)                            # (P, 3) each
            hits = gbuffer.hit.nonzero().squeeze(-1)
            c, n = m.lobes, m.order
            for a in range(0, hits.shape[0], SHADE_CHUNK):
                h = hits[a:a + SHADE_CHUNK]
                vi, wi = idx[h], w[h]                                          # (Q, 3)
                kq = (k[vi] * wi[..., None, None]).reshape(-1, 3 * c, n)      # barycentric weights
                aq = ax_w[vi].reshape(-1, 3 * c, 3)
                kd, ks, al = self._material_arrays(frame, gbuffer.region[h])
                n_spec += int((ks > 0).any(-1).sum())
                out[h] = shade(kq, aq, gbuffer.normal[h], gbuffer.wo[h], light, kd, ks, al,
                               specular=self.config["specular"], ops=self._ops)
            if clamp:   # per shaded sample, before the pixel resolve (the paper does not clamp; see above)
                out = out.clamp_min(0.0)
            self._last_counts = (gbuffer.num_samples, int(hits.numel()), n_spec)
        return gbuffer.resolve(out)

    def memory(self) -> dict[str, int]:
        if self.model is None:
            return {}
        tabs = [] if self._tables is None else list(self._tables[1].values())
        return {"linear_model_X": tensor_bytes(self.model.X),
                "operators": sum(tensor_bytes(t) for t in self._ops.values()),
                "light_sh": 0 if self._light is None else tensor_bytes(self._light[1]),
                "pose_visibility_sh": 0 if self._posed is None else tensor_bytes(self._posed[2]),
                "shade_tables": sum(tensor_bytes(t) for t in tabs)}

    def frame_cost(self, frame_kind: str, num_samples: int) -> FrameCost | None:
        """The compulsory work of one frame of ``frame_kind`` on ``num_samples`` G-buffer samples:
        the paper's run time (§4.3) at its minimum, whatever our implementation does.

        Shaded points: the covered samples ("sample" shading) or the vertices ("vertex"), counted
        from the last render on a G-buffer of ``num_samples`` samples (every sample covered and
        specular if there was none). Per kind (frame_kind letters; what did not change is reused):

        * bytes: G-buffer (`GBUFFER_BYTES_PER_SAMPLE` + the int64 region in "sample" shading) and the
          (P, 3) float32 output per sample; the faces F (int64, face → vertices); the BRDF parameters
          (kd, ks, α per region) and the M^α operators' non-zeros (diffuse + one per specular
          region); the (n², 3) SH lighting — and for "E" the new env map (H·W·3 float32);
          per vertex: with "P" the linear model X ((J+1)·N·6c float32) and the posed normals (the
          local → world frame), else the cached visibility in its smallest form
          (min(n², 6c + 3) floats: SH, or lobes + normal); "vertex" shading reads positions and
          normals (N·6 float32).
        * flops (a multiply-add is 2): with "P", per vertex the model [pose, 1]·X (2(J+1)·6c) and
          per lobe the chart → axis → world transform (25) and ZH → SH (3n²: y(s), Λ_l k_l y, sum);
          with a lighting change (L, E, VL, VBL) one rotation of the SH lighting (6·Σ(2l+1)²) and
          for "E" its projection (separable: 2·H·W·3·(2n−1) + 2·H·n²·3); per shaded point:
          the barycentric interpolation of v ("sample": 6n²), then per term (diffuse about n, α = 1;
          specular about R where ks > 0) the lighting rotated into the frame (6·Σ(2l+1)²), v
          rotated into it (2·Σ(2l+1)², specular only: the diffuse one is the vertex frame), M^α v
          (2·nnz) and the dot (6n²); plus R (9), n·ωo (5) and kd/ks (12). Frames that change only
          the lighting ("L", "E") reuse t = M^α v per point (bytes: n² floats per term, read) and
          redo only the rotation and the dot. Not counted: building rotation matrices, skinning.
        """
        if self.model is None or self.scene is None:
            return None
        kind = str(frame_kind)
        m, cfg = self.model, self.config
        n, c = m.order, m.lobes
        n2, rot = n * n, sum((2 * l + 1) ** 2 for l in range(n))
        geom = self.scene.geometry()
        N, nF = int(geom.num_vertices), int(geom.F.shape[0])
        J1 = int(m.X.shape[0])
        P = int(num_samples)
        if self._last_counts is not None and self._last_counts[0] == P:
            Q, Qs = self._last_counts[1], self._last_counts[2]
        else:
            Q = Qs = N if cfg["shading"] == "vertex" else P
        regions = self.scene.regions
        n_spec_regions = sum(1 for r in regions if self.scene.materials[r].kind == "phong")
        nnz = int((self._op(1.0) != 0).sum())
        pose, light_ch = "P" in kind, any(ch in kind for ch in "LE")
        env_bytes = int(torch.as_tensor(self.scene.envmap.data).numel()) * 4
        H = int(torch.as_tensor(self.scene.envmap.data).shape[0])
        # -- bytes
        b = P * (GBUFFER_BYTES_PER_SAMPLE + (8 if cfg["shading"] == "sample" else 0)) + P * 3 * 4
        b += nF * 3 * 8 + len(regions) * 7 * 4 + (1 + n_spec_regions) * nnz * 4 + n2 * 3 * 4
        b += env_bytes if "E" in kind else 0
        b += (J1 * N * 6 * c + N * 3) * 4 if pose else N * min(n2, 6 * c + 3) * 4
        b += N * 6 * 4 if cfg["shading"] == "vertex" else 0
        # -- flops
        f = N * (2 * J1 * 6 * c + c * (25 + 3 * n2)) if pose else 0
        if light_ch:
            f += 6 * rot
        if "E" in kind:
            f += 2 * (env_bytes // 4) * (2 * n - 1) + 2 * H * n2 * 3
        lighting_only = kind in ("L", "E")
        per_d = 6 * rot + 6 * n2 + (0 if lighting_only else 2 * nnz)
        per_s = 6 * rot + 6 * n2 + (0 if lighting_only else 2 * rot + 2 * nnz + 9)
        if lighting_only:
            b += (Q + Qs) * n2 * 4
        f += Q * (per_d + 5 + 12) + Qs * per_s
        if cfg["shading"] == "sample" and not lighting_only:
            f += Q * 6 * n2
        if cfg["shading"] == "vertex":
            f += P * 3 * 3 * 2                                    # interpolate the radiance
        return FrameCost(bytes=int(b), flops=int(f))

    def _op(self, a: float) -> Tensor:
        if a not in self._ops:
            self._ops[a] = phong_operator(a, self.model.order)
        return self._ops[a]


class _PoseAdapter:
    """Scene view for `pose_visibility` that also accepts the empty pose of a static scene."""

    def __init__(self, scene):
        self._s = scene

    def geometry(self, pose):
        return self._s.geometry(None if self._s.skeleton is None else pose)
