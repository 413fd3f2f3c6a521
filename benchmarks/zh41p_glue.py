"""Where a ZH paper-config frame's time goes between C and Python (session 41, zh41p): every ctypes function of the
libraries `methods.core.native.load` returns is wrapped to add up its thread CPU time; the rest of the frame
("GLUE") is the serial Python / torch work around the calls — what a 2-thread frame waits on whole.

    python -m benchmarks.zh41p_glue [--kind P] [--frames 5] [--repeat 8] [--precompute-code DIR] [--flush 64]

The checkout measured is the one on PYTHONPATH: for another one run this file by its path from that checkout
(``cd /work/wt/base41 && PYTHONPATH=. python /path/to/benchmarks/zh41p_glue.py --precompute-code .``).
1 torch thread (thread CPU time = the frame's CPU); before each frame ``--flush`` MB are written and read and
`benchmarks.common.settle` idles (the harness's cold caches); frame 0 of each repeat untimed. Prints the median
ms of the frame, of GLUE and of each C function. Session 41, bench creature, load 5-8, base 338e016 → zh41p:
P GLUE 1.51 → 1.17 ms (frame 5.21 → 5.01), V 0.89 → 0.87 ms.
"""
from __future__ import annotations

import argparse
import collections
import statistics
import time


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kind", default="P")
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=8)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--flush", type=int, default=64)
    a = ap.parse_args(argv)
    import torch

    from benchmarks.common import precomputed, settle, setup
    from methods.core import native

    torch.set_num_threads(1)
    if a.precompute_code:
        from reports import precompute_cache
        from reports.store import code_closure_fingerprint

        precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, a.precompute_code)
    rec: dict = collections.defaultdict(float)
    load, done = native.load, set()

    def spy(name, source, signatures, extra_flags=()):
        lib = load(name, source, signatures, extra_flags)
        if lib is not None and id(lib) not in done:
            done.add(id(lib))
            for fn in signatures:
                f = getattr(lib, fn)

                def g(*args, _f=f, _n=f"{name}.{fn}"):
                    t = time.thread_time()
                    r = _f(*args)
                    rec[_n] += time.thread_time() - t
                    return r

                setattr(lib, fn, g)
        return lib

    native.load = spy
    from methods.zh_shadow.method import ZHShadow

    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(ZHShadow, scene, {})
    _, frames, gbs, _ = setup(scene, "bench", kind=a.kind, n_frames=a.frames, seed=a.seed)
    m = m.with_render_config()
    junk = torch.empty(max(a.flush, 1) << 18)
    per: dict = collections.defaultdict(list)
    for _ in range(a.repeat):
        for i, (f, gb) in enumerate(zip(frames, gbs)):
            if a.flush:
                junk.fill_(1.0)
                float(junk[::4096].sum())
            settle()
            rec.clear()
            t = time.thread_time()
            m.render(f, gb)
            dt = time.thread_time() - t
            if i == 0:
                continue
            per["FRAME"].append(dt)
            per["GLUE"].append(dt - sum(rec.values()))
            for k, v in rec.items():
                per[k].append(v)
    out = {k: statistics.median(v) * 1e3 for k, v in per.items()}
    for k, v in sorted(out.items(), key=lambda kv: -kv[1]):
        print(f"  {k:40s} {v:.3f} ms")
    return out


if __name__ == "__main__":
    main()
