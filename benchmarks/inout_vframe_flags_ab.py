"""In-out shading "vertex": the V frame's C loop (``native_vframe``, its phases timed as in
``benchmarks.inout_vphases``) built with the x86-64 baseline flags against the host's ISA flags
(``native.isa_flags``), both without contraction, in one process.

    python -m benchmarks.inout_vframe_flags_ab [--scene chess] [--frames 41]

1 thread; each frame after `benchmarks.common.settle`, rendered by both builds in alternating order (frame 0
untimed, the lighting's); the images compared bit for bit (asserted). Prints the median render CPU and
phase (3) ms of each and their ratios.
"""
from __future__ import annotations

import argparse
import ctypes
import statistics
import time

import torch

from benchmarks.common import precomputed, settle, setup
from benchmarks.inout_vphases import patched_source
from methods.core import native
from methods.inout import native_vframe as nv
from methods.inout.method import InOut


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--frames", type=int, default=41)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    scene, frames, gbs, _ = setup(a.scene, "bench", kind="V", n_frames=a.frames, seed=1, spp_side=2)
    m, _ = precomputed(InOut, scene, {"shading": "vertex"})
    m._fast = None
    m._reset_cache()
    src = patched_source(nv._SOURCE)
    base = ("-fopenmp", "-ffp-contract=off")
    libs = {"baseline": native.load("inout_vframe_phases", src, nv._SIGNATURES, extra_flags=base),
            "isa": native.load("inout_vframe_phases", src, nv._SIGNATURES, extra_flags=(*base, *native.isa_flags()))}
    cpu = {k: [] for k in libs}
    p3 = {k: [] for k in libs}
    orig = nv._lib
    try:
        for i, (f, g) in enumerate(zip(frames, gbs)):
            order = ["baseline", "isa"] if i % 2 else ["isa", "baseline"]
            imgs = []
            for k in (order if i else order[:1]):
                lib = libs[k]
                nv._lib = lambda lib=lib: lib
                m._vcall = None                       # bound to this build
                settle()
                c0 = time.process_time()
                imgs.append(m.render(f, g))
                c = time.process_time() - c0
                t = (ctypes.c_double * 8).in_dll(lib, "vf_times")
                if i:
                    cpu[k].append(c)
                    p3[k].append(t[2] - t[1])
            assert len(imgs) < 2 or torch.equal(imgs[0], imgs[1]), f"frame {i}: not the same bits"
    finally:
        nv._lib = orig
        m._vcall = None
    med = {k: (statistics.median(cpu[k]), statistics.median(p3[k])) for k in libs}
    for k, (c, p) in med.items():
        print(f"{a.scene} {k} ({' '.join(native.isa_flags()) if k == 'isa' else 'x86-64'}): render cpu {1e3 * c:.3f} ms, "
              f"phase (3) {1e3 * p:.3f} ms")
    print(f"isa against baseline: render cpu {med['baseline'][0] / med['isa'][0]:.3f}x, phase (3) "
          f"{med['baseline'][1] / med['isa'][1]:.3f}x; images the same bits")
    return med


if __name__ == "__main__":
    main()
