"""SH PRT (Sloan 2002) against Mitsuba references: error falls with the order n, regression pins on
every library scene, interreflection adds the references' indirect light.

Setting: frame 0 of the V sequence, test size (64², S = 2 G-buffer samples per pixel), 256-spp
references (seed 0, cached under $PRTBENCH_CACHE), default config (order 5, 256 rays per vertex,
seed 0) precomputed with bounces 0 unless stated. RMSE measured with 1 thread (2026-12-02):

    scene          floor   RMSE     ×floor  note
    sphere_plane   0.0511  0.4965   9.7     sharp sun + s = 40 Phong sphere: far beyond order 5
    chess (BP)     0.0134  0.0610   4.6     Cook-Torrance "black" → Blinn-Phong s = 2/m² − 2 (see below)
    alcove         0.0104  0.0228   2.2
    shadow_detail  0.0139  0.1017   7.3     window light + thin occluders: low-order shadows blur
    creature       0.0343  0.0882   2.6
    bunny          0.0206  0.1766   8.6     `sunrise` probe (sun ≈ 2000× the mean): order 8 → 0.110, 10 → 0.079
    dragon         0.0210  0.0543   2.6     Blinn-Phong s = 80 through the Phong approximation
    character      0.0271  0.0430   1.6
    alcove b = 1   0.0107  0.0247   2.3     (against the one-bounce reference)
    alcove b = 2   0.0106  0.0264   2.5     (against the two-bounce reference)

The library chess scene has a Cook-Torrance region, which this method does not support (n/a in the
harness, `test_method.test_registered_with_its_capabilities`); it is pinned here with that region
replaced by the Blinn-Phong lobe of the same Beckmann roughness (s = 2/m² − 2, Walter et al. 2007).
"""
from __future__ import annotations

import pytest

from methods.sh_prt.method import SHPRT
from references.gbuffer import make_gbuffer
from references.metrics import rmse
from references.render import render_reference
from scenes.library import SCENES, get_scene
from scenes.materials import BlinnPhong
from scenes.sequences import make_sequence

# RMSE (bounces 0) per library scene (module docstring).
PINNED = {"sphere_plane": 0.4965, "chess": 0.0610, "alcove": 0.0228, "shadow_detail": 0.1017, "creature": 0.0882,
          "bunny": 0.1766, "dragon": 0.0543, "character": 0.0430}
PINNED_BOUNCES = {1: 0.0247, 2: 0.0264}  # alcove
# Room for float/BLAS differences between machines in a deterministic pipeline (same seeds).
SLACK = 1.05
# Error vs order on sphere_plane (n = 3, 5, 8): measured 0.6131, 0.4965, 0.2960.
PINNED_ORDERS = {3: 0.6131, 5: 0.4965, 8: 0.2960}


def _scene(name: str):
    scene = get_scene(name, "test")
    if name == "chess":
        b = scene.materials["black"]
        scene = scene.replace(materials={**scene.materials,
                                         "black": BlinnPhong(kd=b.kd, ks=b.ks, s=2.0 / b.m**2 - 2.0)})
    return scene


def _setup(scene, bounces=0):
    frame = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    gb = make_gbuffer(scene, frame, 2)
    refs = {b: render_reference(scene, frame, bounces=b, spp=256, seed=0) for b in range(bounces + 1)}
    return frame, gb, refs


def test_every_library_scene_is_pinned():
    assert set(PINNED) == set(SCENES)


@pytest.mark.parametrize("name", sorted(PINNED))
def test_error_against_mitsuba_per_scene(name):
    scene = _scene(name)
    frame, gb, refs = _setup(scene)
    m = SHPRT(bounces=0)
    m.precompute(scene)
    ref = refs[0]
    mask = ref.coverage & gb.coverage
    err = rmse(m.render(frame, gb), ref.image, mask)
    print(name, "floor", ref.noise_floor, "rmse", err, "x floor", err / ref.noise_floor)
    assert err <= SLACK * PINNED[name], (err, PINNED[name])
    assert err > ref.noise_floor  # the pin is a real error, not reference noise


def test_error_falls_as_the_order_grows():
    scene = get_scene("sphere_plane", "test")
    frame, gb, refs = _setup(scene)
    mask = refs[0].coverage & gb.coverage
    err = {}
    for n in sorted(PINNED_ORDERS):
        m = SHPRT(order=n, bounces=0)
        m.precompute(scene)
        err[n] = rmse(m.render(frame, gb), refs[0].image, mask)
    print("sphere_plane error vs order", err)
    assert err[3] > err[5] > err[8]
    for n, pin in PINNED_ORDERS.items():
        assert err[n] <= SLACK * pin, (n, err[n], pin)


