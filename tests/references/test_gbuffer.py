"""G-buffer from Mitsuba's primary rays: geometry, ids, coverage, ordering."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from scenes.camera import Camera
from scenes.envmap import EnvMap
from scenes.materials import Lambert
from scenes.mesh import Mesh
from scenes.procedural import icosphere
from scenes.scene import Scene, Shape

from references.gbuffer import film_samples, make_gbuffer

# Mitsuba traces in float32: hit points sit within a few ulps·|p| (|p| ≲ 10) of the exact ray.
RAY_TOL = 2e-5
# Mitsuba's sensor directions vs our float64 Camera.rays, both rounded to float32.
DIR_TOL = 1e-6
# Icosphere (subdivision 3) chord error: the interpolated normal deviates from the exact sphere
# normal by at most ~ half the edge angle (≈ 0.08 rad).
SPHERE_NORMAL_TOL = 0.1


def _env():
    return EnvMap(torch.ones(8, 16, 3))


def _quad(x0, x1, y0, y1, z, n=(0.0, 0.0, 1.0)):
    V = torch.tensor([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], dtype=torch.float32)
    F = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return Mesh(V, F, torch.tensor([n] * 4, dtype=torch.float32)).validate()


def _cam(W=16, H=12, origin=(0.0, 0.0, 4.0), fov=40.0):
    return Camera(origin, (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), fov, W, H)


def _scene(shapes, regions, cam):
    return Scene("t", shapes, regions, cam, _env(), {r: Lambert(0.5) for r in regions})


def test_plane_filling_the_view_is_fully_covered():
    sc = _scene([Shape("wall", "wall", _quad(-10, 10, -10, 10, -1.0))], ["wall"], _cam())
    gb = make_gbuffer(sc, sc.default_frame(), S=2)
    assert (gb.height, gb.width, gb.spp_side) == (12, 16, 2)
    assert gb.hit.shape == (12 * 16 * 4,) and gb.hit.all()
    assert gb.coverage.shape == (12, 16) and gb.coverage.all()
    assert torch.allclose(gb.normal, torch.tensor([0.0, 0.0, 1.0]).expand_as(gb.normal))
    assert (gb.region == 0).all()


def test_positions_are_barycentric_and_on_the_camera_rays():
    sph = icosphere(3, 1.0)
    sc = _scene([Shape("ball", "ball", sph)], ["ball"], _cam(W=20, H=14))
    fr = sc.default_frame()
    S = 3
    gb = make_gbuffer(sc, fr, S=S)
    g = sc.geometry()
    h = gb.hit
    assert 0 < int(h.sum()) < h.numel() and gb.coverage.any() and not gb.coverage.all()
    # Barycentric interpolation of our vertices (independent of GBuffer.interpolate).
    f = gb.face[h]
    u, v = gb.bary[h, 0].double(), gb.bary[h, 1].double()
    p0, p1, p2 = (g.V.double()[g.F[f, k]] for k in range(3))
    p = (1 - u - v)[:, None] * p0 + u[:, None] * p1 + v[:, None] * p2
    assert torch.allclose(gb.position[h].double(), p, atol=1e-6)
    assert (gb.bary[h] >= -1e-6).all() and (gb.bary[h].sum(1) <= 1 + 1e-6).all()
    # The same sub-pixel positions through our Camera model: wo = −d, and p lies on the ray.
    o, d = fr.camera.pixel_rays(S)
    assert torch.allclose(gb.wo, -d, atol=DIR_TOL)
    rel = p - o[h].double()
    t = (rel * d[h].double()).sum(1, keepdim=True)
    assert (t > 0).all()
    assert (rel - t * d[h].double()).norm(dim=1).max() < RAY_TOL
    # Nearest hit: the front of the sphere (facing the camera). The far side would give
    # p̂·wo ≈ −1 almost everywhere; silhouette samples of the tessellated sphere may dip below 0.
    facing = (gb.position[h] / gb.position[h].norm(dim=1, keepdim=True) * gb.wo[h]).sum(1)
    assert facing.min() > -SPHERE_NORMAL_TOL and facing.mean() > 0.5
    # Unit shading normals close to the exact sphere normal.
    assert torch.allclose(gb.normal[h].norm(dim=1), torch.ones(int(h.sum())), atol=1e-6)
    assert (gb.normal[h] - gb.position[h] / gb.position[h].norm(dim=1, keepdim=True)).norm(dim=1).max() < SPHERE_NORMAL_TOL
    # Misses
    assert (gb.face[~h] == -1).all() and (gb.region[~h] == -1).all()
    assert (gb.normal[~h] == 0).all() and (gb.position[~h] == 0).all()
    # Coverage = all S² samples of the pixel hit.
    assert torch.equal(gb.coverage, h.view(14, 20, S * S).all(-1))


def test_shading_normal_interpolates_our_vertex_normals():
    # One big triangle with deliberately different vertex normals: Mitsuba does not see these in
    # the G-buffer; the normals must be OUR normalised barycentric interpolation.
    V = torch.tensor([[-6.0, -6.0, 0.0], [6.0, -6.0, 0.0], [0.0, 6.0, 0.0]])
    N = torch.nn.functional.normalize(torch.tensor([[-0.5, 0.0, 1.0], [0.5, 0.2, 1.0], [0.0, 0.6, 1.0]]), dim=1)
    sc = _scene([Shape("tri", "tri", Mesh(V, torch.tensor([[0, 1, 2]]), N).validate())], ["tri"], _cam(W=8, H=8))
    gb = make_gbuffer(sc, sc.default_frame(), S=2)
    h = gb.hit
    assert h.all()
    u, v = gb.bary[:, 0:1].double(), gb.bary[:, 1:2].double()
    n = (1 - u - v) * N[0].double() + u * N[1].double() + v * N[2].double()
    n = n / n.norm(dim=1, keepdim=True)
    assert torch.allclose(gb.normal.double(), n, atol=1e-6)
    assert torch.allclose(gb.normal, torch.nn.functional.normalize(gb.interpolate(N, sc.geometry().F), dim=1), atol=1e-6)


def test_face_and_region_ids_on_two_shapes():
    # Left half: region "b" (listed second in regions), right half: region "a"; the right quad
    # is the first shape, so global face ids of the left quad are offset by 2.
    right = _quad(0.0, 10, -10, 10, -1.0)
    left = _quad(-10, 0.0, -10, 10, -1.0)
    sc = _scene([Shape("right", "a", right), Shape("left", "b", left)], ["a", "b"], _cam(W=16, H=8))
    gb = make_gbuffer(sc, sc.default_frame(), S=2)
    assert gb.hit.all()
    x = gb.position[:, 0]
    is_left = x < 0
    assert torch.equal(gb.region, torch.where(is_left, 1, 0))
    assert ((gb.face >= 2) == is_left).all() and ((gb.face >= 0) & (gb.face < 4)).all()
    # the image's left half (small pixel x) sees the left quad (x < 0): no mirroring
    cols = torch.arange(16).view(1, 16, 1).expand(8, 16, 4).reshape(-1)
    assert (is_left == (cols < 8)).all()
    # each sample's position is inside its own face
    g = sc.geometry()
    f = gb.face
    p0, p1, p2 = (g.V[g.F[f, k]] for k in range(3))
    lo = torch.minimum(torch.minimum(p0, p1), p2) - 1e-5
    hi = torch.maximum(torch.maximum(p0, p1), p2) + 1e-5
    assert ((gb.position >= lo) & (gb.position <= hi)).all()


def test_sample_order_is_pixel_major():
    pos = film_samples(3, 2, 2)
    assert pos.shape == (3 * 2 * 4, 2)
    # sample s = j·S + i of pixel (x=1, y=1)
    base = (1 * 3 + 1) * 4
    expect = np.array([[(1 + 0.25) / 3, (1 + 0.25) / 2], [(1 + 0.75) / 3, (1 + 0.25) / 2],
                       [(1 + 0.25) / 3, (1 + 0.75) / 2], [(1 + 0.75) / 3, (1 + 0.75) / 2]])
    assert np.allclose(pos[base:base + 4], expect)


def test_posed_geometry_is_used():
    from scenes.library import get_scene

    sc = get_scene("creature", "test")
    import dataclasses

    sc = sc.replace(camera=dataclasses.replace(sc.camera, width=16, height=16))
    J = sc.skeleton.num_joints
    pose = torch.full((J,), 0.4)
    gb_rest = make_gbuffer(sc, sc.default_frame(), S=1)
    gb_pose = make_gbuffer(sc, sc.default_frame(pose=pose), S=1)
    g = sc.geometry(pose)
    h = gb_pose.hit
    # positions interpolate the POSED vertices
    assert torch.allclose(gb_pose.position[h], gb_pose.interpolate(g.V, g.F)[h], atol=1e-6)
    assert not torch.equal(gb_rest.position, gb_pose.position)


def test_bad_S_raises():
    sc = _scene([Shape("wall", "wall", _quad(-10, 10, -10, 10, -1.0))], ["wall"], _cam())
    with pytest.raises(ValueError):
        make_gbuffer(sc, sc.default_frame(), S=0)
