"""Hinge-joint skeletons, forward kinematics and linear blend skinning (torch), and a procedural
articulated creature with a short animation.

Every joint j has one hinge: a rotation by pose[j] radians about the unit axis `axes[j]` through
its rest position `joint_positions[j]` (rest-pose world coordinates). Its world transform relative
to the rest pose is (forward kinematics)
    T_j = T_parent(j) · Tr(p_j) · Rot(a_j, θ_j) · Tr(−p_j),     T_root-parent = I,
so the rest pose (θ = 0) gives identities. Linear blend skinning (Magnenat-Thalmann 1988):
    v' = Σ_j w_vj T_j v,    n' ∝ cof(Σ_j w_vj R_j) n
(the cofactor matrix is the inverse transpose up to a positive factor; normals renormalised).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from methods.core.fused import fused

# Joint angles beyond this (radians) are rejected as nonsensical for a hinge.
MAX_JOINT_ANGLE = math.pi
# Skin weight rows must sum to 1 within this (float32 storage).
WEIGHT_SUM_TOL = 1e-4


def axis_angle_matrix(axis: Tensor, angle: Tensor) -> Tensor:
    """Rodrigues rotation matrices (..., 3, 3) from unit axes (..., 3) and angles (...)."""
    k = axis
    c, s = torch.cos(angle), torch.sin(angle)
    x, y, z = k.unbind(-1)
    zero = torch.zeros_like(x)
    K = torch.stack([torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1), torch.stack([-y, x, zero], -1)], -2)
    I = torch.eye(3, dtype=k.dtype, device=k.device).expand(K.shape)
    return I + s[..., None, None] * K + (1 - c)[..., None, None] * (K @ K)


@dataclass
class Skeleton:
    """parents (J,) int (−1 = root, parents[j] < j); joint_positions (J, 3) rest pivots; axes (J, 3) hinge axes."""

    parents: Tensor
    joint_positions: Tensor
    axes: Tensor
    names: tuple[str, ...] | None = None
    limits: Tensor | None = None  # (J, 2) [min, max] radians the animation stays within (informative)

    def __post_init__(self) -> None:
        self.parents = torch.as_tensor(np.asarray(self.parents), dtype=torch.int64)
        self.joint_positions = torch.as_tensor(np.asarray(self.joint_positions, dtype=np.float32))
        ax = torch.as_tensor(np.asarray(self.axes, dtype=np.float64))
        J = self.parents.shape[0]
        if self.parents.dim() != 1 or J == 0:
            raise ValueError(f"skeleton parents must be (J,) with J >= 1, got {tuple(self.parents.shape)}")
        if self.joint_positions.shape != (J, 3) or ax.shape != (J, 3):
            raise ValueError(f"skeleton joint_positions and axes must be ({J}, 3), got "
                             f"{tuple(self.joint_positions.shape)}, {tuple(ax.shape)}")
        for j, p in enumerate(self.parents.tolist()):
            if not (-1 <= p < j):
                raise ValueError(f"skeleton parent of joint {j} must be -1 or an earlier joint, got {p}")
        if not torch.isfinite(self.joint_positions).all() or not torch.isfinite(ax).all():
            raise ValueError("skeleton joint positions/axes must be finite")
        n = ax.norm(dim=1)
        if (n < 1e-8).any():
            raise ValueError(f"skeleton axis of joint {int((n < 1e-8).nonzero()[0, 0])} is zero")
        self.axes = (ax / n[:, None]).float()
        if self.names is not None and len(self.names) != J:
            raise ValueError(f"skeleton names must have {J} entries")
        if self.limits is not None:
            self.limits = torch.as_tensor(np.asarray(self.limits, dtype=np.float32))

    @property
    def num_joints(self) -> int:
        return int(self.parents.shape[0])

    def check_pose(self, pose) -> Tensor:
        """Validated pose (J,) float tensor (finite, |θ| ≤ π)."""
        pose = torch.as_tensor(pose)
        if not pose.is_floating_point():
            pose = pose.float()
        if pose.shape != (self.num_joints,):
            raise ValueError(f"pose must be ({self.num_joints},) joint angles, got {tuple(pose.shape)}")
        if not torch.isfinite(pose).all():
            raise ValueError("pose has NaN/Inf joint angles")
        if (pose.abs() > MAX_JOINT_ANGLE).any():
            j = int((pose.abs() > MAX_JOINT_ANGLE).nonzero()[0, 0])
            raise ValueError(f"pose angle of joint {j} is {float(pose[j]):.3f} rad, outside [-π, π]")
        return pose

    def forward_kinematics(self, pose) -> Tensor:
        """(J, 4, 4) world transforms relative to the rest pose for pose (J,) radians."""
        pose = self.check_pose(pose)
        dt, dev = pose.dtype, pose.device
        p = self.joint_positions.to(dt).to(dev)
        R = axis_angle_matrix(self.axes.to(dt).to(dev), pose)  # (J, 3, 3)
        local = torch.zeros(self.num_joints, 4, 4, dtype=dt, device=dev)
        local[:, :3, :3] = R
        local[:, :3, 3] = p - (R @ p[:, :, None])[:, :, 0]  # Tr(p) R Tr(−p)
        local[:, 3, 3] = 1
        T = []
        for j, par in enumerate(self.parents.tolist()):
            T.append(local[j] if par < 0 else T[par] @ local[j])
        return torch.stack(T)

    def pose_mesh(self, mesh, weights: Tensor, pose):
        """Skinned copy of `mesh` (scenes.mesh.Mesh) for weights (N, J) and pose (J,)."""
        from scenes.mesh import Mesh

        if mesh.N is None:
            mesh = mesh.validate()
        V, N = skin(mesh.V, mesh.N, weights, self.forward_kinematics(pose))
        return Mesh(V, mesh.F, N, mesh.uv)

    def params(self) -> dict:
        return {"parents": self.parents, "joint_positions": self.joint_positions, "axes": self.axes}


def check_weights(weights: Tensor, n_vertices: int, n_joints: int) -> Tensor:
    """Validate skin weights (N, J): finite, ≥ 0, rows summing to 1."""
    w = torch.as_tensor(weights)
    if w.shape != (n_vertices, n_joints):
        raise ValueError(f"skin weights must be ({n_vertices}, {n_joints}), got {tuple(w.shape)}")
    if not torch.isfinite(w).all() or (w < 0).any():
        raise ValueError("skin weights must be finite and non-negative")
    bad = ((w.sum(1) - 1).abs() > WEIGHT_SUM_TOL)
    if bad.any():
        raise ValueError(f"skin weights of {int(bad.sum())} vertices do not sum to 1 (first: vertex {int(bad.nonzero()[0, 0])})")
    return w


def skin(V: Tensor, N: Tensor | None, weights: Tensor, transforms: Tensor) -> tuple[Tensor, Tensor | None]:
    """Linear blend skinning (the reference path: validates its inputs; `blend_skin` is the fast
    path `Scene.geometry` takes with the weights validated once, when the scene is built).

    Args:
        V: (N, 3) rest positions; N: (N, 3) rest unit normals or None;
        weights: (N, J) skin weights (rows sum to 1); transforms: (J, 4, 4) rest-relative.
    Returns:
        V' (N, 3), N' (N, 3) unit normals (or None), in V's dtype/device.
    """
    if V.dim() != 2 or V.shape[1] != 3:
        raise ValueError(f"V must be (N, 3), got {tuple(V.shape)}")
    if transforms.dim() != 3 or transforms.shape[1:] != (4, 4):
        raise ValueError(f"transforms must be (J, 4, 4), got {tuple(transforms.shape)}")
    w = check_weights(weights, V.shape[0], transforms.shape[0]).to(V.dtype).to(V.device)
    T = transforms.to(V.dtype).to(V.device)
    M = torch.einsum("nj,jab->nab", w, T[:, :3, :])  # (N, 3, 4) blended affine maps
    Vp = (M[:, :, :3] @ V[:, :, None])[:, :, 0] + M[:, :, 3]
    if N is None:
        return Vp, None
    if N.shape != V.shape:
        raise ValueError(f"N must be {tuple(V.shape)} like V, got {tuple(N.shape)}")
    A = M[:, :, :3]
    c0, c1, c2 = A[:, :, 0], A[:, :, 1], A[:, :, 2]
    cof = torch.stack([torch.cross(c1, c2, dim=1), torch.cross(c2, c0, dim=1), torch.cross(c0, c1, dim=1)], dim=2)
    Np = (cof @ N.to(V.dtype)[:, :, None])[:, :, 0]
    Np = Np / Np.norm(dim=1, keepdim=True).clamp_min(1e-12)
    return Vp, Np


# Vertices from which `blend_skin` runs compiled (one static shape per skinned shape: a bench-size
# mesh compiles once, in the harness's warm-up frame); smaller meshes (test size) run it eagerly,
# so tests meeting many small meshes pay no compilations.
BLEND_COMPILE_MIN = 4096


def _blend(V: Tensor, N: Tensor, w: Tensor, T12: Tensor) -> tuple[Tensor, Tensor]:
    """`skin` of V, N (n, 3) with weights w (n, J) and the transforms' top rows T12 (J, 12)
    (row-major [R | t]), componentwise: the blended map M = w · T12 (n, 12), V' = A V + t, the
    cofactor of A (its columns' cross products) times N, renormalised — one pass when compiled."""
    a = (w @ T12).unbind(1)                                   # a[4r + k] = A[r][k], a[4r + 3] = t[r]
    x, y, z = V.unbind(1)
    Vp = torch.stack([a[4 * r] * x + a[4 * r + 1] * y + a[4 * r + 2] * z + a[4 * r + 3] for r in range(3)], 1)
    c = [[a[4 * r + k] for r in range(3)] for k in range(3)]   # columns c_k of A

    def cross(u, v):
        return [u[1] * v[2] - u[2] * v[1], u[2] * v[0] - u[0] * v[2], u[0] * v[1] - u[1] * v[0]]

    cof = [cross(c[1], c[2]), cross(c[2], c[0]), cross(c[0], c[1])]   # columns of cof(A)
    nx, ny, nz = N.unbind(1)
    n = [cof[0][r] * nx + cof[1][r] * ny + cof[2][r] * nz for r in range(3)]
    inv = 1.0 / torch.sqrt(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).clamp_min(1e-12)
    return Vp, torch.stack([u * inv for u in n], 1)


_blend_fused = fused(_blend)


def blend_skin(V: Tensor, N: Tensor, weights: Tensor, transforms: Tensor) -> tuple[Tensor, Tensor]:
    """`skin` without its checks (the fast path): V, N (n, 3) rest positions and unit normals,
    weights (n, J) already validated (`check_weights`: `Scene` does it when built), transforms
    (J, 4, 4). Compiled from `BLEND_COMPILE_MIN` vertices (2.2 ms → 0.3 ms for the bench creature's
    9.7 K vertices, 1 thread), eager below; equal to `skin` to float32 round-off
    (tests/scenes/test_skeleton.py)."""
    T12 = transforms[:, :3, :].to(V.dtype).reshape(-1, 12).contiguous()
    fn = _blend_fused if V.shape[0] >= BLEND_COMPILE_MIN else _blend
    return fn(V.contiguous(), N.to(V.dtype).contiguous(), weights.to(V.dtype).contiguous(), T12)


# -- the procedural creature ---------------------------------------------------------------------

CREATURE_JOINTS = ("root", "neck",
                   "hip_fl", "knee_fl", "hip_fr", "knee_fr", "hip_bl", "knee_bl", "hip_br", "knee_br")


def _smoothstep(x: np.ndarray, a: float, b: float) -> np.ndarray:
    t = np.clip((x - a) / (b - a), 0.0, 1.0)
    return t * t * (3 - 2 * t)


def make_creature(size: str = "test"):
    """A four-legged creature standing on y = 0 (the ground plane is not part of it).

    Torso: an ellipsoid along x; head: a sphere in front (+x) on a neck hinge; four legs, each one
    capsule from hip to foot with a hip and a knee hinge about +z (legs swing in the x–y plane).
    Weights blend smoothly (smoothstep over ±BLEND of the leg length) between torso↔hip and
    hip↔knee, so the skin stays continuous at the joints.

    Returns: (mesh: Mesh, skeleton: Skeleton, weights: (N, J) float32).
    """
    from scenes import procedural as P
    from scenes.mesh import merge

    if size not in ("test", "bench"):
        raise ValueError(f"size must be 'test' or 'bench', got {size!r}")
    q = {"test": dict(seg=10, n_len=8, cap=3, sub=1), "bench": dict(seg=24, n_len=30, cap=6, sub=3)}[size]
    BLEND = 0.09  # fraction of leg length over which weights blend at each joint
    torso_c = np.array([0.0, 1.25, 0.0])
    torso_r = np.array([0.9, 0.42, 0.42])
    leg_len, leg_r = 1.1, 0.13  # hips at y = 1.1: feet touch y = 0
    hips = {"fl": (0.55, 0.28), "fr": (0.55, -0.28), "bl": (-0.55, 0.28), "br": (-0.55, -0.28)}
    neck = np.array([0.82, 1.45, 0.0])
    head_c = np.array([1.2, 1.75, 0.0])

    J = len(CREATURE_JOINTS)
    jidx = {n: i for i, n in enumerate(CREATURE_JOINTS)}
    parents = np.full(J, -1)
    jpos = np.zeros((J, 3))
    axes = np.tile([0.0, 0.0, 1.0], (J, 1))
    jpos[0] = torso_c
    axes[0] = (0.0, 1.0, 0.0)
    jpos[1] = neck
    for k, (x, z) in hips.items():
        hip = np.array([x, torso_c[1] - 0.15, z])
        jpos[jidx["hip_" + k]] = hip
        parents[jidx["hip_" + k]] = 0
        jpos[jidx["knee_" + k]] = hip - (0, leg_len / 2, 0)
        parents[jidx["knee_" + k]] = jidx["hip_" + k]
    parents[1] = 0
    skel = Skeleton(parents, jpos.astype(np.float32), axes, names=CREATURE_JOINTS,
                    limits=np.array([[-0.3, 0.3], [-0.6, 0.5]] + [[-1.4, 1.0], [-1.6, 0.0]] * 4, np.float32))

    parts, weights = [], []
    # torso: an icosphere scaled to an ellipsoid
    torso = P.icosphere(q["sub"] + 1)
    Vt = torso.V.double().numpy() * torso_r + torso_c
    torso = P._mesh(Vt, torso.F.numpy(), (Vt - torso_c) / torso_r**2)  # ellipsoid normal ∝ (p − c)/r²
    parts.append(torso)
    w = np.zeros((torso.num_vertices, J))
    w[:, 0] = 1
    weights.append(w)
    head = P.icosphere(q["sub"] + 1, radius=0.32, center=head_c)
    parts.append(head)
    w = np.zeros((head.num_vertices, J))
    w[:, 1] = 1
    weights.append(w)
    neck_m = P.capsule(torso_c + (0.55, 0.1, 0.0), head_c, 0.14, n_seg=q["seg"], n_len=q["n_len"] // 2, n_cap=q["cap"])
    parts.append(neck_m)
    a = torso_c + (0.55, 0.1, 0.0)
    t = ((neck_m.V.double().numpy() - a) @ (head_c - a)) / np.sum((head_c - a) ** 2)
    s = _smoothstep(t, 0.3, 0.6)
    w = np.zeros((neck_m.num_vertices, J))
    w[:, 0], w[:, 1] = 1 - s, s
    weights.append(w)
    for k in hips:
        hip = jpos[jidx["hip_" + k]]
        top = hip + (0, 0.12, 0)
        foot = hip - (0, leg_len - leg_r, 0)
        leg = P.capsule(foot, top, leg_r, n_seg=q["seg"], n_len=q["n_len"], n_cap=q["cap"])
        parts.append(leg)
        t = (hip[1] - leg.V.double().numpy()[:, 1]) / leg_len  # 0 at the hip, 0.5 at the knee
        s_hip = _smoothstep(t, -BLEND, BLEND)
        s_knee = _smoothstep(t, 0.5 - BLEND, 0.5 + BLEND)
        w = np.zeros((leg.num_vertices, J))
        w[:, 0] = 1 - s_hip
        w[:, jidx["hip_" + k]] = s_hip - s_knee
        w[:, jidx["knee_" + k]] = s_knee
        weights.append(w)
    mesh = merge(parts).validate()
    W = torch.as_tensor(np.concatenate(weights), dtype=torch.float32)
    W = W / W.sum(1, keepdim=True)
    return mesh, skel, W


def creature_animation(n_frames: int, *, phase: float = 0.0) -> Tensor:
    """(F, J) joint angles: a walk-like cycle in which the front-left leg lifts high (shadowing the
    torso and the other front leg), knees bend, the head nods. Frame 0 at phase 0 is not the rest
    pose; all angles lie within the skeleton's `limits`."""
    if int(n_frames) < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    t = torch.arange(int(n_frames), dtype=torch.float64) / max(int(n_frames), 1) * 2 * math.pi + phase
    J = len(CREATURE_JOINTS)
    A = torch.zeros(int(n_frames), J, dtype=torch.float64)
    j = {n: i for i, n in enumerate(CREATURE_JOINTS)}
    # legs swing about +z: a positive angle moves the foot towards +x (forward) and up
    A[:, j["root"]] = 0.15 * torch.sin(t)
    A[:, j["neck"]] = -0.25 + 0.25 * torch.sin(2 * t)
    A[:, j["hip_fl"]] = 0.6 + 0.35 * torch.sin(t)           # raised forward
    A[:, j["knee_fl"]] = -(0.9 + 0.5 * torch.sin(t))        # knee bent back (lower leg folds under)
    A[:, j["hip_fr"]] = -0.35 * torch.sin(t)
    A[:, j["knee_fr"]] = -0.3 * (1 + torch.cos(t))
    A[:, j["hip_bl"]] = 0.35 * torch.sin(t)
    A[:, j["knee_bl"]] = -0.3 * (1 - torch.cos(t))
    A[:, j["hip_br"]] = -0.3 * torch.sin(t + 1.0)
    A[:, j["knee_br"]] = -0.25 * (1 + torch.sin(t))
    return A.float()
