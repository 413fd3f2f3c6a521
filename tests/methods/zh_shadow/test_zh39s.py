"""Session 39 (zh39s): `_fused_planes`' one-thread helpers as threaded passes (`native_threaded`: `screen8`, and
`rest_screen` with `referenced_lut` in one walk, `ZHShadow.threaded_helpers`) against the serial helpers of
`native` (the oracle): the same counts, vertices and lut at 1, 2 and 3 threads (ranges split where the ranks,
the every-16th screen rows and the 8 candidates cross them), the same failures, and frames equal bit for bit."""
from __future__ import annotations

import pytest
import torch

from methods.core.threads import torch_threads
from methods.zh_shadow import native as zn
from methods.zh_shadow import native_threaded as z39

def _skip_unless_native():
    if z39._lib() is None or zn._fused_lib() is None:
        pytest.skip("the C helpers do not build here")


def _masks(g, P):
    """Plane masks: random, long runs of plane samples (the walks' skip of 8), a few rest samples, none."""
    r = torch.rand(P, generator=g) < 0.85
    runs = torch.zeros(P, dtype=torch.bool)
    for a in range(0, P, 977):
        runs[a:a + 900] = True
    few = torch.ones(P, dtype=torch.bool)
    few[torch.randint(0, P, (11,), generator=g)] = False
    return [r, runs, few, torch.ones(P, dtype=torch.bool), torch.zeros(P, dtype=torch.bool)]


