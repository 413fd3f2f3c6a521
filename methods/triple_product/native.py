"""Eq. 7's fine-value sums skipping the zeros of the visibility row: a small C loop (compiled on
first use with ``cc``, called through ctypes) for the two sums `fast_eval` runs with one visibility
row per item — a per-vertex frame's points (`fast_eval.fine_block` with k_v = 1) and a pixel frame's
groups (`fast_eval.group_block`) — with those compiled torch kernels as the fallback and test oracle.

Why: a point's blended visibility is exactly 0 on 38–48 % of its live fine triangles (bench scenes,
``python -m benchmarks.tp_zeros``); those terms add an exact 0 to eq. 7 whatever ρ̃ and L, and
`fast_eval.frame_cost` does not count them (`fast_eval.nonzero_reads`). An Inductor loop cannot run
over per-point variable ranges, so the compiled kernels sum whole live rows. Here every visibility
row gets, once per table (`chunks`: one pass over the table, built at load, not cached in the
precomputation), the starts of the 8-aligned 8-column *chunks* holding its non-zero columns (the
zeros of a row are coherent in direction and the live columns are in the fine values' quadtree
order: on chess bench per-vertex V the shaded vertices' aligned chunks cover 69 % of their live
columns, their non-zeros are 56 %; chunks starting on any non-zero column cover 65 %, but ~7 in 16 of
their vector loads straddle two cache lines: aligned, the per-vertex sums ran 1.04x faster
(session 29) and per pixel no slower) — and the columns after the last whole aligned block
(< 8, when 8 does not divide the row) are summed one by one.
Each chunk is one 8-lane vector of every row read (AVX2 + FMA when the CPU has them).

The sums are the compiled kernels' terms minus exact zeros, in another order (float32 round-off;
tests/methods/triple_product/test_tp_native.py). Each item is summed by one thread in one order, so
the results do not depend on the thread count (items are split in contiguous ranges over
``torch.get_num_threads()`` threads of OpenMP's team, the libgomp torch loaded).

The library is built and loaded by `methods.core.native.load` (once per source text, compiler and
flags, from a private per-user directory); without a compiler, with ``PRTBENCH_COMPILE=0`` or
``PRTBENCH_TP_NATIVE=0``, `available` is False and
`fast_eval` runs the compiled torch kernels. The loop reads without bounds checks: the callers
check every row index once per call (`_rows_ok`).
"""
from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from methods.core import native, switches
from methods.core.fused import compile_enabled

__all__ = ["available", "chunks", "chunk_major", "packed_chunks", "unpack_chunks", "points", "groups", "hit_faces", "resolve", "vertex_lookups", "W"]

W = 8  # columns per chunk (one 8-lane vector)

