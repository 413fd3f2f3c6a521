"""Micro-benchmark of the floor every per-sample stage sits on (issue 14; `methods.core.fused`):
the Gouraud resolve of a 256² × 2×2 frame — gather three vertex colours per sample, weight them by
the barycentrics, sum — eager torch vs ``torch.compile`` with a static and with a symbolic row count,
against the compulsory bytes at the triad bandwidth measured in the same run.

    python -m benchmarks.fused [--samples 262144] [--vertices 10000] [--threads 2]
"""
from __future__ import annotations

import argparse
import time

import torch

from methods.core.fused import fused, map_rows
from reports.measure import triad_bandwidth


def resolve(vidx, bw, col):
    return (col[vidx.long()] * bw[..., None]).sum(1)


def _median_ms(fn, *a, reps: int = 21) -> float:
    for _ in range(3):
        fn(*a)
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        fn(*a)
        ts.append(time.perf_counter() - t)
    return sorted(ts)[reps // 2] * 1e3


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=256 * 256 * 4)
    ap.add_argument("--vertices", type=int, default=10_000)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    g = torch.Generator().manual_seed(0)
    q, v = a.samples, a.vertices
    col = torch.rand(v, 3, generator=g)
    vidx = torch.randint(0, v, (q, 3), dtype=torch.int32, generator=g)
    bw = torch.rand(q, 3, generator=g)
    bw_bytes = triad_bandwidth()
    need = (vidx.numel() * 4 + bw.numel() * 4 + q * 3 * 4 + col.numel() * 4)
    floor = need / bw_bytes * 1e3
    fr = fused(resolve)
    static = _median_ms(lambda: map_rows(fr, (vidx, bw), (col,)))
    symbolic_fn = torch.compile(resolve, dynamic=True)
    symbolic = _median_ms(symbolic_fn, vidx, bw, col)
    eager = _median_ms(resolve, vidx, bw, col)
    err = (map_rows(fr, (vidx, bw), (col,)) - resolve(vidx, bw, col)).abs().max().item()
    print(f"Q = {q} samples, V = {v} vertices, {a.threads} threads; triad {bw_bytes / 1e9:.1f} GB/s")
    print(f"compulsory bytes {need / 1e6:.2f} MB -> floor {floor:.3f} ms")
    for name, ms in (("eager torch", eager), ("compiled, symbolic rows", symbolic),
                     ("compiled, static blocks (map_rows)", static)):
        print(f"  {name:36s} {ms:8.3f} ms   roofline {floor / ms:6.1%}")
    print(f"max |compiled - eager| = {err:.2e}")


if __name__ == "__main__":
    main()
