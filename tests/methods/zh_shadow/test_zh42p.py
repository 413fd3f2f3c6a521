"""Session 42 (zh42p): the paper config's fused plane pass with the object samples' regrouped dot in 16-float
vectors (`ZHShadow.wide_dot`, `native.fused_pixels`' ``wide``: `native_fused16`'s `zh42p_fused_wide`) against
the same pass with the 8-float dot (`zh40p_fused_fma`, ``wide_dot`` off: the oracle) — float32 round-off of the
object samples' terms, the plane samples bit for bit."""
from __future__ import annotations

import pytest
import torch

from testing.gbuffers import knock_out

# float32 round-off of an image (peaks at ~2) whose object samples' 80-term sums run in another order: as
# `test_zh37v`'s tolerance of the regrouped dot against `sample_terms`' bits
IMAGE_TOL = 1e-5


def _skip_unless_wide():
    from methods.zh_shadow import native as zn
    from methods.zh_shadow import native_fused16

    if native_fused16.lib(True, wide=True) is None or native_fused16.lib(True) is None \
            or not zn.fused_available(6, True, True) or zn._fma_fused_lib() is None:
        pytest.skip("the wide fused pass is not available here")


@pytest.mark.parametrize("variant", ((6, True, True), (8, True, False)))
def test_wide_dot_equals_8_float_random(monkeypatch, variant):
    """`native.fused_pixels`(…, fma, vector, wide=True) = (…, wide=False) to float32 round-off on random inputs
    with large, cancelling table rows (each term a sum of ±1e2-sized products), object samples in every position
    of a pixel, a plane mask, clamp on and off, with and without a lut and misses: the plane samples' pixels bit
    for bit, the object samples' terms to round-off of the sum of their magnitudes, the same specular count, the
    same bits at 1 and 2 threads; the two differ somewhere (the wide dot ran); a face out of range: None alike.
    Both `TERMS_VARIANTS` (K = 80 and 48). A dropped corner, a wrong channel's or column block's row, a lost
    barycentric or a lane left out of the sum breaks it."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn

    _skip_unless_wide()
    monkeypatch.setattr(zn, "MIN_PIXELS_PER_THREAD", 1)
    D, dif, spec = variant
    K = zn._terms_k(D, dif, spec)
    g = torch.Generator().manual_seed(42)
    n, S2, N, M = 700, 4, 50, 80
    P = n * S2
    F32 = torch.randint(0, N, (M, 3), generator=g, dtype=torch.int32)
    face = torch.randint(0, M, (P,), generator=g)
    bary = torch.rand(2, P, generator=g).mul_(0.5).T               # column-major, as the G-buffer's
    nrm = torch.nn.functional.normalize(torch.randn(P, 3, generator=g), dim=1)
    wo = torch.nn.functional.normalize(torch.randn(3, P, generator=g), dim=0).T
    mask = torch.rand(P, generator=g) < 0.6
    nrm[mask] = torch.tensor([0.0, 1.0, 0.0])
    region = torch.randint(0, 2, (P,), generator=g)
    u = torch.rand(N, 3, generator=g)
    U = torch.randn(30, 3, K, generator=g) * 1e2
    lut = torch.randint(0, 30, (N,), generator=g, dtype=torch.int32)
    ran = 0
    for clamp in (False, True):
        for lt, UU in ((None, U[:1].expand(N, 3, K).contiguous() + torch.randn(N, 3, K, generator=g)), (lut, U)):
            for hit in (None, torch.rand(P, generator=g) > 0.05):
                m = mask if hit is None else mask & hit
                args = (face, bary, nrm, wo, m, hit, F32, u, UU, lt, region, [False, True], D, dif, spec, clamp, S2)
                with torch_threads(1):
                    a, na = zn.fused_pixels(*args, fma=True, vector=True, wide=True)
                    b, nb = zn.fused_pixels(*args, fma=True, vector=True, wide=False)
                with torch_threads(2):
                    a2, na2 = zn.fused_pixels(*args, fma=True, vector=True, wide=True)
                assert na == nb == na2
                assert torch.equal(a, a2), (clamp, lt is None, hit is None)
                px = m.view(n, S2).all(1)   # pixels of plane samples alone: the same bits
                assert bool(px.any()) and torch.equal(a[px], b[px])
                # each object term's round-off bound: its 3·K products' magnitudes (image = mean of 4 samples)
                bound = 1e-6 * UU.abs().max().item() * 3 * K
                assert (a - b).abs().max().item() <= bound, (clamp, lt is None, hit is None)
                assert not torch.equal(a, b)
                ran += 1
    bad = face.clone()
    bad[int((~mask).nonzero()[3])] = 10 ** 6   # an object sample's face out of range
    args = (bad, bary, nrm, wo, mask, None, F32, u, U, lut, region, [False, True], D, dif, spec, True, S2)
    assert zn.fused_pixels(*args, fma=True, vector=True, wide=True) is None
    assert zn.fused_pixels(*args, fma=True, vector=True, wide=False) is None
    assert ran == 8


def test_wide_dot_terms_equal_float64():
    """The wide pass's object terms against a float64 evaluation of the same dot, to float32 round-off: every
    sample an object sample, clamp off, an image pixel = the mean over its samples of (Σ_i b_i U_i[c]) · f ·
    front. The features f (× front) are read back from the 8-float pass itself: with U = e_k on channel 0 of
    every vertex and one sample a pixel off the plane mask (the others plane samples of u = 0), a pixel is
    (b0 + b1 + b2) f_k front / S² of that sample. The 8-float and the wide pass could share an error; this test
    does not: a wrong channel or corner weight, a lost column block or lane breaks it."""
    from methods.zh_shadow import native as zn

    _skip_unless_wide()
    g = torch.Generator().manual_seed(7)
    D, K, S2, N = 6, 80, 4, 12
    n = 40
    P = n * S2
    F32 = torch.randint(0, N, (20, 3), generator=g, dtype=torch.int32)
    face = torch.randint(0, 20, (P,), generator=g)
    bary = torch.rand(2, P, generator=g).mul_(0.5).T
    nrm = torch.nn.functional.normalize(torch.randn(P, 3, generator=g), dim=1)
    wo = torch.nn.functional.normalize(torch.randn(3, P, generator=g), dim=0).T
    mask = torch.zeros(P, dtype=torch.bool)
    region = torch.ones(P, dtype=torch.int64)
    u = torch.zeros(N, 3)

    def run(U, wide):
        return zn.fused_pixels(face, bary, nrm, wo, mask, None, F32, u, U, None, region, [False, True], D, True, True,
                               False, S2, fma=True, vector=True, wide=wide)[0]

    Ur = torch.randn(N, 3, K, generator=g, dtype=torch.float64)
    a = run(Ur.float(), True).double()
    feats = torch.empty(P, K, dtype=torch.float64)
    for s in range(S2):
        only = torch.ones(P, dtype=torch.bool)
        only[s::S2] = False
        for k in range(K):
            E = torch.zeros(N, 3, K)
            E[:, 0, k] = 1.0
            v = zn.fused_pixels(face, bary, nrm, wo, only, None, F32, u, E, None, region, [False, True], D, True,
                                True, False, S2, fma=True, vector=True, wide=False)[0]
            feats[s::S2, k] = v[:, 0].double() * S2
    bu, bv = bary[:, 0].double(), bary[:, 1].double()
    b = torch.stack([(1.0 - bu) - bv, bu, bv], 1)                                   # (P, 3)
    vi = F32.long()[face]                                                         # (P, 3)
    rows = (b[:, :, None, None] * Ur.float().double()[vi]).sum(1)                                  # (P, 3, K)
    ref = (rows * feats[:, None, :]).sum(2).view(n, S2, 3).mean(1)                # (n, 3)
    scale = (Ur.abs().max() * feats.abs().max() * K).item()
    assert (a - ref).abs().max().item() <= 1e-6 * scale


@pytest.mark.parametrize("kind", ("P", "V", "VB", "VL"))
def test_wide_dot_frames_equal_8_float(creature, monkeypatch, kind):
    """`_fused_planes` with `wide_dot` = without it (the 8-float dot) to float32 round-off, with the same path and
    counts — the kept table and a frame's own, clamp on and off, with misses — and the same bits at 1 and 2
    threads; the two differ somewhere (the wide pass ran)."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _skip_unless_wide()
    monkeypatch.setattr(zn, "MIN_PIXELS_PER_THREAD", 1)
    differ = False
    for table_points in (0.0, 1e9):
        monkeypatch.setattr("methods.zh_shadow.method.VERTEX_TABLE_POINTS", table_points)
        for clamp, misses in ((True, False), (False, False), (True, True)):
            wide, wide2, base = (creature.with_render_config(clamp=clamp) for _ in range(3))
            base.wide_dot = False
            for fr in make_sequence(creature.scene, kind, 3, seed=14):
                gb = make_gbuffer(creature.scene, fr, 2)
                if misses:
                    gb = knock_out(gb, 397 + fr.index, 3 + fr.index)
                with torch_threads(1):
                    a = wide.render(fr, gb)
                    b = base.render(fr, gb)
                with torch_threads(2):
                    a2 = wide2.render(fr, gb)
                assert wide.last_path == base.last_path and wide.last_fused == base.last_fused
                assert torch.equal(a, a2), (kind, clamp, misses, fr.index)
                err = (a - b).abs().max().item()
                assert err <= IMAGE_TOL * b.abs().max().item(), (kind, clamp, misses, fr.index, err)
                differ |= bool(wide.last_fused) and not torch.equal(a, b)
                ca, cb = dict(wide._last_counts), dict(base._last_counts)
                assert ca.pop("plane_vertices")() == cb.pop("plane_vertices")() and ca == cb
    assert differ, "the wide pass never ran"


