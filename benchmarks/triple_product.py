"""Frame times, memory and roofline of TripleProduct (Ma 2006; issue #7 "Performance").

    python -m benchmarks.triple_product --size bench                  # default config
    python -m benchmarks.triple_product --size bench --preset paper   # level 4, n = 320, paper grid
    python -m benchmarks.triple_product --micro                        # evaluator micro-benchmarks
    python -m benchmarks.triple_product --micro-fine                   # fine-value / grouped kernels only

Per evaluator — "class": the independent dense path (``with_evaluator("reference")``); the names
of `fast_eval.EVALUATORS` go through `fast_eval.shade` ("auto" = production: the fine-value path
for full tables, else the list evaluators; "dense" = the list evaluator in `fast_eval.INNER_POINTS`
sub-batches, the previous production path for full tables) — the median wall and process-CPU time
of ``--frames`` − 1 frames after one warm-up frame per evaluator, the evaluators *alternating frame
by frame in one process* (the machine is shared: old/new ratios are taken under the same load),
for a "V" sequence (view changes; lighting fixed) and a "VL" sequence (`make_sequence` "VBL" with
the materials held at the scene's: the env map rotates every frame, so each frame re-projects the
lighting grid; BRDF edits are not scored for this method). Also: `method.memory()` (after the
renders, lighting grid included), `TripleProduct.frame_cost` and the roofline efficiency
max(bytes / bandwidth, flops / peak) / frame time with `reports.measure.triad_bandwidth` and
`reports.measure.matmul_peak` measured in the same run.
Paper (Ma 2006 Table 3, 1024×768, ATI X1900 XTX, 2006): 15–97 fps with visibility textures,
6.8–21.5 fps with interpolated per-vertex visibility (the mode of the default config).

Its numbers are in the README (frame times at bench size), not here: they drift with the machine.

Every run precomputes (no cache of its own: the harness's ``reports.precompute_cache`` is the
project's one precompute cache and serves ``run_bench.py`` cells).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import time

import torch

# Ma 2006 Table 3 (fps at 1024×768): model → (vis. texture n=80, n=320, interpolated n=80, n=320).
PAPER_FPS = {"Dragon 25k": (97.4, 38.4, 21.5, 8.5), "XYZRGB 50k": (46.6, 16.9, 14.7, 6.9),
             "Buddha 50k": (43.5, 17.6, 15.1, 6.8)}


def preset_config(name: str) -> dict:
    """"default" (the class defaults) or "paper" (level 4, n = 320, `PAPER_FRAME_GRID`, 8×8 ωo)."""
    from methods.triple_product.brdf_table import PAPER_BRDF_DIRS
    from methods.triple_product.lighting import PAPER_FRAME_GRID

    if name == "default":
        return {}
    if name == "paper":
        return {"level": 4, "n_coeffs": 320, "frame_grid": PAPER_FRAME_GRID, "brdf_dirs": PAPER_BRDF_DIRS}
    raise ValueError(f"unknown preset {name!r} (default | paper)")


def precomputed(scene, cfg: dict):
    """A TripleProduct precomputed for ``scene`` and its precompute seconds."""
    from methods.triple_product import TripleProduct

    m = TripleProduct(**cfg, progress=True)
    m.precompute(scene)
    return m, m.stats["precompute_seconds"]


def vl_sequence(scene, n_frames: int, seed: int):
    """"VBL" frames with the scene's own materials (view + lighting change)."""
    from scenes.sequences import make_sequence

    out = []
    for f in make_sequence(scene, "VBL", n_frames=n_frames, seed=seed):
        out.append(dataclasses.replace(f, materials=dict(scene.materials), changed=f.changed - {"brdf"}))
    return out


def _with(method, evaluator: str):
    from methods.triple_product import fast_eval

    return fast_eval.use_reference_shading(method) if evaluator == "class" else fast_eval.use_fast_shading(method, evaluator)


def time_sequences(method, frames, gbuffers, evaluators) -> dict[str, tuple[list[float], list[float]]]:
    """Wall and process-CPU seconds per frame for frames[1:] of every evaluator, after one warm-up
    render of frames[0] each (lighting set, run-time tables built); the evaluators alternate frame
    by frame so all see the same machine load."""
    ms = {ev: _with(method, ev) for ev in evaluators}
    for m in ms.values():
        m._light_key = None  # the warm-up frame builds the lighting grid
        m.render(frames[0], gbuffers[0])
    out: dict[str, tuple[list[float], list[float]]] = {ev: ([], []) for ev in evaluators}
    for f, g in zip(frames[1:], gbuffers[1:]):
        for ev, m in ms.items():
            t, c = time.perf_counter(), time.process_time()
            m.render(f, g)
            out[ev][0].append(time.perf_counter() - t)
            out[ev][1].append(time.process_time() - c)
    return out


