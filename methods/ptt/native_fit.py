"""A VB frame's BRDF stage without torch ops (session 41, pt41; issue 14): the run-time fit of every
region's material (`transport.LobeBasis.coords_rows` — ``lobe_grid.GridLobes.project_family`` and
H = g_d kd + g_s ks — for a frame's materials: `fit_materials`; one material: `project`) and the region
tables' a_r (`ar_table`), each one small C call.

Why: a chess bench VB frame fitted its three changed materials serially (``torch_threads(1)`` around each,
before the view stage's threaded passes), each a handful of float64 torch ops on ~2.5–3.5 K values, and
formed a_r by an einsum: in a frame after the harness's G-buffer (caches cold) the fits took ~0.5 ms and
the einsum ~0.17 ms (1 thread, process CPU), all serial at 2 threads, plus four ``set_num_threads`` calls.
Here the fits are one call with the materials dealt to the frame's OpenMP threads and MKL set to one
thread per calling thread (``MKL_Set_Num_Threads_Local``: no ``torch_threads(1)``), a_r one call.

The same bits: the lobe values v are formed by the same IEEE operations in the same order as the torch
ops (products, quotients and the ``0.0 +`` as there) with the functions ATen's kernels call here: pow by
``Vectorized<double>``'s Sleef function (``Sleef_powd8_u10`` for AVX-512, ``Sleef_powd4_u10`` for AVX2;
from libtorch_cpu, as ``methods.ptt.native`` takes its acos / atan2) on the blocks of 2 vectors ATen's
``vectorized_loop`` takes and the C library's ``pow`` on its scalar tail (``std::pow``); exp by MKL's
``vmdExp`` with ATen's VML mode (its exp kernel goes through VML where torch has MKL); the (P, n) @ (n,)
products by MKL's ``dgemv_`` with the arguments torch's ``mv`` passes it. So the coordinates are
`project_family`'s float64 bits (tested on the chess / creature bench materials of 300 VB frames and
on random arrays). Where an entry is not found (a torch without MKL, an ISA without its Sleef pow) the
calls decline and the torch ops run (on a host where ATen does not vectorise, its pow is the C library's
on every element: taken). `FAST_FIT` off, no compiler, or ``PRTBENCH_COMPILE=0``: `project_family`'s torch
ops (the fallback and the test oracle)."""
from __future__ import annotations

import ctypes
import functools
import math
import os
import weakref

import torch
from torch import Tensor

from methods.core import native

# Whether `project` may take the C call (tests switch it off to reach the torch ops).
FAST_FIT = True

