"""Scene files with a researcher's own assets (issue 15): a size (vertex budget, film, env map),
rotate, captured probes by name, and a skinned glTF keeping its skin and clip."""
from __future__ import annotations

import math
from pathlib import Path

import pytest
import torch

from scenes.scenefile import VERTEX_BUDGET, euler_xyz, load_scene_file
from scenes.sequences import make_sequence

ASSETS = Path(__file__).resolve().parents[2] / "scenes" / "assets"
GROUND = Path(__file__).resolve().parents[2] / "scenes" / "examples" / "ground.obj"


def _write(tmp_path, body: str) -> Path:
    p = tmp_path / "mine.toml"
    p.write_text('''name = "mine"
[camera]
origin = [0.0, 1.2, 3.5]
target = [0.0, 0.5, 0.0]
fov_deg = 40.0
width = 96
height = 64
[envmap]
probe = "forest"
''' + body)
    return p


DRAGON = f'''
[[shape]]
name = "dragon"
region = "dragon"
mesh = "{ASSETS / 'meshes' / 'dragon.ply'}"
scale = 1.0
[[shape]]
name = "ground"
region = "ground"
mesh = "{GROUND}"
[materials.dragon]
kind = "phong"
kd = 0.3
ks = 0.3
s = 20
[materials.ground]
kind = "lambert"
kd = 0.5
'''


def test_size_decimates_to_the_budget_and_sets_film_and_env(tmp_path, capsys):
    p = _write(tmp_path, DRAGON)
    whole = load_scene_file(p)  # as written: the stored scan whole, the film and env as given
    n_whole = whole.geometry().V.shape[0]
    assert n_whole > VERTEX_BUDGET["test"] and (whole.camera.width, whole.camera.height) == (96, 64)
    test = load_scene_file(p, size="test")
    assert test.geometry().V.shape[0] <= VERTEX_BUDGET["test"]
    assert (test.camera.width, test.camera.height) == (64, 43)  # larger side = 64, aspect kept
    assert test.envmap.height == 64 and test.size == "test"
    assert "decimated" in capsys.readouterr().err
    bench = load_scene_file(p, size="bench")
    assert bench.geometry().V.shape[0] == n_whole <= VERTEX_BUDGET["bench"]  # within budget: untouched
    assert (bench.camera.width, bench.camera.height) == (256, 171) and bench.envmap.height == 256
    with pytest.raises(ValueError, match="size must be one of"):
        load_scene_file(p, size="huge")


def test_rotate_turns_a_z_up_scan_upright(tmp_path):
    assert torch.allclose(euler_xyz((-90, 0, 0)) @ torch.tensor([0.0, 0, 1], dtype=torch.float64),
                          torch.tensor([0.0, 1, 0], dtype=torch.float64), atol=1e-12)
    plain = load_scene_file(_write(tmp_path, DRAGON))
    rot = load_scene_file(_write(tmp_path, DRAGON.replace("scale = 1.0", "scale = 1.0\nrotate = [-90.0, 0.0, 0.0]")))
    a, b = plain.shapes[0].mesh.V.double(), rot.shapes[0].mesh.V.double()
    ext_a, ext_b = a.max(0).values - a.min(0).values, b.max(0).values - b.min(0).values
    assert torch.allclose(ext_b, ext_a[[0, 2, 1]], rtol=1e-5)  # y and z extents swap
    with pytest.raises(ValueError, match=r"rotate must be 3 numbers|rotate"):
        load_scene_file(_write(tmp_path, DRAGON.replace("scale = 1.0", "rotate = 5")))


def test_probe_by_name_and_unknown_probe(tmp_path):
    sc = load_scene_file(_write(tmp_path, DRAGON))
    assert sc.envmap.height == 64 and float(sc.envmap.data.max()) > 1.0  # HDR
    bad = _write(tmp_path, DRAGON).read_text().replace('probe = "forest"', 'probe = "nowhere"')
    (tmp_path / "bad.toml").write_text(bad)
    with pytest.raises(ValueError, match=r"bad.toml: \[envmap\] probe 'nowhere' unknown"):
        load_scene_file(tmp_path / "bad.toml")


CHARACTER = f'''
[[shape]]
name = "person"
region = "person"
mesh = "{ASSETS / 'characters' / 'bcn_epileptic.glb'}"
[[shape]]
name = "ground"
region = "ground"
mesh = "{GROUND}"
[materials.person]
kind = "phong"
kd = 0.4
ks = 0.2
s = 25
[materials.ground]
kind = "lambert"
kd = 0.5
'''


def test_skinned_gltf_keeps_its_skin_and_clip(tmp_path):
    p = _write(tmp_path, CHARACTER.replace('origin = [0.0, 1.2, 3.5]', 'origin = [0.0, 1.2, 3.5]'))
    sc = load_scene_file(p, size="test")
    assert sc.skeleton is not None and sc.animation is not None and sc.animation.shape[1] == sc.skeleton.num_joints
    assert sc.geometry().V.shape[0] <= VERTEX_BUDGET["test"]
    W = sc.skin_weights["person"]
    assert W.shape[0] == sc.shapes[0].mesh.num_vertices and torch.allclose(W.sum(1), torch.ones(W.shape[0]), atol=1e-5)
    fr = make_sequence(sc, "P", n_frames=3, seed=0)  # driven by the file's own clip
    d = [(sc.animation - f.pose).abs().max(1).values.min() for f in fr]
    assert all(float(x) < math.pi for x in d) and not torch.equal(fr[1].pose, fr[2].pose)
    moved = sc.geometry(fr[1].pose).V
    assert (moved - sc.geometry().V).abs().max() > 1e-3  # the pose moves the mesh
    static = load_scene_file(_write(tmp_path, CHARACTER.replace('mesh = "' + str(ASSETS / 'characters' / 'bcn_epileptic.glb') + '"',
                                                                'mesh = "' + str(ASSETS / 'characters' / 'bcn_epileptic.glb') + '"\nskeleton = false')))
    assert static.skeleton is None
