"""The cost of reading an on/off switch from the environment with the caches a benchmark frame starts
with (`methods.core.switches`, session 43).

    python -m benchmarks.switches [--calls 400]

Per call, alternating: a 64 MB buffer written (the harness rasterises a G-buffer and scores the last
image between frames), then one timed read — ``os.environ.get`` + strip/compare (the old
``compile_enabled``), `switches.on`, and nothing (the timer's own cost) — medians in µs.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from methods.core import switches


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=400)
    a = ap.parse_args(argv)
    buf = np.zeros(16 << 20, dtype=np.float32)
    name = "PRTBENCH_COMPILE"
    ways = {"os.environ.get": lambda: os.environ.get(name, "1").strip() not in ("0", "false", "no", "off"),
            "switches.on": lambda: switches.on(name),
            "nothing": lambda: None}
    got = {k: [] for k in ways}
    for _ in range(a.calls):
        for k, f in ways.items():
            buf[:] = 1.0
            t = time.perf_counter_ns()
            f()
            got[k].append(time.perf_counter_ns() - t)
    for k, v in got.items():
        print(f"{k:>16}: median {statistics.median(v) / 1e3:6.2f} us, p90 {np.percentile(v, 90) / 1e3:6.2f} us")


if __name__ == "__main__":
    main()
