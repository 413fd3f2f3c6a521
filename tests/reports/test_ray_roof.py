"""The traversal roof (issue 14, session 38): a frame that traces shadow rays (the oracle) declares them
in ``FrameCost.rays``; each timed cell measures the ray rate of its scene (``measure.ray_rate``: the
fastest of the suite's tracers on shadow rays from the G-buffer's points), the run divides a cell's rays
by the best rate measured on that scene, and the bound is "traversal" when that term is the largest."""
from __future__ import annotations

import math

import numpy as np
import pytest

from reports import measure, pipeline
from reports.cells import Cell, CellResult


def _nan():
    return float("nan")


def test_roofline_closed_form_with_rays():
    # 1e6 rays at 1e8 rays/s = 10 ms ≥ 3e7 B at 30 GB/s = 1 ms and 1e6 flop / 1e11 = 10 µs: traversal
    assert measure.roofline(3e7, 1e6, 30e9, 1e11, 0.04, 1e6, 1e8) == (pytest.approx(0.25), "traversal")
    assert measure.roofline(3e7, 1e6, 30e9, 1e11, 0.04, 1e6, None) == (pytest.approx(0.025), "memory")
    assert measure.roofline(3e7, 1e6, 30e9, 1e11, 0.04, 1e6, float("nan"))[1] == "memory"  # no rate: no roof
    assert measure.roofline(3e7, 1e6, 30e9, 1e11, 0.04, 0, 1.0)[1] == "memory"           # no rays
    assert measure.roofline(3e7, 1e10, 30e9, 1e11, 0.2, 1e6, 1e8) == (pytest.approx(0.5), "compute")


def test_shadow_rays_sets():
    rng = np.random.default_rng(1)
    n = rng.normal(size=(20000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    p = rng.normal(size=(20000, 3)).astype(np.float32)
    o, d = measure.shadow_rays(p, n, "cosine", offset=0.01)
    assert o.dtype == d.dtype == np.float32 and o.shape == d.shape == (20000, 3)
    np.testing.assert_allclose(o, p + 0.01 * n, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-5)
    cos = np.sum(d * n, axis=1)
    assert cos.min() >= -1e-6
    assert cos.mean() == pytest.approx(2 / 3, abs=0.01)   # E[cos θ] of a cosine-distributed direction
    assert (cos**2).mean() == pytest.approx(1 / 2, abs=0.01)
    o, d = measure.shadow_rays(p, n, "coherent")
    assert len(np.unique(np.abs(d).round(6), axis=0)) == 1   # one direction, flipped per hemisphere
    assert (np.sum(d * n, axis=1) >= 0).all()
    with pytest.raises(ValueError, match="ray_set"):
        measure.shadow_rays(p, n, "random")
    with pytest.raises(ValueError, match="same shape"):
        measure.shadow_rays(p, n[:5], "cosine")


def _floor_under_a_lid():
    """A unit floor at z = 0 with a larger lid at z = 1 (facing down): every ray up from the floor's
    middle is blocked, every ray down from the lid's top side escapes."""
    V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                  [-1e4, -1e4, 1], [1e4, -1e4, 1], [1e4, 1e4, 1], [-1e4, 1e4, 1]], np.float32)
    F = np.array([[0, 1, 2], [0, 2, 3], [4, 6, 5], [4, 7, 6]], np.int64)
    return V, F


@pytest.mark.parametrize("backend", ["embree", "mitsuba"])
def test_ray_rate_measures_a_tracer(backend):
    from references.visibility import make_visibility, mitsuba_usable

    if backend == "mitsuba" and not mitsuba_usable():
        pytest.skip("no vectorised Mitsuba variant")
    V, F = _floor_under_a_lid()
    g = np.random.default_rng(0)
    pts = np.c_[g.uniform(0.2, 0.8, (4096, 2)), np.zeros(4096)].astype(np.float32)
    up = np.tile(np.float32([0, 0, 1]), (4096, 1))
    rate, which = measure.ray_rate(V, F, pts, up, repeats=2, backends=(backend,))
    assert math.isfinite(rate) and rate > 0 and which in (f"{backend}/cosine", f"{backend}/coherent")
    # the rays it times are shadow rays that the tracer answers: all blocked by the lid
    vis = make_visibility(V, F, backend=backend)
    for rs in measure.RAY_SETS:
        o, d = measure.shadow_rays(pts, up, rs, offset=1e-4)
        assert np.asarray(vis.occluded(o, d)).all(), rs
    with pytest.raises(ValueError):
        measure.ray_rate(V, F, pts[:0], up[:0], backends=(backend,))


