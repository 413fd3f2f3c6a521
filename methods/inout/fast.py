"""Batched run time of the in-out renderer (Mahajan, Tseng & Ramamoorthi 2008 eq. 4) — the same
image as the per-sample reference path (`InOut._render_reference`) to float32 round-off, with the
work arranged for the machine instead of for reading.

Lighting (a frame whose ``changed`` has "light"): c_k = T̃_k · L (eq. 4's dot product) per vertex,
and only for the vertices the frame's *shaded* samples reference (those of the faces of the hits
above their horizon, `shaded_faces`: the hits below it have ρ = 0 and need no c): c is cached per
vertex with a validity mask that a lighting change clears, and a later frame that sees more of the
mesh fills in what it references. With the native loop (``methods.inout.csr``, `native`) exactly
those vertices' K rows each are read in place (`light_vertices`); without it, torch's CSR × dense
product over whole blocks of LIGHT_BLOCK vertices (`light_runs`, `light_rows_torch`; the region's
vertices are stored in Morton order, ``transport.locality_order``, so one view's vertices are few
runs of rows). A vertex's c never depends on which others were computed. Measured (creature bench,
1 thread, process CPU time, same process against main, ``benchmarks.inout --base``): the native
loop 1.69× torch's product over the same rows; c of the shaded faces' vertices only, exactly: 3434
of the 4926 vertices the 16-vertex blocks of every hit face computed (chess: 4282 of 6884), which is
the count ``InOut.frame_cost`` states; L / E / VL frames 1.35–1.5× (chess 1.44–1.73×, per-vertex
shading 1.9×).

View (every frame): at a sample with vertices v_j and barycentric weights β_j, eq. 4 reads
B = Σ_k σ_k h_k(ω_o) c̄_k with c̄ = Σ_j β_j c_{v_j} and σ_k h_k the bilinear look-up of one cell of
the hemi-octahedral table (nodes n with weights w_n, ``transport.lut_cell``). Both are linear, so

    B = Σ_j β_j Σ_n w_n X(v_j, n),     X(v, n)_c = Σ_k sh_lut[n, (k, c)] c_{v,k,c},

and X is what a frame forms (`prepare`), on a window of table nodes per referenced vertex: the box
of the cells its entries hit among a subsample of the frame's samples (every `WINDOW_SUBSAMPLE`-th,
compiled `window_cells`), widened by `WINDOW_PAD` cells and clipped to `MAX_WINDOW` nodes a side
around the cell of the direction from the vertex to the camera in the vertex's own frame
(`anchors`: the samples around a vertex see it from nearly that direction). X of all windows is a
compiled K-term reduction with the table rows gathered in place (`window_rows` through
`view_windows`); each sample then reads 3 vertices × 4 nodes of X. Sample–vertex entries whose cell
leaves the window (a cell no subsampled sample of the vertex hit beyond the pad, where
``core.frames.coordinate_system`` flips the tangent, or a triangle spans many cells) are summed
exactly from sh_lut and c (`_outliers`, compiled `outlier_rows`). The window decides only *where* a
sum is formed, never its terms: the estimator is eq. 4 at every sample whatever the windows are (a
window changes the image by float32 round-off only), and each sample takes ω_o in its own shading
frame, as the reference path does (`sample_frame`).

The per-sample stage is one compiled pass (``methods.core.fused``) over static blocks of
`sample_block` samples (`shade_pixels` → `shade_rows`): per sample its frame, table cell, face
vertices, the 12 weighted reads of X per channel and the box filter to the pixel, with only the
pixels and a byte of window-miss flags per sample written; the flagged entries then take the exact
path (their inputs from the compiled `entry_inputs`). Table-sized operands (X, the windows, the
faces, c) are marked dynamic in their row count, so a frame's new X size does not recompile.

Measured (issue 14, 2026-12-03, same process vs the eager stage before it, 1 thread, process CPU
time, load 7–11; ``python -m benchmarks.inout --base MAIN_CHECKOUT``): V frames 1.3–1.5×, L / E /
VL 1.15–1.3×. The compiled per-sample kernel then took ~80 ns per sample on one core (chess bench,
2.6·10⁵ samples: ~21 ms), 48 indirect loads per sample in a scalar loop with a bounds check and a
negative-index wrap per load. Now (`SHADE_OPTIONS`): no index checks (every index in range by
construction, `_shade_rows`), gathers as ``embedding`` look-ups (no wrap), the loop vectorised 8
samples wide: 1.55–1.6× the kernel (51–54 ns per sample), V frames 1.19× on chess bench and 1.42×
on the creature, L 1.08–1.10×, E 1.0–1.06× (same process, 1 thread, ``benchmarks.inout --base``). What bounds it now: Inductor has no vector gather on the
CPU — each of the 48 gathers per sample is 8 scalar loads into a buffer and one vector load, the
arithmetic around them 8-wide; far from the bytes' bound (the G-buffer and the pixels: ~13 MB,
~0.2 ms at triad bandwidth). The V frame's other half is the set-up (the windows' products X,
~45 ms on chess bench) and the exact path of the entries outside their windows (~8 % of the
samples at W = 12). Tried and dropped: the 2 × 2 nodes of a cell as one strided view of X (one
bounds check per vertex instead of 12): 2.7× slower (Inductor materialised the gathered cells);
c = T̃ · L as a weighted ``embedding_bag`` instead of the CSR product: 1.7× slower; the
referenced-face mask as a compiled scatter: no gain; with the kernel vectorised: a per-frame table
of each face's three windows (one 9-word look-up per sample instead of face → vertex → window):
1.02× (noise); X read one node row (N, 3) per look-up, the 3 channels sharing its index: 0.93×.

Split of a V frame (issue 15, 2026-12-03, 1 thread, process CPU time, load 11-13, frames 1-5 of a
5-frame bench V orbit, c cached; chess / creature, ms): set-up 42 / 24 — the windows' products X
(`window_rows`, W = 12 / 8) 20 / 9 (Inductor's K-term reduction at 10-15 GFLOP/s, one accumulator
chain per node and channel), `window_entries` 3.7 / 3.8, c of the vertices the orbit newly sees
(`InOut._ensure_c`) 3.7 / 1.9, `shaded_faces` 1.9 / 1.7, the rest eager glue (masks, anchors,
concatenations of X); per-sample stage 28 / 23 — `shade_rows` 13 / 15, the exact path and its
glue ~15 / ~8 (`_outliers` 5.1 / 1.7, `entry_inputs` 1.8 / 0.8, its gathers from the column-major
G-buffer arrays 3 ms before `take_rows`). Tried for X and dropped: the table regrouped so that a window
row is one contiguous vector load (unfold views, the K reduction outermost, layouts (3, K, R, R)
and (R, 3, K, R)): 0.15-0.3× (Inductor vectorised along the window row but broadcast c per term
and strode the table by K); without index checks: 1.0×. Tried and dropped for the per-vertex view:
its per-sample region check and face index as one compiled pass: 3.5× slower than the eager ops.

Session 16 (2026-12-04, same process against main, 1 thread, process CPU time, load 9-13): X's
blocks are written into one array of all slots (`view_windows` ``out``) instead of concatenated per
slot, then across slots (two copies of X, 7.4 MB on chess): `prepare` 1.03× (28.2 → 27.5 ms on
chess bench), bit-identical. Where a V frame's time goes now (chess / creature, ms): `prepare` 27 /
15 (X 20 / 8, `window_entries` 3 / 3), `shade_pixels` 24 / 18 (`shade_rows` 14 / 13, the exact
path 5.5 / 2.5), `shaded_faces` 2.5 / 2.7. X computes W² = 144 nodes per vertex on chess where the
bounding boxes of each vertex's own sample cells hold 2.9× fewer (~2.1·10⁵ of 6.1·10⁵ nodes) and
the distinct (vertex, node) pairs the samples read 5× fewer (1.2·10⁵): per-vertex window sides
(from the subsample's per-vertex extents) are the next step for X, not yet done.

Session 17 (2026-12-04, issue 14): per-vertex windows. Before, every referenced vertex had one
W × W window centred on its anchor, W chosen per frame (W = 12 on chess bench: 6.2·10⁵ nodes,
~2.1·10⁶ K-weighted entries outside); now each vertex's window is its own subsampled footprint
(above): 2.2-2.9× fewer nodes of X (chess bench 2.6·10⁵), and as many or fewer entries on the exact
path (chess 2.2-2.5·10⁴ against 2.6-2.9·10⁴ per frame). The node's row in its window is found in
float32 inside the K-term loop (`_window_rows`). V frames, same process against main (1 thread,
process CPU time, load 9-11, ``python -m benchmarks.inout --base MAIN --scene chess --threads 1
--kinds V --frames 7``): chess 1.27×, creature 1.16×; `view_windows` 28 → 11 ms on chess.
The exact path's kernel (`outlier_rows`) runs once over all entries with their count dynamic instead
of in power-of-two static blocks (padded up to twice the work), without index checks (indices
clamped): 1.27× on its own (chess bench V, per sample and per vertex, same process, bit-identical).

Session 18 (2026-12-04, issue 14): the vertex shading's view pass (``InOut._vertex_view``) was
eager glue, 4-5 ms of a 9-12 ms V frame (chess / creature bench, 1 thread): the hits' faces and
the region check are one compiled pass (`hit_face_counts`: int32 faces, the check reduced to one
flag in the kernel — a (q,) bool flag written per sample took 2.8× the pass), the referenced-face
mask and the hit count one histogram of those faces; the referenced vertices' cells one compiled
pass (`vertex_cells`) instead of ~20 eager ops. Same process against main (1 thread, process CPU
time, load 6-9, ``python -m benchmarks.inout --base MAIN --scene S --threads 1 --kinds V --frames 9
--config '{"shading":"vertex"}'``): V chess 1.13-1.17×, creature 1.03-1.22× (median per-frame ratio
1.08×); images bit-identical on the bench frames. Per sample: X's products as two kernels
(`window_nodes`, `window_products`: the indices once per row, not per vector of the K-term loop),
the referenced faces as int32 (`shaded_faces`), `entry_inputs` and `window_cells` vectorised
(`VECTOR_OPTIONS`): V chess 1.05× (median per-frame ratio 1.036), creature 1.05× (1.059), same
process against main (``--frames 13``, no ``--config``), bit-identical. What bounds the per-sample V
frame now (chess bench, 1 thread, ~45 ms under load 6-9): `shade_rows` 14 ms (53-58 ns per sample,
the 48 scalar indirect loads), X 5.5 ms (29 ns per node at K = 88: ~1 KB of table rows per node
gathered from beyond L2, ~36 GB/s), the exact path ~6 ms (24·10³ entries, `outlier_rows` ~130 ns
each: 4 table rows + a c row). Tried and dropped: the windows in the order of their first node
(consecutive windows on nearby table rows): 0.98×; `WINDOW_SUBSAMPLE` / `WINDOW_PAD` (4, 0), (4, 1),
(8, 2), (16, 2), (2, 0) against (8, 1): 0.90-1.01×; the shaded-face pass with its region check
reduced to one flag, or vectorised: 0.97×, 0.7×.

Session 19 (2026-12-05, issue 14; same process against main, 1 thread, process CPU time, load 6-9,
``python -m benchmarks.inout --base MAIN --scene S --threads 1 --kinds V --frames 13 --no-micro
[--config '{"shading":"vertex"}']``; images bit-identical). Per sample: `shade_rows` reads one
int64 word per face corner (`pack_windows`: the vertex's window packed) instead of the face's
vertex id and 5 window words — 39 indirect loads per sample instead of 54, the kernel 1.11× (53.5
→ 48 ns per sample, chess bench); the exact path's inputs per entry in one compiled call over the
entries (`entry_rows`, gathering from the G-buffer arrays in place) instead of `take_rows`, the
padded `entry_inputs` blocks and five eager gathers (3.3 → 1.4 ms on chess): V chess 1.08×,
creature 1.04×. Per vertex: the vertices' cells in one dynamic-size call (`vertex_cells_of`): V
chess and creature 1.06×. Where a per-sample V frame goes now (chess bench, 1 thread, ~40 ms):
`shade_rows` 12, X (`view_windows`) 7.7, the exact path 6.5 (`_outliers` 3.8, `entry_rows` 1.4,
the entry and region selection ~1.3), `_ensure_c` 2.5 (the orbit's newly seen vertices: ~35 per
region and frame, ~180 KB of T̃ each, ~6 GB/s), `shaded_faces` 2.2; per vertex (~9 ms): the
view pass 1.9 (`hit_face_counts` 1.1-1.3, `vertex_cells` 0.33), `_ensure_c` 2.6, the Gouraud
resolve 2.2, `vertex_radiance` 0.8 with its table rows in cache, 1.6-1.8 in the frame (cold).
Tried and dropped: X as (N, 4) float32 read as two int64 words per node (24 instead of 36 X loads,
the channels split by shifts and bit casts): 0.93× the kernel; the vertex shading's vertices in the
order of their table cells (`vertex_radiance` reading neighbouring rows one after the other): 0.8×
(the Morton order of the vertices already keeps their cells close, and c then is read out of
order); the 4 nodes of `vertex_radiance` as a weighted ``embedding_bag`` of table rows: 0.4×.
Session 28: the vertex shading's cells and eq. 4 run as C loops (``methods.inout.native``; V chess
1.48×, creature 1.70× at 1 thread); `vertex_cells` and `vertex_radiance` here are their fallback and
test oracle.

Session 29: when its C loop builds, the per-sample view frame runs ``methods.inout.native_sample``
instead of `prepare` and `shade_pixels` (``InOut._render_native``: no set-up pass, X formed at the
(vertex, node) pairs the samples read, in a memo window per vertex; V chess 1.80×, creature 1.90×
at 1 thread); `prepare` and `shade_pixels` stay as its fallback and test oracle.

Plain torch on the device of the precomputed arrays; no per-sample Python loops.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as Fnn
from torch import Tensor

from methods.core.fused import call_rows, fused, map_rows, neighbour_blocks, pow2_block, warm_blocks
from methods.inout import csr
from methods.inout.transport import lut_cell_xyz

__all__ = ["FastRegion", "FastStatic", "Windows", "build_region", "sample_frame", "sample_inputs", "take_rows", "light_runs",
           "light_rows", "light_rows_torch", "light_vertices", "native", "shaded_faces", "shaded_faces_cols", "hit_faces", "hit_face_counts", "vertex_cells", "vertex_cells_of", "anchors", "view_windows", "prepare", "CHUNK", "MAX_WINDOW", "WINDOW_PAD",
           "OUTLIER_COST", "WINDOW_SUBSAMPLE", "LIGHT_CHUNK_ROWS", "LIGHT_BLOCK", "vertex_radiance", "shade_pixels",
           "shade_rows", "pack_windows", "sample_block", "MIN_SAMPLE_BLOCK", "MAX_SAMPLE_BLOCK", "window_rows", "window_nodes", "window_products", "window_cells",
           "entry_inputs", "entry_rows", "outlier_rows"]

# Largest side of a vertex's node window (`prepare`): the window is clipped to the MAX_WINDOW ×
# MAX_WINDOW nodes centred on the vertex's anchor; entries whose cells lie beyond (the tangent flip of
# `coordinate_system`, big triangles) take the exact path instead of growing the window. At most 17
# (`pack_windows` keeps wu − 2 and wv − 2 in 4 bits each).
MAX_WINDOW = 16
# Samples per block of the former eager referenced-face pass of `InOut._view_setup` (now the compiled
# `shaded_faces` over `sample_block` blocks); kept for callers that import it.
CHUNK = 1 << 15
# The windows are chosen on every WINDOW_SUBSAMPLE-th sample's entries (`prepare`).
WINDOW_SUBSAMPLE = 8
# Cells added on every side of the box of cells a vertex's subsampled entries hit (`prepare`): the
# other samples' cells lie around those. K-weighted nodes of X / K-weighted entries outside their
# window, chess bench V frames 1-3 (the global window of side 12 before: 38.9 M / 2.08 M): pad 0
# 11.5 M / 2.06 M, pad 1 17.8 M / 0.69 M, pad 2 26.0 M / 0.34 M, pad 3 35.9 M / 0.24 M; an entry on
# the exact path costs ~24 nodes of X (`OUTLIER_COST`), so pads 1 and 2 tie and 1 keeps X smaller.
WINDOW_PAD = 1
# Work of one sample–vertex entry on the exact path (`_outliers`: a gathered c row, 4 nodes' dot
# products, its own small sparse pattern) in units of one node of X in a window (3 dot products of
# the frame's one sampled product), as the two kernels' times compare on a CPU (``benchmarks.inout``
# on sphere_plane bench: larger windows win over more outliers until about this ratio).
OUTLIER_COST = 24
# Rows of T̃ per sparse product in `light_rows`.
LIGHT_CHUNK_ROWS = 1 << 15
# Vertices per block of `light_runs`: c is computed for whole blocks of consecutive vertices, so a
# lighting change makes at most Vr / LIGHT_BLOCK products per region and computes at most
# LIGHT_BLOCK − 1 unreferenced vertices per run.
LIGHT_BLOCK = 16

# Vectorised over samples (``core.fused``: Inductor's tiling heuristics leave these loops, whose
# loads are strided components of (q, 3) rows and gathers, scalar): `entry_inputs` 1.7×, `window_cells`
# 1.8× (chess bench V, 1 thread, process CPU time, same process), bit-identical.
VECTOR_OPTIONS = {"cpp.enable_tiling_heuristics": False}


@dataclass
class FastRegion:
    """Lighting- and view-independent arrays of one region for the fast path (`build_region`).

    col, val: (nnz,) int32 Haar indices / float32 values of T̃ — the CSR arrays, read in place;
        crow: (Vr·K + 1,) int64 row pointers (rows hold different numbers of coefficients: the
        per-vertex budget, ``transport`` docstring item 4).
    sh_lut: (R², 3K) σ_k h_{k,c} at the table nodes (index 3k + c, the reference's table);
    sh_nc: (R²·3, K) the same regrouped, row (node, colour): the K-vector X's dot products read.
    K: terms; R: nodes per side of the table.
    native: the CSR passed ``csr.check_csr`` (`light_rows` may use the native loop).
    """

    col: Tensor
    val: Tensor
    crow: Tensor
    sh_lut: Tensor
    sh_nc: Tensor
    K: int
    R: int
    native: bool = False


@dataclass
class FastStatic:
    """The fast path's arrays of all regions (built once per precompute, `InOut._fast_static`).

    regions: one `FastRegion` per precomputed region (a *slot*); voff: the S + 1 offsets of the
        slots' vertices in the concatenation of their local ids (a *concatenated id*).
    face_gl: (3, M) int32 concatenated ids of each face's vertices (in its region's slot);
        face_rows: (M, 3) the same, row per face (the compiled stage's gather, `shade_rows`);
    face_region: (M,) int64 the scene region index of each face.
    pos: (ΣVr, 3) float32 vertex positions, frames: (ΣVr, 3, 3) world → local rows (s, t, n) of
        the vertex normals (`core.frames.frame_matrix`), K: (ΣVr,) int64 the terms of each vertex's
        slot — all by concatenated id, for the window anchors (`anchors`).
    R: nodes per side of the tables (all slots).
    """

    regions: list[FastRegion]
    voff: list[int]
    face_gl: Tensor
    face_rows: Tensor
    face_region: Tensor
    pos: Tensor
    frames: Tensor
    K: Tensor
    R: int


def build_region(T: Tensor, sh_lut: Tensor) -> FastRegion:
    """`FastRegion` of a region: T the CSR (Vr·K, D) transport (``transport.transport_haar``),
    sh_lut (R², 3K) the σ_k h_{k,c} table (index 3k + c)."""
    crow, col, val = T.crow_indices().long(), T.col_indices(), T.values()
    RR, K3 = sh_lut.shape
    R = int(round(RR ** 0.5))
    sh_nc = sh_lut.view(RR, K3 // 3, 3).transpose(1, 2).reshape(RR * 3, K3 // 3).contiguous()
    return FastRegion(col=col, val=val, crow=crow, sh_lut=sh_lut, sh_nc=sh_nc,
                      K=K3 // 3, R=R, native=csr.check_csr(crow, col, val, T.shape[1]))


def sample_frame(n: Tensor, wo: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """ω_o in each sample's shading frame, ``frame_matrix(normalize(n)) @ wo`` in closed form:
    n, wo (Q, 3) → the local components (x, y, z), (Q,) each. With the frame of
    ``core.frames.coordinate_system`` (sign = ±1 as n_z ≥ 0, A = −1/(sign + n_z)) and
    u = A (n_x ω_x + n_y ω_y) − ω_z: x = ω_x + sign n_x u, y = sign ω_y + n_y u, z = n·ω_o."""
    nx, ny, nz = n.unbind(-1)
    a, b, c = wo.unbind(-1)
    inv = (nx * nx + ny * ny + nz * nz).sqrt_().clamp_min_(1e-12).reciprocal_()   # F.normalize's eps
    nx, ny, nz = nx * inv, ny * inv, nz * inv
    sign = torch.where(nz >= 0, 1.0, -1.0).to(nz.dtype)
    A = (sign + nz).reciprocal_().neg_()
    d = nx * a + ny * b
    u = A * d - c
    return a + sign * nx * u, sign * b + ny * u, d + nz * c


def take_rows(t: Tensor, idx: Tensor) -> Tensor:
    """``t.index_select(0, idx)`` (the same values) with the gather along ``t``'s layout: a column-major
    (q, C) array — the bench G-buffer's ω_o and barycentrics are ((q, 3) with strides (1, q)) — is
    gathered as its C contiguous columns. torch's row gather from a column-major array takes a slow
    strided path: 2·10⁴ sorted rows of the chess bench ω_o in 1.1 ms against 0.09 ms from a
    contiguous copy (1 thread, process CPU time, load ~11), and the copy itself costs 1.6–2 ms. The
    result is row-major as ``index_select``'s (the compiled kernels downstream see the strides they
    were compiled and warmed for)."""
    if t.dim() == 2 and t.shape[1] > 1 and t.stride(0) == 1 and t.stride(1) >= t.shape[0] and idx.numel() > 1:
        return t.T.index_select(1, idx).T.contiguous()
    return t.index_select(0, idx)


def light_runs(todo: Tensor, nv: int, block: int = LIGHT_BLOCK) -> list[tuple[int, int]]:
    """Vertex ranges [v0, v1) covering the vertices ``todo`` (ascending local ids) with whole blocks
    of ``block`` consecutive vertices, consecutive blocks merged: at most nv / block ranges."""
    if todo.numel() == 0:
        return []
    b = torch.unique_consecutive(todo // block)
    brk = (b[1:] - b[:-1] > 1).nonzero(as_tuple=True)[0]
    starts = torch.cat([b[:1], b[1:][brk]]).tolist()
    ends = torch.cat([b[:-1][brk], b[-1:]]).tolist()
    return [(s0 * block, min(nv, (e0 + 1) * block)) for s0, e0 in zip(starts, ends)]


def native(fr: FastRegion, L: Tensor) -> bool:
    """Whether the lighting product of region ``fr`` under L runs the native loop
    (``methods.inout.csr``: 1.7–1.8× torch's product, one streaming pass over T̃): it is built,
    the region's arrays passed its check, L is float32 on the CPU."""
    return fr.native and L.device.type == "cpu" and L.dtype == torch.float32 and csr.available()


def _pad4(L: Tensor) -> Tensor:
    L4 = torch.zeros(L.shape[0], 4, dtype=L.dtype, device=L.device)
    L4[:, :L.shape[1]] = L
    return L4


def light_vertices(fr: FastRegion, L: Tensor, verts: Tensor) -> Tensor:
    """c_{v,k,c} = Σ_t T̃[(v, k), t] L[t, c] (Mahajan 2008 eq. 4) for the vertices ``verts`` (n,)
    (local ids, any order) → (n, K, 3): the native loop over their K rows each (`native` must hold),
    L zero-padded to 4 columns (aligned 16-byte rows)."""
    out = csr.csr_blocks4(fr.crow, fr.col, fr.val, _pad4(L), verts * fr.K, fr.K)
    return out[:, :L.shape[1]].reshape(verts.numel(), fr.K, L.shape[1])


def light_rows(fr: FastRegion, L: Tensor, v0: int, v1: int, chunk_rows: int = LIGHT_CHUNK_ROWS) -> Tensor:
    """`light_vertices` of the vertices v0 ≤ v < v1 → (v1 − v0, K, 3): the native loop when `native`
    holds, else `light_rows_torch`."""
    if not native(fr, L):
        return light_rows_torch(fr, L, v0, v1, chunk_rows)
    K = fr.K
    out = csr.csr_dense4(fr.crow, fr.col, fr.val, _pad4(L), v0 * K, v1 * K)
    return out[:, :L.shape[1]].reshape(v1 - v0, K, L.shape[1])


def light_rows_torch(fr: FastRegion, L: Tensor, v0: int, v1: int, chunk_rows: int = LIGHT_CHUNK_ROWS) -> Tensor:
    """`light_rows` by torch's CSR × dense product (MKL on this build) over blocks of rows read in
    place, L zero-padded to 4 columns (aligned rows: the product's inner loop is a 4-wide gather):
    the fallback without the native loop, and its test oracle."""
    K = fr.K
    L4 = torch.zeros(L.shape[0], 4, dtype=L.dtype, device=L.device)
    L4[:, :L.shape[1]] = L
    r0, r1 = v0 * K, v1 * K
    out = torch.empty(r1 - r0, 4, dtype=L.dtype, device=L.device)
    for a in range(r0, r1, chunk_rows):
        b = min(r1, a + chunk_rows)
        crow = fr.crow[a:b + 1]
        s0, s1 = int(crow[0]), int(crow[-1])
        T = torch.sparse_csr_tensor((crow - s0).to(fr.col.dtype), fr.col[s0:s1], fr.val[s0:s1],
                                    size=(b - a, L4.shape[0]), check_invariants=False)
        out[a - r0:b - r0] = T @ L4
    return out[:, :L.shape[1]].reshape(v1 - v0, K, L.shape[1])


def anchors(st: FastStatic, ref: Tensor, cam: Tensor) -> tuple[Tensor, Tensor]:
    """Table cell (column, row) (m,) int32 of the direction from each vertex ``ref`` (m,)
    (concatenated ids) to the camera position cam (3,), in the vertex's frame: where the cells of
    the samples around the vertex cluster (they see it from nearly that direction)."""
    d = cam[None, :] - st.pos.index_select(0, ref)
    d = d / d.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    dl = torch.bmm(st.frames.index_select(0, ref), d.unsqueeze(-1)).squeeze(-1)
    iu, iv, _, _ = lut_cell_xyz(*dl.unbind(-1), st.R, index_dtype=torch.int32)
    return iu, iv


def _window_rows(e: Tensor, p: Tensor, wr: Tensor, ref: Tensor, sh_nc: Tensor, c: Tensor, R: int) -> Tensor:
    """X (n, 3) = Σ_k σ_k h_{k,c}(node) c_{v,k,c} at n rows of X (`prepare`), for ``core.fused``: row e (n,)
    int64 of X is node e − offset of the window wr[p] (p (n,) int64; wr (m, 5) int32: first column,
    first row, offset in X, columns wu, rows wv; row-major in the window) of vertex ref[p] (ref (m,)
    local ids). The table rows are gathered inside the K-term reduction (nothing of size n·3K is
    formed); sh_nc (R²·3, K) rows (node, colour), c (Vr, 3, K). The row of a node in its window,
    ⌊l / wu⌋ (l < wu·wv ≤ MAX_WINDOW²), is taken in float32, exact with the half-cell offset: Inductor
    recomputes the indices for every vector of the K-term loop, and an integer division there took
    3.6× the time of the whole reduction (98 against 27 ns per node, chess-like operands, 1 thread).
    Compiled without index checks: p < m, and the node lies in the table for
    the windows `prepare` makes."""
    w = Fnn.embedding(p, wr)                                                           # (n, 5)
    loc = (e - w[:, 2]).to(torch.int32)
    dy = ((loc.to(torch.float32) + 0.5) / w[:, 3].to(torch.float32)).floor().to(torch.int32)
    node = (w[:, 1] + dy) * R + w[:, 0] + (loc - dy * w[:, 3])
    K = sh_nc.shape[1]
    v = Fnn.embedding(p, ref[:, None])[:, 0]
    return (Fnn.embedding(node, sh_nc.view(-1, 3 * K)).view(-1, 3, K)
            * Fnn.embedding(v, c.view(c.shape[0], 3 * K)).view(-1, 3, K)).sum(-1)


window_rows = fused(_window_rows, options={"assert_indirect_indexing": False})


def _window_nodes(e: Tensor, p: Tensor, wr: Tensor, ref: Tensor, R: int) -> tuple[Tensor, Tensor]:
    """`_window_rows`'s indices alone (for ``core.fused``): the table node (n,) int32 and the local
    vertex (n,) int32 of each row e of X (the same arithmetic), for `window_products`."""
    w = Fnn.embedding(p, wr)                                                           # (n, 5)
    loc = (e - w[:, 2]).to(torch.int32)
    dy = ((loc.to(torch.float32) + 0.5) / w[:, 3].to(torch.float32)).floor().to(torch.int32)
    node = (w[:, 1] + dy) * R + w[:, 0] + (loc - dy * w[:, 3])
    return node, Fnn.embedding(p, ref[:, None])[:, 0].to(torch.int32)


def _window_products(node: Tensor, v: Tensor, sh_nc: Tensor, c: Tensor) -> Tensor:
    """`_window_rows`'s K-term reduction (for ``core.fused``) at rows of given table node and local
    vertex (n,) int32 each (`window_nodes`); sh_nc (R²·3, K), c (Vr, 3, K) → (n, 3)."""
    K = sh_nc.shape[1]
    return (Fnn.embedding(node, sh_nc.view(-1, 3 * K)).view(-1, 3, K)
            * Fnn.embedding(v, c.view(c.shape[0], 3 * K)).view(-1, 3, K)).sum(-1)


# `window_rows` as two kernels (what `view_windows` runs): the indices once per row, then the
# reduction reads them instead of recomputing them for every vector of its K-term loop (Inductor
# does; `_window_rows`): X 1.08× (chess bench, 1 thread, process CPU time), bit-identical. No index
# checks: p < m, and the node lies in the table for the windows `prepare` makes.
window_nodes = fused(_window_nodes, options={"assert_indirect_indexing": False})
window_products = fused(_window_products, options={"assert_indirect_indexing": False})


def view_windows(fr: FastRegion, ref: Tensor, c: Tensor, wr: Tensor, out: Tensor) -> Tensor:
    """X = Σ_k σ_k h_{k,c}(node) c_{v,k,c} on the window of each vertex ``ref`` (m,) (local ids of
    one slot; wr (m, 5) int32 its window: first column, first row, offset in X, columns, rows),
    written into its rows of ``out`` (X of all slots, (N, 3); this slot's windows are the rows from
    wr[0, 2] to the last window's end): the compiled `window_rows` once over all of them (the row
    count marked dynamic: windows of any sizes, one kernel per K); c (Vr, 3, K)."""
    m = ref.numel()
    if m == 0:
        return out
    cnt = (wr[:, 3] * wr[:, 4]).long()
    e0 = int(wr[0, 2])
    if m == 1:       # the compiler specialises size 1: a second window row (never indexed) keeps one variant
        wr, ref = torch.cat([wr, wr]), torch.cat([ref, ref])
    e = torch.arange(e0, e0 + int(cnt.sum()), device=ref.device)
    p = torch.repeat_interleave(torch.arange(m, device=ref.device), cnt)
    for t in (e, p, wr, ref, c):                          # the frame's counts: one compiled variant per K
        torch._dynamo.maybe_mark_dynamic(t, 0)
    node, v = window_nodes(e, p, wr, ref, fr.R)           # `window_rows` in two passes (`window_products`)
    for t in (node, v):
        torch._dynamo.maybe_mark_dynamic(t, 0)
    out[e0:e0 + e.numel()] = window_products(node, v, fr.sh_nc, c)
    return out


@dataclass
class Windows:
    """A frame's products X on the windows of its referenced vertices (`prepare`).

    W: the largest window side (reporting); win: (ΣVr, 5) int32 per concatenated vertex id its
    window's first column, first row, the offset of its nodes in X, its columns wu and rows wv
    (≥ 2 each; (0, 0, 0, 2, 2) for unreferenced vertices); X: (max(Σ wu·wv, 4), 3) float32
    node-major, each window row-major, the slots' windows one after the other (zero rows added when
    no vertex is referenced: the compiled stage reads in-range rows for every sample).
    """

    W: int
    win: Tensor
    X: Tensor


def sample_inputs(st: FastStatic, normal: Tensor, wo: Tensor, bary: Tensor, face: Tensor, live: Tensor | None
                  ) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor, Tensor, Tensor], Tensor]:
    """Per-sample inputs of eq. 4 for q G-buffer samples: normal, wo (q, 3), bary (q, 2), face (q,)
    (clamped to a valid face where ``live`` is False), live (q,) bool or None (all live).
    Returns gl (3, q) int32 concatenated vertex ids, bw (3, q) barycentric weights (0 where the
    sample is not shaded: not live, or ω_o below its horizon), the table cell (iu, iv, fu, fv) of
    ω_o in the sample's frame (`sample_frame`, ``transport.lut_cell_xyz``) and front (q,) bool."""
    wl = sample_frame(normal.float(), wo.float())
    front = wl[2] > 0                                                           # ρ = 0 below the horizon
    if live is not None:
        front &= live
    gl = torch.stack([f.index_select(0, face) for f in st.face_gl])
    u, v = bary.float().unbind(-1)
    fw = front.to(u.dtype)
    bw = torch.stack([(1.0 - u - v) * fw, u * fw, v * fw])
    return gl, bw, lut_cell_xyz(*wl, st.R, index_dtype=torch.int32), front


