"""scenes/skeleton.py: forward kinematics and linear blend skinning — rest pose identity, rigid
motion of fully-weighted vertices, unit normals, validation; the creature and its animation."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from scenes.skeleton import (BLEND_COMPILE_MIN, CREATURE_JOINTS, Skeleton, axis_angle_matrix, blend_skin,
                             creature_animation, make_creature, skin)

# float32 skinning of coordinates of order 1–2: a few ulp after two or three 4×4 products.
F32_ATOL = 2e-5


@pytest.fixture(scope="module")
def creature():
    return make_creature("test")


def _chain() -> Skeleton:
    """root at origin about +y, child at (1, 0, 0) about +z, grandchild at (2, 0, 0) about (1, 1, 0)."""
    return Skeleton([-1, 0, 1], [[0, 0, 0], [1, 0, 0], [2, 0, 0]], [[0, 1, 0], [0, 0, 1], [1, 1, 0]])


def test_axis_angle_matrix_is_rotation():
    rng = np.random.default_rng(0)
    k = torch.as_tensor(rng.normal(size=(20, 3)))
    k = k / k.norm(dim=1, keepdim=True)
    a = torch.as_tensor(rng.uniform(-3, 3, 20))
    R = axis_angle_matrix(k, a)
    torch.testing.assert_close(R @ R.transpose(1, 2), torch.eye(3, dtype=R.dtype).expand(20, 3, 3), atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(20, dtype=R.dtype), atol=1e-12, rtol=0)
    torch.testing.assert_close((R @ k[:, :, None])[:, :, 0], k, atol=1e-12, rtol=0)  # axis fixed
    # right-hand rule: +90° about +z maps +x to +y
    Rz = axis_angle_matrix(torch.tensor([0.0, 0.0, 1.0]), torch.tensor(math.pi / 2))
    torch.testing.assert_close(Rz @ torch.tensor([1.0, 0, 0]), torch.tensor([0.0, 1, 0]), atol=1e-7, rtol=0)


def test_fk_rest_pose_is_identity():
    T = _chain().forward_kinematics(torch.zeros(3))
    torch.testing.assert_close(T, torch.eye(4).expand(3, 4, 4), atol=0, rtol=0)


def test_fk_chain_composes_hinges():
    """Child hinge at (1,0,0) rotated 90° about z carries the grandchild pivot (2,0,0) to (1,1,0);
    the root's 90° turn about +y then maps it to (0,1,−1)."""
    sk = _chain()
    T = sk.forward_kinematics(torch.tensor([math.pi / 2, math.pi / 2, 0.3], dtype=torch.float64))
    p = torch.tensor([2.0, 0.0, 0.0, 1.0], dtype=torch.float64)
    torch.testing.assert_close(T[1] @ p, torch.tensor([0.0, 1.0, -1.0, 1.0], dtype=torch.float64), atol=1e-12, rtol=0)
    # the grandchild's own pivot moves like its parent's frame
    torch.testing.assert_close(T[2] @ p, T[1] @ p, atol=1e-12, rtol=0)


def test_rest_pose_leaves_mesh_unchanged(creature):
    mesh, sk, W = creature
    posed = sk.pose_mesh(mesh, W, torch.zeros(sk.num_joints))
    torch.testing.assert_close(posed.V, mesh.V, atol=F32_ATOL, rtol=0)
    torch.testing.assert_close(posed.N, mesh.N, atol=F32_ATOL, rtol=0)
    assert torch.equal(posed.F, mesh.F)


def test_fully_weighted_vertices_move_rigidly(creature):
    mesh, sk, W = creature
    pose = creature_animation(5, phase=0.4)[2]
    T = sk.forward_kinematics(pose)
    posed = sk.pose_mesh(mesh, W, pose)
    checked = 0
    for j in range(sk.num_joints):
        sel = (W[:, j] == 1.0).nonzero()[:, 0]
        if sel.numel() == 0:
            continue
        checked += 1
        R, t = T[j, :3, :3], T[j, :3, 3]
        p_rest = sk.joint_positions[j]
        p_new = R @ p_rest + t
        # distances to the joint preserved
        torch.testing.assert_close((posed.V[sel] - p_new).norm(dim=1), (mesh.V[sel] - p_rest).norm(dim=1),
                                   atol=F32_ATOL, rtol=0)
        # positions and normals moved by the joint's rigid transform
        torch.testing.assert_close(posed.V[sel], mesh.V[sel] @ R.T + t, atol=F32_ATOL, rtol=0)
        torch.testing.assert_close(posed.N[sel], mesh.N[sel] @ R.T, atol=F32_ATOL, rtol=0)
    # root, neck (head) and at least the lower legs have fully-weighted vertices
    assert checked >= 6
    assert not torch.allclose(posed.V, mesh.V, atol=1e-2)


def test_skinned_normals_unit_and_blend_between_joints():
    """A vertex weighted ½/½ between two joints moves to the average of their images."""
    sk = _chain()
    V = torch.tensor([[1.5, 0.2, 0.1], [0.5, 0.0, 0.3]], dtype=torch.float64)
    N = torch.tensor([[0.0, 1.0, 0.0], [0.6, 0.0, 0.8]], dtype=torch.float64)
    W = torch.tensor([[0.0, 0.5, 0.5], [0.3, 0.7, 0.0]], dtype=torch.float64)
    T = sk.forward_kinematics(torch.tensor([0.4, -1.1, 0.8], dtype=torch.float64))
    Vp, Np = skin(V, N, W, T)
    h = torch.cat([V, torch.ones(2, 1, dtype=V.dtype)], 1)
    expect = sum(W[:, j:j + 1] * (h @ T[j].T)[:, :3] for j in range(3))
    torch.testing.assert_close(Vp, expect, atol=1e-12, rtol=0)
    torch.testing.assert_close(Np.norm(dim=1), torch.ones(2, dtype=Np.dtype), atol=1e-12, rtol=0)
    # n' ∝ (Σ w R)^{-T} n
    for i in range(2):
        A = sum(W[i, j] * T[j, :3, :3] for j in range(3))
        n = torch.linalg.inv(A).T @ N[i]
        torch.testing.assert_close(Np[i], n / n.norm(), atol=1e-12, rtol=0)


