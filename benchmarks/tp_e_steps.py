"""An E frame's lighting steps of TripleProduct alone, old and new forms alternating in one process
(session 32): the frame's read pairs and the comb path's arguments are captured from one E frame
(a probe turned about +Y), then per repetition, each after a 64 MB write (caches cooled, as after the
harness's G-buffer pass), process CPU (``--threads 1``) or wall ms, medians:

* ``comb``: `native_light.comb_pairs` of the compiled `lighting.comb_taps` over every base row and
  live triangle (the old path) against `native_light.comb_pairs_uv` (each listed item's taps in the
  loop); the listed entries compared bit for bit;
* ``need``: `native_light.need` as (F, n') bools + `take` against ``need(as_bits=True)`` + `take` of the
  bit table (`native_light.NeedBits`); the pairs compared;
* ``box``: `lighting.box_filtered` by its torch passes against `native_light.box`; compared.

    python -m benchmarks.tp_e_steps [--scene creature] [--shading vertex] [--threads 1] [--reps 25]
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import torch


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--shading", default="vertex")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=25)
    ap.add_argument("--wall", action="store_true")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)

    from benchmarks.common import precomputed, setup
    from methods.core.fused import warming
    from methods.triple_product import TripleProduct, native_light as NL
    from methods.triple_product import lighting as lt

    if not NL.available():
        raise SystemExit("the native loops are not available")
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1)
    m, _ = precomputed(TripleProduct, scene, {"shading": a.shading} if a.shading != "pixel" else {})
    _, frames, gbs, _ = setup(scene, a.size, kind="E", n_frames=2, seed=0)
    with warming():
        m.render(frames[0], gbs[0])
    cap: dict = {}
    need0, pp0 = NL.need, lt.project_pairs

    def need_spy(*args, **kw):
        cap.setdefault("need", args)
        return need0(*args, **kw)

    def pairs_spy(envmap, R, geo, **kw):
        cap.setdefault("pairs", (envmap, R, geo, kw))
        return pp0(envmap, R, geo, **kw)

    NL.need, lt.project_pairs = need_spy, pairs_spy
    try:
        m.render(frames[1], gbs[1])
    finally:
        NL.need, lt.project_pairs = need0, pp0
    if "pairs" not in cap or lt.azimuth_of(cap["pairs"][0].to_world) is None:
        raise SystemExit("the E frame did not take the comb pair path")
    env, R, geo, kw = cap["pairs"]
    grid, tris, pairs, S = kw["grid"], kw["tris"], kw["pairs"], kw["supersample"]
    H, W, J = env.height, env.width, grid.n_phi
    _, wT = lt._live_sample_planes(geo, S, tris)
    u0, v0 = lt._live_azimuthal_samples(geo, S, grid, tris, R.device)
    CT = lt.comb_table(env.periodic_texels(R.device, torch.float32, planes=True), H, W, J)
    gamma = lt.azimuth_of(env.to_world)
    g = torch.tensor(gamma / (2 * math.pi), dtype=torch.float64)
    F, n = grid.size, tris.numel()
    junk = torch.empty(16 << 20)
    clock = time.perf_counter if a.wall else time.process_time
    raw = scene.envmap.data if frames[1].envmap is None else frames[1].envmap.data
    k = lt.prefilter_factor(raw.shape[0], raw.shape[1], lt.sample_spacing(geo, S))

    def comb_old():
        o, w4 = lt._kernel(lt.comb_taps)(u0, v0, g, wT, H, W, J)
        return NL.comb_pairs(pairs, o, w4, CT, grid.n_psi, J, W // J, torch.full((F, 3, n), 7.0))

    def comb_new():
        return NL.comb_pairs_uv(pairs, u0, v0, gamma / (2 * math.pi), wT, H, W, CT, grid.n_psi, J,
                                torch.full((F, 3, n), 7.0))

    def need_old():
        return NL.take(NL.need(*cap["need"]), torch.zeros(F, n, dtype=torch.bool))

    def need_new():
        return NL.take(NL.need(*cap["need"], as_bits=True), torch.zeros(F, n, dtype=torch.bool))

    steps = {"comb": (comb_old, comb_new), "need": (need_old, need_new)}
    if k > 1:
        steps["box"] = (lambda: lt.box_filtered(raw, k, native=False), lambda: lt.box_filtered(raw, k))
    out = {"scene": a.scene, "shading": a.shading, "threads": a.threads, "pairs": int(pairs.numel()),
           "clock": "wall" if a.wall else "process_cpu", "steps": {}}
    for name, (old, new) in steps.items():
        ts: dict[str, list[float]] = {"old": [], "new": []}
        res = {}
        for _ in range(a.reps):
            for tag, fn in (("old", old), ("new", new)):
                junk.add_(1.0)
                t = clock()
                res[tag] = fn()
                ts[tag].append(clock() - t)
        same = (torch.equal(res["old"][0], res["new"][0]) and res["old"][1] == res["new"][1]) if name == "need" \
            else torch.equal(res["old"], res["new"])
        mo, mn = statistics.median(ts["old"]), statistics.median(ts["new"])
        out["steps"][name] = {"old_ms": 1e3 * mo, "new_ms": 1e3 * mn, "ratio": mo / mn, "same": bool(same)}
        print(f"{name:5} old {1e3 * mo:7.3f} ms  new {1e3 * mn:7.3f} ms  {mo / mn:5.2f}x  same {bool(same)}")
    print(json.dumps(out))
    return out


if __name__ == "__main__":
    main()
