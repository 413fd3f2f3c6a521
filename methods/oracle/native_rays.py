"""The oracle's per-ray work as C loops (issue 14): `pretrace` replaces the compiled pre-trace graph
(``methods.oracle._pretrace_stage``) and the env-map cell search before it (``Oracle._light_cells``):
the shading frame, each light sample's cell (``methods.core.envguide``'s guide table and 4 bisection
steps, ``scenes.envmap.count_le`` for the u₀ it does not bracket: the same cells), env-map sampling
in that cell, the BRDF's sample / pdf / eval, the MIS weights, each ray's contribution, whether it is
live and its shadow-ray origin; `trace` hands the rays to Mitsuba's ``scene.ray_test`` as they are —
origins and directions written as component planes (`plane_views`) that Dr.Jit maps without a copy,
``live`` as the active mask, so the live rays are traced and no others (session 31: the C gather of
the live rays, their copy into Dr.Jit and the scatter of the answers back went, ~30 ms of a 370 ms
chess bench frame at 1 thread) — or, on another tracer, gathers the live rays in order and traces them
in one ``occluded`` batch (``Oracle._trace_soa``'s nonzero / index_select / scatter); `shade` looks up
the radiance and sums a sample's rays over those live and not blocked
(``methods.oracle._shade_block_stage``). `uniform` draws the frame's random numbers as ``torch.rand``
does, bit for bit, by a C copy of torch's CPU generator (Mersenne Twister) run from and back to the
generator's state (session 31: torch's serial kernel took ~4 ns a number, 18 ms of a chess bench
frame's 16 × 262 144). For the library's BRDF families that the
compiled path runs with tensor parameters (Lambert, Phong, Blinn-Phong, Cook-Torrance, Ward): the
same operations in the same order as the eager estimator (``Oracle._shade``, ``scenes.materials``,
``scenes.envmap``: float32 where it is float32, float64 where it is float64), from the SAME random
numbers. The compiled path stays beside it as the fallback (no C compiler, ``PRTBENCH_COMPILE=0``,
another BRDF family in the frame, e.g. Torrance-Sparrow or a non-library material) and both are
compared with the eager estimator by ``tests/methods/test_oracle.py``.

Layout: the rays slot-major ((K, Q): light samples first, then BRDF samples, as the eager
estimator's ray axis), one loop per ray slot over the samples of a block of `BLOCK`, vectorised by
GCC over the samples (8 float32 lanes with AVX2). The transcendentals (sin, cos, pow, exp, log1p,
atan2, acos) then come from glibc's vector math library (libmvec, declared SIMD by ``math.h`` under
``__FAST_MATH__``, which is defined for that header only: the code is compiled without
``-ffast-math``, with ``-ffp-contract=off``, so every product and sum rounds as torch's;
``-fno-trapping-math`` only lets GCC vectorise floor). Their results may differ from torch's (Sleef
or libm) by an ulp or so — the same class of difference as the compiled path's Sleef against the
eager path's libm — hence the image equals the reference's to float32 round-off, and a ray whose
direction moves by an ulp may land in a neighbouring env-map cell or flip its shadow test: the
compiled path and this one flip the same ray of chess bench V frame 2 (max |Δ| / max 2.9e-2 on one
pixel, both paths), none on the test scenes. What kept GCC's vectoriser off, and is avoided here:
sin and cos of one argument merged into sincos (a complex result: `NOSINCOS`), byte-wide selects
(Lambert's loop; `fsel`, `fblend`), int64 ↔ double conversions and integer division (AVX-512 only /
none: int32 and float paths), strided loads of a runtime stride (the slot's uniforms are copied to
contiguous buffers first). The guide-table search stays scalar: AVX2 gathers (intrinsics or
``-mtune-ctrl=use_gather``) measured slower on this host (light rays 63 vs 59 ms, chess bench).
Session 32: the search and the radiance look-up wait on memory (a light sample's bucket is a random
entry of a 0.5 MB guide table, its cdf and p_flat entries and a look-up's texels random lines of 1 MB
tables), so both run in passes over a block — the guide entries first, the lines they point to
prefetched, then the steps (`search_cells`; `light_cells` runs it alone, for its test); the texel
coordinates first, their rows prefetched, then the taps (`shade_rows`) —: the same operations on the
same values, the misses of a block overlapped instead of met one sample after another (creature bench
V, 1 thread, a captured frame: `pretrace` 1.3×, `shade` 1.3×). Tried and dropped (no gain measured):
a branchless search, a 2^15-bucket guide with 7 steps (0.8×), the BRDF rays' cell densities in a
second pass, a float32 per-cell density table, blocks of 256, powf's zero lanes kept out of its vector
form. And Phong's and Blinn-Phong's lobes take their powers of integer exponents (s in [0, 127], all
the library's) by float64 products rounded once (``ipow``) instead of libmvec's powf, 7.6 % of a chess
bench frame: `pretrace` chess V 1.25×, creature V 1.04× — the one change here that is not bit for bit:
the correctly rounded power where powf's vector form is an ulp off (images within 1.2e-7 of the peak
of session 31's, the same live rays).
Blocks of samples are split over OpenMP's team (each ray computed by one thread: results do not
depend on the thread count). The per-sample frame (s, t, n), ω_o in it and the geometric normal's
side are recomputed per ray (a few flops) instead of stored.
"""
from __future__ import annotations

import ctypes
import functools
import math

import torch
from torch import Tensor

from methods.core import native
from methods.core.envguide import GUIDE_STEPS, guide_table
from references.visibility import MitsubaVisibility

__all__ = ["KINDS", "Rows", "available", "frame_rows", "int_pow", "light_cells", "pretrace", "shade", "supports", "trace", "uniform"]

assert GUIDE_STEPS == 4, "the C search takes methods.core.envguide's 4 bisection steps"

# BRDF families with a C body (``scenes.materials`` kinds) → their code in the C source.
KINDS = {"lambert": 0, "phong": 1, "blinnphong": 2, "cooktorrance": 3, "ward": 4}

# Samples per block of the OpenMP split (each block runs every ray slot over its samples).
BLOCK = 512
# Samples below which one thread runs a call (a hand-off costs more than its share).
MIN_PER_THREAD = 4096

