"""Rotation matrices for real SH (basis of `methods/core/sh.py`), any order, batched.

Semantics: for a 3×3 rotation R, the matrix M(R) maps the coefficients c of f to the coefficients
c' = M c of the ROTATED function f'(d) = f(Rᵀ d) (the function is rotated by R: a lobe pointing
along a ends up along R a). M is block diagonal with one (2l+1)×(2l+1) orthogonal block per band,
M(R₁R₂) = M(R₁)M(R₂), M(I) = I, and band 1 is R itself in the (y, z, x) ordering of
(m = −1, 0, 1): M¹[i, j] = R[p_i, p_j], p = (1, 2, 0). (Our real SH carry no Condon–Shortley
phase, which is exactly the basis Ivanic & Ruedenberg use, so band 1 needs no sign flips.)

Higher bands: Ivanic & Ruedenberg 1996, "Rotation matrices for real spherical harmonics. Direct
determination by recursion", J. Phys. Chem. 100(15) Table 1–2, with the 1998 errata
(J. Phys. Chem. A 102, 9099): M^l_{mn} = u U + v V + w W built from M^{l−1} and M¹.
"""
from __future__ import annotations

import functools
import math

import numpy as np
import torch
from torch import Tensor

_PERM = (1, 2, 0)  # m = −1, 0, 1  ↔  y, z, x


def _check_R(R: Tensor) -> tuple[Tensor, bool]:
    if R.shape[-2:] != (3, 3) or R.ndim not in (2, 3):
        raise ValueError(f"R must have shape (3, 3) or (B, 3, 3), got {tuple(R.shape)}")
    if not R.is_floating_point():
        R = R.float()
    single = R.ndim == 2
    return (R.unsqueeze(0) if single else R), single


@functools.lru_cache(maxsize=None)
def _band_tables(l: int):
    """Constant factors of the Ivanic–Ruedenberg recurrence for band l ≥ 2, as numpy arrays.

    The recurrence M^l[m, n] = u U + v V + w W (Ivanic & Ruedenberg 1996 Tables 1–2, 1998 errata)
    is bilinear in M¹ and M^{l−1}, and u, v, w factor into an m-part times 1/√denom(n), so
        M^l = (Σ_{i∈{−1,0,1}} C_i · M^{l−1} · G_i) · diag(s),   G_i = Σ_j M¹[i, j] K_j,
    with C_i (2l+1, 2l−1) the m-dependent weights of P(i, l, a, ·), K_j (2l−1, 2l+1) the column
    placements of P (Table 2: b = ±l mix M¹[i, ±1], interior b uses M¹[i, 0]; applied directly in
    `sh_rotation_blocks`) and s_n = 1/√denom(n), denom = (l+n)(l−n) for |n| < l else 2l(2l−1).
    Returns C (3, 2l+1, 2l−1) indexed by i+1 and s (2l+1,).
    """
    C = np.zeros((3, 2 * l + 1, 2 * l - 1))

    def add(i: int, m: int, a: int, val: float) -> None:
        if abs(a) <= l - 1 and val != 0.0:
            C[i + 1, m + l, a + l - 1] += val

    for m in range(-l, l + 1):
        am = abs(m)
        d = 1.0 if m == 0 else 0.0
        u = math.sqrt((l + m) * (l - m))
        v = 0.5 * math.sqrt((1 + d) * (l + am - 1) * (l + am)) * (1 - 2 * d)
        w = -0.5 * math.sqrt((l - am - 1) * (l - am)) * (1 - d) if am < l - 1 else 0.0
        add(0, m, m, u)                                   # U = P(0, m, n)
        if m == 0:                                        # V
            add(1, m, 1, v)
            add(-1, m, -1, v)
        elif m > 0:
            d1 = 1.0 if m == 1 else 0.0
            add(1, m, m - 1, v * math.sqrt(1 + d1))
            add(-1, m, -m + 1, -v * (1 - d1))
        else:
            d1 = 1.0 if m == -1 else 0.0
            add(1, m, m + 1, v * (1 - d1))
            add(-1, m, -m - 1, v * math.sqrt(1 + d1))
        if m > 0:                                         # W (zero for m = 0)
            add(1, m, m + 1, w)
            add(-1, m, -m - 1, w)
        elif m < 0:
            add(1, m, m - 1, w)
            add(-1, m, -m + 1, -w)
    n = np.arange(-l, l + 1)
    denom = np.where(np.abs(n) < l, (l + n) * (l - n), 2 * l * (2 * l - 1)).astype(float)
    return C, 1.0 / np.sqrt(denom)


@functools.lru_cache(maxsize=None)
def _row_gathers(l: int):
    """C_i of `_band_tables` as ≤ 2 (index, weight) pairs per row: idx (3, 2, 2l+1), wt (3, 2, 2l+1)."""
    C, _ = _band_tables(l)
    idx = np.zeros((3, 2, 2 * l + 1), dtype=np.int64)
    wt = np.zeros((3, 2, 2 * l + 1))
    for i in range(3):
        for m in range(2 * l + 1):
            nz = np.nonzero(C[i, m])[0]
            assert len(nz) <= 2
            for k, a in enumerate(nz):
                idx[i, k, m], wt[i, k, m] = a, C[i, m, a]
    return idx, wt


