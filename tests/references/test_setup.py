"""references.setup.frame_setup: the scene → frames → G-buffers → references set-up shared by the
studies and the benchmarks."""
from __future__ import annotations

import pytest
import torch

from references.gbuffer import make_gbuffer
from references.render import render_reference
from references.setup import frame_setup
from scenes.library import get_scene
from scenes.sequences import make_sequence


def test_frame_setup_is_the_hand_written_setup():
    scene = get_scene("sphere_plane", "test")
    su = frame_setup(scene, kind="V", n_frames=2, seed=0, spp_side=1, ref_spp=256, bounces=(0,), ref_spp_side=1)
    frames = make_sequence(scene, "V", n_frames=2, seed=0)
    assert [f.camera for f in su.frames] == [f.camera for f in frames]
    assert su.frame is su.frames[0] and su.gbuffer is su.gbuffers[0] and len(su.gbuffers) == 2
    gb = make_gbuffer(scene, frames[0], 1)
    assert torch.equal(su.gbuffer.coverage, gb.coverage) and torch.equal(su.gbuffer.normal, gb.normal)
    ref = render_reference(scene, frames[0], bounces=0, spp=256, seed=0, spp_side=1)
    assert torch.equal(su.references[0].image, ref.image)
    assert torch.equal(su.mask(0), ref.coverage & gb.coverage)
    with pytest.raises(ValueError, match="bounces"):
        su.mask(1)


def test_frame_setup_takes_frames_and_checks_input():
    scene = get_scene("sphere_plane", "test")
    f = make_sequence(scene, "V", n_frames=3, seed=4)[2]
    su = frame_setup(scene, frames=[f], spp_side=1)
    assert su.frames == [f] and su.references == {}
    with pytest.raises(ValueError, match="ref_spp"):
        frame_setup(scene, ref_spp=-2)
    with pytest.raises(ValueError, match="frames"):
        frame_setup(scene, frames=[])
