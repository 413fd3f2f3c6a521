"""Ma 2006 Figs. 7–8 (study ``ma-fig7-8``: `truncation_sweep` + `plot_truncation_sweep`) and
Tables 1–2 (study ``ma-tables``)."""
import csv

import pytest

from methods.triple_product.study import fig7_8, tables


def test_truncation_sweep_writes_figure_and_error_falls(tmp_path):
    # quick: sphere_plane/test, level 2, n = 10 / 40 / 160, adaptive and top, 256-spp Mitsuba reference
    files = fig7_8(tmp_path, quick=True)
    assert [f.name for f in files] == ["fig7_8.csv", "fig7_8.png"] and all(f.stat().st_size > 0 for f in files)
    rows = list(csv.DictReader(open(files[0])))
    assert len(rows) == 6
    for sel in ("adaptive", "top"):
        e = [float(r["rmse_vs_all"]) for r in rows if r["selection"] == sel]
        assert e[0] > e[1] > e[2] > 0, (sel, e)            # Figs. 7–8: the truncation error falls with n
        m = [float(r["rmse_vs_reference"]) for r in rows if r["selection"] == sel]
        assert m[2] < m[0], (sel, m)                       # and so does the error against Mitsuba


def test_tables_study_writes_the_paper_numbers(tmp_path):
    csv_path, txt = tables(tmp_path)
    rows = {r["setting"]: r for r in csv.DictReader(open(csv_path))}
    assert float(rows["isotropic"]["local_MiB"]) == pytest.approx(170.0, rel=0.01)   # §4.1: 170 MB
    assert float(rows["anisotropic"]["local_MiB"]) == pytest.approx(480.0, rel=0.01)  # 480 MB
    assert float(rows["isotropic"]["global_paper_GB"]) == pytest.approx(82.0, rel=0.01)  # 82 GB
    assert "170.0" in txt.read_text()
