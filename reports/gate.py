"""The sanity gate: a method-independent check that a scored image is not plainly wrong.

An image can sit within a few noise floors of its reference in RMSE and still be wrong where it
matters: a region rendered black (in-out with Cook–Torrance before the fix), negative radiance
(ZH ringing), a whole image 3× too bright. RMSE averages those away; these numbers do not.

Per scored frame (``frame_sanity``), over the pixels the cell scores (``mask``):
* ``negative_frac`` — fraction of pixels with any channel < −``NEG_REL`` × the reference's 99th
  percentile (radiance is never negative; round-off is far below this);
* ``mean_ratio`` — method mean / reference mean;
* ``region_mean_ratio_min`` / ``_max`` — the same ratio per material region, over regions that
  cover at least ``REGION_MIN_FRAC`` of the scored pixels (a whole-image mean hides a failed
  region: a black box beside a bright floor can leave the image at 0.96×). A pixel belongs to a
  region when all its G-buffer sub-samples hit that region (edge pixels belong to none).

``verdict(rows)`` turns a cell's rows into ``None`` (sane) or the reason it is ``suspect``: any
scored frame with a region ratio outside [``RATIO_LO``, ``RATIO_HI``] or ``negative_frac`` above
``NEG_FRAC_MAX``. Thresholds are far outside what noise does at the suites' sample counts (the
reference's own region means are within a few percent at 64 spp on test scenes), so a suspect cell
is a wrong image, not an unlucky one.
"""
from __future__ import annotations

import math

import torch
from torch import Tensor

NEG_REL = 1e-4            # a pixel is negative below −NEG_REL × the reference's 99th percentile
NEG_FRAC_MAX = 0.01       # suspect above 1 % negative pixels
REGION_MIN_FRAC = 0.01    # regions covering < 1 % of the scored pixels are not judged
RATIO_LO, RATIO_HI = 0.67, 1.5  # suspect outside [0.67, 1.5] × the reference's region mean

METRICS = ("negative_frac", "mean_ratio", "region_mean_ratio_min", "region_mean_ratio_max")


def pixel_regions(region: Tensor, height: int, width: int) -> Tensor:
    """(H, W) int64 region of each pixel from the G-buffer's per-sample ``region`` (P,) (pixel-major,
    S² sub-samples per pixel): the region all its sub-samples hit, −1 where they differ or miss."""
    r = region.reshape(height, width, -1)
    first = r[..., 0]
    same = (r == first[..., None]).all(-1)
    return torch.where(same, first, torch.full_like(first, -1))


def frame_sanity(img: Tensor, ref: Tensor, mask: Tensor, regions: Tensor | None = None) -> dict[str, float]:
    """Gate metrics of one frame (module docstring). img, ref: (H, W, 3); mask: (H, W) bool scored
    pixels; regions: (H, W) int64 pixel regions (``pixel_regions``) or None (whole image only)."""
    if img.shape != ref.shape or img.shape[:2] != mask.shape:
        raise ValueError(f"shapes differ: img {tuple(img.shape)}, ref {tuple(ref.shape)}, mask {tuple(mask.shape)}")
    img, ref, mask = img.double().cpu(), ref.double().cpu(), mask.bool().cpu()
    n = int(mask.sum())
    if n == 0:
        raise ValueError("no scored pixels")
    r = ref[mask]
    m = img[mask]
    p99 = float(torch.quantile(r.reshape(-1), 0.99)) if r.numel() else 0.0
    neg = (m < -NEG_REL * p99).any(-1) if p99 > 0 else (m < 0).any(-1)
    out = {"negative_frac": float(neg.double().mean()), "mean_ratio": _ratio(m.mean(), r.mean())}
    ratios = []
    if regions is not None:
        reg = regions.cpu()[mask]
        for k in torch.unique(reg).tolist():
            if k < 0:
                continue
            sel = reg == k
            if int(sel.sum()) < REGION_MIN_FRAC * n:
                continue
            q = _ratio(m[sel].mean(), r[sel].mean())
            if not math.isnan(q):
                ratios.append(q)
    out["region_mean_ratio_min"] = min(ratios) if ratios else out["mean_ratio"]
    out["region_mean_ratio_max"] = max(ratios) if ratios else out["mean_ratio"]
    return out


def _ratio(a: Tensor, b: Tensor) -> float:
    a, b = float(a), float(b)
    if b <= 0:
        return float("nan") if a == 0 else float("inf")
    return a / b


def verdict(rows: list[dict]) -> str | None:
    """None if every scored frame passes the gate, else the reason (one line) the cell is suspect.
    rows: the cell's long-format rows (frame ≥ 0 rows of ``METRICS`` are judged)."""
    why = []
    for r in rows:
        if r.get("frame", -1) < 0 or r["metric"] not in METRICS:
            continue
        v = r["value"]
        if r["metric"] == "negative_frac" and v > NEG_FRAC_MAX:
            why.append(f"frame {r['frame']}: {100 * v:.1f} % negative pixels")
        elif r["metric"] in ("region_mean_ratio_min", "region_mean_ratio_max") and not (RATIO_LO <= v <= RATIO_HI):
            which = "darkest" if r["metric"].endswith("min") else "brightest"
            why.append(f"frame {r['frame']}: {which} region at {v:.2f}× the reference mean")
    if not why:
        return None
    return "; ".join(why[:3]) + (f" (+{len(why) - 3} more)" if len(why) > 3 else "")
