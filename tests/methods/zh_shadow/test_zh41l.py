"""Session 41 (zh41l): a lighting frame's world-space lighting by one C call (`native.light_world`: R Q, the ZYZ
test and angles, the rotation, the float32 rounding; `ZHShadow._light_world`); its oracle the base's steps
(``native.NATIVE_LIGHT`` off: torch's R @ Qᵀ, `runtime.rotate_lighting`, ``.float()``), the same bits."""
from __future__ import annotations

import math

import pytest
import torch

from methods.core.sh import _LATLONG_QT
from methods.zh_shadow import native as zn
from methods.zh_shadow import runtime as rt
from methods.zh_shadow.method import ZHShadow


def _needs_lib():
    if zn._light_lib() is None:
        pytest.skip("no C compiler")


def _rotations(n: int, seed: int) -> list[torch.Tensor]:
    """Random rotations, y rotations (exact zeros: the E
    sequences' to_world), the identity and signed permutations (zeros of either sign)."""
    g = torch.Generator().manual_seed(seed)
    out = []
    for _ in range(n):
        q, r = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))
        q = q * torch.sign(torch.diagonal(r))
        if torch.linalg.det(q) < 0:
            q[:, 0] = -q[:, 0]
        out.append(q)
        t = float(torch.rand(1, generator=g)) * 8 - 4
        c, s = math.cos(t), math.sin(t)
        out.append(torch.tensor([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]], dtype=torch.float64))
    out.append(torch.eye(3, dtype=torch.float64))
    out.append(torch.tensor([[-0.0, 0.0, 1.0], [0.0, -1.0, -0.0], [1.0, 0.0, 0.0]], dtype=torch.float64))
    out.append(torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, -0.0], [0.0, 0.0, 1.0]], dtype=torch.float64))
    return out


@pytest.mark.parametrize("order", [4, 8])
def test_light_world_equals_base_steps(order):
    """`native.light_world` = (R @ Qᵀ by torch, `runtime.rotate_lighting`, ``.float()``) bit for bit over random,
    y-axis (zeros), identity and permutation rotations; None (the caller's steps) where R Q is no rotation."""
    _needs_lib()
    g = torch.Generator().manual_seed(order)
    n2 = order * order
    st = zn.light_setup(n2, 3, _LATLONG_QT, rt._lighting_zyz_tensors(order))
    assert st is not None
    for k, R in enumerate(_rotations(40, order)):
        c = torch.randn(n2, 3, generator=g, dtype=torch.float64)
        got = zn.light_world(st, c, tuple(R.reshape(-1).tolist()), rt.ROTATION_TOL)
        want = rt.rotate_lighting(c, R @ _LATLONG_QT).float()
        assert got is not None and got.dtype == torch.float32, k
        assert torch.equal(got, want) and torch.equal(torch.signbit(got), torch.signbit(want)), (k, R)
    c = torch.randn(n2, 3, generator=g, dtype=torch.float64)
    assert zn.light_world(st, c, (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0), 1e-7) is None
    assert zn.light_world(st, c, (1.01, 0.0, 0.0, 0.0, 1.01, 0.0, 0.0, 0.0, 1.01), 1e-7) is None
    assert zn.light_world(st, c.float(), (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), 1e-7) is None
    assert zn.light_world(st, c[:-1], (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0), 1e-7) is None


