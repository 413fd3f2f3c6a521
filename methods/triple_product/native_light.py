"""A lighting change projected on the (grid frame, live triangle) pairs eq. 7 reads with a non-zero
visibility: a small C loop (built with ``cc`` through `methods.core.native.load`, called through
ctypes), the compiled general projection (`lighting.project_env` with ``tris``: `env_taps`, then
`quad_means`) as its fallback and test oracle.

Why: after a lighting change a frame projects every live fine triangle of every grid frame it looks
up (`TripleProduct.fill_lighting`; chess bench vertex L: 347 frames × 640 triangles), but a point's
eq. 7 multiplies its looked-up frames' lighting by its blended visibility, which is exactly 0 on a
third or more of the live triangles (`native` module docstring). A (frame, triangle) pair no point
reads with a non-zero visibility and a non-zero weight is only ever multiplied by 0; it is not
compulsory (`fast_eval.frame_cost` counts only the read pairs: `nonzero_reads`' "pairs", 157,505 of
222,080 on chess vertex L). An Inductor loop runs over dense (frames, triangles) blocks, so the pairs
are projected here, one pair (4^s samples) at a time:

* `need`: the pairs the points read — per point the OR of its visibility rows' non-zero bit sets
  (`vis_bits`, one bit per live triangle, built once per table) over the grid rows it looks up with a
  non-zero weight (a point whose rows and non-zero flags equal the previous point's is skipped; one
  with the previous point's visibility rows reuses its OR), the points split over the threads;
* `project`: each pair's samples with the general kernel's float32 operations one for one (the
  rotation folded with the emitter's as ``R @ T`` by the same `torch.mm`, `lighting.atan2_f32` /
  `acos_f32`, `latlong.quad_taps`, the quad rows × `quad_lane_weights` × the sample weight, summed in
  `lighting._tree_sum`'s order, then the 4 lanes of each channel), built with ``-ffp-contract=off`` as
  Inductor builds its kernels: the same fine values bit for bit (tested). On a CPU with AVX-512
  (`_wide_flags`) the 16-sample pairs run four at a time in 16-lane vectors (`zproject16`: the AVX2
  loop waited on its taps' latency; 1.4x faster alone, the same bits);
* `comb_pairs`: a map turned about +Y only (E frames, `lighting.comb_pairs_ok`): the comb path's
  sums (`lighting.comb_means`, whose compiled loop summed every frame of the grid and, per output,
  entered a parallel region) for the 8-frame groups holding a read pair only, the one-thread sums bit
  for bit; `comb_pairs_uv` (what `lighting.project_pairs` runs, session 32) makes each listed item's
  taps in the loop with `lighting.comb_taps`' float64 / float32 / int32 operations (the same bits)
  instead of running that compiled pass over every base row and live triangle first (creature bench
  E: 6,242 of 11,152 items listed; the pass was ~0.9 ms of a ~12 ms frame at 1 thread);
* `box`: the E frame's prefilter of a new probe (`lighting.box_filtered`: float64 row then column
  sums in the torch passes' order, the same texels bit for bit) in one pass (~0.4 -> 0.1 ms).
  Creature / chess bench vertex E with both, 1 thread, same process: 1.08x / 1.06x.

Pairs not needed keep the finite values of the table's previous lighting (`TripleProduct._spare_tables`)
or zeros, and are read only with an exact 0 (visibility or weight): the image is the same bit for bit
(tested). Pairs are split in contiguous ranges over ``torch.get_num_threads()`` threads of OpenMP's
team (each pair's sums in one thread: the values do not depend on the thread count).
Without a compiler, with ``PRTBENCH_COMPILE=0`` or ``PRTBENCH_TP_NATIVE=0``, `available` is False and
the frame projects whole live rows with the compiled kernels as before.
"""
from __future__ import annotations

import ctypes
import functools

import torch
from torch import Tensor

from methods.core import native
from methods.triple_product import native as tp_native

__all__ = ["available", "vis_bits", "need", "take", "comb_scatter", "comb_pairs", "comb_pairs_uv", "project", "box"]

_TAP_BODY = r"""
/* TAP_BODY: `tap` for NV vectors of samples at once (vector k in the frame of mk[k]), written out over
   the ISA's macros (VF / VI / VM float, int32 and mask vectors, V* / I* their operations; defined
   before each copy, undefined after it) — one body, compiled as tap4x8 (AVX2, 4 × 8 samples) and as
   ztap (AVX-512, NZ pairs of 16 samples): GCC's vectorised tap evaluated the acos polynomial twice
   and the atan one three times (once per if-converted branch). The same float32 operations one for
   one as `tap`, each select a blend of both sides with the scalar compare's semantics (max(x, y) is
   x > y ? x : y, min(x, y) x < y ? x : y, ordered non-signalling compares: NaN false). Statement by
   statement over the NV vectors: NV independent chains in flight (AVX2: one pair's two at a time
   measured 1.13x slower, eight spilled; AVX-512: four 16-lane chains in 32 registers). */
static inline void TAP_FN(const VF* cx, const VF* cy, const VF* cz, const float* const* mk,
                          VF H1, VF Wf, VF hw, VI H2, VI W1, VI Wp, VI* idx, VF* fx, VF* fy) {
    const VF sign = VSET(-0.0f), one = VSET(1.0f), zero = VZERO();
    VF d0[NV], d1[NV], d2[NV], yv[NV], a[NV], z[NV], s[NV], q[NV], p[NV], r[NV], v[NV];
    VF xx[NV], ax[NV], ay[NV], mn[NV], mx[NV], num[NV], den[NV], t[NV], tz[NV], pq[NV], ra[NV], u[NV], x[NV], y[NV];
    VM big[NV], c[NV];
    VI ix[NV], iy[NV];
#define KV for (int k = 0; k < NV; ++k)
    KV d0[k] = VADD(VADD(VMUL(cx[k], VSET(mk[k][0])), VMUL(cy[k], VSET(mk[k][3]))), VMUL(cz[k], VSET(mk[k][6])));
    KV d1[k] = VADD(VADD(VMUL(cx[k], VSET(mk[k][1])), VMUL(cy[k], VSET(mk[k][4]))), VMUL(cz[k], VSET(mk[k][7])));
    KV d2[k] = VADD(VADD(VMUL(cx[k], VSET(mk[k][2])), VMUL(cy[k], VSET(mk[k][5]))), VMUL(cz[k], VSET(mk[k][8])));
    /* acos_f32 of clamp(d1, -1, 1) / pi */
    KV yv[k] = VMIN(VMAX(d1[k], VSET(-1.0f)), one);
    KV a[k] = VANDN(sign, yv[k]);
    KV big[k] = VGT(a[k], VSET(0.5f));
    KV z[k] = VSEL(big[k], VSUB(VSET(0.5f), VMUL(a[k], VSET(0.5f))), VMUL(a[k], a[k]));
    KV s[k] = VSEL(big[k], VSQRT(z[k]), a[k]);
    KV q[k] = VMUL(VADD(VMUL(VADD(VMUL(VADD(VMUL(VADD(VMUL(z[k], VSET(0.042163199048)), VSET(0.024181311049)), z[k]),
                                         VSET(0.045470025998)), z[k]), VSET(0.074953002686)), z[k]),
                       VSET(0.16666752422)), z[k]);
    KV p[k] = VADD(VMUL(q[k], s[k]), s[k]);
    KV r[k] = VSEL(big[k], VMUL(p[k], VSET(2.0f)), VSUB(VSET(1.5707963267948966), p[k]));
    KV r[k] = VSEL(VLT(yv[k], zero), VSUB(VSET(3.141592653589793), r[k]), r[k]);
    KV v[k] = VMUL(r[k], VSET(0.3183098861837907));
    /* atan2_f32(d0, -d2) / 2 pi */
    KV xx[k] = VXOR(d2[k], sign);
    KV ax[k] = VANDN(sign, xx[k]);
    KV ay[k] = VANDN(sign, d0[k]);
    KV mn[k] = VMIN(ax[k], ay[k]);
    KV mx[k] = VMAX(ax[k], ay[k]);
    KV c[k] = VGT(mn[k], VMUL(mx[k], VSET(0.41421356237309503)));
    KV num[k] = VSEL(c[k], VSUB(mn[k], mx[k]), mn[k]);
    KV den[k] = VSEL(c[k], VADD(mn[k], mx[k]), mx[k]);
    KV den[k] = VSEL(VGT(den[k], zero), den[k], one);
    KV t[k] = VDIV(num[k], den[k]);
    KV tz[k] = VMUL(t[k], t[k]);
    KV pq[k] = VADD(VMUL(VMUL(VSUB(VMUL(VADD(VMUL(VSUB(VMUL(tz[k], VSET(0.0805374449538)), VSET(0.138776856032)), tz[k]),
                                          VSET(0.199777106478)), tz[k]), VSET(0.333329491539)), tz[k]), t[k]), t[k]);
    KV ra[k] = VSEL(c[k], VADD(pq[k], VSET(0.7853981633974483)), pq[k]);
    KV ra[k] = VSEL(VGT(ay[k], ax[k]), VSUB(VSET(1.5707963267948966), ra[k]), ra[k]);
    KV ra[k] = VSEL(VLT(xx[k], zero), VSUB(VSET(3.141592653589793), ra[k]), ra[k]);
    KV ra[k] = VSEL(VLT(d0[k], zero), VXOR(ra[k], sign), ra[k]);
    KV u[k] = VSUB(VMUL(ra[k], VSET(0.15915494309189535)), hw);
    /* quad_taps */
    KV u[k] = VSUB(u[k], VFLOOR(u[k]));
    KV v[k] = VSUB(v[k], VFLOOR(v[k]));
    KV x[k] = VMUL(u[k], Wf);
    KV y[k] = VMUL(v[k], H1);
    KV ix[k] = IMIN(IMAX(ITRUNC(x[k]), IZERO()), W1);
    KV iy[k] = IMIN(IMAX(ITRUNC(y[k]), IZERO()), H2);
    KV idx[k] = IADD(IMUL(iy[k], Wp), ix[k]);
    KV fx[k] = VSUB(x[k], IFLOAT(ix[k]));
    KV fy[k] = VSUB(y[k], IFLOAT(iy[k]));
#undef KV
}
#undef VF
#undef VI
#undef VM
#undef NV
#undef TAP_FN
#undef VSET
#undef VMUL
#undef VADD
#undef VSUB
#undef VDIV
#undef VSQRT
#undef VMIN
#undef VMAX
#undef VANDN
#undef VXOR
#undef VFLOOR
#undef VZERO
#undef VSEL
#undef VLT
#undef VGT
#undef IZERO
#undef IMIN
#undef IMAX
#undef IMUL
#undef IADD
#undef ITRUNC
#undef IFLOAT
"""


