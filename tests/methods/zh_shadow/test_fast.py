"""The fast run-time path (`methods.zh_shadow.runtime`, `ZHShadow.render`) against the slow reference
path (`ZHShadow._render_reference`, §4.3 step by step), its building blocks against closed forms, and
the cost model (`ZHShadow.frame_cost`) against a hand count."""
from __future__ import annotations

import math

import pytest
import torch

from methods.base import GBUFFER_BYTES_PER_SAMPLE
from methods.core.sampling import gauss_legendre_sphere
from methods.core.sh import sh_eval
from methods.zh_shadow import ZHShadow
from methods.zh_shadow import runtime as rt
from methods.zh_shadow.method import shade

# Fast vs reference render: both float32, the same quantity summed in a different order (SH product
# tables vs per-point rotations); measured ≤ 1e-6 absolute on images whose maximum is ~2.
RENDER_TOL = 1e-5
# The library scenes zh_shadow renders (Lambert / Phong only; chess and dragon have other BRDFs).
SCENES = ("sphere_plane", "alcove", "shadow_detail", "creature", "bunny", "character")
ARTICULATED = ("creature", "character")
# A small precompute: the fast/reference agreement does not depend on the fit quality.
SMALL = dict(train_poses=4, n_dirs=64, fit_iters=0)


@pytest.fixture(scope="module")
def small_model():
    from scenes.library import get_scene

    built = {}

    def get(name: str):
        if name not in built:
            sc = get_scene(name, "test")
            m = ZHShadow(**SMALL)
            m.precompute(sc)
            built[name] = m
        return built[name]

    return get


def _check_sequence(m, kind: str, n_frames: int = 2, seed: int = 3):
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    for fr in make_sequence(m.scene, kind, n_frames, seed=seed):   # frame 1 exercises the caches
        gb = make_gbuffer(m.scene, fr, 2)
        fast, ref = m.render(fr, gb), m._render_reference(fr, gb)
        assert ref.abs().max() > 0.05, "degenerate test image"
        err = (fast - ref).abs().max().item()
        assert err <= RENDER_TOL, f"{m.scene.name} {kind} frame {fr.index} {m.config['shading']}: {err}"


@pytest.mark.parametrize("name", SCENES)
def test_fast_equals_reference(small_model, name):
    """V and L frames (P frames too on the articulated scenes), sample shading, default config."""
    m = small_model(name)
    kinds = ("V", "L", "P") if name in ARTICULATED else ("V", "L")
    for kind in kinds:
        _check_sequence(m, kind)


def test_fast_equals_reference_variants(small_model):
    """Vertex shading, a new probe (E: the cached lighting must follow), material changes (VB:
    new exponents), a window and clamp off — on the creature."""
    m = small_model("creature")
    _check_sequence(m.with_render_config(shading="vertex"), "P")
    _check_sequence(m, "E", n_frames=3)
    _check_sequence(m, "VB")
    _check_sequence(m.with_render_config(window="hanning", clamp=False), "VL")


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


def test_frame_cost_hand_count():
    """Bytes and flops of every frame kind on a tiny static scene, counted by hand (order 4,
    2 lobes: Σ(2l+1)² = 84 rotation entries, 44 non-zeros of M^α, 16 SH coefficients)."""
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene

    sc = get_scene("sphere_plane", "test")
    m = ZHShadow(**SMALL)
    m.precompute(sc)
    assert m.frame_cost("V", 1000) is not None
    fr = sc.default_frame()
    gb = make_gbuffer(sc, fr, 1)
    m.render(fr, gb)
    P = gb.num_samples
    Q = int(gb.hit.sum())                                                    # covered samples
    Qs = int((gb.region[gb.hit] == sc.regions.index("sphere")).sum())        # the Phong sphere
    g = sc.geometry()
    N, nF = g.num_vertices, g.F.shape[0]
    J1 = 1                                                                   # static: the bias row
    H, W = sc.envmap.data.shape[:2]
    gbuf = P * (GBUFFER_BYTES_PER_SAMPLE + 8) + P * 12                     # + region, + output
    fixed = nF * 3 * 8 + 2 * 7 * 4 + 2 * 44 * 4 + 16 * 3 * 4                # F, BRDFs, M¹ + M^s, lighting
    vis = N * 15 * 4                                                         # min(16, 6·2 + 3) floats
    diff = 6 * 84 + 6 * 16 + 2 * 44                                           # rotate l, dot, M¹ v
    spec = 6 * 84 + 6 * 16 + 2 * 84 + 2 * 44 + 9                              # + rotate v, R
    per = Q * (diff + 5 + 12 + 6 * 16) + Qs * spec                            # + n·ωo, kd/ks, interpolation
    c = m.frame_cost("V", P)
    assert (c.bytes, c.flops) == (gbuf + fixed + vis, per)
    c = m.frame_cost("VBL", P)
    assert (c.bytes, c.flops) == (gbuf + fixed + vis, per + 6 * 84)
    c = m.frame_cost("P", P)                                                 # the model instead of the cache
    pose = N * (2 * J1 * 12 + 2 * (25 + 3 * 16))
    assert (c.bytes, c.flops) == (gbuf + fixed + (J1 * N * 12 + N * 3) * 4, per + pose)
    c = m.frame_cost("L", P)                                                 # t = M v reused: rotation + dot
    lo = Q * (6 * 84 + 6 * 16 + 5 + 12) + Qs * (6 * 84 + 6 * 16)
    assert (c.bytes, c.flops) == (gbuf + fixed + vis + (Q + Qs) * 16 * 4, lo + 6 * 84)
    c = m.frame_cost("E", P)
    proj = 2 * H * W * 3 * 7 + 2 * H * 16 * 3
    assert (c.bytes, c.flops) == (gbuf + fixed + vis + (Q + Qs) * 16 * 4 + H * W * 3 * 4, lo + 6 * 84 + proj)
    big = m.frame_cost("V", 4 * P)                                           # no render on that size: all covered
    assert big.flops == 4 * P * (diff + 5 + 12 + 6 * 16 + spec)
    mv = m.with_render_config(shading="vertex")
    mv.render(fr, gb)
    c = mv.frame_cost("V", P)
    Ns = int((g.vertex_region == sc.regions.index("sphere")).sum())
    assert c.bytes == P * GBUFFER_BYTES_PER_SAMPLE + P * 12 + fixed + vis + N * 6 * 4
    assert c.flops == N * (diff + 5 + 12) + Ns * spec + P * 18
    assert math.isfinite(c.bytes) and c.flops > 0
