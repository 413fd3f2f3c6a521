"""Session 40 (zh40p): the paper config's fused plane pass with its plane samples 16 at a time (`native_fused16`,
`ZHShadow.vector_plane`) against the scalar plane lines (`native.fused_pixels` with ``vector`` False: the
oracle) — bit for bit."""
from __future__ import annotations

import pytest
import torch

from testing.gbuffers import knock_out


def _bits(x: torch.Tensor) -> torch.Tensor:
    return x.contiguous().view(torch.int32)   # (NaN payloads and signed zeros compared too)


def _inputs(g: torch.Generator, n: int, N: int = 60, M: int = 90):
    """A random G-buffer of n pixels × 4 samples: runs of pixels whose four samples share one face (the vector
    pass's broadcast pixels) and pixels of mixed faces, plane samples facing either way, object samples in
    every position, u with negative values (the clamp matters) and a NaN vertex."""
    P = 4 * n
    F32 = torch.randint(0, N, (M, 3), generator=g, dtype=torch.int32)
    face = torch.randint(0, M, (n,), generator=g).repeat_interleave(4)
    mixed = torch.rand(P, generator=g) < 0.1
    face[mixed] = torch.randint(0, M, (int(mixed.sum()),), generator=g)
    bary = torch.rand(2, P, generator=g).mul_(0.5).T                 # column-major, as the G-buffer's
    nrm = torch.nn.functional.normalize(torch.randn(P, 3, generator=g), dim=1)
    wo = torch.nn.functional.normalize(torch.randn(3, P, generator=g), dim=0).T
    wo[torch.rand(P, generator=g) < 0.5, 1] *= -1.0
    mask = torch.rand(P, generator=g) < 0.75
    mask[: 4 * (n // 3)] |= torch.rand(4 * (n // 3), generator=g) < 0.8   # (whole plane pixels: many)
    nrm[mask] = torch.tensor([0.0, 1.0, 0.0])
    region = torch.randint(0, 2, (P,), generator=g)
    u = torch.randn(N, 3, generator=g)
    u[7] = float("nan")
    K = 80
    U = torch.randn(N, 3, K, generator=g)
    return face, bary, nrm, wo, mask, F32, u, U, region


def test_vector_plane_equals_scalar_random(monkeypatch):
    """`native.fused_pixels`(…, vector=True) = (…, vector=False) bit for bit (NaN and zeros' signs too) and the
    same specular count, on random inputs: pixels of one face and of mixed faces, samples facing away, object
    samples anywhere, with and without ``hit`` (misses), clamp on and off, both dots (``fma``), pixel counts
    that leave a tail in the last chunk, 1 and 2 threads; a face or corner out of range: None alike. A wrong
    corner, channel or barycentric, a lost clamp or front test, another summation order, a sample of a mixed
    pixel not blended in or a tail not run breaks it."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn
    from methods.zh_shadow import native_fused16

    if native_fused16.lib(True) is None or not zn.fused_available(6, True, True):
        pytest.skip("the vector fused pass is not available here")
    monkeypatch.setattr(zn, "MIN_PIXELS_PER_THREAD", 1)
    g = torch.Generator().manual_seed(40)
    ran = 0
    for n in (701, 64 * 9, 3):
        face, bary, nrm, wo, mask, F32, u, U, region = _inputs(g, n)
        P = 4 * n
        for hit in (None, torch.rand(P, generator=g) > 0.05):
            m = mask if hit is None else mask & hit
            for clamp in (False, True):
                for fma in (False, True):
                    args = (face, bary, nrm, wo, m, hit, F32, u, U, None, region, [False, True], 6, True, True,
                            clamp, 4)
                    for threads in (1, 2):
                        with torch_threads(threads):
                            a = zn.fused_pixels(*args, fma=fma, vector=False)
                            b = zn.fused_pixels(*args, fma=fma, vector=True)
                        assert a is not None and b is not None
                        assert torch.equal(_bits(a[0]), _bits(b[0])), (n, hit is None, clamp, fma, threads)
                        assert a[1] == b[1]
                        ran += 1
        # a plane sample's face, then a corner, out of range: both passes decline
        bad = face.clone()
        q = int(mask.nonzero()[len(mask.nonzero()) // 2])
        bad[q] = 10 ** 6
        args = (bad, bary, nrm, wo, mask, None, F32, u, U, None, region, [False, True], 6, True, True, True, 4)
        if float(nrm[q] @ wo[q]) > 0:
            assert zn.fused_pixels(*args, fma=True, vector=False) is None
            assert zn.fused_pixels(*args, fma=True, vector=True) is None
        F_bad = F32.clone()
        F_bad[:, 1] = 10 ** 6
        args = (face, bary, nrm, wo, mask, None, F_bad, u, U, None, region, [False, True], 6, True, True, True, 4)
        assert zn.fused_pixels(*args, fma=True, vector=False) is None
        assert zn.fused_pixels(*args, fma=True, vector=True) is None
    assert ran


def test_vector_plane_other_layouts_run_the_scalar_lines():
    """S² other than 4 (and row-major barycentrics): the vector library's scalar lines, the same bits."""
    from methods.zh_shadow import native as zn
    from methods.zh_shadow import native_fused16

    if native_fused16.lib(True) is None or not zn.fused_available(6, True, True):
        pytest.skip("the vector fused pass is not available here")
    g = torch.Generator().manual_seed(41)
    face, bary, nrm, wo, mask, F32, u, U, region = _inputs(g, 225)
    for S2, b in ((9, bary), (1, bary), (4, bary.contiguous())):
        args = (face, b, nrm, wo, mask, None, F32, u, U, None, region, [False, True], 6, True, True, True, S2)
        a = zn.fused_pixels(*args, fma=True, vector=False)
        c = zn.fused_pixels(*args, fma=True, vector=True)
        assert torch.equal(_bits(a[0]), _bits(c[0])) and a[1] == c[1], S2


@pytest.mark.parametrize("kind", ("P", "V", "VB", "VL"))
def test_vector_plane_frames_equal_scalar(creature, monkeypatch, kind):
    """`_fused_planes` with `vector_plane` = without it (the scalar plane lines), bit for bit, with the same path
    and counts — the kept table and a frame's own, clamp on and off, with misses — at 1 and 2 threads."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn
    from methods.zh_shadow import native_fused16
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if native_fused16.lib(True) is None or not zn.fused_available(6, True, True):
        pytest.skip("the vector fused pass is not available here")
    monkeypatch.setattr(zn, "MIN_PIXELS_PER_THREAD", 1)
    fused = 0
    for table_points in (0.0, 1e9):
        monkeypatch.setattr("methods.zh_shadow.method.VERTEX_TABLE_POINTS", table_points)
        for clamp, misses in ((True, False), (False, False), (True, True)):
            vec, scal = (creature.with_render_config(clamp=clamp) for _ in range(2))
            vec.vector_plane, scal.vector_plane = True, False
            vec.wide_dot = scal.wide_dot = False   # (the 8-float dot on both sides: zh42p's wide one runs with the
            #                                        vector pass alone, `test_zh42p` its oracle)
            for fr in make_sequence(creature.scene, kind, 3, seed=12):
                gb = make_gbuffer(creature.scene, fr, 2)
                if misses:
                    gb = knock_out(gb, 397 + fr.index, 3 + fr.index)
                for threads in (1, 2):
                    with torch_threads(threads):
                        a = vec.render(fr, gb)
                        b = scal.render(fr, gb)
                    assert vec.last_path == scal.last_path and vec.last_fused == scal.last_fused
                    assert torch.equal(_bits(a), _bits(b)), (kind, clamp, misses, fr.index, threads)
                    fused += bool(vec.last_fused)
                ca, cb = dict(vec._last_counts), dict(scal._last_counts)
                assert ca.pop("plane_vertices")() == cb.pop("plane_vertices")() and ca == cb
    assert fused, "the fused pass never ran"


def test_wide_vertex_table_equals_rows4(monkeypatch):
    """`native.vertex_table`(…, wide=True) (`native_vtable16`: 16-float vectors) = `zh38v_vtable` bit for bit:
    every row and through ids, regions sorted and interleaved (runs of four of one region and not), a region
    outside [0, R) (a zero row), C a multiple of 32, of 16 alone and neither (the 16-wide block, then `vrow`),
    1 and 3 threads; an id out of range: None alike. A wrong row, column block or term order breaks it."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn
    from methods.zh_shadow import native_vtable16

    if native_vtable16.lib() is None or zn._vtable4_lib() is None:
        pytest.skip("the wide vertex table is not available here")
    monkeypatch.setattr(zn, "MIN_ROWS_PER_VTABLE_THREAD", 1)
    g = torch.Generator().manual_seed(42)
    N, n2, R = 403, 16, 3
    v = torch.randn(N, n2, generator=g)
    ran = 0
    for C in (240, 48, 80, 19):
        W = torch.randn(R, n2, C, generator=g)
        for vreg in (torch.randint(0, R, (N,), generator=g).sort().values, torch.randint(0, R, (N,), generator=g)):
            vreg = vreg.clone()
            vreg[5] = R + 2
            for idx in (None, torch.randperm(N, generator=g)[:150].sort().values, torch.randperm(N, generator=g)[:97]):
                for threads in (1, 3):
                    with torch_threads(threads):
                        a = zn.vertex_table(v, vreg, W, idx)
                        b = zn.vertex_table(v, vreg, W, idx, wide=True)
                    assert a is not None and torch.equal(a, b), (C, idx is None, threads)
                    ran += 1
        bad = torch.tensor([0, 1, N + 5])
        assert zn.vertex_table(v, vreg, W, bad) is None and zn.vertex_table(v, vreg, W, bad, wide=True) is None
    assert ran


@pytest.mark.parametrize("kind", ("P", "VB", "VL"))
def test_wide_table_frames_equal(creature, monkeypatch, kind):
    """`ZHShadow.wide_table` on = off (`zh38v_vtable`), bit for bit, the kept table and a frame's own."""
    from methods.zh_shadow import native_vtable16
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if native_vtable16.lib() is None:
        pytest.skip("the wide vertex table is not available here")
    for table_points in (0.0, 1e9):
        monkeypatch.setattr("methods.zh_shadow.method.VERTEX_TABLE_POINTS", table_points)
        a_m, b_m = creature.with_render_config(), creature.with_render_config()
        a_m.wide_table, b_m.wide_table = True, False
        for fr in make_sequence(creature.scene, kind, 3, seed=13):
            gb = make_gbuffer(creature.scene, fr, 2)
            a, b = a_m.render(fr, gb), b_m.render(fr, gb)
            assert a_m.last_path == b_m.last_path and torch.equal(_bits(a), _bits(b)), (kind, fr.index)
