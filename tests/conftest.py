"""Test-session settings shared by every test.

pytest runs with 2 xdist workers on a 2-core machine: one torch thread per worker avoids
oversubscription (measured: a materials test file took 95 s with default threading under load,
17 s with one thread).

The harness's warm-up frame does not compile neighbouring block sizes in tests
(``PRTBENCH_WARM=0``, ``reports.measure_cell.warm_up_compiles``): tests assert values, never
timings, and those compilations only keep later *timed* frames from compiling. Tests of warming
call ``methods.core.fused.warming`` themselves or set the variable back.
"""
import os

import torch

os.environ.setdefault("PRTBENCH_WARM", "0")

torch.set_num_threads(1)
