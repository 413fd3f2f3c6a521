"""Session 44 (zh44): the paper configuration's VB / VBL serial steps — a lighting's coefficient table for a new
exponent by one C call (`native_split.light_table`, `ZHShadow.native_light_table`) and the region materials packed
in one tensor (`ZHShadow.packed_materials`) — against their oracles (`runtime.table`; a tensor per colour)."""
from __future__ import annotations

import pytest
import torch

from methods.zh_shadow import native_split as z44
from methods.zh_shadow import runtime as rt
from tests.methods.zh_shadow.conftest import assert_frames_equal


def _bits(x: torch.Tensor) -> torch.Tensor:
    return x.contiguous().view(torch.int32)


def _skip_without_lib() -> None:
    if z44._lib() is None:
        pytest.skip("no C compiler or the native passes switched off")


@pytest.mark.parametrize("n", (2, 3, 4, 5))
def test_light_table_equals_runtime_table(n):
    """`light_table` = `runtime.table` to float32 round-off (float64 sums in another order than BLAS's) for the specular table at many exponents — 0, integers
    (the exact zeros of the Phong factors), fractions, large — and the diffuse one, orders 2-5, 3 and 1 channels.
    A Phong factor off (the recurrence's operands swapped), a band dropped or a row read with the wrong stride
    breaks it."""
    _skip_without_lib()
    g = torch.Generator().manual_seed(44 + n)
    worst = 0.0
    for t in range(12):
        C = 3 if t % 4 else 1
        L = (torch.randn(n * n, C, generator=g) * (1 + t)).contiguous()
        for alpha in (0.0, 1.0, 2.0, 7.0, 12.0, float(torch.rand((), generator=g)) * 60, 200.5):
            want = rt.table(L, alpha, diffuse=False)
            got = z44.light_table(rt._band_operators(n, False), L, alpha)
            assert got is not None and got.shape == want.shape and got.dtype == torch.float32
            worst = max(worst, float(((got - want).abs() / want.abs().max().clamp_min(1e-30)).max()))
        want = rt.table(L, 1.0, diffuse=True)
        got = z44.light_table(rt._table_operator_b(n, 1.0, True), L, None)
        assert got is not None and got.shape == want.shape
        worst = max(worst, float(((got - want).abs() / want.abs().max().clamp_min(1e-30)).max()))
    # (relative to the table's largest entry: entries that are 0 exactly come out as float64 residues of either
    # order of summation; order 4, the bench's, was bit for bit on 768 K entries)
    assert worst <= 2 * torch.finfo(torch.float32).eps, worst


def test_light_table_refuses_other_layouts():
    """None (the caller's `runtime.table` then) for a float64 lighting, a non-contiguous one, an operator of the
    wrong width or dtype."""
    _skip_without_lib()
    L = torch.randn(16, 3)
    Ab = rt._band_operators(4, False)
    assert z44.light_table(Ab, L.double(), 3.0) is None
    assert z44.light_table(Ab, torch.randn(3, 16).T, 3.0) is None
    assert z44.light_table(Ab[:, :-1].contiguous(), L, 3.0) is None
    assert z44.light_table(Ab.float(), L, 3.0) is None
    assert z44.light_table(rt._table_operator_b(4, 1.0, True)[:, :15].contiguous(), L, None) is None


