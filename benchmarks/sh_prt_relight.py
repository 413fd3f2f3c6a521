"""SH PRT's relight pass (`native.relight_add`, session 39: split over the threads at pixel boundaries)
alone on a creature bench E frame's relight cache: 1 thread against 2, alternating, wall and process CPU
medians of 300 reps.

    python -m benchmarks.sh_prt_relight
"""
import sys, time, statistics, torch
from reports import precompute_cache
from reports.store import code_closure_fingerprint
precompute_cache._process_fingerprint = lambda mod: code_closure_fingerprint(mod, "/work/wt/base39")
from reports import backend as be
from methods.sh_prt.method import SHPRT
from methods.sh_prt import native
from benchmarks.common import precomputed
scene = be.get_scene("creature", "bench")
m, _ = precomputed(SHPRT, scene, {}); m = m.with_bounces(0)
frames = be.make_sequence(scene, "E", 3, 0)
for f in frames: img = m.render(f, be.make_gbuffer(scene, f, 2))
c = m._relight[1]; l = m._light
print("Q", c["Qg"], "MB", c["blk"].numel()*4/1e6)
img0 = torch.rand(256*256, 3)
res = {}
for r in range(300):
    for nt in (1, 2):
        torch.set_num_threads(nt)
        x = img0.clone()
        t, cc = time.perf_counter(), time.process_time()
        native.relight_add(x, c["blk"], l, c["p"], 4)
        res.setdefault(nt, []).append((time.perf_counter() - t, time.process_time() - cc))
for nt, v in res.items():
    print(nt, "wall ms %.3f cpu ms %.3f" % (1e3*statistics.median(a for a, _ in v), 1e3*statistics.median(b for _, b in v)))
