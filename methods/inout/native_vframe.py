"""Shading "vertex"'s view frame as one C call (Mahajan 2008 §6: eq. 4 once per vertex, then Gouraud),
for frames whose c_k is computed at every vertex (a view-only frame under the first lighting,
`InOut._render_vertex_native`).

The split path (`InOut._render_vertex`: ``csr.hit_face_mask`` — a pass over the samples for the
referenced faces, one over the faces for their vertices —, ``native.vertex_cells`` over the marked
vertices, serial, ``native.vertex_radiance`` per region, ``core.gouraud.resolve``) runs five to six
OpenMP regions (each a wake-up of the team at 2 threads) and ~10 torch / ctypes calls a frame. Here the
same four phases run in one parallel region, split by barriers: (1) the samples in contiguous ranges
(checks, misses, each hit's face marked with the frame's stamp), (2) the faces (each marked face's
three vertices marked), (3) the vertices in chunks of 512 ids to the next free thread (each marked
vertex's cell as ``native.vertex_cells``, eq. 4 as ``native.vertex_radiance``, the same operations
in the same order, copied, with the next vertex's table and c rows prefetched; 0 below the horizon),
(3b) the faces again (each marked face's three corners' B gathered into its row of a face table,
`FAST` bit 2), (4) the pixels in contiguous ranges (``core.gouraud``'s resolve sums in its order, a
sample's corners one row of the face table). The image is the
split path's bit for bit (no contraction, ``-ffp-contract=off``, and the same operations: the host's ISA
flags only widen the registers; the tests compare them), and the same at any thread count (each vertex and pixel is summed by one thread
in one order; a mark is a relaxed store of the same value by whichever thread).

Nothing is allocated per frame but the image (the arguments bound once, `bind`): B (nv, 3), the face
and vertex stamps and the face table (M, 12) are kept between frames (`memo`, reported by
`InOut.memory`), a frame numbers itself in the stamps, and B's rows and the face table's are only read
where (3) and (3b) wrote them this frame. What `frame_cost`
counts of the view is found after the frame (`InOut._frame_cost_vertex`). The region check of the
split path and ``gouraud.resolve``'s range check are made in (1); either failing returns a flag, and
the caller runs the split path, which raises its errors.

Measured (same process, old and new alternating, 0.2 s idle before each frame, process CPU, 1
thread, load 9-10 on 2 cores): chess bench 1.02x, creature 1.06x (the split path's Python and calls;
the 1-thread work is the same); 2 threads: see the session's final message (under that load the
2-thread medians swung 0.4-3x either way). Tried and dropped: each vertex's B_v computed at the first
sample that reads it (one pass over the samples, a stamp per memo row): 0.75-0.93x at 1 thread (the
per-sample stamp checks and the table rows' latency without a batch to prefetch), and in blocks of
512 samples with a batched, prefetched fill: 0.6-0.9x.

Session 40 (`FAST` bits 2, 4, 8; the same bits): where a creature bench V frame went at 1 thread (``python -m
benchmarks.inout_vphases``, new): render 1.75 ms CPU of which the C call 1.36 — (1) 0.26, (2) 0.09, (3) 0.40,
(4) 0.62 — and ~0.39 ms of Python and torch calls around it, serial at 2 threads (each cold after the suite's
idle: the static arrays' checks, the camera as a tensor ~0.09, the barycentrics' unbind, the stats tensor,
the image's view, ``native.load``'s key ~0.05). Now the call is bound once (`bind`), phase (4) reads a face
table, (1) goes in dynamic chunks and (3) prefetches 6 vertices ahead, built with the host's ISA flags:
render ~1.28 ms CPU (C call ~1.0: (1) 0.27, (2) 0.07, (3) 0.25, (3b) 0.06, (4) 0.32), creature 1.38x and chess
1.36x against beff8b6 (1 thread, same process, max |d| 0). At 2 threads under the helpers' load (2 cores,
load 2-7) every variant's frame swung 0.7-12 ms (the second thread waiting for a core at the first
barrier): not measured. Dropped: phase (1) 8 samples a step on AVX-512 (1.01x); the G-buffer checks by
``is_cpu`` (1.00-1.025x).

Session 43 (the same bits; ``python -m benchmarks.inout43_vframe_ab``: base 0a8e785 against this code, one process,
each frame right after its ``make_gbuffer`` as the harness, alternating, 39 timed frames; A/A 0.98-1.00): creature
bench V 1.12-1.13x at 1 thread (process CPU 1.14-1.19 -> 1.01-1.05 ms), chess 1.09x; at 2 threads
(``GOMP_SPINCOUNT=1000000``, host load 2-4) creature 1.07-1.09x (0.68-0.70 -> 0.64 ms), chess 1.04-1.05x. A creature
frame at 1 thread now: ~91 us of Python before the C call (was ~126: `InOut._vcall_current`, the packed 12-argument
entry — a cold ctypes call costs ~1 us an argument —, ``empty_like``, `_lib`'s inline test), ~16 us after it, the
call ~0.94-1.0 ms: (1) 0.27, (2) 0.07, (3) 0.27, (3b) 0.07, (4) 0.32 (``FAST`` bit 32). Phases (1) and (4) stream the
G-buffer (face read by both: 2 MB each time; region 2 MB for the check) at ~13-16 GB/s whether the frame's caches are
cold or warm; (2), (3), (3b) are bound by reaching their rows (0.18 + 0.06 ms back to back, 0.27 + 0.14 cold).
"""
from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from methods.core import native
from methods.inout.native_sample import AVX512_FLAGS, load_remembered

