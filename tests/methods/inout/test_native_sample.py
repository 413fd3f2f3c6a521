"""In-out's per-sample C loop (``methods.inout.native_sample``, `InOut._render_native`) against the
compiled path it replaces (``fast.prepare`` + ``fast.shade_pixels``, kept as its fallback and test
oracle) and the reference path: the same image to float32 round-off, whatever the memo window (W = 2:
nearly every entry summed exactly; W = the table: none), over V / L / E sequences (c of every vertex,
then lazily of the referenced ones), bit for bit the same at 1 and 2 threads."""
from __future__ import annotations

import copy

import pytest
import torch

from methods.inout import native_sample
from methods.inout.method import InOut
from references.gbuffer import make_gbuffer
from scenes.library import get_scene
from scenes.sequences import make_sequence

TINY = dict(brdf_res=8, cube_res=4, n_coeffs=16, lut_res=16, light_supersample=2, terms=6)
RTOL = 1e-5   # as test_fast.py: the same terms summed in another order, float32

pytestmark = pytest.mark.skipif(not native_sample.available(), reason="no C compiler (the compiled path runs)")


@pytest.fixture(scope="module")
def precomputed():
    built = {}

    def get(name: str) -> InOut:
        if name not in built:
            m = InOut(**{**TINY, **({"terms": None} if name == "sphere_plane" else {})})
            m.precompute(get_scene(name, "test"))
            built[name] = m
        return built[name]

    return get


def _spy(monkeypatch, calls: list):
    """Each frame's loop call (`InOut` keeps its bound call: `Bound.frame`) appends its stats to ``calls``;
    returns the unpatched `Bound.frame`."""
    shade = native_sample.Bound.frame

    def spy(self, *a, **k):
        got = shade(self, *a, **k)
        calls.append(got[1])
        return got

    monkeypatch.setattr(native_sample.Bound, "frame", spy)
    return shade


def _copy(m: InOut) -> InOut:
    c = copy.copy(m)
    c._reset_cache()
    return c


@pytest.mark.parametrize("tiles", [False, True])
@pytest.mark.parametrize("W", [2, 4, 16])
@pytest.mark.parametrize("name", ["bunny", "chess", "creature", "sphere_plane"])
def test_native_sample_equals_the_compiled_path(precomputed, monkeypatch, name, W, tiles):
    """Every frame of V, L and E sequences: the C loop's image equals the compiled path's (and the
    reference's) to float32 round-off; with W = 2 entries take the exact sum, with W ≥ 4 the memo
    (the per-sample loop, `FAST` without bit 256); with the tiles (bit 256, no memo) the same images."""
    m = precomputed(name)
    monkeypatch.setattr(native_sample, "WINDOW", W)
    monkeypatch.setattr(native_sample, "FAST", native_sample.FAST | 256 if tiles else native_sample.FAST & 255)
    calls = []
    _spy(monkeypatch, calls)
    for kind in ("V", "L", "E"):
        new, old, ref = _copy(m), _copy(m), _copy(m)
        old._render_native = lambda f, g: None
        for frame in make_sequence(m.scene, kind, n_frames=3, seed=5):
            gb = make_gbuffer(m.scene, frame, 2)
            got, want, exact = new.render(frame, gb), old.render(frame, gb), ref._render_reference(frame, gb)
            scale = float(exact.abs().max())
            assert scale > 0
            assert float((got - want).abs().max()) <= RTOL * scale, f"{name} {kind} frame {frame.index} W {W}"
            assert float((got - exact).abs().max()) <= RTOL * scale, f"{name} {kind} frame {frame.index} W {W}"
    made, summed = sum(c[0] for c in calls), sum(c[1] for c in calls)
    assert len(calls) == 9 and made > 0
    if tiles and native_sample.cells_available():
        assert summed == 0         # no window: every X of a tile computed there
    elif W == 2:
        assert summed > 0          # the exact sums ran
    if W >= 16:
        assert summed == 0         # the window is the whole table (R = 16)


