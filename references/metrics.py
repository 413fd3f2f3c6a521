"""Image error metrics of a method image against a reference, on the coverage mask.

Every metric compares ``img`` (the method's image) with ``ref`` (the reference) only on the pixels
of ``mask`` (the reference's coverage: every sub-sample of the pixel hit geometry).

Inputs: ``img``, ``ref`` (H, W, 3) linear Rec.709 radiance (torch or numpy), ``mask`` (H, W) bool.

Conventions (stated once):

* ``rmse``  = sqrt(mean over masked pixels and the 3 channels of (img − ref)²).
* ``rel_mse`` = mean((img − ref)² / (ref² + ε)), ε = ``REL_MSE_EPS`` = 1e-2 (Rousselle et al. 2011
  style relative MSE; ε keeps dark pixels from dominating).
* ``psnr``  = 10·log10(peak² / MSE), peak = max of the reference over the mask and channels (an HDR
  image has no natural peak; the reference's maximum makes the number comparable across methods of
  one reference). +inf for identical images.
* ``ssim``  — Wang et al. 2004 SSIM (scikit-image ``structural_similarity``: Gaussian window σ=1.5,
  K1=0.01, K2=0.03, population covariance, data range 1) on the *display* image: linear radiance
  × ``exposure.scale`` → clip to [0, 1] → sRGB OETF. The SSIM map is averaged over the mask and the
  three channels.
* ``flip``  — HDR-FLIP (Andersson et al. 2021, ``flip_evaluator``) with the exposure range fixed per
  scene (``Exposure.flip_*``, computed once from a reference by FLIP's own rule), ACES tone mapper,
  67 pixels per degree; the error map is averaged over the mask.
* ``delta_e2000`` — CIEDE2000 (colour-science): linear × ``exposure.scale`` → clip [0, 1] → sRGB
  OETF → XYZ (sRGB decoding, D65) → CIE L*a*b* (D65) → ΔE00, mean over the mask.

The spatial metrics (SSIM, FLIP) filter across the mask border. So that uncovered pixels add no
error, the method image's pixels *outside* the mask are replaced by the reference's before
filtering; the filtered error is then averaged over the mask only. Negative radiance (possible for
truncated-basis methods) is clipped to 0 for the display metrics (SSIM, ΔE, FLIP — FLIP's HDR mode
requires non-negative input); RMSE / relMSE / PSNR use the raw values.

Bad input: shape mismatches, an empty mask, or NaN/Inf/negative values in the *reference* raise
``ValueError`` (a broken reference must never be scored against). NaN/Inf in the *method* image is
a method failure that must stay visible: every metric returns NaN, and ``all_metrics`` adds
``nonfinite_frac`` (fraction of masked pixels with a non-finite channel) so the report can say why.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

# Relative-MSE regulariser ε in mean((a−b)²/(b²+ε)); 1e-2 ≈ (0.1)², i.e. radiances below ~0.1 are
# measured in absolute rather than relative terms.
REL_MSE_EPS = 1e-2
# SSIM window (Wang et al. 2004 §III-B): 11×11 Gaussian, σ = 1.5.
SSIM_SIGMA = 1.5
# The reference luminance percentile that the display exposure maps to white (1.0): the top 1 % of
# pixels (highlights) may clip, the rest of the image uses the display range.
WHITE_PERCENTILE = 99.0
# FLIP viewing condition: 0.7 m from a 0.7 m wide 3840-px monitor = 67 pixels per degree (FLIP
# paper's default).
FLIP_PPD = 67.0
FLIP_TONEMAPPER = "ACES"
# Rec.709 luminance weights (ITU-R BT.709).
_LUM = (0.2126, 0.7152, 0.0722)


def _as_np(x, name: str) -> np.ndarray:
    if isinstance(x, Tensor):
        return x.detach().cpu().double().numpy()
    return np.asarray(x, dtype=np.float64)


def _check(img, ref, mask) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validate and convert to float64 numpy (H, W, 3), (H, W, 3), bool (H, W)."""
    a, b = _as_np(img, "img"), _as_np(ref, "ref")
    if isinstance(mask, Tensor):
        m = mask.detach().cpu().numpy()
    else:
        m = np.asarray(mask)
    if b.ndim != 3 or b.shape[2] != 3:
        raise ValueError(f"reference must be (H, W, 3), got {b.shape}")
    if a.shape != b.shape:
        raise ValueError(f"image shape {a.shape} does not match the reference {b.shape}")
    if m.shape != b.shape[:2]:
        raise ValueError(f"mask must be {b.shape[:2]} like the images, got {m.shape}")
    if m.dtype != np.bool_:
        raise ValueError(f"mask must be boolean, got {m.dtype}")
    if not m.any():
        raise ValueError("mask is empty: no covered pixel to score")
    if not np.isfinite(b).all():
        raise ValueError(f"reference has {int((~np.isfinite(b)).any(-1).sum())} pixels with NaN/Inf")
    if (b < 0).any():
        raise ValueError(f"reference has {int((b < 0).any(-1).sum())} pixels with negative radiance")
    return a, b, m


