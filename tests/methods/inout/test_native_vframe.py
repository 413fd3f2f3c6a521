"""Shading "vertex"'s view frame as one C loop (``methods.inout.native_vframe``, `InOut._render_vertex_native`)
against the split path it replaces in view frames (`InOut._render_vertex` with the loop off: the
referenced-face pass, ``native.vertex_cells``, ``native.vertex_radiance`` per region, ``core.gouraud``'s
resolve) — the same operations in the same order, so the same bits — and against the reference
(`_render_vertex_reference`, float32 round-off); at 1 and 2 threads; and its checks (a face outside
the mesh, a hit on another region's face) handing the frame to the split path, which raises."""
from __future__ import annotations

import copy

import pytest
import torch

from methods.inout import native_vframe
from methods.inout.method import InOut
from references.gbuffer import make_gbuffer
from scenes.library import SCENES, get_scene
from scenes.sequences import make_sequence

TINY = dict(brdf_res=8, cube_res=4, n_coeffs=16, lut_res=16, light_supersample=2, terms=6, shading="vertex")
# per scene what it exercises besides the default (as tests/methods/inout/test_fast.py): many terms (the
# K-sum's 8 lanes and its tail), three regions
VARIANTS = {"sphere_plane": dict(terms=None), "chess": dict(light_coeffs=24), "bunny": dict(terms=None)}
RTOL = 1e-5

pytestmark = pytest.mark.skipif(not native_vframe.available(), reason="no C compiler (PRTBENCH_COMPILE=0?)")


@pytest.fixture(scope="module")
def precomputed():
    built = {}

    def get(name: str) -> InOut:
        if name not in built:
            m = InOut(**{**TINY, **VARIANTS.get(name, {})})
            m.precompute(get_scene(name, "test"))
            built[name] = m
        return built[name]

    return get


def _copies(m: InOut) -> tuple[InOut, InOut]:
    """(the C loop's copy, the split path's copy) of one precomputation, caches of their own."""
    a, b = copy.copy(m), copy.copy(m)
    a._reset_cache()
    b._reset_cache()
    b._render_vertex_native = lambda frame, gbuffer: None
    return a, b


def _check_sequence(m: InOut, spp_side: int, n_frames: int = 4, seed: int = 3) -> None:
    new, old = _copies(m)
    for frame in make_sequence(m.scene, "V", n_frames=n_frames, seed=seed):
        gb = make_gbuffer(m.scene, frame, spp_side)
        stamp = new._vstamp
        got, split = new.render(frame, gb), old.render(frame, gb)
        assert new._vstamp == stamp + 1, "the C loop did not run"
        assert torch.equal(got, split), f"{m.scene.name} frame {frame.index}: {float((got - split).abs().max())}"
        want = old._render_reference(frame, gb)
        scale = float(want.abs().max())
        assert scale > 0 and float((got - want).abs().max()) <= RTOL * scale
        # what the frame counts: the view found after the frame equals the split path's
        P, px = gb.num_samples, gb.height * gb.width
        assert new.frame_cost("V", P, pixels=px) == old.frame_cost("V", P, pixels=px)


@pytest.mark.parametrize("name", SCENES)
def test_vertex_frame_equals_the_split_path(precomputed, name):
    """Every library scene, V frames at 1 and 2×2 samples per pixel: the C loop's image is the split
    path's bit for bit and the reference's to float32 round-off, and `frame_cost` counts the same."""
    scene = get_scene(name, "test")
    why = InOut.capabilities.why_not(scene, "V", 0)
    if why is not None:
        pytest.skip(why)
    m = precomputed(name)
    for spp in (1, 2):
        _check_sequence(m, spp)


def test_vertex_frame_threads_are_bit_identical(precomputed, monkeypatch):
    """2 threads (every image split over the team: the per-thread pixel floor lowered) give the bits of 1
    thread and of the split path, on the three-region chess scene."""
    monkeypatch.setattr(native_vframe, "MIN_PIXELS_PER_THREAD", 1)
    m = precomputed("chess")
    frames = make_sequence(m.scene, "V", n_frames=4, seed=5)
    gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
    imgs = {}
    old_threads = torch.get_num_threads()
    try:
        for t in (1, 2):
            torch.set_num_threads(t)
            new, old = _copies(m)
            imgs[t] = [new.render(f, g) for f, g in zip(frames, gbs)]
            for img, f, g in zip(imgs[t], frames, gbs):
                assert torch.equal(img, old.render(f, g))
    finally:
        torch.set_num_threads(old_threads)
    assert all(torch.equal(a, b) for a, b in zip(imgs[1], imgs[2]))


