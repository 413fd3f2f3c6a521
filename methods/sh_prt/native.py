"""SH PRT's native loops (`methods.core.native`): l' = M l for some glossy vertices only (Sloan 2002
§7), the list of those vertices, and the glossy samples' radiance added to their pixels
(`add_pixels`, bit-identical to its scatter_add_ oracle).

A frame whose lighting changed needs l' = M_x l at the vertices its glossy samples' faces touch
alone (creature bench: ~1/3 of the glossy vertices), not at all of them (`SHPRT._glossy_light`).
M is stored lighting-major ((C, n², Vg·n²) in memory, `method.lighting_major`), so one vertex's
matrix is n² runs of n² floats, one per lighting coefficient j; the loop reads those runs of the
listed vertices only and writes their l' rows of the channel-major (3, Vg, n²) table:

    out[c, r, i] = Σ_j l[j, c] · M[c', j, r·n² + i]        (c' = c for RGB transfer, 0 for grey)

with the sum over j in ascending order. `rows_torch` is the same product by a torch gather and
`apply_lighting`'s GEMM, the fallback (no compiler, ``PRTBENCH_COMPILE=0``) and the test oracle;
both equal `apply_lighting` over all rows to float32 round-off (the GEMM sums in its own order).
At 2+ threads the rows are split over OpenMP's team (the libgomp torch loaded): a Python thread
pool's hand-off waits for a core the OpenMP workers spin on (`methods.core.gouraud`).
"""
from __future__ import annotations

import ctypes
import math

import torch
from torch import Tensor

from methods.core import native
from methods.core.fused import compile_enabled

