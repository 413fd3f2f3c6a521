"""Shadow-ray throughput of the two visibility backends, and a visibility-bound precompute on each.

    python -m benchmarks.visibility [--rays N] [--repeats R] [--procedural] [--precompute [--poses P]]
                                    [--threads T]

Builds a bench-size mesh (``scenes.library.get_scene("shadow_detail", "bench")`` when available,
else a procedural ground grid with spheres, >= 10K triangles), shoots the same random shadow rays
(from random surface points, cosine-distributed about the normal) through

* ``embreex_1t`` / ``embreex_2t``: ``methods.core.visibility.Visibility.occluded`` (numpy in/out);
* ``mitsuba``: ``references.visibility.MitsubaVisibility.occluded`` (numpy in/out: includes the
  copies into and out of Dr.Jit);
* ``mitsuba_trace``: ``scene.ray_test`` alone on rays already in Dr.Jit arrays (the tracer's bound),

timed round-robin in one process (one warm-up each, then `repeats` rounds alternating the
backends), and prints the median rays per wall second and per process-CPU second (the machine may
be shared: CPU seconds are the steadier measure), the speed ratios and the fraction of rays on
which the tracers agree. ``--precompute`` also times two methods' visibility steps at test size on
each backend, alternating: zh_shadow's ``pose_visibility`` (the creature, `poses` training poses ×
every vertex × 1024 directions; backend chosen through ``PRTBENCH_VISIBILITY``, as a precompute
does) and triple_product's ``visibility_coeffs`` (sphere_plane, geodesic level 3), and how far the
two backends' results are apart (one flipped ray moves a coefficient by ~1e-3).
"""
from __future__ import annotations

import argparse
import os
import statistics
import time
from typing import Callable

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


