"""Fast evaluators of Ma 2006 eq. 7 (`methods.triple_product.fast_eval`) against the dense reference
`spherical_haar.triple_integral`, and the bytes-per-frame model on a tiny config."""
from __future__ import annotations

import pytest
import torch

from methods.core.spherical_haar import inverse, support_areas, triple_integral, triple_integral_sparse
from methods.triple_product import TripleProduct, fast_eval
from references.gbuffer import make_gbuffer
from scenes.library import get_scene
from scenes.materials import Phong
from scenes.sequences import make_sequence

# float64 evaluators agree to summation-order rounding
F64 = 1e-11
# float32: the evaluators sum the same products in different orders; relative to the largest
# |value| of the batch (measured ≤ 4e-7 on random lists and on renders)
F32 = 2e-6


def _lists(B, K, n, gen, dtype, top=False):
    """V (B, 1, 3n), ρ̃ (B, 3, 4n), L (B, 3, 8n) lists with duplicate indices across rows."""
    level = {80: 1, 320: 2, 1280: 3}[K]
    sd = support_areas(level, dtype=torch.float64).sqrt()
    out = []
    for k, C in ((3, 1), (4, 3), (8, 3)):
        if top:
            idx = torch.arange(n).repeat(k).expand(B, k * n).contiguous()
        else:
            idx = torch.randint(0, K, (B, k * n), generator=gen)
            idx[:, n:2 * n] = idx[:, :n]  # the next row repeats the first one's indices
        val = (torch.randn(B, C, k * n, generator=gen, dtype=torch.float64) * sd[idx][:, None]).to(dtype)
        out.append((idx, val))
    return out


def _reference(V, rho, L, K):
    return fast_eval.evaluate(V, rho, L, K, "reference")


@pytest.mark.parametrize("K,n", [(80, 7), (320, 20), (1280, 40)])
def test_evaluators_match_dense_reference_float64(K, n):
    gen = torch.Generator().manual_seed(K + n)
    V, rho, L = _lists(16, K, n, gen, torch.float64)
    ref = _reference(V, rho, L, K)
    assert ref.shape == (16, 3)
    scale = ref.abs().max()
    for ev in ("dense", "sparse", "auto"):
        got = fast_eval.evaluate(V, rho, L, K, ev)
        assert (got - ref).abs().max() <= F64 * scale, ev


def test_sparse_matches_core_sparse_triple():
    """Two-sparse-one-dense core routine (`triple_integral_sparse`) = the three-list evaluator."""
    K, n, B = 320, 15, 8
    gen = torch.Generator().manual_seed(3)
    a_idx = torch.stack([torch.randperm(K, generator=gen)[:n] for _ in range(B)])
    b_idx = torch.stack([torch.randperm(K, generator=gen)[:n] for _ in range(B)])
    a_val = torch.randn(B, n, generator=gen, dtype=torch.float64)
    b_val = torch.randn(B, n, generator=gen, dtype=torch.float64)
    c = torch.randn(B, K, generator=gen, dtype=torch.float64)
    want = triple_integral_sparse(a_idx, a_val, b_idx, b_val, c)
    full = torch.arange(K).expand(B, K)
    got = fast_eval.triple_sparse((a_idx, a_val[:, None]), (b_idx, b_val[:, None]), (full, c[:, None]), K)
    assert (got[:, 0] - want).abs().max() <= F64 * want.abs().max()


def test_top_selection_runs_at_the_coarse_level_and_matches():
    """Indices < 80 at K = 1280: the dense evaluator works at K' = 80 (level 1) — same sums."""
    gen = torch.Generator().manual_seed(1)
    V, rho, L = _lists(8, 1280, 80, gen, torch.float64, top=True)
    assert fast_eval._effective_size(V, rho, L) == 80
    ref = _reference(V, rho, L, 1280)
    got = fast_eval.evaluate(V, rho, L, 1280, "dense")
    assert (got - ref).abs().max() <= F64 * ref.abs().max()


def test_fine_values_and_blocked_layout():
    gen = torch.Generator().manual_seed(2)
    x = torch.randn(4, 1280, generator=gen, dtype=torch.float64)
    assert torch.allclose(fast_eval.fine_values(x), inverse(x), rtol=0, atol=1e-12)
    pos = fast_eval.blocked_order(3)
    assert torch.equal(torch.sort(pos).values, torch.arange(1280))  # a permutation
    xb = torch.empty_like(x)
    xb[:, pos] = x
    fb = fast_eval.fine_values_blocked(xb)
    # same multiset of fine values (the order is ord_L)
    assert torch.allclose(fb.sort(-1).values, inverse(x).sort(-1).values, rtol=0, atol=1e-12)


def test_bad_inputs():
    idx = torch.zeros(2, 3, dtype=torch.long)
    with pytest.raises(ValueError):
        fast_eval.evaluate((idx, torch.zeros(2, 2, 3)), (idx, torch.zeros(2, 3, 3)), (idx, torch.zeros(2, 3, 3)), 80)
    with pytest.raises(ValueError):
        fast_eval.evaluate((idx, torch.zeros(2, 1, 3)), (idx, torch.zeros(2, 3, 3)), (idx, torch.zeros(2, 3, 3)), 81)
    with pytest.raises(ValueError):
        fast_eval.evaluate((idx, torch.zeros(2, 1, 3)), (idx, torch.zeros(2, 3, 3)), (idx, torch.zeros(2, 3, 3)), 80,
                      "fastest")


