"""A pixel frame's grouping and per-sample passes as small C loops (built with ``cc`` through
`methods.core.native.load`, called through ctypes), each with a torch path as its fallback and test
oracle (tests/methods/triple_product/test_tp_native_group.py):

- `group_runs` = `fast_eval.group_runs` (its torch path, ``native_ok=False``): the runs of the points
  and the distinct groups (visibility row, L cell, ρ̃ cell) of the runs — the same groups, order,
  inverse and runs (integers). The torch path is ~15 eager passes and a `torch.unique` sort of the
  runs' S·k_v keys (chess bench pixel V: 262 k points, 72 k runs, 216 k keys, 24 k groups). Here one
  pass over the points finds the runs; the runs' keys row·n_c + cell are numbered in order of
  appearance through a hash table (the previous run's keys checked first: neighbouring runs share
  most rows), and the distinct codes radix-sorted — the torch path's sorted key order (its cell
  renumbering is monotone).
- `blend` = `fast_eval.group_blend_runs` with 4 L and 4 ρ̃ rows (the compiled blend is its oracle),
  to float32 round-off: a channel's 16 (L, ρ̃) terms as two 8-lane products with the weights
  lw_j·bw_k; OpenMP's team at 2 threads.
- `pixel_mean` = torch's mean over a pixel's samples (≤ `MEAN_MAX_SAMPLES`), `vertex_weights` =
  `GBuffer.vertex_weights` and `normalize` = ``torch.nn.functional.normalize(x, dim=-1)`` of (P, 3) rows,
  bit for bit, one pass each.

Without a compiler, with ``PRTBENCH_COMPILE=0`` or ``PRTBENCH_TP_NATIVE=0`` (`native.switched_on`),
`available` is False and the callers run the torch paths.
"""
from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from methods.core import native
from methods.triple_product import native as tp_native

__all__ = ["available", "blend", "group_runs", "normalize", "pixel_mean", "vertex_weights"]

