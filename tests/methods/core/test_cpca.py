"""Tests for methods.core.cpca (Sloan 2003 iterative clustered PCA)."""
from __future__ import annotations

import pytest
import torch

from methods.core.cpca import cpca, reconstruct

# float64 SVDs of O(1)–O(10) data: residuals at the 1e-12 level relative to ‖X‖².
F64_REL = 1e-12


def _affine_subspace_data(K, M, D, n_per, seed):
    g = torch.Generator().manual_seed(seed)
    X, lab = [], []
    for k in range(K):
        mean = 10.0 * torch.randn(D, generator=g, dtype=torch.float64)
        B = torch.linalg.qr(torch.randn(D, M, generator=g, dtype=torch.float64))[0].T  # (M, D)
        w = torch.randn(n_per, M, generator=g, dtype=torch.float64)
        X.append(mean + w @ B)
        lab.append(torch.full((n_per,), k))
    perm = torch.randperm(K * n_per, generator=g)
    return torch.cat(X)[perm], torch.cat(lab)[perm]


def test_recovers_affine_subspaces():
    X, lab = _affine_subspace_data(K=4, M=3, D=12, n_per=60, seed=0)
    r = cpca(X, 4, 3, seed=1)
    total = X.square().sum().item()
    assert r.errors[-1] < F64_REL * total
    # the partition matches the generating labels up to renaming
    for k in range(4):
        assert r.ids[lab == k].unique().numel() == 1
    torch.testing.assert_close(r.reconstruct(), X, atol=1e-9, rtol=0)
    assert r.bases.shape == (4, 3, 12) and r.coeffs.shape == (240, 3) and r.means.shape == (4, 12)
    # orthonormal bases
    torch.testing.assert_close(r.bases @ r.bases.transpose(1, 2), torch.eye(3, dtype=X.dtype).expand(4, 3, 3))


def test_error_non_increasing_and_deterministic():
    g = torch.Generator().manual_seed(3)
    X = torch.randn(400, 16, generator=g, dtype=torch.float64) @ torch.randn(16, 16, generator=g, dtype=torch.float64)
    r = cpca(X, 6, 2, seed=5, n_iter=40)
    assert len(r.errors) >= 2
    for a, b in zip(r.errors, r.errors[1:]):
        assert b <= a * (1 + F64_REL)
    r2 = cpca(X, 6, 2, seed=5, n_iter=40)
    assert torch.equal(r.ids, r2.ids) and torch.equal(r.coeffs, r2.coeffs)
    # more basis vectors never hurt (at least not for the same seed on this data)
    r4 = cpca(X, 6, 4, seed=5, n_iter=40)
    assert r4.errors[-1] < r.errors[-1]


def test_full_basis_is_exact():
    g = torch.Generator().manual_seed(4)
    X = torch.randn(50, 5, generator=g, dtype=torch.float64)
    r = cpca(X, 3, 5, seed=0)
    torch.testing.assert_close(reconstruct(r.ids, r.means, r.bases, r.coeffs), X, atol=1e-12, rtol=0)


def test_bad_input():
    X = torch.zeros(10, 3)
    with pytest.raises(ValueError):
        cpca(X, 11, 1)
    with pytest.raises(ValueError):
        cpca(X, 2, 4)
    with pytest.raises(ValueError):
        cpca(torch.zeros(10), 2, 1)
