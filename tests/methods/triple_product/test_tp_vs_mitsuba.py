"""Triple product (Ma 2006) against Mitsuba's direct-lighting reference on every library scene, in
both shading modes (§3.3): the regression test per rendered scene and shading mode.

Default config (level 3 = 1280 coefficients, all kept, 8×16 BRDF directions, 17×32 lighting grid,
trilinear look-up), frame 0 of the V sequence, test size (64²), S = 2 G-buffer samples per pixel;
RMSE against a 256-spp reference (seed 0), measured with 1 thread:

    scene          floor   mean    per-vertex  per-pixel
    sphere_plane   0.051   0.893   0.2794      0.1654    (sharp sun on an s = 40 Phong sphere)
    chess          0.012   0.224   0.0633      0.0592
    alcove         0.010   0.146   0.0229      0.0220
    shadow_detail  0.014   0.475   0.1104      0.0538    (thin occluders: vertex visibility blurs)
    creature       0.034   0.831   0.0861      0.0768
    bunny, dragon, character: PINNED below

Re-pinned (2026-12-03) when the lighting projection began prefiltering the env map to two samples
per texel (``lighting.prefiltered``: a few-texel sun aliased; the bench bunny's ground was at 0.63
of the reference): bunny 0.1461 / 0.1002 → 0.1376 / 0.0848, creature 0.0890 / 0.0800 → 0.0858 /
0.0766, chess and shadow_detail slightly better, alcove, dragon and character within 2 %, and
sphere_plane 0.2819 / 0.1679 → 0.2864 / 0.1781 — the procedural sun blurred over the prefiltered
5.6° texels on the s = 40 highlight, the price of not aliasing it.

Re-pinned (2026-12-03, session 9) when ``light_supersample`` became 2 (16 samples per fine triangle,
1.4° apart; the map is then prefiltered only where its texels are finer than 2.7°, i.e. not at all
for the 64 × 128 test-size probes). With 4 samples and the 5.6° prefilter, the box blur spread a
sun 10.4° below the ground's horizon (the smoke suite's bunny L frame 1) over triangles above it: the
bunny came out at 1.51× the reference (the sanity gate's `suspect`); the converged projection
(s = 2 and s = 3 agree: 1.297 / 1.296) gives 1.30×, the level-3 basis' own limit. Moves: sphere_plane
0.2864 / 0.1781 → 0.2794 / 0.1654 (its sun no longer blurred), bunny 0.1376 / 0.0848 → 0.1412 /
0.0932 (per-pixel 10 % worse on this V frame: the wider blur had smoothed the sharp sunrise sun that
the level-3 basis cannot resolve — a lucky cancellation, not the method), every other scene within
1 %. Cost: the lighting projection of a lighting change takes ≈ 1.8× as long (bench bunny, 544 grid
frames: 1.8 → 3.2 s at load 8).

The residual above the floor is the level-3 piecewise-constant basis (a 1280-triangle sphere:
≈ 5.6° per triangle) against sharp suns and lobes; per-pixel shading beats per-vertex shading on
every scene at the same vertex count (Ma 2006 §3.3, Fig. 9's point).
"""
from __future__ import annotations

import pytest

from methods.triple_product import TripleProduct
from references.gbuffer import make_gbuffer
from references.metrics import rmse
from references.render import render_reference
from scenes.library import SCENES, get_scene
from scenes.sequences import make_sequence

PINNED = {"sphere_plane": (0.2794, 0.1654), "chess": (0.0633, 0.0592), "alcove": (0.0229, 0.0220),
          "shadow_detail": (0.1104, 0.0538), "creature": (0.0861, 0.0768),
          "bunny": (0.1412, 0.0932), "dragon": (0.0606, 0.0345), "character": (0.0388, 0.0343)}
# Room for float/BLAS differences between machines in a deterministic pipeline (same seeds).
SLACK = 1.05


def test_every_library_scene_is_pinned():
    assert set(PINNED) == set(SCENES)


@pytest.mark.parametrize("name", sorted(PINNED))
def test_error_against_mitsuba_per_scene_and_shading_mode(name):
    scene = get_scene(name, "test")
    frame = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    gb = make_gbuffer(scene, frame, 2)
    ref = render_reference(scene, frame, bounces=0, spp=256, seed=0)
    mask = ref.coverage & gb.coverage
    err = {}
    for shading in ("vertex", "pixel"):
        m = TripleProduct(shading=shading)
        m.precompute(scene)
        err[shading] = rmse(m.render(frame, gb), ref.image, mask)
    print(name, "floor", ref.noise_floor, err)
    for shading, pinned in zip(("vertex", "pixel"), PINNED[name]):
        assert err[shading] <= SLACK * pinned, (shading, err[shading], pinned)
    assert err["pixel"] < err["vertex"], err