_SOURCE = r"""
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

/* Runs of B points: a run starts where the cell lrows[b, 0] * nb + brows[b, 0] or any of the k_v
   visibility rows differs from the previous point's. run[b] (int32): the run of point b; start[s]:
   the first point of run s; cell[s]: its cell. info[0] = S, info[1] = the largest visibility row of
   the run starts, info[2] = the smallest. */
void tp_runs(int64_t B, int64_t kv, const int64_t* vrows, const int64_t* lrows, int64_t kl,
             const int64_t* brows, int64_t kb, int64_t nb, int32_t* run, int64_t* start, int64_t* cell,
             int64_t* info) {
    int64_t S = 0, vmax = 0, vmin = 0, prev = 0;
    for (int64_t b = 0; b < B; ++b) {
        const int64_t c = lrows[b * kl] * nb + brows[b * kb];
        const int64_t* v = vrows + b * kv;
        int fresh = b == 0 || c != prev;
        for (int64_t i = 0; i < kv && !fresh; ++i) fresh = v[i] != v[i - kv];
        if (fresh) {
            for (int64_t i = 0; i < kv; ++i) {
                if (S == 0 && i == 0) { vmax = vmin = v[0]; }
                if (v[i] > vmax) vmax = v[i];
                if (v[i] < vmin) vmin = v[i];
            }
            start[S] = b;
            cell[S] = c;
            ++S;
        }
        run[b] = (int32_t)(S - 1);
        prev = c;
    }
    info[0] = S; info[1] = vmax; info[2] = vmin;
}

static void radix32(uint64_t* x, uint64_t* y, int64_t n, uint64_t top) {
    /* x (n,) sorted by its high 32 bits (< top + 1), stably (LSD, 11 bits a pass); y: work */
    for (int sh = 32; sh < 64 && (top >> (sh - 32)) != 0; sh += 11) {
        int64_t cnt[2048] = {0};
        for (int64_t p = 0; p < n; ++p) ++cnt[(x[p] >> sh) & 2047];
        int64_t o = 0;
        for (int k = 0; k < 2048; ++k) { const int64_t c = cnt[k]; cnt[k] = o; o += c; }
        for (int64_t p = 0; p < n; ++p) y[cnt[(x[p] >> sh) & 2047]++] = x[p];
        for (int64_t p = 0; p < n; ++p) x[p] = y[p];
    }
}

/* The distinct (row, cell) keys of the S runs' k_v keys (key e = s k_v + i: row vrows[start[s], i]
   in [0, nv), cell cell[s] in [0, nc), nv nc <= 2^32), in (row, cell) order: the keys are numbered
   in order of appearance through a hash table (open addressing, grown at half full), then the
   distinct codes row nc + cell sorted (radix) and renumbered. gv[g] the row, gl[g] / gb[g] the L /
   rho rows of a point of the group (the start of its first key's run), inv[e] the group of key e;
   info[0] = G, or -1 when a work table could not be allocated. gv, gl, gb: room for S k_v groups. */
void tp_group_keys(int64_t S, int64_t kv, const int64_t* vrows, const int64_t* start, const int64_t* cell,
                   int64_t nv, int64_t nc, const int64_t* lrows, int64_t kl, const int64_t* brows, int64_t kb,
                   int64_t* gv, int64_t* gl, int64_t* gb, int64_t* inv, int64_t* info) {
    const int64_t E = S * kv;
    int bits = 10;
    while (((int64_t)1 << bits) < E / 4) ++bits;
    int64_t cap = (int64_t)1 << bits, G = 0;
    uint64_t* hk = (uint64_t*)malloc(sizeof(uint64_t) * cap);
    int32_t* hv = (int32_t*)malloc(sizeof(int32_t) * cap);
    uint64_t* gk = (uint64_t*)malloc(sizeof(uint64_t) * (E + 1));   /* (code << 32 | first key) per group */
    uint64_t* w = (uint64_t*)malloc(sizeof(uint64_t) * (E + 1));
    if (!hk || !hv || !gk || !w) goto fail;
    for (int64_t h = 0; h < cap; ++h) hk[h] = ~(uint64_t)0;
    uint64_t mk[8];                                             /* the previous run's keys and groups */
    int64_t mg[8], nm = 0;
    for (int64_t s = 0; s < S; ++s) {
        const int64_t* v = vrows + start[s] * kv;
        for (int64_t i = 0; i < kv; ++i) {
            const uint64_t k = (uint64_t)(v[i] * nc + cell[s]);
            int64_t m = 0;
            while (m < nm && mk[m] != k) ++m;
            if (m < nm) { inv[s * kv + i] = mg[m]; continue; }
            uint64_t h = (k * 0x9E3779B97F4A7C15ull) >> (64 - bits);
            while (hk[h] != k && hk[h] != ~(uint64_t)0) h = (h + 1) & (uint64_t)(cap - 1);
            if (hk[h] == ~(uint64_t)0) {
                hk[h] = k; hv[h] = (int32_t)G;
                gk[G] = (k << 32) | (uint64_t)(s * kv + i);
                ++G;
                if (2 * G > cap) {                              /* grow: re-insert the groups */
                    free(hk); free(hv);
                    ++bits; cap <<= 1;
                    hk = (uint64_t*)malloc(sizeof(uint64_t) * cap);
                    hv = (int32_t*)malloc(sizeof(int32_t) * cap);
                    if (!hk || !hv) goto fail;
                    for (int64_t q = 0; q < cap; ++q) hk[q] = ~(uint64_t)0;
                    for (int64_t g = 0; g < G; ++g) {
                        const uint64_t kg = gk[g] >> 32;
                        uint64_t q = (kg * 0x9E3779B97F4A7C15ull) >> (64 - bits);
                        while (hk[q] != ~(uint64_t)0) q = (q + 1) & (uint64_t)(cap - 1);
                        hk[q] = kg; hv[q] = (int32_t)g;
                    }
                    inv[s * kv + i] = G - 1;
                    continue;
                }
            }
            inv[s * kv + i] = hv[h];
        }
        nm = kv <= 8 ? kv : 0;
        for (int64_t i = 0; i < nm; ++i) { mk[i] = (uint64_t)(v[i] * nc + cell[s]); mg[i] = inv[s * kv + i]; }
    }
    /* order: the groups' codes sorted (distinct: the first-key half only breaks no ties) */
    for (int64_t g = 0; g < G; ++g) w[g] = gk[g];
    radix32(w, gk, G, (uint64_t)(nv * nc - 1));
    int32_t* rank = hv;                                         /* reuse: G <= cap / 2 */
    for (int64_t r = 0; r < G; ++r) {
        const uint64_t k = w[r] >> 32;
        const int64_t e = (int64_t)(w[r] & 0xffffffffu), b = start[e / kv];
        gv[r] = (int64_t)(k / (uint64_t)nc);
        for (int64_t j = 0; j < kl; ++j) gl[r * kl + j] = lrows[b * kl + j];
        for (int64_t j = 0; j < kb; ++j) gb[r * kb + j] = brows[b * kb + j];
        rank[(int64_t)(inv[e])] = (int32_t)r;                  /* inv[e] is the first key's group */
    }
    for (int64_t e = 0; e < E; ++e) inv[e] = rank[inv[e]];
    free(hk); free(hv); free(gk); free(w);
    info[0] = G;
    return;
fail:
    free(hk); free(hv); free(gk); free(w);
    info[0] = -1;
}

typedef float v8 __attribute__((vector_size(32)));
static inline v8 ld(const float* p) { v8 r; __builtin_memcpy(&r, p, sizeof r); return r; }
static inline float hsum(v8 a) {
    return ((a[0] + a[1]) + (a[2] + a[3])) + ((a[4] + a[5]) + (a[6] + a[7]));
}

/* fast_eval.group_blend_runs with 4 L and 4 rho rows, times scale: for points [p0, p1)
   out[p, c] = scale sum_i vw[p, i] sum_j lw[p, j] sum_k bw[p, k] T[inv[run[p], i], (c 4 + j) 4 + k],
   the 16 (j, k) terms of a channel as two 8-lane products with the weights lw_j bw_k. */
void tp_blend(int64_t p0, int64_t p1, int64_t kv, const int32_t* run, const int64_t* inv, const float* vw,
              const float* lw, const float* bw, const float* T, float scale, float* out) {
    for (int64_t p = p0; p < p1; ++p) {
        const int64_t* g = inv + (int64_t)run[p] * kv;
        const float* l = lw + 4 * p;
        const float* b = bw + 4 * p;
        const v8 B4 = {b[0], b[1], b[2], b[3], b[0], b[1], b[2], b[3]};
        const v8 La = {l[0], l[0], l[0], l[0], l[1], l[1], l[1], l[1]};
        const v8 Lb = {l[2], l[2], l[2], l[2], l[3], l[3], l[3], l[3]};
        const v8 W0 = La * B4, W1 = Lb * B4;
        v8 a0 = {0}, a1 = {0}, a2 = {0};
        for (int64_t i = 0; i < kv; ++i) {
            const float* t = T + 48 * g[i];
            const float w = vw[p * kv + i];
            a0 += w * (ld(t) * W0 + ld(t + 8) * W1);
            a1 += w * (ld(t + 16) * W0 + ld(t + 24) * W1);
            a2 += w * (ld(t + 32) * W0 + ld(t + 40) * W1);
        }
        out[3 * p] = hsum(a0) * scale;
        out[3 * p + 1] = hsum(a1) * scale;
        out[3 * p + 2] = hsum(a2) * scale;
    }
}
/* tp_blend over [0, B) on nt threads of OpenMP's team (contiguous ranges) */
void tp_blend_par(int64_t B, int64_t kv, const int32_t* run, const int64_t* inv, const float* vw,
                  const float* lw, const float* bw, const float* T, float scale, float* out, int64_t nt) {
#pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int64_t k = 0; k < nt; ++k)
        tp_blend(B * k / nt, B * (k + 1) / nt, kv, run, inv, vw, lw, bw, T, scale, out);
}

/* The pixel means of ss consecutive samples (P / ss pixels, 3 channels each) of x (P, 3), as torch's
   mean over that dimension: a sequential sum divided by ss (the same values bit for bit). */
void tp_pixel_mean(int64_t npix, int64_t ss, const float* x, float* out) {
    const float d = (float)ss;
    for (int64_t q = 0; q < npix; ++q) {
        const float* p = x + q * ss * 3;
        float a0 = p[0], a1 = p[1], a2 = p[2];
        for (int64_t k = 1; k < ss; ++k) { a0 += p[3 * k]; a1 += p[3 * k + 1]; a2 += p[3 * k + 2]; }
        out[3 * q] = a0 / d; out[3 * q + 1] = a1 / d; out[3 * q + 2] = a2 / d;
    }
}

/* torch.nn.functional.normalize(x, dim=-1) of x (P, 3) float32 rows (row stride sx): x / max(|x|, 1e-12),
   |x| as torch.linalg.vector_norm's float32 sum (fmaf chain; the same values bit for bit, tested); a NaN
   norm stays NaN, as torch's clamp_min leaves it. */
void tp_normalize(int64_t P, const float* x, int64_t sx, float* out) {
    for (int64_t p = 0; p < P; ++p) {
        const float a = x[p * sx], b = x[p * sx + 1], c = x[p * sx + 2];
        float n = sqrtf(fmaf(c, c, fmaf(b, b, a * a)));
        n = n < 1e-12f ? 1e-12f : n;
        out[3 * p] = a / n; out[3 * p + 1] = b / n; out[3 * p + 2] = c / n;
    }
}

/* GBuffer.vertex_weights: idx[p] = F[max(face[p], 0)] (3 int64), w[p] = (1 - u - v, u, v) on a hit, else
   0 (u, v: the barycentrics, element stride sb); status[0] = -1 when a face is past the nF faces. */
void tp_vertex_weights(int64_t P, const int64_t* face, const float* u, const float* v, int64_t sb,
                       const uint8_t* hit, const int64_t* F, int64_t nF, int64_t* idx, float* w, int64_t* status) {
    int64_t bad = 0;
    for (int64_t p = 0; p < P; ++p) {
        int64_t f = face[p] < 0 ? 0 : face[p];
        if (f >= nF) { bad = 1; f = 0; }
        idx[3 * p] = F[3 * f]; idx[3 * p + 1] = F[3 * f + 1]; idx[3 * p + 2] = F[3 * f + 2];
        if (hit[p]) {
            const float a = u[p * sb], b = v[p * sb];
            const float one_a = 1.0f - a;
            w[3 * p] = one_a - b; w[3 * p + 1] = a; w[3 * p + 2] = b;
        } else {
            w[3 * p] = 0.0f; w[3 * p + 1] = 0.0f; w[3 * p + 2] = 0.0f;
        }
    }
    status[0] = bad ? -1 : 0;
}
"""

