"""The common interface every relighting method implements, and the data it receives.

Contract (the harness relies on every word):

* ``Method(**config)`` — every parameter that changes a score is a keyword argument and is recorded
  in the results (``method.config``, read-only: fixed at construction, so the recorded config is
  the one that ran). Bad values raise ``ValueError`` at construction.
* ``precompute(scene)`` — all heavy work; timed by the harness. A method keeps no disk cache of
  its own: with ``cache_precompute = True`` the harness stores its state after ``precompute``
  (``reports.precompute_cache``) and reports the original precompute seconds.
* ``render(frame, gbuffer) -> (H, W, 3)`` float32 linear RGB *exit radiance* towards the camera, for
  the pixels of ``gbuffer`` (pixels not covered return 0). Methods shade the G-buffer's sub-pixel
  samples and return ``gbuffer.resolve(per_sample)``, the box filter the references use.
  A method may cache work between frames of a sequence (``frame.changed`` says what changed since
  the previous frame) but must return the right image for every frame.
* ``memory() -> dict[str, int]`` — bytes of every array kept for run time, by name.
* ``capabilities`` — what the method claims; the harness never scores a cell outside it and the
  report says why ("n/a: static geometry only"). A class attribute; a method whose claims depend on
  its config sets ``self.capabilities`` in ``__init__`` from the config alone (the harness plans
  cells from an instance built with the cell's config).

A *frame* holds everything that may change at run time: lighting (env map + rotation), camera,
per-region material parameters, and the pose of an articulated scene.
"""
from __future__ import annotations

import contextlib
import contextvars
import copy
import dataclasses
from abc import ABC, abstractmethod
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, ClassVar

import torch
from torch import Tensor

from scenes.frame import Frame, GBuffer  # noqa: F401  (re-exported: part of the Method contract)
from scenes.io import cache_dir  # noqa: F401  (re-exported for methods' convenience)

# -- shared precompute pieces -----------------------------------------------------------------
# A caller that precomputes many instances of one method on one geometry (the terms-vs-exponent
# study: every rung of a term ladder at every Phong exponent) may open ``shared_precompute(memo)``
# around their ``precompute`` calls. A method that supports it (``precompute_memo()`` is not None)
# stores in ``memo`` the pieces of its precompute that depend on neither the config keys the caller
# varies nor the material it varies — keyed by *everything* they do depend on (`geometry_key`,
# config values, material hashes) — and takes them from there instead of recomputing: the same
# objects, so the same numbers, and never mutated afterwards (tests compare with and without).
# Without a memo (the harness, the nightly runs) nothing changes. A context variable, not an
# attribute: the precompute cache stores a method's ``__dict__`` and must not see the memo.
_PRECOMPUTE_MEMO: contextvars.ContextVar[dict | None] = contextvars.ContextVar("precompute_memo", default=None)


@contextlib.contextmanager
def shared_precompute(memo: dict) -> Iterator[dict]:
    """Let the ``precompute`` calls inside the block share rung-independent pieces through ``memo``
    (a dict the caller owns and drops; comment above)."""
    if not isinstance(memo, dict):
        raise ValueError(f"memo must be a dict, got {type(memo).__name__}")
    token = _PRECOMPUTE_MEMO.set(memo)
    try:
        yield memo
    finally:
        _PRECOMPUTE_MEMO.reset(token)


def precompute_memo() -> dict | None:
    """The memo of the enclosing `shared_precompute` block, or None."""
    return _PRECOMPUTE_MEMO.get()


def geometry_key(*tensors: Tensor) -> str:
    """sha256 over the dtype, shape and bytes of ``tensors`` (a memo key of geometry-only pieces)."""
    import hashlib

    h = hashlib.sha256()
    for t in tensors:
        a = torch.as_tensor(t).detach().cpu().contiguous()
        h.update(f"{a.dtype}{tuple(a.shape)}".encode())
        h.update(a.numpy().tobytes())
    return h.hexdigest()


# -- capabilities -----------------------------------------------------------------------------