def test_vertex_frame_checks_hand_the_frame_to_the_split_path(precomputed):
    """A hit on a face of another region, or a face outside the mesh: the loop reports it, the split
    path runs and raises its error; a frame after it renders with the loop again."""
    m = precomputed("chess")
    new, _ = _copies(m)
    first, frame = make_sequence(m.scene, "V", n_frames=2, seed=0)     # frame 1 changes the view only
    new.render(first, make_gbuffer(m.scene, first, 1))
    gb = make_gbuffer(m.scene, frame, 1)
    bad = copy.copy(gb)
    bad.region = gb.region.clone()
    k = int(gb.hit.nonzero()[0, 0])
    bad.region[k] = (bad.region[k] + 1) % 3
    with pytest.raises(ValueError, match="another region"):
        new.render(frame, bad)
    bad = copy.copy(gb)
    bad.face = gb.face.clone()
    bad.face[k] = m.F.shape[0]
    with pytest.raises(ValueError):
        new.render(frame, bad)
    bad.face[k] = m.F.shape[0] + 10 ** 9      # far outside: the loop's last phase must not read past the faces
    with pytest.raises(ValueError):
        new.render(frame, bad)
    stamp = new._vstamp
    new.render(frame, gb)
    assert new._vstamp == stamp + 1


def test_vertex_frame_is_not_used_before_every_c_is_computed(precomputed):
    """Under a later lighting (c computed lazily for the view's vertices) the split path runs."""
    m = precomputed("sphere_plane")
    new, _ = _copies(m)
    frames = make_sequence(m.scene, "L", n_frames=3, seed=1)
    new.render(frames[0], make_gbuffer(m.scene, frames[0], 1))   # the first lighting: every c computed
    assert new._vstamp == 1
    for f in frames[1:]:
        new.render(f, make_gbuffer(m.scene, f, 1))
    assert new._lightings == 3 and new._vstamp == 1 and "vertex" in new._last_view[1]


def test_vertex_memo_is_reported():
    """`InOut.memory` counts the loop's memo (B_v, the stamps, the face table) once it exists."""
    scene = get_scene("sphere_plane", "test")
    m = InOut(**{**TINY, "terms": 4})
    m.precompute(scene)
    assert m.memory()["vertex_memo"] == 0
    f = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    m.render(f, make_gbuffer(scene, f, 1))
    nv, M = m._fast_static().voff[-1], int(m._fast_static().face_region.shape[0])
    assert m.memory()["vertex_memo"] == nv * 12 + M * 4 + nv * 4 + M * 48     # B, stamps, the face table


def test_bound_call_follows_its_arrays(precomputed):
    """The loop's static arguments are bound once (`native_vframe.bind`, kept as ``InOut._vcall``) and
    bound again when what they point to changes: another c (new tensors of a region: the image follows
    them, as the split path's), a deep copy (none: its owner binds again), a G-buffer whose barycentrics
    are row-major (read through copies of their columns) — each image the split path's bits."""
    m = precomputed("chess")
    new, old = _copies(m)
    frames = make_sequence(m.scene, "V", n_frames=3, seed=2)
    gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
    assert torch.equal(new.render(frames[0], gbs[0]), old.render(frames[0], gbs[0]))
    bound = new._vcall
    assert bound is not None
    # c replaced by other tensors (twice the values) in both copies: the next frame reads the new ones
    for r in m.regions:
        for x in (new, old):
            c2 = x._cf[r.name] * 2
            x._cf[r.name], x._cf_valid[r.name] = c2, torch.ones(c2.shape[0], dtype=torch.bool)
            x._cf_full[r.name] = x._cf_valid[r.name]
    got, want = new.render(frames[1], gbs[1]), old.render(frames[1], gbs[1])
    assert new._vcall is not bound and torch.equal(got, want)
    # a deep copy of the bound call is none (the library's functions do not copy): its owner binds again
    twin = copy.copy(new)
    twin._vcall = copy.deepcopy(new._vcall)
    assert twin._vcall is None
    assert torch.equal(twin.render(frames[2], gbs[2]), old.render(frames[2], gbs[2]))
    assert twin._vcall is not None and twin._vcall is not new._vcall
    # row-major barycentrics (not the G-buffer's column-major layout): the same image
    gb = copy.copy(gbs[2])
    gb.bary = gbs[2].bary.contiguous()
    assert gb.bary.stride() == (2, 1)
    stamp = new._vstamp
    assert torch.equal(new.render(frames[2], gb), old.render(frames[2], gbs[2]))
    assert new._vstamp == stamp + 1


