"""The in-out fast run-time path (``methods.inout.fast``, `InOut.render`) against the reference path it
replaced (`InOut._render_reference`, Mahajan 2008 eq. 4 per sample, kept as the oracle), its building
blocks against their definitions, and the cost model (`InOut.frame_cost`) against a hand count.

Tiny precompute settings (8×8 BRDF grid, 4×4 cube faces, 16 kept coefficients, a 16² table): this is
about the run-time arithmetic, not accuracy, so every library scene stays within seconds.
"""
from __future__ import annotations

import copy

import pytest
import torch

from methods.base import GBUFFER_BYTES_PER_SAMPLE, FrameCost, tensor_bytes
from methods.core.frames import frame_matrix
from methods.inout import fast
from methods.inout import native_sample
from methods.inout import method as inout_method
from methods.inout import transport as tp
from methods.inout.method import InOut
from references.gbuffer import make_gbuffer
from scenes.library import SCENES, get_scene
from scenes.sequences import make_sequence

TINY = dict(brdf_res=8, cube_res=4, n_coeffs=16, lut_res=16, light_supersample=2, terms=6)
# Per scene, what it exercises besides the default: K from the paper's rule (K = 100 for the Phong
# sphere: many terms), all lighting coefficients kept vs the light_coeffs largest.
VARIANTS = {"sphere_plane": dict(terms=None), "chess": dict(light_coeffs=24), "alcove": {}, "shadow_detail": {},
            "creature": {}, "bunny": dict(terms=None), "dragon": {}, "character": {}}
KINDS = ("V", "L", "E")
# Fast vs reference: float32, the same terms summed in another order (X per vertex and node, then
# the 12 weights, vs c̄ and σh per sample, then the K-term dot product); measured ≤ 3e-7 of the
# image's peak on sphere_plane at K = 100.
RTOL = 1e-5


@pytest.fixture(scope="module")
def precomputed():
    built = {}

    def get(name: str) -> InOut:
        if name not in built:
            scene = get_scene(name, "test")
            m = InOut(**{**TINY, **VARIANTS.get(name, {})})
            m.precompute(scene)
            built[name] = m
        return built[name]

    return get


def _pair(m: InOut) -> tuple[InOut, InOut]:
    """Two copies of one precomputation with caches of their own (fast, reference)."""
    a, b = copy.copy(m), copy.copy(m)
    a._reset_cache()
    b._reset_cache()
    return a, b


def _assert_sequence_equal(m: InOut, kind: str, spp_side: int = 1, n_frames: int = 3, seed: int = 3) -> None:
    fast_m, ref_m = _pair(m)
    for frame in make_sequence(m.scene, kind, n_frames=n_frames, seed=seed):  # frames 1, 2: the caches
        gb = make_gbuffer(m.scene, frame, spp_side)
        got, want = fast_m.render(frame, gb), ref_m._render_reference(frame, gb)
        scale = float(want.abs().max())
        assert scale > 0
        err = float((got - want).abs().max())
        assert err <= RTOL * scale, f"{m.scene.name} {kind} frame {frame.index}: {err} vs peak {scale}"


def _bunny_view(precomputed):
    """The test-size bunny's in-out model, its first V frame, that frame's G-buffer and the fast
    path's view set-up of it (`InOut._view_setup`)."""
    m = precomputed("bunny")
    fast_m, _ = _pair(m)
    frame = make_sequence(m.scene, "V", n_frames=1, seed=0)[0]
    gb = make_gbuffer(m.scene, frame, 2)
    return m, frame, gb, fast_m._view_setup(frame, gb)


@pytest.mark.parametrize("name", SCENES)
def test_fast_path_equals_reference(precomputed, name):
    """Every library scene in-out accepts, V / L / E sequences rendered in order (so both paths'
    caches are exercised): the fast image equals the reference to float32 round-off."""
    scene = get_scene(name, "test")
    why = InOut.capabilities.why_not(scene, "L", 0)
    if why is not None:
        pytest.skip(why)
    m = precomputed(name)
    for kind in KINDS:
        _assert_sequence_equal(m, kind)


@pytest.mark.parametrize("patch", [{"DENSE_HIT_FRACTION": 2.0}, {"DENSE_HIT_FRACTION": 0.0},
                                   {"MAX_WINDOW": 2}, {"CHUNK": 100}])
def test_every_branch_equals_reference(precomputed, monkeypatch, patch):
    """The branches the defaults may not reach on a scene: only the hits gathered first (a G-buffer
    with many misses) or every sample shaded, windows of one cell (nearly every entry on the exact
    path), blocks smaller than a scanline."""
    for key, value in patch.items():
        monkeypatch.setattr(inout_method if key == "DENSE_HIT_FRACTION" else fast, key, value)
    # the compiled path these branches belong to (``native_sample``'s C loop is tested in
    # test_native_sample.py, against this path)
    monkeypatch.setattr(native_sample, "available", lambda: False)
    m = precomputed("bunny")
    for kind in ("V", "L"):
        _assert_sequence_equal(m, kind, spp_side=2)


def _c_reference(m: InOut, L: torch.Tensor) -> dict[str, torch.Tensor]:
    """c (Vr, 3, K) of every vertex of every region under L by the reference product
    (`InOut._ensure_c_reference`: T̃ · L, torch's sparse product), in the fast path's layout."""
    r = copy.copy(m)
    r._reset_cache()
    r.L = L
    r._ensure_c_reference()
    return {reg.name: r._c[reg.name].transpose(1, 2) for reg in m.regions}


def _assert_c_rows_equal(m: InOut, want: dict[str, torch.Tensor]) -> None:
    for name, v in m._cf_valid.items():
        got, ref = m._cf[name][v], want[name][v]
        assert float((got - ref).abs().max()) <= 1e-6 * max(float(ref.abs().max()), 1e-30), name


@pytest.mark.parametrize("shading", ["sample", "vertex"])
def test_lighting_is_computed_for_every_vertex_first_then_where_seen(precomputed, shading):
    """The first lighting after the precompute computes c_k for every vertex of every region (a V
    sequence's later frames then do no lighting work); a later lighting change computes c_k for the
    vertices the view references (in whole blocks), not for every vertex, and a frame that then sees
    other vertices fills those in. Every computed row equals the reference c = T̃ · L, the image
    stays exact."""
    m0 = precomputed("sphere_plane")
    fast_m, _ = _pair(m0)
    fast_m._config = {**m0._config, "shading": shading}
    frames = make_sequence(m0.scene, "L", n_frames=3, seed=5)
    fast_m.render(frames[0], make_gbuffer(m0.scene, frames[0], 1))
    assert fast_m._cf_valid.keys() == {reg.name for reg in m0.regions}
    assert all(bool(v.all()) for v in fast_m._cf_valid.values())     # every vertex under the first lighting
    _assert_c_rows_equal(fast_m, _c_reference(m0, fast_m.L))
    fast_m.render(frames[1], make_gbuffer(m0.scene, frames[1], 1))  # a lighting change: lazily
    valid = {name: v.clone() for name, v in fast_m._cf_valid.items()}
    assert any(not bool(v.all()) for v in valid.values())            # the far side was not computed
    assert any(bool(v.any()) for v in valid.values())
    _assert_c_rows_equal(fast_m, _c_reference(m0, fast_m.L))
    for frame in make_sequence(m0.scene, "V", n_frames=3, seed=6)[1:]:  # other views, the same lighting
        fast_m.render(frame, make_gbuffer(m0.scene, frame, 1))
    for name, v in fast_m._cf_valid.items():
        assert bool((v | ~valid[name]).all())                          # once valid, stays valid (no relight)
    _assert_c_rows_equal(fast_m, _c_reference(m0, fast_m.L))
    _assert_sequence_equal(_vertex(m0) if shading == "vertex" else m0, "L", n_frames=3, seed=5)


