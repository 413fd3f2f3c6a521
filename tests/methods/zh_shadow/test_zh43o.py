"""Session 43 (zh43o): the order-8 / vertex-shaded P frame's serial glue trimmed (``ZHShadow.lean_pose``) and its
referenced-vertex pass split over the threads (``native.PARALLEL_REFERENCED``). Oracles: zh35o's calls
(`front_columns`, ``torch.searchsorted``, `_front_planes`' compare), `native.pose_sh`, torch's plane product and
`referenced_vertices` — and whole P frames with ``lean_pose`` off."""
from __future__ import annotations

import pytest
import torch

from methods.zh_shadow import native as zn
from methods.zh_shadow import runtime as rt


def _needs_lib():
    if zn._front_lib() is None or zn._pref_lib() is None or zn._pose_sh_lib() is None:
        pytest.skip("no C compiler")


def _front_case(seed: int, N: int = 3000):
    g = torch.Generator().manual_seed(seed)
    pos = torch.randn(N, 3, generator=g)
    nrm = torch.nn.functional.normalize(torch.randn(N, 3, generator=g), dim=1)
    nrm[1000:1800] = torch.tensor([0.0, 1.0, 0.0])      # a plane region (one normal bitwise)
    nrm[1900:2600] = torch.tensor([0.0, 0.0, 1.0])      # a near-plane: one vertex differs in z alone
    nrm[2300:2320] = torch.tensor([0.0, 0.0, 0.5])     # (several: some of them front-facing and referenced)
    ref = torch.rand(N, generator=g) < 0.7
    cam = torch.tensor([0.3, 4.0, 2.5])
    starts = [0, 1000, 1800, 1900, 2600, 2600, N]         # (an empty region at 2600)
    return pos, nrm, ref, cam, starts


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_front_regions_equal_front_columns(seed):
    """`native.front_regions` = `front_columns` (idx, nTc, woTc bit for bit, compact and contiguous), its bounds =
    ``torch.searchsorted`` of the region starts, its plane flags = `_front_planes`' compare per region."""
    _needs_lib()
    pos, nrm, ref, cam, starts = _front_case(seed)
    fr = zn.front_regions(pos, nrm, ref, cam, starts)
    fc = zn.front_columns(pos, nrm, ref, cam)
    assert fr is not None and fc is not None
    for a, b in zip(fr[:3], fc):
        assert a.is_contiguous() and a.shape == b.shape and torch.equal(a, b)
    idx, nTc = fc[0], fc[1]
    assert fr[3] == torch.searchsorted(idx, torch.tensor(starts)).tolist()
    want = []
    for b0, b1 in zip(fr[3][:-1], fr[3][1:]):
        blk = nTc[:, b0:b1]
        want.append(bool((blk == blk[:, :1]).all()) if b1 > b0 else True)
    assert fr[4] == want and want[1] and not want[3]   # (the plane's test true, the near-plane's false)
    assert zn.front_regions(pos, nrm, ref, cam, [0, 2000, 1000, 3000]) is None   # (starts not ascending)


def test_plane_rows_equal_torch_product():
    """`native.plane_rows` = (g @ vz[:, b0:b1]).T scattered to rows idx[b0:b1] to float32 round-off; the other rows
    untouched; False for a range past the columns."""
    _needs_lib()
    g_ = torch.Generator().manual_seed(4)
    n2, Q, N = 64, 300, 500
    g = torch.randn(3, n2, generator=g_)
    vz = torch.randn(n2, Q + 7, generator=g_)[:, :Q]       # (rows of stride Q + 7)
    idx = torch.randperm(N, generator=g_)[:Q].sort().values
    out = torch.full((N, 3), 7.0)
    b0, b1 = 30, 230
    assert zn.plane_rows(g, vz, b0, b1, idx, out)
    want = torch.full((N, 3), 7.0)
    want.index_copy_(0, idx[b0:b1], torch.mm(g, vz[:, b0:b1]).T)
    assert (out - want).abs().max() <= 1e-5 * want.abs().max()
    keep = torch.ones(N, dtype=torch.bool)
    keep[idx[b0:b1]] = False
    assert torch.equal(out[keep], want[keep])
    assert not zn.plane_rows(g, vz, 0, Q + 1, idx, out)


