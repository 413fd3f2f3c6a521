"""Thread-count-independent results (issue 17): a method must give the same numbers, bit for bit,
with any torch thread count, so a local run (all cores) and a process pool (one thread per worker)
agree.

Most torch CPU kernels split their work over output elements only, so their results do not depend
on the thread count. The exceptions met in the methods (each found by running the op with 1 and 2
threads on the same inputs, ``tests/methods/test_threads.py``):

* LAPACK factorizations through MKL (``torch.linalg.svd``, ``eigh``, ``lstsq``): the rounding —
  and, inside (near-)degenerate singular or eigen spaces, the vectors themselves — change with the
  thread count;
* reductions of a whole tensor to one number (two-pass: one partial sum per thread);
* LAPACK's ``gelsy`` (``torch.linalg.lstsq``'s default driver) even differs between two calls on
  the same input and thread count: the methods use ``gelsd``;
* float32 matrix products of one matrix with 5–7 or 9–11 rows (MKL sgemm splits such a product
  over the threads with other kernels): ``torch.bmm`` keeps every product of a batch on one
  thread — but a batch of one is a threaded product (`bmm` below), as are batches whose matrices
  are not contiguous.

The fix is at each such call: run it under ``torch_threads(1)`` — only ever around
factorizations of small matrices and cheap reductions, never around a method's bulk work, so the
cost is negligible — or hand ``bmm`` contiguous operands. Found by ``tests/methods/
test_threads.py`` on the test-size scenes; a shape met only at other sizes can still hide one.
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
from torch import Tensor

__all__ = ["bmm", "torch_threads"]


@contextlib.contextmanager
def torch_threads(n: int) -> Iterator[None]:
    """Run the block with ``n`` torch intra-op threads (restored afterwards, also on error).

    ``torch_threads(1)`` makes the ops inside independent of the caller's thread count (module
    docstring)."""
    if isinstance(n, bool) or not isinstance(n, int) or n < 1:
        raise ValueError(f"n must be a positive int, got {n!r}")
    old = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(old)


def bmm(a: Tensor, b: Tensor) -> Tensor:
    """``torch.bmm(a, b)`` for a (B, n, m), b (B, m, p), independent of the thread count: a batch of
    one matrix is multiplied on one thread (module docstring); larger batches as torch does."""
    if a.shape[0] > 1:
        return torch.bmm(a, b)
    with torch_threads(1):
        return torch.bmm(a, b)