def sh_rotation_blocks(R: Tensor, order: int) -> list[Tensor]:
    """Per-band SH rotation blocks.

    Args:
        R: (B, 3, 3) or (3, 3) rotation matrices (orthonormal, det +1; not checked).
        order: n ≥ 1.
    Returns:
        list of n tensors, band l: (B, 2l+1, 2l+1) (or (2l+1, 2l+1) for a single R), indexed
        [m + l, m' + l].
    """
    if not isinstance(order, int) or order < 1:
        raise ValueError(f"order must be an int >= 1, got {order!r}")
    Rb, single = _check_R(R)
    B, dt, dev = Rb.shape[0], Rb.dtype, Rb.device
    p = torch.tensor(_PERM, device=dev)
    blocks = [torch.ones(B, 1, 1, dtype=dt, device=dev)]
    if order > 1:
        blocks.append(Rb[:, p][:, :, p])
        r1 = blocks[1]
    for l in range(2, order):
        # M^l = (Σ_i C_i M^{l−1} G_i) diag(s) (see `_band_tables`), with the sparse C_i applied as
        # row gathers and G_i as column placement (interior: M¹[i,0]; ends: M¹[i,±1] mixes).
        idx, wt = _row_gathers(l)
        _, sc = _band_tables(l)
        idx = torch.as_tensor(idx, device=dev)
        wt = torch.as_tensor(wt, dtype=dt, device=dev)
        prev = blocks[l - 1]                                             # (B, 2l−1, 2l−1)
        out = torch.zeros(B, 2 * l + 1, 2 * l + 1, dtype=dt, device=dev)
        for i in range(3):
            X = (wt[i, 0][None, :, None] * prev[:, idx[i, 0]]
                 + wt[i, 1][None, :, None] * prev[:, idx[i, 1]])          # (B, 2l+1, 2l−1)
            rm, r0, rp = (r1[:, i, j, None] for j in range(3))           # M¹[i, −1 / 0 / +1]
            out[:, :, 1:-1] += r0[..., None] * X
            first, last = X[:, :, 0], X[:, :, -1]
            out[:, :, -1] += rp * last - rm * first                      # n = l
            out[:, :, 0] += rp * first + rm * last                       # n = −l
        blocks.append(out * torch.as_tensor(sc, dtype=dt, device=dev))
    return [b[0] for b in blocks] if single else blocks


def sh_rotation_matrix(R: Tensor, order: int) -> Tensor:
    """Block-diagonal SH rotation matrix.

    Args:
        R: (B, 3, 3) or (3, 3).
        order: n ≥ 1.
    Returns:
        (B, n², n²) (or (n², n²)) with c' = M c the coefficients of f'(d) = f(Rᵀd).
    """
    blocks = sh_rotation_blocks(R, order)
    single = blocks[0].ndim == 2
    Bs = [b.unsqueeze(0) for b in blocks] if single else blocks
    B = Bs[0].shape[0]
    n2 = order * order
    M = torch.zeros(B, n2, n2, dtype=Bs[0].dtype, device=Bs[0].device)
    for l, b in enumerate(Bs):
        s = l * l
        M[:, s:s + 2 * l + 1, s:s + 2 * l + 1] = b
    return M[0] if single else M


def rotate_coeffs(coeffs: Tensor, R: Tensor) -> Tensor:
    """Coefficients of the rotated function f'(d) = f(Rᵀ d), applied band by band.

    Args:
        coeffs: (n²,), (n², C) or (B, n², C) SH coefficients.
        R: (3, 3) or (B, 3, 3) rotations (a batch of R with unbatched coeffs rotates the same
            coefficients by each R → (B, n², C)).
    Returns:
        rotated coefficients: (n²,) / (n², C) for a single R, else (B, n², C) ((B, n²) for 1-D
        coeffs).
    """
    one_d = coeffs.ndim == 1
    c = coeffs.unsqueeze(-1) if one_d else coeffs
    if c.ndim not in (2, 3):
        raise ValueError(f"coeffs must have shape (n²,), (n², C) or (B, n², C), got {tuple(coeffs.shape)}")
    K = c.shape[-2]
    n = math.isqrt(K)
    if n * n != K or n == 0:
        raise ValueError(f"coeffs must have n² entries along the coefficient dim, got {K}")
    Rb, single = _check_R(R.to(c.dtype) if R.is_floating_point() else R)
    if c.ndim == 3 and not (Rb.shape[0] == c.shape[0] or Rb.shape[0] == 1):
        raise ValueError(f"batch of R ({Rb.shape[0]}) does not match batch of coeffs ({c.shape[0]})")
    blocks = sh_rotation_blocks(Rb.to(c.dtype), n)
    cb = c if c.ndim == 3 else c.unsqueeze(0)
    out = torch.cat([blocks[l] @ cb[:, l * l:(l + 1) * (l + 1)] for l in range(n)], dim=1)
    if single and c.ndim == 2:
        out = out[0]
    return out.squeeze(-1) if one_d else out
