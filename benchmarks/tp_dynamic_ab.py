"""TripleProduct frames at 2+ threads with the points loop and the comb loops handed out dynamically
(`native.POINTS_BLOCK`, `native_light.COMB_BLOCK`, session 39) against their static splits (both 0), in
one process, alternating frame by frame (which goes first alternates too), wall ms medians and their
ratio; the images compared bit for bit. The static split's cost is a thread that shares its core
with other work (the harness's threads, other processes) holding the region's end: measure it on a
busy host, where that happens, and on a quiet one, where the ratio should be ~1.

    python -m benchmarks.tp_dynamic_ab [--scene creature] [--shading vertex] [--kinds E VL V]
        [--frames 9] [--repeat 3] [--threads 2] [--precompute-code DIR] [--which both|points|comb]
"""
from __future__ import annotations

import argparse
import json
import statistics
import time


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--shading", default="vertex")
    ap.add_argument("--kinds", nargs="+", default=["E", "VL", "V"])
    ap.add_argument("--frames", type=int, default=9)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--spp-side", type=int, default=2)
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--which", default="both", choices=["both", "points", "comb"])
    a = ap.parse_args(argv)

    from benchmarks.common import apply_ab_options, precomputed, settle, setup
    apply_ab_options(a)
    import torch

    from methods.core.fused import warming
    from methods.triple_product import TripleProduct, native, native_light
    from scenes.library import get_scene

    torch.set_num_threads(a.threads)
    scene = get_scene(a.scene, a.size)
    m, _ = precomputed(TripleProduct, scene, {} if a.shading == "pixel" else {"shading": "vertex"})
    blocks = (native.POINTS_BLOCK, native_light.COMB_BLOCK)

    def use(dynamic: bool) -> None:
        native.POINTS_BLOCK = blocks[0] if dynamic and a.which in ("both", "points") else 0
        native_light.COMB_BLOCK = blocks[1] if dynamic and a.which in ("both", "comb") else 0

    out = {"threads": a.threads, "which": a.which}
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, kind=kind, n_frames=a.frames, seed=0, spp_side=a.spp_side)
        t = {False: [], True: []}
        same = True
        for r in range(a.repeat):
            m._light_key = None
            with warming():
                m.render(frames[0], gbs[0])
            for i, (f, g) in enumerate(zip(frames[1:], gbs[1:])):
                imgs = {}
                for dyn in ((False, True) if (i + r) % 2 == 0 else (True, False)):
                    use(dyn)
                    if kind != "V":      # each of the two renders relights (E, VL): another key, the lazy path
                        m._light_key = ("tp_dynamic_ab",)
                    settle()
                    t0 = time.perf_counter()
                    imgs[dyn] = m.render(f, g)
                    t[dyn].append(time.perf_counter() - t0)
                same = same and torch.equal(imgs[False], imgs[True])
        use(True)
        s, d = statistics.median(t[False]), statistics.median(t[True])
        res = {"static_ms": 1e3 * s, "dynamic_ms": 1e3 * d, "ratio": s / d, "frames": len(t[True]), "same_bits": same}
        out[kind] = res
        print(kind, json.dumps(res), flush=True)
    return out


if __name__ == "__main__":
    main()
