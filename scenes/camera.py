"""Pinhole camera identical to Mitsuba 3's `perspective` sensor with `fov_axis='x'`.

Mitsuba's `look_at(origin, target, up)` gives camera axes (columns of to_world):
  dir = normalize(target − origin), left = normalize(up × dir), up' = dir × left.
A film sample (sx, sy) ∈ [0,1]² (0,0 = top-left) maps to the camera-space point
  ((1 − 2 sx)·tan(fov_x/2), (1 − 2 sy)·tan(fov_x/2)/aspect, 1),  aspect = W/H
(Mitsuba `perspective_projection`), so +x of the image runs towards −left (the right).
"""
from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor


# Largest film the harness accepts (width × height): G-buffers, references and method images hold
# several float32 values per sub-sample — a run measured ~1.4 KB per pixel in all (issue 17: 9 GB
# for 6.4 Mpx) — so the default, 2048² px (~6 GB), fits this 24-GiB machine kind with room and the
# bench sizes (256²) 64 times over; the environment variable overrides it.
# A film side above MAX_FILM_SIDE is refused too (a 100000 × 64 film is a typo, not a benchmark).
MAX_PIXELS = 2048 * 2048
MAX_PIXELS_ENV = "PRTBENCH_MAX_PIXELS"
MAX_FILM_SIDE = 4096
MAX_FILM_SIDE_ENV = "PRTBENCH_MAX_FILM_SIDE"


def _env_limit(var: str, default: int) -> int:
    """A positive integer limit from the environment variable ``var`` (``default`` if unset)."""
    raw = os.environ.get(var)
    if raw is None or raw.strip() == "":
        return default
    try:
        v = int(raw)
    except ValueError:
        raise ValueError(f"environment variable {var} must be a positive integer, got {raw!r}") from None
    if v < 1:
        raise ValueError(f"environment variable {var} must be a positive integer, got {raw!r}")
    return v


def max_pixels() -> int:
    """The film size limit in pixels: ``$PRTBENCH_MAX_PIXELS`` or `MAX_PIXELS`."""
    return _env_limit(MAX_PIXELS_ENV, MAX_PIXELS)


def max_film_side() -> int:
    """The film width/height limit: ``$PRTBENCH_MAX_FILM_SIDE`` or `MAX_FILM_SIDE`."""
    return _env_limit(MAX_FILM_SIDE_ENV, MAX_FILM_SIDE)


def _vec3(x, name: str) -> tuple[float, float, float]:
    a = np.asarray(x, dtype=np.float64).reshape(-1)
    if a.shape != (3,) or not np.isfinite(a).all():
        raise ValueError(f"camera {name} must be 3 finite numbers, got {x!r}")
    return tuple(float(v) for v in a)


