"""A new plane term's rows in one threaded C call (session 45, zh45; `ZHShadow.native_plane_terms`).

`ZHShadow._plane_term` makes, for a frame whose pose, lighting or plane changed (P, VL, VBL), u0 = v · T¹(n0) for
the rows of the regions without a specular term (`native.plane_u` per such region, whose rows fall below
`native.MIN_ROWS_PER_PLANE_U_THREAD`: one thread) and zeros for the others (``zero_``), then u = u0 ⊙ kd per region
(``torch.mul`` a region) — ~10 torch calls and one single-thread C pass, ~0.13 ms of a ~2.4 ms P frame at 2 threads
that the second thread waits through (`benchmarks.zh45_sections P --threads 2 --wall`). `plane_terms` writes both
arrays in one OpenMP region, rows split over the threads: u0's rows by `zh35p_row3`'s operations (the products and
sums apart, j ascending: ``-ffp-contract=off``), u's as one float32 product each (``torch.mul``'s) — the same bits
at any thread count.
"""
from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from methods.zh_shadow import native as zn

_I, _P = ctypes.c_int64, ctypes.c_void_p

_SOURCE = r"""
#include <stdint.h>

/* Rows i < N of region reg[i] (R regions, each on[r] 0 / 1): u0[i] = on ? v[i] (n2) . T (n2, 3) (j ascending,
   multiplies and adds apart: `zh35p_row3`) : 0; u[i, c] = u0[i, c] * kd[reg[i], c]. */
void zh45_plane_terms(int64_t N, const float *v, int64_t n2, const float *T, const int64_t *reg, int64_t R,
                      const uint8_t *on, const float *kd, float *u0, float *u, int64_t nt) {
#pragma omp parallel for num_threads(nt) schedule(static) if(nt > 1)
    for (int64_t i = 0; i < N; ++i) {
        const int64_t r = reg[i];
        float s0 = 0.f, s1 = 0.f, s2 = 0.f;
        if (on[r]) {
            const float *x = v + i * n2;
            s0 = x[0] * T[0]; s1 = x[0] * T[1]; s2 = x[0] * T[2];
            for (int64_t j = 1; j < n2; ++j) {
                s0 = s0 + x[j] * T[3 * j]; s1 = s1 + x[j] * T[3 * j + 1]; s2 = s2 + x[j] * T[3 * j + 2];
            }
        }
        u0[3 * i] = s0; u0[3 * i + 1] = s1; u0[3 * i + 2] = s2;
        const float *k = kd + 3 * r;
        u[3 * i] = s0 * k[0]; u[3 * i + 1] = s1 * k[1]; u[3 * i + 2] = s2 * k[2];
    }
}
"""
_SIGNATURES = {"zh45_plane_terms": [_I, _P, _I, _P, _P, _I, _P, _P, _P, _P, _I]}
# rows a thread takes at least (the rows are light: 16 multiply-adds and 6 stores)
MIN_ROWS_PER_THREAD = 1024


def _lib():
    """The library or None (`native.switched_load`: no compiler, ``PRTBENCH_COMPILE=0``, ``PRTBENCH_ZH_NATIVE=0``)."""
    return zn.switched_load("zh45_plane_terms", _SOURCE, _SIGNATURES, "-fopenmp", "-ffp-contract=off")


def plane_terms(v: Tensor, T: Tensor, vreg: Tensor, on: Tensor, kd: Tensor) -> tuple[Tensor, Tensor] | None:
    """(u0, u), each (N, 3) float32: u0 row i = v[i] @ T as `native.plane_u` (the same bits) where ``on[vreg[i]]``,
    else 0; u row i = u0 row i * kd[vreg[i]] (``torch.mul``'s bits) — or None where the call does not run (no
    library, other dtypes, layouts or shapes). v (N, n²), T (n², 3), kd (R, 3) float32, vreg (N,) int64 with
    values in [0, R) (the caller's `ZHShadow._region_spans` checked them), on (R,) uint8; CPU contiguous."""
    lib = _lib()
    if lib is None or v.dim() != 2 or v.shape[1] == 0 or T.shape != (v.shape[1], 3) or kd.dim() != 2 \
            or kd.shape[1] != 3 or on.shape != (kd.shape[0],) or on.dtype != torch.uint8 \
            or vreg.shape != (v.shape[0],) or vreg.dtype != torch.int64 \
            or any(t.dtype != torch.float32 for t in (v, T, kd)) \
            or any(t.device.type != "cpu" or not t.is_contiguous() for t in (v, T, kd, vreg, on)):
        return None
    N = int(v.shape[0])
    u0 = torch.empty(N, 3, dtype=torch.float32)
    u = torch.empty(N, 3, dtype=torch.float32)
    nt = max(1, min(torch.get_num_threads(), N // MIN_ROWS_PER_THREAD))
    lib.zh45_plane_terms(N, v.data_ptr(), int(v.shape[1]), T.data_ptr(), vreg.data_ptr(), int(kd.shape[0]),
                         on.data_ptr(), kd.data_ptr(), u0.data_ptr(), u.data_ptr(), nt)
    return u0, u