def _oracle_like(scene: str, kind: str, rays: float | None, host_rate: float | None, t: float = 0.04):
    cell = Cell(scene=scene, size="bench", kind=kind, method="oracle", config="{}", bounces=0)
    rows = [{"frame": -1, "metric": "bytes_per_frame", "value": 3e7, "unit": "B", "noise_floor": _nan()},
            {"frame": -1, "metric": "flops_per_frame", "value": 1e6, "unit": "flop", "noise_floor": _nan()},
            {"frame": -1, "metric": "render_time_median", "value": t, "unit": "s", "noise_floor": _nan()}]
    if rays is not None:
        rows.append({"frame": -1, "metric": "rays_per_frame", "value": rays, "unit": "1", "noise_floor": _nan()})
    if host_rate is not None:
        rows.append({"frame": -1, "metric": "host_ray_rate", "value": host_rate, "unit": "1/s", "noise_floor": _nan()})
    return CellResult(key=cell.key(), cell=cell.to_dict(), status="ok", rows=rows)


def test_collect_divides_rays_by_the_best_rate_of_the_scene():
    meta = {"run_id": "r", "time": "t", "git_sha": "x", "versions": {}, "machine": "m", "threads": 2,
            "triad_bandwidth": 30e9, "matmul_peak": 1e11}
    results = [_oracle_like("chess", "V", 1e6, 5e7), _oracle_like("chess", "L", 1e6, 1e8),   # chess: best 1e8
               _oracle_like("creature", "V", 1e6, 2e7), _oracle_like("creature", "L", 1e6, float("nan")),
               _oracle_like("plane", "V", None, None)]                                       # traces nothing
    assert pipeline.ray_rates(results) == {("chess", "bench"): 1e8, ("creature", "bench"): 2e7}
    df = pipeline.collect(results, meta)
    eff = df[df.metric == "roofline_efficiency"].set_index(["scene", "sequence"]).value
    trav = df[df.metric == "roofline_traversal_bound"].set_index(["scene", "sequence"]).value
    assert eff[("chess", "V")] == pytest.approx(1e6 / 1e8 / 0.04) and trav[("chess", "V")] == 1.0
    assert eff[("creature", "L")] == pytest.approx(1e6 / 2e7 / 0.04) and trav[("creature", "L")] == 1.0
    assert eff[("plane", "V")] == pytest.approx(3e7 / 30e9 / 0.04) and trav[("plane", "V")] == 0.0
    from reports.html import summary_table

    html = summary_table(df)   # the report names the bound: traversal for the oracle's rows, memory for the other
    assert html.count("(traversal)") == 2 and html.count("(memory)") == 1


def test_an_oracle_cell_measures_its_ray_rate(tmp_path, monkeypatch):
    """A timed oracle cell (it traces rays) records its rays and its scene's ray rate; the rate is
    measured on the last frame's geometry from its G-buffer's hit points, only when cells measure limits."""
    from reports import cells as C
    from reports import measure_cell as MC

    seen = []

    def fake_rate(V, F, points, normals, **kw):
        seen.append((int(F.shape[0]), int(points.shape[0]), int(normals.shape[0])))
        return 12345.0, "fake/cosine"

    monkeypatch.setattr(measure, "ray_rate", fake_rate)
    monkeypatch.setattr(measure, "machine_limits", lambda *a, **k: {"triad_bandwidth": 1e10, "matmul_peak": 1e10})
    cell = C.Cell(scene="sphere_plane", size="test", kind="V", method="oracle",
                  config='{"light_samples": 1, "brdf_samples": 1}', n_frames=2, ref_spp=4, spp_side=1,
                  eq_err_spp=())
    monkeypatch.setenv("PRTBENCH_CELL_LIMITS", "1")
    r = MC.run_cell(cell, tmp_path / "on", progress=False)
    summ = {row["metric"]: row["value"] for row in r.rows if row["frame"] == -1}
    assert summ["host_ray_rate"] == 12345.0 and summ["rays_per_frame"] > 0
    assert len(seen) == 1 and seen[0][1] == seen[0][2] > 0 and r.info["ray_rate_tracer"] == "fake/cosine"
    monkeypatch.setenv("PRTBENCH_CELL_LIMITS", "0")
    r = MC.run_cell(cell, tmp_path / "off", progress=False)
    summ = {row["metric"]: row["value"] for row in r.rows if row["frame"] == -1}
    assert "host_ray_rate" not in summ and summ["rays_per_frame"] > 0 and len(seen) == 1
