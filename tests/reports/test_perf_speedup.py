"""`benchmarks.perf_speedup`: before / after speed-ups with the host's drift divided out (issue 14)."""
from __future__ import annotations

import json
import math

import pytest

from benchmarks import perf_speedup as S
from reports import store


def _run(path, cells, codes=None):
    """A perf run directory: cells = {(method, config, scene, kind): ms}; codes = {method: key}."""
    rows, prov = [], []
    for i, ((m, c, scene, kind), ms) in enumerate(cells.items()):
        cell = f"cell{i}-{m}-{kind}-{scene}"
        rows.append({"scene": scene, "method": m, "config": c, "sequence": kind, "frame": -1, "status": "ok",
                     "metric": "render_time_median", "value": ms / 1e3, "cell": cell})
        prov.append({"cell": cell, "method": m, "status": "ok", **({"code": codes[m]} if codes else {})})
    path.mkdir()
    store.to_frame(rows).to_parquet(path / "results.parquet")
    (path / "provenance.json").write_text(json.dumps(prov))
    return path


BASE = {("ptt", "{}", "chess", "V"): 5.0, ("ptt", "{}", "chess", "L"): 30.0,
        ("zh_shadow", "{}", "creature", "V"): 6.0, ("zh_shadow", "{}", "creature", "P"): 8.0}


def _after(drift, zh_gain):
    """The host slower by ``drift`` on every cell; ZH's code ``zh_gain`` times faster."""
    return {k: v * drift / (zh_gain if k[0] == "zh_shadow" else 1.0) for k, v in BASE.items()}


def test_the_drift_is_divided_out():
    res = S.speedups([BASE], [_after(1.25, 1.5)], [("ptt", "{}")])
    assert res["drift"] == pytest.approx([0.8])
    zh = res[("zh_shadow", "{}")]
    assert zh["cells"] == 2
    assert zh["raw"] == pytest.approx([1.5 / 1.25])
    assert zh["corrected"] == pytest.approx([1.5])
    assert res[("ptt", "{}")]["corrected"] == pytest.approx([1.0])


def test_every_pair_of_runs_and_by_kind():
    before = [BASE, {k: 1.1 * v for k, v in BASE.items()}]
    after = [_after(1.0, 2.0), _after(0.9, 2.0), _after(1.3, 2.0)]
    res = S.speedups(before, after, [("ptt", "{}")])
    assert len(res["drift"]) == 6
    assert res[("zh_shadow", "{}")]["corrected"] == pytest.approx([2.0] * 6)
    kinds = S.speedups([BASE], [{**_after(1.0, 1.0), ("zh_shadow", "{}", "creature", "P"): 4.0}],
                       [("ptt", "{}")], by_kind=True)
    assert kinds[(("zh_shadow", "{}"), "P")]["corrected"] == pytest.approx([2.0])
    assert kinds[(("zh_shadow", "{}"), "V")]["corrected"] == pytest.approx([1.0])


def test_a_geometric_not_arithmetic_mean():
    """One cell 4x faster and one 4x slower is no change."""
    before = {("a", "{}", "s", "V"): 1.0, ("b", "{}", "s", "V"): 1.0, ("b", "{}", "s", "L"): 1.0}
    after = {("a", "{}", "s", "V"): 1.0, ("b", "{}", "s", "V"): 0.25, ("b", "{}", "s", "L"): 4.0}
    assert S.speedups([before], [after], [("a", "{}")])[("b", "{}")]["corrected"] == pytest.approx([1.0])


def test_reference_from_recorded_code_keys(tmp_path, capsys):
    a = _run(tmp_path / "a", BASE, {"ptt": "k1", "zh_shadow": "z1"})
    b = _run(tmp_path / "b", _after(1.25, 1.5), {"ptt": "k1", "zh_shadow": "z2"})
    assert S.unchanged_groups([a, b]) == [("ptt", "{}")]
    S.main(["--before", str(a), "--after", str(b)])
    out = capsys.readouterr().out
    line = next(x for x in out.splitlines() if x.startswith("| zh_shadow"))
    assert "| 1.20× | 1.50× |" in line
    assert "reference: ptt" in out


def test_runs_without_code_keys_need_unchanged(tmp_path, capsys):
    a = _run(tmp_path / "a", BASE)
    b = _run(tmp_path / "b", _after(1.25, 1.5))
    assert S.unchanged_groups([a, b]) == []
    with pytest.raises(SystemExit, match="pass --unchanged"):
        S.main(["--before", str(a), "--after", str(b)])
    with pytest.raises(SystemExit, match="no such method"):
        S.main(["--before", str(a), "--after", str(b), "--unchanged", "pt"])
    S.main(["--before", str(a), "--after", str(b), "--unchanged", "ptt"])
    assert "| 1.50× |" in capsys.readouterr().out


def test_no_common_reference_cell_is_one_error():
    with pytest.raises(ValueError, match="no reference cell"):
        S.speedups([{("ptt", "{}", "s", "V"): 1.0}], [{("zh", "{}", "s", "V"): 1.0}], [("ptt", "{}")])
    assert math.isnan(S._geomean([]))
