"""The vertices a G-buffer's hit samples reference, by a short C loop (`methods.core.native`), with
its torch path (`referenced_mask_torch`: the fallback and the test oracle).

A vertex-shaded frame needs the radiance of the vertices the resolve reads alone: the corners of the
faces its hit samples lie on (`ZHShadow._render_vertex`). Marking them is a scatter over the P
samples' faces; torch's ``index_fill_`` / ``bincount`` over a bench G-buffer's 262,144 samples took
0.8–1.6 ms at 1 thread (not vectorised: one indexed store per sample through the generic kernel),
the loop ~0.1 ms — a P frame's saving is the per-vertex work of the front-facing vertices no sample
sees (about half of them on the bench creature)."""
from __future__ import annotations

import ctypes
import functools

import torch
from torch import Tensor

from methods.core import native

_SOURCE = r"""
#include <stdint.h>

/* vmark[v] = 1 for each corner v of a face that a hit sample lies on; fmark (M + 1) scratch, zeroed by
   the caller, as vmark (N). face (P,) int64 (a miss: hit 0), hit (P,) uint8, F (M, 3) int64. */
void referenced_vertices(const int64_t *face, const uint8_t *hit, int64_t P, const int64_t *F, int64_t M,
                         uint8_t *fmark, uint8_t *vmark)
{
    for (int64_t p = 0; p < P; p++) {         /* branch-free: a miss or a bad id marks the spare slot M */
        int64_t f = face[p];
        int ok = hit[p] & ((uint64_t)f < (uint64_t)M);
        fmark[ok ? f : M] = 1;
    }
    for (int64_t f = 0; f < M; f++) {
        if (fmark[f]) {
            vmark[F[3 * f]] = 1;
            vmark[F[3 * f + 1]] = 1;
            vmark[F[3 * f + 2]] = 1;
        }
    }
}
"""
_P, _I = ctypes.c_void_p, ctypes.c_int64
_SIGNATURES = {"referenced_vertices": [_P, _P, _I, _P, _I, _P, _P]}


@functools.lru_cache(maxsize=None)
def _kernel():
    lib = native.load("zh_referenced", _SOURCE, _SIGNATURES)
    return None if lib is None else lib.referenced_vertices


def referenced_mask_torch(F: Tensor, face: Tensor, hit: Tensor, N: int) -> Tensor:
    """(N,) bool: the vertices of the faces F (M, 3) that the hit samples (``hit`` (P,) bool) lie on
    (``face`` (P,) their face ids) — torch ops, the oracle of `referenced_mask`."""
    M = int(F.shape[0])
    fm = torch.zeros(M + 1, dtype=torch.bool, device=face.device)
    fm.index_fill_(0, torch.where(hit, face, M), True)
    vm = torch.zeros(N, dtype=torch.bool, device=face.device)
    vm.index_fill_(0, F.to(face.device).long()[fm[:M]].reshape(-1), True)
    return vm


def referenced_mask(F: Tensor, face: Tensor, hit: Tensor, N: int) -> Tensor:
    """`referenced_mask_torch` by the C loop when it is available and the arguments suit it (CPU,
    int64 faces and F, a bool hit mask), else by the torch path; the same mask."""
    fn = _kernel()
    if fn is None or face.device.type != "cpu" or face.dtype != torch.int64 or F.dtype != torch.int64 \
            or hit.dtype != torch.bool or face.dim() != 1 or hit.shape != face.shape or F.dim() != 2 \
            or F.shape[1] != 3 or F.device.type != "cpu":
        return referenced_mask_torch(F, face, hit, N)
    face, hit, F = face.contiguous(), hit.contiguous(), F.contiguous()
    fm = torch.zeros(int(F.shape[0]) + 1, dtype=torch.uint8)
    vm = torch.zeros(N, dtype=torch.bool)
    fn(face.data_ptr(), hit.data_ptr(), int(face.shape[0]), F.data_ptr(), int(F.shape[0]), fm.data_ptr(),
       vm.data_ptr())
    return vm
