"""Reference renders: determinism, halves, bounce settings, noise floor statistics."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from references.metrics import rmse
from references.render import half_seeds, max_depth_for, noise_floor, render_reference

# Noise-floor statistics on a Lambert/overcast scene (near-Gaussian pixel noise, 32×32 px × 3
# channels ≈ 3000 terms): one floor estimate has a relative s.d. of ~3 %, a ratio of two ~4 %
# (measured over 8 seeds: 0.475–0.524 for a 4× spp step). 0.1 absolute is > 3 s.d.
RATIO_TOL = 0.1
# RMSE(image, high-spp image) / predicted sqrt(floor² + floor_hi²): measured 0.95–1.03 over 8 seeds.
PREDICT_TOL = 0.15


def _small(W=16, H=16):
    from scenes.library import get_scene

    sc = get_scene("sphere_plane", "test")
    return sc.replace(camera=dataclasses.replace(sc.camera, width=W, height=H))


@pytest.fixture(scope="module")
def smooth_scene():
    """sphere_plane geometry, Lambert materials, overcast sky: light-tailed Monte Carlo noise."""
    from scenes.envmap import EnvMap
    from scenes.materials import Lambert

    sc = _small(32, 32)
    return sc.replace(envmap=EnvMap.procedural("overcast", height=32),
                      materials={"sphere": Lambert((0.7, 0.5, 0.3)), "plane": Lambert(0.5)})


def test_max_depth_and_seeds():
    assert [max_depth_for(b) for b in (0, 1, 2, None)] == [2, 3, 4, -1]
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError):
            max_depth_for(bad)
    seen = set()
    for s in range(50):
        a, b = half_seeds(s)
        assert a != b
        seen |= {a, b}
    assert len(seen) == 100


@pytest.mark.parametrize("bounces", [0, None])
def test_same_seed_identical_bits_different_seed_differs(bounces):
    sc = _small()
    fr = sc.default_frame()
    r1 = render_reference(sc, fr, bounces=bounces, spp=8, seed=1, use_cache=False)
    r2 = render_reference(sc, fr, bounces=bounces, spp=8, seed=1, use_cache=False)
    r3 = render_reference(sc, fr, bounces=bounces, spp=8, seed=2, use_cache=False)
    assert torch.equal(r1.image, r2.image) and torch.equal(r1.half_a, r2.half_a)
    assert not torch.equal(r1.image, r3.image)
    assert not torch.equal(r1.half_a, r1.half_b)  # the halves are independent renders
    assert torch.equal(r1.image, 0.5 * (r1.half_a + r1.half_b))
    assert r1.image.shape == (16, 16, 3) and r1.image.dtype == torch.float32
    assert torch.isfinite(r1.image).all() and (r1.image >= 0).all()
    assert r1.meta["max_depth"] == max_depth_for(bounces) and r1.meta["spp"] == 8 and r1.meta["seed"] == 1
    assert r1.meta["from_cache"] is False
    for k in ("mitsuba", "variant", "scene_hash", "frame_key", "render_seconds", "threads"):
        assert k in r1.meta


def test_coverage_matches_gbuffer_and_floor_definition():
    from references.gbuffer import make_gbuffer

    sc = _small(12, 10)
    # aim the camera partly at the sky so coverage is not trivial
    sc = sc.replace(camera=dataclasses.replace(sc.camera, target=(0.0, 3.0, 0.0)))
    fr = sc.default_frame()
    r = render_reference(sc, fr, bounces=0, spp=4, use_cache=False, spp_side=3)
    gb = make_gbuffer(sc, fr, 3)
    cov = gb.coverage
    assert torch.equal(r.coverage, cov) and cov.any() and not cov.all()
    assert r.noise_floor == pytest.approx(rmse(r.half_a, r.half_b, cov) / 2, rel=1e-12)
    # hide_emitters: pixels whose sub-samples all see the sky are black
    sky = ~gb.hit.view(10, 12, 9).any(-1)
    assert sky.any() and (r.image[sky] == 0).all()


def test_indirect_light_adds_energy(smooth_scene):
    fr = smooth_scene.default_frame()
    d = render_reference(smooth_scene, fr, bounces=0, spp=32, use_cache=False)
    g = render_reference(smooth_scene, fr, bounces=None, spp=32, use_cache=False)
    m = d.coverage
    # The mean over ~3000 values has a standard error ≈ floor/sqrt(3000); the bounce light on
    # the plane near the sphere is far larger.
    gain = float((g.image[m] - d.image[m]).mean())
    assert gain > 10 * (d.noise_floor + g.noise_floor) / math.sqrt(int(m.sum()) * 3)


def test_noise_floor_scales_with_spp_and_predicts_the_error(smooth_scene):
    fr = smooth_scene.default_frame()
    r16 = render_reference(smooth_scene, fr, bounces=0, spp=16, seed=3, use_cache=False)
    r32 = render_reference(smooth_scene, fr, bounces=0, spp=32, seed=4, use_cache=False)
    # Variance ∝ 1/spp: doubling spp divides the floor by √2.
    assert r32.noise_floor / r16.noise_floor == pytest.approx(1 / math.sqrt(2), abs=RATIO_TOL)
    # The floor estimates the image's own RMSE against the noise-free image: compare with a
    # high-spp render (its own floor adds in quadrature).
    hi = render_reference(smooth_scene, fr, bounces=0, spp=1024, seed=5, use_cache=False)
    actual = rmse(r16.image, hi.image, r16.coverage)
    predicted = math.sqrt(r16.noise_floor ** 2 + hi.noise_floor ** 2)
    assert actual / predicted == pytest.approx(1.0, abs=PREDICT_TOL)


def test_noise_floor_edge_cases_and_validation():
    z = torch.zeros(4, 4, 3)
    assert math.isnan(noise_floor(z, z, torch.zeros(4, 4, dtype=torch.bool)))
    assert noise_floor(z, z + 2.0, torch.ones(4, 4, dtype=torch.bool)) == pytest.approx(1.0)
    sc = _small(8, 8)
    fr = sc.default_frame()
    for kw in (dict(spp=3), dict(spp=0), dict(seed=-1), dict(spp_side=0)):
        args = dict(bounces=0, spp=4, use_cache=False) | kw
        with pytest.raises(ValueError):
            render_reference(sc, fr, **args)


def test_render_time_split_excludes_kernel_compilation():
    """A reference records its time split (``render_halves``): scene export and load, Dr.Jit's kernel
    compilation, and the two renders without it (``frame_seconds``: what the equal-error speedup
    charges Mitsuba, `reports.backend.reference_seconds`). A material value no kernel has seen before
    (literal parameters: a VB frame's perturbed BRDFs) compiles new kernels, counted as compilation.
    The parts add up to the total."""
    import random

    from reports.backend import reference_seconds
    from scenes.materials import Lambert

    sc = _small(8, 8)
    kd = 0.3 + 0.4 * random.random()   # a value no earlier run compiled: the kernels are new
    sc = sc.replace(materials={"sphere": Lambert((kd, 0.5, 0.3)), "plane": Lambert(0.5)})
    first = render_reference(sc, sc.default_frame(), bounces=0, spp=2, seed=0, use_cache=False).meta
    assert first["load_seconds"] > 0 and first["frame_seconds"] > 0 and first["compile_seconds"] > 0
    assert (first["load_seconds"] + first["compile_seconds"] + first["frame_seconds"]
            == pytest.approx(first["render_seconds"], rel=1e-6))
    # (the same scene loaded again usually compiles nothing, but not always: in ~1 of 3 fresh
    # processes its second load compiled a kernel of 2322 IR operations instead of 2319 — counted
    # as compilation too, whatever Mitsuba's reason)
    assert reference_seconds(type("R", (), {"meta": first})()) == first["frame_seconds"]
    assert reference_seconds(type("R", (), {"meta": {"render_seconds": 1.0}})()) is None  # recorded before the split
