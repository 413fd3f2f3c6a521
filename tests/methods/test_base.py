"""methods.base: the contract's guarantees that do not depend on a method."""
from __future__ import annotations

import json

import pytest

from methods.registry import available_methods, get_method
from reports.cells import canonical_config


@pytest.mark.parametrize("name", ["inout", "oracle", "ptt", "sh_prt", "triple_product", "zh_shadow"])
def test_config_is_fixed_at_construction(name):
    """The recorded config is the one that ran: no code can change it after construction."""
    m = get_method(name)()
    before = canonical_config(m.config)
    with pytest.raises(TypeError):
        m.config["anything"] = 1
    assert canonical_config(m.config) == before
    # the recorded config rebuilds the same method (what the harness does with a cell's config)
    assert canonical_config(get_method(name)(**json.loads(before)).config) == before


def test_every_builtin_method_is_registered():
    assert {"inout", "oracle", "ptt", "sh_prt", "triple_product", "zh_shadow"} <= set(available_methods())
    with pytest.raises(KeyError, match="unknown method"):
        get_method("no_such_method")


def _tensors(x, seen=None):
    """Every tensor reachable from ``x`` through containers and project objects."""
    import torch

    seen = set() if seen is None else seen
    if id(x) in seen:
        return
    seen.add(id(x))
    if isinstance(x, torch.Tensor):
        yield x
    elif isinstance(x, dict):
        for v in x.values():
            yield from _tensors(v, seen)
    elif isinstance(x, (list, tuple)):
        for v in x:
            yield from _tensors(v, seen)
    elif hasattr(x, "__dict__") and (type(x).__module__ or "").split(".")[0] in ("methods", "scenes"):
        yield from _tensors(vars(x), seen)


@pytest.fixture(scope="module")
def tiny_setup():
    from references.gbuffer import make_gbuffer
    from scenes.library import get_scene
    from scenes.sequences import make_sequence

    scene = get_scene("sphere_plane", "test")
    frame = make_sequence(scene, "V", 1, 0)[0]
    return scene, frame, make_gbuffer(scene, frame, 1)


def test_to_moves_every_runtime_tensor_and_leaves_the_original(tiny_setup):
    """``Method.to`` on the meta device (no data, every device check applies): every tensor of the
    copy moved, every tensor of the original (and of the shared scene) stayed."""
    import torch

    scene, frame, gb = tiny_setup
    m = get_method("triple_product")(level=1)
    m.precompute(scene)
    before = [t.device for t in _tensors(m)]
    moved = m.to("meta")
    assert all(t.device.type == "meta" for t in _tensors(moved))
    assert len(list(_tensors(moved))) == len(before) > 10
    assert [t.device for t in _tensors(m)] == before and scene.geometry().V.device.type == "cpu"
    assert gb.to("meta").normal.device.type == "meta" and gb.to("cpu") is gb
    assert torch.equal(m.to("cpu").render(frame, gb), m.render(frame, gb))


# Every method on CUDA when there is one (skipped otherwise); on CPU one cheap method checks ``to``.
CASES = [("triple_product", "cpu")] + [(n, "cuda") for n in ("inout", "ptt", "triple_product", "zh_shadow")]


@pytest.mark.parametrize("name,device", CASES)
def test_render_on_device_equals_cpu(tiny_setup, name, device):
    """The same code on every device (no device-only path): a render on ``device`` equals the CPU
    render to float32 round-off."""
    if device == "cuda" and not __import__("torch").cuda.is_available():
        pytest.skip("no CUDA device")
    import torch

    scene, frame, gb = tiny_setup
    small = {"inout": {"terms": 4}, "ptt": {"separate": False}, "triple_product": {"level": 1}, "zh_shadow": {}}
    m = get_method(name)(**small[name])
    m.precompute(scene)
    ref = m.render(frame, gb)
    img = m.to(device).render(frame, gb.to(device)).cpu()
    assert (img - ref).abs().max() <= 1e-5 * ref.abs().max().clamp_min(1e-30)
