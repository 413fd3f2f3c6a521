"""ZHShadow (Nowrouzezahrai 2008 §4.3) behind the common interface: run-time shading vs brute-force
quadrature, rendered held-out pose vs the oracle, configuration errors."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from methods.registry import get_method
from methods.core.sampling import gauss_legendre_sphere
from methods.core.sh import reconstruct, sh_eval
from methods.zh_shadow import ZHShadow
from methods.zh_shadow import precompute as pc
from methods.zh_shadow.method import shade

# Quadrature of band-limited integrands times max(0, ·)^α kinks on a 160 × 320 Gauss–Legendre ×
# uniform grid: measured error ≤ 3e-6 relative to the integral's scale (float64).
QUAD_TOL = 2e-5


def _random_setup(Q=6, L=4, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    k = torch.randn(Q, L, 4, generator=g, dtype=dtype) * 0.5
    k[..., 0] += 1.5
    ax = torch.randn(Q, L, 3, generator=g, dtype=dtype)
    ax = ax / ax.norm(dim=-1, keepdim=True)
    n = torch.randn(Q, 3, generator=g, dtype=dtype)
    n = n / n.norm(dim=-1, keepdim=True)
    wo = torch.randn(Q, 3, generator=g, dtype=dtype)
    wo = wo - (wo * n).sum(-1, keepdim=True).clamp_max(0) * 1.5 * n   # mostly in front
    wo = wo / wo.norm(dim=-1, keepdim=True)
    light = torch.randn(16, 3, generator=g, dtype=dtype) * 0.3
    light[0] += 2.0
    return k, ax, n, wo, light


@pytest.mark.parametrize("alpha", [1.0, 6.0, 25.0])
def test_shade_equals_quadrature(alpha):
    """Diffuse: ∫ L₄ V₄ max(0, n·ω)/π; published Phong: ∫ L₄ V₄ (α+1)/(2π) max(0, R·ω)^α (eq. 2,
    exact for band-limited V and L); cosine variant: the same with V₄ replaced by the order-4
    projection of V₄·max(0, n·ω)."""
    k, ax, n, wo, light = _random_setup()
    Q = k.shape[0]
    d, w = gauss_legendre_sphere(160, 320, dtype=torch.float64)
    Y = sh_eval(d, 4)                                                   # (D, 16)
    L = Y @ light                                                       # (D, 3)
    lobes = pc.lobes_sh(k, ax)                                          # (Q, 16) world SH of V
    V = lobes @ Y.T                                                     # (Q, D)
    R = 2 * (wo * n).sum(-1, keepdim=True) * n - wo
    cos_n = (d @ n.T).T.clamp_min(0)                                    # (Q, D)
    lobe = (alpha + 1) / (2 * math.pi) * (d @ R.T).T.clamp_min(0) ** alpha
    one = torch.ones(Q, 3, dtype=torch.float64)
    zero = torch.zeros(Q, 3, dtype=torch.float64)
    front = ((n * wo).sum(-1) > 0)[:, None]
    diff = shade(k, ax, n, wo, light, one, zero, torch.full((Q,), alpha, dtype=torch.float64))
    want = torch.einsum("qd,dc,d->qc", V * cos_n / math.pi, L, w)
    assert front.any() and torch.where(front, (diff - want).abs(), zero).max() <= QUAD_TOL
    for variant in ("published", "cosine"):
        spec = shade(k, ax, n, wo, light, zero, one, torch.full((Q,), alpha, dtype=torch.float64),
                     specular=variant)
        Vs = V if variant == "published" else ((V * cos_n * w) @ Y) @ Y.T   # P₄[V₄ cos⁺]
        want = torch.einsum("qd,dc,d->qc", Vs * lobe, L, w)
        assert torch.where(front, (spec - want).abs(), zero).max() <= QUAD_TOL, variant
    assert (diff[~front.squeeze(-1)] == 0).all()                        # BRDF is 0 for n·ωo ≤ 0


def test_config_errors():
    bad = [dict(order=1), dict(order=9), dict(lobes=0), dict(lobes=5), dict(train_poses=1), dict(n_dirs=0),
           dict(specular="exact"), dict(shading="pixel"), dict(below_horizon="clip"), dict(train_source="mocap"),
           dict(axis_anchor=-1.0), dict(axis_anchor=float("nan")), dict(fit_iters=-1), dict(order=4.0),
           dict(window="gauss"), dict(window_width=0.0), dict(window_width=float("inf")), dict(clamp=1),
           dict(train_rest=1.0), dict(train_rest=-0.1), dict(train_rest=True)]
    for kw in bad:
        with pytest.raises(ValueError):
            ZHShadow(**kw)


def test_window_and_clamp_apply_once_to_every_mode():
    """`window` is one per-band scale of the SH lighting (the same image as rendering with the
    windowed lighting baked in), in both shading modes and both specular variants; `clamp` only
    zeroes negative shades; both are recorded in the config."""
    from methods.core.zh import convolve_factors, window_factors
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene

    scene = get_scene("shadow_detail", "test")
    frame = scene.default_frame()
    gb = make_gbuffer(scene, frame, 1)
    base = ZHShadow(n_dirs=128, fit_iters=5, clamp=False)
    with pc.torch_threads(1):
        base.precompute(scene)
    sig = window_factors("lanczos", 4, 5.0)
    for sh in ("sample", "vertex"):
        for sp in ("published", "cosine"):
            win = base.with_render_config(shading=sh, specular=sp, window="lanczos", window_width=5.0)
            assert win.config["window"] == "lanczos" and win.model is base.model
            img_win = win.render(frame, gb)
            plain = base.with_render_config(shading=sh, specular=sp)
            raw = plain.render(frame, gb)
            if sp == "published":  # the fast path caches its lighting: bake the windowed one in
                key, light = plain._light
                plain._light = (key, convolve_factors(light, sig.float()))      # windowed lighting baked in
                plain._tables = None  # the coefficient tables were built from the unwindowed lighting
                baked = plain.render(frame, gb)
                assert (img_win - baked).abs().max() <= 1e-5 * baked.abs().max(), (sh, sp)
            else:  # the cos θ_i variant projects the lighting per frame (reference path): the window shows
                assert (img_win - raw).abs().max() > 1e-3 * raw.abs().max(), (sh, sp)
            clamped = base.with_render_config(shading=sh, specular=sp, clamp=True).render(frame, gb)
            assert raw.min() < 0 and clamped.min() >= 0, (sh, sp)             # this view has negatives
            if sh == "sample":   # per shaded sample then S = 1 resolve: exactly max(0, ·) per pixel
                assert torch.equal(clamped, raw.clamp_min(0)), sp
    with pytest.raises(ValueError, match="render"):
        base.with_render_config(n_dirs=64)                                  # a precompute key
    d = ZHShadow().config
    assert (d["window"], d["window_width"], d["clamp"], d["train_rest"]) == ("none", None, True, pc.REST_FRACTION)


def test_registered_and_guards():
    assert get_method("zh_shadow") is ZHShadow
    m = ZHShadow()
    assert m.capabilities.dynamic_geometry and m.capabilities.dynamic_brdf
    assert m.capabilities.max_bounces == 0 and m.capabilities.brdfs == {"lambert", "phong"}
    with pytest.raises(RuntimeError):
        m.render(None, None)


# -- rendered held-out pose vs the oracle -----------------------------------------------------------
# Test creature, held-out frame 1 of make_sequence(scene, "P", 3, seed=5) (training poses: the
# animation at seed 1234 — other phases of the cycle), 64 × 64, 1 sample per pixel; model: 24 training
# poses, 512 rays, 30 refinement steps, 2 lobes, order 4. Oracle: 48 + 48 MIS samples, two seeds,
# averaged; the noise floor of the average is RMSE(seed 0, seed 1) / 2 / √2 (measured 0.046).
CFG = dict(train_poses=24, n_dirs=512, fit_iters=30)
# Measured RMSE vs oracle (linear radiance, covered pixels; mean radiance ≈ 0.8): see PIN_*.
# The error is dominated by order-4 SH truncation of the sun-and-sky lighting, not by the model:
# rendering with lobes fitted to this very pose's ray-cast visibility gives (nearly) the same error.
# Measured: 0.1263 (cosine variant 0.1263, per-vertex shading 0.1293, lobes fitted at the pose
# itself 0.1256, no shadows 0.1558). The reference's own per-pixel noise σ ≈ 0.065 (= √2 × floor)
# is inside this RMSE: the method's error alone is ≈ √(0.126² − 0.065²) ≈ 0.108.
PIN_RMSE = 0.126
# Relative: covers platform differences in the (deterministic) fits and the oracle's sampling;
# 15 % of 0.126 is 0.019, below the 0.03 gap to the unshadowed rendering.
PIN_TOL = 0.15
MODEL_VS_EXACT = 1.10  # the linear model may cost ≤ 10 % over lobes fitted at the pose itself


@pytest.fixture(scope="module")
def rendered():
    from methods.oracle import Oracle
    from references.gbuffer import make_gbuffer
    from references.metrics import rmse
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    scene = get_scene("creature", "test")
    frame = make_sequence(scene, "P", 3, seed=5)[1]
    gb = make_gbuffer(scene, frame, 1)
    mask = gb.coverage.numpy()
    refs = []
    for seed in (0, 1):
        o = Oracle(light_samples=48, brdf_samples=48, seed=seed)
        o.precompute(scene)
        refs.append(o.render(frame, gb).numpy())
    m = ZHShadow(**CFG)
    m.precompute(scene)
    ref = 0.5 * (refs[0] + refs[1])       # the two seeds averaged: noise floor / √2 of one
    out = {"noise": rmse(refs[0], refs[1], mask) / 2 / math.sqrt(2), "stats": m.stats}
    for sh in ("sample", "vertex"):
        for sp in ("published", "cosine"):
            out[(sh, sp)] = rmse(m.with_render_config(shading=sh, specular=sp).render(frame, gb).numpy(), ref, mask)
    out["memory"] = m.memory()
    m.render(frame, gb)
    model = m.model
    v, _ = pc.pose_visibility(scene, frame.pose[None], 4, n_dirs=CFG["n_dirs"])
    with pc.torch_threads(1):
        m.model, _ = pc.build_model(v, frame.pose[None], model.lobes, iters=CFG["fit_iters"])
    m._posed = m._tables = None  # another model: drop the frame caches built from the old one
    out["exact_pose"] = rmse(m.render(frame, gb).numpy(), ref, mask)
    m.model = pc.ZHModel(torch.zeros_like(model.X), 4, model.lobes)
    m.model.X[-1, :, 2] = math.sqrt(4 * math.pi)                        # V ≡ 1: no shadows
    m._posed = m._tables = None
    out["unshadowed"] = rmse(m.render(frame, gb).numpy(), ref, mask)
    m.model = model
    m._posed = m._tables = None
    bad = dataclasses.replace(frame, materials={**frame.materials, "creature": _cook()})
    with pytest.raises(ValueError, match="BRDF"):
        m.render(bad, gb)
    return out


def _cook():
    from scenes.materials import CookTorrance

    return CookTorrance(kd=(0.5, 0.5, 0.5), ks=(0.2, 0.2, 0.2), m=0.3, F0=0.04)


def test_rendered_error_vs_oracle(rendered):
    r = rendered
    msg = {k: (round(v, 4) if isinstance(v, float) else v) for k, v in r.items()}
    e = r[("sample", "published")]
    assert abs(e - PIN_RMSE) <= PIN_TOL * PIN_RMSE, msg
    assert e > r["noise"], msg                                   # cannot beat the reference's noise
    assert e < r["unshadowed"], msg                              # the predicted shadows help
    assert e <= MODEL_VS_EXACT * r["exact_pose"], msg            # the linear model costs little
    assert abs(r[("vertex", "published")] - e) <= 0.2 * e, msg   # per-vertex shading: similar
    assert abs(r[("sample", "cosine")] - e) <= 0.1 * e, msg      # cos θ_i matters little at s = 12
    assert r["memory"]["linear_model_X"] == 11 * 1385 * 12 * 4   # (J+1) × N × 6c float32
    # the roofline's cost model (frame_cost) is checked against a hand count in test_fast.py


def test_static_scene_uses_the_bias_row_alone():
    """A scene without a skeleton: one "pose", X is the bias row; shadows still render (the
    sphere darkens the plane below it) and the model reproduces the lobe fit exactly."""
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene

    scene = get_scene("sphere_plane", "test")
    m = ZHShadow(n_dirs=128, fit_iters=5)
    with pc.torch_threads(1):
        m.precompute(scene)
    assert m.model.X.shape[0] == 1
    assert m.stats["train_model_err_mean"] == pytest.approx(m.stats["lobe_fit_err_mean"], abs=1e-5)
    frame = scene.default_frame()
    img = m.render(frame, make_gbuffer(scene, frame, 1))
    assert img.shape == (64, 64, 3) and torch.isfinite(img).all() and img.mean() > 0
