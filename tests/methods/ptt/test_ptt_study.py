"""Sun 2007 Fig. 8, Figs. 9–10 and the terms-vs-exponent row as study outputs (`methods.ptt.study`).

Image figures run on alcove/test with the study's BASE_CONFIG (64 rays, 6×16×16 direct cube map;
the Fig. 11 test's settings), 256-spp Mitsuba references (cached on disk). Every tolerance below is
a measured number plus margin; the measurement is in its comment.
"""
from __future__ import annotations

import math

import pandas as pd
import pytest
import torch

from methods.ptt import study as S
from methods.ptt.brdf_tensor import hosvd_error_grid

# -- Fig. 8 ---------------------------------------------------------------------------------------
# Measured (n₁ = 1, 2, 4, 8, 16 = full; with / without the PTT's separated lobes): error vs the
# full-resolution image 0.0045, 0.0018, 0.00046, 0.00010, 0 — about ÷4 per doubling, i.e. 19 %,
# 7.6 %, 1.9 %, 0.42 % of the mean indirect radiance (0.024). Allow 1 % at n₁ = 8 (the paper's).
FIG8_REL_FULL_AT_8 = 0.01
# Indirect part vs Mitsuba's (noise floor 0.0048): 0.0078, 0.0064, 0.0061, 0.0061, 0.0061 —
# flat from n₁ = 4 on (0.6 % apart); allow 2 % between n₁ = 4 and 8 and between 8 and full.
FIG8_FLAT = 0.02
# ... while n₁ = 1 is clearly worse: 28 % above n₁ = 8; require 10 %.
FIG8_COARSE_WORSE = 1.10
# Mean indirect radiance at n₁ = 8 vs Mitsuba's: 0.02422 vs 0.02489 (−2.7 %) without the PTT's
# separated lobes, 0.02383 (−4.3 %) with them (PTT default since 2026-11-22); allow 8 %.
FIG8_MEAN_BIAS = 0.08


def _no_lobes() -> dict:
    """PTT config without the run-time separated lobes (Sun §4.1) when the PTT has them: they do
    not touch T¹ (what Figs. 8–10 vary) and cost ≈ 1.5 s per precompute. The measured numbers
    below hold with and without them (differences noted)."""
    import inspect

    from methods.ptt.method import PTT

    return {"separate": False} if "separate" in inspect.signature(PTT).parameters else {}


@pytest.fixture(scope="module")
def fig8(tmp_path_factory):
    out = tmp_path_factory.mktemp("fig8")
    return S.fig8_lighting_resolution("alcove", "test", light_res=(1, 4, 8), full=True, config=_no_lobes(),
                                      out_dir=out), out


def test_fig8_one_bounce_error_flattens_with_lighting_resolution(fig8):
    df, _ = fig8
    df = df.set_index("light_res_1")
    assert list(df.index) == [1, 4, 8, 16] and df.loc[16, "full"]
    vs_full = df["rmse_vs_full"].to_numpy()
    print("fig8 rmse vs full", vs_full, "indirect vs ref", df["rmse_indirect_vs_ref"].to_numpy())
    assert all(a > b for a, b in zip(vs_full, vs_full[1:])), vs_full  # strictly closer to full
    assert vs_full[-1] == 0.0
    assert df.loc[8, "rel_vs_full"] <= FIG8_REL_FULL_AT_8
    ind = df["rmse_indirect_vs_ref"]
    assert abs(ind[4] - ind[8]) <= FIG8_FLAT * ind[8] and abs(ind[8] - ind[16]) <= FIG8_FLAT * ind[16]
    assert ind[1] >= FIG8_COARSE_WORSE * ind[8]
    assert abs(df.loc[8, "indirect_mean"] - df.loc[8, "ref_indirect_mean"]) <= FIG8_MEAN_BIAS * df.loc[8, "ref_indirect_mean"]
    # direct + 1 bounce vs Mitsuba cannot beat the reference's own noise by much: a sanity floor
    assert (df["rmse_vs_ref"] >= 0.5 * df["ref_floor"]).all()
    # the T¹ size grows as L = 6 n₁²
    assert (df["T1_bytes"] / df["L"]).nunique() == 1


def test_fig8_writes_csv_and_png(fig8):
    df, out = fig8
    for f in ("fig8.csv", "fig8.png", "fig8_images.png"):
        assert (out / f).stat().st_size > 0, f
    back = pd.read_csv(out / "fig8.csv")
    assert back["light_res_1"].tolist() == df["light_res_1"].tolist()
    assert back["rmse_vs_ref"].to_numpy() == pytest.approx(df["rmse_vs_ref"].to_numpy())


# -- Figs. 9–10 -----------------------------------------------------------------------------------
# On a 6×4×4 one-bounce lighting (L = 96, a third of the cost of the paper's 6×8×8) and one
# cluster (alcove/test has 1014 vertices: Sun's "one cluster per 1000 vertices").
LR = 4
# Full rank reproduces the dense tensor to float round-off (float64 fit, stored float32).
EXACT_TENSOR = 1e-10
# ... and the dense image: RMSE ≈ 2e-8 measured at n₁ = 8 (radiance ≈ 0.15).
EXACT_IMAGE = 1e-6
LIGHT_VS_EIGEN = 2.0


