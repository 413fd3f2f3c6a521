"""Local-frame spherical-wavelet triple-product relighting (Ma et al. 2006).

``import methods.triple_product`` registers ``TripleProduct`` (name "triple_product").
"""
from methods.triple_product.method import TripleProduct  # noqa: F401  (registers the method)

__all__ = ["TripleProduct"]
