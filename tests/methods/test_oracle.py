"""The oracle agrees with Mitsuba's direct-lighting reference, and the agreement is noise, not bias.

If these fail, a convention differs between our side (scenes, materials, env map, camera, G-buffer)
and Mitsuba's; no method score means anything until they pass.

Estimator budgets: "lo" = 64 samples per pixel on both sides (oracle: 2×2 G-buffer sub-samples ×
(8 env + 8 BRDF) MIS samples; reference: 64 spp), "hi" = 4× that (4×4 sub-samples; 256 spp).
RMSE² = var_oracle + var_reference + bias²: with no bias, quadrupling both budgets halves the RMSE.
"""
from __future__ import annotations

import dataclasses

import pytest
import torch

from methods.registry import get_method
from references.gbuffer import make_gbuffer
from references.metrics import rmse
from references.render import render_reference
from scenes.envmap import procedural
from scenes.library import SCENES, get_scene
from scenes.sequences import make_sequence

# Halving ±30 % (the criterion). The RMSE of a Monte-Carlo estimate over ~4K pixels is
# itself known to a few percent; the pixel-integration error of the stratified G-buffer falls at
# least as fast as the noise, so an unbiased pair lands in [0.35, 0.65].
HALVING, HALVING_TOL = 0.5, 0.3
LO = dict(S=2, light=8, brdf=8, spp=64)
HI = dict(S=4, light=8, brdf=8, spp=256)
ENVMAPS = ["sky_sun", "studio", "window", "overcast"]

CASES = [(s, None) for s in SCENES] + [("sphere_plane", e) for e in ENVMAPS]


def _frame(scene, env_name):
    frame = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    if env_name is not None:
        frame = dataclasses.replace(frame, envmap=procedural(env_name, height=64))
    return frame


def _oracle_vs_reference(scene, frame, budget, seed):
    gb = make_gbuffer(scene, frame, budget["S"])
    oracle = get_method("oracle")(light_samples=budget["light"], brdf_samples=budget["brdf"], seed=seed)
    oracle.precompute(scene)
    img = oracle.render(frame, gb)
    ref = render_reference(scene, frame, bounces=0, spp=budget["spp"], seed=seed + 1)
    return img, ref, gb.coverage


@pytest.mark.slow
@pytest.mark.parametrize("scene_name,env_name", CASES, ids=[f"{s}-{e or 'own'}" for s, e in CASES])
def test_oracle_matches_mitsuba_direct_and_converges(scene_name, env_name):
    scene = get_scene(scene_name, "test")
    frame = _frame(scene, env_name)
    img_lo, ref_lo, cov_lo = _oracle_vs_reference(scene, frame, LO, seed=11)
    img_hi, ref_hi, cov_hi = _oracle_vs_reference(scene, frame, HI, seed=23)
    mask = cov_lo & cov_hi & ref_lo.coverage & ref_hi.coverage
    assert mask.float().mean() > 0.2, "scene covers too few pixels to test anything"
    e_lo = rmse(img_lo, ref_lo.image, mask)
    e_hi = rmse(img_hi, ref_hi.image, mask)
    scale = ref_hi.image[mask].mean().item()
    ratio = e_hi / e_lo
    print(f"{scene_name}/{env_name or 'own'}: rmse lo {e_lo:.4g} hi {e_hi:.4g} ratio {ratio:.3f} "
          f"(mean radiance {scale:.4g}; ref floors {ref_lo.noise_floor:.4g} {ref_hi.noise_floor:.4g})")
    assert abs(ratio - HALVING) <= HALVING_TOL * HALVING, (
        f"oracle-reference RMSE went {e_lo:.4g} -> {e_hi:.4g} (ratio {ratio:.3f}) when both budgets "
        f"quadrupled: not pure noise, a convention differs")
    # The mean over the image must agree too (a global scale error would show here first).
    m_o, m_r = img_hi[mask].mean().item(), ref_hi.image[mask].mean().item()
    assert abs(m_o - m_r) <= 3 * e_hi / mask.sum().item() ** 0.5 + 1e-3 * m_r