def test_packed_materials_equal_per_colour_tensors(creature):
    """`_region_materials_packed` = `_region_materials_of` value for value (kd, ks float32 rows, α; ks zeros for
    Lambert) and its value tuples = the ``tolist`` of each; an unsupported BRDF raises as there."""
    from scenes.materials import Lambert, Phong
    from scenes.sequences import make_sequence

    m = creature.with_render_config()
    for fr in make_sequence(creature.scene, "VB", 3, seed=44):
        mk = tuple(fr.materials[name] for name in m.scene.regions)
        got, vals = m._region_materials_packed(mk)
        want = m._region_materials_of(fr)
        assert len(got) == len(want)
        for (a, b, al), (c, d, be) in zip(got, want):
            assert a.dtype == c.dtype == torch.float32 and torch.equal(a, c) and torch.equal(b, d) and al == be
        assert vals == tuple((tuple(kd.tolist()), tuple(ks.tolist()), float(al)) for kd, ks, al in want)
    mk = (Phong(kd=(0.1, 0.2, 0.3), ks=(0.4, 0.5, 0.6), s=7.5), Lambert(kd=(0.7, 0.8, 0.9)))[:len(m.scene.regions)]
    got, vals = m._region_materials_packed(mk)
    assert vals[0] == (tuple(torch.tensor((0.1, 0.2, 0.3)).tolist()), tuple(torch.tensor((0.4, 0.5, 0.6)).tolist()),
                       7.5)
    if len(mk) > 1:
        assert vals[1][1] == (0.0, 0.0, 0.0) and vals[1][2] == 1.0
    from scenes.materials import BlinnPhong

    with pytest.raises(ValueError):
        m._region_materials_packed((BlinnPhong(kd=(0.1, 0.1, 0.1), ks=(0.2, 0.2, 0.2), s=5.0),) * len(mk))


@pytest.mark.parametrize("kind", ("VB", "VBL", "V", "P", "L"))
def test_zh44_frames_equal_oracle(creature, kind):
    """Frames with the C tables and packed materials = the oracle (`runtime.table`, a tensor per colour), the same
    bits here (float32 round-off allowed by the table's docstring: none on these frames), the same path and counts,
    at 1 and 2 threads. A table made for the wrong exponent or lighting, or a region's ks read as its kd, breaks it."""
    new, orc = creature.with_render_config(), creature.with_render_config()
    orc.native_light_table = orc.packed_materials = False
    assert_frames_equal(creature.scene, new, orc, kind, 44)


def _old_split(nrm, region, spec_t, hit, face, F32, N, lut):
    """The calls `split` replaces, as `ZHShadow._fused_planes` makes them."""
    from methods.zh_shadow import native as zn
    from methods.zh_shadow import native_threaded as z39

    found: list = []

    def match(n0):
        r = zn.plane_mask(nrm, n0, region, spec_t, hit)
        if r is None:
            raise LookupError
        found[:] = [r]
        return r[0], r[1]

    sc = z39.screen8(nrm.T)
    try:
        first = rt.first_plane(nrm.T, rt.PLANAR_MIN_POINTS, match, screen=sc)
    except LookupError:
        return "bad", sc
    if first is None:
        return None, sc
    mask, cnt, ns, _ = found[0]
    m = nrm.shape[0] - cnt
    screen = m >= rt.PLANAR_MIN_POINTS
    pre = z39.rest_lut(mask, hit, nrm, face, F32, N, m, screen, lut) if (screen or lut) else (None, None)
    return (first[0], mask, cnt, ns, m, pre[0] if screen else None, pre[1] if lut else None), sc