_SOURCE = r"""
#include <stdint.h>
#include <math.h>
#include <omp.h>
#if defined(__AVX512F__) || defined(__AVX2__)
#include <immintrin.h>
#endif

/* v[i] = pow(x[i], s) as ATen's pow kernel: blocks of 2 vectors of w doubles through Sleef's pow (w 8:
   AVX-512, 4: AVX2; 0 or no address: none), the tail element by element through the C library's. */
static void vpow(const double* x, double s, int64_t n, const void* vfn, int64_t w, double* v) {
    int64_t i = 0;
#if defined(__AVX512F__)
    if (w == 8 && vfn) {
        const __m512d sv = _mm512_set1_pd(s);
        __m512d (*f)(__m512d, __m512d) = (__m512d (*)(__m512d, __m512d))vfn;
        for (; i + 16 <= n; i += 16) {
            _mm512_storeu_pd(v + i, f(_mm512_loadu_pd(x + i), sv));
            _mm512_storeu_pd(v + i + 8, f(_mm512_loadu_pd(x + i + 8), sv));
        }
    }
#endif
#if defined(__AVX2__)
    if (w == 4 && vfn) {
        const __m256d sv = _mm256_set1_pd(s);
        __m256d (*f)(__m256d, __m256d) = (__m256d (*)(__m256d, __m256d))vfn;
        for (; i + 8 <= n; i += 8) {
            _mm256_storeu_pd(v + i, f(_mm256_loadu_pd(x + i), sv));
            _mm256_storeu_pd(v + i + 4, f(_mm256_loadu_pd(x + i + 4), sv));
        }
    }
#endif
    for (; i < n; ++i) v[i] = pow(x[i], s);
}

/* out = A @ v, A (P, n) row-major: by BLAS's dgemv with the arguments torch's ``A @ v`` passes it
   (``gemv``: a row-major A is the transposed column-major (n, P) matrix) where its address is given (the
   same bits), else summed here over i in order. */
typedef void (*dgemv_t)(const char*, const int*, const int*, const double*, const double*, const int*,
                        const double*, const int*, const double*, double*, const int*);
static void matvec(const void* gemv, const double* A, const double* v, int64_t P, int64_t n, double* out) {
    if (gemv) {
        const char t = 't';
        const int m = (int)n, np = (int)P, lda = (int)n, inc = 1;
        const double one = 1.0, zero = 0.0;
        ((dgemv_t)gemv)(&t, &m, &np, &one, A, &lda, v, &inc, &zero, out, &inc);
        return;
    }
    for (int64_t p = 0; p < P; ++p) {
        const double* a = A + p * n;
        double acc = 0.0;
        for (int64_t i = 0; i < n; ++i) acc = acc + a[i] * v[i];
        out[p] = acc;
    }
}

/* fast.region_tables' a_r (R n, 3L) of H (R, P, 3) and lobe_a (P, n, L): out[(r n + i) 3L + 3l + c] =
   sum_p H[r, p, c] lobe_a[p, i, l], by BLAS's sgemm with the arguments torch's
   ``einsum("rpc,pnl->rnlc", H, lobe_a)`` passes it (its product (R·3, P) @ (P, n·L), H's (r, c) rows
   copied contiguous as einsum's operand), then the output laid out as the einsum's reshape: the same bits.
   hl (3 R P) and c (3 R n L) scratch. */
typedef void (*sgemm_t)(const char*, const char*, const int*, const int*, const int*, const float*, const float*,
                        const int*, const float*, const int*, const float*, float*, const int*);
typedef int (*mkl_local_t)(int);
void ar_table(const float* H, const float* la, int64_t R, int64_t P, int64_t n, int64_t L, const void* gemm,
              const void* mkl_local, float* hl, float* c, float* out) {
    for (int64_t r = 0; r < R; ++r)
        for (int64_t ch = 0; ch < 3; ++ch)
            for (int64_t p = 0; p < P; ++p)
                hl[(r * 3 + ch) * P + p] = H[(r * P + p) * 3 + ch];
    const char t = 'n';
    const int N = (int)(n * L), M = (int)(3 * R), K = (int)P;
    const float one = 1.0f, zero = 0.0f;
    const int prev = mkl_local ? ((mkl_local_t)mkl_local)(1) : 0;  /* MKL on this thread alone */
    ((sgemm_t)gemm)(&t, &t, &N, &M, &K, &one, la, &N, hl, &K, &zero, c, &N);
    if (mkl_local) ((mkl_local_t)mkl_local)(prev);
    for (int64_t r = 0; r < R; ++r)
        for (int64_t i = 0; i < n; ++i)
            for (int64_t l = 0; l < L; ++l)
                for (int64_t ch = 0; ch < 3; ++ch)
                    out[((r * n + i) * L + l) * 3 + ch] = c[(r * 3 + ch) * N + i * L + l];
}

/* Phong / Blinn-Phong: out = Au @ (0.0 + k pow(c, s)); v (n) scratch. */
void lobe_pow(const double* c, const double* Au, int64_t P, int64_t n, double k, double s, const void* vpow_fn,
              int64_t w, const void* gemv, double* v, double* out) {
    vpow(c, s, n, vpow_fn, w, v);
    for (int64_t i = 0; i < n; ++i) v[i] = 0.0 + k * v[i];
    matvec(gemv, Au, v, P, n, out);
}

/* Cook-Torrance: D = exp(ntan2 / mm) / ((pimm c2) c2); out1 = A1 @ D, out2 = A2 @ D; v (2n) scratch.
   exp by MKL's vmdExp with ATen's mode (``vexp``: ATen's exp kernel calls VML where torch has MKL) or,
   without its address, the C library's. */
typedef void (*vml_t)(int, const double*, double*, long long);
void lobe_ct(const double* ntan2, const double* c2, const double* A1, const double* A2, int64_t P, int64_t n,
             double mm, double pimm, const void* vexp, int64_t mode, const void* gemv, double* v, double* out1,
             double* out2) {
    double* x = v + n;
    for (int64_t i = 0; i < n; ++i) x[i] = ntan2[i] / mm;
    if (vexp)
        ((vml_t)vexp)((int)n, x, v, (long long)mode);
    else
        for (int64_t i = 0; i < n; ++i) v[i] = exp(x[i]);
    for (int64_t i = 0; i < n; ++i) v[i] = v[i] / (pimm * c2[i] * c2[i]);
    matvec(gemv, A1, v, P, n, out1);
    matvec(gemv, A2, v, P, n, out2);
}

/* A frame's changed materials in one call (`fit_materials`): material j of family fam[j] (0 Lambert, 1
   Phong, 2 Blinn-Phong, 3 Cook-Torrance) with prm[8 j ..] = kd (3), ks (3), s or (m, F0); the families'
   groups (`GridLobes._groups`) in slot f: x1[f] (c, or −tan²θh), x2[f] (cos²θh), A1[f] (Au, or A1),
   A2[f], nn[f] values. H (nm, P, 3) float32: (float)(gd[p] kd[c] + gs[p] ks[c]) with gs the lobe
   projection (`lobe_pow` / `lobe_ct`; Lambert: kd on row 0, 0 elsewhere) — `LobeBasis.coords_rows`'
   float64 operations and its float32 rounding. The materials are dealt to nt threads (each material one
   thread's: the same bits at any nt); scratch nt (2 nmax + 2 P) doubles. */
/* material j of fit_materials (its comment) with the thread's scratch v (2 nmax) and o1, o2 (P each) */
static void fit_one(int64_t j, const int64_t* fam, const double* prm, const int64_t* x1, const int64_t* x2,
                    const int64_t* A1, const int64_t* A2, const int64_t* nn, int64_t P, const double* gd,
                    const void* vpow_fn, int64_t w, const void* vexp, int64_t mode, const void* gemv, double* v,
                    double* o1, double* o2, float* H) {
    const double* q = prm + 8 * j;
    const int64_t f = fam[j];
    float* h = H + j * P * 3;
    if (f == 0) {
        for (int64_t p = 0; p < P; ++p)
            for (int64_t c = 0; c < 3; ++c) h[p * 3 + c] = p == 0 ? (float)q[c] : 0.0f;
        return;
    }
    const int64_t n = nn[f];
    if (f == 1 || f == 2) {
        const double s = q[6];
        const double k = f == 1 ? (s + 1.0) / (2.0 * M_PI) : (s + 2.0) / (8.0 * M_PI);
        lobe_pow((const double*)x1[f], (const double*)A1[f], P, n, k, s, vpow_fn, w, gemv, v, o1);
    } else {
        const double m = q[6], F0 = q[7], wF = 1.0 - F0;
        lobe_ct((const double*)x1[f], (const double*)x2[f], (const double*)A1[f], (const double*)A2[f], P, n,
                m * m, M_PI * m * m, vexp, mode, gemv, v, o1, o2);
        for (int64_t p = 0; p < P; ++p) o1[p] = F0 * o1[p] + wF * o2[p];
    }
    for (int64_t p = 0; p < P; ++p)
        for (int64_t c = 0; c < 3; ++c) h[p * 3 + c] = (float)(gd[p] * q[c] + o1[p] * q[3 + c]);
}
void fit_materials(int64_t nm, const int64_t* fam, const double* prm, const int64_t* x1, const int64_t* x2,
                   const int64_t* A1, const int64_t* A2, const int64_t* nn, int64_t P, const double* gd,
                   const void* vpow_fn, int64_t w, const void* vexp, int64_t mode, const void* gemv,
                   const void* mkl_local, double* scratch, int64_t nmax, float* H, int64_t nt) {
#pragma omp parallel num_threads(nt)
    {
        const int64_t tid = omp_get_thread_num(), nth = omp_get_num_threads();
        const int prev = mkl_local ? ((mkl_local_t)mkl_local)(1) : 0;  /* MKL on this thread alone */
        double* v = scratch + tid * (2 * nmax + 2 * P);
        double* o1 = v + 2 * nmax;
        double* o2 = o1 + P;
        for (int64_t j = tid; j < nm; j += nth)
            fit_one(j, fam, prm, x1, x2, A1, A2, nn, P, gd, vpow_fn, w, vexp, mode, gemv, v, o1, o2, H);
        if (mkl_local) ((mkl_local_t)mkl_local)(prev);
    }
}
/* A shading="vertex" frame of the one-call route (session 43, pt43: method.FRAME_CALL) on a packed argument
   array (FC_* below): where the frame's materials changed (a[FC_NM] > 0), the work of the Python route's
   fit_materials (into a[FC_H]), ``methods.ptt.native``'s region_tables (W_r in place) and ar_table (a_r in
   place), as tasks of one team of a[FC_TEAM] threads taken in order from a shared counter: the fits (material
   j one task), then W_r's rows in chunks of a[FC_CHUNK] rows of one region each (a chunk waits for its
   region's fit), a_r's product after half of the chunks (it waits for every fit). Each material, row and a_r
   computed by the route's own code with its own arguments (fit_one, native's region_rows_range, ar_table):
   the same bits, whichever thread computes it. a[FC_CHANGED] = 1 where H differs from the last frame's
   (a[FC_HOLD]: any entry not ==, as `render`'s torch.equal; 1 without a last H): the BRDF stage the route
   would count (where the last H is equal the tables are rewritten with the same values). Then that library's
   view_frame (a[FC_VIEW]) on its own packed arguments (a[FC_VARGS]), whose result is returned. */
typedef void (*rows_t)(const float*, const float*, int64_t, int64_t, int64_t, int64_t, float*, int64_t, int64_t);
typedef int64_t (*view_t)(const int64_t*);
enum { FC_NM, FC_FAM, FC_PRM, FC_X1, FC_X2, FC_A1, FC_A2, FC_NN, FC_P, FC_GD, FC_VPOW, FC_W, FC_VEXP, FC_MODE,
       FC_GEMV, FC_LOCAL, FC_SCRATCH, FC_NMAX, FC_H, FC_NTFIT, FC_HOLD, FC_TEAM, FC_ROWS, FC_WROWS, FC_R, FC_T2,
       FC_K, FC_WR, FC_CHUNK, FC_LA, FC_N, FC_L, FC_SGEMM, FC_HL, FC_C, FC_AR, FC_VIEW, FC_VARGS, FC_CHANGED,
       FC_COUNT };
int64_t frame_call_count(void) { return FC_COUNT; }
int64_t frame_call(int64_t* a) {
    a[FC_CHANGED] = 0;
    const int64_t nm = a[FC_NM];
    if (nm > 0) {
        const int64_t P = a[FC_P], R = a[FC_R], T2 = a[FC_T2], K = a[FC_K], nmax = a[FC_NMAX];
        const int64_t ch = a[FC_CHUNK] > 0 ? a[FC_CHUNK] : T2, per = (T2 + ch - 1) / ch, nchunks = R * per;
        const int64_t ar_at = nm + nchunks / 2, ntasks = nm + nchunks + 1;
        float* H = (float*)a[FC_H];
        const void* local = (const void*)a[FC_LOCAL];
        int64_t next = 0;
        unsigned char ready[R > 0 ? R : 1];
        for (int64_t r = 0; r < R; ++r) ready[r] = 0;
#pragma omp parallel num_threads(a[FC_TEAM])
        {
            const int64_t tid = omp_get_thread_num();
            const int prev = local ? ((mkl_local_t)local)(1) : 0;  /* MKL on this thread alone */
            double* v = (double*)a[FC_SCRATCH] + tid * (2 * nmax + 2 * P);
            double* o1 = v + 2 * nmax;
            double* o2 = o1 + P;
            for (;;) {
                const int64_t k = __atomic_fetch_add(&next, 1, __ATOMIC_RELAXED);
                if (k >= ntasks)
                    break;
                if (k < nm) {
                    fit_one(k, (const int64_t*)a[FC_FAM], (const double*)a[FC_PRM], (const int64_t*)a[FC_X1],
                            (const int64_t*)a[FC_X2], (const int64_t*)a[FC_A1], (const int64_t*)a[FC_A2],
                            (const int64_t*)a[FC_NN], P, (const double*)a[FC_GD], (const void*)a[FC_VPOW], a[FC_W],
                            (const void*)a[FC_VEXP], a[FC_MODE], (const void*)a[FC_GEMV], v, o1, o2, H);
                    __atomic_store_n(&ready[k], 1, __ATOMIC_RELEASE);
                } else if (k == ar_at) {
                    for (int64_t r = 0; r < R; ++r)
                        while (!__atomic_load_n(&ready[r], __ATOMIC_ACQUIRE))
                            ;
                    ar_table(H, (const float*)a[FC_LA], R, P, a[FC_N], a[FC_L], (const void*)a[FC_SGEMM], local,
                             (float*)a[FC_HL], (float*)a[FC_C], (float*)a[FC_AR]);
                } else {
                    const int64_t c = k - nm - (k > ar_at), r = c / per, t0 = (c - r * per) * ch;
                    const int64_t t1 = t0 + ch < T2 ? t0 + ch : T2;
                    while (!__atomic_load_n(&ready[r], __ATOMIC_ACQUIRE))
                        ;
                    ((rows_t)a[FC_ROWS])((const float*)a[FC_WROWS], H, P, R, T2, K, (float*)a[FC_WR], r * T2 + t0,
                                         r * T2 + t1);
                }
            }
            if (local) ((mkl_local_t)local)(prev);
        }
        int changed = a[FC_HOLD] == 0;
        if (!changed) {
            const float* h0 = (const float*)a[FC_HOLD];
            for (int64_t i = 0; i < nm * P * 3; ++i)
                if (!(H[i] == h0[i])) {
                    changed = 1;
                    break;
                }
        }
        a[FC_CHANGED] = changed;
    }
    return ((view_t)a[FC_VIEW])((const int64_t*)a[FC_VARGS]);
}
"""

