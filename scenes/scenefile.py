"""TOML scene files: bring your own mesh(es), env map and materials.

`load_scene_file(path, size=None)` reads a TOML file (stdlib `tomllib`) and returns a
`scenes.scene.Scene` built the same way as the library scenes (`scenes/library.py`). With a
``size`` ("test" | "bench", what the harness passes from the suite) the scene gets that size like a
library scene: meshes are decimated (VTK quadric decimation, `library.decimate`) so the whole scene
holds at most ``VERTEX_BUDGET[size]`` vertices (test 2 000, bench 20 000; small meshes stay whole,
the large ones share the rest in proportion to their vertex counts; a line on stderr says so), the film's larger
side becomes the size's (64 / 256 px, aspect kept) and a procedural or probe env map gets the
size's height unless the file sets one. Without ``size`` the file is taken as written. Format::

    name = "my_scene"                 # optional; default: the file's stem

    [camera]                          # required
    origin = [0.0, 2.0, 4.0]          # required, 3 numbers
    target = [0.0, 0.5, 0.0]          # required, 3 numbers
    up = [0.0, 1.0, 0.0]              # optional, default +Y
    fov_deg = 40.0                    # required, horizontal field of view in (0, 180)
    width = 64                        # required, film pixels (positive integer)
    height = 64                       # required

    [envmap]                          # required; exactly one of `file` / `procedural` / `probe`
    procedural = "sky_sun"            # sky_sun | studio | window | overcast
    # probe = "courtyard"             # a vendored captured probe: courtyard | forest | interior | sunrise
    height = 64                       # procedural / probe only (default 64); width = 2·height
    seed = 0                          # procedural only (default 0)
    # file = "env.exr"                # .exr or .hdr lat-long map, relative to the TOML file
    rotate_y_deg = 30.0               # optional: rotate the map about +Y (right-hand rule)
    # key_azimuth_deg = -140.0        # optional (instead of rotate_y_deg): rotate so the
                                      # brightest texel lies at this world azimuth
                                      # (library.aim_key_light convention)

    [[shape]]                         # one or more; order = shape order of the scene
    name = "box"                      # required, unique
    region = "red"                    # required: the material region of the whole mesh
    mesh = "box.obj"                  # required: .obj | .ply | .glb | .gltf, relative to the TOML file
    scale = 0.5                       # optional: a positive number or 3 positive numbers
    rotate = [-90.0, 0.0, 0.0]        # optional: Euler degrees about x, then y, then z (after scale;
                                      # e.g. a Z-up scan becomes +Y up with [-90, 0, 0])
    translate = [0.0, 0.5, 0.0]       # optional: 3 numbers (applied last)
    subdivide = 2                     # optional: rounds of midpoint 1-to-4 subdivision (0-6) before
                                      # the transform; every method here stores transport per vertex,
                                      # so a shadow or highlight inside one big face is lost without it
    skeleton = true                   # optional, .glb/.gltf only: keep the file's skin and its first
                                      # animation clip (default: true when the file is skinned). The
                                      # clip drives the scene's P sequences and the pose models.

    [materials.red]                   # one table per region used by a shape (and no others)
    kind = "phong"                    # lambert | phong | blinnphong | cooktorrance | torrancesparrow | ward
    kd = [0.5, 0.1, 0.1]              # RGB triple or scalar, ≥ 0
    ks = [0.3, 0.3, 0.3]
    s = 30                            # the kind's other parameters (see scenes/materials.py)

Regions are ordered by first use in `[[shape]]`. Every error (TOML syntax, unknown or missing
key, wrong type, unknown material kind, out-of-range parameter, missing/corrupt mesh or env-map
file) raises ONE `ValueError` whose message starts with the file name and names the key, e.g.
``"scene.toml: [materials.sphere] kind 'foo' unknown; one of blinnphong, ..."``.
"""
from __future__ import annotations

