"""Reference cache: hits without rendering, key sensitivity, stale/corrupt entries re-rendered."""
from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np
import pytest
import torch

from references import cache, render


def _small(W=8, H=8):
    from scenes.library import get_scene

    sc = get_scene("sphere_plane", "test")
    return sc.replace(camera=dataclasses.replace(sc.camera, width=W, height=H))


@pytest.fixture
def counted(monkeypatch, tmp_path):
    """Cache relocated to tmp_path (PRTBENCH_CACHE); render_halves counts its calls."""
    monkeypatch.setenv("PRTBENCH_CACHE", str(tmp_path))
    calls = []
    real = render.render_halves

    def fake(*args, **kw):
        calls.append(kw)
        return real(*args, **kw)

    monkeypatch.setattr(render, "render_halves", fake)
    return calls, tmp_path


def _files(root):
    return sorted(p.name for p in (root / "references").iterdir())


def test_hit_returns_identical_data_without_rendering(counted):
    calls, root = counted
    sc = _small()
    fr = sc.default_frame()
    r1 = render.render_reference(sc, fr, bounces=0, spp=4, seed=0)
    assert len(calls) == 1 and r1.meta["from_cache"] is False
    key = r1.meta["cache_key"]
    assert _files(root) == [f"{key}.json", f"{key}.npz"]  # no temporaries left behind
    r2 = render.render_reference(sc, fr, bounces=0, spp=4, seed=0)
    assert len(calls) == 1 and r2.meta["from_cache"] is True
    for f in ("image", "half_a", "half_b", "coverage"):
        assert torch.equal(getattr(r1, f), getattr(r2, f)), f
    assert r2.noise_floor == r1.noise_floor
    assert {k: v for k, v in r2.meta.items() if k != "from_cache"} == {k: v for k, v in r1.meta.items() if k != "from_cache"}
    # use_cache=False renders again (and leaves the entry alone)
    render.render_reference(sc, fr, bounces=0, spp=4, seed=0, use_cache=False)
    assert len(calls) == 2
    # other settings → other entries
    render.render_reference(sc, fr, bounces=1, spp=4, seed=0)
    render.render_reference(sc, fr, bounces=0, spp=4, seed=1)
    assert len(calls) == 4 and len(_files(root)) == 6


def test_key_changes_with_every_field():
    from scenes.materials import Lambert

    sc = _small()
    fr = sc.default_frame()
    base = dict(max_depth=2, spp=4, seed=0, spp_side=2)
    k0 = cache.key_of(cache.reference_fields(sc, fr, **base))
    assert k0 == cache.key_of(cache.reference_fields(sc, sc.default_frame(), **base))  # stable
    mats = dict(fr.materials)
    mats["plane"] = Lambert(kd=(0.6, 0.6, 0.5))
    keys = {
        cache.key_of(cache.reference_fields(sc, dataclasses.replace(fr, materials=mats), **base)),
        cache.key_of(cache.reference_fields(sc, dataclasses.replace(fr, camera=dataclasses.replace(fr.camera, fov_deg=41.0)), **base)),
        cache.key_of(cache.reference_fields(sc, dataclasses.replace(fr, envmap=fr.envmap.rotated(torch.tensor([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]))), **base)),
        cache.key_of(cache.reference_fields(sc.replace(name="other", materials=mats), fr, **base)),
    }
    for k, v in (("max_depth", -1), ("spp", 8), ("seed", 1), ("spp_side", 3)):
        keys.add(cache.key_of(cache.reference_fields(sc, fr, **(base | {k: v}))))
    assert k0 not in keys and len(keys) == 8


@pytest.mark.parametrize("damage", ["truncate_npz", "flip_npz_byte", "delete_npz", "bad_json", "wrong_fields"])
def test_corrupt_or_stale_entry_is_re_rendered(counted, damage):
    calls, root = counted
    sc = _small()
    fr = sc.default_frame()
    r1 = render.render_reference(sc, fr, bounces=0, spp=4, seed=0)
    npz, side = cache.paths(r1.meta["cache_key"])
    if damage == "truncate_npz":
        npz.write_bytes(npz.read_bytes()[:100])
    elif damage == "flip_npz_byte":
        b = bytearray(npz.read_bytes())
        b[len(b) // 2] ^= 0xFF
        npz.write_bytes(bytes(b))
    elif damage == "delete_npz":
        npz.unlink()
    elif damage == "bad_json":
        side.write_text("{not json")
    elif damage == "wrong_fields":
        d = json.loads(side.read_text())
        d["fields"]["mitsuba"] = "0.0.0"  # an entry written by another Mitsuba
        side.write_text(json.dumps(d))
    with pytest.warns(RuntimeWarning, match="stale or corrupt"):
        r2 = render.render_reference(sc, fr, bounces=0, spp=4, seed=0)
    assert len(calls) == 2 and r2.meta["from_cache"] is False
    assert torch.equal(r1.image, r2.image)  # deterministic re-render
    # the entry is healthy again
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r3 = render.render_reference(sc, fr, bounces=0, spp=4, seed=0)
    assert len(calls) == 2 and r3.meta["from_cache"] is True


def test_store_load_round_trip(monkeypatch, tmp_path):
    monkeypatch.setenv("PRTBENCH_CACHE", str(tmp_path))
    fields = {"a": 1, "b": "x"}
    key = cache.key_of(fields)
    arrays = {"x": np.arange(6, dtype=np.float32).reshape(2, 3), "m": np.array([True, False])}
    path = cache.store(key, fields, arrays, {"note": "hi"})
    assert path.parent == tmp_path / "references"
    got, meta = cache.load(key, fields)
    assert meta == {"note": "hi"} and set(got) == {"x", "m"}
    assert np.array_equal(got["x"], arrays["x"]) and got["x"].dtype == np.float32
    assert cache.load(cache.key_of({"a": 2}), {"a": 2}) is None  # plain miss, no warning
    with pytest.warns(RuntimeWarning):
        assert cache.load(key, {"a": 1, "b": "y"}) is None  # same file name, other fields


def test_source_hash_tracks_the_rendering_code(monkeypatch, tmp_path):
    # Editing the exporter/plugins/materials/env map code must change every key.
    for rel in cache._SOURCES:
        (tmp_path / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / rel).write_text(f"# {rel}\n")
    monkeypatch.setattr(cache, "_ROOT", tmp_path)
    h0 = cache.source_hash()
    assert cache.source_hash() == h0
    (tmp_path / cache._SOURCES[1]).write_text("# edited\n")
    h1 = cache.source_hash()
    (tmp_path / cache._SOURCES[0]).unlink()
    assert len({h0, h1, cache.source_hash()}) == 3
