"""Session 42 (zh42l): a steady lighting-only order-8 / vertex-shaded frame by ONE C call (`native.steady_run`:
`zh41l_light`'s rotation of the kept projection — or of a new map's folded projection — then the relight's
blocks and the resolve's rows, `ZHShadow._steady_fused`), its setup made by the frame that records the steady
state. Oracles: ``steady_fused`` off (`_lighting`, then `native.relight_run`: session 41's path) and, for the
call, `light_world` and `relight_run` on the same setup — the same bits."""
from __future__ import annotations

import math

import pytest
import torch

from methods.core.sh import _LATLONG_QT
from methods.zh_shadow import native as zn
from methods.zh_shadow import runtime as rt


def _needs_lib():
    if zn._steady_lib() is None or zn._relightb_lib() is None:
        pytest.skip("no C compiler")


@pytest.mark.parametrize("clamp", [False, True])
@pytest.mark.parametrize("kind", ["L", "E"])
def test_steady_fused_equals_zh41l(order8, kind, clamp, monkeypatch):
    """Order-8 L / E sequences (with misses; at 1 and 2 threads): with the one call (``steady_fused``) = without it
    (`_lighting` + `relight_run`) bit for bit — image, the kept lighting and its key, the kept projection, the
    frame's counts — the call taking every steady frame (its lighting made inside it: a new rotation of the kept
    map, or a new map's projection), its setup made by the recording frame (frame 1), none by a steady frame."""
    from methods.core.threads import torch_threads
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence
    from testing.gbuffers import knock_out

    _needs_lib()
    made = []

    def spy(*a, _f=zn.steady_setup):
        made.append(a[0])
        return _f(*a)
    monkeypatch.setattr(zn, "steady_setup", spy)
    m = order8.with_render_config(clamp=clamp)
    fast, fast2, slow = m.with_render_config(), m.with_render_config(), m.with_render_config()
    slow.steady_fused = False
    frames = make_sequence(order8.scene, kind, 6, seed=5)
    gb = knock_out(make_gbuffer(order8.scene, frames[0], 2), 13, 2)
    paths = []
    for i, f in enumerate(frames):
        n_made = len(made)
        a = fast.render(f, gb)
        with torch_threads(2):
            a2 = fast2.render(f, gb)
        b = slow.render(f, gb)
        paths.append(fast.last_path)
        assert torch.equal(a, b), (kind, i, float((a - b).abs().max()))
        assert torch.equal(a, a2), (kind, i)
        assert fast._light[0] == slow._light[0] and torch.equal(fast._light[1], slow._light[1]), i
        assert fast._env_local[0] == slow._env_local[0] and torch.equal(fast._env_local[1], slow._env_local[1]), i
        assert fast._light[1] is not fast2._light[1]   # (a new tensor each frame: the kept one is not rewritten)
        ca, cb = fast.frame_cost(kind, gb.num_samples), slow.frame_cost(kind, gb.num_samples)
        assert (ca.bytes, ca.flops) == (cb.bytes, cb.flops), i
        if i >= 2:
            assert len(made) == n_made, i   # (no setup in a steady frame)
    assert paths[2:] == ["steady-fused"] * 4, paths
    assert len(made) == 2 and made[0] is fast._steady[8] and fast._steady_call[1] is not None
    assert fast.memory() == slow.memory()   # (the call keeps no copies)


