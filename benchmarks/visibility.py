"""Shadow-ray throughput: embreex (1 and 2 threads) vs Mitsuba's ``scene.ray_test``.

    python -m benchmarks.visibility [--rays N] [--repeats R]

Builds a bench-size mesh (``scenes.library.get_scene("shadow_detail", "bench")`` when available,
else a procedural ground grid with spheres, >= 10K triangles), shoots the same random shadow rays
(from random surface points, cosine-distributed about the normal) through both tracers and prints rays/s
(median of `repeats` timed runs after one warm-up) and the speed ratios, plus the fraction of rays
on which the two tracers agree.
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np


def procedural_mesh(grid: int = 64, spheres: int = 5, sphere_level: int = 3, seed: int = 0):
    """Ground grid y = 0 over [−2, 2]² (2·grid² triangles) + icospheres floating above it.

    Returns V (N, 3) float32, F (M, 3) int64."""
    import trimesh

    rng = np.random.default_rng(seed)
    x = np.linspace(-2, 2, grid + 1)
    X, Z = np.meshgrid(x, x, indexing="ij")
    Vg = np.stack([X.ravel(), np.zeros(X.size), Z.ravel()], -1)
    i = np.arange(grid)[:, None] * (grid + 1) + np.arange(grid)[None, :]
    i = i.ravel()
    # counter-clockwise seen from +y
    Fg = np.concatenate([np.stack([i, i + 1, i + grid + 2], -1), np.stack([i, i + grid + 2, i + grid + 1], -1)])
    Vs, Fs = [Vg], [Fg]
    off = len(Vg)
    for _ in range(spheres):
        s = trimesh.creation.icosphere(subdivisions=sphere_level, radius=rng.uniform(0.15, 0.4))
        c = np.array([rng.uniform(-1.5, 1.5), rng.uniform(0.5, 1.2), rng.uniform(-1.5, 1.5)])
        Vs.append(np.asarray(s.vertices) + c)
        Fs.append(np.asarray(s.faces) + off)
        off += len(s.vertices)
    return np.concatenate(Vs).astype(np.float32), np.concatenate(Fs).astype(np.int64)


def bench_mesh(procedural: bool = False):
    """(V, F, name): the library's shadow_detail bench scene if present, else `procedural_mesh`."""
    try:
        if procedural:
            raise LookupError("procedural mesh requested")
        from scenes.library import get_scene

        g = get_scene("shadow_detail", "bench").geometry()
        V, F = np.asarray(g.V, np.float32), np.asarray(g.F, np.int64)
        if len(F) >= 10_000:
            return V, F, "shadow_detail/bench"
    except Exception:
        pass
    V, F = procedural_mesh()
    return V, F, "procedural(ground 64² + 5 icospheres)"


def shadow_rays(V: np.ndarray, F: np.ndarray, n: int, seed: int = 1):
    """Shadow rays from random surface points (area-weighted faces, uniform barycentrics, offset
    along the face normal by 1e-4 × the bounding-box diagonal) in cosine-distributed directions
    about the face normal — what the oracle and visibility precomputation shoot."""
    rng = np.random.default_rng(seed)
    P = V[F].astype(np.float64)  # (M, 3, 3)
    ng = np.cross(P[:, 1] - P[:, 0], P[:, 2] - P[:, 0])
    area = np.linalg.norm(ng, axis=-1)
    ng = ng / np.maximum(area, 1e-30)[:, None]
    f = rng.choice(len(F), n, p=area / area.sum())
    u, v = rng.random(n), rng.random(n)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    p = (1 - u - v)[:, None] * P[f, 0] + u[:, None] * P[f, 1] + v[:, None] * P[f, 2]
    nrm = ng[f]
    diag = float(np.linalg.norm(V.max(0) - V.min(0)))
    o = p + 1e-4 * diag * nrm
    # cosine-weighted local direction, rotated into the frame of n (Duff et al. 2017 basis)
    u1, u2 = rng.random(n), rng.random(n)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    loc = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], -1)
    sign = np.where(nrm[:, 2] >= 0, 1.0, -1.0)
    a_ = -1.0 / (sign + nrm[:, 2])
    b_ = nrm[:, 0] * nrm[:, 1] * a_
    s_ = np.stack([1 + sign * nrm[:, 0] ** 2 * a_, sign * b_, -sign * nrm[:, 0]], -1)
    t_ = np.stack([b_, sign + nrm[:, 1] ** 2 * a_, -nrm[:, 1]], -1)
    d = loc[:, :1] * s_ + loc[:, 1:2] * t_ + loc[:, 2:] * nrm
    return o.astype(np.float32), d.astype(np.float32)


def _time(fn, repeats: int) -> float:
    fn()  # warm-up (BVH commit / kernel compilation)
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts)


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--procedural", action="store_true", help="use the procedural mesh, not the library scene")
    args = ap.parse_args(argv)

    from methods.core.visibility import Visibility

    V, F, name = bench_mesh(procedural=args.procedural)
    o, d = shadow_rays(V, F, args.rays)
    print(f"mesh: {name}, {len(V)} vertices, {len(F)} triangles; {args.rays} shadow rays, "
          f"median of {args.repeats}; load average {os.getloadavg()[0]:.2f} on {os.cpu_count()} CPUs")
    vis = Visibility(V, F, threads=2)
    res = {}
    occ = {}
    for th in (1, 2):
        t = _time(lambda: occ.__setitem__(th, vis.occluded(o, d, threads=th)), args.repeats)
        res[f"embreex_{th}t"] = args.rays / t
    assert np.array_equal(occ[1], occ[2])

    from references.mitsuba_setup import ensure_variant

    variant = ensure_variant()
    import drjit as dr
    import mitsuba as mi

    mesh = mi.Mesh("bench", vertex_count=len(V), face_count=len(F), has_vertex_normals=False,
                   has_vertex_texcoords=False)
    p = mi.traverse(mesh)
    p["vertex_positions"] = mi.Float(V.ravel())
    p["faces"] = mi.UInt32(F.astype(np.uint32).ravel())
    p.update()
    scene = mi.load_dict({"type": "scene", "mesh": mesh})
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k].copy()) for k in range(3)]),
                   mi.Vector3f(*[mi.Float(d[:, k].copy()) for k in range(3)]))
    dr.eval(ray)
    dr.sync_thread()
    out = {}

    def mi_run():
        h = scene.ray_test(ray)
        out["h"] = np.array(h, dtype=bool)  # forces the (asynchronous) LLVM kernel; numpy like embreex

    t = _time(mi_run, args.repeats)
    res[f"mitsuba_{variant}_{dr.thread_count()}t"] = args.rays / t
    agree = float((out["h"] == occ[1]).mean())

    for k, v in res.items():
        print(f"{k:28s} {v / 1e6:8.2f} Mrays/s")
    mk = [k for k in res if k.startswith("mitsuba")][0]
    print(f"embreex 2t / 1t            {res['embreex_2t'] / res['embreex_1t']:8.2f}")
    print(f"embreex 2t / mitsuba       {res['embreex_2t'] / res[mk]:8.2f}")
    print(f"embreex 1t / mitsuba       {res['embreex_1t'] / res[mk]:8.2f}")
    print(f"occluded fraction {occ[1].mean():.4f}; embreex/mitsuba agreement {agree:.6f}")
    res["agreement"] = agree
    return res


if __name__ == "__main__":
    main()