def _finite(a: np.ndarray, m: np.ndarray) -> bool:
    return bool(np.isfinite(a[m]).all())


def nonfinite_frac(img, mask) -> float:
    """Fraction of masked pixels of ``img`` (H, W, 3) with a NaN/Inf channel."""
    a = _as_np(img, "img")
    m = mask.detach().cpu().numpy() if isinstance(mask, Tensor) else np.asarray(mask)
    return float((~np.isfinite(a[m])).any(-1).mean())


# -- exposure ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class Exposure:
    """Display parameters, fixed per scene (computed once from a reference, then reused).

    scale: linear multiplier applied before clip + sRGB OETF (SSIM, ΔE2000).
    flip_start, flip_stop, flip_num: HDR-FLIP's exposure range c_start, c_stop (stops) and count.
    """

    scale: float
    flip_start: float
    flip_stop: float
    flip_num: int

    def __post_init__(self) -> None:
        if not (math.isfinite(self.scale) and self.scale > 0):
            raise ValueError(f"exposure scale must be finite and > 0, got {self.scale}")
        if not (math.isfinite(self.flip_start) and math.isfinite(self.flip_stop)) or self.flip_start > self.flip_stop:
            raise ValueError(f"FLIP exposures need finite start <= stop, got {self.flip_start}, {self.flip_stop}")
        if int(self.flip_num) < 1:
            raise ValueError(f"FLIP needs >= 1 exposure, got {self.flip_num}")

    def flip_parameters(self) -> dict:
        return {"ppd": FLIP_PPD, "startExposure": float(self.flip_start), "stopExposure": float(self.flip_stop),
                "numExposures": int(self.flip_num), "tonemapper": FLIP_TONEMAPPER}

    def to_dict(self) -> dict:
        return {"scale": self.scale, "flip_start": self.flip_start, "flip_stop": self.flip_stop,
                "flip_num": self.flip_num}

    @classmethod
    def from_reference(cls, ref, mask, *, white_percentile: float = WHITE_PERCENTILE) -> "Exposure":
        """Exposure for a scene from one reference ``ref`` (H, W, 3) on ``mask`` (H, W).

        scale: the ``white_percentile`` of the reference's Rec.709 luminance maps to 1 (scale 1 if
        that is 0). FLIP range: FLIP's own automatic rule (``flip_evaluator`` computes c_start,
        c_stop from the reference's max and median luminance) applied to the covered pixels only,
        so uncovered black pixels do not pull the median down.
        """
        _, b, m = _check(ref, ref, mask)
        px = b[m]  # (K, 3)
        lum = px @ np.asarray(_LUM)
        white = float(np.percentile(lum, white_percentile))
        scale = 1.0 / white if white > 0 else 1.0
        flip_start, flip_stop, flip_num = 0.0, 0.0, 1
        if float(lum.max()) > 0:
            import flip_evaluator

            strip = np.ascontiguousarray(px[None].astype(np.float32))  # (1, K, 3) image
            _, _, params = flip_evaluator.evaluate(strip, strip, "HDR", applyMagma=False, computeMeanError=False,
                                                   parameters={"ppd": FLIP_PPD, "tonemapper": FLIP_TONEMAPPER})
            flip_start, flip_stop = float(params["startExposure"]), float(params["stopExposure"])
            flip_num = int(params["numExposures"])
        return cls(scale=scale, flip_start=flip_start, flip_stop=flip_stop, flip_num=flip_num)


def _display(x: np.ndarray, scale: float) -> np.ndarray:
    """Linear radiance → display sRGB in [0, 1]: × scale, clip, sRGB OETF (IEC 61966-2-1)."""
    y = np.clip(x * scale, 0.0, 1.0)
    return np.where(y <= 0.0031308, 12.92 * y, 1.055 * np.power(y, 1.0 / 2.4) - 0.055)


def _fill_outside(a: np.ndarray, b: np.ndarray, m: np.ndarray) -> np.ndarray:
    """The method image with the reference's pixels outside the mask (no error there)."""
    return np.where(m[..., None], a, b)


