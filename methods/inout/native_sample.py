"""In-out's per-sample view frame as one C loop (Mahajan 2008 eq. 4 at every G-buffer sample, box
filtered): `shade` replaces ``fast.prepare`` (the windows and their products X) and
``fast.shade_pixels`` (the compiled per-sample stage, then the exact path of the entries outside
their windows) when the C loop is available; those stay as the fallback (no C compiler,
``PRTBENCH_COMPILE=0``, arrays of other types) and as the test oracle.

The same sums regrouped the same way (``fast`` docstring): B = Σ_j β_j Σ_n w_n X(v_j, n),
X(v, n)_c = Σ_k σ_k h_{k,c}(n) c_{v,k,c}. What differs is where X comes from. The compiled path
forms X on a window per referenced vertex before the samples (the box of the cells a subsample of
the samples hits: a compiled pass over the subsample, a scatter, the windows' offsets, one K-term
reduction per window node) and reads it per sample; here X is a memo filled while the samples are
shaded: each vertex has a W × W window of table nodes (W = `WINDOW`) around its anchor (the cell
of the direction from the vertex to the camera in its frame, ``fast.anchors``: the samples around a
vertex see it from nearly that direction), set at the first sample that reads the vertex in the
frame, and a node's X is computed at the first sample that reads it. So X is formed at exactly the
(vertex, node) pairs the frame's samples read (chess bench: ~0.8·10⁵ at W = 8, where the windows held
~2.6·10⁵ nodes), and no pass over the samples precedes the shading. An entry whose cell leaves its
vertex's window is summed exactly from the table and c (Σ_n w_n σ_k h_k(n), then the K-term dot
product with c), in the sample's own sum, not in a later pass. The image equals the compiled path's
to float32 round-off (other summation orders; the tests compare them).

Deterministic at any thread count: the window of a vertex is a function of the camera alone, and a
memo row's value of the (vertex, node) pair alone, so whichever thread fills a row writes the same
bits (its stamp is stored after its values with release order, read with acquire order); the
pixels go to OpenMP's team in chunks of `CHUNK` pixels, each to the next free thread (a dynamic
schedule: the image's cost is uneven), each pixel summed by one thread in one order. The memo (per
concatenated vertex id, its W² rows of 4 floats: X's 3 channels and a 0, one 16-byte load; and a
stamp per row) is kept between frames (zeroed once), so nothing is allocated per frame; a frame
counts itself in the stamps, so the previous frame's rows are stale.

Session 31 (`FAST`): each G-buffer array is read along its own layout (the bench's column-major ω_o
and barycentrics as runs, its row-major normals split; the same values), and the memo's and the
exact path's K-term dot products are fused multiply-adds, 16 lanes wide on AVX-512 hosts (`dotf`,
`dot4f`; float32 round-off). Same process against session 30's code, 1 thread, process CPU, V
frames: chess 1.01-1.08×, creature 1.02-1.11× (load 4-6; ``python -m benchmarks.inout --base B
--scene chess|creature --kinds V L --frames 15 --threads 1 --no-micro``). What bounds the loop now
(perf, chess bench, 1 thread): the memo look-ups ~30 % (their stamp and row loads), the memo fills
~25 % and the exact path ~20 % (table rows of 3K floats, K ≤ 88, from a 4.3 MB table: ~8·10⁴ fills
and ~5·10⁴ exact entries a frame), the per-sample set-up ~15 %. Tried and dropped (same process,
alternating, bit-identical): the block's dependent loads in three passes with software prefetches
(face → vertex records → memo rows and stamps): 0.88-0.93×; the row's stamp kept in its 4th float
(one cache line fewer per look-up): 0.99-1.04×.

Session 32 (`FAST` bits 4 and 8, FMA builds): a memo fill computes its cell's four rows at once
(`cell_x`: the 12 dot products, 4 nodes × 3 channels, in one loop, each into its own accumulator,
then a fixed reduction tree), and an entry outside its vertex's window computes the same four
values by the same function, so a (vertex, node) pair's X has the same bits on every path — memo
row, exact entry, whichever thread or cell — and the image the same bits whatever the window; and a
sample on the same face as the last shaded one (~78 % on the chess bench) takes its vertices and
windows from it, in the same cell (~64 %) its 12 X values too (no look-up, no exact sum). The
image equals session 29's loop to float32 round-off (≤ 1.8e-7 of the peak, chess bench). Where the
V frame's time goes (a standalone C driver over a dumped chess bench frame, 1 thread, the caches
flushed or not alike): not the arithmetic — per-row fills by `cell_x`'s arithmetic (half the rows),
a 1024-entry cache of the exact entries (38.9 → 22.6·10³ computed) and huge pages for the memo,
table and c each read ~1.0× — but the per-entry chain of dependent loads (face → vertex record →
stamps → memo rows) and the first touches of the table and c rows; skipping whole entries is what
pays.

Session 33 (`FAST` bits 16 and 32): each thread keeps a 1024-entry cache of (face, cell) entries (the
face's 3 vertices' X at the cell's 4 nodes), looked up when a sample's (face, cell) differs from the
last one's, before the vertex records and the memo (chess bench: ~94·10³ look-ups meet ~37·10³ keys,
the same (face, cell) an image row later; entries summed exactly 43 → 30·10³, near the frame's
~67·10³ distinct (vertex, cell) pairs); and `cell_x` reduces its 12 sums at once (`x4_sums`, AVX-512:
the pairs of ``_mm512_reduce_add_ps``, the same bits). The image is the same bits as bits 4 | 8 (and
as session 32's loop). Where a chess bench V frame's loop time goes now (1 thread, each call right
after its frame's G-buffer was rasterised, ablations in one process): the G-buffer reads, the
samples' cells and the per-sample checks ~23 %, B's 36 multiply-adds per sample ~15 %, the look-ups
(cache entries, vertex records, memo stamps and rows) ~29 %, `cell_x` (70·10³ calls: its table and
c rows streamed from L2 / L3, ~5.3 KB a call at K = 88) ~34 %. Tried and dropped (same process,
alternating, the same bits): the memo rows' validity as a mask in the vertex record (no stamp array)
0.98-1.0×; with it, only the missing rows of a cell computed (memo rows 1.6 → 0.85·10⁵) 0.97-1.04×;
W = 16 with both 0.96×; 2048 / 512 cache entries 1.02× / 0.97× against 1024; looking 8 samples
ahead to prefetch a missing key's stamps and memo rows 0.87-0.99×.

Session 35 (`FAST` bits 64 and 128; the same bits): where a V frame's time goes, whole frame under the
suite's protocol (chess bench): everything of `render` but this loop ~0.08 ms CPU (torch and ctypes
set-up; 13.7 ms with the loop, 1 thread); at 2 threads the two threads' CPU inside the loop sums to
the single thread's (14.3 ms, both busy from start to end: the dynamic chunks balance them), so the
2-thread frame is half the loop's work plus the wake-up. The front end alone (the G-buffer read along
its layouts and `frame_cells`, every sample dead) ~2.2 ms cold; bit 64 makes it 16 samples wide (2.04
ms), bit 128 prefetches the next block's rows. The entries outside their window: ~30·10³ calls a frame
for ~23·10³ distinct (vertex, cell) pairs on ~1.7·10³ vertices (none also in the memo), so a cache of
them could save ≤ 7·10³ `cell_x` calls (~0.4 ms): not tried. Tried and dropped: two threads from the
image's two ends towards each other (contiguous runs of 256-pixel chunks, a shared claim count):
the threads' CPU in the loop 14.26 against 14.30 ms (the same work; 156 against 161·10³ rows made,
fewer filled twice), wall unmeasurable at load 8.

Session 37 (`FAST` bits 256, 512, 1024; the same bits): the batched per-tile form (`shade_tile`). The
pixels go in tiles of `TILE` pixels (at 2+ threads a tile is a chunk of the dynamic schedule), each in
three passes over compact per-tile arrays: (1) resolve — the front end as before, then each shaded
sample's (face, cell) to an entry of the tile (the last sample's, else a 4096-slot hash of packed 8-byte
slots, 32 KB; the tile closes early after a block when its entries near half the slots), its weights and
entry kept (20 B a sample), the entry's vertices with a nonzero weight marked; (2) fill — the entries'
(vertex, cell) needs grouped by vertex (tile-local vertex ids, a counting sort), per vertex its distinct
table nodes (bit 512; else its distinct cells by `cell_x`) four at a time by `rows_x` (`cell_x`'s loop
on any four rows: the same bits per (vertex, node) pair), its c row read once a tile (bit 1024: two
vertices ahead prefetched), each entry's 3 × 4 X written; (3) shade — each sample's B from its entry,
the loop's sum in the loop's order. No memo, vertex record or stamp is read: a (vertex, node) pair met
by several tiles is computed again (chess bench ~155·10³ products a frame at 2048 pixels against the
124.5·10³ distinct ones; 1024: 182·10³, 4096: 148·10³), but each tile reads a vertex's c once and its
look-ups stay in L1 / L2. Where a chess bench V frame's time goes (1 thread, cold, process CPU, a
thread-CPU clock around each pass, host at load ~7): resolve ~3.7 ms (the front end ~2.0 of it), grouping
~0.55, fill ~5.5 (~40·10³ `rows_x` calls: with the four table rows in L1 ~3.5 and with c in L1 too ~3.3,
so ~2 ms is the table rows' L2 → L1 traffic, 1 KB a (vertex, node) product, and ~1.9 ms the per-vertex
node book-keeping), shade ~1.4. Tried and dropped: the memo's window rows read and written in the fill
(128·10³ products, near the minimum, but 0.87-0.92x: a vertex's window rows and stamps cost as many
misses as its c); tiles of 1024 / 4096 pixels (chess 1.12x / 1.13x, creature 1.17x / 1.07x against 1.17x
/ 1.24x at 2048, same process).

Session 39 (`FAST` bit 2048; the same bits): a chess bench V tile pass spends (perf, 1 thread, warm) ~22 % in
`rows_x`'s loop, ~14 % tagging each vertex's distinct nodes (a data-dependent branch per node), ~25 % in the
resolve's per-sample loop (hash probes, region check), ~13 % in the shade pass, ~5 % splitting the normals;
with the table rows in L1 (`benchmarks.inout_tiles`, variant ``table``) the fill drops 4.4 -> 2.3 ms, so the
table rows' traffic (1 KB a (vertex, node) product, ~155·10³ a frame; ~820 distinct nodes a tile, each read by
~6 of the tile's ~240 vertices) is what bounds the fill. Bit 2048 tags the nodes without branches (1.04-1.06x).
Tried and dropped (loop alone, 1 thread, same process, alternating, the same bits): a vertex's cells
deduplicated before its nodes are tagged 0.97x (its entries rarely repeat a cell); the next ``rows_x`` call's
four table rows prefetched 0.95x (per frame 0.997x: the rows stream, their bandwidth not latency bounds);
the table copied with each channel padded to 16 lanes (rows on 64-byte lines, no split loads) 0.97-0.99x;
consecutive vertices (same slot) as pairs, the nodes both need by a two-vertex ``rows_x`` (each table row read
once for both: 23 % fewer row reads on chess) 0.90-0.94x (the pairs' node lists, partition and padding cost more).
Around the loop, each torch op of the frame runs with the loop's cold caches (~20-80 µs each): `shade` passes its
per-slot arrays as one ctypes array and reads its stats with one ``tolist``, and `InOut._render_native` looks
the library up once a frame.

Session 41 (ip41; chess bench V, 1 thread, process CPU, each call after a fresh rasterisation, host at load 5-9):
where the call's ~8.1-8.9 ms go (``python -m benchmarks.inout_tiles --scene chess --variants base table norows
front``): resolve ~2.8 of which the front end ~0.87 (variant ``front``) and the per-sample loop after it ~1.9;
group ~0.45; fill ~3.6-4.2 of which the table rows' traffic ~1.9 (``table``: 2.1-2.3), ``rows_x``'s arithmetic
~0.9 and the book-keeping ~1.3 (``norows``); shade ~1.0. The (vertex, node) products per tile carry ~117 MB of
table rows a frame through L1 (chess: slots K = 88 / 53 / 26: 61 / 77 / 13·10³ products), ~23 MB of them
distinct per tile; between consecutive bench V frames (10° of orbit) only ~34 % of a frame's ~1.2·10⁵ distinct
(vertex, node) pairs recur, so X kept across view frames would save at most a third of the fill. Tried and
dropped (the same bits, the same (vertex, node) products; ``python -m benchmarks.inout_loop_ab --scene chess
--frames 21 --cold --variants 4095 NEW 4095:``; A/A 0.95-1.03x at that load): a vertex's distinct nodes by one
bit mask per table row (R <= 64; the nodes in row order, each entry's slots by popcount, no tags) 0.95-0.98x;
with it the tile's vertices ordered along a Morton curve of their first cell (consecutive vertices reading the
same rows) 0.98-1.00x; the resolve's look-up without the branch on the last key (one probe a sample, the entry
written unconditionally, every entry needing its 3 vertices) 1.02-1.04x; with it the samples' keys, liveness
and region check 8 at a time (AVX-512 gather of the faces' regions) 1.01-1.02x. The per-sample loop after the
front end does not follow its branches or its arithmetic: ablations (region check off -0.3 ms, weights not
written -0.2 ms, one face for every sample -0.55 ms) point at its reads of the G-buffer's face / region / live
columns and its per-tile working set (table rows ~0.6-0.8 MB, c ~0.2 MB, entries' X up to 0.4 MB, weights
0.13 MB against a 1 MB L2). Not tried: the fill node-major within a tile (each table row read once a tile,
the ~6 vertices that need it from L2: c rows instead of table rows per product, plus a transposition).

Session 44 (ip44; 1 thread, process CPU, each call after a fresh rasterisation, host at load ~1-4). The frame
vertex-major (`FAST` bit 131072, `shade_vm`; it loses, so it was not merged: its code is on branch ip44): the samples resolved once (front end, a 24-byte
record per sample), per vertex the spans of the node rows its samples read (16-bit words by bytewise max:
order-free, so the same at any thread count), X at each span node by ``rows_x`` vertex after vertex (a later
vertex's c prefetched), then the samples shaded from that buffer; the same bits as the tiles. Its spans hold
127.8·10³ nodes on a chess bench V frame against 124.5·10³ distinct (vertex, node) pairs (a box per vertex:
278.6·10³; the tiles: 155·10³ products; creature 88.7 / 85.4 / 203.8 / 105·10³), but its passes (``python -m
benchmarks.inout_vm --scene chess|creature`` on branch ip44) cost, chess: resolve 3.3-3.4 ms (front end 0.87, writing the
per-sample records ~0.6 — the front end alone with them 1.48 —, the rest the face / region reads and the
span words; their compare-and-swap, needed at 2+ threads only, ~0.45 more), count + prefix 0.2, fill 3.0-3.5
(table rows in L1: 1.6-2.1; no ``rows_x`` but each vertex's last group, i.e. c's first touch, the X buffer's
writes and the spans: 1.1-1.2), shade 2.0-2.5 (the records back from L3, then up to six dependent look-ups
per new (face, cell)): a call of ~9-9.8 ms against the tiles' ~8.0 (~7.7 with bit 65536); creature 6.5-7.0
against 5.7 (6.0). ``benchmarks.inout_loop_ab --cold --variants 4095 69631 200703``: chess 0.83-0.89x,
creature 0.87-0.88x against 4095. So the fill per product is not cheaper vertex-major (its table rows stream
from L3 where the tile's sit in L2; the vertices sorted by their first cell: 0.94x) and the second pass over
the samples costs more than the tile's grouping: the brief's stop rule (sort + vertex pass must beat ~4 ms)
fails on the vertex pass alone. Node-row spans inside a tile instead of the nodes' tags (the tile fill's
book-keeping): 160.5 against 155.4·10³ products, 0.97x (dropped). Kept: bit 65536, the tile's shade pass a
pixel's four samples per AVX-512 vector, the same bits (chess shade pass 1.0 -> 0.59 ms); with one entry for
all four samples its X broadcast instead of four inserts: 1.00x; the resolve's per-sample weights written four
samples at a time (a 4 x 4 transpose) 0.99x (both dropped). Whole V frames against the base checkout
(``python -m benchmarks.inout --base BASE --scene chess|creature --kinds V --frames 15|21 --threads 1|2
--no-micro``, warm, max |d| 0): chess CPU 1.06x at 1 thread (load ~3), wall 1.17x at 2; creature 1.09x / 1.08x.

Session 48 (tried and dropped, not merged): 2-D tiles instead of 8 image rows (a tile's runs its row segments,
each tile a chunk of the dynamic schedule; the same bits). Fewer (vertex, node) products are made again in a
neighbouring tile (a bench V frame: chess 155.4 -> 133.3·10³ at 64 x 32 pixels, 131.0 at 32 x 64, 133.6 at 32 x 32;
creature 105.3 -> 94.7·10³, 92.7 at 64 x 64; the frame's distinct pairs: 124.5 / 85.4·10³), but the call barely
moves (1 thread, process CPU, each call after a fresh rasterisation, 15 frames alternating, host at load ~0.3;
A/A 0.98-0.99x): chess 1.02-1.03x, creature 0.99-1.02x. So the fill's time does not follow its product count:
another ~14 % fewer products is worth ~2 % of the call.
"""
from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from methods.core import native
from methods.core.fused import compile_enabled