def test_oracle_is_deterministic():
    scene = get_scene("sphere_plane", "test")
    frame = _frame(scene, None)
    gb = make_gbuffer(scene, frame, 1)
    a = get_method("oracle")(light_samples=2, brdf_samples=2, seed=3)
    a.precompute(scene)
    b = get_method("oracle")(light_samples=2, brdf_samples=2, seed=3)
    b.precompute(scene)
    assert torch.equal(a.render(frame, gb), b.render(frame, gb))


@pytest.mark.parametrize("bad", [dict(light_samples=-1), dict(light_samples=0, brdf_samples=0),
                                 dict(brdf_samples=1.5)])
def test_oracle_rejects_bad_config(bad):
    with pytest.raises(ValueError):
        get_method("oracle")(**bad)


# -- the cost model ------------------------------------------------------------------------------


def _counting_visibility(monkeypatch):
    """Patch the oracle's ray tracer so that it counts the shadow rays it is asked to trace."""
    import methods.oracle as oracle_mod

    traced = [0]
    real = oracle_mod.make_visibility
    monkeypatch.setattr(oracle_mod, "OWN_TRACER", False)  # Mitsuba's tracer, not the oracle's own (session 34)

    class Counting:
        def __init__(self, vis):
            self.vis = vis

        def occluded(self, o, d):
            traced[0] += int(o.shape[0])
            return self.vis.occluded(o, d)

    monkeypatch.setattr(oracle_mod, "make_visibility", lambda V, F: Counting(real(V, F)))
    return traced


def test_oracle_frame_cost_is_the_hand_count(monkeypatch):
    """Bytes and flops of the estimator counted here from the G-buffer, the scene and the rays it
    traced (Oracle.frame_cost's docstring): every frame kind costs the same on a static scene."""
    import math

    from methods.base import FrameCost
    from methods.oracle import Oracle

    traced = _counting_visibility(monkeypatch)
    scene = get_scene("sphere_plane", "test")
    frame = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    frame = dataclasses.replace(frame, camera=dataclasses.replace(frame.camera, width=16, height=16))
    gb = make_gbuffer(scene, frame, 1)
    o = Oracle(light_samples=2, brdf_samples=3)
    assert o.frame_cost("V", gb.num_samples) is None
    o.precompute(scene)
    o.render(frame, gb)
    P, Q = gb.num_samples, int(gb.hit.sum())
    faces = torch.unique(gb.face[gb.hit])
    verts = torch.unique(scene.geometry().F[faces]).numel()
    H, W = scene.envmap.data.shape[:2]
    C = (H - 1) * W
    live = traced[0]
    assert 0 < live < Q * 5
    b = Q * 53 + (P - Q) * 1 + P * 12 + faces.numel() * 24 + verts * 12 + min(H * W, 4 * live) * 12 \
        + min(C, Q * 2 * math.ceil(math.log2(C))) * 8 + min(C, Q * 2) * 8
    f = Q * 56 + Q * 5 * 31 + live * 54
    for kind in ("V", "VBL", "L", "E", "P"):          # static scene: a "P" frame skins nothing
        assert o.frame_cost(kind, P) == FrameCost(b, f, live), kind   # rays: the live rays traced
    big = o.frame_cost("V", 4 * P)                     # no render of that size: all hit, all live
    assert big.flops == 4 * P * (56 + 5 * 31 + 5 * 54)
    assert big.rays == 4 * P * 5
    for kind, n in (("X", P), ("V", -1), ("V", 2.0)):
        with pytest.raises(ValueError):
            o.frame_cost(kind, n)


def test_oracle_frame_cost_of_a_posed_frame():
    """A "P" frame adds the skinning: per skinned vertex 12 MACs per joint and 21 to apply it."""
    from methods.oracle import Oracle

    scene = get_scene("creature", "test")
    o = Oracle(light_samples=1, brdf_samples=1)
    o.precompute(scene)
    v, p = o.frame_cost("V", 100), o.frame_cost("P", 100)
    shapes = [(int(w.shape[0]), int(w.shape[1])) for w in scene.skin_weights.values()]
    assert shapes
    assert p.bytes - v.bytes == sum(n * (6 + J) * 4 for n, J in shapes)
    assert p.flops - v.flops == sum(n * 2 * (12 * J + 21) for n, J in shapes)


