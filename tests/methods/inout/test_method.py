"""InOut renderer (Mahajan 2008 eq. 2–4): config validation, factorization identities."""
from __future__ import annotations

import pytest
import torch

from methods.inout import transport as tp
from methods.inout.method import InOut
from scenes.materials import Lambert, Phong

# Bilinear look-up of a 64² hemi-octahedral table of smooth (s = 10) eigenfunctions: ~2 % of max.
LUT_TOL = 0.05


@pytest.mark.parametrize("cfg", [dict(terms=0), dict(cube_res=12), dict(n_coeffs=0), dict(budget="row"), dict(brdf_res=1),
                                 dict(select="x"), dict(terms={"a": -1}), dict(lut_res=1),
                                 dict(shading="pixel"), dict(shading=None)])
def test_bad_config_raises(cfg):
    with pytest.raises(ValueError):
        InOut(**cfg)


def test_bad_shading_names_the_choices():
    with pytest.raises(ValueError, match=r"shading must be one of \('sample', 'vertex'\), got 'pixel'"):
        InOut(shading="pixel")


def test_lambert_is_rank_one():
    kd = (0.5, 0.4, 0.3)
    fac = tp.factorize(Lambert(kd=kd), 16, 4)
    assert fac.K == 1  # a constant BRDF has rank 1 (terms capped at the numerical rank)
    # ||ρ||² = Σ_c (kd_c/π)² (2π)² = 4 Σ kd_c²
    assert abs(fac.sigma[0].item() ** 2 - 4 * sum(k * k for k in kd)) < 1e-9


def test_nystrom_tables_reproduce_grid_and_brdf():
    # K = 50 keeps every term with σ_k ≥ 1e-2 σ_1 at s = 10 (more than K(99 %) = 2.5 s = 25). Terms
    # at round-off level (σ ~ 1e-7, K ≳ 100 here) have arbitrary, high-frequency singular vectors
    # whose Nyström extension g = ρᵀh/σ is not a smooth function; they carry no energy, so the
    # method never uses them (K is capped at the numerical rank) and they are not tested here.
    m = Phong(kd=(0.3, 0.2, 0.1), ks=0.5, s=10.0)
    fac = tp.factorize(m, 24, 50)
    g, sh = tp.nystrom_tables(m, fac, 64)
    err = (tp.lut_lookup(g, fac.dirs) - fac.g.T).abs().max()
    assert err < LUT_TOL * fac.g.abs().max()
    x = torch.nn.functional.normalize(torch.randn(200, 3, dtype=torch.float64,
                                                  generator=torch.Generator().manual_seed(0)), dim=-1)
    x[:, 2] = x[:, 2].abs() + 0.2
    x = torch.nn.functional.normalize(x, dim=-1)
    wi, wo = x[:100], x[100:]
    rec = (tp.lut_lookup(sh, wo).view(100, fac.K, 3) * tp.lut_lookup(g, wi)[..., None]).sum(1)
    true = m.eval(wi, wo)
    assert ((rec - true).norm() / true.norm()).item() < 0.1


# -- rendered error against Mitsuba (Mahajan 2008 Fig. 3B/C, Fig. 6: blur until K reaches the rule) --

# Regression pin for sphere_plane (test size, Phong s = 40 sphere, K = 2.5 s = 100, n_coeffs = 256)
# against Mitsuba's 256-spp direct reference: measured 0.1033 (reference noise floor 0.051, mean
# radiance 0.893; the 64+64-sample oracle scores 0.103 on the same pixels). Both sides are
# deterministic (seeded reference, deterministic method), so 10 % headroom flags real regressions.
# Moved from 0.1156 (0.1132 on the tree before the change) when the per-vertex coefficient budget
# became the default (`budget="vertex"`, transport docstring item 4; "term" still measures 0.1132),
# and from 0.1067 when the default n_coeffs went 128 → 256 (same docstring item).
INOUT_RMSE_PIN = 0.1033
PIN_HEADROOM = 1.10


@pytest.fixture(scope="module")
def sphere_plane_direct():
    from references.gbuffer import make_gbuffer
    from references.render import render_reference
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    scene = get_scene("sphere_plane", "test")
    frame = make_sequence(scene, "V", n_frames=1, seed=0)[0]
    gb = make_gbuffer(scene, frame, 2)
    ref = render_reference(scene, frame, bounces=0, spp=256, seed=0)
    return scene, frame, gb, ref, gb.coverage & ref.coverage


