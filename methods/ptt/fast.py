"""Batched run time of the PTT method (Sun et al. 2007 eq. 3–4, §4.1) — the same image as the
per-stage reference path of ``methods.ptt.method`` (`PTT._render_reference`), to float32 round-off,
with the work arranged for the machine instead of for reading:

Lighting stage (Sun eq. 4, "light" changed):
* E⁰_x(k) = Σ_l C^L_l U^{I0}_x(l, k) as one sparse (CSR) × dense product over the kept (index,
  value) pairs (no (V, K, n_L, 3) gather; `direct_incidence`);
* T¹L = T¹ ·_l C^L and T²L = T² ·_l C^L as plain GEMMs over the contiguous (…, l) layout
  (`relayout_t1` / `relayout_t2` store T¹ (vertex, SH)-major and T² lighting-last once; the
  reference reads views of the same storage), with the (3, n_l) lighting operand row-major
  (`light_product`);
* the prefiltered maps E^(k) on the env map's grid (``specular.on_env_grid``), stacked
  (`EnvStack`) so one bilinear look-up reads every lobe.

BRDF stage ("brdf" or "light" changed), products of H cached for the view stage:
* the per-region view tables W_r(ωo, k, c) = Σ_p H(r, p, c) W(p, ωo, k) — Sun eq. 3's
  D ×_h U^h(H) — and lobe weights a_k(r, θo, c) = Σ_p H(r, p, c) a_k^p(θo) (§4.1);
* E_x(k) (U^{I0} + U^{I1} + U^{I2}): the sums over (r, p) are GEMMs with per-channel weights
  (`brdf_products`); the one-bounce SH radiance I1_x stays in x's frame (shading="vertex") or is
  rotated to the world frame, I1w_x = M(F_xᵀ) I1_x (``methods.core.sh_rotation``; exact for
  band-limited SH; shading="pixel", where it is interpolated over the triangle before evaluation).

View stage, shading="vertex" (Sun's run time: exit radiance per vertex, interpolated), every frame:
* per (vertex, region) pair at the vertex's own view direction ωo_x (`vertex_view`): the glossy
  term B_x = Σ_k W_r(ωo_x, k) E_x(k) (one 4-row bag of the region table), the lobe factors
  s_x(k) = a_k(θo_x) V_c^(k)(x, R_x) (2-node interpolation, 4-row bag of the visibility tables) and
  the one-bounce lobe term u_x (SH at R_x, one GEMM with the Funk–Hecke factors);
* per hit sample, two compiled loops per static block of samples: `mirror_cells` (vectorised over
  the samples: the lat-long coordinates of the mirror direction R about the interpolated shading
  normal — `mirror_uv`, the one formula the reference reads the maps with too — and R's bilinear
  cell, row and fractions) and `shade_block`: the face's three pair rows with the barycentrics,
  the four corners of R's cell in the stacked E^(k) (`env_rows`, on the lanes of the s_k columns),
  max(0, B) + u + Σ_k s_k E^(k)(R) and the box filter of the pixel's samples.
  Each row is one contiguous 64-byte load, and the whole stage is one loop over the pixels
  (`SHADE_OPTIONS`). Measured on the chess bench V frame (1 thread, CPU time, load 11): about a third
  of `shade_block` is the env rows' cache misses (8.4 MB of rows, not L2-resident: every sample
  reading one fixed cell instead ran 1.48x faster), the rest its per-sample scalar arithmetic and
  row products. Visiting the pixels in 8×16 or 4×64 tiles instead of scanlines (index arithmetic
  inside the kernel, same output bits) ran 0.96–0.97x: the env rows of one scanline are still cached
  when the next one reads them. Session 19 (ptv): with every index fixed (all rows in L1) the kernel
  still took 4.6 of 5.6 ms — scalar arithmetic bound, not miss bound; the cell arithmetic moved to
  the sample-vectorised `mirror_cells` (same bits) made the V frame 1.16–1.21x (chess / creature
  bench, 1 thread, CPU time, same process vs main). `shade_samples` is the eager form.
  Session 26 (ptt26): both loops run natively where they can be bit-identical (``methods.ptt.native``:
  `shade_block` as a C loop with prefetched env rows, the cells with Inductor's AVX2 operations and the
  same Sleef acos / atan2, one pass per thread; `USE_NATIVE`); the compiled loops stay the fallback
  and the tests' oracle. V frames 1.24x (chess bench, 11.9 -> 9.6 ms) and 1.17x (creature, 12.2 ->
  10.4 ms), VB 1.25x / 1.19x (1 thread, process CPU, same process vs main, images bit-identical).

View stage, shading="pixel" (every frame), per hit sample and vertex v of its triangle:
* glossy term B_v = Σ_k W_r(ωo in v's frame, k) E_v(k): bilinear in the table, so it is
  Σ_corners w X(v, r, corner) with X(v, r, t) = Σ_k W_r(t, k) E_v(k). X is formed once per frame
  on a WINDOW×WINDOW texel window per (vertex, region) pair around the camera's direction from the
  vertex (`view_windows`); the sample–vertex entries whose bilinear cell lies in the window are
  one ``embedding_bag`` (12 weighted rows per sample), the rest (a few near silhouettes / on large
  triangles) are evaluated exactly from W_r and E (`_glossy_outliers`). The window only decides
  *where* the sum is formed, never its terms;
* lobes: a_k by a 2-row bag over the region tables, the prefiltered maps E^(k)(R) as the
  reference, V_c^(k) as a 12-row bag over the per-vertex tables (stored texel-major), and the SH
  term from the 3-row bag of I1w.

Plain torch on the device of the precomputed arrays; the per-pair and per-sample view passes are
compiled loops (``methods.core.fused``) with eager twins that the tests compare them with.
"""
from __future__ import annotations

import functools
import math
import warnings
from dataclasses import dataclass, field

import torch
import torch.nn.functional as Fnn
from torch import Tensor

from methods.core import sh as _sh
from methods.core.frames import frame_matrix, reflect
from methods.core.fused import fused, map_rows, neighbour_blocks, pow2_block, warm_blocks
from methods.core.latlong import bilinear_taps
from methods.core.sh_rotation import sh_rotation_matrix
from methods.ptt import specular as _spec
from methods.ptt.transport import table_coords

__all__ = ["FastStatic", "build_static", "relayout_t2", "direct_incidence", "view_table_rows", "region_tables", "brdf_products",
           "view_windows", "shade", "specular_lobes", "WINDOW"]

# Side of the per-(vertex, region) texel window of the glossy term (`view_windows`; at most the
# table size): a sample's bilinear cell may sit ±(WINDOW − 2)/2 texels from the anchor and still be
# read from the window (the rest take the exact per-entry path).
WINDOW = 4


@dataclass
class FastStatic:
    """View- and lighting-independent arrays of the fast path (built once after precompute).

    frames: (V, 3, 3) vertex frame matrices (rows s, t, n; ``core.frames.frame_matrix``).
    pair_of: (V·R,) int64 index of the (vertex, region) pair v·R + r (−1: no face of region r
        touches v); pair_v, pair_r: (n_pairs,) its vertex and region.
    sh_rot: (V, S, S) block-diagonal SH rotation local → world per vertex, or None.
    face_pairs: (M, 3) the pair of each face corner (its vertex with the face's region).
    pair_pos: (3, n_pairs) vertex positions, pair_frame: (9, n_pairs) frame rows s, t, n of each
        pair's vertex, components as contiguous rows (shading="vertex").
    pair_is_vertex: the pairs are the vertices in order (every vertex shades one region), so
        per-vertex rows need no gather.
    """

    frames: Tensor
    pair_of: Tensor
    pair_v: Tensor
    pair_r: Tensor
    sh_rot: Tensor | None
    face_pairs: Tensor | None = None
    pair_pos: Tensor | None = None
    pair_frame: Tensor | None = None
    pair_is_vertex: bool = False
    face_pairs_miss: Tensor | None = field(default=None, repr=False)  # `miss_face_pairs` (built on first use)
    pair_rv32: tuple | None = field(default=None, repr=False)  # `pair_indices32` (built on first use)

    def tensors(self) -> list[Tensor]:
        return [t for t in (self.frames, self.pair_of, self.pair_v, self.pair_r, self.sh_rot, self.face_pairs,
                            self.pair_pos, self.pair_frame) if t is not None]


def build_static(V: Tensor, N: Tensor, F: Tensor, face_region: Tensor, n_regions: int,
                 sh_order: int | None) -> FastStatic:
    """`FastStatic` of a mesh: V (V, 3) positions, N (V, 3) unit vertex normals, F (M, 3) faces,
    face_region (M,); sh_order: order of the per-vertex SH rotations (None: not needed)."""
    nv, dev = N.shape[0], N.device
    frames = frame_matrix(N.float())
    key = (F.long() * n_regions + face_region.long()[:, None]).reshape(-1)
    used = torch.zeros(nv * n_regions, dtype=torch.bool, device=dev)
    used[key] = True
    pairs = torch.nonzero(used).squeeze(-1)
    pair_of = torch.full((nv * n_regions,), -1, dtype=torch.int64, device=dev)
    pair_of[pairs] = torch.arange(pairs.numel(), device=dev)
    sh_rot = None
    if sh_order is not None:
        # local coefficients c: f(d_world) = Σ c_s Y_s(F d_world) = f'(d) with f'(d) = f(Rᵀ d), R = Fᵀ
        sh_rot = sh_rotation_matrix(frames.double().transpose(1, 2), sh_order).float()
    face_pairs = pair_of[key].view(-1, 3).contiguous()
    pv = pairs // n_regions
    return FastStatic(frames, pair_of, pv, pairs % n_regions, sh_rot, face_pairs,
                      V.float()[pv].T.contiguous(), frames[pv].reshape(-1, 9).T.contiguous(),
                      bool(pv.numel() == nv and torch.equal(pv, torch.arange(nv, device=dev))))


def miss_face_pairs(st: FastStatic) -> Tensor:
    """``st.face_pairs`` (M, 3) with one more face (M + 1, 3) whose three corners are the zero row
    n_pairs of `vertex_view`'s table, built once per `FastStatic`. A miss sample's face is −1
    (``scenes.frame.GBuffer``), which indexes that last face (negative indices wrap, in eager torch and
    in Inductor's gathers alike), so its Gouraud sum is 0 and the compiled sample stage
    (`shade_pixels_fused`) shades a G-buffer with misses as it shades one without: 0 at a miss, as
    ``GBuffer.resolve`` counts it, and the same static shapes — no second compiled variant. (Before,
    a frame with misses took the two-pass `shade_samples_fused` route; its first such frame compiled
    two more graphs inside a timed frame: chess bench V frame 4, one miss in 262 144 samples, 0.98 s
    against 0.05 s.)"""
    if st.face_pairs_miss is None:
        n = st.pair_v.numel()
        zero = torch.full((1, 3), n, dtype=st.face_pairs.dtype, device=st.face_pairs.device)
        st.face_pairs_miss = torch.cat([st.face_pairs, zero]).contiguous()
    return st.face_pairs_miss



