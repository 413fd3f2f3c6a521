"""The fused plane path's one-thread helpers (`native.screen8`, `native.rest_screen`,
`native.referenced_lut`) as OpenMP passes — the serial part of the paper configuration's P / V / VB / VBL / VL
frames at 2 threads (session 39; ~0.45 ms of a ~3.5 ms VL frame, session 38's zh38v stage timer).

* `rest_lut`: `native.rest_screen` and `native.referenced_lut` in one call — both walk the samples off the
  plane mask; here one walk over them, split over the threads (each thread first counts the mask's zeros
  in its range: the ranks of its rest samples, so the every-16th screen rows and the 8 candidates land
  where the serial walk puts them). The same integer counts, the same lut and vertex list (ascending
  ids), the same failures (None).
* `screen8`: `native.screen8`'s strided screen (every 16th normal against 8 candidates) with its point
  range split over the threads: the same integer counts.

Each returns None where it does not run (no compiler, ``PRTBENCH_COMPILE=0``, ``PRTBENCH_ZH_NATIVE=0``,
other dtypes or layouts); the caller then runs `native`'s serial helpers (the tests' oracle).
"""
from __future__ import annotations

import torch
from torch import Tensor

from methods.zh_shadow import native as zn

import ctypes

_I, _P = ctypes.c_int64, ctypes.c_void_p

