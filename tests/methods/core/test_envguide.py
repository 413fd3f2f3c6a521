"""The guide-table CDF search (`methods.core.envguide`) returns exactly ``scenes.envmap.count_le``'s
cell for every u, and `sample_cells_at` exactly ``sample_cells``' samples (the oracle's light
samples stay bit-identical, issue 14)."""
from __future__ import annotations

import pytest
import torch

import scenes.envmap as E
from methods.core.envguide import (GUIDE_STEPS, fix_unguided, guide_buckets, guide_table, guided_count_le,
                                   sample_cells_at)
from methods.core.fused import fused

_guided = fused(guided_count_le, options={"assert_indirect_indexing": False})


def _probe_us(cdf: torch.Tensor, n: int = 20000) -> torch.Tensor:
    """Random float32 and float64 u, the CDF's own values and their float64 neighbours, bucket
    edges, 0, 1 and just below 1, and a few out of [0, 1]."""
    g = torch.Generator().manual_seed(3)
    G = guide_buckets(cdf.numel())
    c = cdf[torch.randint(0, cdf.numel(), (n,), generator=g)]
    edges = torch.randint(0, G + 1, (n,), generator=g).double() / G
    one = torch.tensor([1.0], dtype=torch.float64)
    special = torch.tensor([0.0, 1.0, -0.0, -1e-300, -0.5, 1.5, float("nan")], dtype=torch.float64)
    return torch.cat([torch.rand(n, generator=g).double(), torch.rand(n, generator=g, dtype=torch.float64),
                      c, torch.nextafter(c, -one), torch.nextafter(c, one), edges, torch.nextafter(edges, -one),
                      torch.nextafter(edges, one), special, torch.nextafter(one, 0 * one),
                      torch.tensor([1 - 2.0 ** -24])])


def _maps():
    for name in E.PROCEDURAL_NAMES + E.PROBE_NAMES:
        yield name, E.named(name, height=64)
    dark = torch.rand(32, 64, 3, generator=torch.Generator().manual_seed(1))
    dark[:12] = 0.0            # zero-probability rows: long runs of tied CDF values
    dark[20:, 10:50] = 0.0
    dark[5, 7] = 1e4           # a sun: one cell holds most of the mass
    yield "ties", E.EnvMap(dark)


@pytest.mark.parametrize("compiled", [True, False], ids=["compiled", "eager"])
def test_guided_search_equals_count_le(compiled, monkeypatch):
    monkeypatch.setenv("PRTBENCH_COMPILE", "1" if compiled else "0")
    for name, env in _maps():
        cdf = env._tables()[0]
        guide = guide_table(cdf)
        assert guide_table(cdf) is guide  # cached per table
        assert guide.shape == (guide_buckets(cdf.numel()) + 1,) and int(guide[-1]) == cdf.numel()
        x = _probe_us(cdf)
        want = E.count_le(cdf, x)
        k, ok = (_guided if compiled else guided_count_le)(x, cdf, guide)
        assert torch.equal(k[ok], want[ok]), name
        frac = ok[:20000].float().mean().item()  # of uniform u (the CDF's own values favour dense runs)
        assert frac > (0.5 if name == "ties" else 0.9), (name, frac)  # the guide does most of the work
        assert not ok[~((x >= 0) & (x <= 1))].any()  # out of range / NaN: searched again
        k32 = k.to(torch.int32)
        fix_unguided(k32, ok, x, cdf, E.count_le)
        assert torch.equal(k32.long(), want), name
        # and searchsorted (count_le's own definition) on the in-range ones
        inr = (x >= 0) & (x <= 1)
        assert torch.equal(k32.long()[inr], torch.searchsorted(cdf, x[inr], right=True)), name


def test_sample_cells_at_is_sample_cells():
    for name, env in _maps():
        cdf, p, omega = env._tables()
        u = torch.rand(5000, 2, generator=torch.Generator().manual_seed(7))
        R = env.to_world.double()
        d0, p0 = E.sample_cells(u, cdf, p.reshape(-1), omega, R, env.height, env.width)
        k = E.count_le(cdf, u[:, 0].double()).to(torch.int32)
        d1, p1 = sample_cells_at(k, u, cdf, p.reshape(-1), omega, R, env.height, env.width)
        assert torch.equal(d0, d1) and torch.equal(p0, p1), name


def test_guide_steps_bracket():
    assert GUIDE_STEPS >= 1 and guide_buckets(130560) == 1 << 17 and guide_buckets(2) == 2
