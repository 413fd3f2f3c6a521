"""Session 43 (sh43): a creature bench V frame's one C pass (`native.sh_view`) alone, cold caches, against
variants of the library source (micro-benchmark; no effect on the method).

    python -m benchmarks.sh_prt43_view [--reps 41] [--variants base ...] [--precompute-code DIR]

Renders a V sequence's frames 0-2 (the l' table complete), captures frame 2's `native.view` arguments, then
per repetition and variant (alternating order): writes a 64 MB buffer (the harness's cold caches), calls the
variant's ``sh_view`` at 1 thread, process CPU. Variants are edits of `native._SOURCE` (``VARIANTS``) built as
their own libraries. Prints per variant the median ms and its ratio to the first.
"""
from __future__ import annotations

import argparse
import ctypes
import statistics
import time

import torch

from methods.core import native as cnative

VARIANTS: dict = {
    "base43": [],     # the base checkout's source (PRTBENCH_SH43_BASE)
    "base": [],       # this checkout's
    "noglossy": [("        if (ng)\n            gl_range(0, ng,", "        if (0)\n            gl_range(0, ng,")],
}
VARIANTS["masked"] = [("#define SH_PX_WIDE_STORE 1", "#define SH_PX_WIDE_STORE 0")]
VARIANTS["setr"] = [("            const __m256 nx0 = _mm256_loadu_ps(fnx), ny0 = _mm256_loadu_ps(fny), nz0 = _mm256_loadu_ps(fnz);\n            const __m256 ox = _mm256_loadu_ps(fox), oy = _mm256_loadu_ps(foy), oz = _mm256_loadu_ps(foz);\n            const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f), tiny",
                      "            const __m256 nx0 = _mm256_setr_ps(fnx[0], fnx[1], fnx[2], fnx[3], fnx[4], fnx[5], fnx[6], fnx[7]), ny0 = _mm256_setr_ps(fny[0], fny[1], fny[2], fny[3], fny[4], fny[5], fny[6], fny[7]), nz0 = _mm256_setr_ps(fnz[0], fnz[1], fnz[2], fnz[3], fnz[4], fnz[5], fnz[6], fnz[7]);\n            const __m256 ox = _mm256_setr_ps(fox[0], fox[1], fox[2], fox[3], fox[4], fox[5], fox[6], fox[7]), oy = _mm256_setr_ps(foy[0], foy[1], foy[2], foy[3], foy[4], foy[5], foy[6], foy[7]), oz = _mm256_setr_ps(foz[0], foz[1], foz[2], foz[3], foz[4], foz[5], foz[6], foz[7]);\n            const __m256 zero = _mm256_setzero_ps(), one = _mm256_set1_ps(1.0f), tiny")]
VARIANTS["lsr25"] = [("    if (fused == 1 && n == 5) {\n", "    if (fused == 1 && n == 5 && lsr == 25) {\n        gl_body(q0, q1, 5, g, face, Mf, reg, Rn, B, br, bc, N, nr, nc, O, orr, oc, ef, fg, lg, lsc, 25, kd, ks, G,\n                vcos, A, sel, out, img, S2, inv, 1);\n        return;\n    }\n    if (fused == 1 && n == 5) {\n")]
VARIANTS["noY"] = [("for (int64_t j = n - 2; j >= 0; --j) P = MADD(P, z, _mm256_set1_ps(A[j * m + i]));", "")]


def _base_source() -> str:
    """`native._SOURCE` of the checkout in PRTBENCH_SH43_BASE (a checkout of the code to compare against),
    read from its file."""
    import ast
    import os
    root = os.environ.get("PRTBENCH_SH43_BASE")
    if not root:
        raise SystemExit("variant base43 needs PRTBENCH_SH43_BASE=<a checkout of the base code>")
    path = os.path.join(root, "methods/sh_prt/native.py")
    for node in ast.parse(open(path).read()).body:
        if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", None) == "_SOURCE":
            return node.value.value
    raise RuntimeError("no _SOURCE in " + path)