# -- the compiled path ---------------------------------------------------------------------------


class _HalfMix:
    """Not a library material: half of ``m`` (eval, pdf and sample delegated), no ``kind``."""

    def __init__(self, m) -> None:
        self.m = m

    def eval(self, wi, wo):
        return 0.5 * self.m.eval(wi, wo)

    def pdf(self, wi, wo):
        return self.m.pdf(wi, wo)

    def sample(self, wo, u):
        return self.m.sample(wo, u)


@pytest.mark.parametrize("scene_name,kind", [("sphere_plane", "VBL"), ("chess", "V"), ("sphere_plane", "ward+ts"),
                                                    ("sphere_plane", "duck")])
@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "eager"])
def test_oracle_fast_equals_reference(scene_name, kind, compiled, monkeypatch):
    """`Oracle.render` (material-free passes compiled, one ray batch) = `render_reference` (the eager
    per-region estimator): same random numbers, same rays traced, the image to float32 round-off
    (amplified at most by the env map's texel-to-texel contrast through the bilinear look-up), for
    both MIS strategies, each alone, and ray batches smaller than a region (max_rays_per_batch)."""
    monkeypatch.setenv("PRTBENCH_COMPILE", "1" if compiled else "0")
    from scenes.materials import TorranceSparrow, Ward

    scene = get_scene(scene_name, "test")
    frame = make_sequence(scene, kind if kind in ("V", "VBL") else "V", n_frames=2, seed=0)[1]
    if kind == "ward+ts":  # the families no library scene uses: Ward compiled, Torrance-Sparrow eager
        mats = [Ward(kd=(0.3, 0.2, 0.1), ks=(0.4, 0.4, 0.4), ax=0.15, ay=0.3),
                TorranceSparrow(kd=(0.2, 0.3, 0.4), ks=(0.5, 0.5, 0.5), sigma=0.25)]
        frame = dataclasses.replace(frame, materials={r: mats[i % 2] for i, r in enumerate(frame.materials)})
    if kind == "duck":  # any object with eval / pdf / sample (no `kind`): its own methods, eagerly
        frame = dataclasses.replace(frame, materials={r: _HalfMix(m) for r, m in frame.materials.items()})
    gb = make_gbuffer(scene, frame, 1)
    for cfg in (dict(light_samples=2, brdf_samples=3, max_rays_per_batch=1 << 12),
                dict(light_samples=0, brdf_samples=2), dict(light_samples=2, brdf_samples=0)):
        o = get_method("oracle")(**cfg, seed=5)
        o.precompute(scene)
        ref = o.render_reference(frame, gb)
        last = o._last
        img = o.render(frame, gb)
        assert o._last == last, cfg          # same hit samples and live (traced) rays
        assert img.shape == ref.shape
        err = (img - ref).abs().max().item()
        assert err <= 1e-4 * ref.abs().max().item(), (cfg, err)


# -- the C loops (methods.oracle.native_rays) ---------------------------------------------------------


def _materials_frame(mats, kind):
    """(scene, frame 1 of a ``kind`` sequence): chess's library materials, or sphere_plane with the
    regions given ``_native_materials(mats)`` in turn."""
    scene = get_scene("chess" if mats == "library" else "sphere_plane", "test")
    frame = make_sequence(scene, kind, n_frames=2, seed=0)[1]
    if mats != "library":
        ms = _native_materials(mats)
        frame = dataclasses.replace(frame, materials={r: ms[i % len(ms)] for i, r in enumerate(frame.materials)})
    return scene, frame


