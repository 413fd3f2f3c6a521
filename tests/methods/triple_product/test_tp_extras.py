"""Triple-product extras (Ma 2006 §3.3 visibility textures, §5 spatially varying BRDF and bump
mapping) against closed forms, exact identities and the brute-force oracle.

Measured (level 3, 64×64 film, S = 1; `python -m pytest -q tests/methods/triple_product/test_tp_extras.py`):
  visibility textures, floor pixels vs a 64+64-sample oracle pair (floor noise of the mean of two):
    sphere_plane / sky_sun (noise 0.066): vertex visibility 0.107, 64² texture 0.072, 128² 0.069
    shadow_detail / window (noise 0.021): vertex visibility 0.044, 64² texture 0.025
    (sphere_plane 64²: 4096 texels, 2 × 20 MB idx/val untruncated at K = 1280 vs 2 × 6.5 MB for
    the 1267 vertices).
  SBRDF w = 0.5 on the sphere_plane floor vs a 16+16 oracle pair on the mixture material
  (overcast): RMSE 0.0286, floor 0.0279, mean 0.320 (material a alone: 0.093).
  Bump map (max tilt 29°) on an unoccluded plane vs a 32+32 oracle pair shading the same perturbed
  normals (overcast): RMSE 0.0202, floor 0.0193, mean 0.363; the un-bumped render: 0.069.
"""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from methods.registry import get_method
from methods.triple_product import TripleProduct
from methods.triple_product import textures as tx
from methods.triple_product.precompute import texel_points
from references.gbuffer import make_gbuffer
from references.metrics import rmse
from scenes import procedural as P
from scenes.camera import Camera
from scenes.envmap import procedural
from scenes.library import get_scene
from scenes.materials import Lambert, Phong
from scenes.scene import Scene, Shape
from scenes.sequences import make_sequence

# Float32 agreement of two evaluations of the same sums in different orders.
F32_ATOL = 1e-5
# Allowed bias vs the oracle relative to the mean radiance (the level-3 piecewise-constant grid:
# measured ≈ 2 % in test_tp_method.py; 4 % leaves room for the uncertainty of the estimate).
BIAS_REL = 0.04
# Noise floors are estimated from one pair of images (~1–4K pixels): ±10 %.
FLOOR_SLACK = 1.1
# Visibility textures must remove at least this fraction of the vertex-visibility bias on the
# floor (measured: bias² = err² − floor² falls from 0.0072 to 0.0009, i.e. by 88 %).
VIS_TEX_BIAS_GAIN = 0.5
# A non-trivial bump must change the image by more than this fraction of the mean radiance
# (measured 18 %: max tilt 29°), and the un-bumped image must be this many times further from the
# bumped oracle than the bumped render is (measured 0.069 vs 0.020).
BUMP_CHANGE_REL = 0.1
BUMP_DISCRIMINATES = 2.0
# Small configuration for the exact-identity tests (identities hold at any resolution).
SMALL = dict(level=2, brdf_dirs=(5, 8), frame_grid=(5, 8, 1))


def _oracle(scene, frame, gb, seed, n):
    o = get_method("oracle")(light_samples=n, brdf_samples=n, seed=seed)
    o.precompute(scene)
    return o.render(frame, gb)


def _oracle_pair(scene, frame, gb, n, mask, seeds=(1, 2)):
    o1, o2 = (_oracle(scene, frame, gb, s, n) for s in seeds)
    return (o1 + o2) / 2, rmse(o1, o2, mask) / 2  # mean of two, its noise floor


def _region_mask(gb, region: int):
    return gb.coverage & (gb.region.view(gb.height, gb.width, -1) == region).all(-1)


def _plane_scene(uv_scale=1.0, uv_offset=0.0, *, film=24, material=None):
    """An unoccluded 4×4 plane (4×4 cells) under `overcast`; UVs affinely remapped."""
    m = P.plane((4.0, 4.0), (4, 4))
    m = P.Mesh(m.V, m.F, m.N, m.uv * uv_scale + uv_offset).validate()
    cam = Camera((0.0, 3.0, 2.5), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 50.0, film, film)
    mat = material or Phong(kd=(0.3, 0.3, 0.25), ks=(0.3, 0.3, 0.3), s=10.0)
    return Scene("plane_only", [Shape("plane", "plane", m)], ["plane"], cam,
                 procedural("overcast", height=32), {"plane": mat})


