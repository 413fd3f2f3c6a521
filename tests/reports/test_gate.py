"""reports.gate: the sanity gate flags plainly wrong images (black, negative, 3× too bright, one
black region in a bright image) and passes right ones, in the metric functions and through a
measured cell (fake backend) whose status becomes "suspect"."""
from __future__ import annotations

import torch

from reports import cells as C
from reports import gate
from reports import measure_cell as MC

FAKE = dict(backend="testing.fakes", plugins=("testing.fakes",))


def _scene(seed: int = 0):
    """A 32×32 reference with two regions (left half 0, right half 1), all pixels scored."""
    g = torch.Generator().manual_seed(seed)
    ref = 0.5 + torch.rand(32, 32, 3, generator=g)
    regions = torch.zeros(32, 32, dtype=torch.int64)
    regions[:, 16:] = 1
    return ref, torch.ones(32, 32, dtype=torch.bool), regions


def _rows(m: dict) -> list[dict]:
    return [{"frame": 0, "metric": k, "value": v} for k, v in m.items()]


def test_right_image_passes():
    ref, mask, regions = _scene()
    noisy = ref + 0.05 * torch.randn(ref.shape, generator=torch.Generator().manual_seed(1))
    m = gate.frame_sanity(noisy, ref, mask, regions)
    assert m["negative_frac"] == 0.0
    assert 0.95 < m["region_mean_ratio_min"] <= m["region_mean_ratio_max"] < 1.05
    assert gate.verdict(_rows(m)) is None


def test_planted_black_image():
    ref, mask, regions = _scene()
    m = gate.frame_sanity(torch.zeros_like(ref), ref, mask, regions)
    assert m["mean_ratio"] == 0.0 and m["region_mean_ratio_max"] == 0.0
    assert "darkest region at 0.00" in gate.verdict(_rows(m))


def test_planted_negative_image():
    ref, mask, regions = _scene()
    img = ref.clone()
    img[:4] = -0.3  # 4 of 32 rows negative: 12.5 % of the pixels
    m = gate.frame_sanity(img, ref, mask, regions)
    assert abs(m["negative_frac"] - 4 / 32) < 1e-12
    assert "negative pixels" in gate.verdict(_rows(m))


def test_planted_three_times_too_bright():
    ref, mask, regions = _scene()
    m = gate.frame_sanity(3 * ref, ref, mask, regions)
    assert abs(m["mean_ratio"] - 3) < 1e-9
    assert "brightest region at 3.00" in gate.verdict(_rows(m))


def test_one_black_region_is_caught_though_the_image_mean_is_fine():
    """A dark region beside a bright one: the whole-image ratio is near 1, the region ratio is not
    (the in-out Cook–Torrance failure on two_boxes.toml)."""
    ref, mask, regions = _scene()
    ref[:, 16:] *= 0.02  # region 1 is dim in the reference...
    img = ref.clone()
    img[:, 16:] *= 0.1   # ...and 10× too dim in the image
    m = gate.frame_sanity(img, ref, mask, regions)
    assert m["mean_ratio"] > 0.95
    assert m["region_mean_ratio_min"] < 0.2
    assert gate.verdict(_rows(m)) is not None


def test_small_regions_and_edge_pixels_are_not_judged():
    ref, mask, regions = _scene()
    regions[0, 0] = 7  # 1 pixel of 1024 < 1 %
    img = ref.clone()
    img[0, 0] = 0.0
    assert gate.verdict(_rows(gate.frame_sanity(img, ref, mask, regions))) is None
    # a pixel whose sub-samples hit different regions belongs to none
    per_sample = torch.tensor([0, 0, 0, 1, 2, 2, 2, 2])
    assert gate.pixel_regions(per_sample, 1, 2).tolist() == [[-1, 2]]


def _cell(bias: float):
    return C.Cell(scene="fake_plane", size="test", kind="V", method="fake", n_frames=2, ref_spp=64, spp_side=1,
                  config=C.canonical_config({"bias": bias}), **FAKE)


def test_measured_cells_become_suspect(tmp_path):
    """Through the harness: the fake method renders truth·(1 + bias)."""
    ok = MC.run_cell(_cell(0.05), tmp_path, progress=False)
    assert ok.status == "ok", ok.reason
    summary = {r["metric"]: r["value"] for r in ok.rows if r["frame"] == -1}
    assert 0.9 < summary["mean_ratio"] < 1.1 and summary["negative_frac"] == 0
    for bias, words in ((2.0, "brightest region"), (-1.0, "darkest region"), (-2.0, "negative pixels")):
        r = MC.run_cell(_cell(bias), tmp_path, progress=False)
        assert r.status == "suspect" and words in r.reason, (bias, r.status, r.reason)
        assert any(row["metric"] == "rmse" for row in r.rows)  # the numbers are kept


def test_suspect_cells_are_counted_printed_and_kept_in_the_table(tmp_path, capsys):
    from reports.pipeline import run_suite
    from reports.suites import Suite
    import pandas as pd

    suite = Suite(name="gate", size="test", kinds=("V",), n_frames=2, ref_spp=16, spp_side=1, scenes=("fake_plane",),
                  isolate=False, configs=(("fake", '{"bias":2.0}'),))
    res = run_suite(suite, tmp_path, methods=["fake"], history=None, progress=False, bandwidth_elements=1 << 16, **FAKE)
    assert (res.n_ok, res.n_suspect, res.n_error) == (0, 1, 0)
    assert "[prtbench] SUSPECT fake/fake_plane/V/b0: frame" in capsys.readouterr().err
    df = pd.read_parquet(res.table)
    cell = df[df["method"] == "fake"]
    assert set(cell["status"]) == {"suspect"} and (cell["metric"] == "rmse").any()  # numbers kept
    assert (cell["metric"] == "roofline_efficiency").any()  # and the roofline
    assert "Suspect cells" in res.report.read_text()


def test_run_overrides_and_strict_exit(tmp_path, capsys):
    import argparse

    import pytest

    import run_bench
    from reports.suites import SMOKE

    ns = argparse.Namespace(ref_spp=512, frames=2, device="cpu")
    s = run_bench._overridden(SMOKE, ns)
    assert (s.ref_spp, s.n_frames) == (512, 2) and max(s.eq_err_spp) == 512
    for bad in (dict(ref_spp=7, frames=None, device="cpu"), dict(ref_spp=None, frames=0, device="cpu"),
                dict(ref_spp=None, frames=None, device="tpu")):
        with pytest.raises(ValueError):
            run_bench._overridden(SMOKE, argparse.Namespace(**bad))
