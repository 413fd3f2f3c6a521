"""The native pair projection (`methods.triple_product.native_light`) against the compiled general
projection it stands in for (`lighting.project_env` with ``tris``: the oracle), and its pair sets
against the count's (`fast_eval.nonzero_reads`)."""
from __future__ import annotations

import pytest
import torch

from methods.triple_product import fast_eval, native_light

pytestmark = pytest.mark.skipif(not native_light.available(), reason="no C compiler (the compiled kernels run)")


@pytest.mark.parametrize("supersample", [0, 1, 2])
def test_project_pairs_equals_the_compiled_projection(supersample):
    """`lighting.project_pairs` writes the compiled live-triangle projection's fine values bit for bit
    (4^s = 1, 4, 16 samples per triangle; the quad rows' lane weights formed from fx, fy directly),
    into the listed (frame, triangle) entries only, the same bits on 1, 2 and 3 threads; it needs a
    map that is not turned about +Y only (`lighting.pairs_ok`)."""
    from methods.core.spherical_haar import Geodesic
    from methods.core.threads import torch_threads
    from methods.triple_product import lighting as lt
    from scenes.library import get_scene
    from scenes.sequences import rotation_y

    g = lt.FrameGrid(5, 8, 1)                                             # 40 frames
    geo, R = Geodesic(1), lt.grid_frames(g)
    tris = torch.tensor([0, 2, 3, 7, 11, 12, 40, 41, 63, 79])
    base = get_scene("bunny", "test").envmap
    gen = torch.Generator().manual_seed(5)
    for rot in ([[1.0, 0.0, 0.0], [0.0, 0.6, -0.8], [0.0, 0.8, 0.6]], [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]):
        env = lt.prefiltered(base.rotated(rot), geo, supersample)
        assert lt.pairs_ok(env)
        whole = lt.project_env(env, R, geo, supersample=supersample, grid=g, tris=tris)[1]   # (F, 3, n')
        sel = torch.rand(g.size, tris.numel(), generator=gen) < 0.4
        pairs = torch.nonzero(sel.view(-1)).squeeze(-1)
        fill = torch.full((g.size, 3, tris.numel()), 7.0)
        with torch_threads(1):
            one = lt.project_pairs(env, R, geo, supersample=supersample, tris=tris, pairs=pairs, out=fill.clone())
        m = sel[:, None, :].expand(-1, 3, -1)
        assert torch.equal(one[m], whole[m]) and bool((one[~m] == 7.0).all())
        old = native_light.MIN_PAIRS_PER_THREAD
        native_light.MIN_PAIRS_PER_THREAD = 4
        try:
            for nt in (2, 3):
                with torch_threads(nt):
                    got = lt.project_pairs(env, R, geo, supersample=supersample, tris=tris, pairs=pairs, out=fill.clone())
                assert torch.equal(got, one), nt
        finally:
            native_light.MIN_PAIRS_PER_THREAD = old
        every = torch.arange(g.size * tris.numel())
        assert torch.equal(lt.project_pairs(env, R, geo, supersample=supersample, tris=tris, pairs=every,
                                            out=torch.zeros_like(whole)), whole)
        mixed = every[torch.randperm(every.numel(), generator=gen)]      # out of order: frames revisited
        with torch_threads(1):
            assert torch.equal(lt.project_pairs(env, R, geo, supersample=supersample, tris=tris, pairs=mixed,
                                                out=torch.zeros_like(whole)), whole)
    assert not lt.pairs_ok(base.rotated(rotation_y(0.7)))               # the azimuthal / comb paths
    with pytest.raises(IndexError):
        native_light.project(torch.tensor([g.size * tris.numel()]), torch.zeros(g.size, 3, 3),
                             torch.zeros(3, tris.numel(), 4), torch.zeros(tris.numel(), 4), 8, 16,
                             torch.zeros(8 * 17, 16), torch.zeros(g.size, 3, tris.numel()))


