"""ZH-predicted shadowing with 1D BRDFs (Nowrouzezahrai et al. 2008). Importing registers
`ZHShadow` (name "zh_shadow") with `methods.base`."""
from methods.zh_shadow.method import ZHShadow

__all__ = ["ZHShadow"]
