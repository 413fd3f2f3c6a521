"""Skinned glTF 2.0 binary (.glb) files ↔ our hinge-joint rig (`scenes.skeleton`), via pygltflib.

Reading (`load_skinned_glb`): the first skinned mesh node — POSITION, NORMAL (computed if absent),
indices, JOINTS_0/WEIGHTS_0 (≤ 4 influences, rows renormalised), the skin's joints and
inverseBindMatrices, the node hierarchy and ONE animation clip's joint rotations.

Mapping to the hinge skeleton. glTF skinning is v' = Σ_j w_j G_j(t) IBM_j v with G_j the global
node transform. If joint j only rotates, L_j(t) = L_j⁰ Δ_j(t) (Δ_j = R_j⁰⁻¹ R_j(t), in the joint's
local frame), then G_j(t) IBM_j = [G_par(t) G_par⁰⁻¹] · G_j⁰ Δ_j G_j⁰⁻¹ · (G_j⁰ IBM_j): a rotation
about the axis a_j = rot(G_j⁰) · axis(Δ_j) through the rest pivot p_j = G_j⁰[:3, 3], composed with
the parent's motion — exactly `Skeleton.forward_kinematics` with rest-world pivots and axes, on the
rest mesh Σ_j w_j G_j⁰ IBM_j v (= the file's positions when the rest pose is the bind pose).
So a clip whose joints each rotate about one fixed local axis maps EXACTLY. Limitations (stated, not
hidden): a joint rotating about a varying axis is projected on its dominant axis (the principal
direction of its rotation vectors over the clip; the angle is the signed projection, and the
discarded rotation is reported as `GltfRig.dropped_rotation` (radians, max over frames));
translations/scales in the clip, morph targets and animated non-joint nodes are ignored; a
scaled rest transform is rejected. Keyframes are used as they are (no resampling); the clip's
times come back as `GltfRig.times`.

Writing (`save_skinned_glb`): one node per joint (rest translation p_j − p_parent, identity
rotation), IBM_j = Tr(−p_j), a rotation channel per joint with quaternions of (a_j, θ_j(t)); the
4 largest skin weights per vertex (renormalised). Used by the round-trip test.
"""
from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from scenes.mesh import Mesh
from scenes.skeleton import Skeleton

_COMP = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_NCOMP = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
# Rest transforms whose 3×3 part deviates from a rotation by more than this are rejected.
RIGID_TOL = 1e-4


@dataclass
class GltfRig:
    """What `load_skinned_glb` read besides the mesh: the hinge skeleton, weights (N, J), the clip's
    joint angles (F, J) and times (F,), joint node names, the glTF inverse bind matrices (J, 4, 4),
    rest global transforms (J, 4, 4) and the dropped off-axis rotation (J,) radians."""

    skeleton: Skeleton
    weights: torch.Tensor
    animation: torch.Tensor
    times: torch.Tensor
    names: tuple[str, ...]
    inverse_bind: torch.Tensor
    rest_global: torch.Tensor
    dropped_rotation: torch.Tensor


# -- small math ------------------------------------------------------------------------------

def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """glTF quaternions (..., 4) as (x, y, z, w) → rotation matrices (..., 3, 3)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1)], -2)


def axis_angle_quat(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(x, y, z, w) quaternions (..., 4) of rotations by angle (...) about unit axis (..., 3)."""
    h = 0.5 * np.asarray(angle, dtype=np.float64)
    return np.concatenate([np.asarray(axis, dtype=np.float64) * np.sin(h)[..., None], np.cos(h)[..., None]], -1)


