"""scenes/scene.py, scenes/library.py, scenes/hashing.py: merged geometry layout, posed geometry,
content hashes, the named scenes at both sizes."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from scenes import library
from scenes.library import SCENES, get_scene
from scenes.scene import Scene, Shape

# Scene sizes promised by library.py / GitHub issue #2.
TEST_MAX_VERTICES = 2000
TEST_MAX_FILM = 64
BENCH_VERTICES = (5000, 20000)
BENCH_FILM = 256


def _check_layout(scene: Scene, g) -> None:
    S = len(scene.shapes)
    assert g.vertex_offset.shape == (S + 1,) and g.face_offset.shape == (S + 1,)
    assert int(g.vertex_offset[0]) == 0 and int(g.face_offset[0]) == 0
    assert int(g.vertex_offset[-1]) == g.num_vertices and int(g.face_offset[-1]) == g.num_faces
    assert g.shape_names == tuple(s.name for s in scene.shapes)
    assert g.F.min() >= 0 and g.F.max() < g.num_vertices
    assert g.N.shape == g.V.shape and g.vertex_region.shape == (g.num_vertices,)
    assert g.face_region.shape == (g.num_faces,)
    for i, s in enumerate(scene.shapes):
        v0, v1 = int(g.vertex_offset[i]), int(g.vertex_offset[i + 1])
        f0, f1 = int(g.face_offset[i]), int(g.face_offset[i + 1])
        assert v1 - v0 == s.mesh.num_vertices and f1 - f0 == s.mesh.num_faces
        # faces of shape i index only shape i's vertices, in the same local pattern
        assert torch.equal(g.F[f0:f1] - v0, s.mesh.F)
        r = scene.region_index(s.region)
        assert (g.vertex_region[v0:v1] == r).all() and (g.face_region[f0:f1] == r).all()
        m = g.shape_mesh(i)
        assert torch.equal(m.V, s.mesh.V) and torch.equal(m.F, s.mesh.F)
    # a face's region is the region of each of its vertices
    assert torch.equal(g.vertex_region[g.F], g.face_region[:, None].expand(-1, 3))
    torch.testing.assert_close(g.N.norm(dim=1), torch.ones(g.num_vertices), atol=1e-5, rtol=0)


@pytest.mark.parametrize("name", SCENES)
def test_test_size_scene(name):
    sc = get_scene(name, "test")
    g = sc.geometry()
    assert g.num_vertices <= TEST_MAX_VERTICES
    assert sc.camera.width <= TEST_MAX_FILM and sc.camera.height <= TEST_MAX_FILM
    _check_layout(sc, g)
    # every region has a material and at least one shape
    assert set(sc.materials) == set(sc.regions)
    assert {s.region for s in sc.shapes} == set(sc.regions)
    assert sc.size == "test"


@pytest.mark.parametrize("name", SCENES)
def test_bench_size_scene(name):
    """Bench builds take < 0.1 s each (measured), so every scene is checked."""
    sc = get_scene(name, "bench")
    g = sc.geometry()
    assert BENCH_VERTICES[0] <= g.num_vertices <= BENCH_VERTICES[1]
    assert (sc.camera.width, sc.camera.height) == (BENCH_FILM, BENCH_FILM)
    _check_layout(sc, g)


def test_unknown_scene_and_size():
    with pytest.raises(KeyError) as e:
        get_scene("no_such_scene")
    for n in SCENES:
        assert n in str(e.value)
    with pytest.raises(ValueError):
        get_scene("chess", "huge")


def test_content_hash_stable_and_sensitive():
    a = library.sphere_plane("test")  # two independent builds (no memo)
    b = library.sphere_plane("test")
    assert a is not b
    h = a.content_hash()
    assert b.content_hash() == h and a.content_hash() == h
    # a material parameter
    m = a.materials["sphere"]
    p = dict(m.params())
    p["s"] = p["s"] + 1.0
    assert a.replace(materials={**a.materials, "sphere": type(m).from_params(p)}).content_hash() != h
    kd = list(p["kd"])
    p2 = dict(m.params())
    p2["kd"] = [kd[0] + 1e-3] + kd[1:]
    assert a.replace(materials={**a.materials, "sphere": type(m).from_params(p2)}).content_hash() != h
    # the env map: a rotation, or different texels
    R = torch.as_tensor(library.rotation_y(0.3), dtype=torch.float32)
    assert a.replace(envmap=a.envmap.rotated(R)).content_hash() != h
    from scenes.envmap import procedural

    env2 = procedural("sky_sun", height=a.envmap.height, seed=1)
    assert a.replace(envmap=env2.rotated(a.envmap.to_world)).content_hash() != h
    # the camera and the geometry
    assert a.replace(camera=a.camera.orbited(0.1)).content_hash() != h
    sh = a.shapes[0]
    moved = Shape(sh.name, sh.region, sh.mesh.transformed(torch.tensor(
        [[1.0, 0, 0, 0.01], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])))
    assert a.replace(shapes=[moved] + a.shapes[1:]).content_hash() != h
    # and replace() without changes keeps it
    assert a.replace().content_hash() == h


def test_creature_posed_geometry():
    sc = get_scene("creature", "test")
    assert sc.dynamic
    from scenes.skeleton import creature_animation

    rest = sc.geometry()
    assert sc.geometry(torch.zeros(sc.skeleton.num_joints)).V.sub(rest.V).abs().max() < 2e-5
    g = sc.geometry(creature_animation(4)[1])
    assert torch.equal(g.F, rest.F) and torch.equal(g.face_offset, rest.face_offset)
    assert torch.equal(g.vertex_offset, rest.vertex_offset) and torch.equal(g.face_region, rest.face_region)
    i = list(g.shape_names).index("creature")
    a, b = int(g.vertex_offset[i]), int(g.vertex_offset[i + 1])
    assert (g.V[a:b] - rest.V[a:b]).norm(dim=1).max() > 0.1   # the creature moved
    assert torch.equal(g.V[:a], rest.V[:a]) and torch.equal(g.V[b:], rest.V[b:])  # the ground did not
    torch.testing.assert_close(g.N.norm(dim=1), torch.ones(g.num_vertices), atol=1e-5, rtol=0)
    # the rest geometry is not modified by posing
    assert torch.equal(sc.geometry().V, rest.V)


def test_static_scene_rejects_pose():
    sc = get_scene("chess", "test")
    with pytest.raises(ValueError):
        sc.geometry(torch.zeros(3))


def test_scene_validation():
    sc = get_scene("sphere_plane", "test")
    with pytest.raises(ValueError, match="no material"):
        sc.replace(materials={"sphere": sc.materials["sphere"]})
    with pytest.raises(ValueError, match="duplicate"):
        sc.replace(shapes=[sc.shapes[0], sc.shapes[0]])
    with pytest.raises(ValueError):
        sc.replace(shapes=[Shape("x", "nowhere", sc.shapes[0].mesh)])
    with pytest.raises(ValueError):
        sc.replace(skin_weights={"sphere": torch.ones(sc.shapes[0].mesh.num_vertices, 1)})  # no skeleton


def test_key_light_aimed():
    """library rotates each env map so its key light is at the requested azimuth."""
    import math

    sc = get_scene("sphere_plane", "test")
    d = library.key_light_direction(sc.envmap)
    assert math.degrees(math.atan2(d[0], -d[2])) == pytest.approx(-140.0, abs=360 / sc.envmap.width)