_P, _I, _D = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double
_SIGNATURES = {"lobe_pow": [_P, _P, _I, _I, _D, _D, _P, _I, _P, _P, _P],
               "lobe_ct": [_P, _P, _P, _P, _I, _I, _D, _D, _P, _I, _P, _P, _P, _P],
               "ar_table": [_P, _P, _I, _I, _I, _I, _P, _P, _P, _P, _P],
               "fit_materials": [_I, _P, _P, _P, _P, _P, _P, _P, _I, _P, _P, _I, _P, _I, _P, _P, _P, _I, _P, _I],
               "frame_call": [_P]}
# As ``methods.ptt.native``: the host's ISA, no contraction into fused multiply-adds (the torch ops'
# roundings: each product and sum rounded), OpenMP (the library binds to the libgomp torch loaded).
_EXTRA_FLAGS = ("-march=native", "-ffp-contract=off", "-fopenmp", f"-DPRTBENCH_CPU_{native.cpu_capability()}")
# ATen's vector width of doubles and its Sleef pow / exp per CPU capability (``Vectorized<double>``).
_VEC = {"AVX512": (8, "Sleef_powd8_u10"), "AVX2": (4, "Sleef_powd4_u10")}
# ATen's VML mode for its exp kernel (``ATen/cpu/vml.h``: VML_HA | VML_FTZDAZ_OFF | VML_ERRMODE_IGNORE).
_VML_MODE = 0x2 | 0x140000 | 0x100