# -- metrics ----------------------------------------------------------------------------------


def rmse(img, ref, mask) -> float:
    """Root-mean-square error over masked pixels and channels. img, ref (H, W, 3); mask (H, W)."""
    a, b, m = _check(img, ref, mask)
    if not _finite(a, m):
        return math.nan
    return float(np.sqrt(np.mean((a[m] - b[m]) ** 2)))


def rel_mse(img, ref, mask, *, eps: float = REL_MSE_EPS) -> float:
    """mean((img − ref)² / (ref² + eps)) over masked pixels and channels."""
    a, b, m = _check(img, ref, mask)
    if not _finite(a, m):
        return math.nan
    d = a[m] - b[m]
    return float(np.mean(d * d / (b[m] ** 2 + eps)))


def psnr(img, ref, mask) -> float:
    """10·log10(peak² / MSE), peak = max of ``ref`` over the mask (all channels); +inf if equal."""
    a, b, m = _check(img, ref, mask)
    if not _finite(a, m):
        return math.nan
    mse = float(np.mean((a[m] - b[m]) ** 2))
    peak = float(b[m].max())
    if mse == 0.0:
        return math.inf
    if peak == 0.0:
        return -math.inf
    return 10.0 * math.log10(peak * peak / mse)


def ssim(img, ref, mask, *, exposure: Exposure) -> float:
    """Mean SSIM (Wang et al. 2004) of the display images over the mask (see the module doc)."""
    from skimage.metrics import structural_similarity

    a, b, m = _check(img, ref, mask)
    if not _finite(a, m):
        return math.nan
    da = _display(_fill_outside(a, b, m), exposure.scale)
    db = _display(b, exposure.scale)
    _, smap = structural_similarity(da, db, data_range=1.0, channel_axis=-1, gaussian_weights=True,
                                    sigma=SSIM_SIGMA, use_sample_covariance=False, full=True)
    return float(smap[m].mean())


def flip(img, ref, mask, *, exposure: Exposure) -> float:
    """Mean HDR-FLIP error over the mask, exposure range fixed by ``exposure``."""
    import flip_evaluator

    a, b, m = _check(img, ref, mask)
    if not _finite(a, m):
        return math.nan
    ta = np.ascontiguousarray(np.clip(_fill_outside(a, b, m), 0.0, None).astype(np.float32))
    tb = np.ascontiguousarray(b.astype(np.float32))
    emap, _, _ = flip_evaluator.evaluate(tb, ta, "HDR", applyMagma=False, computeMeanError=False,
                                         parameters=exposure.flip_parameters())
    return float(np.asarray(emap)[..., 0][m].mean())


def _lab(x: np.ndarray, scale: float) -> np.ndarray:
    import colour

    srgb = _display(x, scale)
    xyz = colour.sRGB_to_XYZ(srgb)  # decodes the sRGB OETF, D65
    return colour.XYZ_to_Lab(xyz)


def delta_e2000(img, ref, mask, *, exposure: Exposure) -> float:
    """Mean CIEDE2000 over the mask of the exposed, clipped sRGB images (see the module doc)."""
    import colour

    a, b, m = _check(img, ref, mask)
    if not _finite(a, m):
        return math.nan
    de = colour.delta_E(_lab(a[m], exposure.scale), _lab(b[m], exposure.scale), method="CIE 2000")
    return float(np.mean(de))


METRICS = ("rmse", "rel_mse", "psnr", "ssim", "flip", "delta_e2000")


def all_metrics(img, ref, mask, *, exposure: Exposure | None = None) -> dict[str, float]:
    """Every metric of ``img`` vs ``ref`` on ``mask``, plus ``nonfinite_frac``.

    img, ref: (H, W, 3); mask: (H, W) bool. ``exposure``: fixed per scene (pass the same one for
    every method and frame of a scene); None → ``Exposure.from_reference(ref, mask)``.
    """
    _check(img, ref, mask)
    if exposure is None:
        exposure = Exposure.from_reference(ref, mask)
    out = {
        "rmse": rmse(img, ref, mask),
        "rel_mse": rel_mse(img, ref, mask),
        "psnr": psnr(img, ref, mask),
        "ssim": ssim(img, ref, mask, exposure=exposure),
        "flip": flip(img, ref, mask, exposure=exposure),
        "delta_e2000": delta_e2000(img, ref, mask, exposure=exposure),
    }
    out["nonfinite_frac"] = nonfinite_frac(img, mask)
    return out