__all__ = ["WINDOW", "available", "cells_available", "shade"]

# Nodes per side of a vertex's memo window (its W² rows of X, 16 B each, and their stamps): entries
# whose cell leaves it take the exact sum. W = 8 against 16 (same process, 1 thread, process CPU, V):
# chess 1.01-1.12×, creature 1.09×, the memo 4× smaller (chess bench 55 → 14 MB, creature 69 → 17 MB);
# chess bench ~8·10⁴ memo rows filled and ~5·10⁴ entries summed exactly per frame (W = 16: 1.1·10⁵,
# 1.7·10⁴).
WINDOW = 8

_SOURCE = r"""
#include <stdint.h>
#include <math.h>
#include <string.h>
#include <stdlib.h>
#include <omp.h>
#if defined(__AVX2__) || defined(__AVX512F__)
#include <immintrin.h>
#endif

typedef float v8 __attribute__((vector_size(32)));
typedef float v4 __attribute__((vector_size(16)));

/* lut_cell_xyz (methods.inout.transport): the cell (iu, iv) and fractions (fu, fv) of a local
   direction (x, y, z), float32 in torch's order of operations. */
static inline void cell_of(float x, float y, float z, int64_t R, int64_t *iu, int64_t *iv, float *fu, float *fv) {
    const float h = 0.5f * (float)(R - 1), top = (float)(R - 1), top2 = (float)(R - 2);
    float s = (fabsf(x) + fabsf(y)) + (z > 0.0f ? z : 0.0f);
    s = s < 1e-30f ? 1e-30f : s;
    const float px = x / s, py = y / s;
    float u = ((px + py) + 1.0f) * h, v = ((px - py) + 1.0f) * h;
    u = u < 0.0f ? 0.0f : (u > top ? top : u);
    v = v < 0.0f ? 0.0f : (v > top ? top : v);
    float fiu = floorf(u), fiv = floorf(v);
    fiu = fiu > top2 ? top2 : fiu;
    fiv = fiv > top2 ? top2 : fiv;
    if (!(fiu >= 0.0f)) fiu = 0.0f;   /* NaN: any in-range cell (the caller skips such a sample) */
    if (!(fiv >= 0.0f)) fiv = 0.0f;
    *iu = (int64_t)fiu; *iv = (int64_t)fiv;
    *fu = u - fiu; *fv = v - fiv;
}

/* sum_k a[k] b[k], 8 lanes combined pairwise, then the tail */
static inline float dot(const float *a, const float *b, int64_t K) {
    v8 s = {0, 0, 0, 0, 0, 0, 0, 0};
    int64_t k = 0;
    for (; k + 8 <= K; k += 8) {
        v8 x, y;
        memcpy(&x, a + k, 32);
        memcpy(&y, b + k, 32);
        s += x * y;
    }
    float acc = ((s[0] + s[1]) + (s[2] + s[3])) + ((s[4] + s[5]) + (s[6] + s[7]));
    for (; k < K; ++k)
        acc += a[k] * b[k];
    return acc;
}

/* sum_k (((s0 w0 + s1 w1) + s2 w2) + s3 w3)[k] cv[k] (the exact path, fast._outlier_rows's sum) */
static inline float dot4(const float *s0, const float *s1, const float *s2, const float *s3, float w0, float w1,
                         float w2, float w3, const float *cv, int64_t K) {
    v8 a8 = {0, 0, 0, 0, 0, 0, 0, 0};
    int64_t k = 0;
    for (; k + 8 <= K; k += 8) {
        v8 x0, x1, x2, x3, cc;
        memcpy(&x0, s0 + k, 32); memcpy(&x1, s1 + k, 32); memcpy(&x2, s2 + k, 32); memcpy(&x3, s3 + k, 32);
        memcpy(&cc, cv + k, 32);
        v8 S = x0 * w0;
        S = S + x1 * w1;
        S = S + x2 * w2;
        S = S + x3 * w3;
        a8 += S * cc;
    }
    float acc = ((a8[0] + a8[1]) + (a8[2] + a8[3])) + ((a8[4] + a8[5]) + (a8[6] + a8[7]));
    for (; k < K; ++k) {
        float S = s0[k] * w0;
        S = S + s1[k] * w1;
        S = S + s2[k] * w2;
        S = S + s3[k] * w3;
        acc += S * cv[k];
    }
    return acc;
}

/* With FMA (and AVX-512 where the library is built for it): sum_k a[k] b[k] by fused multiply-adds in
   two accumulators of whole vectors, the tail masked (AVX-512) or scalar, combined by a fixed tree;
   and the exact path's sum as the four nodes' dot products with c weighted: sum_n w_n (s_n . c), the
   same terms as `dot4` in another order (float32 round-off), four multiply-adds per term instead of
   nine operations. Both are functions of their operands alone (no thread or schedule in them). */
#if defined(__AVX512F__)
static inline float hsum16(__m512 a) { return _mm512_reduce_add_ps(a); }
static inline float dotf(const float *a, const float *b, int64_t K) {
    __m512 s0 = _mm512_setzero_ps(), s1 = _mm512_setzero_ps();
    int64_t k = 0;
    for (; k + 32 <= K; k += 32) {
        s0 = _mm512_fmadd_ps(_mm512_loadu_ps(a + k), _mm512_loadu_ps(b + k), s0);
        s1 = _mm512_fmadd_ps(_mm512_loadu_ps(a + k + 16), _mm512_loadu_ps(b + k + 16), s1);
    }
    for (; k < K; k += 16) {
        const __mmask16 mk = K - k >= 16 ? (__mmask16)0xFFFF : (__mmask16)((1u << (K - k)) - 1u);
        s0 = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(mk, a + k), _mm512_maskz_loadu_ps(mk, b + k), s0);
    }
    return hsum16(_mm512_add_ps(s0, s1));
}
static inline float dot4f(const float *s0, const float *s1, const float *s2, const float *s3, float w0, float w1,
                          float w2, float w3, const float *cv, int64_t K) {
    __m512 a0 = _mm512_setzero_ps(), a1 = _mm512_setzero_ps(), a2 = _mm512_setzero_ps(), a3 = _mm512_setzero_ps();
    for (int64_t k = 0; k < K; k += 16) {
        const __mmask16 mk = K - k >= 16 ? (__mmask16)0xFFFF : (__mmask16)((1u << (K - k)) - 1u);
        const __m512 c = _mm512_maskz_loadu_ps(mk, cv + k);
        a0 = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(mk, s0 + k), c, a0);
        a1 = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(mk, s1 + k), c, a1);
        a2 = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(mk, s2 + k), c, a2);
        a3 = _mm512_fmadd_ps(_mm512_maskz_loadu_ps(mk, s3 + k), c, a3);
    }
    return ((w0 * hsum16(a0) + w1 * hsum16(a1)) + w2 * hsum16(a2)) + w3 * hsum16(a3);
}
/* the vector primitives of `cell_x` (one body for both builds, below): 16 lanes, the tail
   by a load mask */
typedef __m512 vecf;
typedef __mmask16 vecm;
#define VL 16
#define VZERO() _mm512_setzero_ps()
#define VMASK(n) ((n) >= 16 ? (__mmask16)0xFFFF : (__mmask16)((1u << (n)) - 1u))
#define VLOAD(mk, p) _mm512_maskz_loadu_ps(mk, p)
#define VFMA(a, b, c) _mm512_fmadd_ps(a, b, c)
#define VSUM(a) hsum16(a)
#define HAVE_DOTF 1
#elif defined(__FMA__) && defined(__AVX2__)
static inline float hsum8(__m256 a) {
    __m128 x = _mm_add_ps(_mm256_castps256_ps128(a), _mm256_extractf128_ps(a, 1));
    x = _mm_add_ps(x, _mm_movehl_ps(x, x));
    x = _mm_add_ss(x, _mm_movehdup_ps(x));
    return _mm_cvtss_f32(x);
}
static inline float dotf(const float *a, const float *b, int64_t K) {
    __m256 s0 = _mm256_setzero_ps(), s1 = _mm256_setzero_ps();
    int64_t k = 0;
    for (; k + 16 <= K; k += 16) {
        s0 = _mm256_fmadd_ps(_mm256_loadu_ps(a + k), _mm256_loadu_ps(b + k), s0);
        s1 = _mm256_fmadd_ps(_mm256_loadu_ps(a + k + 8), _mm256_loadu_ps(b + k + 8), s1);
    }
    for (; k + 8 <= K; k += 8)
        s0 = _mm256_fmadd_ps(_mm256_loadu_ps(a + k), _mm256_loadu_ps(b + k), s0);
    float acc = hsum8(_mm256_add_ps(s0, s1));
    for (; k < K; ++k)
        acc = fmaf(a[k], b[k], acc);
    return acc;
}
static inline float dot4f(const float *s0, const float *s1, const float *s2, const float *s3, float w0, float w1,
                          float w2, float w3, const float *cv, int64_t K) {
    __m256 a0 = _mm256_setzero_ps(), a1 = _mm256_setzero_ps(), a2 = _mm256_setzero_ps(), a3 = _mm256_setzero_ps();
    int64_t k = 0;
    for (; k + 8 <= K; k += 8) {
        const __m256 c = _mm256_loadu_ps(cv + k);
        a0 = _mm256_fmadd_ps(_mm256_loadu_ps(s0 + k), c, a0);
        a1 = _mm256_fmadd_ps(_mm256_loadu_ps(s1 + k), c, a1);
        a2 = _mm256_fmadd_ps(_mm256_loadu_ps(s2 + k), c, a2);
        a3 = _mm256_fmadd_ps(_mm256_loadu_ps(s3 + k), c, a3);
    }
    float d0 = hsum8(a0), d1 = hsum8(a1), d2 = hsum8(a2), d3 = hsum8(a3);
    for (; k < K; ++k) {
        d0 = fmaf(s0[k], cv[k], d0); d1 = fmaf(s1[k], cv[k], d1); d2 = fmaf(s2[k], cv[k], d2); d3 = fmaf(s3[k], cv[k], d3);
    }
    return ((w0 * d0 + w1 * d1) + w2 * d2) + w3 * d3;
}
/* the vector primitives of `cell_x`: 8 lanes, the tail by masked loads */
typedef __m256 vecf;
typedef __m256i vecm;
static const int32_t vlanes[16] = {-1, -1, -1, -1, -1, -1, -1, -1, 0, 0, 0, 0, 0, 0, 0, 0};
#define VL 8
#define VZERO() _mm256_setzero_ps()
#define VMASK(n) _mm256_loadu_si256((const __m256i *)(vlanes + 8 - ((n) >= 8 ? 8 : (n))))
#define VLOAD(mk, p) _mm256_maskload_ps(p, mk)
#define VFMA(a, b, c) _mm256_fmadd_ps(a, b, c)
#define VSUM(a) hsum8(a)
#define HAVE_DOTF 1
#endif

#ifdef HAVE_DOTF
#ifdef __AVX512F__
/* bit 32 (AVX-512 builds): `cell_x`'s 12 sums as `hsum16` forms each (lanes i + 8 paired, then i + 4,
   i + 2, i + 1: _mm512_reduce_add_ps), the same pairs at every level, but 16 vectors at once (the 12
   and 4 zeros) by transposing shuffles: ~36 instructions for the 12 instead of ~8 each. So the same
   bits as `hsum16`'s; vector v = 4 ch + n reduced into lane 4 n + ch, so the result is x[0..3] (X of
   the 4 nodes, 3 channels and a 0) as one store. */
static inline void x4_sums(__m512 a[4][3], v4 *x) {
    const __m512 z0 = _mm512_setzero_ps();
    __m512 v[16], u[8], w[4], y[2];
    for (int n = 0; n < 4; ++n) {
        for (int ch = 0; ch < 3; ++ch)
            v[4 * ch + n] = a[n][ch];
        v[12 + n] = z0;
    }
    for (int p = 0; p < 6; ++p)      /* lanes i, i + 8 (256-bit halves): u[p] = (v[2p]'s 8 | v[2p + 1]'s 8) */
        u[p] = _mm512_add_ps(_mm512_shuffle_f32x4(v[2 * p], v[2 * p + 1], 0x44), _mm512_shuffle_f32x4(v[2 * p], v[2 * p + 1], 0xEE));
    u[6] = z0; u[7] = z0;
    for (int r = 0; r < 3; ++r)      /* lanes i, i + 4 (quarters): w[r]'s quarter k = v[4r + k]'s 4 */
        w[r] = _mm512_add_ps(_mm512_shuffle_f32x4(u[2 * r], u[2 * r + 1], 0x88), _mm512_shuffle_f32x4(u[2 * r], u[2 * r + 1], 0xDD));
    w[3] = z0;
    for (int q = 0; q < 2; ++q)      /* lanes i, i + 2 within a quarter */
        y[q] = _mm512_add_ps(_mm512_shuffle_ps(w[2 * q], w[2 * q + 1], 0x44), _mm512_shuffle_ps(w[2 * q], w[2 * q + 1], 0xEE));
    /* lanes 0, 1: quarter k = the sums of v[k], v[4 + k], v[8 + k], v[12 + k] */
    const __m512 s = _mm512_add_ps(_mm512_shuffle_ps(y[0], y[1], 0x88), _mm512_shuffle_ps(y[0], y[1], 0xDD));
    _mm512_storeu_ps((float *)x, s);
}
#endif

/* X(v, n) at a cell's four nodes n0, n0 + 1, n0 + R, n0 + R + 1 (table rows t, t + 3K, t + R3K,
   t + R3K + 3K; bit 4 of `fast`): the 12 dot products (4 nodes x 3 channels) with c in one pass, each
   by fused multiply-adds into its own accumulator, VL lanes a step (the tail masked), then summed by
   `VSUM`'s fixed tree: each value a function of its (vertex, node) pair alone, whichever cell,
   thread or path (memo fill or an entry outside the window) computes it. One loop for the 12 sums:
   the per-row fills' 6 loops a row and their branches cost more than the arithmetic. */
static inline void rows_x(const float *r0, const float *r1, const float *r2, const float *r3, const float *cv, int64_t K,
                          v4 *x, int tree) {
    vecf a[4][3];
    for (int n = 0; n < 4; ++n)
        for (int ch = 0; ch < 3; ++ch)
            a[n][ch] = VZERO();
    for (int64_t k = 0; k < K; k += VL) {
        const vecm mk = VMASK(K - k);
        for (int ch = 0; ch < 3; ++ch) {
            const int64_t o = ch * K + k;
            const vecf c = VLOAD(mk, cv + o);
            a[0][ch] = VFMA(VLOAD(mk, r0 + o), c, a[0][ch]);
            a[1][ch] = VFMA(VLOAD(mk, r1 + o), c, a[1][ch]);
            a[2][ch] = VFMA(VLOAD(mk, r2 + o), c, a[2][ch]);
            a[3][ch] = VFMA(VLOAD(mk, r3 + o), c, a[3][ch]);
        }
    }
#ifdef __AVX512F__
    if (tree) {
        x4_sums(a, x);
        return;
    }
#else
    (void)tree;
#endif
    for (int n = 0; n < 4; ++n)
        x[n] = (v4){VSUM(a[n][0]), VSUM(a[n][1]), VSUM(a[n][2]), 0.0f};
}
/* the cell's four nodes (rows_x: any four table rows, each X by the same operations; bit 512 calls it
   with four distinct nodes of a vertex, the same bits per (vertex, node) pair) */
static inline void cell_x(const float *t, int64_t R3K, const float *cv, int64_t K, v4 *x, int tree) {
    rows_x(t, t + 3 * K, t + R3K, t + R3K + 3 * K, cv, K, x, tree);
}

#endif

typedef struct {
    const float *nrm; int64_t n0, n1;       /* normal (q, 3): element strides */
    const float *wo; int64_t w0, w1;        /* wo (q, 3) */
    const float *bary; int64_t b0, b1;      /* bary (q, 2) */
    const int64_t *face; const int64_t *region; const uint8_t *live;   /* (q,) contiguous */
    const int32_t *face_rows; const int64_t *face_region; int64_t M;   /* (M, 3), (M,) */
    const int64_t *voff; int64_t S;         /* slot offsets (S + 1) */
    const int64_t *shp, *cp, *Ks;           /* per slot: table (R^2 3, K) and c (Vr, 3, K) pointers, K */
    const float *pos, *frames, *cam;        /* per vertex (nv, 3), (nv, 9); (3,) */
    int64_t R, W, S2, stamp, chunk;         /* chunk: pixels per chunk of the dynamic schedule (nt > 1) */
    int64_t fast;                           /* bits: 1 the G-buffer read along its layout, 2 `dotf` / `dot4f` */
    int32_t *vrec;                          /* per vertex (nv, 4): stamp, u0, v0, slot */
    float *memo;                            /* per vertex W^2 rows of 4 floats: X (3) and 0 */
    int32_t *mstamp;                        /* per memo row: the frame that filled it */
    int64_t ylog;                           /* bit 16: log2 of the entries of each thread's (face, cell) cache */
    int64_t tile;                           /* bit 256: pixels per tile */
} Args;

/* the vertex's window (its anchor cell's, W x W nodes within the table) and slot, set once a frame */
static inline const int32_t *vertex_window(const Args *A, int64_t g) {
    int32_t *r = A->vrec + 4 * g;
    if (__atomic_load_n(r, __ATOMIC_ACQUIRE) == (int32_t)A->stamp)
        return r;
    int64_t s = 0;
    while (s + 1 < A->S && g >= A->voff[s + 1]) ++s;
    /* fast.anchors: d = cam - pos, normalised, into the vertex's frame, its cell */
    float d0 = A->cam[0] - A->pos[3 * g], d1 = A->cam[1] - A->pos[3 * g + 1], d2 = A->cam[2] - A->pos[3 * g + 2];
    float nn = sqrtf((d0 * d0 + d1 * d1) + d2 * d2);
    nn = nn < 1e-12f ? 1e-12f : nn;
    d0 /= nn; d1 /= nn; d2 /= nn;
    const float *F = A->frames + 9 * g;
    const float x = (F[0] * d0 + F[1] * d1) + F[2] * d2, y = (F[3] * d0 + F[4] * d1) + F[5] * d2;
    const float z = (F[6] * d0 + F[7] * d1) + F[8] * d2;
    int64_t au, av; float fu, fv;
    cell_of(x, y, z, A->R, &au, &av, &fu, &fv);
    const int64_t h = A->W / 2 - 1, hi = A->R - A->W;
    int64_t u0 = au - h, v0 = av - h;
    u0 = u0 < 0 ? 0 : (u0 > hi ? hi : u0);
    v0 = v0 < 0 ? 0 : (v0 > hi ? hi : v0);
    r[1] = (int32_t)u0; r[2] = (int32_t)v0; r[3] = (int32_t)s;
    __atomic_store_n(r, (int32_t)A->stamp, __ATOMIC_RELEASE);
    return r;
}

/* X(v, node) of memo row `row` (vertex g of slot s, table node `node`) unless this frame filled it */
static inline void memo_fill(const Args *A, int64_t g, int64_t s, int64_t row, int64_t node, int64_t *made) {
    if (__atomic_load_n(A->mstamp + row, __ATOMIC_ACQUIRE) == (int32_t)A->stamp)
        return;
    const int64_t K = A->Ks[s];
    const float *sh = (const float *)(intptr_t)A->shp[s] + node * 3 * K;
    const float *cv = (const float *)(intptr_t)A->cp[s] + (g - A->voff[s]) * 3 * K;
    float *m = A->memo + 4 * row;
#ifdef HAVE_DOTF
    if (A->fast & 2) {
        m[0] = dotf(sh, cv, K);
        m[1] = dotf(sh + K, cv + K, K);
        m[2] = dotf(sh + 2 * K, cv + 2 * K, K);
    } else
#endif
    {
        m[0] = dot(sh, cv, K);
        m[1] = dot(sh + K, cv + K, K);
        m[2] = dot(sh + 2 * K, cv + 2 * K, K);
    }
    m[3] = 0.0f;
    __atomic_store_n(A->mstamp + row, (int32_t)A->stamp, __ATOMIC_RELEASE);
    ++*made;
}


/* fast.sample_frame then lut_cell_xyz at n samples given as columns: omega_o in the sample's frame
   (its z) and its table cell (iu, iv) and fractions (fu, fv), float32 in torch's order of operations.
   With AVX2, 8 samples at a time (the inputs padded to a multiple of 8; the same IEEE operations, so
   the same values as the scalar loop but for NaN inputs, whose samples are not shaded: z > 0 fails). */
static void frame_cells(const float *nx_, const float *ny_, const float *nz_, const float *a_, const float *b_,
                        const float *c_, int64_t n, float h, float top, float top2, int32_t *iu_, int32_t *iv_,
                        float *fu_, float *fv_, float *z_, int wide) {
    int64_t i = 0;
#ifdef __AVX512F__
    /* bit 64 (AVX-512 builds): 16 samples at a time, the AVX2 loop's operations one for one (so the
       same values; the inputs padded to a multiple of 16) */
    if (wide) {
        const __m512 one = _mm512_set1_ps(1.0f), m1 = _mm512_set1_ps(-1.0f), zero = _mm512_setzero_ps();
        const __m512 e12 = _mm512_set1_ps(1e-12f), e30 = _mm512_set1_ps(1e-30f), sgn = _mm512_set1_ps(-0.0f);
        const __m512 H = _mm512_set1_ps(h), T = _mm512_set1_ps(top), T2 = _mm512_set1_ps(top2);
        for (; i < n; i += 16) {
            __m512 nx = _mm512_loadu_ps(nx_ + i), ny = _mm512_loadu_ps(ny_ + i), nz = _mm512_loadu_ps(nz_ + i);
            const __m512 a = _mm512_loadu_ps(a_ + i), b = _mm512_loadu_ps(b_ + i), c = _mm512_loadu_ps(c_ + i);
            __m512 inv = _mm512_sqrt_ps(_mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(nx, nx), _mm512_mul_ps(ny, ny)),
                                                      _mm512_mul_ps(nz, nz)));
            inv = _mm512_div_ps(one, _mm512_max_ps(inv, e12));
            nx = _mm512_mul_ps(nx, inv); ny = _mm512_mul_ps(ny, inv); nz = _mm512_mul_ps(nz, inv);
            const __m512 sign = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(nz, zero, _CMP_GE_OQ), m1, one);
            const __m512 Am = _mm512_xor_ps(_mm512_div_ps(one, _mm512_add_ps(sign, nz)), sgn);
            const __m512 d = _mm512_add_ps(_mm512_mul_ps(nx, a), _mm512_mul_ps(ny, b));
            const __m512 u = _mm512_sub_ps(_mm512_mul_ps(Am, d), c);
            const __m512 x = _mm512_add_ps(a, _mm512_mul_ps(_mm512_mul_ps(sign, nx), u));
            const __m512 y = _mm512_add_ps(_mm512_mul_ps(sign, b), _mm512_mul_ps(ny, u));
            const __m512 z = _mm512_add_ps(d, _mm512_mul_ps(nz, c));
            __m512 s = _mm512_add_ps(_mm512_add_ps(_mm512_andnot_ps(sgn, x), _mm512_andnot_ps(sgn, y)), _mm512_max_ps(z, zero));
            s = _mm512_max_ps(s, e30);
            const __m512 px = _mm512_div_ps(x, s), py = _mm512_div_ps(y, s);
            __m512 uu = _mm512_mul_ps(_mm512_add_ps(_mm512_add_ps(px, py), one), H);
            __m512 vv = _mm512_mul_ps(_mm512_add_ps(_mm512_sub_ps(px, py), one), H);
            uu = _mm512_min_ps(_mm512_max_ps(uu, zero), T);
            vv = _mm512_min_ps(_mm512_max_ps(vv, zero), T);
            const __m512 fiu = _mm512_min_ps(_mm512_roundscale_ps(uu, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC), T2);
            const __m512 fiv = _mm512_min_ps(_mm512_roundscale_ps(vv, _MM_FROUND_TO_NEG_INF | _MM_FROUND_NO_EXC), T2);
            _mm512_storeu_si512((void *)(iu_ + i), _mm512_cvttps_epi32(fiu));
            _mm512_storeu_si512((void *)(iv_ + i), _mm512_cvttps_epi32(fiv));
            _mm512_storeu_ps(fu_ + i, _mm512_sub_ps(uu, fiu));
            _mm512_storeu_ps(fv_ + i, _mm512_sub_ps(vv, fiv));
            _mm512_storeu_ps(z_ + i, z);
        }
        return;
    }
#else
    (void)wide;
#endif
#ifdef __AVX2__
    const __m256 one = _mm256_set1_ps(1.0f), m1 = _mm256_set1_ps(-1.0f), zero = _mm256_setzero_ps();
    const __m256 e12 = _mm256_set1_ps(1e-12f), e30 = _mm256_set1_ps(1e-30f), sgn = _mm256_set1_ps(-0.0f);
    const __m256 H = _mm256_set1_ps(h), T = _mm256_set1_ps(top), T2 = _mm256_set1_ps(top2);
    for (; i < n; i += 8) {
        __m256 nx = _mm256_loadu_ps(nx_ + i), ny = _mm256_loadu_ps(ny_ + i), nz = _mm256_loadu_ps(nz_ + i);
        const __m256 a = _mm256_loadu_ps(a_ + i), b = _mm256_loadu_ps(b_ + i), c = _mm256_loadu_ps(c_ + i);
        __m256 inv = _mm256_sqrt_ps(_mm256_add_ps(_mm256_add_ps(_mm256_mul_ps(nx, nx), _mm256_mul_ps(ny, ny)),
                                                  _mm256_mul_ps(nz, nz)));
        inv = _mm256_div_ps(one, _mm256_max_ps(inv, e12));
        nx = _mm256_mul_ps(nx, inv); ny = _mm256_mul_ps(ny, inv); nz = _mm256_mul_ps(nz, inv);
        const __m256 sign = _mm256_blendv_ps(m1, one, _mm256_cmp_ps(nz, zero, _CMP_GE_OQ));
        const __m256 Am = _mm256_xor_ps(_mm256_div_ps(one, _mm256_add_ps(sign, nz)), sgn);
        const __m256 d = _mm256_add_ps(_mm256_mul_ps(nx, a), _mm256_mul_ps(ny, b));
        const __m256 u = _mm256_sub_ps(_mm256_mul_ps(Am, d), c);
        const __m256 x = _mm256_add_ps(a, _mm256_mul_ps(_mm256_mul_ps(sign, nx), u));
        const __m256 y = _mm256_add_ps(_mm256_mul_ps(sign, b), _mm256_mul_ps(ny, u));
        const __m256 z = _mm256_add_ps(d, _mm256_mul_ps(nz, c));
        __m256 s = _mm256_add_ps(_mm256_add_ps(_mm256_andnot_ps(sgn, x), _mm256_andnot_ps(sgn, y)), _mm256_max_ps(z, zero));
        s = _mm256_max_ps(s, e30);
        const __m256 px = _mm256_div_ps(x, s), py = _mm256_div_ps(y, s);
        __m256 uu = _mm256_mul_ps(_mm256_add_ps(_mm256_add_ps(px, py), one), H);
        __m256 vv = _mm256_mul_ps(_mm256_add_ps(_mm256_sub_ps(px, py), one), H);
        uu = _mm256_min_ps(_mm256_max_ps(uu, zero), T);
        vv = _mm256_min_ps(_mm256_max_ps(vv, zero), T);
        const __m256 fiu = _mm256_min_ps(_mm256_floor_ps(uu), T2), fiv = _mm256_min_ps(_mm256_floor_ps(vv), T2);
        _mm256_storeu_si256((__m256i *)(iu_ + i), _mm256_cvttps_epi32(fiu));
        _mm256_storeu_si256((__m256i *)(iv_ + i), _mm256_cvttps_epi32(fiv));
        _mm256_storeu_ps(fu_ + i, _mm256_sub_ps(uu, fiu));
        _mm256_storeu_ps(fv_ + i, _mm256_sub_ps(vv, fiv));
        _mm256_storeu_ps(z_ + i, z);
    }
#endif
    for (; i < n; ++i) {
        float nx = nx_[i], ny = ny_[i], nz = nz_[i];
        const float a = a_[i], b = b_[i], c = c_[i];
        float inv = sqrtf((nx * nx + ny * ny) + nz * nz);
        inv = 1.0f / (inv < 1e-12f ? 1e-12f : inv);
        nx *= inv; ny *= inv; nz *= inv;
        const float sign = nz >= 0.0f ? 1.0f : -1.0f;
        const float Am = -(1.0f / (sign + nz));
        const float d = nx * a + ny * b;
        const float u = Am * d - c;
        const float x = a + sign * nx * u, y = sign * b + ny * u, z = d + nz * c;
        int64_t iu, iv;
        cell_of(x, y, z, (int64_t)top + 1, &iu, &iv, fu_ + i, fv_ + i);
        iu_[i] = (int32_t)iu; iv_[i] = (int32_t)iv;
        z_[i] = z;
    }
}

/* rows q0 .. q0 + n of a (q, nc) float32 array with element strides (s0, s1) as nc columns `cols`,
   read along its layout: column-major as nc runs, row-major rows split, other strides element by
   element (the same values whichever) */
static inline void columns(const float *a, int64_t s0, int64_t s1, int nc, int64_t q0, int64_t n, float **cols, int wide) {
    if (s0 == 1) {
        for (int c = 0; c < nc; ++c)
            memcpy(cols[c], a + q0 + c * s1, (size_t)n * sizeof(float));
    } else if (s1 == 1 && s0 == nc) {
        const float *src = a + nc * q0;
        int64_t i = 0;
#ifdef __AVX512F__
        if (wide && nc == 3) {   /* bit 64: 16 rows (48 floats) at a time split by two permutes per column */
            __m512i i1[3], i2[3];
            for (int c = 0; c < 3; ++c) {
                int32_t x1[16], x2[16];
                for (int l = 0; l < 16; ++l) {
                    const int e = 3 * l + c;
                    x1[l] = e < 32 ? e : 0;
                    x2[l] = e < 32 ? l : 16 + (e - 32);
                }
                i1[c] = _mm512_loadu_si512((const void *)x1);
                i2[c] = _mm512_loadu_si512((const void *)x2);
            }
            for (; i + 16 <= n; i += 16) {
                const __m512 r0 = _mm512_loadu_ps(src + 3 * i), r1 = _mm512_loadu_ps(src + 3 * i + 16),
                             r2 = _mm512_loadu_ps(src + 3 * i + 32);
                for (int c = 0; c < 3; ++c)
                    _mm512_storeu_ps(cols[c] + i, _mm512_permutex2var_ps(_mm512_permutex2var_ps(r0, i1[c], r1), i2[c], r2));
            }
        }
#else
        (void)wide;
#endif
        for (; i < n; ++i)
            for (int c = 0; c < nc; ++c)
                cols[c][i] = src[nc * i + c];
    } else {
        for (int64_t i = 0; i < n; ++i)
            for (int c = 0; c < nc; ++c)
                cols[c][i] = a[(q0 + i) * s0 + c * s1];
    }
}

#define BLK 64   /* pixels per block of the per-sample inputs */

/* bit 128: the next block's G-buffer rows (q0 .. q0 + n) requested into L2 while this block is shaded
   (prefetches only: no value changes) — the arrays' runs as the layouts lay them out */
static inline void pf_range(const void *p, int64_t bytes) {
    const char *c = (const char *)p;
    for (int64_t o = 0; o < bytes; o += 64)
        __builtin_prefetch(c + o, 0, 2);
}
static inline void pf_array(const float *a, int64_t s0, int64_t s1, int nc, int64_t q0, int64_t n) {
    if (s0 == 1) {
        for (int c = 0; c < nc; ++c)
            pf_range(a + q0 + c * s1, n * 4);
    } else if (s1 == 1 && s0 == nc) {
        pf_range(a + nc * q0, nc * n * 4);
    }
}
static inline void pf_block(const Args *A, int64_t q0, int64_t n) {
    pf_array(A->nrm, A->n0, A->n1, 3, q0, n);
    pf_array(A->wo, A->w0, A->w1, 3, q0, n);
    pf_array(A->bary, A->b0, A->b1, 2, q0, n);
    pf_range(A->face + q0, n * 8);
    pf_range(A->region + q0, n * 8);
    pf_range(A->live + q0, n);
}

/* bit 16 (with 4 and 8): per thread a direct-mapped cache of 2^ylog (face, cell) entries, each its
   X(v_j, n) at the face's 3 vertices and the cell's 4 nodes (the ones computed: `have`), tagged by the
   key and the `shade` call (`gen`: a process-wide count, so no entry outlives its call). A sample whose
   (face, cell) differs from the last one's looks it up before the vertex records and the memo: on the
   chess bench ~94·10³ such samples a frame meet ~37·10³ distinct keys in a 1024-entry cache (the same
   (face, cell) one image row later). An entry's values are its pairs' X, the same bits on every path
   (`cell_x`), so the image is the same bits with or without it and at any thread count; the memo's rows
   computed are those of the frame's (vertex, cell) pairs with a weight, whichever path reaches them. */
typedef struct {
    int64_t key; uint64_t gen; int32_t have, pad[3];
    v4 x[3][4];
} yent;

static __thread yent *ytls;
static __thread int64_t ytls_log;
static uint64_t ygen_all;

static yent *ycache(int64_t lg) {
    if (ytls == 0 || ytls_log != lg) {
        free(ytls);
        ytls = (yent *)aligned_alloc(64, sizeof(yent) << lg);
        if (ytls == 0)
            return 0;
        memset(ytls, 0, sizeof(yent) << lg);     /* gen 0: no call's */
        ytls_log = lg;
    }
    return ytls;
}

static void shade_range(const Args *A, int64_t p0, int64_t p1, float *out, int64_t *stats, uint64_t ygen) {
    yent *yc = (A->fast & 28) == 28 && A->ylog > 0 ? ycache(A->ylog) : 0;
    const int64_t R = A->R, W = A->W, S2 = A->S2, WW = W * W, cmax = R * R - R - 2;
    const int32_t cur = (int32_t)A->stamp;
    const float h = 0.5f * (float)(R - 1), top = (float)(R - 1), top2 = (float)(R - 2);
    int64_t made = 0, exact = 0, bad = -1;
    v4 pxl[3][4];                           /* bits 4 | 8: the last shaded sample's X per vertex of its face */
    v4 (*px)[4] = pxl;                      /* (bit 16: its entry of the thread's cache) */
    int32_t havel = 0, *hv = &havel;        /* the vertices of px computed */
    int64_t pf = -1, piu = -1, piv = -1, pg[3] = {0, 0, 0};
    const int32_t *pr[3] = {0, 0, 0};
    int wins = 0;
    float nx_[BLK * 8 + 8], ny_[BLK * 8 + 8], nz_[BLK * 8 + 8], a_[BLK * 8 + 8], b_[BLK * 8 + 8], c_[BLK * 8 + 8];
    float bu_[BLK * 8], bv_[BLK * 8], fu_[BLK * 8 + 8], fv_[BLK * 8 + 8], z_[BLK * 8 + 8];
    int32_t iu_[BLK * 8 + 8], iv_[BLK * 8 + 8];
    memset(nx_, 0, sizeof nx_); memset(ny_, 0, sizeof ny_); memset(nz_, 0, sizeof nz_);
    memset(a_, 0, sizeof a_); memset(b_, 0, sizeof b_); memset(c_, 0, sizeof c_);
    for (int64_t pb = p0; pb < p1; pb += BLK) {
        const int64_t pe = pb + BLK < p1 ? pb + BLK : p1, q0 = pb * S2, n = (pe - pb) * S2;
        if (n > BLK * 8) {   /* S2 > 8: one pixel at a time would need larger buffers; never on the bench */
            continue;
        }
        if (A->fast & 1) {   /* the same values, each array read along its own layout */
            float *nc[3] = {nx_, ny_, nz_}, *wc[3] = {a_, b_, c_}, *bc[2] = {bu_, bv_};
            const int wide = (int)(A->fast >> 6 & 1);
            columns(A->nrm, A->n0, A->n1, 3, q0, n, nc, wide);
            columns(A->wo, A->w0, A->w1, 3, q0, n, wc, wide);
            columns(A->bary, A->b0, A->b1, 2, q0, n, bc, wide);
        } else {
            for (int64_t i = 0; i < n; ++i) {      /* the G-buffer's rows, as columns */
                const int64_t q = q0 + i;
                nx_[i] = A->nrm[q * A->n0]; ny_[i] = A->nrm[q * A->n0 + A->n1]; nz_[i] = A->nrm[q * A->n0 + 2 * A->n1];
                a_[i] = A->wo[q * A->w0]; b_[i] = A->wo[q * A->w0 + A->w1]; c_[i] = A->wo[q * A->w0 + 2 * A->w1];
                bu_[i] = A->bary[q * A->b0]; bv_[i] = A->bary[q * A->b0 + A->b1];
            }
        }
        frame_cells(nx_, ny_, nz_, a_, b_, c_, n, h, top, top2, iu_, iv_, fu_, fv_, z_, (int)(A->fast >> 6 & 1));
        if ((A->fast & 128) && pe < p1)
            pf_block(A, pe * S2, ((pe + BLK < p1 ? pe + BLK : p1) - pe) * S2);
        for (int64_t p = pb; p < pe; ++p) {
            v4 o = {0, 0, 0, 0};
            for (int64_t t = 0; t < S2; ++t) {
                const int64_t i = (p - pb) * S2 + t, q = q0 + i;
                if (!A->live[q] || !(z_[i] > 0.0f))
                    continue;                       /* rho = 0 below the horizon */
                int64_t f = A->face[q];
                f = f < 0 ? 0 : (f >= A->M ? A->M - 1 : f);
                if (A->face_region[f] != A->region[q] && bad < 0)
                    bad = q;
                const int64_t iu = iu_[i], iv = iv_[i];
                const float fu = fu_[i], fv = fv_[i], gu = 1.0f - fu, gv = 1.0f - fv;
                const float w0 = gu * gv, w1 = fu * gv, w2 = gu * fv, w3 = fu * fv;
                const float bu = bu_[i], bv = bv_[i];
                const float beta[3] = {(1.0f - bu) - bv, bu, bv};
                v4 B = {0, 0, 0, 0};
#ifdef HAVE_DOTF
                if (A->fast & 4) {                          /* the cell's four X by `cell_x` */
                    int moved = 1;
                    if (!(A->fast & 8) || f != pf) {      /* bit 8: else the last sample's vertices, windows and, */
                        pf = f; wins = 0;                 /* in the same cell, X */
                        pg[0] = A->face_rows[3 * f]; pg[1] = A->face_rows[3 * f + 1]; pg[2] = A->face_rows[3 * f + 2];
                    } else {
                        moved = iu != piu || iv != piv;
                    }
                    piu = iu; piv = iv;
                    if (moved) {
                        if (yc) {                         /* bit 16: the (face, cell)'s entry of this thread's cache */
                            const int64_t key = f * R * R + iv * R + iu;
                            yent *e = yc + (int64_t)(((uint64_t)key * 0x9E3779B97F4A7C15ull) >> (64 - A->ylog));
                            if (e->gen != ygen || e->key != key) {
                                e->gen = ygen; e->key = key; e->have = 0;
                            }
                            px = e->x; hv = &e->have;
                        } else {
                            *hv = 0;
                        }
                    }
                    int32_t have = *hv;
                    for (int j = 0; j < 3; ++j) {
                        if (beta[j] == 0.0f)
                            continue;
                        v4 *x = px[j];
                        if (!(have >> j & 1)) {
                            have |= 1 << j;
                            const int64_t g = pg[j];
                            if (!(wins >> j & 1)) {
                                pr[j] = vertex_window(A, g);
                                wins |= 1 << j;
                            }
                            const int32_t *r = pr[j];
                            const int64_t s = r[3], dx = iu - r[1], dy = iv - r[2];
                            const int64_t K = A->Ks[s], node = iv * R + iu;
                            const float *t = (const float *)(intptr_t)A->shp[s] + node * 3 * K;
                            const float *cv = (const float *)(intptr_t)A->cp[s] + (g - A->voff[s]) * 3 * K;
                            if (dx >= 0 && dy >= 0 && dx <= W - 2 && dy <= W - 2) {
                                const int64_t row = g * WW + dy * W + dx;
                                int32_t *st = A->mstamp + row;
                                float *m = A->memo + 4 * row;
                                if (__builtin_expect(__atomic_load_n(st, __ATOMIC_ACQUIRE) != cur || __atomic_load_n(st + 1, __ATOMIC_ACQUIRE) != cur
                                                     || __atomic_load_n(st + W, __ATOMIC_ACQUIRE) != cur
                                                     || __atomic_load_n(st + W + 1, __ATOMIC_ACQUIRE) != cur, 0)) {
                                    /* all four rows (the same bits as any row already filled), from the registers */
                                    cell_x(t, R * 3 * K, cv, K, x, (int)(A->fast >> 5 & 1));
                                    memcpy(m, &x[0], 16); memcpy(m + 4, &x[1], 16); memcpy(m + 4 * W, &x[2], 16); memcpy(m + 4 * W + 4, &x[3], 16);
                                    __atomic_store_n(st, cur, __ATOMIC_RELEASE); __atomic_store_n(st + 1, cur, __ATOMIC_RELEASE);
                                    __atomic_store_n(st + W, cur, __ATOMIC_RELEASE); __atomic_store_n(st + W + 1, cur, __ATOMIC_RELEASE);
                                    made += 4;
                                } else {
                                    memcpy(&x[0], m, 16); memcpy(&x[1], m + 4, 16); memcpy(&x[2], m + 4 * W, 16); memcpy(&x[3], m + 4 * W + 4, 16);
                                }
                            } else {                        /* outside the window: the same four values, not kept */
                                cell_x(t, R * 3 * K, cv, K, x, (int)(A->fast >> 5 & 1));
                                ++exact;
                            }
                        }
                        B += ((x[0] * w0 + x[1] * w1) + (x[2] * w2 + x[3] * w3)) * beta[j];
                    }
                    *hv = have;
                    o += B;
                    continue;
                }
#endif
                for (int j = 0; j < 3; ++j) {
                    if (beta[j] == 0.0f)
                        continue;
                    const int64_t g = A->face_rows[3 * f + j];
                    const int32_t *r = vertex_window(A, g);
                    const int64_t s = r[3], dx = iu - r[1], dy = iv - r[2];
                    if (dx >= 0 && dy >= 0 && dx <= W - 2 && dy <= W - 2) {
                        const int64_t row = g * WW + dy * W + dx;
                        const int32_t *st = A->mstamp + row;
                        if (__builtin_expect(st[0] != cur || st[1] != cur || st[W] != cur || st[W + 1] != cur, 0)) {
                            const int64_t node = iv * R + iu;
                            memo_fill(A, g, s, row, node, &made);
                            memo_fill(A, g, s, row + 1, node + 1, &made);
                            memo_fill(A, g, s, row + W, node + R, &made);
                            memo_fill(A, g, s, row + W + 1, node + R + 1, &made);
                        }
                        __atomic_thread_fence(__ATOMIC_ACQUIRE);
                        v4 x0, x1, x2, x3;
                        const float *m = A->memo + 4 * row;
                        memcpy(&x0, m, 16); memcpy(&x1, m + 4, 16); memcpy(&x2, m + 4 * W, 16); memcpy(&x3, m + 4 * W + 4, 16);
                        B += ((x0 * w0 + x1 * w1) + (x2 * w2 + x3 * w3)) * beta[j];
                    } else {                                /* outside the window: the exact sum */
                        const int64_t K = A->Ks[s];
                        int64_t ce = iv * R + iu;
                        ce = ce < 0 ? 0 : (ce > cmax ? cmax : ce);
                        const float *sh = (const float *)(intptr_t)A->shp[s];
                        const float *cv = (const float *)(intptr_t)A->cp[s] + (g - A->voff[s]) * 3 * K;
                        v4 e = {0, 0, 0, 0};
#ifdef HAVE_DOTF
                        if (A->fast & 2) {
                            for (int64_t ch = 0; ch < 3; ++ch)
                                e[ch] = dot4f(sh + (ce * 3 + ch) * K, sh + ((ce + 1) * 3 + ch) * K, sh + ((ce + R) * 3 + ch) * K,
                                              sh + ((ce + R + 1) * 3 + ch) * K, w0, w1, w2, w3, cv + ch * K, K);
                        } else
#endif
                        for (int64_t ch = 0; ch < 3; ++ch)
                            e[ch] = dot4(sh + (ce * 3 + ch) * K, sh + ((ce + 1) * 3 + ch) * K, sh + ((ce + R) * 3 + ch) * K,
                                         sh + ((ce + R + 1) * 3 + ch) * K, w0, w1, w2, w3, cv + ch * K, K);
                        B += e * beta[j];
                        ++exact;
                    }
                }
                o += B;
            }
            const float is = 1.0f / (float)S2;
            out[3 * p] = o[0] * is; out[3 * p + 1] = o[1] * is; out[3 * p + 2] = o[2] * is;
        }
    }
    stats[0] = made; stats[1] = exact; stats[2] = bad;
}

#ifdef HAVE_DOTF
/* bit 256 (FMA builds, with 4): the pixels in tiles of A->tile, each in three passes over its samples'
   compact per-tile data (the memo, vertex records and stamps untouched):
   (1) resolve: the front end as above (the G-buffer along its layouts, `frame_cells`), then each shaded
       sample's (face, cell) key to an entry of the tile (the last sample's, else a tile-local hash
       table), the entry's vertices with a nonzero weight marked;
   (2) fill: the entries' (vertex, cell) needs grouped by vertex (a counting sort on tile-local vertex
       ids), each vertex's distinct cells by `cell_x` one after another (its c row read once a tile, from
       L1 after the first), a repeated cell's four X copied: each entry holds its 3 vertices' 4 X;
   (3) shade: each sample's B from its entry, the same sum in the same order as the loop above.
   X(v, n) is `cell_x`'s value of the pair whatever the path, so the image is the same bits as bits 4..128
   (and the same at any thread count: a tile is shaded by one thread). stats: rows computed = 4 per
   `cell_x` call, no entries outside a window. */
#ifndef PFV
#define PFV 2   /* bit 1024: vertices ahead whose c is prefetched */
#endif
#define TH_LOG 12   /* bit 256: log2 of the tile's (face, cell) hash slots (8 B each: 32 KB, L1-sized) */
/* a slot: (key + 1) << 16 | entry, 0 empty (keys < 2^47, entries < 2^16) */
typedef uint64_t tslot;
typedef struct { int64_t f, slot; int32_t node0, need; } tent;
typedef struct {
    int64_t cap_q, nv;
    int32_t *sent, *item_e, *item_lv, *sorted, *vtag, *vid, *vg, *vcnt, *vpos, *cn, *cidx, tag;
    int64_t rr;                 /* bit 512: per table node (R^2) its tag and slot; a vertex's nodes, their X */
    int32_t *ntag, *nslot, *nodes, ntg;
    v4 *xs;
    float *sw;
    tent *ent;
    v4 *ex;
    tslot *ht;
} tws;
static __thread tws tw;

static void *amalloc(size_t bytes) { return aligned_alloc(64, (bytes + 63) / 64 * 64); }

/* the calling thread's buffers for tiles of Q samples, nv vertices and rr table nodes (kept between calls;
   0 when one cannot be had: the caller takes `shade_range`) */
static int tws_ensure(int64_t Q, int64_t nv, int64_t rr) {
    if (tw.rr < rr || tw.ntg >= 0x7FFFFFF0) {
        free(tw.ntag); free(tw.nslot); free(tw.nodes); free(tw.xs);
        tw.ntag = (int32_t *)calloc(rr, 4); tw.nslot = (int32_t *)calloc(rr, 4);
        tw.nodes = (int32_t *)malloc((rr + 4) * 4); tw.xs = (v4 *)amalloc((size_t)(rr + 4) * sizeof(v4));
        tw.rr = 0; tw.ntg = 0;
        if (!tw.ntag || !tw.nslot || !tw.nodes || !tw.xs)
            return 0;
        tw.rr = rr;
    }
    if (tw.cap_q < Q) {
        const int64_t E = Q < ((int64_t)1 << (TH_LOG - 1)) ? Q : ((int64_t)1 << (TH_LOG - 1));   /* entries */
        free(tw.sent); free(tw.item_e); free(tw.item_lv); free(tw.sorted); free(tw.vg); free(tw.vcnt);
        free(tw.vpos); free(tw.cn); free(tw.cidx); free(tw.sw); free(tw.ent); free(tw.ex); free(tw.ht);
        tw.sent = (int32_t *)malloc(Q * 4); tw.sw = (float *)malloc(Q * 16);
        tw.item_e = (int32_t *)malloc(3 * E * 4); tw.item_lv = (int32_t *)malloc(3 * E * 4);
        tw.sorted = (int32_t *)malloc(3 * E * 4); tw.vg = (int32_t *)malloc(3 * E * 4);
        tw.vcnt = (int32_t *)malloc(3 * E * 4); tw.vpos = (int32_t *)malloc((3 * E + 1) * 4);
        tw.cn = (int32_t *)malloc(3 * E * 4); tw.cidx = (int32_t *)malloc(3 * E * 4);
        tw.ent = (tent *)malloc(E * sizeof(tent));
        tw.ex = (v4 *)amalloc((size_t)E * 12 * sizeof(v4));
        tw.ht = (tslot *)amalloc(sizeof(tslot) << TH_LOG);
        tw.cap_q = 0;
        if (!tw.sent || !tw.sw || !tw.item_e || !tw.item_lv || !tw.sorted || !tw.vg || !tw.vcnt || !tw.vpos || !tw.cn
            || !tw.cidx || !tw.ent || !tw.ex || !tw.ht)
            return 0;
        memset(tw.ht, 0, sizeof(tslot) << TH_LOG);
        tw.cap_q = Q;
    }
    if (tw.nv < nv || tw.tag >= 0x7FFFFFF0) {
        free(tw.vtag); free(tw.vid);
        tw.vtag = (int32_t *)calloc(nv, 4); tw.vid = (int32_t *)malloc(nv * 4);
        tw.nv = 0; tw.tag = 0;
        if (!tw.vtag || !tw.vid)
            return 0;
        tw.nv = nv;
    }
    return 1;
}

/* the tile from pixel p0 up to p1, closed early after a block that leaves fewer than a block's samples of
   free entries below half the hash's slots; returns the pixel after its last */
static int64_t shade_tile(const Args *A, int64_t p0, int64_t p1, float *out, int64_t *made_, int64_t *bad_) {
    const int64_t R = A->R, S2 = A->S2, RR = R * R, hl = TH_LOG, hmask = ((int64_t)1 << hl) - 1;
    const int64_t E = tw.cap_q < ((int64_t)1 << (hl - 1)) ? tw.cap_q : ((int64_t)1 << (hl - 1));
    const int32_t emax = (int32_t)(E - BLK * S2);   /* a block adds at most BLK * S2 entries */
    const float h = 0.5f * (float)(R - 1), top = (float)(R - 1), top2 = (float)(R - 2);
    const int tree = (int)(A->fast >> 5 & 1), wide = (int)(A->fast >> 6 & 1);
    int32_t *sent = tw.sent;
    float *sw = tw.sw;
    tent *ent = tw.ent;
    tslot *ht = tw.ht;
    v4 *ex = tw.ex;
    int64_t made = 0, bad = *bad_, lastkey = -1;
    int32_t nE = 0, laste = -1;
    float nx_[BLK * 8 + 16], ny_[BLK * 8 + 16], nz_[BLK * 8 + 16], a_[BLK * 8 + 16], b_[BLK * 8 + 16], c_[BLK * 8 + 16];
    float bu_[BLK * 8], bv_[BLK * 8], fu_[BLK * 8 + 16], fv_[BLK * 8 + 16], z_[BLK * 8 + 16];
    int32_t iu_[BLK * 8 + 16], iv_[BLK * 8 + 16];
    memset(nx_, 0, sizeof nx_); memset(ny_, 0, sizeof ny_); memset(nz_, 0, sizeof nz_);
    memset(a_, 0, sizeof a_); memset(b_, 0, sizeof b_); memset(c_, 0, sizeof c_);
    /* (1) resolve */
    int64_t pend = p0;
    for (int64_t pb = p0; pb < p1 && (pb == p0 || nE <= emax); pb += BLK) {
        const int64_t pe = pb + BLK < p1 ? pb + BLK : p1, q0 = pb * S2, n = (pe - pb) * S2;
        if (A->fast & 1) {
            float *nc[3] = {nx_, ny_, nz_}, *wc[3] = {a_, b_, c_}, *bc[2] = {bu_, bv_};
            columns(A->nrm, A->n0, A->n1, 3, q0, n, nc, wide);
            columns(A->wo, A->w0, A->w1, 3, q0, n, wc, wide);
            columns(A->bary, A->b0, A->b1, 2, q0, n, bc, wide);
        } else {
            for (int64_t i = 0; i < n; ++i) {
                const int64_t q = q0 + i;
                nx_[i] = A->nrm[q * A->n0]; ny_[i] = A->nrm[q * A->n0 + A->n1]; nz_[i] = A->nrm[q * A->n0 + 2 * A->n1];
                a_[i] = A->wo[q * A->w0]; b_[i] = A->wo[q * A->w0 + A->w1]; c_[i] = A->wo[q * A->w0 + 2 * A->w1];
                bu_[i] = A->bary[q * A->b0]; bv_[i] = A->bary[q * A->b0 + A->b1];
            }
        }
        frame_cells(nx_, ny_, nz_, a_, b_, c_, n, h, top, top2, iu_, iv_, fu_, fv_, z_, wide);
        if ((A->fast & 128) && pe < p1)
            pf_block(A, pe * S2, ((pe + BLK < p1 ? pe + BLK : p1) - pe) * S2);
        pend = pe;
        for (int64_t i = 0; i < n; ++i) {
            const int64_t q = q0 + i, qi = q - p0 * S2;
            if (!A->live[q] || !(z_[i] > 0.0f)) {
                sent[qi] = -1;
                continue;
            }
            int64_t f = A->face[q];
            f = f < 0 ? 0 : (f >= A->M ? A->M - 1 : f);
            if (A->face_region[f] != A->region[q] && bad < 0)
                bad = q;
            const int64_t node0 = (int64_t)iv_[i] * R + iu_[i], key = f * RR + node0;
            int32_t e;
            if (key == lastkey) {
                e = laste;
            } else {
                int64_t hs = (int64_t)(((uint64_t)key * 0x9E3779B97F4A7C15ull) >> (64 - hl));
                const uint64_t kk = (uint64_t)(key + 1) << 16;
                for (;;) {
                    const uint64_t v = ht[hs];
                    if ((v & ~(uint64_t)0xFFFF) == kk) {
                        e = (int32_t)(v & 0xFFFF);
                        break;
                    }
                    if (v == 0) {
                        e = nE++;
                        ht[hs] = kk | (uint64_t)e;
                        ent[e].f = f; ent[e].slot = hs; ent[e].node0 = (int32_t)node0; ent[e].need = 0;
                        break;
                    }
                    hs = (hs + 1) & hmask;
                }
                lastkey = key; laste = e;
            }
            const float bu = bu_[i], bv = bv_[i];
            float *w = sw + 4 * qi;
            w[0] = fu_[i]; w[1] = fv_[i]; w[2] = bu; w[3] = bv;
            ent[e].need |= (((1.0f - bu) - bv) != 0.0f) | ((bu != 0.0f) << 1) | ((bv != 0.0f) << 2);
            sent[qi] = e;
        }
    }
    for (int32_t e = 0; e < nE; ++e)
        ht[ent[e].slot] = 0;
    /* (2) fill: needs grouped by vertex */
    const int32_t tag = ++tw.tag;
    int32_t *vtag = tw.vtag, *vid = tw.vid, *vg = tw.vg, *vcnt = tw.vcnt, *vpos = tw.vpos;
    int32_t *item_e = tw.item_e, *item_lv = tw.item_lv, *sorted = tw.sorted, *cn = tw.cn, *cidx = tw.cidx;
    int32_t nL = 0, nI = 0;
    for (int32_t e = 0; e < nE; ++e) {
        const int32_t need = ent[e].need;
        const int32_t *fr = A->face_rows + 3 * ent[e].f;
        for (int j = 0; j < 3; ++j) {
            if (!(need >> j & 1))
                continue;
            const int32_t g = fr[j];
            if (vtag[g] != tag) {
                vtag[g] = tag; vid[g] = nL; vg[nL] = g; vcnt[nL] = 0; ++nL;
            }
            const int32_t lv = vid[g];
            ++vcnt[lv];
            item_e[nI] = 3 * e + j; item_lv[nI] = lv; ++nI;
        }
    }
    vpos[0] = 0;
    for (int32_t l = 0; l < nL; ++l) {
        vpos[l + 1] = vpos[l] + vcnt[l];
        vcnt[l] = vpos[l];
    }
    for (int32_t it = 0; it < nI; ++it)
        sorted[vcnt[item_lv[it]]++] = item_e[it];
    for (int32_t l = 0; l < nL; ++l) {
        const int64_t g = vg[l];
        int64_t s = 0;
        while (s + 1 < A->S && g >= A->voff[s + 1]) ++s;
        const int64_t K = A->Ks[s];
        const float *sh = (const float *)(intptr_t)A->shp[s];
        const float *cv = (const float *)(intptr_t)A->cp[s] + (g - A->voff[s]) * 3 * K;
        if ((A->fast & 1024) && l + PFV < nL) {      /* bit 1024: a later vertex's c requested */
            const int64_t g2 = vg[l + PFV];
            int64_t s2 = 0;
            while (s2 + 1 < A->S && g2 >= A->voff[s2 + 1]) ++s2;
            pf_range((const float *)(intptr_t)A->cp[s2] + (g2 - A->voff[s2]) * 3 * A->Ks[s2], 3 * A->Ks[s2] * 4);
        }
        if (A->fast & 512) {                /* the vertex's distinct nodes, four at a time */
            const int32_t vt = ++tw.ntg;
            int32_t *ntag = tw.ntag, *nslot = tw.nslot, *nodes = tw.nodes, nN = 0;
            const int32_t d[4] = {0, 1, (int32_t)R, (int32_t)R + 1};
            for (int32_t it = vpos[l]; it < vpos[l + 1]; ++it) {
                const int32_t node0 = ent[sorted[it] / 3].node0;
                if (A->fast & 2048) {       /* bit 2048: the same, without branches */
                    for (int k = 0; k < 4; ++k) {
                        const int32_t nd = node0 + d[k], fresh = ntag[nd] != vt;
                        const int32_t sl = nslot[nd];
                        ntag[nd] = vt; nodes[nN] = nd; nslot[nd] = fresh ? nN : sl; nN += fresh;
                    }
                    continue;
                }
                for (int k = 0; k < 4; ++k) {
                    const int32_t nd = node0 + d[k];
                    if (ntag[nd] != vt) {
                        ntag[nd] = vt; nslot[nd] = nN; nodes[nN++] = nd;
                    }
                }
            }
            v4 *xs = tw.xs;
            const int64_t K3 = 3 * K;
            made += nN;
            for (int32_t b = nN; b & 3; ++b)
                nodes[b] = nodes[nN - 1];
            for (int32_t b = 0; b < nN; b += 4)
                rows_x(sh + nodes[b] * K3, sh + nodes[b + 1] * K3, sh + nodes[b + 2] * K3, sh + nodes[b + 3] * K3, cv, K,
                       xs + b, tree);
            for (int32_t it = vpos[l]; it < vpos[l + 1]; ++it) {
                const int32_t ej = sorted[it], node0 = ent[ej / 3].node0;
                v4 *x = ex + 12 * (ej / 3) + 4 * (ej % 3);
                x[0] = xs[nslot[node0]]; x[1] = xs[nslot[node0 + 1]];
                x[2] = xs[nslot[node0 + R]]; x[3] = xs[nslot[node0 + R + 1]];
            }
            continue;
        }
        int32_t nc = 0;
        for (int32_t it = vpos[l]; it < vpos[l + 1]; ++it) {
            const int32_t ej = sorted[it], e = ej / 3, j = ej - 3 * e, node0 = ent[e].node0, xo = 12 * e + 4 * j;
            int32_t c = 0;
            while (c < nc && cn[c] != node0) ++c;
            if (c < nc) {
                memcpy(ex + xo, ex + cidx[c], 4 * sizeof(v4));
            } else {
                cell_x(sh + node0 * 3 * K, R * 3 * K, cv, K, ex + xo, tree);
                cn[nc] = node0; cidx[nc] = xo; ++nc;
                made += 4;
            }
        }
    }
    /* (3) shade */
    const float is = 1.0f / (float)S2;
    int64_t p = p0;
#ifdef __AVX512F__
    if ((A->fast & 65536) && S2 == 4) {
        /* bit 65536 (AVX-512 builds, 2 x 2 samples): a pixel's four samples at once, sample t in lanes
           4t .. 4t + 3 (its X channels), the loop's operations lane for lane (the weights from each
           sample's (fu, fv, bu, bv) broadcast in its lanes; a term with beta_j = 0 or a dead sample's
           masked, as the loop skips it), then o = (((0 + B_0) + B_1) + B_2) + B_3 in order: a skipped
           sample adds +0, which leaves o as it is (o is never -0: it starts at +0), so the same bits */
        const __m512 one = _mm512_set1_ps(1.0f), zero = _mm512_setzero_ps();
        for (; p < pend; ++p) {
            const int64_t qi = (p - p0) * 4;
            const int32_t *se = sent + qi;
            __mmask16 live = 0;
            const v4 *xe[4];
            for (int t = 0; t < 4; ++t) {
                const int32_t e = se[t];
                xe[t] = ex + 12 * (e < 0 ? 0 : e);
                live |= (__mmask16)(e >= 0 ? 0xF << (4 * t) : 0);
            }
            if (!live) {                  /* no sample shaded: the loop's 0 * is */
                out[3 * p] = 0.0f * is; out[3 * p + 1] = 0.0f * is; out[3 * p + 2] = 0.0f * is;
                continue;
            }
            const __m512 w = _mm512_loadu_ps(sw + 4 * qi);
            const __m512 fu = _mm512_permute_ps(w, 0x00), fv = _mm512_permute_ps(w, 0x55);
            const __m512 bu = _mm512_permute_ps(w, 0xAA), bv = _mm512_permute_ps(w, 0xFF);
            const __m512 gu = _mm512_sub_ps(one, fu), gv = _mm512_sub_ps(one, fv);
            const __m512 w0 = _mm512_mul_ps(gu, gv), w1 = _mm512_mul_ps(fu, gv), w2 = _mm512_mul_ps(gu, fv),
                         w3 = _mm512_mul_ps(fu, fv);
            const __m512 beta[3] = {_mm512_sub_ps(_mm512_sub_ps(one, bu), bv), bu, bv};
            __m512 B = zero;
            for (int j = 0; j < 3; ++j) {
                const __mmask16 m = live & (__mmask16)~_mm512_cmp_ps_mask(beta[j], zero, _CMP_EQ_OQ);
                if (!m)
                    continue;
                __m512 y[4];
                for (int n = 0; n < 4; ++n) {
                    __m512 v = _mm512_castps128_ps512(_mm_loadu_ps((const float *)(xe[0] + 4 * j + n)));
                    v = _mm512_insertf32x4(v, _mm_loadu_ps((const float *)(xe[1] + 4 * j + n)), 1);
                    v = _mm512_insertf32x4(v, _mm_loadu_ps((const float *)(xe[2] + 4 * j + n)), 2);
                    y[n] = _mm512_insertf32x4(v, _mm_loadu_ps((const float *)(xe[3] + 4 * j + n)), 3);
                }
                const __m512 term = _mm512_mul_ps(_mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(y[0], w0), _mm512_mul_ps(y[1], w1)),
                                                                _mm512_add_ps(_mm512_mul_ps(y[2], w2), _mm512_mul_ps(y[3], w3))),
                                                  beta[j]);
                B = _mm512_mask_add_ps(B, m, B, term);
            }
            __m128 o = _mm_add_ps(_mm_setzero_ps(), _mm512_castps512_ps128(B));
            o = _mm_add_ps(o, _mm512_extractf32x4_ps(B, 1));
            o = _mm_add_ps(o, _mm512_extractf32x4_ps(B, 2));
            o = _mm_add_ps(o, _mm512_extractf32x4_ps(B, 3));
            o = _mm_mul_ps(o, _mm_set1_ps(is));
            float r[4];
            _mm_storeu_ps(r, o);
            out[3 * p] = r[0]; out[3 * p + 1] = r[1]; out[3 * p + 2] = r[2];
        }
    }
#endif
    for (; p < pend; ++p) {
        v4 o = {0, 0, 0, 0};
        for (int64_t t = 0; t < S2; ++t) {
            const int64_t qi = (p - p0) * S2 + t;
            const int32_t e = sent[qi];
            if (e < 0)
                continue;
            const float *w = sw + 4 * qi;
            const float fu = w[0], fv = w[1], gu = 1.0f - fu, gv = 1.0f - fv;
            const float w0 = gu * gv, w1 = fu * gv, w2 = gu * fv, w3 = fu * fv;
            const float bu = w[2], bv = w[3];
            const float beta[3] = {(1.0f - bu) - bv, bu, bv};
            const v4 *x = ex + 12 * e;
            v4 B = {0, 0, 0, 0};
            for (int j = 0; j < 3; ++j) {
                if (beta[j] == 0.0f)
                    continue;
                const v4 *y = x + 4 * j;
                B += ((y[0] * w0 + y[1] * w1) + (y[2] * w2 + y[3] * w3)) * beta[j];
            }
            o += B;
        }
        out[3 * p] = o[0] * is; out[3 * p + 1] = o[1] * is; out[3 * p + 2] = o[2] * is;
    }
    *made_ += made;
    *bad_ = bad;
    return pend;
}

/* bit 256: the range's pixels tile by tile (falls back to `shade_range` when its buffers cannot be had) */
static void shade_tiles(const Args *A, int64_t p0, int64_t p1, float *out, int64_t *stats, uint64_t ygen) {
    const int64_t T = A->tile > 0 ? A->tile : 1024;
    if (A->S2 > 8 || A->M * A->R * A->R >= ((int64_t)1 << 47) || !tws_ensure(T * A->S2, A->voff[A->S], A->R * A->R)) {
        shade_range(A, p0, p1, out, stats, ygen);
        return;
    }
    int64_t made = 0, bad = -1;
    for (int64_t t0 = p0; t0 < p1;)
        t0 = shade_tile(A, t0, t0 + T < p1 ? t0 + T : p1, out, &made, &bad);
    stats[0] = made; stats[1] = 0; stats[2] = bad;
}

#endif

/* o[0] = 1 when bits 4 and 8 of `fast` run (`cell_x`: an FMA build), else 0 (they fall back to the
   per-row loop of bits 1 and 2) */
void have_cells(int64_t *o) {
#ifdef HAVE_DOTF
    o[0] = 1;
#else
    o[0] = 0;
#endif
}

/* Eq. 4 at the npx * S2 samples (pixel-major, S2 <= 8), box-filtered into out (npx, 3). stats (nt, 3):
   per thread the memo rows computed, the entries summed exactly, the first sample whose face lies in
   another region than the sample's (-1: none). With nt > 1 the pixels go to the team in chunks of
   A->chunk, each to the next free thread (the image's cost is uneven: a static split in halves left one
   thread ~10 % longer busy on the chess bench); a pixel is still summed by one thread in one order,
   and a memo row's value is its (vertex, node) pair's whichever thread fills it, so the image and the
   memo are the same bits whatever the schedule. */
void shade(const Args *A, int64_t npx, float *out, int64_t *stats, int64_t nt) {
#ifdef HAVE_DOTF
#define RANGE(...) ((A->fast & 260) == 260 ? shade_tiles(__VA_ARGS__) : shade_range(__VA_ARGS__))
#else
#define RANGE(...) shade_range(__VA_ARGS__)
#endif
    const uint64_t ygen = __atomic_add_fetch(&ygen_all, 1, __ATOMIC_RELAXED);
    for (int64_t t = 0; t < nt; ++t) {
        stats[3 * t] = 0; stats[3 * t + 1] = 0; stats[3 * t + 2] = -1;
    }
    if (nt <= 1 || A->chunk < 1) {
        RANGE(A, 0, npx, out, stats, ygen);
        return;
    }
    const int64_t C = A->chunk, nch = (npx + C - 1) / C;
    #pragma omp parallel for num_threads(nt) schedule(dynamic, 1)
    for (int64_t c = 0; c < nch; ++c) {
        int64_t got[3];
        RANGE(A, c * C, (c + 1) * C < npx ? (c + 1) * C : npx, out, got, ygen);
        int64_t *st = stats + 3 * omp_get_thread_num();
        st[0] += got[0]; st[1] += got[1];
        if (got[2] >= 0 && (st[2] < 0 || got[2] < st[2]))
            st[2] = got[2];
    }
}
"""


