"""In-out (Mahajan 2008) on every BRDF family it claims, against Mitsuba, region by region.

The example scene ``scenes/examples/two_boxes.toml`` (64², 1389 vertices: a Phong box, a
Cook–Torrance box standing on a Lambert ground) and variants whose blue box is Blinn–Phong or
Torrance–Sparrow. Frame 0 of the V sequence, S = 2 G-buffer samples
per pixel, 256-spp direct-lighting reference (seed 0), default ``InOut()``.

Per material region (pixels whose every G-buffer sample lies on that region): the RMSE against
the reference as a multiple of that region's own noise floor (``references.render.noise_floor``
of the two half renders on the same pixels), pinned with 10 % headroom, and the mean-brightness
ratio method / reference, which must lie in [0.9, 1.1] (a whole-image mean hides a failed region).
Both sides are deterministic (seeded reference, deterministic method).

Before the cosine-weighted factorization (``methods.inout.transport`` docstring, item 1) the blue
Cook–Torrance box rendered at ≈ 1 % of the reference's brightness; before the inward visibility
sample (``transport.visibility_points``) both boxes were ≈ 35 % too dark (their bottom vertices,
in the ground plane, were fully occluded).

Not pinned: a nearly pure-specular Cook–Torrance red box (kd ≈ 0.02, m = 0.25, F0 = 0.05, the
issue's scanned-model material) measured 0.889 of the reference's mean (RMSE 4.3× its floor) with
the default cube_res = 16, K = 56; 0.932 with K = 120 and 0.963 with cube_res = 32 (K = 55) — the
16² cube-map sampling of T and L, not the factorization, which
``test_cosine_norm_captures_cook_torrance_away_from_grazing`` checks for that material.

``python3 -m tests.methods.inout.test_vs_mitsuba`` (from the repository root) prints the table of
these numbers and, for the smoke suite's setting (3 frames, 64 spp), the per-region mean ratios.
"""
from __future__ import annotations

import dataclasses
from functools import lru_cache
from pathlib import Path

import pytest
import torch

from methods.inout import transport as tp
from methods.inout.method import InOut
from scenes.materials import BlinnPhong, CookTorrance, Lambert, Phong, TorranceSparrow

SCENE_FILE = Path(__file__).resolve().parents[3] / "scenes" / "examples" / "two_boxes.toml"
REF_SPP = 256
RATIO_RANGE = (0.9, 1.1)
PIN_HEADROOM = 1.10
# Bilinear look-up of a 64² table (as test_method.LUT_TOL). The 99 %-energy truncation leaves
# ≈ √1 % = 10 % RMS error of cos θo ρ cos θi over the hemispheres; measured 15–17 % relative error
# of ρ itself where both cosines exceed 0.3 (Phong, Blinn–Phong, Torrance–Sparrow, Cook–Torrance).
LUT_TOL = 0.05
LOBE_TOL = 0.2
# Region RMSE / region noise floor, measured with the default InOut() (see the module docstring):
# variant -> region -> pinned multiple. Region floors ≈ 0.017 (boxes), 0.039 (ground). The ground
# (Lambert, K = 1) sits at ≈ 1.9× its floor: the 16² cube map blurs the sun's shadows. Re-pinned when
# the example's meshes were subdivided (one quad per box face and a 9 × 9 ground → 5 × 5 vertices
# per face and 33 × 33; ``subdivide = 2``): red 2.21 → 2.08, blue 1.80 → 1.82 (Blinn–Phong 2.38 →
# 1.88, Torrance–Sparrow 1.92 → 2.01), ground 1.96 → 1.91. Re-pinned when the default n_coeffs
# went 128 → 256: red 2.08 → 1.71, blue 1.82 → 1.83 (Blinn–Phong 1.88 → 1.91, Torrance–Sparrow
# 2.01 → 1.90), ground 1.91 → 1.90.
PINNED = {
    "two_boxes": {"red": 1.71, "blue": 1.83, "ground": 1.90},
    "blue_blinnphong": {"red": 1.71, "blue": 1.91, "ground": 1.90},
    "blue_torrancesparrow": {"red": 1.71, "blue": 1.90, "ground": 1.90},
}
# The blue box's material per variant (None = the file's Cook–Torrance m = 0.3, F0 = 0.04).
BLUE_KD = (0.08, 0.15, 0.45)
VARIANTS = {
    "two_boxes": {},
    "blue_blinnphong": {"blue": BlinnPhong(kd=BLUE_KD, ks=(0.5, 0.5, 0.5), s=60.0)},
    "blue_torrancesparrow": {"blue": TorranceSparrow(kd=BLUE_KD, ks=(0.5, 0.5, 0.5), sigma=0.2)},
}


