"""Helpers shared by the PTT tests, as fixtures (the tests are no package: ``--import-mode=importlib``)."""
from __future__ import annotations

import dataclasses

import pytest
import torch


@pytest.fixture(scope="session")
def small():
    """``small(frame, side=32)``: the frame seen by a side × side camera (the same view)."""
    def resize(frame, side=32):
        return dataclasses.replace(frame, camera=dataclasses.replace(frame.camera, width=side, height=side))
    return resize


@pytest.fixture(scope="session")
def with_misses():
    """``with_misses(gb, step=37)``: the G-buffer with every step-th sample from the 6th missed, as the G-buffer
    writes a miss (hit False, face -1)."""
    def holes(gb, step=37):
        miss = torch.zeros_like(gb.hit)
        miss[5::step] = True
        return dataclasses.replace(gb, hit=gb.hit & ~miss, face=torch.where(miss, -1, gb.face))
    return holes
