"""Clustered principal component analysis (Sloan, Hall, Hart, Snyder 2003, "Clustered Principal
Components for Precomputed Radiance Transfer", §4 "iterative CPCA").

Signals x_p ∈ R^D (p = 1..N) are partitioned into K clusters; cluster k keeps a mean m_k and M
orthonormal basis vectors B_k (M, D), and x_p ≈ m_k + Σ_i w_pi B_ki (Sloan 2003 eq. 5). The
iteration alternates
  1. PCA step: for the current partition, m_k = cluster mean, B_k = top-M right singular vectors
     of the centred cluster (optimal for the partition);
  2. classification step: each x_p moves to the cluster whose affine subspace reconstructs it best,
     err_k(x) = ‖x − m_k‖² − ‖B_k (x − m_k)‖² (Sloan 2003 §4);
so the total squared error never increases. The partition is seeded by k-means++ (M = 0, i.e.
plain VQ) from a seeded torch.Generator: the result is deterministic for a seed. A cluster that
empties is re-seeded with the currently worst-reconstructed signal.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from methods.core.threads import torch_threads

__all__ = ["CPCAResult", "cpca", "cpca_fit_clusters", "cpca_project", "reconstruct", "squared_error"]


@dataclass
class CPCAResult:
    """ids (N,) int64 cluster per signal; means (K, D); bases (K, M, D) orthonormal rows;
    coeffs (N, M) = B_{ids} (x − m_{ids}); errors: total squared error after each iteration."""

    ids: Tensor
    means: Tensor
    bases: Tensor
    coeffs: Tensor
    errors: list[float] = field(default_factory=list)

    def reconstruct(self) -> Tensor:
        return reconstruct(self.ids, self.means, self.bases, self.coeffs)


def cpca_fit_clusters(X: Tensor, ids: Tensor, K: int, M: int) -> tuple[Tensor, Tensor]:
    """PCA step: per-cluster mean (K, D) and top-M principal directions (K, M, D).

    Empty clusters get a zero mean and zero basis (callers re-seed them)."""
    N, D = X.shape
    means = X.new_zeros(K, D)
    bases = X.new_zeros(K, M, D)
    for k in range(K):
        Xk = X[ids == k]
        if Xk.shape[0] == 0:
            continue
        mk = Xk.mean(0)
        means[k] = mk
        if M > 0:
            # full_matrices so that clusters with < M points still get M orthonormal rows; one
            # LAPACK thread: the vectors must not depend on the thread count (methods.core.threads)
            with torch_threads(1):
                _, _, Vh = torch.linalg.svd(Xk - mk, full_matrices=True)
            bases[k] = Vh[:M]
    return means, bases


def _cluster_errors(X: Tensor, means: Tensor, bases: Tensor, chunk: int = 4096) -> Tensor:
    """(N, K) squared reconstruction error of every signal in every cluster's affine subspace."""
    out = []
    for a in range(0, X.shape[0], chunk):
        Xc = X[a:a + chunk]
        R = Xc[:, None, :] - means[None]  # (n, K, D)
        w = torch.einsum("nkd,kmd->nkm", R, bases)
        out.append(R.square().sum(-1) - w.square().sum(-1))  # Sloan 2003 §4 classification
    return torch.cat(out).clamp_min(0.0)


def cpca_project(X: Tensor, ids: Tensor, means: Tensor, bases: Tensor) -> Tensor:
    """Coefficients (N, M) = B_{ids} (x − m_{ids})."""
    return torch.einsum("nd,nmd->nm", X - means[ids], bases[ids])


def reconstruct(ids: Tensor, means: Tensor, bases: Tensor, coeffs: Tensor) -> Tensor:
    """x̃_p = m_k + Σ_i w_pi B_ki (Sloan 2003 eq. 5) → (N, D)."""
    return means[ids] + torch.einsum("nm,nmd->nd", coeffs, bases[ids])


def squared_error(X: Tensor, X_hat: Tensor) -> Tensor:
    """Total squared error Σ_p ‖x_p − x̃_p‖² (scalar; summed in an order that does not depend on the
    thread count: it decides when `cpca` stops)."""
    with torch_threads(1):
        return (X - X_hat).square().sum()


