"""What bounds a PTT V frame (shading="vertex"): its per-sample stage and the gathers in it, alone, at
a real frame's sizes (issue 14: "a micro-benchmark of the kernel that shows what bounds it").

    python -m benchmarks.ptt_gather [--scene chess] [--size bench] [--spp-side 2] [--threads 1]
                                    [--repeats 9]

No precomputation: the G-buffer is the scene's first V frame (its real face / mirror-direction
coherence), the per-(vertex, region) rows and the stacked prefiltered maps have the shapes of the
perf config (``fast.vertex_view``: 3 + 3·L + 3 columns; ``fast.EnvStack``: the env map's grid, 3·L
columns) with random values (values do not change the work). Prints, per kernel, the median wall
and process-CPU milliseconds, the bytes it touches (operands and output; for a bag, every row each
entry reads, counted at each use — neighbouring samples share rows, so most are cache hits and
"GB/s" can exceed the triad bandwidth: then the gather is not what bounds the stage) and its flops,
and the achieved GB/s and GFLOP/s next to the machine's triad bandwidth and sgemm peak measured in
the same run (``benchmarks.common.machine_limits``); "roofline" is max(bytes / triad, flops / peak) /
CPU time of each kernel.
"""
from __future__ import annotations

import argparse
import json

import torch
import torch.nn.functional as Fnn

from benchmarks.common import machine_limits, setup, wall_cpu_time
from methods.ptt import fast as _fast
from methods.ptt import specular as _spec
from reports import measure

L = 4  # lobes of the perf config (lobe_degrees 0, 7, 14, 21)




def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--spp-side", type=int, default=2)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=9)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    scene, frames, gbs, _ = setup(a.scene, a.size, kind="V", n_frames=1, spp_side=a.spp_side)
    gb, geom = gbs[0], scene.geometry()
    n_pairs = int(geom.V.shape[0])  # one region per vertex in the library scenes (FastStatic.pair_is_vertex)
    g = torch.Generator().manual_seed(0)
    env_map = scene.envmap
    H, W = env_map.data.shape[:2]
    C = 3 + 3 * L + 3
    table = torch.rand(n_pairs + 1, C, generator=g)
    env = _fast.EnvStack(torch.rand(H * (W + 1), 3 * L, generator=g), env_map.to_world.float(), H, W)
    face_pairs = geom.F.long().clamp(max=n_pairs - 1).contiguous()
    Q, S2 = gb.num_samples, gb.spp_side ** 2
    bw0, pk0 = [measure.triad_bandwidth()], [measure.matmul_peak()]
    R = _spec.mirror_dirs(gb.normal, gb.wo)
    u, v = _spec._latlong_uv(R, env.to_world)
    bw, idx, w = _fast.sample_cells(gb.bary, u, v, H, W)
    fp = _fast.rows(face_pairs, gb.face)
    acc = Fnn.embedding_bag(fp, table, per_sample_weights=bw, mode="sum")
    Ek = Fnn.embedding_bag(idx, env.ext, per_sample_weights=w, mode="sum")
    f4, i8 = 4, 8
    kernels = {
        # the whole per-sample stage as a frame runs it: G-buffer in, resolved pixels out
        "sample_stage": (lambda: _fast.shade_pixels_fused(face_pairs, table, gb.face, gb.bary, gb.normal, gb.wo,
                                                          env, L, S2),
                         Q * (8 + 8 + 12 + 12) + (Q // S2) * 3 * f4,
                         Q * 2 * (3 * C + 6 + 4 * L * 3 + L * 3)),
        # Gouraud rows: 3 (index, weight) pairs and 3 rows of C floats per sample
        "bag_pair_rows": (lambda: Fnn.embedding_bag(fp, table, per_sample_weights=bw, mode="sum"),
                          Q * (3 * (i8 + f4) + 3 * C * f4 + C * f4), Q * 2 * 3 * C),
        # E^(k) at R: 4 (index, weight) pairs and 4 rows of 3L floats per sample
        "bag_env_maps": (lambda: Fnn.embedding_bag(idx, env.ext, per_sample_weights=w, mode="sum"),
                         Q * (4 * (i8 + f4) + 4 * 3 * L * f4 + 3 * L * f4), Q * 2 * 4 * 3 * L),
        "mirror_dirs": (lambda: _spec.mirror_dirs(gb.normal, gb.wo), Q * 9 * f4, Q * 2 * 12),
        "latlong_uv": (lambda: _spec._latlong_uv(R, env.to_world), Q * 5 * f4, Q * 2 * 9),
        "sample_cells": (lambda: _fast.sample_cells(gb.bary, u, v, H, W), Q * (4 + 3 + 4 * 2 + 4) * f4, Q * 2 * 8),
        "combine_resolve": (lambda: _fast.combine_resolve(acc, Ek, L, S2), Q * (C + 3 * L) * f4 + (Q // S2) * 3 * f4,
                            Q * 2 * (3 * L + 6)),
    }
    out: dict = {"scene": a.scene, "size": a.size, "threads": a.threads, "samples": Q, "pairs": n_pairs,
                 "env_grid": [H, W], "columns": C, "kernels": {}}
    for name, (fn, nbytes, flops) in kernels.items():
        t = wall_cpu_time(fn, a.repeats)
        out["kernels"][name] = {**t, "bytes": nbytes, "flops": flops}
    B, Pk = machine_limits(out, bw0, pk0)
    print(json.dumps(out, indent=1, default=float))
    print(f"\n{a.scene} {a.size}: {Q} samples, {n_pairs} pairs, {a.threads} thread(s); machine: triad "
          f"{B / 1e9:.1f} GB/s, sgemm {Pk / 1e9:.1f} GFLOP/s")
    print(f"{'kernel':16} {'wall ms':>8} {'cpu ms':>8} {'MB touched':>10} {'GB/s(cpu)':>10} {'GFLOP/s(cpu)':>13} {'roofline(cpu)':>13}")
    for name, r in out["kernels"].items():
        c = r["cpu"]
        eff = measure.roofline(r["bytes"], r["flops"], B, Pk, c)[0]
        print(f"{name:16} {1e3 * r['wall']:8.2f} {1e3 * c:8.2f} {r['bytes'] / 1e6:10.1f} {r['bytes'] / c / 1e9:10.2f} "
              f"{r['flops'] / c / 1e9:13.2f} {eff:13.3f}")
    return out


if __name__ == "__main__":
    main()