def _round_robin(fns: dict[str, Callable[[], object]], repeats: int) -> dict[str, tuple[float, float]]:
    """Median (wall, process-CPU) seconds of each fn: one warm-up each (BVH commit, kernel
    compilation), then `repeats` rounds calling every fn once in turn (so load drifts hit all of
    them alike). CPU seconds count every thread of the process (embreex's, Dr.Jit's, torch's)."""
    for fn in fns.values():
        fn()
    ts: dict[str, list[tuple[float, float]]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t, c = time.perf_counter(), time.process_time()
            fn()
            ts[k].append((time.perf_counter() - t, time.process_time() - c))
    return {k: (statistics.median(x[0] for x in v), statistics.median(x[1] for x in v)) for k, v in ts.items()}


def throughput(V: np.ndarray, F: np.ndarray, rays: int, repeats: int) -> dict:
    """Rays per wall second and per CPU second of each backend on the same `rays` shadow rays,
    and their agreement."""
    import drjit as dr

    from methods.core.visibility import Visibility
    from references.visibility import MitsubaVisibility

    o, d = shadow_rays(V, F, rays)
    em = Visibility(V, F, threads=2)
    mv = MitsubaVisibility(V, F)
    ray = mv._rays(o, d, np.float32(np.inf))
    dr.eval(ray)
    dr.sync_thread()
    out: dict[str, np.ndarray] = {}

    def trace():
        h = mv._scene.ray_test(ray)
        dr.eval(h)
        dr.sync_thread()

    fns = {"embreex_1t": lambda: out.__setitem__("embreex_1t", em.occluded(o, d, threads=1)),
           "embreex_2t": lambda: out.__setitem__("embreex_2t", em.occluded(o, d, threads=2)),
           "mitsuba": lambda: out.__setitem__("mitsuba", mv.occluded(o, d)),
           "mitsuba_trace": trace}
    secs = _round_robin(fns, repeats)
    assert np.array_equal(out["embreex_1t"], out["embreex_2t"])
    res = {}
    for k, (wall, cpu) in secs.items():
        res[f"{k}_rays_per_s"] = rays / wall
        res[f"{k}_rays_per_cpu_s"] = rays / cpu
    res["agreement"] = float((out["mitsuba"] == out["embreex_1t"]).mean())
    res["occluded_fraction"] = float(out["embreex_1t"].mean())
    res["drjit_threads"] = dr.thread_count()
    return res


def _with_backend(backend: str, fn: Callable[[], object]) -> object:
    """fn() with ``PRTBENCH_VISIBILITY`` = backend (restored afterwards)."""
    from references.visibility import ENV_VAR

    old = os.environ.get(ENV_VAR)
    os.environ[ENV_VAR] = backend
    try:
        return fn()
    finally:
        if old is None:
            os.environ.pop(ENV_VAR)
        else:
            os.environ[ENV_VAR] = old


def precompute_steps(poses: int, repeats: int) -> dict:
    """Seconds (wall, CPU) of two methods' visibility steps at test size, per backend:
    zh_shadow's `pose_visibility` (creature, `poses` poses × every vertex × 1024 directions) and
    triple_product's `visibility_coeffs` (sphere_plane, the default level 3: 1280 directions per
    vertex); and how far the two backends' results are apart."""
    import torch

    from methods.core.spherical_haar import Geodesic
    from methods.triple_product import lighting as tp_lt
    from methods.triple_product.precompute import visibility_coeffs
    from methods.zh_shadow import precompute as zh
    from references.visibility import make_visibility
    from scenes.library import get_scene

    creature = get_scene("creature", "test")
    P = zh.training_poses(creature, poses, source="animation", seed=1234)
    g = get_scene("sphere_plane", "test").geometry()
    V, F = g.V.float(), g.F.long()
    N = torch.nn.functional.normalize(g.N.float(), dim=-1)
    R, geo = tp_lt.local_frames(N, "grid"), Geodesic(3)
    out: dict[tuple[str, str], object] = {}

    def zh_step(b: str):
        return lambda: out.__setitem__(("zh", b), _with_backend(
            b, lambda: zh.pose_visibility(creature, P, 4, n_dirs=1024, progress=False)[0]))

    def tp_step(b: str):
        return lambda: out.__setitem__(("tp", b), visibility_coeffs(make_visibility(V, F, backend=b), V, N, R, geo))

    secs = _round_robin({("zh", "embree"): zh_step("embree"), ("zh", "mitsuba"): zh_step("mitsuba"),
                         ("tp", "embree"): tp_step("embree"), ("tp", "mitsuba"): tp_step("mitsuba")}, repeats)
    nv_zh = creature.geometry().V.shape[0]
    res = {}
    for m, rays in (("zh", poses * nv_zh * 1024), ("tp", V.shape[0] * geo.n)):
        a, b = out[(m, "embree")], out[(m, "mitsuba")]
        differ = (a != b).reshape(-1, a.shape[-2], a.shape[-1]).any(-1)  # (poses, vertices)
        res[m] = {"rays": int(rays), "embree_s": secs[(m, "embree")], "mitsuba_s": secs[(m, "mitsuba")],
                  "max_abs_diff": float((a - b).abs().max()), "same_bits": bool(torch.equal(a, b)),
                  "vertices_differing": int(differ.sum()), "vertices": int(differ.numel())}
    return res


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rays", type=int, default=1_000_000)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--procedural", action="store_true", help="use the procedural mesh, not the library scene")
    ap.add_argument("--precompute", action="store_true", help="also time zh_shadow's visibility step per backend")
    ap.add_argument("--poses", type=int, default=8, help="training poses of the --precompute step")
    ap.add_argument("--threads", type=int, default=1, help="torch threads (the tracers keep their own pools)")
    args = ap.parse_args(argv)
    import torch

    torch.set_num_threads(args.threads)

    from references.mitsuba_setup import ensure_variant

    variant = ensure_variant()
    V, F, name = bench_mesh(procedural=args.procedural)
    print(f"mesh: {name}, {len(V)} vertices, {len(F)} triangles; {args.rays} shadow rays, Mitsuba {variant}, "
          f"median of {args.repeats} alternating rounds; torch threads {args.threads}; load average {os.getloadavg()[0]:.2f} on "
          f"{os.cpu_count()} CPUs")
    res = throughput(V, F, args.rays, args.repeats)
    print(f"{'':28s} {'Mrays/s':>8s} {'Mrays/CPU-s':>12s}")
    for k in ("embreex_1t", "embreex_2t", "mitsuba", "mitsuba_trace"):
        print(f"{k:28s} {res[k + '_rays_per_s'] / 1e6:8.2f} {res[k + '_rays_per_cpu_s'] / 1e6:12.2f}")
    for a, b in (("mitsuba", "embreex_2t"), ("mitsuba", "embreex_1t"), ("embreex_2t", "embreex_1t")):
        print(f"{a + ' / ' + b:28s} {res[a + '_rays_per_s'] / res[b + '_rays_per_s']:8.2f} "
              f"{res[a + '_rays_per_cpu_s'] / res[b + '_rays_per_cpu_s']:12.2f}")
    print(f"occluded fraction {res['occluded_fraction']:.4f}; embreex/mitsuba agreement {res['agreement']:.7f}; "
          f"Dr.Jit threads {res['drjit_threads']}")
    if args.precompute:
        pre = precompute_steps(args.poses, args.repeats)
        res["precompute"] = pre
        names = {"zh": f"zh_shadow pose_visibility, creature test, {args.poses} poses",
                 "tp": "triple_product visibility_coeffs, sphere_plane test, level 3"}
        for m, r in pre.items():
            (we, ce), (wm, cm) = r["embree_s"], r["mitsuba_s"]
            print(f"{names[m]} ({r['rays'] / 1e6:.1f} M rays): embree {we:.2f} s ({ce:.2f} CPU-s), "
                  f"mitsuba {wm:.2f} s ({cm:.2f} CPU-s): {we / wm:.2f}× wall, {ce / cm:.2f}× CPU; "
                  f"vertices (× poses) whose coefficients differ: {r['vertices_differing']} of {r['vertices']} "
                  f"(max |diff| {r['max_abs_diff']:.2e})")
        print(f"load average {os.getloadavg()[0]:.2f}")
    return res


if __name__ == "__main__":
    main()
