"""`methods.core.sh_native`: a map's SH by one C pass against `methods.core.sh.project_latlong_polar`."""
from __future__ import annotations

import pytest
import torch


@pytest.mark.parametrize("order", [3, 5, 8])
@pytest.mark.parametrize("threads", [1, 2])
def test_native_projection_equals_project_latlong_polar(order, threads):
    """`sh_native.project_latlong_polar` (one C pass over the float32 texels, float64 sums) equals
    `methods.core.sh.project_latlong_polar` (its oracle: the float64 GEMM) to float64 round-off, on
    maps of several sizes (odd ones: rows split over 2 threads unevenly)."""
    from methods.core.sh import project_latlong_polar
    from methods.core import sh_native as native

    if not native.available():
        pytest.skip("no C compiler")
    gen = torch.Generator().manual_seed(order)
    old = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for H, W in ((32, 64), (131, 250), (256, 512)):
            img = torch.rand(H, W, 3, generator=gen) * torch.rand(1, W, 3, generator=gen) * 5
            got, want = native.project_latlong_polar(img, order), project_latlong_polar(img, order)
            assert got.dtype == torch.float64 and got.shape == want.shape == (order * order, 3)
            assert (got - want).abs().max() <= 1e-13 * want.abs().max()
    finally:
        torch.set_num_threads(old)


@pytest.mark.parametrize("order", [3, 8])
def test_native_projection_has_the_same_bits_at_any_thread_count(order):
    """The map's rows are cut into parts fixed by its size and the parts summed in order, so the
    float64 coefficients are bit-identical at 1, 2 and 3 threads (session 31: the rows used to be
    split by the thread count; 1 and 2 threads differed by ~9e-16 on a 256×512 map)."""
    from methods.core import sh_native as native

    if not native.available():
        pytest.skip("no C compiler")
    gen = torch.Generator().manual_seed(order)
    old = torch.get_num_threads()
    try:
        for H, W in ((131, 250), (256, 512)):
            img = torch.rand(H, W, 3, generator=gen) * torch.rand(1, W, 3, generator=gen) * 5
            got = []
            for t in (1, 2, 3):
                torch.set_num_threads(t)
                got.append(native.project_latlong_polar(img, order))
            assert torch.equal(got[0], got[1]) and torch.equal(got[0], got[2])
    finally:
        torch.set_num_threads(old)