import dataclasses
import math
import sys
import tomllib
from pathlib import Path
from typing import Any

import torch

from scenes.library import SIZES
from scenes.scene import Scene

TOP_KEYS = ("name", "camera", "envmap", "shape", "materials")
CAMERA_REQUIRED = ("origin", "target", "fov_deg", "width", "height")
CAMERA_KEYS = CAMERA_REQUIRED + ("up",)
ENVMAP_KEYS = ("file", "procedural", "probe", "height", "seed", "rotate_y_deg", "key_azimuth_deg")
SHAPE_REQUIRED = ("name", "region", "mesh")
SHAPE_KEYS = SHAPE_REQUIRED + ("scale", "rotate", "translate", "skeleton", "subdivide")
# Most midpoint-subdivision levels a shape may ask for (4^6 = 4096 faces per input face).
MAX_SUBDIVIDE = 6
# Vertex budget of a whole scene per size (scenes/library.py's test / bench sizes).
VERTEX_BUDGET = {"test": 2000, "bench": 20000}
DEFAULT_ENV_HEIGHT = 64  # the "test" size of scenes/library.py


class _Ctx:
    """Error prefixing: every message starts with the TOML file name."""

    def __init__(self, path: Path) -> None:
        self.path = path

    def error(self, where: str, msg: str) -> ValueError:
        return ValueError(f"{self.path.name}: {where} {msg}".replace("  ", " "))


def _is_number(x: Any) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _check_keys(ctx: _Ctx, where: str, table: Any, allowed, required=()) -> dict:
    if not isinstance(table, dict):
        raise ctx.error(where, f"must be a table, got {type(table).__name__}")
    unknown = [k for k in table if k not in allowed]
    if unknown:
        raise ctx.error(where, f"unknown key(s) {', '.join(map(repr, unknown))}; allowed: {', '.join(allowed)}")
    missing = [k for k in required if k not in table]
    if missing:
        raise ctx.error(where, f"missing required key(s) {', '.join(map(repr, missing))}")
    return table


def _number(ctx: _Ctx, where: str, key: str, x: Any) -> float:
    if not _is_number(x) or not math.isfinite(float(x)):
        raise ctx.error(where, f"{key} must be a finite number, got {x!r}")
    return float(x)


def _integer(ctx: _Ctx, where: str, key: str, x: Any, lo: int = 1) -> int:
    if not isinstance(x, int) or isinstance(x, bool) or x < lo:
        raise ctx.error(where, f"{key} must be an integer >= {lo}, got {x!r}")
    return int(x)


def _vec3(ctx: _Ctx, where: str, key: str, x: Any) -> tuple[float, float, float]:
    if not isinstance(x, list) or len(x) != 3 or not all(_is_number(v) and math.isfinite(v) for v in x):
        raise ctx.error(where, f"{key} must be a list of 3 finite numbers, got {x!r}")
    return tuple(float(v) for v in x)  # type: ignore[return-value]


def _string(ctx: _Ctx, where: str, key: str, x: Any) -> str:
    if not isinstance(x, str) or not x:
        raise ctx.error(where, f"{key} must be a non-empty string, got {x!r}")
    return x


# -- sections ------------------------------------------------------------------------------------


def _camera(ctx: _Ctx, t: Any):
    from scenes.camera import Camera

    w = "[camera]"
    t = _check_keys(ctx, w, t, CAMERA_KEYS, CAMERA_REQUIRED)
    origin = _vec3(ctx, w, "origin", t["origin"])
    target = _vec3(ctx, w, "target", t["target"])
    up = _vec3(ctx, w, "up", t.get("up", [0.0, 1.0, 0.0]))
    fov = _number(ctx, w, "fov_deg", t["fov_deg"])
    if not 0.0 < fov < 180.0:
        raise ctx.error(w, f"fov_deg must be in (0, 180), got {fov!r}")
    width = _integer(ctx, w, "width", t["width"])
    height = _integer(ctx, w, "height", t["height"])
    try:
        return Camera(origin, target, up, fov, width, height)
    except ValueError as e:  # degenerate geometry (origin == target, up ∥ view)
        raise ctx.error(w, str(e)) from e