def test_interreflections_against_the_bounce_references():
    """alcove: pins against the 1- and 2-bounce references, and the light each pass ADDS matches
    the references' added light: measured −5 % (pass 1: 0.0236 vs 0.0249) and −11 % (pass 2: 0.0048
    vs 0.0054) — order-5 truncation of the bounced transfer and 256-ray quadrature."""
    scene = get_scene("alcove", "test")
    frame, gb, refs = _setup(scene, bounces=2)
    m = SHPRT(bounces=2)
    m.precompute(scene)
    mask = refs[0].coverage & gb.coverage
    imgs = [m.with_bounces(b).render(frame, gb) for b in range(3)]
    for b, pin in PINNED_BOUNCES.items():
        err = rmse(imgs[b], refs[b].image, mask)
        print("alcove bounces", b, "floor", refs[b].noise_floor, "rmse", err)
        assert err <= SLACK * pin, (b, err, pin)
    for b, tol in ((1, 0.10), (2, 0.20)):
        ours = float((imgs[b] - imgs[b - 1])[mask].mean())
        theirs = float((refs[b].image - refs[b - 1].image)[mask].mean())
        print("alcove: added by pass", b, ours, theirs)
        assert abs(ours - theirs) <= tol * theirs, (b, ours, theirs)


# sphere_plane, pass 1: the plane receives the Phong sphere's glossy reflection (hit points send
# k_s Σ G_l y(R_y)·M l back). Measured added light 0.0578 vs the reference's 0.0573 (+0.9 %); with
# the hit points' diffuse reflection only it was 0.0488 (−15 %).
ADDED_GLOSSY_TOL = 0.05


def test_bounce_carries_the_glossy_reflection_of_hit_points():
    scene = get_scene("sphere_plane", "test")
    frame, gb, refs = _setup(scene, bounces=1)
    m = SHPRT(bounces=1)
    m.precompute(scene)
    mask = refs[0].coverage & gb.coverage
    ours = float((m.render(frame, gb) - m.with_bounces(0).render(frame, gb))[mask].mean())
    theirs = float((refs[1].image - refs[0].image)[mask].mean())
    print("sphere_plane: added by pass 1", ours, theirs)
    assert abs(ours - theirs) <= ADDED_GLOSSY_TOL * theirs, (ours, theirs)


# bunny, lighting-only sequence L (seed 0): the `sunrise` probe rotates about a tilted axis until its
# sun (≈ 2000× the mean radiance) sets below the ground. Order-5 SH of the sun rings over the whole
# sphere: the sanity gate (reports.gate, region means within [0.67, 1.5] × the reference's) flags
# the 64-spp smoke cell "suspect". Measured region-mean ratios (min, max), frames 0 / 1 / 2:
#   order 5:  (0.806, 1.006) / (0.979, 2.000) / (0.666, 1.100)
#   order 10: (0.931, 0.964) / (0.916, 1.182) / (0.951, 0.965)
# — the SH truncation the method is known for, not a wrong lighting rotation (test_method's L test).
BUNNY_L_RATIOS = {5: [(0.806, 1.006), (0.979, 2.000), (0.666, 1.100)],
                  10: [(0.931, 0.964), (0.916, 1.182), (0.951, 0.965)]}
RATIO_TOL = 0.01


def test_sun_probe_ringing_at_order_5_is_the_gates_suspect_and_order_10_cures_it():
    from reports.gate import RATIO_HI, RATIO_LO, frame_sanity, pixel_regions

    scene = get_scene("bunny", "test")
    frames = make_sequence(scene, "L", n_frames=3, seed=0)
    ms = {n: SHPRT(order=n, bounces=0) for n in BUNNY_L_RATIOS}
    for m in ms.values():
        m.precompute(scene)
    for i, f in enumerate(frames):
        gb = make_gbuffer(scene, f, 2)
        ref = render_reference(scene, f, bounces=0, spp=64, seed=0)
        mask = ref.coverage & gb.coverage
        regs = pixel_regions(gb.region, gb.height, gb.width)
        for n, m in ms.items():
            s = frame_sanity(m.render(f, gb), ref.image, mask, regs)
            got = (s["region_mean_ratio_min"], s["region_mean_ratio_max"])
            print("bunny L frame", i, "order", n, got)
            assert all(abs(g - w) <= RATIO_TOL for g, w in zip(got, BUNNY_L_RATIOS[n][i])), (i, n, got)
            if n == 10:
                assert RATIO_LO <= got[0] and got[1] <= RATIO_HI
            if n == 5 and i == 1:
                assert got[1] > RATIO_HI           # what the gate saw