_SOURCE = r"""
#define __FAST_MATH__ 1
#include <math.h>
#undef __FAST_MATH__
#include <stdint.h>
#include <string.h>

typedef struct {
    const float *n, *wo, *ng, *p;          /* (Q, 3) */
    const float *ul;                       /* (Q, NL, 2) */
    const float *ub;                       /* (Q, NB, 2) */
    const double *cdf0, *pflat, *omega, *ztab, *R;  /* (C + 1,) 0 then the cdf, (C,), (H-1,), (H,), (3, 3) */
    const int32_t *guide; int64_t G;       /* methods.core.envguide.guide_table of the cdf, (G + 1,) */
    int64_t Q, NL, NB, C, H, W, QS, PS;   /* QS: rows between ray slots of the outputs, PS: between planes */
    float eps;
    int32_t kind, has_spec;
    double kd[3], ks[3], ps, s, m, F0, ax, ay;
    float *contrib;                        /* (K, QS, 3), rows from this call's first sample */
    float *o, *d;                          /* (3, K, QS) component planes PS apart, rows likewise */
    uint8_t *live;                         /* (K, QS) */
    /* gather mode (idx non-NULL): the call's samples are the G-buffer rows idx[0:Q] (int64), read here per
       block instead of from gathered (Q, 3) rows n, wo, ng, p: positions gp and normals gn (P, 3) rows,
       w_o gw at gw[c * gws0 + s * gws1], the geometric normal ngt[3 * gf[s]] (gf non-NULL: a per-face
       table) or ngt[3 * i] (gf NULL: the call's own rows) */
    const int64_t *idx;
    const float *gp, *gn, *gw, *ngt;
    int64_t gws0, gws1;
    const int64_t *gf;
} PArgs;

#define PI_F ((float)M_PI)
#define MAXB 512  /* samples per block at most (BLOCK) */
#define TINY 1e-12f

static inline __attribute__((always_inline)) float clamp0(float x) { return x < 0.0f ? 0.0f : x; }

/* c ? v : +0, by a bit mask: GCC otherwise moves later comparisons of the result into the select,
   as byte selects that its vectoriser does not take (Lambert's loop stayed scalar) */
static inline __attribute__((always_inline)) float fsel(int c, float v) {
    uint32_t u;
    memcpy(&u, &v, 4);
    u &= -(uint32_t)(c != 0);
    memcpy(&v, &u, 4);
    return v;
}

/* c ? x : y by bit masks (see fsel) */
static inline __attribute__((always_inline)) float fblend(int c, float x, float y) {
    uint32_t a, b, m = -(uint32_t)(c != 0);
    memcpy(&a, &x, 4);
    memcpy(&b, &y, 4);
    a = (a & m) | (b & ~m);
    memcpy(&x, &a, 4);
    return x;
}

/* x^n for an integer exponent n in [0, 127] (the exponents the library's lobes use: Phong 10-40, Blinn-Phong
   25-80): products in float64 of x (exact), rounded once to float32 — within 2^-46 of x^n, so the
   correctly rounded float32 but for a value within that of a rounding boundary (libmvec's vector powf,
   which it replaces, is within an ulp or so, as torch's Sleef / libm powf: all float32 round-off of the
   same power); x = +-0, NaN, inf as powf. The exponent's bits are the same for every lane: a select
   each, no branch. 3-4x fewer instructions than powf's vector form. */
static inline __attribute__((always_inline)) float ipow(float x, int n) {
    double b = x, r = 1.0;
    for (int i = 0; i < 7; i++) {
        r = ((n >> i) & 1) ? r * b : r;
        b = b * b;
    }
    return (float)r;
}

/* powf(x, s), by ipow when ip (s = si, an integer in [0, 127]: `pretrace` picks the block's variant) */
static inline __attribute__((always_inline)) float spow(float x, float s, int ip, int si) {
    return ip ? ipow(x, si) : powf(x, s);
}

/* scenes.materials.power_cosine_pdf: (s+1)/(2pi) max(0, c)^s (c > 0) */
static inline __attribute__((always_inline)) float pcos_pdf(float c, float norm, float s, int ip, int si) {
    return norm * spow(clamp0(c), s, ip, si) * (float)(c > 0.0f);
}

/* half_vector: h flipped into the upper hemisphere, valid (|wi + wo| > 1e-6) */
static inline __attribute__((always_inline)) void half_vec(const float *wi, const float *wo, float *h, float *valid) {
    float hx = wi[0] + wo[0], hy = wi[1] + wo[1], hz = wi[2] + wo[2];
    float nr = sqrtf(hx * hx + hy * hy + hz * hz);
    *valid = (float)(nr > 1e-6f);
    float nc = nr < TINY ? TINY : nr;
    hx = hx / nc; hy = hy / nc; hz = hz / nc;
    if (hz < 0.0f) { hx = -hx; hy = -hy; hz = -hz; }
    h[0] = hx; h[1] = hy; h[2] = hz;
}

/* half_to_wi_pdf */
static inline __attribute__((always_inline)) float h2wi(float ph, const float *wo, const float *h, float valid) {
    float woh = fabsf(wo[0] * h[0] + wo[1] * h[1] + wo[2] * h[2]);
    float out = ph / (4.0f * (woh < TINY ? TINY : woh));
    return ((valid != 0.0f) & (woh > 0.0f)) ? out : 0.0f;
}

/* beckmann_D */
static inline __attribute__((always_inline)) float beckD(float cos_t, float mm, float pimm) {
    float c = cos_t < TINY ? TINY : cos_t;
    float c2 = c * c;
    float tan2 = clamp0(1.0f - c2) / c2;
    float dd = expf(-tan2 / mm) / (pimm * c2 * c2);
    return cos_t > 0.0f ? dd : 0.0f;
}

typedef struct {  /* a material's constants, float32 as the tensors' ops round them */
    int kind, has_spec;
    float kd_pi[3], ks[3], ps, pd, pd_clamped, s, pnorm_phong, bnorm, inv_s1, mm, pimm, neg_mm,
          F0, omF0, ax, ay, piaxay, pi4axay;
    int si;  /* s when an integer in [0, 127] (ipow), else -1 */
} Mat;

/* Material.pdf on local wi, wo */
static inline __attribute__((always_inline)) float mat_pdf(const Mat *M, int kind, const float *wi, const float *wo) {
    const int ip = kind >> 3;  /* the integer-exponent variant (kind | 8) */
    kind &= 7;
    float p = M->pd * (clamp0(wi[2]) / PI_F);
    float sp = 0.0f;
    if (kind == 1) {  /* Phong */
        float Rx = -wo[0], Ry = -wo[1], Rz = wo[2];
        float nr = sqrtf(Rx * Rx + Ry * Ry + Rz * Rz);
        float c = (Rx * wi[0] + Ry * wi[1] + Rz * wi[2]) / (nr < TINY ? TINY : nr);
        sp = pcos_pdf(c, M->pnorm_phong, M->s, ip, M->si);
    } else if (kind == 2 || kind == 3 || kind == 4) {
        float h[3], valid;
        half_vec(wi, wo, h, &valid);
        float ph;
        if (kind == 2) ph = pcos_pdf(h[2], M->pnorm_phong, M->s, ip, M->si);
        else if (kind == 3) ph = beckD(h[2], M->mm, M->pimm) * h[2];
        else {
            float hz = h[2] < TINY ? TINY : h[2];
            float a = h[0] / M->ax, b = h[1] / M->ay;
            float e = (a * a + b * b) / (hz * hz);
            float pw = expf(-e) / (M->piaxay * (hz * hz * hz));
            ph = h[2] > 0.0f ? pw : 0.0f;
        }
        sp = h2wi(ph, wo, h, valid);
    }
    return (kind != 0 && M->has_spec) ? p + M->ps * sp : p;  /* a select: the lobe is computed anyway */
}

/* Material.eval (no cosine) */
static inline __attribute__((always_inline)) void mat_eval(const Mat *M, int kind, const float *wi, const float *wo, float *f) {
    const int ip = kind >> 3;
    kind &= 7;
    float lobe = 0.0f;
    if (kind == 1) {
        float c = -wo[0] * wi[0] + -wo[1] * wi[1] + wo[2] * wi[2];
        lobe = pcos_pdf(c, M->pnorm_phong, M->s, ip, M->si);
    } else if (kind == 2) {
        float h[3], valid;
        half_vec(wi, wo, h, &valid);
        lobe = M->bnorm * spow(clamp0(h[2]), M->s, ip, M->si) * valid;
    } else if (kind == 3) {
        float h[3], valid;
        half_vec(wi, wo, h, &valid);
        float nh = h[2], ni = wi[2], no = wo[2];
        float oh = wo[0] * h[0] + wo[1] * h[1] + wo[2] * h[2];
        oh = oh < TINY ? TINY : oh;
        float g1 = 2.0f * nh * no / oh, g2 = 2.0f * nh * ni / oh;
        float G = g1 < g2 ? g1 : g2;
        G = 1.0f < G ? 1.0f : G;
        float x = clamp0(1.0f - oh);
        float F = M->F0 + M->omF0 * (x * x * x * x * x);
        float den = 4.0f * ni * no;
        lobe = beckD(nh, M->mm, M->pimm) * F * (G / (den < TINY ? TINY : den) * valid);
    } else if (kind == 4) {
        float hx = wi[0] + wo[0], hy = wi[1] + wo[1], hz = wi[2] + wo[2];
        hz = hz < TINY ? TINY : hz;
        float a = hx / M->ax, b = hy / M->ay;
        float e = (a * a + b * b) / (hz * hz);
        float c = wi[2] * wo[2];
        c = sqrtf(c < TINY ? TINY : c);
        lobe = expf(-e) / (M->pi4axay * c);
    }
    int up = (wi[2] > 0.0f) & (wo[2] > 0.0f);
    for (int c = 0; c < 3; c++) {
        float v = kind == 0 ? M->kd_pi[c] : M->kd_pi[c] + M->ks[c] * lobe;
        f[c] = fsel(up, v);
    }
}

/* cos(phi + 0) = cos(phi) bit for bit (phi >= 0 here); the + 0 keeps GCC from merging the sin and cos
   calls into one sincos (a complex result that the vectoriser does not take) */
#define NOSINCOS(x) ((x) + 0.0f)

static inline __attribute__((always_inline)) void from_cos_phi(float z, float u1, float *w) {
    float phi = (float)(2.0 * M_PI) * u1;
    float r = sqrtf(clamp0(1.0f - z * z));
    w[0] = r * cosf(NOSINCOS(phi)); w[1] = r * sinf(phi); w[2] = z;
}

static inline __attribute__((always_inline)) void reflect_about(const float *wo, const float *h, float *wi) {
    float k = 2.0f * (wo[0] * h[0] + wo[1] * h[1] + wo[2] * h[2]);
    for (int c = 0; c < 3; c++) wi[c] = k * h[c] - wo[c];
}

/* Material.sample's direction (its pdf: mat_pdf) */
static inline __attribute__((always_inline)) void mat_sample(const Mat *M, int kind, const float *wo, float u0, float u1, float *wi) {
    kind &= 7;  /* the sample has no integer power (its exponent is 1 / (s + 1)) */
    const float om = 1.0f - 1.1920928955078125e-07f;
    float a = u0 / M->pd_clamped;  /* clamp(0, om), by bit masks (see fsel) */
    a = fblend(a < 0.0f, 0.0f, fblend(a > om, om, a));
    from_cos_phi(sqrtf(clamp0(1.0f - a)), u1, wi);
    if (kind == 0) return;
    float us = (u0 - M->pd) / M->ps;
    us = us < 0.0f ? 0.0f : (us > om ? om : us);
    float w[3];
    const float cl = (float)(1.0 - 1e-7);
    if (kind == 1) {
        float Rx = -wo[0], Ry = -wo[1], Rz = wo[2];
        float nr = sqrtf(Rx * Rx + Ry * Ry + Rz * Rz);
        nr = nr < TINY ? TINY : nr;
        Rx = Rx / nr; Ry = Ry / nr; Rz = Rz / nr;
        float sg = Rz >= 0.0f ? 1.0f : -1.0f;
        float aa = -1.0f / (sg + Rz);
        float bb = Rx * Ry * aa;
        float sx = 1.0f + sg * Rx * Rx * aa, sy = sg * bb, sz = -sg * Rx;
        float tx = bb, ty = sg + Ry * Ry * aa, tz = -Ry;
        float l[3];
        from_cos_phi(powf(clamp0(1.0f - us), M->inv_s1), u1, l);
        w[0] = l[0] * sx + l[1] * tx + l[2] * Rx;
        w[1] = l[0] * sy + l[1] * ty + l[2] * Ry;
        w[2] = l[0] * sz + l[1] * tz + l[2] * Rz;
    } else {
        float h[3];
        if (kind == 2) {
            from_cos_phi(powf(clamp0(1.0f - us), M->inv_s1), u1, h);
        } else if (kind == 3) {
            float tan2 = M->neg_mm * log1pf(-(us > cl ? cl : us));
            from_cos_phi(1.0f / sqrtf(1.0f + tan2), u1, h);
        } else {
            float r = sqrtf(-log1pf(-(us > cl ? cl : us)));
            float phi = (float)(2.0 * M_PI) * u1;
            float sx = M->ax * r * cosf(NOSINCOS(phi)), sy = M->ay * r * sinf(phi);
            float nr = sqrtf(sx * sx + sy * sy + 1.0f);
            h[0] = sx / nr; h[1] = sy / nr; h[2] = 1.0f / nr;
        }
        reflect_about(wo, h, w);
    }
    int spec = M->has_spec & (u0 >= M->pd);  /* a select: the lobe's sample is computed anyway */
    for (int c = 0; c < 3; c++) wi[c] = spec ? w[c] : wi[c];
}

/* The per-sample frame (methods.core.frames.coordinate_system), w_o in it, ng on n's side. */
#define SAMPLE_SETUP                                                                              \
    const int64_t ir = i - ib;  /* the sample's row in n_, wo_, ng_, p_ */                      \
    float nx = n_[3 * ir], ny = n_[3 * ir + 1], nz = n_[3 * ir + 2];                              \
    float wv0 = wo_[3 * ir], wv1 = wo_[3 * ir + 1], wv2 = wo_[3 * ir + 2];                        \
    float sg = nz >= 0.0f ? 1.0f : -1.0f;                                                         \
    float aa = -1.0f / (sg + nz);                                                                 \
    float bb = nx * ny * aa;                                                                      \
    float s0 = 1.0f + sg * nx * nx * aa, s1 = sg * bb, s2 = -sg * nx;                             \
    float t0 = bb, t1 = sg + ny * ny * aa, t2 = -ny;                                              \
    float wol[3] = {s0 * wv0 + s1 * wv1 + s2 * wv2, t0 * wv0 + t1 * wv1 + t2 * wv2,               \
                    nx * wv0 + ny * wv1 + nz * wv2};                                              \
    float g0 = ng_[3 * ir], g1 = ng_[3 * ir + 1], g2 = ng_[3 * ir + 2];                           \
    float gs = (g0 * nx + g1 * ny + g2 * nz < 0.0f) ? -1.0f : 1.0f;                               \
    g0 = gs * g0; g1 = gs * g1; g2 = gs * g2;

/* f cos w, live, shadow-ray origin and direction of ray (j, i): slot-major rows j * QS + i of the
   component planes (PS apart) */
#define RAY_OUT                                                                                   \
    {                                                                                             \
        float f[3];                                                                               \
        mat_eval(&M, kind, wi, wol, f);                                                           \
        float cw = clamp0(wi[2]) * w;                                                             \
        int64_t r = j * QS + i;                                                                   \
        float c0 = f[0] * cw, c1 = f[1] * cw, c2 = f[2] * cw;                                     \
        contrib_[3 * r] = c0; contrib_[3 * r + 1] = c1; contrib_[3 * r + 2] = c2;                 \
        /* amax > 0 (NaN: not live), through a float select (a byte select does not vectorise) */ \
        float pos = ((c0 > 0.0f) | (c1 > 0.0f) | (c2 > 0.0f)) ? 1.0f : 0.0f;                      \
        float nan = ((c0 != c0) | (c1 != c1) | (c2 != c2)) ? 0.0f : 1.0f;                         \
        live_[r] = (uint8_t)(int32_t)(pos * nan);                                                 \
        float sd = g0 * dw[0] + g1 * dw[1] + g2 * dw[2];                                          \
        float side = (float)(sd > 0.0f) - (float)(sd < 0.0f);                                     \
        o_[r] = p_[3 * ir] + side * g0 * eps;                                                     \
        o_[PS + r] = p_[3 * ir + 1] + side * g1 * eps;                                            \
        o_[2 * PS + r] = p_[3 * ir + 2] + side * g2 * eps;                                        \
        d_[r] = dw[0]; d_[PS + r] = dw[1]; d_[2 * PS + r] = dw[2];                                \
    }

static inline __attribute__((always_inline)) float power_h(float a, float b) {
    float a2 = a * a, b2 = b * b;
    return a2 > 0.0f ? a2 / (a2 + b2) : 0.0f;
}

/* The env-map cells k[0:n] (n <= MAXB) of u0[0:n] (x: the same as double; overwritten): count_le(cdf, u0) by
   the guide table (methods.core.envguide.guided_count_le, GUIDE_STEPS = 4 bisection steps in the bucket),
   the u0 it does not bracket by count_le itself (fix_unguided). cdf0: 0 then the cdf (C + 1,); guide:
   (G + 1,). In two passes: the buckets' guide entries (independent loads, the cdf's and p_flat's lines there
   prefetched), then the steps (their loads mostly on those lines): one sample's search no longer waits
   on the last one's misses (guide table 0.5 MB, cdf 1 MB). Session 33: a pass before them prefetches the
   guide entries themselves (the same buckets' lines; pretrace 1.02-1.10x, creature / chess bench V and VB
   frame 1, 1 thread, the same bits). */
static inline __attribute__((always_inline)) void search_cells(const float *bu0, double *bx, int64_t n,
        const double *__restrict cdf0_, const double *__restrict pflat_, const int32_t *__restrict guide_, int64_t G,
        int64_t C, int32_t *bk) {
    int64_t bk64[MAXB], bok[MAXB], bhi[MAXB];
    int64_t top = 1;  /* count_le's first step: the largest power of 2 <= C */
    while (2 * top <= C) top *= 2;
    for (int64_t ii = 0; ii < n; ii++) {
        double x = bx[ii];
        double xs = ((x >= 0.0) & (x <= 1.0)) ? x : 0.0;
        int64_t b = (int32_t)floor(xs * (double)G);
        b = b < 0 ? 0 : (b > G - 1 ? G - 1 : b);
        __builtin_prefetch(guide_ + b);
    }
    for (int64_t ii = 0; ii < n; ii++) {
        double x = bx[ii];
        int64_t inside = (x >= 0.0) & (x <= 1.0);
        double xs = inside ? x : 0.0;
        int64_t b = (int32_t)floor(xs * (double)G);  /* G a power of 2: exact; via int32 (AVX2) */
        b = b < 0 ? 0 : (b > G - 1 ? G - 1 : b);
        int64_t lo = guide_[b], hi = guide_[b + 1];
        __builtin_prefetch(cdf0_ + lo);
        __builtin_prefetch(cdf0_ + lo + 8);
        __builtin_prefetch(pflat_ + lo);
        bk64[ii] = lo;
        bok[ii] = inside & (hi - lo < 16);
        bhi[ii] = hi;
        bx[ii] = xs;
    }
    for (int64_t ii = 0; ii < n; ii++) {
        double xs = bx[ii];
        int64_t k = bk64[ii], hi = bhi[ii];
#define GSTEP(step)                                                                               \
        {                                                                                     \
            int64_t jj = k + (step - 1);                                                      \
            jj = jj > C - 1 ? C - 1 : jj;                                                     \
            double cj = cdf0_[jj + 1];                                                        \
            k = ((k + step <= hi) & (cj <= xs)) ? k + step : k;                               \
        }
        GSTEP(8) GSTEP(4) GSTEP(2) GSTEP(1)
#undef GSTEP
        bk64[ii] = k;
    }
    for (int64_t ii = 0; ii < n; ii++) {
        bk[ii] = (int32_t)bk64[ii];
        if (bok[ii]) continue;
        double x = (double)bu0[ii];  /* scenes.envmap.count_le */
        int64_t k = 0;
        for (int64_t step = top; step; step >>= 1) {
            int64_t jj = k + (step - 1);
            jj = jj > C - 1 ? C - 1 : jj;
            if (k + step <= C && cdf0_[jj + 1] <= x) k += step;
        }
        bk[ii] = (int32_t)k;
    }
}

/* gather mode (PArgs.idx): the rows n, wo, ng, p of the samples i0 .. i1 - 1 of the call, copied from the
   G-buffer's arrays into g (4 x (3, MAXB) rows: n, wo, ng, p) — the values the gathered rows hold */
static void gather_rows(const PArgs *A, int64_t i0, int64_t i1, float *g) {
    const int64_t *idx = A->idx, *gf = A->gf;
    const float *gp = A->gp, *gn = A->gn, *gw = A->gw, *ngt = A->ngt;
    const int64_t s0 = A->gws0, s1 = A->gws1;
    float *bn = g, *bw = g + 3 * MAXB, *bg = g + 6 * MAXB, *bp = g + 9 * MAXB;
    for (int64_t i = i0; i < i1; i++) {
        const int64_t s = idx[i], r = 3 * (i - i0);
        const int64_t f = gf ? gf[s] : i;
        for (int c = 0; c < 3; c++) {
            bn[r + c] = gn[3 * s + c];
            bw[r + c] = gw[c * s0 + s * s1];
            bg[r + c] = ngt[3 * f + c];
            bp[r + c] = gp[3 * s + c];
        }
    }
}

static inline __attribute__((always_inline)) void block(const PArgs *A, const Mat *Mp, const int kind, int64_t i0, int64_t i1) {
    const Mat M = *Mp;
    const int64_t NL = A->NL, NB = A->NB, C = A->C, H = A->H, W = A->W, QS = A->QS, PS = A->PS;
    float grows[12 * MAXB];
    const int gathered = A->idx != 0;
    if (gathered)
        gather_rows(A, i0, i1, grows);
    const int64_t ib = gathered ? i0 : 0;  /* row of sample i: i - ib */
    const float *__restrict n_ = gathered ? grows : A->n, *__restrict wo_ = gathered ? grows + 3 * MAXB : A->wo;
    const float *__restrict ng_ = gathered ? grows + 6 * MAXB : A->ng, *__restrict p_ = gathered ? grows + 9 * MAXB : A->p;
    const float *__restrict ul_ = A->ul, *__restrict ub_ = A->ub;
    const double *__restrict cdf0_ = A->cdf0, *__restrict pflat_ = A->pflat, *__restrict omega_ = A->omega;
    const double *__restrict ztab_ = A->ztab;
    float *__restrict contrib_ = A->contrib, *__restrict o_ = A->o, *__restrict d_ = A->d;
    uint8_t *__restrict live_ = A->live;
    const float eps = A->eps;
    double R[9];
    for (int c = 0; c < 9; c++) R[c] = A->R[c];
    const float fnl = (float)NL, fnb = (float)NB;
    float bu0[MAXB], bu1[MAXB];
    int32_t bk[MAXB];
    int64_t bk64[MAXB], bok[MAXB], bhi[MAXB];
    double bx[MAXB];
    const int32_t *__restrict guide_ = A->guide;
    const int64_t G = A->G;
    int64_t top = 1;  /* count_le's first step: the largest power of 2 <= C */
    while (2 * top <= C) top *= 2;
    for (int64_t j = 0; j < NL; j++) {
        const int64_t n = i1 - i0;
        for (int64_t i = i0; i < i1; i++) {  /* the slot's uniforms, contiguous */
            bu0[i - i0] = ul_[2 * (i * NL + j)]; bu1[i - i0] = ul_[2 * (i * NL + j) + 1];
            bx[i - i0] = (double)bu0[i - i0];
        }
        search_cells(bu0, bx, n, cdf0_, pflat_, guide_, G, C, bk);
#pragma GCC ivdep
        for (int64_t i = i0; i < i1; i++) {
            SAMPLE_SETUP
            /* scenes.envmap.sample_cells after its search (methods.core.envguide.sample_cells_at), float64 */
            double u0 = (double)bu0[i - i0], u1 = (double)bu1[i - i0];
            int32_t k = bk[i - i0];
            k = k > C - 1 ? (int32_t)(C - 1) : k;
            double lo = cdf0_[k];  /* cdf[k - 1], 0 for k = 0 (cdf0: the cdf after a 0) */
            double pk = pflat_[k];
            double r = (u0 - lo) / (pk < 1e-300 ? 1e-300 : pk);
            r = r < 0.0 ? 0.0 : (r > 1.0 ? 1.0 : r);
            /* k // W, k % W in int32 (vector) arithmetic: the double quotient's floor, corrected */
            int32_t iy = (int32_t)(float)((double)k / (double)W);  /* via float: AVX2 converts 8 lanes */
            iy = iy * (int32_t)W > k ? iy - 1 : iy;
            iy = (iy + 1) * (int32_t)W <= k ? iy + 1 : iy;
            int32_t ix = k - iy * (int32_t)W;
            double phi = 2 * M_PI * ((double)ix + 0.5 + r) / (double)W;
            double zt = ztab_[iy], zb = ztab_[iy + 1];
            double zc = zt - u1 * (zt - zb);
            double st = 1 - zc * zc;
            st = sqrt(st < 0.0 ? 0.0 : st);
            double l0 = sin(phi) * st, l1 = zc, l2 = -cos(phi + 0.0) * st;  /* + 0: NOSINCOS */
            float pdf_l = (float)(pk / omega_[iy]);
            float dw[3];
            dw[0] = (float)(l0 * R[0] + l1 * R[1] + l2 * R[2]);
            dw[1] = (float)(l0 * R[3] + l1 * R[4] + l2 * R[5]);
            dw[2] = (float)(l0 * R[6] + l1 * R[7] + l2 * R[8]);
            float wi[3] = {s0 * dw[0] + s1 * dw[1] + s2 * dw[2], t0 * dw[0] + t1 * dw[1] + t2 * dw[2],
                           nx * dw[0] + ny * dw[1] + nz * dw[2]};
            float pdf_b = mat_pdf(&M, kind, wi, wol);
            float w = power_h(pdf_l, pdf_b) / (pdf_l < 1e-30f ? 1e-30f : pdf_l) / fnl;
            w = pdf_l > 0.0f ? w : 0.0f;
            RAY_OUT
        }
    }
    for (int64_t jb = 0; jb < NB; jb++) {
        const int64_t j = NL + jb;
        for (int64_t i = i0; i < i1; i++) {
            bu0[i - i0] = ub_[2 * (i * NB + jb)]; bu1[i - i0] = ub_[2 * (i * NB + jb) + 1];
        }
#pragma GCC ivdep
        for (int64_t i = i0; i < i1; i++) {
            SAMPLE_SETUP
            float wi[3];
            mat_sample(&M, kind, wol, bu0[i - i0], bu1[i - i0], wi);
            float pdf_b = mat_pdf(&M, kind, wi, wol);
            float dw[3] = {wi[0] * s0 + wi[1] * t0 + wi[2] * nx, wi[0] * s1 + wi[1] * t1 + wi[2] * ny,
                           wi[0] * s2 + wi[1] * t2 + wi[2] * nz};
            /* scenes.envmap.cell_pdf, float64 (0 without light samples: a select) */
            double e0 = dw[0], e1 = dw[1], e2 = dw[2];
            double x = e0 * R[0] + e1 * R[3] + e2 * R[6];
            double y = e0 * R[1] + e1 * R[4] + e2 * R[7];
            double z = e0 * R[2] + e1 * R[5] + e2 * R[8];
            double u = atan2(x, -z) * (0.5 / M_PI);
            double v = acos(y < -1.0 ? -1.0 : (y > 1.0 ? 1.0 : y)) * (1.0 / M_PI);
            /* u in [-1/2, 1/2]: floor(u W - 1/2) in [-W/2 - 1, W/2 - 1]; torch.remainder by W */
            int32_t cx = (int32_t)(float)floor(u * (double)W - 0.5);  /* an integer: exact in float */
            cx = cx < 0 ? cx + (int32_t)W : cx;
            cx = cx >= W ? cx - (int32_t)W : cx;
            int32_t cy = (int32_t)(float)floor(v * (double)(H - 1));
            cy = cy < 0 ? 0 : (cy > H - 2 ? (int32_t)(H - 2) : cy);
            float pc = (float)(pflat_[cy * (int32_t)W + cx] / omega_[cy]);
            float pdf_l = NL ? pc : 0.0f;
            float w = power_h(pdf_b, pdf_l) / (pdf_b < 1e-30f ? 1e-30f : pdf_b) / fnb;
            w = pdf_b > 0.0f ? w : 0.0f;
            RAY_OUT
        }
    }
}

/* ipow over n values (`int_pow`, a test's entry) */
void int_pow(const float *x, int64_t n, int32_t e, float *out) {
    for (int64_t i = 0; i < n; i++) out[i] = ipow(x[i], e);
}

/* search_cells on n uniforms u0 (the light samples' cells alone: `light_cells`, a test's entry) */
void light_cells(const float *u0, int64_t n, const double *cdf0, const double *pflat, const int32_t *guide, int64_t G,
                 int64_t C, int32_t *k) {
    double bx[MAXB];
    for (int64_t a = 0; a < n; a += MAXB) {
        int64_t m = n - a < MAXB ? n - a : MAXB;
        for (int64_t i = 0; i < m; i++) bx[i] = (double)u0[a + i];
        search_cells(u0 + a, bx, m, cdf0, pflat, guide, G, C, k + a);
    }
}

void pretrace(const PArgs *A, int64_t block_rows, int32_t nt) {
    Mat M;
    M.kind = A->kind; M.has_spec = A->has_spec;
    for (int c = 0; c < 3; c++) { M.kd_pi[c] = (float)A->kd[c] / PI_F; M.ks[c] = (float)A->ks[c]; }
    M.ps = (float)A->ps; M.pd = (float)(1.0 - A->ps); M.pd_clamped = (float)(1.0 - A->ps < 1e-12 ? 1e-12 : 1.0 - A->ps);
    M.s = (float)A->s;
    M.si = (A->s == floor(A->s) && A->s >= 0.0 && A->s < 128.0 && (double)M.s == A->s) ? (int)A->s : -1;
    M.pnorm_phong = (float)((A->s + 1.0) / (2.0 * M_PI));
    M.bnorm = (float)((A->s + 2.0) / (8.0 * M_PI));
    M.inv_s1 = (float)(1.0 / (A->s + 1.0));
    M.mm = (float)(A->m * A->m); M.pimm = (float)(M_PI * A->m * A->m); M.neg_mm = (float)(-(A->m * A->m));
    M.F0 = (float)A->F0; M.omF0 = (float)(1.0 - A->F0);
    M.ax = (float)A->ax; M.ay = (float)A->ay;
    M.piaxay = (float)(M_PI * A->ax * A->ay); M.pi4axay = (float)(4.0 * M_PI * A->ax * A->ay);
    int64_t nb = (A->Q + block_rows - 1) / block_rows;
#pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t b = 0; b < nb; b++) {
        int64_t i0 = b * block_rows, i1 = i0 + block_rows < A->Q ? i0 + block_rows : A->Q;
        switch (M.kind) {
        case 0: block(A, &M, 0, i0, i1); break;
        case 1: if (M.si >= 0) block(A, &M, 1 | 8, i0, i1); else block(A, &M, 1, i0, i1); break;
        case 2: if (M.si >= 0) block(A, &M, 2 | 8, i0, i1); else block(A, &M, 2, i0, i1); break;
        case 3: block(A, &M, 3, i0, i1); break;
        default: block(A, &M, 4, i0, i1); break;
        }
    }
}

/* Sum over a sample's K rays of contribution * radiance where lit = live and not blocked
   (methods.oracle._shade_stage: scenes.envmap.bilinear_lookup of d @ R in float32, the unlit a fixed
   direction +y counted 0); contributions (K, Q, 3), directions (3, K, Q) component planes PS apart. */
static void shade_rows(const float *__restrict contrib, const uint8_t *__restrict live,
                       const uint8_t *__restrict blocked, const float *__restrict d, const float *__restrict ext,
                       const float *__restrict Rp, int64_t Q, int64_t K, int64_t H, int64_t W,
                       int64_t PS, float *__restrict out, int64_t i0, int64_t i1, int64_t ob) {
    const float hw = (float)(0.5 / W), fW = (float)W, fH1 = (float)(H - 1);
    const float i2pi = (float)(0.5 / M_PI), ipi = (float)(1.0 / M_PI);
    float R[9];
    for (int c = 0; c < 9; c++) R[c] = Rp[c];
    for (int64_t i = i0; i < i1; i++) { out[3 * (i - ob)] = 0.0f; out[3 * (i - ob) + 1] = 0.0f; out[3 * (i - ob) + 2] = 0.0f; }
    int32_t bidx[MAXB];
    float bfx[MAXB], bfy[MAXB], bl[MAXB];
    for (int64_t k = 0; k < K; k++) {
        /* two passes over the block (i1 - i0 <= MAXB): the texel coordinates, their rows prefetched,
           then the taps (the env map's texels, 1.5 MB, no longer waited for one ray after another) */
#pragma GCC ivdep
        for (int64_t i = i0; i < i1; i++) {
            int64_t r = k * Q + i;
            int l = (live[r] != 0) & (blocked[r] == 0);
            float dx = d[r], dy = d[PS + r], dz = d[2 * PS + r];
            float x = l ? dx : 0.0f, y = l ? dy : 1.0f, z = l ? dz : 0.0f;
            float xl = x * R[0] + y * R[3] + z * R[6];
            float yl = x * R[1] + y * R[4] + z * R[7];
            float zl = x * R[2] + y * R[5] + z * R[8];
            float u = atan2f(xl, -zl) * i2pi;
            float v = acosf(yl < -1.0f ? -1.0f : (yl > 1.0f ? 1.0f : yl)) * ipi;
            u = u - hw;
            u = u - floorf(u);
            v = v - floorf(v);
            float fx = u * fW, fy = v * fH1;
            int32_t ix = (int32_t)fx, iy = (int32_t)fy;
            ix = ix > W - 1 ? (int32_t)(W - 1) : ix;
            iy = iy > H - 2 ? (int32_t)(H - 2) : iy;
            int32_t idx = iy * (int32_t)(W + 1) + ix;
            bidx[i - i0] = idx;
            bfx[i - i0] = fx - (float)ix; bfy[i - i0] = fy - (float)iy;
            bl[i - i0] = (float)l;
        }
        for (int64_t i = i0; i < i1; i++) {
            const float *t = ext + 3 * (int64_t)bidx[i - i0];
            __builtin_prefetch(t);
            __builtin_prefetch(t + 5);
            __builtin_prefetch(t + 3 * (W + 1));
            __builtin_prefetch(t + 3 * (W + 1) + 5);
        }
#pragma GCC ivdep
        for (int64_t i = i0; i < i1; i++) {
            int64_t r = k * Q + i;
            int l = bl[i - i0] != 0.0f;
            int32_t idx = bidx[i - i0];
            float fx = bfx[i - i0], fy = bfy[i - i0];
            float w0x = 1.0f - fx, w0y = 1.0f - fy;
#define TAP(c)                                                                                    \
            {                                                                                     \
                float v0 = w0x * ext[3 * idx + c] + fx * ext[3 * (idx + 1) + c];                 \
                float v1 = w0x * ext[3 * (idx + W + 1) + c] + fx * ext[3 * (idx + W + 2) + c];   \
                float L = w0y * v0 + fy * v1;                                                     \
                L = l ? L : 0.0f;                                                                 \
                out[3 * (i - ob) + c] = out[3 * (i - ob) + c] + contrib[3 * r + c] * L;           \
            }
            TAP(0) TAP(1) TAP(2)
#undef TAP
        }
    }
}

/* The live rays (live (n,) nonzero, in order) of the component planes o, d (PS apart) into the
   (m, 3) rows oc, dc: count[0] = m (the fallback tracer's input, `trace`). */
void compact(const uint8_t *live, const float *o, const float *d, int64_t n, int64_t PS, float *oc, float *dc,
             int64_t *count) {
    int64_t m = 0;
    for (int64_t r = 0; r < n; r++) {  /* branchless: every ray written at m (<= r < n), kept if live */
        oc[3 * m] = o[r]; oc[3 * m + 1] = o[PS + r]; oc[3 * m + 2] = o[2 * PS + r];
        dc[3 * m] = d[r]; dc[3 * m + 1] = d[PS + r]; dc[3 * m + 2] = d[2 * PS + r];
        m += live[r] != 0;
    }
    count[0] = m;
}

/* blocked of every ray (0 where not live) from blocked per live ray, in compact's order */
void expand_blocked(const uint8_t *live, const uint8_t *blocked_live, int64_t n, uint8_t *blocked) {
    int64_t m = 0;
    for (int64_t r = 0; r < n; r++) {
        uint8_t l = live[r] != 0;
        blocked[r] = l ? (uint8_t)(blocked_live[m] != 0) : 0;
        m += l;
    }
}

/* out: (Q, 3) rows; or, idx non-NULL, sample i's sum written to out[c * OP + idx[i]] (channel planes OP apart:
   the G-buffer's (3, P) channel-major radiance, `shade`'s scatter) */
void shade(const float *contrib, const uint8_t *live, const uint8_t *blocked, const float *d, const float *ext,
           const float *R, int64_t Q, int64_t K, int64_t H, int64_t W, int64_t PS, float *out, int64_t block_rows,
           int32_t nt, const int64_t *idx, int64_t OP) {
    int64_t nb = (Q + block_rows - 1) / block_rows;
#pragma omp parallel for num_threads(nt) schedule(static)
    for (int64_t b = 0; b < nb; b++) {
        int64_t i0 = b * block_rows, i1 = i0 + block_rows < Q ? i0 + block_rows : Q;
        if (!idx) {
            shade_rows(contrib, live, blocked, d, ext, R, Q, K, H, W, PS, out, i0, i1, 0);
            continue;
        }
        float acc[3 * MAXB];
        shade_rows(contrib, live, blocked, d, ext, R, Q, K, H, W, PS, acc, i0, i1, i0);
        for (int64_t i = i0; i < i1; i++)
            for (int c = 0; c < 3; c++)
                out[c * OP + idx[i]] = acc[3 * (i - i0) + c];
    }
}

/* A frame's samples and frame_cost's counts in one pass (`frame_rows`): order (P,) the hit samples whose
   region r is in [0, R), region after region, ascending within a region (torch.nonzero((region == r) & hit)
   for r = 0 .. R-1, concatenated); counts (R,) of each; stats = (hit samples, faces hit — face[s] of the hit
   samples, a negative index from the end as torch indexes —, their distinct vertices). fflag (M,), vflag (N,):
   scratch. */
void frame_rows(const uint8_t *hit, const int64_t *region, const int64_t *face, int64_t P, int64_t R,
                int64_t *order, int64_t *counts, const int64_t *F, int64_t M, int64_t N, uint8_t *fflag,
                uint8_t *vflag, int64_t *stats) {
    int64_t hits = 0, faces = 0, verts = 0;
    memset(fflag, 0, (size_t)M);
    memset(vflag, 0, (size_t)N);
    for (int64_t r = 0; r < R; r++) counts[r] = 0;
    for (int64_t s = 0; s < P; s++) {
        if (!hit[s]) continue;
        hits++;
        int64_t f = face[s];
        f = f < 0 ? f + M : f;
        if (f >= 0 && f < M) fflag[f] = 1;
        int64_t r = region[s];
        if (r >= 0 && r < R) counts[r]++;
    }
    int64_t off[R > 0 ? R : 1], acc = 0;
    for (int64_t r = 0; r < R; r++) { off[r] = acc; acc += counts[r]; }
    for (int64_t s = 0; s < P; s++) {
        int64_t r = region[s];
        if (hit[s] && r >= 0 && r < R) order[off[r]++] = s;
    }
    for (int64_t f = 0; f < M; f++) {
        if (!fflag[f]) continue;
        faces++;
        for (int c = 0; c < 3; c++) {
            int64_t v = F[3 * f + c];
            v = v < 0 ? v + N : v;
            if (v >= 0 && v < N) vflag[v] = 1;
        }
    }
    for (int64_t v = 0; v < N; v++) verts += vflag[v];
    stats[0] = hits; stats[1] = faces; stats[2] = verts;
}

/* torch's CPU generator (at::mt19937) from its state (st: the 624 words; ln: its left_, next_): n
   uniform floats in [0, 1) exactly as torch.rand draws them ((word & (2^24 - 1)) * 2^-24), the state
   advanced as torch advances it. The twist's loops vectorise (their reads run ahead of their writes
   or 227 words behind them), the tempering too. */
#define MT_N 624
#define MT_M 397
static inline uint32_t mt_twist(uint32_t u, uint32_t v) {
    return (((u & 0x80000000u) | (v & 0x7fffffffu)) >> 1) ^ ((v & 1u) ? 0x9908b0dfu : 0u);
}

void mt_uniform(uint32_t *__restrict st, int64_t *ln, float *__restrict out, int64_t n) {
    int64_t left = ln[0], nx = ln[1], i = 0;
    while (i < n) {
        if (left == 1) {  /* the draw that finds left_ at 1: next_state(), then word 0 */
            uint32_t nw[MT_N];
#pragma GCC ivdep
            for (int j = 0; j < MT_N - MT_M; j++) nw[j] = st[j + MT_M] ^ mt_twist(st[j], st[j + 1]);
            for (int j = MT_N - MT_M; j < MT_N - 1; j++) nw[j] = nw[j + MT_M - MT_N] ^ mt_twist(st[j], st[j + 1]);
            nw[MT_N - 1] = nw[MT_M - 1] ^ mt_twist(st[MT_N - 1], nw[0]);
            memcpy(st, nw, sizeof nw);
            left = MT_N + 1;
            nx = 0;
        }
        int64_t m = left - 1 < n - i ? left - 1 : n - i;
        const uint32_t *w = st + nx;
        float *o = out + i;
        for (int64_t k = 0; k < m; k++) {
            uint32_t y = w[k];
            y ^= (y >> 11);
            y ^= (y << 7) & 0x9d2c5680u;
            y ^= (y << 15) & 0xefc60000u;
            y ^= (y >> 18);
            o[k] = (float)(int32_t)(y & 0xffffffu) * 5.9604644775390625e-08f;
        }
        i += m; left -= m; nx += m;
    }
    ln[0] = left; ln[1] = nx;
}
"""


