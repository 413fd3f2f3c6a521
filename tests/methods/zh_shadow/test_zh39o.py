"""Session 39 (zh39o): the order-8 vertex-shaded config's lighting-only frames — the resolve matrix built by
one C pass (`native.resolve_matrix`) against `gouraud.resolve_matrix` + `method._int32_csr` (its oracle, the
same bits)."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from methods.core import gouraud
from methods.zh_shadow import native as zn
from methods.zh_shadow.method import _int32_csr
from testing.gbuffers import knock_out

def _oracle(F, gb, N):
    return _int32_csr(gouraud.resolve_matrix(F.T, gb.face, gb.bary, gb.hit, gb.height, gb.width, gb.spp_side, N))


def _same_csr(A, B):
    assert A.shape == B.shape and A.layout == B.layout == torch.sparse_csr
    for a, b in ((A.crow_indices(), B.crow_indices()), (A.col_indices(), B.col_indices()), (A.values(), B.values())):
        assert a.dtype == b.dtype and torch.equal(a, b), float((a.double() - b.double()).abs().max()) \
            if a.shape == b.shape else (a.shape, b.shape)


@pytest.mark.parametrize("spp", [1, 2, 3])
def test_native_resolve_matrix_equals_gouraud(order8, spp):
    """`native.resolve_matrix` = `_int32_csr(gouraud.resolve_matrix(...))` bit for bit (row offsets, columns,
    weights; int32 indices) on creature G-buffers of 1, 2×2 and 3×3 samples a pixel (1/9: a weight scale that
    rounds), with misses (and a whole pixel missed), and on one whose every sample of a pixel lies on one face
    (each vertex met S² times: the duplicates' sum order). A weight summed in another order, a duplicate not
    merged, a miss counted, a wrong corner or scale breaks it."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if zn._rmatrix_lib() is None:
        pytest.skip("no C compiler")
    scene = order8.scene
    geom = scene.geometry()
    F, N = geom.F, int(geom.num_vertices)
    f = make_sequence(scene, "L", 1, seed=3)[0]
    gb = make_gbuffer(scene, f, spp)
    S2 = spp * spp
    cases = [gb, knock_out(gb, 7, 3)]
    miss = torch.zeros_like(gb.hit)
    miss[5 * S2:6 * S2] = True                                        # pixel 5: every sample missed
    cases.append(dataclasses.replace(gb, hit=gb.hit & ~miss, face=gb.face.masked_fill(miss, -1)))
    # every sample of a pixel on its first sample's face (random barycentrics): S² entries per vertex
    face = gb.face.view(-1, S2)[:, :1].expand(-1, S2).reshape(-1).contiguous()
    hit = gb.hit.view(-1, S2)[:, :1].expand(-1, S2).reshape(-1).contiguous()
    g = torch.Generator().manual_seed(2)
    u, v = torch.rand(face.shape[0], generator=g), torch.rand(face.shape[0], generator=g)
    bary = torch.stack([u * 0.5, v * 0.5], 1)
    cases.append(dataclasses.replace(gb, face=face, hit=hit, bary=bary))
    cases.append(dataclasses.replace(gb, face=face, hit=hit, bary=bary.T.contiguous().T))   # column-major bary
    # a degenerate face (a corner twice) under a whole pixel: its duplicates merged by the general path
    Fd = F.clone()
    fd = int(gb.face[gb.hit][0])
    Fd[fd, 2] = Fd[fd, 0]
    cases_F = [(F, g_) for g_ in cases] + [(Fd, cases[3])]
    tails = 0
    for Fx, gbx in cases_F:
        B = zn.resolve_matrix(Fx, gbx.face, gbx.bary, gbx.hit, gbx.height, gbx.width, gbx.spp_side, N)
        assert B is not None
        A = _oracle(Fx, gbx, N)
        _same_csr(A, B)
        # the packed form made in the same pass = `csr_pack` of the oracle's matrix, array for array
        S, packed = zn.resolve_matrix(Fx, gbx.face, gbx.bary, gbx.hit, gbx.height, gbx.width, gbx.spp_side, N,
                                      packed=True)
        _same_csr(A, S)
        ref = zn.csr_pack(A)
        assert packed[:2] == ref[:2]
        for x, y in zip(packed[2:], ref[2:]):
            assert x.dtype == y.dtype and torch.equal(x, y)
        tails += int(ref[4].numel())
    assert tails > 0 or spp == 1   # (rows of more than four entries met)


def test_native_resolve_matrix_declines(order8, monkeypatch):
    """None (the caller's torch path) for a face or corner out of range, int32 faces, the switches off."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if zn._rmatrix_lib() is None:
        pytest.skip("no C compiler")
    scene = order8.scene
    geom = scene.geometry()
    F, N = geom.F, int(geom.num_vertices)
    gb = make_gbuffer(scene, make_sequence(scene, "L", 1, seed=3)[0], 2)
    args = (gb.bary, gb.hit, gb.height, gb.width, gb.spp_side)
    assert zn.resolve_matrix(F, gb.face, *args, N) is not None
    i = int(gb.hit.nonzero()[0])
    assert zn.resolve_matrix(F, gb.face.clone().index_fill_(0, torch.tensor([i]), F.shape[0]), *args, N) is None
    assert zn.resolve_matrix(F, gb.face, *args, 10) is None                             # a corner ≥ N
    assert zn.resolve_matrix(F, gb.face.int(), *args, N) is None
    monkeypatch.setattr(zn, "NATIVE_RESOLVE_MATRIX", False)
    assert zn.resolve_matrix(F, gb.face, *args, N) is None
    monkeypatch.setattr(zn, "NATIVE_RESOLVE_MATRIX", True)
    monkeypatch.setenv("PRTBENCH_ZH_NATIVE", "0")
    assert zn.resolve_matrix(F, gb.face, *args, N) is None


@pytest.mark.parametrize("kind", ["L", "E"])
def test_lighting_frames_with_native_matrix_equal_oracle(order8, kind, monkeypatch):
    """Order-8 lighting-only frames (the first builds the matrix; with misses) with the C-built matrix = with
    the torch-built one bit for bit, the C builder taken once per sequence."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if zn._rmatrix_lib() is None:
        pytest.skip("no C compiler")
    calls = []
    rm = zn.resolve_matrix
    monkeypatch.setattr(zn, "resolve_matrix", lambda *a, **k: calls.append(1) or rm(*a, **k))
    fast, slow = order8.with_render_config(), order8.with_render_config()
    frames = make_sequence(order8.scene, kind, 4, seed=5)
    gb = knock_out(make_gbuffer(order8.scene, frames[0], 2), 11, 4)
    for i, f in enumerate(frames):
        a = fast.render(f, gb)
        monkeypatch.setattr(zn, "NATIVE_RESOLVE_MATRIX", False)
        b = slow.render(f, gb)
        monkeypatch.setattr(zn, "NATIVE_RESOLVE_MATRIX", True)
        assert torch.equal(a, b), (kind, i, float((a - b).abs().max()))
    assert fast._resolve_matrix is not None and fast._resolve_matrix[2] is not None
    _same_csr(slow._resolve_matrix[2], fast._resolve_matrix[2])
    assert fast._resolve_packed[0] is fast._resolve_matrix[2]   # (the pass's packed form kept, not packed again)
    for x, y in zip(fast._resolve_packed[1][2:], slow._resolve_packed[1][2:]):
        assert torch.equal(x, y)
    assert len(calls) == 2   # (one build per object: fast's taken, slow's declined)


@pytest.mark.parametrize("clamp", [False, True])
def test_fused_relight_equals_radiance_ranges_and_csr_product(order8, clamp, monkeypatch):
    """Order-8 lighting-only frames (L, E; with misses; at 1 and 2 threads) with the radiance and resolve by one
    C call (`native.relight_resolve`) = with `_radiance_ranges` + `csr_product` (``fused_relight_vertex`` off,
    its oracle) to float32 round-off (the products summed in another order than MKL's: ≤ 8 ulps of the
    image's largest value), the fused call taken on every lighting-only frame (the first builds the matrix). A wrong
    albedo, a dropped specular part, a missed 1/π, a column or region off by one, a lost clamp or zero row
    breaks it far past that."""
    from methods.core.threads import torch_threads
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if zn._relightv_lib() is None:
        pytest.skip("no C compiler")
    monkeypatch.setattr(zn, "MIN_ROWS_PER_CSR_THREAD", 1)   # (test size: the product split over 2 threads too)
    calls = []
    rr = zn.relight_run   # (the C call: `relight_resolve`'s, and zh40l's steady frames' `_steady_relight`)
    monkeypatch.setattr(zn, "relight_run", lambda *a: (lambda o: calls.append(o is not None) or o)(rr(*a)))
    sr = zn.steady_run    # (zh42l: the steady frames' one call, `zh41l_relight` in it; False where it refused a
    #                       rotation without writing, then called again with `_lighting`'s lighting)
    monkeypatch.setattr(zn, "steady_run", lambda *a: (lambda o: (o and calls.append(o)) or o)(sr(*a)))
    m = order8.with_render_config(clamp=clamp)
    for kind in ("L", "E"):
        fast, fast2, slow = m.with_render_config(), m.with_render_config(), m.with_render_config()
        slow.fused_relight_vertex = False
        frames = make_sequence(order8.scene, kind, 5, seed=7)
        gb = knock_out(make_gbuffer(order8.scene, frames[0], 2), 13, 2)
        c0 = len(calls)
        for i, f in enumerate(frames):
            a = fast.render(f, gb)
            with torch_threads(2):
                a2 = fast2.render(f, gb)
            b = slow.render(f, gb)
            tol = 8 * torch.finfo(torch.float32).eps * float(b.abs().max())
            assert float((a - b).abs().max()) <= tol, (kind, i, float((a - b).abs().max()), tol)
            assert torch.equal(a, a2), (kind, i)   # (the product's rows split over threads: the same sums)
            if clamp:
                assert float(a.min()) >= 0.0
        assert calls[c0:] == [True] * 2 * (len(frames) - 1), (kind, calls[c0:])   # (frame 0 a full change)


def test_fused_relight_declines(order8):
    """None (the caller's torch path) for a part that is not its region's span, spans not tiling the columns,
    float64 arrays, the switch off."""
    if zn._relightv_lib() is None:
        pytest.skip("no C compiler")
    n2, Nc = 64, 10
    light, kd, ks = torch.rand(n2, 3), torch.rand(2, 3), torch.rand(2, 3)
    wf = torch.rand(n2, Nc)
    packed = (4, Nc + 1, torch.zeros(4, 4, dtype=torch.int32), torch.zeros(4, 4), torch.zeros(0, dtype=torch.int32),
              torch.zeros(1, dtype=torch.int32), torch.zeros(0, dtype=torch.int32), torch.zeros(0))
    ok = zn.relight_resolve(light, kd, ks, [(0, 6), (6, 10)], wf, {1: ((6, 10), torch.rand(n2, 4))}, False, packed)
    assert ok is not None and torch.equal(ok, torch.zeros(4, 3))
    assert zn.relight_resolve(light, kd, ks, [(0, 6), (6, 10)], wf, {1: ((7, 10), torch.rand(n2, 3))}, False,
                              packed) is None
    assert zn.relight_resolve(light, kd, ks, [(0, 5), (6, 10)], wf, {}, False, packed) is None
    assert zn.relight_resolve(light.double(), kd, ks, [(0, 6), (6, 10)], wf, {}, False, packed) is None
    import methods.zh_shadow.native as nat

    old = nat.FUSED_RELIGHT_VERTEX
    nat.FUSED_RELIGHT_VERTEX = False
    try:
        assert zn.relight_resolve(light, kd, ks, [(0, 6), (6, 10)], wf, {}, False, packed) is None
    finally:
        nat.FUSED_RELIGHT_VERTEX = old
