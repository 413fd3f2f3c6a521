"""PTT frame times, old vs new view stage in one process (issue 14).

    python -m benchmarks.ptt_frames [--scene chess] [--size bench] [--config '{"light_res_1":4}']
                                    [--frames 5] [--threads 2] [--spp-side 2] [--kinds V VB VBL L]
                                    [--old pixel] [--new vertex] [--check]

Precomputes once (kept in ``<cache>/ptt_frames/``, keyed by the scene's content hash and the config;
delete it to recompute), then renders each sequence kind with two instances sharing the
precomputed arrays — ``--old`` and ``--new`` (``PTT.with_shading``: "pixel" is the per-sample view
stage, "vertex" Sun's per-vertex run time; "reference" is the slow reference path of the new
shading) — frame by frame, alternating which goes first, so both see the same machine load. Frame
0 of each sequence fills the caches and is not timed. Prints the median wall and CPU (process)
times, their ratio, the roofline efficiency max(bytes / triad bandwidth, flops / matmul peak) / time
with ``PTT.frame_cost`` and both machine limits measured in this run (before and after the frames;
the higher of each is used) — also with the CPU time in place of the wall time ("eff(cpu)": at one
thread on a shared machine, roughly what an unshared core would take; caches and memory bandwidth
are still shared) — the largest |old − new| pixel difference (the two view stages differ by
design), with ``--check`` the largest |fast − reference| of the new shading on the last frame, and
micro-benchmarks (wall and CPU) of the kernels that bound a frame.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch
import torch.nn.functional as Fnn

from benchmarks.common import frame_args, machine_limits, precomputed, roofline_columns, setup, wall_cpu_time
from methods.ptt.method import PTT
from reports import measure


def _precomputed(scene, config: dict) -> tuple[PTT, float | None]:
    m, pre = precomputed(PTT, scene, config)
    m = m.with_shading("vertex")
    m._fast_static()  # run-time layouts once, shared by the copies of each shading
    return m, pre


def micro(m: PTT, frame, gb) -> dict[str, float]:
    """Seconds (wall and CPU) of the kernels that bound a frame (shading="vertex"), on the arrays of ``frame``:
    the per-vertex view rows, the per-sample shading and its two bags, one elementwise pass over
    the per-sample arrays, and the lighting products (T¹ and T² GEMMs, direct incidence)."""
    from methods.core.zh import expand_bands
    from methods.ptt import fast as _fast
    from methods.ptt import transport as _tp

    m = m.with_shading("vertex")
    m.render(frame, gb)
    st = m._fast_static()
    E, I1 = m._f_E
    Wr, ar = m._f_tabs
    T, K = m.factors.W_tab.shape[-1], m.factors.K
    cam = torch.as_tensor(frame.camera.origin, dtype=torch.float32)
    L = len(m.config["lobe_degrees"]) if m.separate else 0
    lobes = env = None
    if m.separate:
        lobes = dict(ar=ar, n_theta=m.lobe_table.theta.shape[0], Tv=m.lobe_vis.shape[-1],
                     vis=m.lobe_vis.permute(0, 2, 3, 1).reshape(-1, L), I1=I1,
                     f=None if I1 is None else expand_bands(m.lobe_sh), order=m.config["sh_order"])
        env = m._f_light[3][1]
    table = _fast.vertex_view(st, cam, Wr, E, T, K, lobes)
    Q, B = gb.num_samples, _fast.SAMPLE_CHUNK
    a, b = torch.rand(Q, 3), torch.rand(Q, 3)
    fp = _fast.rows(st.face_pairs, gb.face)
    bw = torch.rand(Q, 3)
    out = {"samples": Q, "pairs": int(st.pair_v.numel()),
           "vertex_view_s": wall_cpu_time(lambda: _fast.vertex_view(st, cam, Wr, E, T, K, lobes)),
           "shade_samples_one_pass_s": wall_cpu_time(lambda: _fast.shade_samples(st.face_pairs, table, gb.face, gb.bary,
                                                                         gb.normal, gb.wo, env, L)),
           "shade_samples_chunked_s": wall_cpu_time(lambda: [
               _fast.shade_samples(st.face_pairs, table, gb.face[i:i + B], gb.bary[i:i + B], gb.normal[i:i + B],
                                   gb.wo[i:i + B], env, L) for i in range(0, Q, B)]),
           "elementwise_pass_Qx3_s": wall_cpu_time(lambda: torch.mul(a, b)),
           "bag_Qx3_rows_of_C_s": wall_cpu_time(lambda: Fnn.embedding_bag(fp, table, per_sample_weights=bw, mode="sum"))}
    if env is not None:
        from methods.ptt import specular as _spec

        out["mirror_dirs_s"] = wall_cpu_time(lambda: _spec.mirror_dirs(gb.normal, gb.wo))
        R = _spec.mirror_dirs(gb.normal, gb.wo)
        out["latlong_cells_s"] = wall_cpu_time(lambda: _spec.latlong_cells(R, env.to_world, env.H, env.W))
        idx, w = _spec.latlong_cells(R, env.to_world, env.H, env.W)
        out["env_bag_Qx4_rows_of_3L_s"] = wall_cpu_time(lambda: Fnn.embedding_bag(idx, env.ext, per_sample_weights=w,
                                                                          mode="sum"))
    CL = _tp.env_haar(frame.envmap, m.config["cube_res"], supersample=m.config["light_supersample"])
    out["direct_incidence_s"] = wall_cpu_time(lambda: _fast.direct_incidence(m.dt.idx, m.dt.val, CL), 3)
    if m.T1 is not None:
        T1s, CL1 = m.T1.permute(0, 3, 1, 2, 4), CL[m.blk1]
        out["T1_gemm_s"] = wall_cpu_time(lambda: _fast.light_product(T1s, CL1), 3)
        out["T1_gemm_bytes"] = m.T1.numel() * 4
        out["T1_gemm_flops"] = 2 * m.T1.numel() * 3
        out["T1_stream_sum_s"] = wall_cpu_time(lambda: T1s.sum(), 3)  # one read of T¹ at the machine's pace
    if m.T2 is not None:
        T2s, CL2 = m.T2.permute(0, 2, 3, 4, 5, 1), CL[m.blk2]
        out["T2_gemm_s"] = wall_cpu_time(lambda: _fast.light_product(T2s, CL2), 3)
    return out


def _render(m: PTT, which: str, f, g):
    return m._render_reference(f, g) if which == "reference" else m.render(f, g)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    frame_args(ap, scene="chess", config='{"light_res_1":4}', frames=5, kinds=("V", "VB", "VBL", "L"))
    ap.add_argument("--old", default="pixel", choices=["pixel", "vertex", "reference"])
    ap.add_argument("--new", default="vertex", choices=["pixel", "vertex"])
    ap.add_argument("--check", action="store_true", help="compare the new fast path with its reference")
    ap.add_argument("--no-micro", action="store_true")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    cfg = json.loads(a.config)
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1, spp_side=a.spp_side)
    m, pre = _precomputed(scene, cfg)
    out: dict = {"scene": a.scene, "size": a.size, "config": cfg, "threads": a.threads, "spp_side": a.spp_side,
                 "old": a.old, "new": a.new, "vertices": int(m.V.shape[0]), "precompute_s": pre}
    bw, peak = [measure.triad_bandwidth()], [measure.matmul_peak()]
    kinds = {}
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=1, spp_side=a.spp_side)
        old = m.with_shading(a.new if a.old == "reference" else a.old)
        new = m.with_shading(a.new)
        t_old, t_new, c_old, c_new, diff = [], [], [], [], 0.0
        for i, (f, g) in enumerate(zip(frames, gbs)):
            order = ("old", "new") if i % 2 == 0 else ("new", "old")
            imgs = {}
            for which in order:
                t0, c0 = time.perf_counter(), time.process_time()
                imgs[which] = _render(old, a.old, f, g) if which == "old" else new.render(f, g)
                (t_old if which == "old" else t_new).append(time.perf_counter() - t0)
                (c_old if which == "old" else c_new).append(time.process_time() - c0)
            diff = max(diff, float((imgs["old"] - imgs["new"]).abs().max()))
        r = {"old_s": t_old, "new_s": t_new, "old_median_s": statistics.median(t_old[1:]),
             "new_median_s": statistics.median(t_new[1:]), "old_cpu_median_s": statistics.median(c_old[1:]),
             "new_cpu_median_s": statistics.median(c_new[1:]), "max_abs_diff_old_new": diff,
             "hit_samples": int(gbs[-1].hit.sum())}
        for which, meth in (("old", old), ("new", new)):
            cost = meth.frame_cost(kind, gbs[-1].num_samples, pixels=gbs[-1].height * gbs[-1].width)
            r[f"{which}_bytes"], r[f"{which}_flops"] = cost.bytes, cost.flops
        if a.check:
            ref = m.with_shading(a.new)
            for f, g in zip(frames, gbs):  # the reference's caches follow the sequence like the fast path's
                img_ref = ref._render_reference(f, g)
            r["max_abs_diff_fast_reference"] = float((img_ref - imgs["new"]).abs().max())
            r["image_max"] = float(img_ref.abs().max())
        kinds[kind] = r
    B, Pk = machine_limits(out, bw, peak)
    roofline_columns(kinds, ("old", "new"), B, Pk)
    for kind, r in kinds.items():
        for which in ("old", "new"):
            # the same with the process CPU time: at 1 thread, what an unshared core would give
            r[f"{which}_cpu_efficiency"] = measure.roofline(r[f"{which}_bytes"], r[f"{which}_flops"], B, Pk,
                                                            r[f"{which}_cpu_median_s"])[0]
        r["speedup"] = r["old_median_s"] / r["new_median_s"]
    out["kinds"] = kinds
    if not a.no_micro:
        _, frames, gbs, _ = setup(scene, a.size, kind="V", n_frames=1, seed=1, spp_side=a.spp_side)
        out["micro"] = micro(m, frames[0], gbs[0])
    print(json.dumps(out, indent=1, default=float))
    print(f"\n{a.scene} {a.size}, {a.threads} threads, triad {B / 1e9:.1f} GB/s, sgemm {Pk / 1e9:.1f} GFLOP/s; "
          f"old = {a.old}, new = {a.new}")
    print(f"{'kind':5} {'old ms':>9} {'new ms':>9} {'speedup':>8} {'old cpu':>8} {'new cpu':>8} {'old eff':>8} "
          f"{'new eff':>8} {'eff(cpu)':>8} bound")
    for kind, r in kinds.items():
        print(f"{kind:5} {1e3 * r['old_median_s']:9.1f} {1e3 * r['new_median_s']:9.1f} {r['speedup']:8.1f} "
              f"{1e3 * r['old_cpu_median_s']:8.1f} {1e3 * r['new_cpu_median_s']:8.1f} "
              f"{r['old_efficiency']:8.4f} {r['new_efficiency']:8.4f} {r['new_cpu_efficiency']:8.4f} {r['new_bound']}")
    return out


if __name__ == "__main__":
    main()
