"""Test-session settings shared by every test.

pytest runs with 2 xdist workers on a 2-core machine: one torch thread per worker avoids
oversubscription (measured: a materials test file took 95 s with default threading under load,
17 s with one thread).
"""
import torch

torch.set_num_threads(1)
