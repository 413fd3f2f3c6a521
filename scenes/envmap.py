"""Lat-long environment maps with Mitsuba 3.9's `envmap` conventions (docs/ARCHITECTURE.md).

Mapping (mitsuba3 src/emitters/envmap.cpp, `direction_to_uv` and `eval_spectrum`): a local
direction d goes to
    u = atan2(d.x, −d.z)/(2π),  v = acos(d.y)/π,
then ``u −= 0.5/W`` (half-texel shift: columns are texel-centred, u = (x+0.5)/W), ``uv −= floor(uv)``
(wrapping; note this is applied to v too, so the exact south pole d.y = −1 wraps to v = 0 as in
Mitsuba), ``x = u·W``, ``y = v·(H−1)`` (rows are corner-aligned, v = y/(H−1)), and the texel
values are interpolated bilinearly in an image extended by one column that repeats column 0
(Mitsuba's "periodic boundary" column). Row 0 is the top of the image (d.y = +1).
Inverse (`uv_to_direction`): φ = 2πu, θ = πv, d = (sinφ sinθ, cosθ, −cosφ sinθ).

`EnvMap.to_world` is the emitter's to_world rotation; a world direction d is looked up at
``to_world.T @ d``.

Importance sampling (our own, not Mitsuba's Hierarchical2D): piecewise constant in solid angle
over the W×(H−1) cells of the bilinear lattice (cell (i, j) spans lattice columns j..j+1 and rows
i..i+1). A cell's probability is proportional to the mean luminance of its 4 corner texels times
its solid angle; within a cell, directions are uniform in (φ, cosθ), i.e. uniform in solid angle.
A cell's bilinear radiance is positive somewhere iff its probability is positive, so MIS with the
BRDF stays unbiased. ``pdf(d)`` is exactly the density of ``sample``.
"""
from __future__ import annotations

import math
import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from methods.core.latlong import bilinear_taps
from methods.core.threads import torch_threads

# Rec.709 luminance weights (Mitsuba's `luminance()` for RGB).
_LUM = (0.212671, 0.715160, 0.072169)

PROCEDURAL_NAMES = ("sky_sun", "studio", "window", "overcast")

# Captured HDR light probes vendored under scenes/assets/probes/ (sources and licences in
# scenes/assets/ASSETS.md). Stored lat-long at PROBE_HEIGHT rows × 2·PROBE_HEIGHT columns.
PROBE_NAMES = ("courtyard", "forest", "interior", "sunrise")
PROBE_DIR = Path(__file__).resolve().parent / "assets" / "probes"
PROBE_HEIGHT = 256

# to_world must be a rotation to this tolerance (float32 round-off of a composed rotation).
_ROTATION_TOL = 1e-4

# Largest env map accepted (H × W texels; the bench maps are far smaller): the texels, their
# sampling tables and the methods' projections are each several float32/float64 copies of the map.
# Default 4096 × 8192; the environment variable overrides it.
MAX_ENV_TEXELS = 4096 * 8192
MAX_ENV_TEXELS_ENV = "PRTBENCH_MAX_ENV_TEXELS"
# An env map whose brightest texel or solid-angle mean luminance is at or below this lights
# nothing measurable: every method would score a "perfect" error of ~0 against a black reference.
MIN_ENV_RADIANCE = 1e-6


def max_env_texels() -> int:
    """The env-map size limit in texels: ``$PRTBENCH_MAX_ENV_TEXELS`` or `MAX_ENV_TEXELS`."""
    raw = os.environ.get(MAX_ENV_TEXELS_ENV)
    if raw is None or raw.strip() == "":
        return MAX_ENV_TEXELS
    try:
        v = int(raw)
    except ValueError:
        v = 0
    if v < 1:
        raise ValueError(f"environment variable {MAX_ENV_TEXELS_ENV} must be a positive integer, got {raw!r}")
    return v


class TooLarge(ValueError):
    """An env map above the size limit (`check_size`)."""


def check_size(height: int, width: int, what: str = "env map") -> None:
    """`TooLarge` (a ValueError) if an H × W map exceeds `max_env_texels()` (call before allocating it)."""
    limit = max_env_texels()
    if height * width > limit:
        raise TooLarge(f"{what} height × width = {height} × {width} = {height * width} texels exceeds the "
                         f"limit of {limit} (set {MAX_ENV_TEXELS_ENV} to raise it)")


