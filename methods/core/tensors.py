"""Low-rank matrix and tensor factorizations: truncated SVD and the Tucker decomposition
(HOSVD initialisation + HOOI, De Lathauwer, De Moor, Vandewalle 2000 "On the best rank-(R1,…,RN)
approximation of higher-order tensors", Alg. 4.2). Used by the PTT method (Sun 2007) and the BRDF
factorizations.

Tucker: X ≈ G ×_1 U1 ×_2 U2 … ×_N UN with orthonormal factor columns Un (I_n, R_n) and core
G (R_1, …, R_N). `tucker` calls tensorly 0.10 (`tensorly.decomposition.tucker`, init="svd" = HOSVD,
then HOOI sweeps) under its PyTorch backend inside `tensorly.backend_context`, so the global
tensorly backend of the caller is left untouched and tensors stay torch (dtype/device preserved).
`hosvd` is our own (it is the init and the error bound tests rely on).

Mode-n product (De Lathauwer 2000 Def. 8): (X ×_n M)[i1…j…iN] = Σ_{i_n} X[i1…i_n…iN] M[j, i_n],
M of shape (J, I_n).
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor

from methods.core.threads import torch_threads

__all__ = [
    "truncated_svd",
    "low_rank",
    "unfold",
    "fold",
    "mode_n_product",
    "multi_mode_product",
    "hosvd",
    "tucker",
    "tucker_reconstruct",
    "relative_error",
    "hosvd_error_bound",
]


def truncated_svd(A: Tensor, k: int) -> tuple[Tensor, Tensor, Tensor]:
    """Best rank-k factors (Eckart–Young) of matrices.

    Args:
        A: (..., m, n); k: rank, 1 <= k <= min(m, n).
    Returns:
        U (..., m, k), S (..., k) descending, Vh (..., k, n); A_k = U @ diag(S) @ Vh.
    """
    if A.ndim < 2:
        raise ValueError(f"A must be (..., m, n), got {tuple(A.shape)}")
    m, n = A.shape[-2:]
    if not 1 <= k <= min(m, n):
        raise ValueError(f"k must be in [1, {min(m, n)}], got {k}")
    with torch_threads(1):  # LAPACK's vectors depend on the thread count otherwise (methods.core.threads)
        U, S, Vh = torch.linalg.svd(A, full_matrices=False)
    return U[..., :k], S[..., :k], Vh[..., :k, :]


def low_rank(A: Tensor, k: int) -> Tensor:
    """Rank-k approximation (..., m, n) of A (..., m, n)."""
    U, S, Vh = truncated_svd(A, k)
    return (U * S.unsqueeze(-2)) @ Vh


def unfold(X: Tensor, n: int) -> Tensor:
    """Mode-n unfolding (I_n, Π_{m≠n} I_m) (remaining modes in increasing order, C order)."""
    if not -X.ndim <= n < X.ndim:
        raise ValueError(f"mode {n} out of range for a {X.ndim}-way tensor")
    return torch.movedim(X, n, 0).reshape(X.shape[n], -1)


def fold(M: Tensor, n: int, shape: Sequence[int]) -> Tensor:
    """Inverse of `unfold`: (I_n, …) → tensor of `shape`."""
    shape = list(shape)
    moved = [shape[n]] + shape[:n] + shape[n + 1:]
    return torch.movedim(M.reshape(moved), 0, n)


def mode_n_product(X: Tensor, M: Tensor, n: int) -> Tensor:
    """X ×_n M (De Lathauwer 2000 Def. 8).

    Args:
        X: (I_1, …, I_N); M: (J, I_n); n: mode (0-based).
    Returns:
        (I_1, …, J, …, I_N).
    """
    if M.ndim != 2 or M.shape[1] != X.shape[n]:
        raise ValueError(f"M must be (J, {X.shape[n]}) for mode {n}, got {tuple(M.shape)}")
    return torch.movedim(torch.tensordot(M, X, dims=([1], [n])), 0, n)


def multi_mode_product(X: Tensor, Ms: Sequence[Tensor | None], *, transpose: bool = False) -> Tensor:
    """X ×_1 M1 ×_2 M2 … (None skips a mode); transpose=True uses Mn.T (projection onto factors)."""
    if len(Ms) != X.ndim:
        raise ValueError(f"need {X.ndim} matrices (or None), got {len(Ms)}")
    for n, M in enumerate(Ms):
        if M is not None:
            X = mode_n_product(X, M.T if transpose else M, n)
    return X


def _check_ranks(X: Tensor, ranks: Sequence[int]) -> list[int]:
    ranks = [int(r) for r in ranks]
    if len(ranks) != X.ndim:
        raise ValueError(f"need one rank per mode ({X.ndim}), got {ranks}")
    for n, (r, I) in enumerate(zip(ranks, X.shape)):
        if not 1 <= r <= I:
            raise ValueError(f"rank of mode {n} must be in [1, {I}], got {r}")
    return ranks


def hosvd(X: Tensor, ranks: Sequence[int]) -> tuple[Tensor, list[Tensor]]:
    """Truncated higher-order SVD (De Lathauwer 2000 §2 / Alg. 4.2 init): Un = leading R_n left
    singular vectors of the mode-n unfolding; G = X ×_n Unᵀ.

    Args:
        X: (I_1, …, I_N); ranks: (R_1, …, R_N).
    Returns:
        core (R_1, …, R_N), factors [Un (I_n, R_n)].
    """
    ranks = _check_ranks(X, ranks)
    factors = [truncated_svd(unfold(X, n), r)[0] for n, r in enumerate(ranks)]
    return multi_mode_product(X, factors, transpose=True), factors


def tucker(X: Tensor, ranks: Sequence[int], *, n_iter_max: int = 100, tol: float = 1e-10,
           ) -> tuple[Tensor, list[Tensor]]:
    """Tucker decomposition by HOOI with HOSVD initialisation (De Lathauwer 2000 Alg. 4.2), via
    tensorly's PyTorch backend (global backend restored on exit).

    Args:
        X: (I_1, …, I_N) torch tensor (float32/float64, any device).
        ranks: (R_1, …, R_N), 1 <= R_n <= I_n.
        n_iter_max: HOOI sweeps; tol: stop when the reconstruction error changes by less.
    Returns:
        core (R_1, …, R_N), factors [Un (I_n, R_n)] with orthonormal columns.
    """
    import tensorly as tl
    from tensorly.decomposition import tucker as _tl_tucker

    X = torch.as_tensor(X)
    ranks = _check_ranks(X, ranks)
    if not X.is_floating_point():
        raise ValueError(f"X must be floating point, got {X.dtype}")
    with tl.backend_context("pytorch"):
        core, factors = _tl_tucker(X, rank=ranks, init="svd", n_iter_max=n_iter_max, tol=tol,
                                   svd="truncated_svd")
    return core, list(factors)


def tucker_reconstruct(core: Tensor, factors: Sequence[Tensor]) -> Tensor:
    """G ×_1 U1 ×_2 U2 … ×_N UN: core (R_1, …, R_N), factors [(I_n, R_n)] → (I_1, …, I_N)."""
    if len(factors) != core.ndim:
        raise ValueError(f"need {core.ndim} factors, got {len(factors)}")
    return multi_mode_product(core, list(factors))


def relative_error(X: Tensor, X_hat: Tensor) -> Tensor:
    """‖X − X̂‖_F / ‖X‖_F (scalar tensor)."""
    if X.shape != X_hat.shape:
        raise ValueError(f"shapes differ: {tuple(X.shape)} vs {tuple(X_hat.shape)}")
    return torch.linalg.vector_norm(X - X_hat) / torch.linalg.vector_norm(X)


def hosvd_error_bound(X: Tensor, ranks: Sequence[int]) -> Tensor:
    """De Lathauwer 2000 Property 10: ‖X − X_hosvd‖² ≤ Σ_n Σ_{i > R_n} σ_i^(n)², with σ^(n) the
    singular values of the mode-n unfolding. Returns the bound on ‖X − X̂‖_F (absolute)."""
    ranks = _check_ranks(X, ranks)
    tot = X.new_zeros(())
    for n, r in enumerate(ranks):
        with torch_threads(1):  # as `truncated_svd`
            s = torch.linalg.svdvals(unfold(X, n))
        tot = tot + s[r:].square().sum()
    return tot.sqrt()
