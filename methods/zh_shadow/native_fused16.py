"""`native.fused_pixels`' plane samples 16 at a time (session 40, zh40p): AVX-512 vectors of 16 G-buffer samples
(four pixels of 2×2) in the one pass of the paper configuration's P / V / VB / VBL / VL frames.

`zh37v_fused` (``fma``) and `zh33p_fused` walk each 64-pixel chunk sample by sample: the plane test, n·ωo, the
face's corners, u at them interpolated, the clamp, the pixel's sum — ~11 cycles a sample, scalar, over the
262,144 samples of a bench frame (~0.9–1.0 ms of the pass's ~2.2–2.8 at 1 thread, back to back). Here the same
chunk loop with its plane part as 16-lane code where the layout allows it (S² = 4, the G-buffer's column-major
barycentrics and ωo, indices that fit int32): the mask and hit bytes widened, the normals deinterleaved by two
permutes a component, n·ωo, ωo and the barycentrics loaded as vectors; a pixel whose active samples (plane,
facing the camera) all lie on the face of its first sample (79 % of the bench P frame's plane pixels) reads
that face's corners and their u once and broadcasts them over its four lanes; the other active samples run the
scalar lines one by one (`zh_plane_sample`) and are blended in — gathers (12 a vector) were tried first: 0.97
→ 0.90 ms only, and broadcasting only the groups of four uniform pixels 0.76. Every float operation is the scalar
loop's in the same order (separate products and sums, ``-ffp-contract=off``; the clamp a compare-and-blend that
keeps NaN), and each pixel's four samples are summed in order from the first (((s0 + s1) + s2) + s3, the four
pixels × three channels at once by permutes, stored as the chunk's next 12 outputs): the same bits. The object
samples (mask 0, hit) are collected in the same ascending order and shaded by the same code (`zh37v_fused`'s or
`zh33p_fused`'s dot): the image is bit for bit the pass it replaces (tests, `tests/methods/zh_shadow/
test_zh40p.py`). Pixels of a chunk's tail (fewer than 4 left) and every other layout run the scalar lines.

Bench creature P frame's pass (35,800 object samples), 1 thread, back to back (`python -m
benchmarks.zh40p_fused16_ab --kind P`): plane part alone 0.98 → 0.66 ms (min 0.91 → 0.59), the whole pass
2.55 → 2.27 ms (median). Tried and dropped: sharing the object samples' three table rows over runs of up to 4
consecutive samples on one face (16-lane dots; float32 round-off) — the pass 2.21 → 2.15 ms (1.03×): most runs
are of one sample (the creature's faces are ~2 pixels), and the table rows are not what bounds the object part.

`native.fused_pixels`(…, ``vector``=True) runs it where it runs (no compiler, no AVX-512, ``PRTBENCH_ZH_NATIVE=0``:
the scalar pass, the tests' oracle).
"""
from __future__ import annotations

from methods.core import native
from methods.zh_shadow import native as zn

# The scalar plane lines of the fused pass (`native._FUSED_SOURCE`'s chunk loop), replaced below by the vector
# block (its scalar form kept for the tail and other layouts)
_SCALAR_PLANE = r"""        for (int64_t p = p0; p < p1; ++p) {
            float o0 = 0.f, o1 = 0.f, o2 = 0.f;
            for (int64_t s = 0; s < S2; ++s) {"""


def _deinterleave_idx(c: int) -> tuple[list[int], list[int]]:
    """Index vectors of component c of 16 (x, y, z) triples in three 16-float loads v0, v1, v2:
    t = permutex2var(v0, i1, v1) then permutex2var(t, i2, v2)."""
    e = [3 * i + c for i in range(16)]
    i1 = [x if x < 32 else 0 for x in e]
    i2 = [i if x < 32 else 16 + (x - 32) for i, x in enumerate(e)]
    return i1, i2


def _c_ints(v: list[int]) -> str:
    return ", ".join(str(x) for x in v)