def referenced_pairs(st: FastStatic, face: Tensor) -> tuple[Tensor, Tensor]:
    """The pairs a frame's samples read (the corners' pairs of the faces in ``face`` (n,), a G-buffer's
    faces; −1 and other entries outside [0, M), misses, read none) and the faces' corners remapped
    onto them: sel (m,) the pairs in ascending order, fpc (M + 1, 3) the position in sel of each face
    corner's pair (m for a pair not in sel) with a last face of three m — `miss_face_pairs` for the
    table of `vertex_view(..., pairs=sel)`, whose zero row is m. The native loop
    (``native.referenced_pairs``: one pass over the samples) or the same integers in torch."""
    n_pairs = int(st.pair_v.numel())
    if USE_NATIVE:
        from methods.ptt import native as _native

        out = _native.referenced_pairs(face, st.face_pairs, n_pairs)
        if out is not None:
            return out
    M = int(st.face_pairs.shape[0])
    fm = torch.zeros(M, dtype=torch.bool, device=face.device)
    fm[face[(face >= 0) & (face < M)]] = True
    pm = torch.zeros(n_pairs, dtype=torch.bool, device=face.device)
    pm[st.face_pairs[fm].reshape(-1)] = True
    sel = torch.nonzero(pm).squeeze(-1)
    m = int(sel.numel())
    pos = torch.full((n_pairs + 1,), m, dtype=torch.int64, device=face.device)
    pos[sel] = torch.arange(m, device=face.device)
    return sel, pos[miss_face_pairs(st)]


def referenced_view(st: FastStatic, face: Tensor, cam_origin: Tensor, Wr: Tensor, E: Tensor, T: int, K: int,
                    lobes: dict, width: int) -> tuple[Tensor, Tensor] | None:
    """`referenced_pairs` + `vertex_view(..., pairs=sel)` with the rows at the pairs' own positions
    (``method.FULL_TABLE``): (face_pairs, table) — `miss_face_pairs` (static) and the (n_pairs + 1, C')
    rows of ``native.vertex_rows(..., rows_at=True)``, whose row p is pair p's row of `vertex_view` (the same
    bits: the same loop) for the pairs the faces in ``face`` touch, the last row 0, and the other rows
    unwritten (no face of ``face`` reads them). No compact positions and no (M + 1, 3) corners remapped
    each frame. None where the native loops do not run (lobes without the SH column, int32 rows); the
    caller then takes the compact route."""
    if not USE_NATIVE or lobes is None or lobes["I1"] is not None:
        return None
    vis = lobes["vis"]
    Tv = lobes["Tv"]
    if max(int(Wr.shape[0]), int(vis.shape[0])) >= 2 ** 31 - Tv * Tv - T * T:
        return None
    from methods.ptt import native as _native

    n_pairs = int(st.pair_v.numel())
    sel = _native.referenced_sel(face, st.face_pairs, n_pairs)
    if sel is None or sel.numel() == 0:
        return None
    ri, vi = pair_indices32(st)
    table = _native.vertex_rows(sel, st.pair_pos, st.pair_frame, cam_origin.to(st.pair_pos.dtype), ri, vi, T, Tv,
                                lobes["n_theta"], Wr, E, K, lobes["ar"], vis, max(width, 3 + lobes["ar"].shape[1]),
                                rows_at=True)
    if table is None:
        return None
    return miss_face_pairs(st), table


def all_true(mask: Tensor) -> bool:
    """``bool(mask.all())`` of a bool tensor, as the minimum of its bytes (a bool is stored as one
    byte, 0 false): ``Tensor.all`` on a bool tensor is a slow reduction — the G-buffer's hit mask
    of a bench frame (262 144 samples, 1 thread): 168 µs against 10 µs for the byte minimum, paid
    by every view frame (session 23, ptt23). Tested against ``Tensor.all``."""
    if mask.numel() == 0:
        return True
    if mask.dtype != torch.bool or not mask.is_contiguous():
        return bool(mask.all())
    return int(mask.view(torch.uint8).min()) != 0

def pair_indices32(st: FastStatic) -> tuple[Tensor, Tensor]:
    """``st.pair_r``, ``st.pair_v`` as int32 (built once per `FastStatic`): `pair_cells` computes its
    table rows in the indices' type, and AVX2 converts float <-> int32 natively but emulates
    float <-> int64, 64-bit products and min / max lane by lane (`_mirror_cells`)."""
    if st.pair_rv32 is None:
        st.pair_rv32 = (st.pair_r.to(torch.int32), st.pair_v.to(torch.int32))
    return st.pair_rv32


def relayout_t2(T2: Tensor) -> Tensor:
    """T² (V, L2, R, P, R, P) → the same values stored lighting-last, returned as a (V, L2, R, P, R, P)
    view of that storage (so `T2.permute(0, 2, 3, 4, 5, 1)` is contiguous)."""
    return T2.permute(0, 2, 3, 4, 5, 1).contiguous().permute(0, 5, 1, 2, 3, 4)


def relayout_t1(T1: Tensor) -> Tensor:
    """T¹ (V, R, P, S, L1) → the same values stored (V, S, R, P, L1), returned as a (V, R, P, S, L1)
    view of that storage (so `T1.permute(0, 3, 1, 2, 4)` is contiguous): the lighting product
    then comes out with the (r, p) pairs of one (vertex, SH coefficient) next to each other, and the
    BRDF stage's sum over them is one GEMM (`brdf_products`)."""
    return T1.permute(0, 3, 1, 2, 4).contiguous().permute(0, 2, 3, 1, 4)


# -- lighting / BRDF stages -------------------------------------------------------------------------


def direct_incidence(idx: Tensor, val: Tensor, CL: Tensor) -> Tensor:
    """E⁰_x(k) = Σ_n val[x, k, n] C^L[idx[x, k, n]]: idx, val (V, K, n_L); CL (6N², 3) → (V, K, 3).

    The kept (index, value) pairs are the rows of a CSR matrix (V·K, 6N²) with n_L entries each —
    views of idx and val, only the row offsets are made — times the dense C^L (MKL's sparse × dense
    product; each output row is one thread's, so the result does not depend on the thread count).
    Measured on the chess bench (131 MB of pairs, 1 thread, process CPU time, load 7): 14.9 ms vs
    23.8 ms for the weighted ``embedding_bag`` it replaces (`direct_incidence_bag`, kept as the
    alternative in ``benchmarks.ptt_profile``), 48.8 ms as a compiled gather-and-sum. C^L is padded
    to 4 columns (a zero one; the result is a (V, K, 3) view of the (V·K, 4) product), which MKL's
    product runs faster: on the chess bench's pairs (10 701 × 16 × 96, int32; 1 thread, process CPU
    time, same process, alternating, 15 repeats, load ~11) 19.3 vs 33.7 ms (1.75x; 1.10–1.14x on
    synthetic pairs of that shape) — the same sums in another order (float32 round-off: max
    |diff| 1.5e-6 of values up to 2.07). Row-major vs column-major C^L and sorted column indices
    made no difference (0.97–1.02x), 8 or 16 padded columns were slower than 4."""
    nv, K, nL = val.shape
    n = nv * K
    crow = torch.arange(0, n * nL + 1, nL, dtype=idx.dtype, device=idx.device)
    with warnings.catch_warnings():  # "sparse CSR support is in beta" (once per process)
        warnings.simplefilter("ignore", UserWarning)
        A = torch.sparse_csr_tensor(crow, idx.reshape(-1), val.reshape(-1), (n, CL.shape[0]))
    CL4 = torch.cat([CL.to(val.dtype), CL.new_zeros(CL.shape[0], 1, dtype=val.dtype)], 1)  # (6N², 4)
    return (A @ CL4).view(nv, K, 4)[..., :3]


def direct_incidence_bag(idx: Tensor, val: Tensor, CL: Tensor) -> Tensor:
    """`direct_incidence` as one weighted ``embedding_bag`` (the same sums; the previous fast path)."""
    nv, K, nL = val.shape
    out = Fnn.embedding_bag(idx.reshape(nv * K, nL), CL, per_sample_weights=val.reshape(nv * K, nL), mode="sum")
    return out.reshape(nv, K, 3)


def light_product(T: Tensor, CL: Tensor) -> Tensor:
    """Σ_l T[..., l] C^L[l, c]: T (..., n_l) contiguous, CL (n_l, 3) → (..., 3), as one GEMM with the
    lighting operand transposed (``F.linear``: MKL's skinny N = 3 product is several times faster
    with the (3, n_l) operand row-major than with (n_l, 3))."""
    return Fnn.linear(T.reshape(-1, T.shape[-1]), CL.T.contiguous()).reshape(*T.shape[:-1], 3)


def lighting_products(T1: Tensor | None, T1c, CL1: Tensor | None, T2: Tensor | None, CL2: Tensor | None,
                      n_rp: int) -> tuple[Tensor | None, Tensor | None]:
    """T¹L (V, S, R·P, 3) = T¹ ·_l C^L (dense T¹ stored as `relayout_t1`, or the compressed
    ``compress`` form T1c) and T²L (V, (R·P)², 3) = T² ·_l C^L (T² stored as `relayout_t2`)."""
    T1L = T2L = None
    if T1 is not None:
        T1L = light_product(T1.permute(0, 3, 1, 2, 4), CL1)
        T1L = T1L.reshape(T1L.shape[0], T1L.shape[1], n_rp, 3)
    elif T1c is not None:
        T1L = T1c.contract_light(CL1)  # (V, R·P·S, 3)
        T1L = T1L.reshape(T1L.shape[0], n_rp, -1, 3).permute(0, 2, 1, 3).contiguous()
    if T2 is not None:
        T2L = light_product(T2.permute(0, 2, 3, 4, 5, 1), CL2)
        T2L = T2L.reshape(T2L.shape[0], -1, 3)
    return T1L, T2L


def view_table_rows(W_tab: Tensor, K: int) -> Tensor:
    """The view tables W_tab (P·K, T, T) laid out (P, T², K·3): row (p, texel) holds W(p, k, texel)
    on the lanes (k, c) of every channel c, the left operands of `region_tables`' products (built
    once per precompute; 3× the tables)."""
    P = W_tab.shape[0] // K
    T2 = W_tab.shape[-1] * W_tab.shape[-2]
    return W_tab.reshape(P, K, T2).permute(0, 2, 1)[..., None].expand(P, T2, K, 3).reshape(P, T2, K * 3).contiguous()


