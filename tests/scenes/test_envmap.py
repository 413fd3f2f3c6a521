"""scenes/envmap.py: lat-long convention, rotation, importance sampling, file I/O, validation,
procedural maps. (Agreement with Mitsuba's own envmap: tests/references/test_envmap_mitsuba.py.)"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from scenes.envmap import (PROCEDURAL_NAMES, EnvMap, direction_to_uv, procedural, read_image,
                           rgbe_decode, rgbe_encode, texel_directions, uv_to_direction, write_image)

# float64 lookup at texel centres: only round-off of the interpolation weights remains.
TEXEL_RTOL = 1e-9
# RGBE keeps 8 mantissa bits of the largest component: relative error ≤ 2^-8 of max(r, g, b).
RGBE_RTOL = 2.0**-8
CHI2_ALPHA = 1e-3


def rand_data(H=9, W=16, seed=0):
    g = torch.Generator().manual_seed(seed)
    return torch.rand(H, W, 3, generator=g) * 3


def rot(axis, angle):
    a = torch.tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    K = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def rand_dirs(n, seed):
    g = torch.Generator().manual_seed(seed)
    v = torch.randn(n, 3, generator=g, dtype=torch.float64)
    return v / v.norm(dim=-1, keepdim=True)


# -- convention -------------------------------------------------------------------------------


def test_texel_centres_return_texels():
    data = rand_data()
    env = EnvMap(data)
    # skip the pole rows: every column of row 0 / H−1 is the same direction (the south pole even
    # wraps to v = 0, as in Mitsuba)
    d = texel_directions(9, 16)[1:-1]
    torch.testing.assert_close(env.radiance(d), data[1:-1].double(), rtol=TEXEL_RTOL, atol=1e-9)


def test_axes_convention():
    # u = atan2(x, −z)/2π, v = acos(y)/π: −z is u = 0, +x is u = ¼, +y is v = 0 (the top row)
    d = torch.tensor([[0, 0, -1.0], [1.0, 0, 0], [0, 0, 1.0], [0, 1.0, 0]], dtype=torch.float64)
    u, v = direction_to_uv(d)
    torch.testing.assert_close(torch.remainder(u[:3], 1), torch.tensor([0, 0.25, 0.5], dtype=torch.float64))
    torch.testing.assert_close(v, torch.tensor([0.5, 0.5, 0.5, 0], dtype=torch.float64))
    dd = rand_dirs(1000, 1)
    torch.testing.assert_close(uv_to_direction(*direction_to_uv(dd)), dd)


def test_bilinear_midpoints_and_wrap():
    data = rand_data(5, 8)
    env = EnvMap(data)
    # halfway between columns 7 and 0 (across the seam, u = 0 ≡ 1) on row 2
    d = uv_to_direction(torch.tensor([0.0], dtype=torch.float64), torch.tensor([2 / 4], dtype=torch.float64)).float()
    torch.testing.assert_close(env.radiance(d)[0], 0.5 * (data[2, 7] + data[2, 0]), rtol=1e-5, atol=1e-6)
    # halfway between rows 1 and 2 at column 3's centre
    d = uv_to_direction(torch.tensor([3.5 / 8], dtype=torch.float64), torch.tensor([1.5 / 4], dtype=torch.float64)).float()
    torch.testing.assert_close(env.radiance(d)[0], 0.5 * (data[1, 3] + data[2, 3]), rtol=1e-5, atol=1e-6)


def test_rotation_lookup_and_composition():
    data = rand_data()
    R1, R2 = rot([0.3, 1, -0.2], 0.8), rot([1, 0, 0.4], -1.3)
    d = rand_dirs(5000, 2)
    env = EnvMap(data)
    # the map rotated by R shows at R·d what the original shows at d
    torch.testing.assert_close(env.rotated(R1).radiance(d @ R1.T), env.radiance(d), rtol=1e-9, atol=1e-9)
    e12 = env.rotated(R1).rotated(R2)
    torch.testing.assert_close(e12.to_world, R2 @ R1)
    torch.testing.assert_close(EnvMap(data, R2 @ R1).radiance(d), e12.radiance(d))


def test_follows_dtype_and_device():
    env = EnvMap(rand_data())
    assert env.radiance(rand_dirs(4, 3)).dtype == torch.float64
    out = env.radiance(rand_dirs(12, 3).float().view(3, 4, 3))
    assert out.dtype == torch.float32 and out.shape == (3, 4, 3)


# -- importance sampling ----------------------------------------------------------------------


@pytest.mark.parametrize("name", ["sky_sun", "window"])
def test_sample_pdf_consistent_and_unbiased(name):
    env = procedural(name, height=32).rotated(rot([0.2, 1, 0.1], 0.9))
    g = torch.Generator().manual_seed(4)
    u = torch.rand(100_000, 2, generator=g, dtype=torch.float64)
    d, pdf = env.sample(u)
    torch.testing.assert_close(d.norm(dim=-1), torch.ones(len(d), dtype=torch.float64))
    torch.testing.assert_close(env.pdf(d), pdf, rtol=1e-9, atol=0)
    # E[L/pdf] = ∫ L dω = 4π · mean radiance (mean from the exact cell integrals of the map)
    est = (env.radiance(d) / pdf[:, None]).mean(0)
    torch.testing.assert_close(est, 4 * math.pi * env.mean_radiance().double(), rtol=0.02, atol=0)


def test_pdf_integrates_to_one_and_covers_radiance():
    env = procedural("studio", height=24)
    x, w = np.polynomial.legendre.leggauss(400)  # z = cosθ; the pdf is piecewise constant
    phi = (np.arange(800) + 0.5) * 2 * np.pi / 800
    Z, P = np.meshgrid(x, phi, indexing="ij")
    s = np.sqrt(1 - Z**2)
    d = torch.from_numpy(np.stack([s * np.sin(P), Z, -s * np.cos(P)], -1).reshape(-1, 3))
    p = env.pdf(d)
    total = (p.reshape(400, 800) * torch.from_numpy(w)[:, None]).sum() * 2 * math.pi / 800
    assert total.item() == pytest.approx(1.0, abs=5e-3)  # step discontinuities in the grid
    L = env.radiance(d).sum(-1)
    assert not ((L > 0) & (p <= 0)).any()  # MIS stays unbiased


def test_sample_histogram_chi2():
    # the pdf is piecewise constant on the W×(H−1) lattice cells and uniform in (φ, cosθ) inside a
    # cell: bin samples into 2×2 sub-cells of every lattice cell, whose expected counts are exact
    # (p_cell/4 · n, independently of `pdf`'s own lookup).
    H, W = 16, 32
    env = procedural("window", height=H).rotated(rot([1, 0.5, 0], 0.7))
    n = 200_000
    d, _ = env.sample(torch.rand(n, 2, generator=torch.Generator().manual_seed(5), dtype=torch.float64))
    dl = d @ env.to_world  # to local
    u, v = direction_to_uv(dl)
    x = torch.remainder(u * W - 0.5, W)
    ix, fx = x.floor().long(), x - x.floor()
    theta = v * math.pi
    iy = (v * (H - 1)).floor().long().clamp(0, H - 2)
    z_top, z_bot = torch.cos(math.pi * iy / (H - 1)), torch.cos(math.pi * (iy + 1) / (H - 1))
    fz = (z_top - torch.cos(theta)) / (z_top - z_bot)
    sub = (fx >= 0.5).long() * 2 + (fz >= 0.5).long()
    obs = torch.bincount((iy * W + ix) * 4 + sub, minlength=(H - 1) * W * 4).double().numpy()
    # exact cell probabilities: mean corner luminance × cell solid angle, normalised
    lum = (env.data.double() * torch.tensor([0.212671, 0.715160, 0.072169], dtype=torch.float64)).sum(-1)
    ext = torch.cat([lum, lum[:, :1]], 1)
    corner = 0.25 * (ext[:-1, :-1] + ext[:-1, 1:] + ext[1:, :-1] + ext[1:, 1:])
    z = torch.cos(math.pi * torch.arange(H, dtype=torch.float64) / (H - 1))
    w = corner * (z[:-1] - z[1:])[:, None]
    exp = (w / w.sum()).reshape(-1, 1).expand(-1, 4).reshape(-1).numpy() * n / 4
    m = exp > 5
    chi = ((obs[m] - exp[m]) ** 2 / exp[m]).sum()
    assert stats.chi2.sf(chi, m.sum() - 1) > CHI2_ALPHA
    assert obs[exp == 0].sum() == 0


def test_black_map_samples_uniformly():
    env = EnvMap(torch.zeros(6, 12, 3))
    d, pdf = env.sample(torch.rand(1000, 2, dtype=torch.float64))
    torch.testing.assert_close(pdf, torch.full_like(pdf, 1 / (4 * math.pi)))


# -- files ------------------------------------------------------------------------------------


def test_exr_round_trip_exact(tmp_path):
    env = procedural("sky_sun", height=16)
    env.save(tmp_path / "a.exr")
    back = EnvMap.load(tmp_path / "a.exr")
    assert torch.equal(back.data, env.data)


@pytest.mark.parametrize("shape", [(16, 32), (5, 4)], ids=["rle", "flat"])  # width < 8 → flat scanlines
def test_hdr_round_trip(tmp_path, shape):
    data = procedural("studio", height=16).data[: shape[0], : shape[1]].clone()
    data[0, 0] = 0.0
    data[1, 1] = torch.tensor([1e4, 2e-3, 0.5])
    EnvMap(data).save(tmp_path / "a.hdr")
    back = EnvMap.load(tmp_path / "a.hdr").data
    err = (back - data).abs().max(-1).values / data.max(-1).values.clamp_min(1e-30)
    assert err.max().item() <= RGBE_RTOL
    assert back[0, 0].abs().max().item() == 0.0


def test_rgbe_codec_constant_runs():
    x = np.full((3, 40, 3), 0.75, np.float32)  # long runs exercise the run-length path
    torch.testing.assert_close(torch.from_numpy(rgbe_decode(rgbe_encode(x))), torch.from_numpy(x), rtol=RGBE_RTOL, atol=0)


@pytest.mark.parametrize("ext", [".exr", ".hdr"])
def test_corrupt_files_raise_clear_error(tmp_path, ext):
    p = tmp_path / f"bad{ext}"
    p.write_bytes(b"this is not an image at all" * 10)
    with pytest.raises(ValueError, match="cannot read env map"):
        EnvMap.load(p)


def test_truncated_hdr_and_missing_file(tmp_path):
    p = tmp_path / "t.hdr"
    write_image(p, np.random.default_rng(0).random((8, 16, 3)).astype(np.float32))
    p.write_bytes(p.read_bytes()[:-40])
    with pytest.raises(ValueError, match="cannot read env map"):
        read_image(p)
    with pytest.raises(ValueError, match="not found"):
        EnvMap.load(tmp_path / "missing.exr")
    with pytest.raises(ValueError, match="extension"):
        EnvMap.load(tmp_path / "x.png")


# -- validation -------------------------------------------------------------------------------


@pytest.mark.parametrize("bad, msg", [
    (lambda d: d.__setitem__((1, 2, 0), float("nan")), "NaN"),
    (lambda d: d.__setitem__((1, 2, 0), float("inf")), "NaN/Inf"),
    (lambda d: d.__setitem__((1, 2, 0), -1.0), "negative"),
])
def test_invalid_texels(bad, msg):
    d = rand_data()
    bad(d)
    with pytest.raises(ValueError, match=msg):
        EnvMap(d)


def test_invalid_shapes_and_rotation():
    with pytest.raises(ValueError, match="shape"):
        EnvMap(torch.rand(8, 16))
    with pytest.raises(ValueError, match="shape"):
        EnvMap(torch.rand(8, 16, 4))
    with pytest.raises(ValueError, match="at least"):
        EnvMap(torch.rand(2, 16, 3))
    with pytest.raises(ValueError, match="rotation"):
        EnvMap(rand_data(), to_world=2 * torch.eye(3))
    with pytest.raises(ValueError, match="rotation"):
        EnvMap(rand_data(), to_world=-torch.eye(3))  # a reflection
    with pytest.raises(ValueError, match="to_world"):
        EnvMap(rand_data(), to_world=torch.eye(4))


# -- procedural -------------------------------------------------------------------------------


@pytest.mark.parametrize("name", PROCEDURAL_NAMES)
def test_procedural_maps(name):
    env = procedural(name, height=32, seed=1)
    assert env.data.shape == (32, 64, 3) and env.data.dtype == torch.float32
    assert torch.isfinite(env.data).all() and (env.data >= 0).all()
    assert torch.equal(procedural(name, height=32, seed=1).data, env.data)  # deterministic
    lum = env.data.mean(-1)
    ratio = (lum.max() / lum.median()).item()
    if name == "overcast":
        assert ratio < 5  # smooth and low-frequency
        assert (env.data[:, 1:] - env.data[:, :-1]).abs().max() < 0.1 * env.data.max()
    else:
        assert ratio > 50  # small bright emitters on a dim background
    assert not torch.equal(procedural(name, height=32, seed=2).data, env.data)


def test_sky_sun_energy_in_the_sun():
    env = procedural("sky_sun", height=64)
    lum = env.data.mean(-1).double()
    w = torch.sin(math.pi * torch.arange(64, dtype=torch.float64) / 63)[:, None].expand(64, 128)
    bright = lum > 50
    frac = (lum * w)[bright].sum() / (lum * w).sum()
    assert frac > 0.5 and bright.sum() < 40  # a compact disc carrying most of the energy


def test_procedural_bad_name():
    with pytest.raises(ValueError, match="unknown procedural"):
        procedural("beach")


def test_sampling_tables_do_not_depend_on_the_thread_count():
    """Issue 17: the importance-sampling pdf (the oracle divides by its normaliser) and the mean
    radiance, bit for bit with 1 and 2 torch threads, on a map big enough (256 × 512 cells) for
    torch to split a whole-tensor sum over the threads."""
    from methods.core.threads import torch_threads

    env = procedural("sky_sun", height=256, seed=0)
    out = []
    for t in (1, 2):
        env._table = None
        with torch_threads(t):
            out.append((*env._tables(), env.mean_radiance()))
    for a, b in zip(*out):
        assert torch.equal(a, b)


def test_box_downsample_and_prefilter_for_a_sampler():
    import math

    import pytest
    import torch

    from scenes.envmap import EnvMap

    env = EnvMap(torch.rand(256, 512, 3), to_world=torch.tensor([[0.0, 0, 1], [0, 1, 0], [-1, 0, 0]]))
    half = env.box_downsampled(2)
    assert (half.height, half.width) == (128, 256) and torch.equal(half.to_world, env.to_world)
    torch.testing.assert_close(half.data[3, 5].double(), env.data[6:8, 10:12].double().mean((0, 1)))
    assert env.box_downsampled(1) is env
    for bad in (3, 0, 128):
        with pytest.raises(ValueError, match="box-downsample"):
            env.box_downsampled(bad)
    # texels at least ~2 sampler spacings (5 % slack), a power-of-two factor, never below 3 rows
    for spacing in (1e-3, 0.0123, 0.0495, 0.2, 10.0):
        h = env.prefiltered_for_spacing(spacing).height
        assert h == 256 or math.pi / h >= 1.9 * spacing or h // 2 < 3, (spacing, h)
        assert h == 256 or math.pi / (2 * h) < 1.9 * spacing, (spacing, h)
    assert env.prefiltered_for_spacing(0.0495).height == 32
