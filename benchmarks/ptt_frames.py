"""PTT frame times, old (reference) vs new (fast) path, in one process (issue 14).

    python -m benchmarks.ptt_frames [--scene chess] [--size bench] [--config '{"light_res_1":4}']
                                    [--frames 5] [--threads 2] [--spp-side 2] [--kinds V VB VBL]

Precomputes once (kept in ``<cache>/ptt_frames/``, keyed by the scene's content hash and the config;
delete it to recompute), then renders each sequence kind with two instances sharing the
precomputed arrays — ``_render_reference`` (the old path) and ``render`` (the fast path) — frame by
frame, alternating which goes first, so both see the same machine load. Frame 0 of each sequence
fills the caches and is not timed. Prints the medians, their ratio, the roofline efficiency
max(bytes / triad bandwidth, flops / matmul peak) / time with ``PTT.frame_cost`` and both machine
limits measured in this run (before and after the frames; the higher of each is used), the
largest |old − new| pixel difference, and micro-benchmarks of the kernels that bound a frame:
one elementwise pass over the per-(sample, vertex) arrays, the bilinear bag of the view stage and
the T¹ lighting GEMM.
"""
from __future__ import annotations

import argparse
import copy
import hashlib
import json
import pickle
import statistics
import time
from pathlib import Path

import torch
import torch.nn.functional as Fnn

from benchmarks.common import setup
from methods.base import cache_dir
from methods.ptt.method import PTT
from reports import measure


def _precomputed(scene, config: dict) -> tuple[PTT, float | None]:
    key = hashlib.sha256((scene.content_hash() + json.dumps(config, sort_keys=True)).encode()).hexdigest()[:16]
    path = Path(cache_dir()) / "ptt_frames" / f"{scene.name}_{key}.pkl"
    if path.exists():
        with open(path, "rb") as f:
            m = pickle.load(f)
        m._reset_cache()
        return m, None
    m = PTT(**config)
    t0 = time.perf_counter()
    m.precompute(scene)
    pre = time.perf_counter() - t0
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        pickle.dump(m, f, protocol=pickle.HIGHEST_PROTOCOL)
    tmp.replace(path)
    return m, pre


def _time(fn, repeats: int = 5) -> float:
    fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def micro(m: PTT, Q: int) -> dict[str, float]:
    """Seconds of the kernels that bound a frame, on arrays of a Q-sample frame."""
    nv = int(m.V.shape[0])
    a, b = torch.rand(Q, 3, 3), torch.rand(Q, 3, 3)
    rows = torch.randint(0, nv * 16, (Q, 3))
    w = torch.rand(Q, 3)
    tab3 = torch.rand(nv * 16, 3)
    E = torch.rand(nv, m.factors.K * 3)
    vid = torch.randint(0, nv, (Q, 3))
    out = {"elementwise_pass_Qx3x3_s": _time(lambda: torch.mul(a, b)),
           "bag_Qx3_rows_of_3_s": _time(lambda: Fnn.embedding_bag(rows, tab3, per_sample_weights=w, mode="sum")),
           "bag_Qx3_rows_of_3K_s": _time(lambda: Fnn.embedding_bag(vid, E, per_sample_weights=w, mode="sum"))}
    if m.T1 is not None:
        L1 = m.T1.shape[-1]
        CL = torch.rand(L1, 3)
        out["T1_gemm_s"] = _time(lambda: m.T1.reshape(-1, L1) @ CL, 3)
        out["T1_gemm_bytes"] = m.T1.numel() * 4
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--config", default='{"light_res_1":4}')
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--spp-side", type=int, default=2)
    ap.add_argument("--kinds", nargs="+", default=["V", "VB", "VBL"])
    ap.add_argument("--no-micro", action="store_true")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    cfg = json.loads(a.config)
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1, spp_side=a.spp_side)
    m, pre = _precomputed(scene, cfg)
    out: dict = {"scene": a.scene, "size": a.size, "config": cfg, "threads": a.threads, "spp_side": a.spp_side,
                 "vertices": int(m.V.shape[0]), "precompute_s": pre}
    bw, peak = [measure.triad_bandwidth()], [measure.matmul_peak()]
    kinds = {}
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=1, spp_side=a.spp_side)
        old, new = copy.copy(m), copy.copy(m)
        old._reset_cache()
        new._reset_cache()
        t_old, t_new, diff = [], [], 0.0
        for i, (f, g) in enumerate(zip(frames, gbs)):
            order = ("old", "new") if i % 2 == 0 else ("new", "old")
            imgs = {}
            for which in order:
                t0 = time.perf_counter()
                imgs[which] = old._render_reference(f, g) if which == "old" else new.render(f, g)
                (t_old if which == "old" else t_new).append(time.perf_counter() - t0)
            diff = max(diff, float((imgs["old"] - imgs["new"]).abs().max()))
        cost = new.frame_cost(kind, gbs[-1].num_samples)
        kinds[kind] = {"old_s": t_old, "new_s": t_new, "old_median_s": statistics.median(t_old[1:]),
                       "new_median_s": statistics.median(t_new[1:]), "max_abs_diff": diff,
                       "bytes": cost.bytes, "flops": cost.flops, "hit_samples": int(gbs[-1].hit.sum())}
    bw.append(measure.triad_bandwidth())
    peak.append(measure.matmul_peak())
    B, Pk = max(bw), max(peak)
    out.update(triad_bandwidth=bw, matmul_peak=peak)
    for kind, r in kinds.items():
        for which in ("old", "new"):
            eff, bound = measure.roofline(r["bytes"], r["flops"], B, Pk, r[f"{which}_median_s"])
            r[f"{which}_efficiency"], r["bound"] = eff, bound
        r["speedup"] = r["old_median_s"] / r["new_median_s"]
    out["kinds"] = kinds
    if not a.no_micro:
        out["micro"] = micro(m, kinds[a.kinds[0]]["hit_samples"])
    print(json.dumps(out, indent=1, default=float))
    print(f"\n{a.scene} {a.size}, {a.threads} threads, triad {B / 1e9:.1f} GB/s, sgemm {Pk / 1e9:.1f} GFLOP/s")
    print(f"{'kind':5} {'old ms':>9} {'new ms':>9} {'speedup':>8} {'old eff':>8} {'new eff':>8} bound")
    for kind, r in kinds.items():
        print(f"{kind:5} {1e3 * r['old_median_s']:9.1f} {1e3 * r['new_median_s']:9.1f} {r['speedup']:8.1f} "
              f"{r['old_efficiency']:8.4f} {r['new_efficiency']:8.4f} {r['bound']}")
    return out


if __name__ == "__main__":
    main()