class _PArgs(ctypes.Structure):
    _fields_ = [("n", ctypes.c_void_p), ("wo", ctypes.c_void_p), ("ng", ctypes.c_void_p), ("p", ctypes.c_void_p),
                ("ul", ctypes.c_void_p), ("ub", ctypes.c_void_p),
                ("cdf0", ctypes.c_void_p), ("pflat", ctypes.c_void_p), ("omega", ctypes.c_void_p),
                ("ztab", ctypes.c_void_p), ("R", ctypes.c_void_p), ("guide", ctypes.c_void_p), ("G", ctypes.c_int64),
                ("Q", ctypes.c_int64), ("NL", ctypes.c_int64), ("NB", ctypes.c_int64), ("C", ctypes.c_int64),
                ("H", ctypes.c_int64), ("W", ctypes.c_int64), ("QS", ctypes.c_int64), ("PS", ctypes.c_int64),
                ("eps", ctypes.c_float),
                ("kind", ctypes.c_int32), ("has_spec", ctypes.c_int32),
                ("kd", ctypes.c_double * 3), ("ks", ctypes.c_double * 3), ("ps", ctypes.c_double),
                ("s", ctypes.c_double), ("m", ctypes.c_double), ("F0", ctypes.c_double),
                ("ax", ctypes.c_double), ("ay", ctypes.c_double),
                ("contrib", ctypes.c_void_p), ("o", ctypes.c_void_p), ("d", ctypes.c_void_p),
                ("live", ctypes.c_void_p),
                ("idx", ctypes.c_void_p), ("gp", ctypes.c_void_p), ("gn", ctypes.c_void_p), ("gw", ctypes.c_void_p),
                ("ngt", ctypes.c_void_p), ("gws0", ctypes.c_int64), ("gws1", ctypes.c_int64), ("gf", ctypes.c_void_p)]