@pytest.mark.parametrize("fast", [1, 2, 3, 7, 15])
@pytest.mark.parametrize("name", ["chess", "creature"])
def test_native_sample_variants_equal_session_29s_loop(precomputed, monkeypatch, name, fast):
    """The loop's variants (`native_sample.FAST`) against session 29's loop (FAST = 0), the compiled
    path and the reference, over a V and an L sequence with the G-buffer's layouts (column-major ω_o
    and barycentrics, row-major normals) and row-major copies: bit 1 (each array read along its own
    layout) the same image bit for bit; bit 2 (the dot products fused, 16 lanes on AVX-512 builds)
    and bits 4 and 8 (`cell_x`, the last sample's X reused) the same to float32 round-off, with W = 2
    (nearly every entry on the exact path) and W = 4."""
    m = precomputed(name)
    for W in (2, 4):
        monkeypatch.setattr(native_sample, "WINDOW", W)
        for kind in ("V", "L"):
            new, old, comp, ref = _copy(m), _copy(m), _copy(m), _copy(m)
            comp._render_native = lambda f, g: None
            for frame in make_sequence(m.scene, kind, n_frames=2, seed=7):
                gb = make_gbuffer(m.scene, frame, 2)
                for g in (gb, _row_major(gb)):
                    monkeypatch.setattr(native_sample, "FAST", fast)
                    got = new.render(frame, g)
                    monkeypatch.setattr(native_sample, "FAST", 0)
                    want = old.render(frame, g)
                    exact, cimg = ref._render_reference(frame, g), comp.render(frame, g)
                    scale = float(exact.abs().max())
                    assert scale > 0
                    if fast & 2:
                        assert float((got - want).abs().max()) <= RTOL * scale, f"{name} {kind} W {W}"
                    else:
                        assert torch.equal(got, want), f"{name} {kind} W {W}"
                    assert float((got - cimg).abs().max()) <= RTOL * scale
                    assert float((got - exact).abs().max()) <= RTOL * scale


@pytest.mark.parametrize("name", ["chess", "creature", "sphere_plane"])
def test_native_sample_cells_same_bits_any_window_and_reuse(precomputed, monkeypatch, name):
    """Bit 4 (`cell_x`: a memo row and an entry outside its vertex's window by one function of the
    (vertex, node) pair) and bit 8 (the last shaded sample's vertices and X reused on the same face
    and cell): the image is the same bits whatever the window (W = 2: nearly every entry outside it;
    W = 16, the whole table: none) and with or without the reuse (which ran: fewer entries computed
    outside the window), over a V and an L sequence, and equals session 29's loop (FAST = 0) and the
    reference to float32 round-off. Bit 16 (each thread's cache of (face, cell) entries) the same bits
    again, with fewer entries summed exactly, and with a 2-entry cache (nearly every look-up evicts); the
    L sequence's frames meet the same keys under another lighting (an entry of an earlier call is stale).
    Bit 32 (`x4_sums`: `cell_x`'s 12 sums at once, on AVX-512 builds) the same bits again, with and
    without bit 16, and bits 64 and 128 (the front end 16 samples wide, the next block prefetched) again."""
    if not native_sample.cells_available():
        pytest.skip("no FMA build: bits 4 and 8 fall back to the per-row loop")
    m = precomputed(name)
    shade = native_sample.Bound.frame          # the loop of a frame (`InOut` keeps its bound call)
    for kind in ("V", "L"):
        frames = make_sequence(m.scene, kind, n_frames=2, seed=11)
        gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
        imgs, exact = {}, {}
        for fast, ylog in ((7, 10), (15, 10), (31, 10), (31, 1), (47, 10), (63, 10), (127, 10), (255, 10), (0, 10)):
            for W in ((2, 4, 16) if fast else (4,)):
                monkeypatch.setattr(native_sample, "FAST", fast)
                monkeypatch.setattr(native_sample, "WINDOW", W)
                monkeypatch.setattr(native_sample, "YCACHE_LOG", ylog)
                calls = []

                def spy(self, *a, **k):
                    got = shade(self, *a, **k)
                    calls.append(got[1][1])
                    return got

                monkeypatch.setattr(native_sample.Bound, "frame", spy)
                a = _copy(m)
                imgs[fast, W, ylog] = [a.render(f, g) for f, g in zip(frames, gbs)]
                exact[fast, W, ylog] = sum(calls)
                monkeypatch.setattr(native_sample.Bound, "frame", shade)
        ref = _copy(m)
        want = [ref._render_reference(f, g) for f, g in zip(frames, gbs)]
        for key, got in imgs.items():
            for i, (x, y, r) in enumerate(zip(got, imgs[15, 4, 10], want)):
                scale = float(r.abs().max())
                assert scale > 0
                assert float((x - r).abs().max()) <= RTOL * scale, f"{name} {kind} {key} frame {i}"
                if key[0]:
                    assert torch.equal(x, y), f"{name} {kind} {key} frame {i}"
        assert exact[15, 16, 10] == exact[7, 16, 10] == exact[31, 16, 10] == 0
        assert 0 < exact[31, 2, 10] < exact[15, 2, 10] < exact[7, 2, 10]