_SOURCE = r"""
#include <math.h>
#include <stdint.h>
#include <string.h>
typedef float v8 __attribute__((vector_size(32)));

static inline v8 ld(const float* p) { v8 r; memcpy(&r, p, sizeof r); return r; }
static inline float hsum(v8 a) {
    return ((a[0] + a[1]) + (a[2] + a[3])) + ((a[4] + a[5]) + (a[6] + a[7]));
}

/* Per row r of V (N, n): the starts of the 8-aligned 8-column chunks holding its non-zero columns
   (while a + 8 <= n), and tail[r], the first non-zero column not covered (n when none).
   starts == NULL: count[r] = the row's chunks only. */
void tp_chunks(const float* V, int64_t N, int64_t n, int64_t* count, const int64_t* ptr,
               int32_t* starts, int32_t* tail) {
    for (int64_t r = 0; r < N; ++r) {
        const float* v = V + r * n;
        int64_t c = 0, k = 0, t = n;
        while (c < n) {
            if (v[c] == 0.0f) { ++c; continue; }
            const int64_t a = c & ~(int64_t)7;                /* the 8-aligned block holding c */
            if (a + 8 > n) { t = c; break; }
            if (starts) starts[ptr[r] + k] = (int32_t)a;
            ++k;
            c = a + 8;
        }
        if (count) count[r] = k;
        if (tail) tail[r] = (int32_t)t;
    }
}

/* Point i's rho / L weights b0-b3 / l0-l3 and rows R0-R3 / L0-L3 (tp_points, tp_points_cm): a row with
   weight 0 adds exact zeros (finite tables): read the first weighted row in its place (already in L1),
   not a row of its own (a third of the grid weights are 0) */
#define POINT_ROWS \
    const float b0 = bw[4 * i], b1 = bw[4 * i + 1], b2 = bw[4 * i + 2], b3 = bw[4 * i + 3]; \
    const float l0 = lw[4 * i], l1 = lw[4 * i + 1], l2 = lw[4 * i + 2], l3 = lw[4 * i + 3]; \
    const int64_t kb = b0 != 0.0f ? 0 : b1 != 0.0f ? 1 : b2 != 0.0f ? 2 : 3; \
    const int64_t kl = l0 != 0.0f ? 0 : l1 != 0.0f ? 1 : l2 != 0.0f ? 2 : 3; \
    const int64_t* bi = brow + 4 * i; \
    const int64_t* li = lrow + 4 * i; \
    const float *R0 = R + bi[b0 != 0.0f ? 0 : kb] * 3 * n, *R1 = R + bi[b1 != 0.0f ? 1 : kb] * 3 * n, \
                *R2 = R + bi[b2 != 0.0f ? 2 : kb] * 3 * n, *R3 = R + bi[b3 != 0.0f ? 3 : kb] * 3 * n; \
    const float *L0 = L + li[l0 != 0.0f ? 0 : kl] * 3 * n, *L1 = L + li[l1 != 0.0f ? 1 : kl] * 3 * n, \
                *L2 = L + li[l2 != 0.0f ? 2 : kl] * 3 * n, *L3 = L + li[l3 != 0.0f ? 3 : kl] * 3 * n;

/* fast_eval.fine_block with one visibility row per point and 4 rho / 4 L rows:
   out[i, c] = sum_t (vw_i V[v_i, t]) (sum_k bw_ik R[b_ik, c, t]) (sum_j lw_ij L[l_ij, c, t])
   over the chunks of row v_i and its tail. R (N_R, 3, n), L (N_L, 3, n). */
void tp_points(int64_t b, int64_t n, const float* V, const int64_t* vrow, const float* vw,
               const float* R, const int64_t* brow, const float* bw,
               const float* L, const int64_t* lrow, const float* lw,
               const int64_t* ptr, const int32_t* starts, const int32_t* tail, float* out) {
    for (int64_t i = 0; i < b; ++i) {
        const int64_t v = vrow[i];
        const float w = vw[i];
        const float* Vr = V + v * n;
        POINT_ROWS
        for (int c = 0; c < 3; ++c) {   /* one channel at a time: 9 rows streamed, not 25 */
            const float *Rc0 = R0 + c * n, *Rc1 = R1 + c * n, *Rc2 = R2 + c * n, *Rc3 = R3 + c * n;
            const float *Lc0 = L0 + c * n, *Lc1 = L1 + c * n, *Lc2 = L2 + c * n, *Lc3 = L3 + c * n;
            v8 a = {0}, a2 = {0};   /* two accumulators: chunk pairs, no chain of dependent adds */
            int64_t e = ptr[v];
            const int64_t e1 = ptr[v + 1];
            for (; e + 2 <= e1; e += 2) {
                const int64_t o = starts[e], q = starts[e + 1];
                const v8 r = b0 * ld(Rc0 + o) + b1 * ld(Rc1 + o) + b2 * ld(Rc2 + o) + b3 * ld(Rc3 + o);
                const v8 l = l0 * ld(Lc0 + o) + l1 * ld(Lc1 + o) + l2 * ld(Lc2 + o) + l3 * ld(Lc3 + o);
                const v8 r2 = b0 * ld(Rc0 + q) + b1 * ld(Rc1 + q) + b2 * ld(Rc2 + q) + b3 * ld(Rc3 + q);
                const v8 l2_ = l0 * ld(Lc0 + q) + l1 * ld(Lc1 + q) + l2 * ld(Lc2 + q) + l3 * ld(Lc3 + q);
                a += (w * ld(Vr + o)) * r * l;
                a2 += (w * ld(Vr + q)) * r2 * l2_;
            }
            if (e < e1) {
                const int64_t o = starts[e];
                const v8 r = b0 * ld(Rc0 + o) + b1 * ld(Rc1 + o) + b2 * ld(Rc2 + o) + b3 * ld(Rc3 + o);
                const v8 l = l0 * ld(Lc0 + o) + l1 * ld(Lc1 + o) + l2 * ld(Lc2 + o) + l3 * ld(Lc3 + o);
                a += (w * ld(Vr + o)) * r * l;
            }
            float s = hsum(a + a2);
            for (int64_t t = tail[v]; t < n; ++t) {
                const int64_t o = c * n + t;
                const float r = b0 * R0[o] + b1 * R1[o] + b2 * R2[o] + b3 * R3[o];
                const float l = l0 * L0[o] + l1 * L1[o] + l2 * L2[o] + l3 * L3[o];
                s += (w * Vr[t]) * r * l;
            }
            out[3 * i + c] = s;
        }
    }
}

/* tp_points with the rho and / or L table chunk-major (rc / lc: `chunk_major`, (N, n / 8, 3, 8): a row's
   chunk at column o holds its three channels' 8 values side by side, at 3 o + 8 c) and n a multiple of
   8 (no tail): a point's chunks are visited once for all three channels, its rows read in one pass
   instead of three (each chunk's 96 bytes of a row contiguous), each channel's sum the same products
   in the same order as tp_points (chunk pairs into a and a2, the same blends): the same bits.
   vp: V is the visibility table's chunks packed (`packed_chunks`: chunk e of the lists at V + 8 e), so
   a point streams its visibility without the zero gaps between its chunks. */
static inline __attribute__((always_inline)) void points_cm(
        const int rc, const int lc, const int vp, int64_t b, int64_t n, const float* V, const int64_t* vrow, const float* vw,
        const float* R, const int64_t* brow, const float* bw, const float* L, const int64_t* lrow, const float* lw,
        const int64_t* ptr, const int32_t* starts, float* out) {
    const int64_t rs = rc ? 8 : n, ls = lc ? 8 : n;           /* a channel's stride */
    for (int64_t i = 0; i < b; ++i) {
        const int64_t v = vrow[i];
        const float w = vw[i];
        const float* Vr = V + v * n;
        POINT_ROWS
        v8 a[3] = {{0}}, a2[3] = {{0}};
        int64_t e = ptr[v];
        const int64_t e1 = ptr[v + 1];
        for (; e + 2 <= e1; e += 2) {
            const int64_t o = starts[e], q = starts[e + 1];
            const int64_t ro = rc ? 3 * o : o, rq = rc ? 3 * q : q, lo = lc ? 3 * o : o, lq = lc ? 3 * q : q;
            const v8 x = w * ld(vp ? V + 8 * e : Vr + o), x2 = w * ld(vp ? V + 8 * e + 8 : Vr + q);
            for (int c = 0; c < 3; ++c) {
                const int64_t oc = ro + c * rs, qc = rq + c * rs, pc = lo + c * ls, uc = lq + c * ls;
                const v8 r = b0 * ld(R0 + oc) + b1 * ld(R1 + oc) + b2 * ld(R2 + oc) + b3 * ld(R3 + oc);
                const v8 l = l0 * ld(L0 + pc) + l1 * ld(L1 + pc) + l2 * ld(L2 + pc) + l3 * ld(L3 + pc);
                const v8 r2 = b0 * ld(R0 + qc) + b1 * ld(R1 + qc) + b2 * ld(R2 + qc) + b3 * ld(R3 + qc);
                const v8 l2_ = l0 * ld(L0 + uc) + l1 * ld(L1 + uc) + l2 * ld(L2 + uc) + l3 * ld(L3 + uc);
                a[c] += x * r * l;
                a2[c] += x2 * r2 * l2_;
            }
        }
        if (e < e1) {
            const int64_t o = starts[e];
            const int64_t ro = rc ? 3 * o : o, lo = lc ? 3 * o : o;
            const v8 x = w * ld(vp ? V + 8 * e : Vr + o);
            for (int c = 0; c < 3; ++c) {
                const int64_t oc = ro + c * rs, pc = lo + c * ls;
                const v8 r = b0 * ld(R0 + oc) + b1 * ld(R1 + oc) + b2 * ld(R2 + oc) + b3 * ld(R3 + oc);
                const v8 l = l0 * ld(L0 + pc) + l1 * ld(L1 + pc) + l2 * ld(L2 + pc) + l3 * ld(L3 + pc);
                a[c] += x * r * l;
            }
        }
        for (int c = 0; c < 3; ++c) out[3 * i + c] = hsum(a[c] + a2[c]);
    }
}

void tp_points_cm(int64_t b, int64_t n, const float* V, const int64_t* vrow, const float* vw,
                  const float* R, const int64_t* brow, const float* bw,
                  const float* L, const int64_t* lrow, const float* lw,
                  const int64_t* ptr, const int32_t* starts, const int32_t* tail, float* out, int64_t layout) {
    (void)tail;                                               /* n % 8 == 0: every tail is n */
#define CM(RC, LC, VP) points_cm(RC, LC, VP, b, n, V, vrow, vw, R, brow, bw, L, lrow, lw, ptr, starts, out); break;
    switch (layout) {                                         /* 1: R major, 2: L major, 4: V packed */
    case 1: CM(1, 0, 0)
    case 2: CM(0, 1, 0)
    case 3: CM(1, 1, 0)
    case 4: CM(0, 0, 1)
    case 5: CM(1, 0, 1)
    case 6: CM(0, 1, 1)
    default: CM(1, 1, 1)
    }
#undef CM
}

/* The visibility table's chunks packed (`packed_chunks`): out[8 e + k] = V[r, starts[e] + k] for the
   chunks e of row r (ptr[r] <= e < ptr[r + 1]). */
void tp_pack_chunks(int64_t N, int64_t n, const float* V, const int64_t* ptr, const int32_t* starts, float* out) {
    for (int64_t r = 0; r < N; ++r)
        for (int64_t e = ptr[r]; e < ptr[r + 1]; ++e) memcpy(out + 8 * e, V + r * n + starts[e], 8 * sizeof(float));
}

/* The chunk-major copy of T (N, 3n), n % 8 == 0: out[r, j, c, k] = T[r, c, 8 j + k] (`chunk_major`). */
void tp_chunk_major(int64_t N, int64_t n, const float* T, float* out) {
    for (int64_t r = 0; r < N; ++r)
        for (int64_t j = 0; j < n / 8; ++j)
            for (int c = 0; c < 3; ++c)
                memcpy(out + (r * n / 8 + j) * 24 + 8 * c, T + (r * 3 + c) * n + 8 * j, 8 * sizeof(float));
}

/* fast_eval.group_block with 4 L and 4 rho rows per group:
   out[i, (c * 4 + j) * 4 + k] = sum_t (V[g_i, t] L[l_ij, c, t]) R[b_ik, c, t]
   over the chunks of row g_i and its tail; two L rows (8 sums) per pass over the chunks (tp_groups2;
   tp_groups: four on a CPU with AVX-512, below). */
void tp_groups2(int64_t g, int64_t n, const float* V, const int64_t* vrow, const float* R,
               const int64_t* brow, const float* L, const int64_t* lrow, const int64_t* ptr,
               const int32_t* starts, const int32_t* tail, float* out) {
    for (int64_t i = 0; i < g; ++i) {
        const int64_t v = vrow[i];
        const float* Vr = V + v * n;
        const int64_t e0 = ptr[v], e1 = ptr[v + 1], t0 = tail[v];
        for (int c = 0; c < 3; ++c) {
            const float *R0 = R + (brow[4 * i] * 3 + c) * n, *R1 = R + (brow[4 * i + 1] * 3 + c) * n,
                        *R2 = R + (brow[4 * i + 2] * 3 + c) * n, *R3 = R + (brow[4 * i + 3] * 3 + c) * n;
            for (int j = 0; j < 4; j += 2) {
                const float *La = L + (lrow[4 * i + j] * 3 + c) * n, *Lb = L + (lrow[4 * i + j + 1] * 3 + c) * n;
                v8 a0 = {0}, a1 = {0}, a2 = {0}, a3 = {0}, c0 = {0}, c1 = {0}, c2 = {0}, c3 = {0};
                for (int64_t e = e0; e < e1; ++e) {
                    const int64_t s = starts[e];
                    const v8 x = ld(Vr + s);
                    const v8 ua = x * ld(La + s), ub = x * ld(Lb + s);
                    const v8 r0 = ld(R0 + s), r1 = ld(R1 + s), r2 = ld(R2 + s), r3 = ld(R3 + s);
                    a0 += ua * r0; a1 += ua * r1; a2 += ua * r2; a3 += ua * r3;
                    c0 += ub * r0; c1 += ub * r1; c2 += ub * r2; c3 += ub * r3;
                }
                float sa[4] = {hsum(a0), hsum(a1), hsum(a2), hsum(a3)};
                float sb[4] = {hsum(c0), hsum(c1), hsum(c2), hsum(c3)};
                for (int64_t t = t0; t < n; ++t) {
                    const float ua = Vr[t] * La[t], ub = Vr[t] * Lb[t];
                    sa[0] += ua * R0[t]; sa[1] += ua * R1[t]; sa[2] += ua * R2[t]; sa[3] += ua * R3[t];
                    sb[0] += ub * R0[t]; sb[1] += ub * R1[t]; sb[2] += ub * R2[t]; sb[3] += ub * R3[t];
                }
                float* o = out + 48 * i + (c * 4 + j) * 4;
                for (int k = 0; k < 4; ++k) { o[k] = sa[k]; o[4 + k] = sb[k]; }
            }
        }
    }
}
#if defined(__GNUC__) && defined(__x86_64__) && defined(__AVX2__) && defined(__FMA__)
/* tp_groups2's chunk sums of one (group, channel) with all four L rows per pass over the chunks, in
   AVX-512's 32 vector registers (this function only; tp_groups takes it when the CPU has AVX-512): the
   visibility and rho chunks loaded once, not twice (creature bench pixel frame, 1 thread: tp_groups
   1.12x; with AVX2's 16 registers the 16 sums spill: 0.90x). Each sum gets the same products in the
   same order as in tp_groups2, the tails are summed outside (AVX2 code, as there): the same bits
   (tests/methods/triple_product/test_tp_native.py). */
__attribute__((target("avx512f,avx512vl,avx512dq,avx512bw,avx2,fma")))
static void chunk_sums4(int64_t e0, int64_t e1, const int32_t* starts, const float* Vr, const float* const* Lj,
                        const float* const* Rk, float* out16) {
    v8 a[4][4];
    for (int h = 0; h < 4; ++h)
        for (int k = 0; k < 4; ++k) a[h][k] = (v8){0};
    for (int64_t e = e0; e < e1; ++e) {
        const int64_t s = starts[e];
        const v8 x = ld(Vr + s);
        const v8 r0 = ld(Rk[0] + s), r1 = ld(Rk[1] + s), r2 = ld(Rk[2] + s), r3 = ld(Rk[3] + s);
        for (int h = 0; h < 4; ++h) {
            const v8 u = x * ld(Lj[h] + s);
            a[h][0] += u * r0; a[h][1] += u * r1; a[h][2] += u * r2; a[h][3] += u * r3;
        }
    }
    for (int h = 0; h < 4; ++h)
        for (int k = 0; k < 4; ++k) out16[4 * h + k] = hsum(a[h][k]);
}
#define HAVE_SUMS4 1
#endif

void tp_groups(int64_t g, int64_t n, const float* V, const int64_t* vrow, const float* R,
               const int64_t* brow, const float* L, const int64_t* lrow, const int64_t* ptr,
               const int32_t* starts, const int32_t* tail, float* out) {
#ifdef HAVE_SUMS4
    if (__builtin_cpu_supports("avx512f") && __builtin_cpu_supports("avx512vl")) {
        for (int64_t i = 0; i < g; ++i) {
            const int64_t v = vrow[i];
            const float* Vr = V + v * n;
            const int64_t e0 = ptr[v], e1 = ptr[v + 1], t0 = tail[v];
            for (int c = 0; c < 3; ++c) {
                const float* Rk[4];
                const float* Lj[4];
                for (int k = 0; k < 4; ++k) {
                    Rk[k] = R + (brow[4 * i + k] * 3 + c) * n;
                    Lj[k] = L + (lrow[4 * i + k] * 3 + c) * n;
                }
                float* o = out + 48 * i + c * 16;              /* (c * 4 + j) * 4 + k */
                chunk_sums4(e0, e1, starts, Vr, Lj, Rk, o);
                for (int j = 0; j < 4; ++j) {
                    float sa[4] = {o[4 * j], o[4 * j + 1], o[4 * j + 2], o[4 * j + 3]};
                    for (int64_t t = t0; t < n; ++t) {
                        const float u = Vr[t] * Lj[j][t];
                        sa[0] += u * Rk[0][t]; sa[1] += u * Rk[1][t]; sa[2] += u * Rk[2][t]; sa[3] += u * Rk[3][t];
                    }
                    for (int k = 0; k < 4; ++k) o[4 * j + k] = sa[k];
                }
            }
        }
        return;
    }
#endif
    tp_groups2(g, n, V, vrow, R, brow, L, lrow, ptr, starts, tail, out);
}

/* tp_points / tp_groups over [0, b) items on nt threads of OpenMP's team (the libgomp torch loaded:
   the threads Inductor's kernels use): blk <= 0, thread k the items [b k / nt, b (k + 1) / nt); blk > 0
   (session 39), blocks of blk items handed out dynamically — a thread that shares its core with other
   work (the harness's, another process's) takes fewer blocks instead of holding the region's end. Each
   point's sums in one thread either way: the same bits. */
#define POINTS_SPLIT(CALL)                                                                         \
    if (blk > 0) {                                                                                 \
        const int64_t nb = (b + blk - 1) / blk;                                                    \
        _Pragma("omp parallel for num_threads(nt) schedule(dynamic, 1)")                           \
        for (int64_t q = 0; q < nb; ++q) {                                                         \
            const int64_t a = q * blk, e = a + blk < b ? a + blk : b;                              \
            CALL;                                                                                  \
        }                                                                                          \
    } else {                                                                                       \
        _Pragma("omp parallel for num_threads(nt) schedule(static, 1)")                            \
        for (int64_t k = 0; k < nt; ++k) {                                                         \
            const int64_t a = b * k / nt, e = b * (k + 1) / nt;                                    \
            CALL;                                                                                  \
        }                                                                                          \
    }
void tp_points_par(int64_t b, int64_t n, const float* V, const int64_t* vrow, const float* vw,
                   const float* R, const int64_t* brow, const float* bw,
                   const float* L, const int64_t* lrow, const float* lw,
                   const int64_t* ptr, const int32_t* starts, const int32_t* tail, float* out, int64_t nt,
                   int64_t blk) {
    POINTS_SPLIT(tp_points(e - a, n, V, vrow + a, vw + a, R, brow + 4 * a, bw + 4 * a, L, lrow + 4 * a, lw + 4 * a,
                           ptr, starts, tail, out + 3 * a))
}
void tp_points_cm_par(int64_t b, int64_t n, const float* V, const int64_t* vrow, const float* vw,
                      const float* R, const int64_t* brow, const float* bw,
                      const float* L, const int64_t* lrow, const float* lw,
                      const int64_t* ptr, const int32_t* starts, const int32_t* tail, float* out, int64_t layout,
                      int64_t nt, int64_t blk) {
    POINTS_SPLIT(tp_points_cm(e - a, n, V, vrow + a, vw + a, R, brow + 4 * a, bw + 4 * a, L, lrow + 4 * a,
                              lw + 4 * a, ptr, starts, tail, out + 3 * a, layout))
}
void tp_groups_par(int64_t g, int64_t n, const float* V, const int64_t* vrow, const float* R,
                   const int64_t* brow, const float* L, const int64_t* lrow, const int64_t* ptr,
                   const int32_t* starts, const int32_t* tail, float* out, int64_t nt) {
#pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int64_t k = 0; k < nt; ++k) {
        const int64_t a = g * k / nt, e = g * (k + 1) / nt;
        tp_groups(e - a, n, V, vrow + a, R, brow + 4 * a, L, lrow + 4 * a, ptr, starts, tail, out + 48 * a);
    }
}

/* A per-vertex frame's bookkeeping of what it reads: fseen[f] = 1 for the faces f (of nf) that the
   P samples with hit[i] see (face[i]), vseen[v] = 1 for their vertices (F (nf, 3), nv of them);
   counts[0] = the hit samples, counts[1] = -1 when a hit sample's face or a seen face's vertex is
   outside its table (the marks then undefined), else 0. */
void tp_hit_faces(int64_t P, const uint8_t* hit, const int64_t* face, int64_t nf, const int64_t* F, int64_t nv,
                  uint8_t* fseen, uint8_t* vseen, int64_t* counts, int64_t nt) {
    /* session 39: the samples, then the faces, split over nt threads (the marks are 1 or untouched, stored
       relaxed-atomically: the same marks and counts at any thread count; this ran on one thread,
       ~0.3-0.4 ms of a creature bench vertex frame) */
    int64_t h = 0, bad = 0;
#pragma omp parallel for num_threads(nt) schedule(static) reduction(+:h) reduction(|:bad) if (nt > 1)
    for (int64_t i = 0; i < P; ++i) {
        if (!hit[i]) continue;
        const int64_t f = face[i];
        ++h;
        if ((uint64_t)f >= (uint64_t)nf) { bad = 1; continue; }
        __atomic_store_n(fseen + f, (uint8_t)1, __ATOMIC_RELAXED);
    }
    if (!bad) {
#pragma omp parallel for num_threads(nt) schedule(static) reduction(|:bad) if (nt > 1)
        for (int64_t f = 0; f < nf; ++f) {
            if (!fseen[f]) continue;
            for (int k = 0; k < 3; ++k) {
                const int64_t v = F[3 * f + k];
                if ((uint64_t)v >= (uint64_t)nv) { bad = 1; break; }
                __atomic_store_n(vseen + v, (uint8_t)1, __ATOMIC_RELAXED);
            }
        }
    }
    counts[0] = h;
    counts[1] = bad ? -1 : 0;
}

/* tp_hit_faces with the lists made here: seen (nf + nv bytes, zeroed by the caller) the two marks,
   lists (nf + nv) int64: the seen faces in order at lists[0 ..), the seen vertices in order at
   lists[nf ..); counts[2], counts[3] their numbers (what torch.nonzero of the marks gives). */
void tp_hit_lists(int64_t P, const uint8_t* hit, const int64_t* face, int64_t nf, const int64_t* F, int64_t nv,
                  uint8_t* seen, int64_t* lists, int64_t* counts, int64_t nt) {
    tp_hit_faces(P, hit, face, nf, F, nv, seen, seen + nf, counts, nt);
    if (counts[1] != 0) return;
    int64_t k = 0;
    for (int64_t f = 0; f < nf; ++f)
        if (seen[f]) lists[k++] = f;
    counts[2] = k;
    k = 0;
    for (int64_t v = 0; v < nv; ++v)
        if (seen[nf + v]) lists[nf + k++] = v;
    counts[3] = k;
}

/* A per-vertex frame's Gouraud resolve (methods/core/gouraud.py's resolve3 loop, the same sums in the
   same order with the same float32 operations, no contraction: the same bits) with the seen faces'
   corner colours gathered first into a face table T (nf, 9) (T[9 f + 3 c + ch] = val[3 F[3 f + c] + ch],
   the nfs faces of faces[], `hit_faces`' list), so a sample reads its face's 9 colours from one row
   instead of F's row and then three vertex rows (a chain of two dependent loads fewer). Pixels
   [0, n): out[i, ch] = (1 / S2) sum over its hit samples p, in order, of (x w + y u) + z v, w = 1 - u - v.
   Every hit sample's face must be one of faces[] (hit_faces' list of the same arrays: unchecked here).
   Faces, then pixels, split over nt threads of OpenMP's team (each pixel one thread's: the same bits). */
__attribute__((optimize("-ffp-contract=off")))
void tp_resolve(int64_t n, int64_t S2, const uint8_t* hit, const int64_t* face, const float* bu, const float* bv,
                const int64_t* F, const float* val, const int64_t* faces, int64_t nfs, float* T, float* out,
                int64_t nt) {
    const float inv = 1.0f / (float)S2;
#pragma omp parallel num_threads(nt) if (nt > 1)
    {
#pragma omp for schedule(static)
        for (int64_t k = 0; k < nfs; ++k) {
            const int64_t f = faces[k];
            float* t = T + 9 * f;
            for (int c = 0; c < 3; ++c) {
                const float* x = val + 3 * F[3 * f + c];
                t[3 * c] = x[0]; t[3 * c + 1] = x[1]; t[3 * c + 2] = x[2];
            }
        }
#pragma omp for schedule(static)
        for (int64_t i = 0; i < n; ++i) {
            float a0 = 0.0f, a1 = 0.0f, a2 = 0.0f;
            for (int64_t p = i * S2; p < (i + 1) * S2; ++p) {
                if (!hit[p]) continue;
                const float u = bu[p], v = bv[p], w = 1.0f - u - v;
                const float* x = T + 9 * face[p];
                a0 += (x[0] * w + x[3] * u) + x[6] * v;
                a1 += (x[1] * w + x[4] * u) + x[7] * v;
                a2 += (x[2] * w + x[5] * u) + x[8] * v;
            }
            out[3 * i] = a0 * inv;
            out[3 * i + 1] = a1 * inv;
            out[3 * i + 2] = a2 * inv;
        }
    }
}

/* A per-vertex frame's look-ups (`fast_eval.grid_lookups` of the frames R and the directions to the
   camera, trilinear on a grid with one tangent angle: `brdf_table.outgoing_terms`, then
   `lighting.cell_terms`) for the b vertices used[k] in one pass: wo = normalize(cam - P[v]) (float32,
   as the render's torch ops), its local coordinates R[v] wo (float32), θ, φ of those in float64 (libm
   acos / atan2: within an ulp of the compiled kernel's), the ωo cell's 4 rows + region[v] * ot * op
   and weights, then the 4 grid rows and weights of the normal R[v][2] — the compiled arithmetic step
   by step (no contraction), so the same rows and weights to an ulp of float64 (float32 round-off
   after the cast). ot, op: the ωo grid's n_theta, n_phi; gt, gp: the frame grid's. glr, glw (N, 4) or
   NULL: the grid rows and weights of every vertex's normal, made by this loop before (copied). The
   vertices split over nt threads of OpenMP's team (each vertex's values one thread's: the same bits). */
__attribute__((optimize("-ffp-contract=off")))
void tp_vertex_lookups(int64_t b, const int64_t* used, const float* P, const float* Rf, const int64_t* region,
                       const float* cam, int64_t ot, int64_t op, int64_t gt, int64_t gp, const int64_t* glr,
                       const float* glw, int64_t* brows, float* bw, int64_t* lrows, float* lw, int64_t nt) {
    const double PI = 3.141592653589793, TWO_PI = 6.283185307179586;
    const double sto = 0.5 * PI / (double)ot, spo = TWO_PI / (double)op;
    const double stg = PI / (double)(gt - 1), spg = TWO_PI / (double)gp;
    const int64_t oi_max = ot - 2 > 0 ? ot - 2 : 0;
#pragma omp parallel for num_threads(nt) schedule(static) if (nt > 1)
    for (int64_t k = 0; k < b; ++k) {
        const int64_t v = used[k];
        const float* p = P + 3 * v;
        const float* R = Rf + 9 * v;
        const float dx = cam[0] - p[0], dy = cam[1] - p[1], dz = cam[2] - p[2];
        float nrm = sqrtf(fmaf(dz, dz, fmaf(dy, dy, dx * dx)));      /* torch.linalg.vector_norm's float32 sum */
        nrm = nrm > 1e-12f ? nrm : 1e-12f;
        const float wx = dx / nrm, wy = dy / nrm, wz = dz / nrm;
        const double x = (double)(R[0] * wx + R[1] * wy + R[2] * wz);
        const double y = (double)(R[3] * wx + R[4] * wy + R[5] * wz);
        const double z = (double)(R[6] * wx + R[7] * wy + R[8] * wz);
        double nn = sqrt(x * x + y * y + z * z);
        nn = nn > 1e-30 ? nn : 1e-30;
        double c = z / nn;
        c = c < 0.0 ? 0.0 : c > 1.0 ? 1.0 : c;
        const double th = acos(c);
        double ph = atan2(y, x);
        ph = ph - TWO_PI * floor(ph / TWO_PI);
        double fi = th / sto - 0.5;
        fi = fi < 0.0 ? 0.0 : fi > (double)(ot - 1) ? (double)(ot - 1) : fi;
        const double fj = ph / spo;
        int64_t i0 = (int64_t)floor(fi);
        i0 = i0 < 0 ? 0 : i0 > oi_max ? oi_max : i0;
        double ai = fi - (double)i0;
        ai = ai < 0.0 ? 0.0 : ai > 1.0 ? 1.0 : ai;
        const int64_t i1 = i0 + 1 < ot - 1 ? i0 + 1 : ot - 1;
        const int64_t j0 = (int64_t)floor(fj);
        const double aj = fj - (double)j0;
        const int64_t off = region[v] * ot * op;
        for (int dj = 0; dj < 2; ++dj) {
            int64_t j = j0 + dj;
            j = j >= op ? j - op : j;
            j = j >= op ? j - op : j < 0 ? 0 : j;
            const double wj = dj ? aj : 1.0 - aj;
            brows[4 * k + dj] = i0 * op + j + off;
            brows[4 * k + 2 + dj] = i1 * op + j + off;
            bw[4 * k + dj] = (float)((1.0 - ai) * wj);
            bw[4 * k + 2 + dj] = (float)(ai * wj);
        }
        if (glr) {                      /* the normals' cells given (N, 4): static frames, made once */
            for (int q = 0; q < 4; ++q) { lrows[4 * k + q] = glr[4 * v + q]; lw[4 * k + q] = glw[4 * v + q]; }
            continue;
        }
        /* the grid cell of the normal (row 2 of R): θ from +Y, φ from +X towards +Z */
        double ny = (double)R[7];
        ny = ny < -1.0 ? -1.0 : ny > 1.0 ? 1.0 : ny;
        const double gth = acos(ny);
        double gph = atan2((double)R[8], (double)R[6]);
        gph = gph - TWO_PI * floor(gph / TWO_PI);
        double gi = gth / stg;
        gi = gi < 0.0 ? 0.0 : gi > (double)(gt - 1) ? (double)(gt - 1) : gi;
        const double gj = gph / spg;
        int64_t g0 = (int64_t)floor(gi);
        g0 = g0 < 0 ? 0 : g0 > gt - 2 ? gt - 2 : g0;
        double bi = gi - (double)g0;
        bi = bi < 0.0 ? 0.0 : bi > 1.0 ? 1.0 : bi;
        const int64_t h0 = (int64_t)floor(gj);
        const double bj = gj - (double)h0;
        for (int di = 0; di < 2; ++di)
            for (int dj = 0; dj < 2; ++dj) {
                int64_t j = h0 + dj;
                j = j >= gp ? j - gp : j;
                j = j >= gp ? j - gp : j < 0 ? 0 : j;
                lrows[4 * k + 2 * di + dj] = (g0 + di) * gp + j;
                lw[4 * k + 2 * di + dj] = (float)((di ? bi : 1.0 - bi) * (dj ? bj : 1.0 - bj));
            }
    }
}
"""


