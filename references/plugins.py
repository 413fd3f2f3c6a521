"""Our materials and env maps as Mitsuba 3 objects (docs/ARCHITECTURE.md, "references/").

* Every `scenes.materials` BRDF is a Python BSDF plugin ``prt_<kind>`` (a `mi.BSDF` subclass),
  with the same formulas and the same sampling strategy as the torch code, written in Dr.Jit.
  `register_all()` registers them (idempotent); `material_to_mitsuba(mat)` gives the dict for
  `mi.load_dict`.
* `envmap_to_mitsuba(env)` gives the ``envmap`` emitter dict whose ``eval`` equals
  `EnvMap.radiance` (tested in tests/references/test_envmap_mitsuba.py).

Mitsuba ↔ torch conventions (both in the local shading frame, z = normal):
  Mitsuba ``si.wi`` (towards the viewer)  = our ``wo``;
  Mitsuba ``wo`` argument / ``bs.wo`` (towards the light) = our ``wi``.
  Mitsuba ``BSDF.eval`` returns f·cosθ of the light direction (the cosine IS included; our torch
  ``eval`` excludes it); ``sample`` returns the weight f·cos/pdf.
  Mitsuba's ``pdf`` is 0 below the horizon (the sample is invalid, weight 0), whereas the torch
  ``Material.pdf`` is the density of ``sample`` over the whole sphere; they agree wherever both
  directions are above the horizon, the only place f ≠ 0.
Mixture sampling: ``sample1`` picks the lobe (specular iff sample1 ≥ 1 − p_spec, p_spec =
lum(ks)/(lum(kd)+lum(ks)) as in torch), ``sample2`` drives the lobe's warp directly.

Python BSDFs are fast only in the JIT variants: use `llvm_ad_rgb` (`ensure_variant()`).
"""
from __future__ import annotations

import math

import numpy as np

from references.mitsuba_setup import ensure_variant

_REGISTERED: set[str] = set()  # variants in which the plugins are registered
_CLASSES: dict[str, type] = {}

KINDS = ("lambert", "phong", "blinnphong", "cooktorrance", "torrancesparrow", "ward")
_TINY = 1e-12  # same guard as scenes/materials.py


def plugin_name(kind: str) -> str:
    return f"prt_{kind}"


def material_to_mitsuba(mat) -> dict:
    """BSDF dict for `mi.load_dict`, e.g. {'type': 'prt_phong', 'kd': [...], 'ks': [...], 's': 20.0}.

    Registers the plugins if needed.
    """
    register_all()
    p = dict(mat.params())
    kind = p.pop("kind")
    if kind not in KINDS:
        raise ValueError(f"no Mitsuba plugin for material kind {kind!r}")
    out = {"type": plugin_name(kind)}
    for k, v in p.items():
        out[k] = [float(c) for c in v] if isinstance(v, (list, tuple)) else float(v)
    return out


def envmap_to_mitsuba(env, *, scale: float = 1.0) -> dict:
    """Mitsuba ``envmap`` emitter dict for a `scenes.envmap.EnvMap` (data + to_world rotation).

    Mitsuba's envmap eval at ``si.wi = −d`` then equals ``env.radiance(d)`` (to float32 round-off).
    Checked against mitsuba3 src/emitters/envmap.cpp (3.9): the float32 RGB bitmap is used as is
    (``mi.Bitmap`` of a float32 (H, W, 3) array has srgb_gamma = 0, no conversion); at load time
    Mitsuba appends a copy of column 0 as column W (periodic boundary) — `EnvMap.radiance` does
    the same; ``eval`` multiplies by ``scale`` (default 1; pass `scale` only on purpose).
    Do not update the emitter's ``data`` through ``mi.traverse``: its ``parameters_changed``
    expects the (H, W+1) extended layout and averages the first and last columns; build a new
    emitter from a new EnvMap instead. Mitsuba samples the emitter with its own Hierarchical2D
    warp (luminance × sinθ of the bilinear map); only ``eval`` is required to match ours.
    """
    ensure_variant()
    import mitsuba as mi

    data = np.array(env.data.detach().cpu().numpy(), dtype=np.float32, copy=True, order="C")
    M = np.eye(4)
    M[:3, :3] = env.to_world.detach().cpu().numpy().astype(np.float64)
    d = {"type": "envmap", "bitmap": mi.Bitmap(data), "to_world": mi.ScalarTransform4f(M)}
    if scale != 1.0:
        d["scale"] = float(scale)
    return d