def test_project_pairs_builds_agree():
    """The library built without the host's ISA flags (no AVX2: `pair_means` for every S) and the one
    built with AVX2 only (the 16-sample pairs take `pairs16x2`, two at a time) write the same bits as
    the one the frames use (on an AVX-512 host `zproject16`, four pairs in 16-lane vectors), for
    supersample 2 on a tilted map: all the compiled projection's values; pair counts that are not a
    multiple of two or four (the last pairs repeated) too."""
    from methods.core import native
    from methods.core.spherical_haar import Geodesic
    from methods.core.threads import torch_threads
    from methods.triple_product import lighting as lt
    from scenes.library import get_scene

    g = lt.FrameGrid(9, 16, 1)
    geo, R = Geodesic(2), lt.grid_frames(g)
    tris = torch.arange(0, 320, 3)
    tilt = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.6, -0.8], [0.0, 0.8, 0.6]]) \
        @ torch.tensor([[0.8, -0.6, 0.0], [0.6, 0.8, 0.0], [0.0, 0.0, 1.0]])
    env = lt.prefiltered(get_scene("bunny", "test").envmap.rotated(tilt.tolist()), geo, 2)
    whole = lt.project_env(env, R, geo, supersample=2, grid=g, tris=tris)[1]
    pairs = torch.arange(g.size * tris.numel())
    plain = native.load("tp_light_pairs_plain", native_light._SOURCE, native_light._SIGNATURES,
                        extra_flags=("-ffp-contract=off", "-fno-trapping-math", "-fopenmp"))
    if plain is None:
        pytest.skip("the library did not build without ISA flags")
    builds = {"plain": plain}
    if native.isa_flags():
        builds["avx2"] = native.load("tp_light_pairs_avx2", native_light._SOURCE, native_light._SIGNATURES,
                                     extra_flags=native_light._flags())
    keep = native_light._lib

    def run(lib, sel):
        native_light._lib = (lambda: lib) if lib is not None else keep
        try:
            with torch_threads(1):
                return lt.project_pairs(env, R, geo, supersample=2, tris=tris, pairs=sel, out=torch.zeros_like(whole))
        finally:
            native_light._lib = keep

    assert torch.equal(run(None, pairs), whole)
    for name, lib in builds.items():
        assert lib is not None and torch.equal(run(lib, pairs), whole), name
    for cut in (1, 2, 3):                                  # counts 1, 2, 3 past a multiple of four
        sel = pairs[1::2][:(pairs.numel() // 8) * 4 + cut]
        m = torch.zeros(whole.shape[0] * whole.shape[2], dtype=torch.bool).index_fill_(0, sel, True)
        m = m.view(whole.shape[0], 1, -1).expand(-1, 3, -1)
        for lib in (None, *builds.values()):
            one = run(lib, sel)
            assert torch.equal(one[m], whole[m]) and bool((one[~m] == 0).all()), cut


@pytest.mark.parametrize("grid", [(5, 8, 1), (5, 8, 2), (4, 4, 1), (3, 16, 3), (5, 32, 1)])
def test_comb_pairs_equal_the_comb_path(grid):
    """For a map turned about +Y only (`lighting.comb_pairs_ok`), `lighting.project_pairs` writes the
    comb path's fine values (`project_env` with ``tris``: `comb_taps`, `comb_means` — on one thread,
    whose reduction adds each output's terms in one sequence) bit for bit into the listed pairs, and
    into the other frames of their 8-frame groups (J = n_phi frames per base row: whole groups, and J
    = 4 frames one by one), nothing else; the same bits on 1, 2 and 3 threads; n_psi > 1 (base rows
    i·n_psi + k) too."""
    from methods.core.spherical_haar import Geodesic
    from methods.core.threads import torch_threads
    from methods.triple_product import lighting as lt
    from scenes.library import get_scene
    from scenes.sequences import rotation_y

    g = lt.FrameGrid(*grid)
    lev = 2 if g.n_phi >= 16 else 1
    geo, R = Geodesic(lev), lt.grid_frames(g)
    tris = torch.arange(0, 20 * 4 ** lev, 3)
    env = lt.prefiltered(get_scene("bunny", "test").envmap.rotated(rotation_y(0.7)), geo, 2)
    assert lt.comb_pairs_ok(env, g) and not lt.pairs_ok(env)
    with torch_threads(1):
        whole = lt.project_env(env, R, geo, supersample=2, grid=g, tris=tris)[1]
    gen = torch.Generator().manual_seed(3)
    sel = torch.rand(g.size, tris.numel(), generator=gen) < 0.05
    pairs = torch.nonzero(sel.view(-1)).squeeze(-1)
    J, F, n = g.n_phi, g.size, tris.numel()
    f = torch.arange(F)
    b = f // (J * g.n_psi) * g.n_psi + f % g.n_psi                               # base row i·n_psi + k
    key = (b * 8 + f // g.n_psi % J // 8)[:, None] * n + torch.arange(n)          # (base row, group of j, t)
    hit = torch.zeros_like(sel)
    hit.view(-1)[torch.isin(key.view(-1), key.view(-1)[pairs])] = True
    if J % 8:
        hit = sel                                                                # frames one by one
    m = sel[:, None, :].expand(-1, 3, -1)
    h = hit[:, None, :].expand(-1, 3, -1)
    old = native_light.MIN_PAIRS_PER_THREAD
    native_light.MIN_PAIRS_PER_THREAD = 4
    try:
        for nt in (1, 2, 3):
            with torch_threads(nt):
                got = lt.project_pairs(env, R, geo, supersample=2, tris=tris, pairs=pairs,
                                       out=torch.full((F, 3, n), 7.0), grid=g)
            assert torch.equal(got[m], whole[m]), nt
            assert torch.equal(got[h], whole[h]) and bool((got[~h] == 7.0).all()), nt
    finally:
        native_light.MIN_PAIRS_PER_THREAD = old
    with pytest.raises(ValueError):                                              # the general loop's map only
        lt.project_pairs(env, R, geo, supersample=2, tris=tris, pairs=pairs, out=torch.zeros(F, 3, n))


@pytest.mark.parametrize("H, W, grid, gamma", [(64, 128, (17, 32, 1), 0.7), (24, 96, (5, 32, 1), 2.1),
                                                (20, 160, (5, 32, 2), 5.9), (16, 64, (4, 16, 1), 1.3),
                                                (12, 40, (3, 8, 3), 0.2), (10, 36, (3, 4, 1), 4.4)])
def test_comb_pairs_with_taps_in_the_loop_equal_the_compiled_taps(H, W, grid, gamma):
    """`lighting.project_pairs`' comb path with each listed item's taps made in the C loop
    (`native_light.comb_pairs_uv`, ``COMB_TAPS_NATIVE``) writes the same entries with the same bits as
    `native_light.comb_pairs` of the compiled `lighting.comb_taps` over every item (its oracle) — maps
    whose width is not a power of two (the shift 0.5 / W rounded to float32), n_psi > 1, J = 4 (frames
    one by one), HDR texels — on 1 and 2 threads."""
    from methods.core.spherical_haar import Geodesic
    from methods.core.threads import torch_threads
    from methods.triple_product import lighting as lt
    from scenes.envmap import EnvMap
    from scenes.sequences import rotation_y

    gen = torch.Generator().manual_seed(H + W)
    g = lt.FrameGrid(*grid)
    geo, R = Geodesic(2), lt.grid_frames(g)
    env = EnvMap(torch.rand(H, W, 3, generator=gen) ** 6 * 50).rotated(rotation_y(gamma))
    assert lt.comb_pairs_ok(env, g)
    tris = torch.arange(1, 320, 3)
    F, n = g.size, tris.numel()
    pairs = torch.nonzero((torch.rand(F, n, generator=gen) < 0.3).view(-1)).squeeze(-1)
    old, oldm = lt.COMB_TAPS_NATIVE, native_light.MIN_PAIRS_PER_THREAD
    native_light.MIN_PAIRS_PER_THREAD = 4
    try:
        for nt in (1, 2):
            outs = []
            for fused in (False, True):
                lt.COMB_TAPS_NATIVE = fused
                with torch_threads(nt):
                    outs.append(lt.project_pairs(env, R, geo, supersample=2, tris=tris, pairs=pairs,
                                                 out=torch.full((F, 3, n), 7.0), grid=g))
            assert torch.equal(outs[0], outs[1]), nt
            assert bool((outs[1] != 7.0).any())
    finally:
        lt.COMB_TAPS_NATIVE, native_light.MIN_PAIRS_PER_THREAD = old, oldm


def test_native_box_filter_equals_the_torch_passes():
    """`native_light.box` (what `lighting.box_filtered` runs when built) gives the torch passes' texels bit
    for bit — rows summed in float64 first, then columns, in order — also where the order matters (texels
    spanning ~2^40: a different order rounds differently); other layouts fall back (None)."""
    from methods.triple_product import lighting as lt

    gen = torch.Generator().manual_seed(11)
    x = torch.rand(48, 96, 3, generator=gen) ** 8 * 1e3
    x[::5, ::3] *= 1e12                                                   # a block's terms ~2^40 apart
    # 4 x 4 blocks whose float32 mean rounds by the order: an exact float32 midpoint 1 + 2^-24 and two
    # 2^-53 terms, lost one by one (each a float64 tie, to even) but not when added to each other first
    e, h = 2.0 ** -53, 2.0 ** -24
    x[0:4, 0:4] = 0
    x[0, 0], x[1, 0], x[0, 1], x[0, 2] = 1.0, h, e, e                     # the column sums' order
    x[4:8, 4:8] = 0
    x[4, 4], x[5, 4], x[6, 4], x[7, 4] = e, e, 1.0, h                     # the rows' order within a column
    want = lt.box_filtered(x, 4, native=False)
    assert float(want[0, 0, 0]) == 1 / 16 and float(want[1, 1, 0]) > 1 / 16         # the order, seen
    for k in (2, 4, 8, 3):
        if 48 % k or 96 % k:
            continue
        assert torch.equal(native_light.box(x, k), lt.box_filtered(x, k, native=False)), k
        assert torch.equal(lt.box_filtered(x, k), lt.box_filtered(x, k, native=False)), k
    assert native_light.box(x.double(), 2) is None and native_light.box(x.transpose(0, 1), 2) is None


@pytest.mark.parametrize("n", [1, 45, 640])
def test_take_is_the_new_pairs(n):
    """`native_light.take` = ``nonzero(need & ~done)`` (flat, in order), ``done |= that`` and the
    frames holding one, as the torch operations it replaces (its fallback); nothing new: empty."""
    gen = torch.Generator().manual_seed(9)
    F = 37
    need = torch.rand(F, n, generator=gen) < 0.4
    done = torch.rand(F, n, generator=gen) < 0.3
    need[5], done[6] = False, True                                          # frames with nothing new
    todo = need & ~done
    want = torch.nonzero(todo.view(-1)).squeeze(-1)
    d = done.clone()
    pairs, nf = native_light.take(need, d)
    assert pairs.dtype == torch.int64 and torch.equal(pairs, want) and nf == int(todo.any(1).sum())
    assert torch.equal(d, done | need)
    pairs, nf = native_light.take(need, d)
    assert pairs.numel() == 0 and nf == 0 and torch.equal(d, done | need)


@pytest.mark.parametrize("n", [1, 45, 64, 130, 640])
def test_take_of_the_bit_table_is_take_of_the_bools(n):
    """`native_light.take` of `need`'s bit table (`native_light.NeedBits`, what `fast_eval.read_pairs`
    returns) gives `take` of the (F, n) bools: the same pairs in the same order, the same done and frame
    count — with bits set past column n in the last word (not pairs), frames with nothing new, and a
    second take (nothing new: empty)."""
    gen = torch.Generator().manual_seed(12)
    F, nw = 37, -(-n // 64)
    words = torch.randint(-2 ** 62, 2 ** 62, (F, nw), generator=gen) * torch.randint(1, 3, (F, nw), generator=gen)
    words[5] = 0                                                             # a frame with nothing
    bits = native_light.NeedBits(words, n)
    need = bits.dense()
    assert need.shape == (F, n) and bool(need.any())
    done = torch.rand(F, n, generator=gen) < 0.3
    done[7] = need[7]                                                        # a frame with nothing new
    d1, d2 = done.clone(), done.clone()
    p1, f1 = native_light.take(need, d1)
    p2, f2 = native_light.take(bits, d2)
    assert torch.equal(p1, p2) and f1 == f2 and torch.equal(d1, d2)
    p2, f2 = native_light.take(bits, d2)
    assert p2.numel() == 0 and f2 == 0 and torch.equal(d1, d2)


def test_comb_scatter_is_the_gather_and_copy():
    """`native_light.comb_scatter` writes the rows the comb path's gather and copy wrote
    (``out.index_copy_(0, frames, lighting._comb_select(means.permute(0, 3, 2, 1), rows))``), the same
    values, leaves the other frames' rows alone, and refuses (False) a non-contiguous table."""
    from methods.triple_product import lighting as lt

    gen = torch.Generator().manual_seed(11)
    g = lt.FrameGrid(5, 8, 2)
    B, J, n = g.n_theta * g.n_psi, g.n_phi, 37                           # base rows b = i·n_psi + k, frames j
    means = torch.randn(B, n, 3, J, generator=gen)
    frames = torch.randperm(g.size, generator=gen)[: g.size // 2 + 3]
    rows = lt._comb_rows(g, frames)
    want = torch.full((g.size, 3, n), 7.0)
    want.index_copy_(0, frames, lt._comb_select(means.permute(0, 3, 2, 1), rows))
    got = torch.full((g.size, 3, n), 7.0)
    assert native_light.comb_scatter(means, rows, frames, got)
    assert torch.equal(got, want)
    assert not native_light.comb_scatter(means, rows, frames, torch.zeros(g.size, n, 3).transpose(1, 2))
    with pytest.raises(IndexError):
        native_light.comb_scatter(means, rows + B * J, frames, got)


@pytest.mark.parametrize("n", [45, 64, 130])
def test_need_is_the_read_pairs(n):
    """`native_light.need` = the (grid row, column) pairs some point reads with a non-zero grid
    weight and a non-zero visibility (a visibility row with a zero weight does not count), computed
    directly; points repeated back to back (skipped by the loop), points repeating only the previous
    one's visibility rows (its OR reused, the grid rows it shares with the previous point skipped),
    rows that are all zero; the points split over 1, 2 and 3 threads (the same pairs)."""
    from methods.core.threads import torch_threads

    gen = torch.Generator().manual_seed(6)
    N, F, B = 11, 13, 300
    V = torch.rand(N, n, generator=gen) * (torch.rand(N, n, generator=gen) < 0.3)
    V[0] = 0
    V[1, -1] = 0.5                                                          # the last bit of a word
    for kv, kl, vis_only in ((1, 4, False), (3, 4, False), (3, 8, False), (3, 4, True), (1, 2, True)):
        vrows = torch.randint(0, N, (B, kv), generator=gen)
        lrows = torch.randint(0, F, (B, kl), generator=gen)
        vw = torch.rand(B, kv, generator=gen) * (torch.rand(B, kv, generator=gen) < 0.8)
        lw = torch.rand(B, kl, generator=gen) * (torch.rand(B, kl, generator=gen) < 0.7)
        rep = torch.arange(B) // 3                                            # each point three times in a row
        if vis_only:                                                         # the visibility rows only, grid
            vrows, vw = vrows[rep], vw[rep]                                  # rows partly the previous point's
            lrows = torch.where(torch.rand(B, kl, generator=gen) < 0.5, lrows, lrows[rep])
        else:
            vrows, lrows, vw, lw = vrows[rep], lrows[rep], vw[rep], lw[rep]
        # the first of each three with more zero weights: its repeats read more (not skipped)
        lw[0::3] = lw[0::3] * (torch.rand(lw[0::3].shape, generator=gen) < 0.5)
        vw[0::3] = vw[0::3] * (torch.rand(vw[0::3].shape, generator=gen) < 0.5)
        want = torch.zeros(F, n, dtype=torch.bool)
        for p in range(B):
            vis = torch.zeros(n, dtype=torch.bool)
            for j in range(kv):
                if vw[p, j] != 0:
                    vis |= V[vrows[p, j]] != 0
            for j in range(kl):
                if lw[p, j] != 0:
                    want[lrows[p, j]] |= vis
        old = native_light.MIN_POINTS_PER_THREAD
        native_light.MIN_POINTS_PER_THREAD = 16
        try:
            for nt in (1, 2, 3):
                with torch_threads(nt):
                    got = native_light.need(native_light.vis_bits(V), vrows, vw, lrows, lw, F, n)
                    bits = native_light.need(native_light.vis_bits(V), vrows, vw, lrows, lw, F, n, as_bits=True)
                assert got.dtype == torch.bool and torch.equal(got, want), (kv, kl, vis_only, nt)
                assert isinstance(bits, native_light.NeedBits) and torch.equal(bits.dense(), want), (kv, kl, nt)
        finally:
            native_light.MIN_POINTS_PER_THREAD = old
    with pytest.raises(IndexError):
        native_light.need(native_light.vis_bits(V), vrows, vw, lrows + F, lw, F, n)


@pytest.mark.parametrize("shading", ["vertex", "pixel"])
def test_lazy_lighting_projects_the_read_pairs_that_the_count_counts(shading):
    """A lighting change ("L": tilted axis) on the fine-value path projects the (frame, live triangle)
    pairs its points read (`fast_eval.read_pairs`): exactly the pairs `frame_cost` counts
    (`fast_eval.nonzero_reads`), and the image equals the one from the whole grid projected first."""
    from methods.triple_product import TripleProduct
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    scene = get_scene("sphere_plane", "test")
    cfg = dict(level=1, frame_grid=(9, 16, 1), brdf_dirs=(4, 4), brdf_supersample=1, shading=shading, progress=False)
    frames = make_sequence(scene, "L", n_frames=3, seed=2)
    lazy_m, full_m = TripleProduct(**cfg), TripleProduct(**cfg)
    lazy_m.precompute(scene)
    full_m.precompute(scene)
    for i, frame in enumerate(frames):
        gb = make_gbuffer(scene, frame, 1)
        img = lazy_m.render(frame, gb)
        full_m._set_lighting(frame.envmap)
        assert torch.equal(img, full_m.render(frame, gb)), i
        if i == 0:
            continue
        lz = lazy_m._lazy_light
        live = fast_eval.live_triangles(lazy_m)
        assert lz is not None and lz["pairs"] is not None and live is not None
        rec = lazy_m.last_frame()
        count = fast_eval.nonzero_reads(lazy_m, live, rec["reads"], k_v=3 if shading == "pixel" else 1, pairs=True)
        assert lazy_m.stats["projected_pairs"] == int(lz["pairs"].sum()) == count["pairs"] > 0
        assert count["pairs"] < int(lz["pairs"].any(1).sum()) * live.numel()       # fewer than the frames' rows


@pytest.mark.parametrize("blk", [0, 1, 5, 64])
def test_comb_pairs_dynamic_blocks_same_bits(blk, monkeypatch):
    """Session 39: the comb loops (`native_light.comb_pairs_uv`, and `comb_pairs` of the compiled taps)
    at 2 and 3 threads with their items handed out dynamically in blocks of `COMB_BLOCK` (0: contiguous
    ranges, one a thread) write the same entries with the same bits as one thread."""
    from methods.core.spherical_haar import Geodesic
    from methods.core.threads import torch_threads
    from methods.triple_product import lighting as lt
    from scenes.envmap import EnvMap
    from scenes.sequences import rotation_y

    gen = torch.Generator().manual_seed(blk)
    g = lt.FrameGrid(5, 32, 1)
    geo, R = Geodesic(2), lt.grid_frames(g)
    env = EnvMap(torch.rand(24, 96, 3, generator=gen) ** 6 * 50).rotated(rotation_y(2.1))
    assert lt.comb_pairs_ok(env, g)
    tris = torch.arange(1, 320, 2)
    F, n = g.size, tris.numel()
    pairs = torch.nonzero((torch.rand(F, n, generator=gen) < 0.3).view(-1)).squeeze(-1)
    monkeypatch.setattr(native_light, "MIN_PAIRS_PER_THREAD", 4)
    for fused in (False, True):
        monkeypatch.setattr(lt, "COMB_TAPS_NATIVE", fused)
        with torch_threads(1):
            want = lt.project_pairs(env, R, geo, supersample=2, tris=tris, pairs=pairs,
                                    out=torch.full((F, 3, n), 7.0), grid=g)
        assert bool((want != 7.0).any())
        monkeypatch.setattr(native_light, "COMB_BLOCK", blk)
        for nt in (2, 3):
            with torch_threads(nt):
                got = lt.project_pairs(env, R, geo, supersample=2, tris=tris, pairs=pairs,
                                       out=torch.full((F, 3, n), 7.0), grid=g)
            assert torch.equal(got, want), (fused, nt)
        monkeypatch.setattr(native_light, "COMB_BLOCK", 64)


@pytest.mark.parametrize("blk", [0, 1, 3, 256])
def test_project_pairs_dynamic_blocks_same_bits(blk, monkeypatch):
    """Session 39: `lighting.project_pairs` (the general pair loop, `native_light.project`) at 2 and 3
    threads with its pairs handed out dynamically in blocks of `PROJECT_BLOCK` (0: contiguous ranges,
    one a thread; blocks that are not whole 4-pair vectors too) writes the same bits as one thread,
    16 samples a triangle (the method's default) and 4."""
    from methods.core.spherical_haar import Geodesic
    from methods.core.threads import torch_threads
    from methods.triple_product import lighting as lt
    from scenes.library import get_scene

    g = lt.FrameGrid(5, 8, 1)
    geo, R = Geodesic(1), lt.grid_frames(g)
    tris = torch.arange(0, 80, 2)
    gen = torch.Generator().manual_seed(7 + blk)
    rot = [[1.0, 0.0, 0.0], [0.0, 0.6, -0.8], [0.0, 0.8, 0.6]]
    monkeypatch.setattr(native_light, "MIN_PAIRS_PER_THREAD", 4)
    for supersample in (1, 2):
        env = lt.prefiltered(get_scene("bunny", "test").envmap.rotated(rot), geo, supersample)
        assert lt.pairs_ok(env)
        pairs = torch.nonzero((torch.rand(g.size, tris.numel(), generator=gen) < 0.4).view(-1)).squeeze(-1)
        fill = torch.full((g.size, 3, tris.numel()), 7.0)
        with torch_threads(1):
            one = lt.project_pairs(env, R, geo, supersample=supersample, tris=tris, pairs=pairs, out=fill.clone())
        assert bool((one != 7.0).any())
        monkeypatch.setattr(native_light, "PROJECT_BLOCK", blk)
        for nt in (2, 3):
            with torch_threads(nt):
                got = lt.project_pairs(env, R, geo, supersample=supersample, tris=tris, pairs=pairs, out=fill.clone())
            assert torch.equal(got, one), (supersample, nt)
        monkeypatch.setattr(native_light, "PROJECT_BLOCK", 256)


@pytest.mark.parametrize("threads", [2, 3, 5])
def test_native_box_filter_threads_same_texels(threads, monkeypatch):
    """Session 39: `native_light.box` with its output rows split over the threads (`BOX_THREADS`) gives
    one thread's texels bit for bit (= the torch passes), also with more threads than output rows."""
    from methods.core.threads import torch_threads
    from methods.triple_product import lighting as lt

    gen = torch.Generator().manual_seed(threads)
    x = torch.rand(48, 96, 3, generator=gen) ** 8 * 1e3
    x[::5, ::3] *= 1e12
    monkeypatch.setattr(native_light, "MIN_BOX_ROWS_PER_THREAD", 1)
    for k in (2, 4, 8, 16):
        want = lt.box_filtered(x, k, native=False)
        with torch_threads(threads):
            got = native_light.box(x, k)
        assert torch.equal(got, want), k
