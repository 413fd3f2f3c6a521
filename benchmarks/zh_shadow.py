"""Timing and error of ZHShadow on the creature: `python -m benchmarks.zh_shadow --size bench --threads 2`.

Prints precompute time, model size, per-frame render time of the fast path (median and IQR of
`--repeats` renders after one warm-up) for each frame kind of `--kinds` and both shading modes, the
roofline efficiency against the machine's limits measured in the same run
(`reports.measure.triad_bandwidth`, `matmul_peak`; efficiency = max(bytes/BW, flops/peak) / time
with `ZHShadow.frame_cost`), and — with `--compare N` — the slow reference path
(`_render_reference`) timed in the same process, alternating with the fast one frame by frame
(N frames each; the machine is shared, so only such paired ratios mean much). `--micro` times the
kernels that bound the per-sample cost (one pass over the G-buffer, the feature GEMM, the
visibility interpolation) at the frame's sample count. `--oracle` samples per strategy give the
RMSE against the oracle on a held-out pose (0 skips it).
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch


def _stats(ts: list[float]) -> dict:
    q = statistics.quantiles(ts, n=4) if len(ts) >= 2 else [ts[0]] * 3
    return {"median": statistics.median(ts), "iqr": q[2] - q[0], "n": len(ts)}


def _time(f, repeats: int) -> list[float]:
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        f()
        ts.append(time.perf_counter() - t)
    return ts


def micro(gb, v: torch.Tensor, F: torch.Tensor, repeats: int) -> dict:
    """Kernels of one sample-shading frame at the G-buffer's sample count P (seconds, median):
    a read of the G-buffer arrays shading needs (normal + ωo + bary + face + region: one pass),
    the order-7 feature GEMMs (P × 31 → 48 diffuse, P × 49 → 48 specular) and the barycentric
    interpolation of the (N, 16) visibility."""
    from methods.zh_shadow import runtime as rt

    P = gb.num_samples
    g = torch.Generator().manual_seed(0)
    out = {}
    arrays = (gb.normal, gb.wo, gb.bary, gb.face, gb.region)
    out["gbuffer_pass_s"] = statistics.median(_time(lambda: [a.sum() for a in arrays], repeats))
    fd, fs = torch.randn(31, P, generator=g), torch.randn(49, P, generator=g)
    Wd, Ws = torch.randn(31, 48, generator=g), torch.randn(49, 48, generator=g)
    out["gemm_diffuse_s"] = statistics.median(_time(lambda: Wd.T @ fd, repeats))
    out["gemm_specular_s"] = statistics.median(_time(lambda: Ws.T @ fs, repeats))
    out["gemm_flops"] = 2 * P * 48 * (31 + 49)
    dirs = torch.nn.functional.normalize(torch.randn(3, P, generator=g), dim=0)
    out["features_s"] = statistics.median(_time(lambda: (rt.features(dirs, 4, True), rt.features(dirs, 4, False)),
                                                repeats))
    vT = v.T.contiguous()
    vi = F.index_select(0, gb.face.clamp_min(0)).T.contiguous()
    u, w2 = gb.bary.T

    def interp():
        return vT.index_select(1, vi[0]) * (1 - u - w2) + vT.index_select(1, vi[1]) * u + vT.index_select(1, vi[2]) * w2

    out["interpolate_s"] = statistics.median(_time(interp, repeats))
    return out


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", default="test", choices=["test", "bench"])
    ap.add_argument("--spp-side", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--kinds", default="P,L", help="comma-separated sequence kinds to time")
    ap.add_argument("--compare", type=int, default=0, help="frames of the reference path, alternating (0: skip)")
    ap.add_argument("--micro", action="store_true")
    ap.add_argument("--oracle", type=int, default=0)
    ap.add_argument("--train-poses", type=int, default=32)
    ap.add_argument("--n-dirs", type=int, default=1024)
    ap.add_argument("--fit-iters", type=int, default=60)
    ap.add_argument("--lobes", type=int, default=2)
    ap.add_argument("--order", type=int, default=4)
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    a = ap.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)

    from benchmarks.common import setup
    from methods.zh_shadow import ZHShadow
    from reports.measure import matmul_peak, triad_bandwidth

    scene, _, _, _ = setup("creature", a.size, kind="P", n_frames=1, seed=5, spp_side=a.spp_side)
    m = ZHShadow(train_poses=a.train_poses, n_dirs=a.n_dirs, lobes=a.lobes, order=a.order, fit_iters=a.fit_iters)
    t0 = time.perf_counter()
    m.precompute(scene)
    out = {"size": a.size, "threads": torch.get_num_threads(), "precompute_s": time.perf_counter() - t0,
           "stats": m.stats, "config": dict(m.config)}
    bw, peak = triad_bandwidth(), matmul_peak()
    out["triad_bandwidth_Bps"], out["matmul_peak_flops"] = bw, peak
    precomputed = m
    for kind in a.kinds.split(","):
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=1 + a.repeats, seed=5, spp_side=a.spp_side)
        for mode in ("sample", "vertex"):
            m = precomputed.with_render_config(shading=mode)  # the same precomputation, another shading mode
            m.render(frames[0], gbs[0])                                   # warm-up (lighting SH, tables)
            ts = []
            for f, g in zip(frames[1:], gbs[1:]):
                t = time.perf_counter()
                m.render(f, g)
                ts.append(time.perf_counter() - t)
            st = _stats(ts)
            cost = m.frame_cost(kind, gbs[1].num_samples)
            t_roof, bound = cost.bound(bw, peak)
            st.update({"bytes": cost.bytes, "flops": cost.flops, "roofline_s": t_roof, "bound": bound,
                       "efficiency": t_roof / st["median"]})
            if a.compare and mode == "sample":   # old vs new, alternating in this process
                fast, slow = [], []
                for r in range(a.compare):
                    f, g = frames[1 + r % a.repeats], gbs[1 + r % a.repeats]
                    for path, acc in ((m.render, fast), (m._render_reference, slow)):
                        t = time.perf_counter()
                        path(f, g)
                        acc.append(time.perf_counter() - t)
                st["paired"] = {"fast_median_s": statistics.median(fast), "reference_median_s": statistics.median(slow),
                                "ratios": [s / f for f, s in zip(fast, slow)]}
            out[f"frame_{kind}_{mode}"] = st
        if a.micro and kind == a.kinds.split(",")[0]:
            _, geom, v = precomputed.with_render_config()._pose_state(frames[1])
            out["micro"] = micro(gbs[1], v, geom.F, a.repeats)
    out["memory"] = precomputed.memory()
    if a.oracle:
        from methods.oracle import Oracle
        from references.metrics import rmse

        _, frames, gbs, _ = setup(scene, a.size, kind="P", n_frames=2, seed=5, spp_side=a.spp_side)
        o = Oracle(light_samples=a.oracle, brdf_samples=a.oracle)
        o.precompute(scene)
        ref = o.render(frames[1], gbs[1]).numpy()
        mask = gbs[1].coverage.numpy()
        for mode in ("sample", "vertex"):
            for sp in ("published", "cosine"):
                mm = precomputed.with_render_config(shading=mode, specular=sp)
                out[f"rmse_{mode}_{sp}"] = rmse(mm.render(frames[1], gbs[1]).numpy(), ref, mask)
    print(json.dumps(out, indent=1, default=str))
    return out


if __name__ == "__main__":
    main()
