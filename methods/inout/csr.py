"""c = T̃ · L (Mahajan 2008 eq. 4's dot product, per vertex, term and colour) as one streaming
pass over the CSR arrays of T̃: a 20-line C loop compiled on first use and called through ctypes.

Why not ``torch.sparse`` (the product `fast.light_rows` used before, and keeps as the fallback):
torch's CPU CSR × dense product is MKL's ``mkl_sparse_s_mm``, which with 4 dense columns (L padded,
`fast.light_rows`) ran at 6–8 GB/s of T̃'s bytes on this machine where one streaming read of the
same values and column indices runs at 16–19 GB/s, and three CSR × vector products (one per colour)
each ran at the read's speed (55 ms for the three against 37–40 ms for the 4-column product, creature
bench, 4.9·10³ vertices × K = 30, 3.8·10⁷ kept coefficients, 1 thread, process CPU time). The loop
here reads each coefficient and its column once, multiplies the 4-float row of L (16 B, aligned: L
is 24 KB, L1-resident) by the value and accumulates it in one of 4 independent 4-wide accumulators
(one accumulator chains each multiply-add on the previous: 4 cycles of latency per coefficient,
which is MKL's speed): 21–23 ms for the same product, 13–14 GB/s (1.7–1.8×; GCC vector extensions
at the x86-64 baseline, SSE2 — built with ``-march=native`` (AVX2, 8 coefficients per iteration,
intrinsics) it was no faster: the loop is at the memory's speed, not the instructions'). An Inductor
kernel cannot express it (a reduction over data-dependent row extents); ``embedding_bag`` with
per-sample weights was 1.7× slower than MKL (``fast`` docstring).

Each output row is summed by one thread in one order, whatever the thread count: ``torch.get_num_threads()``
threads each take a contiguous range of rows of about equal coefficient counts, on OpenMP's team (the
libgomp torch loaded; session 27 — a Python thread pool before, whose hand-off waits for a core the
OpenMP workers spin on: `methods.core.gouraud`'s measurement), so results are bit for bit the same at
1 and 2 threads (``tests/methods/test_threads.py``).

The library is built and loaded by `methods.core.native.load` (once per source text and compiler,
from a private per-user directory; without a C compiler, or with ``PRTBENCH_COMPILE=0``,
`available` is False and callers use the torch product). The same library holds a second loop,
`hit_face_mask` (the vertex shading's referenced faces: one pass over a frame's samples, 3.4× the
compiled pass and histogram it replaces when those are unavailable). The CSR loop reads without
bounds checks: `check_csr` validates the arrays once (column indices in [0, D), row pointers
non-decreasing and within the arrays), when ``fast.build_region`` builds a region.
"""
from __future__ import annotations

import ctypes
import torch
from torch import Tensor

from methods.core import native

__all__ = ["available", "check_csr", "csr_blocks4", "csr_dense4", "hit_face_mask"]

