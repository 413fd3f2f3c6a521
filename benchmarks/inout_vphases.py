"""In-out shading "vertex" V frame: where the time goes, phase by phase (``native_vframe``'s four phases
timed by thread 0 with omp_get_wtime in a patched copy of the loop, plus the Python around the call).

    python -m benchmarks.inout_vphases [--scene creature] [--threads 1] [--frames 21]

Each frame after `benchmarks.common.settle`; frame 0 untimed; with several ``--fast`` variants each frame is
rendered under each (rotating order, the images compared bit for bit) and the medians' ratios printed. Prints medians (ms): the whole render (wall,
process CPU), the C call (wall), and phases (1) samples, (2) faces, (3) vertices, (3b) the face table (FAST bit 2), (4) pixels
(wall of thread 0, each ending after its barrier). ``--fast N``: the loop's variant bits.
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
    marks = ["        /* (2) */\n", "        /* (3) chunks", "        if (fast & 2) {\n            /* (3b)", "        /* (4) */\n"]
    for j, mk in enumerate(marks):
        s = s.replace(mk, f"        if (t == 0) vf_times[{j}] = omp_get_wtime() - t0;\n" + mk, 1)
    return s


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--frames", type=int, default=21)
    ap.add_argument("--fast", type=int, nargs="+", default=None,
                    help="native_vframe.FAST variants (default: the module's); several: each frame rendered under "
                         "each, in rotating order, every render after the settle")
    a = ap.parse_args(argv)
    variants = a.fast if a.fast is not None else [nv.FAST]
    torch.set_num_threads(a.threads)
    scene, frames, gbs, _ = setup(a.scene, a.size, kind="V", n_frames=a.frames, seed=1, spp_side=2)
    m, _ = precomputed(InOut, scene, {"shading": "vertex"})
    m._fast = None
    m._reset_cache()
    src = patched_source(nv._SOURCE)
    lib = native.load("inout_vframe_phases", src, nv._SIGNATURES, extra_flags=nv._flags())
    times = (ctypes.c_double * 8).in_dll(lib, "vf_times")
    orig = nv._lib
    nv._lib = lambda: lib
    calls = []
    real = lib.vertex_frame
    real_packed = lib.vertex_frame_packed        # what `native_vframe.Bound.frame` calls under ``PACKED`` (session 43)

    class Wrap:
        def __getattr__(self, k):
            return getattr(lib, k)

        def vertex_frame(self, *args):
            t0 = time.perf_counter()
            real(*args)
            calls.append((time.perf_counter() - t0, list(times)))

        def vertex_frame_packed(self, *args):
            t0 = time.perf_counter()
            real_packed(*args)
            calls.append((time.perf_counter() - t0, list(times)))

    w = Wrap()
    nv._lib = lambda: w
    rows = [[] for _ in variants]
    order = list(range(len(variants)))
    for i, (f, g) in enumerate(zip(frames, gbs)):
        k = i % len(variants)
        first = None
        for j in (order[k:] + order[:k] if i else order[:1]):   # frame 0 (it sets the lighting) once
            nv.FAST = variants[j]
            settle()
            t0, c0 = time.perf_counter(), time.process_time()
            img = m.render(f, g)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            if first is None:
                first = img
            elif not torch.equal(img, first):
                print(f"variant {variants[j]} frame {i}: not the same bits as the frame's first render")
            if i:
                call, ph = calls[-1]
                rows[j].append((wall, cpu, call, ph[0], ph[1] - ph[0], ph[2] - ph[1], ph[3] - ph[2], call - ph[3]))
    nv._lib = orig
    names = ["render wall", "render cpu", "C call", "(1) samples", "(2) faces", "(3) vertices", "(3b) face table", "(4) pixels+exit"]
    out = []
    for j, v in enumerate(variants):
        med = [statistics.median(r[c] for r in rows[j]) * 1e3 for c in range(len(names))]
        out.append(med)
        print(f"{a.scene} {a.size} {a.threads} threads FAST {v} {len(rows[j])} frames: " + ", ".join(f"{n} {x:.3f}" for n, x in zip(names, med)))
    for j, v in enumerate(variants[1:], 1):
        print(f"FAST {v} against {variants[0]}: render cpu {out[0][1] / out[j][1]:.3f}x, C call {out[0][2] / out[j][2]:.3f}x")
    return out


if __name__ == "__main__":
    main()
