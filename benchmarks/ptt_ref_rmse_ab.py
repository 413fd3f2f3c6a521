"""RMSE against Mitsuba of a base checkout's PTT frame and this checkout's (session 39, pt39: does a
run-time change that moves the image by round-off leave the error unchanged?).

    python -m benchmarks.ptt_ref_rmse_ab --base OTHER_CHECKOUT [--scene chess] [--size bench]
                                         [--config '{"light_res_1":4}'] [--kind V] [--frame 1]
                                         [--spp 64] [--precompute-code CHECKOUT]

One precomputation (looked up under ``--precompute-code``'s code fingerprint, default ``--base``,
the perf suite's ``with_bounces(0)``) rendered by both versions (`benchmarks.ptt_ab.as_class`), a
fresh Mitsuba reference of the same frame (``reports.backend.render_reference``, bounces as the
suite maps 0, not cached), and prints each image's RMSE against it and max |base − new|."""
from __future__ import annotations

import argparse
import json

import torch

from benchmarks.common import checkout_modules, precomputed, setup
from benchmarks.ptt_ab import as_class, base_basis, base_class, base_fingerprint
from methods.ptt.method import PTT


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--base", required=True)
    ap.add_argument("--scene", default="chess")
    ap.add_argument("--size", default="bench")
    ap.add_argument("--config", default='{"light_res_1":4}')
    ap.add_argument("--kind", default="V")
    ap.add_argument("--frame", type=int, default=1)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--precompute-code", default=None)
    a = ap.parse_args(argv)
    from reports import precompute_cache
    from reports.backend import render_reference

    fp = base_fingerprint(a.precompute_code or a.base)
    precompute_cache._process_fingerprint = lambda module: fp
    scene, _, _, _ = setup(a.scene, a.size, kind="V", n_frames=1)
    m, _ = precomputed(PTT, scene, json.loads(a.config))
    m = m.with_bounces(0)
    old = as_class(m, base_class(a.base), base_basis(m, a.base))
    new = as_class(m, PTT)
    _, frames, gbs, _ = setup(scene, a.size, kind=a.kind, n_frames=a.frame + 1, seed=1)
    imgs = {}
    for i, (f, g) in enumerate(zip(frames, gbs)):  # the earlier frames as the harness renders them
        with checkout_modules(a.base):
            imgs["old"] = old.render(f, g)
        imgs["new"] = new.render(f, g)
    ref = render_reference(scene, frames[a.frame], bounces=0, spp=a.spp, seed=0, use_cache=False)
    R = torch.as_tensor(ref.image if hasattr(ref, "image") else ref).float()
    out = {k: float(((im.reshape(R.shape) - R) ** 2).mean().sqrt()) for k, im in imgs.items()}
    out["max_diff"] = float((imgs["old"] - imgs["new"]).abs().max())
    print(f"{a.scene} {a.size} {a.kind} frame {a.frame}, Mitsuba {a.spp} spp: RMSE old {out['old']:.10g}  "
          f"new {out['new']:.10g}  max |old - new| {out['max_diff']:.3g} (reference peak {float(R.abs().max()):.3g})")
    return out


if __name__ == "__main__":
    main()
