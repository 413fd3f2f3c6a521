"""SHPRT behind the Method contract: config validation, capabilities, run-time lighting rotation
(Sloan 2002 §7), caching, run-time diffuse colour, with_bounces, the study row."""
from __future__ import annotations

import math

import pytest
import torch

from methods.base import Frame
from methods.core.sh import project_latlong
from methods.sh_prt import study
from methods.registry import get_method
from methods.sh_prt.method import SHPRT, lobe_factors
from methods.studies import TERMS_CONTRIBUTORS
from references.gbuffer import make_gbuffer
from scenes.envmap import EnvMap
from scenes.library import get_scene, rotation_y
from scenes.materials import BlinnPhong, Lambert, Phong
from scenes.sequences import make_sequence

# Rotating the projected coefficients vs projecting the rotated map: both exact (float64
# projection, float32 result) → agreement to float32 round-off of values up to ~10.
ROTATION_TOL = 1e-4
# A lighting frame against a fresh precompute (tests/methods/test_relighting.py's RTOL): both render
# from the same transfer; only the lighting SH differs (rotated vs projected: float32 round-off).
RELIGHT_RTOL = 2e-5


@pytest.fixture(scope="module")
def alcove():
    scene = get_scene("alcove", "test")
    m = SHPRT(order=4, bounces=1, rays=32)
    m.precompute(scene)
    frame = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    return scene, m, frame, make_gbuffer(scene, frame, 1)


@pytest.mark.parametrize("kw, name", [({"order": 1}, "order"), ({"order": 11}, "order"), ({"order": 5.0}, "order"),
                                      ({"bounces": 3}, "bounces"), ({"bounces": -1}, "bounces"),
                                      ({"rays": 0}, "rays"), ({"seed": "x"}, "seed")])
def test_bad_config_is_a_value_error_naming_the_parameter(kw, name):
    with pytest.raises(ValueError, match=name):
        SHPRT(**kw)


def test_registered_with_its_capabilities():
    assert get_method("sh_prt") is SHPRT
    cap = SHPRT.capabilities
    assert cap.dynamic_lighting and not cap.dynamic_brdf and not cap.dynamic_geometry
    assert cap.max_bounces == 2
    chess = get_scene("chess", "test")  # its "black" region is Cook-Torrance
    assert cap.why_not(chess, "V", 0) == "BRDF family not supported: cooktorrance"
    assert cap.why_not(get_scene("sphere_plane", "test"), "V", 2) is None
    assert cap.why_not(get_scene("sphere_plane", "test"), "VB", 0) == "BRDFs fixed at precompute"
    with pytest.raises(ValueError, match="cooktorrance"):
        SHPRT(rays=8, bounces=0).precompute(chess)


def test_rotated_lighting_equals_reprojection_and_projects_once(alcove):
    scene, m, _, _ = alcove
    m._reset_cache()
    env = scene.envmap
    for k, axis_angle in enumerate([0.4, 1.3, -2.2]):
        c, s = math.cos(axis_angle), math.sin(axis_angle)
        Rx = torch.tensor([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])   # tilted axis: not only +Y
        rot = env.rotated(Rx @ torch.as_tensor(rotation_y(0.7 * axis_angle)).float())
        got = m.lighting(rot)
        ref = project_latlong(rot, m.order).float()
        assert (got - ref).abs().max() < ROTATION_TOL * ref.abs().max()
    assert m.stats["project"] == 1 and m.stats["rotate"] == 3


def test_lighting_cache_follows_the_texels(alcove):
    scene, m, frame, gb = alcove
    env = EnvMap(scene.envmap.data.clone(), scene.envmap.to_world)
    f = Frame(envmap=env, camera=frame.camera, materials=frame.materials)
    m._reset_cache()
    a = m.render(f, gb)
    b = m.render(f, gb)
    assert m.stats["light"] == 1 and torch.equal(a, b)
    env.data.mul_(2.0)  # in place: same tensor object, new version
    c = m.render(f, gb)
    assert m.stats["light"] == 2 and m.stats["project"] == 2
    assert torch.allclose(c, 2.0 * a, rtol=1e-5, atol=1e-6)


def test_diffuse_colour_is_a_run_time_scale(alcove):
    scene, m, frame, gb = alcove
    m._reset_cache()
    mats = dict(frame.materials)
    walls = mats["walls"]
    base = m.render(Frame(envmap=frame.envmap, camera=frame.camera, materials={**mats, "walls": Lambert(kd=(0.0, 0.0, 0.0))}), gb)
    img = m.render(frame, gb)
    dbl = m.render(Frame(envmap=frame.envmap, camera=frame.camera,
                         materials={**mats, "walls": Lambert(kd=tuple(2 * k for k in walls.kd))}), gb)
    assert m.stats["light"] == 1                       # materials never re-run the lighting stage
    assert torch.allclose(dbl - base, 2.0 * (img - base), rtol=1e-5, atol=1e-6)
    assert (img - base).amax() > 0.05


def test_with_bounces_sums_the_passes(alcove):
    scene, m, frame, gb = alcove
    m0, m1 = m.with_bounces(0), m.with_bounces(1)
    assert m0.config["bounces"] == 0 and m.config["bounces"] == 1
    assert torch.equal(m1.t, m.t_parts[0] + m.t_parts[1]) and torch.equal(m0.t, m.t_parts[0])
    i0, i1 = m0.render(frame, gb), m1.render(frame, gb)
    assert (i1 - i0).mean() > 0.005   # interreflection adds light (pixels may dip: SH ringing)
    fresh = SHPRT(order=4, bounces=0, rays=32)
    fresh.precompute(scene)
    assert torch.equal(fresh.render(frame, gb), i0)                # same rays: the same direct pass
    with pytest.raises(ValueError, match="bounces"):
        m.with_bounces(2)
    assert m.memory()["transfer_matrices"] > 0
    # Per-vertex terms count only the vertices the samples reference (session 27): e at the corners
    # of the hit faces (nv of them), l' and M at the glossy corners of the glossy samples' faces (ng)
    F, fh = m.F, gb.face[gb.hit].long()
    nv = int(torch.unique(F[fh]).numel())
    gl = m.glossy_regions[gb.region[gb.hit].long()]
    rows = torch.unique(m.gpos[F[fh[gl]]])
    ng = int((rows >= 0).sum())
    assert 0 < nv < m.t.shape[0] and 0 < ng < m.M.shape[0]         # the view leaves vertices unseen
    n2 = m.order ** 2
    v, l, e = (m1.frame_cost(k, gb.num_samples) for k in ("V", "L", "E"))
    assert v.bytes < l.bytes < e.bytes and v.flops < l.flops < e.flops
    # a lighting frame reads t and M of those vertices (RGB transfer: no relight cache)
    assert l.bytes - v.bytes == nv * n2 * 3 * 4 + ng * n2 * n2 * 3 * 4 + nv * 12 + ng * n2 * 12
    # With grey transfer a lighting-only frame is shaded from the relight cache: it reads t, the
    # glossy samples' cached vectors, weights and pixels, not M or l'
    g0 = m0.frame_cost("L", gb.num_samples)
    qg = int(round(float(m0.glossy_regions[gb.region[gb.hit].cpu()].float().mean()) * gb.num_samples))
    v0 = m0.frame_cost("V", gb.num_samples)
    # a V frame: per sample the G-buffer inputs and the output, the faces, per face its material row
    # (kd + glossy flag, 4 float32: a hit's region is its face's), the glossy samples' regions, e and l'
    from methods.base import GBUFFER_BYTES_PER_SAMPLE

    nf = m0.F.shape[0]
    assert v0.bytes == gb.num_samples * (GBUFFER_BYTES_PER_SAMPLE + 12) + m0.F.numel() * m0.F.element_size() \
        + nf * 16 + qg * 8 + nv * 12 + ng * n2 * 12
    assert g0.bytes - v0.bytes == nv * n2 * 4 + nv * 12 - ng * n2 * 12 - qg * 8 + qg * (8 * n2 + 32)
    vl0 = m0.frame_cost("VL", gb.num_samples)  # a view change too: no cache, M read
    assert vl0.bytes - v0.bytes == nv * n2 * 4 + ng * n2 * n2 * 4 + nv * 12 + ng * n2 * 12
    rot = sum(2 * (2 * k + 1) ** 2 * 3 for k in range(m0.order))
    assert vl0.flops - v0.flops == rot + 2 * 3 * (nv * n2 + ng * n2 * n2)


def test_blinn_phong_lobe_is_the_mapped_phong_lobe():
    """Blinn-Phong → Phong(s/4) × (s+2)/(s+4): at normal incidence the two lobes agree to second
    order in the angle from R, so their order-n factors agree for a sharp lobe."""
    n, s = 6, 200.0
    bp = lobe_factors(BlinnPhong(ks=0.5, s=s), n)
    ph = lobe_factors(Phong(ks=0.5, s=s / 4.0), n)
    assert torch.allclose(bp, (s + 2) / (s + 4) * ph)
    with pytest.raises(ValueError, match="lobe"):
        lobe_factors(Lambert(), n)


# Orders needed for 99 % of the Phong lobe's energy, by direct summation of Σ_l f_l² in float64
# with the Ramamoorthi–Hanrahan factors (s = 1: bands 0..2 hold > 99 %).
def test_terms_needed_is_the_first_order_holding_99_percent():
    for s in (1.0, 10.0, 50.0, 200.0):
        n = study.order_needed(s)
        assert study.energy_fraction(s, n) >= 0.99 > study.energy_fraction(s, n - 1) if n > 1 else True
        assert study.terms_needed(s).terms == n * n
    assert study.order_needed(1.0) == 3
    ns = [study.order_needed(s) for s in (10.0, 40.0, 160.0, 640.0)]
    assert all(b > a for a, b in zip(ns, ns[1:]))                 # sharper lobes need more bands
    assert 1.7 < ns[-1] / ns[-2] < 2.3                            # n ∝ √s asymptotically
    with pytest.raises(ValueError, match="exponent"):
        study.terms_needed(-1.0)
    c = TERMS_CONTRIBUTORS["sh_prt"]
    assert c.fn is study.terms_needed and c.target == 0.99


def test_precomputation_round_trips_through_the_harness_cache(alcove, tmp_path, monkeypatch):
    """The state after precompute is what `reports.precompute_cache` can store (tensors, scalars,
    containers, methods/ and scenes/ objects): a loaded instance renders bit for bit the same image.
    (`SHPRT.cache_precompute` is off until tests/reports/test_precompute_cache_methods.py has its
    case; an opted-in subclass exercises the path here.)"""
    import json

    from reports import precompute_cache as PC

    class Cached(SHPRT):
        cache_precompute = True

    monkeypatch.setenv("PRTBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("PRTBENCH_NO_PRECOMPUTE_CACHE", raising=False)
    scene, _, frame, gb = alcove
    cfg = dict(order=3, bounces=1, rays=16)
    key = json.dumps(cfg, sort_keys=True)
    first, loaded = Cached(**cfg), Cached(**cfg)
    assert not PC.precompute(first, scene, key)["cached"]
    assert PC.precompute(loaded, scene, key)["cached"]
    for b in (0, 1):
        want = first.with_bounces(b).render(frame, gb)
        assert want.abs().max() > 0 and torch.equal(loaded.with_bounces(b).render(frame, gb), want)


@pytest.mark.parametrize("kind", ["L", "E"])
def test_lighting_frame_equals_fresh_precompute(kind):
    """As tests/methods/test_relighting.py for the other methods: frame 2 of a lighting-only
    sequence (L: rotation about a tilted axis → rotated SH; E: another probe → re-projection),
    rendered after frames 0–1, equals a fresh precompute + render of a scene with that env map."""
    import dataclasses

    scene = get_scene("sphere_plane", "test")
    frames = make_sequence(scene, kind, n_frames=3, seed=1)
    assert all(frames[i].changed == {"light"} for i in (1, 2))
    gbs = [make_gbuffer(scene, f, 1) for f in frames]
    cfg = dict(order=4, bounces=0, rays=16)
    m = SHPRT(**cfg)
    m.precompute(scene)
    imgs = [m.render(f, g) for f, g in zip(frames, gbs)]
    last = frames[-1]
    fresh = SHPRT(**cfg)
    fresh.precompute(dataclasses.replace(scene, envmap=last.envmap))
    want = fresh.render(dataclasses.replace(last, index=0, changed=frozenset({"view", "brdf", "light", "pose"})),
                        gbs[-1])
    scale = want.abs().max()
    assert (imgs[-1] - want).abs().max() <= RELIGHT_RTOL * scale
    assert (imgs[-1] - imgs[0]).abs().max() > 100 * RELIGHT_RTOL * scale
    assert m.stats["light"] == 3 and m.stats["project"] == (1 if kind == "L" else 3)


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "eager"])
@pytest.mark.parametrize("scene_name", ["alcove", "creature"])
def test_fast_render_equals_reference(scene_name, compiled, monkeypatch):
    """`SHPRT.render` (the diffuse term in one compiled pass, the glossy term on the glossy samples)
    = `render_reference` (the per-chunk eager `_shade`) to float32 round-off; at 1 and 2×2 samples
    per pixel (the glossy samples' pixel by a shift: `_render_fast`)."""
    import dataclasses

    from methods.sh_prt.method import SHPRT
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    monkeypatch.setenv("PRTBENCH_COMPILE", "1" if compiled else "0")
    scene = get_scene(scene_name, "test")
    m = SHPRT(order=3, bounces=0, rays=16)
    m.precompute(scene)
    for i, frame in enumerate(make_sequence(scene, "VBL", n_frames=2, seed=1)):
        frame = dataclasses.replace(frame, materials=dict(scene.materials))
        gb = make_gbuffer(scene, frame, 1 + i)
        ref = m.render_reference(frame, gb)
        img = m.render(frame, gb)
        assert (img - ref).abs().max().item() <= 1e-5 * max(ref.abs().max().item(), 1e-6)