@dataclass(frozen=True)
class Capabilities:
    """What a method claims to handle. The harness builds cells only inside it."""

    dynamic_lighting: bool = True
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
        if ("L" in sequence_kind or sequence_kind == "E") and not self.dynamic_lighting:
            return "lighting fixed at precompute"
        if bounces > self.max_bounces:
            return f"at most {self.max_bounces} bounce(s)" if self.max_bounces else "direct lighting only"
        kinds = {m.kind for m in scene.materials.values()}
        missing = kinds - set(self.brdfs)
        if missing:
            return f"BRDF family not supported: {', '.join(sorted(missing))}"
        return None


# -- cost model -------------------------------------------------------------------------------


@dataclass(frozen=True)
class FrameCost:
    """The compulsory work of one frame (``Method.frame_cost``), what the roofline divides by the
    machine's limits: efficiency = max(bytes / bandwidth, flops / peak, rays / ray rate) / frame time.

    bytes: bytes the frame must move at least once — every run-time array it reads (each element
        once, a perfect cache), the G-buffer inputs it reads (at their dtypes: the hit flag is a 1-byte
        bool), and the (H, W, 3) float32 image it returns (`output_bytes`). The per-sample radiance is
        not output: a frame may average a pixel's S² samples as it shades them (session 36: before, the
        counts had the hit flag as a 4-byte word and a (P, 3) output, 3·P + 12·(P − H·W) bytes too many,
        3.1 MB a bench frame).
    flops: floating-point operations it must do (a multiply-add counts 2), for the arithmetic that
        the method's equations require per frame (not work a faster implementation could skip).
    rays: occlusion queries (shadow rays) the frame must trace against the scene's triangles — those
        whose answer the estimate needs (a ray whose contribution is zero whatever it hits is not
        compulsory). A BVH traversal is neither a stream of bytes nor dense arithmetic, so neither roof
        bounds it; its roof is the ray rate the machine's fastest tracer reaches on the same scene from
        the same G-buffer points, measured in the run (``reports.measure.ray_rate``; session 38). 0 for
        methods whose frame traces nothing (every PRT method: visibility is precomputed).
    """

    bytes: int
    flops: int
    rays: int = 0

    def __post_init__(self) -> None:
        if self.bytes < 0 or self.flops < 0 or self.rays < 0:
            raise ValueError(f"FrameCost must be non-negative, got {self}")

    def bound(self, bandwidth: float, peak_flops: float, ray_rate: float | None = None) -> tuple[float, str]:
        """(seconds at the roofline, "memory" | "compute" | "traversal"): the largest of the lower
        bounds. Without a ``ray_rate`` the rays bound nothing (a lower bound stays a lower bound)."""
        terms = [(self.bytes / bandwidth, "memory"), (self.flops / peak_flops, "compute")]
        if self.rays and ray_rate is not None and ray_rate > 0:
            terms.append((self.rays / ray_rate, "traversal"))
        return max(terms, key=lambda t: t[0])


GBUFFER_HIT_BYTES = 1  # the hit flag (``GBuffer.hit``: bool)
GBUFFER_BYTES_PER_SAMPLE = 4 * (3 + 3) + GBUFFER_HIT_BYTES + 8 + 8  # what shading reads per sample: normal,
# wo (float32), hit (bool), face index (int64) and barycentrics (2 × float32); methods add what else they read


def output_bytes(num_samples: int, pixels: int | None) -> int:
    """Bytes of a frame's output (``FrameCost``): the (H, W, 3) float32 image ``render`` returns —
    ``pixels`` = H·W; None (a caller that does not say): ``num_samples``, an upper bound."""
    n = num_samples if pixels is None else pixels
    if isinstance(n, bool) or not isinstance(n, int) or n < 0 or n > num_samples:
        raise ValueError(f"pixels must be an int in [0, num_samples={num_samples}], got {pixels!r}")
    return n * 3 * 4


# -- methods ----------------------------------------------------------------------------------


