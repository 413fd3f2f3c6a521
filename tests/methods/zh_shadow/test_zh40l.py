"""Session 40 (zh40l): steady lighting-only frames — after a frame that made its image by the fused relight (the
order-8 vertex config's `native.relight_resolve`, the paper config's `native.relight_pixels` in `_relight_planes`),
a lighting-only frame of the same camera, pose, materials and G-buffer size is the frame's lighting and that one
C call on the kept arguments (`ZHShadow._steady_relight`, `ZHShadow._steady_planes`); its oracle the full path
(``steady_relight`` off), the same bits."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from methods.zh_shadow import native as zn
from methods.zh_shadow.method import ZHShadow
from testing.gbuffers import knock_out


@pytest.fixture(autouse=True)
def _tables_not_operator(monkeypatch):
    """(zh41l) The paper config's steady T¹(n0) by the folded operator (``steady_plane_operator``) is float32
    round-off from the full path's tables (test_zh41l.test_steady_plane_operator_equals_tables): these tests
    check the kept call's bits, with the tables."""
    monkeypatch.setattr(ZHShadow, "steady_plane_operator", False)


def _spy(monkeypatch):
    taken = []
    for name in ("_steady_relight", "_steady_planes"):
        def spy(self, frame, gbuffer, _sr=getattr(ZHShadow, name)):
            out = _sr(self, frame, gbuffer)
            taken.append(out is not None)
            return out
        monkeypatch.setattr(ZHShadow, name, spy)
    return taken


# (fixture, a kept cache whose loss makes the next lighting-only frame a full one, the library of the fused call)
CONFIGS = {"order8": ("_vertex_compact", lambda: zn._relightv_lib()),
           "creature": ("_relight", lambda: zn._relight_pixels_lib())}


