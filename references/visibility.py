"""Shadow and closest-hit rays on Mitsuba's ``scene.ray_test`` / ``ray_intersect_preliminary``, and
the factory every method uses to get a visibility tracer.

`MitsubaVisibility` implements ``methods.core.visibility.RayCaster`` — the interface of the
embreex `Visibility` (`occluded`, `intersect`, `visible`, ``V``, ``F``, ``scale``) — on one Mitsuba
scene holding the mesh. It exists beside the core's tracer because the core is renderer-free (it
may not import Mitsuba) while Mitsuba's vectorised variants trace a whole batch in one call
(Embree ray packets over Dr.Jit's thread pool) instead of embreex's one Embree call per ray.

`make_visibility(V, F, backend=...)` returns one or the other:

* ``"mitsuba"`` — `MitsubaVisibility`; needs a vectorised variant (``llvm_*``/``cuda_*``,
  ``references.mitsuba_setup.ensure_variant``), else a RuntimeError;
* ``"embree"`` — ``methods.core.visibility.Visibility`` (embreex);
* ``"auto"`` (default) — Mitsuba when the active variant is vectorised, else embreex (with
  ``scalar_rgb`` Mitsuba traces one ray per Python-level call: far slower than embreex).

The backend comes from the ``backend`` argument, else the environment variable
``PRTBENCH_VISIBILITY`` (``auto`` | ``mitsuba`` | ``embree``), else ``auto``; `resolve_backend`
says which one a call will use and `backend_id` names it with its version, for run records.

Same rays, same hits: both tracers start a ray at t = 0 on the segment convention of
``RayCaster._prepare`` and both run Embree's robust (watertight) traversal — Mitsuba's is switched
on here, its default fast mode leaks rays through shared edges —, so they disagree only on rays
that graze an edge or a surface within float32 round-off (``tests/references/
test_visibility_mitsuba.py`` measures it on every library scene). Mitsuba's answer for a ray
depends only on that ray: the same rays give the same hits whatever the chunking, their order in a
batch and Dr.Jit's thread count (tested). Dr.Jit's thread pool is process-wide
(``drjit.set_thread_count``), so the ``threads`` argument of the interface is accepted and ignored.
"""
from __future__ import annotations

import math
import os
from typing import Any

import numpy as np

from methods.core.visibility import RayCaster, Visibility
from references.mitsuba_setup import ensure_variant

__all__ = ["BACKENDS", "ENV_VAR", "MitsubaVisibility", "backend_id", "make_visibility", "mitsuba_usable",
           "resolve_backend"]

ENV_VAR = "PRTBENCH_VISIBILITY"
BACKENDS = ("auto", "mitsuba", "embree")
# Rays per Dr.Jit batch: bounds the arrays Dr.Jit holds at once (a ray is 7 float32 + the answer,
# ~32 B in Dr.Jit plus the numpy copies) to ~100 MB per chunk.
DEFAULT_CHUNK_RAYS = 1 << 21


def mitsuba_usable() -> bool:
    """True when Mitsuba's active variant traces batches (``llvm_*`` or ``cuda_*``)."""
    try:
        v = ensure_variant()
    except Exception:  # pragma: no cover - no usable Mitsuba at all
        return False
    return v.startswith(("llvm", "cuda"))


def resolve_backend(backend: str | None = None) -> str:
    """``"mitsuba"`` or ``"embree"``: the tracer `make_visibility` builds for `backend` (None: the
    environment variable ``PRTBENCH_VISIBILITY``, else ``"auto"``)."""
    name = "backend"
    if backend is None:
        backend, name = os.environ.get(ENV_VAR, "").strip().lower() or "auto", ENV_VAR
    if backend not in BACKENDS:
        raise ValueError(f"{name} must be one of {BACKENDS}, got {backend!r}")
    if backend == "auto":
        return "mitsuba" if mitsuba_usable() else "embree"
    return backend


def backend_id(backend: str | None = None) -> str:
    """The resolved backend with its version, e.g. ``"mitsuba 3.9.1 llvm_ad_rgb"`` or
    ``"embreex 4.4.0.post1"`` — what a run record or a cache key should carry."""
    from importlib import metadata

    b = resolve_backend(backend)
    if b == "mitsuba":
        import mitsuba as mi

        return f"mitsuba {mi.__version__} {ensure_variant()}"
    try:
        return f"embreex {metadata.version('embreex')}"
    except metadata.PackageNotFoundError:  # pragma: no cover
        return "embreex"


def make_visibility(V: Any, F: Any, *, backend: str | None = None, **kwargs) -> RayCaster:
    """A visibility tracer over the mesh (V (N, 3), F (M, 3)), torch or numpy.

    Args:
        backend: "auto" | "mitsuba" | "embree" (None: ``$PRTBENCH_VISIBILITY``, else "auto").
        kwargs: passed to the backend's constructor (``robust`` for both, ``threads`` for
            embreex, ``chunk_rays`` for Mitsuba).
    Returns:
        `MitsubaVisibility` or ``methods.core.visibility.Visibility``; its ``backend`` attribute
        names it.
    """
    b = resolve_backend(backend)
    return MitsubaVisibility(V, F, **kwargs) if b == "mitsuba" else Visibility(V, F, **kwargs)