def _native_materials(name):
    from scenes.materials import BlinnPhong, CookTorrance, Lambert, Phong, Ward

    return {
        "ward+lambert": [Ward(kd=(0.3, 0.2, 0.1), ks=(0.4, 0.4, 0.4), ax=0.15, ay=0.3), Lambert(kd=(0.5, 0.4, 0.3))],
        "ct+blinn": [CookTorrance(kd=(0.1, 0.2, 0.3), ks=(0.5, 0.5, 0.5), m=0.2, F0=0.3),
                     BlinnPhong(kd=(0.4, 0.3, 0.2), ks=(0.3, 0.3, 0.3), s=25.0)],
        # no diffuse part (the specular lobe sampled alone), no specular part (a Phong with ks = 0)
        "spec-only+no-spec": [Phong(kd=0.0, ks=(0.6, 0.5, 0.4), s=15.0), Phong(kd=(0.5, 0.5, 0.5), ks=0.0, s=15.0)],
    }[name]


@pytest.mark.parametrize("mats", ["library", "ward+lambert", "ct+blinn", "spec-only+no-spec"])
def test_oracle_native_equals_reference_and_compiled(mats, monkeypatch):
    """The C loops (`methods.oracle.native_rays`: every region's BRDF with a C body) = the eager estimator
    (`render_reference`), and on the library's chess materials the compiled path too (the C loops
    switched off): the same rays traced (live counts) and the image to float32 round-off (the
    tolerance of `test_oracle_fast_equals_reference`), for every BRDF family with a C body,
    specular-only and diffuse-only mixtures, both MIS strategies, each alone, and ray batches smaller
    than a region. Checks that the C path ran."""
    import methods.oracle.native_rays as on

    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    if not on.available():
        pytest.skip("no C compiler: the C loops do not run")
    scene, frame = _materials_frame(mats, "VBL")
    gb = make_gbuffer(scene, frame, 1)
    calls = [0]
    real = on.pretrace

    def counting(*a, **k):
        calls[0] += 1
        return real(*a, **k)

    for cfg in (dict(light_samples=3, brdf_samples=2, max_rays_per_batch=1 << 12),
                dict(light_samples=0, brdf_samples=2), dict(light_samples=2, brdf_samples=0)):
        o = get_method("oracle")(**cfg, seed=7)
        o.precompute(scene)
        ref = o.render_reference(frame, gb)
        last = o._last
        monkeypatch.setattr(on, "pretrace", counting)
        calls[0] = 0
        img = o.render(frame, gb)
        assert calls[0] > 0, "the C loops did not run"
        assert o._last == last, cfg
        scale = ref.abs().max().item()
        assert scale > 0
        assert (img - ref).abs().max().item() <= 1e-4 * scale, cfg
        if mats == "library":  # the compiled path (compilations: one material set is enough)
            monkeypatch.setattr(on, "supports", lambda m: False)
            calls[0] = 0
            comp = o.render(frame, gb)
            assert calls[0] == 0 and o._last == last, cfg
            assert (img - comp).abs().max().item() <= 1e-4 * scale, cfg
        monkeypatch.undo()
        monkeypatch.setenv("PRTBENCH_COMPILE", "1")


