"""Frame sequences (Sun 2007 Table 1: V, V&B, V,B&L) and pose animation (P).

* "V":   the camera orbits the target about +Y; lighting and materials fixed.
* "VB":  view + material parameters change (every region keeps its BRDF family; colours,
         exponents/roughness vary).
* "VBL": view + materials + the env map rotates about +Y (by up to LIGHT_SPIN_DEG).
* "P":   pose animation of an articulated scene (view, lighting, materials fixed): its own clip
         (``scene.animation``) when it has one, else a generic track; ValueError without a skeleton.

Lighting-only kinds (relighting is what PRT exists for):
* "L":   fixed view and materials; the env map rotates about a seeded, tilted axis (elevation
         LIGHT_AXIS_ELEV_DEG from the horizon, never +Y, so SH rotation about arbitrary axes and
         re-projection of a tilted map are exercised) by LIGHT_ROT_DEG over the sequence.
* "E":   fixed view and materials; every frame a different env map: frame 0 the scene's own, then
         the probes of ``probes`` (default ``PROBES``) in turn, at the scene map's resolution — so
         a method that kept a cached lighting projection renders the wrong probe.
* "VL":  view + lighting (the L rotation), materials fixed: Sun's "V,B&L" without B, so methods
         with fixed BRDFs get a combined row.

`Frame.changed` is computed by comparing each frame with the previous one (the first frame has
every flag), so it is right by construction. Everything is deterministic in `seed`.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from scenes.frame import Frame

KINDS = ("V", "VB", "VBL", "P", "L", "E", "VL")
LIGHTING_KINDS = ("VBL", "L", "E", "VL")  # kinds whose lighting changes between frames
ALL_CHANGED = frozenset({"view", "brdf", "light", "pose"})
# Total orbit of the camera over a sequence (degrees); the alcove is seen only through its opening.
ORBIT_DEG = {"default": 40.0, "alcove": 16.0}
# Env-map rotation over a VBL sequence (degrees).
LIGHT_SPIN_DEG = 120.0
# L / VL: total rotation about the tilted axis (degrees; ≥ 90) and the axis' elevation range.
LIGHT_ROT_DEG = 120.0
LIGHT_AXIS_ELEV_DEG = (20.0, 70.0)
# E: the captured probes swapped in after frame 0 (scenes/assets/probes, ``scenes.envmap.named``).
PROBES = ("courtyard", "forest", "interior", "sunrise")


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
    clip = getattr(scene, "animation", None)
    if clip is not None:  # the scene's own clip: n_frames evenly over it from a seeded start, linear in between
        F = clip.shape[0]
        t = (phase / (2 * math.pi) * F + torch.arange(n_frames, dtype=torch.float64) * F / max(n_frames, 1)) % F
        i0 = t.floor().long()
        w = (t - i0)[:, None].float()
        return (1 - w) * clip[i0] + w * clip[(i0 + 1) % F]
    if sk.names is not None and tuple(sk.names) == CREATURE_JOINTS:
        return creature_animation(n_frames, phase=phase)
    # generic skeleton: smooth sinusoids inside the joint limits (or ±0.5 rad)
    J = sk.num_joints
    lim = sk.limits if sk.limits is not None else torch.tensor([[-0.5, 0.5]] * J)
    lo, hi = lim[:, 0].double(), lim[:, 1].double()
    t = torch.arange(n_frames, dtype=torch.float64)[:, None] / max(n_frames, 1) * 2 * math.pi
    ph = torch.as_tensor(rng.uniform(0, 2 * math.pi, J))
    return ((lo + hi) / 2 + (hi - lo) / 2 * 0.9 * torch.sin(t + ph)).float()


def rotation_axis_angle(axis, angle_rad: float) -> torch.Tensor:
    """(3, 3) float32 rotation by ``angle_rad`` about the unit ``axis`` (right-hand rule, Rodrigues)."""
    k = torch.as_tensor(axis, dtype=torch.float64)
    k = k / k.norm()
    K = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]], dtype=torch.float64)
    R = torch.eye(3, dtype=torch.float64) + math.sin(angle_rad) * K + (1 - math.cos(angle_rad)) * (K @ K)
    return R.float()


def tilted_axis(rng: np.random.Generator) -> tuple[float, float, float]:
    """A unit axis at a random azimuth and an elevation in LIGHT_AXIS_ELEV_DEG (never ±Y)."""
    az = rng.uniform(0, 2 * math.pi)
    el = math.radians(rng.uniform(*LIGHT_AXIS_ELEV_DEG))
    return (math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az))


def _same_env(a, b) -> bool:
    return a is b or (a.data is b.data and torch.equal(a.to_world, b.to_world))


def make_sequence(scene, kind: str, n_frames: int = 4, seed: int = 0, *, probes=None) -> list[Frame]:
    """Frames of sequence `kind` (``KINDS``, module docstring) for `scene`, deterministic in `seed`.
    probes: env maps (``EnvMap``) or names (``scenes.envmap.named``) for "E" (default
    ``PROBES``), resampled to nothing: a named map is made at the scene map's height."""
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
    axis = tilted_axis(rng) if kind in ("L", "VL") else None
    swaps = _probe_maps(scene, probes) if kind == "E" else None
    if swaps is not None:  # the probes' order and each one's azimuth are seeded
        swaps = [swaps[j].rotated(rotation_y(rng.uniform(0, 2 * math.pi))) for j in rng.permutation(len(swaps))]

    frames: list[Frame] = []
    for i in range(n_frames):
        f = i / max(n_frames - 1, 1)
        cam, env, mats, pose = scene.camera, scene.envmap, dict(scene.materials), None
        if kind in ("V", "VB", "VBL", "VL"):
            cam = scene.camera.orbited(start + orbit * f)
        if kind in ("VB", "VBL") and i > 0:
            mats = {r: perturb_material(m, rng) for r, m in scene.materials.items()}
        if kind == "VBL" and i > 0:  # frame 0 keeps the scene's own lighting
            env = scene.envmap.rotated(rotation_y(spin_sign * math.radians(LIGHT_SPIN_DEG) * f))
        if kind in ("L", "VL") and i > 0:
            env = scene.envmap.rotated(rotation_axis_angle(axis, spin_sign * math.radians(LIGHT_ROT_DEG) * f))
        if kind == "E" and i > 0:
            env = swaps[(i - 1) % len(swaps)]
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


def _probe_maps(scene, probes) -> list:
    """The E sequence's maps (module docstring): EnvMaps as given, names made at the scene map's
    height; at least 2 so consecutive frames always differ (frame 0 is the scene's own map)."""
    from scenes.envmap import EnvMap, named

    names = PROBES if probes is None else tuple(probes)
    maps = [p if isinstance(p, EnvMap) else named(p, height=scene.envmap.height) for p in names]
    maps = [m for m in maps if not torch.equal(m.data, scene.envmap.data)] or maps
    if len(maps) < 2:
        raise ValueError(f"sequence 'E' needs >= 2 probes besides the scene's own map, got {len(maps)}")
    return maps
