"""The per-sample view stage of shading="vertex" (``fast.shade_block``: the face's three pair rows
with the Gouraud weights, the four env rows of the mirror direction's cell, max(0, B) + u + Σ_k s_k
E^(k)(R) and the box filter) as a small C loop compiled on first use and called through ctypes —
the same arithmetic, lane by lane in the same order, as the compiled ``fast.shade_block``, which
stays the fallback and the test oracle.

Why: Inductor's loop over the pixels is vectorised along the 16 lanes of a row, one sample at a time,
and spends ~190 instructions per sample (session 24's count) on what is 7 row loads, 7 lane-wise
products and sums and ~15 scalar weights: index arithmetic in int64 with every intermediate spilled,
a lane-mask ``where`` per row, and the four channel sums of each pixel as masked reductions. Here the
rows are 8-lane GCC vector operations (``-march=native``: AVX2 on this machine), the per-sample
weights scalars, the lanes chosen per row block once (B, u and the lobe lanes are fixed columns), and
the env rows of the sample ``PREFETCH`` samples ahead are prefetched (their cells are known: `r` is
an input) — the env rows are cache-cold (8.4 MB on the chess bench), the pair rows mostly L2-resident.

Each pixel is one thread's, whatever ``torch.get_num_threads()`` (contiguous pixel ranges per thread),
so the bits do not depend on the thread count. The threads are OpenMP's (``-fopenmp``: the library
binds to the libgomp torch loaded, so it runs on the same team as Inductor's kernels, whose workers
spin between them). Session 26: a Python thread pool instead (as ``methods.inout.csr``) read 0.88–0.90x
against main on the chess bench V frame at 2 threads (same process, wall; the pool thread competing
with Inductor's spinning worker for the second core), the OpenMP team 1.57x (V) / 1.63x (VB), creature
1.13x / 1.82x — 2-thread same-process A/Bs are not evidence on this VM, a sanity check only. Compiled with
``-ffp-contract=off`` (as Inductor's kernels): every product and sum is rounded as in the compiled
kernel; the lane sums of the box filter follow AVX2's ``vec_reduce_all`` tree.

The mirror direction's cell (``fast._mirror_cells``) runs in the same pass where it can be exact
(`shade_mirror`, `cells_available`): AVX2 intrinsics one for one with Inductor's generated kernel for
the compiled function (the same products, sums, divisions, NaN-propagating maximum / minimum and
truncating conversions, in its order) and the same Sleef acos / atan2 on 8 floats, called through
their addresses in libtorch_cpu (what ATen's ``Vectorized<float>`` calls in Inductor's AVX2 kernels) —
so the cells and fractions are the compiled kernel's bits (tested), which the reference path's
look-ups read too (``fast.mirror_uv``). Used only where Inductor vectorises for AVX2 or AVX-512 (below);
elsewhere the compiled ``fast.mirror_cells_block`` runs and `shade_pixels` shades its cells. Measured on the chess
bench: the cells alone 2.5 ms native vs 2.6 ms compiled (the Sleef calls are ~1.3 ms of it); the gain
is the compiled call, its (r, fx, fy) arrays and their second pass (V 1.02–1.05x). Session 28 (ptt28):
the cells of 64 vectors are computed in three sweeps — the directions, then their acos calls back to
back, then their atan2 calls and the cells — instead of one vector at a time (each Sleef call is opaque:
the live vectors spilled around it and the next vector's divisions and square root waited for it); the
same operations per lane. Probes on the chess bench sample stage (1 thread, settled): without the Sleef
calls it ran 1.45x faster, without the cells at all 2.1x, with every env row cached 1.09x.

Session 31 (ptt31): on a host where Inductor vectorises for AVX-512 (``pick_vec_isa()`` "avx512 ...",
e.g. this EPYC) its kernel of ``fast._mirror_cells`` is the same operations on 16 lanes (ATen's vec512:
rsqrt as 1 / sqrt, maximum / minimum OR-ing an all-ones NaN mask, floor, truncating conversions) and
calls ``Sleef_acosf16_u10`` / ``Sleef_atan2f16_u10`` (the symbols its .so imports; libtorch_cpu's
AVX-512F builds). ``cells16`` is that kernel's twin — a last vector of 8 samples as the kernel's masked
tail: lanes 8..15 repeat the last sample and are not stored — and `_sleef` hands it the f16 functions
(`_SLEEF`: Inductor's ISA picks the variant; the AVX2 one stays for AVX2 hosts). `vertex_rows` calls the
same f16 functions on 16 pairs and sums B's lanes as the AVX-512 reduction (a 16-lane accumulator: the
8-lane blocks alternate between its halves, which its ``vec_reduce_all`` adds first; for 3K = 24 and 48
that equals the AVX2 order because the channel masks leave one nonzero term per lane, for 3K = 72 it does
not — tested with K = 24). Before, these loops were off here (``cells_available()`` False) and the
compiled cells ran. Same process, 1 thread, CPU time, 15 frames (``python -m benchmarks.ptt_ab --base
e0546d6 --precompute-code e0546d6 --kinds V VB``): chess bench V 1.19x, VB 1.18x; creature V 1.13x,
VB 1.19x; images bit-identical. Tried and dropped: a 16-lane body of `shade_pixels` for width 16 (the
same bits; sample stage 0.98–1.03x, noise), the next run's cells computed a run ahead with its env rows
prefetched into L2 (1.007x).

Session 29 (ptt29): rows without u lanes whose B lanes lie in the first 8 (the perf suite's: B | s,
width 16) take a body whose per-block lane selects are fixed (block 0: max(0, a) on the B lanes, a e
elsewhere; later blocks a e; the values the general selects pick): the sample stage 1.04–1.05x, the
same bits (``python -m benchmarks.ptt_sample_ab --base OTHER --precompute-code OTHER [--scene
creature]``, chess 1.051 / 1.036, creature 1.054).

Session 37 (pt37): ``lean16``, `shade_mirror`'s pixel loop for those rows (width 16, no u lanes,
S2 = 4, the barycentrics as the G-buffer's columns) on AVX-512 — the same operations per lane in the
same order (the same bits; `LEAN` off gives the general body): a row is one zmm register, a run's
per-sample weights (b0, b1, b2, w0..w3) are computed in one vectorised pass into one stack array and
read as broadcasts, a pixel's four samples are unrolled, and the box filter's channel sums of 8 pixels
are reduced together by lane permutes (the AVX2 ``vec_reduce_all`` tree of each: the same additions);
~45 instructions a sample instead of ~100. Same process, 1 thread, process CPU, against 6f20090: the
sample stage alone (``python -m benchmarks.ptt_sample_ab --base B --scene S --kind V --rounds 10``)
chess 1.136x, creature 1.120x; whole frames (``python -m benchmarks.ptt_ab --base B --precompute-code B
--scene S --kinds V VB --frames 17 --threads 1``) chess V 1.10x, VB 1.11x, creature V 1.11x, VB 1.08x;
bit-identical. What is left of a chess bench V stage at 1 thread (~4.4 ms, loaded host): the
cells ~1.5 ms (the Sleef acos / atan2 calls), the pixel loop with every env row cached ~1.9 ms, the env
rows' misses the rest. Tried and dropped: the next run's cells computed inside this run's pixel loop (its
Sleef calls a few per pixel or per 8 pixels beside the loop's loads: 0.88-0.97x, the calls' spills and
a larger stack footprint); pixels dealt to the threads in chunks (`RR_PIXELS`: off, see there).

``vertex_rows`` (session 29, ptt29): ``fast.vertex_view``'s rows of a frame's referenced pairs (with
lobes, without the SH column) in one pass, the compiled ``pair_cells_of`` + ``pair_rows`` bit for bit
(the same Sleef calls, 8 pairs at a time; `cells_available`), the compiled passes its fallback and
test oracle.

Session 38 (pt38): ``referenced_sel`` / ``vertex_rows_at`` (``method.FULL_TABLE``): the referenced pairs'
rows at the pairs' own positions of a full-size table, read through the static face corners — no compact
positions or remapped corners per frame; the same rows, the same bits. Tried and dropped: the lat-long
angles of the cells from inline minimax polynomials instead of the Sleef calls (``pacos16`` / ``patan2_16``:
within 1-1.4 eps of the map's size of the Sleef cells, 9 of 2^20 cells flipped at a boundary; cells 1.8 ->
1.34 ms alone, V frames 1.10x, VB 1.06x at 1 thread) — not the compiled kernel's bits, and a last-bit
change of (u, v) moves a bilinear look-up by the HDR texel contrast: the fast path then missed the
reference on sphere_plane's test V frame by 2.0e-4 (3.6e-5 relative, `test_fast_path_equals_reference`'s
1e-5); and ``vertex_rows`` software-pipelined (block b + 1's offsets and prefetches before block b's rows:
cold 1.00 -> 1.05 ms, warm 0.311 -> 0.312 ms: its misses are not what the prefetch distance limits).

Session 39 (pt39): the cells' lat-long angles are float32 polynomials (``fast.acos_poly`` /
``fast.atan2_poly``, Cephes' asinf / atanf; ``pacos8`` / ``patan2_8`` / ``pacos16`` / ``patan2_16``) — pt38's
way round its dropped attempt: not the native loop alone but THE formula, ``fast._mirror_uv``, which the
reference's look-ups read too, so the fast path keeps the compiled kernel's bits (tested, on 8 and 16
lanes) and the compiled function now equals its eager form bit for bit (tested). The angles are within
1.35 ulps (acos) and 2.9 ulps / 2.6e-7 rad (atan2) of the float64 angle (Sleef's: 0.79 / 1.48 ulps,
2.5e-7 rad; tested with bounds 1.5 and 3 ulps). Against a3a1740, same process, 1 thread, process CPU:
the cells alone (``python -m benchmarks.ptt_cells_micro --base B``, 2^18 samples) 0.81 -> 0.55 ms
(1.47x; A/A 1.01x); the chess sample stage (``benchmarks.ptt_sample_ab``, 10 rounds) 1.10x; frames
(``benchmarks.ptt_ab --base B --precompute-code B --kinds V VB --frames 17 --threads 1``) chess V 1.08x,
VB 1.05x, creature V 1.10x, VB 1.07x (A/A chess 1.00x / 0.99x). Images: not the base's bits — the
angles moved by their round-off, max |base - new| 2.4e-7 / 3.6e-7 (chess V / VB, peak 1.3 / 1.6),
9.5e-7 (creature, peak 3.8). ``vertex_rows`` keeps the Sleef calls (its pair cells' reference is the
compiled ``fast._pair_cells``; ~4 300 pairs a bench frame: a few µs of calls at the cells' rate).

The library is built and loaded by `methods.core.native.load` (per-user private cache directory, keyed
by the source text, flags and compiler; atomic rename); without a compiler, on a failed build or with
``PRTBENCH_COMPILE=0``, `available` is False and the caller uses ``fast.shade_block``. Building it
takes ~2 s of ``cc`` (CPU time) once per machine and source (what CI pays, once).
"""
from __future__ import annotations

import ctypes
import functools
import os

import torch
from torch import Tensor

from methods.core import native

__all__ = ["available", "cells_available", "lean_available", "mirror_cells", "shade_mirror", "shade_pixels",
           "vertex_rows"]

# Samples ahead whose env rows are prefetched.
PREFETCH = 16