def _envmap(ctx: _Ctx, t: Any, env_height: int = DEFAULT_ENV_HEIGHT):
    from scenes.envmap import (PROBE_NAMES, PROCEDURAL_NAMES, EnvMap, TooLarge, check_lit, check_size, probe, procedural,
                               read_image)
    from scenes.library import aim_key_light, rotation_y

    w = "[envmap]"
    t = _check_keys(ctx, w, t, ENVMAP_KEYS)
    if sum(k in t for k in ("file", "procedural", "probe")) != 1:
        raise ctx.error(w, "needs exactly one of 'file', 'procedural' or 'probe'")
    if "rotate_y_deg" in t and "key_azimuth_deg" in t:
        raise ctx.error(w, "give at most one of 'rotate_y_deg' and 'key_azimuth_deg'")
    if "file" in t:
        for k in ("height", "seed"):
            if k in t:
                raise ctx.error(w, f"{k} is only valid with 'procedural' or 'probe'")
        rel = _string(ctx, w, "file", t["file"])
        p = ctx.path.parent / rel
        if not p.is_file():
            raise ctx.error(w, f"file {rel!r} not found (looked for {p})")
        if p.suffix.lower() not in (".exr", ".hdr"):
            raise ctx.error(w, f"file {rel!r} must be .exr or .hdr")
        try:
            data = read_image(p)
        except TooLarge as e:
            raise ctx.error(w, f"file {rel!r}: {e}") from e
        except Exception as e:  # OpenEXR / RGBE readers raise many types on corrupt files
            raise ctx.error(w, f"file {rel!r} cannot be read: {e}") from e
        try:
            env = check_lit(EnvMap(data), "env map")
        except ValueError as e:
            raise ctx.error(w, f"file {rel!r}: {e}") from e
    elif "probe" in t:
        name = _string(ctx, w, "probe", t["probe"])
        if name not in PROBE_NAMES:
            raise ctx.error(w, f"probe {name!r} unknown; one of {', '.join(PROBE_NAMES)}")
        if "seed" in t:
            raise ctx.error(w, "seed is only valid with 'procedural'")
        height = _integer(ctx, w, "height", t.get("height", env_height), lo=3)
        try:
            env = probe(name, height=height)
        except ValueError as e:
            raise ctx.error(w, f"height: {e}") from e
    else:
        name = _string(ctx, w, "procedural", t["procedural"])
        if name not in PROCEDURAL_NAMES:
            raise ctx.error(w, f"procedural {name!r} unknown; one of {', '.join(PROCEDURAL_NAMES)}")
        height = _integer(ctx, w, "height", t.get("height", env_height), lo=3)
        seed = _integer(ctx, w, "seed", t.get("seed", 0), lo=0)
        try:
            check_size(height, 2 * height, "height: procedural map")  # before allocating it
        except ValueError as e:
            raise ctx.error(w, str(e)) from e
        env = procedural(name, height=height, seed=seed)
    if "rotate_y_deg" in t:
        a = math.radians(_number(ctx, w, "rotate_y_deg", t["rotate_y_deg"]))
        env = env.rotated(torch.as_tensor(rotation_y(a), dtype=torch.float32))
    if "key_azimuth_deg" in t:
        env = aim_key_light(env, _number(ctx, w, "key_azimuth_deg", t["key_azimuth_deg"]))
    return env


