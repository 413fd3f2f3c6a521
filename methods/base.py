"""The common interface every relighting method implements, and the data it receives.

Contract (the harness relies on every word):

* ``Method(**config)`` — every parameter that changes a score is a keyword argument and is recorded
  in the results (``method.config``). Bad values raise ``ValueError`` at construction.
* ``precompute(scene)`` — all heavy work; timed by the harness. May cache to disk under
  ``cache_dir()`` keyed by ``scene.content_hash()`` and the config.
* ``render(frame, gbuffer) -> (H, W, 3)`` float32 linear RGB *exit radiance* towards the camera, for
  the pixels of ``gbuffer`` (pixels not covered return 0). Methods shade the G-buffer's sub-pixel
  samples and return ``gbuffer.resolve(per_sample)``, the box filter the references use.
  A method may cache work between frames of a sequence (``frame.changed`` says what changed since
  the previous frame) but must return the right image for every frame.
* ``memory() -> dict[str, int]`` — bytes of every array kept for run time, by name.
* ``capabilities`` — what the method claims; the harness never scores a cell outside it and the
  report says why ("n/a: static geometry only").

A *frame* holds everything that may change at run time: lighting (env map + rotation), camera,
per-region material parameters, and the pose of an articulated scene.
"""
from __future__ import annotations

import os
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import torch
from torch import Tensor

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
        from scenes.hashing import hash_frame  # local import: scenes depends on nothing here

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
        """Vertex indices (P, 3) and barycentric weights (P, 3) of each sample (0 on misses)."""
        f = self.face.clamp_min(0)
        idx = F[f]
        u, v = self.bary.unbind(-1)
        w = torch.stack([1.0 - u - v, u, v], dim=-1)
        w = torch.where(self.hit[:, None], w, torch.zeros_like(w))
        return idx, w

    def interpolate(self, values: Tensor, F: Tensor) -> Tensor:
        """Barycentric interpolation of per-vertex ``values`` (N, ...) → per-sample (P, ...)."""
        idx, w = self.vertex_weights(F)
        vals = values[idx]  # (P, 3, ...)
        w = w.to(values.dtype).view(*w.shape, *([1] * (values.dim() - 1)))
        return (vals * w).sum(1)

    def resolve(self, per_sample: Tensor) -> Tensor:
        """Box-filter per-sample radiance (P, 3) into an image (H, W, 3); misses count as 0."""
        if per_sample.shape != (self.num_samples, 3):
            raise ValueError(f"per-sample radiance must be ({self.num_samples}, 3), got {tuple(per_sample.shape)}")
        x = torch.where(self.hit[:, None], per_sample, torch.zeros_like(per_sample))
        return x.view(self.height, self.width, self.spp_side**2, 3).mean(2).float()


# -- capabilities -----------------------------------------------------------------------------


@dataclass(frozen=True)
class Capabilities:
    """What a method claims to handle. The harness builds cells only inside it."""

    dynamic_lighting: bool = True
    dynamic_view: bool = True
    dynamic_brdf: bool = False
    dynamic_geometry: bool = False
    max_bounces: int = 0  # 0 = direct lighting only
    brdfs: frozenset[str] = frozenset({"lambert", "phong", "blinnphong", "cooktorrance", "torrancesparrow", "ward"})

    def why_not(self, scene, sequence_kind: str, bounces: int) -> str | None:
        """None if the cell is in scope, else the reason shown in the report ("n/a: …")."""
        if sequence_kind == "P" and not self.dynamic_geometry:
            return "static geometry only"
        if getattr(scene, "skeleton", None) is not None and sequence_kind == "P" and not self.dynamic_geometry:
            return "static geometry only"
        if "B" in sequence_kind and not self.dynamic_brdf:
            return "BRDFs fixed at precompute"
        if "L" in sequence_kind and not self.dynamic_lighting:
            return "lighting fixed at precompute"
        if bounces > self.max_bounces:
            return f"at most {self.max_bounces} bounce(s)" if self.max_bounces else "direct lighting only"
        kinds = {m.kind for m in scene.materials.values()}
        missing = kinds - set(self.brdfs)
        if missing:
            return f"BRDF family not supported: {', '.join(sorted(missing))}"
        return None