_SOURCE = r"""
#include <stdint.h>
typedef float v4 __attribute__((vector_size(16)));

/* For each block i < n, the K rows first[i] <= r < first[i] + K of the CSR (crow, col, val):
   out[i * K + r - first[i], 0:4] = sum over e in [crow[r], crow[r + 1]) of val[e] * L4[col[e], 0:4].
   L4 (D, 4) and out (n * K, 4) 16-byte aligned. 4 accumulators, combined as (s0 + s1) + (s2 + s3). */
void csr_blocks4(const int64_t* crow, const int64_t* first, int64_t n, int64_t K, const int32_t* col,
                 const float* val, const float* L4, float* out) {
    const v4* L = (const v4*)L4;
    v4* o = (v4*)out;
    for (int64_t i = 0; i < n; ++i) {
        for (int64_t r = first[i]; r < first[i] + K; ++r) {
            const int64_t b = crow[r + 1];
            int64_t e = crow[r];
            v4 s0 = {0, 0, 0, 0}, s1 = s0, s2 = s0, s3 = s0;
            for (; e + 4 <= b; e += 4) {
                s0 += val[e] * L[col[e]];
                s1 += val[e + 1] * L[col[e + 1]];
                s2 += val[e + 2] * L[col[e + 2]];
                s3 += val[e + 3] * L[col[e + 3]];
            }
            for (; e < b; ++e)
                s0 += val[e] * L[col[e]];
            *o++ = (s0 + s1) + (s2 + s3);
        }
    }
}

/* csr_blocks4 over nt contiguous ranges of blocks on OpenMP's team (the libgomp torch loaded):
   range k is blocks cuts[k] <= i < cuts[k + 1]. */
void csr_blocks4_par(const int64_t* crow, const int64_t* first, int64_t n, int64_t K, const int32_t* col,
                     const float* val, const float* L4, float* out, const int64_t* cuts, int64_t nt) {
    #pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t k = 0; k < nt; ++k) {
        const int64_t a = cuts[k], b = cuts[k + 1];
        if (b > a)
            csr_blocks4(crow, first + a, b - a, K, col, val, L4, out + 4 * K * a);
    }
    (void)n;
}

/* The faces the hits of n samples lie on and their vertices (shading "vertex"'s view, `hit_face_mask`):
   per sample i with hit[i], f = face[i] clamped into [0, M), mask[f] = 1 and bad |= face_region[f] !=
   region[i]; per sample without, one miss. Then per face f with mask[f], vmask[face_gl[j * M + f]] = 1
   for j < 3 (face_gl (3, M); an id outside [0, nv) is skipped: ``fast.FastStatic``'s are all inside).
   mask (M,) and vmask (nv,) zeroed by the caller. out[0] = misses, out[1] = bad (0 / 1), out[2] = the faces marked.
   Both passes split their range over nt threads of OpenMP's team: the marks are relaxed atomic stores
   of 1 (two threads may mark one face or vertex) and the counts are sums, so every output is the same
   at any thread count. */
void hit_face_mask(const int64_t* face, const int64_t* region, const uint8_t* hit, int64_t n,
                   const int64_t* face_region, int64_t M, const int32_t* face_gl, int64_t nv,
                   uint8_t* mask, uint8_t* vmask, int64_t* out, int64_t nt) {
    int64_t misses = 0, bad = 0, faces = 0;
    #pragma omp parallel num_threads(nt) if (nt > 1)
    {
        #pragma omp for schedule(static) reduction(+:misses) reduction(|:bad)
        for (int64_t i = 0; i < n; ++i) {
            if (!hit[i]) {
                ++misses;
                continue;
            }
            int64_t f = face[i];
            f = f < 0 ? 0 : (f >= M ? M - 1 : f);
            __atomic_store_n(mask + f, (uint8_t)1, __ATOMIC_RELAXED);
            bad |= face_region[f] != region[i];
        }
        #pragma omp for schedule(static) reduction(+:faces)
        for (int64_t f = 0; f < M; ++f) {
            if (!mask[f])
                continue;
            ++faces;
            for (int64_t j = 0; j < 3; ++j) {
                const int64_t v = face_gl[j * M + f];
                if (v >= 0 && v < nv)
                    __atomic_store_n(vmask + v, (uint8_t)1, __ATOMIC_RELAXED);
            }
        }
    }
    out[0] = misses;
    out[1] = bad;
    out[2] = faces;
}
"""
# Rows below which one thread does the product (a thread's hand-off costs more than its share).
_MIN_ROWS_PER_THREAD = 1 << 12
# Samples below which one thread finds the referenced faces (`hit_face_mask`).
_MIN_SAMPLES_PER_THREAD = 1 << 15

_I64, _P = ctypes.c_int64, ctypes.c_void_p
_SIGNATURES = {"csr_blocks4": [_P, _P, _I64, _I64, _P, _P, _P, _P],
               "csr_blocks4_par": [_P, _P, _I64, _I64, _P, _P, _P, _P, _P, _I64],
               "hit_face_mask": [_P, _P, _P, _I64, _P, _I64, _P, _I64, _P, _P, _P, _I64]}


def _kernel():
    """The compiled library (`methods.core.native.load`: built once per source and compiler, loaded
    only from a private directory) or None (the callers use the torch paths)."""
    return native.load("inout_csr", _SOURCE, _SIGNATURES, extra_flags=("-fopenmp",))


def available() -> bool:
    """True when `csr_dense4` runs the native loop (else callers use the torch product)."""
    return _kernel() is not None


def check_csr(crow: Tensor, col: Tensor, val: Tensor, D: int) -> bool:
    """Whether (crow, col, val) is a CSR the native loop may read without bounds checks: int64
    row pointers, non-decreasing, from 0 to nnz; int32 column indices in [0, D); float32 values;
    col and val contiguous, of nnz entries."""
    if crow.dtype != torch.int64 or col.dtype != torch.int32 or val.dtype != torch.float32:
        return False
    if crow.device.type != "cpu" or not (crow.is_contiguous() and col.is_contiguous() and val.is_contiguous()):
        return False
    nnz = col.numel()
    if crow.ndim != 1 or crow.numel() < 1 or val.numel() != nnz or int(crow[0]) != 0 or int(crow[-1]) != nnz:
        return False
    if bool((crow[1:] < crow[:-1]).any()):
        return False
    return nnz == 0 or (int(col.min()) >= 0 and int(col.max()) < D)


def csr_dense4(crow: Tensor, col: Tensor, val: Tensor, L4: Tensor, r0: int, r1: int) -> Tensor:
    """Rows r0 ≤ r < r1 of the CSR (crow, col, val) times L4 (D, 4) float32 → (r1 − r0, 4)
    (`csr_blocks4` of one block)."""
    if not 0 <= r0 <= r1 <= crow.numel() - 1:
        raise ValueError(f"rows [{r0}, {r1}) outside the matrix's {crow.numel() - 1}")
    return csr_blocks4(crow, col, val, L4, torch.tensor([r0], dtype=torch.int64), r1 - r0)


