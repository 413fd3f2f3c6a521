"""SH PRT's frame split into its stages (session 41, issue 14): where a creature bench frame's process CPU goes
at 1 thread with cold caches, and how much of it is serial at 2+ threads.

    python -m benchmarks.sh_prt_stages [--kinds V VL L E] [--frames 15] [--threads 1] [--precompute-code DIR]

Runs THIS checkout's `SHPRT` (run it from another checkout, with PYTHONPATH there, for that code's split;
it needs no session-41 name: the wrappers it finds are timed); per kind a fresh sequence, each frame after
`benchmarks.common.settle` (the caches cool as in the perf suite), frames 0-1 untimed; per stage the median
process CPU ms of the Python wrappers (`native.view`, ``view_rows``, ``rows_vertex_major``, ``pixels``,
``relight_add``, ``relight_build``, ``Light``, the method's ``_light_stage``, ``_materials``, ...) and of
the C entry points they call (``C:sh_*``). ``serial`` = the frame minus the C entry points that split over
the threads (`PARALLEL`): the part a 2-thread frame runs on one core (an upper bound of what the second
thread cannot share; the parallel C entries' own serial tails, e.g. `sh_view_rows`' merge, are not in it).
"""
from __future__ import annotations

import argparse
import copy
import functools
import statistics
import time

PARALLEL = ("sh_view", "sh_pixels", "sh_light", "sh_view_rows", "sh_view_rows_z", "sh_vm_rows", "sh_vm_rows_l",
            "sh_relight_add", "sh_relight_build", "sh_glossy", "sh_lg_rows")


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kinds", nargs="+", default=["V", "VL", "L", "E"])
    ap.add_argument("--frames", type=int, default=15)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--precompute-code", default=None)
    a = ap.parse_args(argv)
    import torch

    torch.set_num_threads(a.threads)
    if a.precompute_code:
        from reports import precompute_cache
        from reports.store import code_closure_fingerprint

        precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, a.precompute_code)
    from benchmarks.common import precomputed, settle, setup
    from methods.sh_prt import method as shm, native as nat
    from methods.sh_prt.method import SHPRT

    T: dict[str, float] = {}

    def timed(f, label):
        @functools.wraps(f)
        def g(*args, **kw):
            c = time.process_time()
            try:
                return f(*args, **kw)
            finally:
                T[label] = T.get(label, 0.0) + time.process_time() - c
        return g

    for name in ("view", "view_rows", "rows_vertex_major", "pixels", "relight_add", "relight_build", "rotate",
                 "glossy", "rows"):
        if hasattr(nat, name):
            setattr(nat, name, timed(getattr(nat, name), name))
    if hasattr(nat, "Light"):
        nat.Light.__call__ = timed(nat.Light.__call__, "Light")
    shm.sh_native.project_latlong_polar = timed(shm.sh_native.project_latlong_polar, "project")
    shm.apply_lighting = timed(shm.apply_lighting, "apply_lighting")
    for name in ("_light_stage", "_materials", "_partial_table", "_relight_build", "_render_fast", "render"):
        setattr(SHPRT, name, timed(getattr(SHPRT, name), name))
    lib = nat._lib()
    if lib is not None:
        for fn in PARALLEL + ("sh_add_pixels", "sh_need_rows", "sh_rotate"):
            try:
                f0 = getattr(lib, fn)
            except AttributeError:
                continue
            setattr(lib, fn, timed(f0, "C:" + fn))
    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(SHPRT, scene, {})
    m = m.with_bounces(0)
    out = {}
    for kind in a.kinds:
        _, frames, gbs, _ = setup(scene, "bench", kind=kind, n_frames=a.frames, seed=1)
        mm = copy.copy(m)
        mm._reset_cache()
        rec = []
        for i, (f, g) in enumerate(zip(frames, gbs)):
            settle()
            T.clear()
            c = time.process_time()
            mm.render(f, g)
            tot = time.process_time() - c
            if i >= 2:
                par = sum(v for k, v in T.items() if k.startswith("C:") and k[2:] in PARALLEL)
                rec.append(dict(T, frame=tot, serial=tot - par))
        keys = sorted({k for r in rec for k in r}, key=lambda k: (k in ("frame", "serial"), k))
        out[kind] = {k: 1e3 * statistics.median(r.get(k, 0.0) for r in rec) for k in keys}
        print(f"{kind}: " + "  ".join(f"{k} {v:.3f}" for k, v in out[kind].items()), flush=True)
    return out


if __name__ == "__main__":
    main()
