"""Where a PTT frame's time goes (issue 14): chess bench V, VB and L frames, stage by stage.

    python -m benchmarks.ptt_profile [--scene chess] [--size bench] [--config '{"light_res_1":4}']
                                     [--frames 7] [--threads 1] [--kinds V VB L]

Renders each sequence kind with the fast path (frame 0 fills the caches and is not counted; ``--bounces``, default 0 as the perf suite) with
every stage of `PTT.render` wrapped in a timer (process CPU and wall time), and prints the median
per stage: the BRDF coordinates H (`PTT.coords`, the least-squares fit of a changed material), the
region tables, the BRDF products (Sun eq. 4), the lighting stage's parts (Haar of the env map, the
direct incidence bag, the T¹ / T² GEMMs, the lobe prefilters) and the view stage (per-pair rows,
per-sample shading)."""
from __future__ import annotations

import argparse
import collections
import contextlib
import json
import statistics
import time

import os

import torch

from benchmarks.common import frame_args, precomputed, setup
from methods.ptt import fast as _fast
from methods.ptt import method as _method
from methods.ptt import specular as _spec
from methods.ptt import transport as _tp
from methods.core.fused import fused
from methods.ptt.method import PTT

T_CPU: dict = collections.defaultdict(float)
T_WALL: dict = collections.defaultdict(float)


def _wrap(mod, name, label):
    f = getattr(mod, name)

    def g(*a, **k):
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            return f(*a, **k)
        finally:
            T_WALL[label] += time.perf_counter() - t0
            T_CPU[label] += time.process_time() - c0

    setattr(mod, name, g)
    return f


@contextlib.contextmanager
def instrumented():
    saved = []
    for mod, name, label in [
        (PTT, "coords", "brdf: coords H"),
        (_fast, "region_tables", "brdf: region tables"),
        (_fast, "brdf_products", "brdf: eq.4 products"),
        (_tp, "env_haar", "light: env_haar"),
        (_fast, "direct_incidence", "light: direct incidence"),
        (_fast, "lighting_products", "light: T1/T2 GEMMs"),
        (_spec, "prefilter_env", "light: lobe prefilter"),
        (_spec, "on_env_grid", "light: on_env_grid"),
        (_fast, "env_stack", "light: env_stack"),
        (_fast, "vertex_view", "view: pair rows"),
        (_fast, "shade_pixels_fused", "view: samples"),
        (_fast, "shade_samples_fused", "view: samples (2-pass)"),
    ]:
        saved.append((mod, name, _wrap(mod, name, label)))
    try:
        yield
    finally:
        for mod, name, f in saved:
            setattr(mod, name, f)


def _probe_rows_fn(face, face_pairs, table, erows, r, W: int):
    """`fast.shade_block`'s seven row loads (3 pair rows, 4 env rows) summed, without its arithmetic."""
    p0, p1, p2 = face_pairs[face, 0], face_pairs[face, 1], face_pairs[face, 2]
    t = table[p0] + table[p1] + table[p2] + erows[r] + erows[r + 1] + erows[r + (W + 1)] + erows[r + (W + 2)]
    return t.sum(-1)


def _probe_scalars_fn(face, bary, u, v, face_pairs, H: int, W: int):
    """`fast.shade_block`'s per-sample scalar arithmetic (face-pair indices, Gouraud and lat-long cell
    weights), without its row loads."""
    p0, p1, p2 = face_pairs[face, 0], face_pairs[face, 1], face_pairs[face, 2]
    b1, b2 = bary[:, 0], bary[:, 1]
    uu = u - 0.5 / W
    x = (uu - torch.floor(uu)) * W
    y = (v - torch.floor(v)) * (H - 1)
    ix = x.to(torch.int64).clamp(max=W - 1)
    iy = y.to(torch.int64).clamp(max=H - 2)
    fx, fy = x - ix, y - iy
    r = iy * (W + 1) + ix
    return (p0 + p1 + p2 + r).float() * (1.0 - b1 - b2) + fx * fy


_probe_rows = fused(_probe_rows_fn)
_probe_scalars = fused(_probe_scalars_fn)


