"""scenes/sequences.py: V / VB / VBL / P / L / E / VL sequences — `changed` flags match what actually differs,
fixed parts stay fixed, determinism in the seed, invalid requests."""
from __future__ import annotations

import pytest
import torch

from scenes.hashing import hash_envmap, hash_frame, hash_materials
from scenes.library import get_scene
from scenes.sequences import ALL_CHANGED, KINDS, make_sequence

N_FRAMES = 4
EXPECTED = {"V": {"view"}, "VB": {"view", "brdf"}, "VBL": {"view", "brdf", "light"}, "P": {"pose"},
            "L": {"light"}, "E": {"light"}, "VL": {"view", "light"}}


def _differs(a, b) -> set[str]:
    """What differs between two frames, computed independently of sequences.py (by content hashes)."""
    d = set()
    if a.camera.params() != b.camera.params():
        d.add("view")
    if hash_materials(a.materials) != hash_materials(b.materials):
        d.add("brdf")
    if hash_envmap(a.envmap) != hash_envmap(b.envmap):
        d.add("light")
    pa, pb = a.pose, b.pose
    if (pa is None) != (pb is None) or (pa is not None and not torch.equal(pa, pb)):
        d.add("pose")
    return d


def _scene(kind):
    return get_scene("creature" if kind == "P" else "sphere_plane", "test")


@pytest.mark.parametrize("kind", KINDS)
def test_changed_flags_match_content(kind):
    sc = _scene(kind)
    fr = make_sequence(sc, kind, N_FRAMES, seed=3)
    assert len(fr) == N_FRAMES
    assert [f.index for f in fr] == list(range(N_FRAMES))
    assert fr[0].changed == ALL_CHANGED
    for i in range(1, N_FRAMES):
        assert set(fr[i].changed) == EXPECTED[kind], (i, fr[i].changed)
        assert _differs(fr[i - 1], fr[i]) == EXPECTED[kind], i


@pytest.mark.parametrize("kind", KINDS)
def test_fixed_parts_stay_fixed(kind):
    sc = _scene(kind)
    fr = make_sequence(sc, kind, N_FRAMES, seed=5)
    for f in fr:
        assert set(f.materials) == set(sc.regions)
        for r, m in f.materials.items():  # BRDF family never changes
            assert type(m) is type(sc.materials[r])
        if "brdf" not in EXPECTED[kind]:
            assert hash_materials(f.materials) == hash_materials(sc.materials)
        if "light" not in EXPECTED[kind]:
            assert hash_envmap(f.envmap) == hash_envmap(sc.envmap)
        elif kind != "E":  # E swaps maps; every other lighting change is a rotation of the scene's map
            assert torch.equal(f.envmap.data, sc.envmap.data)  # only rotated
        if "view" not in EXPECTED[kind]:
            assert f.camera == sc.camera
        else:
            assert f.camera.target == sc.camera.target and f.camera.width == sc.camera.width
        if kind == "P":
            assert f.pose is not None and f.pose.shape == (sc.skeleton.num_joints,)
            sc.skeleton.check_pose(f.pose)  # valid pose
        else:
            assert f.pose is None
    assert hash_envmap(fr[0].envmap) == hash_envmap(sc.envmap)  # frame 0 keeps the scene's light


@pytest.mark.parametrize("kind", KINDS)
def test_deterministic_in_seed(kind):
    sc = _scene(kind)
    a = [hash_frame(f) for f in make_sequence(sc, kind, N_FRAMES, seed=11)]
    b = [hash_frame(f) for f in make_sequence(sc, kind, N_FRAMES, seed=11)]
    c = [hash_frame(f) for f in make_sequence(sc, kind, N_FRAMES, seed=12)]
    assert a == b
    assert a != c
    assert len(set(a)) == N_FRAMES  # every frame is distinct content


def test_pose_on_static_scene_raises():
    with pytest.raises(ValueError, match="skeleton"):
        make_sequence(get_scene("chess", "test"), "P", 3)


def test_bad_arguments_raise():
    sc = get_scene("sphere_plane", "test")
    with pytest.raises(ValueError, match="kind"):
        make_sequence(sc, "X", 3)
    with pytest.raises(ValueError):
        make_sequence(sc, "V", 0)


def test_single_frame_sequence():
    fr = make_sequence(get_scene("alcove", "test"), "VBL", 1, seed=0)
    assert len(fr) == 1 and fr[0].changed == ALL_CHANGED


def test_posed_sequence_geometry_moves():
    sc = get_scene("creature", "test")
    fr = make_sequence(sc, "P", N_FRAMES, seed=0)
    g0, g1 = sc.geometry(fr[0].pose), sc.geometry(fr[1].pose)
    assert (g0.V - g1.V).abs().max() > 1e-2


def test_frame_hash_ignores_bookkeeping_and_sees_content():
    from methods.base import Frame

    sc = get_scene("sphere_plane", "test")
    f = sc.default_frame()
    h = hash_frame(f)
    assert hash_frame(Frame(f.envmap, f.camera, dict(f.materials), None, index=7, changed=frozenset())) == h
    assert hash_frame(Frame(f.envmap, f.camera.orbited(1e-3), f.materials)) != h
    assert hash_frame(Frame(f.envmap, f.camera, f.materials, pose=torch.zeros(2))) != h