@pytest.fixture(scope="module")
def fig9():
    return S.fig9_tensor_error("alcove", "test", light_res_1=LR, clusters=1, config=_no_lobes(),
                               eigenvectors=(1, 16, None), light_dims=(1, 16, None))


def test_fig9_tensor_error_monotone_and_exact_at_full_rank(fig9):
    df = fig9
    tab = df.pivot(index="eigenvectors", columns="light_dim", values="rel_sq_err").sort_index().sort_index(axis=1)
    print("fig9 rel_sq_err\n", tab)
    v = tab.to_numpy()
    # one cluster: nested truncations → non-increasing along both axes (tiny slack for round-off)
    assert (v[1:, :] <= v[:-1, :] * (1 + 1e-9) + 1e-12).all()
    assert (v[:, 1:] <= v[:, :-1] * (1 + 1e-9) + 1e-12).all()
    assert v[-1, -1] < EXACT_TENSOR
    assert v[0, 0] > 0.1  # rank (1, 1) is a real approximation (measured 0.86)
    full = df[df["full_rank"]].iloc[0]
    assert full["eigenvectors"] == full["vertices"] and full["light_dim"] == 6 * LR * LR
    assert (df["bytes"] > 0).all()


@pytest.fixture(scope="module")
def fig10(tmp_path_factory):
    out = tmp_path_factory.mktemp("fig10")
    combos = ((16, None), (64, None), (None, 4), (None, 16), (None, None))
    return S.fig10_compression_images("alcove", "test", light_res_1=LR, clusters=1, combos=combos,
                                      config=_no_lobes(), out_dir=out), out


def test_fig10_image_error_falls_with_eigenvectors_and_light_dim(fig10):
    df, out = fig10
    d = df.set_index("label")
    print(df[["label", "rmse_vs_dense", "rel_vs_dense", "rmse_vs_ref"]])
    e_sweep = d.loc[["16/full", "64/full", "full/full"], "rmse_vs_dense"].to_numpy()
    m_sweep = d.loc[["full/4", "full/16", "full/full"], "rmse_vs_dense"].to_numpy()
    assert all(a > b for a, b in zip(e_sweep, e_sweep[1:])), e_sweep
    assert all(a > b for a, b in zip(m_sweep, m_sweep[1:])), m_sweep
    assert d.loc["full/full", "rmse_vs_dense"] < EXACT_IMAGE
    # Sun §4.3: the lighting dimension matters less than the eigenvectors — at equal rank 16,
    # truncating the lighting costs 5.6× less image error than truncating the vertices (measured
    # 6.3e-4 vs 3.5e-3); require 2×.
    assert LIGHT_VS_EIGEN * d.loc["full/16", "rmse_vs_dense"] < d.loc["16/full", "rmse_vs_dense"]
    dense_ref = d.loc["dense", "rmse_vs_ref"]
    assert d.loc["full/full", "rmse_vs_ref"] == pytest.approx(dense_ref, rel=1e-4)
    # compression only adds error on top of the dense PTT's (in quadrature, within the reference noise)
    assert d.loc["full/4", "rmse_vs_ref"] > dense_ref  # measured 0.0152 vs 0.0140
    assert (d.drop(index="dense")["bytes"] > 0).all()
    for f in ("fig10.csv", "fig10.png", "fig10_images.png"):
        assert (out / f).stat().st_size > 0, f


# -- terms vs exponent ----------------------------------------------------------------------------
# Measured on DiskGrid 32 (812 directions), n_ωi for rel_sq_err <= 1 %:
#   s        1   2   4   8  16  32  64 | 256
#   plain    3   3   5   7  13  24  48 | 217
#   sep.    39  47  56  66  77  86  91 |  56
# i.e. the Gaussian lobes (σ <= 7°) are narrower than every Blinn–Phong lobe of the ladder, so
# separation leaves a narrow, high-rank remainder; it pays only beyond s ≈ 128.
TERMS_LADDER = (4.0, 16.0, 64.0)


def test_error_curve_equals_truncated_hosvd():
    from scenes.materials import BlinnPhong

    c = S.tensor_error_curve(8.0)
    g = S._grid(S.TERMS_GRID_N)
    F = BlinnPhong(kd=0.0, ks=1.0, s=8.0).eval(g.dirs[None], g.dirs[:, None])[..., 0][None]
    ranks = [1, 3, 7, 50]
    ref = hosvd_error_grid(F, [1], ranks)
    n2 = float(F.square().sum())
    for b in ranks:
        assert c[b - 1].item() == pytest.approx(ref[(1, b)] / n2, rel=1e-8, abs=1e-14)
    assert c.numel() == g.N and c[-1].item() == 0.0
    assert (c[1:] <= c[:-1] + 1e-15).all()