def _shaded_faces(normal: Tensor, wo: Tensor, face: Tensor, region: Tensor, live: Tensor, face_region: Tensor,
                  margin: float) -> tuple[Tensor, Tensor]:
    """Per sample (for ``core.fused``, `InOut._view_setup`'s referenced-face pass): its face where it
    is live and *shaded* — n·ω_o > −margin |n| |ω_o|, a superset of the samples the per-sample stage
    finds above their horizon (z > 0 after normalising n, `sample_frame`, whose rounding moves z by
    ~1e-7 |ω_o|) — else M = the face count (q,) int32 (the referenced-face histogram,
    ``InOut._face_mask``, counts int32 faces in 0.4 of the time of int64 ones, chess bench), and whether a live sample's face lies in
    another region than the sample's (q,) bool. face < 0 is clamped (a miss: not live)."""
    dot = (normal * wo).sum(-1)
    shaded = (dot > -margin * ((normal * normal).sum(-1) * (wo * wo).sum(-1)).sqrt()) & live
    f = face.clamp_min(0)
    bad = (face_region[f] != region) & live
    return torch.where(shaded, f, face_region.shape[0]).to(torch.int32), bad


shaded_faces = fused(_shaded_faces)


def _shaded_faces_cols(normal: Tensor, wx: Tensor, wy: Tensor, wz: Tensor, face: Tensor, region: Tensor, live: Tensor,
                       face_region: Tensor, margin: float) -> tuple[Tensor, Tensor]:
    """`_shaded_faces` with ω_o as its three columns (q,) each (the stack fuses away when compiled):
    ``core.fused.map_rows`` makes its row arrays contiguous, and the bench G-buffer's ω_o is
    column-major ((q, 3), strides (1, q)), so a (q, 3) ω_o row cost a transposing copy per frame
    (1.8–3.9 ms on chess bench, 1 thread, load ~11) where its columns are contiguous already."""
    return _shaded_faces(normal, torch.stack([wx, wy, wz], -1), face, region, live, face_region, margin)