def _library():
    """(the C library, vector width, Sleef pow, VML exp, BLAS dgemv, BLAS sgemm, MKL's
    ``MKL_Set_Num_Threads_Local`` — addresses or None) or None (no compiler, the build failed,
    ``PRTBENCH_COMPILE=0``: asked at each call, as ``methods.ptt.native``'s ``_kernel``)."""
    lib = native.load("ptt_fit", _SOURCE, _SIGNATURES, extra_flags=_EXTRA_FLAGS)
    return None if lib is None else (lib, *_entries())


@functools.lru_cache(maxsize=None)
def _entries() -> tuple:
    """(vector width, Sleef pow, VML exp, BLAS dgemv, BLAS sgemm, MKL_Set_Num_Threads_Local) from
    libtorch_cpu, looked up once."""
    w, vpow, vexp, gemv, sgemm, local = 0, None, None, None, None, None
    try:
        tl = ctypes.CDLL(os.path.join(os.path.dirname(torch.__file__), "lib", "libtorch_cpu.so"))
    except OSError:
        tl = None
    vec = _VEC.get(native.cpu_capability())
    if vec is not None and tl is not None and hasattr(tl, vec[1]):
        w, vpow = vec[0], ctypes.cast(getattr(tl, vec[1]), ctypes.c_void_p).value
    if vec is None and native.cpu_capability() == "DEFAULT":
        vpow = 0  # ATen's pow is the C library's on every element: w 0 computes it so
    if tl is not None and torch.backends.mkl.is_available() and hasattr(tl, "vmdExp"):
        vexp = ctypes.cast(tl.vmdExp, ctypes.c_void_p).value
    if tl is not None and torch.backends.mkl.is_available() and hasattr(tl, "dgemv_"):
        gemv = ctypes.cast(tl.dgemv_, ctypes.c_void_p).value
    if tl is not None and torch.backends.mkl.is_available() and hasattr(tl, "sgemm_"):
        sgemm = ctypes.cast(tl.sgemm_, ctypes.c_void_p).value
    if tl is not None and torch.backends.mkl.is_available() and hasattr(tl, "MKL_Set_Num_Threads_Local"):
        local = ctypes.cast(tl.MKL_Set_Num_Threads_Local, ctypes.c_void_p).value
    return w, vpow, vexp, gemv, sgemm, local


