"""`native.vertex_table`'s rows with 16-float vectors (session 40, zh40p): the per-vertex table U = v[row] @ W[region]
(n² = 16, C = 240 at the paper configuration) of a VB / VL / VBL / P frame (the referenced rows, ~3.6 K on the
bench creature) by `zh38v_vtable`'s loop — four rows of one region sharing each load of W — with AVX-512 vectors:
4 rows × 32 columns a block (8 accumulators of 16 floats) instead of 4 × 16 (8 of 8). `zh38v_vtable` is bound by
its multiply-adds (16 · 240 a row, ~0.29 ms at 1 thread for 3.6 K rows: ~2 eight-float FMAs a cycle), which
16-float vectors halve on a core with 512-bit FMA units. Every column of every row is the same expression as
`vrow`'s — x[0]·w, then x[j]·w added in j ascending, fused as that library fuses them (the same source text and
``-ffp-contract=fast``) — so the same bits (tests); the columns past the last 32 of a block run 16 at a time,
then `vrow`; rows of other regions and out-of-range rows as `zh38v_vtable` does.

`native.vertex_table`(…, ``wide``=True) runs it where it runs (no compiler, no AVX-512, ``PRTBENCH_ZH_NATIVE=0``:
`zh38v_vtable`, the tests' oracle).
"""
from __future__ import annotations

from methods.core import native
from methods.zh_shadow import native as zn

_VROW32 = r"""
typedef float v16 __attribute__((vector_size(64)));
static inline v16 ld16(const float* p) { v16 v; memcpy(&v, p, 64); return v; }
static inline void st16(float* p, v16 v) { memcpy(p, &v, 64); }

/* `vrow4` with 16-float vectors: rows x0..x3 of one region's table w (n2, C), the columns c < C16 (a multiple of
   16) 32 then 16 at a time; each column the same expression as `vrow`'s */
static inline void vrow4w(const float* x0, const float* x1, const float* x2, const float* x3, const float* w,
                          int64_t n2, int64_t C, int64_t C16, float* o0, float* o1, float* o2, float* o3) {
    int64_t c0 = 0;
    for (; c0 + 32 <= C16; c0 += 32) {
        const v16 wa = ld16(w + c0), wb = ld16(w + c0 + 16);
        v16 a0 = x0[0] * wa, b0 = x0[0] * wb, a1 = x1[0] * wa, b1 = x1[0] * wb;
        v16 a2 = x2[0] * wa, b2 = x2[0] * wb, a3 = x3[0] * wa, b3 = x3[0] * wb;
        for (int64_t j = 1; j < n2; ++j) {
            const v16 ua = ld16(w + j * C + c0), ub = ld16(w + j * C + c0 + 16);
            a0 = a0 + x0[j] * ua; b0 = b0 + x0[j] * ub;
            a1 = a1 + x1[j] * ua; b1 = b1 + x1[j] * ub;
            a2 = a2 + x2[j] * ua; b2 = b2 + x2[j] * ub;
            a3 = a3 + x3[j] * ua; b3 = b3 + x3[j] * ub;
        }
        st16(o0 + c0, a0); st16(o0 + c0 + 16, b0); st16(o1 + c0, a1); st16(o1 + c0 + 16, b1);
        st16(o2 + c0, a2); st16(o2 + c0 + 16, b2); st16(o3 + c0, a3); st16(o3 + c0 + 16, b3);
    }
    for (; c0 < C16; c0 += 16) {
        const v16 wa = ld16(w + c0);
        v16 a0 = x0[0] * wa, a1 = x1[0] * wa, a2 = x2[0] * wa, a3 = x3[0] * wa;
        for (int64_t j = 1; j < n2; ++j) {
            const v16 ua = ld16(w + j * C + c0);
            a0 = a0 + x0[j] * ua; a1 = a1 + x1[j] * ua; a2 = a2 + x2[j] * ua; a3 = a3 + x3[j] * ua;
        }
        st16(o0 + c0, a0); st16(o1 + c0, a1); st16(o2 + c0, a2); st16(o3 + c0, a3);
    }
}
"""


def _source() -> str:
    src = zn._VTABLE4_SOURCE
    head = "/* `zh34p_vtable`, four rows of one region at a time where they are (each thread its contiguous range of i) */"
    call = "                vrow4(v + rows[0] * n2,"
    assert src.count(head) == 1 and src.count(call) == 1 and src.count("void zh38v_vtable(") == 1
    return src.replace(head, _VROW32 + head, 1).replace(call, "                vrow4w(v + rows[0] * n2,", 1) \
        .replace("void zh38v_vtable(", "void zh40p_vtable(", 1)


_SOURCE = _source()
_SIGNATURES = {"zh40p_vtable": zn._VTABLE_SIGNATURES["zh34p_vtable"]}


def lib():
    """The library (`zh40p_vtable`) or None (no AVX-512, no compiler, switched off). Not cached here
    (`native.load` caches the build)."""
    if not zn._avx512_flags() or not zn.terms_switched_on():
        return None
    return zn.load("zh40p_vtable", _SOURCE, _SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=fast", *native.isa_flags(), *zn._avx512_flags()))