class _Args(ctypes.Structure):
    _fields_ = [("nrm", ctypes.c_void_p), ("n0", ctypes.c_int64), ("n1", ctypes.c_int64),
                ("wo", ctypes.c_void_p), ("w0", ctypes.c_int64), ("w1", ctypes.c_int64),
                ("bary", ctypes.c_void_p), ("b0", ctypes.c_int64), ("b1", ctypes.c_int64),
                ("face", ctypes.c_void_p), ("region", ctypes.c_void_p), ("live", ctypes.c_void_p),
                ("face_rows", ctypes.c_void_p), ("face_region", ctypes.c_void_p), ("M", ctypes.c_int64),
                ("voff", ctypes.c_void_p), ("S", ctypes.c_int64),
                ("shp", ctypes.c_void_p), ("cp", ctypes.c_void_p), ("Ks", ctypes.c_void_p),
                ("pos", ctypes.c_void_p), ("frames", ctypes.c_void_p), ("cam", ctypes.c_void_p),
                ("R", ctypes.c_int64), ("W", ctypes.c_int64), ("S2", ctypes.c_int64), ("stamp", ctypes.c_int64),
                ("chunk", ctypes.c_int64), ("fast", ctypes.c_int64),
                ("vrec", ctypes.c_void_p), ("memo", ctypes.c_void_p), ("mstamp", ctypes.c_void_p),
                ("ylog", ctypes.c_int64), ("tile", ctypes.c_int64)]


