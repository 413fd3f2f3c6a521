"""Sequence kinds L, E, VL (lighting-only and view + lighting) and P driven by a scene's own clip."""
from __future__ import annotations

import math

import pytest
import torch

from scenes.library import get_scene
from scenes.sequences import LIGHT_ROT_DEG, PROBES, make_sequence, rotation_axis_angle


@pytest.fixture(scope="module")
def scene():
    return get_scene("sphere_plane", "test")


def _relative_rotation(f0, f1) -> torch.Tensor:
    return f1.envmap.to_world.double() @ f0.envmap.to_world.double().T


def test_L_rotates_about_one_tilted_axis_by_at_least_90_degrees(scene):
    for seed in range(4):
        fr = make_sequence(scene, "L", n_frames=5, seed=seed)
        assert all(f.camera == fr[0].camera and f.materials == fr[0].materials for f in fr)
        assert [f.changed for f in fr[1:]] == [frozenset({"light"})] * 4
        R = _relative_rotation(fr[0], fr[-1])
        angle = math.degrees(math.acos(max(-1.0, min(1.0, (float(torch.trace(R)) - 1) / 2))))
        assert angle >= 90 and abs(angle - LIGHT_ROT_DEG) < 1e-3
        w, v = torch.linalg.eig(R)  # the axis: eigenvector of eigenvalue 1
        axis = v[:, (w - 1).abs().argmin()].real
        axis = axis / axis.norm()
        assert 0.2 < abs(float(axis[1])) < 0.98  # tilted: neither +Y nor horizontal
        for f in fr[1:-1]:  # every frame rotates about the same axis
            Rf = _relative_rotation(fr[0], f)
            assert torch.allclose(Rf @ axis, axis, atol=1e-5)


def test_rotation_axis_angle_is_rodrigues():
    R = rotation_axis_angle((0.0, 1.0, 0.0), math.pi / 2)
    assert torch.allclose(R @ torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 0, -1]), atol=1e-6)
    R = rotation_axis_angle((1.0, 1.0, 0.0), 0.7)
    assert torch.allclose(R @ R.T, torch.eye(3), atol=1e-6) and abs(float(torch.det(R)) - 1) < 1e-6


def test_E_swaps_captured_probes_every_frame(scene):
    fr = make_sequence(scene, "E", n_frames=5, seed=0)
    assert fr[0].envmap is scene.envmap
    datas = [f.envmap.data for f in fr]
    for a, b in zip(datas, datas[1:]):
        assert not torch.equal(a, b)  # every frame a different map
    assert len({f.envmap.data.sum().item() for f in fr[1:]}) >= 3  # >= 3 different probes
    assert all(f.envmap.height == scene.envmap.height for f in fr)
    assert [f.changed for f in fr[1:]] == [frozenset({"light"})] * 4
    assert len(PROBES) >= 3


def test_VL_changes_view_and_lighting_not_materials(scene):
    fr = make_sequence(scene, "VL", n_frames=3, seed=0)
    assert [f.changed for f in fr[1:]] == [frozenset({"view", "light"})] * 2
    assert all(f.materials == scene.materials for f in fr)


def test_P_follows_the_scenes_own_clip():
    sc = get_scene("character", "test")
    assert sc.animation is not None
    fr = make_sequence(sc, "P", n_frames=4, seed=0)
    clip = sc.animation
    for f in fr:  # each pose lies on the clip's piecewise-linear track
        d = (clip - f.pose).abs().max(1).values
        i = int(d.argmin())
        seg = [(clip[i], clip[(i + 1) % len(clip)]), (clip[i - 1], clip[i])]
        ok = False
        for a, b in seg:
            t = float(((f.pose - a) * (b - a)).sum() / (b - a).pow(2).sum().clamp_min(1e-12))
            ok |= 0 <= t <= 1 and torch.allclose(a + t * (b - a), f.pose, atol=1e-4)
        assert ok
    assert make_sequence(sc, "P", n_frames=4, seed=0)[2].pose.equal(fr[2].pose)  # deterministic