def check_lit(env: "EnvMap", what: str = "env map") -> "EnvMap":
    """``env`` if it lights the scene; ValueError if it is black or nearly black (its brightest
    texel, or its solid-angle mean luminance, is at most `MIN_ENV_RADIANCE`)."""
    peak = float(env.data.max())
    if peak <= MIN_ENV_RADIANCE:
        raise ValueError(f"{what} is black (brightest texel {peak:.3g} <= {MIN_ENV_RADIANCE:g}): it lights nothing, "
                         f"so every method would score a perfect error against a black reference")
    lum = float((env.mean_radiance().double() * torch.tensor(_LUM, dtype=torch.float64)).sum())
    if lum <= MIN_ENV_RADIANCE:
        raise ValueError(f"{what} is nearly black (mean luminance {lum:.3g} <= {MIN_ENV_RADIANCE:g} over the sphere): "
                         f"it lights nothing measurable")
    return env


def _as_rotation(R) -> Tensor:
    R = torch.as_tensor(np.asarray(R.detach().cpu() if isinstance(R, Tensor) else R, dtype=np.float64))
    if R.shape != (3, 3):
        raise ValueError(f"to_world must be a (3, 3) rotation matrix, got shape {tuple(R.shape)}")
    if not torch.isfinite(R).all():
        raise ValueError("to_world contains NaN/Inf")
    err = (R @ R.T - torch.eye(3, dtype=R.dtype)).abs().max().item()
    if err > _ROTATION_TOL or torch.linalg.det(R).item() < 0:
        raise ValueError(f"to_world must be a proper rotation (orthonormal, det +1); |R R^T − I| = {err:.2e}")
    return R


def _check_data(data) -> Tensor:
    if isinstance(data, Tensor):
        t = data.detach().to("cpu", torch.float32)
    else:
        try:
            t = torch.from_numpy(np.ascontiguousarray(np.asarray(data, dtype=np.float32)))
        except (TypeError, ValueError) as e:
            raise ValueError(f"env map data must be a numeric (H, W, 3) array: {e}") from None
    if t.ndim != 3 or t.shape[2] != 3:
        raise ValueError(f"env map data must have shape (H, W, 3), got {tuple(t.shape)}")
    if t.shape[0] < 3 or t.shape[1] < 2:
        raise ValueError(f"env map must be at least 3 rows × 2 columns (Mitsuba's limit), got {tuple(t.shape)}")
    check_size(int(t.shape[0]), int(t.shape[1]))
    if not torch.isfinite(t).all():
        raise ValueError("env map data contains NaN/Inf texels")
    if (t < 0).any():
        raise ValueError("env map data contains negative texels")
    return t.contiguous()


def direction_to_uv(d: Tensor) -> tuple[Tensor, Tensor]:
    """Local directions (..., 3) → lat-long (u, v) ∈ [−½, ½] × [0, 1] (Mitsuba `direction_to_uv`)."""
    u = torch.atan2(d[..., 0], -d[..., 2]) * (0.5 / math.pi)
    v = torch.acos(d[..., 1].clamp(-1.0, 1.0)) * (1.0 / math.pi)
    return u, v


def uv_to_direction(u: Tensor, v: Tensor) -> Tensor:
    """(u, v) (...) → local unit directions (..., 3) (Mitsuba `uv_to_direction`)."""
    theta, phi = v * math.pi, u * (2.0 * math.pi)
    st = torch.sin(theta)
    return torch.stack([torch.sin(phi) * st, torch.cos(theta), -torch.cos(phi) * st], dim=-1)


def extend_periodic(data: Tensor) -> Tensor:
    """(H, W, 3) → (H·(W+1), 3): Mitsuba's extra column repeating column 0 (periodic boundary)."""
    return torch.cat([data, data[:, :1]], dim=1).reshape(-1, 3)


def bilinear_lookup(data: Tensor, d_local: Tensor, ext: Tensor | None = None) -> Tensor:
    """Mitsuba envmap `eval_spectrum` for local directions.

    Args:
        data: (H, W, 3) texels; d_local: (..., 3) unit directions in the emitter frame;
        ext: optional precomputed `extend_periodic(data)` in d_local's dtype/device.
    Returns:
        (..., 3) radiance, dtype/device of d_local.
    """
    H, W, _ = data.shape
    if ext is None:
        ext = extend_periodic(data.to(d_local.device, d_local.dtype))
    u, v = direction_to_uv(d_local)
    idx, fx, fy = bilinear_taps(u, v, H, W)  # texel-centred columns, u wraps
    w1x, w1y = fx[..., None], fy[..., None]
    w0x, w0y = 1.0 - w1x, 1.0 - w1y
    v00, v10 = ext[idx], ext[idx + 1]
    v01, v11 = ext[idx + W + 1], ext[idx + W + 2]
    v0 = w0x * v00 + w1x * v10
    v1 = w0x * v01 + w1x * v11
    return w0y * v0 + w1y * v1


