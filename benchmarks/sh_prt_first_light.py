"""SH PRT's FIRST lighting-only frame (the relight cache build, `SHPRT._relight_build`) against another
checkout (session 40, issue 14: the creature L cell's first timed frame read ~1 s in every perf run).

    python -m benchmarks.sh_prt_first_light --baseline DIR [--precompute-code DIR] [--kinds L E]
                                            [--repeat 9] [--threads 1]
    python -m benchmarks.sh_prt_first_light --fresh --baseline DIR [--precompute-code DIR] [--repeat 3]

Default: one process, the creature bench (bounces 0, the perf cells' config); per repeat and kind, each
object's cache reset, frame 0 of the sequence rendered (a full change, untimed), `settle`, then frame 1
(the first lighting-only frame: the build and the shading from it) timed, old and new alternating which
goes first; medians of process CPU (first repeat dropped). ``torch._dynamo`` is imported before the clock:
a one-time import cost is not what this mode measures.

``--fresh``: each checkout in fresh interpreters (alternating, ``--repeat`` each), as a perf process
renders its cells: creature bench V, L, E sequences of 5 frames in that order (frame 0 untimed in the
suite); per frame the process CPU ms, and whether ``torch._dynamo`` got imported. Shows one-time costs
(an import, a first compile) that the same-process mode hides.
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import statistics
import subprocess
import sys
import time

_CHILD = r"""
import json, sys, time, torch
torch.set_num_threads(int(sys.argv[1]))
pc = sys.argv[2]
if pc:
    from reports import precompute_cache
    from reports.store import code_closure_fingerprint
    precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, pc)
from benchmarks.common import precomputed, setup
from methods.sh_prt.method import SHPRT
scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
m, _ = precomputed(SHPRT, scene, {})
m = m.with_bounces(0)
out = {}
for kind in ("V", "L", "E"):
    _, frames, gbs, _ = setup(scene, "bench", kind=kind, n_frames=5, seed=0)
    ts = []
    for f, gb in zip(frames, gbs):
        time.sleep(0.2)
        c = time.process_time()
        m.render(f, gb)
        ts.append(1e3 * (time.process_time() - c))
    out[kind] = ts
out["dynamo"] = "torch._dynamo" in sys.modules
print("RESULT " + json.dumps(out))
"""


def fresh(a) -> None:
    runs: dict[str, list] = {"base": [], "new": []}
    roots = {"base": os.path.abspath(a.baseline), "new": os.path.dirname(os.path.dirname(os.path.abspath(__file__)))}
    for i in range(a.repeat):
        for w in (("new", "base") if i % 2 == 0 else ("base", "new")):
            env = dict(os.environ, PYTHONPATH=roots[w])
            r = subprocess.run([sys.executable, "-c", _CHILD, str(a.threads), a.precompute_code or ""], cwd=roots[w],
                               env=env, capture_output=True, text=True)
            line = [x for x in r.stdout.splitlines() if x.startswith("RESULT ")]
            if not line:
                raise RuntimeError(r.stderr[-3000:])
            res = json.loads(line[-1][7:])
            runs[w].append(res)
            print(w, " ".join(f"{k} [" + " ".join(f"{t:.1f}" for t in res[k]) + "]" for k in ("V", "L", "E")),
                  "dynamo imported" if res["dynamo"] else "", flush=True)
    for k in ("V", "L", "E"):
        b = statistics.median(r[k][1] for r in runs["base"])
        n = statistics.median(r[k][1] for r in runs["new"])
        print(f"{k} frame 1 (first timed; L/E: the relight build) process CPU ms: base {b:.1f} new {n:.1f} "
              f"ratio {b / n:.2f}")


def same_process(a) -> None:
    import torch
    import torch._dynamo  # noqa: F401  (a one-time import: `--fresh` measures it)

    from benchmarks.common import apply_ab_options, checkout_modules, precomputed, settle, setup
    from benchmarks.vview import baseline_class

    apply_ab_options(a)
    from methods.sh_prt.method import SHPRT as New

    Base = baseline_class("sh_prt", a.baseline)
    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(New, scene, {})
    m = m.with_bounces(0)
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, "bench", kind=kind, n_frames=2, seed=0)
        t = {"new": [], "base": []}
        imgs = {}
        for i in range(a.repeat):
            for w in (("new", "base") if i % 2 == 0 else ("base", "new")):
                obj = copy.copy(m)
                obj._reset_cache()
                if w == "base":
                    obj.__class__ = Base
                root = a.baseline if w == "base" else None
                ctx = checkout_modules(root) if root else _null()
                with ctx:
                    obj.render(frames[0], gbs[0])
                    settle()
                    c = time.process_time()
                    img = obj.render(frames[1], gbs[1])
                    t[w].append(time.process_time() - c)
                imgs[w] = img
        b, n = statistics.median(t["base"][1:]), statistics.median(t["new"][1:])
        d = float((imgs["new"] - imgs["base"]).abs().max() / imgs["base"].abs().max())
        print(f"{kind} first lighting-only frame, {a.threads} thread(s), process CPU: base {b * 1e3:.2f} ms "
              f"new {n * 1e3:.2f} ms ratio {b / n:.2f}; max |new - base| / max |base| {d:.2e}", flush=True)


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", required=True)
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--kinds", nargs="+", default=["L", "E"])
    ap.add_argument("--repeat", type=int, default=9)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--fresh", action="store_true")
    a = ap.parse_args(argv)
    fresh(a) if a.fresh else same_process(a)


if __name__ == "__main__":
    main()
