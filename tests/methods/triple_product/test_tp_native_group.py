"""The native grouping (`methods.triple_product.native_group`) against its oracle, the torch path of
`fast_eval.group_runs` (``native_ok=False``): the same groups (gv, gl, gb), order, inverse (inv_s)
and runs, every output's dtype and shape equal — integers, so bit for bit.

Inputs: G-buffer-like points (runs of neighbours sharing rows and cells), every point distinct (the
hash table grows several times), one and two visibility rows, more rows than the loop's memo of the
previous run (9), a single point, cells near the 32-bit code limit; and the cases the loop declines
(the torch path runs): a negative visibility row, codes past 32 bits."""
from __future__ import annotations

import pytest
import torch

from methods.triple_product import fast_eval, native_group

pytestmark = pytest.mark.skipif(not native_group.available(), reason="no C compiler (the torch path runs)")


def _points(B: int, kv: int, gen: torch.Generator, *, run: int = 7, nv: int = 40, nl: int = 20, nb: int = 8):
    """vrows (B, kv), lrows (B, 4), brows (B, 4) int64: runs of ``run`` points sharing their rows
    (neighbouring samples of a triangle), a cell's rows a function of its first (as a look-up's)."""
    m = B // run + 1
    tri = torch.randint(0, nv - kv, (m,), generator=gen).repeat_interleave(run)[:B]
    vrows = torch.stack([tri + i for i in range(kv)], 1)
    l0 = torch.randint(0, nl, (m,), generator=gen).repeat_interleave(run)[:B]
    b0 = torch.randint(0, nb, (m,), generator=gen).repeat_interleave(run)[:B]
    lrows = torch.stack([l0, l0 + 1, l0 + 3, l0 + 4], 1)
    brows = torch.stack([b0, b0 + 1, b0 + 2, b0 + 3], 1)
    return vrows, lrows, brows


def _same(vrows, lrows, brows, **kw):
    want = fast_eval.group_runs(vrows, lrows, brows, native_ok=False, **kw)
    got = native_group.group_runs(vrows, lrows, brows, kw.get("n_b", int(brows[:, 0].max()) + 1))
    assert got is not None
    for a, b in zip(got, want):
        assert a.dtype == b.dtype and a.shape == b.shape and torch.equal(a, b)
    # and through `fast_eval.group_runs` (the frames' call)
    for a, b in zip(fast_eval.group_runs(vrows, lrows, brows, **kw), want):
        assert a.dtype == b.dtype and torch.equal(a, b)
    return want


@pytest.mark.parametrize("kv", [1, 2, 3, 9])
def test_native_groups_equal_torch_path(kv):
    gen = torch.Generator().manual_seed(3 + kv)
    vrows, lrows, brows = _points(3000, kv, gen)
    gv, gl, gb, inv_s, run = _same(vrows, lrows, brows, n_l=24, n_b=12)
    assert gv.numel() < inv_s.numel() < 3000 * kv    # runs and shared groups exercised
    # a point differing from its neighbour in one visibility column only
    vrows[5, kv - 1] += 1
    _same(vrows, lrows, brows, n_l=24, n_b=12)
    _same(vrows, lrows, brows)                           # bounds from the maxima


def test_native_groups_every_point_distinct():
    """No two points share a group: G = B k_v, the hash table grown several times."""
    gen = torch.Generator().manual_seed(11)
    B = 20000
    vrows = torch.randperm(3 * B, generator=gen).view(B, 3)
    lrows = torch.randint(0, 100, (B, 1), generator=gen) + torch.tensor([0, 1, 3, 4])
    brows = torch.randint(0, 300, (B, 1), generator=gen) + torch.tensor([0, 1, 2, 3])
    gv, *_ = _same(vrows, lrows, brows, n_l=110, n_b=310)
    assert gv.numel() == 3 * B


def test_native_groups_edges():
    gen = torch.Generator().manual_seed(5)
    vrows, lrows, brows = _points(1, 3, gen)                     # one point
    _same(vrows, lrows, brows, n_l=24, n_b=12)
    # codes row·n_c + cell just below 2^32
    vrows, lrows, brows = _points(500, 3, gen, nv=60, nl=20, nb=8)
    n_b = 1 << 20                                                # cells up to 20·2^20: 59·(cells) < 2^32
    _same(vrows, lrows, brows, n_l=24, n_b=n_b)
    # declined (None; `fast_eval.group_runs` runs the torch path): codes past 32 bits, a negative row
    big = vrows + (1 << 12)
    assert native_group.group_runs(big, lrows, brows, 1 << 24) is None
    for a, b in zip(fast_eval.group_runs(big, lrows, brows, n_b=1 << 24),
                    fast_eval.group_runs(big, lrows, brows, n_b=1 << 24, native_ok=False)):
        assert torch.equal(a, b)
    neg = vrows.clone()
    neg[3, 1] = -1
    assert native_group.group_runs(neg, lrows, brows, 8) is None


