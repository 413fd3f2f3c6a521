"""Same-process A/B of ZHShadow's shading-table stage (`ZHShadow._table`) under the perf suite's protocol:
each frame right after `make_gbuffer`, frame 0 of each pass untimed inside `warming`, `runtime.TABLE_BANDS`
(the operator of a new exponent from its band parts) on and off alternating pass by pass, each with its
own method object.

    python -m benchmarks.zh_table_ab [--kinds VB VBL VL] [--repeat 6] [--threads 1] [--precompute-code DIR]

A material frame of the suite meets each exponent once; repeating a sequence would find its exponents'
operators cached (``lru_cache``) and its tables kept, so before each timed frame of a kind with "B" the
operator caches and the method's specular tables are cleared (the diffuse table and the lighting stay, as
in the suite). Prints the median ms of the table stage and of the whole frame (process CPU) per setting.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default="{}")
    ap.add_argument("--kinds", nargs="+", default=["VB", "VBL", "VL"])
    ap.add_argument("--frames", type=int, default=5)
    ap.add_argument("--repeat", type=int, default=6)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--precompute-code", default=None,
                    help="take the precomputation from the cache entry of the code in DIR (a run-time-only change)")
    a = ap.parse_args(argv)
    from benchmarks.common import apply_ab_options, precomputed, setup

    apply_ab_options(a)
    from methods.core.fused import warming
    from methods.zh_shadow import runtime as rt
    from methods.zh_shadow.method import ZHShadow
    from references.gbuffer import make_gbuffer

    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1)
    m0, _ = precomputed(ZHShadow, scene, json.loads(a.config))
    acc = [0.0]
    table = ZHShadow._table

    def timed_table(self, *args, **kw):
        t = time.perf_counter()
        try:
            return table(self, *args, **kw)
        finally:
            acc[0] += time.perf_counter() - t

    out: dict = {}
    flag0 = rt.TABLE_BANDS
    ZHShadow._table = timed_table
    try:
        for kind in a.kinds:
            _, frames, _, _ = setup(scene, a.size, kind=kind, n_frames=a.frames, seed=a.seed)
            res: dict = {True: ([], []), False: ([], [])}
            ms = {True: m0.with_render_config(), False: m0.with_render_config()}
            for r in range(a.repeat):
                for flag in ((True, False) if r % 2 == 0 else (False, True)):
                    rt.TABLE_BANDS = flag
                    m = ms[flag]
                    for i, f in enumerate(frames):
                        gb = make_gbuffer(scene, f, 2)
                        acc[0] = 0.0
                        if "B" in kind and i > 0:   # (the suite meets each material frame's exponent once)
                            rt._table_operator.cache_clear()
                            rt._table_operator_b.cache_clear()
                            if m._tables is not None:
                                for k in [k for k in m._tables[1] if k[0] == "s"]:
                                    del m._tables[1][k]
                        with warming(i == 0):
                            c = time.process_time()
                            m.render(f, gb)
                            dc = time.process_time() - c
                        if i > 0:
                            res[flag][0].append(acc[0])
                            res[flag][1].append(dc)
            out[kind] = r_ = {("bands" if fl else "direct"): {"table_ms": 1e3 * statistics.median(res[fl][0]),
                                                               "frame_cpu_ms": 1e3 * statistics.median(res[fl][1])}
                              for fl in (False, True)}
            print(f"{kind}: table {r_['direct']['table_ms']:.3f} -> {r_['bands']['table_ms']:.3f} ms "
                  f"({r_['direct']['table_ms'] / max(r_['bands']['table_ms'], 1e-9):.2f}x), frame cpu "
                  f"{r_['direct']['frame_cpu_ms']:.2f} -> {r_['bands']['frame_cpu_ms']:.2f} ms", flush=True)
    finally:
        ZHShadow._table = table
        rt.TABLE_BANDS = flag0
    return out


if __name__ == "__main__":
    main()