def _synthetic(seed: int, R: int, Nc: int, n2: int = 64):
    """A relight setup of random data: two regions (the first with t_s), a packed resolve of R rows whose lengths run
    0-9 (rows longer than 4 in the tail CSR) over Nc + 1 compact columns (the last the zero row)."""
    g = torch.Generator().manual_seed(seed)
    spans = [(0, Nc // 3 * 2 + 1), (Nc // 3 * 2 + 1, Nc)]
    wf = torch.randn(n2, Nc, generator=g)
    ts = torch.randn(n2, spans[0][1], generator=g)
    lens = torch.randint(0, 10, (R,), generator=g)
    lens[::7] = 4
    crow = torch.zeros(R + 1, dtype=torch.int64)
    crow[1:] = lens.cumsum(0)
    col = torch.randint(0, Nc + 1, (int(crow[-1]),), generator=g)
    val = torch.randn(int(crow[-1]), generator=g)
    S = torch.sparse_csr_tensor(crow, col, val, (R, Nc + 1))
    packed = zn.csr_pack(S)
    rs = zn.relight_setup(spans, wf, {0: (spans[0], ts)}, packed)
    kd, ks = torch.rand(2, 3, generator=g), torch.rand(2, 3, generator=g)
    ks[1] = 0.0
    light = torch.randn(n2, 3, generator=g)
    return rs, kd, ks, light


@pytest.mark.parametrize("R", [1, 6, 4097])
def test_steady_run_equals_relight_run(R):
    """`steady_run` given the lighting = `relight_run` (two-region transfers, one with t_s; packed resolves of row
    lengths 0-9, tails included) at 1-3 threads, clamped or not: the same bits."""
    _needs_lib()
    for clamp in (False, True):
        rs, kd, ks, light = _synthetic(R, R, 300)
        st = zn.steady_setup(rs, kd, ks, clamp, _LATLONG_QT, rt._lighting_zyz_tensors(8))
        assert st is not None
        want = zn.relight_run(rs, light, kd, ks, clamp)
        for nt in (1, 2, 3):
            out = torch.full((R, 3), float("nan"))
            assert zn.steady_run(st, None, None, 0.0, light, out, nt)
            assert torch.equal(out, want), (R, nt, clamp, float((out - want).abs().max()))


def test_steady_run_rotation_equals_light_world():
    """`steady_run` with a rotation: its lighting = `light_world` (the base's steps' bits) over random, y-axis,
    identity and permutation rotations, and its image = `relight_run` of that lighting; R Q no rotation: False and
    neither array written."""
    from tests.methods.zh_shadow.test_zh41l import _rotations

    _needs_lib()
    rs, kd, ks, _ = _synthetic(3, 999, 200)
    tables = rt._lighting_zyz_tensors(8)
    st = zn.steady_setup(rs, kd, ks, True, _LATLONG_QT, tables)
    ls = zn.light_setup(64, 3, _LATLONG_QT, tables)
    g = torch.Generator().manual_seed(1)
    for k, R in enumerate(_rotations(12, 3)):
        c = torch.randn(64, 3, generator=g, dtype=torch.float64)
        flat = tuple(R.reshape(-1).tolist())
        light, out = torch.empty(64, 3), torch.empty(999, 3)
        assert zn.steady_run(st, flat, c, rt.ROTATION_TOL, light, out, 2), k
        want = zn.light_world(ls, c, flat, rt.ROTATION_TOL)
        assert torch.equal(light, want) and torch.equal(torch.signbit(light), torch.signbit(want)), k
        assert torch.equal(out, zn.relight_run(rs, want, kd, ks, True)), k
    light, out = torch.full((64, 3), 7.0), torch.full((999, 3), 7.0)
    assert not zn.steady_run(st, (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0), c, 1e-7, light, out, 1)
    assert bool((light == 7.0).all()) and bool((out == 7.0).all())


def test_steady_fused_refused_rotation_and_window(order8):
    """A steady frame whose map's rotation `light_world` refuses (R not a rotation to its tolerance) takes
    `_lighting`'s fallback and the call given that lighting — the image and lighting = the oracle's; a windowed
    configuration never makes the call's setup (the call reads the lighting unwindowed)."""
    import dataclasses

    from references.gbuffer import make_gbuffer
    from scenes.envmap import EnvMap
    from scenes.sequences import make_sequence

    _needs_lib()
    frames = make_sequence(order8.scene, "L", 4, seed=2)
    gb = make_gbuffer(order8.scene, frames[0], 2)
    fast, slow = order8.with_render_config(), order8.with_render_config()
    slow.steady_fused = False
    env = frames[3].envmap
    bad = EnvMap.__new__(EnvMap)
    bad.__dict__.update(env.__dict__)
    bad.to_world = env.to_world * (1.0 + 1e-5)   # (|R Rᵀ − I| = 2e-5 > ROTATION_TOL)
    seq = [*frames[:3], dataclasses.replace(frames[3], envmap=bad)]
    for i, f in enumerate(seq):
        a, b = fast.render(f, gb), slow.render(f, gb)
        assert torch.equal(a, b), i
        assert fast._light[0] == slow._light[0] and torch.equal(fast._light[1], slow._light[1]), i
    assert fast.last_path == "steady-fused-lit"
    w = order8.with_render_config(window="hanning")
    for f in frames:
        w.render(f, gb)
    assert w._steady is not None and w._steady_call is not None and w._steady_call[1] is None


def test_flat_values_equal_reshape_tolist():
    """`method._flat_values` (`_lighting`'s key of ``to_world``) = ``tuple(t.reshape(-1).tolist())`` for 3×3, 1-D,
    3-D, 0-d, empty and non-contiguous tensors."""
    from methods.zh_shadow.method import _flat_values

    g = torch.Generator().manual_seed(0)
    for t in (torch.randn(3, 3, dtype=torch.float64, generator=g), torch.randn(9, generator=g),
              torch.randn(2, 3, 4, generator=g), torch.tensor(2.0), torch.zeros(0, 3), torch.zeros(3, 0),
              torch.randn(3, 3, generator=g).T, torch.tensor([[-0.0, 1.0, 0.0], [0.0, 0.0, 1.0], [1.0, 0.0, -0.0]])):
        got, want = _flat_values(t), tuple(t.reshape(-1).tolist())
        assert got == want and [math.copysign(1, x) for x in got] == [math.copysign(1, x) for x in want], t.shape