def count_le(cdf: Tensor, x: Tensor) -> Tensor:
    """``torch.searchsorted(cdf, x, right=True)`` for a non-decreasing ``cdf`` (C,): the number of
    entries <= x, by a branchless binary search of ⌊log₂ C⌋ + 1 fixed steps (Shar's search, each a
    gather and a compare) — compiled, 2× faster than ``searchsorted``'s branching search on a
    32K-entry table (scalar, int64 of x's shape)."""
    C = cdf.shape[0]
    k = torch.zeros_like(x, dtype=torch.int64)
    step = 1 << (C.bit_length() - 1) if C else 0
    while step:
        j = (k + (step - 1)).clamp(max=C - 1)
        k = torch.where((k + step <= C) & (cdf[j] <= x), k + step, k)
        step >>= 1
    return k


def sample_cells(u: Tensor, cdf: Tensor, p_flat: Tensor, omega: Tensor, R: Tensor, H: int, W: int,
                 branchless: bool = False) -> tuple[Tensor, Tensor]:
    """`EnvMap.sample` on its tables (a pure tensor function: the oracle compiles it).

    Args:
        u: (..., 2) uniforms; cdf, p_flat: (C,) float64 cumulative and cell probabilities of the
            C = (H − 1)·W cells (``EnvMap._tables``); omega: (H − 1,) float64 cell solid angles;
            R: (3, 3) float64 emitter→world rotation; H, W: the map's size; branchless: the CDF
            search by `count_le` (the same cells; for compiled callers) instead of ``searchsorted``.
    Returns:
        d (..., 3) world unit directions and pdf (...) w.r.t. solid angle, both float64.
    """
    u0, u1 = u[..., 0].double(), u[..., 1].double()
    k = count_le(cdf, u0) if branchless else torch.searchsorted(cdf, u0.contiguous(), right=True)
    k = k.clamp(max=cdf.numel() - 1)
    # right=True: the first cell with cdf > u0, never a zero-probability cell
    lo = torch.where(k > 0, cdf[(k - 1).clamp_min(0)], torch.zeros_like(u0))
    pk = p_flat[k]
    r = ((u0 - lo) / pk.clamp_min(1e-300)).clamp(0.0, 1.0)
    iy, ix = k // W, k % W
    phi = 2 * math.pi * (ix.double() + 0.5 + r) / W
    z_top = torch.cos(math.pi * iy.double() / (H - 1))
    z_bot = torch.cos(math.pi * (iy.double() + 1) / (H - 1))
    zc = z_top - u1 * (z_top - z_bot)
    st = (1 - zc * zc).clamp_min(0).sqrt()
    d_local = torch.stack([torch.sin(phi) * st, zc, -torch.cos(phi) * st], -1)
    pdf = pk / omega[iy]
    return d_local @ R.T, pdf


def cell_pdf(d: Tensor, p: Tensor, omega: Tensor, R: Tensor) -> Tensor:
    """`EnvMap.pdf` on its tables (pure, compiled by the oracle): world directions d (..., 3) →
    float64 solid-angle density (...); p (H − 1, W), omega (H − 1,), R (3, 3), all float64."""
    H, W = p.shape[0] + 1, p.shape[1]
    dl = d.double() @ R  # EnvMap.to_local
    u, v = direction_to_uv(dl)
    xf = u * W - 0.5
    ix = torch.remainder(torch.floor(xf).to(torch.int64), W)
    iy = torch.floor(v * (H - 1)).to(torch.int64).clamp(0, H - 2)
    return p[iy, ix] / omega[iy]


