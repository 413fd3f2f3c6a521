"""One real end-to-end run (Mitsuba references, the oracle, the HTML report) on the tiny test-size
sphere_plane scene: 2 frames of sequence V."""
import math

import pytest

from reports.pipeline import run_suite
from reports.suites import Suite

# The oracle and the reference are both unbiased estimates of direct lighting; with 16+16 oracle
# samples per sub-sample (×4 sub-samples) the oracle's own noise is about the reference's floor, so
# E[RMSE] ≈ sqrt(2)·floor. 4× the floor leaves room for the sun's heavy-tailed noise while any
# convention error (flipped env map, wrong BRDF normalisation) lands far above it.
RMSE_OVER_FLOOR_MAX = 4.0


@pytest.mark.slow
def test_real_smoke_run_oracle_sphere_plane(tmp_path):
    suite = Suite(name="e2e", size="test", scenes=("sphere_plane",), kinds=("V",), dynamic_kinds=(), n_frames=2,
                  ref_spp=32, configs=(("oracle", '{"brdf_samples":16,"light_samples":16}'),), isolate=False)
    res = run_suite(suite, tmp_path, methods=["oracle"], history=tmp_path / "hist.parquet", progress=False,
                    bandwidth_elements=1 << 20)
    assert (res.n_ok, res.n_error) == (1, 0)
    import pandas as pd

    df = pd.read_parquet(res.table)
    rmse = df[(df.metric == "rmse") & (df.frame == -1)].iloc[0]
    assert math.isfinite(rmse.value) and 0 < rmse.value < RMSE_OVER_FLOOR_MAX * rmse.noise_floor
    text = res.report.read_text()
    assert "sphere_plane" in text and text.count("data:image/png;base64,") >= 4
