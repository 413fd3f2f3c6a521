"""Lat-long texel addressing (`methods.core.latlong`): the quad look-up against the reference."""
from __future__ import annotations

import torch


def test_quad_texels_bilinear_equals_envmap_lookup():
    """`latlong.quad_taps` + `quad_texels` rows weighted by `quad_lane_weights` = the reference
    bilinear look-up (`scenes.envmap.bilinear_lookup` through `EnvMap.radiance`) to float32 round-off,
    wrap-around columns and the pole rows included."""
    from methods.core.latlong import quad_lane_weights, quad_lanes, quad_taps, quad_texels
    from scenes.envmap import EnvMap, direction_to_uv

    g = torch.Generator().manual_seed(0)
    H, W = 6, 10
    env = EnvMap(torch.rand(H, W, 3, generator=g) * 4)
    d = torch.nn.functional.normalize(torch.randn(4000, 3, generator=g), dim=-1)
    d = torch.cat([d, torch.tensor([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0], [1.0, 0.0, -1e-7]])])
    u, v = direction_to_uv(d)
    idx, fx, fy = quad_taps(u.float(), v.float(), H, W)
    Q = quad_texels(env.periodic_texels(planes=True), H, W)
    acc = Q[idx.long()] * quad_lane_weights(fx, fy, quad_lanes())
    got = torch.stack([acc[:, 4 * c:4 * c + 4].sum(-1) for c in range(3)], -1)
    want = env.radiance(d)
    assert idx.dtype == torch.int32 and int(idx.min()) >= 0 and int(idx.max()) < Q.shape[0]
    assert (got - want).abs().max() <= 1e-6 * want.abs().max()