shaded_faces_cols = fused(_shaded_faces_cols)


def _window_cells(normal: Tensor, wo: Tensor, bary: Tensor, face: Tensor, live: Tensor, face_rows: Tensor,
                  Kv: Tensor, R: int) -> tuple[Tensor, Tensor]:
    """Per sample–vertex entry of q samples (the `sample_inputs` arithmetic, for ``core.fused``): the
    entry's vertex (q, 3) int64 (concatenated id; ΣVr = Kv's length, one past the last, where the entry
    is not shaded: β_j = 0, ω_o below the horizon, or not live) and the sample's table cell as (q, 4)
    int32 (iu, iv, −iu, −iv): `prepare` takes their minimum per vertex, a box of cells. face < 0 is
    clamped (a miss: not live)."""
    x, y, z = sample_frame(normal, wo)
    front = (z > 0) & live
    iu, iv, _, _ = lut_cell_xyz(x, y, z, R, index_dtype=torch.int32)
    g = face_rows[face.clamp_min(0)].long()                                     # (q, 3)
    u, v = bary[:, 0], bary[:, 1]
    fw = front.to(u.dtype)
    bw = torch.stack([(1.0 - u - v) * fw, u * fw, v * fw], -1)
    return torch.where(bw != 0, g, Kv.shape[0]), torch.stack([iu, iv, -iu, -iv], -1)


