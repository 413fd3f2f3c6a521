"""`method.FRAME_CALL` (session 43, pt43): a frame on an existing view plan with the lighting unchanged runs as
one C call (``native_fit.frame_call``: the batched fit, the region tables in place, ``native.view_frame``) and
renders, bit for bit, the frames of the route it replaces (`PTT.coords` → `fast.region_tables` →
`PTT._view_frame`), which stays its fallback and oracle here; the method's state after each frame (H, the
tables, the stage counts, the last view) is that route's too."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from methods.ptt import fast as F
from methods.ptt import method as PM
from methods.ptt import native as N
from methods.ptt import native_fit as NF
from methods.ptt.method import PTT
from references.gbuffer import make_gbuffer
from scenes.library import get_scene
from scenes.sequences import make_sequence

# the perf suite's shape (lobes, no bounce terms, 3K = 24 lanes) with enough θ nodes that a_r is MKL's product
# (``native_fit.ar_table``) on every test scene
TINY = dict(rays=4, cube_res=4, n_wi=8, brdf_grid=8, brdf_table=8, light_res_1=2, light_res_2=1, n_L=16,
            lobe_fit_samples=256, lobe_vis_samples=128, lobe_vis_res=4, env_res=4, lobe_theta=32, sh_order=2,
            bounces=0)


@pytest.fixture(autouse=True)
def _skip_without_native():
    if not (F.native_shading() and N.cells_available() and NF.frame_call_fn() is not None):
        pytest.skip("no native sample stage / cells / frame call")


def _spy(monkeypatch):
    """Count `PTT._frame_call` calls that rendered the frame."""
    n = {"taken": 0}
    real = PTT._frame_call

    def counting(self, *a):
        out = real(self, *a)
        n["taken"] += out is not None
        return out

    monkeypatch.setattr(PTT, "_frame_call", counting)
    return n


def _state(m):
    return (m._f_H, m._f_tabs[0], m._f_tabs[1], dict(m.stats), m._last_view[0], m._last_view[2])


def _chess_vb(monkeypatch, small, seed):
    """The chess test scene, its PTT, the route's twin (shading "vertex": the same precomputed arrays, its own
    caches), the calls' spy and three VB frames on a 24 x 24 film."""
    scene = get_scene("chess", "test")
    fast = PTT(**TINY)
    fast.precompute(scene)
    frames = [small(f, 24) for f in make_sequence(scene, "VB", n_frames=3, seed=seed)]
    return scene, fast, fast.with_shading("vertex"), _spy(monkeypatch), frames


@pytest.mark.parametrize("name", ["chess", "creature", "sphere_plane"])
def test_frame_call_renders_the_route_frames_bit_for_bit(name, monkeypatch, small, with_misses):
    """V, VB, L, VB sequences at 1 and 2 threads (the loops' minimum shares lowered so every loop splits), two
    image sizes alternating (a new view plan, then a new frame plan), frames with misses: the same images and
    the same state as the route with FRAME_CALL off, and the one call taken on every V / VB frame after a
    sequence's first (which makes the plans; L frames change the lighting: the route)."""
    monkeypatch.setattr(N, "_MIN_PAIRS_PER_THREAD", 8)
    monkeypatch.setattr(N, "_MIN_SAMPLES_PER_THREAD", 64)
    monkeypatch.setattr(N, "_MIN_PIXELS_PER_THREAD", 16)
    monkeypatch.setattr(N, "_MIN_ROWS_PER_THREAD", 8)
    monkeypatch.setattr(PM, "FRAME_CHUNK", 5)  # W_r's rows in many chunks (regions of 16-64 rows at this size)
    scene = get_scene(name, "test")
    fast = PTT(**TINY)
    fast.precompute(scene)
    slow = fast.with_shading("vertex")  # the same precomputed arrays, its own caches
    n = _spy(monkeypatch)
    expect = 0
    for threads in (1, 2):
        torch.set_num_threads(threads)
        try:
            for kind in ("V", "VB", "L", "VB"):
                for i, f in enumerate(make_sequence(scene, kind, n_frames=5, seed=5)):
                    f = small(f, 16 if i == 3 else 24)  # frame 3 on a new layout (a new plan: the route)
                    gb = make_gbuffer(scene, f, 2)
                    if i == 2:
                        gb = with_misses(gb)
                    monkeypatch.setattr(PM, "FRAME_CALL", True)
                    before = n["taken"]
                    a = fast.render(f, gb)
                    if kind != "L" and i in (1, 2):  # (frames 3 and 4: a new layout each, a new view plan)
                        expect += 1
                        assert n["taken"] == before + 1, f"{name} {kind} frame {i}: the one call was not taken"
                    monkeypatch.setattr(PM, "FRAME_CALL", False)
                    b = slow.render(f, gb)
                    assert torch.equal(a, b), f"{name} {kind} frame {i} threads {threads}: {(a - b).abs().max()}"
                    sa, sb = _state(fast), _state(slow)
                    assert all(torch.equal(x, y) for x, y in zip(sa[:3], sb[:3])), f"{name} {kind} frame {i}: tables"
                    assert sa[3:5] == sb[3:5] and torch.equal(sa[5], sb[5]), f"{name} {kind} frame {i}: {sa[3:]} {sb[3:]}"
        finally:
            torch.set_num_threads(1)
    assert n["taken"] >= expect > 0