def _rotvec(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (..., 3) (axis · angle, angle ∈ [0, π]) of rotation matrices (..., 3, 3)."""
    c = np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0)
    ang = np.arccos(c)
    v = np.stack([R[..., 2, 1] - R[..., 1, 2], R[..., 0, 2] - R[..., 2, 0], R[..., 1, 0] - R[..., 0, 1]], -1)
    s = np.sin(ang)
    out = np.where(s[..., None] > 1e-6, v / (2 * np.where(s > 1e-6, s, 1.0))[..., None] * ang[..., None], 0.5 * v)
    # near π: axis from the symmetric part
    near_pi = ang > math.pi - 1e-3
    if np.any(near_pi):
        Rp = R[near_pi]
        B = (Rp + np.eye(3)) / 2
        ax = np.sqrt(np.clip(np.diagonal(B, axis1=-2, axis2=-1), 0, None))
        i = np.argmax(ax, -1)
        a = B[np.arange(len(i)), i] / np.maximum(ax[np.arange(len(i)), i], 1e-12)[:, None]
        a /= np.linalg.norm(a, axis=-1, keepdims=True)
        out[near_pi] = a * ang[near_pi][:, None]
    return out


def _node_local(node) -> np.ndarray:
    """4×4 local transform of a glTF node (matrix, or T·R·S)."""
    if node.matrix is not None and len(node.matrix) == 16:
        return np.asarray(node.matrix, dtype=np.float64).reshape(4, 4).T   # column-major
    M = np.eye(4)
    R = quat_to_matrix(np.asarray(node.rotation if node.rotation else [0, 0, 0, 1], float))
    S = np.diag(node.scale if node.scale else [1.0, 1.0, 1.0])
    M[:3, :3] = R @ S
    M[:3, 3] = node.translation if node.translation else [0.0, 0.0, 0.0]
    return M


# -- reading ---------------------------------------------------------------------------------

def _accessor(gltf, blob: bytes, index: int) -> np.ndarray:
    try:
        acc = gltf.accessors[index]
        view = gltf.bufferViews[acc.bufferView]
    except (IndexError, TypeError) as e:
        raise ValueError(f"glTF accessor {index} or its buffer view is missing") from e
    dt = np.dtype(_COMP.get(acc.componentType, None) or np.float32)
    if acc.componentType not in _COMP or acc.type not in _NCOMP:
        raise ValueError(f"glTF accessor {index}: unsupported componentType/type {acc.componentType}/{acc.type}")
    nc = _NCOMP[acc.type]
    elem = dt.itemsize * nc
    stride = view.byteStride or elem
    start = (view.byteOffset or 0) + (acc.byteOffset or 0)
    need = start + stride * (acc.count - 1) + elem if acc.count else start
    if blob is None or need > len(blob) or need > (view.byteOffset or 0) + view.byteLength:
        raise ValueError(f"glTF accessor {index} reads past the end of its buffer (corrupt file?)")
    if stride == elem:
        a = np.frombuffer(blob, dtype=dt, count=acc.count * nc, offset=start).reshape(acc.count, nc)
    else:
        raw = np.frombuffer(blob, dtype=np.uint8, count=stride * (acc.count - 1) + elem, offset=start)
        a = np.stack([np.frombuffer(raw[i * stride:i * stride + elem].tobytes(), dtype=dt) for i in range(acc.count)])
    a = a.astype(np.float64) if dt == np.float32 else a.copy()
    if acc.normalized and dt != np.float32:
        a = a / float(np.iinfo(dt).max)
    return a


def _load(path) -> tuple[object, bytes]:
    import pygltflib

    p = Path(path)
    if not p.is_file():
        raise ValueError(f"no such glTF file: {p}")
    data = p.read_bytes()
    if len(data) < 20 or data[:4] != b"glTF":
        raise ValueError(f"{p} is not a binary glTF (.glb) file (bad magic)")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2:
        raise ValueError(f"{p}: glTF version {version} is not supported (need 2)")
    if length != len(data):
        raise ValueError(f"{p}: header says {length} bytes, file has {len(data)} (truncated or corrupt)")
    try:
        g = pygltflib.GLTF2.load_from_bytes(data)
    except Exception as e:  # pygltflib raises assorted errors on malformed chunks/JSON
        raise ValueError(f"{p}: corrupt glTF binary ({type(e).__name__}: {e})") from e
    if g is None:
        raise ValueError(f"{p}: corrupt glTF binary")
    return g, g.binary_blob()


def load_skinned_glb(path, *, animation: int = 0) -> tuple[Mesh, Skeleton, torch.Tensor, torch.Tensor]:
    """Read a skinned .glb → (rest Mesh, hinge Skeleton, weights (N, J), joint angles (F, J)).

    `load_skinned_glb_rig` returns the same plus times, names, matrices and the dropped rotation.
    Raises ValueError on corrupt files, files without a skinned mesh, or unsupported content.
    """
    mesh, rig = load_skinned_glb_rig(path, animation=animation)
    return mesh, rig.skeleton, rig.weights, rig.animation


def load_skinned_glb_rig(path, *, animation: int = 0) -> tuple[Mesh, GltfRig]:
    """See the module docstring. animation: index of the clip to read (0 = first; if the file has
    no clip, the animation is one frame of zeros)."""
    g, blob = _load(path)
    nodes = g.nodes or []
    mesh_node = next((i for i, n in enumerate(nodes) if n.mesh is not None and n.skin is not None), None)
    if mesh_node is None:
        raise ValueError(f"{path}: no node with both a mesh and a skin")
    skin = g.skins[nodes[mesh_node].skin]
    joints = list(skin.joints or [])
    if not joints:
        raise ValueError(f"{path}: skin has no joints")
    J = len(joints)
    # mesh: all triangle primitives of the mesh, merged
    Vs, Ns, Fs, JWs = [], [], [], []
    off = 0
    for prim in g.meshes[nodes[mesh_node].mesh].primitives:
        if prim.mode not in (None, 4):
            raise ValueError(f"{path}: only triangle primitives are supported (mode {prim.mode})")
        at = prim.attributes
        if at.POSITION is None or at.JOINTS_0 is None or at.WEIGHTS_0 is None:
            raise ValueError(f"{path}: a skinned primitive needs POSITION, JOINTS_0 and WEIGHTS_0")
        V = _accessor(g, blob, at.POSITION)
        n = V.shape[0]
        N = _accessor(g, blob, at.NORMAL) if at.NORMAL is not None else None
        F = (_accessor(g, blob, prim.indices).reshape(-1, 3) if prim.indices is not None
             else np.arange(n).reshape(-1, 3)).astype(np.int64)
        jj = _accessor(g, blob, at.JOINTS_0).astype(np.int64)
        ww = _accessor(g, blob, at.WEIGHTS_0).astype(np.float64)
        if jj.shape != (n, 4) or ww.shape != (n, 4):
            raise ValueError(f"{path}: JOINTS_0/WEIGHTS_0 must be VEC4 per vertex")
        if jj.min() < 0 or jj.max() >= J:
            raise ValueError(f"{path}: JOINTS_0 indexes outside the skin's {J} joints")
        if F.size and (F.min() < 0 or F.max() >= n):
            raise ValueError(f"{path}: triangle indices outside the vertex range")
        Vs.append(V); Ns.append(N); Fs.append(F + off); JWs.append((jj, ww))
        off += n
    V = np.concatenate(Vs)
    F = np.concatenate(Fs)
    N = None if any(x is None for x in Ns) else np.concatenate(Ns)
    W = np.zeros((V.shape[0], J))
    r = 0
    for jj, ww in JWs:
        rows = np.arange(r, r + jj.shape[0])[:, None].repeat(4, 1)
        np.add.at(W, (rows, jj), ww)
        r += jj.shape[0]
    if not np.isfinite(W).all() or (W < 0).any() or (W.sum(1) <= 0).any():
        raise ValueError(f"{path}: skin weights must be finite, non-negative and not all zero")
    W /= W.sum(1, keepdims=True)
    IBM = (_accessor(g, blob, skin.inverseBindMatrices).reshape(J, 4, 4).transpose(0, 2, 1)
           if skin.inverseBindMatrices is not None else np.tile(np.eye(4), (J, 1, 1)))

    # node hierarchy and rest globals
    parent = np.full(len(nodes), -1)
    for i, n in enumerate(nodes):
        for c in n.children or []:
            if not 0 <= c < len(nodes):
                raise ValueError(f"{path}: node {i} has a child index {c} out of range")
            parent[c] = i
    local0 = [_node_local(n) for n in nodes]
    glob0: dict[int, np.ndarray] = {}

    def G0(i: int) -> np.ndarray:
        if i not in glob0:
            glob0[i] = local0[i] if parent[i] < 0 else G0(int(parent[i])) @ local0[i]
        return glob0[i]

    jset = {nd: k for k, nd in enumerate(joints)}

    def joint_parent(k: int) -> int:
        p = int(parent[joints[k]])
        while p >= 0 and p not in jset:
            p = int(parent[p])
        return -1 if p < 0 else jset[p]

    # topological order (parents before children), as Skeleton requires
    order: list[int] = []
    depth = {}
    for k in range(J):
        d, p = 0, joint_parent(k)
        while p >= 0:
            d += 1
            p = joint_parent(p)
            if d > J:
                raise ValueError(f"{path}: joint hierarchy has a cycle")
        depth[k] = d
    if all(joint_parent(k) < k for k in range(J)):
        order = list(range(J))                                          # already parents-first
    else:
        order = sorted(range(J), key=lambda k: (depth[k], k))
    new_of = {k: i for i, k in enumerate(order)}
    Grest = np.stack([G0(joints[k]) for k in order])                  # (J, 4, 4)
    for k in range(J):
        R = Grest[k, :3, :3]
        if np.abs(R.T @ R - np.eye(3)).max() > RIGID_TOL or np.linalg.det(R) < 0:
            raise ValueError(f"{path}: joint {k} has a scaled/reflected rest transform (unsupported)")
    IBMo = IBM[order]
    # rest mesh: skin by the rest pose (identity when the rest pose is the bind pose)
    Wo = W[:, order]
    Mrest = np.einsum("nj,jab->nab", Wo, Grest @ IBMo)
    Vr = np.einsum("nab,nb->na", Mrest[:, :3, :3], V) + Mrest[:, :3, 3]
    Nr = None
    if N is not None:
        Nr = np.einsum("nab,nb->na", np.linalg.inv(Mrest[:, :3, :3]).transpose(0, 2, 1), N)
        Nr /= np.maximum(np.linalg.norm(Nr, axis=1, keepdims=True), 1e-30)

    # animation: per joint, rotation keyframes
    F_ang, times, axes, dropped = _read_clip(g, blob, path, animation, joints, order, nodes, Grest)
    names = tuple((nodes[joints[k]].name or f"joint{k}") for k in order)
    parents = np.array([-1 if joint_parent(k) < 0 else new_of[joint_parent(k)] for k in order])
    lim = None
    if F_ang.shape[0] > 1:
        lim = np.stack([F_ang.min(0), F_ang.max(0)], 1).astype(np.float32)
    skel = Skeleton(parents, Grest[:, :3, 3].astype(np.float32), axes, names=names, limits=lim)
    mesh = Mesh(torch.as_tensor(Vr, dtype=torch.float32), torch.as_tensor(F),
                None if Nr is None else torch.as_tensor(Nr, dtype=torch.float32)).validate()
    rig = GltfRig(skel, torch.as_tensor(Wo, dtype=torch.float32), torch.as_tensor(F_ang, dtype=torch.float32),
                  torch.as_tensor(times, dtype=torch.float32), names, torch.as_tensor(IBMo, dtype=torch.float32),
                  torch.as_tensor(Grest, dtype=torch.float32), torch.as_tensor(dropped, dtype=torch.float32))
    return mesh, rig


def _read_clip(g, blob, path, index, joints, order, nodes, Grest):
    """(F, J) hinge angles, times (F,), world hinge axes (J, 3), dropped rotation (J,)."""
    J = len(joints)
    anims = g.animations or []
    if not anims:
        return np.zeros((1, J)), np.zeros(1), np.tile([0.0, 0.0, 1.0], (J, 1)), np.zeros(J)
    if not 0 <= index < len(anims):
        raise ValueError(f"{path}: animation {index} does not exist ({len(anims)} clips)")
    an = anims[index]
    tracks = {}
    for ch in an.channels:
        if ch.target is None or ch.target.path != "rotation" or ch.target.node not in joints:
            continue
        smp = an.samplers[ch.sampler]
        t = _accessor(g, blob, smp.input)[:, 0]
        q = _accessor(g, blob, smp.output)
        if smp.interpolation == "CUBICSPLINE":
            q = q.reshape(-1, 3, 4)[:, 1]
        if q.shape != (t.shape[0], 4):
            raise ValueError(f"{path}: rotation sampler output must be VEC4 per key")
        tracks[joints.index(ch.target.node)] = (t, q)
    if not tracks:
        return np.zeros((1, J)), np.zeros(1), np.tile([0.0, 0.0, 1.0], (J, 1)), np.zeros(J)
    times = np.unique(np.concatenate([t for t, _ in tracks.values()]))
    Fn = times.shape[0]
    ang = np.zeros((Fn, J))
    axes = np.tile([0.0, 0.0, 1.0], (J, 1))
    dropped = np.zeros(J)
    for newk, k in enumerate(order):
        if k not in tracks:
            continue
        t, q = tracks[k]
        # key values at every clip time (linear in quaternion components, renormalised; a joint
        # keyed at the same times as the clip — the usual case — is read exactly)
        qq = np.stack([np.interp(times, t, q[:, i]) for i in range(4)], -1)
        R0 = quat_to_matrix(np.asarray(nodes[joints[k]].rotation or [0, 0, 0, 1], float))
        D = np.einsum("ba,fbc->fac", R0, quat_to_matrix(qq))            # Δ = R0ᵀ R(t), local
        rv_local = _rotvec(D)                                              # (F, 3)
        rv = rv_local @ Grest[newk, :3, :3].T                               # world rest frame
        if np.abs(rv).max() < 1e-12:
            continue
        _, _, Vt = np.linalg.svd(rv, full_matrices=False)
        a = Vt[0]
        a = a if a[np.argmax(np.abs(a))] > 0 else -a                        # deterministic sign
        axes[newk] = a
        ang[:, newk] = rv @ a
        dropped[newk] = np.linalg.norm(rv - ang[:, newk:newk + 1] * a, axis=1).max()
    ang = (ang + math.pi) % (2 * math.pi) - math.pi
    return ang, times, axes, dropped


# -- writing ---------------------------------------------------------------------------------

def save_skinned_glb(path, mesh: Mesh, skeleton: Skeleton, weights, animation=None, times=None) -> Path:
    """Write a skinned .glb: mesh (rest = bind pose), hinge skeleton, weights (N, J) (4 largest
    per vertex kept, renormalised), optional animation (F, J) joint angles at times (F,) seconds
    (default 1/30 s apart) as one rotation clip."""
    import pygltflib as G

    mesh = mesh.validate()
    V = mesh.V.double().numpy()
    N = mesh.N.double().numpy()
    Fc = mesh.F.numpy().astype(np.uint32)
    J = skeleton.num_joints
    W = np.asarray(torch.as_tensor(weights).double())
    if W.shape != (V.shape[0], J):
        raise ValueError(f"weights must be ({V.shape[0]}, {J}), got {W.shape}")
    top = np.argsort(-W, axis=1)[:, :4]
    if J < 4:
        top = np.concatenate([top, np.zeros((V.shape[0], 4 - J), np.int64)], 1)
    tw = np.take_along_axis(W, top, 1)
    if J < 4:
        tw[:, J:] = 0
    tw /= tw.sum(1, keepdims=True)
    P = skeleton.joint_positions.double().numpy()
    par = skeleton.parents.numpy()
    axes = skeleton.axes.double().numpy()
    anim = None if animation is None else np.asarray(torch.as_tensor(animation).double())
    if anim is not None:
        if anim.ndim != 2 or anim.shape[1] != J:
            raise ValueError(f"animation must be (F, {J}), got {anim.shape}")
        t = np.arange(anim.shape[0]) / 30.0 if times is None else np.asarray(times, float)
        if t.shape != (anim.shape[0],):
            raise ValueError("times must be (F,)")

    chunks: list[bytes] = []
    views, accs = [], []

    def add(arr: np.ndarray, ctype: int, typ: str, target=None, minmax=False) -> int:
        b = np.ascontiguousarray(arr).tobytes()
        off = sum(len(c) for c in chunks)
        chunks.append(b + b"\0" * ((-len(b)) % 4))
        views.append(G.BufferView(buffer=0, byteOffset=off, byteLength=len(b), target=target))
        kw = {}
        if minmax:
            kw = dict(min=arr.min(0).tolist(), max=arr.max(0).tolist())
        accs.append(G.Accessor(bufferView=len(views) - 1, componentType=ctype, count=int(arr.shape[0]),
                               type=typ, **kw))
        return len(accs) - 1

    a_pos = add(V.astype(np.float32), G.FLOAT, G.VEC3, G.ARRAY_BUFFER, minmax=True)
    a_nrm = add(N.astype(np.float32), G.FLOAT, G.VEC3, G.ARRAY_BUFFER)
    a_jnt = add(top.astype(np.uint16), G.UNSIGNED_SHORT, G.VEC4, G.ARRAY_BUFFER)
    a_wgt = add(tw.astype(np.float32), G.FLOAT, G.VEC4, G.ARRAY_BUFFER)
    a_idx = add(Fc.reshape(-1, 1), G.UNSIGNED_INT, G.SCALAR, G.ELEMENT_ARRAY_BUFFER)
    ibm = np.tile(np.eye(4), (J, 1, 1))
    ibm[:, :3, 3] = -P
    a_ibm = add(ibm.transpose(0, 2, 1).reshape(J, 16).astype(np.float32), G.FLOAT, G.MAT4)

    names = skeleton.names or tuple(f"joint{j}" for j in range(J))
    nodes = []
    for j in range(J):
        t_rel = P[j] - (P[par[j]] if par[j] >= 0 else 0.0)
        nodes.append(G.Node(name=names[j], translation=t_rel.tolist(),
                            children=[c for c in range(J) if par[c] == j]))
    mesh_node = G.Node(name="skinned_mesh", mesh=0, skin=0)
    nodes.append(mesh_node)
    roots = [j for j in range(J) if par[j] < 0] + [J]
    animations = []
    if anim is not None:
        a_t = add(t.astype(np.float32).reshape(-1, 1), G.FLOAT, G.SCALAR, minmax=True)
        samplers, channels = [], []
        for j in range(J):
            q = axis_angle_quat(np.broadcast_to(axes[j], (anim.shape[0], 3)), anim[:, j]).astype(np.float32)
            a_q = add(q, G.FLOAT, G.VEC4)
            samplers.append(G.AnimationSampler(input=a_t, output=a_q, interpolation="LINEAR"))
            channels.append(G.AnimationChannel(sampler=j, target=G.AnimationChannelTarget(node=j, path="rotation")))
        animations.append(G.Animation(name="clip", samplers=samplers, channels=channels))
    blob = b"".join(chunks)
    g = G.GLTF2(
        scene=0, scenes=[G.Scene(nodes=roots)], nodes=nodes,
        meshes=[G.Mesh(primitives=[G.Primitive(attributes=G.Attributes(POSITION=a_pos, NORMAL=a_nrm, JOINTS_0=a_jnt,
                                                                       WEIGHTS_0=a_wgt), indices=a_idx)])],
        skins=[G.Skin(joints=list(range(J)), inverseBindMatrices=a_ibm, skeleton=roots[0])],
        animations=animations, accessors=accs, bufferViews=views, buffers=[G.Buffer(byteLength=len(blob))])
    g.set_binary_blob(blob)
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    g.save_binary(str(p))
    return p


def gltf_skinned_positions(path, key: int, *, animation: int = 0) -> np.ndarray:
    """Reference glTF skinning (quaternion node FK, Σ w G_j IBM_j v) of the file's mesh at keyframe
    `key` of the clip — independent of the hinge mapping; used by the tests. → (N, 3)."""
    g, blob = _load(path)
    nodes = g.nodes
    mesh_node = next(i for i, n in enumerate(nodes) if n.mesh is not None and n.skin is not None)
    skin = g.skins[nodes[mesh_node].skin]
    joints = list(skin.joints)
    prim = g.meshes[nodes[mesh_node].mesh].primitives[0]
    V = _accessor(g, blob, prim.attributes.POSITION)
    jj = _accessor(g, blob, prim.attributes.JOINTS_0).astype(np.int64)
    ww = _accessor(g, blob, prim.attributes.WEIGHTS_0)
    IBM = _accessor(g, blob, skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
    rot = {}
    an = g.animations[animation]
    for ch in an.channels:
        if ch.target.path == "rotation":
            rot[ch.target.node] = _accessor(g, blob, an.samplers[ch.sampler].output)[key]
    parent = {c: i for i, n in enumerate(nodes) for c in (n.children or [])}
    cache: dict[int, np.ndarray] = {}

    def Gl(i):
        if i not in cache:
            L = _node_local(nodes[i])
            if i in rot:
                L[:3, :3] = quat_to_matrix(rot[i])
            cache[i] = L if i not in parent else Gl(parent[i]) @ L
        return cache[i]

    S = np.stack([Gl(j) @ IBM[k] for k, j in enumerate(joints)])
    M = np.einsum("nk,nkab->nab", ww / ww.sum(1, keepdims=True), S[jj])
    return np.einsum("nab,nb->na", M[:, :3, :3], V) + M[:, :3, 3]
