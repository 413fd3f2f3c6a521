"""Direct-lighting wavelet transport and the BRDF-basis plumbing of the PTT method
(Sun 2007 §3.1, §3.3 "Direct Lighting", §4.3)."""
from __future__ import annotations

import math

import pytest
import torch

from methods.core import cubemap
from methods.core.frames import to_local
from methods.core.visibility import Visibility, vertex_visibility
from methods.ptt import transport as tp
from scenes.envmap import procedural
from scenes.materials import BlinnPhong, Lambert

# float32 Haar transforms of ~400 texels and gathers: relative round-off well below 1e-5.
F32_REL = 1e-4


@pytest.fixture(scope="module")
def basis():
    return tp.LobeBasis([BlinnPhong(kd=0.0, ks=1.0, s=8.0), BlinnPhong(kd=0.0, ks=1.0, s=32.0)])


@pytest.fixture(scope="module")
def factors(basis):
    return tp.factor_basis(basis, n_wi=8, grid=16, table=32)


def test_basis_coordinates_exact_and_least_squares(basis):
    m = BlinnPhong(kd=(0.2, 0.3, 0.4), ks=0.5, s=32.0)
    H = basis.coords(m)
    assert torch.equal(H, torch.tensor([[0.2, 0.3, 0.4], [0.0] * 3, [0.5] * 3], dtype=torch.float64))
    assert torch.equal(basis.coords(Lambert(kd=0.7))[1:], torch.zeros(2, 3, dtype=torch.float64))
    # the least-squares path recovers an exact combination of the basis (a property of the fit)
    assert torch.allclose(basis._fit(m), H, atol=1e-8)
    # a material outside the span is fitted, and the fit reproduces the BRDF better than its
    # nearest single lobe does
    p = BlinnPhong(kd=(0.2, 0.3, 0.4), ks=0.5, s=16.0)
    Hp = basis.coords(p)
    wi = torch.nn.functional.normalize(torch.tensor([[0.3, 0.1, 0.9], [-0.5, 0.2, 0.6], [0.1, -0.7, 0.5]]), dim=-1).double()
    wo = torch.nn.functional.normalize(torch.tensor([[-0.3, -0.1, 0.9], [0.4, 0.0, 0.8], [0.0, 0.6, 0.6]]), dim=-1).double()
    f_true = p.eval(wi, wo)
    f_fit = torch.einsum("np,pc->nc", basis.eval(wi, wo), Hp)
    f_one = torch.einsum("np,pc->nc", basis.eval(wi, wo), basis.coords(BlinnPhong(kd=(0.2, 0.3, 0.4), ks=0.5, s=32.0)))
    assert (f_fit - f_true).norm() < (f_one - f_true).norm()


def test_fit_is_the_rgb_least_squares(basis):
    """`LobeBasis._fit` fits one scalar lobe and scales it by ks (every material is kd/π + ks·lobe):
    the same coordinates as the least squares of the RGB BRDF itself on the same grid and weights."""
    from scenes.materials import CookTorrance, Phong

    dirs, w = tp.disk_grid(basis.fit_res)
    inside = w > 0
    d, w = dirs[inside], w[inside]
    wi, wo = d[None, :, :].expand(d.shape[0], -1, 3), d[:, None, :].expand(-1, d.shape[0], 3)
    wt = (w[None, :] * d[None, :, 2] * w[:, None]).sqrt()
    B = (basis.eval(wi, wo) * wt[..., None]).reshape(-1, basis.n_P)
    for m in (BlinnPhong(kd=(0.2, 0.3, 0.4), ks=(0.5, 0.4, 0.3), s=16.0), Phong(kd=0.1, ks=(0.3, 0.2, 0.1), s=5.0),
              CookTorrance(kd=(0.05, 0.1, 0.0), ks=0.6, m=0.3, F0=0.04), Lambert(kd=(0.3, 0.5, 0.7))):
        f = (m.eval(wi, wo).double() * wt[..., None]).reshape(-1, 3)
        want = torch.linalg.lstsq(B.T @ B, B.T @ f).solution
        torch.testing.assert_close(basis._fit(m), want, rtol=1e-9, atol=1e-10)