@pytest.mark.parametrize("scene_name", ["alcove", "creature"])
def test_pixel_pass_face_rows_are_the_gbuffer_regions(scene_name):
    """The pixel pass takes kd and the glossy flag from its face's row (`SHPRT._face_materials`,
    session 25) instead of the G-buffer's region: at every hit the row equals kd and the glossy
    flag of the sample's region (a G-buffer's region is its face's), and it follows the materials."""
    import dataclasses

    from methods.sh_prt.method import SHPRT
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    scene = get_scene(scene_name, "test")
    m = SHPRT(order=2, bounces=0, rays=4)
    m.precompute(scene)
    frame = make_sequence(scene, "V", n_frames=1, seed=1)[0]
    frame = dataclasses.replace(frame, materials=dict(scene.materials))
    gb = make_gbuffer(scene, frame, 1)
    kd = m._materials(frame)[0]
    fk = m._face_materials(kd)
    f, r = gb.face[gb.hit], gb.region[gb.hit]
    assert f.numel() > 0 and fk.shape == (m.F.shape[0], 4)
    assert torch.equal(fk[f, :3], kd[r])
    assert torch.equal(fk[f, 3], m.glossy_regions[r].float())
    assert m._face_materials(kd) is fk                                        # kept while kd is
    name = m.regions[int(r[0])]
    mats = dict(frame.materials, **{name: dataclasses.replace(frame.materials[name], kd=(0.125, 0.25, 0.5))})
    kd2 = m._materials(dataclasses.replace(frame, materials=mats))[0]
    assert torch.equal(m._face_materials(kd2)[f, :3], kd2[r]) and not torch.equal(kd2, kd)


@pytest.mark.parametrize("C", [1, 3])
def test_apply_lighting_equals_its_einsum(C):
    """The lighting stage's t·l and M l (`apply_lighting`: products over transfer rows stored
    (C, n², rows)) = the einsum of the definition to float32 round-off, from either memory layout,
    for the (V, n², C) vectors and the (Vg, n², n², C) matrices viewed as rows."""
    from methods.sh_prt.method import apply_lighting, apply_lighting_reference, lighting_major

    g = torch.Generator().manual_seed(0)
    l = torch.randn(16, 3, generator=g)
    X, M = torch.randn(517, 16, C, generator=g), torch.randn(37, 16, 16, C, generator=g)
    for rows in (X, lighting_major(X), lighting_major(M).reshape(37 * 16, 16, C)):
        want = apply_lighting_reference(rows.contiguous(), l)
        got = apply_lighting(rows, l)
        assert got.shape == (3, rows.shape[0])
        assert (got - want).abs().max() <= 1e-5 * want.abs().max()
    for T in (X, M):
        L = lighting_major(T)
        assert torch.equal(L, T) and L.permute(L.dim() - 1, L.dim() - 2, *range(L.dim() - 2)).is_contiguous()
        assert lighting_major(L) is L


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_polar_projection_rotated_equals_project_latlong(dtype):
    """`project_latlong_polar` (the polar-frame coefficients, one GEMM for the column integrals)
    rotated by Qᵀ, or by R Qᵀ for a map with ``to_world`` R, = `sh.project_latlong` to float64
    round-off; without the rotation (or with Q instead of Qᵀ) it differs at O(1)."""
    from methods.core import sh
    from methods.core.sh import project_latlong_polar
    from methods.core.sh_rotation import rotate_coeffs

    F64 = torch.float64
    g = torch.Generator().manual_seed(3)
    img = torch.rand(9, 14, 3, generator=g, dtype=F64).to(dtype)
    order = 5
    Q = torch.tensor(sh._LATLONG_Q, dtype=F64)
    cp = project_latlong_polar(img, order)
    assert cp.shape == (order * order, 3) and cp.dtype == F64
    want = sh.project_latlong(img.to(F64), order)
    assert (rotate_coeffs(cp, Q.T) - want).abs().max() <= 1e-13 * want.abs().max()
    assert (rotate_coeffs(cp, Q) - want).abs().max() > 1e-3 * want.abs().max()
    assert (cp - want).abs().max() > 1e-3 * want.abs().max()
    R = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=F64))[0]
    R = R * torch.sign(torch.det(R))

    class Env:
        data, to_world = img.to(F64), R

    want = sh.project_latlong(Env(), order)
    assert (rotate_coeffs(cp, R @ Q.T) - want).abs().max() <= 1e-13 * want.abs().max()


# A face corner's l' against the per-vertex M l computed directly for every vertex: the same rays
# and the same float32 quadrature, only the row bookkeeping differs → float32 round-off of
# radiances up to ~0.5 (measured 2-4e-7 relative; before the fix of `SHPRT.precompute` the
# corners shared with the Lambert region read the last l' row: 0.13 relative).
SHARED_VERTEX_RTOL = 1e-5


def _valley_with_shared_crease():
    """A V-shaped valley y = 0.5|x| (x, z ∈ [−1, 1], 6 × 4 cells), its left half (x ≤ 0) the Phong
    region "gloss" and its right half the Lambert region "matte", the crease vertices x = 0 SHARED by
    both regions' faces and assigned to "matte" (vertex_region). Library scenes never share vertices
    between regions (`scenes.scene._merge` gives every shape its own), so the merged geometry is set
    by hand. Returns (scene, the welded geometry)."""
    from scenes.camera import Camera
    from scenes.envmap import procedural as env_procedural
    from scenes.mesh import Mesh, compute_vertex_normals
    from scenes.scene import Scene, SceneGeometry, Shape

    nx, nz = 6, 4
    xs, zs = torch.linspace(-1.0, 1.0, nx + 1), torch.linspace(-1.0, 1.0, nz + 1)
    X, Z = torch.meshgrid(xs, zs, indexing="ij")
    V = torch.stack([X, 0.5 * X.abs(), Z], -1).reshape(-1, 3)
    vid = lambda i, j: i * (nz + 1) + j  # noqa: E731
    F, fr = [], []
    for i in range(nx):
        for j in range(nz):
            a, b, c, d = vid(i, j), vid(i + 1, j), vid(i + 1, j + 1), vid(i, j + 1)
            F += [[a, d, c], [a, c, b]]           # normals towards +y
            fr += [0 if i < nx // 2 else 1] * 2
    F = torch.tensor(F, dtype=torch.int64)
    N = compute_vertex_normals(V, F)
    assert (N[:, 1] > 0.5).all()
    vr = (torch.arange(nx + 1) >= nx // 2).long().repeat_interleave(nz + 1)   # crease column i = 3: "matte"
    left, right = F[torch.tensor(fr) == 0], F[torch.tensor(fr) == 1]
    shapes = []
    for name, Fh in (("gloss", left), ("matte", right)):             # the scene's own (unwelded) shapes
        used = torch.unique(Fh)
        remap = torch.full((V.shape[0],), -1, dtype=torch.int64)
        remap[used] = torch.arange(used.numel())
        shapes.append(Shape(name, name, Mesh(V[used], remap[Fh], N[used])))
    cam = Camera((0.0, 2.0, 3.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 45.0, 16, 16)
    mats = {"gloss": Phong(kd=(0.1, 0.12, 0.08), ks=(0.6, 0.5, 0.4), s=12.0), "matte": Lambert(kd=(0.5, 0.4, 0.3))}
    scene = Scene("valley", shapes, ["gloss", "matte"], cam, env_procedural("studio", height=32, seed=0), mats)
    nf = [int(left.shape[0]), int(right.shape[0])]
    geom = SceneGeometry(V, torch.cat([left, right]), N, None, vr, torch.tensor([0] * nf[0] + [1] * nf[1]),
                         torch.tensor([0, nf[0], nf[0] + nf[1]]), torch.tensor([0, V.shape[0], V.shape[0]]),
                         ("gloss", "matte"))
    scene._rest = geom
    return scene, geom


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "eager"])
def test_glossy_face_with_a_shared_non_glossy_corner(compiled, monkeypatch):
    """A glossy face whose corner vertex belongs to a Lambert region (the regions share the vertex)
    interpolates that vertex's OWN transferred radiance l' = M_x l (Sloan 2002 §7: l' is a per-vertex
    quantity of the geometry, whatever the vertex's region; `SHPRT.precompute`), in the fast path and
    the reference. The independent value: the shadowed glossy transfer of EVERY vertex from the same
    rays (`transfer.shadowed_glossy`), l' = M l, interpolated at each sample of the glossy faces."""
    from methods.core import sh as _sh
    from methods.core import zh as _zh
    from methods.sh_prt import transfer as _tr
    from references.visibility import make_visibility
    from scenes.frame import GBuffer

    monkeypatch.setenv("PRTBENCH_COMPILE", "1" if compiled else "0")
    scene, geom = _valley_with_shared_crease()
    n = 4
    m = SHPRT(order=n, bounces=0, rays=64)
    m.precompute(scene)
    gl_faces = (geom.face_region == 0).nonzero().squeeze(-1)
    shared = torch.isin(m.F[gl_faces], (geom.vertex_region == 1).nonzero().squeeze(-1))
    assert shared.any()                                     # the case under test exists
    # samples: every glossy face at its centre and near each corner (weight 0.8 there)
    W = torch.tensor([[1 / 3, 1 / 3, 1 / 3], [0.8, 0.1, 0.1], [0.1, 0.8, 0.1], [0.1, 0.1, 0.8]])
    face = gl_faces.repeat_interleave(W.shape[0])
    w = W.repeat(gl_faces.numel(), 1)                       # (P, 3) (1 − u − v, u, v)
    P = face.numel()
    tri = m.F[face]
    pos = (geom.V[tri] * w[..., None]).sum(1)
    nrm = torch.nn.functional.normalize((geom.N[tri] * w[..., None]).sum(1), dim=-1)
    wo = torch.nn.functional.normalize(torch.tensor(scene.camera.origin, dtype=torch.float32) - pos, dim=-1)
    gb = GBuffer(height=1, width=P, spp_side=1, hit=torch.ones(P, dtype=torch.bool), face=face,
                 bary=w[:, 1:].contiguous(), position=pos, normal=nrm, wo=wo,
                 region=geom.face_region[face], coverage=torch.ones(1, P, dtype=torch.bool))
    frame = Frame(envmap=scene.envmap, camera=scene.camera, materials=dict(scene.materials))
    # the independent per-vertex quantities
    rays = _tr.trace_rays(make_visibility(geom.V, geom.F), geom.V.float(), m.N, 64, seed=0)
    Nall = geom.V.shape[0]
    M_all = _tr.shadowed_glossy(rays, m.N, n, torch.arange(Nall))              # (V, n², n²)
    t_all = _tr.shadowed_diffuse(rays, m.N, n)                                  # (V, n²)
    l = m.lighting(scene.envmap)                                                # (n², 3)
    lp = torch.einsum("vij,jc->vic", M_all, l)                                  # (V, n², 3) l' = M l
    e = t_all @ l                                                               # (V, 3)
    mat = scene.materials["gloss"]
    R = torch.nn.functional.normalize(2 * (nrm * wo).sum(-1, keepdim=True) * nrm - wo, dim=-1)
    y = _sh.sh_eval(R, n) * _zh.expand_bands(lobe_factors(mat, n)).float()    # (P, n²) G_l y_lm(R)
    lq = (lp[tri] * w[..., None, None]).sum(1)                                  # (P, n², 3)
    want = (torch.tensor(mat.kd) * (e[tri] * w[..., None]).sum(1)
            + torch.tensor(mat.ks_rgb) * torch.einsum("pi,pic->pc", y, lq)).clamp_min(0.0)
    assert ((nrm * wo).sum(-1) > 0).all()
    scale = want.abs().max().item()
    for got in (m.render(frame, gb), m.render_reference(frame, gb)):
        assert (got.view(P, 3) - want).abs().max().item() <= SHARED_VERTEX_RTOL * scale
    assert (m.gpos[m.F[gl_faces]] >= 0).all()  # every corner of a glossy face has its row


@pytest.mark.parametrize("order", [2, 5, 7])
@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "eager"])
def test_glossy_samples_kernel_equals_its_definition(order, compiled, monkeypatch):
    """`_glossy_samples` (the glossy pass: l' interpolated inside one reduction per channel over the
    coefficients i ≥ 1, band 0 added outside) = max(0, ρ·e + k_s Σ_k w_k Σ_i l'_{a_k,i} G_i y_i(R))
    (× n·ωo for a Blinn-Phong region, 0 where n·ωo ≤ 0) written with `sh_eval` and an einsum, on
    random tables: order 2 (one coefficient beyond band 0), 5 (the bench's 24 + 1) and 7 (past the
    hard-coded polynomials of `sh.sh_terms`: y(R) from the kernel's factor tables), a Phong and a
    Blinn-Phong region, back-facing samples, unnormalised normals, and a sample count that is not a
    multiple of the kernel's block (padded last block)."""
    from methods.core import sh as _sh
    from methods.core.fused import map_rows
    from methods.sh_prt import method as shm

    monkeypatch.setenv("PRTBENCH_COMPILE", "1" if compiled else "0")
    gen = torch.Generator().manual_seed(order)
    n2, P, M, Vg, R = order * order, 3000, 40, 30, 3
    face = torch.randint(0, M, (P,), generator=gen)
    u, v = torch.rand(P, generator=gen) * 0.5, torch.rand(P, generator=gen) * 0.5
    bary = torch.stack([u, v], -1)
    normal = torch.randn(P, 3, generator=gen) * 1.7
    wo = torch.nn.functional.normalize(torch.randn(P, 3, generator=gen), dim=-1)
    reg = torch.randint(0, R, (P,), generator=gen)
    ef = torch.rand(M, 9, generator=gen)
    fg = torch.randint(0, Vg, (M, 3), generator=gen, dtype=torch.int32)
    lg3 = torch.randn(3, Vg, n2, generator=gen)
    kd, ks = torch.rand(R, 3, generator=gen), torch.rand(R, 3, generator=gen)
    G = torch.rand(R, n2, generator=gen)
    vcos = torch.tensor([False, True, False])
    g = torch.randperm(P, generator=gen)[:2500].sort().values
    got = map_rows(shm._glossy_samples, [g], (face, bary, normal, wo, reg, ef, fg, lg3, kd, ks, G, vcos), chunk=1024)
    # the definition, sample by sample
    f, r, w = face[g], reg[g], torch.stack([1 - u[g] - v[g], u[g], v[g]], -1)        # (Q, 3) corner weights
    nn = torch.nn.functional.normalize(normal[g], dim=-1)
    cos = (nn * wo[g]).sum(-1)
    Rv = torch.nn.functional.normalize(2 * cos[:, None] * nn - wo[g], dim=-1)
    yG = _sh.sh_eval(Rv, order) * G[r] * torch.where(vcos[r], cos.clamp_min(0), 1.0)[:, None]
    lq = torch.einsum("qk,cqki->qci", w, lg3[:, fg[f]])                               # (Q, 3, n²) l'
    spec = torch.einsum("qci,qi->qc", lq, yG)
    e = torch.einsum("qk,qkc->qc", w, ef[f].view(-1, 3, 3))
    want = torch.where((normal[g] * wo[g]).sum(-1, keepdim=True) > 0, kd[r] * e + ks[r] * spec, 0.0).clamp_min(0.0)
    assert got.shape == (g.numel(), 3)
    assert (want > 0).float().mean() > 0.2 and (want == 0).float().mean() > 0.2        # both cases present
    assert (got - want).abs().max() <= 1e-5 * want.abs().max()