_SOURCE = r"""
#include <stdint.h>
typedef float v8 __attribute__((vector_size(32)));
typedef int32_t v8i __attribute__((vector_size(32)));

static inline v8 ld(const float* p) { v8 v; __builtin_memcpy(&v, p, 32); return v; }
/* m ? x : y lane by lane (m: all ones or zero per lane) */
static inline v8 sel(v8i m, v8 x, v8 y) { return (v8)(((v8i)x & m) | ((v8i)y & ~m)); }

/* fast._shade_block on the pixels [p0, p1): S2 samples per pixel (sample j of pixel p is row p*S2 + j).
   face (n,) int64 (an index outside [0, M) reads face M - 1, the zero face of fast.miss_face_pairs:
   -1 wraps there as in torch); the barycentrics b1 = b1p[i * bs], b2 = b2p[i * bs]; r (n,) int32 the
   first env row of the cell, fx, fy (n,) its fractions; face_pairs (M, 3) int64; table (., width),
   env (., width) rows (width a multiple of 8, at most 64); lanes (5, width) (fast._lane_masks);
   out (P, 3). The env rows of sample i + prefetch are prefetched. Specialised (inlined) for the
   widths 16 and 32 and S2 = 4, so the lane loops unroll. */
static inline __attribute__((always_inline)) void body(
        const int64_t* face, const float* b1p, const float* b2p, int64_t bs, const int32_t* r, const float* fx,
        const float* fy, int64_t p0, int64_t p1, int64_t S2, const int64_t* face_pairs, int64_t M,
        const float* table, const float* env, const float* lanes, const int64_t width, int64_t W,
        int64_t prefetch, int64_t n, const int plain, float* out) {
    const int64_t nb = width / 8;
    const float inv = 1.0f / (float)S2;
    const v8 zero = {0, 0, 0, 0, 0, 0, 0, 0};
    v8i isb[8], isu[8];
    v8 mc[3][8];
    for (int64_t b = 0; b < nb; ++b) {
        isb[b] = ld(lanes + 8 * b) > zero;
        isu[b] = ld(lanes + width + 8 * b) > zero;
        for (int c = 0; c < 3; ++c)
            mc[c][b] = ld(lanes + (2 + c) * width + 8 * b);
    }
    const int64_t rowb = (W + 1) * width;
    for (int64_t p = p0; p < p1; ++p) {
        v8 t[8];
        for (int64_t j = 0; j < S2; ++j) {
            const int64_t i = p * S2 + j;
            if (i + prefetch < n) {
                const float* q = env + (int64_t)r[i + prefetch] * width;
                __builtin_prefetch(q);
                __builtin_prefetch(q + width);
                __builtin_prefetch(q + rowb);
                __builtin_prefetch(q + rowb + width);
            }
            int64_t f = face[i];
            if ((uint64_t)f >= (uint64_t)M)
                f = M - 1;
            const float* a0 = table + face_pairs[3 * f] * width;
            const float* a1 = table + face_pairs[3 * f + 1] * width;
            const float* a2 = table + face_pairs[3 * f + 2] * width;
            const float b1 = b1p[i * bs], b2 = b2p[i * bs];
            const float b0 = (1.0f - b1) - b2;
            const float x = fx[i], y = fy[i];
            const float gx = 1.0f - x, gy = 1.0f - y;
            const float w0 = gx * gy, w1 = x * gy, w2 = gx * y, w3 = x * y;
            const float* e0 = env + (int64_t)r[i] * width;
            const float* e2 = e0 + rowb;
            for (int64_t b = 0; b < nb; ++b) {
                const int64_t o = 8 * b;
                const v8 a = (ld(a0 + o) * b0 + ld(a1 + o) * b1) + ld(a2 + o) * b2;
                const v8 e = ((ld(e0 + o) * w0 + ld(e0 + width + o) * w1) + ld(e2 + o) * w2) + ld(e2 + width + o) * w3;
                /* max(0, a) as Inductor's maximum (NaN propagates), a, a * e */
                v8 tj;
                if (!plain)
                    tj = sel(isb[b], sel((a > zero) | (a != a), a, zero), sel(isu[b], a, a * e));
                else if (b == 0)  /* plain: no u lanes, the B lanes in block 0 */
                    tj = sel(isb[0], sel((a > zero) | (a != a), a, zero), a * e);
                else
                    tj = a * e;
                t[b] = j ? t[b] + tj : tj;
            }
        }
        for (int c = 0; c < 3; ++c) {
            v8 acc = zero;
            for (int64_t b = 0; b < nb; ++b)
                acc = acc + t[b] * mc[c][b];
            /* vec_reduce_all (AVX2): halves, then lanes two apart, then neighbours */
            const float s0 = acc[0] + acc[4], s1 = acc[1] + acc[5], s2 = acc[2] + acc[6], s3 = acc[3] + acc[7];
            out[3 * p + c] = ((s0 + s2) + (s1 + s3)) * inv;
        }
    }
}

void shade_pixels(const int64_t* face, const float* b1p, const float* b2p, int64_t bs, const int32_t* r,
                  const float* fx, const float* fy, int64_t p0, int64_t p1, int64_t S2, const int64_t* face_pairs,
                  int64_t M, const float* table, const float* env, const float* lanes, int64_t width, int64_t W,
                  int64_t prefetch, int64_t n, float* out) {
    /* plain: no u lanes and the B lanes within the first 8 (the perf suite's rows: B | s, width 16), so
       a block's select of max(0, a) / a / a e is known per block (the same values: the selects it skips
       pick a e) */
    int plain = 1;
    for (int64_t l = 0; l < width; ++l)
        plain &= lanes[width + l] == 0.0f && (l < 8 || lanes[l] == 0.0f);
    if (width == 16 && S2 == 4 && plain)
        body(face, b1p, b2p, bs, r, fx, fy, p0, p1, 4, face_pairs, M, table, env, lanes, 16, W, prefetch, n, 1, out);
    else if (width == 16 && S2 == 4)
        body(face, b1p, b2p, bs, r, fx, fy, p0, p1, 4, face_pairs, M, table, env, lanes, 16, W, prefetch, n, 0, out);
    else if (width == 16)
        body(face, b1p, b2p, bs, r, fx, fy, p0, p1, S2, face_pairs, M, table, env, lanes, 16, W, prefetch, n, 0, out);
    else if (width == 32)
        body(face, b1p, b2p, bs, r, fx, fy, p0, p1, S2, face_pairs, M, table, env, lanes, 32, W, prefetch, n, 0, out);
    else
        body(face, b1p, b2p, bs, r, fx, fy, p0, p1, S2, face_pairs, M, table, env, lanes, width, W, prefetch, n, 0, out);
}

/* shade_pixels over all P pixels on nt threads of OpenMP's team (the one torch's and Inductor's
   kernels use: the library shares their libgomp), thread k the pixels [P k / nt, P (k + 1) / nt). */
void shade_pixels_par(const int64_t* face, const float* b1p, const float* b2p, int64_t bs, const int32_t* r,
                      const float* fx, const float* fy, int64_t P, int64_t nt, int64_t S2, const int64_t* face_pairs,
                      int64_t M, const float* table, const float* env, const float* lanes, int64_t width, int64_t W,
                      int64_t prefetch, int64_t n, float* out) {
#pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int64_t k = 0; k < nt; ++k)
        shade_pixels(face, b1p, b2p, bs, r, fx, fy, P * k / nt, P * (k + 1) / nt, S2, face_pairs, M, table, env,
                     lanes, width, W, prefetch, n, out);
}

/* fast.region_tables' W_r: out[r, t, l] = sum over p in order of W_rows[p, t, l] * Hl[p, r, l] (each
   product rounded, then the sum: the eager passes' operations), W_rows (P, T2, KC), Hl (P, R, KC),
   out (R, T2, KC). */
void region_rows(const float* Wrows, const float* Hl, int64_t P, int64_t R, int64_t T2, int64_t KC, float* out) {
    for (int64_t r = 0; r < R; ++r)
        for (int64_t t = 0; t < T2; ++t) {
            float* o = out + (r * T2 + t) * KC;
            const float* w = Wrows + t * KC;
            const float* h = Hl + r * KC;
            for (int64_t l = 0; l < KC; ++l)
                o[l] = w[l] * h[l];
            for (int64_t p = 1; p < P; ++p) {
                const float* wp = w + p * T2 * KC;
                const float* hp = h + p * R * KC;
                for (int64_t l = 0; l < KC; ++l)
                    o[l] = o[l] + wp[l] * hp[l];
            }
        }
}

/* fast.region_tables' W_r in one threaded call (session 40, pt40): `region_rows`' products and sums per
   lane, p in order, with the lanes Hl[p, r, (k, c)] = H[r, p, c] read straight from H (R, P, 3), the rows
   (r, t) split into nt contiguous ranges over OpenMP's team (each row one thread's: the bits do not depend
   on nt), written into out (R, T2, K·3). */
void region_rows_range(const float* Wrows, const float* H, int64_t P, int64_t R, int64_t T2, int64_t K, float* out,
                       int64_t i0, int64_t i1);
void region_tables(const float* Wrows, const float* H, int64_t P, int64_t R, int64_t T2, int64_t K, float* out,
                   int64_t nt) {
    const int64_t rows = R * T2;
#pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int64_t k = 0; k < nt; ++k)
        region_rows_range(Wrows, H, P, R, T2, K, out, rows * k / nt, rows * (k + 1) / nt);
}
/* region_tables' rows i0 <= i < i1 (each row's products and sums as there, whoever computes it: the same bits;
   also ``methods.ptt.native_fit``'s frame_call, which deals them to its team in chunks) */
void region_rows_range(const float* Wrows, const float* H, int64_t P, int64_t R, int64_t T2, int64_t K, float* out,
                       int64_t i0, int64_t i1) {
    const int64_t KC = 3 * K;
    (void)R;
    {
        float hl[P * KC];
        int64_t rcur = -1;
        for (int64_t i = i0; i < i1; ++i) {
            const int64_t r = i / T2, t = i - r * T2;
            if (r != rcur) {
                for (int64_t p = 0; p < P; ++p)
                    for (int64_t l = 0; l < KC; ++l)
                        hl[p * KC + l] = H[(r * P + p) * 3 + l % 3];
                rcur = r;
            }
            float* o = out + i * KC;
            const float* w = Wrows + t * KC;
            for (int64_t l = 0; l < KC; ++l)
                o[l] = w[l] * hl[l];
            for (int64_t p = 1; p < P; ++p) {
                const float* wp = w + p * T2 * KC;
                const float* hp = hl + p * KC;
                for (int64_t l = 0; l < KC; ++l)
                    o[l] = o[l] + wp[l] * hp[l];
            }
        }
    }
}

/* each of nt threads marks the faces of its nt-th of the n samples in its own row of fmark (nt rows of M + 1
   bytes; entries outside [0, M) — misses — mark the spare entry M): referenced_pairs' and referenced_sel's
   marking, merged by their callers */
static void mark_faces(const int64_t* face, int64_t n, int64_t M, int64_t nt, uint8_t* fmark) {
#pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int64_t k = 0; k < nt; ++k) {
        uint8_t* fm = fmark + k * (M + 1);
        for (int64_t f = 0; f <= M; ++f)
            fm[f] = 0;
        for (int64_t i = n * k / nt; i < n * (k + 1) / nt; ++i) {  /* no branch: a miss marks the spare entry M */
            const uint64_t f = (uint64_t)face[i];
            fm[f < (uint64_t)M ? f : (uint64_t)M] = 1;
        }
    }
}

/* fast.referenced_pairs: the (vertex, region) pairs of the faces the samples lie on. face (n,) int64
   (entries outside [0, M) — misses — skipped), face_pairs (M, 3); fmark (M + 1) and pos (np + 1)
   scratch; out sel (np) the pairs in ascending order (returns their count
   m) and fpc (M + 1, 3) the position in sel of each face corner's pair (m for a pair not in sel; row
   M, the miss face, m: the zero row of the compact table). The samples are split over nt threads of
   OpenMP's team, each marking its own nt-th of fmark (nt (M + 1) bytes), then merged. */
int64_t referenced_pairs(const int64_t* face, int64_t n, const int64_t* face_pairs, int64_t M, int64_t np,
                         int64_t nt, uint8_t* fmark, int64_t* pos, int64_t* sel, int64_t* fpc) {
    mark_faces(face, n, M, nt, fmark);
    for (int64_t k = 1; k < nt; ++k)
        for (int64_t f = 0; f < M; ++f)
            fmark[f] |= fmark[k * (M + 1) + f];
    for (int64_t p = 0; p <= np; ++p)
        pos[p] = 0;
    for (int64_t f = 0; f < M; ++f)
        if (fmark[f]) {
            pos[face_pairs[3 * f]] = 1;
            pos[face_pairs[3 * f + 1]] = 1;
            pos[face_pairs[3 * f + 2]] = 1;
        }
    int64_t m = 0;
    for (int64_t p = 0; p < np; ++p)
        if (pos[p]) {
            sel[m] = p;
            pos[p] = m++;
        } else
            pos[p] = -1;
    for (int64_t p = 0; p < np; ++p)
        if (pos[p] < 0)
            pos[p] = m;
    pos[np] = m;
    for (int64_t k = 0; k < 3 * M; ++k)
        fpc[k] = pos[face_pairs[k]];
    fpc[3 * M] = fpc[3 * M + 1] = fpc[3 * M + 2] = m;
    return m;
}

/* the per-thread face marks (nt rows of M + 1 bytes, the spare entry M for misses) merged into row 0, the pairs
   of the marked faces' corners marked in pmark (np bytes) and listed ascending in sel: their count
   (referenced_sel and view_frame's marking) */
static int64_t merge_marks(uint8_t* fmark, int64_t M, int64_t nt, const int64_t* face_pairs, int64_t np,
                           uint8_t* pmark, int64_t* sel) {
    for (int64_t k = 1; k < nt; ++k)
        for (int64_t f = 0; f < M; ++f)
            fmark[f] |= fmark[k * (M + 1) + f];
    for (int64_t p = 0; p < np; ++p)
        pmark[p] = 0;
    for (int64_t f = 0; f < M; ++f)
        if (fmark[f]) {
            pmark[face_pairs[3 * f]] = 1;
            pmark[face_pairs[3 * f + 1]] = 1;
            pmark[face_pairs[3 * f + 2]] = 1;
        }
    int64_t m = 0;
    for (int64_t p = 0; p < np; ++p)
        if (pmark[p])
            sel[m++] = p;
    return m;
}

/* referenced_pairs' sel only (session 38, pt38: FULL_TABLE, whose sample stage reads the rows through the
   static face corners, fast.miss_face_pairs): the same marking of the faces, pmark (np) bytes scratch,
   no positions and no remapped corners. Returns m. */
int64_t referenced_sel(const int64_t* face, int64_t n, const int64_t* face_pairs, int64_t M, int64_t np,
                       int64_t nt, uint8_t* fmark, uint8_t* pmark, int64_t* sel) {
    mark_faces(face, n, M, nt, fmark);
    return merge_marks(fmark, M, nt, face_pairs, np, pmark, sel);
}

/* fast._mirror_cells on AVX2, 8 samples per step, with Inductor's vector operations one for one (its
   generated kernel for the compiled function: the same products, sums, divisions, the maximum /
   minimum that propagate NaN, truncating conversions) and, since session 39, the same polynomial acos /
   atan2 (fast.acos_poly / atan2_poly: pacos8 / patan2_8 below; before, the Sleef functions ATen's
   Vectorized<float> calls, passed in — vertex_rows still calls those), so the cells and fractions are
   the compiled kernel's bits. native_cells_ok() is 0 when not built for AVX2. */
#if defined(__AVX2__)
#include <immintrin.h>
typedef __m256 (*vf1)(__m256);
typedef __m256 (*vf2)(__m256, __m256);
/* bit 0: the AVX2 cells (8 lanes, Sleef's f8 functions); bit 1: also the AVX-512 ones (16 lanes, f16) */
#if defined(__AVX512F__)
int native_cells_ok(void) { return 3; }
#else
int native_cells_ok(void) { return 1; }
#endif
static inline __m256 vmax(__m256 a, __m256 b) {
    return _mm256_or_ps(_mm256_max_ps(a, b), _mm256_cmp_ps(a, b, _CMP_UNORD_Q));
}
static inline __m256 vmin(__m256 a, __m256 b) {
    return _mm256_or_ps(_mm256_min_ps(a, b), _mm256_cmp_ps(a, b, _CMP_UNORD_Q));
}
static inline __m256 lds(const float* p, int64_t s) {
    if (s == 1)
        return _mm256_loadu_ps(p);
    float t[8];
    for (int k = 0; k < 8; ++k)
        t[k] = p[k * s];
    return _mm256_loadu_ps(t);
}
/* x, y, z of 8 (x, y, z) triples stored one after another (24 floats at p): three loads, two blends
   and a permute per component — the values lds(p + c, 3) gathers one float at a time (its eight
   stores and one wide load stall on store-to-load forwarding; _mm256_i32gather_ps was slower still,
   0.88x on the chess bench's sample stage). */
static inline void aos3(const float* p, __m256* x, __m256* y, __m256* z) {
    const __m256 m0 = _mm256_loadu_ps(p), m1 = _mm256_loadu_ps(p + 8), m2 = _mm256_loadu_ps(p + 16);
    /* float 3k + c of the 24 is lane (3k + c) % 8 of m[(3k + c) / 8]: x from m0 lanes 0, 3, 6, m1 lanes 1,
       4, 7 and m2 lanes 2, 5 (blend masks 0x92, 0x24, 0x49: lanes {1, 4, 7}, {2, 5}, {0, 3, 6}) */
    const __m256 tx = _mm256_blend_ps(_mm256_blend_ps(m0, m1, 0x92), m2, 0x24);  /* x0 x3 x6 x1 x4 x7 x2 x5 */
    const __m256 ty = _mm256_blend_ps(_mm256_blend_ps(m0, m1, 0x24), m2, 0x49);  /* y5 y0 y3 y6 y1 y4 y7 y2 */
    const __m256 tz = _mm256_blend_ps(_mm256_blend_ps(m0, m1, 0x49), m2, 0x92);  /* z2 z5 z0 z3 z6 z1 z4 z7 */
    *x = _mm256_permutevar8x32_ps(tx, _mm256_setr_epi32(0, 3, 6, 1, 4, 7, 2, 5));
    *y = _mm256_permutevar8x32_ps(ty, _mm256_setr_epi32(1, 4, 7, 2, 5, 0, 3, 6));
    *z = _mm256_permutevar8x32_ps(tz, _mm256_setr_epi32(2, 5, 0, 3, 6, 1, 4, 7));
}
/* fast.acos_poly of y (clamped to [-1, 1]) and fast.atan2_poly(y, x) on 8 lanes: the compiled kernel's
   float32 operations one for one, in its order (ATen's vec256: abs as and-not of the sign, neg as xor,
   maximum / minimum OR-ing the NaN mask, ordered compares, blendv on the compare's mask; Inductor's
   generated kernel of fast._mirror_cells read for this) — the same bits on any lane width. */
#define PC8(c) _mm256_set1_ps((float)(c))
static inline __m256 pacos8(__m256 y) {
    const __m256 sign = _mm256_set1_ps(-0.f), half = _mm256_set1_ps(0.5f);
    const __m256 a = _mm256_andnot_ps(sign, y);
    const __m256 big = _mm256_cmp_ps(a, half, _CMP_GT_OQ);
    const __m256 z = _mm256_blendv_ps(_mm256_mul_ps(a, a), _mm256_sub_ps(half, _mm256_mul_ps(a, half)), big);
    __m256 q = _mm256_add_ps(_mm256_mul_ps(z, PC8(0.042163199048)), PC8(0.024181311049));
    q = _mm256_add_ps(_mm256_mul_ps(q, z), PC8(0.045470025998));
    q = _mm256_add_ps(_mm256_mul_ps(q, z), PC8(0.074953002686));
    q = _mm256_add_ps(_mm256_mul_ps(q, z), PC8(0.16666752422));
    q = _mm256_mul_ps(q, z);
    const __m256 s = _mm256_blendv_ps(a, _mm256_sqrt_ps(z), big);
    const __m256 p = _mm256_add_ps(_mm256_mul_ps(q, s), s);
    const __m256 r = _mm256_blendv_ps(_mm256_sub_ps(PC8(1.5707963267948966), p), _mm256_mul_ps(p, PC8(2.0)), big);
    return _mm256_blendv_ps(r, _mm256_sub_ps(PC8(3.141592653589793), r), _mm256_cmp_ps(y, _mm256_setzero_ps(), _CMP_LT_OQ));
}
static inline __m256 patan2_8(__m256 y, __m256 x) {
    const __m256 sign = _mm256_set1_ps(-0.f), zero = _mm256_setzero_ps();
    const __m256 ax = _mm256_andnot_ps(sign, x), ay = _mm256_andnot_ps(sign, y);
    const __m256 mn = vmin(ax, ay), mx = vmax(ax, ay);
    const __m256 c = _mm256_cmp_ps(mn, _mm256_mul_ps(mx, PC8(0.41421356237309503)), _CMP_GT_OQ);
    const __m256 num = _mm256_blendv_ps(mn, _mm256_sub_ps(mn, mx), c);
    __m256 den = _mm256_blendv_ps(mx, _mm256_add_ps(mn, mx), c);
    den = _mm256_blendv_ps(PC8(1.0), den, _mm256_cmp_ps(den, zero, _CMP_GT_OQ));
    const __m256 t = _mm256_div_ps(num, den), z = _mm256_mul_ps(t, t);
    __m256 q = _mm256_sub_ps(_mm256_mul_ps(z, PC8(0.0805374449538)), PC8(0.138776856032));
    q = _mm256_add_ps(_mm256_mul_ps(q, z), PC8(0.199777106478));
    q = _mm256_sub_ps(_mm256_mul_ps(q, z), PC8(0.333329491539));
    q = _mm256_mul_ps(_mm256_mul_ps(q, z), t);
    const __m256 p = _mm256_add_ps(q, t);
    __m256 r = _mm256_blendv_ps(p, _mm256_add_ps(p, PC8(0.7853981633974483)), c);
    r = _mm256_blendv_ps(r, _mm256_sub_ps(PC8(1.5707963267948966), r), _mm256_cmp_ps(ay, ax, _CMP_GT_OQ));
    r = _mm256_blendv_ps(r, _mm256_sub_ps(PC8(3.141592653589793), r), _mm256_cmp_ps(x, zero, _CMP_LT_OQ));
    return _mm256_blendv_ps(r, _mm256_xor_ps(sign, r), _mm256_cmp_ps(y, zero, _CMP_LT_OQ));
}
/* samples [i0, i0 + m) (m a multiple of 8): normal component c of sample i at nrm[i * ns + c * nc],
   wo's at wo[i * ws + c * wc]; m (3, 3) to_world row-major; out r, fx, fy from index 0. */
static void cells8(const float* nrm, int64_t ns, int64_t nc, const float* wo, int64_t ws, int64_t wc,
                   const float* mm, int64_t H, int64_t W, vf1 vacos, vf2 vatan2, int64_t i0, int64_t m,
                   int32_t* r, float* fx, float* fy) {
    const __m256 eps = _mm256_set1_ps(1e-24f), two = _mm256_set1_ps(2.0f), one = _mm256_set1_ps(1.0f);
    const __m256 mone = _mm256_set1_ps(-1.0f), negz = _mm256_set1_ps(-0.f);
    const __m256 cpi = _mm256_set1_ps((float)0.3183098861837907), c2pi = _mm256_set1_ps((float)0.15915494309189535);
    const __m256 coff = _mm256_set1_ps((float)(0.5 / (double)W));
    const __m256 hm1 = _mm256_set1_ps((float)(H - 1)), wf = _mm256_set1_ps((float)W);
    const __m256i zi = _mm256_set1_epi32(0), hm2 = _mm256_set1_epi32((int32_t)(H - 2));
    const __m256i wm1 = _mm256_set1_epi32((int32_t)(W - 1)), wp1 = _mm256_set1_epi32((int32_t)(W + 1));
    __m256 M[9];
    for (int k = 0; k < 9; ++k)
        M[k] = _mm256_set1_ps(mm[k]);
    /* per block of up to 64 vectors (512 samples): the mirror directions in the map's frame, then the
       block's acos calls back to back, its atan2 calls, and the cells — the same operations per lane as
       one pass per vector (the same bits). Session 28 (ptt28): the calls' spills and the serial
       dependence of one vector's arithmetic on the previous call were the cost; the chess / creature
       bench sample stage (1 thread, process CPU, 0.2 s settle, alternating) 1.086x / 1.078x. Session 39:
       with the inline polynomials one pass per vector (cells16 with blocks of 1 vector) measured the
       same (chess sample stage 1.005x, noise), so the sweeps stay. */
    __m256 A[64], X[64], Z[64];
    for (int64_t o0 = 0; o0 < m; o0 += 512) {
        const int64_t nv = (m - o0 < 512 ? m - o0 : 512) / 8;
        for (int64_t k = 0; k < nv; ++k) {
            const int64_t i = i0 + o0 + 8 * k;
            __m256 nx, ny, nz;
            if (ns == 3 && nc == 1)  /* the G-buffer's normals: (n, 3) row-major */
                aos3(nrm + 3 * i, &nx, &ny, &nz);
            else {
                nx = lds(nrm + i * ns, ns);
                ny = lds(nrm + i * ns + nc, ns);
                nz = lds(nrm + i * ns + 2 * nc, ns);
            }
            const __m256 wx = lds(wo + i * ws, ws), wy = lds(wo + i * ws + wc, ws), wz = lds(wo + i * ws + 2 * wc, ws);
            const __m256 dot = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(nx, wx), _mm256_mul_ps(ny, wy)), _mm256_mul_ps(nz, wz));
            const __m256 nn = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(nx, nx), _mm256_mul_ps(ny, ny)), _mm256_mul_ps(nz, nz));
            const __m256 s = _mm256_mul_ps(_mm256_div_ps(dot, vmax(nn, eps)), two);
            const __m256 rx = _mm256_sub_ps(_mm256_mul_ps(s, nx), wx);
            const __m256 ry = _mm256_sub_ps(_mm256_mul_ps(s, ny), wy);
            const __m256 rz = _mm256_sub_ps(_mm256_mul_ps(s, nz), wz);
            const __m256 l2 = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(rx, rx), _mm256_mul_ps(ry, ry)), _mm256_mul_ps(rz, rz));
            const __m256 inv = _mm256_div_ps(one, _mm256_sqrt_ps(vmax(l2, eps)));
            const __m256 ax = _mm256_mul_ps(rx, inv), ay = _mm256_mul_ps(ry, inv), az = _mm256_mul_ps(rz, inv);
            const __m256 ly = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(ax, M[1]), _mm256_mul_ps(ay, M[4])), _mm256_mul_ps(az, M[7]));
            A[k] = vmin(vmax(ly, mone), one);
            X[k] = _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(ax, M[0]), _mm256_mul_ps(ay, M[3])), _mm256_mul_ps(az, M[6]));
            Z[k] = _mm256_xor_ps(negz, _mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(ax, M[2]), _mm256_mul_ps(ay, M[5])), _mm256_mul_ps(az, M[8])));
        }
        for (int64_t k = 0; k < nv; ++k)
            A[k] = pacos8(A[k]);
        for (int64_t k = 0; k < nv; ++k)
            X[k] = patan2_8(X[k], Z[k]);
        for (int64_t k = 0; k < nv; ++k) {
            const int64_t o = o0 + 8 * k;
            const __m256 v = _mm256_mul_ps(A[k], cpi);
            const __m256 ua = X[k];
            const __m256 y = _mm256_mul_ps(_mm256_sub_ps(v, _mm256_floor_ps(v)), hm1);
            const __m256i iy = _mm256_min_epi32(_mm256_max_epi32(_mm256_cvttps_epi32(y), zi), hm2);
            const __m256 uu = _mm256_sub_ps(_mm256_mul_ps(ua, c2pi), coff);
            const __m256 x = _mm256_mul_ps(_mm256_sub_ps(uu, _mm256_floor_ps(uu)), wf);
            const __m256i ix = _mm256_min_epi32(_mm256_max_epi32(_mm256_cvttps_epi32(x), zi), wm1);
            _mm256_storeu_si256((__m256i*)(r + o), _mm256_add_epi32(_mm256_mullo_epi32(iy, wp1), ix));
            _mm256_storeu_ps(fx + o, _mm256_sub_ps(x, _mm256_cvtepi32_ps(ix)));
            _mm256_storeu_ps(fy + o, _mm256_sub_ps(y, _mm256_cvtepi32_ps(iy)));
        }
    }
}

#if defined(__AVX512F__)
/* The AVX-512 twin of cells8 for hosts where Inductor vectorises for AVX-512 (16 lanes): its generated
   kernel of fast._mirror_cells is the same operations on __m512 (ATen's vec512: _mm512 products, sums,
   divisions, rsqrt as 1 / sqrt, the maximum / minimum that OR in an all-ones NaN mask, floor as
   roundscale, truncating conversions, int32 min / max / mullo) and the polynomial acos / atan2
   (pacos16 / patan2_16; before session 39 Sleef_acosf16_u10 / Sleef_atan2f16_u10). m a multiple of
   8: a last vector of 8 samples reads its lanes 8..15 from the last sample and stores only 8 (each
   lane's result depends on its own inputs only). */
typedef __m512 (*wf1)(__m512);
typedef __m512 (*wf2)(__m512, __m512);
static inline __m512 wmax(__m512 a, __m512 b) {
    const __mmask16 u = _mm512_cmp_ps_mask(a, b, _CMP_UNORD_Q);
    return _mm512_or_ps(_mm512_max_ps(a, b), _mm512_castsi512_ps(_mm512_mask_set1_epi32(_mm512_setzero_si512(), u, -1)));
}
static inline __m512 wmin(__m512 a, __m512 b) {
    const __mmask16 u = _mm512_cmp_ps_mask(a, b, _CMP_UNORD_Q);
    return _mm512_or_ps(_mm512_min_ps(a, b), _mm512_castsi512_ps(_mm512_mask_set1_epi32(_mm512_setzero_si512(), u, -1)));
}
/* 16 floats p[k s] (k < cnt; lanes k >= cnt repeat lane cnt - 1) */
static inline __m512 lds16(const float* p, int64_t s, int64_t cnt) {
    if (s == 1 && cnt == 16)
        return _mm512_loadu_ps(p);
    float t[16];
    for (int k = 0; k < 16; ++k)
        t[k] = p[(k < cnt ? k : cnt - 1) * s];
    return _mm512_loadu_ps(t);
}
/* x, y, z of 16 (x, y, z) triples stored one after another (48 floats at p): two two-source permutes
   per component (component c of triple k is float 3k + c: from the first 32 floats, then the rest from
   the third register) */
static inline void aos3_16(const float* p, __m512* x, __m512* y, __m512* z) {
    const __m512 m0 = _mm512_loadu_ps(p), m1 = _mm512_loadu_ps(p + 16), m2 = _mm512_loadu_ps(p + 32);
    /* a: float 3k + c < 32 from (m0, m1); b: keeps those lanes (index k) and takes the others from m2
       (index 16 + 3k + c - 32) */
    const __m512i ax = _mm512_setr_epi32(0, 3, 6, 9, 12, 15, 18, 21, 24, 27, 30, 0, 0, 0, 0, 0);
    const __m512i bx = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 17, 20, 23, 26, 29);
    const __m512i ay = _mm512_setr_epi32(1, 4, 7, 10, 13, 16, 19, 22, 25, 28, 31, 0, 0, 0, 0, 0);
    const __m512i by = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 18, 21, 24, 27, 30);
    const __m512i az = _mm512_setr_epi32(2, 5, 8, 11, 14, 17, 20, 23, 26, 29, 0, 0, 0, 0, 0, 0);
    const __m512i bz = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 16, 19, 22, 25, 28, 31);
    *x = _mm512_permutex2var_ps(_mm512_permutex2var_ps(m0, ax, m1), bx, m2);
    *y = _mm512_permutex2var_ps(_mm512_permutex2var_ps(m0, ay, m1), by, m2);
    *z = _mm512_permutex2var_ps(_mm512_permutex2var_ps(m0, az, m1), bz, m2);
}
/* pacos8 / patan2_8 on 16 lanes (ATen's vec512: compares as masks, blends on them) */
#define PC16(c) _mm512_set1_ps((float)(c))
static inline __m512 pacos16(__m512 y) {
    const __m512 half = _mm512_set1_ps(0.5f);
    const __m512 a = _mm512_abs_ps(y);
    const __mmask16 big = _mm512_cmp_ps_mask(a, half, _CMP_GT_OQ);
    const __m512 z = _mm512_mask_blend_ps(big, _mm512_mul_ps(a, a), _mm512_sub_ps(half, _mm512_mul_ps(a, half)));
    __m512 q = _mm512_add_ps(_mm512_mul_ps(z, PC16(0.042163199048)), PC16(0.024181311049));
    q = _mm512_add_ps(_mm512_mul_ps(q, z), PC16(0.045470025998));
    q = _mm512_add_ps(_mm512_mul_ps(q, z), PC16(0.074953002686));
    q = _mm512_add_ps(_mm512_mul_ps(q, z), PC16(0.16666752422));
    q = _mm512_mul_ps(q, z);
    const __m512 s = _mm512_mask_blend_ps(big, a, _mm512_sqrt_ps(z));
    const __m512 p = _mm512_add_ps(_mm512_mul_ps(q, s), s);
    const __m512 r = _mm512_mask_blend_ps(big, _mm512_sub_ps(PC16(1.5707963267948966), p), _mm512_mul_ps(p, PC16(2.0)));
    return _mm512_mask_blend_ps(_mm512_cmp_ps_mask(y, _mm512_setzero_ps(), _CMP_LT_OQ), r, _mm512_sub_ps(PC16(3.141592653589793), r));
}
static inline __m512 patan2_16(__m512 y, __m512 x) {
    const __m512 zero = _mm512_setzero_ps();
    const __m512 ax = _mm512_abs_ps(x), ay = _mm512_abs_ps(y);
    const __m512 mn = wmin(ax, ay), mx = wmax(ax, ay);
    const __mmask16 c = _mm512_cmp_ps_mask(mn, _mm512_mul_ps(mx, PC16(0.41421356237309503)), _CMP_GT_OQ);
    const __m512 num = _mm512_mask_blend_ps(c, mn, _mm512_sub_ps(mn, mx));
    __m512 den = _mm512_mask_blend_ps(c, mx, _mm512_add_ps(mn, mx));
    den = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(den, zero, _CMP_GT_OQ), PC16(1.0), den);
    const __m512 t = _mm512_div_ps(num, den), z = _mm512_mul_ps(t, t);
    __m512 q = _mm512_sub_ps(_mm512_mul_ps(z, PC16(0.0805374449538)), PC16(0.138776856032));
    q = _mm512_add_ps(_mm512_mul_ps(q, z), PC16(0.199777106478));
    q = _mm512_sub_ps(_mm512_mul_ps(q, z), PC16(0.333329491539));
    q = _mm512_mul_ps(_mm512_mul_ps(q, z), t);
    const __m512 p = _mm512_add_ps(q, t);
    __m512 r = _mm512_mask_blend_ps(c, p, _mm512_add_ps(p, PC16(0.7853981633974483)));
    r = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(ay, ax, _CMP_GT_OQ), r, _mm512_sub_ps(PC16(1.5707963267948966), r));
    r = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(x, zero, _CMP_LT_OQ), r, _mm512_sub_ps(PC16(3.141592653589793), r));
    return _mm512_mask_blend_ps(_mm512_cmp_ps_mask(y, zero, _CMP_LT_OQ), r, _mm512_xor_ps(_mm512_set1_ps(-0.f), r));
}
static void cells16(const float* nrm, int64_t ns, int64_t nc, const float* wo, int64_t ws, int64_t wc,
                    const float* mm, int64_t H, int64_t W, wf1 vacos, wf2 vatan2, int64_t i0, int64_t m,
                    int32_t* r, float* fx, float* fy) {
    const __m512 eps = _mm512_set1_ps(1e-24f), two = _mm512_set1_ps(2.0f), one = _mm512_set1_ps(1.0f);
    const __m512 mone = _mm512_set1_ps(-1.0f), negz = _mm512_set1_ps(-0.f);
    const __m512 cpi = _mm512_set1_ps((float)0.3183098861837907), c2pi = _mm512_set1_ps((float)0.15915494309189535);
    const __m512 coff = _mm512_set1_ps((float)(0.5 / (double)W));
    const __m512 hm1 = _mm512_set1_ps((float)(H - 1)), wf = _mm512_set1_ps((float)W);
    const __m512i zi = _mm512_set1_epi32(0), hm2 = _mm512_set1_epi32((int32_t)(H - 2));
    const __m512i wm1 = _mm512_set1_epi32((int32_t)(W - 1)), wp1 = _mm512_set1_epi32((int32_t)(W + 1));
    __m512 M[9];
    for (int k = 0; k < 9; ++k)
        M[k] = _mm512_set1_ps(mm[k]);
    /* per block of up to 32 vectors (512 samples): directions, acos calls, atan2 calls, cells (cells8) */
    __m512 A[32], X[32], Z[32];
    for (int64_t o0 = 0; o0 < m; o0 += 512) {
        const int64_t len = m - o0 < 512 ? m - o0 : 512, nv = (len + 15) / 16;
        for (int64_t k = 0; k < nv; ++k) {
            const int64_t i = i0 + o0 + 16 * k, cnt = len - 16 * k < 16 ? len - 16 * k : 16;
            __m512 nx, ny, nz;
            if (ns == 3 && nc == 1 && cnt == 16)  /* the G-buffer's normals: (n, 3) row-major */
                aos3_16(nrm + 3 * i, &nx, &ny, &nz);
            else {
                nx = lds16(nrm + i * ns, ns, cnt);
                ny = lds16(nrm + i * ns + nc, ns, cnt);
                nz = lds16(nrm + i * ns + 2 * nc, ns, cnt);
            }
            const __m512 wx = lds16(wo + i * ws, ws, cnt), wy = lds16(wo + i * ws + wc, ws, cnt);
            const __m512 wz = lds16(wo + i * ws + 2 * wc, ws, cnt);
            const __m512 dot = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(nx, wx), _mm512_mul_ps(ny, wy)), _mm512_mul_ps(nz, wz));
            const __m512 nn = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(nx, nx), _mm512_mul_ps(ny, ny)), _mm512_mul_ps(nz, nz));
            const __m512 s = _mm512_mul_ps(_mm512_div_ps(dot, wmax(nn, eps)), two);
            const __m512 rx = _mm512_sub_ps(_mm512_mul_ps(s, nx), wx);
            const __m512 ry = _mm512_sub_ps(_mm512_mul_ps(s, ny), wy);
            const __m512 rz = _mm512_sub_ps(_mm512_mul_ps(s, nz), wz);
            const __m512 l2 = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(rx, rx), _mm512_mul_ps(ry, ry)), _mm512_mul_ps(rz, rz));
            const __m512 inv = _mm512_div_ps(one, _mm512_sqrt_ps(wmax(l2, eps)));
            const __m512 ax = _mm512_mul_ps(rx, inv), ay = _mm512_mul_ps(ry, inv), az = _mm512_mul_ps(rz, inv);
            const __m512 ly = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(ax, M[1]), _mm512_mul_ps(ay, M[4])), _mm512_mul_ps(az, M[7]));
            A[k] = wmin(wmax(ly, mone), one);
            X[k] = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(ax, M[0]), _mm512_mul_ps(ay, M[3])), _mm512_mul_ps(az, M[6]));
            Z[k] = _mm512_xor_ps(negz, _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(ax, M[2]), _mm512_mul_ps(ay, M[5])), _mm512_mul_ps(az, M[8])));
        }
        for (int64_t k = 0; k < nv; ++k)
            A[k] = pacos16(A[k]);
        for (int64_t k = 0; k < nv; ++k)
            X[k] = patan2_16(X[k], Z[k]);
        for (int64_t k = 0; k < nv; ++k) {
            const int64_t o = o0 + 16 * k, cnt = len - 16 * k < 16 ? len - 16 * k : 16;
            const __mmask16 st = (__mmask16)((1u << cnt) - 1u);
            const __m512 v = _mm512_mul_ps(A[k], cpi);
            const __m512 y = _mm512_mul_ps(_mm512_sub_ps(v, _mm512_floor_ps(v)), hm1);
            const __m512i iy = _mm512_min_epi32(_mm512_max_epi32(_mm512_cvttps_epi32(y), zi), hm2);
            const __m512 uu = _mm512_sub_ps(_mm512_mul_ps(X[k], c2pi), coff);
            const __m512 x = _mm512_mul_ps(_mm512_sub_ps(uu, _mm512_floor_ps(uu)), wf);
            const __m512i ix = _mm512_min_epi32(_mm512_max_epi32(_mm512_cvttps_epi32(x), zi), wm1);
            _mm512_mask_storeu_epi32(r + o, st, _mm512_add_epi32(_mm512_mullo_epi32(iy, wp1), ix));
            _mm512_mask_storeu_ps(fx + o, st, _mm512_sub_ps(x, _mm512_cvtepi32_ps(ix)));
            _mm512_mask_storeu_ps(fy + o, st, _mm512_sub_ps(y, _mm512_cvtepi32_ps(iy)));
        }
    }
}
#endif

/* cells16 with the Sleef f16 functions when w16 (and built for AVX-512), else cells8 with the f8 ones. */
static void cells(const float* nrm, int64_t ns, int64_t nc, const float* wo, int64_t ws, int64_t wc,
                  const float* mm, int64_t H, int64_t W, const void* vacos, const void* vatan2, int64_t w16,
                  int64_t i0, int64_t m, int32_t* r, float* fx, float* fy) {
#if defined(__AVX512F__)
    if (w16) {
        cells16(nrm, ns, nc, wo, ws, wc, mm, H, W, (wf1)vacos, (wf2)vatan2, i0, m, r, fx, fy);
        return;
    }
#endif
    (void)w16;
    cells8(nrm, ns, nc, wo, ws, wc, mm, H, W, (vf1)vacos, (vf2)vatan2, i0, m, r, fx, fy);
}

/* fast._mirror_cells of samples [i0, i1) (multiples of 8) into r, fx, fy (indexed from i0). */
void mirror_cells(const float* nrm, int64_t ns, int64_t nc, const float* wo, int64_t ws, int64_t wc,
                  const float* mm, int64_t H, int64_t W, const void* vacos, const void* vatan2, int64_t w16,
                  int64_t i0, int64_t i1, int32_t* r, float* fx, float* fy) {
    cells(nrm, ns, nc, wo, ws, wc, mm, H, W, vacos, vatan2, w16, i0, i1 - i0, r + i0, fx + i0, fy + i0);
}

#define CELL_RUN 512
/* The perf suite's rows (width 16, no u lanes, the B lanes within the first 8: shade_pixels' `plain`). */
static int plain16(const float* lanes, int64_t width) {
    int plain = width == 16;
    for (int64_t l = 0; plain && l < width; ++l)
        plain &= lanes[width + l] == 0.0f && (l < 8 || lanes[l] == 0.0f);
    return plain;
}

#if defined(__AVX512F__)
/* shade_pixels' plain width-16, S2 = 4 body (the perf suite's) on AVX-512, for the np <= CELL_RUN / 4
   pixels of one run of shade_mirror (b1, b2 contiguous: bs 1): the same operations per lane in the same
   order, the same bits (session 37, pt37). What differs is the instructions around them: a row of 16
   lanes is one zmm register (two ymm halves before: twice the loads, products and sums issued); the
   per-sample scalar weights b0, w0..w3 are computed for the run in a vectorised pass and read as
   broadcasts (before: 4 scalar loads, 8 scalar operations and 7 register broadcasts a sample, and the
   loop's pointers spilled into vector registers); a pixel's four samples are unrolled; and the box
   filter's channel sums (vec_reduce_all of each 8-lane accumulator: halves, lanes two apart,
   neighbours) run for 8 pixels' 24 sums at once, transposed: s_k = acc_k + acc_(k+4) as 128-bit lane
   permutes of two accumulators, (s0 + s2) and (s1 + s3) as shuffles of two of those, their sum as
   shuffles of two of those — the same additions of the same operands (before: ~15 extracts, shuffles
   and scalar additions per sum). */
static void lean16(const int64_t* face, const float* b1p, const float* b2p, const int32_t* r, const float* fx,
                   const float* fy, int64_t np, const int64_t* face_pairs, int64_t M, const float* table,
                   const float* env, const float* lanes, int64_t W, int64_t prefetch, float* out) {
    /* the weights of sample i: wt[0..2][i] b0, b1, b2, wt[3..6][i] w0..w3 (one stack array: each read
       at a constant offset from one index register) */
    float wt[7][CELL_RUN] __attribute__((aligned(64)));
    const int64_t n = 4 * np;
    for (int64_t i = 0; i < n; ++i) {
        const float x = fx[i], y = fy[i], b1 = b1p[i], b2 = b2p[i];
        const float gx = 1.0f - x, gy = 1.0f - y;
        wt[0][i] = (1.0f - b1) - b2, wt[1][i] = b1, wt[2][i] = b2;
        wt[3][i] = gx * gy, wt[4][i] = x * gy, wt[5][i] = gx * y, wt[6][i] = x * y;
    }
    const __m512 zero = _mm512_setzero_ps();
    const __m256 zero8 = _mm256_setzero_ps(), inv = _mm256_set1_ps(0.25f);
    const __mmask16 isb = _mm512_cmp_ps_mask(_mm512_loadu_ps(lanes), zero, _CMP_GT_OQ);
    const __m512 mc0 = _mm512_loadu_ps(lanes + 32), mc1 = _mm512_loadu_ps(lanes + 48), mc2 = _mm512_loadu_ps(lanes + 64);
    const int64_t rowb = (W + 1) * 16;
    const __m256i lo_hi = _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7);
    float zb[24][16] __attribute__((aligned(64)));
    for (int64_t g = 0; g < np; g += 8) {
        const int64_t ng = np - g < 8 ? np - g : 8;
        for (int64_t q = 0; q < ng; ++q) {
            __m512 t = zero;
#pragma GCC unroll 4
            for (int64_t j = 0; j < 4; ++j) {
                const int64_t i = 4 * (g + q) + j;
                if (i + prefetch < n) {
                    const float* e = env + (int64_t)r[i + prefetch] * 16;
                    __builtin_prefetch(e);
                    __builtin_prefetch(e + 16);
                    __builtin_prefetch(e + rowb);
                    __builtin_prefetch(e + rowb + 16);
                }
                int64_t f = face[i];
                if ((uint64_t)f >= (uint64_t)M)
                    f = M - 1;
                const __m512 a = _mm512_add_ps(
                    _mm512_add_ps(_mm512_mul_ps(_mm512_loadu_ps(table + face_pairs[3 * f] * 16), _mm512_set1_ps(wt[0][i])),
                                  _mm512_mul_ps(_mm512_loadu_ps(table + face_pairs[3 * f + 1] * 16), _mm512_set1_ps(wt[1][i]))),
                    _mm512_mul_ps(_mm512_loadu_ps(table + face_pairs[3 * f + 2] * 16), _mm512_set1_ps(wt[2][i])));
                const float* e0 = env + (int64_t)r[i] * 16;
                const float* e2 = e0 + rowb;
                const __m512 e = _mm512_add_ps(
                    _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(_mm512_loadu_ps(e0), _mm512_set1_ps(wt[3][i])),
                                                _mm512_mul_ps(_mm512_loadu_ps(e0 + 16), _mm512_set1_ps(wt[4][i]))),
                                  _mm512_mul_ps(_mm512_loadu_ps(e2), _mm512_set1_ps(wt[5][i]))),
                    _mm512_mul_ps(_mm512_loadu_ps(e2 + 16), _mm512_set1_ps(wt[6][i])));
                /* B lanes: max(0, a) as Inductor's maximum (a > 0 or NaN: a, else +0); the others a e */
                const __mmask16 pos = _mm512_cmp_ps_mask(a, zero, _CMP_NLE_UQ);
                const __m512 tj = _mm512_mask_blend_ps(isb, _mm512_mul_ps(a, e), _mm512_maskz_mov_ps(pos, a));
                t = j ? _mm512_add_ps(t, tj) : tj;
            }
            _mm512_store_ps(zb[3 * q], _mm512_mul_ps(t, mc0));
            _mm512_store_ps(zb[3 * q + 1], _mm512_mul_ps(t, mc1));
            _mm512_store_ps(zb[3 * q + 2], _mm512_mul_ps(t, mc2));
        }
        for (int64_t k = 3 * ng; k < 24; ++k)
            _mm512_store_ps(zb[k], zero);
        __m256 res[3];
        for (int k = 0; k < 3; ++k) {
            /* acc_l = (0 + lanes 0..7) + lanes 8..15 of sum l (= 8 k + l), as shade_pixels' two blocks */
            __m256 acc[8];
            for (int l = 0; l < 8; ++l)
                acc[l] = _mm256_add_ps(_mm256_add_ps(zero8, _mm256_load_ps(zb[8 * k + l])), _mm256_load_ps(zb[8 * k + l] + 8));
            /* s_(l, m) = acc_l[m] + acc_l[m + 4] (m < 4), two sums l per vector: [s_A | s_B] */
            __m256 s[4];
            for (int l = 0; l < 4; ++l)
                s[l] = _mm256_add_ps(_mm256_permute2f128_ps(acc[2 * l], acc[2 * l + 1], 0x20),
                                     _mm256_permute2f128_ps(acc[2 * l], acc[2 * l + 1], 0x31));
            /* (s0 + s2), (s1 + s3) of four sums: [A02 A13 C02 C13 | B02 B13 D02 D13] */
            const __m256 u0 = _mm256_add_ps(_mm256_shuffle_ps(s[0], s[1], 0x44), _mm256_shuffle_ps(s[0], s[1], 0xEE));
            const __m256 u1 = _mm256_add_ps(_mm256_shuffle_ps(s[2], s[3], 0x44), _mm256_shuffle_ps(s[2], s[3], 0xEE));
            /* (s0 + s2) + (s1 + s3): [A C E G | B D F H] (A..H: sums 0..7) */
            const __m256 v = _mm256_add_ps(_mm256_shuffle_ps(u0, u1, 0x88), _mm256_shuffle_ps(u0, u1, 0xDD));
            res[k] = _mm256_mul_ps(_mm256_permutevar8x32_ps(v, lo_hi), inv);
        }
        float* o = out + 3 * g;
        if (ng == 8) {
            _mm256_storeu_ps(o, res[0]);
            _mm256_storeu_ps(o + 8, res[1]);
            _mm256_storeu_ps(o + 16, res[2]);
        } else {
            float tmp[24];
            _mm256_storeu_ps(tmp, res[0]);
            _mm256_storeu_ps(tmp + 8, res[1]);
            _mm256_storeu_ps(tmp + 16, res[2]);
            for (int64_t k = 0; k < 3 * ng; ++k)
                o[k] = tmp[k];
        }
    }
}
#endif

/* mirror_cells then shade_pixels, per run of CELL_RUN samples (whole pixels: CELL_RUN a multiple of
   8 and of S2 — the caller checks), the cells of a run in stack buffers; pixels [p0, p1). lean: the
   perf suite's rows (plain16, S2 = 4, bs 1) take lean16 where built for AVX-512 (the same bits). */
void shade_mirror(const float* nrm, int64_t ns, int64_t nc, const float* wo, int64_t ws, int64_t wc,
                  const float* mm, int64_t H, const void* vacos, const void* vatan2, int64_t w16,
                  const int64_t* face, const float* b1p, const float* b2p, int64_t bs,
                  int64_t p0, int64_t p1, int64_t S2, const int64_t* face_pairs, int64_t M,
                  const float* table, const float* env, const float* lanes, int64_t width, int64_t W,
                  int64_t prefetch, int64_t lean, float* out) {
    int32_t r[CELL_RUN];
    float fx[CELL_RUN], fy[CELL_RUN];
    const int64_t ppr = CELL_RUN / S2;
#if defined(__AVX512F__)
    lean = lean && S2 == 4 && bs == 1 && plain16(lanes, width);
#else
    lean = 0;
#endif
    for (int64_t a = p0; a < p1; a += ppr) {
        const int64_t b = a + ppr < p1 ? a + ppr : p1;
        const int64_t i0 = a * S2, m = (b - a) * S2;
        cells(nrm, ns, nc, wo, ws, wc, mm, H, W, vacos, vatan2, w16, i0, (m + 7) / 8 * 8, r, fx, fy);
#if defined(__AVX512F__)
        if (lean) {
            lean16(face + i0, b1p + i0, b2p + i0, r, fx, fy, b - a, face_pairs, M, table, env, lanes, W, prefetch,
                   out + 3 * a);
            continue;
        }
#endif
        shade_pixels(face + i0, b1p + i0 * bs, b2p + i0 * bs, bs, r, fx, fy, 0, b - a, S2, face_pairs, M, table, env,
                     lanes, width, W, prefetch, m, out + 3 * a);
    }
}
/* shade_mirror over all P pixels on nt threads of OpenMP's team, in chunks of `chunk` pixels (a
   multiple of CELL_RUN / S2, so of 8) dealt round robin: chunk c to thread c mod nt (session 37,
   pt37; the Python wrapper passes one contiguous range per thread by default: native.RR_PIXELS).
   Each pixel is one thread's, so the bits do not depend on nt or the chunk. */
void shade_mirror_par(const float* nrm, int64_t ns, int64_t nc, const float* wo, int64_t ws, int64_t wc,
                      const float* mm, int64_t H, const void* vacos, const void* vatan2, int64_t w16,
                      const int64_t* face, const float* b1p, const float* b2p, int64_t bs,
                      int64_t P, int64_t nt, int64_t S2, const int64_t* face_pairs, int64_t M,
                      const float* table, const float* env, const float* lanes, int64_t width, int64_t W,
                      int64_t prefetch, int64_t lean, int64_t chunk, float* out) {
    const int64_t nch = (P + chunk - 1) / chunk;
#pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int64_t c = 0; c < nch; ++c) {
        const int64_t a = c * chunk, b = a + chunk < P ? a + chunk : P;
        shade_mirror(nrm, ns, nc, wo, ws, wc, mm, H, vacos, vatan2, w16, face, b1p, b2p, bs, a, b, S2, face_pairs, M,
                     table, env, lanes, width, W, prefetch, lean, out);
    }
}

/* fast._cell: first texel and fraction of table coordinate c on a T-wide table, as the compiled pass
   (clamp into [0, T - 1], floor, at most T - 2; a NaN c gives texel 0). */
static inline int32_t tcell(float c, int64_t T, float* frac) {
    float x = (c + 1.0f) * (float)((double)T / 2.0) - 0.5f;
    x = x > 0.0f ? x : 0.0f;
    x = x < (float)(T - 1) ? x : (float)(T - 1);
    int32_t i = (int32_t)__builtin_floorf(x);
    i = i < (int32_t)(T - 2) ? i : (int32_t)(T - 2);
    i = i > 0 ? i : 0;
    *frac = x - (float)i;
    return i;
}

/* fast.vertex_view(..., pairs=sel) with lobes and without the SH column (order 0) in one pass over
   the pairs: row i of out (m + 1, width) is pair sel[i]'s [B (3) | s (3L) | 0 ...], row m is 0.
   pos (3, np), frame (9, np) component rows (FastStatic.pair_pos / pair_frame); cam (3,); pr, pv (np,)
   the pair's region and vertex; Wr (R T^2, 3K), E (V, 3K) row-major, ar (R nt, 3L), vis (V Tv^2, L)
   texel-major. The formulas of fast._pair_cells + fast._pair_rows with their products and sums in
   their order (-ffp-contract=off), the same Sleef atan2 / acos on 8 pairs at a time as the compiled
   pass's vector loop (passed in, as for `cells`), B's lane sums as its reduction (8 lanes, then
   vec_reduce_all). Per block of VROWS_BLOCK pairs: the directions, then their Sleef calls, then every
   pair's cells, weights and row offsets with its rows prefetched (the visibility rows are cache-cold:
   4 per pair in a large table), then the rows. Pairs split over nth threads of OpenMP's team (each row
   one thread's: the same bits at any nth). */
#define VROWS_BLOCK 32
static inline __attribute__((always_inline)) void vview_body(
        const int64_t* sel, int64_t i0, int64_t i1, const float* pos, const float* frame, int64_t np,
        const float* cam, const int32_t* pr, const int32_t* pv, int64_t T, int64_t Tv, int64_t nt,
        const float* Wr, const float* E, const int64_t K, const float* ar, const int64_t L, const float* vis,
        int64_t width, const void* vacos, const void* vatan2, const int w16, const int at, float* out) {
    const int64_t KC = 3 * K, LC = 3 * L, step = nt > 1 ? 1 : 0;
    const float c2pi = (float)(2.0 / 3.141592653589793), fnt = (float)((double)nt / (3.141592653589793 / 2.0));
    float X[VROWS_BLOCK], Y[VROWS_BLOCK], Z[VROWS_BLOCK], RH[VROWS_BLOCK], AT[VROWS_BLOCK], AC[VROWS_BLOCK];
    int64_t og[VROWS_BLOCK], oe[VROWS_BLOCK], oa[VROWS_BLOCK], oh[VROWS_BLOCK];
    float wg[VROWS_BLOCK][4], wa[VROWS_BLOCK][2], wh[VROWS_BLOCK][4];
    const v8 zero = {0, 0, 0, 0, 0, 0, 0, 0};
    v8 mk[3][3];  /* mk[b][c]: lanes of channel c in the 8-lane block o = 8 b (mod 24) of a row */
    for (int b = 0; b < 3; ++b)
        for (int c = 0; c < 3; ++c)
            for (int l = 0; l < 8; ++l)
                mk[b][c][l] = (8 * b + l) % 3 == c ? 1.0f : 0.0f;
    for (int64_t ib = i0; ib < i1; ib += VROWS_BLOCK) {
        const int64_t nb = i1 - ib < VROWS_BLOCK ? i1 - ib : VROWS_BLOCK;
        for (int64_t j = 0; j < VROWS_BLOCK; ++j) {
            const int64_t q = sel[ib + (j < nb ? j : nb - 1)];
            const float dx = cam[0] - pos[q], dy = cam[1] - pos[np + q], dz = cam[2] - pos[2 * np + q];
            const float inv = 1.0f / __builtin_sqrtf((dx * dx + dy * dy) + dz * dz);
            X[j] = ((frame[q] * dx + frame[np + q] * dy) + frame[2 * np + q] * dz) * inv;
            Y[j] = ((frame[3 * np + q] * dx + frame[4 * np + q] * dy) + frame[5 * np + q] * dz) * inv;
            Z[j] = ((frame[6 * np + q] * dx + frame[7 * np + q] * dy) + frame[8 * np + q] * dz) * inv;
            RH[j] = __builtin_sqrtf(X[j] * X[j] + Y[j] * Y[j]);
        }
#if defined(__AVX512F__)
        if (w16)  /* Inductor's AVX-512 pass: 16 pairs per Sleef f16 call (VROWS_BLOCK a multiple of 16) */
            for (int64_t j = 0; j < nb; j += 16) {
                const __m512 z = _mm512_loadu_ps(Z + j);
                _mm512_storeu_ps(AT + j, ((wf2)vatan2)(_mm512_loadu_ps(RH + j), z));
                _mm512_storeu_ps(AC + j, ((wf1)vacos)(wmin(wmax(z, _mm512_set1_ps(-1.0f)), _mm512_set1_ps(1.0f))));
            }
        else
#endif
        for (int64_t j = 0; j < nb; j += 8) {
            const __m256 z = _mm256_loadu_ps(Z + j);
            _mm256_storeu_ps(AT + j, ((vf2)vatan2)(_mm256_loadu_ps(RH + j), z));
            _mm256_storeu_ps(AC + j, ((vf1)vacos)(vmin(vmax(z, _mm256_set1_ps(-1.0f)), _mm256_set1_ps(1.0f))));
        }
        for (int64_t j = 0; j < nb; ++j) {
            const int64_t q = sel[ib + j];
            const float x = X[j], y = Y[j], z = Z[j], rho = RH[j];
            const float up = z > 0.0f ? 1.0f : 0.0f;
            const float sc = rho > 1e-12f ? AT[j] * c2pi / (rho > 1e-12f ? rho : 1e-12f) : c2pi;
            const float cu = x * sc, cv = y * sc;
            float tx, ty, ux, uy;
            const int32_t ix = tcell(cu, T, &tx), iy = tcell(cv, T, &ty);
            const int32_t jx = tcell(-cu, Tv, &ux), jy = tcell(-cv, Tv, &uy);
            const int64_t r = pr[q], v = pv[q];
            /* W_r's bilinear cell, weight 0 below the horizon */
            const float a = (1.0f - tx) * up, b = tx * up;
            wg[j][0] = a * (1.0f - ty), wg[j][1] = b * (1.0f - ty), wg[j][2] = a * ty, wg[j][3] = b * ty;
            og[j] = (r * T * T + (int64_t)iy * T + ix) * KC;
            oe[j] = v * KC;
            /* a_k(theta_o): linear in theta_o over the nt nodes (fast.theta_nodes) */
            float xt = AC[j] * fnt - 0.5f;
            xt = xt > 0.0f ? xt : 0.0f;
            xt = xt < (float)(nt - 1) ? xt : (float)(nt - 1);
            int32_t n0 = nt > 1 ? (int32_t)__builtin_floorf(xt) : 0;
            n0 = n0 < (int32_t)(nt - 2) ? n0 : (int32_t)(nt - 2);
            n0 = n0 > 0 ? n0 : 0;
            const float t = xt - (float)n0;
            wa[j][0] = (1.0f - t) * up, wa[j][1] = t * up;
            oa[j] = (r * nt + n0) * LC;
            /* V_c^(k)(x, R_x): the bilinear cell of R_x = (-x, -y, z) in the vertex's table */
            const float va = (1.0f - ux) * up, vb = ux * up;
            wh[j][0] = va * (1.0f - uy), wh[j][1] = vb * (1.0f - uy), wh[j][2] = va * uy, wh[j][3] = vb * uy;
            oh[j] = (v * Tv * Tv + (int64_t)jy * Tv + jx) * L;
            __builtin_prefetch(vis + oh[j]);
            __builtin_prefetch(vis + oh[j] + 2 * L - 1);
            __builtin_prefetch(vis + oh[j] + Tv * L);
            __builtin_prefetch(vis + oh[j] + Tv * L + 2 * L - 1);
            for (int64_t o = 0; o < KC; o += 16) {
                __builtin_prefetch(E + oe[j] + o);
                __builtin_prefetch(Wr + og[j] + o);
                __builtin_prefetch(Wr + og[j] + KC + o);
                __builtin_prefetch(Wr + og[j] + T * KC + o);
                __builtin_prefetch(Wr + og[j] + (T + 1) * KC + o);
            }
        }
        for (int64_t j = 0; j < nb; ++j) {
            const float* g0 = Wr + og[j];
            const float* g2 = g0 + T * KC;
            const float* e = E + oe[j];
            const float w0 = wg[j][0], w1 = wg[j][1], w2 = wg[j][2], w3 = wg[j][3];
            /* B channel c: the sum over the 8-lane blocks of the row of P * mask_c, then vec_reduce_all (KC a
               multiple of 8: the caller checks). AVX-512 (w16): Inductor's 16-lane accumulator — blocks
               o = 0, 16, ... into its low half acc, o = 8, 24, ... into its high half ach (a last block of 8
               adds to the low half only: sum_masked_reduce) — then its vec_reduce_all, whose first step
               adds the halves lane by lane and whose later steps are AVX2's on those 8 sums */
            float B[3];
            v8 acc[3] = {zero, zero, zero}, ach[3] = {zero, zero, zero};
            for (int64_t o = 0; o < KC; o += 8) {
                const v8 p = (((ld(g0 + o) * w0 + ld(g0 + KC + o) * w1) + ld(g2 + o) * w2) + ld(g2 + KC + o) * w3)
                             * ld(e + o);
                for (int c = 0; c < 3; ++c) {
                    if (w16 && (o / 8) % 2)
                        ach[c] = ach[c] + p * mk[(o / 8) % 3][c];
                    else
                        acc[c] = acc[c] + p * mk[(o / 8) % 3][c];
                }
            }
            for (int c = 0; c < 3; ++c) {
                const v8 u = w16 ? acc[c] + ach[c] : acc[c];
                const float s0 = u[0] + u[4], s1 = u[1] + u[5], s2 = u[2] + u[6], s3 = u[3] + u[7];
                B[c] = (s0 + s2) + (s1 + s3);
            }
            const float* a0 = ar + oa[j];
            const float* a1 = a0 + step * LC;
            const float aw0 = wa[j][0], aw1 = wa[j][1];
            const float* h0 = vis + oh[j];
            const float* h2 = h0 + Tv * L;
            float* o = out + (at ? sel[ib + j] : ib + j) * width;  /* at: the pair's own row (vertex_rows_at) */
            o[0] = B[0];
            o[1] = B[1];
            o[2] = B[2];
            for (int64_t k = 0; k < L; ++k) {
                const float vc = ((h0[k] * wh[j][0] + h0[L + k] * wh[j][1]) + h2[k] * wh[j][2]) + h2[L + k] * wh[j][3];
                for (int c = 0; c < 3; ++c)
                    o[3 + 3 * k + c] = (a0[3 * k + c] * aw0 + a1[3 * k + c] * aw1) * vc;
            }
            for (int64_t l = 3 + LC; l < width; ++l)
                o[l] = 0.0f;
        }
    }
}

static void vrows(const int64_t* sel, int64_t m, const float* pos, const float* frame, int64_t np, const float* cam,
                  const int32_t* pr, const int32_t* pv, int64_t T, int64_t Tv, int64_t nt, const float* Wr,
                  const float* E, int64_t K, const float* ar, int64_t L, const float* vis, int64_t width,
                  const void* vacos, const void* vatan2, int64_t w16, int64_t nth, const int at, float* out) {
#pragma omp parallel for num_threads(nth) schedule(static, 1)
    for (int64_t k = 0; k < nth; ++k) {
        const int64_t i0 = m * k / nth, i1 = m * (k + 1) / nth;
        if (K == 16 && L == 4 && w16)
            vview_body(sel, i0, i1, pos, frame, np, cam, pr, pv, T, Tv, nt, Wr, E, 16, ar, 4, vis, width, vacos,
                       vatan2, 1, at, out);
        else if (K == 16 && L == 4)
            vview_body(sel, i0, i1, pos, frame, np, cam, pr, pv, T, Tv, nt, Wr, E, 16, ar, 4, vis, width, vacos,
                       vatan2, 0, at, out);
        else
            vview_body(sel, i0, i1, pos, frame, np, cam, pr, pv, T, Tv, nt, Wr, E, K, ar, L, vis, width, vacos,
                       vatan2, (int)w16, at, out);
    }
    const int64_t z = at ? np : m;
    for (int64_t l = 0; l < width; ++l)
        out[z * width + l] = 0.0f;
}
void vertex_rows(const int64_t* sel, int64_t m, const float* pos, const float* frame, int64_t np, const float* cam,
                 const int32_t* pr, const int32_t* pv, int64_t T, int64_t Tv, int64_t nt, const float* Wr,
                 const float* E, int64_t K, const float* ar, int64_t L, const float* vis, int64_t width,
                 const void* vacos, const void* vatan2, int64_t w16, int64_t nth, float* out) {
    vrows(sel, m, pos, frame, np, cam, pr, pv, T, Tv, nt, Wr, E, K, ar, L, vis, width, vacos, vatan2, w16, nth, 0, out);
}
/* vertex_rows with pair sel[i]'s row written at row sel[i] of out (np + 1, width) and the zero row at np
   (session 38, pt38: FULL_TABLE): the rows of the pairs not in sel are not written (never read: the
   samples' faces touch the pairs in sel only, a miss the zero row). */
void vertex_rows_at(const int64_t* sel, int64_t m, const float* pos, const float* frame, int64_t np, const float* cam,
                    const int32_t* pr, const int32_t* pv, int64_t T, int64_t Tv, int64_t nt, const float* Wr,
                    const float* E, int64_t K, const float* ar, int64_t L, const float* vis, int64_t width,
                    const void* vacos, const void* vatan2, int64_t w16, int64_t nth, float* out) {
    vrows(sel, m, pos, frame, np, cam, pr, pv, T, Tv, nt, Wr, E, K, ar, L, vis, width, vacos, vatan2, w16, nth, 1, out);
}

/* A shading="vertex" frame's whole native view stage in one call (session 42, pt42: `view_frame`): the
   Python between referenced_sel, vertex_rows_at and shade_mirror(_par) — ~0.4 ms of cold interpreter work a
   chess bench V frame, serial at 2 threads — replaced by one call on a packed argument array (VF_* below;
   the static entries written once per plan, the G-buffer's pointers and the camera each frame). The same
   three loops with the same arguments, in the same order: the same bits. Also the G-buffer's contract that
   the Python path checked first (all samples hit, or exactly the misses have face -1), in the marking
   pass over the faces. The marking reads face_pairs (M, 3), the shading fps (Ms, 3) — fast.miss_face_pairs,
   whose last face is the zero row's: a miss's face -1 reads it, as the Python path's two calls. Returns m (the referenced pairs, > 0), or -1 (the contract does not hold), or 0
   (no pair referenced): then nothing is shaded and the caller takes the Python path. */
enum { VF_FACE, VF_HIT, VF_N, VF_M, VF_NP, VF_NTS, VF_FACE_PAIRS, VF_FMARK, VF_PMARK, VF_SEL,
       VF_POS, VF_FRAME, VF_CAM, VF_PR, VF_PV, VF_T, VF_TV, VF_NTHETA, VF_WR, VF_E, VF_K, VF_AR, VF_L, VF_VIS,
       VF_WIDTH, VF_ACOS, VF_ATAN2, VF_W16, VF_THREADS, VF_MIN_PAIRS, VF_TABLE,
       VF_NRM, VF_NS, VF_NC, VF_WO, VF_WS, VF_WC, VF_MM, VF_H, VF_B1, VF_B2, VF_BS, VF_P, VF_NT, VF_S2,
       VF_ENV, VF_LANES, VF_W, VF_PREFETCH, VF_LEAN, VF_CHUNK, VF_OUT, VF_FPS, VF_MS, VF_COUNT };
int64_t view_frame_count(void) { return VF_COUNT; }
int64_t view_frame(const int64_t* a) {
    const int64_t* face = (const int64_t*)a[VF_FACE];
    const uint8_t* hit = (const uint8_t*)a[VF_HIT];
    const int64_t n = a[VF_N], M = a[VF_M], np = a[VF_NP], nts = a[VF_NTS];
    const int64_t* face_pairs = (const int64_t*)a[VF_FACE_PAIRS];
    uint8_t* fmark = (uint8_t*)a[VF_FMARK];
    uint8_t* pmark = (uint8_t*)a[VF_PMARK];
    int64_t* sel = (int64_t*)a[VF_SEL];
    /* referenced_sel's marking (the same marks), with the contract's two flags */
    int allhit = 1, cons = 1;
#pragma omp parallel for num_threads(nts) schedule(static, 1) reduction(&: allhit, cons)
    for (int64_t k = 0; k < nts; ++k) {
        uint8_t* fm = fmark + k * (M + 1);
        for (int64_t f = 0; f <= M; ++f)
            fm[f] = 0;
        int ah = 1, cs = 1;
        for (int64_t i = n * k / nts; i < n * (k + 1) / nts; ++i) {
            const uint64_t f = (uint64_t)face[i];
            fm[f < (uint64_t)M ? f : (uint64_t)M] = 1;
            const int h = hit[i] != 0;
            ah &= h;
            cs &= (face[i] == -1) != h;
        }
        allhit &= ah;
        cons &= cs;
    }
    if (!(allhit | cons))
        return -1;
    const int64_t m = merge_marks(fmark, M, nts, face_pairs, np, pmark, sel);
    if (m == 0)
        return 0;
    /* vertex_rows_at: the referenced pairs' rows at their own positions, the zero row at np */
    int64_t nth = m / a[VF_MIN_PAIRS];
    nth = nth < a[VF_THREADS] ? nth : a[VF_THREADS];
    nth = nth > 1 ? nth : 1;
    vrows(sel, m, (const float*)a[VF_POS], (const float*)a[VF_FRAME], np, (const float*)a[VF_CAM],
          (const int32_t*)a[VF_PR], (const int32_t*)a[VF_PV], a[VF_T], a[VF_TV], a[VF_NTHETA], (const float*)a[VF_WR],
          (const float*)a[VF_E], a[VF_K], (const float*)a[VF_AR], a[VF_L], (const float*)a[VF_VIS], a[VF_WIDTH],
          (const void*)a[VF_ACOS], (const void*)a[VF_ATAN2], a[VF_W16], nth, 1, (float*)a[VF_TABLE]);
    /* shade_mirror over the pixels (shade_mirror_par at 2+ threads) */
    if (a[VF_NT] > 1)
        shade_mirror_par((const float*)a[VF_NRM], a[VF_NS], a[VF_NC], (const float*)a[VF_WO], a[VF_WS], a[VF_WC],
                         (const float*)a[VF_MM], a[VF_H], (const void*)a[VF_ACOS], (const void*)a[VF_ATAN2], a[VF_W16],
                         face, (const float*)a[VF_B1], (const float*)a[VF_B2], a[VF_BS], a[VF_P], a[VF_NT], a[VF_S2],
                         (const int64_t*)a[VF_FPS], a[VF_MS], (const float*)a[VF_TABLE], (const float*)a[VF_ENV], (const float*)a[VF_LANES],
                         a[VF_WIDTH], a[VF_W], a[VF_PREFETCH], a[VF_LEAN], a[VF_CHUNK], (float*)a[VF_OUT]);
    else if (a[VF_P])
        shade_mirror((const float*)a[VF_NRM], a[VF_NS], a[VF_NC], (const float*)a[VF_WO], a[VF_WS], a[VF_WC],
                     (const float*)a[VF_MM], a[VF_H], (const void*)a[VF_ACOS], (const void*)a[VF_ATAN2], a[VF_W16],
                     face, (const float*)a[VF_B1], (const float*)a[VF_B2], a[VF_BS], 0, a[VF_P], a[VF_S2],
                     (const int64_t*)a[VF_FPS], a[VF_MS], (const float*)a[VF_TABLE], (const float*)a[VF_ENV], (const float*)a[VF_LANES],
                     a[VF_WIDTH], a[VF_W], a[VF_PREFETCH], a[VF_LEAN], (float*)a[VF_OUT]);
    return m;
}
#else
int native_cells_ok(void) { return 0; }
#endif
"""
# On top of `methods.core.native.FLAGS`: the host's ISA (its capability a define of the build, so part
# of the library's cache key: two hosts sharing a temp folder must not share it), no contraction into fused multiply-adds (as
# Inductor's kernels: the same roundings), OpenMP (the library binds to the libgomp torch loaded).
_EXTRA_FLAGS = ("-march=native", "-ffp-contract=off", "-fopenmp", f"-DPRTBENCH_CPU_{native.cpu_capability()}")
# Pixels below which one thread does the pass.
_MIN_PIXELS_PER_THREAD = 1 << 12
# W_r rows below which one thread writes the region tables (`region_tables`).
_MIN_ROWS_PER_THREAD = 1 << 10
# Samples below which one thread marks the referenced faces (`referenced_pairs`).
_MIN_SAMPLES_PER_THREAD = 1 << 15
_P, _I = ctypes.c_void_p, ctypes.c_int64
_SHADE = [_P, _P, _P, _I, _P, _P, _P, _I, _I, _I, _P, _I, _P, _P, _P, _I, _I, _I, _I, _P]
_SIGNATURES = {"shade_pixels": _SHADE, "shade_pixels_par": _SHADE, "region_rows": [_P, _P, _I, _I, _I, _I, _P],
               "region_tables": [_P, _P, _I, _I, _I, _I, _P, _I],
               "region_rows_range": [_P, _P, _I, _I, _I, _I, _P, _I, _I],
               "referenced_pairs": [_P, _I, _P, _I, _I, _I, _P, _P, _P, _P],
               "referenced_sel": [_P, _I, _P, _I, _I, _I, _P, _P, _P]}


