"""Gouraud resolve: per-vertex radiance interpolated to the G-buffer's samples with their
barycentrics and box-filtered into pixels, in one pass over the samples (issue 14).

The reference is two ``scenes.frame.GBuffer`` calls, ``resolve(interpolate(values, F))``: gather the
three vertex rows of each sample's face, weight them by (1 − u − v, u, v), zero the misses, average
each pixel's S² sub-samples. `resolve` computes the same sums per pixel (unrolled: three vertices,
S² sub-samples) in one pass over the pixels — on the CPU a C loop (`methods.core.native`), else one
compiled kernel over a static block of pixels (``methods.core.fused``), the same sums in the same
order —, so the per-sample radiance is never written to memory; it equals the reference to float32
round-off.

Used by the methods that shade per vertex and interpolate the radiance (the paper's run time of
Mahajan 2008 "interactive at 17K vertices", Ma 2006 §3.3, Sun 2007's GPU path).
"""
from __future__ import annotations

import ctypes
import functools
import warnings

import torch
from torch import Tensor

from methods.core import native
from methods.core.fused import fused, map_rows, pow2_block

__all__ = ["resolve", "resolve_matrix", "resolve_reference"]


# Pixels per static block of `resolve` (`fused.pow2_block` of the image's pixel count).
RESOLVE_BLOCK_MIN = 1 << 10
RESOLVE_BLOCK_MAX = 1 << 16


# No per-load bounds checks in `_pixels`: its gathers are in range by construction — a face is
# clamped at 0 and indexes the faces' corner table fv (3, M) of the geometry the G-buffer was made
# of (`scenes.frame.GBuffer.face`: a face of ``scene.geometry(pose).F``, −1 on a miss), and fv
# holds rows of ``values`` (the callers make both from one mesh; in-out checks its table for −1).
# Inductor checked every indirect load (12 per sample): bench creature 256² × 2², 1 thread,
# settled, process CPU 2.09-2.18 → 1.77-1.79 ms, bit-identical (a ZH P frame's resolve).
_NO_ASSERT = {"assert_indirect_indexing": False}


@functools.partial(fused, options=_NO_ASSERT)
def _pixels(face: Tensor, bu: Tensor, bv: Tensor, hit: Tensor, fv: Tensor, values: Tensor) -> Tensor:
    """(n, C) pixel radiance of n pixels: face (n, S²) int64 (−1 on a miss), bu, bv (n, S²) the
    barycentrics (u, v), hit (n, S²) bool; fv (3, M) vertex rows of each face's corners; values
    (N, C) per-vertex radiance. Indices unchecked (`_NO_ASSERT`): faces < M, fv < N by the caller."""
    S2 = face.shape[1]
    out = None
    for s in range(S2):                       # unrolled: each pixel's sum is one thread's, in order
        f = face[:, s].clamp_min(0)
        u, v = bu[:, s, None], bv[:, s, None]
        b = (values[fv[0][f]] * (1.0 - u - v) + values[fv[1][f]] * u + values[fv[2][f]] * v)
        b = torch.where(hit[:, s, None], b, torch.zeros((), dtype=b.dtype))
        out = b if out is None else out + b
    return out * (1.0 / S2)


