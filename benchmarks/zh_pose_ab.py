"""Same-process A/B of ZHShadow pose (P) frames — and any other kind — against another checkout's
run-time code (`benchmarks.zh_shadow --baseline` only A/Bs sample shading).

    python -m benchmarks.zh_pose_ab --baseline /work/base [--config '{"order":8,"shading":"vertex","specular":"cosine"}']
        [--kinds P] [--frames 9] [--threads 1] [--precompute-code /work/base] [--profile] [--stages-ab]

The baseline is its whole ``methods`` package (`benchmarks.common.checkout_class`; its frames
rendered inside `benchmarks.common.checkout_modules`, so its lazy imports — `native`, `gouraud` —
are the baseline's too), and `scenes/scene.py`'s `Scene.geometry` (the skinning, `_BaseGeometry`)
imported under another name; both classes get one
precomputation (from the harness cache; ``--precompute-code DIR`` keys it on DIR's code — a run-time-only change keeps the cached
state valid) and render each kind's frames alternating which goes first, frames 0–1 untimed
(`benchmarks.common.ab_frames`: medians of process CPU and wall time, their ratio, max
|new − reference| / max |reference| against `_render_reference`). ``--profile``: the new code's
P frame under ``torch.profiler`` (self CPU time per op / compiled kernel) and the split of its
stages (`stages`); ``--stages-ab``: the conjugation stages alone, old against new (`stages_ab`).
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import json
import os
import sys
import time

import torch

from benchmarks.common import (ab_frames, ab_options, ab_report, apply_ab_options, checkout_class, checkout_modules,
                               load_file_module, machine_limits, precomputed, registry_kept, setup)
from reports import measure

PHYSICAL = '{"order":8,"shading":"vertex","specular":"cosine"}'


def baseline_class(root: str):
    """ZHShadow of the checkout ``root``: its whole ``methods`` package (`benchmarks.common.checkout_class`;
    until session 29 its runtime, method and `methods.core.gouraud` were loaded by path and the base
    ran THIS tree's `native.py`, precompute and the rest of core, so a change there read ~1.0x).
    Render its frames inside ``checkout_modules(root)`` (`base_modules`)."""
    return checkout_class(root, "methods.zh_shadow.method", "ZHShadow")


def base_modules(root: str, which: str):
    """``checkout_modules(root)`` for the baseline's frames (``which == "base"``), else a no-op."""
    return checkout_modules(root) if which == "base" else contextlib.nullcontext()


class _BaseGeometry:
    """A scene whose ``geometry(pose)`` is the checkout ``root``'s `Scene.geometry` (its
    ``scenes/scene.py``: the skinning a P frame pays; forward kinematics and the reference `skin`
    are this tree's, unchanged), every other attribute the scene's own — the baseline's view of the
    bench scene, so the A/B times the posing code of both checkouts."""

    def __init__(self, scene, root: str):
        with registry_kept():
            mod = sys.modules.get("_zhp_base_scene") or load_file_module(os.path.join(root, "scenes/scene.py"),
                                                                         "_zhp_base_scene")
        self._scene, self._geometry = scene, mod.Scene.geometry

    def geometry(self, pose=None):
        return self._geometry(self._scene, pose)

    def __getattr__(self, name):
        return getattr(self._scene, name)


def _best(f, repeats: int = 5) -> float:
    f()
    ts = []
    for _ in range(repeats):
        c = time.process_time()
        f()
        ts.append(time.process_time() - c)
    return min(ts)


def stages(m, frame, gb, repeats: int = 5) -> dict:
    """Process-CPU seconds (best of ``repeats``) of the stages of one P frame of ``m`` at its real
    sizes: skinning, the pose model + eq. 1 (`world_visibility`), the cos-weighted visibility w, the
    specular transfer, the per-vertex radiance products and the Gouraud resolve, and the whole
    frame (a fresh pose each time: caches dropped)."""
    from methods.core import gouraud
    from methods.zh_shadow import runtime as rt

    scene, cosine = m.scene, m.config["specular"] == "cosine"
    pose = torch.as_tensor(frame.pose).float() if frame.pose is not None else None
    out = {"skinning": _best(lambda: scene.geometry(pose), repeats)}
    geom = scene.geometry(pose)
    X, c = m.model.X, m.model.lobes
    nrm = geom.N.float()
    fr = "zyz" if cosine else "world"
    out["world_visibility"] = _best(lambda: rt.world_visibility(X, pose, nrm, c, point_minor=True, frame=fr), repeats)
    vT = rt.world_visibility(X, pose, nrm, c, point_minor=True, frame=fr)
    nT = rt.rows(nrm)
    wfn = (lambda: rt.cosine_visibility_zyz(vT, nT)) if cosine else (lambda: rt.cosine_visibility(vT, nT))
    out["cosine_visibility"] = _best(wfn, repeats)
    w = wfn()
    cam = torch.as_tensor(frame.camera.origin, dtype=torch.float32)
    woT = cam[:, None] - rt.rows(geom.V.float())
    woT = woT / (woT * woT).sum(0, keepdim=True).sqrt().clamp_min(1e-12)
    mats = m._region_materials(frame)
    alphas = [al if bool((ks > 0).any()) else None for _, ks, al in mats]
    vreg = geom.vertex_region
    out["specular_transfer"] = _best(lambda: rt.specular_transfer(w if cosine else vT, nT, woT, vreg, alphas), repeats)
    if hasattr(rt, "pose_transfer"):
        out["pose_transfer(w+specular)"] = _best(lambda: rt.pose_transfer(vT, nT, woT, vreg, alphas, cosine=cosine),
                                                 repeats)
    rad = torch.zeros(int(nrm.shape[0]), 3)
    out["resolve"] = _best(lambda: gouraud.resolve(rad, geom.F.T, gb.face, gb.bary, gb.hit, gb.height, gb.width,
                                                   gb.spp_side), repeats)

    def frame_fresh():
        m._posed = m._vertex_diffuse = m._vertex_transfer = None
        m.render(frame, gb)

    out["frame"] = _best(frame_fresh, repeats)
    return {k: 1e3 * v for k, v in out.items()}


def stages_ab(m, frame, root: str, repeats: int = 15) -> dict:
    """The conjugation stages of one P frame of ``m`` (vertex shading), the baseline's runtime
    (the checkout ``root``'s, `baseline_class`) against this tree's, alternating call by
    call: median process-CPU ms of w (`cosine_visibility_zyz` or `cosine_visibility`) and of
    `specular_transfer`, and their ratios."""
    import statistics

    from benchmarks.common import _CHECKOUT_MODULES
    from methods.zh_shadow import runtime as rt

    old = _CHECKOUT_MODULES[root]["methods.zh_shadow.runtime"]
    cosine = m.config["specular"] == "cosine"
    pose = torch.as_tensor(frame.pose).float() if frame.pose is not None else None
    geom = m.scene.geometry(pose)
    nrm = geom.N.float()
    vT = rt.world_visibility(m.model.X, pose, nrm, m.model.lobes, point_minor=True, frame="zyz" if cosine else "world")
    nT = rt.rows(nrm)
    cam = torch.as_tensor(frame.camera.origin, dtype=torch.float32)
    woT = cam[:, None] - rt.rows(geom.V.float())
    woT = woT / (woT * woT).sum(0, keepdim=True).sqrt().clamp_min(1e-12)
    alphas = [al if bool((ks > 0).any()) else None for _, ks, al in m._region_materials(frame)]
    vreg = geom.vertex_region
    out = {}
    for name, fn in (("w", lambda r: r.cosine_visibility_zyz(vT, nT) if cosine else r.cosine_visibility(vT, nT)),
                     ("specular_transfer", lambda r: r.specular_transfer(w if cosine else vT, nT, woT, vreg, alphas))):
        w = rt.cosine_visibility_zyz(vT, nT) if cosine else rt.cosine_visibility(vT, nT)
        t = {"base": [], "new": []}
        for k, r in (("base", old), ("new", rt)):
            with base_modules(root, k):
                fn(r)
        for i in range(repeats):
            for k, r in ((("base", old), ("new", rt)) if i % 2 == 0 else (("new", rt), ("base", old))):
                with base_modules(root, k):
                    c = time.process_time()
                    fn(r)
                    t[k].append(time.process_time() - c)
        mb, mn = statistics.median(t["base"]), statistics.median(t["new"])
        out[name] = {"base_ms": 1e3 * mb, "new_ms": 1e3 * mn, "ratio": mb / mn}
    return out


def profile(m, frames, gbs) -> str:
    """torch.profiler table (self CPU time) of the new code's frames[1:] (frame 0 warms up)."""
    from torch.profiler import ProfilerActivity, profile as prof

    m.render(frames[0], gbs[0])
    with prof(activities=[ProfilerActivity.CPU]) as p:
        for f, g in zip(frames[1:], gbs[1:]):
            m.render(f, g)
    return p.key_averages().table(sort_by="self_cpu_time_total", row_limit=30)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ab_options(ap, config=PHYSICAL, kinds=("P",))
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--stages-ab", action="store_true", help="A/B the conjugation stages of a P frame alone")
    a = ap.parse_args(argv)
    apply_ab_options(a)
    from methods.zh_shadow.method import ZHShadow as New

    cfg = json.loads(a.config)
    Base = baseline_class(a.baseline)
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1)
    m, _ = precomputed(New, scene, cfg)
    out: dict = {"method": "zh_shadow", "scene": a.scene, "config": cfg, "threads": a.threads, "load": os.getloadavg()}
    bw, peak = [measure.triad_bandwidth()], [measure.matmul_peak()]
    kinds = {}
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=a.seed)
        new = m.with_render_config()
        base = copy.copy(new)
        base.__class__ = Base
        base.model = copy.copy(new.model)   # its own X attribute: the new code re-lays X out (`_pose_state`)
        base.scene = _BaseGeometry(scene, a.baseline)
        ref = m.with_render_config()
        kinds[kind] = ab_frames(new, base, ref._render_reference, frames, gbs, kind, base_root=a.baseline)
        if a.profile and kind == "P":
            out["stages_ms"] = stages(m.with_render_config(), frames[-1], gbs[-1])
            print(profile(m.with_render_config(), frames, gbs))
        if a.stages_ab and kind == "P":
            out["stages_ab"] = stages_ab(m.with_render_config(), frames[-1], a.baseline)
            print(json.dumps(out["stages_ab"]), flush=True)
    B, Pk = machine_limits(out, bw, peak)
    ab_report(out, kinds, B, Pk, f"zh_shadow {a.config} {a.scene} {a.size}, {a.threads} thread(s)")
    return out


if __name__ == "__main__":
    main()