@pytest.mark.parametrize("order", [2, 5, 7])
@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "eager"])
def test_sampled_rotation_equals_band_recursion(order, compiled, monkeypatch):
    """`rotate_sampled` (the lighting rotation of `SHPRT.lighting`: P Y(Rᵀ D) c) = the
    Ivanic–Ruedenberg band recursion `sh_rotation.rotate_coeffs` to float64 round-off, for random
    proper rotations; a wrong convention (R instead of Rᵀ) differs at O(1)."""
    from methods.core.sh_rotation import rotate_coeffs
    from methods.core.sh import rotate_sampled

    monkeypatch.setenv("PRTBENCH_COMPILE", "1" if compiled else "0")
    gen = torch.Generator().manual_seed(order)
    c = torch.randn(order * order, 3, generator=gen, dtype=torch.float64)
    for _ in range(3):
        Q = torch.linalg.qr(torch.randn(3, 3, generator=gen, dtype=torch.float64))[0]
        R = Q * torch.sign(torch.det(Q))
        want = rotate_coeffs(c, R)
        assert (rotate_sampled(c, R) - want).abs().max() <= 1e-12 * want.abs().max()
        assert (rotate_coeffs(c, R.T) - want).abs().max() > 1e-3 * want.abs().max()


def test_glossy_blocks_one_call_any_count_equals_the_kernel_per_sample():
    """`_glossy_blocks` (session 19: the whole glossy pass in one compiled call with a symbolic
    sample count; one sample padded to two) = `_glossy_samples` over static blocks (`map_rows`),
    bit for bit, for 2500 samples, 1 sample and 2 samples, with no re-compilation after the first
    two-or-more-sample call (the harness compiles it in its warm-up frame)."""
    from torch._dynamo.utils import counters

    from methods.core.fused import map_rows
    from methods.sh_prt import method as shm

    gen = torch.Generator().manual_seed(5)
    order, P, M, Vg, R = 5, 3000, 40, 30, 3
    face = torch.randint(0, M, (P,), generator=gen)
    bary = torch.rand(P, 2, generator=gen) * 0.5
    normal = torch.randn(P, 3, generator=gen)
    wo = torch.nn.functional.normalize(torch.randn(P, 3, generator=gen), dim=-1)
    reg = torch.randint(0, R, (P,), generator=gen)
    args = (face, bary, normal, wo, reg, torch.rand(M, 9, generator=gen),
            torch.randint(0, Vg, (M, 3), generator=gen, dtype=torch.int32),
            torch.randn(3, Vg, order * order, generator=gen), torch.rand(R, 3, generator=gen),
            torch.rand(R, 3, generator=gen), torch.rand(R, order * order, generator=gen), torch.tensor([False, True, False]))
    g = torch.randperm(P, generator=gen)[:2500].sort().values
    want = map_rows(shm._glossy_samples, [g], args, chunk=1024)
    assert torch.equal(shm._glossy_blocks(g, args), want)
    graphs = counters["stats"]["unique_graphs"]
    for sel in (g[:1], g[7:9], g[:1777]):
        got = shm._glossy_blocks(sel, args)
        assert got.shape == (sel.numel(), 3)
        assert torch.equal(got, want[torch.searchsorted(g, sel)])
    assert counters["stats"]["unique_graphs"] == graphs


def _checker(m: SHPRT):
    """check(frame, gb): ``m.render`` equals `render_reference` of a copy sharing m's precomputation
    (its own caches) to float32 round-off, on a non-black image; returns the render."""
    ref = SHPRT.__new__(SHPRT)
    ref.__dict__ = dict(m.__dict__)
    ref._reset_cache()

    def check(frame, gb):
        img, want = m.render(frame, gb), ref.render_reference(frame, gb)
        assert want.abs().max() > 0
        assert (img - want).abs().max().item() <= 1e-5 * want.abs().max().item()
        return img
    return check


@pytest.mark.parametrize("scene_name", ["alcove", "creature"])
def test_lighting_only_frames_shade_from_the_relight_cache(scene_name):
    """Lighting-only frames (``changed`` ⊆ {"light"}, same camera, materials and G-buffer size as
    the previous render; L and E sequences) shade the glossy samples from the relight cache
    (`SHPRT._relight_build`, built by the first such frame; M l and the glossy pass skipped) and
    still equal `render_reference` (the per-chunk eager `_shade`) to float32 round-off, and a frame
    whose camera or materials changed does not use it (even when its flags claim "light" only)."""
    import dataclasses

    scene = get_scene(scene_name, "test")
    m = SHPRT(order=4, bounces=0, rays=16)
    m.precompute(scene)
    assert m.glossy_regions.any()
    check = _checker(m)

    for kind in ("L", "E"):
        m._reset_cache()
        frames = make_sequence(scene, kind, n_frames=4, seed=2)
        for f in frames:
            check(f, make_gbuffer(scene, f, 1))
        assert m.stats["relight_build"] == 1 and m.stats["relight"] == 2
        assert m.stats["glossy_light"] == 1                    # M l on frame 0 only
        assert m.memory()["relight_cache"] > 0
    last = frames[-1]
    # other materials or another camera under a "light"-only flag: not the cached samples
    mats = {r: (dataclasses.replace(mt, ks=tuple(0.5 * k for k in mt.ks)) if hasattr(mt, "ks") else mt)
            for r, mt in last.materials.items()}
    other = make_sequence(scene, "V", n_frames=2, seed=3)[1]
    for f in (dataclasses.replace(last, materials=mats), dataclasses.replace(last, camera=other.camera)):
        f = dataclasses.replace(f, changed=frozenset({"light"}))
        check(f, make_gbuffer(scene, f, 1))
        assert m.stats["relight"] == 2 and m._relight is None
    # a lighting-only frame after it builds again
    f = dataclasses.replace(frames[1], camera=other.camera, changed=frozenset({"light"}))
    check(f, make_gbuffer(scene, f, 1))
    assert m.stats["relight_build"] == 2


def test_flat_nonzero_equals_torch_nonzero():
    """`_flat_nonzero` (numpy's flatnonzero on the CPU: the glossy selection of a frame) = torch's
    ``nonzero().squeeze(-1)``: the same int64 indices in ascending order, also none and all set."""
    from methods.sh_prt.method import _flat_nonzero

    g = torch.Generator().manual_seed(0)
    for x in (torch.rand(100003, generator=g) < 0.14, torch.zeros(7, dtype=torch.bool),
              torch.ones(9, dtype=torch.bool), torch.rand(4, 64, generator=g)[:, 0] < 0.5):
        got, want = _flat_nonzero(x), x.nonzero().squeeze(-1)
        assert got.dtype == torch.int64 and torch.equal(got, want)


