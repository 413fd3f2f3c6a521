"""Per-pixel frames with a few missed samples (`TripleProduct._miss_fill`, ``MISS_FILL``): every sample shaded
by slices, each miss as a copy of a neighbouring hit, zeroed after — against the gather path (``MISS_FILL``
off: the hit samples' rows gathered, the test oracle) and the all-hit frame, on real G-buffers with planted
misses (stored as `references.gbuffer.make_gbuffer` stores a miss: face / region −1, zero bary, position and
normal)."""
from __future__ import annotations

import dataclasses

import pytest
import torch

from methods.triple_product import TripleProduct
from methods.triple_product import fast_eval
from methods.triple_product import method as tp_method
from methods.triple_product import native_group
from references.gbuffer import make_gbuffer
from scenes.library import get_scene
from scenes.sequences import make_sequence


@pytest.fixture(scope="module")
def chess():
    scene = get_scene("chess", "test")
    m = TripleProduct(level=2, n_coeffs=None, frame_grid=(5, 8, 1), brdf_dirs=(4, 4), brdf_supersample=1,
                      progress=False)
    m.precompute(scene)
    return scene, m


def _plant(gb, idx) -> object:
    """``gb`` with the samples ``idx`` missed (a copy; what `make_gbuffer` stores for a miss; ωo kept)."""
    idx = torch.as_tensor(idx, dtype=torch.long)
    hit, face, region = gb.hit.clone(), gb.face.clone(), gb.region.clone()
    bary, position, normal = gb.bary.clone(), gb.position.clone(), gb.normal.clone()
    hit[idx], face[idx], region[idx] = False, -1, -1
    bary[idx], position[idx], normal[idx] = 0, 0, 0
    S2 = gb.spp_side ** 2
    return dataclasses.replace(gb, hit=hit, face=face, region=region, bary=bary, position=position, normal=normal,
                               coverage=hit.view(gb.height, gb.width, S2).all(-1))


def _record(m) -> dict:
    return {k: v for k, v in m.last_frame().items() if k not in ("reads", "vis_row_ids")}


def _spy(monkeypatch, m, log: list):
    """Records every `fast_eval.shade_pixels` call's ``fill`` and result and every `native_group.pixel_mean`
    input (("mean", (P, 3))), and checks that every row
    `fast_eval.shade_fine` is handed is inside its table and every weight finite (no miss's face / region −1
    or zero normal reaches a look-up)."""
    shade_pixels, shade_fine = fast_eval.shade_pixels, fast_eval.shade_fine
    n_rho = fast_eval._brdf_stack(m)[1].shape[0]

    def pixels(*a, **k):
        res = shade_pixels(*a, **k)
        log.append((k.get("fill"), res.clone()))
        return res

    def fine(method, R, wo, region, vrows, vw, mix=None, **k):
        rows, w, lrows, lw = k["lookups"][:4]
        assert int(rows.min()) >= 0 and int(rows.max()) < n_rho
        assert int(lrows.min()) >= 0 and int(lrows.max()) < method.grid.size
        assert int(vrows.min()) >= 0 and int(vrows.max()) < method.V_val.shape[0]
        for x in (w, lw, vw):
            assert bool(torch.isfinite(x).all())
        return shade_fine(method, R, wo, region, vrows, vw, mix, **k)

    def mean(x, *a):
        log.append(("mean", x.clone()))
        return pixel_mean(x, *a)

    pixel_mean = native_group.pixel_mean
    monkeypatch.setattr(fast_eval, "shade_pixels", pixels)
    monkeypatch.setattr(fast_eval, "shade_fine", fine)
    monkeypatch.setattr(native_group, "pixel_mean", mean)


def _render(m, frame, gb, fill: bool, monkeypatch):
    monkeypatch.setattr(tp_method, "MISS_FILL", fill)
    img = m.render(frame, gb)
    P = gb.num_samples
    return img, _record(m), m.frame_cost("V", P, pixels=gb.height * gb.width)


