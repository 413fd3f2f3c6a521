"""Bad scene input is rejected at load with one ValueError naming the file and the key (issue 17,
"Bad input"): film and env-map size limits, black env maps, meshes collapsed by a transform, a
camera that sees no geometry, BRDF parameters whose float32 evaluation overflows."""
import math
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from scenes import camera as cam_mod
from scenes import envmap as env_mod
from scenes.camera import Camera
from scenes.envmap import EnvMap, procedural
from scenes.materials import (MAX_BLINN_EXPONENT, MAX_PHONG_EXPONENT, MIN_LOBE_WIDTH, BlinnPhong, CookTorrance,
                              Material, Phong, TorranceSparrow, Ward, power_cosine_pdf)
from scenes.mesh import Mesh, check_extent
from scenes.scene import Scene, Shape, covered_pixels
from scenes.scenefile import load_scene_file

EXAMPLES = Path(__file__).resolve().parents[2] / "scenes" / "examples"


def _scene_file(tmp_path, **subst) -> Path:
    """two_boxes.toml copied to tmp_path with whole lines replaced: {"old line start": "new line"}."""
    for f in ("box.obj", "ground.obj"):
        shutil.copy(EXAMPLES / f, tmp_path / f)
    lines = (EXAMPLES / "two_boxes.toml").read_text().splitlines()
    for old, new in subst.items():
        hits = [i for i, l in enumerate(lines) if l.startswith(old)]
        assert hits, old
        lines[hits[0]] = new
    p = tmp_path / "scene.toml"
    p.write_text("\n".join(lines) + "\n")
    return p


def _load_error(p: Path) -> str:
    with pytest.raises(ValueError) as e:
        load_scene_file(p)
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"{p.name}: "), msg
    return msg


# -- 1. resolution limits ---------------------------------------------------------------------


