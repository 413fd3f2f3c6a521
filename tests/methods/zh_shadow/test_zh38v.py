"""Session 38 (zh38v): the lighting's ZYZ rotation in C (`runtime.NATIVE_ROTATE`, `native.rotate_lighting`)
against `runtime.rotate_lighting`'s numpy steps (the oracle): float64 round-off, the same fallbacks."""
from __future__ import annotations

import math

import pytest
import torch

from methods.zh_shadow import runtime as rt

def _rotations(g):
    """Random proper rotations, and the ZYZ angles' edge cases: the identity (sin b = 0, a arbitrary), a half turn
    about z, b = π (R e_z = −e_z), a rotation about y alone (the E probes' frames)."""
    out = [torch.eye(3, dtype=torch.float64), torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64)),
           torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))]
    t = 0.7
    out.append(torch.tensor([[math.cos(t), 0, math.sin(t)], [0, 1, 0], [-math.sin(t), 0, math.cos(t)]],
                            dtype=torch.float64))
    for _ in range(12):
        Q, _ = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=g))
        if torch.det(Q) < 0:
            Q[:, 0] = -Q[:, 0]
        out.append(Q)
    return out


def _skip_unless_native():
    from methods.zh_shadow import native as zn

    if zn._rotate_lib() is None:
        pytest.skip("the C rotation does not build here")


@pytest.mark.parametrize("order", (1, 2, 4, 8))
def test_native_rotation_equals_numpy_steps(monkeypatch, order):
    """`rotate_lighting` by the C calls = by its numpy steps to float64 round-off (1e-14 relative) for rotations
    with every ZYZ edge case and several columns; a matrix that is not a rotation to `ROTATION_TOL` (scaled,
    improper) takes `rotate_sampled` on both: the same values."""
    _skip_unless_native()
    g = torch.Generator().manual_seed(38 + order)
    n2 = order * order
    for R in _rotations(g):
        for C in (1, 3):
            c = torch.randn(n2, C, dtype=torch.float64, generator=g)
            monkeypatch.setattr(rt, "NATIVE_ROTATE", True)
            a = rt.rotate_lighting(c, R)
            monkeypatch.setattr(rt, "NATIVE_ROTATE", False)
            b = rt.rotate_lighting(c, R)
            assert a.shape == b.shape == (n2, C) and a.dtype == b.dtype == torch.float64
            assert (a - b).abs().max().item() <= 1e-14 * b.abs().max().item(), (order, R)
    for R in (_rotations(g)[5] * 1.001, _rotations(g)[6] @ torch.diag(torch.tensor([1.0, 1.0, -1.0],
                                                                                 dtype=torch.float64))):
        c = torch.randn(n2, 3, dtype=torch.float64, generator=g)
        monkeypatch.setattr(rt, "NATIVE_ROTATE", True)
        a = rt.rotate_lighting(c, R)
        monkeypatch.setattr(rt, "NATIVE_ROTATE", False)
        assert torch.equal(a, rt.rotate_lighting(c, R))


