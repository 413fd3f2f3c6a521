"""`method.VIEW_FRAME` (session 42, pt42): a shading="vertex" frame's native view stage as one C call
(``native.view_frame`` on a packed argument plan) renders, bit for bit, the frames of the Python path it
replaces (``native.referenced_sel``, ``native.vertex_rows(..., rows_at=True)``, ``native.shade_mirror``
called one after the other), which stays its fallback and oracle here."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from methods.ptt import fast as F
from methods.ptt import method as PM
from methods.ptt import native as N
from methods.ptt.method import PTT
from references.gbuffer import make_gbuffer
from scenes.library import get_scene
from scenes.sequences import make_sequence

TINY = dict(rays=4, cube_res=4, n_wi=8, brdf_grid=8, brdf_table=8, light_res_1=2, light_res_2=1, n_L=16,
            lobe_fit_samples=256, lobe_vis_samples=128, lobe_vis_res=4, env_res=4, lobe_theta=4, sh_order=2,
            bounces=0)  # the perf suite's shape: lobes, no bounce terms (3K = 24 lanes: the native rows' blocks)


@pytest.fixture(autouse=True)
def _skip_without_native(monkeypatch):
    if not (F.native_shading() and N.cells_available()):
        pytest.skip("no native sample stage / cells")
    # the route these tests are about (`PTT._view_frame`); `method.FRAME_CALL`, which takes it over once the plan
    # exists, has its own tests (test_frame_call.py)
    monkeypatch.setattr(PM, "FRAME_CALL", False)


def _spy(monkeypatch):
    """Count ``native.view_frame`` calls that shaded (returned an image)."""
    n = {"shaded": 0, "declined": 0}
    real = N.view_frame

    def counting(*a):
        out = real(*a)
        n["shaded" if out is not None else "declined"] += 1
        return out

    monkeypatch.setattr(N, "view_frame", counting)
    return n


@pytest.mark.parametrize("native_tables", [True, False])
@pytest.mark.parametrize("name", ["chess", "creature", "sphere_plane"])
def test_view_frame_renders_the_python_path_frames_bit_for_bit(name, native_tables, monkeypatch, small, with_misses):
    """V, VB and L sequences (camera moves, tables rewritten in place — or, without ``fast.NATIVE_TABLES``,
    made anew each VB frame —, a new lighting), at 1 and 2 threads with the threads' minimum shares lowered
    so every loop splits, two image sizes alternating (a new plan per G-buffer layout) and frames with
    misses: the same bits as the Python path, and the one-call route was taken."""
    monkeypatch.setattr(N, "_MIN_PAIRS_PER_THREAD", 8)
    monkeypatch.setattr(N, "_MIN_SAMPLES_PER_THREAD", 64)
    monkeypatch.setattr(N, "_MIN_PIXELS_PER_THREAD", 16)
    monkeypatch.setattr(F, "NATIVE_TABLES", native_tables)
    scene = get_scene(name, "test")
    fast, slow = PTT(**TINY), None
    fast.precompute(scene)
    slow = fast.with_shading("vertex")  # the same precomputed arrays, its own caches
    n = _spy(monkeypatch)
    frames = 0
    for threads in (1, 2):
        torch.set_num_threads(threads)
        try:
            for kind in ("V", "VB", "L"):
                for i, f in enumerate(make_sequence(scene, kind, n_frames=4, seed=5)):
                    f = small(f, 16 if i == 3 else 24)  # frames 1, 2 on frame 0's plan (its layout)
                    gb = make_gbuffer(scene, f, 2)
                    if i == 2:
                        gb = with_misses(gb)
                    monkeypatch.setattr(PM, "VIEW_FRAME", True)
                    before = n["shaded"]
                    a = fast.render(f, gb)
                    assert n["shaded"] == before + 1, f"{name} {kind} frame {i}: the one-call route was not taken"
                    monkeypatch.setattr(PM, "VIEW_FRAME", False)
                    b = slow.render(f, gb)
                    assert torch.equal(a, b), f"{name} {kind} frame {i} threads {threads}: {(a - b).abs().max()}"
                    frames += 1
        finally:
            torch.set_num_threads(1)
    assert frames == 24 and n["declined"] == 0
    # the plan holds the last frame's camera for cost_terms, as the Python path's tensor
    assert torch.equal(fast._last_view[2], slow._last_view[2]) and fast._last_view[0] == slow._last_view[0]
    assert fast.frame_cost("V", gb.num_samples) == slow.frame_cost("V", gb.num_samples)


def test_view_frame_declines_a_gbuffer_off_contract(monkeypatch, small, with_misses):
    """Misses whose face is not -1 (the contract the Python path checks before its native route): the C
    marking pass finds it, shades nothing, and the frame takes the Python path — the same image as
    VIEW_FRAME off, equal to the reference."""
    scene = get_scene("chess", "test")
    m = PTT(**TINY)
    m.precompute(scene)
    n = _spy(monkeypatch)
    f = small(make_sequence(scene, "V", n_frames=1, seed=3)[0], 24)
    gb = make_gbuffer(scene, f, 2)
    holes = with_misses(gb, 29)
    odd = dataclasses.replace(holes, face=torch.where(holes.hit, holes.face, 0))
    monkeypatch.setattr(PM, "VIEW_FRAME", True)
    m.render(f, holes)
    assert n == {"shaded": 1, "declined": 0}
    a = m.render(f, odd)
    assert n == {"shaded": 1, "declined": 1}
    monkeypatch.setattr(PM, "VIEW_FRAME", False)
    b = m.render(f, odd)
    assert torch.equal(a, b)
    ref = m._render_reference(f, odd)
    torch.testing.assert_close(a, ref, rtol=1e-5, atol=2e-6 * max(float(ref.abs().max()), 1.0))


def test_view_frame_plan_follows_the_switches(monkeypatch, small):
    """The plan is made again when a switch it was made under changes (here ``native.LEAN`` and the thread
    count), and not made while they and the frame's inputs stay the same."""
    scene = get_scene("chess", "test")
    m = PTT(**TINY)
    m.precompute(scene)
    made = []
    real = PTT._make_view_plan

    def counting(self, *a):
        made.append(1)
        return real(self, *a)

    monkeypatch.setattr(PTT, "_make_view_plan", counting)
    monkeypatch.setattr(PM, "VIEW_FRAME", True)
    frames = [small(f, 24) for f in make_sequence(scene, "V", n_frames=3, seed=3)]
    gbs = [make_gbuffer(scene, f, 2) for f in frames]
    m.render(frames[0], gbs[0])
    m.render(frames[1], gbs[1])
    assert len(made) == 1
    plan = PM._VIEW_PLANS[m]
    monkeypatch.setattr(N, "LEAN", not N.LEAN)
    m.render(frames[2], gbs[2])
    assert len(made) == 2 and PM._VIEW_PLANS[m] is not plan
    torch.set_num_threads(2)
    try:
        m.render(frames[2], gbs[2])
    finally:
        torch.set_num_threads(1)
    assert len(made) == 3
    m.render(frames[1], gbs[1])
    assert len(made) == 4
