"""Per-frame lighting updates are proven, not assumed: for every method that claims dynamic
lighting, frame i of a lighting-only sequence (L: rotation about a tilted axis; E: a different probe
each frame) rendered after the frames before it equals a fresh precompute + render whose scene has
that frame's env map baked in (to float32 round-off). A method that kept a stale lighting
projection, or rotated about the wrong axis, fails here."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from methods.registry import get_method
from references.gbuffer import make_gbuffer
from scenes.library import get_scene
from scenes.sequences import make_sequence

# Float32 round-off of a whole render pipeline (projections, matmuls, sums over ~10³ terms), relative
# to the image's peak: the two renders do the same arithmetic on the same inputs in a different
# order of cache fills, so differences come from accumulation order only.
RTOL = 2e-5

# Small configs: the property under test is independent of the term counts.
CONFIGS = {
    "inout": {"terms": 8},
    "ptt": dict(bounces=1, n_wi=4, brdf_grid=8, brdf_table=16, cube_res=8, light_res_1=2, rays=16,
                lobe_fit_samples=1024, lobe_vis_samples=256, lobe_vis_res=4, lobe_theta=4, env_res=8,
                lobe_degrees=[0, 14]),  # one bounce and separated lobes: every lighting path runs
    "triple_product": {"level": 2},
    "zh_shadow": {},
    "sh_prt": {"order": 4, "bounces": 0, "rays": 16},
}


@pytest.fixture(scope="module")
def scene():
    return get_scene("sphere_plane", "test")


@pytest.mark.parametrize("kind", ["L", "E"])
@pytest.mark.parametrize("name", sorted(CONFIGS))
def test_lighting_frame_equals_fresh_precompute(scene, name, kind):
    cls = get_method(name)
    assert cls.capabilities.dynamic_lighting
    frames = make_sequence(scene, kind, n_frames=3, seed=1)
    assert all(frames[i].changed == {"light"} for i in (1, 2))
    gbs = [make_gbuffer(scene, f, 1) for f in frames]
    m = cls(**CONFIGS[name])
    m.precompute(scene)
    imgs = [m.render(f, g) for f, g in zip(frames, gbs)]
    last = frames[-1]
    baked = dataclasses.replace(scene, envmap=last.envmap)
    fresh = cls(**CONFIGS[name])
    fresh.precompute(baked)
    want = fresh.render(dataclasses.replace(last, index=0, changed=frozenset({"view", "brdf", "light", "pose"})), gbs[-1])
    scale = want.abs().max()
    assert scale > 0
    assert (imgs[-1] - want).abs().max() <= RTOL * scale, name
    # and the lighting did change the image (the test would be empty otherwise)
    assert (imgs[-1] - imgs[0]).abs().max() > 100 * RTOL * scale
