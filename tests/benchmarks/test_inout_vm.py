"""benchmarks/inout_vm.py: its variants build (their anchors are in the loop's source) and run the
vertex-major frame, which forms X at every (vertex, node) pair of its spans (at least the tiles' distinct
pairs of a tile are among them: products > 0)."""
from __future__ import annotations

import pytest
import torch

from methods.inout import native_sample as ns


def test_inout_vm_variants_run():
    from benchmarks import inout_vm

    if not ns.cells_available():
        pytest.skip("no FMA build of the loop")
    n = torch.get_num_threads()
    try:
        out = inout_vm.main(["--scene", "creature", "--size", "test", "--frames", "2"])
    finally:
        torch.set_num_threads(n)
    assert set(out) == {"base", "table", "norows", "tiles"}
    assert out["base"]["stats"][0] > 0 and out["base"]["stats"][0] == out["table"]["stats"][0]
    assert all(out[k]["fill_ms"] >= 0 for k in ("base", "table", "norows"))
