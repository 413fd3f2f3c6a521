"""Tests for scenes/{mesh,camera,skeleton,scene,hashing,library,sequences}.py."""
import math

import numpy as np
import pytest
import torch

from scenes.camera import Camera
from scenes.mesh import Mesh, compute_vertex_normals, load_mesh
from scenes import procedural as P

RAY_TOL = 2e-6  # float32 rounding of unit directions (a few ulp)
LBS_TOL = 1e-5  # float32 rigid transforms of O(1) coordinates


def _tri():
    return Mesh(torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), torch.tensor([[0, 1, 2]]))


def test_validate_errors():
    m = _tri()
    V = m.V.clone(); V[1, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        Mesh(V, m.F).validate()
    with pytest.raises(ValueError, match="repeated"):
        Mesh(m.V, torch.tensor([[0, 1, 1]])).validate()
    with pytest.raises(ValueError, match="outside"):
        Mesh(m.V, torch.tensor([[0, 1, 3]])).validate()
    with pytest.raises(ValueError, match="outside"):
        Mesh(m.V, torch.tensor([[0, -1, 2]])).validate()
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [2, 0, 0]])
    with pytest.raises(ValueError, match="zero-area"):
        Mesh(V, m.F).validate()
    with pytest.raises(ValueError, match="zero-length"):
        Mesh(m.V, m.F, torch.zeros(3, 3)).validate()


def test_normals_computed_and_normalised():
    m = _tri().validate()
    assert torch.allclose(m.N, torch.tensor([0.0, 0, 1]).expand(3, 3))
    m2 = Mesh(_tri().V, _tri().F, torch.tensor([[0.0, 0, 2]] * 3)).validate()
    assert torch.allclose(m2.N.norm(dim=1), torch.ones(3))
    s = P.icosphere(3)
    n = compute_vertex_normals(s.V, s.F)
    assert (n * s.V).sum(1).min() > 0.999  # area-weighted normals of a sphere ≈ radial


def test_load_mesh_and_corrupt(tmp_path):
    p = tmp_path / "t.obj"
    p.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    m = load_mesh(p)
    assert m.num_faces == 1 and torch.allclose(m.N[:, 2], torch.ones(3))
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n\x00")
    with pytest.raises(ValueError, match="bad.ply"):
        load_mesh(bad)
    with pytest.raises(ValueError, match="not found"):
        load_mesh(tmp_path / "missing.obj")


@pytest.mark.parametrize("mesh", [P.icosphere(2), P.chess_piece("rook"), P.chess_piece("pawn"), P.torus_knot(n_u=64, n_v=8)])
def test_closed_meshes_outward(mesh):
    fn, area = mesh.face_normals()
    c = mesh.V[mesh.F].mean(1)
    vol = (c * fn * area[:, None]).sum() / 3  # divergence theorem
    assert vol > 0
    assert ((mesh.N[mesh.F].mean(1) * fn).sum(1) > 0).all()


def test_camera_matches_mitsuba():
    from references.mitsuba_setup import ensure_variant
    ensure_variant()
    import mitsuba as mi
    cam = Camera((1, 2, 5), (0, 0.5, 0), (0, 1, 0), 40, 48, 32)
    from references.export import camera_to_mitsuba

    sensor = mi.load_dict(camera_to_mitsuba(cam))
    px = torch.rand(200, 2, generator=torch.Generator().manual_seed(0)) * torch.tensor([48.0, 32.0])
    fs = px.double().numpy() / np.array([48, 32])
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(fs[:, 0], fs[:, 1]), mi.Point2f(0.5, 0.5))
    o, d = cam.rays(px)
    assert np.abs(np.array(ray.o).reshape(3, -1).T - o.numpy()).max() < RAY_TOL * 10
    assert np.abs(np.array(ray.d).reshape(3, -1).T - d.numpy()).max() < RAY_TOL


def test_lbs_rest_and_rigid():
    from scenes.skeleton import make_creature, skin
    mesh, sk, W = make_creature("test")
    T0 = sk.forward_kinematics(torch.zeros(sk.num_joints))
    assert torch.allclose(T0, torch.eye(4).expand_as(T0))
    pose = torch.zeros(sk.num_joints); pose[3] = 0.8  # knee_fl
    T = sk.forward_kinematics(pose)
    V, N = skin(mesh.V, mesh.N, W, T)
    assert torch.allclose(N.norm(dim=1), torch.ones(len(N)), atol=1e-5)
    rigid = W[:, 3] > 0.999  # vertices entirely on the lower front-left leg
    assert rigid.sum() > 10
    pd = lambda X: (X[:, None] - X[None]).norm(dim=-1)  # exact pairwise (cdist's mm trick loses ~1e-4)
    d0, d1 = pd(mesh.V[rigid].double()), pd(V[rigid].double())
    assert (d0 - d1).abs().max() < LBS_TOL * 10
    assert (V[rigid] - mesh.V[rigid]).norm(dim=1).max() > 0.1
    static = W[:, 0] > 0.999
    assert torch.allclose(V[static], mesh.V[static])
    with pytest.raises(ValueError):
        sk.forward_kinematics(torch.zeros(3))
    with pytest.raises(ValueError):
        sk.forward_kinematics(torch.full((sk.num_joints,), float("nan")))