def available() -> bool:
    """True when `project` / `fit_materials` run the C call (for Cook-Torrance also needs VML's exp)."""
    L = _library() if FAST_FIT else None
    return L is not None and L[2] is not None and L[4] is not None


_BUF: dict[int, Tensor] = {}


def _scratch(n: int) -> Tensor:
    """A float64 scratch vector of n values, kept per n (the lobe values between the two passes)."""
    b = _BUF.get(n)
    if b is None:
        b = _BUF[n] = torch.empty(n, dtype=torch.float64)
    return b


def _ok(*ts: Tensor) -> bool:
    return all(t.dtype == torch.float64 and t.device.type == "cpu" and t.is_contiguous() for t in ts)


def project(fam: str, groups: tuple[Tensor, ...], params: tuple[float, ...]) -> list[float] | None:
    """`GridLobes.project_family(fam, A, *params, as_list=True)` from its `_groups` (``groups``) by the C
    call (module docstring: the same lobe values, the products summed in column order), or None when it
    does not run here (`available`, not float64 contiguous CPU arrays)."""
    if not FAST_FIT:
        return None
    L = _library()
    if L is None:
        return None
    lib, w, vpow, vexp, gemv, _, _ = L
    if gemv is None or vpow is None or (fam == "cooktorrance" and vexp is None):
        return None
    if fam in ("phong", "blinnphong"):
        c, Au = groups
        if not _ok(c, Au) or Au.ndim != 2 or c.ndim != 1 or Au.shape[1] != c.shape[0]:
            return None
        s, = params
        s = float(s)
        if s in _POW_SPECIAL:
            return None
        k = (s + 1.0) / (2.0 * math.pi) if fam == "phong" else (s + 2.0) / (8.0 * math.pi)
        P, n = Au.shape
        v = _scratch(n)
        out = (ctypes.c_double * P)()
        lib.lobe_pow(c.data_ptr(), Au.data_ptr(), P, n, k, s, vpow, w, gemv, v.data_ptr(), out)
        return list(out)
    if fam == "cooktorrance":
        ntan2, c2, A1, A2 = groups
        if not _ok(ntan2, c2, A1, A2) or A1.shape != A2.shape or A1.ndim != 2 or A1.shape[1] != c2.shape[0] \
                or ntan2.shape != c2.shape:
            return None
        m, F0 = (float(x) for x in params)
        P, n = A1.shape
        v = _scratch(2 * n)
        o1, o2 = (ctypes.c_double * P)(), (ctypes.c_double * P)()
        lib.lobe_ct(ntan2.data_ptr(), c2.data_ptr(), A1.data_ptr(), A2.data_ptr(), P, n, m * m, math.pi * m * m,
                    vexp, _VML_MODE, gemv, v.data_ptr(), o1, o2)
        wF = 1.0 - F0
        return [F0 * a + wF * b for a, b in zip(o1, o2)]
    return None


