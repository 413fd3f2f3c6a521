"""This method's rendered-error row of the terms-vs-exponent study (Mahajan 2008 Fig. 3B/C, Fig. 6).

``error_vs_terms(s, K)``: relative RMSE (RMSE / mean reference radiance, on covered pixels) of the
in-out renderer with K terms on ``sphere_plane`` (test size) whose sphere is a Phong lobe of
exponent s, against Mitsuba's direct-lighting reference (256 spp, cached). Fig. 6's claim is that
K = 2.5 s (hemisphere rule) matches the reference while K = 4 or 12 visibly blur.
"""
from __future__ import annotations

import dataclasses
from functools import lru_cache

from methods.inout.analysis import terms_needed
from methods.studies import register_error_vs_terms, register_terms_contributor

REF_SPP = 256  # reference samples per pixel (noise floor ≈ 5 % of the RMSE scale at this size)


@lru_cache(maxsize=16)
def _setup(s: float):
    from references.gbuffer import make_gbuffer
    from references.render import render_reference
    from scenes.library import get_scene
    from scenes.materials import Phong
    from scenes.sequences import make_sequence

    scene = get_scene("sphere_plane", "test")
    old = scene.materials["sphere"]
    mats = dict(scene.materials)
    mats["sphere"] = Phong(kd=old.kd, ks=old.ks, s=float(s))
    scene = dataclasses.replace(scene, materials=mats)
    frame = dataclasses.replace(make_sequence(scene, "V", n_frames=1, seed=0)[0], materials=mats)
    gb = make_gbuffer(scene, frame, 2)
    ref = render_reference(scene, frame, bounces=0, spp=REF_SPP, seed=0)
    return scene, frame, gb, ref, gb.coverage & ref.coverage


def error_vs_terms(exponent: float, terms: int) -> float:
    """Relative RMSE of the K-term in-out image of a Phong-s sphere (module docstring)."""
    from methods.inout.method import InOut
    from references.metrics import rmse

    scene, frame, gb, ref, mask = _setup(float(exponent))
    m = InOut(terms=int(terms), progress=False)
    m.precompute(scene)
    return rmse(m.render(frame, gb), ref.image, mask) / ref.image[mask].mean().item()


# -- registration (methods.studies) ----------------------------------------------------------------
register_terms_contributor("inout", terms_needed, target=0.99,
                           target_kind="energy fraction (Mahajan 2008, hemisphere, 40x40)")
register_error_vs_terms("inout", error_vs_terms)
