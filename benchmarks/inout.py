"""In-out frame times, old (reference) vs new (fast) path, in one process (issue 14).

    python -m benchmarks.inout [--scene sphere_plane] [--size bench] [--config '{}'] [--frames 5]
                               [--threads 2] [--spp-side 2] [--kinds V L E] [--no-micro]
                               [--base OTHER_CHECKOUT] [--precompute-code DIR]

With ``--base`` the old path is a base checkout's fast path (its ``methods`` package imported beside
this one's, ``benchmarks.ptt_ab`` style: e.g. a worktree of main) instead of the reference path, and
the precomputation is looked up under the base's code fingerprint (the same arrays while this
checkout's edits leave the precompute alone). Both wall and process-CPU time are recorded per
frame; under load compare the CPU ratios at ``--threads 1``.

Precomputes once (kept in ``<cache>/inout_frames/``, keyed by the scene's content hash and the
config; delete it after changing the precompute), then renders each sequence kind with two copies
sharing the precomputed arrays — ``_render_reference`` (the old path) and ``render`` (the fast
path, ``methods.inout.fast``) — frame by frame, alternating which goes first, so both see the same
machine load. Frame 0 of each sequence fills the caches and is not timed. Prints the medians, their
ratio, the roofline efficiency max(bytes / triad bandwidth, flops / matmul peak) / time with
``InOut.frame_cost`` and both machine limits measured in this run (before and after the frames;
the higher of each is used), the largest |old − new| pixel difference, and micro-benchmarks of the
parts of a fast frame against the kernels that bound them (`micro`): the per-frame set-up (c_k and
the window products X), the per-sample stage (inputs; eq. 4's 12 weighted reads per sample), one
read of the G-buffer arrays, and the lighting product c = T̃ · L over the referenced rows beside
one streaming read of the same bytes.
"""
from __future__ import annotations

import argparse
import contextlib
import copy
import json
import statistics
import time

import torch

from benchmarks.common import checkout_class, checkout_fingerprint, checkout_modules, frame_args, inout_regions, machine_limits, precomputed, settle, setup, wall_cpu_time
from methods.inout import fast
from methods.inout.method import InOut
from reports import measure


def _precomputed(scene, config: dict) -> tuple[InOut, float | None]:
    m, pre = precomputed(InOut, scene, config)
    m._fast = None
    m._reset_cache()
    return m, pre


def base_class(root: str):
    """The InOut class of the ``methods`` package under ``root``, imported beside this checkout's."""
    return checkout_class(root, "methods.inout.method", "InOut")


def base_fingerprint(root: str) -> str:
    """``reports.store.code_closure_fingerprint`` of the InOut module of the checkout at ``root``."""
    return checkout_fingerprint(root, "methods.inout.method")


def _time(fn) -> float:
    """Median process-CPU seconds of 5 calls after a warm-up (at ``--threads 1`` the single-core time,
    far less disturbed by other jobs than wall time)."""
    return wall_cpu_time(fn, 5)["cpu"]


