"""Compression of the one-bounce PTTs: CPCA clustering + per-cluster tensor approximation along
the vertex and lighting dimensions (Sun et al. 2007 §4.3 "One-bounce Interreflection", Figs. 9–10).

"[We] apply CPCA [Sloan 2003] to cluster the PTTs of vertices into a number of groups, and then
collect the PTTs of each group into a single tensor by adding a vertex dimension. Each of these
group tensors is then compressed by tensor approximation along only the vertex and lighting
dimensions, while the other tensor dimensions are not compressed."

With the per-vertex PTT flattened to T_x(d, l), d = (r, p, s) (kept whole) and l the lighting
wavelet, cluster c's tensor X_c (n_c, D, L) is approximated by a Tucker-2 model (truncated HOSVD,
De Lathauwer 2000, on the vertex and lighting modes only; the leading singular vectors of the
very wide unfoldings (n_c × D·L, L × n_c·D) are taken from their small Gram matrices with
``torch.linalg.eigh`` — the same factors as ``methods.core.tensors.hosvd``, without an SVD of a
1000 × 25000 matrix):

    X_c ≈ G_c ×_vertex A_c ×_light B_c,   A_c (n_c, e), G_c (e, D, m), B_c (L, m),

e = "eigenvectors" (paper 32), m = "lighting dimension" (paper 64). At run time the lighting is
contracted first: Σ_l C^L_l T_x(d, l) = A_c[x] · (G_c ×_m (B_cᵀ C^L)), so a lighting change costs
O(L m + e D m + n_c e D) per cluster instead of O(n_c D L).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from methods.core.cpca import cpca
from methods.core.threads import torch_threads

__all__ = ["ClusteredTensor", "compress_ptt", "relative_error"]

# Dimension of the global PCA features the vertices are clustered on (CPCA step).
CLUSTER_FEATURES = 128


@dataclass
class ClusteredTensor:
    """Clustered Tucker-2 approximation of per-vertex tensors T (V, D, L).

    ids: (V,) cluster of each vertex; verts[c]: (n_c,) vertex ids; A[c]: (n_c, e_c);
    G[c]: (e_c, D, m_c); B[c]: (L, m_c). shape: (V, D, L).
    """

    ids: Tensor
    verts: list[Tensor]
    A: list[Tensor]
    G: list[Tensor]
    B: list[Tensor]
    shape: tuple[int, int, int]

    def contract_light(self, CL: Tensor) -> Tensor:
        """Σ_l T(v, d, l) CL(l, c): CL (L, C) → (V, D, C)."""
        V, D, L = self.shape
        if CL.ndim != 2 or CL.shape[0] != L:
            raise ValueError(f"lighting must be (L={L}, C), got {tuple(CL.shape)}")
        out = CL.new_zeros(V, D, CL.shape[1])
        for v, A, G, B in zip(self.verts, self.A, self.G, self.B):
            GL = torch.einsum("edm,mc->edc", G, B.T @ CL)  # (e, D, C)
            out[v] = torch.einsum("ne,edc->ndc", A, GL)
        return out

    def reconstruct(self) -> Tensor:
        """(V, D, L) dense tensor."""
        V, D, L = self.shape
        out = self.A[0].new_zeros(V, D, L) if self.A else torch.zeros(V, D, L)
        for v, A, G, B in zip(self.verts, self.A, self.G, self.B):
            out[v] = torch.einsum("ne,edm,lm->ndl", A, G, B)
        return out

    def tensors(self) -> list[Tensor]:
        """Every stored array (for memory accounting)."""
        return [self.ids, *self.verts, *self.A, *self.G, *self.B]


def compress_ptt(T: Tensor, *, clusters: int, eigenvectors: int, light_dim: int, seed: int = 0,
                 cpca_iters: int = 5) -> ClusteredTensor:
    """CPCA clustering of the vertices, then a Tucker-2 (vertex, lighting) model per cluster.

    Args:
        T: (V, D, L) per-vertex tensors (D = n_R·n_P·S for the one-bounce PTT).
        clusters: number of CPCA clusters (paper: about one per 1000 vertices).
        eigenvectors: e, vertex rank per cluster (paper 32; capped at the cluster size).
        light_dim: m, lighting rank per cluster (paper 64; capped at L).
        seed, cpca_iters: CPCA seed and iterations (its basis size is ``eigenvectors``).
    Returns:
        `ClusteredTensor`.
    """
    if T.ndim != 3:
        raise ValueError(f"T must be (V, D, L), got {tuple(T.shape)}")
    V, D, L = T.shape
    for k, v in (("clusters", clusters), ("eigenvectors", eigenvectors), ("light_dim", light_dim)):
        if isinstance(v, bool) or not isinstance(v, int) or v < 1:
            raise ValueError(f"{k} must be a positive int, got {v!r}")
    if clusters > V:
        raise ValueError(f"clusters ({clusters}) must be <= vertices ({V})")
    if clusters == 1:
        ids = torch.zeros(V, dtype=torch.int64)
    else:
        # CPCA on the vertices' coordinates in the global top-CLUSTER_FEATURES PCA basis (the
        # distances CPCA needs, at a fraction of the cost of 25 000-dimensional signals)
        X = T.reshape(V, D * L).double()
        with torch_threads(1):  # MKL's eigh rounds differently with other thread counts, and on AVX-512
            G = X @ X.T         # machines so does this Gram product's long reduction (methods.core.threads)
            w, U = torch.linalg.eigh(G)
        top = torch.argsort(w, descending=True)[:CLUSTER_FEATURES]
        feats = U[:, top] * w[top].clamp_min(0).sqrt()
        ids = cpca(feats, clusters, min(eigenvectors, feats.shape[1]), n_iter=cpca_iters, seed=seed).ids
    verts, As, Gs, Bs = [], [], [], []
    for c in range(clusters):
        v = torch.nonzero(ids == c).squeeze(-1)
        if v.numel() == 0:
            continue
        Xc = T[v].double()
        e, m = min(eigenvectors, v.numel()), min(light_dim, L)
        A = _leading(Xc.reshape(v.numel(), -1), e)                 # vertex factor (n_c, e)
        B = _leading(Xc.permute(2, 0, 1).reshape(L, -1), m)       # lighting factor (L, m)
        with torch_threads(1):                                    # (long reductions, as the Grams)
            G = torch.einsum("ndl,ne,lm->edm", Xc, A, B)          # core (e, D, m)
        verts.append(v)
        As.append(A.to(T.dtype))
        Gs.append(G.to(T.dtype))
        Bs.append(B.to(T.dtype))
    return ClusteredTensor(ids, verts, As, Gs, Bs, (V, D, L))


def _leading(M: Tensor, r: int) -> Tensor:
    """Leading r left singular vectors of a wide matrix M (I, J) from its Gram matrix (I, I)."""
    with torch_threads(1):  # as in `compress_ptt` (the Gram product too)
        G = M @ M.T
        w, U = torch.linalg.eigh(G)
    return U[:, torch.argsort(w, descending=True)[:r]]


def relative_error(T: Tensor, ct: ClusteredTensor) -> float:
    """‖T − T̂‖² / ‖T‖² (the squared error of Sun Fig. 9, relative)."""
    R = ct.reconstruct()
    return float((T - R).double().square().sum() / T.double().square().sum().clamp_min(1e-300))