_VECTOR_PLANE = r"""        int64_t pv = p0;
#ifdef __AVX512F__
        if (vec) {
            const __m512 zero = _mm512_setzero_ps(), one = _mm512_set1_ps(1.0f);
            const __m512i M64 = _mm512_set1_epi64(M);
            const __m512i N32 = _mm512_set1_epi32((int32_t)N);
            for (; pv + 4 <= p1; pv += 4) {
                const int64_t q0 = pv * 4;
                const __mmask16 mk = _mm512_test_epi32_mask(
                    _mm512_cvtepu8_epi32(_mm_loadu_si128((const __m128i *)(mask + q0))), _mm512_set1_epi32(0xff));
                __mmask16 ob = (__mmask16)~mk;
                if (hit)
                    ob &= _mm512_test_epi32_mask(
                        _mm512_cvtepu8_epi32(_mm_loadu_si128((const __m128i *)(hit + q0))), _mm512_set1_epi32(0xff));
                while (ob) {   /* the object samples, ascending */
                    oq[no++] = q0 + __builtin_ctz((unsigned)ob);
                    ob &= (__mmask16)(ob - 1);
                }
                __m512 x0 = zero, x1 = zero, x2 = zero;
                if (mk) {
                    const float *nb3 = nrm + 3 * q0;
                    const __m512 v0 = _mm512_loadu_ps(nb3), v1 = _mm512_loadu_ps(nb3 + 16), v2 = _mm512_loadu_ps(nb3 + 32);
                    const __m512 nx = _mm512_permutex2var_ps(_mm512_permutex2var_ps(v0, IX1, v1), IX2, v2);
                    const __m512 ny = _mm512_permutex2var_ps(_mm512_permutex2var_ps(v0, IY1, v1), IY2, v2);
                    const __m512 nz = _mm512_permutex2var_ps(_mm512_permutex2var_ps(v0, IZ1, v1), IZ2, v2);
                    const __m512 wx = _mm512_loadu_ps(wo + q0), wy = _mm512_loadu_ps(wo + ws0 + q0),
                                 wz = _mm512_loadu_ps(wo + 2 * ws0 + q0);
                    const __m512 dn = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(nx, wx), _mm512_mul_ps(ny, wy)),
                                                    _mm512_mul_ps(nz, wz));
                    const __mmask16 act = mk & _mm512_cmp_ps_mask(dn, zero, _CMP_GT_OQ);
                    if (act) {
                        const __m512i fa = _mm512_loadu_si512((const void *)(face + q0)),
                                      fb = _mm512_loadu_si512((const void *)(face + q0 + 8));
                        const __mmask16 fok = act & (__mmask16)(_mm512_cmplt_epu64_mask(fa, M64)
                                                                | (_mm512_cmplt_epu64_mask(fb, M64) << 8));
                        const __m512i f32 = _mm512_inserti64x4(_mm512_castsi256_si512(_mm512_cvtepi64_epi32(fa)),
                                                               _mm512_cvtepi64_epi32(fb), 1);
                        const __m512 bu = _mm512_loadu_ps(bary + q0), bv = _mm512_loadu_ps(bary + bs0 + q0);
                        const __m512 w = _mm512_sub_ps(_mm512_sub_ps(one, bu), bv);
                        /* a pixel whose active samples share the face of its first sample (in range, its corners
                           too): its corners' u read once, broadcast over its four lanes; the other pixels' active
                           samples gathered (each lane its own face) */
                        __mmask16 rx = 0;
                        __m512 xr0 = zero, xr1 = zero, xr2 = zero;
                        const __mmask16 same = _mm512_cmpeq_epi32_mask(f32, _mm512_permutexvar_epi32(LEAD, f32));
                        __m512 ua[3], ub[3], uc[3];
                        for (int c = 0; c < 3; ++c) ua[c] = ub[c] = uc[c] = zero;
                        __mmask16 upx = 0;   /* the lanes of the pixels read once */
                        for (int j = 0; j < 4; ++j) {
                            const __mmask16 lanes = (__mmask16)(15u << (4 * j));
                            const __mmask16 aj = act & lanes;
                            if (!aj || (aj & (__mmask16)~same) || (fok & lanes) != aj) continue;
                            const int64_t f = face[q0 + 4 * j];
                            const int64_t j0 = F[3 * f], j1 = F[3 * f + 1], j2 = F[3 * f + 2];
                            if ((uint64_t)j0 >= (uint64_t)N || (uint64_t)j1 >= (uint64_t)N || (uint64_t)j2 >= (uint64_t)N)
                                continue;
                            upx |= aj;
                            for (int c = 0; c < 3; ++c) {
                                ua[c] = _mm512_mask_mov_ps(ua[c], lanes, _mm512_set1_ps(u[3 * j0 + c]));
                                ub[c] = _mm512_mask_mov_ps(ub[c], lanes, _mm512_set1_ps(u[3 * j1 + c]));
                                uc[c] = _mm512_mask_mov_ps(uc[c], lanes, _mm512_set1_ps(u[3 * j2 + c]));
                            }
                        }
                        /* the other active samples one by one, as the scalar lines (their values blended in) */
                        const __mmask16 rest = act & (__mmask16)~upx;
                        __mmask16 ok = upx;
                        if (rest) {
                            float xr[3][16] __attribute__((aligned(64)));
                            for (__mmask16 b = rest; b; b &= (__mmask16)(b - 1)) {
                                const int l = __builtin_ctz((unsigned)b);
                                const int64_t q = q0 + l, f = face[q];
                                float x[3];
                                if ((uint64_t)f >= (uint64_t)M
                                        || zh_plane_sample(u, N, F[3 * f], F[3 * f + 1], F[3 * f + 2], bary, bs0, bs1, q,
                                                           clamp, x)) {
                                    ++nb;
                                    continue;
                                }
                                xr[0][l] = x[0]; xr[1][l] = x[1]; xr[2][l] = x[2];
                                ok |= (__mmask16)(1u << l);
                            }
                            rx = ok & rest;
                            xr0 = _mm512_load_ps(xr[0]); xr1 = _mm512_load_ps(xr[1]); xr2 = _mm512_load_ps(xr[2]);
                        }
                        if (ok) {
                            __m512 xs[3];
                            for (int c = 0; c < 3; ++c) {
                                __m512 xc = _mm512_add_ps(_mm512_add_ps(_mm512_mul_ps(ua[c], w), _mm512_mul_ps(ub[c], bu)),
                                                          _mm512_mul_ps(uc[c], bv));
                                if (clamp)   /* clamp_min(0): NaN stays NaN */
                                    xc = _mm512_mask_blend_ps(_mm512_cmp_ps_mask(xc, zero, _CMP_LT_OQ), xc, zero);
                                xs[c] = _mm512_maskz_mov_ps(ok, xc);
                            }
                            x0 = _mm512_mask_mov_ps(xs[0], rx, xr0);
                            x1 = _mm512_mask_mov_ps(xs[1], rx, xr1);
                            x2 = _mm512_mask_mov_ps(xs[2], rx, xr2);
                        }
                    }
                }
                /* each pixel's samples summed in order from the first: T_s lane 3j + c = sample s of pixel j,
                   channel c (four pixels × three channels: the chunk's next 12 outputs, contiguous) */
                const __m512 t01 = _mm512_permutex2var_ps(x0, S01[0], x1), t11 = _mm512_permutex2var_ps(x0, S01[1], x1),
                             t21 = _mm512_permutex2var_ps(x0, S01[2], x1), t31 = _mm512_permutex2var_ps(x0, S01[3], x1);
                const __m512 s0 = _mm512_permutex2var_ps(t01, S2X[0], x2), s1 = _mm512_permutex2var_ps(t11, S2X[1], x2),
                             s2 = _mm512_permutex2var_ps(t21, S2X[2], x2), s3 = _mm512_permutex2var_ps(t31, S2X[3], x2);
                _mm512_mask_storeu_ps(r + 3 * (pv - p0), (__mmask16)0x0FFF,
                                      _mm512_mul_ps(_mm512_add_ps(_mm512_add_ps(_mm512_add_ps(s0, s1), s2), s3), vinv));
            }
        }
#endif
        for (int64_t p = pv; p < p1; ++p) {
            float o0 = 0.f, o1 = 0.f, o2 = 0.f;
            for (int64_t s = 0; s < S2; ++s) {"""

