"""In-out shading per sample vs per vertex (issue 14), in one process on one precomputation.

    python -m benchmarks.inout_vertex [--scene sphere_plane] [--size bench] [--config '{}'] [--frames 7]
                                      [--threads 2] [--spp-side 2] [--kinds V L E]

Precomputes once (the harness's precompute cache, `benchmarks.common.precomputed`; ``shading`` is a
run-time setting, so both copies share it), then renders each sequence kind with ``shading="sample"``
(`InOut.render`'s per-sample fast path) and ``shading="vertex"`` (`InOut._render_vertex`), frame by
frame, alternating which goes first (same machine load for both). Frame 0 fills the caches and is not
timed. Prints the medians, their ratio, the roofline efficiency of the vertex path with its
``frame_cost`` and both machine limits measured in this run, the vertex image's max |difference| from
the per-sample one, and micro-benchmarks of a vertex frame's parts (`micro`) against one read of the
G-buffer arrays it reads (face, barycentrics, hit).
"""
from __future__ import annotations

import argparse
import copy
import json
import statistics
import time

import torch

from benchmarks.common import (frame_args, inout_regions, machine_limits, median_time, precomputed, roofline_columns,
                               setup)
from methods.core import gouraud
from methods.inout import fast
from methods.inout.method import InOut
from reports import measure


def _time(fn) -> float:
    return median_time(fn, 7)


def _copy(m: InOut, shading: str) -> InOut:
    c = copy.copy(m)
    c._config = {**m._config, "shading": shading}
    c._reset_cache()
    return c


def micro(m: InOut, frame, gb) -> dict[str, float]:
    """Seconds (median of 7 after a warm-up) of a vertex frame's parts on ``frame`` (c_k cached):
    the view part (`InOut._vertex_view` uncached: referenced faces and vertices, their cells), eq. 4
    per shaded vertex (``fast.vertex_radiance``), the Gouraud resolve (``core.gouraud.resolve``), one
    read of the G-buffer arrays the frame reads, and the lighting product c = T̃ · L of the shaded
    vertices (`InOut._ensure_c` from scratch)."""
    st = m._fast_static()
    out: dict[str, float] = {}

    def view():
        m._vview = None
        return m._vertex_view(frame, gb)

    vv = view()
    out["view_s"] = _time(view)
    out["shaded_vertices"] = sum(int(s[0].numel()) for s in vv["slots"])
    out["referenced_vertices"] = vv["ref"]
    cs = [m._ensure_c(s, sl[0]) for s, sl in enumerate(vv["slots"])]
    out["vertex_radiance_s"] = _time(lambda: [fast.vertex_radiance(st.regions[s], cs[s], *sl)
                                              for s, sl in enumerate(vv["slots"]) if sl[0].numel()])
    Bv = torch.rand(st.voff[-1], 3)
    out["resolve_s"] = _time(lambda: gouraud.resolve(Bv, st.face_gl, gb.face, gb.bary, gb.hit, gb.height, gb.width,
                                                     gb.spp_side))
    arrays = (gb.face, gb.bary, gb.hit)
    out["gbuffer_bytes"] = sum(a.numel() * a.element_size() for a in arrays)
    out["gbuffer_read_s"] = _time(lambda: [a.max() for a in arrays])

    def light():   # as under a later lighting change (the first one computes every vertex's c)
        m._cf, m._cf_valid, m._lightings = {}, {}, 2
        return [m._ensure_c(s, sl[0]) for s, sl in enumerate(vv["slots"])]

    saved = (m._cf, m._cf_valid, m._lightings)
    out["light_product_s"] = _time(light)
    m._cf, m._cf_valid, m._lightings = saved
    return out


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    frame_args(ap, scene="sphere_plane", frames=8)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    cfg = {k: v for k, v in json.loads(a.config).items() if k != "shading"}
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1, spp_side=a.spp_side)
    m, pre = precomputed(InOut, scene, cfg)
    m._fast = None
    m._reset_cache()
    out: dict = {"scene": a.scene, "size": a.size, "config": cfg, "threads": a.threads, "spp_side": a.spp_side,
                 **inout_regions(m), "precompute_s": pre}
    bw, peak = [measure.triad_bandwidth()], [measure.matmul_peak()]
    kinds, last = {}, None
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=1, spp_side=a.spp_side)
        ms = {"sample": _copy(m, "sample"), "vertex": _copy(m, "vertex")}
        t = {"sample": [], "vertex": []}
        diff, scale = 0.0, 0.0
        for i, (f, g) in enumerate(zip(frames, gbs)):
            imgs = {}
            for which in (("sample", "vertex") if i % 2 == 0 else ("vertex", "sample")):
                t0 = time.perf_counter()
                imgs[which] = ms[which].render(f, g)
                t[which].append(time.perf_counter() - t0)
            diff = max(diff, float((imgs["sample"] - imgs["vertex"]).abs().max()))
            scale = max(scale, float(imgs["sample"].abs().max()))
        r = {"sample_median_s": statistics.median(t["sample"][1:]), "vertex_median_s": statistics.median(t["vertex"][1:]),
             "max_abs_diff_vs_sample": diff, "image_max": scale}
        for which in ("sample", "vertex"):
            c = ms[which].frame_cost(kind, gbs[-1].num_samples, pixels=gbs[-1].height * gbs[-1].width)
            r[f"{which}_bytes"], r[f"{which}_flops"] = c.bytes, c.flops
        kinds[kind] = r
        if last is None or kind == "V":
            last = (ms["vertex"], frames[-1], gbs[-1])
    B, Pk = machine_limits(out, bw, peak)
    roofline_columns(kinds, ("sample", "vertex"), B, Pk)
    for r in kinds.values():
        r["speedup"] = r["sample_median_s"] / r["vertex_median_s"]
    out["kinds"] = kinds
    out["micro"] = micro(*last)
    print(json.dumps(out, indent=1, default=float))
    print(f"\n{a.scene} {a.size}, {a.threads} threads, triad {B / 1e9:.1f} GB/s, sgemm {Pk / 1e9:.1f} GFLOP/s")
    print(f"{'kind':5} {'sample ms':>10} {'vertex ms':>10} {'speedup':>8} {'eff smp':>8} {'eff vtx':>8} bound(vtx)")
    for kind, r in kinds.items():
        print(f"{kind:5} {1e3 * r['sample_median_s']:10.2f} {1e3 * r['vertex_median_s']:10.2f} {r['speedup']:8.1f} "
              f"{r['sample_efficiency']:8.4f} {r['vertex_efficiency']:8.4f} {r['vertex_bound']}")
    u = out["micro"]
    print(f"vertex frame parts: view {1e3 * u['view_s']:.2f} ms ({u['referenced_vertices']} referenced, "
          f"{u['shaded_vertices']} shaded vertices), eq. 4 per vertex {1e3 * u['vertex_radiance_s']:.2f} ms, "
          f"Gouraud resolve {1e3 * u['resolve_s']:.2f} ms, one G-buffer read {1e3 * u['gbuffer_read_s']:.2f} ms "
          f"({u['gbuffer_bytes'] / u['gbuffer_read_s'] / 1e9:.1f} GB/s), c = T·L {1e3 * u['light_product_s']:.2f} ms")
    return out


if __name__ == "__main__":
    main()