def load_variant(name: str):
    """The example scene with the variant's materials swapped in."""
    from scenes.scenefile import load_scene_file

    scene = load_scene_file(SCENE_FILE)
    if VARIANTS[name]:
        mats = {**scene.materials, **VARIANTS[name]}
        scene = dataclasses.replace(scene, materials=mats)
    return scene


def region_masks(scene, gb) -> dict[str, torch.Tensor]:
    """(H, W) bool per region: pixels whose every G-buffer sample hit that region."""
    out = {}
    P = gb.num_samples
    for r, name in enumerate(scene.regions):
        one = ((gb.region == r) & gb.hit).float()[:, None].expand(P, 3).contiguous()
        out[name] = gb.resolve(one)[..., 0] > 1.0 - 1e-6
    return out


def region_errors(scene, frame, gb, img: torch.Tensor, ref) -> dict[str, dict[str, float]]:
    """Per region: rmse, floor (its own noise floor), ratio (mean method / mean reference), pixels."""
    from references.metrics import rmse
    from references.render import noise_floor

    cov = torch.as_tensor(ref.coverage, dtype=torch.bool) & gb.coverage.cpu().bool()
    refimg = torch.as_tensor(ref.image).float()
    out = {}
    for name, m in region_masks(scene, gb).items():
        m = m & cov
        if int(m.sum()) == 0:
            continue
        out[name] = {"rmse": rmse(img, refimg, m), "floor": noise_floor(ref.half_a, ref.half_b, m),
                     "ratio": (img[m].mean() / refimg[m].mean()).item(), "pixels": int(m.sum())}
    return out


@lru_cache(maxsize=None)
def measure(name: str, n_frames: int = 1, spp: int = REF_SPP, config: tuple = ()):
    """(per-frame region errors, method.stats) for a variant; frames 0..n_frames−1 of V."""
    from references.gbuffer import make_gbuffer
    from references.render import render_reference
    from scenes.sequences import make_sequence

    scene = load_variant(name)
    frames = make_sequence(scene, "V", n_frames=n_frames, seed=0)
    m = InOut(progress=False, **dict(config))
    m.precompute(scene)
    res = []
    for f in frames:
        f = dataclasses.replace(f, materials=scene.materials)
        gb = make_gbuffer(scene, f, 2)
        ref = render_reference(scene, f, bounces=0, spp=spp, seed=0)
        res.append(region_errors(scene, f, gb, m.render(f, gb), ref))
    return res, m.stats


# -- the factorization in the cosine norm (closed forms and the BRDF itself) ---------------------


def test_lambert_rank_one_in_cosine_norm():
    kd = (0.5, 0.4, 0.3)
    fac = tp.factorize(Lambert(kd=kd), 16, None, norm="cosine")
    assert fac.K == 1
    # ||cos θo ρ cos θi||² = Σ_c (kd_c/π)² (∫ cos² dω)² = Σ_c (kd_c/π)² (2π/3)² = (4/9) Σ kd_c²;
    # the (cos θ, φ) midpoint grid integrates cos² with error 1/(12 n²) relative ~ 3e-4 at n = 16
    assert fac.sigma[0].item() ** 2 == pytest.approx(4 / 9 * sum(k * k for k in kd), rel=2e-3)


