"""The Gouraud resolve (``methods.core.gouraud``): the fused pass equals the G-buffer's own
interpolate + resolve, compiled and eager, for every sub-pixel count, with misses."""
from __future__ import annotations

import pytest
import torch

from methods.core import gouraud
from scenes.frame import GBuffer


def _case(H: int, W: int, S: int, N: int = 50, M: int = 80, seed: int = 0):
    g = torch.Generator().manual_seed(seed)
    P = H * W * S * S
    values = torch.rand(N, 3, generator=g)
    F = torch.randint(0, N, (M, 3), generator=g)
    face = torch.randint(-1, M, (P,), generator=g)
    face[: P // 7] = -1                                                   # a run of misses
    hit = face >= 0
    uv = torch.rand(P, 2, generator=g) * 0.5
    gb = GBuffer(H, W, S, hit=hit, face=face, bary=uv, position=torch.zeros(P, 3), normal=torch.zeros(P, 3),
                 wo=torch.zeros(P, 3), region=torch.where(hit, 0, -1), coverage=torch.zeros(H, W, dtype=torch.bool))
    return values, F, gb


@pytest.mark.parametrize("S", [1, 2, 3])
@pytest.mark.parametrize("compile_", ["1", "0"])
def test_resolve_equals_gbuffer_interpolate_and_resolve(S, compile_, monkeypatch):
    monkeypatch.setenv("PRTBENCH_COMPILE", compile_)
    values, F, gb = _case(5, 7, S)
    want = gb.resolve(gb.interpolate(values, F))
    fv = F.T.contiguous().to(torch.int32)
    ref = gouraud.resolve_reference(values, fv, gb.face, gb.bary, gb.hit, 5, 7, S)
    got = gouraud.resolve(values, fv, gb.face, gb.bary, gb.hit, 5, 7, S)
    assert got.shape == (5, 7, 3)
    assert (ref - want).abs().max() <= 1e-6
    assert (got - want).abs().max() <= 1e-6
    assert bool((got[0, 0] == 0).all())                                  # a pixel of misses is black


@pytest.mark.parametrize("block_max", [None, 1 << 12])
def test_resolve_many_blocks_and_table_sizes(block_max, monkeypatch):
    """One block for the image (its pixel count rounded up to a power of two: padding), more pixels
    than one block (``RESOLVE_BLOCK_MAX`` lowered: several blocks, the last padded) and another table
    size (no stale kernel)."""
    if block_max is not None:
        monkeypatch.setattr(gouraud, "RESOLVE_BLOCK_MAX", block_max)
    for N in (50, 77):
        values, F, gb = _case(200, 190, 1, N=N, seed=N)
        fv = F.T.contiguous().to(torch.int32)
        want = gb.resolve(gb.interpolate(values, F))
        assert (gouraud.resolve(values, fv, gb.face, gb.bary, gb.hit, 200, 190, 1) - want).abs().max() <= 1e-6


def test_resolve_checks_the_sample_count():
    values, F, gb = _case(5, 7, 2)
    with pytest.raises(ValueError):
        gouraud.resolve(values, F.T.contiguous(), gb.face, gb.bary, gb.hit, 5, 6, 2)


def test_resolve_checks_the_index_ranges():
    """The compiled kernel's loads are unchecked (`gouraud._NO_ASSERT`): a G-buffer face past the
    corner table, a corner row past the values, or a face below −1 is a ValueError, not a read out
    of bounds."""
    values, F, gb = _case(5, 7, 2)
    fv = F.T.contiguous().to(torch.int32)
    gouraud.resolve(values, fv, gb.face, gb.bary, gb.hit, 5, 7, 2)           # in range: fine
    with pytest.raises(ValueError, match="another mesh"):
        gouraud.resolve(values, fv[:, :10], gb.face, gb.bary, gb.hit, 5, 7, 2)  # faces up to 79, 10 in the table
    with pytest.raises(ValueError, match="another mesh"):
        gouraud.resolve(values[:3], fv, gb.face, gb.bary, gb.hit, 5, 7, 2)     # rows up to 49, 3 values
    bad = gb.face.clone()
    bad[-1] = -2
    with pytest.raises(ValueError, match="another mesh"):
        gouraud.resolve(values, fv, bad, gb.bary, gb.hit, 5, 7, 2)
    # a transposed view (ZH passes F.T; its range is read over the contiguous F): checked the same
    Fv = F.T
    assert not Fv.is_contiguous()
    assert torch.equal(gouraud.resolve(values, Fv, gb.face, gb.bary, gb.hit, 5, 7, 2),
                       gouraud.resolve(values, fv, gb.face, gb.bary, gb.hit, 5, 7, 2))
    with pytest.raises(ValueError, match="another mesh"):
        gouraud.resolve(values[:3], Fv, gb.face, gb.bary, gb.hit, 5, 7, 2)
    neg = F.clone()
    neg[4, 1] = -1
    with pytest.raises(ValueError, match="another mesh"):
        gouraud.resolve(values, neg.T, gb.face, gb.bary, gb.hit, 5, 7, 2)


@pytest.mark.parametrize("S", [1, 2, 3])
def test_resolve_matrix_equals_resolve(S):
    """`resolve_matrix` @ values is the image of `resolve` (to float32 round-off: a pixel's weights
    of one vertex are summed first), misses and all, for new values on the same G-buffer."""
    values, F, gb = _case(6, 5, S)
    fv = F.T.contiguous().to(torch.int32)
    M = gouraud.resolve_matrix(fv, gb.face, gb.bary, gb.hit, 6, 5, S, values.shape[0])
    assert M.shape == (30, values.shape[0])
    for seed in (1, 2):
        vals = torch.rand(values.shape, generator=torch.Generator().manual_seed(seed)) - 0.3
        want = gouraud.resolve_reference(vals, fv, gb.face, gb.bary, gb.hit, 6, 5, S)
        assert ((M @ vals).view(6, 5, 3) - want).abs().max() <= 1e-6


def _native_or_skip():
    from methods.core import native

    if native.compiler() is None or gouraud._native() is None:
        pytest.skip("no C compiler: the compiled kernel is the only path")


@pytest.mark.parametrize("S", [1, 2, 3])
def test_native_loop_equals_the_compiled_kernel_bit_for_bit(S, monkeypatch):
    """The C loop (`gouraud._resolve_native`) makes `_pixels`' sums in `_pixels`' order: the same
    bits as the compiled kernel for int32 / int64 corner tables, contiguous and transposed (ZH passes
    F.T), a transposed values table, row-major barycentrics, and split over 1, 2 or 3 threads (each
    pixel summed by one thread). It runs: a call that would not use it returns None."""
    _native_or_skip()
    monkeypatch.setattr(gouraud, "_NATIVE_MIN_PIXELS", 16)               # a 200×190 image splits
    values, F, gb = _case(200, 190, S, N=77, M=120, seed=S)
    want = gouraud.resolve(values, F.T.contiguous(), gb.face, gb.bary, gb.hit, 200, 190, S, native_resolve=False)
    ref = gouraud.resolve_reference(values, F.T.contiguous(), gb.face, gb.bary, gb.hit, 200, 190, S)
    assert (want - ref).abs().max() <= 1e-6
    n = 200 * 190
    bu, bv = gb.bary.float().unbind(-1)
    assert gouraud._resolve_native(values, F.T, gb.face, bu, bv, gb.hit, n, S) is not None
    threads = torch.get_num_threads()
    try:
        for nt in (1, 2, 3):
            torch.set_num_threads(nt)
            for fv in (F.T, F.T.contiguous(), F.T.contiguous().to(torch.int32), F.to(torch.int32).T):
                for vals in (values, values.T.contiguous().T):
                    for bary in (gb.bary, gb.bary.T.contiguous().T):
                        got = gouraud.resolve(vals, fv, gb.face, bary, gb.hit, 200, 190, S)
                        assert torch.equal(got, want), (nt, fv.dtype, fv.stride(), vals.stride(), bary.stride())
    finally:
        torch.set_num_threads(threads)


def test_native_loop_falls_back_off_the_cpu_types(monkeypatch):
    """Arrays the C loop does not take (float64 values, 4 channels) go through the compiled kernel
    (`_resolve_native` returns None), with the same image as the reference; ``PRTBENCH_COMPILE=0``
    switches the loop off with the compiler."""
    _native_or_skip()
    values, F, gb = _case(6, 5, 2)
    bu, bv = gb.bary.float().unbind(-1)
    for vals in (values.double(), torch.cat([values, values[:, :1]], 1)):
        assert gouraud._resolve_native(vals, F.T, gb.face, bu, bv, gb.hit, 30, 4) is None
        want = gouraud.resolve_reference(vals.float(), F.T, gb.face, gb.bary, gb.hit, 6, 5, 2)
        assert (gouraud.resolve(vals, F.T, gb.face, gb.bary, gb.hit, 6, 5, 2) - want).abs().max() <= 1e-6
    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    assert gouraud._resolve_native(values, F.T, gb.face, bu, bv, gb.hit, 30, 4) is None


@pytest.mark.parametrize("name", ["sphere_plane", "chess", "alcove", "shadow_detail", "creature", "bunny",
                                  "dragon", "character"])
def test_native_loop_equals_the_compiled_kernel_on_library_scenes(name):
    """Every library scene at test size, the G-buffer of its default frame (Mitsuba), random
    per-vertex radiance: the C loop's image equals the compiled kernel's bit for bit."""
    _native_or_skip()
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene

    sc = get_scene(name, "test")
    fr = sc.default_frame()
    gb = make_gbuffer(sc, fr, S=2)
    F = sc.geometry().F
    vals = torch.rand(int(F.max()) + 1, 3, generator=torch.Generator().manual_seed(3))
    args = (vals, F.T, gb.face, gb.bary, gb.hit, gb.height, gb.width, gb.spp_side)
    assert bool(gb.hit.any())
    assert torch.equal(gouraud.resolve(*args), gouraud.resolve(*args, native_resolve=False))
