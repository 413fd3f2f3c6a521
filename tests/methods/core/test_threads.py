"""methods.core.threads: the thread-count context manager and the thread-count-independent bmm."""
import pytest
import torch

from methods.core.threads import bmm, torch_threads


def test_torch_threads_sets_and_restores():
    before = torch.get_num_threads()
    with torch_threads(2):
        assert torch.get_num_threads() == 2
        with torch_threads(1):
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 2
    assert torch.get_num_threads() == before
    with pytest.raises(RuntimeError), torch_threads(2):
        raise RuntimeError("inside")
    assert torch.get_num_threads() == before
    for bad in (0, -1, 1.5, True, "2"):
        with pytest.raises(ValueError), torch_threads(bad):
            pass


@pytest.mark.parametrize("batch", [1, 2, 7])
def test_bmm_is_bmm_and_independent_of_the_thread_count(batch):
    """Float32 products with 5–11 rows are where a single threaded MKL product rounds differently
    with 1 and 2 threads; every row count around them, one batch size that torch hands to one
    threaded product and two it splits over the threads."""
    g = torch.Generator().manual_seed(batch)
    for rows in range(1, 14):
        a = torch.randn(batch, rows, 16, generator=g)
        b = torch.randn(batch, 16, 24, generator=g)
        out = []
        for t in (1, 2):
            with torch_threads(t):
                out.append(bmm(a, b))
        assert torch.equal(out[0], out[1]), rows
        with torch_threads(1):
            assert torch.equal(out[0], torch.bmm(a, b))
