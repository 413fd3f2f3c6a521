"""Same-process before/after of PTT's BRDF navigation (`transport.LobeBasis._fit`, the least-squares
coordinates H of a changed material, Sun 2007 §3.1): a base checkout's ``LobeBasis`` (``--base``,
e.g. /work/base) against this checkout's, on the perturbed materials of VB frames.

    python -m benchmarks.ptt_fit --base OTHER_CHECKOUT [--scenes chess creature] [--frames 12]

Frames alternate which version goes first; frame 0 (grid set-up) is not counted. Prints per scene
the median process-CPU ms of one frame's fits (1 thread), the ratio base / new and the largest
relative |base − new| of the coordinates."""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from benchmarks.common import checkout_class, get_scene
from methods.ptt import transport as tp
from scenes.sequences import perturb_material


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True)
    ap.add_argument("--scenes", nargs="+", default=["chess", "creature"])
    ap.add_argument("--size", default="bench")
    ap.add_argument("--frames", type=int, default=12)
    a = ap.parse_args(argv)
    torch.set_num_threads(1)
    Old = checkout_class(a.base, "methods.ptt.transport", "LobeBasis")
    out = {}
    for name in a.scenes:
        sc = get_scene(name, a.size)
        new = tp.scene_basis(sc.materials)
        old = Old(list(new.lobes), diffuse=new.diffuse, fit_res=new.fit_res)
        rng = np.random.default_rng(0)
        mats = [[perturb_material(m, rng) for m in sc.materials.values()] for _ in range(a.frames)]
        t: dict = {"old": [], "new": []}
        dmax = 0.0
        for k, ms in enumerate(mats):
            res = {}
            for which in (("old", "new") if k % 2 == 0 else ("new", "old")):
                b = old if which == "old" else new
                c0 = time.process_time()
                res[which] = [b._fit(m) for m in ms]
                t[which].append(time.process_time() - c0)
            for x, y in zip(res["old"], res["new"]):
                dmax = max(dmax, float(((x - y).abs() / x.abs().max().clamp_min(1e-300)).max()))
        mo, mn = statistics.median(t["old"][1:]), statistics.median(t["new"][1:])
        out[name] = {"old_cpu_ms": 1e3 * mo, "new_cpu_ms": 1e3 * mn, "ratio": mo / mn, "max_rel_diff": dmax}
        print(f"{name}: one frame's fits old {1e3 * mo:.2f} ms, new {1e3 * mn:.2f} ms (cpu), ratio {mo / mn:.2f}, "
              f"max rel |old-new| {dmax:.1e}", flush=True)
    return out


if __name__ == "__main__":
    main()