def _gbuffer_like(P, N, M, g, plane_share, misses, second=False):
    n0 = torch.tensor([0.0, 1.0, 0.0])
    nrm = torch.nn.functional.normalize(torch.randn(P, 3, generator=g), dim=1)
    on = torch.rand(P, generator=g) < plane_share
    nrm[on] = n0
    if second:   # a second plane among the samples off the first
        off = (~on).nonzero().squeeze(-1)
        nrm[off[: off.shape[0] // 2]] = torch.tensor([1.0, 0.0, 0.0])
    region = torch.where(on, torch.ones(P, dtype=torch.int64), torch.zeros(P, dtype=torch.int64))
    face = torch.randint(0, M, (P,), generator=g)
    hit = torch.ones(P, dtype=torch.bool)
    if misses:
        idx = torch.randperm(P, generator=g)[:misses]
        idx = idx[~on[idx]]   # (a miss's normal is 0, never the plane's)
        hit[idx] = False
        nrm[idx] = 0.0
        face[idx] = -1
        region[idx] = 0
    F32 = torch.randint(0, N, (M, 3), generator=g, dtype=torch.int32)
    return nrm.contiguous(), region, face, hit if misses else None, F32


@pytest.mark.parametrize("case", ("plain", "misses", "second", "spec", "noplane", "small"))
def test_split_equals_the_three_calls(case):
    """`native_split.split` = screen8, `first_plane` over `plane_mask` and `rest_lut`: the same candidate, mask,
    counts, rest screen, lut and vertex list, at 1, 2 and 3 threads — with misses, a second plane, a specular
    region on the plane, no plane (status 1), too few samples off it to screen. A rank or zero count off by one,
    the lut made from the plane's samples, a candidate other than the first screened, or a stale mask byte breaks
    it."""
    from methods.core.threads import torch_threads

    _skip_without_lib()
    if z44._split_lib() is None:
        pytest.skip("no split library")
    g = torch.Generator().manual_seed(hash(case) % 1000)
    P, N, M = 1 << 17, 5000, 9000
    share = {"noplane": 0.0, "small": 0.995}.get(case, 0.8)
    nrm, region, face, hit, F32 = _gbuffer_like(P, N, M, g, share, 40 if case == "misses" else 0, case == "second")
    spec_t = torch.tensor([True, case == "spec"])
    for lut in (False, True):
        want, sc = _old_split(nrm, region, spec_t, hit, face, F32, N, lut)
        for threads in (1, 2, 3):
            with torch_threads(threads):
                got = z44.split(nrm, region, spec_t, hit, rt.PLANAR_MIN_POINTS, rt.PLANAR_MIN_POINTS, lut, face, F32,
                                N)
            assert got is not None
            assert got[8] == sc, (threads, got[8], sc)
            if want is None:
                assert got[0] == 1
                continue
            assert got[0] == 0, got[:2]
            n0, mask, cnt, ns, m, rs, rl = want
            assert torch.equal(nrm[got[1] * P // 8], n0)
            assert torch.equal(got[2], mask) and (got[3], got[4], got[5]) == (cnt, ns, m)
            assert got[6] == rs, (threads, got[6], rs)
            if lut:
                assert rl is not None and got[7] is not None
                assert torch.equal(got[7][0], rl[0]) and torch.equal(got[7][1], rl[1])
            else:
                assert got[7] is None


def test_split_reports_a_short_or_bad_candidate():
    """Status 2 where the first screened candidate's full count is under the minimum (the old search goes on to the
    next candidate) or a miss lies on the plane (`plane_mask` refuses): the caller's old calls then."""
    _skip_without_lib()
    if z44._split_lib() is None:
        pytest.skip("no split library")
    g = torch.Generator().manual_seed(5)
    P, N, M = 1 << 15, 100, 200
    nrm, region, face, _, F32 = _gbuffer_like(P, N, M, g, 0.5, 0)
    spec_t = torch.tensor([False, False])
    got = z44.split(nrm, region, spec_t, None, P, 32, False, face, F32, N)   # (min_points above the count)
    assert got[0] in (1, 2)
    hit = torch.ones(P, dtype=torch.bool)
    on = (nrm == torch.tensor([0.0, 1.0, 0.0])).all(1).nonzero().squeeze(-1)
    hit[on[5]] = False
    got = z44.split(nrm, region, spec_t, hit, rt.PLANAR_MIN_POINTS, rt.PLANAR_MIN_POINTS, False, face, F32, N)
    assert got[0] == 2


@pytest.mark.parametrize("kind", ("VB", "P", "V", "VBL"))
def test_one_split_frames_equal_oracle(creature, kind):
    """Frames with `one_split` = the three calls (`one_split` off) bit for bit, the same path and counts, 1 and 2
    threads."""
    new, orc = creature.with_render_config(), creature.with_render_config()
    orc.one_split = False
    calls = []
    split = z44._run   # (`split` and its bound call, `native_split.SplitBound` (zh46), both run `_run`)

    def spy(*a, **k):
        r = split(*a, **k)
        calls.append(None if r is None else r[0])
        return r

    import methods.zh_shadow.method as M
    M.z44._run, old = spy, M.z44._run
    try:
        assert_frames_equal(creature.scene, new, orc, kind, 7, fused=True)
    finally:
        M.z44._run = old
    assert 0 in calls   # (the one call took the frames)