@pytest.mark.parametrize("kind", ("L", "E", "VL"))
def test_native_rotation_frames(creature, monkeypatch, kind):
    """Lighting frames with the C rotation = with the numpy steps: the world-space lighting to float32
    round-off and the image to float32 round-off of its peak."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _skip_unless_native()
    fast, ref = creature.with_render_config(), creature.with_render_config()
    for fr in make_sequence(creature.scene, kind, 4, seed=13):
        gb = make_gbuffer(creature.scene, fr, 2)
        monkeypatch.setattr(rt, "NATIVE_ROTATE", True)
        a, la = fast.render(fr, gb), fast._light[1].clone()
        monkeypatch.setattr(rt, "NATIVE_ROTATE", False)
        b, lb = ref.render(fr, gb), ref._light[1].clone()
        assert (la - lb).abs().max().item() <= 4e-7 * lb.abs().max().item(), (kind, fr.index)
        assert (a - b).abs().max().item() <= 1e-6 * max(b.abs().max().item(), 1e-30), (kind, fr.index)


def test_vtable_rows4_equals_rows():
    """`native.vertex_table` four rows a load of W (`VTABLE_ROWS4`, `zh38v_vtable`) = row by row (`zh34p_vtable`)
    bit for bit: every row or referenced ids, regions changing inside a block of four, a row whose region is out
    of range (zeros), column counts that are and are not multiples of 16, at 1 and 2 threads; an id out of range:
    None from both."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn

    if zn._vtable4_lib() is None or zn._vtable_lib() is None:
        pytest.skip("the table pass does not build here")
    g = torch.Generator().manual_seed(381)
    try:
        for N, n2, C, R in ((2600, 16, 240, 2), (1000, 16, 93, 3), (517, 64, 40, 1), (50, 9, 8, 2)):
            v = torch.randn(N, n2, generator=g)
            vreg = torch.randint(0, R, (N,), generator=g)
            vreg[: N // 2] = vreg[: N // 2].sort().values      # runs of one region, and a mixed half
            vreg[N // 3] = R + 1
            W = torch.randn(R, n2, C, generator=g)
            for idx in (None, torch.randint(0, N, (N // 3,), generator=g).unique()):
                outs = []
                for rows4, nt in ((False, 1), (True, 1), (True, 2)):
                    zn.VTABLE_ROWS4 = rows4
                    with torch_threads(nt):
                        outs.append(zn.vertex_table(v, vreg, W, idx))
                assert torch.equal(outs[1], outs[0]) and torch.equal(outs[2], outs[0]), (N, n2, C, R, idx is None)
            bad = torch.tensor([0, 1, 2, N], dtype=torch.int64)
            for rows4 in (True, False):
                zn.VTABLE_ROWS4 = rows4
                assert zn.vertex_table(v, vreg, W, bad) is None
    finally:
        zn.VTABLE_ROWS4 = True


@pytest.mark.parametrize("kind", ("VL", "VB", "V"))
def test_plane_term_spans_equal_every_row(creature, kind):
    """`_fused_planes` with the plane term of the regions without a specular term alone (`plane_term_spans`)
    = with every vertex's (off), bit for bit, on the same fused path; the rows it makes are the others' rows
    bit for bit and the specular region's rows are not made (0)."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    fast, full = creature.with_render_config(), creature.with_render_config()
    full.plane_term_spans = False
    ran = False
    for fr in make_sequence(creature.scene, kind, 4, seed=14):
        gb = make_gbuffer(creature.scene, fr, 2)
        a, b = fast.render(fr, gb), full.render(fr, gb)
        assert fast.last_path == full.last_path and getattr(fast, "last_fused", False) == getattr(full, "last_fused", False)
        assert torch.equal(a, b), (kind, fr.index, (a - b).abs().max().item())
        if getattr(fast, "last_fused", False) and fast._plane_u0[0][-1] is not None:
            ran = True
            spans = fast._region_spans(fast.scene.geometry().vertex_region, len(fast.scene.regions))
            only = fast._plane_u0[0][-1]
            for (a0, a1), on in zip(spans, only):
                if on:
                    assert torch.equal(fast._plane_u[3][a0:a1], full._plane_u[3][a0:a1])
                else:
                    assert not fast._plane_u0[3][a0:a1].any()
    assert ran, "the plane term of the diffuse regions alone never ran"


def test_native_region_tables_equal_torch():
    """`native.region_tables` = `runtime.region_tables`(…, out=) bit for bit: regions with and without a specular
    table (its columns 0 there), none specular, every cell of ``out`` written (a poisoned buffer)."""
    from methods.zh_shadow import native as zn

    if zn._rtables_lib() is None:
        pytest.skip("the C pass does not build here")
    g = torch.Generator().manual_seed(383)
    for n2, Kd, Ks in ((16, 31, 49), (9, 5, 7), (64, 3, 2)):
        Wd, Ws, Ws2 = (torch.randn(k, 3 * n2, generator=g) for k in (Kd, Ks, Ks))
        rnd = lambda: torch.rand(3, generator=g)   # noqa: E731
        for tabs in ([(rnd(), rnd(), Wd, Ws), (rnd(), torch.zeros(3), Wd, None), (rnd(), rnd(), Wd, Ws2)],
                     [(rnd(), torch.zeros(3), Wd, None)] * 2, [(rnd(), rnd(), Wd, Ws)]):
            K = Kd + (Ks if any(t[3] is not None for t in tabs) else 0)
            a = torch.full((len(tabs), n2, 3 * K), float("nan"))
            b = torch.full((len(tabs), n2, 3 * K), float("nan"))
            assert zn.region_tables(tabs, n2, a) == rt.region_tables(tabs, n2, "cpu", torch.float32, out=b)[0] == K
            assert torch.equal(a, b)


@pytest.mark.parametrize("kind", ("VL", "VBL"))
def test_native_region_tables_frames(creature, kind):
    """Frames with `native_region_tables` = without it (`runtime.region_tables`), bit for bit."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    fast, ref = creature.with_render_config(), creature.with_render_config()
    ref.native_region_tables = False
    for fr in make_sequence(creature.scene, kind, 4, seed=15):
        gb = make_gbuffer(creature.scene, fr, 2)
        a, b = fast.render(fr, gb), ref.render(fr, gb)
        assert fast.last_path == ref.last_path
        assert torch.equal(a, b), (kind, fr.index, (a - b).abs().max().item())