_CONSTS = "\n".join(
    f"static const int32_t ZH40_I{ax}1[16] __attribute__((aligned(64))) = {{{_c_ints(_deinterleave_idx(c)[0])}}};\n"
    f"static const int32_t ZH40_I{ax}2[16] __attribute__((aligned(64))) = {{{_c_ints(_deinterleave_idx(c)[1])}}};"
    for c, ax in enumerate("XYZ"))

def _sum_idx() -> tuple[list[list[int]], list[list[int]]]:
    """Index vectors of the pixel sums: lane L = 3 j + c (j < 4 pixels, c < 3 channels) of T_s takes lane 4 j + s
    of x_c: first from (x0, x1) (c < 2; lanes 0..31), then from (t, x2) (c = 2: 16 + lane)."""
    a, b = [], []
    for s_ in range(4):
        ia, ib = [], []
        for L in range(16):
            j, c = divmod(L, 3)
            src = 4 * j + s_ if j < 4 else 0
            ia.append(src + 16 * c if c < 2 and j < 4 else 0)
            ib.append(16 + src if c == 2 and j < 4 else L)
        a.append(ia)
        b.append(ib)
    return a, b


_CONSTS += "\n" + "\n".join(
    f"static const int32_t ZH40_{nm}[4][16] __attribute__((aligned(64))) = {{"
    + ", ".join("{" + _c_ints(v) + "}" for v in vs) + "};" for nm, vs in zip(("S01", "S2X"), _sum_idx()))