def check_equal(method, frame, gbuffer, evaluators) -> dict[str, float]:
    """Max |image − "class" image| / max |"class" image| of each evaluator on one frame."""
    from methods.triple_product import fast_eval

    ref = fast_eval.use_reference_shading(method).render(frame, gbuffer)
    out = {}
    for ev in evaluators:
        if ev == "class":
            continue
        img = fast_eval.use_fast_shading(method, ev).render(frame, gbuffer)
        out[ev] = float((img - ref).abs().max() / ref.abs().max().clamp_min(1e-30))
    return out


def micro(threads: int, points: int = 32, reps: int = 5) -> list[dict]:
    """µs per point (best of ``reps``) of each evaluator on random lists of the render's shape:
    3 V rows, 4 ρ̃ rows, 8 L rows of n entries each (dense lists when n = K). The costs depend on
    the list lengths and K, not on the index values."""
    from methods.core.spherical_haar import support_areas
    from methods.triple_product import fast_eval

    torch.set_num_threads(threads)
    g = torch.Generator().manual_seed(0)
    rows = []
    for level in (3, 4):
        K = 20 * 4 ** level
        for n in (20, 80, 320, K):
            def lst(k, C):
                if n == K:  # all coefficients: `shading_lists` blends them into dense lists
                    return None, torch.randn(points, C, K, generator=g) * support_areas(level)[None, None].sqrt()
                idx = torch.randint(0, K, (points, k * n), generator=g)
                val = torch.randn(points, C, k * n, generator=g) * support_areas(level)[idx][:, None].sqrt()
                return idx, val
            V, rho, L = lst(3, 1), lst(4, 3), lst(8, 3)
            evs = ["reference", "dense", "sparse"] if n < K else ["reference", "dense"]
            best = {e: float("inf") for e in evs}
            for _ in range(reps):
                for ev in evs:
                    t = time.perf_counter()
                    fast_eval.evaluate(V, rho, L, K, ev)
                    best[ev] = min(best[ev], time.perf_counter() - t)
            rows.append({"threads": threads, "K": K, "n": n,
                         "auto": fast_eval.choose_evaluator(7 * n, K) if n < K else "dense",
                         **{f"{e}_us": round(v / points * 1e6, 1) for e, v in best.items()}})
            print(json.dumps(rows[-1]), flush=True)
    return rows