_SOURCE = r"""
#include <stdint.h>
#include <string.h>
#include <math.h>

#define RUN 16
typedef float v8 __attribute__((vector_size(32), aligned(4)));

/* The rows in runs of consecutive vertices (at most RUN; ``rows`` ascending, as `nonzero` gives
   them): a run of k vertices is one stretch of k·n² floats in each of M's n² lighting rows and
   in each channel of the output. Per 8 floats of the stretch the sums over j (ascending) stay in
   registers and each value of M is read once (grey transfer: for the three channels). */
static void lg_rows(int64_t C, int64_t n2, int64_t ncols, const float *X, const float *l,
                    const int64_t *rows, int64_t R, int64_t Vg, float *out) {
    int64_t q = 0;
    while (q < R) {
        int64_t k = 1;
        while (q + k < R && k < RUN && rows[q + k] == rows[q] + k) ++k;
        const int64_t w = k * n2, base = rows[q] * n2, w8 = w & ~(int64_t)7;
        for (int64_t c = 0; c < (C == 1 ? 1 : 3); ++c) {
            const float *Xc = X + c * n2 * ncols + base;
            float *o0 = out + (C == 1 ? 0 : c) * Vg * n2 + base;
            int64_t t = 0;
            for (; t < w8; t += 8) {
                v8 a0 = {0}, a1 = {0}, a2 = {0};
                for (int64_t j = 0; j < n2; ++j) {
                    const v8 v = *(const v8 *)(Xc + j * ncols + t);
                    if (C == 1) { a0 += l[j * 3] * v; a1 += l[j * 3 + 1] * v; a2 += l[j * 3 + 2] * v; }
                    else a0 += l[j * 3 + c] * v;
                }
                *(v8 *)(o0 + t) = a0;
                if (C == 1) { *(v8 *)(o0 + Vg * n2 + t) = a1; *(v8 *)(o0 + 2 * Vg * n2 + t) = a2; }
            }
            for (; t < w; ++t) {
                float s0 = 0, s1 = 0, s2 = 0;
                for (int64_t j = 0; j < n2; ++j) {
                    const float v = Xc[j * ncols + t];
                    if (C == 1) { s0 += l[j * 3] * v; s1 += l[j * 3 + 1] * v; s2 += l[j * 3 + 2] * v; }
                    else s0 += l[j * 3 + c] * v;
                }
                o0[t] = s0;
                if (C == 1) { o0[Vg * n2 + t] = s1; o0[2 * Vg * n2 + t] = s2; }
            }
        }
        q += k;
    }
}

/* The glossy rows a frame's glossy samples g read: mark the rows fg[face[g[s]]] (three per sample;
   all >= 0 on a glossy face) in ``mark`` (Vg bytes, zero on entry), then list the marked rows not
   yet ``valid`` (if given) in ascending order into ``rows``, their count into ``count``. */
void sh_need_rows(const int64_t *g, int64_t Qg, const int64_t *face, int64_t Mf, const int32_t *fg, int64_t Vg,
                  uint8_t *mark, const uint8_t *valid, int64_t *rows, int64_t *count) {
    for (int64_t s = 0; s < Qg; ++s) {
        const int64_t f = face[g[s]];                      /* < M by the G-buffer's contract; */
        const int32_t *r = fg + 3 * (f < 0 ? 0 : (f >= Mf ? Mf - 1 : f));   /* clamped, never read out */
        mark[r[0]] = 1; mark[r[1]] = 1; mark[r[2]] = 1;
    }
    int64_t n = 0;
    for (int64_t r = 0; r < Vg; ++r)
        if (mark[r] && !(valid && valid[r])) rows[n++] = r;
    *count = n;
}

/* Session 35: the rows of l' that a view's glossy samples read, from the G-buffer itself (no glossy list):
   the glossy samples are the pixel pass's (`px_range`: hit[q] && fk[f, 3] != 0, f = face[q] clamped to
   [0, Mf)), so the rows are fg[f] of the faces f that some hit sample lies on and whose fk[f, 3] != 0.
   The n samples are split over nt threads, each marking its faces in its own Mf + 1 bytes of ``fmark`` (nt·(Mf + 1),
   any content on entry; entry Mf a miss's), then merged; the glossy faces' rows marked in ``mark`` (Vg bytes, zero on entry)
   and those not yet ``valid`` (if given) listed in ascending order into ``rows``, their count into
   ``count``: the list `sh_need_rows` makes from the pixel pass's glossy list. */
void sh_view_rows(int64_t n, const int64_t *face, const uint8_t *hit, const float *fk, int64_t Mf,
                  const int32_t *fg, int64_t Vg, uint8_t *fmark, uint8_t *mark, const uint8_t *valid,
                  int64_t *rows, int64_t *count, int64_t nt) {
    if (nt < 1) nt = 1;
    #pragma omp parallel for num_threads(nt) schedule(static, 1) if (nt > 1)
    for (int64_t k = 0; k < nt; ++k) {
        uint8_t *fm = fmark + k * (Mf + 1);
        memset(fm, 0, (size_t)(Mf + 1));
        for (int64_t q = n * k / nt; q < n * (k + 1) / nt; ++q) {   /* stores only, no branch: a miss marks */
            int64_t f = face[q];                                      /* the spare entry Mf */
            f = f < 0 ? 0 : (f >= Mf ? Mf - 1 : f);
            fm[hit[q] ? f : Mf] = 1;
        }
    }
    for (int64_t f = 0; f < Mf; ++f) {
        uint8_t any = 0;
        for (int64_t k = 0; k < nt; ++k) any |= fmark[k * (Mf + 1) + f];
        if (any && fk[4 * f + 3] != 0.f) {
            const int32_t *r = fg + 3 * f;
            mark[r[0]] = 1; mark[r[1]] = 1; mark[r[2]] = 1;
        }
    }
    int64_t m = 0;
    for (int64_t r = 0; r < Vg; ++r)
        if (mark[r] && !(valid && valid[r])) rows[m++] = r;
    *count = m;
}

/* Session 41: `sh_view_rows` with ``mark`` zeroed here (a kept scratch buffer, not a fresh torch.zeros). */
void sh_view_rows_z(int64_t n, const int64_t *face, const uint8_t *hit, const float *fk, int64_t Mf,
                    const int32_t *fg, int64_t Vg, uint8_t *fmark, uint8_t *mark, const uint8_t *valid,
                    int64_t *rows, int64_t *count, int64_t nt) {
    memset(mark, 0, (size_t)Vg);
    sh_view_rows(n, face, hit, fk, Mf, fg, Vg, fmark, mark, valid, rows, count, nt);
}

/* Session 35: `sh.rotate_sampled` (c' = P Y(Rᵀ D) c, the coefficients of f(Rᵀd)) in one C call, float64:
   X = D R (K, 3), per direction j the n² real SH values y(X_j) by the normalised recurrence of
   `sh._terms_recurrence` (Holmes & Featherstone; the same basis as `sh.sh_terms`), (Y c)[j] (C), then
   out = P (Y c) (n², C). c (n², C), R (3, 3), D (K, 3), P (n², K) row-major doubles; n <= 8, C <= 4,
   K <= 4·64. The same sums as the compiled call in another order: float64 round-off. */
void sh_rotate(int64_t n, int64_t K, int64_t C, const double *c, const double *R, const double *D,
               const double *P, double *out) {
    const int64_t n2 = n * n;
    double Yc[256 * 4];
    const double sqrt2 = sqrt(2.0);
    for (int64_t j = 0; j < K; ++j) {
        const double *d = D + 3 * j;
        const double x = d[0] * R[0] + d[1] * R[3] + d[2] * R[6];
        const double y = d[0] * R[1] + d[1] * R[4] + d[2] * R[7];
        const double z = d[0] * R[2] + d[1] * R[5] + d[2] * R[8];
        double v[64];
        double qmm = 1.0 / sqrt(4.0 * 3.14159265358979323846), cr = 1.0, si = 0.0;
        for (int64_t m = 0; m < n; ++m) {
            if (m > 0) {
                qmm *= sqrt((double)(2 * m + 1) / (double)(2 * m));
                const double c2 = x * cr - y * si, s2 = x * si + y * cr;
                cr = c2; si = s2;
            }
            double qp2 = 0.0, qp = qmm;
            for (int64_t l = m; l < n; ++l) {
                double q;
                if (l == m) q = qp;
                else if (l == m + 1) q = sqrt((double)(2 * m + 3)) * z * qp;
                else {
                    const double a = sqrt((double)(4 * l * l - 1) / (double)(l * l - m * m));
                    const double b = sqrt((double)((l - 1) * (l - 1) - m * m) / (double)(4 * (l - 1) * (l - 1) - 1));
                    q = a * (z * qp - b * qp2);
                }
                if (m == 0) v[l * (l + 1)] = q;
                else { v[l * (l + 1) + m] = sqrt2 * q * cr; v[l * (l + 1) - m] = sqrt2 * q * si; }
                if (l > m) { qp2 = qp; qp = q; }
            }
        }
        for (int64_t ch = 0; ch < C; ++ch) {
            double acc = 0.0;
            for (int64_t i = 0; i < n2; ++i) acc += v[i] * c[i * C + ch];
            Yc[j * C + ch] = acc;
        }
    }
    for (int64_t i = 0; i < n2; ++i)
        for (int64_t ch = 0; ch < C; ++ch) {
            double acc = 0.0;
            for (int64_t j = 0; j < K; ++j) acc += P[i * K + j] * Yc[j * C + ch];
            out[i * C + ch] = acc;
        }
}

/* img[g[q] / S2, c] += vals[q, c] * inv for q ascending (one thread: each pixel's sum in the order of
   its samples, as scatter_add_ at one thread). g[q] / S2 < n by the caller's check. */
void sh_add_pixels(const int64_t *g, int64_t Q, int64_t S2, const float *vals, float inv, float *img) {
    for (int64_t q = 0; q < Q; ++q) {
        float *o = img + 3 * (g[q] / S2);
        const float *v = vals + 3 * q;
        o[0] += v[0] * inv; o[1] += v[1] * inv; o[2] += v[2] * inv;
    }
}

/* The pixel pass (`method._pixels_impl`, its oracle): per pixel p of [p0, p1) and sub-sample s,
   sample q = p·S2 + s, f = face[q] clamped to [0, Mf), (u, v) its barycentrics, w0 = 1 − u − v;
   glossy = hit[q] && fk[f, 3] != 0 (listed in ``gl``, ascending); kept = hit[q] && n·ωo > 0 && !glossy;
   per channel img[p, c] = (Σ_s kept ? max(0, fk[f, c] · (ef[f, c] w0 + ef[f, 3+c] u + ef[f, 6+c] v)) : 0)
   · inv, the sums in the oracle's order (no contraction: -ffp-contract=off). Arrays with element
   strides (row, column): bary, normal, wo. Returns the count of listed glossy samples. */
static int64_t px_range(int64_t p0, int64_t p1, int64_t S2, const int64_t *face, const uint8_t *hit,
                        const float *B, int64_t br, int64_t bc, const float *N, int64_t nr, int64_t nc,
                        const float *O, int64_t orr, int64_t oc, const float *ef, const float *fk, int64_t Mf,
                        float inv, float *img, int64_t *gl) {
    int64_t ng = 0;
    for (int64_t p = p0; p < p1; ++p) {
        float a0 = 0.f, a1 = 0.f, a2 = 0.f;
        for (int64_t s = 0; s < S2; ++s) {
            const int64_t q = p * S2 + s;
            int64_t f = face[q];
            f = f < 0 ? 0 : (f >= Mf ? Mf - 1 : f);
            const float *E = ef + 9 * f, *K = fk + 4 * f;
            const int h = hit[q] != 0;
            const int gs = h & (K[3] != 0.f);
            gl[ng] = q; ng += gs;                          /* branch-free append */
            const float ndo = N[q * nr] * O[q * orr] + N[q * nr + nc] * O[q * orr + oc]
                              + N[q * nr + 2 * nc] * O[q * orr + 2 * oc];
            const int keep = (ndo > 0.f) & h & !gs;
            const float u = B[q * br], v = B[q * br + bc];
            const float w0 = 1.0f - u - v;
            float x0 = K[0] * (E[0] * w0 + E[3] * u + E[6] * v);
            float x1 = K[1] * (E[1] * w0 + E[4] * u + E[7] * v);
            float x2 = K[2] * (E[2] * w0 + E[5] * u + E[8] * v);
            x0 = x0 < 0.f ? 0.f : x0;                       /* clamp_min (NaN kept) */
            x1 = x1 < 0.f ? 0.f : x1;
            x2 = x2 < 0.f ? 0.f : x2;
            x0 = keep ? x0 : 0.f; x1 = keep ? x1 : 0.f; x2 = keep ? x2 : 0.f;
            if (s == 0) { a0 = x0; a1 = x1; a2 = x2; }
            else { a0 += x0; a1 += x1; a2 += x2; }
        }
        img[3 * p] = a0 * inv; img[3 * p + 1] = a1 * inv; img[3 * p + 2] = a2 * inv;
    }
    return ng;
}

#ifdef __AVX2__
#include <immintrin.h>
/* 8 × 8 transpose of eight AVX2 rows in place (the pixel pass below and the glossy pass). */
static inline void tr8(__m256 *r) {
    __m256 t0 = _mm256_unpacklo_ps(r[0], r[1]), t1 = _mm256_unpackhi_ps(r[0], r[1]);
    __m256 t2 = _mm256_unpacklo_ps(r[2], r[3]), t3 = _mm256_unpackhi_ps(r[2], r[3]);
    __m256 t4 = _mm256_unpacklo_ps(r[4], r[5]), t5 = _mm256_unpackhi_ps(r[4], r[5]);
    __m256 t6 = _mm256_unpacklo_ps(r[6], r[7]), t7 = _mm256_unpackhi_ps(r[6], r[7]);
    __m256 s0 = _mm256_shuffle_ps(t0, t2, 0x44), s1 = _mm256_shuffle_ps(t0, t2, 0xEE);
    __m256 s2 = _mm256_shuffle_ps(t1, t3, 0x44), s3 = _mm256_shuffle_ps(t1, t3, 0xEE);
    __m256 s4 = _mm256_shuffle_ps(t4, t6, 0x44), s5 = _mm256_shuffle_ps(t4, t6, 0xEE);
    __m256 s6 = _mm256_shuffle_ps(t5, t7, 0x44), s7 = _mm256_shuffle_ps(t5, t7, 0xEE);
    r[0] = _mm256_permute2f128_ps(s0, s4, 0x20); r[1] = _mm256_permute2f128_ps(s1, s5, 0x20);
    r[2] = _mm256_permute2f128_ps(s2, s6, 0x20); r[3] = _mm256_permute2f128_ps(s3, s7, 0x20);
    r[4] = _mm256_permute2f128_ps(s0, s4, 0x31); r[5] = _mm256_permute2f128_ps(s1, s5, 0x31);
    r[6] = _mm256_permute2f128_ps(s2, s6, 0x31); r[7] = _mm256_permute2f128_ps(s3, s7, 0x31);
}
/* `px_range` at S2 = 4, eight samples (two pixels) per step in AVX2 lanes: the face rows gathered, every
   operation the scalar loop's in its order (elementwise IEEE, no contraction), each pixel's four
   samples summed in order ((x0 + x1) + x2) + x3, the glossy samples appended in ascending order: the
   same image and list bit for bit. Pixels [p0, p1); returns the count listed. */
#ifndef SH_GB_PF
#define SH_GB_PF 16      /* groups of 8 samples between the G-buffer streams' prefetch and their use; 0: none */
#endif
#ifndef SH_PX_PF
#define SH_PX_PF 8       /* groups of 8 samples between a group's face-row prefetch and its use (`px_range8`); 0: none */
#endif
#ifndef SH_PX_WIDE_STORE
#define SH_PX_WIDE_STORE 1  /* session 43: the pixel pair's second pixel stored 4 wide but in a range's last group */
#endif
#ifndef SH_PX_PF_STEP
#define SH_PX_PF_STEP 1  /* every sample's face rows prefetched (2: one per two samples, ...) */
#endif
static inline __m256 px_ld(const float *p, int64_t stride, __m256i lane) {
    if (stride == 1)
        return _mm256_loadu_ps(p);
    return _mm256_i32gather_ps(p, _mm256_mullo_epi32(lane, _mm256_set1_epi32((int32_t)stride)), 4);
}
static int64_t px_range8(int64_t p0, int64_t p1, const int64_t *face, const uint8_t *hit,
                         const float *B, int64_t br, int64_t bc, const float *N, int64_t nr, int64_t nc,
                         const float *O, int64_t orr, int64_t oc, const float *ef, const float *fk, int64_t Mf,
                         float inv, float *img, int64_t *gl) {
    int64_t ng = 0;
    const __m256i lane = _mm256_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7), lo = _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6);
    const __m256i zero64 = _mm256_setzero_si256(), top64 = _mm256_set1_epi64x(Mf - 1);
    const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f);
    float xs[3][8];
    __m256 X3[3];
    const __m256 invv = _mm256_set1_ps(inv);
    (void)xs; (void)X3; (void)invv;
    for (int64_t p = p0; p < p1; p += 2) {
        const int64_t q = p * 4;
        __m256i fa = _mm256_loadu_si256((const __m256i *)(face + q)), fb = _mm256_loadu_si256((const __m256i *)(face + q + 4));
        fa = _mm256_blendv_epi8(fa, zero64, _mm256_cmpgt_epi64(zero64, fa));
        fb = _mm256_blendv_epi8(fb, zero64, _mm256_cmpgt_epi64(zero64, fb));
        fa = _mm256_blendv_epi8(fa, top64, _mm256_cmpgt_epi64(fa, top64));
        fb = _mm256_blendv_epi8(fb, top64, _mm256_cmpgt_epi64(fb, top64));
        const __m256i f = _mm256_permute2x128_si256(_mm256_permutevar8x32_epi32(fa, lo),
                                                    _mm256_permutevar8x32_epi32(fb, lo), 0x20);   /* (8,) int32 */
#if SH_GB_PF > 0
        /* session 40: the G-buffer streams SH_GB_PF groups ahead (as `relight_add`'s stream, the hardware
           prefetch did not keep up with the frame's first, cold read) */
        if (p + 2 * SH_GB_PF < p1) {
            const int64_t qa = q + 8 * SH_GB_PF;
            __builtin_prefetch(face + qa); __builtin_prefetch(hit + qa);
            __builtin_prefetch(B + qa * br); __builtin_prefetch(B + qa * br + bc);
            __builtin_prefetch(N + qa * nr); __builtin_prefetch(N + qa * nr + 16 * nc);
            __builtin_prefetch(O + qa * orr); __builtin_prefetch(O + qa * orr + oc); __builtin_prefetch(O + qa * orr + 2 * oc);
        }
#endif
#if SH_PX_PF > 0
        /* session 40: the face rows (ef, fk: 1.4 MB on the creature bench, more than L2, read in screen order,
           not the faces' order) of the group SH_PX_PF ahead prefetched — their misses were ~30 % of the pass —
           every SH_PX_PF_STEP-th sample's (a pixel's samples mostly share a face) */
        if (p + 2 * SH_PX_PF < p1) {
            const int64_t *fq = face + q + 8 * SH_PX_PF;
            for (int b = 0; b < 8; b += SH_PX_PF_STEP) {
                int64_t ff = fq[b]; ff = ff < 0 ? 0 : (ff >= Mf ? Mf - 1 : ff);
                __builtin_prefetch(ef + 9 * ff); __builtin_prefetch(ef + 9 * ff + 8); __builtin_prefetch(fk + 4 * ff);
            }
        }
#endif
        int32_t fi[8];
        _mm256_storeu_si256((__m256i *)fi, f);
        __m256 E[8], K[4];
        for (int b = 0; b < 8; ++b)                         /* the rows, transposed below: E[k] lane b = ef[f_b, k] */
            E[b] = _mm256_loadu_ps(ef + 9 * (int64_t)fi[b]);
        tr8(E);
        const __m256 E8 = _mm256_setr_ps(ef[9 * (int64_t)fi[0] + 8], ef[9 * (int64_t)fi[1] + 8], ef[9 * (int64_t)fi[2] + 8],
                                         ef[9 * (int64_t)fi[3] + 8], ef[9 * (int64_t)fi[4] + 8], ef[9 * (int64_t)fi[5] + 8],
                                         ef[9 * (int64_t)fi[6] + 8], ef[9 * (int64_t)fi[7] + 8]);
        for (int b = 0; b < 4; ++b)
            K[b] = _mm256_set_m128(_mm_loadu_ps(fk + 4 * (int64_t)fi[b + 4]), _mm_loadu_ps(fk + 4 * (int64_t)fi[b]));
        {
            const __m256 t0 = _mm256_unpacklo_ps(K[0], K[1]), t1 = _mm256_unpackhi_ps(K[0], K[1]);
            const __m256 t2 = _mm256_unpacklo_ps(K[2], K[3]), t3 = _mm256_unpackhi_ps(K[2], K[3]);
            K[0] = _mm256_shuffle_ps(t0, t2, 0x44); K[1] = _mm256_shuffle_ps(t0, t2, 0xEE);
            K[2] = _mm256_shuffle_ps(t1, t3, 0x44); K[3] = _mm256_shuffle_ps(t1, t3, 0xEE);
        }
        const __m256i hv = _mm256_cvtepu8_epi32(_mm_loadl_epi64((const __m128i *)(hit + q)));
        const __m256 h = _mm256_castsi256_ps(_mm256_cmpgt_epi32(hv, _mm256_setzero_si256()));
        const __m256 K3 = K[3];
        const __m256 gs = _mm256_and_ps(h, _mm256_cmp_ps(K3, zero, _CMP_NEQ_UQ));
        int gm = _mm256_movemask_ps(gs);
        while (gm) {                                        /* ascending sample order */
            const int b = __builtin_ctz(gm);
            gl[ng++] = q + b;
            gm &= gm - 1;
        }
        __m256 N0, N1, N2;
        if (nr == 3 && nc == 1) {                           /* row-major (q, 3): 24 floats split into x, y, z */
            const float *np = N + 3 * q;
            const __m256 m03 = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(np)), _mm_loadu_ps(np + 12), 1);
            const __m256 m14 = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(np + 4)), _mm_loadu_ps(np + 16), 1);
            const __m256 m25 = _mm256_insertf128_ps(_mm256_castps128_ps256(_mm_loadu_ps(np + 8)), _mm_loadu_ps(np + 20), 1);
            const __m256 xy = _mm256_shuffle_ps(m14, m25, _MM_SHUFFLE(2, 1, 3, 2));
            const __m256 yz = _mm256_shuffle_ps(m03, m14, _MM_SHUFFLE(1, 0, 2, 1));
            N0 = _mm256_shuffle_ps(m03, xy, _MM_SHUFFLE(2, 0, 3, 0));
            N1 = _mm256_shuffle_ps(yz, xy, _MM_SHUFFLE(3, 1, 2, 0));
            N2 = _mm256_shuffle_ps(yz, m25, _MM_SHUFFLE(3, 0, 3, 1));
        } else {
            N0 = px_ld(N + q * nr, nr, lane); N1 = px_ld(N + q * nr + nc, nr, lane); N2 = px_ld(N + q * nr + 2 * nc, nr, lane);
        }
        const __m256 O0 = px_ld(O + q * orr, orr, lane), O1 = px_ld(O + q * orr + oc, orr, lane),
                     O2 = px_ld(O + q * orr + 2 * oc, orr, lane);
        const __m256 ndo = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(N0, O0), _mm256_mul_ps(N1, O1)), _mm256_mul_ps(N2, O2));
        const __m256 keep = _mm256_andnot_ps(gs, _mm256_and_ps(_mm256_cmp_ps(ndo, zero, _CMP_GT_OQ), h));
        const __m256 u = px_ld(B + q * br, br, lane), v = px_ld(B + q * br + bc, br, lane);
        const __m256 w0 = _mm256_sub_ps(_mm256_sub_ps(one, u), v);
        for (int c = 0; c < 3; ++c) {
            const __m256 Kc = K[c], Ea = E[c], Eb = E[3 + c], Ec = c == 2 ? E8 : E[6 + c];
            __m256 x = _mm256_mul_ps(Kc, _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(Ea, w0), _mm256_mul_ps(Eb, u)),
                                                       _mm256_mul_ps(Ec, v)));
            x = _mm256_blendv_ps(x, zero, _mm256_cmp_ps(x, zero, _CMP_LT_OQ));   /* clamp_min (NaN kept) */
            x = _mm256_and_ps(x, keep);
#ifdef SH_NO_VSUM
            _mm256_storeu_ps(xs[c], x);
#else
            X3[c] = x;
#endif
        }
#ifdef SH_NO_VSUM
        for (int k = 0; k < 2; ++k)
            for (int c = 0; c < 3; ++c) {
                float a = xs[c][4 * k];
                a += xs[c][4 * k + 1];
                a += xs[c][4 * k + 2];
                a += xs[c][4 * k + 3];
                img[3 * (p + k) + c] = a * inv;
            }
#else
        {   /* session 40: each pixel's ((x0 + x1) + x2) + x3 per channel in vector lanes (the scalar sums' order:
               the same bits) — X_c's 4 x 4 blocks (a pixel's samples, one per 128-bit lane) transposed so that
               lane c of S_s holds channel c's sample s; the two pixels' 3 values stored as 4 + masked 3 */
            const __m256 a01 = _mm256_unpacklo_ps(X3[0], X3[1]), b01 = _mm256_unpackhi_ps(X3[0], X3[1]);
            const __m256 a2z = _mm256_unpacklo_ps(X3[2], zero), b2z = _mm256_unpackhi_ps(X3[2], zero);
            const __m256 S0 = _mm256_shuffle_ps(a01, a2z, 0x44), S1 = _mm256_shuffle_ps(a01, a2z, 0xEE);
            const __m256 S2v = _mm256_shuffle_ps(b01, b2z, 0x44), S3 = _mm256_shuffle_ps(b01, b2z, 0xEE);
            const __m256 sum = _mm256_mul_ps(_mm256_add_ps(_mm256_add_ps(_mm256_add_ps(S0, S1), S2v), S3), invv);
            _mm_storeu_ps(img + 3 * p, _mm256_castps256_ps128(sum));
#if SH_PX_WIDE_STORE
            /* session 43: the second pixel's 3 values stored as 4 floats (the 4th, 0, on the next pixel's first
               channel, which the next group's store writes after it, in this thread) except in a range's last
               group, whose pixel after is another range's: AMD's masked store was a slow spot of the pass */
            if (p + 2 < p1)
                _mm_storeu_ps(img + 3 * p + 3, _mm256_extractf128_ps(sum, 1));
            else
#endif
            _mm_maskstore_ps(img + 3 * p + 3, _mm_setr_epi32(-1, -1, -1, 0), _mm256_extractf128_ps(sum, 1));
        }
#endif
    }
    return ng;
}
#endif

/* `px_range`, by `px_range8` where it applies (fast, AVX2, S2 = 4, strides whose gather indices fit
   int32), the odd last pixel by the scalar loop. */
static int64_t px_any(int64_t p0, int64_t p1, int64_t S2, const int64_t *face, const uint8_t *hit,
                      const float *B, int64_t br, int64_t bc, const float *N, int64_t nr, int64_t nc,
                      const float *O, int64_t orr, int64_t oc, const float *ef, const float *fk, int64_t Mf,
                      float inv, float *img, int64_t *gl, int64_t fast) {
#ifdef __AVX2__
    if (fast && S2 == 4 && Mf < ((int64_t)1 << 27) && br > 0 && br < (1 << 27) && nr > 0 && nr < (1 << 27)
            && orr > 0 && orr < (1 << 27)) {
        const int64_t pm = p0 + ((p1 - p0) & ~(int64_t)1);
        const int64_t ng = px_range8(p0, pm, face, hit, B, br, bc, N, nr, nc, O, orr, oc, ef, fk, Mf, inv, img, gl);
        return ng + px_range(pm, p1, S2, face, hit, B, br, bc, N, nr, nc, O, orr, oc, ef, fk, Mf, inv, img, gl + ng);
    }
#endif
    (void)fast;
    return px_range(p0, p1, S2, face, hit, B, br, bc, N, nr, nc, O, orr, oc, ef, fk, Mf, inv, img, gl);
}

void sh_pixels(int64_t n, int64_t S2, const int64_t *face, const uint8_t *hit,
               const float *B, int64_t br, int64_t bc, const float *N, int64_t nr, int64_t nc,
               const float *O, int64_t orr, int64_t oc, const float *ef, const float *fk, int64_t Mf,
               float inv, float *img, int64_t *gl, int64_t *count, int64_t nt, int64_t fast) {
    if (nt <= 1) {
        const int64_t c = px_any(0, n, S2, face, hit, B, br, bc, N, nr, nc, O, orr, oc, ef, fk, Mf, inv, img, gl, fast);
        if (count) *count = c;
        return;
    }
    int64_t cnt[64];
    if (nt > 64) nt = 64;
    #pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t k = 0; k < nt; ++k) {
        const int64_t a = n * k / nt, e = n * (k + 1) / nt;
        cnt[k] = px_any(a, e, S2, face, hit, B, br, bc, N, nr, nc, O, orr, oc, ef, fk, Mf, inv, img, gl + a * S2, fast);
    }
    if (!count) return;                                /* session 41: no list wanted (a relit frame) */
    int64_t tot = cnt[0];
    for (int64_t k = 1; k < nt; ++k) {                 /* each range's list after the previous ones */
        memmove(gl + tot, gl + (n * k / nt) * S2, (size_t)cnt[k] * sizeof(int64_t));
        tot += cnt[k];
    }
    *count = tot;
}

/* A lighting-only frame's glossy samples (`method._relight_add`) from the packed relight cache
   (`relight_pack`): per block of 8 samples [d (n², 8) | q (n², 8) | kd (3, 8) | ks (3, 8)] floats;
   o_d[c] = Σ_i l[i, c] d[i], o_g[c] = Σ_i l[i, c] q[i] (i ascending), then
   img[pix[s], c] += max(0, kd[c] o_d[c] + ks[c] o_g[c]) · inv for the samples s in [a, b), ascending
   (the blocks that hold them computed whole: a block's values do not depend on the range). */
#ifndef SH_RL_PF
#define SH_RL_PF 4
#endif
static void relight_range(int64_t a, int64_t b, int64_t n2, const float *blk, const float *l, const int64_t *pix,
                          float inv, float *img) {
    const int64_t bs = (2 * n2 + 6) * 8;
    for (int64_t q0 = a - a % 8; q0 < b; q0 += 8) {
        const float *bk = blk + (q0 / 8) * bs;
#if SH_RL_PF > 0
        /* session 40: the block SH_RL_PF ahead ((2n² + 6)·8 floats) prefetched */
        if (q0 + 8 * SH_RL_PF < b)
            for (int64_t o = 0; o < bs; o += 16) __builtin_prefetch(bk + SH_RL_PF * bs + o);
#endif
        v8 d0 = {0}, d1 = {0}, d2 = {0}, g0 = {0}, g1 = {0}, g2 = {0};
        for (int64_t i = 0; i < n2; ++i) {
            const v8 d = *(const v8 *)(bk + 8 * i), g = *(const v8 *)(bk + 8 * (n2 + i));
            const float l0 = l[3 * i], l1 = l[3 * i + 1], l2 = l[3 * i + 2];
            d0 += l0 * d; d1 += l1 * d; d2 += l2 * d;
            g0 += l0 * g; g1 += l1 * g; g2 += l2 * g;
        }
        const float *k = bk + 16 * n2;
        const v8 r0 = *(const v8 *)(k) * d0 + *(const v8 *)(k + 24) * g0;
        const v8 r1 = *(const v8 *)(k + 8) * d1 + *(const v8 *)(k + 32) * g1;
        const v8 r2 = *(const v8 *)(k + 16) * d2 + *(const v8 *)(k + 40) * g2;
        const int64_t b0 = q0 < a ? a - q0 : 0, nb = b - q0 < 8 ? b - q0 : 8;
        for (int64_t s = b0; s < nb; ++s) {
            float *o = img + 3 * pix[q0 + s];
            o[0] += (r0[s] < 0.f ? 0.f : r0[s]) * inv;
            o[1] += (r1[s] < 0.f ? 0.f : r1[s]) * inv;
            o[2] += (r2[s] < 0.f ? 0.f : r2[s]) * inv;
        }
    }
}

/* session 39: the samples [0, Q) split over nt threads at PIXEL boundaries (pix ascending: the split
   Q k / nt moved on while the pixel repeats), so that each pixel's samples are added in ascending order by
   one thread — the same sums in the same order as one thread: the same bits at any thread count (the
   pass was serial: ~1.1 ms of a creature bench L / E frame at 2 threads). */
static int64_t relight_split(int64_t Q, int64_t k, int64_t nt, const int64_t *pix) {
    int64_t s = Q * k / nt;
    while (s > 0 && s < Q && pix[s] == pix[s - 1]) ++s;
    return s;
}

void sh_relight_add(int64_t Q, int64_t n2, const float *blk, const float *l, const int64_t *pix, float inv,
                    float *img, int64_t nt) {
    if (nt <= 1) { relight_range(0, Q, n2, blk, l, pix, inv, img); return; }
    #pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int64_t k = 0; k < nt; ++k)
        relight_range(relight_split(Q, k, nt, pix), relight_split(Q, k + 1, nt, pix), n2, blk, l, pix, inv, img);
}

/* l' = M l at the listed rows from a VERTEX-major grey M (Vg, n², n²) (row r's matrix one
   contiguous n²·n² block; `rows_vertex_major`): out[c, r, i] = Σ_j M[r, i, j] l[j, c], the sum over j
   as 8-float partial vectors (j in blocks of 8), their lanes pairwise, then the tail j ≥ 8⌊n²/8⌋;
   n² ≤ 64. */
#ifdef __AVX2__
#include <immintrin.h>
/* The lane sums s_k = ((a_k[0] + a_k[4]) + (a_k[1] + a_k[5])) + ((a_k[2] + a_k[6]) + (a_k[3] + a_k[7])) of
   8 vectors as one vector (s_0 .. s_7), each addition the scalar one's (hadd adds neighbours: x0 + x1 is
   a_k[0] + a_k[4] plus a_k[1] + a_k[5]; an IEEE sum does not depend on its operands' order). */
static inline v8 hsum8x8(const v8 *a) {
    __m256 x[4];
    for (int k = 0; k < 4; ++k) {         /* [a_2k lo + hi | a_2k+1 lo + hi]: (x0, x1, x2, x3) of each */
        const __m256 u = (__m256)a[2 * k], w = (__m256)a[2 * k + 1];
        x[k] = _mm256_add_ps(_mm256_permute2f128_ps(u, w, 0x20), _mm256_permute2f128_ps(u, w, 0x31));
    }
    const __m256 h0 = _mm256_hadd_ps(x[0], x[1]);    /* (y0, y1) of a_0, a_2 | of a_1, a_3 */
    const __m256 h1 = _mm256_hadd_ps(x[2], x[3]);    /* (y0, y1) of a_4, a_6 | of a_5, a_7 */
    const __m256 s = _mm256_hadd_ps(h0, h1);         /* s_0 s_2 s_4 s_6 | s_1 s_3 s_5 s_7 */
    return (v8)_mm256_permutevar8x32_ps(s, _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7));
}
#endif
#ifndef SH_VM_PF
#define SH_VM_PF 2  /* rows between a row's prefetch and its sums (`vm_rows`); 0: none */
#endif
static void vm_rows(int64_t n2, const float *__restrict M, const float *__restrict lt, const int64_t *rows,
                    int64_t R, int64_t Vg, float *__restrict out) {
    const int64_t n8 = n2 & ~(int64_t)7, nb = n8 / 8;           /* nb <= 8: n² <= 64 */
    v8 L[3][8];
    for (int64_t c = 0; c < 3; ++c)
        for (int64_t b = 0; b < nb; ++b) L[c][b] = *(const v8 *)(lt + c * n2 + 8 * b);
    for (int64_t q = 0; q < R; ++q) {
        const int64_t r = rows[q];
        const float *Mr = M + r * n2 * n2;
#if SH_VM_PF > 0
        /* session 40: the row SH_VM_PF ahead (n⁴ floats, one block) prefetched while this one is summed:
           the listed rows are scattered over M (24 MB on the creature bench, out of cache when a lighting
           change's frame starts), and each row's start waited for memory */
        if (q + SH_VM_PF < R) {
            const float *Mn = M + rows[q + SH_VM_PF] * n2 * n2;
            for (int64_t o = 0; o < n2 * n2; o += 16) __builtin_prefetch(Mn + o);
            __builtin_prefetch(Mn + n2 * n2 - 1);
        }
#endif
        int64_t i0 = 0;
#ifdef __AVX2__
        /* session 34: 8 outputs i at a time per channel, their lane sums as one 8 × 8 transpose-and-add
           (`hsum8x8`: the same additions in the same order as the scalar sums below) and the tail
           j >= n8 across the 8 lanes: the same bits, a third of the instructions */
        for (; i0 + 8 <= n2; i0 += 8)
            for (int64_t c = 0; c < 3; ++c) {
                v8 a[8];
                for (int k = 0; k < 8; ++k) {
                    const float *row = Mr + (i0 + k) * n2;
                    v8 acc = {0};
                    for (int64_t b = 0; b < nb; ++b)
                        acc += *(const v8 *)(row + 8 * b) * L[c][b];
                    a[k] = acc;
                }
                v8 sv = hsum8x8(a);
                for (int64_t j = n8; j < n2; ++j) {
                    const float *col = Mr + i0 * n2 + j;
                    const v8 x = {col[0], col[n2], col[2 * n2], col[3 * n2], col[4 * n2], col[5 * n2], col[6 * n2],
                                  col[7 * n2]};
                    sv = sv + x * lt[c * n2 + j];
                }
                __builtin_memcpy(out + (c * Vg + r) * n2 + i0, &sv, 32);
            }
#endif
        for (int64_t i = i0; i < n2; ++i) {
            const float *row = Mr + i * n2;
            v8 a0 = {0}, a1 = {0}, a2 = {0};
            for (int64_t b = 0; b < nb; ++b) {
                const v8 x = *(const v8 *)(row + 8 * b);
                a0 += x * L[0][b]; a1 += x * L[1][b]; a2 += x * L[2][b];
            }
            float s0 = ((a0[0] + a0[4]) + (a0[1] + a0[5])) + ((a0[2] + a0[6]) + (a0[3] + a0[7]));
            float s1 = ((a1[0] + a1[4]) + (a1[1] + a1[5])) + ((a1[2] + a1[6]) + (a1[3] + a1[7]));
            float s2 = ((a2[0] + a2[4]) + (a2[1] + a2[5])) + ((a2[2] + a2[6]) + (a2[3] + a2[7]));
            for (int64_t j = n8; j < n2; ++j) {
                s0 += row[j] * lt[j]; s1 += row[j] * lt[n2 + j]; s2 += row[j] * lt[2 * n2 + j];
            }
            out[r * n2 + i] = s0; out[(Vg + r) * n2 + i] = s1; out[(2 * Vg + r) * n2 + i] = s2;
        }
    }
}

/* Session 41: `sh_vm_rows` from l (n², 3) as the frame holds it (its (3, n²) transpose built here, not by
   three torch calls), the rows checked here ([0, Vg): else *bad = 1 and nothing written). */
void sh_vm_rows(int64_t n2, const float *M, const float *lt, const int64_t *rows, int64_t R, int64_t Vg,
                float *out, int64_t nt);
void sh_vm_rows_l(int64_t n2, const float *M, const float *l, const int64_t *rows, int64_t R, int64_t Vg,
                  float *out, int64_t nt, int64_t *bad) {
    for (int64_t q = 0; q < R; ++q)
        if (rows[q] < 0 || rows[q] >= Vg) { *bad = 1; return; }
    float lt[3 * 64];
    for (int64_t j = 0; j < n2; ++j)
        for (int64_t c = 0; c < 3; ++c) lt[c * n2 + j] = l[3 * j + c];
    sh_vm_rows(n2, M, lt, rows, R, Vg, out, nt);
}

void sh_vm_rows(int64_t n2, const float *M, const float *lt, const int64_t *rows, int64_t R, int64_t Vg,
                float *out, int64_t nt) {
    if (nt <= 1) { vm_rows(n2, M, lt, rows, R, Vg, out); return; }
    #pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t k = 0; k < nt; ++k) {
        const int64_t a = R * k / nt, e = R * (k + 1) / nt;
        vm_rows(n2, M, lt, rows + a, e - a, Vg, out);
    }
}

/* The glossy samples' whole radiance (`method._glossy_samples_impl`, its oracle: Sloan 2002 §6-7)
   for odd orders n (n² − 1 a multiple of 8), AVX2. Per block of 8 samples g[q]: their scalars across
   the 8 lanes (n̂ = n/|n|, d = n̂·ωo, R = 2 d n̂ − ωo normalised to (x, y, z), sc = n·ωo⁺ on
   Blinn-Phong else 1, the powers Re / Im (x + iy)^k), y_i(R) = A_i(z) T_i for i ≥ 1 (Horner in z
   over the tables of `_sh_factor_tables`, T_i = 1 or the power sel[i] picks) into a (n² − 1, 8)
   block, transposed 8 × 8 to per-sample rows; then per sample and channel
   spec = Σ_{i≥1} (w0 L[a0, i] + u L[a1, i] + v L[a2, i]) y_i G_i sc + (the same at i = 0) Y00 G_0 sc,
   e from the corner table, out = n·ωo > 0 ? max(0, kd e + ks spec) : 0. */
#ifdef __AVX2__
#include <immintrin.h>
static inline float hsum8(__m256 a) {
    __m128 l = _mm256_castps256_ps128(a), h = _mm256_extractf128_ps(a, 1);
    l = _mm_add_ps(l, h);
    l = _mm_add_ps(l, _mm_movehl_ps(l, l));
    l = _mm_add_ss(l, _mm_shuffle_ps(l, l, 1));
    return _mm_cvtss_f32(l);
}
#define GMAXB 8     /* (n² − 1) / 8 <= 8: orders <= 7 */
#ifndef SH_PF_DIST
#define SH_PF_DIST 1 /* blocks of 8 glossy samples between a block's prefetch and its use */
#endif
#ifdef __FMA__
#define MADD(a, b, c) (fused ? _mm256_fmadd_ps(a, b, c) : _mm256_add_ps(_mm256_mul_ps(a, b), c))
#else
#define MADD(a, b, c) _mm256_add_ps(_mm256_mul_ps(a, b), c)
#endif
static inline __attribute__((always_inline)) void gl_body(
                     int64_t q0, int64_t q1, int64_t n, const int64_t *g, const int64_t *face, int64_t Mf,
                     const int64_t *reg, int64_t Rn, const float *B, int64_t br, int64_t bc,
                     const float *N, int64_t nr, int64_t nc, const float *O, int64_t orr, int64_t oc,
                     const float *ef, const int32_t *fg, const float *lg, int64_t lsc, int64_t lsr,
                     const float *kd, const float *ks, const float *G, const uint8_t *vcos,
                     const float *A, const int32_t *sel, float *out, float *img, int64_t S2, float inv,
                     const int fused) {
    const int64_t n2 = n * n, m = n2 - 1, nb = m / 8;
    const float Y00 = 0.28209479177387814f;
    float fu[8], fv[8], fnx[8], fny[8], fnz[8], fox[8], foy[8], foz[8], fvc[8];
    int64_t fi[8], ri[8];
    float X[8], Yv[8], Z[8], SC[8], FR[8];
    __m256 yb[GMAXB][8];
    for (int64_t b0 = q0; b0 < q1; b0 += 8) {
        const int64_t nb8 = q1 - b0 < 8 ? q1 - b0 : 8;
        for (int64_t b = 0; b < 8; ++b) {
            const int64_t s = g[b0 + (b < nb8 ? b : nb8 - 1)];
            int64_t f = face[s]; f = f < 0 ? 0 : (f >= Mf ? Mf - 1 : f);
            int64_t r = reg[s]; r = r < 0 ? 0 : (r >= Rn ? Rn - 1 : r);
            fi[b] = f; ri[b] = r;
            fu[b] = B[s * br]; fv[b] = B[s * br + bc];
            fnx[b] = N[s * nr]; fny[b] = N[s * nr + nc]; fnz[b] = N[s * nr + 2 * nc];
            fox[b] = O[s * orr]; foy[b] = O[s * orr + oc]; foz[b] = O[s * orr + 2 * oc];
            fvc[b] = vcos[r] ? 1.0f : 0.0f;
        }
#ifndef SH_NO_PREFETCH
        /* session 40: the rows of l' (9 per sample: 3 corners x 3 channels, n² floats each) of the block
           SH_PF_DIST blocks ahead prefetched while this block computes its y(R) and sums (the rows' first
           loads were the pass's hot spot: L2 misses on a table larger than L2; the first blocks' rows at
           the range's start); a face repeated from the sample before skipped */
        for (int64_t pb = (b0 == q0 ? b0 : b0 + 8 * SH_PF_DIST); pb <= b0 + 8 * SH_PF_DIST && pb < q1; pb += 8) {
            const int64_t e = q1 - pb < 8 ? q1 - pb : 8;
            int64_t pf = -1;
            for (int64_t b = 0; b < e; ++b) {
                int64_t f = face[g[pb + b]]; f = f < 0 ? 0 : (f >= Mf ? Mf - 1 : f);
                if (f == pf) continue;
                pf = f;
                const int32_t *fr = fg + 3 * f;
                for (int64_t k = 0; k < 3; ++k)
                    for (int64_t c = 0; c < 3; ++c) {
                        const float *L = lg + c * lsc + fr[k] * lsr;
                        __builtin_prefetch(L);
                        __builtin_prefetch(L + n2 - 1);
                        if (n2 > 16) __builtin_prefetch(L + 16);
                    }
            }
        }
#ifndef SH_NO_PREFETCH2
        /* and, one block further, what that prefetch and the block's gather read first: the face's rows of
           l' (fg) and the sample's region (reg: not read by the pixel pass, so out of cache) */
        for (int64_t pb = (b0 == q0 ? b0 : b0 + 8 * (SH_PF_DIST + 1)); pb <= b0 + 8 * (SH_PF_DIST + 1) && pb < q1; pb += 8) {
            const int64_t e = q1 - pb < 8 ? q1 - pb : 8;
            for (int64_t b = 0; b < e; ++b) {
                const int64_t x = g[pb + b];
                int64_t f = face[x]; f = f < 0 ? 0 : (f >= Mf ? Mf - 1 : f);
                __builtin_prefetch(fg + 3 * f);
                __builtin_prefetch(reg + x);
            }
        }
#endif
#endif
        {
            const __m256 nx0 = _mm256_loadu_ps(fnx), ny0 = _mm256_loadu_ps(fny), nz0 = _mm256_loadu_ps(fnz);
            const __m256 ox = _mm256_loadu_ps(fox), oy = _mm256_loadu_ps(foy), oz = _mm256_loadu_ps(foz);
            const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f), tiny = _mm256_set1_ps(1e-12f);
            const __m256 two = _mm256_set1_ps(2.0f);
            __m256 dot0 = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(nx0, ox), _mm256_mul_ps(ny0, oy)), _mm256_mul_ps(nz0, oz));
            _mm256_storeu_ps(FR, _mm256_and_ps(_mm256_cmp_ps(dot0, zero, _CMP_GT_OQ), one));
            __m256 nn = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(nx0, nx0), _mm256_mul_ps(ny0, ny0)), _mm256_mul_ps(nz0, nz0));
            nn = _mm256_max_ps(_mm256_sqrt_ps(nn), tiny);
            const __m256 nx = _mm256_div_ps(nx0, nn), ny = _mm256_div_ps(ny0, nn), nz = _mm256_div_ps(nz0, nn);
            const __m256 d = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(nx, ox), _mm256_mul_ps(ny, oy)), _mm256_mul_ps(nz, oz));
            const __m256 d2 = _mm256_mul_ps(two, d);
            const __m256 Rx = _mm256_sub_ps(_mm256_mul_ps(d2, nx), ox), Ry = _mm256_sub_ps(_mm256_mul_ps(d2, ny), oy);
            const __m256 Rz = _mm256_sub_ps(_mm256_mul_ps(d2, nz), oz);
            __m256 rn = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(Rx, Rx), _mm256_mul_ps(Ry, Ry)), _mm256_mul_ps(Rz, Rz));
            rn = _mm256_max_ps(_mm256_sqrt_ps(rn), tiny);
            const __m256 x = _mm256_div_ps(Rx, rn), y = _mm256_div_ps(Ry, rn), z = _mm256_div_ps(Rz, rn);
            _mm256_storeu_ps(X, x); _mm256_storeu_ps(Yv, y); _mm256_storeu_ps(Z, z);
            const __m256 vc = _mm256_cmp_ps(_mm256_loadu_ps(fvc), zero, _CMP_NEQ_OQ);
            _mm256_storeu_ps(SC, _mm256_blendv_ps(one, _mm256_max_ps(d, zero), vc));
            __m256 T[16];                                    /* 1, Re_1, Im_1, Re_2, ... */
            T[0] = one;
            __m256 cm = x, sm = y;
            for (int64_t k = 1; k < n; ++k) {
                if (k > 1) {
                    const __m256 c2 = _mm256_sub_ps(_mm256_mul_ps(x, cm), _mm256_mul_ps(y, sm));
                    sm = _mm256_add_ps(_mm256_mul_ps(x, sm), _mm256_mul_ps(y, cm));
                    cm = c2;
                }
                T[2 * k - 1] = cm; T[2 * k] = sm;
            }
            for (int64_t i = 0; i < m; ++i) {
                __m256 P = _mm256_set1_ps(A[(n - 1) * m + i]);
                for (int64_t j = n - 2; j >= 0; --j) P = MADD(P, z, _mm256_set1_ps(A[j * m + i]));
                yb[i / 8][i % 8] = _mm256_mul_ps(P, T[sel[i]]);
            }
            for (int64_t k = 0; k < nb; ++k) tr8(yb[k]);          /* yb[k][b]: lanes 8k.. of sample b */
        }
        for (int64_t b = 0; b < nb8; ++b) {
            float *o = out + 3 * (b0 + b);
            float *po = img ? img + 3 * (g[b0 + b] / S2) : 0;   /* `sh_add_pixels`' sum, sample by sample */
            if (FR[b] == 0.0f) {
                o[0] = o[1] = o[2] = 0.0f;
                if (po) { po[0] += o[0] * inv; po[1] += o[1] * inv; po[2] += o[2] * inv; }
                continue;
            }
            const int64_t f = fi[b], r = ri[b];
            const float u = fu[b], v = fv[b], w0 = 1.0f - u - v, sc = SC[b];
            const float *Gr = G + r * n2;
            const __m256 scv = _mm256_set1_ps(sc);
            __m256 q[GMAXB];
            for (int64_t k = 0; k < nb; ++k)
                q[k] = _mm256_mul_ps(yb[k][b], _mm256_mul_ps(_mm256_loadu_ps(Gr + 1 + 8 * k), scv));
            const float y0 = Y00 * Gr[0] * sc;
            const int32_t *fr = fg + 3 * f;
            const float *ec = ef + 9 * f;
            const __m256 W = _mm256_set1_ps(w0), U = _mm256_set1_ps(u), V = _mm256_set1_ps(v);
            float ov[3];
            for (int64_t c = 0; c < 3; ++c) {
                const float *L0 = lg + c * lsc + fr[0] * lsr, *L1 = lg + c * lsc + fr[1] * lsr,
                            *L2 = lg + c * lsc + fr[2] * lsr;
                __m256 acc = _mm256_setzero_ps();
                for (int64_t k = 0; k < nb; ++k) {
                    __m256 li;
                    if (fused)      /* ((L0 w0) + L1 u) + L2 v, each add fused with its product */
                        li = MADD(_mm256_loadu_ps(L2 + 1 + 8 * k), V,
                                  MADD(_mm256_loadu_ps(L1 + 1 + 8 * k), U, _mm256_mul_ps(_mm256_loadu_ps(L0 + 1 + 8 * k), W)));
                    else
                        li = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(_mm256_loadu_ps(L0 + 1 + 8 * k), W),
                                                         _mm256_mul_ps(_mm256_loadu_ps(L1 + 1 + 8 * k), U)),
                                           _mm256_mul_ps(_mm256_loadu_ps(L2 + 1 + 8 * k), V));
                    acc = fused ? MADD(li, q[k], acc) : _mm256_add_ps(acc, _mm256_mul_ps(li, q[k]));
                }
                const float spec = hsum8(acc) + (L0[0] * w0 + L1[0] * u + L2[0] * v) * y0;
                const float e = ec[c] * w0 + ec[3 + c] * u + ec[6 + c] * v;
                const float val = kd[r * 3 + c] * e + ks[r * 3 + c] * spec;
                ov[c] = val < 0.0f ? 0.0f : val;
            }
            /* session 43: the values kept in registers for the pixel's add (they were stored to ``out`` and read
               back: ``out`` and ``img`` may alias, as far as the compiler knows) */
            o[0] = ov[0]; o[1] = ov[1]; o[2] = ov[2];
            if (po) { po[0] += ov[0] * inv; po[1] += ov[1] * inv; po[2] += ov[2] * inv; }
        }
    }
}
#undef MADD

/* `gl_body` as session 28 wrote it (fused = 0: the compiled kernel's products and sums in its order) or,
   on FMA builds (fused = 1), with Horner's steps for y(R) and the reduction's multiply-adds fused
   (l' interpolated as fma(L2, v, fma(L1, u, L0 w0)), acc = fma(l', q, acc)): 52 instead of 88 vector
   operations per glossy sample at order 5, other roundings (float32 round-off). */
static void gl_range(int64_t q0, int64_t q1, int64_t n, const int64_t *g, const int64_t *face, int64_t Mf,
                     const int64_t *reg, int64_t Rn, const float *B, int64_t br, int64_t bc,
                     const float *N, int64_t nr, int64_t nc, const float *O, int64_t orr, int64_t oc,
                     const float *ef, const int32_t *fg, const float *lg, int64_t lsc, int64_t lsr,
                     const float *kd, const float *ks, const float *G, const uint8_t *vcos,
                     const float *A, const int32_t *sel, float *out, float *img, int64_t S2, float inv,
                     int64_t fused) {
#ifdef __FMA__
    /* session 43: the paper's order 5 (the perf suite's) a body of its own, n a constant (its loops unrolled:
       the same operations, the same bits; `ORDER5_BODY`); fused = 3: fused, always the body for any n */
    if (fused == 1 && n == 5) {
        gl_body(q0, q1, 5, g, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, ef, fg, lg, lsc, lsr, kd, ks, G,
                vcos, A, sel, out, img, S2, inv, 1);
        return;
    }
    if (fused) {
        gl_body(q0, q1, n, g, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, ef, fg, lg, lsc, lsr, kd, ks, G,
                vcos, A, sel, out, img, S2, inv, 1);
        return;
    }
#endif
    gl_body(q0, q1, n, g, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, ef, fg, lg, lsc, lsr, kd, ks, G,
            vcos, A, sel, out, img, S2, inv, 0);
}
#endif

void sh_glossy(int64_t Q, int64_t n, const int64_t *g, const int64_t *face, int64_t Mf, const int64_t *reg, int64_t Rn,
               const float *B, int64_t br, int64_t bc, const float *N, int64_t nr, int64_t nc,
               const float *O, int64_t orr, int64_t oc, const float *ef, const int32_t *fg, const float *lg,
               int64_t lsc, int64_t lsr, const float *kd, const float *ks, const float *G, const uint8_t *vcos,
               const float *A, const int32_t *sel, float *out, int64_t nt, int64_t *ok, int64_t fused,
               float *img, int64_t S2, float inv) {
#ifdef __AVX2__
    *ok = 1;
    if (nt <= 1) {
        gl_range(0, Q, n, g, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, ef, fg, lg, lsc, lsr, kd, ks, G,
                 vcos, A, sel, out, img, S2, inv, fused);
        return;
    }
    /* img != NULL: the ranges start at a pixel's first listed sample (g ascending), so each pixel's samples
       are added by one thread in their order, as `sh_add_pixels` adds them */
    #pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t k = 0; k < nt; ++k) {
        int64_t a = Q * k / nt, e = Q * (k + 1) / nt;
        if (img) {
            while (a > 0 && a < Q && g[a] / S2 == g[a - 1] / S2) ++a;
            while (e > 0 && e < Q && g[e] / S2 == g[e - 1] / S2) ++e;
        }
        if (a < e)
            gl_range(a, e, n, g, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, ef, fg, lg, lsc, lsr, kd, ks, G,
                     vcos, A, sel, out, img, S2, inv, fused);
    }
#else
    *ok = 0;
#endif
}

/* A view frame in one pass (session 32, `view`): the pixel pass (`sh_pixels`) and the glossy pass adding
   into the pixels (`sh_glossy` with img), per chunk of ``chunk`` pixels (even) — the chunk's pixels by
   `px_any`, its glossy samples listed in a chunk-local buffer, then shaded by `gl_range` and added to the
   chunk's pixels while its G-buffer rows are still in cache. Each pixel's value is written and then its
   glossy samples added in ascending order by one thread, as the two passes do: the same image bit for
   bit, whatever the thread count (chunks handed out dynamically: the glossy samples are not spread
   evenly over the image). One OpenMP region per frame instead of two, no glossy list or radiance array
   returned. ``ok`` = 0 (nothing written) without AVX2. */
#define VIEW_CHUNK_SAMPLES 1024
void sh_view(int64_t npx, int64_t S2, const int64_t *face, const uint8_t *hit,
             const float *B, int64_t br, int64_t bc, const float *N, int64_t nr, int64_t nc,
             const float *O, int64_t orr, int64_t oc, const float *ef, const float *fk, int64_t Mf,
             float inv, float *img, int64_t fast, int64_t n, const int64_t *reg, int64_t Rn,
             const int32_t *fg, const float *lg, int64_t lsc, int64_t lsr, const float *kd, const float *ks,
             const float *G, const uint8_t *vcos, const float *A, const int32_t *sel, int64_t fused,
             int64_t chunk, int64_t nt, int64_t *ok) {
#ifdef __AVX2__
    *ok = 1;
    if (chunk < 2) chunk = 2;
    chunk &= ~(int64_t)1;
    if (chunk * S2 > VIEW_CHUNK_SAMPLES) chunk = VIEW_CHUNK_SAMPLES / S2 > 0 ? VIEW_CHUNK_SAMPLES / S2 : 1;
    const int64_t nch = (npx + chunk - 1) / chunk;
    #pragma omp parallel for num_threads(nt > 0 ? nt : 1) schedule(dynamic, 2) if (nt > 1)
    for (int64_t k = 0; k < nch; ++k) {
        int64_t gl[VIEW_CHUNK_SAMPLES];
        float out[3 * VIEW_CHUNK_SAMPLES];
        const int64_t p0 = k * chunk, p1 = p0 + chunk < npx ? p0 + chunk : npx;
        const int64_t ng = px_any(p0, p1, S2, face, hit, B, br, bc, N, nr, nc, O, orr, oc, ef, fk, Mf, inv, img, gl, fast);
        if (ng)
            gl_range(0, ng, n, gl, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, ef, fg, lg, lsc, lsr, kd, ks,
                     G, vcos, A, sel, out, img, S2, inv, fused);
    }
#else
    *ok = 0;
#endif
}

void sh_lg_rows(int64_t C, int64_t n2, int64_t ncols, const float *X, const float *l,
                const int64_t *rows, int64_t R, int64_t Vg, float *out, int64_t nt) {
    if (nt <= 1) { lg_rows(C, n2, ncols, X, l, rows, R, Vg, out); return; }
    #pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t k = 0; k < nt; ++k) {
        const int64_t a = R * k / nt, e = R * (k + 1) / nt;
        lg_rows(C, n2, ncols, X, l, rows + a, e - a, Vg, out);
    }
}

/* Session 40: the relight cache of a lighting-only frame (`method.SHPRT._relight_build`, its oracle: the
   same quantities, sums in another order, float32 round-off) straight into `relight_add`'s packed layout
   (`relight_pack`: per block of 8 samples [d (n², 8) | q (n², 8) | kd (3, 8) | ks (3, 8)], a short last
   block zero-padded). Per glossy sample s = g[q]: f = face[s], r = reg[s] (clamped), w = (1 − u − v, u, v);
   n̂ = n/max(|n|, 1e-12), R = 2(n̂·ωo)n̂ − ωo normalised, y_i(R) = A_i(z) T_i (`_sh_factor_tables`, as
   `sh_glossy`), qv_i = y_i G[r, i] (× max(n̂·ωo, 0) where vcos[r]); d_i = Σ_k w_k t[F[f, k], i] (t at
   T + v·tv + i·ti) and the transferred lobe Σ_k w_k Σ_i qv_i M[fg[f, k], i, j] (M vertex-major (Vg, n², n²));
   kd, ks of region r, zero where n·ωo <= 0; pix[q] = s / S2. Blocks [b0, b1). n² <= 64. */
/* acc[j] = Σ_k w_k (Σ_i qv_i M_k[i, j]) (i ascending, then k: the sums of the scalar loop before, in 8-lane
   blocks of j held in registers, the j >= n8 tail scalar) — M_k = Mv's row ai[k] (n² x n², row-major). */
static inline __attribute__((always_inline)) void rb_lobe(const int64_t n2, const float *Mv, const int32_t *ai,
                                                          const float *qv, const float *wk, float *acc) {
    const int64_t n8 = n2 & ~(int64_t)7, nbj = n8 / 8;
    v8 A8[8];
    float At[8];
    for (int64_t b = 0; b < nbj; ++b) A8[b] = (v8){0};
    for (int64_t j = n8; j < n2; ++j) At[j - n8] = 0.f;
    for (int64_t k = 0; k < 3; ++k) {
        const float *Mk = Mv + (int64_t)ai[k] * n2 * n2;
        v8 T8[8];
        float Tt[8];
        for (int64_t b = 0; b < nbj; ++b) T8[b] = (v8){0};
        for (int64_t j = n8; j < n2; ++j) Tt[j - n8] = 0.f;
        for (int64_t i = 0; i < n2; ++i) {
            const float a = qv[i];
            const float *row = Mk + i * n2;
            for (int64_t b = 0; b < nbj; ++b) T8[b] += a * *(const v8 *)(row + 8 * b);
            for (int64_t j = n8; j < n2; ++j) Tt[j - n8] += a * row[j];
        }
        const float w = wk[k];
        for (int64_t b = 0; b < nbj; ++b) A8[b] += T8[b] * w;
        for (int64_t j = n8; j < n2; ++j) At[j - n8] += Tt[j - n8] * w;
    }
    for (int64_t b = 0; b < nbj; ++b) __builtin_memcpy(acc + 8 * b, &A8[b], 32);
    for (int64_t j = n8; j < n2; ++j) acc[j] = At[j - n8];
}

/* one glossy sample x: its face and region (clamped into range), barycentrics u, v, the front flag and the
   n² coefficients qv of its lobe about the reflected view direction (Y00·G_0·sc, then each band's Legendre
   polynomial in Z times the azimuth factor cos / sin(k φ) by recurrence times G times sc, sc = n·ωo for
   view-cosine BRDFs): the scalar set-up of rb_range and of rb_range2's path without AVX2 (the same operations) */
static inline void rb_sample(int64_t x, int64_t n, const int64_t *face, int64_t Mf, const int64_t *reg, int64_t Rn,
                             const float *B, int64_t br, int64_t bc, const float *N, int64_t nr, int64_t nc,
                             const float *O, int64_t orr, int64_t oc, const float *G, const uint8_t *vcos,
                             const float *A, const int32_t *sel, int64_t *fo, int64_t *ro, float *uo, float *vo,
                             float *fronto, float *qv) {
    const int64_t n2 = n * n, m = n2 - 1;
    const float Y00 = 0.28209479177387814f;
    int64_t f = face[x]; f = f < 0 ? 0 : (f >= Mf ? Mf - 1 : f);
    int64_t r = reg[x]; r = r < 0 ? 0 : (r >= Rn ? Rn - 1 : r);
    const float u = B[x * br], v = B[x * br + bc], w0 = 1.0f - u - v;
    const float nx0 = N[x * nr], ny0 = N[x * nr + nc], nz0 = N[x * nr + 2 * nc];
    const float ox = O[x * orr], oy = O[x * orr + oc], oz = O[x * orr + 2 * oc];
    const float front = (nx0 * ox + ny0 * oy) + nz0 * oz > 0.f ? 1.0f : 0.0f;
    float nn = sqrtf(nx0 * nx0 + ny0 * ny0 + nz0 * nz0);
    nn = nn > 1e-12f ? nn : 1e-12f;
    const float nx = nx0 / nn, ny = ny0 / nn, nz = nz0 / nn;
    const float d = (nx * ox + ny * oy) + nz * oz, d2 = 2.0f * d;
    const float Rx = d2 * nx - ox, Ry = d2 * ny - oy, Rz = d2 * nz - oz;
    float rn = sqrtf(Rx * Rx + Ry * Ry + Rz * Rz);
    rn = rn > 1e-12f ? rn : 1e-12f;
    const float X = Rx / rn, Y = Ry / rn, Z = Rz / rn;
    const float sc = vcos[r] ? (d > 0.f ? d : 0.f) : 1.0f;
    float Tp[16];
    Tp[0] = 1.0f;
    float cm = X, sm = Y;
    for (int64_t k = 1; k < n; ++k) {
        if (k > 1) {
            const float c2 = X * cm - Y * sm;
            sm = X * sm + Y * cm;
            cm = c2;
        }
        Tp[2 * k - 1] = cm; Tp[2 * k] = sm;
    }
    const float *Gr = G + r * n2;
    qv[0] = Y00 * Gr[0] * sc;
    for (int64_t i = 0; i < m; ++i) {
        float P = A[(n - 1) * m + i];
        for (int64_t j = n - 2; j >= 0; --j) P = P * Z + A[j * m + i];
        qv[1 + i] = P * Tp[sel[i]] * Gr[1 + i] * sc;
    }
    (void)w0;
    *fo = f; *ro = r; *uo = u; *vo = v; *fronto = front;
}

static void rb_range(int64_t b0, int64_t b1, int64_t Q, int64_t n, const int64_t *g, const int64_t *face, int64_t Mf,
                     const int64_t *reg, int64_t Rn, const float *B, int64_t br, int64_t bc, const float *N,
                     int64_t nr, int64_t nc, const float *O, int64_t orr, int64_t oc, const int64_t *F,
                     const int32_t *fg, const float *T, int64_t tv, int64_t ti, const float *Mv, const float *kd,
                     const float *ks, const float *G, const uint8_t *vcos, const float *A, const int32_t *sel,
                     int64_t S2, float *blk, int64_t *pix) {
    const int64_t n2 = n * n, bs = (2 * n2 + 6) * 8;
    float qv[64], acc[64];
    for (int64_t bi = b0; bi < b1; ++bi) {
        float *bk = blk + bi * bs;
        memset(bk, 0, (size_t)bs * sizeof(float));
        for (int64_t s = 0; s < 8; ++s) {
            const int64_t q = bi * 8 + s;
            if (q >= Q) break;
            const int64_t x = g[q];
            int64_t f, r;
            float u, v, front;
            rb_sample(x, n, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, G, vcos, A, sel, &f, &r, &u, &v, &front, qv);
            const float w0 = 1.0f - u - v;
            pix[q] = x / S2;
            const int64_t *vi = F + 3 * f;
            const int32_t *ai = fg + 3 * f;
            const float wk[3] = {w0, u, v};
            const float *t0 = T + vi[0] * tv, *t1 = T + vi[1] * tv, *t2 = T + vi[2] * tv;
            for (int64_t i = 0; i < n2; ++i)
                bk[8 * i + s] = (t0[i * ti] * w0 + t1[i * ti] * u) + t2[i * ti] * v;
            if (n2 == 25) rb_lobe(25, Mv, ai, qv, wk, acc);     /* order 5: the loops unrolled */
            else rb_lobe(n2, Mv, ai, qv, wk, acc);
            for (int64_t j = 0; j < n2; ++j) bk[8 * (n2 + j) + s] = acc[j];
            for (int64_t c = 0; c < 3; ++c) {
                bk[16 * n2 + 8 * c + s] = kd[r * 3 + c] * front;
                bk[16 * n2 + 24 + 8 * c + s] = ks[r * 3 + c] * front;
            }
        }
    }
}

/* Session 42 (sh42): `rb_range` with (AVX2) each block's per-sample scalars and lobe row qv (n̂, R, sc, the
   powers, y_i(R) G_i sc by Horner) computed across the block's 8 samples in vector lanes (`rb_range` ran them
   per sample with a run-time order's short loops: ~1 ms of a creature bench build at 1 thread), the three
   corners' lobes summed in ONE loop over i (`rb_lobe3`: nine independent 8-lane accumulator chains where
   `rb_lobe` ran the corners one after the other), each sample's d and lobe written to a contiguous row and the
   block's 2n² rows stored by 8 x 8 transposes (AVX2: where 2n² scalar stores 32 bytes apart per sample were;
   the pass 1.06x, bit-identical), and no memset of each block (every lane a sample writes is written; the
   last block's padding lanes zeroed). Every operation and sum is `rb_range`'s, in its order
   (IEEE elementwise, no contraction): the same bits (tested). Tried and dropped: the next faces' M blocks and
   transfer rows prefetched 4-16 samples ahead (no gain, cold or warm: the lobe is bound by its arithmetic,
   ~75 % of the pass in `perf`). */
static inline __attribute__((always_inline)) void rb_lobe3(const int64_t n2, const float *Mv, const int32_t *ai,
                                                           const float *qv, const int64_t qs, const float *wk,
                                                           float *acc) {
    const int64_t n8 = n2 & ~(int64_t)7, nbj = n8 / 8;
    const float *M0 = Mv + (int64_t)ai[0] * n2 * n2, *M1 = Mv + (int64_t)ai[1] * n2 * n2,
                *M2 = Mv + (int64_t)ai[2] * n2 * n2;
    v8 T0[8], T1[8], T2[8];
    float t0[8], t1[8], t2[8];
    for (int64_t b = 0; b < nbj; ++b) { T0[b] = (v8){0}; T1[b] = (v8){0}; T2[b] = (v8){0}; }
    for (int64_t j = n8; j < n2; ++j) { t0[j - n8] = 0.f; t1[j - n8] = 0.f; t2[j - n8] = 0.f; }
    for (int64_t i = 0; i < n2; ++i) {
        const float a = qv[i * qs];
        const float *r0 = M0 + i * n2, *r1 = M1 + i * n2, *r2 = M2 + i * n2;
        for (int64_t b = 0; b < nbj; ++b) {
            T0[b] += a * *(const v8 *)(r0 + 8 * b);
            T1[b] += a * *(const v8 *)(r1 + 8 * b);
            T2[b] += a * *(const v8 *)(r2 + 8 * b);
        }
        for (int64_t j = n8; j < n2; ++j) {
            t0[j - n8] += a * r0[j]; t1[j - n8] += a * r1[j]; t2[j - n8] += a * r2[j];
        }
    }
    const float w0 = wk[0], w1 = wk[1], w2 = wk[2];
    for (int64_t b = 0; b < nbj; ++b) {
        v8 A = (v8){0};
        A += T0[b] * w0; A += T1[b] * w1; A += T2[b] * w2;
        __builtin_memcpy(acc + 8 * b, &A, 32);
    }
    for (int64_t j = n8; j < n2; ++j) {
        float A = 0.f;
        A += t0[j - n8] * w0; A += t1[j - n8] * w1; A += t2[j - n8] * w2;
        acc[j] = A;
    }
}

static void rb_range2(int64_t b0, int64_t b1, int64_t Q, int64_t n, const int64_t *g, const int64_t *face, int64_t Mf,
                      const int64_t *reg, int64_t Rn, const float *B, int64_t br, int64_t bc, const float *N,
                      int64_t nr, int64_t nc, const float *O, int64_t orr, int64_t oc, const int64_t *F,
                      const int32_t *fg, const float *T, int64_t tv, int64_t ti, const float *Mv, const float *kd,
                      const float *ks, const float *G, const uint8_t *vcos, const float *A, const int32_t *sel,
                      int64_t S2, float *blk, int64_t *pix) {
    const int64_t n2 = n * n, m = n2 - 1, bs = (2 * n2 + 6) * 8;
    const float Y00 = 0.28209479177387814f;
#ifdef __AVX2__
    float QV[64][8], FRv[8];          /* per block: qv_i of its 8 samples in lanes, front */
    float DL[8][128];                 /* per block: each sample's [d | lobe] (2n² <= 128) */
    int64_t fi[8], ri[8];
    float fu[8], fv[8], fnx[8], fny[8], fnz[8], fox[8], foy[8], foz[8], fvc[8];
#else
    float qv[64], acc[64];
#endif
    for (int64_t bi = b0; bi < b1; ++bi) {
        float *bk = blk + bi * bs;
        const int64_t nb8 = Q - bi * 8 < 8 ? Q - bi * 8 : 8;
        if (nb8 < 8) {                                        /* the last block's padding lanes: zero */
            for (int64_t r = 0; r < 2 * n2 + 6; ++r)
                for (int64_t s = nb8; s < 8; ++s) bk[8 * r + s] = 0.f;
#ifdef __AVX2__
            for (int64_t s = nb8; s < 8; ++s) memset(DL[s], 0, sizeof(DL[s]));
#endif
        }
#ifdef __AVX2__
        /* the samples' scalars and qv across 8 lanes (each operation `rb_range`'s scalar one, IEEE elementwise,
           no contraction: the same bits; max(a, b) = a > b ? a : b as the scalar selects, NaN included) */
        for (int64_t b = 0; b < 8; ++b) {
            const int64_t x = g[bi * 8 + (b < nb8 ? b : nb8 - 1)];
            int64_t f = face[x]; f = f < 0 ? 0 : (f >= Mf ? Mf - 1 : f);
            int64_t r = reg[x]; r = r < 0 ? 0 : (r >= Rn ? Rn - 1 : r);
            fi[b] = f; ri[b] = r;
            fu[b] = B[x * br]; fv[b] = B[x * br + bc];
            fnx[b] = N[x * nr]; fny[b] = N[x * nr + nc]; fnz[b] = N[x * nr + 2 * nc];
            fox[b] = O[x * orr]; foy[b] = O[x * orr + oc]; foz[b] = O[x * orr + 2 * oc];
            fvc[b] = vcos[r] ? 1.0f : 0.0f;
        }
        {
            const __m256 nx0 = _mm256_loadu_ps(fnx), ny0 = _mm256_loadu_ps(fny), nz0 = _mm256_loadu_ps(fnz);
            const __m256 ox = _mm256_loadu_ps(fox), oy = _mm256_loadu_ps(foy), oz = _mm256_loadu_ps(foz);
            const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f), tiny = _mm256_set1_ps(1e-12f);
            const __m256 two = _mm256_set1_ps(2.0f);
            const __m256 dot0 = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(nx0, ox), _mm256_mul_ps(ny0, oy)),
                                              _mm256_mul_ps(nz0, oz));
            _mm256_storeu_ps(FRv, _mm256_and_ps(_mm256_cmp_ps(dot0, zero, _CMP_GT_OQ), one));
            __m256 nn = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(nx0, nx0), _mm256_mul_ps(ny0, ny0)),
                                      _mm256_mul_ps(nz0, nz0));
            nn = _mm256_max_ps(_mm256_sqrt_ps(nn), tiny);
            const __m256 nx = _mm256_div_ps(nx0, nn), ny = _mm256_div_ps(ny0, nn), nz = _mm256_div_ps(nz0, nn);
            const __m256 d = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(nx, ox), _mm256_mul_ps(ny, oy)),
                                           _mm256_mul_ps(nz, oz));
            const __m256 d2 = _mm256_mul_ps(two, d);
            const __m256 Rx = _mm256_sub_ps(_mm256_mul_ps(d2, nx), ox), Ry = _mm256_sub_ps(_mm256_mul_ps(d2, ny), oy);
            const __m256 Rz = _mm256_sub_ps(_mm256_mul_ps(d2, nz), oz);
            __m256 rn = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(Rx, Rx), _mm256_mul_ps(Ry, Ry)), _mm256_mul_ps(Rz, Rz));
            rn = _mm256_max_ps(_mm256_sqrt_ps(rn), tiny);
            const __m256 x = _mm256_div_ps(Rx, rn), y = _mm256_div_ps(Ry, rn), z = _mm256_div_ps(Rz, rn);
            const __m256 vc = _mm256_cmp_ps(_mm256_loadu_ps(fvc), zero, _CMP_NEQ_OQ);
            const __m256 sc = _mm256_blendv_ps(one, _mm256_max_ps(d, zero), vc);
            __m256 Tp[16];
            Tp[0] = one;
            __m256 cm = x, sm = y;
            for (int64_t k = 1; k < n; ++k) {
                if (k > 1) {
                    const __m256 c2 = _mm256_sub_ps(_mm256_mul_ps(x, cm), _mm256_mul_ps(y, sm));
                    sm = _mm256_add_ps(_mm256_mul_ps(x, sm), _mm256_mul_ps(y, cm));
                    cm = c2;
                }
                Tp[2 * k - 1] = cm; Tp[2 * k] = sm;
            }
            const float *G0 = G + ri[0] * n2, *G1 = G + ri[1] * n2, *G2 = G + ri[2] * n2, *G3 = G + ri[3] * n2,
                        *G4 = G + ri[4] * n2, *G5 = G + ri[5] * n2, *G6 = G + ri[6] * n2, *G7 = G + ri[7] * n2;
            _mm256_storeu_ps(QV[0], _mm256_mul_ps(_mm256_mul_ps(_mm256_set1_ps(Y00),
                _mm256_setr_ps(G0[0], G1[0], G2[0], G3[0], G4[0], G5[0], G6[0], G7[0])), sc));
            for (int64_t i = 0; i < m; ++i) {
                __m256 P = _mm256_set1_ps(A[(n - 1) * m + i]);
                for (int64_t j = n - 2; j >= 0; --j) P = _mm256_add_ps(_mm256_mul_ps(P, z), _mm256_set1_ps(A[j * m + i]));
                const __m256 Gi = _mm256_setr_ps(G0[1 + i], G1[1 + i], G2[1 + i], G3[1 + i], G4[1 + i], G5[1 + i],
                                                 G6[1 + i], G7[1 + i]);
                _mm256_storeu_ps(QV[1 + i], _mm256_mul_ps(_mm256_mul_ps(_mm256_mul_ps(P, Tp[sel[i]]), Gi), sc));
            }
        }
#endif
        for (int64_t s = 0; s < nb8; ++s) {
            const int64_t q = bi * 8 + s;
            const int64_t x = g[q];
            pix[q] = x / S2;
#ifdef __AVX2__
            const int64_t f = fi[s], r = ri[s];
            const float u = fu[s], v = fv[s], w0 = 1.0f - u - v, front = FRv[s];
            const float *qv = &QV[0][s];
            const int64_t qs = 8;
#else
            int64_t f, r;
            float u, v, front;
            rb_sample(x, n, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, G, vcos, A, sel, &f, &r, &u, &v, &front, qv);
            const float w0 = 1.0f - u - v;
            const int64_t qs = 1;
#endif
            const int64_t *vi = F + 3 * f;
            const int32_t *ai = fg + 3 * f;
            const float wk[3] = {w0, u, v};
            const float *t0 = T + vi[0] * tv, *t1 = T + vi[1] * tv, *t2 = T + vi[2] * tv;
#ifdef __AVX2__
            /* d and the lobe into the sample's row of DL (contiguous), transposed into the block below */
            float *dl = DL[s];
            for (int64_t i = 0; i < n2; ++i)
                dl[i] = (t0[i * ti] * w0 + t1[i * ti] * u) + t2[i * ti] * v;
            if (n2 == 25) rb_lobe3(25, Mv, ai, qv, qs, wk, dl + 25);    /* order 5: the loops unrolled */
            else rb_lobe3(n2, Mv, ai, qv, qs, wk, dl + n2);
#else
            for (int64_t i = 0; i < n2; ++i)
                bk[8 * i + s] = (t0[i * ti] * w0 + t1[i * ti] * u) + t2[i * ti] * v;
            if (n2 == 25) rb_lobe3(25, Mv, ai, qv, qs, wk, acc);    /* order 5: the loops unrolled */
            else rb_lobe3(n2, Mv, ai, qv, qs, wk, acc);
            for (int64_t j = 0; j < n2; ++j) bk[8 * (n2 + j) + s] = acc[j];
#endif
            for (int64_t c = 0; c < 3; ++c) {
                bk[16 * n2 + 8 * c + s] = kd[r * 3 + c] * front;
                bk[16 * n2 + 24 + 8 * c + s] = ks[r * 3 + c] * front;
            }
        }
#ifdef __AVX2__
        /* the block's [d | lobe] rows (2n², 8) from the samples' DL rows: 8 x 8 transposes, the tail rows
           scalar; the lanes of the samples past Q zero (their DL rows zeroed above) */
        const int64_t r2 = 2 * n2, r8 = r2 & ~(int64_t)7;
        for (int64_t r0 = 0; r0 < r8; r0 += 8) {
            __m256 x[8];
            for (int b = 0; b < 8; ++b) x[b] = _mm256_loadu_ps(DL[b] + r0);
            tr8(x);
            for (int b = 0; b < 8; ++b) _mm256_storeu_ps(bk + 8 * (r0 + b), x[b]);
        }
        for (int64_t rr = r8; rr < r2; ++rr)
            for (int64_t b = 0; b < 8; ++b) bk[8 * rr + b] = DL[b][rr];
#endif
    }
}

void sh_relight_build(int64_t Q, int64_t n, const int64_t *g, const int64_t *face, int64_t Mf, const int64_t *reg,
                      int64_t Rn, const float *B, int64_t br, int64_t bc, const float *N, int64_t nr, int64_t nc,
                      const float *O, int64_t orr, int64_t oc, const int64_t *F, const int32_t *fg, const float *T,
                      int64_t tv, int64_t ti, const float *Mv, const float *kd, const float *ks, const float *G,
                      const uint8_t *vcos, const float *A, const int32_t *sel, int64_t S2, float *blk,
                      int64_t *pix, int64_t nt, int64_t P, int64_t *bad) {
    const int64_t nb = (Q + 7) / 8;
    if (nt < 0) {                                     /* session 42: `rb_range2` (the same bits), -nt threads */
        nt = -nt;
        if (P >= 0) {                                 /* the samples checked here: g in [0, P), else *bad = 1 */
            int64_t lo = 0, hi = 0;
            for (int64_t q = 0; q < Q; ++q) { lo |= g[q] < 0; hi |= g[q] >= P; }
            if (lo | hi) { *bad = 1; return; }
        }
        if (nt <= 1) {
            rb_range2(0, nb, Q, n, g, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, F, fg, T, tv, ti, Mv, kd, ks,
                      G, vcos, A, sel, S2, blk, pix);
            return;
        }
        #pragma omp parallel for num_threads(nt) schedule(static)
        for (int64_t k = 0; k < nt; ++k)
            rb_range2(nb * k / nt, nb * (k + 1) / nt, Q, n, g, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, F,
                      fg, T, tv, ti, Mv, kd, ks, G, vcos, A, sel, S2, blk, pix);
        return;
    }
    if (nt <= 1) {
        rb_range(0, nb, Q, n, g, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, F, fg, T, tv, ti, Mv, kd, ks,
                 G, vcos, A, sel, S2, blk, pix);
        return;
    }
    #pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t k = 0; k < nt; ++k)
        rb_range(nb * k / nt, nb * (k + 1) / nt, Q, n, g, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, F, fg,
                 T, tv, ti, Mv, kd, ks, G, vcos, A, sel, S2, blk, pix);
}

/* Session 41: a lighting change's light stage in one call (`SHPRT._light_stage` on grey transfer, `light`):
   R = W Qᵀ (3 × 3 row-major doubles), lw = `sh_rotate`(cl, R) (n², 3) doubles, lf = (float) lw,
   e3[c, v] = Σ_j lf[j, c] t[j, v] (t (n², V) floats: the lighting-major grey transfer; j ascending),
   ef[f, 3k + c] = e3[c, F[f, k]] (F (Mf, 3) int64, each in [0, V)). The vertices, then the faces,
   split over nt threads (one OpenMP region). Its oracle is the torch stage (`rotate` after the 3 × 3
   product, `apply_lighting`'s GEMM, the corner gather): float32 round-off (the GEMM's own order). */
static void le_range(int64_t a, int64_t b, int64_t n2, int64_t V, const float *t, const float *lf, float *e3) {
    int64_t v = a;
    for (; v + 8 <= b; v += 8) {
        v8 s0 = {0}, s1 = {0}, s2 = {0};
        for (int64_t j = 0; j < n2; ++j) {
            const v8 x = *(const v8 *)(t + j * V + v);
            s0 += lf[3 * j] * x; s1 += lf[3 * j + 1] * x; s2 += lf[3 * j + 2] * x;
        }
        *(v8 *)(e3 + v) = s0; *(v8 *)(e3 + V + v) = s1; *(v8 *)(e3 + 2 * V + v) = s2;
    }
    for (; v < b; ++v) {
        float s0 = 0, s1 = 0, s2 = 0;
        for (int64_t j = 0; j < n2; ++j) {
            const float x = t[j * V + v];
            s0 += lf[3 * j] * x; s1 += lf[3 * j + 1] * x; s2 += lf[3 * j + 2] * x;
        }
        e3[v] = s0; e3[V + v] = s1; e3[2 * V + v] = s2;
    }
}

static void lf_range(int64_t a, int64_t b, int64_t V, const int64_t *F, const float *e3, float *ef) {
    for (int64_t f = a; f < b; ++f)
        for (int64_t k = 0; k < 3; ++k) {
            const int64_t x = F[3 * f + k];
            ef[9 * f + 3 * k] = e3[x]; ef[9 * f + 3 * k + 1] = e3[V + x]; ef[9 * f + 3 * k + 2] = e3[2 * V + x];
        }
}

void sh_light(int64_t n, int64_t K, const double *cl, const double *W, const double *QT, const double *D,
              const double *P, double *lw, float *lf, int64_t V, const float *t, float *e3, int64_t Mf,
              const int64_t *F, float *ef, int64_t nt) {
    double R[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j)
            R[i * 3 + j] = W[i * 3] * QT[j] + W[i * 3 + 1] * QT[3 + j] + W[i * 3 + 2] * QT[6 + j];
    sh_rotate(n, K, 3, cl, R, D, P, lw);
    const int64_t n2 = n * n;
    for (int64_t i = 0; i < 3 * n2; ++i) lf[i] = (float)lw[i];
    if (nt <= 1) {
        le_range(0, V, n2, V, t, lf, e3);
        lf_range(0, Mf, V, F, e3, ef);
        return;
    }
    #pragma omp parallel num_threads(nt)
    {
        #pragma omp for schedule(static)
        for (int64_t k = 0; k < nt; ++k)
            le_range(k == 0 ? 0 : (V * k / nt) & ~(int64_t)7, k == nt - 1 ? V : (V * (k + 1) / nt) & ~(int64_t)7,
                     n2, V, t, lf, e3);
        #pragma omp for schedule(static)
        for (int64_t k = 0; k < nt; ++k)
            lf_range(Mf * k / nt, Mf * (k + 1) / nt, V, F, e3, ef);
    }
}
"""