# -- the native loop (CPU): `_pixels`' sums as a C loop over the pixels -------------------------------
#
# The same sums in the same order as `_pixels` (per pixel, its sub-samples in order, each one's three
# corners as ((V0 (1 − u − v) + V1 u) + V2 v), a miss adding nothing; the sum times 1 / S²), without
# the compiled kernel's guards and per-call wrapper, and with scalar loads where Inductor emits
# per-lane gathers: bench chess, 256² × 2², 1 thread, process CPU, the kernel alone (values random):
# 1.35 → 0.79 ms back to back, 2.0 → 1.3 ms after 0.2 s idle, bit-identical (session 26,
# /work/scratch/res_bench.py). Unchecked loads: `resolve` checks the ranges first, as for `_pixels`.
_SOURCE = r"""
#include <stdint.h>
/* Pixels i0 <= i < i1: out[i, c] = (1 / S2) * sum over s < S2 with hit[p] (p = i * S2 + s) of
   (V[fv[0, f], c] (1 - u - v) + V[fv[1, f], c] u) + V[fv[2, f], c] v, f = max(face[p], 0), u = bu[p],
   v = bv[p]; fv (3, M) with strides (sj, sf); V (N, 3) and out (n, 3) contiguous. The layouts of u, v
   and V are fixed (runtime strides for them made the loop 1.6x slower); fv's are not. */
#define RESOLVE3(NAME, IT)                                                                             \
void NAME(const int64_t* face, const float* bu, const float* bv, const uint8_t* hit, const IT* fv,    \
          int64_t sj, int64_t sf, const float* val, int64_t S2, int64_t i0, int64_t i1, float* out) { \
    const float inv = 1.0f / (float)S2;                                                               \
    for (int64_t i = i0; i < i1; ++i) {                                                                \
        float a0 = 0.0f, a1 = 0.0f, a2 = 0.0f;                                                         \
        for (int64_t p = i * S2; p < (i + 1) * S2; ++p) {                                              \
            if (!hit[p]) continue;                                                                     \
            const int64_t f = face[p] < 0 ? 0 : face[p];                                               \
            const float u = bu[p], v = bv[p], w = 1.0f - u - v;                                        \
            const float* x = val + 3 * (int64_t)fv[f * sf];                                            \
            const float* y = val + 3 * (int64_t)fv[sj + f * sf];                                       \
            const float* z = val + 3 * (int64_t)fv[2 * sj + f * sf];                                   \
            a0 += (x[0] * w + y[0] * u) + z[0] * v;                                                    \
            a1 += (x[1] * w + y[1] * u) + z[1] * v;                                                    \
            a2 += (x[2] * w + y[2] * u) + z[2] * v;                                                    \
        }                                                                                              \
        out[3 * i] = a0 * inv;                                                                         \
        out[3 * i + 1] = a1 * inv;                                                                     \
        out[3 * i + 2] = a2 * inv;                                                                     \
    }                                                                                                  \
}
RESOLVE3(resolve3_i64, int64_t)
RESOLVE3(resolve3_i32, int32_t)
/* The same over pixels [0, n) on nt threads of OpenMP's team (the libgomp torch loaded: the threads
   Inductor's kernels use), thread k the pixels [n k / nt, n (k + 1) / nt): each pixel one thread's. */
#define RESOLVE3_PAR(NAME, SERIAL, IT)                                                                 \
void NAME(const int64_t* face, const float* bu, const float* bv, const uint8_t* hit, const IT* fv,    \
          int64_t sj, int64_t sf, const float* val, int64_t S2, int64_t n, int64_t nt, float* out) {  \
    _Pragma("omp parallel for num_threads(nt) schedule(static, 1)")                                   \
    for (int64_t k = 0; k < nt; ++k)                                                                   \
        SERIAL(face, bu, bv, hit, fv, sj, sf, val, S2, n * k / nt, n * (k + 1) / nt, out);            \
}
RESOLVE3_PAR(resolve3_i64_par, resolve3_i64, int64_t)
RESOLVE3_PAR(resolve3_i32_par, resolve3_i32, int32_t)
"""
_I64, _P = ctypes.c_int64, ctypes.c_void_p
_SIG = [_P, _P, _P, _P, _P, _I64, _I64, _P, _I64, _I64, _I64, _P]
# Pixels per thread below which one thread resolves the image. More go to OpenMP's team (the libgomp
# torch loaded, `_SOURCE`): chess bench 256² × 2², 2 threads, quiet machine, 10 ms idle and a parallel
# torch op before each call (`python -m benchmarks.gouraud_resolve`): compiled kernel 1.33 ms, native
# on one thread 1.41, native on the team 0.93 (session 26); a Python thread pool instead (its
# hand-off waits for a core the OpenMP workers spin on) read 1.63 quiet and 8.7 ms at load ~6.
_NATIVE_MIN_PIXELS = 1 << 13


def _native() -> "ctypes.CDLL | None":
    return native.load("gouraud", _SOURCE, {"resolve3_i64": _SIG, "resolve3_i32": _SIG, "resolve3_i64_par": _SIG,
                                            "resolve3_i32_par": _SIG}, extra_flags=("-fopenmp",))


