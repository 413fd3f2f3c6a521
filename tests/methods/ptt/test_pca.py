"""Tests for methods.ptt.pca (Sun 2007 §3.1/§4.3 PCA BRDF basis of the PTTs)."""
from __future__ import annotations

import pytest
import torch

from methods.ptt.brdf_space import BlinnPhongSpace, CookTorranceSpace
from methods.ptt.brdf_tensor import DiskGrid, brdf_tensor
from methods.ptt.pca import PAPER_PCA_ERROR, pca_basis
from scenes.materials import CookTorrance

# Gram-eigen route vs explicit SVD, float64: agreement to ~1e-10 relative.
F64_RTOL = 1e-9
# Pinned regression values (uncentred PCA, 4 specular terms, W = 1, DiskGrid(12)); float64, but
# eigh/BLAS differ across machines and the small tail eigenvalues carry cancellation: 1e-4 rel.
PIN_RTOL = 1e-4
PINNED = {"bp": 1.54060e-04, "ct": 3.77947e-04}
PIN_GRID_N = 12


def _small_space():
    return BlinnPhongSpace(shininess=(1.0, 4.0, 10.0, 30.0, 80.0, 200.0))


@pytest.mark.parametrize("center", [False, True])
def test_gram_pca_matches_explicit_svd(center):
    space, g = _small_space(), DiskGrid(8)
    basis = pca_basis(space, grid_n=8, n_spec=3, center=center)
    X = brdf_tensor(space, g).reshape(space.n_h, -1)                     # (N_h, N²)
    # explicit reconstruction with the basis evaluated at the grid's direction pairs
    B = basis.eval(g.dirs[None, :, :], g.dirs[:, None, :])[..., :-1].reshape(-1, 3).T  # (3, N²)
    if not center:  # orthonormal basis: the coordinates are the least-squares ones
        coef = torch.linalg.lstsq(B.T, X.T).solution.T
        torch.testing.assert_close(coef, basis.C, rtol=F64_RTOL,
                                   atol=F64_RTOL * float(basis.C.abs().max()))
    else:  # mean BRDF with coefficient 1, then the centred PCs
        torch.testing.assert_close(B[0], X.mean(0))
        assert (basis.C[:, 0] == 1).all()
    sse = float((X - basis.C @ B).square().sum())
    assert basis.sq_error()["sse"] == pytest.approx(sse, rel=1e-7)
    if not center:
        # uncentred PCA = truncated SVD of the data matrix (Eckart–Young)
        s = torch.linalg.svdvals(X)
        assert sse == pytest.approx(float(s[3:].square().sum()), rel=1e-7)
        torch.testing.assert_close(B @ B.T, torch.eye(3, dtype=torch.float64), rtol=0, atol=1e-9)


def test_H_is_linear_in_navigation_weights_and_reconstructs():
    space = CookTorranceSpace()
    basis = pca_basis(space, grid_n=8)
    assert basis.n_P == 5
    # a navigated point: H is the weighted sum of the vertices' H (PTTs rely on this linearity)
    q = (0.5 * space.points[10] + 0.3 * space.points[20] + 0.2 * space.points[30])
    w = space.weights(q)
    H = basis.H(w, kd=(0.1, 0.2, 0.3), ks=0.5)
    H_sum = sum(float(w[h]) * basis.H(torch.eye(100, dtype=torch.float64)[h], kd=(0.1, 0.2, 0.3), ks=0.5)
                for h in torch.nonzero(w).flatten().tolist())
    torch.testing.assert_close(H, H_sum)
    torch.testing.assert_close(H[-1], torch.tensor([0.1, 0.2, 0.3], dtype=torch.float64))
    # a sampled material is reproduced up to the basis' truncation error
    F0, m = space.points[42]
    mat = CookTorrance(kd=0.2, ks=0.8, F0=float(F0), m=float(m))
    g = DiskGrid(8)
    wi, wo = g.dirs[None, :, :], g.dirs[:, None, :]
    got = basis.reconstruct(basis.coords(mat), wi, wo)
    ref = mat.eval(wi, wo)
    rel = float((got - ref).square().sum() / ref.square().sum())
    assert rel < 0.05, rel
    # the transport side's protocol, and Lambert materials
    from methods.ptt.transport import BRDFBasis as Protocol
    from scenes.materials import Lambert
    assert isinstance(basis, Protocol)
    torch.testing.assert_close(basis.coords(Lambert(kd=0.4))[:, 0],
                               torch.tensor([0, 0, 0, 0, 0.4], dtype=torch.float64))


@pytest.mark.parametrize("kind", ["bp", "ct"])
def test_pca_error_regression(kind):
    err = pca_basis(kind, grid_n=PIN_GRID_N).sq_error()
    assert err["rel_sq_err"] == pytest.approx(PINNED[kind], rel=PIN_RTOL)


def test_pca_ct_error_same_order_as_paper():
    """Sun 2007 §4.3: 6.23e-4 (CT). Our relative squared error on DiskGrid(12), 3.78e-4, lies
    within a factor 3 of it (normalisation and sampling of the paper unknown; see the report)."""
    err = pca_basis("ct", grid_n=PIN_GRID_N).sq_error()["rel_sq_err"]
    assert PAPER_PCA_ERROR["ct"] / 3 < err < 3 * PAPER_PCA_ERROR["ct"]


@pytest.mark.xfail(strict=True, reason="Sun 2007 §4.3 reports 1.61e-7 for Blinn-Phong (5 terms); we "
                   "measure rel_sq_err 1.54e-4 (DiskGrid(12)) / 1.68e-4 (DiskGrid(16)) for s = 1..200 "
                   "with the normalised (s+2)/(8π) lobe; only a per-entry solid-angle MSE (1.1e-7) "
                   "is of that size")
def test_pca_bp_paper_value():
    err = pca_basis("bp", grid_n=PIN_GRID_N).sq_error()["rel_sq_err"]
    assert err == pytest.approx(PAPER_PCA_ERROR["bp"], rel=1.0)


def test_bad_arguments():
    with pytest.raises(ValueError):
        pca_basis(_small_space(), grid_n=4, n_spec=7)
    with pytest.raises(ValueError):
        pca_basis(_small_space(), grid_n=4, weighting="cosine")
