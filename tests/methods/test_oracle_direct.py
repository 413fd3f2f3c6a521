"""The oracle's C-loop frame without torch's gathers and scatter (or35): `Oracle._render_direct` (the C loops
read each block's G-buffer rows themselves, ``native_rays.Rows``, and ``native_rays.shade`` writes the estimates
into the frame's channel-major radiance) and ``native_rays.frame_rows`` (the sample order and `frame_cost`'s
counts by one C pass) give the same images and counts, bit for bit, as the torch path beside them
(``DIRECT`` / ``FRAME_ROWS`` off) — on every library scene, posed frames, both geometric-normal layouts
(per sample and per face) and ray batches smaller than a region."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from methods.registry import get_method
from references.gbuffer import make_gbuffer
from scenes.library import SCENES, get_scene
from scenes.sequences import make_sequence


def _native(monkeypatch):
    import methods.oracle.native_rays as on

    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    if not on.available():
        pytest.skip("no C compiler: the C loops do not run")
    return on


def test_direct_frames_equal_torch_path_on_every_library_scene(monkeypatch):
    """Every library scene (test size; the articulated ones posed, frame 1 of a P sequence), one and two
    sub-samples a side, a G-buffer thinned to fewer hits than faces, and batches of rays smaller than a region: the same image (``torch.equal``) and
    the same `frame_cost` counts (``_last``) with ``DIRECT`` and ``FRAME_ROWS`` on as off; the direct path
    ran (``Rows`` given to ``pretrace``) and both geometric-normal layouts occurred."""
    import methods.oracle as O

    on = _native(monkeypatch)
    real, seen, layouts = on.pretrace, [0], set()

    def counting(mat, n, *a, **k):
        seen[0] += isinstance(n, on.Rows)
        if isinstance(n, on.Rows):
            layouts.add(n.face is None)
        return real(mat, n, *a, **k)

    monkeypatch.setattr(on, "pretrace", counting)
    for name in SCENES:
        scene = get_scene(name, "test")
        kind = "P" if scene.skin_weights else "VBL"
        frame = make_sequence(scene, kind, n_frames=2, seed=0)[1]
        for spp, cfg in ((1, dict(light_samples=3, brdf_samples=2, max_rays_per_batch=1 << 12)),
                         (2, dict(light_samples=2, brdf_samples=2)), (-1, dict(light_samples=2, brdf_samples=1))):
            gb = make_gbuffer(scene, frame, abs(spp))
            if spp < 0:  # two samples in three made misses: fewer hit samples than faces (normals per sample)
                gb = dataclasses.replace(gb, hit=gb.hit & (torch.arange(gb.num_samples) % 3 == 0))
            out = {}
            for on_ in (True, False):
                monkeypatch.setattr(O, "DIRECT", on_)
                monkeypatch.setattr(O, "FRAME_ROWS", on_)
                o = get_method("oracle")(**cfg, seed=5)
                o.precompute(scene)
                seen[0] = 0
                out[on_] = (o.render(frame, gb), o._last)
                assert (seen[0] > 0) == on_, (name, spp)
            assert torch.equal(out[True][0], out[False][0]), (name, spp)
            assert out[True][1] == out[False][1], (name, spp)
    assert layouts == {True, False}


def test_frame_rows_equal_torch():
    """``native_rays.frame_rows`` = ``torch.nonzero((region == r) & hit)`` per region, concatenated, and
    `Oracle._record`'s counts, on random G-buffer arrays with misses, hit samples outside every region, and
    negative face indices (torch's from-the-end indexing)."""
    import methods.oracle.native_rays as on

    if on._lib() is None:
        pytest.skip("no C compiler: the C loops do not run")
    g = torch.Generator().manual_seed(3)
    P, R, M, N = 5000, 3, 700, 400
    hit = torch.rand(P, generator=g) < 0.7
    region = torch.randint(-1, R + 1, (P,), generator=g)
    face = torch.randint(-M, M, (P,), generator=g)
    F = torch.randint(0, N, (M, 3), generator=g)
    scratch = {}

    def work(name, shape, dtype):
        return scratch.setdefault(name, torch.zeros(shape, dtype=dtype))

    order, counts, hits, faces, verts = on.frame_rows(hit, region, face, R, F, N, work)
    want = [torch.nonzero((region == r) & hit).squeeze(-1) for r in range(R)]
    assert torch.equal(order, torch.cat(want)) and counts == [w.numel() for w in want]
    hit_idx = torch.nonzero(hit).squeeze(-1)
    hit_face = torch.zeros(M, dtype=torch.bool)
    hit_face[face[hit_idx]] = True
    hit_vert = torch.zeros(N, dtype=torch.bool)
    hit_vert[F[torch.nonzero(hit_face).squeeze(-1)].reshape(-1)] = True
    assert (hits, faces, verts) == (hit_idx.numel(), int(hit_face.sum()), int(hit_vert.sum()))


@pytest.mark.parametrize("name,kind", [("chess", "VBL"), ("creature", "P")])
def test_face_normals_kept_across_frames_equal_computed(name, kind, monkeypatch):
    """`Oracle._face_table` keeps the per-face geometric normals of the last frame's mesh: a sequence rendered
    by one oracle (static geometry: the table computed once, then kept; a posed sequence: computed for each
    new pose) gives the images of the torch path (``DIRECT``, ``FRAME_ROWS`` and ``FACE_CACHE`` off), frame
    after frame; two sub-samples a side, so the per-face table is taken."""
    import methods.oracle as O

    _native(monkeypatch)
    scene = get_scene(name, "test")
    frames = make_sequence(scene, kind, n_frames=4, seed=1)
    cfg = dict(light_samples=2, brdf_samples=2, seed=3)
    a = get_method("oracle")(**cfg)
    a.precompute(scene)
    computed, real = [0], O.geometric_normals

    def counting(V, F, face):
        computed[0] += 1
        return real(V, F, face)

    for f in frames:
        gb = make_gbuffer(scene, f, 2)
        monkeypatch.setattr(O, "geometric_normals", counting)
        img = a.render(f, gb)
        monkeypatch.setattr(O, "geometric_normals", real)
        for flag in ("DIRECT", "FRAME_ROWS", "FACE_CACHE"):
            monkeypatch.setattr(O, flag, False)
        b = get_method("oracle")(**cfg)
        b.precompute(scene)
        want = b.render(f, gb)
        for flag in ("DIRECT", "FRAME_ROWS", "FACE_CACHE"):
            monkeypatch.setattr(O, flag, True)
        assert torch.equal(img, want) and a._last == b._last, f.index
    assert computed[0] == (1 if kind == "VBL" else len(frames))