_LOADS = r"""
#ifdef __AVX512F__
    const __m512i IX1 = _mm512_load_si512(ZH40_IX1), IX2 = _mm512_load_si512(ZH40_IX2);
    const __m512i IY1 = _mm512_load_si512(ZH40_IY1), IY2 = _mm512_load_si512(ZH40_IY2);
    const __m512i IZ1 = _mm512_load_si512(ZH40_IZ1), IZ2 = _mm512_load_si512(ZH40_IZ2);
    const __m512i S01[4] = {_mm512_load_si512(ZH40_S01[0]), _mm512_load_si512(ZH40_S01[1]),
                            _mm512_load_si512(ZH40_S01[2]), _mm512_load_si512(ZH40_S01[3])};
    const __m512i S2X[4] = {_mm512_load_si512(ZH40_S2X[0]), _mm512_load_si512(ZH40_S2X[1]),
                            _mm512_load_si512(ZH40_S2X[2]), _mm512_load_si512(ZH40_S2X[3])};
    const __m512 vinv = _mm512_set1_ps(inv);
    const __m512i LEAD = _mm512_set_epi32(12, 12, 12, 12, 8, 8, 8, 8, 4, 4, 4, 4, 0, 0, 0, 0);
    const int vec = S2 == 4 && bs1 == 1 && 3 * M < 2147483647LL && 3 * N < 2147483647LL;
#endif
"""


def _source(base: str, old: str, new: str) -> str:
    assert base.count(_SCALAR_PLANE) == 1 and base.count(f"void {old}(") == 1
    src = base.replace(_SCALAR_PLANE, _VECTOR_PLANE, 1).replace(f"void {old}(", f"void {new}(", 1)
    head = "#include <immintrin.h>\n" + _CONSTS + "\n"
    src = src.replace("#include <math.h>\n", "#include <math.h>\n" + head, 1)
    anchor = "    const int64_t nch = (n + ZH33P_CHUNK - 1) / ZH33P_CHUNK;\n"
    assert src.count(anchor) == 1
    return src.replace(anchor, anchor + _LOADS, 1)


# the exact pass (`zh33p_fused`'s dot) and the regrouped one (`zh37v_fused`'s), each with the vector plane part
_SOURCE = _source(zn._FUSED_SOURCE, "zh33p_fused", "zh40p_fused")
_FMA_SOURCE = _source(zn._FMA_FUSED_SOURCE, "zh37v_fused", "zh40p_fused_fma")
_SIGNATURES = {"zh40p_fused": zn._FUSED_SIGNATURES["zh33p_fused"]}
_FMA_SIGNATURES = {"zh40p_fused_fma": zn._FUSED_SIGNATURES["zh33p_fused"]}


