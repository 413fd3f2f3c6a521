"""Ray-cast visibility over a triangle mesh with embreex (Intel Embree 4 bindings).

One `Visibility` object wraps one Embree scene built from a mesh ``(V (N,3), F (M,3))``; it answers
shadow-ray queries (`occluded`) and closest-hit queries (`intersect`). On top of it live the PRT
visibility helpers: per-vertex visibility over a direction set, visibility cube maps, SH projection
of visibility, and barycentric interpolation of per-vertex visibility at a hit point
(Sun 2007 §4.3).

Conventions
-----------
* Visibility ``True`` means *visible* (the ray escapes); `occluded` returns the opposite.
* Barycentrics are Mitsuba's ``prim_uv`` convention, p = (1−u−v)·p0 + u·p1 + v·p2 with
  (p0, p1, p2) = V[F[face]]. Embree reports exactly this (u, v) (checked in the tests).
* ``t`` is in units of ``|d|`` (directions need not be unit length, but usually are); a miss has
  ``t = inf`` and ``face = -1``.
* Inputs may be torch tensors or numpy arrays; outputs follow the input kind (torch tensors on
  the input's device, or numpy arrays). Embree itself always computes in float32 on the CPU.

Threads
-------
embreex releases the GIL inside ``EmbreeScene.run``, so a large batch is split into ``threads``
contiguous chunks traced concurrently. Measured: 1.85× with 2 threads on an idle 2-core machine
(icosphere, 400K rays); no gain when the cores are oversubscribed (load ≈ 5–7, see
``python -m benchmarks.visibility``). Results are identical to the single-threaded call.
embreex traces one ray per Embree call; Mitsuba's ``scene.ray_test`` (llvm_ad_rgb, Embree packets)
is faster on the same rays. It lives a layer up (the core is renderer-free):
``references.visibility.MitsubaVisibility`` implements the same `RayCaster` interface, and
``references.visibility.make_visibility`` picks the backend (``PRTBENCH_VISIBILITY``).
"""
from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor
from typing import Any

import numpy as np
import torch
from torch import Tensor

import embreex.mesh_construction as _emc
import embreex.rtcore_scene as _ers

__all__ = [
    "RayCaster",
    "Visibility",
    "offset_origins",
    "vertex_visibility",
    "visibility_cubemap",
    "visibility_sh",
    "interpolate_at_hits",
]

# Batches smaller than this are traced on the calling thread: the split is not worth a thread.
MIN_RAYS_PER_THREAD = 16384
# Relative normal offset of shadow-ray origins: float32 positions carry ~6e-8 relative error,
# a 1e-4 relative offset clears self-intersection on curved tessellated surfaces while staying
# far below any feature a visibility test of ours resolves.
DEFAULT_OFFSET_EPS = 1e-4

_EXECUTORS: dict[int, ThreadPoolExecutor] = {}


def _executor(n: int) -> ThreadPoolExecutor:
    ex = _EXECUTORS.get(n)
    if ex is None:
        ex = ThreadPoolExecutor(max_workers=n, thread_name_prefix="prt-embree")
        _EXECUTORS[n] = ex
    return ex


def _as_np(x: Any, name: str, shape_tail: tuple[int, ...] | None = None, dtype=np.float32) -> np.ndarray:
    if isinstance(x, Tensor):
        x = x.detach().cpu().numpy()
    a = np.ascontiguousarray(np.asarray(x), dtype=dtype)
    if shape_tail is not None:
        if a.ndim != 1 + len(shape_tail) or tuple(a.shape[1:]) != shape_tail:
            raise ValueError(f"{name} must have shape (R, {', '.join(map(str, shape_tail))}), got {a.shape}")
    return a


def _out(a: np.ndarray, like: Any) -> Any:
    """Return `a` as the same kind of array as `like` (torch on like's device, else numpy)."""
    if isinstance(like, Tensor):
        return torch.from_numpy(a).to(like.device)
    return a


def _per_ray(x: Any, R: int, name: str) -> np.ndarray:
    """Scalar or (R,) → float64 array: 0-d for a scalar (it broadcasts), else (R,)."""
    if isinstance(x, Tensor):
        x = x.detach().cpu().numpy()
    a = np.asarray(x, dtype=np.float64)
    if a.ndim == 0:
        return a
    if a.shape != (R,):
        raise ValueError(f"{name} must be a scalar or have shape ({R},), got {a.shape}")
    return a


