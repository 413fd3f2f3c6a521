"""SH PRT's relight cache build pass alone (session 42, issue 14): `native.relight_build` with
`FAST_RELIGHT_BUILD` on (`rb_range2`) and off (session 40's `rb_range`, its oracle) in one process, alternating,
on the real arguments of a creature bench L sequence's first lighting-only frame (bounces 0, the perf cells').

    python -m benchmarks.sh_prt42_build [--threads 1] [--repeat 15] [--warm] [--precompute-code DIR]

Before each call the caches are cooled as the perf suite's loop cools them (a 64 MB buffer written, 0.1 s
idle; ``--warm``: back to back). Prints the median process CPU ms of each (first repeat dropped), their ratio
and whether the packed caches and pixels are equal bit for bit.
"""
from __future__ import annotations

import argparse
import statistics
import time


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--warm", action="store_true")
    ap.add_argument("--precompute-code", default=None)
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(a.threads)
    if a.precompute_code:
        from reports import precompute_cache
        from reports.store import code_closure_fingerprint

        precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, a.precompute_code)
    from benchmarks.common import precomputed, setup
    from methods.sh_prt import native as nat
    from methods.sh_prt.method import SHPRT

    cap: dict = {}
    real = nat.relight_build

    def spy(*args):
        cap["args"] = args
        return real(*args)

    nat.relight_build = spy
    try:
        scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
        m, _ = precomputed(SHPRT, scene, {})
        m = m.with_bounces(0)
        _, frames, gbs, _ = setup(scene, "bench", kind="L", n_frames=2, seed=0)
        m.render(frames[0], gbs[0])
        m.render(frames[1], gbs[1])
    finally:
        nat.relight_build = real
    args = cap["args"]
    junk = torch.empty(16 << 20)
    t: dict = {True: [], False: []}
    res: dict = {}
    old_flag = nat.FAST_RELIGHT_BUILD
    try:
        for r in range(a.repeat):
            for fast in ((True, False) if r % 2 else (False, True)):
                nat.FAST_RELIGHT_BUILD = fast
                if not a.warm:
                    junk.fill_(1.0)
                    time.sleep(0.1)
                c = time.process_time()
                res[fast] = real(*args)
                if r:
                    t[fast].append(time.process_time() - c)
    finally:
        nat.FAST_RELIGHT_BUILD = old_flag
    out = {"glossy samples": int(args[0].numel()), "old ms": 1e3 * statistics.median(t[False]),
           "new ms": 1e3 * statistics.median(t[True])}
    out["ratio"] = out["old ms"] / out["new ms"]
    out["same bits"] = bool(torch.equal(res[True][0], res[False][0]) and torch.equal(res[True][1], res[False][1]))
    print(f"relight build, {out['glossy samples']} glossy samples, {a.threads} thread(s), "
          f"{'warm' if a.warm else 'caches cooled'}: old {out['old ms']:.3f} ms, new {out['new ms']:.3f} ms CPU, "
          f"ratio {out['ratio']:.2f}, same bits {out['same bits']}")
    return out


if __name__ == "__main__":
    main()