def micro_fine(threads: int, points: int = 1 << 14, reps: int = 5) -> list[dict]:
    """The fine-value kernel (`fast_eval.fine_kernel`, the production path with full tables) on
    random tables of the bench default's shapes (16803 vertex rows, 2 regions × 128 ωo rows, 544
    grid rows; K' = 1280 and 5120) with pixel-like coherence (neighbouring points share rows):
    µs per point (best wall time of ``reps``, like the matmul peak; the first compiles) and the model's GFLOP/s (3 V + 4 ρ̃
    + 4 L rows blended, 3 flops per channel and fine triangle in the product) beside
    `reports.measure.matmul_peak`; and the grouped form pixel frames run (`fast_eval.fine_grouped`):
    µs per point of the whole, GFLOP/s and gathered GB/s of its per-group sums (`group_block`) —
    what bounds a pixel frame."""
    from methods.triple_product import fast_eval
    from reports.measure import matmul_peak

    torch.set_num_threads(threads)
    peak = matmul_peak()
    g = torch.Generator().manual_seed(0)
    rows = []
    for Kp in (1280, 5120):
        Vt, Rt, Lt = (torch.randn(n, c * Kp, generator=g) for n, c in ((16803, 1), (256, 3), (544, 3)))
        i = torch.arange(points)[:, None]
        vr, br, lr = (i // 8 + torch.arange(3)) % 16803, (i // 16 + torch.arange(4)) % 256, (i // 32 + torch.arange(4)) % 544
        vw, bw, lw = torch.rand(points, 3, generator=g), torch.rand(points, 4, generator=g), torch.rand(points, 4, generator=g)
        best = float("inf")
        for _ in range(reps):
            c = time.perf_counter()
            fast_eval.fine_kernel(Vt, Rt, Lt, vr, vw, br, bw, lr, lw)
            best = min(best, time.perf_counter() - c)
        flops = points * (Kp * (5 + 3 * 7 + 3 * 7) + 9 * Kp)  # (2k − 1)·K' per blend of k rows and channel
        # the grouped form pixel frames run (`fast_eval.fine_grouped`): its sums per distinct
        # (vertex, L cell, ρ̃ cell) alone (`group_block`), then the whole (with `group_rows` and the blend)
        gv, gl, gb, _ = fast_eval.group_rows(vr, lr, br)
        R3, L3 = Rt.view(-1, 3, Kp), Lt.view(-1, 3, Kp)
        blk = fast_eval.GROUP_BLOCK
        gv, gl, gb = (x[:gv.shape[0] // blk * blk] for x in (gv, gl, gb))  # whole blocks only
        g_best = w_best = float("inf")
        for _ in range(reps):
            c = time.perf_counter()
            fast_eval.map_rows(fast_eval._group_block, [gv, gl, gb], (Vt, R3, L3), chunk=blk)
            g_best = min(g_best, time.perf_counter() - c)
            c = time.perf_counter()
            fast_eval.fine_grouped(Vt, Rt, Lt, vr, vw, br, bw, lr, lw)
            w_best = min(w_best, time.perf_counter() - c)
        g_flops = gv.shape[0] * 3 * Kp * (4 + 2 * 16)                   # `fast_eval.grouped_flops`, per group
        g_bytes = gv.shape[0] * 4 * Kp * (1 + 2 * 3 * 4)                 # rows gathered per group (from cache)
        rows.append({"threads": threads, "K'": Kp, "us_per_point": round(best / points * 1e6, 2),
                     "model_GFLOPs": round(flops / best / 1e9, 2), "matmul_peak_GFLOPs": round(peak / 1e9, 1),
                     "groups_per_point": round(gv.shape[0] / points, 3),
                     "grouped_us_per_point": round(w_best / points * 1e6, 3),
                     "group_block_GFLOPs": round(g_flops / g_best / 1e9, 2),
                     "group_block_gathered_GBs": round(g_bytes / g_best / 1e9, 1)})
        print(json.dumps(rows[-1]), flush=True)
    return rows


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="test", choices=["test", "bench"])
    ap.add_argument("--scene", default="sphere_plane")
    ap.add_argument("--preset", default="default", choices=["default", "paper"])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a config value (python literal), e.g. --set n_coeffs=80")
    ap.add_argument("--frames", type=int, default=3, help="frames per sequence (the first is a warm-up)")
    ap.add_argument("--spp-side", type=int, default=1)
    ap.add_argument("--evaluators", default="dense,auto",
                    help="comma list of class|auto|dense|sparse|reference")
    ap.add_argument("--kinds", default="V,VL")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--micro", action="store_true", help="only the evaluator micro-benchmark (1 and 2 threads)")
    ap.add_argument("--micro-fine", action="store_true",
                    help="only the fine-value / grouped kernel micro-benchmark (1 and 2 threads)")
    a = ap.parse_args(argv)
    if a.micro_fine:
        return {"fine": micro_fine(1) + micro_fine(2)}
    if a.micro:
        return {"micro": micro(1) + micro(2), "fine": micro_fine(1) + micro_fine(2)}
    import ast

    from benchmarks.common import setup
    from scenes.library import get_scene

    torch.set_num_threads(a.threads)
    cfg = preset_config(a.preset)
    for kv in a.set:
        k, v = kv.split("=", 1)
        cfg[k] = ast.literal_eval(v)
    scene = get_scene(a.scene, a.size)
    m, pre_s = precomputed(scene, cfg)
    evaluators = a.evaluators.split(",")
    out = {"scene": a.scene, "size": a.size, "preset": a.preset, "config": m.config, "threads": a.threads,
           "precompute_s": pre_s, "paper_fps_table3": PAPER_FPS}
    from reports.measure import matmul_peak, triad_bandwidth

    bw, peak = triad_bandwidth(), matmul_peak()
    out["triad_bandwidth"], out["matmul_peak"] = bw, peak
    for kind in a.kinds.split(","):
        _, frames, gbs, _ = setup(scene, kind="V", n_frames=a.frames, seed=0, spp_side=a.spp_side,
                                  frames=None if kind == "V" else vl_sequence(scene, a.frames, 0))
        out["shading_points"] = int(gbs[0].hit.sum())
        if kind == "V":
            out["max_rel_diff_vs_class"] = check_equal(m, frames[0], gbs[0], evaluators)
        res = time_sequences(m, frames, gbs, evaluators)
        m.render(frames[-1], gbs[-1])  # the cost model reads the last frame's counts
        cost = m.frame_cost(kind, gbs[-1].num_samples, pixels=gbs[-1].height * gbs[-1].width)
        out[f"frame_cost_{kind}"] = None if cost is None else {"bytes": cost.bytes, "flops": cost.flops}
        for ev in evaluators:
            ts, cpu = res[ev]
            t = statistics.median(ts)
            eff = None if cost is None else cost.bound(bw, peak)
            out[f"{kind}/{ev}"] = {"median_s": t, "fps": 1.0 / t, "times_s": ts,
                                   "median_cpu_s": statistics.median(cpu), "cpu_s": cpu,
                                   "roofline_eff": None if eff is None else eff[0] / t,
                                   "bound": None if eff is None else eff[1],
                                   "lighting_s": m.stats.get("lighting_seconds")}
            print(kind, ev, json.dumps(out[f"{kind}/{ev}"]), flush=True)
        if len(evaluators) > 1:
            first = statistics.median(res[evaluators[0]][0])
            out[f"{kind}/ratio"] = {ev: first / statistics.median(res[ev][0]) for ev in evaluators[1:]}
            print(kind, f"median time ratio {evaluators[0]} / other", json.dumps(out[f"{kind}/ratio"]), flush=True)
    out["memory"] = m.memory()  # after the renders: includes the truncated lighting grid
    out["memory_bytes"] = sum(out["memory"].values())
    print(json.dumps(out, indent=1, default=str))
    return out


if __name__ == "__main__":
    main()
