"""Micro-benchmark of the lighting projection of TripleProduct (Ma 2006 §4.1; `lighting.project_env`):
the compiled kernel `lighting.env_block` alone on a frame's real sizes (the default grid's 544 frames
× 20·4^level fine triangles × 4^light_supersample samples, the bench chess probe prefiltered as the
method does), and two ablations that show what bounds it:

* ``no_trig``: (u, v) from the emitter-frame direction by a linear map instead of atan2 / acos (same
  gathers, same arithmetic otherwise) — the cost of the two transcendentals;
* ``no_gather``: the bilinear weights summed without the 12 texel loads — the cost of the gathers;
* ``azimuthal``: the E-frame kernel (`lighting.env_block_azimuthal`: the map turned about +Y, each
  frame's (u, v) the shifted base coordinates — no rotation, no atan2 / acos; 31 flops per sample).

Prints per variant the median process-CPU ms per lighting change (1 thread, or ``--threads``), ns per
sample, and the achieved GFLOP/s of the frame-cost count (`fast_eval.relight_flops`: 45 flops per
sample, 31 azimuthal) next to the machine's matmul peak and triad bandwidth (`reports.measure`).

    python -m benchmarks.tp_lighting [--threads 1] [--reps 7] [--scene chess] [--size bench]
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import torch


def _variant(kind: str):
    from methods.core.latlong import bilinear_taps

    def block(R, cp, wT, T, planes, H: int, W: int):
        cx, cy, cz = cp[0][None], cp[1][None], cp[2][None]
        Rb = R[:, :, :, None, None]
        dw = [cx * Rb[:, 0, i] + cy * Rb[:, 1, i] + cz * Rb[:, 2, i] for i in range(3)]
        d = [dw[0] * T[0, k] + dw[1] * T[1, k] + dw[2] * T[2, k] for k in range(3)]
        if kind == "no_trig":
            u, v = d[0] * 0.3 + 0.5 * d[2], d[1] * 0.5 + 0.5
        else:
            u = torch.atan2(d[0], -d[2]) * (0.5 / math.pi)
            v = torch.acos(d[1].clamp(-1.0, 1.0)) * (1.0 / math.pi)
        idx, fx, fy = bilinear_taps(u, v, H, W)
        w0x, w0y = 1.0 - fx, 1.0 - fy
        out = []
        for ch in range(3):
            if kind == "no_gather":
                val = (w0y * (w0x * planes[ch, 0] + fx * planes[ch, 1]) + fy * (w0x * planes[ch, 2] + fx * planes[ch, 3])
                       + idx.to(torch.float32) * 1e-30)
            else:
                e = planes[ch]
                val = w0y * (w0x * e[idx] + fx * e[idx + 1]) + fy * (w0x * e[idx + W + 1] + fx * e[idx + W + 2])
            out.append((val * wT[None]).sum(1))
        return torch.stack(out, 1)

    return block


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--level", type=int, default=3)
    ap.add_argument("--supersample", type=int, default=2)
    ap.add_argument("--only", default="", help="comma-separated variants (default: all)")
    a = ap.parse_args(argv)

    from methods.core.fused import fused, map_rows
    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt
    from reports import measure
    from scenes.library import get_scene

    torch.set_num_threads(a.threads)
    geo = Geodesic(a.level)
    R = lt.grid_frames(lt.FrameGrid(17, 32, 1)).float()
    env = lt.prefiltered(get_scene(a.scene, a.size).envmap, geo, a.supersample)
    cp, wT = lt._env_sample_planes(geo, a.supersample)
    planes = env.periodic_texels(planes=True)
    args = (cp, wT, env.to_world.float(), planes, env.height, env.width)
    samples = R.shape[0] * cp.shape[1] * cp.shape[2]
    flops = 45 * samples
    out = {"frames": R.shape[0], "samples": samples, "env": [env.height, env.width], "threads": a.threads,
           "block": lt.env_block_frames(R.shape[0], cp.shape[1] * cp.shape[2]), "matmul_peak_gflops": measure.matmul_peak() / 1e9,
           "triad_gbs": measure.triad_bandwidth() / 1e9}
    # E frames (a map turned about +Y): shifted base coordinates, no rotation or trig
    grid = lt.FrameGrid(17, 32, 1)
    u0, v0 = lt._azimuthal_samples(geo, a.supersample, grid)
    f_ = torch.arange(grid.size)
    base = f_ // (grid.n_phi * grid.n_psi) * grid.n_psi + f_ % grid.n_psi
    shift = torch.remainder((f_ // grid.n_psi % grid.n_phi).double() / grid.n_phi - 0.7 / (2 * math.pi), 1.0)
    az = ((shift, base), (u0, v0, wT, planes, env.height, env.width))
    kinds = (("env_block", lt.env_block, (R,), args), ("no_trig", _variant("no_trig"), (R,), args),
             ("no_gather", _variant("no_gather"), (R,), args), ("azimuthal", lt.env_block_azimuthal, *az))
    for name, fn, rows, fargs in kinds:
        if a.only and name not in a.only.split(","):
            continue
        f = fused(fn)
        map_rows(f, rows, fargs, chunk=out["block"])                  # compile / warm up
        ts = []
        for _ in range(a.reps):
            t = time.process_time()
            map_rows(f, rows, fargs, chunk=out["block"])
            ts.append(time.process_time() - t)
        t = statistics.median(ts)
        fl = 31 * samples if name == "azimuthal" else flops     # its frame-cost count (`relight_flops`)
        out[name] = {"cpu_ms": 1e3 * t, "ns_per_sample": 1e9 * t / samples * a.threads, "gflops": fl / t / 1e9}
        print(name, json.dumps(out[name]), flush=True)
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
