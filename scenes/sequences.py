"""Frame sequences (Sun 2007 Table 1: V, V&B, V,B&L) and pose animation (P).

* "V":   the camera orbits the target about +Y; lighting and materials fixed.
* "VB":  view + material parameters change (every region keeps its BRDF family; colours,
         exponents/roughness vary).
* "VBL": view + materials + the env map rotates about +Y (by up to LIGHT_SPIN_DEG).
* "P":   pose animation of an articulated scene (view, lighting, materials fixed); ValueError
         for a scene without a skeleton.

`Frame.changed` is computed by comparing each frame with the previous one (the first frame has
every flag), so it is right by construction. Everything is deterministic in `seed`.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from scenes.frame import Frame

KINDS = ("V", "VB", "VBL", "P")
ALL_CHANGED = frozenset({"view", "brdf", "light", "pose"})
# Total orbit of the camera over a sequence (degrees); the alcove is seen only through its opening.
ORBIT_DEG = {"default": 40.0, "alcove": 16.0}
# Env-map rotation over a VBL sequence (degrees).
LIGHT_SPIN_DEG = 120.0


def rotation_y(angle_rad: float) -> torch.Tensor:
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float32)


def perturb_material(mat, rng: np.random.Generator):
    """Same BRDF family, new parameters: kd ×U(0.7, 1.25) per channel, ks × one U(0.7, 1.25) (≤ 0.95),
    Phong/Blinn exponents ×exp(U(−0.7, 0.7)) within [2, 400], roughnesses ×exp(U(−0.35, 0.35))."""
    p = dict(mat.params())
    if "kd" in p:
        p["kd"] = [float(v) for v in np.clip(np.asarray(p["kd"], float) * rng.uniform(0.7, 1.25, 3), 0.0, 0.95)]
    if "ks" in p:  # specular colour stays neutral: one factor for all channels
        p["ks"] = [float(v) for v in np.clip(np.asarray(p["ks"], float) * rng.uniform(0.7, 1.25), 0.0, 0.95)]
    if "kd" in p and "ks" in p:  # keep kd + ks ≤ 0.98 per channel (energy conservation)
        tot = np.asarray(p["kd"]) + np.asarray(p["ks"])
        f = np.minimum(1.0, 0.98 / np.maximum(tot, 1e-12))
        p["kd"] = [float(v) for v in np.asarray(p["kd"]) * f]
        p["ks"] = [float(v) for v in np.asarray(p["ks"]) * f]
    if "s" in p:
        p["s"] = float(np.clip(p["s"] * math.exp(rng.uniform(-0.7, 0.7)), 2.0, 400.0))
    for k in ("m", "sigma", "ax", "ay"):
        if k in p:
            p[k] = float(np.clip(p[k] * math.exp(rng.uniform(-0.35, 0.35)), 0.03, 1.0))
    return type(mat).from_params(p)


def _pose_track(scene, n_frames: int, rng: np.random.Generator) -> torch.Tensor:
    from scenes.skeleton import CREATURE_JOINTS, creature_animation

    sk = scene.skeleton
    phase = float(rng.uniform(0, 2 * math.pi))
    if sk.names is not None and tuple(sk.names) == CREATURE_JOINTS:
        return creature_animation(n_frames, phase=phase)
    # generic skeleton: smooth sinusoids inside the joint limits (or ±0.5 rad)
    J = sk.num_joints
    lim = sk.limits if sk.limits is not None else torch.tensor([[-0.5, 0.5]] * J)
    lo, hi = lim[:, 0].double(), lim[:, 1].double()
    t = torch.arange(n_frames, dtype=torch.float64)[:, None] / max(n_frames, 1) * 2 * math.pi
    ph = torch.as_tensor(rng.uniform(0, 2 * math.pi, J))
    return ((lo + hi) / 2 + (hi - lo) / 2 * 0.9 * torch.sin(t + ph)).float()


def _same_env(a, b) -> bool:
    return a is b or (a.data is b.data and torch.equal(a.to_world, b.to_world))


def make_sequence(scene, kind: str, n_frames: int = 4, seed: int = 0) -> list[Frame]:
    """Frames of sequence `kind` ("V", "VB", "VBL", "P") for `scene`, deterministic in `seed`."""
    if kind not in KINDS:
        raise ValueError(f"unknown sequence kind {kind!r}; choose from {', '.join(KINDS)}")
    n_frames = int(n_frames)
    if n_frames < 1:
        raise ValueError(f"n_frames must be >= 1, got {n_frames}")
    if kind == "P" and scene.skeleton is None:
        raise ValueError(f"sequence 'P' needs an articulated scene; {scene.name!r} has no skeleton")
    rng = np.random.default_rng([int(seed), KINDS.index(kind)])
    orbit = math.radians(ORBIT_DEG.get(scene.name, ORBIT_DEG["default"]))
    start = -orbit / 2 + rng.uniform(-0.1, 0.1) * orbit
    spin_sign = 1.0 if rng.uniform() < 0.5 else -1.0
    poses = _pose_track(scene, n_frames, rng) if kind == "P" else None

    frames: list[Frame] = []
    for i in range(n_frames):
        f = i / max(n_frames - 1, 1)
        cam, env, mats, pose = scene.camera, scene.envmap, dict(scene.materials), None
        if kind != "P":
            cam = scene.camera.orbited(start + orbit * f)
        if kind in ("VB", "VBL") and i > 0:
            mats = {r: perturb_material(m, rng) for r, m in scene.materials.items()}
        if kind == "VBL" and i > 0:  # frame 0 keeps the scene's own lighting
            env = scene.envmap.rotated(rotation_y(spin_sign * math.radians(LIGHT_SPIN_DEG) * f))
        if kind == "P":
            pose = poses[i]
        if i == 0:
            changed = ALL_CHANGED
        else:
            prev = frames[-1]
            ch = set()
            if cam != prev.camera:
                ch.add("view")
            if any(mats[r] != prev.materials[r] for r in mats):
                ch.add("brdf")
            if not _same_env(env, prev.envmap):
                ch.add("light")
            if (pose is None) != (prev.pose is None) or (pose is not None and not torch.equal(pose, prev.pose)):
                ch.add("pose")
            changed = frozenset(ch)
        frames.append(Frame(envmap=env, camera=cam, materials=mats, pose=pose, index=i, changed=changed))
    return frames
