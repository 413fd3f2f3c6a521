"""`methods.core.switches.on`: the environment's on/off switches, read at each call by one look-up in
``os.environ``'s own mapping — the same answers as ``os.environ.get`` for every value, set, changed and
deleted between calls."""
import os

import pytest

from methods.core import fused, switches

NAME = "PRTBENCH_TEST_SWITCH_X"


def _slow(name):
    return os.environ.get(name, "1").strip().lower() not in switches.OFF


@pytest.mark.parametrize("value", ["0", "false", "FALSE", " off ", "No", "1", "true", "", "  ", "yes", "2", "offf",
                                   "é", "0 1"])
def test_on_equals_the_environ_read(monkeypatch, value):
    monkeypatch.setenv(NAME, value)
    assert switches.on(NAME) is _slow(NAME)
    assert switches.on(NAME) is (value.strip().lower() not in ("0", "false", "no", "off"))


def test_unset_is_on_and_changes_are_seen_at_each_call(monkeypatch):
    monkeypatch.delenv(NAME, raising=False)
    assert switches.on(NAME) is True
    monkeypatch.setenv(NAME, "0")
    assert switches.on(NAME) is False
    monkeypatch.setenv(NAME, "1")
    assert switches.on(NAME) is True
    monkeypatch.setenv(NAME, "off")
    assert switches.on(NAME) is False
    monkeypatch.delenv(NAME)
    assert switches.on(NAME) is True


def test_compile_enabled_follows_the_switch(monkeypatch):
    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    assert fused.compile_enabled() is False
    monkeypatch.setenv("PRTBENCH_COMPILE", "Off")
    assert fused.compile_enabled() is False
    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    assert fused.compile_enabled() is True


def test_a_replaced_environ_is_read_through_its_get(monkeypatch):
    """Where ``os.environ`` is not the POSIX mapping (a test double), its ``get`` answers."""
    monkeypatch.setattr(os, "environ", {NAME: "no"})
    assert switches.on(NAME) is False
    monkeypatch.setattr(os, "environ", {})
    assert switches.on(NAME) is True