window_cells = fused(_window_cells, options=VECTOR_OPTIONS)                    # see `VECTOR_OPTIONS`


def _hit_faces(face: Tensor, region: Tensor, hit: Tensor, face_region: Tensor) -> tuple[Tensor, Tensor]:
    """Per sample (for ``core.fused``, `hit_face_counts`): its face where it is a hit, else M = the
    face count (q,) int32, and whether any hit's face lies in another region than the sample's ()
    bool. face is clamped into [0, M) (a miss: not a hit), so the look-up needs no index check."""
    f = face.clamp(0, face_region.shape[0] - 1)
    bad = (face_region[f] != region) & hit
    return torch.where(hit, f, face_region.shape[0]).to(torch.int32), bad.any()


# No index checks (the face is clamped, `_hit_faces`). The region check as one reduced flag: with a
# (q,) bool flag written per sample instead, the pass took 2.8× the time (chess bench, 1 thread).
hit_faces = fused(_hit_faces, options={"assert_indirect_indexing": False})


def _vertex_cells(ref: Tensor, pos: Tensor, frames: Tensor, cam: Tensor, R: int) -> tuple[Tensor, Tensor, Tensor]:
    """Per vertex of the vertex shading (for ``core.fused``, ``InOut._vertex_view``): ref (n,) int64
    concatenated ids; pos (ΣVr, 3), frames (ΣVr, 3, 3) world → local rows; cam (3,). The direction
    d = cam − pos to the camera in the vertex's frame (the hemi-octahedral cell needs no unit vector)
    → whether it is above the horizon (n,) bool, the first node of its table cell (n,) int64 and the
    4 bilinear node weights (n, 4) (``transport.lut_cell_xyz``)."""
    d = cam - pos[ref]                                                          # (n, 3)
    Fm = frames[ref]                                                            # (n, 3, 3)
    x, y, z = ((Fm * d[:, None, :]).sum(-1)).unbind(-1)
    iu, iv, fu, fv = lut_cell_xyz(x, y, z, R)
    gu, gv = 1 - fu, 1 - fv
    return z > 0, iv * R + iu, torch.stack([gu * gv, fu * gv, gu * fv, fu * fv], -1)


