"""TOML scene files: the shipped example loads and renders; bad input → one ValueError naming
the file and the key; relative paths resolve against the TOML file's folder."""
from __future__ import annotations

import shutil
from pathlib import Path

import pytest
import torch

from scenes.camera import Camera
from scenes.mesh import load_mesh
from scenes.scenefile import load_scene_file

EXAMPLES = Path(__file__).resolve().parents[2] / "scenes" / "examples"
EXAMPLE = EXAMPLES / "two_boxes.toml"
BOX = EXAMPLES / "box.obj"

# float32 positions after an affine transform of exact OBJ coordinates (several ulps of ~1)
POS_TOL = 1e-6

GOOD = """
name = "t"
[camera]
origin = [0.0, 2.0, 3.0]
target = [0.0, 0.0, 0.0]
fov_deg = 40
width = 8
height = 8
[envmap]
procedural = "overcast"
height = 8
[[shape]]
name = "b"
region = "r"
mesh = "box.obj"
[materials.r]
kind = "phong"
kd = [0.5, 0.5, 0.5]
ks = 0.2
s = 20
"""


def _write(dir_: Path, text: str, name: str = "scene.toml") -> Path:
    shutil.copy(BOX, dir_ / "box.obj")
    p = dir_ / name
    p.write_text(text)
    return p


def test_example_loads_and_renders_through_the_pipeline():
    from methods.registry import get_method
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    scene = load_scene_file(EXAMPLE)
    assert scene.name == "two_boxes"
    assert scene.regions == ["red", "blue", "ground"]
    assert [s.name for s in scene.shapes] == ["tall_box", "small_box", "ground"]
    g = scene.geometry()
    # subdivide = 2: 16 faces per input face; box faces 5 x 5 vertices, the 9 x 9 ground 33 x 33
    assert g.num_vertices == 2 * 6 * 25 + 33 * 33 and g.num_faces == 16 * (12 + 12 + 128)
    # boxes are closed with outward faces: each face normal points away from its box centre
    for i in range(2):
        m = g.shape_mesh(i)
        fn, area = m.face_normals()
        cen = m.V[m.F].mean(1) - m.V.mean(0)
        assert ((fn * cen).sum(1) > 0).all() and (area > 0).all()
    h = scene.content_hash()
    assert h == load_scene_file(EXAMPLE).content_hash()  # deterministic
    c = scene.camera
    small = scene.replace(camera=Camera(c.origin, c.target, c.up, c.fov_deg, 16, 16))
    frames = make_sequence(small, "V", 2)
    assert len(frames) == 2
    gb = make_gbuffer(small, frames[0], 1)
    oracle = get_method("oracle")(light_samples=4, brdf_samples=4, seed=0)
    oracle.precompute(small)
    img = oracle.render(frames[0], gb)
    assert img.shape == (16, 16, 3) and torch.isfinite(img).all()
    assert (img >= 0).all() and img.mean() > 0  # lit by the sky


def test_scale_translate_and_relative_paths(tmp_path, monkeypatch):
    sub = tmp_path / "a" / "b"
    sub.mkdir(parents=True)
    text = GOOD.replace('mesh = "box.obj"', 'mesh = "box.obj"\nscale = [2.0, 1.0, 0.5]\ntranslate = [1.0, 2.0, 3.0]')
    p = _write(sub, text)
    monkeypatch.chdir(tmp_path)  # the mesh path is NOT relative to the working directory
    scene = load_scene_file(Path("a/b/scene.toml"))
    V0 = load_mesh(BOX).V
    want = V0 * torch.tensor([2.0, 1.0, 0.5]) + torch.tensor([1.0, 2.0, 3.0])
    assert torch.allclose(scene.geometry().V, want, atol=POS_TOL)
    # normals stay unit and axis-aligned under the non-uniform scale
    assert torch.allclose(scene.geometry().N.norm(dim=1), torch.ones(24), atol=POS_TOL)
    assert load_scene_file(str(p)).content_hash() == scene.content_hash()


def test_subdivide_refines_a_box_without_changing_its_shape(tmp_path):
    from scenes.mesh import subdivide

    base = load_scene_file(_write(tmp_path, GOOD)).shapes[0].mesh
    fine = load_scene_file(_write(tmp_path, GOOD.replace('mesh = "box.obj"', 'mesh = "box.obj"\nsubdivide = 2'))).shapes[0].mesh
    assert fine.num_faces == 16 * base.num_faces
    # each of the 6 faces (2 triangles, 4 own corners) becomes a 5 x 5 grid of vertices
    assert base.num_vertices == 24 and fine.num_vertices == 6 * 25
    assert torch.allclose(fine.V.min(0).values, base.V.min(0).values) and torch.allclose(fine.V.max(0).values, base.V.max(0).values)
    a0, a1 = base.face_normals()[1].sum(), fine.face_normals()[1].sum()
    assert abs(float(a1 - a0)) < 1e-5 * float(a0)
    # every new vertex lies on a face of the box (|coordinate| = half extent on one axis) with its face's normal
    half = base.V.abs().max()
    on_face = (fine.V.abs() - half).abs().min(1).values < 1e-6
    assert bool(on_face.all())
    nz = fine.N.abs().argmax(1)
    assert bool(((fine.V.abs() - half).abs().gather(1, nz[:, None]).squeeze(1) < 1e-6).all())
    assert subdivide(base, 0).num_faces == base.num_faces
    with pytest.raises(ValueError):
        subdivide(base, -1)


