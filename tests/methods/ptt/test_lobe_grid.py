"""``methods.ptt.lobe_grid``: the scenes' lobe families with their direction-only factors cached
(the run time's BRDF navigation, Sun 2007 §3.1) equal the materials' own evaluation bit for bit."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from methods.ptt import transport as tp
from methods.ptt.lobe_grid import GridLobes
from scenes.materials import BlinnPhong, CookTorrance, Lambert, Phong, TorranceSparrow, Ward


def _pairs(n: int, seed: int, dtype) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    wi = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=g, dtype=torch.float64), dim=-1)
    wo[: n // 2, 2] = wo[: n // 2, 2].abs()  # half the pairs above the horizon on both sides
    wi[: n // 4, 2] = wi[: n // 4, 2].abs()
    wi[n // 8: n // 4] = torch.stack(  # mirror pairs (the lobes' peaks)
        [-wo[n // 8: n // 4, 0], -wo[n // 8: n // 4, 1], wo[n // 8: n // 4, 2]], -1)
    return wi.to(dtype), wo.to(dtype)


def _lobes(rng: np.random.Generator):
    for _ in range(6):
        yield tp._spec_lobe(Phong(s=float(np.exp(rng.uniform(np.log(0.5), np.log(2000.0))))))
        yield tp._spec_lobe(BlinnPhong(s=float(np.exp(rng.uniform(np.log(0.5), np.log(2000.0))))))
        yield tp._spec_lobe(CookTorrance(m=float(np.exp(rng.uniform(np.log(0.02), np.log(1.0)))),
                                         F0=float(rng.uniform(0.0, 1.0))))
    yield tp._spec_lobe(Phong(s=1.0))
    yield tp._spec_lobe(CookTorrance(m=1.0, F0=0.0))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_grid_lobes_equal_the_materials_eval_bitwise(dtype):
    """Random parameters of every family PTT takes, on random pairs (some below the horizon, some
    at the mirror direction) and on the fit grid's own pairs: ``torch.equal`` with ``eval``."""
    wi, wo = _pairs(4096, 0, dtype)
    grids = [GridLobes(wi, wo)]
    b = tp.LobeBasis([BlinnPhong(s=8.0)])
    b._fit(BlinnPhong(s=9.0))
    grids.append(b._fold[0])
    rng = np.random.default_rng(1)
    for lobe in _lobes(rng):
        for g in grids:
            if g.wi.dtype != dtype:
                continue
            want = lobe.eval(g.wi, g.wo)[..., 0]
            got = g.eval(lobe)
            assert got.dtype == want.dtype
            assert torch.equal(got, want), (lobe, float((got - want).abs().max()))
            assert torch.equal(g.eval(lobe), want)  # the cached factors are not modified


def test_grid_lobes_project_equals_the_product_with_eval():
    """`GridLobes.project` (the lobe once per distinct direction factor, A's columns summed per
    value) equals ``A @ eval(lobe)`` to float64 round-off: random parameters of every family on
    random pairs (masked pairs and pairs below the horizon: ``up`` set), on the pairs repeated
    (distinct values shared by many pairs) and on the fit grid's own pairs, for two operators A
    (the per-family cache follows A); other families and weights fall back to the product."""
    wi, wo = _pairs(2048, 4, torch.float64)
    grids = [GridLobes(wi, wo), GridLobes(torch.cat([wi, wi.flip(0), wi]), torch.cat([wo, wo.flip(0), wo]))]
    b = tp.LobeBasis([BlinnPhong(s=8.0)])
    b._fit(BlinnPhong(s=9.0))
    grids.append(b._fold[0])
    assert grids[0].up is not None and grids[2].up is None
    rng = np.random.default_rng(5)
    g = torch.Generator().manual_seed(6)
    for grid in grids:
        n = grid.wi.shape[0]
        for A in (torch.randn(4, n, generator=g, dtype=torch.float64), torch.rand(3, n, generator=g, dtype=torch.float64)):
            for lobe in list(_lobes(rng)) + [tp._spec_lobe(TorranceSparrow(sigma=0.3)), BlinnPhong(kd=0.2, ks=0.5, s=20.0)]:
                want = A @ grid.eval(lobe)
                got = grid.project(lobe, A)
                assert got.shape == want.shape and got.dtype == want.dtype
                tol = 1e-13 * float((A.abs() @ grid.eval(lobe).abs()).max())
                assert float((got - want).abs().max()) <= tol, (lobe, float((got - want).abs().max()), tol)
    fam = grids[1]._groups("phong", A)[0]
    assert fam.numel() < grids[1].wi.shape[0] // 2  # the repeated pairs share their factor values


def test_grid_lobes_fall_back_for_other_families_and_weights():
    wi, wo = _pairs(512, 2, torch.float64)
    g = GridLobes(wi, wo)
    for m in (tp._spec_lobe(TorranceSparrow(sigma=0.3)), tp._spec_lobe(Ward(ax=0.2, ay=0.4)),
              BlinnPhong(kd=0.2, ks=0.5, s=20.0), Phong(kd=0.0, ks=(1.0, 0.5, 0.5), s=7.0), Lambert(kd=0.3)):
        assert torch.equal(g.eval(m), m.eval(wi, wo)[..., 0])


def test_fit_matches_the_unfolded_least_squares():
    """`LobeBasis._fit` (folded normal equations, GridLobes) against the plain least squares of the
    RGB BRDF on the full (o, i) grid, for perturbed materials of each family and a 3-lobe basis."""
    from scenes.sequences import perturb_material

    mats = [BlinnPhong(kd=(0.7, 0.68, 0.62), ks=0.25, s=60.0), CookTorrance(kd=0.06, ks=0.6, m=0.25),
            Phong(kd=(0.45, 0.3, 0.18), ks=0.1, s=10.0)]
    b = tp.scene_basis(mats)
    dirs, w = tp.disk_grid(b.fit_res)
    inside = w > 0
    d, w = dirs[inside], w[inside]
    wi, wo = d[None, :, :].expand(d.shape[0], -1, 3), d[:, None, :].expand(-1, d.shape[0], 3)
    wt = (w[None, :] * d[None, :, 2] * w[:, None]).sqrt()
    B = (b.eval(wi, wo) * wt[..., None]).reshape(-1, b.n_P)
    rng = np.random.default_rng(3)
    for _ in range(3):
        for m0 in mats:
            m = perturb_material(m0, rng)
            f = (m.eval(wi, wo).double() * wt[..., None]).reshape(-1, 3)
            want = torch.linalg.lstsq(B.T @ B, B.T @ f, driver="gelsd").solution
            torch.testing.assert_close(b._fit(m), want, rtol=1e-9, atol=1e-10)