def _resolve_native(values: Tensor, fv: Tensor, face: Tensor, bu: Tensor, bv: Tensor, hit: Tensor, n: int,
                    S2: int) -> Tensor | None:
    """`_pixels` over all n pixels by the native loop (on ``torch.get_num_threads()`` threads of
    OpenMP's team, at least `_NATIVE_MIN_PIXELS` pixels each, in contiguous ranges; each pixel's sum by
    one thread: the same bits at any thread count),
    or None when the loop is not built or the arrays are not CPU tensors of its types (face int64 and
    hit bool contiguous, u / v float32, fv (3, M) int32 / int64 of any strides, values (N, 3)
    float32)."""
    lib = _native()
    if (lib is None or values.ndim != 2 or values.shape[1] != 3 or values.dtype != torch.float32
            or face.dtype != torch.int64 or hit.dtype != torch.bool or bu.dtype != torch.float32
            or fv.dtype not in (torch.int32, torch.int64) or fv.ndim != 2 or fv.shape[0] != 3
            or not (face.is_contiguous() and hit.is_contiguous())
            or any(t.device.type != "cpu" for t in (values, fv, face, bu, bv, hit))):
        return None
    # the loop's fixed layouts (its C source): no copy for the G-buffer's column-major barycentrics,
    # a (N, 3) copy of a transposed values table (N·12 bytes)
    values, bu, bv = values.contiguous(), bu.contiguous(), bv.contiguous()
    out = torch.empty(n, 3, dtype=torch.float32)
    fn = lib.resolve3_i64 if fv.dtype == torch.int64 else lib.resolve3_i32
    args = (face.data_ptr(), bu.data_ptr(), bv.data_ptr(), hit.data_ptr(), fv.data_ptr(), fv.stride(0),
            fv.stride(1), values.data_ptr(), S2)
    op = out.data_ptr()
    nt = max(1, min(torch.get_num_threads(), n // _NATIVE_MIN_PIXELS))
    if nt == 1:
        fn(*args, 0, n, op)
    else:
        par = lib.resolve3_i64_par if fv.dtype == torch.int64 else lib.resolve3_i32_par
        par(*args, n, nt, op)
    return out


def resolve(values: Tensor, fv: Tensor, face: Tensor, bary: Tensor, hit: Tensor, height: int, width: int,
            spp_side: int, *, native_resolve: bool = True) -> Tensor:
    """The (height, width, C) image of per-vertex radiance ``values`` (N, C) Gouraud-interpolated to
    the samples (face (P,) int64, −1 on a miss; bary (P, 2) float32 (u, v); hit (P,) bool; P =
    height·width·spp_side², pixel-major as ``GBuffer``) and box-filtered; fv (3, M) int the rows of
    ``values`` at each face's three corners (a face's corner may map to a per-region copy of a vertex).
    Misses count as 0. Equals `resolve_reference` to float32 round-off. The kernel's loads are not
    bounds-checked (`_NO_ASSERT`); the ranges (every face in [−1, M), every entry of fv in [0, N))
    are checked once per call: ValueError otherwise. On the CPU the sums are made by a C loop
    (`_resolve_native`, the same bits as the compiled kernel) when it is built; ``native_resolve``
    False (tests: the oracle) or no C compiler runs the compiled kernel."""
    S2 = spp_side * spp_side
    n = height * width
    if face.shape[0] != n * S2:
        raise ValueError(f"G-buffer has {face.shape[0]} samples, expected {height}x{width}x{S2}")
    # the kernel's loads are unchecked, so the ranges are checked here, once per call (two
    # reductions: ~0.05 ms of the ~0.3 ms the per-load checks cost a bench frame): a G-buffer of
    # another mesh, or a corner table of another ``values``, is an error, not a read out of bounds
    if fv.numel() and face.numel():
        flo, fhi = torch.aminmax(face)
        # over the contiguous layout when fv is a transposed view (ZH passes F.T): the same elements,
        # so the same min and max, without aminmax's copy of a strided input (bench creature, 1
        # thread: 0.27 -> 0.02 ms of every vertex-shaded frame; issue 14, session 25)
        vlo, vhi = torch.aminmax(fv.T if not fv.is_contiguous() and fv.T.is_contiguous() else fv)
        if int(flo) < -1 or int(fhi) >= fv.shape[1] or int(vlo) < 0 or int(vhi) >= values.shape[0]:
            raise ValueError(f"G-buffer faces in [{int(flo)}, {int(fhi)}] and corner rows in [{int(vlo)}, "
                             f"{int(vhi)}] do not fit {fv.shape[1]} faces and {values.shape[0]} vertex rows "
                             "(a G-buffer of another mesh?)")
    # the tables' sizes vary per scene: symbolic, so one compiled kernel serves every scene
    torch._dynamo.maybe_mark_dynamic(values, 0)
    torch._dynamo.maybe_mark_dynamic(fv, 1)
    # u and v as two (n, S²) rows: views, no copy, of a column-major (P, 2) bary (the G-buffer's);
    # the (n, S², 2) row-major copy `map_rows` made of it cost 1/5 of the stage (bench creature,
    # 256² × 2², 1 thread, load ~9: 3.70 → 2.98 and 2.77 → 2.23 ms, bit-identical; issue 14)
    bu, bv = bary.float().unbind(-1)
    img = _resolve_native(values, fv, face, bu, bv, hit, n, S2) if native_resolve else None
    if img is not None:
        return img.view(height, width, -1)
    rows = (face.view(n, S2), bu.view(n, S2), bv.view(n, S2), hit.view(n, S2))
    # the frame's pixels in one static block (its pixel count rounded up to a power of two, at most
    # `RESOLVE_BLOCK_MAX`): the count is the image's, the same every frame of a sequence, so one
    # variant per resolution, compiled by the warm-up frame. Blocks of CHUNK / S² pixels were 8 calls
    # per bench frame, ~0.08 ms each of guards and wrapper: bench creature 256² × 2², 1 thread,
    # same process, load ~8: 2.15-2.38 → 1.49 ms, bit-identical
    img = map_rows(_pixels, rows, (fv, values.float()), chunk=pow2_block(n, RESOLVE_BLOCK_MIN, RESOLVE_BLOCK_MAX))
    return img.view(height, width, -1)


def resolve_reference(values: Tensor, fv: Tensor, face: Tensor, bary: Tensor, hit: Tensor, height: int,
                      width: int, spp_side: int) -> Tensor:
    """`resolve` step by step (the test oracle): the G-buffer's barycentric interpolation, then its
    box filter (``GBuffer.interpolate`` and ``GBuffer.resolve``)."""
    f = face.clamp_min(0)
    idx = fv.T.long()[f]                                              # (P, 3)
    u, v = bary.float().unbind(-1)
    w = torch.stack([1.0 - u - v, u, v], -1)
    w = torch.where(hit[:, None], w, torch.zeros_like(w))
    per_sample = (values.float()[idx] * w[..., None]).sum(1)
    x = torch.where(hit[:, None], per_sample, torch.zeros_like(per_sample))
    return x.view(height, width, spp_side * spp_side, -1).mean(2)


def resolve_matrix(fv: Tensor, face: Tensor, bary: Tensor, hit: Tensor, height: int, width: int, spp_side: int,
                   num_values: int) -> Tensor:
    """`resolve` as a sparse (height·width, num_values) CSR matrix S (float32): ``S @ values`` is
    the (height·width, C) image of `resolve` (arguments as there) — each pixel's S²·3 barycentric
    weights ÷ S², misses dropped, a vertex met by several of a pixel's samples summed once (3.4
    entries per pixel on the bench creature instead of 12). For a caller that resolves new values
    on the same G-buffer (a lighting-only frame: the camera and geometry unchanged): one sparse
    product (0.86 vs 2.6 ms for `resolve` at 256² × 2², 1 thread), the same sums to float32
    round-off (the merged weights are added first). Building it sorts the P·3 entries (~0.1 s)."""
    S2 = spp_side * spp_side
    n = height * width
    if face.shape[0] != n * S2:
        raise ValueError(f"G-buffer has {face.shape[0]} samples, expected {height}x{width}x{S2}")
    keep = hit.nonzero().squeeze(-1)
    u, v = bary.float().index_select(0, keep).unbind(-1)
    w = torch.stack([1.0 - u - v, u, v], 1) * (1.0 / S2)                           # (H, 3)
    vid = fv.T.long().index_select(0, face.index_select(0, keep))                 # (H, 3)
    pix = (keep // S2)[:, None].expand(-1, 3)
    S = torch.sparse_coo_tensor(torch.stack([pix.reshape(-1), vid.reshape(-1)]), w.reshape(-1), (n, num_values),
                                check_invariants=False)   # (in range by construction)
    with warnings.catch_warnings():   # "sparse CSR support is in beta": the product used is the plain one
        warnings.simplefilter("ignore", UserWarning)
        return S.coalesce().to_sparse_csr()
