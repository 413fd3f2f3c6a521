"""Gouraud resolve: per-vertex radiance interpolated to the G-buffer's samples with their
barycentrics and box-filtered into pixels, in one pass over the samples (issue 14).

The reference is two ``scenes.frame.GBuffer`` calls, ``resolve(interpolate(values, F))``: gather the
three vertex rows of each sample's face, weight them by (1 − u − v, u, v), zero the misses, average
each pixel's S² sub-samples. `resolve` computes the same sums per pixel (unrolled: three vertices,
S² sub-samples) as one compiled kernel over static blocks of pixels (``methods.core.fused``), so the
per-sample radiance is never written to memory; it equals the reference to float32 round-off.

Used by the methods that shade per vertex and interpolate the radiance (the paper's run time of
Mahajan 2008 "interactive at 17K vertices", Ma 2006 §3.3, Sun 2007's GPU path).
"""
from __future__ import annotations

import functools
import warnings

import torch
from torch import Tensor

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


def resolve(values: Tensor, fv: Tensor, face: Tensor, bary: Tensor, hit: Tensor, height: int, width: int,
            spp_side: int) -> Tensor:
    """The (height, width, C) image of per-vertex radiance ``values`` (N, C) Gouraud-interpolated to
    the samples (face (P,) int64, −1 on a miss; bary (P, 2) float32 (u, v); hit (P,) bool; P =
    height·width·spp_side², pixel-major as ``GBuffer``) and box-filtered; fv (3, M) int the rows of
    ``values`` at each face's three corners (a face's corner may map to a per-region copy of a vertex).
    Misses count as 0. Equals `resolve_reference` to float32 round-off. The kernel's loads are not
    bounds-checked (`_NO_ASSERT`); the ranges (every face in [−1, M), every entry of fv in [0, N))
    are checked once per call: ValueError otherwise."""
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