def micro(m: PTT, frame, gb, threads: int) -> None:
    """The kernels that bound the frames, alone on this frame's sizes, with their achieved GB/s next
    to the machine's triad bandwidth (``benchmarks.common.machine_limits``): the per-sample view stage
    (`fast.shade_pixels_fused`) and its two compiled loops (`fast.mirror_cells_block`, `fast.shade_block`;
    `fast.mirror_uv` alone for comparison),
    two probes that split `shade_block` into its row loads and its per-sample scalar arithmetic,
    the eager passes and bags of the previous route, the direct incidence product (CSR, and the
    ``embedding_bag`` it replaced), one cube resampling of the env map (``cubemap.from_envmap``)
    and the resampling of the prefiltered maps onto the env grid (``specular.on_env_grid``)."""
    import torch.nn.functional as Fnn

    from methods.ptt import native as _native

    from benchmarks.common import machine_limits, wall_cpu_time
    from methods.core import cubemap
    from reports import measure

    m.render(frame, gb)
    st = m._fast_static()
    E, I1 = m._f_E
    Wr, ar = m._f_tabs
    L = len(m.config["lobe_degrees"])
    T, K = m.factors.W_tab.shape[-1], m.factors.K
    cam = torch.as_tensor(frame.camera.origin, dtype=torch.float32)
    from methods.core.zh import expand_bands
    lobes = dict(ar=ar, n_theta=m.lobe_table.theta.shape[0], Tv=m.lobe_vis.shape[-1],
                 vis=m.lobe_vis.permute(0, 2, 3, 1).reshape(-1, L), I1=I1,
                 f=None if I1 is None else expand_bands(m.lobe_sh), order=m.config["sh_order"])
    env = m._f_light[3][1]
    C = 3 + 3 * L + (3 if I1 is not None else 0)
    width = _fast.table_width(C)
    table = _fast.vertex_view(st, cam, Wr, E, T, K, lobes, width)
    Q, S2 = gb.num_samples, gb.spp_side ** 2
    u, v = _fast.mirror_uv(gb.normal, gb.wo, env.to_world)
    rc, fxc, fyc = _fast.mirror_cells_block(gb.normal, gb.wo, env.to_world, env.H, env.W)
    erows = _fast.env_rows(env, width)
    lanes = _fast._lane_masks(C, L, width)
    # the previous route (eager cells, ``embedding_bag``s), for comparison
    idx, w = _spec._uv_cells(u, v, env.H, env.W)
    bw = torch.stack([1.0 - gb.bary[:, 0] - gb.bary[:, 1], gb.bary[:, 0], gb.bary[:, 1]], -1)
    zf, zr = torch.zeros_like(gb.face), torch.zeros_like(idx[:, 0])
    f4 = 4
    if os.environ.get("PTT_DUMP_SHADE"):
        torch.save(dict(face=gb.face, bary=gb.bary, r=rc, fx=fxc, fy=fyc, face_pairs=st.face_pairs, table=table,
                        env=erows, lanes=lanes, W=env.W, S2=S2), os.environ["PTT_DUMP_SHADE"])
    # bytes each kernel must move at least: its inputs once and its output
    kern = {
        "samples: whole stage (shade_pixels_fused)": (lambda: _fast.shade_pixels_fused(
            st.face_pairs, table, gb.face, gb.bary, gb.normal, gb.wo, env, L, S2, C), Q * (8 + 8 + 12 + 12) + Q // S2 * 12),
        "samples: mirror_uv (compiled)": (lambda: _fast.mirror_uv(gb.normal, gb.wo, env.to_world), Q * (24 + 8)),
        "samples: mirror_cells (compiled)": (lambda: _fast.mirror_cells_block(gb.normal, gb.wo, env.to_world, env.H,
                                                                               env.W), Q * (24 + 12)),
        "samples: shade_block (compiled)": (lambda: _fast.shade_block(gb.face, gb.bary, rc, fxc, fyc, st.face_pairs,
                                                                      table, erows, lanes, env.W, S2),
                                            Q * (8 + 8 + 12) + Q // S2 * 12),
        "samples: shade_block (native)": (lambda: _native.shade_pixels(gb.face, gb.bary, rc, fxc, fyc, st.face_pairs,
                                                                      table, erows, lanes, env.W, S2),
                                          Q * (8 + 8 + 12) + Q // S2 * 12),
        "samples: cells + shade_block (native.shade_mirror)": (
            lambda: _native.shade_mirror(gb.normal, gb.wo, env.to_world, env.H, gb.face, gb.bary, st.face_pairs, table,
                                         erows, lanes, env.W, S2), Q * (8 + 8 + 24 + 12) + Q // S2 * 12),
        "samples: mirror_cells (native)": (lambda: _native.mirror_cells(gb.normal, gb.wo, env.to_world, env.H, env.W),
                                           Q * (24 + 12)),
        "  probe: its 7 row loads only": (lambda: _probe_rows(gb.face, st.face_pairs, table, erows, idx[:, 0], env.W),
                                          Q * (8 + 8) + Q * 4),
        "  probe: the same 7 loads, every index 0 (L1)": (
            lambda: _probe_rows(zf, st.face_pairs, table, erows, zr, env.W),
            Q * (8 + 8) + Q * 4),
        "  probe: its per-sample scalars only": (lambda: _probe_scalars(gb.face, gb.bary, u, v, st.face_pairs, env.H, env.W),
                                                 Q * (8 + 8 + 8) + Q * 4),
        "samples: eager mirror_dirs + latlong_uv (before)": (
            lambda: _spec._latlong_uv(_spec.mirror_dirs(gb.normal, gb.wo), env.to_world), Q * (24 + 8)),
        "samples: face rows + Gouraud bag (before)": (
            lambda: Fnn.embedding_bag(_fast.rows(st.face_pairs, gb.face), table[:, :C].contiguous(),
                                      per_sample_weights=bw, mode="sum"), Q * (8 + 12 + C * f4)),
        "samples: env bag (4 rows of 3L) (before)": (
            lambda: Fnn.embedding_bag(idx, env.ext, per_sample_weights=w, mode="sum"), Q * (32 + 16 + 3 * L * f4)),
        "pairs: vertex_view": (lambda: _fast.vertex_view(st, cam, Wr, E, T, K, lobes, width), table.numel() * f4),
    }
    CL = _tp.env_haar(frame.envmap, m.config["cube_res"], supersample=m.config["light_supersample"])
    dt = (m.dt.idx.numel() * m.dt.idx.element_size() + m.dt.val.numel() * 4)
    kern["light: direct incidence (CSR)"] = (lambda: _fast.direct_incidence(m.dt.idx, m.dt.val, CL), dt)
    kern["light: direct incidence (embedding_bag)"] = (lambda: _fast.direct_incidence_bag(m.dt.idx, m.dt.val, CL), dt)
    kern["light: one cube resampling (32², s 8)"] = (
        lambda: cubemap.from_envmap(frame.envmap, m.config["cube_res"], supersample=m.config["light_supersample"]),
        frame.envmap.data.numel() * 4)
    maps = _spec.prefilter_env(frame.envmap, m.env_filters, supersample=m.config["light_supersample"])
    kern["light: on_env_grid"] = (lambda: _spec.on_env_grid(maps, frame.envmap), 3 * frame.envmap.data.numel() * 4)
    lim: dict = {}
    B, Pk = machine_limits(lim, [measure.triad_bandwidth()], [measure.matmul_peak()])
    print(f"\nmicro-benchmarks ({threads} thread(s); {Q} samples, {table.shape[0] - 1} pairs; triad {B / 1e9:.1f} GB/s,"
          f" sgemm {Pk / 1e9:.1f} GFLOP/s); ms wall / cpu, CPU ns per sample, GB/s of the compulsory bytes on wall / cpu time"
          f" (under load the CPU-time figure is the one to compare with a quiet machine's triad, ~36 GB/s):")
    for name, (fn, nbytes) in kern.items():
        t = wall_cpu_time(fn, 7)
        per = f"{1e9 * t['cpu'] / Q:5.1f} ns/sample" if name.lstrip().startswith(("samples", "probe")) else " " * 14
        print(f"  {name:48s} {1e3 * t['wall']:7.2f} {1e3 * t['cpu']:7.2f}  {per}  {nbytes / 1e6:7.1f} MB "
              f"{nbytes / t['wall'] / 1e9:6.2f} / {nbytes / max(t['cpu'], 1e-9) / 1e9:6.2f} GB/s "
              f"({100 * nbytes / t['wall'] / B:.1f} % of the triad measured now)")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    frame_args(ap, scene="chess", config='{"light_res_1":4}', frames=7, kinds=("V", "VB", "L"))
    ap.add_argument("--bounces", type=int, default=0, help="rendered bounces (the perf suite: 0)")
    ap.add_argument("--micro", action="store_true", help="also time the bounding kernels alone (`micro`)")
    ap.add_argument("--precompute-of", default="",
                    help="look the precomputation up under this checkout's code fingerprint ('' = this one's; "
                         "benchmarks.ptt_ab.base_fingerprint)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    if a.precompute_of:
        from benchmarks.ptt_ab import base_fingerprint
        from reports import precompute_cache

        fp = base_fingerprint(a.precompute_of)
        precompute_cache._process_fingerprint = lambda module: fp
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1, spp_side=a.spp_side)
    m, _ = precomputed(PTT, scene, json.loads(a.config))
    m = m.with_shading("vertex").with_bounces(a.bounces)
    m._fast_static()
    res = {}
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=1, spp_side=a.spp_side)
        r = m.with_shading("vertex")
        per = collections.defaultdict(list)
        with instrumented():
            for i, (f, g) in enumerate(zip(frames, gbs)):
                T_CPU.clear(); T_WALL.clear()
                t0, c0 = time.perf_counter(), time.process_time()
                r.render(f, g)
                w, c = time.perf_counter() - t0, time.process_time() - c0
                if i == 0:
                    continue
                per["frame"].append((w, c))
                for k in T_CPU:
                    per[k].append((T_WALL[k], T_CPU[k]))
        n = len(per["frame"])
        out = {}
        for k, v in per.items():
            v = v + [(0.0, 0.0)] * (n - len(v))
            out[k] = (1e3 * statistics.median(x[0] for x in v), 1e3 * statistics.median(x[1] for x in v))
        res[kind] = out
        print(f"\n{a.scene} {a.size} {kind}, {a.threads} thread(s), median of {n} frames (ms wall / cpu):")
        for k, (w, c) in sorted(out.items(), key=lambda kv: -kv[1][1]):
            print(f"  {k:28s} {w:8.2f} {c:8.2f}")
    if a.micro:
        _, frames, gbs, _ = setup(scene, a.size, kind="V", n_frames=1, seed=1, spp_side=a.spp_side)
        micro(m.with_shading("vertex"), frames[0], gbs[0], a.threads)
    return res


if __name__ == "__main__":
    main()
