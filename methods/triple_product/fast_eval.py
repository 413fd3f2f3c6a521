"""Fast exact evaluation of Ma 2006 eq. 7 and the frame-cost (roofline) model of `TripleProduct`.

    B^{x,ωo} = Σ_ijk C_ijk L^x_i V^x_j ρ̃^{ωo}_k                                   (Ma 2006 eq. 7)

At a shading point every factor is a *blend of stored truncated rows*: L = Σ_r w_r L_r over the k_L
nearby lighting-grid frames (8 for trilinear look-up), V = Σ_v w_v V_v over the triangle's three
vertices, ρ̃ = Σ_o w_o ρ̃_o over four tabulated outgoing directions. A blend is carried as a
*list*: indices (B, m) with duplicates allowed and values (B, C, m), m = k·n, C = 1 or 3 — the
tripling is trilinear, so a list with repeated indices is the same function as its coalesced form.

Three exact evaluators of the same sum ("dense" / "sparse" chosen by `choose_evaluator`, measured by
``python -m benchmarks.triple_product --micro``; "fine" when the tables allow it):

* ``"dense"`` — scatter the three lists into dense vectors and use the *fine-value identity*: the
  product of three level-L piecewise-constant functions is level-L piecewise constant, so
  Σ C_ijk f_i g_j h_k = A_L Σ_t f̂_t ĝ_t ĥ_t with f̂ = `spherical_haar.inverse`(f) (equal-area
  measure, A_L = 4^−L; the same tripling coefficients, Ma 2006 §3.1, summed in closed form).
  One inverse transform per channel plus one product pass — fewer K-length passes than the three
  scaling pyramids and per-level rule sums of `spherical_haar.triple_integral`.
  When every stored index is < 20·4^l for some l < L (``selection="top"`` with n ≤ 20·4^l, e.g.
  the paper's n = 20 / 80 / 320 = levels 0 / 1 / 2) the functions live in the level-l space and
  the evaluation runs at K' = 20·4^l instead of K (the prefix of the layout *is* level l's layout).
  Tables whose every row is 0..n−1 (all coefficients, or "top") are blended densely into
  (B, C, K') "dense lists" (idx None) instead of k·n-entry lists: no scatter.
* ``"sparse"`` — visit only the stored coefficients with the three tripling rules (Ma 2006 §3.1;
  the parent-sum form of `spherical_haar.triple_integral_sparse`, extended to three sparse lists):
  for every entry of list a, rule 1 (same level-0 scaling function), rule 2 (the other two
  wavelet types of the same triangle in b and c), rule 3 (b or c has the same wavelet; the third
  function enters through its average over the wavelet's support, i.e. its 1 + 3l coarser
  ancestors); for every entry of b, rule 3 with c identical and a coarser. Look-ups go through
  dense scratch rows (B, 7, K) of a sub-batch of `INNER_POINTS` points: O(m·L) gathers plus an
  O(K) memset per point, so it only wins when m ≪ K (n = 20 at level 4).

The lighting list (the longest, k_L·n entries) is never enumerated ("c"); V is "a", ρ̃ is "b".

* ``"fine"`` (what "auto" runs when every table is *full* — every row's indices 0..n−1: all
  coefficients kept, or ``selection="top"``): the fine-value identity with the blends done on
  *fine-value tables* (`fine_table`: each stored row's fine values, computed once per table; fine
  values are linear, so blending them = the fine values of the blend) — the three blends and the
  product summed in one compiled loop per point and channel (`fine_block` through
  `methods.core.fused`, one call with a symbolic point count; the blends are never stored).
  Measured on chess (bench, 262144 samples, same process, load ~12 on 2 cores): 1.0-1.6 s against
  10.2 s for the previous eager form (three weighted `embedding_bag` blends and a batched product
  per 256 points).
  Pixel frames (G-buffer samples, several visibility rows each) go *by groups* (`fine_grouped`,
  comment before `grouping_pays`): eq. 7 is trilinear, so its K'-long sums are done once per
  distinct (visibility row, L cell, ρ̃ cell) — 0.07–0.09 per sample on the bench scenes — and every
  sample blends its groups' k_L·k_ρ values. Chess bench V, same process, 1 thread: 2253 ms → 250 ms
  process CPU per frame.
  Where one visibility row is summed per item (per-vertex points, pixel groups) and a C compiler is
  at hand, a native loop (`native`) sums only the 8-column chunks of the live columns where that
  row is non-zero (`vis_chunks`): the same sums without their exact zeros, float32 round-off.

Frame cost (the roofline model, `frame_cost` → `methods.base.FrameCost`): the minimum work of a
frame, n = kept coefficients per function, counts of the last rendered frame of the same size
(``method.last_frame()``: shaded samples, distinct faces, distinct visibility rows, shaded
vertices, groups of `fine_grouped`; before any render, upper bounds from the sample count):
  * bytes — every array read once: the visibility rows the G-buffer touches (n values + n indices;
    indices of a full table carry nothing and are not counted; on the fine-value path their non-zeros
    only, see below), every ρ̃ table (SBRDF "b" tables
    too), the truncated lighting grid, the touched faces' vertex indices, per shaded vertex its
    frame, position and region (vertex shading), the UV-space extras' arrays whole (small); the
    G-buffer inputs (`GBUFFER_BYTES_PER_SAMPLE` + the int64 region per sample for pixel shading;
    vertex shading reads no normal / ωo); the (H, W, 3) float32 image (`methods.base.output_bytes`).
    Frames whose lighting changed ("L" or "E" in the kind) add the env map's texels read and the truncated grid written (and the
    base coordinates read when the last re-projection was azimuthal, `relight_table_bytes`).
  * flops — per shading point (pixel: every hit sample; vertex: every shaded vertex, plus the
    Gouraud blend of 3 vertex colours per hit sample, 3·5 flops): forming the three functions from
    their stored rows, a blend of k rows costing (2k − 1)·n flops per channel (k multiplies, k − 1
    adds; none for a single row of weight 1) — V: 3 vertex rows for pixels (1 channel), its own
    row for a vertex; ρ̃: 4 ωo rows × 3 channels; L: the look-up's distinct grid rows × 3 — 4 for
    trilinear with n_psi = 1, 8 else, 1 nearest — plus eq. 7's triple sum with n coefficients per
    function, the smaller of
    (a) the sparse tripling rules (Ma 2006 §3.1, the parent-sum form of ``"sparse"``), per output
        channel Σ_{V entries}(10 + 2A) + Σ_{ρ̃ entries}(3 + A), A = 1 + 3l the rule-3 ancestor
        count of a level-l wavelet (0 for scaling functions), averaged over the stored indices;
    (b) the fine-value product: 3 flops per channel per fine triangle of K' (K' = the smallest
        20·4^l holding the kept prefix when tables are full, then no transform is needed since
        full rows can be kept as fine values at the same size; else K plus 7 inverse transforms,
        8(K − 20)/3 flops each).
    Where the fine-value path runs and some fine triangles are dead (`live_triangles`: every
    visibility row or every ρ̃ row exactly 0 there, so they add an exact 0 to eq. 7 whatever the
    lighting; about half of the local sphere on the bench scenes), only the n' live ones count
    (session 19: the implementation reads, sums and projects only those): n' values per stored V,
    ρ̃ and grid row, K' = n' in (b) and the grouped form, n' per blend, and a re-projection of the
    live triangles' samples only, without the transform (their fine values are what eq. 7 reads).
    Finer still, at the grain of the zeros (`nonzero_reads`, issue 14's cost model, session 25): a
    point whose blended visibility is exactly 0 on a live triangle (every row it blends with a
    non-zero weight is 0 there; 38–48 % of the live triangles per vertex on the bench scenes) gets
    an exact 0 from that triangle whatever ρ̃ and L, so its blends and its sum count only its own
    non-zero triangles (K' = its count in (b)); a group counts its row's non-zero triangles; and a
    re-projection counts only the (grid frame, live triangle) pairs some point looks up with a
    non-zero weight and has non-zero visibility on (60–67 % of the looked-up frames' pairs), the
    grid written likewise. The visibility rows' bytes at the same grain (session 37; until then whole
    rows, on the grounds that the zeros are known only from the row — but a bit per live column says
    where they are for 1/32 of the row): per distinct row read its non-zero values, ⌈n'/8⌉ bytes of
    bit mask and an int64 start (`visibility_read_bytes`; creature bench per vertex 11.4 → ~6.7 MB).
    Our implementation skips most of those
    zeros where one visibility row is summed per item (per-vertex points, pixel groups: the native
    loop of `native`, over each row's non-zero 8-column chunks — 63-67 % of the live columns summed
    where 54-57 % are non-zero on the bench scenes, 75-83 % of the zeros skipped); the re-projection
    still projects every live triangle of the looked-up frames (not the pairs counted).
    A pixel frame summed by groups (`fine_grouped`) counts instead, when smaller, the grouped form
    (`grouped_flops`): per group and channel K'·(k_L + 2·k_L·k_ρ), per shaded sample and channel
    k_v·(2·k_L·k_ρ + k_L) + k_v − 1 (k_v = 3, k_ρ = 4, k_L as above).
    Frames whose lighting changed add the re-projection (`relight_flops`; 31 instead of 45 flops per
    sample when the last one was azimuthal, ``method.stats["lighting_path"]``: a map turned about +Y).
  ``light_lookup="exact"`` projects per shading point: not modelled (None).
"""
from __future__ import annotations

import math
from functools import lru_cache

import torch
from torch import Tensor

from methods.core.fused import call_rows, fused, map_rows
from methods.core.spherical_haar import coefficient_structure, level_of_size, n_triangles
from methods.triple_product import brdf_table as bt
from methods.triple_product import lighting as lt
from methods.triple_product import native
from methods.triple_product import native_group
from methods.triple_product import native_light
from methods.triple_product.precompute import truncate

EVALUATORS = ("auto", "fine", "dense", "sparse", "reference")
# "auto" picks "sparse" when the enumerated entries per point (m_a + m_b) times this factor are
# fewer than K: a sparse entry costs ≈ 6·(1 + 3L) gathers, a dense coefficient ≈ 20 streaming ops
# over 7 channels. Measured (`python -m benchmarks.triple_product --micro`, 32 points, 1 thread,
# µs/point dense vs sparse): K = 5120, n = 20 (K/(7n) = 37): 87 vs 54; K = 1280, n = 20 (ratio 9):
# 20 vs 25; K = 5120, n = 80 (ratio 9): 99 vs 131. On a real bench-size frame (sphere_plane,
# level 4, n = 20): sparse 2.7 s vs dense 6.2 s CPU.
SPARSE_BREAK_EVEN = 12.0
# Points per evaluation sub-batch: the dense scratch (B, 7, K) float32 of 32 points is 1.1 MB at
# K = 1280 and 4.6 MB at K = 5120; 16–32 measured fastest on this machine (L2 = 2 MiB per core).
INNER_POINTS = 32

SparseList = tuple[Tensor | None, Tensor]  # idx (B, m) int64, val (B, C, m); or (None, (B, C, K)) dense


def _check_list(name: str, lst: SparseList, B: int | None = None, K: int | None = None) -> SparseList:
    idx, val = lst
    if idx is None:  # dense list (B, C, K'), K' = 20·4^l ≤ K
        if val.ndim != 3 or val.shape[1] not in (1, 3) or _round_size(val.shape[2]) != val.shape[2] or \
                (K is not None and val.shape[2] > K) or (B is not None and val.shape[0] != B):
            raise ValueError(f"{name}: a dense list must be (B, 1|3, 20·4^l ≤ K), got {tuple(val.shape)}")
        return None, val
    if idx.ndim != 2 or val.ndim != 3 or val.shape[0] != idx.shape[0] or val.shape[2] != idx.shape[1]:
        raise ValueError(f"{name}: idx (B, m) and val (B, C, m) expected, got {tuple(idx.shape)}, {tuple(val.shape)}")
    if val.shape[1] not in (1, 3):
        raise ValueError(f"{name}: 1 or 3 channels expected, got {val.shape[1]}")
    if B is not None and idx.shape[0] != B:
        raise ValueError(f"{name}: batch {idx.shape[0]} differs from {B}")
    return idx.long(), val


# -- building the lists ----------------------------------------------------------------------------


def blend_list(idx: Tensor, val: Tensor, rows: Tensor, w: Tensor, *, full: bool = False) -> SparseList:
    """The list form of the blend Σ_r w_r f_{rows_r} of stored truncated rows (no densification).

    Args:
        idx: (N, n) int stored indices; val: (N, n) or (N, C, n) stored values.
        rows: (B, k) int64 rows; w: (B, k) weights.
        full: every row of ``idx`` is 0..n−1 (all coefficients kept, or "top" selection): the
            blend is summed densely and returned as a *dense list* (None, (B, C, K')), zero-padded
            to K' = the smallest 20·4^l ≥ n (the functions live in level l's space).
    Returns:
        idx (B, k·n) int64 (duplicates possible) and val (B, C, k·n); (None, (B, C, K')) if full.
    """
    if rows.ndim != 2 or w.shape != rows.shape:
        raise ValueError(f"rows and w must be matching (B, k), got {tuple(rows.shape)}, {tuple(w.shape)}")
    B, k = rows.shape
    n = idx.shape[-1]
    if full:
        v = val if val.ndim == 3 else val[:, None, :]
        wv = w.to(v.dtype)
        acc = v[rows[:, 0]] * wv[:, 0, None, None]
        for r in range(1, k):
            acc.addcmul_(v[rows[:, r]], wv[:, r, None, None])
        Kp = _round_size(n)
        return None, (acc if Kp == n else torch.nn.functional.pad(acc, (0, Kp - n)))
    ii = idx[rows].long().reshape(B, k * n)
    if val.ndim == 2:
        vv = (val[rows] * w[..., None].to(val.dtype)).reshape(B, 1, k * n)
    elif val.ndim == 3:
        C = val.shape[1]
        vv = (val[rows] * w[..., None, None].to(val.dtype)).permute(0, 2, 1, 3).reshape(B, C, k * n)
    else:
        raise ValueError(f"val must be (N, n) or (N, C, n), got {tuple(val.shape)}")
    return ii, vv


def _brdf_stack(method, which: str = "a") -> tuple[Tensor, Tensor]:
    """All regions' ρ̃ tables stacked in region order: idx (R·n_o, n), val (R·n_o, 3, n).

    which: "a" (the regions' materials, ``method.tables``) or "b" (the SBRDF second material of
    blended regions, ``method.blends``; the "a" table stands in elsewhere and gets weight 0).
    Cached on the identity of the table tensors (a material edit replaces them)."""
    tabs = [method.tables[name] for name in method.scene.regions]
    if which == "b":
        blends = getattr(method, "blends", {}) or {}
        tabs = [(blends[name][1], blends[name][2]) if name in blends else t
                for name, t in zip(method.scene.regions, tabs)]
    key = tuple(id(t) for pair in tabs for t in pair)
    cache = method.__dict__.setdefault("_perf_cache", {})
    if cache.get(("brdf_key", which)) != key:
        cache[("brdf_key", which)] = key
        cache[("brdf_src", which)] = tabs  # keeps the sources alive: their ids cannot be reused
        cache[("brdf", which)] = (torch.cat([i for i, _ in tabs]), torch.cat([v for _, v in tabs]))
    return cache[("brdf", which)]


