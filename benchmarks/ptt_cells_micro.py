"""The mirror direction's lat-long cells alone (``native.mirror_cells``: the directions, acos / atan2 and
the cell of 2^18 samples, a chess bench V frame's count) of a base checkout's ``methods/ptt/native.py``
against this checkout's, same process, alternating, process CPU time (session 39, pt39: the polynomial
angles against the Sleef calls).

    python -m benchmarks.ptt_cells_micro --base OTHER_CHECKOUT [--n 262144] [--rounds 41] [--threads 1]

Random unit view directions and shading normals (the G-buffer's layouts: normals row-major, wo as
columns of a (3, n) array), a 256 × 512 map. Prints the median ms of each, the ratio base / new and
how many cells (first rows) differ."""
from __future__ import annotations

import argparse
import statistics
import time

import torch

from benchmarks.ptt_sample_ab import base_native
from methods.ptt import native as N


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True)
    ap.add_argument("--n", type=int, default=1 << 18)
    ap.add_argument("--rounds", type=int, default=41)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    B = base_native(a.base)
    g = torch.Generator().manual_seed(0)
    n = a.n
    normal = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1).T.contiguous().T
    to_world = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0].float().contiguous()
    H, W = 256, 512
    mods = {"old": B, "new": N}
    res = {k: m.mirror_cells(normal, wo, to_world, H, W) for k, m in mods.items()}
    assert all(r is not None for r in res.values()), "native cells not available"
    t = {k: [] for k in mods}
    for i in range(a.rounds):
        for k in (("old", "new") if i % 2 else ("new", "old")):
            c0 = time.process_time()
            mods[k].mirror_cells(normal, wo, to_world, H, W)
            t[k].append(time.process_time() - c0)
    med = {k: statistics.median(v[1:]) * 1e3 for k, v in t.items()}
    diff = int((res["old"][0] != res["new"][0]).sum())
    print(f"cells of {n} samples, {a.threads} thread(s), cpu ms: old {med['old']:.3f}  new {med['new']:.3f}  "
          f"ratio {med['old'] / med['new']:.3f}  cells differing {diff} of {n}")
    return {"old_ms": med["old"], "new_ms": med["new"], "diff": diff}


if __name__ == "__main__":
    main()
