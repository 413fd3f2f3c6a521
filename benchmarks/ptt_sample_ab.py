"""Same-process before/after of PTT's native sample stage alone (issue 14): the C source of a base
checkout's ``methods/ptt/native.py`` (``--base``) against this checkout's, on the very calls a
shading="vertex" frame makes.

    python -m benchmarks.ptt_sample_ab --base OTHER_CHECKOUT [--scene chess] [--size bench]
                                       [--config '{"light_res_1":4}'] [--frames 5] [--rounds 8]
                                       [--threads 1] [--kind V] [--precompute-code CHECKOUT]

Renders ``--frames`` frames of one sequence with this checkout's PTT (the perf suite's spacing: a
5-frame sequence by default), records the arguments of every ``native.shade_mirror`` call (the
one-pass cells + shading of `fast.shade_pixels_fused`), drops frame 0's, and replays them ``--rounds``
times through each checkout's ``methods/ptt/native.py`` (the base's loaded as a file module: its own
Python wrapper and C source, built by `methods.core.native` as one library per source text), the
order of the two alternating per round and ``PRTBENCH_SETTLE`` idle before every call, as the frame
tools do. Every replayed image of this checkout is asserted equal, bit for bit, to its first; the
base's are compared with it: prints the largest |base − new| over the calls relative to the image's
peak (0: bit-identical), the median process-CPU ms of each and the ratio base / new. (Before session
29 it swapped ``native._SOURCE`` under this checkout's wrapper, which needs the two sources to share
their C signatures.) The stage is ~2/3 of a V frame at 1 thread; a frame A/B (``benchmarks.ptt_ab``) adds the
rest of the frame and its noise. The precomputation is looked up under ``--precompute-code``'s code
fingerprint (default ``--base``), as ``benchmarks.ptt_ab``."""
from __future__ import annotations

import argparse
import importlib.util
import json
import statistics
import time

import torch

from benchmarks.common import precomputed, settle, setup
from benchmarks.ptt_ab import base_fingerprint
from methods.ptt import native as N
from methods.ptt.method import PTT


def base_native(root: str):
    """``methods/ptt/native.py`` under the checkout ``root``, loaded as a file module."""
    spec = importlib.util.spec_from_file_location("_ptt_sample_ab_base_native", f"{root}/methods/ptt/native.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True, help="the other checkout (e.g. a git worktree of main)")
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--config", default='{"light_res_1":4}')
    ap.add_argument("--kind", default="V")
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--precompute-code", default=None)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    from reports import precompute_cache

    fp = base_fingerprint(a.precompute_code or a.base)
    precompute_cache._process_fingerprint = lambda module: fp
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1)
    m, _ = precomputed(PTT, scene, json.loads(a.config))
    m = m.with_bounces(0)
    _, frames, gbs, _ = setup(scene, a.size, kind=a.kind, n_frames=a.frames, seed=1)
    calls, real = [], N.shade_mirror
    N.shade_mirror = lambda *args: calls.append(args) or real(*args)
    import methods.ptt.method as _pm

    _pm.VIEW_FRAME = False  # (session 42) the frames' shade_mirror calls as separate calls, to record them
    try:
        for f, g in zip(frames, gbs):
            m.render(f, g)
    finally:
        N.shade_mirror = real
    calls = calls[1:]
    if not calls:
        raise SystemExit("no native.shade_mirror call (no compiler / AVX2, or not a shading='vertex' frame)")
    fns = {"old": base_native(a.base).shade_mirror, "new": real}
    want = [real(*c) for c in calls]
    diff = max(float((fns["old"](*c) - w).abs().max()) / max(float(w.abs().max()), 1e-30) for c, w in zip(calls, want))
    t: dict = {"old": [], "new": []}
    tw: dict = {"old": [], "new": []}
    for k in range(a.rounds):
        for which in (("old", "new") if k % 2 == 0 else ("new", "old")):
            for c, w in zip(calls, want):
                settle()
                c0, w0 = time.process_time(), time.perf_counter()
                out = fns[which](*c)
                t[which].append(time.process_time() - c0)
                tw[which].append(time.perf_counter() - w0)
                if which == "new" and not torch.equal(out, w):
                    raise AssertionError("new: the sample stage's image differs from its first replay")
    r = {w: 1e3 * statistics.median(v) for w, v in t.items()}
    r["ratio"], r["max_rel_diff"] = r["old"] / r["new"], diff
    rw = {w: 1e3 * statistics.median(v) for w, v in tw.items()}
    r["wall_old"], r["wall_new"], r["wall_ratio"] = rw["old"], rw["new"], rw["old"] / rw["new"]
    # per-round wall ratios (each round: every call of both, alternating): their spread
    k = len(calls)
    rr = sorted(statistics.median(tw["old"][i:i + k]) / statistics.median(tw["new"][i:i + k])
                for i in range(0, len(tw["new"]), k))
    r["wall_ratio_range"] = (rr[0], rr[-1])
    print(f"{a.scene} {a.kind} sample stage ({len(calls)} calls x {a.rounds} rounds, {a.threads} thread(s)), cpu: "
          f"old {r['old']:.3f} ms  new {r['new']:.3f} ms  ratio {r['ratio']:.3f}; wall old {rw['old']:.3f} ms  new "
          f"{rw['new']:.3f} ms  ratio {r['wall_ratio']:.3f} (rounds {rr[0]:.3f}-{rr[-1]:.3f})  "
          f"max |old - new| / peak {diff:.2e}",
          flush=True)
    return r


if __name__ == "__main__":
    main()