_P, _I = ctypes.c_void_p, ctypes.c_int64
_SIGNATURES = {"sh_lg_rows": [_I, _I, _I, _P, _P, _P, _I, _I, _P, _I],
               "sh_add_pixels": [_P, _I, _I, _P, ctypes.c_float, _P],
               "sh_need_rows": [_P, _I, _P, _I, _P, _I, _P, _P, _P, _P],
               "sh_rotate": [_I, _I, _I, _P, _P, _P, _P, _P],
               "sh_light": [_I, _I, _P, _P, _P, _P, _P, _P, _P, _I, _P, _P, _I, _P, _P, _I],
               "sh_view_rows": [_I, _P, _P, _P, _I, _P, _I, _P, _P, _P, _P, _P, _I],
               "sh_glossy": [_I, _I, _P, _P, _I, _P, _I, _P, _I, _I, _P, _I, _I, _P, _I, _I, _P, _P, _P, _I, _I,
                             _P, _P, _P, _P, _P, _P, _P, _I, _P, _I, _P, _I, ctypes.c_float],
               "sh_vm_rows": [_I, _P, _P, _P, _I, _I, _P, _I],
               "sh_vm_rows_l": [_I, _P, _P, _P, _I, _I, _P, _I, _P],
               "sh_view_rows_z": [_I, _P, _P, _P, _I, _P, _I, _P, _P, _P, _P, _P, _I],
               "sh_relight_add": [_I, _I, _P, _P, _P, ctypes.c_float, _P, _I],
               "sh_relight_build": [_I, _I, _P, _P, _I, _P, _I, _P, _I, _I, _P, _I, _I, _P, _I, _I, _P, _P, _P, _I, _I,
                                    _P, _P, _P, _P, _P, _P, _P, _I, _P, _P, _I, _I, _P],
               "sh_pixels": [_I, _I, _P, _P, _P, _I, _I, _P, _I, _I, _P, _I, _I, _P, _P, _I, ctypes.c_float, _P,
                             _P, _P, _I, _I],
               "sh_view": [_I, _I, _P, _P, _P, _I, _I, _P, _I, _I, _P, _I, _I, _P, _P, _I, ctypes.c_float, _P, _I,
                           _I, _P, _I, _P, _P, _I, _I, _P, _P, _P, _P, _P, _P, _I, _I, _I, _P]}
