"""SH PRT frames split into process CPU per stage and their serial part (session 42): like
`benchmarks.sh_prt_stages` (whose frames 0-1 are untimed), plus the first lighting-only frame (kinds "Lb", "Eb":
the relight cache build; per repeat the cache reset, frame 0 rendered, `settle`, frame 1 timed).

    python -m benchmarks.sh_prt42_serial [Lb] [Eb] [V] [VL] [L] [E]

The checkout on PYTHONPATH is the one measured (run it with another checkout's PYTHONPATH for that code's split;
the precomputation of the checkout PRTBENCH_SH42_PRECOMPUTE_CODE names is taken when it is set, else this one's). ``serial``
= the frame minus the C entry points (each splits over the threads): what a 2-thread frame runs on one core.
"""
import copy, time, statistics, sys, functools
import torch
torch.set_num_threads(1)
from reports import precompute_cache
from reports.store import code_closure_fingerprint
_PRE = __import__("os").environ.get("PRTBENCH_SH42_PRECOMPUTE_CODE")   # another checkout's precomputation (unset: this one's)
if _PRE:
    precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, _PRE)
import torch._dynamo
from benchmarks.common import precomputed, settle, setup
from methods.sh_prt import method as shm, native as nat
from methods.sh_prt.method import SHPRT
T = {}
def timed(f, label):
    @functools.wraps(f)
    def g(*a, **k):
        c = time.process_time()
        try: return f(*a, **k)
        finally: T[label] = T.get(label, 0) + time.process_time() - c
    return g
lib = nat._lib()
C = ("sh_relight_build", "sh_pixels", "sh_relight_add", "sh_light", "sh_view", "sh_view_rows_z", "sh_vm_rows_l")
for fn in C:
    setattr(lib, fn, timed(getattr(lib, fn), "C:" + fn))
for fn in ("pixels", "relight_build", "relight_add", "view", "view_rows", "rows_vertex_major"):
    setattr(nat, fn, timed(getattr(nat, fn), "py:" + fn))
nat.Light.__call__ = timed(nat.Light.__call__, "py:Light")
for name in ("_light_stage", "_light_native", "_materials", "_face_materials", "_relight_build", "_render_fast", "render", "_vertex_major_M", "_view_rows", "_partial_table"):
    setattr(SHPRT, name, timed(getattr(SHPRT, name), name))
shm._relight_add = timed(shm._relight_add, "_relight_add")
scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
m, _ = precomputed(SHPRT, scene, {})
m = m.with_bounces(0)
kinds = sys.argv[1:] or ["Lb"]
for kind in kinds:
    rec = []
    if kind in ("Lb", "Eb"):
        _, frames, gbs, _ = setup(scene, "bench", kind=kind[0], n_frames=2, seed=0)
        for r in range(9):
            mm = copy.copy(m); mm._reset_cache()
            mm.render(frames[0], gbs[0]); settle(); T.clear()
            c = time.process_time(); mm.render(frames[1], gbs[1]); tot = time.process_time() - c
            if r: rec.append(dict(T, frame=tot))
    else:
        _, frames, gbs, _ = setup(scene, "bench", kind=kind, n_frames=12, seed=1)
        mm = copy.copy(m); mm._reset_cache()
        for i, (f, g) in enumerate(zip(frames, gbs)):
            settle(); T.clear()
            c = time.process_time(); mm.render(f, g); tot = time.process_time() - c
            if i >= 2: rec.append(dict(T, frame=tot))
    for r in rec: r["serial"] = r["frame"] - sum(v for k, v in r.items() if k.startswith("C:"))
    keys = sorted(rec[0])
    print(kind, "  ".join(f"{k} {1e3*statistics.median(x.get(k,0) for x in rec):.3f}" for k in keys), flush=True)