# Below this many multiply-adds (R·3 · P · n·L) ATen's bmm takes its own loops instead of BLAS
# (``bmm_out_or_baddbmm_``: contraction × rows × columns < 400): `ar_table` declines (another order).
_BLAS_MIN = 400
_AR_BUF: dict[tuple[int, ...], tuple[Tensor, Tensor]] = {}


def ar_table(H: Tensor, lobe_a: Tensor, out: Tensor | None = None) -> Tensor | None:
    """``einsum("rpc,pnl->rnlc", H, lobe_a).reshape(R·n, L·3)`` (`fast.region_tables`' a_r) by one C call
    (MKL's sgemm with the einsum's arguments: the same bits, tested), written into ``out`` when it fits;
    None when it does not run here (`available`, no sgemm entry, not float32 contiguous CPU arrays, a
    product small enough for ATen's own loops)."""
    fa = ar_args(H, lobe_a, out)
    if fa is None:
        return None
    Lb, R, P, n, L, hl, c, out = fa
    with _one_mkl_thread(Lb):
        Lb[0].ar_table(H.data_ptr(), lobe_a.data_ptr(), R, P, n, L, Lb[5], Lb[6], hl.data_ptr(), c.data_ptr(),
                       out.data_ptr())
    return out


def ar_args(H: Tensor, lobe_a: Tensor, out: Tensor | None = None) -> tuple | None:
    """`ar_table`'s C call without H's values: (the library tuple, R, P, n, L, its two scratch tensors, the
    output — ``out`` where it fits, else a new tensor), or None where `ar_table` declines (the same checks)."""
    if not FAST_FIT:
        return None
    Lb = _library()
    if Lb is None or Lb[5] is None:
        return None
    if H.ndim != 3 or lobe_a.ndim != 3 or H.shape[2] != 3 or lobe_a.shape[0] != H.shape[1]:
        return None
    if not all(t.dtype == torch.float32 and t.device.type == "cpu" and t.is_contiguous() for t in (H, lobe_a)):
        return None
    R, P, _ = H.shape
    _, n, L = lobe_a.shape
    if R * 3 * P * n * L < _BLAS_MIN or R * n * L * 3 >= 2 ** 31:
        return None
    if out is None or out.shape != (R * n, L * 3) or out.dtype != torch.float32 or not out.is_contiguous():
        out = torch.empty(R * n, L * 3, dtype=torch.float32)
    key = (R, P, n, L)
    buf = _AR_BUF.get(key)
    if buf is None:
        buf = _AR_BUF[key] = (torch.empty(R * 3 * P, dtype=torch.float32), torch.empty(R * 3 * n * L, dtype=torch.float32))
    return Lb, R, P, n, L, buf[0], buf[1], out


