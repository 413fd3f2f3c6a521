"""Fast evaluators of Ma 2006 eq. 7 (`methods.triple_product.fast_eval`) against the dense reference
`spherical_haar.triple_integral`, and the frame-cost model on a tiny config."""
from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from methods.core.spherical_haar import inverse, support_areas, triple_integral_sparse
from methods.triple_product import TripleProduct, fast_eval
from references.gbuffer import make_gbuffer
from scenes.library import SCENES, get_scene
from scenes.materials import Phong
from scenes.sequences import make_sequence

# float64 evaluators agree to summation-order rounding
F64 = 1e-11
# float32: the evaluators sum the same products in different orders; relative to the largest
# |value| of the batch (measured ≤ 4e-7 on random lists and on renders)
F32 = 2e-6
# Images whose lighting grid the compiled projection (`lighting.project_env`) made: its vectorised
# atan2/acos differ from ATen's by an ulp of the sample direction, which a bilinear env map turns into
# an error of ulp × (texel-scale gradient) — largest beside a sun (measured 2.1e-6 of the image's
# maximum on shadow_detail, 5e-6 of the largest coefficient on chess bench)
F32_LIGHT = 1e-5


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
    for ev in ("auto", "dense", "sparse") + (("fine",) if fast_eval.fine_ok(m) else ()):  # "auto" = the default config
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
    for ev in ("dense", "sparse", "auto") + (("fine",) if n is None else ()):  # "fine": texel taps, 8 ρ̃ rows
        assert (fast_eval.use_fast_shading(m, ev).render(frame, gb) - ref).abs().max() <= F32 * ref.abs().max(), ev
    if n is not None:
        with pytest.raises(ValueError, match="fine"):  # truncated adaptive tables: no fine-value path
            fast_eval.use_fast_shading(m, "fine").render(frame, gb)


def _hand_triple(m, n, full, nl=80):
    """Eq. 7's per-point triple flops by hand (level 1: indices < 20 are level-0 scaling functions,
    A = 0; the rest level-0 wavelets, A = 1 + 3·0 = 1); the fine-value product over the nl live
    fine triangles of full tables."""
    K = 80
    bi = torch.cat([i for i, _ in m.tables.values()])
    av, ab = float((m.V_idx >= 20).double().mean()), float((bi >= 20).double().mean())
    sparse = 3 * (n * (10 + 2 * av) + n * (3 + ab))
    dense = 9 * nl if full else 9 * K + 7 * 8 * (K - 20) // 3
    return int(min(sparse, dense))