vertex_cells = fused(_vertex_cells)


def vertex_cells_of(ref: Tensor, pos: Tensor, frames: Tensor, cam: Tensor, R: int) -> tuple[Tensor, Tensor, Tensor]:
    """`vertex_cells` of the n referenced vertices ``ref`` in one compiled call, n marked dynamic
    (``InOut._vertex_view``; static blocks of `sample_block` vertices, padded up to twice the work,
    took 0.6 against 0.33 ms on chess bench, 1 thread; `methods.core.fused.call_rows`)."""
    return call_rows(vertex_cells, [ref], (pos, frames, cam, R))


def hit_face_counts(face: Tensor, region: Tensor, hit: Tensor, face_region: Tensor) -> tuple[Tensor, bool]:
    """The histogram (M + 1,) int64 of the hits' faces of q samples (face, region (q,) int64, hit
    (q,) bool; bin M: the misses) and whether a hit's face lies in another region than the sample's
    (face_region (M,) int64): the compiled `hit_faces` over static blocks of `sample_block` samples
    (the last padded by repeating its last sample), then one ``torch.bincount``."""
    q, M = int(face.shape[0]), int(face_region.shape[0])
    B = sample_block(q)
    rows = [face.contiguous(), region.contiguous(), hit.contiguous()]
    torch._dynamo.maybe_mark_dynamic(face_region, 0)             # the scene's face count: one variant
    warm_blocks(hit_faces, rows, (face_region,), warm_sizes(B))
    fh = torch.empty(q, dtype=torch.int32, device=face.device)
    bad = []
    for a in range(0, q, B):
        blk = [r[a:a + B] for r in rows]
        n = blk[0].shape[0]
        if n < B:
            blk = [torch.cat([t, t[-1:].expand(B - n)]) for t in blk]
        f, b = hit_faces(*blk, face_region)
        fh[a:a + n] = f[:n]
        bad.append(b)
    return torch.bincount(fh, minlength=M + 1), bool(torch.stack(bad).any()) if bad else False


