"""ZH lobe fitting, lobe parameterisation, linear model (Nowrouzezahrai 2008 §3), and the fit
errors of Figs. 3 and 5 on the test creature (held-out poses)."""
from __future__ import annotations

import math

import pytest
import torch

from methods.zh_shadow import precompute as pc

EXACT = 1e-9          # float64 algebra
# Lobe recovery after a grid search + fixed-step Adam refinement (relative SH error; Adam with a
# fixed step stalls at ~lr²-sized axis jitter: measured ≤ 5e-4 with lr = 0.02, 100 steps).
FIT_EXACT = 2e-3


def _rand_axes(g, shape):
    a = torch.randn(*shape, 3, generator=g, dtype=torch.float64)
    a = a / a.norm(dim=-1, keepdim=True)
    return torch.where(a[..., 2:3] < 0, -a, a)


def test_chart_round_trip():
    g = torch.Generator().manual_seed(0)
    a = _rand_axes(g, (500,))
    assert (pc.chart_to_axis(pc.axis_to_chart(a)) - a).abs().max() <= EXACT
    assert pc.axis_to_chart(torch.tensor([0.0, 0.0, 1.0])).abs().max() == 0   # the normal ↦ (0, 0)
    far = pc.chart_to_axis(torch.tensor([[10.0, 0.0]], dtype=torch.float64))  # clamped to r = 2: −z
    assert torch.allclose(far, torch.tensor([[0.0, 0.0, -1.0]], dtype=torch.float64), atol=EXACT)


def test_canonical_flip_preserves_the_function():
    g = torch.Generator().manual_seed(1)
    k = torch.randn(50, 2, 4, generator=g, dtype=torch.float64)
    a = torch.randn(50, 2, 3, generator=g, dtype=torch.float64)
    a = a / a.norm(dim=-1, keepdim=True)
    k2, a2 = pc.canonical_lobes(k, a)
    assert (a2[..., 2] >= 0).all()
    assert (pc.lobes_sh(k2, a2) - pc.lobes_sh(k, a)).abs().max() <= EXACT


def test_coefficients_are_least_squares():
    """Closed-form per-band normal equations recover the ZH coefficients of known lobes."""
    g = torch.Generator().manual_seed(2)
    a = _rand_axes(g, (40, 2))
    k = torch.randn(40, 2, 4, generator=g, dtype=torch.float64)
    k[:, 1, 0] = 0.0        # band 0 is shared by the lobes: make the split unique
    k[:, 0, 0] = 1.0
    v = pc.lobes_sh(k, a)
    k_hat = pc.solve_lobe_coeffs(v, a, ridge=1e-10)   # band 0 is singular without a ridge
    assert (pc.lobes_sh(k_hat, a) - v).abs().max() <= 1e-5   # the ridge's bias on band 0
    assert (k_hat[:, :, 1:] - k[:, :, 1:]).abs().max() <= 1e-6


def test_fit_recovers_a_single_lobe():
    g = torch.Generator().manual_seed(3)
    a = _rand_axes(g, (64, 1))
    k = torch.randn(64, 1, 4, generator=g, dtype=torch.float64)
    v = pc.lobes_sh(k, a)
    k1, a1 = pc.fit_zh_lobes(v, 1, iters=100, lr=0.02)
    err = (pc.lobes_sh(k1, a1) - v).norm(dim=1) / v.norm(dim=1)
    assert err.max() <= FIT_EXACT
    k2, a2 = pc.fit_zh_lobes(v, 2, iters=30)
    # two lobes for one-lobe data: the c ≥ 2 ridge (LOBE_RIDGE) biases near-parallel pairs
    # (measured max 4.2 %)
    assert ((pc.lobes_sh(k2, a2) - v).norm(dim=1) / v.norm(dim=1)).max() <= 0.08


def test_linear_model_is_exact_for_linear_data():
    g = torch.Generator().manual_seed(4)
    P = torch.rand(12, 5, generator=g)
    Xt = torch.randn(6, 7, 3, generator=g)
    B = pc.synthesize(Xt, P)
    X = pc.fit_linear_model(P, B)
    assert (X - Xt).abs().max() <= 1e-4
    assert pc.synthesize(X, P[0]).shape == (7, 3)
    with pytest.raises(ValueError):
        pc.fit_linear_model(P[:5], B)


def test_bad_inputs():
    with pytest.raises(ValueError):
        pc.fit_zh_lobes(torch.zeros(3, 15), 1)
    with pytest.raises(ValueError):
        pc.fit_zh_lobes(torch.zeros(3, 16), 0)
    from scenes.library import get_scene

    with pytest.raises(ValueError):
        pc.training_poses(get_scene("creature", "test"), 8, source="mocap")
    with pytest.raises(ValueError):
        pc.training_poses(get_scene("sphere_plane", "test"), 8)