@pytest.mark.parametrize("name", ["chess", "creature"])
def test_native_sample_wide_front_end_same_bits(precomputed, monkeypatch, name):
    """Bit 64 (AVX-512 builds: the row-major normals split 16 rows at a time by permutes, the samples'
    frames and cells 16 at a time) and bit 128 (the next block's G-buffer rows prefetched): the same
    image bits as without them, over a V and an L sequence, with the G-buffer's layouts (row-major
    normals: the split runs) and row-major copies of every array, at 2 threads in chunks of 99 pixels
    (blocks of 396 samples: a tail of 12 after the 16-row steps)."""
    monkeypatch.setattr(native_sample, "MIN_PER_THREAD", 1)
    monkeypatch.setattr(native_sample, "CHUNK", 99)
    m = precomputed(name)
    n = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        for kind in ("V", "L"):
            frames = make_sequence(m.scene, kind, n_frames=2, seed=13)
            gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
            assert gbs[0].normal.stride() == (3, 1)          # the layout the 16-row split reads
            assert gbs[0].num_samples // 4 > 2 * 99
            imgs = {}
            for fast in (native_sample.FAST | 192, native_sample.FAST & ~192):
                monkeypatch.setattr(native_sample, "FAST", fast)
                a = _copy(m)
                imgs[fast] = [a.render(f, g) for f, gb in zip(frames, gbs) for g in (gb, _row_major(gb))]
            x, y = imgs.values()
            assert all(torch.equal(p, q) for p, q in zip(x, y)), f"{name} {kind}"
    finally:
        torch.set_num_threads(n)


@pytest.mark.parametrize("name", ["chess", "creature", "sphere_plane"])
def test_native_sample_tiles_same_bits(precomputed, monkeypatch, name):
    """Bit 256 (the pixels in tiles: each shaded sample's (face, cell) resolved to an entry of its tile,
    the entries' X filled vertex by vertex, then the samples shaded from the entries; no memo) with and
    without bit 512 (a vertex's distinct nodes four at a time instead of its distinct cells) and bit 1024
    (a later vertex's c prefetched) and bit 2048 (a vertex's distinct nodes found without branches): the same image bits as the per-sample loop (`FAST` & 255: `cell_x`,
    the same X per (vertex, node) pair) over a V and an L sequence, with the G-buffer's layouts and
    row-major copies, at 1 and 2 threads, with tiles of 1 pixel (a tile inside a block), 100 (tiles
    ending inside a block, closed early: 400 samples leave 144 entries before the next block) and 4096
    pixels (the whole test image, closed early when its entries near half the hash's slots); and the
    reference to float32 round-off."""
    if not native_sample.cells_available():
        pytest.skip("no FMA build: bit 256 falls back to the per-sample loop")
    monkeypatch.setattr(native_sample, "MIN_PER_THREAD", 1)
    m = precomputed(name)
    n = torch.get_num_threads()
    try:
        for kind in ("V", "L"):
            frames = make_sequence(m.scene, kind, n_frames=2, seed=17)
            gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
            gbs = [g for gb in gbs for g in (gb, _row_major(gb))]
            frames = [f for f in frames for _ in (0, 1)]
            torch.set_num_threads(1)
            monkeypatch.setattr(native_sample, "FAST", native_sample.FAST & 255)
            want = [_copy(m).render(f, g) for f, g in zip(frames, gbs)]
            ref = _copy(m)
            exact = [ref._render_reference(f, g) for f, g in zip(frames, gbs)]
            fasts = (255 | 256, 255 | 256 | 512, 255 | 256 | 512 | 1024, 255 | 256 | 512 | 1024 | 2048)
            for what, i, got in _each_setting(m, monkeypatch, frames, gbs, fasts, (1, 100, 4096)):
                assert torch.equal(got, want[i]), f"{name} {kind} {what}"
                scale = float(exact[i].abs().max())
                assert float((got - exact[i]).abs().max()) <= RTOL * scale
    finally:
        torch.set_num_threads(n)