def build(name: str, edits):
    from methods.sh_prt import native as nat
    src = _base_source() if name == "base43" else nat._SOURCE
    for a, b in edits:
        assert a in src, a
        src = src.replace(a, b)
    return cnative.load("sh_lg_rows", src + f"\n/* variant {name} */\n", nat._SIGNATURES, extra_flags=nat._flags())


def capture(precompute_code=None):
    if precompute_code:
        from reports import precompute_cache
        from reports.store import code_closure_fingerprint
        precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, precompute_code)
    from benchmarks.common import precomputed, setup
    from methods.sh_prt import method as shm, native as nat
    from methods.sh_prt.method import SHPRT
    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(SHPRT, scene, {})
    m = m.with_bounces(0)
    _, frames, gbs, _ = setup(scene, "bench", kind="V", n_frames=3, seed=1)
    m._reset_cache()
    got = {}
    orig = nat.view

    def spy(*a, **k):
        got["a"], got["k"] = a, k
        return orig(*a, **k)
    nat.view = spy
    again = shm.VIEW_AGAIN
    shm.VIEW_AGAIN = False          # (session 43's `_view_again` calls the kept pass, not `native.view`)
    imgs = [m.render(f, g) for f, g in zip(frames, gbs)]
    nat.view, shm.VIEW_AGAIN = orig, again
    return m, got, imgs[-1]


def call_args(got):
    """The ctypes arguments of `native.view`'s ``sh_view`` call for the captured frame (1 thread)."""
    from methods.sh_prt import native as nat
    (face, hit, bary, normal, wo, ef, fk, S2, reg, fg, lg3, kd, ks, G, vcos, A, S) = got["a"]
    v8, sel = nat._view_tables(vcos, S)
    n = int(round(G.shape[1] ** 0.5))
    npx = face.numel() // S2
    img = torch.empty(npx, 3)
    ok = ctypes.c_int64(0)
    args = [npx, S2, face.data_ptr(), hit.data_ptr(), bary.data_ptr(), bary.stride(0), bary.stride(1),
            normal.data_ptr(), normal.stride(0), normal.stride(1), wo.data_ptr(), wo.stride(0), wo.stride(1),
            ef.data_ptr(), fk.data_ptr(), int(ef.shape[0]), 1.0 / S2, img.data_ptr(), 1, n, reg.data_ptr(),
            int(kd.shape[0]), fg.data_ptr(), lg3.data_ptr(), lg3.stride(0), lg3.stride(1), kd.data_ptr(),
            ks.data_ptr(), G.data_ptr(), v8.data_ptr(), A.data_ptr(), sel.data_ptr(), int(bool(nat.FUSED_GLOSSY)),
            int(nat.VIEW_CHUNK), 1, ctypes.addressof(ok)]
    return args, img, ok, (v8, sel)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--reps", type=int, default=41)
    ap.add_argument("--variants", nargs="+", default=["base", "noglossy"])
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--warm", action="store_true", help="no 64 MB write between calls")
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    m, got, ref = capture(a.precompute_code)
    args, img, ok, keep = call_args(got)
    libs = {v: build(v, VARIANTS[v]) for v in a.variants}
    flush = torch.empty(16 << 20)
    T = {v: [] for v in a.variants}
    imgs = {}
    for r in range(a.reps):
        order = a.variants if r % 2 == 0 else a.variants[::-1]
        for v in order:
            if not a.warm:
                flush.fill_(r)
            c = time.process_time()
            libs[v].sh_view(*args)
            c = time.process_time() - c
            if r:
                T[v].append(c)
            if r == 0:
                imgs[v] = img.clone()
    b = statistics.median(T[a.variants[0]])
    for v in a.variants:
        md = statistics.median(T[v])
        d = float((imgs[v].view(-1) - ref.reshape(-1)).abs().max())
        print(f"{v:16s} {1e3 * md:7.3f} ms  ratio {b / md:5.3f}  max|img - frame 2's| {d:.3g}", flush=True)
    return T


if __name__ == "__main__":
    main()