def csr_blocks4(crow: Tensor, col: Tensor, val: Tensor, L4: Tensor, first: Tensor, K: int) -> Tensor:
    """Blocks of K consecutive rows, block i the rows first[i] ≤ r < first[i] + K, of the CSR
    (crow, col, val) times L4 (D, 4) float32 → (n·K, 4), block-major: the native loop over
    ``torch.get_num_threads()`` contiguous ranges of blocks of about equal coefficient counts (module
    docstring). The CSR must pass `check_csr` (the caller checks once), `available` be True, and
    every block lie in the matrix (checked here)."""
    fn = _kernel()
    L4 = L4.contiguous()
    if L4.dtype != torch.float32 or L4.ndim != 2 or L4.shape[1] != 4:
        raise ValueError(f"L4 must be (D, 4) float32, got {tuple(L4.shape)} {L4.dtype}")
    first = first.to(torch.int64).contiguous()
    n = first.numel()
    out = torch.empty(n * K, 4, dtype=torch.float32)
    if n == 0 or K == 0:
        return out
    if int(first.min()) < 0 or int(first.max()) + K > crow.numel() - 1:
        raise ValueError(f"row blocks outside the matrix's {crow.numel() - 1} rows")
    nt = max(1, min(torch.get_num_threads(), n * K // _MIN_ROWS_PER_THREAD))
    cp, fp, colp, valp, Lp, op = (t.data_ptr() for t in (crow, first, col, val, L4, out))
    if nt == 1:
        fn.csr_blocks4(cp, fp, n, K, colp, valp, Lp, op)
        return out
    # nt ranges of blocks of about equal coefficient counts
    cum = (crow.index_select(0, first + K) - crow.index_select(0, first)).cumsum(0)
    cuts = torch.cat([torch.zeros(1, dtype=torch.int64),
                      torch.searchsorted(cum, torch.linspace(0, float(cum[-1]), nt + 1)[1:-1]).clamp_max(n),
                      torch.full((1,), n, dtype=torch.int64)])
    fn.csr_blocks4_par(cp, fp, n, K, colp, valp, Lp, op, cuts.data_ptr(), nt)
    return out


def hit_face_mask(face: Tensor, region: Tensor, hit: Tensor, face_region: Tensor, face_gl: Tensor,
                  nv: int) -> tuple[Tensor, int, int, bool] | None:
    """The referenced vertices of shading "vertex"'s view — those of the faces the hits of q samples
    lie on, (nv,) bool over the concatenated ids of ``face_gl`` (3, M) int32 —, the count of those
    faces, the miss count and whether a hit's face lies in another region than the sample's:
    ``fast.hit_face_counts``'s histogram reduced to what the view reads of it, by one pass of the
    native loop over the samples (each hit's face clamped into [0, M) as there), then one over the
    faces (an id outside [0, nv) is skipped; ``fast.FastStatic``'s are all inside). None when the loop
    is not available or the arrays are not (q,) int64 / bool, (M,) int64, (3, M) int32 contiguous CPU
    tensors (the caller uses the compiled pass).

    At 2+ threads (``torch.get_num_threads()``) both passes split over OpenMP's team, each thread a
    range of samples, then of faces; the outputs are the same at any thread count. One thread: 0.62–0.79
    ms on chess bench (2.6·10⁵ samples, after the suite's 0.2 s idle, process CPU). (A split over a
    Python thread pool took 9 ms on this loaded 2-core machine: its hand-off waits for a core.)"""
    fn = _kernel()
    if fn is None:
        return None
    q, M = int(face.shape[0]), int(face_region.shape[0])
    ok = (face.dtype == region.dtype == face_region.dtype == torch.int64 and hit.dtype == torch.bool and M > 0
          and face.ndim == region.ndim == hit.ndim == face_region.ndim == 1 and region.shape[0] == q == hit.shape[0]
          and face_gl.dtype == torch.int32 and face_gl.shape == (3, M)
          and all(t.device.type == "cpu" and t.is_contiguous() for t in (face, region, hit, face_region, face_gl)))
    if not ok:
        return None
    mask = torch.zeros(M, dtype=torch.bool)
    vmask = torch.zeros(nv, dtype=torch.bool)
    out = torch.zeros(3, dtype=torch.int64)
    nt = max(1, min(torch.get_num_threads(), q // _MIN_SAMPLES_PER_THREAD))
    fn.hit_face_mask(face.data_ptr(), region.data_ptr(), hit.data_ptr(), q, face_region.data_ptr(), M,
                     face_gl.data_ptr(), nv, mask.data_ptr(), vmask.data_ptr(), out.data_ptr(), nt)
    misses, bad, faces = out.tolist()
    return vmask, int(faces), int(misses), bool(bad)