def _each_setting(m, monkeypatch, frames, gbs, fasts, tiles, chunks: bool = False):
    """Per `FAST` value, tile (with ``chunks``: also the chunk of the dynamic schedule) and 1 / 2 threads, a
    fresh copy of ``m`` renders the frames: yields (the setting as text, the frame's index, its image)."""
    for fast in fasts:
        for tile in tiles:
            for t in (1, 2):
                torch.set_num_threads(t)
                monkeypatch.setattr(native_sample, "FAST", fast)
                monkeypatch.setattr(native_sample, "TILE", tile)
                if chunks:
                    monkeypatch.setattr(native_sample, "CHUNK", tile)
                a = _copy(m)
                for i, (f, g) in enumerate(zip(frames, gbs)):
                    yield f"FAST {fast} tile {tile} threads {t} frame {i}", i, a.render(f, g)


def _row_major(gb):
    """A copy of the G-buffer with every (q, C) array row-major (the loop's other layout)."""
    g = copy.copy(gb)
    g.normal, g.wo, g.bary = g.normal.contiguous(), g.wo.contiguous(), g.bary.contiguous()
    return g


@pytest.mark.parametrize("tiles", [False, True])
def test_native_sample_bit_identical_at_one_and_two_threads(precomputed, monkeypatch, tiles):
    """The frame split over two threads (pixels per thread lowered to 1) gives the single thread's
    image and memo bit for bit: each memo row's value is its (vertex, node) pair's alone (the tiles,
    bit 256: the image; the memo is not used)."""
    monkeypatch.setattr(native_sample, "FAST", native_sample.FAST | 256 if tiles else native_sample.FAST & 255)
    monkeypatch.setattr(native_sample, "TILE", 128)
    monkeypatch.setattr(native_sample, "MIN_PER_THREAD", 1)
    monkeypatch.setattr(native_sample, "WINDOW", 4)
    m = precomputed("creature")
    frames = make_sequence(m.scene, "V", n_frames=3, seed=2) + make_sequence(m.scene, "L", n_frames=2, seed=2)
    gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
    n = torch.get_num_threads()
    runs = []
    try:
        for t in (1, 2):
            torch.set_num_threads(t)
            a = _copy(m)
            runs.append(([a.render(f, g) for f, g in zip(frames, gbs)], [x.clone() for x in a._xmemo]))
    finally:
        torch.set_num_threads(n)
    for x, y in zip(runs[0][0] + runs[0][1], runs[1][0] + runs[1][1]):
        assert torch.equal(x, y)


@pytest.mark.parametrize("tiles", [False, True])
@pytest.mark.parametrize("chunk", [1, 64, 100])
def test_native_sample_dynamic_chunks_bit_identical(precomputed, monkeypatch, chunk, tiles):
    """Two threads taking the pixels in many small chunks (the dynamic schedule; 100: chunks that end
    inside a block of 64 pixels) give the single thread's image and memo bit for bit, and report the
    same first sample of a face in another region (the tiles, bit 256: chunks of `TILE` pixels)."""
    monkeypatch.setattr(native_sample, "FAST", native_sample.FAST | 256 if tiles else native_sample.FAST & 255)
    monkeypatch.setattr(native_sample, "MIN_PER_THREAD", 1)
    monkeypatch.setattr(native_sample, "WINDOW", 4)
    monkeypatch.setattr(native_sample, "CHUNK", chunk)
    monkeypatch.setattr(native_sample, "TILE", chunk)
    m = precomputed("chess")
    frames = make_sequence(m.scene, "V", n_frames=2, seed=3) + make_sequence(m.scene, "L", n_frames=2, seed=3)
    gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
    assert gbs[0].num_samples // 4 > 4 * max(chunk, 64)      # several chunks per thread
    n = torch.get_num_threads()
    runs, bads = [], []
    try:
        for t in (1, 2):
            torch.set_num_threads(t)
            a = _copy(m)
            runs.append(([a.render(f, g) for f, g in zip(frames, gbs)], [x.clone() for x in a._xmemo]))
            # the first lighting: c of every vertex, no pass before the loop
            bad, ks = _first_foreign_sample(m, frames[0], gbs[0], monkeypatch, (3, 2, 1))
            bads.append(bad)
    finally:
        torch.set_num_threads(n)
    for x, y in zip(runs[0][0] + runs[0][1], runs[1][0] + runs[1][1]):
        assert torch.equal(x, y)
    assert bads[0] == bads[1] == int(ks.min())


