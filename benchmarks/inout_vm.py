"""Where in-out's vertex-major frame (``methods.inout.native_sample``, `FAST` bit 131072, ``shade_vm``) spends a
V frame: its four passes' thread CPU (the library's ``vm_profile``), and copies whose table rows are redirected
into L1 or whose ``rows_x`` calls are left out (issue 14, session 44).

    python -m benchmarks.inout_vm --scene chess|creature [--frames 9] [--variants base table norows]
                                  [--precompute-code DIR]

Each variant is the loop's source with a few lines replaced (built under its own name by
``methods.core.native.load``; the module is not touched), run at 1 thread with ``FAST`` | 131072 | 256 | 4:

- ``base``: the passes as they are: resolve (front end, per-sample records, the node-row span words), count
  (the referenced vertices, their spans' node counts, the prefix), fill (X at the span nodes by ``rows_x``),
  shade (each sample's X from the frame's buffer);
- ``table``: ``rows_x`` reads four table rows that stay in L1 instead of the span's (wrong values);
- ``norows``: the fill's full runs without ``rows_x`` (zeros written; a vertex's last partial group still
  computed).

Each call right after a fresh ``make_gbuffer`` (the perf suite's protocol), variants alternating per frame;
medians over frames 1.. of the call's process CPU and each pass's thread CPU (thread 0). Also timed: the
tiles (``FAST`` without 131072) as ``tiles``, the reference of the ratio.

Session 44 (ip44), 1 thread, host at load ~1-4 (ms): chess tiles ~7.7, base ~9.0-9.8 (resolve 3.3-3.4, count
0.2, fill 3.0-3.5, shade 2.0-2.5; 125.2·10³ products), table fill ~1.6-2.1, norows fill ~1.2; creature tiles
~6.0, base ~6.5-7.0 (3.2-3.3, 0.17, 1.2-1.3, 1.7-2.0; 88.7·10³ products).
"""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.common import inout_loop_state, settle
from methods.core import native
from methods.inout import native_sample as ns
from references.gbuffer import make_gbuffer

_L1 = ("typedef struct { int32_t f, node0; float w[4]; } vsamp;",
       "typedef struct { int32_t f, node0; float w[4]; } vsamp;\n"
       "static float l1t[4 * 3 * 128 + 64] __attribute__((aligned(64)));")
_CALL = "rows_x(rp[0], rp[1], rp[2], rp[3], cv, K, xo + at, tree);"
VARIANTS = {
    "base": [],
    "table": [_L1, ("rp[nb++] = sh + ((int64_t)r * R + u) * K3;", "rp[nb] = l1t + nb * (K3 < 384 ? K3 : 0); nb++; (void)sh;")],
    "norows": [(_CALL, "xo[at] = (v4){0, 0, 0, 0}; xo[at + 1] = xo[at]; xo[at + 2] = xo[at]; xo[at + 3] = xo[at];")],
}


def _build(name: str):
    src = ns._SOURCE
    for old, new in VARIANTS[name]:
        if old not in src:
            raise SystemExit(f"the loop's source changed: {old!r} not found")
        src = src.replace(old, new)
    return native.load("inout_vm_" + name, src, ns._SIGNATURES, extra_flags=ns._flags())


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--frames", type=int, default=9)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--precompute-code", default=None,
                    help="take the precomputation from the harness cache entry of the code in DIR")
    a = ap.parse_args(argv)
    if a.precompute_code:
        from reports import precompute_cache
        from reports.store import code_closure_fingerprint

        precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, a.precompute_code)
    torch.set_num_threads(1)
    libs = {k: _build(k) for k in a.variants}
    libs["tiles"] = ns._lib()
    if any(lib is None for lib in libs.values()):
        raise SystemExit("the C loop is not available (no compiler or PRTBENCH_COMPILE=0)")
    scene, frames, gbs, _, st, cs = inout_loop_state(a.scene, a.size, a.frames)
    names = list(libs)
    mem = ns.memo(st.voff[-1], ns.WINDOW)
    prof = torch.zeros(4, dtype=torch.int64)
    T = {k: [] for k in names}
    P = {k: [] for k in names}
    stats = {}
    vm = ns.FAST | 131072 | 256 | 4
    saved = ns.FAST
    try:
        for i, (f, g) in enumerate(zip(frames, gbs)):
            cam = torch.tensor(f.camera.origin, dtype=torch.float32)
            for k in (names if i % 2 == 0 else names[::-1]):
                lib = libs[k]
                ns.FAST = saved & ~131072 if k == "tiles" else vm
                lib.vm_profile(prof.data_ptr() if k != "tiles" else None)
                settle()
                make_gbuffer(scene, f, 2)
                c0 = time.process_time()
                _, s = ns.shade(st, cs, g.normal, g.wo, g.bary, g.face, g.region, g.hit, 4, cam, mem, 2 * i + 1 + (k == "tiles"),
                                ns.WINDOW, lib=lib)
                T[k].append(time.process_time() - c0)
                P[k].append([x / 1e6 for x in prof.tolist()])
                stats[k] = s
                lib.vm_profile(None)
    finally:
        ns.FAST = saved
    print(f"{a.scene} {a.size} V, 1 thread, {a.frames} frames (cold), FAST {vm} (tiles: {saved & ~131072})")
    res = {}
    for k in names:
        med = 1e3 * statistics.median(T[k][1:])
        parts = [statistics.median(p[j] for p in P[k][1:]) for j in range(4)]
        res[k] = {"median_ms": med, "stats": stats[k]}
        if k != "tiles":
            res[k].update(resolve_ms=parts[0], count_ms=parts[1], fill_ms=parts[2], shade_ms=parts[3])
            print(f"{k:>8}  call {med:7.3f} ms  resolve {parts[0]:6.3f}  count {parts[1]:6.3f}  fill {parts[2]:6.3f}  "
                  f"shade {parts[3]:6.3f}  (vertex, node) products {stats[k][0]}")
        else:
            print(f"{k:>8}  call {med:7.3f} ms  (vertex, node) products {stats[k][0]}")
    return res


if __name__ == "__main__":
    main()