_P, _I = ctypes.c_void_p, ctypes.c_int64
_SIGNATURES = {"shade": [_P, _I, _P, _P, _I], "have_cells": [_P]}
# Pixels below which one thread shades the frame (a hand-off costs more than its share).
MIN_PER_THREAD = 1024
# Pixels per chunk of the dynamic schedule at 2+ threads (16 blocks of 64; the chess bench has 64 chunks).
# The static halves it replaces: on the chess bench the second half's thread took 1.02-1.16x (median
# ~1.07x) the CPU time of the mean of the two (8 frames), the frame waiting for it. The C loop alone,
# old and new alternating in one process at 2 threads on a loaded machine: chess wall 1.12-1.23x (CPU
# 1.05-1.17x), creature wall 1.04x (CPU 1.06x); chunks of 512 / 2048 pixels read 1.14x / 1.08-1.32x.
CHUNK = 1024
# What the loop does beyond session 29's (bits; 0: that loop, the same values bit for bit — the test
# oracle of the others): 1 each G-buffer array read along its own layout (column runs copied, row-major
# (q, 3) rows split; the same values), 2 the dot products by fused multiply-adds, 16 lanes wide on an
# AVX-512 build (`dotf`, `dot4f`: other roundings, float32 round-off). Chess bench V, 1 thread, process
# CPU, same process alternating: 3 against 0 1.08x (the table rows' and memo's misses bound the rest).
# 4 (FMA builds) the memo's fills and the entries outside the window by `cell_x` (a pair's X the same
# bits on every path; other roundings than bit 2's per-row sums), 8 (with 4) the last shaded sample's
# vertices, windows and, in the same cell, X reused (the same bits as 4 alone). V frames, 1 thread,
# process CPU, against bc5fbe4 (``python -m benchmarks.inout --base B --scene chess|creature --kinds V
# --frames 15 --threads 1 --no-micro``, host at load 5-10): chess 1.05-1.16x, creature 1.23x; the loop
# alone (15 against 3, same process, alternating, after 0.2 s idle) chess 1.16x, and 1.17-1.19x in a
# standalone C driver of the loop over a dumped chess frame (caches flushed or not alike).
# 16 (with 4 and 8) each thread's cache of (face, cell) entries (`YCACHE_LOG`; the same bits as 4 | 8).
# 32 (AVX-512 builds, with 4) `cell_x`'s 12 sums reduced at once by transposing shuffles (`x4_sums`: the
# same pairs as `hsum16`, the same bits). Loop alone, 1 thread, process CPU, each call after the frame's
# G-buffer was rasterised, 21 frames alternating, 63 against 15: chess 1.12x, creature 1.10x.
# 64 (AVX-512 builds) the front end 16 samples wide: the row-major normals split 16 rows at a time by
# permutes, `frame_cells` 16 samples at a time (the AVX2 loop's operations one for one: the same bits).
# 128 the next block's G-buffer rows prefetched into L2 while a block is shaded (no value changes).
# Session 35, 1 thread, process CPU, each call after a fresh rasterisation, 41 frames alternating
# (``python -m benchmarks.inout_loop_ab --scene chess|creature --threads 1 --frames 41 --cold
# --variants 63 255``, host at load 5-12): 255 against 63 chess 1.024x (per frame 1.025x), creature
# 1.019x (per frame 1.026x); the front end alone (no live sample) 1.07x with 64 (2.19 -> 2.04 ms).
# 256 (FMA builds, with 4) the pixels in tiles (`shade_tile`: resolve, fill, shade; no memo), 512 (with 256)
# a vertex's distinct nodes four at a time (`rows_x`) instead of its distinct cells, 1024 (with 256) a later
# vertex's c prefetched; the same bits as 4..128. Session 37, 1 thread, process CPU, each call after a fresh
# rasterisation, alternating (``python -m benchmarks.inout_loop_ab --scene chess|creature --threads 1
# --frames 11 --cold --variants 255 2047``, host at load 6-8): chess 1.21x (per frame 1.22x), creature
# 1.22x (per frame 1.24x); at 2 threads chess 1.45x (per frame 1.42x, load 10). Whole V frames against the
# base checkout (``python -m benchmarks.inout --base B --scene chess|creature --kinds V --frames 15
# --threads 1|2 --no-micro``, process CPU, load 7-10): chess 1.18x / 1.01x, creature 1.12x / 1.07x at 1 / 2
# threads; max |d| 0 (the same bits).
# 2048 (with 512) a vertex's distinct nodes tagged without branches (the tag, slot and node list written
# whether the node is new or not, the count advanced by the test's 0 / 1; the same nodes in the same order, so
# the same bits): perf put ~14 % of a chess bench V call in the branchy form (its new-or-not branch is
# data-dependent). Session 39, 1 thread, process CPU, each call after a fresh rasterisation, 21 frames
# alternating (``python -m benchmarks.inout_loop_ab --scene chess|creature --frames 21 --cold --variants 2047
# 4095 2047: --precompute-code BASE``, host at load 3-8): chess 1.053x (per frame 1.061x), creature 1.042x
# (per frame 1.036x); A/A (2047 against 2047:) 0.998x / 1.009x. Whole V frames against the base checkout
# (``python -m benchmarks.inout --base B --scene chess|creature --kinds V --threads 1 --frames 21 --no-micro``,
# with the torch ops trimmed around the loop): CPU chess 1.07x, creature 1.05x; max |d| 0.
# (4096, 8192, 16384 and 32768: the edits of ``benchmarks.inout_nodemajor_ab``, session 42.)
# (131072: the frame vertex-major, `shade_vm`, session 44: 0.83-0.89x, not merged; branch ip44, module docstring.)
# 65536 (AVX-512 builds, with 256, 2 x 2 samples) the tile's shade pass a pixel's four samples per vector (the
# loop's operations lane for lane, a skipped term or sample masked; the same bits). Session 44, 1 thread,
# process CPU, each call after a fresh rasterisation, 21 frames alternating (``python -m
# benchmarks.inout_loop_ab --scene chess|creature --frames 21 --cold --variants 4095 69631 4095:``, host at
# load ~1-2): chess 1.072x (per frame 1.094x), creature 1.072x (per frame 1.078x); A/A 1.002x / 0.994x.
FAST = 69631
# log2 of the entries of each thread's (face, cell) cache (bit 16 of `FAST`)
YCACHE_LOG = 10
# pixels per tile of bit 256 (at 2+ threads a chunk, `CHUNK`, is cut into tiles of this many)
TILE = 2048