def _shape(ctx: _Ctx, i: int, t: Any):
    from scenes.mesh import check_extent, load_mesh, subdivide
    from scenes.scene import Shape

    w = f"[[shape]] #{i}"
    if isinstance(t, dict) and isinstance(t.get("name"), str):
        w = f"[[shape]] #{i} ({t['name']!r})"
    t = _check_keys(ctx, w, t, SHAPE_KEYS, SHAPE_REQUIRED)
    name = _string(ctx, w, "name", t["name"])
    region = _string(ctx, w, "region", t["region"])
    mesh_rel = _string(ctx, w, "mesh", t["mesh"])
    mesh_path = ctx.path.parent / mesh_rel
    if "scale" in t:
        s = t["scale"]
        scale = (_number(ctx, w, "scale", s),) * 3 if _is_number(s) else _vec3(ctx, w, "scale", s)
        if min(scale) <= 0:
            raise ctx.error(w, f"scale must be > 0, got {s!r}")
    else:
        scale = (1.0, 1.0, 1.0)
    translate = _vec3(ctx, w, "translate", t.get("translate", [0.0, 0.0, 0.0]))
    rotate = _vec3(ctx, w, "rotate", t.get("rotate", [0.0, 0.0, 0.0]))
    want_skin = t.get("skeleton")
    if want_skin is not None and not isinstance(want_skin, bool):
        raise ctx.error(w, f"skeleton must be true or false, got {want_skin!r}")
    rig = None
    try:
        if mesh_path.suffix.lower() in (".glb", ".gltf") and want_skin is not False and _is_skinned(mesh_path):
            from scenes.gltf import load_skinned_glb_rig

            mesh, rig = load_skinned_glb_rig(mesh_path)
        else:
            if want_skin:
                raise ValueError("skeleton = true but the file has no skinned mesh")
            mesh = load_mesh(mesh_path)
    except ValueError as e:
        raise ctx.error(w, f"mesh {mesh_rel!r}: {e}") from e
    if "subdivide" in t:
        k = t["subdivide"]
        if isinstance(k, bool) or not isinstance(k, int) or not 0 <= k <= MAX_SUBDIVIDE:
            raise ctx.error(w, f"subdivide must be an integer in [0, {MAX_SUBDIVIDE}], got {k!r}")
        if rig is not None:
            raise ctx.error(w, "subdivide is not available for a skinned mesh (its weights are per vertex)")
        mesh = subdivide(mesh, k)
    R = euler_xyz(rotate)
    if scale != (1.0, 1.0, 1.0) or translate != (0.0, 0.0, 0.0) or rotate != (0.0, 0.0, 0.0):
        M = torch.eye(4, dtype=torch.float64)
        M[:3, :3] = R @ torch.diag(torch.tensor(scale, dtype=torch.float64))
        M[:3, 3] = torch.tensor(translate, dtype=torch.float64)
        try:  # a collapsing scale leaves zero-area faces or a point
            mesh = check_extent(mesh.transformed(M).validate(), "mesh")
        except ValueError as e:
            raise ctx.error(w, f"scale/rotate/translate: mesh {mesh_rel!r} after the transform: {e}") from e
        if rig is not None:
            if len(set(scale)) != 1:
                raise ctx.error(w, "a skinned mesh takes a uniform scale only (its skeleton moves with it)")
            rig = _transformed_rig(rig, M)
    return Shape(name, region, mesh), rig


def euler_xyz(deg) -> torch.Tensor:
    """(3, 3) float64 rotation by Euler angles in degrees about x, then y, then z (R = Rz·Ry·Rx)."""
    ax, ay, az = (math.radians(float(a)) for a in deg)
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    Rx = torch.tensor([[1, 0, 0], [0, cx, -sx], [0, sx, cx]], dtype=torch.float64)
    Ry = torch.tensor([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]], dtype=torch.float64)
    Rz = torch.tensor([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]], dtype=torch.float64)
    return Rz @ Ry @ Rx


