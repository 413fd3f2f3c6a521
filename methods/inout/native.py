"""In-out's native loops of shading "vertex" (Mahajan 2008 §6: eq. 4 once per vertex, then Gouraud):
the view's table cells of the referenced vertices (`vertex_cells`) and eq. 4 at those vertices
(`vertex_radiance`), built and loaded by `methods.core.native.load`.

Both replace compiled passes (``fast.vertex_cells`` and ``fast.outlier_rows``) whose per-call cost
and gathers dominated a vertex-shaded view frame (chess bench, 1 thread, session 28: the three
regions' eq. 4 took 2.1 ms compiled against 1.3–1.4 ms in this loop; the cells pass and the slots'
index arithmetic ~1 ms). The compiled passes stay as the fallback (no C compiler,
``PRTBENCH_COMPILE=0``, tensors that are not contiguous CPU float32 / int64) and as the test oracle:

- `vertex_cells` does `fast._vertex_cells`'s float32 operations in its order (d = cam − pos, each
  component of the vertex's frame times d summed left to right, ``transport.lut_cell_xyz``), so its
  cells and weights are those of the compiled pass up to the compiler's rounding of the same
  expressions (the tests compare them);
- `vertex_radiance` sums Σ_n w_n σ_k h_k(n) over the 4 nodes in `fast._outlier_rows`'s order and
  the K-term dot product in 8 lanes, combined pairwise, then the tail: another summation order than
  the compiled reduction, so equal to it to float32 round-off, not bit for bit.

Eq. 4's loop splits the vertices over OpenMP's team (the libgomp torch loaded) at 2+ threads; each
vertex is one thread's, so the image is bit for bit the same at any thread count. Built without
contraction into fused multiply-adds (``-ffp-contract=off``), at the x86-64 baseline ISA: the loop is
bound by its table reads, AVX2 measured the same (1.61 against 1.48× of the compiled pass, noise).
"""
from __future__ import annotations

import ctypes

import torch
from torch import Tensor

from methods.core import native

__all__ = ["available", "vertex_cells", "vertex_radiance"]

