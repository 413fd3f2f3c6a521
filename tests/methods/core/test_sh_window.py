"""SH windowing σ-factors (`methods.core.zh.window_factors`, Sloan 2008 "Stupid SH Tricks")."""
from __future__ import annotations

import math

import pytest
import torch

from methods.core.sh import sh_eval
from methods.core.sampling import fibonacci_sphere
from methods.core.zh import convolve_factors, window_factors


def test_closed_forms():
    assert torch.equal(window_factors("none", 4), torch.ones(4, dtype=torch.float64))
    h = window_factors("hanning", 4)                       # w = n = 4
    want = [1.0, (1 + math.cos(math.pi / 4)) / 2, 0.5, (1 + math.cos(3 * math.pi / 4)) / 2]
    assert torch.allclose(h, torch.tensor(want, dtype=torch.float64), atol=1e-15)
    lz = window_factors("lanczos", 5, 4.0)
    want = [1.0] + [math.sin(math.pi * l / 4) / (math.pi * l / 4) for l in (1, 2, 3)] + [0.0]
    assert torch.allclose(lz, torch.tensor(want, dtype=torch.float64), atol=1e-15)
    assert window_factors("hanning", 6, 3.0)[4:].abs().max() == 0          # zero past the width
    # wider windows damp less: σ_l increases with w for every band
    for kind in ("hanning", "lanczos"):
        a, b = window_factors(kind, 4, 4.0), window_factors(kind, 4, 8.0)
        assert a[0] == b[0] == 1 and (b[1:] > a[1:]).all()


def test_window_damps_ringing_of_a_delta():
    """A unit impulse projected to order 4 rings below zero (the deepest negative lobe is 25 % of the
    peak); the Hanning window (w = 4) shrinks that lobe more than four-fold (measured: 4.6 %)."""
    n = 4
    up = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    c = sh_eval(up, n).T                                                    # (n², 1): the delta at +z
    d, _ = fibonacci_sphere(4000, dtype=torch.float64)
    Y = sh_eval(d, n)
    raw = (Y @ c).squeeze(-1)
    win = (Y @ convolve_factors(c, window_factors("hanning", n))).squeeze(-1)
    assert raw.min() < -0.2 * raw.max()
    assert win.min() / win.max() > 0.25 * raw.min() / raw.max()
    assert convolve_factors(c, window_factors("hanning", n))[0] == c[0]      # σ_0 = 1 keeps the mean


def test_bad_inputs():
    with pytest.raises(ValueError, match="kind"):
        window_factors("gauss", 4)
    with pytest.raises(ValueError, match="width"):
        window_factors("hanning", 4, 0.0)
    with pytest.raises(ValueError, match="order"):
        window_factors("hanning", 0)
