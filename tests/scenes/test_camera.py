"""scenes/camera.py: rays agree with Mitsuba's `perspective` sensor; frame conventions; validation."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from scenes.camera import Camera

# Mitsuba computes in float32: unit directions agree to a few float32 ulp (ulp(1) = 1.2e-7;
# measured max 1.0e-7).
DIR_ATOL = 1e-6
# Ray origins lie near |origin| ≈ 5.4: ~4 ulp of that magnitude (ulp(4) = 4.8e-7; measured 1.2e-7).
ORIGIN_ATOL = 2e-6

CAM = Camera(origin=(2.0, 3.0, 4.0), target=(-0.5, 0.7, 0.3), up=(0.1, 1.0, -0.2), fov_deg=50.0,
             width=48, height=27)


def _mitsuba_rays(cam: Camera, px: np.ndarray):
    import mitsuba as mi

    from references.mitsuba_setup import ensure_variant

    ensure_variant()
    from references.export import camera_to_mitsuba

    sensor = mi.load_dict(camera_to_mitsuba(cam))
    n = px.shape[0]
    film = mi.Point2f(px[:, 0] / cam.width, px[:, 1] / cam.height)
    # time 0, wavelength sample 0.5, aperture sample (0.5, 0.5) (irrelevant for a pinhole)
    ray, _ = sensor.sample_ray(0.0, 0.5, film, mi.Point2f(0.5, 0.5))
    o = np.stack([np.asarray(ray.o.x), np.asarray(ray.o.y), np.asarray(ray.o.z)], 1)
    d = np.stack([np.asarray(ray.d.x), np.asarray(ray.d.y), np.asarray(ray.d.z)], 1)
    assert o.shape == (n, 3) and d.shape == (n, 3)
    return o, d


@pytest.mark.parametrize("cam", [CAM, Camera((0.0, 1.0, -3.0), (0.0, 0.5, 0.0), (0, 1, 0), 30.0, 20, 64)])
def test_rays_match_mitsuba(cam):
    rng = np.random.default_rng(1)
    px = np.concatenate([rng.uniform(0, 1, (200, 2)) * (cam.width, cam.height),
                         [[0, 0], [cam.width, cam.height], [cam.width / 2, cam.height / 2], [0.5, cam.height - 0.5]]])
    px = px.astype(np.float32)
    o_mi, d_mi = _mitsuba_rays(cam, px)
    o, d = cam.rays(torch.from_numpy(px))
    assert o.dtype == torch.float32 and d.dtype == torch.float32
    np.testing.assert_allclose(d.numpy(), d_mi, atol=DIR_ATOL)
    np.testing.assert_allclose(o.numpy(), o_mi, atol=ORIGIN_ATOL)


def test_centre_ray_is_look_direction_and_unit():
    o, d = CAM.rays(torch.tensor([[CAM.width / 2, CAM.height / 2]], dtype=torch.float64))
    fwd = np.subtract(CAM.target, CAM.origin)
    fwd /= np.linalg.norm(fwd)
    np.testing.assert_allclose(d[0].numpy(), fwd, atol=1e-12)
    np.testing.assert_allclose(o[0].numpy(), np.asarray(CAM.origin) + CAM.near_clip * fwd, atol=1e-12)
    _, d = CAM.pixel_rays(2)
    assert d.shape == (CAM.width * CAM.height * 4, 3)
    torch.testing.assert_close(d.norm(dim=1), torch.ones(d.shape[0]), atol=DIR_ATOL, rtol=0)


def test_image_orientation_and_fov():
    """+x of the image is the camera's right, +y is down; corner-to-corner angle along x = fov."""
    cam = Camera((0, 0, 0), (0, 0, -1), (0, 1, 0), 60.0, 40, 20)
    _, d = cam.rays(torch.tensor([[0.0, 10.0], [40.0, 10.0], [20.0, 0.0], [20.0, 20.0]], dtype=torch.float64))
    assert d[1, 0] > 0 > d[0, 0]      # right edge looks towards +x (right of a camera looking down −z)
    assert d[2, 1] > 0 > d[3, 1]      # top row looks up
    ang = math.degrees(math.acos(float((d[0] * d[1]).sum())))
    assert ang == pytest.approx(60.0, abs=1e-9)
    # vertical extent follows the aspect: tan(fov_y/2) = tan(fov_x/2)·H/W
    assert float(d[2, 1] / -d[2, 2]) == pytest.approx(math.tan(math.radians(30)) / 2, rel=1e-12)


def test_orbit_keeps_distance_and_target():
    c2 = CAM.orbited(0.7)
    assert c2.target == CAM.target
    r1 = np.linalg.norm(np.subtract(CAM.origin, CAM.target))
    r2 = np.linalg.norm(np.subtract(c2.origin, c2.target))
    assert r2 == pytest.approx(r1, rel=1e-12)
    assert c2.origin[1] == pytest.approx(CAM.origin[1], abs=1e-12)  # about +Y: height unchanged
    assert c2 != CAM


@pytest.mark.parametrize("kw", [dict(fov_deg=0.0), dict(fov_deg=180.0), dict(width=0), dict(height=2.5),
                                dict(target=(2.0, 3.0, 4.0)), dict(up=(-2.5, -2.3, -3.7)),
                                dict(origin=(np.nan, 0, 0)), dict(near_clip=0.0)])
def test_invalid_camera_raises(kw):
    base = dict(origin=(2.0, 3.0, 4.0), target=(-0.5, 0.7, 0.3), up=(0, 1, 0), fov_deg=50.0, width=8, height=8)
    base.update(kw)
    with pytest.raises(ValueError):
        Camera(**base)


def test_rays_bad_shape_raises():
    with pytest.raises(ValueError):
        CAM.rays(torch.zeros(5, 3))
