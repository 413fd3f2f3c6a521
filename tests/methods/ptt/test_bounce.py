"""One- and two-bounce PTTs against closed forms (Sun 2007 §3.1, §3.3).

Corner furnace: an (almost) infinite Lambert wall x = 0 (albedo ρw, normal +x) standing on an
(almost) infinite Lambert floor y = 0 (albedo ρf, normal +y), a uniform white env map (L = 1).
Every wall point sees the sky over half its hemisphere (the floor blocks the rest) and so does
every floor point (the wall blocks the rest): each surface's direct irradiance is π/2·L and its
direct radiance ρ/2·L, everywhere. A floor probe therefore gets
    direct      B0 = ρf/π · π/2                      = ρf/2
    one bounce  B1 = ρf/π · (ρw/2) · π/2             = ρf ρw/4    (sky → wall → probe)
    two bounces B2 = ρf/π · (ρw/π · ρf/2 · π/2) π/2  = ρf² ρw/8   (sky → floor → wall → probe)
and in all three the incident radiance is piecewise constant, so the uniform-radiance assumption
of T² is exact in irradiance. The basis is built here (Lambert + one Blinn-Phong lobe), so the
test does not depend on the colleague's PCA basis.
"""
from __future__ import annotations


import pytest
import torch

from methods.base import GBuffer
from methods.ptt.bounce import one_bounce_ptt, trace_hemispheres
from methods.ptt.method import PTT
from methods.ptt.transport import LobeBasis
from methods.core.visibility import Visibility
from scenes.camera import Camera
from scenes.envmap import EnvMap
from scenes.materials import BlinnPhong, Lambert
from scenes.mesh import Mesh
from scenes.scene import Scene, Shape

RHO_W, RHO_F = 0.8, 0.6
EXTENT = 400.0  # size of wall and floor; the probe is 1 unit from the wall
# Relative tolerance of each bounce term. Budget: finite extent (the probe's cosine-weighted view
# of the wall is > 99 % below height 100, where the linearly interpolated wall irradiance is
# within ~1.5 % of π/2), hemisphere quadrature of a step (sky|wall) with 256 Fibonacci rays
# (~1 %), order-4 SH truncation of the half-hemisphere step seen through C^{ωi} (~1–2 %), and the
# rank-K factorization of the Lambert basis function (< 0.5 %).
REL_TOL = 0.04


def corner_scene() -> Scene:
    Z, X, H = EXTENT, EXTENT, EXTENT
    # both meshes are fans around a vertex near the probe, so that what the probe sees is
    # interpolated from vertices that see the (almost) infinite configuration, not from the far
    # corners (which see the sky around the edges)
    wv = torch.tensor([[0, 0, 0], [0, 0, -Z], [0, H, -Z], [0, H, Z], [0, 0, Z]], dtype=torch.float32)
    wall = Mesh(wv, torch.tensor([[0, 1, 2], [0, 2, 3], [0, 3, 4]]), torch.tensor([[1.0, 0, 0]] * 5))
    fv = torch.tensor([[1, 0, 0], [0, 0, 0], [0, 0, -Z], [X, 0, -Z], [X, 0, Z], [0, 0, Z]], dtype=torch.float32)
    floor = Mesh(fv, torch.tensor([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5], [0, 5, 1]]),
                 torch.tensor([[0, 1.0, 0]] * 6))
    env = EnvMap(torch.ones(16, 32, 3))
    cam = Camera((5.0, 5.0, 5.0), (0.0, 0.0, 0.0), (0.0, 1.0, 0.0), 40.0, 8, 8)
    mats = {"wall": Lambert(kd=RHO_W), "floor": Lambert(kd=RHO_F)}
    return Scene("corner", [Shape("wall", "wall", wall), Shape("floor", "floor", floor)], ["wall", "floor"],
                 cam, env, mats)


