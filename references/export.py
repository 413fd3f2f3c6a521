"""Scene + Frame → a Mitsuba 3 scene dictionary for ``mi.load_dict``.

One ``mi.Mesh`` per ``Shape`` of the scene, built from the *posed* merged geometry
(``scene.geometry(frame.pose)``), with OUR per-vertex normals (so Mitsuba's shading normal is the
normalised barycentric interpolation of the same normals the methods use) and uv when present.
Shapes are stored under the keys ``shape_00000, shape_00001, …`` in ``scene.shapes`` order and the
meshes carry the same names, so a Mitsuba shape maps back to our shape index by its id
(``shape_index_of``) — ``mi_scene.shapes()`` keeps the dictionary order, but nothing relies on that.

Each shape's BSDF is ``references.plugins.material_to_mitsuba(frame.materials[shape.region])``;
the emitter is ``references.plugins.envmap_to_mitsuba(frame.envmap)``; the sensor is
``camera_to_mitsuba(frame.camera)`` (perspective, box reconstruction filter) with an ``independent``
sampler; the integrator is ``path`` with ``max_depth`` (2 = direct lighting only, 3 = +1 bounce,
4 = +2 bounces, −1 = full global illumination) and ``hide_emitters=True``.
"""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np
import torch

SHAPE_KEY = "shape_{:05d}"
_SHAPE_RE = re.compile(r"^shape_(\d{5})$")


def _mi():
    from references.mitsuba_setup import ensure_variant

    ensure_variant()
    import mitsuba as mi

    return mi


@dataclass(frozen=True)
class ShapeSlice:
    """Where shape i lives in the merged geometry: vertices [v0, v1), faces [f0, f1)."""

    v0: int
    v1: int
    f0: int
    f1: int


def shape_slices(geom, n_shapes: int) -> list[ShapeSlice]:
    """Per-shape vertex/face ranges of a ``SceneGeometry`` (offsets of length n or n + 1)."""
    vo = [int(x) for x in torch.as_tensor(geom.vertex_offset).reshape(-1).tolist()]
    fo = [int(x) for x in torch.as_tensor(geom.face_offset).reshape(-1).tolist()]
    n_v, n_f = int(geom.V.shape[0]), int(geom.F.shape[0])
    if len(vo) == n_shapes:
        vo = vo + [n_v]
    if len(fo) == n_shapes:
        fo = fo + [n_f]
    if len(vo) != n_shapes + 1 or len(fo) != n_shapes + 1:
        raise ValueError(f"geometry offsets do not match {n_shapes} shapes: vertex_offset {len(vo)}, "
                         f"face_offset {len(fo)}")
    if vo[-1] != n_v or fo[-1] != n_f or any(b < a for a, b in zip(vo, vo[1:])) or any(b < a for a, b in zip(fo, fo[1:])):
        raise ValueError("geometry offsets are not increasing ranges covering V and F")
    return [ShapeSlice(vo[i], vo[i + 1], fo[i], fo[i + 1]) for i in range(n_shapes)]


def make_mesh(name: str, V: torch.Tensor, F: torch.Tensor, N: torch.Tensor, uv: torch.Tensor | None = None,
              bsdf=None):
    """A ``mi.Mesh`` from local arrays V (n, 3), F (m, 3) (indices into V), N (n, 3), uv (n, 2)|None.

    ``bsdf``: a Mitsuba BSDF object or dict (None → Mitsuba's default diffuse).
    """
    mi = _mi()
    V = torch.as_tensor(V).detach().cpu()
    F = torch.as_tensor(F).detach().cpu()
    N = torch.as_tensor(N).detach().cpu()
    n, m = int(V.shape[0]), int(F.shape[0])
    if V.shape != (n, 3) or N.shape != (n, 3) or F.shape != (m, 3):
        raise ValueError(f"mesh {name}: V (n,3), N (n,3), F (m,3) expected, got {tuple(V.shape)}, "
                         f"{tuple(N.shape)}, {tuple(F.shape)}")
    if m == 0 or n == 0:
        raise ValueError(f"mesh {name} is empty")
    if int(F.min()) < 0 or int(F.max()) >= n:
        raise ValueError(f"mesh {name}: face indices outside [0, {n})")
    if uv is not None:
        uv = torch.as_tensor(uv).detach().cpu()
        if uv.shape != (n, 2):
            raise ValueError(f"mesh {name}: uv must be ({n}, 2), got {tuple(uv.shape)}")
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = mi.load_dict(bsdf) if isinstance(bsdf, dict) else bsdf
    mesh = mi.Mesh(name, vertex_count=n, face_count=m, props=props, has_vertex_normals=True,
                   has_vertex_texcoords=uv is not None)
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(V.numpy().astype(np.float32).reshape(-1))
    p["vertex_normals"] = mi.Float(N.numpy().astype(np.float32).reshape(-1))
    p["faces"] = mi.UInt32(F.numpy().astype(np.uint32).reshape(-1))
    if uv is not None:
        p["vertex_texcoords"] = mi.Float(uv.numpy().astype(np.float32).reshape(-1))
    p.update()  # calls parameters_changed(): bbox, acceleration data
    return mesh


def _geometry_uv(scene, geom, sl: ShapeSlice, i: int):
    uv = getattr(geom, "uv", None)
    if uv is not None:
        return uv[sl.v0:sl.v1]
    mesh_uv = getattr(scene.shapes[i].mesh, "uv", None)
    if mesh_uv is not None and mesh_uv.shape[0] == sl.v1 - sl.v0:
        return mesh_uv
    return None