@pytest.mark.parametrize("C", [1, 3])
@pytest.mark.parametrize("order", [3, 5, 8])
def test_native_glossy_rows_equal_the_full_product(C, order, monkeypatch):
    """`native.rows` (the C loop) and `native.rows_torch` (its oracle) write l' = M l at the listed
    glossy vertices only, equal to `apply_lighting` over every row to float32 round-off, and leave
    the other rows untouched; at 1 and 2 threads (OpenMP's split)."""
    from methods.sh_prt import native
    from methods.sh_prt.method import apply_lighting, lighting_major

    g = torch.Generator().manual_seed(order * 10 + C)
    n2, Vg = order * order, 700
    M = lighting_major(torch.randn(Vg, n2, n2, C, generator=g))
    l = torch.randn(n2, 3, generator=g)
    full = apply_lighting(M.reshape(Vg * n2, n2, C), l).view(3, Vg, n2)
    Xm = M.permute(3, 2, 0, 1).reshape(C, n2, Vg * n2)
    rows = torch.randperm(Vg, generator=g)[:611].sort().values
    others = torch.ones(Vg, dtype=torch.bool)
    others[rows] = False
    fns = [native.rows_torch] + ([native.rows] if native.available() else [])
    for fn in fns:
        for threads in (1, 2):
            monkeypatch.setattr(torch, "get_num_threads", lambda t=threads: t)
            out = torch.full((3, Vg, n2), 7.0)
            fn(Xm, l, rows, out)
            assert (out[:, rows] - full[:, rows]).abs().max() <= 1e-5 * full.abs().max()
            assert bool((out[:, others] == 7.0).all())
    with pytest.raises(IndexError):
        native.rows(Xm, l, torch.tensor([Vg]), torch.empty(3, Vg, n2))


@pytest.mark.parametrize("scene_name, bounces", [("alcove", 0), ("creature", 0), ("alcove", 1)])
def test_lighting_change_computes_only_the_referenced_glossy_rows(scene_name, bounces):
    """A frame whose lighting changed computes l' = M l only at the glossy vertices of its glossy
    samples' faces (`SHPRT._glossy_light`, session 27) and still equals `render_reference`; a later
    frame under the same lighting whose view sees other vertices completes the table (every row
    then equal to the full product), and its image is right too."""
    import dataclasses

    from methods.sh_prt.method import apply_lighting

    scene = get_scene(scene_name, "test")
    m = SHPRT(order=4, bounces=bounces, rays=16)              # bounces 1: RGB transfer (C = 3)
    m.precompute(scene)
    assert m.M.shape[-1] == (3 if bounces else 1)
    check = _checker(m)

    frames = make_sequence(scene, "VL", n_frames=3, seed=4)
    for f in frames:
        gb = make_gbuffer(scene, f, 1)
        check(f, gb)
        F, fh = m.F, gb.face[gb.hit].long()
        gl = m.glossy_regions[gb.region[gb.hit].long()]
        want_rows = torch.unique(m.gpos[F[fh[gl]]])
        assert m._lg_valid is not None                                   # a subset, not every row
        assert torch.equal(m._lg_valid.nonzero().squeeze(-1), want_rows[want_rows >= 0])
    # the same lighting, another view: the rest of the rows, once
    other = make_sequence(scene, "V", n_frames=3, seed=9)[2]
    f = dataclasses.replace(other, envmap=frames[-1].envmap, changed=frozenset({"view"}))
    check(f, make_gbuffer(scene, f, 1))
    assert m._lg_valid is None
    ng, n2 = m.M.shape[0], m.M.shape[1]
    full = apply_lighting(m.M.reshape(ng * n2, *m.M.shape[2:]), m._light).view(3, ng, n2)
    assert (m._lg3 - full).abs().max() <= 1e-5 * full.abs().max()


def test_native_need_rows_equal_the_torch_rows():
    """`native.need_rows` (one C pass) lists the same glossy rows as `native.need_rows_torch`: the
    corner rows of the glossy samples' faces, ascending, without the ones already ``valid``."""
    from methods.sh_prt import native

    g = torch.Generator().manual_seed(3)
    M, Vg, P = 500, 300, 4000
    fg = torch.randint(0, Vg, (M, 3), generator=g, dtype=torch.int32)
    face = torch.randint(-1, M, (P,), generator=g)
    samples = (face >= 0).nonzero().squeeze(-1)[::3].contiguous()
    valid = torch.rand(Vg, generator=g) < 0.4
    for v in (None, valid):
        want = native.need_rows_torch(samples, face, fg, Vg, v)
        got = native.need_rows(samples, face, fg, Vg, v)
        assert 0 < want.numel() < Vg and torch.equal(got, want)


