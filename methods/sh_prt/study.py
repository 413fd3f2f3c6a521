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

from methods.core.zh import phong_energy_fraction, phong_lobe_energy, phong_order_needed
from methods.sh_prt.method import SHPRT
from methods.studies import TermsRecord, register_term_ladder, register_terms_contributor

TARGET_KIND = "energy fraction of the Phong lobe in order-n SH (n² terms)"

# The lobe-energy arithmetic is shared with zh_shadow's row (methods/core/zh.py).
lobe_energy, energy_fraction, order_needed = phong_lobe_energy, phong_energy_fraction, phong_order_needed


def terms_needed(exponent: float, target: float = 0.99) -> TermsRecord:
    """terms-vs-exponent contributor: n² SH coefficients holding ``target`` of a Phong lobe's energy."""
    n = order_needed(exponent, target)
    return TermsRecord("sh_prt", float(exponent), float(target), n * n, TARGET_KIND,
                       f"order {n}; the paper's order 5 holds {energy_fraction(exponent, 5):.3f}")


register_terms_contributor("sh_prt", terms_needed, target=0.99, target_kind=TARGET_KIND)


# The one-yardstick terms-vs-exponent study (reports/studies.py): SH order n = 2..10 (n² terms),
# direct lighting (bounces = 0, so the material may change at render time).
register_term_ladder("sh_prt", [dict(order=n) for n in range(2, 11)], lambda c, r: SHPRT(bounces=0, **c),
                     lambda c: c["order"] ** 2, quick=[dict(order=2, rays=32), dict(order=3, rays=32)],
                     material_at_render=True, term_name="n^2 (SH order n)", scan=True)
