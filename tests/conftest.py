"""Test-session settings shared by every test.

pytest runs with 2 xdist workers on a 2-core machine: one torch thread per worker avoids
oversubscription (measured: a materials test file took 95 s with default threading under load,
17 s with one thread).

The harness's warm-up frame does not compile neighbouring block sizes in tests
(``PRTBENCH_WARM=0``, ``reports.measure_cell.warm_up_compiles``): tests assert values, never
timings, and those compilations only keep later *timed* frames from compiling. Tests of warming
call ``methods.core.fused.warming`` themselves or set the variable back. Nor does each timed cell
measure the machine's limits (``PRTBENCH_CELL_LIMITS=0``, ``reports.measure_cell.cell_limits``:
~0.2 s per cell); ``tests/reports/test_machine_limits.py`` turns it on.
"""
import os

import pytest
import torch

os.environ.setdefault("PRTBENCH_WARM", "0")
os.environ.setdefault("PRTBENCH_CELL_LIMITS", "0")

torch.set_num_threads(1)


@pytest.fixture
def lapack_other_basis(monkeypatch):
    """``torch.linalg.svd`` made to return every cluster of equal singular values in a random other
    orthonormal basis (what LAPACK may return on another machine or thread count;
    ``methods.core.stable``). Yields the list of the cluster sizes it rotated (appended per call)."""
    from methods.core import stable

    real_svd = torch.linalg.svd
    g = torch.Generator().manual_seed(5)
    sizes: list[int] = []

    def other_basis_svd(A, full_matrices=True, **kw):
        U, S, Vh = real_svd(A, full_matrices=full_matrices, **kw)
        for a, b in stable.svd_clusters(S):
            O = torch.linalg.qr(torch.randn(b - a, b - a, generator=g, dtype=U.dtype))[0]
            U[:, a:b], Vh[a:b] = U[:, a:b] @ O, O.T @ Vh[a:b]
            sizes.append(b - a)
        return U, S, Vh

    monkeypatch.setattr(torch.linalg, "svd", other_basis_svd)
    yield sizes