_SOURCE = r"""
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>

/* One projection sample's footprint: lighting.env_taps (direction m^T c in the emitter frame,
   atan2_f32 / acos_f32) then latlong.quad_taps, the compiled kernel's float32 operations one for
   one (m = R T, row-major). */
static inline void tap(float cx, float cy, float cz, const float* m, float H1, float Wf, float hw,
                       int32_t H2, int32_t W1, int32_t Wp, int32_t* restrict idx, float* restrict fx,
                       float* restrict fy) {
    const float d0 = (cx * m[0] + cy * m[3]) + cz * m[6];
    const float d1 = (cx * m[1] + cy * m[4]) + cz * m[7];
    const float d2 = (cx * m[2] + cy * m[5]) + cz * m[8];
    float yv = d1 > -1.0f ? d1 : -1.0f;                       /* clamp(-1, 1) */
    yv = yv < 1.0f ? yv : 1.0f;
    const float a = fabsf(yv);
    const int big = a > 0.5f;
    const float z = big ? 0.5f - a * 0.5f : a * a;
    const float sq = sqrtf(z);
    const float s = big ? sq : a;
    const float q = ((((z * (float)0.042163199048 + (float)0.024181311049) * z + (float)0.045470025998) * z
                      + (float)0.074953002686) * z + (float)0.16666752422) * z;
    const float p = q * s + s;
    float r = big ? p * 2.0f : (float)1.5707963267948966 - p;
    r = yv < 0.0f ? (float)3.141592653589793 - r : r;
    float v = r * (float)0.3183098861837907;
    const float xx = -d2;                                     /* atan2_f32(d0, -d2) */
    const float ax = fabsf(xx), ay = fabsf(d0);
    const float mn = ax < ay ? ax : ay;
    const float mx = ax > ay ? ax : ay;
    const int c = mn > mx * (float)0.41421356237309503;
    const float num = c ? mn - mx : mn;
    const float den0 = c ? mn + mx : mx;
    const float den = den0 > 0.0f ? den0 : 1.0f;
    const float t = num / den;
    const float tz = t * t;
    const float pq = ((((tz * (float)0.0805374449538 - (float)0.138776856032) * tz + (float)0.199777106478) * tz
                       - (float)0.333329491539) * tz) * t + t;
    float ra = c ? pq + (float)0.7853981633974483 : pq;
    ra = ay > ax ? (float)1.5707963267948966 - ra : ra;
    ra = xx < 0.0f ? (float)3.141592653589793 - ra : ra;
    ra = d0 < 0.0f ? -ra : ra;
    float u = ra * (float)0.15915494309189535;
    u = u - hw;                                               /* quad_taps */
    u = u - floorf(u);
    v = v - floorf(v);
    const float x = u * Wf, y = v * H1;
    int32_t ix = (int32_t)x, iy = (int32_t)y;
    ix = ix > 0 ? ix : 0;
    ix = ix < W1 ? ix : W1;
    iy = iy > 0 ? iy : 0;
    iy = iy < H2 ? iy : H2;
    *idx = iy * Wp + ix;
    *fx = x - (float)ix;
    *fy = y - (float)iy;
}

#define MAXS 64
typedef float v8 __attribute__((vector_size(32)));
typedef float v4 __attribute__((vector_size(16)));
static inline v8 ld8(const float* p) { v8 r; memcpy(&r, p, sizeof r); return r; }
static inline v4 ld4(const float* p) { v4 r; memcpy(&r, p, sizeof r); return r; }

/* one pair's fine values (3, strided by n) of live triangle tr in the frame of m: the S samples'
   footprints and their 4 taps' weights (latlong.quad_lane_weights times wT: lane 4c + t's
   (l0 + l1 fx) (l2 + l3 fy) is (1 - fx or fx) (1 - fy or fy) exactly, its lane constants being 0, 1
   and -1), the quad rows' 12 texel lanes times them (lanes 12-15 hold zeros no output reads), summed
   over the samples in lighting._tree_sum's order, then each channel's 4 lanes as quad_means does */
static inline void pair_means(const float* m, int64_t tr, int64_t n, int64_t S, const float* cp, const float* wT,
                              float H1, float Wf, float hw, int32_t H2, int32_t W1, int32_t Wp,
                              const float* Q, float* o) {
    int32_t idx[MAXS];
    float fx[MAXS], fy[MAXS], wt[MAXS][4];
    v8 t8[MAXS];
    v4 t4[MAXS];
    const float *px = cp + tr * S, *py = cp + (n + tr) * S, *pz = cp + (2 * n + tr) * S;
    const float* w = wT + tr * S;
    for (int64_t s = 0; s < S; ++s)
        tap(px[s], py[s], pz[s], m, H1, Wf, hw, H2, W1, Wp, idx + s, fx + s, fy + s);
    for (int64_t s = 0; s < S; ++s) {
        const float gx = 1.0f - fx[s], gy = 1.0f - fy[s];
        wt[s][0] = (gx * gy) * w[s];
        wt[s][1] = (fx[s] * gy) * w[s];
        wt[s][2] = (gx * fy[s]) * w[s];
        wt[s][3] = (fx[s] * fy[s]) * w[s];
    }
    for (int64_t s = 0; s < S; ++s) {
        const float* qr = Q + 16 * (int64_t)idx[s];
        const v4 q = ld4(wt[s]);
        const v8 q8 = {q[0], q[1], q[2], q[3], q[0], q[1], q[2], q[3]};
        t8[s] = ld8(qr) * q8;
        t4[s] = ld4(qr + 8) * q;
    }
    int64_t k = S;                                            /* lighting._tree_sum's pairs */
    while (k > 1) {
        const int64_t h = k / 2;
        for (int64_t i = 0; i < h; ++i) {
            t8[i] = t8[2 * i] + t8[2 * i + 1];
            t4[i] = t4[2 * i] + t4[2 * i + 1];
        }
        if (k & 1) {
            t8[h] = t8[k - 1];
            t4[h] = t4[k - 1];
        }
        k -= h;
    }
    const v8 a = t8[0];
    const v4 b = t4[0];
    o[0] = (a[0] + a[1]) + (a[2] + a[3]);
    o[n] = (a[4] + a[5]) + (a[6] + a[7]);
    o[2 * n] = (b[0] + b[1]) + (b[2] + b[3]);
}

#if defined(__AVX2__)
#include <immintrin.h>

#define SET(x) _mm256_set1_ps((float)(x))
#define MUL _mm256_mul_ps
#define SUB _mm256_sub_ps

/* tap for 4 × 8 samples (AVX2; vector k in the frame of mk[k]): TAP_BODY (below) over these macros */
#define VF __m256
#define VI __m256i
#define VM __m256                                              /* a compare's result: a lane mask */
#define NV 4
#define TAP_FN tap4x8
#define VSET(x) _mm256_set1_ps((float)(x))
#define VMUL _mm256_mul_ps
#define VADD _mm256_add_ps
#define VSUB _mm256_sub_ps
#define VDIV _mm256_div_ps
#define VSQRT _mm256_sqrt_ps
#define VMIN _mm256_min_ps
#define VMAX _mm256_max_ps
#define VANDN _mm256_andnot_ps
#define VXOR _mm256_xor_ps
#define VFLOOR(x) _mm256_floor_ps(x)
#define VZERO _mm256_setzero_ps
#define VSEL(c, a, b) _mm256_blendv_ps((b), (a), (c))          /* c ? a : b */
#define VLT(a, b) _mm256_cmp_ps((a), (b), _CMP_LT_OQ)
#define VGT(a, b) _mm256_cmp_ps((a), (b), _CMP_GT_OQ)
#define IZERO _mm256_setzero_si256
#define IMIN _mm256_min_epi32
#define IMAX _mm256_max_epi32
#define IMUL _mm256_mullo_epi32
#define IADD _mm256_add_epi32
#define ITRUNC _mm256_cvttps_epi32
#define IFLOAT _mm256_cvtepi32_ps
@TAP_BODY@

/* pair_means' sums for S = 16 from its taps (samples 0-7: iA, fxA, fyA; 8-15: iB, fxB, fyB), the
   same operations in registers: the weights 4 × 8 transposed to {w of sample s, w of sample s + 8}
   (s < 8), each sample's quad weights broadcast to both halves for its 12 texel lanes, the tree of
   _tree_sum in registers */
static inline void sums16(__m256i iA, __m256i iB, __m256 fxA, __m256 fyA, __m256 fxB, __m256 fyB,
                          const float* w, int64_t n, const float* Q, float* o) {
    const __m256 one = SET(1.0f), wA = _mm256_loadu_ps(w), wB = _mm256_loadu_ps(w + 8);
    const __m256 gxA = SUB(one, fxA), gyA = SUB(one, fyA), gxB = SUB(one, fxB), gyB = SUB(one, fyB);
    const __m256 W0A = MUL(MUL(gxA, gyA), wA), W1A = MUL(MUL(fxA, gyA), wA), W2A = MUL(MUL(gxA, fyA), wA),
                 W3A = MUL(MUL(fxA, fyA), wA);
    const __m256 W0B = MUL(MUL(gxB, gyB), wB), W1B = MUL(MUL(fxB, gyB), wB), W2B = MUL(MUL(gxB, fyB), wB),
                 W3B = MUL(MUL(fxB, fyB), wB);
    __m256 ws[8];
    {
        const __m256 X0 = _mm256_permute2f128_ps(W0A, W0B, 0x20), X1 = _mm256_permute2f128_ps(W1A, W1B, 0x20),
                     X2 = _mm256_permute2f128_ps(W2A, W2B, 0x20), X3 = _mm256_permute2f128_ps(W3A, W3B, 0x20);
        const __m256 Y0 = _mm256_permute2f128_ps(W0A, W0B, 0x31), Y1 = _mm256_permute2f128_ps(W1A, W1B, 0x31),
                     Y2 = _mm256_permute2f128_ps(W2A, W2B, 0x31), Y3 = _mm256_permute2f128_ps(W3A, W3B, 0x31);
        __m256 t0 = _mm256_unpacklo_ps(X0, X1), t1 = _mm256_unpackhi_ps(X0, X1);
        __m256 t2 = _mm256_unpacklo_ps(X2, X3), t3 = _mm256_unpackhi_ps(X2, X3);
        ws[0] = _mm256_shuffle_ps(t0, t2, 0x44); ws[1] = _mm256_shuffle_ps(t0, t2, 0xEE);
        ws[2] = _mm256_shuffle_ps(t1, t3, 0x44); ws[3] = _mm256_shuffle_ps(t1, t3, 0xEE);
        t0 = _mm256_unpacklo_ps(Y0, Y1); t1 = _mm256_unpackhi_ps(Y0, Y1);
        t2 = _mm256_unpacklo_ps(Y2, Y3); t3 = _mm256_unpackhi_ps(Y2, Y3);
        ws[4] = _mm256_shuffle_ps(t0, t2, 0x44); ws[5] = _mm256_shuffle_ps(t0, t2, 0xEE);
        ws[6] = _mm256_shuffle_ps(t1, t3, 0x44); ws[7] = _mm256_shuffle_ps(t1, t3, 0xEE);
    }
    int32_t ii[16];
    _mm256_storeu_si256((__m256i*)ii, iA);
    _mm256_storeu_si256((__m256i*)(ii + 8), iB);
#define QR(s) (Q + 16 * (int64_t)ii[s])
#define WQ(s) ((s) < 8 ? _mm256_permute2f128_ps(ws[(s) & 7], ws[(s) & 7], 0x00) \
                       : _mm256_permute2f128_ps(ws[(s) & 7], ws[(s) & 7], 0x11))
#define P8(s) MUL(_mm256_loadu_ps(QR(s)), WQ(s))
#define P4(s) _mm_mul_ps(_mm_loadu_ps(QR(s) + 8), _mm256_castps256_ps128(WQ(s)))
#define T4(P, s) ((P(s) + P(s + 1)) + (P(s + 2) + P(s + 3)))
#define T16(P) ((T4(P, 0) + T4(P, 4)) + (T4(P, 8) + T4(P, 12)))
    const v8 A = (v8)T16(P8);
    const v4 B = (v4)T16(P4);
#undef QR
#undef WQ
#undef P8
#undef P4
#undef T4
#undef T16
    o[0] = (A[0] + A[1]) + (A[2] + A[3]);
    o[n] = (A[4] + A[5]) + (A[6] + A[7]);
    o[2 * n] = (B[0] + B[1]) + (B[2] + B[3]);
}

/* two pairs of S = 16 samples (live triangles t0 in the frame m0, t1 in m1; the same pair twice for
   an odd count's last): their four sample vectors through tap4x8, then each pair's sums16 */
static inline void pairs16x2(const float* m0, const float* m1, int64_t t0, int64_t t1, int64_t n, const float* cp,
                             const float* wT, __m256 H1, __m256 Wf, __m256 hw, __m256i H2, __m256i W1, __m256i Wp,
                             const float* Q, float* o0, float* o1) {
    const float *x0 = cp + t0 * 16, *y0 = cp + (n + t0) * 16, *z0 = cp + (2 * n + t0) * 16;
    const float *x1 = cp + t1 * 16, *y1 = cp + (n + t1) * 16, *z1 = cp + (2 * n + t1) * 16;
    const __m256 cx[4] = {_mm256_loadu_ps(x0), _mm256_loadu_ps(x0 + 8), _mm256_loadu_ps(x1), _mm256_loadu_ps(x1 + 8)};
    const __m256 cy[4] = {_mm256_loadu_ps(y0), _mm256_loadu_ps(y0 + 8), _mm256_loadu_ps(y1), _mm256_loadu_ps(y1 + 8)};
    const __m256 cz[4] = {_mm256_loadu_ps(z0), _mm256_loadu_ps(z0 + 8), _mm256_loadu_ps(z1), _mm256_loadu_ps(z1 + 8)};
    const float* mk[4] = {m0, m0, m1, m1};
    __m256i ii[4];
    __m256 fx[4], fy[4];
    tap4x8(cx, cy, cz, mk, H1, Wf, hw, H2, W1, Wp, ii, fx, fy);
    sums16(ii[0], ii[1], fx[0], fy[0], fx[1], fy[1], wT + t0 * 16, n, Q, o0);
    sums16(ii[2], ii[3], fx[2], fy[2], fx[3], fy[3], wT + t1 * 16, n, Q, o1);
}
#undef SET
#undef MUL
#undef SUB
#define HAVE_PAIR16 1
#endif

#if defined(__AVX512F__) && defined(__AVX512DQ__)
#include <immintrin.h>
/* With AVX-512 (`_flags`: when torch found the CPU to have it) the 16-sample pairs take zproject16:
   one pair's 16 samples in one 16-lane vector, four pairs (four independent chains) at once, in 32
   vector registers — the AVX2 loop's four 8-lane chains spent most of their time waiting on the taps'
   latency (chess bench L pairs, 1 thread: 1.4x faster). The same float32 operations one for one as
   tap4x8 / sums16: the same bits (tested against the compiled projection and the other builds). */
#define ZS(x) _mm512_set1_ps((float)(x))
#define ZMUL _mm512_mul_ps
#define ZADD _mm512_add_ps
#define ZSUB _mm512_sub_ps
#define NZ 4                                                   /* pairs at once */

/* tap4x8 with one pair's 16 samples in a 16-lane vector, NZ pairs at once (pair k in the frame of
   mk[k]): TAP_BODY (below) over these macros — AVX-512 min / max / compares / blends with the scalar
   code's semantics, as tap4x8's */
#define VF __m512
#define VI __m512i
#define VM __mmask16                                           /* a compare's result: a lane mask */
#define NV NZ
#define TAP_FN ztap
#define VSET(x) _mm512_set1_ps((float)(x))
#define VMUL _mm512_mul_ps
#define VADD _mm512_add_ps
#define VSUB _mm512_sub_ps
#define VDIV _mm512_div_ps
#define VSQRT _mm512_sqrt_ps
#define VMIN _mm512_min_ps
#define VMAX _mm512_max_ps
#define VANDN _mm512_andnot_ps
#define VXOR _mm512_xor_ps
#define VFLOOR(x) _mm512_roundscale_ps((x), _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC)
#define VZERO _mm512_setzero_ps
#define VSEL(c, a, b) _mm512_mask_blend_ps((c), (b), (a))      /* c ? a : b */
#define VLT(a, b) _mm512_cmp_ps_mask((a), (b), _CMP_LT_OQ)
#define VGT(a, b) _mm512_cmp_ps_mask((a), (b), _CMP_GT_OQ)
#define IZERO _mm512_setzero_si512
#define IMIN _mm512_min_epi32
#define IMAX _mm512_max_epi32
#define IMUL _mm512_mullo_epi32
#define IADD _mm512_add_epi32
#define ITRUNC _mm512_cvttps_epi32
#define IFLOAT _mm512_cvtepi32_ps
@TAP_BODY@

/* pair_means' sums for one pair (S = 16) from its 16-lane taps: the weights transposed to one
   {w0 w1 w2 w3} per 128-bit lane (lane k of X[j]: sample 4 k + j), each sample's weights broadcast
   to the quad row's four 4-lane groups (channel c at lanes 4 c + t; lanes 12-15 zeros), the products
   summed in _tree_sum's order, then each channel's 4 lanes: sums16's values bit for bit */
static inline void zsums(__m512i ii, __m512 fx, __m512 fy, const float* w, int64_t n, const float* Q, float* o) {
    const __m512 one = ZS(1.0f), wv = _mm512_loadu_ps(w);
    const __m512 gx = ZSUB(one, fx), gy = ZSUB(one, fy);
    const __m512 W0 = ZMUL(ZMUL(gx, gy), wv), W1 = ZMUL(ZMUL(fx, gy), wv), W2 = ZMUL(ZMUL(gx, fy), wv),
                 W3 = ZMUL(ZMUL(fx, fy), wv);
    const __m512 t0 = _mm512_unpacklo_ps(W0, W1), t1 = _mm512_unpackhi_ps(W0, W1);
    const __m512 t2 = _mm512_unpacklo_ps(W2, W3), t3 = _mm512_unpackhi_ps(W2, W3);
    __m512 X[4];
    X[0] = _mm512_shuffle_ps(t0, t2, 0x44); X[1] = _mm512_shuffle_ps(t0, t2, 0xEE);
    X[2] = _mm512_shuffle_ps(t1, t3, 0x44); X[3] = _mm512_shuffle_ps(t1, t3, 0xEE);
    int32_t is[16];
    _mm512_storeu_si512((void*)is, ii);
#define ZQ(s) _mm512_mul_ps(_mm512_loadu_ps(Q + 16 * (int64_t)is[s]), \
                            _mm512_shuffle_f32x4(X[(s) & 3], X[(s) & 3], ((s) >> 2) * 0x55))
#define ZT4(s) ZADD(ZADD(ZQ(s), ZQ(s + 1)), ZADD(ZQ(s + 2), ZQ(s + 3)))
    const __m512 A = ZADD(ZADD(ZT4(0), ZT4(4)), ZADD(ZT4(8), ZT4(12)));
#undef ZQ
#undef ZT4
    float a[16];
    _mm512_storeu_ps(a, A);
    o[0] = (a[0] + a[1]) + (a[2] + a[3]);
    o[n] = (a[4] + a[5]) + (a[6] + a[7]);
    o[2 * n] = (a[8] + a[9]) + (a[10] + a[11]);
}

/* tp_project's S = 16 loop, NZ pairs at a time (the last pairs repeated for a count not a multiple) */
static void zproject16(int64_t np, const int64_t* pairs, int64_t n, const float* M, const float* cp,
                       const float* wT, int64_t H, int64_t W, const float* Q, float* out) {
    const __m512 H1 = _mm512_set1_ps((float)(H - 1)), Wf = _mm512_set1_ps((float)W), hw = _mm512_set1_ps((float)(0.5 / (double)W));
    const __m512i H2 = _mm512_set1_epi32((int32_t)(H - 2)), W1 = _mm512_set1_epi32((int32_t)(W - 1)),
                  Wp = _mm512_set1_epi32((int32_t)(W + 1));
    int64_t f = -1, lo = 0;                                      /* pairs[e] in [lo, lo + n): frame f */
    for (int64_t e = 0; e < np; e += NZ) {
        const float* mk[NZ];
        int64_t tk[NZ];
        float* ok[NZ];
        __m512 cx[NZ], cy[NZ], cz[NZ], fx[NZ], fy[NZ];
        __m512i ii[NZ];
        for (int k = 0; k < NZ; ++k) {
            const int64_t pe = pairs[e + k < np ? e + k : np - 1];
            if (f < 0 || pe < lo || pe - lo >= n) { f = pe / n; lo = f * n; }
            tk[k] = pe - lo;
            mk[k] = M + 9 * f;
            ok[k] = out + f * 3 * n + tk[k];
            cx[k] = _mm512_loadu_ps(cp + tk[k] * 16);
            cy[k] = _mm512_loadu_ps(cp + (n + tk[k]) * 16);
            cz[k] = _mm512_loadu_ps(cp + (2 * n + tk[k]) * 16);
        }
        ztap(cx, cy, cz, mk, H1, Wf, hw, H2, W1, Wp, ii, fx, fy);
        for (int k = 0; k < NZ; ++k) zsums(ii[k], fx[k], fy[k], wT + tk[k] * 16, n, Q, ok[k]);
    }
}
#undef ZS
#undef ZMUL
#undef ZADD
#undef ZSUB
#define HAVE_PAIR16Z 1
#endif

/* out[f, c, t] (F, 3, n) for the pairs f * n + t: the mean of the map's bilinear radiance over the
   S samples of live triangle t seen in frame f (lighting.quad_means). M (F, 9) = R T; cp (3, n, S)
   the live triangles' sample planes, wT (n, S) their weights; Q the quad rows (H (W + 1), 16).
   S = 16 (supersample 2, the method's default) takes zproject16, four pairs at a time, when built
   with AVX-512, else pairs16x2, two pairs at a time, when built with AVX2 (the frame of consecutive
   pairs kept: no division per pair), else pair_means with S a constant (unrolled): the same bits. */
void tp_project(int64_t np, const int64_t* pairs, int64_t n, int64_t S, const float* M, const float* cp,
                const float* wT, int64_t H, int64_t W, const float* Q, float* out) {
    const float H1 = (float)(H - 1), Wf = (float)W, hw = (float)(0.5 / (double)W);
    const int32_t H2 = (int32_t)(H - 2), W1 = (int32_t)(W - 1), Wp = (int32_t)(W + 1);
#ifdef HAVE_PAIR16Z
    if (S == 16) {
        zproject16(np, pairs, n, M, cp, wT, H, W, Q, out);
        return;
    }
#elif defined(HAVE_PAIR16)
    if (S == 16) {
        const __m256 H1v = _mm256_set1_ps(H1), Wfv = _mm256_set1_ps(Wf), hwv = _mm256_set1_ps(hw);
        const __m256i H2v = _mm256_set1_epi32(H2), W1v = _mm256_set1_epi32(W1), Wpv = _mm256_set1_epi32(Wp);
        int64_t f = -1, lo = 0;                                  /* pairs[e] in [lo, lo + n): frame f */
        for (int64_t e = 0; e < np; e += 2) {
            const int64_t e1 = e + 1 < np ? e + 1 : e;
            if (f < 0 || pairs[e] < lo || pairs[e] - lo >= n) { f = pairs[e] / n; lo = f * n; }
            const int64_t f0 = f, t0 = pairs[e] - lo;
            if (pairs[e1] < lo || pairs[e1] - lo >= n) { f = pairs[e1] / n; lo = f * n; }
            const int64_t t1 = pairs[e1] - lo;
            pairs16x2(M + 9 * f0, M + 9 * f, t0, t1, n, cp, wT, H1v, Wfv, hwv, H2v, W1v, Wpv, Q,
                      out + f0 * 3 * n + t0, out + f * 3 * n + t1);
        }
        return;
    }
#else
    if (S == 16) {
        for (int64_t e = 0; e < np; ++e) {
            const int64_t f = pairs[e] / n, tr = pairs[e] % n;
            pair_means(M + 9 * f, tr, n, 16, cp, wT, H1, Wf, hw, H2, W1, Wp, Q, out + f * 3 * n + tr);
        }
        return;
    }
#endif
    for (int64_t e = 0; e < np; ++e) {
        const int64_t f = pairs[e] / n, tr = pairs[e] % n;
        pair_means(M + 9 * f, tr, n, S, cp, wT, H1, Wf, hw, H2, W1, Wp, Q, out + f * 3 * n + tr);
    }
}

/* tp_project over np pairs on nt threads of OpenMP's team: blk <= 0, thread k the pairs [np k / nt,
   np (k + 1) / nt); blk > 0 (session 39), blocks of blk pairs handed out dynamically (each pair's sums in
   one thread either way: the same bits). */
void tp_project_par(int64_t np, const int64_t* pairs, int64_t n, int64_t S, const float* M, const float* cp,
                    const float* wT, int64_t H, int64_t W, const float* Q, float* out, int64_t nt, int64_t blk) {
    if (blk > 0) {
        const int64_t nb = (np + blk - 1) / blk;
#pragma omp parallel for num_threads(nt) schedule(dynamic, 1)
        for (int64_t q = 0; q < nb; ++q) {
            const int64_t a = q * blk, e = a + blk < np ? a + blk : np;
            tp_project(e - a, pairs + a, n, S, M, cp, wT, H, W, Q, out);
        }
        return;
    }
#pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int64_t k = 0; k < nt; ++k) {
        const int64_t a = np * k / nt, e = np * (k + 1) / nt;
        tp_project(e - a, pairs + a, n, S, M, cp, wT, H, W, Q, out);
    }
}

/* need (F, n) bytes: 1 where some point looks up grid row f with a non-zero weight and one of its
   visibility rows with a non-zero weight is non-zero at live triangle t, i.e. the OR of the bit sets
   Vb[v] (N_V, nw) (bit t % 64 of word t / 64) over the (v, f) pairs of the points' non-zero weights.
   A point whose visibility rows and non-zero flags equal the previous point's reuses its OR (acc),
   and then skips each grid row the previous point ORed it into already (a point with the same rows
   and flags adds nothing: skipped whole, as before; a set of the distinct (v, f) pairs seen instead
   cost more than it saved: 2^16 open-addressing slots, chess bench pixel L, 11 against 7 ms). The
   points are split in nt contiguous ranges over OpenMP's team, each range ORed into its own bit
   table (the first point of a range computes its OR), the tables then ORed together (the same
   bits whatever nt). status[0]: 0, or -1 when a row index read with a non-zero weight is outside its
   table (need then undefined), -2 out of memory. */
static int need_range(int64_t b0, int64_t b1, int64_t kv, const int64_t* vrows, const float* vw, int64_t kl,
                      const int64_t* lrows, const float* lw, int64_t nw, const uint64_t* Vb, int64_t NV, int64_t F,
                      uint64_t* bits, uint64_t* acc) {
    for (int64_t b = b0; b < b1; ++b) {
        const int64_t *v = vrows + b * kv, *l = lrows + b * kl;
        const float *x = vw + b * kv, *y = lw + b * kl;
        int samev = b > b0;                                      /* acc holds point b - 1's OR */
        for (int64_t j = 0; j < kv && samev; ++j)
            samev = v[j] == v[j - kv] && (x[j] != 0.0f) == (x[j - kv] != 0.0f);
        if (!samev) {
            memset(acc, 0, (size_t)nw * sizeof(uint64_t));
            for (int64_t j = 0; j < kv; ++j)
                if (x[j] != 0.0f) {
                    if (v[j] < 0 || v[j] >= NV) return 1;
                    const uint64_t* r = Vb + v[j] * nw;
                    for (int64_t w = 0; w < nw; ++w) acc[w] |= r[w];
                }
        }
        for (int64_t j = 0; j < kl; ++j)
            if (y[j] != 0.0f) {
                if (l[j] < 0 || l[j] >= F) return 1;
                if (samev) {                                     /* ORed by point b - 1 already? */
                    int seen = 0;
                    for (int64_t i = 0; i < kl && !seen; ++i) seen = l[i - kl] == l[j] && y[i - kl] != 0.0f;
                    if (seen) continue;
                }
                uint64_t* o = bits + l[j] * nw;
                for (int64_t w = 0; w < nw; ++w) o[w] |= acc[w];
            }
    }
    return 0;
}

void tp_need(int64_t B, int64_t kv, const int64_t* vrows, const float* vw, int64_t kl, const int64_t* lrows,
             const float* lw, int64_t nw, const uint64_t* Vb, int64_t NV, int64_t F, int64_t n, uint8_t* need,
             int64_t* status, int64_t nt, uint64_t* bits_out) {
    if (nt < 1) nt = 1;
    const int64_t per = F * nw + nw;                             /* a range's bit table and its acc */
    uint64_t* bits = (uint64_t*)calloc((size_t)(nt * per), sizeof(uint64_t));
    int64_t bad = 0;
    if (!bits) { status[0] = -2; return; }
    if (nt == 1) {
        bad = need_range(0, B, kv, vrows, vw, kl, lrows, lw, nw, Vb, NV, F, bits, bits + F * nw);
    } else {
#pragma omp parallel for num_threads(nt) schedule(static, 1) reduction(|:bad)
        for (int64_t q = 0; q < nt; ++q)
            bad |= need_range(B * q / nt, B * (q + 1) / nt, kv, vrows, vw, kl, lrows, lw, nw, Vb, NV, F,
                              bits + q * per, bits + q * per + F * nw);
        for (int64_t q = 1; q < nt && !bad; ++q)
            for (int64_t i = 0; i < F * nw; ++i) bits[i] |= bits[q * per + i];
    }
    if (!bad && bits_out)                                        /* the bit table itself (tp_take_bits) */
        memcpy(bits_out, bits, (size_t)(F * nw) * sizeof(uint64_t));
    if (!bad && need)
        for (int64_t f = 0; f < F; ++f)
            for (int64_t t = 0; t < n; ++t)
                need[f * n + t] = (uint8_t)((bits[f * nw + t / 64] >> (t % 64)) & 1u);
    free(bits);
    status[0] = bad ? -1 : 0;
}

/* The pairs of need (N bytes) not in done, in index order: counts[0] = their number when pairs is
   NULL; else pairs[0 .. counts[0]) = them, done[i] = 1 for each, and counts[1] = the rows of n that
   hold one (a frame with a pair to project). */
void tp_take(int64_t N, int64_t n, const uint8_t* need, uint8_t* done, int64_t* pairs, int64_t* counts) {
    int64_t k = 0;
    if (!pairs) {
        for (int64_t i = 0; i < N; ++i) k += need[i] & (done[i] ^ 1);
        counts[0] = k;
        return;
    }
    int64_t rows = 0;
    for (int64_t a = 0; a < N; a += n) {
        const int64_t e = a + n < N ? a + n : N, k0 = k;
        for (int64_t i = a; i < e; ++i)
            if (need[i] & (done[i] ^ 1)) { pairs[k++] = i; done[i] = 1; }
        rows += k > k0;
    }
    counts[1] = rows;
}

/* tp_take of need given as tp_need's bit table (F rows of nw words, bit t % 64 of word t / 64 for
   column t < n): its set bits visited in order (f, then t) instead of the F n need bytes scanned —
   the same pairs, done and counts. */
void tp_take_bits(int64_t F, int64_t n, int64_t nw, const uint64_t* bits, uint8_t* done, int64_t* pairs,
                  int64_t* counts) {
    int64_t k = 0, rows = 0;
    const uint64_t last = n % 64 ? (((uint64_t)1 << (n % 64)) - 1u) : ~(uint64_t)0;
    for (int64_t f = 0; f < F; ++f) {
        const int64_t k0 = k;
        for (int64_t w = 0; w < nw; ++w) {
            uint64_t x = bits[f * nw + w];
            if (w == nw - 1) x &= last;
            while (x) {
                const int64_t i = f * n + w * 64 + __builtin_ctzll(x);
                x &= x - 1;
                if (done[i]) continue;
                if (pairs) { pairs[k] = i; done[i] = 1; }
                ++k;
            }
        }
        rows += k > k0;
    }
    counts[0] = k;
    counts[1] = rows;
}

/* E frames: a map turned about +Y only (lighting.comb_means, the comb table CT of J = n_phi frames,
   m = W / J columns per frame step) for the listed pairs f * n + t only. Grid frame f is base row
   b = i n_psi + k and comb frame j (f = (i J + j) n_psi + k, lighting._comb_rows); its mean of live
   triangle t is comb_means' sum: over the S samples s, then the taps (dy, e), of
   CT[o[b, t, s] + j + c cs + dy rs + e es] w4[b, t, s, dy, e] (cs = 4 J, es = 2 J, rs = 3 m cs),
   added in that order to 0 one by one, as the compiled reduction does on one thread: the same bits.
   Per (b, t) holding a listed pair, each 8-frame group of j holding one is summed 8 frames per
   vector, two groups at a time (six independent sums); frames of J past the last whole group one
   by one. Every frame of a summed group is written (its true value). Items (b, t) are split in
   contiguous ranges over nt threads. status[0]: 0, -2 out of memory, -1 J > 64. */
typedef float cv8 __attribute__((vector_size(32)));
static inline cv8 cld8(const float* p) { cv8 r; memcpy(&r, p, sizeof r); return r; }

static inline void comb_two(const int32_t* ot, const float* wt, int64_t S, const float* CT, int64_t j0, int64_t j1,
                            int64_t cs, int64_t es, int64_t rs, cv8* r0, cv8* r1) {
    cv8 a0 = {0}, a1 = {0}, a2 = {0}, b0 = {0}, b1 = {0}, b2 = {0};
    for (int64_t s = 0; s < S; ++s) {
        const float* base = CT + ot[s];
        for (int dy = 0; dy < 2; ++dy)
            for (int e = 0; e < 2; ++e) {
                const float w = wt[4 * s + 2 * dy + e];
                const float* p = base + dy * rs + e * es;
                a0 += cld8(p + j0) * w; a1 += cld8(p + j0 + cs) * w; a2 += cld8(p + j0 + 2 * cs) * w;
                b0 += cld8(p + j1) * w; b1 += cld8(p + j1 + cs) * w; b2 += cld8(p + j1 + 2 * cs) * w;
            }
    }
    r0[0] = a0; r0[1] = a1; r0[2] = a2;
    r1[0] = b0; r1[1] = b1; r1[2] = b2;
}

/* The taps of lighting.comb_taps for one item's S samples (u0 float64, v0 float32, the samples'
   weights wT float32, g = gamma / 2 pi float64; map H x W, m = W / J): ot[s] and wt[4 s + 2 dy + e] —
   the compiled kernel's float64 / float32 / int32 operations one for one (no contraction in this
   library): the same offsets and weights bit for bit. */
typedef struct { const double* u0; const float* v0; const float* wT; double g; int64_t H, W; } comb_uv;

static inline void comb_item_taps(const comb_uv* uv, int64_t it, int64_t t, int64_t S, int64_t J, int64_t m,
                                  int32_t* ot, float* wt) {
    const double* u0 = uv->u0 + it * S;
    const float* v0 = uv->v0 + it * S;
    const float* wT = uv->wT + t * S;
    const int32_t W = (int32_t)uv->W, H = (int32_t)uv->H, mi = (int32_t)m, st = (int32_t)(12 * J);
    const float half = (float)(0.5 / (double)uv->W), Wf = (float)uv->W, Hf = (float)(uv->H - 1);
    for (int64_t s = 0; s < S; ++s) {
        const double ud = u0[s] - uv->g;
        float u = (float)(ud - floor(ud));
        u = u - half;
        const float x = (u - floorf(u)) * Wf;
        int32_t ix = (int32_t)x;
        ix = ix < 0 ? 0 : ix > W - 1 ? W - 1 : ix;
        const float fx = x - (float)ix;
        const double ixd = (double)ix;
        const double qd = floor(ixd / (double)m);
        const double pd = ixd - qd * (double)m;
        const float v = v0[s] - floorf(v0[s]);
        const float y = v * Hf;
        int32_t iy = (int32_t)y;
        iy = iy < 0 ? 0 : iy > H - 2 ? H - 2 : iy;
        const float fy = y - (float)iy;
        ot[s] = (iy * mi + (int32_t)pd) * st + (int32_t)qd;
        const float w = wT[s];
        wt[4 * s] = ((1.0f - fx) * (1.0f - fy)) * w;
        wt[4 * s + 1] = (fx * (1.0f - fy)) * w;
        wt[4 * s + 2] = ((1.0f - fx) * fy) * w;
        wt[4 * s + 3] = (fx * fy) * w;
    }
}

static void comb_items(int64_t i0, int64_t i1, const int64_t* items, const uint64_t* mask, int64_t n, int64_t S,
                       int64_t n_psi, int64_t J, const int32_t* o, const float* w4, const float* CT, int64_t m,
                       float* out, const comb_uv* uv) {
    const int64_t cs = 4 * J, es = 2 * J, rs = 3 * m * cs, G = J / 8;
    int32_t obuf[64];
    float wbuf[256];
    for (int64_t q = i0; q < i1; ++q) {
        const int64_t it = items[q], b = it / n, t = it % n, i = b / n_psi, k = b % n_psi;
        const uint64_t mk = mask[it];
        const int32_t* ot = uv ? obuf : o + it * S;
        const float* wt = uv ? wbuf : w4 + it * S * 4;
        if (uv) comb_item_taps(uv, it, t, S, J, m, obuf, wbuf);
        int64_t gs[8], ng = 0;
        for (int64_t g = 0; g < G; ++g)
            if ((mk >> (8 * g)) & 0xffu) gs[ng++] = g;
        for (int64_t a = 0; a < ng; a += 2) {
            const int64_t g0 = gs[a], g1 = a + 1 < ng ? gs[a + 1] : gs[a];
            cv8 r0[3], r1[3];
            comb_two(ot, wt, S, CT, 8 * g0, 8 * g1, cs, es, rs, r0, r1);
            for (int64_t l = 0; l < 8; ++l) {
                const int64_t f0 = ((i * J + 8 * g0 + l) * n_psi + k) * 3 * n + t;
                const int64_t f1 = ((i * J + 8 * g1 + l) * n_psi + k) * 3 * n + t;
                for (int c = 0; c < 3; ++c) { out[f0 + c * n] = r0[c][l]; out[f1 + c * n] = r1[c][l]; }
            }
        }
        for (int64_t j = 8 * G; j < J; ++j) {                   /* frames past the last whole group */
            if (!((mk >> j) & 1u)) continue;
            float acc[3] = {0.0f, 0.0f, 0.0f};
            for (int64_t s = 0; s < S; ++s)
                for (int dy = 0; dy < 2; ++dy)
                    for (int e = 0; e < 2; ++e) {
                        const float w = wt[4 * s + 2 * dy + e];
                        const float* p = CT + ot[s] + j + dy * rs + e * es;
                        for (int c = 0; c < 3; ++c) acc[c] += p[c * cs] * w;
                    }
            const int64_t f = ((i * J + j) * n_psi + k) * 3 * n + t;
            for (int c = 0; c < 3; ++c) out[f + c * n] = acc[c];
        }
    }
}

static void comb_pairs_body(int64_t np, const int64_t* pairs, int64_t n, int64_t S, int64_t n_psi, int64_t J,
                            int64_t B, const int32_t* o, const float* w4, const float* CT, int64_t m, float* out,
                            int64_t nt, int64_t blk, int64_t* status, const comb_uv* uv) {
    if (J > 64) { status[0] = -1; return; }
    uint64_t* mask = (uint64_t*)calloc((size_t)(B * n), sizeof(uint64_t));
    int64_t* items = (int64_t*)malloc((size_t)(B * n + 1) * sizeof(int64_t));
    if (!mask || !items) { free(mask); free(items); status[0] = -2; return; }
    int64_t f = -1, lo = 0, row = 0;                             /* pairs[e] in [lo, lo + n): frame f */
    uint64_t bit = 0;
    for (int64_t e = 0; e < np; ++e) {
        if (f < 0 || pairs[e] < lo || pairs[e] - lo >= n) {     /* divisions once per frame */
            f = pairs[e] / n;
            lo = f * n;
            const int64_t k = f % n_psi, j = f / n_psi % J, i = f / (J * n_psi);
            row = (i * n_psi + k) * n;
            bit = (uint64_t)1 << j;
        }
        mask[row + pairs[e] - lo] |= bit;
    }
    int64_t ni = 0;
    for (int64_t it = 0; it < B * n; ++it)
        if (mask[it]) items[ni++] = it;
    if (nt <= 1 || ni < 2 * nt) {
        comb_items(0, ni, items, mask, n, S, n_psi, J, o, w4, CT, m, out, uv);
    } else if (blk > 0) {       /* session 39: blocks of blk items handed out dynamically (the same bits) */
        const int64_t nb = (ni + blk - 1) / blk;
#pragma omp parallel for num_threads(nt) schedule(dynamic, 1)
        for (int64_t q = 0; q < nb; ++q)
            comb_items(q * blk, (q + 1) * blk < ni ? (q + 1) * blk : ni, items, mask, n, S, n_psi, J, o, w4, CT, m,
                       out, uv);
    } else {
#pragma omp parallel for num_threads(nt) schedule(static, 1)
        for (int64_t q = 0; q < nt; ++q)
            comb_items(ni * q / nt, ni * (q + 1) / nt, items, mask, n, S, n_psi, J, o, w4, CT, m, out, uv);
    }
    free(mask);
    free(items);
    status[0] = 0;
}

void tp_comb_pairs(int64_t np, const int64_t* pairs, int64_t n, int64_t S, int64_t n_psi, int64_t J, int64_t B,
                   const int32_t* o, const float* w4, const float* CT, int64_t m, float* out, int64_t nt,
                   int64_t blk, int64_t* status) {
    comb_pairs_body(np, pairs, n, S, n_psi, J, B, o, w4, CT, m, out, nt, blk, status, NULL);
}

/* tp_comb_pairs with each listed item's taps made in the loop from its samples' base coordinates
   (comb_item_taps: lighting.comb_taps' values bit for bit) instead of read from comb_taps' arrays
   of every base row and live triangle: an E frame's items are about half of them, and the (B, n, S)
   offsets and (B, n, S, 4) weights are neither written nor read back. S <= 64. */
void tp_comb_pairs_uv(int64_t np, const int64_t* pairs, int64_t n, int64_t S, int64_t n_psi, int64_t J, int64_t B,
                      const double* u0, const float* v0, const float* wT, double g, int64_t H, int64_t W,
                      const float* CT, int64_t m, float* out, int64_t nt, int64_t blk, int64_t* status) {
    if (S > 64) { status[0] = -3; return; }
    const comb_uv uv = {u0, v0, wT, g, H, W};
    comb_pairs_body(np, pairs, n, S, n_psi, J, B, NULL, NULL, CT, m, out, nt, blk, status, &uv);
}

/* lighting.box_filtered of texels d (H, W, C) float32 (k >= 2 dividing H and W) into out (H/k, W/k, C):
   per output, its k rows of each column summed in float64 in row order (d[k I] + d[k I + 1] + ...),
   then those k column sums in column order, times 1 / k^2, rounded to float32 once — the torch
   loop's operations in its order, the same bits (no contraction in this library). One output row
   of column sums (W C doubles) at a time. status[0]: 0, -2 out of memory. */
static void box_rows(int64_t I0, int64_t I1, int64_t W, int64_t C, int64_t k, const float* d, float* out, double* a) {
    const int64_t n = W * C, Wo = W / k;
    const double inv = 1.0 / (double)(k * k);
    for (int64_t I = I0; I < I1; ++I) {
        const float* r = d + I * k * n;
        for (int64_t x = 0; x < n; ++x) a[x] = (double)r[x];
        for (int64_t i = 1; i < k; ++i) {
            const float* ri = r + i * n;
            for (int64_t x = 0; x < n; ++x) a[x] += (double)ri[x];
        }
        float* o = out + I * Wo * C;
        for (int64_t J = 0; J < Wo; ++J)
            for (int64_t c = 0; c < C; ++c) {
                const double* aj = a + J * k * C + c;
                double b = aj[0] + aj[C];
                for (int64_t j = 2; j < k; ++j) b += aj[j * C];
                o[J * C + c] = (float)(b * inv);
            }
    }
}

/* session 39: the output rows split over nt threads (each output's sums in one thread, each thread its own
   row of column sums: the same texels at any thread count; this ran on one thread, ~0.2-0.3 ms of a
   creature bench vertex E frame) */
void tp_box(int64_t H, int64_t W, int64_t C, int64_t k, const float* d, float* out, int64_t* status, int64_t nt) {
    const int64_t n = W * C, Ho = H / k;
    if (nt < 1) nt = 1;
    double* a = (double*)malloc((size_t)(n * nt) * sizeof(double));
    if (!a) { status[0] = -2; return; }
#pragma omp parallel for num_threads(nt) schedule(static, 1) if (nt > 1)
    for (int64_t q = 0; q < nt; ++q)
        box_rows(Ho * q / nt, Ho * (q + 1) / nt, W, C, k, d, out, a + q * n);
    free(a);
    status[0] = 0;
}

/* The comb path's live-triangle means (B, n, 3, J) contiguous, row b J + j of frame dst[b J + j]
   (< 0: not wanted), copied into out (F, 3, n): out[dst, c, t] = means[b, t, c, j], each wanted
   frame's rows written in order (its means read with stride 3 J: a base row's 3 n J means stay in
   L2 over its J frames). */
void tp_comb_scatter(int64_t B, int64_t n, int64_t J, const float* means, const int64_t* dst, float* out) {
    for (int64_t b = 0; b < B; ++b)
        for (int64_t j = 0; j < J; ++j) {
            const int64_t r = dst[b * J + j];
            if (r < 0) continue;
            for (int64_t c = 0; c < 3; ++c) {
                const float* m = means + (b * n * 3 + c) * J + j;
                float* o = out + (r * 3 + c) * n;
                for (int64_t t = 0; t < n; ++t) o[t] = m[t * 3 * J];
            }
        }
}
"""
_SOURCE = _SOURCE.replace("@TAP_BODY@", _TAP_BODY.strip("\n"))  # the one tap body, twice


