"""Every method that opts in to the precompute cache round-trips through it: the image rendered
after loading the entry equals, bit for bit, the image of the instance that computed it (test-size
scenes, small configs). And zh_shadow's damaged-cache cases of issue 17 (a truncated file failed
every later run with OSError, a zeroed one gave a wrong "ok" image)."""
from __future__ import annotations

import json

import pytest
import torch

from methods.registry import available_methods, get_method
from references.gbuffer import make_gbuffer
from reports import precompute_cache as PC
from scenes.library import get_scene
from scenes.sequences import make_sequence

_PTT_SMALL = dict(bounces=2, n_wi=4, brdf_grid=8, brdf_table=16, cube_res=8, light_res_1=2, light_res_2=2, rays=16,
                  lobe_fit_samples=1024, lobe_vis_samples=256, lobe_vis_res=4, lobe_theta=4, env_res=8,
                  lobe_degrees=[0, 14], compress=dict(clusters=2, eigenvectors=2, light_dim=8))
# case → (method, scene, sequence kind, small config); kinds the method scores, so frame 1 changes them.
CASES = {
    "ptt": ("ptt", "sphere_plane", "VBL", _PTT_SMALL),
    "ptt_pca": ("ptt", "sphere_plane", "VBL", _PTT_SMALL | dict(basis="pca", pca_terms=2, pca_grid=4)),
    "triple_product": ("triple_product", "sphere_plane", "V", dict(level=2, brdf_dirs=[5, 8], frame_grid=[5, 8, 1])),
    "zh_shadow": ("zh_shadow", "creature", "P", dict(train_poses=4, n_dirs=32, fit_iters=2)),
    "sh_prt": ("sh_prt", "sphere_plane", "V", dict(order=3, bounces=1, rays=16)),
    "inout": ("inout", "sphere_plane", "V", dict(terms=8, brdf_res=8, cube_res=8)),
}


@pytest.fixture(autouse=True)
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("PRTBENCH_CACHE", str(tmp_path / "cache"))
    monkeypatch.delenv("PRTBENCH_NO_PRECOMPUTE_CACHE", raising=False)
    return tmp_path / "cache" / "precompute"


def test_every_opted_in_method_has_a_round_trip_case():
    opted = {n for n in available_methods()
             if get_method(n).cache_precompute and get_method(n).__module__.startswith("methods.")}
    assert opted == {c[0] for c in CASES.values()}


def _setup(case):
    name, scene_name, kind, cfg = CASES[case]
    scene = get_scene(scene_name, "test")
    frame = make_sequence(scene, kind, n_frames=2, seed=3)[1]
    return get_method(name), scene, frame, make_gbuffer(scene, frame, 1), cfg


def _images(m, frame, gb) -> list[torch.Tensor]:
    """The image at the configured bounce count (PTT: 2, so the one- and two-bounce state is used)."""
    return [m.render(frame, gb)]


@pytest.mark.parametrize("case", sorted(CASES))
def test_render_after_loading_equals_render_after_computing(case):
    cls, scene, frame, gb, cfg = _setup(case)
    key = json.dumps(cfg, sort_keys=True)
    first = cls(**cfg)
    computed = PC.precompute(first, scene, key)
    loaded_m = cls(**cfg)
    loaded = PC.precompute(loaded_m, scene, key)
    assert not computed["cached"] and loaded["cached"] and loaded["seconds"] == computed["seconds"]
    assert loaded_m.memory() == first.memory()
    want, got = _images(first, frame, gb), _images(loaded_m, frame, gb)
    for b, (w, g) in enumerate(zip(want, got)):
        assert w.abs().max() > 0 and torch.isfinite(w).all(), (case, b)
        assert torch.equal(w, g), (case, b, float((w - g).abs().max()))


@pytest.mark.parametrize("damage", ["truncated", "zeroed"])
def test_damaged_zh_shadow_entry_is_recomputed_with_the_right_image(cache, damage):
    """Issue 17 #4: a truncated zh_shadow cache file made every later run fail with OSError until
    deleted by hand; a zeroed one gave RMSE 1.11 instead of 0.51 and "ok"."""
    cls, scene, frame, gb, cfg = _setup("zh_shadow")
    first = cls(**cfg)
    PC.precompute(first, scene, "{}")
    want = first.render(frame, gb)
    (data,) = cache.glob("*.pt")
    raw = data.read_bytes()
    data.write_bytes(raw[: len(raw) // 2] if damage == "truncated" else bytes(len(raw)))
    m = cls(**cfg)
    with pytest.warns(UserWarning, match="ignoring precompute cache zh_shadow-.*deleted, recomputing"):
        info = PC.precompute(m, scene, "{}")
    assert not info["cached"]
    assert torch.equal(m.render(frame, gb), want)
    again = cls(**cfg)
    assert PC.precompute(again, scene, "{}")["cached"] and torch.equal(again.render(frame, gb), want)