def register_all() -> None:
    """Register ``prt_<kind>`` for every material kind in the active variant (idempotent)."""
    variant = ensure_variant()
    if variant in _REGISTERED:
        return
    import mitsuba as mi

    cls = _make_class()
    for kind in KINDS:
        mi.register_bsdf(plugin_name(kind), lambda props, kind=kind: cls(props, kind))
    _REGISTERED.add(variant)


def _make_class():
    """Build the BSDF class against the active variant's `mi.BSDF` (one class, kind-dispatched)."""
    import drjit as dr
    import mitsuba as mi

    variant = mi.variant()
    if variant in _CLASSES:
        return _CLASSES[variant]

    Float = mi.Float
    INV_PI = 1.0 / math.pi
    LUM = (0.212671, 0.715160, 0.072169)  # scenes.materials.LUMINANCE_WEIGHTS

    def lum(c):
        return sum(w * x for w, x in zip(LUM, c))

    def spherical(cos_t, phi):
        sin_t = dr.sqrt(dr.maximum(1.0 - cos_t * cos_t, 0.0))
        s, c = dr.sincos(phi)
        return mi.Vector3f(sin_t * c, sin_t * s, cos_t)

    def power_cosine_pdf(c, s):
        return dr.select(c > 0, (s + 1.0) / (2.0 * math.pi) * dr.power(dr.maximum(c, 0.0), s), 0.0)

    def power_cosine_sample(u, s):
        cos_t = dr.power(dr.maximum(1.0 - u.x, 0.0), 1.0 / (s + 1.0))
        return spherical(cos_t, 2.0 * math.pi * u.y)

    def half_vector(wi, wo):
        h = wi + wo
        n = dr.norm(h)
        valid = n > 1e-6
        h = h / dr.maximum(n, _TINY)
        h = dr.select(h.z < 0, -h, h)
        return h, valid

    def half_to_wi_pdf(p_h, wo, h, valid):
        woh = dr.abs(dr.dot(wo, h))
        return dr.select(valid & (woh > 0), p_h / (4.0 * dr.maximum(woh, _TINY)), 0.0)

    def reflect_about(wo, h):
        return 2.0 * dr.dot(wo, h) * h - wo

    def beckmann_D(cos_t, m):
        c = dr.maximum(cos_t, _TINY)
        c2 = c * c
        tan2 = dr.maximum(1.0 - c2, 0.0) / c2
        d = dr.exp(-tan2 / (m * m)) / (math.pi * m * m * c2 * c2)
        return dr.select(cos_t > 0, d, 0.0)

    def ts_half_pdf(cos_t, sigma):
        E = 1.0 - math.exp(-((math.pi / 2) / sigma) ** 2)
        c = dr.clip(cos_t, -1.0, 1.0)
        theta = dr.acos(c)
        sin_t = dr.sqrt(dr.maximum(1.0 - c * c, 0.0))
        ratio = dr.select(theta > 1e-3, theta / dr.maximum(sin_t, _TINY), 1.0 + theta * theta / 6.0)
        p = ratio * dr.exp(-dr.square(theta / sigma)) / (math.pi * sigma * sigma * E)
        return dr.select(cos_t > 0, p, 0.0)

    def ward_half_pdf(h, ax, ay):
        hz = dr.maximum(h.z, _TINY)
        e = (dr.square(h.x / ax) + dr.square(h.y / ay)) / (hz * hz)
        p = dr.exp(-e) / (math.pi * ax * ay * hz * hz * hz)
        return dr.select(h.z > 0, p, 0.0)

    class PrtBSDF(mi.BSDF):
        """One of the `scenes.materials` BRDFs (see the module docstring for conventions)."""

        def __init__(self, props, kind):
            mi.BSDF.__init__(self, props)
            from scenes.materials import Material

            params = {"kind": kind}
            for k in props.keys():
                v = props[k]
                params[k] = [float(x) for x in v] if not isinstance(v, (int, float)) else float(v)
            self.material = Material.from_params(params)  # validates (ValueError naming the parameter)
            self.kind = kind
            self.kd_t = tuple(self.material.kd)
            self.ks_t = tuple(self.material.ks_rgb)
            self.kd = mi.Color3f(*self.kd_t)
            self.ks = mi.Color3f(*self.ks_t)
            self.p = {k: float(v) for k, v in params.items() if k not in ("kind", "kd", "ks")}
            diffuse = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
            glossy = mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
            if kind == "ward" and self.p["ax"] != self.p["ay"]:
                glossy = glossy | mi.BSDFFlags.Anisotropic
            self.m_components = [diffuse, glossy]
            self.m_flags = diffuse | glossy

        # -- lobe selection honouring the context's component/type mask
        def _weights(self, ctx):
            has_d = ctx.is_enabled(mi.BSDFFlags.DiffuseReflection, 0)
            has_s = ctx.is_enabled(mi.BSDFFlags.GlossyReflection, 1) and self.kind != "lambert"
            ld, ls = lum(self.kd_t), lum(self.ks_t)
            if has_d and has_s:
                ps = ls / (ld + ls) if ld + ls > 0 else 0.0
            else:
                ps = 1.0 if has_s else 0.0
            return has_d, has_s, ps

        # -- specular part in our convention: wi = light, wo = view; returns a Float factor of ks
        def _spec_eval(self, wi, wo):
            k, p = self.kind, self.p
            if k == "phong":  # Mahajan 2008 eq. 5
                R = mi.Vector3f(-wo.x, -wo.y, wo.z)
                return power_cosine_pdf(dr.dot(R, wi), p["s"])
            if k == "blinnphong":
                h, valid = half_vector(wi, wo)
                s = p["s"]
                return dr.select(valid, (s + 2.0) / (8.0 * math.pi) * dr.power(dr.maximum(h.z, 0.0), s), 0.0)
            if k == "cooktorrance":  # Cook & Torrance 1982
                h, valid = half_vector(wi, wo)
                nh, ni, no = h.z, wi.z, wo.z
                oh = dr.maximum(dr.dot(wo, h), _TINY)
                D = beckmann_D(nh, p["m"])
                F0 = p["F0"]
                F = F0 + (1.0 - F0) * dr.power(dr.maximum(1.0 - oh, 0.0), 5.0)
                G = dr.minimum(1.0, dr.minimum(2 * nh * no / oh, 2 * nh * ni / oh))
                v = D * F * G / dr.maximum(4.0 * ni * no, _TINY)
                return dr.select(valid, v, 0.0)
            if k == "torrancesparrow":  # Mahajan 2008 eq. 14
                h, valid = half_vector(wi, wo)
                sig = p["sigma"]
                th = dr.acos(dr.clip(h.z, -1.0, 1.0))
                return dr.select(valid, dr.exp(-dr.square(th / sig)) / (4.0 * math.pi * sig * sig), 0.0)
            if k == "ward":  # Ward 1992 eq. 5a
                ax, ay = p["ax"], p["ay"]
                h = wi + wo
                hz = dr.maximum(h.z, _TINY)
                e = (dr.square(h.x / ax) + dr.square(h.y / ay)) / (hz * hz)
                c = dr.sqrt(dr.maximum(wi.z * wo.z, _TINY))
                return dr.exp(-e) / (4.0 * math.pi * ax * ay * c)
            return Float(0.0)

        def _spec_pdf(self, wi, wo):
            k, p = self.kind, self.p
            if k == "phong":
                R = mi.Vector3f(-wo.x, -wo.y, wo.z)
                return power_cosine_pdf(dr.dot(R, wi) / dr.maximum(dr.norm(R), _TINY), p["s"])
            h, valid = half_vector(wi, wo)
            if k == "blinnphong":
                ph = power_cosine_pdf(h.z, p["s"])
            elif k == "cooktorrance":
                ph = beckmann_D(h.z, p["m"]) * h.z
            elif k == "torrancesparrow":
                ph = ts_half_pdf(h.z, p["sigma"])
            elif k == "ward":
                ph = ward_half_pdf(h, p["ax"], p["ay"])
            else:
                return Float(0.0)
            return half_to_wi_pdf(ph, wo, h, valid)

        def _spec_sample(self, wo, u):
            k, p = self.kind, self.p
            if k == "phong":
                R = dr.normalize(mi.Vector3f(-wo.x, -wo.y, wo.z))
                return mi.Frame3f(R).to_world(power_cosine_sample(u, p["s"]))
            if k == "blinnphong":
                h = power_cosine_sample(u, p["s"])
            elif k == "cooktorrance":
                m = p["m"]
                tan2 = -(m * m) * dr.log(dr.maximum(1.0 - u.x, 1e-7))
                h = spherical(dr.rsqrt(1.0 + tan2), 2.0 * math.pi * u.y)
            elif k == "torrancesparrow":
                sig = p["sigma"]
                E = 1.0 - math.exp(-((math.pi / 2) / sig) ** 2)
                theta = dr.minimum(sig * dr.sqrt(-dr.log(1.0 - u.x * E)), math.pi / 2)
                h = spherical(dr.cos(theta), 2.0 * math.pi * u.y)
            elif k == "ward":
                r = dr.sqrt(-dr.log(dr.maximum(1.0 - u.x, 1e-7)))
                s, c = dr.sincos(2.0 * math.pi * u.y)
                h = dr.normalize(mi.Vector3f(p["ax"] * r * c, p["ay"] * r * s, 1.0))
            else:
                return mi.Vector3f(0, 0, 1)
            return reflect_about(wo, h)

        # -- the mi.BSDF interface
        def _f(self, wi, wo, has_d, has_s):
            f = mi.Color3f(0.0)
            if has_d:
                f += self.kd * INV_PI
            if has_s:
                f += self.ks * self._spec_eval(wi, wo)
            return f

        def _pdf(self, wi, wo, has_d, has_s, ps):
            p = Float(0.0)
            if has_d and ps < 1.0:
                p += (1.0 - ps) * dr.maximum(wi.z, 0.0) * INV_PI
            if has_s and ps > 0.0:
                p += ps * self._spec_pdf(wi, wo)
            return p

        def eval(self, ctx, si, wo, active=True):
            has_d, has_s, _ = self._weights(ctx)
            wi_, wo_ = wo, si.wi  # ours: wi = light (Mitsuba wo), wo = view (Mitsuba si.wi)
            ok = active & (wi_.z > 0) & (wo_.z > 0)
            val = self._f(wi_, wo_, has_d, has_s) * wi_.z  # Mitsuba's eval includes cosθ
            return dr.select(ok, val, 0.0)

        def pdf(self, ctx, si, wo, active=True):
            has_d, has_s, ps = self._weights(ctx)
            ok = active & (wo.z > 0) & (si.wi.z > 0)
            return dr.select(ok, self._pdf(wo, si.wi, has_d, has_s, ps), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            has_d, has_s, ps = self._weights(ctx)
            wo_ = si.wi
            bs = dr.zeros(mi.BSDFSample3f)
            if not (has_d or has_s):
                return bs, mi.Color3f(0.0)
            pick_s = sample1 >= (1.0 - ps)  # same rule as Material.sample
            wi_ = mi.warp.square_to_cosine_hemisphere(sample2)
            if has_s and ps > 0.0:
                wi_ = dr.select(pick_s, self._spec_sample(wo_, sample2), wi_)
            pdf = self._pdf(wi_, wo_, has_d, has_s, ps)
            ok = active & (wo_.z > 0) & (wi_.z > 0) & (pdf > 0)
            bs.wo = wi_
            bs.pdf = dr.select(ok, pdf, 0.0)
            bs.eta = 1.0
            bs.sampled_component = dr.select(pick_s, mi.UInt32(1), mi.UInt32(0))
            bs.sampled_type = dr.select(pick_s, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                        mi.UInt32(+mi.BSDFFlags.DiffuseReflection))
            weight = self._f(wi_, wo_, has_d, has_s) * (wi_.z / dr.maximum(pdf, _TINY))
            return bs, dr.select(ok, weight, 0.0)

        def traverse(self, callback):
            pass  # parameters are fixed at construction (not differentiable)

        def parameters_changed(self, keys):
            pass

        def to_string(self):
            return f"PrtBSDF[{self.material!r}]"

    _CLASSES[variant] = PrtBSDF
    return PrtBSDF


__all__ = ["register_all", "material_to_mitsuba", "envmap_to_mitsuba", "plugin_name", "KINDS"]