@pytest.mark.parametrize("kv", [3, 4, 1])
def test_native_blend_equals_compiled_blend(kv):
    """`native_group.blend` = `fast_eval.group_blend_runs` (eager here: the oracle) to float32
    round-off, for groups of `group_runs`; runs longer than one point; ``scale`` multiplies."""
    gen = torch.Generator().manual_seed(20 + kv)
    B = 5000
    vrows, lrows, brows = _points(B, kv, gen)
    gv, gl, gb, inv_s, run = fast_eval.group_runs(vrows, lrows, brows)
    T = torch.randn(gv.shape[0], 48, generator=gen)
    vw, lw, bw = (torch.rand(B, k, generator=gen) for k in (kv, 4, 4))
    want = fast_eval.group_blend_runs(run, inv_s, vw, lw, bw, T)
    got = native_group.blend(run, inv_s, vw, lw, bw, T)
    assert got.shape == (B, 3) and got.dtype == torch.float32
    assert (got - want).abs().max() <= 2e-6 * want.abs().max()
    half = native_group.blend(run, inv_s, vw, lw, bw, T, 0.25)
    assert torch.equal(half, got * 0.25)
    # on two threads (OpenMP's team; the same per-point sums)
    old, least = torch.get_num_threads(), native_group.MIN_POINTS_PER_THREAD
    torch.set_num_threads(2)
    native_group.MIN_POINTS_PER_THREAD = 16
    try:
        assert torch.equal(native_group.blend(run, inv_s, vw, lw, bw, T), got)
    finally:
        torch.set_num_threads(old)
        native_group.MIN_POINTS_PER_THREAD = least
    # declined (the compiled blend runs): other row counts, dtypes
    assert native_group.blend(run, inv_s, vw, lw[:, :3], bw[:, :3], T[:, :27]) is None
    assert native_group.blend(run, inv_s, vw.double(), lw, bw, T) is None
    with pytest.raises(IndexError):
        native_group.blend(run, inv_s, vw, lw, bw, T[:-1])


@pytest.mark.parametrize("ss", [1, 2, 3, 4, 9])
def test_pixel_mean_equals_torch_mean(ss):
    """`native_group.pixel_mean` = torch's mean over each pixel's samples, bit for bit (9: torch's
    mean, past `MEAN_MAX_SAMPLES`)."""
    gen = torch.Generator().manual_seed(ss)
    H, W = 13, 17
    x = torch.rand(H * W * ss, 3, generator=gen) * torch.rand(H * W * ss, 1, generator=gen) * 50
    want = x.reshape(H, W, ss, 3).mean(2)
    got = native_group.pixel_mean(x, H, W, ss)
    assert got.shape == want.shape and torch.equal(got, want)


def test_vertex_weights_equal_the_gbuffers():
    """`native_group.vertex_weights` = `GBuffer.vertex_weights`, bit for bit: misses (face −1), both
    barycentric layouts (the G-buffer's planes and rows); a face past the mesh raises."""
    from scenes.frame import GBuffer

    gen = torch.Generator().manual_seed(2)
    H, W, ss = 9, 11, 2
    P = H * W * ss * ss
    F = torch.randint(0, 50, (30, 3), generator=gen)
    hit = torch.rand(P, generator=gen) < 0.7
    face = torch.where(hit, torch.randint(0, 30, (P,), generator=gen), torch.full((P,), -1))
    bary = torch.rand(P, 2, generator=gen) * 0.5
    z = torch.zeros(P, 3)
    for b in (bary.t().contiguous().t(), bary.contiguous()):
        g = GBuffer(H, W, ss, hit=hit, face=face, bary=b, position=z, normal=z, wo=z,
                    region=torch.where(hit, 0, -1), coverage=torch.ones(H, W))
        want = g.vertex_weights(F)
        got = native_group.vertex_weights(g, F)
        for x, y in zip(got, want):
            assert x.dtype == y.dtype and x.shape == y.shape and torch.equal(x, y)
    g.face[3] = 30
    with pytest.raises(IndexError):
        native_group.vertex_weights(g, F)


def test_normalize_equals_torch():
    """`native_group.normalize` = ``torch.nn.functional.normalize(x, dim=-1)``, bit for bit (torch at 1 and
    2 threads): unit-ish rows at scales 1, 1e-3, 1e3, tiny rows (the 1e-12 clamp), huge ones (the squares
    overflow), zero rows (a G-buffer miss), a NaN row, a real G-buffer's normals, rows of a wider array (row
    stride 4); a (3, P) planes layout takes torch's path."""
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    gen = torch.Generator().manual_seed(4)
    x = torch.randn(50000, 3, generator=gen)
    x = x / x.norm(dim=-1, keepdim=True) * (1 + 1e-3 * torch.randn(50000, 1, generator=gen))
    rows = [x, x * 1e-3, x * 1e3, x * 1e-13, x * 1e-30, x * 1e25, torch.randn(999, 3, generator=gen) * 7]
    edge = torch.zeros(5, 3)
    edge[1] = float("nan")
    edge[2, 0] = float("nan")
    edge[3] = torch.tensor([0.0, -0.0, 1e-45])
    edge[4] = torch.tensor([float("inf"), 1.0, 0.0])
    rows.append(edge)
    scene = get_scene("chess", "test")
    gb = make_gbuffer(scene, make_sequence(scene, "V", n_frames=1, seed=1)[0], 2)
    rows.append(gb.normal)
    wide = torch.randn(777, 4, generator=gen)
    rows.append(wide[:, :3])
    threads = torch.get_num_threads()
    try:
        for nt in (1, 2):
            torch.set_num_threads(nt)
            for r in rows:
                want = torch.nn.functional.normalize(r.float(), dim=-1)
                got = native_group.normalize(r)
                assert got.dtype == want.dtype and got.shape == want.shape
                assert torch.equal(got.nan_to_num(7.0), want.nan_to_num(7.0)) and torch.equal(got.isnan(), want.isnan())
                assert torch.equal(got.signbit(), want.signbit())
    finally:
        torch.set_num_threads(threads)
    planes = x.t().contiguous().t()
    assert torch.equal(native_group.normalize(planes), torch.nn.functional.normalize(planes, dim=-1))