def test_posed_creature_normals_unit(creature):
    mesh, sk, W = creature
    for pose in creature_animation(3):
        posed = sk.pose_mesh(mesh, W, pose)
        torch.testing.assert_close(posed.N.norm(dim=1), torch.ones(mesh.num_vertices), atol=F32_ATOL, rtol=0)
        assert torch.isfinite(posed.V).all()


@pytest.mark.parametrize("pose", [torch.zeros(3), torch.zeros(10, 1), torch.zeros(1, 10),
                                  torch.full((10,), float("nan")), torch.tensor([float("inf")] + [0.0] * 9),
                                  torch.tensor([4.0] + [0.0] * 9)])
def test_bad_pose_raises(creature, pose):
    mesh, sk, W = creature
    with pytest.raises(ValueError):
        sk.pose_mesh(mesh, W, pose)


def test_bad_weights_raise(creature):
    mesh, sk, W = creature
    pose = torch.zeros(sk.num_joints)
    with pytest.raises(ValueError, match="sum to 1"):
        sk.pose_mesh(mesh, W * 0.5, pose)
    with pytest.raises(ValueError):
        sk.pose_mesh(mesh, W[:, :-1], pose)
    Wn = W.clone()
    Wn[0, 0] = float("nan")
    with pytest.raises(ValueError):
        sk.pose_mesh(mesh, Wn, pose)


@pytest.mark.parametrize("size", ["test", "bench"])
def test_blend_skin_equals_skin(size):
    """The fast path (`blend_skin`: unchecked, componentwise; compiled on the bench mesh, eager on the
    test one) equals the reference `skin`, and `Scene.geometry` takes it (same posed arrays)."""
    from scenes.library import get_scene

    mesh, sk, W = make_creature(size)
    assert (mesh.num_vertices >= BLEND_COMPILE_MIN) == (size == "bench")
    for pose in creature_animation(3):
        T = sk.forward_kinematics(pose)
        V0, N0 = skin(mesh.V, mesh.N, W, T)
        V1, N1 = blend_skin(mesh.V, mesh.N, W, T)
        assert V1.dtype == V0.dtype and V1.shape == V0.shape and N1.shape == N0.shape
        assert torch.allclose(V1, V0, atol=F32_ATOL, rtol=0) and torch.allclose(N1, N0, atol=F32_ATOL, rtol=0)
    scene = get_scene("creature", size)
    pose = creature_animation(3)[1]
    g, r = scene.geometry(pose), scene.rest_geometry()
    T = scene.skeleton.forward_kinematics(pose)
    for i, name in enumerate(g.shape_names):
        a, b = int(g.vertex_offset[i]), int(g.vertex_offset[i + 1])
        if name in scene.skin_weights:
            V0, N0 = skin(r.V[a:b], r.N[a:b], scene.skin_weights[name], T)
        else:
            V0, N0 = r.V[a:b], r.N[a:b]
        assert torch.allclose(g.V[a:b], V0, atol=F32_ATOL, rtol=0)
        assert torch.allclose(g.N[a:b], N0, atol=F32_ATOL, rtol=0)


def test_bad_skeleton_raises():
    with pytest.raises(ValueError):
        Skeleton([-1, 2, 0], np.zeros((3, 3)), np.ones((3, 3)))   # parent after child
    with pytest.raises(ValueError):
        Skeleton([-1, 0], np.zeros((2, 3)), [[0, 1, 0], [0, 0, 0]])  # zero axis
    with pytest.raises(ValueError):
        Skeleton([-1, 0], np.zeros((3, 3)), np.ones((2, 3)))


def test_creature_and_animation_consistent(creature):
    mesh, sk, W = creature
    assert sk.num_joints == len(CREATURE_JOINTS)
    assert W.shape == (mesh.num_vertices, sk.num_joints)
    torch.testing.assert_close(W.sum(1), torch.ones(mesh.num_vertices), atol=1e-6, rtol=0)
    A = creature_animation(12, phase=0.3)
    assert A.shape == (12, sk.num_joints)
    lo, hi = sk.limits[:, 0], sk.limits[:, 1]
    assert ((A >= lo - 1e-6) & (A <= hi + 1e-6)).all(), "animation must stay within the joint limits"
    assert A[0].abs().max() > 0.1  # frame 0 is not the rest pose
    with pytest.raises(ValueError):
        creature_animation(0)


# Feet within this of y = 0 count as standing on the ground (the capsule pole vertex is exact up
# to float32 rounding; 1 mm is far below any visible gap in a contact shadow).
GROUND_ATOL = 1e-3


def test_creature_stands_on_ground(creature):
    mesh, _, _ = creature
    assert float(mesh.V[:, 1].min()) == pytest.approx(0.0, abs=GROUND_ATOL)


def test_animated_creature_never_sinks_below_ground(creature):
    """Hinge swings only raise the feet; LBS blending must not push skin through y = 0."""
    mesh, sk, W = creature
    lowest = min(float(sk.pose_mesh(mesh, W, p).V[:, 1].min()) for p in creature_animation(16))
    assert lowest >= -GROUND_ATOL