def test_oracle_native_trace_direct_equals_gathered(monkeypatch):
    """`native_rays.trace` on Mitsuba's tracer hands the component planes to ``ray_test`` with ``live`` as
    its active mask (chunks of the tracer's ``chunk_rays``, here small so that a frame takes several):
    the same blocked flags, live ray for live ray, as the live rays gathered and traced by ``occluded``
    (the fallback, forced by an instance-level ``occluded``), and the same image and live count."""
    import methods.oracle as oracle_mod
    import methods.oracle.native_rays as on

    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    monkeypatch.setattr(oracle_mod, "OWN_TRACER", False)  # Mitsuba's tracer, not the oracle's own (session 34)
    if not on.available():
        pytest.skip("no C compiler: the C loops do not run")
    scene = get_scene("chess", "test")
    frame = make_sequence(scene, "VBL", n_frames=2, seed=0)[1]
    gb = make_gbuffer(scene, frame, 1)
    o = get_method("oracle")(light_samples=3, brdf_samples=2, seed=11)
    o.precompute(scene)
    o.render(frame, gb)  # builds the tracer
    vis = o._vis[1]
    if not on._direct(vis):
        pytest.skip(f"the tracer is {vis.backend}: no direct hand-off to Mitsuba")
    monkeypatch.setattr(vis, "chunk_rays", 1000)
    seen, real = [], on.trace

    def keep(vis_, live, org, dirs, blocked):
        m = real(vis_, live, org, dirs, blocked)
        seen.append((on._direct(vis_), live.clone(), org.clone(), dirs.clone(), blocked.clone(), m))
        return m

    monkeypatch.setattr(on, "trace", keep)
    img = o.render(frame, gb)
    last = o._last
    real_occluded = vis.occluded
    monkeypatch.setattr(vis, "occluded", lambda *a, **k: real_occluded(*a, **k))  # the gathering fallback
    img2 = o.render(frame, gb)
    assert [s[0] for s in seen] == [True, False]
    (_, live, org, dirs, b1, m1), (_, live2, org2, dirs2, b2, m2) = seen
    assert torch.equal(live, live2) and torch.equal(org, org2) and torch.equal(dirs, dirs2)
    assert m1 == m2 == int(live.sum()) > live.numel() // 2
    assert int(live.sum()) > 3 * vis.chunk_rays
    assert torch.equal(b1 & live, b2) and bool(b2.any()) and bool((live & ~b2).any())
    assert torch.equal(img, img2) and o._last == last


def test_oracle_work_arrays_reused_across_frames():
    """The work arrays (`Oracle._work`) kept between frames change no image: a frame rendered after
    frames of another G-buffer size equals the same frame rendered by a fresh oracle (three regions,
    batches smaller than a region); ``memory()`` reports them."""
    scene = get_scene("chess", "test")
    frames = make_sequence(scene, "VBL", n_frames=3, seed=0)
    gbs = [make_gbuffer(scene, frames[0], 1), make_gbuffer(scene, frames[1], 2), make_gbuffer(scene, frames[2], 1)]
    cfg = dict(light_samples=3, brdf_samples=2, seed=2, max_rays_per_batch=1 << 12)
    a = get_method("oracle")(**cfg)
    a.precompute(scene)
    for f, g in zip(frames, gbs):
        a.render(f, g)
    assert sum(a.memory().values()) > 0
    kept = {k: v.data_ptr() for k, v in a._scratch.items()}
    again = a.render(frames[0], gbs[0])  # the size of the last frame's G-buffer: its arrays reused
    assert {k: v.data_ptr() for k, v in a._scratch.items()} == kept
    b = get_method("oracle")(**cfg)
    b.precompute(scene)
    assert torch.equal(again, b.render(frames[0], gbs[0]))


def test_oracle_c_generator_equals_torch_rand(monkeypatch):
    """`native_rays.uniform` (the C generator, from and back to the torch generator's state) = ``torch.rand``
    into the same arrays in turn: the same numbers bit for bit, across twists of the state (624 words)
    and from a state part-way through one, and the generator left in the same state (later torch draws
    equal)."""
    import methods.oracle.native_rays as on

    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    if not on.available():
        pytest.skip("no C compiler: the C loops do not run")
    for seed, skip, shapes in ((0, 0, [(5, 4, 2), (700, 3, 2), (1, 1, 2)]), (17, 611, [(1000, 4, 2), (20000,)]),
                               (3, 623, [(1,), (624,), (625,), (3, 2)])):
        g, h = torch.Generator().manual_seed(seed), torch.Generator().manual_seed(seed)
        torch.rand(skip, generator=g), torch.rand(skip, generator=h)
        outs = [torch.empty(s) for s in shapes]
        assert on.uniform(g, outs)
        for x, s in zip(outs, shapes):
            assert torch.equal(x, torch.rand(s, generator=h)), (seed, s)
        assert torch.equal(g.get_state(), h.get_state())
        assert torch.equal(torch.rand(50, generator=g), torch.rand(50, generator=h))