def _is_skinned(path: Path) -> bool:
    """Whether a glTF file has a skin (read from its JSON, no geometry decoded)."""
    import pygltflib

    try:
        g = pygltflib.GLTF2().load(str(path))
    except Exception as e:  # corrupt file: load_mesh names the problem
        raise ValueError(f"cannot read glTF: {e}") from e
    return bool(g.skins)


def _transformed_rig(rig, M: torch.Tensor):
    """The rig after the similarity transform M (uniform scale s, rotation, translation): joint
    positions move with the mesh, hinge axes rotate with it."""
    from scenes.skeleton import Skeleton

    sk = rig.skeleton
    A = M[:3, :3]
    s = float(torch.linalg.det(A)) ** (1 / 3)
    Rm = A / s
    P = sk.joint_positions.double() @ A.T + M[:3, 3]
    axes = sk.axes.double() @ Rm.T
    skel = Skeleton(sk.parents, P, axes, names=sk.names, limits=sk.limits)
    return dataclasses.replace(rig, skeleton=skel)


def _material(ctx: _Ctx, region: str, t: Any):
    from scenes.materials import MATERIAL_KINDS, Material

    w = f"[materials.{region}]"
    if not isinstance(t, dict):
        raise ctx.error(w, f"must be a table, got {type(t).__name__}")
    if "kind" not in t:
        raise ctx.error(w, "missing required key 'kind'")
    kind = t["kind"]
    if not isinstance(kind, str) or kind not in MATERIAL_KINDS:
        raise ctx.error(w, f"kind {kind!r} unknown; one of {', '.join(MATERIAL_KINDS)}")
    for k, v in t.items():
        if k == "kind":
            continue
        ok = _is_number(v) or (isinstance(v, list) and all(_is_number(c) for c in v))
        if not ok:
            raise ctx.error(w, f"{k} must be a number or a list of numbers, got {v!r}")
    try:
        return Material.from_params(dict(t))
    except (ValueError, TypeError) as e:  # from_params names the bad parameter
        raise ctx.error(w, str(e)) from e


# -- entry point ---------------------------------------------------------------------------------


def load_scene_file(path, size: str | None = None) -> Scene:
    """Load a TOML scene file (format in the module docstring) as a `scenes.scene.Scene`.

    Relative mesh / env-map paths resolve against the TOML file's folder. size: None (as written) or
    "test" | "bench" (vertex budget, film and env-map size of that size; module docstring). Any
    problem raises one ValueError naming the file and the offending key.
    """
    if size is not None and size not in VERTEX_BUDGET:
        raise ValueError(f"size must be one of {list(VERTEX_BUDGET)} or None, got {size!r}")
    from scenes.scene import covered_pixels

    path = Path(path)
    ctx = _Ctx(path)
    if not path.is_file():
        raise ValueError(f"{path}: scene file not found")
    try:
        with path.open("rb") as f:
            doc = tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path.name}: invalid TOML: {e}") from e
    except UnicodeDecodeError as e:
        raise ValueError(f"{path.name}: not UTF-8 text: {e}") from e
    _check_keys(ctx, "top level", doc, TOP_KEYS, ("camera", "envmap", "shape", "materials"))
    name = _string(ctx, "top level", "name", doc.get("name", path.stem))

    camera = _camera(ctx, doc["camera"])
    shapes_t = doc["shape"]
    if not isinstance(shapes_t, list) or not shapes_t:
        raise ctx.error("[[shape]]", "must be a non-empty array of tables")
    loaded = [_shape(ctx, i, t) for i, t in enumerate(shapes_t)]
    shapes = [sh for sh, _ in loaded]
    rigs = [(i, rig) for i, (_, rig) in enumerate(loaded) if rig is not None]
    if len(rigs) > 1:
        raise ctx.error("[[shape]]", "at most one skinned mesh per scene (one skeleton)")
    if size is not None:
        shapes, rigs, camera = _sized(ctx, size, shapes, rigs, camera)
    names = [s.name for s in shapes]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ctx.error("[[shape]]", f"name(s) {', '.join(map(repr, dup))} used more than once")
    regions: list[str] = []
    for s in shapes:
        if s.region not in regions:
            regions.append(s.region)

    mats_t = doc["materials"]
    if not isinstance(mats_t, dict):
        raise ctx.error("[materials]", f"must be a table of tables, got {type(mats_t).__name__}")
    missing = [r for r in regions if r not in mats_t]
    if missing:
        raise ctx.error("[materials]", f"no material for region(s) {', '.join(map(repr, missing))} "
                                       f"(add [materials.{missing[0]}])")
    unused = [r for r in mats_t if r not in regions]
    if unused:
        raise ctx.error("[materials]", f"material(s) for region(s) {', '.join(map(repr, unused))} not used by any "
                                       f"shape; regions: {', '.join(regions)}")
    materials = {r: _material(ctx, r, mats_t[r]) for r in regions}
    envmap = _envmap(ctx, doc["envmap"], SIZES[size]["env"] if size is not None else DEFAULT_ENV_HEIGHT)
    skin = {}
    if rigs:
        i, rig = rigs[0]
        skin = dict(skeleton=rig.skeleton, skin_weights={shapes[i].name: rig.weights}, animation=rig.animation)
    try:
        scene = Scene(name, shapes, regions, camera, envmap, materials, size=size or "test", **skin)
    except ValueError as e:
        raise ValueError(f"{path.name}: {e}") from e
    if covered_pixels(scene) == 0:
        raise ctx.error("[camera]", f"fov_deg/origin/target: the camera sees no geometry (no pixel of its "
                                    f"{camera.width}×{camera.height} film is covered; fov_deg = {camera.fov_deg:g}, "
                                    f"origin = {list(camera.origin)}, target = {list(camera.target)})")
    return scene