class EnvMap:
    """A lat-long HDR environment map (radiance, linear Rec.709 RGB) and its rotation.

    data: (H, W, 3) float32 texels, row 0 = top (+Y); to_world: (3, 3) rotation (emitter→world).
    """

    def __init__(self, data, to_world=None) -> None:
        self.data: Tensor = _check_data(data)
        self.to_world: Tensor = _as_rotation(np.eye(3) if to_world is None else to_world)
        self._table: tuple[Tensor, Tensor, Tensor] | None = None  # sampling tables (lazy)
        self._ext: dict = {}  # (device, dtype, planes) → periodic-extended texels (`periodic_texels`)

    # -- basics
    @property
    def height(self) -> int:
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        return int(self.data.shape[1])

    def __repr__(self) -> str:
        return f"EnvMap({self.height}×{self.width}, to_world={self.to_world.tolist()})"

    def rotated(self, R) -> "EnvMap":
        """The same map rotated by R (3, 3): new to_world = R @ to_world; shares the data."""
        out = EnvMap.__new__(EnvMap)
        out.data = self.data
        out.to_world = _as_rotation(_as_rotation(R) @ self.to_world)
        out._table = self._table
        out._ext = self._ext  # same data ⇒ same extended copies
        return out

    def to_local(self, d: Tensor) -> Tensor:
        """World directions (..., 3) → emitter frame: to_world.T @ d."""
        R = self.to_world.to(d.device, d.dtype)
        return d @ R  # (d @ R)_j = Σ_i d_i R_ij = (R^T d)_j

    def to_world_dirs(self, d_local: Tensor) -> Tensor:
        R = self.to_world.to(d_local.device, d_local.dtype)
        return d_local @ R.T

    def radiance(self, d: Tensor) -> Tensor:
        """Radiance arriving from world directions d (..., 3) (unit) → (..., 3); equals Mitsuba's
        envmap ``eval`` with ``si.wi = −d``."""
        if d.shape[-1] != 3:
            raise ValueError(f"directions must have shape (..., 3), got {tuple(d.shape)}")
        return bilinear_lookup(self.data, self.to_local(d), self.periodic_texels(d.device, d.dtype))

    def periodic_texels(self, device=None, dtype=torch.float32, *, planes: bool = False) -> Tensor:
        """`extend_periodic` (data) on ``device`` in ``dtype``, (H·(W+1), 3): the table `radiance`
        interpolates; ``planes=True``: its transpose as contiguous channel planes (3, H·(W+1)).
        Cached per (device, dtype, planes) and shared by `rotated` copies (same data)."""
        key = (torch.device("cpu") if device is None else torch.device(device), dtype, bool(planes))
        if key not in self._ext:
            ext = extend_periodic(self.data.to(key[0], dtype))
            self._ext[key] = ext.T.contiguous() if planes else ext
        return self._ext[key]

    def box_downsampled(self, k: int) -> "EnvMap":
        """The map with each k×k block of texels averaged (as `probe` sizes the vendored maps),
        same rotation; k must divide height and width and leave ≥ 3 rows. k = 1: ``self``."""
        k = int(k)
        if k == 1:
            return self
        if k < 1 or self.height % k or self.width % k or self.height // k < 3:
            raise ValueError(f"cannot box-downsample a {self.height}x{self.width} env map by {k}")
        d = self.data.double().reshape(self.height // k, k, self.width // k, k, 3).mean((1, 3))
        return EnvMap(d.float(), self.to_world)

    def prefiltered_for_spacing(self, spacing: float) -> "EnvMap":
        """The map box-downsampled (by a power of two) until its texels are at least twice a point
        sampler's ``spacing`` (radians), so that every texel gets sub-samples: a sampler coarser
        than the texels aliases a small bright source (a sun of a few texels is missed or counted
        over a whole sample's solid angle). ``self`` when its texels are already that coarse."""
        k = 1
        while math.pi / (self.height // k) < 1.9 * spacing:  # 2 per texel side, 5 % slack on a mean spacing
            k2 = 2 * k
            if self.height % k2 or self.width % k2 or self.height // k2 < 3:
                break
            k = k2
        return self.box_downsampled(k)

    def mean_radiance(self) -> Tensor:
        """(3,) average radiance over the sphere (solid-angle weighted, from the sampling cells)."""
        _, _, omega = self._tables()
        ext = torch.cat([self.data, self.data[:, :1]], 1).double()
        cell = 0.25 * (ext[:-1, :-1] + ext[:-1, 1:] + ext[1:, :-1] + ext[1:, 1:])  # (H−1, W, 3)
        with torch_threads(1):  # summed in an order independent of the thread count (methods.core.threads)
            return ((cell * omega[:, None, None]).sum((0, 1)) / (4 * math.pi)).float()

    # -- importance sampling
    def _tables(self) -> tuple[Tensor, Tensor, Tensor]:
        """(cdf (C,), cell probabilities (H−1, W), cell solid angles (H−1,)), float64."""
        if self._table is None:
            H, W = self.height, self.width
            lum = (self.data.double() * torch.tensor(_LUM, dtype=torch.float64)).sum(-1)
            ext = torch.cat([lum, lum[:, :1]], 1)  # (H, W+1)
            corner = 0.25 * (ext[:-1, :-1] + ext[:-1, 1:] + ext[1:, :-1] + ext[1:, 1:])  # (H−1, W)
            rows = torch.arange(H, dtype=torch.float64)
            z = torch.cos(math.pi * rows / (H - 1))
            omega = (2 * math.pi / W) * (z[:-1] - z[1:])  # (H−1,) solid angle of a cell in each row
            w = corner * omega[:, None]
            with torch_threads(1):  # a sum in an order that does not depend on the thread count
                total = w.sum()     # (methods.core.threads): the oracle's pdf divides by it
            if total <= 0:  # all-black map: uniform in solid angle
                w = omega[:, None].expand(H - 1, W).clone()
                total = w.sum()
            p = w / total
            cdf = torch.cumsum(p.reshape(-1), 0)
            cdf[-1] = 1.0
            self._table = (cdf, p, omega)
        return self._table

    def sample(self, u: Tensor) -> tuple[Tensor, Tensor]:
        """Sample world directions ∝ (piecewise-constant) luminance.

        Args:
            u: (..., 2) uniforms in [0, 1).
        Returns:
            d (..., 3) world unit directions and pdf (...) w.r.t. solid angle (dtype of u).
        """
        if u.shape[-1] != 2:
            raise ValueError(f"u must have shape (..., 2), got {tuple(u.shape)}")
        cdf, p, omega = self._tables()
        dev = u.device
        R = self.to_world.to(dev, torch.float64)
        d, pdf = sample_cells(u, cdf.to(dev), p.reshape(-1).to(dev), omega.to(dev), R, self.height, self.width)
        return d.to(u.dtype), pdf.to(u.dtype)

    def pdf(self, d: Tensor) -> Tensor:
        """Solid-angle density of `sample` at world directions d (..., 3) → (...)."""
        if d.shape[-1] != 3:
            raise ValueError(f"directions must have shape (..., 3), got {tuple(d.shape)}")
        _, p, omega = self._tables()
        R = self.to_world.to(d.device, torch.float64)
        return cell_pdf(d, p.to(d.device), omega.to(d.device), R).to(d.dtype)

    # -- files
    @classmethod
    def load(cls, path, to_world=None) -> "EnvMap":
        """Read an ``.exr`` (OpenEXR) or ``.hdr`` (Radiance RGBE) lat-long map; ValueError if it is
        unreadable, too large (`check_size`) or black (`check_lit`)."""
        return check_lit(cls(read_image(path), to_world), f"env map {str(path)!r}")

    def save(self, path) -> None:
        """Write the texels (not the rotation) as ``.exr`` (float32) or ``.hdr`` (RGBE)."""
        write_image(path, self.data.numpy())

    @classmethod
    def procedural(cls, name: str, *, height: int = 128, seed: int = 0) -> "EnvMap":
        return procedural(name, height=height, seed=seed)


# -- file I/O ----------------------------------------------------------------------------------


def read_image(path) -> np.ndarray:
    """(H, W, 3) float32 from .exr / .hdr; ValueError with the reason for anything unreadable."""
    p = Path(path)
    ext = p.suffix.lower()
    if ext not in (".exr", ".hdr", ".pic", ".rgbe"):
        raise ValueError(f"cannot read env map {str(p)!r}: unsupported extension {ext!r} (use .exr or .hdr)")
    if not p.is_file():
        raise ValueError(f"cannot read env map {str(p)!r}: file not found")
    try:
        arr = _read_exr(p) if ext == ".exr" else _read_rgbe(p)
    except TooLarge as e:
        raise TooLarge(f"env map {str(p)!r}: {e}") from e
    except Exception as e:  # corrupt file: one clear message with the underlying reason
        raise ValueError(f"cannot read env map {str(p)!r}: corrupt or unsupported file ({type(e).__name__}: {e})") from e
    return np.ascontiguousarray(arr, dtype=np.float32)


def write_image(path, data: np.ndarray) -> None:
    """Write (H, W, 3) float data as .exr (float32, ZIP) or .hdr (RGBE, RLE)."""
    p = Path(path)
    data = np.ascontiguousarray(np.asarray(data, dtype=np.float32))
    if data.ndim != 3 or data.shape[2] != 3:
        raise ValueError(f"image must have shape (H, W, 3), got {data.shape}")
    ext = p.suffix.lower()
    if ext == ".exr":
        _write_exr(p, data)
    elif ext in (".hdr", ".pic", ".rgbe"):
        _write_rgbe(p, data)
    else:
        raise ValueError(f"cannot write env map {str(p)!r}: unsupported extension {ext!r} (use .exr or .hdr)")


def _read_exr(p: Path) -> np.ndarray:
    import OpenEXR

    if not OpenEXR.isOpenExrFile(str(p)):
        raise ValueError("not an OpenEXR file")
    with OpenEXR.File(str(p), header_only=True) as f:  # the size before the pixels are allocated
        (x0, y0), (x1, y1) = (tuple(int(v) for v in c) for c in f.header()["dataWindow"])
    check_size(y1 - y0 + 1, x1 - x0 + 1)
    with OpenEXR.File(str(p)) as f:
        ch = f.channels()
        if "RGB" in ch:
            arr = np.asarray(ch["RGB"].pixels)
        elif "RGBA" in ch:
            arr = np.asarray(ch["RGBA"].pixels)[..., :3]
        elif all(c in ch for c in "RGB"):
            arr = np.stack([np.asarray(ch[c].pixels) for c in "RGB"], -1)
        elif "Y" in ch:
            arr = np.repeat(np.asarray(ch["Y"].pixels)[..., None], 3, -1)
        else:
            raise ValueError(f"no RGB/Y channels (found {sorted(ch)})")
    return arr.astype(np.float32)


def _write_exr(p: Path, data: np.ndarray) -> None:
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": data}) as f:
        f.write(str(p))


def rgbe_encode(data: np.ndarray) -> np.ndarray:
    """(H, W, 3) float → (H, W, 4) uint8 RGBE (Ward, Graphics Gems II "Real pixels")."""
    v = data.max(-1)
    m, e = np.frexp(v)
    scale = np.where(v > 1e-32, m * 256.0 / np.where(v > 1e-32, v, 1.0), 0.0)
    rgb = np.clip(np.floor(data * scale[..., None]), 0, 255).astype(np.uint8)
    ex = np.where(v > 1e-32, e + 128, 0).astype(np.uint8)
    return np.concatenate([rgb, ex[..., None]], -1)


def rgbe_decode(rgbe: np.ndarray) -> np.ndarray:
    """(H, W, 4) uint8 → (H, W, 3) float32 with Radiance's (mantissa + ½)·2^(e−136)."""
    e = rgbe[..., 3].astype(np.int32)
    f = np.where(e > 0, np.ldexp(1.0, e - 136), 0.0)
    return ((rgbe[..., :3].astype(np.float64) + 0.5) * f[..., None]).astype(np.float32)


def _write_rgbe(p: Path, data: np.ndarray) -> None:
    H, W, _ = data.shape
    enc = rgbe_encode(data)
    out = bytearray(b"#?RADIANCE\n# written by prtbench\nFORMAT=32-bit_rle_rgbe\n\n")
    out += f"-Y {H} +X {W}\n".encode()
    rle = 8 <= W < 0x8000
    for y in range(H):
        row = enc[y]
        if not rle:
            out += row.tobytes()
            continue
        out += bytes([2, 2, W >> 8, W & 0xFF])
        for c in range(4):  # "new" RLE, each component separately; literal chunks and runs
            comp = row[:, c]
            i = 0
            while i < W:
                j = i + 1
                while j < W and j - i < 127 and comp[j] == comp[i]:
                    j += 1
                if j - i >= 4:  # run
                    out += bytes([128 + (j - i), int(comp[i])])
                    i = j
                    continue
                j = i  # literal chunk until the next run of >= 4 (or 128 bytes)
                while j < W and j - i < 128:
                    if j + 3 < W and comp[j] == comp[j + 1] == comp[j + 2] == comp[j + 3]:
                        break
                    j += 1
                out += bytes([j - i]) + comp[i:j].tobytes()
                i = j
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_bytes(bytes(out))
    os.replace(tmp, p)


def _read_rgbe(p: Path) -> np.ndarray:
    raw = p.read_bytes()
    if not (raw.startswith(b"#?RADIANCE") or raw.startswith(b"#?RGBE")):
        raise ValueError("missing '#?RADIANCE' signature")
    pos = 0
    fmt_ok = True
    while True:  # header lines until an empty line
        end = raw.index(b"\n", pos)
        line = raw[pos:end].strip()
        pos = end + 1
        if not line:
            break
        if line.startswith(b"FORMAT=") and line != b"FORMAT=32-bit_rle_rgbe":
            fmt_ok = False
    if not fmt_ok:
        raise ValueError("only FORMAT=32-bit_rle_rgbe is supported")
    end = raw.index(b"\n", pos)
    res = raw[pos:end].split()
    pos = end + 1
    if len(res) != 4 or res[0] != b"-Y" or res[2] != b"+X":
        raise ValueError(f"unsupported resolution line {raw[pos:end]!r} (need '-Y H +X W')")
    H, W = int(res[1]), int(res[3])
    if H <= 0 or W <= 0:
        raise ValueError("bad resolution")
    check_size(H, W)  # before allocating the pixels
    out = np.zeros((H, W, 4), np.uint8)
    buf = memoryview(raw)
    for y in range(H):
        if pos + 4 > len(raw):
            raise ValueError("truncated pixel data")
        b0, b1, b2, b3 = raw[pos], raw[pos + 1], raw[pos + 2], raw[pos + 3]
        if 8 <= W < 0x8000 and b0 == 2 and b1 == 2 and b2 < 128:
            if (b2 << 8 | b3) != W:
                raise ValueError("scanline width mismatch")
            pos += 4
            for c in range(4):
                x = 0
                while x < W:
                    n = raw[pos]
                    pos += 1
                    if n > 128:
                        n -= 128
                        if x + n > W:
                            raise ValueError("run overflows scanline")
                        out[y, x:x + n, c] = raw[pos]
                        pos += 1
                    else:
                        if n == 0 or x + n > W or pos + n > len(raw):
                            raise ValueError("bad literal chunk")
                        out[y, x:x + n, c] = np.frombuffer(buf[pos:pos + n], np.uint8)
                        pos += n
                    x += n
        else:  # flat (uncompressed) scanline
            n = 4 * W
            if pos + n > len(raw):
                raise ValueError("truncated pixel data")
            out[y] = np.frombuffer(buf[pos:pos + n], np.uint8).reshape(W, 4)
            pos += n
    return rgbe_decode(out)


def load(path, to_world=None) -> EnvMap:
    """`EnvMap.load`."""
    return EnvMap.load(path, to_world)


def save(env: EnvMap, path) -> None:
    """`EnvMap.save`."""
    env.save(path)


# -- procedural maps -----------------------------------------------------------------------------


def texel_directions(height: int, width: int) -> Tensor:
    """(H, W, 3) float64 local directions of the texels: u = (x+½)/W, v = y/(H−1)."""
    v = torch.arange(height, dtype=torch.float64) / (height - 1)
    u = (torch.arange(width, dtype=torch.float64) + 0.5) / width
    return uv_to_direction(u[None, :].expand(height, width), v[:, None].expand(height, width))


def _smoothstep(e0: float, e1: float, x: Tensor) -> Tensor:
    t = ((x - e0) / (e1 - e0)).clamp(0, 1)
    return t * t * (3 - 2 * t)


def _dir(az_deg: float, el_deg: float) -> Tensor:
    """Local direction at azimuth φ (u = φ/2π) and elevation above the horizon (degrees)."""
    az, el = math.radians(az_deg), math.radians(el_deg)
    return torch.tensor([math.sin(az) * math.cos(el), math.sin(el), -math.cos(az) * math.cos(el)], dtype=torch.float64)


def _rect_mask(d: Tensor, centre: Tensor, w_deg: float, h_deg: float, soft: float) -> Tensor:
    """Soft rectangle in angular coordinates around `centre` (w × h degrees, edge width `soft` rad)."""
    up0 = torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64)
    right = torch.linalg.cross(up0, centre)
    if right.norm() < 1e-6:
        right = torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64)
    right = right / right.norm()
    up = torch.linalg.cross(centre, right)
    c = d @ centre
    a = torch.atan2(d @ right, c).abs()
    b = torch.atan2(d @ up, c).abs()
    ma = 1 - _smoothstep(math.radians(w_deg) / 2 - soft / 2, math.radians(w_deg) / 2 + soft / 2, a)
    mb = 1 - _smoothstep(math.radians(h_deg) / 2 - soft / 2, math.radians(h_deg) / 2 + soft / 2, b)
    return ma * mb * (c > 0)


