"""Tests for methods/core/sh.py: scipy agreement (Condon–Shortley converted), orthonormality,
fast path = recurrence, projection/reconstruction, lat-long projection."""
import math

import numpy as np
import pytest
import torch
from scipy import special

from methods.core import sh
from methods.core.sampling import gauss_legendre_sphere, latlong_directions

F64 = torch.float64
ROUNDOFF = 1e-12      # float64 evaluation of O(1) polynomials
GRAM_TOL = 1e-11      # exact quadrature (Gauss–Legendre × uniform φ) in float64
LATLONG_TOL = 8e-3    # 65×128 map of an order-4 function: bilinear-interpolation / texel-rule error
                      # is O(h²); measured 5.3e-3 (exact interpolant), 1.7e-3 (hat rule)
ENVMAP_TOL = 5e-5     # 20k spherical-Fibonacci points on a 33×64 bilinear map: QMC error 4.7e-6 measured


def _dirs(n, seed=0):
    g = torch.Generator().manual_seed(seed)
    d = torch.randn(n, 3, generator=g, dtype=F64)
    return d / d.norm(dim=-1, keepdim=True)


def _scipy_real_sh(l, m, d):
    """Our real SH from scipy's complex Y_l^m (which includes (−1)^m): remove the phase."""
    theta = np.arccos(np.clip(d[:, 2], -1, 1))
    phi = np.arctan2(d[:, 1], d[:, 0]) % (2 * np.pi)
    Y = special.sph_harm_y(l, abs(m), theta, phi)
    cs = (-1.0) ** abs(m)
    if m == 0:
        return Y.real
    if m > 0:
        return cs * math.sqrt(2) * Y.real
    return cs * math.sqrt(2) * Y.imag


@pytest.mark.parametrize("fast", [True, False])
def test_matches_scipy_without_condon_shortley(fast):
    order = 6 if fast else 13
    d = _dirs(50)
    ours = sh.sh_eval(d, order, fast=fast).numpy()
    for l in range(order):
        for m in range(-l, l + 1):
            ref = _scipy_real_sh(l, m, d.numpy())
            assert np.abs(ours[:, l * (l + 1) + m] - ref).max() < ROUNDOFF, (l, m)


def test_band1_is_yzx_with_positive_sign():
    d = _dirs(10)
    c = math.sqrt(3 / (4 * math.pi))
    Y = sh.sh_eval(d, 2)
    assert torch.allclose(Y[:, 1:4], c * d[:, [1, 2, 0]], atol=ROUNDOFF)
    assert torch.allclose(Y[:, 0], torch.full((10,), 0.5 / math.sqrt(math.pi), dtype=F64))


@pytest.mark.parametrize("order", [1, 2, 3, 4, 5, 6])
def test_fast_path_equals_recurrence(order):
    d = _dirs(200, seed=order)
    assert torch.allclose(sh.sh_eval(d, order), sh.sh_eval_recurrence(d, order), atol=ROUNDOFF, rtol=0)
    d32 = d.float()
    y32 = sh.sh_eval(d32, order)
    assert y32.dtype == torch.float32 and y32.shape == (200, order * order)


@pytest.mark.parametrize("order", [8, 30])
def test_orthonormal_by_exact_quadrature(order):
    d, w = gauss_legendre_sphere(order + 1, 2 * order + 1, dtype=F64)
    Y = sh.sh_eval(d, order)
    G = Y.T @ (Y * w[:, None])
    assert (G - torch.eye(order * order, dtype=F64)).abs().max() < GRAM_TOL


def test_batch_shapes():
    d = _dirs(24).reshape(2, 3, 4, 3)
    Y = sh.sh_eval(d, 3)
    assert Y.shape == (2, 3, 4, 9)
    assert torch.allclose(Y.reshape(-1, 9), sh.sh_eval(d.reshape(-1, 3), 3))


def test_project_recovers_band_limited_coefficients_and_reconstructs():
    order = 5
    g = torch.Generator().manual_seed(2)
    c = torch.randn(order * order, 3, generator=g, dtype=F64)
    d, w = gauss_legendre_sphere(order + 1, 2 * order + 1, dtype=F64)
    f = sh.reconstruct(c, d)
    assert f.shape == (d.shape[0], 3)
    c2 = sh.project(f, d, w, order)
    assert torch.allclose(c2, c, atol=GRAM_TOL)
    # 1-D values; projecting to a lower order truncates
    c3 = sh.project(f[:, 0], d, w, 3)
    assert c3.shape == (9,) and torch.allclose(c3, c[:9, 0], atol=GRAM_TOL)
    dd = _dirs(7)
    assert torch.allclose(sh.reconstruct(c[:, 1], dd), sh.sh_eval(dd, order) @ c[:, 1])


def _bandlimited_map(c, H, W, to_world=None):
    d = latlong_directions(H, W, dtype=F64)
    if to_world is not None:
        d = d @ to_world.T
    return sh.reconstruct(c, d)  # (H, W, C)


@pytest.mark.parametrize("method", ["exact", "hat", "supersample"])
def test_project_latlong_recovers_coefficients(method):
    order = 4
    c = torch.randn(order * order, 3, generator=torch.Generator().manual_seed(4), dtype=F64)
    img = _bandlimited_map(c, 65, 128)
    c2 = sh.project_latlong(img, order, method=method, supersample=2)
    assert (c2 - c).abs().max() < LATLONG_TOL
    # the texel rule and the interpolant both converge at second order in the map resolution
    e1 = (sh.project_latlong(_bandlimited_map(c, 17, 32), order, method=method) - c).abs().max()
    e2 = (sh.project_latlong(_bandlimited_map(c, 33, 64), order, method=method) - c).abs().max()
    assert e2 < e1 / 3.0


