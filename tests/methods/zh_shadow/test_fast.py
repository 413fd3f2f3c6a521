"""The fast run-time path (`methods.zh_shadow.runtime`, `ZHShadow.render`) against the slow reference
path (`ZHShadow._render_reference`, §4.3 step by step), its building blocks against closed forms, and
the cost model (`ZHShadow.frame_cost`) against a hand count."""
from __future__ import annotations

import dataclasses
import math

from unittest import mock

import pytest
import torch

from methods.base import GBUFFER_BYTES_PER_SAMPLE
from methods.core.sampling import gauss_legendre_sphere
from methods.core.sh import sh_eval
from methods.zh_shadow import ZHShadow
from methods.zh_shadow import runtime as rt
from methods.zh_shadow.method import shade
from testing.gbuffers import knock_out

# Fast vs reference render: both float32, the same quantity summed in a different order (SH product
# tables vs per-point rotations); measured ≤ 1e-6 absolute on images whose maximum is ~2.
RENDER_TOL = 1e-5
# The library scenes zh_shadow renders (Lambert / Phong only; chess and dragon have other BRDFs).
SCENES = ("sphere_plane", "alcove", "shadow_detail", "creature", "bunny", "character")
ARTICULATED = ("creature", "character")
# A small precompute: the fast/reference agreement does not depend on the fit quality.
SMALL = dict(train_poses=4, n_dirs=64, fit_iters=0)


@pytest.fixture(scope="module")
def small_model(zh_scene):
    """name → a ZHShadow precomputed on that test-size scene (`zh_scene`: "chess" is the Phong
    stand-in). Callers that render take ``.with_render_config()`` (fresh frame caches)."""
    built = {}

    def get(name: str):
        if name not in built:
            m = ZHShadow(**SMALL)
            m.precompute(zh_scene(name))
            built[name] = m
        return built[name].with_render_config()

    return get


def _check_frames(m, frames, label: str = ""):
    from references.gbuffer import make_gbuffer

    for fr in frames:
        gb = make_gbuffer(m.scene, fr, 2)
        fast, ref = m.render(fr, gb), m._render_reference(fr, gb)
        assert ref.abs().max() > 0.05, "degenerate test image"
        err = (fast - ref).abs().max().item()
        assert err <= RENDER_TOL, f"{m.scene.name} {label} frame {fr.index} {m.config['shading']}: {err}"


def _check_sequence(m, kind: str, n_frames: int = 2, seed: int = 3):
    """Fast == reference on every frame of a ``kind`` sequence (frame 1 on exercises the caches; the
    second lighting-only frame of an L or E sequence shades from the cached transfer)."""
    from scenes.sequences import make_sequence

    _check_frames(m, make_sequence(m.scene, kind, n_frames, seed=seed), kind)
    if kind in ("L", "E") and n_frames >= 3 and m.config["shading"] == "sample":
        assert m._relight is not None, "lighting-only frames did not use the transfer cache"


@pytest.mark.parametrize("order", [4, 8])
def test_lighting_equals_project_latlong(zh_scene, order):
    """`ZHShadow._lighting` (a new map: `project_latlong_polar` then one rotation by R Qᵀ; the same
    map rotated: that kept projection rotated by the new R Qᵀ, no projection — or with ``rotated_lighting``
    off its own-frame projection, made once, rotated by R) = `sh.project_latlong(env)` (the oracle
    `_render_reference` uses) to float32 round-off, on E then L frames of the library scene."""
    from methods.core.sh import project_latlong
    from scenes.sequences import make_sequence

    scene = zh_scene("creature")
    for rotated in (True, False):   # a rotated map: its kept polar-frame projection rotated by R Qᵀ, or the oracle's
        m = ZHShadow(order=order)                                 # `_lighting` needs no precompute
        m.rotated_lighting = rotated
        for kind in ("E", "L", "E"):
            for fr in make_sequence(scene, kind, 3, seed=5):
                with mock.patch("methods.zh_shadow.method.project_latlong", wraps=project_latlong) as pl:
                    got = m._lighting(fr.envmap)
                assert pl.called == (not rotated and kind == "L" and fr.index == 1), (rotated, kind, fr.index)
                want = project_latlong(fr.envmap, order).float()
                assert got.shape == want.shape == (order * order, 3)
                assert (got - want).abs().max() <= 1e-6 * want.abs().max(), (kind, rotated)


@pytest.mark.parametrize("order", [2, 4, 5, 8])
def test_rotate_lighting_equals_rotate_coeffs(order):
    """`runtime.rotate_lighting` (ZYZ angles, three z rotations and two fixed products, numpy) =
    `sh_rotation.rotate_coeffs` (the band recursion, the oracle) and `sh.rotate_sampled` (what
    `ZHShadow._lighting` called before) to float64 round-off: random rotations, the ZYZ singular
    ones (b = 0, b = π, sin b ~ 1e-9) and a rotation about each axis; rotations perturbed by ~3e-8
    (the scenes' to_world are orthonormal to float32 round-off) to 2e-6 (each way rotates a
    non-orthonormal R its own way); a matrix that is no rotation to `runtime.ROTATION_TOL` goes to
    `rotate_sampled` unchanged."""
    from methods.core.sh import rotate_sampled
    from methods.core.sh_rotation import rotate_coeffs

    def axis(i, t):
        c, s = math.cos(t), math.sin(t)
        j, k = [(1, 2), (2, 0), (0, 1)][i]
        R = torch.eye(3, dtype=torch.float64)
        R[j, j] = R[k, k] = c
        R[k, j], R[j, k] = s, -s
        return R

    g = torch.Generator().manual_seed(order)
    Rs = [torch.eye(3, dtype=torch.float64), torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64)),
          torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)), axis(2, 0.7) @ axis(1, 1e-9) @ axis(2, 2.1),
          axis(2, -2.5) @ axis(1, math.pi - 1e-9) @ axis(2, 0.4), axis(0, 1.1), axis(1, -0.6), axis(2, 2.9)]
    for _ in range(12):
        Q = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=g))[0]
        Rs.append(Q if torch.linalg.det(Q) > 0 else -Q)
    for R in Rs:
        c = torch.randn(order * order, 3, dtype=torch.float64, generator=g)
        got = rt.rotate_lighting(c, R)
        assert got.dtype == torch.float64 and got.shape == c.shape
        assert (got - rotate_coeffs(c, R)).abs().max() <= 1e-12 * c.abs().max()
        assert (got - rotate_sampled(c, R)).abs().max() <= 1e-12 * c.abs().max()
    for R in Rs[3:]:   # orthonormal to float32 round-off only (the scenes' composed to_world): agree to it
        R = R + 3e-8 * torch.randn(3, 3, dtype=torch.float64, generator=g)
        c = torch.randn(order * order, 3, dtype=torch.float64, generator=g)
        got = rt.rotate_lighting(c, R)
        assert (got - rotate_sampled(c, R)).abs().max() <= 2e-6 * c.abs().max()
        assert (got - rotate_coeffs(c, R)).abs().max() <= 2e-6 * c.abs().max()
    R = Rs[-1] * (1 + 1e-6)                                   # not orthonormal to 1e-7: the old path
    c = torch.randn(order * order, 3, dtype=torch.float64, generator=g)
    assert torch.equal(rt.rotate_lighting(c, R), rotate_sampled(c, R))


@pytest.mark.parametrize("name", SCENES + ("chess",))
def test_fast_equals_reference(small_model, name):
    """V, L and E frames (3 of each lighting kind: the cached transfer is built, then used) and P
    frames on the articulated scenes; sample shading, default config. Planes cover the cases:
    one plane holding most samples (every scene), a second one spanning two regions with a
    specular one (alcove), a specular plane (chess: its Phong board)."""
    m = small_model(name)
    for kind in ("V", "L", "E") + (("P",) if name in ARTICULATED else ()):
        _check_sequence(m, kind, n_frames=3 if kind in ("L", "E") else 2)


def test_fast_equals_reference_variants(small_model):
    """Vertex shading, material changes (VB: new exponents), view + lighting (VL) with a window and
    clamp off, and no planar groups — on the creature."""
    m = small_model("creature")
    _check_sequence(m.with_render_config(shading="vertex"), "P")
    _check_sequence(m.with_render_config(shading="vertex"), "L", n_frames=3)
    _check_sequence(m, "VB")
    _check_sequence(m.with_render_config(window="hanning", clamp=False), "VL")
    _check_sequence(m.with_render_config(window="hanning", clamp=False), "L", n_frames=3)


@pytest.mark.parametrize("order", (2, 3, 6, 8))
def test_fast_equals_reference_orders(zh_scene, order):
    """Other SH orders: monomial features and eq. 1 by monomials (2, 3), SH features above
    `MONOMIAL_MAX_ORDER` (6, 8 — the order of the suites' physical ZH setting), V and lighting-only
    frames, on the creature (P frames: the pose model)."""
    m = ZHShadow(**SMALL, order=order)
    m.precompute(zh_scene("creature"))
    for kind, n in (("P", 2), ("L", 3)):
        _check_sequence(m.with_render_config(), kind, n_frames=n)


@pytest.mark.parametrize("name", ("alcove", "creature"))
def test_fast_equals_reference_small_planes(small_model, monkeypatch, name):
    """Planes down to 16 points, so vertex shading has them too (the test-size grounds have
    < `PLANAR_MIN_POINTS` vertices) and sample shading finds more, smaller ones."""
    monkeypatch.setattr(rt, "PLANAR_MIN_POINTS", 16)
    m = small_model(name)
    for shading in ("sample", "vertex"):
        mm = m.with_render_config(shading=shading)
        _check_sequence(mm, "V")
        _check_sequence(mm, "L", n_frames=3)
        if shading == "vertex":
            assert mm._last_counts["groups"] >= 1


def test_transfer_cache_invalidation(small_model):
    """A frame that says only the lighting changed but whose camera, pose or exponents differ
    from the previous frame's is shaded from scratch (the cache key), a real lighting-only frame
    after it rebuilds the cache, and a changed albedo (kd, ks: applied at shading time) is
    honoured by the cached transfer."""
    from scenes.materials import Phong
    from scenes.sequences import make_sequence

    m = small_model("creature")
    L = make_sequence(m.scene, "L", 4, seed=5)
    V = make_sequence(m.scene, "V", 2, seed=5)
    P = make_sequence(m.scene, "P", 2, seed=5)
    light_only = frozenset({"light"})
    lie_view = dataclasses.replace(V[1], envmap=L[2].envmap, changed=light_only)
    lie_pose = dataclasses.replace(P[1], envmap=L[2].envmap, changed=light_only)
    mat = m.scene.materials["creature"]
    lie_alpha = dataclasses.replace(L[2], materials={**L[2].materials, "creature": Phong(kd=mat.kd, ks=mat.ks, s=3.0)},
                                    changed=light_only)
    albedo = dataclasses.replace(L[3], materials={**L[3].materials,
                                                  "creature": Phong(kd=(0.2, 0.6, 0.3), ks=(0.4, 0.1, 0.2), s=mat.s)},
                                 changed=light_only)
    cached = []
    for fr in (L[0], L[1], L[2], albedo, lie_view, L[3], lie_pose, L[1], L[2], lie_alpha, L[3]):
        _check_frames(m, [fr], "mixed")
        cached.append(None if m._relight is None else id(m._relight[3]))
    # L[1], the first lighting-only frame after L[0], builds the transfer; L[2] and the albedo
    # change reuse it; every lie is shaded from scratch (and drops it), so is the frame after it
    # (its predecessor's state differs); the next true lighting-only frame rebuilds.
    assert cached[0] is None and cached[1] is not None and cached[1] == cached[2] == cached[3]
    assert cached[4:8] == [None] * 4
    assert cached[8] is not None and cached[9] is None and cached[10] is None


@pytest.mark.parametrize("order", (4, 8))
def test_fast_equals_reference_cosine(zh_scene, order):
    """``specular="cosine"`` (the suites' physical setting at order 8): sample shading on P, VB and
    lighting-only frames (the transfer cache with the cos θ_i-weighted t_s), vertex shading on P
    and L (the per-vertex w cached with the pose)."""
    m = ZHShadow(**SMALL, order=order, specular="cosine")
    m.precompute(zh_scene("creature"))
    _check_sequence(m.with_render_config(), "P")
    _check_sequence(m.with_render_config(), "VB")
    _check_sequence(m.with_render_config(), "L", n_frames=3)
    _check_sequence(m.with_render_config(shading="vertex"), "P")
    _check_sequence(m.with_render_config(shading="vertex"), "L", n_frames=3)


def test_cosine_visibility_equals_rotations():
    """`runtime.cosine_visibility` = M¹ applied in the frame of n through explicit SH rotations
    (`methods.core.sh_rotation`, the reference path's way), orders 2–8, normals at the poles
    included; float64 to round-off, float32 within 2e-6."""
    from methods.core.frames import frame_matrix
    from methods.core.sh_rotation import rotate_coeffs
    from methods.zh_shadow.convolution import phong_operator

    g = torch.Generator().manual_seed(2)
    for order in (2, 3, 4, 5, 8):
        Q = 300
        nrm = torch.randn(Q, 3, generator=g, dtype=torch.float64)
        nrm = nrm / nrm.norm(dim=-1, keepdim=True)
        nrm[:3] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
        v = torch.randn(Q, order * order, generator=g, dtype=torch.float64)
        Fn = frame_matrix(nrm)
        vn = rotate_coeffs(v[..., None], Fn)[..., 0]
        want = rotate_coeffs((vn @ phong_operator(1.0, order, dtype=torch.float64))[..., None],
                             Fn.transpose(-1, -2))[..., 0]
        got = rt.cosine_visibility(v.T.contiguous(), nrm.T.contiguous()).T
        assert (got - want).abs().max() <= 1e-13 * want.abs().max(), order
        got32 = rt.cosine_visibility(v.T.float().contiguous(), nrm.T.float().contiguous()).T.double()
        assert (got32 - want).abs().max() <= 2e-6 * want.abs().max(), order


def test_specular_transfer_regions():
    """`runtime.specular_transfer` with per-region exponents: a region whose points are one range
    of columns (sliced) and one whose points are scattered (gathered) each equal `zonal_conjugate`
    of all points scaled by (α+1)/(2π) on the region's columns, zero where there is no specular
    term (float64, to round-off; the region of a vertex mesh is a range: the vertex path's case)."""
    g = torch.Generator().manual_seed(5)
    order, Q = 8, 301
    v = torch.randn(order * order, Q, generator=g, dtype=torch.float64)
    nT = torch.randn(3, Q, generator=g, dtype=torch.float64)
    woT = torch.randn(3, Q, generator=g, dtype=torch.float64)
    nT, woT = nT / nT.norm(dim=0), woT / woT.norm(dim=0)
    R = rt.reflect_T(nT, woT)
    alphas = [12.0, 3.0, None]
    scattered = torch.full((Q,), 2, dtype=torch.int64)
    scattered[40:200] = 0                              # a range
    scattered[200::3] = 1                              # scattered
    scattered[0:40:7] = 1
    ranges = torch.full((Q,), 2, dtype=torch.int64)    # every region a range: only the gaps zeroed
    ranges[40:200], ranges[250:] = 0, 1
    for vreg in (scattered, ranges):
        got = rt.specular_transfer(v, nT, woT, vreg, alphas)
        want = torch.zeros_like(v)
        for r, a in enumerate(alphas[:2]):
            full = rt.zonal_conjugate(v, R, ("phong", a)) * ((a + 1.0) / (2.0 * math.pi))
            want[:, vreg == r] = full[:, vreg == r]
        assert (got[:, vreg == 2] == 0).all()
        assert (got - want).abs().max() <= 1e-13 * want.abs().max()
    # one region holding every point (no copy)
    got = rt.specular_transfer(v, nT, woT, torch.zeros(Q, dtype=torch.int64), [12.0])
    want = rt.zonal_conjugate(v, R, ("phong", 12.0)) * (13.0 / (2.0 * math.pi))
    assert (got - want).abs().max() <= 1e-13 * want.abs().max()


def test_cosine_visibility_zyz_equals_world():
    """`runtime.cosine_visibility_zyz` of the visibility made in the ZYZ normal frames
    (`world_visibility`, ``frame="zyz"``: the vertex path with the cosine) = `cosine_visibility` of
    the world-space one, orders 2–8, normals at the poles included: float64 to round-off; float32
    within 2e-6 of the float32 world path (both are ~1e-3 from float64 here: the pose model's own
    float32 round-off on these random charts, not the frame change)."""
    g = torch.Generator().manual_seed(3)
    for order in (2, 4, 5, 8):
        N, c = 500, 2
        X = torch.randn(4, N, c * (2 + order), generator=g, dtype=torch.float64) * 0.3
        pose = torch.randn(3, generator=g, dtype=torch.float64)
        nrm = torch.randn(N, 3, generator=g, dtype=torch.float64)
        nrm[:3] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]], dtype=torch.float64)
        nrm = nrm / nrm.norm(dim=-1, keepdim=True)
        nT = nrm.T.contiguous()
        want = rt.cosine_visibility(rt.world_visibility(X, pose, nrm, c, point_minor=True), nT)
        got = rt.cosine_visibility_zyz(rt.world_visibility(X, pose, nrm, c, point_minor=True, frame="zyz"), nT)
        assert (got - want).abs().max() <= 1e-13 * want.abs().max(), order
        X32, p32, n32 = X.float(), pose.float(), nrm.float()
        want32 = rt.cosine_visibility(rt.world_visibility(X32, p32, n32, c, point_minor=True), nT.float()).double()
        got32 = rt.cosine_visibility_zyz(rt.world_visibility(X32, p32, n32, c, point_minor=True, frame="zyz"),
                                         nT.float()).double()
        assert (got32 - want32).abs().max() <= 2e-6 * want.abs().max(), order
        # the rows made in the product's order by the compiled pass (`zyz_rows`, the vertex path):
        # the same numbers as the gather of the SH-ordered rows, bit for bit
        rows = rt.zyz_rows(order)
        vz32 = rt.world_visibility(X32, p32, n32, c, point_minor=True, frame="zyz")
        vo32 = rt.world_visibility(X32, p32, n32, c, point_minor=True, frame="zyz", rows=rows)
        assert torch.equal(vo32, vz32.index_select(0, rows)), order
        assert torch.equal(rt.cosine_visibility_zyz(vo32, nT.float(), ordered=True),
                           rt.cosine_visibility_zyz(vz32, nT.float())), order
    with pytest.raises(ValueError):
        rt.world_visibility(X, pose, nrm, c, frame="local")
    with pytest.raises(ValueError):
        rt.world_visibility(X, pose, nrm, c, rows=torch.zeros(64, dtype=torch.int64))