def procedural(name: str, *, height: int = 128, seed: int = 0) -> EnvMap:
    """Synthetic HDR maps (width = 2·height), deterministic in (name, height, seed):

    * ``sky_sun``: smooth sky gradient + dark ground + a small very bright sun disc (≈2° radius)
      carrying most of the energy (hard shadows).
    * ``studio``: dark background + three bright rectangular softboxes (key, fill, rim).
    * ``window``: dim room + one small, very bright window with a dark cross mullion
      (all-frequency shadows).
    * ``overcast``: smooth, low-frequency CIE-overcast-like sky (soft lighting).
    """
    if name not in PROCEDURAL_NAMES:
        raise ValueError(f"unknown procedural env map {name!r}; choose from {', '.join(PROCEDURAL_NAMES)}")
    height = int(height)
    if height < 3:
        raise ValueError(f"height must be >= 3, got {height}")
    W = 2 * height
    check_size(height, W, f"procedural env map {name!r}")
    g = torch.Generator().manual_seed(int(seed))

    def rnd(lo, hi):
        return lo + (hi - lo) * torch.rand((), generator=g, dtype=torch.float64).item()

    d = texel_directions(height, W)  # (H, W, 3)
    y = d[..., 1]
    texel = math.pi / (height - 1)  # angular texel size (rows)
    col = lambda *c: torch.tensor(c, dtype=torch.float64)  # noqa: E731

    if name == "sky_sun":
        sun = _dir(rnd(0, 360), rnd(30, 50))
        zenith, horizon, ground = col(0.20, 0.40, 0.85), col(0.95, 0.95, 1.0), col(0.20, 0.18, 0.15)
        t = (1 - y.clamp(0, 1)) ** 3
        sky = zenith * (1 - t[..., None]) + horizon * t[..., None]
        gamma = torch.acos((d @ sun).clamp(-1, 1))
        sky = sky + 0.8 * torch.exp(-(gamma / 0.25) ** 2)[..., None] * col(1.0, 0.9, 0.7)  # circumsolar
        blend = _smoothstep(-0.03, 0.03, y)[..., None]
        L = blend * sky + (1 - blend) * ground
        r = max(math.radians(2.0), 1.5 * texel)
        disc = 1 - _smoothstep(r - 0.5 * texel, r + 0.5 * texel, gamma)
        L = L + disc[..., None] * (1500.0 * (math.radians(2.0) / r) ** 2) * col(1.0, 0.95, 0.85)
    elif name == "studio":
        L = (0.02 + 0.01 * y.clamp(0, 1))[..., None] * col(1.0, 1.0, 1.0)
        a0 = rnd(0, 360)
        boxes = [  # (azimuth offset, elevation, width, height, radiance, colour)
            (0.0, 35.0, 35.0, 25.0, 8.0, (1.0, 0.97, 0.92)),   # key
            (120.0, 15.0, 25.0, 40.0, 3.0, (0.90, 0.95, 1.0)),  # fill
            (215.0, 50.0, 40.0, 12.0, 6.0, (1.0, 1.0, 1.0)),   # rim / top strip
        ]
        for daz, el, w, h, rad, c in boxes:
            m = _rect_mask(d, _dir(a0 + daz + rnd(-10, 10), el + rnd(-5, 5)), w, h, texel)
            L = L + (rad * m)[..., None] * col(*c)
    elif name == "window":
        L = (0.03 + 0.01 * y.clamp(0, 1))[..., None] * col(1.0, 0.93, 0.85)
        centre = _dir(rnd(0, 360), rnd(15, 30))
        win = _rect_mask(d, centre, 14.0, 20.0, 0.5 * texel)
        bars = _rect_mask(d, centre, 1.5, 20.0, 0.5 * texel) + _rect_mask(d, centre, 14.0, 1.5, 0.5 * texel)
        win = (win - bars.clamp(max=1)).clamp(0, 1)
        L = L + (80.0 * win)[..., None] * col(0.92, 0.96, 1.0)
    else:  # overcast: CIE overcast sky L ∝ (1 + 2 sin(elevation))/3 + low-frequency variation
        sky = ((1 + 2 * y.clamp(0, 1)) / 3)[..., None] * col(0.95, 0.97, 1.0)
        ground = col(0.12, 0.11, 0.10)
        blend = _smoothstep(-0.2, 0.2, y)[..., None]
        a = torch.rand(4, generator=g, dtype=torch.float64) * 2 - 1
        vary = 1 + 0.15 * (a[0] * d[..., 0] + a[1] * d[..., 2] + a[2] * d[..., 0] * d[..., 2] + a[3] * (d[..., 0] ** 2 - d[..., 2] ** 2))
        L = (blend * sky + (1 - blend) * ground) * vary[..., None]
    return EnvMap(L.clamp_min(0).float())