_P, _I = ctypes.c_void_p, ctypes.c_int64
_MITSUBA_OCCLUDED = MitsubaVisibility.occluded
_SIGNATURES = {"pretrace": [_P, _I, ctypes.c_int32], "light_cells": [_P, _I, _P, _P, _P, _I, _I, _P], "int_pow": [_P, _I, ctypes.c_int32, _P], "compact": [_P, _P, _P, _I, _I, _P, _P, _P],
               "expand_blocked": [_P, _P, _I, _P], "mt_uniform": [_P, _P, _P, _I],
               "frame_rows": [_P, _P, _P, _I, _I, _P, _P, _P, _I, _I, _P, _P, _P],
               "shade": [_P, _P, _P, _P, _P, _P, _I, _I, _I, _I, _I, _P, _I, ctypes.c_int32, _P, _I]}


def _lib():
    # not cached here: `native.load` caches the build and reads PRTBENCH_COMPILE at each call, so a
    # None met while compilation was off (a test's monkeypatch) is not kept for the process
    # libmvec: the vector variants of the math functions (module docstring); linked explicitly
    return native.load("oracle_rays", _SOURCE, _SIGNATURES,
                       extra_flags=("-fopenmp", "-ffp-contract=off", "-fno-trapping-math", *native.isa_flags(),
                                    "-Wl,--no-as-needed", "-lmvec", "-lm"))


