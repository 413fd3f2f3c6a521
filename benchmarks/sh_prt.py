"""SH PRT frames against another checkout's code in one process, and what bounds them (issue 14).

    python -m benchmarks.sh_prt --baseline OTHER_CHECKOUT [--scene creature] [--kinds V L E VL]
                                [--frames 9] [--threads 1] [--bounces 0] [--micro] [--precompute-code DIR]
                                [--build-repeat N]

Precomputes once (`benchmarks.common.precomputed`; ``--precompute-code DIR``: take the harness cache
entry of the code in DIR — a change of run-time code only leaves the precomputed state the same),
gives the state to this tree's `SHPRT` and to the baseline's (imported with its whole ``methods``
package, `benchmarks.vview.baseline_class`; its frames render inside `checkout_modules`), renders each kind's frames
alternating which goes first, frames 0–1 untimed, and prints per kind the medians of process CPU
and wall time, their ratio, the roofline efficiency of the new code (its ``frame_cost``, the machine
limits measured in the run) and max |new − reference| / max |reference| (`render_reference`).

``--build-repeat N`` (session 42): the L / E kinds' medians above are of their steady frames (frames 0-1 untimed:
the relight cache's build is frame 1); this also times that first lighting-only frame N times per kind, each
object's cache reset, old and new alternating (`benchmarks.sh_prt_first_light`, first repeat dropped).

``--micro``: each stage of the new code alone on the last frame's real sizes (median of 7 after a
warm-up, process CPU ms), with its achieved GB/s or GFLOP/s next to the machine's:
  light  project (E frames: SH of the env map in its polar frame, `project_latlong_polar`; also
         `sh.project_latlong`, which it replaced), rotate (L: the cached coefficients), t·l and M l
         (`apply_lighting`; bytes: t or M streamed once; also the einsum it replaced), the face-corner
         table e[F];
  (session 28: also the native C loops that run where a compiler is — ``native ms`` of the projection,
  the pixel pass with its glossy list, the glossy pass — next to the compiled / torch stages above)
  view   the per-pixel diffuse pass (`_pixels`; bytes: the G-buffer inputs it reads — face, hit,
         bary, normal, wo; not the region — the face tables and the pixels written), the glossy selection (nonzero of the pass's flags), the glossy pass (`_glossy_samples`: ns
         per glossy sample and GFLOP/s of the counted (18 + 3 + 1 + 6)·n² flops per sample).
"""
from __future__ import annotations

import argparse
import copy
import json
import os

import torch

from benchmarks.common import ab_frames, ab_report, frame_args, machine_limits, precomputed, setup, wall_cpu_time
from benchmarks.vview import baseline_class
from reports import measure


def main(argv: list[str] | None = None) -> dict:
    ap = frame_args(argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter),
                    scene="creature", frames=9, kinds=("V", "L", "E", "VL"))
    ap.set_defaults(threads=1)
    ap.add_argument("--baseline", required=True, help="the checkout whose methods/sh_prt is the 'before'")
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--micro", action="store_true")
    ap.add_argument("--build-repeat", type=int, default=0,
                    help="session 42: also time the first lighting-only frame (the relight cache's build, never in "
                         "the steady medians above: frames 0-1 are untimed) of the L / E kinds this many times, "
                         "old and new alternating (`benchmarks.sh_prt_first_light`'s same-process mode, bounces 0)")
    ap.add_argument("--bounces", type=int, default=0, help="interreflection passes rendered (`SHPRT.with_bounces`; "
                    "the perf suite's cells: 0)")
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)
    if a.precompute_code:
        from reports import precompute_cache
        from reports.store import code_closure_fingerprint

        precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, a.precompute_code)
    from methods.sh_prt.method import SHPRT as New

    cfg = json.loads(a.config)
    Base = baseline_class("sh_prt", a.baseline)
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1)
    m, _ = precomputed(New, scene, cfg)
    m = m.with_bounces(a.bounces)
    out: dict = {"scene": a.scene, "size": a.size, "config": cfg, "bounces": a.bounces, "threads": a.threads,
                 "load": os.getloadavg()}
    bw, peak = [measure.triad_bandwidth()], [measure.matmul_peak()]
    kinds, last = {}, {}
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=1, spp_side=a.spp_side)
        new = copy.copy(m)
        new._reset_cache()
        base = copy.copy(new)
        base.__class__ = Base
        ref = copy.copy(new)
        r = ab_frames(new, base, ref.render_reference, frames, gbs, kind, base_root=a.baseline)
        kinds[kind] = r
        last = {"m": new, "frame": frames[-1], "gb": gbs[-1], "frames": frames}
    B, Pk = machine_limits(out, bw, peak)
    if a.micro:
        out["micro"] = micro(last["m"], last["frames"], last["gb"], B, Pk)
    ab_report(out, kinds, B, Pk, f"sh_prt {a.config} bounces {a.bounces}, {a.scene} {a.size}, {a.threads} thread(s)",
              show_mb=True)
    build_kinds = [k for k in a.kinds if k in ("L", "E")]
    if a.build_repeat > 0 and build_kinds:
        from benchmarks import sh_prt_first_light

        print("the first lighting-only frame (the relight cache's build; the steady medians above exclude it):")
        sh_prt_first_light.same_process(argparse.Namespace(baseline=a.baseline, precompute_code=a.precompute_code,
                                                           kinds=build_kinds, repeat=a.build_repeat,
                                                           threads=a.threads))
    return out