def test_world_visibility_point_minor_model():
    """`runtime.world_visibility` from X laid out (J+1, d, N) in memory (`point_minor_model`, the
    layout `ZHShadow._pose_state` gives the model: the product then writes the point-minor
    parameters itself) = from the least-squares layout (the transposed copy of its product), both
    result layouts, float32 to round-off (`VIS_LAYOUT_TOL`); the model's values are unchanged."""
    g = torch.Generator().manual_seed(4)
    for order, N in ((4, 700), (8, 300)):
        c = 2
        X = torch.randn(c * (2 + order), N, 5, generator=g).permute(2, 1, 0) * 0.3   # (5, N, d), strides of lstsq
        assert not X.transpose(1, 2).is_contiguous()
        Xp = rt.point_minor_model(X)
        assert Xp.transpose(1, 2).is_contiguous() and torch.equal(Xp, X) and rt.point_minor_model(Xp) is Xp
        pose = torch.randn(4, generator=g)
        nrm = torch.randn(N, 3, generator=g)
        nrm = nrm / nrm.norm(dim=-1, keepdim=True)
        for kw in ({}, {"point_minor": True}, {"point_minor": True, "frame": "zyz", "rows": rt.zyz_rows(order)}):
            want = rt.world_visibility(X, pose, nrm, c, **kw)
            got = rt.world_visibility(Xp, pose, nrm, c, **kw)
            assert got.shape == want.shape
            assert (got - want).abs().max() <= VIS_LAYOUT_TOL * want.abs().max(), (order, kw)


@pytest.mark.parametrize("order, kw", [(4, {}), (8, {"point_minor": True, "frame": "zyz"})])
def test_world_visibility_compiled_equals_eager(order, kw):
    """`runtime.world_visibility` from `VERTEX_COMPILE_MIN` vertices (`_vertex_sh` compiled, one
    kernel for every vertex count) = the eager `_vertex_sh` (below it), float32 to round-off: the
    suites' two variants (paper: order 4, (N, n²); physical: order 8, ZYZ frames, rows in
    `zyz_rows` order, (n², N)), at two vertex counts.

    Round-off is judged against the eager path in float64: the compiled float32 result must be as
    accurate as the eager float32 one (within `VIS_COMPILED_FACTOR` of its error, max-norm). A
    fixed bound between the two float32 results (1e-6 of the peak until session 21) is below their
    own round-off at order 8 on a host without AVX-512: compiled − eager 1.15e-6 there, each
    1.3–1.5e-6 from float64 (the FMAs Inductor contracts differ with the vector width)."""
    g = torch.Generator().manual_seed(6)
    c = 2
    for N in (rt.VERTEX_COMPILE_MIN, rt.VERTEX_COMPILE_MIN + 777):
        # (charts well inside the disk of radius 2: at its rim the axis's √(1 − r²/4) amplifies the
        # product's round-off without bound — one of 4,096 random points at scale 0.3 moved by 1e-3)
        X = rt.point_minor_model(torch.randn(5, N, c * (2 + order), generator=g) * 0.15)
        pose = torch.randn(4, generator=g)
        nrm = torch.randn(N, 3, generator=g)
        nrm = nrm / nrm.norm(dim=-1, keepdim=True)
        nrm[:2] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
        args = dict(kw, rows=rt.zyz_rows(order)) if kw else kw
        got = rt.world_visibility(X, pose, nrm, c, **args)
        with mock.patch.object(rt, "VERTEX_COMPILE_MIN", N + 1):
            want = rt.world_visibility(X, pose, nrm, c, **args)
            ref = rt.world_visibility(X.double(), pose.double(), nrm.double(), c, **args)
        assert got.dtype == want.dtype == torch.float32 and got.shape == want.shape == ref.shape
        err_got = float((got.double() - ref).abs().max())
        err_want = float((want.double() - ref).abs().max())
        floor = 8 * torch.finfo(torch.float32).eps * float(ref.abs().max())   # a few ulps of the peak
        assert err_got <= VIS_COMPILED_FACTOR * max(err_want, floor), (order, N, err_got, err_want)


