"""Session 46 (zh46): the paper configuration's fused pass with its chunks handed out dynamically
(`ZHShadow.balanced_fused`, `native_balanced`) and `_fused_planes`' calls bound once (`ZHShadow.bound_glue`:
`native.FusedBound`, `native.VTableBound`, `native_split.SplitBound`) against their oracles (the static split, the
unbound calls) — the same bits, at 1, 2 and 3 threads."""
from __future__ import annotations

import pytest
import torch

from methods.core.threads import torch_threads


def _bits(x: torch.Tensor) -> torch.Tensor:
    return x.contiguous().view(torch.int32)


def _skip_unless_balanced():
    from methods.zh_shadow import native as zn
    from methods.zh_shadow import native_balanced, native_fused16

    if native_balanced.lib() is None or native_fused16.lib(True, wide=True) is None \
            or not zn.fused_available(6, True, True) or zn._fma_fused_lib() is None:
        pytest.skip("the wide fused pass is not available here")


def _fused_args(seed: int, n: int = 3000, hit_rate: float = 1.0, clamp: bool = True):
    """A random plane frame's `fused_pixels` arguments (K = 80, a lut, the object samples bunched in one part of
    the image as an object on screen is)."""
    from methods.zh_shadow import native as zn

    g = torch.Generator().manual_seed(seed)
    D, S2, N, M = 6, 4, 60, 90
    K = zn._terms_k(D, True, True)
    P = n * S2
    F32 = torch.randint(0, N, (M, 3), generator=g, dtype=torch.int32)
    face = torch.randint(0, M, (P,), generator=g)
    bary = torch.rand(2, P, generator=g).mul_(0.5).T
    nrm = torch.nn.functional.normalize(torch.randn(P, 3, generator=g), dim=1)
    wo = torch.nn.functional.normalize(torch.randn(3, P, generator=g), dim=0).T
    mask = torch.ones(P, dtype=torch.bool)
    mask[P // 5: P // 5 + P // 4] = torch.rand(P // 4, generator=g) < 0.2   # (the object: one band)
    nrm[mask] = torch.tensor([0.0, 1.0, 0.0])
    hit = None if hit_rate >= 1.0 else torch.rand(P, generator=g) < hit_rate
    if hit is not None:   # (a miss: normal 0, as the G-buffer's)
        mask &= hit
        nrm[~hit] = 0.0
    region = torch.randint(0, 2, (P,), generator=g)
    u = torch.rand(N, 3, generator=g)
    U = torch.randn(40, 3, K, generator=g)
    lut = torch.randint(0, 40, (N,), generator=g, dtype=torch.int32)
    return (face, bary, nrm, wo, mask, hit, F32, u, U, lut, region, [False, True], D, True, True, clamp, S2)


@pytest.mark.parametrize("seed", (0, 1))
def test_balanced_fused_same_bits(monkeypatch, seed):
    """`native.fused_pixels`(…, wide, balanced=True) (chunks handed out dynamically) = (…, balanced=False) (the
    static split: the oracle) bit for bit, the same specular count, at 1, 2 and 3 threads, with and without misses
    and the clamp; a face out of range: None alike. A chunk skipped or computed twice into the wrong pixels, or a
    count lost in the reduction, breaks it."""
    from methods.zh_shadow import native as zn

    _skip_unless_balanced()
    monkeypatch.setattr(zn, "MIN_PIXELS_PER_THREAD", 1)
    for hit_rate, clamp in ((1.0, True), (0.97, False)):
        args = _fused_args(seed, hit_rate=hit_rate, clamp=clamp)
        with torch_threads(1):
            ref, nref = zn.fused_pixels(*args, fma=True, vector=True, wide=True, balanced=False)
        assert nref > 0
        for t in (1, 2, 3):
            with torch_threads(t):
                a, na = zn.fused_pixels(*args, fma=True, vector=True, wide=True, balanced=True)
            assert na == nref and torch.equal(_bits(a), _bits(ref)), (hit_rate, t)
    bad = list(_fused_args(seed))
    bad[0] = bad[0].clone()
    bad[0][int((~bad[4]).nonzero()[-1])] = 10 ** 6   # (an object sample's face)
    with torch_threads(2):
        assert zn.fused_pixels(*bad, fma=True, vector=True, wide=True, balanced=True) is None
        assert zn.fused_pixels(*bad, fma=True, vector=True, wide=True, balanced=False) is None


def test_fused_bound_equals_fused_pixels(monkeypatch):
    """`native.fused_bind`'s call = `native.fused_pixels` with the same flags bit for bit (its kept stat array reset
    each call: a good call after one that failed returns the image), at 1 and 2 threads; None where the unbound call
    gives None."""
    from methods.zh_shadow import native as zn

    _skip_unless_balanced()
    monkeypatch.setattr(zn, "MIN_PIXELS_PER_THREAD", 1)
    for balanced in (False, True):
        b = zn.fused_bind([False, True], 6, True, True, True, 4, fma=True, vector=True, wide=True, balanced=balanced)
        assert b is not None
        for seed in (3, 4):
            args = _fused_args(seed)
            bad = list(args)
            bad[0] = bad[0].clone()
            bad[0][int((~bad[4]).nonzero()[0])] = -2   # (an object sample's face)
            for t in (1, 2):
                with torch_threads(t):
                    ref, nref = zn.fused_pixels(*args, fma=True, vector=True, wide=True, balanced=balanced)
                    assert b(*bad[:11]) is None
                    a, na = b(*args[:11])
                assert na == nref and torch.equal(_bits(a), _bits(ref)), (balanced, seed, t)
                assert b(args[0], args[1], args[2], args[3], args[4], args[5], args[6], args[7],
                         args[8][:, :, :-1], args[9], args[10]) is None   # (another K)


def test_vtable_bound_equals_vertex_table(monkeypatch):
    """`native.vtable_bind`'s call = `native.vertex_table` (every row, referenced rows into ``out``) bit for bit at
    1 and 2 threads, its kept failure flag reset each call (a good call after an id out of range)."""
    from methods.zh_shadow import native as zn

    monkeypatch.setattr(zn, "MIN_ROWS_PER_VTABLE_THREAD", 1)
    g = torch.Generator().manual_seed(5)
    N, n2, C = 300, 16, 240
    v = torch.randn(N, n2, generator=g)
    vreg = torch.randint(0, 2, (N,), generator=g)
    W = torch.randn(2, n2, C, generator=g)
    idx = torch.randint(0, N, (123,), generator=g)
    bad = idx.clone()
    bad[-1] = N
    for wide in (False, True):
        b = zn.vtable_bind(wide)
        if b is None:
            pytest.skip("no vertex-table library here")
        for t in (1, 2):
            with torch_threads(t):
                ref_all = zn.vertex_table(v, vreg, W, wide=wide)
                ref_idx = zn.vertex_table(v, vreg, W, idx, wide=wide)
                assert b(v, vreg, W, bad) is None
                a_all = b(v, vreg, W)
                out = torch.full((idx.shape[0], C), float("nan"))
                a_idx = b(v, vreg, W, idx, out=out)
            assert a_idx is out
            assert torch.equal(_bits(a_all), _bits(ref_all)) and torch.equal(_bits(a_idx), _bits(ref_idx)), (wide, t)


def test_split_bound_equals_split(monkeypatch):
    """`native_split.split_bind`'s call = `native_split.split` (status, candidate, mask, counts, rest screen, lut and
    vertices) on consecutive G-buffers (its kept status array read before each call returns), at 1 and 2 threads."""
    from methods.zh_shadow import native_split as z44

    monkeypatch.setattr(z44, "MIN_SAMPLES_PER_THREAD", 64)
    spec = torch.tensor([False, True])
    b = z44.split_bind(spec)
    if b is None:
        pytest.skip("no split library here")
    for seed in (6, 7, 8):
        face, bary, nrm, wo, mask, hit, F32, *_ = _fused_args(seed, n=2000, hit_rate=1.0 if seed != 7 else 0.99)
        region = torch.zeros(face.shape[0], dtype=torch.int64)
        for t in (1, 2):
            with torch_threads(t):
                ref = z44.split(nrm, region, spec, hit, 512, 512, True, face, F32, 60)
                got = b(nrm, region, hit, 512, 512, True, face, F32, 60)
            assert ref is not None and got is not None and ref[0] == got[0] == 0
            for x, y in zip(ref, got):
                if isinstance(x, torch.Tensor):
                    assert torch.equal(x, y)
                elif isinstance(x, tuple):
                    assert all(torch.equal(p, q) for p, q in zip(x, y))
                else:
                    assert x == y


@pytest.mark.parametrize("kind", ("P", "VB", "VBL", "VL", "V"))
def test_zh46_frames_equal_oracle(creature, monkeypatch, kind):
    """Whole frames with `balanced_fused` and `bound_glue` on render the same image bits, path and counts as with
    both off (the oracle) at 1 and 2 threads (the thread thresholds lowered so that the test-size frames run on 2),
    the bound fused call running in them."""
    from methods.zh_shadow import native as zn
    from methods.zh_shadow import native_split as z44
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _skip_unless_balanced()
    for mod, name in ((zn, "MIN_PIXELS_PER_THREAD"), (zn, "MIN_ROWS_PER_VTABLE_THREAD"),
                      (z44, "MIN_SAMPLES_PER_THREAD")):
        monkeypatch.setattr(mod, name, 16)
    ran = []
    call = zn.FusedBound.__call__
    monkeypatch.setattr(zn.FusedBound, "__call__", lambda self, *a: ran.append(1) or call(self, *a))
    for threads in (1, 2):
        with torch_threads(threads):
            new, old = creature.with_render_config(), creature.with_render_config()
            old.balanced_fused = old.bound_glue = False
            n_ran = len(ran)
            for fr in make_sequence(creature.scene, kind, 4, seed=46):
                gb = make_gbuffer(creature.scene, fr, 2)
                a, b = new.render(fr, gb), old.render(fr, gb)
                assert new.last_path == old.last_path and new.last_fused == old.last_fused, (kind, fr.index)
                assert torch.equal(_bits(a), _bits(b)), (kind, threads, fr.index)
                ca, cb = dict(new._last_counts), dict(old._last_counts)
                pa, pb = ca.pop("plane_vertices", None), cb.pop("plane_vertices", None)
                assert ca == cb and (pa() if callable(pa) else pa) == (pb() if callable(pb) else pb)
                if new._plane_u is not None or old._plane_u is not None:   # (the kept plane term: the same bits)
                    assert torch.equal(_bits(new._plane_u[3]), _bits(old._plane_u[3])), (kind, threads, fr.index)
            assert len(ran) > n_ran, (kind, threads)


def test_all_hit_equals_all():
    """`native_hits.all_hit` = ``bool(mask.all())`` on masks with no zero, one zero at any position of a 64-byte block
    or in the tail, several zeros, and the empty mask; None for another dtype or a strided mask."""
    from methods.zh_shadow import native_hits

    if native_hits._lib() is None:
        pytest.skip("no C compiler or the native passes switched off")
    for n in (0, 1, 63, 64, 65, 1000, 262144):
        m = torch.ones(n, dtype=torch.bool)
        assert native_hits.all_hit(m) is True
        for p in sorted({0, n // 2, n - 1, 63, 64} & set(range(n))):
            z = m.clone()
            z[p] = False
            assert native_hits.all_hit(z) is False, (n, p)
    g = torch.Generator().manual_seed(9)
    for _ in range(20):
        m = torch.rand(5000, generator=g) > 0.0005
        assert native_hits.all_hit(m) == bool(m.all())
    assert native_hits.all_hit(torch.ones(10, dtype=torch.uint8)) is None
    assert native_hits.all_hit(torch.ones(20, dtype=torch.bool)[::2]) is None


def test_rows_into_equals_call(creature, monkeypatch):
    """`native.PoseSHBound.rows_into` = its ``__call__`` with ``rows`` and ``out``: the rows asked for the same bits,
    the others untouched, at 1 and 2 threads; None where the call gives None (an id out of range, another layout)."""
    from methods.zh_shadow import native as zn

    monkeypatch.setattr(zn, "MIN_COLS_PER_POSE_SH_THREAD", 8)
    m = creature.with_render_config()
    from scenes.sequences import make_sequence
    from references.gbuffer import make_gbuffer

    fr = make_sequence(m.scene, "P", 2, seed=46)[1]
    m.render(fr, make_gbuffer(m.scene, fr, 2))
    pb = m._pose_bound
    if pb is None or not pb.vmaj:
        pytest.skip("no vertex-major bound call here")
    pose = torch.as_tensor(fr.pose).float()
    geom = m._posed[1]
    g = torch.Generator().manual_seed(4)
    rows = torch.randint(0, pb.N, (pb.N // 3,), generator=g)
    for t in (1, 2):
        with torch_threads(t):
            a = torch.full((pb.N, pb.n * pb.n), 7.0)
            b = a.clone()
            assert pb.rows_into(pose, geom.N, rows, a) is a
            assert pb(pose, geom.N, rows, out=b) is b
        assert torch.equal(_bits(a), _bits(b)) and bool((a[:5][~torch.isin(torch.arange(5), rows)] == 7.0).all())
    bad = rows.clone()
    bad[-1] = pb.N
    assert pb.rows_into(pose, geom.N, bad, torch.empty(pb.N, pb.n * pb.n)) is None
    assert pb.rows_into(pose, geom.N, rows, torch.empty(pb.n * pb.n, pb.N)) is None
