"""Same-process A/B of one ZHShadow switch (a class attribute or a `methods.zh_shadow.native` module flag) with this
checkout on both sides: frames of bench-size creature sequences rendered by two objects, the switch on for one and
off for the other, alternating which goes first; before each timed frame a 64 MB buffer is written and the suite's
idle kept (`settle`), so every frame starts with cold caches as in the perf harness. Medians of process CPU time,
frames 0-1 of each repeat untimed (frame 0 a full change, frame 1 the first lighting-only frame's build).

    python -m benchmarks.zh41l_flag_ab --config '{}' --flag steady_plane_operator [--kinds L E] [--repeat 10]
        [--threads 1] [--precompute-code DIR]

``--flag native.NAME`` switches a module flag of `methods.zh_shadow.native` instead (read while the setups are made:
the module flag is set for the "off" object's frames only). ``--flag none`` is an A/A run (the noise).
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from benchmarks.common import apply_ab_options, precomputed, settle, setup


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="{}")
    ap.add_argument("--flag", required=True)
    ap.add_argument("--kinds", nargs="+", default=["L", "E"])
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--precompute-code", default=None)
    a = ap.parse_args(argv)
    apply_ab_options(a)
    from methods.zh_shadow import native as zn
    from methods.zh_shadow.method import ZHShadow

    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(ZHShadow, scene, json.loads(a.config))
    buf = torch.empty(16 * 1024 * 1024)
    module = a.flag.startswith("native.")
    name = a.flag.split(".", 1)[1] if module else a.flag
    out = {}
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, "bench", kind=kind, n_frames=a.frames, seed=a.seed)
        on, off = m.with_render_config(), m.with_render_config()
        if not module and name != "none":
            setattr(off, name, False)
        t: dict = {"on": [], "off": []}
        for rep in range(a.repeat):
            for i, (f, g) in enumerate(zip(frames, gbs)):
                for w in (("on", "off") if (rep + i) % 2 else ("off", "on")):
                    obj = on if w == "on" else off
                    if module:
                        setattr(zn, name, w == "on")
                    buf.fill_(float(i))
                    settle()
                    c = time.process_time()
                    obj.render(f, g)
                    d = time.process_time() - c
                    if i >= 2:
                        t[w].append(d)
        if module:
            setattr(zn, name, True)
        b, n = statistics.median(t["off"]), statistics.median(t["on"])
        out[kind] = b / n
        print(f"{kind} {a.flag}: off {b * 1e3:.3f} ms on {n * 1e3:.3f} ms ratio {b / n:.3f} ({len(t['on'])} frames "
              f"a side)", flush=True)
    return out


if __name__ == "__main__":
    main()
