"""Two short C loops (`methods.core.native`), each beside its torch path (the fallback and the test
oracle): the vertices a G-buffer's hit samples reference (`referenced_mask`), and the per-sample
stage of the per-vertex-table shading (`sample_terms`).

The referenced vertices.

A vertex-shaded frame needs the radiance of the vertices the resolve reads alone: the corners of the
faces its hit samples lie on (`ZHShadow._render_vertex`). Marking them is a scatter over the P
samples' faces; torch's ``index_fill_`` / ``bincount`` over a bench G-buffer's 262,144 samples took
0.8–1.6 ms at 1 thread (not vectorised: one indexed store per sample through the generic kernel),
the loop ~0.1 ms — a P frame's saving is the per-vertex work of the front-facing vertices no sample
sees (about half of them on the bench creature)."""
from __future__ import annotations

import ctypes
import functools
import math

import torch
from torch import Tensor

from methods.core import native, sh_native, switches

_SOURCE = r"""
#include <stdint.h>

/* vmark[v] = 1 for each corner v of a face that a hit sample lies on; fmark (M + 1) scratch, zeroed by
   the caller, as vmark (N). face (P,) int64 (a miss: hit 0), hit (P,) uint8, F (M, 3) int64. */
void referenced_vertices(const int64_t *face, const uint8_t *hit, int64_t P, const int64_t *F, int64_t M,
                         uint8_t *fmark, uint8_t *vmark)
{
    for (int64_t p = 0; p < P; p++) {         /* branch-free: a miss or a bad id marks the spare slot M */
        int64_t f = face[p];
        int ok = hit[p] & ((uint64_t)f < (uint64_t)M);
        fmark[ok ? f : M] = 1;
    }
    for (int64_t f = 0; f < M; f++) {
        if (fmark[f]) {
            vmark[F[3 * f]] = 1;
            vmark[F[3 * f + 1]] = 1;
            vmark[F[3 * f + 2]] = 1;
        }
    }
}
"""
_P, _I = ctypes.c_void_p, ctypes.c_int64
_SIGNATURES = {"referenced_vertices": [_P, _P, _I, _P, _I, _P, _P]}


def _kernel():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75)
    lib = native.load("zh_referenced", _SOURCE, _SIGNATURES)
    return None if lib is None else lib.referenced_vertices


def referenced_mask_torch(F: Tensor, face: Tensor, hit: Tensor, N: int) -> Tensor:
    """(N,) bool: the vertices of the faces F (M, 3) that the hit samples (``hit`` (P,) bool) lie on
    (``face`` (P,) their face ids) — torch ops, the oracle of `referenced_mask`."""
    M = int(F.shape[0])
    fm = torch.zeros(M + 1, dtype=torch.bool, device=face.device)
    fm.index_fill_(0, torch.where(hit, face, M), True)
    vm = torch.zeros(N, dtype=torch.bool, device=face.device)
    vm.index_fill_(0, F.to(face.device).long()[fm[:M]].reshape(-1), True)
    return vm


# zh43o: `referenced_vertices` split over the frame's threads (OpenMP; a P frame's serial ~0.2 ms pass over the
# G-buffer's 2 MB of face ids with the caches cold, 1 thread): each thread marks the faces of its samples, then
# of its faces the corners — the marks' stores relaxed atomics (several threads may mark one face or vertex: the
# same 1), so the same mask at any thread count; both mark arrays zeroed in the call (no torch zeros). False:
# `referenced_vertices` (the tests' oracle).
PARALLEL_REFERENCED = True
_PREF_SOURCE = r"""
#include <stdint.h>
#include <string.h>
#include <omp.h>

void zh43o_referenced(const int64_t *face, const uint8_t *hit, int64_t P, const int64_t *F, int64_t M,
                      uint8_t *fmark, uint8_t *vmark, int64_t N, int64_t nt)
{
    memset(fmark, 0, (size_t)(M + 1));
    memset(vmark, 0, (size_t)N);
    #pragma omp parallel num_threads(nt) if(nt > 1)
    {
        #pragma omp for schedule(static)
        for (int64_t p = 0; p < P; p++) {   /* as `referenced_vertices`: a miss or a bad id marks the spare slot M */
            const int64_t f = face[p];
            const int ok = hit[p] & ((uint64_t)f < (uint64_t)M);
            __atomic_store_n(&fmark[ok ? f : M], (uint8_t)1, __ATOMIC_RELAXED);
        }
        #pragma omp for schedule(static)
        for (int64_t f = 0; f < M; f++) {
            if (__atomic_load_n(&fmark[f], __ATOMIC_RELAXED)) {
                __atomic_store_n(&vmark[F[3 * f]], (uint8_t)1, __ATOMIC_RELAXED);
                __atomic_store_n(&vmark[F[3 * f + 1]], (uint8_t)1, __ATOMIC_RELAXED);
                __atomic_store_n(&vmark[F[3 * f + 2]], (uint8_t)1, __ATOMIC_RELAXED);
            }
        }
    }
}
"""
_PREF_SIGNATURES = {"zh43o_referenced": [_P, _P, _I, _P, _I, _P, _P, _I, _I]}
MIN_REFERENCED_SAMPLES_PER_THREAD = 32768


def _pref_lib():
    return load("zh43o_referenced", _PREF_SOURCE, _PREF_SIGNATURES, extra_flags=("-fopenmp",))


def referenced_mask(F: Tensor, face: Tensor, hit: Tensor, N: int) -> Tensor:
    """`referenced_mask_torch` by the C loop when it is available and the arguments suit it (CPU,
    int64 faces and F, a bool hit mask), else by the torch path; the same mask. (zh43o: by the threads'
    loop `zh43o_referenced` where it runs, ``PARALLEL_REFERENCED``.)"""
    pl = _pref_lib() if PARALLEL_REFERENCED else None
    fn = _kernel() if pl is None else pl.zh43o_referenced
    if fn is None or face.device.type != "cpu" or face.dtype != torch.int64 or F.dtype != torch.int64 \
            or hit.dtype != torch.bool or face.dim() != 1 or hit.shape != face.shape or F.dim() != 2 \
            or F.shape[1] != 3 or F.device.type != "cpu":
        return referenced_mask_torch(F, face, hit, N)
    if not (face.is_contiguous() and hit.is_contiguous() and F.is_contiguous()):
        face, hit, F = face.contiguous(), hit.contiguous(), F.contiguous()
    if pl is not None:
        M, P = int(F.shape[0]), int(face.shape[0])
        fm = (ctypes.c_uint8 * (M + 1))()
        vm = torch.empty(N, dtype=torch.bool)
        nt = max(1, min(torch.get_num_threads(), P // MIN_REFERENCED_SAMPLES_PER_THREAD))
        pl.zh43o_referenced(face.data_ptr(), hit.data_ptr(), P, F.data_ptr(), M, ctypes.addressof(fm), vm.data_ptr(),
                            N, nt)
        return vm
    fm = torch.zeros(int(F.shape[0]) + 1, dtype=torch.uint8)
    vm = torch.zeros(N, dtype=torch.bool)
    fn(face.data_ptr(), hit.data_ptr(), int(face.shape[0]), F.data_ptr(), int(F.shape[0]), fm.data_ptr(),
       vm.data_ptr())
    return vm


# --- the per-sample stage of `runtime.sample_terms` --------------------------------------------------
#
# `runtime._sample_block` (Inductor, one call over the Q points with Q symbolic) computes each point's
# K features — monomials of n and of R = reflect(ωo, n) — into a (Q, K) buffer in ~30 separate scalar
# loops with stride-K stores (each feature row its own pass over the points), then the interpolated
# dot Σ_f ((U[v0]·b0 + U[v1]·b1) + U[v2]·b2)[c, f] · feature[f] as 8-lane vectors with AVX2's
# ``vec_reduce_all`` tree. Here one pass per point: the features into a stack array (the same
# products: each monomial one product of the same two values, as `runtime._monomial_rows`' tree),
# then the same lane-wise products, sums and tree — compiled with ``-ffp-contract=off`` (as Inductor's
# kernels: nothing fused into an FMA), so the terms are the compiled kernel's bits (tested). Only for
# float32 and K a multiple of 16 (the order-4 diffuse + specular table: K = 31 + 49 = 80; Inductor's
# masked tail is not reproduced) and where Inductor vectorises for AVX2 (8 lanes: its tree) or AVX-512
# (16 lanes and at::vec's AVX-512 tree — 256-, 128-, 64-, 32-bit shuffles —, each 16-lane vector as two
# 8-float halves under the AVX2 flags: the lanes' arithmetic is the same bits at any width; session 30:
# the bench machine's Inductor picks AVX-512, so the loop had not run there); otherwise
# `runtime._sample_block` runs. Each point is one thread's (OpenMP's team, as `methods.ptt.native`), so
# the bits do not depend on the thread count. Bench creature, paper setting, 37 K object samples of a
# P frame, 1 thread: ~3.2 ms (features ~0.7, the interpolated dot ~2.5: ~150 cycles a point, the
# 3 · 10 eight-lane (U0·b0 + U1·b1 + U2·b2)·f steps at two vector operations a cycle) against ~6–8.5 ms.
def _monomial_code(names: tuple[str, str, str], degrees: tuple[int, ...], tag: str) -> tuple[list[str], list[str]]:
    """C statements computing the monomials of the variables ``names`` = (x, y, z) of each degree in
    ``degrees`` (each >= 1) by `runtime._monomial_rows`' recurrence — level k from level k − 1: x ·
    (each of it), then y · (its last k), then z · (its last one); one product per monomial, of the same
    two values — and their names in `runtime._monos` order, degree by degree."""
    levels = {1: list(names)}
    prev, code = levels[1], []
    for k in range(2, max(degrees) + 1):
        p = len(prev)
        cur = [f"{tag}{k}_{i}" for i in range(p + k + 1)]
        ops = [(t, names[0]) for t in prev] + [(t, names[1]) for t in prev[p - k:]] + [(prev[-1], names[2])]
        code += [f"const float {c} = {u} * {w};" for c, (u, w) in zip(cur, ops)]
        levels[k] = prev = cur
    return code, [t for k in degrees for t in levels[k]]


# The reflection r = 2 (n·ω_o) n − ω_o, normalised as Inductor's kernel does (its maximum: NaN propagates),
# as scalar statements (`_terms_variant`, `_point_terms`) and on 8-float vectors (`_features8`).
_REFLECT = ("const float dn = (nx * wx + ny * wy) + nz * wz;",
            "const float t2 = dn * 2.0f;",
            "const float r0 = t2 * nx - wx, r1 = t2 * ny - wy, r2 = t2 * nz - wz;",
            "float nr = __builtin_sqrtf((r0 * r0 + r1 * r1) + r2 * r2);",
            "nr = (nr != nr) ? nr : (nr > 1e-12f ? nr : 1e-12f);   /* at::vec::maximum: NaN propagates */",
            "const float rx = r0 / nr, ry = r1 / nr, rz = r2 / nr;")
_REFLECT8 = ("const v8 dn = (nx * wx + ny * wy) + nz * wz;",
             "const v8 t2 = dn * 2.0f;",
             "const v8 r0 = t2 * nx - wx, r1 = t2 * ny - wy, r2 = t2 * nz - wz;",
             "v8 nr = __builtin_ia32_sqrtps256((r0 * r0 + r1 * r1) + r2 * r2);",
             "{ const v8i keep = (nr != nr) | (nr > 1e-12f);   /* NaN stays, else max(nr, 1e-12) */",
             "  nr = (v8)(((v8i)nr & keep) | ((v8i)tiny & ~keep)); }",
             "const v8 rx = r0 / nr, ry = r1 / nr, rz = r2 / nr;")


def _feature_code(D: int, dif: bool, spec: bool, reflect: tuple[str, ...] = _REFLECT) -> tuple[list[str], list[str]]:
    """C statements computing one point's features from its normal (nx, ny, nz) and, with ``spec``,
    its ω_o (wx, wy, wz, defined by the caller) — the diffuse monomials of n (degrees D and 1), the
    reflection r = 2 (n·ω_o) n − ω_o normalised as Inductor's kernel does (its maximum: NaN propagates),
    the specular monomials of r (degrees D and D − 1) — and the features' names in `runtime`'s order.
    Shared by `_terms_variant` (rows) and `_point_terms` (one point)."""
    code, feats = [], []
    if dif:
        c, f = _monomial_code(("nx", "ny", "nz"), (D, 1), "a")
        code, feats = code + c, feats + f
    if spec:
        c, f = _monomial_code(("rx", "ry", "rz"), (D, D - 1), "s")
        code = code + list(reflect) + c
        feats += f
    return code, feats


def _terms_variant(D: int, dif: bool, spec: bool, lanes: int = 8) -> str:
    """The C function ``terms_<D>_<dif>_<spec>_<lanes>`` of `_TERMS_SOURCE`: the features of one point
    as straight-line code (`_monomial_code`), stored to a stack array, then the interpolated dot in
    vectors of ``lanes`` floats (8: Inductor's AVX2 kernel, 16: its AVX-512 one) and that ISA's
    ``vec_reduce_all`` tree."""
    code, feats = _feature_code(D, dif, spec)
    if spec:
        code = ["const float wx = woT[q], wy = woT[Q + q], wz = woT[2 * Q + q];"] + code
    K = len(feats)
    assert K % lanes == 0 and lanes in (8, 16)
    body = "\n            ".join(code + [f"f[{i}] = {t};" for i, t in enumerate(feats)])
    if lanes == 8:   # AVX2's vec_reduce_all: halves, lanes two apart, neighbours; + 0
        tree = """const float s0 = a[0] + a[4], s1 = a[1] + a[5], s2 = a[2] + a[6], s3 = a[3] + a[7];
            out[c * Q + q] = 0.0f + ((s0 + s2) + (s1 + s3));"""
    else:            # AVX-512's (at::vec VecReduceAllSIMD): 256-bit, 128-bit, 64-bit, 32-bit shuffles; + 0
        tree = """const v8 w = a + ah[c];   /* the 16 lanes as two 8-lane halves: w[i] = a[i] + a[i + 8] */
            const float x0 = w[0] + w[4], x1 = w[1] + w[5], x2 = w[2] + w[6], x3 = w[3] + w[7];
            out[c * Q + q] = 0.0f + ((x0 + x2) + (x1 + x3));"""
    if lanes == 8:
        dot = f"""v8 acc[3] = {{{{0}}, {{0}}, {{0}}}};
        for (int j = 0; j < {K}; j += 8) {{
            const v8 fj = ld(f + j);
            for (int c = 0; c < 3; ++c) {{
                const int o = c * {K} + j;
                acc[c] = acc[c] + ((ld(u0 + o) * b0 + ld(u1 + o) * b1) + ld(u2 + o) * b2) * fj;
            }}
        }}"""
    else:   # 16 lanes as two 8-float halves (acc: lanes 0–7, ah: lanes 8–15): the same lane arithmetic in
        #     AVX2 registers (GCC's 64-byte generic vectors under the AVX2 flags ran 1.3x slower than Inductor)
        dot = f"""v8 acc[3] = {{{{0}}, {{0}}, {{0}}}}, ah[3] = {{{{0}}, {{0}}, {{0}}}};
        for (int j = 0; j < {K}; j += 16) {{
            const v8 fj = ld(f + j), fh = ld(f + j + 8);
            for (int c = 0; c < 3; ++c) {{
                const int o = c * {K} + j;
                acc[c] = acc[c] + ((ld(u0 + o) * b0 + ld(u1 + o) * b1) + ld(u2 + o) * b2) * fj;
                ah[c] = ah[c] + ((ld(u0 + o + 8) * b0 + ld(u1 + o + 8) * b1) + ld(u2 + o + 8) * b2) * fh;
            }}
        }}"""
    return f"""
static int64_t terms_{D}_{int(dif)}_{int(spec)}_{lanes}(const float* U, int64_t N, const int64_t* vi, const float* b,
        const float* nT, const float* woT, int64_t Q, int64_t q0, int64_t q1, float* out) {{
    int64_t bad = 0;
    for (int64_t q = q0; q < q1; ++q) {{
        float f[{K}] __attribute__((aligned(64)));
        {{
            const float nx = nT[q], ny = nT[Q + q], nz = nT[2 * Q + q];
            {body}
        }}
        const int64_t i0 = vi[3 * q], i1 = vi[3 * q + 1], i2 = vi[3 * q + 2];
        if ((uint64_t)i0 >= (uint64_t)N || (uint64_t)i1 >= (uint64_t)N || (uint64_t)i2 >= (uint64_t)N) {{
            ++bad;
            continue;
        }}
        const float b0 = b[3 * q], b1 = b[3 * q + 1], b2 = b[3 * q + 2];
        const float* u0 = U + i0 * {3 * K};
        const float* u1 = U + i1 * {3 * K};
        const float* u2 = U + i2 * {3 * K};
        {dot}
        for (int c = 0; c < 3; ++c) {{   /* vec_reduce_all of the ISA */
            const v8 a = acc[c];
            {tree}
        }}
    }}
    return bad;
}}
"""


# the (D, diffuse, specular) the C loop has (K a multiple of 16): order 4 with both terms (K = 80),
# order 5 diffuse alone (K = 48)
TERMS_VARIANTS = ((6, True, True), (8, True, False))
# the vector widths (floats) of Inductor's kernels the C loop reproduces: AVX2 (8), AVX-512 (16); the
# C function of variant i at width TERMS_LANES[j] is number j · len(TERMS_VARIANTS) + i
TERMS_LANES = (8, 16)

_TERMS_SOURCE = r"""
#include <stdint.h>
typedef float v8 __attribute__((vector_size(32)));
static inline v8 ld(const float* p) { v8 v; __builtin_memcpy(&v, p, 32); return v; }
""" + "".join(_terms_variant(*v, lanes=w) for w in TERMS_LANES for v in TERMS_VARIANTS) + r"""
typedef int64_t (*terms_fn)(const float*, int64_t, const int64_t*, const float*, const float*, const float*,
                            int64_t, int64_t, int64_t, float*);

/* U (N, 3, K) float32, vi (Q, 3) int64, b (Q, 3), nT / woT (3, Q), out (3, Q); variant an index of
   TERMS_VARIANTS. Every point on nt threads of OpenMP's team (thread k the points [Q k / nt,
   Q (k + 1) / nt)); bad[0] the count of points with a vertex id outside [0, N) (left unwritten). */
void sample_terms(const float* U, int64_t N, const int64_t* vi, const float* b, const float* nT, const float* woT,
                  int64_t Q, int64_t variant, int64_t nt, float* out, int64_t* bad) {
    static const terms_fn fns[] = {""" + ", ".join(f"terms_{D}_{int(d)}_{int(sp)}_{w}" for w in TERMS_LANES
                                                    for D, d, sp in TERMS_VARIANTS) + r"""};
    const terms_fn fn = fns[variant];
    int64_t nb = 0;
    if (nt <= 1) {
        nb = fn(U, N, vi, b, nT, woT, Q, 0, Q, out);
    } else {
#pragma omp parallel for num_threads(nt) schedule(static, 1) reduction(+:nb)
        for (int64_t k = 0; k < nt; ++k)
            nb += fn(U, N, vi, b, nT, woT, Q, Q * k / nt, Q * (k + 1) / nt, out);
    }
    bad[0] = nb;
}
"""
_TERMS_SIGNATURES = {"sample_terms": [_P, _I, _P, _P, _P, _P, _I, _I, _I, _P, _P]}


_LOADED: dict = {}


def load(name: str, source: str, signatures: dict, extra_flags: tuple = ()):
    """`native.load`(name, source, signatures, extra_flags) remembered once it loaded (zh41p): a later call with
    the same source and signatures objects and flags — while ``native.load`` is the same function (a test's spy
    on it sees every call) — is one dict look-up. ``PRTBENCH_COMPILE`` is read at each call (a None met while
    it is off is not kept). `native.load`'s own cache rebuilds its key each call (the signatures as nested
    tuples, the flags): ~8 µs a library with the caches cold, ~10 libraries in a paper-config frame."""
    if not native.compile_enabled():
        return None
    hit = _LOADED.get(name)
    if hit is not None and hit[0] is source and hit[1] is signatures and hit[2] == extra_flags \
            and hit[3] is native.load:
        return hit[4]
    lib = native.load(name, source, signatures, extra_flags=extra_flags)
    if lib is not None:
        _LOADED[name] = (source, signatures, extra_flags, native.load, lib)
    return lib


def switches_on() -> bool:
    """``PRTBENCH_COMPILE`` and ``PRTBENCH_ZH_NATIVE`` both on: read once a frame by a caller of the bound calls
    (`SkinBound`, `PoseSHBound`, zh41p), which do not read them per call (each read ~1 µs warm, ~15 µs as the
    first of a frame with the caches cold)."""
    return native.compile_enabled() and terms_switched_on()


def terms_switched_on() -> bool:
    """False when ``PRTBENCH_ZH_NATIVE`` is 0 / false / no / off: `sample_terms` then returns None
    (the compiled `runtime._sample_block` runs; A/Bs and tests)."""
    return switches.on("PRTBENCH_ZH_NATIVE")


_FLAGS: dict = {}   # (the flags asked for -> with `native.isa_flags`, made once: it asks torch for the CPU each call)


def switched_load(name: str, source: str, signatures: dict, *flags: str):
    """`native.load`(name, source, signatures) built with ``flags`` and the ISA flags (`native.isa_flags`) — or None
    (no compiler, ``PRTBENCH_COMPILE=0``, ``PRTBENCH_ZH_NATIVE=0``). Not cached here (`native.load` caches the
    build; `load` the look-up)."""
    if not terms_switched_on():
        return None
    f = _FLAGS.get(flags)
    if f is None:
        _FLAGS[flags] = f = (*flags, *native.isa_flags())
    return load(name, source, signatures, extra_flags=f)


@functools.lru_cache(maxsize=None)
def _inductor_lanes() -> int | None:
    """The float lanes of Inductor's CPU vectors here — 8 (AVX2) or 16 (AVX-512): the width and
    reduction tree the C loop reproduces — or None (another ISA: its kernel's bits would differ)."""
    try:
        from torch._inductor.cpu_vec_isa import pick_vec_isa

        isa = str(pick_vec_isa()).split()   # ("avx512 avx512_vnni": a VNNI machine's AVX-512, same vectors)
        return {"avx2": 8, "avx512": 16}.get(isa[0]) if isa else None
    except Exception:  # pragma: no cover - another torch
        return None


def _inductor_avx2() -> bool:
    """Whether Inductor vectorises for AVX2 here (8 lanes)."""
    return _inductor_lanes() == 8


def _terms_lib():
    """The library (`methods.core.native.load`, cached there) or None: no compiler, the build failed,
    ``PRTBENCH_COMPILE=0``, or Inductor vectorises for neither AVX2 nor AVX-512 here (its kernel's
    bits would differ)."""
    if _inductor_lanes() not in TERMS_LANES:
        return None
    return native.load("zh_sample_terms", _TERMS_SOURCE, _TERMS_SIGNATURES,
                       extra_flags=("-ffp-contract=off", "-fopenmp", *native.isa_flags()))


def sample_terms(U: Tensor, vi: Tensor, b: Tensor, nT: Tensor, woT: Tensor, D: int, diffuse: bool,
                 specular: bool) -> Tensor | None:
    """(3, Q) = `runtime.rows`(`runtime._sample_block`(U, vi, b, nT, woT, D, diffuse, specular)) by the C
    loop — the same bits — or None where it does not apply (no library, switched off, not float32 /
    CPU, K not a multiple of 8, three vertices per point, a vertex id outside U's rows): the caller
    then runs `runtime._sample_block`. U (N, 3, K); vi (Q, 3) int64, b (Q, 3), nT, woT (3, Q), all
    contiguous."""
    key = (D, bool(diffuse), bool(specular))
    if not terms_switched_on() or key not in TERMS_VARIANTS or U.dim() != 3 or U.dtype != torch.float32 \
            or U.device.type != "cpu":
        return None
    N, C, K = U.shape
    Q = int(nT.shape[1])
    Kf = (((D + 1) * (D + 2) // 2 + 3) if diffuse else 0) + ((D + 1) * (D + 2) // 2 + D * (D + 1) // 2 if specular else 0)
    if C != 3 or K != Kf or vi.shape != (Q, 3) or vi.dtype != torch.int64 or b.shape != (Q, 3) \
            or nT.shape != (3, Q) or woT.shape != (3, Q) \
            or any(t.dtype != torch.float32 or t.device.type != "cpu" for t in (b, nT, woT)):
        return None
    fn = _terms_lib()
    if fn is None:
        return None
    U, vi, b, nT, woT = (t.contiguous() for t in (U, vi, b, nT, woT))
    out = torch.empty(3, Q, dtype=torch.float32)
    bad = torch.zeros(1, dtype=torch.int64)
    fn.sample_terms(U.data_ptr(), N, vi.data_ptr(), b.data_ptr(), nT.data_ptr(), woT.data_ptr(), Q,
                    TERMS_LANES.index(_inductor_lanes()) * len(TERMS_VARIANTS) + TERMS_VARIANTS.index(key),
                    torch.get_num_threads(), out.data_ptr(), bad.data_ptr())
    return None if int(bad[0]) else out


# --- a plane frame's split of the G-buffer (`ZHShadow._render_planes`) ---------------------------------
#
# The plane path splits the samples into the plane's (a mask over the G-buffer, box-filtered in place by
# `method._plane_pixels`) and the others (the object), whose face corners, barycentrics, normals and ωo it
# gathers for `runtime.shade`. In torch that was the compiled match over the P normals, ``nonzero`` of
# its complement, then one ``index_select`` per G-buffer array (and a bool gather, a stack, a (Q, 3) →
# (3, Q) copy): ~8 passes over P or Q elements. Here two passes: `plane_mask` (the match and its two
# counts) and `object_rows` (the complement's positions and rows, written where `runtime.shade` reads
# them). Pure copies and the barycentric weight (1 − u) − v: the same values bit for bit.
_SPLIT_SOURCE = r"""
#include <stdint.h>

/* mask[p] = normal[p] == n0 (float compares of the three components, as `runtime._plane_match`),
   p in [0, P), on nt threads of OpenMP's team (thread k the samples [P k / nt, P (k + 1) / nt));
   cnt[3 k] the matches of thread k, cnt[3 k + 1] those whose region has a specular term (spec (R,)),
   cnt[3 k + 2] the samples whose region is outside [0, R). normal (P, 3) row-major; region (P,).
   hit (P,) or NULL (every sample hits): a miss's region is not read, and a miss that matches counts
   as outside (the caller's torch path then). */
void plane_mask(const float* normal, const float* n0, const int64_t* region, const uint8_t* spec, int64_t R,
                int64_t P, int64_t nt, uint8_t* mask, int64_t* cnt, const uint8_t* hit) {
#pragma omp parallel for num_threads(nt) schedule(static, 1) if(nt > 1)
    for (int64_t k = 0; k < nt; ++k) {
        const float a = n0[0], b = n0[1], c = n0[2];
        int64_t ne = 0, ns = 0, bad = 0;
        for (int64_t p = P * k / nt; p < P * (k + 1) / nt; ++p) {
            const float* n = normal + 3 * p;
            const uint8_t e = (n[0] == a) & (n[1] == b) & (n[2] == c);
            mask[p] = e;
            ne += e;
            const int64_t r = region[p];
            const int ok = (uint64_t)r < (uint64_t)R, h = hit ? hit[p] : 1;
            bad += (!ok & h) | (e & !h);
            ns += e & (ok ? spec[r] : 0);
        }
        cnt[3 * k] = ne;
        cnt[3 * k + 1] = ns;
        cnt[3 * k + 2] = bad;
    }
}

/* The samples p with mask[p] == 0, ascending (Q of them; thread k's range of `plane_mask` starts at
   position start[k] of the output): rest[j] = p, vi[3 j + i] = F[3 face[p] + i], b[3 j ..] =
   ((1 - u) - v, u, v) with u = bary[p bs0], v = bary[p bs0 + bs1], nT[i Q + j] = normal[3 p + i],
   woT[i Q + j] = wo[p ws0 + i ws1], reg[j] = region[p]. bad[k]: thread k's faces outside [0, M). */
void object_rows(const uint8_t* mask, int64_t P, int64_t nt, const int64_t* start, int64_t Q,
                 const int64_t* face, const int32_t* F, int64_t M, const float* bary, int64_t bs0, int64_t bs1,
                 const float* normal, const float* wo, int64_t ws0, int64_t ws1, const int64_t* region,
                 int64_t* rest, int32_t* vi, float* b, float* nT, float* woT, int64_t* reg, int64_t* bad) {
#pragma omp parallel for num_threads(nt) schedule(static, 1) if(nt > 1)
    for (int64_t k = 0; k < nt; ++k) {
        int64_t j = start[k], nb = 0;
        for (int64_t p = P * k / nt; p < P * (k + 1) / nt; ++p) {
            if (mask[p])
                continue;
            int64_t f = face[p];
            if ((uint64_t)f >= (uint64_t)M) {
                ++nb;
                f = 0;
            }
            rest[j] = p;
            vi[3 * j] = F[3 * f];
            vi[3 * j + 1] = F[3 * f + 1];
            vi[3 * j + 2] = F[3 * f + 2];
            const float u = bary[p * bs0], v = bary[p * bs0 + bs1];
            b[3 * j] = (1.0f - u) - v;
            b[3 * j + 1] = u;
            b[3 * j + 2] = v;
            nT[j] = normal[3 * p];
            nT[Q + j] = normal[3 * p + 1];
            nT[2 * Q + j] = normal[3 * p + 2];
            woT[j] = wo[p * ws0];
            woT[Q + j] = wo[p * ws0 + ws1];
            woT[2 * Q + j] = wo[p * ws0 + 2 * ws1];
            reg[j] = region[p];
            ++j;
        }
        bad[k] = nb;
    }
}
"""
_SPLIT_SIGNATURES = {"plane_mask": [_P, _P, _P, _P, _I, _I, _I, _P, _P, _P],
                     "object_rows": [_P, _I, _I, _P, _I, _P, _P, _I, _P, _I, _I, _P, _P, _I, _I, _P,
                                     _P, _P, _P, _P, _P, _P, _P]}


def _split_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75)
    return load("zh_plane_split", _SPLIT_SOURCE, _SPLIT_SIGNATURES, extra_flags=("-fopenmp",))


def split_available() -> bool:
    """True when `plane_mask` / `object_rows` run natively (else `ZHShadow._render_planes`' torch path)."""
    return terms_switched_on() and _split_lib() is not None


def plane_mask(normal: Tensor, n0: Tensor, region: Tensor, spec: Tensor, hit: Tensor | None = None
               ) -> tuple[Tensor, int, int, list[int]] | None:
    """(mask (P,) bool: ``normal`` (P, 3) row-major equals n0 (3,), as `runtime._plane_match`; its count;
    the count of those whose region has a specular term (``spec`` (R,) bool); the per-thread counts of
    the matches, for `object_rows`) by the C loop, or None (not available, not float32 / int64 / CPU
    contiguous arrays, a region outside [0, R)): the caller's torch path then. ``hit`` (P,) bool: the
    misses' regions are not read (a miss that matches: None)."""
    fn = _split_lib() if terms_switched_on() else None
    P = int(normal.shape[0])
    if fn is None or normal.dtype != torch.float32 or normal.shape != (P, 3) or not normal.is_contiguous() \
            or region.dtype != torch.int64 or region.shape != (P,) or not region.is_contiguous() \
            or normal.device.type != "cpu" or region.device.type != "cpu":
        return None
    n0 = n0.to(torch.float32).contiguous()
    sp = spec.to(torch.uint8).contiguous()
    nt = max(1, torch.get_num_threads())
    mask = torch.empty(P, dtype=torch.bool)
    cnt = torch.zeros(nt, 3, dtype=torch.int64)
    if hit is not None and (hit.dtype != torch.bool or hit.shape != (P,) or not hit.is_contiguous()
                            or hit.device.type != "cpu"):
        return None
    vec = _pmask_lib() if VECTOR_PLANE_MASK and sp.dim() == 1 and sp.shape[0] <= 64 else None   # (zh37v)
    (fn.plane_mask if vec is None else vec.zh37v_plane_mask)(
        normal.data_ptr(), n0.data_ptr(), region.data_ptr(), sp.data_ptr(), int(sp.shape[0]), P, nt,
        mask.data_ptr(), cnt.data_ptr(), 0 if hit is None else hit.data_ptr())
    c = cnt.tolist()
    if any(r[2] for r in c):
        return None
    return mask, sum(r[0] for r in c), sum(r[1] for r in c), [r[0] for r in c]


def object_rows(mask: Tensor, per_thread: list[int], face: Tensor, F32: Tensor, bary: Tensor, normal: Tensor,
                wo: Tensor, region: Tensor) -> tuple[Tensor, ...] | None:
    """The samples off ``mask`` (from `plane_mask`, ``per_thread`` its per-thread match counts, at the
    same thread count) and their rows, as `ZHShadow._render_planes`' torch gathers make them: (rest (Q,)
    int64 ascending, vi (Q, 3) int32 = F32[face[rest]], b (Q, 3) = `runtime.barycentrics`(bary[rest]),
    nT, woT (3, Q) = normal[rest]ᵀ, wo[rest]ᵀ, reg (Q,) = region[rest]); None when a face is outside F32's
    rows or an array does not suit the loop (bary, wo (P, 2) / (P, 3) float32 views of any strides)."""
    fn = _split_lib()
    P, nt = int(mask.shape[0]), len(per_thread)
    if fn is None or nt != max(1, torch.get_num_threads()) or face.dtype != torch.int64 or not face.is_contiguous() \
            or F32.dtype != torch.int32 or not F32.is_contiguous() or F32.dim() != 2 or F32.shape[1] != 3 \
            or bary.dtype != torch.float32 or bary.shape != (P, 2) or wo.dtype != torch.float32 or wo.shape != (P, 3):
        return None
    sizes = [(P * (k + 1)) // nt - (P * k) // nt - per_thread[k] for k in range(nt)]
    start = torch.tensor([sum(sizes[:k]) for k in range(nt)], dtype=torch.int64)
    Q = sum(sizes)
    rest = torch.empty(Q, dtype=torch.int64)
    vi = torch.empty(Q, 3, dtype=torch.int32)
    b = torch.empty(Q, 3, dtype=torch.float32)
    nT = torch.empty(3, Q, dtype=torch.float32)
    woT = torch.empty(3, Q, dtype=torch.float32)
    reg = torch.empty(Q, dtype=torch.int64)
    bad = torch.zeros(nt, dtype=torch.int64)
    fn.object_rows(mask.data_ptr(), P, nt, start.data_ptr(), Q, face.data_ptr(), F32.data_ptr(), int(F32.shape[0]),
                   bary.data_ptr(), bary.stride(0), bary.stride(1), normal.data_ptr(), wo.data_ptr(), wo.stride(0),
                   wo.stride(1), region.data_ptr(), rest.data_ptr(), vi.data_ptr(), b.data_ptr(), nT.data_ptr(),
                   woT.data_ptr(), reg.data_ptr(), bad.data_ptr())
    if int(bad.sum()):
        return None
    return rest, vi, b, nT, woT, reg


# --- a new env map's SH (`ZHShadow._lighting`, E frames) -----------------------------------------------
#
# `methods.core.sh.project_latlong_polar` copies the (H, W, 3) float32 map to float64 channel-major
# (0.5 ms at 256 × 512), multiplies it by the (W, 2n) cos/sin factors (one GEMM) and weights the rows
# (an index_select and an einsum): ~2.4 ms at 1 thread on the bench map, about half of an E frame.
# `methods.core.sh_native.project_latlong_polar` (shared with SH PRT) does it in one C pass over the
# float32 texels, float64 sums (float64 round-off).


# Here (session 31) ZH's own pass halves that loop's multiplies: the columns' azimuths φ_w = (w + ½)Δφ
# and φ_{w + W/2} = φ_w + π give cos / sin(m φ) the factor (−1)^m between the two halves of a row, so per
# pair of texels (w, w + W/2) the even-m factors take x_w + x_{w+W/2} and the odd-m ones x_w − x_{w+W/2}:
# W/2 columns of factors, each half as wide (the even-m and odd-m columns of `sh._latlong_polar_factors`'
# B, each padded to whole 4-double vectors), the sums as fused multiply-adds. The same integrals to
# float64 round-off (B's second half is the first's times ±1 up to the round-off of cos / sin there);
# odd widths and orders above 12 take `methods.core.sh_native`'s pass.
_PROJECT_SOURCE = r"""
#include <stdint.h>

/* rows [h0, h1) of the (H, W, 3) float32 map X (W even, half = W / 2): per channel c the column sums
   E[c][j] = sum_{w < half} (X[h, w, c] + X[h, w + half, c]) Bf[w, j] over the NV vectors of the even-m
   columns, O[c][j] = sum (X[h, w, c] - X[h, w + half, c]) Bf[w, VL NV + j] over the NV of the odd-m ones
   (Bf (half, 2 VL NV) float64, VL doubles a vector, each group zero-padded to NV vectors), then
   out[i, c] += T[h, i] G[c][k[i]] (G = E then O). One function per (VL, NV): the accumulators in registers
   (a loop over a run-time count kept them in memory); VL 8 where built with AVX-512 (half the
   instructions when a group fills the vectors). */
#define PROJ_ROWS(NAME, VL, NV)                                                                             \
typedef double NAME##_v __attribute__((vector_size(8 * VL), aligned(8)));                                  \
static void NAME(int64_t h0, int64_t h1, int64_t W, const float *X, const double *Bf, const int64_t *k,      \
                 const double *T, int64_t n2, double *out) {                                               \
    const int64_t half = W / 2;                                                                            \
    for (int64_t h = h0; h < h1; ++h) {                                                                    \
        NAME##_v a[3][2 * NV];                                                                             \
        for (int c = 0; c < 3; ++c)                                                                        \
            for (int v = 0; v < 2 * NV; ++v) a[c][v] = (NAME##_v){0};                                      \
        const float *row = X + h * W * 3, *row2 = row + half * 3;                                          \
        for (int64_t w = 0; w < half; ++w) {                                                               \
            const double x0 = row[3 * w], x1 = row[3 * w + 1], x2 = row[3 * w + 2];                        \
            const double y0 = row2[3 * w], y1 = row2[3 * w + 1], y2 = row2[3 * w + 2];                     \
            const double s0 = x0 + y0, s1 = x1 + y1, s2 = x2 + y2;                                         \
            const double d0 = x0 - y0, d1 = x1 - y1, d2 = x2 - y2;                                         \
            const NAME##_v *b = (const NAME##_v *)(Bf + w * 2 * VL * NV);                                  \
            for (int v = 0; v < NV; ++v) {                                                                 \
                a[0][v] += s0 * b[v]; a[1][v] += s1 * b[v]; a[2][v] += s2 * b[v];                          \
            }                                                                                              \
            for (int v = NV; v < 2 * NV; ++v) {                                                            \
                a[0][v] += d0 * b[v]; a[1][v] += d1 * b[v]; a[2][v] += d2 * b[v];                          \
            }                                                                                              \
        }                                                                                                  \
        double g[3][2 * VL * NV];                                                                          \
        for (int c = 0; c < 3; ++c)                                                                        \
            for (int v = 0; v < 2 * NV; ++v)                                                               \
                for (int l = 0; l < VL; ++l) g[c][VL * v + l] = a[c][v][l];                                \
        const double *t = T + h * n2;                                                                      \
        for (int64_t i = 0; i < n2; ++i) {                                                                 \
            const int64_t j = k[i];                                                                        \
            for (int c = 0; c < 3; ++c) out[3 * i + c] += t[i] * g[c][j];                                  \
        }                                                                                                  \
    }                                                                                                      \
}

PROJ_ROWS(proj_rows4_1, 4, 1)
PROJ_ROWS(proj_rows4_2, 4, 2)
PROJ_ROWS(proj_rows4_3, 4, 3)
#ifdef __AVX512F__
PROJ_ROWS(proj_rows8_1, 8, 1)
PROJ_ROWS(proj_rows8_2, 8, 2)
#endif

/* lanes[0] = 8 when the 8-double rows were built (AVX-512), else 4 */
void zh_project_lanes(int64_t *lanes) {
#ifdef __AVX512F__
    lanes[0] = 8;
#else
    lanes[0] = 4;
#endif
}

/* out (n2, 3) = the sum over the np parts p (in order) of part[p] (np, n2, 3), zeroed by the caller: part
   p's rows [H p / np, H (p + 1) / np) — np fixed by the caller whatever the thread count, the parts shared
   by nt threads: the same bits at any thread count; (vl, nv) Bf's layout (4: nv 1-3, 8: nv 1-2; the caller
   keeps to those) */
void zh_project(int64_t H, int64_t W, const float *X, const double *Bf, int64_t vl, int64_t nv, const int64_t *k,
                const double *T, int64_t n2, double *part, int64_t np, int64_t nt, double *out) {
    void (*rows)(int64_t, int64_t, int64_t, const float *, const double *, const int64_t *, const double *,
                 int64_t, double *) = nv == 1 ? proj_rows4_1 : nv == 2 ? proj_rows4_2 : proj_rows4_3;
#ifdef __AVX512F__
    if (vl == 8) rows = nv == 1 ? proj_rows8_1 : proj_rows8_2;
#endif
    #pragma omp parallel for num_threads(nt) schedule(static) if(nt > 1)
    for (int64_t p = 0; p < np; ++p)
        rows(H * p / np, H * (p + 1) / np, W, X, Bf, k, T, n2, part + p * n2 * 3);
    for (int64_t i = 0; i < n2 * 3; ++i) {
        double s = part[i];
        for (int64_t p = 1; p < np; ++p) s += part[p * n2 * 3 + i];
        out[i] = s;
    }
}
"""
_PROJECT_SIGNATURES = {"zh_project": [_I, _I, _P, _P, _I, _I, _P, _P, _I, _P, _I, _I, _P], "zh_project_lanes": [_P]}


def _project_lib():
    # not cached here (`native.load` caches the build); multiply-adds fused (float64 round-off)
    return native.load("zh_project", _PROJECT_SOURCE, _PROJECT_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=fast", *native.isa_flags(), *_avx512_flags()))


def _avx512_flags() -> tuple[str, ...]:
    """``-mavx512f`` where torch found AVX-512 (the pass then takes 8-double vectors)."""
    return ("-mavx512f",) if native.cpu_capability() == "AVX512" else ()


_LANES: dict = {}


def _project_lanes(lib) -> int:
    """The vector lanes ``lib`` (`_project_lib`) was built for, asked once per library object (zh42l: a tensor and
    a C call in every E frame before)."""
    got = _LANES.get(lib)
    if got is None:
        out = torch.zeros(1, dtype=torch.int64)
        lib.zh_project_lanes(out.data_ptr())
        _LANES[lib] = got = int(out[0])
    return got


@functools.lru_cache(maxsize=8)
def _folded_factors(H: int, W: int, order: int, lanes: int, nv: int) -> tuple[Tensor, Tensor, Tensor]:
    """`sh._latlong_polar_factors` (B (W, 2n), k, T) for `_PROJECT_SOURCE`: B's first W / 2 rows with
    its columns regrouped — those of even m (cos and sin) then those of odd m, each group padded with
    zero columns to ``nv`` vectors of ``lanes`` doubles — as Bf (W / 2, 2 lanes nv) contiguous, k mapped
    to the regrouped columns, T."""
    from methods.core.sh import _latlong_polar_factors

    B, k, T = _latlong_polar_factors(H, W, order, torch.device("cpu"))
    Bf = torch.zeros(W // 2, 2 * lanes * nv, dtype=torch.float64)
    pos = {}
    for parity in (0, 1):
        for a, j in enumerate(j for j in range(2 * order) if (j % order) % 2 == parity):
            Bf[:, parity * lanes * nv + a] = B[:W // 2, j]
            pos[j] = parity * lanes * nv + a
    k2 = torch.tensor([pos[int(j)] for j in k.tolist()], dtype=torch.int64)
    return Bf.contiguous(), k2, T.contiguous()


def project_latlong_polar_folded(image: Tensor, order: int) -> Tensor | None:
    """`methods.core.sh.project_latlong_polar(image, order)` (n², 3) float64 by ZH's C pass over the
    float32 texels with the half-period fold (above; float64 round-off; the same bits at any thread
    count: the parts of `sh_native.row_parts`, as `sh_native`'s pass since session 31), or None where it does not run
    (no compiler, ``PRTBENCH_ZH_NATIVE=0``, not a float32 (H, W, 3) CPU map, W odd, order > 12)."""
    lib = _project_lib() if terms_switched_on() else None
    if (lib is None or image.device.type != "cpu" or image.dtype != torch.float32 or image.dim() != 3
            or image.shape[2] != 3 or image.shape[1] % 2 or image.shape[1] < 2 or order < 1 or 2 * order > 24):
        return None
    H, W, _ = image.shape
    per = -(-order // 2) * 2            # columns of the larger parity group (even m: cos and sin)
    # 8-double vectors where built and a group fills one (order >= 7), else 4
    vl = 8 if _project_lanes(lib) == 8 and per >= 8 else 4
    nv = -(-per // vl)
    Bf, k, T = _folded_factors(int(H), int(W), int(order), vl, nv)
    X = image.contiguous()
    n2 = order * order
    # the row parts fixed by the map's size (their sums in order: the same bits at any thread count)
    np_, nt = sh_native.row_parts(int(H))
    part = torch.zeros(np_, n2, 3, dtype=torch.float64)
    out = torch.empty(n2, 3, dtype=torch.float64)
    lib.zh_project(int(H), int(W), X.data_ptr(), Bf.data_ptr(), vl, nv, k.data_ptr(), T.data_ptr(), n2,
                   part.data_ptr(), np_, nt, out.data_ptr())
    return out


def project_latlong_polar(image: Tensor, order: int) -> Tensor:
    """`methods.core.sh.project_latlong_polar(image, order)` (n², 3) float64 by ZH's folded C pass
    (`project_latlong_polar_folded`), else `methods.core.sh_native`'s C pass, or by that function (the
    oracle) with ``PRTBENCH_ZH_NATIVE=0`` (and wherever neither pass runs: no compiler, not a float32 CPU
    (H, W, 3) map, order > 12)."""
    if not terms_switched_on():
        from methods.core.sh import project_latlong_polar as oracle

        return oracle(image, order)
    out = project_latlong_polar_folded(image, order)
    return sh_native.project_latlong_polar(image, order) if out is None else out


# --- a lighting-only vertex-shaded frame's resolve (`ZHShadow._render_vertex`) ----------------------------
#
# The kept resolve matrix S (`gouraud.resolve_matrix`: per pixel the interpolation weights of its samples'
# face corners, ÷ S²; int32 CSR, `method._int32_csr`) times the (N, 3) vertex radiance. torch's CSR
# product took ~0.6 ms back to back at 1 thread on the bench creature's 65,536 rows and 222 K non-zeros
# (a plain C loop over the CSR rows the same: the rows' lengths — 3 for 71 % of them, 4 for 24 %, up to
# 11 — mispredict every row's loop exit). Here S is packed once, when the matrix is built (`csr_pack`):
# each row's first four entries in a fixed-width (R, 4) table (a shorter row padded with weight 0 at
# column 0), the rest of the longer rows (~5 %) as a CSR tail; the product is one branch-free pass over
# the table and one over the tail, each row's sums in the CSR order (the padding adds a zero: the same
# bits, up to the sign of a zero sum), split over OpenMP's team by rows.
# The packed resolve product (`csr_pack`'s form: four entries a row in col4 / val4, the longer rows' rest in
# the tail CSR trow / tcrow / tcol / tval) of x (N, 3) into out (R, 3), as two worksharing loops of an
# enclosing OpenMP region: one text in `_CSR_SOURCE`'s product and in `_RELIGHTV_SOURCE`'s fused frame
# (the same operations in the same order: the same bits).
_PACKED_PRODUCT_C = r"""#pragma omp for schedule(static)
        for (int64_t r = 0; r < R; ++r) {
            const int32_t *c = col4 + 4 * r;
            const float *w = val4 + 4 * r;
            const float *v0 = x + 3 * (int64_t)c[0], *v1 = x + 3 * (int64_t)c[1];
            const float *v2 = x + 3 * (int64_t)c[2], *v3 = x + 3 * (int64_t)c[3];
            float a0 = 0.f, a1 = 0.f, a2 = 0.f;
            a0 += w[0] * v0[0]; a1 += w[0] * v0[1]; a2 += w[0] * v0[2];
            a0 += w[1] * v1[0]; a1 += w[1] * v1[1]; a2 += w[1] * v1[2];
            a0 += w[2] * v2[0]; a1 += w[2] * v2[1]; a2 += w[2] * v2[2];
            a0 += w[3] * v3[0]; a1 += w[3] * v3[1]; a2 += w[3] * v3[2];
            out[3 * r] = a0; out[3 * r + 1] = a1; out[3 * r + 2] = a2;
        }
#pragma omp for schedule(static)
        for (int64_t t = 0; t < T; ++t) {
            float *o = out + 3 * (int64_t)trow[t];
            float a0 = o[0], a1 = o[1], a2 = o[2];
            for (int32_t e = tcrow[t]; e < tcrow[t + 1]; ++e) {
                const float w = tval[e];
                const float *v = x + 3 * (int64_t)tcol[e];
                a0 += w * v[0]; a1 += w * v[1]; a2 += w * v[2];
            }
            o[0] = a0; o[1] = a1; o[2] = a2;
        }
"""


_CSR_SOURCE = r"""
#include <stdint.h>

/* out[r, c] = (((0 + w0 x[c0, c]) + w1 x[c1, c]) + w2 x[c2, c]) + w3 x[c3, c] over row r's four table
   entries (col4, val4 (R, 4)), rows split over nt threads; then for each tail row trow[t] its entries
   [tcrow[t], tcrow[t+1]) added in order. Columns are checked by the packing (`csr_pack`). */
void zh_ell_rows(int64_t R, const int32_t *col4, const float *val4, const float *x, float *out, int64_t nt,
                 int64_t T, const int32_t *trow, const int32_t *tcrow, const int32_t *tcol, const float *tval) {
#pragma omp parallel num_threads(nt) if(nt > 1)
    {
""" + _PACKED_PRODUCT_C + r"""    }
}

/* `csr_pack`: row r's first four entries (crow, col int64, val) into col4 / val4 (R, 4) (a shorter row
   padded with column 0, weight 0), the rest of tail row t (trow (T,), rows longer than 4) into tcol / tval
   from tcrow[t]; bad[0] = the columns outside [0, N). */
void zh_ell_pack(int64_t R, const int64_t *crow, const int64_t *col, const float *val, int64_t N, int32_t *col4,
                 float *val4, int64_t T, const int32_t *trow, const int32_t *tcrow, int32_t *tcol, float *tval,
                 int64_t *bad) {
    int64_t nb = 0;
    for (int64_t r = 0; r < R; ++r) {
        const int64_t e0 = crow[r], n = crow[r + 1] - e0;
        for (int64_t i = 0; i < 4; ++i) {
            int64_t c = i < n ? col[e0 + i] : 0;
            if ((uint64_t)c >= (uint64_t)N) { ++nb; c = 0; }
            col4[4 * r + i] = (int32_t)c;
            val4[4 * r + i] = i < n ? val[e0 + i] : 0.f;
        }
    }
    for (int64_t t = 0; t < T; ++t) {
        const int64_t r = trow[t];
        for (int64_t e = crow[r] + 4, o = tcrow[t]; e < crow[r + 1]; ++e, ++o) {
            int64_t c = col[e];
            if ((uint64_t)c >= (uint64_t)N) { ++nb; c = 0; }
            tcol[o] = (int32_t)c;
            tval[o] = val[e];
        }
    }
    bad[0] = nb;
}
"""
_CSR_SIGNATURES = {"zh_ell_rows": [_I, _P, _P, _P, _P, _I, _I, _P, _P, _P, _P],
                   "zh_ell_pack": [_I, _P, _P, _P, _I, _P, _P, _I, _P, _P, _P, _P, _P]}
MIN_ROWS_PER_CSR_THREAD = 8192      # resolve rows below which one thread runs the product


def _csr_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75)
    return native.load("zh_ell_rows", _CSR_SOURCE, _CSR_SIGNATURES, extra_flags=("-fopenmp", "-ffp-contract=off"))


def csr_pack(S: Tensor) -> tuple | None:
    """The CSR matrix S (R, N) (int32 or int64 indices, float32 values, CPU) packed for `csr_product`:
    (R, N, col4 (R, 4) int32, val4 (R, 4) float32 — each row's first four entries, padded with (column
    0, weight 0) —, trow (T,) int32 the rows longer than 4, tcrow (T + 1,) int32, tcol, tval their
    remaining entries in order), or None (no C loop here, switched off, another layout / dtype /
    device, a column outside [0, N), N = 0, over 2³¹ entries)."""
    lib = _csr_lib() if terms_switched_on() else None
    if lib is None or S.layout != torch.sparse_csr or S.device.type != "cpu" \
            or S.values().dtype != torch.float32 or S.dim() != 2:
        return None
    R, N = int(S.shape[0]), int(S.shape[1])
    crow, col, val = S.crow_indices().long(), S.col_indices().long().contiguous(), S.values().contiguous()
    nnz = int(col.numel())
    if N == 0 or nnz >= 2 ** 31 - 1 or R >= 2 ** 31 - 1:
        return None
    ln = crow[1:] - crow[:-1]
    trow = (ln > 4).nonzero().squeeze(-1)
    tcrow = torch.zeros(int(trow.numel()) + 1, dtype=torch.int64)
    torch.cumsum(ln.index_select(0, trow) - 4, 0, out=tcrow[1:])
    T, nt_ = int(trow.numel()), int(tcrow[-1])
    col4 = torch.empty(R, 4, dtype=torch.int32)
    val4 = torch.empty(R, 4, dtype=torch.float32)
    trow, tcrow = trow.to(torch.int32), tcrow.to(torch.int32)
    tcol = torch.empty(nt_, dtype=torch.int32)
    tval = torch.empty(nt_, dtype=torch.float32)
    bad = torch.zeros(1, dtype=torch.int64)
    lib.zh_ell_pack(R, crow.data_ptr(), col.data_ptr(), val.data_ptr(), N, col4.data_ptr(), val4.data_ptr(), T,
                    trow.data_ptr(), tcrow.data_ptr(), tcol.data_ptr(), tval.data_ptr(), bad.data_ptr())
    return None if int(bad[0]) else (R, N, col4, val4, trow, tcrow, tcol, tval)


def csr_compact(packed: tuple, idx: Tensor) -> tuple:
    """`csr_pack`'s ``packed`` with its columns renumbered over the rows ``idx`` (Nc,) int64 (distinct
    vertex ids) of a compact x (Nc + 1, 3) whose last row is zero: column j → its position in idx, or Nc
    where j is not in idx — so ``csr_product(csr_compact(packed, idx), cat([xc, 0]))`` = ``csr_product(
    packed, x)`` for x zero off idx and x[idx] = xc, bit for bit (the same products, a zero row read
    where x's row was zero)."""
    R, N, col4, val4, trow, tcrow, tcol, tval = packed
    Nc = int(idx.numel())
    pos = torch.full((N,), Nc, dtype=torch.int32)
    pos.index_copy_(0, idx.to(torch.int64), torch.arange(Nc, dtype=torch.int32))
    return (R, Nc + 1, pos.index_select(0, col4.view(-1).long()).view(R, 4), val4, trow, tcrow,
            pos.index_select(0, tcol.long()), tval)


def csr_product(packed: tuple, x: Tensor) -> Tensor | None:
    """``S @ x`` (R, 3) float32 for S packed by `csr_pack` and x (N, 3) float32 by the C loop — torch's
    CSR product's bits (each row's sums over its entries in order from 0; a zero sum may differ in its
    sign) — or None (not float32 / CPU / (N, 3)): the caller then takes torch's product (the oracle)."""
    R, N, col4, val4, trow, tcrow, tcol, tval = packed
    if x.device.type != "cpu" or x.dtype != torch.float32 or x.shape != (N, 3):
        return None
    lib = _csr_lib()
    if lib is None:   # compilation switched off since the pack
        return None
    x = x.contiguous()
    out = torch.empty(R, 3, dtype=torch.float32)
    nt = max(1, min(torch.get_num_threads(), R // MIN_ROWS_PER_CSR_THREAD))
    lib.zh_ell_rows(R, col4.data_ptr(), val4.data_ptr(), x.data_ptr(), out.data_ptr(), nt, int(trow.numel()),
                    trow.data_ptr(), tcrow.data_ptr(), tcol.data_ptr(), tval.data_ptr())
    return out


# --- a lighting-only frame's plane pass (`ZHShadow._relight_planes`) ------------------------------------
#
# `method._plane_face_pixels` (Inductor) box-filters the plane's samples into their pixels from the
# plane faces' corner table: ~1–2 ms of a ~3 ms paper-setting L frame at 1 thread on the bench creature
# (262,144 samples), plus its compiled call's guards. Here one C pass over the pixels, the kernel's
# expressions in its order (no FMA: `-ffp-contract=off`, as Inductor), so the same bits (tested).
_FACE_PIXELS_SOURCE = r"""
#include <stdint.h>

typedef float v4 __attribute__((vector_size(16)));
typedef int32_t i4 __attribute__((vector_size(16)));

/* out[p, c] = (Σ_s x_s[c]) · inv over the S2 samples s of pixel p (s ascending, from x_0), x_s = 0 where
   face[p, s] < 0, else max(uf[f, c] ((1 − u) − v) + uf[f, 4 + c] u + uf[f, 8 + c] v, 0) (the max if clamp)
   with u = bary[(p S2 + s) bs1], v = bary[bs0 + (p S2 + s) bs1] — the three channels as the lanes 0–2 of
   one 4-float vector (uf (F, 12): each corner's three values and a zero); pixels split over nt threads;
   bad[0] counts faces ≥ F (taken as 0). face (n, S2) int32 contiguous, out (n, 3). */
static inline v4 face_sample(const int32_t *face, const float *bary, int64_t bs0, int64_t bs1, const float *uf,
                             int64_t F, int64_t clamp, int64_t q, int64_t *nb) {
    const v4 zero = {0.f, 0.f, 0.f, 0.f};
    int64_t f = face[q];
    const int32_t on = f >= 0;                       /* branch-free: off the plane reads face 0, masked */
    if (f >= F) { ++*nb; f = 0; }
    f = on ? f : 0;
    const float u = bary[q * bs1], v = bary[bs0 + q * bs1];
    const float w = (1.0f - u) - v;
    const v4 *t = (const v4 *)(uf + 12 * f);
    v4 x = (t[0] * w + t[1] * u) + t[2] * v;
    if (clamp) x = (v4)((i4)x & ~(x < zero));      /* max(x, 0): 0 where x < 0 */
    return (v4)((i4)x & -(i4){on, on, on, on});      /* 0 off the plane */
}

/* out[p] = (Σ_s face_sample(p S2 + s), s ascending) · inv: one pixel of `zh_face_pixels` (also
   `zh35p_relight_pixels`') */
static inline void face_pixel(const int32_t *face, const float *bary, int64_t bs0, int64_t bs1, const float *uf,
                              int64_t F, int64_t clamp, float inv, float *out, int64_t S2, int64_t p, int64_t *nb) {
    v4 o;
    if (S2 == 4) {
        const int64_t q = 4 * p;
        o = face_sample(face, bary, bs0, bs1, uf, F, clamp, q, nb);
        o = o + face_sample(face, bary, bs0, bs1, uf, F, clamp, q + 1, nb);
        o = o + face_sample(face, bary, bs0, bs1, uf, F, clamp, q + 2, nb);
        o = o + face_sample(face, bary, bs0, bs1, uf, F, clamp, q + 3, nb);
    } else {
        o = face_sample(face, bary, bs0, bs1, uf, F, clamp, p * S2, nb);
        for (int64_t s = 1; s < S2; ++s) o = o + face_sample(face, bary, bs0, bs1, uf, F, clamp, p * S2 + s, nb);
    }
    o = o * inv;
    out[3 * p] = o[0]; out[3 * p + 1] = o[1]; out[3 * p + 2] = o[2];
}

void zh_face_pixels(int64_t n, int64_t S2, const int32_t *face, const float *bary, int64_t bs0, int64_t bs1,
                    const float *uf, int64_t F, int64_t clamp, float inv, float *out, int64_t nt, int64_t *bad) {
    int64_t nb = 0;
#pragma omp parallel for num_threads(nt) schedule(static) reduction(+:nb) if(nt > 1)
    for (int64_t p = 0; p < n; ++p)
        face_pixel(face, bary, bs0, bs1, uf, F, clamp, inv, out, S2, p, &nb);
    bad[0] = nb;
}
"""
_FACE_PIXELS_SIGNATURES = {"zh_face_pixels": [_I, _I, _P, _P, _I, _I, _P, _I, _I, ctypes.c_float, _P, _I, _P]}
MIN_PIXELS_PER_THREAD = 8192        # pixels below which one thread runs the plane pass


def _face_pixels_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75)
    return native.load("zh_face_pixels", _FACE_PIXELS_SOURCE, _FACE_PIXELS_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", *native.isa_flags()))


def face_pixels(face: Tensor, bary: Tensor, uf: Tensor, clamp: bool) -> Tensor | None:
    """`method._plane_face_pixels(face, bary, uf, clamp)` (n, 3) by the C loop — the same bits — or None
    where it does not run (no compiler, ``PRTBENCH_ZH_NATIVE=0``, not float32 / int32 / CPU, a face
    outside uf's rows): the caller then runs the compiled pass. face (n, S²) int32 (−1: no plane
    sample), bary (2, n, S²) (u, v) with any strides of the form (bs0, S² bs1, bs1), uf (F_p, 9)."""
    lib = _face_pixels_lib() if terms_switched_on() else None
    if (lib is None or face.dtype != torch.int32 or face.dim() != 2 or bary.dtype != torch.float32
            or uf.dtype != torch.float32 or uf.dim() != 2 or uf.shape[1] != 9 or uf.shape[0] == 0
            or any(t.device.type != "cpu" for t in (face, bary, uf))):
        return None
    n, S2 = int(face.shape[0]), int(face.shape[1])
    if bary.shape != (2, n, S2) or bary.stride(1) != S2 * bary.stride(2):
        return None
    face = face.contiguous()
    u12 = torch.zeros(int(uf.shape[0]), 3, 4, dtype=torch.float32)   # (each corner's 3 values + a zero lane)
    u12[:, :, :3] = uf.view(-1, 3, 3)
    out = torch.empty(n, 3, dtype=torch.float32)
    bad = torch.zeros(1, dtype=torch.int64)
    nt = max(1, min(torch.get_num_threads(), n // MIN_PIXELS_PER_THREAD))
    lib.zh_face_pixels(n, S2, face.data_ptr(), bary.data_ptr(), bary.stride(0), bary.stride(2), u12.data_ptr(),
                       int(uf.shape[0]), int(bool(clamp)), 1.0 / S2, out.data_ptr(), nt, bad.data_ptr())
    return None if int(bad[0]) else out


# --- a P / V frame's plane pass (`method._plane_pixels`) ------------------------------------------------
#
# The plane samples of a frame that is not lighting-only (a new camera or pose: no kept plane faces) go
# straight from the G-buffer into the pixels by the compiled `method._plane_pixels` (~2.3 ms of a ~10 ms
# paper-setting V frame on the bench creature at 1 thread, session 30's profile). Here the same per-sample
# expressions in one C loop over the pixels: the n·ωo test as ((nx ωx + ny ωy) + nz ωz) > 0 and the plane
# mask, the face's three corner vertices, (u0 ((1 − bu) − bv) + u1 bu) + u2 bv per channel, 0 off the plane
# or facing away, the clamp, the samples summed in order from the first and scaled by 1 / S² — pure
# elementwise float32 (``-ffp-contract=off``), so the compiled pass's bits (tested); a sample off the plane
# reads nothing else. Each pixel one thread's: the bits do not depend on the thread count.
# One plane sample (zh35p): its front test n·ωo, its face's three corner values of u interpolated at its
# barycentrics (Gouraud) and the clamp — included by both plane passes that read the G-buffer (`zh_plane_pixels`
# and `zh33p_fused`), which wrote these lines twice. Elementwise float32 (both built with ``-ffp-contract=off``):
# the same bits in either.
_PLANE_SAMPLE_C = r"""
/* n·ωo of sample q: ((n_x ωx + n_y ωy) + n_z ωz), normal (P, 3) row-major, ωo rows ws0 apart */
static inline float zh_plane_dn(const float *nrm, const float *wo, int64_t ws0, int64_t q) {
    return (nrm[3 * q] * wo[q] + nrm[3 * q + 1] * wo[ws0 + q]) + nrm[3 * q + 2] * wo[2 * ws0 + q];
}

/* x[c] = (u[i0, c] ((1 − bu) − bv) + u[i1, c] bu) + u[i2, c] bv (max(·, 0) if clamp; NaN stays NaN) with
   bu = bary[q bs1], bv = bary[bs0 + q bs1]; returns 1 (x untouched) when a corner is outside [0, N) */
static inline int zh_plane_sample(const float *u, int64_t N, int64_t i0, int64_t i1, int64_t i2, const float *bary,
                                  int64_t bs0, int64_t bs1, int64_t q, int64_t clamp, float *x) {
    if ((uint64_t)i0 >= (uint64_t)N || (uint64_t)i1 >= (uint64_t)N || (uint64_t)i2 >= (uint64_t)N)
        return 1;
    const float bu = bary[q * bs1], bv = bary[bs0 + q * bs1];
    const float w = (1.0f - bu) - bv;
    const float *a = u + 3 * i0, *b = u + 3 * i1, *c = u + 3 * i2;
    float x0 = (a[0] * w + b[0] * bu) + c[0] * bv;
    float x1 = (a[1] * w + b[1] * bu) + c[1] * bv;
    float x2 = (a[2] * w + b[2] * bu) + c[2] * bv;
    if (clamp) {   /* clamp_min(0): NaN stays NaN */
        x0 = x0 < 0.f ? 0.f : x0;
        x1 = x1 < 0.f ? 0.f : x1;
        x2 = x2 < 0.f ? 0.f : x2;
    }
    x[0] = x0; x[1] = x1; x[2] = x2;
    return 0;
}
"""
_PLANE_PIXELS_SOURCE = r"""
#include <stdint.h>
""" + _PLANE_SAMPLE_C + r"""

/* out[p, c] = (Σ_s x_s[c]) · inv over the S2 samples q = p S2 + s of pixel p (s ascending, from x_0);
   x_s = 0 unless mask[q] and (n[q, 0] wo[q] + n[q, 1] wo[ws0 + q]) + n[q, 2] wo[2 ws0 + q] > 0, else
   (u[i0, c] ((1 − bu) − bv) + u[i1, c] bu) + u[i2, c] bv (max(·, 0) if clamp) with i_k = fv[k M + face[q]],
   bu = bary[q bs1], bv = bary[bs0 + q bs1]; pixels split over nt threads; bad[0] counts plane samples
   whose face is outside [0, M) or whose corner is outside [0, N) (their x taken as 0). */
void zh_plane_pixels(int64_t n, int64_t S2, const int64_t *face, const float *bary, int64_t bs0, int64_t bs1,
                     const float *nrm, const float *wo, int64_t ws0, const uint8_t *mask, const int64_t *fv,
                     int64_t M, const float *u, int64_t N, int64_t clamp, float inv, float *out, int64_t nt,
                     int64_t *bad) {
    int64_t nb = 0;
#pragma omp parallel for num_threads(nt) schedule(static) reduction(+:nb) if(nt > 1)
    for (int64_t p = 0; p < n; ++p) {
        float o0 = 0.f, o1 = 0.f, o2 = 0.f;
        for (int64_t s = 0; s < S2; ++s) {
            const int64_t q = p * S2 + s;
            float x[3] = {0.f, 0.f, 0.f};
            if (mask[q] && zh_plane_dn(nrm, wo, ws0, q) > 0.f) {
                const int64_t f = face[q];
                if ((uint64_t)f >= (uint64_t)M
                        || zh_plane_sample(u, N, fv[f], fv[M + f], fv[2 * M + f], bary, bs0, bs1, q, clamp, x))
                    ++nb;
            }
            if (s == 0) { o0 = x[0]; o1 = x[1]; o2 = x[2]; }
            else { o0 = o0 + x[0]; o1 = o1 + x[1]; o2 = o2 + x[2]; }
        }
        out[3 * p] = o0 * inv; out[3 * p + 1] = o1 * inv; out[3 * p + 2] = o2 * inv;
    }
    bad[0] = nb;
}
"""
_PLANE_PIXELS_SIGNATURES = {"zh_plane_pixels": [_I, _I, _P, _P, _I, _I, _P, _P, _I, _P, _P, _I, _P, _I, _I,
                                                ctypes.c_float, _P, _I, _P]}


def _plane_pixels_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75)
    return native.load("zh_plane_pixels", _PLANE_PIXELS_SOURCE, _PLANE_PIXELS_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", *native.isa_flags()))


def plane_pixels(face: Tensor, bary: Tensor, normal: Tensor, wo: Tensor, mask: Tensor, fv: Tensor, u: Tensor,
                 clamp: bool) -> Tensor | None:
    """`method._plane_pixels(face, bary, normal, wo, mask, fv, u, clamp)` (n, 3) by the C loop — the same
    bits — or None where it does not run (no compiler, ``PRTBENCH_ZH_NATIVE=0``, not float32 / int64 /
    CPU, other layouts, a plane sample's face or corner out of range): the caller then runs the compiled
    pass. face (n, S²) int64 contiguous, bary (2, n, S²) with strides (bs0, S² bs1, bs1), normal (n, S², 3)
    contiguous, wo (3, n, S²) with strides (ws0, S², 1), mask (n, S²) bool contiguous, fv (3, M) int64
    contiguous, u (N, 3) float32."""
    lib = _plane_pixels_lib() if terms_switched_on() else None
    if lib is None or face.dim() != 2:
        return None
    n, S2 = int(face.shape[0]), int(face.shape[1])
    if (face.dtype != torch.int64 or fv.dtype != torch.int64 or mask.dtype != torch.bool
            or any(t.dtype != torch.float32 for t in (bary, normal, wo, u))
            or any(t.device.type != "cpu" for t in (face, bary, normal, wo, mask, fv, u))
            or bary.shape != (2, n, S2) or bary.stride(1) != S2 * bary.stride(2)
            or normal.shape != (n, S2, 3) or not normal.is_contiguous()
            or wo.shape != (3, n, S2) or wo.stride(1) != S2 or wo.stride(2) != 1
            or mask.shape != (n, S2) or fv.dim() != 2 or fv.shape[0] != 3 or u.dim() != 2 or u.shape[1] != 3):
        return None
    face, mask, fv, u = face.contiguous(), mask.contiguous(), fv.contiguous(), u.contiguous()
    out = torch.empty(n, 3, dtype=torch.float32)
    bad = torch.zeros(1, dtype=torch.int64)
    nt = max(1, min(torch.get_num_threads(), n // MIN_PIXELS_PER_THREAD))
    lib.zh_plane_pixels(n, S2, face.data_ptr(), bary.data_ptr(), bary.stride(0), bary.stride(2), normal.data_ptr(),
                        wo.data_ptr(), wo.stride(0), mask.data_ptr(), fv.data_ptr(), int(fv.shape[1]), u.data_ptr(),
                        int(u.shape[0]), int(bool(clamp)), 1.0 / S2, out.data_ptr(), nt, bad.data_ptr())
    return None if int(bad[0]) else out


# --- a lighting-only frame's object samples (`ZHShadow._relight_planes`) ----------------------------------
#
# Per region the cached transfer of the samples off the plane, td and ts (n², Q) (`runtime.relight_cache`),
# was shaded by two small GEMMs — (l ⊙ kd)ᵀ td + (l ⊙ ks)ᵀ ts, (3, n²) @ (n², Q) — a clamp, and three
# ``index_add_`` into the pixels (one per channel): ~1.5–2 ms of a ~3 ms paper-setting L frame on the bench
# creature (37 K object samples, 1 thread), for ~4.7 MB of transfer read. Here one C pass over the samples,
# 512 at a time (each of the 2n² rows' 512 values one contiguous run of 8-float vectors), the sums over i
# ascending (the GEMM's order is the BLAS's: float32 round-off against it), then clamp and the samples'
# pixels in order.
_RELIGHT_SOURCE = r"""
#include <stdint.h>

typedef float v8 __attribute__((vector_size(32), aligned(4)));

enum { CH = 512, NB = CH / 8 };

/* acc[c][j] = Σ_i l[i, c] x[i Q + 8 j + b] (lane b), i ascending: one table's sums over the CH samples from x
   on (each of its n2 rows' CH values one contiguous run) */
static inline void accumulate_block(v8 acc[3][NB], const float *x, const float *l, int64_t n2, int64_t Q) {
    for (int64_t c = 0; c < 3; ++c)
        for (int64_t j = 0; j < NB; ++j) acc[c][j] = (v8){0};
    for (int64_t i = 0; i < n2; ++i) {
        const float *xi = x + i * Q;
        const float l0 = l[3 * i], l1 = l[3 * i + 1], l2 = l[3 * i + 2];
        for (int64_t j = 0; j < NB; ++j) {
            const v8 xv = *(const v8 *)(xi + 8 * j);
            acc[0][j] += l0 * xv; acc[1][j] += l1 * xv; acc[2][j] += l2 * xv;
        }
    }
}

/* the same sums for the one sample at x (the tail of a range shorter than CH) */
static inline void accumulate_one(float r[3], const float *x, const float *l, int64_t n2, int64_t Q) {
    float r0 = 0.f, r1 = 0.f, r2 = 0.f;
    for (int64_t i = 0; i < n2; ++i) {
        const float xi = x[i * Q];
        r0 += l[3 * i] * xi; r1 += l[3 * i + 1] * xi; r2 += l[3 * i + 2] * xi;
    }
    r[0] = r0; r[1] = r1; r[2] = r2;
}

/* img[pix[q], c] += max(Σ_i ld[i, c] td[i, q] + Σ_i ls[i, c] ts[i, q], 0) · inv (the max if clamp; no ts
   term when ts is NULL), q ascending; td, ts (n2, Q) row-major, ld, ls (n2, 3); bad[0] counts pixels
   outside [0, npix) (skipped). */
static int64_t relight_range(int64_t qa, int64_t qb, int64_t Q, int64_t n2, const float *td, const float *ts,
                             const float *ld, const float *ls, const int64_t *pix, int64_t clamp, float inv,
                             float *img, int64_t npix) {
    int64_t nb = 0;
    int64_t q0 = qa;
    /* CH samples at a time: each row's CH values read as one contiguous run (a per-sample pass over the
       2 n2 rows Q floats apart read 32 streams at once: slower than the GEMMs from a cold cache) */
    v8 d[3][NB], sp[3][NB];
    for (; q0 + CH <= qb; q0 += CH) {
        accumulate_block(d, td + q0, ld, n2, Q);
        if (ts) {
            accumulate_block(sp, ts + q0, ls, n2, Q);
            for (int64_t c = 0; c < 3; ++c)
                for (int64_t j = 0; j < NB; ++j) d[c][j] += sp[c][j];
        }
        for (int64_t j = 0; j < NB; ++j)
            for (int64_t b = 0; b < 8; ++b) {
                const int64_t p = pix[q0 + 8 * j + b];
                if ((uint64_t)p >= (uint64_t)npix) { ++nb; continue; }
                float r0 = d[0][j][b], r1 = d[1][j][b], r2 = d[2][j][b];
                if (clamp) { r0 = r0 < 0.f ? 0.f : r0; r1 = r1 < 0.f ? 0.f : r1; r2 = r2 < 0.f ? 0.f : r2; }
                float *o = img + 3 * p;
                o[0] += r0 * inv; o[1] += r1 * inv; o[2] += r2 * inv;
            }
    }
    for (int64_t q = q0; q < qb; ++q) {
        float r[3], s[3];
        accumulate_one(r, td + q, ld, n2, Q);
        if (ts) {
            accumulate_one(s, ts + q, ls, n2, Q);
            r[0] += s[0]; r[1] += s[1]; r[2] += s[2];
        }
        float r0 = r[0], r1 = r[1], r2 = r[2];
        const int64_t p = pix[q];
        if ((uint64_t)p >= (uint64_t)npix) { ++nb; continue; }
        if (clamp) { r0 = r0 < 0.f ? 0.f : r0; r1 = r1 < 0.f ? 0.f : r1; r2 = r2 < 0.f ? 0.f : r2; }
        float *o = img + 3 * p;
        o[0] += r0 * inv; o[1] += r1 * inv; o[2] += r2 * inv;
    }
    return nb;
}

/* the samples [start[t], start[t + 1]) on thread t of nt (the caller splits between pixels: each pixel's
   samples are one thread's, added in order) */
void zh_relight_add(int64_t Q, int64_t n2, const float *td, const float *ts, const float *ld, const float *ls,
                    const int64_t *pix, int64_t clamp, float inv, float *img, int64_t npix, const int64_t *start,
                    int64_t nt, int64_t *bad) {
    int64_t nb = 0;
#pragma omp parallel for num_threads(nt) schedule(static, 1) reduction(+:nb) if(nt > 1)
    for (int64_t t = 0; t < nt; ++t)
        nb += relight_range(start[t], start[t + 1], Q, n2, td, ts, ld, ls, pix, clamp, inv, img, npix);
    bad[0] = nb;
}
"""
_RELIGHT_SIGNATURES = {"zh_relight_add": [_I, _I, _P, _P, _P, _P, _P, _I, ctypes.c_float, _P, _I, _P, _I, _P]}
MIN_SAMPLES_PER_RELIGHT_THREAD = 8192   # object samples below which one thread shades them


def _relight_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75)
    return native.load("zh_relight_add", _RELIGHT_SOURCE, _RELIGHT_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", *native.isa_flags()))


def relight_add(img: Tensor, td: Tensor, ts: Tensor | None, ld: Tensor, ls: Tensor | None, pix: Tensor, clamp: bool,
                inv: float) -> bool:
    """img (n, 3) += max(ldᵀ td + lsᵀ ts, 0) · inv at the pixels pix (Q,) int64 ascending (``ZHShadow._relight_planes``'
    GEMMs, clamp and ``index_add_``; float32 round-off against the GEMMs) by one C pass (split over OpenMP's
    team between pixels: the same bits at any thread count); False (nothing
    done) where it does not run (no compiler, ``PRTBENCH_ZH_NATIVE=0``, not float32 / CPU contiguous
    arrays of these shapes, a pixel outside img: its row is skipped, the caller redoes the frame's terms
    by torch — it is only checked here). td, ts (n², Q); ld, ls (n², 3) = l ⊙ kd, l ⊙ ks."""
    lib = _relight_lib() if terms_switched_on() else None
    if lib is None or td.dim() != 2:
        return False
    n2, Q = int(td.shape[0]), int(td.shape[1])
    arrs = (img, td, ld) + ((ts, ls) if ts is not None else ())
    if (any(t.dtype != torch.float32 or t.device.type != "cpu" or not t.is_contiguous() for t in arrs)
            or pix.dtype != torch.int64 or pix.shape != (Q,) or not pix.is_contiguous() or pix.device.type != "cpu"
            or img.dim() != 2 or img.shape[1] != 3 or ld.shape != (n2, 3)
            or (ts is not None and (ts.shape != (n2, Q) or ls is None or ls.shape != (n2, 3)))):
        return False
    if Q and (int(pix.min()) < 0 or int(pix.max()) >= int(img.shape[0])):
        return False
    bad = torch.zeros(1, dtype=torch.int64)
    nt = max(1, min(torch.get_num_threads(), Q // MIN_SAMPLES_PER_RELIGHT_THREAD))
    cuts = [0]
    for t in range(1, nt):   # thread t from Q t / nt on, moved past the samples of the pixel there
        c = max(Q * t // nt, cuts[-1])
        while 0 < c < Q and int(pix[c]) == int(pix[c - 1]):
            c += 1
        cuts.append(c)
    cuts.append(Q)
    start = torch.tensor(cuts, dtype=torch.int64)
    lib.zh_relight_add(Q, n2, td.data_ptr(), 0 if ts is None else ts.data_ptr(), ld.data_ptr(),
                       0 if ts is None else ls.data_ptr(), pix.data_ptr(), int(bool(clamp)), float(inv),
                       img.data_ptr(), int(img.shape[0]), start.data_ptr(), nt, bad.data_ptr())
    return True


# --- `runtime.first_plane`'s candidate screening ------------------------------------------------------------
#
# `runtime.first_plane` screens 8 candidate normals on every 16th point (a strided copy, then per candidate
# three compares, two ands, a sum and its ``int``: ~60 small ops, ~0.3 ms at 1 thread whatever the size)
# — run twice by a plane frame's split (`ZHShadow._native_split`: over the G-buffer, then over the
# object's samples for a second plane). Here the 8 screened counts in one C pass (the same float compares).
_SCREEN_SOURCE = r"""
#include <stdint.h>

/* cnt[c] = #{j = 0, 16, 32, … < m : x[j s1] == x[k s1], y … , z …} for the candidates k = c m / 8, c < 8
   (x, y, z = base, base + s0, base + 2 s0: the three components; strides in floats). */
void zh_screen(const float *base, int64_t s0, int64_t s1, int64_t m, int64_t *cnt) {
    for (int64_t c = 0; c < 8; ++c) {
        const int64_t k = c * m / 8;
        const float a = base[k * s1], b = base[s0 + k * s1], d = base[2 * s0 + k * s1];
        int64_t n = 0;
        for (int64_t j = 0; j < m; j += 16)
            n += (base[j * s1] == a) & (base[s0 + j * s1] == b) & (base[2 * s0 + j * s1] == d);
        cnt[c] = n;
    }
}
"""
_SCREEN_SIGNATURES = {"zh_screen": [_P, _I, _I, _I, _P]}


def _screen_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75)
    return native.load("zh_screen", _SCREEN_SOURCE, _SCREEN_SIGNATURES)


def screen_counts(cur: Tensor) -> list[int] | None:
    """`runtime.first_plane`'s 8 screened counts of the normals cur (3, m) (any strides, float32, CPU):
    for candidate c (the normal of point c·m // 8) the points j = 0, 16, 32, … equal to it componentwise —
    or None where the C pass does not run (the caller screens by torch)."""
    lib = _screen_lib() if terms_switched_on() else None
    if lib is None or cur.dtype != torch.float32 or cur.device.type != "cpu" or cur.dim() != 2 or cur.shape[0] != 3 \
            or cur.shape[1] == 0:
        return None
    cnt = torch.zeros(8, dtype=torch.int64)
    lib.zh_screen(cur.data_ptr(), cur.stride(0), cur.stride(1), int(cur.shape[1]), cnt.data_ptr())
    return cnt.tolist()


# --- `runtime.zonal_conjugate` of the specular term as one C pass -------------------------------------------
#
# The conjugation helpers shared by the order-8 C sources (`_CONJ_SOURCE`, `_VIEW_SOURCE`; zh34v: one
# string both translation units start with, instead of two copies): 16-lane float vectors, the z
# rotation, X by its gathered terms, the angle rows and the polar angles' rows.
_CONJ_HELPERS = r"""
#include <stdint.h>
#include <string.h>
#include <math.h>

#define L 16
#define MAXN 8
#define MAXN2 (MAXN * MAXN)
typedef float vf __attribute__((vector_size(4 * L)));

static inline vf vsqrt(vf x) { vf r; for (int l = 0; l < L; ++l) r[l] = sqrtf(x[l]); return r; }

/* z rotation of the rows a (n2) into o: o[r] = a[r] C[|m|] + a[perm r] (S[|m|] sg[r]). */
static inline void rz(int64_t n2, const vf *a, const vf *C, const vf *S, const int64_t *perm, const int64_t *absm,
                      const float *sg, vf *o) {
    for (int64_t r = 0; r < n2; ++r)
        o[r] = a[r] * C[absm[r]] + a[perm[r]] * (S[absm[r]] * sg[r]);
}

/* o[r] = sum_j t[idx[r, j]] w[r, j], j = 0..k-1 in order (X or its transpose by its gathered terms). */
static inline void gx(int64_t n2, int64_t k, const vf *t, const int64_t *idx, const float *w, vf *o) {
    for (int64_t r = 0; r < n2; ++r) {
        vf s = t[idx[r * k]] * w[r * k];
        for (int64_t j = 1; j < k; ++j) s = s + t[idx[r * k + j]] * w[r * k + j];
        o[r] = s;
    }
}

/* Angle rows cos(m a), sin(m a), m < n, of cos a = c, sin a = s (the Chebyshev recurrence of `_angle_rows`). */
static inline void angles(int64_t n, vf c, vf s, vf *C, vf *S) {
    const vf one = (vf){0} + 1.0f, zero = (vf){0};
    C[0] = one; S[0] = zero;
    if (n > 1) { C[1] = c; S[1] = s; }
    for (int64_t m = 2; m < n; ++m) {
        C[m] = C[m - 1] * c - S[m - 1] * s;
        S[m] = S[m - 1] * c + C[m - 1] * s;
    }
}

/* The polar angles' rows of the unit vectors (R0, R1, R2) (`_polar`: phi = 0 on the pole). */
static inline void polar_rows(int64_t n, vf R0, vf R1, vf R2, vf *Cp, vf *Sp, vf *Ct, vf *St) {
    vf z, cp, sp;
    const vf rho = vsqrt(R0 * R0 + R1 * R1);
    for (int l = 0; l < L; ++l) {
        z[l] = R2[l] < -1.0f ? -1.0f : (R2[l] > 1.0f ? 1.0f : R2[l]);
        const int ok = rho[l] > 1e-20f;
        const float safe = ok ? rho[l] : 1.0f;
        cp[l] = ok ? R0[l] / safe : 1.0f;
        sp[l] = ok ? R1[l] / safe : 0.0f;
    }
    angles(n, cp, sp, Cp, Sp);
    angles(n, z, rho, Ct, St);
}
/* The blocks of a plan's product: u[i] = sum_j K[i - r0, j] t[ci[j]], ci[j] = cols ? cols[c0 + j] : c0 + j, for
   the nb blocks (r0, r1, c0, c1) of spans, their values K concatenated (each (r1 - r0, c1 - c0) row-major).
   Each row's sum in j order with multiply-adds fused (the same operations as one row at a time), BROWS
   rows at a time: independent chains in flight instead of one dependent chain of c1 - c0 per row
   (-DBROWS=1: one row at a time, the loop before session 34: tests). */
#ifndef BROWS
#define BROWS 4
#endif
static inline void block_products(int64_t nb, const int64_t *spans, const float *K, const vf *t, const int64_t *cols,
                                  vf *u) {
    int64_t ci[MAXN2];
    for (int64_t b = 0; b < nb; ++b) {
        const int64_t r0 = spans[4 * b], r1 = spans[4 * b + 1], c0 = spans[4 * b + 2], c1 = spans[4 * b + 3];
        const int64_t wd = c1 - c0;
        for (int64_t j = 0; j < wd; ++j) ci[j] = cols ? cols[c0 + j] : c0 + j;
        int64_t i = r0;
#if BROWS > 1
        for (; i + BROWS <= r1; i += BROWS, K += BROWS * wd) {
            vf s[BROWS];
            const vf x = t[ci[0]];
            for (int q = 0; q < BROWS; ++q) s[q] = x * K[q * wd];
            for (int64_t j = 1; j < wd; ++j) {
                const vf y = t[ci[j]];
                for (int q = 0; q < BROWS; ++q) s[q] = s[q] + y * K[q * wd + j];
            }
            for (int q = 0; q < BROWS; ++q) u[i + q] = s[q];
        }
#endif
        for (; i < r1; ++i, K += wd) {
            vf s = t[ci[0]] * K[0];
            for (int64_t j = 1; j < wd; ++j) s = s + t[ci[j]] * K[j];
            u[i] = s;
        }
    }
}
"""

# A vertex-shaded view frame's t_s (`runtime.specular_parts`) was the reflection directions (`reflect_T`,
# ~8 small ops over index-selected copies of n and ωo), the compiled angle tables (`_zyz_angle_tables`),
# the first compiled half (`_zyz_down`), the block products (`_blocked_product`: one GEMM per block) and
# the second compiled half (`_zyz_up`): ~5 separate passes over (n², Q) arrays and ~10 dispatches,
# 3.5 of a ~7 ms order-8 V frame (bench creature, 1 thread, process CPU). Here the same maths for
# 16 points at a time, each point's rows held in L1 from the column gather to the store: R, its polar
# angles and their cos / sin rows, R_z(−φ), X, R_z(−θ), the blocks of X M Xᵀ, R_z(θ), Xᵀ, R_z(φ).
# The same operations as the compiled passes on every row (the z rotations as a·C + a[perm]·(S·sgn),
# X's gathered terms in order, zero-padded terms included); the block products' sums in row order with
# multiply-adds fused: float32 round-off against the GEMMs (tests). Each point is one thread's: the same
# bits at any thread count.
_CONJ_SOURCE = _CONJ_HELPERS + r"""
/* out (n2, Q) row-major: for point q < Q (column col[q] = idx ? idx[q] : off + q of src (n2 rows, row
   stride ld) and of nT, woT (3 rows, row stride ldn)) the conjugation M(R_R) M M(R_R)^T of its column,
   R = reflect(wo, n) normalised. sgn: the + signs (the first half takes -sgn); xi, xw / ti, tw (n2, k):
   X / X^T by gathered terms; nb blocks with spans (r0, r1, c0, c1) and values Kv concatenated (each
   (r1-r0, c1-c0) row-major); cols: the first half's rows in block order; srow: row r of the product at
   srow[r]. nt threads, each point one thread's. lifted: the columns are already in the first half's
   output frame (`runtime.cosine_visibility_zyz`: the blocks of X M read them in place, cols their row
   order), the angles those of nT itself (woT not read): the second half alone. */
void zh_conj(int64_t lifted, int64_t n, int64_t Q, const float *src, int64_t ld, const int64_t *idx, int64_t off,
             const float *nT, const float *woT, int64_t ldn,
             const int64_t *perm, const int64_t *absm, const float *sgn,
             int64_t k, const int64_t *xi, const float *xw, const int64_t *ti, const float *tw,
             int64_t nb, const int64_t *spans, const float *Kv, const int64_t *cols, const int64_t *srow,
             float *out, int64_t nt) {
    const int64_t n2 = n * n, nblk = (Q + L - 1) / L;
    float nsg[MAXN2];
    for (int64_t r = 0; r < n2; ++r) nsg[r] = -sgn[r];
    #pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t bk = 0; bk < nblk; ++bk) {
        vf a[MAXN2], t[MAXN2], u[MAXN2], Cp[MAXN], Sp[MAXN], Ct[MAXN], St[MAXN];
        int64_t c[L];
        const int64_t q0 = bk * L, m = Q - q0 < L ? Q - q0 : L;
        for (int64_t l = 0; l < L; ++l) {
            const int64_t q = q0 + (l < m ? l : m - 1);       /* the tail's spare lanes repeat the last point */
            c[l] = idx ? idx[q] : off + q;
        }
        vf n0, n1, n2v, R0, R1, R2;
        for (int64_t l = 0; l < L; ++l) {
            n0[l] = nT[c[l]]; n1[l] = nT[ldn + c[l]]; n2v[l] = nT[2 * ldn + c[l]];
        }
        if (lifted) {
            R0 = n0; R1 = n1; R2 = n2v;
        } else {
            vf w0, w1, w2, nr;
            for (int64_t l = 0; l < L; ++l) {
                w0[l] = woT[c[l]]; w1[l] = woT[ldn + c[l]]; w2[l] = woT[2 * ldn + c[l]];
            }
            /* `reflect_T`: R = -wo + 2 (wo . n) n, over its norm clamped at 1e-12 */
            const vf d2 = ((w0 * n0 + w1 * n1) + w2 * n2v) * 2.0f;
            R0 = -w0 + d2 * n0; R1 = -w1 + d2 * n1; R2 = -w2 + d2 * n2v;
            const vf nn = vsqrt((R0 * R0 + R1 * R1) + R2 * R2);
            for (int l = 0; l < L; ++l) nr[l] = nn[l] > 1e-12f ? nn[l] : 1e-12f;
            R0 = R0 / nr; R1 = R1 / nr; R2 = R2 / nr;
        }
        /* `_polar`: cos / sin of theta and phi (phi = 0 on the pole) */
        polar_rows(n, R0, R1, R2, Cp, Sp, Ct, St);
        for (int64_t r = 0; r < n2; ++r) {
            const float *row = src + r * ld;
            for (int64_t l = 0; l < L; ++l) a[r][l] = row[c[l]];
        }
        if (lifted) {
            memcpy(t, a, n2 * sizeof(vf));
        } else {   /* first half: R_z(-theta) X R_z(-phi) a */
            rz(n2, a, Cp, Sp, perm, absm, nsg, t);
            gx(n2, k, t, xi, xw, u);
            rz(n2, u, Ct, St, perm, absm, nsg, t);
        }
        /* the blocks of X M X^T: u[r0 + i] = sum_j K[i, j] t[cols[c0 + j]] (rows in block order) */
        block_products(nb, spans, Kv, t, cols, u);
        for (int64_t r = 0; r < n2; ++r) a[r] = u[srow[r]];
        /* second half: R_z(phi) X^T R_z(theta) */
        rz(n2, a, Ct, St, perm, absm, sgn, t);
        gx(n2, k, t, ti, tw, u);
        rz(n2, u, Cp, Sp, perm, absm, sgn, t);
        if (m == L) {
            for (int64_t r = 0; r < n2; ++r) memcpy(out + r * Q + q0, &t[r], sizeof(vf));
        } else {
            for (int64_t r = 0; r < n2; ++r)
                for (int64_t l = 0; l < m; ++l) out[r * Q + q0 + l] = t[r][l];
        }
    }
}
"""
_CONJ_SIGNATURES = {"zh_conj": [_I, _I, _I, _P, _I, _P, _I, _P, _P, _I, _P, _P, _P, _I, _P, _P, _P, _P, _I, _P, _P,
                                _P, _P, _P, _I]}
CONJ_MAX_ORDER = 8


def _conj_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75)
    return native.load("zh_conj", _CONJ_SOURCE, _CONJ_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=fast", *native.isa_flags(), *_avx512_flags()))


def specular_conjugate(srcT: Tensor, nT: Tensor, woT: Tensor | None, cols: Tensor | tuple[int, int], tables: tuple,
                       plan: tuple, *, lifted: bool = False) -> Tensor | None:
    """(n², Q) float32: `runtime.zonal_conjugate`(srcT[:, cols], `runtime.reflect_T`(nT[:, cols], woT[:, cols]),
    …) of the columns ``cols`` — (Q,) int64 positions, or a range (a0, a1) — of srcT (n², N), nT, woT (3, N),
    by one C pass (above; float32 round-off against the compiled passes and GEMMs, the same bits at any
    thread count), or None where it does not run (no compiler, ``PRTBENCH_ZH_NATIVE=0``, order above
    `CONJ_MAX_ORDER`, not float32 CPU arrays with unit column stride). ``tables``: `runtime._conjugate_tables`
    (float32, CPU); ``plan``: `runtime._block_plan` of the operator (scale folded in).

    ``lifted``: `runtime.cosine_visibility_zyz`(srcT[:, cols], nT[:, cols], ordered=True) instead — srcT's
    rows in the lifted plan's column order (`runtime.zyz_rows`), the second half alone about nT (woT
    not read; None allowed)."""
    lib = _conj_lib() if terms_switched_on() else None
    if lifted:
        woT = nT
    if lib is None or woT is None or srcT.dim() != 2 or nT.dim() != 2 or woT.dim() != 2:
        return None
    n2 = int(srcT.shape[0])
    n = int(round(n2 ** 0.5))
    if n * n != n2 or n > CONJ_MAX_ORDER or nT.shape[0] != 3 or woT.shape != nT.shape \
            or nT.shape[1] != srcT.shape[1]:
        return None
    arrs = (srcT, nT, woT)
    if any(t.dtype != torch.float32 or t.device.type != "cpu" or t.stride(1) != 1 for t in arrs) \
            or nT.stride(0) != woT.stride(0):
        return None
    N = int(srcT.shape[1])
    if isinstance(cols, tuple):
        a0, a1 = int(cols[0]), int(cols[1])
        if not 0 <= a0 <= a1 <= N:
            return None
        Q, idx, off = a1 - a0, None, a0
    else:
        if cols.dtype != torch.int64 or cols.dim() != 1 or not cols.is_contiguous() or cols.device.type != "cpu":
            return None
        Q, idx, off = int(cols.shape[0]), cols, 0
        if Q and (int(cols.min()) < 0 or int(cols.max()) >= N):
            return None
    out = torch.empty(n2, Q, dtype=torch.float32)
    if Q == 0:
        return out
    perm, absm, sgn, xi, xw, ti, tw = tables
    flat = _flat_plan(plan)
    spans, Kv, pcols, psrc = flat
    if lifted:   # (the rows already in the product's order: read in place)
        pcols = _identity_rows(n2)
    k = int(xi.shape[1])
    lib.zh_conj(int(bool(lifted)), n, Q, srcT.data_ptr(), srcT.stride(0), 0 if idx is None else idx.data_ptr(), off,
                nT.data_ptr(), woT.data_ptr(), nT.stride(0), perm.data_ptr(), absm.data_ptr(), sgn.data_ptr(),
                k, xi.data_ptr(), xw.data_ptr(), ti.data_ptr(), tw.data_ptr(), len(plan[2]), spans.data_ptr(),
                Kv.data_ptr(), pcols.data_ptr(), psrc.data_ptr(), out.data_ptr(), max(1, torch.get_num_threads()))
    return out


_FLAT: dict = {}


def _flat_plan(plan: tuple) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """`runtime._block_plan`'s (cols, src, blocks) as the C pass reads them: spans (nb, 4) int64, the blocks'
    values concatenated (float32), cols and src int64 contiguous — kept per plan (plans are kept per
    operator by `runtime._block_plan`'s cache; keyed on its identity, the plan held so it stays alive)."""
    hit = _FLAT.get(id(plan))
    if hit is not None and hit[0] is plan:
        return hit[1]
    cols, src, blocks = plan
    spans = torch.tensor([[r0, r1, c0, c1] for r0, r1, c0, c1, _ in blocks], dtype=torch.int64).contiguous()
    Kv = torch.cat([K.reshape(-1) for *_, K in blocks]).to(torch.float32).contiguous()
    flat = (spans, Kv, cols.to(torch.int64).contiguous(), src.to(torch.int64).contiguous())
    if len(_FLAT) > 64:
        _FLAT.clear()
    _FLAT[id(plan)] = (plan, flat)
    return flat


@functools.lru_cache(maxsize=None)
def _identity_rows(n2: int) -> Tensor:
    return torch.arange(n2, dtype=torch.int64)


# === zh33p ==================================================================================================
#
# A plane frame's whole sample stage in one pass over the G-buffer (`ZHShadow._fused_planes`, session 33).
# `ZHShadow._render_planes` ran, after the plane search (`plane_mask`), `object_rows` (the object samples'
# rows gathered into new arrays), `sample_terms` over those rows, the front test (`runtime.dot_T`), the clamp,
# `plane_pixels` over every sample and three ``index_add_`` of the object samples into their pixels: five
# parallel regions and ~7 passes over P- or Q-long arrays (bench creature, paper setting, V frame, 1 thread:
# ~3.5 of ~5.3 ms). Here each pixel is one thread's from the G-buffer to the image: its plane samples as
# `zh_plane_pixels` (the same expressions), then its object samples in order, each shaded as `sample_terms`
# shades a row (the same straight-line features and lane arithmetic: `_point_terms`), times the front test
# (n·ωo as `runtime.dot_T`: two fused multiply-adds), clamped, added into the pixel as ``index_add_`` adds
# (self + src · alpha). The same bits as the separate passes (tested), at any thread count. Also here: the
# first plane search's 8-candidate screen in one pass (`screen8`: `screen_counts`' counts, one strided read
# instead of eight), the second plane's screen over the object samples straight from the mask
# (`rest_screen`: `screen_counts` of their rows), and the vertices those samples reference
# (`referenced_lut`: `runtime.referenced_vertices` of their face corners) without gathering their rows.


def _point_terms(D: int, dif: bool, spec: bool, lanes: int) -> str:
    """C function ``pt_<D>_<dif>_<spec>_<lanes>``: one point's three terms, as `_terms_variant`'s loop body
    computes a row's (the same statements: `_monomial_code`, the reflection, the dot and its reduction
    tree), from the point's values instead of (3, Q) rows; o[c] the terms."""
    code, feats = _feature_code(D, dif, spec)
    K = len(feats)
    assert K % lanes == 0 and lanes in (8, 16)
    body = "\n        ".join(code + [f"f[{i}] = {t};" for i, t in enumerate(feats)])
    if lanes == 8:
        dot = f"""v8 acc[3] = {{{{0}}, {{0}}, {{0}}}};
    for (int j = 0; j < {K}; j += 8) {{
        const v8 fj = ld(f + j);
        for (int c = 0; c < 3; ++c) {{
            const int o = c * {K} + j;
            acc[c] = acc[c] + ((ld(u0 + o) * b0 + ld(u1 + o) * b1) + ld(u2 + o) * b2) * fj;
        }}
    }}
    for (int c = 0; c < 3; ++c) {{
        const v8 a = acc[c];
        const float s0 = a[0] + a[4], s1 = a[1] + a[5], s2 = a[2] + a[6], s3 = a[3] + a[7];
        out[c] = 0.0f + ((s0 + s2) + (s1 + s3));
    }}"""
    else:
        dot = f"""v8 acc[3] = {{{{0}}, {{0}}, {{0}}}}, ah[3] = {{{{0}}, {{0}}, {{0}}}};
    for (int j = 0; j < {K}; j += 16) {{
        const v8 fj = ld(f + j), fh = ld(f + j + 8);
        for (int c = 0; c < 3; ++c) {{
            const int o = c * {K} + j;
            acc[c] = acc[c] + ((ld(u0 + o) * b0 + ld(u1 + o) * b1) + ld(u2 + o) * b2) * fj;
            ah[c] = ah[c] + ((ld(u0 + o + 8) * b0 + ld(u1 + o + 8) * b1) + ld(u2 + o + 8) * b2) * fh;
        }}
    }}
    for (int c = 0; c < 3; ++c) {{
        const v8 a = acc[c];
        const v8 w = a + ah[c];
        const float x0 = w[0] + w[4], x1 = w[1] + w[5], x2 = w[2] + w[6], x3 = w[3] + w[7];
        out[c] = 0.0f + ((x0 + x2) + (x1 + x3));
    }}"""
    return f"""
static void pt_{D}_{int(dif)}_{int(spec)}_{lanes}(const float* u0, const float* u1, const float* u2, float b0, float b1,
        float b2, float nx, float ny, float nz, float wx, float wy, float wz, float* out) {{
    float f[{K}] __attribute__((aligned(64)));
    {{
        {body}
    }}
    (void)wx; (void)wy; (void)wz;
    {dot}
}}
"""



def _features8(D: int, dif: bool, spec: bool) -> str:
    """C function ``ft_<D>_<dif>_<spec>``: the features of 8 points at once (each variable an 8-float vector:
    `_point_terms`' statements on vectors, elementwise the same IEEE operations — products, the reflection,
    the square root and the divisions — so each point's features are the same bits), stored transposed:
    f[p K + k] the feature k of point p."""
    code, feats = _feature_code(D, dif, spec, _REFLECT8)
    K = len(feats)
    code = [ln.replace("const float ", "const v8 ") for ln in code]
    body = "\n    ".join(code + [f"F[{i}] = {t};" for i, t in enumerate(feats)])
    return f"""
static void ft_{D}_{int(dif)}_{int(spec)}(v8 nx, v8 ny, v8 nz, v8 wx, v8 wy, v8 wz, float* f) {{
    v8 F[{K}];
    const v8 tiny = {{1e-12f, 1e-12f, 1e-12f, 1e-12f, 1e-12f, 1e-12f, 1e-12f, 1e-12f}};
    (void)tiny; (void)wx; (void)wy; (void)wz;
    {body}
    for (int k = 0; k < {K}; k += 8) {{   /* 8 x 8 blocks transposed by shuffles */
        const v8 t0 = __builtin_ia32_unpcklps256(F[k], F[k + 1]), t1 = __builtin_ia32_unpckhps256(F[k], F[k + 1]);
        const v8 t2 = __builtin_ia32_unpcklps256(F[k + 2], F[k + 3]), t3 = __builtin_ia32_unpckhps256(F[k + 2], F[k + 3]);
        const v8 t4 = __builtin_ia32_unpcklps256(F[k + 4], F[k + 5]), t5 = __builtin_ia32_unpckhps256(F[k + 4], F[k + 5]);
        const v8 t6 = __builtin_ia32_unpcklps256(F[k + 6], F[k + 7]), t7 = __builtin_ia32_unpckhps256(F[k + 6], F[k + 7]);
        const v8 s0 = __builtin_ia32_shufps256(t0, t2, 0x44), s1 = __builtin_ia32_shufps256(t0, t2, 0xEE);
        const v8 s2 = __builtin_ia32_shufps256(t1, t3, 0x44), s3 = __builtin_ia32_shufps256(t1, t3, 0xEE);
        const v8 s4 = __builtin_ia32_shufps256(t4, t6, 0x44), s5 = __builtin_ia32_shufps256(t4, t6, 0xEE);
        const v8 s6 = __builtin_ia32_shufps256(t5, t7, 0x44), s7 = __builtin_ia32_shufps256(t5, t7, 0xEE);
        st(f + 0 * {K} + k, __builtin_ia32_vperm2f128_ps256(s0, s4, 0x20));
        st(f + 1 * {K} + k, __builtin_ia32_vperm2f128_ps256(s1, s5, 0x20));
        st(f + 2 * {K} + k, __builtin_ia32_vperm2f128_ps256(s2, s6, 0x20));
        st(f + 3 * {K} + k, __builtin_ia32_vperm2f128_ps256(s3, s7, 0x20));
        st(f + 4 * {K} + k, __builtin_ia32_vperm2f128_ps256(s0, s4, 0x31));
        st(f + 5 * {K} + k, __builtin_ia32_vperm2f128_ps256(s1, s5, 0x31));
        st(f + 6 * {K} + k, __builtin_ia32_vperm2f128_ps256(s2, s6, 0x31));
        st(f + 7 * {K} + k, __builtin_ia32_vperm2f128_ps256(s3, s7, 0x31));
    }}
}}
"""


def _dot_terms(D: int, dif: bool, spec: bool, lanes: int) -> str:
    """C function ``dt_<D>_<dif>_<spec>_<lanes>``: `_point_terms`' interpolated dot and reduction from a
    point's features f (K,)."""
    src = _point_terms(D, dif, spec, lanes)
    a, b = src.index("    float f["), src.index("    (void)wx; (void)wy; (void)wz;")
    src = src[:a] + src[b + len("    (void)wx; (void)wy; (void)wz;"):]
    return src.replace(f"static void pt_{D}_{int(dif)}_{int(spec)}_{lanes}(const float* u0",
                       f"static void dt_{D}_{int(dif)}_{int(spec)}_{lanes}(const float* f, const float* u0") \
        .replace("float b2, float nx, float ny, float nz, float wx, float wy, float wz, float* out)",
                 "float b2, float* out)")

_FUSED_SOURCE = r"""
#include <stdint.h>
#include <stdlib.h>
#include <math.h>
""" + _PLANE_SAMPLE_C + r"""
typedef float v8 __attribute__((vector_size(32)));
static inline v8 ld(const float* p) { v8 v; __builtin_memcpy(&v, p, 32); return v; }
typedef int32_t v8i __attribute__((vector_size(32)));
static inline void st(float* p, v8 v) { __builtin_memcpy(p, &v, 32); }
""" + "".join(_dot_terms(*v, lanes=w) for w in TERMS_LANES for v in TERMS_VARIANTS) \
    + "".join(_features8(*v) for v in TERMS_VARIANTS) + r"""
typedef void (*dt_fn)(const float*, const float*, const float*, const float*, float, float, float, float*);
typedef void (*ft_fn)(v8, v8, v8, v8, v8, v8, float*);
#define ZH33P_CHUNK 64

/* Per pixel p < n (S2 samples q = p S2 + s): out[p] = (the plane samples' sum, as zh_plane_pixels) · inv, then
   + t_q · inv for each object sample q (mask[q] == 0 and hit: hit NULL = every sample) in order, t_q its terms
   (`sample_terms`' variant ``variant``, U (NU, 3, K) rows lut[F[face]] or F[face] when lut is NULL, b = ((1 − u)
   − v, u, v)) times (n·ωo > 0, as runtime.dot_T), max(·, 0) if clamp. Plane corners from u (N, 3) by the same
   face table F (M, 3) int32. stat[0]: samples with a face or vertex out of range, or an object sample's region
   outside [0, R) (nothing trusted then); stat[1]: object samples whose region has sreg[region] set. */
void zh33p_fused(int64_t n, int64_t S2, const int64_t *face, const float *bary, int64_t bs0, int64_t bs1,
                 const float *nrm, const float *wo, int64_t ws0, const uint8_t *mask, const uint8_t *hit,
                 const int32_t *F, int64_t M, const float *u, int64_t N, const float *U, int64_t NU, int64_t K,
                 const int32_t *lut, const int64_t *region, const uint8_t *sreg, int64_t R, int64_t variant,
                 int64_t clamp, float inv, float *out, int64_t nt, int64_t *stat) {
    static const dt_fn dts[] = {""" + ", ".join(f"dt_{D}_{int(d)}_{int(sp)}_{w}" for w in TERMS_LANES
                                                for D, d, sp in TERMS_VARIANTS) + r"""};
    static const ft_fn fts[] = {""" + ", ".join(f"ft_{D}_{int(d)}_{int(sp)}" for w in TERMS_LANES
                                                for D, d, sp in TERMS_VARIANTS) + r"""};
    const dt_fn dt = dts[variant];
    const ft_fn ft = fts[variant];
    const int64_t nch = (n + ZH33P_CHUNK - 1) / ZH33P_CHUNK;
    int64_t nb = 0, ns = 0;
#pragma omp parallel for num_threads(nt) schedule(static, 1) reduction(+:nb, ns) if(nt > 1)
    for (int64_t ch = 0; ch < nch; ++ch) {
        const int64_t p0 = ch * ZH33P_CHUNK, p1 = p0 + ZH33P_CHUNK < n ? p0 + ZH33P_CHUNK : n;
        float r[3 * ZH33P_CHUNK];
        int64_t oq[ZH33P_CHUNK * 16];   /* the chunk's object samples, in order (S2 <= 16) */
        int64_t no = 0;
        for (int64_t p = p0; p < p1; ++p) {
            float o0 = 0.f, o1 = 0.f, o2 = 0.f;
            for (int64_t s = 0; s < S2; ++s) {
                const int64_t q = p * S2 + s;
                float x[3] = {0.f, 0.f, 0.f};
                if (mask[q]) {
                    if (zh_plane_dn(nrm, wo, ws0, q) > 0.f) {
                        const int64_t f = face[q];
                        if ((uint64_t)f >= (uint64_t)M
                                || zh_plane_sample(u, N, F[3 * f], F[3 * f + 1], F[3 * f + 2], bary, bs0, bs1, q, clamp, x))
                            ++nb;
                    }
                } else if (!hit || hit[q]) {
                    oq[no++] = q;
                }
                if (s == 0) { o0 = x[0]; o1 = x[1]; o2 = x[2]; }
                else { o0 = o0 + x[0]; o1 = o1 + x[1]; o2 = o2 + x[2]; }
            }
            const int64_t k = 3 * (p - p0);
            r[k] = o0 * inv; r[k + 1] = o1 * inv; r[k + 2] = o2 * inv;
        }
        for (int64_t g = 0; g < no; g += 8) {   /* the object samples 8 at a time (the last batch padded) */
            const int64_t m = no - g < 8 ? no - g : 8;
            float fx[8], fy[8], fz[8], gx[8], gy[8], gz[8];
            for (int i = 0; i < 8; ++i) {
                const int64_t q = oq[g + (i < m ? i : m - 1)];
                fx[i] = nrm[3 * q]; fy[i] = nrm[3 * q + 1]; fz[i] = nrm[3 * q + 2];
                gx[i] = wo[q]; gy[i] = wo[ws0 + q]; gz[i] = wo[2 * ws0 + q];
            }
            float fb[8 * 80] __attribute__((aligned(64)));
            ft(ld(fx), ld(fy), ld(fz), ld(gx), ld(gy), ld(gz), fb);
            for (int i = 0; i < m; ++i) {
                const int64_t q = oq[g + i];
                const int64_t f = face[q], rg = region[q];
                if ((uint64_t)f >= (uint64_t)M || (uint64_t)rg >= (uint64_t)R) { ++nb; continue; }
                int64_t i0 = F[3 * f], i1 = F[3 * f + 1], i2 = F[3 * f + 2];
                if (lut) {
                    if ((uint64_t)i0 >= (uint64_t)N || (uint64_t)i1 >= (uint64_t)N || (uint64_t)i2 >= (uint64_t)N) {
                        ++nb;
                        continue;
                    }
                    i0 = lut[i0]; i1 = lut[i1]; i2 = lut[i2];
                }
                if ((uint64_t)i0 >= (uint64_t)NU || (uint64_t)i1 >= (uint64_t)NU || (uint64_t)i2 >= (uint64_t)NU) {
                    ++nb;
                    continue;
                }
                const float bu = bary[q * bs1], bv = bary[bs0 + q * bs1];
                float t[3];
                dt(fb + i * K, U + i0 * 3 * K, U + i1 * 3 * K, U + i2 * 3 * K, (1.0f - bu) - bv, bu, bv, t);
                const float fr = (__builtin_fmaf(fz[i], gz[i], __builtin_fmaf(fy[i], gy[i], fx[i] * gx[i])) > 0.f)
                                 ? 1.0f : 0.0f;
                for (int c = 0; c < 3; ++c) {
                    float x = t[c] * fr;
                    if (clamp)
                        x = x < 0.f ? 0.f : x;
                    t[c] = x;
                }
                const int64_t k = 3 * (q / S2 - p0);
                r[k] = r[k] + t[0] * inv;
                r[k + 1] = r[k + 1] + t[1] * inv;
                r[k + 2] = r[k + 2] + t[2] * inv;
                ns += sreg[rg];
            }
        }
        for (int64_t i = 0; i < 3 * (p1 - p0); ++i)
            out[3 * p0 + i] = r[i];
    }
    stat[0] = nb;
    stat[1] = ns;
}

/* `zh_screen`'s counts for the normals (rows x, y, z = base, base + s0, base + 2 s0; stride s1) in one pass:
   cnt[c] = #{j = 0, 16, … < m : normal j == normal c m / 8}. */
void zh33p_screen8(const float *base, int64_t s0, int64_t s1, int64_t m, int64_t *cnt) {
    float a[8], b[8], d[8];
    int64_t n[8];
    for (int c = 0; c < 8; ++c) {
        const int64_t k = c * m / 8;
        a[c] = base[k * s1]; b[c] = base[s0 + k * s1]; d[c] = base[2 * s0 + k * s1];
        n[c] = 0;
    }
    for (int64_t j = 0; j < m; j += 16) {
        const float x = base[j * s1], y = base[s0 + j * s1], z = base[2 * s0 + j * s1];
        for (int c = 0; c < 8; ++c)
            n[c] += (x == a[c]) & (y == b[c]) & (z == d[c]);
    }
    for (int c = 0; c < 8; ++c)
        cnt[c] = n[c];
}

/* The same counts for the normals (P, 3) row-major of the samples p with mask[p] == 0 (m of them), in order
   (`zh_screen` of their (3, m) rows). Returns -1 when the mask does not hold m zeros or memory runs out. */
int64_t zh33p_rest_screen(const uint8_t *mask, const float *nrm, int64_t P, int64_t m, int64_t *cnt) {
    if (m <= 0) return -1;
    const int64_t ns = (m + 15) / 16;
    float *sub = (float *)malloc(sizeof(float) * 3 * (size_t)ns);
    if (!sub) return -1;
    float cand[24];
    int64_t rank[8];
    for (int c = 0; c < 8; ++c) rank[c] = c * m / 8;
    int next = 0;
    int64_t j = 0;
    for (int64_t p = 0; p < P; ++p) {
        if (mask[p]) {
            uint64_t w;   /* (skip 8 plane samples at a time: most are) */
            while (p + 9 <= P && (__builtin_memcpy(&w, mask + p + 1, 8), w == 0x0101010101010101ULL))
                p += 8;
            continue;
        }
        const float *x = nrm + 3 * p;
        if ((j & 15) == 0 && (j >> 4) < ns) {
            sub[3 * (j >> 4)] = x[0]; sub[3 * (j >> 4) + 1] = x[1]; sub[3 * (j >> 4) + 2] = x[2];
        }
        while (next < 8 && rank[next] == j) {
            cand[3 * next] = x[0]; cand[3 * next + 1] = x[1]; cand[3 * next + 2] = x[2];
            ++next;
        }
        ++j;
    }
    if (j != m || next != 8) { free(sub); return -1; }
    for (int c = 0; c < 8; ++c) {
        int64_t k = 0;
        for (int64_t i = 0; i < ns; ++i)
            k += (sub[3 * i] == cand[3 * c]) & (sub[3 * i + 1] == cand[3 * c + 1]) & (sub[3 * i + 2] == cand[3 * c + 2]);
        cnt[c] = k;
    }
    free(sub);
    return 0;
}

/* lut[i] (N,) = the rank of vertex i among the corners F[face[p]] of the samples with mask[p] == 0 and hit
   (ascending vertex ids), -1 for the others; idx[r] the vertex of rank r. Returns their count, or -1 when a
   face or a corner is out of range. */
int64_t zh33p_referenced_lut(const uint8_t *mask, const uint8_t *hit, const int64_t *face, const int32_t *F, int64_t M,
                             int64_t P, int64_t N, int32_t *lut, int64_t *idx) {
    for (int64_t i = 0; i < N; ++i) lut[i] = 0;
    for (int64_t p = 0; p < P; ++p) {
        if (mask[p]) {
            uint64_t w;   /* (skip 8 plane samples at a time: most are) */
            while (p + 9 <= P && (__builtin_memcpy(&w, mask + p + 1, 8), w == 0x0101010101010101ULL))
                p += 8;
            continue;
        }
        if (hit && !hit[p]) continue;
        const int64_t f = face[p];
        if ((uint64_t)f >= (uint64_t)M) return -1;
        for (int k = 0; k < 3; ++k) {
            const int64_t i = F[3 * f + k];
            if ((uint64_t)i >= (uint64_t)N) return -1;
            lut[i] = 1;
        }
    }
    int64_t r = 0;
    for (int64_t i = 0; i < N; ++i) {
        if (lut[i]) { idx[r] = i; lut[i] = (int32_t)r; ++r; }
        else lut[i] = -1;
    }
    return r;
}
"""
_FUSED_SIGNATURES = {
    "zh33p_fused": [_I, _I, _P, _P, _I, _I, _P, _P, _I, _P, _P, _P, _I, _P, _I, _P, _I, _I, _P, _P, _P, _I, _I, _I,
                    ctypes.c_float, _P, _I, _P],
    "zh33p_screen8": [_P, _I, _I, _I, _P],
    "zh33p_rest_screen": [_P, _P, _I, _I, _P],
    "zh33p_referenced_lut": [_P, _P, _P, _P, _I, _I, _I, _P, _P]}
_FUSED_RESTYPES = {"zh33p_rest_screen": ctypes.c_int64, "zh33p_referenced_lut": ctypes.c_int64}


def _fused_lib():
    """The library or None (no compiler, ``PRTBENCH_COMPILE=0``, ``PRTBENCH_ZH_NATIVE=0``, or Inductor vectorises
    for neither AVX2 nor AVX-512: `sample_terms`' lane arithmetic would not be its kernel's). Not cached here:
    `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75)."""
    if not terms_switched_on() or _inductor_lanes() not in TERMS_LANES:
        return None
    lib = load("zh33p_fused", _FUSED_SOURCE, _FUSED_SIGNATURES,
                      extra_flags=("-ffp-contract=off", "-fopenmp", *native.isa_flags()))
    if lib is not None:
        for name, rt_ in _FUSED_RESTYPES.items():
            getattr(lib, name).restype = rt_
    return lib


def fused_available(D: int, diffuse: bool, specular: bool) -> bool:
    """Whether `fused_pixels` runs for the features (D, diffuse, specular) (a `TERMS_VARIANTS` entry)."""
    return (D, bool(diffuse), bool(specular)) in TERMS_VARIANTS and _fused_lib() is not None


def screen8(cur: Tensor) -> list[int] | None:
    """`screen_counts`(cur) in one pass over the screened points (the same counts), or None (no library)."""
    lib = _fused_lib()
    if lib is None or cur.dtype != torch.float32 or cur.device.type != "cpu" or cur.dim() != 2 or cur.shape[0] != 3 \
            or cur.shape[1] == 0:
        return None
    cnt = torch.zeros(8, dtype=torch.int64)
    lib.zh33p_screen8(cur.data_ptr(), cur.stride(0), cur.stride(1), int(cur.shape[1]), cnt.data_ptr())
    return cnt.tolist()


def rest_screen(mask: Tensor, normal: Tensor, m: int) -> list[int] | None:
    """`screen_counts` of the (3, m) rows of the normals (P, 3) of the samples off ``mask`` (P,) bool (m of
    them), without gathering them; None where the C pass does not run."""
    lib = _fused_lib()
    P = int(mask.shape[0])
    if lib is None or m <= 0 or mask.dtype != torch.bool or not mask.is_contiguous() or normal.dtype != torch.float32 \
            or normal.shape != (P, 3) or not normal.is_contiguous():
        return None
    cnt = torch.zeros(8, dtype=torch.int64)
    if lib.zh33p_rest_screen(mask.data_ptr(), normal.data_ptr(), P, int(m), cnt.data_ptr()) != 0:
        return None
    return cnt.tolist()


def referenced_lut(mask: Tensor, hit: Tensor | None, face: Tensor, F32: Tensor, N: int) -> tuple[Tensor, Tensor] | None:
    """(idx (M,) int64 ascending, lut (N,) int32: a vertex's rank in idx, −1 off it) of the vertices the
    samples off ``mask`` (and hit) reference through their faces — `runtime.referenced_vertices` of their
    rows' vertex ids, lut[vi] its renumbered ids — or None (no library, a face or corner out of range)."""
    lib = _fused_lib()
    P = int(mask.shape[0])
    if lib is None or mask.dtype != torch.bool or not mask.is_contiguous() or face.dtype != torch.int64 \
            or face.shape != (P,) or not face.is_contiguous() or F32.dtype != torch.int32 or not F32.is_contiguous() \
            or (hit is not None and (hit.dtype != torch.bool or hit.shape != (P,) or not hit.is_contiguous())):
        return None
    lut = torch.empty(N, dtype=torch.int32)
    idx = torch.empty(N, dtype=torch.int64)
    r = lib.zh33p_referenced_lut(mask.data_ptr(), 0 if hit is None else hit.data_ptr(), face.data_ptr(),
                                 F32.data_ptr(), int(F32.shape[0]), P, int(N), lut.data_ptr(), idx.data_ptr())
    if r < 0:
        return None
    return idx[:r], lut


def fused_pixels(face: Tensor, bary: Tensor, normal: Tensor, wo: Tensor, mask: Tensor, hit: Tensor | None,
                 F32: Tensor, u: Tensor, U: Tensor, lut: Tensor | None, region: Tensor, spec_regions: list[bool],
                 D: int, diffuse: bool, specular: bool, clamp: bool, S2: int, fma: bool = False,
                 vector: bool = False, wide: bool = False, balanced: bool = False) -> tuple[Tensor, int] | None:
    """(img (n, 3), the object samples in a region with a specular term) of a plane frame in one pass
    (`zh33p_fused`): the plane samples (``mask``) as `plane_pixels`(…, u, clamp) and the others (hit) as
    `sample_terms`(U, …) × (n·ωo > 0), clamped, added in order as ``index_add_`` — bit for bit those passes'
    image — or None where it does not run (no library, a variant `sample_terms` lacks, other dtypes or
    layouts, a face, vertex or region out of range). face (P,) int64, bary (P, 2) float32 of any strides, wo
    (P, 3) float32 column-major (the G-buffer's layout), normal (P, 3) contiguous, mask / hit (P,) bool, F32
    (M, 3) int32, u (N, 3), U (NU, 3, K) float32 (rows lut[vertex] when lut (N,) int32 is given), region (P,)
    int64. ``fma``: the object samples' dot regrouped (`zh37v_fused`: float32 round-off against those bits).
    ``vector``: the plane samples 16 at a time where it runs (`native_fused16`, zh40p: the same bits as the
    pass it replaces). ``wide`` (with ``fma`` and ``vector``): the object samples' dot in 16-float vectors
    and the plane samples' corners read once per distinct face of a vector (`native_fused16`'s `zh42p_fused_wide`,
    zh42p: float32 round-off against the ``fma`` pass; the plane samples the same bits). ``balanced`` (with
    ``wide``): its chunks handed out to the threads dynamically where it runs (`native_balanced`, zh46: the same
    bits)."""
    r = _fused_resolve(D, diffuse, specular, fma, vector, wide, balanced)
    if r is None:
        return None
    sreg = torch.tensor([bool(s) for s in spec_regions], dtype=torch.uint8)
    stat = torch.zeros(2, dtype=torch.int64)
    return _fused_run(r, sreg, stat, face, bary, normal, wo, mask, hit, F32, u, U, lut, region, clamp, S2)


def _fused_resolve(D: int, diffuse: bool, specular: bool, fma: bool, vector: bool, wide: bool, balanced: bool
                   ) -> tuple | None:
    """(C function, variant, K) `fused_pixels` runs for these flags, or None (no library, a variant lacking)."""
    vec = None
    if vector:
        from methods.zh_shadow import native_fused16

        vec = None
        if balanced and fma and wide:
            from methods.zh_shadow import native_balanced

            vec = native_balanced.lib()
        if vec is None:
            vec = native_fused16.lib(fma, wide=True) if fma and wide else None
        if vec is None:   # (no wide dot asked for, or its library not built: the 8-float dot's)
            vec = native_fused16.lib(fma)
    lib = _fma_fused_lib() if fma else None
    if lib is None:   # (the regrouped dot's library not built: `zh33p_fused`'s bits)
        lib, fma = _fused_lib(), False
        if vector and vec is not None:
            vec = native_fused16.lib(False)
    key = (D, bool(diffuse), bool(specular))
    if lib is None or key not in TERMS_VARIANTS:
        return None
    K = (((D + 1) * (D + 2) // 2 + 3) if diffuse else 0) + ((D + 1) * (D + 2) // 2 + D * (D + 1) // 2 if specular else 0)
    variant = TERMS_LANES.index(_inductor_lanes()) * len(TERMS_VARIANTS) + TERMS_VARIANTS.index(key)
    return (vec[1] if vec is not None else lib.zh37v_fused if fma else lib.zh33p_fused), variant, K


def _fused_run(r: tuple, sreg: Tensor, stat: Tensor, face: Tensor, bary: Tensor, normal: Tensor, wo: Tensor,
               mask: Tensor, hit: Tensor | None, F32: Tensor, u: Tensor, U: Tensor, lut: Tensor | None,
               region: Tensor, clamp: bool, S2: int) -> tuple[Tensor, int] | None:
    """`fused_pixels`' checks and call of the resolved pass ``r`` (`_fused_resolve`), sreg (R,) uint8 the regions'
    specular flags, stat (2,) int64 scratch (zeroed here)."""
    fn, variant, K = r
    P = int(face.shape[0])
    if S2 <= 0 or S2 > 16 or P % S2 or face.dtype != torch.int64 or face.shape != (P,) or not face.is_contiguous() \
            or mask.dtype != torch.bool or mask.shape != (P,) or not mask.is_contiguous() \
            or (hit is not None and (hit.dtype != torch.bool or hit.shape != (P,) or not hit.is_contiguous())) \
            or normal.dtype != torch.float32 or normal.shape != (P, 3) or not normal.is_contiguous() \
            or bary.dtype != torch.float32 or bary.shape != (P, 2) \
            or wo.dtype != torch.float32 or wo.shape != (P, 3) or wo.stride(0) != 1 \
            or F32.dtype != torch.int32 or F32.dim() != 2 or F32.shape[1] != 3 or not F32.is_contiguous() \
            or u.dtype != torch.float32 or u.dim() != 2 or u.shape[1] != 3 \
            or U.dtype != torch.float32 or U.dim() != 3 or U.shape[1] != 3 \
            or region.dtype != torch.int64 or region.shape != (P,) or not region.is_contiguous() \
            or (lut is not None and (lut.dtype != torch.int32 or not lut.is_contiguous())) \
            or any(t.device.type != "cpu" for t in (face, bary, normal, wo, mask, F32, u, U, region)):
        return None
    if U.shape[2] != K:
        return None
    u, U = u.contiguous(), U.contiguous()
    N = int(u.shape[0])
    if lut is not None and lut.shape != (N,):
        return None
    n = P // S2
    out = torch.empty(n, 3, dtype=torch.float32)
    sp = stat.data_ptr()
    ctypes.memset(sp, 0, 16)
    nt = max(1, min(torch.get_num_threads(), n // MIN_PIXELS_PER_THREAD))
    fn(n, S2, face.data_ptr(), bary.data_ptr(), bary.stride(1), bary.stride(0), normal.data_ptr(),
       wo.data_ptr(), wo.stride(1), mask.data_ptr(), 0 if hit is None else hit.data_ptr(),
       F32.data_ptr(), int(F32.shape[0]), u.data_ptr(), N, U.data_ptr(), int(U.shape[0]), K,
       0 if lut is None else lut.data_ptr(), region.data_ptr(), sreg.data_ptr(), int(sreg.shape[0]),
       variant, int(bool(clamp)), 1.0 / S2, out.data_ptr(), nt, sp)
    if ctypes.c_int64.from_address(sp).value:
        return None
    return out, ctypes.c_int64.from_address(sp + 8).value


class FusedBound:
    """`fused_pixels` for one set of flags, regions' specular flags, clamp and S² (zh46): its library, variant and
    small arrays resolved once (`fused_bind`) — per call only the arrays' checks and the C call (the same pass, the
    same bits). The library look-ups, ``torch.tensor`` of the flags and the stat array were ~0.1 ms of serial
    Python a bench P frame at 2 threads with the caches cold. The switches are the caller's to read."""

    __slots__ = ("key", "r", "sreg", "stat", "clamp", "S2")

    def __call__(self, face: Tensor, bary: Tensor, normal: Tensor, wo: Tensor, mask: Tensor, hit: Tensor | None,
                 F32: Tensor, u: Tensor, U: Tensor, lut: Tensor | None, region: Tensor) -> tuple[Tensor, int] | None:
        return _fused_run(self.r, self.sreg, self.stat, face, bary, normal, wo, mask, hit, F32, u, U, lut, region,
                          self.clamp, self.S2)


def fused_bind(spec_regions: list[bool], D: int, diffuse: bool, specular: bool, clamp: bool, S2: int,
               fma: bool = False, vector: bool = False, wide: bool = False, balanced: bool = False
               ) -> FusedBound | None:
    """A `FusedBound` of `fused_pixels`(…, spec_regions, D, diffuse, specular, clamp, S2, fma, vector, wide,
    balanced), or None where `fused_pixels` would not run (no library, a variant lacking)."""
    r = _fused_resolve(D, diffuse, specular, fma, vector, wide, balanced)
    if r is None:
        return None
    b = FusedBound()
    b.key = (tuple(bool(s) for s in spec_regions), D, bool(diffuse), bool(specular), bool(clamp), int(S2), bool(fma),
             bool(vector), bool(wide), bool(balanced))
    b.r, b.clamp, b.S2 = r, bool(clamp), int(S2)
    b.sreg = torch.tensor([bool(s) for s in spec_regions], dtype=torch.uint8)
    b.stat = torch.zeros(2, dtype=torch.int64)
    return b


# -- zh33v ------------------------------------------------------------------------------------------
# A view frame's per-vertex radiance in one C pass (`view_radiance`, `ZHShadow._render_vertex`): the
# order-8 cosine V / VB / VL / VBL frames ran `_view_directions`, the front test, `runtime.specular_parts`
# (`specular_conjugate` per specular region, its index and plan set-up), the diffuse product and the
# specular products, the front mask and the clamp as ~25 dispatches and Python steps around the C pass
# (~1.5 ms of a ~3.5 ms frame at 1 thread). Here: per vertex ωo = (cam − x) / |cam − x| and n·ωo as
# torch computes them (`_view_directions`, `runtime.dot_T`: the products rounded, the dot's two
# multiply-adds fused — the same bits, so the same front-facing set), then for the front-facing vertices
# of each region kd ⊙ (lᵀ w) / π, and of a specular region + ks ⊙ (lᵀ t_s) with t_s the conjugation of
# `specular_conjugate` (R, the angles, both halves, the blocks; the same code) — t_s never written —,
# clamped at 0 if asked; the other vertices 0. The sums over the n² rows in row order with multiply-
# adds fused: float32 round-off against the torch path's products (tests). Each vertex is one lane of
# one thread's block: the same bits at any thread count.
_VIEW_SOURCE = _CONJ_HELPERS + r"""
#ifdef __AVX512F__
#include <immintrin.h>
#endif

/* a value the compiler may not fuse into a later add (torch rounds the product first) */
static inline float rounded(float x) { __asm__("" : "+x"(x)); return x; }
static inline vf vrounded(vf x) { __asm__("" : "+v"(x)); return x; }

/* a[r] = the columns c[0..L) of the n2 rows (stride ldw) of w: one load where they are consecutive,
   two and a lane permute where they lie within 32 columns (the front-facing vertices of a mesh
   region: a median span of 27 on the bench creature), else a gather */
static inline void gather_cols(int64_t n2, const float *w, int64_t ldw, int64_t N, const int64_t *c, vf *a) {
    const int64_t c0 = c[0], span = c[L - 1] - c0;
    if (span == L - 1) {
        for (int64_t r = 0; r < n2; ++r) memcpy(&a[r], w + r * ldw + c0, sizeof(vf));
        return;
    }
#ifdef __AVX512F__
    if (span < 2 * L && c0 + 2 * L <= N) {
        int32_t rel[L];
        for (int l = 0; l < L; ++l) rel[l] = (int32_t)(c[l] - c0);
        const __m512i ix = _mm512_loadu_si512(rel);
        for (int64_t r = 0; r < n2; ++r) {
            const float *row = w + r * ldw + c0;
            a[r] = (vf)_mm512_permutex2var_ps(_mm512_loadu_ps(row), ix, _mm512_loadu_ps(row + L));
        }
        return;
    }
#endif
    for (int64_t r = 0; r < n2; ++r) {
        const float *row = w + r * ldw;
        for (int64_t l = 0; l < L; ++l) a[r][l] = row[c[l]];
    }
}

/* One block: the m <= L vertices c[0..m) (spare lanes repeat the last) of region r; spec: with the
   conjugation by the region's plan (nb blocks spans / Kv, cols, srow). out rows (N, 3). */
/* lp: a lifted plan (nb, spans, Kv, srow; its columns in place) when w's columns hold the visibility in
   the ZYZ normal frames (`runtime.cosine_visibility_zyz`, ``ordered``: a P frame's), then w itself is
   made first (the blocks of X M^1 and the second half about n, as `specular_conjugate`'s lifted pass);
   o: the out rows of the lanes (NULL: c). */
static void block(int64_t n, int spec, const int64_t *c, const int64_t *o, int64_t m, const float *w,
                  int64_t ldw, int64_t Nw, const float *nT, const float *woT, int64_t ldn, const float *lT,
                  const float *co, const int64_t *perm, const int64_t *absm, const float *sgn, const float *nsg,
                  int64_t k, const int64_t *xi, const float *xw, const int64_t *ti, const float *tw,
                  int64_t nb, const int64_t *spans, const float *Kv, const int64_t *cols, const int64_t *srow,
                  const int64_t *lp, int64_t clamp, float *out) {
    const int64_t n2 = n * n;
    vf a[MAXN2], t[MAXN2], u[MAXN2], Cp[MAXN], Sp[MAXN], Ct[MAXN], St[MAXN];
    gather_cols(n2, w, ldw, Nw, c, a);
    if (lp) {   /* w = M(R_n) M^1 of the lifted columns: the blocks in place, then the second half */
        vf n0, n1, n2v;
        for (int64_t l = 0; l < L; ++l) { n0[l] = nT[c[l]]; n1[l] = nT[ldn + c[l]]; n2v[l] = nT[2 * ldn + c[l]]; }
        polar_rows(n, n0, n1, n2v, Cp, Sp, Ct, St);
        const int64_t lnb = lp[0], *lsp = (const int64_t *)(intptr_t)lp[1], *lsr = (const int64_t *)(intptr_t)lp[3];
        block_products(lnb, lsp, (const float *)(intptr_t)lp[2], a, NULL, u);
        for (int64_t r = 0; r < n2; ++r) t[r] = u[lsr[r]];
        rz(n2, t, Ct, St, perm, absm, sgn, u);
        gx(n2, k, u, ti, tw, t);
        rz(n2, t, Cp, Sp, perm, absm, sgn, a);
    }
    /* (l . w) kd / pi: co[0..3) = kd / pi (the order of `ZHShadow._diffuse_ranges`: the sum, then the albedo) */
    vf d0 = a[0] * lT[0], d1 = a[0] * lT[n2], d2 = a[0] * lT[2 * n2];
    for (int64_t r = 1; r < n2; ++r) {
        d0 = d0 + a[r] * lT[r]; d1 = d1 + a[r] * lT[n2 + r]; d2 = d2 + a[r] * lT[2 * n2 + r];
    }
    d0 = d0 * co[0]; d1 = d1 * co[1]; d2 = d2 * co[2];
    if (spec) {
        vf n0, n1, n2v, w0, w1, w2, R0, R1, R2, nr;
        for (int64_t l = 0; l < L; ++l) {
            n0[l] = nT[c[l]]; n1[l] = nT[ldn + c[l]]; n2v[l] = nT[2 * ldn + c[l]];
            w0[l] = woT[c[l]]; w1[l] = woT[ldn + c[l]]; w2[l] = woT[2 * ldn + c[l]];
        }
        const vf dd = ((w0 * n0 + w1 * n1) + w2 * n2v) * 2.0f;
        R0 = -w0 + dd * n0; R1 = -w1 + dd * n1; R2 = -w2 + dd * n2v;
        const vf nn = vsqrt((R0 * R0 + R1 * R1) + R2 * R2);
        for (int l = 0; l < L; ++l) nr[l] = nn[l] > 1e-12f ? nn[l] : 1e-12f;
        R0 = R0 / nr; R1 = R1 / nr; R2 = R2 / nr;
        polar_rows(n, R0, R1, R2, Cp, Sp, Ct, St);
        rz(n2, a, Cp, Sp, perm, absm, nsg, t);
        gx(n2, k, t, xi, xw, u);
        rz(n2, u, Ct, St, perm, absm, nsg, t);
        block_products(nb, spans, Kv, t, cols, u);
        for (int64_t r = 0; r < n2; ++r) a[r] = u[srow[r]];
        rz(n2, a, Ct, St, perm, absm, sgn, t);
        gx(n2, k, t, ti, tw, u);
        rz(n2, u, Cp, Sp, perm, absm, sgn, t);
        /* + (l . t_s) ks: co[3..6) = ks */
        vf s0 = t[0] * lT[0], s1 = t[0] * lT[n2], s2 = t[0] * lT[2 * n2];
        for (int64_t r = 1; r < n2; ++r) {
            s0 = s0 + t[r] * lT[r]; s1 = s1 + t[r] * lT[n2 + r]; s2 = s2 + t[r] * lT[2 * n2 + r];
        }
        d0 = d0 + s0 * co[3]; d1 = d1 + s1 * co[4]; d2 = d2 + s2 * co[5];
    }
    for (int64_t l = 0; l < m; ++l) {
        float x0 = d0[l], x1 = d1[l], x2 = d2[l];
        if (clamp) { x0 = x0 > 0.0f ? x0 : 0.0f; x1 = x1 > 0.0f ? x1 : 0.0f; x2 = x2 > 0.0f ? x2 : 0.0f; }
        float *y = out + 3 * (o ? o[c[l]] : c[l]);
        y[0] = x0; y[1] = x1; y[2] = x2;
    }
}

/* s[q] = |cam - pos[q]|^2 as `_view_directions` sums it: ((x0 x0 + x1 x1) + x2 x2), products rounded */
void zh33v_sq(int64_t N, const float *pos, const float *cam, float *s) {
    const float c0 = cam[0], c1 = cam[1], c2 = cam[2];
    for (int64_t q = 0; q < N; ++q) {
        const float x0 = c0 - pos[3 * q], x1 = c1 - pos[3 * q + 1], x2 = c2 - pos[3 * q + 2];
        s[q] = (rounded(x0 * x0) + rounded(x1 * x1)) + rounded(x2 * x2);
    }
}

/* Vertices [0, N): pos (N, 3) rows, norm (N,) |cam - pos| (torch's square root: not IEEE's here), nT (3, N) rows of stride ldn, w (n2, N) rows of stride ldw; nreg
   regions, region r the vertices [rsp[2r], rsp[2r+1]), lT (3, n2) the lighting, co (nreg, 6) kd / pi and ks,
   spec[r] 1 for a specular term by the plan at the addresses pl[5r..5r+5) (nb, spans, Kv, cols, srow).
   Out: woT (3, N) scratch, front (N,) the test n . wo > 0, list (N,) and blk (N / L + 2 nreg, 3)
   scratch, out (N, 3) the radiance (0 off the front). nt threads. */
void zh33v_view(int64_t n, int64_t N, const float *pos, const float *norm, const float *nT, int64_t ldn,
                const float *w, int64_t ldw,
                const float *cam, int64_t nreg, const int64_t *rsp, const float *lT, const float *co,
                const int64_t *spec, const int64_t *pl,
                const int64_t *perm, const int64_t *absm, const float *sgn,
                int64_t k, const int64_t *xi, const float *xw, const int64_t *ti, const float *tw,
                int64_t clamp, float *woT, uint8_t *front, int64_t *list, int64_t *blk, float *out, int64_t nt) {
    const int64_t n2 = n * n;
    float nsg[MAXN2];
    for (int64_t r = 0; r < n2; ++r) nsg[r] = -sgn[r];
    int64_t nblk = 0;
    const float c0 = cam[0], c1 = cam[1], c2 = cam[2];
    /* serial (cheap: ~13 K vertices' tests and one scan), so that the team meets once, at the end of the
       blocks (a barrier per phase cost a time slice each on a loaded host) */
    {
        /* `_view_directions` (norm: torch's square root of `zh33v_sq`'s sums) and `runtime.dot_T`
           (fma(n2, w2, fma(n1, w1, n0 w0)) > 0) */
        for (int64_t g = 0; g < (N + L - 1) / L; ++g) {
            const int64_t q0 = g * L;
            if (q0 + L <= N) {   /* 16 vertices as vectors: the same operations lane by lane */
                vf x0, x1, x2, m0, m1, m2, d;
                for (int l = 0; l < L; ++l) {
                    x0[l] = pos[3 * (q0 + l)]; x1[l] = pos[3 * (q0 + l) + 1]; x2[l] = pos[3 * (q0 + l) + 2];
                }
                x0 = c0 - x0; x1 = c1 - x1; x2 = c2 - x2;
                vf nn;
                memcpy(&nn, norm + q0, sizeof(vf));
                for (int l = 0; l < L; ++l) nn[l] = nn[l] < 1e-12f ? 1e-12f : nn[l];
                x0 = x0 / nn; x1 = x1 / nn; x2 = x2 / nn;
                memcpy(woT + q0, &x0, sizeof(vf)); memcpy(woT + ldn + q0, &x1, sizeof(vf));
                memcpy(woT + 2 * ldn + q0, &x2, sizeof(vf));
                memcpy(&m0, nT + q0, sizeof(vf)); memcpy(&m1, nT + ldn + q0, sizeof(vf));
                memcpy(&m2, nT + 2 * ldn + q0, sizeof(vf));
                d = vrounded(m0 * x0);
                for (int l = 0; l < L; ++l) d[l] = fmaf(m1[l], x1[l], d[l]);
                for (int l = 0; l < L; ++l) d[l] = fmaf(m2[l], x2[l], d[l]);
                for (int l = 0; l < L; ++l) {
                    const int64_t q = q0 + l;
                    front[q] = d[l] > 0.0f;
                    if (!(d[l] > 0.0f)) { out[3 * q] = 0.0f; out[3 * q + 1] = 0.0f; out[3 * q + 2] = 0.0f; }
                }
                continue;
            }
            for (int64_t q = q0; q < N; ++q) {
                const float x0 = c0 - pos[3 * q], x1 = c1 - pos[3 * q + 1], x2 = c2 - pos[3 * q + 2];
                float nn = norm[q];
                nn = nn < 1e-12f ? 1e-12f : nn;
                const float w0 = x0 / nn, w1 = x1 / nn, w2 = x2 / nn;
                woT[q] = w0; woT[ldn + q] = w1; woT[2 * ldn + q] = w2;
                const float d = fmaf(nT[2 * ldn + q], w2, fmaf(nT[ldn + q], w1, rounded(nT[q] * w0)));
                front[q] = d > 0.0f;
                if (!(d > 0.0f)) { out[3 * q] = 0.0f; out[3 * q + 1] = 0.0f; out[3 * q + 2] = 0.0f; }
            }
        }
        {   /* the front-facing vertices per region, in blocks of at most L (region, first, count) */
            int64_t m = 0;
            for (int64_t r = 0; r < nreg; ++r) {
                const int64_t m0 = m;
                for (int64_t q = rsp[2 * r]; q < rsp[2 * r + 1]; ++q)
                    if (front[q]) list[m++] = q;
                for (int64_t b = m0; b < m; b += L) {
                    blk[3 * nblk] = r; blk[3 * nblk + 1] = b; blk[3 * nblk + 2] = m - b < L ? m - b : L;
                    ++nblk;
                }
            }
        }
    }
    #pragma omp parallel for num_threads(nt) schedule(static, 1)
        for (int64_t b = 0; b < nblk; ++b) {
            const int64_t r = blk[3 * b], f = blk[3 * b + 1], m = blk[3 * b + 2];
            int64_t c[L];
            for (int64_t l = 0; l < L; ++l) c[l] = list[f + (l < m ? l : m - 1)];
            const int64_t *p = pl + 5 * r;
            block(n, (int)spec[r], c, NULL, m, w, ldw, N, nT, woT, ldn, lT, co + 6 * r, perm, absm, sgn,
                  nsg, k, xi, xw, ti, tw, p[0], (const int64_t *)(intptr_t)p[1], (const float *)(intptr_t)p[2],
                  (const int64_t *)(intptr_t)p[3], (const int64_t *)(intptr_t)p[4], NULL, clamp, out);
        }
}

/* A P frame's front-facing (and referenced) vertices, compacted: Q columns of vz (n2, Q, row stride ldz:
   `world_visibility`'s rows in the ZYZ normal frames, the lifted plan's order), nTc, woTc (3, Q contiguous)
   their normals and view directions, idx (Q,) their vertex ids; region r the columns [rsp[2r], rsp[2r+1])
   (empty: not made here), lT, co, spec, pl as `zh33v_view`'s, lp (4) the lifted plan. out (N, 3): the
   rows idx[j] written (the caller zeroed the others). blk scratch (Q / L + nreg + 1, 3). */
void zh33v_pose(int64_t n, int64_t Q, const float *vz, int64_t ldz, const float *nTc, const float *woTc,
                const int64_t *idx, int64_t nreg, const int64_t *rsp, const float *lT, const float *co,
                const int64_t *spec, const int64_t *pl, const int64_t *lp,
                const int64_t *perm, const int64_t *absm, const float *sgn,
                int64_t k, const int64_t *xi, const float *xw, const int64_t *ti, const float *tw,
                int64_t clamp, int64_t *blk, float *out, int64_t nt) {
    const int64_t n2 = n * n;
    float nsg[MAXN2];
    for (int64_t r = 0; r < n2; ++r) nsg[r] = -sgn[r];
    int64_t nblk = 0;
    for (int64_t r = 0; r < nreg; ++r)
        for (int64_t b = rsp[2 * r]; b < rsp[2 * r + 1]; b += L) {
            blk[3 * nblk] = r; blk[3 * nblk + 1] = b; blk[3 * nblk + 2] = rsp[2 * r + 1] - b < L ? rsp[2 * r + 1] - b : L;
            ++nblk;
        }
    #pragma omp parallel for num_threads(nt) schedule(static, 1)
    for (int64_t b = 0; b < nblk; ++b) {
        const int64_t r = blk[3 * b], f = blk[3 * b + 1], m = blk[3 * b + 2];
        int64_t c[L];
        for (int64_t l = 0; l < L; ++l) c[l] = f + (l < m ? l : m - 1);
        const int64_t *p = pl + 5 * r;
        block(n, (int)spec[r], c, idx, m, vz, ldz, Q, nTc, woTc, Q, lT, co + 6 * r, perm, absm, sgn,
              nsg, k, xi, xw, ti, tw, p[0], (const int64_t *)(intptr_t)p[1], (const float *)(intptr_t)p[2],
              (const int64_t *)(intptr_t)p[3], (const int64_t *)(intptr_t)p[4], lp, clamp, out);
    }
}
"""
_VIEW_SIGNATURES = {"zh33v_sq": [_I, _P, _P, _P],
                    "zh33v_pose": [_I, _I, _P, _I, _P, _P, _P, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P, _I, _P, _P, _P,
                                   _P, _I, _P, _P, _I],
                    "zh33v_view": [_I, _I, _P, _P, _P, _I, _P, _I, _P, _I, _P, _P, _P, _P, _P, _P, _P, _P, _I, _P, _P,
                                   _P, _P, _I, _P, _P, _P, _P, _P, _I]}


def _view_lib():
    # (zh43o: through this module's `load`, remembered once loaded; PRTBENCH_COMPILE still read at each call)
    return load("zh33v_view", _VIEW_SOURCE, _VIEW_SIGNATURES,
                extra_flags=("-fopenmp", "-ffp-contract=fast", *native.isa_flags(), *_avx512_flags()))


def view_setup(light: Tensor, kd: Tensor, ks: Tensor, plans: list, tables: tuple) -> tuple | None:
    """The lighting-, material- and plan-dependent arguments of `view_radiance` / `pose_radiance` (kept by
    the caller while those stay), or None where the pass does not take them: light (n², 3) float32 the
    lighting; kd, ks (R, 3) float32 per region its albedos (kd without the 1 / π); plans per region
    `runtime._block_plan` of its Phong operator (scale folded in) or None (no specular term); tables
    `runtime._conjugate_tables` (float32, CPU)."""
    return view_setup_flat(light, kd, ks, [None if p is None else _flat_plan(p) for p in plans], tables, plans)


def view_setup_flat(light: Tensor, kd: Tensor, ks: Tensor, flats: list, tables: tuple, keep: object = None
                    ) -> tuple | None:
    """`view_setup` of the plans already as the C passes read them (`_flat_plan`'s or `phong_flat_plan`'s
    (spans, Kv, cols, src), or None); ``keep``: an object the setup holds alive beside them."""
    R = len(flats)
    if light.dim() != 2 or light.shape[1] != 3 or tuple(kd.shape) != (R, 3) or tuple(ks.shape) != (R, 3) \
            or any(t.dtype != torch.float32 or t.device.type != "cpu" for t in (light, kd, ks)):
        return None
    pl = []
    for f in flats:
        if f is None:
            pl += [0, 0, 0, 0, 0]
            continue
        spans_b, Kv, pcols, psrc = f
        pl += [int(spans_b.shape[0]), spans_b.data_ptr(), Kv.data_ptr(), pcols.data_ptr(), psrc.data_ptr()]
    keep = (keep, flats)
    spec = torch.tensor([f is not None for f in flats], dtype=torch.int64)
    co = torch.cat([kd * (1.0 / math.pi), ks], 1).contiguous()       # (as `ZHShadow._diffuse_ranges`' kd, 1 / π)
    # the plans' addresses as a ctypes array, not a tensor: a method's kept tensors are its state, the same
    # numbers at any thread count (tests/methods/test_threads.py), and addresses differ per process
    return (R, light.T.contiguous(), co, spec, (ctypes.c_int64 * len(pl))(*pl), tables, keep)


def _region_rows(spans: list, R: int, N: int, tile: bool) -> Tensor | None:
    """(2R,) int64 of the regions' column ranges, or None: not R ranges in [0, N) (``tile``: tiling it)."""
    if len(spans) != R:
        return None
    a = 0
    for a0, a1 in spans:
        if a1 < a0 or a0 < 0 or a1 > N or (tile and a0 != a):
            return None
        a = a1
    if tile and a != N:
        return None
    return torch.tensor([x for sp in spans for x in sp], dtype=torch.int64)


def view_radiance(setup: tuple | None, spans: list, pos: Tensor, nT: Tensor, w: Tensor, cam: Tensor,
                  clamp: bool) -> tuple[Tensor, Tensor] | None:
    """((N, 3) radiance, (N,) bool front-facing) of a view frame's vertices by one C pass (above), or None
    where it does not run (no compiler, ``PRTBENCH_ZH_NATIVE=0``, order above `CONJ_MAX_ORDER`, not float32
    CPU arrays of unit column stride, no ``setup``, regions not ranges tiling [0, N)). setup: `view_setup`;
    spans per region (a0, a1); pos (N, 3) posed positions, nT (3, N) unit normals contiguous, w (n², N) the
    cosine-weighted visibility (world SH), cam (3,) the camera origin."""
    lib = _view_lib() if terms_switched_on() else None
    if lib is None or setup is None or w.dim() != 2 or nT.dim() != 2 or pos.dim() != 2:
        return None
    R, lT, co, spec, plt, tables, _ = setup
    n2, N = int(w.shape[0]), int(w.shape[1])
    n = int(round(n2 ** 0.5))
    rsp = _region_rows(spans, R, N, True)
    if rsp is None or n * n != n2 or n > CONJ_MAX_ORDER or tuple(nT.shape) != (3, N) \
            or tuple(pos.shape) != (N, 3) or int(lT.shape[1]) != n2 or cam.numel() != 3:
        return None
    if any(t.dtype != torch.float32 or t.device.type != "cpu" for t in (pos, nT, w, cam)) or not nT.is_contiguous() \
            or w.stride(1) != 1 or not (pos.is_contiguous() and cam.is_contiguous()):
        return None
    perm, absm, sgn, xi, xw, ti, tw = tables
    # |cam − x|: the sums in C, the square root by torch (`_view_directions`' bits: torch's float32 sqrt
    # is not the correctly rounded one on this host — MKL's — and the front test must be torch's)
    sq = torch.empty(N, dtype=torch.float32)
    lib.zh33v_sq(N, pos.data_ptr(), cam.data_ptr(), sq.data_ptr())
    norm = sq.sqrt_()
    woT = torch.empty(3, N, dtype=torch.float32)
    front = torch.empty(N, dtype=torch.bool)
    lst = torch.empty(N, dtype=torch.int64)
    blk = torch.empty(N // 16 + 2 * R + 1, 3, dtype=torch.int64)
    out = torch.empty(N, 3, dtype=torch.float32)
    lib.zh33v_view(n, N, pos.data_ptr(), norm.data_ptr(), nT.data_ptr(), nT.stride(0), w.data_ptr(), w.stride(0),
                   cam.data_ptr(), R, rsp.data_ptr(), lT.data_ptr(), co.data_ptr(), spec.data_ptr(), ctypes.addressof(plt),
                   perm.data_ptr(), absm.data_ptr(), sgn.data_ptr(), int(xi.shape[1]), xi.data_ptr(), xw.data_ptr(),
                   ti.data_ptr(), tw.data_ptr(), int(bool(clamp)), woT.data_ptr(), front.data_ptr(), lst.data_ptr(),
                   blk.data_ptr(), out.data_ptr(), max(1, torch.get_num_threads()))
    return out, front


def pose_radiance(setup: tuple | None, lifted: tuple, spans: list, vz: Tensor, nTc: Tensor, woTc: Tensor,
                  idx: Tensor, out: Tensor, clamp: bool, ids_in_range: bool = False) -> bool:
    """A P frame's radiance of its front-facing vertices (`ZHShadow._front_radiance`) by one C pass: per
    column j of vz (n², Q) — the visibility in the ZYZ normal frames, rows in the lifted plan's order
    (`runtime.world_visibility`, ``frame="zyz"``) — w = `runtime.cosine_visibility_zyz` (``ordered``), then
    kd ⊙ (lᵀ w) / π and for a specular region + ks ⊙ (lᵀ t_s), t_s = `specular_conjugate` of w about
    R = reflect(ωo, n), clamped if asked, written to row idx[j] of out (N, 3); w and t_s never written.
    spans per region its columns (a0, a1) (empty: not made here, e.g. a plane's); nTc, woTc (3, Q)
    contiguous; lifted `runtime._block_plan`(("phong", 1.0), n, True, …). False (out untouched) where it
    does not run (as `view_radiance`). ``ids_in_range``: the caller's idx are known to lie in [0, N) (made by
    `front_regions` for out's N rows: no min / max pass; zh43o). (zh43o: the small arrays — region rows, the
    lifted plan's addresses, the block scratch — as `ctypes` arrays, not tensors: ~0.05 ms of torch calls a P
    frame with the caches cold; the same values.)"""
    lib = _view_lib() if terms_switched_on() else None
    if lib is None or setup is None or vz.dim() != 2:
        return False
    R, lT, co, spec, plt, tables, _ = setup
    n2, Q = int(vz.shape[0]), int(vz.shape[1])
    n = int(round(n2 ** 0.5))
    rsp = None
    if len(spans) == R and all(0 <= a0 <= a1 <= Q for a0, a1 in spans):   # (`_region_rows`' test, ``tile`` off)
        rsp = (ctypes.c_int64 * (2 * R))(*(x for sp in spans for x in sp))
    if rsp is None or n * n != n2 or n > CONJ_MAX_ORDER or tuple(nTc.shape) != (3, Q) \
            or tuple(woTc.shape) != (3, Q) or tuple(idx.shape) != (Q,) or int(lT.shape[1]) != n2 \
            or out.dim() != 2 or out.shape[1] != 3:
        return False
    if any(t.dtype != torch.float32 or t.device.type != "cpu" for t in (vz, nTc, woTc, out)) \
            or idx.dtype != torch.int64 or not (nTc.is_contiguous() and woTc.is_contiguous() and idx.is_contiguous()
                                                and out.is_contiguous()) or vz.stride(1) != 1:
        return False
    if Q and not ids_in_range and (int(idx.min()) < 0 or int(idx.max()) >= out.shape[0]):
        return False
    perm, absm, sgn, xi, xw, ti, tw = tables
    lspans, lKv, _, lsrc = _flat_plan(lifted)
    lp = (ctypes.c_int64 * 4)(len(lifted[2]), lspans.data_ptr(), lKv.data_ptr(), lsrc.data_ptr())
    blk = (ctypes.c_int64 * (3 * (Q // 16 + 2 * R + 1)))()
    lib.zh33v_pose(n, Q, vz.data_ptr(), vz.stride(0), nTc.data_ptr(), woTc.data_ptr(), idx.data_ptr(), R,
                   ctypes.addressof(rsp), lT.data_ptr(), co.data_ptr(), spec.data_ptr(), ctypes.addressof(plt),
                   ctypes.addressof(lp), perm.data_ptr(), absm.data_ptr(), sgn.data_ptr(), int(xi.shape[1]),
                   xi.data_ptr(), xw.data_ptr(), ti.data_ptr(), tw.data_ptr(), int(bool(clamp)), ctypes.addressof(blk),
                   out.data_ptr(), max(1, torch.get_num_threads()))
    return True

# `gouraud.resolve` for the vertex-shaded frames (zh33v): the same C loop (the same sums in the same order:
# the same bits), its range check made in the loop on the entries each sample reads — a hit sample's face
# in [0, M) (a miss reads nothing), its three corners in [0, N) — instead of two `aminmax` passes over the
# G-buffer's faces and the corner table before it, and without the wrapper's steps for the compiled
# fallback (dynamic-shape marks, the views for its blocks): ~0.1-0.2 ms of each vertex-shaded frame at 1
# thread. A bad entry stops the loop before its loads (no read out of bounds) and raises as
# `gouraud.resolve` does; `gouraud.resolve` stays the fallback (and the oracle: tests).
_RESOLVE_SOURCE = r"""
#include <stdint.h>
/* Pixels i0 <= i < i1 of `gouraud`'s resolve3: out[i, c] = (1 / S2) sum over hit sub-samples p of
   (V[F[f, 0], c] (1 - u - v) + V[F[f, 1], c] u) + V[F[f, 2], c] v, F (M, 3) int64 rows, V (N, 3).
   Returns 0, or 1 at the first sample whose face or corner is out of range (nothing read from it). */
static int64_t resolve_range(const int64_t *face, const float *bu, const float *bv, const uint8_t *hit,
                             const int64_t *F, int64_t M, const float *val, int64_t N, int64_t S2, int64_t i0,
                             int64_t i1, float *out) {
    const float inv = 1.0f / (float)S2;
    for (int64_t i = i0; i < i1; ++i) {
        float a0 = 0.0f, a1 = 0.0f, a2 = 0.0f;
        for (int64_t p = i * S2; p < (i + 1) * S2; ++p) {
            if (!hit[p]) continue;
            const int64_t f = face[p];
            if ((uint64_t)f >= (uint64_t)M) return 1;
            const int64_t j0 = F[3 * f], j1 = F[3 * f + 1], j2 = F[3 * f + 2];
            if (((uint64_t)j0 >= (uint64_t)N) | ((uint64_t)j1 >= (uint64_t)N) | ((uint64_t)j2 >= (uint64_t)N)) return 1;
            const float u = bu[p], v = bv[p], w = 1.0f - u - v;
            const float *x = val + 3 * j0, *y = val + 3 * j1, *z = val + 3 * j2;
            a0 += (x[0] * w + y[0] * u) + z[0] * v;
            a1 += (x[1] * w + y[1] * u) + z[1] * v;
            a2 += (x[2] * w + y[2] * u) + z[2] * v;
        }
        out[3 * i] = a0 * inv;
        out[3 * i + 1] = a1 * inv;
        out[3 * i + 2] = a2 * inv;
    }
    return 0;
}
/* Over pixels [0, n) on nt threads, thread k the pixels [n k / nt, n (k + 1) / nt); bad[0] set to 1 when
   any range found an entry out of range. */
void zh33v_resolve(const int64_t *face, const float *bu, const float *bv, const uint8_t *hit, const int64_t *F,
                   int64_t M, const float *val, int64_t N, int64_t S2, int64_t n, int64_t nt, float *out,
                   int64_t *bad) {
    int64_t b = 0;
    if (nt <= 1) {
        b = resolve_range(face, bu, bv, hit, F, M, val, N, S2, 0, n, out);
    } else {
        #pragma omp parallel for num_threads(nt) schedule(static, 1) reduction(|:b)
        for (int64_t k = 0; k < nt; ++k)
            b |= resolve_range(face, bu, bv, hit, F, M, val, N, S2, n * k / nt, n * (k + 1) / nt, out);
    }
    bad[0] = b;
}
"""
_RESOLVE_SIGNATURES = {"zh33v_resolve": [_P, _P, _P, _P, _P, _I, _P, _I, _I, _I, _I, _P, _P]}
# pixels per thread below which one thread resolves the image (`gouraud._NATIVE_MIN_PIXELS`)
MIN_RESOLVE_PIXELS_PER_THREAD = 1 << 13


def _resolve_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75);
    # no ISA flags and no multiply-adds fused: `gouraud`'s loop's build (-O3, the same sums' bits)
    return native.load("zh33v_resolve", _RESOLVE_SOURCE, _RESOLVE_SIGNATURES, extra_flags=("-fopenmp",))


def _resolve_inputs(values: Tensor, F: Tensor, face: Tensor, bary: Tensor, hit: Tensor, P: int
                    ) -> tuple[Tensor, Tensor, Tensor] | None:
    """The resolve loops' inputs (`resolve`, `resolve_table`): (values contiguous, bu, bv) when they are CPU
    tensors of the loops' types — values (N, 3) float32, F (M, 3) int64 contiguous, face (P,) int64, hit (P,)
    bool contiguous, bary (P, 2) float32 — else None (the caller falls back)."""
    if values.dim() != 2 or values.shape[1] != 3 or values.dtype != torch.float32 \
            or F.dtype != torch.int64 or F.dim() != 2 or F.shape[1] != 3 or not F.is_contiguous() \
            or face.dtype != torch.int64 or hit.dtype != torch.bool or bary.dtype != torch.float32 \
            or bary.dim() != 2 or bary.shape[1] != 2 or not (face.is_contiguous() and hit.is_contiguous()) \
            or face.shape[0] != P or hit.shape[0] != P \
            or any(t.device.type != "cpu" for t in (values, F, face, bary, hit)):
        return None
    return values.contiguous(), bary[:, 0].contiguous(), bary[:, 1].contiguous()  # (column-major bary's views)


def resolve(values: Tensor, F: Tensor, face: Tensor, bary: Tensor, hit: Tensor, height: int, width: int,
            spp_side: int) -> Tensor | None:
    """`gouraud.resolve`(values, F.T, face, bary, hit, height, width, spp_side) by one C loop with the
    range check in it (above; the same bits), or None where it does not run (no compiler,
    ``PRTBENCH_ZH_NATIVE=0``, not CPU tensors of the loop's types: values (N, 3) float32, F (M, 3) int64
    contiguous, face (P,) int64, hit (P,) bool, bary (P, 2) float32). ValueError on a face or corner out
    of range, as `gouraud.resolve`."""
    lib = _resolve_lib() if terms_switched_on() else None
    S2 = spp_side * spp_side
    n = height * width
    args = None if lib is None else _resolve_inputs(values, F, face, bary, hit, n * S2)
    if args is None:
        return None
    values, bu, bv = args
    out = torch.empty(n, 3, dtype=torch.float32)
    bad = torch.zeros(1, dtype=torch.int64)
    nt = max(1, min(torch.get_num_threads(), n // MIN_RESOLVE_PIXELS_PER_THREAD))
    lib.zh33v_resolve(face.data_ptr(), bu.data_ptr(), bv.data_ptr(), hit.data_ptr(), F.data_ptr(), int(F.shape[0]),
                      values.data_ptr(), int(values.shape[0]), S2, n, nt, out.data_ptr(), bad.data_ptr())
    if int(bad[0]):
        raise ValueError(f"G-buffer faces or corner rows out of range of {int(F.shape[0])} faces and "
                         f"{int(values.shape[0])} vertex rows (a G-buffer of another mesh?)")
    return out.view(height, width, 3)


# --- zh34v: a B frame's plans of the C passes without the per-exponent torch passes ---------------------
#
# A VB / VBL frame meets a new Phong exponent per specular region, and `ZHShadow._pass_setup` made its plan
# by `runtime._block_plan` (M by `convolution.phong_operator`, K = X M Xᵀ by two float64 GEMMs, the gather
# of the blocks' entries, a copy per block) and `_flat_plan` (their concatenation): ~40 torch and numpy
# steps, 0.13 ms per exponent back to back but ~0.35 ms right after a rasteriser evicted the caches (the
# suite's protocol). M's entries are Σ_k d_k B(α+1, k+1) over the exponent-free moments d (`_u_table`),
# so the blocks' entries of K are linear in the beta row: Kv = G β with G = (X ⊗ X)[flat] · D, made once
# per order and non-zero pattern. Kv equals `_flat_plan`'s to float64 round-off before the float32 cast
# (tests); the rest of the plan (spans, cols, src) is `_plan_layout`'s.
_PHONG_G: dict = {}


def _phong_beta(a: float, k: int):
    import numpy as np

    beta = np.empty(k)
    beta[0] = 1.0 / (a + 1.0)
    for i in range(1, k):                  # (as `phong_operator`'s)
        beta[i] = beta[i - 1] * i / (a + i + 1.0)
    return beta


def phong_flat_plan(alpha: float, order: int, scale: float = 1.0) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """`_flat_plan`(`runtime._block_plan`(("phong", alpha), order, False, float32, "cpu", scale)) — spans,
    Kv, cols, src as the C passes read them — by one product with the exponent's beta row (above), kept
    per exponent (a plan per exponent, as `_block_plan`'s cache)."""
    import numpy as np
    from methods.zh_shadow import convolution as cv
    from methods.zh_shadow import runtime as rt

    key = (float(alpha), int(order), float(scale))
    hit = _PHONG_G.get(key)
    if hit is not None:
        return hit
    a = cv._check(alpha, order)
    n2 = order * order
    I, J, D = cv._u_table(order)
    beta = _phong_beta(a, D.shape[1])
    acc = D @ beta                                      # M's entries (i <= j), as `phong_operator` sums them
    nz = acc != 0
    lkey = (int(order), nz.tobytes())
    lay = _PHONG_G.get(lkey)
    if lay is None:
        pattern = np.zeros((n2, n2), dtype=bool)
        pattern[I[nz], J[nz]] = pattern[J[nz], I[nz]] = True
        cols, src, spans, flat = rt._plan_layout(pattern.tobytes(), order, False, "cpu")
        X = rt._zyz_tables(order)[3].numpy()
        f = flat.numpy()
        ra, rb = f // n2, f % n2                      # K[ra, rb] = Σ_(i,j) X[ra, i] M[i, j] X[rb, j]
        A = X[ra][:, I] * X[rb][:, J]
        off = I != J                                  # (M symmetric: its (j, i) entry too)
        A[:, off] += X[ra][:, J[off]] * X[rb][:, I[off]]
        A[:, ~nz] = 0.0
        G = A @ D
        lay = (torch.tensor([list(s) for s in spans], dtype=torch.int64).contiguous(), G,
               cols.to(torch.int64).contiguous(), src.to(torch.int64).contiguous())
        _PHONG_G[lkey] = lay
    spans, G, cols, src = lay
    Kv = G @ beta
    if scale != 1.0:
        Kv = Kv * scale
    out = (spans, torch.from_numpy(Kv).to(torch.float32), cols, src)
    if len(_PHONG_G) > 256:
        _PHONG_G.clear()
    _PHONG_G[key] = out
    return out


# -- zh34p ------------------------------------------------------------------------------------------
# A per-vertex table (`runtime.vertex_table`) — U[i] = v[row_i] @ W_{region(row_i)}, (n², 3K) per region
# — by one C pass over the rows (`vertex_table`): the rows a frame's points reference taken straight from
# v through their ids (no gather of v and of the regions first), each row's n² products summed in order
# in multiply-adds, 8 columns a vector, the region's table in the L1 cache. The same products as the
# GEMMs' to float32 round-off (their sum order and fusing differ). Bench creature, paper setting, 1
# thread: the 3.6 K referenced rows of a VL / P frame (n² = 16, 3K = 240) took ~1.1 ms of sgemm (K = 16
# is short: the GEMM streams its packed panels for 3.8 K multiply-adds a row) and the gathers ~0.2 ms.
# Also the plane term's v · T¹(n0) (`ZHShadow._plane_term`: (N, 16) @ (16, 3), ~0.36 ms of sgemm).
_VTABLE_SOURCE = r"""
#include <stdint.h>
#include <string.h>
typedef float v8 __attribute__((vector_size(32)));
static inline v8 ld8(const float* p) { v8 v; memcpy(&v, p, 32); return v; }
static inline void st8(float* p, v8 v) { memcpy(p, &v, 32); }

/* U[i, :] (NU, C) = sum_j v[row, j] W[r, j, :] (j ascending) with row = idx[i] (idx NULL: i), r = vreg[row]
   (R == 1: r = 0 for every row), zeros where r is outside [0, R); W (R, n2, C), v (N, n2) row-major.
   bad[0]: rows outside [0, N) (their U rows left unwritten). Rows split over nt threads: each row one
   thread's, the same bits at any thread count. */
/* out[c] for the columns c >= c0 of the row x of one region's table w (n2, C) */
static inline void vrow(const float* x, const float* w, int64_t n2, int64_t C, float* out, int64_t c0) {
    for (; c0 + 64 <= C; c0 += 64) {
        v8 a[8];
        for (int k = 0; k < 8; ++k) a[k] = x[0] * ld8(w + c0 + 8 * k);
        for (int64_t j = 1; j < n2; ++j)
            for (int k = 0; k < 8; ++k) a[k] = a[k] + x[j] * ld8(w + j * C + c0 + 8 * k);
        for (int k = 0; k < 8; ++k) st8(out + c0 + 8 * k, a[k]);
    }
    for (; c0 + 8 <= C; c0 += 8) {
        v8 a = x[0] * ld8(w + c0);
        for (int64_t j = 1; j < n2; ++j) a = a + x[j] * ld8(w + j * C + c0);
        st8(out + c0, a);
    }
    for (; c0 < C; ++c0) {
        float a = x[0] * w[c0];
        for (int64_t j = 1; j < n2; ++j) a = a + x[j] * w[j * C + c0];
        out[c0] = a;
    }
}

/* U[i, :] (NU, C) = sum_j v[row, j] W[r, j, :] (j ascending) with row = idx[i] (idx NULL: i), r = vreg[row]
   (R == 1: r = 0 for every row), zeros where r is outside [0, R); W (R, n2, C), v (N, n2) row-major.
   bad[0]: rows outside [0, N) (their U rows left unwritten). Rows split over nt threads: each row one
   thread's, the same bits at any thread count. */
void zh34p_vtable(int64_t NU, const int64_t* idx, const float* v, int64_t N, int64_t n2, const int64_t* vreg,
                  int64_t R, const float* W, int64_t C, float* U, int64_t nt, int64_t* bad) {
    int64_t nb = 0;
#pragma omp parallel for num_threads(nt) schedule(static) reduction(+:nb) if(nt > 1)
    for (int64_t i = 0; i < NU; ++i) {
        const int64_t row = idx ? idx[i] : i;
        float* out = U + i * C;
        if ((uint64_t)row >= (uint64_t)N) { ++nb; continue; }
        const int64_t r = R == 1 ? 0 : vreg[row];
        if ((uint64_t)r >= (uint64_t)R) { memset(out, 0, sizeof(float) * (size_t)C); continue; }
        vrow(v + row * n2, W + r * n2 * C, n2, C, out, 0);
    }
    bad[0] = nb;
}
"""
_VTABLE_SIGNATURES = {"zh34p_vtable": [_I, _P, _P, _I, _I, _P, _I, _P, _I, _P, _I, _P]}
MIN_ROWS_PER_VTABLE_THREAD = 1024   # table rows below which one thread builds them


def _vtable_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75);
    # multiply-adds fused (float32 round-off against the GEMMs)
    return load("zh34p_vtable", _VTABLE_SOURCE, _VTABLE_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=fast", *native.isa_flags()))


def vertex_table(v: Tensor, vreg: Tensor, W: Tensor, idx: Tensor | None = None, out: Tensor | None = None,
                 wide: bool = False) -> Tensor | None:
    """(NU, C) float32: row i = v[idx[i]] @ W[vreg[idx[i]]] (idx None: every row of v, NU = N; W (R, n², C)
    float32 the per-region tables; R == 1: W[0] for every row; a region outside [0, R): a zero row) by
    `zh34p_vtable` — float32 round-off of the products — or None where it does not run (no compiler,
    ``PRTBENCH_ZH_NATIVE=0``, not CPU float32 / int64 arrays of these shapes, an id outside [0, N)).
    ``out`` (NU, C) float32 contiguous: written there (and returned). ``wide``: `zh38v_vtable`'s loop with
    16-float vectors where it runs (`native_vtable16`, zh40p: the same bits)."""
    fn = _vtable_resolve(wide)
    if fn is None:
        return None
    return _vtable_run(fn, torch.zeros(1, dtype=torch.int64), v, vreg, W, idx, out)


def _vtable_resolve(wide: bool):
    """The C function `vertex_table`(…, ``wide``) runs, or None (no library, switched off)."""
    lib = _vtable_lib() if terms_switched_on() else None
    if lib is None:
        return None
    lib4 = _vtable4_lib() if VTABLE_ROWS4 else None   # (four rows a load of W where it builds: the same bits)
    fn = lib.zh34p_vtable if lib4 is None else lib4.zh38v_vtable
    if wide and lib4 is not None:
        from methods.zh_shadow import native_vtable16

        lw = native_vtable16.lib()
        fn = fn if lw is None else lw.zh40p_vtable
    return fn


def _vtable_run(fn, bad: Tensor, v: Tensor, vreg: Tensor, W: Tensor, idx: Tensor | None, out: Tensor | None
                ) -> Tensor | None:
    """`vertex_table`'s checks and call of ``fn`` (`_vtable_resolve`), bad (1,) int64 scratch (zeroed here)."""
    if v.dtype != torch.float32 or v.dim() != 2 or W.dtype != torch.float32 or W.dim() != 3 \
            or W.shape[1] != v.shape[1] or vreg.dtype != torch.int64 or vreg.shape != (v.shape[0],) \
            or (idx is not None and (idx.dtype != torch.int64 or idx.dim() != 1)) \
            or any(t.device.type != "cpu" for t in (v, vreg, W)) or (idx is not None and idx.device.type != "cpu"):
        return None
    v, vreg, W = v.contiguous(), vreg.contiguous(), W.contiguous()
    if idx is not None:
        idx = idx.contiguous()
    N, n2 = int(v.shape[0]), int(v.shape[1])
    R, C = int(W.shape[0]), int(W.shape[2])
    NU = N if idx is None else int(idx.shape[0])
    if out is not None and (out.shape != (NU, C) or out.dtype != torch.float32 or not out.is_contiguous()
                            or out.device.type != "cpu"):
        return None
    U = torch.empty(NU, C, dtype=torch.float32) if out is None else out
    bp = bad.data_ptr()
    ctypes.memset(bp, 0, 8)
    nt = max(1, min(torch.get_num_threads(), NU // MIN_ROWS_PER_VTABLE_THREAD))
    fn(NU, 0 if idx is None else idx.data_ptr(), v.data_ptr(), N, n2, vreg.data_ptr(), R, W.data_ptr(), C,
       U.data_ptr(), nt, bp)
    return None if ctypes.c_int64.from_address(bp).value else U


class VTableBound:
    """`vertex_table`(…, ``wide``) with its C function resolved once (`vtable_bind`, zh46): per call the arrays'
    checks and the call (the same loop, the same bits). The three libraries' look-ups (each reading the switches
    and the ISA flags) were ~0.05 ms of serial Python a bench P frame with the caches cold. The switches are the
    caller's to read."""

    __slots__ = ("wide", "fn", "bad")

    def __call__(self, v: Tensor, vreg: Tensor, W: Tensor, idx: Tensor | None = None, out: Tensor | None = None
                 ) -> Tensor | None:
        return _vtable_run(self.fn, self.bad, v, vreg, W, idx, out)


def vtable_bind(wide: bool = False) -> VTableBound | None:
    """A `VTableBound` of `vertex_table`(…, ``wide``), or None where it would not run."""
    fn = _vtable_resolve(wide)
    if fn is None:
        return None
    b = VTableBound()
    b.wide, b.fn, b.bad = bool(wide), fn, torch.zeros(1, dtype=torch.int64)
    return b


# --- zh35o ------------------------------------------------------------------------------------------------
#
# A P frame's pose product for the vertices it needs alone. `runtime.world_visibility` forms [pose, 1] · X
# over every vertex (X streamed once, (J+1)·N·c(2+n) floats: 11.8 MB on the bench creature at order 8) and
# then gathers the front-facing, referenced vertices' columns (4.3 K of 13.4 K on a bench P frame) — the
# count (`ZHShadow.frame_cost`) credits only those columns' rows of X. With X laid out vertex-major
# ((N, J+1, d) in memory, `vertex_major`: each vertex's J+1 rows one contiguous 880-byte block at order 8,
# two lobes) the product reads exactly the blocks of the vertices asked for, in ascending order. Each output
# sums its J+1 terms in the same order as `runtime._pose_product` (i = 0, 1, …, J; products and sums not
# fused: `-ffp-contract=off`), so the same bits (tested); the vertices split over the threads (each output
# one thread's: the same bits at any thread count).
_POSE_COLS_SOURCE = r"""
#include <stdint.h>
#include <string.h>
#define DMAX 256
typedef float v16 __attribute__((vector_size(64)));
typedef float v4 __attribute__((vector_size(16)));
#ifndef PF_AHEAD
#define PF_AHEAD 8
#endif
/* out[k * Q + q] = sum_i a[i] X[(j * J1 + i) * d + k], j = idx[q] (idx NULL: j = q), the terms added
   i = 0, 1, ..., J1 - 1, for q0 <= q < q1. Returns 1 at the first id out of [0, N) (nothing read from it). */
static int64_t cols_range(int64_t J1, int64_t d, const float *a, const float *X, const int64_t *idx, int64_t N,
                          int64_t Q, int64_t q0, int64_t q1, float *out) {
    float acc[DMAX];
    for (int64_t q = q0; q < q1; ++q) {
        const int64_t j = idx ? idx[q] : q;
        if ((uint64_t)j >= (uint64_t)N) return 1;
        if (idx && q + PF_AHEAD < q1) {
            const int64_t jn = idx[q + PF_AHEAD];
            if ((uint64_t)jn < (uint64_t)N) {
                const char *p = (const char *)(X + jn * J1 * d);
                for (int64_t b = 0; b < J1 * d * 4; b += 64) __builtin_prefetch(p + b, 0, 3);
            }
        }
        const float *x = X + j * J1 * d;
        if (d == 20) {   /* order 8, two lobes: the 20 sums as a 16- and a 4-lane vector (the same operations) */
            v16 s, xv;
            v4 s4, x4;
            memcpy(&xv, x, 64); memcpy(&x4, x + 16, 16);
            s = 0.0f + a[0] * xv; s4 = 0.0f + a[0] * x4;
            for (int64_t i = 1; i < J1; ++i) {
                memcpy(&xv, x + i * 20, 64); memcpy(&x4, x + i * 20 + 16, 16);
                s = s + a[i] * xv; s4 = s4 + a[i] * x4;
            }
            for (int k = 0; k < 16; ++k) out[k * Q + q] = s[k];
            for (int k = 0; k < 4; ++k) out[(16 + k) * Q + q] = s4[k];
            continue;
        }
        for (int64_t k = 0; k < d; ++k) acc[k] = 0.0f + a[0] * x[k];
        for (int64_t i = 1; i < J1; ++i) {
            const float ai = a[i];
            const float *xi = x + i * d;
            for (int64_t k = 0; k < d; ++k) acc[k] = acc[k] + ai * xi[k];
        }
        for (int64_t k = 0; k < d; ++k) out[k * Q + q] = acc[k];
    }
    return 0;
}
void zh35o_pose_cols(int64_t J1, int64_t d, const float *a, const float *X, const int64_t *idx, int64_t N,
                     int64_t Q, int64_t nt, float *out, int64_t *bad) {
    int64_t b = 0;
    if (nt <= 1) {
        b = cols_range(J1, d, a, X, idx, N, Q, 0, Q, out);
    } else {
        #pragma omp parallel for num_threads(nt) schedule(static, 1) reduction(|:b)
        for (int64_t t = 0; t < nt; ++t)
            b |= cols_range(J1, d, a, X, idx, N, Q, Q * t / nt, Q * (t + 1) / nt, out);
    }
    bad[0] = b;
}
"""
_POSE_COLS_SIGNATURES = {"zh35o_pose_cols": [_I, _I, _P, _P, _P, _I, _I, _I, _P, _P]}
POSE_COLS_DMAX = 256
MIN_COLS_PER_POSE_THREAD = 1024     # vertices per thread below which one thread forms the product


def _pose_cols_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75);
    # products and sums not fused: `runtime._pose_product`'s bits
    return native.load("zh35o_pose_cols", _POSE_COLS_SOURCE, _POSE_COLS_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", *native.isa_flags(), *_avx512_flags()))


def pose_cols_available() -> bool:
    """Whether `pose_columns` can run here (a compiler, ``PRTBENCH_COMPILE`` / ``PRTBENCH_ZH_NATIVE`` on)."""
    return terms_switched_on() and _pose_cols_lib() is not None


def is_vertex_major(X: Tensor) -> bool:
    """Whether X (J+1, N, d) is laid out (N, J+1, d) in memory (`vertex_major`'s layout)."""
    return X.dim() == 3 and X.permute(1, 0, 2).is_contiguous()


def vertex_major(X: Tensor) -> Tensor:
    """X (J+1, N, d) with its memory laid out (N, J+1, d): the same values, the layout `pose_columns`
    reads (X itself if it already is)."""
    return X if is_vertex_major(X) else X.permute(1, 0, 2).contiguous().permute(1, 0, 2)


def pose_columns(X: Tensor, a: Tensor, idx: Tensor | None = None) -> Tensor | None:
    """(d, Q) float32: column q = Σ_i a[i] X[i, idx[q]] (idx None: every vertex, Q = N) — the columns idx
    of `runtime._pose_product`(a, X) in `runtime.world_visibility`'s point-minor layout, the same bits —
    by `zh35o_pose_cols` (above), or None where it does not run (no compiler, ``PRTBENCH_ZH_NATIVE=0``, X
    not float32 CPU (J+1, N, d) laid out vertex-major (`vertex_major`), d above `POSE_COLS_DMAX`, a (J+1,)
    not float32, idx not int64, an id outside [0, N))."""
    lib = _pose_cols_lib() if terms_switched_on() else None
    if lib is None or X.dtype != torch.float32 or X.device.type != "cpu" or not is_vertex_major(X) \
            or a.dtype != torch.float32 or a.device.type != "cpu" or a.dim() != 1 or a.shape[0] != X.shape[0] \
            or X.shape[2] > POSE_COLS_DMAX or X.shape[2] < 1 \
            or (idx is not None and (idx.dtype != torch.int64 or idx.dim() != 1 or idx.device.type != "cpu")):
        return None
    J1, N, d = (int(s) for s in X.shape)
    a = a.contiguous()
    if idx is not None:
        idx = idx.contiguous()
    Q = N if idx is None else int(idx.shape[0])
    out = torch.empty(d, Q, dtype=torch.float32)
    bad = torch.zeros(1, dtype=torch.int64)
    nt = max(1, min(torch.get_num_threads(), Q // MIN_COLS_PER_POSE_THREAD))
    lib.zh35o_pose_cols(J1, d, a.data_ptr(), X.data_ptr(), 0 if idx is None else idx.data_ptr(), N, Q, nt,
                        out.data_ptr(), bad.data_ptr())
    return None if int(bad[0]) else out


# --- zh35o: a pose's skinning (`ZHShadow._posed_geometry`) ---------------------------------------------------
#
# `Scene.geometry(pose)` spends ~0.6 ms of a bench P frame (1 thread, cooled by the rasteriser) in
# `Skeleton.forward_kinematics` (~40 torch ops on 4 × 4 matrices) and ~0.7 ms in `skeleton.blend_skin`
# (compiled; 9.7 K creature vertices) and its copies. Here one C call: the forward kinematics of the J
# joints (Rodrigues per joint, T_j = T_parent L_j, in float64; the transforms then float32 as
# `blend_skin` takes them), then per vertex of the skinned ranges the blended map a = w · T12, V' = A V + t
# and the cofactor of A times N renormalised — `blend_skin`'s operations in float32 (equal to
# `Scene.geometry` to float32 round-off, tested); the vertices split over the threads (each vertex one
# thread's: the same bits at any thread count). The other vertices' rows are copied.
_SKIN_SOURCE = r"""
#include <math.h>
#include <stdint.h>
#include <string.h>
#define JMAX 256
static void fk(int64_t J, const int64_t *parent, const float *jp, const float *axis, const float *pose, float *T12) {
    double T[JMAX][12];
    for (int64_t j = 0; j < J; ++j) {
        const double x = axis[3 * j], y = axis[3 * j + 1], z = axis[3 * j + 2], th = pose[j];
        const double c = cos(th), s = sin(th), o = 1.0 - c;
        const double K[3][3] = {{0.0, -z, y}, {z, 0.0, -x}, {-y, x, 0.0}};
        double L[12];
        for (int r = 0; r < 3; ++r)
            for (int k = 0; k < 3; ++k) {
                double kk = K[r][0] * K[0][k] + K[r][1] * K[1][k] + K[r][2] * K[2][k];
                L[4 * r + k] = (r == k ? 1.0 : 0.0) + s * K[r][k] + o * kk;
            }
        const double px = jp[3 * j], py = jp[3 * j + 1], pz = jp[3 * j + 2];
        for (int r = 0; r < 3; ++r)
            L[4 * r + 3] = (r == 0 ? px : r == 1 ? py : pz) - (L[4 * r] * px + L[4 * r + 1] * py + L[4 * r + 2] * pz);
        const int64_t p = parent[j];
        if (p < 0) {
            memcpy(T[j], L, sizeof L);
        } else {
            for (int r = 0; r < 3; ++r) {
                for (int k = 0; k < 4; ++k)
                    T[j][4 * r + k] = T[p][4 * r] * L[k] + T[p][4 * r + 1] * L[4 + k] + T[p][4 * r + 2] * L[8 + k]
                                      + (k == 3 ? T[p][4 * r + 3] : 0.0);
            }
        }
        for (int k = 0; k < 12; ++k) T12[12 * j + k] = (float)T[j][k];
    }
}
static void blend_range(int64_t J, const float *T12, const float *V, const float *N, const float *w, int64_t i0,
                        int64_t i1, float *Vo, float *No) {
    for (int64_t i = i0; i < i1; ++i) {
        float a[12];
        for (int k = 0; k < 12; ++k) a[k] = 0.0f;
        const float *wi = w + i * J;
        for (int64_t j = 0; j < J; ++j) {
            const float wj = wi[j];
            if (wj == 0.0f) continue;
            for (int k = 0; k < 12; ++k) a[k] += wj * T12[12 * j + k];
        }
        const float x = V[3 * i], y = V[3 * i + 1], z = V[3 * i + 2];
        for (int r = 0; r < 3; ++r) Vo[3 * i + r] = a[4 * r] * x + a[4 * r + 1] * y + a[4 * r + 2] * z + a[4 * r + 3];
        /* columns c_k = (a[k], a[4 + k], a[8 + k]); cof = (c1 x c2, c2 x c0, c0 x c1) as columns */
        const float c0[3] = {a[0], a[4], a[8]}, c1[3] = {a[1], a[5], a[9]}, c2[3] = {a[2], a[6], a[10]};
        const float k0[3] = {c1[1] * c2[2] - c1[2] * c2[1], c1[2] * c2[0] - c1[0] * c2[2], c1[0] * c2[1] - c1[1] * c2[0]};
        const float k1[3] = {c2[1] * c0[2] - c2[2] * c0[1], c2[2] * c0[0] - c2[0] * c0[2], c2[0] * c0[1] - c2[1] * c0[0]};
        const float k2[3] = {c0[1] * c1[2] - c0[2] * c1[1], c0[2] * c1[0] - c0[0] * c1[2], c0[0] * c1[1] - c0[1] * c1[0]};
        const float nx = N[3 * i], ny = N[3 * i + 1], nz = N[3 * i + 2];
        float n[3];
        for (int r = 0; r < 3; ++r) n[r] = k0[r] * nx + k1[r] * ny + k2[r] * nz;
        float l = sqrtf(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]);
        const float inv = 1.0f / (l > 1e-12f ? l : 1e-12f);
        for (int r = 0; r < 3; ++r) No[3 * i + r] = n[r] * inv;
    }
}
/* V, N, Vo, No (n, 3); ranges (S, 2) the skinned vertex ranges [a, b), wofs (S,) each range's first row in
   the weights w (sum of the range lengths, J); the other rows copied from V, N. */
void zh35o_skin(int64_t J, const int64_t *parent, const float *jp, const float *axis, const float *pose, int64_t n,
                const float *V, const float *N, int64_t S, const int64_t *ranges, const int64_t *wofs, const float *w,
                float *Vo, float *No, float *T12, int64_t nt) {
    fk(J, parent, jp, axis, pose, T12);
    memcpy(Vo, V, sizeof(float) * 3 * n);
    memcpy(No, N, sizeof(float) * 3 * n);
    for (int64_t s = 0; s < S; ++s) {
        const int64_t a = ranges[2 * s], b = ranges[2 * s + 1];
        const float *ws = w + wofs[s] * J - a * J;
        if (nt <= 1 || b - a < 2048) {
            blend_range(J, T12, V, N, ws, a, b, Vo, No);
        } else {
            #pragma omp parallel for num_threads(nt) schedule(static, 1)
            for (int64_t t = 0; t < nt; ++t)
                blend_range(J, T12, V, N, ws, a + (b - a) * t / nt, a + (b - a) * (t + 1) / nt, Vo, No);
        }
    }
}
"""
_SKIN_SIGNATURES = {"zh35o_skin": [_I, _P, _P, _P, _P, _I, _P, _P, _I, _P, _P, _P, _P, _P, _P, _I]}
SKIN_JMAX = 256


def _skin_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75)
    return native.load("zh35o_skin", _SKIN_SOURCE, _SKIN_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", *native.isa_flags()))


def skin_setup(scene) -> tuple | None:
    """The constant arguments of `skin` for ``scene`` (a skeleton, skin weights per shape), or None where the
    pass does not take them (no skeleton, more than `SKIN_JMAX` joints, not float32 CPU arrays)."""
    sk, sw = scene.skeleton, scene.skin_weights
    if sk is None or sw is None:
        return None
    g = scene.rest_geometry()
    J = sk.num_joints
    if J > SKIN_JMAX or g.V.dtype != torch.float32 or g.N.dtype != torch.float32 or g.V.device.type != "cpu":
        return None
    ranges, ws, ofs = [], [], 0
    for i, s in enumerate(scene.shapes):
        if s.name not in sw:
            continue
        a, b = int(g.vertex_offset[i]), int(g.vertex_offset[i + 1])
        w = sw[s.name]
        if tuple(w.shape) != (b - a, J):
            return None
        ranges.append((a, b))
        ws.append((ofs, w.to(torch.float32).contiguous()))
        ofs += b - a
    if not ranges:
        return None
    wcat = torch.cat([w for _, w in ws]) if len(ws) > 1 else ws[0][1]
    rng = torch.tensor(ranges, dtype=torch.int64).reshape(-1, 2).contiguous()
    wofs = torch.tensor([o for o, _ in ws], dtype=torch.int64)
    return (J, sk.parents.to(torch.int64).contiguous(), sk.joint_positions.float().contiguous(),
            sk.axes.float().contiguous(), g.V.contiguous(), g.N.contiguous(), rng, wofs, wcat.contiguous())


def skin(setup: tuple | None, pose: Tensor) -> tuple[Tensor, Tensor] | None:
    """The posed (V, N) (n, 3) float32 of ``setup`` (`skin_setup`) at ``pose`` (J,) by `zh35o_skin` (above;
    `Scene.geometry`'s to float32 round-off), or None where it does not run (no compiler,
    ``PRTBENCH_ZH_NATIVE=0``, no setup, a pose not (J,) float32 CPU). The pose's range checks are the
    caller's (`Skeleton.check_pose`)."""
    lib = _skin_lib() if terms_switched_on() else None
    if lib is None or setup is None:
        return None
    J, par, jp, ax, V, N, rng, wofs, w = setup
    if pose.dtype != torch.float32 or pose.device.type != "cpu" or tuple(pose.shape) != (J,):
        return None
    pose = pose.contiguous()
    n = int(V.shape[0])
    Vo, No = torch.empty(n, 3, dtype=torch.float32), torch.empty(n, 3, dtype=torch.float32)
    T12 = torch.empty(J, 12, dtype=torch.float32)
    nt = max(1, min(torch.get_num_threads(), n // 4096))
    lib.zh35o_skin(J, par.data_ptr(), jp.data_ptr(), ax.data_ptr(), pose.data_ptr(), n, V.data_ptr(), N.data_ptr(),
                   int(rng.shape[0]), rng.data_ptr(), wofs.data_ptr(), w.data_ptr(), Vo.data_ptr(), No.data_ptr(),
                   T12.data_ptr(), nt)
    return Vo, No


# --- zh35o: a P frame's front-facing, referenced vertices (`ZHShadow._front_radiance`) ----------------------
#
# `_front_radiance` found them by torch passes over every vertex — the normals' rows (`runtime.rows`), the
# directions to the camera (`_view_directions`), n·ωo (`runtime.dot_T`), the test, `&` the referenced mask,
# `nonzero` and three column gathers: ~1 ms of a bench P frame cooled by the rasteriser (1 thread). Here one
# loop over the referenced vertices alone: ωo = (cam − x) / max(|cam − x|, 1e-12) (the sums as
# `_view_directions`' — the square root IEEE's, torch's here is MKL's: round-off), n·ωo as `runtime.dot_T`
# (two fused multiply-adds), and for n·ωo > 0 the vertex's id, normal and ωo appended as columns.
_FRONT_SOURCE = r"""
#include <math.h>
#include <stdint.h>
/* pos, nrm (N, 3) rows; ref (N,) uint8; cam (3,). Out: idx (N,) the ids of the referenced vertices with
   n . wo > 0, ascending, cnT and cwo (3, ld) their normals and directions as columns; returns their count
   in cnt[0]. */
/* the front test's loop (zh35o_front, zh43o_front): the ids of the referenced vertices with n . wo > 0,
   ascending, into idx; their normals and directions as columns of leading dimension ld; returns their count */
static int64_t front_loop(int64_t N, const float *pos, const float *nrm, const uint8_t *ref, const float *cam,
                          int64_t ld, int64_t *idx, float *cnT, float *cwo) {
    const float c0 = cam[0], c1 = cam[1], c2 = cam[2];
    int64_t Q = 0;
    for (int64_t j = 0; j < N; ++j) {
        if (!ref[j]) continue;
        const float x0 = c0 - pos[3 * j], x1 = c1 - pos[3 * j + 1], x2 = c2 - pos[3 * j + 2];
        const float x00 = x0 * x0, x11 = x1 * x1, x22 = x2 * x2;
        float nn = sqrtf((x00 + x11) + x22);
        nn = nn < 1e-12f ? 1e-12f : nn;
        const float w0 = x0 / nn, w1 = x1 / nn, w2 = x2 / nn;
        const float n0 = nrm[3 * j], n1 = nrm[3 * j + 1], n2 = nrm[3 * j + 2];
        const float d = fmaf(n2, w2, fmaf(n1, w1, n0 * w0));
        if (d > 0.0f) {
            idx[Q] = j;
            cnT[Q] = n0; cnT[ld + Q] = n1; cnT[2 * ld + Q] = n2;
            cwo[Q] = w0; cwo[ld + Q] = w1; cwo[2 * ld + Q] = w2;
            ++Q;
        }
    }
    return Q;
}

void zh35o_front(int64_t N, const float *pos, const float *nrm, const uint8_t *ref, const float *cam, int64_t ld,
                 int64_t *idx, float *cnT, float *cwo, int64_t *cnt) {
    cnt[0] = front_loop(N, pos, nrm, ref, cam, ld, idx, cnT, cwo);
}

/* zh43o: `zh35o_front`'s loop (the same statements: the same bits), its columns written straight into the
   compact (3, Q) layout (cnT, cwo (3 N) each, rows 1, 2 moved down to Q after the loop: no copies by the
   caller), and per region of the nreg ranges bnd (nreg + 1 ascending starts, then the end) the column bounds
   cnt[1 .. nreg + 1] (how many ids lie below each: `torch.searchsorted`'s left side, the ids ascending) and
   in cnt[2 + nreg + r] whether region r's columns all hold its first column's normal (float ==, as
   `ZHShadow._front_planes`' ``(blk == blk[:, :1]).all()``; 1 for an empty region). */
void zh43o_front(int64_t N, const float *pos, const float *nrm, const uint8_t *ref, const float *cam,
                 int64_t nreg, const int64_t *bnd, int64_t *idx, float *cnT, float *cwo, int64_t *cnt) {
    const int64_t ld = N;
    const int64_t Q = front_loop(N, pos, nrm, ref, cam, ld, idx, cnT, cwo);
    for (int64_t q = 0; q < Q; ++q) { cnT[Q + q] = cnT[ld + q]; cwo[Q + q] = cwo[ld + q]; }
    for (int64_t q = 0; q < Q; ++q) { cnT[2 * Q + q] = cnT[2 * ld + q]; cwo[2 * Q + q] = cwo[2 * ld + q]; }
    cnt[0] = Q;
    int64_t q = 0;
    for (int64_t b = 0; b <= nreg; ++b) {
        while (q < Q && idx[q] < bnd[b]) ++q;
        cnt[1 + b] = q;
    }
    for (int64_t r = 0; r < nreg; ++r) {
        const int64_t b0 = cnt[1 + r], b1 = cnt[2 + r];
        int all = 1;
        for (int64_t k = b0 + 1; k < b1 && all; ++k)
            all = cnT[k] == cnT[b0] && cnT[Q + k] == cnT[Q + b0] && cnT[2 * Q + k] == cnT[2 * Q + b0];
        cnt[2 + nreg + r] = all;
    }
}

/* zh43o: a P frame's plane rows (`ZHShadow._front_radiance`): for j in [b0, b1) row idx[j] of out (N, 3) =
   g (3, n2) . vz[:, j] (vz rows of stride ldz), the n2 products summed in k order (float32, no multiply-add
   fused), 64 columns at a time. */
void zh43o_plane(int64_t n2, const float *g, const float *vz, int64_t ldz, int64_t b0, int64_t b1,
                 const int64_t *idx, float *out) {
    for (int64_t j0 = b0; j0 < b1; j0 += 64) {
        const int64_t m = b1 - j0 < 64 ? b1 - j0 : 64;
        float a0[64], a1[64], a2[64];
        for (int64_t l = 0; l < 64; ++l) { a0[l] = 0.0f; a1[l] = 0.0f; a2[l] = 0.0f; }
        for (int64_t k = 0; k < n2; ++k) {
            const float g0 = g[k], g1 = g[n2 + k], g2 = g[2 * n2 + k];
            const float *v = vz + k * ldz + j0;
            for (int64_t l = 0; l < m; ++l) { a0[l] += g0 * v[l]; a1[l] += g1 * v[l]; a2[l] += g2 * v[l]; }
        }
        for (int64_t l = 0; l < m; ++l) {
            const int64_t q = idx[j0 + l];
            out[3 * q] = a0[l]; out[3 * q + 1] = a1[l]; out[3 * q + 2] = a2[l];
        }
    }
}
"""
_FRONT_SIGNATURES = {"zh35o_front": [_I, _P, _P, _P, _P, _I, _P, _P, _P, _P],
                     "zh43o_front": [_I, _P, _P, _P, _P, _I, _P, _P, _P, _P, _P],
                     "zh43o_plane": [_I, _P, _P, _I, _I, _I, _P, _P]}


def _front_lib():
    # (zh43o: through this module's `load`, remembered once loaded; PRTBENCH_COMPILE still read at each call)
    return load("zh35o_front", _FRONT_SOURCE, _FRONT_SIGNATURES,
                extra_flags=("-ffp-contract=off", *native.isa_flags()))


def front_columns(pos: Tensor, nrm: Tensor, ref: Tensor, cam: Tensor) -> tuple[Tensor, Tensor, Tensor] | None:
    """(idx (Q,) int64 ascending, nTc (3, Q), woTc (3, Q) contiguous float32): the referenced vertices (``ref``
    (N,) bool) whose unit normal faces the camera at ``cam`` (3,) (n·ωo > 0, ωo the unit direction from the
    vertex at ``pos`` (N, 3) to the camera), their normals (``nrm`` (N, 3)) and ωo as columns — torch's
    `_view_directions` + `runtime.dot_T` + gathers to float32 round-off — by `zh35o_front` (above), or None
    where it does not run (no compiler, ``PRTBENCH_ZH_NATIVE=0``, not float32 / bool CPU arrays of these
    shapes)."""
    lib = _front_lib() if terms_switched_on() else None
    if lib is None or pos.dim() != 2 or pos.shape[1] != 3 or nrm.shape != pos.shape or ref.shape != (pos.shape[0],) \
            or ref.dtype != torch.bool or cam.numel() != 3 \
            or any(t.dtype != torch.float32 for t in (pos, nrm, cam)) \
            or any(t.device.type != "cpu" for t in (pos, nrm, ref, cam)):
        return None
    pos, nrm, ref, cam = pos.contiguous(), nrm.contiguous(), ref.contiguous(), cam.reshape(3).contiguous()
    N = int(pos.shape[0])
    idx = torch.empty(N, dtype=torch.int64)
    cn, cw = torch.empty(3, N, dtype=torch.float32), torch.empty(3, N, dtype=torch.float32)
    cnt = torch.zeros(1, dtype=torch.int64)
    lib.zh35o_front(N, pos.data_ptr(), nrm.data_ptr(), ref.data_ptr(), cam.data_ptr(), N, idx.data_ptr(),
                    cn.data_ptr(), cw.data_ptr(), cnt.data_ptr())
    Q = int(cnt[0])
    return idx[:Q], cn[:, :Q].contiguous(), cw[:, :Q].contiguous()


def plane_rows(g: Tensor, vz: Tensor, b0: int, b1: int, idx: Tensor, out: Tensor) -> bool:
    """Rows idx[b0:b1] of out (N, 3) float32 contiguous = (g @ vz[:, b0:b1]).T — g (3, n²), vz (n², Q) float32 of
    unit column stride, idx (Q,) int64 contiguous ids in [0, N) (the caller's: `front_regions`') — by one C loop
    (`zh43o_plane`: the products summed in order, float32; torch's product to float32 round-off, not its bits),
    True; False where it does not run (out untouched)."""
    lib = _front_lib() if terms_switched_on() else None
    if lib is None or g.dtype != torch.float32 or vz.dtype != torch.float32 or out.dtype != torch.float32 \
            or idx.dtype != torch.int64 or g.dim() != 2 or vz.dim() != 2 or g.shape[0] != 3 \
            or g.shape[1] != vz.shape[0] or not g.is_contiguous() or vz.stride(1) != 1 or not idx.is_contiguous() \
            or not out.is_contiguous() or out.dim() != 2 or out.shape[1] != 3 \
            or not 0 <= b0 <= b1 <= min(int(vz.shape[1]), int(idx.shape[0])) \
            or any(t.device.type != "cpu" for t in (g, vz, idx, out)):
        return False
    lib.zh43o_plane(int(g.shape[1]), g.data_ptr(), vz.data_ptr(), vz.stride(0), b0, b1, idx.data_ptr(), out.data_ptr())
    return True


def front_regions(pos: Tensor, nrm: Tensor, ref: Tensor, cam: Tensor, starts: list
                  ) -> tuple[Tensor, Tensor, Tensor, list, list] | None:
    """`front_columns` (the same idx, nTc, woTc bits: `zh43o_front`, the same loop, its columns written compact —
    no copies after the call) and, for the regions whose vertices are the ranges ``starts`` (nreg + 1 ascending
    ints: each region's first vertex, then the end), the list of nreg + 1 column bounds (each region's front
    columns [b[r], b[r + 1]): `torch.searchsorted`(idx, starts)) and per region whether its columns all hold
    one normal (`ZHShadow._front_planes`' test) — or None where it does not run (as `front_columns`, or
    ``starts`` not ascending). (zh43o: a P frame's ~0.1-0.2 ms of serial torch calls around the loop with the
    caches cold: the outputs' copies, the search, the planes' compare.)"""
    lib = _front_lib() if terms_switched_on() else None
    if lib is None or pos.dim() != 2 or pos.shape[1] != 3 or nrm.shape != pos.shape or ref.shape != (pos.shape[0],) \
            or ref.dtype != torch.bool or cam.numel() != 3 \
            or any(t.dtype != torch.float32 for t in (pos, nrm, cam)) \
            or any(t.device.type != "cpu" for t in (pos, nrm, ref, cam)) \
            or len(starts) < 2 or any(b < a for a, b in zip(starts[:-1], starts[1:])):
        return None
    # (each torch call ~10-30 µs with the caches cold: the inputs' copies only where not contiguous, the scalars
    # through `ctypes`, the outputs one strided view each)
    if not pos.is_contiguous():
        pos = pos.contiguous()
    if not nrm.is_contiguous():
        nrm = nrm.contiguous()
    if not ref.is_contiguous():
        ref = ref.contiguous()
    if cam.dim() != 1 or not cam.is_contiguous():
        cam = cam.reshape(3).contiguous()
    N, nreg = int(pos.shape[0]), len(starts) - 1
    ib = torch.empty(N + 3 + 3 * nreg, dtype=torch.int64)     # idx, then cnt (Q, bounds, flags), then starts
    fb = torch.empty(6 * N, dtype=torch.float32)              # nTc, then woTc
    ip = ib.data_ptr()
    tail = (ctypes.c_int64 * (3 + 3 * nreg)).from_address(ip + 8 * N)
    for i, b in enumerate(starts):   # (no torch call: `ctypes` writes of Python ints)
        tail[2 + 2 * nreg + i] = int(b)
    fp = fb.data_ptr()
    lib.zh43o_front(N, pos.data_ptr(), nrm.data_ptr(), ref.data_ptr(), cam.data_ptr(), nreg,
                    ip + 8 * (N + 2 + 2 * nreg), ip, fp, fp + 12 * N, ip + 8 * N)
    Q = int(tail[0])
    return (ib[:Q], fb.as_strided((3, Q), (Q, 1)), fb.as_strided((3, Q), (Q, 1), 3 * N), list(tail[1:2 + nreg]),
            [bool(x) for x in tail[2 + nreg:2 + 2 * nreg]])


# --- zh35o: the checked resolve with a face table (`ZHShadow._render_vertex`) --------------------------------
#
# `resolve`'s loop reads per hit sample its face's row of F and then three vertex rows (a chain of two
# dependent loads). As the per-vertex triple product's `tp_resolve` (tp34), every face's nine corner colours
# are gathered first into a face table T (M, 9) — T[9 f + 3 c + ch] = val[3 F[3 f + c] + ch], every corner's
# range checked there — so a sample reads one row of T. The same sums in the same order with the same
# float32 operations (no contraction): `resolve`'s bits (tested). Every face, not only the seen ones: a list
# of the seen faces is a pass over the G-buffer (2.4 MB on a bench frame) against one over F (0.64 MB).
# Bench creature, 1 thread, caches evicted before each call: 1.15-1.22 → 0.85-0.88 ms.
_TRESOLVE_SOURCE = r"""
#include <stdint.h>
/* faces [f0, f1): T[9 f + 3 c + ch] = val[3 F[3 f + c] + ch]; 1 at a corner out of [0, N) */
static int64_t table_range(const int64_t *F, const float *val, int64_t N, int64_t f0, int64_t f1, float *T) {
    for (int64_t f = f0; f < f1; ++f) {
        const int64_t j0 = F[3 * f], j1 = F[3 * f + 1], j2 = F[3 * f + 2];
        if (((uint64_t)j0 >= (uint64_t)N) | ((uint64_t)j1 >= (uint64_t)N) | ((uint64_t)j2 >= (uint64_t)N)) return 1;
        const float *x = val + 3 * j0, *y = val + 3 * j1, *z = val + 3 * j2;
        float *t = T + 9 * f;
        t[0] = x[0]; t[1] = x[1]; t[2] = x[2];
        t[3] = y[0]; t[4] = y[1]; t[5] = y[2];
        t[6] = z[0]; t[7] = z[1]; t[8] = z[2];
    }
    return 0;
}
static int64_t pix_range(const int64_t *face, const float *bu, const float *bv, const uint8_t *hit, int64_t M,
                         const float *T, int64_t S2, int64_t i0, int64_t i1, float *out) {
    const float inv = 1.0f / (float)S2;
    for (int64_t i = i0; i < i1; ++i) {
        float a0 = 0.0f, a1 = 0.0f, a2 = 0.0f;
        for (int64_t p = i * S2; p < (i + 1) * S2; ++p) {
            if (!hit[p]) continue;
            const int64_t f = face[p];
            if ((uint64_t)f >= (uint64_t)M) return 1;
            const float u = bu[p], v = bv[p], w = 1.0f - u - v;
            const float *x = T + 9 * f;
            a0 += (x[0] * w + x[3] * u) + x[6] * v;
            a1 += (x[1] * w + x[4] * u) + x[7] * v;
            a2 += (x[2] * w + x[5] * u) + x[8] * v;
        }
        out[3 * i] = a0 * inv;
        out[3 * i + 1] = a1 * inv;
        out[3 * i + 2] = a2 * inv;
    }
    return 0;
}
void zh35o_resolve(const int64_t *face, const float *bu, const float *bv, const uint8_t *hit, const int64_t *F,
                   int64_t M, const float *val, int64_t N, int64_t S2, int64_t n, int64_t nt, float *T, float *out,
                   int64_t *bad) {
    int64_t b = 0;
    if (nt <= 1) {
        b = table_range(F, val, N, 0, M, T);
        if (!b) b = pix_range(face, bu, bv, hit, M, T, S2, 0, n, out);
    } else {
        #pragma omp parallel num_threads(nt) reduction(|:b)
        {
            #pragma omp for schedule(static)
            for (int64_t t = 0; t < nt; ++t) b |= table_range(F, val, N, M * t / nt, M * (t + 1) / nt, T);
            #pragma omp for schedule(static)
            for (int64_t t = 0; t < nt; ++t) b |= pix_range(face, bu, bv, hit, M, T, S2, n * t / nt, n * (t + 1) / nt, out);
        }
    }
    bad[0] = b;
}
"""
_TRESOLVE_SIGNATURES = {"zh35o_resolve": [_P, _P, _P, _P, _P, _I, _P, _I, _I, _I, _I, _P, _P, _P]}


def _tresolve_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75);
    # no ISA flags and no multiply-adds fused: `resolve`'s build (the same sums' bits)
    return native.load("zh35o_resolve", _TRESOLVE_SOURCE, _TRESOLVE_SIGNATURES, extra_flags=("-fopenmp",))


def resolve_table(values: Tensor, F: Tensor, face: Tensor, bary: Tensor, hit: Tensor, height: int, width: int,
                  spp_side: int) -> Tensor | None:
    """`resolve` (the same arguments, the same bits, ValueError on a hit sample's face out of range and on a
    corner out of range — of any face: the table reads every face's) by the loop with a face table (above), or
    None where it does not run (as `resolve`)."""
    lib = _tresolve_lib() if terms_switched_on() else None
    S2 = spp_side * spp_side
    n = height * width
    args = None if lib is None else _resolve_inputs(values, F, face, bary, hit, n * S2)
    if args is None:
        return None
    values, bu, bv = args
    M = int(F.shape[0])
    T = torch.empty(M, 9, dtype=torch.float32)
    out = torch.empty(n, 3, dtype=torch.float32)
    bad = torch.zeros(1, dtype=torch.int64)
    nt = max(1, min(torch.get_num_threads(), n // MIN_RESOLVE_PIXELS_PER_THREAD))
    lib.zh35o_resolve(face.data_ptr(), bu.data_ptr(), bv.data_ptr(), hit.data_ptr(), F.data_ptr(), M,
                      values.data_ptr(), int(values.shape[0]), S2, n, nt, T.data_ptr(), out.data_ptr(), bad.data_ptr())
    if int(bad[0]):
        raise ValueError(f"G-buffer faces or corner rows out of range of {M} faces and "
                         f"{int(values.shape[0])} vertex rows (a G-buffer of another mesh?)")
    return out.view(height, width, 3)


def warm_pose_libraries() -> None:
    """Load (building once, `native.load`'s cache) the session-35 libraries a later P frame calls, from a frame
    that does not (the harness's untimed full-change frame 0): the first P frame then pays no dlopen — the
    front loop (`front_columns`) is called by no other frame kind, the pose pass (`pose_radiance`, `_view_lib`)
    and the referenced vertices (`referenced_mask`, `_kernel`) by no full-change frame."""
    if terms_switched_on():
        for get in (_pose_cols_lib, _skin_lib, _front_lib, _tresolve_lib, _view_lib, _pose_sh_lib, _vskin_lib,
                    _vresolve_lib):   # (+ session 38's vector skinning and resolve)
            get()
    _kernel()
    if PARALLEL_REFERENCED:   # (zh43o's threaded referenced loop)
        _pref_lib()


# === zh35p ==================================================================================================
#
# A lighting-only frame's image in one parallel region (`ZHShadow._relight_planes`, `relight_pixels`). Session
# 34's L / E frame (paper setting, bench creature) ran `face_pixels` (the plane samples, over the pixels) and
# then `relight_add` (the object samples' cached transfer, per region entry) as two C calls, each its own
# OpenMP region, and `relight_add`'s Python (the pixels' range, the threads' cuts: ~10 small torch ops per
# entry). Here thread t of the team takes a range of pixels — their plane samples exactly as `zh_face_pixels`
# (the same function), then, entry by entry in order, the object samples whose pixel lies in the range (each
# entry's pixels ascending: its range by bisection), exactly as `zh_relight_add` shades and adds them (the
# same function) — so every pixel sees the same additions in the same order as the two passes: the same bits
# at any thread count. The ranges balance the two kinds of work (a pixel's plane samples weigh 1, an object
# sample `RELIGHT_OBJECT_WEIGHT`), as the object is not spread evenly over the image.
_RELIGHT_PIXELS_SOURCE = _FACE_PIXELS_SOURCE + _RELIGHT_SOURCE + r"""
#include <omp.h>

/* o[c] = Σ_j x[j] T[j, c] (j ascending, multiplies and adds apart) for c < 3: one row of v · T¹(n0) */
static inline void zh35p_row3(const float *x, int64_t n2, const float *T, float *o) {
    float s0 = x[0] * T[0], s1 = x[0] * T[1], s2 = x[0] * T[2];
    for (int64_t j = 1; j < n2; ++j) {
        s0 = s0 + x[j] * T[3 * j]; s1 = s1 + x[j] * T[3 * j + 1]; s2 = s2 + x[j] * T[3 * j + 2];
    }
    o[0] = s0; o[1] = s1; o[2] = s2;
}

/* out (N, 3) = v (N, n2) @ T (n2, 3) by rows (`zh35p_row3`), rows split over nt threads (each row one
   thread's: the same bits at any thread count) — `ZHShadow._plane_term`'s v · T¹(n0) */
void zh35p_plane_u(int64_t N, const float *v, int64_t n2, const float *T, float *out, int64_t nt) {
#pragma omp parallel for num_threads(nt) schedule(static) if(nt > 1)
    for (int64_t i = 0; i < N; ++i) zh35p_row3(v + i * n2, n2, T, out + 3 * i);
}

/* the first index i of a (n,) ascending with a[i] >= x (n if none) */
static int64_t zh35p_lower(const int64_t *a, int64_t n, int64_t x) {
    int64_t lo = 0, hi = n;
    while (lo < hi) {
        const int64_t mid = lo + (hi - lo) / 2;
        if (a[mid] < x) lo = mid + 1; else hi = mid;
    }
    return lo;
}

/* the work of the pixels [0, p): p + w · (the entries' samples whose pixel is below p) */
static double zh35p_work(int64_t p, int64_t E, const int64_t *Qs, const int64_t *const *pixs, double w) {
    double c = (double)p;
    for (int64_t e = 0; e < E; ++e) c += w * (double)zh35p_lower(pixs[e], Qs[e], p);
    return c;
}

/* out (n, 3) = zh_face_pixels(face, bary, uf, clamp, inv), then for e = 0 … E − 1: zh_relight_add(td[e], ts[e]
   (NULL: none), ld[e], ls[e], pix[e], clamp, inv) into it — each pixel's work one thread's. td[e], ts[e] (n2,
   Qs[e]) row-major, ld[e], ls[e] (n2, 3), pix[e] (Qs[e],) ascending in [0, n) (checked: else bad[0] = −1 and
   nothing written). With v (N, nv2) given, uf (F, 12) is written first (in the same region, before a barrier):
   corner i = 3 f + k of plane face f gets uf[f, 4 k + c] = (Σ_j v[corners[i], j] T[j, c], j ascending) ·
   kd[creg[i], c] and uf[f, 4 k + 3] = 0 — the plane term kd ⊙ v · T¹(n0) at the corners (`ZHShadow._plane_term`'s
   product, float32 round-off against its GEMM). bad[0]: plane faces ≥ F, corners or regions out of range and
   object pixels out of range (their work skipped). */
void zh35p_relight_pixels(int64_t n, int64_t S2, const int32_t *face, const float *bary, int64_t bs0, int64_t bs1,
                          float *uf, int64_t F, int64_t clamp, float inv, float *out, int64_t E,
                          const int64_t *Qs, int64_t n2, const int64_t *tds, const int64_t *tss, const int64_t *lds,
                          const int64_t *lss, const int64_t *pixp, double w, const float *v, int64_t N, int64_t nv2,
                          const int64_t *corners, const int64_t *creg, const float *T, const float *kd, int64_t R,
                          int64_t nt, int64_t *bad) {
    const int64_t *const *pixs = (const int64_t *const *)pixp;
    for (int64_t e = 0; e < E; ++e) {   /* each entry's pixels ascending and inside the image */
        const int64_t *pix = pixs[e];
        for (int64_t q = 0; q < Qs[e]; ++q)
            if ((uint64_t)pix[q] >= (uint64_t)n || (q && pix[q] < pix[q - 1])) { bad[0] = -1; return; }
    }
    int64_t nb = 0;
#pragma omp parallel num_threads(nt) reduction(+:nb) if(nt > 1)
    {
        if (v) {
#pragma omp for schedule(static)
            for (int64_t i = 0; i < 3 * F; ++i) {
                float *o = uf + 4 * i;
                const int64_t vi = corners[i], r = creg[i];
                if ((uint64_t)vi >= (uint64_t)N || (uint64_t)r >= (uint64_t)R) {
                    ++nb;
                    o[0] = o[1] = o[2] = o[3] = 0.f;
                    continue;
                }
                zh35p_row3(v + vi * nv2, nv2, T, o);
                o[0] = o[0] * kd[3 * r]; o[1] = o[1] * kd[3 * r + 1]; o[2] = o[2] * kd[3 * r + 2]; o[3] = 0.f;
            }   /* (the barrier: every thread reads any face's row) */
        }
        const int64_t T = omp_get_num_threads(), t = omp_get_thread_num();
        /* this thread's pixels [p0, p1): the work's t / T and (t + 1) / T points (bisection; the same cuts
           in every thread) */
        int64_t cut[2];
        const double total = zh35p_work(n, E, Qs, pixs, w);
        for (int k = 0; k < 2; ++k) {
            const int64_t tk = t + k;
            if (tk == 0) { cut[k] = 0; continue; }
            if (tk == T) { cut[k] = n; continue; }
            const double goal = total * (double)tk / (double)T;
            int64_t lo = 0, hi = n;
            while (lo < hi) {
                const int64_t mid = lo + (hi - lo) / 2;
                if (zh35p_work(mid, E, Qs, pixs, w) < goal) lo = mid + 1; else hi = mid;
            }
            cut[k] = lo;
        }
        const int64_t p0 = cut[0], p1 = cut[1];
        for (int64_t p = p0; p < p1; ++p)   /* as zh_face_pixels */
            face_pixel(face, bary, bs0, bs1, uf, F, clamp, inv, out, S2, p, &nb);
        for (int64_t e = 0; e < E; ++e) {     /* as zh_relight_add, entry by entry */
            const int64_t *pix = pixs[e];
            const int64_t a = zh35p_lower(pix, Qs[e], p0), b = zh35p_lower(pix, Qs[e], p1);
            nb += relight_range(a, b, Qs[e], n2, (const float *)tds[e], (const float *)tss[e], (const float *)lds[e],
                                (const float *)lss[e], pix, clamp, inv, out, n);
        }
    }
    bad[0] = nb;
}
"""
_RELIGHT_PIXELS_SIGNATURES = {"zh35p_relight_pixels": [_I, _I, _P, _P, _I, _I, _P, _I, _I, ctypes.c_float, _P, _I, _P,
                                                       _I, _P, _P, _P, _P, _P, ctypes.c_double, _P, _I, _I, _P, _P,
                                                       _P, _P, _I, _I, _P],
                              "zh35p_plane_u": [_I, _P, _I, _P, _P, _I]}
MIN_ROWS_PER_PLANE_U_THREAD = 4096   # rows below which one thread makes `plane_u`'s product
RELIGHT_OBJECT_WEIGHT = 2.0   # an object sample's work in pixels' plane passes (`relight_pixels`' thread ranges)


def _relight_pixels_lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75)
    return load("zh35p_relight_pixels", _RELIGHT_PIXELS_SOURCE, _RELIGHT_PIXELS_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", *native.isa_flags()))


def relight_pixels(face: Tensor, bary: Tensor, uf: Tensor | None, clamp: bool, entries: list, inv: float,
                   planes: tuple | None = None) -> Tensor | None:
    """`face_pixels(face, bary, uf, clamp)` then, for each entry (td, ts, ld, ls, pix) in order, `relight_add(img,
    td, ts, ld, ls, pix, clamp, inv)` — the same bits — in one C pass (`zh35p_relight_pixels`: one OpenMP
    region), or None where it does not run (no compiler, ``PRTBENCH_ZH_NATIVE=0``, other dtypes / layouts, a
    plane face outside uf's rows, an entry's pixels not ascending inside the image): the caller then runs the
    two passes. face (n, S²) int32 (−1: no plane sample), bary (2, n, S²) with strides (bs0, S² bs1, bs1), uf
    (F_p, 9); td, ts (n², Q) (ts None: no specular term), ld, ls (n², 3) float32 contiguous, pix (Q,) int64.

    ``uf`` None: made in the same pass from ``planes`` = (v (N, n²), corners (3 F_p,) int64, creg (3 F_p,) int64
    their regions, T (n², 3), kd (R, 3)) as uf[f, 3 k + c] = (v[corners[3 f + k]] · T[:, c]) kd[creg[3 f + k], c]
    (`ZHShadow._relight_planes`' ``(v[corners] @ T¹(n0)) ⊙ kd``: float32 round-off against its GEMM) — then
    `relight_pixels_run`(`relight_pixels_setup`(...), ...) (zh40l: the same call)."""
    if uf is None:
        st = relight_pixels_setup(face, bary, clamp, entries, inv, planes)
        return None if st is None else relight_pixels_run(st, [e[2] for e in entries], [e[3] for e in entries],
                                                          planes[3])
    lib = _relight_pixels_lib() if terms_switched_on() else None
    if (lib is None or face.dtype != torch.int32 or face.dim() != 2 or bary.dtype != torch.float32
            or any(t.device.type != "cpu" for t in (face, bary))):
        return None
    if uf.dtype != torch.float32 or uf.dim() != 2 or uf.shape[1] != 9 or uf.shape[0] == 0 or uf.device.type != "cpu":
        return None
    Fp = int(uf.shape[0])
    u12 = torch.zeros(Fp, 3, 4, dtype=torch.float32)   # (as `face_pixels`)
    u12[:, :, :3] = uf.view(-1, 3, 3)
    pl = (0, 0, 0, 0, 0, 0, 0, 0)
    st = _relight_pixels_entries(lib, face, bary, clamp, entries, inv, u12, Fp, pl, None)
    return None if st is None else relight_pixels_run(st, [e[2] for e in entries], [e[3] for e in entries], None)


def relight_pixels_setup(face: Tensor, bary: Tensor, clamp: bool, entries: list, inv: float, planes: tuple | None,
                         blocked: bool = False) -> tuple | None:
    """The checks and arguments of `relight_pixels` with ``uf`` None but the lighting's (each entry's ld, ls and
    the planes' T: their shapes checked here, their values read by `relight_pixels_run`), or None where it does
    not run. zh40l: kept by `ZHShadow._relight_planes` for the next lighting-only frames of its transfer cache
    (`ZHShadow._steady_planes`), which only bring a new lighting. ``blocked``: the entries read from blocked
    copies made here (`blocked_transfer`, ``zh40l_relight_pixels``: the same bits) where that library runs and
    ``BLOCKED_RELIGHT`` is on."""
    lib = _relight_pixels_lib() if terms_switched_on() else None
    if (lib is None or face.dtype != torch.int32 or face.dim() != 2 or bary.dtype != torch.float32
            or any(t.device.type != "cpu" for t in (face, bary))):
        return None
    if planes is None:
        return None
    v, corners, creg, T, kd = planes
    n2v = int(v.shape[1]) if v.dim() == 2 else -1
    if (v.dim() != 2 or any(t.dtype != torch.float32 or t.device.type != "cpu" or not t.is_contiguous()
                            for t in (v, T, kd))
            or any(t.dtype != torch.int64 or t.device.type != "cpu" or not t.is_contiguous() or t.dim() != 1
                   for t in (corners, creg))
            or corners.shape[0] == 0 or corners.shape[0] % 3 or creg.shape != corners.shape
            or T.shape != (n2v, 3) or kd.dim() != 2 or kd.shape[1] != 3):
        return None
    Fp = int(corners.shape[0]) // 3
    u12 = torch.empty(Fp, 3, 4, dtype=torch.float32)   # (every value written by the pass: scratch)
    pl = [v.data_ptr(), int(v.shape[0]), n2v, corners.data_ptr(), creg.data_ptr(), 0, kd.data_ptr(),
          int(kd.shape[0])]
    st = _relight_pixels_entries(lib, face, bary, clamp, entries, inv, u12, Fp, pl, (v, corners, creg, kd, n2v))
    blib = _blk_relight_lib() if st is not None and blocked and BLOCKED_RELIGHT else None
    if blib is None:
        return st
    ptrs, xbs = st[10], []
    for e, (td, ts, _, _, _) in enumerate(entries):
        xbs.append(blocked_transfer(td, ts))
        ptrs[0][e] = xbs[-1].data_ptr()
        ptrs[1][e] = 0 if ts is None else 1
    fn = blib.zh40l_relight_pixels
    olib = _once_relight_lib() if PIXELS_CHECKED_ONCE else None
    if olib is not None and all(_pixels_ascending_inside(pix, int(face.shape[0])) for _, _, _, _, pix in entries):
        fn = olib.zh41l_relight_pixels   # (zh41l: the kept pixels checked here, once)
    return (fn, *st[1:-1], (*st[-1], xbs))


def _relight_pixels_entries(lib, face, bary, clamp, entries, inv, u12, Fp, pl, keep) -> tuple | None:
    n, S2 = int(face.shape[0]), int(face.shape[1])
    if bary.shape != (2, n, S2) or bary.stride(1) != S2 * bary.stride(2) or not face.is_contiguous():
        return None
    n2 = None
    E = len(entries)
    ptrs = [(ctypes.c_int64 * max(E, 1))() for _ in range(6)]   # td, ts, ld, ls, pix pointers; Q
    for e, (td, ts, ld, ls, pix) in enumerate(entries):
        if n2 is None:
            n2 = int(td.shape[0]) if td.dim() == 2 else -1
        arrs = (td, ld) + ((ts, ls) if ts is not None else ())
        if (td.dim() != 2 or td.shape[0] != n2 or any(t.dtype != torch.float32 or t.device.type != "cpu"
                                                      or not t.is_contiguous() for t in arrs)
                or pix.dtype != torch.int64 or pix.shape != (td.shape[1],) or not pix.is_contiguous()
                or pix.device.type != "cpu" or ld.shape != (n2, 3)
                or (ts is not None and (ts.shape != td.shape or ls is None or ls.shape != (n2, 3)))):
            return None
        for lst, t in zip(ptrs, (td, ts, None, None, pix)):
            lst[e] = 0 if t is None else t.data_ptr()
        ptrs[5][e] = int(td.shape[1])
    spec = [ts is not None for _, ts, _, _, _ in entries]
    kept = (face, bary, [(td, ts, pix) for td, ts, _, _, pix in entries], keep)
    return (lib.zh35p_relight_pixels, n, S2, face, bary, u12, Fp, bool(clamp), float(inv), E, ptrs,
            0 if n2 is None else n2, pl, spec, kept)


def relight_pixels_run(setup: tuple, lds: list, lss: list, T: Tensor | None) -> Tensor | None:
    """`relight_pixels` of a `relight_pixels_setup` with the entries' ld, ls (n², 3) and the planes' T (n², 3) of
    this frame (float32 CPU contiguous, the setup's shapes; else None): the same C call, the same bits."""
    fn, n, S2, face, bary, u12, Fp, clamp, inv, E, ptrs, n2, pl, spec, kept = setup
    if len(lds) != E or len(lss) != E:
        return None
    for e in range(E):
        ld, ls = lds[e], lss[e]
        for t in (ld, ls) if spec[e] else (ld,):
            if t is None or t.dtype != torch.float32 or t.device.type != "cpu" or not t.is_contiguous() \
                    or t.shape != (n2, 3):
                return None
        ptrs[2][e] = ld.data_ptr()
        ptrs[3][e] = ls.data_ptr() if spec[e] else 0
    if kept[3] is not None:
        n2v = kept[3][4]
        if T is None or T.dtype != torch.float32 or T.device.type != "cpu" or not T.is_contiguous() \
                or T.shape != (n2v, 3):
            return None
        pl = list(pl)
        pl[5] = T.data_ptr()
    out = torch.empty(n, 3, dtype=torch.float32)
    bad = ctypes.c_int64(0)
    nt = max(1, min(torch.get_num_threads(), n // MIN_PIXELS_PER_THREAD))
    fn(n, S2, face.data_ptr(), bary.data_ptr(), bary.stride(0), bary.stride(2), u12.data_ptr(),
       Fp, int(clamp), inv, out.data_ptr(), E, ctypes.addressof(ptrs[5]),
       n2, *(ctypes.addressof(p) for p in ptrs[:5]),
       RELIGHT_OBJECT_WEIGHT, *pl, nt, ctypes.byref(bad))
    return None if bad.value else out


# -- zh40l ------------------------------------------------------------------------------------------
# `zh35p_relight_pixels` with each object entry's transfer read from a blocked copy (``BLOCKED_RELIGHT``): the
# entry's td (and ts) (n², Q) row-major copied, once per kept setup (`relight_pixels_setup`: the first lighting-only
# frame of a transfer), into blocks of RB = 32 samples — block b its td rows then its ts rows, RB floats each, one
# contiguous run — whose 32 sums a table sit in registers (zh35p: CH = 512 samples a step, its 3 × 64 vector
# accumulators in memory, 2 n² rows Q floats apart). Per sample the same expressions in the same order (a sample
# of a partial block — a thread's cut, the last block — by `accumulate_one` at stride RB): the same bits. Bench
# creature L frame's call, 1 thread, after 0.2 s idle: 1.13 -> 0.94 ms.
_BLK_RELIGHT_C = r"""
/* zh40l: the object entries' sums from a blocked copy of their transfer — entry e's xb (nblk, k, n2, RB) float32,
   k = 1 (td) or 2 (td then ts), block b the samples [RB b, RB b + RB) (the last zero-padded): each block one
   contiguous run, its RB samples' sums in registers (RB = 8 KB lanes). Per sample the same expressions as
   `relight_range` (Σ_i l[i, c] x[i, q], i ascending, from 0; td's sum + ts's; the clamp; o += r · inv) in the
   same sample order: the same bits. */
enum { KB = 4, RB = 8 * KB };

static inline void blk_sums(v8 a[3][KB], const float *x, const float *l, int64_t n2) {
    for (int c = 0; c < 3; ++c)
        for (int k = 0; k < KB; ++k) a[c][k] = (v8){0};
    for (int64_t i = 0; i < n2; ++i) {
        const float l0 = l[3 * i], l1 = l[3 * i + 1], l2 = l[3 * i + 2];
        const float *xi = x + i * RB;
        for (int k = 0; k < KB; ++k) {
            const v8 xv = *(const v8 *)(xi + 8 * k);
            a[0][k] += l0 * xv; a[1][k] += l1 * xv; a[2][k] += l2 * xv;
        }
    }
}

static int64_t relight_range_blk(int64_t qa, int64_t qb, int64_t n2, const float *xb, int64_t spec,
                                 const float *ld, const float *ls, const int64_t *pix, int64_t clamp, float inv,
                                 float *img, int64_t npix) {
    int64_t nb = 0;
    const int64_t kk = spec ? 2 : 1, bstride = kk * n2 * RB;
    int64_t q = qa;
    while (q < qb) {
        const int64_t b = q / RB, off = q - b * RB;
        const float *x = xb + b * bstride;
        if (off == 0 && q + RB <= qb) {
            v8 d[3][KB];
            blk_sums(d, x, ld, n2);
            if (spec) {
                v8 s[3][KB];
                blk_sums(s, x + n2 * RB, ls, n2);
                for (int c = 0; c < 3; ++c)
                    for (int k = 0; k < KB; ++k) d[c][k] += s[c][k];
            }
            for (int k = 0; k < KB; ++k)
                for (int l = 0; l < 8; ++l) {
                    const int64_t p = pix[q + 8 * k + l];
                    if ((uint64_t)p >= (uint64_t)npix) { ++nb; continue; }
                    float r0 = d[0][k][l], r1 = d[1][k][l], r2 = d[2][k][l];
                    if (clamp) { r0 = r0 < 0.f ? 0.f : r0; r1 = r1 < 0.f ? 0.f : r1; r2 = r2 < 0.f ? 0.f : r2; }
                    float *o = img + 3 * p;
                    o[0] += r0 * inv; o[1] += r1 * inv; o[2] += r2 * inv;
                }
            q += RB;
            continue;
        }
        float r[3], s[3];
        accumulate_one(r, x + off, ld, n2, RB);
        if (spec) {
            accumulate_one(s, x + n2 * RB + off, ls, n2, RB);
            r[0] += s[0]; r[1] += s[1]; r[2] += s[2];
        }
        float r0 = r[0], r1 = r[1], r2 = r[2];
        const int64_t p = pix[q];
        ++q;
        if ((uint64_t)p >= (uint64_t)npix) { ++nb; continue; }
        if (clamp) { r0 = r0 < 0.f ? 0.f : r0; r1 = r1 < 0.f ? 0.f : r1; r2 = r2 < 0.f ? 0.f : r2; }
        float *o = img + 3 * p;
        o[0] += r0 * inv; o[1] += r1 * inv; o[2] += r2 * inv;
    }
    return nb;
}
"""



def _blocked_source(base: str) -> str:
    """``base`` (`_RELIGHT_PIXELS_SOURCE`) with the entries read by `relight_range_blk` (tds[e]: the entry's blocked
    copy, tss[e]: 1 with a ts part, else 0), as ``zh40l_relight_pixels``."""
    s = base.replace("void zh35p_plane_u(", "static void unused_zh35p_plane_u(")
    s = s.replace("#include <omp.h>\n", "#include <omp.h>\n" + _BLK_RELIGHT_C, 1)
    old = ("nb += relight_range(a, b, Qs[e], n2, (const float *)tds[e], (const float *)tss[e], "
           "(const float *)lds[e],\n                                (const float *)lss[e], pix, clamp, inv, out, n);")
    assert s.count(old) == 1
    s = s.replace(old, "nb += relight_range_blk(a, b, n2, (const float *)tds[e], tss[e] != 0, (const float *)lds[e],\n"
                       "                                    (const float *)lss[e], pix, clamp, inv, out, n);")
    return s.replace("void zh35p_relight_pixels(", "void zh40l_relight_pixels(")


_BLK_RELIGHT_SOURCE = _blocked_source(_RELIGHT_PIXELS_SOURCE)
_BLK_RELIGHT_SIGNATURES = {"zh40l_relight_pixels": _RELIGHT_PIXELS_SIGNATURES["zh35p_relight_pixels"]}
BLOCKED_RELIGHT = True   # `relight_pixels_setup(..., blocked=True)` by the blocked copies (off: zh35p's pass)
RELIGHT_BLOCK = 32       # RB of `_BLK_RELIGHT_C`


# zh41l: `zh40l_relight_pixels` without its per-call check of the entries' pixel indices (ascending, inside the
# image): a serial loop over every object sample (35.7 K on the bench creature, 286 KB read cold) before the
# parallel region, every frame, of arrays the kept setup never changes. `relight_pixels_setup` checks them once
# (the same conditions, `_pixels_ascending_inside`) and takes this pass only when they hold (else zh40l's, which
# refuses them). ``PIXELS_CHECKED_ONCE`` False: zh40l's pass (the tests' oracle; the same bits either way).
_CHK = """    for (int64_t e = 0; e < E; ++e) {   /* each entry's pixels ascending and inside the image */
        const int64_t *pix = pixs[e];
        for (int64_t q = 0; q < Qs[e]; ++q)
            if ((uint64_t)pix[q] >= (uint64_t)n || (q && pix[q] < pix[q - 1])) { bad[0] = -1; return; }
    }
"""
assert _BLK_RELIGHT_SOURCE.count(_CHK) == 1
_ONCE_RELIGHT_SOURCE = _BLK_RELIGHT_SOURCE.replace(_CHK, "    /* (the entries' pixels checked by the setup) */\n").replace(
    "void zh40l_relight_pixels(", "void zh41l_relight_pixels(")
_ONCE_RELIGHT_SIGNATURES = {"zh41l_relight_pixels": _RELIGHT_PIXELS_SIGNATURES["zh35p_relight_pixels"]}
PIXELS_CHECKED_ONCE = True


def _once_relight_lib():
    return native.load("zh41l_relight_pixels", _ONCE_RELIGHT_SOURCE, _ONCE_RELIGHT_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", *native.isa_flags()))


def _pixels_ascending_inside(pix: Tensor, n: int) -> bool:
    """zh40l's check of one entry's pixel indices (int64 (Q,)): every one in [0, n), ascending."""
    if pix.numel() == 0:
        return True
    return int(pix.min()) >= 0 and int(pix.max()) < n and not bool((pix[1:] < pix[:-1]).any())


def _blk_relight_lib():
    return native.load("zh40l_relight_pixels", _BLK_RELIGHT_SOURCE, _BLK_RELIGHT_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", *native.isa_flags()))


def blocked_transfer(td: Tensor, ts: Tensor | None) -> Tensor:
    """(nblk, k, n², RB) float32: td (and ts; k = 2) (n², Q) in blocks of RB samples, the last zero-padded."""
    n2, Q = int(td.shape[0]), int(td.shape[1])
    RB = RELIGHT_BLOCK
    nb = (Q + RB - 1) // RB
    out = torch.empty(nb, 1 if ts is None else 2, n2, RB, dtype=torch.float32)
    full = Q // RB
    if Q > full * RB:
        out[full].zero_()   # (the last block's padding)
    for j, t in enumerate((td,) if ts is None else (td, ts)):
        if full:
            out[:full, j].copy_(t[:, :full * RB].reshape(n2, full, RB).permute(1, 0, 2))
        if Q > full * RB:
            out[full, j, :, :Q - full * RB].copy_(t[:, full * RB:])
    return out


def plane_u(v: Tensor, T: Tensor, out: Tensor | None = None) -> Tensor | None:
    """(N, 3) v (N, n²) @ T (n², 3) float32 by one C pass over the rows (`zh35p_plane_u`: each row's n² products
    summed in order; float32 round-off against the GEMM, whose 3-column product runs at a fraction of its
    peak: ~0.36 ms for the bench creature's 13.4 K rows at 1 thread), or None where it does not run (no
    compiler, ``PRTBENCH_ZH_NATIVE=0``, not CPU float32 contiguous arrays of these shapes). ``out`` (N, 3) float32
    contiguous: written there (zh38v: a row range of a caller's array)."""
    lib = _relight_pixels_lib() if terms_switched_on() else None
    if (lib is None or v.dim() != 2 or T.shape != (v.shape[1], 3) or v.shape[1] == 0
            or any(t.dtype != torch.float32 or t.device.type != "cpu" or not t.is_contiguous() for t in (v, T))):
        return None
    N = int(v.shape[0])
    if out is None:
        out = torch.empty(N, 3, dtype=torch.float32)
    elif out.shape != (N, 3) or out.dtype != torch.float32 or out.device.type != "cpu" or not out.is_contiguous():
        return None
    nt = max(1, min(torch.get_num_threads(), N // MIN_ROWS_PER_PLANE_U_THREAD))
    lib.zh35p_plane_u(N, v.data_ptr(), int(v.shape[1]), T.data_ptr(), out.data_ptr(), nt)
    return out


# === zh36o ==================================================================================================
#
# A P frame's visibility of the vertices it needs (`ZHShadow._pose_visibility`, order-8 vertex shading with the
# cosine) in one C call: per vertex the pose product [pose, 1] · X (`zh35o_pose_cols`' operations, the same
# bits) and then eq. 1 in the ZYZ frame of its normal — the chart → local axis (`precompute.chart_to_axis`),
# local → world through (s, t, n) (`frames._coordinate_components`), world → (e1, e2, n) (`runtime.zyz_axes`),
# the SH basis by `sh._terms_recurrence`'s recurrence and float32 constants, scaled by Λ_l k_l and summed over
# the lobes — `runtime._vertex_sh`'s operations in its order, in float32 without contraction (equal to the
# compiled pass to float32 round-off, tested), 16 vertices a block as vector lanes. Session 35: the product
# 0.45 ms and the compiled eq. 1 ~0.8 ms (its Dynamo guards, the (d, Q) and (n², Q) passes) per bench P frame.
_POSE_SH_SOURCE = r"""
#include <math.h>
#include <stdint.h>
#include <string.h>
#define DMAX 256
#define NMAX 8
#define L 16
typedef float v16 __attribute__((vector_size(64)));
typedef float v4 __attribute__((vector_size(16)));
#define LANES for (int k = 0; k < L; ++k)
@FAST_TERMS@

/* p[k] = sum_i a[i] x[i * d + k], i ascending (as zh35o_pose_cols) */
static void pose_row(int64_t J1, int64_t d, const float *a, const float *x, float *p) {
#ifndef ZH42P_NO_ROW12
    if (d == 12) {   /* order 4, two lobes (zh42p): the 12 sums as an 8- and a 4-lane vector (the same operations) */
        typedef float v8p __attribute__((vector_size(32)));
        v8p s, xv;
        v4 s4, x4;
        memcpy(&xv, x, 32); memcpy(&x4, x + 8, 16);
        s = 0.0f + a[0] * xv; s4 = 0.0f + a[0] * x4;
        for (int64_t i = 1; i < J1; ++i) {
            memcpy(&xv, x + i * 12, 32); memcpy(&x4, x + i * 12 + 8, 16);
            s = s + a[i] * xv; s4 = s4 + a[i] * x4;
        }
        memcpy(p, &s, 32); memcpy(p + 8, &s4, 16);
        return;
    }
#endif
    if (d == 20) {
        v16 s, xv;
        v4 s4, x4;
        memcpy(&xv, x, 64); memcpy(&x4, x + 16, 16);
        s = 0.0f + a[0] * xv; s4 = 0.0f + a[0] * x4;
        for (int64_t i = 1; i < J1; ++i) {
            memcpy(&xv, x + i * 20, 64); memcpy(&x4, x + i * 20 + 16, 16);
            s = s + a[i] * xv; s4 = s4 + a[i] * x4;
        }
        memcpy(p, &s, 64); memcpy(p + 16, &s4, 16);
        return;
    }
    for (int64_t k = 0; k < d; ++k) p[k] = 0.0f + a[0] * x[k];
    for (int64_t i = 1; i < J1; ++i) {
        const float ai = a[i];
        const float *xi = x + i * d;
        for (int64_t k = 0; k < d; ++k) p[k] = p[k] + ai * xi[k];
    }
}

/* columns [q0, q1): out[r * ldo + q] (vmaj: out[q * n2 + r]) = sum over lobes of Y_perm[r](axis) (k_l Λ_l), the
   axis in the ZYZ frame of the normal (zyz) or in world space; 1 at an id out of [0, N) */
static int64_t sh_range(int64_t J1, int64_t d, int64_t lobes, int64_t n, const float *a, const float *X,
                        const int64_t *idx, int64_t N, const float *nT, int64_t ldn, int64_t ldq, const float *lam,
                        const int64_t *perm, const float *cq, float rmax, int64_t q0, int64_t q1, float *out,
                        int64_t ldo, int64_t zyz, int64_t vmaj, int64_t scatter) {
    float P[DMAX][L] __attribute__((aligned(64)));
    float acc[NMAX * NMAX][L] __attribute__((aligned(64)));
    float Y[NMAX * NMAX][L] __attribute__((aligned(64)));
    float p[DMAX];
    const int64_t per = 2 + n, n2 = n * n;
    const float sqrt2 = cq[0];
    for (int64_t b0 = q0; b0 < q1; b0 += L) {
        const int64_t cnt = q1 - b0 < L ? q1 - b0 : L;
        float nx[L], ny[L], nz[L];
        for (int k = 0; k < L; ++k) {
            const int64_t q = b0 + (k < cnt ? k : 0);
            const int64_t j = idx ? idx[q] : q;
            if ((uint64_t)j >= (uint64_t)N) return 1;
            if (k < cnt && idx && q + L < q1) {
                const int64_t jn = idx[q + L];
                if ((uint64_t)jn < (uint64_t)N) {
                    const char *pp = (const char *)(X + jn * J1 * d);
                    for (int64_t bb = 0; bb < J1 * d * 4; bb += 64) __builtin_prefetch(pp + bb, 0, 3);
                }
            }
            pose_row(J1, d, a, X + j * J1 * d, p);
            for (int64_t c = 0; c < d; ++c) P[c][k] = p[c];
            const int64_t qn = scatter ? j : q;   /* (scatter: the normal and the output row of vertex j) */
            nx[k] = nT[qn * ldq]; ny[k] = nT[ldn + qn * ldq]; nz[k] = nT[2 * ldn + qn * ldq];
        }
        /* (s, t) of the normal (frames._coordinate_components) and the ZYZ axes e1, e2 (runtime.zyz_axes) */
        float s0[L], s1[L], s2[L], t0[L], t1[L], t2[L], e10[L], e11[L], e12[L], e20[L], e21[L];
        LANES {
            const float x = nx[k], y = ny[k], z = nz[k];
            const float sg = z >= 0.0f ? 1.0f : -1.0f;
            const float aa = -1.0f / (sg + z);
            const float bb = (x * y) * aa;
            s0[k] = 1.0f + ((sg * x) * x) * aa; s1[k] = sg * bb; s2[k] = (-sg) * x;
            t0[k] = bb; t1[k] = sg + (y * y) * aa; t2[k] = -y;
            const float zc = z < -1.0f ? -1.0f : (z > 1.0f ? 1.0f : z);
            const float rho = sqrtf(x * x + y * y);
            const int ok = rho > 1e-20f;
            const float safe = ok ? rho : 1.0f;
            const float cp = ok ? x / safe : 1.0f, sp = ok ? y / safe : 0.0f;
            e10[k] = zc * cp; e11[k] = zc * sp; e12[k] = -rho;
            e20[k] = -sp; e21[k] = cp;
        }
        v16 vx, vy, vz, vs0, vs1, vs2, vt0, vt1, vt2, ve10, ve11, ve12, ve20, ve21;
        memcpy(&vx, nx, 64); memcpy(&vy, ny, 64); memcpy(&vz, nz, 64);
        memcpy(&vs0, s0, 64); memcpy(&vs1, s1, 64); memcpy(&vs2, s2, 64);
        memcpy(&vt0, t0, 64); memcpy(&vt1, t1, 64); memcpy(&vt2, t2, 64);
        memcpy(&ve10, e10, 64); memcpy(&ve11, e11, 64); memcpy(&ve12, e12, 64);
        memcpy(&ve20, e20, 64); memcpy(&ve21, e21, 64);
        for (int64_t c = 0; c < lobes; ++c) {
            const float *Xc = P[c * per], *Yc = P[c * per + 1];
            float l0a[L], l1a[L], zza[L];
            LANES {
                float X0 = Xc[k], Y0 = Yc[k];
                float r2 = X0 * X0 + Y0 * Y0;
                const float sc = r2 > rmax * rmax ? rmax / sqrtf(r2 < 1e-30f ? 1e-30f : r2) : 1.0f;
                X0 = X0 * sc; Y0 = Y0 * sc;
                r2 = X0 * X0 + Y0 * Y0;
                zza[k] = 1.0f - 0.5f * r2;
                float ff = 1.0f - 0.25f * r2;
                ff = sqrtf(ff < 0.0f ? 0.0f : ff);
                l0a[k] = ff * X0; l1a[k] = ff * Y0;
            }
            v16 l0, l1, zz;
            memcpy(&l0, l0a, 64); memcpy(&l1, l1a, 64); memcpy(&zz, zza, 64);
            const v16 w0 = (vs0 * l0 + vt0 * l1) + vx * zz;
            const v16 w1 = (vs1 * l0 + vt1 * l1) + vy * zz;
            const v16 w2 = (vs2 * l0 + vt2 * l1) + vz * zz;
            const v16 ax = zyz ? (ve10 * w0 + ve11 * w1) + ve12 * w2 : w0;
            const v16 ay = zyz ? (ve20 * w0 + ve21 * w1) + 0.0f * w2 : w1;
            const v16 az = zyz ? (vx * w0 + vy * w1) + vz * w2 : w2;
            v16 Y[NMAX * NMAX];
            /* sh._terms_fast's polynomials up to its FAST_MAX_ORDER (generated from it, `_fast_terms_code`) */
            if (terms_fast(n, ax, ay, az, Y)) goto scaled;
            /* sh._terms_recurrence (cq: sqrt2, then per m: qmm, then per l > m: A, B or the l = m + 1 factor) */
            v16 cc = (v16){} + 1.0f, ss = (v16){};
            const float *cm = cq + 1;
            for (int64_t m = 0; m < n; ++m) {
                if (m > 0) {
                    const v16 c2 = ax * cc - ay * ss, s2_ = ax * ss + ay * cc;
                    cc = c2; ss = s2_;
                }
                v16 qp = (v16){} + *cm++, qp2 = (v16){}, qq;
                for (int64_t l = m; l < n; ++l) {
                    if (l == m + 1) {
                        const float f1 = *cm++;
                        qq = (f1 * az) * qp;
                    } else if (l > m + 1) {
                        const float A = cm[0], B = cm[1];
                        cm += 2;
                        qq = A * (az * qp - B * qp2);
                    } else {
                        qq = qp;
                    }
                    if (m == 0) {
                        Y[l * (l + 1)] = qq;
                    } else {
                        const v16 h = sqrt2 * qq;
                        Y[l * (l + 1) + m] = h * cc; Y[l * (l + 1) - m] = h * ss;
                    }
                    if (l > m) { qp2 = qp; qp = qq; }
                }
            }
          scaled:
            for (int64_t l = 0; l < n; ++l) {
                v16 kl;
                memcpy(&kl, P[c * per + 2 + l], 64);
                const v16 g = kl * lam[l];
                for (int64_t i = l * l; i < (l + 1) * (l + 1); ++i) {
                    v16 o;
                    if (c == 0) o = Y[i] * g;
                    else { memcpy(&o, acc[i], 64); o = o + Y[i] * g; }
                    memcpy(acc[i], &o, 64);
                }
            }
        }
        if (vmaj) {
            for (int64_t k = 0; k < cnt; ++k) {
                const int64_t row = scatter ? idx[b0 + k] : b0 + k;
                for (int64_t r = 0; r < n2; ++r) out[row * n2 + r] = acc[perm[r]][k];
            }
        } else if (cnt == L) {
            for (int64_t r = 0; r < n2; ++r) memcpy(out + r * ldo + b0, acc[perm[r]], 64);
        } else {
            for (int64_t r = 0; r < n2; ++r) {
                const float *o = acc[perm[r]];
                float *dst = out + r * ldo + b0;
                for (int64_t k = 0; k < cnt; ++k) dst[k] = o[k];
            }
        }
    }
    return 0;
}

/* zh41p: the normal of column q read at nT[r * ldn + q * ldq] (ldq 3, ldn 1: the (N, 3) rows as they are);
   scatter (with idx and vmaj): vertex idx[q]'s normal read at nT[r * ldn + idx[q] * ldq] and its row written
   to out[idx[q] * n2 ...] (an (N, n2) array: the rows of the vertices asked for, each the same bits as there) */
void zh41p_pose_sh(int64_t J1, int64_t d, int64_t lobes, int64_t n, const float *a, const float *X,
                   const int64_t *idx, int64_t N, int64_t Q, const float *nT, int64_t ldn, int64_t ldq,
                   const float *lam, const int64_t *perm, const float *cq, float rmax, int64_t zyz, int64_t vmaj,
                   int64_t scatter, int64_t nt, float *out, int64_t *bad) {
    int64_t b = 0;
    if (!idx || !vmaj) scatter = 0;
    if (nt <= 1) {
        b = sh_range(J1, d, lobes, n, a, X, idx, N, nT, ldn, ldq, lam, perm, cq, rmax, 0, Q, out, Q, zyz, vmaj,
                     scatter);
    } else {
        const int64_t nb = (Q + L - 1) / L;
        #pragma omp parallel for num_threads(nt) schedule(static, 1) reduction(|:b)
        for (int64_t t = 0; t < nt; ++t) {
            int64_t a0 = nb * t / nt * L, a1 = nb * (t + 1) / nt * L;
            if (a1 > Q) a1 = Q;
            if (a0 < a1)
                b |= sh_range(J1, d, lobes, n, a, X, idx, N, nT, ldn, ldq, lam, perm, cq, rmax, a0, a1, out, Q, zyz,
                              vmaj, scatter);
        }
    }
    bad[0] = b;
}

void zh36o_pose_sh(int64_t J1, int64_t d, int64_t lobes, int64_t n, const float *a, const float *X,
                   const int64_t *idx, int64_t N, int64_t Q, const float *nT, int64_t ldn, const float *lam,
                   const int64_t *perm, const float *cq, float rmax, int64_t zyz, int64_t vmaj, int64_t nt, float *out,
                   int64_t *bad) {
    zh41p_pose_sh(J1, d, lobes, n, a, X, idx, N, Q, nT, ldn, 1, lam, perm, cq, rmax, zyz, vmaj, 0, nt, out, bad);
}
"""
_POSE_SH_SIGNATURES = {"zh36o_pose_sh": [_I, _I, _I, _I, _P, _P, _P, _I, _I, _P, _I, _P, _P, _P, ctypes.c_float,
                                         _I, _I, _I, _P, _P],
                       "zh41p_pose_sh": [_I, _I, _I, _I, _P, _P, _P, _I, _I, _P, _I, _I, _P, _P, _P, ctypes.c_float,
                                         _I, _I, _I, _I, _P, _P]}


class _Sym:
    """A float32 vector expression of `_fast_terms_code`'s trace: each operation one C statement, in Python's order."""

    def __init__(self, name: str, lines: list):
        self.name, self.lines = name, lines

    def _op(self, other, op: str, swap: bool = False) -> "_Sym":
        o = other.name if isinstance(other, _Sym) else f"(float){float(other)!r}"
        a, b = (o, self.name) if swap else (self.name, o)
        t = _Sym(f"t{len(self.lines)}", self.lines)
        self.lines.append(f"const v16 {t.name} = {a} {op} {b};")
        return t

    def __mul__(self, o): return self._op(o, "*")
    def __rmul__(self, o): return self._op(o, "*", True)
    def __add__(self, o): return self._op(o, "+")
    def __radd__(self, o): return self._op(o, "+", True)
    def __sub__(self, o): return self._op(o, "-")
    def __rsub__(self, o): return self._op(o, "-", True)


def _fast_terms_code() -> str:
    """C of ``int terms_fast(n, x, y, z, Y)``: for n up to `sh.FAST_MAX_ORDER`, Y[i] = `sh._terms_fast`(x, y, z, n)[i]
    by the same float32 operations in the same order (traced from it; its constants cast to float as torch
    takes a Python scalar), returning 1; 0 above it (the caller's recurrence)."""
    import types

    from methods.core import sh

    fn = sh._terms_fast
    body = ["static int terms_fast(int64_t n, v16 x, v16 y, v16 z, v16 *Y) {", "    switch (n) {"]
    for order in range(1, sh.FAST_MAX_ORDER + 1):
        lines: list = []
        shim = types.SimpleNamespace(full_like=lambda v, c, _l=lines: _Sym(f"((v16){{}} + (float){float(c)!r})", _l))
        traced = types.FunctionType(fn.__code__, {**fn.__globals__, "torch": shim})
        out = traced(_Sym("x", lines), _Sym("y", lines), _Sym("z", lines), order)
        body.append(f"    case {order}: {{")
        body += ["        " + ln for ln in lines]
        body += [f"        Y[{i}] = {t.name};" for i, t in enumerate(out)]
        body += ["        return 1;", "    }"]
    body += ["    default: return 0;", "    }", "}"]
    return "\n".join(body)
POSE_SH_NMAX = 8
MIN_COLS_PER_POSE_SH_THREAD = 1024   # vertices per thread below which one thread makes `pose_sh`


def _pose_sh_lib(row12: bool = True):
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call (b541a75);
    # products and sums not fused: `runtime._vertex_sh`'s operations (and `zh35o_pose_cols`' bits).
    # ``row12`` False: built without the 12-sum vector pose row (zh42p; `-DZH42P_NO_ROW12`: the generic loop,
    # the tests' oracle of the same bits)
    return load("zh36o_pose_sh" if row12 else "zh42p_pose_sh_loop", _pose_sh_source(), _POSE_SH_SIGNATURES,
                extra_flags=("-fopenmp", "-ffp-contract=off", *native.isa_flags(), *_avx512_flags(),
                             *(() if row12 else ("-DZH42P_NO_ROW12",))))


@functools.lru_cache(maxsize=None)
def _pose_sh_source() -> str:
    """`_POSE_SH_SOURCE` with `_fast_terms_code` in place (made once: pure, no library loaded here)."""
    return _POSE_SH_SOURCE.replace("@FAST_TERMS@", _fast_terms_code())


@functools.lru_cache(maxsize=None)
def _recurrence_constants(n: int) -> Tensor:
    """float32 constants of `sh._terms_recurrence` at order n, in the order `zh36o_pose_sh` reads them: √2,
    then per m the sectoral start q_m^m and per l > m the factor √(2m+3) (l = m + 1) or a_lm, b_lm — each
    the Python float the recurrence multiplies by (float32 as torch takes a scalar)."""
    out = [math.sqrt(2.0)]
    qmm = 1.0 / math.sqrt(4.0 * math.pi)
    for m in range(n):
        if m > 0:
            qmm *= math.sqrt((2 * m + 1) / (2 * m))
        out.append(qmm)
        for l in range(m + 1, n):
            if l == m + 1:
                out.append(math.sqrt(2 * m + 3))
            else:
                out += [math.sqrt((4 * l * l - 1) / (l * l - m * m)),
                        math.sqrt(((l - 1) ** 2 - m * m) / (4 * (l - 1) ** 2 - 1))]
    return torch.tensor(out, dtype=torch.float32)


@functools.lru_cache(maxsize=64)
def _pose_sh_constants(n: int, lam: tuple, perm: tuple) -> tuple[Tensor, Tensor, Tensor] | None:
    """(Λ (n,) float32, perm (n²,) int64, `_recurrence_constants`(n)) as `zh36o_pose_sh` reads them, once per
    (order, Λ, perm) — or None: perm not a permutation of the n² rows (pure: no library is loaded here)."""
    if sorted(perm) != list(range(n * n)):
        return None
    return torch.tensor(lam, dtype=torch.float32), torch.tensor(perm, dtype=torch.int64), _recurrence_constants(n)


def pose_sh_available() -> bool:
    """Whether `pose_sh` can run here (a compiler, ``PRTBENCH_COMPILE`` / ``PRTBENCH_ZH_NATIVE`` on)."""
    return terms_switched_on() and _pose_sh_lib() is not None


def pose_sh(X: Tensor, a: Tensor, idx: Tensor | None, nT: Tensor, lam: tuple, perm: tuple, lobes: int, n: int,
            rmax: float, out: Tensor | None = None, zyz: bool = True, dim: int = 0) -> Tensor | None:
    """(n², Q) float32: `runtime._vertex_sh`(`pose_columns`(X, a, idx), nT, lam, lobes, n, 0, True, perm) — the
    visibility of the vertices idx (None: every vertex) in the ZYZ frames of their unit normals nT (3, Q), rows
    in the order perm — by one C call (`zh36o_pose_sh`, above: the product's bits, eq. 1 to float32 round-off
    against the compiled pass), or None where it does not run (no compiler, ``PRTBENCH_ZH_NATIVE=0``, X not
    float32 CPU vertex-major (`vertex_major`) with d = lobes (2 + n) ≤ `POSE_COLS_DMAX`, n above
    `POSE_SH_NMAX`, a not (J+1,) float32, idx not int64, nT not (3, Q) float32 with unit column stride, perm
    not a permutation of the n² rows, an id out of [0, N)). ``out``: a float32 buffer of at least n² Q elements
    the result is written into (its first n² Q, viewed (n², Q): the caller's buffer kept across frames, no fresh
    pages per call), else a new one. ``zyz`` False: the SH in world space (`_vertex_sh`'s ``zyz`` False); ``dim``
    1: the result (Q, n²) (`_vertex_sh`'s ``dim``)."""
    lib = _pose_sh_lib() if terms_switched_on() else None
    if lib is None or X.dtype != torch.float32 or X.device.type != "cpu" or X.dim() != 3 or not is_vertex_major(X) \
            or not 1 <= n <= POSE_SH_NMAX or lobes < 1 or X.shape[2] != lobes * (2 + n) \
            or X.shape[2] > POSE_COLS_DMAX or len(lam) != n or len(perm) != n * n \
            or a.dtype != torch.float32 or a.device.type != "cpu" or a.dim() != 1 or a.shape[0] != X.shape[0] \
            or (idx is not None and (idx.dtype != torch.int64 or idx.dim() != 1 or idx.device.type != "cpu")) \
            or dim not in (0, 1):
        return None
    J1, N, d = (int(s) for s in X.shape)
    Q = N if idx is None else int(idx.shape[0])
    if nT.dtype != torch.float32 or nT.device.type != "cpu" or tuple(nT.shape) != (3, Q) or (Q and nT.stride(1) != 1):
        return None
    consts = _pose_sh_constants(n, tuple(float(x) for x in lam), tuple(int(i) for i in perm))
    if consts is None:
        return None
    lamt, permt, cq = consts
    a = a.contiguous()
    if idx is not None:
        idx = idx.contiguous()
    if out is not None and (out.dtype != torch.float32 or out.device.type != "cpu" or not out.is_contiguous()
                            or out.numel() < n * n * Q):
        out = None
    shape = (n * n, Q) if dim == 0 else (Q, n * n)
    out = torch.empty(shape, dtype=torch.float32) if out is None else out.view(-1)[:n * n * Q].view(shape)
    if Q == 0:
        return out
    bad = torch.zeros(1, dtype=torch.int64)
    nt = max(1, min(torch.get_num_threads(), Q // MIN_COLS_PER_POSE_SH_THREAD))
    lib.zh36o_pose_sh(J1, d, lobes, n, a.data_ptr(), X.data_ptr(), 0 if idx is None else idx.data_ptr(), N, Q,
                      nT.data_ptr(), nT.stride(0), lamt.data_ptr(), permt.data_ptr(), cq.data_ptr(), float(rmax),
                      int(bool(zyz)), int(dim == 1), nt, out.data_ptr(), bad.data_ptr())
    return None if int(bad[0]) else out


class PoseSHBound:
    """`pose_sh` of every vertex (``idx`` None) for one model X, Λ, perm, order and layout, its constant
    arguments checked and resolved once (`pose_sh_bind`; zh41p): per pose only the pose's checks, ``a`` = [pose, 1]
    written into a kept buffer and one C call (`zh41p_pose_sh`, the same loop as `zh36o_pose_sh`: the same
    bits), the normals read as the (N, 3) rows they are (no (3, N) copy). A P frame's serial Python around
    the call (the library look-up, the checks of X, the constants' keys, ``torch.cat`` of the pose and the
    normals' transpose) was ~0.2 ms of the bench creature's frame with the caches cold (1 thread)."""

    __slots__ = ("X", "fn", "J1", "d", "lobes", "n", "N", "lamt", "permt", "cq", "rmax", "zyz", "vmaj", "a", "bad",
                 "xp", "lp", "pp", "qp", "ap", "bp")

    def __call__(self, pose: Tensor, normal: Tensor, rows: Tensor | None = None, out: Tensor | None = None
                 ) -> Tensor | None:
        """(N, n²) (``dim`` 1) or (n², N): `pose_sh`(X, [pose, 1], None, normal.T, …) — or None where it does not
        run (``pose`` not (J1 − 1,) float32 CPU, ``normal`` not (N, 3) float32 CPU contiguous, ``out`` not such
        an array of that shape, ``rows`` given without ``dim`` 1 or ``out``, or not int64 CPU, or an id out of
        [0, N)). ``out``: written there. ``rows`` (Q,) int64: the rows of those vertices alone written into
        ``out`` (each the same bits as the full call's; the others untouched; an id twice: written twice, the
        same) — a P frame's rows it reads (`ZHShadow._fill_visibility`). The switches (``PRTBENCH_COMPILE``,
        ``PRTBENCH_ZH_NATIVE``) are the caller's to read (`switches_on`, once a frame)."""
        N, n2 = self.N, self.n * self.n
        shape = (N, n2) if self.vmaj else (n2, N)
        if pose.dtype != torch.float32 \
                or pose.device.type != "cpu" or pose.shape != (self.J1 - 1,) or normal.dtype != torch.float32 \
                or normal.device.type != "cpu" or normal.shape != (N, 3) or not normal.is_contiguous() \
                or (out is not None and (out.dtype != torch.float32 or out.device.type != "cpu"
                                         or out.shape != shape or not out.is_contiguous())) \
                or (rows is not None and (out is None or not self.vmaj or rows.dtype != torch.int64
                                          or rows.device.type != "cpu" or rows.dim() != 1)):
            return None
        self.a[:-1].copy_(pose)
        if out is None:
            out = torch.empty(shape, dtype=torch.float32)
        if rows is not None:
            rows = rows.contiguous()
        Q = N if rows is None else int(rows.shape[0])
        if Q == 0:
            return out
        nt = max(1, min(torch.get_num_threads(), Q // MIN_COLS_PER_POSE_SH_THREAD))
        self.fn(self.J1, self.d, self.lobes, self.n, self.ap, self.xp, 0 if rows is None else rows.data_ptr(), N, Q,
                normal.data_ptr(), 1, 3, self.lp, self.pp, self.qp, self.rmax, self.zyz, self.vmaj,
                int(rows is not None), nt, out.data_ptr(), self.bp)
        return None if int(self.bad[0]) else out

    def _write_pose(self, pose: Tensor) -> None:
        """a = [pose, 1]: the pose's J1 − 1 floats into the kept buffer by ``memmove`` (no torch call)."""
        if not pose.is_contiguous():
            pose = pose.contiguous()
        ctypes.memmove(self.ap, pose.data_ptr(), 4 * (self.J1 - 1))

    def rows_into(self, pose: Tensor, normal: Tensor, rows: Tensor, out: Tensor) -> Tensor | None:
        """``__call__``(pose, normal, rows, out) of a vertex-major binding (the same C call, the same rows bits) with
        its pose written by ``memmove`` and the failure flag read by ctypes instead of torch indexing (zh46: a P
        frame's `ZHShadow._fill_visibility` under ``bound_glue``); the same checks, None where ``__call__`` gives
        None."""
        N, n2 = self.N, self.n * self.n
        if not self.vmaj or pose.dtype != torch.float32 or pose.device.type != "cpu" or pose.shape != (self.J1 - 1,) \
                or normal.dtype != torch.float32 or normal.device.type != "cpu" or normal.shape != (N, 3) \
                or not normal.is_contiguous() or out.dtype != torch.float32 or out.device.type != "cpu" \
                or out.shape != (N, n2) or not out.is_contiguous() or rows.dtype != torch.int64 \
                or rows.device.type != "cpu" or rows.dim() != 1:
            return None
        self._write_pose(pose)
        if not rows.is_contiguous():
            rows = rows.contiguous()
        Q = int(rows.shape[0])
        if Q == 0:
            return out
        nt = max(1, min(torch.get_num_threads(), Q // MIN_COLS_PER_POSE_SH_THREAD))
        self.fn(self.J1, self.d, self.lobes, self.n, self.ap, self.xp, rows.data_ptr(), N, Q, normal.data_ptr(), 1, 3,
                self.lp, self.pp, self.qp, self.rmax, self.zyz, self.vmaj, 1, nt, out.data_ptr(), self.bp)
        return None if ctypes.c_int64.from_address(self.bp).value else out

    def columns(self, pose: Tensor, idx: Tensor, nT: Tensor, buf: Tensor | None = None) -> Tensor | None:
        """(n², Q) float32: `pose_sh`(X, [pose, 1], idx, nT, …) of this binding (``dim`` 0 only: None for a
        vertex-major one) — a P frame's columns (zh43o: without `pose_sh`'s look-ups, checks of X and constants'
        keys and the ``torch.cat`` of the pose: ~0.1 ms of serial Python a bench frame with the caches cold; the
        same C loop, the same bits) — written into ``buf``'s first n² Q elements (float32 CPU contiguous, at least
        that many; else a new array), or None where it does not run (``pose`` not (J1 − 1,) float32 CPU, idx not
        (Q,) int64 CPU, nT not (3, Q) float32 CPU of unit column stride, an id out of [0, N))."""
        if self.vmaj or pose.dtype != torch.float32 or pose.device.type != "cpu" or pose.shape != (self.J1 - 1,) \
                or idx.dtype != torch.int64 or idx.device.type != "cpu" or idx.dim() != 1 \
                or nT.dtype != torch.float32 or nT.device.type != "cpu" or nT.dim() != 2:
            return None
        Q, n2 = int(idx.shape[0]), self.n * self.n
        if tuple(nT.shape) != (3, Q) or (Q and nT.stride(1) != 1):
            return None
        if buf is None or buf.dtype != torch.float32 or buf.device.type != "cpu" or not buf.is_contiguous() \
                or buf.numel() < n2 * Q:
            out = torch.empty(n2, Q, dtype=torch.float32)
        else:
            out = buf.view(-1)[:n2 * Q].view(n2, Q)
        if Q == 0:
            return out
        self._write_pose(pose)
        if not idx.is_contiguous():
            idx = idx.contiguous()
        nt = max(1, min(torch.get_num_threads(), Q // MIN_COLS_PER_POSE_SH_THREAD))
        self.fn(self.J1, self.d, self.lobes, self.n, self.ap, self.xp, idx.data_ptr(), self.N, Q, nT.data_ptr(),
                nT.stride(0), 1, self.lp, self.pp, self.qp, self.rmax, self.zyz, 0, 0, nt, out.data_ptr(), self.bp)
        return None if ctypes.c_int64.from_address(self.bp).value else out


def pose_sh_bind(X: Tensor, lam: tuple, perm: tuple, lobes: int, n: int, rmax: float, zyz: bool = True,
                 dim: int = 0) -> PoseSHBound | None:
    """A `PoseSHBound` of `pose_sh`(X, ·, None, ·, lam, perm, lobes, n, rmax, None, zyz, dim), or None where
    `pose_sh` would not run for these arguments (then the caller's `pose_sh`)."""
    lib = _pose_sh_lib() if terms_switched_on() else None
    if lib is None or X.dtype != torch.float32 or X.device.type != "cpu" or X.dim() != 3 or not is_vertex_major(X) \
            or not 1 <= n <= POSE_SH_NMAX or lobes < 1 or X.shape[2] != lobes * (2 + n) \
            or X.shape[2] > POSE_COLS_DMAX or len(lam) != n or len(perm) != n * n or dim not in (0, 1):
        return None
    consts = _pose_sh_constants(n, tuple(float(x) for x in lam), tuple(int(i) for i in perm))
    if consts is None:
        return None
    b = PoseSHBound()
    b.X, b.fn = X, lib.zh41p_pose_sh
    b.J1, b.N, b.d = (int(s) for s in X.shape)
    b.lobes, b.n, b.rmax, b.zyz, b.vmaj = int(lobes), int(n), float(rmax), int(bool(zyz)), int(dim == 1)
    b.lamt, b.permt, b.cq = consts
    b.a = torch.ones(b.J1, dtype=torch.float32)
    b.bad = torch.zeros(1, dtype=torch.int64)
    b.xp, b.lp, b.pp, b.qp = X.data_ptr(), b.lamt.data_ptr(), b.permt.data_ptr(), b.cq.data_ptr()
    b.ap, b.bp = b.a.data_ptr(), b.bad.data_ptr()
    return b


# -- zh37v ------------------------------------------------------------------------------------------
# `fused_pixels`' object samples with the interpolated dot regrouped (``fma``, `ZHShadow.fma_terms`):
# `zh33p_fused` evaluates Σ_f ((U0[c, f] b0 + U1[c, f] b1) + U2[c, f] b2) · feature[f] lane by lane as
# Inductor's `sample_terms` kernel does (its bits: per point and channel 10 eight-lane steps of 3 products,
# 2 sums, a product and a sum — ~210 vector operations a point; `perf` puts ~1/3 of a paper V frame's ~4.3 ms
# fused pass at 1 thread in that dot); here the same sum as b0 (U0[c]·f) + b1 (U1[c]·f) + b2 (U2[c]·f): per point 9 running
# dot products of fused multiply-adds (3 corners × 3 channels, 9 independent chains) and one 8-lane
# combination and tree per channel — 3·K/8·3 multiply-adds instead of 7·3·K/8 operations. The same terms to
# float32 round-off (not the same bits: the sums in another order, products fused), the plane samples and
# everything else as `zh33p_fused` (the same source, ``-ffp-contract=off`` outside the explicit multiply-adds).
# Each point is one thread's: the bits do not depend on the thread count. Bench creature V frame, 36 K object
# samples, 1 thread, same process (`benchmarks.zh_fused_ab`): the pass 4.43 → 4.26 ms (p25; 4.19 → 3.94 min),
# with every table row in L1 3.76 → 3.57 — the dot's arithmetic is not what bounds the object samples (the
# plane part alone is ~1.8 ms; the table rows' misses ~0.6). Dropped: prefetching the next 8 points' rows
# (+0.3 ms with the rows in L1, within the noise with the real table).
def _fma_dot(K: int) -> str:
    assert K % 8 == 0
    return f"""
static void df_{K}(const float* f, const float* u0, const float* u1, const float* u2, float b0, float b1, float b2,
                   float* out) {{
    v8 a0[3] = {{{{0}}, {{0}}, {{0}}}}, a1[3] = {{{{0}}, {{0}}, {{0}}}}, a2[3] = {{{{0}}, {{0}}, {{0}}}};
#pragma GCC unroll 16
    for (int j = 0; j < {K}; j += 8) {{
        const v8 fj = ld(f + j);
        for (int c = 0; c < 3; ++c) {{
            a0[c] = fma8(ld(u0 + c * {K} + j), fj, a0[c]);
            a1[c] = fma8(ld(u1 + c * {K} + j), fj, a1[c]);
            a2[c] = fma8(ld(u2 + c * {K} + j), fj, a2[c]);
        }}
    }}
    const v8 B0 = {{b0, b0, b0, b0, b0, b0, b0, b0}}, B1 = {{b1, b1, b1, b1, b1, b1, b1, b1}},
             B2 = {{b2, b2, b2, b2, b2, b2, b2, b2}};
    for (int c = 0; c < 3; ++c) {{
        const v8 w = fma8(a2[c], B2, fma8(a1[c], B1, a0[c] * B0));
        const float s0 = w[0] + w[4], s1 = w[1] + w[5], s2 = w[2] + w[6], s3 = w[3] + w[7];
        out[c] = (s0 + s2) + (s1 + s3);
    }}
}}
"""


def _terms_k(D: int, dif: bool, spec: bool) -> int:
    return (((D + 1) * (D + 2) // 2 + 3) if dif else 0) + ((D + 1) * (D + 2) // 2 + D * (D + 1) // 2 if spec else 0)


_FMA_DOT_CALL = "dt(fb + i * K, U + i0 * 3 * K, U + i1 * 3 * K, U + i2 * 3 * K, (1.0f - bu) - bv, bu, bv, t);"
_FMA_FUSED_SOURCE = _FUSED_SOURCE.replace(
    "typedef void (*dt_fn)", r"""static inline v8 fma8(v8 a, v8 b, v8 c) {
#ifdef __FMA__
    return __builtin_ia32_vfmaddps256(a, b, c);
#else
    v8 r;
    for (int i = 0; i < 8; ++i) r[i] = __builtin_fmaf(a[i], b[i], c[i]);
    return r;
#endif
}
""" + "".join(_fma_dot(_terms_k(*v)) for v in TERMS_VARIANTS) + "typedef void (*dt_fn)", 1) \
    .replace("void zh33p_fused(", "void zh37v_fused(", 1) \
    .replace("    const dt_fn dt = dts[variant];",
             "    static const dt_fn dfs[] = {" + ", ".join(f"df_{_terms_k(*v)}" for v in TERMS_VARIANTS) + "};\n"
             f"    const dt_fn dt = dfs[variant % {len(TERMS_VARIANTS)}];", 1)
assert _FMA_FUSED_SOURCE.count(_FMA_DOT_CALL) == 1 and "zh37v_fused(" in _FMA_FUSED_SOURCE \
    and "dfs[variant" in _FMA_FUSED_SOURCE
_FMA_FUSED_SIGNATURES = {"zh37v_fused": _FUSED_SIGNATURES["zh33p_fused"]}


def _fma_fused_lib():
    """`_fused_lib`'s conditions, then the library of `zh37v_fused` or None. Not cached here (b541a75)."""
    if not terms_switched_on() or _inductor_lanes() not in TERMS_LANES:
        return None
    return load("zh37v_fused", _FMA_FUSED_SOURCE, _FMA_FUSED_SIGNATURES,
                       extra_flags=("-ffp-contract=off", "-fopenmp", *native.isa_flags()))


# `plane_mask` as vector code (zh37v): the same match, counts and checks per sample as `zh_plane_split`'s loop,
# written so that the compiler vectorises it (built with the ISA flags; that library's build has none, and its
# per-sample ``spec[region]`` load and ``hit ? hit[p] : 1`` kept the loop scalar): the regions' specular flags
# as one 64-bit word (R ≤ 64), one loop without and one with ``hit``. Integer counts and a byte mask from float
# compares: the same values. Bench creature, 262,144 samples, 1 thread: 0.65 → 0.28 ms back to back.
_PMASK_SOURCE = r"""
#include <stdint.h>

void zh37v_plane_mask(const float* normal, const float* n0, const int64_t* region, const uint8_t* spec, int64_t R,
                      int64_t P, int64_t nt, uint8_t* mask, int64_t* cnt, const uint8_t* hit) {
    uint64_t bits = 0;
    for (int64_t r = 0; r < R && r < 64; ++r) bits |= (uint64_t)(spec[r] != 0) << r;
    const uint64_t R_ = (uint64_t)R;   /* (the caller: 0 <= R <= 64) */
#pragma omp parallel for num_threads(nt) schedule(static, 1) if(nt > 1)
    for (int64_t k = 0; k < nt; ++k) {
        const float a = n0[0], b = n0[1], c = n0[2];
        int64_t ne = 0, ns = 0, bad = 0;
        const int64_t p0 = P * k / nt, p1 = P * (k + 1) / nt;
        if (!hit) {
            for (int64_t p = p0; p < p1; ++p) {
                const float* n = normal + 3 * p;
                const int64_t e = (n[0] == a) & (n[1] == b) & (n[2] == c);
                mask[p] = (uint8_t)e;
                ne += e;
                const uint64_t r = (uint64_t)region[p];
                const int64_t ok = r < R_;
                bad += !ok;
                ns += e & ok & (int64_t)((bits >> (r & 63)) & 1);
            }
        } else {
            for (int64_t p = p0; p < p1; ++p) {
                const float* n = normal + 3 * p;
                const int64_t e = (n[0] == a) & (n[1] == b) & (n[2] == c);
                mask[p] = (uint8_t)e;
                ne += e;
                const uint64_t r = (uint64_t)region[p];
                const int64_t ok = r < R_, h = hit[p] != 0;
                bad += (!ok & h) | (e & !h);
                ns += e & ok & (int64_t)((bits >> (r & 63)) & 1);
            }
        }
        cnt[3 * k] = ne;
        cnt[3 * k + 1] = ns;
        cnt[3 * k + 2] = bad;
    }
}
"""
_PMASK_SIGNATURES = {"zh37v_plane_mask": _SPLIT_SIGNATURES["plane_mask"]}
# `plane_mask` by `zh37v_plane_mask` where it builds; False: `zh_plane_split`'s loop (the tests' oracle)
VECTOR_PLANE_MASK = True


def _pmask_lib():
    """The library of `zh37v_plane_mask` or None. Not cached here (b541a75)."""
    return load("zh37v_plane_mask", _PMASK_SOURCE, _PMASK_SIGNATURES,
                       extra_flags=("-fopenmp", *native.isa_flags()))


# -- zh38v ------------------------------------------------------------------------------------------
# The lighting's ZYZ rotation (`runtime.rotate_lighting`: L / VL / VBL frames rotate the kept projection, E
# frames take a new map's to world space) in one C call: its three z rotations (cos / sin of |m|·angle per
# coefficient, the (l, −m) partner's sign) and its two fixed (n², n²) products, the same steps as its numpy
# code in float64 — the same coefficients to float64 round-off (numpy's cos / sin and BLAS's sums in another
# order). numpy's ~20 calls on (n², 3) arrays cost ~0.2 ms at order 4 and ~0.4 at order 8 inside a lighting
# frame (serial at any thread count); the C call a few microseconds.
_ROTATE_SOURCE = r"""
#include <stdint.h>
#include <math.h>

/* one z rotation of x (n2, C) into y: y[i] = cos(t |m_i|) x[i] + (sin(t |m_i|) sgn_i) x[perm_i] */
static void zh38v_rz(int64_t n2, int64_t C, double t, const double *mabs, const int64_t *perm, const double *sgn,
                     const double *x, double *y) {
    for (int64_t i = 0; i < n2; ++i) {
        const double a = t * mabs[i], cs = cos(a), sn = sin(a) * sgn[i];
        const double *xi = x + i * C, *xp = x + perm[i] * C;
        for (int64_t c = 0; c < C; ++c) y[i * C + c] = cs * xi[c] + sn * xp[c];
    }
}

/* y (n2, C) = X (n2, n2) x */
static void zh38v_mm(int64_t n2, int64_t C, const double *X, const double *x, double *y) {
    for (int64_t i = 0; i < n2; ++i)
        for (int64_t c = 0; c < C; ++c) {
            double s = 0.0;
            for (int64_t j = 0; j < n2; ++j) s += X[i * n2 + j] * x[j * C + c];
            y[i * C + c] = s;
        }
}

/* `runtime.rotate_lighting`'s test and angles of R (3, 3) row-major, as its Python code computes them (the
   same libm calls and operations: the same values): returns 0 with ang = (g, b, a) when det R > 0 and every
   |(R Rᵀ)_ij − δ_ij| <= tol, else 1 */
int64_t zh38v_angles(const double *R, double tol, double *ang) {
    const double r00 = R[0], r01 = R[1], r02 = R[2], r10 = R[3], r11 = R[4], r12 = R[5], r20 = R[6], r21 = R[7],
                 r22 = R[8];
    const double det = r00 * (r11 * r22 - r12 * r21) - r01 * (r10 * r22 - r12 * r20) + r02 * (r10 * r21 - r11 * r20);
    if (!(det > 0)) return 1;
    double mx = 0.0;
    for (int i = 0; i < 3; ++i)
        for (int j = i; j < 3; ++j) {
            const double d = fabs(((R[3 * i] * R[3 * j]) + R[3 * i + 1] * R[3 * j + 1]) + R[3 * i + 2] * R[3 * j + 2]
                                  - (double)(i == j));
            if (!(d <= mx)) mx = d;   /* (Python's max: a NaN first stays) */
        }
    if (!(mx <= tol)) return 1;
    const double s = hypot(r02, r12);
    const double a = s > 0 ? atan2(r12, r02) : 0.0;
    const double b = atan2(s, r22);
    const double ca = cos(a), sa = sin(a), cb = cos(b), sb = sin(b);
    const double u0 = ca * r00 + sa * r10, u1 = -sa * r00 + ca * r10;
    ang[0] = atan2(u1, cb * u0 - sb * r20);
    ang[1] = b;
    ang[2] = a;
    return 0;
}

/* out (n2, C) = Rz(ang[2]) Xm Rz(ang[1]) Xp Rz(ang[0]) c (`runtime.rotate_lighting`'s steps, in its order);
   w: 2 n2 C doubles of scratch */
void zh38v_rotate(int64_t n2, int64_t C, const double *c, const double *ang, const double *mabs, const int64_t *perm,
                  const double *sgn, const double *Xm, const double *Xp, double *w, double *out) {
    double *a = w, *b = w + n2 * C;
    zh38v_rz(n2, C, ang[0], mabs, perm, sgn, c, a);
    zh38v_mm(n2, C, Xp, a, b);
    zh38v_rz(n2, C, ang[1], mabs, perm, sgn, b, a);
    zh38v_mm(n2, C, Xm, a, b);
    zh38v_rz(n2, C, ang[2], mabs, perm, sgn, b, out);
}
"""
_ROTATE_SIGNATURES = {"zh38v_rotate": [_I, _I, _P, _P, _P, _P, _P, _P, _P, _P, _P],
                      "zh38v_angles": [_P, ctypes.c_double, _P]}


def _rotate_lib():
    """The library of `zh38v_rotate` or None (no compiler, ``PRTBENCH_COMPILE=0``, ``PRTBENCH_ZH_NATIVE=0``).
    Not cached here (b541a75)."""
    if not terms_switched_on():
        return None
    lib = native.load("zh38v_rotate", _ROTATE_SOURCE, _ROTATE_SIGNATURES, extra_flags=("-ffp-contract=off",))
    if lib is not None:
        lib.zh38v_angles.restype = ctypes.c_int64
    return lib


def rotate_lighting(c: Tensor, R: Tensor, tol: float, tables: tuple) -> Tensor | None:
    """`runtime.rotate_lighting`(c, R) by two C calls (its test and ZYZ angles of R: the same values; then
    `rotate_zyz`), or None: the library does not run, c or R not float64 CPU arrays of its shapes, or R not a
    rotation to ``tol`` (the caller's fallback then)."""
    lib = _rotate_lib()
    if lib is None or R.dtype != torch.float64 or R.device.type != "cpu" or R.shape != (3, 3):
        return None
    ang = torch.empty(3, dtype=torch.float64)
    R = R.contiguous()   # (zh41l: kept alive through the call — a temporary's memory was freed before C read it)
    if lib.zh38v_angles(R.data_ptr(), float(tol), ang.data_ptr()) != 0:
        return None
    return _rotate_zyz(lib, c, ang, tables)


def rotate_zyz(c: Tensor, angles: tuple[float, float, float], tables: tuple) -> Tensor | None:
    """(n², C) float64 = `runtime.rotate_lighting`'s three z rotations by ``angles`` (g, b, a) and its fixed
    products, ``tables`` its `_lighting_zyz_tables` as contiguous tensors (mabs, perm int64, sgn, Xm, Xp), by
    one C call; None where it does not run (no library, c not a float64 CPU (n², C) array)."""
    lib = _rotate_lib()
    return None if lib is None else _rotate_zyz(lib, c, torch.tensor(angles, dtype=torch.float64), tables)


def _rotate_zyz(lib, c: Tensor, ang: Tensor, tables: tuple) -> Tensor | None:
    if c.dtype != torch.float64 or c.device.type != "cpu" or c.dim() != 2:
        return None
    mabs, perm, sgn, Xm, Xp = tables
    n2, C = int(c.shape[0]), int(c.shape[1])
    if mabs.shape != (n2,) or Xm.shape != (n2, n2):
        return None
    c = c.contiguous()
    w = torch.empty(2 * n2 * C, dtype=torch.float64)
    out = torch.empty(n2, C, dtype=torch.float64)
    lib.zh38v_rotate(n2, C, c.data_ptr(), ang.data_ptr(), mabs.data_ptr(), perm.data_ptr(), sgn.data_ptr(),
                     Xm.data_ptr(), Xp.data_ptr(), w.data_ptr(), out.data_ptr())
    return out


# -- zh41l ------------------------------------------------------------------------------------------
# A lighting frame's world-space lighting (`ZHShadow._lighting`: R = the map's to_world, c its polar-frame
# projection) by ONE C call: R Q (Q = `sh._LATLONG_QT`, a signed permutation: each entry ((0 + R_i0 Q_0j) +
# R_i1 Q_1j) + R_i2 Q_2j, exact — one non-zero product — and the zeros' signs torch's 3×3 product gives, +0),
# `zh38v_angles`' test and angles, `zh38v_rotate` (the same source, the same flags: the same bits as
# `rotate_lighting`) and the float64 → float32 rounding of ``.float()``. In the base these were a torch product,
# the key's tensor, `rotate_lighting`'s wrappers (its library lookup, three torch.empty, two ctypes calls) and
# ``.to(float32)``: ~0.31 ms of a lighting-only order-8 frame at 1 thread after the suite's idle, for ~10 µs of
# arithmetic. The scratch (float64 angles / steps / result) is kept per projection (`light_setup`); the float32
# result is a new tensor each call (callers keep it: `ZHShadow._light`).
_LIGHT_SOURCE = _ROTATE_SOURCE + r"""
/* out (n2, C) float32 = (float) `zh38v_rotate`(c, angles of R Q); 0, or 1 where `zh38v_angles` refuses R Q
   (then nothing written). a: the kept arguments n2, C, Q, mabs, perm, sgn, Xm, Xp, w (w: 3 n2 C + 3 doubles
   of scratch). */
int64_t zh41l_light(const int64_t *a, const double *R, const double *c, double tol, float *out) {
    const int64_t n2 = a[0], C = a[1];
    const double *Q = (const double *)(intptr_t)a[2];
    double *w = (double *)(intptr_t)a[8];
    double RQ[9];
    for (int i = 0; i < 3; ++i)
        for (int j = 0; j < 3; ++j) {
            double s = 0.0;
            for (int k = 0; k < 3; ++k) s += R[3 * i + k] * Q[3 * k + j];
            RQ[3 * i + j] = s;
        }
    double *ang = w + 3 * n2 * C, *o = w + 2 * n2 * C;
    if (zh38v_angles(RQ, tol, ang) != 0) return 1;
    zh38v_rotate(n2, C, c, ang, (const double *)(intptr_t)a[3], (const int64_t *)(intptr_t)a[4],
                 (const double *)(intptr_t)a[5], (const double *)(intptr_t)a[6], (const double *)(intptr_t)a[7], w, o);
    for (int64_t i = 0; i < n2 * C; ++i) out[i] = (float)o[i];
    return 0;
}
"""
_LIGHT_SIGNATURES = {**_ROTATE_SIGNATURES, "zh41l_light": [_P, _P, _P, ctypes.c_double, _P]}
# `ZHShadow._lighting`'s rotation of a kept projection by `light_world` where it runs; False: the base's steps
# (R Q by torch, `runtime.rotate_lighting`, ``.float()``; the tests' oracle)
NATIVE_LIGHT = True


def _light_lib():
    """The library of `zh41l_light` or None (as `_rotate_lib`; not cached here, b541a75)."""
    if not (NATIVE_LIGHT and terms_switched_on()):
        return None
    lib = native.load("zh41l_light", _LIGHT_SOURCE, _LIGHT_SIGNATURES, extra_flags=("-ffp-contract=off",))
    if lib is not None:
        lib.zh41l_light.restype = ctypes.c_int64
        lib.zh38v_angles.restype = ctypes.c_int64
    return lib


def light_setup(n2: int, C: int, Q: Tensor, tables: tuple) -> tuple | None:
    """`light_world`'s kept arguments for (n², C) projections, Q (3, 3) float64 and ``tables``
    (`runtime._lighting_zyz_tensors` of order n), or None where it does not run (then the caller's steps):
    (the library's function, the packed arguments' address, n², C, a 9-double buffer for R, what they point
    into). The function is kept: `light_world` checks the off switches (``NATIVE_LIGHT``, ``PRTBENCH_ZH_NATIVE``,
    ``PRTBENCH_COMPILE``) at each call instead of looking the library up (b541a75: no None is kept)."""
    lib = _light_lib()
    if lib is None or Q.shape != (3, 3) or Q.dtype != torch.float64 or Q.device.type != "cpu":
        return None
    mabs, perm, sgn, Xm, Xp = tables
    if mabs.shape != (n2,) or Xm.shape != (n2, n2) or Xp.shape != (n2, n2) or perm.dtype != torch.int64 \
            or not all(t.is_contiguous() and t.device.type == "cpu" for t in tables):
        return None
    Q = Q.contiguous()
    w = torch.empty(3 * n2 * C + 3, dtype=torch.float64)
    vals = [n2, C, Q.data_ptr(), *(t.data_ptr() for t in tables), w.data_ptr()]
    args = (ctypes.c_int64 * len(vals))(*vals)  # not a tensor: the method's state holds no addresses (test_threads)
    Rbuf = (ctypes.c_double * 9)()
    return lib.zh41l_light, ctypes.addressof(args), n2, C, Rbuf, (Q, tables, w, args, lib)


def light_world(st: tuple, c: Tensor, R: tuple, tol: float) -> Tensor | None:
    """(n², C) float32 = ``runtime.rotate_lighting(c, R @ Q).float()`` (its C path) for `light_setup`'s Q and R the
    nine floats of a (3, 3) rotation row-major, by one C call (the same bits), or None: switched off, c not a
    contiguous (n², C) float64 CPU array, or R Q not a rotation to ``tol`` (`zh38v_angles`)."""
    fn, args, n2, C, Rbuf, _ = st
    if not (NATIVE_LIGHT and terms_switched_on() and native.compile_enabled()) or len(R) != 9 \
            or c.dtype != torch.float64 or c.device.type != "cpu" or c.shape != (n2, C) or not c.is_contiguous():
        return None
    Rbuf[:] = R
    out = torch.empty(n2, C, dtype=torch.float32)
    return out if fn(args, Rbuf, c.data_ptr(), tol, out.data_ptr()) == 0 else None


# -- zh38v ------------------------------------------------------------------------------------------
# `vertex_table`'s rows four at a time (``VTABLE_ROWS4``): `zh34p_vtable` streams its region's table W (n², C)
# once per row — a load of W per multiply-add, ~0.65 ms for a VL frame's 3.6 K referenced rows at 1 thread
# (n² = 16, C = 240), bound by those loads. Here four consecutive rows of one region share each load of W
# (4 rows × 16 columns: 8 accumulators), every column of every row the same expression as `vrow`'s — x[0]·w
# then x[j]·w added in j order, fused as that library fuses them (the same source and flags) — so the same
# bits; rows of other regions, out-of-range rows and the columns past the last 16 as `vrow` row by row.
_VTABLE4_SOURCE = _VTABLE_SOURCE + r"""
/* rows x0..x3 of one region's table w (n2, C): out_k[c] for the columns c < C16 (a multiple of 16) */
static inline void vrow4(const float* x0, const float* x1, const float* x2, const float* x3, const float* w,
                         int64_t n2, int64_t C, int64_t C16, float* o0, float* o1, float* o2, float* o3) {
    for (int64_t c0 = 0; c0 < C16; c0 += 16) {
        const v8 wa = ld8(w + c0), wb = ld8(w + c0 + 8);
        v8 a0 = x0[0] * wa, b0 = x0[0] * wb, a1 = x1[0] * wa, b1 = x1[0] * wb;
        v8 a2 = x2[0] * wa, b2 = x2[0] * wb, a3 = x3[0] * wa, b3 = x3[0] * wb;
        for (int64_t j = 1; j < n2; ++j) {
            const v8 ua = ld8(w + j * C + c0), ub = ld8(w + j * C + c0 + 8);
            a0 = a0 + x0[j] * ua; b0 = b0 + x0[j] * ub;
            a1 = a1 + x1[j] * ua; b1 = b1 + x1[j] * ub;
            a2 = a2 + x2[j] * ua; b2 = b2 + x2[j] * ub;
            a3 = a3 + x3[j] * ua; b3 = b3 + x3[j] * ub;
        }
        st8(o0 + c0, a0); st8(o0 + c0 + 8, b0); st8(o1 + c0, a1); st8(o1 + c0 + 8, b1);
        st8(o2 + c0, a2); st8(o2 + c0 + 8, b2); st8(o3 + c0, a3); st8(o3 + c0 + 8, b3);
    }
}

/* `zh34p_vtable`, four rows of one region at a time where they are (each thread its contiguous range of i) */
void zh38v_vtable(int64_t NU, const int64_t* idx, const float* v, int64_t N, int64_t n2, const int64_t* vreg,
                  int64_t R, const float* W, int64_t C, float* U, int64_t nt, int64_t* bad) {
    int64_t nb = 0;
    const int64_t C16 = C / 16 * 16;
#pragma omp parallel for num_threads(nt) schedule(static, 1) reduction(+:nb) if(nt > 1)
    for (int64_t t = 0; t < nt; ++t) {
        const int64_t i1 = NU * (t + 1) / nt;
        for (int64_t i = NU * t / nt; i < i1;) {
            int64_t rows[4], rg[4];
            int ok = i + 4 <= i1;
            for (int k = 0; ok && k < 4; ++k) {
                rows[k] = idx ? idx[i + k] : i + k;
                ok = (uint64_t)rows[k] < (uint64_t)N;
                if (ok) {
                    rg[k] = R == 1 ? 0 : vreg[rows[k]];
                    ok = (uint64_t)rg[k] < (uint64_t)R && rg[k] == rg[0];
                }
            }
            if (ok) {
                const float* w = W + rg[0] * n2 * C;
                vrow4(v + rows[0] * n2, v + rows[1] * n2, v + rows[2] * n2, v + rows[3] * n2, w, n2, C, C16,
                      U + i * C, U + (i + 1) * C, U + (i + 2) * C, U + (i + 3) * C);
                if (C16 < C)
                    for (int k = 0; k < 4; ++k) vrow(v + rows[k] * n2, w, n2, C, U + (i + k) * C, C16);
                i += 4;
                continue;
            }
            const int64_t row = idx ? idx[i] : i;
            float* out = U + i * C;
            if ((uint64_t)row >= (uint64_t)N) { ++nb; ++i; continue; }
            const int64_t r = R == 1 ? 0 : vreg[row];
            if ((uint64_t)r >= (uint64_t)R) memset(out, 0, sizeof(float) * (size_t)C);
            else vrow(v + row * n2, W + r * n2 * C, n2, C, out, 0);
            ++i;
        }
    }
    bad[0] = nb;
}
"""
_VTABLE4_SIGNATURES = {"zh38v_vtable": _VTABLE_SIGNATURES["zh34p_vtable"]}
# `vertex_table` by `zh38v_vtable` (four rows a load of W: the same bits) where it builds; False: `zh34p_vtable`
VTABLE_ROWS4 = True


def _vtable4_lib():
    # not cached here (b541a75); `_vtable_lib`'s flags
    return load("zh38v_vtable", _VTABLE4_SOURCE, _VTABLE4_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=fast", *native.isa_flags()))


# -- zh38v ------------------------------------------------------------------------------------------
# `runtime.region_tables`' ``out`` (R, n², 3K) in one C call (`ZHShadow._native_table`, a lighting or material
# frame's): out[r, j, c, k] = Wd[k, 3 j + c] · kd_r[c] (k < Kd), Ws_r[k − Kd, 3 j + c] · ks_r[c] (a region with a
# specular table), 0 (a region without one when another has one) — the same single float32 products as its
# torch.mul, so the same bits; 2–4 strided torch products and a fill per region (~0.17 ms inside a bench VL
# frame at 1 thread) become one call.
_RTABLES_SOURCE = r"""
#include <stdint.h>

/* Wd (Kd, n2 3); ws[r] the address of region r's Ws (Ks, n2 3) or 0; kd, ks (R, 3); out (R, n2, 3, Kd + Ks) */
void zh38v_region_tables(int64_t R, int64_t n2, int64_t Kd, int64_t Ks, const float *Wd, const float *kd,
                         const int64_t *ws, const float *ks, float *out) {
    const int64_t K = Kd + Ks;
    for (int64_t r = 0; r < R; ++r) {
        const float *Ws = (const float *)(intptr_t)ws[r];
        for (int64_t j = 0; j < n2; ++j)
            for (int64_t c = 0; c < 3; ++c) {
                float *o = out + ((r * n2 + j) * 3 + c) * K;
                const float a = kd[3 * r + c], b = ks[3 * r + c];
                for (int64_t k = 0; k < Kd; ++k) o[k] = Wd[k * n2 * 3 + 3 * j + c] * a;
                for (int64_t k = 0; k < Ks; ++k) o[Kd + k] = Ws ? Ws[k * n2 * 3 + 3 * j + c] * b : 0.0f;
            }
    }
}
"""
_RTABLES_SIGNATURES = {"zh38v_region_tables": [_I, _I, _I, _I, _P, _P, _P, _P, _P]}


def _rtables_lib():
    # not cached here (b541a75); products only (no sums: nothing to fuse)
    return load("zh38v_region_tables", _RTABLES_SOURCE, _RTABLES_SIGNATURES, extra_flags=("-ffp-contract=off",))


def region_tables(tabs: list, n2: int, out: Tensor) -> int | None:
    """`runtime.region_tables`(tabs, n2, cpu, float32, out=out) by one C call (the same products: the same
    bits): K = Kd + Ks, or None where it does not run (no library, not float32 CPU tables of its shapes) —
    then nothing is written. tabs: per region (kd (3,), ks (3,), Wd (Kd, 3 n²), Ws (Ks, 3 n²) or None)."""
    lib = _rtables_lib() if terms_switched_on() else None
    if lib is None or not tabs:
        return None
    Wd = tabs[0][2]
    Ws = [t[3] for t in tabs]
    Kd = int(Wd.shape[0]) if Wd.dim() == 2 else -1
    Ks = next((int(w.shape[0]) for w in Ws if w is not None), 0)
    R = len(tabs)
    ok = Kd > 0 and Wd.shape == (Kd, 3 * n2) and out.shape == (R, n2, 3 * (Kd + Ks)) and out.is_contiguous()
    for t in (Wd, out, *[w for w in Ws if w is not None]):
        ok = ok and t.dtype == torch.float32 and t.device.type == "cpu" and t.is_contiguous()
    ok = ok and all(w is None or w.shape == (Ks, 3 * n2) for w in Ws) and all(t[2] is Wd for t in tabs)
    if not ok:
        return None
    kd = torch.stack([t[0] for t in tabs]).to(torch.float32).contiguous()
    ks = torch.stack([t[1] for t in tabs]).to(torch.float32).contiguous()
    if kd.shape != (R, 3) or ks.shape != (R, 3):
        return None
    ptr = torch.tensor([0 if w is None else w.data_ptr() for w in Ws], dtype=torch.int64)
    lib.zh38v_region_tables(R, n2, Kd, Ks, Wd.data_ptr(), kd.data_ptr(), ptr.data_ptr(), ks.data_ptr(),
                            out.data_ptr())
    return Kd + Ks


# === zh38p ==================================================================================================
#
# The vertex-shaded frames' resolve (`resolve_table`: the radiance interpolated per sample, box-filtered per
# pixel) with a pixel of 2×2 samples as one AVX-512 vector (`VECTOR_RESOLVE`): lane 4j + c holds sample j's
# channel c; its three corner rows (the face table's (x, y, z) rows) read as 4-float loads into the quarters;
# per lane the same products and sums as `zh35o_resolve`'s loop (no multiply-adds fused: -ffp-contract=off),
# the pixel's sum ((((0 + s0) + s1) + s2) + s3) over the quarters in order, a miss sample's quarter +0.0 (the
# skipped addition's bits: a sum that starts at +0.0 is never -0.0) — the same bits as `resolve_table` (the
# tests' oracle), ~1.6× faster on a bench frame (0.73 → 0.46 ms at 1 thread: the scalar loop was
# instruction-bound, ~30 operations a sample; a 16-lane gather per corner channel was slower, 1.1 ms). The face
# table has 3 spare floats at its end (the last row's z load). Other sample counts, no AVX-512: the scalar loop.
_VRESOLVE_SOURCE = _TRESOLVE_SOURCE.replace("void zh35o_resolve(", "static void unused_zh35o_resolve(") + r"""
#include <string.h>
#ifdef __AVX512F__
#include <immintrin.h>
#endif
#ifdef __AVX512F__
/* pix_range for S2 = 4, a pixel a step as one vector: lane 4j + c holds sample j's channel c (lane 3 of each
   quarter a spare), its three corner rows read as 4-float loads (the table has 3 spare floats at its end);
   per lane the same products and sums as pix_range, the pixel's sum ((((0 + s0) + s1) + s2) + s3) over the
   quarters in order; a miss sample's quarter is +0.0, which leaves a sum that starts at +0.0 unchanged (the
   skipped addition's bits). Build without fused multiply-adds (-ffp-contract=off). */
static int64_t pix4_range(const int64_t *face, const float *bu, const float *bv, const uint8_t *hit, int64_t M,
                          const float *T, int64_t i0, int64_t i1, float *out) {
    const __m512 one = _mm512_set1_ps(1.0f);
    const __m128 inv = _mm_set1_ps(0.25f);
    const __m512i rep = _mm512_set_epi32(3, 3, 3, 3, 2, 2, 2, 2, 1, 1, 1, 1, 0, 0, 0, 0);
    for (int64_t i = i0; i < i1; ++i) {
        const int64_t p = 4 * i;
        uint32_t hb;
        memcpy(&hb, hit + p, 4);
        if (hb == 0) { out[3 * i] = 0.0f; out[3 * i + 1] = 0.0f; out[3 * i + 2] = 0.0f; continue; }
        const __mmask16 hm = (__mmask16)((hb & 0xff ? 0x000f : 0) | (hb & 0xff00 ? 0x00f0 : 0)
                                         | (hb & 0xff0000 ? 0x0f00 : 0) | (hb & 0xff000000u ? 0xf000 : 0));
        const float *r[4];
        for (int j = 0; j < 4; ++j) {
            int64_t f = face[p + j];
            if ((hb >> (8 * j)) & 0xff) {
                if ((uint64_t)f >= (uint64_t)M) return 1;
            } else {
                f = 0;
            }
            r[j] = T + 9 * f;
        }
        __m512 X = _mm512_castps128_ps512(_mm_loadu_ps(r[0])), Y = _mm512_castps128_ps512(_mm_loadu_ps(r[0] + 3)),
               Z = _mm512_castps128_ps512(_mm_loadu_ps(r[0] + 6));
        X = _mm512_insertf32x4(X, _mm_loadu_ps(r[1]), 1); Y = _mm512_insertf32x4(Y, _mm_loadu_ps(r[1] + 3), 1);
        Z = _mm512_insertf32x4(Z, _mm_loadu_ps(r[1] + 6), 1);
        X = _mm512_insertf32x4(X, _mm_loadu_ps(r[2]), 2); Y = _mm512_insertf32x4(Y, _mm_loadu_ps(r[2] + 3), 2);
        Z = _mm512_insertf32x4(Z, _mm_loadu_ps(r[2] + 6), 2);
        X = _mm512_insertf32x4(X, _mm_loadu_ps(r[3]), 3); Y = _mm512_insertf32x4(Y, _mm_loadu_ps(r[3] + 3), 3);
        Z = _mm512_insertf32x4(Z, _mm_loadu_ps(r[3] + 6), 3);
        const __m512 u = _mm512_permutexvar_ps(rep, _mm512_castps128_ps512(_mm_loadu_ps(bu + p)));
        const __m512 v = _mm512_permutexvar_ps(rep, _mm512_castps128_ps512(_mm_loadu_ps(bv + p)));
        const __m512 w = _mm512_sub_ps(_mm512_sub_ps(one, u), v);
        const __m512 s = _mm512_maskz_add_ps(hm, _mm512_add_ps(_mm512_mul_ps(X, w), _mm512_mul_ps(Y, u)),
                                             _mm512_mul_ps(Z, v));
        __m128 a = _mm_add_ps(_mm_setzero_ps(), _mm512_castps512_ps128(s));
        a = _mm_add_ps(a, _mm512_extractf32x4_ps(s, 1));
        a = _mm_add_ps(a, _mm512_extractf32x4_ps(s, 2));
        a = _mm_add_ps(a, _mm512_extractf32x4_ps(s, 3));
        a = _mm_mul_ps(a, inv);
        float o[4];
        _mm_storeu_ps(o, a);
        out[3 * i] = o[0]; out[3 * i + 1] = o[1]; out[3 * i + 2] = o[2];
    }
    return 0;
}
#endif
static int64_t pixels(const int64_t *face, const float *bu, const float *bv, const uint8_t *hit, int64_t M,
                      const float *T, int64_t S2, int64_t i0, int64_t i1, float *out, int64_t vec) {
#ifdef __AVX512F__
    if (vec && S2 == 4) return pix4_range(face, bu, bv, hit, M, T, i0, i1, out);
#endif
    return pix_range(face, bu, bv, hit, M, T, S2, i0, i1, out);
}
void zh38p_resolve(const int64_t *face, const float *bu, const float *bv, const uint8_t *hit, const int64_t *F,
                   int64_t M, const float *val, int64_t N, int64_t S2, int64_t n, int64_t nt, float *T, float *out,
                   int64_t *bad, int64_t vec) {
    int64_t b = 0;
    if (nt <= 1) {
        b = table_range(F, val, N, 0, M, T);
        if (!b) b = pixels(face, bu, bv, hit, M, T, S2, 0, n, out, vec);
    } else {
        #pragma omp parallel num_threads(nt) reduction(|:b)
        {
            #pragma omp for schedule(static)
            for (int64_t t = 0; t < nt; ++t) b |= table_range(F, val, N, M * t / nt, M * (t + 1) / nt, T);
            #pragma omp for schedule(static)
            for (int64_t t = 0; t < nt; ++t) b |= pixels(face, bu, bv, hit, M, T, S2, n * t / nt, n * (t + 1) / nt, out, vec);
        }
    }
    bad[0] = b;
}
"""
_VRESOLVE_SIGNATURES = {"zh38p_resolve": [_P, _P, _P, _P, _P, _I, _P, _I, _I, _I, _I, _P, _P, _P, _I]}
VECTOR_RESOLVE = True   # False: `resolve_table` (the tests switch it to compare)


def _vresolve_lib():
    """The library of `zh38p_resolve` or None (no AVX-512 host: `resolve_table`'s loop). Not cached (b541a75)."""
    if not _avx512_flags():
        return None
    return load("zh38p_resolve", _VRESOLVE_SOURCE, _VRESOLVE_SIGNATURES,   # (zh43o: the module's `load`)
                extra_flags=("-fopenmp", "-ffp-contract=off", *_avx512_flags()))


def resolve_vector(values: Tensor, F: Tensor, face: Tensor, bary: Tensor, hit: Tensor, height: int, width: int,
                   spp_side: int) -> Tensor | None:
    """`resolve_table` (the same arguments, the same bits, the same ValueError) by `zh38p_resolve` with 2×2
    samples a pixel (above), or None where it does not run (``VECTOR_RESOLVE`` off, no AVX-512 host, another
    sample count, and where `resolve_table` does not): then the caller's `resolve_table`."""
    if not VECTOR_RESOLVE or spp_side != 2:
        return None
    lib = _vresolve_lib() if terms_switched_on() else None
    S2 = 4
    n = height * width
    args = None if lib is None else _resolve_inputs(values, F, face, bary, hit, n * S2)
    if args is None:
        return None
    values, bu, bv = args
    M = int(F.shape[0])
    T = torch.empty(M * 9 + 3, dtype=torch.float32)   # (+3: the last row's 4-float z load)
    out = torch.empty(n, 3, dtype=torch.float32)
    bad = ctypes.c_int64(0)   # (zh43o: a `ctypes` scalar, not a tensor: two torch calls less)
    nt = max(1, min(torch.get_num_threads(), n // MIN_RESOLVE_PIXELS_PER_THREAD))
    lib.zh38p_resolve(face.data_ptr(), bu.data_ptr(), bv.data_ptr(), hit.data_ptr(), F.data_ptr(), M,
                      values.data_ptr(), int(values.shape[0]), S2, n, nt, T.data_ptr(), out.data_ptr(),
                      ctypes.addressof(bad), 1)
    if bad.value:
        raise ValueError(f"G-buffer faces or corner rows out of range of {M} faces and "
                         f"{int(values.shape[0])} vertex rows (a G-buffer of another mesh?)")
    return out.view(height, width, 3)


# A P frame's skinning (`ZHShadow._posed_geometry`, `skin`) with 16 vertices a vector (`VECTOR_SKIN`): the
# weights laid out joint-major once per scene (`skin_vector_setup`: (J, n_skinned), and the rest positions and
# normals as (3, n) rows), so a joint's weights of 16 vertices are one load; a joint none of them weighs is
# skipped, a lane whose weight is 0 keeps its sum (a masked add: `blend_range` skips it) — per lane the same
# products, sums and order as `blend_range` (no multiply-adds fused), the same square root and division: the
# same bits as `zh35o_skin` (the tests' oracle). The scalar loop's ~12 multiply-adds a weight, its branch per
# joint and its scalar cofactor, square root and division were ~24 ns a vertex (bench creature, 9,694
# skinned vertices, ~0.23 ms at 1 thread).
_VSKIN_SOURCE = _SKIN_SOURCE.replace("void zh35o_skin(", "static void unused_zh35o_skin(") + r"""
#ifdef __AVX512F__
#include <immintrin.h>
typedef float vf __attribute__((vector_size(64)));
typedef int32_t vi __attribute__((vector_size(64)));
/* vertices [i0, i1) of a range starting at a: wT (J rows of stride ldw, the range's column 0 at wT), VT, NT
   (3, ldv) the rest rows; tail (< 16) by blend_range (w the range's row-major weights as zh35o_skin's). */
static void blend_vec(int64_t J, const float *T12, const float *V, const float *N, const float *w,
                      const float *VT, const float *NT, int64_t ldv, const float *wT, int64_t ldw, int64_t a,
                      int64_t i0, int64_t i1, float *Vo, float *No) {
    int64_t i = i0;
    for (; i + 16 <= i1; i += 16) {
        vf acc[12];
        for (int k = 0; k < 12; ++k) acc[k] = (vf){0};
        for (int64_t j = 0; j < J; ++j) {
            vf wj;
            memcpy(&wj, wT + j * ldw + (i - a), sizeof wj);
            const vi m = wj != 0.0f;
            if (!_mm512_test_epi32_mask((__m512i)m, (__m512i)m)) continue;
            for (int k = 0; k < 12; ++k) {
                const vf s = acc[k] + wj * T12[12 * j + k];
                acc[k] = (vf)(((vi)s & m) | ((vi)acc[k] & ~m));
            }
        }
        vf x, y, z, nx, ny, nz;
        memcpy(&x, VT + i, sizeof x); memcpy(&y, VT + ldv + i, sizeof y); memcpy(&z, VT + 2 * ldv + i, sizeof z);
        memcpy(&nx, NT + i, sizeof nx); memcpy(&ny, NT + ldv + i, sizeof ny); memcpy(&nz, NT + 2 * ldv + i, sizeof nz);
        vf vo[3], n[3];
        for (int r = 0; r < 3; ++r) vo[r] = acc[4 * r] * x + acc[4 * r + 1] * y + acc[4 * r + 2] * z + acc[4 * r + 3];
        const vf *c0[3] = {&acc[0], &acc[4], &acc[8]}, *c1[3] = {&acc[1], &acc[5], &acc[9]},
                 *c2[3] = {&acc[2], &acc[6], &acc[10]};
        const vf k0[3] = {*c1[1] * *c2[2] - *c1[2] * *c2[1], *c1[2] * *c2[0] - *c1[0] * *c2[2], *c1[0] * *c2[1] - *c1[1] * *c2[0]};
        const vf k1[3] = {*c2[1] * *c0[2] - *c2[2] * *c0[1], *c2[2] * *c0[0] - *c2[0] * *c0[2], *c2[0] * *c0[1] - *c2[1] * *c0[0]};
        const vf k2[3] = {*c0[1] * *c1[2] - *c0[2] * *c1[1], *c0[2] * *c1[0] - *c0[0] * *c1[2], *c0[0] * *c1[1] - *c0[1] * *c1[0]};
        for (int r = 0; r < 3; ++r) n[r] = k0[r] * nx + k1[r] * ny + k2[r] * nz;
        const vf l = (vf)_mm512_sqrt_ps((__m512)(n[0] * n[0] + n[1] * n[1] + n[2] * n[2]));
        const vf inv = 1.0f / (vf)_mm512_max_ps((__m512)l, _mm512_set1_ps(1e-12f));   /* (l > 1e-12 ? l : 1e-12) */
        for (int r = 0; r < 3; ++r) n[r] = n[r] * inv;
        for (int q = 0; q < 16; ++q)
            for (int r = 0; r < 3; ++r) { Vo[3 * (i + q) + r] = vo[r][q]; No[3 * (i + q) + r] = n[r][q]; }
    }
    blend_range(J, T12, V, N, w, i, i1, Vo, No);
}
#endif
/* zh35o_skin's arguments, then wT (J, ldw) the weights joint-major (range s's columns from wofs[s]), VT, NT
   (3, n) the rest rows. */
void zh38p_skin(int64_t J, const int64_t *parent, const float *jp, const float *axis, const float *pose, int64_t n,
                const float *V, const float *N, int64_t S, const int64_t *ranges, const int64_t *wofs, const float *w,
                float *Vo, float *No, float *T12, int64_t nt, const float *wT, int64_t ldw, const float *VT,
                const float *NT) {
    fk(J, parent, jp, axis, pose, T12);
    memcpy(Vo, V, sizeof(float) * 3 * n);
    memcpy(No, N, sizeof(float) * 3 * n);
    for (int64_t s = 0; s < S; ++s) {
        const int64_t a = ranges[2 * s], b = ranges[2 * s + 1];
        const float *ws = w + wofs[s] * J - a * J;
#ifdef __AVX512F__
        const float *wTs = wT + wofs[s];
        if (nt <= 1 || b - a < 2048) {
            blend_vec(J, T12, V, N, ws, VT, NT, n, wTs, ldw, a, a, b, Vo, No);
        } else {
            #pragma omp parallel for num_threads(nt) schedule(static, 1)
            for (int64_t t = 0; t < nt; ++t)
                blend_vec(J, T12, V, N, ws, VT, NT, n, wTs, ldw, a, a + (b - a) * t / nt, a + (b - a) * (t + 1) / nt,
                          Vo, No);
        }
#else
        (void)wT; (void)ldw; (void)VT; (void)NT;
        blend_range(J, T12, V, N, ws, a, b, Vo, No);
#endif
    }
}
"""
_VSKIN_SIGNATURES = {"zh38p_skin": [*_SKIN_SIGNATURES["zh35o_skin"], _P, _I, _P, _P]}
VECTOR_SKIN = True   # False: `skin` (the tests switch it to compare)


def _vskin_lib():
    """The library of `zh38p_skin` or None (no AVX-512 host: `skin`). Not cached (b541a75)."""
    if not _avx512_flags():
        return None
    return load("zh38p_skin", _VSKIN_SOURCE, _VSKIN_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", *native.isa_flags(), *_avx512_flags()))


def skin_vector_setup(setup: tuple | None) -> tuple | None:
    """`skin_vector`'s layouts of a `skin_setup` (kept beside it by the caller): (wT (J, n_skinned) the weights
    joint-major, VT, NT (3, n) the rest rows), or None (no setup)."""
    if setup is None:
        return None
    J, _, _, _, V, N, _, _, w = setup
    return (w.T.contiguous(), V.T.contiguous(), N.T.contiguous())


def skin_vector(setup: tuple | None, vsetup: tuple | None, pose: Tensor) -> tuple[Tensor, Tensor] | None:
    """`skin` (the same bits) by `zh38p_skin` (16 vertices a vector, above), or None where it does not run
    (``VECTOR_SKIN`` off, no AVX-512 host, and where `skin` does not): then the caller's `skin`."""
    if not VECTOR_SKIN or vsetup is None:
        return None
    lib = _vskin_lib() if terms_switched_on() else None
    if lib is None or setup is None:
        return None
    J, par, jp, ax, V, N, rng, wofs, w = setup
    wT, VT, NT = vsetup
    if pose.dtype != torch.float32 or pose.device.type != "cpu" or tuple(pose.shape) != (J,):
        return None
    pose = pose.contiguous()
    n = int(V.shape[0])
    Vo, No = torch.empty(n, 3, dtype=torch.float32), torch.empty(n, 3, dtype=torch.float32)
    T12 = torch.empty(J, 12, dtype=torch.float32)
    nt = max(1, min(torch.get_num_threads(), n // 4096))
    lib.zh38p_skin(J, par.data_ptr(), jp.data_ptr(), ax.data_ptr(), pose.data_ptr(), n, V.data_ptr(), N.data_ptr(),
                   int(rng.shape[0]), rng.data_ptr(), wofs.data_ptr(), w.data_ptr(), Vo.data_ptr(), No.data_ptr(),
                   T12.data_ptr(), nt, wT.data_ptr(), int(wT.shape[1]), VT.data_ptr(), NT.data_ptr())
    return Vo, No


class SkinBound:
    """`skin_vector` for one setup, its constant arguments resolved once (`skin_bind`; zh41p): per pose only the
    pose's checks, the two outputs and one C call (the same bits); the joints' scratch T12 kept. The look-ups
    and checks around the call were ~0.15 ms of a bench P frame's serial Python with the caches cold."""

    __slots__ = ("setup", "vsetup", "fn", "J", "n", "head", "tail", "T12")

    def __call__(self, pose: Tensor) -> tuple[Tensor, Tensor] | None:
        """`skin_vector`(setup, vsetup, pose) or None; the switches are the caller's (`switches_on`)."""
        if not VECTOR_SKIN or pose.dtype != torch.float32 or pose.device.type != "cpu" or pose.shape != (self.J,):
            return None
        pose = pose.contiguous()
        n = self.n
        Vo, No = torch.empty(n, 3, dtype=torch.float32), torch.empty(n, 3, dtype=torch.float32)
        nt = max(1, min(torch.get_num_threads(), n // 4096))
        self.fn(*self.head, pose.data_ptr(), n, *self.tail[0], Vo.data_ptr(), No.data_ptr(), self.T12.data_ptr(), nt,
                *self.tail[1])
        return Vo, No


def skin_bind(setup: tuple | None, vsetup: tuple | None) -> SkinBound | None:
    """A `SkinBound` of `skin_vector`(setup, vsetup, ·), or None where `skin_vector` would not run."""
    if not VECTOR_SKIN or vsetup is None or setup is None:
        return None
    lib = _vskin_lib() if terms_switched_on() else None
    if lib is None:
        return None
    J, par, jp, ax, V, N, rng, wofs, w = setup
    wT, VT, NT = vsetup
    b = SkinBound()
    b.setup, b.vsetup, b.fn, b.J, b.n = setup, vsetup, lib.zh38p_skin, int(J), int(V.shape[0])
    b.head = (J, par.data_ptr(), jp.data_ptr(), ax.data_ptr())
    b.tail = ((V.data_ptr(), N.data_ptr(), int(rng.shape[0]), rng.data_ptr(), wofs.data_ptr(), w.data_ptr()),
              (wT.data_ptr(), int(wT.shape[1]), VT.data_ptr(), NT.data_ptr()))
    b.T12 = torch.empty(J, 12, dtype=torch.float32)
    return b


# --- the resolve matrix of a lighting-only vertex-shaded frame, built by one C pass (zh39o) -----------------
#
# `gouraud.resolve_matrix` (the oracle) makes the (H·W, N) interpolation + box-filter operator as a COO tensor
# of the P·3 (pixel, vertex, weight) entries, coalesced (a sort of all of them) and converted to CSR;
# `method._int32_csr` then narrows its indices. The first lighting-only frame of a camera and pose (the first
# timed L / E frame of the perf suite) paid that: 60–77 ms at 2 threads on the bench creature (262,144
# samples), against a ~1.5 ms frame. The entries of one pixel are its S² samples' 3 corners, so the sort is
# per pixel: here each pixel's ≤ 3·S² entries in their COO order (sample ascending, corner 0..2) stably
# sorted by vertex id (an insertion sort) and duplicates summed in that order, from the first — what
# coalesce's stable sort and sequential accumulation give —, the weights as there: ((1 − u) − v, u, v)
# each times (float) 1/S² (no multiply-add fused: `-ffp-contract=off`). The same crow / col / values bits
# (tested against the oracle).
_RMATRIX_SOURCE = r"""
#include <stdint.h>

/* pixels [0, n): crow (n + 1) int32, col / val (≤ n·3·S2) the CSR entries; face (n·S2) int64, hit uint8,
   bu / bv the barycentrics (contiguous), F (M, 3) int64; inv = (float)(1/S2). With col4 non-null also
   `csr_pack`'s form: col4 / val4 (n, 4) each row's first four entries (padded with column 0, weight 0),
   trow the rows of more than four, tcrow (T + 1) their tails' offsets, tcol / tval the tails.
   cnt[0] counts hit samples whose face is outside [0, M) or whose corner is outside [0, N) (then the
   caller falls back), cnt[1] = T. A pixel whose S2 samples all hit one face of three distinct in-range
   corners takes the short path: per corner its S2 weights summed in sample order, the corners sorted —
   what the general path's stable sort and in-order sums give for it. */
void zh39o_rmatrix(int64_t n, int64_t S2, const int64_t *face, const uint8_t *hit, const float *bu,
                   const float *bv, const int64_t *F, int64_t M, int64_t N, float inv, int32_t *crow,
                   int32_t *col, float *val, int32_t *col4, float *val4, int32_t *trow, int32_t *tcrow,
                   int32_t *tcol, float *tval, int64_t *cnt) {
    int64_t nb = 0, e = 0, T = 0;
    int64_t ec[48];
    float ew[48];
    crow[0] = 0;
    if (col4) tcrow[0] = 0;
    for (int64_t p = 0; p < n; ++p) {
        const int64_t q0 = p * S2, f0 = face[q0];
        int one = (uint64_t)f0 < (uint64_t)M;
        for (int64_t s = 0; s < S2 && one; ++s) one = hit[q0 + s] && face[q0 + s] == f0;
        int64_t a = 0, b = 0, c = 0;
        if (one) {
            a = F[3 * f0]; b = F[3 * f0 + 1]; c = F[3 * f0 + 2];
            one = (uint64_t)a < (uint64_t)N && (uint64_t)b < (uint64_t)N && (uint64_t)c < (uint64_t)N
                  && a != b && a != c && b != c;
        }
        const int64_t e0 = e;
        if (one) {
            float s0 = ((1.0f - bu[q0]) - bv[q0]) * inv, s1 = bu[q0] * inv, s2 = bv[q0] * inv;
            for (int64_t s = 1; s < S2; ++s) {
                const float u = bu[q0 + s], v = bv[q0 + s];
                s0 += ((1.0f - u) - v) * inv; s1 += u * inv; s2 += v * inv;
            }
            /* sorted by vertex id (distinct) */
            int64_t i0 = a, i1 = b, i2 = c;
            float w0 = s0, w1 = s1, w2 = s2, tw;
            int64_t ti;
            if (i0 > i1) { ti = i0; i0 = i1; i1 = ti; tw = w0; w0 = w1; w1 = tw; }
            if (i1 > i2) { ti = i1; i1 = i2; i2 = ti; tw = w1; w1 = w2; w2 = tw; }
            if (i0 > i1) { ti = i0; i0 = i1; i1 = ti; tw = w0; w0 = w1; w1 = tw; }
            col[e] = (int32_t)i0; val[e] = w0;
            col[e + 1] = (int32_t)i1; val[e + 1] = w1;
            col[e + 2] = (int32_t)i2; val[e + 2] = w2;
            e += 3;
        } else {
            /* the distinct vertex ids met so far, ascending, each with its weights' running sum (in the
               entries' order: what the stable sort then the in-order sums give) */
            int64_t k = 0;
            for (int64_t s = 0; s < S2; ++s) {
                const int64_t q = q0 + s;
                if (!hit[q]) continue;
                const int64_t f = face[q];
                if ((uint64_t)f >= (uint64_t)M) { ++nb; continue; }
                const float u = bu[q], v = bv[q];
                const float w[3] = {((1.0f - u) - v) * inv, u * inv, v * inv};
                for (int cc = 0; cc < 3; ++cc) {
                    const int64_t vid = F[3 * f + cc];
                    if ((uint64_t)vid >= (uint64_t)N) { ++nb; continue; }
                    int64_t j = k;
                    while (j > 0 && ec[j - 1] > vid) --j;
                    if (j > 0 && ec[j - 1] == vid) { ew[j - 1] += w[cc]; continue; }
                    for (int64_t i = k; i > j; --i) { ec[i] = ec[i - 1]; ew[i] = ew[i - 1]; }
                    ec[j] = vid; ew[j] = w[cc];
                    ++k;
                }
            }
            for (int64_t i = 0; i < k; ++i) {
                col[e] = (int32_t)ec[i];
                val[e] = ew[i];
                ++e;
            }
        }
        crow[p + 1] = (int32_t)e;
        if (col4) {
            const int64_t k = e - e0;
            for (int64_t i = 0; i < 4; ++i) {
                col4[4 * p + i] = i < k ? col[e0 + i] : 0;
                val4[4 * p + i] = i < k ? val[e0 + i] : 0.f;
            }
            if (k > 4) {
                const int32_t o = tcrow[T];
                for (int64_t i = 4; i < k; ++i) { tcol[o + i - 4] = col[e0 + i]; tval[o + i - 4] = val[e0 + i]; }
                trow[T] = (int32_t)p;
                tcrow[T + 1] = o + (int32_t)(k - 4);
                ++T;
            }
        }
    }
    cnt[0] = nb;
    cnt[1] = T;
}
"""
_RMATRIX_SIGNATURES = {"zh39o_rmatrix": [_I, _I, _P, _P, _P, _P, _P, _I, _I, ctypes.c_float, _P, _P, _P, _P, _P, _P,
                                         _P, _P, _P, _P]}
NATIVE_RESOLVE_MATRIX = True   # `resolve_matrix` by the C pass (off: `gouraud.resolve_matrix`, the oracle)


def _rmatrix_lib():
    return native.load("zh39o_rmatrix", _RMATRIX_SOURCE, _RMATRIX_SIGNATURES, extra_flags=("-ffp-contract=off",))


def resolve_matrix(F: Tensor, face: Tensor, bary: Tensor, hit: Tensor, height: int, width: int, spp_side: int,
                   num_values: int, packed: bool = False):
    """`method._int32_csr(gouraud.resolve_matrix(F.T, face, bary, hit, height, width, spp_side, num_values))`
    — the (H·W, num_values) CSR resolve operator with int32 indices — by one C pass over the pixels (above;
    the same bits), or None where it does not run (``NATIVE_RESOLVE_MATRIX`` off, no compiler,
    ``PRTBENCH_ZH_NATIVE=0``, not CPU tensors of the loop's types, more than 16 samples a pixel, counts past
    int32, a face or corner out of range): then the caller's torch path (which raises where it must).
    ``packed``: (that matrix, its `csr_pack` made in the same pass — the same arrays) or None."""
    if not NATIVE_RESOLVE_MATRIX or not 1 <= spp_side <= 4:
        return None
    lib = _rmatrix_lib() if terms_switched_on() else None
    S2 = spp_side * spp_side
    n = height * width
    N = int(num_values)
    args = None if lib is None else _resolve_inputs(torch.empty(0, 3), F, face, bary, hit, n * S2)
    if args is None or n * S2 * 3 >= 2 ** 31 - 1 or N >= 2 ** 31 - 1 or n >= 2 ** 31 - 1 or (packed and N == 0):
        return None
    _, bu, bv = args
    crow = torch.empty(n + 1, dtype=torch.int32)
    col = torch.empty(n * S2 * 3, dtype=torch.int32)
    val = torch.empty(n * S2 * 3, dtype=torch.float32)
    cnt = torch.zeros(2, dtype=torch.int64)
    if packed:
        col4 = torch.empty(n, 4, dtype=torch.int32)
        val4 = torch.empty(n, 4, dtype=torch.float32)
        nt_max = n * max(S2 * 3 - 4, 0)
        trow, tcrow = torch.empty(n, dtype=torch.int32), torch.empty(n + 1, dtype=torch.int32)
        tcol, tval = torch.empty(nt_max, dtype=torch.int32), torch.empty(nt_max, dtype=torch.float32)
        ptrs = [t.data_ptr() for t in (col4, val4, trow, tcrow, tcol, tval)]
    else:
        ptrs = [None] * 6
    lib.zh39o_rmatrix(n, S2, face.data_ptr(), hit.data_ptr(), bu.data_ptr(), bv.data_ptr(), F.data_ptr(),
                      int(F.shape[0]), N, float(torch.tensor(1.0 / S2, dtype=torch.float32)), crow.data_ptr(),
                      col.data_ptr(), val.data_ptr(), *ptrs, cnt.data_ptr())
    if int(cnt[0]):
        return None
    nnz = int(crow[-1])
    import warnings

    with warnings.catch_warnings():   # "sparse CSR support is in beta" (as `method._int32_csr`)
        warnings.simplefilter("ignore", UserWarning)
        # (the entries' leading views, no copies: the pages past them were never touched, so never mapped)
        S = torch.sparse_csr_tensor(crow, col[:nnz], val[:nnz], (n, N))
    if not packed:
        return S
    T = int(cnt[1])
    nt_ = int(tcrow[T])
    return S, (n, N, col4, val4, trow[:T], tcrow[:T + 1], tcol[:nt_], tval[:nt_])


# --- a lighting-only vertex-shaded frame's radiance and resolve by one C call (zh39o) ---------------------
#
# A lighting-only order-8 frame under a kept resolve matrix and compact transfer (`ZHShadow._render_vertex`)
# was ~15 torch ops — per region (l ⊙ kd / π)ᵀ w and (l ⊙ ks)ᵀ t_s by two MKL products, their sum copied
# transposed, then a zero row appended and `csr_product` — each op after the suite's idle costing 2–10× its
# warm time. Here one call: per compact column j of region r, x[j] = Σ_i (l ⊙ kd_r / π)[i] w[i, j]
# (+ Σ_i (l ⊙ ks_r)[i] t_s[i, j − b0]), i ascending (not MKL's order: float32 round-off from the products'),
# clamped if asked, x[Nc] = 0; then `zh_ell_rows`' product of the compact ELL matrix (`csr_compact`) — the
# same sums in the same order as `csr_product` on those x.
_RELIGHTV_SOURCE = r"""
#include <stdint.h>

/* columns [j0, j0 + jn) (jn <= 64) of region r's range [b0, b1) of x: Σ_i Ld[i] w[i, j] (+ Σ_i Ls[i] t[i, j − b0])
   i ascending, clamped if asked (the same expressions whatever thread runs the block) */
static void relight_block(int64_t n2, int64_t Nc, const float *Ld, const float *Ls, const float *wf, const float *ts,
                          int64_t b0, int64_t m, int64_t j0, int64_t jn, int64_t clamp, float *x) {
    float a0[64], a1[64], a2[64];
    for (int64_t j = 0; j < jn; ++j) { a0[j] = 0.f; a1[j] = 0.f; a2[j] = 0.f; }
    for (int64_t i = 0; i < n2; ++i) {
        const float *w = wf + i * Nc + b0 + j0;
        const float l0 = Ld[3 * i], l1 = Ld[3 * i + 1], l2 = Ld[3 * i + 2];
        for (int64_t j = 0; j < jn; ++j) { a0[j] += l0 * w[j]; a1[j] += l1 * w[j]; a2[j] += l2 * w[j]; }
    }
    if (ts) {
        float s0[64], s1[64], s2[64];
        for (int64_t j = 0; j < jn; ++j) { s0[j] = 0.f; s1[j] = 0.f; s2[j] = 0.f; }
        for (int64_t i = 0; i < n2; ++i) {
            const float *t = ts + i * m + j0;
            const float l0 = Ls[3 * i], l1 = Ls[3 * i + 1], l2 = Ls[3 * i + 2];
            for (int64_t j = 0; j < jn; ++j) { s0[j] += l0 * t[j]; s1[j] += l1 * t[j]; s2[j] += l2 * t[j]; }
        }
        for (int64_t j = 0; j < jn; ++j) { a0[j] += s0[j]; a1[j] += s1[j]; a2[j] += s2[j]; }
    }
    float *o = x + 3 * (b0 + j0);
    for (int64_t j = 0; j < jn; ++j) {
        float v0 = a0[j], v1 = a1[j], v2 = a2[j];
        if (clamp) { v0 = v0 < 0.f ? 0.f : v0; v1 = v1 < 0.f ? 0.f : v1; v2 = v2 < 0.f ? 0.f : v2; }
        o[3 * j] = v0; o[3 * j + 1] = v1; o[3 * j + 2] = v2;
    }
}

/* The relight passes' shared head: per region r the scaled lighting Ld = light (kd_r / π), Ls = light ks_r
   into L (nreg · 2 · n2 · 3); returns the number of 64-column blocks over the regions' spans. */
static int64_t relight_light(int64_t n2, const float *light, int64_t nreg, const float *kd, const float *ks,
                             const int64_t *spans, float inv_pi, float *L) {
    int64_t nb = 0;
    for (int64_t r = 0; r < nreg; ++r) {
        float *Ld = L + r * 6 * n2, *Ls = Ld + 3 * n2;
        for (int64_t i = 0; i < n2; ++i)
            for (int c = 0; c < 3; ++c) {
                Ld[3 * i + c] = light[3 * i + c] * (kd[3 * r + c] * inv_pi);
                Ls[3 * i + c] = light[3 * i + c] * ks[3 * r + c];
            }
        const int64_t m = spans[2 * r + 1] - spans[2 * r];
        nb += m > 0 ? (m + 63) / 64 : 0;
    }
    return nb;
}

/* Block k (in region order) is the kk-th of region r (returned): its columns j0 .. j0 + jn of the region's m. */
static int64_t relight_block_of(int64_t k, int64_t nreg, const int64_t *spans, int64_t *j0, int64_t *jn,
                                int64_t *m) {
    int64_t r = 0, kk = k;
    *m = 0;
    for (; r < nreg; ++r) {
        *m = spans[2 * r + 1] - spans[2 * r];
        const int64_t c = *m > 0 ? (*m + 63) / 64 : 0;
        if (kk < c) break;
        kk -= c;
    }
    *j0 = kk * 64;
    *jn = *m - *j0 < 64 ? *m - *j0 : 64;
    return r;
}

/* light (n2, 3), kd / ks (nreg, 3), spans (nreg, 2) compact column ranges (tiling [0, Nc)), wf (n2, Nc),
   tsp (nreg) addresses of t_s (n2, b1 − b0) or 0, inv_pi = (float)(1/π); x (Nc + 1, 3) written (row Nc
   zero); L (nreg · 2 · n2 · 3) scratch; then out (R, 3) = the compact ELL matrix (col4, val4, the tails)
   times x, as `zh_ell_rows` (its loops and expressions). One OpenMP region of nt threads: the column
   blocks of 64 split over them, a barrier, then the rows. */
void zh39o_relight(int64_t n2, int64_t Nc, const float *light, int64_t nreg, const float *kd, const float *ks,
                   const int64_t *spans, const float *wf, const int64_t *tsp, float inv_pi, int64_t clamp,
                   float *x, float *L, int64_t R, const int32_t *col4, const float *val4, float *out, int64_t nt,
                   int64_t T, const int32_t *trow, const int32_t *tcrow, const int32_t *tcol, const float *tval) {
    const int64_t nb = relight_light(n2, light, nreg, kd, ks, spans, inv_pi, L);
    x[3 * Nc] = 0.f; x[3 * Nc + 1] = 0.f; x[3 * Nc + 2] = 0.f;
#pragma omp parallel num_threads(nt) if(nt > 1)
    {
#pragma omp for schedule(static)
        for (int64_t k = 0; k < nb; ++k) {
            int64_t j0, jn, m;
            const int64_t r = relight_block_of(k, nreg, spans, &j0, &jn, &m);
            const float *Ld = L + r * 6 * n2;
            relight_block(n2, Nc, Ld, Ld + 3 * n2, wf, (const float *)(intptr_t)tsp[r], spans[2 * r], m, j0, jn,
                          clamp, x);
        }
        /* (the implicit barrier: every x row written) */
""" + _PACKED_PRODUCT_C + r"""    }
}
"""
_RELIGHTV_SIGNATURES = {"zh39o_relight": [_I, _I, _P, _I, _P, _P, _P, _P, _P, ctypes.c_float, _I, _P, _P,
                                          _I, _P, _P, _P, _I, _I, _P, _P, _P, _P]}
FUSED_RELIGHT_VERTEX = True   # `relight_resolve` (off: None — the caller's `_radiance_ranges` + `csr_product`)


def _relightv_lib():
    return native.load("zh39o_relight", _RELIGHTV_SOURCE, _RELIGHTV_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", *_avx512_flags()))


def relight_resolve(light: Tensor, kd: Tensor, ks: Tensor, spans: list, wf: Tensor, tsc: dict, clamp: bool,
                    packed: tuple) -> Tensor | None:
    """The (R, 3) resolved image of a lighting-only vertex-shaded frame: the compact radiance of the columns
    of wf (n², Nc) — per region r (kd, ks (nreg, 3) its albedos, ``spans`` its compact columns, tiling
    [0, Nc)) (l ⊙ kd_r / π)ᵀ w (+ (l ⊙ ks_r)ᵀ t_s for tsc[r] = (its span, t_s (n², b1 − b0))), clamped at 0
    if ``clamp`` — then `csr_product`(``packed``, [x; 0]) (``packed``: `csr_compact`'s, Nc + 1 columns), by
    one C call (above): float32 round-off from `ZHShadow._radiance_ranges` + `csr_product`, its oracle. None
    where it does not run (``FUSED_RELIGHT_VERTEX`` off, no compiler, ``PRTBENCH_ZH_NATIVE=0``, not float32
    CPU arrays of these shapes, a part not its region's span). = `relight_run`(`relight_setup`(...), ...)."""
    st = relight_setup(spans, wf, tsc, packed)
    return None if st is None else relight_run(st, light, kd, ks, clamp)


def relight_setup(spans: list, wf: Tensor, tsc: dict, packed: tuple) -> tuple | None:
    """The lighting-free half of `relight_resolve`'s checks and arguments (zh40l: made once per kept compact
    transfer and resolve matrix, `ZHShadow._steady_relight`, then `relight_run` per frame): (library, n2, Nc,
    nreg, spans (nreg, 2) int64, t_s addresses (nreg,) int64, the t_s kept alive, packed, x and L scratch), or
    None where `relight_resolve` does not run."""
    if not FUSED_RELIGHT_VERTEX:
        return None
    lib = _relightv_lib() if terms_switched_on() else None
    if lib is None:
        return None
    R, Ncp, col4, val4, trow, tcrow, tcol, tval = packed
    n2, Nc = int(wf.shape[0]), int(wf.shape[1])
    nreg = len(spans)
    if Ncp != Nc + 1 or wf.device.type != "cpu" or wf.dtype != torch.float32 or not wf.is_contiguous():
        return None
    sp = torch.tensor(spans, dtype=torch.int64).view(nreg, 2) if nreg else torch.zeros(0, 2, dtype=torch.int64)
    if nreg and (int(sp[0, 0]) != 0 or int(sp[-1, 1]) != Nc or bool((sp[1:, 0] != sp[:-1, 1]).any())):
        return None
    tsp = torch.zeros(max(nreg, 1), dtype=torch.int64)
    keep = []
    for r, (span, t) in tsc.items():
        if t is None:
            continue
        b0, b1 = spans[r]
        if tuple(span) != (b0, b1) or t.dtype != torch.float32 or tuple(t.shape) != (n2, b1 - b0) \
                or t.device.type != "cpu":
            return None
        t = t.contiguous()
        keep.append(t)
        tsp[r] = t.data_ptr()
    x = torch.empty(Nc + 1, 3, dtype=torch.float32)               # (scratch: every row written by the call)
    L = torch.empty(max(nreg, 1) * 6 * n2, dtype=torch.float32)
    libb = _relightb_lib() if BLOCKED_RELIGHT_VERTEX else None
    if libb is not None:   # (zh41l: the tiles in place of wf and t_s)
        wb, tb = relight_blocks(spans, wf, tsc)
        keep = [*keep, wb] + ([] if tb is None else [tb])
        return libb, n2, Nc, nreg, sp, tsp, keep, packed, (wb, tb), x, L
    return lib, n2, Nc, nreg, sp, tsp, keep, packed, wf, x, L


# zh41l: `zh39o_relight` reading a blocked copy of its transfer (``BLOCKED_RELIGHT_VERTEX``): each 64-column block of
# w (and t_s) as one contiguous (n², 64) tile, padded with zero columns (`relight_blocks`, made once by
# `relight_setup`), so a block streams 16 KB in order instead of n² rows of 256 bytes each Nc floats apart, and
# its sums (64 columns × 3 channels, fixed width) stay in registers; every column the same products and sums in
# the same order as `relight_block` (the padding's columns are computed and not stored): the same bits.
_RELIGHTB_SOURCE = _RELIGHTV_SOURCE + r"""
/* `relight_block` of one (n2, 64) tile wb (and tb) of a block with jn <= 64 real columns */
static void relight_tile(int64_t n2, const float *Ld, const float *Ls, const float *wb, const float *tb,
                         int64_t jn, int64_t clamp, float *o) {
    float a0[64], a1[64], a2[64];
    for (int64_t j = 0; j < 64; ++j) { a0[j] = 0.f; a1[j] = 0.f; a2[j] = 0.f; }
    for (int64_t i = 0; i < n2; ++i) {
        const float *w = wb + i * 64;
        const float l0 = Ld[3 * i], l1 = Ld[3 * i + 1], l2 = Ld[3 * i + 2];
        for (int64_t j = 0; j < 64; ++j) { a0[j] += l0 * w[j]; a1[j] += l1 * w[j]; a2[j] += l2 * w[j]; }
    }
    if (tb) {
        float s0[64], s1[64], s2[64];
        for (int64_t j = 0; j < 64; ++j) { s0[j] = 0.f; s1[j] = 0.f; s2[j] = 0.f; }
        for (int64_t i = 0; i < n2; ++i) {
            const float *t = tb + i * 64;
            const float l0 = Ls[3 * i], l1 = Ls[3 * i + 1], l2 = Ls[3 * i + 2];
            for (int64_t j = 0; j < 64; ++j) { s0[j] += l0 * t[j]; s1[j] += l1 * t[j]; s2[j] += l2 * t[j]; }
        }
        for (int64_t j = 0; j < 64; ++j) { a0[j] += s0[j]; a1[j] += s1[j]; a2[j] += s2[j]; }
    }
    for (int64_t j = 0; j < jn; ++j) {
        float v0 = a0[j], v1 = a1[j], v2 = a2[j];
        if (clamp) { v0 = v0 < 0.f ? 0.f : v0; v1 = v1 < 0.f ? 0.f : v1; v2 = v2 < 0.f ? 0.f : v2; }
        o[3 * j] = v0; o[3 * j + 1] = v1; o[3 * j + 2] = v2;
    }
}

/* `zh39o_relight` with the transfer's blocks read from their tiles: block k (in region order) of region r is
   wb + k n2 64 (and tb + k n2 64 where region r has t_s, tsp[r] != 0); the same values written */
void zh41l_relight(int64_t n2, int64_t Nc, const float *light, int64_t nreg, const float *kd, const float *ks,
                   const int64_t *spans, const float *wb, const float *tb, const int64_t *tsp, float inv_pi,
                   int64_t clamp, float *x, float *L, int64_t R, const int32_t *col4, const float *val4, float *out,
                   int64_t nt, int64_t T, const int32_t *trow, const int32_t *tcrow, const int32_t *tcol,
                   const float *tval) {
    const int64_t nb = relight_light(n2, light, nreg, kd, ks, spans, inv_pi, L);
    x[3 * Nc] = 0.f; x[3 * Nc + 1] = 0.f; x[3 * Nc + 2] = 0.f;
#pragma omp parallel num_threads(nt) if(nt > 1)
    {
#pragma omp for schedule(static)
        for (int64_t k = 0; k < nb; ++k) {
            int64_t j0, jn, m;
            const int64_t r = relight_block_of(k, nreg, spans, &j0, &jn, &m);
            const float *Ld = L + r * 6 * n2;
            relight_tile(n2, Ld, Ld + 3 * n2, wb + k * n2 * 64, tsp[r] ? tb + k * n2 * 64 : 0, jn, clamp,
                         x + 3 * (spans[2 * r] + j0));
        }
        /* (the implicit barrier: every x row written) */
""" + _PACKED_PRODUCT_C + r"""    }
}
"""
_RELIGHTB_SIGNATURES = {"zh41l_relight": [_I, _I, _P, _I, _P, _P, _P, _P, _P, _P, ctypes.c_float, _I, _P, _P,
                                          _I, _P, _P, _P, _I, _I, _P, _P, _P, _P]}
# `relight_setup` keeps the blocked tiles and `relight_run` calls `zh41l_relight`; False: `zh39o_relight` over
# wf and t_s (the tests' oracle)
BLOCKED_RELIGHT_VERTEX = True


def _relightb_lib():
    return native.load("zh41l_relight", _RELIGHTB_SOURCE, _RELIGHTB_SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", *_avx512_flags()))


def relight_blocks(spans: list, wf: Tensor, tsc: dict) -> tuple[Tensor, Tensor | None]:
    """The tiles `zh41l_relight` reads: wb (nb, n², 64) — block k (region order: region r's columns
    [b0 + 64 kk, b0 + 64 kk + 64) of wf (n², Nc), zero past b1) — and tb alike of each region's t_s (n², b1 − b0)
    (the blocks of a region without t_s left unwritten), or None when no region has t_s."""
    n2 = int(wf.shape[0])
    wparts, tparts = [], []
    for r, (b0, b1) in enumerate(spans):
        m = b1 - b0
        nbr = -(-m // 64) if m > 0 else 0
        if nbr == 0:
            continue
        pad = torch.zeros(n2, nbr * 64, dtype=torch.float32)
        pad[:, :m] = wf[:, b0:b1]
        wparts.append(pad.view(n2, nbr, 64).transpose(0, 1))
        t = tsc.get(r, (None, None))[1] if r in tsc else None
        tp = torch.zeros(n2, nbr * 64, dtype=torch.float32)
        if t is not None:
            tp[:, :m] = t
        tparts.append((t is not None, tp.view(n2, nbr, 64).transpose(0, 1)))
    wb = torch.cat(wparts).contiguous() if wparts else torch.zeros(0, n2, 64)
    tb = torch.cat([t for _, t in tparts]).contiguous() if any(h for h, _ in tparts) else None
    return wb, tb


# zh41l: a steady lighting-only frame's lighting terms of the paper configuration (`ZHShadow._steady_planes`) by one
# C call: the plane's T¹(n0) (n², 3) = (float) (G (n², n²) · l) in float64 — G = Σ_k f_k A_k, the diffuse table's
# operator (`runtime.table`: W = A l) folded with the plane normal's features f (`runtime.diffuse_at`: Tᵀ = Wᵀ f),
# made once per kept state — and each region's l ⊙ kd, l ⊙ ks (float32 products: the bits of torch's). The base
# made W by a float64 GEMM, rounded it to float32 and took Wᵀ f by a float32 GEMV (two MKL calls whose code, cold
# after the suite's idle, cost ~0.1-0.2 ms of a ~1.4 ms frame at 1 thread): T¹(n0) here is the same sums in another
# order and rounding, float32 round-off from the base's.
_PLANE_LIGHT_SOURCE = r"""
#include <stdint.h>

/* T (n2, 3) = (float)(G (n2, n2) · (double) l), l (n2, 3) float32; Lo (nreg, 2, n2, 3) = l ⊙ kd_r, l ⊙ ks_r */
void zh41l_plane_light(int64_t n2, const float *l, const double *G, int64_t nreg, const float *kd, const float *ks,
                       float *T, float *Lo) {
    for (int64_t j = 0; j < n2; ++j) {
        double s0 = 0.0, s1 = 0.0, s2 = 0.0;
        for (int64_t i = 0; i < n2; ++i) {
            const double g = G[j * n2 + i];
            s0 += g * (double)l[3 * i]; s1 += g * (double)l[3 * i + 1]; s2 += g * (double)l[3 * i + 2];
        }
        T[3 * j] = (float)s0; T[3 * j + 1] = (float)s1; T[3 * j + 2] = (float)s2;
    }
    for (int64_t r = 0; r < nreg; ++r) {
        float *d = Lo + r * 6 * n2, *s = d + 3 * n2;
        for (int64_t i = 0; i < n2; ++i)
            for (int c = 0; c < 3; ++c) {
                d[3 * i + c] = l[3 * i + c] * kd[3 * r + c];
                s[3 * i + c] = l[3 * i + c] * ks[3 * r + c];
            }
    }
}
"""
_PLANE_LIGHT_SIGNATURES = {"zh41l_plane_light": [_I, _P, _P, _I, _P, _P, _P, _P]}


def _plane_light_lib():
    """The library of `zh41l_plane_light` or None (not cached here, b541a75)."""
    if not terms_switched_on():
        return None
    return native.load("zh41l_plane_light", _PLANE_LIGHT_SOURCE, _PLANE_LIGHT_SIGNATURES,
                       extra_flags=("-ffp-contract=off",))


def plane_light_setup(G: Tensor, kd: Tensor, ks: Tensor) -> tuple | None:
    """`plane_light`'s kept arguments: G (n², n²) float64, the regions' kd, ks (nreg, 3) float32; or None where it
    does not run. Its outputs are kept buffers (T (n², 3) and each region's l ⊙ kd, l ⊙ ks (n², 3)), rewritten by
    every call: read them before the next."""
    lib = _plane_light_lib()
    if lib is None or G.dtype != torch.float64 or G.dim() != 2 or G.shape[0] != G.shape[1] \
            or any(t.dtype != torch.float32 or t.dim() != 2 or t.shape[1] != 3 for t in (kd, ks)) \
            or kd.shape != ks.shape or any(t.device.type != "cpu" for t in (G, kd, ks)):
        return None
    n2, nreg = int(G.shape[0]), int(kd.shape[0])
    G, kd, ks = G.contiguous(), kd.contiguous(), ks.contiguous()
    T = torch.empty(n2, 3, dtype=torch.float32)
    Lo = torch.empty(max(nreg, 1), 2, n2, 3, dtype=torch.float32)
    return (lib.zh41l_plane_light, n2, nreg, G.data_ptr(), kd.data_ptr(), ks.data_ptr(), T, T.data_ptr(), Lo,
            Lo.data_ptr(), (G, kd, ks, lib))


def plane_light(st: tuple, light: Tensor) -> tuple[Tensor, Tensor] | None:
    """(T (n², 3), L (nreg, 2, n², 3): l ⊙ kd_r, l ⊙ ks_r) of `plane_light_setup` for the lighting (n², 3) float32
    CPU, by one C call (the kept buffers), or None (switched off, another shape)."""
    fn, n2, nreg, G, kd, ks, T, Tp, Lo, Lp, _ = st
    if not (terms_switched_on() and native.compile_enabled()) or light.dtype != torch.float32 \
            or light.device.type != "cpu" or light.shape != (n2, 3):
        return None
    light = light.contiguous()
    fn(n2, light.data_ptr(), G, nreg, kd, ks, Tp, Lp)
    return T, Lo


_INV_PI32 = float(torch.tensor(1.0 / math.pi, dtype=torch.float32))


def relight_run(setup: tuple, light: Tensor, kd: Tensor, ks: Tensor, clamp: bool) -> Tensor | None:
    """`relight_resolve` of a `relight_setup` for the lighting ``light`` (n², 3) and albedos kd, ks (nreg, 3):
    the same C call (the same bits); None where it does not run (not float32 CPU arrays of these shapes)."""
    lib, n2, Nc, nreg, sp, tsp, keep, packed, wf, x, L = setup
    R, _, col4, val4, trow, tcrow, tcol, tval = packed
    if any(t.device.type != "cpu" or t.dtype != torch.float32 for t in (light, kd, ks)) \
            or tuple(light.shape) != (n2, 3) or tuple(kd.shape) != (nreg, 3) or tuple(ks.shape) != (nreg, 3):
        return None
    light, kd, ks = light.contiguous(), kd.contiguous(), ks.contiguous()
    out = torch.empty(R, 3, dtype=torch.float32)
    nt = max(1, min(torch.get_num_threads(), R // MIN_ROWS_PER_CSR_THREAD))
    if isinstance(wf, tuple):   # (`zh41l_relight`: the tiles)
        wb, tb = wf
        lib.zh41l_relight(n2, Nc, light.data_ptr(), nreg, kd.data_ptr(), ks.data_ptr(), sp.data_ptr(), wb.data_ptr(),
                          0 if tb is None else tb.data_ptr(), tsp.data_ptr(), _INV_PI32, int(bool(clamp)),
                          x.data_ptr(), L.data_ptr(), R, col4.data_ptr(), val4.data_ptr(), out.data_ptr(), nt,
                          int(trow.numel()), trow.data_ptr(), tcrow.data_ptr(), tcol.data_ptr(), tval.data_ptr())
        return out
    lib.zh39o_relight(n2, Nc, light.data_ptr(), nreg, kd.data_ptr(), ks.data_ptr(), sp.data_ptr(), wf.data_ptr(),
                      tsp.data_ptr(), _INV_PI32, int(bool(clamp)),
                      x.data_ptr(), L.data_ptr(), R, col4.data_ptr(), val4.data_ptr(), out.data_ptr(), nt,
                      int(trow.numel()), trow.data_ptr(), tcrow.data_ptr(), tcol.data_ptr(), tval.data_ptr())
    return out


# -- zh42l ------------------------------------------------------------------------------------------
# A steady lighting-only order-8 / vertex-shaded frame (`ZHShadow._steady_relight`) by ONE C call on arguments kept
# per steady state: the world-space lighting of the kept polar-frame projection (`zh41l_light`, the very function:
# the same bits as `light_world`) and, from it, the radiance and resolve (`zh41l_relight`, the very function: the
# same bits as `relight_run`). In session 41's frame those were two calls, each behind ~15 Python checks, tensor
# allocations, ~25 `data_ptr` calls, 24 ctypes conversions and the off switches' environment reads (each torch call
# the first of its kind after the harness's G-buffer: 10-70 µs with the caches cold), all of it serial at 2 threads.
# (Tried and dropped, zh42l: the resolve's rows four at a time — a row's three channels one 4-float vector, the tail
# rows' entries in the same pass, 16-bit columns; the same bits — L 1.047x, E 1.008x against an A/A of 1.043x /
# 1.015x (`benchmarks.zh41l_flag_ab`); with streaming stores L 0.98x, E 0.97x: the pass is bound by its cold reads.)
_STEADY_SOURCE = _LIGHT_SOURCE + _RELIGHTB_SOURCE.replace("#include <stdint.h>\n", "", 1) + r"""
/* a: `zh41l_light`'s nine kept arguments (n2, C = 3, Q, mabs, perm, sgn, Xm, Xp, w), then `zh41l_relight`'s kept
   ones: Nc, nreg, kd, ks, spans, wb, tb, tsp, clamp, x, L, R, col4, val4, T, trow, tcrow, tcol, tval. With R (3, 3)
   given, light (n2, 3) = `zh41l_light`(R, c) first (returns 1, nothing written, where it refuses R); else light is
   read as given. Then out (R, 3) = `zh41l_relight`(light) on nt threads; returns 0. */
int64_t zh42l_steady(const int64_t *a, const double *R, const double *c, double tol, float inv_pi, float *light,
                     float *out, int64_t nt) {
    if (R && zh41l_light(a, R, c, tol, light) != 0) return 1;
    const int64_t *b = a + 9;
#define P_(k, T) ((T)(intptr_t)b[k])
    zh41l_relight(a[0], b[0], light, b[1], P_(2, const float *), P_(3, const float *), P_(4, const int64_t *),
                  P_(5, const float *), P_(6, const float *), P_(7, const int64_t *), inv_pi, b[8], P_(9, float *),
                  P_(10, float *), b[11], P_(12, const int32_t *), P_(13, const float *), out, nt, b[14],
                  P_(15, const int32_t *), P_(16, const int32_t *), P_(17, const int32_t *), P_(18, const float *));
#undef P_
    return 0;
}
"""
_STEADY_SIGNATURES = {"zh42l_steady": [_P, _P, _P, ctypes.c_double, ctypes.c_float, _P, _P, _I]}
# `ZHShadow._steady_relight` by `steady_run` where it runs; False: `light_world` / `_lighting` then `relight_run`
# (the tests' oracle)
STEADY_FUSED = True


def _steady_lib():
    """The library of `zh42l_steady` or None (switched off, no compiler; not cached here, b541a75)."""
    if not (STEADY_FUSED and terms_switched_on()):
        return None
    lib = load("zh42l_steady", _STEADY_SOURCE, _STEADY_SIGNATURES,
               extra_flags=("-fopenmp", "-ffp-contract=off", *_avx512_flags()))
    if lib is not None:
        lib.zh42l_steady.restype = ctypes.c_int64
    return lib


def steady_setup(rs: tuple, kd: Tensor, ks: Tensor, clamp: bool, Q: Tensor, tables: tuple) -> tuple | None:
    """`steady_run`'s kept arguments for a `relight_setup` ``rs`` of the blocked pass (`zh41l_relight`), the albedos
    kd, ks (nreg, 3) float32 CPU, ``clamp``, and `light_setup`'s Q and rotation ``tables`` (C = 3); or None where it
    does not run (then `light_world` and `relight_run`): (the function, the packed arguments' address, a 9-double
    buffer for R, n2, R, what the addresses point into). Addresses in a ctypes array, not a tensor (test_threads:
    the method's state holds no addresses)."""
    lib = _steady_lib()
    if lib is None or not native.compile_enabled():
        return None
    _, n2, Nc, nreg, sp, tsp, keep, packed, wf, x, L = rs
    if not isinstance(wf, tuple):   # (zh39o's pass: `relight_run`)
        return None
    wb, tb = wf
    R, _, col4, val4, trow, tcrow, tcol, tval = packed
    if any(t.device.type != "cpu" or t.dtype != torch.float32 for t in (kd, ks)) \
            or tuple(kd.shape) != (nreg, 3) or tuple(ks.shape) != (nreg, 3):
        return None
    if Q.shape != (3, 3) or Q.dtype != torch.float64 or Q.device.type != "cpu":
        return None
    mabs, perm, sgn, Xm, Xp = tables
    if mabs.shape != (n2,) or Xm.shape != (n2, n2) or Xp.shape != (n2, n2) or perm.dtype != torch.int64 \
            or not all(t.is_contiguous() and t.device.type == "cpu" for t in tables):
        return None
    kd, ks, Q = kd.contiguous(), ks.contiguous(), Q.contiguous()
    w = torch.empty(3 * n2 * 3 + 3, dtype=torch.float64)
    vals = [n2, 3, Q.data_ptr(), *(t.data_ptr() for t in tables), w.data_ptr(),
            Nc, nreg, kd.data_ptr(), ks.data_ptr(), sp.data_ptr(), wb.data_ptr(), 0 if tb is None else tb.data_ptr(),
            tsp.data_ptr(), int(bool(clamp)), x.data_ptr(), L.data_ptr(), R, col4.data_ptr(), val4.data_ptr(),
            int(trow.numel()), trow.data_ptr(), tcrow.data_ptr(), tcol.data_ptr(), tval.data_ptr()]
    args = (ctypes.c_int64 * len(vals))(*vals)
    Rbuf = (ctypes.c_double * 9)()
    return lib.zh42l_steady, ctypes.addressof(args), Rbuf, n2, R, (rs, kd, ks, Q, tables, w, args, lib)


def steady_run(st: tuple, R: tuple | None, c: Tensor | None, tol: float, light: Tensor, out: Tensor, nt: int) -> bool:
    """One `zh42l_steady` call of `steady_setup`'s ``st``: with ``R`` (nine floats, row-major) the lighting (n², 3)
    float32 ``light`` = `light_world`(c, R) first (c the kept (n², 3) float64 contiguous projection) — False, nothing
    written, where that refuses R —, else ``light`` read as given; then ``out`` (R, 3) float32 = `relight_run`'s
    image on ``nt`` threads. The caller owns the checks: ``light`` and ``out`` new contiguous float32 CPU tensors of
    those shapes, c the projection `light_world` would read (no check
    here: the steady frame's hot path)."""
    fn, args, Rbuf, _, _, _ = st
    if R is None:
        return fn(args, None, None, 0.0, _INV_PI32, light.data_ptr(), out.data_ptr(), nt) == 0
    Rbuf[:] = R
    return fn(args, Rbuf, c.data_ptr(), tol, _INV_PI32, light.data_ptr(), out.data_ptr(), nt) == 0
