"""The native zero-skipping loops (`methods.triple_product.native`) against the compiled torch
kernels they stand in for (`fast_eval.fine_block`, `fast_eval.group_block`, eager here: the oracle).

Visibility rows with every zero pattern the chunk lists handle: a row all zero, a row with no zero,
non-zeros only in the last (< 8) columns (the scalar tail), a single non-zero at column 0, runs of
zeros shorter and longer than a chunk, random rows; a row length that is not a multiple of 8."""
from __future__ import annotations

import pytest
import torch

from methods.triple_product import fast_eval, native

pytestmark = pytest.mark.skipif(not native.available(), reason="no C compiler (the torch kernels run)")

# float32: the same products without the exact zeros, summed in another order; relative to the
# largest |value| of the batch (as test_tp_fast_eval.F32)
F32 = 2e-6


def _vis(n: int, gen: torch.Generator) -> torch.Tensor:
    """(12, n) visibility fine values with the zero patterns of the module docstring."""
    V = torch.rand(12, n, generator=gen) + 0.1
    V[0] = 0                                             # all zero
    # V[1]: no zero
    V[2, : n - 3] = 0                                    # non-zeros in the tail only
    V[3, 1:] = 0                                         # one non-zero, at column 0
    V[4, 3:6] = 0                                        # a zero run shorter than a chunk
    V[4, 20:37] = 0                                      # and longer than two
    V[5, ::2] = 0                                        # alternating
    V[6, : n // 2] = 0                                   # a half
    V[7, n // 2:] = 0
    V[8, -1] = 0                                         # the last column only
    V[9:] *= torch.rand(3, n, generator=gen) < 0.5       # random
    V[11, n - 9: n - 1] = 0                              # a chunk's width of zeros before the last column
    return V


def _tables(n: int, gen: torch.Generator):
    return _vis(n, gen), torch.randn(7, 3 * n, generator=gen), torch.randn(9, 3 * n, generator=gen)


@pytest.mark.parametrize("n", [45, 64, 7])
def test_chunks_cover_every_non_zero_once(n):
    """Every non-zero column of a row lies in exactly one of its chunks or at/after its tail; chunks
    are whole (inside the row), 8-aligned and hold a non-zero column; the tail starts on a non-zero
    column after the last whole aligned block (or is n)."""
    gen = torch.Generator().manual_seed(1)
    V = _vis(n, gen)
    ptr, starts, tail = native.chunks(V)
    assert ptr.shape == (V.shape[0] + 1,) and int(ptr[-1]) == starts.numel()
    for r in range(V.shape[0]):
        cover = torch.zeros(n, dtype=torch.int64)
        for s in starts[ptr[r]:ptr[r + 1]].tolist():
            assert 0 <= s <= n - native.W and s % native.W == 0 and bool((V[r, s:s + native.W] != 0).any())
            cover[s:s + native.W] += 1
        t = int(tail[r])
        assert t == n or (V[r, t] != 0 and t >= n // native.W * native.W and cover[t] == 0)
        cover[t:] += 1
        nz = V[r] != 0
        assert bool((cover[nz] == 1).all()) and bool((cover <= 1).all()), r
    assert int(ptr[1] - ptr[0]) == 0 and int(tail[0]) == n                 # the all-zero row: nothing
    assert int(ptr[2] - ptr[1]) == n // native.W                             # the full row: whole chunks


@pytest.mark.parametrize("n", [45, 64])
def test_points_equal_fine_block(n):
    """`native.points` = `fast_eval.fine_block` (one visibility row per point, 4 ρ̃ and 4 grid rows)
    to float32 round-off; the all-zero row gives exactly 0."""
    gen = torch.Generator().manual_seed(2)
    Vt, Rt, Lt = _tables(n, gen)
    B = 60
    vrows = torch.arange(B) % Vt.shape[0]
    vw = torch.rand(B, generator=gen) + 0.5
    brows, lrows = torch.randint(0, 7, (B, 4), generator=gen), torch.randint(0, 9, (B, 4), generator=gen)
    bw, lw = torch.rand(B, 4, generator=gen), torch.rand(B, 4, generator=gen)
    want = fast_eval.fine_block(vrows[:, None], vw[:, None], brows, bw, lrows, lw, Vt, Rt.view(-1, 3, n), Lt.view(-1, 3, n))
    ch = native.chunks(Vt)
    got = native.points(Vt, Rt, Lt, vrows, vw, brows, bw, lrows, lw, ch)
    assert got.shape == (B, 3)
    assert (got - want).abs().max() <= F32 * want.abs().max()
    assert bool((got[vrows == 0] == 0).all())
    # per row: no row's sum is lost in the batch's largest value
    for r in range(Vt.shape[0]):
        sel = vrows == r
        assert (got[sel] - want[sel]).abs().max() <= F32 * max(float(want[sel].abs().max()), 1e-30) + 1e-30, r
    # the frames' entry point: `fast_eval.fine_kernel` with the chunk lists (several threads too)
    args = (Vt, Rt, Lt, vrows[:, None], vw[:, None], brows, bw, lrows, lw)
    assert torch.equal(fast_eval.fine_kernel(*args, chunks=ch), got)
    old, t = native.MIN_ITEMS_PER_THREAD, torch.get_num_threads()
    native.MIN_ITEMS_PER_THREAD = 8
    torch.set_num_threads(2)
    try:
        assert torch.equal(native.points(Vt, Rt, Lt, vrows, vw, brows, bw, lrows, lw, ch), got)  # same order per point
    finally:
        native.MIN_ITEMS_PER_THREAD = old
        torch.set_num_threads(t)
    # weights 0 (a third of a frame's grid weights; some points all 0): the loop reads the point's
    # first weighted row in place of such a row, the same sums
    bz = bw * (torch.rand(B, 4, generator=gen) < 0.6)
    lz = lw * (torch.rand(B, 4, generator=gen) < 0.6)
    bz[:3], lz[3:6] = 0, 0
    lz[6:9, 0] = 0
    want = fast_eval.fine_block(vrows[:, None], vw[:, None], brows, bz, lrows, lz, Vt, Rt.view(-1, 3, n), Lt.view(-1, 3, n))
    got = native.points(Vt, Rt, Lt, vrows, vw, brows, bz, lrows, lz, ch)
    for r in range(B):
        assert (got[r] - want[r]).abs().max() <= F32 * max(float(want[r].abs().max()), 1e-30) + 1e-30, r
    assert bool((got[:6] == 0).all())
    with pytest.raises(IndexError):
        native.points(Vt, Rt, Lt, vrows + Vt.shape[0], vw, brows, bw, lrows, lw, ch)


@pytest.mark.parametrize("n", [64, 48])
def test_points_chunk_major_same_bits(n):
    """`native.points` reading the ρ̃ table (and the L table) chunk-major (`native.chunk_major`:
    ``tp_points_cm``, one pass over a point's chunks for the three channels) and the visibility chunks
    packed (`native.packed_chunks`) = the row-major loop bit for bit — with weights 0 (the first weighted row read in their place), all-zero points, zero rows
    and on two threads; a row length not a multiple of 8 gets no copy and raises."""
    gen = torch.Generator().manual_seed(5)
    Vt, Rt, Lt = _tables(n, gen)
    B = 70
    vrows = torch.arange(B) % Vt.shape[0]
    vw = torch.rand(B, generator=gen) + 0.5
    vw[::3] = 1.0
    brows, lrows = torch.randint(0, 7, (B, 4), generator=gen), torch.randint(0, 9, (B, 4), generator=gen)
    bw = torch.rand(B, 4, generator=gen) * (torch.rand(B, 4, generator=gen) < 0.7)
    lw = torch.rand(B, 4, generator=gen) * (torch.rand(B, 4, generator=gen) < 0.6)
    bw[:3], lw[3:6], lw[6:9, 0] = 0, 0, 0
    ch = native.chunks(Vt)
    Rm, Lm = native.chunk_major(Rt), native.chunk_major(Lt)
    assert torch.equal(Rm.view(-1, n // 8, 3, 8), Rt.view(-1, 3, n // 8, 8).transpose(1, 2))
    args = (vrows, vw, brows, bw, lrows, lw, ch)
    want = native.points(Vt, Rt, Lt, *args)
    Vp = native.packed_chunks(Vt, ch)
    assert Vp.shape == (ch[1].numel(), 8)
    for r in range(Vt.shape[0]):                                        # row r's chunks, in order
        for e in range(int(ch[0][r]), int(ch[0][r + 1])):
            assert torch.equal(Vp[e], Vt[r, int(ch[1][e]):int(ch[1][e]) + 8])
    for R, L, rm, lm in ((Rm, Lt, True, False), (Rt, Lm, False, True), (Rm, Lm, True, True)):
        for vp in (None, Vp):
            got = native.points(Vt, R, L, *args, r_major=rm, l_major=lm, v_packed=vp)
            assert torch.equal(got, want), (rm, lm, vp is None)
    assert torch.equal(native.points(Vt, Rt, Lt, *args, v_packed=Vp), want)
    old, t = native.MIN_ITEMS_PER_THREAD, torch.get_num_threads()
    native.MIN_ITEMS_PER_THREAD = 8
    torch.set_num_threads(2)
    try:
        assert torch.equal(native.points(Vt, Rm, Lt, *args, r_major=True), want)
        assert torch.equal(native.points(Vt, Rm, Lm, *args, r_major=True, l_major=True, v_packed=Vp), want)
    finally:
        native.MIN_ITEMS_PER_THREAD = old
        torch.set_num_threads(t)
    ref = fast_eval.fine_block(vrows[:, None], vw[:, None], brows, bw, lrows, lw, Vt, Rt.view(-1, 3, n), Lt.view(-1, 3, n))
    assert (want - ref).abs().max() <= F32 * ref.abs().max()
    Vo, Ro, Lo = _tables(45, gen)
    assert native.chunk_major(Ro) is None
    with pytest.raises(ValueError):
        native.points(Vo, Ro, Lo, vrows, vw, brows, bw, lrows, lw, native.chunks(Vo), r_major=True)


def test_vis_packed_follows_its_table():
    """`fast_eval.vis_packed` is cached per visibility table and chunk lists: another table (or its own
    table with other lists) gets its own packed chunks, not the cached ones."""
    from types import SimpleNamespace

    gen = torch.Generator().manual_seed(6)
    m = SimpleNamespace()
    V1, V2 = _vis(64, gen), _vis(64, gen)
    c1, c2 = native.chunks(V1), native.chunks(V2)
    p1 = fast_eval.vis_packed(m, V1, c1)
    assert fast_eval.vis_packed(m, V1, c1) is p1                             # cached
    assert torch.equal(fast_eval.vis_packed(m, V2, c2), native.packed_chunks(V2, c2))
    assert torch.equal(fast_eval.vis_packed(m, V1, c1), p1)


def _chess_vertex(seed: int):
    """A per-vertex triple product on the chess test scene (its auto-evaluator twin without the perf cache),
    its V, L, V frames of ``seed`` and its first region (the renders below edit that region's material)."""
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    from methods.triple_product import TripleProduct

    scene = get_scene("chess", "test")
    m = TripleProduct(level=2, n_coeffs=None, shading="vertex", frame_grid=(5, 8, 1), brdf_dirs=(4, 4),
                      brdf_supersample=1, progress=False)
    m.precompute(scene)
    off = m.with_evaluator("auto")
    off.__dict__.pop("_perf_cache", None)
    views, lights = make_sequence(scene, "V", n_frames=2, seed=seed), make_sequence(scene, "L", n_frames=2, seed=seed)
    return scene, m, off, views, views + lights + views, next(iter(scene.regions))


def test_render_chunk_major_same_bits(monkeypatch):
    """Per-vertex renders reading the ρ̃ table chunk-major (`fast_eval.rho_major`, chess test scene: 160
    live triangles), the lighting table once its lighting is complete (`fast_eval.light_major`) and the
    packed visibility chunks (`fast_eval.vis_packed`) = with ``RHO_CHUNK_MAJOR`` / ``LIGHT_CHUNK_MAJOR`` /
    ``VIS_PACKED`` off, bit for bit, over view changes, lighting changes
    (pending: no lighting copy; completed by the next frame of the same lighting: a copy of that
    lighting's table) and a material edit (new ρ̃ and live tables get new copies); the copies count in
    ``memory()``."""
    import dataclasses

    from references.gbuffer import make_gbuffer
    from scenes.materials import Phong

    scene, m, off, views, frames, region = _chess_vertex(1)
    frames.append(dataclasses.replace(frames[-1], materials={**frames[-1].materials, region: Phong(kd=0.3, ks=0.4, s=20.0)}))
    rho, light, complete = [], [], []
    for f in frames:
        gb = make_gbuffer(scene, f, 1)
        for k in ("RHO_CHUNK_MAJOR", "LIGHT_CHUNK_MAJOR", "VIS_PACKED"):
            monkeypatch.setattr(fast_eval, k, True)
        monkeypatch.setattr(fast_eval, "VIS_PACKED_ONLY", False)          # the rows kept beside (tested below)
        img = m.render(f, gb)
        hit = m._perf_cache.get(("major", "rho"))
        assert hit is not None and hit[2] is not None                     # the chunk-major loop ran
        rho.append(hit[2])
        vp = m._perf_cache.get(("major", "V"))
        assert vp is not None and vp[2] is not None                       # the packed visibility chunks
        hl = m._perf_cache.get(("major", "L"))
        complete.append(m._lazy_light is None)
        assert (hl is not None and hl[2] is not None) == complete[-1]     # a copy only of a complete lighting
        light.append(hl[2] if hl is not None else None)
        mem = m.memory()["fine_values"]
        for k in ("RHO_CHUNK_MAJOR", "LIGHT_CHUNK_MAJOR", "VIS_PACKED"):
            monkeypatch.setattr(fast_eval, k, False)
        ref = off.render(f, gb)
        assert all(off._perf_cache.get(("major", k)) is None for k in ("rho", "L", "V"))
        assert off._perf_cache.get(("packed", "V")) is None
        assert torch.equal(img, ref)
        extra = rho[-1].numel() * 4 + vp[2].numel() * 4 + (light[-1].numel() * 4 if light[-1] is not None else 0)
        assert mem == off.memory()["fine_values"] + extra
    assert rho[0] is rho[5] and rho[6] is not rho[5]                      # one copy per ρ̃ table
    assert light[0] is light[1] is light[2] and light[5] is not light[0]  # one per lighting table
    assert complete == [True, True, True, False, False, True, True]      # pending and complete lightings


@pytest.mark.parametrize("n", [45, 64])
def test_groups_four_rows_agree(n):
    """`tp_groups` (on a CPU with AVX-512: all four L rows per pass over the chunks, `chunk_sums4`)
    writes the bits of `tp_groups2` (two L rows per pass, the loop it replaces): the same products
    in the same order per sum; with tails (n not a multiple of 8) and groups repeating a row."""
    lib = native._lib()
    gen = torch.Generator().manual_seed(4)
    Vt, Rt, Lt = _tables(n, gen)
    ptr, starts, tail = native.chunks(Vt)
    G = 48
    gv = torch.arange(G) % Vt.shape[0]
    gb, gl = torch.randint(0, 7, (G, 4), generator=gen), torch.randint(0, 9, (G, 4), generator=gen)
    gl[:5, 1] = gl[:5, 0]
    out = {}
    for name in ("tp_groups", "tp_groups2"):
        o = torch.full((G, 48), float("nan"))
        getattr(lib, name)(G, n, Vt.data_ptr(), gv.data_ptr(), Rt.data_ptr(), gb.data_ptr(), Lt.data_ptr(),
                           gl.data_ptr(), ptr.data_ptr(), starts.data_ptr(), tail.data_ptr(), o.data_ptr())
        out[name] = o
    assert torch.equal(out["tp_groups"], out["tp_groups2"])
    assert torch.equal(native.groups(Vt, Rt, Lt, gv, gl, gb, (ptr, starts, tail)), out["tp_groups2"])


@pytest.mark.parametrize("n", [45, 64])
def test_groups_equal_group_block(n):
    """`native.groups` = `fast_eval.group_block` (one visibility row per group) to float32 round-off,
    and `fast_eval.fine_grouped` with the chunk lists = `fast_eval.fine_kernel`."""
    gen = torch.Generator().manual_seed(3)
    Vt, Rt, Lt = _tables(n, gen)
    G = 36
    gv = torch.arange(G) % Vt.shape[0]
    gb, gl = torch.randint(0, 7, (G, 4), generator=gen), torch.randint(0, 9, (G, 4), generator=gen)
    want = fast_eval.group_block(gv, gl, gb, Vt, Rt.view(-1, 3, n), Lt.view(-1, 3, n))
    ch = native.chunks(Vt)
    got = native.groups(Vt, Rt, Lt, gv, gl, gb, ch)
    assert got.shape == want.shape == (G, 48)
    assert (got - want).abs().max() <= F32 * want.abs().max()
    assert bool((got[gv == 0] == 0).all())
    for r in range(Vt.shape[0]):
        sel = gv == r
        assert (got[sel] - want[sel]).abs().max() <= F32 * max(float(want[sel].abs().max()), 1e-30) + 1e-30, r
    # split over 2 and 3 threads of OpenMP's team (`tp_groups_par`): each group one thread's, the same bits
    old, t = native.MIN_ITEMS_PER_THREAD, torch.get_num_threads()
    native.MIN_ITEMS_PER_THREAD = 4
    try:
        for nt in (2, 3):
            torch.set_num_threads(nt)
            assert torch.equal(native.groups(Vt, Rt, Lt, gv, gl, gb, ch), got), nt
    finally:
        native.MIN_ITEMS_PER_THREAD = old
        torch.set_num_threads(t)
    # pixel-frame form: points with 3 visibility rows each, summed by groups
    B = 400
    vrows = torch.randint(0, Vt.shape[0], (B // 8 + 1, 3), generator=gen).repeat_interleave(8, 0)[:B]
    l0 = torch.randint(0, 5, (B // 8 + 1,), generator=gen).repeat_interleave(8)[:B]
    b0 = torch.randint(0, 3, (B // 8 + 1,), generator=gen).repeat_interleave(8)[:B]
    lrows, brows = torch.stack([l0, l0 + 1, l0 + 3, l0 + 4], 1), torch.stack([b0, b0 + 1, b0 + 2, b0 + 3], 1)
    vw, lw, bw = (torch.rand(B, k, generator=gen) for k in (3, 4, 4))
    ref = fast_eval.fine_kernel(Vt, Rt, Lt, vrows, vw, brows, bw, lrows, lw)
    out = fast_eval.fine_grouped(Vt, Rt, Lt, vrows, vw, brows, bw, lrows, lw, chunks=ch)
    assert (out - ref).abs().max() <= F32 * ref.abs().max()


@pytest.mark.parametrize("shading", ["vertex", "pixel"])
def test_render_with_native_equals_the_compiled_kernels(shading, monkeypatch):
    """A render whose eq. 7 sums run the native loop (full tables: the live-triangle path) = the same
    render with it off (``PRTBENCH_TP_NATIVE=0``: `fast_eval.fine_block` / `group_block`) to float32
    round-off; a material edit that leaves the live triangles as they were keeps the chunk lists (a
    rebuilt visibility table of the same columns), and the edited frame matches too."""
    import dataclasses

    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene
    from scenes.materials import Phong
    from scenes.sequences import make_sequence

    from methods.triple_product import TripleProduct

    scene = get_scene("sphere_plane", "test")
    frame = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    gb = make_gbuffer(scene, frame, 1)
    m = TripleProduct(level=2, n_coeffs=None, shading=shading, frame_grid=(5, 8, 1), brdf_dirs=(4, 4),
                      brdf_supersample=1, progress=False)
    m.precompute(scene)
    img = m.render(frame, gb)
    ch = m._perf_cache.get(("chunks",))
    assert ch is not None and fast_eval.live_triangles(m) is not None    # the native loop ran
    monkeypatch.setenv("PRTBENCH_TP_NATIVE", "0")
    off = m.with_evaluator("auto")
    off.__dict__.pop("_perf_cache", None)
    ref = off.render(frame, gb)
    assert off.__dict__.get("_perf_cache", {}).get(("chunks",)) is None
    assert (img - ref).abs().max() <= F32 * ref.abs().max()
    monkeypatch.setenv("PRTBENCH_TP_NATIVE", "1")
    edited = dataclasses.replace(frame, materials={**frame.materials, "sphere": Phong(kd=0.3, ks=0.4, s=20.0)})
    live = fast_eval.live_triangles(m)
    img2 = m.render(edited, gb)
    ch2 = m._perf_cache[("chunks",)]
    assert torch.equal(fast_eval.live_triangles(m), live)                   # the same live columns
    assert ch2[1] is ch[1] and ch2[0] is not ch[0]
    monkeypatch.setenv("PRTBENCH_TP_NATIVE", "0")
    ref2 = off.render(edited, gb)
    assert (img2 - ref2).abs().max() <= F32 * ref2.abs().max() and (img2 - img).abs().max() > 0


def test_hit_faces_equal_the_torch_bookkeeping():
    """`native.hit_faces` = the per-vertex frame's torch bookkeeping it replaces (`method._hit_faces`,
    `method._distinct` of those faces' vertices, ``hit.sum()``): misses (face −1) skipped, faces seen
    many times once; an index outside its table raises."""
    from methods.triple_product.method import _distinct, _hit_faces
    from types import SimpleNamespace

    gen = torch.Generator().manual_seed(4)
    nv, nf, P = 300, 500, 20000
    F = torch.randint(0, nv, (nf, 3), generator=gen)
    hit = torch.rand(P, generator=gen) < 0.7
    face = torch.where(hit, torch.randint(0, nf // 3, (P,), generator=gen) * 2, torch.full((P,), -1))
    got = native.hit_faces(hit, face, F, nv)
    if got is None:
        pytest.skip("no native loops")
    faces = _hit_faces(SimpleNamespace(hit=hit, face=face), nf)
    assert torch.equal(got[0], faces) and torch.equal(got[1], _distinct(F[faces].reshape(-1), nv))
    assert got[2] == int(hit.sum())
    old = native.HIT_LISTS
    native.HIT_LISTS = not old                                               # the lists by torch.nonzero (or by C)
    try:
        other = native.hit_faces(hit, face, F, nv)
    finally:
        native.HIT_LISTS = old
    assert torch.equal(other[0], got[0]) and torch.equal(other[1], got[1]) and other[2] == got[2]
    none = native.hit_faces(torch.zeros(P, dtype=torch.bool), face, F, nv)
    assert none[0].numel() == 0 and none[1].numel() == 0 and none[2] == 0
    bad = face.clone()
    bad[torch.nonzero(hit)[0]] = nf
    with pytest.raises(IndexError):
        native.hit_faces(hit, bad, F, nv)
    F2 = F.clone()
    F2[faces[0], 2] = nv                                                    # a seen face's vertex
    with pytest.raises(IndexError):
        native.hit_faces(hit, face, F2, nv)


@pytest.mark.parametrize("ogrid, fgrid", [((8, 16), (17, 32, 1)), ((1, 3), (2, 5, 1)), ((4, 4), (5, 8, 1))])
def test_vertex_lookups_equal_grid_lookups(ogrid, fgrid):
    """`native.vertex_lookups` = `fast_eval.grid_lookups` of R[used] and normalize(cam − P[used]) with the
    ωo rows offset by region · outgoing.size (as `fast_eval.shading_rows` makes them), bit for bit:
    random normals and points, normals at the poles (±Y) and on the φ seam (+X), ωo along the normal
    (θ = 0) and below the horizon (clamped), vertices in any order; the normals' cells given
    (``cells``) the same, and at 2 and 3 threads; a grid with two tangent angles → None."""
    from methods.triple_product import brdf_table as bt
    from methods.triple_product import lighting as lt

    gen = torch.Generator().manual_seed(6)
    N = 6000
    n = torch.nn.functional.normalize(torch.randn(N, 3, generator=gen), dim=-1)
    n[:8] = torch.tensor([0.0, 1.0, 0.0])
    n[8:16] = torch.tensor([0.0, -1.0, 0.0])
    n[16:24] = torch.tensor([1.0, 0.0, 0.0])
    n[24:32] = torch.nn.functional.normalize(torch.tensor([1.0, 0.3, -1e-8]), dim=0)
    R = lt.local_frames(n, "grid").float().contiguous()
    cam = torch.tensor([0.3, 2.0, 4.0])
    P = torch.randn(N, 3, generator=gen)
    P[32:40] = cam - 2.0 * n[32:40]                   # ωo = n: θ = 0
    P[40:48] = cam + 1.5 * n[40:48]                   # ωo = −n: below the horizon
    region = torch.randint(0, 3, (N,), generator=gen)
    used = torch.randperm(N, generator=gen)[: N - 500]
    og, grid = bt.OutgoingGrid(*ogrid), lt.FrameGrid(*fgrid)
    got = native.vertex_lookups(used, P, R, region, cam, og, grid)
    if got is None:
        pytest.skip("no native loops")
    wo = torch.nn.functional.normalize(cam - P[used], dim=-1)
    rows, w, lrows, lw = fast_eval.grid_lookups(R[used], wo, og, grid, "trilinear")
    want = (rows + region[used][:, None] * og.size, w, lrows, lw)
    for g, x in zip(got, want):
        assert g.dtype == x.dtype and torch.equal(g, x)
    every = native.vertex_lookups(torch.arange(N), P, R, region, cam, og, grid)
    again = native.vertex_lookups(used, P, R, region, cam, og, grid, cells=(every[2], every[3]))
    for g, x in zip(again, got):
        assert torch.equal(g, x)
    old, t = native.MIN_ITEMS_PER_THREAD, torch.get_num_threads()
    native.MIN_ITEMS_PER_THREAD = 8
    try:
        for nt in (2, 3):                             # split over OpenMP's team: the same bits
            torch.set_num_threads(nt)
            for g, x in zip(native.vertex_lookups(used, P, R, region, cam, og, grid), got):
                assert torch.equal(g, x), nt
    finally:
        native.MIN_ITEMS_PER_THREAD = old
        torch.set_num_threads(t)
    assert native.vertex_lookups(used, P, R, region, cam, og, lt.FrameGrid(fgrid[0], fgrid[1], 2)) is None
    with pytest.raises(IndexError):
        native.vertex_lookups(used + N, P, R, region, cam, og, grid)


def test_render_vertex_lookups_native_equals_torch(monkeypatch):
    """A per-vertex render whose look-ups come from `native.vertex_lookups` (`TripleProduct._vertex_lookups`)
    = the same render with them from `fast_eval.grid_lookups` (``VERTEX_LOOKUPS`` off), bit for bit, over a
    view change and a lighting change (the cells of the normals made once, reused)."""
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    from methods.triple_product import TripleProduct
    from methods.triple_product import method as tp_method

    scene = get_scene("sphere_plane", "test")
    m = TripleProduct(level=2, n_coeffs=None, shading="vertex", frame_grid=(5, 8, 1), brdf_dirs=(4, 4),
                      brdf_supersample=1, progress=False)
    m.precompute(scene)
    for kind in ("V", "L"):
        frames = make_sequence(scene, kind, n_frames=3, seed=1)
        gbs = [make_gbuffer(scene, f, 1) for f in frames]
        monkeypatch.setattr(tp_method, "VERTEX_LOOKUPS", True)
        on = [m.render(f, g) for f, g in zip(frames, gbs)]
        assert m._perf_cache.get(("vertex_cells",)) is not None          # the native look-ups ran
        monkeypatch.setattr(tp_method, "VERTEX_LOOKUPS", False)
        off = m.with_evaluator("auto")
        off.__dict__.pop("_perf_cache", None)
        off._light_key = None
        ref = [off.render(f, g) for f, g in zip(frames, gbs)]
        for a, b in zip(on, ref):
            assert torch.equal(a, b), kind


def test_checked_resolve_equals_gouraud_resolve(monkeypatch):
    """A per-vertex frame's Gouraud resolve without `gouraud.resolve`'s range passes (`fast_eval.gouraud_image`
    with ``checked``: `native.hit_faces` checked them) = `gouraud.resolve` bit for bit on a G-buffer
    with misses; a whole per-vertex render with it = with ``CHECKED_RESOLVE`` off, bit for bit."""
    import dataclasses

    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene
    from scenes.sequences import make_sequence
    from methods.core import gouraud

    from methods.triple_product import TripleProduct

    scene = get_scene("sphere_plane", "test")
    frames = make_sequence(scene, "V", n_frames=2, seed=3)
    gbs = [make_gbuffer(scene, f, 2) for f in frames]
    miss = torch.rand(gbs[1].hit.shape, generator=torch.Generator().manual_seed(6)) < 0.2
    gbs[1] = dataclasses.replace(gbs[1], hit=gbs[1].hit & ~miss, face=torch.where(miss, -1, gbs[1].face))
    assert not bool(gbs[1].hit.all())                                    # misses (planted) in a frame
    geo = scene.geometry()
    F = geo.F
    nv = geo.V.shape[0]
    Bv = torch.rand(nv, 3, generator=torch.Generator().manual_seed(5)) + 0.1
    old, t = native.MIN_PIXELS_PER_THREAD, torch.get_num_threads()
    try:
        for gb in gbs:
            want = gouraud.resolve(Bv, F.T, gb.face, gb.bary, gb.hit, gb.height, gb.width, gb.spp_side)
            assert torch.equal(fast_eval.gouraud_image(gb, F, Bv, checked=True), want)
            faces = native.hit_faces(gb.hit, gb.face, F, nv)[0]
            for nt, per in ((1, old), (2, 64), (3, 64)):           # the face table and the pixels on 1-3 threads
                torch.set_num_threads(nt)
                native.MIN_PIXELS_PER_THREAD = per
                assert torch.equal(native.resolve(Bv, F, faces, gb.hit, gb.face, gb.bary, gb.height, gb.width,
                                                  gb.spp_side), want), nt
                assert torch.equal(fast_eval.gouraud_image(gb, F, Bv, checked=True, faces=faces), want), nt
    finally:
        native.MIN_PIXELS_PER_THREAD = old
        torch.set_num_threads(t)
    m = TripleProduct(level=2, n_coeffs=None, shading="vertex", frame_grid=(5, 8, 1), brdf_dirs=(4, 4),
                      brdf_supersample=1, progress=False)
    m.precompute(scene)
    calls = []
    real = gouraud.resolve
    monkeypatch.setattr(gouraud, "resolve", lambda *a, **k: calls.append(1) or real(*a, **k))
    tab = []
    real_tab = native.resolve
    monkeypatch.setattr(native, "resolve", lambda *a, **k: tab.append(1) or real_tab(*a, **k))
    on = [m.render(f, g) for f, g in zip(frames, gbs)]
    assert not calls and len(tab) == 2                                   # the face-table loop ran
    monkeypatch.setattr(fast_eval, "FACE_TABLE_RESOLVE", False)
    mid = [m.render(f, g) for f, g in zip(frames, gbs)]
    assert not calls and len(tab) == 2                                   # the shared loop, unchecked
    monkeypatch.setattr(fast_eval, "CHECKED_RESOLVE", False)
    off = [m.render(f, g) for f, g in zip(frames, gbs)]
    assert len(calls) == 2
    for a, b, c in zip(on, mid, off):
        assert torch.equal(a, c) and torch.equal(b, c)


@pytest.mark.parametrize("n", [64, 48])
def test_unpack_chunks_gives_the_table(n):
    """`native.unpack_chunks` of a table's packed chunks (`native.packed_chunks`) is the table (every
    zero pattern of `_vis`, 8 dividing n: the chunks cover every non-zero); a row length 8 does not
    divide, or lists of another table, raise."""
    gen = torch.Generator().manual_seed(7)
    V = _vis(n, gen)
    ch = native.chunks(V)
    got = native.unpack_chunks(native.packed_chunks(V, ch), ch, V.shape)
    assert torch.equal(got, V)
    Vo = _vis(45, gen)
    co = native.chunks(Vo)
    with pytest.raises(ValueError):
        native.unpack_chunks(native.packed_chunks(Vo, co), co, Vo.shape)
    with pytest.raises(ValueError):
        native.unpack_chunks(native.packed_chunks(V, ch), ch, (V.shape[0] + 1, n))


def test_render_packed_only_same_bits(monkeypatch):
    """Per-vertex renders with the packed visibility chunks as the only copy of the live visibility
    table (`fast_eval.VIS_PACKED_ONLY`: its rows dropped after the frame that packed them) = with the
    rows kept beside them, bit for bit, over view changes, lighting changes (the pairs a pending
    lighting projects read the bit sets kept in the packed entry), a material edit (new live
    triangles: the rows rebuilt, packed again) and the views after it; the same `frame_cost` (its
    zero counts read the rows unpacked); ``memory()`` smaller by exactly the rows; readers of whole
    rows on the packed-only instance (`fast_eval.live_table`, a grouped pixel-style call) get the
    rows back (`native.unpack_chunks`) and the same sums."""
    import dataclasses

    from references.gbuffer import make_gbuffer
    from scenes.materials import Phong

    scene, m, off, views, frames, region = _chess_vertex(2)
    edit = dataclasses.replace(frames[-1], materials={**frames[-1].materials, region: Phong(kd=0.3, ks=0.4, s=20.0)})
    frames += [edit, dataclasses.replace(views[0], materials=edit.materials)]
    kinds = ["V", "V", "L", "L", "V", "V", "VB", "V"]
    packs = []
    for f, kind in zip(frames, kinds):
        gb = make_gbuffer(scene, f, 1)
        monkeypatch.setattr(fast_eval, "VIS_PACKED_ONLY", True)
        img = m.render(f, gb)
        cost = m.frame_cost(kind, gb.num_samples)
        pk = m._perf_cache.get(("packed", "V"))
        assert pk is not None and pk[5] is not None                        # packed, bit sets kept
        assert all(m._perf_cache.get(k) is None for k in (("live", "V"), ("chunks",), ("major", "V"), ("vis_bits",)))
        packs.append(pk[4])
        live = fast_eval.live_triangles(m)
        monkeypatch.setattr(fast_eval, "VIS_PACKED_ONLY", False)
        ref = off.render(f, gb)
        assert off._perf_cache.get(("packed", "V")) is None
        rows = off._perf_cache[("live", "V")][2]
        assert torch.equal(img, ref)
        assert cost == off.frame_cost(kind, gb.num_samples)
        assert m.memory()["fine_values"] == off.memory()["fine_values"] - rows.numel() * 4
        assert torch.equal(fast_eval.live_table(m, "V", m.V_val, live), rows)
        assert torch.equal(packs[-1], off._perf_cache[("major", "V")][2])
    assert packs[0] is packs[5] and packs[6] is not packs[5]               # packed once per live table
    # a grouped (pixel-style: 3 visibility rows per point) call on the packed-only instance
    gen = torch.Generator().manual_seed(8)
    B = 300
    v = torch.randint(0, m.V.shape[0], (B,), generator=gen)
    vrows = torch.randint(0, m.V.shape[0], (B, 3), generator=gen)
    vw = torch.rand(B, 3, generator=gen)
    wo = torch.nn.functional.normalize(torch.randn(B, 3, generator=gen), dim=-1)
    args = (m.R[v], wo, m.vertex_region[v], vrows, vw / vw.sum(1, keepdim=True))
    got = fast_eval.shade_fine(m, *args, grouped=True)
    assert m._perf_cache.get(("live", "V")) is None                      # unpacked for the call, not kept
    assert torch.equal(got, fast_eval.shade_fine(off, *args, grouped=True))


def test_packed_only_native_switched_off(monkeypatch):
    """An instance holding its visibility packed only (`fast_eval.VIS_PACKED_ONLY`) whose native loops
    are switched off afterwards (``PRTBENCH_COMPILE=0``: `native.available` False) renders through the
    torch kernels on the rows unpacked — the image of an instance that kept its rows, bit for bit."""
    from references.gbuffer import make_gbuffer

    scene, m, off, (f0, f1), _, _ = _chess_vertex(4)
    g0, g1 = make_gbuffer(scene, f0, 1), make_gbuffer(scene, f1, 1)
    m.render(f0, g0)
    assert m._perf_cache.get(("packed", "V")) is not None and m._perf_cache.get(("live", "V")) is None
    off.render(f0, g0)
    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    assert not native.available()
    assert torch.equal(m.render(f1, g1), off.render(f1, g1))
    assert m._perf_cache.get(("live", "V")) is None                       # unpacked for the frame, not kept


def test_pixel_frames_read_the_kept_rows(monkeypatch):
    """A per-pixel instance's frames after its first (views, then a lighting change) read the live
    visibility rows and chunk lists built once — no row unpacked (`fast_eval.unpacked`,
    `native.unpack_chunks`: `VIS_PACKED_ONLY` is the per-vertex loop's), nothing packed, no fine-value
    table, chunk list or fullness test rebuilt — through the grouped native loop (`native.groups`), with
    the full index table held broadcast (`method._broadcast_full`); the image equals that of an instance
    built the session-35 way (index table dense, packed-only off) bit for bit. Session 37's check of
    the per-pixel V frames that read 0.85x in session 36's runs (tp37): a per-frame unpack or rebuild
    fails it."""
    import copy

    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    from methods.triple_product import TripleProduct

    scene = get_scene("chess", "test")
    m = TripleProduct(level=2, n_coeffs=None, frame_grid=(5, 8, 1), brdf_dirs=(4, 4), brdf_supersample=1,
                      progress=False)
    m.precompute(scene)
    assert m.config["shading"] == "pixel" and m.V_idx.stride() == (0, 1)
    dense = copy.copy(m.with_evaluator("auto"))
    dense.__dict__.pop("_perf_cache", None)
    dense.V_idx = m.V_idx.contiguous()
    frames = make_sequence(scene, "V", n_frames=3, seed=5) + make_sequence(scene, "L", n_frames=2, seed=5)
    calls: dict[str, int] = {}

    def counted(mod, name):
        f = getattr(mod, name)

        def g(*a, **k):
            calls[name] = calls.get(name, 0) + 1
            return f(*a, **k)
        monkeypatch.setattr(mod, name, g)

    for mod, name in ((fast_eval, "unpacked"), (native, "unpack_chunks"), (native, "packed_chunks"),
                      (native, "chunks"), (fast_eval, "fine_values"), (native, "groups")):
        counted(mod, name)
    keep = ("live", "V"), ("chunks",), ("full", "V"), ("live_tris",)
    held = None
    for i, f in enumerate(frames):
        gb = make_gbuffer(scene, f, 1)
        calls.clear()
        img = m.render(f, gb)
        now = {k: m._perf_cache.get(k) for k in keep}
        assert all(v is not None for v in now.values())
        assert m._perf_cache.get(("packed", "V")) is None and m._perf_cache.get(("major", "V")) is None
        if i:
            assert all(now[k] is held[k] for k in keep), i                # the tables of the first frame
            assert calls.get("groups", 0) >= 1, calls                     # the grouped native loop ran
            for name in ("unpacked", "unpack_chunks", "packed_chunks", "chunks"):
                assert calls.get(name, 0) == 0, (i, name, calls)
            if i < 3:                                                     # a view change transforms nothing
                assert calls.get("fine_values", 0) == 0, (i, calls)
        held = now
        monkeypatch.setattr(fast_eval, "VIS_PACKED_ONLY", False)
        ref = dense.render(f, gb)
        monkeypatch.setattr(fast_eval, "VIS_PACKED_ONLY", True)
        assert torch.equal(img, ref), i


def test_library_memo_follows_the_switches(monkeypatch):
    """`native.loaded` keeps a library that loaded (a `_lib` call in a frame is a dict look-up) but reads
    ``PRTBENCH_TP_NATIVE`` and ``PRTBENCH_COMPILE`` at every call (None while either is off, the same
    library when back on), never keeps a None, and is what `native.load` gives."""
    from methods.core import native as core_native
    from methods.triple_product import native_group, native_light

    libs = (native._lib(), native_group._lib(), native_light._lib())
    assert all(lib is not None for lib in libs)
    assert native._lib() is libs[0] and native_group._lib() is libs[1] and native_light._lib() is libs[2]
    # the library `native.load` gives: the same shared object, the same dlopen handle (not necessarily the same
    # CDLL object: a test earlier in this worker may have called `methods.core.native.cache_clear()`, after which
    # `load` wraps the loaded library in a new CDLL while the memo keeps the first — CI of de12025)
    core = core_native.load("tp_zeros", native._SOURCE, native._SIGNATURES, extra_flags=native._flags())
    assert (libs[0]._name, libs[0]._handle) == (core._name, core._handle)
    for var in ("PRTBENCH_TP_NATIVE", "PRTBENCH_COMPILE"):
        monkeypatch.setenv(var, "0")
        assert native._lib() is None and native_group._lib() is None and native_light._lib() is None, var
        assert not native.available()
        monkeypatch.setenv(var, "1")
        assert native._lib() is libs[0] and native_group._lib() is libs[1] and native_light._lib() is libs[2], var
    # a library that does not load is not remembered
    monkeypatch.setattr(core_native, "load", lambda *a, **k: None)
    assert native.loaded("tp_memo_test", "", {}, ("-x",)) is None
    assert ("tp_memo_test", ("-x",)) not in native._LOADED


@pytest.mark.parametrize("blk", [0, 1, 7, 64])
def test_points_dynamic_blocks_same_bits(blk, monkeypatch):
    """Session 39: `native.points` at 2 and 3 threads with its points handed out dynamically in blocks
    of `POINTS_BLOCK` (0: the static split) = one thread bit for bit, row-major and chunk-major tables,
    packed visibility chunks too (each point's sums in one thread)."""
    gen = torch.Generator().manual_seed(11)
    n = 64
    Vt, Rt, Lt = _tables(n, gen)
    B = 203
    vrows = torch.arange(B) % Vt.shape[0]
    vw = torch.rand(B, generator=gen) + 0.5
    brows, lrows = torch.randint(0, 7, (B, 4), generator=gen), torch.randint(0, 9, (B, 4), generator=gen)
    bw = torch.rand(B, 4, generator=gen) * (torch.rand(B, 4, generator=gen) < 0.7)
    lw = torch.rand(B, 4, generator=gen) * (torch.rand(B, 4, generator=gen) < 0.6)
    ch = native.chunks(Vt)
    Rm, Lm, Vp = native.chunk_major(Rt), native.chunk_major(Lt), native.packed_chunks(Vt, ch)
    args = (vrows, vw, brows, bw, lrows, lw, ch)
    want = native.points(Vt, Rt, Lt, *args)
    want_cm = native.points(Vt, Rm, Lm, *args, r_major=True, l_major=True, v_packed=Vp)
    assert bool((want != 0).any())
    monkeypatch.setattr(native, "MIN_ITEMS_PER_THREAD", 8)
    monkeypatch.setattr(native, "POINTS_BLOCK", blk)
    t = torch.get_num_threads()
    try:
        for nt in (2, 3):
            torch.set_num_threads(nt)
            assert torch.equal(native.points(Vt, Rt, Lt, *args), want), nt
            assert torch.equal(native.points(Vt, Rm, Lm, *args, r_major=True, l_major=True, v_packed=Vp), want_cm), nt
    finally:
        torch.set_num_threads(t)


@pytest.mark.parametrize("threads", [2, 3])
def test_hit_faces_threads_same_lists(threads, monkeypatch):
    """Session 39: `native.hit_faces` with its marks split over the threads (`HIT_THREADS`) gives the
    lists and the count of one thread (C lists and torch.nonzero lists), and still raises on an index
    outside its table."""
    gen = torch.Generator().manual_seed(threads)
    nv, nf, P = 700, 900, 50001
    F = torch.randint(0, nv, (nf, 3), generator=gen)
    hit = torch.rand(P, generator=gen) < 0.6
    face = torch.where(hit, torch.randint(0, nf // 2, (P,), generator=gen) * 2, torch.full((P,), -1))
    want = native.hit_faces(hit, face, F, nv)
    if want is None:
        pytest.skip("no native loops")
    monkeypatch.setattr(native, "MIN_HIT_SAMPLES_PER_THREAD", 16)
    t = torch.get_num_threads()
    try:
        torch.set_num_threads(threads)
        for lists in (True, False):
            monkeypatch.setattr(native, "HIT_LISTS", lists)
            got = native.hit_faces(hit, face, F, nv)
            assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1]) and got[2] == want[2], lists
        bad = face.clone()
        bad[torch.nonzero(hit)[-1]] = nf                                  # in the last thread's share
        with pytest.raises(IndexError):
            native.hit_faces(hit, bad, F, nv)
        F2 = F.clone()
        F2[want[0][-1], 0] = nv
        with pytest.raises(IndexError):
            native.hit_faces(hit, face, F2, nv)
    finally:
        torch.set_num_threads(t)
