"""Same-process before/after of PTT frames (issue 14): a base checkout's ``methods`` package (``--base``,
e.g. a git worktree of main) against this checkout's, on one precomputation and the same frames.

    python -m benchmarks.ptt_ab --base OTHER_CHECKOUT [--scene chess] [--size bench]
                                [--config '{"light_res_1":4}'] [--bounces 0] [--frames 7]
                                [--threads 1] [--kinds V VB VBL L E VL] [--no-limits]
                                [--precompute-code CHECKOUT]

Both packages are imported into this process (the base's ``methods.*`` modules under their own
names, then set aside in ``sys.modules``), the precomputation is loaded once through the harness
cache (`benchmarks.common.precomputed`, the perf suite's ``with_bounces(bounces)``), and the base
renders with a copy of the method whose class is the base's PTT — so both read the same arrays —
and whose BRDF basis, when it is the default ``LobeBasis``, is the base's class (`base_basis`: the
run-time fit of changed materials is the base's code too).
Unless ``--own-precompute``, the
precomputation is looked up under the base's code fingerprint (valid while this checkout's edits
leave the precompute alone; it saves recomputing it after every run-time edit). Before each timed frame
``--flush-mb`` MB are read and written (default 64: the harness's G-buffer and scoring between timed
frames leave the caches cold; session 41) and ``PRTBENCH_SETTLE`` idled. Frames alternate
which version goes first; frame 0 of each sequence fills the caches and is not
counted. Prints per kind the median wall and process-CPU ms of both (CPU time is the less
load-sensitive: compare CPU ratios at 1 thread), the ratio base / new, the largest |base − new|
pixel difference over the frames, and the roofline efficiency of the new frames
(``PTT.frame_cost`` of the new code, ``reports.measure`` triad bandwidth and matmul peak measured
in this run) on wall and CPU time."""
from __future__ import annotations

import argparse
import contextlib
import copy
import json
import statistics
import time

import torch

from benchmarks.common import checkout_class, checkout_fingerprint, checkout_modules, frame_args, machine_limits, precomputed, settle, setup
from methods.ptt.method import PTT


def base_class(root: str):
    """The PTT class of the ``methods`` package under ``root``, imported beside this checkout's."""
    return checkout_class(root, "methods.ptt.method", "PTT")


def base_fingerprint(root: str) -> str:
    """``reports.store.code_closure_fingerprint`` of the PTT module of the checkout at ``root``."""
    return checkout_fingerprint(root, "methods.ptt.method")


def base_basis(m: PTT, root: str):
    """``m.basis`` as the checkout at ``root`` would fit it: a `transport.LobeBasis` (the default
    basis, whose `coords` fits every changed material at run time) re-classed to that checkout's
    ``LobeBasis`` with empty fit caches, so the base's VB frames time the base's fit; any other basis
    as is."""
    from methods.ptt.transport import LobeBasis

    if type(m.basis) is not LobeBasis:
        return m.basis
    b = copy.copy(m.basis)
    b.__class__ = checkout_class(root, "methods.ptt.transport", "LobeBasis")
    b._gram = b._fold = None
    return b