# -- zh42p ------------------------------------------------------------------------------------------------------
# The regrouped pass (`zh37v_fused`'s dot, ``fma``) with the object samples' dot in 16-float vectors (session 42,
# zh42p; `ZHShadow.wide_dot`): b0 (U0[c]·f) + b1 (U1[c]·f) + b2 (U2[c]·f) as `_fma_dot`'s nine running dots of fused
# multiply-adds, 16 lanes a step instead of 8 (K = 80: 5 steps, 45 multiply-adds a point instead of 90), combined by
# the same two multiply-adds and one product per channel, then the 16 lanes summed by a tree
# (``_mm512_reduce_add_ps``). The same terms to float32 round-off (not the same bits as the 8-lane dot: each lane
# sums other products, the final tree differs); the plane samples, the front test, the clamp and every sum into
# the pixels unchanged (the same source). Each point is one thread's: the bits do not depend on the thread count.
# Bench creature P frame's pass (35,800 object samples), 1 thread, process CPU, the pass's own arguments, 64 MB
# written before each call (`python -m benchmarks.zh42p_fused_ab --kind P`): 2.93 → 2.65 ms median (1.11×; A/A
# 1.00), caches warm 2.58 → 2.35 (1.10×); max |diff| 2.2e-7 of the image's largest pixel. With the plane samples
# grouped by face (`_FACE_GROUPS`, below): 2.99 → 2.46 ms (1.22×, A/A 0.995). Tried and dropped: the features 16
# points at once (`_features8`'s statements on 16-float vectors, the same bits): 0.98× against the wide pass.
def _wide_dot(K: int) -> str:
    assert K % 16 == 0
    return f"""
static inline void zh42_dw_{K}(const float* f, const float* u0, const float* u1, const float* u2, float b0, float b1,
                               float b2, float* out) {{
    __m512 a0[3], a1[3], a2[3];
    for (int c = 0; c < 3; ++c) a0[c] = a1[c] = a2[c] = _mm512_setzero_ps();
#pragma GCC unroll 8
    for (int j = 0; j < {K}; j += 16) {{
        const __m512 fj = _mm512_loadu_ps(f + j);
        for (int c = 0; c < 3; ++c) {{
            a0[c] = _mm512_fmadd_ps(_mm512_loadu_ps(u0 + c * {K} + j), fj, a0[c]);
            a1[c] = _mm512_fmadd_ps(_mm512_loadu_ps(u1 + c * {K} + j), fj, a1[c]);
            a2[c] = _mm512_fmadd_ps(_mm512_loadu_ps(u2 + c * {K} + j), fj, a2[c]);
        }}
    }}
    const __m512 B0 = _mm512_set1_ps(b0), B1 = _mm512_set1_ps(b1), B2 = _mm512_set1_ps(b2);
    for (int c = 0; c < 3; ++c)
        out[c] = _mm512_reduce_add_ps(_mm512_fmadd_ps(a2[c], B2, _mm512_fmadd_ps(a1[c], B1, _mm512_mul_ps(a0[c], B0))));
}}
"""


# the K of each `TERMS_VARIANTS` entry with a 16-lane dot (every one: 80 and 48)
_WIDE_KS = tuple(k for k in (zn._terms_k(*v) for v in zn.TERMS_VARIANTS) if k % 16 == 0)


def _wide_source() -> str:
    src = _FMA_SOURCE.replace("void zh40p_fused_fma(", "void zh42p_fused_wide(", 1)
    call = "                " + zn._FMA_DOT_CALL
    assert src.count(call) == 1 and src.count("typedef void (*dt_fn)") == 1
    args = "(fb + i * K, U + i0 * 3 * K, U + i1 * 3 * K, U + i2 * 3 * K, (1.0f - bu) - bv, bu, bv, t);"
    wide = "".join(f"                if (K == {k}) zh42_dw_{k}{args}\n                else " for k in _WIDE_KS)
    src = src.replace(call, wide + zn._FMA_DOT_CALL, 1)
    return src.replace("typedef void (*dt_fn)", "".join(_wide_dot(k) for k in _WIDE_KS) + "typedef void (*dt_fn)", 1)