@functools.lru_cache(maxsize=None)
def _functions(lib: ctypes.CDLL):
    """``shade_pixels`` with the library's other loops as attributes (``par``, ``region_rows``, and
    where the AVX2 build has them — ``cells_ok`` — ``mirror_cells``, ``shade_mirror``,
    ``shade_mirror_par``)."""
    fn = lib.shade_pixels
    fn.par, fn.region_rows, fn.region_tables = lib.shade_pixels_par, lib.region_rows, lib.region_tables
    fn.region_rows_range = lib.region_rows_range
    fn.referenced_pairs = lib.referenced_pairs
    fn.referenced_pairs.restype = ctypes.c_int64
    fn.referenced_sel = lib.referenced_sel
    fn.referenced_sel.restype = ctypes.c_int64
    fn.cells_isa = int(lib.native_cells_ok())  # bit 0: the AVX2 cells; bit 1: the AVX-512 ones
    fn.cells_ok = bool(fn.cells_isa)
    if fn.cells_ok:
        fn.mirror_cells, fn.shade_mirror = lib.mirror_cells, lib.shade_mirror
        fn.mirror_cells.restype = fn.shade_mirror.restype = None
        fn.mirror_cells.argtypes = [_P, _I, _I, _P, _I, _I, _P, _I, _I, _P, _P, _I, _I, _I, _P, _P, _P]
        fn.shade_mirror.argtypes = [_P, _I, _I, _P, _I, _I, _P, _I, _P, _P, _I, _P, _P, _P, _I, _I, _I, _I, _P, _I,
                                    _P, _P, _P, _I, _I, _I, _I, _P]
        fn.shade_mirror_par = lib.shade_mirror_par
        fn.shade_mirror_par.restype = None
        fn.shade_mirror_par.argtypes = fn.shade_mirror.argtypes[:-1] + [_I, _P]
        fn.vertex_rows = lib.vertex_rows
        fn.vertex_rows.restype = None
        fn.vertex_rows.argtypes = [_P, _I, _P, _P, _I, _P, _P, _P, _I, _I, _I, _P, _P, _I, _P, _I, _P, _I, _P, _P,
                                   _I, _I, _P]
        fn.vertex_rows_at = lib.vertex_rows_at
        fn.vertex_rows_at.restype = None
        fn.vertex_rows_at.argtypes = fn.vertex_rows.argtypes
        fn.view_frame = lib.view_frame
        fn.view_frame.restype = ctypes.c_int64
        fn.view_frame.argtypes = [_P]
        lib.view_frame_count.restype = ctypes.c_int64
        fn.view_frame_count = int(lib.view_frame_count())
    return fn


