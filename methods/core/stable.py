"""Results that are the same on every machine: singular vectors and top-n selections.

Two discrete choices in the methods are decided by round-off, and round-off differs between
machines (MKL and torch's own kernels take other code paths with other instruction sets: SSE, AVX2,
AVX-512) and thread counts (``methods.core.threads``, fixed by one-thread factorizations):

1. LAPACK returns each singular vector only up to its sign, and inside a cluster of equal singular
   values any orthonormal basis of the cluster's space. An isotropic BRDF's SVD has exactly such
   clusters: equal pairs (cos mφ, sin mφ). A method that uses the individual vectors, not only the
   space they span, then gives machine-dependent results (`canonical_svd`).
2. A "keep the n largest coefficients" selection splits a group of coefficients that are equal by
   symmetry (the same wavelet mirrored to another cube face, the same basis pair) wherever the cut
   falls inside it, and round-off decides which of them is kept (`keep_largest`).

Both met in PTT (Sun 2007), which keeps the n_L largest Haar coefficients of each incident factor
k's transport: its bench creature's V RMSE read 0.100 on one machine and 0.091 on another with the
same code, and on one machine 0.091 against 0.086 with torch's and MKL's vector kernels switched off
(``ATEN_CPU_CAPABILITY=default MKL_ENABLE_INSTRUCTIONS=SSE4_2``). With (1) alone the factors agreed
to 2e-8 but 11 181 of the 214 640 (vertex, k) selections still kept a different coefficient of a
tied pair (their magnitudes equal to 1e-6 relative, some of them 0.7 of the largest), and the RMSE
still moved 5 %; in-out (Mahajan 2008) moved 1e-4 from (1) alone.

`canonical_svd` fixes the basis of every cluster from the cluster's space alone: with U_c the
cluster's left vectors and G a fixed matrix (integer hash, the same bits everywhere), the columns of
the orthogonal projection U_c U_cᵀ G = U_c M, orthonormalised in order (QR of M with a positive
diagonal R, so U_c' = U_c Q), are the new vectors, and V_c' = V_c Q keeps A = U S Vᴴ. Replacing U_c
by U_c O for any orthogonal O gives M' = Oᵀ M = (Oᵀ Q) R, hence the same U_c O Oᵀ Q = U_c Q: the
result depends on the space only, i.e. it moves with round-off, not with the basis LAPACK chose. A
single vector is the r = 1 case (its sign: ⟨u, g⟩ > 0). Singular values whose neighbours are
within ``rtol``·S₀ form one cluster; rotating a cluster of unequal values changes U S Vᴴ by at most
their spread (≤ r·rtol·S₀ in the 2-norm).

`keep_largest` ranks by the weighted magnitude rounded to bins of 2^(1/256) (0.27 %) and breaks
ties inside a bin by the lower index: coefficients equal up to round-off (~1e-7 relative in float32)
share a bin unless they straddle a bin edge (≈ 1e-7 / 2.7e-3 of such pairs), so the same ones are
kept everywhere; the kept set is the n largest up to that 0.27 % (an error a few 1e-3 of the cut
coefficient's, against the cut coefficient's own magnitude for the arbitrary choice it replaces).
"""
from __future__ import annotations

import torch
from torch import Tensor

from methods.core.threads import torch_threads

__all__ = ["canonical_svd", "canonicalize_svd", "svd_clusters", "keep_largest", "CLUSTER_RTOL", "RANK_BINS_PER_OCTAVE"]

# Relative to S₀: LAPACK's singular values are accurate to ~p(m, n)·eps·S₀; equal pairs of an
# isotropic BRDF come out 2e-16–8e-16 apart (relative), distinct ones ≥ 1e-3 in the methods' SVDs.
CLUSTER_RTOL = 1e-10

_MAX_SALTS = 8

# `keep_largest`'s magnitude bins per factor of 2 (module docstring)
RANK_BINS_PER_OCTAVE = 256  # tries of G until M is well conditioned (a generic G needs one)


def svd_clusters(S: Tensor, rtol: float = CLUSTER_RTOL) -> list[tuple[int, int]]:
    """[start, end) index ranges of runs of (near-)equal singular values S (descending, 1-D):
    neighbours closer than ``rtol``·S₀ share a run. Every index is in exactly one range."""
    if S.ndim != 1:
        raise ValueError(f"S must be 1-D, got {tuple(S.shape)}")
    if not rtol >= 0.0:
        raise ValueError(f"rtol must be >= 0, got {rtol!r}")
    n = S.shape[0]
    if n == 0:
        return []
    tol = float(rtol) * float(S[0].abs())
    gaps = (S[:-1] - S[1:]).abs().tolist()
    out, start = [], 0
    for i, g in enumerate(gaps):
        if g > tol:
            out.append((start, i + 1))
            start = i + 1
    out.append((start, n))
    return out


