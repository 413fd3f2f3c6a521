"""G-buffer from Mitsuba's own primary rays, so method images align pixel-for-pixel with references.

Sub-pixel sample s = (i, j) of pixel (x, y) (S×S grid, s = j·S + i) is the ray of Mitsuba's sensor
through the film position ((x + (i + 0.5)/S)/W, (y + (j + 0.5)/S)/H) (``sensor.sample_ray``), the
same stratified positions as ``Camera.pixel_rays``. ``scene.ray_intersect_preliminary`` gives the
shape, the triangle index within it and Mitsuba's ``prim_uv`` barycentrics; everything else is
computed in torch from OUR posed geometry: the global face index (shape's face offset + triangle),
the hit position (barycentric interpolation of our vertices), the unit shading normal (normalised
barycentric interpolation of our vertex normals — what Mitsuba shades with), the region.

``wo`` is −(ray direction) for every sample (also for misses, where it is the direction towards the
camera of the background); misses have face/region −1 and zero bary/position/normal.
"""
from __future__ import annotations

import numpy as np
import torch

from scenes.frame import GBuffer
from references.export import _mi, geometry_dict, shape_indices, shape_slices

# Unit-normal guard: interpolated normals shorter than this (opposite vertex normals) are replaced
# by the geometric face normal.
NORMAL_EPS = 1e-12