_P, _I, _F = ctypes.c_void_p, ctypes.c_int64, ctypes.c_float
_SIGNATURES = {"tp_runs": [_I, _I, _P, _P, _I, _P, _I, _I, _P, _P, _P, _P],
               "tp_group_keys": [_I, _I, _P, _P, _P, _I, _I, _P, _I, _P, _I, _P, _P, _P, _P, _P],
               "tp_blend": [_I, _I, _I, _P, _P, _P, _P, _P, _P, _F, _P],
               "tp_blend_par": [_I, _I, _P, _P, _P, _P, _P, _P, _F, _P, _I],
               "tp_pixel_mean": [_I, _I, _P, _P],
               "tp_vertex_weights": [_I, _P, _P, _P, _I, _P, _P, _I, _P, _P, _P],
               "tp_normalize": [_I, _P, _I, _P]}


def _lib():
    """The library (`methods.core.native.load`) or None: no compiler, the build failed,
    ``PRTBENCH_COMPILE=0`` or ``PRTBENCH_TP_NATIVE=0``."""
    return tp_native.loaded("tp_group_runs", _SOURCE, _SIGNATURES, ("-ffp-contract=fast", "-fopenmp", *native.isa_flags()))


def available() -> bool:
    """True when the native grouping runs (else `fast_eval.group_runs` runs its torch path)."""
    return _lib() is not None