@pytest.mark.parametrize("env_name", ["sky_sun", "studio", "window", "bench"])
def test_oracle_native_light_cells_equal_count_le(env_name, monkeypatch):
    """The C loops' env-map cell search (`native_rays.light_cells`: the guide table's buckets in one pass,
    their prefetched bisection steps in the next, count_le for the buckets wider than 15 cells) = the
    eager search ``scenes.envmap.count_le`` on the float32 u₀ the oracle draws, at the adversarial ones
    too: next to every cdf entry (both float32 neighbours), on and next to every bucket edge b / G, 0,
    the largest float below 1, 1, and outside [0, 1]; on maps whose buckets span 0 to hundreds of cells."""
    import methods.oracle.native_rays as on
    from methods.core.envguide import guide_table
    from scenes.envmap import count_le

    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    if not on.available():
        pytest.skip("no C compiler: the C loops do not run")
    env = procedural("sky_sun" if env_name == "bench" else env_name, height=256 if env_name == "bench" else 64)
    cdf, p, _ = env._tables()
    guide = guide_table(cdf)
    widths = guide[1:] - guide[:-1]
    assert int(widths.max()) >= 16 and bool(((widths >= 8) & (widths < 16)).any())  # both searches run
    G = guide.shape[0] - 1
    near = cdf.float()
    edges = torch.arange(G + 1, dtype=torch.float32) / G
    u = torch.cat([near, torch.nextafter(near, torch.zeros(1)), torch.nextafter(near, torch.ones(1)),
                   edges, torch.nextafter(edges, torch.zeros(1)), torch.nextafter(edges, torch.ones(1)),
                   torch.rand(50_000, generator=torch.Generator().manual_seed(3)),
                   torch.tensor([0.0, 1.0 - 2.0 ** -24, 1.0, -0.5, 1.5])])
    k = on.light_cells(u, cdf, p.reshape(-1))
    want = count_le(cdf, u.double())
    assert torch.equal(k.long(), want), int((k.long() != want).sum())


def test_oracle_native_integer_powers(monkeypatch):
    """The C loops' powers of integer exponents (`native_rays.int_pow`, the Phong / Blinn-Phong lobes' for
    s in [0, 127], in place of powf) = x^e correctly rounded to float32 (float64 ``torch.pow`` of the
    float32 x, rounded; exact to ~2^-46 for these x and e, far below float32's half ulp) for every e in
    [0, 127] on cosines over [0, 1] (dense near 1, where the lobes live), and powf's values at
    ±0, 1, NaN, inf: the same values but for one in 10^5 at most, and none more than an ulp away."""
    import methods.oracle.native_rays as on

    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    if not on.available():
        pytest.skip("no C compiler: the C loops do not run")
    g = torch.Generator().manual_seed(11)
    x = torch.cat([torch.rand(20_000, generator=g), 1 - torch.rand(20_000, generator=g) ** 4,
                   torch.linspace(0, 1, 4097)]).float()
    off, total = 0, 0
    for e in range(128):
        got = on.int_pow(x, e)
        want = torch.pow(x.double(), e).float()
        ulp = (got.view(torch.int32).long() - want.view(torch.int32).long()).abs()
        assert int(ulp.max()) <= 1, (e, int(ulp.max()))
        off += int((ulp > 0).sum())
        total += x.numel()
        sp = torch.tensor([0.0, -0.0, 1.0, float("nan"), float("inf")])
        assert torch.equal(on.int_pow(sp, e).isnan(), torch.pow(sp, e).isnan())
        ok = ~torch.pow(sp, e).isnan()
        assert torch.equal(on.int_pow(sp, e)[ok], torch.pow(sp, e)[ok]), e
    assert off <= total * 1e-5, (off, total)