@pytest.mark.parametrize("clamp", [False, True])
@pytest.mark.parametrize("kind", ["L", "E"])
@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_steady_relight_equals_full_path(config, kind, clamp, monkeypatch, request):
    """L / E sequences (with misses; at 1 and 2 threads): with the steady path = without it (``steady_relight``
    off: `_render_vertex` every frame) bit for bit, the steady path taken on every lighting-only frame after the
    first (which builds the resolve matrix and records what the next reads). A stale lighting, a lost clamp or
    albedo, the wrong kept arguments break it."""
    from methods.core.threads import torch_threads
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    order8 = request.getfixturevalue(config)   # (either configuration's model)
    if CONFIGS[config][1]() is None:
        pytest.skip("no C compiler")
    taken = _spy(monkeypatch)
    m = order8.with_render_config(clamp=clamp)
    fast, fast2, slow = m.with_render_config(), m.with_render_config(), m.with_render_config()
    slow.steady_relight = False
    frames = make_sequence(order8.scene, kind, 5, seed=9)
    gb = make_gbuffer(order8.scene, frames[0], 2)
    if config == "order8":   # (with misses; the paper config's relight-planes path needs every sample hit)
        gb = knock_out(gb, 13, 2)
    for i, f in enumerate(frames):
        a = fast.render(f, gb)
        with torch_threads(2):
            a2 = fast2.render(f, gb)
        b = slow.render(f, gb)
        assert torch.equal(a, b), (kind, i, float((a - b).abs().max()))
        assert torch.equal(a, a2), (kind, i)
        assert fast._last_counts["Q"] == slow._last_counts["Q"] and fast._last_counts["P"] == slow._last_counts["P"]
        if config == "creature" and i > 0:
            assert slow.last_path == fast.last_path == "relight-planes"
            # (the kept blocked copies of the entries' transfer counted: td and ts, padded to whole blocks)
            extra = fast.memory()["relight_transfer"] - slow.memory()["relight_transfer"]
            assert extra == sum(-(-td.shape[1] // zn.RELIGHT_BLOCK) * zn.RELIGHT_BLOCK * td.shape[0] * 4
                                * (1 if ts is None else 2)
                                for entries in fast._relight[3]["regions"] for _, td, ts in entries
                                if td is not None), extra
    # frames 2-4 of fast and fast2 (frame 1 builds the matrix: no steady state before it; slow never has one)
    assert taken == [True] * 6, taken
    assert fast.frame_cost(kind, gb.num_samples).bytes == slow.frame_cost(kind, gb.num_samples).bytes


@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_steady_relight_declines_other_state(config, monkeypatch, request):
    """A frame flagged lighting-only (``changed`` = {"light"}) whose camera, materials, pose or G-buffer size
    differ from the recorded frame's, or after a kept cache was replaced, is not a steady frame: its image = the
    full path's (an object with the same history and ``steady_relight`` off) bit for bit. Dropping any of the
    checks renders the recorded frame's view / albedos / matrix instead and breaks it."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    order8 = request.getfixturevalue(config)
    if CONFIGS[config][1]() is None:
        pytest.skip("no C compiler")
    taken = _spy(monkeypatch)
    scene = order8.scene
    frames = make_sequence(scene, "L", 4, seed=11)
    gb = make_gbuffer(scene, frames[0], 2)
    light_only = frozenset({"light"})
    cam2 = dataclasses.replace(frames[2], camera=frames[2].camera.orbited(0.3), changed=light_only)
    mats = dict(frames[2].materials)
    name = next(r for r, mt in mats.items() if hasattr(mt, "kd"))
    mats[name] = dataclasses.replace(mats[name], kd=tuple(0.5 * x for x in mats[name].kd))
    mat2 = dataclasses.replace(frames[2], materials=mats, changed=light_only)
    cases = [(cam2, make_gbuffer(scene, cam2, 2)), (mat2, gb), (frames[2], make_gbuffer(scene, frames[2], 1))]
    if scene.skeleton is not None:
        pose = torch.zeros(scene.skeleton.num_joints)
        pose[0] = 0.2
        p2 = dataclasses.replace(frames[2], pose=pose, changed=light_only)
        cases.append((p2, make_gbuffer(scene, p2, 2)))
    for f2, g2 in cases:
        fast, slow = order8.with_render_config(), order8.with_render_config()
        slow.steady_relight = False
        for f in frames[:2]:
            assert torch.equal(fast.render(f, gb), slow.render(f, gb))
        assert fast._steady is not None
        taken.clear()
        a, b = fast.render(f2, g2), slow.render(f2, g2)
        assert taken == [False], taken
        assert torch.equal(a, b), float((a - b).abs().max())
    # a kept cache replaced (here the compact transfer dropped) between two lighting-only frames: the full path
    fast, slow = order8.with_render_config(), order8.with_render_config()
    slow.steady_relight = False
    for f in frames[:2]:
        fast.render(f, gb), slow.render(f, gb)
    setattr(fast, CONFIGS[config][0], None)
    setattr(slow, CONFIGS[config][0], None)
    taken.clear()
    assert torch.equal(fast.render(frames[2], gb), slow.render(frames[2], gb))
    assert taken == [False]
    taken.clear()
    assert torch.equal(fast.render(frames[3], gb), slow.render(frames[3], gb))
    assert taken == [True]   # (recorded again by the full frame before)


def test_blocked_relight_pixels_equals_zh35p():
    """`native.relight_pixels_setup(..., blocked=True)` (the entries read from their blocked copies,
    ``zh40l_relight_pixels``) = the unblocked setup (zh35p's pass) bit for bit: three entries whose pixels overlap,
    with and without ts, Q not a multiple of the block (and one shorter than a block), clamp on and off, 1, 2 and 3
    threads with the object weight at 0, 2 and 50 (thread cuts inside blocks: partial blocks on both sides), two
    lightings through one setup; a pixel outside the image still refused (None). A block's sample off by one, a
    lost ts part or its stride, a partial block read at the wrong lane breaks it."""
    from unittest import mock

    if zn._blk_relight_lib() is None or zn._relight_pixels_lib() is None:
        pytest.skip("no C compiler")
    g = torch.Generator().manual_seed(40)
    n, S2, N, n2, R = 3000, 4, 900, 16, 3
    Fp = 300
    face = torch.randint(-1, Fp, (n, S2), generator=g, dtype=torch.int64).to(torch.int32)
    bT = torch.rand(n * S2, 2, generator=g).T.contiguous().T.T.view(2, n, S2)
    v = torch.randn(N, n2, generator=g)
    corners = torch.randint(0, N, (3 * Fp,), generator=g)
    creg = torch.randint(0, R, (3 * Fp,), generator=g)
    kd = torch.rand(R, 3, generator=g)
    ents = []
    for Q, with_ts, lo, hi in ((1003, True, 0, n), (517, False, 200, 1400), (23, True, 1000, 1100)):
        td = torch.randn(n2, Q, generator=g)
        ts = torch.randn(n2, Q, generator=g) if with_ts else None
        ld = torch.randn(n2, 3, generator=g)
        ls = torch.randn(n2, 3, generator=g) if with_ts else None
        ents.append((td, ts, ld, ls, torch.sort(torch.randint(lo, hi, (Q,), generator=g)).values))
    lights = [([e[2] for e in ents], [e[3] for e in ents], torch.randn(n2, 3, generator=g))]
    lights.append(([torch.randn(n2, 3, generator=g) for _ in ents],
                   [None if e[1] is None else torch.randn(n2, 3, generator=g) for e in ents],
                   torch.randn(n2, 3, generator=g)))
    for clamp in (True, False):
        for nt in (1, 2, 3):
            for w in (0.0, 2.0, 50.0):
                with mock.patch.object(zn, "MIN_PIXELS_PER_THREAD", 1), \
                        mock.patch.object(torch, "get_num_threads", lambda: nt), \
                        mock.patch.object(zn, "RELIGHT_OBJECT_WEIGHT", w):
                    planes = (v, corners, creg, lights[0][2], kd)
                    a = zn.relight_pixels_setup(face, bT, clamp, ents, 0.25, planes, blocked=True)
                    b = zn.relight_pixels_setup(face, bT, clamp, ents, 0.25, planes, blocked=False)
                    assert a[0] is not b[0]   # (the blocked library's function)
                    for lds, lss, T in lights:
                        x, y = zn.relight_pixels_run(a, lds, lss, T), zn.relight_pixels_run(b, lds, lss, T)
                        assert x is not None and torch.equal(x, y), (clamp, nt, w, float((x - y).abs().max()))
    td, ts, ld, ls, pix = ents[0]
    bad = pix.clone().index_fill_(0, torch.tensor([len(pix) - 1]), n)                    # outside the image
    st = zn.relight_pixels_setup(face, bT, True, [(td, ts, ld, ls, bad)] + ents[1:], 0.25,
                                 (v, corners, creg, lights[0][2], kd), blocked=True)
    assert st is None or zn.relight_pixels_run(st, *lights[0]) is None
    xb = zn.blocked_transfer(td, ts)
    RB = zn.RELIGHT_BLOCK
    assert xb.shape == ((td.shape[1] + RB - 1) // RB, 2, n2, RB)
    assert torch.equal(xb[3, 1, 5], ts[5, 3 * RB:4 * RB]) and torch.equal(xb[-1, 0, 2, :td.shape[1] % RB],
                                                                           td[2, -(td.shape[1] % RB):])
