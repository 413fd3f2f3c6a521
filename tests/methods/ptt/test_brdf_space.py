"""Tests for methods.ptt.brdf_space (Sun 2007 §4.2 BRDF navigation)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from methods.ptt.brdf_space import (BP_SHININESS, CT_F0_RANGE, CT_M_RANGE, BlinnPhongSpace,
                                    CookTorranceSpace, cook_torrance_samples, get_space)
from scenes.materials import BlinnPhong, CookTorrance, Lambert

# float64 barycentric/linear weights: exact up to a few ulps of O(1) numbers.
F64_TOL = 1e-12
# float64 BRDF values up to ~1e3 (sharp CT lobes) combined with <= 3 weights.
BRDF_RTOL = 1e-10


def _dirs(n, seed):
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(n, 3, generator=g, dtype=torch.float64)
    v[:, 2] = v[:, 2].abs() + 0.05
    return v / v.norm(dim=-1, keepdim=True)


@pytest.fixture(scope="module")
def ct():
    return CookTorranceSpace()


@pytest.fixture(scope="module")
def bp():
    return BlinnPhongSpace()


def test_bp_samples_are_integers_1_to_200(bp):
    assert bp.n_h == 200 and bp.shininess == BP_SHININESS
    assert bp.shininess[0] == 1.0 and bp.shininess[-1] == 200.0


def test_bp_interpolation_exact_at_samples(bp):
    W = bp.weights(torch.tensor(BP_SHININESS, dtype=torch.float64))
    torch.testing.assert_close(W, torch.eye(200, dtype=torch.float64), atol=0, rtol=0)
    wi, wo = _dirs(64, 0), _dirs(64, 1)
    for s in (1.0, 37.0, 200.0):
        ref = BlinnPhong(kd=0.0, ks=1.0, s=s).eval(wi, wo)[..., 0]
        torch.testing.assert_close(bp.eval_spec(bp.weights(s), wi, wo), ref, rtol=BRDF_RTOL, atol=0)


def test_bp_interpolation_is_linear_between_samples(bp):
    s = torch.tensor([1.25, 10.5, 199.9], dtype=torch.float64)
    W = bp.weights(s)
    for row, si in zip(W, s.tolist()):
        lo = int(np.floor(si))
        t = si - lo
        assert torch.count_nonzero(row) == 2
        assert abs(float(row[lo - 1]) - (1 - t)) < F64_TOL and abs(float(row[lo]) - t) < F64_TOL
    wi, wo = _dirs(32, 2), _dirs(32, 3)
    mid = bp.eval_spec(bp.weights(10.5), wi, wo)
    ref = 0.5 * (BlinnPhong(kd=0, ks=1, s=10).eval(wi, wo) + BlinnPhong(kd=0, ks=1, s=11).eval(wi, wo))[..., 0]
    torch.testing.assert_close(mid, ref, rtol=BRDF_RTOL, atol=0)


@pytest.mark.parametrize("bad", [0.5, 200.5, float("nan")])
def test_bp_out_of_range_raises(bp, bad):
    with pytest.raises(ValueError, match="shininess"):
        bp.weights(bad)


def test_ct_samples_deterministic_and_in_range():
    P = cook_torrance_samples()
    assert P.shape == (100, 2)
    np.testing.assert_array_equal(P, cook_torrance_samples())
    assert P[:, 0].min() == pytest.approx(CT_F0_RANGE[0]) and P[:, 0].max() == pytest.approx(CT_F0_RANGE[1])
    assert P[:, 1].min() == pytest.approx(CT_M_RANGE[0]) and P[:, 1].max() == pytest.approx(CT_M_RANGE[1])
    assert len(np.unique(P, axis=0)) == 100


def test_delaunay_reproduces_vertices(ct):
    W = ct.weights(ct.points)
    torch.testing.assert_close(W, torch.eye(100, dtype=torch.float64), atol=F64_TOL, rtol=0)


def test_delaunay_weights_linear_inside_triangles(ct):
    rng = np.random.default_rng(0)
    for t in rng.choice(len(ct.tri.simplices), size=10, replace=False):
        V = ct.points[ct.tri.simplices[t]]                        # (3, 2)
        b = rng.dirichlet([1.0, 1.0, 1.0], size=8) * 0.98 + 0.02 / 3  # strictly inside
        Q = b @ V
        W = ct.weights(torch.from_numpy(Q)).numpy()
        # the weights are the barycentric coordinates on the triangle's vertices, nothing else
        np.testing.assert_allclose(W[:, ct.tri.simplices[t]], b, atol=1e-10)
        assert np.count_nonzero(W, axis=1).max() == 3
        # linear precision: Σ w_h p_h = q, and affine in q inside one triangle
        np.testing.assert_allclose(W @ ct.points, Q, atol=1e-12)
        np.testing.assert_allclose(ct.weights(torch.from_numpy(0.3 * Q[0] + 0.7 * Q[1])).numpy(),
                                   0.3 * W[0] + 0.7 * W[1], atol=1e-10)


def test_ct_outside_hull_raises(ct):
    with pytest.raises(ValueError, match="convex hull"):
        ct.weights((0.5, 0.01))


def test_ct_vertex_equals_project_material_with_weights(ct):
    wi, wo = _dirs(64, 4), _dirs(64, 5)
    F0, m = ct.points[17]
    kd, ks = (0.2, 0.3, 0.4), (0.9, 0.5, 0.1)
    got = ct.eval((F0, m), wi, wo, kd=kd, ks=ks)
    ref = CookTorrance(kd=kd, ks=ks, F0=F0, m=m).eval(wi, wo)
    torch.testing.assert_close(got, ref, rtol=BRDF_RTOL, atol=1e-14)


def test_material_round_trip_and_kind_check(ct, bp):
    mat = CookTorrance(kd=0.1, ks=0.7, F0=float(ct.points[3, 0]), m=float(ct.points[3, 1]))
    w, kd, ks = ct.material_weights(mat)
    assert float(w[3]) == pytest.approx(1.0) and kd == (0.1,) * 3 and ks == (0.7,) * 3
    assert bp.point_of(BlinnPhong(s=42.0)) == 42.0
    with pytest.raises(ValueError):
        bp.point_of(Lambert())
    with pytest.raises(ValueError):
        get_space("ward")
