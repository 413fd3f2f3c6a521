"""`benchmarks.inout_bound`: its variants of in-out's per-sample loop build from the loop's current
source (each replaced line still found), and those that move the table, c and memo loads into L1 keep
the loop's control flow: the same memo rows computed and entries summed exactly as the loop itself."""
import pytest


def test_inout_bound_variants_keep_the_loops_work():
    from benchmarks import inout_bound
    from methods.inout import native_sample as ns

    if not ns.available():
        pytest.skip("no C compiler (PRTBENCH_COMPILE=0)")
    out = inout_bound.main(["--scene", "sphere_plane", "--size", "test", "--frames", "3", "--warm"])
    assert set(out) == set(inout_bound.variants())
    base = out["base"]["stats"]
    assert base[0] > 0
    for k in ("L1 table", "+ c", "+ memo", "no cell_x"):
        assert out[k]["stats"] == base, k
    assert out["no X"]["stats"][:2] == (0, 0)
    assert all(r["median_ms"] > 0 for r in out.values())