def test_project_latlong_exact_integrates_the_bilinear_interpolant():
    g = torch.Generator().manual_seed(8)
    img = torch.rand(5, 8, 2, generator=g, dtype=F64)
    order = 5
    exact = sh.project_latlong(img, order)
    # midpoint supersampling of the same interpolant converges to it at O(1/k²)
    e4 = (sh.project_latlong(img, order, method="supersample", supersample=4) - exact).abs().max()
    e8 = (sh.project_latlong(img, order, method="supersample", supersample=8) - exact).abs().max()
    assert e8 < e4 / 3.5 and e8 < 1e-2
    # a constant map is exactly the constant function: only y00 survives, for any resolution
    const = sh.project_latlong(torch.full((3, 4, 1), 2.0, dtype=F64), 6)
    assert abs(const[0, 0].item() - 4 * math.sqrt(math.pi)) < ROUNDOFF
    assert const[1:].abs().max() < ROUNDOFF


def test_project_latlong_matches_envmap_radiance():
    """Cross-check of the lat-long convention against scenes.envmap.EnvMap.radiance (world frame)."""
    from scenes.envmap import EnvMap
    from methods.core.sampling import fibonacci_sphere

    order = 4
    c = torch.randn(order * order, 3, generator=torch.Generator().manual_seed(9), dtype=F64)
    c[1:] *= 0.1
    c[0] = 3.0  # keep the map positive (EnvMap rejects negative texels)
    a = 0.9
    Ry = torch.tensor([[math.cos(a), 0, math.sin(a)], [0, 1, 0], [-math.sin(a), 0, math.cos(a)]], dtype=F64)
    Rz = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]], dtype=F64)
    R = (Ry @ Rz).float()
    env = EnvMap(_bandlimited_map(c, 33, 64).float(), R)
    d, w = fibonacci_sphere(20_000, dtype=F64)
    ref = sh.project(env.radiance(d.float()).double(), d, w, order)   # ∫ L̃ y over the sphere
    assert (sh.project_latlong(env, order).double() - ref).abs().max() < ENVMAP_TOL
    # the texel rule (4.5e-3 here) and a missing rotation both fail this tolerance (the test can fail)
    assert (sh.project_latlong(env, order, method="hat").double() - ref).abs().max() > 10 * ENVMAP_TOL
    assert (sh.project_latlong(env.data, order).double() - ref).abs().max() > 10 * ENVMAP_TOL


def test_project_latlong_envmap_like_uses_to_world():
    class FakeEnv:
        pass

    order = 3
    a = 0.7
    Rz = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]], dtype=F64)
    c = torch.randn(order * order, 3, generator=torch.Generator().manual_seed(6), dtype=F64)
    env = FakeEnv()
    env.to_world = Rz
    env.data = _bandlimited_map(c, 65, 128, to_world=Rz)  # texel (local d) shows f(to_world @ d)
    for method in ("exact", "hat"):
        assert (sh.project_latlong(env, order, method=method) - c).abs().max() < LATLONG_TOL
    # without the rotation the result differs (the test can fail)
    assert (sh.project_latlong(env.data, order) - c).abs().max() > 10 * LATLONG_TOL


def test_project_latlong_float32_follows_input():
    img = torch.ones(9, 16, 3)
    for method in ("exact", "hat"):
        c = sh.project_latlong(img, 3, method=method)
        assert c.dtype == torch.float32
        assert abs(c[0, 0].item() - 2 * math.sqrt(math.pi)) < 1e-5  # Σw = 4π exactly; ∫ y00 = 2√π


def test_bad_input_raises():
    with pytest.raises(ValueError):
        sh.sh_eval(torch.zeros(4, 2), 3)
    with pytest.raises(ValueError):
        sh.sh_eval(torch.zeros(4, 3), 0)
    d, w = gauss_legendre_sphere(3, 5)
    with pytest.raises(ValueError):
        sh.project(torch.zeros(d.shape[0] + 1, 3), d, w, 2)
    with pytest.raises(ValueError):
        sh.project(torch.zeros(d.shape[0], 3), d, w[:-1], 2)
    with pytest.raises(ValueError):
        sh.reconstruct(torch.zeros(8, 3), d)
    with pytest.raises(ValueError):
        sh.project_latlong(torch.zeros(1, 8, 3), 2)
    with pytest.raises(ValueError):
        sh.project_latlong(torch.zeros(4, 8, 3), 2, method="nearest")


def test_rotate_sampled_follows_the_device_of_its_input(monkeypatch):
    """`rotate_sampled` takes its fixed directions and pseudo-inverse to the device of c (they are
    built on the CPU): on the meta device (shapes only, standing in for a GPU) it runs and returns
    a tensor there instead of mixing devices; the CPU result is unchanged."""
    from methods.core.sh import rotate_sampled

    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    c = torch.randn(16, 3, dtype=torch.float64)
    R = torch.eye(3, dtype=torch.float64)
    out = rotate_sampled(c.to("meta"), R.to("meta"))
    assert out.device.type == "meta" and out.shape == (16, 3)
    assert (rotate_sampled(c, R) - c).abs().max() <= 1e-12 * c.abs().max()
