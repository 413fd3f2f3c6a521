"""G-buffer helpers for tests."""
from __future__ import annotations

import dataclasses

import torch


def knock_out(gb, every: int = 97, offset: int = 5):
    """A copy of the G-buffer ``gb`` whose samples offset, offset + every, … miss (as a miss is stored:
    face / region −1, normal, position and barycentrics 0, coverage off)."""
    miss = torch.zeros_like(gb.hit)
    miss[offset::every] = True
    S = gb.spp_side
    cov = gb.coverage & ~miss.view(gb.height, gb.width, S * S).any(-1)
    return dataclasses.replace(gb, hit=gb.hit & ~miss, face=gb.face.masked_fill(miss, -1),
                               region=gb.region.masked_fill(miss, -1), bary=gb.bary.masked_fill(miss[:, None], 0.0),
                               normal=gb.normal.masked_fill(miss[:, None], 0.0),
                               position=gb.position.masked_fill(miss[:, None], 0.0), coverage=cov)