__all__ = ["Bound", "available", "bind", "memo", "vertex_frame"]

_SOURCE = r"""
#include <stdint.h>
#include <math.h>
#include <omp.h>
#if defined(__AVX2__) || defined(__AVX512F__)
#include <immintrin.h>
#endif

#define VCHUNK 512
#define PCHUNK 8192
#define PF_AHEAD 6

/* phase (1) at sample p: the checks, the misses counted, a hit's face marked */
#define SAMPLE_CHECK_MARK(p) {                                                         \
        const int64_t f0 = face[p];                                                    \
        if (f0 < -1 || f0 >= M)                                                        \
            err |= 1;                                                                  \
        if (!hit[p]) {                                                                 \
            ++miss;                                                                    \
        } else {                                                                       \
            const int64_t f = f0 < 0 ? 0 : (f0 >= M ? M - 1 : f0);                   \
            __atomic_store_n(fst + f, st32, __ATOMIC_RELAXED);                         \
            if (face_region[f] != region[p])                                           \
                err |= 2;                                                              \
        }                                                                              \
    }

typedef float v8 __attribute__((vector_size(32)));
typedef float v4 __attribute__((vector_size(16)));

typedef struct {
    const float *pos, *frames, *cam;            /* (nv, 3), (nv, 9), (3,) */
    const int64_t *voff;                         /* (S + 1,) */
    int64_t S, R;
    const float *const *sh;                      /* per slot: (R^2 3, K) table */
    const float *const *c;                       /* per slot: (Vr, 3, K) */
    const int64_t *K;                            /* per slot */
} View;

/* The table cell of concatenated vertex g (native.vertex_cells' operations in its order): its slot
   *sp, first node *cp (clamped as native.vertex_radiance) and bilinear weights wt[0:4]; 0 when the
   camera is below the vertex's horizon (B_v = 0), else 1. */
static inline int cell_of(const View *w, int64_t g, int64_t *sp, int64_t *cp, float *wt) {
    int64_t s = 0;
    while (s + 1 < w->S && g >= w->voff[s + 1])
        ++s;
    const int64_t R = w->R;
    const float *pos = w->pos, *cam = w->cam;
    const float d0 = cam[0] - pos[3 * g], d1 = cam[1] - pos[3 * g + 1], d2 = cam[2] - pos[3 * g + 2];
    const float *F = w->frames + 9 * g;
    const float z = (F[6] * d0 + F[7] * d1) + F[8] * d2;
    if (!(z > 0.0f))
        return 0;
    const float h = 0.5f * (float)(R - 1), top = (float)(R - 1), top2 = (float)(R - 2);
    const float x = (F[0] * d0 + F[1] * d1) + F[2] * d2;
    const float y = (F[3] * d0 + F[4] * d1) + F[5] * d2;
    float sn = (fabsf(x) + fabsf(y)) + z;
    sn = sn < 1e-30f ? 1e-30f : sn;
    const float px = x / sn, py = y / sn;
    float u = ((px + py) + 1.0f) * h, v = ((px - py) + 1.0f) * h;
    u = u < 0.0f ? 0.0f : (u > top ? top : u);
    v = v < 0.0f ? 0.0f : (v > top ? top : v);
    float iu = floorf(u), iv = floorf(v);
    iu = iu > top2 ? top2 : iu;
    iv = iv > top2 ? top2 : iv;
    const float fu = u - iu, fv = v - iv, gu = 1.0f - fu, gv = 1.0f - fv;
    wt[0] = gu * gv;
    wt[1] = fu * gv;
    wt[2] = gu * fv;
    wt[3] = fu * fv;
    const int64_t cmax = R * R - R - 2;
    int64_t ce = (int64_t)iv * R + (int64_t)iu;
    *cp = ce < 0 ? 0 : (ce > cmax ? cmax : ce);
    *sp = s;
    return 1;
}

/* Eq. 4 at vertex g of slot s in cell ce (native.vertex_radiance's sums in its order) into b[0:3]. */
static inline void radiance(const View *w, int64_t s, int64_t g, int64_t ce, const float *wt, float *b) {
    const int64_t R = w->R, K = w->K[s], K3 = 3 * K;
    const float w0 = wt[0], w1 = wt[1], w2 = wt[2], w3 = wt[3];
    const float *sh = w->sh[s];
    const float *s0 = sh + ce * K3, *s1 = sh + (ce + 1) * K3, *s2 = sh + (ce + R) * K3, *s3 = sh + (ce + R + 1) * K3;
    const float *cv = w->c[s] + (g - w->voff[s]) * K3;
    for (int64_t ch = 0; ch < 3; ++ch) {
        const int64_t o = ch * K;
        v8 a8 = {0, 0, 0, 0, 0, 0, 0, 0};
        int64_t k = 0;
        for (; k + 8 <= K; k += 8) {
            v8 x0, x1, x2, x3, cc;
            __builtin_memcpy(&x0, s0 + o + k, 32);
            __builtin_memcpy(&x1, s1 + o + k, 32);
            __builtin_memcpy(&x2, s2 + o + k, 32);
            __builtin_memcpy(&x3, s3 + o + k, 32);
            __builtin_memcpy(&cc, cv + o + k, 32);
            v8 S = x0 * w0;
            S = S + x1 * w1;
            S = S + x2 * w2;
            S = S + x3 * w3;
            a8 += S * cc;
        }
        float acc = ((a8[0] + a8[1]) + (a8[2] + a8[3])) + ((a8[4] + a8[5]) + (a8[6] + a8[7]));
        for (; k < K; ++k) {
            const int64_t j = o + k;
            float S = s0[j] * w0;
            S = S + s1[j] * w1;
            S = S + s2[j] * w2;
            S = S + s3[j] * w3;
            acc += S * cv[j];
        }
        b[ch] = acc;
    }
}

/* One frame on nt threads of OpenMP's team (one parallel region, phases split by barriers):
   (1) samples in nt contiguous ranges (fast & 4: in chunks of PCHUNK to the next free thread): per sample the checks (err bit 1: a face outside [-1, M); bit 2:
       a hit whose face's region is not the sample's), per hit its face f = max(face, 0) marked
       (fst[f] = stamp, a relaxed store: two threads may mark one face), misses counted;
   (2) faces in nt contiguous ranges: each marked face's three vertices marked (vst[g] = stamp,
       relaxed stores of the same value);
   (3) vertex ids in chunks of VCHUNK to the next free thread, each marked vertex in ascending order:
       the cell (native.vertex_cells' operations), then eq. 4 (native.vertex_radiance's) with a later
       vertex's table and c rows prefetched (the next; fast & 8: the 6th next), into B (nv, 3); 0 below
       the horizon;
   (3b) (fast & 2) faces in nt contiguous ranges: each marked face's corners' B rows into its FB row
       (M, 12): [B[fv[0, f]], 0, B[fv[1, f]], 0, B[fv[2, f]], 0];
   (4) pixels in nt contiguous ranges: core/gouraud.c's resolve3 sums in its order: out[i, c] = (1 / S2)
       * sum over the hits p of (B[fv[0, f]] (1 - u - v) + B[fv[1, f]] u) + B[fv[2, f]] v (fast & 2: the
       corners from f's FB row, the channels as lanes of one vector, the same operations per channel).
   Every B row (4) reads is a referenced vertex's, written in (3): no row is cleared. fst (M,) and vst
   (nv,) int32 stamps, kept between frames. out (n, 3); stats[0] =
   misses, stats[1] = error bits. */
void vertex_frame(const int64_t *face, const int64_t *region, const uint8_t *hit, const float *bu,
                  const float *bv, int64_t n, int64_t S2, const int64_t *face_region, int64_t M,
                  const int32_t *fv, const float *pos, const float *frames, const float *cam,
                  const int64_t *voff, int64_t S, int64_t R, const int64_t *shp, const int64_t *cp,
                  const int64_t *K, float *B, int32_t *fst, int32_t *vst, float *FB, int64_t stamp,
                  float *out, int64_t nt, int64_t fast, int64_t *stats) {
    View w = {pos, frames, cam, voff, S, R, (const float *const *)shp, (const float *const *)cp, K};
    const int64_t nv = voff[S], q = n * S2;
    const int32_t st32 = (int32_t)stamp;
    int64_t err = 0, miss = 0;
    #pragma omp parallel num_threads(nt) reduction(|:err) reduction(+:miss) if (nt > 1)
    {
        const int64_t T = omp_get_num_threads(), t = omp_get_thread_num();
        /* (1) */
        if (fast & 4) {
            /* chunks of PCHUNK samples to the next free thread: a frame's second thread, woken from its
               sleep after the suite's idle, starts ~10-35 us after the first, which takes the chunks
               meanwhile instead of waiting for it at the barrier (the marks are the same whoever makes them) */
            #pragma omp for schedule(dynamic, 1)
            for (int64_t c = 0; c < (q + PCHUNK - 1) / PCHUNK; ++c) {
                const int64_t pe = (c + 1) * PCHUNK < q ? (c + 1) * PCHUNK : q;
                for (int64_t p = c * PCHUNK; p < pe; ++p)
                    SAMPLE_CHECK_MARK(p)
            }
        } else {
            for (int64_t p = q * t / T; p < q * (t + 1) / T; ++p)
                SAMPLE_CHECK_MARK(p)
            #pragma omp barrier
        }
        /* (2) */
        for (int64_t f = M * t / T; f < M * (t + 1) / T; ++f) {
            if (__atomic_load_n(fst + f, __ATOMIC_RELAXED) != st32)
                continue;
            for (int64_t j = 0; j < 3; ++j)
                __atomic_store_n(vst + fv[j * M + f], st32, __ATOMIC_RELAXED);
        }
        #pragma omp barrier
        /* (3) chunks of VCHUNK vertex ids to the next free thread; in a chunk, the marked vertices in
           ascending order in runs of 64: the cells, then eq. 4 */
        int64_t ls[64], lc[64], lg[64];
        float lw[4 * 64];
        #pragma omp for schedule(dynamic, 1)
        for (int64_t ch = 0; ch < (nv + VCHUNK - 1) / VCHUNK; ++ch) {
            const int64_t ve = (ch + 1) * VCHUNK < nv ? (ch + 1) * VCHUNK : nv;
            int64_t g = ch * VCHUNK;
            while (g < ve) {
                int64_t m = 0;
                for (; g < ve && m < 64; ++g) {
                    if (__atomic_load_n(vst + g, __ATOMIC_RELAXED) != st32)
                        continue;
                    if (cell_of(&w, g, ls + m, lc + m, lw + 4 * m)) {
                        lg[m++] = g;
                    } else {
                        B[3 * g] = 0.0f;
                        B[3 * g + 1] = 0.0f;
                        B[3 * g + 2] = 0.0f;
                    }
                }
                /* each vertex's 4 table rows (2 runs of 2 rows) and c row prefetched D vertices ahead (fast & 8:
                   PF_AHEAD, the first D of the run before it; else the next one's) */
                const int64_t D = (fast & 8) ? PF_AHEAD : 1;
                for (int64_t i = (fast & 8) ? 0 : 1; i < D && i < m; ++i) {
                    const int64_t s1 = ls[i], K3 = 3 * K[s1], cn = lc[i];
                    const float *sh = w.sh[s1];
                    const float *cv = w.c[s1] + (lg[i] - voff[s1]) * K3;
                    for (int64_t k = 0; k < 2 * K3; k += 16) {
                        __builtin_prefetch(sh + cn * K3 + k);
                        __builtin_prefetch(sh + (cn + R) * K3 + k);
                    }
                    for (int64_t k = 0; k < K3; k += 16)
                        __builtin_prefetch(cv + k);
                }
                for (int64_t i = 0; i < m; ++i) {
                    if (i + D < m) {
                        const int64_t s1 = ls[i + D], K3 = 3 * K[s1], cn = lc[i + D];
                        const float *sh = w.sh[s1];
                        const float *cv = w.c[s1] + (lg[i + D] - voff[s1]) * K3;
                        for (int64_t k = 0; k < 2 * K3; k += 16) {
                            __builtin_prefetch(sh + cn * K3 + k);
                            __builtin_prefetch(sh + (cn + R) * K3 + k);
                        }
                        for (int64_t k = 0; k < K3; k += 16)
                            __builtin_prefetch(cv + k);
                    }
                    radiance(&w, ls[i], lg[i], lc[i], lw + 4 * i, B + 3 * lg[i]);
                }
            }
        }
        if (fast & 2) {
            /* (3b) faces in nt contiguous ranges: each marked face's three corners' B in its row of FB
               (12 floats: the corners' 3 channels and a 0 each), so (4) reads one row a sample; every B
               row is written: (3)'s worksharing loop ends with a barrier */
            for (int64_t f = M * t / T; f < M * (t + 1) / T; ++f) {
                if (__atomic_load_n(fst + f, __ATOMIC_RELAXED) != st32)
                    continue;
                float *o = FB + 12 * f;
                for (int64_t j = 0; j < 3; ++j) {
                    const float *x = B + 3 * (int64_t)fv[j * M + f];
                    o[4 * j] = x[0];
                    o[4 * j + 1] = x[1];
                    o[4 * j + 2] = x[2];
                    o[4 * j + 3] = 0.0f;
                }
            }
            #pragma omp barrier
        }
        /* (4) */
        const float inv = 1.0f / (float)S2;
        const int64_t i0 = n * t / T, i1 = n * (t + 1) / T;
        if (fast & 2) {
            /* the sums of the loop below, the three channels as lanes of one vector (the same operations
               on each channel in the same order: the same bits) */
            for (int64_t i = i0; i < i1; ++i) {
                v4 acc = {0.0f, 0.0f, 0.0f, 0.0f};
#if defined(__AVX512F__)
                uint32_t h4 = 0;
                if ((fast & 32) && S2 == 4)
                    __builtin_memcpy(&h4, hit + 4 * i, 4);
                if (h4 == 0x01010101u) {
                    /* (fast & 32) a pixel's 4 samples, all hits, as the 4 lane groups of one 16-float vector: each
                       sample's (x ww + y u) + z v in its group (the same operations per lane), then added to acc
                       in the samples' order (the loop below's bits) */
                    const int64_t p = 4 * i;
                    int64_t fq[4];
                    for (int64_t j = 0; j < 4; ++j)
                        fq[j] = face[p + j] < 0 ? 0 : (face[p + j] >= M ? M - 1 : face[p + j]);
                    const float *r0 = FB + 12 * fq[0], *r1 = FB + 12 * fq[1], *r2 = FB + 12 * fq[2], *r3 = FB + 12 * fq[3];
                    __m512 X = _mm512_castps128_ps512(_mm_loadu_ps(r0));
                    __m512 Y = _mm512_castps128_ps512(_mm_loadu_ps(r0 + 4));
                    __m512 Z = _mm512_castps128_ps512(_mm_loadu_ps(r0 + 8));
                    X = _mm512_insertf32x4(X, _mm_loadu_ps(r1), 1);
                    Y = _mm512_insertf32x4(Y, _mm_loadu_ps(r1 + 4), 1);
                    Z = _mm512_insertf32x4(Z, _mm_loadu_ps(r1 + 8), 1);
                    X = _mm512_insertf32x4(X, _mm_loadu_ps(r2), 2);
                    Y = _mm512_insertf32x4(Y, _mm_loadu_ps(r2 + 4), 2);
                    Z = _mm512_insertf32x4(Z, _mm_loadu_ps(r2 + 8), 2);
                    X = _mm512_insertf32x4(X, _mm_loadu_ps(r3), 3);
                    Y = _mm512_insertf32x4(Y, _mm_loadu_ps(r3 + 4), 3);
                    Z = _mm512_insertf32x4(Z, _mm_loadu_ps(r3 + 8), 3);
                    const __m128 u4 = _mm_loadu_ps(bu + p), v4_ = _mm_loadu_ps(bv + p);
                    const __m128 w4 = _mm_sub_ps(_mm_sub_ps(_mm_set1_ps(1.0f), u4), v4_);   /* 1.0f - u - v */
                    const __m512i spread = _mm512_set_epi32(3, 3, 3, 3, 2, 2, 2, 2, 1, 1, 1, 1, 0, 0, 0, 0);
                    const __m512 U = _mm512_permutexvar_ps(spread, _mm512_castps128_ps512(u4));
                    const __m512 V = _mm512_permutexvar_ps(spread, _mm512_castps128_ps512(v4_));
                    const __m512 WW = _mm512_permutexvar_ps(spread, _mm512_castps128_ps512(w4));
                    const __m512 Sm = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(X, WW), _mm512_mul_ps(Y, U)),
                                                    _mm512_mul_ps(Z, V));
                    v4 s0, s1, s2, s3;
                    {
                        const __m128 e0 = _mm512_castps512_ps128(Sm), e1 = _mm512_extractf32x4_ps(Sm, 1);
                        const __m128 e2 = _mm512_extractf32x4_ps(Sm, 2), e3 = _mm512_extractf32x4_ps(Sm, 3);
                        __builtin_memcpy(&s0, &e0, 16);
                        __builtin_memcpy(&s1, &e1, 16);
                        __builtin_memcpy(&s2, &e2, 16);
                        __builtin_memcpy(&s3, &e3, 16);
                    }
                    acc += s0;
                    acc += s1;
                    acc += s2;
                    acc += s3;
                } else
#endif
                for (int64_t p = i * S2; p < (i + 1) * S2; ++p) {
                    if (!hit[p])
                        continue;
                    const int64_t f = face[p] < 0 ? 0 : (face[p] >= M ? M - 1 : face[p]);
                    const float u = bu[p], v = bv[p], ww = 1.0f - u - v;
                    const float *r = FB + 12 * f;
                    v4 x, y, z;
                    __builtin_memcpy(&x, r, 16);
                    __builtin_memcpy(&y, r + 4, 16);
                    __builtin_memcpy(&z, r + 8, 16);
                    acc += (x * ww + y * u) + z * v;
                }
                acc *= inv;
                if (i + 1 < i1) {
                    __builtin_memcpy(out + 3 * i, &acc, 16);    /* its 4th lane: this thread's next pixel's, written after */
                } else {
                    out[3 * i] = acc[0];
                    out[3 * i + 1] = acc[1];
                    out[3 * i + 2] = acc[2];
                }
            }
        } else {
        for (int64_t i = i0; i < i1; ++i) {
            float a0 = 0.0f, a1 = 0.0f, a2 = 0.0f;
            for (int64_t p = i * S2; p < (i + 1) * S2; ++p) {
                if (!hit[p])
                    continue;
                /* clamped as in (1): a face >= M (err bit 1, the image is not used) must not read past fv */
                const int64_t f = face[p] < 0 ? 0 : (face[p] >= M ? M - 1 : face[p]);
                const float u = bu[p], v = bv[p], ww = 1.0f - u - v;
                const float *x = B + 3 * (int64_t)fv[f];
                const float *y = B + 3 * (int64_t)fv[M + f];
                const float *z = B + 3 * (int64_t)fv[2 * M + f];
                a0 += (x[0] * ww + y[0] * u) + z[0] * v;
                a1 += (x[1] * ww + y[1] * u) + z[1] * v;
                a2 += (x[2] * ww + y[2] * u) + z[2] * v;
            }
            out[3 * i] = a0 * inv;
            out[3 * i + 1] = a1 * inv;
            out[3 * i + 2] = a2 * inv;
        }
        }
    }
    stats[0] = miss;
    stats[1] = err;
}

/* vertex_frame with its frame-independent arguments from the packed array a (`bind`: face_region, M, fv, pos,
   frames, cam, voff, S, R, shp, cp, K, B, fst, vst, FB, stats, in vertex_frame's order): a cold ctypes call
   costs ~1 us an argument (session 43) */
void vertex_frame_packed(const int64_t *a, const int64_t *face, const int64_t *region, const uint8_t *hit,
                         const float *bu, const float *bv, int64_t n, int64_t S2, int64_t stamp, float *out,
                         int64_t nt, int64_t fast) {
    vertex_frame(face, region, hit, bu, bv, n, S2, (const int64_t *)a[0], a[1], (const int32_t *)a[2],
                 (const float *)a[3], (const float *)a[4], (const float *)a[5], (const int64_t *)a[6], a[7], a[8],
                 (const int64_t *)a[9], (const int64_t *)a[10], (const int64_t *)a[11], (float *)a[12],
                 (int32_t *)a[13], (int32_t *)a[14], (float *)a[15], stamp, out, nt, fast, (int64_t *)a[16]);
}
"""

