"""Where the terms-vs-exponent study's error lies in the image (session 47): one study frame (`reports.studies.
_phong_frame`, the study's 16384-spp reference), each named method at the top rung of its term ladder, and the
oracle, their relative RMSE over the glossy region's own pixels, the other region's, the silhouette pixels that mix
both, and the whole image, with each part's share of the image's squared error.

    python -m benchmarks.yardstick_split sphere_plane:sphere 1 inout sh_prt [--oracle-samples 256]
    python -m benchmarks.yardstick_split sphere_plane:sphere 1 'zh_shadow={"order":8}' --oracle-samples 0

A method is a term ladder's name (rendered at its top rung) or ``name={json}`` (that configuration, made by the
ladder's factory for the varied region).

Each part's RMSE is relative to the reference's mean over that part (as the study's). Session 47, sphere_plane s = 1:
in-out (K = 256) sphere 2.3 %, plane 8.4 %, 95 % of the squared error on the plane; SH PRT (order 10) 2.4 % / 7.5 %,
94 %; the oracle at 256 + 256 samples 3.7 % / 2.5 % (its own noise). So the
image-wide error the study searched before was the plane's per-vertex shadows, which no rung of a ladder changes
(the ladders vary the glossy region only): the study now searches the region's error (`reports.studies.MEASURES`).
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from methods.registry import get_method
from methods.studies import TERM_LADDERS
from references.metrics import rmse
from reports.studies import YARDSTICK, _phong_frame, region_pixels, restrict


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene_region", help="scene:region of the study, e.g. sphere_plane:sphere")
    ap.add_argument("exponent", type=float)
    ap.add_argument("methods", nargs="*", help="term ladders (each rendered at its top rung) or name={json config}")
    ap.add_argument("--oracle-samples", type=int, default=256, help="light and BRDF samples of the oracle (0: none)")
    a = ap.parse_args(argv)
    scene_name, region = a.scene_region.split(":")
    fr = _phong_frame(scene_name, region, a.exponent, restrict(YARDSTICK, measure="region"))
    g, covered = fr.gbuffer, np.asarray(fr.image_mask)
    own = ((g.region == list(fr.scene.regions).index(region)) & g.hit).view(g.height, g.width, g.spp_side ** 2)
    parts = {"region": np.asarray(region_pixels(g, fr.scene, region, fr.image_mask)),
             "other": np.asarray(~own.any(-1)) & covered,
             "edge": np.asarray(own.any(-1) & ~own.all(-1)) & covered, "image": covered}
    print(f"{scene_name} s = {a.exponent:g}: pixels " + ", ".join(f"{k} {int(m.sum())}" for k, m in parts.items()))
    ref = np.asarray(fr.reference.image)

    def show(label, img):
        img = np.asarray(img)
        se = ((img - ref) ** 2).mean(-1)
        tot = se[covered].sum()
        cells = [f"{k} {rmse(img, ref, m) / float(ref[m].mean()):.4f} ({se[m].sum() / tot:.0%})"
                 for k, m in parts.items() if m.any()]
        print(f"  {label}: relative RMSE (share of squared error) " + ", ".join(cells), flush=True)

    for spec in a.methods:
        name, _, given = spec.partition("=")
        lad = TERM_LADDERS[name]
        cfg = json.loads(given) if given else dict(lad.ladder[-1])
        m = lad.make(dict(cfg), region)
        m.precompute(fr.scene)
        show(f"{name} {cfg}", m.render(fr.frame, fr.gbuffer))
    if a.oracle_samples:
        o = get_method("oracle")(light_samples=a.oracle_samples, brdf_samples=a.oracle_samples)
        o.precompute(fr.scene)
        show(f"oracle {a.oracle_samples} + {a.oracle_samples}", o.render(fr.frame, fr.gbuffer))


if __name__ == "__main__":
    main()