def test_error_falls_with_K_and_rule_matches_reference(sphere_plane_direct):
    from references.metrics import rmse

    scene, frame, gb, ref, mask = sphere_plane_direct
    errs = {}
    for K in (1, 4, 16, None):  # None = the paper's rule (2.5 s on the hemisphere)
        m = InOut(terms=K) if K else InOut()
        m.precompute(scene)
        errs[K] = rmse(m.render(frame, gb), ref.image, mask)
    assert errs[1] > errs[4] > errs[16] > errs[None], errs  # Fig. 6: K = 4, 12 blur; K = 75+ matches
    assert errs[None] <= INOUT_RMSE_PIN * PIN_HEADROOM, errs
    assert errs[None] >= ref.noise_floor  # cannot beat the reference's own noise


def test_vertex_budget_beats_per_term_budget_at_equal_bytes(sphere_plane_direct):
    """Transport docstring item 4: keeping each vertex's n·K largest σ_k-weighted coefficients over
    all its terms approximates the all-coefficient render better than n per (vertex, k), with
    exactly the same number of stored coefficients where K ≥ MIN_BUDGET_TERMS (the glossy sphere,
    K = 100; the Lambert plane, K = 1, gets the floor's n·4 and is left out of the comparison).
    Measured (test size, K = 100, n = 128): relative difference to the all-coefficient image 0.036
    ("term") vs 0.024 ("vertex"); at bench size the per-term budget left 0.6-1.2 % negative pixels
    on the sphere."""
    from methods.inout.transport import MIN_BUDGET_TERMS

    scene, frame, gb, ref, mask = sphere_plane_direct
    imgs, nnz = {}, {}
    for budget, n in (("term", 128), ("vertex", 128), ("vertex", None)):
        m = InOut(budget=budget, n_coeffs=n)
        m.precompute(scene)
        imgs[budget, n] = m.render(frame, gb)
        nnz[budget, n] = {r.name: int(r.T.values().numel()) for r in m.regions}
        if n is not None:  # n·K per vertex ("term"), n·max(K, floor) ("vertex")
            for r in m.regions:
                per_vertex = r.K * n if budget == "term" else min(max(r.K, MIN_BUDGET_TERMS) * n,
                                                                   r.K * 6 * m.config["cube_res"] ** 2)
                assert nnz[budget, n][r.name] == r.verts.numel() * per_vertex
    glossy = [r.name for r in m.regions if r.K >= MIN_BUDGET_TERMS]
    assert glossy and all(nnz["term", 128][g] == nnz["vertex", 128][g] for g in glossy)
    # pixels whose every sub-sample lies on a glossy region
    gi = torch.tensor([scene.regions.index(g) for g in glossy])
    on = torch.isin(gb.region, gi).reshape(gb.height, gb.width, -1).all(-1)
    mask = mask & on
    assert int(mask.sum()) > 100
    full = imgs["vertex", None][mask]

    def rel(img):
        return float((img[mask] - full).norm() / full.norm())

    e_term, e_vertex = rel(imgs["term", 128]), rel(imgs["vertex", 128])
    assert e_vertex < 0.8 * e_term, (e_term, e_vertex)
    # Fewer negative values, not none. Phong's singular values come in equal groups (one per SH
    # band, Mahajan Fig. 2), so the SVD's basis inside a group is arbitrary and differs between
    # machines (MKL's AVX2 vs AVX-512 paths); the kept Haar coefficients follow it. Measured: on an
    # AVX-512 host "vertex" leaves 4 negative channel values of 3,264 (min -0.024), "term" 18
    # (min -0.022); CI's hosts until 2026-12-04 had none for "vertex" (the assertion was "none").
    # Neither budget guarantees a non-negative image: it is a truncated signed expansion.
    n_neg = {b: int((imgs[b, 128][mask] < -1e-4).sum()) for b in ("term", "vertex")}
    assert n_neg["vertex"] <= n_neg["term"] // 2, n_neg


def test_factors_do_not_depend_on_lapacks_basis_of_equal_singular_values(request):
    """An isotropic BRDF's equal singular-value pairs come back from LAPACK in a basis its round-off
    picks (machine, threads); the per-term transport truncation depends on the individual factors,
    so `factorize` must return a function of the pairs' planes (`methods.core.stable`). LAPACK is made
    to return every cluster in a random other basis; g and h must not move."""
    m = Phong(kd=0.1, ks=0.6, s=20.0)
    ref = tp.factorize(m, 16, 12)
    sizes = request.getfixturevalue("lapack_other_basis")  # from here on, LAPACK's other basis
    got = tp.factorize(m, 16, 12)
    assert max(sizes) >= 2
    for a, b in ((ref.g, got.g), (ref.h, got.h)):
        assert float((a - b).abs().max()) <= 1e-9 * float(a.abs().max())
