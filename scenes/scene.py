"""A scene: shapes (each a mesh with one region/material), camera, env map, materials, and for
dynamic scenes a skeleton with skin weights.

`scene.geometry(pose)` merges every shape into one indexed triangle mesh (`SceneGeometry`), the
layout every method, the G-buffer and the Mitsuba exporter share: shape i owns vertices
vertex_offset[i]:vertex_offset[i+1] and faces face_offset[i]:face_offset[i+1] (global indices).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from scenes.frame import Frame
from scenes.hashing import hash_envmap, hash_materials, hash_params, hash_tensor
from scenes.envmap import EnvMap, check_lit
from scenes.mesh import Mesh, check_extent
from scenes.skeleton import blend_skin, check_weights


@dataclass
class Shape:
    """One mesh with one region (material) name."""

    name: str
    region: str
    mesh: Mesh


@dataclass
class SceneGeometry:
    """Merged geometry. V (N, 3) f32, F (M, 3) i64, N (N, 3) f32 unit normals, uv (N, 2) | None,
    vertex_region (N,) i64 and face_region (M,) i64 indices into `scene.regions`,
    face_offset (S+1,) and vertex_offset (S+1,) i64 per shape, shape_names (S,)."""

    V: Tensor
    F: Tensor
    N: Tensor
    uv: Tensor | None
    vertex_region: Tensor
    face_region: Tensor
    face_offset: Tensor
    vertex_offset: Tensor
    shape_names: tuple[str, ...] = ()

    @property
    def num_vertices(self) -> int:
        return int(self.V.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.F.shape[0])

    def shape_mesh(self, i: int) -> Mesh:
        """The i-th shape's mesh (local vertex indices) — e.g. for exporting one Mitsuba shape."""
        v0, v1 = int(self.vertex_offset[i]), int(self.vertex_offset[i + 1])
        f0, f1 = int(self.face_offset[i]), int(self.face_offset[i + 1])
        return Mesh(self.V[v0:v1], self.F[f0:f1] - v0, self.N[v0:v1], None if self.uv is None else self.uv[v0:v1])