class MitsubaVisibility(RayCaster):
    """One Mitsuba scene over one triangle mesh; rays traced in chunks by ``scene.ray_test``
    (shadow rays) and ``scene.ray_intersect_preliminary`` (closest hits).

    Args:
        V: (N, 3) vertex positions; F: (M, 3) triangle vertex indices (torch or numpy).
        robust: Embree's robust (watertight) traversal, Mitsuba's scene flag
            ``embree_use_robust_intersections``; default True, as the embreex tracer. Mitsuba's
            own default (False, the fast mode) lets rays through shared edges and vertices, which
            structured rays (from vertices along axis and diagonal directions) hit often
            (mitsuba3 issue #1149); robust mode closes them (tested).
        chunk_rays: rays per Dr.Jit batch (bounds memory; results do not depend on it).
    """

    backend = "mitsuba"

    def __init__(self, V: Any, F: Any, *, robust: bool = True, chunk_rays: int = DEFAULT_CHUNK_RAYS):
        if int(chunk_rays) < 1:
            raise ValueError(f"chunk_rays must be >= 1, got {chunk_rays}")
        super().__init__(V, F)
        variant = ensure_variant()
        if not variant.startswith(("llvm", "cuda")):
            raise RuntimeError(f"MitsubaVisibility needs a vectorised Mitsuba variant (llvm_*/cuda_*), the "
                               f"active one is {variant}; use backend='embree'")
        import mitsuba as mi

        self.chunk_rays = int(chunk_rays)
        self.variant = variant
        mesh = mi.Mesh("prtbench_visibility", vertex_count=self.V.shape[0], face_count=self.F.shape[0],
                       has_vertex_normals=False, has_vertex_texcoords=False)
        p = mi.traverse(mesh)
        p["vertex_positions"] = mi.Float(self.V.ravel())
        p["faces"] = mi.UInt32(self.F.astype(np.uint32).ravel())
        p.update()
        self.robust = bool(robust)
        self._scene = mi.load_dict({"type": "scene", "mesh": mesh,  # builds the BVH once
                                    "embree_use_robust_intersections": self.robust})

    def _rays(self, o: np.ndarray, d: np.ndarray, seg: np.ndarray):
        """Dr.Jit rays of one chunk: o, d (R, 3), seg (R,) or 0-d → mi.Ray3f with maxt = seg."""
        import drjit as dr
        import mitsuba as mi

        ray = mi.Ray3f(dr.unravel(mi.Point3f, mi.Float(np.ascontiguousarray(o).ravel())),
                       dr.unravel(mi.Vector3f, mi.Float(np.ascontiguousarray(d).ravel())))
        if seg.ndim:
            ray.maxt = mi.Float(np.ascontiguousarray(seg))
        elif np.isfinite(seg):  # else Mitsuba's default maxt (the largest float) = unbounded
            ray.maxt = mi.Float(float(seg))
        return ray

    def occluded(self, origins: Any, dirs: Any, tnear: Any = 0.0, tfar: Any = math.inf, *,
                 threads: int | None = None) -> Any:
        """Shadow-ray test: is any triangle hit at t ∈ (tnear, tfar)?

        Args:
            origins: (R, 3); dirs: (R, 3) ray directions (t in units of |d|).
            tnear, tfar: scalars or (R,) segment bounds; threads: ignored (Dr.Jit's pool).
        Returns:
            (R,) bool, True where the segment is blocked (torch on origins' device, or numpy).
        """
        o, d, _, seg = self._prepare(origins, dirs, tnear, tfar)
        R = o.shape[0]
        hit = np.zeros(R, bool)
        for a in range(0, R, self.chunk_rays):
            b = min(R, a + self.chunk_rays)
            hit[a:b] = self._scene.ray_test(self._rays(o[a:b], d[a:b], seg[a:b] if seg.ndim else seg)).numpy()
        return self._wrap(hit, origins)

    def intersect(self, origins: Any, dirs: Any, tnear: Any = 0.0, tfar: Any = math.inf, *,
                  threads: int | None = None):
        """Closest hit along each ray (``ray_intersect_preliminary``).

        Args:
            origins: (R, 3); dirs: (R, 3); tnear, tfar: scalars or (R,); threads: ignored.
        Returns:
            t (R,) float32 (inf on a miss), face (R,) int64 (−1 on a miss), u (R,), v (R,) float32
            barycentrics in Mitsuba's prim_uv convention p = (1−u−v)p0 + u p1 + v p2 (0 on a miss).
        """
        import drjit as dr

        o, d, tn, seg = self._prepare(origins, dirs, tnear, tfar)
        R = o.shape[0]
        t = np.full(R, np.inf, np.float32)
        face = np.full(R, -1, np.int64)
        u = np.zeros(R, np.float32)
        v = np.zeros(R, np.float32)
        for a in range(0, R, self.chunk_rays):
            b = min(R, a + self.chunk_rays)
            pi = self._scene.ray_intersect_preliminary(self._rays(o[a:b], d[a:b], seg[a:b] if seg.ndim else seg))
            valid = pi.is_valid()
            dr.eval(pi.t, pi.prim_index, pi.prim_uv, valid)
            ok = valid.numpy()
            t[a:b] = pi.t.numpy()
            face[a:b] = np.where(ok, pi.prim_index.numpy().astype(np.int64), -1)
            u[a:b] = pi.prim_uv.x.numpy()
            v[a:b] = pi.prim_uv.y.numpy()
        return self._hits(origins, tn, t, face, u, v)
