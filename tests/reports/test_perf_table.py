"""`benchmarks.perf_table`: README's run-time table from a perf run's long table (issue 14)."""
from __future__ import annotations

from benchmarks.perf_table import table
from reports import store


def _rows(method, config, scene, kind, ms, roof, speed):
    ident = {"scene": scene, "method": method, "config": config, "sequence": kind, "frame": -1, "status": "ok"}
    return [{**ident, "metric": "render_time_median", "value": ms / 1e3},
            {**ident, "metric": "roofline_efficiency", "value": roof},
            {**ident, "metric": "eq_error_speedup", "value": speed}]


def test_table_reads_frame_times_ranges_and_the_cells_below_the_threshold():
    now = store.to_frame(_rows("inout", "{}", "chess", "V", 11.0, 0.052, 14.0)
                         + _rows("inout", "{}", "chess", "L", 49.0, 0.20, 127.0)
                         + _rows("inout", "{}", "creature", "VB", 8.0, 0.30, 20.0)  # not a column, in the ranges
                         + _rows("zh_shadow", "{}", "creature", "P", 10.4, 0.041, 19.0))
    before = store.to_frame(_rows("inout", "{}", "chess", "V", 25.6, 0.02, 5.0))
    tab, lines = table(now, before, 0.10)
    rows = tab.splitlines()
    inout = next(r for r in rows if r.startswith("| inout"))
    assert "| 11 (26) / 49 / – | – | – |" in inout  # E missing on chess, creature has only VB
    assert "5.2–30.0 %" in inout and "14–127×" in inout
    zh = next(r for r in rows if r.startswith("| zh_shadow"))
    assert "| 10 |" in zh and "4.1–4.1 %" in zh
    assert lines[0] == "Roofline ≥ 10 %: 2 of 4 cells"
    below = lines[lines.index("Below:") + 1:]
    assert below == ["  inout chess V: 5.2 %", "  zh_shadow creature P: 4.1 %"]