def test_shared_factorization_converges_with_rank(basis):
    g = torch.Generator().manual_seed(0)
    wi = torch.randn(4000, 3, generator=g); wi[:, 2] = wi[:, 2].abs(); wi = torch.nn.functional.normalize(wi, dim=-1)
    wo = torch.randn(4000, 3, generator=g); wo[:, 2] = wo[:, 2].abs(); wo = torch.nn.functional.normalize(wo, dim=-1)
    exact = basis.eval(wi, wo)
    errs, caps = [], []
    for K in (2, 4, 8, 16):
        fac = tp.factor_basis(basis, n_wi=K, grid=16, table=32)
        # error of f·cos θi (what shading integrates against the light)
        approx = (fac.W(wo) * fac.Ucos(wi)[..., None, :]).sum(-1)
        fc = exact * wi[:, 2:3]
        err = (approx - fc).square().mean(0).sqrt() / fc.square().mean(0).sqrt()
        errs.append(err)
        caps.append(fac.captured)
    assert all(a < b for a, b in zip(caps, caps[1:]))
    assert all((a[1:] > b[1:]).all() for a, b in zip(errs, errs[1:])), errs
    # Lambert is smooth: at K = 8 on a 16² disk grid f·cos θi is reconstructed to a few % (measured
    # 3.3 %; the residual is the coarse rim cells of the 16² SVD grid and the bilinear tables)
    assert errs[2][0] < 0.05


def test_view_mode_rank_is_a_tucker_truncation(basis):
    """Sun eq. 2–3: with n_wo the view factor W(p, ωo, k) has rank n_wo over ωo (the (P·K) × T²
    table matrix), n_wo = P·K or None is the untruncated factorization, and the BRDF error falls as
    the rank grows (weighted by the same √dω cos^γ the SVD minimises)."""
    full = tp.factor_basis(basis, n_wi=8, grid=16, table=32)
    P, K = full.n_P, full.K
    assert torch.equal(tp.factor_basis(basis, n_wi=8, grid=16, table=32, n_wo=P * K).W_tab, full.W_tab)
    g = torch.Generator().manual_seed(1)
    wo = torch.randn(3000, 3, generator=g, dtype=torch.float64); wo[:, 2] = wo[:, 2].abs()
    wo = torch.nn.functional.normalize(wo, dim=-1)
    ref = full.W(wo)
    errs = []
    for n in (1, 2, 4, 8):
        f = tp.factor_basis(basis, n_wi=8, grid=16, table=32, n_wo=n)
        s = torch.linalg.svdvals(f.W_tab.reshape(P * K, -1).double())
        assert (s[n:] <= 1e-5 * s[0]).all(), (n, s[: n + 2])  # rank n over ωo
        errs.append(float((f.W(wo) - ref).norm() / ref.norm()))
    assert all(a > b for a, b in zip(errs, errs[1:])), errs
    with pytest.raises(ValueError):
        tp.factor_basis(basis, n_wo=0)


def test_direct_incidence_is_the_texel_quadrature(factors):
    """With every coefficient kept, Σ_l C^L_l U^{I0}(l, k) = Σ_texels L̄ U(ω_loc, k)(ω·n)V Ω
    (Parseval for the orthonormal Haar basis) — checked against a direct texel sum, with a
    triangle occluding part of the vertex's sky."""
    V = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0],
                      [-0.5, 0.5, -0.5], [0.8, 0.6, -0.5], [0.0, 0.7, 0.8]], dtype=torch.float32)
    F = torch.tensor([[0, 2, 1], [3, 4, 5]])
    vis = Visibility(V, F)
    pts = torch.tensor([[0.1, 0.0, 0.1]]); nrm = torch.tensor([[0.0, 1.0, 0.0]])
    N = 8
    env = procedural("sky_sun", height=32, seed=0)
    dt = tp.direct_transport(vis, pts, nrm, factors, N=N, n_L=6 * N * N, coarse=2)
    E0 = tp.direct_incidence(dt, tp.env_haar(env, N))[0]  # (K, 3)
    d = cubemap.texel_directions(N).reshape(-1, 3)
    Lbar = cubemap.from_radiance(env.radiance, N, supersample=2, source_res=env.height).reshape(-1, 3)  # as env_haar
    vb = vertex_visibility(vis, pts, nrm, d, below_horizon="hide")[0].float()
    assert 0.05 < 1 - vb[d[:, 1] > 0].mean() < 0.95, "the occluder should block part of the sky"
    loc = to_local(d, nrm.expand_as(d))
    w = vb * cubemap.texel_solid_angles(N).reshape(-1)
    ref = torch.einsum("tk,t,tc->kc", factors.Ucos(loc), w, Lbar)
    assert torch.allclose(E0, ref, rtol=F32_REL, atol=F32_REL * ref.abs().max().item())
    # fewer kept coefficients → an approximation, not the same numbers
    dt16 = tp.direct_transport(vis, pts, nrm, factors, N=N, n_L=16)
    assert not torch.allclose(tp.direct_incidence(dt16, tp.env_haar(env, N))[0], ref, rtol=1e-3)