MAX_N2 = 64                     # acc's size: orders up to 8
MIN_ROWS_PER_THREAD = 256       # rows below which one thread does the sums
# `relight_add` split over torch's threads at pixel boundaries (session 39; the same bits: each pixel's
# samples added in order by one thread); False: one thread (the pass before session 39)
RELIGHT_THREADS = True
MIN_RELIGHT_PER_THREAD = 1024   # glossy samples below which one thread does the pass
# The glossy pass with its multiply-adds fused where the build has FMA (`gl_range`; float32 round-off
# from the unfused loop, which False restores). Creature bench V frame's glossy samples, 1 thread,
# process CPU, same process alternating: 1.08x the pass.
FUSED_GLOSSY = True
# Session 43 (sh43): the fused glossy pass at order 5 (the paper's and the perf suite's) by a body compiled with
# n = 5 a constant (`gl_range`: its loops unrolled, the same operations in the same order: the same bits) and the
# pass's values handed to the pixel's add in registers (they went through ``out`` in memory, for all orders);
# creature bench V frame's one pass (`benchmarks.sh_prt43_view`, 1 thread, caches cold, same process alternating
# against the base's library): 1.08x. False: the body for any order (its oracle).
ORDER5_BODY = True


def _fused() -> int:
    """The glossy pass's ``fused`` argument: 0 unfused, 1 fused (at order 5 its own body: `ORDER5_BODY`), 3 fused
    with the body for any order."""
    return (1 if ORDER5_BODY else 3) if FUSED_GLOSSY else 0