def as_class(m: PTT, cls, basis=None) -> PTT:
    """A copy of ``m`` of class ``cls`` with empty run-time caches and no fast-path statics (``_fs``),
    so ``cls``'s own `_fast_static` lays out the arrays its frames read: a layout change in one
    version would otherwise hand the other version's storage to the copy (and, e.g., make it copy a
    44 MB table every frame and look falsely slow; found by the ptt22 helper)."""
    out = copy.copy(m)
    out.__class__ = cls
    if basis is not None:
        out.basis = basis
    out._reset_cache()
    out._fs = None
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    frame_args(ap, scene="chess", config='{"light_res_1":4}', frames=7, kinds=("V", "VB", "VBL", "L", "E", "VL"))
    ap.add_argument("--base", required=True, help="the other checkout (e.g. a git worktree of main)")
    ap.add_argument("--bounces", type=int, default=0)
    ap.add_argument("--no-limits", action="store_true", help="skip the bandwidth / peak measurement")
    ap.add_argument("--flush-mb", type=int, default=64,
                    help="MB read and written before each timed frame (the harness's G-buffer and scoring between "
                         "frames evict the caches; session 41; 0: none, as before)")
    ap.add_argument("--own-precompute", action="store_true",
                    help="key the precompute cache on this checkout's code (default: on the base's, see below)")
    ap.add_argument("--precompute-code", default=None,
                    help="look the precomputation up under the code of the checkout at this path instead of "
                         "--base's (e.g. --precompute-code /work/base when --base is a later snapshot whose "
                         "precompute code is the same)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    Base = base_class(a.base)
    if not a.own_precompute:
        # the precompute cache keys on the code the method runs (reports.precompute_cache), so every
        # run-time edit would recompute the bench precomputation (minutes); when the edits leave the
        # precompute alone, load the base's entry (the same arrays) instead
        from reports import precompute_cache

        fp = base_fingerprint(a.precompute_code or a.base)
        precompute_cache._process_fingerprint = lambda module: fp
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1, spp_side=a.spp_side)
    m, _ = precomputed(PTT, scene, json.loads(a.config))
    m = m.with_bounces(a.bounces)
    m._fast_static()
    out = {"scene": a.scene, "threads": a.threads, "bounces": a.bounces, "base": a.base, "kinds": {}}
    flush = torch.zeros(a.flush_mb << 18) if a.flush_mb > 0 else None
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=1, spp_side=a.spp_side)
        new, old = copy.copy(m), as_class(m, Base, base_basis(m, a.base))
        new._reset_cache()
        t = {"old": [], "new": []}
        c = {"old": [], "new": []}
        diff, vmax = 0.0, 0.0
        for i, (f, g) in enumerate(zip(frames, gbs)):
            imgs = {}
            for which in (("old", "new") if i % 2 == 0 else ("new", "old")):
                meth = old if which == "old" else new
                # the base's frames with the base's modules also for its lazy imports (`checkout_modules`:
                # its fast.py imports native at call time; without the swap it ran this checkout's)
                with checkout_modules(a.base) if which == "old" else contextlib.nullcontext():
                    if flush is not None:
                        flush.add_(1.0)
                    settle()
                    t0, c0 = time.perf_counter(), time.process_time()
                    imgs[which] = meth.render(f, g)
                    t[which].append(time.perf_counter() - t0)
                    c[which].append(time.process_time() - c0)
            diff = max(diff, float((imgs["old"] - imgs["new"]).abs().max()))
            vmax = max(vmax, float(imgs["old"].abs().max()))
        r = {w: {"wall_ms": 1e3 * statistics.median(t[w][1:]), "cpu_ms": 1e3 * statistics.median(c[w][1:])}
             for w in ("old", "new")}
        r["cpu_ratio"] = r["old"]["cpu_ms"] / r["new"]["cpu_ms"]
        r["wall_ratio"] = r["old"]["wall_ms"] / r["new"]["wall_ms"]
        r["max_abs_diff"], r["image_max"] = diff, vmax
        cost = new.frame_cost(kind, gbs[-1].num_samples, pixels=gbs[-1].height * gbs[-1].width)
        r["bytes"], r["flops"] = cost.bytes, cost.flops
        out["kinds"][kind] = r
        print(f"{kind:4s} old {r['old']['wall_ms']:7.1f} / {r['old']['cpu_ms']:7.1f} ms  new {r['new']['wall_ms']:7.1f} / "
              f"{r['new']['cpu_ms']:7.1f} ms (wall / cpu)  cpu ratio {r['cpu_ratio']:.2f}  wall ratio "
              f"{r['wall_ratio']:.2f}  max|old-new| {diff:.2e} (image max {vmax:.3g})", flush=True)
    if not a.no_limits:
        from reports import measure

        B, Pk = machine_limits(out, [measure.triad_bandwidth()], [measure.matmul_peak()])
        print(f"triad {B / 1e9:.1f} GB/s, sgemm {Pk / 1e9:.1f} GFLOP/s")
        for kind, r in out["kinds"].items():
            for w in ("wall", "cpu"):
                r[f"eff_{w}"] = {v: measure.roofline(r["bytes"], r["flops"], B, Pk, r[v][f"{w}_ms"] / 1e3)[0]
                                 for v in ("old", "new")}
            print(f"{kind:4s} roofline (new frame_cost) old {100 * r['eff_wall']['old']:.1f} % -> new "
                  f"{100 * r['eff_wall']['new']:.1f} % (wall), {100 * r['eff_cpu']['old']:.1f} % -> "
                  f"{100 * r['eff_cpu']['new']:.1f} % (cpu)")
    return out


if __name__ == "__main__":
    main()