def test_coarse_block_is_the_piecewise_constant_projection():
    """Σ_{l ∈ block(N, n)} C^L_l C^T_l = Σ_{coarse texels} mean(L)·sum(T): the 6×n×n lighting of
    the bounce PTTs is exactly the top-left Haar block of the fine layout (transport docstring)."""
    g = torch.Generator().manual_seed(1)
    N, n = 16, 4
    L = torch.rand(6, N, N, generator=g, dtype=torch.float64)
    T = torch.randn(6, N, N, generator=g, dtype=torch.float64)
    b = tp.block_index(N, n)
    lhs = (cubemap.haar_forward(L).reshape(-1)[b] * cubemap.haar_forward(T).reshape(-1)[b]).sum()
    k = N // n
    Lc = L.reshape(6, n, k, n, k).mean((2, 4))
    Tc = T.reshape(6, n, k, n, k).sum((2, 4))
    assert torch.allclose(lhs, (Lc * Tc).sum(), rtol=1e-12)
    # and the sub-block of a block is the block of the coarser resolution
    assert torch.equal(b[tp.block_index(n, 2)], tp.block_index(N, 2))


def test_sh_light_matrix_band0_is_the_uniform_vector(factors):
    C = tp.sh_light_matrix(factors, 4)
    Cu = tp.uniform_light_vector(factors)
    assert C.shape == (16, factors.K)
    assert torch.allclose(C[0], Cu * (0.5 / math.sqrt(math.pi)), rtol=1e-5, atol=1e-7)


def test_ray_points_move_junction_vertices_off_the_other_surface():
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 0, 1], [0, 1, 0]])
    F = torch.tensor([[0, 1, 2], [0, 2, 3]])
    P = tp.ray_points(V, F)
    assert P[0, 0] > 0 and P[0, 1] > 0 and P[0, 2] > 0  # moved into both faces' interiors
    assert (P - V).norm(dim=-1).max() < 0.02


def test_bad_inputs_raise():
    with pytest.raises(ValueError):
        tp.block_index(8, 3)
    with pytest.raises(ValueError):
        tp.block_index(8, 16)
    with pytest.raises(ValueError):
        tp.factor_basis(tp.LobeBasis([]), n_wi=0)
    with pytest.raises(ValueError):
        tp.LobeBasis([Lambert(kd=0.5)])  # a lobe needs a specular term
    with pytest.raises(ValueError):
        tp.disk_grid(1)


def test_env_cube_shares_and_pools_the_resampling():
    """`transport.env_cube`: a lighting stage's memo returns the kept cube for a repeated (N, s) and
    pools a half-resolution cube with the same sub-samples from it (``cubemap.pool_means``) — equal
    to its own resampling to float32 round-off; without the shared grid it resamples."""
    env = procedural("sky_sun", height=64, seed=3).rotated(
        torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]]))
    cubes: dict = {}
    c16 = tp.env_cube(env, 16, 2, cubes)  # s raised to 4 (64 rows / 16)
    assert torch.equal(c16, cubemap.from_envmap(env, 16, supersample=2))
    assert tp.env_cube(env, 16, 2, cubes) is c16
    c8 = tp.env_cube(env, 8, 2, cubes)  # s = 8: the 16² cube's sub-samples, pooled
    want = cubemap.from_envmap(env, 8, supersample=2)
    torch.testing.assert_close(c8, want, rtol=F32_REL, atol=1e-6 * float(want.abs().max()))
    c4 = tp.env_cube(env, 4, 8, cubes)  # s = 16 on a 4² face: 64 per side like the 8² cube's → pooled from it
    torch.testing.assert_close(c4, cubemap.from_envmap(env, 4, supersample=8), rtol=F32_REL,
                               atol=1e-6 * float(want.abs().max()))
    other: dict = {}
    tp.env_cube(env, 16, 8, other)  # s = 8 on 16²: 128 per side, not the 8² cube's 64 → resampled
    assert torch.equal(tp.env_cube(env, 8, 2, other), want)