def shape_meshes(scene, frame, *, with_bsdfs: bool = True) -> list:
    """One ``mi.Mesh`` per ``scene.shapes`` entry (same order) from the posed merged geometry."""
    geom = scene.geometry(frame.pose)
    slices = shape_slices(geom, len(scene.shapes))
    material_to_mitsuba = None
    if with_bsdfs:
        from references import plugins

        if hasattr(plugins, "register_all"):
            plugins.register_all()
        material_to_mitsuba = plugins.material_to_mitsuba
    meshes = []
    for i, (shape, sl) in enumerate(zip(scene.shapes, slices)):
        bsdf = None
        if with_bsdfs:
            if shape.region not in frame.materials:
                raise ValueError(f"frame has no material for region {shape.region!r} (shape {shape.name!r})")
            bsdf = material_to_mitsuba(frame.materials[shape.region])
        V = geom.V[sl.v0:sl.v1]
        N = geom.N[sl.v0:sl.v1]
        F = geom.F[sl.f0:sl.f1] - sl.v0
        meshes.append(make_mesh(SHAPE_KEY.format(i), V, F, N, _geometry_uv(scene, geom, sl, i), bsdf))
    return meshes


def camera_to_mitsuba(camera) -> dict:
    """Mitsuba ``perspective`` sensor dict of a ``scenes.camera.Camera`` (fov along x, box
    reconstruction filter, RGB film)."""
    mi = _mi()
    return {
        "type": "perspective",
        "fov": camera.fov_deg,
        "fov_axis": "x",
        "near_clip": camera.near_clip,
        "to_world": mi.ScalarTransform4f().look_at(origin=list(camera.origin), target=list(camera.target),
                                                    up=list(camera.up)),
        "film": {"type": "hdrfilm", "width": camera.width, "height": camera.height,
                 "rfilter": {"type": "box"}, "pixel_format": "rgb"},
    }


def sensor_dict(camera, *, spp: int = 1, seed: int = 0) -> dict:
    """``camera_to_mitsuba(camera)`` with an ``independent`` sampler and a box-filtered RGB film."""
    s = camera_to_mitsuba(camera)
    film = dict(s.get("film", {"type": "hdrfilm", "width": camera.width, "height": camera.height}))
    film["rfilter"] = {"type": "box"}  # the G-buffer's resolve() is a box filter too
    film["pixel_format"] = "rgb"
    film["component_format"] = "float32"
    s["film"] = film
    s["sampler"] = {"type": "independent", "sample_count": int(spp), "seed": int(seed)}
    return s


def _check_settings(max_depth: int, spp: int, seed: int) -> None:
    if int(max_depth) != max_depth or not (max_depth == -1 or max_depth >= 1):
        raise ValueError(f"max_depth must be -1 or >= 1, got {max_depth!r}")
    if int(spp) != spp or spp < 1:
        raise ValueError(f"spp must be a positive integer, got {spp!r}")
    if int(seed) != seed or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")


def to_mitsuba(scene, frame, *, max_depth: int, spp: int, seed: int) -> dict:
    """The ``mi.load_dict`` dictionary of ``scene`` as seen in ``frame``.

    max_depth: path length (2 = direct only, 3 = one bounce, 4 = two, −1 = unbounded);
    spp: samples per pixel of the sensor's sampler; seed: its seed.
    Keys: ``shape_00000``… (scene.shapes order), ``emitter``, ``sensor``, ``integrator``.
    """
    _check_settings(max_depth, spp, seed)
    from references import plugins

    d: dict = {"type": "scene"}
    for i, mesh in enumerate(shape_meshes(scene, frame)):
        d[SHAPE_KEY.format(i)] = mesh
    d["emitter"] = plugins.envmap_to_mitsuba(frame.envmap)
    d["sensor"] = sensor_dict(frame.camera, spp=spp, seed=seed)
    d["integrator"] = {"type": "path", "max_depth": int(max_depth), "hide_emitters": True}
    return d


def geometry_dict(scene, frame) -> dict:
    """Shapes (default BSDF) + sensor only: what the G-buffer needs (no plugins, no emitter)."""
    d: dict = {"type": "scene"}
    for i, mesh in enumerate(shape_meshes(scene, frame, with_bsdfs=False)):
        d[SHAPE_KEY.format(i)] = mesh
    d["sensor"] = sensor_dict(frame.camera)
    return d


def load(scene, frame, *, max_depth: int, spp: int, seed: int):
    """``mi.load_dict(to_mitsuba(...))``."""
    mi = _mi()
    return mi.load_dict(to_mitsuba(scene, frame, max_depth=max_depth, spp=spp, seed=seed))


def shape_index_of(mi_shape) -> int:
    """Our shape index of a Mitsuba shape exported by this module (from its id ``shape_NNNNN``)."""
    m = _SHAPE_RE.match(mi_shape.id())
    if not m:
        raise ValueError(f"Mitsuba shape {mi_shape.id()!r} was not exported by references.export")
    return int(m.group(1))


def shape_indices(mi_scene) -> np.ndarray:
    """(n,) our shape index of each entry of ``mi_scene.shapes()`` (in Mitsuba's order)."""
    return np.array([shape_index_of(s) for s in mi_scene.shapes()], dtype=np.int64)
