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


def test_efficiencies_at_a_fixed_bandwidth():
    """`--triad`: every cell's efficiency recomputed at one bandwidth — max(bytes / bw, flops /
    peak) / median frame time — so runs with different own triads compare."""
    from benchmarks.perf_table import at_bandwidth

    rows = []
    for kind, nbytes, flops, ms in (("V", 20e6, 1e6, 4.0), ("L", 1e6, 8e9, 50.0)):
        ident = {"scene": "chess", "method": "m", "config": "{}", "sequence": kind, "frame": -1, "status": "ok",
                 "cell": f"c{kind}"}
        rows += [{**ident, "metric": "render_time_median", "value": ms / 1e3},
                 {**ident, "metric": "bytes_per_frame", "value": nbytes},
                 {**ident, "metric": "flops_per_frame", "value": flops},
                 {**ident, "metric": "roofline_efficiency", "value": 0.5}]
    df = at_bandwidth(store.to_frame(rows), 50e9, 100e9)
    eff = dict(zip(df[df.metric == "roofline_efficiency"].sequence, df[df.metric == "roofline_efficiency"].value))
    assert abs(eff["V"] - (20e6 / 50e9) / 4e-3) < 1e-12  # memory-bound: 0.1
    assert abs(eff["L"] - (8e9 / 100e9) / 50e-3) < 1e-12  # compute-bound: 1.6
    assert (df[df.metric == "render_time_median"].value.values == [4e-3, 50e-3]).all()  # nothing else moved
