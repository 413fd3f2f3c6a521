"""A lighting's coefficient table for a new Phong exponent, and the plane split, each in one C call (sessions 44-45,
zh44 / zh45; `ZHShadow.native_light_table`, `ZHShadow.one_split`).

`runtime.table`(light, α) at orders ≤ `runtime.MONOMIAL_MAX_ORDER` is ``((F(α) @ A_b).view(K·n², n²) @
light.double()).view(K, n²·C).float()``: F(α) the exact Phong factors of the B = 2n − 1 bands (`core.zh.phong_factors`,
a Python loop into numpy, then a tensor), A_b (B, K·n²·n²) float64 the kept band parts of the operator
(`runtime._band_operators`, 0.7 MB at order 4), then a (K·n², n²) @ (n², C) product and two dtype conversions. A VB
frame (every frame a new exponent in the perf suite, whose cells each run one 5-frame sequence) builds one such
table, a VBL frame two (the diffuse one for its new lighting too): ~0.29 ms of serial Python, numpy and torch in a
frame with the caches cold (`python -m benchmarks.zh44_sections VB`: `rt.table` 0.287 ms median of 24 frames, 1
thread) for a few hundred kflop. zh43p's `light_table` (session 43, not merged) made the last product a C call but
kept F(α) and F @ A_b in torch, and its A/B repeated the same frames (`--repeat 24`): a VB frame's table was made in
the first repeat only.

Here, one call: F(α) by the same recurrence in double (F_0 = 1, F_1 = (s + 1)/(s + 2), F_l = F_{l−2} (s − l + 2)/(s + l
+ 1), the same operations in the same order, no contraction: the same bits as `phong_factors`), then per row r of
the operator a_r = Σ_b F_b A_b[r] (float64, b in order) and each output Σ_i a_r[i] L[i, c] (float64, i in order,
multiply-adds fused), rounded once to float32. Float32 round-off against `runtime.table` at most (float64 sums in
another order than BLAS's: an output can round to the neighbouring float32 only at a tie; tests). The diffuse
table (α = 1, its operator kept by `runtime._table_operator_b`'s cache) goes through the same call with B = 1, F = 1.

Below, the plane split in one call (`split`). Session 44 measured both at 1 thread only (0.98-1.04x: not merged);
session 45 (zh45) took them for their effect at 2 threads, where each serial step is paid in full while the
second thread waits: wall time, same process, alternating, harness-like frames (`benchmarks.zh45_harness_ab
--threads 2`, 120 frames a side): VB 1.059x, VBL 1.052x (without the table, ``native_light_table`` off: 1.017x,
1.030x), P 1.018x; A/A 0.99-1.01x. The images were the same bits in every A/B frame.
"""
from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from methods.zh_shadow import native as zn
from methods.zh_shadow import native_threaded as z39

_I, _P, _D = ctypes.c_int64, ctypes.c_void_p, ctypes.c_double

_SOURCE = r"""
#include <stdint.h>
#include <math.h>

/* out (R, C) float32: row r = (float)(sum_i a_r[i] L[i, c]) with a_r = sum_b F_b A[b, r, :] (A (B, R, n2) float64),
   F = phong factors of alpha over B bands when use_alpha (the recurrence of `core.zh.phong_factors`), else F_0 = 1
   (B must be 1). Returns 0, or 1 (a shape the buffers below do not hold: nothing written). The rows split over nt
   threads (zh45: each row one thread's, the same operations: the same bits at any thread count). */
int64_t zh44_table(int64_t B, double alpha, int64_t use_alpha, const double *A, int64_t R, int64_t n2, int64_t C,
                   const float *L, float *out, int64_t nt) {
    double F[64], l[256];
    if (B < 1 || B > 64 || n2 < 1 || n2 > 64 || C < 1 || n2 * C > 256 || (!use_alpha && B != 1)) return 1;
    F[0] = 1.0;
    if (use_alpha) {
        const double s = alpha;
        if (B > 1) F[1] = (s + 1.0) / (s + 2.0);
        for (int64_t b = 2; b < B; ++b) F[b] = F[b - 2] * ((s - (double)b) + 2.0) / ((s + (double)b) + 1.0);
    }
    for (int64_t i = 0; i < n2 * C; ++i) l[i] = (double)L[i];
    const int64_t stride = R * n2;
#pragma omp parallel for num_threads(nt) schedule(static) if(nt > 1)
    for (int64_t r = 0; r < R; ++r) {
        double a[64];
        const double *ar = A + r * n2;
        for (int64_t i = 0; i < n2; ++i) a[i] = F[0] * ar[i];
        for (int64_t b = 1; b < B; ++b) {
            const double fb = F[b], *ab = ar + b * stride;
            for (int64_t i = 0; i < n2; ++i) a[i] = fma(fb, ab[i], a[i]);
        }
        for (int64_t c = 0; c < C; ++c) {
            double s = 0.0;
            for (int64_t i = 0; i < n2; ++i) s = fma(a[i], l[i * C + c], s);
            out[r * C + c] = (float)s;
        }
    }
    return 0;
}
"""
_SIGNATURES = {"zh44_table": [_I, _D, _I, _P, _I, _I, _I, _P, _P, _I]}

