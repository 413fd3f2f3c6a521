"""In-out's per-sample V loop with the tile fill NODE-MAJOR (session 42, ip42; tried and dropped): the loop's
C source (``methods.inout.native_sample``) with the edits below, built under its own name, against the
module's loop, alternating in one process (the protocol of ``benchmarks.inout_loop_ab``).

    python -m benchmarks.inout_nodemajor_ab --scene chess|creature [--frames 15] [--cold]
                                            [--variants base 16383 32767] [--precompute-code DIR]

A variant is ``base`` (the module's loop, its ``FAST``) or a ``FAST`` value run on the edited source (a
trailing ``:`` a second copy, for an A/A pair), whose
new bits are (all with 256, the tiles):
- 4096: the fill node-major. Per vertex its distinct nodes as bit 2048 does (tags), each a (vertex, node)
  pair of the tile, each pair's (slot, node) a tile-local node (a per-(slot, node) tag word); the entries
  keep their pairs' ids (4 int32 per (entry, vertex) instead of 4 X); the pairs sorted by node (counting
  sort); per node its table row read once a tile and X of its vertices by ``cols_x`` (one table row, up to
  ``CXN`` = 4 c rows: ``rows_x``'s operations with the roles of the operands swapped, the same k steps,
  masks, fused multiply-adds and reduction tree, so the same bits per pair); the shade pass reads X by id.
- 8192: the table row of the node ``NMPF`` = 2 ahead prefetched (all its lines).
- 16384: the sorted pairs four at a time whatever their nodes (``pairs_x``: 4 table rows, 4 c rows, one K;
  no per-node remainder calls), rows prefetched ``NMPA`` = 12 pairs ahead with 8192.
Every variant gives the module loop's image bit for bit (printed: max |d|).

Measured (1 thread, process CPU, each call right after a fresh rasterisation, host at load 2-3; the module's
FAST 4095 against the variants, ``--frames 15 --cold --variants base 16383 32767 base: --precompute-code
BASE``): chess 16383 0.89x (per frame 0.89x), 32767 0.92x (per frame 0.92x), A/A 1.006x (1.013x); creature
16383 0.90x (0.90x), 32767 0.91x (0.91x), A/A 1.009x (1.006x); 8191 (no prefetch) chess 0.80x; max |d| 0.
Per pass on chess (``benchmarks.inout_tiles``-style thread-CPU clocks around the passes, same builds, ms):
vertex-major fill ~3.9-4.0 (book-keeping ~1.27, ``rows_x`` arithmetic ~0.9, the table rows' traffic ~1.75)
against node-major ~4.1 (the vertex loop with the pair ids and the node tags ~1.47, counting sort ~0.1, the
node loop with its table stream ~0.5, ``cols_x`` with c from L2 ~2.0, of which c's traffic ~0.7-0.9: with
every c row from one L1-resident row the fill reads 3.4). The table traffic is gone, but the c rows now
cross L2 -> L1 once per pair (~116 MB a chess frame instead of the table's ~117 MB), a node has ~5
vertices (calls of 4 + 1: the arithmetic ~1.4x ``rows_x``'s), and the pair book-keeping costs more than
the X copies it replaces. ``CXN`` = 6 / 8 (more vertices a call: register spills) 0.93x / 0.95x of 4 (the call; fill
4.75 / 4.63 against 4.18 ms). A first form that deduplicated the pairs per node instead of per vertex (each
(entry, vertex) item's 4 node references sorted by node, ~400·10³ a chess frame against 155·10³ pairs)
spent ~3.2 ms in its book-keeping alone.
Numbers (chess, per frame): ~100·10³ (entry, vertex) items, 155·10³ (vertex, node) pairs over ~35 tiles,
~31·10³ tile-local nodes (~900 a tile, ~5 pairs each), ~8.3·10³ tile vertices (~240 a tile, ~19 nodes each).
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.common import inout_loop_state, settle
from methods.core import native
from methods.inout import native_sample as ns
from references.gbuffer import make_gbuffer

# the edits: (old, new) pairs applied in order to ``native_sample._SOURCE``
_EDITS = [(' ((int64_t)1 << 47) || !tws_ensure(T * A->S2, A->voff[A->S],',
  ' ((int64_t)1 << 47) || !tws_ensure(T * A->S2, A->voff[A->S], A->R * A->R, A->S *'),
 ('f - bu) - bv, bu, bv};\n            const v4 *x = ex + 12 * e;\n            v4 B = {0, 0, 0, 0}',
  'f - bu) - bv, bu, bv};\n            const v4 *x = ex + 12 * e'),
 ('w[3];\n            const float beta[3] = {(1.0f - bu) - bv, bu, bv};\n            ',
  'w[3];\n'
  '            const float beta[3] = {(1.0f - bu) - bv, bu, bv};\n'
  '            v4 B = {0, 0, 0, 0};\n'
  "            if (nodemajor) {                /* bit 4096: the entry's pairs' X by their ids */\n"
  '                const int32_t *xi = tw.eidx + 12 * e;\n'
  '                const v4 *xp = tw.xp;\n'
  '                for (int j = 0; j < 3; ++j) {\n'
  '                    if (beta[j] == 0.0f)\n'
  '                        continue;\n'
  '                    const int32_t *y = xi + 4 * j;\n'
  '                    B += ((xp[y[0]] * w0 + xp[y[1]] * w1) + (xp[y[2]] * w2 + xp[y[3]] * w3)) * beta[j];\n'
  '                }\n'
  '                o += B;\n'
  '                continue;\n'
  '            }\n'
  '            '),
 ('item_lv[it]]++] = item_e[it];\n    for (int32_t l = 0; l < nL',
  'item_lv[it]]++] = item_e[it];\n'
  '    for (int32_t l = 0; l < nL; ++l) {\n'
  '            const int64_t g = vg[l];\n'
  '            int64_t s = 0;\n'
  '            while (s + 1 < A->S && g >= A->voff[s + 1]) ++s;\n'
  '            vcp[l] = (const float *)(intptr_t)A->cp[s] + (g - A->voff[s]) * 3 * A->Ks[s];\n'
  '            const int32_t vt = ++tw.ntg;\n'
  '            int32_t nN = 0;\n'
  '            for (int32_t it = vpos[l]; it < vpos[l + 1]; ++it) {\n'
  '                const int32_t node0 = ent[sorted[it] / 3].node0;\n'
  '                for (int k = 0; k < 4; ++k) {\n'
  '                    const int32_t nd = node0 + d[k], fresh = ntag[nd] != vt;\n'
  '                    const int32_t sl = nslot[nd];\n'
  '                    ntag[nd] = vt; nodes[nN] = nd; nslot[nd] = fresh ? nN : sl; nN += fresh;\n'
  '                }\n'
  '            }\n'
  '            const int32_t sb = (int32_t)(s * RR);\n'
  '            for (int32_t i = 0; i < nN; ++i) {\n'
  '                const int32_t key = sb + nodes[i];\n'
  '                const uint64_t v = ttn[key];\n'
  '                const int32_t fresh = (v >> 32) != (uint64_t)(uint32_t)tt;\n'
  '                const int32_t id = fresh ? nT : (int32_t)(uint32_t)v;\n'
  '                ttn[key] = th | (uint32_t)id;\n'
  '                tkey[id] = key;\n'
  '                tpos[id] = (fresh ? 0 : tpos[id]) + 1;\n'
  '                nT += fresh;\n'
  '                pv[nP + i] = l; pn[nP + i] = id;\n'
  '            }\n'
  '            for (int32_t it = vpos[l]; it < vpos[l + 1]; ++it) {\n'
  '                const int32_t ej = sorted[it], node0 = ent[ej / 3].node0;\n'
  '                int32_t *xi = eidx + 4 * ej;\n'
  '                xi[0] = nP + nslot[node0]; xi[1] = nP + nslot[node0 + 1];\n'
  '                xi[2] = nP + nslot[node0 + R]; xi[3] = nP + nslot[node0 + R + 1];\n'
  '            }\n'
  '            nP += nN;\n'
  '        }\n'
  '        made += nP;\n'
  '        int32_t acc = 0;\n'
  '        for (int32_t id = 0; id < nT; ++id) {\n'
  '            const int32_t c = tpos[id];\n'
  '            tpos[id] = acc; acc += c;\n'
  '        }\n'
  '        for (int32_t p = 0; p < nP; ++p) {\n'
  '            const int32_t b = tpos[pn[p]]++;\n'
  '            ord[b] = p; pc[b] = vcp[pv[p]];\n'
  '        }\n'
  '        v4 *xp = tw.xp;\n'
  '        if (A->fast & 16384) {      /* bit 16384: the sorted pairs four at a time, any nodes (one K a call) */\n'
  '            const float **pr = tw.pr, **trow = tw.trow;\n'
  '            int32_t *pk = tw.pk;\n'
  '            int32_t bb = 0;\n'
  '            for (int32_t id = 0; id < nT; ++id) {\n'
  '                const int32_t key = tkey[id];\n'
  '                const int64_t s = key / RR;\n'
  '                const int32_t K = (int32_t)A->Ks[s];\n'
  '                const float *row = (const float *)(intptr_t)A->shp[s] + (key - s * RR) * 3 * (int64_t)K;\n'
  '                trow[id] = row;\n'
  '                for (; bb < tpos[id]; ++bb) {\n'
  '                    pr[bb] = row; pk[bb] = K;\n'
  '                }\n'
  '            }\n'
  '            for (int i = 0; i < 4; ++i) {      /* padding: the last pair again */\n'
  '                pr[nP + i] = pr[nP - 1 < 0 ? 0 : nP - 1]; pc[nP + i] = pc[nP - 1 < 0 ? 0 : nP - 1]; pk[nP + i] '
  '= -1;\n'
  '            }\n'
  '            int32_t pf = 0;\n'
  '            for (int32_t b = 0; b < nP; b += 4) {\n'
  '                if (A->fast & 8192) {\n'
  '                    for (; pf < nT && (pf == 0 ? 0 : tpos[pf - 1]) <= b + NMPA; ++pf) {\n'
  '                        const char *r2 = (const char *)trow[pf];\n'
  '                        const int64_t K2 = pk[pf == 0 ? 0 : tpos[pf - 1]];\n'
  '                        for (int64_t o = 0; o < 12 * K2; o += 64)\n'
  '                            __builtin_prefetch(r2 + o, 0, 3);\n'
  '                    }\n'
  '                }\n'
  '                const int32_t K = pk[b];\n'
  '                v4 x[4];\n'
  '                if ((pk[b + 1] == K || pk[b + 1] < 0) && (pk[b + 2] == K || pk[b + 2] < 0) && (pk[b + 3] == K '
  '|| pk[b + 3] < 0)) {\n'
  '                    pairs_x(pr + b, pc + b, K, x, tree);\n'
  '                } else {\n'
  '                    for (int i = 0; i < 4 && b + i < nP; ++i) {\n'
  '                        const float *r4[4] = {pr[b + i], pr[b + i], pr[b + i], pr[b + i]}, *c4[4] = {pc[b + i], '
  'pc[b + i], pc[b + i], pc[b + i]};\n'
  '                        v4 y[4];\n'
  '                        pairs_x(r4, c4, pk[b + i], y, tree);\n'
  '                        x[i] = y[0];\n'
  '                    }\n'
  '                }\n'
  '                for (int i = 0; i < 4 && b + i < nP; ++i)\n'
  '                    xp[ord[b + i]] = x[i];\n'
  '            }\n'
  '            nT = 0;                 /* done */\n'
  '        }\n'
  '        int32_t b0 = 0;\n'
  '        for (int32_t id = 0; id < nT; ++id) {\n'
  '            const int32_t b1 = tpos[id], key = tkey[id];\n'
  '            const int64_t s = key / RR, node = key - s * RR, K = A->Ks[s];\n'
  '            const float *row = (const float *)(intptr_t)A->shp[s] + node * 3 * K;\n'
  "            if ((A->fast & 8192) && id + NMPF < nT) {   /* bit 8192: a later node's table row requested */\n"
  '                const int32_t k2 = tkey[id + NMPF];\n'
  '                const int64_t s2 = k2 / RR;\n'
  '                const char *r2 = (const char *)((const float *)(intptr_t)A->shp[s2] + (k2 - s2 * RR) * 3 * '
  'A->Ks[s2]);\n'
  '                for (int64_t o = 0; o < 12 * A->Ks[s2]; o += 64)\n'
  '                    __builtin_prefetch(r2 + o, 0, 3);\n'
  '            }\n'
  '            for (int32_t b = b0; b < b1; b += CXN) {\n'
  '                const int nv = b1 - b < CXN ? (int)(b1 - b) : CXN;\n'
  '                v4 x[8];\n'
  '                cols_xn(row, pc + b, K, nv, x, tree);\n'
  '                for (int i = 0; i < nv; ++i)\n'
  '                    xp[ord[b + i]] = x[i];\n'
  '            }\n'
  '            b0 = b1;\n'
  '        }\n'
  '    }\n'
  '    for (int32_t l = 0; l < (nodemajor ? 0 : nL)'),
 ('++it)\n        sorted[vcnt[item_lv[it]]++] = item_e[it];\n    ',
  '++it)\n'
  '        sorted[vcnt[item_lv[it]]++] = item_e[it];\n'
  '    const int nodemajor = (A->fast & 4352) == 4352;   /* bit 4096 (with 256) */\n'
  '    if (nodemajor) {\n'
  '        /* bit 4096: per vertex its distinct nodes (as bit 2048), each a (vertex, node) pair of the tile and\n'
  "           each pair's (slot, node) a tile-local node (numbered as met); the entries keep their pairs' ids; "
  'the\n'
  '           pairs sorted by node (counting sort); per node its table row read once (requested NMPF nodes ahead,\n'
  '           bit 8192) and X of its pairs by `cols_x`, four vertices at a time */\n'
  '        const int32_t tt = ++tw.ttg;\n'
  '        const uint64_t th = (uint64_t)(uint32_t)tt << 32;\n'
  '        uint64_t *ttn = tw.ttn;\n'
  '        int32_t *tkey = tw.tkey, *tpos = tw.tpos, *pv = tw.pv, *pn = tw.pn, *ord = tw.ord, *eidx = tw.eidx;\n'
  '        int32_t *ntag = tw.ntag, *nslot = tw.nslot, *nodes = tw.nodes;\n'
  '        const float **vcp = tw.vcp, **pc = tw.pc;\n'
  '        const int32_t d[4] = {0, 1, (int32_t)R, (int32_t)R + 1};\n'
  '        int32_t nP = 0, nT = 0;\n'
  '        '),
 ('/\nstatic int tws_ensure(int64_t Q, int64_t nv, int64_t rr) {',
  '/\n'
  'static int tws_ensure(int64_t Q, int64_t nv, int64_t rr) {\n'
  '    if (tw.srr < srr || tw.ttg >= 0x7FFFFFF0) {\n'
  '        free(tw.ttn);\n'
  '        tw.ttn = (uint64_t *)calloc(srr, 8);\n'
  '        tw.srr = 0; tw.ttg = 0;\n'
  '        if (!tw.ttn)\n'
  '            return 0;\n'
  '        tw.srr = srr;\n'
  '    }\n'
  '    if (tw.cap_p < Q) {     /* pairs: at most 4 per item, 3 items per entry */\n'
  '        const int64_t E = Q < ((int64_t)1 << (TH_LOG - 1)) ? Q : ((int64_t)1 << (TH_LOG - 1)), P = 12 * E;\n'
  '        free(tw.tkey); free(tw.tpos); free(tw.pv); free(tw.pn); free(tw.ord); free(tw.eidx); free(tw.vcp); '
  'free(tw.pc);\n'
  '        free(tw.xp);\n'
  '        tw.tkey = (int32_t *)malloc(P * 4); tw.tpos = (int32_t *)malloc((P + 1) * 4);\n'
  '        tw.pv = (int32_t *)malloc(P * 4); tw.pn = (int32_t *)malloc(P * 4); tw.ord = (int32_t *)malloc(P * 4);\n'
  '        tw.eidx = (int32_t *)malloc(P * 4); tw.vcp = (const float **)malloc(3 * E * sizeof(float *));\n'
  '        tw.pc = (const float **)malloc((P + 4) * sizeof(float *));\n'
  '        free(tw.pr); free(tw.trow); free(tw.pk);\n'
  '        tw.pr = (const float **)malloc((P + 4) * sizeof(float *)); tw.trow = (const float **)malloc((P + 4) * '
  'sizeof(float *));\n'
  '        tw.pk = (int32_t *)malloc((P + 4) * 4);\n'
  '        if (!tw.pr || !tw.trow || !tw.pk)\n'
  '            return 0;\n'
  '        tw.xp = (v4 *)amalloc((size_t)(P + 4) * sizeof(v4));\n'
  '        tw.cap_p = 0;\n'
  '        if (!tw.tkey || !tw.tpos || !tw.pv || !tw.pn || !tw.ord || !tw.eidx || !tw.vcp || !tw.pc || !tw.xp)\n'
  '            return 0;\n'
  '        tw.cap_p = Q;\n'
  '    }'),
 (') */\nstatic int tws_ensure(int64_t Q, int64_t nv, int64_t rr',
  ') */\nstatic int tws_ensure(int64_t Q, int64_t nv, int64_t rr, int64_t srr'),
 (' */\n    int32_t *ntag, *nslot, *nodes, ntg;\n    v4 *xs;\n    ',
  ' */\n'
  '    int32_t *ntag, *nslot, *nodes, ntg;\n'
  '    v4 *xs;\n'
  "    int64_t srr, cap_p;         /* bit 4096: per (slot, node) its tile tag and tile-local id; the tile's pairs "
  '*/\n'
  "    uint64_t *ttn;              /* per (slot, node): the tile's tag << 32 | its tile-local id */\n"
  '    int32_t *tkey, *tpos, *pv, *pn, *ord, *eidx, ttg;\n'
  '    const float **vcp, **pc, **pr, **trow;\n'
  '    int32_t *pk;\n'
  '    v4 *xp;\n'
  '    '),
 ('* bit 1024: vertices ahead whose c is prefetched */\n#endif\n#',
  '* bit 1024: vertices ahead whose c is prefetched */\n'
  '#endif\n'
  '#ifndef NMPA\n'
  "#define NMPA 12  /* bit 16384 (with 8192): pairs ahead whose node's table row is prefetched */\n"
  '#endif\n'
  '#ifndef NMPF\n'
  '#define NMPF 2   /* bit 8192: nodes ahead whose table row is prefetched */\n'
  '#endif\n'
  '#'),
 ('(t, t + 3 * K, t + R3K, t + R3K + 3 * K, cv, K, x, tree);\n}\n',
  '(t, t + 3 * K, t + R3K, t + R3K + 3 * K, cv, K, x, tree);\n'
  '}\n'
  '\n'
  '/* bit 4096: X(v_i, n) of one table row r (node n) with the c rows of up to four vertices (nv of them): each\n'
  "   (vertex, node) pair's 3 sums by `rows_x`'s operations — the same k steps, masks and fused multiply-adds\n"
  '   (table value times c value) into its own accumulator, then the same reduction — so the same bits as\n'
  '   `rows_x` / `cell_x` give the pair; only which operand stays in L1 differs (the table row here). */\n'
  'static inline __attribute__((always_inline)) void cols_x(const float *r, const float *const *cs, int64_t K, int '
  'nv, v4 *x,\n'
  '                                                         int tree) {\n'
  '    vecf a[8][3];\n'
  '    for (int n = 0; n < 8; ++n)\n'
  '        for (int ch = 0; ch < 3; ++ch)\n'
  '            a[n][ch] = VZERO();\n'
  '    for (int64_t k = 0; k < K; k += VL) {\n'
  '        const vecm mk = VMASK(K - k);\n'
  '        for (int ch = 0; ch < 3; ++ch) {\n'
  '            const int64_t o = ch * K + k;\n'
  '            const vecf t = VLOAD(mk, r + o);\n'
  '            for (int i = 0; i < nv; ++i)\n'
  '                a[i][ch] = VFMA(t, VLOAD(mk, cs[i] + o), a[i][ch]);\n'
  '        }\n'
  '    }\n'
  '#ifdef __AVX512F__\n'
  '    if (tree) {\n'
  '        x4_sums(a, x);\n'
  '        if (nv > 4)\n'
  '            x4_sums(a + 4, x + 4);\n'
  '        return;\n'
  '    }\n'
  '#else\n'
  '    (void)tree;\n'
  '#endif\n'
  '    for (int n = 0; n < nv; ++n)\n'
  '        x[n] = (v4){VSUM(a[n][0]), VSUM(a[n][1]), VSUM(a[n][2]), 0.0f};\n'
  '}\n'
  '/* up to CXN vertices a call (x: room for 8) */\n'
  '#ifndef CXN\n'
  '#define CXN 4\n'
  '#endif\n'
  'static void cols_xn(const float *r, const float *const *cs, int64_t K, int nv, v4 *x, int tree) {\n'
  '    switch (nv) {\n'
  '    case 1: cols_x(r, cs, K, 1, x, tree); break;\n'
  '    case 2: cols_x(r, cs, K, 2, x, tree); break;\n'
  '    case 3: cols_x(r, cs, K, 3, x, tree); break;\n'
  '    case 4: cols_x(r, cs, K, 4, x, tree); break;\n'
  '    case 5: cols_x(r, cs, K, 5, x, tree); break;\n'
  '    case 6: cols_x(r, cs, K, 6, x, tree); break;\n'
  '    case 7: cols_x(r, cs, K, 7, x, tree); break;\n'
  '    default: cols_x(r, cs, K, 8, x, tree); break;\n'
  '    }\n'
  '}\n'
  "/* bit 16384: X of four arbitrary (vertex, node) pairs (table rows r[i], c rows c[i], one K): each pair's 3 "
  'sums\n'
  "   by `rows_x`'s operations (the same k steps, masks, fused multiply-adds of table value by c value into its "
  'own\n'
  '   accumulator, the same reduction), so the same bits per pair */\n'
  'static inline void pairs_x(const float *const *r, const float *const *c, int64_t K, v4 *x, int tree) {\n'
  '    vecf a[4][3];\n'
  '    for (int n = 0; n < 4; ++n)\n'
  '        for (int ch = 0; ch < 3; ++ch)\n'
  '            a[n][ch] = VZERO();\n'
  '    for (int64_t k = 0; k < K; k += VL) {\n'
  '        const vecm mk = VMASK(K - k);\n'
  '        for (int ch = 0; ch < 3; ++ch) {\n'
  '            const int64_t o = ch * K + k;\n'
  '            for (int i = 0; i < 4; ++i)\n'
  '                a[i][ch] = VFMA(VLOAD(mk, r[i] + o), VLOAD(mk, c[i] + o), a[i][ch]);\n'
  '        }\n'
  '    }\n'
  '#ifdef __AVX512F__\n'
  '    if (tree) {\n'
  '        x4_sums(a, x);\n'
  '        return;\n'
  '    }\n'
  '#else\n'
  '    (void)tree;\n'
  '#endif\n'
  '    for (int n = 0; n < 4; ++n)\n'
  '        x[n] = (v4){VSUM(a[n][0]), VSUM(a[n][1]), VSUM(a[n][2]), 0.0f};\n'
  '}')]


def source() -> str:
    """The loop's source with the node-major edits (each anchor must occur once, else the loop changed)."""
    src = ns._SOURCE
    for old, new in _EDITS:
        if src.count(old) != 1:
            raise SystemExit(f"the loop's source changed: {old[:80]!r}")
        src = src.replace(old, new)
    return src