_LOADED: list = [None]


def _lib():
    # a None is not kept: `native.load` reads PRTBENCH_COMPILE at each call, so a None met while compilation
    # was off (a test's monkeypatch) is not kept for the process. Session 41: the loaded library is kept here
    # (PRTBENCH_COMPILE still read at each call): `native.load`'s lookup (its signature tuples, the flags,
    # the source key) cost 20-60 µs a call with the caches cold, 3-5 calls a frame
    if not compile_enabled():
        return None
    lib = _LOADED[0]
    if lib is None:
        lib = _LOADED[0] = native.load("sh_lg_rows", _SOURCE, _SIGNATURES, extra_flags=_flags())
    return lib


def _flags() -> tuple[str, ...]:
    """OpenMP; AVX2 when torch found the CPU to have it (the library is built on the machine that
    runs it, and the flags are part of its cache key; `methods.core.native.isa_flags`). No
    contraction into fused multiply-adds: `add_pixels` must round as its oracle's multiply, then add."""
    return ("-fopenmp", "-ffp-contract=off", *native.isa_flags())


def available() -> bool:
    """True when the C loop runs (else `rows` takes `rows_torch`)."""
    return _lib() is not None


def _check(Xm: Tensor, l: Tensor, rows: Tensor, out: Tensor) -> tuple[int, int, int, int]:
    C, n2, ncols = Xm.shape
    Vg = ncols // max(n2, 1)
    if C not in (1, 3) or Vg * n2 != ncols or l.shape != (n2, 3) or out.shape != (3, Vg, n2):
        raise ValueError(f"M (C, n², Vg·n²), l (n², 3), out (3, Vg, n²) expected, got {tuple(Xm.shape)}, "
                         f"{tuple(l.shape)}, {tuple(out.shape)}")
    if rows.numel() and (int(rows.min()) < 0 or int(rows.max()) >= Vg):
        raise IndexError("a glossy row outside M")
    return C, n2, ncols, Vg