@pytest.mark.parametrize("kind", ["V", "L"])
def test_few_misses_equal_gather_path(chess, kind, monkeypatch):
    """Planted misses (a run starting the frame, one alone, a run of two, the last sample, 1 % at random,
    exactly `MISS_SHARE`): the slices' frame = the gather path's bit for bit — image, the frame's record
    (shaded samples, faces, visibility rows, groups) and `frame_cost` —, the fill path ran, and every hit's
    radiance = that of the all-hit frame, bit for bit; a lighting change (L) projects the same pairs."""
    scene, m = chess
    frames = make_sequence(scene, kind, n_frames=2, seed=2)
    gb0 = make_gbuffer(scene, frames[1], 2)
    P = gb0.num_samples
    assert bool(gb0.hit.all())
    g = torch.Generator().manual_seed(0)
    sets = [[0, 1, 2], [5000], [100, 101, 7000, P - 1], torch.randperm(P, generator=g)[:P // 100],
            torch.randperm(P, generator=g)[:int(P * tp_method.MISS_SHARE)]]
    log: list = []
    _spy(monkeypatch, m, log)
    m._light_key = None
    m.render(frames[0], make_gbuffer(scene, frames[0], 2))
    full, _, _ = _render(m, frames[1], gb0, True, monkeypatch)
    assert log[-2][0] is None
    full_res = log[-2][1]
    for idx in sets:
        gb = _plant(gb0, idx)
        miss = ~gb.hit
        m._light_key = None                 # the lighting re-projected by both paths (L: the frame's pairs)
        old, rec_old, cost_old = _render(m, frames[1], gb, False, monkeypatch)
        assert log[-2][0] is None and log[-2][1].shape[0] == int(gb.hit.sum())
        pairs_old = [m.stats.get(k) for k in ("projected_pairs", "projected_frames")]
        m._light_key = None
        new, rec_new, cost_new = _render(m, frames[1], gb, True, monkeypatch)
        fill, res = log[-2]
        radiance = log[-1][1]                                  # what the pixel mean reads: +0 on every miss
        assert not bool(radiance[miss].signbit().any()) and not bool(radiance[miss].any())
        assert fill is not None and torch.equal(torch.sort(fill[0]).values, torch.nonzero(miss).squeeze(-1))
        assert bool(gb.hit[fill[1]].all())
        assert torch.equal(old, new), len(idx)
        assert rec_old == rec_new and cost_old == cost_new, (rec_old, rec_new, cost_old, cost_new)
        assert [m.stats.get(k) for k in ("projected_pairs", "projected_frames")] == pairs_old
        assert torch.equal(res[gb.hit], full_res[gb.hit])     # the hits as in the all-hit frame
        assert not torch.equal(new, full)


def test_many_misses_gather_unless_allowed(chess, monkeypatch):
    """More than `MISS_SHARE` missed: the gather path; with the share raised to 1, the slices' frame
    (half the samples missed, at random) equals it bit for bit all the same; no sample hit: a black image."""
    scene, m = chess
    frame = make_sequence(scene, "V", n_frames=1, seed=3)[0]
    gb0 = make_gbuffer(scene, frame, 2)
    P = gb0.num_samples
    gb = _plant(gb0, torch.randperm(P, generator=torch.Generator().manual_seed(1))[:P // 2])
    log: list = []
    _spy(monkeypatch, m, log)
    old, rec_old, cost_old = _render(m, frame, gb, True, monkeypatch)
    assert log[-2][0] is None and log[-2][1].shape[0] == int(gb.hit.sum())
    monkeypatch.setattr(tp_method, "MISS_SHARE", 1.0)
    new, rec_new, cost_new = _render(m, frame, gb, True, monkeypatch)
    assert log[-2][0] is not None
    assert torch.equal(old, new) and rec_old == rec_new and cost_old == cost_new
    none = _plant(gb0, torch.arange(P))
    assert torch.equal(m.render(frame, none), torch.zeros(gb0.height, gb0.width, 3))


def test_miss_donors():
    """`_miss_donors`: the hit before each run of adjacent misses, the hit after a run that starts the mask;
    a mask without a miss or without a hit is refused."""
    hit = torch.ones(40, dtype=torch.bool)
    hit[[0, 1, 2, 7, 10, 11, 39]] = False
    miss, donor = tp_method._miss_donors(hit)
    assert miss.tolist() == [0, 1, 2, 7, 10, 11, 39]
    assert donor.tolist() == [3, 3, 3, 6, 9, 9, 38]
    assert bool(hit[donor].all())
    hit[[20, 21, 22]] = False
    assert tp_method._miss_donors(hit)[1].tolist() == [3, 3, 3, 6, 9, 9, 19, 19, 19, 38]
    for bad in (torch.ones(5, dtype=torch.bool), torch.zeros(5, dtype=torch.bool)):
        with pytest.raises(ValueError):
            tp_method._miss_donors(bad)