def _one_mkl_thread(Lb):
    """Nothing where the C calls set MKL to one thread themselves (``MKL_Set_Num_Threads_Local``, on
    each calling thread: cheap), else ``torch_threads(1)`` around the call (MKL's products as torch
    runs them under ``torch_threads(1)``: the same bits at any thread count)."""
    import contextlib

    from methods.core.threads import torch_threads

    return contextlib.nullcontext() if Lb[6] is not None else torch_threads(1)


_FAMILY_SLOT = {"phong": 1, "blinnphong": 2, "cooktorrance": 3}
# Exponents ATen's pow kernel computes by other means than pow (products, sqrt, reciprocals: its scalar
# exponent specialisations) and more: `project` / `fit_materials` decline them (the torch ops run).
_POW_SPECIAL = frozenset({0.0, 0.5, -0.5, 1.0, -1.0, 2.0, -2.0, 3.0, -3.0})


# `_family_table`'s arrays per basis (beside it, not on it: a basis stays picklable).
_TABLES: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _family_table(basis, grid, A: Tensor, g_d: Tensor, fams: set) -> dict | None:
    """The C arrays of `fit_materials` for the families ``fams`` (kept per basis for its A: the groups'
    addresses, their sizes, g_d's column), or None when a group is not float64 contiguous."""
    tab = _TABLES.get(basis)
    if tab is None or tab["A"] is not A:
        tab = _TABLES[basis] = {"A": A, "fams": set(), "keep": [], "gd": g_d[:, 0].contiguous(),
                                   "x1": (ctypes.c_int64 * 4)(), "x2": (ctypes.c_int64 * 4)(),
                                   "A1": (ctypes.c_int64 * 4)(), "A2": (ctypes.c_int64 * 4)(),
                                   "n": (ctypes.c_int64 * 4)()}
    for fam in fams - tab["fams"]:
        g = grid._groups(fam, A)
        if fam == "cooktorrance":
            x1, x2, a1, a2 = g
        else:
            (x1, a1), x2, a2 = g, g[0], g[1]
        if not _ok(x1, x2, a1, a2) or a1.ndim != 2 or a1.shape != a2.shape or a1.shape[1] != x1.shape[0] \
                or x1.shape != x2.shape or a1.shape[0] != tab["gd"].shape[0]:
            return None
        f = _FAMILY_SLOT[fam]
        tab["x1"][f], tab["x2"][f], tab["A1"][f], tab["A2"][f] = (t.data_ptr() for t in (x1, x2, a1, a2))
        tab["n"][f] = int(x1.shape[0])
        tab["keep"].append(g)
        tab["fams"].add(fam)
    return tab


_MODULES: tuple = ()


def _modules() -> tuple:
    """(lobe_grid, transport, scenes.materials), imported once (not at import time: transport imports this
    module's callers)."""
    global _MODULES
    from methods.ptt import lobe_grid as _lg
    from methods.ptt import transport as _tp
    from scenes import materials as _mat

    _MODULES = (_lg, _tp, _mat)
    return _MODULES


def fit_materials(basis, mats: list, nt: int = 1) -> Tensor | None:
    """(len(mats), P, 3) float32: ``torch.tensor(basis.coords_rows(m), dtype=torch.float32)`` of each
    material (`transport.LobeBasis.coords_rows`: Lambert, or a `lobe_grid.FAMILIES` material fitted on
    the grid) in one C call, the materials dealt to ``nt`` OpenMP threads (each one thread's: the same
    bits at any nt; the float64 values and their float32 rounding as coords_rows', tested). None when it
    does not run here (`available`), the basis has no diffuse function, or a material is of another type
    or is one of the basis's own lobes (coords_rows' exact rows): the caller then fits per material."""
    fa = fit_args(basis, mats, nt)
    if fa is None:
        return None
    Lb, args, keep = fa
    H = torch.empty(args[0], args[8], 3, dtype=torch.float32)
    args[18] = H.data_ptr()
    with _one_mkl_thread(Lb):
        Lb[0].fit_materials(*args)
    del keep  # (the material arrays the call read)
    return H