_P, _I = ctypes.c_void_p, ctypes.c_int64
_SIGNATURES = {"vertex_frame": [_P, _P, _P, _P, _P, _I, _I, _P, _I, _P, _P, _P, _P, _P, _I, _I, _P, _P, _P,
                                _P, _P, _P, _P, _I, _P, _I, _I, _P],
               "vertex_frame_packed": [_P, _P, _P, _P, _P, _P, _I, _I, _I, _P, _I, _I]}
# Samples a chunk of phase (1) under ``FAST`` bit 4 (the C source's PCHUNK)
PCHUNK = 8192
assert f"#define PCHUNK {PCHUNK}\n" in _SOURCE
# Frame numbers on one memo are below this (int32 stamps)
STAMP_MAX = (1 << 31) - 1
# Pixels per thread below which one thread shades the frame (`core.gouraud`'s threshold)
MIN_PIXELS_PER_THREAD = 1 << 13
# Variants of the loop (the same bits; a bit off: the plain form, kept as the test oracle):
#   2  the face table FB (phase (3b): each referenced face's three corners' B in one row) and phase (4)
#      reading one row of it a sample, the three channels as the lanes of one vector. Creature bench V,
#      1 thread, same process, 30 frames alternating (``python -m benchmarks.inout_vphases --fast 0 2 0``):
#      the loop 1.07x (phase (4) 0.56 -> 0.41 ms, (3b) +0.07 ms).
#   4  phase (1) in chunks of 8192 samples to the next free thread (not nt contiguous ranges): at 2
#      threads the second, woken late, no longer holds the first at (1)'s barrier (the same work, the
#      same marks; not measurable at 1 thread).
#   8  phase (3): each vertex's table and c rows prefetched 6 vertices ahead (the first 6 of each run of
#      64 before it), not the next one's only.
#   32 (with 2, AVX-512 builds, 2×2 samples) phase (4): a pixel whose 4 samples all hit in one 16-float vector (the 4
#      samples' corner rows as its 4 lane groups, the same operations per lane), the 4 sums then added to the
#      pixel's accumulator in the samples' order (session 43; creature bench V, 1 thread, 30 frames alternating,
#      ``python -m benchmarks.inout_vphases --fast 14 46``: phase (4) 0.342 -> 0.316 ms, the C call 1.035x).
#   (session 43, dropped: phase (1) marking the vertices of each face it marks first (no phase (2)), per run of
#   samples on one face: the C call 0.75x, phase (1) 0.28 -> 0.67 ms, the run test's branch mispredicted at
#   ~48·10³ face changes a frame; phase (3)'s K-sum tail (K mod 8 terms) as masked 8-lane vectors: 1.00x,
#   (3) is bound by reaching its rows; phase (4)'s G-buffer streams prefetched 512 samples ahead: 1.00x.)
#   (bit 1, dropped: phase (1) 8 samples a step on AVX-512, only the samples whose (face, region)
#   differs from the previous hit's marking and checking their face: 1.01x, within the A/A's 1.02x;
#   the phase streams 4.5 MB of G-buffer and is not bound by its instructions.)
FAST = 46
# `Bound.frame` calls ``vertex_frame_packed`` (12 arguments: the frame-independent ones packed once by `bind`) instead
# of ``vertex_frame`` (28): with the caches the suite's rasteriser leaves, a ctypes call of a trivial C function
# took 36 us with 28 integer arguments and 24 with 11 (session 43, median of 48 cold calls); the same loop
PACKED = True


