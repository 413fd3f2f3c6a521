"""Sun 2007 Figs. 5 and 6 (`methods.ptt.study`: BRDF tensor error with and without lobe
separation) and the registered Sun studies."""
from __future__ import annotations

import pytest

from methods.ptt.brdf_space import BlinnPhongSpace
from methods.ptt.study import PAPER_FIG5_NO_SEPARATION, fig5, fig5_grid, fig6_lobe_study, plot_fig5

# Fig. 5 setting of the tests: Cook–Torrance space (100 materials), DiskGrid(12) (112 directions).
FIG5_GRID_N = 12


def test_fig5_bad_input():
    with pytest.raises(ValueError):
        fig5_grid(BlinnPhongSpace(shininess=(1.0, 2.0)), grid_n=4, n_omega=(4, 32))


def test_fig5_writes_csv_and_pngs(tmp_path):
    df = fig5(tmp_path, BlinnPhongSpace(shininess=(5.0, 50.0, 200.0)), grid_n=8, n_h=(1, 2), n_omega=(4, 8))
    assert len(df) == 8
    names = sorted(p.name for p in tmp_path.iterdir())
    assert names == ["fig5_bp.csv", "fig5_bp_nosep.png", "fig5_bp_sep.png"]


@pytest.fixture(scope="module")
def ct_fig5():
    return fig5_grid("ct", grid_n=FIG5_GRID_N)


def test_fig5_grid_monotone_in_ranks(ct_fig5, tmp_path):
    df = ct_fig5
    assert len(df) == 2 * 6 * 4 and set(df.columns) >= {"separated", "n_h", "n_omega", "rel_sq_err"}
    for sep, g in df.groupby("separated"):
        tab = g.pivot(index="n_h", columns="n_omega", values="rel_sq_err")
        # more terms never hurt (nested truncated-HOSVD subspaces); 1e-12 allows round-off
        assert (tab.diff(axis=0).iloc[1:] <= 1e-12).all().all()
        assert (tab.diff(axis=1).iloc[:, 1:] <= 1e-12).all().all()
        assert ((tab > 0) & (tab < 1)).all().all()
    paths = plot_fig5(df, tmp_path)
    assert len(paths) == 2 and all(p.stat().st_size > 1000 for p in paths)


def test_fig5_separation_lowers_error(ct_fig5):
    """Sun 2007 §4.1/Fig. 5: with separation the error is far lower at every (n_h, n_ω), and even
    the coarsest separated setting beats the finest unseparated one."""
    t = ct_fig5.pivot_table(index=["n_h", "n_omega"], columns="separated", values="rel_sq_err")
    assert (t[True] < 0.1 * t[False]).all()
    assert t[True].max() < t[False].min()


@pytest.mark.xfail(strict=True, reason="Sun 2007 reports 0.952465 without separation at n_h = 6, "
                   "n_ωi = 32 (100 MERL fits, N_ω and normalisation unstated); we measure "
                   "rel_sq_err 0.109 on DiskGrid(12) and 0.0618 on DiskGrid(32) (N = 812) for our "
                   "generated Cook-Torrance set")
def test_fig5_paper_value_without_separation(ct_fig5):
    row = ct_fig5.query("not separated and n_h == 6 and n_omega == 32")
    assert float(row.rel_sq_err.iloc[0]) == pytest.approx(PAPER_FIG5_NO_SEPARATION, rel=0.1)


def test_fig6_more_lobes_lower_error():
    """Sun 2007 Fig. 6: "a greater number of lobe components leads to better approximations" —
    over the whole Blinn–Phong space, each added lobe lowers the total error (coarse grid)."""
    df = fig6_lobe_study("bp", grid_n=8, lobe_sets=((), (0.0,), (0.0, 7.0)))
    tot = df.groupby("n_lobes")["total_rel_sq_err"].first()
    assert list(tot.index) == [0, 1, 2]
    assert all(a > b for a, b in zip(tot, tot.iloc[1:])), tot.to_dict()
