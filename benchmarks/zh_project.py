"""A new env map's SH projection alone (ZH's E frames, `ZHShadow._lighting`): ZH's folded C pass
(`methods.zh_shadow.native.project_latlong_polar_folded`, session 31) against `methods.core.sh_native`'s
pass (what ZH called before) and the torch oracle (`methods.core.sh.project_latlong_polar`), in one
process, alternating, process CPU time.

    python -m benchmarks.zh_project [--orders 4 8] [--height 256] [--width 512] [--threads 1] [--reps 40]
                                    [--idle 0]

``--idle`` seconds of sleep before each call (0.2: the perf suite's settle). Random float32 map; prints
per order each pass's median ms and the folded pass's largest difference from the oracle (relative to
the oracle's largest coefficient: float64 round-off)."""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from methods.core import sh_native
from methods.core.sh import project_latlong_polar as oracle
from methods.zh_shadow import native as zn


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--orders", type=int, nargs="+", default=[4, 8])
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=40)
    ap.add_argument("--idle", type=float, default=0.0)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    img = torch.rand(a.height, a.width, 3, generator=torch.Generator().manual_seed(0)) * 4.0
    passes = {"folded": zn.project_latlong_polar_folded, "sh_native": sh_native.project_latlong_polar,
              "oracle": oracle}
    out = {}
    for order in a.orders:
        want = oracle(img, order)
        got = zn.project_latlong_polar_folded(img, order)
        err = None if got is None else float((got - want).abs().max() / want.abs().max())
        t: dict = {k: [] for k in passes}
        names = list(passes)
        for i in range(a.reps + 2):
            for k in (names if i % 2 == 0 else names[::-1]):
                if a.idle > 0:
                    time.sleep(a.idle)
                c = time.process_time()
                passes[k](img, order)
                if i >= 2:
                    t[k].append(time.process_time() - c)
        med = {k: 1e3 * statistics.median(v) for k, v in t.items()}
        out[order] = {"ms": med, "rel_err": err}
        print(f"order {order}: " + ", ".join(f"{k} {v:.3f} ms" for k, v in med.items())
              + f"; folded vs sh_native {med['sh_native'] / med['folded']:.2f}x; rel. diff from the oracle {err}",
              flush=True)
    return out


if __name__ == "__main__":
    main()