def _hash_matrix(m: int, r: int, salt: int, dtype, device) -> Tensor:
    """(m, r) entries in [−0.5, 0.5) from an integer hash of (row, column, salt): exact integer
    arithmetic, so every machine builds the same matrix."""
    i = torch.arange(m, dtype=torch.int64, device=device)[:, None]
    j = torch.arange(r, dtype=torch.int64, device=device)[None, :]
    x = (i * 2654435761 + j * 40503 + salt * 97 + 12345) & 0xFFFFFFFF
    x = (x ^ (x >> 15)) * 2246822519 & 0xFFFFFFFF
    x = (x ^ (x >> 13)) * 3266489917 & 0xFFFFFFFF
    x = x ^ (x >> 16)
    return (x.to(torch.float64) / 4294967296.0 - 0.5).to(dtype)


def canonicalize_svd(U: Tensor, S: Tensor, Vh: Tensor, *, rtol: float = CLUSTER_RTOL) -> tuple[Tensor, Tensor, Tensor]:
    """The basis of every cluster of `svd_clusters` (S, rtol) made a function of its space only
    (module docstring). U (m, k), S (k,), Vh (k, n) of one matrix (thin SVD); returns new U, S
    (unchanged), Vh with U S Vh equal to the input's up to each cluster's spread of S."""
    if U.ndim != 2 or Vh.ndim != 2 or S.ndim != 1 or U.shape[1] != S.shape[0] or Vh.shape[0] != S.shape[0]:
        raise ValueError(f"need U (m, k), S (k,), Vh (k, n); got {tuple(U.shape)}, {tuple(S.shape)}, {tuple(Vh.shape)}")
    U, Vh = U.clone(), Vh.clone()
    m = U.shape[0]
    for a, b in svd_clusters(S, rtol):
        r = b - a
        Uc = U[:, a:b]
        for salt in range(_MAX_SALTS):
            G = _hash_matrix(m, r, salt, U.dtype, U.device)
            with torch_threads(1):
                Q, R = torch.linalg.qr(Uc.T @ G)
            d = R.diagonal()
            if float(d.abs().min()) > 1e-6 * float(d.abs().max()) * max(1.0, r ** 0.5) and float(d.abs().max()) > 0:
                break
        else:  # pragma: no cover - a generic G is never this degenerate
            raise RuntimeError(f"no well-conditioned probe for singular values {a}..{b}")
        Q = Q * torch.sign(d)[None, :]
        U[:, a:b] = Uc @ Q
        Vh[a:b] = Q.T @ Vh[a:b]
    return U, S, Vh


def canonical_svd(A: Tensor, *, rtol: float = CLUSTER_RTOL) -> tuple[Tensor, Tensor, Tensor]:
    """Thin SVD A (m, n) = U diag(S) Vh on one LAPACK thread, with `canonicalize_svd`'s basis in
    every cluster of equal singular values and every vector's sign: the same vectors, up to
    round-off, on every machine and with any thread count."""
    if A.ndim != 2:
        raise ValueError(f"A must be (m, n), got {tuple(A.shape)}")
    with torch_threads(1):
        U, S, Vh = torch.linalg.svd(A, full_matrices=False)
    return canonicalize_svd(U, S, Vh, rtol=rtol)


def keep_largest(coeffs: Tensor, n: int, *, weights: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """The n coefficients with the largest |c|·w in every row, the same ones on every machine
    (module docstring): ``methods.core.cubemap.keep_largest`` with magnitudes compared in bins of
    2^(1/`RANK_BINS_PER_OCTAVE`) and ties broken by the lower index.

    Args:
        coeffs: (..., K) coefficient vectors; n: number kept per row (clamped to K);
        weights: optional (K,) or broadcastable (..., K) non-negative weights (e.g. Haar support
            areas); None = plain magnitude.
    Returns:
        indices (..., n) int64 ordered by decreasing binned magnitude (lower index first inside a
        bin), values (..., n) = coeffs at those indices.
    """
    if coeffs.ndim < 1:
        raise ValueError("coeffs must have a trailing coefficient dimension")
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    K = coeffs.shape[-1]
    n = min(int(n), K)
    score = coeffs.detach().abs().double()
    if weights is not None:
        weights = torch.as_tensor(weights, device=coeffs.device)
        if weights.shape[-1] != K:
            raise ValueError(f"weights must end in K={K}, got {tuple(weights.shape)}")
        if bool((weights < 0).any()):
            raise ValueError("weights must be non-negative")
        score = score * weights.double()
    if not bool(torch.isfinite(score).all()):
        raise ValueError("coefficients and weights must be finite")
    # bins of log2|c|·w (zeros below every bin), then the lower index: one int64 key per entry
    b = torch.floor(torch.log2(score) * RANK_BINS_PER_OCTAVE)
    b = torch.where(score > 0, b, torch.full_like(b, -(2.0 ** 40)))
    key = b.to(torch.int64) * K + (K - 1 - torch.arange(K, device=coeffs.device))
    idx = torch.topk(key, n, dim=-1, largest=True, sorted=True).indices
    return idx, torch.gather(coeffs, -1, idx)
