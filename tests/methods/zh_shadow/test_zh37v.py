"""Session 37 (zh37v): the paper config's fused plane pass with the object samples' dot regrouped into fused
multiply-adds (`ZHShadow.fma_terms`, `native.fused_pixels`' ``fma``: `zh37v_fused`) against the same pass
with `sample_terms`' bits (`zh33p_fused`, ``fma_terms`` off: itself bit for bit the separate passes)."""
from __future__ import annotations

from unittest import mock

import pytest
import torch

from testing.gbuffers import knock_out

# float32 round-off of an image (peaks at ~2) whose object samples' 80-term sums run in another order with
# products fused into multiply-adds: as the other fast paths' image tolerance against their oracle
IMAGE_TOL = 1e-5


@pytest.mark.parametrize("kind", ("V", "VB", "VL", "P"))
def test_fma_terms_equal_exact_fused_pass(creature, monkeypatch, kind):
    """`_fused_planes` with ``fma_terms`` (the regrouped dot) = the same pass without it (``fma_terms`` off:
    `sample_terms`' bits) to float32 round-off, with the same path and counts — with the kept table and a
    frame's own table of the referenced vertices, clamp on and off, with misses — and the same bits at 1 and
    2 threads; the two differ somewhere (the regrouped pass ran). A dropped or swapped corner, a wrong
    channel's row or a lost front test / clamp breaks the image."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if not zn.fused_available(6, True, True) or zn._fma_fused_lib() is None:
        pytest.skip("the fused pass is not available here")
    monkeypatch.setattr(zn, "MIN_PIXELS_PER_THREAD", 1)   # (test size: 4,096 pixels, one thread otherwise)
    differ = False
    for table_points in (0.0, 1e9):
        monkeypatch.setattr("methods.zh_shadow.method.VERTEX_TABLE_POINTS", table_points)
        for clamp, misses in ((True, False), (False, False), (True, True)):
            fast, fast2, exact = (creature.with_render_config(clamp=clamp) for _ in range(3))
            exact.fma_terms = False
            for fr in make_sequence(creature.scene, kind, 3, seed=11):
                gb = make_gbuffer(creature.scene, fr, 2)
                if misses:
                    gb = knock_out(gb, 397 + fr.index, 3 + fr.index)
                    assert 0 < int((~gb.hit).sum()) <= 64
                with torch_threads(1):
                    a = fast.render(fr, gb)
                    b = exact.render(fr, gb)
                with torch_threads(2):
                    a2 = fast2.render(fr, gb)
                assert fast.last_path == exact.last_path == "planes" and fast.last_fused == exact.last_fused
                assert torch.equal(a, a2), (kind, clamp, misses, fr.index)
                err = (a - b).abs().max().item()
                assert err <= IMAGE_TOL * b.abs().max().item(), (kind, clamp, misses, fr.index, err)
                differ |= fast.last_fused and not torch.equal(a, b)
                ca, cb = dict(fast._last_counts), dict(exact._last_counts)
                assert ca.pop("plane_vertices")() == cb.pop("plane_vertices")() and ca == cb
    assert differ, "the regrouped pass never ran"


def test_fma_fused_pixels_equal_exact_random():
    """`native.fused_pixels`(…, fma=True) = (…, fma=False) to float32 round-off on random inputs with large,
    cancelling table rows (each term a sum of ±1e2-sized products), object samples in every position of a
    pixel, a plane mask, clamp on and off, with a lut: the plane samples bit for bit, the object samples'
    terms to round-off of the sum of their magnitudes; the same number of specular samples."""
    from methods.zh_shadow import native as zn

    if not zn.fused_available(6, True, True) or zn._fma_fused_lib() is None:
        pytest.skip("the fused pass is not available here")
    g = torch.Generator().manual_seed(37)
    n, S2, N, M, K = 700, 4, 50, 80, 80
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
    for clamp in (False, True):
        for lt, UU in ((None, U[:1].expand(N, 3, K).contiguous() + torch.randn(N, 3, K, generator=g)), (lut, U)):
            args = (face, bary, nrm, wo, mask, None, F32, u, UU, lt, region, [False, True], 6, True, True, clamp, S2)
            a, na = zn.fused_pixels(*args, fma=True)
            b, nb = zn.fused_pixels(*args, fma=False)
            assert na == nb
            px = mask.view(n, S2).all(1)   # pixels of plane samples alone: the same bits
            assert torch.equal(a[px], b[px])
            # each object term's round-off bound: its 3·80 products' magnitudes (image = mean of 4 samples)
            bound = 1e-6 * U.abs().max().item() * 3 * K
            assert (a - b).abs().max().item() <= bound, (clamp, lt is None)
            assert not torch.equal(a, b)


def test_vector_plane_mask_equals_loop(monkeypatch):
    """`native.plane_mask` by `zh37v_plane_mask` (``VECTOR_PLANE_MASK``) = by `zh_plane_split`'s loop (off):
    the same mask, counts and per-thread counts, or None alike — random normals with a plane's share, regions
    in and outside [0, R) (negative too), specular flags on some regions, with and without ``hit`` (misses
    that match the plane among them), 1 to 3 threads, P not a multiple of the thread count."""
    from methods.zh_shadow import native as zn

    if zn._pmask_lib() is None or not zn.split_available():
        pytest.skip("the native plane mask is not available here")
    g = torch.Generator().manual_seed(371)
    P = 10007
    n0 = torch.tensor([0.0, 1.0, 0.0])
    for trial in range(12):
        nrm = torch.nn.functional.normalize(torch.randn(P, 3, generator=g), dim=1)
        on = torch.rand(P, generator=g) < 0.7
        nrm[on] = n0
        nrm[torch.rand(P, generator=g) < 0.05, 1] = 1.0             # (two of three components match)
        R = (1, 2, 3, 5, 64, 7)[trial % 6]
        region = torch.randint(0, R, (P,), generator=g)
        if trial % 3 == 1:
            region[int(torch.randint(0, P, (1,), generator=g))] = (R, -1)[trial % 2]   # outside [0, R)
        spec = torch.rand(R, generator=g) < 0.5
        hit = None
        if trial % 4 >= 2:
            hit = torch.rand(P, generator=g) > 0.01
            if trial % 4 == 3:
                hit |= on    # (no miss on the plane; the misses' normals as a miss's: 0)
                nrm[~hit] = 0.0
        for nt in (1, 2, 3):
            with mock.patch.object(torch, "get_num_threads", lambda: nt):
                monkeypatch.setattr(zn, "VECTOR_PLANE_MASK", True)
                a = zn.plane_mask(nrm, n0, region, spec, hit)
                monkeypatch.setattr(zn, "VECTOR_PLANE_MASK", False)
                b = zn.plane_mask(nrm, n0, region, spec, hit)
            assert (a is None) == (b is None), (trial, nt)
            if a is not None:
                assert torch.equal(a[0], b[0]) and a[1:] == b[1:], (trial, nt, a[1:], b[1:])
                assert a[1] > 0 and (not spec.any() or a[2] > 0 or trial % 6 == 0)
