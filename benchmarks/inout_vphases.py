"""In-out shading "vertex" V frame: where the time goes, phase by phase (``native_vframe``'s four phases
timed by thread 0 with omp_get_wtime in a patched copy of the loop, plus the Python around the call).

    python -m benchmarks.inout_vphases [--scene creature] [--threads 1] [--frames 21]

Each frame after `benchmarks.common.settle`; frame 0 untimed. Prints medians (ms): the whole render (wall,
process CPU), the C call (wall), and phases (1) samples, (2) faces, (3) vertices, (4) pixels (wall of thread 0,
each ending after its barrier).
"""
from __future__ import annotations

import argparse
import ctypes
import statistics
import time

import torch

from benchmarks.common import precomputed, settle, setup
from methods.core import native
from methods.inout import native_vframe as nv
from methods.inout.method import InOut


def patched_source(src: str) -> str:
    s = src.replace("#define VCHUNK 512", "#define VCHUNK 512\ndouble vf_times[8];")
    s = s.replace("        /* (1) */\n", "        double t0 = omp_get_wtime();\n        /* (1) */\n", 1)
    marks = ["        /* (2) */\n", "        /* (3) chunks", "        /* (4) */\n"]
    for j, mk in enumerate(marks):
        s = s.replace(mk, f"        if (t == 0) vf_times[{j}] = omp_get_wtime() - t0;\n" + mk, 1)
    s = s.replace("    stats[0] = miss;\n", "    vf_times[3] = -1; \n    stats[0] = miss;\n", 1)
    return s


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--frames", type=int, default=21)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    scene, frames, gbs, _ = setup(a.scene, a.size, kind="V", n_frames=a.frames, seed=1, spp_side=2)
    m, _ = precomputed(InOut, scene, {"shading": "vertex"})
    m._fast = None
    m._reset_cache()
    src = patched_source(nv._SOURCE)
    lib = native.load("inout_vframe_phases", src, nv._SIGNATURES, extra_flags=("-fopenmp", "-ffp-contract=off"))
    times = (ctypes.c_double * 8).in_dll(lib, "vf_times")
    orig = nv._lib
    nv._lib = lambda: lib
    calls = []
    real = lib.vertex_frame

    class Wrap:
        def __getattr__(self, k):
            return getattr(lib, k)

        def vertex_frame(self, *args):
            t0 = time.perf_counter()
            real(*args)
            calls.append((time.perf_counter() - t0, list(times)))

    w = Wrap()
    nv._lib = lambda: w
    rows = []
    for i, (f, g) in enumerate(zip(frames, gbs)):
        settle()
        t0, c0 = time.perf_counter(), time.process_time()
        img = m.render(f, g)
        wall, cpu = time.perf_counter() - t0, time.process_time() - c0
        if i:
            call, ph = calls[-1]
            rows.append((wall, cpu, call, ph[0], ph[1] - ph[0], ph[2] - ph[1], call - ph[2]))
    nv._lib = orig
    names = ["render wall", "render cpu", "C call", "(1) samples", "(2) faces", "(3) vertices", "(4) pixels+exit"]
    med = [statistics.median(r[j] for r in rows) * 1e3 for j in range(len(names))]
    print(f"{a.scene} {a.size} {a.threads} threads {len(rows)} frames: " + ", ".join(f"{n} {v:.3f}" for n, v in zip(names, med)))
    return med


if __name__ == "__main__":
    main()
