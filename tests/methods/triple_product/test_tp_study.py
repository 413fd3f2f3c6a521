"""Ma 2006 Figs. 7–8 as a study output (`methods.triple_product.study.truncation_sweep`)."""
import csv

from methods.triple_product.study import plot_truncation_sweep, truncation_sweep


def test_truncation_sweep_writes_figure_and_error_falls(tmp_path):
    rows = truncation_sweep("sphere_plane", "test", ns=(10, 40, 160), reference="mitsuba", level=2,
                            frame_grid=(9, 16, 1), brdf_dirs=(4, 8), progress=False)
    files = plot_truncation_sweep(rows, tmp_path)
    assert [f.name for f in files] == ["fig7_8.csv", "fig7_8.png"] and all(f.stat().st_size > 0 for f in files)
    assert len(list(csv.DictReader(open(files[0])))) == 6
    for sel in ("adaptive", "top"):
        e = [r["rmse_vs_all"] for r in rows if r["selection"] == sel]
        assert e[0] > e[1] > e[2] > 0, (sel, e)            # Figs. 7–8: the truncation error falls with n
        m = [r["rmse_vs_reference"] for r in rows if r["selection"] == sel]
        assert m[2] < m[0], (sel, m)                       # and so does the error against Mitsuba