def group_runs(vrows: Tensor, lrows: Tensor, brows: Tensor, nb: int) -> tuple[Tensor, ...] | None:
    """`fast_eval.group_runs` (gv, gl, gb, inv_s, run) of vrows (B, k_v), lrows (B, k_L), brows (B, k_ρ)
    int64 with brows[:, 0] < nb, B ≥ 1; None when the loop does not apply (no library, a negative
    visibility row, cells that do not fit 32 bits): the caller runs the torch path."""
    lib = _lib()
    if lib is None:
        return None
    B, kv = vrows.shape
    kl, kb = lrows.shape[1], brows.shape[1]
    if B == 0 or lrows.shape[0] != B or brows.shape[0] != B:
        return None
    vrows, lrows, brows = (x.to(torch.int64).contiguous() for x in (vrows, lrows, brows))
    run = torch.empty(B, dtype=torch.int32)
    start = torch.empty(B, dtype=torch.int64)
    cell = torch.empty(B, dtype=torch.int64)
    info = torch.zeros(3, dtype=torch.int64)
    lib.tp_runs(B, kv, vrows.data_ptr(), lrows.data_ptr(), kl, brows.data_ptr(), kb, int(nb), run.data_ptr(),
                start.data_ptr(), cell.data_ptr(), info.data_ptr())
    S, vmax, vmin = (int(x) for x in info.tolist())
    cs = cell[:S]
    nc = int(cs.max()) + 1
    if vmin < 0 or int(cs.min()) < 0 or (vmax + 1) * nc > 2 ** 32 or S * kv >= 2 ** 32:
        return None
    E = S * kv
    gv = torch.empty(E, dtype=torch.int64)
    gl = torch.empty(E, kl, dtype=torch.int64)
    gb = torch.empty(E, kb, dtype=torch.int64)
    inv = torch.empty(S, kv, dtype=torch.int64)
    lib.tp_group_keys(S, kv, vrows.data_ptr(), start.data_ptr(), cs.data_ptr(), vmax + 1, nc, lrows.data_ptr(), kl,
                      brows.data_ptr(), kb, gv.data_ptr(), gl.data_ptr(), gb.data_ptr(), inv.data_ptr(), info.data_ptr())
    G = int(info[0])
    if G < 0:
        raise MemoryError("tp_group_keys could not allocate its tables")
    return gv[:G], gl[:G], gb[:G], inv, run