def _frame(scene, **kw):
    return dataclasses.replace(make_sequence(scene, "V", n_frames=1, seed=0)[0], **kw)


# -- pure texture functions -------------------------------------------------------------------


def test_bilinear_reproduces_linear_ramp_and_gradient():
    H, W = 5, 7
    c = tx.texel_centres(H, W, dtype=torch.float64)
    tex = (2.0 * c[:, 0] - 3.0 * c[:, 1] + 0.5).view(H, W)  # linear in (u, v): bilinear is exact
    uv = torch.rand(200, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    inside = ((uv[:, 0] >= 0.5 / W) & (uv[:, 0] <= 1 - 0.5 / W) & (uv[:, 1] >= 0.5 / H) & (uv[:, 1] <= 1 - 0.5 / H))
    uv = uv[inside]
    torch.testing.assert_close(tx.bilinear(tex, uv), 2.0 * uv[:, 0] - 3.0 * uv[:, 1] + 0.5)
    g = tx.bilinear_gradient(tex, uv)
    torch.testing.assert_close(g, torch.tensor([2.0, -3.0], dtype=torch.float64).expand_as(g))
    # at texel centres the look-up returns the texel itself; outside it clamps to the edge
    torch.testing.assert_close(tx.bilinear(tex, c), tex.reshape(-1))
    far = torch.tensor([[-0.5, 0.5], [1.5, 0.5]], dtype=torch.float64)
    torch.testing.assert_close(tx.bilinear(tex, far), tx.bilinear(tex, far.clamp(0.5 / W, 1 - 0.5 / W)))
    assert (tx.bilinear_gradient(tex, far)[:, 0] == 0).all()


def test_rasterize_uv_covers_plane_and_recovers_points():
    m = P.plane((4.0, 2.0), (3, 2))
    res = 16
    texel, face, pts, nrm = texel_points(m.V, m.N, m.F, m.uv, res)
    assert texel.numel() == res * res  # the UV square is fully covered by the plane's triangles
    # the UV map of `plane` is affine: texel centre (u, v) ↦ p = corner + u·Pu + v·Pv
    dpdu, dpdv, ok = tx.uv_jacobian(m.V, m.F, m.uv)
    assert ok.all() and torch.allclose(dpdu, dpdu[:1].expand_as(dpdu), atol=1e-5)
    c = tx.texel_centres(res, res)[texel]
    p0 = m.V[(m.uv.norm(dim=1) == 0).nonzero()[0, 0]]
    torch.testing.assert_close(pts, p0 + c[:, :1] * dpdu[0] + c[:, 1:] * dpdv[0], atol=1e-5, rtol=0)
    torch.testing.assert_close(nrm, torch.tensor([0.0, 1.0, 0.0]).expand_as(nrm))
    # a chart covering only [0.25, 0.75]² leaves the other texels uncovered
    face2, _ = tx.rasterize_uv(m.uv * 0.5 + 0.25, m.F, res, res)
    cov = (face2 >= 0).view(res, res)
    assert cov[4:12, 4:12].all() and cov.sum() == 64


def test_perturb_normals_closed_form_tilt():
    # plane y = 0, ∂p/∂u = (a, 0, 0), ∂p/∂v = (0, 0, b) (UV orientation opposite to +Y: σ = −1),
    # height h = c·u, scale s: the displaced surface y = s c x / a has normal ∝ (−s c / a, 1, 0)
    a, b, c, s = 2.0, 3.0, 0.7, 0.5
    n = torch.tensor([[0.0, 1.0, 0.0]], dtype=torch.float64)
    out = tx.perturb_normals(n, torch.tensor([[a, 0.0, 0.0]], dtype=torch.float64),
                             torch.tensor([[0.0, 0.0, b]], dtype=torch.float64),
                             torch.tensor([[c, 0.0]], dtype=torch.float64), s)
    want = torch.nn.functional.normalize(torch.tensor([[-s * c / a, 1.0, 0.0]], dtype=torch.float64), dim=-1)
    torch.testing.assert_close(out, want)
    # h = c·v: normal ∝ (0, 1, −s c / b); no UV map (zero Jacobian): unchanged
    out = tx.perturb_normals(n, torch.tensor([[a, 0.0, 0.0]], dtype=torch.float64),
                             torch.tensor([[0.0, 0.0, b]], dtype=torch.float64),
                             torch.tensor([[0.0, c]], dtype=torch.float64), s)
    torch.testing.assert_close(out, torch.nn.functional.normalize(
        torch.tensor([[0.0, 1.0, -s * c / b]], dtype=torch.float64), dim=-1))
    z = torch.zeros(1, 3, dtype=torch.float64)
    torch.testing.assert_close(tx.perturb_normals(n, z, z, torch.tensor([[c, c]], dtype=torch.float64), s), n)


# -- visibility textures ----------------------------------------------------------------------


def test_visibility_texture_equals_vertex_visibility_on_unoccluded_plane():
    # UVs in [0.1, 0.9]²: the border texels are uncovered, so this also proves they do not leak
    # (an uncovered tap kept with weight > 0 would darken the image edges)
    scene = _plane_scene(0.8, 0.1)
    frame = _frame(scene)
    gb = make_gbuffer(scene, frame, 1)
    base = TripleProduct(**SMALL)
    base.precompute(scene)
    m = TripleProduct(**SMALL, vis_texture=10)
    m.precompute(scene)
    nv = m.n_vertex_rows
    assert m.stats["texels"] == 64  # 8 × 8 covered centres of the 10 × 10 texture
    torch.testing.assert_close(m.V_val[nv:], m.V_val[:1].expand(64, -1))  # the same hemisphere
    rows, w = m.visibility_blend(gb)
    hit = gb.hit
    assert (rows[hit] >= nv).any(1).all()  # every sample is shaded from the texture
    torch.testing.assert_close(w[hit].sum(1), torch.ones(int(hit.sum())))
    img = m.render(frame, gb)
    torch.testing.assert_close(img, base.render(frame, gb), atol=F32_ATOL, rtol=1e-5)
    mem = m.memory()
    assert mem["vis_texture_val"] == 64 * m.K * 4 and mem["visibility_val"] == nv * m.K * 4


def test_visibility_texture_taps_stay_on_their_chart():
    # a box's six faces share the UV square (overlapping charts): taps from another face must be
    # dropped (distance / normal check), never blended into this face's visibility
    box = P.box((1.0, 1.0, 1.0), (0.0, 0.5, 0.0), n=1)
    scene = Scene("box", [Shape("box", "box", box), Shape("floor", "floor", P.plane((6.0, 6.0), (2, 2)))],
                  ["box", "floor"], Camera((2.0, 2.5, 3.0), (0.0, 0.4, 0.0), (0.0, 1.0, 0.0), 45.0, 24, 24),
                  procedural("overcast", height=32), {"box": Lambert(0.5), "floor": Lambert(0.5)})
    frame = _frame(scene)
    gb = make_gbuffer(scene, frame, 1)
    m = TripleProduct(level=1, brdf_dirs=(3, 4), frame_grid=(3, 4, 1), vis_texture=8)
    m.precompute(scene)
    rows, w = m.visibility_blend(gb)
    nv = m.n_vertex_rows
    used = gb.hit[:, None] & (w > 0) & (rows >= nv)
    s, k = used.nonzero(as_tuple=True)
    assert s.numel() > 0
    tn = m.tex_nrm[rows[s, k] - nv]
    assert ((tn * gb.normal[s]).sum(-1) > 0.99).all()  # same face (box faces are 90° apart)


def test_visibility_texture_sharpens_floor_shadow_vs_oracle():
    scene = get_scene("sphere_plane", "test")  # coarse floor, sky_sun: a sharp sphere shadow
    frame = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    gb = make_gbuffer(scene, frame, 1)
    mask = _region_mask(gb, scene.regions.index("plane"))
    ref, floor = _oracle_pair(scene, frame, gb, 64, mask)
    errs = {}
    for vt in (None, 64):
        m = TripleProduct(level=3, frame_grid=(9, 16, 1), vis_texture=vt)
        m.precompute(scene)
        errs[vt] = rmse(m.render(frame, gb), ref, mask)
    bias2 = {k: max(e ** 2 - floor ** 2, 0.0) for k, e in errs.items()}
    assert errs[64] < errs[None], (errs, floor)  # measured 0.072 vs 0.107 (floor 0.066)
    assert bias2[64] <= (1 - VIS_TEX_BIAS_GAIN) * bias2[None], (errs, floor)


def test_vis_texture_config_validated():
    for cfg in (dict(vis_texture=0), dict(vis_texture=2.5), dict(vis_texture=True),
                dict(vis_texture=16, shading="vertex")):
        with pytest.raises(ValueError):
            TripleProduct(**cfg)


# -- spatially varying BRDF -------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class _Mix:
    """(f_a + f_b)/2 with the matching sampling mixture: what the oracle needs from a material is
    eval, sample and pdf (not a registered `Material` kind, so it stays local to this test)."""

    a: Material
    b: Material

    def eval(self, wi, wo):
        return 0.5 * (self.a.eval(wi, wo) + self.b.eval(wi, wo))

    def pdf(self, wi, wo):
        return 0.5 * (self.a.pdf(wi, wo) + self.b.pdf(wi, wo))

    def sample(self, wo, u):
        pick_a = u[..., 0] < 0.5
        u2 = torch.stack([torch.where(pick_a, 2 * u[..., 0], 2 * u[..., 0] - 1).clamp(0, 1 - 1e-7), u[..., 1]], -1)
        wa, _ = self.a.sample(wo, u2)
        wb, _ = self.b.sample(wo, u2)
        wi = torch.where(pick_a[..., None], wa, wb)
        return wi, self.pdf(wi, wo)


B_MAT = Phong(kd=(0.1, 0.2, 0.45), ks=(0.4, 0.4, 0.4), s=20.0)


@pytest.fixture(scope="module")
def sp():
    scene = get_scene("sphere_plane", "test")
    frame = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    frame = dataclasses.replace(frame, envmap=procedural("overcast", height=32))
    return scene, frame, make_gbuffer(scene, frame, 1)


def test_blend_extremes_and_half_reproduce_single_material_renders(sp):
    scene, frame, gb = sp
    m = TripleProduct(**SMALL)
    m.precompute(scene)
    img_a = m.render(frame, gb)
    scene_b = scene.replace(materials={**scene.materials, "plane": B_MAT})
    mb = TripleProduct(**SMALL)
    mb.precompute(scene_b)
    img_b = mb.render(dataclasses.replace(frame, materials=scene_b.materials), gb)
    m.set_blend("plane", B_MAT, torch.zeros(4, 4))
    torch.testing.assert_close(m.render(frame, gb), img_a, atol=F32_ATOL, rtol=0)
    m.set_blend("plane", B_MAT, torch.ones(3, 5))
    torch.testing.assert_close(m.render(frame, gb), img_b, atol=F32_ATOL, rtol=0)
    w = torch.zeros(8, 8)
    w[:, 4:] = 1.0  # u ≥ ½ material b, u < ½ material a
    m.set_blend("plane", B_MAT, w)
    mix = m.blend_weights(gb).view(gb.height, gb.width, 1)  # S = 1: one sample per pixel
    plane = (gb.region == scene.regions.index("plane")).view(gb.height, gb.width)
    assert (mix[plane] == 0).any() and (mix[plane] == 1).any() and ((mix > 0) & (mix < 1)).any()
    torch.testing.assert_close(m.render(frame, gb), (1 - mix) * img_a + mix * img_b, atol=F32_ATOL, rtol=0)
    assert "brdf_b[plane]" in m.memory() and m.memory()["blend_weight[plane]"] == 64 * 4
    m.set_blend("plane", B_MAT, None)
    torch.testing.assert_close(m.render(frame, gb), img_a, atol=F32_ATOL, rtol=0)


def test_blend_half_matches_oracle_on_mixture_material(sp):
    scene, frame, gb = sp
    mask = _region_mask(gb, scene.regions.index("plane"))
    mixed = _Mix(scene.materials["plane"], B_MAT)
    fo = dataclasses.replace(frame, materials={**frame.materials, "plane": mixed})
    ref, floor = _oracle_pair(scene, fo, gb, 16, mask, seeds=(3, 4))
    m = TripleProduct(level=3, frame_grid=(9, 16, 1))
    m.precompute(scene)
    img_a = m.render(frame, gb)
    m.set_blend("plane", B_MAT, torch.full((2, 2), 0.5))
    err = rmse(m.render(frame, gb), ref, mask)  # measured 0.0286, floor 0.0279, mean 0.320
    mean = ref[mask].mean().item()
    assert err ** 2 <= (FLOOR_SLACK * floor) ** 2 + (BIAS_REL * mean) ** 2, (err, floor, mean)
    # and the blend matters: material a alone is far off the mixture (measured 0.093)
    assert rmse(img_a, ref, mask) > 2 * err, (rmse(img_a, ref, mask), err)


def test_blend_and_bump_inputs_validated(sp):
    scene, frame, gb = sp
    with pytest.raises(RuntimeError):
        TripleProduct(**SMALL).set_blend("plane", B_MAT, torch.zeros(2, 2))
    m = TripleProduct(**SMALL)
    m.precompute(scene)
    for region, w in (("nope", torch.zeros(2, 2)), ("sphere", torch.zeros(2, 2)),  # sphere: no UV map
                      ("plane", torch.zeros(2, 2, 2)), ("plane", torch.zeros(0, 3)),
                      ("plane", torch.tensor([[0.5, float("nan")]])), ("plane", torch.tensor([[0.5, 1.5]])),
                      ("plane", torch.tensor([[-0.1, 0.5]]))):
        with pytest.raises(ValueError):
            m.set_blend(region, B_MAT, w)
    for region, h, s in (("sphere", torch.zeros(2, 2), 1.0), ("plane", torch.zeros(4), 1.0),
                         ("plane", torch.tensor([[float("inf")]]), 1.0), ("plane", torch.zeros(2, 2), float("nan"))):
        with pytest.raises(ValueError):
            m.set_bump(region, h, s)
    v = TripleProduct(**SMALL, shading="vertex")
    v.precompute(scene)
    with pytest.raises(ValueError, match="pixel"):
        v.set_blend("plane", B_MAT, torch.zeros(2, 2))
    with pytest.raises(ValueError, match="pixel"):
        v.set_bump("plane", torch.zeros(2, 2), 1.0)


# -- bump mapping -----------------------------------------------------------------------------


def _height(H=32, W=32):
    c = tx.texel_centres(H, W)
    return (0.12 * torch.sin(2 * math.pi * 3 * c[:, 0]) * torch.sin(2 * math.pi * 2 * c[:, 1])).view(H, W)


def test_bump_matches_oracle_on_the_same_perturbed_normals():
    scene = _plane_scene(film=32)
    frame = _frame(scene)
    gb = make_gbuffer(scene, frame, 1)
    m = TripleProduct(level=3, frame_grid=(9, 16, 1))
    m.precompute(scene)
    flat = m.render(frame, gb)
    m.set_bump("plane", _height(), 1.0)
    n_b = m.shading_normals(gb)
    tilt = torch.rad2deg(torch.acos((n_b[gb.hit] * gb.normal[gb.hit]).sum(-1).clamp(-1, 1)))
    assert tilt.max() > 20.0  # a non-trivial bump (measured max ≈ 29°)
    img = m.render(frame, gb)
    gb_b = dataclasses.replace(gb, normal=n_b)  # the oracle shades with gbuffer.normal
    ref, floor = _oracle_pair(scene, frame, gb_b, 32, gb.coverage, seeds=(5, 6))
    mean = ref[gb.coverage].mean().item()
    err = rmse(img, ref, gb.coverage)  # measured 0.0202, floor 0.0193, mean 0.363
    assert err ** 2 <= (FLOOR_SLACK * floor) ** 2 + (BIAS_REL * mean) ** 2, (err, floor, mean)
    change = rmse(img, flat, gb.coverage)
    assert change > BUMP_CHANGE_REL * mean, (change, mean)
    assert rmse(flat, ref, gb.coverage) > BUMP_DISCRIMINATES * err, (rmse(flat, ref, gb.coverage), err)
    assert m.memory()["bump_height[plane]"] == 32 * 32 * 4
    m.set_bump("plane", None)
    torch.testing.assert_close(m.render(frame, gb), flat, atol=F32_ATOL, rtol=0)