_SOURCE = r"""
#include <stdint.h>
#include <stdlib.h>
#include <string.h>
#ifdef _OPENMP
#include <omp.h>
#endif

/* zeros of the 0/1 bytes m[0..n) */
static int64_t zeros(const uint8_t *m, int64_t n) {
    int64_t s = 0;
    for (int64_t i = 0; i < n; ++i) s += m[i];
    return n - s;
}

/* One thread's range [p0, p1) of the rest samples (first rank j, next candidate ``next``): the screen rows and
   candidates (screen) and the lut marks (lut); returns the rank after the range; *bad: a face or corner out of
   range (the marks stop). */
static inline __attribute__((always_inline)) int64_t walk(
        const uint8_t *restrict mask, const uint8_t *restrict hit, const float *restrict nrm,
        const int64_t *restrict face, const int32_t *restrict F, int64_t M, int64_t N, int64_t p0, int64_t p1,
        const int screen, const int lut_on, int64_t j, int next, const int64_t *rank, int64_t ns,
        float *restrict sub, float *restrict cand, int32_t *restrict lut, int *bad) {
    int lbad = 0;
    for (int64_t p = p0; p < p1; ++p) {
        if (mask[p]) {
            uint64_t w;   /* (skip 8 plane samples at a time: most are) */
            while (p + 9 <= p1 && (memcpy(&w, mask + p + 1, 8), w == 0x0101010101010101ULL))
                p += 8;
            continue;
        }
        if (screen) {
            const float *x = nrm + 3 * p;
            if ((j & 15) == 0 && (j >> 4) < ns) {
                sub[3 * (j >> 4)] = x[0]; sub[3 * (j >> 4) + 1] = x[1]; sub[3 * (j >> 4) + 2] = x[2];
            }
            while (next < 8 && rank[next] == j) {
                cand[3 * next] = x[0]; cand[3 * next + 1] = x[1]; cand[3 * next + 2] = x[2];
                ++next;
            }
            ++j;
        }
        if (lut_on && !lbad && (!hit || hit[p])) {
            const int64_t f = face[p];
            if ((uint64_t)f >= (uint64_t)M) { lbad = 1; continue; }
            const int32_t *c = F + 3 * f;
            const int64_t i0 = c[0], i1 = c[1], i2 = c[2];
            if ((uint64_t)i0 >= (uint64_t)N || (uint64_t)i1 >= (uint64_t)N || (uint64_t)i2 >= (uint64_t)N) {
                lbad = 1;
                continue;
            }
            __atomic_store_n(lut + i0, 1, __ATOMIC_RELAXED);
            __atomic_store_n(lut + i1, 1, __ATOMIC_RELAXED);
            __atomic_store_n(lut + i2, 1, __ATOMIC_RELAXED);
        }
    }
    *bad = lbad;
    return j;
}

/* The samples p < P with mask[p] == 0 ("rest"), ranked j in p order, split over nt threads (each a range of p).
   do_screen: as zh33p_rest_screen (m the expected count): cnt[c] = #{i < ns : sub[i] == cand[c]}, sub[i] the
   normal of rank 16 i (ns = (m + 15) / 16), cand[c] that of rank c m / 8; st[0] = 0, or -1 when the mask
   does not hold m zeros (or memory runs out). do_lut: as zh33p_referenced_lut over the rest samples with
   hit (hit NULL: all): lut[i] (N,) = the rank of vertex i among their faces' corners (ascending ids), -1
   for the others, idx[r] the vertex of rank r; st[1] = their count, or -1 when a face or corner is out of
   range. zc: nt + 1 int64 of scratch. */
void zh39s_rest_lut(const uint8_t *mask, const uint8_t *hit, const float *nrm, const int64_t *face, const int32_t *F,
                    int64_t M, int64_t P, int64_t N, int64_t do_screen, int64_t m, int64_t do_lut, int64_t nt,
                    int64_t *cnt, int32_t *lut, int64_t *idx, int64_t *zc, int64_t *st) {
    const int64_t ns = m > 0 ? (m + 15) / 16 : 0;
    float *sub = NULL;
    float cand[24];
    int64_t rank[8];
    int bad_screen = 0, bad_lut = 0;
    if (do_screen) {
        if (m <= 0) bad_screen = 1;
        else {
            sub = (float *)malloc(sizeof(float) * 3 * (size_t)ns);
            if (!sub) bad_screen = 1;
        }
        for (int c = 0; c < 8; ++c) rank[c] = c * m / 8;
    }
    const int screen = do_screen && !bad_screen;
    for (int64_t t = 0; t <= nt; ++t) zc[t] = -1;
#pragma omp parallel num_threads(nt) if(nt > 1)
    {
#ifdef _OPENMP
        const int64_t k = omp_get_thread_num(), T = omp_get_num_threads();
#else
        const int64_t k = 0, T = 1;
#endif
        const int64_t p0 = P * k / T, p1 = P * (k + 1) / T;
        if (screen && T > 1) zc[k] = zeros(mask + p0, p1 - p0);   /* (one thread: its ranks start at 0) */
        if (do_lut) {
            const int64_t i0 = N * k / T, i1 = N * (k + 1) / T;
            memset(lut + i0, 0, sizeof(int32_t) * (size_t)(i1 - i0));
        }
#pragma omp barrier
        int64_t j = 0;   /* the rank of this range's first rest sample */
        if (screen)
            for (int64_t t = 0; t < k; ++t) j += zc[t];
        int next = 0;
        if (screen)
            while (next < 8 && rank[next] < j) ++next;
        int lbad = 0;
        if (screen)
            j = walk(mask, hit, nrm, face, F, M, N, p0, p1, 1, do_lut, j, next, rank, ns, sub, cand, lut, &lbad);
        else if (do_lut)
            walk(mask, hit, nrm, face, F, M, N, p0, p1, 0, 1, j, next, rank, ns, sub, cand, lut, &lbad);
        if (lbad) {
#pragma omp atomic write
            bad_lut = 1;
        }
        if (screen && k == T - 1) zc[T] = j;   /* the total rank count, for the check below */
    }
    if (screen) {   /* (zc[T] written by the team's last thread: the highest slot set) */
        int64_t total = -1;
        for (int64_t t = nt; t >= 1; --t)
            if (zc[t] >= 0) { total = zc[t]; break; }
        if (total != m) bad_screen = 1;
        else
            for (int c = 0; c < 8; ++c) {
                int64_t q = 0;
                for (int64_t i = 0; i < ns; ++i)
                    q += (sub[3 * i] == cand[3 * c]) & (sub[3 * i + 1] == cand[3 * c + 1])
                         & (sub[3 * i + 2] == cand[3 * c + 2]);
                cnt[c] = q;
            }
    }
    free(sub);
    st[0] = do_screen ? (bad_screen ? -1 : 0) : -1;
    if (do_lut && !bad_lut) {
        int64_t r = 0;
        for (int64_t i = 0; i < N; ++i) {
            if (lut[i]) { idx[r] = i; lut[i] = (int32_t)r; ++r; }
            else lut[i] = -1;
        }
        st[1] = r;
    } else {
        st[1] = -1;
    }
}

/* zh33p_screen8 with the points j = 0, 16, ... < m split over nt threads: the same counts. */
void zh39s_screen8(const float *base, int64_t s0, int64_t s1, int64_t m, int64_t nt, int64_t *cnt) {
    float a[8], b[8], d[8];
    for (int c = 0; c < 8; ++c) {
        const int64_t k = c * m / 8;
        a[c] = base[k * s1]; b[c] = base[s0 + k * s1]; d[c] = base[2 * s0 + k * s1];
    }
    const int64_t nj = (m + 15) / 16;   /* the screened points j = 16 i, i < nj */
    int64_t n0 = 0, n1 = 0, n2 = 0, n3 = 0, n4 = 0, n5 = 0, n6 = 0, n7 = 0;
#pragma omp parallel for num_threads(nt) schedule(static) reduction(+:n0, n1, n2, n3, n4, n5, n6, n7) if(nt > 1)
    for (int64_t i = 0; i < nj; ++i) {
        const int64_t j = 16 * i;
        const float x = base[j * s1], y = base[s0 + j * s1], z = base[2 * s0 + j * s1];
        n0 += (x == a[0]) & (y == b[0]) & (z == d[0]);
        n1 += (x == a[1]) & (y == b[1]) & (z == d[1]);
        n2 += (x == a[2]) & (y == b[2]) & (z == d[2]);
        n3 += (x == a[3]) & (y == b[3]) & (z == d[3]);
        n4 += (x == a[4]) & (y == b[4]) & (z == d[4]);
        n5 += (x == a[5]) & (y == b[5]) & (z == d[5]);
        n6 += (x == a[6]) & (y == b[6]) & (z == d[6]);
        n7 += (x == a[7]) & (y == b[7]) & (z == d[7]);
    }
    cnt[0] = n0; cnt[1] = n1; cnt[2] = n2; cnt[3] = n3; cnt[4] = n4; cnt[5] = n5; cnt[6] = n6; cnt[7] = n7;
}
"""
_SIGNATURES = {
    "zh39s_rest_lut": [_P, _P, _P, _P, _P, _I, _I, _I, _I, _I, _I, _I, _P, _P, _P, _P, _P],
    "zh39s_screen8": [_P, _I, _I, _I, _I, _P]}