def film_samples(width: int, height: int, S: int) -> np.ndarray:
    """(H·W·S², 2) film positions in [0, 1]², ordered (y, x, s), s = j·S + i (i along x)."""
    y, x, s = np.meshgrid(np.arange(height), np.arange(width), np.arange(S * S), indexing="ij")
    fx = (x + (s % S + 0.5) / S) / width
    fy = (y + (s // S + 0.5) / S) / height
    return np.stack([fx, fy], -1).reshape(-1, 2)


def primary_hits(mi_scene, S: int) -> dict:
    """Trace the S×S sub-pixel rays of the scene's first sensor.

    Returns numpy arrays over P = H·W·S² samples: ``hit`` (P,) bool, ``shape`` (P,) our shape
    index (−1 on a miss), ``prim`` (P,) triangle index within the shape, ``bary`` (P, 2),
    ``o``, ``d`` (P, 3) ray origins and unit directions, ``t`` (P,) hit distances.
    """
    mi = _mi()
    import drjit as dr

    sensor = mi_scene.sensors()[0]
    W, H = (int(v) for v in sensor.film().crop_size())
    pos = film_samples(W, H, S)
    P = pos.shape[0]
    ray, _ = sensor.sample_ray(
        time=0.0,
        sample1=0.5,
        sample2=mi.Point2f(mi.Float(pos[:, 0].astype(np.float32)), mi.Float(pos[:, 1].astype(np.float32))),
        sample3=mi.Point2f(mi.Float(np.full(P, 0.5, np.float32)), mi.Float(np.full(P, 0.5, np.float32))),
    )
    pi = mi_scene.ray_intersect_preliminary(ray, coherent=True)
    valid = pi.is_valid()
    ptr = dr.reinterpret_array(mi.UInt32, pi.shape)
    dr.eval(valid, ptr, pi.prim_index, pi.prim_uv, pi.t, ray.o, ray.d)
    hit = np.array(valid, dtype=bool).reshape(-1)
    ptr = np.array(ptr, dtype=np.int64).reshape(-1)
    # Map Mitsuba's shape pointers (registry ids in JIT variants) → our shape index.
    table = np.array(dr.reinterpret_array(mi.UInt32, mi_scene.shapes_dr()), dtype=np.int64).reshape(-1)
    ours = shape_indices(mi_scene)
    order = np.argsort(table)
    pos_in = np.searchsorted(table[order], ptr)
    pos_in = np.clip(pos_in, 0, len(table) - 1)
    found = table[order][pos_in] == ptr
    if (hit & ~found).any():
        raise RuntimeError("primary hit on a shape missing from scene.shapes_dr()")
    shape = np.where(hit, ours[order][pos_in], -1)
    prim = np.where(hit, np.array(pi.prim_index, dtype=np.int64).reshape(-1), -1)
    uv = np.array(pi.prim_uv, dtype=np.float32).reshape(2, -1).T if P else np.zeros((0, 2), np.float32)
    bary = np.where(hit[:, None], uv, 0.0).astype(np.float32)
    o = np.array(ray.o, dtype=np.float64).reshape(3, -1).T
    d = np.array(ray.d, dtype=np.float64).reshape(3, -1).T
    t = np.where(hit, np.array(pi.t, dtype=np.float64).reshape(-1), np.inf)
    return {"hit": hit, "shape": shape, "prim": prim, "bary": bary, "o": o, "d": d, "t": t,
            "width": W, "height": H}


def make_gbuffer(scene, frame, S: int = 2) -> GBuffer:
    """G-buffer of ``scene`` in ``frame`` (posed geometry, frame.camera), S×S samples per pixel."""
    if int(S) != S or S < 1:
        raise ValueError(f"S (sub-samples per pixel side) must be a positive integer, got {S!r}")
    S = int(S)
    mi = _mi()
    mi_scene = mi.load_dict(geometry_dict(scene, frame))
    h = primary_hits(mi_scene, S)
    geom = scene.geometry(frame.pose)
    slices = shape_slices(geom, len(scene.shapes))
    W, H = h["width"], h["height"]
    if (W, H) != (frame.camera.width, frame.camera.height):
        raise RuntimeError(f"Mitsuba film {W}x{H} differs from the camera {frame.camera.width}x{frame.camera.height}")

    hit = torch.from_numpy(h["hit"])
    f_off = torch.tensor([s.f0 for s in slices], dtype=torch.int64)
    shape = torch.from_numpy(h["shape"])
    prim = torch.from_numpy(h["prim"])
    face = torch.where(hit, f_off[shape.clamp_min(0)] + prim, torch.full_like(prim, -1))
    bary = torch.from_numpy(h["bary"])
    V = torch.as_tensor(geom.V).detach().cpu()
    Nv = torch.as_tensor(geom.N).detach().cpu()
    F = torch.as_tensor(geom.F).detach().cpu().long()

    gb = GBuffer(height=H, width=W, spp_side=S, hit=hit, face=face, bary=bary,
                 position=torch.zeros(0), normal=torch.zeros(0), wo=torch.zeros(0),
                 region=torch.zeros(0), coverage=torch.zeros(0))
    # p = (1−u−v)·p0 + u·p1 + v·p2 (Mitsuba prim_uv convention), in float64 then float32.
    position = gb.interpolate(V.double(), F).float()
    n = gb.interpolate(Nv.double(), F)
    ln = n.norm(dim=1, keepdim=True)
    # Degenerate interpolated normal (never for sane meshes): fall back to the face normal.
    fi = face.clamp_min(0)
    p0, p1, p2 = V.double()[F[fi, 0]], V.double()[F[fi, 1]], V.double()[F[fi, 2]]
    ng = torch.cross(p1 - p0, p2 - p0, dim=1)
    ng = ng / ng.norm(dim=1, keepdim=True).clamp_min(1e-300)
    normal = torch.where(ln > NORMAL_EPS, n / ln.clamp_min(NORMAL_EPS), ng)
    normal = torch.where(hit[:, None], normal, torch.zeros_like(normal)).float()
    d = torch.from_numpy(h["d"])
    wo = (-d / d.norm(dim=1, keepdim=True)).float()
    face_region = torch.as_tensor(geom.face_region).detach().cpu().long()
    region = torch.where(hit, face_region[fi], torch.full_like(face, -1))
    coverage = hit.view(H, W, S * S).all(-1)
    gb.position, gb.normal, gb.wo, gb.region, gb.coverage = position, normal, wo, region, coverage
    return gb