def micro(m: InOut, frame, gb) -> dict[str, float]:
    """Process-CPU seconds (`_time`) of the parts and kernels of a fast frame, on the last
    frame of the V sequence (``frame`` on G-buffer ``gb``; c_k cached): the per-frame set-up
    (`InOut._view_setup`: referenced vertices, c_k, the window products X), the per-sample stage
    (``fast.shade_pixels``: eq. 4 and the box filter), against the kernels that bound them: one
    read of the G-buffer arrays a frame reads (the bulk of the roofline's bytes) and, for a lighting
    change, c = T̃ · L over the referenced rows against one streaming read of the same bytes."""
    out: dict[str, float] = {}
    view = m._view_setup(frame, gb)
    out["view_setup_s"] = _time(lambda: m._view_setup(frame, gb))
    out["window"] = view.wins.W
    S2 = gb.spp_side ** 2
    if view.sel is None:
        args = (gb.normal, gb.wo, gb.bary, gb.face, gb.hit, S2)
    else:
        args = tuple(t.index_select(0, view.sel) for t in (gb.normal, gb.wo, gb.bary, gb.face)) + (
            torch.ones(view.sel.numel(), dtype=torch.bool), 1)
    out["shade_s"] = _time(lambda: fast.shade_pixels(view.st, view.cs, view.wins, *args))
    out["X_nodes"] = int(view.wins.X.shape[0])
    # the dominant kernel alone: the compiled per-sample pass (`fast.shade_rows`) over the frame's
    # blocks, its streamed bytes (the G-buffer arrays it reads, the pixels it writes) and its
    # indirect loads (per sample 3 packed window words, 3 vertices × 4 nodes × 3 channels)
    q, S = int(args[0].shape[0]), args[-1]
    npx, blk = q // S, max(1, fast.sample_block(q) // S)
    rows = [t.unflatten(0, (npx, S)) for t in args[:5]]
    pad = [[r[a:a + blk] for r in rows] for a in range(0, npx, blk)]
    pad = [[torch.cat([b, b[-1:].expand(blk - b.shape[0], *b.shape[1:])]) for b in bl] for bl in pad]
    st, w = view.st, view.wins
    fwin = fast.pack_windows(w.win, st.face_rows, st.R)
    out["shade_rows_s"] = _time(lambda: [fast.shade_rows(*bl, fwin, w.X, st.R) for bl in pad])
    out["shade_rows_samples"] = q
    out["shade_rows_bytes"] = sum(t.numel() * t.element_size() for t in args[:5]) + npx * 3 * 4
    out["shade_rows_gathers"] = q * (3 + 36)
    arrays = (gb.normal, gb.wo, gb.bary, gb.face, gb.region, gb.hit)
    out["gbuffer_bytes"] = sum(a.numel() * a.element_size() for a in arrays)
    out["gbuffer_read_s"] = _time(lambda: [a.max() for a in arrays])
    reg = max(m.regions, key=lambda r: r.T.values().numel())
    fr = m._fast_static().regions[m.regions.index(reg)]
    # the rows a later lighting change computes (the first one computes every vertex's c): the
    # view's referenced vertices, by `InOut._view_setup` under that state
    saved = (m._cf, m._cf_valid, m._lightings)
    m._cf, m._cf_valid, m._lightings = {}, {}, 2
    m._view_setup(frame, gb)
    ref = m._cf_valid[reg.name].nonzero(as_tuple=True)[0]
    m._cf, m._cf_valid, m._lightings = saved
    nat = fast.native(fr, m.L)         # the native loop computes exactly ``ref``, torch's product whole blocks
    runs = fast.light_runs(ref, reg.verts.numel(), block=1 if nat else fast.LIGHT_BLOCK)
    rows = sum(v1 - v0 for v0, v1 in runs) * reg.K
    spans = [(int(fr.crow[v0 * reg.K]), int(fr.crow[v1 * reg.K])) for v0, v1 in runs]   # CSR entries of each run
    nnz = sum(s1 - s0 for s0, s1 in spans)
    out.update(region=reg.name, K=reg.K, c_valid_vertices=int(ref.numel()), light_rows=rows,
               light_bytes=nnz * (fr.val.element_size() + fr.col.element_size()))

    def light():
        if nat:
            fast.light_vertices(fr, m.L, ref)
            return
        for v0, v1 in runs:
            fast.light_rows(fr, m.L, v0, v1)

    def stream():  # one read of the same values and indices (a vectorised max: no arithmetic to speak of)
        for s0, s1 in spans:
            fr.val[s0:s1].max()
            fr.col[s0:s1].max()

    out["light_product_s"] = _time(light)
    out["light_stream_read_s"] = _time(stream)
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    frame_args(ap, scene="sphere_plane", frames=5)
    ap.add_argument("--no-micro", action="store_true")
    ap.add_argument("--base", default=None, help="time this checkout's fast path (e.g. a worktree of main) "
                                                 "as the old path instead of the reference path")
    ap.add_argument("--precompute-code", default=None,
                    help="look the precomputation up under the code fingerprint of the checkout in DIR (default: "
                         "--base's): e.g. --base a worktree of this branch's last commit with the base39 entry")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    cfg = json.loads(a.config)
    Base = None
    if a.base is not None:
        Base = base_class(a.base)
    if a.base is not None or a.precompute_code is not None:
        from reports import precompute_cache

        fp = base_fingerprint(a.precompute_code or a.base)
        precompute_cache._process_fingerprint = lambda module: fp
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1, spp_side=a.spp_side)
    m, pre = _precomputed(scene, cfg)
    out: dict = {"scene": a.scene, "size": a.size, "config": cfg, "threads": a.threads, "spp_side": a.spp_side,
                 **inout_regions(m), "precompute_s": pre}
    bw, peak = [measure.triad_bandwidth()], [measure.matmul_peak()]
    kinds, last = {}, None
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=1, spp_side=a.spp_side)
        old, new = copy.copy(m), copy.copy(m)
        if Base is not None:
            old.__class__ = Base
        old._reset_cache()
        new._reset_cache()
        old_render = old.render if Base is not None else old._render_reference
        t_old, t_new, c_old, c_new, diff, scale = [], [], [], [], 0.0, 0.0
        for i, (f, g) in enumerate(zip(frames, gbs)):
            order = ("old", "new") if i % 2 == 0 else ("new", "old")
            imgs = {}
            for which in order:
                # a base checkout's frames with its modules also for lazy imports (`checkout_modules`)
                with checkout_modules(a.base) if which == "old" and Base is not None else contextlib.nullcontext():
                    settle()
                    t0, c0 = time.perf_counter(), time.process_time()
                    imgs[which] = old_render(f, g) if which == "old" else new.render(f, g)
                    (t_old if which == "old" else t_new).append(time.perf_counter() - t0)
                    (c_old if which == "old" else c_new).append(time.process_time() - c0)
            diff = max(diff, float((imgs["old"] - imgs["new"]).abs().max()))
            scale = max(scale, float(imgs["old"].abs().max()))
        cost = new.frame_cost(kind, gbs[-1].num_samples, pixels=gbs[-1].height * gbs[-1].width)
        kinds[kind] = {"old_s": t_old, "new_s": t_new, "old_median_s": statistics.median(t_old[1:]),
                       "new_median_s": statistics.median(t_new[1:]), "old_cpu_s": c_old, "new_cpu_s": c_new,
                       "old_cpu_median_s": statistics.median(c_old[1:]),
                       "new_cpu_median_s": statistics.median(c_new[1:]), "max_abs_diff": diff, "image_max": scale,
                       "bytes": cost.bytes, "flops": cost.flops, "hit_samples": int(gbs[-1].hit.sum())}
        if last is None or kind == "V":   # the micro-benchmarks run on a view-only frame when there is one
            last = (new, frames[-1], gbs[-1])
    B, Pk = machine_limits(out, bw, peak)
    for kind, r in kinds.items():
        for which in ("old", "new"):
            eff, bound = measure.roofline(r["bytes"], r["flops"], B, Pk, r[f"{which}_median_s"])
            r[f"{which}_efficiency"], r["bound"] = eff, bound
        r["roofline_s"] = max(r["bytes"] / B, r["flops"] / Pk)
        r["speedup"] = r["old_median_s"] / r["new_median_s"]
        r["cpu_speedup"] = r["old_cpu_median_s"] / r["new_cpu_median_s"]
        r["new_cpu_efficiency"] = measure.roofline(r["bytes"], r["flops"], B, Pk, r["new_cpu_median_s"])[0]
    out["kinds"] = kinds
    if not a.no_micro and last is not None:
        out["micro"] = micro(*last)
    print(json.dumps(out, indent=1, default=float))
    print(f"\n{a.scene} {a.size}, {a.threads} threads, triad {B / 1e9:.1f} GB/s, sgemm {Pk / 1e9:.1f} GFLOP/s, "
          f"old = {a.base + ' (base checkout)' if a.base else 'reference path'}")
    print(f"{'kind':5} {'old ms':>9} {'new ms':>9} {'speedup':>8} {'old cpu':>8} {'new cpu':>8} {'cpu x':>6} "
          f"{'roof ms':>8} {'old eff':>8} {'new eff':>8} {'cpu eff':>8} {'max|d|':>9} bound")
    for kind, r in kinds.items():
        print(f"{kind:5} {1e3 * r['old_median_s']:9.1f} {1e3 * r['new_median_s']:9.1f} {r['speedup']:8.2f} "
              f"{1e3 * r['old_cpu_median_s']:8.1f} {1e3 * r['new_cpu_median_s']:8.1f} {r['cpu_speedup']:6.2f} "
              f"{1e3 * r['roofline_s']:8.2f} {r['old_efficiency']:8.4f} {r['new_efficiency']:8.4f} "
              f"{r['new_cpu_efficiency']:8.4f} {r['max_abs_diff'] / max(r['image_max'], 1e-30):9.2e} {r['bound']}")
    if "micro" in out:
        u = out["micro"]
        print(f"last frame: set-up (c_k, X; W = {u['window']}) {1e3 * u['view_setup_s']:.1f} ms, per-sample stage "
              f"(eq. 4, box filter) {1e3 * u['shade_s']:.1f} ms; one G-buffer read "
              f"{1e3 * u['gbuffer_read_s']:.2f} ms ({u['gbuffer_bytes'] / u['gbuffer_read_s'] / 1e9:.1f} GB/s)")
        print(f"per-sample kernel alone (fast.shade_rows, {u['shade_rows_samples']} samples): "
              f"{1e3 * u['shade_rows_s']:.1f} ms = {1e9 * u['shade_rows_s'] / u['shade_rows_samples']:.1f} ns/sample, "
              f"{u['shade_rows_bytes'] / u['shade_rows_s'] / 1e9:.2f} GB/s streamed (triad {B / 1e9:.1f}), "
              f"{u['shade_rows_gathers'] / u['shade_rows_s'] / 1e9:.2f} G indirect loads/s")
        print(f"lighting ({u['region']}, {u['light_rows']} rows): c = T·L {1e3 * u['light_product_s']:.1f} ms "
              f"({u['light_bytes'] / u['light_product_s'] / 1e9:.1f} GB/s), one read of T "
              f"{1e3 * u['light_stream_read_s']:.1f} ms ({u['light_bytes'] / u['light_stream_read_s'] / 1e9:.1f} GB/s)")
    return out


if __name__ == "__main__":
    main()