@pytest.mark.parametrize("separated", [False, True])
def test_terms_needed_is_the_smallest_rank_and_grows_with_exponent(separated):
    fn = S.terms_needed_separated if separated else S.terms_needed
    terms = []
    for s in TERMS_LADDER:
        r = fn(s, S.TERMS_TARGET)
        c = S.tensor_error_curve(s, separated=separated)
        n = r.terms
        assert r.method == ("ptt_separated" if separated else "ptt") and r.exponent == s and r.target == S.TERMS_TARGET
        assert c[n - 1] <= S.TERMS_TARGET and (n == 1 or c[n - 2] > S.TERMS_TARGET)
        terms.append(n)
    print("terms", separated, terms)
    assert all(a <= b for a, b in zip(terms, terms[1:])) and terms[-1] > terms[0]


def test_lobe_separation_pays_only_for_shiny_lobes():
    """Measured finding (table above): at s <= 64 separation needs MORE n_ωi; at s = 256 fewer."""
    for s in (4.0, 64.0):
        assert S.terms_needed_separated(s).terms > S.terms_needed(s).terms
    assert 2 * S.terms_needed_separated(256.0).terms < S.terms_needed(256.0).terms


def test_terms_contributors_plug_into_the_study(monkeypatch):
    from methods import studies

    # the module registered both rows at import (methods.ptt.study)
    assert studies.TERMS_CONTRIBUTORS["ptt"].fn is S.terms_needed
    assert studies.TERMS_CONTRIBUTORS["ptt_separated"].fn is S.terms_needed_separated
    recs = studies.terms_table([4.0, 16.0], ["ptt", "ptt_separated"])
    assert [(r.method, r.exponent) for r in recs] == [("ptt", 4.0), ("ptt", 16.0), ("ptt_separated", 4.0),
                                                      ("ptt_separated", 16.0)]
    assert all(r.terms >= 1 for r in recs)


@pytest.mark.parametrize("kw", [dict(exponent=0.0), dict(exponent=math.inf), dict(exponent=4.0, target=0.0),
                                dict(exponent=4.0, target=1.0)])
def test_terms_bad_input_raises(kw):
    with pytest.raises(ValueError):
        S.terms_needed(**kw)


def test_bad_figure_arguments_raise():
    with pytest.raises(ValueError):
        S.fig8_lighting_resolution(light_res=(3,))
    with pytest.raises(ValueError):
        S.fig8_lighting_resolution(light_res=(32,), full=False)  # > cube_res 16
    with pytest.raises(ValueError):
        S.fig10_compression_images(combos=())


def test_one_cluster_error_grid_equals_per_cell_compression():
    """The Fig. 9 fast path (one full-rank fit + Pythagoras) equals `compress_ptt` per cell."""
    from methods.ptt.compress import compress_ptt, relative_error

    g = torch.Generator().manual_seed(3)
    T = torch.einsum("va,adb,lb->vdl", torch.randn(40, 6, generator=g), torch.randn(6, 10, 7, generator=g),
                     torch.randn(24, 7, generator=g)) + 0.05 * torch.randn(40, 10, 24, generator=g)
    grid = S._one_cluster_error_grid(T, seed=0)
    for e, m in ((1, 1), (3, 5), (6, 24), (40, 2), (40, 24)):
        ct = compress_ptt(T.double(), clusters=1, eigenvectors=e, light_dim=m)
        assert grid[e - 1, m - 1].item() == pytest.approx(relative_error(T.double(), ct), rel=1e-9, abs=1e-12)
        assert S._tucker2_bytes(40, 10, 24, e, m, itemsize=8) == sum(t.numel() * t.element_size() for t in ct.tensors())


def test_run_all_writes_the_brdf_side_figures_too(tmp_path, monkeypatch):
    """The `ptt-figures` study also writes Figs. 5 (CT and BP) and 6 (the image figures are
    stubbed out here: they have their own tests above)."""
    for name in ("fig8_lighting_resolution", "fig9_tensor_error", "fig10_compression_images", "terms_study"):
        monkeypatch.setattr(S, name, lambda *a, **k: None)
    files = S.run_all(tmp_path, quick=True)
    assert sorted(p.name for p in files) == sorted(["fig5_ct.csv", "fig5_ct_nosep.png", "fig5_ct_sep.png",
                                                    "fig5_bp.csv", "fig5_bp_nosep.png", "fig5_bp_sep.png",
                                                    "fig6_bp.csv"])
    f5 = pd.read_csv(tmp_path / "fig5_ct.csv")
    t = f5.pivot_table(index=["n_h", "n_omega"], columns="separated", values="rel_sq_err")
    assert (t[True] < t[False]).all()  # Sun Fig. 5: separation lowers the tensor error
    f6 = pd.read_csv(tmp_path / "fig6_bp.csv")
    tot = f6.groupby("n_lobes")["total_rel_sq_err"].first()
    assert tot.iloc[-1] < tot.iloc[0]  # Sun Fig. 6: more lobe components, better approximation