def probe_gbuffer(scene: Scene) -> GBuffer:
    """One G-buffer sample exactly at the probe vertex (global vertex 5: after the wall's 5)."""
    g = scene.geometry()
    pv = 5
    face = int(torch.nonzero((g.F == pv).any(1))[0])
    j = int(torch.nonzero(g.F[face] == pv)[0])
    bary = torch.tensor([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]][j]).view(1, 2)
    n = g.N[pv].view(1, 3)
    return GBuffer(1, 1, 1, torch.ones(1, dtype=torch.bool), torch.tensor([face]), bary, g.V[pv].view(1, 3),
                   n, n.clone(), g.vertex_region[pv].view(1), torch.ones(1, 1, dtype=torch.bool))


@pytest.fixture(scope="module")
def corner():
    scene = corner_scene()
    basis = LobeBasis([BlinnPhong(kd=0.0, ks=1.0, s=8.0)])
    m = PTT(bounces=2, basis=basis, n_wi=8, brdf_grid=16, brdf_table=32, cube_res=8, n_L=384,
            light_res_1=4, light_res_2=2, rays=256)
    m.precompute(scene)
    return scene, m


def test_corner_furnace_bounces_match_closed_form(corner):
    scene, m = corner
    frame = scene.default_frame()
    gb = probe_gbuffer(scene)
    B = [m.with_bounces(b).render(frame, gb)[0, 0] for b in (0, 1, 2)]
    got = [B[0], B[1] - B[0], B[2] - B[1]]
    want = [RHO_F / 2, RHO_F * RHO_W / 4, RHO_F**2 * RHO_W / 8]
    for name, g, w in zip(("direct", "one bounce", "two bounces"), got, want):
        assert torch.allclose(g, torch.full((3,), w), rtol=REL_TOL), f"{name}: {g.tolist()} vs {w:.5f}"


def test_bounce_terms_scale_with_region_brdfs(corner):
    """PTTs are BRDF-independent: changing H at run time rescales each path by its albedos
    (B1 ∝ ρf ρw, B2 ∝ ρf² ρw) without recomputing anything."""
    scene, m = corner
    frame = scene.default_frame()
    gb = probe_gbuffer(scene)
    rw, rf = 0.3, 0.9
    frame2 = type(frame)(envmap=frame.envmap, camera=frame.camera,
                         materials={"wall": Lambert(kd=rw), "floor": Lambert(kd=rf)}, changed=frozenset({"brdf"}))
    b = {k: [m.with_bounces(k).render(f, gb)[0, 0] for f in (frame, frame2)] for k in (0, 1, 2)}
    one = [b[1][i] - b[0][i] for i in (0, 1)]
    two = [b[2][i] - b[1][i] for i in (0, 1)]
    # exact linearity in H (same PTTs): ratios equal the albedo ratios up to float32 round-off
    assert torch.allclose(one[1] / one[0], torch.full((3,), rf * rw / (RHO_F * RHO_W)), rtol=1e-4)
    assert torch.allclose(two[1] / two[0], torch.full((3,), rf**2 * rw / (RHO_F**2 * RHO_W)), rtol=1e-4)


def test_open_plane_has_no_interreflection():
    """A single plane under the sky: every hemisphere ray escapes, so T¹ must be exactly 0."""
    V = torch.tensor([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], dtype=torch.float32)
    F = torch.tensor([[0, 1, 2], [0, 2, 3]])
    N = torch.tensor([[0, 1.0, 0]] * 4)
    vis = Visibility(V, F)
    hits = trace_hemispheres(vis, V, N, 64)
    assert (hits.face < 0).all()
    from methods.ptt.transport import factor_basis

    fac = factor_basis(LobeBasis([]), n_wi=2, grid=8, table=8)
    T1 = one_bounce_ptt(hits, F, N, torch.zeros(2, dtype=torch.long), 1, fac, torch.ones(4, fac.K, 24))
    assert T1.shape == (4, 1, 1, 16, 24) and (T1 == 0).all()


def test_trace_rejects_bad_ray_count():
    V = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 0, 1]], dtype=torch.float32)
    with pytest.raises(ValueError):
        trace_hemispheres(Visibility(V, torch.tensor([[0, 1, 2]])), V, torch.tensor([[0, 1.0, 0]] * 3), 0)
