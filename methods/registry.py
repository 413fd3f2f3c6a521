"""Every method and every paper study the project ships, loaded in one place.

The top of the ``methods`` layer: it imports each method package (whose ``@register`` adds the
method to ``methods.base``'s registry) and each package's ``study`` module (which registers that
paper's figures and tables in ``methods.studies``). Nothing in ``methods/`` imports this module;
``reports`` and ``run_bench.py`` do. Adding a method = one line in each tuple below.
"""
from __future__ import annotations

import methods.inout.method  # noqa: F401  (registers "inout")
import methods.inout.study  # noqa: F401  (Mahajan 2008 studies)
import methods.oracle  # noqa: F401  (registers "oracle")
import methods.ptt.method  # noqa: F401  (registers "ptt")
import methods.ptt.study  # noqa: F401  (Sun 2007 studies)
import methods.sh_prt.method  # noqa: F401  (registers "sh_prt", the Sloan 2002 baseline)
import methods.sh_prt.study  # noqa: F401  (its terms-vs-exponent row)
import methods.triple_product  # noqa: F401  (registers "triple_product")
import methods.triple_product.study  # noqa: F401  (Ma 2006 studies)
import methods.zh_shadow  # noqa: F401  (registers "zh_shadow")
import methods.zh_shadow.study  # noqa: F401  (Nowrouzezahrai 2008 studies)
from methods.base import _REGISTRY, Method
from methods.studies import STUDIES, Study


def available_methods() -> list[str]:
    """Names of every registered method, sorted."""
    return sorted(_REGISTRY)


def get_method(name: str) -> type[Method]:
    """The method class registered as ``name`` (``KeyError`` naming the available ones)."""
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown method {name!r}; available: {', '.join(sorted(_REGISTRY))}") from None


def studies() -> dict[str, Study]:
    """Every registered study by name (paper figures/tables and cross-method sweeps)."""
    return dict(STUDIES)