_LOADED: list = []      # the library once loaded (`_lib`)


def load_remembered(loaded: list, name: str, source: str, signatures: dict, flags) -> ctypes.CDLL | None:
    """`native.load`(name, source, signatures, extra_flags=flags()) remembered in ``loaded`` once it loaded,
    or None. PRTBENCH_COMPILE is read at each call, so a None met while compilation was off (a test's
    monkeypatch) is not kept for the process; a loaded library is one look-up afterwards (`native.load`'s
    own cache costs ~50 us a frame with the caches cold: its key tuples and the flags' queries);
    ``native.cache_clear`` does not forget it (the same file). `compile_enabled` reads the variable by one
    look-up in ``os.environ``'s mapping (`methods.core.switches`, session 43; session 41 had that look-up
    here as ``compile_unset``)."""
    if not compile_enabled():
        return None
    if loaded:
        return loaded[0]
    lib = native.load(name, source, signatures, extra_flags=flags())
    if lib is not None:
        loaded.append(lib)
    return lib


def _lib():
    return load_remembered(_LOADED, "inout_sample", _SOURCE, _SIGNATURES, _flags)


# AVX-512 where torch found the CPU to have it (the dot products 16 lanes wide, `dotf`, `dot4f`)
AVX512_FLAGS = ("-mavx512f", "-mavx512dq", "-mavx512vl", "-mavx512bw")


