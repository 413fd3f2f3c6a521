"""The per-vertex eq. 7 loop (`methods.triple_product.native.points`) alone under its table layouts
(session 35), on the arguments of one real frame: the ρ̃ / lighting fine-value tables row-major (the
loop of session 34) or chunk-major (`native.chunk_major`), the visibility rows or their chunks packed
(`native.packed_chunks`). The arguments are captured from a frame of ``--kind`` (after the harness-like
warm-up frame), then per repetition each variant runs once after a 64 MB write (caches cooled, as after
the harness's G-buffer pass); process CPU (``--threads 1``), medians, ratios against the row-major loop,
every variant's output compared bit for bit with it.

    python -m benchmarks.tp_points_layouts [--scene creature] [--kind V] [--threads 1] [--reps 30]

Session 35, 1 thread, loaded host (each the same bits as row-major): creature bench V ρ̃ chunk-major
1.10x, both tables 1.12x, both and the packed visibility chunks 1.36x (creature L 1.05 / 1.09 / 1.25x,
chess V 1.05 / 1.09 / 1.23x; L frames read their lighting row-major: its lighting is pending).
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import torch


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="creature")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--kind", default="V")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--reps", type=int, default=30)
    a = ap.parse_args(argv)
    torch.set_num_threads(a.threads)

    from benchmarks.common import precomputed, setup
    from methods.core.fused import warming
    from methods.triple_product import TripleProduct, native

    if not native.available():
        raise SystemExit("the native loops are not available")
    scene, frames, gbs, _ = setup(a.scene, a.size, kind=a.kind, n_frames=2, seed=0)
    m, _ = precomputed(TripleProduct, scene, {"shading": "vertex"})
    cap: dict = {}
    p0 = native.points

    def spy(*args, **kw):
        cap["args"], cap["kw"] = args, kw
        return p0(*args, **kw)

    with warming():
        m.render(frames[0], gbs[0])
    native.points = spy
    try:
        m.render(frames[1], gbs[1])
    finally:
        native.points = p0
    if "args" not in cap:
        raise SystemExit("the frame did not run native.points")
    V, R, L, vrow, vw, brows, bw, lrows, lw, ch = cap["args"]
    if V is None:   # the visibility kept packed only (`fast_eval.VIS_PACKED_ONLY`): its rows unpacked
        V = native.unpack_chunks(cap["kw"]["v_packed"], ch, cap["kw"]["v_shape"])
    # the frame may have passed chunk-major copies: their row-major tables are the keys of their caches
    cache = m._perf_cache
    Rr = cache[("major", "rho")][0] if cap["kw"].get("r_major") else R
    Lr = cache[("major", "L")][0] if cap["kw"].get("l_major") else L
    n = V.shape[1]
    if n % native.W:
        raise SystemExit(f"row length {n}: the chunk-major layouts need a multiple of {native.W}")
    rows = dict(vrow=vrow, vw=vw, brows=brows, bw=bw, lrows=lrows, lw=lw)
    Rm, Lm, Vp = native.chunk_major(Rr), native.chunk_major(Lr), native.packed_chunks(V, ch)
    variants = {"row-major": (Rr, Lr, {}), "rho chunk-major": (Rm, Lr, {"r_major": True}),
                "both chunk-major": (Rm, Lm, {"r_major": True, "l_major": True}),
                "both + packed V": (Rm, Lm, {"r_major": True, "l_major": True, "v_packed": Vp})}
    junk = torch.empty(16 << 20)
    ts: dict = {k: [] for k in variants}
    outs: dict = {}
    for _ in range(a.reps):
        for k, (Rt, Lt, kw) in variants.items():
            junk.add_(1.0)
            t = time.process_time()
            outs[k] = native.points(V, Rt, Lt, *rows.values(), ch, **kw)
            ts[k].append(time.process_time() - t)
    base = statistics.median(ts["row-major"])
    res = {k: {"ms": 1e3 * statistics.median(v), "ratio": base / statistics.median(v),
               "same_bits": bool(torch.equal(outs[k], outs["row-major"]))} for k, v in ts.items()}
    print(json.dumps({"scene": a.scene, "kind": a.kind, "points": int(vrow.numel()), "n": int(n), **res}, indent=1))
    return res



if __name__ == "__main__":
    main()