def _kernel():
    """The compiled loops (`_functions`) or None: no compiler, the build failed, ``PRTBENCH_COMPILE=0``
    (`methods.core.native.load`)."""
    lib = native.load("ptt_shade", _SOURCE, _SIGNATURES, extra_flags=_EXTRA_FLAGS)
    return None if lib is None else _functions(lib)


def available() -> bool:
    """True when `shade_pixels` runs the native loop."""
    return _kernel() is not None




def _check(face: Tensor, bary: Tensor, face_pairs: Tensor, table: Tensor, env: Tensor, lanes: Tensor, S2: int,
           n: int) -> tuple | None:
    """The arguments `shade_pixels` / `shade_mirror` read, contiguous where they must be (the
    barycentrics read in place as two columns), or None when they do not suit the loop."""
    width = int(table.shape[1])
    ok = (face.dtype == torch.int64 and face_pairs.dtype == torch.int64 and face.shape == (n,)
          and bary.dtype == table.dtype == env.dtype == lanes.dtype == torch.float32
          and width % 8 == 0 and 0 < width <= 64 and env.shape[1] == width and lanes.shape[1] >= width
          and bary.shape == (n, 2) and face_pairs.ndim == 2 and face_pairs.shape[1] == 3 and S2 > 0 and n % S2 == 0
          and all(t.device.type == "cpu" for t in (face, bary, face_pairs, table, env, lanes)))
    if not ok:
        return None
    face, face_pairs, table, env = (t.contiguous() for t in (face, face_pairs, table, env))
    b1, b2 = bary[:, 0], bary[:, 1]  # read in place: the G-buffer's are columns of a (2, n) array
    if b1.stride(0) != b2.stride(0):
        bary = bary.contiguous()
        b1, b2 = bary[:, 0], bary[:, 1]
    return face, b1, b2, face_pairs, table, env, lanes[:, :width].contiguous(), width