class RayCaster:
    """What every visibility backend shares: the mesh, its checks, the ray-segment convention.

    A backend (`Visibility` here; ``references.visibility.MitsubaVisibility`` on Mitsuba's
    ``scene.ray_test``) implements `occluded` and `intersect` with the signatures below, on the
    segment convention of `_prepare`: a ray (o, d, tnear, tfar) is traced as the segment from
    o + tnear·d of length tfar − tnear (both tracers start rays at t = 0), so the same rays give the
    same hits on either backend up to grazing rays.

    Attributes:
        V (N, 3) float32, F (M, 3) int32 numpy arrays; bbox (lo, hi); scale: bounding-box
        diagonal (the unit of scale-aware ray offsets, `offset_origins`); backend: its name.
    """

    backend: str = "?"

    def __init__(self, V: Any, F: Any):
        Vn = _as_np(V, "V", (3,))
        Fn = _as_np(F, "F", (3,), dtype=np.int64)
        if Fn.shape[0] == 0:
            raise ValueError("F must contain at least one triangle")
        if not np.isfinite(Vn).all():
            raise ValueError("V contains NaN or Inf")
        if Fn.min() < 0 or Fn.max() >= Vn.shape[0]:
            raise ValueError(f"F indexes outside V (0..{Vn.shape[0] - 1})")
        self.V = Vn  # (N, 3) float32
        self.F = Fn.astype(np.int32)  # (M, 3) int32
        lo, hi = Vn.min(0), Vn.max(0)
        self.bbox = (lo, hi)
        # (scalar) scene scale: bounding-box diagonal, used for scale-aware ray offsets
        self.scale = float(np.linalg.norm(hi - lo)) or 1.0

    @property
    def num_faces(self) -> int:
        return int(self.F.shape[0])

    def _prepare(self, origins, dirs, tnear, tfar):
        """→ o (R, 3), d (R, 3) float32 contiguous, tn float64, seg float32: the segment starts at
        o (the origin moved to tnear) and has length seg (inf allowed); tn and seg are (R,) arrays,
        or 0-d when tnear and tfar are both scalars (the common case: no per-ray arrays built)."""
        o = _as_np(origins, "origins", (3,))
        d = _as_np(dirs, "dirs", (3,))
        if o.shape != d.shape:
            raise ValueError(f"origins {o.shape} and dirs {d.shape} must have the same shape")
        R = o.shape[0]
        tn = _per_ray(tnear, R, "tnear")
        tf = _per_ray(tfar, R, "tfar")
        if (tn < 0).any():
            raise ValueError("tnear must be >= 0")
        # the tracers start rays at t = 0: move the origin to tnear instead (same segment).
        if (tn != 0).any():
            o = np.ascontiguousarray(o + (tn[..., None] * d).astype(np.float32))
        seg = np.maximum(tf - tn, 0.0).astype(np.float32)  # inf stays inf (Embree accepts inf)
        if tn.ndim != seg.ndim:  # one scalar bound, one per-ray: per-ray both
            tn = np.broadcast_to(tn, seg.shape)
        return o, d, tn, seg

    # numpy result → the array kind of the input (torch on its device, else numpy)
    _wrap = staticmethod(_out)

    @staticmethod
    def _hits(origins: Any, tn: np.ndarray, t: np.ndarray, face: np.ndarray, u: np.ndarray, v: np.ndarray):
        """Closest-hit outputs in the `intersect` convention (misses: face < 0 → t = inf, −1, 0, 0),
        t measured from the original origin; arrays of the kind of `origins`."""
        face = face.astype(np.int64)
        miss = face < 0
        t = (t.astype(np.float64) + tn).astype(np.float32)
        u = u.astype(np.float32)
        v = v.astype(np.float32)
        face[miss] = -1
        t[miss] = np.inf
        u[miss] = 0.0
        v[miss] = 0.0
        return _out(t, origins), _out(face, origins), _out(u, origins), _out(v, origins)

    def occluded(self, origins: Any, dirs: Any, tnear: Any = 0.0, tfar: Any = math.inf, *,
                 threads: int | None = None) -> Any:
        """(R,) bool, True where the segment is blocked (contract: `Visibility.occluded`)."""
        raise NotImplementedError

    def intersect(self, origins: Any, dirs: Any, tnear: Any = 0.0, tfar: Any = math.inf, *,
                  threads: int | None = None):
        """Closest hit t, face, u, v (contract: `Visibility.intersect`)."""
        raise NotImplementedError

    def visible(self, origins: Any, dirs: Any, tnear: Any = 0.0, tfar: Any = math.inf, *,
                threads: int | None = None) -> Any:
        """(R,) bool, True where the ray segment is free (= ~occluded)."""
        occ = self.occluded(origins, dirs, tnear, tfar, threads=threads)
        return ~occ