def test_bound_frame_checks_each_argument(precomputed):
    """`native_vframe.Bound.frame` (session 41: dtypes compared by identity, devices by ``is_cpu``, the camera
    written into a kept ctypes array) hands back None for each G-buffer array of another dtype, shape or
    device and for non-contiguous ones; and the kept camera array takes each frame's position: two frames
    of one bound call with different cameras are each the split path's bits."""
    m = precomputed("chess")
    new, old = _copies(m)
    frames = make_sequence(m.scene, "V", n_frames=2, seed=4)
    gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
    assert torch.equal(new.render(frames[0], gbs[0]), old.render(frames[0], gbs[0]))
    b, g = new._vcall, gbs[1]
    n, S2 = g.height * g.width, g.spp_side ** 2
    args = dict(face=g.face, bary=g.bary, region=g.region, hit=g.hit)

    def call(**kw):
        a = {**args, **kw}
        new._vstamp += 1
        return b.frame(a["face"], a["bary"], a["region"], a["hit"], n, S2, frames[1].camera.origin, new._vstamp)

    assert call() is not None
    bad = {"face": [g.face.int(), g.face[:-1], g.face.to("meta"), torch.stack([g.face, g.face], 1)[:, 0]],
           "region": [g.region.int(), g.region[:-1], g.region.to("meta"), torch.stack([g.region, g.region], 1)[:, 0]],
           "hit": [g.hit.to(torch.uint8), g.hit[:-1], g.hit.to("meta"), torch.stack([g.hit, g.hit], 1)[:, 0]],
           "bary": [g.bary.double(), g.bary[:-1], g.bary.to("meta")]}
    for name, values in bad.items():
        for v in values:
            assert call(**{name: v}) is None, (name, v.dtype, tuple(v.shape), v.device)
    # the kept camera array: each frame's own position (the previous frame's would give other pixels)
    for f, gb in zip(frames[::-1], gbs[::-1]):
        assert torch.equal(new.render(f, gb), old.render(f, gb))
    assert new._vcall is b


@pytest.mark.parametrize("threads", [1, 2])
def test_face_table_variant_same_bits(precomputed, monkeypatch, threads):
    """``FAST`` bit 2 (the face table and phase (4) from its rows, channels as lanes), bit 4 (phase (1)
    in dynamic chunks), bit 8 (phase (3)'s rows prefetched further ahead) and bit 32 (with 2: phase (4) a
    pixel's 4 samples in one AVX-512 vector; 2×2 samples, pixels with misses the per-sample loop), alone and together, against
    the plain loop: the same bits on the three-region chess scene and on the creature-like sphere_plane, 1 and
    2×2 samples, at 1 and 2 threads (every image split over the team)."""
    _variants_same_bits(precomputed, monkeypatch, threads, "FAST", (0, 2, 4, 6, 8, 14, 34, 46))