@pytest.mark.parametrize("n,lobes", ((4, 2), (8, 2), (3, 2), (4, 1)))
def test_pose_row12_equals_loop(n, lobes):
    """`native.pose_sh`'s library with the 12-sum vector pose row (zh42p: d = lobes (2 + n) = 12, the paper
    config) = the same source built without it (`_pose_sh_lib(row12=False)`: the generic loop, the oracle), bit
    for bit — through `PoseSHBound` on every vertex and on rows (unsorted, a tail of fewer than 16), vertex- and
    row-major, world and ZYZ frames, 1 and 2 threads, poses one after another; d = 20, 10 and 6 (the loop and the
    order-8 vector row in both libraries) alike. A wrong joint's row, a lost joint, the 4-lane part read or
    written at the wrong offset breaks it."""
    from methods.core.threads import torch_threads

    if not zn_pose_sh_available():
        pytest.skip("no C compiler or the native passes switched off")
    from methods.zh_shadow import native as zn
    from methods.zh_shadow import runtime as rt
    from methods.zh_shadow.precompute import CHART_RMAX

    loop = zn._pose_sh_lib(row12=False)
    assert loop is not None and loop is not zn._pose_sh_lib()
    J1, N = 11, 203
    g = torch.Generator().manual_seed(4242 + 10 * n + lobes)
    Xv = zn.vertex_major(torch.randn(J1, N, lobes * (2 + n), generator=g) * 0.6)
    nrm = torch.nn.functional.normalize(torch.randn(N, 3, generator=g), dim=1).contiguous()
    lam = rt._band_norms(n)
    ran = 0
    for zyz, dim in ((False, 1), (True, 0), (True, 1)):
        perm = tuple(int(i) for i in rt.zyz_rows(n).tolist()) if zyz else tuple(range(n * n))
        new = zn.pose_sh_bind(Xv, lam, perm, lobes, n, CHART_RMAX, zyz, dim)
        old = zn.pose_sh_bind(Xv, lam, perm, lobes, n, CHART_RMAX, zyz, dim)
        assert new is not None and old is not None
        old.fn = loop.zh41p_pose_sh
        for k in range(2):
            pose = torch.randn(J1 - 1, generator=g)
            for threads in (1, 2):
                with torch_threads(threads):
                    a, b = new(pose, nrm), old(pose, nrm)
                assert a is not None and torch.equal(a.view(torch.int32), b.view(torch.int32)), (zyz, dim, k, threads)
                ran += 1
                if dim == 1:
                    rows = torch.randperm(N, generator=g)[:77]
                    oa, ob = torch.full((N, n * n), float("nan")), torch.full((N, n * n), float("nan"))
                    with torch_threads(threads):
                        new(pose, nrm, rows, out=oa)
                        old(pose, nrm, rows, out=ob)
                    assert torch.equal(oa.view(torch.int32), ob.view(torch.int32)), (zyz, k, threads)
    assert ran == 12