class Method(ABC):
    """Base class of every relighting method (see the module docstring for the contract)."""

    name: ClassVar[str]
    capabilities: ClassVar[Capabilities]
    # Opt in to the harness's disk cache of precomputations (``reports.precompute_cache``): the
    # instance's state after ``precompute`` must depend only on (scene, config, code) and hold only
    # tensors, numpy arrays, scalars, containers and instances of classes from methods/ and scenes/.
    cache_precompute: ClassVar[bool] = False
    # Config keys that only `render` reads: the state `precompute` leaves is the same for every value
    # of them (tests/reports/test_precompute_cache_methods.py checks it), so the precompute cache
    # keys an entry without them and cells that differ only in them share one precomputation.
    render_config_keys: ClassVar[tuple[str, ...]] = ()

    def __init__(self, **config: Any) -> None:
        self._config: dict[str, Any] = dict(config)

    @property
    def config(self) -> Mapping[str, Any]:
        """The constructor's keyword arguments (read-only: ``method.config[k] = v`` raises)."""
        return MappingProxyType(self._config)

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

    def frame_cost(self, frame_kind: str, num_samples: int, *, pixels: int | None = None) -> "FrameCost | None":
        """The compulsory work of one frame of ``frame_kind`` (a sequence kind: which inputs changed)
        on a G-buffer of ``num_samples`` samples and ``pixels`` = H·W pixels (the output image,
        `output_bytes`; None: ``num_samples``) — the roofline's numerators (``FrameCost``). Called
        after ``precompute``; None = not modelled. The count is the minimum any implementation of
        the method must do, never what ours happens to do: arrays read once, no padding."""
        return None

    def bytes_per_frame(self, frame_kind: str = "VBL") -> int | None:
        """Deprecated: bytes a frame touches, without the G-buffer (use ``frame_cost``)."""
        return None

    def to(self, device) -> "Method":
        """This (precomputed) method with every run-time tensor on ``device``: a copy whose tensor
        attributes — also inside dicts, lists, tuples and objects of this project's classes — are
        moved; shared inputs (the scene) are copied, never moved in place. Methods render on the
        device of their arrays and of the G-buffer (device-agnostic torch), so the harness calls
        ``method.to(d)`` after ``precompute`` and renders ``gbuffer.to(d)``."""
        device = torch.device(device)
        memo: dict[int, Any] = {}
        m = copy.copy(self)
        m.__dict__ = {k: _to_device(v, device, memo) for k, v in self.__dict__.items()}
        return m

    def __repr__(self) -> str:
        cfg = ", ".join(f"{k}={v!r}" for k, v in sorted(self.config.items()))
        return f"{type(self).__name__}({cfg})"


def _to_device(x, device, memo: dict[int, Any]):
    """``x`` with its tensors on ``device`` (``Method.to``): containers and project objects are
    rebuilt (memoised by identity, so shared and cyclic references stay shared), other values kept."""
    if isinstance(x, (str, bytes, int, float, bool, type(None), torch.device, torch.dtype)):
        return x
    if id(x) in memo:
        return memo[id(x)]
    if isinstance(x, Tensor):
        memo[id(x)] = out = x if x.device == device else x.to(device)
        return out
    if isinstance(x, dict):
        out: Any = {}
        memo[id(x)] = out
        out.update({k: _to_device(v, device, memo) for k, v in x.items()})
        return out
    if isinstance(x, list):
        out = []
        memo[id(x)] = out
        out.extend(_to_device(v, device, memo) for v in x)
        return out
    if isinstance(x, tuple) and not hasattr(x, "_fields"):
        out = tuple(_to_device(v, device, memo) for v in x)
        memo[id(x)] = out
        return out
    mod = type(x).__module__ or ""
    if hasattr(x, "__dict__") and not isinstance(x, type) and mod.split(".")[0] in ("methods", "scenes"):
        out = copy.copy(x)
        memo[id(x)] = out
        if dataclasses.is_dataclass(x) and getattr(type(x), "__dataclass_params__").frozen:
            for k, v in x.__dict__.items():
                object.__setattr__(out, k, _to_device(v, device, memo))
        else:
            out.__dict__.update({k: _to_device(v, device, memo) for k, v in x.__dict__.items()})
        return out
    return x


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