@dataclass(eq=False)
class Scene:
    """name; shapes: list[Shape]; regions: list[str] (index order used by vertex/face_region);
    camera: scenes.camera.Camera; envmap: scenes.envmap.EnvMap; materials: region → Material;
    skeleton: scenes.skeleton.Skeleton | None; skin_weights: shape name → (N_shape, J) weights of
    the skinned shapes (others are static); size: "test" | "bench"; animation: the scene's own clip,
    (F, J) joint angles per clip frame (e.g. a glTF's animation), which drives its "P" sequences."""

    name: str
    shapes: list[Shape]
    regions: list[str]
    camera: Any
    envmap: Any
    materials: dict[str, Any]
    skeleton: Any = None
    skin_weights: dict[str, Tensor] | None = None
    size: str = "test"
    animation: Tensor | None = None
    _rest: SceneGeometry | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        self.shapes = list(self.shapes)
        self.regions = list(self.regions)
        if not self.shapes:
            raise ValueError(f"scene {self.name!r} has no shapes")
        names = [s.name for s in self.shapes]
        if len(set(names)) != len(names):
            raise ValueError(f"scene {self.name!r} has duplicate shape names: {names}")
        if len(set(self.regions)) != len(self.regions):
            raise ValueError(f"scene {self.name!r} has duplicate regions: {self.regions}")
        for s in self.shapes:
            if s.region not in self.regions:
                raise ValueError(f"shape {s.name!r} has region {s.region!r} not in regions {self.regions}")
        missing = [r for r in self.regions if r not in self.materials]
        if missing:
            raise ValueError(f"scene {self.name!r}: no material for region(s) {missing}")
        extra = [r for r in self.materials if r not in self.regions]
        if extra:
            raise ValueError(f"scene {self.name!r}: materials for unknown region(s) {extra}")
        self.shapes = [Shape(s.name, s.region, s.mesh if s.mesh.N is not None else s.mesh.validate()) for s in self.shapes]
        if self.animation is not None:
            if self.skeleton is None:
                raise ValueError(f"scene {self.name!r}: an animation needs a skeleton")
            a = torch.as_tensor(self.animation, dtype=torch.float32)
            if a.dim() != 2 or a.shape[0] < 2 or a.shape[1] != self.skeleton.num_joints or not torch.isfinite(a).all():
                raise ValueError(f"scene {self.name!r}: animation must be finite (F >= 2, J = "
                                 f"{self.skeleton.num_joints}) joint angles, got {tuple(a.shape)}")
            self.animation = a
        for s in self.shapes:
            check_extent(s.mesh, f"shape {s.name!r}")
        if isinstance(self.envmap, EnvMap):
            check_lit(self.envmap, f"scene {self.name!r}: env map")
        if self.skin_weights is not None:
            if self.skeleton is None:
                raise ValueError("skin_weights given without a skeleton")
            by_name = {s.name: s for s in self.shapes}
            sw = {}
            for k, w in self.skin_weights.items():
                if k not in by_name:
                    raise ValueError(f"skin_weights for unknown shape {k!r}")
                sw[k] = check_weights(torch.as_tensor(w, dtype=torch.float32), by_name[k].mesh.num_vertices,
                                      self.skeleton.num_joints)
            self.skin_weights = sw
        elif self.skeleton is not None:
            raise ValueError("a scene with a skeleton needs skin_weights")

    # ARCHITECTURE.md spells the constructor argument `skin`; both names refer to the same data.
    @property
    def skin(self) -> dict[str, Tensor] | None:
        return self.skin_weights

    @property
    def dynamic(self) -> bool:
        return self.skeleton is not None

    def region_index(self, region: str) -> int:
        return self.regions.index(region)

    def rest_geometry(self) -> SceneGeometry:
        if self._rest is None:
            self._rest = _merge(self.shapes, self.regions)
        return self._rest

    def geometry(self, pose=None) -> SceneGeometry:
        """Merged geometry, skinned by `pose` (J,) if the scene has a skeleton (rest pose if None)."""
        g = self.rest_geometry()
        if pose is None:
            return g
        if self.skeleton is None:
            raise ValueError(f"scene {self.name!r} has no skeleton; pose must be None")
        T = self.skeleton.forward_kinematics(torch.as_tensor(pose, dtype=torch.float32))
        V, N = g.V.clone(), g.N.clone()
        for i, s in enumerate(self.shapes):
            if s.name not in self.skin_weights:
                continue
            a, b = int(g.vertex_offset[i]), int(g.vertex_offset[i + 1])
            # the weights were validated when the scene was built (`check_weights`, __post_init__)
            V[a:b], N[a:b] = blend_skin(g.V[a:b], g.N[a:b], self.skin_weights[s.name], T)
        return SceneGeometry(V, g.F, N, g.uv, g.vertex_region, g.face_region, g.face_offset, g.vertex_offset,
                             g.shape_names)

    def default_frame(self, pose=None):
        """The scene's own frame (its env map, camera, materials; rest pose)."""
        return Frame(envmap=self.envmap, camera=self.camera, materials=dict(self.materials), pose=pose)

    def content_hash(self) -> str:
        """sha256 over rest geometry bytes, regions, materials, env map data, camera, skeleton/skin."""
        g = self.rest_geometry()
        parts = {
            "geometry": [hash_tensor(t) for t in (g.V, g.F, g.N, g.vertex_region, g.face_offset, g.vertex_offset)]
                        + [None if g.uv is None else hash_tensor(g.uv)],
            "shapes": [[s.name, s.region] for s in self.shapes],
            "regions": self.regions,
            "materials": hash_materials(self.materials),
            "envmap": hash_envmap(self.envmap),
            "camera": self.camera.params(),
            "skeleton": None if self.skeleton is None else hash_params(self.skeleton.params()),
            "skin": None if self.skin_weights is None else {k: hash_tensor(v) for k, v in sorted(self.skin_weights.items())},
        }
        if self.animation is not None:  # (absent key: hashes of scenes without a clip are unchanged)
            parts["animation"] = hash_tensor(self.animation)
        return hash_params(parts)

    def replace(self, **changes) -> "Scene":
        """A copy with some constructor fields changed (geometry cache dropped)."""
        kw = dict(name=self.name, shapes=self.shapes, regions=self.regions, camera=self.camera, envmap=self.envmap,
                  materials=self.materials, skeleton=self.skeleton, skin_weights=self.skin_weights, size=self.size,
                  animation=self.animation)
        kw.update(changes)
        return Scene(**kw)


# Sub-samples per pixel side of the coverage test (= references.render's default coverage S).
COVERAGE_S = 2
# Pixels of the coarse grid `covered_pixels` tests on a large film (per side).
COVERAGE_GRID = 64
# Largest projected-bounding-box region `covered_pixels` tests pixel by pixel.
COVERAGE_REGION_PIXELS = 4096


