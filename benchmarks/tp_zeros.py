"""How much of the triple product's counted work multiplies an exact 0 (issue 14's cost model).

    python -m benchmarks.tp_zeros [chess creature] [--size bench]

`fast_eval.frame_cost` drops a fine triangle where every reader multiplies it by an exact 0
(`fast_eval.live_triangles`) and, since session 25, counts each point's own non-zero triangles and
the (frame, triangle) pairs read (`fast_eval.nonzero_reads`). This prints how much that finer grain
drops, per scene (per-vertex shading, precomputation through the harness's cache):
  * per vertex: the share of the live triangles where its visibility is non-zero (the per-vertex
    triple product over the others adds exact zeros);
  * per vertex: the share of the live triangles the native loop sums (`triple_product.native`: the
    8-column chunks covering the row's non-zeros, `fast_eval.vis_chunks`) and the share of the
    row's zeros it skips (when the native loop is available);
  * per grid frame (of the frames some vertex looks up, all four look-up corners): the share of
    the (frame, live triangle) pairs where some vertex reading that frame has non-zero visibility
    (the others' projected lighting is only ever multiplied by 0) — session 24's helper measured
    it on its own superset as 72–73 %.
"""
from __future__ import annotations

import argparse

import torch


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scenes", nargs="*", default=["chess", "creature"])
    ap.add_argument("--size", default="bench")
    a = ap.parse_args(argv)
    from benchmarks.common import precomputed, setup
    from methods.triple_product import fast_eval as fe
    from methods.triple_product.method import TripleProduct

    out = {}
    for name in a.scenes:
        scene, frames, gbs, _ = setup(name, a.size, kind="L", n_frames=2)
        m, _ = precomputed(TripleProduct, scene, {"shading": "vertex"})
        m.render(frames[0], gbs[0])
        live = fe.live_triangles(m)
        n_v = int(m.V.shape[0])
        rows = fe.grid_lookups(m.R, m.R[:, 2].contiguous(), m.outgoing, m.grid, m.config["light_lookup"])[2]
        vis = fe.live_table(m, "V", m.V_val, live)[:n_v] != 0                       # (N, live)
        need = torch.zeros(m.grid.size, live.numel(), dtype=torch.int32)
        for k in range(rows.shape[1]):
            need.index_add_(0, rows[:, k], vis.to(torch.int32))
        looked = torch.zeros(m.grid.size, dtype=torch.bool)
        looked[rows.reshape(-1)] = True
        out[name] = {"live": int(live.numel()), "K": int(m.K), "looked_up_frames": int(looked.sum()),
                     "frames": int(m.grid.size), "pairs_read": float((need[looked] > 0).float().mean()),
                     "vertex_nonzero": float(vis.float().mean())}
        r = out[name]
        ch = fe.vis_chunks(m, fe.live_table(m, "V", m.V_val, live))
        if ch is not None:
            ptr, _, tail = ch
            n = live.numel()
            summed = float((8 * (ptr[1:n_v + 1] - ptr[:n_v]) + (n - tail[:n_v].long())).double().sum()) / (n_v * n)
            r["vertex_summed"] = summed
            r["zeros_skipped"] = (1 - summed) / max(1 - r["vertex_nonzero"], 1e-30)
        print(f"{name}: {r['live']} of {r['K']} triangles live; {r['looked_up_frames']} of {r['frames']} grid "
              f"frames looked up; pairs read {100 * r['pairs_read']:.1f} %; per-vertex non-zero visibility "
              f"{100 * r['vertex_nonzero']:.1f} % of the live triangles"
              + (f"; the native loop sums {100 * r['vertex_summed']:.1f} % of them ({100 * r['zeros_skipped']:.1f} % "
                 f"of the zeros skipped)" if "vertex_summed" in r else ""))
    return out


if __name__ == "__main__":
    main()