def _threads(P: int) -> int:
    """Threads of the pass over P pixels: ``torch.get_num_threads()``, fewer for small frames."""
    return max(1, min(torch.get_num_threads(), P // _MIN_PIXELS_PER_THREAD))


def shade_pixels(face: Tensor, bary: Tensor, r: Tensor, fx: Tensor, fy: Tensor, face_pairs: Tensor, table: Tensor,
                 env: Tensor, lanes: Tensor, W: int, S2: int) -> Tensor | None:
    """``fast._shade_block`` (same arguments, same result to float32 round-off) by the native loop,
    or None when it is not available or the arguments are not what it reads (CPU, dtypes, shapes:
    face (n,) int64, bary (n, 2), r (n,) int32, fx, fy (n,) float32; face_pairs (M, 3) int64; table,
    env (·, width) float32 with width a multiple of 8 and at most 64; lanes (5, ≥ width); n a
    multiple of S2). The indices are those ``fast.shade_block`` reads unchecked too: face in [−1, M)
    (others read the zero face M − 1), face_pairs rows of ``table``, r + W + 2 a row of ``env``."""
    fn = _kernel()
    if fn is None:
        return None
    n = int(face.shape[0])
    if not (r.dtype == torch.int32 and fx.dtype == fy.dtype == torch.float32 and r.shape == fx.shape == fy.shape == (n,)
            and all(t.device.type == "cpu" for t in (r, fx, fy))):
        return None
    chk = _check(face, bary, face_pairs, table, env, lanes, S2, n)
    if chk is None:
        return None
    face, b1, b2, face_pairs, table, env, lanes, width = chk
    r, fx, fy = r.contiguous(), fx.contiguous(), fy.contiguous()
    P = n // S2
    out = torch.empty(P, 3, dtype=torch.float32)
    args = (face.data_ptr(), b1.data_ptr(), b2.data_ptr(), b1.stride(0), r.data_ptr(), fx.data_ptr(), fy.data_ptr())
    rest = (S2, face_pairs.data_ptr(), int(face_pairs.shape[0]), table.data_ptr(), env.data_ptr(), lanes.data_ptr(),
            width, int(W), PREFETCH, n, out.data_ptr())
    nt = _threads(P)
    if nt > 1:
        fn.par(*args, P, nt, *rest)
    elif P:
        fn(*args, 0, P, *rest)
    return out


# Inductor's vector ISA → (lanes flag of the native cells, the Sleef acos / atan2 its kernels call:
# ATen's ``Vectorized<float>::acos`` / ``atan2`` of that ISA).
_SLEEF = {"avx2": (0, "Sleef_acosf8_u10", "Sleef_atan2f8_u10"), "avx512": (1, "Sleef_acosf16_u10", "Sleef_atan2f16_u10")}


def _vec_isa() -> str:
    """The vector ISA Inductor's CPU kernels are compiled for here ("avx2", "avx512", ...; its first word:
    ``pick_vec_isa()`` reads e.g. "avx512 avx512_vnni"), "" when unknown."""
    try:
        from torch._inductor.cpu_vec_isa import pick_vec_isa

        return str(pick_vec_isa()).split(" ")[0]
    except (ImportError, AttributeError):
        return ""


@functools.lru_cache(maxsize=None)
def _sleef() -> tuple[int, int, int] | None:
    """(acos, atan2, w16): the addresses of the Sleef acos / atan2 that Inductor's kernels call here —
    on 8 floats where it vectorises for AVX2 (w16 0), on 16 where for AVX-512 (w16 1: ``Sleef_*f16_u10``,
    what its kernels link to) —, from libtorch_cpu; None on any other ISA (its kernels call other Sleef
    variants: the native cells are not used). Not `native.load`'s result: caching it is safe."""
    isa = _SLEEF.get(_vec_isa())
    if isa is None:
        return None
    try:
        lib = ctypes.CDLL(os.path.join(os.path.dirname(torch.__file__), "lib", "libtorch_cpu.so"))
        return (ctypes.cast(getattr(lib, isa[1]), ctypes.c_void_p).value,
                ctypes.cast(getattr(lib, isa[2]), ctypes.c_void_p).value, isa[0])
    except (OSError, AttributeError):
        return None


def cells_available() -> bool:
    """True when `mirror_cells` / `shade_mirror` / `vertex_rows` run natively: the library has the cells
    of the ISA Inductor vectorises for (AVX2: 8 lanes; AVX-512: 16) and its Sleef functions resolved."""
    fn = _kernel()
    sl = _sleef()
    return fn is not None and sl is not None and bool(fn.cells_isa & (2 if sl[2] else 1))


def lean_available() -> bool:
    """True when `shade_mirror` runs and its library has the AVX-512 body ``lean16`` (built for AVX-512:
    ``native_cells_ok`` bit 1), which it takes for the perf suite's rows when `LEAN` (width 16 without u
    lanes, S2 = 4, the barycentrics as the G-buffer's columns)."""
    fn = _kernel()
    return cells_available() and bool(fn.cells_isa & 2)


def _dirs(normal: Tensor, wo: Tensor, n: int) -> tuple | None:
    """(pointer, sample stride, component stride) of normal and wo (n, 3) float32 CPU, or None."""
    out = []
    for t in (normal, wo):
        if t.dtype != torch.float32 or t.device.type != "cpu" or t.shape != (n, 3):
            return None
        out += [t.data_ptr(), t.stride(0), t.stride(1)]
    return tuple(out)


def mirror_cells(normal: Tensor, wo: Tensor, to_world: Tensor, H: int, W: int) -> tuple[Tensor, Tensor, Tensor] | None:
    """``fast.mirror_cells_block`` (r, fx, fy) by the native AVX2 loop, the same bits; None when not
    `cells_available` or the sample count is not a multiple of 8."""
    n = int(normal.shape[0])
    d = _dirs(normal, wo, n)
    if not cells_available() or d is None or n % 8:
        return None
    fn, (ac, at, w16) = _kernel(), _sleef()
    m = to_world.to(torch.float32).contiguous()
    r = torch.empty(n, dtype=torch.int32)
    fx, fy = torch.empty(n), torch.empty(n)
    fn.mirror_cells(*d, m.data_ptr(), int(H), int(W), ac, at, w16, 0, n, r.data_ptr(), fx.data_ptr(), fy.data_ptr())
    return r, fx, fy


# Whether `shade_mirror` shades the perf suite's rows (width 16, no u lanes, S2 = 4) with the AVX-512
# body ``lean16`` where the library is built for AVX-512 (the same bits; tests switch it off to compare).
LEAN = True

# Pixels per chunk of `shade_mirror` at 2+ threads, dealt round robin (`_chunk` rounds it to whole runs of
# the cells' stack buffers); 0: one contiguous range of runs per thread. Session 37 (pt37): OFF — the
# halves leave one thread ~7 % more work on the chess bench (its middle rows cost the most), but dealt
# rows cost more in all (each core's L2 sees every other row of the env map's footprint): run one share
# alone each (1 thread, process CPU, lean16), the critical path read 2.29 ms for the halves against
# 2.44 / 2.49 / 2.32 ms for chunks of 1024 / 2048 / 4096 pixels (sums 4.37 against 4.81 / 4.87 / 4.57),
# and the 2-thread wall time could not be measured on the loaded host (load 8-10: rounds 0.4-2.3x).
RR_PIXELS = 0


def _chunk(S2: int, P: int, nt: int) -> int:
    """`RR_PIXELS` rounded down to whole runs of CELL_RUN = 512 samples (at least one run); with
    `RR_PIXELS` 0, one contiguous range of whole runs per thread (the split before session 37)."""
    run = 512 // S2
    if not RR_PIXELS:
        return -(-P // (nt * run)) * run
    return max(run, RR_PIXELS // run * run)


def shade_mirror(normal: Tensor, wo: Tensor, to_world: Tensor, H: int, face: Tensor, bary: Tensor,
                 face_pairs: Tensor, table: Tensor, env: Tensor, lanes: Tensor, W: int, S2: int) -> Tensor | None:
    """``fast._shade_pixels_block`` (`mirror_cells`, then `shade_pixels` on the cells) in one native
    pass per thread, the cells of 512 samples at a time in stack buffers; the same bits. None when not
    `cells_available`, or the arguments do not suit it (`shade_pixels`; also n a multiple of 8 and
    S2 dividing 512)."""
    n = int(face.shape[0])
    d = _dirs(normal, wo, n)
    if d is None or n % 8 or 512 % max(S2, 1) or not cells_available():
        return None
    chk = _check(face, bary, face_pairs, table, env, lanes, S2, n)
    if chk is None:
        return None
    face, b1, b2, face_pairs, table, env, lanes, width = chk
    fn, (ac, at, w16) = _kernel(), _sleef()
    m = to_world.to(torch.float32).contiguous()
    P = n // S2
    out = torch.empty(P, 3, dtype=torch.float32)
    head = (*d, m.data_ptr(), int(H), ac, at, w16, face.data_ptr(), b1.data_ptr(), b2.data_ptr(), b1.stride(0))
    rest = (S2, face_pairs.data_ptr(), int(face_pairs.shape[0]), table.data_ptr(), env.data_ptr(), lanes.data_ptr(),
            width, int(W), PREFETCH, int(LEAN), out.data_ptr())
    nt = _threads(P)
    if nt > 1:
        fn.shade_mirror_par(*head, P, nt, *rest[:-1], _chunk(S2, P, nt), rest[-1])
    elif P:
        fn.shade_mirror(*head, 0, P, *rest)
    return out


def region_rows(W_rows: Tensor, Hl: Tensor) -> Tensor | None:
    """``fast.region_tables``' W_r (R, T², KC) = Σ_p W_rows[p] · Hl[p] (W_rows (P, T², KC), Hl (P, R, KC)
    or (P, R, 1, KC)), the products and sums in the eager passes' order in one pass: the same bits.
    None when the loop is not available or the arguments are not float32 CPU tensors."""
    fn = _kernel()
    if fn is None or W_rows.dtype != torch.float32 or Hl.dtype != torch.float32 or W_rows.ndim != 3:
        return None
    P, T2, KC = W_rows.shape
    Hl = Hl.reshape(Hl.shape[0], -1, Hl.shape[-1])
    if Hl.shape[0] != P or Hl.shape[2] != KC or W_rows.device.type != "cpu" or Hl.device.type != "cpu":
        return None
    R = int(Hl.shape[1])
    W_rows, Hl = W_rows.contiguous(), Hl.contiguous()
    out = torch.empty(R, T2, KC, dtype=torch.float32)
    fn.region_rows(W_rows.data_ptr(), Hl.data_ptr(), P, R, T2, KC, out.data_ptr())
    return out


def region_tables(W_rows: Tensor, H: Tensor, nt: int = 1, out: Tensor | None = None) -> Tensor | None:
    """``fast.region_tables``' W_r (R·T², K·3) by the native loop ``region_tables`` (its C comment): the
    same bits as `region_rows`, the rows split over ``nt`` threads (the same bits at any ``nt``), the lanes
    read from H (R, P, 3) directly. ``out``: the previous frame's W_r, written in place when its shape fits
    (no fresh pages each VB frame). None when the loop is not available or the arguments are not float32
    CPU tensors."""
    ta = region_tables_args(W_rows, H, nt, out)
    if ta is None:
        return None
    fn, W_rows, P, R, T2, K, out, nt = ta
    H = H.contiguous()
    fn.region_tables(W_rows.data_ptr(), H.data_ptr(), P, R, T2, K, out.data_ptr(), nt)
    return out


def region_tables_args(W_rows: Tensor, H: Tensor, nt: int = 1, out: Tensor | None = None) -> tuple | None:
    """`region_tables`' C call without H's values: (the loops, W_rows contiguous, P, R, T², K, the output —
    ``out`` where it fits, else a new tensor —, the threads), or None where `region_tables` declines (the
    same checks)."""
    fn = _kernel()
    if fn is None or W_rows.dtype != torch.float32 or H.dtype != torch.float32 or W_rows.ndim != 3 or H.ndim != 3:
        return None
    P, T2, KC = W_rows.shape
    R = int(H.shape[0])
    if H.shape[1:] != (P, 3) or KC % 3 or W_rows.device.type != "cpu" or H.device.type != "cpu":
        return None
    W_rows = W_rows.contiguous()
    if (out is None or out.shape != (R * T2, KC) or out.dtype != torch.float32 or not out.is_contiguous()
            or out.device.type != "cpu"):
        out = torch.empty(R * T2, KC, dtype=torch.float32)
    nt = max(1, min(int(nt), (R * T2) // _MIN_ROWS_PER_THREAD))
    return fn, W_rows, P, R, T2, KC // 3, out, nt


def referenced_pairs(face: Tensor, face_pairs: Tensor, n_pairs: int) -> tuple[Tensor, Tensor] | None:
    """``fast.referenced_pairs`` (sel, fpc) by the native loop (the same integers at any thread count:
    the samples split over ``torch.get_num_threads()`` threads of OpenMP's team for large n, each
    marking its own copy of the face marks); None when the loop
    is not available or the arguments are not int64 CPU tensors (face (n,), face_pairs (M, 3) with
    entries in [0, n_pairs))."""
    fn = _kernel()
    if fn is None or face.dtype != torch.int64 or face_pairs.dtype != torch.int64 or face.ndim != 1:
        return None
    if face.device.type != "cpu" or face_pairs.device.type != "cpu" or face_pairs.ndim != 2 or face_pairs.shape[1] != 3:
        return None
    face, face_pairs = face.contiguous(), face_pairs.contiguous()
    M, n = int(face_pairs.shape[0]), int(face.shape[0])
    nt = max(1, min(torch.get_num_threads(), n // _MIN_SAMPLES_PER_THREAD))
    fmark = torch.empty(nt * (M + 1), dtype=torch.uint8)
    pos = torch.empty(n_pairs + 1, dtype=torch.int64)
    sel = torch.empty(n_pairs, dtype=torch.int64)
    fpc = torch.empty(M + 1, 3, dtype=torch.int64)
    m = fn.referenced_pairs(face.data_ptr(), n, face_pairs.data_ptr(), M, int(n_pairs), nt, fmark.data_ptr(),
                            pos.data_ptr(), sel.data_ptr(), fpc.data_ptr())
    return sel[:m], fpc


def referenced_sel(face: Tensor, face_pairs: Tensor, n_pairs: int) -> Tensor | None:
    """`referenced_pairs`' sel alone (the same integers; no remapped face corners: `FULL_TABLE`), or None
    under the same conditions."""
    fn = _kernel()
    if fn is None or face.dtype != torch.int64 or face_pairs.dtype != torch.int64 or face.ndim != 1:
        return None
    if face.device.type != "cpu" or face_pairs.device.type != "cpu" or face_pairs.ndim != 2 or face_pairs.shape[1] != 3:
        return None
    face, face_pairs = face.contiguous(), face_pairs.contiguous()
    M, n = int(face_pairs.shape[0]), int(face.shape[0])
    nt = max(1, min(torch.get_num_threads(), n // _MIN_SAMPLES_PER_THREAD))
    fmark = torch.empty(nt * (M + 1), dtype=torch.uint8)
    pmark = torch.empty(max(int(n_pairs), 1), dtype=torch.uint8)
    sel = torch.empty(n_pairs, dtype=torch.int64)
    m = fn.referenced_sel(face.data_ptr(), n, face_pairs.data_ptr(), M, int(n_pairs), nt, fmark.data_ptr(),
                          pmark.data_ptr(), sel.data_ptr())
    return sel[:m]


# Pairs below which one thread computes `vertex_rows`.
_MIN_PAIRS_PER_THREAD = 1 << 11


def vertex_rows(pairs: Tensor, pos: Tensor, frame: Tensor, cam: Tensor, r32: Tensor, v32: Tensor, T: int, Tv: int,
                nt: int, Wr: Tensor, E: Tensor, K: int, ar: Tensor, vis: Tensor, width: int,
                rows_at: bool = False) -> Tensor | None:
    """``fast.vertex_view(..., pairs=pairs)``'s rows (m + 1, width) with lobes and without the SH
    column (order 0), by the native loop (`cells_available`: the Sleef atan2 / acos of the compiled
    pass); None when it is not available or the arguments are not what it reads (CPU float32 / int32 /
    int64 as ``FastStatic``'s, E (V, 3K) and Wr (·, 3K) row-major with 3K a multiple of 8 — the lane
    blocks of the compiled pass's reduction that B's sums follow —, ar (·, 3L), vis (·, L), width ≥
    3 + 3L). The indices are those the compiled passes read unchecked too.

    rows_at (`FULL_TABLE`): the rows (n_pairs + 1, width), pair p's at row p and the zero row last (n_pairs =
    pos.shape[1]); the rows of pairs not in ``pairs`` are not written (uninitialised: never read when
    ``pairs`` are a frame's `referenced_sel`)."""
    if not cells_available():
        return None
    L = int(vis.shape[1]) if vis.ndim == 2 else -1
    ok = (pairs.dtype == torch.int64 and pairs.ndim == 1 and pairs.numel() > 0 and r32.dtype == v32.dtype == torch.int32
          and all(t.dtype == torch.float32 for t in (pos, frame, cam, Wr, E, ar, vis))
          and pos.ndim == 2 and pos.shape[0] == 3 and frame.shape == (9, pos.shape[1]) and cam.numel() == 3
          and Wr.ndim == 2 and Wr.shape[1] == 3 * K and E.ndim == 2 and E.shape[1] == 3 * K and (3 * K) % 8 == 0
          and ar.ndim == 2 and ar.shape[1] == 3 * L and width >= 3 + 3 * L
          and all(t.device.type == "cpu" for t in (pairs, pos, frame, cam, r32, v32, Wr, E, ar, vis)))
    if not ok:
        return None
    fn, (ac, at, w16) = _kernel(), _sleef()
    pairs, pos, frame, cam, r32, v32, Wr, E, ar, vis = (t.contiguous() for t in (pairs, pos, frame, cam, r32, v32, Wr,
                                                                                   E, ar, vis))
    m = int(pairs.numel())
    out = torch.empty((int(pos.shape[1]) if rows_at else m) + 1, width, dtype=torch.float32)
    nth = max(1, min(torch.get_num_threads(), m // _MIN_PAIRS_PER_THREAD))
    (fn.vertex_rows_at if rows_at else fn.vertex_rows)(
                   pairs.data_ptr(), m, pos.data_ptr(), frame.data_ptr(), int(pos.shape[1]), cam.data_ptr(),
                   r32.data_ptr(), v32.data_ptr(), int(T), int(Tv), int(nt), Wr.data_ptr(), E.data_ptr(), int(K),
                   ar.data_ptr(), L, vis.data_ptr(), int(width), ac, at, w16, nth, out.data_ptr())
    return out


# -- one call per shading="vertex" frame (session 42, pt42) ---------------------------------------------

# The slots of `view_frame`'s packed argument array (the C enum VF_*, in its order).
VF = ("face", "hit", "n", "M", "np", "nts", "face_pairs", "fmark", "pmark", "sel", "pos", "frame", "cam", "pr", "pv",
      "T", "Tv", "ntheta", "Wr", "E", "K", "ar", "L", "vis", "width", "acos", "atan2", "w16", "threads", "min_pairs",
      "table", "nrm", "ns", "nc", "wo", "ws", "wc", "mm", "H", "b1", "b2", "bs", "P", "nt", "S2", "env", "lanes", "W",
      "prefetch", "lean", "chunk", "out", "fps", "Ms")
_VF = {k: i for i, k in enumerate(VF)}


class ViewPlan:
    """The packed arguments of ``view_frame`` (`view_plan`): ``args`` a ctypes int64 array whose static
    slots are written once, ``keep`` the tensors whose addresses it holds (kept alive with it), ``layout``
    the G-buffer layout it was made for (`gbuffer_layout`), ``P`` the pixels. Not a tensor-holding object
    of the ``methods`` packages' state walk (tests/methods/test_threads.py): its tensors are in a tuple of
    a plain namespace."""

    __slots__ = ("args", "keep", "layout", "P", "fn", "key", "cam", "cam_c", "tables")

    def __init__(self, args, keep, layout, P, fn, key, tables):
        self.args, self.keep, self.layout, self.P, self.fn, self.key = args, keep, layout, P, fn, key
        self.cam = torch.zeros(3, dtype=torch.float32)  # the camera origin, written through cam_c each frame
        self.cam_c = (ctypes.c_float * 3).from_address(self.cam.data_ptr())
        self.args[_VF["cam"]] = self.cam.data_ptr()
        self.tables = tables  # (W_r, a_r) as given: `same_tables`

    def same_tables(self, Wr: Tensor, ar: Tensor | None) -> bool:
        """Whether (Wr, ar) are the plan's tables' memory (the same address, shape and strides: the plan keeps
        its tensors alive, so only a tensor of the same storage can have that address)."""
        if ar is None:
            return False
        return all(a.data_ptr() == b.data_ptr() and a.shape == b.shape and a.stride() == b.stride()
                   and a.dtype == b.dtype for a, b in zip((Wr, ar), self.tables))


def gbuffer_layout(face: Tensor, bary: Tensor, normal: Tensor, wo: Tensor, hit: Tensor, spp_side: int, height: int,
                   width: int) -> tuple:
    """What a `ViewPlan` assumes of a G-buffer: dtype, shape, strides and device of each array, and its
    samples per pixel side and image size."""
    return tuple((t.dtype, t.shape, t.stride(), t.is_cpu) for t in (face, bary, normal, wo, hit)) + (spp_side, height,
                                                                                                  width)


def view_plan(st_face_pairs: Tensor, miss_pairs: Tensor, pos: Tensor, frame: Tensor, r32: Tensor, v32: Tensor, T: int, Tv: int, nt: int,
              Wr: Tensor, E: Tensor, K: int, ar: Tensor, vis: Tensor, width: int, to_world: Tensor, H: int,
              env: Tensor, lanes: Tensor, W: int, S2: int, face: Tensor, bary: Tensor, normal: Tensor, wo: Tensor,
              hit: Tensor, key: tuple, layout: tuple) -> ViewPlan | None:
    """A `ViewPlan` for frames of this G-buffer layout: `referenced_sel`, `vertex_rows` (rows_at) and
    `shade_mirror` with these arguments, or None where any of the three would not run (their own checks,
    repeated here: the caller then takes those calls' path, which decides as before)."""
    fn = _kernel()
    if fn is None or not cells_available() or not hasattr(fn, "view_frame") or len(VF) != fn.view_frame_count:
        return None
    n = int(face.shape[0])
    L = int(vis.shape[1]) if vis.ndim == 2 else -1
    ok = (face.dtype == torch.int64 and face.ndim == 1 and st_face_pairs.dtype == torch.int64
          and hit.dtype == torch.bool and hit.shape == (n,) and hit.is_contiguous() and face.is_contiguous()
          and r32.dtype == v32.dtype == torch.int32
          and all(t.dtype == torch.float32 for t in (pos, frame, Wr, E, ar, vis))
          and pos.ndim == 2 and pos.shape[0] == 3 and frame.shape == (9, pos.shape[1])
          and Wr.ndim == 2 and Wr.shape[1] == 3 * K and E.ndim == 2 and E.shape[1] == 3 * K and (3 * K) % 8 == 0
          and ar.ndim == 2 and ar.shape[1] == 3 * L and width >= 3 + 3 * L
          and all(t.device.type == "cpu" for t in (pos, frame, r32, v32, Wr, E, ar, vis, hit)))
    d = _dirs(normal, wo, n)
    if not ok or d is None or n % 8 or S2 <= 0 or 512 % S2 or n % S2 or layout[-2] * layout[-1] * S2 != n:
        return None
    chk = _check(face, bary, miss_pairs, env, env, lanes, S2, n)  # (env for the table: its width is checked)
    if chk is None or int(env.shape[1]) != width:
        return None
    _, b1, b2, fps, _, env, lanes, _ = chk
    face_pairs = st_face_pairs.contiguous()
    if face_pairs.ndim != 2 or face_pairs.shape[1] != 3:
        return None
    Wr0, ar0 = Wr, ar
    pos, frame, r32, v32, Wr, E, ar, vis = (t.contiguous() for t in (pos, frame, r32, v32, Wr, E, ar, vis))
    M, np_ = int(face_pairs.shape[0]), int(pos.shape[1])
    if np_ == 0:
        return None
    threads = torch.get_num_threads()
    nts = max(1, min(threads, n // _MIN_SAMPLES_PER_THREAD))
    P = n // S2
    ntp = _threads(P)
    ac, at, w16 = _sleef()
    m = to_world.to(torch.float32).contiguous()
    fmark = torch.empty(nts * (M + 1), dtype=torch.uint8)
    pmark = torch.empty(max(np_, 1), dtype=torch.uint8)
    sel = torch.empty(np_, dtype=torch.int64)
    table = torch.empty(np_ + 1, width, dtype=torch.float32)
    v = dict(n=n, M=M, np=np_, nts=nts, face_pairs=face_pairs.data_ptr(), fmark=fmark.data_ptr(),
             pmark=pmark.data_ptr(), sel=sel.data_ptr(), pos=pos.data_ptr(), frame=frame.data_ptr(), pr=r32.data_ptr(),
             pv=v32.data_ptr(), T=int(T), Tv=int(Tv), ntheta=int(nt), Wr=Wr.data_ptr(), E=E.data_ptr(), K=int(K),
             ar=ar.data_ptr(), L=L, vis=vis.data_ptr(), width=int(width), acos=ac, atan2=at, w16=w16, threads=threads,
             min_pairs=_MIN_PAIRS_PER_THREAD, table=table.data_ptr(), ns=d[1], nc=d[2], ws=d[4], wc=d[5],
             mm=m.data_ptr(), H=int(H), bs=b1.stride(0), P=P, nt=ntp, S2=int(S2), env=env.data_ptr(),
             lanes=lanes.data_ptr(), W=int(W), prefetch=PREFETCH, lean=int(LEAN), chunk=_chunk(S2, P, max(ntp, 1)),
             fps=fps.data_ptr(), Ms=int(fps.shape[0]))
    args = (ctypes.c_int64 * len(VF))()
    for k, x in v.items():
        args[_VF[k]] = int(x)
    if not (Wr0.data_ptr() == Wr.data_ptr() and ar0.data_ptr() == ar.data_ptr()):
        return None  # (contiguous copies: `same_tables` could not tell a rewritten table)
    keep = (face_pairs, fps, fmark, pmark, sel, pos, frame, r32, v32, Wr, E, ar, vis, table, m, env, lanes)
    return ViewPlan(args, keep, layout, P, fn, key, (Wr0, ar0))


def view_frame(plan: ViewPlan, face: Tensor, bary: Tensor, normal: Tensor, wo: Tensor, hit: Tensor, height: int,
               width: int) -> Tensor | None:
    """The image (height, width, 3) of one frame by ``view_frame`` on ``plan`` (the G-buffer of `plan.layout`,
    height · width = plan.P; the camera in ``plan.cam``), or None: the G-buffer breaks the contract the Python
    path checks (hit / face -1) or its samples reference no pair — nothing was shaded, the caller takes the
    Python path."""
    a = plan.args
    out = torch.empty(height, width, 3, dtype=torch.float32)
    p = bary.data_ptr()
    a[0], a[1], a[31], a[34], a[39], a[40], a[51] = (face.data_ptr(), hit.data_ptr(), normal.data_ptr(), wo.data_ptr(),
                                                      p, p + 4 * bary.stride(1), out.data_ptr())
    return out if plan.fn.view_frame(a) > 0 else None
