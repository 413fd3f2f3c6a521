"""Frame times of ZHShadow on the creature: `python -m benchmarks.zh_shadow --size bench --threads 2`.

Per frame kind of `--kinds` (default P, L, E, V) and shading mode: the median and IQR of the render
time over `--repeats` frames after one warm-up frame — wall clock and process CPU time (the
machine is shared: CPU time is what the frame cost this process; with 1 thread it is the better
figure under load) — the roofline efficiency against the machine's limits measured in the same
run (`reports.measure.triad_bandwidth`, `matmul_peak`; efficiency = max(bytes/BW, flops/peak) /
time with `ZHShadow.frame_cost`) and the bound. For lighting-only kinds (L, E) the first timed
frame builds the cached lighting-free transfer (`runtime.relight_cache`); its time is reported
apart ("first_s") and the median is over the frames after it.

`--compare N`: the slow reference path (`_render_reference`, §4.3 step by step: the test oracle of
the fast one) timed in the same process, alternating with the fast path frame by frame (N frames
each). `--baseline REV`: the same alternation against the fast path of git revision REV (its
`methods/zh_shadow` package loaded beside this one; the rest of the code is this checkout's) — the
before/after of a change, in one process. `--micro` times the kernels that bound a P frame
(`micro`; `micro_vertex` with vertex shading: `--modes vertex --order 8 --specular cosine` is the
perf suite's physical config). `--oracle` samples per strategy give the RMSE against the oracle on a held-out pose.

Precomputation goes through the harness's cache (`reports.precompute_cache`: keyed on the scene,
the config and the code), so repeated runs of unchanged code skip it.
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import torch

KINDS = ("P", "L", "E", "V")


def _stats(ts: list[float]) -> dict:
    q = statistics.quantiles(ts, n=4) if len(ts) >= 2 else [ts[0]] * 3
    return {"median": statistics.median(ts), "iqr": q[2] - q[0], "n": len(ts)}


def _clock(f) -> tuple[float, float]:
    """(wall, process CPU) seconds of f()."""
    t, c = time.perf_counter(), time.process_time()
    f()
    return time.perf_counter() - t, time.process_time() - c


def _best(f, repeats: int) -> float:
    """Smallest CPU time of ``repeats`` calls after one warm-up (the kernel's cost, least disturbed)."""
    f()
    return min(_clock(f)[1] for _ in range(repeats))


def load_baseline(rev: str):
    """The ZHShadow class of git revision ``rev``: its `methods/zh_shadow` package copied to a temp
    folder under another name (so both import side by side; not registered)."""
    root = Path(__file__).resolve().parents[1]
    files = subprocess.run(["git", "-C", str(root), "ls-tree", "--name-only", rev, "methods/zh_shadow/"],
                           check=True, capture_output=True, text=True).stdout.split()
    tmp = Path(tempfile.mkdtemp(prefix="zh_baseline_"))
    pkg = tmp / "zh_baseline"
    pkg.mkdir()
    for f in files:
        if f.endswith(".py"):
            src = subprocess.run(["git", "-C", str(root), "show", f"{rev}:{f}"], check=True, capture_output=True,
                                 text=True).stdout
            src = src.replace("methods.zh_shadow", "zh_baseline").replace("\n@register\n", "\n")
            (pkg / Path(f).name).write_text(src)
    sys.path.insert(0, str(tmp))
    from zh_baseline.method import ZHShadow as Baseline

    return Baseline


def micro(m, frame, gbuffer, repeats: int) -> dict:
    """CPU seconds (best of ``repeats``) of the kernels of one sample-shaded P frame at its real
    sizes: skinning (`Scene.geometry`), the pose model + eq. 1 (`runtime.world_visibility`), the
    planes' diffuse term (one `runtime.interpolate` of a 3-vector per vertex over every covered
    sample), the samples off the planes (`runtime.shade` of those alone, planes off) and, of
    that, the feature GEMM alone (``gemm_flops``: [Wd; Ws]ᵀ (n²·3 × K_d+K_s) @ features, 31 + 49
    rows at order 4; its rate against `matmul_peak` says how close to the compute roof the
    dominant kernel runs), and the resolve."""
    from methods.zh_shadow import runtime as rt

    scene = m.scene
    pose = torch.as_tensor(frame.pose).float() if frame.pose is not None else None
    out = {"skinning_s": _best(lambda: scene.geometry(pose), repeats)}
    geom = scene.geometry(pose)
    X = m.model.X
    out["pose_model_s"] = _best(lambda: rt.world_visibility(X, pose, geom.N.float(), m.model.lobes), repeats)
    v = rt.world_visibility(X, pose, geom.N.float(), m.model.lobes)
    hits = gbuffer.hit.nonzero().squeeze(-1)
    vi = geom.F.to(torch.int32).index_select(0, gbuffer.face.index_select(0, hits))
    b = rt.barycentrics(gbuffer.bary.index_select(0, hits))
    u = v[:, :3].contiguous()
    out["planes_interpolate_s"] = _best(lambda: rt.interpolate(u, vi, b), repeats)
    nT = rt.rows(gbuffer.normal.index_select(0, hits))
    woT = rt.rows(gbuffer.wo.index_select(0, hits))
    region = gbuffer.region.index_select(0, hits)
    _, _, rest = rt.planar_groups(nT)
    rest = torch.arange(hits.shape[0]) if rest is None else rest
    light = m._lighting(frame.envmap)
    Wd = rt.table(light, 1.0, diffuse=True)
    tabs = [(kd, ks, Wd, rt.table(light, al, diffuse=False) if bool((ks > 0).any()) else None)
            for kd, ks, al in m._region_materials(frame)]
    args = (v, vi[rest], b[rest], nT[:, rest], woT[:, rest], region[rest], geom.vertex_region, geom.N, tabs)
    out["off_plane_samples"] = Q = int(rest.shape[0])
    out["off_plane_shade_s"] = _best(lambda: rt.shade(*args, planar=False), repeats)
    Ws = next(t[3] for t in tabs if t[3] is not None)
    W = torch.cat([Wd, Ws])
    n = m.model.order
    f = torch.cat([rt.features(nT[:, rest], n, True), rt.features(nT[:, rest], n, False)])
    C = rt.CHUNK

    def gemms():
        for a in range(0, Q, C):
            W.T @ f[:, a:a + C]

    out["gemm_flops"] = 2 * Q * W.shape[0] * W.shape[1]
    out["gemm_s"] = _best(gemms, repeats)
    out["gemm_flops_per_s"] = out["gemm_flops"] / max(out["gemm_s"], 1e-12)
    out["resolve_s"] = _best(lambda: gbuffer.resolve(torch.zeros(3, gbuffer.num_samples), channels_first=True),
                             repeats)
    return out


def micro_vertex(m, frame, gbuffer, repeats: int, peak: float) -> dict:
    """CPU seconds (best of ``repeats``) of the kernels of one vertex-shaded P frame at its real
    sizes (N vertices): skinning, the pose model + eq. 1 (`runtime.world_visibility`, point-minor
    as the vertex path takes it), the cos θ_i-weighted visibility and the specular transfer
    (`runtime.cosine_visibility`, `runtime.zonal_conjugate` about R: the dominant kernels at order
    8) and, of one of those, the dense (n², n²) @ (n², N) X M Xᵀ GEMM alone — its rate
    (``gemm_flops_per_s``) against `matmul_peak` says how far the conjugation is from the compute
    roof (``conjugate_flops_per_s``: the GEMM's flops over the whole conjugation's time) — and the
    Gouraud resolve."""
    from methods.core import gouraud
    from methods.zh_shadow import runtime as rt

    scene = m.scene
    pose = torch.as_tensor(frame.pose).float() if frame.pose is not None else None
    out = {"skinning_s": _best(lambda: scene.geometry(pose), repeats)}
    geom = scene.geometry(pose)
    X, c = m.model.X, m.model.lobes
    nrm = geom.N.float()
    out["pose_model_s"] = _best(lambda: rt.world_visibility(X, pose, nrm, c, point_minor=True), repeats)
    vT = rt.world_visibility(X, pose, nrm, c, point_minor=True)
    nT = rt.rows(nrm)
    cam = torch.as_tensor(frame.camera.origin, dtype=torch.float32)
    woT = cam[:, None] - rt.rows(geom.V.float())
    woT = woT / (woT * woT).sum(0, keepdim=True).sqrt().clamp_min(1e-12)
    R = rt.reflect_T(nT, woT)
    out["vertices"] = N = int(vT.shape[1])
    out["cosine_visibility_s"] = _best(lambda: rt.cosine_visibility(vT, nT), repeats)
    al = next((float(a) for _, ks, a in m._region_materials(frame) if bool((ks > 0).any())), 1.0)
    out["specular_conjugate_s"] = _best(lambda: rt.zonal_conjugate(vT, R, ("phong", al)), repeats)
    n2 = vT.shape[0]
    K = rt._conjugated(("phong", al), math.isqrt(n2)).float()
    out["gemm_flops"] = 2 * n2 * n2 * N
    out["gemm_s"] = _best(lambda: K @ vT, repeats)
    out["gemm_flops_per_s"] = out["gemm_flops"] / max(out["gemm_s"], 1e-12)
    out["conjugate_flops_per_s"] = out["gemm_flops"] / max(out["specular_conjugate_s"], 1e-12)
    rad = torch.zeros(N, 3)
    out["resolve_s"] = _best(lambda: gouraud.resolve(rad, geom.F.T, gbuffer.face, gbuffer.bary, gbuffer.hit,
                                                     gbuffer.height, gbuffer.width, gbuffer.spp_side), repeats)
    out["matmul_peak_flops"] = peak
    return out


def time_kind(m, frames, gbs, kind: str, repeats: int) -> dict:
    """Render frames[0] (warm-up) then frames[1:]; for L/E the first of those builds the transfer."""
    m.render(frames[0], gbs[0])
    wall, cpu = [], []
    for f, g in zip(frames[1:], gbs[1:]):
        w, c = _clock(lambda: m.render(f, g))
        wall.append(w)
        cpu.append(c)
    st = {}
    if kind in ("L", "E") and m.config["shading"] == "sample" and len(wall) > 1:
        st["first_s"], st["first_cpu_s"] = wall[0], cpu[0]
        wall, cpu = wall[1:], cpu[1:]
    st["wall"], st["cpu"] = _stats(wall), _stats(cpu)
    return st


def paired(paths: list, frames, gbs, n: int) -> dict:
    """Alternate the render paths frame by frame (n frames each, cycling over frames[1:] in order
    — the caches see the sequence as it comes); medians of wall and CPU seconds per path."""
    acc = {name: ([], []) for name, _ in paths}
    for _, p in paths:
        p(frames[0], gbs[0])
    for r in range(n):
        i = 1 + r % (len(frames) - 1)
        for name, p in paths:
            w, c = _clock(lambda: p(frames[i], gbs[i]))
            acc[name][0].append(w)
            acc[name][1].append(c)
    return {name: {"wall_median_s": statistics.median(w), "cpu_median_s": statistics.median(c)}
            for name, (w, c) in acc.items()}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--size", default="test", choices=["test", "bench"])
    ap.add_argument("--spp-side", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--kinds", default=",".join(KINDS), help="comma-separated sequence kinds to time")
    ap.add_argument("--modes", default="sample,vertex", help="shading modes to time")
    ap.add_argument("--compare", type=int, default=0, help="frames of the reference path, alternating (0: skip)")
    ap.add_argument("--baseline", default=None, help="git revision whose fast path to alternate with")
    ap.add_argument("--micro", action="store_true")
    ap.add_argument("--oracle", type=int, default=0)
    ap.add_argument("--train-poses", type=int, default=32)
    ap.add_argument("--n-dirs", type=int, default=1024)
    ap.add_argument("--fit-iters", type=int, default=60)
    ap.add_argument("--lobes", type=int, default=2)
    ap.add_argument("--order", type=int, default=4)
    ap.add_argument("--specular", default="published", choices=["published", "cosine"])
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    a = ap.parse_args(argv)
    if a.threads:
        torch.set_num_threads(a.threads)

    from benchmarks.common import setup
    from methods.zh_shadow import ZHShadow
    from reports import precompute_cache
    from reports.cells import canonical_config
    from reports.measure import matmul_peak, triad_bandwidth

    scene, _, _, _ = setup("creature", a.size, kind="P", n_frames=1, seed=5, spp_side=a.spp_side)
    cfg = dict(train_poses=a.train_poses, n_dirs=a.n_dirs, lobes=a.lobes, order=a.order, fit_iters=a.fit_iters)
    m = ZHShadow(**cfg)
    pre = precompute_cache.precompute(m, scene, canonical_config(cfg))
    out = {"size": a.size, "threads": torch.get_num_threads(), "precompute": pre, "stats": m.stats,
           "config": dict(m.config)}
    bw, peak = triad_bandwidth(), matmul_peak()
    out["triad_bandwidth_Bps"], out["matmul_peak_flops"] = bw, peak
    precomputed = m
    if a.baseline:
        base_cls = load_baseline(a.baseline)
        out["baseline"] = a.baseline
    kinds = a.kinds.split(",")
    for kind in kinds:
        n = 1 + a.repeats + (1 if kind in ("L", "E") else 0)
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=n, seed=5, spp_side=a.spp_side)
        for mode in a.modes.split(","):
            m = precomputed.with_render_config(shading=mode, specular=a.specular)   # the same precomputation,
            #                                                                      fresh frame caches
            st = time_kind(m, frames, gbs, kind, a.repeats)
            cost = m.frame_cost(kind, gbs[1].num_samples, pixels=gbs[1].height * gbs[1].width)
            t_roof, bound = cost.bound(bw, peak)
            st.update({"bytes": cost.bytes, "flops": cost.flops, "roofline_s": t_roof, "bound": bound,
                       "efficiency": t_roof / st["wall"]["median"]})
            if mode == "sample" and (a.compare or a.baseline):
                paths = [("fast", precomputed.with_render_config(shading=mode).render)]
                if a.compare:
                    ref = precomputed.with_render_config(shading=mode)
                    paths.append(("reference", ref._render_reference))
                if a.baseline:
                    base = base_cls(**{**cfg, "shading": mode})
                    base.scene = precomputed.scene
                    base.model = _baseline_model(precomputed.model)
                    paths.append(("baseline", base.render))
                st["paired"] = paired(paths, frames, gbs, max(a.compare, a.repeats if a.baseline else 0))
            out[f"frame_{kind}_{mode}"] = st
    if a.micro:
        _, frames, gbs, _ = setup(scene, a.size, kind="P", n_frames=2, seed=5, spp_side=a.spp_side)
        modes = a.modes.split(",")
        if "sample" in modes:
            out["micro"] = micro(precomputed.with_render_config(specular=a.specular), frames[1], gbs[1], a.repeats)
            out["micro"]["matmul_peak_flops"] = peak
        if "vertex" in modes:
            out["micro_vertex"] = micro_vertex(precomputed, frames[1], gbs[1], a.repeats, peak)
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


def _baseline_model(model):
    """The baseline package's ZHModel holding this model's arrays."""
    from zh_baseline.precompute import ZHModel

    return ZHModel(model.X, model.order, model.lobes)


if __name__ == "__main__":
    main()
