"""The oracle's C loops alone (``methods.oracle.native_rays``: `pretrace`, `shade`) against another
checkout's, on one captured frame (issue 14; session 32).

    python -m benchmarks.oracle_native_ab --baseline /work/base [--scene creature] [--kind V]
        [--rounds 7] [--threads 1]

Renders frame 1 of the sequence with this tree's `Oracle` and records the arguments of every
`pretrace` call and of the `shade` call (the work arrays they write stay the frame's); then, in one
process, alternates rounds of the baseline's C loops (its ``methods/oracle/native_rays.py`` loaded by
path: its C source, built by this tree's ``methods.core.native``) and this tree's on those arguments —
3 calls a round, process CPU — and prints the median of each and their ratio, and whether the two
write the same outputs (bit for bit; else the largest difference relative to each output's peak, and
whether the live rays are the same). Back to back, so the caches are warmer than in a frame
(`benchmarks.frame_protocol` times the suite's protocol; `benchmarks.oracle_ab` whole frames).
"""
from __future__ import annotations

import argparse
import importlib.util
import os
import statistics
import time


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", required=True, help="a checkout whose methods/oracle/native_rays.py is the baseline")
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--kind", default="V")
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(a.threads)
    import methods.oracle as O
    import methods.oracle.native_rays as N
    from benchmarks.common import setup

    path = os.path.join(a.baseline, "methods", "oracle", "native_rays.py")
    spec = importlib.util.spec_from_file_location("_baseline_native_rays", path)
    B = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(B)
    if not (N.available() and B.available()):
        raise SystemExit("the C loops are not built here (no compiler or PRTBENCH_COMPILE=0)")
    scene, frames, gbs, _ = setup(a.scene, a.size, kind=a.kind, n_frames=2)
    m = O.Oracle(light_samples=4, brdf_samples=4)
    m.precompute(scene)
    calls, shades = [], []
    real_p, real_s = N.pretrace, N.shade

    def rec_p(*args):
        calls.append(args)
        return real_p(*args)

    def rec_s(*args):
        shades.append(args)
        return real_s(*args)

    N.pretrace, N.shade = rec_p, rec_s
    try:
        m.render(frames[1], gbs[1])
    finally:
        N.pretrace, N.shade = real_p, real_s

    def outputs(mod) -> list:
        for args in calls:
            mod.pretrace(*args)
        out = [x.clone() for x in calls[0][-1]]  # the frame's work arrays (every region's rows)
        return out + [mod.shade(*shades[0])]

    ob, on = outputs(B), outputs(N)
    same = all(torch.equal(x, y) for x, y in zip(ob, on))
    rel = max(((x.float() - y.float()).abs().max() / x.float().abs().max().clamp_min(1e-30)).item()
              for x, y in zip(ob, on) if x.is_floating_point())
    live_same = torch.equal(ob[1], on[1])

    def pretrace(mod) -> float:
        t0 = time.process_time()
        for _ in range(3):
            for args in calls:
                mod.pretrace(*args)
        return (time.process_time() - t0) / 3

    def shade(mod) -> float:
        t0 = time.process_time()
        for _ in range(3):
            mod.shade(*shades[0])
        return (time.process_time() - t0) / 3

    T = {k: [] for k in ("pretrace base", "pretrace new", "shade base", "shade new")}
    for _ in range(a.rounds):
        T["pretrace base"].append(pretrace(B))
        T["pretrace new"].append(pretrace(N))
        T["shade base"].append(shade(B))
        T["shade new"].append(shade(N))
    med = {k: 1e3 * statistics.median(v) for k, v in T.items()}
    out = {"scene": a.scene, "kind": a.kind, "threads": a.threads, "same_outputs": same, "max_rel_diff": rel,
           "same_live": live_same, "ms": med,
           "regions": [args[0].kind for args in calls]}
    print(f"oracle C loops, {a.scene} {a.kind} ({a.size}) frame 1, {a.threads} threads, regions {out['regions']}; "
          f"outputs {'bit-identical' if same else f'max |new - base| / max |base| {rel:.2g}'}, "
          f"live rays {'the same' if live_same else 'DIFFER'}")
    for k in ("pretrace", "shade"):
        b, n = med[f"{k} base"], med[f"{k} new"]
        print(f"  {k:9s} base {b:7.1f} ms  new {n:7.1f} ms  ratio {b / n:.3f}")
    return out


if __name__ == "__main__":
    main()
