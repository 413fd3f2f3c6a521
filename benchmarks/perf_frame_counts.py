"""Per timed frame of one perf-suite cell: its render time, the G-buffer's hit count and (triple product) the
lighting pairs it projected — the suite's own frame loop (`reports.measure_cell._measure`) with `render`
wrapped, in this process (issue 14, session 43).

    python -m benchmarks.perf_frame_counts METHOD SCENE KIND [--config '{}'] [--threads 2]

Session 43 found with it why the triple product's per-pixel V / VL cells have one frame +10-15 ms slower in
every run at fixed positions (chess V frame 4, chess VL 4, creature V 2, creature VL 3): exactly those frames'
G-buffers hold one missed sample of 262,144 (hits 262,143), which sends `TripleProduct.render` from its all-hit
path (slices) to its gather path; the lighting's lazy projection is not it (the warm-up frame projects all 544
grid frames, the timed frames 0 pairs).
"""
from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import torch

from reports import measure_cell, suites

_STATS = ("projected_pairs", "projected_frames")


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("method")
    ap.add_argument("scene")
    ap.add_argument("kind")
    ap.add_argument("--config", default=None, help="the cell's config exactly as the suite writes it (default: the first)")
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args(argv)
    cells = [c for c in suites.plan_cells(suites.get_suite("perf"), methods=[a.method], scenes=[a.scene])
             if c.kind == a.kind and (a.config is None or c.config == a.config)]
    if not cells:
        raise SystemExit(f"no perf cell {a.method} {a.scene} {a.kind} {a.config or ''}")
    cell = cells[0]
    torch.set_num_threads(a.threads)
    log: list[dict] = []
    get = measure_cell.get_method

    def get_method(name):
        cls = get(name)
        if getattr(cls, "_counted", False):
            return cls
        render = cls.render

        def counted(self, frame, gbuffer):
            before = {k: getattr(self, "stats", {}).get(k, 0) for k in _STATS}
            t = time.perf_counter()
            try:
                return render(self, frame, gbuffer)
            finally:
                dt = time.perf_counter() - t
                after = getattr(self, "stats", {})
                log.append({"ms": 1e3 * dt, "hits": int(gbuffer.hit.sum()), "samples": int(gbuffer.num_samples),
                            **{k: after.get(k, 0) - v for k, v in before.items()}})
        cls.render, cls._counted = counted, True
        return cls

    measure_cell.get_method = get_method
    try:
        measure_cell._measure(cell, Path(tempfile.mkdtemp()), False, part="all")
    finally:
        measure_cell.get_method = get
    print(cell.key(), cell.config)
    for i, r in enumerate(log):
        print(f"frame {i}: {r['ms']:9.2f} ms  hits {r['hits']}/{r['samples']}  "
              + "  ".join(f"{k} {r[k]}" for k in _STATS))
    return log


if __name__ == "__main__":
    main()