def _is_full(method, name: str, idx: Tensor) -> bool:
    """Every row of the stored index table is 0..n−1 (n_coeffs = all, or "top" selection);
    cached per tensor."""
    cache = method.__dict__.setdefault("_perf_cache", {})
    key = ("full", name)
    if key not in cache or cache[key][0] is not idx:  # holds idx: no id reuse while cached
        n = idx.shape[-1]
        cache[key] = (idx, bool(torch.equal(idx, torch.arange(n, dtype=idx.dtype, device=idx.device).expand_as(idx))))
    return cache[key][1]


def shading_rows(method, R: Tensor | None, wo_world: Tensor, region: Tensor, vrows: Tensor, vw: Tensor,
                 mix: Tensor | None = None, *, lookups: tuple | None = None) -> list[list[tuple]]:
    """The look-ups of eq. 7's three factors at B points, before blending (cheap, O(B)).

    Same arguments as `shading_lists`; ``lookups``: the (rows, w, lrows, lw) of `grid_lookups`
    already at hand (`pixel_lookups`: from the normals), then R may be None. Returns, for V, ρ̃ and L, a list of parts: ("blend",
    idx_table, val_table, rows (B, k), w (B, k), full) or ("list", idx (B, m), val (B, C, m)) (the
    per-point lighting of ``light_lookup="exact"``). `lists_from_rows` blends any slice of points.
    """
    B = wo_world.shape[0]
    if R is None and (lookups is None or method.config["light_lookup"] == "exact"):
        raise ValueError("shading_rows needs the frames R (or the look-ups of a grid light_lookup)")
    if (R is not None and R.shape != (B, 3, 3)) or wo_world.shape != (B, 3) or region.shape != (B,) \
            or vrows.shape != vw.shape or vrows.shape[0] != B:
        raise ValueError("R (B, 3, 3), wo_world (B, 3), region (B,), vrows/vw (B, k) expected, got "
                         f"{None if R is None else tuple(R.shape)}, {tuple(wo_world.shape)}, {tuple(region.shape)}, {tuple(vrows.shape)}")
    cfg = method.config
    if lookups is None and hasattr(method, "fill_lighting"):
        method.fill_lighting()  # a lazily set grid (`TripleProduct._set_lighting`): every frame projected
    Vp = [("blend", method.V_idx, method.V_val, vrows, vw, _is_full(method, "V", method.V_idx))]
    grid_mode = None if cfg["light_lookup"] == "exact" else cfg["light_lookup"]
    rows, w, lrows, lw = grid_lookups(R, wo_world, method.outgoing, method.grid, grid_mode) if lookups is None \
        else lookups[:4]
    bi, bv = _brdf_stack(method)
    # `pixel_lookups` with the regions (`shade_pixels`: lookups[4] True): its rows are already brows
    brows = rows if lookups is not None and len(lookups) > 4 and lookups[4] else \
        rows + region[:, None].long() * method.outgoing.size
    blends = getattr(method, "blends", None)
    if mix is not None and blends:
        if mix.shape != (B,):
            raise ValueError(f"mix must be ({B},), got {tuple(mix.shape)}")
        names = method.scene.regions
        has = torch.tensor([name in blends for name in names], dtype=torch.bool, device=region.device)[region]
        mb = torch.where(has, mix.to(w.dtype), torch.zeros_like(mix, dtype=w.dtype))[:, None]
        bi2, bv2 = _brdf_stack(method, "b")
        # Ma 2006 §5 SBRDF: linear in ρ̃, so the two tables' lists concatenate
        rp = [("blend", bi, bv, brows, w * (1 - mb), _is_full(method, "rho", bi)),
              ("blend", bi2, bv2, brows, w * mb, _is_full(method, "rho_b", bi2))]
    else:
        rp = [("blend", bi, bv, brows, w, _is_full(method, "rho", bi))]
    if cfg["light_lookup"] == "exact":
        Lc = lt.project_lighting(method._exact_env.radiance, R, method.geo, supersample=cfg["light_supersample"])
        li, lv = truncate(Lc, method._n(), cfg["selection"], method.level)
        Lp = [("list", li.long(), lv)]
    else:
        Lp = [("blend", method.L_idx, method.L_val, lrows, lw, _is_full(method, "L", method.L_idx))]
    return [Vp, rp, Lp]


def _lookups(R: Tensor, wo_world: Tensor, outgoing, grid, mode: str | None) -> tuple[Tensor, ...]:
    """`brdf_table.outgoing_weights` at ωo in the local frames R and `lighting.lookup_weights`
    of R (mode None: no grid look-up) — for a trilinear look-up on a grid with one tangent angle
    `lighting.cell_weights` (its 4 distinct frames, no ψ) — as one function to compile, every output
    column a 1-D (b,) plane: 4 ωo rows, 4 weights, then the k_L grid rows and k_L weights. With
    stacked (b, k) outputs Inductor left the loops scalar (libm trig, one loop per output shape,
    each recomputing the trig)."""
    rows, w = bt.outgoing_terms((R @ wo_world.unsqueeze(-1)).squeeze(-1), outgoing)
    if mode is None:
        return (*rows, *w)
    if mode == "trilinear" and grid.n_psi == 1:
        lrows, lw = lt.cell_terms(R, grid)
        return (*rows, *w, *lrows, *lw)
    lrows, lw = lt.lookup_weights(R, grid, mode)
    return (*rows, *w, *lrows.unbind(1), *lw.unbind(1))


# Inductor settings of the eq. 7 kernels (`fine_block`, `group_block`): the table rows they gather
# come from the grid / ωo look-ups and the G-buffer's vertices (in range by construction), so the
# per-load index checks are dropped; and every channel's sum stays in the one loop over the fine
# triangles (with the default realize thresholds two of `fine_block`'s three (b, K') products were
# stored and summed in separate passes). Chess bench, 1 thread, same process: vertex V fine_kernel
# 14.4 -> 12.4 ms CPU.
# Products and sums contracted into fused multiply-adds (Inductor compiles with -ffp-contract=off by
# default, to match eager torch bit for bit; these loops are multiply-then-accumulate, so they ran
# two vector instructions where one does): chess bench pixel V, 1 thread, same process, `group_block`
# 56 -> 41-47 ms (the sums change by float32 round-off, tests/methods/triple_product).
KERNEL_OPTIONS = {"assert_indirect_indexing": False, "realize_opcount_threshold": 1000,
                  "realize_reads_threshold": 1000, "realize_acc_reads_threshold": 1000,
                  "cpp.enable_floating_point_contract_flag": "fast"}
# Inductor's tiling heuristics leave these loops (loads of (b, 3) / (b, 3, 3) components, reductions
# over the 3 components) scalar with scalar libm trig; without them the per-point front end of a pixel
# frame ran ~1.5x faster (1 thread, 2^17 points, loaded machine).
FRONT_OPTIONS = {"cpp.enable_tiling_heuristics": False}
_lookups_fused = fused(_lookups, options=FRONT_OPTIONS)
_local_frames_fused = fused(lt.local_frames, options=FRONT_OPTIONS)
# Points per compiled block of the per-sample look-ups (a frame's front end: trig in float64 that
# eager torch runs as ~40 passes over (P,) arrays); smaller batches (per-vertex frames) use the tail.
LOOKUP_BLOCK = 1 << 15
LOOKUP_TAIL = 1 << 12


def _rows_chunk(B: int) -> int:
    return LOOKUP_BLOCK if B >= LOOKUP_BLOCK else LOOKUP_TAIL


def local_frames(n: Tensor, tangent: str) -> Tensor:
    """`lighting.local_frames` (B, 3) → (B, 3, 3), compiled over static blocks (`methods.core.fused`)."""
    if n.ndim != 2 or n.shape[1] != 3:
        raise ValueError(f"normals must be (B, 3), got {tuple(n.shape)}")
    return map_rows(_local_frames_fused, [n], (tangent,), chunk=_rows_chunk(n.shape[0]))


def _front_planes(n: Tensor, wo: Tensor, outgoing, grid, region: Tensor | None = None) -> tuple[Tensor, ...]:
    """`_lookups` (mode "trilinear", grid with n_psi = 1) of the frames `lighting.local_frames`
    (n, "grid") of unit normals n (b, 3) float32, at world ωo given as planes (3, b) — the same arithmetic written
    per component on 1-D (b,) planes: R is never formed, no (b, 3) intermediate exists. Inductor
    vectorises a (b, 3) tensor's size-3 dimension (3 of 8 lanes, masked loads; one loop nest per
    intermediate), which left the front end of a pixel frame at ~70 ms for 2^18 samples (local
    frames + `_lookups`, chess bench, 1 thread); on planes it is one 8-lane loop (float32 trig)
    and one 4-lane loop (float64 trig), ~20 ms (`benchmarks.tp_frames_ab` reports the frame).
    Same planes as ``_lookups(local_frames(n, "grid"), wo, outgoing, grid, "trilinear")``: rows
    equal, weights to float32 round-off (tests/methods/triple_product/test_tp_fast_eval.py).
    ``region`` (b,) int64 given: the ωo rows come offset to the point's region's ρ̃ stack,
    rows + region·outgoing.size (`shading_rows`' brows, formed here instead of three (b, 4) int64
    passes after). The cell indices are int32 inside the loop (8 lanes, not two 4-lane int64 halves),
    widened to int64 rows at the end: the same integers (they are < n_θ·n_φ; a non-finite angle's
    index is negative either way and `lighting.periodic_index` / the θ clamps map it alike)."""
    nx, ny, nz = n[:, 0], n[:, 1], n[:, 2]
    # `lighting.local_frames` "grid": s = s0(θ, φ) made orthogonal to n, t = n × s (float32)
    theta = torch.acos(ny.clamp(-1.0, 1.0))
    phi = torch.remainder(torch.atan2(nz, nx), 2 * math.pi)
    st, ct, sp, cp = torch.sin(theta), torch.cos(theta), torch.sin(phi), torch.cos(phi)
    s0x, s0y, s0z = ct * cp, -st, ct * sp
    d = s0x * nx + s0y * ny + s0z * nz
    sx, sy, sz = s0x - d * nx, s0y - d * ny, s0z - d * nz
    nrm = (sx * sx + sy * sy + sz * sz).sqrt().clamp_min(1e-12)
    sx, sy, sz = sx / nrm, sy / nrm, sz / nrm
    tx, ty, tz = ny * sz - nz * sy, nz * sx - nx * sz, nx * sy - ny * sx
    wx, wy, wz = wo[0], wo[1], wo[2]
    lx = sx * wx + sy * wy + sz * wz                                   # ωo in the local frame (R ωo)
    ly = tx * wx + ty * wy + tz * wz
    lz = nx * wx + ny * wy + nz * wz
    # `brdf_table.outgoing_terms` (float64)
    x, y, z = lx.double(), ly.double(), lz.double()
    r = (x * x + y * y + z * z).sqrt().clamp_min(1e-30)
    th = torch.acos((z / r).clamp(0.0, 1.0))
    ph = torch.remainder(torch.atan2(y, x), 2 * math.pi)
    fi = (th / (0.5 * math.pi / outgoing.n_theta) - 0.5).clamp(0, outgoing.n_theta - 1)
    fj = ph / (2 * math.pi / outgoing.n_phi)
    i0 = fi.floor().to(torch.int32).clamp(0, max(outgoing.n_theta - 2, 0))
    ai = (fi - i0).clamp(0, 1)
    i1 = (i0 + 1).clamp(max=outgoing.n_theta - 1)
    j0 = fj.floor().to(torch.int32)
    aj = fj - j0
    rows, w = [], []
    for di, wi in ((0, 1 - ai), (1, ai)):
        for dj, wj in ((0, 1 - aj), (1, aj)):
            r = ((i1 if di else i0) * outgoing.n_phi + lt.periodic_index(j0 + dj, outgoing.n_phi)).long()
            rows.append(r if region is None else r + region * outgoing.size)
            w.append((wi * wj).to(wo.dtype))
    # `lighting.cell_terms` (float64 angles of n; `lighting._bilinear_cell` with int32 indices)
    gth = torch.acos(ny.double().clamp(-1.0, 1.0))
    gph = torch.remainder(torch.atan2(nz.double(), nx.double()), 2 * math.pi)
    gfi, gfj = lt._normal_coordinates(gth, gph, grid)
    gi0 = gfi.floor().to(torch.int32).clamp(0, grid.n_theta - 2)
    gai = (gfi - gi0).clamp(0, 1)
    gj0 = gfj.floor().to(torch.int32)
    gaj = gfj - gj0
    lrows, lw = [], []
    for di, wi in ((0, 1 - gai), (1, gai)):
        for dj, wj in ((0, 1 - gaj), (1, gaj)):
            lrows.append(((gi0 + di) * grid.n_phi + lt.periodic_index(gj0 + dj, grid.n_phi)).long())
            lw.append((wi * wj).to(n.dtype))
    return (*rows, *w, *lrows, *lw)



