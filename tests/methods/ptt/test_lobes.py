"""Tests for methods.ptt.lobes (Sun 2007 §4.1 specular lobe separation)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.optimize import nnls

from methods.core import tensors as T
from methods.core.sampling import fibonacci_sphere
from methods.ptt.brdf_space import BlinnPhongSpace
from methods.ptt.brdf_tensor import DiskGrid, brdf_tensor, mirror_dirs, separate_tensor
from methods.ptt.lobes import (LOBE_DEGREES, fit_lobe_weights, gaussian_lobe, gaussian_lobe_mass,
                               lobe_basis, lobe_sigma, lobe_values, separate_lobes)

# Fibonacci quadrature with 400k points (spacing ≈ 0.32°) of lobes with σ >= 2.3°: error ~1e-5.
MASS_TOL = 1e-4
# Exact planted lobes, float64, 4×4 normal equations with condition number <= ~1e6 on this grid.
RECOVERY_RTOL = 1e-6
# KKT residuals of the NNLS optimum relative to ‖Bᵀf‖ (float64 pinv solves).
KKT_TOL = 1e-8
# Sun 2007 Fig. 5/6: separation must cut the tensor error of shiny Blinn–Phong lobes by a lot;
# measured ratio ≈ 0.077 on this setting, we require < 0.25 (a 4× reduction).
SEPARATION_GAIN = 0.25


def test_sigma_three_sigma_rule():
    assert lobe_sigma(21.0) == pytest.approx(math.radians(7.0))
    with pytest.raises(ValueError):
        lobe_sigma(0.0)


@pytest.mark.parametrize("k", [7.0, 14.0, 21.0])
def test_gaussian_lobes_have_unit_mass(k):
    d, w = fibonacci_sphere(400_000, dtype=torch.float64)
    c = torch.tensor([0.3, -0.2, 0.9], dtype=torch.float64)
    c = c / c.norm()
    mass = float((gaussian_lobe(d @ c, lobe_sigma(k)) * w).sum())
    assert mass == pytest.approx(1.0, abs=MASS_TOL)
    # small-σ limit of Z(σ) = 2πσ²(1 − σ²/3 + …)
    s = lobe_sigma(k)
    assert gaussian_lobe_mass(s) == pytest.approx(2 * math.pi * s * s * (1 - s * s / 3), rel=s ** 4)


@pytest.fixture(scope="module")
def basis():
    """A fine grid (Δ ≈ 2.4°) and 40 view directions: the 7° lobe (σ = 2.3°) spans several nodes."""
    grid = DiskGrid(48)
    sel = torch.arange(0, grid.N, grid.N // 40)[:40]
    R = mirror_dirs(grid)[sel]
    B = lobe_basis(grid.dirs, R, degrees=LOBE_DEGREES, delta=grid.delta(R))
    return grid, B


def test_delta_lobe_has_unit_discrete_mass(basis):
    grid, B = basis
    torch.testing.assert_close((B[:, 0] * grid.solid_angle).sum(-1), torch.ones(B.shape[0], dtype=torch.float64))


def test_fit_recovers_planted_weights(basis):
    grid, B = basis
    g = torch.Generator().manual_seed(0)
    a = torch.rand(3, B.shape[0], 4, generator=g, dtype=torch.float64)
    a[a < 0.3] = 0.0                                   # some lobes absent
    f = lobe_values(a, B)
    got = fit_lobe_weights(f, B)
    torch.testing.assert_close(got, a, rtol=RECOVERY_RTOL, atol=RECOVERY_RTOL * float(a.max()))
    f_r, a2 = separate_lobes(f, B)
    assert float(f_r.abs().max()) <= RECOVERY_RTOL * float(f.abs().max())


def test_fit_is_the_nnls_optimum(basis):
    grid, B = basis
    g = torch.Generator().manual_seed(1)
    # a smooth positive background plus lobes of mixed sign: the optimum has zero weights
    f = lobe_values(torch.randn(1, B.shape[0], 4, generator=g, dtype=torch.float64), B)[0]
    f = f + 0.5 * grid.dirs[:, 2][None, :]
    a = fit_lobe_weights(f, B)
    assert (a >= 0).all()
    for o in range(0, B.shape[0], 7):                  # slow reference: scipy's active-set NNLS
        ref, _ = nnls(B[o].T.numpy(), f[o].numpy())
        np.testing.assert_allclose(a[o].numpy(), ref, rtol=1e-6, atol=1e-9 * np.abs(ref).max())
    # KKT: gradient ≥ 0 on zero weights and ≈ 0 on active ones
    grad = torch.einsum("okj,oj->ok", B, lobe_values(a, B) - f)
    scale = torch.einsum("okj,oj->ok", B, f).abs().amax(-1, keepdim=True)
    assert (grad >= -KKT_TOL * scale).all()
    assert (grad.abs()[a > 0] <= KKT_TOL * scale.expand_as(grad)[a > 0]).all()


def test_missing_delta_raises():
    with pytest.raises(ValueError, match="delta"):
        lobe_basis(torch.eye(3, dtype=torch.float64), torch.eye(3, dtype=torch.float64))


def test_separation_lowers_tensor_error_of_shiny_lobes():
    space = BlinnPhongSpace(shininess=(100.0, 125.0, 150.0, 175.0, 200.0))
    grid = DiskGrid(16)
    F = brdf_tensor(space, grid)
    F_r, a, B = separate_tensor(F, grid)
    assert (a >= 0).all() and a.shape == (5, grid.N, 4)
    torch.testing.assert_close(F_r + lobe_values(a, B), F)
    ranks = (2, 8, 8)
    err = lambda X: float((X - T.tucker_reconstruct(*T.hosvd(X, ranks))).square().sum())  # noqa: E731
    e_plain, e_sep = err(F), err(F_r)
    assert e_sep < SEPARATION_GAIN * e_plain, (e_sep, e_plain)
    # the residual is also smaller in plain energy: the high-frequency peak went into the lobes
    assert float(F_r.square().sum()) < 0.1 * float(F.square().sum())