# The plane lanes of `_VECTOR_PLANE` grouped by face (zh42p, the wide library only): every distinct face among a
# vector's active samples (plane, facing the camera) reads its corners' u once and broadcasts them over its lanes —
# where zh40p's block broadcasts a pixel only when all its active samples lie on its first sample's face and runs
# the others (21 % of the bench P frame's plane pixels) through the scalar lines one by one. Every sample's value is
# the same expression on the same operands ((u_a w + u_b b_u) + u_c b_v, w = (1 − b_u) − b_v, the clamp keeping NaN)
# and a face or corner out of range counts one failure a sample as the scalar lines do: the same bits.
_PIXEL_FACES = _VECTOR_PLANE[_VECTOR_PLANE.index("                        /* a pixel whose active samples share the face"):
                             _VECTOR_PLANE.index("                        if (ok) {\n                            __m512 xs[3];")]
_FACE_GROUPS = r"""                        /* each distinct face among the active samples: its corners' u read once, broadcast over
                           its lanes (zh42p) */
                        __mmask16 rx = 0;
                        __m512 xr0 = zero, xr1 = zero, xr2 = zero;
                        __m512 ua[3], ub[3], uc[3];
                        for (int c = 0; c < 3; ++c) ua[c] = ub[c] = uc[c] = zero;
                        __mmask16 ok = 0;
                        const __mmask16 badf = act & (__mmask16)~fok;   /* a face out of range: one failure a sample */
                        nb += __builtin_popcount((unsigned)badf);
                        __mmask16 todo = act & fok;
                        while (todo) {
                            const int l = __builtin_ctz((unsigned)todo);
                            const int64_t f = face[q0 + l];
                            const __mmask16 sm = todo & _mm512_cmpeq_epi32_mask(f32, _mm512_set1_epi32((int32_t)f));
                            todo &= (__mmask16)~sm;
                            const int64_t j0 = F[3 * f], j1 = F[3 * f + 1], j2 = F[3 * f + 2];
                            if ((uint64_t)j0 >= (uint64_t)N || (uint64_t)j1 >= (uint64_t)N || (uint64_t)j2 >= (uint64_t)N) {
                                nb += __builtin_popcount((unsigned)sm);
                                continue;
                            }
                            ok |= sm;
                            for (int c = 0; c < 3; ++c) {
                                ua[c] = _mm512_mask_mov_ps(ua[c], sm, _mm512_set1_ps(u[3 * j0 + c]));
                                ub[c] = _mm512_mask_mov_ps(ub[c], sm, _mm512_set1_ps(u[3 * j1 + c]));
                                uc[c] = _mm512_mask_mov_ps(uc[c], sm, _mm512_set1_ps(u[3 * j2 + c]));
                            }
                        }
"""


def _face_groups(src: str) -> str:
    assert src.count(_PIXEL_FACES) == 1
    return src.replace(_PIXEL_FACES, _FACE_GROUPS, 1)


_WIDE_SOURCE = _face_groups(_wide_source())
_WIDE_SIGNATURES = {"zh42p_fused_wide": zn._FUSED_SIGNATURES["zh33p_fused"]}


def available() -> bool:
    """Whether the vector pass can run here: the fused pass's conditions and AVX-512 (`native._avx512_flags`)."""
    return bool(zn._avx512_flags()) and zn.terms_switched_on() and zn._inductor_lanes() in zn.TERMS_LANES


def lib(fma: bool, wide: bool = False):
    """(library, its pass) of the vector plane part — `zh40p_fused_fma` (``fma``: `zh37v_fused`'s dot),
    `zh42p_fused_wide` (``fma`` and ``wide``: that dot in 16-float vectors, zh42p) or `zh40p_fused` (`zh33p_fused`'s)
    — or None (no AVX-512, no compiler, switched off). Not cached here (`native.load` caches the build and reads
    PRTBENCH_COMPILE at each call)."""
    if not available():
        return None
    flags = ("-ffp-contract=off", "-fopenmp", *native.isa_flags(), *zn._avx512_flags())
    if fma and wide:
        lb = zn.load("zh42p_fused_wide", _WIDE_SOURCE, _WIDE_SIGNATURES, extra_flags=flags)
        return None if lb is None else (lb, lb.zh42p_fused_wide)
    if fma:
        lb = zn.load("zh40p_fused_fma", _FMA_SOURCE, _FMA_SIGNATURES, extra_flags=flags)
        return None if lb is None else (lb, lb.zh40p_fused_fma)
    lb = zn.load("zh40p_fused", _SOURCE, _SIGNATURES, extra_flags=flags)
    return None if lb is None else (lb, lb.zh40p_fused)