_SOURCE = r"""
#include <stdint.h>
#include <math.h>

typedef float v8 __attribute__((vector_size(32)));

/* The view of shading "vertex": over the vertices g < nv marked in vmask (ascending concatenated ids;
   region s holds voff[s] <= g < voff[s + 1]), d = cam - pos[g] and (x, y, z) = frames[g] d (rows of
   the 3x3 world-to-local matrix, each ((F0 d0 + F1 d1) + F2 d2)). A vertex with z > 0 gets its
   hemi-octahedral table cell (transport.lut_cell_xyz) written to region s's slice, which starts at
   voff[s]: loc = g - voff[s], first = iv R + iu, wc = the 4 bilinear node weights. cnt[s] = the
   vertices written for region s; out[0] = the vertices marked. */
void vertex_cells(const uint8_t *vmask, int64_t nv, const int64_t *voff, int64_t S, const float *pos,
                  const float *frames, const float *cam, int64_t R, int64_t *loc, int64_t *first, float *wc,
                  int64_t *cnt, int64_t *out) {
    const float h = 0.5f * (float)(R - 1), top = (float)(R - 1), top2 = (float)(R - 2);
    int64_t marked = 0;
    for (int64_t s = 0; s < S; ++s) {
        int64_t o = voff[s];
        const int64_t end = voff[s + 1] < nv ? voff[s + 1] : nv;
        for (int64_t g = voff[s]; g < end; ++g) {
            if (!vmask[g])
                continue;
            ++marked;
            const float d0 = cam[0] - pos[3 * g], d1 = cam[1] - pos[3 * g + 1], d2 = cam[2] - pos[3 * g + 2];
            const float *F = frames + 9 * g;
            const float z = (F[6] * d0 + F[7] * d1) + F[8] * d2;
            if (!(z > 0.0f))
                continue;
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
            loc[o] = g - voff[s];
            first[o] = (int64_t)iv * R + (int64_t)iu;
            wc[4 * o] = gu * gv;
            wc[4 * o + 1] = fu * gv;
            wc[4 * o + 2] = gu * fv;
            wc[4 * o + 3] = fu * fv;
            ++o;
        }
        cnt[s] = o - voff[s];
    }
    out[0] = marked;
}

/* Eq. 4 at n vertices of one region: out[(off + v[i]) * 3 + ch] = sum_k c[v[i], ch, k] *
   (((sh[r0, k] w0 + sh[r1, k] w1) + sh[r2, k] w2) + sh[r3, k] w3), r_j = (cell_i + (0, 1, R, R + 1)_j) * 3
   + ch the rows of the (R^2 3, K) table sh; c (Vr, 3, K). cell and v clamped into range (as
   fast._outlier_rows). The K-sum in 8 lanes, combined pairwise, then the tail in order. */
static void radiance_range(const int64_t *v, const int64_t *cell, const float *wc, int64_t a, int64_t b,
                           const float *sh, const float *c, int64_t K, int64_t R, int64_t Vr, float *out,
                           int64_t off) {
    const int64_t cmax = R * R - R - 2, K3 = 3 * K;
    for (int64_t i = a; i < b; ++i) {
        int64_t ce = cell[i];
        ce = ce < 0 ? 0 : (ce > cmax ? cmax : ce);
        int64_t vi = v[i];
        vi = vi < 0 ? 0 : (vi >= Vr ? Vr - 1 : vi);
        const float w0 = wc[4 * i], w1 = wc[4 * i + 1], w2 = wc[4 * i + 2], w3 = wc[4 * i + 3];
        const float *s0 = sh + ce * K3, *s1 = sh + (ce + 1) * K3, *s2 = sh + (ce + R) * K3, *s3 = sh + (ce + R + 1) * K3;
        const float *cv = c + vi * K3;
        if (i + 1 < b) {  /* the next vertex's 4 table rows: 4 runs of 3K floats */
            int64_t cn = cell[i + 1];
            cn = cn < 0 ? 0 : (cn > cmax ? cmax : cn);
            for (int64_t t = 0; t < K3; t += 16) {
                __builtin_prefetch(sh + cn * K3 + t);
                __builtin_prefetch(sh + (cn + R) * K3 + t);
            }
        }
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
            out[(off + vi) * 3 + ch] = acc;
        }
    }
}

void vertex_radiance(const int64_t *v, const int64_t *cell, const float *wc, int64_t n, const float *sh,
                     const float *c, int64_t K, int64_t R, int64_t Vr, float *out, int64_t off, int64_t nt) {
    if (nt <= 1) {
        radiance_range(v, cell, wc, 0, n, sh, c, K, R, Vr, out, off);
        return;
    }
    #pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t t = 0; t < nt; ++t)
        radiance_range(v, cell, wc, n * t / nt, n * (t + 1) / nt, sh, c, K, R, Vr, out, off);
}
"""

_P, _I = ctypes.c_void_p, ctypes.c_int64
_SIGNATURES = {"vertex_cells": [_P, _I, _P, _I, _P, _P, _P, _I, _P, _P, _P, _P, _P],
               "vertex_radiance": [_P, _P, _P, _I, _P, _P, _I, _I, _I, _P, _I, _I]}
# Vertices below which one thread shades a region (a hand-off costs more than its share).
MIN_PER_THREAD = 512


def _lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call, so a
    # None met while compilation was off (a test's monkeypatch) is not kept for the process
    return native.load("inout_vertex", _SOURCE, _SIGNATURES, extra_flags=("-fopenmp", "-ffp-contract=off"))


def available() -> bool:
    """True when the C loops run (else the callers take the compiled passes)."""
    return _lib() is not None


def _cpu(*ts: Tensor) -> bool:
    return all(t.device.type == "cpu" and t.is_contiguous() for t in ts)


