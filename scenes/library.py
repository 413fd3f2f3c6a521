"""The named benchmark scenes, at two sizes.

size "test": ≤ 2K vertices, 64×64 film, env maps of height 64 (unit tests, CI).
size "bench": 5–20K vertices, 256×256 film, env maps of height 256 (nightly benchmark).

Real-asset scenes (`bunny`, `dragon`: scans; `character`: a skinned glTF human): vendored files
under scenes/assets/ (sources and licences in scenes/assets/ASSETS.md) under captured light
probes (`scenes.envmap.PROBE_NAMES`). The vendored mesh is the bench-size object; the test size is
produced at load time by quadric decimation (VTK via pyvista: `decimate`, `decimate_skinned`) to
TEST_SCAN_VERTICES.

Light placement: the procedural env maps put their key light (sun, window, key softbox) at a
seeded azimuth; each scene rotates its env map about +Y so the key light shines from a chosen
azimuth relative to the camera (shadows fall visibly in front of the camera).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from scenes import procedural as P
from scenes.camera import Camera
from scenes.scene import Scene, Shape

SCENES = ["sphere_plane", "chess", "alcove", "shadow_detail", "creature", "bunny", "dragon", "character"]
SIZES = {"test": dict(film=64, env=64), "bench": dict(film=256, env=256)}
ASSET_DIR = Path(__file__).resolve().parent / "assets"
# Vertex budget of a scanned object at test size (the ground adds 441 vertices: ≤ 2K in all).
TEST_SCAN_VERTICES = 1400


def _check_size(size: str) -> dict:
    if size not in SIZES:
        raise ValueError(f"size must be one of {list(SIZES)}, got {size!r}")
    return SIZES[size]


def rotation_y(angle_rad: float) -> np.ndarray:
    """(3, 3) rotation about +Y by `angle_rad` (right-hand rule)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def key_light_direction(env) -> np.ndarray:
    """World direction (3,) of the brightest texel (by luminance × solid angle) of an EnvMap."""
    from scenes.envmap import texel_directions

    H, W = env.height, env.width
    lum = (env.data.double() @ torch.tensor([0.2126, 0.7152, 0.0722], dtype=torch.float64))
    sin_theta = torch.sin(torch.linspace(0, math.pi, H, dtype=torch.float64))[:, None]
    i = int(torch.argmax(lum * sin_theta))
    d = texel_directions(H, W)[i // W, i % W]
    R = env.to_world.double()
    return (R @ d).numpy()


def aim_key_light(env, azimuth_deg: float):
    """Rotate `env` about +Y so its key light lies at world azimuth `azimuth_deg`.

    Azimuth convention of the env-map (docs/ARCHITECTURE.md): a direction at azimuth φ is
    (sin φ, ·, −cos φ), i.e. φ = 0 looks towards −Z, φ = 90° towards +X.
    """
    d = key_light_direction(env)
    a = math.atan2(d[0], -d[2])
    # R_y(α) maps azimuth a to a − α
    return env.rotated(torch.as_tensor(rotation_y(a - math.radians(azimuth_deg)), dtype=torch.float32))


def _env(name: str, size: str, azimuth_deg: float | None, seed: int = 0):
    from scenes.envmap import named

    env = named(name, height=SIZES[size]["env"], seed=seed)
    return env if azimuth_deg is None else aim_key_light(env, azimuth_deg)


def graded_plane(half_size: float, n: int, *, y: float = 0.0, k: float = 8.0, center=(0.0, 0.0)) -> "P.Mesh":
    """Horizontal plane facing +Y, n×n cells, fine near `center` and coarse far away.

    Grid coordinate x(t) = half_size·(t + k t³)/(1 + k), t ∈ [−1, 1] uniform: the centre cells are
    (1 + 3k)× smaller than the border cells, so shadows near the objects get enough vertices while
    the plane still fills the background.
    """
    m = P.plane((2.0, 2.0), (n, n))
    V = m.V.double().clone()
    g = lambda t: half_size * (t + k * t**3) / (1 + k)  # noqa: E731
    V[:, 0] = g(V[:, 0]) + center[0]
    V[:, 2] = g(V[:, 2]) + center[1]
    V[:, 1] = y
    return P.Mesh(V.float(), m.F, m.N, m.uv).validate()


def decimate(mesh: "P.Mesh", max_vertices: int) -> "P.Mesh":
    """Quadric-error decimation (VTK `vtkQuadricDecimation` via pyvista, volume preserving) of a
    triangle mesh to at most `max_vertices` vertices; deterministic. Returns the mesh unchanged
    if it is already within budget; normals are recomputed (area-weighted) and the result is
    validated. `mesh`: Mesh with V (N, 3), F (M, 3)."""
    import pyvista as pv

    from scenes.mesh import Mesh

    max_vertices = int(max_vertices)
    if max_vertices < 4:
        raise ValueError(f"max_vertices must be >= 4, got {max_vertices}")
    if mesh.num_vertices <= max_vertices:
        return mesh
    pd = pv.PolyData.from_regular_faces(mesh.V.double().numpy(), mesh.F.numpy())
    target = max_vertices
    for _ in range(20):  # a closed mesh has ~2 faces per vertex; shrink the target until it fits
        d = pd.decimate(1.0 - 2.0 * target / pd.n_cells, volume_preservation=True)
        if d.n_points <= max_vertices:
            break
        target -= max(1, (d.n_points - max_vertices))
    else:
        raise ValueError(f"decimation could not reach {max_vertices} vertices")
    F = torch.as_tensor(np.asarray(d.regular_faces, dtype=np.int64))
    V = torch.as_tensor(np.asarray(d.points, dtype=np.float64))
    # drop faces decimation collapsed to zero area, then unreferenced vertices
    c = torch.linalg.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    F = F[c.norm(dim=1) > 1e-12 * float(((V.max(0).values - V.min(0).values) ** 2).sum())]
    used = torch.unique(F)
    remap = torch.full((V.shape[0],), -1, dtype=torch.int64)
    remap[used] = torch.arange(used.numel())
    return Mesh(V[used].float(), remap[F]).validate()


def decimate_skinned(mesh: "P.Mesh", weights: torch.Tensor, max_vertices: int) -> tuple["P.Mesh", torch.Tensor]:
    """`decimate` a skinned mesh and carry its skin weights over: each new vertex takes the
    barycentric interpolation of the weights of the original triangle closest to it (VTK cell
    locator), rows renormalised. weights: (N, J) → returns (Mesh, (N', J) float32)."""
    import pyvista as pv

    W = torch.as_tensor(weights, dtype=torch.float64)
    if W.dim() != 2 or W.shape[0] != mesh.num_vertices:
        raise ValueError(f"weights must be ({mesh.num_vertices}, J), got {tuple(W.shape)}")
    d = decimate(mesh, max_vertices)
    if d is mesh:
        return mesh, W.float()
    pd = pv.PolyData.from_regular_faces(mesh.V.double().numpy(), mesh.F.numpy())
    cells, pts = pd.find_closest_cell(d.V.double().numpy(), return_closest_point=True)
    tri = mesh.F[torch.as_tensor(cells, dtype=torch.int64)]                 # (N', 3)
    a, b, c = (mesh.V.double()[tri[:, k]] for k in range(3))
    p = torch.as_tensor(np.asarray(pts, dtype=np.float64))
    v0, v1, v2 = b - a, c - a, p - a                                         # barycentric coordinates
    d00, d01, d11 = (v0 * v0).sum(1), (v0 * v1).sum(1), (v1 * v1).sum(1)
    d20, d21 = (v2 * v0).sum(1), (v2 * v1).sum(1)
    den = (d00 * d11 - d01 * d01).clamp_min(1e-300)
    l1, l2 = (d11 * d20 - d01 * d21) / den, (d00 * d21 - d01 * d20) / den
    bary = torch.stack([1 - l1 - l2, l1, l2], 1).clamp_min(0.0)
    bary = bary / bary.sum(1, keepdim=True)
    Wn = (bary[:, :, None] * W[tri]).sum(1)
    return d, (Wn / Wn.sum(1, keepdim=True)).float()


_SCANS: dict[tuple[str, int | None], "P.Mesh"] = {}


def scanned_mesh(name: str, *, height: float, max_vertices: int | None = None) -> "P.Mesh":
    """A vendored scan (scenes/assets/meshes/<name>.ply, +Y up as stored) scaled to `height`,
    centred on the Y axis and resting on y = 0 (lifted by 0.2 % of its height so its base is not
    coplanar with a ground plane); decimated to `max_vertices` first if given."""
    from scenes.mesh import load_mesh

    key = (name, max_vertices)
    if key not in _SCANS:
        m = load_mesh(ASSET_DIR / "meshes" / f"{name}.ply")
        _SCANS[key] = m if max_vertices is None else decimate(m, max_vertices)
    m = _SCANS[key]
    lo, hi = m.V.double().min(0).values, m.V.double().max(0).values
    s = height / float(hi[1] - lo[1])
    c = 0.5 * (lo + hi)
    M = torch.eye(4, dtype=torch.float64) * s
    M[3, 3] = 1.0
    M[:3, 3] = torch.stack([-s * c[0], -s * lo[1] + 0.002 * height, -s * c[2]])
    return P.Mesh(m.V, m.F, None, m.uv).transformed(M).validate()


# -- scenes --------------------------------------------------------------------------------------


def sphere_plane(size: str = "test") -> Scene:
    """Glossy Phong sphere (s = 40) on a diffuse plane under `sky_sun`."""
    from scenes.materials import Lambert, Phong

    q = _check_size(size)
    sub, n = (3, 24) if size == "test" else (5, 80)
    shapes = [Shape("sphere", "sphere", P.icosphere(sub, 1.0, (0.0, 1.0, 0.0))),
              Shape("plane", "plane", graded_plane(40.0, n))]
    cam = Camera((0.0, 3.2, 4.2), (0.0, 0.8, 0.0), (0.0, 1.0, 0.0), 40.0, q["film"], q["film"])
    mats = {"sphere": Phong(kd=(0.35, 0.12, 0.08), ks=(0.45, 0.45, 0.45), s=40.0),
            "plane": Lambert(kd=(0.6, 0.6, 0.55))}
    return Scene("sphere_plane", shapes, ["sphere", "plane"], cam, _env("sky_sun", size, -140.0), mats, size=size)


def chess(size: str = "test") -> Scene:
    """Lathe chess pieces on a board; regions white, black, board under `studio`."""
    from scenes.materials import BlinnPhong, CookTorrance, Phong

    q = _check_size(size)
    seg, det, n = (12, 4, 15) if size == "test" else (40, 12, 60)
    pieces = [("white", "king", (-0.5, -0.3)), ("white", "rook", (-1.1, 0.5)), ("white", "pawn", (0.1, 0.6)),
              ("black", "bishop", (0.6, -0.5)), ("black", "pawn", (1.1, 0.3)), ("black", "rook", (0.0, -1.1))]
    shapes = []
    for i, (col, kind, (x, z)) in enumerate(pieces):
        shapes.append(Shape(f"{col}_{kind}_{i}", col, P.chess_piece(kind, n_seg=seg, detail=det, center=(x, 0.0, z))))
    shapes.append(Shape("board", "board", graded_plane(25.0, n, k=6.0)))
    cam = Camera((0.0, 2.6, 3.4), (0.0, 0.35, 0.0), (0.0, 1.0, 0.0), 42.0, q["film"], q["film"])
    mats = {"white": BlinnPhong(kd=(0.7, 0.68, 0.62), ks=(0.25, 0.25, 0.25), s=60.0),
            "black": CookTorrance(kd=(0.06, 0.05, 0.05), ks=(0.6, 0.6, 0.6), m=0.25, F0=0.04),
            "board": Phong(kd=(0.45, 0.3, 0.18), ks=(0.1, 0.1, 0.1), s=10.0)}
    return Scene("chess", shapes, ["white", "black", "board"], cam, _env("studio", size, -150.0), mats, size=size)


def vase(n_seg: int, detail: int) -> "P.Mesh":
    """A lathe vase ~1.1 high standing on y = 0."""
    t = np.linspace(0.0, 1.0, 4 * detail)
    r = 0.28 + 0.17 * np.sin(np.pi * 1.3 * t) - 0.1 * t
    y = 0.04 + 1.05 * t
    prof = [(0.0, 0.0), (0.25, 0.0), (0.28, 0.04)] + list(zip(r[1:], y[1:])) + [(0.22, 1.09), (0.0, 1.09)]
    return P.lathe(P._clean(prof), n_seg)


def alcove(size: str = "test") -> Scene:
    """A glossy vase in a three-walled niche (diffuse walls and floor) under `overcast`."""
    from scenes.materials import Lambert, Phong

    q = _check_size(size)
    n, seg, det = (12, 16, 4) if size == "test" else (40, 48, 12)
    walls = P.niche(width=3.0, height=2.6, depth=2.2, center=(0.0, 0.0, 0.0), n=n)
    obj = P._affine(vase(seg, det), translate=(0.1, 0.0, -0.2))
    shapes = [Shape("walls", "walls", walls), Shape("vase", "object", obj)]
    cam = Camera((0.0, 1.2, 3.0), (0.0, 0.8, -0.5), (0.0, 1.0, 0.0), 36.0, q["film"], q["film"])
    mats = {"walls": Lambert(kd=(0.7, 0.68, 0.64)), "object": Phong(kd=(0.1, 0.25, 0.45), ks=(0.4, 0.4, 0.4), s=30.0)}
    return Scene("alcove", shapes, ["walls", "object"], cam, _env("overcast", size, None), mats, size=size)


def shadow_detail(size: str = "test") -> Scene:
    """A (2, 3) torus knot hovering over a plane under `window` (fine self- and cast shadows)."""
    from scenes.materials import Lambert, Phong

    q = _check_size(size)
    nu, nv, n = (96, 10, 20) if size == "test" else (384, 20, 60)
    knot = P.torus_knot(2, 3, n_u=nu, n_v=nv, R=1.0, r_tube=0.22, center=(0.0, 1.0, 0.0), scale=0.9)
    shapes = [Shape("knot", "object", knot), Shape("ground", "ground", graded_plane(30.0, n))]
    cam = Camera((0.0, 3.6, 3.6), (0.0, 0.7, 0.0), (0.0, 1.0, 0.0), 45.0, q["film"], q["film"])
    mats = {"object": Phong(kd=(0.55, 0.5, 0.45), ks=(0.2, 0.2, 0.2), s=20.0), "ground": Lambert(kd=(0.6, 0.6, 0.6))}
    return Scene("shadow_detail", shapes, ["object", "ground"], cam, _env("window", size, -120.0), mats, size=size)


def creature(size: str = "test") -> Scene:
    """The skinned four-legged creature (rest pose) on a ground plane under `sky_sun`."""
    from scenes.materials import Lambert, Phong
    from scenes.skeleton import make_creature

    q = _check_size(size)
    mesh, skel, W = make_creature(size)
    n = 20 if size == "test" else 60
    shapes = [Shape("creature", "creature", mesh), Shape("ground", "ground", graded_plane(40.0, n))]
    cam = Camera((1.0, 3.4, 4.2), (0.2, 1.0, 0.0), (0.0, 1.0, 0.0), 45.0, q["film"], q["film"])
    mats = {"creature": Phong(kd=(0.5, 0.35, 0.2), ks=(0.15, 0.15, 0.15), s=12.0), "ground": Lambert(kd=(0.5, 0.55, 0.45))}
    return Scene("creature", shapes, ["creature", "ground"], cam, _env("sky_sun", size, -160.0), mats,
                 skeleton=skel, skin_weights={"creature": W}, size=size)


def bunny(size: str = "test") -> Scene:
    """The Stanford bunny (scan) in glossy Phong on a diffuse ground under the `sunrise` probe."""
    from scenes.materials import Lambert, Phong

    q = _check_size(size)
    obj = scanned_mesh("bunny", height=1.5, max_vertices=TEST_SCAN_VERTICES if size == "test" else None)
    n = 20 if size == "test" else 60
    shapes = [Shape("bunny", "bunny", obj), Shape("ground", "ground", graded_plane(30.0, n))]
    cam = Camera((0.6, 2.4, 4.0), (0.0, 0.65, 0.0), (0.0, 1.0, 0.0), 38.0, q["film"], q["film"])
    mats = {"bunny": Phong(kd=(0.55, 0.42, 0.3), ks=(0.3, 0.3, 0.3), s=40.0), "ground": Lambert(kd=(0.5, 0.5, 0.48))}
    return Scene("bunny", shapes, ["bunny", "ground"], cam, _env("sunrise", size, -150.0), mats, size=size)


def dragon(size: str = "test") -> Scene:
    """The Stanford dragon (scan) in Blinn-Phong on a diffuse ground under the `forest` probe."""
    from scenes.materials import BlinnPhong, Lambert

    q = _check_size(size)
    obj = scanned_mesh("dragon", height=1.4, max_vertices=TEST_SCAN_VERTICES if size == "test" else None)
    n = 20 if size == "test" else 60
    shapes = [Shape("dragon", "dragon", obj), Shape("ground", "ground", graded_plane(30.0, n))]
    cam = Camera((0.0, 1.9, 3.3), (0.0, 0.55, 0.0), (0.0, 1.0, 0.0), 40.0, q["film"], q["film"])
    mats = {"dragon": BlinnPhong(kd=(0.15, 0.4, 0.25), ks=(0.35, 0.35, 0.35), s=80.0),
            "ground": Lambert(kd=(0.45, 0.42, 0.38))}
    return Scene("dragon", shapes, ["dragon", "ground"], cam, _env("forest", size, -140.0), mats, size=size)


_RIGS: dict[str, tuple] = {}


def character_rig(size: str = "test"):
    """The vendored skinned character (scenes/assets/characters/bcn_epileptic.glb) standing on y = 0,
    centred on the Y axis: (mesh, skeleton, weights (N, J), clip joint angles (F, J), times (F,)).
    At test size the mesh is decimated to TEST_SCAN_VERTICES with its weights carried over.
    Memoised: treat the returned objects as read-only."""
    _check_size(size)
    if size not in _RIGS:
        _RIGS[size] = _character_rig(size)
    return _RIGS[size]


def _character_rig(size: str):
    from scenes.gltf import load_skinned_glb_rig
    from scenes.skeleton import Skeleton

    mesh, rig = load_skinned_glb_rig(ASSET_DIR / "characters" / "bcn_epileptic.glb")
    W = rig.weights
    if size == "test":
        mesh, W = decimate_skinned(mesh, W, TEST_SCAN_VERTICES)
    lo, hi = mesh.V.double().min(0).values, mesh.V.double().max(0).values
    t = torch.stack([-0.5 * (lo[0] + hi[0]), -lo[1] + 0.002 * (hi[1] - lo[1]), -0.5 * (lo[2] + hi[2])])
    M = torch.eye(4, dtype=torch.float64)
    M[:3, 3] = t
    sk = rig.skeleton
    skel = Skeleton(sk.parents, sk.joint_positions.double() + t, sk.axes, names=sk.names, limits=sk.limits)
    return mesh.transformed(M).validate(), skel, W, rig.animation, rig.times


def character(size: str = "test") -> Scene:
    """The skinned human (rest pose) in Phong on a diffuse ground under the `courtyard` probe."""
    from scenes.materials import Lambert, Phong

    q = _check_size(size)
    mesh, skel, W, clip, _ = character_rig(size)
    n = 20 if size == "test" else 60
    shapes = [Shape("character", "character", mesh), Shape("ground", "ground", graded_plane(30.0, n))]
    cam = Camera((0.7, 1.5, 3.0), (0.0, 0.85, 0.0), (0.0, 1.0, 0.0), 40.0, q["film"], q["film"])
    mats = {"character": Phong(kd=(0.45, 0.3, 0.22), ks=(0.2, 0.2, 0.2), s=25.0), "ground": Lambert(kd=(0.5, 0.5, 0.5))}
    return Scene("character", shapes, ["character", "ground"], cam, _env("courtyard", size, -140.0), mats,
                 skeleton=skel, skin_weights={"character": W}, size=size, animation=clip)


_BUILDERS = {"sphere_plane": sphere_plane, "chess": chess, "alcove": alcove, "shadow_detail": shadow_detail,
             "creature": creature, "bunny": bunny, "dragon": dragon, "character": character}
_CACHE: dict[tuple[str, str], Scene] = {}


def get_scene(name: str, size: str = "test") -> Scene:
    """Build (and memoise) a named scene. Unknown name → KeyError listing `SCENES`.

    The returned Scene is shared between callers: treat it as read-only (use `scene.replace`).
    """
    if name not in _BUILDERS:
        raise KeyError(f"unknown scene {name!r}; available: {', '.join(SCENES)}")
    _check_size(size)
    key = (name, size)
    if key not in _CACHE:
        _CACHE[key] = _BUILDERS[name](size)
    return _CACHE[key]
