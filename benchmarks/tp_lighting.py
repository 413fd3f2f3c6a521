"""Micro-benchmark of the lighting projection of TripleProduct (Ma 2006 §4.1; `lighting.project_env`):
its compiled kernels alone on a frame's real sizes (the default grid's 544 frames × 20·4^level fine
triangles × 4^light_supersample samples, the bench probe prefiltered as the method does, blocks of
`lighting.env_block_frames` frames), to show what bounds a lighting change:

* ``taps``: `lighting.env_taps` — per sample the folded rotation, atan2 / acos and the bilinear
  footprint (L frames: a map on a tilted axis);
* ``taps_azimuthal``: `lighting.env_taps_azimuthal` — the E-frame footprints (the map turned about
  +Y: the base coordinates shifted in u, no rotation or trig);
* ``means``: `lighting.quad_means_coeffs` — per sample one 64-byte quad row of the map
  (`methods.core.latlong.quad_texels`) weighted into its fine triangle's mean, then the forward
  transform.

Prints per kernel the median process-CPU ms per lighting change (1 thread, or ``--threads``), ns per
sample, and the achieved GFLOP/s of its share of the frame-cost count (`fast_eval.relight_flops`:
per sample 15 rotation + 24 bilinear + 6 weighted sum; 1 shift instead of the rotation on E frames)
and GB/s of the bytes it reads and writes, next to the machine's matmul peak and triad bandwidth
(`reports.measure`).

    python -m benchmarks.tp_lighting [--threads 1] [--reps 7] [--scene chess] [--size bench]
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
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--level", type=int, default=3)
    ap.add_argument("--supersample", type=int, default=2)
    a = ap.parse_args(argv)

    from methods.core.latlong import quad_lanes, quad_texels
    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as lt
    from reports import measure
    from scenes.library import get_scene

    torch.set_num_threads(a.threads)
    geo = Geodesic(a.level)
    grid = lt.FrameGrid(17, 32, 1)
    R = lt.grid_frames(grid).float()
    env = lt.prefiltered(get_scene(a.scene, a.size).envmap, geo, a.supersample)
    cp, wT = lt._env_sample_planes(geo, a.supersample)
    H, W = env.height, env.width
    Q, lanes = quad_texels(env.periodic_texels(planes=True), H, W), quad_lanes()
    T = env.to_world.float()
    n, S = cp.shape[1], cp.shape[2]
    samples = R.shape[0] * S * n
    chunk = lt.env_block_frames(R.shape[0], S * n)
    out = {"frames": R.shape[0], "samples": samples, "env": [H, W], "threads": a.threads, "block": chunk,
           "matmul_peak_gflops": measure.matmul_peak() / 1e9, "triad_gbs": measure.triad_bandwidth() / 1e9}
    u0, v0 = lt._azimuthal_samples(geo, a.supersample, grid)
    f_ = torch.arange(grid.size)
    base = f_ // (grid.n_phi * grid.n_psi) * grid.n_psi + f_ % grid.n_psi
    shift = torch.remainder((f_ // grid.n_psi % grid.n_phi).double() / grid.n_phi - 0.7 / (2 * math.pi), 1.0)
    taps, taps_az, means = lt._kernel(lt.env_taps), lt._kernel(lt.env_taps_azimuthal), lt._kernel(lt.quad_means_coeffs)
    starts = range(0, R.shape[0] - chunk + 1, chunk)                   # whole blocks only
    done = len(starts) * chunk * S * n
    blocks = [taps(R[s:s + chunk], cp, T, H, W) for s in starts]
    kinds = {  # name: (call, flops per sample of the count, bytes per sample read + written)
        "taps": (lambda: [taps(R[s:s + chunk], cp, T, H, W) for s in starts], 15 + 4, 4 * 3),
        "taps_azimuthal": (lambda: [taps_az(shift[s:s + chunk], base[s:s + chunk], u0, v0, H, W) for s in starts],
                           1 + 4, 8 + 4 + 4 * 3),
        "means": (lambda: [means(*b, wT, Q, lanes) for b in blocks], 20 + 6, 4 * 3 + 64),
    }
    for name, (call, fl, by) in kinds.items():
        call()                                                          # compile / warm up
        ts = []
        for _ in range(a.reps):
            t = time.process_time()
            call()
            ts.append(time.process_time() - t)
        t = statistics.median(ts)
        out[name] = {"cpu_ms": 1e3 * t * samples / done, "ns_per_sample": 1e9 * t / done * a.threads,
                     "gflops": fl * done / t / 1e9, "gbs": by * done / t / 1e9}
        print(name, json.dumps(out[name]), flush=True)
    print(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