_LOADED: list = []      # the library once loaded (`_lib`)


def _lib():
    """The library, or None (no compiler, the build failed, ``PRTBENCH_COMPILE=0``: read at each call);
    remembered once loaded (`native_sample.load_remembered`)."""
    return load_remembered(_LOADED, "inout_vframe", _SOURCE, _SIGNATURES, _flags)


def _flags() -> tuple[str, ...]:
    """No contraction (each product and sum rounded alone, as the split path's baseline build), and the
    host's ISA flags (``native.isa_flags``: AVX2, each 8-lane operation of (3) one instruction instead of
    two; the same IEEE operations lane by lane, so the same bits — the tests compare them with the split
    path's). Same process, 1 thread, 40 frames alternating against the baseline build
    (``python -m benchmarks.inout_vframe_flags_ab --scene S``): chess bench V 1.10x (phase (3) 1.23x), creature 1.07x
    (1.14x)."""
    return ("-fopenmp", "-ffp-contract=off", *native.isa_flags(),
            *(AVX512_FLAGS if native.cpu_capability() == "AVX512" else ()))


def available() -> bool:
    """True when the C loop runs (else the caller takes the split path)."""
    return _lib() is not None


def memo(nv: int, M: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """A memo for ``nv`` concatenated vertices and ``M`` faces: (B (nv, 3) float32, face stamps (M,)
    int32 zeroed, vertex stamps (nv,) int32 zeroed, the face table FB (M, 12) float32: per face its
    corners' B, written for the frame's referenced faces, ``FAST`` bit 2)."""
    return (torch.zeros(nv, 3, dtype=torch.float32), torch.zeros(M, dtype=torch.int32),
            torch.zeros(nv, dtype=torch.int32), torch.zeros(M, 12, dtype=torch.float32))


class Bound:
    """`vertex_frame`'s arguments that do not change between frames — the scene's arrays of ``st``, the
    slots' tables and c, the memo — checked and packed once (`bind`); `frame` checks the G-buffer's
    arrays and runs one frame. Each torch op and attribute read around the loop runs with the loop's
    cold caches (the suite's idle, the G-buffer's rasterisation before it): the per-frame checks of the
    static arrays, the camera as a tensor, the barycentrics' unbind, the stats tensor and the image's
    view cost a creature bench frame ~0.25 ms of serial Python (1 thread); here ~a tenth of that."""

    __slots__ = ("st", "cs", "mem", "lib", "fn", "nv", "M", "S", "meta", "stats", "head", "tail", "cam", "like",
                 "regions", "names", "fnp", "pack", "pk")

    def fits(self, st, cs: list[Tensor], mem, lib) -> bool:
        """True when bound to these very objects (the tensors' identity: their storage is not replaced
        in place anywhere in `InOut`)."""
        return (self.st is st and self.mem is mem and self.lib is lib and len(cs) == len(self.cs)
                and all(a is b for a, b in zip(cs, self.cs)))

    def frame(self, face: Tensor, bary: Tensor, region: Tensor, hit: Tensor, n: int, S2: int, origin,
              stamp: int, shape: tuple[int, ...] | None = None) -> tuple[Tensor, int, int] | None:
        """`vertex_frame` with the camera position ``origin`` (3 numbers, taken as float32) and the
        image allocated as ``shape`` (default (n, 3); its elements n·3).

        Session 41 (the same checks, fewer cold code paths: each distinct torch or ctypes operation costs
        ~10-50 us right after the suite's idle and rasterisation, whatever it does): dtypes compared by
        identity, devices by ``is_cpu``, the camera written into a kept ctypes array."""
        q = n * S2
        if (face.dtype is not torch.int64 or region.dtype is not torch.int64 or hit.dtype is not torch.bool
                or bary.dtype is not torch.float32 or face.shape != (q,) or region.shape != (q,) or hit.shape != (q,)
                or bary.shape != (q, 2) or not 0 < stamp < STAMP_MAX or len(origin) != 3
                or not (face.is_cpu and region.is_cpu and hit.is_cpu and bary.is_cpu)
                or not (face.is_contiguous() and region.is_contiguous() and hit.is_contiguous())):
            return None
        if bary.stride() == (1, q):               # the G-buffer's column-major barycentrics: its columns
            bu = bary.data_ptr()
            bv = bu + 4 * q
        else:
            u, v = bary.unbind(-1)
            u, v = u.contiguous(), v.contiguous()
            bu, bv = u.data_ptr(), v.data_ptr()
        cam = self.cam
        cam[0:3] = origin                         # float32 as torch.tensor(origin, dtype=torch.float32)
        shape = shape if shape is not None else (n, 3)
        like = self.like
        if like is None or like.shape != shape:
            # a float32 tensor of the image's shape and no memory (strides 0): `torch.empty_like` of it is a
            # contiguous image, ~10 us cheaper than `torch.empty`'s argument parsing with cold caches (session 43)
            like = self.like = torch.zeros((), dtype=torch.float32).expand(shape)
        out = torch.empty_like(like, memory_format=torch.contiguous_format)
        if out.numel() != 3 * n:
            return None
        nt = max(1, min(torch.get_num_threads(), n // MIN_PIXELS_PER_THREAD))
        st = self.stats
        if PACKED:
            self.fnp(self.pk, face.data_ptr(), region.data_ptr(), hit.data_ptr(), bu, bv, n, S2, stamp, out.data_ptr(),
                     nt, FAST)
        else:
            self.fn(face.data_ptr(), region.data_ptr(), hit.data_ptr(), bu, bv, n, S2, *self.head, cam,
                    *self.tail, stamp, out.data_ptr(), nt, FAST, st)
        return out, st[0], st[1]

    def __deepcopy__(self, memo):
        return None    # a deep copy of its owner binds its own call (the library's functions do not copy)


def bind(st, cs: list[Tensor], mem: tuple[Tensor, Tensor, Tensor], lib=None) -> Bound | None:
    """A `Bound` call for ``st`` (the ``fast.FastStatic``), cs[s] (Vr_s, 3, K_s) float32 the c of slot s
    (valid at every vertex) and ``mem`` (a `memo` of ``st``'s vertices and faces), or None when the
    loop is not available or the arrays are not CPU tensors of those types and shapes (the caller runs
    the split path). ``lib``: the library as `_lib` gave it to the caller (else looked up here)."""
    lib = _lib() if lib is None else lib
    if lib is None:
        return None
    nv, M, S = st.voff[-1], int(st.face_region.shape[0]), len(cs)
    sh = [fr.sh_nc for fr in st.regions]
    if len(mem) != 4:
        return None
    B, fst, vst, FB = mem
    ts = (st.face_region, st.face_gl, st.pos, st.frames, B, fst, vst, FB, *sh, *cs)
    if (S == 0 or S != len(sh) or S != len(st.voff) - 1 or M == 0
            or st.face_region.dtype != torch.int64 or st.face_gl.dtype != torch.int32 or st.face_gl.shape != (3, M)
            or st.pos.shape != (nv, 3) or st.frames.shape != (nv, 3, 3)
            or B.shape != (nv, 3) or fst.shape != (M,) or vst.shape != (nv,) or FB.shape != (M, 12)
            or any(t.dtype != torch.int32 for t in (fst, vst))
            or any(t.dtype != torch.float32 for t in (st.pos, st.frames, B, FB, *sh, *cs))
            or any(t.device.type != "cpu" or not t.is_contiguous() for t in ts)):
        return None
    K = []
    for s in range(S):
        vr = st.voff[s + 1] - st.voff[s]
        k = int(cs[s].shape[2])
        if cs[s].shape != (vr, 3, k) or sh[s].shape != (st.R * st.R * 3, k):
            return None
        K.append(k)
    b = Bound()
    b.st, b.cs, b.mem, b.lib, b.fn = st, list(cs), mem, lib, lib.vertex_frame
    b.nv, b.M, b.S = nv, M, S
    vals = [*st.voff, *(t.data_ptr() for t in sh), *(t.data_ptr() for t in cs), *K]
    b.meta = (ctypes.c_int64 * len(vals))(*vals)     # kept alive with the bound call
    mp = ctypes.addressof(b.meta)
    b.stats = (ctypes.c_int64 * 2)()                  # the loop writes both
    b.cam = (ctypes.c_float * 3)()                    # the frame's camera position (`Bound.frame`)
    b.like = b.regions = b.names = None
    b.head = (st.face_region.data_ptr(), M, st.face_gl.data_ptr(), st.pos.data_ptr(), st.frames.data_ptr())
    b.tail = (mp, S, st.R, mp + 8 * (S + 1), mp + 8 * (2 * S + 1), mp + 8 * (3 * S + 1), B.data_ptr(),
              fst.data_ptr(), vst.data_ptr(), FB.data_ptr())
    b.fnp = lib.vertex_frame_packed
    statics = (*b.head, ctypes.addressof(b.cam), *b.tail, ctypes.addressof(b.stats))
    b.pack = (ctypes.c_int64 * len(statics))(*statics)      # `vertex_frame_packed`'s a, kept with the bound call
    b.pk = ctypes.addressof(b.pack)
    return b


def vertex_frame(st, cs: list[Tensor], face: Tensor, bary: Tensor, region: Tensor, hit: Tensor, n: int, S2: int,
                 cam: Tensor, mem: tuple[Tensor, Tensor, Tensor], stamp: int, lib=None) -> tuple[Tensor, int, int] | None:
    """The image (n, 3) of a vertex-shaded frame (module docstring), the miss count and the error
    bits (1: a face outside [−1, M); 2: a hit on a face of another region; the image is then not to be
    used). ``st`` the ``fast.FastStatic``, cs[s] (Vr_s, 3, K_s) float32 the c of slot s (valid at every
    vertex), face, region (q,) int64, hit (q,) bool, bary (q, 2) float32 (any strides: its columns are
    read as rows), cam (3,) float32, ``mem`` a `memo` of ``st``'s vertices and faces, ``stamp`` in
    (0, `STAMP_MAX`) this frame's number (distinct from every earlier frame's on ``mem``). None when
    the loop is not available or the arrays are not CPU tensors of those types (the caller runs the
    split path). ``lib``: the library as `_lib` gave it to the caller (else looked up here). One frame
    of `bind` (`InOut` keeps the bound call between frames)."""
    if cam.dtype != torch.float32 or cam.shape != (3,) or cam.device.type != "cpu":
        return None
    b = bind(st, cs, mem, lib)
    return None if b is None else b.frame(face, bary, region, hit, n, S2, cam.tolist(), stamp)