# -- Figs. 3 and 5 on the test creature ----------------------------------------------------------
# Config of the measurement (kept small for the test budget): 24 training poses of the creature's
# training clip (`pc.training_poses`, seed 1234: 6 frames easing in from the rest pose, then 18 of
# the animation), 4 held-out poses of the animation cycle at other phases (seed 7), and the rest
# pose itself (the pose of every V/VB/VBL frame), 256 rays per
# vertex, order 4, 30 refinement steps. Errors: ‖v_pred − v_true‖ / ‖unoccluded‖ (`pc.sh_error`)
# over the creature's vertices × held-out poses, mean ± std.
FIG_POSES, FIG_HELD, FIG_DIRS, FIG_ITERS = 24, 4, 256, 30
# Measured (this machine, torch 2.13): see PINNED; the pins hold to ±REL_PIN relative — the fits use
# a deterministic grid + Adam, so changes beyond that mean the algorithm or the data changed.
# Re-measured after the pose least squares became truncated (`pc.POSE_RCOND`: the animation spans
# only 4 of the 10 joint dimensions, so the untruncated fit extrapolated along round-off directions;
# before: v 0.125 / 0.071, vcos 0.106 / 0.067, blue 0.123 / 0.078).
# Re-measured when the training clip started easing in from the rest pose (issue 15; before → after):
# v 0.1235 / 0.0628 → 0.1240 / 0.0622, vcos 0.0999 / 0.0522 → 0.1008 / 0.0525, blue 0.1216 / 0.0725
# → 0.1223 / 0.0715 (held-out animation poses: within ±1.5 %); lobe fit alone 0.1205 / 0.0572 →
# 0.1203 / 0.0543; the rest pose 0.221 / 0.215 → 0.128 / 0.065 (it was off the training clip).
PINNED = {
    ("v", 1): 0.1240, ("v", 2): 0.0622,          # Fig. 5: 1 vs 2 lobes (unweighted visibility)
    ("vcos", 1): 0.1008, ("vcos", 2): 0.0525,    # Fig. 3 red: linear fit of cosine-weighted data
    ("blue", 1): 0.1223, ("blue", 2): 0.0715,    # Fig. 3 blue: M¹ · (unweighted prediction)
    ("rest", 1): 0.1275, ("rest", 2): 0.0649,    # the rest pose (first frame of the clip's ease-in)
}
# (measured with the creature's feet on the ground (leg length 1.1); std: 0.089 / 0.063,
# 0.084 / 0.063, 0.097 / 0.071, rest 0.091 / 0.070; lobe fit alone 0.120 / 0.054; order-4 truncation
# floor of the blue curve 0.042; all 16 SH coefficients predicted linearly 0.031.) NOT reproduced: the paper's Fig. 3 has blue < red; here red < blue for both c.
REL_PIN = 0.15


@pytest.fixture(scope="module")
def fig_errors():
    from methods.zh_shadow.study import fig3_5_errors

    return fig3_5_errors(poses=FIG_POSES, held=FIG_HELD, n_dirs=FIG_DIRS, iters=FIG_ITERS)


def test_two_lobes_beat_one(fig_errors):
    """Fig. 5: the 2-lobe model's held-out error is below the 1-lobe model's (mean and std)."""
    e1, e2 = fig_errors[("v", 1)], fig_errors[("v", 2)]
    assert e2.mean() < e1.mean()
    assert fig_errors[("fit", 2)].mean() < fig_errors[("fit", 1)].mean()   # lobe fit alone too


def test_fit_errors_pinned(fig_errors):
    msg = {k: (round(float(e.mean()), 4), round(float(e.std()), 4)) for k, e in fig_errors.items()}
    for key, want in PINNED.items():
        got = float(fig_errors[key].mean())
        assert abs(got - want) <= REL_PIN * want, f"{key}: {got:.4f} vs pinned {want} ({msg})"
    # every prediction is worse than the truncation floor, and the ZH model is worse than
    # predicting all 16 SH coefficients linearly (the price of the rotatable lobes)
    assert fig_errors[("blue", 1)].mean() > fig_errors["floor_blue"].mean()
    assert fig_errors[("v", 2)].mean() > fig_errors["direct_sh"].mean()


def test_rest_pose_is_on_the_training_clip(fig_errors):
    """Issue 15: the rest pose's error is at the held-out animation poses' level (it is the first
    frame of the training clip's ease-in; before, off the clip, it was 3.4× the animation's)."""
    for c in (1, 2):
        assert fig_errors[("rest", c)].mean() <= 1.5 * fig_errors[("v", c)].mean()


def test_training_clip_eases_in_from_the_rest_pose():
    from scenes.library import get_scene

    scene = get_scene("creature", "test")
    clip = pc.training_poses(scene, 8, seed=3, rest=0.0)
    P = pc.training_poses(scene, 8, seed=3, rest=0.25)                 # 2 ease-in frames + 6 of the clip
    assert P.shape == (8, scene.skeleton.num_joints)
    assert P[0].abs().max() == 0                                       # the rest pose
    assert torch.allclose(P[1], 0.5 * P[2])                            # halfway to the clip's first frame
    assert torch.equal(P[2:], pc.training_poses(scene, 6, seed=3, rest=0.0))
    assert not (clip.abs().sum(1) == 0).any()                          # the walk alone never rests
    for bad in (-0.1, 1.0, True, "0.2"):
        with pytest.raises(ValueError, match="rest"):
            pc.training_poses(scene, 8, rest=bad)
