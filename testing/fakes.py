"""A tiny, torch-only stand-in for the project (scenes, G-buffers, references, metrics, methods)
so the harness, store, report and CLI can be tested in milliseconds. Used as
``Cell.backend = "testing.fakes"``; importing it registers the fake methods ``fake`` and
``fake_fail``. Nothing here is used by real runs.

The "truth" image of a frame is ``intensity · pattern`` on an H×W grid; a reference at ``spp``
adds Gaussian noise of std ``SIGMA/sqrt(spp)`` (two halves, so the noise floor is honest).
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import torch

from methods.base import Capabilities, Frame, GBuffer, Method, register, tensor_bytes

H = W = 8
SIGMA = 0.5  # per-sample std of the fake Monte Carlo estimator
SCENES = ["fake_plane", "fake_creature"]


@dataclass(frozen=True)
class FakeMaterial:
    kind: str = "lambert"
    kd: float = 0.5


@dataclass
class FakeScene:
    name: str
    size: str
    materials: dict = field(default_factory=lambda: {"floor": FakeMaterial()})
    skeleton: Any = None

    def content_hash(self) -> str:
        return f"{self.name}-{self.size}-{sorted(self.materials.items())}"


@dataclass
class FakeReference:
    image: torch.Tensor
    half_a: torch.Tensor
    half_b: torch.Tensor
    noise_floor: float
    coverage: torch.Tensor
    meta: dict


def get_scene(name: str, size: str = "test") -> FakeScene:
    if name not in SCENES:
        raise ValueError(f"unknown fake scene {name!r}")
    return FakeScene(name, size, skeleton=("bones" if name == "fake_creature" else None))


def scene_names() -> list[str]:
    return list(SCENES)


def is_dynamic(scene) -> bool:
    return scene.skeleton is not None


def make_sequence(scene, kind: str, n_frames: int, seed: int) -> list[Frame]:
    g = torch.Generator().manual_seed(seed)
    out = []
    for i in range(n_frames):
        inten = 1.0 + 0.5 * float(torch.rand((), generator=g))
        out.append(Frame(envmap=inten, camera=None, materials=dict(scene.materials), index=i,
                         changed=frozenset({"view", "brdf", "light", "pose"}) if i == 0 else frozenset({"view"})))
    return out


def geometry(scene, frame):
    V = torch.tensor([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
    F = torch.tensor([[0, 1, 2], [0, 2, 3]])
    return V, F


def _pattern() -> torch.Tensor:
    y, x = torch.meshgrid(torch.arange(H, dtype=torch.float32), torch.arange(W, dtype=torch.float32), indexing="ij")
    base = 0.2 + (x + 1) / W * 0.8 * (y + 1) / H
    return torch.stack([base, 0.8 * base, 0.6 * base], -1)  # (H, W, 3)


def _coverage() -> torch.Tensor:
    cov = torch.ones(H, W, dtype=torch.bool)
    cov[0, 0] = False  # one uncovered pixel, so masks are exercised
    return cov


def truth(frame) -> torch.Tensor:
    return float(frame.envmap) * _pattern()


def make_gbuffer(scene, frame, S: int) -> GBuffer:
    P = H * W * S * S
    y, x = torch.meshgrid(torch.arange(H), torch.arange(W), indexing="ij")
    u = ((x + 0.5) / W).repeat_interleave(S * S)  # pixel-major (y, x, s)
    v = ((y + 0.5) / H).repeat_interleave(S * S)
    face = (v > u).long().flatten()
    hit = _coverage().flatten().repeat_interleave(S * S)
    bary = torch.stack([u.flatten() * 0.5, v.flatten() * 0.5], -1).float()
    return GBuffer(height=H, width=W, spp_side=S, hit=hit, face=torch.where(hit, face, -1), bary=bary,
                   position=torch.zeros(P, 3), normal=torch.tensor([0.0, 0, 1]).expand(P, 3).clone(),
                   wo=torch.tensor([0.0, 0, 1]).expand(P, 3).clone(), region=torch.where(hit, 0, -1),
                   coverage=_coverage())


def render_reference(scene, frame, *, bounces: int, spp: int, seed: int, spp_side: int = 1) -> FakeReference:
    if spp < 2:
        raise ValueError("spp must be >= 2")
    g = torch.Generator().manual_seed(seed * 1000 + frame.index)
    t = truth(frame)
    s = SIGMA / math.sqrt(spp / 2)
    a = t + s * torch.randn(t.shape, generator=g)
    b = t + s * torch.randn(t.shape, generator=g)
    cov = _coverage()
    img = 0.5 * (a + b)
    floor = float(torch.sqrt(((a - b)[cov] ** 2).mean()) / 2)
    return FakeReference(img * cov[..., None], a, b, floor, cov,
                         {"render_seconds": 1e-3 + 1e-5 * spp, "spp": spp, "bounces": bounces})


def reference_seconds(ref) -> float | None:
    return ref.meta.get("render_seconds")


def timed_reference(scene, frame, *, bounces: int, spp: int, seed: int, spp_side: int = 1):
    ref = render_reference(scene, frame, bounces=bounces, spp=spp, seed=seed, spp_side=spp_side)
    return ref, reference_seconds(ref)


def make_exposure(ref, mask) -> float:
    return 1.0


def all_metrics(img, ref, mask, *, exposure=None) -> dict:
    d = (img - ref)[mask]
    mse = float((d**2).mean())
    rmse = math.sqrt(mse)
    return {"rmse": rmse, "psnr": 10 * math.log10(float(ref[mask].max()) ** 2 / max(mse, 1e-20)),
            "rel_mse": float((d**2 / (ref[mask] ** 2 + 1e-2)).mean())}


@register
class FakeMethod(Method):
    """Renders the fake truth times (1 + bias); ``delay`` seconds of sleep per frame."""

    name = "fake"
    capabilities = Capabilities(dynamic_brdf=False, max_bounces=0, brdfs=frozenset({"lambert"}))

    def __init__(self, *, bias: float = 0.05, delay: float = 0.0, _extra: dict | None = None):
        if delay < 0:
            raise ValueError("delay must be >= 0")
        super().__init__(bias=bias, delay=delay, **(_extra or {}))
        self.bias, self.delay = bias, delay
        self.coeffs: torch.Tensor | None = None

    def precompute(self, scene) -> None:
        self.coeffs = torch.ones(256)

    def render(self, frame, gbuffer) -> torch.Tensor:
        if self.delay:
            time.sleep(self.delay)
        img = truth(frame) * (1.0 + self.bias)
        return img * gbuffer.coverage[..., None]

    def memory(self) -> dict[str, int]:
        return {"coeffs": tensor_bytes(self.coeffs)}

    def bytes_per_frame(self, frame_kind: str = "VBL") -> int | None:
        return 4096


@register
class FakeFailingMethod(FakeMethod):
    """Raises in ``render`` (tests that one failing cell does not stop a run)."""

    name = "fake_fail"

    def render(self, frame, gbuffer):
        raise RuntimeError("planted failure")


@register
class FakeGIMethod(FakeMethod):
    """Claims one indirect bounce and dynamic BRDFs (tests the bounce / capability planning)."""

    name = "fake_gi"
    capabilities = Capabilities(dynamic_brdf=True, max_bounces=1, brdfs=frozenset({"lambert"}))

    def with_bounces(self, bounces: int) -> "FakeGIMethod":
        if bounces > 1:
            raise ValueError(f"at most 1 bounce, got {bounces}")
        WITH_BOUNCES_CALLS.append(bounces)
        return self


WITH_BOUNCES_CALLS: list[int] = []


@register
class FakeCachedMethod(FakeMethod):
    """Opts in to the harness's precompute cache; its precompute sleeps ``precompute_delay`` s and
    counts its calls in ``PRECOMPUTE_CALLS`` (tests of ``reports.precompute_cache``)."""

    name = "fake_cached"
    cache_precompute = True

    def __init__(self, *, bias: float = 0.05, delay: float = 0.0, precompute_delay: float = 0.05):
        super().__init__(bias=bias, delay=delay, _extra={"precompute_delay": precompute_delay})
        self.precompute_delay = precompute_delay

    def precompute(self, scene) -> None:
        PRECOMPUTE_CALLS.append(scene.name)
        time.sleep(self.precompute_delay)
        self.coeffs = torch.arange(256, dtype=torch.float32)


PRECOMPUTE_CALLS: list[str] = []
