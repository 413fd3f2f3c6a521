"""One scene → frames → G-buffers → Mitsuba references set-up, shared by the paper studies
(``methods/<m>/study.py``) and the benchmarks (``benchmarks/common.py``).

``frame_setup(scene, kind="V", n_frames=1, seed=0, spp_side=2, ref_spp=256, bounces=(0,))`` makes
the frames of one `scenes.sequences.make_sequence` sequence (or takes ``frames``), a G-buffer of
each, and path-traced references (`references.render.render_reference`, cached on disk) of the
FIRST frame for every bounce count in ``bounces`` (none when ``ref_spp`` is 0). The scored pixels
of a study are ``FrameSetup.mask(b)`` = reference coverage & G-buffer coverage of that frame.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

from torch import Tensor

from references.gbuffer import make_gbuffer
from references.render import Reference, render_reference
from scenes.frame import Frame, GBuffer
from scenes.sequences import make_sequence


@dataclass(frozen=True)
class FrameSetup:
    """scene; frames (n_frames); gbuffers (one per frame, G-buffer of ``spp_side``² samples per
    pixel); references: bounces → `Reference` of ``frames[0]`` (bounces None = full GI)."""

    scene: object
    frames: list[Frame]
    gbuffers: list[GBuffer]
    references: dict[int | None, Reference]

    @property
    def frame(self) -> Frame:
        """The first frame (the one the references show)."""
        return self.frames[0]

    @property
    def gbuffer(self) -> GBuffer:
        """The first frame's G-buffer."""
        return self.gbuffers[0]

    def mask(self, bounces: int | None = 0) -> Tensor:
        """(H, W) bool: pixels covered by the ``bounces`` reference and the first G-buffer."""
        if bounces not in self.references:
            raise ValueError(f"bounces={bounces!r} has no reference; rendered: {sorted(self.references, key=str)}")
        return self.references[bounces].coverage & self.gbuffers[0].coverage


def frame_setup(scene, *, frames: Sequence[Frame] | None = None, kind: str = "V", n_frames: int = 1,
                seed: int = 0, spp_side: int = 2, ref_spp: int = 0,
                bounces: Sequence[int | None] = (0,), ref_seed: int | None = None,
                ref_spp_side: int = 2) -> FrameSetup:
    """Frames, G-buffers and references of ``scene`` (a `scenes.scene.Scene`).

    Args:
        frames: use these frames (e.g. with edited materials) instead of ``make_sequence(scene,
            kind, n_frames, seed)``.
        spp_side: G-buffer sub-samples per pixel side (S).
        ref_spp: reference samples per pixel (even, >= 2); 0 = no references.
        bounces: the references' bounce counts (0 = direct, None = full GI).
        ref_seed: reference seed (default: ``seed``); ref_spp_side: the S stored with the
            reference's coverage (part of its cache key).
    """
    if isinstance(ref_spp, bool) or int(ref_spp) != ref_spp or ref_spp < 0:
        raise ValueError(f"ref_spp must be an int >= 0 (0: no references), got {ref_spp!r}")
    if frames is None:
        frames = make_sequence(scene, kind, n_frames=n_frames, seed=seed)
    frames = list(frames)
    if not frames:
        raise ValueError("frames must be non-empty")
    gbuffers = [make_gbuffer(scene, f, spp_side) for f in frames]
    refs: dict[int | None, Reference] = {}
    if ref_spp:
        rs = seed if ref_seed is None else ref_seed
        for b in bounces:
            refs[b] = render_reference(scene, frames[0], bounces=b, spp=int(ref_spp), seed=rs,
                                       spp_side=ref_spp_side)
    return FrameSetup(scene, frames, gbuffers, refs)