def _flags() -> tuple[str, ...]:
    isa = native.isa_flags()
    if native.cpu_capability() == "AVX512":
        isa = (*isa, *AVX512_FLAGS)
    return ("-fopenmp", "-ffp-contract=off", *isa)


def available() -> bool:
    """True when the C loop runs (else the caller takes ``fast.prepare`` and ``fast.shade_pixels``)."""
    return _lib() is not None


def cells_available() -> bool:
    """True when the loop's bits 4 and 8 run (`FAST`: the C loop built with FMA), else they fall back
    to the per-row memo and the exact path's weighted sums (bits 1 and 2)."""
    lib = _lib()
    if lib is None:
        return False
    o = torch.zeros(1, dtype=torch.int64)
    lib.have_cells(o.data_ptr())
    return bool(o[0])


def memo(nv: int, W: int) -> tuple[Tensor, Tensor, Tensor]:
    """A zeroed memo for ``nv`` concatenated vertices: (vrec (nv, 4) int32, rows (nv·W², 4) float32,
    their stamps (nv·W²,) int32)."""
    return (torch.zeros(nv, 4, dtype=torch.int32), torch.zeros(nv * W * W, 4, dtype=torch.float32),
            torch.zeros(nv * W * W, dtype=torch.int32))


class Bound:
    """`shade`'s arguments that do not change between frames — the scene's arrays of ``st``, the slots'
    tables and c, the memo, W — checked and packed once (`bind`) into the loop's argument struct;
    `frame` checks the G-buffer's arrays, writes their pointers and the frame's numbers into it and runs
    one frame. Each torch op and attribute read around the loop runs with the loop's cold caches: the
    per-frame checks of ~20 static arrays, the camera as a tensor, the stats tensor and its ``tolist``
    and the image's view cost a chess bench V frame ~0.2 ms of serial Python (1 thread)."""

    __slots__ = ("st", "cs", "mem", "W", "lib", "fn", "args", "meta", "cam", "stats")

    def fits(self, st, cs: list[Tensor], mem, W: int, lib) -> bool:
        """True when bound to these very objects (the tensors' identity: their storage is not replaced
        in place anywhere in `InOut`) and window."""
        return (self.st is st and self.mem is mem and self.W == W and self.lib is lib and len(cs) == len(self.cs)
                and all(a is b for a, b in zip(cs, self.cs)))

    def frame(self, normal: Tensor, wo: Tensor, bary: Tensor, face: Tensor, region: Tensor, live: Tensor, S2: int,
              origin, stamp: int, shape: tuple[int, ...] | None = None):
        """`shade` with the camera position ``origin`` (3 numbers, taken as float32) and the image
        allocated as ``shape`` (default (n, 3); n·3 elements)."""
        q = int(face.shape[0])
        if (normal.dtype != torch.float32 or wo.dtype != torch.float32 or bary.dtype != torch.float32
                or face.dtype != torch.int64 or region.dtype != torch.int64 or live.dtype != torch.bool
                or normal.shape != (q, 3) or wo.shape != (q, 3) or bary.shape != (q, 2) or face.shape != (q,)
                or region.shape != (q,) or live.shape != (q,)
                or not (normal.is_cpu and wo.is_cpu and bary.is_cpu and face.is_cpu and region.is_cpu and live.is_cpu)
                or not (face.is_contiguous() and region.is_contiguous() and live.is_contiguous())
                or q % S2 or not 1 <= S2 <= 8 or not 0 < stamp < 2 ** 31 or len(origin) != 3):
            return None
        npx = q // S2
        out = torch.empty(shape if shape is not None else (npx, 3), dtype=torch.float32)
        if out.numel() != 3 * npx:
            return None
        nt = max(1, min(torch.get_num_threads(), npx // MIN_PER_THREAD))
        if len(self.stats) < 3 * nt:
            self.stats = (ctypes.c_int64 * (3 * nt))()
        a = self.args
        a.nrm, (a.n0, a.n1) = normal.data_ptr(), normal.stride()
        a.wo, (a.w0, a.w1) = wo.data_ptr(), wo.stride()
        a.bary, (a.b0, a.b1) = bary.data_ptr(), bary.stride()
        a.face, a.region, a.live = face.data_ptr(), region.data_ptr(), live.data_ptr()
        a.S2, a.stamp, a.chunk, a.fast, a.ylog, a.tile = S2, stamp, TILE if FAST & 256 else CHUNK, int(FAST), YCACHE_LOG, TILE
        self.cam[0], self.cam[1], self.cam[2] = origin      # float32 as torch.tensor(origin, dtype=torch.float32)
        st = self.stats
        self.fn(ctypes.byref(a), npx, out.data_ptr(), ctypes.addressof(st), nt)
        rows = st[:3 * nt]                                   # the loop sets every thread's row first
        bad = [b for b in rows[2::3] if b >= 0]
        return out, (sum(rows[0::3]), sum(rows[1::3]), min(bad) if bad else -1)

    def __deepcopy__(self, memo):
        return None    # a deep copy of its owner binds its own call (the library's functions do not copy)


def bind(st, cs: list[Tensor], mem: tuple[Tensor, Tensor, Tensor], W: int, lib=None) -> Bound | None:
    """A `Bound` call for ``st`` (the ``fast.FastStatic``), cs[s] (Vr_s, 3, K_s) float32 the c of slot s,
    ``mem`` a `memo` of ``st``'s vertices for window ``W``, or None when the loop is not available or
    the arrays are not CPU tensors of those types and shapes (the caller runs the compiled path).
    ``lib``: the library as `_lib` gave it to the caller (else looked up here)."""
    lib = _lib() if lib is None else lib
    if lib is None:
        return None
    vrec, rows, mst = mem
    nv = st.voff[-1]
    ts = (st.face_rows, st.face_region, st.pos, st.frames, vrec, rows, mst, *cs, *(fr.sh_nc for fr in st.regions))
    if (any(t.device.type != "cpu" or not t.is_contiguous() for t in ts)
            or not all(c.dtype == torch.float32 and c.dim() == 3 and c.shape[1] == 3 for c in cs)
            or not all(fr.sh_nc.dtype == torch.float32 for fr in st.regions)
            or st.face_rows.dtype != torch.int32 or st.face_region.dtype != torch.int64
            or st.pos.dtype != torch.float32 or st.frames.dtype != torch.float32
            or vrec.shape != (nv, 4) or rows.shape != (nv * W * W, 4) or mst.shape != (nv * W * W,) or st.R < W or W < 2
            or len(cs) != len(st.regions)):
        return None
    for s, (c, fr) in enumerate(zip(cs, st.regions)):
        if c.shape[0] != st.voff[s + 1] - st.voff[s] or c.shape[2] != fr.K or fr.sh_nc.shape != (st.R * st.R * 3, fr.K):
            return None
    b = Bound()
    b.st, b.cs, b.mem, b.W, b.lib, b.fn = st, list(cs), mem, W, lib, lib.shade
    S = len(st.regions)
    # the per-slot arrays as one ctypes int64 array: table pointers, c pointers, K (each at least one
    # entry), the slot offsets
    S1 = max(S, 1)
    vals = [*([fr.sh_nc.data_ptr() for fr in st.regions] or [0]), *([c.data_ptr() for c in cs] or [0]),
            *([fr.K for fr in st.regions] or [1]), *st.voff]
    b.meta = (ctypes.c_int64 * len(vals))(*vals)      # kept alive with the bound call
    mp = ctypes.addressof(b.meta)
    b.cam = (ctypes.c_float * 3)()
    b.stats = (ctypes.c_int64 * 6)()
    b.args = _Args(0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
                   st.face_rows.data_ptr(), st.face_region.data_ptr(), int(st.face_region.shape[0]),
                   mp + 24 * S1, S, mp, mp + 8 * S1, mp + 16 * S1,
                   st.pos.data_ptr(), st.frames.data_ptr(), ctypes.addressof(b.cam), st.R, W, 1, 0,
                   CHUNK, 0, vrec.data_ptr(), rows.data_ptr(), mst.data_ptr(), YCACHE_LOG, TILE)
    return b


def shade(st, cs: list[Tensor], normal: Tensor, wo: Tensor, bary: Tensor, face: Tensor, region: Tensor,
          live: Tensor, S2: int, cam: Tensor, mem: tuple[Tensor, Tensor, Tensor], stamp: int, W: int, lib=None):
    """Eq. 4 at q = n·S2 G-buffer samples (pixel-major; normal, wo (q, 3) and bary (q, 2) float32 in
    any strides, face, region (q,) int64, live (q,) bool), box-filtered → ``(out (n, 3), stats)``;
    ``st`` the ``fast.FastStatic``, cs[s] (Vr_s, 3, K_s) the c of slot s (valid at every vertex a
    shaded entry reads), cam (3,), ``mem`` a `memo` of ``st``'s vertices, ``stamp`` > 0 this frame's
    number (distinct from every earlier frame's on this memo). stats: memo rows computed, entries
    summed exactly, the first sample whose face lies in another region than its own (-1: none).
    None when the loop is not available or the arrays are not CPU tensors of those types. ``lib``: the
    library as `_lib` gave it to the caller (else looked up here)."""
    if cam.dtype != torch.float32 or cam.shape != (3,) or cam.device.type != "cpu":
        return None
    b = bind(st, cs, mem, W, lib)
    return None if b is None else b.frame(normal, wo, bary, face, region, live, S2, cam.tolist(), stamp)
