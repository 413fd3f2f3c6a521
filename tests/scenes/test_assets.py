"""The vendored real assets (scenes/assets/): provenance listing, licences, size budget, probes,
the load-time decimation of scans, the scanned library scenes and the skinned character."""
from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch

from scenes import envmap as E
from scenes import library
from scenes.library import ASSET_DIR, TEST_SCAN_VERTICES, decimate, get_scene
from scenes.mesh import load_mesh

ASSETS_MD = ASSET_DIR / "ASSETS.md"
BUDGET_BYTES = 15 * 1024 * 1024
# Files that carry data (each must be listed in ASSETS.md with its hash prefix).
DATA_EXT = {".ply", ".exr", ".glb"}
SCANS = {"bunny": "bunny", "dragon": "dragon"}  # scene name → mesh file stem


def _files() -> list[Path]:
    return sorted(p for p in ASSET_DIR.rglob("*") if p.is_file() and "__pycache__" not in p.parts)


def test_every_file_listed_with_its_hash():
    text = ASSETS_MD.read_text()
    for p in _files():
        rel = p.relative_to(ASSET_DIR).as_posix()
        if rel == "ASSETS.md":
            continue
        assert f"`{rel}`" in text, f"{rel} is not listed in ASSETS.md"
        if p.suffix in DATA_EXT:
            h = hashlib.sha256(p.read_bytes()).hexdigest()[:16]
            assert h in text, f"{rel}: sha256 {h}… not in ASSETS.md (file changed without updating it?)"


def test_licences_present_and_named():
    text = ASSETS_MD.read_text()
    lic = sorted((ASSET_DIR / "LICENSES").iterdir())
    assert lic, "no licence files"
    for p in lic:
        assert p.stat().st_size > 50 and f"LICENSES/{p.name}" in text
    bsd = (ASSET_DIR / "LICENSES" / "BSD-3-Clause-assimp.txt").read_text()
    assert "Neither the names of the copyright holders" in bsd   # the third clause
    assert "CC0" in (ASSET_DIR / "LICENSES" / "CC0-blender-studiolights-world.txt").read_text()
    # every asset section states source, author, licence, attribution and changes
    sections = text.split("\n### ")[1:]
    assert len(sections) == 4
    for s in sections:
        for field in ("**Source**", "**Original author**", "**Licence**", "**Attribution**", "**Changes**"):
            assert field in s, f"section {s.splitlines()[0]!r} lacks {field}"


def test_size_budget():
    total = sum(p.stat().st_size for p in _files())
    assert total <= BUDGET_BYTES, f"scenes/assets holds {total / 2**20:.2f} MiB > 15 MiB"


@pytest.mark.parametrize("name", E.PROBE_NAMES)
def test_probes_load_finite_non_negative(name):
    full = E.probe(name)
    assert (full.height, full.width) == (E.PROBE_HEIGHT, 2 * E.PROBE_HEIGHT)
    assert torch.isfinite(full.data).all() and (full.data >= 0).all()
    assert full.data.max() > 10 * full.data.mean()   # an HDR probe, not a clipped LDR image
    small = E.probe(name, height=64)
    assert (small.height, small.width) == (64, 128)
    # box averaging by an integer factor keeps the plain texel mean exactly (up to round-off)
    torch.testing.assert_close(small.data.double().mean((0, 1)), full.data.double().mean((0, 1)),
                               rtol=1e-5, atol=0)
    assert torch.equal(E.named(name, height=64).data, small.data)


def test_probe_errors(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match="unknown probe"):
        E.probe("no_such_probe")
    with pytest.raises(ValueError, match="height"):
        E.probe("forest", height=100)   # does not divide 256
    with pytest.raises(ValueError, match="unknown env map"):
        E.named("no_such_map", height=64)
    assert E.named("sky_sun", height=16).height == 16   # procedural names still work
    bad = np.ones((E.PROBE_HEIGHT, 2 * E.PROBE_HEIGHT, 3), np.float32)
    bad[3, 4, 1] = np.nan
    E.write_image(tmp_path / "forest.exr", bad)
    monkeypatch.setattr(E, "PROBE_DIR", tmp_path)
    with pytest.raises(ValueError, match="NaN"):
        E.probe("forest")
    bad[3, 4, 1] = -1.0
    E.write_image(tmp_path / "forest.exr", bad)
    with pytest.raises(ValueError, match="negative"):
        E.probe("forest")