def _first_foreign_sample(m, frame, gb, monkeypatch, at):
    """Render ``frame`` with ``gb``'s region changed at the hits numel // a for a in ``at`` (1: the last hit):
    the loop's reported first sample of a foreign face (the render raises) and those samples."""
    gb = copy.copy(gb)
    gb.region = gb.region.clone()
    hits = gb.hit.nonzero()[:, 0]
    ks = hits[torch.tensor([hits.numel() // a if a > 1 else hits.numel() - 1 for a in at])]
    gb.region[ks] = (gb.region[ks] + 1) % len(m.scene.regions)
    got = []
    shade = _spy(monkeypatch, got)
    with pytest.raises(ValueError, match="another region"):
        _copy(m).render(frame, gb)
    monkeypatch.setattr(native_sample.Bound, "frame", shade)
    return got[0][2], ks


def test_native_sample_rejects_faces_of_another_region(precomputed):
    """A hit sample whose face lies in another region than the sample's: the C loop reports it and
    `render` raises, as the compiled path's referenced-face pass does."""
    m = _copy(precomputed("bunny"))
    frame = make_sequence(m.scene, "V", n_frames=1, seed=0)[0]
    gb = make_gbuffer(m.scene, frame, 1)
    m.render(frame, gb)                                              # c of every vertex: no pass before the loop
    k = int(gb.hit.nonzero()[0])
    gb.region = gb.region.clone()
    gb.region[k] = (int(gb.region[k]) + 1) % len(m.scene.regions)
    with pytest.raises(ValueError, match="another region"):
        m.render(frame, gb)


def test_bound_call_follows_its_arrays(precomputed, monkeypatch):
    """The loop's static arguments are bound once (`native_sample.bind`, kept as ``InOut._xcall``) and bound
    again when what they point to changes: another c (new tensors of each region: the image follows them,
    as the compiled path's), a deep copy (none: its owner binds again); a frame's own arrays (row-major
    barycentrics, other strides) are read through their strides — each image the compiled path's to
    float32 round-off, and the same bits as a fresh method's on the same c."""
    m = precomputed("chess")
    new, old = _copy(m), _copy(m)
    old._render_native = lambda f, g: None
    frames = make_sequence(m.scene, "V", n_frames=3, seed=2)
    gbs = [make_gbuffer(m.scene, f, 2) for f in frames]

    def close(a, b):
        scale = float(b.abs().max())
        return scale > 0 and float((a - b).abs().max()) <= RTOL * scale

    assert close(new.render(frames[0], gbs[0]), old.render(frames[0], gbs[0]))
    bound = new._xcall
    assert bound is not None
    for r in m.regions:                                  # c replaced by other tensors (twice the values)
        for x in (new, old):
            c2 = x._cf[r.name] * 2
            x._cf[r.name], x._cf_valid[r.name] = c2, torch.ones(c2.shape[0], dtype=torch.bool)
            x._cf_full[r.name] = x._cf_valid[r.name]
    got = new.render(frames[1], gbs[1])
    assert new._xcall is not bound and close(got, old.render(frames[1], gbs[1]))
    twin = copy.copy(new)
    twin._xcall = copy.deepcopy(new._xcall)
    assert twin._xcall is None
    gb = copy.copy(gbs[2])
    gb.bary = gbs[2].bary.contiguous()                   # row-major (the G-buffer's is column-major)
    assert gb.bary.stride() != gbs[2].bary.stride()
    stamp = new._xstamp
    got = new.render(frames[2], gb)
    assert new._xstamp == stamp + 1
    assert torch.equal(got, twin.render(frames[2], gbs[2]))
    assert twin._xcall is not None and twin._xcall is not new._xcall


WIDE = 65536   # `native_sample.FAST`'s bit: the tile's shade pass a pixel's four samples per vector


@pytest.mark.parametrize("name", ["chess", "creature", "sphere_plane"])
def test_native_sample_wide_shade_same_bits(precomputed, monkeypatch, name):
    """Bit 65536 (the tile's shade pass a pixel's four samples per AVX-512 vector) gives the tiles' image bits
    (bit 256 without it: the tile loop, its oracle), over a V and an L sequence, at 2 x 2 samples (the vector
    shade) and 1 x 1 (its fallback), with the G-buffer's layouts and row-major copies, at 1 and 2 threads,
    with chunks of 100 pixels (ending inside a block) and 4096 (the whole test image). Planted errors it
    caught (session 44): a pixel's samples summed last first, beta_0 without - bv. (Swapping the first two
    samples' sum is not an error: IEEE addition commutes.)"""
    if not native_sample.cells_available():
        pytest.skip("no FMA build: bit 256 falls back to the per-sample loop")
    monkeypatch.setattr(native_sample, "MIN_PER_THREAD", 1)
    m = precomputed(name)
    n = torch.get_num_threads()
    base = (native_sample.FAST | 256) & ~WIDE
    try:
        for kind, spp in (("V", 2), ("L", 2), ("V", 1)):
            frames = make_sequence(m.scene, kind, n_frames=2, seed=23)
            gbs = [make_gbuffer(m.scene, f, spp) for f in frames]
            gbs = [g for gb in gbs for g in (gb, _row_major(gb))]
            frames = [f for f in frames for _ in (0, 1)]
            torch.set_num_threads(1)
            monkeypatch.setattr(native_sample, "FAST", base)
            want = [_copy(m).render(f, g) for f, g in zip(frames, gbs)]
            for what, i, got in _each_setting(m, monkeypatch, frames, gbs, (base | WIDE,), (100, 4096), chunks=True):
                assert torch.equal(got, want[i]), f"{name} {kind} spp {spp} {what}"
    finally:
        torch.set_num_threads(n)


def test_first_lighting_warm_up_compiles_the_later_lightings_pass(precomputed, monkeypatch):
    """Under the first lighting the loop runs no referenced-vertex pass (every vertex's c is computed), so
    the harness's untimed warm-up frame (``core.fused.warming``) compiles that pass's kernel
    (``fast.shaded_faces_cols``) for the frame's sample block: the next lighting's frame — the first timed
    frame of a lighting cell — runs the pass without compiling (it compiled there before: ~110 ms of a
    chess bench L frame, session 44). Dynamo's caches are reset first, so nothing compiled by an earlier
    test can stand in for the warm-up."""
    from torch._dynamo.utils import counters

    from methods.core import fused

    if not fused.compile_enabled():
        pytest.skip("PRTBENCH_COMPILE off: nothing is compiled")
    m = precomputed("creature")
    frames = make_sequence(m.scene, "L", n_frames=2, seed=5)
    gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
    torch._dynamo.reset()
    fused._warmed.clear()     # what was warmed was compiled code the reset dropped (later tests warm it again)
    refs = []
    view_refs = InOut._view_refs

    def spy(self, *a, **k):
        refs.append(1)
        return view_refs(self, *a, **k)

    monkeypatch.setattr(InOut, "_view_refs", spy)
    a = _copy(m)
    with fused.warming():
        a.render(frames[0], gbs[0])
    assert not refs                                  # the first lighting: no pass before the loop
    graphs = int(counters["stats"]["unique_graphs"])
    a.render(frames[1], gbs[1])
    assert refs                                      # the second lighting runs the pass ...
    assert int(counters["stats"]["unique_graphs"]) == graphs     # ... compiled in the warm-up frame
