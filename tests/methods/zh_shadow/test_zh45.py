"""Session 45 (zh45): a new plane term's u0 = v · T¹(n0) and u = u0 ⊙ kd in one threaded C call
(`native_plane_terms.plane_terms`, `ZHShadow.native_plane_terms`) against its oracle (`native.plane_u` a region, ``zero_`` and
``torch.mul``: `_plane_term`'s own steps) — the same bits, at 1 and 2 threads."""
from __future__ import annotations

import pytest
import torch

from methods.zh_shadow import native as zn
from methods.zh_shadow import native_plane_terms as z45


def _bits(x: torch.Tensor) -> torch.Tensor:
    return x.contiguous().view(torch.int32)


def _skip_without_lib() -> None:
    if z45._lib() is None or zn._relight_pixels_lib() is None:
        pytest.skip("no C compiler or the native passes switched off")


def _oracle(v, T, spans, on, kd):
    """`ZHShadow._plane_term`'s ``only`` steps: `native.plane_u` per region with ``on``, zeros for the others, then
    ``torch.mul`` by the region's kd."""
    u0 = torch.empty(v.shape[0], 3)
    for (a0, a1), o in zip(spans, on):
        if not o:
            u0[a0:a1].zero_()
        elif a1 > a0:
            assert zn.plane_u(v[a0:a1], T, out=u0[a0:a1]) is not None
    u = torch.empty_like(u0)
    for (a0, a1), k in zip(spans, kd):
        torch.mul(u0[a0:a1], k, out=u[a0:a1])
    return u0, u


@pytest.mark.parametrize("threads", (1, 2))
@pytest.mark.parametrize("n2", (4, 16, 64))
def test_plane_terms_equal_plane_u_and_mul(threads, n2, monkeypatch):
    """The same bits as the oracle for random rows (signs mixed, kd with negative and zero entries: u0 = 0 times a
    negative kd is −0 in both), region layouts with an empty region and the specular flags either way; rows split
    over the threads (`MIN_ROWS_PER_THREAD` lowered so that both threads take rows). A product summed in another
    order, a channel's kd swapped, a region's flag ignored or a row range off breaks it."""
    _skip_without_lib()
    monkeypatch.setattr(z45, "MIN_ROWS_PER_THREAD", 16)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        g = torch.Generator().manual_seed(45 + n2)
        for counts, on in (((300, 500), (True, False)), ((120, 0, 400, 77), (False, True, True, False)),
                           ((999,), (True,)), ((250, 250), (False, True))):
            N = sum(counts)
            v = torch.randn(N, n2, generator=g) * 3
            T = torch.randn(n2, 3, generator=g)
            kd = torch.randn(len(counts), 3, generator=g)
            kd[0, 1] = 0.0
            spans, a = [], 0
            for c in counts:
                spans.append((a, a + c))
                a += c
            vreg = torch.repeat_interleave(torch.arange(len(counts)), torch.tensor(counts))
            want0, want = _oracle(v, T, spans, on, kd)
            got = z45.plane_terms(v, T, vreg, torch.tensor(on, dtype=torch.uint8), kd)
            assert got is not None
            assert torch.equal(_bits(got[0]), _bits(want0)), (counts, on)
            assert torch.equal(_bits(got[1]), _bits(want)), (counts, on)
    finally:
        torch.set_num_threads(old)


def test_plane_terms_refuse_other_layouts():
    """None (the caller's own steps then) for float64 rows, a transposed T, a region id array of the wrong length
    or dtype, flags that are not bytes or of another count than kd's rows."""
    _skip_without_lib()
    v, T, kd = torch.randn(10, 16), torch.randn(16, 3), torch.rand(2, 3)
    vreg, on = torch.tensor([0] * 4 + [1] * 6), torch.tensor([1, 0], dtype=torch.uint8)
    assert z45.plane_terms(v, T, vreg, on, kd) is not None
    assert z45.plane_terms(v.double(), T, vreg, on, kd) is None
    assert z45.plane_terms(v, torch.randn(3, 16).T, vreg, on, kd) is None
    assert z45.plane_terms(v, T, vreg[:-1], on, kd) is None
    assert z45.plane_terms(v, T, vreg.int(), on, kd) is None
    assert z45.plane_terms(v, T, vreg, on.bool(), kd) is None
    assert z45.plane_terms(v, T, vreg, on[:1], kd) is None


@pytest.mark.parametrize("kind", ("P", "VL", "VBL", "VB"))
def test_native_plane_terms_frames_equal_oracle(creature, monkeypatch, kind):
    """Frames whose plane term is made anew (P: a new pose's v; VL / VBL: a new lighting's T¹(n0); VB: the albedos
    alone, the kept u0 times the new kd) render the same image bits, and keep the same u0 and u bits, with the one
    call as with `_plane_term`'s own steps (``native_plane_terms`` off) — at 1 and 2 threads; the call ran in the
    frames that make u0 anew."""
    _skip_without_lib()
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    ran = []
    orig = z45.plane_terms
    monkeypatch.setattr(z45, "plane_terms", lambda *a: ran.append(1) or orig(*a))
    monkeypatch.setattr(z45, "MIN_ROWS_PER_THREAD", 16)
    old = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            fast, slow = creature.with_render_config(), creature.with_render_config()
            slow.native_plane_terms = False
            n_ran = len(ran)
            for fr in make_sequence(creature.scene, kind, 4, seed=45):
                gb = make_gbuffer(creature.scene, fr, 2)
                a, b = fast.render(fr, gb), slow.render(fr, gb)
                assert fast.last_path == slow.last_path == "planes"
                assert torch.equal(_bits(a), _bits(b)), (kind, threads, fr.index)
                assert torch.equal(_bits(fast._plane_u[3]), _bits(slow._plane_u[3]))
                assert torch.equal(_bits(fast._plane_u0[3]), _bits(slow._plane_u0[3]))
            assert len(ran) > n_ran
    finally:
        torch.set_num_threads(old)


@pytest.mark.parametrize("n", (3, 4))
def test_light_table_rows_over_threads_same_bits(n, monkeypatch):
    """`native_split.light_table`'s rows split over 2 threads (zh45; its threshold lowered so that small orders split
    too) = the 1-thread table bit for bit, for the specular table at several exponents and the diffuse one. A row
    range that skips or repeats rows, or a row buffer shared between the threads, breaks it."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native_split as z44
    from methods.zh_shadow import runtime as rt

    if z44._lib() is None:
        pytest.skip("no C compiler or the native passes switched off")
    monkeypatch.setattr(z44, "MIN_TABLE_ROWS_PER_THREAD", 8)
    g = torch.Generator().manual_seed(450 + n)
    for t in range(4):
        L = torch.randn(n * n, 3, generator=g) * (1 + t)
        for alpha in (None, 0.0, 3.0, 37.5):
            A = rt._table_operator_b(n, 1.0, True) if alpha is None else rt._band_operators(n, False)
            with torch_threads(1):
                one = z44.light_table(A, L, alpha)
            with torch_threads(2):
                two = z44.light_table(A, L, alpha)
            assert one is not None and two is not None
            assert torch.equal(_bits(one), _bits(two)), (n, t, alpha)
            want = rt.table(L, 1.0 if alpha is None else alpha, diffuse=alpha is None)
            assert float((two - want).abs().max()) <= 2 * torch.finfo(torch.float32).eps * float(want.abs().max())
