"""Mahajan 2008 analysis figures as studies (`methods.inout.study`): Figs. 3A, 2/5 and 7C at quick
sizes, and the line fit they report."""
from __future__ import annotations

import csv

import pytest
import torch

from methods.inout import study as S

# Singular values vs the exact Phong F_l on the quick 16² sphere grid (measured 0.011 at s = 8).
SV_VS_FL = 0.02


@pytest.fixture
def one_torch_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def test_fit_line():
    a, b = S.fit_line([1, 2, 3], [5, 7, 9])
    assert a == pytest.approx(2) and b == pytest.approx(3)
    with pytest.raises(ValueError):
        S.fit_line([1], [2])


def test_fig3a_terms_grow_linearly_with_exponent(tmp_path, one_torch_thread):
    files, summary = S.fig3a_k_vs_s(tmp_path, s_values=S.QUICK.s_values, n=S.QUICK.n)
    assert [f.name for f in files] == ["k_vs_s.csv", "k_vs_s.png"]
    rows = list(csv.DictReader(open(tmp_path / "k_vs_s.csv")))
    K = [int(r["K_sphere"]) for r in rows]
    assert K == sorted(K) and K[0] < K[-1]
    for r in rows:  # the quick grid (16²) does not cap K at s <= 8
        assert abs(int(r["K_sphere"]) - int(r["K_sphere_exact"])) <= 2
    # Fig. 3A: the sphere needs more terms per unit s than the hemisphere (paper: 5s vs 2.5s)
    assert summary["slope_sphere"] > summary["slope_hemisphere"] > 0


def test_fig2_5_and_fig7c_write_their_tables(tmp_path, one_torch_thread):
    files = S.fig2_5_singular_values(tmp_path, sv_s=(8,), n=S.QUICK.n)
    rows = list(csv.DictReader(open(files[0])))
    assert {r["domain"] for r in rows} == {"sphere", "hemisphere"}
    sph = [r for r in rows if r["domain"] == "sphere"]
    # Fig. 2: band l appears 2l+1 times on the sphere and σ_k follows the exact F_l of its band
    # (16² grid, s = 8: measured max |σ − F_l| 0.011 over l <= 2)
    assert [int(r["l"]) for r in sph[:9]] == [0, 1, 1, 1, 2, 2, 2, 2, 2]
    assert max(abs(float(r["sigma"]) - float(r["F_l"])) for r in sph[:9]) <= SV_VS_FL
    files, summary = S.fig7c_torrance_sparrow(tmp_path, sigmas=(0.3, 0.4), n=S.QUICK.n, n_ts_check=0)
    assert [f.name for f in files] == ["ts_k_vs_lstar.csv", "ts_k_vs_lstar.png"]
    ts = summary["ts"]
    assert ts[0]["K"] > ts[1]["K"]  # rougher (larger σ) → fewer terms
    assert "ts_slope" in summary