def build():
    return native.load("inout_nodemajor", source(), ns._SIGNATURES, extra_flags=ns._flags())


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--frames", type=int, default=15)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--cold", action="store_true", help="make the frame's G-buffer right before each call")
    ap.add_argument("--variants", nargs="+", default=["base", "16383", "32767"])
    ap.add_argument("--precompute-code", default=None,
                    help="take the precomputation from the harness cache entry of the code in DIR (a base checkout)")
    a = ap.parse_args(argv)
    if a.precompute_code:
        from reports import precompute_cache
        from reports.store import code_closure_fingerprint

        precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, a.precompute_code)
    torch.set_num_threads(a.threads)
    base, nm = ns._lib(), build()
    if base is None or nm is None:
        raise SystemExit("the C loop is not available (no compiler or PRTBENCH_COMPILE=0)")
    scene, frames, gbs, m, st, cs = inout_loop_state(a.scene, a.size, a.frames)
    variants = list(dict.fromkeys(a.variants))
    # a trailing ":" names a second copy of a variant (an A/A pair: ``base base:``)
    run = {v: (base, ns.FAST) if v.rstrip(":") == "base" else (nm, int(v.rstrip(":"))) for v in variants}
    mems = {v: ns.memo(st.voff[-1], ns.WINDOW) for v in variants}
    T: dict[str, list[float]] = {v: [] for v in variants}
    stats, imgs, diff, saved = {}, {}, 0.0, ns.FAST
    try:
        for i, (f, g) in enumerate(zip(frames, gbs)):
            cam = torch.tensor(f.camera.origin, dtype=torch.float32)
            for v in (variants if i % 2 == 0 else variants[::-1]):
                lib, ns.FAST = run[v]
                settle()
                if a.cold:
                    make_gbuffer(scene, f, 2)
                c0 = time.process_time()
                out, s = ns.shade(st, cs, g.normal, g.wo, g.bary, g.face, g.region, g.hit, 4, cam, mems[v], i + 1,
                                  ns.WINDOW, lib)
                T[v].append(time.process_time() - c0)
                stats[v], imgs[v] = s, out
            diff = max(diff, *(float((imgs[v] - imgs[variants[0]]).abs().max()) for v in variants))
    finally:
        ns.FAST = saved
    print(f"{a.scene} {a.size} V, {a.threads} thread(s), {a.frames} frames{' (cold)' if a.cold else ''}; "
          f"max |d| against {variants[0]}: {diff:.3g}")
    res = {}
    for v in variants:
        med = 1e3 * statistics.median(T[v][1:])
        ratio = statistics.median(T[variants[0]][1:]) / statistics.median(T[v][1:])
        paired = statistics.median(x / y for x, y in zip(T[variants[0]][1:], T[v][1:]))
        res[v] = {"median_ms": med, "ratio": ratio, "paired": paired, "stats": stats[v]}
        print(f"{v:>8}  median {med:7.3f} ms  {variants[0]}/{v} {ratio:5.3f} (per frame {paired:5.3f})  stats {stats[v]}")
    return {"variants": res, "max_diff": diff}


if __name__ == "__main__":
    main()