def _lut_rel_error(m, fac, R: int = 64, min_cos: float = 0.3) -> float:
    """Relative L² error of Σ_k σ_k h_k(ω_o) ĝ_k(ω_i) (the look-up tables) against ρ(ω_i, ω_o)
    at random direction pairs with both cosines above ``min_cos`` (where the image's light is)."""
    g, sh = tp.nystrom_tables(m, fac, R)
    gen = torch.Generator().manual_seed(1)
    x = torch.nn.functional.normalize(torch.randn(4000, 3, dtype=torch.float64, generator=gen), dim=-1)
    x[:, 2] = x[:, 2].abs()
    x = x[x[:, 2] > min_cos][:1000]
    wi, wo = x[:500], x[500:1000]
    rec = (tp.lut_lookup(sh, wo).view(-1, fac.K, 3) * tp.lut_lookup(g, wi)[..., None]).sum(1)
    true = m.eval(wi, wo)
    return ((rec - true).norm() / true.norm()).item()


def test_cosine_norm_captures_cook_torrance_away_from_grazing():
    # the material: the 99 % rule in the BRDF's own norm spends its terms on the grazing
    # spike of 1/(4 cos θi cos θo) and is ~all wrong away from grazing; in the cosine norm the
    # same rule reconstructs the lobe where the image's light is
    m = CookTorrance(kd=(0.02, 0.01, 0.01), ks=(1.0, 1.0, 1.0), m=0.25, F0=0.05)
    fac_b = tp.factorize(m, 24, None, norm="brdf")
    fac_c = tp.factorize(m, 24, None, norm="cosine")
    err_b, err_c = _lut_rel_error(m, fac_b), _lut_rel_error(m, fac_c)
    assert err_b > 0.9, err_b
    assert err_c < LOBE_TOL, err_c
    assert fac_c.K <= 24 * 24 // 4  # a lobe, not the grid


@pytest.mark.parametrize("m", [Phong(kd=0.2, ks=0.5, s=20.0), BlinnPhong(kd=0.2, ks=0.5, s=40.0),
                               TorranceSparrow(kd=0.2, ks=0.5, sigma=0.3)], ids=lambda m: m.kind)
def test_cosine_norm_reproduces_grid_and_lobe_families(m):
    # K(99 %) in the cosine norm (terms far below it have high-frequency singular vectors that a
    # 64² table does not resolve; test_method.py's Nyström test says the same for the BRDF norm)
    fac = tp.factorize(m, 24, None, norm="cosine")
    g, _ = tp.nystrom_tables(m, fac, 64)
    # ĝ = g / cos θi at the grid nodes (the Nyström identity reproduces the grid); bilinear LUT error
    err = (tp.lut_lookup(g, fac.dirs) - fac.g_hat.T).abs().max()
    assert err < LUT_TOL * fac.g_hat.abs().max()
    assert _lut_rel_error(m, fac) < LOBE_TOL


def test_visibility_points_pull_contact_vertices_off_the_ground():
    from scenes.scenefile import load_scene_file

    scene = load_scene_file(SCENE_FILE)
    geom = scene.geometry()
    V = torch.as_tensor(geom.V).float()
    F = torch.as_tensor(geom.F).long()
    N = torch.nn.functional.normalize(torch.as_tensor(geom.N).float(), dim=-1)
    P = tp.visibility_points(V, F, N)
    box = torch.as_tensor(geom.face_region) != scene.regions.index("ground")
    bv = torch.unique(F[box].reshape(-1))
    side = bv[(N[bv, 1].abs() < 0.5) & (V[bv, 1].abs() < 1e-6)]  # side-face vertices on the ground
    assert side.numel() == 2 * 4 * 5   # 2 boxes × 4 side faces × 5 bottom-edge vertices (subdivide = 2)
    # lifted into their face by INWARD_PULL (1 %) of the way to their faces' mean centroid, about a
    # third of a cell row up (measured 5e-4 to 1.2e-3 here), far above float32 round-off
    assert (P[side, 1] > 1e-4).all()
    assert ((P - V) * N).sum(-1).abs().max() < 1e-6                     # tangential only
    assert (P - V).norm(dim=-1).max() < 0.02 * 1.2                      # 1 % of ≤ 1.2 (face size)


# -- against Mitsuba, per region --------------------------------------------------------------


def test_region_masks_partition_the_covered_pixels():
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    scene = load_variant("two_boxes")
    f = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    gb = make_gbuffer(scene, f, 2)
    masks = region_masks(scene, gb)
    total = sum(m.long() for m in masks.values())
    assert int(total.max()) == 1
    assert all(int(m.sum()) > 50 for m in masks.values())  # every region covers > 1 % of 64²


