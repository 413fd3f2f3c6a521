"""`methods.core.stable`: singular vectors that depend on the singular spaces only, not on the basis
LAPACK picks inside a cluster of equal singular values (that pick follows the machine's
instruction set and thread count; module docstring)."""
from __future__ import annotations

import math

import pytest
import torch

from methods.core import stable as csvd


def _orthonormal(n: int, k: int, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.linalg.qr(torch.randn(n, k, generator=g, dtype=torch.float64))[0]


def _with_clusters(seed: int = 0):
    """A (40, 30) matrix with singular values 5, 3, 3, 2, 1, 1, 1, 0.5, … (a pair and a triple)."""
    S = torch.tensor([5.0, 3.0, 3.0, 2.0, 1.0, 1.0, 1.0] + [0.5 / (i + 1) for i in range(23)], dtype=torch.float64)
    U, V = _orthonormal(40, 30, seed), _orthonormal(30, 30, seed + 1)
    return (U * S) @ V.T, S


def _rotate_clusters(U, S, Vh, seed: int):
    """The same SVD with another basis in every cluster and random signs: what another machine's
    LAPACK may return."""
    g = torch.Generator().manual_seed(seed)
    U, Vh = U.clone(), Vh.clone()
    for a, b in csvd.svd_clusters(S):
        O = torch.linalg.qr(torch.randn(b - a, b - a, generator=g, dtype=U.dtype))[0]
        O = O * torch.where(torch.rand(b - a, generator=g) < 0.5, -1.0, 1.0).to(U.dtype)
        U[:, a:b] = U[:, a:b] @ O
        Vh[a:b] = O.T @ Vh[a:b]
    return U, S, Vh


def test_clusters_of_equal_singular_values():
    A, S = _with_clusters()
    s = torch.linalg.svdvals(A)
    assert torch.allclose(s, S, rtol=1e-12, atol=0)
    assert csvd.svd_clusters(s)[:5] == [(0, 1), (1, 3), (3, 4), (4, 7), (7, 8)]
    # every index in exactly one range
    r = csvd.svd_clusters(s)
    assert r[0][0] == 0 and r[-1][1] == 30 and all(x[1] == y[0] for x, y in zip(r, r[1:]))
    with pytest.raises(ValueError):
        csvd.svd_clusters(s, rtol=-1.0)


def test_canonical_vectors_depend_on_the_spaces_only():
    A, _ = _with_clusters()
    U, S, Vh = torch.linalg.svd(A, full_matrices=False)
    U0, S0, Vh0 = csvd.canonicalize_svd(U, S, Vh)
    for seed in range(5):
        U1, S1, Vh1 = csvd.canonicalize_svd(*_rotate_clusters(U, S, Vh, seed))
        assert torch.allclose(U1, U0, atol=1e-12, rtol=0) and torch.allclose(Vh1, Vh0, atol=1e-12, rtol=0)
    # ... whereas the rotated inputs themselves differ at O(1) inside the clusters
    Ur = _rotate_clusters(U, S, Vh, 0)[0]
    assert float((Ur[:, 1:3] - U[:, 1:3]).abs().max()) > 0.1
    # still an SVD of A: orthonormal, same values, same product
    assert torch.equal(S0, S)
    assert torch.allclose(U0.T @ U0, torch.eye(30, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(Vh0 @ Vh0.T, torch.eye(30, dtype=torch.float64), atol=1e-12)
    assert torch.allclose((U0 * S0) @ Vh0, A, atol=1e-12)


def test_canonical_svd_of_a_perturbed_matrix_moves_with_the_perturbation():
    """Round-off-sized changes of A (what another instruction set does) change the canonical vectors
    by round-off, while LAPACK's own vectors of a pair may turn by any angle."""
    A, _ = _with_clusters(3)
    g = torch.Generator().manual_seed(7)
    B = A + 1e-14 * torch.randn(A.shape, generator=g, dtype=A.dtype)
    Ua, _, _ = csvd.canonical_svd(A)
    Ub, _, _ = csvd.canonical_svd(B)
    assert float((Ua - Ub).abs().max()) < 1e-9


def test_an_isotropic_lobe_pair_is_canonical():
    """cos φ, sin φ on a ring sampled at two rotations of the same directions: the same function of
    the direction comes out (LAPACK's pair could be any rotation of it)."""
    n = 64
    phi = torch.arange(n, dtype=torch.float64) * (2 * math.pi / n)
    A = torch.stack([torch.cos(phi), torch.sin(phi), torch.full_like(phi, 0.3)], 1)  # a pair + a single
    U, S, Vh = csvd.canonical_svd(A)
    assert csvd.svd_clusters(S) == [(0, 2), (2, 3)]
    for seed in range(3):
        U1, _, _ = csvd.canonicalize_svd(*_rotate_clusters(*torch.linalg.svd(A, full_matrices=False), seed))
        assert torch.allclose(U1, U, atol=1e-12, rtol=0)


def test_bad_shapes_raise():
    with pytest.raises(ValueError):
        csvd.canonical_svd(torch.zeros(3))
    with pytest.raises(ValueError):
        csvd.canonicalize_svd(torch.zeros(3, 2), torch.zeros(3), torch.zeros(2, 4))


def test_keep_largest_is_the_n_largest_when_there_are_no_ties():
    from methods.core import cubemap

    g = torch.Generator().manual_seed(2)
    x = torch.randn(7, 300, generator=g)
    w = torch.rand(300, generator=g) + 0.1
    for n in (0, 1, 10, 300, 400):
        i0, v0 = cubemap.keep_largest(x, n, weights=w)
        i1, v1 = csvd.keep_largest(x, n, weights=w)
        assert torch.equal(i0.sort(-1).values, i1.sort(-1).values)  # random magnitudes: no two in one bin at the cut
        assert torch.equal(torch.gather(x, -1, i1), v1)


def test_keep_largest_decides_ties_the_same_under_round_off():
    """Coefficients equal by symmetry (here: each value four times, as a wavelet mirrored onto four
    cube faces) with a cut inside a group: float32 round-off of either sign (what another machine's
    kernels give) must not change which are kept; torch.topk's choice does change."""
    g = torch.Generator().manual_seed(4)
    base = torch.rand(64, 20, generator=g) + 0.05
    x = base.repeat(1, 4)                              # (64, 80): every magnitude four times
    n = 10                                             # cuts inside a group in most rows
    ref, _ = csvd.keep_largest(x, n)
    moved_topk = 0
    for seed in range(6):
        e = 1.0 + 2e-7 * torch.randn(x.shape, generator=torch.Generator().manual_seed(100 + seed))
        y = (x * e).float()
        got, val = csvd.keep_largest(y, n)
        assert torch.equal(got, ref)
        assert torch.equal(val, torch.gather(y, -1, got))
        moved_topk += int((torch.topk(y.abs(), n).indices.sort(-1).values != torch.topk(x.abs(), n).indices.sort(-1).values).any(-1).sum())
    assert moved_topk > 0  # the plain selection is decided by the round-off


def test_keep_largest_rejects_bad_input():
    with pytest.raises(ValueError):
        csvd.keep_largest(torch.tensor([1.0, float("nan")]), 1)
    with pytest.raises(ValueError):
        csvd.keep_largest(torch.ones(4), 2, weights=-torch.ones(4))
    with pytest.raises(ValueError):
        csvd.keep_largest(torch.ones(4), -1)
    i, v = csvd.keep_largest(torch.zeros(3, 5), 2)  # all zero: the lowest indices
    assert torch.equal(i, torch.tensor([[0, 1]] * 3))