def test_default_name_is_file_stem(tmp_path):
    p = _write(tmp_path, GOOD.replace('name = "t"\n', ""), "my_room.toml")
    assert load_scene_file(p).name == "my_room"


def test_envmap_file_and_rotation(tmp_path):
    from scenes.envmap import procedural

    procedural("studio", height=8).save(tmp_path / "env.exr")
    text = GOOD.replace('procedural = "overcast"\nheight = 8', 'file = "env.exr"\nrotate_y_deg = 90')
    scene = load_scene_file(_write(tmp_path, text))
    assert scene.envmap.height == 8
    # R_y(90°) maps +X to −Z
    R = scene.envmap.to_world.double()
    assert torch.allclose(R @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
                          torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64), atol=POS_TOL)


BAD = [
    # (replace old → new, substrings the message must contain)
    ('kind = "phong"', 'kind = "foo"', ["[materials.r]", "kind", "'foo'", "phong"]),
    ("s = 20", "s = -1", ["[materials.r]", "s must be"]),
    ("s = 20", "s = 20\nq = 3", ["[materials.r]", "q"]),
    ("s = 20", 's = "20"', ["[materials.r]", "s must be a number"]),
    ('kd = [0.5, 0.5, 0.5]', 'kd = [0.5, 0.5]', ["[materials.r]", "kd"]),
    ('kind = "phong"\n', "", ["[materials.r]", "kind"]),
    ("[materials.r]", "[materials.other]", ["[materials]", "'r'"]),
    ('mesh = "box.obj"', 'mesh = "nope.obj"', ["[[shape]]", "mesh", "nope.obj"]),
    ('mesh = "box.obj"', 'mesh = "corrupt.ply"', ["[[shape]]", "mesh", "corrupt.ply"]),
    ('mesh = "box.obj"', 'mesh = "box.obj"\nscale = 0', ["[[shape]]", "scale"]),
    ('mesh = "box.obj"', 'mesh = "box.obj"\ntranslate = [1, 2]', ["[[shape]]", "translate"]),
    ('mesh = "box.obj"', 'mesh = "box.obj"\ncolour = 1', ["[[shape]]", "colour"]),
    ('region = "r"\n', "", ["[[shape]]", "region"]),
    ('mesh = "box.obj"', 'mesh = "box.obj"\nsubdivide = 7', ["[[shape]]", "subdivide", "[0, 6]"]),
    ('mesh = "box.obj"', 'mesh = "box.obj"\nsubdivide = 1.5', ["[[shape]]", "subdivide"]),
    ('mesh = "box.obj"', 'mesh = "box.obj"\nsubdivide = -1', ["[[shape]]", "subdivide"]),
    ('name = "b"', "name = 3", ["[[shape]]", "name"]),
    ('procedural = "overcast"', 'procedural = "disco"', ["[envmap]", "disco", "sky_sun"]),
    ('procedural = "overcast"\nheight = 8', 'file = "missing.exr"', ["[envmap]", "file", "missing.exr"]),
    ('procedural = "overcast"\nheight = 8', 'file = "corrupt.exr"', ["[envmap]", "file", "corrupt.exr"]),
    ('procedural = "overcast"', 'procedural = "overcast"\nfile = "x.exr"', ["[envmap]", "file", "procedural"]),
    ("height = 8\n[[shape]]", "height = 8.5\n[[shape]]", ["[envmap]", "height"]),
    ("fov_deg = 40", "fov_deg = 200", ["[camera]", "fov_deg"]),
    ("fov_deg = 40\n", "", ["[camera]", "fov_deg"]),
    ("width = 8", 'width = "8"', ["[camera]", "width"]),
    ("origin = [0.0, 2.0, 3.0]", "origin = [0.0, 0.0, 0.0]", ["[camera]", "coincide"]),
    ('name = "t"', 'name = "t"\nlights = 1', ["top level", "lights"]),
    ('name = "t"', 'name = "t" = ', ["invalid TOML"]),
]


@pytest.mark.parametrize("old,new,needles", BAD, ids=[f"{i}:{b[1][:24]}" for i, b in enumerate(BAD)])
def test_bad_input_raises_one_clear_value_error(tmp_path, old, new, needles):
    assert old in GOOD
    (tmp_path / "corrupt.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 9\x00\xff")
    (tmp_path / "corrupt.exr").write_bytes(b"\x76\x2f\x31\x01garbage")
    p = _write(tmp_path, GOOD.replace(old, new, 1))
    with pytest.raises(ValueError) as ei:
        load_scene_file(p)
    msg = str(ei.value)
    assert msg.startswith("scene.toml:"), msg
    for n in needles:
        assert n in msg, (n, msg)


def test_missing_scene_file(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        load_scene_file(tmp_path / "none.toml")


def test_good_baseline_loads(tmp_path):
    # the BAD cases are single edits of this file, so it must load cleanly
    scene = load_scene_file(_write(tmp_path, GOOD))
    assert scene.materials["r"].s == 20.0 and scene.materials["r"].ks == (0.2, 0.2, 0.2)