def test_world_visibility_cols_equal_columns_of_all():
    """`runtime.world_visibility` with ``cols`` (a P frame's front-facing vertices,
    `ZHShadow._front_radiance`) = those columns (rows) of the visibility of every vertex, bit for bit
    when both run eagerly (each vertex's numbers are its own: the product over every vertex, then a
    gather), for both layouts and the ZYZ frame; a permuted, repeated selection too."""
    g = torch.Generator().manual_seed(8)
    for order, N in ((4, 700), (8, 300)):
        c = 2
        X = rt.point_minor_model(torch.randn(5, N, c * (2 + order), generator=g) * 0.15)
        pose = torch.randn(4, generator=g)
        nrm = torch.randn(N, 3, generator=g)
        nrm = nrm / nrm.norm(dim=-1, keepdim=True)
        cols = torch.cat([torch.randperm(N, generator=g)[:N // 3], torch.tensor([0, N - 1, 0])])
        for kw in ({}, {"point_minor": True}, {"point_minor": True, "frame": "zyz", "rows": rt.zyz_rows(order)}):
            full = rt.world_visibility(X, pose, nrm, c, **kw)
            got = rt.world_visibility(X, pose, nrm, c, cols=cols, **kw)
            want = full.index_select(1 if kw.get("point_minor") else 0, cols)
            assert got.shape == want.shape and torch.equal(got, want), (order, kw)


# The compiled float32 `_vertex_sh` is as accurate as the eager float32 one, against float64
# (Inductor contracts the SH polynomials' multiply-adds into FMAs, so the two round differently;
# measured on a host without AVX-512: ratios 0.87–1.0 at order 8, 0.96–1.0 at order 4)
VIS_COMPILED_FACTOR = 2.0


# float32: the product [pose, 1] · X summed in another blocking order by the two layouts
VIS_LAYOUT_TOL = 1e-6


def test_operator_blocks_equal_dense_product():
    """`runtime._zyz_product` through `_operator_blocks` (the block-sparse X M Xᵀ and X M) = the
    dense product, float64 to round-off, orders 2–9 and several exponents; the blocks cover every
    row and column once, hold all of K's entries above round-off, and at order 8 are 4 blocks of
    1,056 entries (of 4,096)."""
    g = torch.Generator().manual_seed(7)
    for order in (2, 3, 4, 5, 8, 9):
        n2 = order * order
        for alpha in (1.0, 3.0, 12.0, 100.0):
            for lifted in (False, True):
                K = rt._lifted(("phong", alpha), order) if lifted else rt._conjugated(("phong", alpha), order)
                blocks = rt._operator_blocks(("phong", alpha), order, lifted, torch.float64, torch.device("cpu"))
                rows = torch.cat([b[0] for b in blocks]).sort().values
                cols = torch.cat([b[1] for b in blocks]).sort().values
                assert torch.equal(rows, torch.arange(n2)) and torch.equal(cols, torch.arange(n2))
                covered = torch.zeros(n2, n2, dtype=torch.bool)
                for r, c, Kb in blocks:
                    covered[r[:, None], c[None, :]] = True
                    assert torch.equal(Kb, K[r][:, c])
                assert K[~covered].abs().max() <= 1e-14 * K.abs().max(), (order, alpha, lifted)
                if order == 8:
                    assert len(blocks) == 4 and int(covered.sum()) == 1056
                a = torch.randn(n2, 97, generator=g, dtype=torch.float64)
                want = K @ a
                got = rt._zyz_product(K, a, blocks)
                assert (got - want).abs().max() <= 1e-14 * want.abs().max(), (order, alpha, lifted)
                # the fast layout (`_block_plan`, `_blocked_product`: rows in block order, no
                # gathers or scatters) holds the same numbers, float64 and float32 — bit for bit
                # where K has several blocks (the same block products); one block is all of K
                # with its rows and columns permuted (the sums in another order: round-off)
                for dt, tol in ((torch.float64, 1e-14), (torch.float32, 1e-6)):
                    cols, src, _ = plan = rt._block_plan(("phong", alpha), order, lifted, dt, torch.device("cpu"))
                    ad = a.to(dt)
                    fast = rt._blocked_product(plan, ad.index_select(0, cols)).index_select(0, src)
                    blocks_dt = rt._operator_blocks(("phong", alpha), order, lifted, dt, torch.device("cpu"))
                    slow = rt._zyz_product(K.to(dt), ad, blocks_dt)
                    if len(blocks) > 1:
                        assert torch.equal(fast, slow), (order, alpha, lifted, dt)
                    assert (fast - slow).abs().max() <= tol * slow.abs().max(), (order, alpha, lifted, dt)


def _block_plan_reference(op_key, order, lifted, dtype, scale=1.0):
    """`runtime._block_plan` as it was made before it kept its layout per non-zero pattern (from
    `_operator_blocks` of that dtype, or of float64 scaled then cast): its test oracle."""
    dev = torch.device("cpu")
    blocks = rt._operator_blocks(op_key, order, lifted, dtype, dev)
    if scale != 1.0:
        b64 = rt._operator_blocks(op_key, order, lifted, torch.float64, dev)
        blocks = tuple((r, c, (K64 * scale).to(dtype)) for (r, c, _), (_, _, K64) in zip(blocks, b64))
    rows = torch.cat([r for r, _, _ in blocks])
    cols = torch.cat([c for _, c, _ in blocks])
    src = torch.empty_like(rows)
    src[rows] = torch.arange(rows.shape[0])
    spans, r0, c0 = [], 0, 0
    for r, c, K_b in blocks:
        spans.append((r0, r0 + r.shape[0], c0, c0 + c.shape[0], K_b))
        r0, c0 = r0 + r.shape[0], c0 + c.shape[0]
    return cols, src, tuple(spans)


def test_block_plan_equals_operator_blocks_plan():
    """`runtime._block_plan` (the layout kept per M's non-zero pattern, `_plan_layout`; per exponent
    M, K and one gather of the blocks' entries) = the plan made from `_operator_blocks` bit for bit
    — cols, src, spans and every block — orders 2–9, exponents 1 (the cosine: a pattern of its own
    at some orders), fresh non-integer ones (each a new exponent after the layout was kept, as a VB
    frame meets it), lifted or not, float32 / float64, with and without a scale."""
    g = torch.Generator().manual_seed(11)
    for order in (2, 3, 4, 5, 8, 9):
        alphas = [1.0, 12.0] + [float(1.0 + 80.0 * torch.rand((), generator=g, dtype=torch.float64)) for _ in range(3)]
        for alpha in alphas:
            for lifted in (False, True):
                for dt in (torch.float32, torch.float64):
                    for scale in (1.0, (alpha + 1.0) / (2.0 * math.pi)):
                        got = rt._block_plan(("phong", alpha), order, lifted, dt, torch.device("cpu"), scale)
                        want = _block_plan_reference(("phong", alpha), order, lifted, dt, scale)
                        assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])
                        assert len(got[2]) == len(want[2]), (order, alpha, lifted)
                        for a, b in zip(got[2], want[2]):
                            assert a[:4] == b[:4], (order, alpha, lifted)
                            assert a[4].dtype == dt and a[4].is_contiguous() and torch.equal(a[4], b[4]), \
                                (order, alpha, lifted, dt, scale)


def test_shade_terms_equal_reference_shade():
    """`runtime.shade_terms` = `method.shade` (per-point rotations, M^α) for random lobes, normals,
    views, lighting and exponents, orders 2–6 (monomial and SH features), float64."""
    g = torch.Generator().manual_seed(1)
    for order in (2, 3, 4, 5, 6):
        Q, n2 = 40, order * order
        k = torch.randn(Q, 3, order, generator=g, dtype=torch.float64)
        ax = torch.randn(Q, 3, 3, generator=g, dtype=torch.float64)
        ax = ax / ax.norm(dim=-1, keepdim=True)
        nrm = torch.randn(Q, 3, generator=g, dtype=torch.float64)
        nrm = nrm / nrm.norm(dim=-1, keepdim=True)
        wo = torch.randn(Q, 3, generator=g, dtype=torch.float64)
        wo = wo / wo.norm(dim=-1, keepdim=True)
        light = torch.randn(n2, 3, generator=g, dtype=torch.float64)
        from methods.core.zh import zh_lobes_to_sh

        v = zh_lobes_to_sh(k, ax)
        one, zero = torch.ones(Q, 3, dtype=torch.float64), torch.zeros(Q, 3, dtype=torch.float64)
        for alpha in (1.0, 7.5, 40.0):
            want_d = shade(k, ax, nrm, wo, light, one, zero, torch.full((Q,), alpha, dtype=torch.float64))
            want_s = shade(k, ax, nrm, wo, light, zero, one, torch.full((Q,), alpha, dtype=torch.float64))
            d, s = rt.shade_terms(v.T, nrm.T, wo.T, rt.table(light, 1.0, diffuse=True),
                                  rt.table(light, alpha, diffuse=False))
            front = (nrm * wo).sum(-1, keepdim=True) > 0
            scale = want_d.abs().max() + want_s.abs().max()
            assert torch.where(front, (d.T - want_d).abs(), zero).max() <= 1e-10 * scale, (order, alpha)
            assert torch.where(front, (s.T - want_s).abs(), zero).max() <= 1e-10 * scale, (order, alpha)


# Per-vertex table vs per-point GEMMs (float64): the same sums in another order.
TABLES_TOL = 1e-10


@pytest.mark.parametrize("order", (2, 3, 4, 5, 6))
def test_vertex_table_equals_point_gemms(order):
    """`runtime.shade` through the per-vertex table U (`vertex_table`, `sample_terms`; compiled
    features and interpolated dot) = through the per-point feature GEMMs (`shade_terms`), float64,
    on random meshes of two regions (one without a specular term, exponents 1–40), a plane holding
    most points (its specular term on the per-point path) and a point count that is not a multiple
    of the block (the padded last block); orders 2–5 (monomial features) and 6 (SH features)."""
    g = torch.Generator().manual_seed(order)
    N, Q, n2 = 60, 3 * rt.SAMPLE_BLOCK // 2 + 7, order * order
    v = torch.randn(N, n2, generator=g, dtype=torch.float64)
    vreg = (torch.arange(N) >= N // 2).long()
    face = torch.randint(0, N // 2, (Q, 3), generator=g)
    region = (torch.rand(Q, generator=g) < 0.4).long()
    vi = (face + region[:, None] * (N // 2)).to(torch.int32)               # a face's vertices share its region
    b = torch.rand(Q, 3, generator=g, dtype=torch.float64)
    b = b / b.sum(1, keepdim=True)
    nrm = torch.randn(3, Q, generator=g, dtype=torch.float64)
    plane = torch.rand(Q, generator=g) < 0.6
    nrm[:, plane] = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)[:, None]
    nrm = nrm / nrm.norm(dim=0, keepdim=True)
    wo = torch.randn(3, Q, generator=g, dtype=torch.float64)
    wo = wo / wo.norm(dim=0, keepdim=True)
    light = torch.randn(n2, 3, generator=g, dtype=torch.float64)
    Wd = rt.table(light, 1.0, diffuse=True)
    for alphas in ((7.5, None), (40.0, 1.0), (None, None)):
        mats = [(torch.rand(3, generator=g, dtype=torch.float64), torch.rand(3, generator=g, dtype=torch.float64), Wd,
                 None if a is None else rt.table(light, a, diffuse=False)) for a in alphas]
        for planar in (True, False):
            want, cw = rt.shade(v, vi, b, nrm, wo, region, vreg, nrm.T, mats, planar=planar, tables="point")
            got, cg = rt.shade(v, vi, b, nrm, wo, region, vreg, nrm.T, mats, planar=planar, tables="vertex")
            U = rt.vertex_table(v, vreg, mats)
            kept, _ = rt.shade(v, vi, b, nrm, wo, region, vreg, nrm.T, mats, planar=planar, U=U)
            assert want.abs().max() > 0.1
            err = max((got - want).abs().max().item(), (kept - want).abs().max().item())
            assert err <= TABLES_TOL * want.abs().max().item(), (order, alphas, planar, err)
            assert {k: v_ for k, v_ in cg.items() if k != "plane_vertices"} == \
                {k: v_ for k, v_ in cw.items() if k != "plane_vertices"}
    with pytest.raises(ValueError):
        rt.shade(v, vi, b, nrm, wo, region, vreg, nrm.T, mats, tables="rows")


def test_view_frames_keep_the_vertex_table(small_model):
    """A view-only sequence builds the per-vertex table on its first view-only frame and shades
    the next ones from it (fast == reference on each); a pose, lighting or material change drops
    it (the key), and the cosine variant never uses it."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    m = small_model("creature")
    frames = make_sequence(m.scene, "V", 4, seed=3)
    _check_frames(m, frames[:2], "V")
    U = m._vtable[2]
    _check_frames(m, frames[2:], "V")
    assert m._vtable[2] is U, "the view-only frames rebuilt the vertex table"
    assert m.memory()["vertex_table"] == U.numel() * U.element_size()
    fr = make_sequence(m.scene, "VB", 2, seed=4)[1]            # new materials, changed ⊄ {"view"}
    with mock.patch("methods.zh_shadow.method.VERTEX_TABLE_POINTS", math.inf):   # few points per vertex
        m.render(fr, make_gbuffer(m.scene, fr, 2))
    assert m._vtable[2] is U                                     # kept, but not used: its key differs
    # a frame shading many samples per vertex off the planes builds its own table (not reused):
    # VB and P frames, each equal to the reference — on the plane path, of the vertices its samples
    # reference alone and not kept (`test_referenced_vertex_table_equals_full_table`); with that
    # off, of every vertex, kept
    with mock.patch("methods.zh_shadow.method.VERTEX_TABLE_POINTS", 0.0):
        _check_frames(m, [fr], "VB many")
        assert m.last_path == "planes" and m._vtable[2] is U
        with mock.patch.object(type(m), "referenced_table", False):
            _check_frames(m, [fr], "VB many")
            assert m._vtable[2] is not U
            for fp in make_sequence(m.scene, "P", 3, seed=5)[1:]:
                U1 = m._vtable[2]
                _check_frames(m, [fp], "P many")
                assert m._vtable[2] is not U1 and m._vtable[0][0] == m._posed[0]
    mc = m.with_render_config(specular="cosine")
    _check_frames(mc, frames[:3], "V cosine")
    assert mc._vtable is None


@pytest.mark.parametrize("name,path", (("creature", "planes"), ("sphere_plane", "planes"), ("alcove", "samples"),
                                       ("character", "samples")))
def test_plane_path_equals_general_path(small_model, monkeypatch, name, path):
    """`ZHShadow._render_planes` (every sample a hit, one plane without a specular term: the plane
    shaded straight from the G-buffer) is taken where it applies and nowhere else (alcove: two
    planes; character: samples that miss), equals the reference and the general path (image to
    round-off, the same point counts for `frame_cost`) on V and VB frames, with the clamp on and off.
    A wrong plane term, front test, clamp or box filter breaks the image; a wrong count the counts."""
    cases = (("V", True), ("VB", True), ("V", False))
    for kind, fr, fast, slow in _fast_vs_general(small_model(name), monkeypatch, "_render_planes", cases, 2, 5):
        assert fast.last_path == path, (name, kind, fast.last_path)
        ca, cb = dict(fast._last_counts), dict(slow._last_counts)
        pa, pb = ca.pop("plane_vertices"), cb.pop("plane_vertices")
        assert ca == cb and (pa() if callable(pa) else pa) == (pb() if callable(pb) else pb)
        # the plane path's kept term is reported as memory; the general path keeps none
        us = [fast._plane_u[3], fast._plane_u0[3]] if path == "planes" else []
        assert fast.memory()["plane_term"] == sum(u.numel() * u.element_size() for u in us)
        assert slow.memory()["plane_term"] == 0


def test_referenced_vertices():
    """`runtime.referenced_vertices`: the referenced ids ascending, and vi renumbered over them."""
    g = torch.Generator().manual_seed(0)
    vi = torch.randint(0, 50, (40, 3), generator=g, dtype=torch.int64) * 3 + 1   # ids 1, 4, …: gaps
    for dt in (torch.int32, torch.int64):
        idx, vr = rt.referenced_vertices(vi.to(dt), 200)
        assert torch.equal(idx, torch.unique(vi)) and vr.dtype == dt and vr.shape == vi.shape
        assert torch.equal(idx[vr.long()], vi)


@pytest.mark.parametrize("kind", ("VB", "VL", "P"))
def test_referenced_vertex_table_equals_full_table(small_model, monkeypatch, kind):
    """A frame that is not view-only and shades many samples per vertex off the planes (VB, VL and P
    frames at bench size; here forced) builds its table for the vertices its object samples reference
    alone (`ZHShadow._vertex_table`'s ``vi``): the image equals, bit for bit, the one from the table of
    every vertex (``referenced_table`` off, the oracle) — the same rows, renumbered — and the
    reference to round-off; the kept view table is left as it was. A wrong renumbering, or a
    table missing a referenced vertex, breaks the image."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    monkeypatch.setattr("methods.zh_shadow.method.VERTEX_TABLE_POINTS", 0.0)
    m = small_model("creature")
    fast, full = m.with_render_config(), m.with_render_config()
    full.referenced_table = False
    calls = []
    orig = rt.referenced_vertices
    monkeypatch.setattr(rt, "referenced_vertices", lambda vi, N: calls.append(N) or orig(vi, N))
    from methods.zh_shadow import native as zn
    orig_lut = zn.referenced_lut   # (the fused pass's: the same vertices, found through the mask)
    monkeypatch.setattr(zn, "referenced_lut", lambda *a: calls.append(a[-1]) or orig_lut(*a))
    from methods.zh_shadow import native_threaded as z39
    orig_rl = z39.rest_lut   # (zh39s: the same vertices found with the second plane's screen, `threaded_helpers`)
    monkeypatch.setattr(z39, "rest_lut", lambda *a: (a[-1] and calls.append(a[5])) or orig_rl(*a))
    from methods.zh_shadow import native_split as z44
    # (zh44 / zh45: the same vertices found by the one-call split, `one_split`; zh46: `split` and its bound call,
    # `native_split.SplitBound`, both run `_run`)
    orig_split = z44._run

    def split(*a):
        r = orig_split(*a)
        if r is not None and r[0] == 0 and r[7] is not None:
            calls.append(a[-1])
        return r
    monkeypatch.setattr(z44, "_run", split)
    for fr in make_sequence(m.scene, kind, 3, seed=8):
        gb = make_gbuffer(m.scene, fr, 2)
        kept = fast._vtable
        n0 = len(calls)
        a = fast.render(fr, gb)
        b = full.render(fr, gb)
        assert fast.last_path == full.last_path == "planes"
        if fr.index > 0:
            assert len(calls) == n0 + 1 and fast._vtable is kept   # its own table, not kept
        assert torch.equal(a, b), (kind, fr.index, (a - b).abs().max().item())
        ref = m.with_render_config()._render_reference(fr, gb)
        assert (a - ref).abs().max().item() <= RENDER_TOL


@pytest.mark.parametrize("spans", (False, True))
def test_plane_term_keeps_the_albedo_free_part(small_model, spans):
    """`ZHShadow._plane_term` over a VB sequence (new albedos every frame, same pose and lighting):
    u = kd ⊙ (v · T¹(n0)) equals, bit for bit, the product with the albedos gathered per vertex
    (the old expression), and its albedo-free part is made once and kept. With `plane_term_spans`
    (zh38v) the rows of the regions without a specular term (those it makes: the key's last entry)
    equal it bit for bit and the others are 0."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    m = small_model("creature").with_render_config()
    m.plane_term_spans = spans
    u0 = None
    for fr in make_sequence(m.scene, "VB", 3, seed=9):
        m.render(fr, make_gbuffer(m.scene, fr, 2))
        assert m.last_path == "planes"
        geom, v = m._posed[1], m._posed[2]
        Wd, n0 = m._plane_u[2], torch.tensor(m._plane_u[0][3])
        kd_v = torch.stack([k for k, _, _ in m._region_materials(fr)]).index_select(0, geom.vertex_region)
        want = (v @ rt.diffuse_at(Wd, n0)) * kd_v
        only = m._plane_u[0][4]
        assert (only is not None) == spans
        if only is not None:
            made = torch.tensor(only).index_select(0, geom.vertex_region)
            assert made.any() and not made.all()
            want = torch.where(made[:, None], want, torch.zeros_like(want))
        assert torch.equal(m._plane_u[3], want)
        assert u0 is None or m._plane_u0[3] is u0
        u0 = m._plane_u0[3]


@pytest.mark.parametrize("kind", ("V", "VB"))
def test_plane_path_with_misses_equals_general_path(small_model, monkeypatch, kind):
    """A G-buffer with samples that miss (the bench creature's VB / VL views miss one sample in
    some frames) still takes `ZHShadow._render_planes`: the misses are 0, neither plane nor object
    samples, the image equals the general path's and the reference to round-off, with the same
    point counts (Q: the hits), clamp on and off. A miss counted as an object or a plane sample,
    or not zero, breaks the image or the counts."""
    from methods.zh_shadow.method import ZHShadow as Z
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    m = small_model("creature")
    for clamp in (True, False):
        fast, slow = m.with_render_config(clamp=clamp), m.with_render_config(clamp=clamp)
        for fr in make_sequence(m.scene, kind, 3, seed=7):
            gb0 = make_gbuffer(m.scene, fr, 2)
            gb = knock_out(gb0, 97 + fr.index, 5 + fr.index)
            assert bool(gb0.hit.all()) and not bool(gb.hit.all())
            a = fast.render(fr, gb)
            assert fast.last_path == "planes", (kind, fr.index, fast.last_path)
            with monkeypatch.context() as mp:
                mp.setattr(Z, "_render_planes", lambda *args, **kw: None)
                b = slow.render(fr, gb)
            assert slow.last_path == "samples"
            ca, cb = dict(fast._last_counts), dict(slow._last_counts)   # (before the reference sets its own)
            ref = m.with_render_config(clamp=clamp)._render_reference(fr, gb)
            assert ref.abs().max() > 0.05
            assert (a - b).abs().max().item() <= RENDER_TOL and (a - ref).abs().max().item() <= RENDER_TOL
            pa, pb = ca.pop("plane_vertices"), cb.pop("plane_vertices")
            assert ca == cb and ca["Q"] == int(gb.hit.sum())
            assert (pa() if callable(pa) else pa) == (pb() if callable(pb) else pb)


def _fast_vs_general(m, monkeypatch, fast_path: str, cases, n_frames: int, seed: int):
    """For each (kind, clamp) of ``cases`` and each frame of that sequence: render with ``m``'s
    fast path and with the ZHShadow method ``fast_path`` disabled (the general path), check both
    against each other and the reference to RENDER_TOL, and yield (kind, frame, fast, general)
    for the caller's own checks (paths taken, counts)."""
    from methods.zh_shadow.method import ZHShadow as Z
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    for kind, clamp in cases:
        fast, slow = m.with_render_config(clamp=clamp), m.with_render_config(clamp=clamp)
        for fr in make_sequence(m.scene, kind, n_frames, seed=seed):
            gb = make_gbuffer(m.scene, fr, 2)
            a = fast.render(fr, gb)
            with monkeypatch.context() as mp:
                mp.setattr(Z, fast_path, lambda *args, **kw: None)
                b = slow.render(fr, gb)
            ref = fast._render_reference(fr, gb)
            assert (a - b).abs().max().item() <= RENDER_TOL and (a - ref).abs().max().item() <= RENDER_TOL
            yield kind, fr, fast, slow


@pytest.mark.parametrize("name", ("creature", "sphere_plane"))
def test_relight_plane_path_equals_general_relight(small_model, monkeypatch, name):
    """`ZHShadow._relight_planes` (a lighting-only frame from the cached transfer, one plane shaded
    straight from the G-buffer into the pixels) is taken from the second L / E frame on, and equals
    `runtime.relight` + clamp + resolve (the general path) and the reference, clamp on and off."""
    cases = (("L", True), ("E", True), ("L", False))
    for kind, fr, fast, slow in _fast_vs_general(small_model(name), monkeypatch, "_relight_planes", cases, 3, 6):
        assert fast.last_path == ("planes" if fr.index == 0 else "relight-planes"), (name, kind, fast.last_path)
        assert fast._last_counts["Q"] == slow._last_counts["Q"]


def test_product_tensor_and_features():
    """G[a, j, i] reproduces the product y_j y_i pointwise (it is exact: the product is band-limited
    to 2n−1), and the monomial features map onto the order-B SH exactly on the sphere."""
    d, _ = gauss_legendre_sphere(7, 13, dtype=torch.float64)
    for order in (2, 3, 4, 5):
        B = 2 * order - 1
        G = rt.product_tensor(order)
        Yn, YB = sh_eval(d, order), sh_eval(d, B)
        prod = torch.einsum("dj,di->dji", Yn, Yn)
        assert (torch.einsum("da,aji->dji", YB, G) - prod).abs().max() <= 1e-12
        for diffuse in (True, False):
            _, rows, C = rt.monomial_basis(order, diffuse)
            feats = rt.features(d.T.contiguous(), order, diffuse)             # (K, D)
            assert (feats.T @ C - YB[:, rows]).abs().max() <= 1e-11, (order, diffuse)


def _front_vertices(g, fr) -> torch.Tensor:
    """(N,) the vertices facing the camera: n · (camera − x) > 0."""
    cam = torch.as_tensor(fr.camera.origin, dtype=torch.float32)
    return (g.N.float() * (cam - g.V.float())).sum(-1) > 0


def _referenced(g, gb) -> torch.Tensor:
    """(N,) the vertices the hit samples of ``gb`` reference: the corners of the faces they lie on."""
    ref = torch.zeros(g.num_vertices, dtype=torch.bool)
    ref[g.F.long()[gb.face[gb.hit].long()].reshape(-1)] = True
    return ref


def test_frame_cost_hand_count():
    """Bytes and flops of every frame kind on a tiny static scene, counted by hand (order 4,
    2 lobes: Σ(2l+1)² = 84 rotation entries, 44 non-zeros of M^α, 16 SH coefficients). The plane's
    samples (Lambert, all with the normal +y) are counted here from the G-buffer and the mesh,
    independently of `runtime.planar_groups`; the per-vertex terms over the vertices the hit samples
    reference (`_referenced`), with vertex shading the front-facing ones among them."""
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene

    sc = get_scene("sphere_plane", "test")
    m = ZHShadow(**SMALL)
    m.precompute(sc)
    assert m.frame_cost("V", 1000) is not None
    fr = sc.default_frame()
    gb = make_gbuffer(sc, fr, 1)
    P = gb.num_samples
    up = torch.tensor([0.0, 1.0, 0.0])
    g = sc.geometry()
    N, nF = g.num_vertices, g.F.shape[0]
    Q = int(gb.hit.sum())                                                    # covered samples
    Qs = int((gb.region[gb.hit] == sc.regions.index("sphere")).sum())        # the Phong sphere
    Qp = int((gb.hit & (gb.normal == up).all(-1)).sum())                     # on the plane (Lambert)
    ref = _referenced(g, gb)
    Nr = int(ref.sum())                                                      # referenced vertices
    Np = int(((g.N == up).all(-1) & (g.vertex_region == sc.regions.index("plane")) & ref).sum())  # plane's, referenced
    assert Qp == Q - Qs and Qp >= 1024 and 0 < Np <= int((g.vertex_region == sc.regions.index("plane")).sum())
    assert Nr < N                                                            # the sphere's far side is not seen
    J1 = 1                                                                   # static: the bias row
    H, W = sc.envmap.data.shape[:2]
    plane = 12 * 84 + 6 * 44 + Np * 6 * 16                                  # l to the plane's frame; v·T per vertex
    gbuf = P * (GBUFFER_BYTES_PER_SAMPLE + 8) + P * 12                     # + region, + output
    fixed = nF * 3 * 8 + 2 * 7 * 4 + 2 * 44 * 4 + 16 * 3 * 4                # F, BRDFs, M¹ + M^s, lighting
    vis = Nr * 15 * 4                                                        # min(16, 6·2 + 3) floats
    diff = 6 * 84 + 6 * 16 + 2 * 44                                           # rotate l, dot, M¹ v
    spec = 6 * 84 + 6 * 16 + 2 * 84 + 2 * 44 + 9                              # + rotate v, R
    per = Qs * (diff + spec + 6 * 16) + Q * (5 + 12) + Qp * 18 + plane        # + interpolation of v / of v·T
    for shading in ("sample", "sample-reference"):
        mm = m.with_render_config()
        (mm._render_reference if shading.endswith("reference") else mm.render)(fr, gb)
        c = mm.frame_cost("V", P)
        assert (c.bytes, c.flops) == (gbuf + fixed + vis, per), shading
    m.render(fr, gb)
    c = m.frame_cost("VBL", P)
    assert (c.bytes, c.flops) == (gbuf + fixed + vis, per + 6 * 84)
    mc = m.with_render_config(specular="cosine")                             # + M¹ v per specular point
    mc.render(fr, gb)
    c = mc.frame_cost("V", P)
    assert (c.bytes, c.flops) == (gbuf + fixed + vis, per + Qs * 2 * 44)
    c = m.frame_cost("P", P)                                                 # the model instead of the cache
    pose = Nr * (2 * J1 * 12 + 2 * (25 + 3 * 16))
    assert (c.bytes, c.flops) == (gbuf + fixed + (J1 * Nr * 12 + Nr * 3) * 4, per + pose)
    lo_b = P * 12 + fixed + Qs * 2 * 16 * 4 + Np * 16 * 4 + Qp * 12          # t_d, t_s; plane v, face + u, v
    lo_f = Qs * 2 * 6 * 16 + Q * 12 + Qp * 18 + plane + 6 * 84                # t·l per term, kd/ks, plane, rotate l
    c = m.frame_cost("L", P)
    assert (c.bytes, c.flops) == (lo_b, lo_f)
    c = m.frame_cost("E", P)
    proj = 2 * H * W * 3 * 7 + 2 * H * 16 * 3
    assert (c.bytes, c.flops) == (lo_b + H * W * 3 * 4, lo_f + proj)
    # once a lighting-only frame took the plane pass (`_relight_planes`): it reads v at the corners of
    # the plane faces its front-facing samples hit only — those distinct vertices instead of Np
    gb2 = make_gbuffer(sc, fr, 2)
    mp = m.with_render_config()
    light = dataclasses.replace(fr, changed=frozenset({"light"}))
    mp.render(fr, gb2)
    for _ in range(2):
        mp.render(light, gb2)
    if bool(gb2.hit.all()):
        assert mp.last_path == "relight-planes"
        onp = gb2.hit & (gb2.normal == up).all(-1) & ((gb2.normal * gb2.wo).sum(-1) > 0)
        Nc = torch.unique(g.F.long()[torch.unique(gb2.face[onp].long())]).numel()
        Np2 = int(((g.N == up).all(-1) & (g.vertex_region == sc.regions.index("plane")) & _referenced(g, gb2)).sum())
        assert 0 < Nc <= Np2
        P2, Q2 = gb2.num_samples, int(gb2.hit.sum())
        Qs2 = int((gb2.region[gb2.hit] == sc.regions.index("sphere")).sum())
        Qp2 = int((gb2.hit & (gb2.normal == up).all(-1)).sum())
        want_b = P2 * 12 + fixed + Qs2 * 2 * 16 * 4 + Nc * 16 * 4 + Qp2 * 12
        want_f = Qs2 * 2 * 6 * 16 + Q2 * 12 + Qp2 * 18 + 12 * 84 + 6 * 44 + Nc * 6 * 16 + 6 * 84
        c = mp.frame_cost("L", P2)
        assert (c.bytes, c.flops) == (want_b, want_f)
    big = m.frame_cost("V", 4 * P)                                           # no render on that size: all covered
    assert big.flops == 4 * P * (diff + 5 + 12 + 6 * 16 + spec)
    # vertex shading: the points are the front-facing vertices (a vertex facing away has radiance
    # 0: none of its work is compulsory), counted here from the mesh and the camera
    front = _front_vertices(g, fr) & ref                                     # front-facing AND referenced
    Nf, Nsf = int(front.sum()), int((front & (g.vertex_region == sc.regions.index("sphere"))).sum())
    assert 0 < Nsf < N - Np and Nf == Nsf + Np and Nf < int(_front_vertices(g, fr).sum())
    for shading in ("vertex", "vertex-reference"):
        mv = m.with_render_config(shading="vertex")
        (mv._render_reference if shading.endswith("reference") else mv.render)(fr, gb)
        assert mv._last_counts["groups"] == 0          # 625 plane vertices < PLANAR_MIN_POINTS: no plane
        c = mv.frame_cost("V", P)
        assert c.bytes == P * 17 + P * 12 + fixed + Nf * 15 * 4 + Nr * 6 * 4, shading
        assert c.flops == Nf * diff + Nsf * spec + Nf * (5 + 12) + P * 18, shading
        c = mv.frame_cost("P", P)                                            # the model of those vertices
        assert c.flops == Nf * (2 * J1 * 12 + 2 * (25 + 3 * 16)) + Nf * diff + Nsf * spec + Nf * (5 + 12) + P * 18
    mv.render(fr, gb)
    # a lighting-only frame on the same G-buffer (2×2 samples a pixel): before the interpolation
    # operator is kept, its 17 bytes per sample; after (the second such frame builds and reads it),
    # 8 per (pixel, vertex) pair with a hit sample — counted here from the G-buffer — + 4 per pixel
    gb2 = make_gbuffer(sc, fr, 2)
    P2, S2 = gb2.num_samples, gb2.spp_side ** 2
    mv.render(fr, gb2)
    lo_v = mv.frame_cost("L", P2).bytes
    light = dataclasses.replace(fr, changed=frozenset({"light"}))
    for _ in range(2):
        mv.render(light, gb2)
    hit = gb2.hit.nonzero().squeeze(-1)
    vid = g.F.long()[gb2.face[hit].long()]                                   # (hits, 3) vertices
    op = torch.unique((hit // S2)[:, None] * N + vid).numel() * 8 + P2 // S2 * 4
    assert op < P2 * 17                                                      # the operator is the smaller
    assert mv.frame_cost("L", P2).bytes == lo_v - P2 * 17 + op - nF * 3 * 8   # F no longer read
    assert math.isfinite(c.bytes) and c.flops > 0


def _left_half_misses(gb):
    """A copy of ``gb`` whose samples in the left half of the image miss (stored as `testing.gbuffers.knock_out`'s)."""
    S2 = gb.spp_side ** 2
    x = torch.arange(gb.width).view(1, gb.width, 1).expand(gb.height, gb.width, S2).reshape(-1)
    return dataclasses.replace(gb, **_misses(gb, x < gb.width // 2))


def _misses(gb, miss):
    """The G-buffer fields of ``gb`` with the samples ``miss`` (P,) bool stored as misses."""
    S = gb.spp_side
    return dict(hit=gb.hit & ~miss, face=gb.face.masked_fill(miss, -1), region=gb.region.masked_fill(miss, -1),
                bary=gb.bary.masked_fill(miss[:, None], 0.0), normal=gb.normal.masked_fill(miss[:, None], 0.0),
                position=gb.position.masked_fill(miss[:, None], 0.0),
                coverage=gb.coverage & ~miss.view(gb.height, gb.width, S * S).any(-1))


def test_frame_cost_counts_referenced_vertices_only():
    """A G-buffer whose left half misses references about half the mesh: the per-vertex terms of
    the count — a P frame's model product, posed normals and eq. 1 against a V frame's cached
    visibility ("sample"); the points and the positions and normals read ("vertex") — cover exactly
    the vertices its hit samples' faces touch (fewer than the full G-buffer's, counted here from
    the faces), for the fast path and the reference alike. A count over an unreferenced vertex
    (every vertex, or the front-facing ones) fails."""
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene

    sc = get_scene("sphere_plane", "test")
    m = ZHShadow(**SMALL)
    m.precompute(sc)
    fr = sc.default_frame()
    full = make_gbuffer(sc, fr, 1)
    gb = _left_half_misses(full)
    g = sc.geometry()
    ref, ref_full = _referenced(g, gb), _referenced(g, full)
    Nr = int(ref.sum())
    assert 0 < Nr < int(ref_full.sum()) < g.num_vertices and bool((ref <= ref_full).all())
    P, J1 = gb.num_samples, 1
    for path in ("render", "_render_reference"):
        mm = m.with_render_config()
        getattr(mm, path)(fr, gb)
        cP, cV = mm.frame_cost("P", P), mm.frame_cost("V", P)
        assert cP.bytes - cV.bytes == (J1 * Nr * 12 + Nr * 3) * 4 - Nr * 15 * 4, path
        assert cP.flops - cV.flops == Nr * (2 * J1 * 12 + 2 * (25 + 3 * 16)), path
    front = _front_vertices(g, fr)
    Nf = int((front & ref).sum())
    assert 0 < Nf < int((front & ref_full).sum())
    for path in ("render", "_render_reference"):
        mv = m.with_render_config(shading="vertex")
        getattr(mv, path)(fr, gb)
        assert mv._last_counts["Q"] == Nf, path
        cP, cV = mv.frame_cost("P", P), mv.frame_cost("V", P)
        assert cP.flops - cV.flops == Nf * (2 * J1 * 12 + 2 * (25 + 3 * 16)), path
        assert cP.bytes - cV.bytes == J1 * Nf * 12 * 4 - Nf * 15 * 4, path     # posed normals: in N_r·6
        mv.render(fr, full)                                                  # the full G-buffer: more
        cF = mv.frame_cost("V", P)
        Nrf, Nff = int(ref_full.sum()), int((front & ref_full).sum())
        assert cF.bytes - cV.bytes == (Nff - Nf) * 15 * 4 + (Nrf - Nr) * 6 * 4, path


def test_frame_cost_vertex_planes(monkeypatch):
    """Vertex shading with planes (threshold lowered to 64 points): the plane's 625 vertices and the
    sphere's pole (its normal is exactly +y too) form one plane over both regions; counted by hand."""
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene

    monkeypatch.setattr(rt, "PLANAR_MIN_POINTS", 64)
    sc = get_scene("sphere_plane", "test")
    m = ZHShadow(**SMALL, shading="vertex")
    m.precompute(sc)
    fr = sc.default_frame()
    gb = make_gbuffer(sc, fr, 1)
    m.render(fr, gb)
    P, g = gb.num_samples, sc.geometry()
    on = (g.N == torch.tensor([0.0, 1.0, 0.0])).all(-1)
    front = _front_vertices(g, fr) & _referenced(g, gb)                      # the points (test above)
    assert int(on.sum()) == 626 and bool(_front_vertices(g, fr)[on].all())
    Np = int((on & front).sum())                                             # the plane's, referenced
    Nf, Nsf = int(front.sum()), int((front & (g.vertex_region == sc.regions.index("sphere"))).sum())
    assert 64 <= Np < 626 and m._last_counts["groups"] == 1 and m._last_counts["planar"] == Np
    diff = 6 * 84 + 6 * 16 + 2 * 44
    spec = 6 * 84 + 6 * 16 + 2 * 84 + 2 * 44 + 9
    c = m.frame_cost("V", P)
    assert c.flops == 12 * 84 + 6 * 44 + Np * 6 * 16 + (Nf - Np) * diff + Nsf * spec + Nf * (5 + 12) + P * 18


def test_specular_parts_keep_equals_kept_columns():
    """`runtime.specular_parts` with ``keep`` (the front-facing vertices of vertex shading) = the
    kept columns of the parts made without it (the columns are independent), by position, float32
    to round-off; a region of no kept column and one with no specular term make no part."""
    g = torch.Generator().manual_seed(5)
    Q, n2 = 700, 64
    vT = torch.randn(n2, Q, generator=g)
    nT = torch.randn(3, Q, generator=g)
    nT = nT / nT.norm(dim=0)
    woT = torch.randn(3, Q, generator=g)
    woT = woT / woT.norm(dim=0)
    vreg = torch.cat([torch.zeros(300), torch.ones(250), torch.full((150,), 2.0)]).long()
    vreg[::7] = 3                                                # a region that is not one range
    keep = rt.dot_T(nT, woT) > 0
    keep[300:550] = False                                        # region 1: nothing kept
    alphas = [12.0, 30.0, None, 7.5]
    full = {r: (sp, t) for r, sp, t in rt.specular_parts(vT, nT, woT, vreg, alphas)}
    kept = rt.specular_parts(vT, nT, woT, vreg, alphas, keep=keep)
    assert sorted(r for r, _, _ in kept) == [0, 3]
    for r, sp, t in kept:
        want_pos = ((vreg == r) & keep).nonzero().squeeze(-1)
        assert torch.equal(sp, want_pos) and t.shape == (n2, want_pos.shape[0])
        fsp, ft = full[r]
        fpos = torch.arange(fsp[0], fsp[1]) if isinstance(fsp, tuple) else fsp
        want = ft[:, (fpos[:, None] == want_pos[None, :]).int().argmax(0)]
        assert (t - want).abs().max() <= 1e-6 * want.abs().max(), r
    # assembled, the columns not kept are zero
    ts = rt.specular_transfer(vT, nT, None, vreg, alphas, parts=kept)
    assert ts[:, ~keep].abs().max() == 0


def test_vertex_shading_front_only_transfer_equals_full(zh_scene, monkeypatch):
    """Vertex shading's t_s made for the front-facing vertices alone (`ZHShadow._render_vertex`,
    ``specular_parts(keep=front)``, the spans path adding it by position) = t_s made for every
    vertex of the specular regions, on V / VB / P frames and the L frames that reuse it (order 8,
    cosine: the physical setting); and both = the reference."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    fast, full = m.with_render_config(), m.with_render_config()
    fast.view_pass = full.view_pass = False   # (the torch path's t_s: `test_view_pass_equals_torch_path`)
    parts = rt.specular_parts

    def every_column(*args, keep=None, **kw):
        return parts(*args, **kw)

    for kind in ("V", "VB", "P", "L"):
        for f in make_sequence(m.scene, kind, 3, seed=4):
            gb = make_gbuffer(m.scene, f, 2)
            a = fast.render(f, gb)
            if fast._vertex_transfer is not None:   # (None: a P frame's `_front_radiance`, tested below)
                ts = fast._vertex_transfer[2]
                assert ts and all(not isinstance(sp, tuple) for _, sp, _ in ts)   # the positions path ran
                front = fast._vertex_transfer[3]
                assert sum(int(sp.shape[0]) for _, sp, _ in ts) < int(front.numel())
            with monkeypatch.context() as mp:
                mp.setattr(rt, "specular_parts", every_column)
                b = full.render(f, gb)
            assert (a - b).abs().max() <= 1e-5 * b.abs().max(), kind
    _check_sequence(fast.with_render_config(), "VB")


def test_pose_frame_front_only_radiance_equals_all_vertices(zh_scene):
    """A P frame's radiance with w and t_s made for the front-facing vertices alone
    (`ZHShadow._front_radiance`) = the path over all vertices (the same frame with "view" added to
    ``changed``: that branch is then not taken) to float32 round-off, = the reference; a later frame
    of the same pose under another camera makes every vertex's w again (cosine, order 8)."""
    import dataclasses

    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    fast, full = m.with_render_config(), m.with_render_config()
    frames = make_sequence(m.scene, "P", 3, seed=5)
    for i, f in enumerate(frames):
        gb = make_gbuffer(m.scene, f, 2)
        a = fast.render(f, gb)
        if i > 0:
            assert fast._vertex_diffuse is None and fast._vertex_transfer is None   # the front-only branch ran
            assert fast._posed[2] is None   # its visibility made for the front-facing vertices alone
        b = full.render(dataclasses.replace(f, changed=frozenset(f.changed | {"view"})), gb)
        assert full._vertex_diffuse is not None
        assert (a - b).abs().max() <= 1e-5 * b.abs().max(), i
    # the last pose under another camera: every vertex's w again (nothing partial was kept)
    g = dataclasses.replace(frames[-1], camera=m.scene.camera.orbited(0.3), changed=frozenset({"view"}))
    gb = make_gbuffer(m.scene, g, 2)
    a = fast.render(g, gb)
    assert fast._vertex_diffuse is not None and int(fast._vertex_diffuse[3].shape[1]) == m.scene.geometry().num_vertices
    want = fast._render_reference(g, gb)
    assert (a - want).abs().max() <= 1e-5 * want.abs().max()
    _check_sequence(fast.with_render_config(), "P", n_frames=3)


@pytest.mark.parametrize("n0", [(0.0, 1.0, 0.0), (0.0, 0.0, 1.0), (0.48, -0.6, 0.64)])
def test_plane_cosine_operator_equals_cosine_visibility(n0):
    """`runtime.plane_cosine_operator` K(n0) (float64, the factors applied to the identity) times
    visibility in the `zyz_rows` order = `cosine_visibility_zyz(…, ordered=True)` of every point
    with the normal n0 (float32, compiled) to round-off, = `cosine_visibility` of the world-space v
    (the conjugation M(R_n) M¹ M(R_n)ᵀ v), for a +y plane, the pole and a generic normal."""
    from methods.core.sh_rotation import sh_rotation_matrix

    order, Q = 8, 300
    g = torch.Generator().manual_seed(11)
    vz = torch.randn(order * order, Q, generator=g)
    n = torch.tensor(n0)
    nT = (n / n.norm())[:, None].expand(3, Q).contiguous()
    K = rt.plane_cosine_operator(tuple(float(x) for x in nT[:, 0].tolist()), order)
    assert K.dtype == torch.float64 and K.shape == (order * order, order * order)
    rows = rt.zyz_rows(order)
    want = rt.cosine_visibility_zyz(vz.index_select(0, rows), nT, ordered=True)
    got = (K @ vz.index_select(0, rows).double()).float()
    assert (got - want).abs().max() <= 1e-5 * want.abs().max()
    # the same as the world-space conjugation of v = M(R_n) v_zyz (R_n = (e1, e2, n), `zyz_axes`)
    e1, e2 = rt.zyz_axes(nT[:, :1].double())
    R = torch.stack([torch.cat(e1), torch.cat(e2), nT[:, 0].double()], 1)
    v = sh_rotation_matrix(R, order).float() @ vz
    assert (got - rt.cosine_visibility(v, nT)).abs().max() <= 1e-5 * want.abs().max()


def test_pose_frame_plane_operator_equals_per_vertex_w(zh_scene, monkeypatch):
    """A P frame whose ground's front-facing vertices share one normal (`ZHShadow._front_planes`,
    plane threshold lowered to 64 vertices for the test-size creature) shades them by the plane's
    operator (`runtime.plane_cosine_operator`: no w of their own) = the path making every front
    vertex's w (``plane_operators`` off) to float32 round-off, = the reference (order 8, cosine)."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    monkeypatch.setattr(rt, "PLANAR_MIN_POINTS", 64)
    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    fast, slow = m.with_render_config(), m.with_render_config()
    slow.plane_operators = False
    fast.view_pass = slow.view_pass = False   # (w by `cosine_visibility_zyz`: the torch path; the C pass's planes:
    #                                           `test_pose_pass_equals_torch_path`)
    used, cv = [], rt.cosine_visibility_zyz

    def counted(vzT, nT, **kw):
        used.append(int(vzT.shape[1]))
        return cv(vzT, nT, **kw)

    monkeypatch.setattr(rt, "cosine_visibility_zyz", counted)
    for i, f in enumerate(make_sequence(m.scene, "P", 3, seed=5)):
        gb = make_gbuffer(m.scene, f, 2)
        used.clear()
        b = slow.render(f, gb)
        wide = list(used)
        used.clear()
        a = fast.render(f, gb)
        if i > 0:   # the front-only branch: w for fewer columns (not the plane's)
            g = m.scene.geometry(torch.as_tensor(f.pose).float())
            front = _front_vertices(g, f) & _referenced(g, gb)                # (`referenced_work`)
            ground = g.vertex_region == m.scene.regions.index("ground")
            assert wide[0] == int(front.sum())
            assert len(used) == 1 and used[0] == wide[0] - int((front & ground).sum()), (used, wide)
        assert (a - b).abs().max() <= 1e-5 * b.abs().max(), i
        want = fast._render_reference(f, gb)
        assert (a - want).abs().max() <= RENDER_TOL, i


def test_warm_up_frame_compiles_the_front_only_pose_path(zh_scene, monkeypatch):
    """The harness's warm-up frame (a full change, rendered inside `warming`) also compiles the
    kernels of the front-only P path (`ZHShadow._front_radiance`): the P frames after it compile
    nothing while timed (perf run of ec5aced: the first P frame compiled one Inductor graph, 310 ms
    against 12-16). Dynamo's caches are reset first, so kernels compiled by other tests do not
    hide a missing warm-up."""
    import torch._dynamo
    from torch._dynamo.utils import counters

    from methods.core import fused as fz
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if not fz.compile_enabled():
        pytest.skip("PRTBENCH_COMPILE=0: nothing compiles")
    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    frames = make_sequence(m.scene, "P", 3, seed=5)
    gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
    monkeypatch.setattr(fz, "_warmed", set())
    torch._dynamo.reset()
    with fz.warming():
        m.render(frames[0], gbs[0])
    graphs = int(counters["stats"]["unique_graphs"])
    for f, gb in zip(frames[1:], gbs[1:]):
        m.render(f, gb)
        assert m._vertex_diffuse is None                                       # the front-only path ran
    assert int(counters["stats"]["unique_graphs"]) == graphs


def test_vertex_radiance_by_ranges_equals_gathered(zh_scene):
    """Vertex shading's radiance made region range by region range (`ZHShadow._region_spans`, the
    albedos folded into the lighting, t_s as `runtime.specular_parts`) = the general path (albedos
    gathered per vertex, t_s assembled by `runtime.specular_transfer`), both = the reference on P
    and L frames (cosine, order 8: the physical setting's path)."""
    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    fast = m.with_render_config()
    slow = m.with_render_config()
    slow._region_spans = lambda vreg, regions: None
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    assert fast._region_spans(m.scene.geometry().vertex_region, len(m.scene.regions)) is not None
    for f in make_sequence(m.scene, "P", 2, seed=3):
        gb = make_gbuffer(m.scene, f, 2)
        a, b = fast.render(f, gb), slow.render(f, gb)
        assert (a - b).abs().max() <= 1e-5 * b.abs().max()
    _check_sequence(slow, "P")
    _check_sequence(slow, "L", n_frames=3)


def test_resolve_matrix_int32_equals_int64(zh_scene):
    """`method._int32_csr` (the kept resolve matrix of lighting-only vertex frames with int32
    indices: the 8 bytes per non-zero `ZHShadow._resolve_bytes` counts) gives the same products as
    `gouraud.resolve_matrix`'s int64 CSR, bit for bit; the matrix a vertex-shaded L sequence keeps
    is the int32 one, and its frames equal the reference."""
    from methods.core import gouraud
    from methods.zh_shadow.method import _int32_csr
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    scene = zh_scene("creature")
    f = make_sequence(scene, "L", 1, seed=2)[0]
    gb, geom = make_gbuffer(scene, f, 2), scene.geometry()
    S = gouraud.resolve_matrix(geom.F.T, gb.face, gb.bary, gb.hit, gb.height, gb.width, gb.spp_side,
                               int(geom.num_vertices))
    S32 = _int32_csr(S)
    assert S32.crow_indices().dtype == S32.col_indices().dtype == torch.int32
    assert torch.equal(S32.crow_indices().long(), S.crow_indices()) and torch.equal(S32.col_indices().long(),
                                                                                     S.col_indices())
    x = torch.randn(int(geom.num_vertices), 3, generator=torch.Generator().manual_seed(3))
    assert torch.equal(S32 @ x, S @ x)
    assert _int32_csr(S32) is S32
    m = ZHShadow(**SMALL, order=4, shading="vertex", specular="cosine")
    m.precompute(scene)
    _check_sequence(m, "L", n_frames=3)
    assert m._resolve_matrix[2] is not None and m._resolve_matrix[2].col_indices().dtype == torch.int32


def test_lighting_frames_over_front_vertices_equal_every_vertex(zh_scene):
    """Vertex-shaded lighting-only frames under a kept resolve matrix shade the front-facing
    vertices alone (`ZHShadow._compact_transfer`: their w and t_s columns gathered once) = the path
    over every vertex (``compact_lighting`` off) to float32 round-off, = the reference, on L and E
    sequences (order 8, cosine), and a view frame after them drops what was gathered."""
    import dataclasses

    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    for kind in ("L", "E"):
        fast, slow = m.with_render_config(), m.with_render_config()
        slow.compact_lighting = False
        frames = make_sequence(m.scene, kind, 4, seed=6)
        for i, f in enumerate(frames):
            gb = make_gbuffer(m.scene, f, 2)
            a, b = fast.render(f, gb), slow.render(f, gb)
            if i > 0:   # the kept matrix's frames: the front-facing columns gathered once
                idx, wf = fast._vertex_compact[2][:2]
                N = m.scene.geometry().num_vertices
                assert 0 < idx.numel() < N and wf.shape[1] == idx.numel() and fast._resolve_matrix[2] is not None
                assert slow._vertex_compact is None
            assert (a - b).abs().max() <= 1e-5 * b.abs().max(), (kind, i)
            want = fast._render_reference(f, gb)
            assert (a - want).abs().max() <= RENDER_TOL, (kind, i)
        g = dataclasses.replace(frames[-1], camera=m.scene.camera.orbited(0.3), changed=frozenset({"view"}))
        gb = make_gbuffer(m.scene, g, 2)
        a = fast.render(g, gb)
        assert fast._resolve_matrix[2] is None and fast._vertex_compact is None
        assert (a - fast._render_reference(g, gb)).abs().max() <= RENDER_TOL


def test_view_frames_reuse_the_diffuse_radiance(zh_scene):
    """Vertex-shaded view / BRDF frames (V, VB) reuse the per-vertex albedo-free diffuse radiance
    lᵀ w / π (`ZHShadow._diffuse_ranges`, kept while lighting and w stay), scale it by the albedos
    and add the new specular term = the radiance made with the specular term every frame
    (``diffuse_cache`` off) to float32 round-off, = the reference; a frame with new lighting (VL)
    takes the path without it (nothing to reuse; order 8, cosine)."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    for kind in ("V", "VB", "VL"):
        fast, slow = m.with_render_config(), m.with_render_config()
        slow.diffuse_cache = False
        fast.view_pass = slow.view_pass = False   # (the torch path's cache: the C pass keeps none)
        kept = []
        for i, f in enumerate(make_sequence(m.scene, kind, 4, seed=7)):
            gb = make_gbuffer(m.scene, f, 2)
            a, b = fast.render(f, gb), slow.render(f, gb)
            kept.append(None if fast._vertex_rad_d is None else fast._vertex_rad_d[2])
            assert slow._vertex_rad_d is None
            assert (a - b).abs().max() <= 1e-6 * b.abs().max(), (kind, i)
            want = fast._render_reference(f, gb)
            assert (a - want).abs().max() <= RENDER_TOL, (kind, i)
        # frame 0 (a full change) and every VL frame: new lighting, the radiance made as before
        assert kept[0] is None and (all(x is kept[1] for x in kept[2:]) and kept[1] is not None if kind != "VL"
                                    else all(x is None for x in kept)), (kind, kept)
    assert m.with_render_config().memory()["relight_transfer"] == 0   # (before any frame)


def test_pose_product_is_the_model_product_at_any_thread_count():
    """`runtime._pose_product` ([pose, 1] · X in `world_visibility`, compiled) equals the float64
    product to float32 round-off and gives the same bits with 1 and 2 threads — it replaced a
    one-row product run under `torch_threads(1)` (MKL splits such a product's reduction over the
    threads on AVX-512 machines), on both layouts `world_visibility` passes."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import runtime as rt

    g = torch.Generator().manual_seed(3)
    a = torch.randn(11, generator=g)
    for X in (torch.randn(11, 20, 3001, generator=g).transpose(1, 2),   # point-minor (J1, N, d) view
              torch.randn(11, 3001, 20, generator=g)):                  # point-major
        pm = X.transpose(1, 2).is_contiguous()
        Xf = X.transpose(1, 2).reshape(11, -1) if pm else X.reshape(11, -1)
        want = (a.double()[None] @ Xf.double())[0]
        outs = []
        for n in (1, 2):
            with torch_threads(n):
                outs.append(rt._pose_product(a, Xf))
        assert torch.equal(outs[0], outs[1])
        assert float((outs[0].double() - want).abs().max()) <= 1e-6 * float(want.abs().max())


def test_referenced_mask_native_equals_torch():
    """`native.referenced_mask` (the C loop) = `referenced_mask_torch` = the corners of the hit
    samples' faces counted here, on a G-buffer with misses (face −1) and on one whose missed
    samples keep a stale face id (the hit mask, not the id, decides)."""
    from methods.zh_shadow import native as zn
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene

    sc = get_scene("sphere_plane", "test")
    fr = sc.default_frame()
    g = sc.geometry()
    full = make_gbuffer(sc, fr, 2)
    half = _left_half_misses(full)
    stale = dataclasses.replace(half, face=full.face)                        # misses with real face ids
    for gb in (full, half, stale):
        want = _referenced(g, gb) if gb is not stale else _referenced(g, half)
        a = zn.referenced_mask(g.F, gb.face, gb.hit, g.num_vertices)
        b = zn.referenced_mask_torch(g.F, gb.face, gb.hit, g.num_vertices)
        assert torch.equal(a, want) and torch.equal(b, want)
    from methods.core import native
    from methods.core.fused import compile_enabled

    assert zn._kernel() is not None or not native.compiler() or not compile_enabled()   # (the loop ran)


def test_vertex_referenced_work_equals_every_front_vertex(zh_scene):
    """Vertex shading with a P frame's w, t_s and radiance, and a lighting frame's compact transfer,
    made for the front-facing vertices the hit samples reference alone (``referenced_work``) = made
    for every front-facing vertex (the oracle, ``referenced_work = False``) and = the reference, to
    float32 round-off, on V / VB / VL / P / L sequences (order 8, cosine) — and lighting frames
    under one camera, then a view change that brings vertices no earlier sample referenced into
    view under the kept pose, then lighting frames there (the kept compact transfer must not be
    reused for them)."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    fast, slow = m.with_render_config(), m.with_render_config()
    slow.referenced_work = False
    for kind in ("V", "VB", "VL", "P", "L"):
        for f in make_sequence(m.scene, kind, 3, seed=6):
            gb = make_gbuffer(m.scene, f, 2)
            a, b = fast.render(f, gb), slow.render(f, gb)
            assert (a - b).abs().max() <= 1e-5 * b.abs().max(), (kind, f.index)
            if kind == "L" and f.index == 2:   # (the second lighting frame: the compact transfer)
                assert 0 < fast._vertex_compact[2][0].numel() < slow._vertex_compact[2][0].numel()
    f0 = make_sequence(m.scene, "V", 1, seed=6)[0]
    seen = None
    for cam in (m.scene.camera, m.scene.camera.orbited(2.5)):
        f = dataclasses.replace(f0, camera=cam, changed=frozenset({"view"}))
        gb = make_gbuffer(m.scene, f, 2)
        fast.render(f, gb), slow.render(f, gb)
        light = dataclasses.replace(f, changed=frozenset({"light"}))
        for _ in range(2):                                                 # (the second: the compact path)
            a, b = fast.render(light, gb), slow.render(light, gb)
            assert (a - b).abs().max() <= 1e-5 * b.abs().max()
        cols = torch.zeros(m.scene.geometry().num_vertices, dtype=torch.bool)
        cols[fast._vertex_compact[2][0]] = True
        if seen is not None:
            assert int((cols & ~seen).sum()) > 0                           # vertices new to the compact set
        seen = cols
    want = fast._render_reference(light, gb)
    assert (a - want).abs().max() <= 1e-5 * want.abs().max()


@pytest.mark.parametrize("order,diffuse,specular", ((4, True, True), (5, True, False)))
def test_sample_terms_native_equals_compiled(order, diffuse, specular, monkeypatch):
    """`native.sample_terms` (the C loop) = the compiled `runtime._sample_block` bit for bit (the same
    products, sums and the AVX2 or AVX-512 reduction tree of Inductor's vectors here) and = its eager function to float32 round-off, at 1 and 2
    threads, on random points (some with ωo = n: R = n, some grazing); through `runtime.sample_terms`
    too. None (the compiled kernel then runs) for a vertex id outside U's rows, a variant it lacks,
    float64, and with ``PRTBENCH_ZH_NATIVE=0``."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn

    g = torch.Generator().manual_seed(order)
    D = 2 * order - 2
    K = ((D + 1) * (D + 2) // 2 + 3 if diffuse else 0) + ((D + 1) * (D + 2) // 2 + D * (D + 1) // 2 if specular else 0)
    N, Q = 97, 5003
    U = torch.randn(N, 3, K, generator=g)
    vi = torch.randint(0, N, (Q, 3), generator=g)
    b = torch.rand(Q, 3, generator=g)
    b = b / b.sum(1, keepdim=True)
    nT = torch.randn(3, Q, generator=g)
    nT = nT / nT.norm(dim=0)
    woT = torch.randn(3, Q, generator=g)
    woT[:, :50] = nT[:, :50]                                                  # R = n
    woT[:, 50:100] = torch.stack([nT[1, 50:100], -nT[0, 50:100], torch.zeros(50)])   # n·ωo = 0
    woT = woT / woT.norm(dim=0)
    got = zn.sample_terms(U, vi, b, nT, woT, D, diffuse, specular)
    if got is None:   # no compiler, PRTBENCH_COMPILE=0, or Inductor on neither AVX2 nor AVX-512: nothing to check
        assert zn._terms_lib() is None
        pytest.skip("the native sample terms are not available here")
    with torch_threads(2):
        assert torch.equal(zn.sample_terms(U, vi, b, nT, woT, D, diffuse, specular), got)
    eager = rt.rows(rt._sample_block.eager(U, vi, b, nT, woT, D, diffuse, specular))
    assert float((got - eager).abs().max()) <= 1e-5 * float(eager.abs().max())
    U_, vi_, b_, n_, wo_ = U.clone(), vi.clone(), b.clone(), nT.clone(), woT.clone()
    torch._dynamo.maybe_mark_dynamic(U_, 0)
    for t, d in ((vi_, 0), (b_, 0), (n_, 1), (wo_, 1)):
        torch._dynamo.maybe_mark_dynamic(t, d)
    compiled = rt.rows(rt._sample_block(U_, vi_, b_, n_, wo_, D, diffuse, specular))
    assert torch.equal(got, compiled)
    assert torch.equal(rt.sample_terms(U, vi.to(torch.int32), b, nT, woT, order, diffuse=diffuse, specular=specular),
                       got)
    bad = vi.clone()
    bad[Q // 2, 1] = N
    assert zn.sample_terms(U, bad, b, nT, woT, D, diffuse, specular) is None
    assert zn.sample_terms(U.double(), vi, b.double(), nT.double(), woT.double(), D, diffuse, specular) is None
    assert zn.sample_terms(U[..., :K - 8].contiguous(), vi, b, nT, woT, D, diffuse, not specular) is None
    monkeypatch.setenv("PRTBENCH_ZH_NATIVE", "0")
    assert zn.sample_terms(U, vi, b, nT, woT, D, diffuse, specular) is None
    assert torch.equal(rt.sample_terms(U, vi, b, nT, woT, order, diffuse=diffuse, specular=specular), got)


def test_native_split_equals_torch_split(small_model):
    """`ZHShadow._native_split` (`native.plane_mask`, `native.object_rows`) = the torch path's plane
    search and gathers bit for bit: the plane, its mask and the object samples' positions, vertex ids,
    barycentric weights, normals, ωo and regions, at 1 and 2 threads; images of V / VB / P frames equal
    with it on and off (the oracle: ``native_split = False``); False where the torch path finds no
    single plane (alcove: two planes) or one with a specular term — and not used when more than
    `SPLIT_MAX_MISSES` samples miss."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    m = small_model("creature")
    if not zn.split_available():
        pytest.skip("the native split is not available here")
    fr = make_sequence(m.scene, "V", 1, seed=2)[0]
    gb = make_gbuffer(m.scene, fr, 2)
    geom = m.scene.geometry()
    F32 = geom.F.to(torch.int32)
    assert m.scene.regions == ["creature", "ground"]
    assert m._native_split(gb, [False, True], F32) is False   # a specular term on the plane (the ground)
    for spec in ([False, False], [True, False]):
        for nt in (1, 2):
            with torch_threads(nt):
                got = m._native_split(gb, spec, F32)
            groups, mask, rest, vi, b, nT, woT, reg = got
            n0 = groups[0][0]
            nrm = gb.normal
            eq = (nrm[:, 0] == n0[0]) & (nrm[:, 1] == n0[1]) & (nrm[:, 2] == n0[2])
            want_rest = (~eq).nonzero().squeeze(-1)
            assert int(eq.sum()) * 2 > gb.num_samples and torch.equal(mask, eq) and torch.equal(rest, want_rest)
            bu, bv = gb.bary.index_select(0, rest).unbind(-1)
            assert torch.equal(vi, F32.index_select(0, gb.face.index_select(0, rest)))
            assert torch.equal(b, torch.stack([1.0 - bu - bv, bu, bv], -1))
            assert torch.equal(nT, rt.rows(nrm.index_select(0, rest))) and torch.equal(reg, gb.region[rest])
            assert torch.equal(woT, gb.wo.T.index_select(1, rest))
    fast = m.with_render_config()
    fast.fma_terms = False   # (the fused pass with `sample_terms`' bits; the regrouped dot: test_zh37v.py)
    slow = m.with_render_config()
    slow.native_split = False
    for kind in ("V", "VB", "P"):
        for f in make_sequence(m.scene, kind, 2, seed=4):
            g = make_gbuffer(m.scene, f, 2)
            a, c = fast.render(f, g), slow.render(f, g)
            assert fast.last_path == slow.last_path == "planes", (kind, fast.last_path)
            assert torch.equal(a, c), kind
            ca, cb = dict(fast._last_counts), dict(slow._last_counts)
            assert ca.pop("plane_vertices")() == cb.pop("plane_vertices")() and ca == cb
    half = _left_half_misses(gb)
    calls = []
    with mock.patch.object(type(fast), "_native_split", lambda self, *a: calls.append(1)):
        fast.render(fr, half)
    assert not calls
    al = small_model("alcove")
    fa = make_sequence(al.scene, "V", 1, seed=2)[0]
    assert al._native_split(make_gbuffer(al.scene, fa, 2), [False] * len(al.scene.regions),
                            al.scene.geometry().F.to(torch.int32)) is False


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 8, 12])
def test_project_latlong_polar_folded_equals_torch(order):
    """`native.project_latlong_polar_folded` (ZH's C pass: the texel pairs half a turn apart summed
    for the even-m and differenced for the odd-m factors, fused multiply-adds; 4- and, on AVX-512, 8-double
    vectors) = `sh.project_latlong_polar` (the oracle) to float64 round-off on random maps (even widths,
    the bench map's 256 × 512, a non-contiguous view, 1–3 threads: the same bits at each) — and the pass
    ran (not None) where a compiler is; an odd width is left to `methods.core.sh_native` (None)."""
    from methods.core import native
    from methods.core.fused import compile_enabled
    from methods.core.sh import project_latlong_polar as oracle
    from methods.zh_shadow import native as zn

    runs = native.compiler() is not None and compile_enabled() and zn.terms_switched_on()
    g = torch.Generator().manual_seed(100 + order)
    for H, W in ((64, 128), (37, 76), (256, 512), (3, 2)):
        img = torch.rand(H, W, 3, generator=g) * 4.0 - 1.0
        views = (img, torch.rand(W, H, 3, generator=g).transpose(0, 1))     # (a strided view too)
        for x in views:
            want = oracle(x, order)
            first = None
            for nt in (1, 2, 3):
                with mock.patch.object(torch, "get_num_threads", lambda: nt):
                    got = zn.project_latlong_polar_folded(x, order)
                if not runs:
                    assert got is None
                    continue
                assert got is not None and got.dtype == torch.float64 and got.shape == (order * order, 3)
                assert float((got - want).abs().max()) <= 1e-13 * float(want.abs().max()), (H, W, nt)
                first = got if first is None else first
                assert torch.equal(got, first), (H, W, nt)   # the same bits at any thread count
    assert zn.project_latlong_polar_folded(torch.rand(8, 15, 3, generator=g), order) is None   # (odd width)


@pytest.mark.parametrize("order", [4, 8])
def test_project_latlong_polar_native_equals_torch(order, monkeypatch):
    """`native.project_latlong_polar` (ZH's folded C pass over the float32 texels, `methods.core.sh_native`'s
    for odd widths; `ZHShadow._lighting`'s new map) = `sh.project_latlong_polar` (the oracle: a float64 copy, a GEMM and an einsum) to float64
    round-off on random maps (odd sizes, a non-contiguous view, 1 and 2 threads); the switch off
    (``PRTBENCH_ZH_NATIVE=0``) and a float64 map give the oracle itself."""
    from methods.core import native, sh_native
    from methods.core.fused import compile_enabled
    from methods.core.sh import project_latlong_polar as oracle
    from methods.zh_shadow import native as zn

    g = torch.Generator().manual_seed(order)
    for H, W in ((64, 128), (37, 75), (256, 512)):
        img = torch.rand(H, W, 3, generator=g) * 4.0
        views = (img, torch.rand(W, H, 3, generator=g).transpose(0, 1))     # (a strided view too)
        for x in views:
            want = oracle(x, order)
            for nt in (1, 2):
                with mock.patch.object(torch, "get_num_threads", lambda: nt):
                    got = zn.project_latlong_polar(x, order)
                assert got.dtype == torch.float64 and got.shape == (order * order, 3)
                assert float((got - want).abs().max()) <= 1e-13 * float(want.abs().max()), (H, W, nt)
    assert sh_native.available() or not native.compiler() or not compile_enabled()   # (the loop ran)
    x = torch.rand(16, 32, 3, generator=g)
    assert torch.equal(zn.project_latlong_polar(x.double(), order), oracle(x.double(), order))
    monkeypatch.setenv("PRTBENCH_ZH_NATIVE", "0")
    assert torch.equal(zn.project_latlong_polar(x, order), oracle(x, order))


def test_resolve_packed_native_equals_csr_product(zh_scene, monkeypatch):
    """`native.csr_product` of `native.csr_pack` (the kept resolve matrix as a 4-wide table + a CSR
    tail, one C pass) = torch's CSR product bit for bit: the creature's resolve matrix (int32 and int64
    indices) and a random CSR with empty rows and rows of up to 12 entries, at 1 and 2 threads, and with
    its columns renumbered over a compact x (`native.csr_compact`); a vertex-shaded L sequence renders
    the same images with ``native_resolve`` off (torch's product of the scattered radiance)."""
    from methods.core import gouraud, native
    from methods.core.fused import compile_enabled
    from methods.zh_shadow import native as zn
    from methods.zh_shadow.method import _int32_csr
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    scene = zh_scene("creature")
    f = make_sequence(scene, "L", 1, seed=2)[0]
    gb, geom = make_gbuffer(scene, f, 2), scene.geometry()
    N = int(geom.num_vertices)
    S = gouraud.resolve_matrix(geom.F.T, gb.face, gb.bary, gb.hit, gb.height, gb.width, gb.spp_side, N)
    g = torch.Generator().manual_seed(4)
    R, Nr = 300, 50
    ln = torch.randint(0, 13, (R,), generator=g)
    ln[::7] = 0
    crow = torch.zeros(R + 1, dtype=torch.int64)
    crow[1:] = ln.cumsum(0)
    nnz = int(crow[-1])
    rnd = torch.sparse_csr_tensor(crow, torch.randint(0, Nr, (nnz,), generator=g), torch.randn(nnz, generator=g),
                                  (R, Nr))
    for M in (S, _int32_csr(S), rnd):
        pk = zn.csr_pack(M)
        if pk is None:
            assert zn._csr_lib() is None or not zn.terms_switched_on()
            pytest.skip("the native resolve is not available here")
        x = torch.randn(int(M.shape[1]), 3, generator=g)
        for nt in (1, 2):
            with mock.patch.object(zn, "MIN_ROWS_PER_CSR_THREAD", 16), mock.patch.object(torch, "get_num_threads",
                                                                                        lambda: nt):
                got = zn.csr_product(pk, x)
            assert torch.equal(got, M @ x), nt
        idx = torch.randperm(int(M.shape[1]), generator=g)[: int(M.shape[1]) // 3].sort().values
        xz = torch.zeros_like(x).index_copy_(0, idx, x[idx])                  # zero off idx
        xc = torch.cat([x[idx], x.new_zeros(1, 3)])
        assert torch.equal(zn.csr_product(zn.csr_compact(pk, idx), xc), M @ xz)
    assert zn._csr_lib() is not None or not native.compiler() or not compile_enabled()
    assert zn.csr_product(zn.csr_pack(rnd), torch.randn(Nr + 1, 3)) is None          # (a wrong size: the oracle)
    bad = torch.sparse_csr_tensor(crow, torch.full((nnz,), Nr), torch.ones(nnz), (R, Nr + 1))
    assert zn.csr_pack(torch.sparse_csr_tensor(crow, torch.full((nnz,), Nr), torch.ones(nnz), (R, Nr))) is None
    assert zn.csr_pack(bad) is not None
    m = ZHShadow(**SMALL, order=4, shading="vertex", specular="cosine")
    m.precompute(scene)
    slow = m.with_render_config()
    slow.native_resolve = False
    fast = m.with_render_config()
    fast.fused_relight_vertex = False   # (zh39o: that one C call's radiance is float32 round-off from the
    #                                     products', `test_zh39o.test_fused_relight_*`; here the product alone)
    for fr in make_sequence(scene, "L", 4, seed=3):
        gbf = make_gbuffer(scene, fr, 2)
        assert torch.equal(fast.render(fr, gbf), slow.render(fr, gbf))
    assert fast._resolve_packed is not None and fast._resolve_packed[1] is not None
    assert fast._resolve_compact is not None          # (the compact radiance read by the resolve)
    assert slow._resolve_packed[1] is None


def test_face_pixels_native_equals_compiled(small_model):
    """`native.face_pixels` (the C loop) = `method._plane_face_pixels` (the compiled pass, its oracle)
    bit for bit: random face tables and faces (−1 = no plane sample) with clamp on and off, at 1 and
    2 threads, the component-major barycentrics the G-buffer stores; None for a face outside the table;
    L / E sequences of the creature render the same images (to float32 round-off: `native.relight_add`)
    with ``native_plane_pass`` off."""
    from methods.core import native
    from methods.core.fused import compile_enabled
    from methods.zh_shadow import native as zn
    from methods.zh_shadow.method import _plane_face_pixels
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    g = torch.Generator().manual_seed(6)
    n, S2, Fp = 20000, 4, 700
    face = torch.randint(-1, Fp, (n, S2), generator=g, dtype=torch.int64).to(torch.int32)
    face[:50] = -1
    bary = torch.rand(n * S2, 2, generator=g).T.contiguous().T          # (P, 2) column-major, as the G-buffer
    bT = bary.T.view(2, n, S2)
    uf = torch.randn(Fp, 9, generator=g)
    for clamp in (True, False):
        want = _plane_face_pixels(face, bT, uf, clamp)
        for nt in (1, 2):
            with mock.patch.object(zn, "MIN_PIXELS_PER_THREAD", 64), mock.patch.object(torch, "get_num_threads",
                                                                                      lambda: nt):
                got = zn.face_pixels(face, bT, uf, clamp)
            if got is None:
                assert zn._face_pixels_lib() is None or not zn.terms_switched_on()
                pytest.skip("the native plane pass is not available here")
            assert torch.equal(got, want), (clamp, nt)
    assert zn._face_pixels_lib() is not None or not native.compiler() or not compile_enabled()
    assert zn.face_pixels(face, bT, uf[:Fp - 1].contiguous(), True) is None          # a face outside the table
    m = small_model("creature")
    fast = m.with_render_config()
    slow = m.with_render_config()
    slow.native_plane_pass = False
    for kind in ("L", "E"):
        for fr in make_sequence(m.scene, kind, 4, seed=4):
            gb = make_gbuffer(m.scene, fr, 2)
            a, b = fast.render(fr, gb), slow.render(fr, gb)
            assert fast.last_path == slow.last_path
            # (the object samples' terms by `native.relight_add`: float32 round-off against the GEMMs)
            assert float((a - b).abs().max()) <= 1e-6 * float(b.abs().max()), (kind, fr.index)
        assert fast.last_path == "relight-planes", kind


def test_plane_pixels_native_equals_compiled(small_model):
    """`native.plane_pixels` (the C loop of a P / V frame's plane pass) = `method._plane_pixels` (the
    compiled pass, its oracle) bit for bit: random faces, corners, normals (some facing away, some with
    n·ωo = 0 exactly), plane masks and per-vertex terms (some negative: the clamp) with clamp on and off,
    at 1 and 2 threads, in the layouts `_render_planes` passes (the G-buffer's component-major
    barycentrics and ωo); None for a plane sample's face outside the table or a corner outside u; P / V /
    VB frames of the creature render the same images with ``native_plane_pixels`` off."""
    from methods.core import native
    from methods.core.fused import compile_enabled
    from methods.zh_shadow import native as zn
    from methods.zh_shadow.method import _plane_pixels
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    g = torch.Generator().manual_seed(7)
    n, S2, M, N = 20000, 4, 900, 500
    P = n * S2
    face = torch.randint(0, M, (n, S2), generator=g, dtype=torch.int64)
    bary = torch.rand(P, 2, generator=g).T.contiguous().T                # (P, 2) column-major, as the G-buffer
    nrm = torch.nn.functional.normalize(torch.randn(P, 3, generator=g), dim=1)
    wo = torch.nn.functional.normalize(torch.randn(P, 3, generator=g), dim=1)
    wo[:300] = torch.stack([nrm[:300, 1], -nrm[:300, 0], torch.zeros(300)], 1)   # n·ωo = 0 (or round-off)
    wo = wo.T.contiguous().T                                                   # column-major, as the G-buffer
    mask = torch.rand(P, generator=g) < 0.8
    fv = torch.randint(0, N, (3, M), generator=g, dtype=torch.int64)
    u = torch.randn(N, 3, generator=g)
    args = (face, bary.T.view(2, n, S2), nrm.view(n, S2, 3), wo.T.view(3, n, S2), mask.view(n, S2), fv, u)
    for clamp in (True, False):
        want = _plane_pixels(*args, clamp)
        for nt in (1, 2):
            with mock.patch.object(zn, "MIN_PIXELS_PER_THREAD", 64), mock.patch.object(torch, "get_num_threads",
                                                                                      lambda: nt):
                got = zn.plane_pixels(*args, clamp)
            if got is None:
                assert zn._plane_pixels_lib() is None or not zn.terms_switched_on()
                pytest.skip("the native plane pass is not available here")
            assert torch.equal(got, want), (clamp, nt)
    assert zn._plane_pixels_lib() is not None or not native.compiler() or not compile_enabled()
    on = int((mask & ((nrm * wo).sum(1) > 0.1)).nonzero()[0])               # a plane sample facing the viewer
    bad = face.clone()
    bad.view(-1)[on] = M
    assert zn.plane_pixels(bad, *args[1:], True) is None                      # a face outside the table
    assert zn.plane_pixels(*args[:6], u[:N - 1].contiguous(), True) is None    # a corner outside u
    m = small_model("creature")
    fast = m.with_render_config()
    fast.fma_terms = False   # (the fused pass with `sample_terms`' bits; the regrouped dot: test_zh37v.py)
    slow = m.with_render_config()
    slow.native_plane_pixels = False
    for kind in ("P", "V", "VB"):
        for fr in make_sequence(m.scene, kind, 4, seed=5):
            gb = make_gbuffer(m.scene, fr, 2)
            a, b = fast.render(fr, gb), slow.render(fr, gb)
            assert fast.last_path == slow.last_path
            assert torch.equal(a, b), (kind, fr.index)
        assert fast.last_path == "planes", kind


def test_relight_add_native_equals_gemms(monkeypatch):
    """`native.relight_add` (one C pass over the object samples of a lighting-only plane frame) = the
    torch path it replaces — (l ⊙ kd)ᵀ td + (l ⊙ ks)ᵀ ts, the clamp and ``index_add_`` per channel ÷ S² —
    to float32 round-off: with and without ts, clamp on and off, Q not a multiple of 8, repeated pixels,
    the same bits on 1, 2 and 3 threads;
    False (img untouched) for a pixel outside the image, a wrong shape or the switch off."""
    from methods.zh_shadow import native as zn

    g = torch.Generator().manual_seed(8)
    n2, Q, npix = 16, 1003, 400
    td, ts = torch.randn(n2, Q, generator=g), torch.randn(n2, Q, generator=g)
    ld, ls = torch.randn(n2, 3, generator=g), torch.randn(n2, 3, generator=g)
    pix = torch.sort(torch.randint(0, npix, (Q,), generator=g)).values
    img0 = torch.rand(npix, 3, generator=g)
    for with_ts in (True, False):
        for clamp in (True, False):
            img = img0.clone()
            if not zn.relight_add(img, td, ts if with_ts else None, ld, ls if with_ts else None, pix, clamp, 0.25):
                assert zn._relight_lib() is None or not zn.terms_switched_on()
                pytest.skip("the native relight is not available here")
            for nt in (2, 3):   # split between pixels over the team: the same bits
                img2 = img0.clone()
                with mock.patch.object(zn, "MIN_SAMPLES_PER_RELIGHT_THREAD", 64), \
                        mock.patch.object(torch, "get_num_threads", lambda: nt):
                    assert zn.relight_add(img2, td, ts if with_ts else None, ld, ls if with_ts else None, pix, clamp,
                                          0.25)
                assert torch.equal(img2, img), nt
            rad = ld.T @ td
            if with_ts:
                rad = torch.addmm(rad, ls.T, ts)
            if clamp:
                rad = rad.clamp_min(0.0)
            want = img0.clone()
            for c in range(3):
                want[:, c].index_add_(0, pix, rad[c], alpha=0.25)
            assert float((img - want).abs().max()) <= 1e-5 * float(want.abs().max()), (with_ts, clamp)
    img = img0.clone()
    bad = pix.clone()
    bad[-1] = npix
    assert not zn.relight_add(img, td, ts, ld, ls, bad, True, 0.25) and torch.equal(img, img0)
    assert not zn.relight_add(img, td, ts[:, :-1].contiguous(), ld, ls, pix, True, 0.25) and torch.equal(img, img0)
    monkeypatch.setenv("PRTBENCH_ZH_NATIVE", "0")
    assert not zn.relight_add(img, td, ts, ld, ls, pix, True, 0.25) and torch.equal(img, img0)


def test_screen_counts_native_equals_torch_screening():
    """`native.screen_counts` (one C pass) = `runtime.first_plane`'s torch screening (every 16th point
    against each of the 8 candidates, componentwise float equality) on normals with planes of several
    sizes, −0.0 against 0.0 and NaNs, as (3, m) contiguous rows and as the transpose of (m, 3); and
    `first_plane` with those counts = without them."""
    from methods.zh_shadow import native as zn

    g = torch.Generator().manual_seed(9)
    m = 5003
    n = torch.randn(m, 3, generator=g)
    n[100:2500] = torch.tensor([0.0, 1.0, 0.0])
    n[3000:3400] = torch.tensor([0.0, -0.0, 1.0])
    n[3400:3500] = torch.tensor([0.0, 0.0, 1.0])
    n[4000:4100, 1] = float("nan")
    for cur in (n.T, n.T.contiguous(), n[:1000].T, n[4000:4100].T):
        got = zn.screen_counts(cur)
        if got is None:
            assert zn._screen_lib() is None or not zn.terms_switched_on()
            pytest.skip("the native screening is not available here")
        k = cur.shape[1]
        sub = cur[:, ::16]
        want = [int(((sub[0] == cur[0, c * k // 8]) & (sub[1] == cur[1, c * k // 8]) & (sub[2] == cur[2, c * k // 8]))
                    .sum()) for c in range(8)]
        assert got == want
        for mp in (16, 64, 1024):
            a, b = rt.first_plane(cur, mp), rt.first_plane(cur, mp, screen=got)
            assert (a is None) == (b is None)
            if a is not None:
                assert torch.equal(a[0], b[0]) and torch.equal(a[1], b[1]) and a[2] == b[2]


def _skip_without_c_compiler() -> None:
    """Skip a test of a C pass on a machine without a C compiler (the passes cannot build there)."""
    from methods.core import native as core_native

    if core_native.compiler() is None:   # pragma: no cover - no C compiler here
        pytest.skip("no C compiler")


def _count_native_calls(monkeypatch, name: str = "specular_conjugate") -> list[bool]:
    """Wrap `native.<name>` (a C pass that returns None when it declines) so a test sees whether
    each call ran the C pass (True) or declined (False)."""
    import methods.zh_shadow.native as zn

    calls: list[bool] = []
    real = getattr(zn, name)

    def counted(*a, **kw):
        out = real(*a, **kw)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(zn, name, counted)
    return calls


@pytest.mark.parametrize("order", [2, 4, 8])
def test_specular_conjugate_native_equals_compiled(order, monkeypatch):
    """`runtime.specular_parts` by the C pass (`native.specular_conjugate`: R, the angles, both halves
    and the blocks per point) = by `reflect_T` + `zonal_conjugate` (the compiled passes and GEMMs), to
    float32 round-off, on parts that are a range of columns and parts by position, with and without
    ``keep``, points at both poles of R and exponents whose plans differ; the same bits at 1 and 2
    threads; and both within float32 round-off of the float64 conjugation."""

    _skip_without_c_compiler()
    g = torch.Generator().manual_seed(11)
    Q, n2 = 701, order * order
    vT = torch.randn(n2, Q, generator=g)
    nT = torch.randn(3, Q, generator=g)
    woT = torch.randn(3, Q, generator=g)
    nT[:, 5], woT[:, 5] = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 0.0, 1.0])     # R on the pole
    nT[:, 6], woT[:, 6] = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 0.0, -1.0])    # and below it
    nT, woT = nT / nT.norm(dim=0), woT / woT.norm(dim=0)
    vreg = torch.cat([torch.zeros(300), torch.ones(250), torch.full((151,), 2.0)]).long()
    vreg[0:300:7] = 3                                            # a region that is not one range
    alphas = [12.0, 30.0, None, 7.5]
    calls = _count_native_calls(monkeypatch)
    for keep in (None, rt.dot_T(nT, woT) > 0):
        monkeypatch.setattr(rt, "native_conjugate", False)
        want = rt.specular_parts(vT, nT, woT, vreg, alphas, keep=keep)
        monkeypatch.setattr(rt, "native_conjugate", True)
        got = {}
        for threads in (1, 2):
            with torch_threads_(threads):
                got[threads] = rt.specular_parts(vT, nT, woT, vreg, alphas, keep=keep)
        assert calls and all(calls)                               # the C pass ran
        kinds = set()
        for (r, sp, t), (r1, sp1, t1), (r2, sp2, t2) in zip(got[1], got[2], want):
            assert r == r1 == r2
            kinds.add(type(sp))
            if isinstance(sp, tuple):
                assert sp == sp1 == sp2
                cols = torch.arange(sp[0], sp[1])
            else:
                assert torch.equal(sp, sp1) and torch.equal(sp, sp2)
                cols = sp
            assert torch.equal(t, t1)                              # the same bits at any thread count
            assert (t - t2).abs().max() <= 2e-6 * t2.abs().max(), (order, r)
            a = alphas[r]
            R = rt.reflect_T(nT[:, cols].double(), woT[:, cols].double())
            ref = rt.zonal_conjugate(vT[:, cols].double(), R, ("phong", a), (a + 1.0) / (2.0 * math.pi))
            scale = ref.abs().max()
            assert (t.double() - ref).abs().max() <= 2e-6 * scale, (order, r)
            assert (t2.double() - ref).abs().max() <= 2e-6 * scale, (order, r)
        assert kinds == ({tuple, torch.Tensor} if keep is None else {torch.Tensor})


def torch_threads_(n: int):
    from methods.core.threads import torch_threads

    return torch_threads(n)


@pytest.mark.parametrize("order", [2, 4, 8])
def test_cosine_visibility_zyz_native_equals_compiled(order, monkeypatch):
    """`runtime.cosine_visibility_zyz` by the C pass (`native.specular_conjugate`,
    ``lifted``: the blocks of X M¹ and the second half per point) = by `_blocked_product` + `_zyz_up`
    (the compiled pass and GEMMs), to float32 round-off, on every column and on a column range of a
    wider array (`ZHShadow._front_radiance`'s view), normals on both poles; the same bits at 1 and 2
    threads."""

    _skip_without_c_compiler()
    g = torch.Generator().manual_seed(12)
    Q, n2 = 517, order * order
    vzT = torch.randn(n2, Q, generator=g)
    nT = torch.randn(3, Q, generator=g)
    nT[:, 3], nT[:, 4] = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 0.0, -1.0])
    nT = nT / nT.norm(dim=0)
    calls = _count_native_calls(monkeypatch)
    for a0, a1 in ((0, Q), (100, 333)):
        v, n_ = vzT[:, a0:a1], nT[:, a0:a1]
        monkeypatch.setattr(rt, "native_conjugate", False)
        want = rt.cosine_visibility_zyz(v, n_, ordered=True)
        monkeypatch.setattr(rt, "native_conjugate", True)
        got = {}
        for threads in (1, 2):
            with torch_threads_(threads):
                got[threads] = rt.cosine_visibility_zyz(v, n_, ordered=True)
        assert calls and all(calls)
        assert torch.equal(got[1], got[2])
        assert (got[1] - want).abs().max() <= 2e-6 * want.abs().max(), (order, a0)


def test_native_split_with_few_misses_equals_torch_split(small_model):
    """A G-buffer where a few samples miss (up to `SPLIT_MAX_MISSES`: the bench views miss 0-1) is split
    by the native passes too (`ZHShadow._native_split` with ``misses``: the misses neither on the plane
    nor among the object's rows), the same rows bit for bit as the torch path's and the same images
    and counts on V / VB / P frames (the oracle: ``native_split = False``), at 1 and 2 threads; more
    misses than that: the torch path."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import method as zm
    from methods.zh_shadow import native as zn
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    m = small_model("creature")
    if not zn.split_available():
        pytest.skip("the native split is not available here")
    fast = m.with_render_config()
    fast.fused_planes = False   # (`_native_split` itself: the fused pass has its own test with misses)
    slow = m.with_render_config()
    slow.native_split = False
    results = []
    split = type(fast)._native_split

    def spy(self, *a):
        out = split(self, *a)
        results.append(out)
        return out

    for kind in ("V", "VB", "P"):
        for f in make_sequence(m.scene, kind, 2, seed=4):
            g = make_gbuffer(m.scene, f, 2)
            on_plane = g.normal[:, 2] == g.normal[:, 2].mode().values   # (the ground's samples, about)
            pos = torch.cat([on_plane.nonzero().squeeze(-1)[[3, 1000, -5]], (~on_plane & g.hit).nonzero().squeeze(-1)[[0, 7, -1]]])
            miss = torch.zeros(g.num_samples, dtype=torch.bool)
            miss[pos] = True
            gm = dataclasses.replace(g, **_misses(g, miss))
            assert int((~gm.hit).sum()) == 6 <= zm.SPLIT_MAX_MISSES
            for nt in (1, 2):
                results.clear()
                with torch_threads(nt), mock.patch.object(type(fast), "_native_split", spy):
                    a = fast.render(f, gm)
                with torch_threads(nt):
                    c = slow.render(f, gm)
                assert len(results) == 1 and isinstance(results[0], tuple), (kind, nt)   # the native split ran
                assert fast.last_path == slow.last_path == "planes", (kind, fast.last_path)
                assert torch.equal(a, c), (kind, nt)
                ca, cb = dict(fast._last_counts), dict(slow._last_counts)
                assert ca.pop("plane_vertices")() == cb.pop("plane_vertices")() and ca == cb
    many = torch.zeros(g.num_samples, dtype=torch.bool)
    many[:zm.SPLIT_MAX_MISSES + 1] = True
    results.clear()
    with mock.patch.object(type(fast), "_native_split", spy):
        fast.render(f, dataclasses.replace(g, **_misses(g, many)))
    assert not results


@pytest.mark.parametrize("kind", ("V", "VB", "VL", "P"))
def test_fused_planes_equal_separate_passes(small_model, monkeypatch, kind):
    """`ZHShadow._fused_planes` (the plane frame's sample stage as one C pass, `native.fused_pixels`) is
    taken on the creature's plane frames and equals, bit for bit, the separate passes (``fused_planes``
    off: `native.object_rows`, `sample_terms`, the front test, the clamp, `plane_pixels`, ``index_add_``),
    with the same counts for `frame_cost` — with the kept table and with a frame's own table of the
    referenced vertices (`native.referenced_lut`), clamp on and off, with misses, at 1 and 2 threads (the
    pixels split between them) — and the reference to round-off. A wrong front test, clamp, order of the
    sums, renumbering or miss handling breaks the image."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if not zn.fused_available(6, True, True):
        pytest.skip("the fused pass is not available here")
    monkeypatch.setattr(zn, "MIN_PIXELS_PER_THREAD", 1)   # (test size: 4,096 pixels, one thread otherwise)
    m = small_model("creature")
    for table_points in (0.0, 1e9):   # every non-view frame builds its own referenced table / none does
        monkeypatch.setattr("methods.zh_shadow.method.VERTEX_TABLE_POINTS", table_points)
        for clamp, misses, nt in ((True, False, 1), (False, False, 2), (True, True, 2)):
            fast, slow = m.with_render_config(clamp=clamp), m.with_render_config(clamp=clamp)
            slow.fused_planes = False
            fast.fma_terms = False   # (the regrouped dot: float32 round-off against this pass, test_zh37v.py)
            for fr in make_sequence(m.scene, kind, 3, seed=11):
                gb = make_gbuffer(m.scene, fr, 2)
                if misses:
                    gb = knock_out(gb, 397 + fr.index, 3 + fr.index)
                    assert 0 < int((~gb.hit).sum()) <= 64
                with torch_threads(nt):
                    a = fast.render(fr, gb)
                    b = slow.render(fr, gb)
                assert fast.last_path == slow.last_path == "planes" and not slow.last_fused
                # (no table kept or built: the point GEMMs, not fused — a non-view frame without tables)
                assert fast.last_fused == (kind == "V" or fr.index == 0 or table_points == 0.0), (kind, fr.index)
                assert torch.equal(a, b), (kind, clamp, misses, nt, fr.index, (a - b).abs().max().item())
                ca, cb = dict(fast._last_counts), dict(slow._last_counts)
                assert ca.pop("plane_vertices")() == cb.pop("plane_vertices")() and ca == cb
                if fr.index == 1 and nt == 1:
                    ref = m.with_render_config(clamp=clamp)._render_reference(fr, gb)
                    assert (a - ref).abs().max().item() <= RENDER_TOL


def test_fused_planes_helpers_equal_torch():
    """The fused path's helpers = what they replace: `native.screen8` = `native.screen_counts` (strided and
    contiguous rows), `native.rest_screen` = `screen_counts` of the gathered rows off a mask, and
    `native.referenced_lut` = `runtime.referenced_vertices` of the rows' face corners (hits only)."""
    from methods.zh_shadow import native as zn

    if zn._fused_lib() is None:
        pytest.skip("the fused pass is not available here")
    g = torch.Generator().manual_seed(3)
    nrm = torch.randn(5000, 3, generator=g)
    nrm[::3] = nrm[7]
    nrm[1::5] = nrm[11]
    for cur in (nrm.T, nrm.T.contiguous(), nrm[:37].T):
        assert zn.screen8(cur) == zn.screen_counts(cur)
    mask = torch.rand(5000, generator=g) < 0.6
    m = int((~mask).sum())
    assert zn.rest_screen(mask, nrm, m) == zn.screen_counts(rt.rows(nrm[~mask]))
    assert zn.rest_screen(mask, nrm, m + 1) is None
    F32 = torch.randint(0, 300, (200, 3), generator=g, dtype=torch.int32) * 2
    face = torch.randint(0, 200, (5000,), generator=g)
    hit = torch.rand(5000, generator=g) < 0.9
    for h in (None, hit):
        keep = ~mask if h is None else ~mask & h
        idx, lut = zn.referenced_lut(mask, h, face, F32, 700)
        want_idx, want_vi = rt.referenced_vertices(F32.index_select(0, face[keep]), 700)
        assert torch.equal(idx, want_idx) and lut.dtype == torch.int32
        assert torch.equal(lut.long()[F32.index_select(0, face[keep]).long()], want_vi.long())
        assert bool((lut[torch.isin(torch.arange(700), idx, invert=True)] == -1).all())
    assert zn.referenced_lut(mask, None, face, F32, 500) is None   # a corner outside [0, N)


def _torch_view_radiance(pos, nT, w, cam, vreg, mats, light, clamp):
    """The torch path's per-vertex radiance of a view frame (`ZHShadow._render_vertex` with ``view_pass``
    off): `_view_directions`, the front test `runtime.dot_T` > 0, kd ⊙ (lᵀ w) / π, + ks ⊙ (lᵀ t_s) by
    `runtime.specular_parts` (keep = front), masked, clamped."""
    woT = cam[:, None] - rt.rows(pos)
    woT = woT / (woT * woT).sum(0, keepdim=True).sqrt().clamp_min(1e-12)
    front = rt.dot_T(nT, woT) > 0
    kd = torch.stack([k for k, _, _ in mats], 1).index_select(1, vreg)
    ks = torch.stack([k for _, k, _ in mats], 1).index_select(1, vreg)
    rad = ((light.T * (1.0 / math.pi)) @ w) * kd
    tsf = rt.specular_transfer(w, nT, woT, vreg, [a for _, _, a in mats],
                               parts=rt.specular_parts(w, nT, woT, vreg, [a for _, _, a in mats], keep=front))
    if tsf is not None:
        rad = rad + (light.T @ tsf) * ks
    rad = rad * front
    return (rad.clamp_min(0.0) if clamp else rad).T.contiguous(), front


@pytest.mark.parametrize("order", [4, 8])
def test_view_radiance_native_equals_torch(order, monkeypatch):
    """`native.view_radiance` (one C pass: ωo, the front test, the diffuse and specular radiance with t_s
    in registers) = the torch path (`_torch_view_radiance`) to float32 round-off, the front-facing set
    bit for bit — normals built within ~1e-8 of perpendicular to ωo included, where an unfused or a
    differently rounded n·ωo flips the test —, on regions that are ranges of 16 consecutive front
    vertices, of scattered ones (the permute and the gather loads), a vertex count off the 16-lane
    blocks, R on both poles, two exponents and a diffuse region; clamped and not; the same bits at 1
    and 2 threads."""
    import methods.zh_shadow.native as zn

    _skip_without_c_compiler()
    g = torch.Generator().manual_seed(21)
    N, n2 = 1203, order * order
    pos = torch.randn(N, 3, generator=g)
    cam = torch.tensor([0.4, 2.5, 3.0])
    wo = cam - pos
    wo = wo / wo.norm(dim=1, keepdim=True)
    nrm = torch.randn(N, 3, generator=g)
    nrm = nrm / nrm.norm(dim=1, keepdim=True)
    nrm[:300] = wo[:300] * torch.sign(torch.randn(300, 1, generator=g))   # region 0: runs of front ones
    tang = torch.linalg.cross(wo[600:900], torch.randn(300, 3, generator=g), dim=1)
    nrm[600:900] = tang / tang.norm(dim=1, keepdim=True) + 1e-8 * torch.randn(300, 3, generator=g)   # grazing
    nrm[700] = torch.tensor([0.0, 0.0, 1.0])
    nT = rt.rows(nrm / nrm.norm(dim=1, keepdim=True))
    w = torch.randn(n2, N, generator=g)
    light = torch.randn(n2, 3, generator=g)
    vreg = torch.cat([torch.zeros(300), torch.ones(300), torch.full((400,), 2.0), torch.full((203,), 3.0)]).long()
    spans = [(0, 300), (300, 600), (600, 1000), (1000, 1203)]
    kd = [torch.rand(3, generator=g) for _ in spans]
    ks = [torch.rand(3, generator=g) for _ in spans]
    alphas = [12.0, None, 30.0, 1.0]
    mats = [(kd[r], ks[r] if alphas[r] is not None else torch.zeros(3), alphas[r]) for r in range(4)]
    plans = [None if a is None else rt._block_plan(("phong", a), order, False, torch.float32, "cpu",
                                                   (a + 1.0) / (2.0 * math.pi)) for a in alphas]
    setup = zn.view_setup(light, torch.stack(kd), torch.stack([k for _, k, _ in mats]), plans,
                          rt._conjugate_tables(order, torch.float32, "cpu"))
    for clamp in (False, True):
        want, wfront = _torch_view_radiance(pos, nT, w, cam, vreg, mats, light, clamp)
        got = {}
        for threads in (1, 2):
            with torch_threads_(threads):
                got[threads] = zn.view_radiance(setup, spans, pos, nT, w, cam, clamp)
        assert got[1] is not None
        rad, front = got[1]
        assert torch.equal(rad, got[2][0]) and torch.equal(front, got[2][1])   # the same bits at any thread count
        assert torch.equal(front, wfront)                                     # the same front-facing set
        assert 0 < int(front[600:900].sum()) < 300
        assert (rad - want).abs().max() <= 2e-6 * want.abs().max(), (order, clamp)
        assert bool((rad[~front] == 0).all())
        if clamp:
            assert bool((rad >= 0).all())
        else:
            assert bool((rad < 0).any())


def test_view_pass_equals_torch_path(zh_scene, monkeypatch):
    """Vertex-shaded view frames of a kept pose (V, VB, VL, VBL; order 8, cosine) by one C pass
    (`ZHShadow._view_radiance`, `native.view_radiance`) = the torch path (``view_pass`` off) to float32
    round-off, with the same counts (the same front-facing set), the same bits at 1 and 2 threads, and
    = the reference; a frame 0 (a full change) and a lighting-only frame take the torch path (the t_s a
    following lighting frame reuses is made there)."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _skip_without_c_compiler()
    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    calls = _count_native_calls(monkeypatch, "view_radiance")
    for kind in ("V", "VB", "VL", "VBL", "L"):
        fast, fast2, slow = m.with_render_config(), m.with_render_config(), m.with_render_config()
        slow.view_pass = slow.own_resolve = False
        for i, f in enumerate(make_sequence(m.scene, kind, 3, seed=8)):
            gb = make_gbuffer(m.scene, f, 2)
            c0 = len(calls)
            a = fast.render(f, gb)
            assert calls[c0:] == ([True] if i > 0 and kind != "L" else []), (kind, i)
            with torch_threads_(2):
                a2 = fast2.render(f, gb)
            b = slow.render(f, gb)
            assert torch.equal(a, a2), (kind, i)
            assert (a - b).abs().max() <= 2e-6 * b.abs().max(), (kind, i)
            assert fast.frame_cost(kind, gb.num_samples) == slow.frame_cost(kind, gb.num_samples), (kind, i)
            want = fast._render_reference(f, gb)
            assert (a - want).abs().max() <= RENDER_TOL, (kind, i)


@pytest.mark.parametrize("name", ["resolve", "resolve_table", "resolve_vector"])
def test_resolve_native_equals_gouraud_resolve(name):
    """`native.resolve` (zh_shadow's C loop, the range check in it) and `native.resolve_table` (session 35:
    every face's corner colours in a face table first) and `native.resolve_vector` (session 38: a pixel's 2×2
    samples as one AVX-512 vector) = `gouraud.resolve` bit for bit — misses, faces whose
    corners repeat, an image split over 2 threads and one that is not —; a hit sample's face or a read corner
    out of range raises ValueError (as `gouraud.resolve`) instead of being read."""
    from methods.core import gouraud
    import methods.zh_shadow.native as zn

    _skip_without_c_compiler()
    resolve = getattr(zn, name)
    g = torch.Generator().manual_seed(31)
    N, M = 900, 1500
    F = torch.randint(0, N, (M + 1, 3), generator=g)[:M]   # (a row M after it: a missed check reads valid ids)
    F[7] = torch.tensor([5, 5, 9])
    values = torch.randn(N, 3, generator=g)
    for H, W in ((128, 130), (40, 24)):
        P = H * W * 4
        face = torch.randint(0, M, (P,), generator=g)
        hit = torch.rand(P, generator=g) > 0.1
        face[~hit] = -1
        bary = torch.rand(2, P, generator=g).T * 0.5                     # column-major, as the G-buffer's
        want = gouraud.resolve(values, F.T, face, bary, hit, H, W, 2)
        for threads in (1, 2):
            with torch_threads_(threads):
                got = resolve(values, F, face, bary, hit, H, W, 2)
            assert got is not None and torch.equal(got, want), (H, threads)
        bad = face.clone()
        bad[int(hit.nonzero()[-1])] = M                                  # a hit sample's face out of range
        with pytest.raises(ValueError):
            resolve(values, F, bad, bary, hit, H, W, 2)
        Fb = F.clone()
        Fb[int(face[int(hit.nonzero()[3])]), 1] = N                       # a read corner out of range
        with pytest.raises(ValueError):
            resolve(values, Fb, face, bary, hit, H, W, 2)


@pytest.mark.parametrize("planes", [True, False])
def test_pose_pass_equals_torch_path(zh_scene, monkeypatch, planes):
    """A P frame's front-facing radiance (`ZHShadow._front_radiance`) by one C pass (`native.pose_radiance`:
    w from the ZYZ-frame visibility, the diffuse term, t_s and the specular term per vertex, none of them
    written) = the torch path (``view_pass`` off: `cosine_visibility_zyz`, `specular_parts`,
    `_radiance_ranges`) to float32 round-off, with the same counts, the same bits at 1 and 2 threads, and =
    the reference; with the ground by its plane operator (beside the pass) and without (a diffuse region in
    the pass)."""
    import methods.zh_shadow.native as zn
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _skip_without_c_compiler()
    if planes:   # (the test-size ground's front vertices as a plane: `test_pose_frame_plane_operator_equals_per_vertex_w`)
        monkeypatch.setattr(rt, "PLANAR_MIN_POINTS", 64)
    ops = []
    pco = rt.plane_cosine_operator
    monkeypatch.setattr(rt, "plane_cosine_operator", lambda *a: ops.append(a) or pco(*a))
    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    calls: list[bool] = []
    pr = zn.pose_radiance

    def counted(*a, **kw):
        out = pr(*a, **kw)
        calls.append(out)
        return out

    monkeypatch.setattr(zn, "pose_radiance", counted)
    fast, fast2, slow = m.with_render_config(), m.with_render_config(), m.with_render_config()
    slow.view_pass = slow.own_resolve = False
    for x in (fast, fast2, slow):
        x.plane_operators = planes
    for i, f in enumerate(make_sequence(m.scene, "P", 3, seed=9)):
        gb = make_gbuffer(m.scene, f, 2)
        c0 = len(calls)
        a = fast.render(f, gb)
        if i > 0:
            assert calls[c0:] == [True], i
        with torch_threads_(2):
            a2 = fast2.render(f, gb)
        b = slow.render(f, gb)
        assert torch.equal(a, a2), i
        assert (a - b).abs().max() <= 2e-6 * b.abs().max(), i
        assert fast.frame_cost("P", gb.num_samples) == slow.frame_cost("P", gb.num_samples), i
        want = fast._render_reference(f, gb)
        assert (a - want).abs().max() <= RENDER_TOL, i
    assert bool(ops) == planes   # (the plane operator beside the pass, or none)


@pytest.mark.parametrize("order", [2, 4, 8])
def test_block_products_rows_at_a_time_equal_one_row_at_a_time(order, monkeypatch):
    """The plans' block products several rows at a time (`native._CONJ_HELPERS`' ``block_products``,
    ``BROWS`` = 4: independent multiply-add chains) = one row at a time (``-DBROWS=1``, the loop before
    session 34) bit for bit, in all three passes that take them: `specular_conjugate` (``lifted`` and
    not: a region that is a range, one by position, ``keep``), `view_radiance` and `pose_radiance`
    (its lifted plan in place) — the same sums in the same order per row; blocks whose row count is not
    a multiple of 4 (orders 2 and 4) take the one-row tail."""
    import methods.zh_shadow.native as zn
    from methods.core import native as core_native

    _skip_without_c_compiler()

    def rows1(name, source, sigs):
        return lambda: core_native.load(name + "_rows1", source, sigs, extra_flags=(
            "-fopenmp", "-ffp-contract=fast", *core_native.isa_flags(), *zn._avx512_flags(), "-DBROWS=1"))

    libs = {"_conj_lib": rows1("zh_conj", zn._CONJ_SOURCE, zn._CONJ_SIGNATURES),
            "_view_lib": rows1("zh33v_view", zn._VIEW_SOURCE, zn._VIEW_SIGNATURES)}
    assert all(f() is not None for f in libs.values())
    g = torch.Generator().manual_seed(41)
    N, n2 = 803, order * order
    pos = torch.randn(N, 3, generator=g)
    cam = torch.tensor([0.4, 2.5, 3.0])
    nrm = torch.randn(N, 3, generator=g)
    nT = rt.rows(nrm / nrm.norm(dim=1, keepdim=True))
    woT = cam[:, None] - rt.rows(pos)
    woT = woT / woT.norm(dim=0, keepdim=True)
    w = torch.randn(n2, N, generator=g)
    light = torch.randn(n2, 3, generator=g)
    vreg = torch.cat([torch.zeros(300), torch.ones(300), torch.full((203,), 2.0)]).long()
    vreg[0:300:7] = 3                                            # (specular_parts: a region by position)
    spans = [(0, 300), (300, 600), (600, 803)]
    alphas = [12.0, 30.0, 7.5]
    kd = torch.rand(3, 3, generator=g)
    ks = torch.rand(3, 3, generator=g)
    plans = [rt._block_plan(("phong", a), order, False, torch.float32, "cpu", (a + 1.0) / (2.0 * math.pi))
             for a in alphas]
    lifted = rt._block_plan(("phong", 1.0), order, True, torch.float32, "cpu")
    tables = rt._conjugate_tables(order, torch.float32, "cpu")
    setup = zn.view_setup(light, kd, ks, plans, tables)

    def outputs() -> list:
        out = [t for keep in (None, rt.dot_T(nT, woT) > 0)
               for _, _, t in rt.specular_parts(w, nT, woT, vreg, alphas + [20.0], keep=keep)]
        out.append(zn.specular_conjugate(w, nT, None, (0, N), tables, lifted, lifted=True))
        out += list(zn.view_radiance(setup, spans, pos, nT, w, cam, False))
        idx = torch.arange(0, N, 2)
        rad = torch.zeros(N, 3)
        assert zn.pose_radiance(setup, lifted, [(0, 150), (150, 300), (300, idx.shape[0])], w[:, idx].contiguous(),
                                nT[:, idx].contiguous(), woT[:, idx].contiguous(), idx, rad, False)
        return out + [rad]

    monkeypatch.setattr(rt, "native_conjugate", True)
    calls = _count_native_calls(monkeypatch)
    want = outputs()
    assert calls and all(calls)                                  # (the C pass ran)
    for name, f in libs.items():
        monkeypatch.setattr(zn, name, f)
    got = outputs()
    assert len(got) == len(want)
    for i, (a, b) in enumerate(zip(got, want)):
        assert a is not None and torch.equal(a, b), (order, i)


@pytest.mark.parametrize("order", [2, 4, 8])
def test_phong_flat_plan_equals_block_plan(order):
    """`native.phong_flat_plan` (a new exponent's plan as one product with its beta row: the VB / VBL
    frames' `_pass_setup`) = `native._flat_plan`(`runtime._block_plan`(...)) — spans, cols and src bit for
    bit, the blocks' values to float32 round-off (float64 round-off before the cast; bit for bit on most
    exponents) — on exponents 0 to 5000 including the integers whose M or K has extra zeros; and
    `view_radiance` of a setup by it (`native.view_setup_flat`) = by `view_setup` to float32 round-off."""
    import methods.zh_shadow.native as zn

    _skip_without_c_compiler()
    for a in (0.0, 0.5, 1.0, 2.0, 3.0, 7.5, 12.0, 30.0, 64.0, 200.0, 1000.0, 5000.0):
        s = (a + 1.0) / (2.0 * math.pi)
        want = zn._flat_plan(rt._block_plan(("phong", a), order, False, torch.float32, "cpu", s))
        got = zn.phong_flat_plan(a, order, s)
        for i in (0, 2, 3):
            assert torch.equal(got[i], want[i]), (order, a, i)
        assert got[1].dtype == torch.float32 and got[1].shape == want[1].shape
        assert (got[1] - want[1]).abs().max() <= 1e-7 * want[1].abs().max(), (order, a)
        assert zn.phong_flat_plan(a, order, s) is got                        # (kept per exponent)
    g = torch.Generator().manual_seed(43)
    N, n2 = 500, order * order
    pos = torch.randn(N, 3, generator=g)
    nrm = torch.randn(N, 3, generator=g)
    nT = rt.rows(nrm / nrm.norm(dim=1, keepdim=True))
    w = torch.randn(n2, N, generator=g)
    light = torch.randn(n2, 3, generator=g)
    cam = torch.tensor([0.4, 2.5, 3.0])
    kd, ks = torch.rand(2, 3, generator=g), torch.rand(2, 3, generator=g)
    alphas = [17.0, 1.0]
    scale = [(a + 1.0) / (2.0 * math.pi) for a in alphas]
    tables = rt._conjugate_tables(order, torch.float32, "cpu")
    plans = [rt._block_plan(("phong", a), order, False, torch.float32, "cpu", s) for a, s in zip(alphas, scale)]
    want = zn.view_radiance(zn.view_setup(light, kd, ks, plans, tables), [(0, 250), (250, N)], pos, nT, w, cam,
                            False)
    flats = [zn.phong_flat_plan(a, order, s) for a, s in zip(alphas, scale)]
    got = zn.view_radiance(zn.view_setup_flat(light, kd, ks, flats, tables), [(0, 250), (250, N)], pos, nT, w,
                           cam, False)
    assert torch.equal(got[1], want[1])
    assert (got[0] - want[0]).abs().max() <= 2e-6 * want[0].abs().max()


def test_native_vertex_table_equals_gemms():
    """`native.vertex_table` (zh34p: a per-vertex table's rows by one C pass) = `runtime.vertex_table`'s GEMMs
    to float32 round-off: every row, a frame's referenced rows read through their ids (in any order, repeated),
    three regions whose vertices are not ranges, a region without a specular term (zero specular columns),
    vertices outside every region (zero rows), a single region (its table for every row, whatever the
    region ids); the same bits at 1 and 2 threads; None for an id outside the rows."""
    import methods.zh_shadow.native as zn
    from methods.core.threads import torch_threads

    _skip_without_c_compiler()
    g = torch.Generator().manual_seed(34)
    N, n2 = 3001, 16
    v = torch.randn(N, n2, generator=g)
    vreg = torch.randint(0, 3, (N,), generator=g)
    vreg[::97] = 3                                     # outside the three regions: zero rows
    light = torch.randn(n2, 3, generator=g)
    Wd = rt.table(light, 1.0, diffuse=True)
    Ws = rt.table(light, 12.0, diffuse=False)
    mats = [(torch.rand(3, generator=g), torch.rand(3, generator=g), Wd, Ws),
            (torch.rand(3, generator=g), torch.zeros(3), Wd, None),
            (torch.rand(3, generator=g), torch.rand(3, generator=g), Wd, Ws)]
    m = ZHShadow(**SMALL)
    idx = torch.randint(0, N, (1777,), generator=g)
    for tabs, reg in ((mats, vreg), (mats[:1], vreg), ([mats[1]], vreg)):
        for rows in (None, idx, idx.sort().values):
            want = rt.vertex_table(v if rows is None else v[rows], reg if rows is None else reg[rows], tabs)
            got = {}
            for nt in (1, 2):
                with torch_threads(nt), mock.patch.object(zn, "MIN_ROWS_PER_VTABLE_THREAD", 1):
                    got[nt] = m._native_table(v, reg, tabs, rows)
                    got[nt] = None if got[nt] is None else got[nt].clone()   # (a frame's rows: a kept buffer)
            assert got[1] is not None and got[1].shape == want.shape
            assert torch.equal(got[1], got[2])
            assert (got[1] - want).abs().max().item() <= 1e-6 * want.abs().max().item()
            if len(tabs) > 1:
                assert bool((got[1][(reg if rows is None else reg[rows]) == 3] == 0).all())
    # the kept per-region tables (`_region_stack`) follow the albedos of the same W tensors
    m._native_table(v, vreg, mats)
    for kd_or_ks in (0, 1):
        other = [tuple(t * 0.5 if j == kd_or_ks else t for j, t in enumerate(mt[:2])) + mt[2:] for mt in mats]
        want = rt.vertex_table(v, vreg, other)
        assert (m._native_table(v, vreg, other) - want).abs().max().item() <= 1e-6 * want.abs().max().item()
    # the per-region tables written in place = the folded products, bit for bit
    K, plain = rt.region_tables(mats, n2, "cpu", torch.float32)
    into = torch.full((3, n2, 3 * K), float("nan"))
    assert rt.region_tables(mats, n2, "cpu", torch.float32, out=into)[0] == K
    assert torch.equal(into, torch.stack(plain))
    assert zn.vertex_table(v, vreg, torch.stack(plain), torch.tensor([0, N])) is None


@pytest.mark.parametrize("kind", ("VB", "P"))
def test_native_vertex_table_frames(small_model, monkeypatch, kind):
    """The plane frames with the native table (`ZHShadow._native_table`: the kept table of a view frame, a
    frame's own table of its referenced rows) equal those with `runtime.vertex_table` (``native_table`` off)
    to float32 round-off, down the same path, with the same counts, at 1 and 2 threads; the per-region
    tables kept while the tables and albedos stay (a P frame's) are rebuilt when the albedos change (VB)."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _skip_without_c_compiler()
    monkeypatch.setattr(zn, "MIN_ROWS_PER_VTABLE_THREAD", 1)
    monkeypatch.setattr("methods.zh_shadow.method.VERTEX_TABLE_POINTS", 0.0)   # every frame builds a table
    m = small_model("creature")
    for nt in (1, 2):
        fast, slow = m.with_render_config(), m.with_render_config()
        slow.native_table = False
        for fr in make_sequence(m.scene, kind, 3, seed=5):
            gb = make_gbuffer(m.scene, fr, 2)
            with torch_threads(nt):
                a = fast.render(fr, gb)
                b = slow.render(fr, gb)
            assert fast.last_path == slow.last_path == "planes" and fast.last_fused == slow.last_fused
            assert (a - b).abs().max().item() <= 1e-6 * b.abs().max().item(), (kind, nt, fr.index)
            ca, cb = dict(fast._last_counts), dict(slow._last_counts)
            assert ca.pop("plane_vertices")() == cb.pop("plane_vertices")() and ca == cb
            assert fast._region_stack is not None and slow._region_stack is None


def test_relight_pixels_equals_two_passes():
    """`native.relight_pixels` (a lighting-only frame's plane pass and object entries in one C pass, one
    OpenMP region) = `native.face_pixels` then `native.relight_add` per entry in order, bit for bit: random
    plane faces (−1 = none), three entries whose pixels overlap (the order of the additions into a pixel
    matters), with and without ts, Q not a multiple of 8, clamp on and off, on 1, 2 and 3 threads and with
    the object weight of the thread ranges at 0 and 50 (other cuts); None for a plane face outside uf,
    an entry's pixel outside the image or not ascending, and with the switch off. The plane faces' table
    made in the pass (``planes``: v, corners, regions, T, kd) = the torch product ``(v[corners] @ T) ⊙
    kd[regions]`` to float32 round-off, the same bits at any thread count; None for a corner or region out
    of range or a partial face."""
    from methods.zh_shadow import native as zn

    g = torch.Generator().manual_seed(35)
    n, S2, Fp, n2 = 3000, 4, 300, 16
    face = torch.randint(-1, Fp, (n, S2), generator=g, dtype=torch.int64).to(torch.int32)
    bT = torch.rand(n * S2, 2, generator=g).T.contiguous().T.T.view(2, n, S2)
    uf = torch.randn(Fp, 9, generator=g)
    ents = []
    for Q, with_ts, lo, hi in ((1003, True, 0, n), (517, False, 200, 1400), (61, True, 1000, 1100)):
        td = torch.randn(n2, Q, generator=g)
        ts = torch.randn(n2, Q, generator=g) if with_ts else None
        ld = torch.randn(n2, 3, generator=g)
        ls = torch.randn(n2, 3, generator=g) if with_ts else None
        ents.append((td, ts, ld, ls, torch.sort(torch.randint(lo, hi, (Q,), generator=g)).values))
    for clamp in (True, False):
        with mock.patch.object(zn, "MIN_PIXELS_PER_THREAD", 1):
            want = zn.face_pixels(face, bT, uf, clamp)
            if want is None:
                assert zn._face_pixels_lib() is None or not zn.terms_switched_on()
                pytest.skip("the native plane pass is not available here")
            for e in ents:
                assert zn.relight_add(want, *e, clamp, 0.25)
            for nt in (1, 2, 3):
                for w in (0.0, 2.0, 50.0):
                    with mock.patch.object(torch, "get_num_threads", lambda: nt), \
                            mock.patch.object(zn, "RELIGHT_OBJECT_WEIGHT", w):
                        got = zn.relight_pixels(face, bT, uf, clamp, ents, 0.25)
                    assert got is not None and torch.equal(got, want), (clamp, nt, w)
    assert torch.equal(zn.relight_pixels(face, bT, uf, True, [], 0.25), zn.face_pixels(face, bT, uf, True))
    assert zn.relight_pixels(face, bT, uf[:Fp - 1].contiguous(), True, ents, 0.25) is None   # a face outside uf
    td, ts, ld, ls, pix = ents[0]
    for bad in (pix.clone().index_fill_(0, torch.tensor([len(pix) - 1]), n),            # outside the image
                pix.clone().index_fill_(0, torch.tensor([0]), 5000 % n + 1)):           # not ascending
        assert zn.relight_pixels(face, bT, uf, True, [(td, ts, ld, ls, bad)] + ents[1:], 0.25) is None
    # the plane faces' table made in the pass from v, the corners, their regions, T and kd = the torch
    # product to float32 round-off, then the same image as from that table
    N, R = 900, 3
    v = torch.randn(N, n2, generator=g)
    corners = torch.randint(0, N, (3 * Fp,), generator=g)
    creg = torch.randint(0, R, (3 * Fp,), generator=g)
    T, kd = torch.randn(n2, 3, generator=g), torch.rand(R, 3, generator=g)
    uf_t = ((v.index_select(0, corners) @ T) * kd.index_select(0, creg)).view(-1, 9)
    for clamp in (True, False):
        for nt in (1, 2, 3):
            with mock.patch.object(zn, "MIN_PIXELS_PER_THREAD", 1), mock.patch.object(torch, "get_num_threads",
                                                                                     lambda: nt):
                got = zn.relight_pixels(face, bT, None, clamp, ents, 0.25, planes=(v, corners, creg, T, kd))
                want = zn.relight_pixels(face, bT, uf_t, clamp, ents, 0.25)
            assert got is not None and float((got - want).abs().max()) <= 1e-5 * float(want.abs().max()), (clamp, nt)
            if nt == 1:
                one = got
            assert torch.equal(got, one), (clamp, nt)   # (the same bits at any thread count)
    for c2, r2, kd2 in ((corners.clone().index_fill_(0, torch.tensor([7]), N), creg, kd),   # a corner outside v
                        (corners, creg.clone().index_fill_(0, torch.tensor([5]), R), kd),    # a region outside kd
                        (corners[:-1], creg[:-1], kd)):                                      # not whole faces
        assert zn.relight_pixels(face, bT, None, True, ents, 0.25, planes=(v, c2, r2, T, kd2)) is None
    assert zn.relight_pixels(face, bT, None, True, ents, 0.25) is None                       # neither
    with mock.patch.dict("os.environ", {"PRTBENCH_ZH_NATIVE": "0"}):
        assert zn.relight_pixels(face, bT, uf, True, ents, 0.25) is None


@pytest.mark.parametrize("name", ("creature", "sphere_plane"))
def test_fused_relight_equals_two_passes_frames(small_model, monkeypatch, name):
    """A lighting-only plane frame (`ZHShadow._relight_planes`) by `native.relight_pixels` (``fused_relight``:
    the plane faces' table, the plane pass and the object entries in one pass) renders the image of the GEMM
    and the two C passes it joins (``fused_relight`` off) to float32 round-off, and the reference; L and E
    sequences, clamp on and off, 1 and 2 threads (the pixels split between them); the fused pass is taken."""
    from methods.core.threads import torch_threads
    from methods.zh_shadow import native as zn
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    monkeypatch.setattr(zn, "MIN_PIXELS_PER_THREAD", 1)   # (test size: 4,096 pixels, one thread otherwise)
    taken = []
    real = zn.relight_pixels_run   # (the C call: `relight_pixels`', and zh40l's steady frames' `_steady_planes`)

    def spy(*a, **k):
        r = real(*a, **k)
        taken.append(r is not None)
        return r

    monkeypatch.setattr(zn, "relight_pixels_run", spy)
    m = small_model(name)
    for kind, clamp, nt in (("L", True, 1), ("E", True, 2), ("L", False, 2)):
        fast, slow = m.with_render_config(clamp=clamp), m.with_render_config(clamp=clamp)
        slow.fused_relight = False
        for fr in make_sequence(m.scene, kind, 4, seed=5):
            gb = make_gbuffer(m.scene, fr, 2)
            with torch_threads(nt):
                a = fast.render(fr, gb)
                n_taken = len(taken)
                b = slow.render(fr, gb)
            assert len(taken) == n_taken   # (the slow side never calls it)
            assert fast.last_path == slow.last_path
            # (the plane faces' table in the pass: float32 round-off against the GEMM)
            assert float((a - b).abs().max()) <= 1e-6 * float(b.abs().max()), (name, kind, clamp, nt, fr.index)
            if fr.index == 2 and nt == 1:
                assert (a - fast._render_reference(fr, gb)).abs().max().item() <= RENDER_TOL
        assert fast.last_path == "relight-planes", (name, kind)
    if zn._relight_pixels_lib() is not None and zn.terms_switched_on():
        assert taken and all(taken)


@pytest.mark.parametrize("kind", ("P", "VL"))
def test_plane_u_native_equals_gemm(small_model, kind):
    """`native.plane_u` (`ZHShadow._plane_term`'s v · T¹(n0) by one C pass over the rows) = the GEMM to float32
    round-off on random rows (several row counts, 1 to 3 threads: the same bits), None for other shapes or
    strides and with the switch off; P / VL frames of the creature (a new plane term each frame) render the
    image of ``native_plane_u`` off to round-off and the reference."""
    from methods.zh_shadow import native as zn
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    g = torch.Generator().manual_seed(36)
    for N, n2 in ((1, 16), (4099, 16), (9000, 64)):
        v, T = torch.randn(N, n2, generator=g), torch.randn(n2, 3, generator=g)
        got = zn.plane_u(v, T)
        if got is None:
            assert zn._relight_pixels_lib() is None or not zn.terms_switched_on()
            pytest.skip("the native plane term is not available here")
        want = v @ T
        assert float((got - want).abs().max()) <= 1e-5 * float(want.abs().max()), (N, n2)
        for nt in (2, 3):
            with mock.patch.object(zn, "MIN_ROWS_PER_PLANE_U_THREAD", 1), \
                    mock.patch.object(torch, "get_num_threads", lambda: nt):
                assert torch.equal(zn.plane_u(v, T), got), (N, nt)
    v, T = torch.randn(50, 16, generator=g), torch.randn(16, 3, generator=g)
    assert zn.plane_u(v, T[:15]) is None and zn.plane_u(v.T.contiguous().T, T) is None
    assert zn.plane_u(v.double(), T.double()) is None
    with mock.patch.dict("os.environ", {"PRTBENCH_ZH_NATIVE": "0"}):
        assert zn.plane_u(v, T) is None
    m = small_model("creature")
    fast, slow = m.with_render_config(), m.with_render_config()
    slow.native_plane_u = False
    for fr in make_sequence(m.scene, kind, 3, seed=12):
        gb = make_gbuffer(m.scene, fr, 2)
        a, b = fast.render(fr, gb), slow.render(fr, gb)
        assert fast.last_path == slow.last_path == "planes", (kind, fr.index)
        assert float((a - b).abs().max()) <= 1e-6 * float(b.abs().max()), (kind, fr.index)
        if fr.index == 1:
            assert (a - fast._render_reference(fr, gb)).abs().max().item() <= RENDER_TOL