def test_factors_do_not_depend_on_lapacks_basis_of_equal_singular_values(basis, request):
    """An isotropic BRDF's SVD has equal pairs (cos mφ, sin mφ) whose vectors LAPACK returns in a
    basis its round-off picks (another machine's instruction set, another thread count), and the
    transport keeps the n_L largest Haar coefficients of each factor k separately: the factors must
    be a function of the pairs' planes (`methods.core.stable`). Here LAPACK is made to return every
    cluster in a random other basis with random signs; U^{ωi} and W must not move. (Before: PTT's
    bench creature read V RMSE 0.100 on one machine and 0.091 on another.)"""
    ref = tp.factor_basis(basis, n_wi=8, grid=16, table=32, n_wo=6)
    rotated = request.getfixturevalue("lapack_other_basis")  # from here on, LAPACK's other basis
    got = tp.factor_basis(basis, n_wi=8, grid=16, table=32, n_wo=6)
    assert max(rotated) >= 2  # the basis has equal pairs inside the kept factors
    for a, b in ((ref.U_tab, got.U_tab), (ref.W_tab, got.W_tab)):
        assert float((a - b).abs().max()) <= 1e-5 * float(a.abs().max())


def test_coords_rows_are_coords_bit_for_bit():
    """`LobeBasis.coords_rows` (session 40: no unit-lobe material, the projection by
    `GridLobes.project_family`, H = g_d kd + g_s ks in Python floats) gives `coords`' float64 values
    exactly, for perturbed materials of every family `GridLobes` evaluates, the basis lobes themselves
    (exact coordinates), a Cook-Torrance lobe equal to a basis lobe but for F0, and Lambert; None for the
    families it leaves to `coords` and for a basis without the diffuse function."""
    import dataclasses

    import numpy as np

    from scenes.materials import CookTorrance, Phong, TorranceSparrow, Ward
    from scenes.sequences import perturb_material

    mats = [BlinnPhong(kd=(0.7, 0.68, 0.62), ks=0.25, s=60.0), CookTorrance(kd=(0.06, 0.05, 0.05), ks=0.6, m=0.25, F0=0.04),
            Phong(kd=(0.45, 0.3, 0.18), ks=0.1, s=10.0), Lambert(kd=(0.5, 0.55, 0.45))]
    b = tp.scene_basis(mats)
    rng = np.random.default_rng(7)
    checked = 0
    extra = [CookTorrance(kd=(0.1, 0.2, 0.3), ks=0.5, m=0.25, F0=0.5),  # a basis lobe's m, another F0: a fit
             Phong(kd=0.2, ks=(0.3, 0.2, 0.1), s=10.0), BlinnPhong(kd=0.0, ks=0.4, s=61.0)]
    for it in range(40):
        for m in (mats + extra if it == 0 else [perturb_material(x, rng) for x in mats]):
            got = b.coords_rows(m)
            assert got is not None
            assert torch.equal(torch.tensor(got, dtype=torch.float64), b.coords(m)), m
            checked += 1
    assert checked == 7 + 39 * 4
    for f in (Phong, BlinnPhong, CookTorrance):  # the key holds every field of the unit lobe beside kd / ks
        names = {x.name for x in dataclasses.fields(f)} - {"kd", "ks"}
        assert len(tp._lobe_key(f())[1]) == len(names)
    assert b.coords_rows(TorranceSparrow()) is None and b.coords_rows(Ward()) is None
    assert tp.LobeBasis(b.lobes, diffuse=False).coords_rows(mats[0]) is None