@pytest.mark.parametrize("n", [10, None])
def test_frame_cost_tiny_config(scene_frame, n):
    """`frame_cost` = a hand count (module docstring of `fast_eval`), vertex and pixel shading, "V"
    and lighting-change kinds; indices of full tables (n = None) are not counted."""
    from methods.base import GBUFFER_BYTES_PER_SAMPLE

    scene, frame, gb = scene_frame
    m = TripleProduct(level=1, n_coeffs=n, frame_grid=(2, 2, 1), brdf_dirs=(1, 2), shading="vertex",
                      progress=False)
    m.precompute(scene)
    K, F, n_o, R, P = 80, 4, 2, len(scene.regions), gb.num_samples
    nk = K if n is None else n
    ib = 0 if n is None else 4                  # int32 index per kept coefficient (not for full tables)
    hit = gb.hit
    faces = torch.unique(gb.face[hit])
    verts = torch.unique(m.F[faces].reshape(-1))
    nf, nv, nh = faces.numel(), verts.numel(), int(hit.sum())
    m.render(frame, gb)
    # full tables: the fine triangles where some visibility row and some ρ̃ row are non-zero (the
    # others add an exact 0 to eq. 7: `fast_eval.live_triangles`, checked against the tables in
    # test_live_triangles_are_where_no_table_is_zero) are all a frame reads, sums and projects
    live = fast_eval.live_triangles(m) if n is None else None
    nl = K if live is None else live.numel()
    if n is None:
        assert nl < K                          # this scene has dead triangles: the reduction is tested
    nw = nk if n is not None else nl           # values per stored row read
    tables = R * n_o * nw * (3 * 4 + ib)       # RGB values (+ index) per ωo
    grid = F * nw * (3 * 4 + ib)               # truncated lighting grid
    mesh = nf * 3 * 8                          # vertex indices of the touched faces
    out = P * 3 * 4
    triple = _hand_triple(m, nk, n is None, nl)
    # a blend of k rows: k multiplies + (k − 1) adds per value — ρ̃: 4 rows × RGB; L: 4 distinct
    # trilinear rows × RGB; V of a vertex is its own row (no flops)
    blend_v = nw * (3 * (4 + 3) + 3 * (4 + 3))
    got = m.frame_cost("V", P)
    want_b = nv * nw * (4 + ib) + tables + grid + mesh + nv * (9 * 4 + 3 * 4 + 8) \
        + P * (GBUFFER_BYTES_PER_SAMPLE - 24) + out
    want_f = nv * (blend_v + triple) + nh * 3 * (3 + 2)  # Gouraud: 3 weights × RGB + 2 adds
    if n is None:
        # at the grain of the zeros: a vertex sums (and blends ρ̃ and L) only over the live triangles
        # where its own visibility is non-zero (the others add an exact 0 to its eq. 7)
        Vfine = fast_eval.fine_values(m.V_val.float()[:, None, :])[:, 0][:, live] != 0      # (N_V, n')
        nz = Vfine[verts].sum(1)
        assert int(nz.sum()) < nv * nl                   # this scene has such zeros: the grain is tested
        want_f = sum(int(z) * (3 * (4 + 3) + 3 * (4 + 3)) + _hand_triple(m, nk, True, int(z)) for z in nz) \
            + nh * 3 * (3 + 2)
        # and its visibility row's bytes likewise: its non-zero values, a bit per live triangle, an int64 start
        want_b += int(nz.sum()) * 4 + nv * ((nl + 7) // 8 + 8) - nv * nw * 4
    assert (got.bytes, got.flops) == (want_b, want_f)
    from methods.triple_product import lighting as lt

    H, W = frame.envmap.data.shape[:2]
    S = 4 ** m.config["light_supersample"]               # sub-samples per fine triangle (default 2: 16)
    # the re-projection: per sample a rotation (15), the bilinear RGB look-up (24), the weighted sum
    # (6); a map turned about +Y only (`lighting.env_taps_azimuthal`) adds a shift to the base u (1)
    # instead of rotating, and reads the base coordinates (float64 u0 + float32 v0 per sample of the
    # n_theta·n_psi = 2 base frames)
    tilted = frame.envmap.rotated([[1.0, 0.0, 0.0], [0.0, 0.6, -0.8], [0.0, 0.8, 0.6]])
    turned = frame.envmap.rotated([[0.6, 0.0, 0.8], [0.0, 1.0, 0.0], [-0.8, 0.0, 0.6]])
    assert lt.azimuth_of(tilted.to_world) is None and lt.azimuth_of(turned.to_world) is not None
    written = grid
    if n is None:
        # full tables: only the (grid frame, live triangle) pairs some vertex looks up (non-zero
        # trilinear weight) and has non-zero visibility on are projected
        rows, wts = lt.lookup_weights(m.R[verts], m.grid, "trilinear")[:2]
        need = torch.zeros(F, nl, dtype=torch.bool)
        for i in range(verts.numel()):
            for r, wt in zip(rows[i].tolist(), wts[i].tolist()):
                if wt != 0:
                    need[r] |= Vfine[verts[i]]
        pairs = int(need.sum())
        assert 0 < pairs < F * nl
        written = pairs * 3 * 4
    for env, per_sample in ((tilted, 45), (turned, 31 if n is None else 45)):  # truncated: the slow path
        m.render(dataclasses.replace(frame, envmap=env), gb)
        assert m.stats["lighting_path"] == ("azimuthal" if per_sample == 31 else "general")
        # full tables: the live triangles' samples only — of the pairs read —, and no transform
        # (their fine values are read)
        relight_f = per_sample * pairs * S if n is None else F * (per_sample * K * S + 3 * 8 * (K - 20) // 3)
        table_b = 2 * (nl if n is None else K) * S * (8 + 4) if per_sample == 31 else 0
        for kind in ("L", "VL", "E", "VBL"):
            c = m.frame_cost(kind, P)
            assert (c.bytes, c.flops) == (want_b + H * W * 3 * 4 + written + table_b, want_f + relight_f), kind
    for bad in ("P", "X", ""):
        with pytest.raises(ValueError):
            m.frame_cost(bad, P)
    with pytest.raises(ValueError):
        m.frame_cost("V", -1)

    pixel = TripleProduct(**{**dict(m.config), "shading": "pixel"}, progress=False)
    pixel.precompute(scene)
    pixel.render(frame, gb)
    idx, w = gb.vertex_weights(pixel.F)
    rows = torch.unique(idx[hit][w[hit] != 0])
    c = pixel.frame_cost("V", P)
    want_b = rows.numel() * nw * (4 + ib) + tables + grid + mesh + P * (GBUFFER_BYTES_PER_SAMPLE + 8) + out
    if n is None:  # the rows' non-zero values, a bit per live triangle, an int64 start (as per vertex)
        want_b += int(Vfine[rows].sum()) * 4 + rows.numel() * ((nl + 7) // 8 + 8) - rows.numel() * nw * 4
    want_f = nh * (nw * ((3 + 2) + 3 * (4 + 3) + 3 * (4 + 3)) + triple)  # V: 3 vertex rows
    if n is None:  # full tables: summed by groups (fast_eval.fine_grouped) — its count is smaller
        from methods.triple_product import brdf_table as bt

        s = torch.nonzero(hit).squeeze(-1)
        Rs = lt.local_frames(torch.nn.functional.normalize(gb.normal[s].float(), dim=-1), "grid")
        l0 = lt.lookup_weights(Rs, pixel.grid, "trilinear")[0][:, 0]     # a grid cell: its first row
        b0 = bt.outgoing_weights((Rs @ gb.wo[s].float()[..., None])[..., 0], pixel.outgoing)[0][:, 0] \
            + gb.region[s].long() * 2                                       # ωo cell in its region's table
        uniq = torch.unique(torch.stack([idx[s], l0[:, None].expand(-1, 3), b0[:, None].expand(-1, 3)], -1)
                            .reshape(-1, 3), dim=0)
        groups = uniq.shape[0]
        # at the grain of the zeros: a sample blends and sums over the live triangles where one of
        # its vertex rows (weight ≠ 0) is non-zero; a group sums over its own row's non-zero ones
        vs = (Vfine[idx[s]] & (w[s] != 0)[..., None]).any(1).sum(1)                       # (hits,)
        want_f = sum(int(z) * ((3 + 2) + 3 * (4 + 3) + 3 * (4 + 3)) + _hand_triple(m, nk, True, int(z)) for z in vs)
        # per group and channel: 4 products V̂·L̂_j and 16 sums of (·ρ̂_k), 2 flops each, per fine
        # triangle; per sample and channel: 3 vertices × (16 products and adds + 4 L weights) + 2 adds
        want_f = min(want_f, int(Vfine[uniq[:, 0]].sum()) * 3 * (4 + 2 * 16) + nh * 3 * (3 * (2 * 16 + 4) + 2))
        assert 0 < groups < 3 * nh
    assert (c.bytes, c.flops) == (want_b, want_f)
    # the fine-value tables of the full-table fast path are run-time arrays: memory() reports them
    # (V and ρ̃ as their live columns only, `fast_eval.live_triangles`; the grid's fine values whole,
    # as projected, and their live columns, what the sums read)
    nrows = pixel.V_idx.shape[0]
    assert (fast_eval.live_triangles(pixel) is None) == (live is None)
    want_mem = (nrows * nl + R * n_o * 3 * nl + F * 3 * K + (0 if live is None else F * 3 * nl)) * 4
    # and the visibility table's chunk lists of the native loop (`fast_eval.vis_chunks`): row pointers
    # (int64), chunk starts and tails (int32)
    ch = pixel.__dict__.get("_perf_cache", {}).get(("chunks",))
    if ch is not None:
        want_mem += (nrows + 1) * 8 + int(ch[1][0][-1]) * 4 + nrows * 4
    assert pixel.memory()["fine_values"] == (want_mem if n is None else 0)
    exact = TripleProduct(**{**dict(m.config), "light_lookup": "exact"}, progress=False)
    exact.precompute(scene)
    assert exact.frame_cost("V", P) is None


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


def test_project_env_equals_project_lighting():
    """The compiled lighting projection (coefficients and fine values) = `project_lighting` (the
    slow path) on a rotated library probe, to the look-up's round-off (F32_LIGHT)."""
    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt

    scene = get_scene("bunny", "test")
    env = scene.envmap.rotated([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    geo, R = Geodesic(2), lt.grid_frames(lt.FrameGrid(5, 8, 1))
    ref = lt.project_lighting(env.radiance, R, geo, supersample=1)
    coef, fine = lt.project_env(env, R, geo, supersample=1)
    assert (coef - ref).abs().max() <= F32_LIGHT * ref.abs().max()
    want = fast_eval.fine_values(ref)
    assert (fine - want).abs().max() <= F32_LIGHT * want.abs().max()


def _project_lighting64(env, R, geo):
    """`lighting.project_lighting`'s integral (eq. 7) evaluated in float64: the exact value both the
    float32 slow path and the compiled paths approximate."""
    Rd = R.double()

    def fn(c):
        L = env.radiance(torch.einsum("pj,fji->fpi", c.double(), Rd))
        return L.permute(1, 0, 2).reshape(c.shape[0], -1)

    return geo.project(fn, supersample=1, dtype=torch.float64).reshape(R.shape[0], 3, -1)


@pytest.mark.parametrize("grid", [(5, 8, 1), (4, 6, 3)])
def test_project_env_azimuthal_equals_project_lighting(grid):
    """A map turned about +Y only (E frames) takes the shifted base coordinates
    (`lighting.env_taps_azimuthal`: no rotation, no atan2 / acos) = `project_lighting`'s integral to
    float32 round-off (F32_LIGHT of the largest coefficient on the bunny's unfiltered test map, which
    is sharper than any prefiltered one the method projects), with and without tangent angles; a
    tilted map keeps the general kernel. The reference is the integral in float64: the float32 slow
    path is itself 7–11e-6 off it at these angles (AVX-512 Inductor code, 2026-12-04), so two float32
    paths can differ by up to twice F32_LIGHT (the comparison with it failed at 1.09e-5 on such a
    machine, identically before and after session 16's changes), while the compiled paths stay within
    3.0–5.3e-6 of the float64 value."""
    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt
    from scenes.sequences import rotation_y

    g = lt.FrameGrid(*grid)
    geo, R = Geodesic(2), lt.grid_frames(g)
    for angle in (0.0, 0.7, -2.5):
        env = get_scene("bunny", "test").envmap.rotated(rotation_y(angle))
        st = {}
        ref = _project_lighting64(env, R, geo)
        coef, fine = lt.project_env(env, R, geo, supersample=1, grid=g, stats=st)
        assert st["lighting_path"] == "azimuthal"
        assert (coef.double() - ref).abs().max() <= F32_LIGHT * ref.abs().max(), angle
        want = fast_eval.fine_values(ref)
        assert (fine.double() - want).abs().max() <= F32_LIGHT * want.abs().max(), angle
    st = {}
    lt.project_env(env.rotated([[1.0, 0.0, 0.0], [0.0, 0.6, -0.8], [0.0, 0.8, 0.6]]), R, geo, supersample=1,
                   grid=g, stats=st)
    assert st["lighting_path"] == "general"


def test_project_env_comb_equals_the_per_frame_azimuthal_kernel(monkeypatch):
    """E frames whose grid's n_phi divides the map's width go through the comb table
    (`lighting.comb_means`: footprints once per base row, the n_phi frames of a row summed together)
    = the per-frame azimuthal kernel (`lighting.env_taps_azimuthal` + `quad_means_coeffs`, ``COMB``
    off) to the look-up's round-off (F32_LIGHT), for the whole grid; a selection of frames gives the
    whole projection's rows bit for bit."""
    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt
    from scenes.sequences import rotation_y

    g = lt.FrameGrid(5, 8, 1)
    geo, R = Geodesic(2), lt.grid_frames(g)
    sel = torch.tensor([0, 3, 4, 9, 17, 20, 31, 39])
    for angle in (0.0, 0.7, -2.5):
        env = lt.prefiltered(get_scene("bunny", "test").envmap.rotated(rotation_y(angle)), geo, 1)
        assert lt.comb_ok(g, env.width)
        monkeypatch.setattr(lt, "COMB", True)
        coef, fine = lt.project_env(env, R, geo, supersample=1, grid=g)
        part = lt.project_env(env, R, geo, supersample=1, grid=g, frames=sel)
        assert torch.equal(part[0], coef[sel]) and torch.equal(part[1], fine[sel])
        monkeypatch.setattr(lt, "COMB", False)
        ref, ref_fine = lt.project_env(env, R, geo, supersample=1, grid=g)
        assert (coef - ref).abs().max() <= F32_LIGHT * ref.abs().max(), angle
        assert (fine - ref_fine).abs().max() <= F32_LIGHT * ref_fine.abs().max(), angle
    assert not lt.comb_ok(lt.FrameGrid(5, 7, 1), env.width)


def _comb_taps_reference(u0, v0, g, wT, H: int, W: int, n_phi: int):
    """`lighting.comb_taps` written out eagerly: frame 0's u = (u0 − γ/2π) mod 1 (torch.remainder in
    float64, rounded once), its footprint by `latlong.quad_taps`, the comb offset of the top-left tap
    and the 4 taps' bilinear weights times wT, each (dy, e) written on its own."""
    from methods.core.latlong import quad_taps

    m, J = W // n_phi, n_phi
    u = torch.remainder(u0 - g, 1.0).float()
    idx, fx, fy = quad_taps(u, v0, H, W)
    ix, iy = idx % (W + 1), idx // (W + 1)
    o = (iy * m + ix % m) * (3 * 2 * 2 * J) + ix // m
    w4 = torch.empty(*u.shape, 2, 2)
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for e, wx in ((0, 1 - fx), (1, fx)):
            w4[..., dy, e] = (wx * wy) * wT[None]
    return o, w4


def test_comb_taps_equals_the_eager_footprints():
    """The compiled `lighting.comb_taps` (u mod 1 as u − ⌊u⌋, the 4 weights in one stack) = the eager
    footprints of `_comb_taps_reference` bit for bit: a live-triangle selection (B, n', S) of a
    level-2 grid's base coordinates under four map turns, and coordinates at the edges (with γ/2π =
    0.25: u0 − γ/2π exactly 0, 1, −1, 0.25, 1 ulp-ish below and above 0; u0 = ±0 under the turns)."""
    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt

    grid, H, W = lt.FrameGrid(5, 8, 1), 16, 32
    geo = Geodesic(2)
    u0, v0 = lt._azimuthal_samples(geo, 1, grid)
    _, wT = lt._env_sample_planes(geo, 1)
    live = torch.arange(0, u0.shape[1], 3)                       # a live-triangle selection
    cases = [(u0[:, live].contiguous(), v0[:, live].contiguous(), wT[live].contiguous())]
    edge = torch.tensor([0.25, -0.0, 0.0, 1.25, -0.75, 0.25 - 2.0 ** -40, 0.25 + 2.0 ** -40, 0.5], dtype=torch.float64)
    cases.append((edge.view(1, 2, 4).expand(3, 2, 4).contiguous(), torch.rand(3, 2, 4, generator=torch.Generator().manual_seed(1)),
                  torch.rand(2, 4, generator=torch.Generator().manual_seed(2))))
    kernel = lt._kernel(lt.comb_taps)
    for u, v, w in cases:
        for gamma in (0.25, 0.7, -2.5, 3.0):
            g = torch.tensor(gamma / (2 * math.pi) if gamma != 0.25 else 0.25, dtype=torch.float64)
            o, w4 = kernel(u, v, g, w, H, W, grid.n_phi)
            ro, rw4 = _comb_taps_reference(u, v, g, w, H, W, grid.n_phi)
            assert o.dtype == torch.int32 and torch.equal(o, ro.to(torch.int32)), gamma
            assert w4.shape == rw4.shape and w4.stride() == rw4.stride() and torch.equal(w4, rw4), gamma


def test_comb_means_equals_the_sequential_sums():
    """The compiled `lighting.comb_means` (the J frames in reductions of COMB_LANES, side by side) =
    each output's S·4 terms added one by one from 0 in (sample, dy, e) order, eagerly from the comb
    table (`comb_table`), bit for bit: J = 32 (4 parts, as the bench grid), 8 and 12 (a short part)."""
    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt

    gen = torch.Generator().manual_seed(3)
    geo = Geodesic(2)
    _, wT = lt._env_sample_planes(geo, 1)
    live = torch.arange(1, wT.shape[0], 4)
    for n_phi, H, W in ((32, 8, 64), (8, 16, 32), (12, 6, 24)):
        grid = lt.FrameGrid(3, n_phi, 1)
        u0, v0 = lt._azimuthal_samples(geo, 1, grid)
        u0, v0, w = u0[:, live].contiguous(), v0[:, live].contiguous(), wT[live].contiguous()
        planes = torch.rand(3, H * (W + 1), generator=gen)
        CT = lt.comb_table(planes, H, W, n_phi)
        o, w4 = lt._kernel(lt.comb_taps)(u0, v0, torch.tensor(0.1, dtype=torch.float64), w, H, W, n_phi)
        m, J = W // n_phi, n_phi
        got = lt._kernel(lt.comb_means)(o, w4, CT, J, m)
        j = torch.arange(J)
        ref = torch.zeros(*o.shape[:2], 3, J)
        for si in range(o.shape[2]):
            for dy in range(2):
                for e in range(2):
                    for c in range(3):
                        at = o[:, :, si, None].long() + c * 4 * J + dy * m * 12 * J + e * 2 * J + j
                        ref[:, :, c] = ref[:, :, c] + CT[at] * w4[:, :, si, dy, e, None]
        assert got.shape == ref.shape and torch.equal(got, ref), n_phi
        # the eager function (PRTBENCH_COMPILE=0's path; its window view is bounds-checked, and
        # until session 30 reached 2 channel strides past the table): the same sums to round-off
        eager = lt.comb_means(o, w4, CT, J, m)
        assert eager.shape == ref.shape and torch.allclose(eager, ref, rtol=1e-5, atol=1e-6), n_phi


def test_comb_table_is_its_definition():
    """`lighting.comb_table` (a strided view of the rows repeated, copied once) = its definition
    CT[r, p, c, e, k] = texel(r, (p + e + m·k) mod W, c) element by element, from the channel
    planes (3, H·(W + 1)) (their extra column never read): m = 4 (bench), 1 (W = n_phi), 3, 2."""
    from methods.triple_product import lighting as lt

    gen = torch.Generator().manual_seed(4)
    for H, W, n_phi in ((64, 128, 32), (5, 8, 8), (6, 24, 8), (4, 24, 12)):
        planes = torch.rand(3, H * (W + 1), generator=gen)
        planes.view(3, H, W + 1)[:, :, W] = -1.0                          # the periodic column: never read
        m, J = W // n_phi, n_phi
        tex = planes.view(3, H, W + 1)
        ref = torch.empty(H, m, 3, 2, 2 * J)
        for p in range(m):
            for e in range(2):
                for k in range(2 * J):
                    ref[:, p, :, e, k] = tex[:, :, (p + e + m * k) % W].T
        assert torch.equal(lt.comb_table(planes, H, W, n_phi), ref.reshape(-1)), (H, W, n_phi)


def test_project_env_does_not_depend_on_threads(monkeypatch):
    """`lighting.quad_means` sums each output's samples in one thread: 1 and 2 threads agree bit for
    bit (blocks of `lighting.env_block_frames` frames, the last one padded)."""
    from methods.core.spherical_haar import Geodesic
    from methods.core.threads import torch_threads
    from methods.triple_product import lighting as lt

    env = get_scene("bunny", "test").envmap.rotated([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    geo, R = Geodesic(2), lt.grid_frames(lt.FrameGrid(5, 7, 1))       # 35 frames
    assert lt.env_block_frames(35, 320 * 16) == 35 and lt.env_block_frames(544, 20480) == 68
    with torch_threads(2):
        whole = lt.project_env(env, R, geo, supersample=2)                # one block of 35
    monkeypatch.setattr(lt, "ENV_BLOCK_SAMPLES", 4 * 320 * 16)          # 9 blocks of 4, the last padded
    with torch_threads(1):
        one = lt.project_env(env, R, geo, supersample=2)
    with torch_threads(2):
        two = lt.project_env(env, R, geo, supersample=2)
    assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])
    assert torch.equal(one[1], whole[1])


def test_project_env_tail_blocks_equal_the_whole_projection(monkeypatch):
    """A selection of frames (a lazy lighting change) runs in full blocks and tail blocks
    (`lighting.env_blocks`: the last few frames in small padded blocks, not one padded full block):
    each projected row equals the whole grid's projection of that frame bit for bit, on both paths
    (general kernel, map turned about +Y)."""
    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt
    from scenes.sequences import rotation_y

    assert lt.env_tail_sizes(68) == (32, 16, 8) and lt.env_tail_sizes(15) == ()
    assert lt.env_blocks(347, 68) == [68] * 5 + [8] and lt.env_blocks(328, 68) == [68] * 4 + [32, 16, 8]
    assert lt.env_blocks(60, 68) == [68] and lt.env_blocks(5, 68) == [8] and lt.env_blocks(0, 68) == []
    g = lt.FrameGrid(5, 7, 1)                                             # 35 frames
    geo, R = Geodesic(1), lt.grid_frames(g)
    monkeypatch.setattr(lt, "ENV_BLOCK_SAMPLES", 12 * 80 * 4)            # blocks of 12 frames
    monkeypatch.setattr(lt, "ENV_TAIL_MIN", 2)                            # tails of 4 and 2 frames
    assert lt.env_block_frames(35, 80 * 4) == 12 and lt.env_blocks(17, 12) == [12, 4, 2]
    sel = torch.tensor([0, 1, 3, 4, 6, 7, 9, 12, 13, 16, 20, 21, 25, 27, 30, 33, 34])   # 17 frames
    for env in (get_scene("bunny", "test").envmap.rotated([[1.0, 0.0, 0.0], [0.0, 0.6, -0.8], [0.0, 0.8, 0.6]]),
                get_scene("bunny", "test").envmap.rotated(rotation_y(0.7))):
        whole = lt.project_env(env, R, geo, supersample=1, grid=g)
        part = lt.project_env(env, R, geo, supersample=1, grid=g, frames=sel)
        assert part[0].shape == (17, 3, geo.n)
        assert torch.equal(part[0], whole[0][sel]) and torch.equal(part[1], whole[1][sel])


def test_project_env_live_triangles_equal_the_whole_projection(monkeypatch):
    """`lighting.project_env` with ``tris`` (the live triangles' samples only) gives the whole
    projection's fine values of those triangles bit for bit, on every path (general kernel, the
    per-frame azimuthal kernel, the comb table), whole grid and a selection in tail blocks, into new
    tensors and into an ``out`` table; and `lighting.warm_live` in the warm-up frame compiles every
    kernel a later live projection runs."""
    from torch._dynamo.utils import counters

    from methods.core.fused import warming
    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt
    from scenes.sequences import rotation_y

    g = lt.FrameGrid(5, 8, 1)                                             # 40 frames
    geo, R = Geodesic(1), lt.grid_frames(g)
    monkeypatch.setattr(lt, "ENV_BLOCK_SAMPLES", 12 * 80 * 4)            # blocks of frames and tails
    monkeypatch.setattr(lt, "ENV_TAIL_MIN", 2)
    tris = torch.tensor([0, 2, 3, 7, 11, 12, 40, 41, 63, 79])
    sel = torch.tensor([0, 1, 3, 4, 6, 7, 9, 12, 13, 16, 20, 21, 25, 27, 30, 33, 34, 39])
    base = get_scene("bunny", "test").envmap
    with warming():
        lt.warm_live(lt.prefiltered(base, geo, 1), R, geo, supersample=1, grid=g, tris=tris)
    graphs = int(counters["stats"]["unique_graphs"])
    for comb in (True, False):
        monkeypatch.setattr(lt, "COMB", comb)
        for env in (base.rotated([[1.0, 0.0, 0.0], [0.0, 0.6, -0.8], [0.0, 0.8, 0.6]]), base.rotated(rotation_y(0.7))):
            env = lt.prefiltered(env, geo, 1)
            whole = lt.project_env(env, R, geo, supersample=1, grid=g)[1]
            if comb:                                                      # compiled in the warm-up above
                c0 = int(counters["stats"]["unique_graphs"])
            coef, fine = lt.project_env(env, R, geo, supersample=1, grid=g, tris=tris)
            assert coef is None and torch.equal(fine, whole[:, :, tris])
            out = torch.zeros(g.size, 3, tris.numel())
            lt.project_env(env, R, geo, supersample=1, grid=g, tris=tris, frames=sel, out=(None, out))
            assert torch.equal(out[sel], whole[sel][:, :, tris])
            assert int(out.abs().sum(-1).sum(-1).ne(0).sum()) == sel.numel()    # no other row written
            if comb:
                assert int(counters["stats"]["unique_graphs"]) == c0
    assert int(counters["stats"]["unique_graphs"]) >= graphs
    # another index tensor of the same size, then the first again: the live samples cached on geo
    # (`lighting._live_sample_planes`, `_live_azimuthal_samples`) follow the tensor given
    other = torch.tensor([1, 4, 5, 6, 9, 30, 44, 55, 70, 78])
    for comb in (True, False):
        monkeypatch.setattr(lt, "COMB", comb)
        for env in (base.rotated([[1.0, 0.0, 0.0], [0.0, 0.6, -0.8], [0.0, 0.8, 0.6]]), base.rotated(rotation_y(-1.1))):
            env = lt.prefiltered(env, geo, 1)
            whole = lt.project_env(env, R, geo, supersample=1, grid=g)[1]
            for t in (other, tris, other.clone()):
                assert torch.equal(lt.project_env(env, R, geo, supersample=1, grid=g, tris=t)[1], whole[:, :, t])


def test_live_triangles_are_where_no_table_is_zero(scene_frame):
    """`fast_eval.live_triangles`: the fine triangles where some visibility row and some ρ̃ row are
    non-zero — every other triangle has an all-zero visibility or ρ̃ column (so its lighting is
    multiplied by an exact 0); about the lower half of the local sphere on a library scene; the
    live-column tables are those columns of the whole fine-value tables."""
    scene, frame, gb = scene_frame
    m = TripleProduct(level=2, frame_grid=(5, 8, 1), brdf_dirs=(4, 4), brdf_supersample=1, shading="vertex",
                      progress=False)
    m.precompute(scene)
    m.render(frame, gb)
    live = fast_eval.live_triangles(m)
    assert live is not None and 0 < live.numel() < m.K
    Vt = fast_eval.fine_values(m.V_val.float()[:, None, :])[:, 0]           # (N_V, K)
    bi, bv = fast_eval._brdf_stack(m)
    Rt = fast_eval.fine_values(bv.float())                                # (N_ρ, 3, K)
    dead = torch.ones(m.K, dtype=torch.bool)
    dead[live] = False
    assert bool(((Vt[:, dead] == 0).all(0) | (Rt[:, :, dead] == 0).all(0).all(0)).all())
    assert bool(((Vt[:, live] != 0).any(0) & (Rt[:, :, live] != 0).any(0).any(0)).all())
    assert abs(live.numel() / m.K - 0.5) < 0.15
    assert torch.equal(fast_eval.live_table(m, "V", m.V_val, live), Vt[:, live])
    assert torch.equal(fast_eval.live_table(m, "rho", bv, live).view(-1, 3, live.numel()), Rt[:, :, live])


def test_comb_warm_up_compiles_the_general_path(monkeypatch):
    """A warm-up frame whose lighting turns about +Y (the comb path: chess / creature "L" start with
    the scene's own map) compiles the general path's kernels too, full and tail blocks (`env_taps`
    and `quad_means_coeffs`): a later lighting on a tilted axis compiles nothing in a timed frame."""
    from torch._dynamo.utils import counters

    from methods.core.fused import warming
    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt
    from scenes.sequences import rotation_y

    g = lt.FrameGrid(3, 8, 1)                                             # 24 frames
    geo, R = Geodesic(1), lt.grid_frames(g)
    monkeypatch.setattr(lt, "ENV_BLOCK_SAMPLES", 8 * 80 * 16)            # blocks of 8 frames
    monkeypatch.setattr(lt, "ENV_TAIL_MIN", 2)                            # tails of 4 and 2 frames
    assert lt.env_block_frames(24, 80 * 16) == 8 and lt.env_blocks(5, 8) == [4, 2]
    base = get_scene("bunny", "test").envmap
    env = lt.prefiltered(base.rotated(rotation_y(0.7)), geo, 2)
    assert lt.comb_ok(g, env.width)
    with warming():
        lt.project_env(env, R, geo, supersample=2, grid=g)
    graphs = int(counters["stats"]["unique_graphs"])
    tilted = lt.prefiltered(base.rotated([[1.0, 0.0, 0.0], [0.0, 0.6, -0.8], [0.0, 0.8, 0.6]]), geo, 2)
    lt.project_env(tilted, R, geo, supersample=2, grid=g)                                  # 3 full blocks
    lt.project_env(tilted, R, geo, supersample=2, grid=g, frames=torch.tensor([0, 5, 9, 13, 20]))  # 4 + 2
    assert int(counters["stats"]["unique_graphs"]) == graphs


def test_prefiltered_reuses_the_box_filter_across_rotations_only():
    """`lighting.prefiltered` keeps the last box-filtered texels: a rotated copy of the same data gets
    them with its own rotation; a new map (new data) is filtered anew."""
    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt
    from scenes.envmap import EnvMap

    geo = Geodesic(3)
    sp = lt.sample_spacing(geo, 2)
    env = EnvMap(torch.rand(256, 512, 3, generator=torch.Generator().manual_seed(3)))
    a = lt.prefiltered(env, geo, 2)
    assert a.height < env.height and torch.equal(a.data, env.prefiltered_for_spacing(sp).data)
    rot = env.rotated([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    b = lt.prefiltered(rot, geo, 2)
    assert b.data.data_ptr() == a.data.data_ptr() and torch.equal(b.to_world, rot.to_world)  # not filtered again
    other = EnvMap(env.data * 2.0, rot.to_world)
    c = lt.prefiltered(other, geo, 2)
    assert torch.equal(c.data, other.prefiltered_for_spacing(sp).data) and torch.equal(c.to_world, other.to_world)
    small = EnvMap(torch.rand(16, 32, 3))                                # coarse enough already
    assert lt.prefiltered(small, geo, 2) is small
    # the filtered map is made without EnvMap's checks: every attribute as the constructor's (also
    # of a map whose sampling tables and periodic copies were made before it was filtered)
    e3 = EnvMap(torch.rand(256, 512, 3, generator=torch.Generator().manual_seed(4)), rot.to_world)
    e3.pdf(torch.tensor([[0.0, 1.0, 0.0]]))
    e3.periodic_texels()
    f3 = lt.prefiltered(e3, geo, 2)
    for m, x in ((a, env), (c, other), (f3, e3)):
        made = EnvMap(m.data, x.to_world)
        assert vars(m).keys() == vars(made).keys()
        for key, val in vars(made).items():
            got = vars(m)[key]
            assert (torch.equal(got, val) and got.dtype == val.dtype) if isinstance(val, torch.Tensor) else got == val, key
    for m, x in ((a, env), (c, other), (f3, e3)):                        # each its own data's copies
        assert torch.equal(m.periodic_texels(), EnvMap(m.data).periodic_texels())
        assert torch.equal(x.periodic_texels(), EnvMap(x.data).periodic_texels())


def test_box_filter_equals_the_envmap_box_downsample_bit_for_bit():
    """`lighting.box_filtered` (the prefilter an E frame runs on every new probe) gives the texels of
    ``EnvMap.box_downsampled`` bit for bit on every captured probe and every library scene's map at
    bench size, for k = 2, 4, 8, and `prefilter_factor` the k of ``prefiltered_for_spacing``."""
    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt
    from scenes.envmap import EnvMap, named
    from scenes.sequences import PROBES

    maps = [named(p, height=256) for p in PROBES] + [get_scene(n, "bench").envmap for n in ("chess", "creature")]
    maps.append(EnvMap(torch.rand(96, 192, 3, generator=torch.Generator().manual_seed(5)) ** 8 * 1e3))
    for env in maps:
        for k in (2, 4, 8):
            if env.height % k or env.width % k or env.height // k < 3:
                continue
            assert torch.equal(lt.box_filtered(env.data, k), env.box_downsampled(k).data), (env.height, k)
    for H, W in ((256, 512), (96, 192), (100, 200), (12, 24), (6, 10), (7, 14)):
        for lvl, ss in ((1, 1), (2, 1), (3, 1), (3, 2), (3, 3)):
            sp = lt.sample_spacing(Geodesic(lvl), ss)
            env = EnvMap(torch.ones(H, W, 3))
            assert lt.prefilter_factor(H, W, sp) == H // env.prefiltered_for_spacing(sp).height, (H, W, lvl, ss)


@pytest.mark.parametrize("name", SCENES)
def test_production_path_equals_reference_on_library(name):
    """The default evaluator ("auto": the compiled fine-value path `fast_eval.fine_block` for full
    tables, per sample and per vertex; the list evaluators for truncated ones) renders every library
    scene like the independent dense path (``with_evaluator("reference")``) to float32 round-off, on
    view ("V") and lighting ("L") frames."""
    scene = get_scene(name, "test")
    frames = make_sequence(scene, "V", n_frames=2, seed=1) + make_sequence(scene, "L", n_frames=2, seed=1)[1:]
    assert frames[2].changed == {"light"}  # the lighting rotated: the grid is re-projected
    gbs = [make_gbuffer(scene, f, 1) for f in frames]
    small = dict(frame_grid=(5, 8, 1), brdf_dirs=(4, 4), brdf_supersample=1)
    for cfg in (dict(level=1), dict(level=1, shading="vertex"), dict(level=2, n_coeffs=20, shading="vertex")):
        m = TripleProduct(**cfg, **small, progress=False)
        m.precompute(scene)
        ref_m = m.with_evaluator("reference")
        for frame, gb in zip(frames, gbs):
            ref = ref_m.render(frame, gb)
            img = m.render(frame, gb)
            scale = ref.abs().max()
            assert scale > 0, (name, cfg)
            tol = F32_LIGHT if cfg.get("n_coeffs") is None else F32  # full tables: projected by `project_env`
            assert (img - ref).abs().max() <= tol * scale, (name, cfg, frame.changed)
        assert fast_eval.fine_ok(m) == (cfg.get("n_coeffs") is None)  # level 1: the fine-value path ran


def test_prefiltered_lighting_keeps_a_small_suns_energy():
    """`lighting.prefiltered`: the projection's point samples (level 3, 4 per fine triangle, 2.8°
    apart) on a 256 × 512 map with a 2 × 2-texel sun (99 % of the energy), at 8 sun positions.
    Unfiltered, the sampled ∫ L dω misses or multiplies the sun (measured −92 % to +93 %; the bench
    bunny's ground came out at 0.63 of the reference); prefiltered to 32 rows (5.6° texels, two
    samples per texel side) the worst is 15 % (measured): what is left is the block mean's own
    error — rows are corner-aligned (Mitsuba), so a k × k block's mean sits up to half a block
    away from its rows and is weighted by its own row's solid angle. On the bench bunny the ground
    went 0.63 → 1.06 of the reference (README)."""
    import math

    from methods.core.spherical_haar import Geodesic, _spherical_triangle_area
    from methods.triple_product import lighting as lt
    from scenes.envmap import EnvMap

    geo = Geodesic(3)
    c, wn = lt._env_samples(geo, 1)
    tri = _spherical_triangle_area(geo.triangles[-1]).double()

    def sampled(env):
        vals = env.radiance(c.double()).double().reshape(geo.n, -1, 3)
        return ((vals * wn.double()[..., None]).sum(1) * tri[:, None]).sum(0)

    H, W = 256, 512
    theta = torch.arange(H, dtype=torch.float64) * math.pi / (H - 1)    # corner-aligned rows
    dA = (2 * math.pi / W) * (math.pi / (H - 1)) * torch.sin(theta)      # each texel's hat integral
    gen = torch.Generator().manual_seed(5)
    worst_raw, worst_pre = 0.0, 0.0
    for _ in range(8):
        data = torch.full((H, W, 3), 0.2)
        r, col = int(torch.randint(20, 110, (1,), generator=gen)), int(torch.randint(0, 510, (1,), generator=gen))
        data[r:r + 2, col:col + 2] = 5.0e4
        env = EnvMap(data)
        ref = (data.double() * dA[:, None, None]).sum((0, 1))
        pre_env = lt.prefiltered(env, geo, 1)
        assert pre_env.height == 32
        worst_raw = max(worst_raw, float(((sampled(env) - ref).abs() / ref).max()))
        worst_pre = max(worst_pre, float(((sampled(pre_env) - ref).abs() / ref).max()))
    assert worst_pre < 0.16, worst_pre
    assert worst_raw > 0.5, worst_raw


def test_grouped_kernel_equals_per_point_kernel():
    """`fast_eval.fine_grouped` (eq. 7 once per distinct (visibility row, L cell, ρ̃ cell), then
    blended per point) = `fine_kernel` (per point) to float32 round-off, on points that share cells
    like neighbouring G-buffer samples; `group_rows` gives every point a group with its own rows."""
    gen = torch.Generator().manual_seed(7)
    Kp, B = 80, 700
    Vt = torch.randn(40, Kp, generator=gen)
    Rt = torch.randn(12, 3 * Kp, generator=gen)
    Lt = torch.randn(24, 3 * Kp, generator=gen)
    tri = torch.randint(0, 38, (B // 7 + 1,), generator=gen).repeat_interleave(7)[:B]
    vrows = torch.stack([tri, tri + 1, tri + 2], 1)
    l0 = torch.randint(0, 20, (B // 7 + 1,), generator=gen).repeat_interleave(7)[:B]
    b0 = torch.randint(0, 8, (B // 7 + 1,), generator=gen).repeat_interleave(7)[:B]
    lrows = torch.stack([l0, l0 + 1, l0 + 3, l0 + 4], 1)   # a cell's rows: a function of its first
    brows = torch.stack([b0, b0 + 1, b0 + 2, b0 + 3], 1)
    vw, lw, bw = (torch.rand(B, k, generator=gen) for k in (3, 4, 4))
    gv, gl, gb, inv = fast_eval.group_rows(vrows, lrows, brows)
    assert gv.numel() < B  # the 3·B (point, vertex) pairs share groups
    # the run-then-unique dedup = one `torch.unique` of every (point, vertex) key: same sorted groups
    nl, nb = int(lrows[:, 0].max()) + 1, int(brows[:, 0].max()) + 1
    keys = vrows * (nl * nb) + (lrows[:, 0] * nb + brows[:, 0])[:, None]
    uk, uinv = torch.unique(keys.reshape(-1), return_inverse=True)
    assert torch.equal(gv * (nl * nb) + gl[:, 0] * nb + gb[:, 0], uk) and torch.equal(inv, uinv.view(B, 3))
    # the table bounds given (the frames' call), or cells renumbered with int64 keys (no dense
    # table, `GROUP_CELL_TABLE`; or keys past int32): the same groups, order and inverse
    for kw, table in (({"n_l": 24, "n_b": 12}, None), ({}, 0), ({"n_l": 1 << 20, "n_b": 1 << 20}, None)):
        old = fast_eval.GROUP_CELL_TABLE
        fast_eval.GROUP_CELL_TABLE = old if table is None else table
        try:
            other = fast_eval.group_rows(vrows, lrows, brows, **kw)
        finally:
            fast_eval.GROUP_CELL_TABLE = old
        assert all(torch.equal(a, b) and a.dtype == b.dtype for a, b in zip(other, (gv, gl, gb, inv)))
    # the frames' form: the groups per run of points and each point's run (int32); expanded, `group_rows`
    rgv, rgl, rgb, inv_s, run = fast_eval.group_runs(vrows, lrows, brows, n_l=24, n_b=12)
    assert all(torch.equal(a, b) for a, b in zip((rgv, rgl, rgb), (gv, gl, gb)))
    assert run.dtype == torch.int32 and inv_s.shape[0] == int(run.max()) + 1 < B
    assert torch.equal(inv_s[run.long()], inv) and bool((run.diff() >= 0).all())
    # a point differing from its neighbour in one visibility column only starts a new run
    vr2 = vrows.clone()
    vr2[5, 2] += 1
    assert torch.equal(fast_eval.group_rows(vr2, lrows, brows)[0][fast_eval.group_rows(vr2, lrows, brows)[3][5, 2]], vr2[5, 2])
    vw_, lw_, bw_ = (torch.rand(B, k, generator=gen) for k in (3, 4, 4))
    T = torch.randn(gv.shape[0], 3 * 16, generator=gen)
    assert torch.equal(fast_eval.group_blend_runs(run, inv_s, vw_, lw_, bw_, T), fast_eval.group_blend(inv, vw_, lw_, bw_, T))
    shuffled = fast_eval.group_rows(vrows.flip(0), lrows.flip(0), brows.flip(0))  # runs in another order
    assert torch.equal(shuffled[0], gv) and torch.equal(shuffled[3], inv.flip(0))
    for i in range(3):
        assert torch.equal(gv[inv[:, i]], vrows[:, i])
        assert torch.equal(gl[inv[:, i]], lrows) and torch.equal(gb[inv[:, i]], brows)
    want = fast_eval.fine_kernel(Vt, Rt, Lt, vrows, vw, brows, bw, lrows, lw)
    got = fast_eval.fine_grouped(Vt, Rt, Lt, vrows, vw, brows, bw, lrows, lw, points=64)
    assert (got - want).abs().max() <= F32 * want.abs().max()
    # every group in one call (symbolic group count, the frames' path): the blocks' sums bit for bit
    assert torch.equal(fast_eval.fine_grouped(Vt, Rt, Lt, vrows, vw, brows, bw, lrows, lw), got)


@pytest.mark.parametrize("grid,mode", [((17, 32, 1), "trilinear"), ((5, 8, 3), "trilinear"), ((5, 8, 1), "nearest")])
def test_grid_lookups_equal_the_eager_lookups(grid, mode):
    """`fast_eval.grid_lookups` (compiled, every output a 1-D plane; `lighting.cell_weights` for a
    trilinear look-up with n_psi = 1) = the eager `brdf_table.outgoing_weights` and
    `lighting.lookup_weights` (each node's two ψ entries merged when n_psi = 1) at random frames and
    ωo (5000 points: whole blocks and a padded tail): the same rows, weights to float32 round-off."""
    from methods.triple_product import brdf_table as bt
    from methods.triple_product import lighting as lt

    gen = torch.Generator().manual_seed(11)
    n = torch.nn.functional.normalize(torch.randn(5000, 3, generator=gen), dim=-1)
    n[:7] = torch.tensor([0.0, 1.0, 0.0])                                # floor normals: a grid node
    wo = torch.nn.functional.normalize(torch.randn(5000, 3, generator=gen), dim=-1)
    og, g = bt.OutgoingGrid(8, 16), lt.FrameGrid(*grid)
    R = lt.local_frames(n, "grid")
    rows, w, lrows, lw = fast_eval.grid_lookups(R, wo, og, g, mode)
    er, ew = bt.outgoing_weights((R @ wo.unsqueeze(-1)).squeeze(-1), og)
    el, elw = lt.lookup_weights(R, g, mode)
    if mode == "trilinear" and g.n_psi == 1:
        el, elw = el[:, 0::2], elw[:, 0::2] + elw[:, 1::2]
    assert torch.equal(rows, er) and torch.equal(lrows, el)
    assert (w - ew).abs().max() <= F32 and (lw - elw).abs().max() <= F32
    assert fast_eval.grid_lookups(R, wo, og, g, None)[2:] == (None, None)
    if mode == "trilinear" and g.n_psi == 1:
        # from the normals, no frames formed (`pixel_lookups`) = the compiled chain it replaces in
        # pixel frames (`fast_eval.local_frames`, then `grid_lookups`): the frames' float32 trig is
        # the same vectorised code there, so the ωo weights agree to float32 round-off (against the
        # eager frames' libm trig they differ by up to ~4e-6 near the ωo grid's poles, as
        # `fast_eval.local_frames` does)
        crow, cw, clrows, clw = fast_eval.grid_lookups(fast_eval.local_frames(n, "grid"), wo, og, g, mode)
        prow, pw, plrows, plw = fast_eval.pixel_lookups(n, wo, og, g)
        assert torch.equal(prow, crow) and torch.equal(plrows, el) and torch.equal(clrows, el)
        assert (pw - cw).abs().max() <= F32 and (plw - elw).abs().max() <= F32
        wrong = fast_eval.pixel_lookups(n, -wo, og, g)                   # ωo enters the ρ̃ look-up
        assert not torch.equal(wrong[0], er) and torch.equal(wrong[2], el)
        # with the regions (the frames' call): the ωo rows offset to each region's ρ̃ stack, as
        # `shading_rows` offsets them; the rest the same values bit for bit
        region = torch.randint(0, 5, (n.shape[0],), generator=gen)
        brow, bw, blrows, blw = fast_eval.pixel_lookups(n, wo, og, g, region)
        assert brow.dtype == torch.int64 and torch.equal(brow, prow + region[:, None] * og.size)
        assert torch.equal(bw, pw) and torch.equal(blrows, plrows) and torch.equal(blw, plw)


def _lazy_and_full(shading: str, kind: str, *, n_frames: int, seed: int):
    """A ``kind`` sequence on sphere_plane (test size) with its G-buffers, and two precomputed level-1
    `TripleProduct`s of one configuration: (frames, gbuffers, the lazily lit one, the eagerly lit one)."""
    scene = get_scene("sphere_plane", "test")
    cfg = dict(level=1, frame_grid=(9, 16, 1), brdf_dirs=(4, 4), brdf_supersample=1, shading=shading,
               progress=False)
    frames = make_sequence(scene, kind, n_frames=n_frames, seed=seed)
    gbs = [make_gbuffer(scene, f, 1) for f in frames]
    lazy_m, full_m = TripleProduct(**cfg), TripleProduct(**cfg)
    lazy_m.precompute(scene)
    full_m.precompute(scene)
    return frames, gbs, lazy_m, full_m


@pytest.mark.parametrize("shading", ["pixel", "vertex"])
def test_lazy_lighting_projects_the_looked_up_frames_only_and_renders_the_same(shading):
    """A lighting change on the fine-value path projects only the grid frames the frame looks up
    with a non-zero weight (`TripleProduct.fill_lighting` from `fast_eval.shade_fine`); the image
    equals the one rendered from the whole grid projected first, and completing the grid gives the
    whole projection's coefficients and fine values exactly (the same `lighting.project_env` blocks).
    An "L" sequence (tilted axis, general kernel) and an "E" one (probes turned about +Y)."""
    for kind in ("L", "E"):
        frames, gbs, lazy_m, full_m = _lazy_and_full(shading, kind, n_frames=3, seed=2)
        for i, (frame, gb) in enumerate(zip(frames, gbs)):
            img = lazy_m.render(frame, gb)
            # frames projected whole, or on the live triangles only (`fast_eval.live_triangles`)
            lz = lazy_m._lazy_light
            done = None if lz is None else lz["done"] | lz.get("live", torch.zeros_like(lz["done"]))
            if lz is not None and lz.get("pairs") is not None:   # the read pairs only (`lighting.project_pairs`;
                assert lazy_m.stats["projected_pairs"] == int(lz["pairs"].sum())   # E: `comb_pairs_ok`)
                done = done | lz["pairs"].any(1)
            if i == 0:              # the first lighting (the harness's warm-up frame): the whole grid
                assert done is None and lazy_m.stats["projected_frames"] == lazy_m.grid.size
            elif shading == "pixel":  # the sphere's far side and the plane's one normal: not every frame
                assert done is not None and 0 < int(done.sum()) < lazy_m.grid.size, kind
                # the compulsory count: the frames projected, not the whole grid
                assert lazy_m.stats["projected_frames"] == int(done.sum())
                P = gb.num_samples
                part = lazy_m.frame_cost(kind, P)      # the grain of the zeros: the pairs read
                rec = lazy_m.stats["last_frame"]
                reads, rec["reads"] = rec["reads"], None
                coarse = lazy_m.frame_cost(kind, P)    # the live grain: the projected frames whole
                lazy_m.stats["projected_frames"] = lazy_m.grid.size
                whole = lazy_m.frame_cost(kind, P)
                lazy_m.stats["projected_frames"], rec["reads"] = int(done.sum()), reads
                assert part.flops <= coarse.flops < whole.flops and part.bytes <= coarse.bytes < whole.bytes
            full_m._set_lighting(frame.envmap)                           # the whole grid, eagerly
            assert full_m._lazy_light is None
            want = full_m.render(frame, gb)
            assert torch.equal(img, want), (shading, kind)
            again = lazy_m.render(frame, gb)      # the next frame with this lighting completes the grid
            assert lazy_m._lazy_light is None and torch.equal(again, want)
            assert torch.equal(lazy_m.L_val, full_m.L_val)
            assert torch.equal(fast_eval.fine_table(lazy_m, "L", lazy_m.L_idx, lazy_m.L_val, lazy_m.K),
                               fast_eval.fine_table(full_m, "L", full_m.L_idx, full_m.L_val, full_m.K))
            assert lazy_m.stats["lighting_path"] == full_m.stats["lighting_path"]


@pytest.mark.parametrize("shading", ["vertex", "pixel"])
def test_lazy_lighting_recycles_the_replaced_tables_and_renders_the_same(shading):
    """Consecutive lighting changes that never complete the grid (every frame a new lighting) reuse
    the replaced lazy lighting's table memory (`TripleProduct._spare_tables`, the live-column table
    in `fill_lighting`) instead of zero-filling new tables: its stale rows are finite and read only
    with exact 0 weights, so every image equals the one rendered from the whole grid projected."""
    for kind in ("L", "E"):
        frames, gbs, lazy_m, full_m = _lazy_and_full(shading, kind, n_frames=5, seed=3)
        ptrs = []
        for i, (frame, gb) in enumerate(zip(frames, gbs)):
            img = lazy_m.render(frame, gb)
            ptrs.append(lazy_m.L_val.data_ptr())
            full_m._set_lighting(frame.envmap)                           # the whole grid, eagerly
            want = full_m.render(frame, gb)
            assert torch.equal(img, want), (shading, kind, i)
        assert ptrs[2] == ptrs[3] == ptrs[4], (shading, kind)            # recycled from the second change on



def test_pixel_render_equals_the_resolved_samples(scene_frame, monkeypatch):
    """A per-pixel frame returns `GBuffer.resolve` of its per-sample radiance bit for bit, the radiance
    scattered into a zero-filled (P, 3) array (the old form) — every sample hit in one batch (its
    radiance is the frame's: no zero-filled copy, no mask), in several batches, and with misses (the
    hit samples written into zeros, the resolve's mask skipped)."""
    import methods.triple_product.method as tpm

    scene, frame, _ = scene_frame
    gb = make_gbuffer(scene, frame, 2)                                    # 2 × 2 samples per pixel
    m = TripleProduct(level=2, n_coeffs=None, progress=False)
    m.precompute(scene)
    assert bool(gb.hit.all())
    miss = torch.zeros_like(gb.hit)
    miss[::5] = True                                                      # every fifth sample a miss
    holed = dataclasses.replace(gb, hit=gb.hit & ~miss, face=torch.where(miss, -1, gb.face),
                                region=torch.where(miss, -1, gb.region))
    seen = []
    real = fast_eval.shade_pixels

    def spy(*a, **k):
        r = real(*a, **k)
        seen.append(r.clone())
        return r

    monkeypatch.setattr(fast_eval, "shade_pixels", spy)
    for g, chunk in ((gb, tpm.FINE_RENDER_POINTS), (gb, 1000), (holed, tpm.FINE_RENDER_POINTS), (holed, 999)):
        monkeypatch.setattr(tpm, "FINE_RENDER_POINTS", chunk)
        seen.clear()
        img = m.render(frame, g)
        out = torch.zeros(g.num_samples, 3)
        out[torch.nonzero(g.hit).squeeze(-1)] = torch.cat(seen)
        assert len(seen) == -(-int(g.hit.sum()) // chunk)
        assert torch.equal(img, g.resolve(out)), (g.num_samples, chunk)
