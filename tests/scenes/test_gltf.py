"""scenes/gltf.py: skinned .glb round trip, hinge mapping vs glTF's own skinning, corrupt files."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from scenes.gltf import (gltf_skinned_positions, load_skinned_glb, load_skinned_glb_rig, save_skinned_glb)
from scenes.skeleton import Skeleton, creature_animation, make_creature

# Positions/weights/matrices are stored as float32 in the file: round trips are exact up to that.
F32 = 1e-6
# Hinge skinning vs glTF quaternion skinning: float32 quaternions, positions of size ~2.
SKIN_TOL = 2e-6


@pytest.fixture(scope="module")
def creature_glb(tmp_path_factory):
    mesh, sk, W = make_creature("test")
    A = creature_animation(6)
    p = save_skinned_glb(tmp_path_factory.mktemp("glb") / "creature.glb", mesh, sk, W, A)
    return p, mesh, sk, W, A


def test_round_trip(creature_glb):
    p, mesh, sk, W, A = creature_glb
    m2, sk2, W2, A2 = load_skinned_glb(p)
    assert torch.equal(m2.F, mesh.F)
    assert (m2.V - mesh.V).abs().max() <= F32
    assert (m2.N - mesh.N).abs().max() <= F32
    assert (W2 - W).abs().max() <= F32                      # ≤ 3 influences per vertex: all kept
    assert torch.equal(sk2.parents, sk.parents)
    assert (sk2.joint_positions - sk.joint_positions).abs().max() <= F32
    assert (sk2.axes - sk.axes).abs().max() <= F32
    assert A2.shape == A.shape and (A2 - A).abs().max() <= 10 * F32
    _, rig = load_skinned_glb_rig(p)
    assert rig.names == sk.names
    ibm = torch.eye(4).repeat(sk.num_joints, 1, 1)
    ibm[:, :3, 3] = -sk.joint_positions
    assert (rig.inverse_bind - ibm).abs().max() <= F32
    assert rig.dropped_rotation.max() <= F32                 # pure hinges: nothing dropped
    assert torch.allclose(rig.times, torch.arange(6) / 30.0)


def test_hinge_skinning_equals_gltf_skinning(creature_glb):
    p, *_ = creature_glb
    m2, sk2, W2, A2 = load_skinned_glb(p)
    for k in range(A2.shape[0]):
        ours = sk2.pose_mesh(m2, W2, A2[k]).V.double().numpy()
        ref = gltf_skinned_positions(p, k)
        assert np.abs(ours - ref).max() <= SKIN_TOL


def test_off_axis_rotation_is_projected_and_reported(tmp_path):
    """A joint animated about a varying axis: hinge = dominant axis, the rest is reported."""
    from scenes.gltf import axis_angle_quat
    import pygltflib

    mesh, sk, W = make_creature("test")
    A = creature_animation(4)
    p = save_skinned_glb(tmp_path / "c.glb", mesh, sk, W, A)
    g = pygltflib.GLTF2().load_binary(str(p))
    blob = bytearray(g.binary_blob())
    # tilt joint 3's (knee_fl, axis +z) keys by a small x rotation in frame 2
    ch = g.animations[0].channels[3]
    acc = g.accessors[g.animations[0].samplers[ch.sampler].output]
    view = g.bufferViews[acc.bufferView]
    q = np.frombuffer(bytes(blob[view.byteOffset:view.byteOffset + view.byteLength]), np.float32).reshape(-1, 4).copy()
    extra = 0.2
    ax = np.array([math.sin(extra), 0.0, math.cos(extra)])
    q[2] = axis_angle_quat(ax, float(A[2, 3])).astype(np.float32)
    blob[view.byteOffset:view.byteOffset + view.byteLength] = q.tobytes()
    g.set_binary_blob(bytes(blob))
    g.save_binary(str(tmp_path / "tilted.glb"))
    _, rig = load_skinned_glb_rig(tmp_path / "tilted.glb")
    assert rig.dropped_rotation[3] > 0.05                    # |θ| sin(0.2) ≈ 0.23 rad off-axis
    assert rig.dropped_rotation[[0, 1, 2, 4, 5]].max() <= F32


def test_corrupt_files(tmp_path, creature_glb):
    p, *_ = creature_glb
    data = p.read_bytes()
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"NOPE" + data[4:])
    with pytest.raises(ValueError, match="magic"):
        load_skinned_glb(bad)
    bad.write_bytes(data[: len(data) // 2])
    with pytest.raises(ValueError, match="truncated|corrupt"):
        load_skinned_glb(bad)
    bad.write_bytes(data[:20] + b"\xff" * (len(data) - 20))
    with pytest.raises(ValueError):
        load_skinned_glb(bad)
    with pytest.raises(ValueError, match="no such"):
        load_skinned_glb(tmp_path / "missing.glb")
    import trimesh

    box = tmp_path / "box.glb"
    trimesh.creation.box().export(box)
    with pytest.raises(ValueError, match="skin"):
        load_skinned_glb(box)


def test_writer_validates(tmp_path):
    mesh, sk, W = make_creature("test")
    with pytest.raises(ValueError):
        save_skinned_glb(tmp_path / "x.glb", mesh, sk, W[:, :3])
    with pytest.raises(ValueError):
        save_skinned_glb(tmp_path / "x.glb", mesh, sk, W, torch.zeros(3, 2))