def prepare(st: FastStatic, cs: list[Tensor], ref: Tensor, cam: Tensor, sub: tuple) -> Windows:
    """The frame's `Windows`: a window of table nodes per referenced vertex ``ref`` (m,)
    (concatenated ids, ascending), and X = the windows' products with the c of each slot (cs[s]
    (Vr_s, 3, K_s), valid on ``ref``). A vertex's window is the box of the cells its entries among
    a subsample of the frame's samples hit (``sub`` = their normal, wo, bary, face (< 0: a miss),
    live; `window_cells`), widened by `WINDOW_PAD` cells on every side and clipped to the
    `MAX_WINDOW`-sided window centred on its anchor (the cell of the direction to the camera cam
    (3,), `anchors`); a vertex no subsampled entry hits gets its anchor cell."""
    R, dev, n_all, m = st.R, ref.device, st.voff[-1], ref.numel()
    au, av = anchors(st, ref, cam)
    torch._dynamo.maybe_mark_dynamic(st.face_rows, 0)
    torch._dynamo.maybe_mark_dynamic(st.K, 0)
    B = sample_block(sub[0].shape[0])
    vid, cell = map_rows(window_cells, list(sub), (st.face_rows, st.K, R), chunk=B, warm=warm_sizes(B))
    big = torch.iinfo(torch.int32).max
    box = torch.full((n_all + 1, 4), big, dtype=torch.int32, device=dev)   # row ΣVr: the unshaded entries
    for j in range(3):
        box.scatter_reduce_(0, vid[:, j:j + 1].expand(-1, 4), cell, "amin")
    box = box.index_select(0, ref)
    seen = box[:, 0] != big
    lo_u, lo_v = box[:, 0], box[:, 1]
    hi_u, hi_v = box[:, 2].neg(), box[:, 3].neg()
    h, pad, cap = MAX_WINDOW // 2 - 1, WINDOW_PAD, MAX_WINDOW - 2         # cells [a − h, a − h + cap] at most
    sides = []
    for lo, hi, a in ((lo_u, hi_u, au), (lo_v, hi_v, av)):
        lo = torch.maximum(torch.where(seen, lo, a) - pad, a - h).clamp_(min=0)
        hi = torch.minimum(torch.where(seen, hi, a) + pad, a - h + cap).clamp_(max=R - 2)
        empty = lo > hi                                 # every subsampled cell beyond the clip: the anchor's
        sides.append((torch.where(empty, a, lo), torch.where(empty, a, hi)))
    (u0, u1), (v0, v1) = sides
    wu, wv = u1 - u0 + 2, v1 - v0 + 2
    cnt = (wu * wv).long()
    off = torch.cumsum(cnt, 0) - cnt
    N = int(cnt.sum()) if m else 0
    wr = torch.stack([u0, v0, off.to(torch.int32), wu, wv], 1).to(torch.int32)
    win = torch.zeros(n_all, 5, dtype=torch.int32, device=dev)
    win[:, 3:] = 2
    win[ref] = wr
    b = [int(x) for x in torch.searchsorted(ref, torch.tensor(st.voff, device=dev)).tolist()]
    X = torch.empty(max(N, 4), 3, dtype=torch.float32, device=dev)           # at least 4 rows (`_shade_rows`)
    for s, fr in enumerate(st.regions):                            # each slot's windows written in place
        view_windows(fr, ref[b[s]:b[s + 1]] - st.voff[s], cs[s], wr[b[s]:b[s + 1]], X)
    return Windows(W=int(torch.maximum(wu, wv).max()) if m else 2, win=win, X=X)


# Static blocks of the compiled per-sample stage (`shade_pixels`): the frame's shaded sample count
# rounded up to a power of two within [MIN_SAMPLE_BLOCK, MAX_SAMPLE_BLOCK] (`sample_block`), so a
# bench frame (256² × 4 samples) is one block (as PTT's sample stage: per-block launches and guards
# cost more than the L2 residency of small blocks saves) and the compiled variants stay few.
MIN_SAMPLE_BLOCK = 1 << 10
MAX_SAMPLE_BLOCK = 1 << 18


def sample_block(q: int) -> int:
    """Samples per static block of `shade_pixels` for q shaded samples (`MAX_SAMPLE_BLOCK` comment)."""
    return pow2_block(q, MIN_SAMPLE_BLOCK, MAX_SAMPLE_BLOCK)


def warm_sizes(block: int) -> tuple[int, ...]:
    """The other `sample_block` sizes a later frame may meet, compiled in the harness's warm-up frame
    (``core.fused.warm_blocks``: the count of entries outside their windows moved 4096-16384 over the
    creature's V orbit, and each new size re-traced inside a timed frame)."""
    return tuple(b for b in neighbour_blocks(block, MIN_SAMPLE_BLOCK, MAX_SAMPLE_BLOCK) if b != block)


