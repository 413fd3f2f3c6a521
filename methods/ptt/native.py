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

Each pixel is one thread's, whatever ``torch.get_num_threads()`` (contiguous pixel ranges per thread,
ctypes releases the GIL), so the bits do not depend on the thread count. Compiled with
``-ffp-contract=off`` (as Inductor's kernels): every product and sum is rounded as in the compiled
kernel; the lane sums of the box filter follow AVX2's ``vec_reduce_all`` tree.

The library is built like ``methods.inout.csr``'s (per-user private cache directory, keyed by the
source text, flags and compiler; atomic rename); without a compiler, on a failed build or with
``PRTBENCH_COMPILE=0``, `available` is False and the caller uses ``fast.shade_block``.
"""
from __future__ import annotations

import ctypes
import functools
import hashlib
import os
import subprocess
import sys
import tempfile
import warnings
from concurrent.futures import ThreadPoolExecutor

import torch
from torch import Tensor

from methods.core.fused import compile_enabled

__all__ = ["available", "shade_pixels"]

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
        int64_t prefetch, int64_t n, float* out) {
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
                const v8 cl = sel((a > zero) | (a != a), a, zero);
                const v8 tj = sel(isb[b], cl, sel(isu[b], a, a * e));
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
    if (width == 16 && S2 == 4)
        body(face, b1p, b2p, bs, r, fx, fy, p0, p1, 4, face_pairs, M, table, env, lanes, 16, W, prefetch, n, out);
    else if (width == 16)
        body(face, b1p, b2p, bs, r, fx, fy, p0, p1, S2, face_pairs, M, table, env, lanes, 16, W, prefetch, n, out);
    else if (width == 32)
        body(face, b1p, b2p, bs, r, fx, fy, p0, p1, S2, face_pairs, M, table, env, lanes, 32, W, prefetch, n, out);
    else
        body(face, b1p, b2p, bs, r, fx, fy, p0, p1, S2, face_pairs, M, table, env, lanes, width, W, prefetch, n, out);
}
"""
_FLAGS = ("-O3", "-march=native", "-shared", "-fPIC", "-fno-math-errno", "-ffp-contract=off")
# Pixels below which one thread does the pass.
_MIN_PIXELS_PER_THREAD = 1 << 12


@functools.lru_cache(maxsize=None)
def _library(cc: str | None):
    """The compiled kernel (ctypes function) or None (no compiler, or the build failed: warns once)."""
    if cc is None:
        return None
    key = hashlib.sha256("\0".join((_SOURCE, cc, *_FLAGS, sys.platform)).encode()).hexdigest()[:20]
    root = os.path.join(tempfile.gettempdir(), f"prtbench-native-{os.getuid() if hasattr(os, 'getuid') else 0}")
    path = os.path.join(root, f"ptt_shade_{key}.so")
    try:
        from methods.inout.csr import _private_dir

        os.makedirs(root, mode=0o700, exist_ok=True)
        if not _private_dir(root):
            raise OSError(f"{root} is not a directory only this user can write; not loading code from it")
        if not os.path.exists(path):
            with tempfile.TemporaryDirectory(dir=root) as tmp:
                src, so = os.path.join(tmp, "shade.c"), os.path.join(tmp, "shade.so")
                with open(src, "w") as f:
                    f.write(_SOURCE)
                subprocess.run([cc, *_FLAGS, src, "-o", so], check=True, capture_output=True)
                os.replace(so, path)  # atomic: a concurrent build finds a whole file
        fn = ctypes.CDLL(path).shade_pixels
    except (OSError, subprocess.CalledProcessError) as e:
        warnings.warn(f"ptt: the native shading loop did not build ({e}); using the compiled shade_block")
        return None
    fn.restype = None
    P, I = ctypes.c_void_p, ctypes.c_int64
    fn.argtypes = [P, P, P, I, P, P, P, I, I, I, P, I, P, P, P, I, I, I, I, P]
    return fn


def _kernel():
    if not compile_enabled():
        return None
    from methods.inout.csr import _compiler

    return _library(_compiler())


def available() -> bool:
    """True when `shade_pixels` runs the native loop."""
    return _kernel() is not None


_pool: ThreadPoolExecutor | None = None
_pool_size = 0


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
    width = int(table.shape[1])
    ok = (face.dtype == torch.int64 and r.dtype == torch.int32 and face_pairs.dtype == torch.int64
          and bary.dtype == fx.dtype == fy.dtype == table.dtype == env.dtype == lanes.dtype == torch.float32
          and width % 8 == 0 and 0 < width <= 64 and env.shape[1] == width and lanes.shape[1] >= width
          and bary.shape == (n, 2) and r.shape == fx.shape == fy.shape == (n,) and face_pairs.ndim == 2
          and face_pairs.shape[1] == 3 and S2 > 0 and n % S2 == 0
          and all(t.device.type == "cpu" for t in (face, bary, r, fx, fy, face_pairs, table, env, lanes)))
    if not ok:
        return None
    face, r, fx, fy, face_pairs, table, env = (t.contiguous() for t in (face, r, fx, fy, face_pairs, table, env))
    b1, b2 = bary[:, 0], bary[:, 1]  # read in place: the G-buffer's are columns of a (2, n) array
    if b1.stride(0) != b2.stride(0):
        bary = bary.contiguous()
        b1, b2 = bary[:, 0], bary[:, 1]
    lanes = lanes[:, :width].contiguous()
    P = n // S2
    out = torch.empty(P, 3, dtype=torch.float32)
    if P == 0:
        return out
    M = int(face_pairs.shape[0])
    args = (face.data_ptr(), b1.data_ptr(), b2.data_ptr(), b1.stride(0), r.data_ptr(), fx.data_ptr(), fy.data_ptr())
    rest = (S2, face_pairs.data_ptr(), M, table.data_ptr(), env.data_ptr(), lanes.data_ptr(), width, int(W),
            PREFETCH, n, out.data_ptr())
    nt = max(1, min(torch.get_num_threads(), P // _MIN_PIXELS_PER_THREAD))
    if nt == 1:
        fn(*args, 0, P, *rest)
        return out
    global _pool, _pool_size
    if _pool is None or _pool_size < nt - 1:
        _pool, _pool_size = ThreadPoolExecutor(max_workers=nt - 1, thread_name_prefix="ptt-shade"), nt - 1
    cuts = [P * k // nt for k in range(nt + 1)]
    jobs = [_pool.submit(fn, *args, a, b, *rest) for a, b in zip(cuts[:-2], cuts[1:-1])]
    fn(*args, cuts[-2], cuts[-1], *rest)  # the last range on this thread
    for j in jobs:
        j.result()
    return out