# Points below which one thread blends (a hand-off costs more than the share).
MIN_POINTS_PER_THREAD = 4096


def blend(run: Tensor, inv_s: Tensor, vw: Tensor, lw: Tensor, bw: Tensor, T: Tensor, scale: float = 1.0) -> Tensor | None:
    """`fast_eval.group_blend_runs` (run (B,) int32, inv_s (S, k_v) int64, vw (B, k_v), lw / bw (B, 4)
    float32, T (G, 48) float32) times ``scale`` → (B, 3) float32, to float32 round-off (the 16 (j, k)
    terms of a channel summed as two 8-lane products with the weights lw_j·bw_k, not k then j); None
    when the loop does not apply (no library, other shapes or dtypes)."""
    lib = _lib()
    if lib is None:
        return None
    B, kv = vw.shape
    S = inv_s.shape[0]
    if run.shape != (B,) or run.dtype != torch.int32 or inv_s.ndim != 2 or inv_s.shape[1] != kv \
            or inv_s.dtype != torch.int64 or lw.shape != (B, 4) or bw.shape != (B, 4) or T.ndim != 2 \
            or T.shape[1] != 48 or any(x.dtype != torch.float32 for x in (vw, lw, bw, T)):
        return None
    out = torch.empty(B, 3, dtype=torch.float32)
    if B == 0:
        return out
    run, inv_s, vw, lw, bw, T = (x.contiguous() for x in (run, inv_s, vw, lw, bw, T))
    # the loop reads without bounds checks: every run names a row of inv_s, every group a row of T
    if int(run.min()) < 0 or int(run.max()) >= S or S and (int(inv_s.min()) < 0 or int(inv_s.max()) >= T.shape[0]):
        raise IndexError("a run or group outside its table")
    args = (kv, run.data_ptr(), inv_s.data_ptr(), vw.data_ptr(), lw.data_ptr(), bw.data_ptr(), T.data_ptr(),
            float(scale), out.data_ptr())
    nt = max(1, min(torch.get_num_threads(), B // MIN_POINTS_PER_THREAD))
    lib.tp_blend(0, B, *args) if nt == 1 else lib.tp_blend_par(B, *args, nt)
    return out


# Samples per pixel up to which torch's mean is a sequential sum (tested; at 9 it sums in another order).
MEAN_MAX_SAMPLES = 4


def pixel_mean(x: Tensor, height: int, width: int, ss: int) -> Tensor:
    """``x.reshape(height, width, ss, 3).mean(2)`` of samples x (P, 3) float32 (a pixel's ss samples
    consecutive), the same values bit for bit (torch sums that dimension in order, then divides):
    one pass instead of a strided reduction (~2.6 ms of a bench frame, 1 thread). Falls back to
    torch without the library, for other dtypes / layouts and past `MEAN_MAX_SAMPLES` samples."""
    lib = _lib()
    if lib is None or x.dtype != torch.float32 or x.shape != (height * width * ss, 3) or not x.is_contiguous() \
            or x.device.type != "cpu" or ss > MEAN_MAX_SAMPLES:
        return x.float().reshape(height, width, ss, 3).mean(2)
    out = torch.empty(height, width, 3, dtype=torch.float32)
    lib.tp_pixel_mean(height * width, ss, x.data_ptr(), out.data_ptr())
    return out


def vertex_weights(gbuffer, F: Tensor) -> tuple[Tensor, Tensor]:
    """``gbuffer.vertex_weights(F)`` (vertex indices (P, 3) int64, barycentric weights (P, 3), 0 on
    misses) in one pass over the samples (the G-buffer's gather, weight columns and mask are ~6 eager
    passes: ~4-5 ms of a bench frame, 1 thread); the same values bit for bit. Falls back to the
    G-buffer's method without the library or for other dtypes / devices."""
    lib = _lib()
    face, bary, hit = gbuffer.face, gbuffer.bary, gbuffer.hit
    if lib is None or face.dtype != torch.int64 or F.dtype != torch.int64 or bary.dtype != torch.float32 \
            or hit.dtype != torch.bool or F.ndim != 2 or F.shape[1] != 3 or face.device.type != "cpu" \
            or bary.ndim != 2 or bary.shape[1] != 2:
        return gbuffer.vertex_weights(F)
    P = face.shape[0]
    if bary.shape[0] != P or hit.shape != (P,):
        return gbuffer.vertex_weights(F)
    face, hit, F = face.contiguous(), hit.contiguous(), F.contiguous()
    if bary.stride(0) < 1:
        bary = bary.contiguous()
    u, v = bary[:, 0], bary[:, 1]
    idx = torch.empty(P, 3, dtype=torch.int64)
    w = torch.empty(P, 3, dtype=torch.float32)
    st = torch.zeros(1, dtype=torch.int64)
    lib.tp_vertex_weights(P, face.data_ptr(), u.data_ptr(), v.data_ptr(), bary.stride(0), hit.data_ptr(),
                          F.data_ptr(), F.shape[0], idx.data_ptr(), w.data_ptr(), st.data_ptr())
    if int(st[0]) != 0:
        raise IndexError("a G-buffer face outside the mesh")
    return idx, w


# `normalize` runs the C pass (False: torch's, its oracle).
NORMALIZE = True


def normalize(x: Tensor) -> Tensor:
    """``torch.nn.functional.normalize(x.float(), dim=-1)`` of rows x (P, 3) float32 in one pass (torch's
    norm over the size-3 rows and the division: ~1.5 ms of a bench frame's 2^18 G-buffer normals, 1 thread;
    the C pass ~0.4 ms), the same values bit for bit (torch's float32 norm is the fmaf chain of `tp_normalize`,
    tests/methods/triple_product/test_tp_native_group.py). Torch's for other dtypes / layouts / devices, without
    the library or with `NORMALIZE` off."""
    lib = _lib() if NORMALIZE else None
    if lib is None or x.dtype != torch.float32 or x.ndim != 2 or x.shape[1] != 3 or x.device.type != "cpu" \
            or x.stride(1) != 1:
        return torch.nn.functional.normalize(x.float(), dim=-1)
    out = torch.empty(x.shape[0], 3, dtype=torch.float32)
    if x.shape[0]:
        lib.tp_normalize(x.shape[0], x.data_ptr(), x.stride(0), out.data_ptr())
    return out