@pytest.mark.parametrize("P", (4999, 65536 + 13))
def test_rest_lut_equals_serial_helpers(monkeypatch, P):
    """`native_threaded.rest_lut` = (`native.rest_screen`, `native.referenced_lut`) for random and run-length masks,
    with and without hits, the screen and the lut each on and off, a wrong count m (None), a corner outside
    [0, N) and a face outside [0, M) (no lut), at 1, 2 and 3 threads."""
    _skip_unless_native()
    monkeypatch.setattr(z39, "MIN_SAMPLES_PER_THREAD", 1000)
    g = torch.Generator().manual_seed(39 + P)
    nrm = torch.randn(P, 3, generator=g)
    nrm[::3] = nrm[7]
    nrm[1::5] = nrm[11]
    nrm[2::7] = nrm[5]
    F32 = torch.randint(0, 300, (200, 3), generator=g, dtype=torch.int32) * 2
    face = torch.randint(0, 200, (P,), generator=g)
    hit = torch.rand(P, generator=g) < 0.9
    bad_face = face.clone()
    bad_face[P // 2 + 1] = 200
    for mask in _masks(g, P):
        m = int((~mask).sum())
        for nt in (1, 2, 3):
            with torch_threads(nt):
                for h in (None, hit):
                    want_l = zn.referenced_lut(mask, h, face, F32, 700)
                    for mm in (m, m + 1, m - 1):
                        want_s = zn.rest_screen(mask, nrm, mm)
                        for screen, lut in ((True, True), (True, False), (False, True)):
                            rs, rl = z39.rest_lut(mask, h, nrm, face, F32, 700, mm, screen, lut)
                            assert rs == (want_s if screen else None), (nt, mm, screen, lut)
                            if not lut:
                                assert rl is None
                            else:
                                assert rl is not None and want_l is not None
                                assert torch.equal(rl[0], want_l[0]) and torch.equal(rl[1], want_l[1]), (nt, mm)
                    if m > 0:   # (a corner / a face out of range: no lut, the screen still its own)
                        rs, rl = z39.rest_lut(mask, h, nrm, face, F32, 500, m, True, True)
                        assert rl is None and zn.referenced_lut(mask, h, face, F32, 500) is None
                        assert rs == zn.rest_screen(mask, nrm, m)
                        rs, rl = z39.rest_lut(mask, h, nrm, bad_face, F32, 700, m, True, True)
                        want = zn.referenced_lut(mask, h, bad_face, F32, 700)
                        assert (rl is None) == (want is None)


def test_screen8_equals_serial(monkeypatch):
    """`native_threaded.screen8` = `native.screen8` on strided and contiguous rows, counts off the 16-point grid and
    short ones, at 1, 2 and 3 threads."""
    _skip_unless_native()
    monkeypatch.setattr(z39, "MIN_SAMPLES_PER_THREAD", 100)
    g = torch.Generator().manual_seed(9)
    nrm = torch.randn(20011, 3, generator=g)
    nrm[::3] = nrm[7]
    nrm[1::5] = nrm[11]
    nrm[::16][::7] = nrm[0]
    for nt in (1, 2, 3):
        with torch_threads(nt):
            for cur in (nrm.T, nrm.T.contiguous(), nrm[:37].T, nrm[:5].T, nrm[:16 * 97 + 1].T):
                assert z39.screen8(cur) == zn.screen8(cur), (nt, cur.shape)


@pytest.mark.parametrize("kind", ("V", "VB", "VL", "P"))
def test_threaded_helpers_frames(creature, monkeypatch, kind):
    """Plane frames with `threaded_helpers` = without (the serial helpers, the oracle), bit for bit, with the
    same counts, at 1 and 2 threads, with a few misses: a non-view frame takes its referenced vertices from `rest_lut` (forced
    here: every non-view frame builds its own table) and the serial `referenced_lut` is not called."""
    _skip_unless_native()
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if not zn.fused_available(6, True, True):
        pytest.skip("the fused pass is not available here")
    monkeypatch.setattr(z39, "MIN_SAMPLES_PER_THREAD", 1)
    monkeypatch.setattr(zn, "MIN_PIXELS_PER_THREAD", 1)
    monkeypatch.setattr("methods.zh_shadow.method.VERTEX_TABLE_POINTS", 0.0)
    calls = {"rest_lut": 0, "lut_from_rest": 0, "referenced_lut": 0}
    orig_rl, orig_ref = z39.rest_lut, zn.referenced_lut

    def rl(*a):
        calls["rest_lut"] += 1
        out = orig_rl(*a)
        calls["lut_from_rest"] += int(out is not None and out[1] is not None)
        return out

    def ref(*a):
        calls["referenced_lut"] += 1
        return orig_ref(*a)
    monkeypatch.setattr(z39, "rest_lut", rl)
    monkeypatch.setattr(zn, "referenced_lut", ref)
    from testing.gbuffers import knock_out

    for nt, misses in ((1, False), (2, False), (2, True)):
        fast, slow = creature.with_render_config(), creature.with_render_config()
        slow.threaded_helpers = False
        fast.one_split = False   # (these helpers, not the one-call split that replaces them: test_zh44.py)
        for fr in make_sequence(creature.scene, kind, 4, seed=5):
            gb = make_gbuffer(creature.scene, fr, 2)
            if misses:   # (a few misses: the hits' vertices alone)
                gb = knock_out(gb, 397 + fr.index, 3 + fr.index)
                assert 0 < int((~gb.hit).sum()) <= 64
            before = dict(calls)
            with torch_threads(nt):
                a = fast.render(fr, gb)
            mid = dict(calls)
            with torch_threads(nt):
                b = slow.render(fr, gb)
            assert fast.last_path == slow.last_path == "planes" and fast.last_fused and slow.last_fused
            assert torch.equal(a, b), (kind, nt, fr.index, (a - b).abs().max().item())
            ca, cb = dict(fast._last_counts), dict(slow._last_counts)
            assert ca.pop("plane_vertices")() == cb.pop("plane_vertices")() and ca == cb
            if kind != "V" and fr.index > 0:   # its own table: the vertices from the threaded walk
                assert mid["lut_from_rest"] == before["lut_from_rest"] + 1
                assert mid["referenced_lut"] == before["referenced_lut"], (kind, fr.index)
                assert calls["referenced_lut"] == mid["referenced_lut"] + 1   # (the oracle's own)


def test_helpers_follow_the_compile_switch(monkeypatch):
    """With ``PRTBENCH_COMPILE=0`` the threaded helpers do not run (None: the caller's serial helpers, which
    then do not run either: the torch split); back on, they load (not cached while off, b541a75)."""
    from methods.core import native as core_native

    if core_native.compiler() is None:   # pragma: no cover - no C compiler here
        pytest.skip("no C compiler")
    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    mask = torch.ones(100, dtype=torch.bool)
    mask[3] = False
    nrm = torch.randn(100, 3)
    assert z39._lib() is None and z39.screen8(nrm.T) is None
    assert z39.rest_lut(mask, None, nrm, torch.zeros(100, dtype=torch.int64), torch.zeros(1, 3, dtype=torch.int32),
                        1, 1, True, True) is None
    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    assert z39._lib() is not None and z39.screen8(nrm.T) == zn.screen8(nrm.T)