def vertex_cells(vmask: Tensor, voff: list[int], pos: Tensor, frames: Tensor, cam: Tensor, R: int):
    """The view of shading "vertex" for the vertices marked in ``vmask`` (ΣVr,) bool (concatenated
    ids; region s holds ``voff[s] <= id < voff[s + 1]``): ``(slots, marked)`` with, per region s, the
    vertices above their horizon as seen from ``cam`` (3,) — (loc (n_s,) int64 local ids ascending,
    first (n_s,) int64 the first node of the table cell, wc (n_s, 4) float32 the bilinear node
    weights), views into three arrays of ΣVr rows — and the count of marked vertices. pos (ΣVr, 3)
    and frames (ΣVr, 3, 3) float32 as ``fast.FastStatic``. None when the loop is not available or the
    arrays are not contiguous CPU tensors of those types (the caller runs ``fast.vertex_cells_of``)."""
    lib = _lib()
    nv = int(vmask.shape[0])
    if (lib is None or not _cpu(vmask, pos, frames, cam) or vmask.dtype != torch.bool
            or pos.dtype != torch.float32 or frames.dtype != torch.float32 or cam.dtype != torch.float32
            or pos.shape != (nv, 3) or frames.shape != (nv, 3, 3) or cam.shape != (3,) or voff[-1] != nv):
        return None
    S = len(voff) - 1
    vo = torch.tensor(voff, dtype=torch.int64)
    loc = torch.empty(nv, dtype=torch.int64)
    first = torch.empty(nv, dtype=torch.int64)
    wc = torch.empty(nv, 4, dtype=torch.float32)
    cnt = torch.empty(max(S, 1), dtype=torch.int64)
    out = torch.empty(1, dtype=torch.int64)
    lib.vertex_cells(vmask.data_ptr(), nv, vo.data_ptr(), S, pos.data_ptr(), frames.data_ptr(), cam.data_ptr(), R,
                     loc.data_ptr(), first.data_ptr(), wc.data_ptr(), cnt.data_ptr(), out.data_ptr())
    n = cnt.tolist()
    slots = [(loc[voff[s]:voff[s] + n[s]], first[voff[s]:voff[s] + n[s]], wc[voff[s]:voff[s] + n[s]])
             for s in range(S)]
    return slots, int(out[0])


def vertex_radiance(sh_nc: Tensor, R: int, c: Tensor, v: Tensor, cell: Tensor, wc: Tensor, out: Tensor,
                    off: int) -> bool:
    """Eq. 4 at vertices ``v`` (n,) int64 (local ids) of one region, written to rows ``off + v`` of
    ``out`` (ΣVr, 3) float32: ``fast.vertex_radiance`` (the region's table sh_nc (R²·3, K), c (Vr, 3,
    K), first nodes ``cell`` (n,) int64 and weights ``wc`` (n, 4)) to float32 round-off. False (nothing
    written) when the loop is not available or the arrays are not contiguous CPU tensors of those
    types (the caller runs the compiled pass)."""
    lib = _lib()
    n = int(v.shape[0])
    if (lib is None or not _cpu(sh_nc, c, v, cell, wc, out) or sh_nc.dtype != torch.float32
            or c.dtype != torch.float32 or out.dtype != torch.float32 or v.dtype != torch.int64
            or cell.dtype != torch.int64 or wc.dtype != torch.float32 or c.dim() != 3 or c.shape[1] != 3
            or sh_nc.shape != (R * R * 3, c.shape[2]) or cell.shape != (n,) or wc.shape != (n, 4)
            or out.dim() != 2 or out.shape[1] != 3 or c.shape[0] < 1 or R < 2):
        return False
    if n == 0:
        return True
    if not (0 <= off and off + c.shape[0] <= out.shape[0]):
        raise ValueError(f"rows {off}..{off + c.shape[0]} of c do not fit the {out.shape[0]} output rows")
    nt = max(1, min(torch.get_num_threads(), n // MIN_PER_THREAD))
    lib.vertex_radiance(v.data_ptr(), cell.data_ptr(), wc.data_ptr(), n, sh_nc.data_ptr(), c.data_ptr(),
                        int(c.shape[2]), R, int(c.shape[0]), out.data_ptr(), off, nt)
    return True
