"""What a method receives each frame: the ``Frame`` (lighting, camera, materials, pose) and the
``GBuffer`` (Mitsuba's primary-ray hits).

They live in ``scenes`` (below ``references`` and ``methods``) so that sequences, the G-buffer
builder and every method share one definition; ``methods.base`` re-exports both.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from scenes.hashing import hash_frame

# -- frames -----------------------------------------------------------------------------------


@dataclass
class Frame:
    """One frame of a sequence.

    envmap: ``scenes.envmap.EnvMap`` (its ``to_world`` carries the lighting rotation).
    camera: ``scenes.camera.Camera``.
    materials: region name → ``scenes.materials.Material``.
    pose: (J,) joint angles for articulated scenes, or None (rest pose / static scene).
    index: position in its sequence.
    changed: what changed since the previous frame: subset of {"view", "brdf", "light", "pose"};
        the first frame of a sequence has all of them.
    """

    envmap: Any
    camera: Any
    materials: dict[str, Any]
    pose: Tensor | None = None
    index: int = 0
    changed: frozenset[str] = frozenset({"view", "brdf", "light", "pose"})

    def key(self) -> str:
        """A stable content hash of the frame (used by the reference cache)."""
        return hash_frame(self)


# -- G-buffer ---------------------------------------------------------------------------------


@dataclass
class GBuffer:
    """Primary-ray hits from Mitsuba's own sensor rays, S×S sub-pixel samples per pixel.

    All per-sample arrays are flat over P = H·W·S² samples, ordered pixel-major
    (``(y, x, s)`` with s the sub-sample index), so ``values.view(H, W, S*S, C)`` regroups them.

    height, width, spp_side: H, W, S.
    hit: (P,) bool — the sample's primary ray hit geometry.
    face: (P,) int64 — global face index into ``scene.geometry(pose).F`` (−1 on a miss).
    bary: (P, 2) float32 — Mitsuba ``prim_uv`` (u, v): p = (1−u−v)·p0 + u·p1 + v·p2.
    position: (P, 3) world hit points; normal: (P, 3) interpolated unit shading normals;
    wo: (P, 3) unit directions from the hit point towards the camera.
    region: (P,) int64 region index into ``scene.regions`` (−1 on a miss).
    coverage: (H, W) bool — every sub-sample of the pixel hit geometry (the scored pixels).
    """

    height: int
    width: int
    spp_side: int
    hit: Tensor
    face: Tensor
    bary: Tensor
    position: Tensor
    normal: Tensor
    wo: Tensor
    region: Tensor
    coverage: Tensor

    @property
    def num_samples(self) -> int:
        return self.height * self.width * self.spp_side**2

    def vertex_weights(self, F: Tensor) -> tuple[Tensor, Tensor]:
        """Vertex indices (P, 3) and barycentric weights (P, 3) of each sample (0 on misses).

        ``F[face]`` by `index_select` and the weights written in place: the eager advanced-indexing
        gather of the (P, 3) int64 rows alone took ~4 ms on a bench G-buffer (262 144 samples, 1
        thread), `index_select` ~1 ms (session 20); the same values bit for bit as
        ``stack([1 − u − v, u, v])`` masked by ``where``."""
        idx = F.index_select(0, self.face.clamp_min(0))
        u, v = self.bary.unbind(-1)
        w = torch.empty(u.shape[0], 3, dtype=(1.0 - u).dtype, device=u.device)
        torch.sub(1.0 - u, v, out=w[:, 0])
        w[:, 1], w[:, 2] = u, v
        return idx, w.masked_fill_(~self.hit[:, None], 0.0)

    def interpolate(self, values: Tensor, F: Tensor) -> Tensor:
        """Barycentric interpolation of per-vertex ``values`` (N, ...) → per-sample (P, ...)."""
        idx, w = self.vertex_weights(F)
        vals = values[idx]  # (P, 3, ...)
        w = w.to(values.dtype).view(*w.shape, *([1] * (values.dim() - 1)))
        return (vals * w).sum(1)

    def to(self, device) -> "GBuffer":
        """This G-buffer with every array on ``device`` (a copy; itself if already there)."""
        device = torch.device(device)
        if self.hit.device == device:
            return self
        arrays = {k: getattr(self, k).to(device) for k in ("hit", "face", "bary", "position", "normal", "wo", "region",
                                                           "coverage")}
        return GBuffer(self.height, self.width, self.spp_side, **arrays)

    def resolve(self, per_sample: Tensor, *, channels_first: bool = False) -> Tensor:
        """Box-filter per-sample radiance (P, 3) into an image (H, W, 3); misses count as 0.

        ``channels_first``: the radiance is (3, P) (channel-major, the layout of batched shading
        kernels); the same image, from a reduction over contiguous sub-samples (~3× faster)."""
        if channels_first:
            if per_sample.shape != (3, self.num_samples):
                raise ValueError(f"channel-major radiance must be (3, {self.num_samples}), got {tuple(per_sample.shape)}")
            x = per_sample if bool(self.hit.all()) else \
                torch.where(self.hit, per_sample, torch.zeros((), dtype=per_sample.dtype, device=per_sample.device))
            img = x.view(3, self.height * self.width, self.spp_side**2).mean(-1)
            return img.T.reshape(self.height, self.width, 3).float()
        if per_sample.shape != (self.num_samples, 3):
            raise ValueError(f"per-sample radiance must be ({self.num_samples}, 3), got {tuple(per_sample.shape)}")
        x = torch.where(self.hit[:, None], per_sample, torch.zeros_like(per_sample))
        return x.view(self.height, self.width, self.spp_side**2, 3).mean(2).float()
