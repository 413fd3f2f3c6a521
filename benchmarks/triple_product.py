"""Frame times, memory and roofline of TripleProduct (Ma 2006; issue #7 "Performance").

    python -m benchmarks.triple_product --size bench                  # default config
    python -m benchmarks.triple_product --size bench --preset paper   # level 4, n = 320, paper grid
    python -m benchmarks.triple_product --micro                        # evaluator micro-benchmark

Per evaluator — "class": whatever ``TripleProduct._shade`` does (today the dense `triple_integral`
of densified vectors in chunks of ~1000 points); the names of `fast_eval.EVALUATORS` go through
`fast_eval.shade` ("reference" = that same dense `triple_integral`, in `fast_eval.INNER_POINTS` sub-batches)
— the median wall and process-CPU time (CPU time is the steadier number on a shared machine) of
``--frames`` − 1 frames after one warm-up frame, for a "V" sequence (view changes; lighting fixed)
and a "VL" sequence (`make_sequence` "VBL" with the materials held at the scene's: the env map
rotates every frame, so each frame re-projects the lighting grid; BRDF edits are not scored for
this method). Also: `method.memory()` (after the renders, lighting grid included),
`fast_eval.bytes_per_frame` and the roofline efficiency (bytes_per_frame / BANDWIDTH) / frame time.
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

# Machine facts of the project's bench host (brief H4): torch triad bandwidth.
BANDWIDTH = 34e9
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


def time_sequence(method, frames, gbuffers, evaluator: str) -> tuple[list[float], list[float]]:
    """Wall and process-CPU seconds per frame for frames[1:] after rendering frames[0] (warm-up,
    lighting set). On a shared machine the CPU time (1 thread) is the steadier of the two."""
    from methods.triple_product import fast_eval

    method = fast_eval.use_reference_shading(method) if evaluator == "class" else fast_eval.use_fast_shading(method, evaluator)
    method._light_key = None  # the first frame builds the lighting grid
    method.render(frames[0], gbuffers[0])
    ts, cpu = [], []
    for f, g in zip(frames[1:], gbuffers[1:]):
        t, c = time.perf_counter(), time.process_time()
        method.render(f, g)
        ts.append(time.perf_counter() - t)
        cpu.append(time.process_time() - c)
    return ts, cpu


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


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", default="test", choices=["test", "bench"])
    ap.add_argument("--scene", default="sphere_plane")
    ap.add_argument("--preset", default="default", choices=["default", "paper"])
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="override a config value (python literal), e.g. --set n_coeffs=80")
    ap.add_argument("--frames", type=int, default=3, help="frames per sequence (the first is a warm-up)")
    ap.add_argument("--spp-side", type=int, default=1)
    ap.add_argument("--evaluators", default="class,auto",
                    help="comma list of class|auto|dense|sparse|reference")
    ap.add_argument("--kinds", default="V,VL")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--micro", action="store_true", help="only the evaluator micro-benchmark (1 and 2 threads)")
    a = ap.parse_args(argv)
    if a.micro:
        return {"micro": micro(1) + micro(2)}
    import ast

    from benchmarks.common import setup
    from methods.triple_product import fast_eval
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
    for kind in a.kinds.split(","):
        _, frames, gbs, _ = setup(scene, kind="V", n_frames=a.frames, seed=0, spp_side=a.spp_side,
                                  frames=None if kind == "V" else vl_sequence(scene, a.frames, 0))
        out["shading_points"] = int(gbs[0].hit.sum())
        bpf = fast_eval.bytes_per_frame(m, kind, envmap=frames[-1].envmap)
        out[f"bytes_per_frame_{kind}"] = bpf
        if kind == "V":
            out["max_rel_diff_vs_class"] = check_equal(m, frames[0], gbs[0], evaluators)
        for ev in evaluators:
            ts, cpu = time_sequence(m, frames, gbs, ev)
            t = statistics.median(ts)
            out[f"{kind}/{ev}"] = {"median_s": t, "fps": 1.0 / t, "times_s": ts,
                                   "median_cpu_s": statistics.median(cpu), "cpu_s": cpu,
                                   "roofline_eff": None if bpf is None else bpf / BANDWIDTH / t,
                                   "lighting_s": m.stats.get("lighting_seconds")}
            print(kind, ev, json.dumps(out[f"{kind}/{ev}"]), flush=True)
    out["memory"] = m.memory()  # after the renders: includes the truncated lighting grid
    out["memory_bytes"] = sum(out["memory"].values())
    print(json.dumps(out, indent=1, default=str))
    return out


if __name__ == "__main__":
    main()