def _flags() -> tuple[str, ...]:
    """Fused multiply-adds, OpenMP and the host's ISA (`methods.core.native.isa_flags`)."""
    return ("-ffp-contract=fast", "-fopenmp", *native.isa_flags())


_P, _I = ctypes.c_void_p, ctypes.c_int64
_SIGNATURES = {"tp_chunks": [_P, _I, _I, _P, _P, _P, _P],
               "tp_points": [_I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P],
               "tp_groups": [_I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P],
               "tp_groups2": [_I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P],
               "tp_points_par": [_I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _I, _I],
               "tp_points_cm": [_I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _I],
               "tp_points_cm_par": [_I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _I, _I, _I],
               "tp_chunk_major": [_I, _I, _P, _P],
               "tp_pack_chunks": [_I, _I, _P, _P, _P, _P],
               "tp_groups_par": [_I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _P, _I],
               "tp_hit_faces": [_I, _P, _P, _I, _P, _I, _P, _P, _P, _I],
               "tp_hit_lists": [_I, _P, _P, _I, _P, _I, _P, _P, _P, _I],
               "tp_resolve": [_I, _I, _P, _P, _P, _P, _P, _P, _P, _I, _P, _P, _I],
               "tp_vertex_lookups": [_I, _P, _P, _P, _P, _P, _I, _I, _I, _I, _P, _P, _P, _P, _P, _P, _I]}