@functools.lru_cache(maxsize=None)
def _flags() -> tuple[str, ...]:
    """Inductor's floating-point flags for its CPU kernels (no contraction: the compiled projection's
    values bit for bit; no trapping math: floorf and the float → int conversions vectorise), OpenMP,
    and AVX2 + FMA when torch found the CPU to have them (`methods.core.native.isa_flags`)."""
    return ("-ffp-contract=off", "-fno-trapping-math", "-fopenmp", *native.isa_flags())


# AVX-512 (foundation, DQ for its float logic, VL / BW for the 32 registers in the 8-lane code too)
AVX512_FLAGS = ("-mavx512f", "-mavx512dq", "-mavx512vl", "-mavx512bw")


def _wide_flags() -> tuple[str, ...] | None:
    """`_flags` plus `AVX512_FLAGS` when torch found the CPU to have AVX-512 (`native.cpu_capability`),
    else None (the 16-sample pairs' zproject16 loop; the same bits as the AVX2 build)."""
    return (*_flags(), *AVX512_FLAGS) if native.cpu_capability() == "AVX512" else None


_P, _I = ctypes.c_void_p, ctypes.c_int64
_SIGNATURES = {"tp_project": [_I, _P, _I, _I, _P, _P, _P, _I, _I, _P, _P],
               "tp_project_par": [_I, _P, _I, _I, _P, _P, _P, _I, _I, _P, _P, _I, _I],
               "tp_need": [_I, _I, _P, _P, _I, _P, _P, _I, _P, _I, _I, _I, _P, _P, _I, _P],
               "tp_take_bits": [_I, _I, _I, _P, _P, _P, _P],
               "tp_take": [_I, _I, _P, _P, _P, _P],
               "tp_comb_pairs_uv": [_I, _P, _I, _I, _I, _I, _I, _P, _P, _P, ctypes.c_double, _I, _I, _P, _I, _P, _I, _I,
                                    _P],
               "tp_box": [_I, _I, _I, _I, _P, _P, _P, _I],
               "tp_comb_scatter": [_I, _I, _I, _P, _P, _P],
               "tp_comb_pairs": [_I, _P, _I, _I, _I, _I, _I, _P, _P, _P, _I, _P, _I, _I, _P]}