# `pretrace`'s library on an AVX-512 host (``native.cpu_capability()``): the same source built for 512-bit
# vectors (GCC then takes libmvec's 16-lane float / 8-lane double variants of sin, cos, atan2, acos, powf, ...
# where the AVX2 build takes its 8 / 4-lane ones). Session 33, creature bench V frame 1, 1 thread, captured
# arguments (`benchmarks.oracle_native_ab`): pretrace 1.19-1.23x (AVX-512 at 256-bit width: 1.19x); `shade`
# measured 0.88x at 512 bits and stays in the AVX2 build (`_lib`). Another vector width of the same
# functions: results an ulp or so apart where libmvec's variants are (float32 round-off of the same
# operations, as the AVX2 build against torch's Sleef); the test compares the two builds.
AVX512_FLAGS = ("-mavx512f", "-mavx512dq", "-mavx512vl", "-mavx512bw", "-mprefer-vector-width=512")


def _ray_lib():
    """The library `pretrace` (and its parts' test entries `light_cells`, `int_pow`) run: the AVX-512 build
    on an AVX-512 host (`AVX512_FLAGS`), else — or when that build fails — `_lib`'s; None as `_lib`."""
    if native.cpu_capability() == "AVX512":
        lib = native.load("oracle_rays512", _SOURCE, _SIGNATURES,
                          extra_flags=("-fopenmp", "-ffp-contract=off", "-fno-trapping-math", *native.isa_flags(),
                                       *AVX512_FLAGS, "-Wl,--no-as-needed", "-lmvec", "-lm"))
        if lib is not None:
            return lib
    return _lib()


