"""Tests for methods.core.tensors (truncated SVD, HOSVD, Tucker/HOOI via tensorly)."""
from __future__ import annotations

import pytest
import torch

from methods.core import tensors as T

# float64 decompositions of O(1) data: errors at the 1e-12 level; HOOI converged to tol 1e-10.
F64_TOL = 1e-9


def _rand(shape, seed, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    return torch.randn(*shape, generator=g, dtype=dtype)


def _low_rank_tensor(shape, ranks, seed):
    G = _rand(ranks, seed)
    Us = [torch.linalg.qr(_rand((I, R), seed + 1 + n))[0] for n, (I, R) in enumerate(zip(shape, ranks))]
    return T.tucker_reconstruct(G, Us)


def test_mode_n_product_definition():
    X = _rand((3, 4, 5), 0)
    M = _rand((6, 4), 1)
    Y = T.mode_n_product(X, M, 1)
    assert Y.shape == (3, 6, 5)
    torch.testing.assert_close(Y, torch.einsum("ijk,lj->ilk", X, M))
    # unfolding identity: (X ×_n M)_(n) = M X_(n)
    torch.testing.assert_close(T.unfold(Y, 1), M @ T.unfold(X, 1))
    torch.testing.assert_close(T.fold(T.unfold(X, 2), 2, X.shape), X)
    with pytest.raises(ValueError):
        T.mode_n_product(X, M, 0)


def test_truncated_svd_eckart_young():
    A = _rand((2, 10, 7), 2)
    U, S, Vh = T.truncated_svd(A, 3)
    s_all = torch.linalg.svdvals(A)
    err = torch.linalg.matrix_norm(A - T.low_rank(A, 3))
    torch.testing.assert_close(err, s_all[:, 3:].square().sum(-1).sqrt())
    torch.testing.assert_close(U.transpose(-1, -2) @ U, torch.eye(3, dtype=A.dtype).expand(2, 3, 3))
    with pytest.raises(ValueError):
        T.truncated_svd(A, 8)


def test_tucker_exact_recovery_of_low_rank_tensor():
    X = _low_rank_tensor((8, 9, 10), (2, 3, 4), 3)
    core, factors = T.tucker(X, (2, 3, 4))
    assert core.shape == (2, 3, 4) and [f.shape for f in factors] == [(8, 2), (9, 3), (10, 4)]
    assert T.relative_error(X, T.tucker_reconstruct(core, factors)) < F64_TOL


def test_tucker_orthonormal_factors_and_bound_and_monotone():
    X = _rand((7, 8, 9), 4) + 3 * _low_rank_tensor((7, 8, 9), (2, 2, 2), 5)
    errs = []
    for ranks in ((1, 1, 1), (2, 2, 2), (3, 3, 3), (5, 5, 5), (7, 8, 9)):
        core, factors = T.tucker(X, ranks)
        for U in factors:
            torch.testing.assert_close(U.T @ U, torch.eye(U.shape[1], dtype=X.dtype), atol=F64_TOL, rtol=0)
        e = torch.linalg.vector_norm(X - T.tucker_reconstruct(core, factors))
        g, fs = T.hosvd(X, ranks)
        e_hosvd = torch.linalg.vector_norm(X - T.tucker_reconstruct(g, fs))
        # HOOI starts from HOSVD and only improves; HOSVD obeys De Lathauwer's Property 10 bound
        assert e <= e_hosvd + F64_TOL
        assert e_hosvd <= T.hosvd_error_bound(X, ranks) + F64_TOL
        errs.append(e.item())
    assert all(a >= b - F64_TOL for a, b in zip(errs, errs[1:]))
    assert errs[-1] < F64_TOL  # full rank in every mode → exact


def test_tucker_keeps_backend_dtype_and_validates():
    import tensorly as tl

    before = tl.get_backend()
    X = _rand((5, 6, 7), 6, dtype=torch.float32)
    core, factors = T.tucker(X, (2, 2, 2))
    assert tl.get_backend() == before
    assert core.dtype == torch.float32 and isinstance(factors[0], torch.Tensor)
    with pytest.raises(ValueError):
        T.tucker(X, (2, 2))
    with pytest.raises(ValueError):
        T.tucker(X, (6, 2, 2))