@dataclass(frozen=True)
class Camera:
    """origin, target, up: 3-vectors; fov_deg: horizontal field of view; width, height: film pixels."""

    origin: tuple[float, float, float]
    target: tuple[float, float, float]
    up: tuple[float, float, float]
    fov_deg: float
    width: int
    height: int
    near_clip: float = 1e-2  # Mitsuba's default; ray origins lie on the near plane like Mitsuba's

    def __post_init__(self) -> None:
        object.__setattr__(self, "origin", _vec3(self.origin, "origin"))
        object.__setattr__(self, "target", _vec3(self.target, "target"))
        object.__setattr__(self, "up", _vec3(self.up, "up"))
        if not (0.0 < float(self.fov_deg) < 180.0):
            raise ValueError(f"camera fov_deg must be in (0, 180), got {self.fov_deg}")
        object.__setattr__(self, "fov_deg", float(self.fov_deg))
        if not (float(self.near_clip) > 0.0):
            raise ValueError(f"camera near_clip must be > 0, got {self.near_clip}")
        object.__setattr__(self, "near_clip", float(self.near_clip))
        for k in ("width", "height"):
            v = getattr(self, k)
            if int(v) != v or int(v) < 1:
                raise ValueError(f"camera {k} must be a positive integer, got {v!r}")
            object.__setattr__(self, k, int(v))
        side = max_film_side()
        for k in ("width", "height"):
            if getattr(self, k) > side:
                raise ValueError(f"camera {k} = {getattr(self, k)} exceeds the limit of {side} pixels "
                                 f"(set {MAX_FILM_SIDE_ENV} to raise it)")
        limit = max_pixels()
        if self.width * self.height > limit:
            raise ValueError(f"camera width × height = {self.width} × {self.height} = "
                             f"{self.width * self.height} pixels exceeds the limit of {limit} "
                             f"(set {MAX_PIXELS_ENV} to raise it)")
        d = np.subtract(self.target, self.origin)
        if np.linalg.norm(d) == 0:
            raise ValueError("camera origin and target coincide")
        if np.linalg.norm(np.cross(self.up, d)) < 1e-9 * np.linalg.norm(d) * max(np.linalg.norm(self.up), 1e-300):
            raise ValueError("camera up is parallel to the viewing direction (or zero)")

    # -- frame -------------------------------------------------------------------------------

    def axes(self) -> np.ndarray:
        """(3, 3) float64 matrix with columns (left, up', dir) — Mitsuba look_at's rotation."""
        o, t, u = (np.asarray(x, np.float64) for x in (self.origin, self.target, self.up))
        d = (t - o) / np.linalg.norm(t - o)
        left = np.cross(u, d)
        left /= np.linalg.norm(left)
        new_up = np.cross(d, left)
        return np.stack([left, new_up, d], axis=1)

    def to_world(self) -> np.ndarray:
        """(4, 4) float64 camera-to-world matrix (Mitsuba's `look_at`)."""
        M = np.eye(4)
        M[:3, :3] = self.axes()
        M[:3, 3] = self.origin
        return M

    @property
    def aspect(self) -> float:
        return self.width / self.height

    # -- rays --------------------------------------------------------------------------------

    def rays(self, px: Tensor) -> tuple[Tensor, Tensor]:
        """Primary rays through film positions.

        Args:
            px: (P, 2) pixel coordinates in [0, W]×[0, H]; (0, 0) is the top-left corner,
                +x right, +y down (pixel (i, j)'s centre is (i + 0.5, j + 0.5)).
        Returns:
            o (P, 3) ray origins on the near plane (origin + d·near_clip/cosθ, as Mitsuba's
            `perspective.sample_ray`), d (P, 3) unit directions, in px's
            floating dtype (float32 for integer input) and device.
        """
        px = torch.as_tensor(px)
        if px.dim() != 2 or px.shape[1] != 2:
            raise ValueError(f"px must be (P, 2), got {tuple(px.shape)}")
        dtype = px.dtype if px.is_floating_point() else torch.float32
        p = px.to(torch.float64)
        sx = p[:, 0] / self.width
        sy = p[:, 1] / self.height
        tx = math.tan(math.radians(self.fov_deg) / 2)
        ty = tx / self.aspect
        local = torch.stack([(1 - 2 * sx) * tx, (1 - 2 * sy) * ty, torch.ones_like(sx)], dim=1)
        local = local / local.norm(dim=1, keepdim=True)
        R = torch.as_tensor(self.axes(), dtype=torch.float64, device=px.device)
        d = local @ R.T
        near_t = self.near_clip / local[:, 2:3]
        o = torch.as_tensor(self.origin, dtype=torch.float64, device=px.device) + d * near_t
        return o.to(dtype), d.to(dtype)

    def pixel_rays(self, spp_side: int = 1) -> tuple[Tensor, Tensor]:
        """Rays through an S×S stratified grid in every pixel, ordered (y, x, s): (H·W·S², 3) each."""
        S = int(spp_side)
        j, i, s = torch.meshgrid(torch.arange(self.height), torch.arange(self.width), torch.arange(S * S), indexing="ij")
        sx = (s % S + 0.5) / S
        sy = (s // S + 0.5) / S
        px = torch.stack([i + sx, j + sy], -1).reshape(-1, 2).double()
        o, d = self.rays(px)
        return o.float(), d.float()

    def look_dir(self) -> np.ndarray:
        return self.axes()[:, 2]

    def orbited(self, angle_rad: float, axis=(0.0, 1.0, 0.0)) -> "Camera":
        """Copy rotated about `axis` through the target by `angle_rad` (right-hand rule)."""
        k = np.asarray(axis, float)
        k /= np.linalg.norm(k)
        Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        R = np.eye(3) + math.sin(angle_rad) * Kx + (1 - math.cos(angle_rad)) * Kx @ Kx
        t = np.asarray(self.target)
        o = t + R @ (np.asarray(self.origin) - t)
        return Camera(tuple(o), self.target, tuple(R @ np.asarray(self.up)), self.fov_deg, self.width, self.height,
                      self.near_clip)

    def params(self) -> dict:
        """JSON-able description (used by hashing)."""
        return {"origin": list(self.origin), "target": list(self.target), "up": list(self.up),
                "fov_deg": self.fov_deg, "width": self.width, "height": self.height, "near_clip": self.near_clip}