# -- methods ----------------------------------------------------------------------------------


class Method(ABC):
    """Base class of every relighting method (see the module docstring for the contract)."""

    name: ClassVar[str]
    capabilities: ClassVar[Capabilities]
    # Opt in to the harness's disk cache of precomputations (``reports.precompute_cache``): the
    # instance's state after ``precompute`` must pickle, and depend only on (scene, config, code).
    cache_precompute: ClassVar[bool] = False

    def __init__(self, **config: Any) -> None:
        self.config: dict[str, Any] = dict(config)

    @abstractmethod
    def precompute(self, scene) -> None:
        """Heavy, lighting/view-independent work for ``scene`` (timed by the harness)."""

    @abstractmethod
    def render(self, frame: Frame, gbuffer: GBuffer) -> Tensor:
        """(H, W, 3) float32 linear-RGB exit radiance for ``frame`` on ``gbuffer``'s pixels."""

    @abstractmethod
    def memory(self) -> dict[str, int]:
        """Bytes of every array kept for run time, by name."""

    def with_bounces(self, bounces: int) -> "Method":
        """A method rendering exactly ``bounces`` indirect bounces, sharing this precomputation.
        Methods with ``capabilities.max_bounces > 0`` must implement it (the harness calls it after
        ``precompute`` with the cell's bounce count); raise ValueError for a count they cannot do."""
        if bounces != 0 or self.capabilities.max_bounces > 0:
            raise NotImplementedError(f"{type(self).__name__} does not implement with_bounces")
        return self

    def bytes_per_frame(self, frame_kind: str = "VBL") -> int | None:
        """Bytes a frame of this kind touches (for the roofline); None if unknown."""
        return None

    def __repr__(self) -> str:
        cfg = ", ".join(f"{k}={v!r}" for k, v in sorted(self.config.items()))
        return f"{type(self).__name__}({cfg})"


def tensor_bytes(*tensors: Tensor | None) -> int:
    """Total storage bytes of the given tensors (None ignored)."""
    return int(sum(t.element_size() * t.nelement() for t in tensors if t is not None))


# -- registry ---------------------------------------------------------------------------------

_REGISTRY: dict[str, type[Method]] = {}


def register(cls: type[Method]) -> type[Method]:
    """Class decorator: make a method available to the harness by ``cls.name``."""
    if not getattr(cls, "name", None):
        raise TypeError(f"{cls.__name__} has no `name`")
    _REGISTRY[cls.name] = cls
    return cls


def _load_builtin() -> None:
    import importlib

    # The module of each method that registers it (packages keep their __init__ light).
    for mod in ("methods.oracle", "methods.inout.method", "methods.zh_shadow", "methods.triple_product",
                "methods.ptt.method"):
        try:
            importlib.import_module(mod)
        except ModuleNotFoundError as e:  # a method package not written yet
            if e.name is None or not e.name.startswith(mod):
                raise


def available_methods() -> list[str]:
    _load_builtin()
    return sorted(_REGISTRY)


def get_method(name: str) -> type[Method]:
    _load_builtin()
    try:
        return _REGISTRY[name]
    except KeyError:
        raise KeyError(f"unknown method {name!r}; available: {', '.join(sorted(_REGISTRY))}") from None


def cache_dir(*parts: str) -> Path:
    """Root of generated data (git-ignored): ``$PRTBENCH_CACHE`` or ``<project>/.cache``."""
    root = Path(os.environ.get("PRTBENCH_CACHE", Path(__file__).resolve().parent.parent / ".cache"))
    p = root.joinpath(*parts)
    p.mkdir(parents=True, exist_ok=True)
    return p