def test_camera_pixel_limit(monkeypatch):
    with pytest.raises(ValueError, match=r"camera width = 100000 exceeds the limit of 4096 .*PRTBENCH_MAX_FILM_SIDE"):
        Camera((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 100000, 64)  # ate 9 GB
    Camera((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 2048, 2048)  # the defaults allow the bench sizes (256²) with room
    with pytest.raises(ValueError, match=r"4096 × 4096 = 16777216 pixels exceeds the limit of 4194304"):
        Camera((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 4096, 4096)
    monkeypatch.setenv("PRTBENCH_MAX_FILM_SIDE", "100000")
    Camera((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 100000, 40)  # 4 Mpx: under the pixel limit
    with pytest.raises(ValueError, match=r"camera width × height = 100000 × 1000 .* PRTBENCH_MAX_PIXELS"):
        Camera((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 100000, 1000)
    monkeypatch.setenv("PRTBENCH_MAX_PIXELS", "100")
    Camera((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 10, 10)
    with pytest.raises(ValueError, match="exceeds the limit of 100"):
        Camera((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 11, 10)
    monkeypatch.setenv("PRTBENCH_MAX_PIXELS", "lots")
    with pytest.raises(ValueError, match="PRTBENCH_MAX_PIXELS must be a positive integer"):
        cam_mod.max_pixels()


def test_scene_file_camera_width_limit(tmp_path):
    msg = _load_error(_scene_file(tmp_path, **{"width =": "width = 100000"}))
    assert "[camera]" in msg and "width" in msg and "exceeds" in msg


def test_env_map_texel_limit(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match=r"procedural env map 'sky_sun' height × width = 100000 × 200000"):
        procedural("sky_sun", height=100000)  # raised before allocating (was a 160 GB allocation)
    msg = _load_error(_scene_file(tmp_path, **{"height = 32": "height = 100000"}))
    assert "[envmap]" in msg and "height" in msg and "PRTBENCH_MAX_ENV_TEXELS" in msg

    # a file's header is checked before its pixels are allocated
    fake = tmp_path / "huge.hdr"
    fake.write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 100000 +X 200000\n")
    with pytest.raises(ValueError, match=r"huge.hdr.*100000 × 200000 = 20000000000 texels exceeds"):
        EnvMap.load(fake)
    monkeypatch.setenv("PRTBENCH_MAX_ENV_TEXELS", "64")
    procedural("studio", height=5)  # 5 × 10 = 50 texels
    procedural("studio", height=4).save(tmp_path / "small.exr")  # 32 texels
    env = EnvMap(torch.rand(4, 8, 3) + 0.1)
    env.save(tmp_path / "a.exr")
    monkeypatch.setenv("PRTBENCH_MAX_ENV_TEXELS", "16")
    with pytest.raises(ValueError, match=r"a.exr.*4 × 8 = 32 texels exceeds the limit of 16"):
        EnvMap.load(tmp_path / "a.exr")
    assert env_mod.max_env_texels() == 16


# -- 2. black env maps ------------------------------------------------------------------------


def test_black_env_map_rejected(tmp_path):
    EnvMap(torch.zeros(8, 16, 3)).save(tmp_path / "black.exr")
    with pytest.raises(ValueError, match=r"black.exr' is black"):
        EnvMap.load(tmp_path / "black.exr")
    EnvMap(torch.full((8, 16, 3), 1e-9)).save(tmp_path / "dim.exr")
    with pytest.raises(ValueError, match="black"):
        EnvMap.load(tmp_path / "dim.exr")
    # nearly black on average: one faint texel in a large map
    d = torch.zeros(64, 128, 3)
    d[10, 10] = 1e-3
    with pytest.raises(ValueError, match="nearly black .*mean luminance"):
        env_mod.check_lit(EnvMap(d))
    EnvMap(torch.full((8, 16, 3), 1e-3)).save(tmp_path / "night.exr")
    EnvMap.load(tmp_path / "night.exr")  # dark is fine

    p = _scene_file(tmp_path, **{"procedural =": 'file = "black.exr"', "height = 32": "# no height"})
    msg = _load_error(p)
    assert "[envmap] file 'black.exr'" in msg and "black" in msg
    sc = load_scene_file(_scene_file(tmp_path))
    with pytest.raises(ValueError, match="scene 'two_boxes': env map is black"):
        sc.replace(envmap=EnvMap(torch.zeros(8, 16, 3)))


# -- 3. meshes collapsed by a transform -------------------------------------------------------


@pytest.mark.parametrize("scale, translate, what", [
    ("1e-30", "[-0.5, 0.5, -0.2]", "zero-area faces|degenerate"),  # collapses onto the translation
    ("1e-30", "[0.0, 0.0, 0.0]", "zero-area faces|degenerate"),  # tiny but float32-representable
    ("[1.0, 1e-30, 1.0]", "[0.0, 0.0, 0.0]", "zero-area faces"),  # flattened box
])
def test_collapsed_mesh_rejected(tmp_path, scale, translate, what):
    p = _scene_file(tmp_path, **{"scale = [0.5, 1.0, 0.5]": f"scale = {scale}", "translate = [-0.5": f"translate = {translate}"})
    msg = _load_error(p)
    assert "[[shape]] #0 ('tall_box') scale/rotate/translate" in msg and re.search(what, msg), msg


def test_scene_rejects_degenerate_shape():
    V = torch.tensor([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=torch.float32)
    F = torch.tensor([[0, 1, 2]])
    ok = Mesh(V, F).validate()
    tiny = Mesh(V * 1e-30, F, ok.N)
    check_extent(ok)
    with pytest.raises(ValueError, match="shape 'speck' is degenerate"):
        Scene("s", [Shape("big", "a", ok), Shape("speck", "a", tiny)], ["a"],
              Camera((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 8, 8), procedural("overcast", height=8), {"a": Phong()})


# -- 4. a camera that sees no geometry --------------------------------------------------------


@pytest.mark.parametrize("line, new", [
    ("fov_deg =", "fov_deg = 179.99"),  # every pixel wider than the scene: the coverage mask was empty
    ("target =", "target = [0.0, 4.0, 8.0]"),  # looking away
])
def test_camera_that_sees_nothing_is_reported(tmp_path, line, new):
    msg = _load_error(_scene_file(tmp_path, **{line: new}))
    assert "[camera] fov_deg/origin/target: the camera sees no geometry" in msg


def test_covered_pixels_matches_the_gbuffer_coverage():
    """The cheap check counts the same fully covered pixels as the Mitsuba G-buffer mask."""
    from references.gbuffer import make_gbuffer

    sc = load_scene_file(EXAMPLES / "two_boxes.toml")
    n = covered_pixels(sc)
    cov = make_gbuffer(sc, sc.default_frame(), 2).coverage
    assert abs(n - int(cov.sum())) <= 2 and n > 1000, (n, int(cov.sum()))


# -- 5. BRDF parameters that overflow float32 ---------------------------------------------------


def test_phong_exponent_overflow_rejected_in_scene_file(tmp_path):
    msg = _load_error(_scene_file(tmp_path, **{"s = 30": "s = 1e12"}))
    assert "[materials.red] s = 1000000000000.0 exceeds" in msg


def test_lobe_parameter_bounds():
    Phong(s=MAX_PHONG_EXPONENT)
    BlinnPhong(s=MAX_BLINN_EXPONENT)
    CookTorrance(m=MIN_LOBE_WIDTH)
    TorranceSparrow(sigma=MIN_LOBE_WIDTH)
    Ward(ax=MIN_LOBE_WIDTH, ay=MIN_LOBE_WIDTH)
    for kind, p in [("phong", dict(s=MAX_PHONG_EXPONENT * 1.01)), ("blinnphong", dict(s=MAX_BLINN_EXPONENT * 1.01)),
                    ("cooktorrance", dict(m=MIN_LOBE_WIDTH / 1.01)), ("torrancesparrow", dict(sigma=MIN_LOBE_WIDTH / 1.01)),
                    ("ward", dict(ax=MIN_LOBE_WIDTH / 100, ay=MIN_LOBE_WIDTH * 50))]:
        with pytest.raises(ValueError, match=rf"^{re.escape(next(iter(p)))}|^sqrt\(ax·ay\)"):
            Material.from_params({"kind": kind, **p})


def test_phong_bound_rationale_in_float32():
    """R·wi of float32 unit vectors rounds up to 2 ulp above 1; (1+2·2⁻²³)^s overflows float32 at
    s ≈ 3e8 and stays within a factor e of the peak at the accepted bound 2²²."""
    c = torch.tensor([1.0 + 2 * 2.0**-23], dtype=torch.float32)
    assert float(c) > 1.0
    s = MAX_PHONG_EXPONENT
    peak = (s + 1) / (2 * math.pi)
    v = float(power_cosine_pdf(c, s))
    assert math.isfinite(v) and peak < v <= math.e * peak * 1.001
    assert math.isinf(float(power_cosine_pdf(c, 3.1e8)))
    # float32 dot products of unit vectors near the mirror direction do round above 1
    g = torch.Generator().manual_seed(0)
    a = torch.nn.functional.normalize(torch.randn(200000, 3, generator=g), dim=1)
    b = torch.nn.functional.normalize(a + 1e-7 * torch.randn(200000, 3, generator=g), dim=1)
    assert float((a * b).sum(-1).max()) > 1.0
