"""The pose path's C calls of session 36 (zh36o) against their oracles: the pose product and eq. 1 in one C call
(`native.pose_sh`) = `native.pose_columns` then the compiled `runtime._vertex_sh` (their numbers: the same
operations in the same order), and P frames rendered with it (``native_eq1``, the default) = without (the two
steps) to float32 round-off, with the same counts and the same bits at 1 and 2 threads."""
from __future__ import annotations

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


@pytest.mark.parametrize("J1,N,n,lobes", [(11, 13415, 8, 2), (5, 3001, 4, 1), (3, 517, 6, 3), (2, 40, 2, 4)])
def test_pose_sh_equals_product_then_eq1(J1, N, n, lobes):
    """`native.pose_sh` = `runtime._vertex_sh`(`native.pose_columns`(…), …, zyz, perm) (the compiled pass) to
    float32 round-off — every vertex, a sorted subset, one with repeats, a tail of
    fewer than 16 columns, none; charts beyond the clamp radius; normals on and near the poles and in the
    plane z = 0; the same bits at 1 and 2 threads and with a reused buffer; None for an id out of range, X not
    vertex-major, a perm that is not one, a of the wrong length."""
    from methods.core.threads import torch_threads

    _skip_without_c_compiler()
    g = torch.Generator().manual_seed(J1 * 100 + n)
    d = lobes * (2 + n)
    X = torch.randn(J1, N, d, generator=g) * 0.6
    X[:, :7, 0] *= 8.0                       # (charts beyond CHART_RMAX: the clamp)
    Xv = zn.vertex_major(X)
    a = torch.randn(J1, generator=g)
    nrm = torch.nn.functional.normalize(torch.randn(N, 3, generator=g), dim=1)
    nrm[:6] = torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0], [0, 1.0, 0], [0, 0.6, -0.8], [1e-21, 0, 1.0]])
    lam = rt._band_norms(n)
    perm = tuple(int(i) for i in rt.zyz_rows(n).tolist())
    sub = torch.sort(torch.randperm(N, generator=g)[: N // 3]).values
    mixed = torch.randint(0, N, (N // 5 + 3,), generator=g)
    for idx in (None, sub, mixed, sub[:13], torch.zeros(0, dtype=torch.int64)):
        pT = zn.pose_columns(Xv, a, idx)
        nT = nrm.T.contiguous() if idx is None else nrm.T.index_select(1, idx).contiguous()
        want = rt._vertex_sh(pT, nT, lam, lobes, n, 0, True, perm) if pT.shape[1] else \
            torch.zeros(n * n, 0)   # (the compiled pass at every count: its operations, not eager torch's)
        got = zn.pose_sh(Xv, a, idx, nT, lam, perm, lobes, n, CHART_RMAX)
        assert got is not None and got.shape == want.shape
        scale = max(float(want.abs().max()), 1e-30) if want.numel() else 1.0
        assert float((got - want).abs().max()) <= 2e-6 * scale if want.numel() else True, idx
        buf = torch.full((got.numel() + 5,), float("nan"))
        assert torch.equal(zn.pose_sh(Xv, a, idx, nT, lam, perm, lobes, n, CHART_RMAX, buf), got)
        with torch_threads(2):
            assert torch.equal(zn.pose_sh(Xv, a, idx, nT, lam, perm, lobes, n, CHART_RMAX), got)
    nT = nrm.T.contiguous()
    assert zn.pose_sh(Xv, a, torch.tensor([0, N]), nT[:, :2].contiguous(), lam, perm, lobes, n, CHART_RMAX) is None
    assert zn.pose_sh(Xv, a, torch.tensor([-1]), nT[:, :1].contiguous(), lam, perm, lobes, n, CHART_RMAX) is None
    if J1 > 1:
        assert zn.pose_sh(X, a, None, nT, lam, perm, lobes, n, CHART_RMAX) is None
        assert zn.pose_sh(Xv, a[:-1], None, nT, lam, perm, lobes, n, CHART_RMAX) is None
    assert zn.pose_sh(Xv, a, None, nT, lam, (0,) * (n * n), lobes, n, CHART_RMAX) is None


@pytest.mark.parametrize("J1,N,n,lobes,dim", [(11, 13415, 4, 2, 1), (3, 517, 6, 3, 0), (4, 300, 8, 1, 1)])
def test_pose_sh_world_frame_equals_vertex_sh(J1, N, n, lobes, dim):
    """`native.pose_sh` with the SH in world space (``zyz`` False: the paper configuration's `_pose_state`; up to
    `sh.FAST_MAX_ORDER` its traced polynomials, above it the recurrence), rows or columns per vertex (``dim``) =
    the compiled `runtime._vertex_sh` of `native.pose_columns` to float32 round-off; the same bits at 2 threads."""
    from methods.core.threads import torch_threads

    _skip_without_c_compiler()
    g = torch.Generator().manual_seed(J1 * 10 + n)
    X = torch.randn(J1, N, lobes * (2 + n), generator=g) * 0.6
    Xv = zn.vertex_major(X)
    a = torch.randn(J1, generator=g)
    nT = torch.nn.functional.normalize(torch.randn(3, N, generator=g), dim=0).contiguous()
    nT[:, :3] = torch.tensor([[0, 0, 1.0], [0, 0, -1.0], [1.0, 0, 0]]).T
    lam = rt._band_norms(n)
    want = rt._vertex_sh(zn.pose_columns(Xv, a, None), nT, lam, lobes, n, dim, False, None)
    got = zn.pose_sh(Xv, a, None, nT, lam, tuple(range(n * n)), lobes, n, CHART_RMAX, None, False, dim)
    assert got is not None and got.shape == want.shape
    assert float((got - want).abs().max()) <= 2e-6 * float(want.abs().max())
    with torch_threads(2):
        assert torch.equal(zn.pose_sh(Xv, a, None, nT, lam, tuple(range(n * n)), lobes, n, CHART_RMAX, None, False,
                                      dim), got)


@pytest.mark.parametrize("config", ["order8", "paper"])
@pytest.mark.parametrize("planes", [True, False])
def test_pose_frames_native_eq1_equal_two_steps(zh_scene, monkeypatch, planes, config):
    """P frames of the order-8 configuration (vertex-shaded cosine: the front-facing referenced vertices) and of
    the paper configuration (every vertex's world-space v) with the product and eq. 1 in one C call
    (``native_eq1``) = with the two steps (``native_eq1`` off: `native.pose_columns` and the compiled
    `runtime._vertex_sh`, or `runtime.world_visibility`) to float32 round-off, the same counts, the same bits at 1 and 2 threads, the C call
    taken; then a view frame of the last pose (every vertex's visibility, kept by `_pose_state`) likewise."""
    import dataclasses

    from methods.core.threads import torch_threads
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _skip_without_c_compiler()
    if planes:
        monkeypatch.setattr(rt, "PLANAR_MIN_POINTS", 64)
    calls = []
    ps_ = zn.pose_sh
    monkeypatch.setattr(zn, "pose_sh", lambda *a: calls.append(1) or ps_(*a))
    pb_ = zn.PoseSHBound.__call__   # (session 41: the paper config's bound call, `native.PoseSHBound`; counted as it)
    monkeypatch.setattr(zn.PoseSHBound, "__call__", lambda self, *a: calls.append(1) or pb_(self, *a))
    pc_ = zn.PoseSHBound.columns   # (zh43o: the order-8 P frame's bound call of its columns; counted as it)
    monkeypatch.setattr(zn.PoseSHBound, "columns", lambda self, *a: calls.append(1) or pc_(self, *a))
    m = ZHShadow(**SMALL, **(dict(order=8, specular="cosine", shading="vertex") if config == "order8" else {}))
    m.precompute(zh_scene("creature"))
    fast, fast2, slow = m.with_render_config(), m.with_render_config(), m.with_render_config()
    slow.native_eq1 = False
    for x in (fast, fast2, slow):
        x.plane_operators = planes
    frames = list(make_sequence(m.scene, "P", 4, seed=3))
    view = list(make_sequence(m.scene, "V", 2, seed=3))[1]
    frames.append(dataclasses.replace(view, pose=frames[-1].pose, changed=frozenset({"view"})))
    for i, f in enumerate(frames):
        gb = make_gbuffer(m.scene, f, 2)
        c0 = len(calls)
        a = fast.render(f, gb)
        if 0 < i < len(frames) - 1 or (i and config == "order8"):   # (a new pose; order 8: its view frame's every vertex)
            assert len(calls) > c0, i
        with torch_threads(2):
            a2 = fast2.render(f, gb)
        b = slow.render(f, gb)
        assert torch.equal(a, a2), i
        assert (a - b).abs().max() <= 2e-6 * b.abs().max(), i
        kind = "P" if i < len(frames) - 1 else "V"
        assert fast.frame_cost(kind, gb.num_samples) == slow.frame_cost(kind, gb.num_samples), i
    if config == "order8":
        assert fast.memory()["pose_visibility_sh"] >= fast._pose_sh_buf.numel() * 4 > 0


def test_pose_sh_follows_the_off_switch(monkeypatch):
    """`native.pose_sh`'s library follows PRTBENCH_COMPILE at each call (not lru-cached: b541a75): None while
    it is 0 (then `pose_sh` returns None: the caller's two steps), loaded once it is back on; and it is among
    the libraries a full-change frame loads for the P frames after it (`native.warm_pose_libraries`)."""
    from methods.core import native as core_native

    _skip_without_c_compiler()
    n, lobes, N = 8, 2, 50
    Xv = zn.vertex_major(torch.randn(3, N, lobes * (2 + n)))
    nT = torch.nn.functional.normalize(torch.randn(3, N), dim=0).contiguous()
    args = (Xv, torch.randn(3), None, nT, rt._band_norms(n), tuple(int(i) for i in rt.zyz_rows(n).tolist()), lobes, n,
            CHART_RMAX)
    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    assert zn._pose_sh_lib() is None and not zn.pose_sh_available() and zn.pose_sh(*args) is None
    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    assert zn._pose_sh_lib() is not None and zn.pose_sh(*args) is not None
    names = []
    load = core_native.load
    monkeypatch.setattr(core_native, "load", lambda name, *a, **k: names.append(name) or load(name, *a, **k))
    zn.warm_pose_libraries()
    assert "zh36o_pose_sh" in names