# samples a thread takes at least (below: fewer threads; one thread under this many)
MIN_SAMPLES_PER_THREAD = 32768


def _lib():
    """The library or None (no compiler, ``PRTBENCH_COMPILE=0``, ``PRTBENCH_ZH_NATIVE=0``: `native`'s
    switch). Not cached here (`native.load` caches the build, b541a75)."""
    return zn.switched_load("zh39s_helpers", _SOURCE, _SIGNATURES, "-fopenmp")


def _threads(n: int) -> int:
    return max(1, min(torch.get_num_threads(), n // MIN_SAMPLES_PER_THREAD, 64))


def rest_lut(mask: Tensor, hit: Tensor | None, normal: Tensor, face: Tensor, F32: Tensor, N: int, m: int,
             screen: bool, lut: bool) -> tuple[list[int] | None, tuple[Tensor, Tensor] | None] | None:
    """(``native.rest_screen(mask, normal, m)`` if ``screen`` else None, ``native.referenced_lut(mask, hit, face,
    F32, N)`` if ``lut`` else None) by one threaded pass — the same values (each None where that helper
    returns None) — or None where the pass does not run (no library, other dtypes or layouts)."""
    lib = _lib()
    P = int(mask.shape[0])
    if lib is None or not (screen or lut) or mask.dtype != torch.bool or mask.dim() != 1 or not mask.is_contiguous() \
            or mask.device.type != "cpu":
        return None
    if screen and (normal.dtype != torch.float32 or normal.shape != (P, 3) or not normal.is_contiguous()):
        return None
    if lut and (face.dtype != torch.int64 or face.shape != (P,) or not face.is_contiguous()
                or F32.dtype != torch.int32 or F32.dim() != 2 or F32.shape[1] != 3 or not F32.is_contiguous()
                or (hit is not None and (hit.dtype != torch.bool or hit.shape != (P,) or not hit.is_contiguous()))):
        return None
    if screen and m <= 0:   # (`rest_screen`'s own answer)
        if not lut:
            return None, None
        screen = False
    nt = _threads(P)
    cnt = torch.empty(10 + nt + 1, dtype=torch.int64)   # cnt[0:8], st[8:10], zc[10:]
    base = cnt.data_ptr()
    lt = torch.empty(max(N, 1), dtype=torch.int32) if lut else None
    ix = torch.empty(max(N, 1), dtype=torch.int64) if lut else None
    lib.zh39s_rest_lut(mask.data_ptr(), 0 if (hit is None or not lut) else hit.data_ptr(),
                       normal.data_ptr() if screen else 0, face.data_ptr() if lut else 0,
                       F32.data_ptr() if lut else 0, int(F32.shape[0]) if lut else 0, P, int(N) if lut else 0,
                       int(screen), int(m), int(lut), nt, cnt.data_ptr(), lt.data_ptr() if lut else 0,
                       ix.data_ptr() if lut else 0, base + 80, base + 64)
    c = cnt.tolist()
    rs = c[:8] if screen and c[8] == 0 else None
    rl = (ix[:c[9]], lt[:N]) if lut and c[9] >= 0 else None
    return rs, rl


def screen8(cur: Tensor) -> list[int] | None:
    """`native.screen8`(cur) (the same counts) with the screened points split over the threads, or None where
    it does not run."""
    lib = _lib()
    if lib is None or cur.dtype != torch.float32 or cur.device.type != "cpu" or cur.dim() != 2 or cur.shape[0] != 3 \
            or cur.shape[1] == 0:
        return None
    m = int(cur.shape[1])
    cnt = torch.empty(8, dtype=torch.int64)
    lib.zh39s_screen8(cur.data_ptr(), cur.stride(0), cur.stride(1), m, _threads(m), cnt.data_ptr())
    return cnt.tolist()