def test_pose_sh_bound_columns_equal_pose_sh(order8):
    """`PoseSHBound.columns` (bound by `ZHShadow._cols_bound`) = `native.pose_sh` of those columns bit for bit, at
    1 and 2 threads, into a kept buffer; None for an id out of range."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow.precompute import CHART_RMAX

    _needs_lib()
    m = order8.with_render_config()
    m.model.X = zn.vertex_major(m.model.X)
    X, n = m.model.X, 8
    cb = m._cols_bound()
    assert cb[0] is X and cb[1] is not None
    N = int(X.shape[1])
    g = torch.Generator().manual_seed(5)
    pose = torch.randn(int(X.shape[0]) - 1, generator=g) * 0.3
    idx = torch.randperm(N, generator=g)[:N // 2].sort().values
    nT = torch.nn.functional.normalize(torch.randn(3, idx.shape[0], generator=g), dim=0).contiguous()
    perm = m._zyz_perm(n, rt.zyz_rows(n))
    want = zn.pose_sh(X, torch.cat([pose, torch.ones(1)]), idx, nT, rt._band_norms(n), perm, m.model.lobes, n,
                      CHART_RMAX)
    buf = torch.zeros(64 * N)
    for t in (1, 2):
        with torch_threads(t):
            got = cb[1].columns(pose, idx, nT, buf)
        assert got is not None and got.data_ptr() == buf.data_ptr() and torch.equal(got, want), t
    bad = idx.clone()
    bad[-1] = N
    assert cb[1].columns(pose, bad, nT, buf) is None


def test_parallel_referenced_equals_loop(monkeypatch):
    """`referenced_mask` by the threads' loop (``PARALLEL_REFERENCED``) = by `referenced_vertices` = the torch
    oracle, at 1 and 2 threads, with misses and stale face ids of missed samples."""
    from methods.core.threads import torch_threads

    _needs_lib()
    monkeypatch.setattr(zn, "MIN_REFERENCED_SAMPLES_PER_THREAD", 64)
    g = torch.Generator().manual_seed(6)
    N, M, P = 900, 1500, 20000
    F = torch.randint(0, N, (M, 3), generator=g)
    face = torch.randint(0, M, (P,), generator=g)
    hit = torch.rand(P, generator=g) < 0.8
    face[~hit & (torch.rand(P, generator=g) < 0.5)] = -1
    want = zn.referenced_mask_torch(F, face, hit, N)
    for t in (1, 2):
        with torch_threads(t):
            assert torch.equal(zn.referenced_mask(F, face, hit, N), want), t
    monkeypatch.setattr(zn, "PARALLEL_REFERENCED", False)
    assert torch.equal(zn.referenced_mask(F, face, hit, N), want)


@pytest.mark.parametrize("planes", [True, False])
def test_lean_pose_frames_equal_zh35o_calls(order8, monkeypatch, planes):
    """Order-8 P frames (then a view frame of the last pose) with ``lean_pose`` = without (zh35o's calls): the
    same image bits (the plane rows, `native.plane_rows`, checked to float32 round-off), the same counts, the
    same bits at 1 and 2 threads; the lean calls taken by every P frame."""
    import dataclasses

    from methods.core.threads import torch_threads
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _needs_lib()
    if planes:
        monkeypatch.setattr(rt, "PLANAR_MIN_POINTS", 64)
    calls = {"regions": 0, "cols": 0, "plane": 0}
    fr_, pc_, pr_ = zn.front_regions, zn.PoseSHBound.columns, zn.plane_rows
    monkeypatch.setattr(zn, "front_regions", lambda *a: calls.__setitem__("regions", calls["regions"] + 1) or fr_(*a))
    monkeypatch.setattr(zn.PoseSHBound, "columns", lambda self, *a: calls.__setitem__("cols", calls["cols"] + 1)
                        or pc_(self, *a))
    monkeypatch.setattr(zn, "plane_rows", lambda *a: calls.__setitem__("plane", calls["plane"] + 1) or pr_(*a))
    m = order8
    fast, fast2, slow = m.with_render_config(), m.with_render_config(), m.with_render_config()
    slow.lean_pose = False
    for x in (fast, fast2, slow):
        x.plane_operators = planes
    frames = list(make_sequence(m.scene, "P", 4, seed=8))
    # (a new pose with new albedos: the planes' kept rows are the lighting's, albedos' and normal's)
    mats = {k: dataclasses.replace(v, kd=tuple(0.5 * x for x in v.kd)) for k, v in frames[2].materials.items()}
    frames.append(dataclasses.replace(frames[2], materials=mats, changed=frozenset({"pose", "brdf"})))
    view = list(make_sequence(m.scene, "V", 2, seed=8))[1]
    frames.append(dataclasses.replace(view, pose=frames[-1].pose, changed=frozenset({"view"})))
    for i, f in enumerate(frames):
        gb = make_gbuffer(m.scene, f, 2)
        c0 = dict(calls)
        a = fast.render(f, gb)
        if 0 < i < len(frames) - 1:
            assert calls["regions"] > c0["regions"] and calls["cols"] > c0["cols"], i
            assert not planes or calls["plane"] > c0["plane"], i
        with torch_threads(2):
            a2 = fast2.render(f, gb)
        b = slow.render(f, gb)
        assert torch.equal(a, a2), i
        assert (a - b).abs().max() <= 1e-6 * b.abs().max(), i
        kind = "P" if i < len(frames) - 1 else "V"
        assert fast.frame_cost(kind, gb.num_samples) == slow.frame_cost(kind, gb.num_samples), i


@pytest.mark.parametrize("kind", ["L", "E"])
def test_lean_steady_counts_equal(order8, kind):
    """Order-8 lighting-only sequences: a steady frame after another keeps the last credit's counts (``lean_pose``,
    `ZHShadow.render`) — the same frame costs and images as making them anew (``lean_pose`` off), frame by frame,
    the kept branch taken from the second steady frame on."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _needs_lib()
    fast, slow = order8.with_render_config(), order8.with_render_config()
    slow.lean_pose = False
    frames = list(make_sequence(order8.scene, kind, 5, seed=2))
    kept = 0
    for i, f in enumerate(frames):
        gb = make_gbuffer(order8.scene, f, 2)
        cr = fast._credited
        a, b = fast.render(f, gb), slow.render(f, gb)
        kept += cr is not None and fast._credited is cr and fast._last_counts is cr[3]
        assert torch.equal(a, b), i
        assert fast.frame_cost(kind, gb.num_samples) == slow.frame_cost(kind, gb.num_samples), i
    assert kept >= 2


def test_full_change_frame_sizes_the_p_frame_buffer(order8):
    """The full-change frame binds the P frames' visibility call and makes their columns' buffer (half the vertices'
    columns), so the P frames after it make neither while it is large enough (`ZHShadow._cols_bound`)."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _needs_lib()
    m = order8.with_render_config()
    frames = list(make_sequence(m.scene, "P", 4, seed=3))
    for i, f in enumerate(frames):
        gb = make_gbuffer(m.scene, f, 2)
        b0, cb0 = m._pose_sh_buf, m._pose_cols_bound
        m.render(f, gb)
        if i == 0:
            N = int(m.scene.geometry().num_vertices)
            assert m._pose_sh_buf is not None and m._pose_sh_buf.numel() == 64 * (N // 2)
            assert m._pose_cols_bound is not None and m._pose_cols_bound[1] is not None
        else:
            assert m._pose_cols_bound is cb0
            assert m._pose_sh_buf is b0 or b0.numel() < 64 * int(m._last_counts["Q"]), i