def _front_stacked(n: Tensor, wo: Tensor, outgoing, grid, region: Tensor | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """`_front_planes` stacked in the compiled loop: (rows, w, lrows, lw), each (b, 4) — the layout
    `pixel_lookups` returns, written by `map_rows(out=...)` straight into the frame's arrays. The
    planes were concatenated over the blocks and then stacked (`_unplane`): two more passes over
    16 planes of 2^18 samples (1 thread, same process, chess-bench-sized random normals: 44-46 vs
    30-33 ms for the look-ups, bit-identical)."""
    p = _front_planes(n, wo, outgoing, grid, region)
    return tuple(torch.stack(p[4 * i:4 * i + 4], 1) for i in range(4))


_front_stacked_fused = fused(_front_stacked, options=FRONT_OPTIONS)


def front_ok(method) -> bool:
    """`pixel_lookups` applies: tangent "grid", trilinear look-up on a grid with one tangent angle."""
    return method.config["tangent"] == "grid" and method.config["light_lookup"] == "trilinear" and \
        method.grid.n_psi == 1


def pixel_lookups(normals: Tensor, wo_world: Tensor, outgoing, grid, region: Tensor | None = None) -> tuple[Tensor, ...]:
    """(rows, w, lrows, lw) of `grid_lookups` (mode "trilinear", n_psi = 1) at the frames
    `lighting.local_frames` (normals, "grid") — from the normals, without forming the frames
    (`_front_planes`, compiled once with a symbolic point count and called on the whole frame).
    It ran over static blocks (`map_rows(out=...)`), each block's 4 (b, 4) results copied into
    the frame's arrays: ~6 of ~22 ms for 2^18 samples. This loop is compute-bound (trig), so the
    symbolic count costs nothing measurable: 2^18 random normals, 1 thread, same process,
    25.6 -> 18.2 ms, the same values bit for bit (one compilation serves every frame size).
    ``region`` (B,) given (the frames' call, `shade_pixels`): rows are offset to each point's ρ̃ stack
    (`_front_planes`), ``rows + region[:, None] * outgoing.size``, as `shading_rows` forms them."""
    if normals.ndim != 2 or normals.shape[1] != 3 or wo_world.shape != normals.shape:
        raise ValueError(f"normals and wo must be (B, 3), got {tuple(normals.shape)}, {tuple(wo_world.shape)}")
    if grid.n_psi != 1:
        raise ValueError(f"pixel_lookups needs a grid with n_psi = 1, got {grid}")
    # ωo as (3, B) planes: the G-buffer stores it so (`make_gbuffer`: strides (1, P)), then no copy,
    # and the loop loads each component contiguously (it copied the (B, 3) rows: ~2 ms a bench frame)
    n, wo = normals.float().contiguous(), wo_world.float().t().contiguous()
    xs = [n, wo]
    if region is not None:
        if region.shape != (n.shape[0],):
            raise ValueError(f"region must be ({n.shape[0]},), got {tuple(region.shape)}")
        xs.append(region.long().contiguous())
    if n.shape[0] <= 1:                               # sizes Dynamo would specialise
        return _front_stacked(*xs[:2], outgoing, grid, *xs[2:])
    for x in xs:                                      # one compiled variant for every frame size
        torch._dynamo.maybe_mark_dynamic(x, x.ndim - 1 if x is wo else 0)
    return _front_stacked_fused(*xs[:2], outgoing, grid, *xs[2:])


def _unplane(planes: tuple[Tensor, ...], mode: str | None, grid) -> tuple:
    """(rows, w, lrows, lw) (B, k) from `_lookups`' planes (lrows, lw None when ``mode`` is None)."""
    rows, w = torch.stack(planes[0:4], 1), torch.stack(planes[4:8], 1)
    if mode is None:
        return rows, w, None, None
    k = (len(planes) - 8) // 2
    return rows, w, torch.stack(planes[8:8 + k], 1), torch.stack(planes[8 + k:], 1)


def _lookups_stacked(R: Tensor, wo_world: Tensor, outgoing, grid, mode: str | None) -> tuple:
    """`_lookups` stacked in the compiled loop: (rows, w[, lrows, lw]), each (b, k)."""
    rows, w, lrows, lw = _unplane(_lookups(R, wo_world, outgoing, grid, mode), mode, grid)
    return (rows, w) if mode is None else (rows, w, lrows, lw)


_lookups_stacked_fused = fused(_lookups_stacked, options=FRONT_OPTIONS)


def grid_lookups(R: Tensor, wo_world: Tensor, outgoing, grid, mode: str | None):
    """The ωo look-up (rows, w (B, 4), `brdf_table.outgoing_weights` of ωo in the frames R (B, 3, 3))
    and, unless ``mode`` is None, the lighting-grid look-up (`lighting.lookup_weights` of R; its 4
    distinct frames, `lighting.cell_weights`, for a trilinear look-up with n_psi = 1), compiled:
    (rows, w, lrows, lw), the last two None when ``mode`` is None. One call with a symbolic point
    count, the (b, k) results stacked inside it (`methods.core.fused.call_rows`; a compute-bound
    loop, as `pixel_lookups`); it ran over static blocks of `LOOKUP_TAIL` / `LOOKUP_BLOCK` points,
    the 16 planes concatenated over the blocks and stacked after (chess bench per-vertex V, 10701
    vertices: three blocks of 4096, one padded): 1.8 -> 1.1 ms per frame, 1 thread, per-stage
    timers; the same frame images bit for bit (`benchmarks.tp_frames_ab`)."""
    if R.ndim != 3 or R.shape[1:] != (3, 3) or wo_world.shape != (R.shape[0], 3):
        raise ValueError(f"R (B, 3, 3) and wo (B, 3) expected, got {tuple(R.shape)}, {tuple(wo_world.shape)}")
    out = call_rows(_lookups_stacked_fused, [R, wo_world], (outgoing, grid, mode))
    return out if mode is not None else (*out, None, None)


def lists_from_rows(spec: list[list[tuple]], s: slice, K: int) -> tuple[SparseList, SparseList, SparseList]:
    """The (V, ρ̃, L) lists of the points ``s`` of a `shading_rows` result."""
    out = []
    for parts in spec:
        lists = []
        for p in parts:
            if p[0] == "list":
                lists.append((p[1][s], p[2][s]))
            else:
                _, it, vt, rows, w, full = p
                lists.append(blend_list(it, vt, rows[s], w[s], full=full))
        if len(lists) == 1:
            out.append(lists[0])
        elif any(x[0] is None for x in lists):  # dense lists: add
            out.append((None, sum(_scatter(x, K) for x in lists)))
        else:
            out.append((torch.cat([x[0] for x in lists], 1), torch.cat([x[1] for x in lists], 2)))
    return tuple(out)


def shading_lists(method, R: Tensor, wo_world: Tensor, region: Tensor, vrows: Tensor,
                  vw: Tensor, mix: Tensor | None = None) -> tuple[SparseList, SparseList, SparseList]:
    """The three factors of eq. 7 at B points as lists, from a precomputed `TripleProduct`
    whose lighting is set (``method._set_lighting`` ran, as in ``render``).

    Args: R (B, 3, 3) local frames (rows s, t, n); wo_world (B, 3); region (B,) int64;
        vrows, vw (B, k) visibility rows / weights into the visibility table (vertices, texels);
        mix: (B,) SBRDF weight (Ma 2006 §5: ρ̃ = (1 − mix) ρ̃_a + mix ρ̃_b in regions with a blend,
        ``method.blends``), or None.
    Returns: (V, ρ̃, L) lists: V (B, 1, k·n), ρ̃ (B, 3, 4n) (8n with a blend), L (B, 3, k_L·n)
        (dense lists (None, (B, C, K)) when all coefficients are kept).
    """
    return lists_from_rows(shading_rows(method, R, wo_world, region, vrows, vw, mix), slice(None), method.K)


# -- dense evaluator ----------------------------------------------------------------------------


def fine_values(x: Tensor) -> Tensor:
    """`spherical_haar.inverse` with the sign matrix unrolled (child = s ± w0 ± w1 ± w2).

    Args: x (..., 20·4^L) coefficients. Returns (..., 20·4^L) fine values."""
    L = level_of_size(x.shape[-1])
    s = x[..., :20]
    for l in range(L):
        lo = n_triangles(l)
        w = x[..., lo:4 * lo].unflatten(-1, (lo, 3))
        w0, w1, w2 = w.unbind(-1)
        u, v = s + w0, s - w0
        p, q = w1 + w2, w1 - w2
        # children a, b, c, d (Ma 2006 §3.1 sign pattern, `spherical_haar._SIGNS`)
        s = torch.stack((u + p, u - p, v + q, v - q), -1).flatten(-2)
    return s


@lru_cache(maxsize=16)
def blocked_order(level: int) -> Tensor:
    """(K,) int64 position of every coefficient in the *blocked* layout used by `fine_values_blocked`.

    Same content as the module layout, reordered so that every step of the inverse transform is a
    contiguous block operation: level-l scaling values are kept in an order ord_l (ord_0 = 0..19,
    ord_{l+1} = [4·ord_l + p for p = a, b, c, d] concatenated), and the level-l wavelets are stored
    type-major in that node order (position 20·4^l + t·n_l + j for node ord_l[j]).
    The fine values come out in the order ord_L (a permutation of the triangles): fine-value sums
    and products are order-independent, so three functions in this layout give the same triple sum.
    """
    L = int(level)
    pos = torch.empty(n_triangles(L), dtype=torch.int64)
    pos[:20] = torch.arange(20)
    ordl = torch.arange(20)
    for l in range(L):
        lo = n_triangles(l)
        for t in range(3):
            pos[lo + 3 * ordl + t] = lo + t * lo + torch.arange(lo)
        ordl = torch.cat([4 * ordl + p for p in range(4)])
    return pos


@lru_cache(maxsize=16)
def _blocked_inverse(level: int, device_type: str) -> Tensor:
    """(K,) coefficient index stored at each position of the blocked layout (inverse of `blocked_order`)."""
    return torch.argsort(blocked_order(level)).to(torch.device(device_type))


def fine_values_blocked(x: Tensor) -> Tensor:
    """Fine values (in the order ord_L, `blocked_order`) of coefficients x (..., K) in the blocked
    layout; each level is 8 contiguous block operations."""
    L = level_of_size(x.shape[-1])
    s = x[..., :20]
    for l in range(L):
        lo = n_triangles(l)
        w0, w1, w2 = x[..., lo:2 * lo], x[..., 2 * lo:3 * lo], x[..., 3 * lo:4 * lo]
        u, v = s + w0, s - w0
        p, q = w1 + w2, w1 - w2
        out = torch.empty(*x.shape[:-1], 4, lo, dtype=x.dtype, device=x.device)
        # children a, b, c, d (Ma 2006 §3.1 sign pattern, `spherical_haar._SIGNS`)
        torch.add(u, p, out=out[..., 0, :])
        torch.sub(u, p, out=out[..., 1, :])
        torch.add(v, q, out=out[..., 2, :])
        torch.sub(v, q, out=out[..., 3, :])
        s = out.view(*x.shape[:-1], 4 * lo)
    return s


def _round_size(m: int) -> int:
    """Smallest 20·4^l ≥ m."""
    K = 20
    while K < m:
        K *= 4
    return K


def _effective_size(*lists: SparseList) -> int:
    """Smallest 20·4^l covering every index and every dense list (the functions then live in
    level l's space)."""
    top = 1
    for idx, val in lists:
        top = max(top, val.shape[2] if idx is None else (int(idx.max()) + 1 if idx.numel() else 1))
    return _round_size(top)


def _scatter(lst: SparseList, K: int) -> Tensor:
    idx, val = lst
    if idx is None:
        return val if val.shape[-1] == K else torch.nn.functional.pad(val, (0, K - val.shape[-1]))
    B, C, m = val.shape
    return torch.zeros(B, C, K, dtype=val.dtype, device=val.device).scatter_add_(
        2, idx[:, None, :].expand(B, C, m), val)


def triple_dense(a: SparseList, b: SparseList, c: SparseList, K: int, *, K_eff: int | None = None) -> Tensor:
    """Σ C_ijk a_i b_j c_k via fine values (module docstring, "dense").

    The three lists are scattered into one (B, C_a + C_b + C_c, K') buffer in the blocked layout
    (`blocked_order`) and inverse-transformed together.

    Args:
        a, b, c: lists (idx (B, m), val (B, C, m)), C ∈ {1, 3}; K: 20·4^L.
        K_eff: evaluate at this size (every index and dense list must fit: `_effective_size`, the
            default, is the smallest that does).
    Returns:
        (B, C_out) sums, C_out = max channels.
    """
    level_of_size(K)
    B = a[1].shape[0]
    a, b, c = _check_list("a", a, B, K), _check_list("b", b, B, K), _check_list("c", c, B, K)
    Ke = _effective_size(a, b, c) if K_eff is None else K_eff
    if Ke > K or _round_size(Ke) != Ke:
        raise ValueError(f"K_eff = {Ke} must be 20·4^l ≤ K = {K}")
    Le = level_of_size(Ke)
    pos = blocked_order(Le).to(a[1].device)
    Cs = [x[1].shape[1] for x in (a, b, c)]
    dense = any(x[0] is None for x in (a, b, c))
    D = (torch.empty if dense else torch.zeros)(B, sum(Cs), Ke, dtype=a[1].dtype, device=a[1].device)
    c0 = 0
    for (idx, val), C in zip((a, b, c), Cs):
        if idx is None:  # coefficient at each position (zero-padded to K')
            D[:, c0:c0 + C] = _scatter((None, val), Ke)[..., _blocked_inverse(Le, val.device.type)]
        else:
            if dense:
                D[:, c0:c0 + C].zero_()
            D[:, c0:c0 + C].scatter_add_(2, pos[idx][:, None, :].expand(B, C, idx.shape[1]), val)
        c0 += C
    f = fine_values_blocked(D)
    fa, fb, fc = f[:, :Cs[0]], f[:, Cs[0]:Cs[0] + Cs[1]], f[:, Cs[0] + Cs[1]:]
    return (fa * fb * fc).sum(-1) * 0.25 ** Le  # A_L of the evaluation level (equal-area measure)


# -- sparse evaluator -----------------------------------------------------------------------------


@lru_cache(maxsize=8)
def _tables(L: int, device_type: str):
    """Per-coefficient tables for the sparse evaluator at level L (cached):
    anc (K, 1+3L) int64 ancestors and sgn (K, 1+3L) float32 signs (`spherical_haar.coefficient_structure`),
    sib (K, 2) int64 the other two wavelet types of the same triangle (self for scaling
    functions), m1 (K,) 1 for level-0 scaling functions else 0 (rule 1, A_0 = 1), mw (K,) A_l for
    wavelets else 0 (rules 2, 3)."""
    lvl, typ, anc, sgn = coefficient_structure(L)
    k = torch.arange(n_triangles(L))
    wav = lvl >= 0
    base = k - typ
    sib = torch.stack([torch.where(wav, base + (typ + 1) % 3, k), torch.where(wav, base + (typ + 2) % 3, k)], -1)
    m1 = (~wav).float()
    mw = torch.where(wav, 0.25 ** lvl.clamp_min(0).double(), torch.zeros((), dtype=torch.float64)).float()
    dev = torch.device(device_type)
    return anc.to(dev), sgn.float().to(dev), sib.to(dev), m1.to(dev), mw.to(dev)


def _gather(D: Tensor, idx: Tensor) -> Tensor:
    """D (B, C, K), idx (B, q) → (B, C, q)."""
    return D.gather(2, idx[:, None, :].expand(D.shape[0], D.shape[1], idx.shape[1]))


def triple_sparse(a: SparseList, b: SparseList, c: SparseList, K: int) -> Tensor:
    """Σ C_ijk a_i b_j c_k visiting only listed coefficients (module docstring, "sparse").

    Args:
        a, b, c: lists (idx (B, m), val (B, C, m)), C ∈ {1, 3}, indices in [0, K); K = 20·4^L.
            a and b are enumerated (cost ∝ (m_a + m_b)·L); c only looked up (put the longest there).
    Returns:
        (B, C_out) sums, C_out = max channels.
    """
    L = level_of_size(K)
    B = a[1].shape[0]
    a, b, c = _check_list("a", a, B, K), _check_list("b", b, B, K), _check_list("c", c, B, K)
    a, b, c = ((torch.arange(v.shape[2], device=v.device).expand(B, -1) if i is None else i, v)
               for i, v in (a, b, c))  # dense lists: every index once
    anc_t, sgn_t, sib_t, m1_t, mw_t = _tables(L, a[1].device.type)
    (ai, av), (bi, bv), (ci, cv) = a, b, c
    Ca, Cb, Cc = av.shape[1], bv.shape[1], cv.shape[1]
    dt, dev = av.dtype, av.device
    P = anc_t.shape[1]
    # dense scratch: a alone, b and c side by side (one gather serves both)
    Da = torch.zeros(B, Ca, K, dtype=dt, device=dev).scatter_add_(2, ai[:, None, :].expand(B, Ca, ai.shape[1]), av)
    Dbc = torch.zeros(B, Cb + Cc, K, dtype=dt, device=dev)
    Dbc[:, :Cb].scatter_add_(2, bi[:, None, :].expand(B, Cb, bi.shape[1]), bv)
    Dbc[:, Cb:].scatter_add_(2, ci[:, None, :].expand(B, Cc, ci.shape[1]), cv)

    # entries of a: rules 1, 2, 3 (a with b or c identical)
    ma = ai.shape[1]
    same = _gather(Dbc, ai)                                              # (B, Cb+Cc, ma)
    anc = anc_t[ai].reshape(B, ma * P)
    avg = (_gather(Dbc, anc).view(B, Cb + Cc, ma, P) * sgn_t[ai][:, None]).sum(-1)  # (B, Cb+Cc, ma)
    sib = sib_t[ai]                                                      # (B, ma, 2)
    s1, s2 = _gather(Dbc, sib[..., 0]), _gather(Dbc, sib[..., 1])
    bs, cs = same[:, :Cb], same[:, Cb:]
    r23 = bs * avg[:, Cb:] + cs * avg[:, :Cb] + s1[:, :Cb] * s2[:, Cb:] + s2[:, :Cb] * s1[:, Cb:]
    tot = (av * (m1_t[ai][:, None] * bs * cs + mw_t[ai][:, None] * r23)).sum(-1)
    # entries of b: rule 3 with c identical and a coarser
    mb = bi.shape[1]
    avga = (_gather(Da, anc_t[bi].reshape(B, mb * P)).view(B, Ca, mb, P) * sgn_t[bi][:, None]).sum(-1)
    tot = tot + (bv * _gather(Dbc[:, Cb:], bi) * avga * mw_t[bi][:, None]).sum(-1)
    return tot


# -- fine-value tables (all coefficients kept) ---------------------------------------------------------


def fine_table(method, name: str, idx: Tensor, val: Tensor, Kp: int) -> Tensor:
    """Fine values (`fine_values`, equal-area measure) of every row of a *full* stored table
    (every row's indices are 0..n−1; zero-padded to K' = 20·4^l ≥ n): (N, C·K') float32, cached on
    the identity of ``val`` (a new lighting grid or an edited BRDF table replaces the tensor).

    Fine values are linear in the coefficients, so the fine values of a blend of rows are the same
    blend of the rows' fine values (Ma 2006 §3.1: the level-L scaling basis is another basis of
    the same space): the per-point blends need no inverse transform."""
    cache = method.__dict__.setdefault("_perf_cache", {})
    key = ("fine", name)
    hit = cache.get(key)
    if hit is not None and hit[0] is val and hit[1] == Kp:
        return hit[2]
    v = val if val.ndim == 3 else val[:, None, :]
    n = v.shape[-1]
    if n != idx.shape[-1] or n > Kp:
        raise ValueError(f"{name}: table of {n} coefficients does not fit K' = {Kp}")
    if n < Kp:
        v = torch.nn.functional.pad(v, (0, Kp - n))
    tab = fine_values(v.float()).reshape(v.shape[0], -1).contiguous()
    cache[key] = (val, Kp, tab)  # holds val: no id reuse while cached
    return tab


def seed_fine_table(method, name: str, val: Tensor, fine: Tensor) -> None:
    """Set the fine-value table of a full table ``val`` (N, C, K) to fine values already at hand
    (N, C, K) in `fine_values` order — `lighting.project_env` returns the grid's fine values
    before transforming them, = ``fine_values(val)`` to float32 round-off."""
    if fine.shape != val.shape or val.ndim != 3:
        raise ValueError(f"fine values {tuple(fine.shape)} must match the table {tuple(val.shape)}")
    cache = method.__dict__.setdefault("_perf_cache", {})
    cache[("fine", name)] = (val, val.shape[-1], fine.float().reshape(val.shape[0], -1).contiguous())


def fine_bytes(method) -> int:
    """Bytes of the fine-value tables `shade_fine` keeps (reported by ``method.memory()``): the
    whole tables and their live-triangle columns (`live_table`), the ρ̃ and lighting tables' chunk-major
    copies (`rho_major`, `light_major`), the visibility table's chunk lists (`vis_chunks`) and its
    chunks packed (`vis_packed`), or those two alone once they are its only copy (`keep_packed_only`)."""
    cache = method.__dict__.get("_perf_cache", {})
    tabs = sum(v[2].element_size() * v[2].nelement() for k, v in cache.items()
               if k[0] in ("fine", "live", "major") and v[2] is not None)
    ch = cache.get(("chunks",))
    pk = cache.get(("packed", "V"))        # the visibility kept packed only (`keep_packed_only`)
    packed = 0 if pk is None else sum(t.element_size() * t.nelement() for t in (*pk[3], pk[4]))
    return tabs + packed + (0 if ch is None or ch[1] is None else sum(t.element_size() * t.nelement() for t in ch[1]))


# -- live triangles: the fine triangles eq. 7 does not multiply by an exact zero -----------------------
#
# In the fine-value sum Σ_t V̂(t) ρ̂_c(t) L̂_c(t) a triangle t where every visibility row is exactly 0
# (below every vertex's horizon: `precompute.visibility_coeffs` counts those directions as blocked) or
# every ρ̃ row is (max(0, cos θi) = 0 over the whole triangle, `brdf_table`) adds 0·finite = ±0 to
# every point's sum, whatever the lighting: half of the local sphere (bench chess 640 of 1280, creature
# 656). Those triangles' lighting needs no projection (`lighting.project_env` with ``tris``: the
# samples of the live triangles only), and the sums run over the live columns of the three tables
# (`live_table`): the same terms, in another association (float32 round-off; a lighting projected
# lazily on the live triangles and one projected whole give the same image bit for bit, tested).


def live_triangles(method, Kp: int | None = None) -> Tensor | None:
    """(n',) int64 sorted fine triangles where some visibility row and some ρ̃ row are non-zero
    (comment above), of the full fine-value tables at K' = ``Kp`` (default K); None when every
    triangle is live, no fine path applies (`fine_ok`), K' < K (top-truncated tables) or an SBRDF
    blend is set. Cached on the identities of the stored tables; builds the tables' live columns
    (`live_table`) and drops their whole fine-value tables (only the live columns are read)."""
    Kp = method.K if Kp is None else int(Kp)
    if Kp != method.K or getattr(method, "blends", None) or not fine_ok(method):
        return None
    bi, bv = _brdf_stack(method)
    cache = method.__dict__.setdefault("_perf_cache", {})
    hit = cache.get(("live_tris",))
    if hit is not None and hit[0] is method.V_val and hit[1] is bv:
        return hit[2]
    Vt = fine_table(method, "V", method.V_idx, method.V_val, Kp)       # (N_V, K)
    Rt = fine_table(method, "rho", bi, bv, Kp)                          # (N_ρ, 3K)
    live_v = (Vt != 0).any(0)
    live_r = (Rt.view(Rt.shape[0], 3, Kp) != 0).any(0).any(0)
    live = torch.nonzero(live_v & live_r, as_tuple=False).squeeze(-1)
    if live.numel() in (0, Kp):
        live = None
    cache[("live_tris",)] = (method.V_val, bv, live)
    cache.pop(("packed", "V"), None)                                      # of the live triangles before
    if live is not None:
        cache[("live", "V")] = (method.V_val, live, Vt[:, live].contiguous())
        cache[("live", "rho")] = (bv, live, Rt.view(-1, 3, Kp)[:, :, live].reshape(Rt.shape[0], -1).contiguous())
        cache.pop(("fine", "V"), None)                                    # read through the live columns
        cache.pop(("fine", "rho"), None)
    return live


def live_table(method, name: str, val: Tensor, live: Tensor) -> Tensor:
    """The live columns (`live_triangles`) of the fine-value table ``name`` ("V": (N_V, n'), "rho":
    (N_ρ, 3n'), "L": (F, 3n')) of the stored table ``val``. "L": the lighting grid's — of a lazily
    set grid the table `TripleProduct.fill_lighting` fills (``live`` given there), else the live
    columns of the whole grid's fine values (completed first)."""
    cache = method.__dict__.setdefault("_perf_cache", {})
    hit = cache.get(("live", name))
    if hit is not None and hit[0] is val and hit[1] is live:
        return hit[2]
    pk = packed_only(method, val, live) if name == "V" else None
    if pk is not None:   # kept only as its packed chunks (`VIS_PACKED_ONLY`): unpacked for this reader
        return unpacked(pk)
    if name != "L":
        raise RuntimeError(f"live table {name!r} not built for this table (call live_triangles first)")
    method.fill_lighting()
    full = fine_table(method, "L", method.L_idx, method.L_val, method.K)
    tab = full.view(full.shape[0], 3, -1)[:, :, live].reshape(full.shape[0], -1).contiguous()
    cache[("live", "L")] = (method.L_val, live, tab)
    return tab


def fine_ok(method, mix: Tensor | None = None) -> bool:
    """`shade_fine` applies: every table the frame blends is full (all coefficients or "top") and
    the lighting comes from the grid (not ``light_lookup="exact"``)."""
    if method.config["light_lookup"] == "exact" or method.L_idx is None:
        return False
    bi, _ = _brdf_stack(method)
    ok = _is_full(method, "V", method.V_idx) and _is_full(method, "rho", bi) and _is_full(method, "L", method.L_idx)
    if ok and mix is not None and getattr(method, "blends", None):
        ok = _is_full(method, "rho_b", _brdf_stack(method, "b")[0])
    return ok


def _merge_psi(rows: Tensor, w: Tensor, n_psi: int) -> tuple[Tensor, Tensor]:
    """Trilinear grid look-ups with one tangent angle (n_psi = 1) name each of their 4 (θ, φ) rows
    twice (dk = 0, 1, adjacent in `lighting.lookup_weights`): merge them (4 rows, weights summed)."""
    if n_psi != 1 or rows.shape[1] != 8:
        return rows, w
    return rows[:, 0::2], w[:, 0::2] + w[:, 1::2]


def shade_fine(method, R: Tensor | None, wo_world: Tensor, region: Tensor, vrows: Tensor, vw: Tensor,
               mix: Tensor | None = None, *, points: int | None = None, grouped: bool | None = None,
               lookups: tuple | None = None) -> Tensor:
    """Eq. 7 for B points → (B, 3) when every table is full (`fine_ok`): the fine-value identity
    (module docstring, "dense") with the blends done on fine-value tables (`fine_table`):

        B_c = A_L' Σ_t V̂(t) ρ̂_c(t) L̂_c(t),  V̂ = Σ_v w_v V̂_v,  ρ̂ = Σ_o w_o ρ̂_o,  L̂ = Σ_r w_r L̂_r

    The blends and the sum over t run in one compiled loop per point and channel (`fine_kernel`),
    or — when the points share their rows (pixel shading: ≈ 11 G-buffer samples per distinct
    (visibility row, L rows, ρ̃ rows), `grouping_pays`) — the trilinear form of the same sum
    (`fine_grouped`). ``grouped``: force one of the two (None: `grouping_pays`).
    Same arguments as `shade`; ``lookups`` as `shading_rows`.
    A lazily set lighting grid (`TripleProduct._set_lighting`): only the grid frames the points
    look up with a non-zero weight are projected (`TripleProduct.fill_lighting`; a weight-0 row is
    read as 0·finite, and an unprojected row is 0: the same sums).
    The sums run over the live triangles only (`live_triangles`: where no table row is exactly 0
    throughout), and a lazily set lighting is projected on those only."""
    live = live_triangles(method)
    vis_bits(method, live)                    # built in the first frame (a later lighting change reads them)
    if getattr(method, "_lazy_light", None) is not None and method.config["light_lookup"] != "exact":
        if lookups is None:
            lookups = grid_lookups(R, wo_world, method.outgoing, method.grid, method.config["light_lookup"])
        need = read_pairs(method, live, vrows, vw, lookups[2], lookups[3])
        # the looked-up frames (a boolean gather of every look-up: ~5 ms of a pixel frame) only without the pairs
        method.fill_lighting(None if need is not None else lookups[2][lookups[3] != 0], live=live, need=need)
    spec = shading_rows(method, R, wo_world, region, vrows, vw, mix, lookups=lookups)
    (vp,), rps, (lp,) = spec
    Kp = max(_round_size(p[1].shape[-1]) for p in (vp, *rps, lp))
    Le = level_of_size(Kp)
    lrows, lw = _merge_psi(lp[3], lp[4], method.grid.n_psi)
    read, pk = None, None
    if live is not None and Kp == method.K and len(rps) == 1:   # the live columns only (comment above)
        # the rows this call read, for `frame_cost` (references, no copy; counted after the frame)
        reads = method.stats.get("frame_reads")
        if reads is not None:
            read = {"vrows": vp[3], "vw": vp[4], "lrows": lrows, "lw": lw}
            reads.append(read)
        pk = packed_only(method, vp[2], live)     # the table kept only as its packed chunks (`VIS_PACKED_ONLY`)
        if pk is not None and not native.available():   # the native loops switched off since: the compiled
            pk, Vt = None, unpacked(pk)                  # kernels read the rows, unpacked for this call
        else:
            Vt = live_table(method, "V", vp[2], live) if pk is None else None  # (N_V, n')
        Lt = live_table(method, "L", lp[2], live)                        # (F, 3n')
        Rt = live_table(method, "rho", rps[0][2], live)                  # (R·n_o, 3n')
        brows, bw = rps[0][3], rps[0][4]
    elif len(rps) == 1:
        Vt = fine_table(method, "V", vp[1], vp[2], Kp)                   # (N_V, K')
        Lt = fine_table(method, "L", lp[1], lp[2], Kp)                   # (F, 3K')
        Rt = fine_table(method, "rho", rps[0][1], rps[0][2], Kp)          # (R·n_o, 3K')
        brows, bw = rps[0][3], rps[0][4]
    else:  # SBRDF: the two stacks side by side, rows of "b" offset (Ma 2006 §5, linear in ρ̃)
        Vt = fine_table(method, "V", vp[1], vp[2], Kp)                   # (N_V, K')
        Lt = fine_table(method, "L", lp[1], lp[2], Kp)                   # (F, 3K')
        Ra = fine_table(method, "rho", rps[0][1], rps[0][2], Kp)
        Rb = fine_table(method, "rho_b", rps[1][1], rps[1][2], Kp)
        cache = method.__dict__["_perf_cache"]
        hit = cache.get(("fine", "rho_ab"))
        if hit is None or hit[0] is not Ra or hit[1] is not Rb:
            hit = cache[("fine", "rho_ab")] = (Ra, Rb, torch.cat([Ra, Rb]))
        Rt = hit[2]
        brows = torch.cat([rps[0][3], rps[1][3] + Ra.shape[0]], 1)
        bw = torch.cat([rps[0][4], rps[1][4]], 1)
    # A_L' of the evaluation level (equal-area measure)
    if grouped is None:
        grouped = grouping_pays(vp[3], lrows, brows)
    if pk is not None:
        ch = pk[3] if points is None else None
        if grouped or points is not None or not _native_points(vp[3], brows, lrows):
            Vt = unpacked(pk)          # a reader of whole rows: the table unpacked for this call (not kept)
    else:
        ch = vis_chunks(method, Vt, (vp[2], live)) if points is None else None
    if grouped:  # the frame's group count goes to `frame_cost` (``method.stats["frame_groups"]``)
        st = {}
        out = fine_grouped(Vt, Rt, Lt, vp[3], vp[4], brows, bw, lrows, lw, points=points, stats=st, chunks=ch)
        method.stats["frame_groups"] = method.stats.get("frame_groups", 0) + st["groups"]
        if read is not None:
            read["group_vis"] = st["group_vis"]
        return out.mul_(0.25 ** Le)
    per_vertex = ch is not None and vp[3].shape[1] == 1
    if pk is not None and Vt is None:   # the packed chunks are the only copy: the native loop streams them
        rm, lm = rho_major(method, Rt), light_major(method, Lt)
        return native.points(None, Rt if rm is None else rm, Lt if lm is None else lm, vp[3][:, 0], vp[4][:, 0],
                             brows, bw, lrows, lw, ch, r_major=rm is not None, l_major=lm is not None,
                             v_packed=pk[4], v_shape=pk[2]).mul_(0.25 ** Le)
    packed = vis_packed(method, Vt, ch) if per_vertex else None
    out = fine_kernel(Vt, Rt, Lt, vp[3], vp[4], brows, bw, lrows, lw, points=points, chunks=ch,
                      rho_major=rho_major(method, Rt) if per_vertex else None,
                      light_major=light_major(method, Lt) if per_vertex else None,
                      vis_packed=packed).mul_(0.25 ** Le)
    if packed is not None and VIS_PACKED_ONLY and live is not None and Vt.shape[1] % native.W == 0 \
            and points is None and _native_points(vp[3], brows, lrows):
        keep_packed_only(method, vp[2], live, Vt, ch, packed)   # the loop read the packed chunks: drop the rows
    return out


def _native_points(vrows: Tensor, brows: Tensor, lrows: Tensor) -> bool:
    """`fine_kernel` runs the native per-point loop on these rows (with its chunk lists and no ``points``):
    one visibility row, 4 ρ̃ and 4 grid rows per point."""
    return vrows.shape[1] == 1 and brows.shape[1] == 4 and lrows.shape[1] == 4


def read_pairs(method, live: Tensor | None, vrows: Tensor, vw: Tensor, lrows: Tensor, lw: Tensor):
    """(F, n') bool — as `native_light.NeedBits` (its bit table) when ``NEED_BITS`` — : the (grid frame,
    live triangle) pairs that points with visibility rows / weights
    (vrows, vw) and grid look-ups (lrows, lw) read with a non-zero weight and a non-zero visibility
    (`native_light.need`; what `frame_cost` counts as a re-projection's compulsory pairs,
    `nonzero_reads`) — the pairs a lazily set lighting projects (`TripleProduct.fill_lighting`); None
    (whole live rows) when the lighting is not pending, no live triangles apply or the pair
    projection does not (`lighting.pairs_ok`, `lighting.comb_pairs_ok`). The visibility table's bit sets are built once per
    table (`native_light.vis_bits`)."""
    lazy = getattr(method, "_lazy_light", None)
    if live is None or lazy is None or not (lt.pairs_ok(lazy["env"]) or lt.comb_pairs_ok(lazy["env"], method.grid)):
        return None
    return native_light.need(vis_bits(method, live), vrows, vw, lrows, lw, method.grid.size, live.numel(),
                             as_bits=NEED_BITS)


# `read_pairs` hands `TripleProduct.fill_lighting` the read pairs as `native_light.need`'s bit table
# (`native_light.NeedBits`: `native_light.take` visits its set bits) instead of an (F, n') bool array
# written and scanned twice (the same pairs). False: the bool array (the test oracle).
NEED_BITS = True


def vis_bits(method, live: Tensor | None) -> Tensor | None:
    """`native_light.vis_bits` of the live visibility table (cached on its identity; built in the
    first frame — the harness's warm-up — by `shade_fine`), or None: no live triangles or no native
    pair projection."""
    if live is None or not native_light.available():
        return None
    pk = packed_only(method, method.V_val, live)
    if pk is not None and pk[5] is not None:
        return pk[5]
    Vt = live_table(method, "V", method.V_val, live)
    cache = method.__dict__.setdefault("_perf_cache", {})
    if pk is not None:   # kept packed only, without its bit sets: made once from the rows unpacked
        cache[("packed", "V")] = (*pk[:5], native_light.vis_bits(Vt))
        return cache[("packed", "V")][5]
    hit = cache.get(("vis_bits",))
    if hit is None or hit[0] is not Vt:
        hit = cache[("vis_bits",)] = (Vt, native_light.vis_bits(Vt))       # holds Vt: no id reuse
    return hit[1]


def vis_chunks(method, Vt: Tensor, source: tuple | None = None) -> tuple[Tensor, Tensor, Tensor] | None:
    """The chunk lists (`native.chunks`) of the visibility fine-value table ``Vt`` the frame reads,
    built once per table (at the first frame: the warm-up frame) and cached on its identity; None
    when the native loops are not available (`native.available`). ``source``: (stored visibility
    values, live triangles or None) ``Vt`` was made from — a table rebuilt from the same values and
    the same live triangles (`live_triangles` after a material edit that left them live) keeps its
    lists (the same columns: the same zeros)."""
    if not native.available() or Vt.dtype != torch.float32 or Vt.device.type != "cpu":
        return None
    cache = method.__dict__.setdefault("_perf_cache", {})
    hit = cache.get(("chunks",))
    if hit is not None and hit[0] is not Vt and source is not None and hit[2] is not None \
            and hit[2][0] is source[0] and hit[0].shape == Vt.shape \
            and ((hit[2][1] is None and source[1] is None) or
                 (hit[2][1] is not None and source[1] is not None and torch.equal(hit[2][1], source[1]))):
        hit = cache[("chunks",)] = (Vt, hit[1], source)
    if hit is None or hit[0] is not Vt:
        # holds Vt and its source: no id reuse while cached
        hit = cache[("chunks",)] = (Vt, native.chunks(Vt), source)
    return hit[1]


# Per-vertex frames read the ρ̃ fine-value table chunk-major (`native.chunk_major`, made once per table
# and cached like the chunk lists; `native.points` with ``r_major``): the same sums bit for bit, the
# loop 1.06-1.08x (creature / chess bench vertex, cache cooled, 1 thread). The lighting table too once
# its lighting is complete (`light_major`): a lighting change writes its live table in place while it
# is pending, so frames of a new lighting read it row-major; a frame with a complete one (a view
# sequence's: the copy made in the warm-up frame, ~2 ms) reads the copy — the loop 1.09-1.12x with
# both. False: the row-major tables (the test oracle).
RHO_CHUNK_MAJOR = True
LIGHT_CHUNK_MAJOR = True
# ... and the visibility rows' chunks packed (`native.packed_chunks`: a point streams its chunks without
# the zero gaps between them; the same bits, the loop with both tables chunk-major 1.2-1.3x faster
# again, for a copy of the chunks: creature bench 21 MB, chess 20, made once per table). False: the
# visibility rows (the test oracle).
VIS_PACKED = True


def vis_packed(method, Vt: Tensor, ch) -> Tensor | None:
    """`native.packed_chunks` of the visibility fine-value table ``Vt`` and its chunk lists ``ch``
    (`vis_chunks`), cached on both identities (built in the first frame: the harness's warm-up), or
    None (`VIS_PACKED` off, no chunk lists or native loops)."""
    if not VIS_PACKED or ch is None:
        return None
    cache = method.__dict__.setdefault("_perf_cache", {})
    hit = cache.get(("major", "V"))
    if hit is None or hit[0] is not Vt or hit[1] is not ch:
        hit = cache[("major", "V")] = (Vt, ch, native.packed_chunks(Vt, ch))     # holds both: no id reuse
    return hit[2]


# ... and, once a per-vertex frame has streamed them, the packed chunks are the only copy of the live
# visibility table kept (`keep_packed_only`, session 36): its row table (creature bench 35 MB, chess 27)
# and the caches that held it (chunk lists, bit sets: kept, re-keyed on the stored values and the live
# triangles) are dropped, so the visibility costs its packed chunks and lists (21.5 + 2.8 MB creature)
# instead of rows + packed. A reader of whole rows (a pixel-style call on a per-vertex instance, the
# compiled fallback, `frame_cost`'s zero counts: none in a per-vertex frame) gets the rows unpacked
# (`unpacked`: `native.unpack_chunks`, for that call only); a material edit that rebuilds the live
# triangles rebuilds the rows (`live_triangles`) until the next per-vertex frame packs them again.
# False: the rows stay beside the packed chunks (the test oracle).
VIS_PACKED_ONLY = True


def packed_only(method, val: Tensor, live: Tensor | None):
    """The packed-only entry (`keep_packed_only`) of the live visibility table of the stored values
    ``val`` and live triangles ``live`` — (val, live, (N, n'), chunk lists, packed chunks, bit sets or
    None) — or None (the rows are kept, or another table's entry)."""
    hit = method.__dict__.get("_perf_cache", {}).get(("packed", "V"))
    if hit is None or live is None or hit[0] is not val or hit[1] is not live:
        return None
    return hit


def keep_packed_only(method, val: Tensor, live: Tensor, Vt: Tensor, ch, packed: Tensor) -> None:
    """Make the packed chunks ``packed`` (`vis_packed` of the live visibility table ``Vt`` of ``val`` and
    ``live``, chunk lists ``ch``) its only copy: the row table and the caches keyed on it (``Vt``'s chunk
    lists, packed chunks, bit sets) give way to one entry keyed on (``val``, ``live``) holding the
    lists, the packed chunks and the bit sets (`packed_only`)."""
    cache = method.__dict__.setdefault("_perf_cache", {})
    bits = cache.get(("vis_bits",))
    cache[("packed", "V")] = (val, live, (int(Vt.shape[0]), int(Vt.shape[1])), ch, packed,
                              bits[1] if bits is not None and bits[0] is Vt else None)
    for k in (("live", "V"), ("chunks",), ("major", "V"), ("vis_bits",)):
        cache.pop(k, None)


def unpacked(pk) -> Tensor:
    """The live visibility rows of a packed-only entry (`packed_only`), unpacked (`native.unpack_chunks`;
    = the rows it was packed from, ±0 aside) for one reader (not kept)."""
    return native.unpack_chunks(pk[4], pk[3], pk[2])


def light_major(method, Lt: Tensor) -> Tensor | None:
    """`native.chunk_major` of the live lighting table ``Lt`` the frame reads when its lighting is
    complete (no lazy grid pending: `TripleProduct.fill_lighting` writes ``Lt`` in place only while one
    is), cached on the identity of ``Lt`` (a new lighting gets new table objects) and dropped while a
    lighting is pending; else None (also `LIGHT_CHUNK_MAJOR` off, no native loops, a row length not a
    multiple of `native.W`)."""
    cache = method.__dict__.setdefault("_perf_cache", {})
    if not LIGHT_CHUNK_MAJOR or getattr(method, "_lazy_light", None) is not None:
        cache.pop(("major", "L"), None)
        return None
    hit = cache.get(("major", "L"))
    if hit is None or hit[0] is not Lt:
        hit = cache[("major", "L")] = (Lt, None, native.chunk_major(Lt))      # holds Lt: no id reuse
    return hit[2]


def rho_major(method, Rt: Tensor) -> Tensor | None:
    """`native.chunk_major` of the ρ̃ fine-value table ``Rt`` the frame reads (cached on its identity,
    built in the first frame: the harness's warm-up), or None (`RHO_CHUNK_MAJOR` off, no native loops,
    a row length not a multiple of `native.W`)."""
    if not RHO_CHUNK_MAJOR:
        return None
    cache = method.__dict__.setdefault("_perf_cache", {})
    hit = cache.get(("major", "rho"))
    if hit is None or hit[0] is not Rt:
        hit = cache[("major", "rho")] = (Rt, None, native.chunk_major(Rt))      # holds Rt: no id reuse
    return hit[2]


def _blend_rows(table: Tensor, rows: Tensor, w: Tensor) -> Tensor:
    """Σ_r w[:, r] table[rows[:, r]] with the k terms unrolled (k is static when traced):
    table (N, ...), rows/w (b, k) → (b, ...). (2k − 1) flops per output element."""
    shape = (-1,) + (1,) * (table.dim() - 1)
    acc = w[:, 0].reshape(shape) * table[rows[:, 0]]
    for r in range(1, rows.shape[1]):
        acc = acc + w[:, r].reshape(shape) * table[rows[:, r]]
    return acc


def fine_block(vrows: Tensor, vw: Tensor, brows: Tensor, bw: Tensor, lrows: Tensor, lw: Tensor,
               Vt: Tensor, Rt: Tensor, Lt: Tensor) -> Tensor:
    """Σ_t V̂(t) ρ̂_c(t) L̂_c(t) of a block of b points (Ma 2006 eq. 7 by the fine-value identity,
    module docstring "fine"; no A_L' factor): V̂ = Σ_v w_v Vt[v], ρ̂ = Σ_o w_o Rt[o], L̂ = Σ_r w_r Lt[r].

    Args: rows (b, k) int64 and weights (b, k) per table (k static); Vt (N_V, K'),
        Rt (N_ρ, 3, K'), Lt (N_L, 3, K') fine-value tables. Returns (b, 3).
    Written as one expression so that `methods.core.fused` compiles it into a single loop per
    (point, channel) over the K' fine triangles — the blends are never stored (the eager form
    makes 7 K'-long passes per point through memory)."""
    V = _blend_rows(Vt, vrows, vw)                                       # (b, K')
    # one reduction per channel: Inductor then emits one loop over t per (point, channel) with
    # every gather inline (a (b, 3, K') product is otherwise stored between two passes)
    return torch.stack([(V * _blend_rows(Rt[:, c], brows, bw) * _blend_rows(Lt[:, c], lrows, lw)).sum(-1)
                        for c in range(3)], -1)


_fine_block = fused(fine_block, options=KERNEL_OPTIONS)
# Points per compiled block of `fine_kernel` when it is given ``points`` (tests): blocks of ``points``,
# the remainder in blocks of at most FINE_TAIL (`methods.core.fused.map_rows`: one static shape each).
FINE_TAIL = 1024


def _fine_tables(Vt: Tensor, Rt: Tensor, Lt: Tensor) -> tuple[int, torch.dtype, Tensor, Tensor]:
    """K', dtype and the (N, 3, K') channel views of the ρ̃ and L fine-value tables of `fine_kernel` /
    `fine_grouped` (checked); the table row counts vary by scene / grid / regions, so they are
    marked dynamic (one compiled variant)."""
    Kp = Vt.shape[1]
    if Rt.shape[1] != 3 * Kp or Lt.shape[1] != 3 * Kp:
        raise ValueError(f"tables must be (N, K'), (N, 3K'), (N, 3K'), got {tuple(Vt.shape)}, {tuple(Rt.shape)}, {tuple(Lt.shape)}")
    R3, L3 = Rt.view(-1, 3, Kp), Lt.view(-1, 3, Kp)
    for t in (Vt, R3, L3):
        torch._dynamo.maybe_mark_dynamic(t, 0)
    return Kp, Vt.dtype, R3, L3


def fine_kernel(Vt: Tensor, Rt: Tensor, Lt: Tensor, vrows: Tensor, vw: Tensor, brows: Tensor, bw: Tensor,
                lrows: Tensor, lw: Tensor, *, points: int | None = None, chunks: tuple | None = None,
                rho_major: Tensor | None = None, light_major: Tensor | None = None,
                vis_packed: Tensor | None = None) -> Tensor:
    """Σ_t V̂(t) ρ̂_c(t) L̂_c(t) for B points from fine-value tables (`shade_fine` without the A_L'
    factor): Vt (N_V, K'), Rt (N_ρ, 3K'), Lt (N_L, 3K'); rows/weights (B, k) per table. → (B, 3).
    `fine_block` compiled (`methods.core.fused`) in one call over all B points (a symbolic count),
    or over static blocks of ``points`` when given (tests). It ran over static blocks of
    8192 / `FINE_TAIL` points (chess bench per-vertex V, 10701 vertices: one block of 8192 and
    three of 1024, the last padded, then concatenated): 6.0 -> 3.9-4.1 ms per frame, 1 thread,
    the same sums bit for bit (per-stage timers, loaded machine).
    ``chunks`` (`vis_chunks` of Vt), one visibility row per point and 4 ρ̃ and 4 grid rows (per-vertex
    frames): the native loop over each row's non-zero chunks (`native.points`), to float32 round-off.
    The points stay in their order (vertex order: the visibility rows, the most bytes, stream; taken
    in the order of their (ρ̃, grid) rows the loop was 1.1x slower, chess bench vertex V, 1 thread).
    ``rho_major`` / ``light_major``: `native.chunk_major` of Rt / Lt (`rho_major`, `light_major`), which
    that loop then reads instead, ``vis_packed`` the visibility chunks packed (`vis_packed`; the same
    bits)."""
    if chunks is not None and points is None and vrows.shape[1] == 1 and brows.shape[1] == 4 \
            and lrows.shape[1] == 4 and Vt.dtype == torch.float32:
        return native.points(Vt, Rt if rho_major is None else rho_major, Lt if light_major is None else light_major,
                             vrows[:, 0], vw[:, 0], brows, bw, lrows, lw, chunks,
                             r_major=rho_major is not None, l_major=light_major is not None,
                             v_packed=vis_packed if vis_packed is not None and Vt.shape[1] % native.W == 0 else None)
    Kp, dt, R3, L3 = _fine_tables(Vt, Rt, Lt)
    rows = (vrows.long(), vw.to(dt), brows.long(), bw.to(dt), lrows.long(), lw.to(dt))
    if points is None:
        # one call with a symbolic point count (`methods.core.fused.call_rows`; the loop is
        # compute-bound): no padded tail blocks, no per-block call overhead, no concatenation
        return call_rows(_fine_block, rows, (Vt, R3, L3))
    p = int(points)
    head = rows[0].shape[0] // p * p if rows[0].shape[0] > p else 0
    tail = min(p, FINE_TAIL)  # the rest in small blocks: padding ≤ FINE_TAIL − 1 points
    # both block sizes compiled in the warm-up frame (``core.fused.warm_blocks``): a later frame may
    # need the one the first did not
    parts = [map_rows(_fine_block, [r[:head] for r in rows], (Vt, R3, L3), chunk=p, warm=(tail,))] if head else []
    if head < rows[0].shape[0] or not head:
        parts.append(map_rows(_fine_block, [r[head:] for r in rows], (Vt, R3, L3), chunk=tail, warm=(p,)))
    return parts[0] if len(parts) == 1 else torch.cat(parts)


# -- grouped evaluation: once per distinct (visibility row, L look-up, ρ̃ look-up) ----------------------
#
# Eq. 7 is trilinear, so with V̂ = Σ_i w_i V̂_i, L̂ = Σ_j w_j L̂_j, ρ̂ = Σ_k w_k ρ̂_k
#
#     B_c = Σ_i w_i Σ_j w_j Σ_k w_k T_c[v_i, l_j, b_k],    T_c[v, l, b] = Σ_t V̂_v(t) L̂_{l,c}(t) ρ̂_{b,c}(t)
#
# A grid look-up's rows are a function of its first row (the trilinear cell of `lighting.lookup_weights`,
# the bilinear cell of `brdf_table.outgoing_weights`, offset by the region / SBRDF stack), so every
# G-buffer sample touching visibility row v with the same two cells needs the same k_L·k_ρ·3 values
# T_c[v, ·, ·]: a *group* (v, l_0, b_0). Pixel frames of the bench have ≈ 0.07–0.09 groups per sample
# (chess, creature: 4 spp, neighbouring samples share triangle and cells), so the K'-long sums are done
# once per group (`group_block`: per t, 1 + 2·3·4 loads for 3·(4 + 2·16) flops, against 27 loads and
# 72 flops per t for every sample in `fine_block`), and each sample blends its 3·16·3 values.


def grouping_pays(vrows: Tensor, lrows: Tensor, brows: Tensor) -> bool:
    """The grouped form does less work than the per-point one: the points are G-buffer samples (more
    than one visibility row each) and there are enough of them to share cells (a per-vertex frame
    has one visibility row per point: nothing to share)."""
    return vrows.shape[1] > 1 and vrows.shape[0] >= GROUP_MIN_POINTS and lrows.shape[1] * brows.shape[1] <= 64


# Cells per frame up to which `group_rows` renumbers the (L cell, ρ̃ cell) pairs densely (a table of
# that many int32 counters): the keys then fit int32 (bench chess: 2187 distinct of 209 k cells), whose
# sort runs ~1.6x faster than int64's.
GROUP_CELL_TABLE = 1 << 22


def group_rows(vrows: Tensor, lrows: Tensor, brows: Tensor, *, n_l: int | None = None,
               n_b: int | None = None) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The distinct groups (v, L cell, ρ̃ cell) of B points and each point's group per visibility row.

    Args: vrows (B, k_v), lrows (B, k_L), brows (B, k_ρ) int64 table rows (a look-up's rows are a
        function of its first one, module comment above); n_l, n_b: bounds of lrows[:, 0] and
        brows[:, 0] (the L and ρ̃ table row counts; default: their maxima + 1, two more passes).
    Returns: gv (G,), gl (G, k_L), gb (G, k_ρ) int64 rows of every group (sorted by v, then cells)
        and inv (B, k_v) int64 group of every (point, visibility row).

    `group_runs` with its per-run groups expanded to the points (``inv = inv_s[run]``): the frames'
    path (`fine_grouped`) reads the (S, k_v) groups of the runs through each point's run instead."""
    gv, gl, gb, inv_s, run = group_runs(vrows, lrows, brows, n_l=n_l, n_b=n_b)
    return gv, gl, gb, inv_s.index_select(0, run.long())


def group_runs(vrows: Tensor, lrows: Tensor, brows: Tensor, *, n_l: int | None = None,
               n_b: int | None = None, native_ok: bool = True) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """`group_rows` with the groups given per run of points: (gv, gl, gb, inv_s (S, k_v) int64 the
    groups of every run, run (B,) int32 the run of every point); ``inv_s[run]`` is `group_rows`' inv.

    The keys are deduplicated in two steps, same result as one `torch.unique` of all B·k_v keys:
    runs of neighbouring points with the same visibility rows and both cells (G-buffer samples of
    one triangle — the S² sub-samples of a pixel are adjacent — mostly share both cells), found
    with one pass over the (B, k_v) rows; then `torch.unique` of the k_v keys of the run starts
    only, every point taking its run's groups. Chess bench V (262k points, 3 rows each, 1 thread,
    same process): 45 → ~20 ms per frame for runs per visibility column (the full sort was 33 ms
    of it), then 37-42 → 26-27 ms for runs of whole points (B instead of B·k_v flags, run indices
    and inverse gathers; the same groups, order and inverse). Then the gathers by `index_select`
    (eager advanced indexing of a (B, 3) int64 array by a (B,) index: 4.2 ms, `index_select` 0.85)
    and the run starts' cells renumbered in order (`GROUP_CELL_TABLE`) so that the keys sorted are
    int32 when they fit: the same groups, order and inverse (tests/methods/triple_product).
    The points' (B, k_v) int64 groups are no longer formed (a 6 MB gather written here and read back
    by the blend on a bench frame: the blend gathers through the int32 run index instead), the cell
    codes come from contiguous columns, the row changes are or-ed column by column and the run index
    is an int32 scan: the same groups, order and inverse.
    ``native_ok`` (default): the C loop of `native_group` when it applies (int64 CPU rows; its oracle
    is this torch path, ``native_ok=False``): the same groups, order, inverse and runs; chess pixel V
    frame, 1 thread, same process: see `native_group`."""
    B, kv = vrows.shape
    dev = vrows.device
    if B == 0:
        e = vrows.new_zeros(0)
        return e, lrows[:0], brows[:0], vrows.new_zeros(0, kv), torch.zeros(0, dtype=torch.int32, device=dev)
    nb = int(brows[:, 0].max()) + 1 if n_b is None else int(n_b)
    if native_ok and dev.type == "cpu" and vrows.dtype == lrows.dtype == brows.dtype == torch.int64:
        out = native_group.group_runs(vrows, lrows, brows, nb)
        if out is not None:
            return out
    nl = int(lrows[:, 0].max()) + 1 if n_l is None else int(n_l)
    # (B,) cell codes lrows0·nb + brows0 from contiguous copies of the two columns (integer ops on
    # the strided columns ran unvectorised: 1.5-2.1 ms against ~1.0 on a bench frame)
    cell = lrows[:, 0].contiguous().mul_(nb).add_(brows[:, 0].contiguous())
    new = torch.ones(B, dtype=torch.bool, device=dev)                     # run starts
    torch.ne(cell[1:], cell[:-1], out=new[1:])
    ne = vrows[1:] != vrows[:-1]                                          # (B − 1, k_v)
    for i in range(kv):                                                   # or of the columns: `any(1)` 3x slower
        new[1:] |= ne[:, i]
    start = torch.nonzero(new, as_tuple=False).squeeze(-1)               # (S,)
    run = torch.cumsum(new, 0, dtype=torch.int32).sub_(1)                 # (B,) run of every point
    cs = cell.index_select(0, start)                                      # (S,) cells of the runs
    vs = vrows.index_select(0, start)                                     # (S, k_v)
    nc = nl * nb                                                          # cell codes
    if nc <= GROUP_CELL_TABLE:                                            # renumber the cells seen, in order
        seen = torch.zeros(nc, dtype=torch.int32, device=dev)
        seen[cs] = 1
        code = torch.cumsum(seen, 0, dtype=torch.int32).sub_(1)
        nc = int(code[-1]) + 1
        cs = code.index_select(0, cs)
    wide = (int(vs.max()) + 1) * nc >= 2 ** 31
    key = vs.to(torch.int64 if wide else torch.int32).mul_(nc).add_(cs[:, None])  # (S, k_v)
    uk, inv_s = torch.unique(key.view(-1), return_inverse=True)
    G = uk.numel()
    # a member point of every group (whichever write lands: all members have the group's rows)
    rep = torch.empty(G, dtype=torch.int64, device=dev)
    rep[inv_s] = start.repeat_interleave(kv) if kv > 1 else start
    return (uk // nc).long(), lrows.index_select(0, rep), brows.index_select(0, rep), inv_s.view(-1, kv), run


def group_block(gv: Tensor, gl: Tensor, gb: Tensor, Vt: Tensor, Rt: Tensor, Lt: Tensor) -> Tensor:
    """T_c[v, l_j, b_k] = Σ_t V̂_v(t) L̂_{l_j,c}(t) ρ̂_{b_k,c}(t) of a block of g groups (module
    comment above; no A_L' factor): gv (g,), gl (g, k_L), gb (g, k_ρ) rows; Vt (N_V, K'),
    Rt (N_ρ, 3, K'), Lt (N_L, 3, K') fine-value tables. Returns (g, 3·k_L·k_ρ), index (c, j, k).
    One expression of 3·k_L·k_ρ sums over t: Inductor emits one loop over t per group, every row
    loaded once per t (the products V̂·L̂_j formed once and reused for the k_ρ rows)."""
    V = Vt[gv]                                                           # (g, K')
    out = []
    for c in range(3):
        Rc = [Rt[gb[:, k], c] for k in range(gb.shape[1])]
        for j in range(gl.shape[1]):
            u = V * Lt[gl[:, j], c]
            out += [(u * r).sum(-1) for r in Rc]
    return torch.stack(out, -1)


def group_blend(inv: Tensor, vw: Tensor, lw: Tensor, bw: Tensor, T: Tensor) -> Tensor:
    """Σ_i vw_i Σ_j lw_j Σ_k bw_k T[inv_i, c, j, k] of a block of b points → (b, 3): inv (b, k_v)
    groups, vw (b, k_v), lw (b, k_L), bw (b, k_ρ) weights, T (G, 3·k_L·k_ρ). The small sums are
    unrolled (a reduction over them would be split across threads by Inductor)."""
    kl, kb = lw.shape[1], bw.shape[1]
    out = []
    for c in range(3):
        acc = None
        for i in range(inv.shape[1]):
            Ti = T[inv[:, i]]
            si = None
            for j in range(kl):
                sj = None
                for k in range(kb):
                    x = bw[:, k] * Ti[:, (c * kl + j) * kb + k]
                    sj = x if sj is None else sj + x
                sj = lw[:, j] * sj
                si = sj if si is None else si + sj
            si = vw[:, i] * si
            acc = si if acc is None else acc + si
        out.append(acc)
    return torch.stack(out, -1)


def group_blend_runs(run: Tensor, inv_s: Tensor, vw: Tensor, lw: Tensor, bw: Tensor, T: Tensor) -> Tensor:
    """`group_blend` with every point's groups read through its run (`group_runs`): run (b,) int32,
    inv_s (S, k_v) the runs' groups — ``inv = inv_s[run]`` gathered inside the compiled loop, not
    stored (the same sums bit for bit)."""
    return group_blend(inv_s[run.long()], vw, lw, bw, T)


_group_block = fused(group_block, options=KERNEL_OPTIONS)
_group_blend = fused(group_blend_runs, options={"cpp.enable_floating_point_contract_flag": "fast"})
# Groups per compiled block of `fine_grouped` when it is given ``points`` (tests; and its remainder blocks).
# 2048 rather than 1024 groups per block: chess bench pixel V groups, 1 thread, micro-benchmark under
# load, 46.7 -> 40.4 ms (fewer calls, each ~0.2 ms of Dynamo / wrapper overhead).
GROUP_BLOCK = 2048
GROUP_TAIL = 128
# Fewer points than this: the per-point kernel (no grouping overhead; tests' tiny frames use both).
GROUP_MIN_POINTS = 256


def fine_grouped(Vt: Tensor, Rt: Tensor, Lt: Tensor, vrows: Tensor, vw: Tensor, brows: Tensor, bw: Tensor,
                 lrows: Tensor, lw: Tensor, *, points: int | None = None, stats: dict | None = None,
                 chunks: tuple | None = None) -> Tensor:
    """`fine_kernel` (same arguments and result) by groups: `group_rows`, `group_block` over the
    groups (one call with a symbolic group count; ``points`` given: compiled static blocks of that
    many groups), `group_blend` per point. ``stats``: receives ``"groups"``, the number of groups.
    One call instead of the blocks of GROUP_BLOCK: chess pixel V frame, 1 thread, same process,
    1.06x (L 1.02x), T bit for bit. ``chunks`` (`vis_chunks` of Vt) and 4 ρ̃ and 4 grid rows: T by
    the native loop over each group's non-zero chunks (`native.groups`), to float32 round-off, and
    the blend by `native_group.blend` (to float32 round-off; the compiled `group_blend_runs` is its
    oracle and fallback)."""
    Kp, dt, R3, L3 = _fine_tables(Vt, Rt, Lt)
    gv, gl, gb, inv_s, run = group_runs(vrows.long(), lrows.long(), brows.long(), n_l=L3.shape[0], n_b=R3.shape[0])
    p = GROUP_BLOCK if points is None else int(points)
    G = gv.shape[0]
    if stats is not None:
        stats["groups"] = int(G)
        stats["group_vis"] = gv  # each group's visibility row (`frame_cost`: its non-zero triangles)
    if chunks is not None and points is None and gl.shape[1] == 4 and gb.shape[1] == 4 and dt == torch.float32:
        T = native.groups(Vt, Rt, Lt, gv, gl, gb, chunks)  # each group's non-zero chunks (`native`)
        # and the blend by the C loop of `native_group` (to float32 round-off; None: compiled below)
        out = native_group.blend(run, inv_s, vw.float(), lw.float(), bw.float(), T)
        if out is not None:
            return out
    elif points is None and G <= 1:  # a size Dynamo would specialise (a compilation in a timed frame)
        T = group_block(gv, gl, gb, Vt, R3, L3)
    elif points is None:
        # every group in one call with a symbolic group count: no per-block call overhead, no
        # concatenation of the blocks' T (one compiled variant for every frame)
        gv, gl, gb = gv.contiguous(), gl.contiguous(), gb.contiguous()
        for x in (gv, gl, gb):
            torch._dynamo.maybe_mark_dynamic(x, 0)
        T = _group_block(gv, gl, gb, Vt, R3, L3)
    else:
        head = G // p * p if G > p else 0
        tail = min(p, GROUP_TAIL)  # both sizes compiled in the warm-up frame (chess L frame 1 re-traced the tail)
        parts = [map_rows(_group_block, [gv[:head], gl[:head], gb[:head]], (Vt, R3, L3), chunk=p, warm=(tail,))] if head else []
        if head < G or not head:
            parts.append(map_rows(_group_block, [gv[head:], gl[head:], gb[head:]], (Vt, R3, L3), chunk=tail, warm=(p,)))
        T = parts[0] if len(parts) == 1 else torch.cat(parts)
    torch._dynamo.maybe_mark_dynamic(T, 0)
    # the blend of every point in one call with a symbolic point count (not `map_rows` blocks of
    # GROUP_BLEND_POINTS and their concatenation): one compiled variant for every frame size;
    # synthetic chess-sized groups (2.5e5 points, 3 rows), 1 thread, same process: 10.0 -> 6.9 ms,
    # bit for bit
    rows = [run, vw.to(dt).contiguous(), lw.to(dt).contiguous(), bw.to(dt).contiguous()]
    inv_s = inv_s.contiguous()
    if rows[0].shape[0] <= 1 or inv_s.shape[0] <= 1:  # sizes Dynamo would specialise
        return group_blend_runs(rows[0], inv_s, *rows[1:], T)
    for x in (*rows, inv_s):
        torch._dynamo.maybe_mark_dynamic(x, 0)
    return _group_blend(rows[0], inv_s, *rows[1:], T)


# A per-vertex frame whose ranges `native.hit_faces` checked resolves by the shared C loop directly
# (`gouraud_image` with ``checked``). False: `methods.core.gouraud.resolve` always (its own checks).
CHECKED_RESOLVE = True


# ... and by the triple product's own copy of that loop with the seen faces' colours in a face table
# (`native.resolve`, the same bits) when the caller hands `native.hit_faces`' face list. False: the
# shared loop (the test oracle).
FACE_TABLE_RESOLVE = True


def gouraud_image(gbuffer, F: Tensor, Bv: Tensor, *, checked: bool = False, faces: Tensor | None = None) -> Tensor:
    """The (H, W, 3) image of per-vertex colours Bv (N, 3) on ``gbuffer`` (Ma 2006 §3.3, per-vertex
    shading: each sample interpolates its triangle's vertex colours barycentrically, 0 on a miss, the
    pixel is their mean) — the shared compiled Gouraud resolve, `methods.core.gouraud.resolve`
    (= ``gbuffer.resolve(gbuffer.interpolate(Bv, F))`` to float32 round-off).

    ``checked``: the caller has checked, on these very arrays, what `gouraud.resolve` checks before
    its unchecked loop reads — every hit sample's face in [0, len(F)) and every vertex of those faces
    in [0, len(Bv)) (`native.hit_faces`' one pass over the samples, whose counts[1] raises otherwise;
    the loop reads no face of a missed sample and no other face's corners) — so its C loop
    (`gouraud._resolve_native`, the same call and so the same bits) runs without `resolve`'s two
    `torch.aminmax` passes over the faces and the corner table (~0.3 ms of a bench frame at 1 thread,
    a parallel region at 2). ``faces`` (with ``checked``): `native.hit_faces`' face list of these arrays —
    `native.resolve` (that loop reading each seen face's 9 colours from a face table made first; the
    same bits). Any other case, or no C loop: `gouraud.resolve`."""
    from methods.core import gouraud

    if checked and faces is not None and FACE_TABLE_RESOLVE and Bv.shape[0] > 0:
        img = native.resolve(Bv, F, faces, gbuffer.hit, gbuffer.face, gbuffer.bary, gbuffer.height, gbuffer.width,
                             gbuffer.spp_side)
        if img is not None:
            return img
    if checked and CHECKED_RESOLVE and Bv.shape[0] > 0:
        fv = F.T
        S2 = gbuffer.spp_side * gbuffer.spp_side
        n = gbuffer.height * gbuffer.width
        if gbuffer.face.shape[0] == n * S2 and gbuffer.hit.shape == gbuffer.face.shape:
            bu, bv = gbuffer.bary.float().unbind(-1)
            img = gouraud._resolve_native(Bv, fv, gbuffer.face, bu, bv, gbuffer.hit, n, S2)
            if img is not None:
                return img.view(gbuffer.height, gbuffer.width, -1)
    return gouraud.resolve(Bv, F.T, gbuffer.face, gbuffer.bary, gbuffer.hit, gbuffer.height, gbuffer.width,
                           gbuffer.spp_side)


# -- front end --------------------------------------------------------------------------------------


def choose_evaluator(m_enumerated: int, K_eff: int) -> str:
    """"sparse" when (m_a + m_b)·`SPARSE_BREAK_EVEN` < K_eff, else "dense"."""
    return "sparse" if m_enumerated * SPARSE_BREAK_EVEN < K_eff else "dense"


def evaluate(V: SparseList, rho: SparseList, Lgt: SparseList, K: int, evaluator: str = "auto") -> Tensor:
    """Eq. 7 for B points from the three lists (`shading_lists`) → (B, 3).

    evaluator: "auto" | "dense" | "sparse" | "reference" (densify + `spherical_haar.triple_integral`,
    the current `TripleProduct._shade`)."""
    if evaluator not in EVALUATORS:
        raise ValueError(f"evaluator must be one of {EVALUATORS}, got {evaluator!r}")
    if evaluator == "reference":
        from methods.core.spherical_haar import triple_integral

        return triple_integral(_scatter(Lgt, K), _scatter(V, K), _scatter(rho, K))
    Ke = _effective_size(V, rho, Lgt)
    if evaluator == "fine":  # the list form of `shade_fine`'s sum
        evaluator = "dense"
    if evaluator == "auto":
        evaluator = choose_evaluator(V[1].shape[2] + rho[1].shape[2], Ke)
    if evaluator == "sparse":
        return triple_sparse(V, rho, Lgt, K)
    return triple_dense(V, rho, Lgt, K, K_eff=Ke)


def shade(method, R: Tensor, wo_world: Tensor, region: Tensor, vrows: Tensor, vw: Tensor,
          mix: Tensor | None = None, *, evaluator: str = "auto", points: int | None = None) -> Tensor:
    """Drop-in for `TripleProduct._shade` (mix None) and `TripleProduct._shade_blend` (mix (B,)):
    eq. 7 for B points → (B, 3) (same inputs, `shading_lists`).

    The look-ups are done for all B points (`shading_rows`), then the blending and the evaluation
    run in sub-batches of ``points`` (default `INNER_POINTS`) so the blended vectors and the
    scratch stay in the L2 cache (measured 2–3× faster than batches of ~1000 points)."""
    if evaluator not in EVALUATORS:
        raise ValueError(f"evaluator must be one of {EVALUATORS}, got {evaluator!r}")
    if evaluator == "fine" or (evaluator == "auto" and fine_ok(method, mix)):
        if not fine_ok(method, mix):
            raise ValueError("evaluator 'fine' needs full tables (n_coeffs=None or selection='top') "
                             "and a grid light_lookup")
        return shade_fine(method, R, wo_world, region, vrows, vw, mix)
    B = R.shape[0]
    spec = shading_rows(method, R, wo_world, region, vrows, vw, mix)
    p = INNER_POINTS if points is None else int(points)
    out = torch.empty(B, 3, dtype=torch.float32, device=R.device)
    for a in range(0, B, p):
        s = slice(a, a + p)
        out[s] = evaluate(*lists_from_rows(spec, s, method.K), method.K, evaluator)
    return out


def lookups_fill_ok(method, evaluator: str, mix: Tensor | None = None) -> bool:
    """`shade_pixels` takes its look-ups from `pixel_lookups` (so it can ``fill`` rows of them)."""
    return evaluator in ("auto", "fine") and fine_ok(method, mix) and front_ok(method)


def shade_pixels(method, normals: Tensor, wo_world: Tensor, region: Tensor, vrows: Tensor, vw: Tensor,
                 mix: Tensor | None = None, *, evaluator: str = "auto",
                 fill: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """`shade` at G-buffer samples given by their unit shading normals (B, 3) instead of their
    frames: ``shade(method, local_frames(normals, tangent), ...)``. When the fine-value path runs
    with the "grid" tangent and a trilinear look-up on a one-ψ grid (the default config), the
    look-ups come straight from the normals (`pixel_lookups`) and the frames are never formed.

    ``fill`` = (dst, src) (k,) int64 (`lookups_fill_ok` only): the points dst take the look-ups (ωo rows
    with their regions' offsets, grid rows, weights) of the points src, before anything reads them —
    a frame's missed samples (zero normal, region −1: rows outside the ρ̃ stack) shaded as a copy of a
    neighbouring hit (`TripleProduct.render`); their radiance is the caller's to discard."""
    if evaluator not in EVALUATORS:
        raise ValueError(f"evaluator must be one of {EVALUATORS}, got {evaluator!r}")
    if lookups_fill_ok(method, evaluator, mix):
        look = pixel_lookups(normals, wo_world, method.outgoing, method.grid, region)
        if fill is not None:
            dst, src = fill
            for t in look:                      # (B, 4) each: k rows copied
                t.index_copy_(0, dst, t.index_select(0, src))
        return shade_fine(method, None, wo_world, region, vrows, vw, mix, lookups=(*look, True))
    if fill is not None:
        raise ValueError("fill needs the pixel look-ups' path (`lookups_fill_ok`)")
    R = local_frames(normals, method.config["tangent"])
    return shade(method, R, wo_world, region, vrows, vw, mix, evaluator=evaluator)


def use_fast_shading(method, evaluator: str = "auto"):
    """``method`` (a precomputed `TripleProduct`) summing eq. 7 with `shade`'s ``evaluator``: a copy
    sharing its arrays (``method.with_evaluator``); the method itself is unchanged."""
    return method.with_evaluator(evaluator)


def use_reference_shading(method):
    """``method`` with its independent dense `triple_integral` path (``evaluator="reference"`` of
    `TripleProduct`, not `shade`'s list-based "reference"): a copy sharing its arrays."""
    return method.with_evaluator("reference")


# -- roofline ---------------------------------------------------------------------------------------


def _kept(method) -> int:
    """n: coefficients kept per function (all K when ``n_coeffs`` is None)."""
    n = method._n()
    return method.K if n is None else min(n, method.K)


def _idx_bytes(method, name: str, idx: Tensor | None) -> int:
    """Bytes per stored entry of an index table: 0 when the table is full (every row 0..n−1, so
    the indices carry no information a frame must read), else the element size."""
    if idx is None:
        return 4 if method._n() is not None and method._n() < method.K and method.config["selection"] != "top" else 0
    return 0 if _is_full(method, name, idx) else idx.element_size()


def _mean_ancestors(method, name: str, idx: Tensor | None) -> float:
    """Mean of A = 1 + 3l (a level-l wavelet's coarser functions: Ma 2006 §3.1 rule 3; 0 for
    level-0 scaling functions) over the kept coefficients of a table (cached per tensor)."""
    if idx is None:
        return 0.0
    cache = method.__dict__.setdefault("_perf_cache", {})
    hit = cache.get(("anc", name))
    if hit is None or hit[0] is not idx:
        lvl = coefficient_structure(method.level)[0].to(idx.device)[idx.long()]
        a = torch.where(lvl >= 0, 1.0 + 3.0 * lvl.double(), torch.zeros((), dtype=torch.float64))
        hit = cache[("anc", name)] = (idx, float(a.mean()) if a.numel() else 0.0)
    return hit[1]


def triple_flops(method, live: int | None = None) -> int:
    """Minimum flops of eq. 7's triple sum at one shading point once its three functions are
    formed, n kept coefficients per function (module docstring "Frame cost"): min(sparse rule,
    fine-value product). ``live``: the live fine triangles (`live_triangles`) the fine-value
    product sums over, when fewer than K'."""
    sparse, full, Kp = _triple_terms(method)
    if full and live is not None:
        Kp = min(Kp, int(live))
    dense = 9 * Kp + (0 if full else 7 * 8 * (Kp - 20) // 3)
    return int(min(sparse, dense))


def _triple_terms(method) -> tuple[float, bool, int]:
    """`triple_flops`' parts: the sparse rules' count, whether the tables are full, and K' (3 flops per
    channel and fine triangle of K' in the fine-value product, plus 7 transforms when not full)."""
    n, C = _kept(method), 3
    bi = _brdf_stack(method)[0] if method.tables else None
    av, ab = _mean_ancestors(method, "V", method.V_idx), _mean_ancestors(method, "rho", bi)
    sparse = C * (n * (10 + 2 * av) + n * (3 + ab))
    full = all(x is not None and _is_full(method, nm, x) for nm, x in (("V", method.V_idx), ("rho", bi))) and \
        (method.config["selection"] == "top" or method._n() is None or method._n() >= method.K)
    return sparse, full, (_round_size(n) if full else method.K)


def blend_terms(k: int) -> int:
    """Flops per output value of a weighted blend of k rows: k multiplies and k − 1 adds (2k − 1);
    0 for k ≤ 1 (a single row has weight 1: it is used as stored)."""
    return 2 * k - 1 if k > 1 else 0


def blend_flops(method, k_v: int, live: int | None = None) -> int:
    """Flops of forming V, ρ̃ and L at one point from k_v visibility rows (1 channel), 4 ρ̃ rows and
    the grid look-up's distinct rows (3 channels each): (2k − 1)·n per blend of k rows and channel
    (n: the live fine triangles ``live`` when given, `live_triangles`)."""
    k_l = {"nearest": 1, "trilinear": 4 if method.grid.n_psi == 1 else 8}[method.config["light_lookup"]]
    return (_kept(method) if live is None else int(live)) * (blend_terms(k_v) + 3 * blend_terms(4) + 3 * blend_terms(k_l))


def grouped_flops(method, groups: int, shaded: int, k_v: int = 3, live: int | None = None) -> int:
    """Flops of eq. 7 by groups (`fine_grouped`, full tables, K' fine triangles): per group and
    channel, the k_L products V̂·L̂_j and the k_L·k_ρ sums of their products with ρ̂_k
    (K'·(k_L + 2·k_L·k_ρ)); per shaded sample and channel, the blend of its k_v groups' values,
    Σ_i w_i (Σ_j w_j (Σ_k w_k T_ijk)): k_v·(2·k_L·k_ρ + k_L) + k_v − 1. k_ρ = 4 ωo rows, k_L the
    look-up's distinct grid rows (as `blend_flops`). ``live``: the live fine triangles
    (`live_triangles`) instead of K'."""
    k_l = {"nearest": 1, "trilinear": 4 if method.grid.n_psi == 1 else 8}[method.config["light_lookup"]]
    k_b, Kp = 4, _round_size(_kept(method)) if live is None else int(live)
    return int(groups * 3 * Kp * (k_l + 2 * k_l * k_b) + shaded * 3 * (k_v * (2 * k_l * k_b + k_l) + k_v - 1))


def relight_flops(method, envmap, *, azimuthal: bool = False, frames: int | None = None,
                  live: int | None = None) -> int:
    """Flops of re-projecting the lighting into the F grid frames (`lighting.project_lighting`):
    per sample direction (K·4^s per frame) a 3×3 rotation (15), a bilinear 4-tap RGB env look-up
    (24) and its solid-angle-weighted accumulation (6); per frame the RGB forward transform
    (8 adds per 4 children per level: 8(K − 20)/3 per channel). ``azimuthal``: the map turns about
    +Y only (`lighting.env_taps_azimuthal`): the rotation is one add to the base u (1 + 24 + 6).
    ``frames``: the grid frames projected (default all; a lazily set grid projects the looked-up ones).
    ``live``: the live fine triangles (`live_triangles`): only their samples are projected, and their
    fine values are what eq. 7 reads (no transform)."""
    K, s = method.K, method.config["light_supersample"]
    per_sample = 31 if azimuthal else 45
    F = method.grid.size if frames is None else int(frames)
    if live is not None:
        return int(F * per_sample * int(live) * 4 ** s)
    return int(F * (per_sample * K * 4 ** s + 3 * 8 * (K - 20) // 3))


# Points per chunk of `nonzero_reads` (a (chunk, n') bool mask and its int32 copy: ~3 MB at n' = 656).
NONZERO_CHUNK = 4096


def _sum_point_flops(method, k_v: int, nz: Tensor) -> int:
    """Σ over points of `blend_flops`(k_v) + `triple_flops` with each point's own count ``nz`` (P,)
    of fine triangles in place of the live ones (full tables: the live path)."""
    sparse, full, Kp = _triple_terms(method)
    if not full:
        raise ValueError("per-point fine-triangle counts need full tables (the live-triangle path)")
    z = nz.double()
    tri = torch.minimum(torch.full_like(z, float(sparse)), 9.0 * z.clamp(max=Kp)).floor()  # int(min(...)) per point
    return int(blend_flops(method, k_v, 1)) * int(nz.sum()) + int(tri.sum())


def nonzero_reads(method, live: Tensor, reads: list, *, k_v: int, pairs: bool) -> dict:
    """The frame's work at the grain of its zeros (module docstring, "Frame cost"): what the
    fine-value path read (``reads``: per `shade_fine` call its points' visibility rows / weights, grid
    rows / weights, and under grouping each group's visibility row), counted over the fine triangles
    where the point's visibility is non-zero — a triangle where every visibility row a point blends
    (with a non-zero weight) is exactly 0 adds an exact 0 to that point's eq. 7, whatever ρ̃ and L.

    Returns ``point`` (Σ_p `blend_flops`(k_v) + `triple_flops` over the point's non-zero triangles),
    ``group`` (Σ over groups of their row's non-zero triangles: the K' of `grouped_flops`; None when no
    call grouped), and with ``pairs`` the number of (grid frame, live triangle) pairs some point looks
    up with a non-zero weight and has non-zero visibility on (the lighting a re-projection must
    produce; the rest is only ever multiplied by 0)."""
    Vl = live_table(method, "V", method.V_val, live) != 0                 # (N_V, n')
    need = torch.zeros(method.grid.size, Vl.shape[1], dtype=torch.int32) if pairs else None
    point, group = 0, None
    for r in reads:
        # the points' distinct (visibility rows, grid rows) with a weight-0 row as −1 (many samples
        # share them; each distinct one counted with its multiplicity)
        kv = r["vrows"].shape[1]
        key = torch.cat([torch.where(r["vw"] != 0, r["vrows"].long(), -1),
                         torch.where(r["lw"] != 0, r["lrows"].long(), -1) if need is not None else
                         r["vrows"].new_zeros(r["vrows"].shape[0], 0, dtype=torch.long)], 1)
        key, mult = torch.unique(key, dim=0, return_counts=True)
        for a in range(0, key.shape[0], NONZERO_CHUNK):
            kc, mc = key[a:a + NONZERO_CHUNK], mult[a:a + NONZERO_CHUNK]
            mask = torch.zeros(kc.shape[0], Vl.shape[1], dtype=torch.bool)
            for j in range(kv):
                mask |= Vl[kc[:, j].clamp_min(0)] & (kc[:, j:j + 1] >= 0)
            point += _sum_point_flops(method, k_v, mask.sum(1).repeat_interleave(mc))
            if need is not None:
                mi = mask.to(torch.int32)
                for k in range(kv, kc.shape[1]):
                    sel = kc[:, k] >= 0
                    need.index_add_(0, kc[sel, k], mi[sel])
        if r.get("group_vis") is not None:
            group = (group or 0) + int(Vl.sum(1)[r["group_vis"].long()].sum())
    return {"point": point, "group": group, "pairs": None if need is None else int((need > 0).sum())}


def visibility_read_bytes(method, live: Tensor, rows: Tensor) -> int:
    """Bytes of the visibility rows ``rows`` (distinct row indices) of the live fine-value table (`live_table`
    of the live triangles ``live``) a frame must read at least once, at the grain of their zeros (module
    docstring, "Frame cost"): per row its non-zero values (float32), a bit per live column saying which
    are non-zero (⌈n'/8⌉ bytes) and where its values start (int64). The native loops read more (the
    8-column chunks holding the non-zeros and an int32 start per chunk, `native.chunks`); the torch
    path whole rows."""
    if rows.numel() == 0:
        return 0
    Vl = live_table(method, "V", method.V_val, live)
    nonzero = int((Vl.index_select(0, rows.to(Vl.device).long()) != 0).sum())
    return nonzero * 4 + int(rows.numel()) * ((int(Vl.shape[1]) + 7) // 8 + 8)


def relight_table_bytes(method, live: int | None = None) -> int:
    """Bytes of the base coordinates an azimuthal re-projection reads (`lighting._azimuthal_samples`:
    float64 u0 and float32 v0 per sample of the n_theta·n_psi base frames; of the live fine
    triangles' samples only when ``live`` is given)."""
    g = method.grid
    return g.n_theta * g.n_psi * (method.K if live is None else int(live)) * 4 ** method.config["light_supersample"] * (8 + 4)


def frame_cost(method, frame_kind: str, num_samples: int, *, envmap=None, pixels: int | None = None):
    """The compulsory work of a frame (`methods.base.FrameCost`; model in the module docstring).

    Args:
        method: a precomputed `TripleProduct`.
        frame_kind: a sequence kind ("V", "L", "E", "VL", "VB", "VBL", ...); "L"/"E" in it = the
            lighting changed (re-projection counted).
        num_samples: G-buffer samples P of the frame.
        envmap: the env map of an "L"/"E" frame (its texel count enters); default the scene's.
        pixels: H·W of the frame's image (its output, `methods.base.output_bytes`); None: num_samples.
    Returns:
        FrameCost(bytes, flops), or None for ``light_lookup="exact"`` (per-point projection).
    """
    from methods.base import GBUFFER_BYTES_PER_SAMPLE, FrameCost, output_bytes

    if not isinstance(frame_kind, str) or not frame_kind or set(frame_kind) - set("VBLEP"):
        raise ValueError(f"frame_kind must be a sequence kind made of 'V', 'B', 'L', 'E', got {frame_kind!r}")
    if "P" in frame_kind:
        raise ValueError("frame_kind: triple_product has static geometry, no 'P' frames")
    if isinstance(num_samples, bool) or not isinstance(num_samples, int) or num_samples < 0:
        raise ValueError(f"num_samples must be an int >= 0, got {num_samples!r}")
    if method.scene is None:
        raise ValueError("frame_cost needs a precomputed method")
    cfg = method.config
    if cfg["light_lookup"] == "exact":
        return None
    n = _kept(method)
    pixel = cfg["shading"] == "pixel"
    # the live fine triangles (`live_triangles`: the others multiply eq. 7 by an exact 0), where the
    # fine-value path is what runs: its tables, sums and re-projection span only those
    live_t = live_triangles(method) if cfg["evaluator"] in ("auto", "fine") and fine_ok(method) else None
    nl = None if live_t is None else int(live_t.numel())
    nw = n if nl is None else nl                                         # values per stored row read
    rec = method.last_frame()
    if rec.get("samples") != num_samples:  # no frame of this size rendered yet: upper bounds
        rec = {"shaded": num_samples, "faces": min(int(method.F.shape[0]), num_samples),
               "vis_rows": min(int(method.V_idx.shape[0]), (4 if method.tex_rows is not None else 3) * num_samples),
               "vertices": min(int(method.V.shape[0]), 3 * num_samples)}
    f4 = 4
    # run-time arrays read once; the visibility rows of the fine-value path at the grain of their zeros
    # (`visibility_read_bytes`), else whole (n values + n indices)
    ids = rec.get("vis_row_ids")
    if live_t is not None and ids is not None and not callable(ids) and _idx_bytes(method, "V", method.V_idx) == 0:
        vis = visibility_read_bytes(method, live_t, ids)
    else:
        vis = rec["vis_rows"] * nw * (f4 + _idx_bytes(method, "V", method.V_idx))
    bi = _brdf_stack(method)[0]
    n_tab = len(method.tables) + len(getattr(method, "blends", {}) or {})
    brdf = n_tab * method.outgoing.size * nw * (3 * f4 + _idx_bytes(method, "rho", bi))
    grid = method.grid.size * nw * (3 * f4 + _idx_bytes(method, "L", method.L_idx))
    mesh = rec["faces"] * 3 * method.F.element_size()                  # the faces' vertex indices
    if pixel:
        gbuf = num_samples * (GBUFFER_BYTES_PER_SAMPLE + 8)               # + region (int64)
        extras = sum(v for k, v in method.memory().items()
                              if k.startswith(("blend_weight", "bump_height", "uv", "vis_texture_map", "vis_texture_points")))
        per_vertex = 0
    else:
        gbuf = num_samples * (GBUFFER_BYTES_PER_SAMPLE - 2 * 3 * 4)      # normal and ωo are not read
        extras = 0
        per_vertex = rec["vertices"] * (9 * f4 + 3 * f4 + method.vertex_region.element_size())  # R, p, region
    out = output_bytes(num_samples, pixels)                               # the (H, W, 3) image
    nbytes = vis + brdf + grid + mesh + gbuf + extras + per_vertex + out
    relit = "L" in frame_kind or "E" in frame_kind
    # the frame's reads at the grain of their zeros (`nonzero_reads`), where the fine-value path ran
    # on the live triangles and recorded them; else the live-triangle grain
    zr = nonzero_reads(method, live_t, rec["reads"], k_v=3 if pixel else 1, pairs=relit) \
        if live_t is not None and rec.get("reads") else None
    # flops: per shading point, form the three functions and sum eq. 7
    if pixel:
        flops = zr["point"] if zr else rec["shaded"] * (blend_flops(method, 3, nl) + triple_flops(method, nl))
        if rec.get("groups"):  # the trilinear form by groups ran (`fine_grouped`): its count if smaller
            if zr and zr["group"] is not None:
                grouped = grouped_flops(method, 1, 0, live=zr["group"]) + grouped_flops(method, 0, rec["shaded"], live=1)
            else:
                grouped = grouped_flops(method, rec["groups"], rec["shaded"], live=nl)
            flops = min(flops, grouped)
    else:
        flops = (zr["point"] if zr else rec["vertices"] * (blend_flops(method, 1, nl) + triple_flops(method, nl))) \
            + rec["shaded"] * 3 * blend_terms(3)
    if relit:
        env = envmap if envmap is not None else (getattr(method, "_envmap", None) or method.scene.envmap)
        az = method.stats.get("lighting_path") == "azimuthal"            # what the last re-projection ran
        # the grid frames the change projected: all, or those the frame looked up (a lazily set grid,
        # `TripleProduct.fill_lighting`; the frames it did not need are not compulsory work)
        Fp = min(int(method.stats.get("projected_frames", method.grid.size)), method.grid.size)
        if zr:  # only the (frame, live triangle) pairs some point reads with non-zero visibility
            written = grid * zr["pairs"] // (method.grid.size * nw)
            rf = relight_flops(method, env, azimuthal=az, frames=1, live=zr["pairs"])
        else:
            written = grid * Fp // method.grid.size
            rf = relight_flops(method, env, azimuthal=az, frames=Fp, live=nl)
        nbytes += int(env.data.numel()) * f4 + written + (relight_table_bytes(method, nl) if az else 0)  # texels read, grid written
        flops += rf
    return FrameCost(int(nbytes), int(flops))