def rows_torch(Xm: Tensor, l: Tensor, rows: Tensor, out: Tensor) -> None:
    """out[:, rows, :] = (M l)[:, rows, :] by a gather of the rows' columns and `apply_lighting`'s
    contraction (lᵀ X for grey transfer, l_c X_c per channel): the oracle of `rows`."""
    C, n2, ncols, Vg = _check(Xm, l, rows, out)
    cols = (rows.long()[:, None] * n2 + torch.arange(n2, device=rows.device)).reshape(-1)
    sub = Xm.index_select(2, cols)                                              # (C, n², R·n²)
    lg = l.T @ sub[0] if C == 1 else torch.stack([l[:, c] @ sub[c] for c in range(3)])
    out[:, rows.long(), :] = lg.view(3, -1, n2)


def rows(Xm: Tensor, l: Tensor, rows: Tensor, out: Tensor) -> None:
    """out[:, rows, :] = (M l)[:, rows, :] for M in its lighting-major memory Xm (C, n², Vg·n²)
    float32 (contiguous), l (n², 3) and out (3, Vg, n²) float32 contiguous; the C loop when it is
    available (CPU, n² ≤ `MAX_N2`), else `rows_torch`."""
    lib = _lib()
    C, n2, ncols, Vg = _check(Xm, l, rows, out)
    ok = (lib is not None and Xm.device.type == "cpu" and n2 <= MAX_N2 and Xm.dtype == torch.float32
          and out.dtype == torch.float32 and Xm.is_contiguous() and out.is_contiguous())
    if not ok:
        rows_torch(Xm, l, rows, out)
        return
    r = rows.to(torch.int64).contiguous()
    lc = l.to(torch.float32).contiguous()
    R = int(r.numel())
    if R == 0:
        return
    nt = max(1, min(torch.get_num_threads(), R // MIN_ROWS_PER_THREAD))
    lib.sh_lg_rows(C, n2, ncols, Xm.data_ptr(), lc.data_ptr(), r.data_ptr(), R, Vg, out.data_ptr(), nt)


def need_rows_torch(g: Tensor, face: Tensor, fg: Tensor, Vg: int, valid: Tensor | None) -> Tensor:
    """The rows of l' that the glossy samples g (int64, of the G-buffer's ``face``) read: the
    (ascending, int64) rows fg[face[g]] (fg (M, 3) int32: each face's corner rows) not yet ``valid``
    ((Vg,) bool or None: none are). The oracle of `need_rows`."""
    need = torch.zeros(Vg, dtype=torch.bool, device=fg.device)
    need[fg.index_select(0, face.index_select(0, g)).view(-1).long()] = True
    if valid is not None:
        need &= ~valid
    return need.nonzero().squeeze(-1)


def need_rows(g: Tensor, face: Tensor, fg: Tensor, Vg: int, valid: Tensor | None) -> Tensor:
    """`need_rows_torch` in one C pass (CPU, int64 g and face, int32 fg), else by it."""
    lib = _lib()
    if (lib is None or g.device.type != "cpu" or g.dtype != torch.int64 or face.dtype != torch.int64
            or fg.dtype != torch.int32 or fg.ndim != 2 or fg.shape[1] != 3):
        return need_rows_torch(g, face, fg, Vg, valid)
    g, face, fg = g.contiguous(), face.contiguous(), fg.contiguous()
    if g.numel() and (int(g.min()) < 0 or int(g.max()) >= face.numel()):
        raise IndexError("a sample outside the G-buffer")
    mark = torch.zeros(Vg, dtype=torch.uint8)
    out = torch.empty(Vg, dtype=torch.int64)
    n = torch.zeros(1, dtype=torch.int64)
    v = valid.contiguous().view(torch.uint8) if valid is not None else None
    lib.sh_need_rows(g.data_ptr(), int(g.numel()), face.data_ptr(), int(fg.shape[0]), fg.data_ptr(), Vg, mark.data_ptr(),
                     v.data_ptr() if v is not None else None, out.data_ptr(), n.data_ptr())
    return out[:int(n)]


def rotate(c: Tensor, R: Tensor) -> Tensor | None:
    """`methods.core.sh.rotate_sampled(c, R)` (c (n², C) float64, R (3, 3)) by one C call (`sh_rotate`:
    the same samples D and pseudo-inverse P, the same recurrence's basis; float64 round-off against the
    compiled call, which costs ~0.35 ms of Dynamo's dispatch for ~10 K flops). None where it does not run
    (no compiler, not CPU float64, order above 8, more than 4 channels): the caller takes `rotate_sampled`."""
    lib = _lib()
    n = math.isqrt(int(c.shape[0])) if c.ndim == 2 else 0
    if (lib is None or c.ndim != 2 or n * n != c.shape[0] or not 1 <= n <= 8 or not 1 <= c.shape[1] <= 4
            or c.dtype != torch.float64 or c.device.type != "cpu" or tuple(R.shape) != (3, 3)):
        return None
    from methods.core.sh import _rotation_samples

    D, P = _rotation_samples(n, "cpu")
    if D.shape[0] > 256 or P.shape != (n * n, D.shape[0]):
        return None
    c = c.contiguous()
    R = R.to(torch.float64).contiguous()
    out = torch.empty(n * n, int(c.shape[1]), dtype=torch.float64)
    lib.sh_rotate(n, int(D.shape[0]), int(c.shape[1]), c.data_ptr(), R.data_ptr(), D.contiguous().data_ptr(),
                  P.contiguous().data_ptr(), out.data_ptr())
    return out


def view_rows_torch(face: Tensor, hit: Tensor, fk: Tensor, fg: Tensor, Vg: int, valid: Tensor | None) -> Tensor:
    """The rows of l' a view's glossy samples read, from the G-buffer (`native.view_rows`' oracle): the
    glossy samples are the pixel pass's — hit, on a face f (clamped to the table) with fk[f, 3] != 0 — and
    the rows `need_rows_torch` lists for them."""
    f = face.clamp(0, fk.shape[0] - 1)
    g = torch.nonzero(hit & (fk[f, 3] != 0)).squeeze(-1)
    return need_rows_torch(g, f, fg, Vg, valid)


def view_rows(face: Tensor, hit: Tensor, fk: Tensor, fg: Tensor, Vg: int, valid: Tensor | None,
              marks: Tensor | None = None) -> Tensor | None:
    """`view_rows_torch` in one C pass over the samples' faces (session 35: the rows a lighting change's
    view reads, before its one pass `view`, where the two passes took them from the pixel pass's glossy
    list); the samples split over torch's threads (each marks its faces, then merged: the same list at any
    thread count). None where the loop does not run (the caller takes the two passes). ``marks`` (session 42):
    a contiguous (≥ Vg,) bool or uint8 CPU tensor that receives the row marks (1 at every row the glossy
    faces touch, 0 elsewhere; with ``valid`` None: exactly the rows listed) instead of a kept scratch buffer
    — the caller's table of rows set, without a fill of its own (`SHPRT._view_rows`)."""
    lib = _lib()
    if (lib is None or face.device.type != "cpu" or face.dtype != torch.int64 or hit.dtype != torch.bool
            or fk.dtype != torch.float32 or fk.ndim != 2 or fk.shape[1] != 4 or fg.dtype != torch.int32
            or fg.ndim != 2 or fg.shape[1] != 3 or fg.shape[0] != fk.shape[0] or face.shape != hit.shape
            or face.ndim != 1 or fk.shape[0] == 0):
        return None
    face, hit, fk, fg = _c(face), _c(hit), _c(fk), _c(fg)
    n, Mf = int(face.numel()), int(fk.shape[0])
    nt = max(1, min(torch.get_num_threads(), n // MIN_SAMPLES_PER_MARK_THREAD))
    # session 41: the face and row marks in kept scratch buffers (the C call zeroes what it reads), the count
    # in a ctypes integer: four torch allocations fewer a frame
    fmark = _scratch(0, nt * (Mf + 1))
    if marks is not None and (marks.device.type != "cpu" or marks.dtype not in (torch.bool, torch.uint8)
                              or not marks.is_contiguous() or marks.numel() < Vg):
        raise ValueError("marks: a contiguous CPU bool / uint8 tensor of at least Vg entries expected")
    mark = marks if marks is not None else _scratch(1, Vg)
    out = torch.empty(Vg, dtype=torch.int64)
    cnt = ctypes.c_int64(0)
    v = valid.contiguous().view(torch.uint8) if valid is not None else None
    lib.sh_view_rows_z(n, face.data_ptr(), hit.data_ptr(), fk.data_ptr(), Mf, fg.data_ptr(), Vg, fmark.data_ptr(),
                       mark.data_ptr(), v.data_ptr() if v is not None else None, out.data_ptr(), ctypes.addressof(cnt),
                       nt)
    return out[:cnt.value]


_SCRATCH: list = [torch.empty(0, dtype=torch.uint8), torch.empty(0, dtype=torch.uint8)]


def _scratch(i: int, nbytes: int) -> Tensor:
    """Kept uint8 scratch buffer ``i`` of at least ``nbytes`` (its contents undefined: `view_rows`' C call
    zeroes the parts it reads)."""
    if _SCRATCH[i].numel() < nbytes:
        _SCRATCH[i] = torch.empty(nbytes, dtype=torch.uint8)
    return _SCRATCH[i]


def _c(x: Tensor) -> Tensor:
    """``x`` when contiguous (no torch call), else a contiguous copy."""
    return x if x.is_contiguous() else x.contiguous()


MIN_SAMPLES_PER_MARK_THREAD = 1 << 15   # G-buffer samples below which one thread marks the faces (`view_rows`)


def add_pixels_torch(img: Tensor, g: Tensor, vals: Tensor, S2: int) -> None:
    """img (n, 3) += the glossy samples' radiance vals (Qg, 3) × 1/S² at their pixels g // S²
    (scatter_add_; the pixel by a shift where S² is a power of two: the same non-negative indices).
    The oracle of `add_pixels`."""
    vals = vals * (1.0 / S2)
    pix = g >> (S2.bit_length() - 1) if S2 & (S2 - 1) == 0 else g // S2
    img.scatter_add_(0, pix[:, None].expand(-1, 3), vals)


def add_pixels(img: Tensor, g: Tensor, vals: Tensor, S2: int) -> None:
    """`add_pixels_torch` as one C pass (CPU, float32, contiguous, g int64 ascending — each pixel's
    samples added in their order, as scatter_add_ at one thread), else by it."""
    lib = _lib()
    if (lib is None or img.device.type != "cpu" or img.dtype != torch.float32 or vals.dtype != torch.float32
            or g.dtype != torch.int64 or not (img.is_contiguous() and vals.is_contiguous() and g.is_contiguous())
            or img.ndim != 2 or img.shape[1] != 3 or vals.shape != (g.numel(), 3)):
        add_pixels_torch(img, g, vals, S2)
        return
    if g.numel() == 0:
        return
    if int(g[0]) < 0 or int(g[-1]) >= img.shape[0] * S2:
        raise IndexError("a sample outside the image")
    lib.sh_add_pixels(g.data_ptr(), int(g.numel()), int(S2), vals.data_ptr(), 1.0 / S2, img.data_ptr())


MIN_PIXELS_PER_THREAD = 4096    # pixels below which one thread runs the pixel pass
# The pixel pass 8 samples per step in AVX2 lanes at 2 × 2 samples per pixel (`px_range8`: the same
# image and glossy list bit for bit as the scalar `px_range`, which False restores).
VECTOR_PIXELS = True


def pixels(face: Tensor, hit: Tensor, bary: Tensor, normal: Tensor, wo: Tensor, ef: Tensor, fk: Tensor,
           S2: int, *, listed: bool = True, shape: tuple | None = None, copy: bool = True
           ) -> tuple[Tensor, Tensor | None] | None:
    """`method._pixels_impl`'s pass as one C loop that also lists the glossy samples: (img (n, 3),
    g (Qg,) int64 ascending, the samples ``hit & fk[face, 3] != 0``) for the G-buffer arrays face
    (P,) int64, hit (P,) bool, bary (P, 2), normal and wo (P, 3) float32 (any strides), P = n·S2,
    the face-corner table ef (M, 9) and the face rows fk (M, 4) float32; None where the C loop does
    not run (no compiler, not the CPU, other dtypes): the caller takes the compiled pass."""
    lib = _lib()
    if (lib is None or face.device.type != "cpu" or face.dtype != torch.int64 or hit.dtype != torch.bool
            or any(x.dtype != torch.float32 or x.dim() != 2 for x in (bary, normal, wo, ef, fk))
            or bary.shape[1] != 2 or normal.shape[1] != 3 or wo.shape[1] != 3 or ef.shape[1] != 9
            or fk.shape != (ef.shape[0], 4) or ef.shape[0] == 0):
        return None
    P = int(face.numel())
    if P % S2 or any(int(x.shape[0]) != P for x in (hit, bary, normal, wo)):
        raise ValueError("the G-buffer arrays differ in length or are not whole pixels")
    face, hit, ef, fk = _c(face), _c(hit), _c(ef), _c(fk)
    n = P // S2
    # session 41: ``listed=False`` (a frame shaded from the relight cache: no glossy list read) skips the
    # list's serial merge and copy; the image in ``shape`` when given (n·3 values); the count a ctypes int
    img = torch.empty(shape if shape is not None and math.prod(shape) == 3 * n else (n, 3))
    gl = _gl_buffer(P)
    cnt = ctypes.c_int64(0)
    nt = max(1, min(torch.get_num_threads(), n // MIN_PIXELS_PER_THREAD))
    lib.sh_pixels(n, S2, face.data_ptr(), hit.data_ptr(), bary.data_ptr(), bary.stride(0), bary.stride(1),
                  normal.data_ptr(), normal.stride(0), normal.stride(1), wo.data_ptr(), wo.stride(0), wo.stride(1),
                  ef.data_ptr(), fk.data_ptr(), int(ef.shape[0]), 1.0 / S2, img.data_ptr(), gl.data_ptr(),
                  ctypes.addressof(cnt) if listed else None, nt, int(bool(VECTOR_PIXELS)))
    # session 42: ``copy=False`` returns the list as a view of the kept buffer (valid until the next `pixels`
    # call: the caller consumes it within its frame; the copy was ~0.1 ms of the first lighting-only frame)
    return img, ((gl[:cnt.value].clone() if copy else gl[:cnt.value]) if listed else None)


_GL: list = [torch.empty(0, dtype=torch.int64)]


def _gl_buffer(P: int) -> Tensor:
    """The glossy list's buffer of `pixels` (P int64: every sample may be glossy), kept between
    frames (a fresh 2 MB buffer's pages were faulted in each frame). `pixels` returns a copy of its
    listed part."""
    if _GL[0].numel() < P:
        _GL[0] = torch.empty(P, dtype=torch.int64)
    return _GL[0]


def relight_pack(DG: Tensor, kd: Tensor, ks: Tensor) -> Tensor:
    """The relight cache's columns (`method.SHPRT._relight_build`: DG (n², 2Q) [d | q], kd and ks
    (3, Q)) in the sample-blocked layout of `relight_add`: per block of 8 samples (the last padded
    with zeros) [d (n², 8) | q (n², 8) | kd (3, 8) | ks (3, 8)], one contiguous run (2n² + 6)·8
    floats → (⌈Q/8⌉, (2n² + 6)·8) float32. (The column-major DG read 2n² streams 2Q floats apart at
    once, beyond the prefetchers: 5.7 GB/s.)"""
    n2, Q = int(DG.shape[0]), int(kd.shape[1])
    Qb = -(-Q // 8)
    X = torch.zeros(2 * n2 + 6, Qb * 8, dtype=torch.float32, device=DG.device)
    X[:n2, :Q], X[n2:2 * n2, :Q] = DG[:, :Q], DG[:, Q:]
    X[2 * n2:2 * n2 + 3, :Q], X[2 * n2 + 3:, :Q] = kd, ks
    return X.view(2 * n2 + 6, Qb, 8).permute(1, 0, 2).contiguous().view(Qb, -1)


MIN_BUILD_PER_THREAD = 256       # glossy samples below which one thread builds the relight cache
# Session 42 (sh42): the build by `rb_range2` (the three corners' lobes in one loop, no memset of the blocks,
# the next faces' M blocks prefetched; the same bits as `rb_range`, which False restores)
FAST_RELIGHT_BUILD = True


def relight_build(g: Tensor, face: Tensor, bary: Tensor, normal: Tensor, wo: Tensor, reg: Tensor, F: Tensor,
                  fg: Tensor, T: Tensor, Mv: Tensor, kd: Tensor, ks: Tensor, G: Tensor, vcos: Tensor, A: Tensor,
                  S: Tensor, S2: int) -> tuple[Tensor, Tensor] | None:
    """The packed relight cache of the glossy samples g (Qg,) int64 (`relight_pack`'s (⌈Qg/8⌉, (2n² + 6)·8)
    float32 and the pixels (Qg,) int64) by one C pass (session 40; `method.SHPRT._relight_build`'s torch
    build, its oracle: float32 round-off), or None where it does not run. F (M, 3) int64 vertex ids, fg
    (M, 3) int32 rows of M per face, T (V, n²) float32 the transfer vectors (any strides), Mv (Vg, n², n²)
    float32 contiguous the vertex-major M (`SHPRT._vertex_major_M`); kd, ks (R, 3), G (R, n²), vcos (R,),
    A, S `_sh_factor_tables`; the G-buffer arrays as `glossy`'s."""
    lib = _lib()
    n = math.isqrt(int(G.shape[1]))
    if (lib is None or g.device.type != "cpu" or n * n != G.shape[1] or n * n > MAX_N2 or n < 1
            or any(x.dtype != torch.int64 for x in (g, face, reg, F)) or fg.dtype != torch.int32
            or any(x.dtype != torch.float32 for x in (bary, normal, wo, T, Mv, kd, ks, G, A))
            or Mv.dim() != 3 or not Mv.is_contiguous() or tuple(Mv.shape[1:]) != (n * n, n * n)
            or T.dim() != 2 or T.shape[1] != n * n or F.shape != fg.shape or F.dim() != 2 or F.shape[1] != 3):
        return None
    Q = int(g.numel())
    blk = torch.empty(-(-Q // 8), (2 * n * n + 6) * 8, dtype=torch.float32)
    pix = torch.empty(Q, dtype=torch.int64)
    if Q == 0:
        return blk, pix
    g, face, reg, F, fg, kd, ks, G, A = (_c(x) for x in (g, face, reg, F, fg, kd, ks, G, A))
    nt = max(1, min(torch.get_num_threads(), Q // MIN_BUILD_PER_THREAD))
    bad = ctypes.c_int64(0)
    if FAST_RELIGHT_BUILD:
        # session 42 (sh42): `rb_range2` (the same bits); the samples' bounds checked by the C call and vcos / S's
        # tables kept (`_view_tables`): g.min / max, vcos.to and S.argmax were ~0.1-0.15 ms each with the caches
        # cold (the first lighting-only frame, 1 thread)
        nt = -nt
        v8, sel = _view_tables(vcos, S)
    else:
        if int(g.min()) < 0 or int(g.max()) >= face.numel():
            raise IndexError("a glossy sample outside the G-buffer")
        v8 = vcos.to(torch.uint8).contiguous()
        sel = S.argmax(0).to(torch.int32).contiguous()
    lib.sh_relight_build(Q, n, g.data_ptr(), face.data_ptr(), int(F.shape[0]), reg.data_ptr(), int(kd.shape[0]),
                         bary.data_ptr(), bary.stride(0), bary.stride(1), normal.data_ptr(), normal.stride(0),
                         normal.stride(1), wo.data_ptr(), wo.stride(0), wo.stride(1), F.data_ptr(), fg.data_ptr(),
                         T.data_ptr(), T.stride(0), T.stride(1), Mv.data_ptr(), kd.data_ptr(), ks.data_ptr(),
                         G.data_ptr(), v8.data_ptr(), A.data_ptr(), sel.data_ptr(), int(S2), blk.data_ptr(),
                         pix.data_ptr(), nt, int(face.numel()), ctypes.addressof(bad))
    if bad.value:
        raise IndexError("a glossy sample outside the G-buffer")
    return blk, pix


def relight_unpack(blk: Tensor, Q: int, n2: int) -> tuple[Tensor, Tensor, Tensor]:
    """`relight_pack`'s inverse: (DG (n², 2Q), kd (3, Q), ks (3, Q)) (copies)."""
    X = blk.view(blk.shape[0], 2 * n2 + 6, 8).permute(1, 0, 2).reshape(2 * n2 + 6, -1)[:, :Q]
    return (torch.cat([X[:n2], X[n2:2 * n2]], 1), X[2 * n2:2 * n2 + 3].contiguous(), X[2 * n2 + 3:].contiguous())


def relight_add(img: Tensor, blk: Tensor, l: Tensor, pix: Tensor, S2: int, prange: tuple | None = None) -> bool:
    """img (n, 3) += max(0, kd · lᵀd + ks · lᵀq) / S² at the pixels pix (Q,) int64 (ascending) of the
    packed relight cache blk (`relight_pack`) by one C pass (`method._relight_add` on the unpacked
    cache is its oracle: the same products and sums, i ascending); False (nothing done) where it
    does not run."""
    lib = _lib()
    Q = int(pix.numel())
    n2 = int(l.shape[0])
    if (lib is None or img.device.type != "cpu" or any(x.dtype != torch.float32 for x in (img, blk, l))
            or pix.dtype != torch.int64 or not (img.is_contiguous() and blk.is_contiguous() and pix.is_contiguous())
            or blk.shape != (-(-Q // 8), (2 * n2 + 6) * 8) or l.shape != (n2, 3) or img.ndim < 2 or img.shape[-1] != 3):
        return False
    if Q == 0:
        return True
    # session 41: the pixels of any contiguous (..., 3) image (the caller's (H, W, 3)); ``prange`` = (pix[0],
    # pix[-1]) when the caller keeps them (the cache's pixels are fixed: two torch calls fewer a frame)
    lo, hi = prange if prange is not None else (int(pix[0]), int(pix[-1]))
    if lo < 0 or hi >= img.numel() // 3:
        raise IndexError("a sample outside the image")
    lc = _c(l)
    # session 39: split over the threads at pixel boundaries (the same bits at any thread count)
    nt = max(1, min(torch.get_num_threads(), Q // MIN_RELIGHT_PER_THREAD)) if RELIGHT_THREADS else 1
    lib.sh_relight_add(Q, n2, blk.data_ptr(), lc.data_ptr(), pix.data_ptr(), 1.0 / S2, img.data_ptr(), nt)
    return True


def rows_vertex_major(Mv: Tensor, l: Tensor, rows: Tensor, out: Tensor) -> bool:
    """out[:, rows, :] = (M l)[:, rows, :] from a grey M in VERTEX-major memory Mv (Vg, n², n²)
    float32 contiguous (each row's n²×n² matrix one contiguous block: a listed row is one 2.5 KB
    read at order 5, where the lighting-major M of `rows` spreads it over n² runs Vg·n² floats apart),
    l (n², 3), out (3, Vg, n²) float32 contiguous, by one C loop (the same sums as `rows_torch`, its
    oracle, in another order: float32 round-off); False (nothing done) where it does not run."""
    lib = _lib()
    if (lib is None or Mv.device.type != "cpu" or Mv.dtype != torch.float32 or out.dtype != torch.float32
            or Mv.dim() != 3 or not Mv.is_contiguous() or not out.is_contiguous() or Mv.shape[1] > MAX_N2):
        return False
    Vg, n2 = int(Mv.shape[0]), int(Mv.shape[1])
    if Mv.shape[2] != n2 or l.shape != (n2, 3) or out.shape != (3, Vg, n2):
        raise ValueError(f"M (Vg, n², n²), l (n², 3), out (3, Vg, n²) expected, got {tuple(Mv.shape)}, "
                         f"{tuple(l.shape)}, {tuple(out.shape)}")
    r = rows if rows.dtype == torch.int64 and rows.is_contiguous() else rows.to(torch.int64).contiguous()
    R = int(r.numel())
    if R == 0:
        return True
    nt = max(1, min(torch.get_num_threads(), R // MIN_ROWS_PER_THREAD))
    if l.dtype == torch.float32 and l.is_contiguous() and l.device.type == "cpu":
        # session 41: l as it is, transposed and the rows checked by the C call (no torch call)
        bad = ctypes.c_int64(0)
        lib.sh_vm_rows_l(n2, Mv.data_ptr(), l.data_ptr(), r.data_ptr(), R, Vg, out.data_ptr(), nt, ctypes.addressof(bad))
        if bad.value:
            raise IndexError("a glossy row outside M")
        return True
    if int(r.min()) < 0 or int(r.max()) >= Vg:
        raise IndexError("a glossy row outside M")
    lt = l.to(torch.float32).T.contiguous()                                    # (3, n²)
    lib.sh_vm_rows(n2, Mv.data_ptr(), lt.data_ptr(), r.data_ptr(), R, Vg, out.data_ptr(), nt)
    return True


MIN_GLOSSY_PER_THREAD = 512     # glossy samples below which one thread shades them


def glossy(g: Tensor, face: Tensor, bary: Tensor, normal: Tensor, wo: Tensor, reg: Tensor, ef: Tensor, fg: Tensor,
           lg3: Tensor, kd: Tensor, ks: Tensor, G: Tensor, vcos: Tensor, A: Tensor, S: Tensor,
           img: Tensor | None = None, S2: int = 1) -> Tensor | None:
    """`method._glossy_samples_impl`'s radiance (Qg, 3) of the glossy samples g by one AVX2 C loop
    (module source: `sh_glossy`; the same arithmetic in another order, float32 round-off), or None
    where it does not run (no library or AVX2, not the CPU, other dtypes, an even order or one
    above 7): the caller then runs the compiled kernel. Arguments as that function's. With ``img``
    (n, 3) float32 contiguous (g ascending, g // S2 < n): the radiance is also added to its pixels as
    `add_pixels` adds it, bit for bit, in the same pass (img untouched when None is returned)."""
    lib = _lib()
    n = math.isqrt(int(G.shape[1]))
    if (lib is None or n % 2 == 0 or n > 7 or n * n != G.shape[1] or g.device.type != "cpu"
            or g.dtype != torch.int64 or face.dtype != torch.int64 or reg.dtype != torch.int64
            or fg.dtype != torch.int32 or lg3.dim() != 3 or lg3.stride(2) != 1
            or any(x.dtype != torch.float32 for x in (bary, normal, wo, ef, lg3, kd, ks, G, A))):
        return None
    Q = int(g.numel())
    if img is not None and (img.device.type != "cpu" or img.dtype != torch.float32 or not img.is_contiguous()
                            or img.ndim != 2 or img.shape[1] != 3):
        return None
    out = torch.empty(Q, 3, dtype=torch.float32)
    if Q == 0:
        return out
    if int(g.min()) < 0 or int(g.max()) >= face.numel():
        raise IndexError("a glossy sample outside the G-buffer")
    if img is not None and int(g.max()) >= img.shape[0] * S2:
        raise IndexError("a sample outside the image")
    g, face, reg, fg, ef, kd, ks, G, A = (x.contiguous() for x in (g, face, reg, fg, ef, kd, ks, G, A))
    v8 = vcos.to(torch.uint8).contiguous()
    sel = S.argmax(0).to(torch.int32).contiguous()
    nt = max(1, min(torch.get_num_threads(), Q // MIN_GLOSSY_PER_THREAD))
    ok = torch.zeros(1, dtype=torch.int64)
    lib.sh_glossy(Q, n, g.data_ptr(), face.data_ptr(), int(ef.shape[0]), reg.data_ptr(), int(kd.shape[0]),
                  bary.data_ptr(), bary.stride(0), bary.stride(1), normal.data_ptr(), normal.stride(0), normal.stride(1),
                  wo.data_ptr(), wo.stride(0), wo.stride(1), ef.data_ptr(), fg.data_ptr(), lg3.data_ptr(),
                  lg3.stride(0), lg3.stride(1), kd.data_ptr(), ks.data_ptr(), G.data_ptr(), v8.data_ptr(),
                  A.data_ptr(), sel.data_ptr(), out.data_ptr(), nt, ok.data_ptr(), _fused(),
                  None if img is None else img.data_ptr(), int(S2), 1.0 / S2)
    return out if int(ok) else None


_VT: list = [None]


def _view_tables(vcos: Tensor, S: Tensor) -> tuple[Tensor, Tensor]:
    """(vcos as uint8, S's one-hot rows as int32 indices) of `view`, kept while vcos and S are the same
    tensors at the same versions (`SHPRT._materials` and `_sh_factor_tables` return their cached ones)."""
    c = _VT[0]
    if c is None or c[0] is not vcos or c[1] is not S or c[2] != (vcos._version, S._version):
        c = _VT[0] = (vcos, S, (vcos._version, S._version), vcos.to(torch.uint8).contiguous(),
                      S.argmax(0).to(torch.int32).contiguous())
    return c[3], c[4]


# Pixels per chunk of `view` (its pixel pass and glossy pass per chunk; at most 1024 samples).
VIEW_CHUNK = 256


def view(face: Tensor, hit: Tensor, bary: Tensor, normal: Tensor, wo: Tensor, ef: Tensor, fk: Tensor, S2: int,
         reg: Tensor, fg: Tensor, lg3: Tensor, kd: Tensor, ks: Tensor, G: Tensor, vcos: Tensor, A: Tensor,
         S: Tensor, shape: tuple | None = None) -> Tensor | None:
    """A view frame's image (n, 3) in one C pass (session 32): `pixels` and then `glossy` adding into the
    pixels (``img``), per chunk of `VIEW_CHUNK` pixels — the same image bit for bit (the same loops, each
    pixel's value written, then its glossy samples added in ascending order, by one thread). For a frame
    whose l' table (``lg3`` (3, Vg, n²)) is complete: no glossy list is returned. None where either loop
    would not run (then the caller takes the two passes). Arguments as `pixels`' and `glossy`'s; ``shape``: the
    image's shape when it holds n·3 values (session 41: the caller's (H, W, 3)), else (n, 3)."""
    lib = _lib()
    c = _VS[0]
    if (VIEW_STATIC_KEPT and c is not None and c[0] is lib and c[1] is ef and c[2] is fk and c[3] is fg
            and c[4] is lg3 and c[5] is kd and c[6] is ks and c[7] is G and c[8] is vcos and c[9] is A and c[10] is S
            and c[11] == (vcos._version, S._version) and c[12] == S2 and c[13][17] == _fused()):
        return _view_kept(c, face, hit, bary, normal, wo, reg, shape)
    n = math.isqrt(int(G.shape[1]))
    if (lib is None or face.device.type != "cpu" or face.dtype != torch.int64 or hit.dtype != torch.bool
            or any(x.dtype != torch.float32 or x.dim() != 2 for x in (bary, normal, wo, ef, fk))
            or bary.shape[1] != 2 or normal.shape[1] != 3 or wo.shape[1] != 3 or ef.shape[1] != 9
            or fk.shape != (ef.shape[0], 4) or ef.shape[0] == 0 or not 1 <= S2 <= 256
            or n % 2 == 0 or n > 7 or n * n != G.shape[1] or reg.dtype != torch.int64
            or fg.dtype != torch.int32 or lg3.dim() != 3 or lg3.stride(2) != 1
            or any(x.dtype != torch.float32 for x in (lg3, kd, ks, G, A))):
        return None
    P = int(face.numel())
    if P % S2 or any(int(x.shape[0]) != P for x in (hit, bary, normal, wo, reg)):
        raise ValueError("the G-buffer arrays differ in length or are not whole pixels")
    static = (ef, fk, fg, kd, ks, G, A)
    kept = VIEW_STATIC_KEPT and all(x.is_contiguous() and x.device.type == "cpu" for x in static) \
        and lg3.device.type == "cpu" and int(kd.shape[0]) == int(ks.shape[0]) == int(G.shape[0])
    face, hit, reg, ef, fk, fg, kd, ks, G, A = (_c(x) for x in (face, hit, reg, ef, fk, fg, kd, ks, G, A))
    v8, sel = _view_tables(vcos, S)
    if kept:        # session 42: the checked static arguments kept for the next frame with the same tensors
        _VS[0] = (lib, ef, fk, fg, lg3, kd, ks, G, vcos, A, S, (vcos._version, S._version), S2,
                  (ef.data_ptr(), fk.data_ptr(), int(ef.shape[0]), 1.0 / S2, int(bool(VECTOR_PIXELS)), n,
                   int(kd.shape[0]), fg.data_ptr(), lg3.data_ptr(), lg3.stride(0), lg3.stride(1), kd.data_ptr(),
                   ks.data_ptr(), G.data_ptr(), v8.data_ptr(), A.data_ptr(), sel.data_ptr(), _fused(),
                   int(VIEW_CHUNK)), v8, sel)
    npx = P // S2
    # session 41: the image in the caller's shape (`SHPRT._render_fast` returns it as it is), the flag a ctypes
    # integer: two torch calls fewer a frame
    img = torch.empty(shape if shape is not None and math.prod(shape) == 3 * npx else (npx, 3))
    ok = ctypes.c_int64(0)
    nt = max(1, min(torch.get_num_threads(), npx // MIN_PIXELS_PER_THREAD))
    lib.sh_view(npx, S2, face.data_ptr(), hit.data_ptr(), bary.data_ptr(), bary.stride(0), bary.stride(1),
                normal.data_ptr(), normal.stride(0), normal.stride(1), wo.data_ptr(), wo.stride(0), wo.stride(1),
                ef.data_ptr(), fk.data_ptr(), int(ef.shape[0]), 1.0 / S2, img.data_ptr(), int(bool(VECTOR_PIXELS)),
                n, reg.data_ptr(), int(kd.shape[0]), fg.data_ptr(), lg3.data_ptr(), lg3.stride(0), lg3.stride(1),
                kd.data_ptr(), ks.data_ptr(), G.data_ptr(), v8.data_ptr(), A.data_ptr(), sel.data_ptr(),
                _fused(), int(VIEW_CHUNK), nt, ctypes.addressof(ok))
    return img if ok.value else None


# Session 42 (sh42): `view` keeps the checked values of its static arguments (the corner and face tables, the
# l' table, the materials, the SH tables: the method's kept tensors, the same objects frame after frame) and
# on a frame with the very same tensors checks and passes only the G-buffer's; False: every argument checked
# and read each call. The tensors are compared by identity (and vcos / S by version, their derived tables):
# their pointers, shapes and strides do not change while they live (the method never resizes them).
VIEW_STATIC_KEPT = True
_VS: list = [None]


def _view_kept(c: tuple, face: Tensor, hit: Tensor, bary: Tensor, normal: Tensor, wo: Tensor, reg: Tensor,
               shape: tuple | None) -> Tensor | None:
    """`view` with its static arguments' values ``c`` (kept by the last call with the same tensors): the
    G-buffer's arrays checked (as `view` checks them) and the C pass run."""
    if (face.device.type != "cpu" or face.dtype != torch.int64 or hit.dtype != torch.bool or reg.dtype != torch.int64
            or bary.dtype != torch.float32 or normal.dtype != torch.float32 or wo.dtype != torch.float32
            or bary.dim() != 2 or normal.dim() != 2 or wo.dim() != 2 or bary.shape[1] != 2 or normal.shape[1] != 3
            or wo.shape[1] != 3 or bary.device.type != "cpu" or normal.device.type != "cpu"
            or wo.device.type != "cpu" or hit.device.type != "cpu" or reg.device.type != "cpu"):
        return None
    S2 = c[12]
    P = int(face.numel())
    if (P % S2 or hit.shape[0] != P or bary.shape[0] != P or normal.shape[0] != P or wo.shape[0] != P
            or reg.shape[0] != P):
        raise ValueError("the G-buffer arrays differ in length or are not whole pixels")
    face, hit, reg = _c(face), _c(hit), _c(reg)
    npx = P // S2
    img = torch.empty(shape if shape is not None and math.prod(shape) == 3 * npx else (npx, 3))
    ok = ctypes.c_int64(0)
    nt = max(1, min(torch.get_num_threads(), npx // MIN_PIXELS_PER_THREAD))
    bs, ns, os_ = bary.stride(), normal.stride(), wo.stride()
    a = c[13]
    c[0].sh_view(npx, S2, face.data_ptr(), hit.data_ptr(), bary.data_ptr(), bs[0], bs[1], normal.data_ptr(), ns[0],
                 ns[1], wo.data_ptr(), os_[0], os_[1], a[0], a[1], a[2], a[3], img.data_ptr(), a[4], a[5],
                 reg.data_ptr(), a[6], *a[7:], nt, ctypes.addressof(ok))
    return img if ok.value else None


MIN_LIGHT_PER_THREAD = 4096     # vertices below which one thread runs `light`'s passes


class Light:
    """A lighting change's light stage by one C call (session 41, `sh_light`): the world-frame lighting
    l (n², 3) float32 — the polar-frame coefficients cl (n², 3) float64 rotated by W Qᵀ (W the map's
    ``to_world``, Qᵀ `sh._LATLONG_QT`; `rotate`'s samples and sums) and rounded —, e = t·l channel-major
    (3, V) and the face-corner table ef (M, 9) (ef[f, 3k + c] = e[c, F[f, k]]), where `SHPRT._light_stage`
    ran ~10 torch calls (each 20-170 µs with the caches cold after the harness's idle and G-buffer:
    ~0.65 ms of a creature VL frame, serial at any thread count). Bound once to the static arguments
    (t, F, the order), checked here; `__call__` returns None where it does not run (the caller takes
    the torch stage, its oracle: float32 round-off, the GEMM's own order of the sums over j)."""

    def __init__(self, t: Tensor, F: Tensor, order: int) -> None:
        self.ok = False
        lib = _lib()
        if lib is None or not 1 <= order <= 8 or t.device.type != "cpu" or F.device.type != "cpu":
            return
        n2 = order * order
        if t.dim() != 3 or t.shape[1] != n2 or t.shape[2] != 1 or t.dtype != torch.float32:
            return
        V = int(t.shape[0])
        tl = t.permute(2, 1, 0)                        # (1, n², V): the lighting-major memory of grey t
        if not tl.is_contiguous() or F.dim() != 2 or F.shape[1] != 3 or F.dtype != torch.int64 or F.numel() == 0:
            return
        from methods.core.sh import _LATLONG_QT, _rotation_samples

        D, P = _rotation_samples(order, "cpu")
        if D.shape[0] > 256 or P.shape != (n2, D.shape[0]):
            return
        F = F.contiguous()
        if int(F.min()) < 0 or int(F.max()) >= V:
            raise IndexError("a face corner outside the vertices")
        self.lib, self.t, self.F, self.order, self.n2, self.V, self.Mf = lib, t, F, order, n2, V, int(F.shape[0])
        self.D, self.P = D.contiguous(), P.contiguous()
        self.QT = _LATLONG_QT.to(torch.float64).contiguous()
        self.lw = torch.empty(n2, 3, dtype=torch.float64)          # the rotated doubles (scratch)
        self.ok = True

    def __call__(self, cl: Tensor, W: Tensor) -> tuple[Tensor, Tensor, Tensor] | None:
        """(l (n², 3) float32, e (3, V) float32, ef (M, 9) float32) of the polar coefficients cl (n², 3)
        float64 and the map's rotation W (3, 3) float64 (CPU, contiguous); None where it does not run."""
        if (not self.ok or cl.dtype != torch.float64 or W.dtype != torch.float64 or tuple(cl.shape) != (self.n2, 3)
                or tuple(W.shape) != (3, 3) or cl.device.type != "cpu" or W.device.type != "cpu"
                or not cl.is_contiguous() or not W.is_contiguous()):
            return None
        lf = torch.empty(self.n2, 3)
        e3 = torch.empty(3, self.V)
        ef = torch.empty(self.Mf, 9)
        nt = max(1, min(torch.get_num_threads(), self.V // MIN_LIGHT_PER_THREAD))
        self.lib.sh_light(self.order, int(self.D.shape[0]), cl.data_ptr(), W.data_ptr(), self.QT.data_ptr(),
                          self.D.data_ptr(), self.P.data_ptr(), self.lw.data_ptr(), lf.data_ptr(), self.V,
                          self.t.data_ptr(), e3.data_ptr(), self.Mf, self.F.data_ptr(), ef.data_ptr(), nt)
        return lf, e3, ef
