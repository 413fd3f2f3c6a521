"""``methods.ptt.native_fit`` (session 41, pt41): a VB frame's run-time fit of every region's material in one
C call and the region tables' a_r by MKL's sgemm with the einsum's arguments — the same bits as the torch
paths they replace (which stay the fallback and the oracle)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from methods.ptt import fast as _fast
from methods.ptt import native_fit as nf
from methods.ptt import transport as tp
from scenes.materials import BlinnPhong, CookTorrance, Lambert, Phong, TorranceSparrow
from scenes.sequences import perturb_material

pytestmark = pytest.mark.skipif(not nf.available(), reason="no C compiler (native_fit off)")

MATS = [BlinnPhong(kd=(0.7, 0.68, 0.62), ks=0.25, s=60.0), CookTorrance(kd=(0.06, 0.05, 0.05), ks=0.6, m=0.25, F0=0.04),
        Phong(kd=(0.45, 0.3, 0.18), ks=0.1, s=10.0), Lambert(kd=(0.5, 0.55, 0.45))]


@pytest.fixture(scope="module")
def basis():
    b = tp.scene_basis(MATS)
    b.prepare()
    return b


def _torch_rows(b, mats, monkeypatch):
    """torch.tensor(coords_rows) of each material by the torch ops (FAST_FIT off), under one thread as
    `PTT.coords` runs them."""
    from methods.core.threads import torch_threads

    monkeypatch.setattr(nf, "FAST_FIT", False)
    with torch_threads(1):
        out = torch.tensor([b.coords_rows(m) for m in mats], dtype=torch.float32)
        ref = torch.stack([b.coords(m).float() for m in mats])
    monkeypatch.setattr(nf, "FAST_FIT", True)
    assert torch.equal(out, ref)
    return out


@pytest.mark.parametrize("threads", [1, 2])
def test_fit_materials_are_the_torch_fit_bit_for_bit(basis, threads, monkeypatch):
    """`fit_materials` (one C call for a frame's materials: Sleef pow / VML exp / MKL dgemv as the torch
    ops call them, the materials dealt to nt threads) equals coords_rows' torch ops and `coords`, float32
    bit for bit, for perturbed materials of every family and Lambert, at any nt and torch thread count;
    and `project` (coords_rows' single-material C call) gives project_family's float64 values exactly."""
    from methods.ptt.lobe_grid import FAMILIES

    rng = np.random.default_rng(11)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for it in range(12):
            mats = [perturb_material(x, rng) for x in MATS]
            mats = mats[it % 4:] + mats[:it % 4]  # every family in every slot and thread
            want = _torch_rows(basis, mats, monkeypatch)
            for nt in (1, 2, 3, 5):
                got = nf.fit_materials(basis, mats, nt)
                assert got is not None and got.dtype == torch.float32 and got.shape == want.shape
                assert torch.equal(got, want), (nt, mats)
            grid, A, _ = basis.prepare()
            for m in mats:
                fam = FAMILIES.get(type(m))
                if fam is None:
                    continue
                key = tp._lobe_key(m)[1]
                c_vals = nf.project(fam, grid._groups(fam, A), key)
                assert c_vals is not None
                assert c_vals == grid.project_family(fam, A, *key).tolist(), m
    finally:
        torch.set_num_threads(old)


def test_fit_materials_declines_what_it_does_not_fit(basis, monkeypatch):
    """None (the caller's per-material path) for a basis lobe's own material (coords_rows' exact rows),
    a family it does not evaluate, an exponent ATen's pow specialises, a basis without the diffuse
    function; and `PTT.coords`' H is the per-material one either way."""
    rng = np.random.default_rng(3)
    ok = [perturb_material(x, rng) for x in MATS]
    assert nf.fit_materials(basis, ok, 2) is not None
    assert nf.fit_materials(basis, ok[:1] + [MATS[1]], 2) is None  # MATS[1]: a basis lobe itself
    assert nf.fit_materials(basis, ok + [TorranceSparrow()], 2) is None
    assert nf.fit_materials(basis, [dataclasses.replace(ok[0], s=2.0)], 1) is None
    assert nf.fit_materials(tp.LobeBasis(basis.lobes, diffuse=False), ok, 1) is None
    monkeypatch.setattr(nf, "FAST_FIT", False)
    assert nf.fit_materials(basis, ok, 1) is None and not nf.available()


@pytest.mark.parametrize("R,P,n,L", [(3, 4, 32, 4), (2, 2, 32, 4), (1, 4, 32, 4), (4, 3, 16, 4), (6, 5, 32, 3),
                                     (2, 3, 5, 7)])
def test_ar_table_is_the_einsum_bit_for_bit(R, P, n, L):
    """`ar_table` (MKL's sgemm with the einsum's arguments, laid out as its reshape) equals
    ``einsum("rpc,pnl->rnlc").reshape`` bit for bit, written into a given table of its shape; at torch 1
    and 2 threads (MKL set to one thread inside the call)."""
    g = torch.Generator().manual_seed(R * 100 + P * 10 + n + L)
    old = torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            H, la = torch.randn(R, P, 3, generator=g), torch.randn(P, n, L, generator=g)
            from methods.core.threads import torch_threads

            with torch_threads(1):
                want = torch.einsum("rpc,pnl->rnlc", H, la).reshape(R * n, L * 3)
            got = nf.ar_table(H, la)
            assert got is not None and torch.equal(got, want)
            prev = torch.full_like(want, float("nan"))
            assert nf.ar_table(H, la, prev) is prev and torch.equal(prev, want)
    finally:
        torch.set_num_threads(old)


def test_region_tables_without_the_threads_switch_are_the_same(monkeypatch):
    """`fast.region_tables(..., one_thread=True)` (no ``torch_threads(1)`` around it: native W_r on nt
    threads, a_r by `ar_table`; any other path under one thread inside) equals the call under
    ``torch_threads(1)``, with and without the native loops."""
    from methods.core.threads import torch_threads

    g = torch.Generator().manual_seed(5)
    R, P, K, T = 3, 4, 8, 12
    H, W_tab, lobe_a = torch.rand(R, P, 3, generator=g), torch.randn(P * K, T, T, generator=g), torch.rand(P, 9, 4, generator=g)
    W_rows = _fast.view_table_rows(W_tab, K)
    with torch_threads(1):
        want = _fast.region_tables(H, W_tab, K, lobe_a, W_rows)
    for native in (True, False):
        monkeypatch.setattr(_fast, "USE_NATIVE", native)
        for nt in (1, 2):
            got = _fast.region_tables(H, W_tab, K, lobe_a, W_rows, nt=nt, one_thread=True)
            assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
            got = _fast.region_tables(H, W_tab, K, None, W_rows, nt=nt, one_thread=True)
            assert torch.equal(got[0], want[0]) and got[1] is None


def test_vb_frames_with_the_batched_fit_are_the_same_images(monkeypatch):
    """Chess (test size) VB frames with FIT_BATCH (the batched fit and no threads switches) render the
    images of FIT_BATCH off bit for bit, and the same H."""
    from methods.ptt import method as _method
    from methods.ptt.method import PTT
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    scene = get_scene("chess", "test")
    m = PTT(n_wi=4, brdf_grid=8, brdf_table=16, cube_res=8, n_L=16, rays=16, lobe_theta=8, lobe_fit_samples=256,
            lobe_vis_res=4, lobe_vis_samples=64, env_res=16, bounces=0)
    m.precompute(scene)
    frames = make_sequence(scene, "VB", n_frames=4, seed=9)
    gbs = [make_gbuffer(scene, f, 1) for f in frames]
    calls = {"fit": 0, "ar": 0}
    fit, ar = nf.fit_materials, nf.ar_table

    def spy_fit(*a, **k):
        r = fit(*a, **k)
        calls["fit"] += r is not None
        return r

    def spy_ar(*a, **k):
        r = ar(*a, **k)
        calls["ar"] += r is not None
        return r

    monkeypatch.setattr(nf, "fit_materials", spy_fit)
    monkeypatch.setattr(nf, "ar_table", spy_ar)
    out = {}
    for on in (True, False):
        monkeypatch.setattr(_method, "FIT_BATCH", on)
        m._reset_cache()
        out[on] = [(m.render(f, g), m._f_H.clone()) for f, g in zip(frames, gbs)]
        if on:  # the VB frames after the first (the scene's own materials: basis lobes) took the C calls
            assert calls["fit"] == len(frames) - 1 and calls["ar"] >= len(frames) - 1
    for (a, ha), (b, hb) in zip(out[True], out[False]):
        assert torch.equal(ha, hb) and torch.equal(a, b)


def test_the_library_follows_the_compile_switch_at_each_call(monkeypatch):
    """Asked for while PRTBENCH_COMPILE=0 the calls decline (the torch paths run); back on, they run:
    no None kept for the process (``tests/methods/test_native_off_switch.py``)."""
    H, la = torch.rand(3, 4, 3), torch.rand(4, 32, 4)
    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    assert nf._library() is None and not nf.available() and nf.ar_table(H, la) is None
    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    assert nf._library() is not None and nf.available() and nf.ar_table(H, la) is not None