@pytest.mark.parametrize("threads", [1, 2])
def test_face_table_rows_are_written_each_frame(precomputed, monkeypatch, threads):
    """Every B row and face table row phase (4) reads was written in this frame's (3) and (3b): both poisoned
    (NaN) before each frame, and the samples at the ends of phase (1)'s chunks and ranges moved onto the
    first and last faces of the mesh and of each thread's range of faces (the ends of (2)'s and (3b)'s
    ranges); the image is the split path's bits."""
    monkeypatch.setattr(native_vframe, "MIN_PIXELS_PER_THREAD", 1)
    m = precomputed("chess")
    M = int(m.F.shape[0])
    st_region = None
    old_threads = torch.get_num_threads()
    try:
        torch.set_num_threads(threads)
        new, old = _copies(m)
        for f in make_sequence(m.scene, "V", n_frames=3, seed=6):
            gb = copy.copy(make_gbuffer(m.scene, f, 2))
            if st_region is None:
                new.render(f, gb)                                  # the first frame: the memo exists after it
                old.render(f, gb)
                st_region = new._fast_static().face_region
                continue
            gb.face, gb.region, gb.hit = gb.face.clone(), gb.region.clone(), gb.hit.clone()
            gb.bary = gb.bary.clone()
            q, C = gb.face.shape[0], native_vframe.PCHUNK
            ends = sorted({0, M - 1, *(M * t // threads for t in range(1, threads)),
                           *(M * t // threads - 1 for t in range(1, threads))})
            # the samples at the ends of (1)'s ranges (its chunks, its threads' halves), each on one of them
            at = sorted({k for k in (0, C - 1, C, 2 * C - 1, q // 2 - 1, q // 2, q - 1) if 0 <= k < q})
            for j, k in enumerate(at):
                fe = ends[j % len(ends)]
                gb.hit[k] = True
                gb.bary[k] = torch.tensor([0.25, 0.5])
                gb.face[k] = fe
                gb.region[k] = st_region[fe]
            new._vmemo[0].fill_(float("nan"))                     # B
            new._vmemo[3].fill_(float("nan"))                     # the face table
            stamp = new._vstamp
            got = new.render(f, gb)
            assert new._vstamp == stamp + 1, "the C loop did not run"
            assert torch.equal(got, old.render(f, gb))
    finally:
        torch.set_num_threads(old_threads)


@pytest.mark.parametrize("off", ["0", "off", " no "])
def test_loaded_libraries_follow_the_off_switch(monkeypatch, off):
    """`native_sample.load_remembered` reads PRTBENCH_COMPILE at each call (`methods.core.switches`): set to
    an off value after both loops' libraries loaded, both are None; set to 1 or unset again, both load."""
    from methods.inout import native_sample

    monkeypatch.delenv("PRTBENCH_COMPILE", raising=False)
    assert native_vframe._lib() is not None and native_sample._lib() is not None
    monkeypatch.setenv("PRTBENCH_COMPILE", off)
    assert native_vframe._lib() is None and native_sample._lib() is None
    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    assert native_vframe._lib() is not None and native_sample._lib() is not None
    monkeypatch.delenv("PRTBENCH_COMPILE")
    assert native_vframe._lib() is not None


def test_bound_call_runs_first_while_current(precomputed, monkeypatch):
    """Session 43: a view frame whose bound call is current (`InOut._vcall_current`) runs it without
    `_render_vertex_native` (made to raise here): the split path's bits, a new contiguous image each frame
    (not the previous one's storage); with another memo, a region's c or its validity flags replaced it is
    not current (the checks `_render_vertex_native` makes; a light change:
    `test_vertex_frame_is_not_used_before_every_c_is_computed`)."""
    m = precomputed("chess")
    new, old = _copies(m)
    frames = make_sequence(m.scene, "V", n_frames=4, seed=7)
    gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
    prev = new.render(frames[0], gbs[0])
    assert torch.equal(prev, old.render(frames[0], gbs[0]))
    b = new._vcall

    def boom(frame, gbuffer):
        raise AssertionError("the bound call was not taken first")

    monkeypatch.setattr(new, "_render_vertex_native", boom)
    for f, g in zip(frames[1:], gbs[1:]):
        stamp = new._vstamp
        img = new.render(f, g)
        assert new._vstamp == stamp + 1 and new._vcall is b
        assert img.is_contiguous() and img.shape == (g.height, g.width, 3)
        assert img.data_ptr() != prev.data_ptr() and torch.equal(img, old.render(f, g))
        prev = img
    assert new._vcall_current(b)
    saved = new._vmemo
    new._vmemo = tuple(x.clone() for x in saved)
    assert not new._vcall_current(b)
    new._vmemo = saved
    name = m.regions[0].name
    c = new._cf[name]
    new._cf[name] = c.clone()
    assert not new._vcall_current(b)
    new._cf[name] = c
    v = new._cf_valid[name]
    new._cf_valid[name] = v.clone()
    assert not new._vcall_current(b)
    new._cf_valid[name] = v
    assert new._vcall_current(b)


@pytest.mark.parametrize("threads", [1, 2])
def test_packed_call_same_bits(precomputed, monkeypatch, threads):
    """``PACKED`` (``vertex_frame_packed``: the frame-independent arguments from `bind`'s packed array) against
    the 28-argument ``vertex_frame``: the same bits, chess and sphere_plane, 1 and 2×2 samples, 1 and 2 threads."""
    _variants_same_bits(precomputed, monkeypatch, threads, "PACKED", (False, True))


def _variants_same_bits(precomputed, monkeypatch, threads, attr, values):
    """`native_vframe`.``attr`` set to each of ``values`` in turn: a 3-frame V sequence on chess and sphere_plane at
    1 and 2×2 samples, ``threads`` threads, through the C loop every frame; every value's images the same bits
    as the first value's."""
    monkeypatch.setattr(native_vframe, "MIN_PIXELS_PER_THREAD", 1)
    old_threads = torch.get_num_threads()
    try:
        torch.set_num_threads(threads)
        for name in ("chess", "sphere_plane"):
            m = precomputed(name)
            for spp in (1, 2):
                imgs = {}
                for v in values:
                    monkeypatch.setattr(native_vframe, attr, v)
                    new, _ = _copies(m)
                    imgs[v] = []
                    for f in make_sequence(m.scene, "V", n_frames=3, seed=4):
                        stamp = new._vstamp
                        imgs[v].append(new.render(f, make_gbuffer(m.scene, f, spp)))
                        assert new._vstamp == stamp + 1, "the C loop did not run"
                for v in values[1:]:
                    assert all(torch.equal(a, b) for a, b in zip(imgs[values[0]], imgs[v])), f"{name} spp {spp} {attr}={v}"
    finally:
        torch.set_num_threads(old_threads)