@pytest.mark.parametrize("name", sorted(VARIANTS))
def test_regions_against_mitsuba(name):
    (res,), stats = measure(name)
    lo, hi = RATIO_RANGE
    for region, e in res.items():
        print(name, region, f"K={stats['regions'][region]['K']}", e)
        assert lo <= e["ratio"] <= hi, (name, region, e)
        pin = PINNED[name][region]
        assert e["rmse"] <= pin * PIN_HEADROOM * e["floor"], (name, region, e, pin)


# Every frame of the example's V, L and E sequences (3 frames each, the smoke suite's), against
# 1024-spp references: the issue-19 criterion, each region's mean within [0.9, 1.1] of the
# reference's. With 128 coefficients per term the red Phong box fell to 0.874 (E frame 2, a
# captured probe) and 0.897 (V frame 2); 256 (the default since) measured [0.964, 1.025] over all
# regions and frames (``methods.inout.transport`` docstring, item 4).
SEQ_SPP = 1024


def test_regions_on_every_frame_of_view_and_lighting_sequences():
    from references.gbuffer import make_gbuffer
    from references.render import render_reference
    from scenes.scenefile import load_scene_file
    from scenes.sequences import make_sequence

    scene = load_scene_file(SCENE_FILE)
    m = InOut(progress=False)
    m.precompute(scene)
    lo, hi = RATIO_RANGE
    seen = {}
    for kind in ("V", "L", "E"):
        for i, f in enumerate(make_sequence(scene, kind, n_frames=3, seed=0)):
            gb = make_gbuffer(scene, f, 2)
            ref = render_reference(scene, f, bounces=0, spp=SEQ_SPP, seed=0)
            for region, e in region_errors(scene, f, gb, m.render(f, gb), ref).items():
                seen[kind, i, region] = round(e["ratio"], 3)
    bad = {k: v for k, v in seen.items() if not lo <= v <= hi}
    assert len(seen) == 27 and not bad, (bad, seen)


def test_k_is_reported_per_region():
    _, stats = measure("two_boxes")
    r = stats["regions"]
    assert r["ground"]["K"] == 1
    # Phong s = 30: eq. 13's 2.5 s = 75, completed to the end of its pair of equal σ_k
    assert r["red"]["K_rule"] == 75 and r["red"]["K"] == 76 and r["red"]["K_source"] == "k_rule"
    assert r["blue"]["K_source"] == "energy99_cosine" and r["blue"]["K"] == r["blue"]["K_energy"] > 4
    for reg in ("red", "blue"):  # K never cuts a degenerate pair (an isotropic BRDF's cos mφ, sin mφ)
        fac = tp.factorize(load_variant("two_boxes").materials[reg], 24, r[reg]["K"] + 1, norm="cosine")
        assert fac.sigma[-1] < (1 - 1e-4) * fac.sigma[-2]
    assert all(v["norm"] == "cosine" for v in r.values())


def _main() -> None:  # pragma: no cover - a report, not a test
    torch.set_num_threads(2)
    print("variant              region  K    pixels  rmse     floor    rmse/floor  ratio")
    for name in sorted(VARIANTS):
        (res,), stats = measure(name)
        for region, e in res.items():
            print(f"{name:20s} {region:7s} {stats['regions'][region]['K']:<4d} {e['pixels']:<7d} "
                  f"{e['rmse']:.4f}   {e['floor']:.4f}   {e['rmse'] / e['floor']:<10.2f}  {e['ratio']:.3f}")
    print("\nsmoke setting (two_boxes, V, 3 frames, 64 spp): per-region mean ratio method/reference")
    for cfg in ((("norm", "brdf"),), ()):
        res, stats = measure("two_boxes", 3, 64, cfg)
        ratios = {r: [f[r]["ratio"] for f in res] for r in res[0]}
        print(dict(cfg) or "default", {r: f"{min(v):.3f}..{max(v):.3f}" for r, v in ratios.items()},
              "K", {r: s["K"] for r, s in stats["regions"].items()})


if __name__ == "__main__":  # pragma: no cover
    _main()