@pytest.mark.parametrize("kind", ["L", "E"])
@pytest.mark.parametrize("config", ["order8", "creature"])
def test_lighting_frames_equal_base_steps(config, kind, request, monkeypatch):
    """L / E sequences of both configurations: with `_light_world` = without it (``NATIVE_LIGHT`` off) bit for
    bit, image and lighting, and `_light_world` made every frame's lighting."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _needs_lib()
    model = request.getfixturevalue(config)
    made = []

    def spy(self, polar, flat, tw, data, _f=ZHShadow._light_world):
        out = _f(self, polar, flat, tw, data)
        made.append((self is fast, out is not None))
        return out
    monkeypatch.setattr(ZHShadow, "_light_world", spy)
    fast, slow = model.with_render_config(), model.with_render_config()
    # (zh42l: the steady order-8 frames' lighting made inside their one C call — `zh41l_light`, the function
    # `light_world` calls: test_zh42l — not by `_light_world`; off here, so that `_light_world` makes every frame's)
    fast.steady_fused = False
    frames = make_sequence(model.scene, kind, 5, seed=3)
    gb = make_gbuffer(model.scene, frames[0], 2)
    for i, f in enumerate(frames):
        a = fast.render(f, gb)
        monkeypatch.setattr(zn, "NATIVE_LIGHT", False)
        b = slow.render(f, gb)
        monkeypatch.setattr(zn, "NATIVE_LIGHT", True)
        assert torch.equal(fast._light[1], slow._light[1]), (kind, i)
        assert torch.equal(a, b), (kind, i, float((a - b).abs().max()))
    assert made and all(m == (True, True) for m in made if m[0]) and not any(m[1] for m in made if not m[0]), made
    assert sum(m[0] for m in made) == 5, made   # (one lighting a frame: E a new map, L a new rotation)


def test_relight_blocks_layout():
    """`native.relight_blocks`: tile k of region r is its columns [b0 + 64 kk, +64) of wf (zero past b1), t_s's
    alike where the region has one; no t_s anywhere: None."""
    g = torch.Generator().manual_seed(0)
    n2, spans = 16, [(0, 70), (70, 70), (70, 200)]
    wf = torch.randn(n2, 200, generator=g)
    t2 = torch.randn(n2, 130, generator=g)
    wb, tb = zn.relight_blocks(spans, wf, {2: ((70, 200), t2)})
    assert wb.shape == (2 + 3, n2, 64) and tb.shape == wb.shape
    assert torch.equal(wb[1, :, :6], wf[:, 64:70]) and not wb[1, :, 6:].any()
    assert torch.equal(wb[2], wf[:, 70:134]) and torch.equal(wb[4, :, :2], wf[:, 198:200]) and not wb[4, :, 2:].any()
    assert torch.equal(tb[3], t2[:, 64:128]) and torch.equal(tb[4, :, :2], t2[:, 128:130])
    assert zn.relight_blocks(spans, wf, {})[1] is None


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("clamp", [False, True])
@pytest.mark.parametrize("kind", ["L", "E"])
def test_blocked_relight_equals_zh39o(order8, kind, clamp, threads, monkeypatch):
    """Order-8 L / E sequences (with misses): the steady frames' `zh41l_relight` over the tiles = `zh39o_relight`
    over wf and t_s (``BLOCKED_RELIGHT_VERTEX`` off when the setup is made) bit for bit, at 1 and 2 threads; the
    tiles counted in `memory` (the difference of the two objects' ``relight_transfer``)."""
    from methods.core.threads import torch_threads
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence
    from testing.gbuffers import knock_out

    if zn._relightb_lib() is None or zn._relightv_lib() is None:
        pytest.skip("no C compiler")
    m = order8.with_render_config(clamp=clamp)
    fast, slow = m.with_render_config(), m.with_render_config()
    frames = make_sequence(order8.scene, kind, 5, seed=4)
    gb = knock_out(make_gbuffer(order8.scene, frames[0], 2), 13, 2)
    with torch_threads(threads):
        for i, f in enumerate(frames):
            a = fast.render(f, gb)
            monkeypatch.setattr(zn, "BLOCKED_RELIGHT_VERTEX", False)
            b = slow.render(f, gb)
            monkeypatch.setattr(zn, "BLOCKED_RELIGHT_VERTEX", True)
            assert torch.equal(a, b), (kind, i, float((a - b).abs().max()))
    assert isinstance(fast._steady[8][8], tuple) and not isinstance(slow._steady[8][8], tuple)
    wb, tb = fast._steady[8][8]
    extra = fast.memory()["relight_transfer"] - slow.memory()["relight_transfer"]
    assert extra == wb.numel() * 4 + (0 if tb is None else tb.numel() * 4) > 0


@pytest.mark.parametrize("clamp", [False, True])
@pytest.mark.parametrize("kind", ["L", "E"])
def test_steady_plane_operator_equals_tables(creature, kind, clamp, monkeypatch):
    """Paper configuration, L / E sequences: the steady frames' T¹(n0) and l ⊙ kd, l ⊙ ks by `native.plane_light`
    (G = Σ_k f_k A_k folded once) = `_table` + `runtime.diffuse_at` and torch's products (``steady_plane_operator``
    off) to float32 round-off: T within 1e-6 of its largest entry, the products bit for bit, the images within
    1e-6 of the largest pixel (measured: ≤ 2e-7 on the bench creature); the operator taken on every steady frame."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if zn._plane_light_lib() is None or zn._relight_pixels_lib() is None:
        pytest.skip("no C compiler")
    seen = []

    def spy(self, light, n0, regs, _f=ZHShadow._steady_plane_terms):
        out = _f(self, light, n0, regs)
        if out is not None:
            Tn, lds, lss = out
            Wd = self._table(light, self._light[0], 1.0, True)
            T0 = rt.diffuse_at(Wd, n0)
            assert float((Tn - T0).abs().max()) <= 1e-6 * float(T0.abs().max())
            k = 0
            for kd, ks, n_entries, spec in regs:
                for _ in range(n_entries):
                    assert torch.equal(lds[k], light * kd) and (lss[k] is None) == (not spec)
                    assert lss[k] is None or torch.equal(lss[k], light * ks)
                    k += 1
            assert k == len(lds) == len(lss)
        seen.append(out is not None)
        return out
    monkeypatch.setattr(ZHShadow, "_steady_plane_terms", spy)
    m = creature.with_render_config(clamp=clamp)
    fast, slow = m.with_render_config(), m.with_render_config()
    slow.steady_plane_operator = False
    frames = make_sequence(creature.scene, kind, 5, seed=5)
    gb = make_gbuffer(creature.scene, frames[0], 2)
    for i, f in enumerate(frames):
        a = fast.render(f, gb)
        b = slow.render(f, gb)
        assert fast.last_path == slow.last_path
        assert float((a - b).abs().max()) <= 1e-6 * float(b.abs().max()), (kind, i, float((a - b).abs().max()))
    assert seen.count(True) == 3 and fast.memory()["shade_tables"] > slow.memory()["shade_tables"], seen


def test_plane_operator_made_by_the_building_frame(creature, monkeypatch):
    """Paper configuration, a lighting-only sequence: the steady plane operator (`_plane_light_setup`) is made
    once, by the first lighting-only frame (the one that builds the transfer and records the steady state), not
    by the first steady frame after it (session 41: that frame read 1.5-1.6 ms against 0.75 for the next ones
    in the perf runs, doubling the cell's median); the steady frames take it (``_steady_plane_terms``)."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if zn._plane_light_lib() is None or zn._relight_pixels_lib() is None:
        pytest.skip("no C compiler")
    made, paths = [], []

    def spy(self, light, n0, regs, _f=ZHShadow._plane_light_setup):
        made.append(len(paths))   # the index of the frame that made it
        return _f(self, light, n0, regs)
    monkeypatch.setattr(ZHShadow, "_plane_light_setup", spy)
    m = creature.with_render_config()
    frames = make_sequence(creature.scene, "L", 5, seed=7)
    gb = make_gbuffer(creature.scene, frames[0], 2)
    for f in frames:
        m.render(f, gb)
        paths.append(m.last_path)
    assert paths[1:] == ["relight-planes"] * 4, paths
    assert made == [1], (made, paths)
    assert m._plane_light is not None and m._plane_light[0] is m._steady and m._plane_light[1] is not None


@pytest.mark.parametrize("kind", ["L", "E"])
def test_pixels_checked_once_equals_zh40l(creature, kind, monkeypatch):
    """Paper configuration: the steady setup's pass without the per-call pixel check (`zh41l_relight_pixels`, the
    kept pixels checked once by the setup) = zh40l's (``PIXELS_CHECKED_ONCE`` off) bit for bit, and taken."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if zn._once_relight_lib() is None or zn._blk_relight_lib() is None:
        pytest.skip("no C compiler")
    fast, slow = creature.with_render_config(), creature.with_render_config()
    frames = make_sequence(creature.scene, kind, 4, seed=6)
    gb = make_gbuffer(creature.scene, frames[0], 2)
    for i, f in enumerate(frames):
        a = fast.render(f, gb)
        monkeypatch.setattr(zn, "PIXELS_CHECKED_ONCE", False)
        b = slow.render(f, gb)
        monkeypatch.setattr(zn, "PIXELS_CHECKED_ONCE", True)
        assert torch.equal(a, b), (kind, i, float((a - b).abs().max()))
    assert fast._steady[8][0].__name__ == "zh41l_relight_pixels"
    assert slow._steady[8][0].__name__ == "zh40l_relight_pixels"


def test_pixels_checked_once_refuses_bad_pixels():
    """The setup's check (`_pixels_ascending_inside`) = zh40l's per-call one: an index out of the image, negative or
    out of order is refused (then zh40l's pass, which reports it: the run gives None)."""
    assert zn._pixels_ascending_inside(torch.tensor([0, 0, 3, 9]), 10)
    assert zn._pixels_ascending_inside(torch.zeros(0, dtype=torch.int64), 10)
    assert not zn._pixels_ascending_inside(torch.tensor([0, 3, 10]), 10)
    assert not zn._pixels_ascending_inside(torch.tensor([-1, 3, 4]), 10)
    assert not zn._pixels_ascending_inside(torch.tensor([0, 4, 3]), 10)
    if zn._once_relight_lib() is None or zn._blk_relight_lib() is None:
        pytest.skip("no C compiler")
    n, S2, n2, Q = 8, 4, 4, 5
    face = torch.full((n, S2), -1, dtype=torch.int32)
    bary = torch.zeros(2, n, S2)
    v, corners, creg = torch.zeros(3, n2), torch.tensor([0, 1, 2]), torch.zeros(3, dtype=torch.int64)
    T, kd = torch.zeros(n2, 3), torch.ones(1, 3)
    td = torch.rand(n2, Q)
    ld = torch.rand(n2, 3)
    for pix, ok in ((torch.tensor([0, 1, 1, 5, 7]), True), (torch.tensor([0, 1, 1, 5, 8]), False),
                    (torch.tensor([0, 2, 1, 5, 7]), False)):
        st = zn.relight_pixels_setup(face, bary, False, [(td, None, ld, None, pix)], 0.25, (v, corners, creg, T, kd),
                                     blocked=True)
        assert st is not None
        assert st[0].__name__ == ("zh41l_relight_pixels" if ok else "zh40l_relight_pixels")
        out = zn.relight_pixels_run(st, [ld], [None], T)
        assert (out is not None) == ok
