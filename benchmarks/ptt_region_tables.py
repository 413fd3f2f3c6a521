"""Micro-benchmark of a PTT VB frame's region tables (issue 14, session 40): ``fast.region_tables``' W_r by
the base's one-thread pass (``native.region_rows`` into a fresh table, under ``torch_threads(1)`` as
`PTT.render` ran it) against ``native.region_tables`` (the rows split over ``--threads`` OpenMP threads,
written into the previous frame's table), on the chess bench shapes (R = 3 regions, P = 4 basis
functions, K = 16, 48 × 48 view table; random values: the work does not depend on them).

    python -m benchmarks.ptt_region_tables [--threads 2] [--reps 200] [--flush-mb 64]

Each call after ``PRTBENCH_SETTLE`` idle and a pass over ``--flush-mb`` MB (the frame's tables come
cold after the harness's G-buffer), the two alternating; prints the median wall and process-CPU ms of
each and asserts the tables equal bit for bit. At 2 threads the wall time is what the frame waits."""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.common import settle
from methods.core.threads import torch_threads
from methods.ptt import fast, native


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--reps", type=int, default=200)
    ap.add_argument("--flush-mb", type=int, default=64)
    ap.add_argument("--R", type=int, default=3)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    R, P, K, T = a.R, 4, 16, 48
    g = torch.Generator().manual_seed(0)
    W_rows = fast.view_table_rows(torch.randn(P * K, T, T, generator=g), K)
    flush = torch.zeros(a.flush_mb << 18)
    prev = None
    t = {"old": [], "new": []}
    c = {"old": [], "new": []}
    for i in range(a.reps):
        H = torch.rand(R, P, 3, generator=g)
        for which in (("old", "new") if i % 2 == 0 else ("new", "old")):
            settle()
            flush.add_(1.0)
            t0, c0 = time.perf_counter(), time.process_time()
            if which == "old":
                with torch_threads(1):
                    Hl = H.permute(1, 0, 2)[:, :, None, None, :].expand(P, R, 1, K, 3).reshape(P, R, 1, K * 3)
                    old = native.region_rows(W_rows, Hl).view(R * T * T, K * 3)
            else:
                with torch_threads(1):
                    prev = native.region_tables(W_rows, H, a.threads, prev)
            t[which].append(time.perf_counter() - t0)
            c[which].append(time.process_time() - c0)
        assert torch.equal(old, prev)
    out = {w: (1e3 * statistics.median(t[w]), 1e3 * statistics.median(c[w])) for w in t}
    print(f"threads {a.threads}: old {out['old'][0]:.3f} / {out['old'][1]:.3f} ms, new {out['new'][0]:.3f} / "
          f"{out['new'][1]:.3f} ms (wall / cpu), wall ratio {out['old'][0] / out['new'][0]:.2f}")
    return out


if __name__ == "__main__":
    main()