def _random_csr(rows: int, D: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """A CSR (int64 crow, int32 col, float32 val) with empty rows, rows of 1-3 entries (the loop's
    tail only) and long rows, columns repeated within a row."""
    g = torch.Generator().manual_seed(seed)
    n = torch.randint(0, 40, (rows,), generator=g)
    n[::7] = 0
    n[1::5] = torch.randint(1, 4, (n[1::5].numel(),), generator=g)
    n[3::11] = 300
    crow = torch.cat([torch.zeros(1, dtype=torch.int64), n.cumsum(0)])
    nnz = int(crow[-1])
    return crow, torch.randint(0, D, (nnz,), generator=g, dtype=torch.int32), torch.randn(nnz, generator=g)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_native_csr_product_is_the_sparse_product(monkeypatch, threads):
    """``csr.csr_dense4`` (the native c = T̃ · L loop) on any row range equals torch's CSR × dense
    product to float32 round-off, bit for bit the same at 1 and 2 threads (each row one thread's
    sum), and `light_rows` takes it; `check_csr` refuses arrays the unchecked loop must not read."""
    from methods.core.threads import torch_threads
    from methods.inout import csr

    if not csr.available():
        pytest.skip("no C compiler: light_rows uses torch's product")
    monkeypatch.setattr(csr, "_MIN_ROWS_PER_THREAD", 8)           # split even this small matrix
    D = 96
    crow, col, val = _random_csr(1000, D, 0)
    assert csr.check_csr(crow, col, val, D)
    L4 = torch.randn(D, 4, generator=torch.Generator().manual_seed(1))
    want = torch.sparse_csr_tensor(crow, col.long(), val.double(), size=(1000, D)) @ L4.double()
    peak = float(want.abs().max())
    for r0, r1 in [(0, 1000), (7, 8), (3, 3), (250, 999), (998, 1000)]:
        with torch_threads(threads):
            got = csr.csr_dense4(crow, col, val, L4, r0, r1)
        with torch_threads(1):
            one = csr.csr_dense4(crow, col, val, L4, r0, r1)
        assert got.shape == (r1 - r0, 4) and torch.equal(got, one)
        assert float((got.double() - want[r0:r1]).abs().sum(1).max()) <= 1e-6 * peak if r1 > r0 else True
    # many blocks of K rows (`light_vertices`' call): split over the threads' ranges, the same bits
    first = torch.randint(0, 1000 - 5, (300,), generator=torch.Generator().manual_seed(4))
    with torch_threads(threads):
        got = csr.csr_blocks4(crow, col, val, L4, first, 5)
    with torch_threads(1):
        one = csr.csr_blocks4(crow, col, val, L4, first, 5)
    rows = (first[:, None] + torch.arange(5)).reshape(-1)
    assert torch.equal(got, one) and float((got.double() - want[rows]).abs().max()) <= 1e-6 * peak
    # light_rows of a region (K = 5 terms per vertex) takes the native loop and equals the torch path
    fr = fast.FastRegion(col=col, val=val, crow=crow, sh_lut=torch.zeros(4, 15), sh_nc=torch.zeros(12, 5), K=5,
                         R=2, native=True)
    L = L4[:, :3].contiguous()
    native, calls = csr.csr_dense4, []
    monkeypatch.setattr(csr, "csr_dense4", lambda *a: calls.append(a[-2:]) or native(*a))
    got = fast.light_rows(fr, L, 10, 150)
    assert calls == [(50, 750)]
    want_rows = fast.light_rows_torch(fr, L, 10, 150)
    assert got.shape == want_rows.shape == (140, 5, 3)
    assert float((got - want_rows).abs().max()) <= 1e-6 * float(want_rows.abs().max())
    # arrays the loop must not read unchecked
    bad = col.clone()
    bad[5] = D
    assert not csr.check_csr(crow, bad, val, D)
    bad[5] = -1
    assert not csr.check_csr(crow, bad, val, D)
    dec = crow.clone()
    dec[10] = dec[9] - 1
    assert not csr.check_csr(dec, col, val, D)
    assert not csr.check_csr(crow, col.long(), val, D)
    assert not csr.check_csr(crow, col[:-1], val[:-1], D)                # crow[-1] past the arrays


def test_light_vertices_is_the_sparse_product_of_those_rows():
    """``fast.light_vertices`` (any vertex order, repeats) = the rows of `light_rows_torch`."""
    from methods.inout import csr

    if not csr.available():
        pytest.skip("no C compiler: light_rows uses torch's product")
    crow, col, val = _random_csr(600, 50, 2)
    fr = fast.FastRegion(col=col, val=val, crow=crow, sh_lut=torch.zeros(4, 9), sh_nc=torch.zeros(12, 3), K=3, R=2,
                         native=True)
    L = torch.randn(50, 3, generator=torch.Generator().manual_seed(3))
    assert fast.native(fr, L) and not fast.native(fr, L.double())
    verts = torch.tensor([199, 0, 5, 5, 123, 17, 198])
    want = fast.light_rows_torch(fr, L, 0, 200)[verts]
    got = fast.light_vertices(fr, L, verts)
    assert got.shape == (7, 3, 3)
    assert float((got - want).abs().max()) <= 1e-6 * float(want.abs().max())
    with pytest.raises(ValueError):
        fast.light_vertices(fr, L, torch.tensor([200]))                       # rows 600..602: past the matrix


def test_take_rows_is_index_select():
    """``fast.take_rows`` (the gather along the array's layout) returns ``index_select``'s values and
    row-major layout for column-major (the bench G-buffer's ω_o, barycentrics), row-major, sliced and
    1-D arrays, any index order, repeats and the empty index."""
    g = torch.Generator().manual_seed(6)
    q = 1000
    base = torch.randn(3, q, generator=g)
    arrays = [base.T, base.T.contiguous(), torch.randn(2, q, generator=g).T, base.T[:, :2], base.T[::2],
              torch.randint(0, 50, (q,), generator=g), torch.rand(q, generator=g) > 0.5]
    for t in arrays:
        n = t.shape[0]
        for idx in (torch.randperm(n, generator=g)[:300], torch.randint(0, n, (500,), generator=g).sort().values,
                    torch.zeros(0, dtype=torch.long), torch.tensor([5]), torch.tensor([n - 1, 0, n - 1])):
            a, b = fast.take_rows(t, idx), t.index_select(0, idx)
            assert torch.equal(a, b) and a.stride() == b.stride() and a.dtype == b.dtype


def test_face_mask_is_the_indexed_mask():
    """`InOut`'s referenced-face mask (a histogram of the samples' faces, M = none) equals
    ``mask[face] = True`` over the M faces."""
    g = torch.Generator().manual_seed(7)
    M = 37
    for face in (torch.randint(0, M + 1, (5000,), generator=g), torch.full((10,), M), torch.zeros(0, dtype=torch.long),
                 torch.tensor([0, M - 1, M, 3, 3])):
        ref = torch.zeros(M + 1, dtype=torch.bool)
        ref[face] = True
        assert torch.equal(inout_method._face_mask(face, M), ref[:M])


def test_hit_face_counts_is_the_histogram_of_the_hits_faces(monkeypatch):
    """``fast.hit_face_counts`` (the vertex shading's referenced-face pass: compiled blocks, the last
    padded) is the histogram of the hits' faces (bin M: the misses) and flags a hit on a face of
    another region, whatever the block size."""
    g = torch.Generator().manual_seed(5)
    M = 23
    face_region = torch.arange(M) % 3
    for q in (1, 1000, 5000):
        for block in (1024, 4096):
            monkeypatch.setattr(fast, "MIN_SAMPLE_BLOCK", block)
            monkeypatch.setattr(fast, "MAX_SAMPLE_BLOCK", block)
            face = torch.randint(-1, M, (q,), generator=g)
            hit = face >= 0
            region = face_region[face.clamp_min(0)]
            counts, bad = fast.hit_face_counts(face, region, hit, face_region)
            want = torch.bincount(torch.where(hit, face, M), minlength=M + 1)
            assert torch.equal(counts, want) and not bad
            miss = (~hit).nonzero(as_tuple=True)[0]
            if miss.numel():                                        # a miss's region is never checked
                region[miss[0]] = (region[miss[0]] + 1) % 3
                assert not fast.hit_face_counts(face, region, hit, face_region)[1]
            k = int(hit.nonzero()[-1, 0])                            # the last hit: maybe in the padding
            region[k] = (region[k] + 1) % 3
            assert fast.hit_face_counts(face, region, hit, face_region)[1]


def test_hit_face_mask_is_the_histogram_of_the_hits_faces():
    """``csr.hit_face_mask`` (the native pass of the vertex view) against ``fast.hit_face_counts``
    and the vertices of its faces: the vertex mask of the faces with a hit, their count, the miss
    count and the region flag, with out-of-range faces on hits (clamped by both), misses of any face
    and region, no sample, at 1 and 2 threads (70000 samples split over OpenMP's team); non-int64 /
    strided arrays are refused (None: the caller takes the compiled pass)."""
    from methods.inout import csr

    if not csr.available():
        pytest.skip("no native kernel")
    threads = torch.get_num_threads()
    try:
        for t in (1, 2):
            torch.set_num_threads(t)
            _check_hit_face_mask(csr)
    finally:
        torch.set_num_threads(threads)


def _check_hit_face_mask(csr) -> None:
    g = torch.Generator().manual_seed(7)
    M, nv = 23, 31
    face_region = torch.arange(M) % 3
    face_gl = torch.randint(0, nv, (3, M), generator=g, dtype=torch.int32)
    for q in (0, 1, 1000, 70000):
        face = torch.randint(-3, M + 3, (q,), generator=g)
        hit = torch.rand(q, generator=g) < 0.8
        region = face_region[face.clamp(0, M - 1)]
        region[~hit] = torch.randint(0, 3, (int((~hit).sum()),), generator=g)  # never checked
        for flip in (False, True):
            if flip and q:
                k = int(hit.nonzero()[-1, 0])
                region[k] = (region[k] + 1) % 3
            vmask, nfaces, misses, bad = csr.hit_face_mask(face, region, hit, face_region, face_gl, nv)
            counts, want_bad = fast.hit_face_counts(face, region, hit, face_region)
            faces = (counts[:M] > 0).nonzero(as_tuple=True)[0]
            want = torch.zeros(nv, dtype=torch.bool)
            want[face_gl[:, faces].reshape(-1).long()] = True
            assert vmask.dtype == torch.bool and torch.equal(vmask, want) and nfaces == faces.numel()
            assert misses == int(counts[M]) == int((~hit).sum()) and bad == want_bad == (flip and q > 0)
    assert csr.hit_face_mask(face.int(), region, hit, face_region, face_gl, nv) is None
    assert csr.hit_face_mask(face[::2], region[::2], hit[::2], face_region, face_gl, nv) is None
    assert csr.hit_face_mask(face, region, hit, face_region, face_gl.long(), nv) is None


def test_vertex_view_without_the_native_pass_equals_reference(precomputed, monkeypatch):
    """The vertex view's fallback (the compiled pass and histogram, ``fast.hit_face_counts``) when
    the native pass is not available: the same images as the reference."""
    from methods.inout import csr

    monkeypatch.setattr(csr, "hit_face_mask", lambda *a: None)
    _assert_sequence_equal(_vertex(precomputed("sphere_plane")), "V", spp_side=2)


def test_vertex_view_rejects_faces_of_another_region(precomputed):
    """Shading "vertex": a hit whose region is not its face's raises, as the reference does."""
    m = _vertex(precomputed("sphere_plane"))
    frame = make_sequence(m.scene, "V", n_frames=1, seed=0)[0]
    gb = make_gbuffer(m.scene, frame, 1)
    gb.region = gb.region.clone()
    k = int(gb.hit.nonzero()[0, 0])
    gb.region[k] = 1 - gb.region[k]
    with pytest.raises(ValueError, match="another region"):
        m.render(frame, gb)


def test_vertex_cells_is_the_eager_frame_product(precomputed):
    """``fast.vertex_cells`` (compiled) against the vertex view's former eager arithmetic: the
    direction to the camera by a batched 3 × 3 product, then ``transport.lut_cell_xyz``."""
    m = _vertex(precomputed("bunny"))
    st = m._fast_static()
    g = torch.Generator().manual_seed(6)
    ref = torch.randperm(st.voff[-1], generator=g)[:300].sort().values
    cam = torch.tensor([0.3, 2.0, -1.5])
    front, first, wc = fast.vertex_cells(ref, st.pos, st.frames, cam, st.R)
    d = cam[None, :] - st.pos.index_select(0, ref)
    x, y, z = torch.bmm(st.frames.index_select(0, ref), d.unsqueeze(-1)).squeeze(-1).unbind(-1)
    iu, iv, fu, fv = tp.lut_cell_xyz(x, y, z, st.R)
    # the continuous node coordinates (cell + fraction): a sum in another order may move a
    # coordinate on a cell edge to the neighbouring cell, at the same point
    gu_, gv_ = (first % st.R).float() + wc[:, 1] + wc[:, 3], (first // st.R).float() + wc[:, 2] + wc[:, 3]
    assert torch.allclose(gu_, iu + fu, rtol=0, atol=1e-4) and torch.allclose(gv_, iv + fv, rtol=0, atol=1e-4)
    assert torch.allclose(wc.sum(-1), torch.ones(ref.numel()), rtol=0, atol=1e-5)
    assert torch.equal(front[z.abs() > 1e-5], (z > 0)[z.abs() > 1e-5])


def test_shaded_faces_is_a_superset_of_the_horizon_test():
    """``fast.shaded_faces`` (the referenced-face pass) keeps every live sample the per-sample stage
    shades (z > 0 in its frame, eager `sample_frame` and the compiled `entry_inputs`), near-grazing
    directions included, drops the clearly back-facing ones, and flags faces of another region."""
    g = torch.Generator().manual_seed(4)
    q = 4096
    n = torch.randn(q, 3, generator=g) * torch.rand(q, 1, generator=g) * 3
    t = torch.linalg.cross(n, torch.randn(q, 3, generator=g))
    eps = torch.randn(q, 1, generator=g) * torch.logspace(-9, -1, q)[:, None]
    wo = torch.nn.functional.normalize(t, dim=-1) + eps * n                 # within ~eps of the horizon
    wo[::3] = torch.randn(q // 3 + 1, 3, generator=g)                       # and arbitrary directions
    face = torch.randint(-1, 10, (q,), generator=g)
    face_region = torch.arange(10) % 2
    region = face_region[face.clamp_min(0)]
    region[7] = 1 - region[7]
    live = face >= 0
    f, bad = fast.shaded_faces(n, wo, face, region, live, face_region, inout_method.SHADED_MARGIN)
    z = fast.sample_frame(n, wo)[2]
    front = (z > 0) & live
    _, bw, _, _ = fast.entry_inputs(n, wo, torch.full((q, 2), 0.25), face, live, torch.zeros(10, 3, dtype=torch.int32), 16)
    assert bool((front <= (f < 10)).all()) and bool(((bw[:, 0] != 0) <= (f < 10)).all())
    assert bool((f[front] == face[front]).all())
    back = live & ((n * wo).sum(-1) < -1e-3 * n.norm(dim=-1) * wo.norm(dim=-1))
    assert bool(back.any()) and bool((f[back] == 10).all())
    assert bool(bad[7]) == bool(live[7]) and int(bad.sum()) == int(live[7])
    # ω_o as columns (`InOut._view_setup`'s call), from a column-major array as the bench G-buffer's
    wo_cm = wo.T.contiguous().T
    f2, bad2 = fast.shaded_faces_cols(n, *wo_cm.unbind(1), face, region, live, face_region, inout_method.SHADED_MARGIN)
    assert torch.equal(f2, f) and torch.equal(bad2, bad)


def test_shade_rows_indices_in_range_for_any_input(precomputed):
    """The compiled per-sample kernel reads without index checks (``fast.SHADE_OPTIONS``): on inputs
    no G-buffer should hold — NaN, infinite and zero normals and directions, faces below −1 and past
    the last face — it equals the eager function, whose look-ups check every index (an index out of
    range raises there), and such samples add nothing and set no miss bit."""
    m, frame, gb, view = _bunny_view(precomputed)
    st, w = view.st, view.wins
    n, S = fast.MIN_SAMPLE_BLOCK // 4, 4
    q = n * S
    g = torch.Generator().manual_seed(7)
    normal = torch.randn(q, 3, generator=g)
    wo = torch.randn(q, 3, generator=g)
    bad = torch.tensor([[float("nan"), 0.0, 1.0], [float("inf"), 0.0, 0.0], [0.0, 0.0, 0.0],
                        [-float("inf"), float("inf"), 1.0], [float("nan")] * 3])
    normal[: 5 * 40] = bad.repeat(40, 1)
    wo[100: 100 + 5 * 40] = bad.repeat(40, 1)
    M = st.face_rows.shape[0]
    face = torch.randint(-3, M + 3, (q,), generator=g)
    face[::7] = M + 100
    live = face >= 0
    bary = torch.rand(q, 2, generator=g) * 0.5
    args = [t.unflatten(0, (n, S)) for t in (normal, wo, bary, face, live)] + [fast.pack_windows(w.win, st.face_rows, st.R), w.X, st.R]
    got, got_miss = fast.shade_rows(*args)
    want, want_miss = fast.shade_rows.eager(*args)
    assert torch.equal(got_miss, want_miss)
    scale = float(want[torch.isfinite(want)].abs().max())
    assert torch.allclose(got, want, rtol=RTOL, atol=RTOL * scale, equal_nan=True)
    # a NaN or infinite normal, a zero normal or a NaN direction: ω_o's z is NaN or 0, not above the horizon
    unshaded = ~torch.isfinite(normal).all(-1) | torch.isnan(wo).any(-1) | (normal == 0).all(-1)
    assert not bool(got_miss.reshape(-1)[unshaded].any())
    assert bool(unshaded.any()) and bool(got_miss.any())            # both kinds of sample are present


def test_pack_windows_keeps_every_field(precomputed):
    """`fast.pack_windows`: each face corner's word decodes to its vertex's window (first column,
    first row, columns, rows, offset in X) — the fields `shade_rows` reads."""
    m, frame, gb, view = _bunny_view(precomputed)
    st, w = view.st, view.wins
    p = fast.pack_windows(w.win, st.face_rows, st.R)
    want = w.win.long()[st.face_rows.long()]                                    # (M, 3, 5)
    got = torch.stack([p & 4095, (p >> 12) & 4095, p >> 32, ((p >> 24) & 15) + 2, ((p >> 28) & 15) + 2], -1)
    assert torch.equal(got, want)
    big = torch.tensor([[4095, 4094, 2**31 - 1, fast.MAX_WINDOW, fast.MAX_WINDOW]], dtype=torch.int32)
    q = fast.pack_windows(big, torch.zeros(1, 3, dtype=torch.int32), 4096)
    assert int(q[0, 0] >> 32) == 2**31 - 1 and int(q[0, 0] & 4095) == 4095 and int((q[0, 0] >> 12) & 4095) == 4094
    assert int((q[0, 0] >> 24) & 15) + 2 == fast.MAX_WINDOW and int((q[0, 0] >> 28) & 15) + 2 == fast.MAX_WINDOW
    with pytest.raises(ValueError):
        fast.pack_windows(big, torch.zeros(1, 3, dtype=torch.int32), 4097)


def test_sample_frame_is_frame_matrix():
    """The closed form of ω_o in the sample's frame equals frame_matrix(normalize(n)) @ ω_o,
    for normals on both sides of the tangent flip at n_z = 0 and not quite unit."""
    g = torch.Generator().manual_seed(0)
    n = torch.randn(5000, 3, generator=g) * 1.001
    n[:10, 2] = 0.0
    n[10:20, 2] = -1e-7
    wo = torch.nn.functional.normalize(torch.randn(5000, 3, generator=g), dim=-1)
    want = (frame_matrix(torch.nn.functional.normalize(n, dim=-1)) @ wo.unsqueeze(-1)).squeeze(-1)
    got = torch.stack(fast.sample_frame(n, wo), -1)
    assert (got - want).abs().max() <= 1e-6


def test_lut_cell_xyz_is_lut_cell():
    g = torch.Generator().manual_seed(1)
    d = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=-1)
    base, f = tp.lut_cell(d, 16)
    iu, iv, fu, fv = tp.lut_cell_xyz(*d.unbind(-1), 16, index_dtype=torch.int32)
    assert torch.equal(base, (iv * 16 + iu).long()) and torch.equal(f, torch.stack([fu, fv], -1))


def test_locality_order_is_a_morton_permutation():
    g = torch.Generator().manual_seed(2)
    p = torch.rand(500, 3, generator=g)
    perm = tp.locality_order(p)
    assert torch.equal(torch.sort(perm).values, torch.arange(500))
    # the 8 corners of a cube come in Z-order: x fastest, then y, then z
    corners = torch.tensor([[x, y, z] for z in (0.0, 1.0) for y in (0.0, 1.0) for x in (0.0, 1.0)])
    assert torch.equal(tp.locality_order(corners.flip(0)), torch.arange(7, -1, -1))
    with pytest.raises(ValueError):
        tp.locality_order(torch.zeros(4, 2))


def test_windows_hold_the_subsampled_cells_and_their_products(precomputed):
    """`fast.prepare`: each referenced vertex's window holds every cell its subsampled entries hit
    (widened by WINDOW_PAD, unless beyond MAX_WINDOW of its anchor), lies in the table, is at most
    MAX_WINDOW nodes a side, the windows lie in X without overlap; X is the K-term sum at each node."""
    m, frame, gb, view = _bunny_view(precomputed)
    st, w = view.st, view.wins
    R, k = st.R, fast.WINDOW_SUBSAMPLE
    gl, bw, (iu, iv, _, _), _ = fast.sample_inputs(st, gb.normal[::k], gb.wo[::k], gb.bary[::k],
                                                   gb.face[::k].clamp_min(0), gb.hit[::k])
    ref = torch.unique(gl[bw != 0].long())
    u0, v0, off, wu, wv = w.win.long().unbind(-1)
    assert bool((wu >= 2).all() and (wv >= 2).all())
    assert bool((wu[ref] <= fast.MAX_WINDOW).all() and (wv[ref] <= fast.MAX_WINDOW).all())
    assert bool((u0 + wu <= R).all() and (v0 + wv <= R).all())
    order = torch.argsort(off[ref])
    ends = (off + wu * wv)[ref][order]
    assert bool((off[ref][order][1:] >= ends[:-1]).all()) and int(ends[-1]) <= w.X.shape[0]   # disjoint, in X
    au, av = fast.anchors(st, ref, torch.tensor(frame.camera.origin, dtype=torch.float32))
    h = fast.MAX_WINDOW // 2 - 1
    for j in range(3):
        e = bw[j] != 0
        v, cu, cv = gl[j][e].long(), iu[e].long(), iv[e].long()
        pos = torch.searchsorted(ref, v)
        near = ((cu - au.long()[pos]).abs() <= h) & ((cv - av.long()[pos]).abs() <= h)
        inside = (cu >= u0[v]) & (cu <= u0[v] + wu[v] - 2) & (cv >= v0[v]) & (cv <= v0[v] + wv[v] - 2)
        assert bool(inside[near].all())
    # X at a few nodes of a few vertices of the first slot against the K-term sum
    fr, c = st.regions[0], view.cs[0]
    for vg in ref[ref < st.voff[1]][:: max(1, int((ref < st.voff[1]).sum()) // 7)].tolist():
        for dy in range(int(wv[vg])):
            for dx in range(int(wu[vg])):
                node = (int(v0[vg]) + dy) * R + int(u0[vg]) + dx
                want = (fr.sh_nc[node * 3:node * 3 + 3] * c[vg]).sum(-1)
                got = w.X[int(off[vg]) + dy * int(wu[vg]) + dx]
                assert torch.allclose(got, want, rtol=RTOL, atol=1e-6)


# -- the cost model ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def tiny(precomputed):
    m = precomputed("sphere_plane")
    fast_m, _ = _pair(m)
    frame = make_sequence(m.scene, "V", n_frames=1, seed=0)[0]
    gb = make_gbuffer(m.scene, frame, 2)
    return fast_m, frame, gb


def test_frame_cost_is_the_hand_count(tiny):
    """Bytes and flops of every frame kind, re-derived here from the G-buffer, the scene and the
    precomputed arrays' shapes (method docstring of `InOut.frame_cost`)."""
    m, frame, gb = tiny
    m.render(frame, gb)
    P = gb.num_samples
    hit = gb.hit
    wl = (frame_matrix(torch.nn.functional.normalize(gb.normal.float(), dim=-1))
          @ gb.wo.float().unsqueeze(-1)).squeeze(-1)
    shaded = hit & (wl[:, 2] > 0)
    Qh, Qs = int(hit.sum()), int(shaded.sum())
    faces = gb.face[shaded]
    geom_F = m.F
    b = P * 12 + Qh * (GBUFFER_BYTES_PER_SAMPLE + 8) + (P - Qh) * 1 + torch.unique(faces).numel() * 24
    f = Qh * 18 + Qs * (16 + 72)
    light_b, light_f = 0, 0
    for r, name in enumerate(m.scene.regions):
        reg = next(x for x in m.regions if x.name == name)
        K, R = reg.K, m.config["lut_res"]
        mine = shaded & (gb.region == r)
        verts = torch.unique(geom_F[gb.face[mine]])
        assert bool((reg.local_of[verts] >= 0).all())
        cells, _ = tp.lut_cell(wl[mine], R)
        nodes = torch.unique(torch.cat([cells, cells + 1, cells + R, cells + R + 1])).numel()
        b += verts.numel() * K * 12 + nodes * K * 12
        f += verts.numel() * 4 * 3 * K * 2
        # the kept coefficients of the referenced vertices (their number varies per vertex: budget "vertex")
        nnz = _kept_nnz(reg, verts, K)
        assert nnz > 0
        light_b += nnz * (4 + reg.T.col_indices().element_size())
        light_f += 2 * 3 * nnz
    rb, rf = _resample_cost(m)
    light_b, light_f = light_b + rb, light_f + rf
    assert m.frame_cost("V", P) == FrameCost(b, f)
    for kind in ("L", "E", "VL"):
        assert m.frame_cost(kind, P) == FrameCost(b + light_b, f + light_f)


def test_frame_cost_upper_bound_without_a_render(tiny):
    """No render on that G-buffer size: every sample shaded, every vertex, face and node referenced."""
    m, frame, gb = tiny
    m.render(frame, gb)
    P = 1000
    R = m.config["lut_res"]
    b = P * 12 + P * (GBUFFER_BYTES_PER_SAMPLE + 8) + m.F.shape[0] * 24
    f = P * (18 + 16 + 72)
    for reg in m.regions:
        b += reg.verts.numel() * reg.K * 12 + R * R * reg.K * 12
        f += reg.verts.numel() * 4 * 3 * reg.K * 2
    assert m.frame_cost("V", P) == FrameCost(b, f)


def test_frame_cost_bytes_bounded_by_the_arrays_read(tiny):
    """No padding: a frame's bytes never exceed the G-buffer + output + every run-time array."""
    m, frame, gb = tiny
    m.render(frame, gb)
    everything = sum(m.memory().values()) + tensor_bytes(m.scene.envmap.data) \
        + gb.num_samples * (GBUFFER_BYTES_PER_SAMPLE + 8 + 12)
    v, light = m.frame_cost("V", gb.num_samples), m.frame_cost("L", gb.num_samples)
    assert 0 < v.bytes < light.bytes <= everything and 0 < v.flops < light.flops


def test_frame_cost_validates_and_needs_precompute(tiny):
    assert InOut().frame_cost("V", 10) is None
    m, _, _ = tiny
    for kind, n in (("VB", 10), ("VBL", 10), ("P", 10), ("X", 10), ("V", -1), ("V", 1.5), ("V", True)):
        with pytest.raises(ValueError):
            m.frame_cost(kind, n)


def test_memory_counts_the_fast_arrays(tiny):
    """memory() reports the fast path's static arrays and c_k at their real sizes."""
    m, frame, gb = tiny
    m.render(frame, gb)
    st, mem = m._fast_static(), m.memory()
    assert mem["fast_static"] == tensor_bytes(st.face_gl, st.face_region, st.pos, st.frames, st.K)
    for reg in m.regions:
        assert mem[f"{reg.name}/c"] == tensor_bytes(m._cf[reg.name], m._cf_valid[reg.name])
        assert mem[f"{reg.name}/sh_table_fast"] == tensor_bytes(st.regions[m.regions.index(reg)].sh_nc)



def _compiled_vertex_slots(st, vmask: torch.Tensor, cam: torch.Tensor):
    """The vertex view's slots by the compiled pass (`InOut._vertex_view`'s fallback): the referenced
    ids, ``fast.vertex_cells_of``, then per region the vertices above their horizon."""
    ref = vmask.nonzero(as_tuple=True)[0]
    front, first, wc = fast.vertex_cells_of(ref, st.pos, st.frames, cam, st.R)
    b = torch.searchsorted(ref, torch.tensor(st.voff)).tolist()
    slots = []
    for s in range(len(st.voff) - 1):
        sel = front[b[s]:b[s + 1]].nonzero(as_tuple=True)[0] + b[s]
        slots.append((ref[sel] - st.voff[s], first[sel], wc[sel]))
    return slots, int(ref.numel())


@pytest.mark.parametrize("name", ["chess", "bunny", "creature"])
def test_native_vertex_cells_equal_the_compiled_pass(precomputed, name):
    """``native.vertex_cells`` (one C pass over the marked vertices, per region compacted) against the
    compiled pass and the slots cut from it: the same vertices above their horizon, cells and weights
    bit for bit (the same float32 operations in the same order), the same marked count — random masks
    and cameras on every side of the scene, every region."""
    from methods.inout import native

    if not native.available():
        pytest.skip("no C compiler")
    m = _vertex(precomputed(name))
    st = m._fast_static()
    g = torch.Generator().manual_seed(5)
    shaded = torch.zeros(len(m.regions), dtype=torch.int64)
    for _ in range(6):
        vmask = torch.rand(st.voff[-1], generator=g) < 0.4
        cam = torch.randn(3, generator=g) * 3.0
        got, nref = native.vertex_cells(vmask, st.voff, st.pos, st.frames, cam, st.R)
        want, want_ref = _compiled_vertex_slots(st, vmask, cam)
        assert nref == want_ref == int(vmask.sum())
        assert len(got) == len(want) == len(m.regions)
        for s, ((l1, f1, w1), (l2, f2, w2)) in enumerate(zip(got, want)):
            shaded[s] += l2.numel()
            assert torch.equal(l1, l2) and torch.equal(f1, f2) and torch.equal(w1, w2)
    assert bool((shaded > 0).all())                       # every region had vertices to compare
    # not contiguous CPU float32 / bool: None (the caller runs the compiled pass)
    assert native.vertex_cells(vmask.int(), st.voff, st.pos, st.frames, cam, st.R) is None
    assert native.vertex_cells(vmask, st.voff, st.pos.double(), st.frames, cam, st.R) is None


@pytest.mark.parametrize("K", [5, 8, 13, 88])
def test_native_vertex_radiance_equals_the_compiled_pass(K):
    """``native.vertex_radiance`` (eq. 4 at vertices, a C loop) against ``fast.vertex_radiance`` (the
    compiled pass, its oracle): random tables with K below, at and above the loop's 8 lanes, cells up
    to the table's last one, written to rows off + v of a larger output (the other rows untouched);
    float32 round-off (the K-sum in another order), and bit for bit the same at 1 and 2 threads."""
    from methods.inout import native

    if not native.available():
        pytest.skip("no C compiler")
    g = torch.Generator().manual_seed(K)
    R, Vr, n, off = 16, 3000, 1500, 7
    sh_nc = torch.randn(R * R * 3, K, generator=g)
    c = torch.randn(Vr, 3, K, generator=g)
    v = torch.randperm(Vr, generator=g)[:n].sort().values
    cell = torch.randint(0, R * R - R - 1, (n,), generator=g)
    cell[:3] = torch.tensor([0, R * R - R - 2, R - 2])
    wc = torch.rand(n, 4, generator=g)
    fr = fast.FastRegion(col=torch.zeros(0, dtype=torch.int32), val=torch.zeros(0), crow=torch.zeros(1, dtype=torch.int64),
                         sh_lut=torch.zeros(R * R, 3 * K), sh_nc=sh_nc, K=K, R=R)
    want = fast.vertex_radiance(fr, c, v, cell, wc)
    outs = []
    threads = torch.get_num_threads()
    try:
        for t in (1, 2):
            torch.set_num_threads(t)
            out = torch.full((off + Vr + 5, 3), -7.0)
            assert native.vertex_radiance(sh_nc, R, c, v, cell, wc, out, off)
            outs.append(out)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(outs[0], outs[1])
    got = outs[0][off + v]
    assert float((got - want).abs().max()) <= 1e-5 * float(want.abs().max())
    rest = torch.ones(off + Vr + 5, dtype=torch.bool)
    rest[off + v] = False
    assert bool((outs[0][rest] == -7.0).all())
    # arrays it does not take: False, nothing written
    out = torch.zeros(off + Vr, 3)
    assert not native.vertex_radiance(sh_nc.double(), R, c, v, cell, wc, out, off)
    assert not native.vertex_radiance(sh_nc, R, c, v.int(), cell, wc, out, off)
    assert bool((out == 0).all())
    with pytest.raises(ValueError, match="do not fit"):
        native.vertex_radiance(sh_nc, R, c, v, cell, wc, torch.zeros(Vr, 3), off)


def test_vertex_fast_path_without_the_native_loops_equals_reference(precomputed, monkeypatch):
    """Shading "vertex" when the native loops are not available (no compiler, PRTBENCH_COMPILE=0):
    the compiled passes (``fast.vertex_cells``, ``fast.vertex_radiance``) give the reference's images
    on the three-region chess scene, V then L."""
    from methods.inout import native

    monkeypatch.setattr(native, "_lib", lambda: None)
    m = _vertex(precomputed("chess"))
    _assert_sequence_equal(m, "V", spp_side=2)
    _assert_sequence_equal(m, "L")


# -- shading "vertex" (eq. 4 per vertex, Gouraud to the samples) -----------------------------------


def _vertex(m: InOut) -> InOut:
    """The precomputation ``m`` shading per vertex, with caches of its own (shading is a run-time
    setting: the precomputation is the same)."""
    v = copy.copy(m)
    v._config = {**m._config, "shading": "vertex"}
    v._reset_cache()
    return v


@pytest.mark.parametrize("name", SCENES)
def test_vertex_fast_path_equals_reference(precomputed, name):
    """Every library scene, V / L / E in order, 1 and 2×2 samples per pixel: `_render_vertex` equals
    `_render_vertex_reference` (the per-sample code evaluated at each vertex, then the G-buffer's
    interpolate + resolve) to float32 round-off."""
    scene = get_scene(name, "test")
    why = InOut.capabilities.why_not(scene, "L", 0)
    if why is not None:
        pytest.skip(why)
    m = _vertex(precomputed(name))
    for spp in (1, 2):
        _assert_sequence_equal(m, "V", spp_side=spp)
    for kind in ("L", "E"):
        _assert_sequence_equal(m, kind)


def test_vertex_reference_is_per_sample_at_the_vertices(precomputed):
    """The vertex reference's per-vertex radiance is the per-sample reference evaluated with a G-buffer
    whose samples sit on the vertices (barycentrics (0, 0): the face's first corner), normal the
    vertex normal and ω_o towards the camera."""
    m = _vertex(precomputed("sphere_plane"))
    frame = make_sequence(m.scene, "V", n_frames=1, seed=0)[0]
    gb = make_gbuffer(m.scene, frame, 1)
    geom = m.scene.geometry()
    F = m.F
    hitf = torch.unique(gb.face[gb.hit])[:50]
    v0 = F[hitf, 0]
    V = torch.as_tensor(geom.V).float()
    Nrm = torch.nn.functional.normalize(torch.as_tensor(geom.N).float(), dim=-1)
    cam = torch.tensor(frame.camera.origin, dtype=torch.float32)
    n = hitf.numel()
    fake = type(gb)(1, n, 1, hit=torch.ones(n, dtype=torch.bool), face=hitf, bary=torch.zeros(n, 2),
                    position=V[v0], normal=Nrm[v0], wo=torch.nn.functional.normalize(cam - V[v0], dim=-1),
                    region=m._fast_static().face_region[hitf], coverage=torch.ones(1, n, dtype=torch.bool))
    s = copy.copy(precomputed("sphere_plane"))
    s._reset_cache()
    want = s._render_reference(frame, fake)
    got = m._render_reference(frame, fake)
    assert (got - want).abs().max() <= 1e-6 * float(want.abs().max())


def test_vertex_view_is_kept_across_lighting_changes(precomputed):
    """L / E frames: the view's referenced vertices and cells are reused (only c_k and B_v recomputed);
    a new camera, another sample count, a hit fewer, or a hit moved to a face none of whose vertices
    was referenced (the same hit count) recomputes them — and the images stay the reference's. (The
    split path's view: the first lighting's frame would run the one-loop view frame, which keeps no
    view, ``native_vframe``, so it is off here; tests/methods/inout/test_native_vframe.py tests it.)"""
    m = _vertex(precomputed("sphere_plane"))
    m._render_vertex_native = lambda frame, gbuffer: None
    frames = make_sequence(m.scene, "L", n_frames=3, seed=1)
    gb = make_gbuffer(m.scene, frames[0], 1)
    m.render(frames[0], gb)
    vv = m._vview
    m.render(frames[1], make_gbuffer(m.scene, frames[1], 1))
    assert m._vview is vv
    m.render(frames[2], make_gbuffer(m.scene, frames[2], 2))                # another sample count
    assert m._vview is not vv
    vv = m._vview
    gb2 = make_gbuffer(m.scene, frames[2], 1)
    gb2.face = gb2.face.clone()
    gb2.hit = gb2.hit.clone()
    gb2.face[gb2.hit.nonzero()[0, 0]] = -1                                  # one hit fewer, same camera
    gb2.hit = gb2.face >= 0
    m.render(frames[2], gb2)
    assert m._vview is not vv and m._vview["hits"] == int(gb2.hit.sum())
    vv = m._vview
    # one hit moved to a face of its region with no referenced vertex: same camera, same hit count
    st = m._fast_static()
    k = int(gb2.hit.nonzero()[0, 0])
    unref = ~vv["vmask"][st.face_gl.long()].any(0) & (st.face_region == gb2.region[k])
    gb3 = copy.copy(gb2)
    gb3.face = gb2.face.clone()
    gb3.face[k] = int(unref.nonzero()[0, 0])
    m.render(frames[2], gb3)
    assert m._vview is not vv and m._vview["ref"] == vv["ref"] + 3 and m._vview["hits"] == vv["hits"]
    _, ref_m = _pair(m)
    want = ref_m._render_reference(frames[2], gb3)
    assert float((m.render(frames[2], gb3) - want).abs().max()) <= RTOL * float(want.abs().max())
    for f in make_sequence(m.scene, "V", n_frames=2, seed=2):
        m.render(f, make_gbuffer(m.scene, f, 1))
    assert m._vview["key"][1] == tuple(float(x) for x in f.camera.origin)


@pytest.mark.parametrize("kind", ["L", "E"])
def test_vertex_lighting_frame_equals_fresh_precompute(kind):
    """As ``tests/methods/test_relighting.py`` for shading "vertex": frame 2 of a lighting-only
    sequence equals a fresh precompute with that lighting baked in (no stale c_k or B_v)."""
    import dataclasses

    scene = get_scene("sphere_plane", "test")
    frames = make_sequence(scene, kind, n_frames=3, seed=1)
    gbs = [make_gbuffer(scene, f, 1) for f in frames]
    m = InOut(terms=8, shading="vertex", **{k: v for k, v in TINY.items() if k != "terms"})
    m.precompute(scene)
    imgs = [m.render(f, g) for f, g in zip(frames, gbs)]
    fresh = InOut(terms=8, shading="vertex", **{k: v for k, v in TINY.items() if k != "terms"})
    fresh.precompute(dataclasses.replace(scene, envmap=frames[-1].envmap))
    want = fresh.render(dataclasses.replace(frames[-1], index=0, changed=frozenset({"view", "brdf", "light", "pose"})),
                        gbs[-1])
    scale = float(want.abs().max())
    assert float((imgs[-1] - want).abs().max()) <= 2e-5 * scale
    assert float((imgs[-1] - imgs[0]).abs().max()) > 2e-3 * scale


def test_vertex_frame_cost_is_the_hand_count(tiny):
    """Shading "vertex" (`InOut._frame_cost_vertex` docstring), re-derived from the G-buffer, the
    geometry and the precomputed arrays: only hit faces' vertices, only those the camera sees above
    their horizon read c_k, T̃ and σ_k h_k."""
    m0, frame, gb = tiny
    m = _vertex(m0)
    m.render(frame, gb)
    P, hit = gb.num_samples, gb.hit
    Qh = int(hit.sum())
    geom = m.scene.geometry()
    V = torch.as_tensor(geom.V).float()
    Nrm = torch.nn.functional.normalize(torch.as_tensor(geom.N).float(), dim=-1)
    cam = torch.tensor(frame.camera.origin, dtype=torch.float32)
    faces = torch.unique(gb.face[hit])
    b = P * 12 + Qh * 17 + (P - Qh) * 1 + faces.numel() * 24
    f = Qh * 18
    light_b, light_f = 0, 0
    nref = culled = 0
    face_region = torch.as_tensor(geom.face_region).long()
    for r, name in enumerate(m.scene.regions):
        reg = next(x for x in m.regions if x.name == name)
        K, R = reg.K, m.config["lut_res"]
        verts = torch.unique(m.F[faces[face_region[faces] == r]])           # per region: its own copies
        nref += verts.numel()
        d = torch.nn.functional.normalize(cam - V[verts], dim=-1)
        wl = (frame_matrix(Nrm[verts]) @ d.unsqueeze(-1)).squeeze(-1)
        front = wl[:, 2] > 0
        cells, _ = tp.lut_cell(wl[front], R)
        nodes = torch.unique(torch.cat([cells, cells + 1, cells + R, cells + R + 1])).numel()
        nv = int(front.sum())
        assert nv > 0
        culled += verts.numel() - nv
        b += nv * K * 12 + nodes * K * 12
        f += nv * (4 + 24 * K + 24)
        nnz = _kept_nnz(reg, verts[front], K)
        light_b += nnz * (4 + reg.T.col_indices().element_size())
        light_f += 6 * nnz
    assert culled > 0                                                          # the sphere's silhouette rim
    b += nref * 24
    f += nref * 21
    rb, rf = _resample_cost(m)
    light_b, light_f = light_b + rb, light_f + rf
    assert m.frame_cost("V", P) == FrameCost(b, f)
    for kind in ("L", "E", "VL"):
        assert m.frame_cost(kind, P) == FrameCost(b + light_b, f + light_f)
    # no render of that size: the upper bound (every sample, face, vertex, node)
    Pn = 1000
    ub = m.frame_cost("V", Pn)
    nall = sum(int(reg.verts.numel()) for reg in m.regions)
    b = Pn * 12 + Pn * 17 + m.F.shape[0] * 24 + nall * 24
    f = Pn * 18 + nall * 21
    for reg in m.regions:
        R = m.config["lut_res"]
        b += reg.verts.numel() * reg.K * 12 + R * R * reg.K * 12
        f += reg.verts.numel() * (4 + 24 * reg.K + 24)
    assert ub == FrameCost(b, f)
    # and it reads less than the per-sample path on the same frame
    m0.render(frame, gb)
    assert m.frame_cost("V", P).bytes < m0.frame_cost("V", P).bytes


def _kept_nnz(reg, verts, K: int) -> int:
    """Kept transport coefficients of the region's vertices ``verts`` (their number varies per vertex
    under the "vertex" budget): the CSR rows of their K terms."""
    crow, loc = reg.T.crow_indices().long(), reg.local_of[verts]
    return int(sum(int(crow[(v + 1) * K] - crow[v * K]) for v in loc.tolist()))


def _resample_cost(m) -> tuple[int, int]:
    """Hand count of a lighting change's env → cube resampling (bytes, flops): the texels its
    6N²s² sub-samples touch (at most H·W) and the cube written; the flops as `InOut.frame_cost`
    documents them (per sub-sample, per texel and channel)."""
    N, s = m.config["cube_res"], m.config["light_supersample"]
    H, W = m.scene.envmap.data.shape[:2]
    return (min(H * W, 4 * 6 * N * N * s * s) * 12 + 6 * N * N * 12,
            6 * N * N * s * s * 2 * 24 + 6 * N * N * 3 * 4)


def test_outlier_rows_clamps_every_index_and_is_the_eager_sum():
    """`fast.outlier_rows` is compiled without index checks: its cells and vertices are clamped into
    range inside (a direction with an infinite component gives an arbitrary cell), so the compiled
    kernel equals the eager function on any integers, and `fast._outliers` (the count dynamic, fewer
    than two entries padded) equals the 4-node sum of each entry."""
    g = torch.Generator().manual_seed(5)
    R, K, Vr = 16, 6, 30
    sh_nc = torch.randn(R * R * 3, K, generator=g)
    c = torch.randn(Vr, 3, K, generator=g)
    fr = fast.FastRegion(col=torch.zeros(0, dtype=torch.int32), val=torch.zeros(0), crow=torch.zeros(1, dtype=torch.long),
                         sh_lut=sh_nc.view(R * R, 3, K).transpose(1, 2).reshape(R * R, 3 * K), sh_nc=sh_nc, K=K, R=R)
    n = 300
    v = torch.randint(-5, Vr + 5, (n,), generator=g)
    cell = torch.randint(-2**40, 2**40, (n,), generator=g)
    wc = torch.rand(n, 4, generator=g)
    assert torch.allclose(fast.outlier_rows(v, cell, wc, sh_nc, c, R), fast.outlier_rows.eager(v, cell, wc, sh_nc, c, R),
                          rtol=RTOL, atol=1e-5)
    for m in (0, 1, 2, 77):
        vv = torch.randint(0, Vr, (m,), generator=g)
        cc = torch.randint(0, R - 1, (m,), generator=g) * R + torch.randint(0, R - 1, (m,), generator=g)
        w = wc[:m]
        nodes = cc[:, None] + torch.tensor([0, 1, R, R + 1])
        want = (sh_nc.view(R * R, 3, K)[nodes] * w[..., None, None] * c[vv][:, None]).sum((1, 3))
        got = fast._outliers(fr, c, vv, cc, w)
        assert got.shape == (m, 3) and torch.allclose(got, want, rtol=RTOL, atol=1e-5)


def test_window_kernel_serves_every_window_set_without_recompiling(precomputed):
    """The windows change from frame to frame (`fast.prepare`: their number and sizes); the compiled
    `window_rows` takes its row counts as symbolic sizes, so a new set of windows does not re-trace it
    inside a timed frame — and each set still gives the eager result."""
    from methods.core.fused import compile_enabled

    if not compile_enabled():
        pytest.skip("compilation disabled (PRTBENCH_COMPILE=0)")
    from torch._dynamo.utils import counters

    m = precomputed("bunny")
    fast_m, _ = _pair(m)
    frame = make_sequence(m.scene, "V", n_frames=1, seed=0)[0]
    view = fast_m._view_setup(frame, make_gbuffer(m.scene, frame, 2))
    st = view.st
    fr = st.regions[0]
    nv = int(st.voff[1])
    g = torch.Generator().manual_seed(3)
    cw = torch.randn(nv, 3, fr.sh_nc.shape[1], generator=g)
    graphs = []
    for n, top in ((40, 4), (300, 9), (1, 16), (77, 16), (500, 2)):
        ref = torch.sort(torch.randperm(nv, generator=g)[:min(n, nv)]).values
        n = ref.numel()
        wu = torch.randint(2, top + 1, (n,), generator=g, dtype=torch.int32)
        wv = torch.randint(2, top + 1, (n,), generator=g, dtype=torch.int32)
        u0 = (torch.rand(n, generator=g) * (fr.R - wu + 1).float()).int()
        v0 = (torch.rand(n, generator=g) * (fr.R - wv + 1).float()).int()
        cnt = (wu * wv).long()
        off = torch.cumsum(cnt, 0) - cnt + 5                    # the slot's windows need not start at row 0
        wr = torch.stack([u0, v0, off.int(), wu, wv], 1)
        X = torch.full((int(cnt.sum()) + 5, 3), float("nan"))
        fast.view_windows(fr, ref, cw, wr, X)
        e = torch.arange(5, X.shape[0])
        p = torch.repeat_interleave(torch.arange(n), cnt)
        want = fast.window_rows.eager(e, p, wr, ref, fr.sh_nc, cw, fr.R)
        assert torch.allclose(X[5:], want, rtol=RTOL, atol=1e-6) and bool(X[:5].isnan().all())
        loc = e - off[p]                                        # the node of each row, by integer division
        node = (v0.long()[p] + loc // wu.long()[p]) * fr.R + u0.long()[p] + loc % wu.long()[p]
        direct = (fr.sh_nc.view(-1, 3, fr.sh_nc.shape[1])[node] * cw[ref[p]]).sum(-1)
        assert torch.allclose(want, direct, rtol=RTOL, atol=1e-6)
        graphs.append(counters["stats"]["unique_graphs"])
    assert graphs[-1] == graphs[0], graphs          # the later window sets reuse the first's kernel


def test_native_kernel_is_not_loaded_from_a_directory_others_can_write(tmp_path, monkeypatch):
    """The compiled CSR loop is loaded from a per-user directory in the temp folder: one another
    user could write (a planted library) is refused, with a warning, and the torch product is used."""
    import os
    import tempfile

    from methods.core import native
    from methods.inout import csr

    if native.compiler() is None:
        pytest.skip("no C compiler")
    monkeypatch.setattr(tempfile, "gettempdir", lambda: str(tmp_path))
    root = tmp_path / f"prtbench-native-{os.getuid()}"
    root.mkdir()
    root.chmod(0o777)
    native.cache_clear()
    try:
        with pytest.warns(UserWarning, match="not a directory only this user can write"):
            assert csr._kernel() is None
        root.chmod(0o700)
        native.cache_clear()
        assert csr._kernel() is not None
    finally:
        native.cache_clear()
