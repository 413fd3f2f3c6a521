"""How much of a frame's time is the perf suite's protocol: each frame timed right after the
harness made its G-buffer (`reports.measure_cell`: Mitsuba rasterises, torch's pool idles), against
the same frames timed back to back with their G-buffers made ahead (the papers' fps loops).

    python -m benchmarks.frame_protocol --method zh_shadow [--config '{}'] [--scene creature]
        [--kinds V L E] [--frames 8] [--repeat 2] [--threads 2] [--spp-side 2]

Per kind: the method precomputed once (the harness's cache), then ``--repeat`` alternating passes
over the same ``--frames`` + 1 frames in order — "suite": ``make_gbuffer`` then the timed
``render``; "b2b": the G-buffers made ahead, ``render`` after ``render`` — each pass's frame 0
untimed. Prints the median wall ms of each, their ratio, and the roofline efficiency of each under
the method's ``frame_cost`` and this run's best triad / sgemm (`reports.measure`). Images are the
same in both (the same frames in the same order; checked). Written in session 31 for the open
question of which protocol the suite's run-time table should use; it changes nothing in the suite.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--method", required=True)
    ap.add_argument("--config", default="{}")
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--kinds", nargs="+", default=["V", "L", "E"])
    ap.add_argument("--frames", type=int, default=8)
    ap.add_argument("--repeat", type=int, default=2)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--per-frame", action="store_true", help="print each frame's ms of the first pass of each protocol")
    ap.add_argument("--spp-side", type=int, default=2, help="G-buffer samples per pixel side (the perf suite's: 2)")
    a = ap.parse_args(argv)
    if a.frames < 2 or a.repeat < 1 or a.threads < 1:
        raise SystemExit("--frames must be >= 2, --repeat and --threads >= 1")

    from benchmarks.common import precomputed, setup
    from methods.registry import get_method
    from references.gbuffer import make_gbuffer
    from reports import measure

    torch.set_num_threads(a.threads)
    config = json.loads(a.config)
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1)
    method, _ = precomputed(get_method(a.method), scene, config)
    bw, peak = [measure.triad_bandwidth()], [measure.matmul_peak()]
    out: dict = {"method": a.method, "config": config, "scene": a.scene, "size": a.size, "threads": a.threads,
                 "kinds": {}}
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames + 1, seed=a.seed, spp_side=a.spp_side)
        times: dict[str, list[float]] = {"suite": [], "b2b": []}
        first: dict[str, list[float]] = {"suite": [], "b2b": []}
        images: dict[str, list] = {"suite": [], "b2b": []}
        for rep in range(a.repeat):
            for proto in ("suite", "b2b"):
                for i, frame in enumerate(frames):
                    gb = make_gbuffer(scene, frame, a.spp_side) if proto == "suite" else gbs[i]
                    t0 = time.perf_counter()
                    img = method.render(frame, gb)
                    dt = time.perf_counter() - t0
                    if i > 0:
                        times[proto].append(dt)
                    if rep == 0:
                        first[proto].append(dt)
                    if rep == 0 and i == len(frames) - 1:
                        images[proto] = img.detach().clone()
        same = bool(torch.equal(images["suite"], images["b2b"]))
        cost = method.frame_cost(kind, gbs[-1].num_samples, pixels=gbs[-1].height * gbs[-1].width)
        out["kinds"][kind] = r = {p: statistics.median(t) for p, t in times.items()}
        r["same_image"] = same
        r["first_pass_ms"] = {p: [round(1e3 * t, 2) for t in v] for p, v in first.items()}
        if a.per_frame:
            for p, v in r["first_pass_ms"].items():
                print(f"{kind} {p} first pass ms (frame 0 untimed in the medians): {v}")
        r["cost"] = None if cost is None else (float(cost.bytes), float(cost.flops))
    bw.append(measure.triad_bandwidth())
    peak.append(measure.matmul_peak())
    B, Pk = max(bw), max(peak)
    print(f"{a.method} {a.config} {a.scene} {a.size}, {a.threads} threads, triad {B / 1e9:.1f} GB/s, "
          f"sgemm {Pk / 1e9:.0f} GFLOP/s; median of {a.frames * a.repeat} frames each")
    print(f"{'kind':6} {'suite ms':>9} {'b2b ms':>8} {'ratio':>6} {'suite eff':>10} {'b2b eff':>8}  same image")
    for kind, r in out["kinds"].items():
        eff = {}
        for p in ("suite", "b2b"):
            rl = None if r["cost"] is None else measure.roofline(r["cost"][0], r["cost"][1], B, Pk, r[p])
            eff[p] = rl[0] if rl else float("nan")
            r[f"{p}_efficiency"] = eff[p]
        print(f"{kind:6} {1e3 * r['suite']:9.2f} {1e3 * r['b2b']:8.2f} {r['suite'] / r['b2b']:6.2f} "
              f"{100 * eff['suite']:9.1f}% {100 * eff['b2b']:7.1f}%  {r['same_image']}")
    return out


if __name__ == "__main__":
    main()
