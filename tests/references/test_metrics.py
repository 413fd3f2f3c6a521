"""Metrics vs hand computations, closed forms and properties (mask handling, bad input)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from references import metrics as M

# float64 pipelines compared with float64 hand computations.
TOL = 1e-9
# colour-science's sRGB → XYZ → Lab goes through a 3×3 matrix rounded to 4–7 digits and D65 chroma
# coordinates: a neutral grey lands at |a*|, |b*| ~ 1e-3, which moves ΔE00 by ~1e-4.
LAB_TOL = 2e-3


def _pair(seed=0, H=20, W=24):
    g = torch.Generator().manual_seed(seed)
    ref = torch.rand(H, W, 3, generator=g, dtype=torch.float64) * 2.0
    img = ref + 0.1 * torch.randn(H, W, 3, generator=g, dtype=torch.float64)
    mask = torch.ones(H, W, dtype=torch.bool)
    mask[:4] = False
    mask[:, -3:] = False
    return img, ref, mask


def test_rmse_relmse_psnr_match_hand_computation():
    img, ref, mask = _pair()
    a, b = img.numpy()[mask.numpy()], ref.numpy()[mask.numpy()]
    mse = sum(((x - y) ** 2).sum() for x, y in zip(a, b)) / a.size
    assert M.rmse(img, ref, mask) == pytest.approx(math.sqrt(mse), rel=TOL)
    rel = np.mean((a - b) ** 2 / (b ** 2 + 1e-2))
    assert M.REL_MSE_EPS == 1e-2
    assert M.rel_mse(img, ref, mask) == pytest.approx(rel, rel=TOL)
    peak = b.max()
    assert M.psnr(img, ref, mask) == pytest.approx(10 * math.log10(peak ** 2 / mse), rel=TOL)


def test_metrics_ignore_pixels_outside_the_mask():
    img, ref, mask = _pair(1)
    e = M.Exposure.from_reference(ref, mask)
    base = M.all_metrics(img, ref, mask, exposure=e)
    img2, ref2 = img.clone(), ref.clone()
    img2[~mask] = 50.0  # a wild method value outside the mask
    ref2[~mask] = 0.0  # and a different reference there: PSNR's peak is taken on the mask only
    # Outside pixels of the method image are replaced by the reference's for SSIM/FLIP, so only
    # the reference change can influence them (through the window): compare the pure-img change.
    img3 = img.clone()
    img3[~mask] = 50.0
    got = M.all_metrics(img3, ref, mask, exposure=e)
    for k in M.METRICS:
        assert got[k] == pytest.approx(base[k], rel=1e-12, abs=1e-12), k
    assert M.rmse(img2, ref2, mask) == pytest.approx(base["rmse"], rel=1e-12)
    assert M.rel_mse(img2, ref2, mask) == pytest.approx(base["rel_mse"], rel=1e-12)
    assert M.psnr(img2, ref2, mask) == pytest.approx(base["psnr"], rel=1e-12)
    assert M.delta_e2000(img2, ref2, mask, exposure=e) == pytest.approx(base["delta_e2000"], rel=1e-12)


def test_identical_images_score_perfectly():
    _, ref, mask = _pair(2)
    got = M.all_metrics(ref, ref, mask)
    assert got["rmse"] == 0 and got["rel_mse"] == 0 and got["psnr"] == math.inf
    assert got["ssim"] == pytest.approx(1.0, abs=1e-12)
    assert got["flip"] == 0.0
    assert got["delta_e2000"] == pytest.approx(0.0, abs=1e-9)
    assert got["nonfinite_frac"] == 0.0


def test_ssim_closed_form_on_constant_images():
    # Constant images: σ = 0, so SSIM = (2 μa μb + C1)/(μa² + μb² + C1) (Wang 2004 eq. 13),
    # C1 = (0.01·L)², L = 1, with μ the display (exposed, clipped, sRGB-encoded) values.
    H, W = 16, 16
    ga, gb = 0.2, 0.35
    img = torch.full((H, W, 3), ga, dtype=torch.float64)
    ref = torch.full((H, W, 3), gb, dtype=torch.float64)
    mask = torch.ones(H, W, dtype=torch.bool)
    e = M.Exposure(scale=1.5, flip_start=0.0, flip_stop=1.0, flip_num=2)

    def oetf(x):
        x = min(max(x, 0.0), 1.0)
        return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055

    ma, mb = oetf(ga * 1.5), oetf(gb * 1.5)
    C1 = 0.01 ** 2
    expect = (2 * ma * mb + C1) / (ma ** 2 + mb ** 2 + C1)
    assert M.ssim(img, ref, mask, exposure=e) == pytest.approx(expect, rel=1e-9)


def test_delta_e2000_closed_form_for_neutral_greys():
    # Neutral greys: a* = b* = 0, so CIEDE2000 reduces to |ΔL*| / S_L with
    # S_L = 1 + 0.015 (L̄ − 50)² / sqrt(20 + (L̄ − 50)²) (Sharma et al. 2005 eq. 13), and
    # L* = 116 Y^(1/3) − 16 with Y = the linear grey level (sRGB rows sum to Y_white = 1).
    ga, gb, scale = 0.18, 0.4, 1.2
    img = torch.full((4, 4, 3), ga, dtype=torch.float64)
    ref = torch.full((4, 4, 3), gb, dtype=torch.float64)
    mask = torch.ones(4, 4, dtype=torch.bool)
    e = M.Exposure(scale=scale, flip_start=0.0, flip_stop=1.0, flip_num=2)
    La, Lb = (116 * (g * scale) ** (1 / 3) - 16 for g in (ga, gb))
    Lm = 0.5 * (La + Lb)
    SL = 1 + 0.015 * (Lm - 50) ** 2 / math.sqrt(20 + (Lm - 50) ** 2)
    assert M.delta_e2000(img, ref, mask, exposure=e) == pytest.approx(abs(La - Lb) / SL, abs=LAB_TOL)


def test_flip_grows_with_error_and_uses_fixed_exposure():
    img, ref, mask = _pair(3)
    e = M.Exposure.from_reference(ref, mask)
    small = ref * 1.02
    big = ref * 1.3
    f_small = M.flip(small, ref, mask, exposure=e)
    f_big = M.flip(big, ref, mask, exposure=e)
    assert 0.0 < f_small < f_big <= 1.0
    # The exposure range is a parameter: a different range gives a different score.
    e2 = M.Exposure(scale=e.scale, flip_start=e.flip_start - 3, flip_stop=e.flip_stop + 3, flip_num=e.flip_num + 6)
    assert M.flip(big, ref, mask, exposure=e2) != f_big


def test_exposure_from_reference():
    _, ref, mask = _pair(4)
    e = M.Exposure.from_reference(ref, mask)
    lum = ref.numpy()[mask.numpy()] @ np.array([0.2126, 0.7152, 0.0722])
    assert e.scale == pytest.approx(1.0 / np.percentile(lum, M.WHITE_PERCENTILE), rel=TOL)
    assert e.flip_start <= e.flip_stop and e.flip_num >= 1
    # depends on covered pixels only
    ref2 = ref.clone()
    ref2[~mask] = 100.0
    assert M.Exposure.from_reference(ref2, mask) == e
    with pytest.raises(ValueError):
        M.Exposure(scale=0.0, flip_start=0.0, flip_stop=1.0, flip_num=2)
    with pytest.raises(ValueError):
        M.Exposure(scale=1.0, flip_start=2.0, flip_stop=1.0, flip_num=2)


def test_nonfinite_method_image_gives_nan_and_flag():
    img, ref, mask = _pair(5)
    img[10, 5, 1] = float("nan")
    img[11, 5, 0] = float("inf")
    got = M.all_metrics(img, ref, mask)
    for k in M.METRICS:
        assert math.isnan(got[k]), k
    assert got["nonfinite_frac"] == pytest.approx(2 / int(mask.sum()))
    # NaN outside the mask is not scored
    img2 = ref.clone()
    img2[0, 0, 0] = float("nan")
    assert not mask[0, 0]
    assert M.rmse(img2, ref, mask) == 0.0


def test_bad_input_raises():
    img, ref, mask = _pair(6)
    bad = ref.clone()
    bad[5, 5, 0] = float("nan")
    with pytest.raises(ValueError, match="reference"):
        M.rmse(img, bad, mask)
    neg = ref.clone()
    neg[5, 5, 0] = -1.0
    with pytest.raises(ValueError, match="negative"):
        M.rmse(img, neg, mask)
    with pytest.raises(ValueError, match="shape"):
        M.rmse(img[:-1], ref, mask)
    with pytest.raises(ValueError, match="mask"):
        M.rmse(img, ref, mask[:-1])
    with pytest.raises(ValueError, match="empty"):
        M.rmse(img, ref, torch.zeros_like(mask))
    with pytest.raises(ValueError, match="boolean"):
        M.rmse(img, ref, mask.float())
    with pytest.raises(ValueError):
        M.rmse(img[..., :2], ref[..., :2], mask)


def test_negative_method_values_are_clipped_for_display_metrics_only():
    _, ref, mask = _pair(7)
    img = ref.clone()
    img[mask] = -0.5
    e = M.Exposure.from_reference(ref, mask)
    zero = torch.where(mask[..., None], torch.zeros_like(ref), ref)
    assert M.ssim(img, ref, mask, exposure=e) == pytest.approx(M.ssim(zero, ref, mask, exposure=e), abs=1e-12)
    assert M.flip(img, ref, mask, exposure=e) == pytest.approx(M.flip(zero, ref, mask, exposure=e), abs=1e-7)
    assert M.rmse(img, ref, mask) > M.rmse(zero, ref, mask)
