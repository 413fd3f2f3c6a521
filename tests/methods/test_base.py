"""methods.base: the contract's guarantees that do not depend on a method."""
from __future__ import annotations

import json

import pytest

from methods.registry import available_methods, get_method
from reports.cells import canonical_config


@pytest.mark.parametrize("name", ["inout", "oracle", "ptt", "triple_product", "zh_shadow"])
def test_config_is_fixed_at_construction(name):
    """The recorded config is the one that ran: no code can change it after construction."""
    m = get_method(name)()
    before = canonical_config(m.config)
    with pytest.raises(TypeError):
        m.config["anything"] = 1
    assert canonical_config(m.config) == before
    # the recorded config rebuilds the same method (what the harness does with a cell's config)
    assert canonical_config(get_method(name)(**json.loads(before)).config) == before


def test_every_builtin_method_is_registered():
    assert {"inout", "oracle", "ptt", "triple_product", "zh_shadow"} <= set(available_methods())
    with pytest.raises(KeyError, match="unknown method"):
        get_method("no_such_method")