class Visibility(RayCaster):
    """An Embree scene over one triangle mesh (embreex).

    Args:
        V: (N, 3) vertex positions; F: (M, 3) triangle vertex indices (torch or numpy).
        threads: worker threads used for large batches (default 2; 1 = calling thread only).
        robust: Embree's robust traversal mode (watertight edges; no rays slip between
            triangles sharing an edge). Default True.
    """

    backend = "embree"

    def __init__(self, V: Any, F: Any, *, threads: int = 2, robust: bool = True):
        if threads < 1:
            raise ValueError(f"threads must be >= 1, got {threads}")
        super().__init__(V, F)
        self.threads = int(threads)
        self._scene = _ers.EmbreeScene(robust=robust)
        self._mesh = _emc.TriangleMesh(self._scene, self.V, self.F)  # keep alive with the scene
        # Commit the BVH now (embreex commits lazily on the first query; doing it here keeps the
        # first threaded call free of a race on the commit).
        self._scene.run(np.zeros((1, 3), np.float32), np.array([[0, 0, 1]], np.float32), query="OCCLUDED")

    # -- raw queries -------------------------------------------------------------------------

    def _run(self, o: np.ndarray, d: np.ndarray, seg: np.ndarray, query: str, output: bool, threads: int | None):
        R = o.shape[0]
        n = self.threads if threads is None else int(threads)
        n = max(1, min(n, R // MIN_RAYS_PER_THREAD))

        def job(sl: slice):
            # embreex writes the hit distance into `dists` in place: pass a private copy
            n_sl = sl.stop - sl.start
            dists = np.full(n_sl, seg, np.float32) if seg.ndim == 0 else seg[sl].copy()
            return self._scene.run(o[sl], d[sl], dists=dists, query=query, output=output)

        if n == 1:
            return [job(slice(0, R))]
        bounds = np.linspace(0, R, n + 1).astype(int)
        sls = [slice(bounds[i], bounds[i + 1]) for i in range(n)]
        return list(_executor(n).map(job, sls))

    def occluded(self, origins: Any, dirs: Any, tnear: Any = 0.0, tfar: Any = math.inf, *,
                 threads: int | None = None) -> Any:
        """Shadow-ray test: is any triangle hit at t ∈ (tnear, tfar)?

        Args:
            origins: (R, 3); dirs: (R, 3) ray directions (t in units of |d|).
            tnear, tfar: scalars or (R,) segment bounds.
            threads: override the object's thread count for this call.
        Returns:
            (R,) bool, True where the segment is blocked.
        """
        o, d, _, seg = self._prepare(origins, dirs, tnear, tfar)
        if o.shape[0] == 0:
            return _out(np.zeros(0, bool), origins)
        parts = self._run(o, d, seg, "OCCLUDED", False, threads)
        hit = np.concatenate(parts) != -1  # embreex returns geomID of the blocker, -1 when free
        return self._wrap(hit, origins)

    def intersect(self, origins: Any, dirs: Any, tnear: Any = 0.0, tfar: Any = math.inf, *,
                  threads: int | None = None):
        """Closest hit along each ray.

        Args:
            origins: (R, 3); dirs: (R, 3); tnear, tfar: scalars or (R,).
        Returns:
            t (R,) float32 (inf on a miss), face (R,) int64 (−1 on a miss), u (R,), v (R,) float32
            barycentrics in Mitsuba's prim_uv convention p = (1−u−v)p0 + u p1 + v p2 (0 on a miss).
        """
        o, d, tn, seg = self._prepare(origins, dirs, tnear, tfar)
        R = o.shape[0]
        if R == 0:
            z = np.zeros(0, np.float32)
            return (_out(z, origins), _out(np.zeros(0, np.int64), origins), _out(z, origins), _out(z, origins))
        parts = self._run(o, d, seg, "INTERSECT", True, threads)
        cat = lambda k: np.concatenate([p[k] for p in parts])  # noqa: E731
        return self._hits(origins, tn, cat("tfar"), cat("primID"), cat("u"), cat("v"))


# -- helpers ---------------------------------------------------------------------------------


def offset_origins(p: Tensor, n: Tensor, eps: float = DEFAULT_OFFSET_EPS, *,
                   scale: float | None = None) -> Tensor:
    """Move surface points off the surface along their normals (shadow-ray origins).

    The offset is ``eps * scale`` with ``scale`` the scene size (e.g. `Visibility.scale`, the
    bounding-box diagonal) when given, else ``eps * (1 + max_i |p_i|)`` per point — proportional to
    the float32 spacing at p, like Mitsuba's ``(1 + max|p|)·RayEpsilon`` (Pharr et al. PBRT §3.9).

    Args:
        p: (..., 3) points; n: (..., 3) unit normals (same shape).
    Returns:
        (..., 3) offset points.
    """
    p = torch.as_tensor(p)
    n = torch.as_tensor(n, dtype=p.dtype, device=p.device)
    if p.shape[-1] != 3 or p.shape != n.shape:
        raise ValueError(f"p and n must both have shape (..., 3), got {tuple(p.shape)} and {tuple(n.shape)}")
    if scale is not None:
        off = torch.full(p.shape[:-1] + (1,), eps * float(scale), dtype=p.dtype, device=p.device)
    else:
        off = eps * (1.0 + p.abs().amax(-1, keepdim=True))
    return p + off * n


def vertex_visibility(vis: RayCaster, points: Tensor, normals: Tensor, dirs: Tensor, *,
                      local: bool = False, eps: float = DEFAULT_OFFSET_EPS,
                      below_horizon: str = "trace", chunk_rays: int = 1 << 20,
                      progress: bool | None = None) -> Tensor:
    """Binary visibility of a direction set from every point.

    Args:
        vis: the scene's `RayCaster` (embreex `Visibility` or another backend).
        points: (V, 3) surface points; normals: (V, 3) unit normals (origins are offset along them
            with `offset_origins(..., scale=vis.scale)`).
        dirs: (D, 3) unit directions, world frame (``local=False``) or each point's local frame
            (``local=True``: z = normal, tangent from `methods.core.frames.coordinate_system`).
        below_horizon: "trace" (trace every direction) or "hide" (directions with n·d <= 0 are
            reported not visible without tracing them).
        chunk_rays: rays traced per batch; progress: tqdm bar (default: when stderr is a TTY).
    Returns:
        (V, D) bool on points' device, True = visible (the ray escapes).
    """
    from methods.core.frames import to_world  # local import: frames is tiny, avoid cycles
    from tqdm.auto import tqdm
    import sys

    points = torch.as_tensor(points)
    normals = torch.as_tensor(normals)
    dirs = torch.as_tensor(dirs)
    if points.ndim != 2 or points.shape[-1] != 3 or normals.shape != points.shape:
        raise ValueError(f"points, normals must be (V, 3), got {tuple(points.shape)}, {tuple(normals.shape)}")
    if dirs.ndim != 2 or dirs.shape[-1] != 3:
        raise ValueError(f"dirs must be (D, 3), got {tuple(dirs.shape)}")
    if below_horizon not in ("trace", "hide"):
        raise ValueError(f"below_horizon must be 'trace' or 'hide', got {below_horizon!r}")
    dev = points.device
    P = points.detach().cpu().float()
    N = normals.detach().cpu().float()
    Dd = dirs.detach().cpu().float()
    nV, nD = P.shape[0], Dd.shape[0]
    out = torch.zeros(nV, nD, dtype=torch.bool)
    if nV == 0 or nD == 0:
        return out.to(dev)
    O = offset_origins(P, N, eps, scale=vis.scale)
    per = max(1, chunk_rays // nD)  # vertices per chunk
    if progress is None:
        progress = sys.stderr.isatty()
    for a in tqdm(range(0, nV, per), disable=not progress, desc="visibility", unit="chunk"):
        b = min(nV, a + per)
        if local:
            n_ = N[a:b, None, :].expand(b - a, nD, 3)
            w = to_world(Dd[None].expand(b - a, nD, 3), n_)  # (v, D, 3)
        else:
            w = Dd[None].expand(b - a, nD, 3)
        o = O[a:b, None, :].expand(b - a, nD, 3)
        free = ~torch.from_numpy(vis.occluded(o.reshape(-1, 3).numpy(), w.reshape(-1, 3).numpy()))
        free = free.reshape(b - a, nD)
        if below_horizon == "hide":
            free &= (w * N[a:b, None, :]).sum(-1) > 0
        out[a:b] = free
    return out.to(dev)


def visibility_cubemap(vis: RayCaster, points: Tensor, normals: Tensor, N: int, *,
                       local: bool = False, supersample: int = 1, eps: float = DEFAULT_OFFSET_EPS,
                       below_horizon: str = "trace", progress: bool | None = None) -> Tensor:
    """Visibility as cube maps (`methods.core.cubemap` face order/orientation).

    Args:
        points, normals: (V, 3).
        N: face resolution; supersample: s → s×s rays per texel (stratified texel centres),
            averaged; local: texel directions in each point's local frame (z = normal).
    Returns:
        (V, 6, N, N) float32 in [0, 1]: fraction of each texel's rays that escape.
    """
    from methods.core.cubemap import texel_directions_supersampled

    points = torch.as_tensor(points)
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    dirs = texel_directions_supersampled(N, s, dtype=torch.float32)  # (6, N, N, s*s, 3)
    vis_b = vertex_visibility(vis, points, normals, dirs.reshape(-1, 3), local=local, eps=eps,
                              below_horizon=below_horizon, progress=progress)
    return vis_b.float().reshape(points.shape[0], 6, N, N, s * s).mean(-1)


def visibility_sh(vis: RayCaster, points: Tensor, normals: Tensor, order: int, *,
                  n_dirs: int = 4096, local: bool = True, eps: float = DEFAULT_OFFSET_EPS,
                  below_horizon: str = "trace", progress: bool | None = None) -> Tensor:
    """SH projection of binary visibility by quadrature on a shared spherical Fibonacci set
    (`methods.core.sampling.fibonacci_sphere`, weights 4π/n):

        V_i = ∫ V(ω) y_i(ω) dω ≈ Σ_k w_k V(ω_k) y_i(ω_k)

    Args:
        points, normals: (V, 3); order: SH order n (bands 0..n−1, n² coefficients, the real SH
            convention of `methods.core.sh`).
        n_dirs: quadrature directions; local: coefficients in each point's local frame (z = normal,
            tangent from `frames.coordinate_system`) rather than the world frame.
    Returns:
        (V, order²) float32 on points' device.
    """
    from methods.core import sh as _sh
    from methods.core.sampling import fibonacci_sphere

    points = torch.as_tensor(points)
    dirs, w = fibonacci_sphere(n_dirs, dtype=torch.float32)
    vb = vertex_visibility(vis, points, normals, dirs, local=local, eps=eps,
                           below_horizon=below_horizon, progress=progress)  # (V, D)
    Y = _sh.sh_eval(dirs, order)  # (D, n²)
    return ((vb.float().cpu() * w) @ Y).to(points.device)


def interpolate_at_hits(vertex_values: Tensor, F: Tensor, face: Tensor, u: Tensor, v: Tensor) -> Tensor:
    """Barycentric interpolation of per-vertex data at hit points (Sun 2007 §4.3: the visibility
    at a point inside a triangle is interpolated from its three vertices' visibility vectors).

    Args:
        vertex_values: (Nv, ...) per-vertex data (e.g. visibility vectors (Nv, K)).
        F: (M, 3) faces; face: (R,) face index per hit (−1 = miss → zeros);
        u, v: (R,) barycentrics, value = (1−u−v)·x0 + u·x1 + v·x2 (Mitsuba prim_uv).
    Returns:
        (R, ...) interpolated values, dtype of vertex_values (bool promoted to float32).
    """
    X = torch.as_tensor(vertex_values)
    if X.dtype == torch.bool:
        X = X.float()
    F = torch.as_tensor(F, device=X.device).long()
    face = torch.as_tensor(face, device=X.device).long()
    u = torch.as_tensor(u, device=X.device, dtype=X.dtype)
    v = torch.as_tensor(v, device=X.device, dtype=X.dtype)
    if F.ndim != 2 or F.shape[1] != 3:
        raise ValueError(f"F must be (M, 3), got {tuple(F.shape)}")
    if face.ndim != 1 or u.shape != face.shape or v.shape != face.shape:
        raise ValueError("face, u, v must all be (R,)")
    hit = face >= 0
    tri = F[face.clamp_min(0)]  # (R, 3)
    extra = (1,) * (X.ndim - 1)
    w0 = (1.0 - u - v).reshape(-1, *extra)
    out = w0 * X[tri[:, 0]] + u.reshape(-1, *extra) * X[tri[:, 1]] + v.reshape(-1, *extra) * X[tri[:, 2]]
    return out * hit.reshape(-1, *extra).to(out.dtype)
