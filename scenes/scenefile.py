"""TOML scene files: bring your own mesh(es), env map and materials.

`load_scene_file(path)` reads a TOML file (stdlib `tomllib`) and returns a `scenes.scene.Scene`
built the same way as the library scenes (`scenes/library.py`). Format::

    name = "my_scene"                 # optional; default: the file's stem

    [camera]                          # required
    origin = [0.0, 2.0, 4.0]          # required, 3 numbers
    target = [0.0, 0.5, 0.0]          # required, 3 numbers
    up = [0.0, 1.0, 0.0]              # optional, default +Y
    fov_deg = 40.0                    # required, horizontal field of view in (0, 180)
    width = 64                        # required, film pixels (positive integer)
    height = 64                       # required

    [envmap]                          # required; exactly one of `file` / `procedural`
    procedural = "sky_sun"            # sky_sun | studio | window | overcast
    height = 64                       # procedural only (default 64); width = 2·height
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
    translate = [0.0, 0.5, 0.0]       # optional: 3 numbers (applied after scale)

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

import math
import tomllib
from pathlib import Path
from typing import Any

import torch

TOP_KEYS = ("name", "camera", "envmap", "shape", "materials")
CAMERA_REQUIRED = ("origin", "target", "fov_deg", "width", "height")
CAMERA_KEYS = CAMERA_REQUIRED + ("up",)
ENVMAP_KEYS = ("file", "procedural", "height", "seed", "rotate_y_deg", "key_azimuth_deg")
SHAPE_REQUIRED = ("name", "region", "mesh")
SHAPE_KEYS = SHAPE_REQUIRED + ("scale", "translate")
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


def _envmap(ctx: _Ctx, t: Any):
    from scenes.envmap import PROCEDURAL_NAMES, EnvMap, TooLarge, check_lit, check_size, procedural, read_image
    from scenes.library import aim_key_light, rotation_y

    w = "[envmap]"
    t = _check_keys(ctx, w, t, ENVMAP_KEYS)
    if ("file" in t) == ("procedural" in t):
        raise ctx.error(w, "needs exactly one of 'file' or 'procedural'")
    if "rotate_y_deg" in t and "key_azimuth_deg" in t:
        raise ctx.error(w, "give at most one of 'rotate_y_deg' and 'key_azimuth_deg'")
    if "file" in t:
        for k in ("height", "seed"):
            if k in t:
                raise ctx.error(w, f"{k} is only valid with 'procedural'")
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
    else:
        name = _string(ctx, w, "procedural", t["procedural"])
        if name not in PROCEDURAL_NAMES:
            raise ctx.error(w, f"procedural {name!r} unknown; one of {', '.join(PROCEDURAL_NAMES)}")
        height = _integer(ctx, w, "height", t.get("height", DEFAULT_ENV_HEIGHT), lo=3)
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
    from scenes.mesh import check_extent, load_mesh
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
    try:
        mesh = load_mesh(mesh_path)
    except ValueError as e:
        raise ctx.error(w, f"mesh {mesh_rel!r}: {e}") from e
    if scale != (1.0, 1.0, 1.0) or translate != (0.0, 0.0, 0.0):
        M = torch.eye(4, dtype=torch.float64)
        M[:3, :3] = torch.diag(torch.tensor(scale, dtype=torch.float64))
        M[:3, 3] = torch.tensor(translate, dtype=torch.float64)
        try:  # a collapsing scale leaves zero-area faces or a point
            mesh = check_extent(mesh.transformed(M).validate(), "mesh")
        except ValueError as e:
            raise ctx.error(w, f"scale/translate: mesh {mesh_rel!r} after the transform: {e}") from e
    return Shape(name, region, mesh)


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


def load_scene_file(path) -> "Scene":  # noqa: F821
    """Load a TOML scene file (format in the module docstring) as a `scenes.scene.Scene`.

    Relative mesh / env-map paths resolve against the TOML file's folder. Any problem raises one
    ValueError naming the file and the offending key.
    """
    from scenes.scene import Scene, covered_pixels

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
    shapes = [_shape(ctx, i, t) for i, t in enumerate(shapes_t)]
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
    envmap = _envmap(ctx, doc["envmap"])
    try:
        scene = Scene(name, shapes, regions, camera, envmap, materials)
    except ValueError as e:
        raise ValueError(f"{path.name}: {e}") from e
    if covered_pixels(scene) == 0:
        raise ctx.error("[camera]", f"fov_deg/origin/target: the camera sees no geometry (no pixel of its "
                                    f"{camera.width}×{camera.height} film is covered; fov_deg = {camera.fov_deg:g}, "
                                    f"origin = {list(camera.origin)}, target = {list(camera.target)})")
    return scene