@pytest.mark.parametrize("mats", ["library", "ward+lambert", "ct+blinn", "spec-only+no-spec"])
def test_oracle_native_avx512_build_equals_avx2(mats, monkeypatch):
    """On an AVX-512 host `pretrace` runs the AVX-512 build of the C loops (`native_rays._ray_lib`, session
    33) = the AVX2 build (`native_rays._lib`, the build the other C-loop tests compared with the eager
    estimator until then) on the same arguments, every ray: the same live rays, contributions, origins and
    directions to float32 round-off of the same operations (libmvec's vector variants of another width: a
    few ulps, through the lobes' powers); on every BRDF family with a C body, a VB frame's materials
    (non-integer Phong exponents: powf) and both MIS strategies."""
    import methods.oracle.native_rays as on
    from methods.core import native

    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    if not on.available():
        pytest.skip("no C compiler: the C loops do not run")
    if native.cpu_capability() != "AVX512":
        pytest.skip("not an AVX-512 host: pretrace runs the AVX2 build")
    fast, ref = on._ray_lib(), on._lib()
    assert fast is not None and fast is not ref
    scene, frame = _materials_frame(mats, "VB")
    gb = make_gbuffer(scene, frame, 2)
    calls, real = [], on.pretrace

    def keep(mat, *a):
        calls.append((mat, a))
        return real(mat, *a)

    monkeypatch.setattr(on, "pretrace", keep)
    o = get_method("oracle")(light_samples=3, brdf_samples=2, seed=13)
    o.precompute(scene)
    o.render(frame, gb)
    monkeypatch.undo()
    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    assert calls and len({m.kind for m, _ in calls}) == len({m.kind for m in frame.materials.values()})
    for mat, a in calls:
        outs = {}
        for name, lib in (("fast", fast), ("ref", ref)):
            out = tuple(torch.full_like(x, float("nan")) if x.is_floating_point() else torch.zeros_like(x)
                        for x in a[-1])
            monkeypatch.setattr(on, "_ray_lib", lambda lib=lib: lib)
            on.pretrace(mat, *a[:-1], out)
            outs[name] = out
        monkeypatch.undo()
        (c1, l1, o1, d1), (c2, l2, o2, d2) = outs["fast"], outs["ref"]
        assert torch.equal(l1, l2), mat.kind
        assert int(l1.sum()) > 0
        for x, y in ((c1, c2), (o1, o2), (d1, d2)):
            assert not x.isnan().any()
            assert (x - y).abs().max().item() <= 1e-5 * y.abs().max().item(), mat.kind


def test_oracle_pose_written_into_the_tracer_equals_a_new_tracer(monkeypatch):
    """A posed frame after another pose (P) writes the new vertex positions into the last tracer's Mitsuba
    scene (`methods.oracle._repose`, session 33) instead of building a new one: the same tracer object
    frame after frame, and every frame's image and counts bit for bit those of an oracle that builds
    the tracer of that pose afresh (the same rays hit the same triangles); the rest pose again after
    poses too. With the oracle's own tracer of posed frames off (`OWN_TRACER`, session 34: Mitsuba's
    tracer is its fallback; ``tests/methods/test_oracle_embree.py``)."""
    import methods.oracle as oracle_mod
    from references.visibility import resolve_backend

    monkeypatch.setattr(oracle_mod, "OWN_TRACER", False)

    if resolve_backend() != "mitsuba":
        pytest.skip("the tracer is embreex: a new one per pose")
    scene = get_scene("creature", "test")
    frames = make_sequence(scene, "P", n_frames=4, seed=0)
    frames = frames + [dataclasses.replace(frames[0], pose=None, index=7)]
    assert len({repr(f.pose) for f in frames}) == len(frames)
    cfg = dict(light_samples=2, brdf_samples=2, seed=3)
    a = get_method("oracle")(**cfg)
    a.precompute(scene)
    tracers = []
    for f in frames:
        gb = make_gbuffer(scene, f, 1)
        img = a.render(f, gb)
        tracers.append(a._vis[1])
        b = get_method("oracle")(**cfg)
        b.precompute(scene)
        want = b.render(f, gb)
        assert b._vis[1] is not a._vis[1]
        assert torch.equal(img, want), f.index
        assert a._last == b._last, f.index
        assert bool((a._vis[1].V == b._vis[1].V).all()) and a._vis[1].scale == b._vis[1].scale
    assert all(t is tracers[0] for t in tracers)