@functools.lru_cache(maxsize=None)
def _frame_fn(lib: ctypes.CDLL):
    """The library's ``frame_call`` with its int64 result and ``frame_call_count``'s slot count."""
    fn = lib.frame_call
    fn.restype = ctypes.c_int64
    fn.argtypes = [ctypes.c_void_p]
    lib.frame_call_count.restype = ctypes.c_int64
    return fn, int(lib.frame_call_count())


# The slots of ``frame_call``'s packed argument array (the C enum FC_*, in its order): 0-19 `fit_materials`'.
FC = ("nm", "fam", "prm", "x1", "x2", "A1", "A2", "nn", "P", "gd", "vpow", "w", "vexp", "mode", "gemv", "local",
      "scratch", "nmax", "H", "ntfit", "hold", "team", "rows", "wrows", "R", "T2", "K", "wr", "chunk", "la", "n",
      "L", "sgemm", "hl", "c", "ar", "view", "vargs", "changed")
_FC = {k: i for i, k in enumerate(FC)}


def frame_call_fn():
    """(``frame_call``, its slot count) or None (`available` false, or no MKL per-thread switch: the Python
    route then wraps the products in ``torch_threads(1)``, which the one call does not)."""
    if not FAST_FIT:
        return None
    Lb = _library()
    if Lb is None or Lb[2] is None or Lb[4] is None or Lb[5] is None or Lb[6] is None:
        return None
    fn, n = _frame_fn(Lb[0])
    return (fn, n) if n == len(FC) else None


def fit_args(basis, mats: list, nt: int = 1, Lb: tuple | None = None, team: int = 0) -> tuple | None:
    """`fit_materials`' C call without its output: (the library tuple, the call's 20 arguments as a list —
    slot 18, H's address, still 0 —, the ctypes arrays they point into, to keep alive), or None where
    `fit_materials` declines (the same checks). ``Lb``: `_library()`'s tuple as the caller looked it up in
    this frame (``method.FRAME_CALL``'s plan, made under the same compile switch), else looked up here.
    ``team``: scratch for that many threads at least (``frame_call``'s team)."""
    if not FAST_FIT or not mats or not getattr(basis, "diffuse", False):
        return None
    if Lb is None:
        Lb = _library()
    if Lb is None or Lb[2] is None or Lb[4] is None:
        return None
    _lg, _tp, _mat = _MODULES or _modules()

    keys = basis.__dict__.get("_lobe_keys")
    if keys is None:
        keys = basis._lobe_keys = [_tp._lobe_key(l) for l in basis.lobes]
    nm = len(mats)
    fam = (ctypes.c_int64 * nm)()
    prm = (ctypes.c_double * (8 * nm))()
    fams = set()
    for j, m in enumerate(mats):
        kind = type(m)
        kd = m.kd
        prm[8 * j], prm[8 * j + 1], prm[8 * j + 2] = kd
        if kind is _mat.Lambert:
            continue  # fam 0
        f = _lg.FAMILIES.get(kind)
        if f is None:
            return None
        key = _tp._lobe_key(m)
        if key in keys:
            return None
        ks = m.ks_rgb
        prm[8 * j + 3], prm[8 * j + 4], prm[8 * j + 5] = ks
        if f == "cooktorrance":
            if Lb[3] is None:
                return None
            prm[8 * j + 6], prm[8 * j + 7] = key[1]
        else:
            if float(key[1][0]) in _POW_SPECIAL:
                return None
            prm[8 * j + 6] = key[1][0]
        fam[j] = _FAMILY_SLOT[f]
        fams.add(f)
    grid, A, g_d = basis.prepare()
    tab = _family_table(basis, grid, A, g_d, fams)
    if tab is None:
        return None
    P = int(tab["gd"].shape[0])
    nmax = max([tab["n"][_FAMILY_SLOT[f]] for f in fams], default=0)
    nt = max(1, min(int(nt), nm))
    scratch = _scratch(max(nt, team) * (2 * nmax + 2 * P))
    _, w, vpow, vexp, gemv, _, local = Lb
    ad = ctypes.addressof
    return Lb, [nm, ad(fam), ad(prm), ad(tab["x1"]), ad(tab["x2"]), ad(tab["A1"]), ad(tab["A2"]), ad(tab["n"]), P,
                tab["gd"].data_ptr(), vpow or 0, w, vexp or 0, _VML_MODE, gemv or 0, local or 0, scratch.data_ptr(),
                nmax, 0, nt], (fam, prm)