# operator rows a thread takes at least (zh45: each row B · n² + n² · C multiply-adds, its B · n² doubles read)
MIN_TABLE_ROWS_PER_THREAD = 256

def _lib():
    """The table's library or None (`native.switched_load`)."""
    lib = zn.switched_load("zh44_table", _SOURCE, _SIGNATURES, "-fopenmp", "-ffp-contract=off")
    if lib is not None:
        lib.zh44_table.restype = ctypes.c_int64
    return lib


def light_table(A: Tensor, light: Tensor, alpha: float | None) -> Tensor | None:
    """(K, n²·C) float32 table of ``light`` (n², C) float32 from A: with ``alpha``, A = `runtime._band_operators`
    (B, K·n²·n²) float64 and the table is `runtime.table`(light, alpha)'s; without, A = the operator itself (K·n², n²)
    float64 (`runtime._table_operator_b`'s) — float32 round-off against `runtime.table` — or None where the call does
    not run (no library, other dtypes, layouts or shapes)."""
    lib = _lib()
    if lib is None or light.dtype != torch.float32 or A.dtype != torch.float64 or light.dim() != 2 \
            or A.device.type != "cpu" or light.device.type != "cpu" or not A.is_contiguous() \
            or not light.is_contiguous():
        return None
    n2, C = int(light.shape[0]), int(light.shape[1])
    if alpha is None:
        if A.dim() != 2 or A.shape[1] != n2:
            return None
        B, R = 1, int(A.shape[0])
    else:
        if A.dim() != 2 or A.shape[1] % (n2 * n2):
            return None
        B, R = int(A.shape[0]), int(A.shape[1]) // n2
    if n2 == 0 or R % n2:
        return None
    out = torch.empty(R // n2, n2 * C, dtype=torch.float32)
    nt = max(1, min(torch.get_num_threads(), R // MIN_TABLE_ROWS_PER_THREAD))
    if lib.zh44_table(B, 0.0 if alpha is None else float(alpha), int(alpha is not None), A.data_ptr(), R, n2, C,
                      light.data_ptr(), out.data_ptr(), nt) != 0:
        return None
    return out


# -- the plane split in one call ---------------------------------------------------------------------------------
# `ZHShadow._fused_planes` finds its plane and the samples off it by three threaded C calls with Python between
# them: `native_threaded.screen8` (every 16th normal against 8 candidates), `runtime.first_plane` over
# `native.plane_mask` (the mask of the first screened candidate's normal, its counts), then
# `native_threaded.rest_lut` (the second plane's screen over the samples off the mask and the vertices their faces
# reference) — three OpenMP regions, ~0.7 ms of a ~3.8 ms VB frame at 1 thread with the caches cold
# (`benchmarks.zh44_sections`), plus the glue. `split` does the same in ONE region: the screen, a barrier, the
# candidate, the mask and its per-thread counts, a barrier, the rest walk (`native_threaded`'s, the ranks from the
# per-thread zero counts of the mask) — the same integer counts, mask, lut and vertex list. Where the first
# screened candidate's full count falls short or a sample is out of range (the old search would go on to the next
# candidate or give up), it reports that and the caller runs the old calls.
#
# `native_threaded`'s one-thread walk over the samples off the mask (`walk`) and `native.plane_mask`'s two loops over a
# thread's range (`zh37v_plane_mask`), their text taken from those sources: the same code in the split
_WALK = z39._SOURCE[z39._SOURCE.index("/* One thread's range"):z39._SOURCE.index("    return j;\n}\n") + len("    return j;\n}\n")]
_MASK_LOOPS = zn._PMASK_SOURCE[zn._PMASK_SOURCE.index("        if (!hit) {"):zn._PMASK_SOURCE.index("        cnt[3 * k] = ne;")]
_SPLIT_SOURCE = r"""
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif
""" + _WALK + r"""
/* st (out, 24 int64): [0] status (0 ok: the first screened candidate's mask made and walked; 1 no candidate passes
   the screen; 2 its count < min_points or a sample out of range: nothing trusted but st[1..]), [1] the candidate
   (0..7), [2] the mask's count, [3] its samples in a specular region, [4] m = P - count, [5] rest screen made
   (1) / not asked (0) / failed (-1), [6..14) its 8 counts, [14] lut vertices (>= 0) or -1 (not asked or out of
   range), [15..23) the 8 screen counts of the first pass. scratch: 16 * (nt + 1) int64. */
void zh44_split(int64_t P, const float *nrm, const int64_t *region, const uint8_t *spec, int64_t R,
                const uint8_t *hit, int64_t min_points, int64_t screen_min, int64_t do_lut, const int64_t *face,
                const int32_t *F, int64_t M, int64_t N, int64_t nt, uint8_t *mask, int32_t *lut, int64_t *idx,
                int64_t *scratch, int64_t *st) {
    uint64_t bits = 0;
    for (int64_t r = 0; r < R && r < 64; ++r) bits |= (uint64_t)(spec[r] != 0) << r;
    const uint64_t R_ = (uint64_t)R;
    for (int i = 0; i < 24; ++i) st[i] = 0;
    st[14] = -1;
    int64_t cand = -1, m = 0, ns = 0, screen = 0, do_walk = 0, lut_bad = 0;
    float a = 0.f, b = 0.f, c = 0.f;
    float *sub = NULL;
    float cn[24];
    int64_t rank[8];
    int64_t *tc = scratch;   /* per thread k: tc[16 k + 0..8) screen counts, +8 matches, +9 in spec, +10 bad,
                                +11 zeros, +12 lut bad */
#pragma omp parallel num_threads(nt) if(nt > 1)
    {
#ifdef _OPENMP
        const int64_t k = omp_get_thread_num(), T = omp_get_num_threads();
#else
        const int64_t k = 0, T = 1;
#endif
        int64_t *my = tc + 16 * k;
        /* 1. the screen: every 16th normal against those of the samples c P / 8 (`zh39s_screen8`) */
        {
            float x8[8], y8[8], z8[8];
            for (int q = 0; q < 8; ++q) {
                const int64_t s = q * P / 8;
                x8[q] = nrm[3 * s]; y8[q] = nrm[3 * s + 1]; z8[q] = nrm[3 * s + 2];
            }
            const int64_t nj = (P + 15) / 16, i0 = nj * k / T, i1 = nj * (k + 1) / T;
            int64_t n8[8] = {0, 0, 0, 0, 0, 0, 0, 0};
            for (int64_t i = i0; i < i1; ++i) {
                const float *x = nrm + 3 * 16 * i;
                for (int q = 0; q < 8; ++q) n8[q] += (x[0] == x8[q]) & (x[1] == y8[q]) & (x[2] == z8[q]);
            }
            for (int q = 0; q < 8; ++q) my[q] = n8[q];
        }
#pragma omp barrier
#pragma omp single
        {
            for (int q = 0; q < 8; ++q) {
                int64_t s = 0;
                for (int64_t t = 0; t < T; ++t) s += tc[16 * t + q];
                st[15 + q] = s;
                if (cand < 0 && s * 32 >= min_points) cand = q;
            }
            if (cand >= 0) {
                const int64_t s = cand * P / 8;
                a = nrm[3 * s]; b = nrm[3 * s + 1]; c = nrm[3 * s + 2];
            }
        }   /* (implicit barrier) */
        if (cand >= 0) {
            /* 2. the mask of that normal (`zh37v_plane_mask`'s loop and counts) */
            const int64_t p0 = P * k / T, p1 = P * (k + 1) / T;
            int64_t ne = 0, nsp = 0, bad = 0;
            {   /* (`zh37v_plane_mask`'s two loops, their text: `native._PMASK_SOURCE`) */
                const float *normal = nrm;
                int64_t ns = 0;
""" + _MASK_LOOPS + r"""                nsp = ns;
            }
            my[8] = ne; my[9] = nsp; my[10] = bad; my[11] = (p1 - p0) - ne; my[12] = 0;
            if (do_lut) {
                const int64_t v0 = N * k / T, v1 = N * (k + 1) / T;
                memset(lut + v0, 0, sizeof(int32_t) * (size_t)(v1 - v0));
            }
#pragma omp barrier
#pragma omp single
            {
                int64_t cnt = 0, nb = 0;
                for (int64_t t = 0; t < T; ++t) { cnt += tc[16 * t + 8]; ns += tc[16 * t + 9]; nb += tc[16 * t + 10]; }
                m = P - cnt;
                st[2] = cnt; st[3] = ns; st[4] = m;
                if (nb || cnt < min_points) st[0] = 2;
                else {
                    screen = m >= screen_min && m > 0;
                    if (screen) {
                        sub = (float *)malloc(sizeof(float) * 3 * (size_t)((m + 15) / 16));
                        if (!sub) screen = 0, st[5] = -1;
                        for (int q = 0; q < 8; ++q) rank[q] = q * m / 8;
                    }
                    do_walk = screen || do_lut;
                }
            }   /* (implicit barrier) */
            if (do_walk) {
                /* 3. the samples off the mask, ranked j in p order (`zh39s_rest_lut`'s walk) */
                const int64_t ns16 = (m + 15) / 16;
                int64_t j = 0;
                for (int64_t t = 0; t < k; ++t) j += tc[16 * t + 11];
                int next = 0;
                if (screen)
                    while (next < 8 && rank[next] < j) ++next;
                int lbad = 0;   /* (`zh39s_rest_lut`'s walk over this thread's range, the same function) */
                walk(mask, hit, nrm, face, F, M, N, p0, p1, (int)screen, (int)do_lut, j, next, rank, ns16, sub, cn, lut,
                     &lbad);
                my[12] = lbad;
            }
        }
    }
    if (cand < 0) { st[0] = 1; return; }
    st[1] = cand;
    if (st[0] != 0) { free(sub); return; }
    if (screen) {
        const int64_t ns16 = (m + 15) / 16;
        for (int q = 0; q < 8; ++q) {
            int64_t s = 0;
            for (int64_t i = 0; i < ns16; ++i)
                s += (sub[3 * i] == cn[3 * q]) & (sub[3 * i + 1] == cn[3 * q + 1]) & (sub[3 * i + 2] == cn[3 * q + 2]);
            st[6 + q] = s;
        }
        st[5] = 1;
    }
    free(sub);
    if (do_lut) {
        for (int64_t t = 0; t < nt; ++t) lut_bad |= tc[16 * t + 12];
        if (!lut_bad) {
            int64_t r = 0;
            for (int64_t i = 0; i < N; ++i) {
                if (lut[i]) { idx[r] = i; lut[i] = (int32_t)r; ++r; }
                else lut[i] = -1;
            }
            st[14] = r;
        }
    }
}
"""
_SPLIT_SIGNATURES = {"zh44_split": [_I, _P, _P, _P, _I, _P, _I, _I, _I, _P, _P, _I, _I, _I, _P, _P, _P, _P, _P]}

def _split_lib():
    """The split's library or None (`native.switched_load`)."""
    return zn.switched_load("zh44_split", _SPLIT_SOURCE, _SPLIT_SIGNATURES, "-fopenmp")


# samples a thread takes at least (`native_threaded.MIN_SAMPLES_PER_THREAD`'s rule)
MIN_SAMPLES_PER_THREAD = 32768


def split(normal: Tensor, region: Tensor, spec: Tensor, hit: Tensor | None, min_points: int, screen_min: int,
          lut: bool, face: Tensor, F32: Tensor, N: int) -> tuple | None:
    """The plane search and the samples off its mask in one threaded call, or None where it does not run (no
    library, other dtypes or layouts, more than 64 regions). Returns (status, candidate, mask (P,) bool, count,
    in-specular count, m, rest screen (8 counts) or None, (idx (r,) int64, lut (N,) int32) or None, the first
    screen's 8 counts): status 0 — ``mask`` is `native.plane_mask`'s for the normal of sample candidate·P/8, the
    first whose screen count ·32 >= ``min_points``, with its count >= ``min_points`` and every sample in range; the
    rest screen is `native_threaded.rest_lut`'s (made where m >= ``screen_min``), the lut its (made where ``lut``;
    None where a face or corner is out of range); 1 — no candidate passes the screen; 2 — that candidate's count
    falls short or a sample is out of range (then nothing but the counts is meaningful: the caller's old calls)."""
    lib = _split_lib()
    if lib is None or spec.dim() != 1 or spec.shape[0] > 64:
        return None
    return _run(lib.zh44_split, spec.to(torch.uint8).contiguous(), {}, normal, region, hit, min_points, screen_min, lut,
                face, F32, N)


def _run(fn, sp: Tensor, bufs: dict, normal: Tensor, region: Tensor, hit: Tensor | None, min_points: int,
         screen_min: int, lut: bool, face: Tensor, F32: Tensor, N: int) -> tuple | None:
    """`split`'s checks and call of ``fn`` (`zh44_split`), sp (R,) uint8 the regions' specular flags, ``bufs`` the
    status and scratch arrays kept per thread count (their values read before this returns)."""
    P = int(normal.shape[0])
    if P == 0 or normal.dtype != torch.float32 or normal.shape != (P, 3) or not normal.is_contiguous() \
            or region.dtype != torch.int64 or region.shape != (P,) or not region.is_contiguous() \
            or face.dtype != torch.int64 or face.shape != (P,) \
            or not face.is_contiguous() or F32.dtype != torch.int32 or F32.dim() != 2 or F32.shape[1] != 3 \
            or not F32.is_contiguous() or normal.device.type != "cpu" or region.device.type != "cpu" \
            or (hit is not None and (hit.dtype != torch.bool or hit.shape != (P,) or not hit.is_contiguous())):
        return None
    nt = max(1, min(torch.get_num_threads(), P // MIN_SAMPLES_PER_THREAD, 64))
    buf = bufs.get(nt)
    if buf is None:
        bufs[nt] = buf = torch.empty(24 + 16 * (nt + 1), dtype=torch.int64)   # st[0:24], scratch
    mask = torch.empty(P, dtype=torch.bool)
    base = buf.data_ptr()
    lt = torch.empty(max(N, 1), dtype=torch.int32) if lut else None
    ix = torch.empty(max(N, 1), dtype=torch.int64) if lut else None
    fn(P, normal.data_ptr(), region.data_ptr(), sp.data_ptr(), int(sp.shape[0]),
       0 if hit is None else hit.data_ptr(), int(min_points), int(screen_min), int(bool(lut)),
       face.data_ptr(), F32.data_ptr(), int(F32.shape[0]), int(N), nt, mask.data_ptr(),
       lt.data_ptr() if lut else 0, ix.data_ptr() if lut else 0, base + 8 * 24, base)
    s = list((ctypes.c_int64 * 24).from_address(base))
    rs = s[6:14] if s[5] == 1 else None
    rl = (ix[:s[14]], lt[:N]) if lut and s[14] >= 0 else None
    return s[0], s[1], mask, s[2], s[3], s[4], rs, rl, s[15:23]


class SplitBound:
    """`split` for one set of the regions' specular flags, its library resolved once (`split_bind`, zh46): per call
    the arrays' checks and the call (the same loop: the same mask, counts, lut). The library look-up, the flags'
    conversion and the status array were ~0.03 ms of serial Python a bench P frame with the caches cold. The
    switches are the caller's to read."""

    __slots__ = ("spec", "fn", "sp", "bufs")

    def __call__(self, normal: Tensor, region: Tensor, hit: Tensor | None, min_points: int, screen_min: int,
                 lut: bool, face: Tensor, F32: Tensor, N: int) -> tuple | None:
        return _run(self.fn, self.sp, self.bufs, normal, region, hit, min_points, screen_min, lut, face, F32, N)


def split_bind(spec: Tensor) -> SplitBound | None:
    """A `SplitBound` of `split`(…, ``spec``, …) (spec (R,) bool, kept as given: the caller's key), or None where
    `split` would not run for it."""
    lib = _split_lib()
    if lib is None or spec.dim() != 1 or spec.shape[0] > 64:
        return None
    b = SplitBound()
    b.spec, b.fn, b.sp, b.bufs = spec, lib.zh44_split, spec.to(torch.uint8).contiguous(), {}
    return b
