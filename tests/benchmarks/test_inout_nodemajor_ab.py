"""`benchmarks.inout_nodemajor_ab` (session 42's node-major tile fill, tried and dropped): its edits still apply
to the loop's current source, and every variant gives the module loop's image bit for bit (the same X per
(vertex, node) pair whichever operand order or grouping forms it), with tiles of 100 pixels (ending inside a
block) and of `TILE`, at 1 and 2 threads. Planted errors it caught (session 42): `cols_x` reading one c row
for every vertex, the shade pass reading node 0's X for node 1, a pair's slot taken from the wrong node, and
`pairs_x` multiplying and adding in two roundings instead of one fused multiply-add (max |d| 6e-8)."""
import pytest
import torch

from methods.inout import native_sample as ns


@pytest.mark.parametrize("scene", ["creature"])   # (chess too by hand: ~2x the time, the same code paths)
def test_nodemajor_variants_same_bits(monkeypatch, scene):
    from benchmarks import inout_nodemajor_ab as nm

    if not ns.cells_available() or not ns.FAST & 256:
        pytest.skip("no FMA build of the loop (no tiles)")
    n = torch.get_num_threads()
    monkeypatch.setattr(ns, "MIN_PER_THREAD", 1)
    try:
        for tile in (100, ns.TILE):
            monkeypatch.setattr(ns, "TILE", tile)
            for t in (1, 2):
                out = nm.main(["--scene", scene, "--size", "test", "--frames", "3", "--threads", str(t),
                               "--variants", "base", "16383", "32767", "24575"])
                assert out["max_diff"] == 0.0, (tile, t)
                # (the products count is not compared: a tile closes early by its thread's buffer capacity, the
                # largest tile that thread met in its library, so it depends on the calls before)
                assert all(v["stats"][0] > 0 and v["stats"][1:] == (0, -1) for v in out["variants"].values()), (tile, t)
    finally:
        torch.set_num_threads(n)