MAX_SAMPLES = 64  # 4^s samples per fine triangle the loop takes (MAXS: supersample <= 3)


def _lib():
    """The library (`methods.core.native.load`; built with `_wide_flags` when the CPU has AVX-512,
    else — or when that build fails — with `_flags`) or None: no compiler, the build failed,
    ``PRTBENCH_COMPILE=0`` or ``PRTBENCH_TP_NATIVE=0``."""
    if not tp_native.switched_on():
        return None
    wide = _wide_flags()
    if wide is not None:
        lib = _quiet_load("tp_light_pairs_z", wide)
        if lib is not None:
            return lib
    return tp_native.loaded("tp_light_pairs", _SOURCE, _SIGNATURES, _flags())


def _quiet_load(name: str, flags: tuple[str, ...]):
    """`native.load` of this source with ``flags`` without its build-failure warning (a compiler
    without AVX-512 support: the AVX2 build serves, the same bits), remembered once loaded
    (`tp_native.loaded`)."""
    return tp_native.loaded(name, _SOURCE, _SIGNATURES, flags, quiet=True)


def available() -> bool:
    """True when the pair projection runs (else the frame projects whole live rows, compiled)."""
    return _lib() is not None


def vis_bits(Vt: Tensor) -> Tensor:
    """(N, ⌈n/64⌉) int64 bit sets of the non-zero columns of a visibility table Vt (N, n): bit t % 64
    of word t // 64 (once per table)."""
    N, n = Vt.shape
    nw = -(-n // 64)
    nz = torch.zeros(N, nw * 64, dtype=torch.int64)
    nz[:, :n] = (Vt != 0).to(torch.int64)
    sh = torch.arange(64, dtype=torch.int64)
    return (nz.view(N, nw, 64) << sh).sum(-1)        # distinct bits: the sum is their OR (wraps to int64)


# Pairs below which one thread projects (a hand-off costs more than the share).
MIN_PAIRS_PER_THREAD = 256
# The comb loops at 2+ threads (session 39): blocks of this many (base row, triangle) items handed out
# dynamically (the same bits: each item's sums in one thread); 0: contiguous ranges, one a thread — the
# default: the static halves differ by 4-8 % at 1 thread, but the comb pass alone at 2 threads (host at
# load ~2, `benchmarks.tp_passes_ab`) read 0.92x / 0.90x / 0.82x with blocks of 64 / 512 / 2048 items
# (1.58x only under heavy contention); consecutive items share their comb-table rows, which a thread's
# contiguous range keeps in its cache.
COMB_BLOCK = 0
# `project` at 2+ threads (session 39): blocks of this many pairs handed out dynamically (the same bits:
# each pair's sums in one thread); 0: contiguous ranges, one a thread — the default: the two halves of a
# creature bench VL frame's pairs cost the same within 0.7 % at 1 thread (`tp_passes_ab` could not time
# 2 threads on a host at load 6-8), so the dynamic split is kept only as an option.
PROJECT_BLOCK = 0
# `box` (an E frame's prefilter of the new probe) split over torch's threads by output rows (session 39);
# False: one thread (the pass before).
BOX_THREADS = True
MIN_BOX_ROWS_PER_THREAD = 8


# Points below which one thread finds the read pairs (`need`; each range ORs into its own table).
MIN_POINTS_PER_THREAD = 8192


class NeedBits:
    """`need`'s pairs as its bit table: ``bits`` (F, ⌈n/64⌉) int64, bit t % 64 of word t / 64 set where
    the (grid row, live triangle t) pair is read; `take` visits its set bits. ``shape`` (F, n)."""

    __slots__ = ("bits", "shape")

    def __init__(self, bits: Tensor, n: int) -> None:
        self.bits, self.shape = bits, (bits.shape[0], n)

    def dense(self) -> Tensor:
        """The (F, n) bool of `need` (tests)."""
        F, n = self.shape
        sh = torch.arange(64, dtype=torch.int64)
        return ((self.bits[:, :, None] >> sh) & 1).view(F, -1)[:, :n].bool()


def need(bits: Tensor, vrows: Tensor, vw: Tensor, lrows: Tensor, lw: Tensor, F: int, n: int, *,
         as_bits: bool = False) -> Tensor | NeedBits:
    """(F, n) bool: the (grid row, live triangle) pairs that points with visibility rows / weights
    (vrows, vw (B, k_v)) and grid rows / weights (lrows, lw (B, k_L)) read with a non-zero visibility
    and a non-zero weight; ``bits`` = `vis_bits` of their visibility table. ``as_bits``: the same pairs
    as a `NeedBits` (no F·n bytes written; `take` reads its set bits: what `fast_eval.read_pairs`
    hands `TripleProduct.fill_lighting`)."""
    lib = _lib()
    if lib is None:
        raise RuntimeError("the native kernel is not available")
    if vrows.ndim == 1:
        vrows, vw = vrows[:, None], vw[:, None]
    B, kv = vrows.shape
    kl = lrows.shape[1]
    if vw.shape != (B, kv) or lrows.shape != (B, kl) or lw.shape != (B, kl) or bits.ndim != 2 \
            or bits.shape[1] != -(-n // 64) or bits.dtype != torch.int64:
        raise ValueError("vrows, vw (B, k_v), lrows, lw (B, k_L) and bits (N_V, ceil(n / 64)) int64 expected")
    vrows, lrows = (x.to(torch.int64).contiguous() for x in (vrows, lrows))
    vw, lw = (x.to(torch.float32).contiguous() for x in (vw, lw))
    bits = bits.contiguous()
    out = None if as_bits else torch.empty(F, n, dtype=torch.uint8)
    tab = torch.empty(F, bits.shape[1], dtype=torch.int64) if as_bits else None
    st = torch.zeros(1, dtype=torch.int64)
    nt = max(1, min(torch.get_num_threads(), B // MIN_POINTS_PER_THREAD))
    lib.tp_need(B, kv, vrows.data_ptr(), vw.data_ptr(), kl, lrows.data_ptr(), lw.data_ptr(), bits.shape[1],
                bits.data_ptr(), bits.shape[0], F, n, None if as_bits else out.data_ptr(), st.data_ptr(), nt,
                tab.data_ptr() if as_bits else None)
    r = int(st[0])
    if r == -1:
        raise IndexError("a row index outside its table (read with a non-zero weight)")
    if r != 0:
        raise MemoryError("tp_need could not allocate its tables")
    return NeedBits(tab, n) if as_bits else out.view(torch.bool)


def take(need: Tensor | NeedBits, done: Tensor) -> tuple[Tensor, int]:
    """The (frame, triangle) pairs of ``need`` (F, n) bool not yet in ``done`` (F, n) bool, which
    receives them: (their flat indices f·n + t (P,) int64 in order, the number of frames f holding one)
    — ``torch.nonzero(need & ~done)``, ``done |= that``, ``that.any(1).sum()`` in one pass (those
    torch operations without the library; its test oracle)."""
    if isinstance(need, NeedBits):
        return _take_bits(need, done)
    if need.shape != done.shape or need.ndim != 2 or need.dtype != torch.bool or done.dtype != torch.bool:
        raise ValueError("need and done (F, n) bool expected")
    lib = _lib()
    if lib is None or not (need.is_contiguous() and done.is_contiguous()):
        todo = need & ~done
        done |= todo
        return torch.nonzero(todo.view(-1), as_tuple=False).squeeze(-1), int(todo.any(1).sum())
    N, n = need.numel(), need.shape[1]
    counts = torch.zeros(2, dtype=torch.int64)
    a, b = need.view(torch.uint8), done.view(torch.uint8)
    lib.tp_take(N, max(n, 1), a.data_ptr(), b.data_ptr(), None, counts.data_ptr())
    pairs = torch.empty(int(counts[0]), dtype=torch.int64)
    if pairs.numel() == 0:
        return pairs, 0
    lib.tp_take(N, n, a.data_ptr(), b.data_ptr(), pairs.data_ptr(), counts.data_ptr())
    return pairs, int(counts[1])


def _take_bits(need: NeedBits, done: Tensor) -> tuple[Tensor, int]:
    """`take` of a `NeedBits` (``tp_take_bits``: its set bits in order; the same pairs, done and frame
    count as `take` of ``need.dense()``), or of ``need.dense()`` without the library."""
    F, n = need.shape
    if done.shape != (F, n) or done.dtype != torch.bool:
        raise ValueError("done (F, n) bool expected")
    lib = _lib()
    if lib is None or not done.is_contiguous() or not need.bits.is_contiguous() or F == 0 or n == 0:
        return take(need.dense(), done)
    nw = need.bits.shape[1]
    if nw != -(-n // 64) or need.bits.dtype != torch.int64:
        raise ValueError("a bit table of another shape")
    counts = torch.zeros(2, dtype=torch.int64)
    d = done.view(torch.uint8)
    lib.tp_take_bits(F, n, nw, need.bits.data_ptr(), d.data_ptr(), None, counts.data_ptr())
    pairs = torch.empty(int(counts[0]), dtype=torch.int64)
    if pairs.numel() == 0:
        return pairs, 0
    lib.tp_take_bits(F, n, nw, need.bits.data_ptr(), d.data_ptr(), pairs.data_ptr(), counts.data_ptr())
    return pairs, int(counts[1])


def comb_scatter(means: Tensor, rows: Tensor, frames: Tensor, out: Tensor) -> bool:
    """``out[frames] = means`` rows ``rows`` for the comb path's live-triangle means (B, n', 3, J)
    (row b·J + j: `lighting._comb_rows`, frame (b, j)) into ``out`` (F, 3, n'): one pass over the
    means instead of gathering (f, 3, n') from their permuted view and copying it in
    (``out.index_copy_(0, frames, lighting._comb_select(...))``, the fallback and test oracle). The
    same values. False (nothing written) without the library or for other layouts."""
    lib = _lib()
    if lib is None or means.ndim != 4 or out.ndim != 3 or means.dtype != torch.float32 or out.dtype != torch.float32 \
            or not (means.is_contiguous() and out.is_contiguous()) or means.device.type != "cpu" \
            or out.device.type != "cpu" or means.shape[2] != 3 or out.shape[1:] != (3, means.shape[1]) \
            or rows.shape != frames.shape or rows.ndim != 1:
        return False
    B, n, _, J = means.shape
    if rows.numel() == 0:
        return True
    rows, frames = rows.to(torch.int64), frames.to(torch.int64)
    if int(rows.min()) < 0 or int(rows.max()) >= B * J or int(frames.min()) < 0 or int(frames.max()) >= out.shape[0]:
        raise IndexError("a comb row or frame outside its table")
    dst = torch.full((B * J,), -1, dtype=torch.int64)
    dst[rows] = frames
    lib.tp_comb_scatter(B, n, J, means.data_ptr(), dst.data_ptr(), out.data_ptr())
    return True


def comb_pairs_uv(pairs: Tensor, u0: Tensor, v0: Tensor, g: float, wT: Tensor, H: int, W: int, CT: Tensor,
                  n_psi: int, J: int, out: Tensor) -> Tensor:
    """`comb_pairs` of ``lighting.comb_taps(u0, v0, g, wT, H, W, J)`` with the taps made in the loop for
    the listed pairs' items only (``tp_comb_pairs_uv``; the same fine values bit for bit, the same
    entries written): u0 (B, n, S) float64 and v0 (B, n, S) float32 the live triangles' base
    coordinates (`lighting._live_azimuthal_samples`), g = γ/2π, wT (n, S) float32 their samples'
    weights, CT the comb table of the H × W map (`lighting.comb_table`), J = n_phi (J | W). Raises
    RuntimeError without the library."""
    lib = _lib()
    if lib is None:
        raise RuntimeError("the native kernel is not available")
    F, C, n = out.shape
    if u0.ndim != 3 or u0.shape[1] != n or v0.shape != u0.shape or wT.shape != (n, u0.shape[2]) \
            or u0.dtype != torch.float64 or v0.dtype != torch.float32 or wT.dtype != torch.float32 \
            or CT.dtype != torch.float32 or out.dtype != torch.float32 or C != 3 or not out.is_contiguous() \
            or J > 64 or W % J or F != u0.shape[0] * J or F % n_psi or u0.shape[0] % n_psi \
            or u0.shape[2] > MAX_SAMPLES or H < 2:
        raise ValueError("u0 (B, n, S <= 64) float64, v0 (B, n, S) float32, wT (n, S) float32, "
                         "out (B·J, 3, n) float32 contiguous, J <= 64 dividing W expected")
    _on_cpu(u0, v0, wT, CT, out)
    m = W // J
    if CT.numel() != H * m * 3 * 2 * 2 * J:
        raise ValueError("the comb table of another map")
    pairs = _checked_pairs(pairs, F * n)
    if pairs.numel() == 0:
        return out
    B, _, S = u0.shape
    u0, v0, wT, CT = u0.contiguous(), v0.contiguous(), wT.contiguous(), CT.contiguous()
    return _comb_run(lib.tp_comb_pairs_uv, "tp_comb_pairs_uv", pairs, (n, S, n_psi, J, B),
                     (u0.data_ptr(), v0.data_ptr(), wT.data_ptr(), float(g), H, W, CT.data_ptr(), m), out)


def box(data: Tensor, k: int) -> Tensor | None:
    """`lighting.box_filtered` (data (H, W, C) float32, k >= 2 dividing H and W) by one C pass (``tp_box``:
    its float64 sums in its order, the same texels bit for bit; ~4x less time than its torch passes),
    or None without the library or for other layouts / dtypes (the torch path runs then)."""
    lib = _lib()
    if lib is None or data.dtype != torch.float32 or data.ndim != 3 or data.device.type != "cpu" \
            or not data.is_contiguous() or k < 2:
        return None
    H, W, C = data.shape
    if H % k or W % k:
        raise ValueError(f"k = {k} must divide the map's {H} x {W} texels")
    out = torch.empty(H // k, W // k, C, dtype=torch.float32)
    st = torch.zeros(1, dtype=torch.int64)
    # session 39: the output rows over the threads (`BOX_THREADS`; the same texels at any thread count)
    nt = max(1, min(torch.get_num_threads(), (H // k) // MIN_BOX_ROWS_PER_THREAD)) if BOX_THREADS else 1
    lib.tp_box(H, W, C, k, data.data_ptr(), out.data_ptr(), st.data_ptr(), nt)
    if int(st[0]) != 0:
        raise MemoryError("tp_box could not allocate its row")
    return out


def _on_cpu(*ts: Tensor) -> None:
    """ValueError unless every tensor is on the CPU."""
    for t in ts:
        if t.device.type != "cpu":
            raise ValueError("CPU tensors expected")


def _pair_threads(P: int) -> int:
    """Threads of a pass over P pairs (`MIN_PAIRS_PER_THREAD` each at least)."""
    return max(1, min(torch.get_num_threads(), P // MIN_PAIRS_PER_THREAD))


def _comb_run(fn, name: str, pairs: Tensor, head: tuple, tables: tuple, out: Tensor) -> Tensor:
    """Run a comb loop (``tp_comb_pairs`` / ``tp_comb_pairs_uv``: the checked ``pairs``, then ``head``
    = (n, S, n_psi, J, B), its ``tables``, ``out``, the threads and a status) and return ``out``;
    MemoryError when the loop could not allocate its tables."""
    P = pairs.numel()
    st = torch.zeros(1, dtype=torch.int64)
    fn(P, pairs.data_ptr(), *head, *tables, out.data_ptr(), _pair_threads(P), COMB_BLOCK, st.data_ptr())
    if int(st[0]) != 0:
        raise MemoryError(f"{name} could not allocate its tables")
    return out


def _checked_pairs(pairs: Tensor, size: int) -> Tensor:
    """``pairs`` as contiguous int64, every one inside a table of ``size`` entries (else IndexError)."""
    pairs = pairs.to(torch.int64).contiguous()
    if pairs.numel() and (int(pairs.min()) < 0 or int(pairs.max()) >= size):
        raise IndexError("a pair outside the table")
    return pairs


def project(pairs: Tensor, M: Tensor, cp: Tensor, wT: Tensor, H: int, W: int, Q: Tensor, out: Tensor) -> Tensor:
    """Project the pairs f·n + t (``pairs`` (P,) int64) into ``out`` (F, 3, n) float32 (returned): the
    fine value of live triangle t in frame f, as `lighting.quad_means` of `lighting.env_taps` with the
    frames' folded rotations M (F, 3, 3) = R @ T float32, the live triangles' sample planes cp (3, n, S)
    and weights wT (n, S) (`lighting._live_sample_planes`) and the map's quad rows Q (H·(W + 1), 16)
    (`latlong.quad_texels`; `latlong.quad_lane_weights`' lane constants are 0, 1, −1, so its weights are
    (1 − fx or fx)(1 − fy or fy) exactly, as the loop forms them)."""
    lib = _lib()
    if lib is None:
        raise RuntimeError("the native kernel is not available")
    F, C, n = out.shape
    S = cp.shape[2]
    if C != 3 or cp.shape[:2] != (3, n) or wT.shape != (n, S) or M.shape != (F, 3, 3) or Q.shape[1] != 16 \
            or S > MAX_SAMPLES:
        raise ValueError(f"out (F, 3, n), M (F, 3, 3), cp (3, n, S <= {MAX_SAMPLES}), wT (n, S), Q (·, 16) expected")
    for t in (M, cp, wT, Q, out):
        if t.dtype != torch.float32 or t.device.type != "cpu":
            raise ValueError("float32 CPU tensors expected")
    if not out.is_contiguous():
        raise ValueError("out must be contiguous")
    if Q.shape[0] < H * (W + 1):
        raise ValueError("quad rows of another map")
    pairs = _checked_pairs(pairs, F * n)
    P = pairs.numel()
    if P == 0:
        return out
    M, cp, wT, Q = (x.contiguous() for x in (M, cp, wT, Q))
    args = (P, pairs.data_ptr(), n, S, M.data_ptr(), cp.data_ptr(), wT.data_ptr(), H, W, Q.data_ptr(), out.data_ptr())
    nt = _pair_threads(P)
    lib.tp_project(*args) if nt == 1 else lib.tp_project_par(*args, nt, PROJECT_BLOCK)
    return out


def comb_pairs(pairs: Tensor, o: Tensor, w4: Tensor, CT: Tensor, n_psi: int, J: int, m: int, out: Tensor) -> Tensor:
    """The comb path's fine values (`lighting.comb_means` of a map turned about +Y only) of the pairs
    f·n + t (``pairs`` (P,) int64) only, into ``out`` (F, 3, n) float32 (returned): o (B, n, S) int32
    and w4 (B, n, S, 2, 2) float32 from `lighting.comb_taps` of the live triangles, CT the comb table
    (`lighting.comb_table`), J = n_phi frames per base row, m = W / J. The compiled reduction's sums on
    one thread bit for bit; every frame of an 8-frame group holding a listed pair is written (with its
    value), other entries untouched. Base rows b = i·n_psi + k, grid frame f = (i·J + j)·n_psi + k
    (`lighting._comb_rows`). Raises RuntimeError without the library."""
    lib = _lib()
    if lib is None:
        raise RuntimeError("the native kernel is not available")
    F, C, n = out.shape
    if o.ndim != 3 or o.shape[1] != n or w4.shape != (*o.shape, 2, 2) or C != 3 or o.dtype != torch.int32 \
            or w4.dtype != torch.float32 or CT.dtype != torch.float32 or out.dtype != torch.float32 \
            or not out.is_contiguous() or J > 64 or F != o.shape[0] * J or F % n_psi or o.shape[0] % n_psi:
        raise ValueError("o (B, n, S) int32, w4 (B, n, S, 2, 2) float32, out (B·J, 3, n) float32 contiguous, J <= 64 expected")
    _on_cpu(o, w4, CT, out)
    pairs = _checked_pairs(pairs, F * n)
    if pairs.numel() == 0:
        return out
    B, _, S = o.shape
    o, w4, CT = o.contiguous(), w4.contiguous(), CT.contiguous()
    if int(o.min()) < 0 or int(o.max()) + 3 * m * 4 * J + 2 * J + 2 * 4 * J + J - 1 >= CT.numel():   # rs + es + 2 cs + J - 1
        raise IndexError("a comb offset outside the table")
    return _comb_run(lib.tp_comb_pairs, "tp_comb_pairs", pairs, (n, S, n_psi, J, B),
                     (o.data_ptr(), w4.data_ptr(), CT.data_ptr(), m), out)