def region_tables(H: Tensor, W_tab: Tensor, K: int, lobe_a: Tensor | None,
                  W_rows: Tensor | None = None, *, nt: int = 1,
                  out: tuple[Tensor, Tensor | None] | None = None,
                  one_thread: bool = False) -> tuple[Tensor, Tensor | None]:
    """Products of the BRDF coordinates H (R, P, 3) cached for the view stage:
    W_r (R·T², K·3) rows (r, texel) of Σ_p H(r, p, c) W(p, ·, k) (W_tab (P·K, T, T)), and
    a_r (R·n_θ, L·3) rows (r, θ node) of Σ_p H(r, p, c) a_k^p(θ) (lobe_a (P, n_θ, L)) or None.

    W_r is Σ_p W_rows[p] · H(r, p, c) over all regions at once, p in order, one lane-wise product
    and one add per p into W_r's layout (`view_table_rows`: the tables stored texel-major with each
    value on the three channel lanes, built once; None: built here) — the sum MKL's batched
    (T²·K, P) @ (P, 3) products formed, in the same order without FMA: the same bits (tested
    against the explicit float32 sum). Decision (session 22, ptt22): those products ran at ~1–2
    GFLOP/s (N = 3, K = P = 4: MKL's small-matrix path); chess bench (R = 3, P = 4, K = 16, T = 48;
    1 thread, back to back / 10 ms idle before each): bmm 1.06–1.12 / 1.48–1.58 ms, these seven
    passes 0.44–0.54 / 0.74–0.96 ms, the einsum of session 19 0.80 ms. ``addcmul_`` (0.37 ms) rounds
    the product and the sum once (FMA): other bits, not taken.

    With the native loop and NATIVE_TABLES (session 40) W_r comes from ``native.region_tables``: its rows
    over ``nt`` threads, written into ``out``'s W_r (the previous tables, when it fits) instead of fresh
    pages; the same bits. a_r stays the einsum (MKL's bits, which change with the shapes: fused
    multiply-adds for some, not for others — not reproduced in C).

    Session 41 (pt41): a_r by ``native_fit.ar_table`` — MKL's sgemm called with the einsum's own arguments
    (the same bits at every shape, tested) and the output laid out in the same C call, MKL on one thread by
    ``MKL_Set_Num_Threads_Local`` — instead of the einsum (its permutes, bmm dispatch and reshape copy:
    0.17–0.19 ms of a chess bench VB frame at 1 thread after the harness's G-buffer, 0.04–0.05 ms now).
    one_thread: the caller runs at its own thread count (no ``torch_threads(1)`` around the call: two
    ``set_num_threads`` calls fewer a VB frame); the paths other than the native W_r / a_r then run
    under ``torch_threads(1)`` here (BRDF_STAGE_THREADS; the einsum's bits at any thread count)."""
    if one_thread:
        from methods.core.threads import torch_threads

        Wr, ar = _region_tables_native(H, lobe_a, W_rows, nt, out) if USE_NATIVE else (None, None)
        if Wr is not None and (ar is not None or lobe_a is None):
            return Wr.view(-1, Wr.shape[-1]), ar
        with torch_threads(1):
            return region_tables(H, W_tab, K, lobe_a, W_rows, nt=nt, out=out)
    R, P, _ = H.shape
    if W_rows is None:
        W_rows = view_table_rows(W_tab, K)
    T2 = W_rows.shape[1]
    Wr = None
    if USE_NATIVE and NATIVE_TABLES:  # threaded, in place, the lanes from H (``native.region_tables``): the same bits
        from methods.ptt import native

        Wr = native.region_tables(W_rows, H, nt, None if out is None else out[0])
    if Wr is None:
        Hl = H.permute(1, 0, 2)[:, :, None, None, :].expand(P, R, 1, K, 3).reshape(P, R, 1, K * 3)  # lane (k, c): H(r, p, c)
    if Wr is None and USE_NATIVE:  # the same products and sums in one pass (``native.region_rows``)
        from methods.ptt import native

        Wr = native.region_rows(W_rows, Hl)
    if Wr is None:
        Wr = torch.mul(W_rows[0], Hl[0])  # (R, T², K·3)
        if P > 1:
            tmp = torch.empty_like(Wr)
            for p in range(1, P):
                torch.mul(W_rows[p], Hl[p], out=tmp)
                Wr.add_(tmp)
    ar = None
    if lobe_a is not None and USE_NATIVE:  # one C call: MKL's sgemm with the einsum's arguments, the same bits
        from methods.ptt import native_fit

        ar = native_fit.ar_table(H, lobe_a, None if out is None else out[1])
    if lobe_a is not None and ar is None:
        n, L = lobe_a.shape[1:]
        ar = torch.einsum("rpc,pnl->rnlc", H, lobe_a).reshape(R * n, L * 3)
    return Wr.view(R * T2, K * 3), ar


def _region_tables_native(H: Tensor, lobe_a: Tensor | None, W_rows: Tensor | None, nt: int,
                          out: tuple[Tensor, Tensor | None] | None) -> tuple[Tensor | None, Tensor | None]:
    """`region_tables`' native W_r (``native.region_tables``, ``nt`` threads) and a_r
    (``native_fit.ar_table``), each None where its loop does not run (or, W_r, without ``W_rows``)."""
    Wr = ar = None
    if W_rows is not None and NATIVE_TABLES:
        from methods.ptt import native

        Wr = native.region_tables(W_rows, H, nt, None if out is None else out[0])
    if Wr is not None and lobe_a is not None:
        from methods.ptt import native_fit

        ar = native_fit.ar_table(H, lobe_a, None if out is None else out[1])
    return Wr, ar


def _channel_weights(w: Tensor) -> Tensor:
    """(n, 3) weights → (3, n·3) matrix M with M[c, i·3 + c] = w[i, c] (0 elsewhere): x (…, n·3)
    @ Mᵀ is Σ_i x[…, i, c] w[i, c] per channel c as one GEMM."""
    n = w.shape[0]
    M = torch.zeros(3, n, 3, dtype=w.dtype, device=w.device)
    for c in range(3):
        M[c, :, c] = w[:, c]
    return M.reshape(3, n * 3)


def brdf_products(H: Tensor, E0: Tensor, T1L: Tensor | None, C: Tensor | None, T2L: Tensor | None,
                  Cu: Tensor | None) -> tuple[Tensor, Tensor | None]:
    """Sun eq. 4 for the current H (R, P, 3): E (V, K, 3) = E⁰ + Σ_s C(s, k) I1(s) + C_u(k) I2 and
    the one-bounce SH radiance I1 (V, S, 3) (None without bounces).
    T1L (V, S, R·P, 3); C (S, K); T2L (V, (R·P)², 3); Cu (K,). The sums over (r, p) are GEMMs over
    the contiguous (r, p, c) rows with per-channel weights (`_channel_weights`)."""
    E, I1 = E0, None
    Hf = H.reshape(-1, 3)
    if T1L is not None:  # U^{I1}
        nv, S = T1L.shape[:2]
        I1 = Fnn.linear(T1L.reshape(nv * S, -1), _channel_weights(Hf)).reshape(nv, S, 3)
        E = E + torch.einsum("sk,vsc->vkc", C, I1)
    if T2L is not None:  # U^{I2}
        HH = (Hf[:, None, :] * Hf[None, :, :]).reshape(-1, 3)
        I2 = Fnn.linear(T2L.reshape(T2L.shape[0], -1), _channel_weights(HH))
        E = E + Cu[None, :, None] * I2[:, None, :]
    return E, I1


# -- view stage -------------------------------------------------------------------------------------


def rows(t: Tensor, idx: Tensor) -> Tensor:
    """t[idx] for an integer index of any shape, as one ``index_select`` along dim 0 (faster than
    advanced indexing on CPU)."""
    return torch.index_select(t, 0, idx.reshape(-1)).reshape(*idx.shape, *t.shape[1:])


