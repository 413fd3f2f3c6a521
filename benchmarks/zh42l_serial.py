"""Process CPU of a steady order-8 lighting-only ZH frame and of its C calls, the rest being what a 2-thread frame
runs serially (Python, torch calls, the wrappers): bench creature, 1 thread, a 64 MB write and ``PRTBENCH_SETTLE``
idle before every frame (the perf harness's cold caches), frames 2-4 of ``--repeat`` sequences of 5 (frame 0 a full
change, frame 1 the build). The C calls timed: session 41's `zh41l_relight` and `zh41l_light` (through the kept
library and light plan) or zh42l's one `zh42l_steady` (through ``_steady_call``), whichever the code runs.

    PYTHONPATH=. python -m benchmarks.zh42l_serial --kinds L E [--root /work/wt/base42]   # (--root: that checkout's
                                                                                         # ``methods``, printed)

(zh42l, 1 thread, base42 -> zh42l, outside the C calls: L 0.397 -> 0.257 ms, E 0.738 -> 0.642 ms (90 frames a kind);
again, 60 frames: L 0.320 -> 0.271, E 0.726 -> 0.600; the C calls 0.25-0.28 ms either way.) Separate processes:
absolute times under whatever load there is (load 5-8 here), not a same-process ratio (`benchmarks.zh_sample_ab`).
"""
from __future__ import annotations

import argparse
import statistics
import time
from types import SimpleNamespace


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kinds", nargs="+", default=["L", "E"])
    ap.add_argument("--repeat", type=int, default=30)
    ap.add_argument("--precompute-code", default=None)   # another checkout whose precomputation to reuse
    ap.add_argument("--root", default=None, help="import ``methods`` from this checkout (before anything imports it)")
    a = ap.parse_args(argv)
    if a.root:
        import sys

        assert not any(k == "methods" or k.startswith("methods.") for k in sys.modules), "methods imported already"
        sys.path.insert(0, a.root)
    from benchmarks.common import apply_ab_options, precomputed, settle, setup

    apply_ab_options(SimpleNamespace(threads=1, precompute_code=a.precompute_code))
    import torch

    import methods.zh_shadow.method as zm
    from methods.zh_shadow.method import ZHShadow

    print("methods from", zm.__file__, flush=True)
    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(ZHShadow, scene, {"order": 8, "shading": "vertex", "specular": "cosine"})
    buf = torch.empty(16 * 1024 * 1024)
    pt = time.process_time_ns
    acc = [0]

    def timed(f):
        def g(*args):
            t = pt()
            out = f(*args)
            acc[0] += pt() - t
            return out
        return g

    res = {}
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, "bench", kind=kind, n_frames=5, seed=0)
        tot, cc = [], []
        for _ in range(a.repeat):
            obj = m.with_render_config()
            for i, (f, g) in enumerate(zip(frames, gbs)):
                if i == 2:   # (after the build frame: the kept calls wrapped)
                    sc = getattr(obj, "_steady_call", None)
                    if sc is not None and sc[1] is not None:
                        obj._steady_call = (sc[0], (timed(sc[1][0]),) + sc[1][1:], *sc[2:])
                    else:
                        lib = obj._steady[-1][0]
                        if not getattr(lib, "_zh42l_timed", False):
                            lib.zh41l_relight = timed(lib.zh41l_relight)
                            lib._zh42l_timed = True
                        lp = obj._light_plan
                        obj._light_plan = (lp[0], (timed(lp[1][0]),) + lp[1][1:])
                buf.fill_(float(i))
                settle()
                acc[0] = 0
                c = pt()
                obj.render(f, g)
                d = pt() - c
                if i >= 2:
                    tot.append(d)
                    cc.append(acc[0])
        res[kind] = {"frame_ms": statistics.median(tot) / 1e6, "c_ms": statistics.median(cc) / 1e6,
                     "rest_ms": statistics.median([x - y for x, y in zip(tot, cc)]) / 1e6, "frames": len(tot)}
        r = res[kind]
        print(f"{kind}: frame {r['frame_ms']:.3f} ms, C calls {r['c_ms']:.3f} ms, the rest {r['rest_ms']:.3f} ms "
              f"(medians of {r['frames']} frames)", flush=True)
    return res


if __name__ == "__main__":
    main()
