"""Session 40 (zh40l): steady lighting-only frames — after a frame that made its image by the fused relight (the
order-8 vertex config's `native.relight_resolve`, the paper config's `native.relight_pixels` in `_relight_planes`),
a lighting-only frame of the same camera, pose, materials and G-buffer size is the frame's lighting and that one
C call on the kept arguments (`ZHShadow._steady_relight`, `ZHShadow._steady_planes`); its oracle the full path
(``steady_relight`` off), the same bits."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from methods.zh_shadow import native as zn
from methods.zh_shadow.method import ZHShadow
from testing.gbuffers import knock_out


def _spy(monkeypatch):
    taken = []
    for name in ("_steady_relight", "_steady_planes"):
        def spy(self, frame, gbuffer, _sr=getattr(ZHShadow, name)):
            out = _sr(self, frame, gbuffer)
            taken.append(out is not None)
            return out
        monkeypatch.setattr(ZHShadow, name, spy)
    return taken


# (fixture, a kept cache whose loss makes the next lighting-only frame a full one, the library of the fused call)
CONFIGS = {"order8": ("_vertex_compact", lambda: zn._relightv_lib()),
           "creature": ("_relight", lambda: zn._relight_pixels_lib())}


@pytest.mark.parametrize("clamp", [False, True])
@pytest.mark.parametrize("kind", ["L", "E"])
@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_steady_relight_equals_full_path(config, kind, clamp, monkeypatch, request):
    """L / E sequences (with misses; at 1 and 2 threads): with the steady path = without it (``steady_relight``
    off: `_render_vertex` every frame) bit for bit, the steady path taken on every lighting-only frame after the
    first (which builds the resolve matrix and records what the next reads). A stale lighting, a lost clamp or
    albedo, the wrong kept arguments break it."""
    from methods.core.threads import torch_threads
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    order8 = request.getfixturevalue(config)   # (either configuration's model)
    if CONFIGS[config][1]() is None:
        pytest.skip("no C compiler")
    taken = _spy(monkeypatch)
    m = order8.with_render_config(clamp=clamp)
    fast, fast2, slow = m.with_render_config(), m.with_render_config(), m.with_render_config()
    slow.steady_relight = False
    frames = make_sequence(order8.scene, kind, 5, seed=9)
    gb = make_gbuffer(order8.scene, frames[0], 2)
    if config == "order8":   # (with misses; the paper config's relight-planes path needs every sample hit)
        gb = knock_out(gb, 13, 2)
    for i, f in enumerate(frames):
        a = fast.render(f, gb)
        with torch_threads(2):
            a2 = fast2.render(f, gb)
        b = slow.render(f, gb)
        assert torch.equal(a, b), (kind, i, float((a - b).abs().max()))
        assert torch.equal(a, a2), (kind, i)
        assert fast._last_counts["Q"] == slow._last_counts["Q"] and fast._last_counts["P"] == slow._last_counts["P"]
        if config == "creature" and i > 0:
            assert slow.last_path == fast.last_path == "relight-planes"
    # frames 2-4 of fast and fast2 (frame 1 builds the matrix: no steady state before it; slow never has one)
    assert taken == [True] * 6, taken
    assert fast.frame_cost(kind, gb.num_samples).bytes == slow.frame_cost(kind, gb.num_samples).bytes


@pytest.mark.parametrize("config", sorted(CONFIGS))
def test_steady_relight_declines_other_state(config, monkeypatch, request):
    """A frame flagged lighting-only (``changed`` = {"light"}) whose camera, materials, pose or G-buffer size
    differ from the recorded frame's, or after a kept cache was replaced, is not a steady frame: its image = the
    full path's (an object with the same history and ``steady_relight`` off) bit for bit. Dropping any of the
    checks renders the recorded frame's view / albedos / matrix instead and breaks it."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    order8 = request.getfixturevalue(config)
    if CONFIGS[config][1]() is None:
        pytest.skip("no C compiler")
    taken = _spy(monkeypatch)
    scene = order8.scene
    frames = make_sequence(scene, "L", 4, seed=11)
    gb = make_gbuffer(scene, frames[0], 2)
    light_only = frozenset({"light"})
    cam2 = dataclasses.replace(frames[2], camera=frames[2].camera.orbited(0.3), changed=light_only)
    mats = dict(frames[2].materials)
    name = next(r for r, mt in mats.items() if hasattr(mt, "kd"))
    mats[name] = dataclasses.replace(mats[name], kd=tuple(0.5 * x for x in mats[name].kd))
    mat2 = dataclasses.replace(frames[2], materials=mats, changed=light_only)
    cases = [(cam2, make_gbuffer(scene, cam2, 2)), (mat2, gb), (frames[2], make_gbuffer(scene, frames[2], 1))]
    if scene.skeleton is not None:
        pose = torch.zeros(scene.skeleton.num_joints)
        pose[0] = 0.2
        p2 = dataclasses.replace(frames[2], pose=pose, changed=light_only)
        cases.append((p2, make_gbuffer(scene, p2, 2)))
    for f2, g2 in cases:
        fast, slow = order8.with_render_config(), order8.with_render_config()
        slow.steady_relight = False
        for f in frames[:2]:
            assert torch.equal(fast.render(f, gb), slow.render(f, gb))
        assert fast._steady is not None
        taken.clear()
        a, b = fast.render(f2, g2), slow.render(f2, g2)
        assert taken == [False], taken
        assert torch.equal(a, b), float((a - b).abs().max())
    # a kept cache replaced (here the compact transfer dropped) between two lighting-only frames: the full path
    fast, slow = order8.with_render_config(), order8.with_render_config()
    slow.steady_relight = False
    for f in frames[:2]:
        fast.render(f, gb), slow.render(f, gb)
    setattr(fast, CONFIGS[config][0], None)
    setattr(slow, CONFIGS[config][0], None)
    taken.clear()
    assert torch.equal(fast.render(frames[2], gb), slow.render(frames[2], gb))
    assert taken == [False]
    taken.clear()
    assert torch.equal(fast.render(frames[3], gb), slow.render(frames[3], gb))
    assert taken == [True]   # (recorded again by the full frame before)
