"""Same-process before/after of PTT's native sample stage alone (issue 14): the C source of a base
checkout's ``methods/ptt/native.py`` (``--base``) against this checkout's, on the very calls a
shading="vertex" frame makes.

    python -m benchmarks.ptt_sample_ab --base OTHER_CHECKOUT [--scene chess] [--size bench]
                                       [--config '{"light_res_1":4}'] [--frames 5] [--rounds 8]
                                       [--threads 1] [--kind V] [--precompute-code CHECKOUT]

Renders ``--frames`` frames of one sequence with this checkout's PTT (the perf suite's spacing: a
5-frame sequence by default), records the arguments of every ``native.shade_mirror`` call (the
one-pass cells + shading of `fast.shade_pixels_fused`), drops frame 0's, and replays them ``--rounds``
times through the library built from each source (``native._SOURCE`` swapped: `methods.core.native`
builds one library per source text), the order of the two alternating per round and
``PRTBENCH_SETTLE`` idle before every call, as the frame tools do. Every replayed image is asserted
equal, bit for bit, to this checkout's. Prints the median process-CPU ms of each and the ratio
base / new. The stage is ~2/3 of a V frame at 1 thread; a frame A/B (``benchmarks.ptt_ab``) adds the
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


def base_source(root: str) -> str:
    """``_SOURCE`` of ``methods/ptt/native.py`` under the checkout ``root`` (loaded as a file module)."""
    spec = importlib.util.spec_from_file_location("_ptt_sample_ab_base_native", f"{root}/methods/ptt/native.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod._SOURCE


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
    try:
        for f, g in zip(frames, gbs):
            m.render(f, g)
    finally:
        N.shade_mirror = real
    calls = calls[1:]
    if not calls:
        raise SystemExit("no native.shade_mirror call (no compiler / AVX2, or not a shading='vertex' frame)")
    new_src = N._SOURCE
    sources = {"old": base_source(a.base), "new": new_src}
    want = [real(*c) for c in calls]
    t: dict = {"old": [], "new": []}
    try:
        for k in range(a.rounds):
            for which in (("old", "new") if k % 2 == 0 else ("new", "old")):
                N._SOURCE = sources[which]
                for c, w in zip(calls, want):
                    settle()
                    c0 = time.process_time()
                    out = real(*c)
                    t[which].append(time.process_time() - c0)
                    if not torch.equal(out, w):
                        raise AssertionError(f"{which}: the sample stage's image differs from this checkout's")
    finally:
        N._SOURCE = new_src
    r = {w: 1e3 * statistics.median(v) for w, v in t.items()}
    r["ratio"] = r["old"] / r["new"]
    print(f"{a.scene} {a.kind} sample stage ({len(calls)} calls x {a.rounds} rounds, {a.threads} thread(s), cpu): "
          f"old {r['old']:.3f} ms  new {r['new']:.3f} ms  ratio {r['ratio']:.3f}  (images bit-equal)", flush=True)
    return r


if __name__ == "__main__":
    main()