def micro(m, frames, gb, B: float, Pk: float) -> dict:
    """The stages of `SHPRT.render` alone on the frame's real sizes (module docstring)."""
    from methods.core import sh as _sh
    from methods.core.fused import map_rows
    from methods.sh_prt import method as shm

    ms = lambda fn: 1e3 * wall_cpu_time(fn, 7)["cpu"]  # noqa: E731
    frame = frames[-1]
    env = frame.envmap
    m._light_stage(env)
    kd, ks, G, vcos = m._materials(frame)
    res: dict = {}
    data = env.data
    res["light: project"] = {"ms": ms(lambda: _sh.project_latlong_polar(data, m.order)),
                             "texels": float(data.shape[0] * data.shape[1]),
                             "sh.project_latlong ms": ms(lambda: _sh.project_latlong(data.double(), m.order))}
    res["light: project"]["native ms"] = ms(lambda: shm.sh_native.project_latlong_polar(data, m.order))
    res["light: rotate"] = {"ms": ms(lambda: m.lighting(env))}
    l = m._light
    ng, n2 = m.M.shape[0], m.M.shape[1]
    Mr = m.M.reshape(ng * n2, *m.M.shape[2:])
    for name, X in (("t", m.t), ("M", Mr)):
        t_new = ms(lambda: shm.apply_lighting(X, l))
        t_ref = ms(lambda: shm.apply_lighting_reference(X, l))
        nb = X.numel() * X.element_size()
        res[f"light: {name}·l"] = {"ms": t_new, "MB": nb / 1e6, "GB/s": nb / t_new / 1e6, "einsum ms": t_ref,
                                   "stream-read ms": ms(lambda: X.sum()), "triad GB/s": B / 1e9}
    e3 = m._e.T.contiguous()
    res["light: corner table"] = {"ms": ms(lambda: e3.view(-1).index_select(0, m._corner_index(e3.device)).view(-1, 9)),
                                  "row gather ms": ms(lambda: m._e.contiguous().index_select(0, m.F.view(-1)).view(-1, 9))}
    S2, n = gb.spp_side ** 2, gb.height * gb.width
    face, bary, hit, normal, wo, reg = gb.face, gb.bary.float(), gb.hit, gb.normal.float(), gb.wo.float(), gb.region
    vecs = [shm._pixel_rows(x, n, S2) for x in (bary, normal, wo)]
    rows = (face.view(n, S2), hit.view(n, S2), *(c for v in vecs for c in v))
    fk = m._face_materials(kd)
    kernel = shm._pixels_kernel(tuple(len(v) for v in vecs))
    run_pix = lambda: map_rows(kernel, rows, (m._ef, fk), chunk=max(1, shm.PIXEL_CHUNK // S2))  # noqa: E731
    t_pix = ms(run_pix)
    P = gb.num_samples
    b_pix = P * (8 + 1 + 12 + 12 + 8) + n * 12 + (m._ef.numel() + fk.numel()) * 4
    res["view: pixels (diffuse)"] = {"ms": t_pix, "ns/sample": 1e6 * t_pix / P, "GB/s": b_pix / t_pix / 1e6,
                                     "triad GB/s": B / 1e9}
    res["view: pixels (diffuse)"]["native ms (+ glossy list)"] = ms(
        lambda: shm._native.pixels(face, hit, bary, normal, wo, m._ef, fk, S2))
    out = run_pix()
    res["view: glossy select"] = {"ms": ms(lambda: shm._flat_nonzero(out[1].view(-1))),
                                  "torch nonzero ms": ms(lambda: out[1].view(-1).nonzero())}
    g = shm._flat_nonzero(out[1].view(-1))
    args = (face, bary, normal, wo, reg, m._ef, m._fg, m._glossy_light(), kd, ks, G, vcos)
    t_g = ms(lambda: shm._glossy_blocks(g, args))
    f_g = int(g.numel()) * (18 + 3 + 1 + 6) * n2
    res["view: glossy samples"] = {"ms": t_g, "samples": float(g.numel()), "ns/sample": 1e6 * t_g / max(1, g.numel()),
                                   "GFLOP/s": f_g / t_g / 1e6, "sgemm GFLOP/s": Pk / 1e9}
    AS = shm._sh_factor_tables(m.order, G.device)
    if shm._native.glossy(g, *args, *AS) is not None:
        t_n = ms(lambda: shm._native.glossy(g, *args, *AS))
        res["view: glossy samples"].update({"native ms": t_n, "native ns/sample": 1e6 * t_n / max(1, g.numel())})
    res["frame V (render)"] = {"ms": ms(lambda: m.render(frame, gb))}
    return res


if __name__ == "__main__":
    main()
