"""Same-process A/B of the triple product's per-pixel frames with a few missed samples (issue 14, session 44):
a perf cell's own frames and G-buffers (`reports.suites` "perf": the frames whose G-buffer has one miss of
262,144 are there), rendered by a baseline checkout's `TripleProduct` (``--baseline``; its frames inside
`benchmarks.common.checkout_modules`) and by this tree's, on the same precomputed method (two copies),
alternating which goes first; each render after `benchmarks.common.settle` (idle, cold caches, as the suite
times a frame right after `make_gbuffer`). Per timed frame: its hit count, the median process-CPU ms of each
(``--threads 1``), the ratio, and whether the images are equal bit for bit (else the max |diff|).

    python -m benchmarks.tp_miss_ab --baseline OTHER_CHECKOUT [--scene creature] [--kind V] [--config '{}']
        [--reps 7] [--threads 1] [--plant 1 16 256] [--aa] [--precompute-code OTHER_CHECKOUT]

``--plant K ...``: also every all-hit timed frame with K misses planted at random (stored as `make_gbuffer`
stores a miss). ``--aa``: the baseline against itself (the noise of the ratio). Before each timed render a
64 MB buffer is written (and `settle` idles); a lighting-changing kind (L / E / VL) first renders the
previous frame (untimed), so that each timed render changes the lighting as the suite's frame does.
``--precompute-code DIR``: the precomputation of DIR's cache entry (a run-time-only change has the same state).
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import json
import statistics
import time


def plant(gb, idx):
    """``gb`` with the samples ``idx`` missed (a copy; face / region −1, zero bary, position and normal; ωo kept)."""
    import torch

    idx = torch.as_tensor(idx, dtype=torch.long)
    arrays = {k: getattr(gb, k).clone() for k in ("hit", "face", "region", "bary", "position", "normal")}
    arrays["hit"][idx] = False
    arrays["face"][idx] = -1
    arrays["region"][idx] = -1
    for k in ("bary", "position", "normal"):
        arrays[k][idx] = 0
    cov = arrays["hit"].view(gb.height, gb.width, gb.spp_side ** 2).all(-1)
    return dataclasses.replace(gb, coverage=cov, **arrays)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--baseline", required=True)
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--kind", default="V")
    ap.add_argument("--config", default="{}", help="the perf cell's config as the suite writes it")
    ap.add_argument("--reps", type=int, default=7)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--plant", type=int, nargs="*", default=[])
    ap.add_argument("--aa", action="store_true")
    ap.add_argument("--seed", type=int, default=0, help="of the planted misses")
    a = ap.parse_args(argv)

    import torch

    from benchmarks.common import apply_ab_options, checkout_class, checkout_modules, settle
    from methods.core.fused import warming
    from methods.triple_product import TripleProduct
    from reports import measure_cell, precompute_cache, suites

    apply_ab_options(a)
    cells = [c for c in suites.plan_cells(suites.get_suite("perf"), methods=["triple_product"], scenes=[a.scene])
             if c.kind == a.kind and c.config == a.config]
    if not cells:
        raise SystemExit(f"no perf cell triple_product {a.scene} {a.kind} {a.config}")
    cell = cells[0]
    be = measure_cell.load_backend(cell.backend)
    scene = be.get_scene(cell.scene_ref, cell.size)
    frames = be.make_sequence(scene, cell.kind, cell.n_frames, cell.seed)
    m = TripleProduct(**json.loads(cell.config))
    precompute_cache.precompute(m, scene, cell.config)
    gbs = [be.make_gbuffer(scene, f, cell.spp_side) for f in frames]
    old_cls = checkout_class(a.baseline, "methods.triple_product.method", "TripleProduct")
    with checkout_modules(a.baseline):
        from methods.core.fused import warming as base_warming
    objs = {}
    for name in ("base", "new"):
        o = copy.copy(m)
        o.__dict__.pop("_perf_cache", None)
        o.stats = {}
        if name == "base" or a.aa:
            o.__class__ = old_cls
        objs[name] = o
    base_side = {"base": True, "new": a.aa}
    for name, o in objs.items():          # warm-up frame (compiles, builds tables), as the harness's frame 0
        with (checkout_modules(a.baseline) if base_side[name] else _null()), \
                (base_warming() if base_side[name] else warming()):
            o.render(frames[0], gbs[0])
    cases = []
    g = torch.Generator().manual_seed(a.seed)
    for i in range(1, len(frames)):
        cases.append((i, str(i), gbs[i]))
        if bool(gbs[i].hit.all()):
            for k in a.plant:
                cases.append((i, f"{i}+{k}", plant(gbs[i], torch.randperm(gbs[i].num_samples, generator=g)[:k])))
    relight = any(c in cell.kind for c in "LE")
    out = {"cell": cell.key(), "threads": a.threads, "aa": a.aa, "frames": {}}
    scratch = torch.empty(16 << 20)                     # 64 MB
    for i, label, gb in cases:
        f = frames[i]
        t = {"base": [], "new": []}
        imgs = {}
        for r in range(a.reps):
            for name in (("base", "new") if r % 2 == 0 else ("new", "base")):
                o = objs[name]
                with checkout_modules(a.baseline) if base_side[name] else _null():
                    if relight:     # the lighting changes from the previous frame's, as in the suite
                        o.render(frames[i - 1], gbs[i - 1])
                    scratch.fill_(1.0)              # caches cold, as after the suite's `make_gbuffer`
                    settle()
                    c = time.process_time()
                    imgs[name] = o.render(f, gb)
                    t[name].append(time.process_time() - c)
        mb, mn = statistics.median(t["base"]), statistics.median(t["new"])
        same = torch.equal(imgs["base"], imgs["new"])
        r = {"hits": int(gb.hit.sum()), "samples": gb.num_samples, "base_ms": 1e3 * mb, "new_ms": 1e3 * mn,
             "ratio": mb / mn, "equal": same, "max_abs_diff": float((imgs["base"] - imgs["new"]).abs().max())}
        out["frames"][label] = r
        print(f"frame {label:>7}: hits {r['hits']}/{r['samples']}  base {r['base_ms']:6.1f}  new {r['new_ms']:6.1f} ms"
              f"  ratio {r['ratio']:.3f}  {'equal' if same else 'max|diff| %.3g' % r['max_abs_diff']}", flush=True)
    return out


class _null:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


if __name__ == "__main__":
    main()