def _shade_rows(normal: Tensor, wo: Tensor, bary: Tensor, face: Tensor, live: Tensor, fwin: Tensor, X: Tensor,
                R: int) -> tuple[Tensor, Tensor]:
    """Eq. 4 (module docstring) at a block of n pixels × S sub-samples, every step of `sample_inputs`
    and `shade` in one pass for ``core.fused`` (no per-sample intermediate leaves the block):
    normal, wo (n, S, 3), bary (n, S, 2), face (n, S) int64 (< 0: a miss), live (n, S) bool;
    fwin (M, 3) int64 the window of each face's three vertices packed in one word each
    (`pack_windows`: first column, first row, last cell column wu − 2 and row wv − 2, offset in X;
    `Windows.win`), X (N, 3) the windows' products node-major (`Windows.X`). Returns the pixels' box-filtered radiance (n, 3) from the
    entries inside their windows, and per sample the bits j of the entries (vertex j) that are
    shaded but outside their window (n, S) uint8: the caller adds those by the exact path.

    Every gather is an ``embedding`` (a row look-up whose index Inductor does not wrap for negative
    values, unlike ``X[i]``) and `shade_rows` is compiled without index checks (`SHADE_OPTIONS`),
    so each index must be in range by construction, for any input (NaN or infinite normals and
    directions included): the face is clamped into [0, M); a face corner's word holds its vertex's
    window (`pack_windows`, from `Windows.win`; offset 0 and a 2 × 2 window for a vertex no face of
    the frame references: X has at least 4 rows, `prepare`); and the
    node offsets in the window, dx and dy, are clamped into [0, wu − 2] and [0, wv − 2] (wu, wv ≥ 2,
    and offset + wu·wv ≤ X's rows) whatever iu, iv are (a NaN direction gives NaN
    cell coordinates in ``lut_cell_xyz``, an arbitrary integer after the cast), so the 12 nodes read
    lie in the vertex's wu × wv window. Such a sample has ω_o not above its horizon (z > 0 is False
    for NaN), so its weights are 0 and it sets no miss bit. ``test_fast.py`` checks the compiled
    kernel against this function run eagerly (whose look-ups check their indices) on such inputs."""
    x, y, z = sample_frame(normal, wo)
    front = (z > 0) & live                                                      # ρ = 0 below the horizon
    iu, iv, fu, fv = lut_cell_xyz(x, y, z, R, index_dtype=torch.int32)
    g = Fnn.embedding(face.clamp(0, fwin.shape[0] - 1), fwin)                   # (n, S, 3) int64
    u, v = bary[..., 0], bary[..., 1]
    fw = front.to(u.dtype)
    beta = ((1.0 - u - v) * fw, u * fw, v * fw)
    gu, gv = 1 - fu, 1 - fv
    wc = (gu * gv, fu * gv, gu * fv, fu * fv)                                   # bilinear weights
    Xf = X.reshape(-1, 1)                       # node-major (N·3, 1): per channel, not per (n, S, 3) element
    B = [None, None, None]                      # channels apart: a (.., 3) result would redo the indexing per channel
    miss = torch.zeros_like(face, dtype=torch.uint8)
    for j in range(3):                                                          # B = Σ_j Σ_n β_j w_n X(v_j, n)
        pw = g[..., j]
        dx, dy = iu - (pw & 4095).to(torch.int32), iv - ((pw >> 12) & 4095).to(torch.int32)
        cu, cv = ((pw >> 24) & 15).to(torch.int32), ((pw >> 28) & 15).to(torch.int32)  # last cell column, row
        inside = (torch.minimum(dx, dy) >= 0) & (dx <= cu) & (dy <= cv)
        row = 3 * (cu + 2)
        base = (pw >> 32).to(torch.int32) * 3 + torch.minimum(dy.clamp(min=0), cv) * row + torch.minimum(dx.clamp(min=0), cu) * 3
        wi = beta[j] * inside
        for wn, off in zip(wc, (0, 3, row, row + 3)):
            w = wi * wn
            for c in range(3):
                t = Fnn.embedding(base + (off + c), Xf)[..., 0] * w
                B[c] = t if B[c] is None else B[c] + t
        miss = miss | (((beta[j] != 0) & ~inside).to(torch.uint8) << j)
    out = []
    for c in range(3):                                                          # the box filter (GBuffer.resolve)
        o = B[c][:, 0]
        for s in range(1, B[c].shape[1]):
            o = o + B[c][:, s]
        out.append(o * (1.0 / B[c].shape[1]))
    return torch.stack(out, -1), miss


# Inductor settings of `shade_rows`: no per-look-up index check (every index is in range by
# construction, `_shade_rows`), and the loop vectorised over 8 samples although nearly all its loads
# are gathers (Inductor's tiling heuristic leaves a loop with ≥ 35 non-contiguous loads scalar; the
# gathers stay 8 scalar loads each, the arithmetic around them — the frame, the cell, the weights, the
# index chains — runs 8-wide). Chess bench, 1 thread, same process: 1.55–1.6× (79 → 51–54 ns per sample).
SHADE_OPTIONS = {"assert_indirect_indexing": False, "cpp.enable_tiling_heuristics": False}


shade_rows = fused(_shade_rows, options=SHADE_OPTIONS)


def pack_windows(win: Tensor, face_rows: Tensor, R: int) -> Tensor:
    """Each face corner's window (`Windows.win` of its vertex) in one int64 word, (M, 3) for the M
    faces of ``face_rows`` (M, 3) int32 concatenated vertex ids: bits 0-11 the first column u0,
    12-23 the first row v0, 24-27 the last cell column wu − 2, 28-31 the last cell row wv − 2, 32-63
    the offset in X. `_shade_rows` reads one word per corner instead of the face's vertex id and 5
    words of its window: 39 indirect loads per sample instead of 54, the kernel 1.11× (chess bench V,
    1 thread, process CPU time, same process; bit-identical). Needs u0, v0 < 4096 (R ≤ 4096 nodes a
    side), wu, wv ≤ 17 (`MAX_WINDOW`) and offsets < 2³¹."""
    if R > 4096:
        raise ValueError(f"table of {R} nodes a side: at most 4096 fit the packed windows")
    w = win.long()
    p = w[:, 0] | (w[:, 1] << 12) | ((w[:, 3] - 2) << 24) | ((w[:, 4] - 2) << 28) | (w[:, 2] << 32)
    return p.index_select(0, face_rows.reshape(-1).long()).view(-1, 3)


