"""This method's row of the terms-vs-exponent study (`reports.studies`, DESIGN.md "studies").

At run time the Phong term is t = ((α+1)/(2π)) M^α v in the reflection frame, dotted with order-n
lighting (Nowrouzezahrai 2008 eq. 2, §4.3). For unoccluded visibility (v = √(4π) e₀) the shade is
Σ_{l<n} f_l L_l0 with f_l the ZH coefficients of the normalised Phong lobe (α+1)/(2π) max(0, cos)^α
(`methods.core.zh.phong_kernel`): order n keeps exactly the lobe's bands l < n. So the terms the
method needs for exponent α are n², n the smallest order whose bands hold a fraction `target` of
the lobe's energy ∫ lobe² dω = Σ_l f_l² = (α+1)² / (2π (2α+1)) (Parseval; the lobe is zonal). The
linear model itself stores c·(2+n) scalars per vertex and pose parameter, but every shade uses n²
SH coefficients of visibility and lighting; the order, not the lobe count, caps the exponent.

Register in `reports/studies.py` (not this package's file):
    register_terms_contributor("zh_shadow", "methods.zh_shadow.study:terms_needed", target=0.99,
                               target_kind="energy fraction of the Phong lobe in order-n SH (n² terms)")
"""
from __future__ import annotations

import math

from methods.core.zh import phong_kernel
from methods.studies import TermsRecord, register_terms_contributor

# Orders searched (n² ≤ 40 000 terms: enough for α ≈ 10⁵ at 99 %).
MAX_ORDER = 200


def lobe_energy_fraction(exponent: float, order: int) -> float:
    """Fraction of ∫ lobe² of the normalised Phong lobe captured by SH bands l < order."""
    s = float(exponent)
    k = phong_kernel(s, order)
    total = (s + 1.0) ** 2 / (2.0 * math.pi * (2.0 * s + 1.0))
    return float((k * k).sum()) / total


def order_needed(exponent: float, target: float = 0.99) -> int:
    """Smallest SH order n whose bands hold `target` of the Phong lobe's energy."""
    s = float(exponent)
    if not math.isfinite(s) or s < 0:
        raise ValueError(f"exponent must be finite and >= 0, got {exponent!r}")
    if not 0 < target < 1:
        raise ValueError(f"target must be in (0, 1), got {target!r}")
    k = phong_kernel(s, MAX_ORDER)
    total = (s + 1.0) ** 2 / (2.0 * math.pi * (2.0 * s + 1.0))
    acc = 0.0
    for n in range(1, MAX_ORDER + 1):
        acc += float(k[n - 1]) ** 2
        if acc >= target * total:
            return n
    raise ValueError(f"exponent {s} needs more than order {MAX_ORDER} for {target:.3%}")


def terms_needed(exponent: float, target: float = 0.99):
    """terms-vs-exponent contributor: n² SH terms for Phong exponent `exponent` (TermsRecord)."""
    n = order_needed(exponent, target)
    return TermsRecord("zh_shadow", float(exponent), float(target), n * n,
                       "energy fraction of the Phong lobe in order-n SH (n² terms)",
                       f"order {n}; paper's order 4 holds {lobe_energy_fraction(exponent, 4):.3f}")


# -- registration (methods.studies) ----------------------------------------------------------------
register_terms_contributor("zh_shadow", terms_needed, target=0.99,
                           target_kind="energy fraction of the Phong lobe in order-n SH (n² terms)")