def switched_on() -> bool:
    """False when ``PRTBENCH_TP_NATIVE`` is 0 / false / no / off: the triple product's native loops
    (this module's and `native_light`'s) are then not used."""
    return switches.on("PRTBENCH_TP_NATIVE")


# The libraries this package loaded (`loaded`): a `_lib` call in a frame is the two switches and a dict
# look-up instead of `native.load`'s (its signature tuples built and its lru key hashed at each call: ~25-30
# µs on a loaded host, 6-11 calls a per-vertex frame). Only a library that loaded is kept — a None (no
# compiler, an off switch, a failed build) is never remembered, and the switches are read at every call
# (tests/methods/test_native_off_switch.py). False: `native.load` at every call.
LIB_MEMO = True
_LOADED: dict = {}


def loaded(name: str, source: str, signatures: dict, flags: tuple[str, ...], *, quiet: bool = False):
    """`methods.core.native.load` (name, source, signatures, extra_flags=flags) — without its build-failure
    warning when ``quiet`` — remembered once it loaded (`LIB_MEMO`); None when ``PRTBENCH_TP_NATIVE`` or
    ``PRTBENCH_COMPILE`` is off (read at each call) or the library does not load."""
    if not switched_on() or not compile_enabled():
        return None
    key = (name, flags)
    lib = _LOADED.get(key) if LIB_MEMO else None
    if lib is None:
        if quiet:
            import warnings

            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                lib = native.load(name, source, signatures, extra_flags=flags)
        else:
            lib = native.load(name, source, signatures, extra_flags=flags)
        if lib is not None and LIB_MEMO:
            _LOADED[key] = lib
    return lib