def _kmeanspp(X: Tensor, K: int, gen: torch.Generator) -> Tensor:
    N = X.shape[0]
    first = int(torch.randint(N, (1,), generator=gen))
    C = [X[first]]
    d2 = (X - X[first]).square().sum(-1)
    for _ in range(1, K):
        p = d2.double().cpu()
        if p.sum() <= 0:
            j = int(torch.randint(N, (1,), generator=gen))
        else:
            j = int(torch.multinomial(p / p.sum(), 1, generator=gen))
        C.append(X[j])
        d2 = torch.minimum(d2, (X - X[j]).square().sum(-1))
    return torch.stack(C)


def cpca(X: Tensor, K: int, M: int, *, n_iter: int = 30, n_vq_iter: int = 10, seed: int = 0,
         tol: float = 0.0) -> CPCAResult:
    """Iterative CPCA (Sloan 2003 §4).

    Args:
        X: (N, D) signals (float32/float64, any device).
        K: clusters (1 <= K <= N); M: basis vectors per cluster (0 <= M <= D; M = 0 is VQ).
        n_iter: maximum PCA/classification iterations; n_vq_iter: k-means iterations used to seed
            the partition; seed: RNG seed (deterministic result); tol: stop when the relative error
            decrease of an iteration is <= tol (and always when the partition stops changing).
    Returns:
        `CPCAResult` (errors[i] = total squared error after iteration i, non-increasing).
    """
    X = torch.as_tensor(X)
    if X.ndim != 2:
        raise ValueError(f"X must be (N, D), got {tuple(X.shape)}")
    N, D = X.shape
    if not 1 <= K <= N:
        raise ValueError(f"K must be in [1, N={N}], got {K}")
    if not 0 <= M <= D:
        raise ValueError(f"M must be in [0, D={D}], got {M}")
    if not X.is_floating_point():
        X = X.float()
    gen = torch.Generator().manual_seed(int(seed))
    # seed the partition: k-means++ then Lloyd (VQ, the M = 0 case of the same iteration)
    C = _kmeanspp(X, K, gen)
    ids = torch.cdist(X, C).argmin(-1)
    for _ in range(n_vq_iter):
        means, _ = cpca_fit_clusters(X, ids, K, 0)
        new = _cluster_errors(X, means, X.new_zeros(K, 0, D)).argmin(-1)
        if torch.equal(new, ids):
            break
        ids = new

    errors: list[float] = []
    means, bases = cpca_fit_clusters(X, ids, K, M)
    for _ in range(n_iter):
        E = _cluster_errors(X, means, bases)  # (N, K)
        cur = E.gather(1, ids[:, None]).squeeze(1)
        # classification step; keep the current cluster on ties (no pointless flips)
        best = E.argmin(-1)
        new = torch.where(E.gather(1, best[:, None]).squeeze(1) < cur, best, ids)
        # re-seed empty clusters with the worst-reconstructed signals (deterministic)
        counts = torch.bincount(new, minlength=K)
        empty = (counts == 0).nonzero().flatten().tolist()
        if empty:
            err_now = E.gather(1, new[:, None]).squeeze(1)
            order = err_now.argsort(descending=True).tolist()
            for k, p in zip(empty, order):
                new[p] = k
        changed = not torch.equal(new, ids)
        ids = new
        means, bases = cpca_fit_clusters(X, ids, K, M)
        coeffs = cpca_project(X, ids, means, bases)
        err = float(squared_error(X, reconstruct(ids, means, bases, coeffs)))
        errors.append(err)
        if not changed:
            break
        if tol > 0 and len(errors) > 1 and errors[-2] - err <= tol * max(errors[-2], 1e-300):
            break
    coeffs = cpca_project(X, ids, means, bases)
    if not errors:
        errors.append(float(squared_error(X, reconstruct(ids, means, bases, coeffs))))
    return CPCAResult(ids=ids, means=means, bases=bases, coeffs=coeffs, errors=errors)
