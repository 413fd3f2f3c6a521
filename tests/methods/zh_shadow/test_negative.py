"""zh_shadow without negative light, and right at the rest pose (issue 19 item 2, issue 15 item 4).

Per scene — the library scenes zh_shadow renders (chess with Phong stand-ins, conftest
`phong_chess`; not dragon, Blinn–Phong only), among them the vendored bunny scan under a captured
probe and the vendored skinned character, a thin-part object (conftest `thin_part_scene`: a mug
with a thin ring handle and a thin spout on a ground plane under the `window` probe) and the
creature with generic pose tracks (conftest `generic_creature`) — frames V 0–2 and VBL 0–2 (seed 0;
for the articulated scenes these are rest-pose frames) and, for those, P 0–2 (their animation at a
phase / clip frames the model was not trained on). Against a 256-spp Mitsuba direct-lighting
reference (seed 0), S = 2:
  * negative fraction: covered pixels with any channel < −1e-4 × the reference's 99th percentile,
    < 0.1 % on every frame;
  * mean brightness: method / reference mean over covered pixels, within 10 % on every frame;
  * RMSE (mean over the frames) pinned.
Default config except the articulated scenes' cheaper fit (`CREATURE_CFG`, the one of
test_method.py).

Measured (this machine, 1 thread; mean over the frames; "before" = the code before issue 19: no
clamp, a training clip without the rest pose; window none in both):

    scene              frames  floor  RMSE before → after  neg. px before → after  mean ratio before → after
    sphere_plane       V, VBL  0.049  0.4519 → 0.4518      0.61 % (max 1.6 %) → 0   0.994–1.023 → 0.994–1.024
    chess (Phong)      V, VBL  0.014  0.0841 → 0.0841      0.53 % (max 1.1 %) → 0   0.932–1.023 → 0.932–1.024
    alcove             V, VBL  0.010  0.0227 → 0.0227      0 → 0                    0.977–0.993 → same
    shadow_detail      V, VBL  0.013  0.1078 → 0.1078      0.70 % (max 1.6 %) → 0   0.959–0.990 → 0.959–0.991
    thin_parts         V, VBL  0.011  0.1017 → 0.1015      2.5 % (max 3.1 %) → 0    0.931–1.012 → 0.933–1.015
    creature           V, VBL  0.034  0.372 → 0.1005       0 → 0                    0.566–0.574 → 0.984–0.998
    creature           P       0.034  0.1029 → 0.1028      0 → 0                    0.990–0.994 → 0.991–0.994
    bunny              V, VBL  0.022  0.2287 → 0.2287      0.21 % (max 0.5 %) → 0   0.979–1.037 → same
    character          V, VBL  0.027  0.0503 → 0.0500      0.38 % (max 0.7 %) → 0   1.025–1.044 → 1.026–1.043
    character          P       0.027  0.0533 → 0.0523      0.71 % (max 0.8 %) → 0   1.035–1.043 → 1.033–1.046
    creature_generic   V, VBL  0.034  0.607 → 0.1017       0 → 0                    0.280–0.285 → 0.982–0.998
    creature_generic   P       0.034  0.143 → 0.1069       0 → 0                    0.903–1.136 → 0.983–0.991

(creature_generic: P frames off the training clip. Trained on its own clip, the character's
rest-pose frames were already right before.) The rest-pose and off-clip errors are the pose model
extrapolating: with a clip that never passes the rest pose,
the bias row of the linear model is an extrapolation, and every pose direction the clip does not
explore falls back on it.

Cause (see methods/zh_shadow/method.py): the order-4 projection of the probes rings — it is
negative over 40 % (sky_sun) to 46 % (window) of the sphere, down to −2.0× / −3.5× the probe's
mean. On the thin-part scene (unclamped): fitted lobes 2.5 % negative pixels, exact ray-cast SH
visibility 3.5 %, no visibility at all (V ≡ 1) 5.1 %. Windowing the lighting (`window`,
`window_width`; clamped in every case), RMSE relative to no window on frames V0 and VBL2
(sphere_plane, chess, alcove, shadow_detail, creature, bunny, character, thin_parts):
    Hanning w = 4   1.20 1.27 1.06 1.57 1.52 1.30 1.91 1.00
    Hanning w = 6   1.07 1.10 1.01 1.24 1.17 1.13 1.39 0.91
    Hanning w = 8   1.03 1.05 1.00 1.12 1.07 1.06 1.21 0.92
    Lanczos w = 4   1.13 1.18 1.02 1.39 1.31 1.21 1.62 0.94
    Lanczos w = 6   1.04 1.06 1.00 1.15 1.09 1.08 1.25 0.92
with the mean brightness moved by −13…+10 % (w = 4) / −6…+5 % (w = 6); unclamped, Hanning w = 4
still leaves 3.1 % negative pixels on thin_parts (the windowed `window` probe is still negative
over 38 % of the sphere). A non-negative least-squares lighting fit: images 1.1–1.7× too bright.
So: no window, clamp at 0 (the defaults).
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from methods.zh_shadow import ZHShadow
from methods.zh_shadow import precompute as pc

SCENES = ("sphere_plane", "chess", "alcove", "shadow_detail", "creature", "bunny", "character", "thin_parts",
          "creature_generic")
CREATURE_CFG = dict(train_poses=24, n_dirs=512, fit_iters=30)
NEG_MAX = 1e-3          # issue 19: < 0.1 % negative pixels
MEAN_TOL = 0.10         # issue 19: mean brightness within 10 % of the reference
REST_VS_ANIM = 1.5      # issue 15: rest-pose RMSE within 1.5× the animation's
# RMSE (mean over the frames, clamped default) pinned per scene: measured values; SLACK covers
# float / BLAS differences of a deterministic pipeline with fixed seeds (as test_tp_vs_mitsuba.py).
PINNED = {"sphere_plane": 0.4518, "chess": 0.0841, "alcove": 0.0227, "shadow_detail": 0.1078,
          "creature": 0.1012, "bunny": 0.2287, "character": 0.0508, "thin_parts": 0.1015,
          "creature_generic": 0.1035}
SLACK = 1.05
WINDOWS = [("hanning", 4.0), ("hanning", 6.0), ("lanczos", 6.0)]
WINDOW_FRAMES = {("V", 0), ("VBL", 2)}


def frame_stats(img, ref, gb) -> dict:
    """RMSE, negative fraction and mean ratio of a method image (H, W, 3) against a Reference."""
    from references.metrics import rmse

    img = np.asarray(img)
    R = ref.image.numpy()
    cov = ref.coverage.numpy() & gb.coverage.numpy()
    p99 = np.percentile(R[cov], 99)
    neg = ((img < -1e-4 * p99).any(-1) & cov).sum() / cov.sum()
    return {"rmse": rmse(img, R, cov), "neg": float(neg), "ratio": float(img[cov].mean() / R[cov].mean()),
            "floor": ref.noise_floor}


_RESULTS: dict = {}


def _results(name, zh_scene) -> dict:
    """{(kind, i): stats} for the default method, the unclamped one and the windowed ones."""
    if name in _RESULTS:
        return _RESULTS[name]
    from references.gbuffer import make_gbuffer
    from references.render import render_reference
    from scenes.sequences import make_sequence

    scene = zh_scene(name)
    m = ZHShadow(**CREATURE_CFG) if scene.skeleton is not None else ZHShadow()
    with pc.torch_threads(1):
        m.precompute(scene)
    kinds = ("V", "VBL", "P") if scene.skeleton is not None else ("V", "VBL")
    out = {}
    for kind in kinds:
        for i, fr in enumerate(make_sequence(scene, kind, 3, seed=0)):
            gb = make_gbuffer(scene, fr, 2)
            ref = render_reference(scene, fr, bounces=0, spp=256, seed=0)
            variants = [("default", {}), ("unclamped", {"clamp": False})]
            # the windows on 2 frames per scene (test time); creature_generic's V/VBL frames are the
            # creature's rest pose again
            if (kind, i) in WINDOW_FRAMES and name != "creature_generic":
                variants += [((w, ww), {"window": w, "window_width": ww}) for w, ww in WINDOWS]
            for key, cfg in variants:
                out[(key, kind, i)] = frame_stats(m.with_render_config(**cfg).render(fr, gb).numpy(), ref, gb)
    _RESULTS[name] = out
    return out


def _mean(res, variant, kinds=("V", "VBL", "P"), key="rmse"):
    return float(np.mean([s[key] for (v, k, _), s in res.items() if v == variant and k in kinds]))


@pytest.mark.parametrize("name", SCENES)
def test_no_negative_light_and_right_brightness(name, zh_scene):
    res = _results(name, zh_scene)
    table = {f"{k}{i}": (round(s["rmse"], 4), s["neg"], round(s["ratio"], 3))
             for (v, k, i), s in res.items() if v == "default"}
    for (v, k, i), s in res.items():
        if v == "default":
            assert s["neg"] < NEG_MAX, (k, i, table)
            assert abs(s["ratio"] - 1.0) <= MEAN_TOL, (k, i, table)
    err = _mean(res, "default")
    assert err <= SLACK * PINNED[name], (err, PINNED[name], table)
    assert err > _mean(res, "default", key="floor"), table          # cannot beat the reference's noise
    # the clamp only removes negative light: it never costs error
    assert err <= _mean(res, "unclamped") + 1e-6


@pytest.mark.parametrize("name", ["shadow_detail", "thin_parts"])
def test_unclamped_shade_goes_negative(name, zh_scene):
    """Without the clamp (the paper's shade = t·l) the negative pixels are there (measured 0.7 % and
    2.5 % of the covered pixels): the test above can fail."""
    res = _results(name, zh_scene)
    assert _mean(res, "unclamped", key="neg") > 3 * NEG_MAX


def test_default_window_has_the_lowest_error(zh_scene):
    """The default (no window) has the lowest RMSE against Mitsuba: the geometric mean over the
    scenes of RMSE(window) / RMSE(none) exceeds 1 for every window tried."""
    for w in WINDOWS:
        logs = []
        for name in SCENES[:-1]:                                          # not creature_generic
            res = _results(name, zh_scene)
            frames = {(k, i) for (v, k, i) in res if v == w}
            same = [(res[("default", k, i)]["rmse"], res[(w, k, i)]["rmse"]) for k, i in sorted(frames)]
            logs.append(math.log(np.mean([x for _, x in same]) / np.mean([d for d, _ in same])))
        assert math.exp(np.mean(logs)) > 1.0, (w, [round(math.exp(x), 3) for x in logs])


@pytest.mark.parametrize("name", ["creature", "creature_generic"])
def test_rest_pose_error_at_the_animation_level(name, zh_scene):
    """Issue 15: the training clip eases in from the rest pose, so the rest-pose frames (V, VBL) are
    about as right as the animation (P) (see the module docstring for before/after)."""
    res = _results(name, zh_scene)
    rest, anim = _mean(res, "default", ("V", "VBL")), _mean(res, "default", ("P",))
    assert rest <= REST_VS_ANIM * anim, (rest, anim)


def test_lighting_truncation_is_the_cause(zh_scene):
    """The order-4 lighting itself is negative over a large part of the sphere, and on the
    thin-part scene exact ray-cast SH visibility (no lobe fit, no pose model) or no visibility at all
    leave at least as many negative pixels as the fitted lobes (measured 3.5 % / 5.1 % vs 2.5 %)."""
    from methods.core.sampling import fibonacci_sphere
    from methods.core.sh import project_latlong, sh_eval
    from methods.zh_shadow.method import _PoseAdapter
    from references.gbuffer import make_gbuffer
    from references.render import render_reference
    from scenes.sequences import make_sequence

    scene = zh_scene("thin_parts")
    d, _ = fibonacci_sphere(4000, dtype=torch.float64)
    L = sh_eval(d, 4) @ project_latlong(scene.envmap, 4).double()
    assert (L.min(-1).values < 0).double().mean() > 0.3                          # measured 0.46

    m = ZHShadow(clamp=False)
    with pc.torch_threads(1):
        m.precompute(scene)
    v, _ = pc.pose_visibility(_PoseAdapter(scene), torch.zeros(1, 0), 4, n_dirs=m.config["n_dirs"])
    v = v[0].double()
    ax, _ = fibonacci_sphere(12, dtype=torch.float64)                   # 12 fixed generic axes hold any
    ax = ax[None].expand(v.shape[0], 12, 3)                             # order-4 SH vector exactly
    k = pc.solve_lobe_coeffs(v, ax, ridge=1e-9)
    assert (pc.lobes_sh(k, ax) - v).abs().max() <= 1e-6
    exact = pc.ZHModel(torch.cat([pc.axis_to_chart(ax), k], -1).reshape(1, v.shape[0], -1).float(), 4, 12)
    none = pc.ZHModel(torch.zeros_like(m.model.X), 4, m.model.lobes)
    none.X[-1, :, 2] = math.sqrt(4 * math.pi)                                   # V ≡ 1
    fitted = m.model
    neg = {"fitted": [], "exact": [], "unshadowed": []}
    for fr in make_sequence(scene, "V", 3, seed=0):
        gb = make_gbuffer(scene, fr, 2)
        ref = render_reference(scene, fr, bounces=0, spp=256, seed=0)
        for key, model in (("fitted", fitted), ("exact", exact), ("unshadowed", none)):
            m.model = model
            neg[key].append(frame_stats(m.render(fr, gb).numpy(), ref, gb)["neg"])
    f, e, u = (float(np.mean(neg[k])) for k in ("fitted", "exact", "unshadowed"))
    assert f > 3 * NEG_MAX and e >= 0.8 * f and u >= f, neg