def test_frame_call_equal_h_keeps_the_tables_and_brdf_change_forces_them(monkeypatch, small):
    """A VB frame whose new material objects have the last frame's values (the same H): the tables keep their
    memory and values and the BRDF stage is not counted unless the frame says "brdf" changed — as the route's
    torch.equal; the images equal the route's either way. Then one entry of H changed: seen."""
    scene, fast, slow, n, frames = _chess_vb(monkeypatch, small, 2)
    for f in frames[:2]:
        gb = make_gbuffer(scene, f, 2)
        fast.render(f, gb)
        monkeypatch.setattr(PM, "FRAME_CALL", False)
        slow.render(f, gb)
        monkeypatch.setattr(PM, "FRAME_CALL", True)
    taken = n["taken"]
    copies = {r: dataclasses.replace(mat) for r, mat in frames[1].materials.items()}  # new objects, same values
    for changed in (frozenset({"view"}), frozenset({"view", "brdf"})):
        f = dataclasses.replace(frames[2], materials=copies, changed=changed)
        copies = {r: dataclasses.replace(mat) for r, mat in copies.items()}
        gb = make_gbuffer(scene, f, 2)
        ptr = fast._f_tabs[0].data_ptr()
        before = torch.clone(fast._f_tabs[0])
        a = fast.render(f, gb)
        monkeypatch.setattr(PM, "FRAME_CALL", False)
        b = slow.render(f, gb)
        monkeypatch.setattr(PM, "FRAME_CALL", True)
        assert torch.equal(a, b) and fast.stats == slow.stats, (changed, fast.stats, slow.stats)
        assert fast._f_tabs[0].data_ptr() == ptr and torch.equal(fast._f_tabs[0], before)
    # one entry of H changed (region 0's red diffuse: H[0, 0, 0] alone where only the diffuse function has a
    # diffuse weight): the tables are rewritten
    r0 = fast.regions[0]
    kd = copies[r0].kd
    copies[r0] = dataclasses.replace(copies[r0], kd=(kd[0] * 0.5 + 0.01, kd[1], kd[2]))
    f = dataclasses.replace(frames[2], materials=copies, changed=frozenset({"view"}))
    gb = make_gbuffer(scene, f, 2)
    a = fast.render(f, gb)
    monkeypatch.setattr(PM, "FRAME_CALL", False)
    b = slow.render(f, gb)
    assert not torch.equal(fast._f_tabs[0], before) and torch.equal(fast._f_tabs[0], slow._f_tabs[0])
    assert torch.equal(a, b) and fast.stats == slow.stats, (fast.stats, slow.stats)
    assert n["taken"] == taken + 3


def test_frame_call_declines_a_gbuffer_off_contract(monkeypatch, small, with_misses):
    """Misses whose face is not -1 on a VB frame: the view call declines after the fit and the tables, the route
    then renders the frame (finding H and the tables current) — the same image and state as FRAME_CALL off."""
    scene, fast, slow, n, frames = _chess_vb(monkeypatch, small, 3)
    for i, f in enumerate(frames):
        gb = make_gbuffer(scene, f, 2)
        if i == 2:
            holes = with_misses(gb, 29)
            gb = dataclasses.replace(holes, face=torch.where(holes.hit, holes.face, 0))
        a = fast.render(f, gb)
        monkeypatch.setattr(PM, "FRAME_CALL", False)
        b = slow.render(f, gb)
        monkeypatch.setattr(PM, "FRAME_CALL", True)
        assert torch.equal(a, b) and fast.stats == slow.stats, (i, fast.stats, slow.stats)
        assert torch.equal(fast._f_H, slow._f_H) and torch.equal(fast._f_tabs[0], slow._f_tabs[0])
    assert n["taken"] == 1  # frame 1 (frame 0 makes the plans, frame 2 declined)
