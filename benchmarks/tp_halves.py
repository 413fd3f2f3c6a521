"""Intrinsic imbalance of the static 2-way splits of TripleProduct's per-vertex passes (session 39):
`native.points`, the E frames' comb loop (`native_light._comb_run`) and the VL frames' pair projection
(`native_light.project`), their arguments captured from real frames, each half of the work alone at 1
thread, process CPU, order alternating, medians; max/mean is what a static split at 2 threads loses to
a balanced one on a quiet host.

    python -m benchmarks.tp_halves E|VL|V     (creature bench, vertex shading, the base's precompute)
"""
import sys, time, statistics, torch
from benchmarks.common import apply_ab_options, precomputed, setup
class A: threads=1; precompute_code=__import__("os").environ.get("PRTBENCH_PRECOMPUTE_CODE", "/work/wt/base39")
apply_ab_options(A)
from methods.triple_product import TripleProduct, native, native_light as nl
from methods.core.fused import warming
from scenes.library import get_scene
scene = get_scene("creature", "bench")
m, _ = precomputed(TripleProduct, scene, {"shading": "vertex"})
kind = sys.argv[1]
_, frames, gbs, _ = setup(scene, kind=kind, n_frames=5, seed=0, spp_side=2)
capP, capC, capJ = [], [], []
oP, oC, oJ = native.points, nl._comb_run, nl.project
def recP(*a, **k): capP.append((a, k)); return oP(*a, **k)
def recC(fn, name, pairs, head, tables, out): capC.append((fn, pairs.clone(), head, tables, out)); return oC(fn, name, pairs, head, tables, out)
def recJ(pairs, *a): capJ.append((pairs.clone(), a)); return oJ(pairs, *a)
native.points, nl._comb_run, nl.project = recP, recC, recJ
with warming(): m.render(frames[0], gbs[0])
capP.clear(); capC.clear(); capJ.clear()
for f, g in zip(frames[1:], gbs[1:]): m.render(f, g)
native.points, nl._comb_run, nl.project = oP, oC, oJ
fs = {}
for ci, (a, k) in enumerate(capP[-3:]):
    V, R, L, vrow, vw, brows, bw, lrows, lw, ch = a
    b = vrow.shape[0]
    def part(lo, hi, a=a, k=k):
        V, R, L, vrow, vw, brows, bw, lrows, lw, ch = a
        a2 = (V, R, L, vrow[lo:hi], vw[lo:hi], brows[lo:hi], bw[lo:hi], lrows[lo:hi], lw[lo:hi], ch)
        return lambda: oP(*a2, **k)
    fs[f"points{ci} h0"], fs[f"points{ci} h1"] = part(0, b // 2), part(b // 2, b)
for ci, (fn, pairs, head, tables, out) in enumerate(capC[-3:]):
    n, S, n_psi, J, B = head
    f = pairs // n; t = pairs % n
    it = ((f // (J * n_psi)) * n_psi + f % n_psi) * n + t
    u, inv = torch.unique(it, return_inverse=True)
    ni = u.numel()
    st = torch.zeros(1, dtype=torch.int64)
    def run(sel, fn=fn, head=head, tables=tables, out=out):
        p = sel.contiguous()
        return lambda: fn(p.numel(), p.data_ptr(), *head, *tables, out.data_ptr(), 1, 0, st.data_ptr())
    fs[f"comb{ci} h0"], fs[f"comb{ci} h1"] = run(pairs[inv < ni // 2]), run(pairs[inv >= ni // 2])
for ci, (pairs, a) in enumerate(capJ[-3:]):
    P = pairs.numel()
    def runj(sel, a=a):
        return lambda: oJ(sel, *a)
    fs[f"project{ci} h0"], fs[f"project{ci} h1"] = runj(pairs[:P // 2]), runj(pairs[P // 2:])
ts = {x: [] for x in fs}
names = list(fs)
for r in range(60):
    for x in (names if r % 2 == 0 else names[::-1]):
        t0 = time.process_time(); fs[x](); ts[x].append(time.process_time() - t0)
med = {x: 1e3 * statistics.median(v) for x, v in ts.items()}
for x in names[::2]:
    y = x.replace("h0", "h1")
    h0, h1 = med[x], med[y]
    print(kind, x[:-3], "h0 %.3f h1 %.3f ms  max/mean %.3f" % (h0, h1, max(h0, h1) / ((h0 + h1) / 2)))