def _entry_inputs(normal: Tensor, wo: Tensor, bary: Tensor, face: Tensor, live: Tensor, face_rows: Tensor,
                  R: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """`sample_inputs` of q samples for the exact path, for ``core.fused``: vertex ids (q, 3) int64,
    barycentric weights (q, 3) (0 where not shaded), the 4 bilinear node weights (q, 4) and the
    first node of the table cell (q,) int64. face < 0 is clamped (a miss: not live)."""
    x, y, z = sample_frame(normal, wo)
    front = (z > 0) & live
    iu, iv, fu, fv = lut_cell_xyz(x, y, z, R)
    u, v = bary[:, 0], bary[:, 1]
    fw = front.to(u.dtype)
    bw = torch.stack([(1.0 - u - v) * fw, u * fw, v * fw], -1)
    gu, gv = 1 - fu, 1 - fv
    return (face_rows[face.clamp_min(0)].long(), bw, torch.stack([gu * gv, fu * gv, gu * fv, fu * fv], -1),
            iv * R + iu)


entry_inputs = fused(_entry_inputs, options=VECTOR_OPTIONS)


def _entry_rows(i: Tensor, j: Tensor, k: Tensor, normal: Tensor, wo: Tensor, bary: Tensor, face: Tensor,
                live: Tensor, face_rows: Tensor, R: int, S2: int) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The exact path's inputs per sample–vertex entry outside its window (for ``core.fused``;
    `shade_pixels`): entry n is vertex j[n] of sample k[i[n]] of the q G-buffer samples (normal, wo
    (q, 3), bary (q, 2) in any layout, face (q,) int64, live (q,) bool), its inputs gathered here
    (`_entry_inputs`' arithmetic: the same values). Returns its concatenated vertex id (n,) int64,
    the first node of its table cell (n,) int64, its 4 node weights times β_j / S2 (n, 4) and its
    pixel (n,) int64. Compiled without index checks: i < k's rows, k < q, j < 3, the face clamped."""
    s = Fnn.embedding(i, k[:, None])[:, 0]
    x, y, z = sample_frame(Fnn.embedding(s, normal), Fnn.embedding(s, wo))
    b = Fnn.embedding(s, bary)
    f = Fnn.embedding(s, face[:, None])[:, 0]
    front = (z > 0) & (Fnn.embedding(s, live.to(torch.int32)[:, None])[:, 0] != 0)
    iu, iv, fu, fv = lut_cell_xyz(x, y, z, R)
    u, v = b[:, 0], b[:, 1]
    fw = front.to(u.dtype)
    bw = torch.where(j == 0, (1.0 - u - v) * fw, torch.where(j == 1, u * fw, v * fw))
    gu, gv = 1 - fu, 1 - fv
    wc = torch.stack([gu * gv, fu * gv, gu * fv, fu * fv], -1)
    vid = Fnn.embedding(f.clamp(0, face_rows.shape[0] - 1) * 3 + j, face_rows.view(-1, 1))[:, 0].long()
    return vid, iv * R + iu, wc * (bw * (1.0 / S2))[:, None], s // S2


entry_rows = fused(_entry_rows, options={"assert_indirect_indexing": False, **VECTOR_OPTIONS})


def shade_pixels(st: FastStatic, cs: list[Tensor], wins: Windows, normal: Tensor, wo: Tensor, bary: Tensor,
                 face: Tensor, live: Tensor, S2: int) -> Tensor:
    """Eq. 4 at q = n·S2 samples (pixel-major, S2 sub-samples per pixel; normal, wo (q, 3), bary
    (q, 2), face (q,) int64 (< 0: a miss), live (q,) bool), box-filtered → (n, 3): the compiled
    `shade_rows` over static blocks of `sample_block` samples, then the entries outside their
    windows from sh_lut and c (`_outliers`; their inputs recomputed by the compiled `entry_inputs`)."""
    q = int(face.shape[0])
    npx = q // S2
    dev = wins.X.device
    out = torch.empty(npx, 3, dtype=wins.X.dtype, device=dev)
    miss = torch.empty(npx, S2, dtype=torch.uint8, device=dev)
    rows = [t.unflatten(0, (npx, S2)) for t in (normal, wo, bary, face, live)]
    P = max(1, sample_block(q) // S2)
    fwin = pack_windows(wins.win, st.face_rows, st.R)
    for t in (wins.X, fwin):                           # rows vary per frame / scene: one compiled variant
        torch._dynamo.maybe_mark_dynamic(t, 0)
    args = (fwin, wins.X, st.R)
    warm_blocks(shade_rows, rows, args, [b // S2 for b in warm_sizes(P * S2) if b >= S2])
    for a in range(0, npx, P):
        blk = [t[a:a + P] for t in rows]
        n = blk[0].shape[0]
        if n < P:  # pad by repeating the last pixel (``core.fused.map_rows``); the padding is dropped
            blk = [torch.cat([b, b[-1:].expand(P - n, *b.shape[1:])]) for b in blk]
        o, mb = shade_rows(*blk, *args)
        out[a:a + n] = o[:n]
        miss[a:a + n] = mb[:n]
    k = miss.view(-1).nonzero(as_tuple=True)[0]
    if k.numel():                                      # entries outside their windows: the exact path
        bits = miss.view(-1).index_select(0, k)
        e = ((bits[:, None] >> torch.arange(3, device=dev, dtype=torch.uint8)) & 1).nonzero()
        i, j = e[:, 0], e[:, 1]
        ne = int(i.numel())
        if ne < 2:   # the compiler specialises sizes 0 and 1: one variant for every count (as `_outliers`)
            i, j = torch.cat([i, i[:1].expand(2 - ne)]), torch.cat([j, j[:1].expand(2 - ne)])
        for t in (i, j, k, normal, wo, bary, face, live):
            torch._dynamo.maybe_mark_dynamic(t, 0)
        ent = entry_rows(i, j, k, normal, wo, bary, face, live, st.face_rows, st.R, S2)
        v, first, wcm, px = (t[:ne] for t in ent)
        for s, fr in enumerate(st.regions):
            sel = ((v >= st.voff[s]) & (v < st.voff[s + 1])).nonzero(as_tuple=True)[0]
            o = _outliers(fr, cs[s], v[sel] - st.voff[s], first[sel], wcm[sel])  # empty: warms only
            if sel.numel():
                out.index_add_(0, px[sel], o)
    return out


def vertex_radiance(fr: FastRegion, c: Tensor, v: Tensor, cell: Tensor, wc: Tensor) -> Tensor:
    """Eq. 4 at vertices (shading "vertex", ``InOut._render_vertex``): B_v = Σ_n w_n X(v, n) over
    the 4 nodes of each vertex's own cell (the direction to the camera in its frame) — the sum
    `_outliers` forms for a sample–vertex entry, here once per vertex. v, cell (n,) int64 local
    vertex / first node; wc (n, 4) bilinear node weights; c (Vr, 3, K) → (n, 3)."""
    return _outliers(fr, c, v, cell, wc)


def _outlier_rows(v: Tensor, cell: Tensor, wc: Tensor, sh_nc: Tensor, c: Tensor, R: int) -> Tensor:
    """Σ_n w_n Σ_k σ_k h_{k,c}(n) c_{v,k,c} over the 4 nodes n of each entry's cell, for ``core.fused``
    (the 4 nodes unrolled, the table rows gathered inside the K-term reduction). v, cell (n,) int64
    local vertex / first node; wc (n, 4) node weights; sh_nc (R²·3, K); c (Vr, 3, K) → (n, 3)."""
    ch = torch.arange(3, device=v.device)
    # compiled without index checks (`outlier_rows`): every index clamped into range here, for any
    # input (a direction with an infinite component has z > 0 but a NaN table cell, an arbitrary
    # integer after the cast, and its entry misses its window)
    cell = cell.clamp(0, R * R - R - 2)
    v = v.clamp(0, c.shape[0] - 1)
    S = None
    for i, off in enumerate((0, 1, R, R + 1)):
        t = sh_nc[((cell + off) * 3)[:, None] + ch] * wc[:, i, None, None]         # (n, 3, K)
        S = t if S is None else S + t
    return (S * c[v]).sum(-1)


# No index checks (the indices are clamped into range, `_outlier_rows`): with the entry count dynamic
# (`_outliers`), 1.3-1.4× the static blocks with checks (chess bench V, 1 thread, same process).
outlier_rows = fused(_outlier_rows, options={"assert_indirect_indexing": False})


def _outliers(fr: FastRegion, c: Tensor, v: Tensor, cell: Tensor, wc: Tensor) -> Tensor:
    """Σ_n w_n X(v, n) for entries outside their vertex's window, each from its own 4 nodes: the
    compiled `outlier_rows` once over all of them, the entry count marked dynamic (static blocks of
    `sample_block` entries, a power of two, padded up to twice the work: 2.4·10⁴ entries in blocks
    of 16384 on chess bench; the per-vertex shading's 4.3·10³ vertices in one of 8192). Fewer than
    two entries are padded to two (vertex 0, node 0, zero weights): the compiler specialises sizes
    0 and 1, and a region with no such entry in the warm-up frame may have some later (the
    creature's second region: none in V frame 0, 1024 in frame 2) — the padded call compiles its
    variant in the warm-up frame. v, cell (n,) int64 local vertex / first node; wc (n, 4) node
    weights (β_j folded in); c (Vr, 3, K) → (n, 3)."""
    n = v.numel()
    if n < 2:
        z = torch.zeros(2 - n, dtype=v.dtype, device=v.device)
        v, cell = torch.cat([v, z]), torch.cat([cell, z])
        wc = torch.cat([wc, torch.zeros(2 - n, 4, dtype=wc.dtype, device=wc.device)])
    rows = [v.contiguous(), cell.contiguous(), wc.contiguous()]
    for t in (*rows, c):
        torch._dynamo.maybe_mark_dynamic(t, 0)
    return outlier_rows(*rows, fr.sh_nc, c, fr.R)[:n]
