"""Kernel A/B of `native.pose_sh`'s 12-sum vector pose row (session 42, zh42p: the paper config's d = lobes (2 + n)
= 12) against the generic loop (`native._pose_sh_lib(row12=False)`: the same source built with
``-DZH42P_NO_ROW12``), same process, the bound call (`native.PoseSHBound`) of a P frame's referenced rows.

    python -m benchmarks.zh42p_pose_row_ab [--precompute-code DIR] [--threads 1] [--repeat 150] [--flush 64]

Renders four P frames (bench creature, config ``{}``), keeps the last call that made rows of a pending
visibility (`ZHShadow._fill_visibility` with ``rows``: the plane's and the object samples' referenced vertices),
checks both libraries' rows bit for bit, then times, alternating, process CPU per call (the collector off;
``--flush`` MB written and read before each call): the loop ("old"), the vector row ("new"), the loop again
("old2": the A/A). Prints the medians and ratios.
"""
from __future__ import annotations

import argparse
import gc
import statistics
import time


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--precompute-code", default=None)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--repeat", type=int, default=150)
    ap.add_argument("--flush", type=int, default=64)
    a = ap.parse_args(argv)
    import torch

    from benchmarks.common import apply_ab_options, precomputed, setup

    apply_ab_options(a)
    from methods.zh_shadow import native as zn
    from methods.zh_shadow.method import ZHShadow

    scene, _, _, _ = setup("creature", "bench", kind="V", n_frames=1)
    m, _ = precomputed(ZHShadow, scene, {})
    _, frames, gbs, _ = setup(scene, "bench", kind="P", n_frames=4, seed=0)
    mm = m.with_render_config()
    cap: list = []
    orig = ZHShadow._fill_visibility

    def spy(self, v0, rows=None):
        if rows is not None and self._v_pending is not None:
            cap.append((self._v_pending[1].clone(), self._v_pending[2], rows.clone()))
        return orig(self, v0, rows)

    ZHShadow._fill_visibility = spy
    try:
        for f, g in zip(frames, gbs):
            mm.render(f, g)
    finally:
        ZHShadow._fill_visibility = orig
    if not cap or mm._pose_bound is None:
        raise SystemExit("no rows of a pending visibility were made")
    pb = mm._pose_bound
    old, new = zn._pose_sh_lib(row12=False).zh41p_pose_sh, zn._pose_sh_lib().zh41p_pose_sh
    pose, geom, rows = cap[-1]
    N, n2 = pb.N, pb.n * pb.n
    outs = {}
    for k, fn in (("old", old), ("new", new)):
        pb.fn = fn
        o = torch.zeros(N, n2)
        pb(pose, geom.N, rows, out=o)
        outs[k] = o
    out = {"d": pb.d, "rows": int(rows.shape[0]),
           "bit-equal": torch.equal(outs["old"].view(torch.int32), outs["new"].view(torch.int32))}
    print(out)
    junk = torch.empty(a.flush << 18) if a.flush else None
    ts: dict = {"old": [], "new": [], "old2": []}
    o = torch.empty(N, n2)
    gc.disable()
    try:
        for i in range(a.repeat):
            for k in (["old", "new", "old2"] if i % 2 else ["old2", "new", "old"]):
                if junk is not None:
                    junk.fill_(1.0)
                    float(junk[::4096].sum())
                pb.fn = new if k == "new" else old
                c = time.process_time()
                pb(pose, geom.N, rows, out=o)
                ts[k].append(time.process_time() - c)
    finally:
        gc.enable()
        pb.fn = new
    md = {k: statistics.median(v) for k, v in ts.items()}
    for k, v in md.items():
        print(f"{k:5s} median {v * 1e3:.3f} ms")
    out["ratio"], out["A/A"] = md["old"] / md["new"], md["old"] / md["old2"]
    print(f"ratio old / new {out['ratio']:.3f}   A/A old / old2 {out['A/A']:.3f}")
    return out


if __name__ == "__main__":
    main()