def covered_pixels(scene: "Scene", camera=None, *, S: int = COVERAGE_S) -> int:
    """How many of the tested pixels of ``camera`` (default the scene's) are fully covered by the
    rest geometry: all S×S sub-sample rays (``Camera.pixel_rays``' pattern) hit a triangle — the
    coverage mask the references score on. 0 means the camera sees no geometry.

    Cheap: it tests a coarse grid of at most `COVERAGE_GRID`² pixels over the film plus every pixel
    of the film-space bounding box of the vertices in front of the camera when that box holds at
    most `COVERAGE_REGION_PIXELS` pixels (the case of geometry seen as a few pixels), with Embree.
    """
    import math

    import numpy as np

    from methods.core.visibility import Visibility

    cam = camera if camera is not None else scene.camera
    W, H = cam.width, cam.height
    g = scene.rest_geometry()
    step = max(1, math.ceil(max(W, H) / COVERAGE_GRID))
    jj, ii = np.meshgrid(np.arange(0, H, step), np.arange(0, W, step), indexing="ij")
    pix = [np.stack([ii.reshape(-1), jj.reshape(-1)], 1)]
    # film positions of the vertices in front of the camera (Camera.rays inverted)
    loc = (g.V.double().numpy() - np.asarray(cam.origin)) @ cam.axes()
    loc = loc[loc[:, 2] > cam.near_clip]
    if len(loc):
        tx = math.tan(math.radians(cam.fov_deg) / 2)
        ty = tx / cam.aspect
        fx = (1 - loc[:, 0] / (loc[:, 2] * tx)) / 2 * W
        fy = (1 - loc[:, 1] / (loc[:, 2] * ty)) / 2 * H
        x0, x1 = int(np.clip(np.floor(fx.min()) - 1, 0, W)), int(np.clip(np.ceil(fx.max()) + 1, 0, W))
        y0, y1 = int(np.clip(np.floor(fy.min()) - 1, 0, H)), int(np.clip(np.ceil(fy.max()) + 1, 0, H))
        if 0 < (x1 - x0) * (y1 - y0) <= COVERAGE_REGION_PIXELS:
            jj, ii = np.meshgrid(np.arange(y0, y1), np.arange(x0, x1), indexing="ij")
            pix.append(np.stack([ii.reshape(-1), jj.reshape(-1)], 1))
    pix = np.unique(np.concatenate(pix), axis=0)  # (P, 2) pixel (i, j)
    s = (np.arange(S) + 0.5) / S
    sub = np.stack(np.meshgrid(s, s, indexing="xy"), -1).reshape(-1, 2)  # (S², 2) (x, y) offsets
    px = (pix[:, None, :] + sub[None]).reshape(-1, 2)
    o, d = cam.rays(torch.as_tensor(px, dtype=torch.float64))
    hit = Visibility(g.V, g.F, threads=1).occluded(o.float(), d.float())
    hit = np.asarray(hit).reshape(len(pix), S * S)
    return int(hit.all(1).sum())


def _merge(shapes: list[Shape], regions: list[str]) -> SceneGeometry:
    Vs, Fs, Ns, uvs, vr, fr = [], [], [], [], [], []
    voff, foff = [0], [0]
    for s in shapes:
        m = s.mesh
        r = regions.index(s.region)
        Vs.append(m.V)
        Fs.append(m.F + voff[-1])
        Ns.append(m.N)
        uvs.append(m.uv)
        vr.append(torch.full((m.num_vertices,), r, dtype=torch.int64))
        fr.append(torch.full((m.num_faces,), r, dtype=torch.int64))
        voff.append(voff[-1] + m.num_vertices)
        foff.append(foff[-1] + m.num_faces)
    uv = torch.cat(uvs) if all(u is not None for u in uvs) else None
    return SceneGeometry(
        V=torch.cat(Vs).float().contiguous(), F=torch.cat(Fs).contiguous(), N=torch.cat(Ns).float().contiguous(), uv=uv,
        vertex_region=torch.cat(vr), face_region=torch.cat(fr),
        face_offset=torch.tensor(foff, dtype=torch.int64), vertex_offset=torch.tensor(voff, dtype=torch.int64),
        shape_names=tuple(s.name for s in shapes),
    )
