"""A new env map's SH coefficients by one C pass over its texels (`methods.core.native`): the
lighting projection of the methods that project a map per frame (SH PRT's and ZH's E frames).

`project_latlong_polar` is `methods.core.sh.project_latlong_polar` (the coefficients in the map's
polar frame: per row the column integrals against the 2n azimuthal factors, then the rows weighted
by the polar factors) over the float32 texels with float64 sums, no float64 copy of the map; that
function (one float64 GEMM) is its fallback and test oracle (float64 round-off). The map's rows are
cut into parts fixed by its size (`ROWS_PER_PROJECT_PART` rows a part, at most `MAX_PROJECT_PARTS`),
the parts shared by OpenMP's team (the libgomp torch loaded) and summed in order: the same bits at
any thread count (session 31; before, the rows were split by the thread count and the float64 sums
differed between 1 and 2 threads by ~9e-16 on a 256×512 map). Written for SH PRT in session 28;
shared with ZH since session 29.
"""
from __future__ import annotations

import ctypes
import functools

import torch
from torch import Tensor

from methods.core import native

_SOURCE = r"""
#include <stdint.h>
#include <string.h>

/* `sh.project_latlong_polar` of rows [h0, h1) of the (H, W, 3) float32 map X into out (n², 3)
   float64: per row the column sums F[c][j] = Σ_w X[h, w, c] B[w, j] over the 2n factors (B (W, J)
   float64, J = 2n padded to a multiple of 4 with zeros), then out[i, c] += T[h, i] F[c][k[i]]. */
typedef double d4 __attribute__((vector_size(32), aligned(8)));
#define MAXJ 24
static void proj_rows(int64_t h0, int64_t h1, int64_t W, const float *X, const double *B, int64_t J,
                      const int64_t *k, const double *T, int64_t n2, double *out) {
    const int64_t nv = J / 4;
    for (int64_t h = h0; h < h1; ++h) {
        d4 a[3][MAXJ / 4];
        for (int64_t c = 0; c < 3; ++c)
            for (int64_t v = 0; v < nv; ++v) a[c][v] = (d4){0, 0, 0, 0};
        const float *row = X + h * W * 3;
        for (int64_t w = 0; w < W; ++w) {
            const double x0 = row[3 * w], x1 = row[3 * w + 1], x2 = row[3 * w + 2];
            const d4 *b = (const d4 *)(B + w * J);
            for (int64_t v = 0; v < nv; ++v) {
                a[0][v] += x0 * b[v]; a[1][v] += x1 * b[v]; a[2][v] += x2 * b[v];
            }
        }
        const double *t = T + h * n2;
        for (int64_t i = 0; i < n2; ++i) {
            const int64_t j = k[i];
            for (int64_t c = 0; c < 3; ++c) out[3 * i + c] += t[i] * a[c][j / 4][j % 4];
        }
    }
}

void sh_project(int64_t H, int64_t W, const float *X, const double *B, int64_t J, const int64_t *k,
                const double *T, int64_t n2, double *part, int64_t np, int64_t nt, double *out) {
    /* part (np, n², 3) zeroed by the caller: part p's rows [H p / np, H (p+1) / np), np fixed by the
       caller whatever the thread count; out (n², 3) = the parts summed in order p = 0, 1, ... */
    #pragma omp parallel for num_threads(nt) schedule(static) if(nt > 1)
    for (int64_t p = 0; p < np; ++p)
        proj_rows(H * p / np, H * (p + 1) / np, W, X, B, J, k, T, n2, part + p * n2 * 3);
    for (int64_t i = 0; i < n2 * 3; ++i) {
        double s = part[i];
        for (int64_t p = 1; p < np; ++p) s += part[p * n2 * 3 + i];
        out[i] = s;
    }
}

"""

_P, _I = ctypes.c_void_p, ctypes.c_int64
_SIGNATURES = {"sh_project": [_I, _I, _P, _P, _I, _P, _P, _I, _P, _I, _I, _P]}


def _lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call, so a
    # None met while compilation was off (a test's monkeypatch) is not kept for the process.
    # No contraction into fused multiply-adds (the bits of session 28's SH PRT library); the host's ISA
    return native.load("sh_project", _SOURCE, _SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", *native.isa_flags()))


def available() -> bool:
    """True when the C pass runs (else `project_latlong_polar` is its oracle)."""
    return _lib() is not None


ROWS_PER_PROJECT_PART = 64    # map rows a part (each part one thread's)
MAX_PROJECT_PARTS = 4         # (the parts are fixed by the map's size, not by the thread count)


def row_parts(H: int) -> tuple[int, int]:
    """(parts, threads) of a projection of an H-row map: the parts fixed by H alone (their sums in order
    give the same bits at any thread count), shared by at most torch's thread count. Also ZH's folded
    pass (`methods.zh_shadow.native.project_latlong_polar_folded`)."""
    np_ = max(1, min(MAX_PROJECT_PARTS, int(H) // ROWS_PER_PROJECT_PART))
    return np_, max(1, min(torch.get_num_threads(), np_))


@functools.lru_cache(maxsize=8)
def _project_factors(H: int, W: int, order: int) -> tuple[Tensor, Tensor, Tensor, int]:
    """`sh._latlong_polar_factors` (B (W, 2n), k, T) with B's columns padded with zeros to a multiple
    of 4 (whole 4-double vectors in `sh_project`) → (B (W, J), k, T, J), contiguous, CPU."""
    from methods.core.sh import _latlong_polar_factors

    B, k, T = _latlong_polar_factors(H, W, order, torch.device("cpu"))
    J = -(-B.shape[1] // 4) * 4
    Bp = torch.zeros(W, J, dtype=torch.float64)
    Bp[:, :B.shape[1]] = B
    return Bp, k.to(torch.int64).contiguous(), T.contiguous(), J


def project_latlong_polar(image: Tensor, order: int) -> Tensor:
    """`methods.core.sh.project_latlong_polar(image, order)` (n², 3) float64 by one C pass over the
    float32 (H, W, 3) texels (float64 sums: the same integrals in another order, float64 round-off;
    no float64 copy of the map), or by that function (its oracle) where the loop does not run (no
    compiler, ``PRTBENCH_COMPILE=0``, not a float32 (H, W, 3) CPU map, order > 12)."""
    from methods.core.sh import project_latlong_polar as oracle

    lib = _lib()
    if (lib is None or image.device.type != "cpu" or image.dtype != torch.float32 or image.dim() != 3
            or image.shape[2] != 3 or 2 * order > 24):
        return oracle(image, order)
    H, W, _ = image.shape
    B, k, T, J = _project_factors(int(H), int(W), int(order))
    X = image.contiguous()
    n2 = order * order
    np_, nt = row_parts(int(H))
    part = torch.zeros(np_, n2, 3, dtype=torch.float64)
    out = torch.empty(n2, 3, dtype=torch.float64)
    lib.sh_project(int(H), int(W), X.data_ptr(), B.data_ptr(), J, k.data_ptr(), T.data_ptr(), n2, part.data_ptr(),
                   np_, nt, out.data_ptr())
    return out