def _bilinear(uv: Tensor, T: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Texel-centred bilinear cell of table coordinates uv (..., 2) on a T×T table, border-clamped
    like ``grid_sample(align_corners=False, padding_mode="border")`` (and
    ``specular.lookup_vertex_tables``): column, row of the top-left corner (int64) and the
    fractions tx, ty."""
    x = ((uv + 1.0) * (T / 2.0) - 0.5).clamp(0.0, T - 1.0)
    i0 = x.floor().long().clamp(max=T - 2)
    t = x - i0.to(x.dtype)
    return i0[..., 0], i0[..., 1], t[..., 0], t[..., 1]


def _corner_weights(tx: Tensor, ty: Tensor, w: Tensor) -> list[Tensor]:
    """Weights w·bilinear of the corners (dx, dy) = (0,0), (1,0), (0,1), (1,1), four tensors of tx's shape."""
    a, b = (1 - tx) * w, tx * w
    return [a * (1 - ty), b * (1 - ty), a * ty, b * ty]


def _bilinear_bag(table: Tensor, base: Tensor, T: int, wc: list[Tensor]) -> Tensor:
    """Σ_{rows j, corners} wc[corner][q, j] table[base[q, j] + corner offset]: base (Q, m) flat index
    of the top-left corner in a row-major T-wide table (T·rows, C) → (Q, C); one bag per corner."""
    out = None
    for off, w in zip((0, 1, T, T + 1), wc):
        o = Fnn.embedding_bag(base + off if off else base, table, per_sample_weights=w, mode="sum")
        out = o if out is None else out + o
    return out


def to_vertex_frames(frames_q: Tensor, d: Tensor) -> Tensor:
    """Directions d (Q, 3, m) (m column vectors) in the frames (Q, 3, 3, 3) of each sample's 3
    vertices → (Q, 3, 3, m): [q, j, :, i] = frame_j @ d[q, :, i] (``core.frames.to_local``)."""
    Q, m = d.shape[0], d.shape[-1]
    return torch.bmm(frames_q.reshape(Q, 9, 3), d).reshape(Q, 3, 3, m)


def latlong_lookup(maps: list, d: Tensor) -> Tensor:
    """``EnvMap.radiance`` of several maps at the same world directions d (Q, 3) → (Q, len(maps), 3),
    the lat-long coordinates computed once per distinct map rotation (``scenes.envmap.bilinear_lookup``)."""
    from scenes.envmap import direction_to_uv

    out, uv = [], {}
    for e in maps:
        key = e.to_world.to(d).flatten().tolist()
        if tuple(key) not in uv:
            uv[tuple(key)] = direction_to_uv(e.to_local(d))
        u, v = uv[tuple(key)]
        H, W, _ = e.data.shape
        idx, fx, fy = bilinear_taps(u, v, H, W)
        ext = e.periodic_texels(d.device, d.dtype)
        wc = _corner_weights(fx, fy, torch.ones_like(fx))
        out.append(sum(w[:, None] * rows(ext, idx + o) for w, o in zip(wc, (0, 1, W + 1, W + 2))))
    return torch.stack(out, 1)


def view_windows(st: FastStatic, V: Tensor, cam_origin: Tensor, Wr: Tensor, E: Tensor, T: int, K: int,
                 window: int = WINDOW) -> tuple[Tensor, Tensor, Tensor]:
    """Per (vertex, region) pair: the window's first column/row (n_pairs,) int64 and
    X (n_pairs·window², 3) = Σ_k W_r(texel, k, c) E_v(k, c) on its texels (row-major in the window).
    The window is centred on the bilinear cell of the direction from the vertex to cam_origin (3,)."""
    v, r = st.pair_v, st.pair_r
    d = cam_origin[None, :] - rows(V, v)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    loc = torch.einsum("nab,nb->na", rows(st.frames, v), d)
    ix, iy, _, _ = _bilinear(table_coords(loc), T)
    h = (window - 2) // 2
    ax = (ix - h).clamp(0, T - window)
    ay = (iy - h).clamp(0, T - window)
    o = torch.arange(window, device=V.device)
    tex = (ay[:, None, None] + o[None, :, None]) * T + ax[:, None, None] + o[None, None, :]  # (n, w, w)
    idx = (r[:, None, None] * (T * T) + tex).reshape(v.numel(), window * window)
    X = (rows(Wr, idx).reshape(v.numel(), window * window, K, 3) * rows(E, v).reshape(-1, 1, K, 3)).sum(2)
    return ax, ay, X.reshape(-1, 3)


def shade(st: FastStatic, win: tuple[Tensor, Tensor, Tensor], Wr: Tensor, E: Tensor, T: int, K: int,
          vidx: Tensor, bw: Tensor, region: Tensor, loc_wo: Tensor, window: int = WINDOW) -> Tensor:
    """Glossy part of Sun eq. 3 at hit samples (module docstring): vidx, bw (Q, 3); region (Q,);
    loc_wo (Q, 3, 3) ωo in each vertex's frame → (Q, 3), clamped at 0 like the reference."""
    ax, ay, X = win
    nR = st.pair_of.numel() // st.frames.shape[0]
    ix, iy, tx, ty = _bilinear(table_coords(loc_wo), T)  # (Q, 3)
    w = bw * (loc_wo[..., 2] > 0).to(bw.dtype)
    pair = rows(st.pair_of, vidx * nR + region[:, None])  # (Q, 3)
    p = pair.clamp_min(0)
    dx, dy = ix - rows(ax, p), iy - rows(ay, p)
    inside = (pair >= 0) & (dx >= 0) & (dx <= window - 2) & (dy >= 0) & (dy <= window - 2)
    base = p * (window * window) + dy.clamp(0, window - 2) * window + dx.clamp(0, window - 2)
    out = _bilinear_bag(X, base, window, _corner_weights(tx, ty, w * inside.to(w.dtype)))
    miss = torch.nonzero(~inside & (w != 0))
    if miss.numel():
        q, j = miss[:, 0], miss[:, 1]
        wc = torch.stack(_corner_weights(tx[q, j], ty[q, j], w[q, j]), -1)
        out.index_add_(0, q, _glossy_outliers(Wr, E, T, K, vidx[q, j], region[q], ix[q, j], iy[q, j], wc))
    return out.clamp_min(0.0)


def _glossy_outliers(Wr: Tensor, E: Tensor, T: int, K: int, v: Tensor, r: Tensor, ix: Tensor, iy: Tensor,
                     wc: Tensor) -> Tensor:
    """The glossy term of sample–vertex entries outside their window, straight from W_r and E:
    v, r, ix, iy (n,); wc (n, 4) corner weights → (n, 3)."""
    base = r * (T * T) + iy * T + ix
    Wi = (wc[:, 0, None] * rows(Wr, base) + wc[:, 1, None] * rows(Wr, base + 1)
          + wc[:, 2, None] * rows(Wr, base + T) + wc[:, 3, None] * rows(Wr, base + T + 1))
    return (Wi.reshape(-1, K, 3) * rows(E, v).reshape(-1, K, 3)).sum(1)


def reflection(normal: Tensor, wo: Tensor) -> tuple[Tensor, Tensor]:
    """Unit shading normal n and mirror direction R = reflect(wo, n) (Q, 3) each, as the reference."""
    n = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    R = reflect(wo, n)
    return n, R / R.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def specular_lobes(lobe_theta_n: int, ar: Tensor, Ek: list, lobe_vis_rows: Tensor, Tv: int,
                   I1w: Tensor | None, lobe_sh: Tensor | None, order: int, n: Tensor, R: Tensor, wo: Tensor,
                   region: Tensor, vidx: Tensor, bw: Tensor, Rl: Tensor) -> Tensor:
    """Sun §4.1 separated lobes at hit samples (``specular`` docstring; the reference is
    `PTT._specular_lobes`): Σ_k a_k(H, θo) [E^(k)(R) Σ_v β_v V_c^(k)(v, R) + max(0, n·R) L1^(k)(R)].

    ar (R·n_θ, L·3) region lobe weights; Ek: L prefiltered maps; lobe_vis_rows (V·Tv², L);
    I1w (V, 3·S) world-frame one-bounce SH radiance (channel-major) or None; lobe_sh (L, order) Funk–Hecke factors;
    n, R (Q, 3) from `reflection`; wo (Q, 3); region (Q,); vidx, bw (Q, 3); Rl (Q, 3, 3) R in each
    vertex's frame. Returns (Q, 3)."""
    Q = wo.shape[0]
    L = len(Ek)
    cos_o = (n * wo).sum(-1)
    # a_k(H, θo): linear in θo over the nodes (specular.lobe_weights), per region
    nt = lobe_theta_n
    th = torch.acos(cos_o.clamp(-1.0, 1.0))
    x = (th / (math.pi / 2) * nt - 0.5).clamp(0.0, nt - 1.0)
    i0 = x.floor().long().clamp(max=nt - 2) if nt > 1 else torch.zeros_like(x, dtype=torch.long)
    t = x - i0.to(x.dtype)
    up = (cos_o > 0).to(t.dtype)
    r0 = region * nt
    ak = rows(ar, r0 + i0) * ((1 - t) * up)[:, None] + rows(ar, r0 + (i0 + 1).clamp(max=nt - 1)) * (t * up)[:, None]
    ak = ak.reshape(Q, L, 3)
    Erad = latlong_lookup(Ek, R)  # (Q, L, 3)
    # V_c^(k): per-vertex tables at R in each vertex's frame, interpolated over the triangle
    ix, iy, tx, ty = _bilinear(table_coords(Rl), Tv)
    wc = _corner_weights(tx, ty, bw * (Rl[..., 2] > 0).to(bw.dtype))
    Vc = _bilinear_bag(lobe_vis_rows, vidx * (Tv * Tv) + iy * Tv + ix, Tv, wc)  # (Q, L)
    Lk = Erad * Vc[..., None]
    if I1w is not None:  # one-bounce SH radiance, lobe-prefiltered, evaluated at R (world frame)
        S = order * order
        I = Fnn.embedding_bag(vidx, I1w, per_sample_weights=bw, mode="sum").reshape(Q, 3, S)
        IY = (I * _sh.sh_eval(R, order)[:, None, :]).reshape(Q * 3, S)
        band = torch.cat([torch.full((2 * b + 1,), b, device=wo.device) for b in range(order)])
        Li = (IY @ lobe_sh[:, band].T).reshape(Q, 3, L).transpose(1, 2)  # Σ_s f(l, band s) Y_s I_s
        Lk = Lk + Li.clamp_min(0.0) * (n * R).sum(-1).clamp_min(0.0)[:, None, None]
    return (ak * Lk).sum(1)


# -- view stage, per vertex (Sun's run time) --------------------------------------------------------


def pair_view_dirs(st: FastStatic, V: Tensor, cam_origin: Tensor,
                   pairs: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor]:
    """Vertex v, region r and ωo_x in x's frame (n, 3) of the (vertex, region) pairs ``pairs``
    (None: all), ωo_x = (cam − x)/|cam − x| the direction from the vertex to the camera."""
    v, r = (st.pair_v, st.pair_r) if pairs is None else (st.pair_v[pairs], st.pair_r[pairs])
    d = cam_origin[None, :] - rows(V, v)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    return v, r, torch.bmm(rows(st.frames, v), d[:, :, None])[:, :, 0]


def theta_nodes(cos_o: Tensor, nt: int, itype: torch.dtype = torch.int64) -> tuple[Tensor, Tensor]:
    """Node i0 (int64, or ``itype``) and fraction t of θo = acos(cos_o) on the n_θ lobe-table nodes,
    linear in θo and clamped at the end nodes (``specular.lobe_weights``)."""
    th = torch.acos(cos_o.clamp(-1.0, 1.0))
    x = (th * (nt / (math.pi / 2)) - 0.5).clamp(0.0, nt - 1.0)
    i0 = x.floor().to(itype).clamp(max=nt - 2) if nt > 1 else torch.zeros_like(x, dtype=itype)
    return i0, x - i0.to(x.dtype)


def _cell(c: Tensor, T: int, itype: torch.dtype = torch.int64) -> tuple[Tensor, Tensor]:
    """One axis of `_bilinear`: table coordinate c (n,) in [−1, 1] → first texel (int64, or ``itype``),
    fraction."""
    x = c.add(1.0).mul_(T / 2.0).sub_(0.5).clamp_(0.0, T - 1.0)
    i = x.floor().to(itype).clamp_(max=T - 2)
    return i, x.sub_(i)


def _bilinear_rows(base: Tensor, ix: Tensor, iy: Tensor, tx: Tensor, ty: Tensor, T: int,
                   w: Tensor) -> tuple[Tensor, Tensor]:
    """Rows (n, 4) base + (iy + dy)·T + ix + dx of the corners (0,0), (1,0), (0,1), (1,1) of a T-wide
    table and their weights (n, 4) = w · bilinear."""
    i0 = base + iy * T + ix
    idx = i0[:, None] + torch.tensor([0, 1, T, T + 1], dtype=i0.dtype, device=i0.device)
    a, b = (1.0 - tx) * w, tx * w
    wt = torch.empty(idx.shape, dtype=w.dtype, device=w.device)
    torch.mul(a, 1.0 - ty, out=wt[:, 0])
    torch.mul(b, 1.0 - ty, out=wt[:, 1])
    torch.mul(a, ty, out=wt[:, 2])
    torch.mul(b, ty, out=wt[:, 3])
    return idx, wt


def vertex_view(st: FastStatic, cam_origin: Tensor, Wr: Tensor, E: Tensor, T: int, K: int,
                lobes: dict | None = None, width: int = 0, pairs: Tensor | None = None) -> Tensor:
    """Per (vertex, region) pair, at the vertex's own view direction ωo_x = (cam − x)/|cam − x|:
    the rows (n_pairs + 1, C) that the samples interpolate (the last row is 0, for padding). The
    reference is `PTT._vertex_terms`.

    Columns: B (3) = Σ_k W_r(ωo_x, k) E_x(k) (Sun eq. 3, glossy remainder; 0 when ωo_x is below
    x's horizon); with lobes (§4.1) also s (3L, lobe-major) = a_k(r, θo_x) V_c^(k)(x, R_x) and,
    with the one-bounce SH radiance, u (3) = cos⁺θo_x Σ_k a_k(r, θo_x) max(0, L1^(k)_x(R_x)), R_x
    the mirror direction of ωo_x about n_x (in x's frame (−ωo_x, −ωo_y, ωo_z), so its table
    coordinates are those of ωo_x negated).

    width > C: the rows padded with zero columns to that width (`table_width`, what the compiled
    sample stage reads).

    pairs (m,) int64: the rows of these pairs only (m + 1 rows, the zero row last; `referenced_pairs`
    gives the pairs a frame's samples read and the faces remapped onto them), by the same compiled
    loops with the pair columns gathered inside (`pair_cells_of`) and the pair count symbolic (one
    compiled variant for every m): row i equals row pairs[i] of the full table bit for bit (tested).

    Wr (R·T², K·3), E (V, K·3) row-major; lobes: dict(ar (R·n_θ, L·3), n_theta, vis (V·Tv², L)
    texel-major, Tv, I1 (V, S, 3) local-frame one-bounce SH radiance or None, f (L, S) the lobes'
    Funk–Hecke factors per SH coefficient, order). Components are handled as contiguous rows
    (``FastStatic.pair_pos`` / ``pair_frame``).

    Two compiled passes: the per-pair directions, table cells and the visibility look-up V_c
    (`pair_cells`) and the combination (`pair_rows`: the W_r bag as four row loads, its sums over K
    and the SH coefficients unrolled). Measured on the chess bench (10 701 pairs, 1 thread, process
    CPU time, load 6–8): 1.4 ms vs 5.4–5.9 ms for the same arithmetic as ~150 eager passes (each a
    launch over n elements plus its temporaries); the W_r bag moved into `pair_rows` (session 19,
    ptv): bag + `pair_rows` 1.12 ms -> 0.67 ms (load ~12).

    Decision (session 20, ptv): the weighted 4-row bag of the visibility tables (an eager
    ``embedding_bag`` over the (V·Tv², L) rows, 44 MB on the chess bench, its rows cache-cold in a
    suite frame) is gathered inside `pair_cells`, the loop that computes its cells, vectorised over
    the pairs: no (n, 4) index / weight arrays and no third pass, and the loads of 16 pairs are in
    flight together. `vertex_view` alone (1 thread, process CPU time, same process, alternating,
    0.2 s idle before each call as the suite's frames; two runs, load 3–6): chess bench 3.64–3.68 ->
    3.39–3.41 ms and 2.89 -> 2.61 ms, creature 3.82 -> 3.43 ms (back to back 1.30–1.82 -> 1.24–1.48). Moving the bag into `pair_rows` instead was slower (3.3 -> 4.2 ms
    settled): that loop is vectorised along the 16 lanes of a row, so the L = 4 values of each
    corner became per-lane scalar gathers with an integer division each.

    Decision (session 29, ptt29): with ``pairs`` (a shading="vertex" frame's referenced pairs), lobes
    and no SH column (order 0: the perf suite's bounces 0), one native pass (``native.vertex_rows``,
    `cells_available`) computes the rows: the compiled passes' products and sums in their order, the
    same Sleef atan2 / acos on 8 pairs at a time, B's lane sums as their reduction — the same bits
    (tested against the compiled passes) — without the two compiled calls (their guards, the
    symbolic-size launches, the (m, 4) index / weight arrays between them, the index_select of E),
    and with each pair's visibility, W_r and E rows prefetched a block of 32 pairs ahead. Chess bench
    V frames' calls (4 311 pairs, 1 thread, process CPU, 0.2 s settle, alternating): 1.91 -> 0.97 ms."""
    v, r = st.pair_v, st.pair_r
    order = lobes["order"] if lobes is not None and lobes["I1"] is not None else 0
    nt = lobes["n_theta"] if lobes is not None else 1
    Tv = lobes["Tv"] if lobes is not None else 2
    # table rows in int32 unless a table could have 2³¹ rows (`pair_indices32`)
    small = max(int(Wr.shape[0]), int(lobes["vis"].shape[0]) if lobes is not None else 0) < 2 ** 31 - Tv * Tv - T * T
    ri, vi = pair_indices32(st) if small else (r, v)
    pos, frm = st.pair_pos, st.pair_frame
    Ex = E if st.pair_is_vertex else rows(E, v)
    I1x = None
    if order:
        I1x = lobes["I1"] if st.pair_is_vertex else rows(lobes["I1"], v)
    vis = lobes["vis"] if lobes is not None else None
    if pairs is not None and USE_NATIVE and lobes is not None and not order and small:
        from methods.ptt import native as _native  # the same rows in one C pass (`native.vertex_rows`)

        out = _native.vertex_rows(pairs, pos, frm, cam_origin.to(st.pair_pos.dtype), ri, vi, T, Tv, nt, Wr, E, K,
                                  lobes["ar"], vis, max(width, 3 + lobes["ar"].shape[1]))
        if out is not None:
            return out
    if pairs is not None:  # the rows of these pairs only (`referenced_pairs`), their count symbolic
        m = int(pairs.numel())
        if m < 2:  # Dynamo specialises sizes 0 and 1 (``core.fused.call_rows``)
            pairs = torch.cat([pairs, pairs.new_zeros(2 - m)])
        torch._dynamo.maybe_mark_dynamic(pairs, 0)
        c = pair_cells_of(pairs, pos, frm, cam_origin.to(st.pair_pos.dtype), ri, vi, T, Tv, nt, lobes is not None,
                          order, vis)
        Ex = Ex.index_select(0, pairs)
        if I1x is not None:
            I1x = I1x.index_select(0, pairs)
        for t in (*c, Ex) + ((I1x,) if I1x is not None else ()):  # `pair_rows`' rows symbolic too
            torch._dynamo.maybe_mark_dynamic(t, 0)
    else:
        c = pair_cells(pos, frm, cam_origin.to(st.pair_pos.dtype), ri, vi, T, Tv, nt, lobes is not None, order, vis)
    masks = _channel_masks(K, str(Wr.device))
    if lobes is None:
        out = pair_rows(c[0], c[1], Wr, Ex, masks, K, width=width)
    else:
        out = pair_rows(c[0], c[1], Wr, Ex, masks, K, lobes["ar"], c[2], c[3], c[4], c[5], 1 if nt > 1 else 0, I1x,
                        c[7] if order else None, lobes["f"] if order else None, c[6], width)
    if pairs is not None and m < 2:  # the padding dropped: m rows and the zero row
        out = torch.cat([out[:m], out[-1:]])
    return out


def _pair_cells(pos: Tensor, frame: Tensor, cam: Tensor, r: Tensor, v: Tensor, T: int, Tv: int, nt: int,
                lobes: bool, order: int, vis: Tensor | None = None) -> tuple:
    """The gather-free per-pair arithmetic of `vertex_view`, for ``core.fused``: ωo_x in x's frame,
    the bilinear cell of its table coordinates in the region's W_r rows (idx, wt (n, 4); weight 0
    below x's horizon); with lobes the θo nodes of a_k (row r0 (n,), weights w0, w1 (n,)), the
    visibility V_c^(k)(x, R_x) (n, L) — the bilinear cell of R_x in x's table of ``vis`` (V·Tv², L)
    texel-major, its four rows weighted (the bag of the eager form) — cos⁺θo (n,) and, order > 0, the
    SH basis at R_x (n, order²). pos (3, n), frame (9, n) (``FastStatic.pair_pos`` / ``pair_frame``),
    cam (3,). Gather-free but for those four visibility rows."""
    dx, dy, dz = cam[0] - pos[0], cam[1] - pos[1], cam[2] - pos[2]
    inv = torch.rsqrt(dx * dx + dy * dy + dz * dz)
    x = (frame[0] * dx + frame[1] * dy + frame[2] * dz) * inv  # ωo_x in the frame (s, t, n)
    y = (frame[3] * dx + frame[4] * dy + frame[5] * dz) * inv
    z = (frame[6] * dx + frame[7] * dy + frame[8] * dz) * inv
    up = (z > 0).to(z.dtype)
    # table coordinates (transport.table_coords) of ωo_x
    rho = torch.sqrt(x * x + y * y)
    sc = torch.atan2(rho, z) * (2.0 / math.pi) / rho.clamp_min(1e-12)
    sc = torch.where(rho > 1e-12, sc, torch.full_like(sc, 2.0 / math.pi))
    cu, cv = x * sc, y * sc
    it = r.dtype  # int32 (`vertex_view`): AVX2 converts float <-> int32 natively, not int64 (`_mirror_cells`)
    ix, tx = _cell(cu, T, it)
    iy, ty = _cell(cv, T, it)
    idx, wt = _corner_rows(r * (T * T) + iy * T + ix, tx, ty, T, up)
    if not lobes:
        return idx, wt
    i0, t = theta_nodes(z, nt, it)  # a_k(θo): linear in θo over the nodes (specular.lobe_weights)
    jx, ux = _cell(-cu, Tv, it)  # R_x = (−x, −y, z): table coordinates negated
    jy, uy = _cell(-cv, Tv, it)
    vidx, vwt = _corner_rows(v * (Tv * Tv) + jy * Tv + jx, ux, uy, Tv, up)
    # rows by ``embedding``: no negative-index wrap (the indices are >= 0; `_shade_block`)
    Vc = (Fnn.embedding(vidx[:, 0], vis) * vwt[:, 0:1] + Fnn.embedding(vidx[:, 1], vis) * vwt[:, 1:2]
          + Fnn.embedding(vidx[:, 2], vis) * vwt[:, 2:3] + Fnn.embedding(vidx[:, 3], vis) * vwt[:, 3:4])  # (n, L) V_c^(k)(x, R_x): the weighted 4-row bag, gathered here
    out = (idx, wt, r * nt + i0, (1 - t) * up, t * up, Vc, z.clamp_min(0.0))
    if order:
        out = out + (_sh.sh_eval(torch.stack([-x, -y, z], -1), order),)
    return out


def _pair_cells_of(pairs: Tensor, pos: Tensor, frame: Tensor, cam: Tensor, r: Tensor, v: Tensor, T: int, Tv: int,
                   nt: int, lobes: bool, order: int, vis: Tensor | None = None) -> tuple:
    """`_pair_cells` of the pairs ``pairs`` (m,) only: their columns of pos, frame and entries of r, v
    gathered in the same loop."""
    return _pair_cells(pos[:, pairs], frame[:, pairs], cam, r[pairs], v[pairs], T, Tv, nt, lobes, order, vis)


def _corner_rows(i0: Tensor, tx: Tensor, ty: Tensor, T: int, w: Tensor) -> tuple[Tensor, Tensor]:
    """`_bilinear_rows` from the top-left row i0 (n,), as stacked columns (for ``core.fused``)."""
    a, b = (1.0 - tx) * w, tx * w
    idx = torch.stack([i0, i0 + 1, i0 + T, i0 + (T + 1)], -1)
    return idx, torch.stack([a * (1.0 - ty), b * (1.0 - ty), a * ty, b * ty], -1)


@functools.lru_cache(maxsize=8)
def _channel_masks(K: int, device: str) -> Tensor:
    """(3, K·3) float32 masks of the lanes (k, c) of channel c = 0, 1, 2 (`_pair_rows`)."""
    lane = torch.arange(3 * K)
    return torch.stack([(lane % 3 == c).float() for c in range(3)]).contiguous().to(device)


def _pair_rows(idx: Tensor, wt: Tensor, Wr: Tensor, Ex: Tensor, masks: Tensor, K: int, ar: Tensor | None = None,
               r0: Tensor | None = None, w0: Tensor | None = None, w1: Tensor | None = None, Vc: Tensor | None = None,
               step: int = 1, I1x: Tensor | None = None, Y: Tensor | None = None, f: Tensor | None = None,
               zc: Tensor | None = None, width: int = 0) -> Tensor:
    """The rows (n + 1, C) of `vertex_view` from the bilinear cells (idx, wt (n, 4): `_pair_cells`) in
    the region tables Wr (R·T², K·3) and E_x (n, K·3), for ``core.fused`` (sums unrolled):
    B = Σ_k Wi E_x with Wi = Σ_j wt_j Wr[idx_j] (four contiguous row loads, the bag of the eager
    form) and the sum over k as one lane-wise product and three masked lane sums (``masks``:
    `_channel_masks`); with lobes s = a_k V_c (a_k from the a_r rows r0, r0 + step with weights w0,
    w1; Vc (n, L)) and with I1x (n, S, 3), Y (n, S), f (L, S):
    u = cos⁺θo Σ_k a_k max(0, Σ_s f(k, s) Y_s I1_s); zero columns up to ``width``. Compiled with
    `SHADE_OPTIONS` (the gathered rows stay vector loads in the one loop over the pairs)."""
    n = idx.shape[0]
    Wi = (Fnn.embedding(idx[:, 0], Wr) * wt[:, 0:1] + Fnn.embedding(idx[:, 1], Wr) * wt[:, 1:2]
          + Fnn.embedding(idx[:, 2], Wr) * wt[:, 2:3] + Fnn.embedding(idx[:, 3], Wr) * wt[:, 3:4])
    P = Wi * Ex
    B = torch.stack([(P * masks[c]).sum(-1) for c in range(3)], -1)
    cols = [B]
    if ar is not None:
        L = ar.shape[1] // 3
        ak = Fnn.embedding(r0, ar) * w0[:, None] + Fnn.embedding(r0 + step, ar) * w1[:, None]  # (n, 3L)
        cols.append((ak.view(n, L, 3) * Vc[:, :, None]).reshape(n, 3 * L))
        if I1x is not None:
            S = Y.shape[1]
            P = [I1x[:, s_] * Y[:, s_:s_ + 1] for s_ in range(S)]  # Y_s I1_s (n, 3)
            u = None
            for k in range(L):
                Li = P[0] * f[k, 0]
                for s_ in range(1, S):
                    Li = Li + P[s_] * f[k, s_]
                t = ak[:, 3 * k:3 * k + 3] * Li.clamp_min(0.0)
                u = t if u is None else u + t
            cols.append(u * zc[:, None])
    C = sum(c.shape[1] for c in cols)
    if width > C:
        cols.append(B.new_zeros(n, width - C))
    # the zero last row padded onto every column block: one concatenation writes the rows in place
    return torch.cat([Fnn.pad(c, (0, 0, 0, 1)) for c in cols], 1)


pair_cells = fused(_pair_cells)
pair_cells_of = fused(_pair_cells_of)


@dataclass
class EnvStack:
    """The L maps E^(k) on one lat-long grid (``specular.on_env_grid``: the env map's, in its frame),
    their texels side by side so one bilinear look-up reads every lobe (`lookup_stack`):
    ext (H·(W+1), 3·L) periodic-extended (``scenes.envmap.extend_periodic``) texels, lobe-major
    columns (k, c) (a view of ``rows`` when `env_stack` wrote those first); to_world (3, 3) the
    maps' common frame (local = d @ to_world); H, W the grid.
    The lane-aligned copy of the texels that the compiled sample stage reads is `env_rows`."""

    ext: Tensor
    to_world: Tensor
    H: int
    W: int
    rows: dict = field(default_factory=dict, repr=False)  # width → `env_rows` (built on first use)


def env_stack(maps: list, width: int = 0) -> EnvStack:
    """`EnvStack` of EnvMaps sharing one grid and frame (``specular.on_env_grid``); ValueError if not.

    width > 0 (the `table_width` the compiled sample stage will read): the texels are written once,
    straight into their `env_rows` of that width, and ``ext`` is the (strided) view of those rows'
    lobe columns — no packed copy made first and then copied again onto the lanes. Measured on the
    chess bench's four 256×512 maps (1 thread, process CPU time, load ~10): 4.1–4.4 ms vs 6.3–6.4 ms
    for the packed ``ext`` and then `env_rows` (the same values, bit-identical)."""
    from scenes.envmap import extend_periodic

    H, W = maps[0].data.shape[:2]
    if any(m.data.shape[:2] != (H, W) or not torch.equal(m.to_world, maps[0].to_world) for m in maps):
        raise ValueError("the maps of an EnvStack must share their grid and to_world (specular.on_env_grid)")
    to_world = maps[0].to_world.to(maps[0].data.device, torch.float32).contiguous()
    L = len(maps)
    if width < 3 + 3 * L:
        ext = torch.cat([extend_periodic(m.data.float()) for m in maps], 1).contiguous()
        return EnvStack(ext, to_world, H, W)
    data = [m.data.float() for m in maps]
    pad = [data[0].new_zeros(H, W, 3)] + data + ([data[0].new_zeros(H, W, width - 3 - 3 * L)] if width > 3 + 3 * L
                                                 else [])
    out = data[0].new_empty(H, W + 1, width)
    torch.cat(pad, -1, out=out[:, :W])
    out[:, W] = out[:, 0]  # the periodic column (extend_periodic)
    out = out.view(H * (W + 1), width)
    return EnvStack(out[:, 3:3 + 3 * L], to_world, H, W, {width: out})


def env_rows(st: EnvStack, width: int) -> Tensor:
    """The stack's texels (H·(W+1), width) on the lanes of the per-pair rows (`table_width`): E^(k)
    channel c in column 3 + 3k + c (the column of s_k in `vertex_view`'s rows), 0 elsewhere. Built
    once per stack and width (a lighting change), so one 64-byte row load per bilinear corner reads
    every lobe in the compiled sample stage (`shade_block`)."""
    if width not in st.rows:
        out = torch.zeros(st.ext.shape[0], width, dtype=st.ext.dtype, device=st.ext.device)
        out[:, 3:3 + st.ext.shape[1]] = st.ext
        st.rows[width] = out
    return st.rows[width]


# -- the mirror direction's lat-long angles as float32 polynomials (session 39, pt39) --------------
#
# Before, `_mirror_uv` called torch.atan2 / torch.acos, which Inductor vectorises as Sleef's 1-ulp
# (double-float) routines, and the native cells (``native.shade_mirror``) called the same Sleef
# functions through libtorch_cpu to keep the compiled kernel's bits: ~1.3 of the chess bench cells'
# ~1.8 ms (1 thread). Now the ONE formula of the mirror look-up evaluates Cephes' single-precision
# minimax polynomials in plain float32 arithmetic (atanf on |t| <= tan π/8 after one reduction; asinf
# on |x| <= 1/2, the half-angle identity above it; one division and one square root per sample, no
# tables; the triple product's footprint kernel uses the same ones, ``triple_product.lighting``).
# Every step is an IEEE float32 operation (products, sums, one division, one square root, compares
# and selects; Inductor and the native loop are both compiled without FMA contraction), so the
# compiled kernel, the eager form and ``native.cells8`` / ``cells16`` (the same operations in the same
# order) give the same bits — the fast path stays bit-identical to the reference, which reads its
# maps through this function too. Accuracy (tested, ``test_fast.py``): within a few float32 ulps of
# the float64 angle of the float32 input, as Sleef's (pt38 found that ANY change of the angle's last
# bit moves a look-up by a texel's contrast, which is why both paths must share the formula).


def atan2_poly(y: Tensor, x: Tensor) -> Tensor:
    """atan2(y, x) in [−π, π] as float32 polynomials (comment above): the octant reduction t = min /
    max of |x|, |y| (t → (t − 1)/(t + 1), + π/4, above tan π/8; the same one division), Cephes' atanf
    polynomial, then the quadrant. atan2(±0, x < 0) = ±π, atan2(0, 0) = 0 (x = −0: π, as ATen's
    only for y = +0; the same lat-long u mod 1)."""
    ax, ay = x.abs(), y.abs()
    mn, mx = torch.minimum(ax, ay), torch.maximum(ax, ay)
    c = mn > mx * 0.41421356237309503                                      # t > tan(π/8)
    num = torch.where(c, mn - mx, mn)
    den = torch.where(c, mn + mx, mx)
    t = num / torch.where(den > 0.0, den, 1.0)
    z = t * t
    p = (((z * 0.0805374449538 - 0.138776856032) * z + 0.199777106478) * z - 0.333329491539) * z * t + t
    r = torch.where(c, p + 0.7853981633974483, p)
    r = torch.where(ay > ax, 1.5707963267948966 - r, r)
    r = torch.where(x < 0.0, 3.141592653589793 - r, r)
    return torch.where(y < 0.0, -r, r)


def acos_poly(y: Tensor) -> Tensor:
    """acos(y) for y in [−1, 1] as float32 polynomials (comment above): Cephes' asinf polynomial on
    |y| <= 1/2 (acos = π/2 − asin), 2·asin(√((1 − |y|)/2)) above; acos(−y) = π − acos(y)."""
    a = y.abs()
    big = a > 0.5
    z = torch.where(big, 0.5 - a * 0.5, a * a)
    # √z through float64: correctly rounded (as the compiled kernel's and the native loop's float32
    # square root) in eager torch too, whose float32 sqrt is not (an ulp off for ~20 % of inputs)
    s = torch.where(big, z.double().sqrt().float(), a)
    p = ((((z * 0.042163199048 + 0.024181311049) * z + 0.045470025998) * z + 0.074953002686) * z
         + 0.16666752422) * z * s + s
    r = torch.where(big, p * 2.0, 1.5707963267948966 - p)
    return torch.where(y < 0.0, 3.141592653589793 - r, r)


def _mirror_uv(normal: Tensor, wo: Tensor, to_world: Tensor) -> tuple[Tensor, Tensor]:
    """`specular.mirror_dirs` then `specular._latlong_uv` as one loop (for ``core.fused``): normal,
    wo (Q, 3), to_world (3, 3) → the lat-long coordinates (u, v) (Q,) each of the unit mirror
    direction R = reflect(ωo, n̂) in the map's frame."""
    nx, ny, nz = normal[:, 0], normal[:, 1], normal[:, 2]
    wx, wy, wz = wo[:, 0], wo[:, 1], wo[:, 2]
    s = (nx * wx + ny * wy + nz * wz) / (nx * nx + ny * ny + nz * nz).clamp_min(1e-24) * 2.0
    rx, ry, rz = s * nx - wx, s * ny - wy, s * nz - wz  # R = 2 (n̂·ωo) n̂ − ωo, unnormalised
    inv = torch.rsqrt((rx * rx + ry * ry + rz * rz).clamp_min(1e-24))
    rx, ry, rz = rx * inv, ry * inv, rz * inv
    m = to_world
    lx = rx * m[0, 0] + ry * m[1, 0] + rz * m[2, 0]  # local = to_worldᵀ R (EnvMap.to_local)
    ly = rx * m[0, 1] + ry * m[1, 1] + rz * m[2, 1]
    lz = rx * m[0, 2] + ry * m[1, 2] + rz * m[2, 2]
    u = atan2_poly(lx, -lz) * (0.5 / math.pi)
    v = acos_poly(ly.clamp(-1.0, 1.0)) * (1.0 / math.pi)
    return u, v


# Vectorised over the samples although every load is strided (module docstring of ``core.fused``).
mirror_uv_block = fused(_mirror_uv, options={"cpp.enable_tiling_heuristics": False})


def mirror_uv(normal: Tensor, wo: Tensor, to_world: Tensor) -> tuple[Tensor, Tensor]:
    """Lat-long coordinates (u, v) (Q,) each, in a map of frame ``to_world`` (3, 3), of the mirror
    directions of ωo (Q, 3) about the shading normals (Q, 3) — THE formula of the per-sample map
    look-ups: the eager fast path (`shade_samples`) and the reference (`PTT._shade_vertex`) both
    call this one compiled function on static blocks of `sample_block` rows, so they read the maps
    at the same bits; the compiled sample stage reads the cells of the same (u, v) computed in one
    loop with them (`_mirror_cells`; ``tests/methods/ptt/test_fast.py`` checks those cells equal
    ``specular._uv_cells`` of this function's (u, v) bit for bit).

    Decision (2026-12-03, ptt-v4): a compiled acos / atan2 differs from the eager one in the last
    bit for ~20–30 % of the samples, and a last-bit change of (u, v) flips a bilinear cell where the
    value sits on a cell boundary — a change that scales with the HDR texel contrast, not bounded by
    any round-off tolerance. So the reference does not keep its own eager copy of the formula;
    ``tests/methods/ptt/test_fast.py`` checks this compiled function against the eager
    `specular.mirror_dirs` + `specular._latlong_uv` to a few ulps (and the cells equal except
    within a few ulps of a boundary). Measured on the chess bench V frame (262 144 samples, 1
    thread, CPU time): 2.5 ms vs 2.9 ms eager (its strided (Q, 3) loads make it cost as much as the
    eager passes); the win is that the cells and the gathers after it become one compiled loop.

    Session 39 (pt39): the angles are `atan2_poly` / `acos_poly` (float32 polynomials, comment above
    them) instead of torch.atan2 / torch.acos: this compiled function now equals its eager form
    `_mirror_uv` bit for bit (tested), the native cells evaluate the same polynomials (their bits
    tested against this function's cells), and (u, v) stay within the few-ulp tolerance of the eager
    library formula above."""
    q = int(normal.shape[0])
    B = sample_block(q)
    return map_rows(mirror_uv_block, [normal, wo], (to_world.to(normal).contiguous(),), chunk=B, warm=warm_sizes(B))


def _mirror_cells(normal: Tensor, wo: Tensor, to_world: Tensor, H: int, W: int) -> tuple[Tensor, Tensor, Tensor]:
    """`_mirror_uv` then the lat-long cell of (u, v) on an H × W map (``specular._uv_cells``, the same
    arithmetic) as one loop vectorised over the samples (for ``core.fused``): → the cell's first row
    r (Q,) int32 in the periodic-extended texels (`EnvStack`: row iy·(W + 1) + ix) and its fractions
    fx, fy (Q,) — what `shade_block` reads per sample instead of (u, v).

    Decision (2026-12-05, ptv): the cell arithmetic (floor, scale, float → int conversions, clamps,
    the row index) was scalar code inside `shade_block`'s loop (vectorised along the lanes of a row,
    one sample at a time); here it runs 16 samples per instruction in the loop that already computes
    (u, v), for 4 more bytes per sample (r, fx, fy against u, v). Chess bench V frame (262 144
    samples, 1 thread, process CPU time, same process, alternating, load ~7): the sample stage 9.0 ms
    -> 7.2 ms, the same output bits (the same IEEE operations on the same (u, v) bits).

    Decision (session 23, ptt23): the cell indices are int32 throughout (they are < H·(W + 1) < 2³¹),
    not int64 narrowed at the end: AVX2 has no float ↔ int64 conversion, no 64-bit multiply and no
    64-bit min / max, so Inductor emulated each of those lane by lane; int32 has them all
    (cvttps2dq, cvtdq2ps, pmulld, pminsd). The same values: x, y in [0, W] are truncated toward zero
    in both; a NaN direction gets row 0 in both (tested). Chess bench (262 144 samples,
    1 thread, process CPU time, back to back): 3.3–3.6 ms -> 2.5–2.7 ms, the same output bits."""
    u, v = _mirror_uv(normal, wo, to_world)
    uu = u - 0.5 / W
    x = (uu - torch.floor(uu)) * W
    y = (v - torch.floor(v)) * (H - 1)
    ix = x.to(torch.int32).clamp(0, W - 1)  # the lower bounds only matter for a NaN direction: a row
    iy = y.to(torch.int32).clamp(0, H - 2)  # inside the table instead of an out-of-bounds read
    return iy * (W + 1) + ix, x - ix, y - iy


mirror_cells_block = fused(_mirror_cells, options={"cpp.enable_tiling_heuristics": False})


def lookup_stack(st: EnvStack, u: Tensor, v: Tensor) -> Tensor:
    """``EnvMap.radiance`` of every map of the stack at the lat-long coordinates (u, v) (Q,) of
    `mirror_uv` → (Q, 3·L): ``specular._uv_cells`` once, the four corners as one weighted bag."""
    idx, w = _spec._uv_cells(u, v, st.H, st.W)
    return Fnn.embedding_bag(idx, st.ext, per_sample_weights=w, mode="sum")


def shade_samples(face_pairs: Tensor, table: Tensor, face: Tensor, bary: Tensor, normal: Tensor | None,
                  wo: Tensor | None, env: EnvStack | None, L: int, out: Tensor | None = None) -> Tensor:
    """Radiance (Q, 3) of hit samples from the per-pair rows of `vertex_view` (the reference is
    `PTT._shade_vertex`): Gouraud interpolation with the barycentrics β of the rows of the sample's
    face (one 3-row bag), B clamped at 0 after it + u + Σ_k E^(k)(R) s_k with the prefiltered maps
    read per sample at the mirror direction R of ωo about the interpolated shading normal (env None:
    no lobes). The eager form of `shade_block` (kept for ``method.FUSED_VIEW = False`` and as its
    test oracle); call it on chunks of `SAMPLE_CHUNK` samples.

    face_pairs (M, 3) pair row of each face corner; table (n_pairs + 1, C) (C = 3 + 3L [+ 3]);
    face (Q,) int64; bary (Q, 2); normal, wo (Q, 3); out: optional (Q, 3) tensor written in place."""
    u, v = bary.unbind(-1)
    bw = torch.stack([1.0 - u - v, u, v], -1)
    acc = Fnn.embedding_bag(rows(face_pairs, face), table, per_sample_weights=bw, mode="sum")
    out = torch.clamp_min(acc[:, :3], 0.0, out=out)
    if env is None:
        return out
    Ek = lookup_stack(env, *mirror_uv(normal, wo, env.to_world))  # (Q, 3·L), lobe-major
    for k in range(L):
        out.addcmul_(acc[:, 3 + 3 * k:6 + 3 * k], Ek[:, 3 * k:3 * k + 3])
    if acc.shape[1] > 3 + 3 * L:
        out.add_(acc[:, 3 + 3 * L:3 + 3 * L + 3])
    return out


# Samples per `shade_samples` call: its working set (≈ 200 bytes per sample) fits the L2 cache.
SAMPLE_CHUNK = 1 << 15

# Static blocks of the compiled sample stage (`shade_samples_fused`, `shade_pixels_fused`,
# `mirror_uv`): the frame's sample count rounded up to a power of two within [MIN_SAMPLE_BLOCK,
# MAX_SAMPLE_BLOCK] (`sample_block`), so a bench frame (256² × 4 samples) is one block. Measured on
# the chess bench V frame (1 thread, process CPU time, same process, frames interleaved, load 6–8):
# whole-frame blocks 23.5–26.4 ms vs 27.7–29.8 ms with blocks of 2¹⁵ (and 46 ms with 2¹³): the
# per-block cost of a pass (launches, Dynamo guards) outweighs the L2 residency of smaller blocks.
# A power of two keeps the compiled variants few (one per size class), holds whole pixels of any
# S2 = 4^j and is a multiple of the vector width (no scalar tail loop, whose libm acos / atan2
# would differ in the last bit from the vectorised ones: `mirror_uv`).
MIN_SAMPLE_BLOCK = 1 << 10
MAX_SAMPLE_BLOCK = 1 << 18

# Lanes of the rows the compiled sample stage reads (`table_width`): one AVX-512 register / one
# cache line per row for up to 5 lobes without the bounce column.
LANES = 16


def sample_block(q: int) -> int:
    """Rows per static block of the compiled sample stage for q samples (`MAX_SAMPLE_BLOCK` comment)."""
    return pow2_block(q, MIN_SAMPLE_BLOCK, MAX_SAMPLE_BLOCK)


def warm_sizes(block: int) -> tuple[int, ...]:
    """The other `sample_block` sizes a later frame may meet, compiled in the harness's warm-up frame
    (``core.fused.warm_blocks``; session 13's perf run: chess V frame 4 re-traced, 783 ms vs 13 ms)."""
    return tuple(b for b in neighbour_blocks(block, MIN_SAMPLE_BLOCK, MAX_SAMPLE_BLOCK) if b != block)


def table_width(C: int) -> int:
    """Columns of the per-pair rows and the env rows of the compiled sample stage: C rounded up to
    a multiple of `LANES` (the extra columns are 0)."""
    return -(-int(C) // LANES) * LANES


def padded(table: Tensor, width: int) -> Tensor:
    """``table`` (n, C) with zero columns up to ``width`` (itself when already that wide)."""
    if table.shape[1] == width:
        return table
    return torch.cat([table, table.new_zeros(table.shape[0], width - table.shape[1])], 1)


@functools.lru_cache(maxsize=16)
def _lane_masks(C: int, L: int, width: int) -> Tensor:
    """(5, width) float32 lane masks of `shade_block` for rows of C columns B (3) | s (3L) | u (3)?:
    0 clamp-at-0 lanes (B), 1 added lanes (u), 2–4 the lanes of channel c = 0, 1, 2."""
    lane = torch.arange(width)
    m = torch.zeros(5, width)
    m[0, :3] = 1.0
    m[1, 3 + 3 * L:C] = 1.0
    for c in range(3):
        m[2 + c] = ((lane < C) & (lane % 3 == c)).float()
    return m.contiguous()


def _shade_block(face: Tensor, bary: Tensor, r: Tensor, fx: Tensor, fy: Tensor, face_pairs: Tensor, table: Tensor,
                 env: Tensor, lanes: Tensor, W: int, S2: int) -> Tensor:
    """The per-sample stage of `shade_samples` + `box_filter` as one compiled loop over a block's
    pixels, after `mirror_cells` (for ``core.fused``): per sample the face's three pair rows
    (table (n_pairs + 1, width), `table_width` lanes) with the Gouraud weights (1 − β1 − β2, β1, β2)
    and the four corners of its lat-long cell (first row r, fractions fx, fy: `_mirror_cells`) in the
    lane-aligned env rows (`env_rows`, rows W + 1 wide), each a contiguous row load (Inductor
    vectorises along the lanes; a per-column gather would cost one scalar load per value); then
    t = max(0, a) on the B lanes, a on the u lanes, a·e on the others — exactly max(0, B), u and
    s_k E^(k) —
    summed over the pixel's S2 samples (unrolled: sub-sample j of pixel p is row p·S2 + j), and
    each channel's sum over the lanes / S2 (the box filter).
    face (n,), bary (n, 2), r (n,) int32, fx, fy (n,) with n a multiple of S2 (pixel-major);
    lanes (5, width) (`_lane_masks`) → (n / S2, 3).

    The sub-samples are unrolled (not a reduction over S2·width lanes of a (n / S2, S2·width) view)
    and the kernel is compiled with `SHADE_OPTIONS`, so Inductor emits ONE loop over the pixels whose
    row loads stay vector loads: before, it stored a and e as two (n, width) arrays (2 × 16 MB per
    bench frame) and summed them in a third loop (`SHADE_OPTIONS` comment).

    Decision (session 23, ptt23): (1) the pair and env rows are read with ``embedding`` rather than
    ``table[idx]``: Inductor lowers both to the same row load, but wraps every ``[idx]`` index for
    negative values (a compare and a select per row, 7 per sample) and ``embedding``'s not — those
    indices are ≥ 0 by construction (the face index, which may be −1 for a miss, still wraps, as
    `miss_face_pairs` needs). (2) The lanes are chosen with ``where`` instead of
    t = max(0, a)·[B lanes] + a·e + a·[u lanes] (two products and two sums per lane and sample
    fewer): the same values, as the env rows are 0 on the B and u lanes (`env_rows`), so the old
    form's extra terms were ±0 (the two differ only where a is ±inf, which the old form made NaN);
    tested bit for bit (eager) against the old form. Alone on the chess bench frame (1 thread,
    process CPU time, alternating, 25 repeats, load ~3): 5.07 -> 4.41 ms (1.15x), the same output
    bits."""
    n = face.shape[0]
    P = n // S2
    width = table.shape[1]
    fv, b1v, b2v = face.view(P, S2), bary[:, 0].view(P, S2), bary[:, 1].view(P, S2)
    rv, fxv, fyv = r.view(P, S2), fx.view(P, S2), fy.view(P, S2)
    is_b, is_u = lanes[0, :width] > 0, lanes[1, :width] > 0
    t = None
    for j in range(S2):
        f = fv[:, j]
        p0, p1, p2 = face_pairs[f, 0], face_pairs[f, 1], face_pairs[f, 2]
        b1, b2 = b1v[:, j], b2v[:, j]
        b0 = 1.0 - b1 - b2
        fx_, fy_ = fxv[:, j], fyv[:, j]
        gx, gy = 1.0 - fx_, 1.0 - fy_
        rj = rv[:, j].to(torch.int64)
        a = (Fnn.embedding(p0, table) * b0[:, None] + Fnn.embedding(p1, table) * b1[:, None]
             + Fnn.embedding(p2, table) * b2[:, None])
        e = (Fnn.embedding(rj, env) * (gx * gy)[:, None] + Fnn.embedding(rj + 1, env) * (fx_ * gy)[:, None]
             + Fnn.embedding(rj + (W + 1), env) * (gx * fy_)[:, None]
             + Fnn.embedding(rj + (W + 2), env) * (fx_ * fy_)[:, None])
        tj = torch.where(is_b, a.clamp_min(0.0), torch.where(is_u, a, a * e))
        t = tj if t is None else t + tj
    out = torch.stack([(t * lanes[2 + c, :width]).sum(-1) for c in range(3)], -1)
    return out * (1.0 / S2)


# Inductor settings of `shade_block`: its gathers read rows whose indices are in range by
# construction (a face of the G-buffer or −1, which wraps to `miss_face_pairs`' zero face; pair rows
# of ``face_pairs``; lat-long cells clamped into the table), so the per-load index checks are dropped
# (alone: 1.005x); and with the default realize thresholds Inductor stores the Gouraud sum a and the
# env sum e (each read three times) as (n, width) arrays and sums them in separate passes, where
# these keep the whole stage in the one loop over the pixels (as ``triple_product.fast_eval``'s
# KERNEL_OPTIONS). Chess bench V frame (262 144 samples, 1 thread, process CPU time, same process,
# alternating, load 6–9): shade_block 10.6 -> 7.3 ms (1.45x), the same output bits; the previous
# (n / S2, S2·width) reduction with these options made the row loads scalar gathers (0.42x).
SHADE_OPTIONS = {"assert_indirect_indexing": False, "realize_opcount_threshold": 1000,
                 "realize_reads_threshold": 1000, "realize_acc_reads_threshold": 1000}
shade_block = fused(_shade_block, options=SHADE_OPTIONS)
pair_rows = fused(_pair_rows, options=SHADE_OPTIONS)  # `vertex_view`'s combination (defined above)


def _fused_inputs(table: Tensor, env: EnvStack, L: int, C: int | None) -> tuple[Tensor, Tensor, Tensor]:
    C = table.shape[1] if C is None else C
    width = table_width(C)
    return padded(table, width), env_rows(env, width), _lane_masks(C, L, width).to(table.device)


def shade_samples_fused(face_pairs: Tensor, table: Tensor, face: Tensor, bary: Tensor, normal: Tensor | None,
                        wo: Tensor | None, env: EnvStack | None, L: int, C: int | None = None) -> Tensor:
    """`shade_samples` of any number of hit samples as two compiled loops per static block of
    `sample_block` samples (``core.fused.map_rows``): `mirror_cells` and `shade_block` (S2 = 1) → (Q, 3).
    Equal to `shade_samples` to float32 round-off. C: the meaningful columns of ``table`` (None: all;
    `vertex_view` may return it already `padded`)."""
    if env is None:
        return shade_samples(face_pairs, table[:, :3] if C is None else table[:, :C], face, bary, None, None, None, 0)
    tab, erows, lanes = _fused_inputs(table, env, L, C)

    def block(face, bary, normal, wo):
        return _shade_pixels_block(face, bary, normal, wo, face_pairs, tab, erows, lanes, env, 1)

    B = sample_block(face.shape[0])
    return map_rows(block, [face, bary, normal, wo], chunk=B, warm=warm_sizes(B))


def shade_pixels_fused(face_pairs: Tensor, table: Tensor, face: Tensor, bary: Tensor, normal: Tensor,
                       wo: Tensor, env: EnvStack, L: int, S2: int, C: int | None = None) -> Tensor | None:
    """`shade_samples_fused` and `box_filter` of a G-buffer whose every sample hit, pixel-major with
    S2 sub-samples per pixel, in two compiled loops per static block of `sample_block` samples
    (`mirror_cells`, `shade_block`, which ends in the box filter: no per-sample radiance array, no
    separate resolve pass) → (Q / S2, 3). None when the blocks cannot hold whole pixels (the block
    not a multiple of S2); the caller then takes the two-pass route."""
    q = int(face.shape[0])
    B = sample_block(q)
    if B % S2 or q % S2:
        return None
    tab, erows, lanes = _fused_inputs(table, env, L, C)
    warm_blocks(_shade_pixels_block, [face, bary, normal, wo], (face_pairs, tab, erows, lanes, env, S2),
                [b for b in warm_sizes(B) if b % S2 == 0])
    if q == B:  # one full block (a bench frame): its result is the image, not copied into another
        # (65 536 × 3 floats: 75 µs per bench frame at 1 thread; session 23, ptt23)
        return _shade_pixels_block(face, bary, normal, wo, face_pairs, tab, erows, lanes, env, S2)
    out = torch.empty(q // S2, 3, dtype=table.dtype, device=table.device)
    for a in range(0, q, B):
        blk = [t[a:a + B] for t in (face, bary, normal, wo)]
        n = blk[0].shape[0]
        if n < B:  # pad whole pixels by repeating the last sample (map_rows); the padding is dropped
            blk = [torch.cat([b, b[-1:].expand(B - n, *b.shape[1:])]) for b in blk]
        o = _shade_pixels_block(*blk, face_pairs, tab, erows, lanes, env, S2)
        out[a // S2:(a + n) // S2].copy_(o[:n // S2])
    return out


def _shade_pixels_block(face: Tensor, bary: Tensor, normal: Tensor, wo: Tensor, face_pairs: Tensor, tab: Tensor,
                        erows: Tensor, lanes: Tensor, env: EnvStack, S2: int) -> Tensor:
    """One block of `shade_pixels_fused`: `mirror_cells` and `shade_block` (S2 sub-samples per pixel);
    one native pass when ``native.shade_mirror`` runs here (the same bits, `shade_cells`)."""
    if USE_NATIVE:
        from methods.ptt import native

        out = native.shade_mirror(normal, wo, env.to_world, env.H, face, bary, face_pairs, tab, erows, lanes, env.W, S2)
        if out is not None:
            return out
    r, fx, fy = mirror_cells_block(normal, wo, env.to_world, env.H, env.W)
    return shade_cells(face, bary, r, fx, fy, face_pairs, tab, erows, lanes, env.W, S2)


def shade_cells(face: Tensor, bary: Tensor, r: Tensor, fx: Tensor, fy: Tensor, face_pairs: Tensor, table: Tensor,
                env: Tensor, lanes: Tensor, W: int, S2: int) -> Tensor:
    """`shade_block` by the native loop (``methods.ptt.native``: the same bits, tested) when it is
    available and the arguments suit it, else the compiled `shade_block`.

    Decision (session 26, ptt26): the native loop does `shade_block`'s arithmetic with 8-lane vector
    row operations and scalar per-sample weights, and prefetches the env rows of the cells 16 samples
    ahead (``native`` docstring)."""
    if USE_NATIVE:
        from methods.ptt import native

        out = native.shade_pixels(face, bary, r, fx, fy, face_pairs, table, env, lanes, W, S2)
        if out is not None:
            return out
    return shade_block(face, bary, r, fx, fy, face_pairs, table, env, lanes, W, S2)


# Whether the sample stage (`shade_cells`, `_shade_pixels_block`) and `region_tables` may take the
# native loops of ``methods.ptt.native`` (tests switch it off to reach the compiled / eager code).
USE_NATIVE = True
# `region_tables`' W_r through ``native.region_tables`` (threaded, written in place); off:
# ``native.region_rows`` (the same bits; tests compare the two).
NATIVE_TABLES = True


def native_shading() -> bool:
    """True when the sample stage runs the native loop (`USE_NATIVE` and ``native.available()``),
    which reads a table of any row count without compiling a variant for it."""
    if not USE_NATIVE:
        return False
    from methods.ptt import native

    return native.available()


def box_filter(per_sample: Tensor, H: int, W: int, S2: int) -> Tensor:
    """``GBuffer.resolve`` of an image whose every sample hit: per-sample radiance (H·W·S2, 3) →
    (H, W, 3), the mean of each pixel's S2 sub-samples as sums of slices."""
    x = per_sample.view(H * W, S2 * 3)
    out = x[:, :3].clone()
    for j in range(1, S2):
        out.add_(x[:, 3 * j:3 * j + 3])
    return out.mul_(1.0 / S2).view(H, W, 3)