# -- captured probes ----------------------------------------------------------------------------


def probe(name: str, *, height: int = PROBE_HEIGHT) -> EnvMap:
    """A vendored captured light probe (`PROBE_NAMES`) at `height` rows (width = 2·height).

    The stored map (PROBE_HEIGHT × 2·PROBE_HEIGHT) is box-averaged by the integer factor
    PROBE_HEIGHT / height (each output texel is the mean of a k×k block), so `height` must divide
    PROBE_HEIGHT. The file is validated on load like any env map (ValueError on NaN/Inf or
    negative texels, unreadable file).
    """
    if name not in PROBE_NAMES:
        raise ValueError(f"unknown probe {name!r}; choose from {', '.join(PROBE_NAMES)}")
    height = int(height)
    if height < 3 or PROBE_HEIGHT % height:
        raise ValueError(f"probe height must divide {PROBE_HEIGHT} and be >= 3, got {height}")
    data = read_image(PROBE_DIR / f"{name}.exr")
    if data.shape != (PROBE_HEIGHT, 2 * PROBE_HEIGHT, 3):
        raise ValueError(f"probe file {name!r} has shape {data.shape}, expected "
                         f"({PROBE_HEIGHT}, {2 * PROBE_HEIGHT}, 3)")
    env = EnvMap(data)  # validates the stored texels
    k = PROBE_HEIGHT // height
    if k > 1:
        d = env.data.double().reshape(height, k, 2 * height, k, 3).mean((1, 3))
        env = EnvMap(d.float())
    return env


def named(name: str, *, height: int, seed: int = 0) -> EnvMap:
    """Any named env map: a procedural one (`PROCEDURAL_NAMES`, seeded) or a captured probe
    (`PROBE_NAMES`; `seed` unused)."""
    if name in PROBE_NAMES:
        return probe(name, height=height)
    if name in PROCEDURAL_NAMES:
        return procedural(name, height=height, seed=seed)
    raise ValueError(f"unknown env map {name!r}; choose from {', '.join(PROCEDURAL_NAMES + PROBE_NAMES)}")


__all__ = ["EnvMap", "procedural", "probe", "named", "PROBE_NAMES", "check_lit", "check_size", "TooLarge",
           "max_env_texels", "MAX_ENV_TEXELS", "MIN_ENV_RADIANCE", "load", "save", "read_image", "write_image",
           "PROCEDURAL_NAMES",
           "direction_to_uv", "uv_to_direction", "bilinear_lookup", "sample_cells", "cell_pdf", "texel_directions"]
