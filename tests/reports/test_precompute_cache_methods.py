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


# case → the other values of its method's render_config_keys (every key changed at once)
RENDER_CHANGES = {
    "inout": dict(shading="vertex"),
    "triple_product": dict(shading="vertex"),
    "zh_shadow": dict(specular="cosine", shading="vertex", window="hanning", window_width=2.0, clamp=False),
}


def test_render_config_keys_have_a_case():
    declared = {n for n in available_methods() if get_method(n).__module__.startswith("methods.")
                and get_method(n).render_config_keys}
    assert declared == {CASES[c][0] for c in RENDER_CHANGES}
    for case, changes in RENDER_CHANGES.items():
        assert set(changes) == set(get_method(CASES[case][0]).render_config_keys), case


def _state(m) -> tuple[str, list[torch.Tensor]]:
    """The encoded state without the config and without wall-clock stats (``*seconds*`` and ``time*`` entries)."""
    tree, tensors = PC.encode_state({k: v for k, v in m.__dict__.items() if k != "_config"}, m.scene)

    def strip(x):
        if isinstance(x, list):
            if len(x) == 2 and isinstance(x[0], str) and ("seconds" in x[0] or x[0].startswith("time")):
                return [x[0], None]
            return [strip(v) for v in x]
        return {k: strip(v) for k, v in x.items()} if isinstance(x, dict) else x

    return json.dumps(strip(json.loads(tree))), tensors


@pytest.mark.parametrize("case", sorted(RENDER_CHANGES))
def test_render_config_keys_leave_the_precomputation_unchanged(case):
    """What lets two configs share an entry: precomputing with every render-only key changed leaves
    the same state (all of ``__dict__`` but the config, tensors bit for bit)."""
    cls, scene, frame, gb, cfg = _setup(case)
    a, b = cls(**cfg), cls(**(cfg | RENDER_CHANGES[case]))
    a.precompute(scene)
    b.precompute(scene)
    (ta, xa), (tb, xb) = _state(a), _state(b)
    assert ta == tb
    assert len(xa) == len(xb) and all(torch.equal(u, v) for u, v in zip(xa, xb))


@pytest.mark.parametrize("case", sorted(RENDER_CHANGES))
def test_entry_is_shared_across_render_config_and_renders_with_the_loaders_config(case, cache):
    """The cell with the other render keys loads the first one's entry (one file, cached) and renders
    exactly what it renders after computing its own precomputation."""
    cls, scene, frame, gb, cfg = _setup(case)
    other = cfg | RENDER_CHANGES[case]
    PC.precompute(cls(**cfg), scene, json.dumps(cfg, sort_keys=True))
    loaded = cls(**other)
    info = PC.precompute(loaded, scene, json.dumps(other, sort_keys=True))
    assert info["cached"] and len(list(cache.glob("*.json"))) == 1
    assert dict(loaded.config) == dict(cls(**other).config)
    computed = cls(**other)
    computed.precompute(scene)
    want, got = computed.render(frame, gb), loaded.render(frame, gb)
    assert torch.isfinite(want).all() and want.abs().max() > 0
    assert torch.equal(want, got), float((want - got).abs().max())