@pytest.mark.parametrize("S2", [1, 4, 9])
def test_native_add_pixels_is_the_scatter_add(S2):
    """`native.add_pixels` (one C pass) adds the glossy samples' radiance × 1/S² to their pixels bit
    for bit as its oracle `native.add_pixels_torch` (scatter_add_), repeats of a pixel included."""
    from methods.sh_prt import native

    gen = torch.Generator().manual_seed(S2)
    n = 500
    g = torch.randperm(n * S2, generator=gen)[: n * S2 // 2].sort().values
    vals = torch.rand(g.numel(), 3, generator=gen)
    img0 = torch.rand(n, 3, generator=gen)
    want, got = img0.clone(), img0.clone()
    native.add_pixels_torch(want, g, vals, S2)
    native.add_pixels(got, g, vals, S2)
    assert not torch.equal(want, img0) and torch.equal(got, want)
    with pytest.raises(IndexError):
        native.add_pixels(img0.clone(), torch.tensor([n * S2]), vals[:1], S2)


@pytest.mark.parametrize("vector", [False, True])
@pytest.mark.parametrize("S2", [1, 4, 9])
@pytest.mark.parametrize("threads", [1, 2])
def test_native_pixel_pass_equals_the_compiled_pass(S2, threads, vector, monkeypatch):
    """`native.pixels` (the pixel pass as one C loop that also lists the glossy samples) gives bit for
    bit the image of `_pixels_impl` (eager, and compiled by `_pixels_kernel`) and the ascending list
    of its glossy flags, for the G-buffer's layouts (column-major bary and wo, row-major normal) and
    others, with misses (face −1), back-facing samples, negative diffuse values (clamped), glossy
    faces and more pixels than one thread's share (2 threads: the per-thread lists joined); the
    scalar loop and (``vector``, S2 = 4 on AVX2 builds) its 8-lane form, whose odd last pixel the
    scalar loop takes (an odd pixel count per thread)."""
    from methods.core.fused import map_rows
    from methods.sh_prt import method as shm, native

    if not native.available():
        pytest.skip("no C compiler")
    monkeypatch.setattr(native, "VECTOR_PIXELS", vector)
    gen = torch.Generator().manual_seed(S2 + 10 * threads)
    n, M = 3 * native.MIN_PIXELS_PER_THREAD + 17, 300
    P = n * S2
    face = torch.randint(-1, M, (P,), generator=gen)
    hit = (face >= 0) & (torch.rand(P, generator=gen) < 0.95)
    bary = torch.rand(2, P, generator=gen).T * 0.5                               # column-major (Mitsuba)
    normal = torch.randn(P, 3, generator=gen)                                     # row-major
    wo = torch.randn(3, P, generator=gen).T                                       # column-major
    ef = torch.randn(M, 9, generator=gen)                                         # some e < 0: clamped
    fk = torch.cat([torch.rand(M, 3, generator=gen), (torch.rand(M, 1, generator=gen) < 0.3).float()], 1)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for layout in ((bary, normal, wo), (bary.contiguous(), normal.T.contiguous().T, wo.contiguous())):
            vecs = [shm._pixel_rows(x, n, S2) for x in layout]
            rows = (face.view(n, S2), hit.view(n, S2), *(c for v in vecs for c in v))
            lay = tuple(len(v) for v in vecs)
            want = shm._pixels_impl(*[r.contiguous() for r in rows], ef, fk, layout=lay)
            comp = map_rows(shm._pixels_kernel(lay), rows, (ef, fk), chunk=max(1, shm.PIXEL_CHUNK // S2))
            img, g = native.pixels(face, hit, *layout, ef, fk, S2)
            wg = want[1].reshape(-1).nonzero().squeeze(-1)
            assert 0 < g.numel() < P and torch.equal(g, wg)
            assert (want[0] > 0).any() and torch.equal(img, want[0]) and torch.equal(img, comp[0])
            # session 41: without the list (a relit frame) the same image, in the shape asked for
            img2, g2 = native.pixels(face, hit, *layout, ef, fk, S2, listed=False, shape=(1, n, 3))
            assert g2 is None and img2.shape == (1, n, 3) and torch.equal(img2.view(n, 3), img)
    finally:
        torch.set_num_threads(old)


@pytest.mark.parametrize("S2", [1, 4])
@pytest.mark.parametrize("threads", [1, 2])
def test_native_glossy_adding_to_the_pixels_equals_add_pixels(S2, threads, monkeypatch):
    """`native.glossy` with ``img`` (session 31: the glossy pass adds its radiance to the pixels as it
    shades, its threads' ranges moved to pixel boundaries) leaves the image `native.add_pixels_torch`
    (scatter_add_) makes from its radiance, bit for bit, and returns the same radiance: pixels with
    several glossy samples, a thread boundary inside a pixel's samples (2 threads, MIN_GLOSSY_PER_THREAD
    lowered), back-facing samples (radiance 0)."""
    from methods.sh_prt import method as shm, native

    if native.glossy is None or not native.available():
        pytest.skip("no C compiler")
    monkeypatch.setattr(native, "MIN_GLOSSY_PER_THREAD", 8)
    gen = torch.Generator().manual_seed(31 + S2 + 10 * threads)
    order, n = 5, 700
    n2, P, M, Vg, R = order * order, n * S2, 40, 30, 3
    face = torch.randint(0, M, (P,), generator=gen)
    bary = (torch.rand(2, P, generator=gen) * 0.5).T
    normal = torch.randn(P, 3, generator=gen)
    wo = torch.nn.functional.normalize(torch.randn(3, P, generator=gen), dim=0).T
    reg = torch.randint(0, R, (P,), generator=gen)
    ef = torch.rand(M, 9, generator=gen)
    fg = torch.randint(0, Vg, (M, 3), generator=gen, dtype=torch.int32)
    kd, ks, G = torch.rand(R, 3, generator=gen), torch.rand(R, 3, generator=gen), torch.rand(R, n2, generator=gen)
    vcos = torch.tensor([False, True, False])
    g = torch.randperm(P, generator=gen)[:P * 2 // 3].sort().values
    AS = shm._sh_factor_tables(order, torch.device("cpu"))
    args = (face, bary, normal, wo, reg, ef, fg, torch.randn(3, Vg, n2, generator=gen), kd, ks, G, vcos)
    img0 = torch.rand(n, 3, generator=gen)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        vals = native.glossy(g, *args, *AS)
        got = img0.clone()
        vals2 = native.glossy(g, *args, *AS, img=got, S2=S2)
    finally:
        torch.set_num_threads(old)
    want = img0.clone()
    native.add_pixels_torch(want, g, vals, S2)
    assert (vals == 0).any() and (vals > 0).any() and torch.equal(vals2, vals)
    assert not torch.equal(want, img0) and torch.equal(got, want)


@pytest.mark.parametrize("S2", [1, 4])
def test_native_view_kept_static_arguments(S2, monkeypatch):
    """Session 42 (sh42): `native.view` keeping its static arguments' checked values (`VIEW_STATIC_KEPT`) gives
    the image of the path that reads every argument each call, bit for bit, call after call: with the same
    tensors (kept), after any one of them is another tensor (the l' table, the corner table, the materials,
    vcos changed in place: read anew, never a stale pointer), with another S2 and other G-buffer arrays; the
    kept path checks the G-buffer's arrays as the full path does."""
    from methods.sh_prt import method as shm, native

    if not native.available():
        pytest.skip("no C compiler")
    gen = torch.Generator().manual_seed(42 + S2)
    order, n, M, Vg, R = 5, 515, 60, 50, 3
    n2, P = order * order, n * S2

    def gbuffer():
        face = torch.randint(-1, M, (P,), generator=gen)
        hit = (face >= 0) & (torch.rand(P, generator=gen) < 0.95)
        return (face, hit, (torch.rand(2, P, generator=gen) * 0.5).T, torch.randn(P, 3, generator=gen),
                torch.nn.functional.normalize(torch.randn(3, P, generator=gen), dim=0).T,
                torch.randint(0, R, (P,), generator=gen))

    def tables():
        return {"ef": torch.randn(M, 9, generator=gen),
                "fk": torch.cat([torch.rand(M, 3, generator=gen), (torch.rand(M, 1, generator=gen) < 0.4).float()], 1),
                "fg": torch.randint(0, Vg, (M, 3), generator=gen, dtype=torch.int32),
                "lg3": torch.randn(3, Vg, n2, generator=gen), "kd": torch.rand(R, 3, generator=gen),
                "ks": torch.rand(R, 3, generator=gen), "G": torch.rand(R, n2, generator=gen),
                "vcos": torch.tensor([False, True, False])}

    AS = shm._sh_factor_tables(order, torch.device("cpu"))

    def run(gb, t, kept):
        monkeypatch.setattr(native, "VIEW_STATIC_KEPT", kept)
        face, hit, bary, normal, wo, reg = gb
        return native.view(face, hit, bary, normal, wo, t["ef"], t["fk"], S2, reg, t["fg"], t["lg3"], t["kd"], t["ks"],
                           t["G"], t["vcos"], *AS)

    gb, t = gbuffer(), tables()
    first = run(gb, t, True)
    if first is None:
        pytest.skip("no AVX2")
    assert native._VS[0] is not None and native._VS[0][4] is t["lg3"]
    seen = [first]
    steps = [lambda: None, lambda: gb.__setitem__(slice(None), gbuffer())]
    steps += [lambda k=k: t.__setitem__(k, tables()[k]) for k in ("lg3", "ef", "fk", "fg", "kd", "ks", "G", "vcos")]
    steps += [lambda: t["lg3"].mul_(2.0), lambda: t["vcos"].logical_not_()]
    gb = list(gb)
    for step in steps:
        step()
        got, want = run(gb, t, True), run(gb, t, False)
        assert got is not None and torch.equal(got, want)
        seen.append(got)
    assert sum(not torch.equal(a, b) for a, b in zip(seen, seen[1:])) >= len(steps) - 2   # each change shows
    run(gb, t, True)
    assert native._VS[0] is not None and native._VS[0][4] is t["lg3"]        # kept: the next call takes the kept path
    face, hit, bary, normal, wo, reg = gb
    monkeypatch.setattr(native, "VIEW_STATIC_KEPT", True)
    args = (t["ef"], t["fk"], S2, reg, t["fg"], t["lg3"], t["kd"], t["ks"], t["G"], t["vcos"], *AS)
    assert native.view(face, hit, bary.double(), normal, wo, *args) is None
    assert native.view(face.int(), hit, bary, normal, wo, *args) is None
    with pytest.raises(ValueError):
        native.view(face, hit[:-1], bary, normal, wo, *args)


def _random_view_inputs(gen, n2, P, M, Vg, R, *, normal_scale=1.0, glossy_share=0.4):
    """A view pass's random G-buffer (P samples: misses, column-major barycentrics, unnormalised normals times
    ``normal_scale``) and tables (M faces, a ``glossy_share`` of them glossy, Vg glossy vertices, R regions of n2
    SH terms, the second region's lobe with its cosine), drawn from ``gen`` in one fixed order:
    (face, hit, bary, normal, wo, reg, ef, fk, fg, kd, ks, G, vcos, lg3)."""
    face = torch.randint(-1, M, (P,), generator=gen)
    hit = (face >= 0) & (torch.rand(P, generator=gen) < 0.95)
    bary = (torch.rand(2, P, generator=gen) * 0.5).T                              # column-major (Mitsuba)
    normal = torch.randn(P, 3, generator=gen) * normal_scale
    wo = torch.nn.functional.normalize(torch.randn(3, P, generator=gen), dim=0).T
    reg = torch.randint(0, R, (P,), generator=gen)
    ef = torch.randn(M, 9, generator=gen)
    fk = torch.cat([torch.rand(M, 3, generator=gen), (torch.rand(M, 1, generator=gen) < glossy_share).float()], 1)
    fg = torch.randint(0, Vg, (M, 3), generator=gen, dtype=torch.int32)
    kd, ks, G = torch.rand(R, 3, generator=gen), torch.rand(R, 3, generator=gen), torch.rand(R, n2, generator=gen)
    vcos = torch.tensor([False, True, False])
    lg3 = torch.randn(3, Vg, n2, generator=gen)
    return face, hit, bary, normal, wo, reg, ef, fk, fg, kd, ks, G, vcos, lg3


@pytest.mark.parametrize("S2", [1, 4, 9])
@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("chunk", [2, 7, 256])
def test_native_view_equals_the_two_passes(S2, threads, chunk, monkeypatch):
    """`native.view` (session 32: a view frame's pixel pass and glossy pass in one C pass, per chunk of
    pixels) gives bit for bit the image of `native.pixels` then `native.glossy` adding into its pixels —
    at 1 and 2 threads, chunk sizes odd (rounded to even), small and large, a last partial chunk, an odd
    pixel count (the scalar tail of the 8-lane pixel pass), misses, back-facing and glossy samples."""
    from methods.sh_prt import method as shm, native

    if not native.available():
        pytest.skip("no C compiler")
    monkeypatch.setattr(native, "VIEW_CHUNK", chunk)
    monkeypatch.setattr(native, "MIN_PIXELS_PER_THREAD", 64)
    gen = torch.Generator().manual_seed(32 + S2 + 10 * threads + chunk)
    order, n = 5, 1001
    n2, P, M, Vg, R = order * order, n * S2, 60, 50, 3
    face, hit, bary, normal, wo, reg, ef, fk, fg, kd, ks, G, vcos, lg3 = _random_view_inputs(gen, n2, P, M, Vg, R)
    AS = shm._sh_factor_tables(order, torch.device("cpu"))
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        got = native.view(face, hit, bary, normal, wo, ef, fk, S2, reg, fg, lg3, kd, ks, G, vcos, *AS)
        want, g = native.pixels(face, hit, bary, normal, wo, ef, fk, S2)
        before = want.clone()
        vals = native.glossy(g, face, bary, normal, wo, reg, ef, fg, lg3, kd, ks, G, vcos, *AS, img=want, S2=S2)
    finally:
        torch.set_num_threads(old)
    if got is None:
        assert vals is None
        pytest.skip("no AVX2")
    assert g.numel() > 100 and (vals > 0).any() and not torch.equal(want, before)
    assert torch.equal(got, want)


def _switch_frames(monkeypatch, threads: int, kind: str, seed: int, switch: str, entry: str, check=None) -> int:
    """A ``kind`` sequence of the test creature rendered by two copies of one SH PRT model, ``switch`` on for
    the first and off for the second: the images equal bit for bit (and ``check(a, b)`` after each frame);
    returns how many times `native.<entry>` ran."""
    import copy

    from methods.sh_prt import method as shm, native
    from references.gbuffer import make_gbuffer

    if not native.available():
        pytest.skip("no C compiler")
    scene = get_scene("creature", "test")
    m = shm.SHPRT(order=5, bounces=0, rays=16)
    m.precompute(scene)
    calls = []
    real = getattr(native, entry)
    monkeypatch.setattr(native, entry, lambda *a, **k: calls.append(1) or real(*a, **k))
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        a, b = copy.copy(m), copy.copy(m)
        a._reset_cache()
        b._reset_cache()
        for frame in make_sequence(scene, kind, n_frames=4, seed=seed):
            gb = make_gbuffer(scene, frame, 2)
            monkeypatch.setattr(shm, switch, True)
            x = a.render(frame, gb)
            monkeypatch.setattr(shm, switch, False)
            y = b.render(frame, gb)
            assert torch.equal(x, y)
            if check is not None:
                check(a, b)
    finally:
        torch.set_num_threads(old)
    return len(calls)


@pytest.mark.parametrize("threads", [1, 2])
def test_view_frames_in_one_pass_equal_the_two_passes(threads, monkeypatch):
    """A view sequence rendered with `NATIVE_VIEW` (session 32: from its second frame, once l' is
    complete, `native.view`) gives the images of the two passes bit for bit, and takes that path."""
    assert _switch_frames(monkeypatch, threads, "V", 2, "NATIVE_VIEW", "view") >= 2


@pytest.mark.parametrize("threads", [1, 2])
def test_lighting_change_frames_in_one_pass_equal_the_two_passes(threads, monkeypatch):
    """A VL sequence (every frame a lighting change and a new view) rendered with `NATIVE_VIEW_ROWS`
    (session 35: the rows each frame reads listed from the faces, computed, then one pass `native.view`)
    gives the images of the two passes bit for bit, the same rows of l' set, and takes that path."""
    def same_rows(a, b):
        assert (a._lg_valid is None) == (b._lg_valid is None)
        if a._lg_valid is not None:
            assert torch.equal(a._lg_valid, b._lg_valid)
            rows = a._lg_valid.nonzero().squeeze(-1)
            assert torch.equal(a._lg3[:, rows], b._lg3[:, rows])

    assert _switch_frames(monkeypatch, threads, "VL", 5, "NATIVE_VIEW_ROWS", "view_rows", same_rows) == 4


@pytest.mark.parametrize("fail_rows", [False, True])
@pytest.mark.parametrize("kind, threads", [("VL", 1), ("VL", 2), ("V", 1)])
def test_view_rows_marks_equal_the_index_put(kind, threads, fail_rows, monkeypatch):
    """Session 42 (sh42): a lighting change's frame taking its table's "row set" flags from `native.view_rows`'
    marks (`VIEW_ROWS_MARKS`) gives the images of the zeroed flags + index_put bit for bit and the same flags
    and rows after every frame (a V sequence: its second frame completes the table from those flags); with
    `native.rows_vertex_major` failing (``fail_rows``: the two passes then compute the rows) no row is taken
    as set."""
    from methods.sh_prt import native

    if fail_rows:
        monkeypatch.setattr(native, "rows_vertex_major", lambda *a, **k: False)

    def same_rows(a, b):
        assert (a._lg_valid is None) == (b._lg_valid is None)
        if a._lg_valid is not None:
            assert a._lg_valid.dtype == torch.bool and torch.equal(a._lg_valid, b._lg_valid)
            rows = a._lg_valid.nonzero().squeeze(-1)
            assert torch.equal(a._lg3[:, rows], b._lg3[:, rows])

    assert _switch_frames(monkeypatch, threads, kind, 7, "VIEW_ROWS_MARKS", "view_rows", same_rows) >= 1


@pytest.mark.parametrize("Q", [1, 8, 1001])
def test_native_relight_add_equals_the_gemm(Q):
    """`native.relight_add` on the packed relight cache (`native.relight_pack`, per 8 samples) adds
    to the pixels what `_relight_add`'s GEMM and scatter_add_ add on the unpacked one (to float32
    round-off; the same sums), repeated pixels and a padded last block included, and
    `relight_unpack` inverts the packing."""
    from methods.sh_prt import method as shm, native

    if not native.available():
        pytest.skip("no C compiler")
    gen = torch.Generator().manual_seed(Q)
    n2, S2, n = 25, 4, 400
    DG = torch.randn(n2, 2 * Q, generator=gen)
    kd, ks = torch.rand(3, Q, generator=gen), torch.rand(3, Q, generator=gen)
    pix = torch.randint(0, n, (Q,), generator=gen).sort().values
    l = torch.randn(n2, 3, generator=gen)
    cache = {"DG": DG, "kd": kd, "ks": ks, "pix": pix[:, None].expand(-1, 3)}
    packed = shm._relight_packed(cache)
    back = native.relight_unpack(packed["blk"], Q, n2)
    assert all(torch.equal(a, b) for a, b in zip(back, (DG, kd, ks)))
    img0 = torch.rand(n, 3, generator=gen)
    want, got = img0.clone(), img0.clone()
    shm._relight_add(want, cache, l, S2)
    assert native.relight_add(got, packed["blk"], l, packed["p"], S2)
    assert not torch.equal(want, img0)
    assert (got - want).abs().max() <= 1e-6 * (want - img0).abs().max()


@pytest.mark.parametrize("order", [3, 5, 8])
def test_native_vertex_major_rows_equal_the_full_product(order, monkeypatch):
    """`native.rows_vertex_major` (l' = M l at the listed rows from the vertex-major (Vg, n², n²) M)
    writes those rows equal to `apply_lighting` over every row to float32 round-off and leaves the
    others untouched, at 1 and 2 threads; and `SHPRT._vertex_major_M` is M's vertex-major first pass
    exactly when M is (bounces 0), None otherwise."""
    from methods.sh_prt import native
    from methods.sh_prt.method import apply_lighting, lighting_major

    if not native.available():
        pytest.skip("no C compiler")
    g = torch.Generator().manual_seed(order)
    n2, Vg = order * order, 700
    Mv = torch.randn(Vg, n2, n2, generator=g)
    l = torch.randn(n2, 3, generator=g)
    full = apply_lighting(lighting_major(Mv[..., None]).reshape(Vg * n2, n2, 1), l).view(3, Vg, n2)
    rows = torch.randperm(Vg, generator=g)[:611].sort().values
    others = torch.ones(Vg, dtype=torch.bool)
    others[rows] = False
    for threads in (1, 2):
        monkeypatch.setattr(torch, "get_num_threads", lambda t=threads: t)
        out = torch.full((3, Vg, n2), 7.0)
        assert native.rows_vertex_major(Mv, l, rows, out)
        assert (out[:, rows] - full[:, rows]).abs().max() <= 1e-5 * full.abs().max()
        assert bool((out[:, others] == 7.0).all())
        # session 41: l transposed in the C call; a strided l takes the torch transpose: the same bits
        out2 = torch.full((3, Vg, n2), 7.0)
        assert native.rows_vertex_major(Mv, l.T.contiguous().T, rows, out2) and torch.equal(out2, out)
    for bad in ([Vg], [0, -1]):                     # the rows checked (session 41: by the C call)
        out = torch.full((3, Vg, n2), 7.0)
        with pytest.raises(IndexError):
            native.rows_vertex_major(Mv, l, torch.tensor(bad), out)
        assert bool((out == 7.0).all())


def test_vertex_major_M_is_M_without_bounces(alcove):
    """`SHPRT._vertex_major_M`: the (Vg, n², n²) vertex-major values of M when it is the first pass
    alone (bounces 0, grey transfer), None when M sums bounces."""
    _, m, _, _ = alcove
    assert m.bounces == 1 and m._vertex_major_M() is None
    m0 = m.with_bounces(0)
    Mv = m0._vertex_major_M()
    assert Mv is not None and Mv.is_contiguous() and torch.equal(Mv, m0.M[..., 0])


@pytest.mark.parametrize("fused", [False, True])
@pytest.mark.parametrize("order", [3, 5, 7])
@pytest.mark.parametrize("threads", [1, 2])
def test_native_glossy_equals_the_kernel(order, threads, fused, monkeypatch):
    """`native.glossy` (the glossy samples' radiance in one AVX2 C loop, 8 samples per block) equals
    `_glossy_samples_impl` (eager: the compiled kernel's definition, its oracle) to float32 round-off
    on random tables: a Phong and a Blinn-Phong region, back-facing samples, unnormalised normals,
    a count that leaves a partial last block, l' in another memory layout, 1 and 2 threads, its
    multiply-adds unfused and (``fused``, FMA builds) fused; and it declines (None) the even orders
    it does not handle."""
    from methods.sh_prt import method as shm, native

    if native.glossy is None or not native.available():
        pytest.skip("no C compiler")
    monkeypatch.setattr(native, "FUSED_GLOSSY", fused)
    gen = torch.Generator().manual_seed(order + 100 * threads)
    n2, P, M, Vg, R = order * order, 3000, 40, 30, 3
    face = torch.randint(0, M, (P,), generator=gen)
    bary = (torch.rand(2, P, generator=gen) * 0.5).T                                # column-major
    normal = torch.randn(P, 3, generator=gen) * 1.7
    wo = torch.nn.functional.normalize(torch.randn(3, P, generator=gen), dim=0).T    # column-major
    reg = torch.randint(0, R, (P,), generator=gen)
    ef = torch.rand(M, 9, generator=gen)
    fg = torch.randint(0, Vg, (M, 3), generator=gen, dtype=torch.int32)
    kd, ks = torch.rand(R, 3, generator=gen), torch.rand(R, 3, generator=gen)
    G = torch.rand(R, n2, generator=gen)
    vcos = torch.tensor([False, True, False])
    g = torch.randperm(P, generator=gen)[:2501].sort().values
    AS = shm._sh_factor_tables(order, torch.device("cpu"))
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        lg = torch.randn(3, Vg, n2, generator=gen)
        for lg3 in (lg, lg.permute(1, 0, 2).contiguous().permute(1, 0, 2)):
            args = (face, bary, normal, wo, reg, ef, fg, lg3, kd, ks, G, vcos)
            want = shm._glossy_samples_impl(g, *args, *AS)[0]
            got = native.glossy(g, *args, *AS)
            assert got is not None and got.shape == (g.numel(), 3)
            assert (want > 0).float().mean() > 0.2 and (want == 0).float().mean() > 0.2
            assert (got - want).abs().max() <= 1e-5 * want.abs().max()
    finally:
        torch.set_num_threads(old)
    G4 = torch.rand(R, 16, generator=gen)
    assert native.glossy(g, face, bary, normal, wo, reg, ef, fg, torch.randn(3, Vg, 16), kd, ks, G4, vcos,
                         *shm._sh_factor_tables(4, torch.device("cpu"))) is None


def _vm_rows_scalar_order(Mv: torch.Tensor, l: torch.Tensor, rows: torch.Tensor) -> torch.Tensor:
    """l' = M l at ``rows`` (R, 3, n²) with the scalar sums of ``native.vm_rows`` in torch (each float32
    product and sum rounded as the C loop rounds it): per output the 8-lane partial vectors over the
    j blocks of 8, their lanes ((a0 + a4) + (a1 + a5)) + ((a2 + a6) + (a3 + a7)), then the tail j >= n8."""
    n2 = Mv.shape[1]
    n8 = n2 & ~7
    X = Mv[rows]                                                        # (R, n², n²): [q, i, j]
    lt = l.T.contiguous()                                               # (3, n²)
    out = []
    for c in range(3):
        a = torch.zeros(X.shape[0], n2, 8)
        for b in range(n8 // 8):
            a = a + X[:, :, 8 * b:8 * b + 8] * lt[c, 8 * b:8 * b + 8]
        s = ((a[..., 0] + a[..., 4]) + (a[..., 1] + a[..., 5])) + ((a[..., 2] + a[..., 6]) + (a[..., 3] + a[..., 7]))
        for j in range(n8, n2):
            s = s + X[:, :, j] * lt[c, j]
        out.append(s)
    return torch.stack(out, 1)


@pytest.mark.parametrize("order", [3, 5, 8])
def test_native_vertex_major_rows_keep_the_scalar_sums(order, monkeypatch):
    """`native.rows_vertex_major` computes 8 outputs at a time with their lane sums as one transpose-and-add
    (session 34, ``hsum8x8``): the same bits as the scalar sums it had (`_vm_rows_scalar_order`), at 1
    and 2 threads, for n² with and without a tail of outputs (9, 25) and of inputs (64: none)."""
    from methods.sh_prt import native

    if not native.available():
        pytest.skip("no C compiler")
    g = torch.Generator().manual_seed(100 + order)
    n2, Vg = order * order, 700
    Mv = torch.randn(Vg, n2, n2, generator=g)
    l = torch.randn(n2, 3, generator=g)
    rows = torch.randperm(Vg, generator=g)[:611].sort().values
    want = _vm_rows_scalar_order(Mv, l, rows)
    for threads in (1, 2):
        monkeypatch.setattr(torch, "get_num_threads", lambda t=threads: t)
        out = torch.full((3, Vg, n2), 7.0)
        assert native.rows_vertex_major(Mv, l, rows, out)
        assert torch.equal(out[:, rows].permute(1, 0, 2), want)


@pytest.mark.parametrize("threads", [1, 2])
def test_native_view_rows_equal_the_torch_rows(threads, monkeypatch):
    """`native.view_rows` (session 35: the rows of l' a view's glossy samples read, from the G-buffer's
    faces) lists the rows of `native.view_rows_torch` — those `need_rows` lists for the pixel pass's glossy
    samples (hit, on a face with the glossy flag): ascending, without the ones already ``valid`` — at 1
    and 2 threads (each thread marking its own faces), misses (face −1) and faces with the flag off."""
    from methods.sh_prt import native

    if not native.available():
        pytest.skip("no C compiler")
    monkeypatch.setattr(native, "MIN_SAMPLES_PER_MARK_THREAD", 64)
    g = torch.Generator().manual_seed(35 + threads)
    M, Vg, P = 3000, 6000, 4001                      # most faces under one sample or none: hit decides
    fg = torch.randint(0, Vg, (M, 3), generator=g, dtype=torch.int32)
    fk = torch.cat([torch.rand(M, 3, generator=g), (torch.rand(M, 1, generator=g) < 0.3).float()], 1)
    valid = torch.rand(Vg, generator=g) < 0.4
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for _ in range(3):            # (session 41: the marks in kept scratch buffers: each call its own)
            face = torch.randint(-1, M, (P,), generator=g)
            hit = (face >= 0) & (torch.rand(P, generator=g) < 0.9)
            for v in (None, valid):
                want = native.view_rows_torch(face, hit, fk, fg, Vg, v)
                got = native.view_rows(face, hit, fk, fg, Vg, v)
                assert 0 < want.numel() < Vg and torch.equal(got, want)
        gl = (hit & (fk[face.clamp_min(0), 3] != 0)).nonzero().squeeze(-1)
        assert torch.equal(native.view_rows_torch(face, hit, fk, fg, Vg, None),
                           native.need_rows_torch(gl, face, fg, Vg, None))
    finally:
        torch.set_num_threads(old)





@pytest.mark.parametrize("order", [1, 2, 3, 5, 8])
@pytest.mark.parametrize("C", [1, 3])
def test_native_rotate_equals_rotate_sampled(order, C):
    """`native.rotate` (session 35: the lighting's rotation in one C call) gives `rotate_sampled`'s
    coefficients to float64 round-off, for proper and improper rotations (Rᵀ applied: not R)."""
    from methods.core.sh import rotate_sampled
    from methods.sh_prt import native

    if not native.available():
        pytest.skip("no C compiler")
    g = torch.Generator().manual_seed(order * 10 + C)
    c = torch.randn(order * order, C, dtype=torch.float64, generator=g)
    for _ in range(3):
        R = torch.linalg.qr(torch.randn(3, 3, dtype=torch.float64, generator=g))[0]
        want = rotate_sampled(c, R)
        got = native.rotate(c, R)
        assert got is not None and got.dtype == torch.float64 and got.shape == want.shape
        assert (got - want).abs().max() <= 1e-13 * max(1.0, want.abs().max().item())
        if order > 1:
            assert (native.rotate(c, R.T) - want).abs().max() > 1e-3


@pytest.mark.parametrize("threads", [2, 3, 7])
def test_native_relight_add_threads_split_at_pixels(threads, monkeypatch):
    """Session 39: `native.relight_add` split over the threads at pixel boundaries (`RELIGHT_THREADS`)
    adds the same bits as one thread (each pixel's samples in order by one thread) — pixels with many
    samples across block and split boundaries, a padded last block — and both equal the GEMM oracle
    to float32 round-off."""
    from methods.sh_prt import method as shm, native

    if not native.available():
        pytest.skip("no C compiler")
    gen = torch.Generator().manual_seed(threads)
    n2, S2, n, Q = 25, 4, 300, 5003
    DG = torch.randn(n2, 2 * Q, generator=gen)
    kd, ks = torch.rand(3, Q, generator=gen), torch.rand(3, Q, generator=gen)
    pix = torch.randint(0, n, (Q,), generator=gen).sort().values        # ~17 samples a pixel
    l = torch.randn(n2, 3, generator=gen)
    cache = {"DG": DG, "kd": kd, "ks": ks, "pix": pix[:, None].expand(-1, 3)}
    packed = shm._relight_packed(cache)
    img0 = torch.rand(n, 3, generator=gen)
    want = img0.clone()
    shm._relight_add(want, cache, l, S2)
    old = torch.get_num_threads()
    imgs = []
    try:
        for nt, on in ((1, True), (threads, False), (threads, True)):
            torch.set_num_threads(nt)
            monkeypatch.setattr(native, "RELIGHT_THREADS", on)
            monkeypatch.setattr(native, "MIN_RELIGHT_PER_THREAD", 1)
            got = img0.clone()
            assert native.relight_add(got, packed["blk"], l, packed["p"], S2)
            imgs.append(got)
    finally:
        torch.set_num_threads(old)
    assert torch.equal(imgs[0], imgs[1]) and torch.equal(imgs[0], imgs[2])
    assert (imgs[2] - want).abs().max() <= 1e-6 * (want - img0).abs().max()
    # session 41: an (H, W, 3) image and the pixels' range kept by the caller: the same bits; a range
    # beyond the image is refused before anything is added
    img3 = img0.clone().view(3, n // 3, 3)
    assert native.relight_add(img3, packed["blk"], l, packed["p"], S2, (int(pix[0]), int(pix[-1])))
    assert torch.equal(img3.view(n, 3), imgs[0])
    with pytest.raises(IndexError):
        native.relight_add(img0.clone(), packed["blk"], l, packed["p"], S2, (0, n))
    with pytest.raises(IndexError):
        native.relight_add(img0.clone()[: n - 1], packed["blk"], l, packed["p"], S2, (0, n - 1))


def test_native_frames_do_not_import_dynamo():
    """Session 40: where the C passes run (order 5, bounces 0, AVX2), V, L, E and VL frames never touch
    `torch._dynamo` — its first touch imports it (~1 s of process CPU), which the first lighting-only frame
    of every perf process did for nothing (`torch._dynamo.maybe_mark_dynamic` of kernels that did not run:
    the creature L cell's ~1 s first timed frame). In a fresh interpreter, as the perf suite's processes."""
    import os
    import subprocess
    import sys

    from methods.sh_prt import native

    if not native.available() or not torch.backends.cpu.get_cpu_capability().startswith("AVX"):
        pytest.skip("no native SH PRT passes here")
    code = (
        "import sys\n"
        "from methods.sh_prt.method import SHPRT\n"
        "from references.gbuffer import make_gbuffer\n"
        "from scenes.library import get_scene\n"
        "from scenes.sequences import make_sequence\n"
        "scene = get_scene('sphere_plane', 'test')\n"
        "m = SHPRT(order=5, bounces=0, rays=16)\n"
        "m.precompute(scene)\n"
        "assert 'torch._dynamo' not in sys.modules\n"
        "for kind in ('V', 'L', 'E', 'VL'):\n"
        "    for f in make_sequence(scene, kind, n_frames=3, seed=1):\n"
        "        m.render(f, make_gbuffer(scene, f, 2))\n"
        "    assert 'torch._dynamo' not in sys.modules, kind\n"
        "assert m.stats['relight_build'] == 2 and m.stats['relight'] == 2, m.stats\n"
        "print('ok')\n")
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
    env = dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-c", code], cwd=root, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0 and r.stdout.strip().endswith("ok"), r.stderr[-2000:]


def _relight_inputs(scene_name: str, order: int, blinn: bool):
    """(m, frame, the `SHPRT._relight_build` arguments of a 2×2-sample G-buffer's glossy samples)."""
    import dataclasses

    scene = get_scene(scene_name, "test")
    m = SHPRT(order=order, bounces=0, rays=16)
    m.precompute(scene)
    frame = make_sequence(scene, "L", n_frames=1, seed=3)[0]
    if blinn:
        frame = dataclasses.replace(frame, materials={
            r: (BlinnPhong(kd=mt.kd, ks=mt.ks, s=4.0 * mt.s) if isinstance(mt, Phong) else mt)
            for r, mt in frame.materials.items()})
    gb = make_gbuffer(scene, frame, 2)
    m.render(frame, gb)                                                 # sets the per-face tables
    kd, ks, G, vcos = m._materials(frame)
    fk = m._face_materials(kd)
    face, hit = gb.face, gb.hit
    g = (hit & (fk[face.clamp(0, fk.shape[0] - 1), 3] != 0)).nonzero().squeeze(-1)
    args = (g, face, gb.bary.float(), gb.normal.float(), gb.wo.float(), gb.region, kd, ks, G, vcos, 4)
    return m, args


@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("scene_name, order, blinn", [("creature", 5, False), ("creature", 5, True),
                                                      ("alcove", 3, False), ("alcove", 8, True), ("creature", 2, True)])
def test_native_relight_build_equals_the_torch_build(scene_name, order, blinn, threads, monkeypatch):
    """Session 40: the relight cache by one C pass straight into the packed layout (`native.relight_build`,
    `NATIVE_RELIGHT_BUILD`) equals the torch build (its oracle, then `relight_pack`): the pixels and the kd /
    ks rows (zero on back-facing samples) bit for bit, d and the transferred lobe Σ_k w_k M_kᵀ q to float32
    round-off (their sums in another order), the padding of the last block zero; at 1 and 3 threads the same
    bits; with the transfer vectors vertex-major or strided (lighting-major) the same bits. Phong and
    Blinn-Phong (× n·ωo) lobes."""
    from methods.sh_prt import method as shm, native

    if not native.available():
        pytest.skip("no C compiler")
    m, args = _relight_inputs(scene_name, order, blinn)
    g, n2, Q = args[0], order * order, int(args[0].numel())
    assert Q > 100 and bool(args[9].any()) == blinn
    monkeypatch.setattr(shm, "NATIVE_RELIGHT_BUILD", False)
    want = m._relight_build(*args)
    monkeypatch.setattr(shm, "NATIVE_RELIGHT_BUILD", True)
    monkeypatch.setattr(native, "MIN_BUILD_PER_THREAD", 1)
    old = torch.get_num_threads()
    try:
        torch.set_num_threads(threads)
        got = m._relight_build(*args)
        torch.set_num_threads(1)
        one = m._relight_build(*args)
        # the same pass on the lighting-major (strided) transfer vectors
        kd, ks, G, vcos = args[6:10]
        strided = native.relight_build(g, args[1], args[2], args[3], args[4], args[5], m.F, m._fg, m.t[..., 0],
                                       m._vertex_major_M(), kd, ks, G, vcos, *shm._sh_factor_tables(order, G.device), 4)
    finally:
        torch.set_num_threads(old)
    assert "blk" in got and got["blk"].shape == want["blk"].shape and got["Qg"] == Q and got["n2"] == n2
    assert torch.equal(got["blk"], one["blk"]) and torch.equal(got["p"], one["p"])
    assert m.t[..., 0].stride(0) == 1 and torch.equal(strided[0], got["blk"]) and torch.equal(strided[1], got["p"])
    assert torch.equal(got["p"], want["p"])
    a, b = native.relight_unpack(got["blk"], Q, n2), native.relight_unpack(want["blk"], Q, n2)
    assert torch.equal(a[1], b[1]) and torch.equal(a[2], b[2]) and bool((b[1] == 0).any())   # some back-facing
    for x, y in ((a[0][:, :Q], b[0][:, :Q]), (a[0][:, Q:], b[0][:, Q:])):             # d, then the lobe
        assert y.abs().max() > 0 and (x - y).abs().max() <= 2e-6 * y.abs().max()
    pad = got["blk"].view(-1, 2 * n2 + 6, 8)[-1, :, Q % 8:] if Q % 8 else torch.zeros(1)
    assert bool((pad == 0).all())


@pytest.mark.parametrize("isa", ["host", "scalar"])
@pytest.mark.parametrize("scene_name, order, blinn", [("creature", 5, False), ("creature", 5, True),
                                                      ("alcove", 3, False), ("alcove", 8, True), ("creature", 2, True)])
def test_fast_relight_build_equals_the_session_40_pass(scene_name, order, blinn, isa, monkeypatch):
    """Session 42 (sh42): `rb_range2` (`FAST_RELIGHT_BUILD`: each block's per-sample scalars and lobe row in
    vector lanes, the three corners' lobes in one loop, the [d | lobe] rows stored by 8 x 8 transposes, no
    memset of the blocks) equals `rb_range` (session 40's
    pass, its oracle) bit for bit: every value of every block, the last block's padding lanes zero even where
    the buffer held other values, the pixels; at 1 and 3 threads (block ranges split over the threads); with
    the host's ISA flags (the AVX2 lanes) and without any ("scalar": the library's fallback loops). Phong and
    Blinn-Phong lobes, orders 2, 3, 5 (unrolled) and 8."""
    from methods.sh_prt import method as shm, native

    if not native.available():
        pytest.skip("no C compiler")
    if isa == "scalar":
        monkeypatch.setattr(native, "_flags", lambda: ("-fopenmp", "-ffp-contract=off"))
        monkeypatch.setattr(native, "_LOADED", [None])          # (the library rebuilt with those flags)
    m, args = _relight_inputs(scene_name, order, blinn)
    g, face, bary, normal, wo, reg, kd, ks, G, vcos, S2 = args
    Q = int(g.numel())
    assert Q > 100 and (isa == "host" or Q % 8)        # (the creature's test G-buffer: a short last block)
    T, Mv = m.t_parts[0][..., 0], m._vertex_major_M()
    AS = shm._sh_factor_tables(order, G.device)
    monkeypatch.setattr(native, "MIN_BUILD_PER_THREAD", 1)
    real_empty = torch.empty

    def dirty_empty(*a, **k):                          # a buffer full of garbage: the padding must be written
        return real_empty(*a, **k).fill_(float("nan") if k.get("dtype", torch.float32) == torch.float32 else -7)

    old = torch.get_num_threads()
    try:
        res = {}
        for fast in (False, True):
            monkeypatch.setattr(native, "FAST_RELIGHT_BUILD", fast)
            for threads in (1, 3):
                torch.set_num_threads(threads)
                monkeypatch.setattr(native.torch, "empty", dirty_empty)
                res[fast, threads] = native.relight_build(g, face, bary, normal, wo, reg, m.F, m._fg, T, Mv, kd, ks, G,
                                                          vcos, *AS, S2)
                monkeypatch.setattr(native.torch, "empty", real_empty)
    finally:
        torch.set_num_threads(old)
        monkeypatch.setattr(native.torch, "empty", real_empty)
    want = res[False, 1]
    assert want is not None and bool(torch.isfinite(want[0]).all())
    for key, got in res.items():
        assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1]), key
    if Q % 8:
        assert bool((want[0].view(-1, 2 * order ** 2 + 6, 8)[-1, :, Q % 8:] == 0).all())
    # the samples' bounds, checked by the C call on this path (`FAST_RELIGHT_BUILD`): one sample outside the
    # G-buffer, at either end, raises as the Python check did
    monkeypatch.setattr(native, "FAST_RELIGHT_BUILD", True)
    for bad in (-1, int(face.numel())):
        gb_ = g.clone()
        gb_[Q // 2] = bad
        with pytest.raises(IndexError):
            native.relight_build(gb_, face, bary, normal, wo, reg, m.F, m._fg, T, Mv, kd, ks, G, vcos, *AS, S2)


@pytest.mark.parametrize("threads", [1, 3])
@pytest.mark.parametrize("scene_name, order", [("sphere_plane", 5), ("alcove", 3), ("alcove", 8), ("sphere_plane", 2)])
def test_native_light_stage_equals_the_torch_stage(scene_name, order, threads, monkeypatch):
    """Session 41: a lighting change's light stage by one C call (`native.Light`, `NATIVE_LIGHT`: the rotation
    of the cached polar coefficients, e = t·l and the face-corner table) equals the torch stage (its oracle):
    l to float32 round-off (the 3 × 3 product W Qᵀ in another order), e = t·l to float32 round-off (the
    GEMM's own order over j), the corner table = e at each face's corners bit for bit, the same bits at 1
    and 3 threads (vertex ranges split off the 8-lane blocks); the same lighting is not recomputed, a new
    rotation is; L and VL frames' images equal the torch stage's to float32 round-off."""
    from methods.sh_prt import method as shm, native

    if not native.available():
        pytest.skip("no C compiler")
    scene = get_scene(scene_name, "test")
    m = SHPRT(order=order, bounces=0, rays=16)
    m.precompute(scene)
    monkeypatch.setattr(native, "MIN_LIGHT_PER_THREAD", 1)
    V = int(m.t.shape[0])
    assert V % 8 and V > 24                     # a scalar tail and, at 3 threads, ranges split off the blocks
    old = torch.get_num_threads()
    try:
        for kind in ("L", "VL", "E"):
            frames = make_sequence(scene, kind, n_frames=3, seed=2)
            gbs = [make_gbuffer(scene, f, 2) for f in frames]
            a, b, one = (m.with_bounces(0) for _ in range(3))
            for f, gb in zip(frames, gbs):
                monkeypatch.setattr(shm, "NATIVE_LIGHT", False)
                want = b.render(f, gb)
                monkeypatch.setattr(shm, "NATIVE_LIGHT", True)
                torch.set_num_threads(threads)
                n_light = a.stats["light"]
                got = a.render(f, gb)
                assert a.stats["light"] == n_light + 1 and a._nlight is not None and a._nlight[2].ok
                a.render(f, gb)                                       # the same lighting: not again
                assert a.stats["light"] == n_light + 1
                torch.set_num_threads(1)
                one.render(f, gb)
                lmax = b._light.abs().max()
                assert (a._light - b._light).abs().max() <= 1e-6 * lmax
                emax = b._e.abs().max()
                assert (a._e - b._e).abs().max() <= 2e-6 * emax and float((a._e - b._e).abs().max()) < 1e-3
                e3 = a._e.T
                assert torch.equal(a._ef, e3.reshape(-1)[m._corner_index("cpu")].view(-1, 9))
                assert torch.equal(a._e, one._e) and torch.equal(a._ef, one._ef) and torch.equal(a._light, one._light)
                assert (got - want).abs().max() <= 1e-5 * want.abs().max().clamp_min(1e-6)
    finally:
        torch.set_num_threads(old)
    rgb = m.with_bounces(0)
    rgb.t = rgb.t.expand(-1, -1, 3)                             # RGB transfer: the torch stage
    f = make_sequence(scene, "L", n_frames=1, seed=2)[0]
    rgb._light_stage(f.envmap)
    assert (rgb._nlight is None or rgb._nlight[2] is None) and rgb.stats["light"] == 1


def test_light_stage_key_follows_the_rotation_in_place():
    """Session 41: `_light_stage` skips its key's values when the map's ``to_world`` is the same tensor at the
    same version (a V frame), and recomputes when that tensor is changed in place (its version bumps) or
    another tensor holds other values; another tensor with the same values is the same lighting."""
    scene = get_scene("sphere_plane", "test")
    m = SHPRT(order=3, bounces=0, rays=8)
    m.precompute(scene)
    env = make_sequence(scene, "L", n_frames=1, seed=1)[0].envmap.rotated(torch.eye(3, dtype=torch.float64))
    m._light_stage(env)
    n, l0 = m.stats["light"], m._light.clone()
    m._light_stage(env)
    assert m.stats["light"] == n
    m._light_stage(env.rotated(torch.eye(3, dtype=torch.float64)))      # a new tensor, the same values
    assert m.stats["light"] == n
    m._light_stage(env)                                                 # (this tensor the key's again)
    assert m.stats["light"] == n and m._key_w[0] is env.to_world
    env.to_world.copy_(torch.as_tensor(rotation_y(0.7), dtype=torch.float64) @ env.to_world)
    m._light_stage(env)
    assert m.stats["light"] == n + 1 and (m._light - l0).abs().max() > 1e-3
    want = SHPRT.lighting(m, env).float()
    assert (m._light - want).abs().max() <= 1e-6 * want.abs().max()


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("S2", [1, 4])
def test_order5_glossy_body_equals_the_body_for_any_order(threads, S2, monkeypatch):
    """Session 43 (sh43): the fused glossy pass's order-5 body (`native.ORDER5_BODY`: n a compile-time constant)
    and the pass's values handed to the pixels' add in registers give bit for bit the body for any order's
    results — `native.glossy` (its values and the pixels it adds to) and `native.view` — on random tables with a
    Phong and a Blinn-Phong region, back-facing samples, unnormalised normals, a partial last block; and order 3
    and 7 (the body for any order) are unchanged by the switch."""
    from methods.sh_prt import method as shm, native

    if not native.available():
        pytest.skip("no C compiler")
    monkeypatch.setattr(native, "FUSED_GLOSSY", True)
    monkeypatch.setattr(native, "MIN_PIXELS_PER_THREAD", 64)
    monkeypatch.setattr(native, "MIN_GLOSSY_PER_THREAD", 64)
    gen = torch.Generator().manual_seed(43 + S2 + 10 * threads)
    for order in (5, 3, 7):
        n2, n, M, Vg, R = order * order, 1001, 60, 50, 3
        P = n * S2
        face, hit, bary, normal, wo, reg, ef, fk, fg, kd, ks, G, vcos, lg3 = _random_view_inputs(
            gen, n2, P, M, Vg, R, normal_scale=1.7, glossy_share=0.5)
        AS = shm._sh_factor_tables(order, torch.device("cpu"))
        g = hit.logical_and(fk[face.clamp(0, M - 1), 3] != 0).nonzero().squeeze(-1)
        old = torch.get_num_threads()
        torch.set_num_threads(threads)
        out = {}
        try:
            for body in (True, False):
                monkeypatch.setattr(native, "ORDER5_BODY", body)
                img = torch.rand(n, 3, generator=torch.Generator().manual_seed(7))
                vals = native.glossy(g, face.clamp(0, M - 1), bary, normal, wo, reg, ef, fg, lg3, kd, ks, G, vcos, *AS,
                                     img=img, S2=S2)
                view = native.view(face, hit, bary, normal, wo, ef, fk, S2, reg, fg, lg3, kd, ks, G, vcos, *AS)
                out[body] = (vals, img, view)
        finally:
            torch.set_num_threads(old)
        if out[True][2] is None:
            pytest.skip("no AVX2")
        (va, ia, wa), (vb, ib, wb) = out[True], out[False]
        assert g.numel() > 100 and (va > 0).float().mean() > 0.2 and (va == 0).float().mean() > 0.05
        assert torch.equal(va, vb) and torch.equal(ia, ib) and torch.equal(wa, wb)


@pytest.mark.parametrize("threads", [1, 2])
def test_view_again_equals_render(threads, monkeypatch):
    """Session 43 (sh43): a view frame after a one-pass view frame rendered by `SHPRT._view_again` (`VIEW_AGAIN`:
    the kept `native.view` call) gives bit for bit `_render`'s image (the switch off) and the same state, frame after
    frame of a sequence that also changes, between view frames, the lighting's rotation (a new tensor, and the same
    tensor rotated in place), the env map's texels in place, a material (a new object), the G-buffer's sample
    count, the thread count and the glossy pass's switches; it takes the fast path on the plain view frames only."""
    import copy
    import dataclasses

    from methods.sh_prt import method as shm, native
    from scenes.library import rotation_y

    if not native.available():
        pytest.skip("no C compiler")
    scene = get_scene("creature", "test")
    m = shm.SHPRT(order=5, bounces=0, rays=16)
    m.precompute(scene)
    frames = make_sequence(scene, "V", n_frames=14, seed=3)
    env2 = EnvMap(frames[0].envmap.data.clone(), frames[0].envmap.to_world)
    name = next(r for r in m.regions if frames[0].materials[r].kind == "lambert")
    mats = dict(frames[0].materials, **{name: Lambert(kd=(0.2, 0.5, 0.3))})
    events = {4: "rotation", 6: "rotate in place", 8: "texels", 10: "material", 11: "spp", 12: "threads",
              13: "fused"}
    taken = []
    real = shm.SHPRT._view_again

    def spy(self, *a):
        img = real(self, *a)
        taken.append(img is not None)
        return img
    monkeypatch.setattr(shm.SHPRT, "_view_again", spy)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    a, b = copy.copy(m), copy.copy(m)
    a._reset_cache()
    b._reset_cache()
    try:
        for i, frame in enumerate(frames):
            ev = events.get(i)
            if ev == "rotation":
                env2.to_world = torch.as_tensor(rotation_y(0.7), dtype=env2.to_world.dtype)
            if ev == "rotate in place":
                env2.to_world.copy_(torch.as_tensor(rotation_y(-0.4), dtype=env2.to_world.dtype))
            if ev == "texels":
                env2.data.mul_(1.5)
            if ev == "threads":
                torch.set_num_threads(3 - threads)
            if ev == "fused":
                monkeypatch.setattr(native, "ORDER5_BODY", False)
            if i >= 4:
                frame = dataclasses.replace(frame, envmap=env2, materials=mats if i >= 10 else frame.materials)
            gb = make_gbuffer(scene, frame, 1 if ev == "spp" else 2)
            taken.clear()
            monkeypatch.setattr(shm, "VIEW_AGAIN", True)
            x = a.render(frame, gb)
            fast = taken == [True]
            monkeypatch.setattr(shm, "VIEW_AGAIN", False)
            y = b.render(frame, gb)
            assert torch.equal(x, y), (i, ev)
            assert a.stats == b.stats and a._view_state == b._view_state and a._last_gbuffer is b._last_gbuffer
            assert (a._relight is None) == (b._relight is None)
            # frames 0-1: the lighting change and the table's completion; the first frame after each change, and
            # the spp / thread frames (another G-buffer or the same call at another thread count: fast), take it
            # only where nothing it checks changed
            want_fast = i >= 2 and ev not in ("rotation", "rotate in place", "texels", "material", "spp", "fused") \
                and events.get(i - 1) not in ("rotation", "rotate in place", "texels", "material", "spp", "fused")
            assert fast == want_fast, (i, ev, taken)
    finally:
        torch.set_num_threads(old)


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("n", [1000, 1001])
def test_pixel_pass_writes_no_pixel_past_its_range(threads, n, monkeypatch):
    """Session 43 (sh43): the 8-lane pixel pass stores a pixel pair's second pixel 4 floats wide (the 4th on the next
    pixel, written after it) except in its range's last group (`SH_PX_WIDE_STORE`): called on an image buffer one
    pixel longer than its n pixels, the pixel after them keeps its values (a wide last store would zero its first
    channel), and the n pixels are `native.pixels`' — at 1 and 2 threads (ranges ending mid-image), n even and odd."""
    import ctypes

    from methods.sh_prt import native

    lib = native._lib()
    if lib is None:
        pytest.skip("no C compiler")
    monkeypatch.setattr(native, "MIN_PIXELS_PER_THREAD", 64)
    gen = torch.Generator().manual_seed(n + threads)
    S2, M = 4, 60
    P = n * S2
    face = torch.randint(-1, M, (P,), generator=gen)
    hit = (face >= 0) & (torch.rand(P, generator=gen) < 0.95)
    bary = (torch.rand(2, P, generator=gen) * 0.5).T
    normal = torch.randn(P, 3, generator=gen)
    wo = torch.nn.functional.normalize(torch.randn(3, P, generator=gen), dim=0).T
    ef = torch.rand(M, 9, generator=gen) + 0.5
    fk = torch.cat([torch.rand(M, 3, generator=gen) + 0.5, (torch.rand(M, 1, generator=gen) < 0.3).float()], 1)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        want = native.pixels(face, hit, bary, normal, wo, ef, fk, S2)
        if want is None:
            pytest.skip("no C loop")
        img = torch.full((n + 1, 3), 7.0)
        gl = torch.empty(P, dtype=torch.int64)
        cnt = ctypes.c_int64(0)
        lib.sh_pixels(n, S2, face.data_ptr(), hit.data_ptr(), bary.data_ptr(), bary.stride(0), bary.stride(1),
                      normal.data_ptr(), normal.stride(0), normal.stride(1), wo.data_ptr(), wo.stride(0),
                      wo.stride(1), ef.data_ptr(), fk.data_ptr(), M, 1.0 / S2, img.data_ptr(), gl.data_ptr(),
                      ctypes.addressof(cnt), threads, 1)
    finally:
        torch.set_num_threads(old)
    assert (want[0] > 0).float().mean() > 0.3
    assert torch.equal(img[n], torch.full((3,), 7.0)) and torch.equal(img[:n], want[0])
