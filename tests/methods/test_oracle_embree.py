"""The oracle's own tracer (``methods.oracle.embree_rays``, session 34) gives Mitsuba's tracer's answers: the
same blocked flag for every shadow ray of posed frames (a refitted BVH pose after pose) and of the rest
pose, and the same images and counts as the oracle on Mitsuba's tracer (`OWN_TRACER` off: `_repose`)."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from methods.registry import get_method
from references.gbuffer import make_gbuffer
from references.visibility import MitsubaVisibility, resolve_backend
from scenes.library import get_scene
from scenes.sequences import make_sequence


def _require(monkeypatch):
    import methods.oracle.embree_rays as E
    import methods.oracle.native_rays as on

    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    if resolve_backend() != "mitsuba":
        pytest.skip("the tracer is embreex: the own tracer stands in for Mitsuba's only")
    if not on.available() or E._lib() is None or E._api() is None:
        pytest.skip("no C compiler or no Embree library: Mitsuba's tracer runs")


def _posed_frames(n=4):
    """Posed creature frames, then the rest pose again."""
    scene = get_scene("creature", "test")
    frames = make_sequence(scene, "P", n_frames=n, seed=0)
    assert len({repr(f.pose) for f in frames}) == len(frames)
    return scene, frames + [dataclasses.replace(frames[0], pose=None, index=9)]


def test_own_tracer_blocked_equals_mitsuba(monkeypatch):
    """Every shadow ray of posed frames and the rest pose (the same tracer reposed frame after frame: its
    BVH refitted): blocked by the own tracer exactly where Mitsuba's tracer of that pose (a new one) says
    so."""
    import methods.oracle as O
    import methods.oracle.native_rays as on

    _require(monkeypatch)
    scene, frames = _posed_frames()
    o = get_method("oracle")(light_samples=2, brdf_samples=2, seed=5)
    o.precompute(scene)
    seen = []
    real = O.EmbreeTracer.trace

    def keep(self, live, org, dirs, blocked, threads):
        m = real(self, live, org, dirs, blocked, threads)
        seen.append((self, live.clone(), org.clone(), dirs.clone(), blocked.clone(), m))
        return m

    monkeypatch.setattr(O.EmbreeTracer, "trace", keep)
    for f in frames:
        o.render(f, make_gbuffer(scene, f, 1))
    assert len(seen) == len(frames) and all(s[0] is seen[0][0] for s in seen)
    for f, (_, live, org, dirs, blocked, m) in zip(frames, seen):
        geom = scene.geometry(f.pose)
        want = torch.empty_like(blocked)
        assert on.trace(MitsubaVisibility(geom.V, geom.F), live, org, dirs, want) == m == int(live.sum())
        assert torch.equal(blocked, want), (f.index, int((blocked != want).sum()))
        assert bool((live & blocked).any()) and bool((live & ~blocked).any())
        assert not bool((blocked & ~live).any())


def test_posed_frames_equal_mitsuba_tracer_path(monkeypatch):
    """Posed frames (and the rest pose after them) on the own tracer: bit for bit the images and counts
    of the oracle on Mitsuba's tracer (`OWN_TRACER` off), frame after frame; no Mitsuba scene is built;
    when the own tracer cannot be built, Mitsuba's runs (the same images). And a rigid scene's frames
    (chess, VBL)."""
    import methods.oracle as O
    import methods.oracle.embree_rays as E

    _require(monkeypatch)
    scene, frames = _posed_frames()
    cfg = dict(light_samples=2, brdf_samples=3, seed=2)
    a, b = get_method("oracle")(**cfg), get_method("oracle")(**cfg)
    a.precompute(scene)
    b.precompute(scene)
    for f in frames:
        gb = make_gbuffer(scene, f, 1)
        img = a.render(f, gb)
        assert isinstance(a._own[1], E.EmbreeTracer) and a._vis is None
        monkeypatch.setattr(O, "OWN_TRACER", False)
        want = b.render(f, gb)
        monkeypatch.setattr(O, "OWN_TRACER", True)
        assert b._own is None
        assert torch.equal(img, want), f.index
        assert a._last == b._last, f.index
    chess = get_scene("chess", "test")
    a2, b2 = get_method("oracle")(**cfg), get_method("oracle")(**cfg)
    a2.precompute(chess)
    b2.precompute(chess)
    monkeypatch.setattr(O, "OWN_TRACER", False)
    for f in make_sequence(chess, "VBL", n_frames=2, seed=0):
        gb = make_gbuffer(chess, f, 1)
        want = b2.render(f, gb)
        monkeypatch.setattr(O, "OWN_TRACER", True)
        assert torch.equal(a2.render(f, gb), want) and a2._last == b2._last and a2._vis is None
        monkeypatch.setattr(O, "OWN_TRACER", False)
    monkeypatch.setattr(O, "OWN_TRACER", True)
    monkeypatch.setattr(E.EmbreeTracer, "create", classmethod(lambda cls, V, F: None))
    c = get_method("oracle")(**cfg)
    c.precompute(scene)
    f = frames[1]
    gb = make_gbuffer(scene, f, 1)
    assert torch.equal(c.render(f, gb), b.render(f, gb)) and c._own is False and c._vis is not None
