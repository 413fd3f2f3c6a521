"""PTT (Sun 2007) costs and Fig. 11 numbers on one scene.

    python -m benchmarks.ptt [--scene alcove] [--size test] [--spp 512] [--frames 6]
                             [--config '{"rays": 64, "cube_res": 16}']

Prints (JSON) precompute time and memory per vertex, Sun Fig. 11 (RMSE against Mitsuba of the same
bounce count and of full GI, for 0 / 1 / 2 bounces) and the median frame time of V, V&B and V,B&L
sequences (first frame excluded: it fills the caches).
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch

from benchmarks.common import setup
from methods.ptt.method import PTT
from references.metrics import rmse


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="alcove")
    ap.add_argument("--size", default="test")
    ap.add_argument("--spp", type=int, default=512)
    ap.add_argument("--frames", type=int, default=6)
    ap.add_argument("--threads", type=int, default=torch.get_num_threads())
    ap.add_argument("--config", default='{"rays": 64, "cube_res": 16}')
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    scene, (frame,), (gb,), refs = setup(a.scene, a.size, kind="V", n_frames=1, seed=0, spp_side=2,
                                         ref_spp=a.spp, bounces=(0, 1, 2, None))
    m = PTT(**json.loads(a.config))
    t = time.perf_counter()
    m.precompute(scene)
    pre = time.perf_counter() - t
    nv = int(m.V.shape[0])
    mem = m.memory()
    out = {"scene": a.scene, "size": a.size, "config": m.config, "threads": a.threads, "vertices": nv,
           "precompute_s": pre, "precompute_per_vertex_ms": 1e3 * pre / nv, "timings": m.timings,
           "memory_bytes": mem, "memory_per_vertex_kib": sum(mem.values()) / nv / 1024}
    mask = refs[0].coverage & gb.coverage
    fig11 = {}
    for b in range(m.bounces + 1):
        img = m.with_bounces(b).render(frame, gb)
        fig11[b] = {"rmse_same": rmse(img, refs[b].image, mask), "rmse_full": rmse(img, refs[None].image, mask),
                    "floor_same": refs[b].noise_floor, "mean": img[mask].mean().item(),
                    "ref_mean": refs[b].image[mask].mean().item()}
    out["fig11"] = fig11
    out["full_gi_ref_mean"] = refs[None].image[mask].mean().item()
    times = {}
    r = m.with_bounces(m.bounces)
    for kind in ("V", "VB", "VBL"):
        _, frames, gbs, _ = setup(scene, kind=kind, n_frames=a.frames, seed=1, spp_side=1)
        ts = []
        for f, g in zip(frames, gbs):
            t = time.perf_counter()
            r.render(f, g)
            ts.append(time.perf_counter() - t)
        times[kind] = {"median_s": statistics.median(ts[1:]), "all_s": ts}
    out["frame_times"] = times
    out["bytes_per_frame"] = {kind: r.bytes_per_frame(kind) for kind in ("V", "VB", "VBL")}
    print(json.dumps(out, indent=1, default=float))
    return out


if __name__ == "__main__":
    main()
