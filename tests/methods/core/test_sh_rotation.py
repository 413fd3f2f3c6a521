"""Tests for methods/core/sh_rotation.py: re-projection, composition, orthogonality, band 1."""
import math

import pytest
import torch

from methods.core import sh
from methods.core.sampling import gauss_legendre_sphere
from methods.core.sh_rotation import rotate_coeffs, sh_rotation_blocks, sh_rotation_matrix
from methods.core.zh import zh_to_sh

F64 = torch.float64
EXACT = 1e-12     # float64, recurrences of O(order) steps on O(1) numbers
HIGH_ORDER = 1e-10  # order 20: error grows mildly with the number of recurrence steps


def random_rotations(B, seed=0):
    """Uniform random rotations from normalised Gaussian quaternions → (B, 3, 3)."""
    q = torch.randn(B, 4, generator=torch.Generator().manual_seed(seed), dtype=F64)
    q = q / q.norm(dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    return torch.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w),
                        2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w),
                        2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
                       dim=-1).reshape(B, 3, 3)


def test_rotation_equals_reprojection_of_rotated_function():
    order = 7
    R = random_rotations(4)
    M = sh_rotation_matrix(R, order)
    assert M.shape == (4, order * order, order * order)
    d, w = gauss_legendre_sphere(order + 1, 2 * order + 1, dtype=F64)  # exact for products
    Y = sh.sh_eval(d, order)
    # f'(d) = f(Rᵀ d): M_ij = ∫ y_i(d) y_j(Rᵀ d) dω ; row-vector d @ R = (Rᵀ d)ᵀ
    Mref = torch.einsum("di,bdj->bij", Y * w[:, None], sh.sh_eval(d @ R, order))
    assert (M - Mref).abs().max() < EXACT


def test_rotate_coeffs_rotates_the_function_by_R():
    order = 6
    R = random_rotations(3, seed=1)
    c = torch.randn(order * order, 2, generator=torch.Generator().manual_seed(2), dtype=F64)
    d = torch.randn(50, 3, generator=torch.Generator().manual_seed(3), dtype=F64)
    d = d / d.norm(dim=-1, keepdim=True)
    c_rot = rotate_coeffs(c, R)                              # (3, n², 2)
    for b in range(3):
        assert torch.allclose(sh.reconstruct(c_rot[b], d), sh.reconstruct(c, d @ R[b]), atol=EXACT)
        assert torch.allclose(rotate_coeffs(c, R[b]), c_rot[b], atol=EXACT)
    assert torch.allclose(rotate_coeffs(c[:, 0], R[0]), c_rot[0, :, 0], atol=EXACT)
    # batched coeffs with batched R
    cb = torch.stack([c, 2 * c, -c])
    assert torch.allclose(rotate_coeffs(cb, R), torch.stack([c_rot[0], 2 * c_rot[1], -c_rot[2]]), atol=EXACT)
    # a lobe around axis a ends up around R a
    k = torch.tensor([1.0, 0.5, 0.25, 0.1, 0.05, 0.01], dtype=F64)
    a = torch.tensor([0.3, -0.4, math.sqrt(0.75)], dtype=F64)
    assert torch.allclose(rotate_coeffs(zh_to_sh(k, a), R[0]), zh_to_sh(k, R[0] @ a), atol=EXACT)


def test_composition_identity_orthogonality():
    order = 8
    R1, R2 = random_rotations(5, seed=4), random_rotations(5, seed=5)
    M1, M2, M12 = (sh_rotation_matrix(R, order) for R in (R1, R2, R1 @ R2))
    assert (M12 - M1 @ M2).abs().max() < EXACT
    eye = torch.eye(order * order, dtype=F64)
    assert (M1 @ M1.transpose(-1, -2) - eye).abs().max() < EXACT
    assert (sh_rotation_matrix(torch.eye(3, dtype=F64), order) - eye).abs().max() < EXACT
    # Rᵀ gives the inverse
    assert (sh_rotation_matrix(R1.transpose(-1, -2), order) - M1.transpose(-1, -2)).abs().max() < EXACT


def test_high_order_stays_orthogonal():
    order = 20
    M = sh_rotation_matrix(random_rotations(2, seed=6), order)
    eye = torch.eye(order * order, dtype=F64)
    assert (M @ M.transpose(-1, -2) - eye).abs().max() < HIGH_ORDER


def test_band1_is_R_in_yzx_order():
    R = random_rotations(3, seed=7)
    blocks = sh_rotation_blocks(R, 3)
    assert [b.shape for b in blocks] == [(3, 1, 1), (3, 3, 3), (3, 5, 5)]
    p = [1, 2, 0]
    assert torch.allclose(blocks[1], R[:, p][:, :, p], atol=0)
    assert torch.allclose(blocks[0], torch.ones(3, 1, 1, dtype=F64))
    single = sh_rotation_blocks(R[0], 3)
    assert single[2].shape == (5, 5) and torch.allclose(single[2], blocks[2][0])


def test_float32_and_errors():
    R = random_rotations(2).float()
    M = sh_rotation_matrix(R, 4)
    assert M.dtype == torch.float32
    with pytest.raises(ValueError):
        sh_rotation_matrix(torch.eye(4), 3)
    with pytest.raises(ValueError):
        rotate_coeffs(torch.zeros(8, 3), torch.eye(3))
    with pytest.raises(ValueError):
        rotate_coeffs(torch.zeros(2, 9, 3), random_rotations(3).float())