def _lib():
    """The library (`methods.core.native.load`, through `loaded`) or None: no compiler, the build failed,
    ``PRTBENCH_COMPILE=0`` or ``PRTBENCH_TP_NATIVE=0``."""
    return loaded("tp_zeros", _SOURCE, _SIGNATURES, _flags())


def available() -> bool:
    """True when the native loops run (else `fast_eval` uses the compiled torch kernels)."""
    return _lib() is not None


def chunks(V: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The chunk lists of a visibility fine-value table V (N, n) float32 (module docstring): row
    pointers (N + 1,) int64, chunk starts (ptr[-1],) int32 and tails (N,) int32. Two passes over V
    (chess bench, 10701 × 640: a few ms, once per table)."""
    lib = _lib()
    if lib is None:
        raise RuntimeError("the native kernel is not available")
    V = V.contiguous()
    if V.dtype != torch.float32 or V.ndim != 2 or V.device.type != "cpu":
        raise ValueError(f"V must be (N, n) float32 on the CPU, got {tuple(V.shape)} {V.dtype}")
    N, n = V.shape
    count = torch.empty(N, dtype=torch.int64)
    lib.tp_chunks(V.data_ptr(), N, n, count.data_ptr(), None, None, None)
    ptr = torch.zeros(N + 1, dtype=torch.int64)
    torch.cumsum(count, 0, out=ptr[1:])
    starts = torch.empty(int(ptr[-1]), dtype=torch.int32)
    tail = torch.empty(N, dtype=torch.int32)
    lib.tp_chunks(V.data_ptr(), N, n, None, ptr.data_ptr(), starts.data_ptr(), tail.data_ptr())
    return ptr, starts, tail


def _rows_ok(rows: Tensor, N: int) -> bool:
    return rows.numel() == 0 or (int(rows.min()) >= 0 and int(rows.max()) < N)


# Items below which one thread does the sums (a hand-off costs more than the share).
MIN_ITEMS_PER_THREAD = 256
# `points` at 2+ threads (session 39): blocks of this many points handed out dynamically (the same bits:
# each point's sums in one thread); 0: the static split, thread k the points [b k / nt, b (k + 1) / nt).
POINTS_BLOCK = 64
# `hit_faces`' marks split over torch's threads (session 39); False: one thread (the loop before).
HIT_THREADS = True
MIN_HIT_SAMPLES_PER_THREAD = 16384


def _threads(b: int) -> int:
    """Threads of a pass over b items: ``torch.get_num_threads()``, fewer for small passes. More than
    one runs the ``_par`` loop on OpenMP's team: a Python thread pool's hand-off waits for a core the
    OpenMP workers spin on (`methods.core.gouraud`'s measurement: 1.63 against 0.93 ms)."""
    return max(1, min(torch.get_num_threads(), b // MIN_ITEMS_PER_THREAD))


def _check_tables(V: Tensor | None, R: Tensor, L: Tensor, ch, v_shape: tuple[int, int] | None = None) -> int:
    """The row length n of the tables (checked). V None: a visibility table of shape ``v_shape`` (N, n)
    kept only as its chunks packed (`packed_chunks`, checked by the caller)."""
    if V is None and v_shape is None:
        raise ValueError("a visibility table or its shape (v_shape) expected")
    N, n = (int(v_shape[0]), int(v_shape[1])) if V is None else (V.shape[0], V.shape[1])
    for t in (R, L) if V is None else (V, R, L):
        if t.dtype != torch.float32 or t.ndim != 2 or not t.is_contiguous() or t.device.type != "cpu":
            raise ValueError("tables must be contiguous float32 (N, ·) CPU tensors")
    if R.shape[1] != 3 * n or L.shape[1] != 3 * n:
        raise ValueError(f"tables must be (N, n), (N, 3n), (N, 3n), got {(N, n)}, {tuple(R.shape)}, {tuple(L.shape)}")
    ptr, starts, tail = ch
    if ptr.numel() != N + 1 or tail.numel() != N:
        raise ValueError("chunk lists of another table")
    return n


def chunk_major(T: Tensor) -> Tensor | None:
    """The chunk-major copy of a ρ̃ or L fine-value table T (N, 3n) float32, n a multiple of `W`:
    (N, 3n) whose row r holds, chunk j after chunk j − 1, the three channels' 8 values T[r, c, 8j: 8j + 8]
    (``T.view(N, 3, n // W, W).transpose(1, 2)``, one pass in C) — what `points` reads with ``r_major`` /
    ``l_major``; None without the library or for another shape."""
    lib = _lib()
    if lib is None or T.dtype != torch.float32 or T.ndim != 2 or T.shape[1] % (3 * W) or T.device.type != "cpu":
        return None
    T = T.contiguous()
    out = torch.empty_like(T)
    lib.tp_chunk_major(T.shape[0], T.shape[1] // 3, T.data_ptr(), out.data_ptr())
    return out


def packed_chunks(V: Tensor, ch) -> Tensor | None:
    """The chunks ``ch`` (`chunks` of V) of the visibility table V (N, n) float32 packed, row after row
    in their order: (ptr[-1], 8), row e the 8 values of chunk e (what `points` reads with ``v_packed``;
    one pass in C); None without the library."""
    lib = _lib()
    if lib is None or V.dtype != torch.float32 or V.ndim != 2 or V.device.type != "cpu":
        return None
    ptr, starts, tail = ch
    if ptr.numel() != V.shape[0] + 1:
        raise ValueError("chunk lists of another table")
    V = V.contiguous()
    out = torch.empty(int(ptr[-1]), W, dtype=torch.float32)
    lib.tp_pack_chunks(V.shape[0], V.shape[1], V.data_ptr(), ptr.data_ptr(), starts.data_ptr(), out.data_ptr())
    return out


def unpack_chunks(packed: Tensor, ch, shape: tuple[int, int]) -> Tensor:
    """The visibility table (N, n) = ``shape`` whose chunks ``ch`` (`chunks` of it) ``packed``
    (`packed_chunks`) holds: every chunk's 8 values back at its columns, 0 elsewhere — the table
    `packed_chunks` was made from where it is non-zero (`chunks` covers every non-zero column of a row
    when 8 divides n; a −0 outside the chunks comes back as +0). In torch (readers that need whole rows
    of a table kept packed only: slow, not cached by this function)."""
    ptr, starts, _ = ch
    N, n = int(shape[0]), int(shape[1])
    if n % W or ptr.numel() != N + 1 or packed.shape != (starts.numel(), W):
        raise ValueError("packed chunks of another table, or a row length not a multiple of 8")
    out = torch.zeros(N * n, dtype=packed.dtype)
    row = torch.repeat_interleave(torch.arange(N, dtype=torch.int64), ptr.diff())
    at = (row * n + starts.to(torch.int64))[:, None] + torch.arange(W, dtype=torch.int64)
    out[at.reshape(-1)] = packed.reshape(-1)
    return out.view(N, n)


def points(V: Tensor | None, R: Tensor, L: Tensor, vrow: Tensor, vw: Tensor, brows: Tensor, bw: Tensor,
           lrows: Tensor, lw: Tensor, ch, *, r_major: bool = False, l_major: bool = False,
           v_packed: Tensor | None = None, v_shape: tuple[int, int] | None = None) -> Tensor:
    """`fast_eval.fine_block` of b points with one visibility row each (vrow (b,), vw (b,)), 4 ρ̃ rows
    (brows, bw (b, 4)) and 4 grid rows (lrows, lw (b, 4)), over the chunks ``ch`` (`chunks` of V)
    of each point's row: V (N_V, n), R (N_ρ, 3n), L (N_L, 3n) float32 (finite: a row with weight 0
    is not read, the point's first weighted row is read in its place, times 0). → (b, 3).
    ``r_major`` / ``l_major``: R / L is `chunk_major` (n a multiple of `W`): ``tp_points_cm`` visits a
    point's chunks once for the three channels, reading each row in one pass — the same sums bit for
    bit (creature bench vertex V, cache cooled, 1 thread: the loop 1.12x with both tables chunk-major,
    1.06x with ρ̃ only; `fast_eval.rho_major`, `fast_eval.light_major`). ``v_packed``: `packed_chunks` of
    V and ``ch``, which the loop streams instead of V's rows (the same bits; the loop with both tables
    chunk-major 1.2-1.3x faster again). V None: the table kept only as ``v_packed`` (`fast_eval.vis_packed`
    with ``VIS_PACKED_ONLY``), its shape ``v_shape`` (N, n)."""
    lib = _lib()
    if V is None and v_packed is None:
        raise ValueError("V None needs its packed chunks (v_packed)")
    n = _check_tables(V, R, L, ch, v_shape)
    N = int(v_shape[0]) if V is None else V.shape[0]
    layout = int(r_major) + 2 * int(l_major) + 4 * int(v_packed is not None)
    if v_packed is not None and (v_packed.dtype != torch.float32 or not v_packed.is_contiguous()
                                 or v_packed.shape != (ch[1].numel(), W)):
        raise ValueError("v_packed must be packed_chunks of V and its chunk lists")
    if layout and n % W:
        raise ValueError(f"chunk-major tables need a row length that is a multiple of {W}, got {n}")
    b = vrow.shape[0]
    vrow, brows, lrows = (x.to(torch.int64).contiguous() for x in (vrow, brows, lrows))
    vw, bw, lw = (x.to(torch.float32).contiguous() for x in (vw, bw, lw))
    if vrow.shape != (b,) or vw.shape != (b,) or brows.shape != (b, 4) or bw.shape != (b, 4) \
            or lrows.shape != (b, 4) or lw.shape != (b, 4):
        raise ValueError("vrow, vw (b,) and brows, bw, lrows, lw (b, 4) expected")
    if not (_rows_ok(vrow, N) and _rows_ok(brows, R.shape[0]) and _rows_ok(lrows, L.shape[0])):
        raise IndexError("a row index outside its table")
    out = torch.empty(b, 3, dtype=torch.float32)
    if b == 0:
        return out
    ptr, starts, tail = ch
    tabs = (v_packed.data_ptr() if V is None else V.data_ptr(), R.data_ptr(), L.data_ptr(), ptr.data_ptr(), starts.data_ptr(), tail.data_ptr())

    args = (b, n, tabs[0], vrow.data_ptr(), vw.data_ptr(), tabs[1], brows.data_ptr(), bw.data_ptr(),
            tabs[2], lrows.data_ptr(), lw.data_ptr(), *tabs[3:], out.data_ptr())
    nt = _threads(b)
    if layout:
        if v_packed is not None:
            args = (args[0], args[1], v_packed.data_ptr(), *args[3:])
        lib.tp_points_cm(*args, layout) if nt == 1 else lib.tp_points_cm_par(*args, layout, nt, POINTS_BLOCK)
    else:
        lib.tp_points(*args) if nt == 1 else lib.tp_points_par(*args, nt, POINTS_BLOCK)
    return out


def groups(V: Tensor, R: Tensor, L: Tensor, gv: Tensor, gl: Tensor, gb: Tensor, ch) -> Tensor:
    """`fast_eval.group_block` of g groups (gv (g,), gl (g, 4) grid rows, gb (g, 4) ρ̃ rows) over the
    chunks ``ch`` of each group's visibility row: (g, 48), index (c, j, k)."""
    lib = _lib()
    n = _check_tables(V, R, L, ch)
    g = gv.shape[0]
    gv, gl, gb = (x.to(torch.int64).contiguous() for x in (gv, gl, gb))
    if gv.shape != (g,) or gl.shape != (g, 4) or gb.shape != (g, 4):
        raise ValueError("gv (g,), gl and gb (g, 4) expected")
    if not (_rows_ok(gv, V.shape[0]) and _rows_ok(gb, R.shape[0]) and _rows_ok(gl, L.shape[0])):
        raise IndexError("a row index outside its table")
    out = torch.empty(g, 48, dtype=torch.float32)
    if g == 0:
        return out
    ptr, starts, tail = ch

    args = (g, n, V.data_ptr(), gv.data_ptr(), R.data_ptr(), gb.data_ptr(), L.data_ptr(), gl.data_ptr(),
            ptr.data_ptr(), starts.data_ptr(), tail.data_ptr(), out.data_ptr())
    nt = _threads(g)
    lib.tp_groups(*args) if nt == 1 else lib.tp_groups_par(*args, nt)
    return out


def vertex_lookups(used: Tensor, P: Tensor, R: Tensor, region: Tensor, cam: Tensor, outgoing, grid,
                   cells: tuple[Tensor, Tensor] | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor] | None:
    """A per-vertex frame's look-ups of the vertices ``used`` (b,) int64 in one C pass: (brows, bw,
    lrows, lw), (b, 4) each — the ωo rows of `fast_eval.grid_lookups` (R[used], normalize(cam −
    P[used]), ``outgoing``, ``grid``, "trilinear") offset by region[used] · outgoing.size (as
    `fast_eval.shading_rows` makes them), its weights, and the grid rows / weights of the normals
    R[used][:, 2] (`lighting.cell_terms`) — the rows those give and their weights to float32
    round-off (float64 libm trig in place of the compiled kernel's: an ulp of float64 before the
    cast to float32). P (N, 3), R (N, 3, 3) float32, region (N,) int64, cam (3,) float32; ``cells``:
    (lrows, lw) (N, 4) of every vertex (this function's of all vertices: the frames are static), copied
    instead of made (two float64 trig calls a vertex fewer). None
    without the library, for a grid with more than one tangent angle or other dtypes / layouts
    (`fast_eval.grid_lookups` serves)."""
    lib = _lib()
    if lib is None or grid.n_psi != 1 or grid.n_theta < 2 or P.dtype != torch.float32 \
            or R.dtype != torch.float32 or region.dtype != torch.int64 or used.dtype != torch.int64 \
            or P.ndim != 2 or P.shape[1] != 3 or R.shape != (P.shape[0], 3, 3) or region.shape != (P.shape[0],) \
            or cam.shape != (3,) or used.ndim != 1 or not (P.is_contiguous() and R.is_contiguous()
                                                           and region.is_contiguous() and used.is_contiguous()) \
            or any(t.device.type != "cpu" for t in (used, P, R, region, cam)):
        return None
    if cells is not None and (cells[0].shape != (P.shape[0], 4) or cells[1].shape != (P.shape[0], 4)
                              or cells[0].dtype != torch.int64 or cells[1].dtype != torch.float32
                              or not (cells[0].is_contiguous() and cells[1].is_contiguous())):
        raise ValueError("cells (N, 4) int64 and float32 contiguous expected")
    b = used.numel()
    if b and (int(used.min()) < 0 or int(used.max()) >= P.shape[0]):
        raise IndexError("a vertex outside the mesh")
    cam = cam.to(torch.float32).contiguous()
    brows, lrows = torch.empty(b, 4, dtype=torch.int64), torch.empty(b, 4, dtype=torch.int64)
    bw, lw = torch.empty(b, 4, dtype=torch.float32), torch.empty(b, 4, dtype=torch.float32)
    if b:
        lib.tp_vertex_lookups(b, used.data_ptr(), P.data_ptr(), R.data_ptr(), region.data_ptr(), cam.data_ptr(),
                              outgoing.n_theta, outgoing.n_phi, grid.n_theta, grid.n_phi,
                              None if cells is None else cells[0].data_ptr(), None if cells is None else cells[1].data_ptr(),
                              brows.data_ptr(),
                              bw.data_ptr(), lrows.data_ptr(), lw.data_ptr(), _threads(b))
    return brows, bw, lrows, lw


# Pixels per thread below which one thread resolves (as `methods.core.gouraud`'s loop).
MIN_PIXELS_PER_THREAD = 1 << 13


def resolve(values: Tensor, F: Tensor, faces: Tensor, hit: Tensor, face: Tensor, bary: Tensor, height: int,
            width: int, spp_side: int) -> Tensor | None:
    """The (height, width, 3) Gouraud image of per-vertex colours ``values`` (N, 3) float32 on a G-buffer
    (hit (P,) bool, face (P,) int64, bary (P, 2) float32 (u, v), P = height·width·spp_side², pixel-major)
    — `methods.core.gouraud.resolve` (``values``, F.T, ...) bit for bit, its loop with the seen faces'
    colours gathered into a face table first (``tp_resolve``) — or None without the library or for
    other dtypes / layouts (`gouraud.resolve` serves). ``faces``: `hit_faces`' distinct faces of these
    very ``hit`` / ``face`` with ``F`` (N ≥ every vertex of them), which checked the ranges the loop
    reads unchecked; no other caller may pass them."""
    lib = _lib()
    S2 = spp_side * spp_side
    n = height * width
    if lib is None or values.dtype != torch.float32 or values.ndim != 2 or values.shape[1] != 3 \
            or F.dtype != torch.int64 or F.ndim != 2 or F.shape[1] != 3 or faces.dtype != torch.int64 \
            or hit.dtype != torch.bool or face.dtype != torch.int64 or bary.dtype != torch.float32 \
            or bary.shape != (face.shape[0], 2) or hit.shape != face.shape or face.shape[0] != n * S2 \
            or not (values.is_contiguous() and F.is_contiguous() and faces.is_contiguous()
                    and hit.is_contiguous() and face.is_contiguous()) \
            or any(t.device.type != "cpu" for t in (values, F, faces, hit, face, bary)):
        return None
    bu, bv = (x.contiguous() for x in bary.unbind(-1))     # views of the G-buffer's column-major bary
    T = torch.empty(F.shape[0], 9, dtype=torch.float32)
    out = torch.empty(height, width, 3, dtype=torch.float32)
    nt = max(1, min(torch.get_num_threads(), n // MIN_PIXELS_PER_THREAD))
    lib.tp_resolve(n, S2, hit.data_ptr(), face.data_ptr(), bu.data_ptr(), bv.data_ptr(), F.data_ptr(),
                   values.data_ptr(), faces.data_ptr(), faces.numel(), T.data_ptr(), out.data_ptr(), nt)
    return out


def hit_faces(hit: Tensor, face: Tensor, F: Tensor, nv: int) -> tuple[Tensor, Tensor, int] | None:
    """(the distinct faces the samples with ``hit`` (P,) bool see (``face`` (P,) int64, rows of F),
    the distinct vertices of those faces (F (nf, 3) int64, nv vertices), both sorted int64, the
    number of hit samples) in one pass over the samples — what a per-vertex frame shades and records
    (`TripleProduct.render`: `_hit_faces`, `_distinct` of their vertices and ``hit.sum()``, its
    torch path and test oracle) — or None without the library or for other dtypes / layouts."""
    lib = _lib()
    if lib is None or hit.dtype != torch.bool or face.dtype != torch.int64 or F.dtype != torch.int64 \
            or hit.device.type != "cpu" or face.device.type != "cpu" or F.device.type != "cpu" \
            or hit.shape != face.shape or hit.ndim != 1 or F.ndim != 2 or F.shape[1] != 3 \
            or not (hit.is_contiguous() and face.is_contiguous() and F.is_contiguous()):
        return None
    nf = F.shape[0]
    # session 39: the marks over the threads (`HIT_THREADS`; the same marks and lists at any thread count)
    nt = max(1, min(torch.get_num_threads(), hit.numel() // MIN_HIT_SAMPLES_PER_THREAD)) if HIT_THREADS else 1
    if HIT_LISTS:   # the two lists made by the C loop too (`tp_hit_lists`): no torch.nonzero passes (~0.2 ms)
        seen = torch.zeros(nf + nv, dtype=torch.uint8)
        lists = torch.empty(nf + nv, dtype=torch.int64)
        counts = torch.zeros(4, dtype=torch.int64)
        lib.tp_hit_lists(hit.numel(), hit.data_ptr(), face.data_ptr(), nf, F.data_ptr(), nv, seen.data_ptr(),
                         lists.data_ptr(), counts.data_ptr(), nt)
        h, bad, kf, kv = counts.tolist()
        if bad != 0:
            raise IndexError("a hit sample's face or a face's vertex outside its table")
        return lists[:kf], lists[nf:nf + kv], h
    fseen = torch.zeros(nf, dtype=torch.uint8)
    vseen = torch.zeros(nv, dtype=torch.uint8)
    counts = torch.zeros(2, dtype=torch.int64)
    lib.tp_hit_faces(hit.numel(), hit.data_ptr(), face.data_ptr(), nf, F.data_ptr(), nv, fseen.data_ptr(),
                     vseen.data_ptr(), counts.data_ptr(), nt)
    if int(counts[1]) != 0:
        raise IndexError("a hit sample's face or a face's vertex outside its table")
    return (torch.nonzero(fseen, as_tuple=False).squeeze(-1), torch.nonzero(vseen, as_tuple=False).squeeze(-1),
            int(counts[0]))


# `hit_faces` takes the face and vertex lists from the C loop (``tp_hit_lists``); False: torch.nonzero of
# its marks (the test oracle).
HIT_LISTS = True