def _sized(ctx: _Ctx, size: str, shapes, rigs, camera):
    """Shapes decimated to the size's vertex budget (proportional shares), the film at the size's
    side (aspect kept); a line on stderr for each change."""
    from scenes.camera import Camera
    from scenes.library import decimate, decimate_skinned
    from scenes.scene import Shape

    budget = VERTEX_BUDGET[size]
    total = sum(s.mesh.num_vertices for s in shapes)
    rig_of = dict(rigs)
    if total > budget:
        # water-filling: meshes under an equal share of what is left keep every vertex; the rest
        # share the remaining budget in proportion to their size
        counts = {i: s.mesh.num_vertices for i, s in enumerate(shapes)}
        big, left = set(counts), budget
        while True:
            small = {i for i in big if counts[i] <= left / len(big)}
            if not small:
                break
            big -= small
            left -= sum(counts[i] for i in small)
            if not big:
                break
        n_big = sum(counts[i] for i in big)
        out = []
        for i, sh in enumerate(shapes):
            share = max(16, int(left * counts[i] / n_big)) if i in big else counts[i]
            if sh.mesh.num_vertices <= share:
                out.append(sh)
                continue
            if i in rig_of:
                mesh, W = decimate_skinned(sh.mesh, rig_of[i].weights, share)
                rig_of[i] = dataclasses.replace(rig_of[i], weights=W)
            else:
                mesh = decimate(sh.mesh, share)
            print(f"[prtbench] {ctx.path.name}: shape {sh.name!r} decimated {sh.mesh.num_vertices} -> "
                  f"{mesh.num_vertices} vertices ({size} budget {budget} for the scene)", file=sys.stderr)
            out.append(Shape(sh.name, sh.region, mesh))
        shapes = out
    side = SIZES[size]["film"]
    big = max(camera.width, camera.height)
    if big != side:
        w, h = max(1, round(camera.width * side / big)), max(1, round(camera.height * side / big))
        camera = Camera(camera.origin, camera.target, camera.up, camera.fov_deg, w, h)
    return shapes, sorted(rig_of.items()), camera
