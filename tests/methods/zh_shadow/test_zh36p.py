"""Session 36 (zh36p): the paper config's material / lighting frames — the shading tables' operator from
its band parts (`runtime.TABLE_BANDS`) against the operator built from the triple products."""
from __future__ import annotations

import pytest
import torch

from methods.zh_shadow import ZHShadow
from methods.zh_shadow import runtime as rt

SMALL = dict(train_poses=4, n_dirs=64, fit_iters=0)
# float64 round-off in the operator, then the float32 cast: each entry equal or one float32 ulp apart
# (entries that are zero but for float64 round-off: the absolute term)
ULP32 = 2.0 ** -23
# Images from tables one ulp apart: float32 round-off of the sums (images peak at ~2)
IMAGE_TOL = 1e-6


@pytest.mark.parametrize("order", (2, 3, 4, 5))
def test_band_table_operator_equals_direct(order, monkeypatch):
    """`runtime.table` by `_table_operator_b` (Σ_b F_b(α) A_b) equals it by the direct operator
    (`_table_operator`): the operator to float64 round-off, the float32 table to one ulp per entry —
    diffuse and specular, exponents from 1 to 500. A band left out or a band's factor on the wrong band
    breaks it."""
    torch.manual_seed(order)
    n2 = order * order
    light = torch.randn(n2, 3)
    for diffuse, alphas in ((True, (1.0,)), (False, (1.0, 2.0, 3.7, 10.0, 33.3, 128.0, 500.0))):
        for a in alphas:
            A = rt._table_operator(order, a, diffuse)
            Ab = rt._table_operator_b(order, a, diffuse)
            assert Ab.shape == A.shape and Ab.dtype == A.dtype
            assert (Ab - A).abs().max().item() <= 1e-12 * A.abs().max().item()
            monkeypatch.setattr(rt, "TABLE_BANDS", False)
            W0 = rt.table(light, a, diffuse=diffuse)
            monkeypatch.setattr(rt, "TABLE_BANDS", True)
            W1 = rt.table(light, a, diffuse=diffuse)
            assert W1.shape == W0.shape and W1.dtype == W0.dtype and W1.is_contiguous()
            bound = ULP32 * W0.abs() + 1e-12 * W0.abs().max()
            assert bool(((W1 - W0).abs() <= bound).all()), (order, diffuse, a)


@pytest.mark.parametrize("kind", ("VB", "VBL", "VL"))
def test_band_tables_frames(zh_scene, kind):
    """Material and lighting frames of the creature (plane path, fused pass) with the band-part tables
    equal the direct operator's frames to float32 round-off."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    m = ZHShadow(**SMALL)
    m.precompute(zh_scene("creature"))
    fast, slow = m.with_render_config(), m.with_render_config()
    for fr in make_sequence(m.scene, kind, 4, seed=5):
        gb = make_gbuffer(m.scene, fr, 2)
        a = fast.render(fr, gb)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(rt, "TABLE_BANDS", False)
            b = slow.render(fr, gb)
        assert fast.last_path == slow.last_path
        assert b.abs().max() > 0.05
        assert (a - b).abs().max().item() <= IMAGE_TOL * b.abs().max().item(), (kind, fr.index)