def test_geometry_offsets_and_hash():
    from scenes.library import SCENES, _BUILDERS, get_scene
    s = get_scene("chess")
    g = s.geometry()
    assert g.face_offset[-1] == g.num_faces and g.vertex_offset[-1] == g.num_vertices
    for i, sh in enumerate(s.shapes):
        f0, f1 = int(g.face_offset[i]), int(g.face_offset[i + 1])
        v0, v1 = int(g.vertex_offset[i]), int(g.vertex_offset[i + 1])
        assert f1 - f0 == sh.mesh.num_faces and ((g.F[f0:f1] >= v0) & (g.F[f0:f1] < v1)).all()
        assert (g.vertex_region[v0:v1] == s.regions.index(sh.region)).all()
    a, b = _BUILDERS["sphere_plane"]("test"), _BUILDERS["sphere_plane"]("test")
    assert a.content_hash() == b.content_hash()
    from scenes.materials import Phong
    c = a.replace(materials={**a.materials, "sphere": Phong(kd=0.3, ks=0.4, s=41.0)})
    assert c.content_hash() != a.content_hash()
    with pytest.raises(KeyError, match="sphere_plane"):
        get_scene("nope")


@pytest.mark.parametrize("name", ["sphere_plane", "chess", "alcove", "shadow_detail", "creature"])
def test_scene_sizes(name):
    from scenes.library import get_scene
    s = get_scene(name, "test")
    assert s.geometry().num_vertices <= 2000 and (s.camera.width, s.camera.height) == (64, 64)


def test_sequences_changed():
    from scenes.library import get_scene
    from scenes.sequences import make_sequence
    s = get_scene("creature")
    expect = {"V": {"view"}, "VB": {"view", "brdf"}, "VBL": {"view", "brdf", "light"}, "P": {"pose"}}
    for k, ch in expect.items():
        fr = make_sequence(s, k, 3, seed=1)
        assert fr[0].changed == frozenset({"view", "brdf", "light", "pose"})
        assert all(f.changed == ch for f in fr[1:])
        assert [f.key() for f in fr] == [f.key() for f in make_sequence(s, k, 3, seed=1)]
        for f in fr[1:]:
            assert all(f.materials[r].kind == s.materials[r].kind for r in s.regions)
    with pytest.raises(ValueError):
        make_sequence(get_scene("sphere_plane"), "P")


def test_gbuffer_resolve_channels_first():
    """`GBuffer.resolve(channels_first=True)` on (3, P) radiance = the (P, 3) box filter (misses
    count as 0, whatever the radiance there), with and without misses; bad shapes rejected."""
    from scenes.frame import GBuffer

    H, W, S = 3, 5, 2
    P = H * W * S * S
    g = torch.Generator().manual_seed(0)
    rad = torch.randn(P, 3, generator=g)
    for hit in (torch.ones(P, dtype=torch.bool), torch.rand(P, generator=g) > 0.3):
        z = torch.zeros(P)
        gb = GBuffer(H, W, S, hit, z.long(), torch.zeros(P, 2), torch.zeros(P, 3), torch.zeros(P, 3),
                     torch.zeros(P, 3), z.long(), torch.ones(H, W, dtype=torch.bool))
        want = gb.resolve(rad)
        got = gb.resolve(rad.T.contiguous(), channels_first=True)
        assert got.shape == (H, W, 3)
        assert (got - want).abs().max() <= 1e-6
        with pytest.raises(ValueError, match="channel-major"):
            gb.resolve(rad, channels_first=True)


def test_vertex_weights_equal_the_gathered_form():
    """`GBuffer.vertex_weights` (`index_select` and in-place weights, session 20) = the plain form
    ``F[face]``, ``where(hit, stack([1 − u − v, u, v]), 0)`` bit for bit, misses (face −1, any bary)
    included; on a real bench-like G-buffer layout (P, 2) bary, random faces."""
    from scenes.frame import GBuffer

    g = torch.Generator().manual_seed(3)
    H, W, S = 6, 5, 2
    P = H * W * S * S
    F = torch.randint(0, 40, (30, 3), generator=g)
    for frac in (0.0, 0.4, 1.0):
        hit = torch.rand(P, generator=g) >= frac
        face = torch.where(hit, torch.randint(0, 30, (P,), generator=g), torch.full((P,), -1))
        bary = torch.rand(P, 2, generator=g) * 0.5
        bary[~hit] = float("nan") if frac == 0.4 else 0.0
        gb = GBuffer(H, W, S, hit, face, bary, torch.zeros(P, 3), torch.zeros(P, 3), torch.zeros(P, 3),
                     torch.zeros(P, dtype=torch.long), torch.ones(H, W, dtype=torch.bool))
        idx, w = gb.vertex_weights(F)
        u, v = bary.unbind(-1)
        want_w = torch.where(hit[:, None], torch.stack([1.0 - u - v, u, v], -1), torch.zeros(P, 3))
        assert torch.equal(idx, F[face.clamp_min(0)])
        assert torch.equal(w, want_w)