def available() -> bool:
    """True when the C loops run (else the caller takes the compiled path)."""
    return _lib() is not None


def supports(mat) -> bool:
    """Whether ``mat`` (a library material, ``scenes.materials``) has a C body (`KINDS`)."""
    return type(mat).__module__ == "scenes.materials" and getattr(mat, "kind", None) in KINDS


def _threads(q: int) -> int:
    return max(1, min(torch.get_num_threads(), q // MIN_PER_THREAD))


@functools.lru_cache(maxsize=8)
def _ztab(H: int) -> Tensor:
    """cos(π·iy/(H − 1)) for iy = 0 … H − 1, as ``scenes.envmap.sample_cells`` computes z_top / z_bot
    (the same float64 expression, so the same values)."""
    iy = torch.arange(H, dtype=torch.int64)
    return torch.cos(math.pi * iy.double() / (H - 1))


_CDF0: list = [None, None]  # (the cdf, its `_cdf0`) of the last call (an env map's tables are reused)


def _cdf0(cdf: Tensor) -> Tensor:
    """(C + 1,) float64: 0, then ``cdf`` — cdf0[k] is the probability below cell k (``sample_cells``' lo)."""
    if _CDF0[0] is not cdf:
        _CDF0[:] = [cdf, torch.cat([cdf.new_zeros(1), cdf])]
    return _CDF0[1]


def _ptr(t: Tensor) -> int:
    return t.data_ptr()


class Rows:
    """The G-buffer rows of a call's samples, read by the C loops themselves (`pretrace`'s gather mode, or35):
    ``idx`` (Q,) int64 contiguous, the samples' G-buffer rows; ``position``, ``normal`` (P, 3) float32
    contiguous; ``wo`` (P, 3) float32, any strides (ω_o's (3, P) channel planes transposed, say); ``ng`` the
    geometric normals, (F, 3) float32 contiguous per face with ``face`` (P,) int64 contiguous, or (Q, 3) rows
    of the call's samples with ``face`` None. `pretrace` then reads each block's rows into a block buffer —
    the values ``position[idx]`` etc. (``Oracle._gather``) hold — instead of rows gathered by torch before."""

    def __init__(self, idx: Tensor, position: Tensor, normal: Tensor, wo: Tensor, ng: Tensor, face: Tensor | None):
        ok = (idx.dtype == torch.int64 and idx.dim() == 1 and idx.is_contiguous()
              and all(x.dtype == torch.float32 and x.dim() == 2 and x.shape[1] == 3 for x in (position, normal, wo, ng))
              and position.is_contiguous() and normal.is_contiguous() and ng.is_contiguous()
              and position.shape == normal.shape == wo.shape
              and (face is None and ng.shape[0] == idx.shape[0]
                   or face is not None and face.dtype == torch.int64 and face.is_contiguous()
                   and face.shape == position.shape[:1]))
        if not ok:
            raise ValueError("Rows: idx (Q,) int64, position / normal (P, 3) float32 contiguous, wo (P, 3) float32, "
                             "ng (F, 3) with face (P,) int64 or (Q, 3) rows with face None")
        self.idx, self.position, self.normal, self.wo, self.ng, self.face = idx, position, normal, wo, ng, face

    def __getitem__(self, sl: slice) -> "Rows":
        """The rows of the samples ``idx[sl]`` (a step-1 slice)."""
        ng = self.ng if self.face is not None else self.ng[sl]
        return Rows(self.idx[sl], self.position, self.normal, self.wo, ng, self.face)


def pretrace(mat, n: Tensor | Rows, wo: Tensor, ng: Tensor, p: Tensor, U_l: Tensor, U_b: Tensor, NL: int, NB: int,
             tables: tuple, H: int, W: int, eps: float, out: tuple[Tensor, Tensor, Tensor, Tensor]) -> None:
    """The rays of Q samples of one region (material ``mat``, `supports`) into ``out`` = (contributions
    f·cos·w, live (bool), shadow-ray origins, world directions), row slices [:, a:b] of (K, QS, 3) resp.
    (K, QS) contiguous arrays, origins and directions [..., a:b] of (3, K, QS) component planes
    (`plane_views`: each plane contiguous, the tracer's input as it is) (rays slot-major), K = NL + NB, light samples first. n, wo, ng, p: (Q, 3)
    float32 contiguous; U_l (Q, NL, 2), U_b (Q, NB, 2) float32 contiguous (ignored when NL resp. NB is
    0); tables = (cdf (C,), p_flat (C,), omega (H − 1,), R (3, 3)) float64 contiguous. The light
    samples' env-map cells are searched here (``Oracle._light_cells``' result, by the same guide table).
    ``n`` a `Rows` (``wo``, ``ng``, ``p`` then ignored): the samples' rows read from the G-buffer by the C loops
    (gather mode), the same outputs."""
    lib = _ray_lib()
    rows = n if isinstance(n, Rows) else None
    Q = int(rows.idx.shape[0] if rows is not None else n.shape[0])
    if Q == 0:
        return
    cdf, p_flat, omega, R = tables
    a = _PArgs()
    if rows is None:
        a.n, a.wo, a.ng, a.p = _ptr(n), _ptr(wo), _ptr(ng), _ptr(p)
    else:
        a.idx, a.gp, a.gn, a.gw, a.ngt = (_ptr(x) for x in (rows.idx, rows.position, rows.normal, rows.wo, rows.ng))
        a.gws0, a.gws1 = int(rows.wo.stride(1)), int(rows.wo.stride(0))
        a.gf = _ptr(rows.face) if rows.face is not None else None
    a.ul, a.ub = _ptr(U_l), _ptr(U_b)
    zt, guide = _ztab(H), guide_table(cdf)
    a.cdf0, a.pflat, a.omega, a.ztab, a.R = _ptr(_cdf0(cdf)), _ptr(p_flat), _ptr(omega), _ptr(zt), _ptr(R)
    a.guide, a.G = _ptr(guide), int(guide.shape[0]) - 1
    a.Q, a.NL, a.NB, a.C, a.H, a.W = Q, NL, NB, int(cdf.shape[0]), H, W
    a.eps = float(eps)
    a.kind, a.has_spec = KINDS[mat.kind], int(mat.spec_weight > 0)
    a.kd[:] = [float(x) for x in mat.kd]
    a.ks[:] = [float(x) for x in mat.ks_rgb]
    a.ps = float(mat.spec_weight)
    for f in ("s", "m", "F0", "ax", "ay"):
        setattr(a, f, float(getattr(mat, f, 1.0)))
    contrib, live, o, d = out
    if not (all(x.dim() == 3 and x.shape[0] == 3 and x.stride()[1:] == live.stride() for x in (o, d))
            and live.stride(1) == 1 and o.stride(0) == d.stride(0) >= live.numel()
            and contrib.stride() == (3 * live.stride(0), 3, 1)):
        raise ValueError("pretrace: outputs must be row slices of (K, QS, 3) / (K, QS) contiguous arrays and of "
                         "(3, K, QS) component planes (each contiguous, the same plane stride)")
    a.QS, a.PS = int(live.stride(0)), int(o.stride(0))
    a.contrib, a.live, a.o, a.d = _ptr(contrib), _ptr(live), _ptr(o), _ptr(d)
    lib.pretrace(ctypes.byref(a), BLOCK, _threads(Q))  # BLOCK <= MAXB


def light_cells(u0: Tensor, cdf: Tensor, p_flat: Tensor) -> Tensor:
    """The env-map cells (n,) int32 that `pretrace` samples for the light uniforms u₀ (n,) float32 — its
    search alone (``scenes.envmap.count_le(cdf, u₀)`` by the guide table; the test's entry); cdf and
    p_flat (C,) float64 (``EnvMap._tables``)."""
    u0, p_flat = u0.contiguous(), p_flat.contiguous()
    guide = guide_table(cdf)
    k = torch.empty(u0.shape[0], dtype=torch.int32)
    _ray_lib().light_cells(_ptr(u0), int(u0.shape[0]), _ptr(_cdf0(cdf)), _ptr(p_flat), _ptr(guide), int(guide.shape[0]) - 1,
                       int(cdf.shape[0]), _ptr(k))
    return k


def int_pow(x: Tensor, e: int) -> Tensor:
    """x ** e (x float32 (n,), e an int in [0, 127]) as `pretrace` computes the Phong / Blinn-Phong lobes'
    powers of integer exponents (``ipow``: float64 products rounded once; the test's entry)."""
    if not 0 <= e < 128:
        raise ValueError(f"e must be in [0, 127], got {e}")
    x = x.contiguous()
    out = torch.empty_like(x)
    _ray_lib().int_pow(_ptr(x), int(x.numel()), int(e), _ptr(out))
    return out


def plane_views(buf: Tensor, K: int, Q: int) -> Tensor:
    """(3, K, Q) component planes on a flat float32 ``buf`` of at least `plane_numel` (K·Q) elements,
    each plane contiguous, planes `plane_stride` apart (not a multiple of 4 KiB: planes a power of 2
    apart — creature's 8 × 2¹⁸ rays — would map a ray's three components to one cache set)."""
    PS = plane_stride(K * Q)
    return buf[:3 * PS].view(3, PS)[:, :K * Q].view(3, K, Q)


def plane_stride(n: int) -> int:
    """Elements between the component planes of n rays (`plane_views`): n rounded up to 16 (64-byte
    rows) plus 17 × 16 (an odd number of cache lines)."""
    return -(-n // 16) * 16 + 17 * 16


def _direct(vis) -> bool:
    """Whether ``vis`` is Mitsuba's tracer (``references.visibility.MitsubaVisibility``) with its own
    ``occluded`` (not replaced on the class or the instance, e.g. by a benchmark timing or capturing
    it): `trace` then hands it the rays without gathering them."""
    return (type(vis) is MitsubaVisibility and type(vis).occluded is _MITSUBA_OCCLUDED
            and "occluded" not in vars(vis))


def trace(vis, live: Tensor, o: Tensor, d: Tensor, blocked: Tensor) -> int:
    """Shadow rays of live (K, Q) bool, origins and world directions (3, K, Q) float32 component planes
    (each contiguous; `plane_views`): whether each live ray is blocked into ``blocked`` ((K, Q) bool contiguous; False where
    not live) → the number of live rays. On Mitsuba's tracer (`_direct`) the planes are handed to
    ``scene.ray_test`` as they are (Dr.Jit maps the arrays, no copy) with ``live`` as its active mask,
    in chunks of the tracer's ``chunk_rays``: the rays that are not live are not traced, and Mitsuba's
    answer for a ray depends on that ray only (``references.visibility``), so it is the answer of
    ``occluded`` on the live rays alone. Else (embreex, an instrumented tracer) the live rays are
    gathered in order (C) and traced in one ``vis.occluded`` call."""
    lib = _lib()
    n = live.numel()
    m = int(torch.count_nonzero(live))
    if not m:
        blocked.zero_()
        return 0
    if _direct(vis):
        import mitsuba as mi

        lv, bo = live.view(-1).numpy(), blocked.view(-1).numpy()
        op = [o[c].reshape(-1).numpy() for c in range(3)]
        dp = [d[c].reshape(-1).numpy() for c in range(3)]
        for a in range(0, n, vis.chunk_rays):
            b = min(n, a + vis.chunk_rays)
            ray = mi.Ray3f(mi.Point3f(*(mi.Float(x[a:b]) for x in op)), mi.Vector3f(*(mi.Float(x[a:b]) for x in dp)))
            bo[a:b] = vis._scene.ray_test(ray, mi.Bool(lv[a:b])).numpy()
        return m
    oc, dc = torch.empty(n, 3), torch.empty(n, 3)
    cnt = torch.zeros(1, dtype=torch.int64)
    lib.compact(_ptr(live), _ptr(o), _ptr(d), n, int(o.stride(0)), _ptr(oc), _ptr(dc), _ptr(cnt))
    assert int(cnt[0]) == m
    bl = torch.as_tensor(vis.occluded(oc[:m], dc[:m])).to(torch.bool).contiguous()
    if bl.shape != (m,):
        raise ValueError(f"occluded returned {tuple(bl.shape)} for {m} rays")
    lib.expand_blocked(_ptr(live), _ptr(bl), n, _ptr(blocked))
    return m


def shade(contrib: Tensor, live: Tensor, blocked: Tensor, d: Tensor, ext: Tensor, R32: Tensor, H: int,
          W: int, into: tuple[Tensor, Tensor] | None = None) -> Tensor:
    """Σ_k contribution · radiance over the lit rays, live and not blocked (``methods.oracle._shade_stage``):
    contributions (K, Q, 3) float32 contiguous, world directions (3, K, Q) float32 component planes (each
    contiguous), live and blocked (K, Q) bool contiguous; ext the periodic-extended texels (H·(W + 1), 3), R32 (3, 3) float32 → (Q, 3).
    ``into`` = (idx (Q,) int64 contiguous, planes (3, P) float32 contiguous): sample i's sum written to
    ``planes[:, idx[i]]`` instead (the G-buffer's channel-major radiance, `GBuffer.resolve(channels_first=True)`'s
    input; the same values as ``planes[:, idx] = shade(...).T``), → planes."""
    K, Q = int(live.shape[0]), int(live.shape[1])
    if into is None:
        out, idx, OP = torch.empty(Q, 3, dtype=torch.float32), None, 0
    else:
        idx, out = into
        if not (idx.dtype == torch.int64 and idx.shape == (Q,) and idx.is_contiguous() and out.dim() == 2
                and out.shape[0] == 3 and out.dtype == torch.float32 and out.is_contiguous()):
            raise ValueError("shade: into = (idx (Q,) int64, planes (3, P) float32), contiguous")
        OP = int(out.shape[1])
    if Q:
        _lib().shade(_ptr(contrib), _ptr(live), _ptr(blocked), _ptr(d), _ptr(ext), _ptr(R32), Q, K, H, W,
                     int(d.stride(0)), _ptr(out), BLOCK, _threads(Q), None if idx is None else _ptr(idx), OP)
    return out


def frame_rows(hit: Tensor, region: Tensor, face: Tensor, R: int, F: Tensor, N: int, scratch) -> tuple | None:
    """A frame's samples, as ``Oracle.render`` orders them, and `frame_cost`'s counts, by one C pass (or35): →
    (order (Q,) int64: the hit samples of regions 0 … R − 1, region after region, ascending — ``torch.cat`` of
    ``torch.nonzero((region == r) & hit)`` —, [samples per region], hit samples, faces hit (``face`` of the hit
    samples), their distinct vertices (rows of ``F`` (M, 3))) — ``Oracle._record``'s counts, the same
    integers. hit (P,) bool, region and face (P,) int64, F int64, contiguous CPU; ``scratch(name, shape,
    dtype)`` gives work arrays. None where it does not run (no C loops, other dtypes / devices)."""
    lib = _lib()
    ts = (hit, region, face, F)
    if (lib is None or not all(t.device.type == "cpu" and t.is_contiguous() for t in ts) or hit.dtype != torch.bool
            or region.dtype != torch.int64 or face.dtype != torch.int64 or F.dtype != torch.int64
            or F.dim() != 2 or F.shape[1] != 3 or not hit.shape == region.shape == face.shape or hit.dim() != 1):
        return None
    P, M = int(hit.shape[0]), int(F.shape[0])
    order = scratch("order", (P,), torch.int64)
    counts = torch.zeros(max(R, 1), dtype=torch.int64)
    stats = torch.zeros(3, dtype=torch.int64)
    lib.frame_rows(_ptr(hit), _ptr(region), _ptr(face), P, int(R), _ptr(order), _ptr(counts), _ptr(F), M, int(N),
                   _ptr(scratch("face_flags", (max(M, 1),), torch.uint8)),
                   _ptr(scratch("vertex_flags", (max(int(N), 1),), torch.uint8)), _ptr(stats))
    c = [int(x) for x in counts[:R].tolist()]
    hits, faces, verts = (int(x) for x in stats.tolist())
    return order[:sum(c)], c, hits, faces, verts


# torch's CPU generator state (``torch.Generator.get_state``, at::CPUGeneratorImplState): the legacy POD's
# initial seed (uint64), left_ (int32), seeded (int32), next_ (uint64), the 624 words (as uint64), ...
_STATE_BYTES, _LEFT, _NEXT, _WORDS = 5056, 8, 16, 24
_MT_CHECKED: list = []  # [True / False] once checked in this process (with the C loops built)


def _draw(gen: torch.Generator, outs: list) -> None:
    """Each of ``outs`` (float32 contiguous CPU tensors) filled in turn by the C generator `mt_uniform`
    from ``gen``'s state, which is then advanced (set) as the draws advanced it."""
    s = gen.get_state()
    a = s.numpy()
    ln = torch.tensor([int(a[_LEFT:_LEFT + 4].view("<i4")[0]), int(a[_NEXT:_NEXT + 8].view("<u8")[0])],
                      dtype=torch.int64)
    st = torch.from_numpy(a[_WORDS:_WORDS + 8 * 624].view("<u8").astype("<u4"))
    lib = _lib()
    for x in outs:
        lib.mt_uniform(_ptr(st), _ptr(ln), _ptr(x), x.numel())
    a[_WORDS:_WORDS + 8 * 624].view("<u8")[:] = st.numpy()
    a[_LEFT:_LEFT + 4].view("<i4")[0] = int(ln[0])
    a[_NEXT:_NEXT + 8].view("<u8")[0] = int(ln[1])
    gen.set_state(s)


def _mt_ok() -> bool:
    """Whether `_draw` reproduces ``torch.rand`` on this torch (its generator's state layout), checked
    once per process on 3 000 numbers across two twists: the numbers and the state after them."""
    if not _MT_CHECKED:
        ok = False
        g = torch.Generator().manual_seed(20261206)
        if g.get_state().numel() == _STATE_BYTES:
            torch.rand(5, generator=g)
            h = torch.Generator()
            h.set_state(g.get_state())
            outs = [torch.empty(7), torch.empty(1300), torch.empty(1693)]
            _draw(g, outs)
            want = torch.rand(3000, generator=h)
            ok = torch.equal(torch.cat(outs), want) and torch.equal(g.get_state(), h.get_state())
        _MT_CHECKED.append(ok)
    return _MT_CHECKED[0]


def uniform(gen: torch.Generator, outs: list) -> bool:
    """``torch.rand(x.shape, generator=gen, out=x)`` for each x of ``outs`` in turn (float32 contiguous CPU
    tensors), by the C generator (~4 ns a number in torch's serial kernel, a fraction of it here): the
    same numbers, ``gen`` left in the same state. False (nothing drawn) where it does not run: no C
    loops, a generator other than the CPU one, or a torch whose generator state it does not know."""
    if _lib() is None or gen.device.type != "cpu" or not _mt_ok():
        return False
    if not all(x.dtype == torch.float32 and x.device.type == "cpu" and x.is_contiguous() for x in outs):
        return False
    _draw(gen, outs)
    return True
