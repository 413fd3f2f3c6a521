"""EnvMap.radiance equals Mitsuba 3.9's own `envmap` emitter built by
`references.plugins.envmap_to_mitsuba` (docs/ARCHITECTURE.md, env map convention)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from scenes.envmap import EnvMap, procedural

import mitsuba as mi

# Both sides run in float32. Differences come from float32 round-off of the direction → (u, v)
# map (atan2/acos, and the to_world product for rotated maps), amplified by the texel gradient;
# measured 2.5e-6 (identity) and 2.3e-5 (rotated) of the map's maximum at 10⁵ directions.
RADIANCE_TOL = 2e-4  # × max texel value
N_DIRS = 20_000


def rot(axis, angle):
    a = np.asarray(axis, float)
    a /= np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


@pytest.fixture(scope="module")
def mitsuba():
    from references.mitsuba_setup import ensure_variant

    ensure_variant()
    import drjit as dr

    return mi, dr


def mitsuba_radiance(env, d):
    """Mitsuba emitter.eval for radiance arriving from world directions d (N, 3)."""
    import drjit as dr

    from references.plugins import envmap_to_mitsuba

    emitter = mi.load_dict(envmap_to_mitsuba(env))
    si = dr.zeros(mi.SurfaceInteraction3f, d.shape[0])
    si.wi = mi.Vector3f(-d.T)  # wi points away from the emitter towards the scene: −d
    return np.array(emitter.eval(si)).T


CASES = {
    "random_identity": lambda: EnvMap(torch.rand(9, 16, 3, generator=torch.Generator().manual_seed(0)) * 3),
    "random_rotated": lambda: EnvMap(torch.rand(9, 16, 3, generator=torch.Generator().manual_seed(0)) * 3,
                                     rot([0.3, 0.8, -0.5], 0.7)),
    "sky_sun_rotated": lambda: procedural("sky_sun", height=32).rotated(rot([0, 1, 0], 2.0) @ rot([1, 0, 0], 0.4)),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_radiance_equals_mitsuba_eval(mitsuba, case):
    env = CASES[case]()
    g = torch.Generator().manual_seed(1)
    d = torch.randn(N_DIRS, 3, generator=g)
    d = d / d.norm(dim=-1, keepdim=True)
    ours = env.radiance(d).numpy()
    theirs = mitsuba_radiance(env, d.numpy())
    assert theirs.shape == ours.shape
    err = np.abs(ours - theirs).max() / env.data.max().item()
    assert err < RADIANCE_TOL, f"max |ours − mitsuba| / max texel = {err:.2e}"


def test_mitsuba_disagrees_with_a_wrong_convention(mitsuba):
    # the comparison can fail: a map whose columns are shifted by half a texel (corner-aligned
    # columns instead of texel-centred) is detected
    env = CASES["random_identity"]()
    d = torch.randn(N_DIRS, 3, generator=torch.Generator().manual_seed(2))
    d = d / d.norm(dim=-1, keepdim=True)
    theirs = mitsuba_radiance(env, d.numpy())
    R = rot([0, 1, 0], -math.pi / env.width)  # rotate about +y by half a texel
    wrong = env.rotated(R).radiance(d).numpy()
    assert np.abs(wrong - theirs).max() / env.data.max().item() > 100 * RADIANCE_TOL
