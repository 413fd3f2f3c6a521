"""The roofline count's shared terms (``methods.base.FrameCost``, session 36): the G-buffer's bytes per
sample are those of its arrays (the hit flag a 1-byte bool, not a 4-byte word), and a frame's output is
the (H, W, 3) float32 image ``render`` returns — not the (P, 3) per-sample radiance, which a frame may
average as it shades (before: 3·P + 12·(P − H·W) bytes too many, 3.1 MB a bench frame). Every method
counts its output through ``output_bytes``: with ``pixels`` = H·W its bytes are 12·(P − H·W) fewer than
without (the upper bound), its flops the same."""
from __future__ import annotations

import pytest

from methods.base import GBUFFER_BYTES_PER_SAMPLE, GBUFFER_HIT_BYTES, output_bytes
from methods.registry import get_method
from references.gbuffer import make_gbuffer
from scenes.library import get_scene
from scenes.sequences import make_sequence
from testing.small_configs import CASES

# one case per method's own count (the other CASES share these counts' code)
_CASES = ("inout", "inout-vertex", "oracle", "ptt", "sh_prt", "triple_product", "zh_shadow")


def test_gbuffer_bytes_per_sample_are_the_arrays():
    scene = get_scene("sphere_plane", "test")
    frame = make_sequence(scene, "V", 1, 0)[0]
    gb = make_gbuffer(scene, frame, 2)
    P = gb.num_samples
    per_sample = {k: getattr(gb, k).element_size() * getattr(gb, k).numel() // P
                  for k in ("normal", "wo", "hit", "face", "bary")}
    assert per_sample["hit"] == GBUFFER_HIT_BYTES == 1
    assert sum(per_sample.values()) == GBUFFER_BYTES_PER_SAMPLE


def test_output_bytes():
    assert output_bytes(400, 100) == 1200
    assert output_bytes(400, None) == 4800           # no pixel count: the per-sample upper bound
    for bad in (401, -1, 2.0, True):
        with pytest.raises(ValueError):
            output_bytes(400, bad)


@pytest.mark.parametrize("case", _CASES)
def test_frame_cost_counts_the_image(case):
    name, scene_name, config = CASES[case]
    scene = get_scene(scene_name, "test")
    frame = make_sequence(scene, "V", 1, 0)[0]
    gb = make_gbuffer(scene, frame, 2)                 # 2 × 2 samples a pixel: P = 4·H·W
    m = get_method(name)(**config)
    m.precompute(scene)
    m.render(frame, gb)
    P, HW = gb.num_samples, gb.height * gb.width
    assert P == 4 * HW
    for kind in ("V", "L"):
        upper = m.frame_cost(kind, P)
        image = m.frame_cost(kind, P, pixels=HW)
        assert upper is not None and image is not None, kind
        assert upper.bytes - image.bytes == 12 * (P - HW), kind
        assert upper.flops == image.flops, kind
    with pytest.raises(ValueError):
        m.frame_cost("V", P, pixels=P + 1)


def test_frame_cost_bound_has_a_traversal_roof():
    """Session 38: ``FrameCost.rays`` (compulsory shadow rays) is a third roof, bounded by a measured
    ray rate; without a rate (or with no rays) it bounds nothing."""
    from methods.base import FrameCost

    c = FrameCost(bytes=100, flops=50, rays=30)
    assert c.bound(100.0, 100.0) == (1.0, "memory")                   # no rate: bytes / bandwidth
    assert c.bound(100.0, 10.0) == (5.0, "compute")
    assert c.bound(100.0, 100.0, ray_rate=10.0) == (3.0, "traversal")
    assert c.bound(100.0, 100.0, ray_rate=60.0) == (1.0, "memory")    # traversal 0.5 s < memory
    assert FrameCost(100, 50).bound(100.0, 100.0, ray_rate=1e-9) == (1.0, "memory")  # no rays
    with pytest.raises(ValueError):
        FrameCost(1, 1, rays=-1)