def test_decimate_budget_shape_and_determinism():
    m = load_mesh(ASSET_DIR / "meshes" / "bunny.ply")
    d = decimate(m, 600)
    assert 500 <= d.num_vertices <= 600
    assert torch.equal(d.V, decimate(m, 600).V) and torch.equal(d.F, decimate(m, 600).F)
    assert decimate(m, m.num_vertices) is m          # within budget: unchanged
    # same surface: area within 3 %, every decimated vertex within 0.5 % of the bbox diagonal of
    # the original surface (VTK implicit distance to the original triangles)
    import pyvista as pv

    area = lambda x: float(x.face_normals()[1].sum())  # noqa: E731
    assert area(d) == pytest.approx(area(m), rel=0.03)
    pd = lambda x: pv.PolyData.from_regular_faces(x.V.double().numpy(), x.F.numpy())  # noqa: E731
    dist = np.abs(pd(d).compute_implicit_distance(pd(m))["implicit_distance"])
    diag = float((m.V.max(0).values - m.V.min(0).values).norm())
    assert dist.max() < 0.005 * diag
    with pytest.raises(ValueError, match="max_vertices"):
        decimate(m, 3)


@pytest.mark.parametrize("name", sorted(SCANS))
def test_scan_scenes_sizes_and_placement(name):
    for size, lo, hi in (("test", 0, 2000), ("bench", 5000, 20000)):
        sc = get_scene(name, size)
        obj = next(s.mesh for s in sc.shapes if s.name == name)
        assert lo <= sc.geometry().num_vertices <= hi
        if size == "test":
            assert obj.num_vertices <= TEST_SCAN_VERTICES
        else:   # the bench object is the vendored mesh, whole
            assert obj.num_vertices == load_mesh(ASSET_DIR / "meshes" / f"{SCANS[name]}.ply").num_vertices
        # standing on the ground plane (y = 0), just above it, centred on the Y axis
        ymin = float(obj.V[:, 1].min())
        assert 0.0 < ymin < 0.01
        c = 0.5 * (obj.V.max(0).values + obj.V.min(0).values)
        assert abs(float(c[0])) < 1e-4 and abs(float(c[2])) < 1e-4
        # lit by a captured probe at the size's resolution
        assert sc.envmap.height == library.SIZES[size]["env"]


def test_skinned_character_loads_with_its_clip():
    from scenes.gltf import load_skinned_glb_rig
    from scenes.skeleton import skin

    mesh, rig = load_skinned_glb_rig(ASSET_DIR / "characters" / "bcn_epileptic.glb")
    # the whole body (torso + head + legs joined), 54 joints, one 100-key clip
    assert (mesh.num_vertices, mesh.num_faces) == (3014, 5126)
    assert rig.skeleton.num_joints == 54 and rig.animation.shape == (100, 54)
    lo, hi = mesh.V.min(0).values, mesh.V.max(0).values
    assert int(torch.argmax(hi - lo)) == 1                 # standing: tallest along +Y
    torch.testing.assert_close(rig.weights.sum(1), torch.ones(mesh.num_vertices))
    # posing by a clip frame moves the body and keeps it finite
    T = rig.skeleton.forward_kinematics(rig.animation[50])
    V, N = skin(mesh.V, mesh.N, rig.weights, T)
    assert torch.isfinite(V).all() and (V - mesh.V).norm(dim=1).max() > 0.05


def test_character_scene_sizes_pose_and_weight_transfer():
    """`character`: the glTF rig as a library scene; the test size is decimated with its weights
    carried over, so posing it by a clip frame stays on the posed full-resolution surface."""
    import pyvista as pv

    from scenes.library import character_rig
    from scenes.sequences import make_sequence
    from scenes.skeleton import skin

    for size, lo, hi in (("test", 0, 2000), ("bench", 5000, 20000)):
        sc = get_scene("character", size)
        assert sc.dynamic and lo <= sc.geometry().num_vertices <= hi
        obj = next(s.mesh for s in sc.shapes if s.name == "character")
        assert 0.0 < float(obj.V[:, 1].min()) < 0.01                 # rest pose stands on the ground
        torch.testing.assert_close(sc.skin_weights["character"].sum(1), torch.ones(obj.num_vertices))
        frames = make_sequence(sc, "P", n_frames=3, seed=0)             # P cells can be planned
        assert all(torch.isfinite(sc.geometry(f.pose).V).all() for f in frames)
    full, sk_f, W_f, clip, _ = character_rig("bench")
    small, sk_s, W_s, _, _ = character_rig("test")
    assert small.num_vertices <= TEST_SCAN_VERTICES
    height = float(full.V[:, 1].max() - full.V[:, 1].min())
    pd = lambda V, F: pv.PolyData.from_regular_faces(V.double().numpy(), F.numpy())  # noqa: E731
    for k in (30, 60):
        Vf, _ = skin(full.V, full.N, W_f, sk_f.forward_kinematics(clip[k]))
        Vs, _ = skin(small.V, small.N, W_s, sk_s.forward_kinematics(clip[k]))
        d = np.abs(pd(Vs, small.F).compute_implicit_distance(pd(Vf, full.F))["implicit_distance"])
        assert d.max() < 0.015 * height, (k, d.max() / height)
