"""Session 37 (zh37p): a sample-shaded P frame's visibility made for the vertices its hit samples reference alone
(`ZHShadow._pose_state`, ``referenced_visibility``; `native.referenced_ids`, `native.pose_sh`'s ``scatter``) against
the every-vertex visibility (the flag off: the oracle)."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from methods.zh_shadow import ZHShadow
from methods.zh_shadow import native as zn
from methods.zh_shadow import runtime as rt
from methods.zh_shadow.precompute import CHART_RMAX

SMALL = dict(train_poses=4, n_dirs=64, fit_iters=0)


def _skip_without_c_compiler() -> None:
    from methods.core import native as core_native

    if core_native.compiler() is None:   # pragma: no cover - no C compiler here
        pytest.skip("no C compiler")


def test_referenced_ids_equal_the_torch_mask():
    """`native.referenced_ids` = (`referenced_mask_torch`, its ``nonzero``) with misses, a face id out of range
    and unused faces, at 1 and 2 threads."""
    from methods.core.threads import torch_threads

    _skip_without_c_compiler()
    g = torch.Generator().manual_seed(7)
    N, M, P = 5003, 9001, 1 << 17
    F = torch.randint(0, N, (M, 3), generator=g)
    face = torch.randint(0, M // 3, (P,), generator=g)
    face[::7] = torch.randint(M // 2, M, (len(face[::7]),), generator=g)
    hit = torch.rand(P, generator=g) > 0.1
    face[~hit] = -1
    face[5] = M + 3
    hit[5] = True                                  # (a hit with a bad face id: marks nothing)
    want = zn.referenced_mask_torch(F, face.clamp(0, M - 1), hit & (face < M), N)
    for nt in (1, 2):
        with torch_threads(nt):
            got = zn.referenced_ids(F, face, hit, N)
        assert got is not None
        assert torch.equal(got[0], want), nt
        assert torch.equal(got[1], want.nonzero().squeeze(-1)), nt


@pytest.mark.parametrize("J1,N,n,lobes", [(11, 13415, 4, 2), (3, 517, 6, 3), (2, 40, 2, 4)])
def test_pose_sh_scatter_rows(J1, N, n, lobes):
    """`native.pose_sh`(…, scatter=True) = the compact call's rows at rows idx of an (N, n²) array, 0 elsewhere
    (every row written: a buffer of NaN in, none out), at 1 and 2 threads; None for ids not increasing."""
    from methods.core.threads import torch_threads

    _skip_without_c_compiler()
    g = torch.Generator().manual_seed(J1 * 10 + n)
    d = lobes * (2 + n)
    Xv = zn.vertex_major(torch.randn(J1, N, d, generator=g) * 0.6)
    a = torch.randn(J1, generator=g)
    nrm = torch.nn.functional.normalize(torch.randn(N, 3, generator=g), dim=1)
    lam = rt._band_norms(n)
    perm = tuple(range(n * n))
    for idx in (torch.sort(torch.randperm(N, generator=g)[: N // 3]).values, torch.arange(N),
                torch.tensor([0, N - 1]), torch.tensor([N // 2]), torch.zeros(0, dtype=torch.int64)):
        compact = zn.pose_sh(Xv, a, idx, nrm.T.index_select(1, idx).contiguous(), lam, perm, lobes, n, CHART_RMAX,
                             None, False, 1)
        want = torch.zeros(N, n * n)
        want[idx] = compact
        for nt in (1, 2):
            buf = torch.full((N * n * n + 3,), float("nan"))
            with torch_threads(nt):
                got = zn.pose_sh(Xv, a, idx, nrm.T, lam, perm, lobes, n, CHART_RMAX, buf, False, 1, True)
            assert got is not None and got.shape == (N, n * n)
            assert torch.equal(got, want), (nt, idx.shape)
    bad = torch.tensor([3, 2]) if N > 3 else torch.tensor([1, 1])
    assert zn.pose_sh(Xv, a, bad, nrm.T, lam, perm, lobes, n, CHART_RMAX, None, False, 1, True) is None
    assert zn.pose_sh(Xv, a, torch.tensor([1, 1]), nrm.T, lam, perm, lobes, n, CHART_RMAX, None, False, 1, True) is None


@pytest.mark.parametrize("planes", [True, False])
def test_referenced_visibility_frames_equal_every_vertex(zh_scene, monkeypatch, planes):
    """Paper-configuration P frames with the referenced vertices' visibility alone (``referenced_visibility``, the
    default) = with every vertex's (off), bit for bit, with the same counts and the same bits at 2 threads; the
    partial visibility made (its other rows 0); then frames of the last pose: the same camera and a G-buffer whose
    samples reference a subset (kept), another camera (every vertex's, a new array), the first G-buffer knocked
    out and then the whole one again (kept, then made whole) — each image equal to the oracle's (the last to float32
    round-off: the oracle's kept transfer (a lighting-only frame) against the planes pass of a new array)."""
    from methods.core.threads import torch_threads
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _skip_without_c_compiler()
    if planes:
        monkeypatch.setattr(rt, "PLANAR_MIN_POINTS", 64)
    m = ZHShadow(**SMALL)
    m.precompute(zh_scene("creature"))
    fast, fast2, slow = m.with_render_config(), m.with_render_config(), m.with_render_config()
    slow.referenced_visibility = False
    frames = list(make_sequence(m.scene, "P", 4, seed=5))
    view = list(make_sequence(m.scene, "V", 2, seed=5))[1]
    last = frames[-1]
    gb_last = make_gbuffer(m.scene, last, 2)
    knocked = dataclasses.replace(gb_last, hit=gb_last.hit.clone())
    knocked.hit[: knocked.hit.shape[0] // 2] = False     # (the top half misses: fewer vertices referenced)
    knocked.face = torch.where(knocked.hit, knocked.face, torch.full_like(knocked.face, -1))
    again = dict(changed=frozenset({"pose"}))
    seq = [(f, None) for f in frames] + [
        (dataclasses.replace(last, **again), make_gbuffer(m.scene, last, 2)),        # same pose, a new G-buffer
        (dataclasses.replace(view, pose=last.pose, changed=frozenset({"view"})), None),   # another camera
        (dataclasses.replace(frames[1], changed=frozenset({"pose"})), None),
        (dataclasses.replace(last, changed=frozenset({"pose"})), knocked),           # half the samples miss
        (dataclasses.replace(last, changed=frozenset({"light"})), gb_last)]          # the whole G-buffer again
    partial = []
    for i, (f, gb) in enumerate(seq):
        gb = make_gbuffer(m.scene, f, 2) if gb is None else gb
        a = fast.render(f, gb)
        with torch_threads(2):
            a2 = fast2.render(f, gb)
        b = slow.render(f, gb)
        if i < len(seq) - 1:
            assert fast.last_path == slow.last_path and torch.equal(a, b), (i, float((a - b).abs().max()))
        else:   # (the visibility made whole: a new array, so no kept transfer — the planes path, not the relight)
            assert float((a - b).abs().max()) <= 2e-6 * float(b.abs().max()), i
        assert torch.equal(a, a2), i
        assert fast.frame_cost("P", gb.num_samples) == slow.frame_cost("P", gb.num_samples), i
        part = fast._posed_part
        partial.append(part is not None and part[0] is fast._posed[2])
        if partial[-1]:
            v, vs = fast._posed[2], slow._posed[2]
            rows = part[2]
            assert torch.equal(v[rows], vs[rows]) and not bool(v[~rows].any()) and int(rows.sum()) < v.shape[0]
    # new poses: partial; the same pose and G-buffer content: kept; another camera: whole; the knocked-out
    # G-buffer of a new pose: partial, then the whole G-buffer of that pose: made whole
    assert partial == [False, True, True, True, True, False, True, True, False], partial
