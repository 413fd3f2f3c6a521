"""The SH PRT row of the terms-vs-exponent study: the curve the four seed papers escape.

Sloan 2002 §6 renders a glossy surface by convolving the order-n transferred radiance with the
lobe's zonal factors G_l, l < n: whatever of the lobe lies in bands l ≥ n is lost. For the
normalised Phong lobe (s+1)/(2π) max(0, cos)^s with ZH coefficients f_l (`zh.phong_kernel`) the
energy ∫ lobe² dω = Σ_l f_l² = (s+1)² / (2π (2s+1)) (Parseval; the lobe is zonal), so the terms the
method needs for exponent s are n², n the smallest order whose bands hold a fraction ``target``
of that energy.

Registered with `methods.studies` at import (``methods.registry`` imports this module); the
cross-method study ``terms-vs-exponent`` calls `terms_needed`.
"""
from __future__ import annotations

import math

from methods.core.zh import phong_kernel
from methods.studies import TermsRecord, register_terms_contributor

TARGET_KIND = "energy fraction of the Phong lobe in order-n SH (n² terms)"

# Orders searched (n² ≤ 40 000 terms: enough for s ≈ 10⁵ at 99 %).
MAX_ORDER = 200


def lobe_energy(exponent: float) -> float:
    """∫ lobe² dω of the normalised Phong lobe: (s+1)² / (2π (2s+1))."""
    s = float(exponent)
    return (s + 1.0) ** 2 / (2.0 * math.pi * (2.0 * s + 1.0))


def energy_fraction(exponent: float, order: int) -> float:
    """Fraction of the Phong lobe's energy in SH bands l < order."""
    k = phong_kernel(float(exponent), order)
    return float((k * k).sum()) / lobe_energy(exponent)


def order_needed(exponent: float, target: float = 0.99) -> int:
    """Smallest SH order n whose bands hold ``target`` of the Phong lobe's energy."""
    s = float(exponent)
    if not math.isfinite(s) or s < 0:
        raise ValueError(f"exponent must be finite and >= 0, got {exponent!r}")
    if not 0 < target < 1:
        raise ValueError(f"target must be in (0, 1), got {target!r}")
    k = phong_kernel(s, MAX_ORDER)
    cum = (k * k).cumsum(0) / lobe_energy(s)
    hit = (cum >= target).nonzero()
    if hit.numel() == 0:
        raise ValueError(f"exponent {s} needs more than order {MAX_ORDER} for {target:.3%}")
    return int(hit[0, 0]) + 1


def terms_needed(exponent: float, target: float = 0.99) -> TermsRecord:
    """terms-vs-exponent contributor: n² SH coefficients holding ``target`` of a Phong lobe's energy."""
    n = order_needed(exponent, target)
    return TermsRecord("sh_prt", float(exponent), float(target), n * n, TARGET_KIND,
                       f"order {n}; the paper's order 5 holds {energy_fraction(exponent, 5):.3f}")


register_terms_contributor("sh_prt", terms_needed, target=0.99, target_kind=TARGET_KIND)