@pytest.fixture(scope="module")
def scene_frame():
    scene = get_scene("sphere_plane", "test")
    frame = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    return scene, frame, make_gbuffer(scene, frame, 1)


@pytest.mark.parametrize("cfg", [
    dict(level=2, n_coeffs=20),                                       # adaptive, trilinear, pixel
    dict(level=2, n_coeffs=None, shading="vertex", light_lookup="nearest"),   # all coefficients
    dict(level=3, n_coeffs=80, selection="top", frame_grid=(5, 8, 1)),        # K' = 80 path
    dict(level=2, n_coeffs=50, selection="top", brdf_dirs=(2, 4)),            # prefix padded to 80
])
def test_render_equals_reference_render(scene_frame, cfg):
    scene, frame, gb = scene_frame
    m = TripleProduct(**cfg, evaluator="reference", progress=False)
    m.precompute(scene)
    ref = m.render(frame, gb)
    scale = ref.abs().max()
    assert scale > 0
    for ev in ("auto", "dense", "sparse"):  # "auto" = the default config
        fast = fast_eval.use_fast_shading(m, ev)
        assert fast.config["evaluator"] == ev and m.config["evaluator"] == "reference"  # a copy says what ran
        img = fast.render(frame, gb)
        assert (img - ref).abs().max() <= F32 * scale, ev
    assert torch.equal(m.render(frame, gb), ref)


@pytest.mark.parametrize("level,n", [(2, 20), (1, None)])
def test_render_with_texture_sbrdf_bump_equals_reference(scene_frame, level, n):
    """Visibility textures (4 taps), SBRDF blend and bump map on the plane (Ma 2006 §3.3, §5);
    sparse lists and dense (all-coefficient) lists."""
    scene, frame, gb = scene_frame
    m = TripleProduct(level=level, n_coeffs=n, vis_texture=16, evaluator="reference", progress=False)
    m.precompute(scene)
    gen = torch.Generator().manual_seed(4)
    m.set_blend("plane", Phong(kd=0.2, ks=0.5, s=20.0), torch.rand(8, 8, generator=gen))
    m.set_bump("plane", torch.rand(8, 8, generator=gen), 0.02)
    ref = m.render(frame, gb)
    for ev in ("dense", "sparse"):
        assert (fast_eval.use_fast_shading(m, ev).render(frame, gb) - ref).abs().max() <= F32 * ref.abs().max(), ev


def test_bytes_per_frame_tiny_config(scene_frame):
    scene, frame, gb = scene_frame
    m = TripleProduct(level=1, n_coeffs=10, frame_grid=(2, 2, 1), brdf_dirs=(1, 2), shading="vertex",
                      progress=False)
    m.precompute(scene)
    N = scene.geometry().V.shape[0]
    K, n, F, n_o, R = 80, 10, 4, 2, len(scene.regions)
    vis = N * n * (4 + 4)                       # int32 idx + float32 value per kept coefficient
    frames = N * 9 * 4                          # vertex frames (vertex shading)
    tables = R * n_o * n * (4 + 3 * 4)          # idx + RGB values per ωo
    grid = F * n * (4 + 3 * 4)                  # truncated lighting grid
    assert fast_eval.bytes_per_frame(m, "V") == vis + frames + tables + grid   # before the lighting is set
    m.render(frame, gb)
    assert fast_eval.bytes_per_frame(m, "V") == vis + frames + tables + grid
    H, W = frame.envmap.data.shape[:2]
    relight = H * W * 3 * 4 + 2 * F * 3 * K * 4 + grid
    assert fast_eval.bytes_per_frame(m, "VL", envmap=frame.envmap) == vis + frames + tables + grid + relight
    assert fast_eval.bytes_per_frame(m, "VBL", envmap=frame.envmap) == fast_eval.bytes_per_frame(m, "VL", envmap=frame.envmap)
    assert fast_eval.bytes_per_frame(m, "VL") == fast_eval.bytes_per_frame(m, "VL", envmap=scene.envmap)  # default
    with pytest.raises(ValueError):
        fast_eval.bytes_per_frame(m, "P")
    cfg = dict(m.config)
    pixel = TripleProduct(**{**cfg, "shading": "pixel"}, progress=False)  # frames are rebuilt from the G-buffer: not read
    pixel.precompute(scene)
    pixel.render(frame, gb)
    assert fast_eval.bytes_per_frame(pixel, "V") == vis + tables + grid
    exact = TripleProduct(**{**cfg, "light_lookup": "exact"}, progress=False)
    exact.precompute(scene)
    assert fast_eval.bytes_per_frame(exact, "V") is None


def test_fast_shading_follows_material_edits(scene_frame):
    """The stacked ρ̃ tables are rebuilt after `edit_material` (cache keyed on the tables)."""
    import dataclasses

    scene, frame, gb = scene_frame
    m = TripleProduct(level=2, n_coeffs=20, progress=False)
    m.precompute(scene)
    m = fast_eval.use_fast_shading(m, "dense")
    first = m.render(frame, gb)
    edited = dataclasses.replace(frame, materials={**frame.materials, "sphere": Phong(kd=0.1, ks=0.6, s=40.0)})
    fast = m.render(edited, gb)
    ref = fast_eval.use_reference_shading(m).render(edited, gb)
    assert (fast - first).abs().max() > 100 * F32 * ref.abs().max()  # the edit shows
    assert (fast - ref).abs().max() <= F32 * ref.abs().max()