def zn_pose_sh_available() -> bool:
    from methods.zh_shadow import native as zn

    return zn.pose_sh_available() and zn._pose_sh_lib(row12=False) is not None


def test_face_groups_plane_equals_scalar_random(monkeypatch):
    """The wide library's plane samples grouped by face (`native_fused16._FACE_GROUPS`, zh42p) = the scalar plane
    lines (``vector`` False: the oracle) bit for bit (NaN and zeros' signs too): `test_zh40p`'s random G-buffers
    (pixels of one face, of mixed faces, samples facing away, a NaN vertex), every non-plane sample a miss (no
    object samples: the plane part alone) and with object samples (their pixels then within round-off, the
    others bit for bit), clamp on and off, a tail in the last chunk, 1 and 2 threads; a plane sample's face or a
    corner out of range: None alike. A lane of another face taken in, a corner or channel swapped, a lost clamp or
    front test breaks it."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn

    from tests.methods.zh_shadow.test_zh40p import _bits, _inputs

    _skip_unless_wide()
    monkeypatch.setattr(zn, "MIN_PIXELS_PER_THREAD", 1)
    g = torch.Generator().manual_seed(4242)
    ran = 0
    for n in (701, 64 * 9, 3):
        face, bary, nrm, wo, mask, F32, u, U, region = _inputs(g, n)
        P = 4 * n
        for hit in (mask.clone(), mask | (torch.rand(P, generator=g) < 0.5)):
            for clamp in (False, True):
                args = (face, bary, nrm, wo, mask, hit, F32, u, U, None, region, [False, True], 6, True, True,
                        clamp, 4)
                for threads in (1, 2):
                    with torch_threads(threads):
                        a = zn.fused_pixels(*args, fma=True, vector=False)
                        b = zn.fused_pixels(*args, fma=True, vector=True, wide=True)
                    assert a is not None and b is not None and a[1] == b[1]
                    px = (mask | ~hit).view(n, 4).all(1)   # pixels without object samples: the same bits
                    assert bool(px.any())
                    assert torch.equal(_bits(a[0][px]), _bits(b[0][px])), (n, clamp, threads)
                    ran += 1
        front = (mask & ((nrm * wo).sum(1) > 0)).nonzero().squeeze(1)   # (plane samples facing the camera)
        for q in (int(front[len(front) // 2]), int(front[-1])):
            bad = face.clone()
            bad[q] = 10 ** 6
            args = (bad, bary, nrm, wo, mask, None, F32, u, U, None, region, [False, True], 6, True, True, True, 4)
            assert zn.fused_pixels(*args, fma=True, vector=False) is None
            assert zn.fused_pixels(*args, fma=True, vector=True, wide=True) is None
        F_bad = F32.clone()
        F_bad[:, 1] = 10 ** 6
        for h in (None, mask):   # (hit = the mask: no object samples, the plane lines' own check)
            args = (face, bary, nrm, wo, mask, h, F_bad, u, U, None, region, [False, True], 6, True, True, True, 4)
            assert zn.fused_pixels(*args, fma=True, vector=False) is None
            assert zn.fused_pixels(*args, fma=True, vector=True, wide=True) is None
    assert ran == 24
