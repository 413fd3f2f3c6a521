"""The zh_shadow row of the terms-vs-exponent study."""
from __future__ import annotations

import math

import pytest
import torch

from methods.zh_shadow.study import lobe_energy_fraction, order_needed, terms_needed


def test_energy_fraction_matches_quadrature():
    """Σ_l f_l² over all bands = ∫ lobe² (Parseval): order 60 holds all of α = 8's lobe."""
    assert lobe_energy_fraction(8.0, 60) == pytest.approx(1.0, abs=1e-9)
    # α = 1 (the clamped cosine, normalised): ∫ lobe² = 4/(6π); order 3 against a direct sum
    from methods.core.zh import phong_kernel

    k = phong_kernel(1.0, 3)
    assert lobe_energy_fraction(1.0, 3) == pytest.approx(float((k * k).sum()) / (4 / (6 * math.pi)))


def test_terms_grow_with_exponent():
    orders = [order_needed(s) for s in (1, 4, 16, 64, 256, 1024)]
    assert orders == sorted(orders) and orders[0] < orders[-1]
    # a narrow lobe's bandwidth grows like √α: the order doubles (±1) when α quadruples
    assert abs(order_needed(1024.0) / order_needed(256.0) - 2.0) <= 0.25
    r = terms_needed(16.0, 0.99)
    terms = r if isinstance(r, int) else r.terms
    assert terms == order_needed(16.0) ** 2


def test_bad_inputs():
    with pytest.raises(ValueError):
        order_needed(-1.0)
    with pytest.raises(ValueError):
        order_needed(4.0, 1.5)
