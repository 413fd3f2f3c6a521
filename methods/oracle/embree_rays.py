"""The oracle's own shadow-ray tracer (issue 14, session 34): an Embree scene of the oracle's, built on
the Embree library Mitsuba ships (``mitsuba/libembree3.so``, its API called through ctypes) with a
*dynamic* build for a deforming mesh, and its rays traced by a C loop handing the live rays of the (3, K, Q)
component planes of `methods.oracle.native_rays` to Embree's stream entry point ``rtcOccluded1M``.

Why: (1) Mitsuba builds its scene's BVH at ``RTC_BUILD_QUALITY_HIGH`` (``Scene::accel_init_cpu``) and offers
no way to change it, so writing a new pose into its scene (``methods.oracle._repose``) costs a full
build (~11 ms CPU of a creature bench pose, 26 560 triangles, 1 thread). Here the scene is built once at
``RTC_BUILD_QUALITY_LOW`` with ``RTC_SCENE_FLAG_DYNAMIC`` (Embree's two-level build) and the mesh's own BVH
at `QUALITY` (``RTC_BUILD_QUALITY_REFIT``: the first pose's SAH tree, whose bounds a new pose refits,
~1.2 ms). (2) Mitsuba's ``ray_test`` traces 16-ray packets of consecutive rays (Dr.Jit's width), the rays
that are not live masked off; a stream of the live rays alone lets Embree form its own packets
(`_SOURCE`): creature bench, 1 thread, captured rays traced alternately, P 72 ms against Mitsuba's 85
(its tracer of each pose, HIGH), V 66 against 75.

The same answers: the scene takes Mitsuba's flag ``RTC_SCENE_FLAG_ROBUST`` (``MitsubaVisibility``'s
``robust=True``: watertight triangle tests, conservative box tests), so whether a ray is blocked
depends on that ray and the triangles only — not on the tree built over them, nor on the rays traced
with it; the rays are Mitsuba's ``ray_test``'s (tnear 0, tfar the largest float, time, mask, id and flags
0), blocked where Embree set tfar to −∞ (``tfar != FLT_MAX``), in the same library.
``tests/methods/test_oracle_embree.py`` compares the blocked flags with Mitsuba's tracer, bit for bit, on
posed and rest-pose frames, and the images of whole sequences.

`EmbreeTracer.create` returns None — the caller then takes Mitsuba's tracer — when the C loops are not
built (no compiler, ``PRTBENCH_COMPILE=0``), the library or one of its entry points is not found, or
Embree reports an error.
"""
from __future__ import annotations

import ctypes
import os

import numpy as np
import torch
from torch import Tensor

from methods.core import native

# The per-mesh BVH's build quality (the scene's is LOW: Embree's two-level dynamic build, which builds
# each mesh at its own quality). Creature bench P, 1 thread, process CPU, 8 posed frames' captured rays
# traced alternately (medians): REFIT (the first pose's SAH tree, its bounds refitted) a pose 1.2 ms
# (update included), its rays 88.7 ms; HIGH in a one-level scene (Mitsuba's build) 13.7 ms and 83.8 ms
# (Mitsuba's own tracer: 84.1 ms); LOW (a Morton build) ~2 ms and ~160 ms.
QUALITY = 3  # RTC_BUILD_QUALITY_REFIT
_SCENE_QUALITY = 0  # RTC_BUILD_QUALITY_LOW
_SCENE_FLAGS = 1 | 4  # RTC_SCENE_FLAG_DYNAMIC | RTC_SCENE_FLAG_ROBUST
_TRIANGLE, _INDEX, _VERTEX = 0, 0, 1  # RTC_GEOMETRY_TYPE_TRIANGLE, RTC_BUFFER_TYPE_INDEX / _VERTEX
_FLOAT3, _UINT3 = 0x9003, 0x5003  # RTC_FORMAT_FLOAT3, RTC_FORMAT_UINT3

_SOURCE = r"""
#include <stdint.h>
#include <float.h>
#include <string.h>
#include <stdlib.h>

typedef struct { uint32_t flags; void *filter; uint32_t inst_id[1]; } Context;  /* RTCIntersectContext */
typedef struct __attribute__((aligned(16))) {                                  /* RTCRay */
    float org_x, org_y, org_z, tnear, dir_x, dir_y, dir_z, time, tfar;
    uint32_t mask, id, flags;
} Ray;
typedef void (*occluded1m_fn)(void *scene, Context *ctx, Ray *ray, unsigned M, size_t stride);

#define CHUNK 4096  /* rays per stream (a 4096-ray chunk of the planes, its live rays) */

/* blocked[i] = live[i] && the ray (o, d)[i] hits a triangle at t in (0, FLT_MAX), for i < n; o, d (3, n)
   component planes PS apart. The live rays of each chunk of CHUNK rays go to rtcOccluded1M as one stream of
   Mitsuba's ray_test's rays (tnear 0, tfar the largest float; time, mask, id, flags 0; an incoherent
   context), blocked where Embree set tfar to -inf; each chunk traced by one thread (any team size
   gives the same answers). */
void occluded(void *fn, void *scene, const uint8_t *live, const float *o, const float *d, int64_t PS,
              int64_t n, uint8_t *blocked, int32_t nt)
{
    occluded1m_fn occ = (occluded1m_fn) fn;
    int64_t nc = (n + CHUNK - 1) / CHUNK;
#pragma omp parallel num_threads(nt)
    {
        Ray *r = (Ray *) aligned_alloc(64, sizeof(Ray) * CHUNK);
        int32_t *idx = (int32_t *) malloc(sizeof(int32_t) * CHUNK);
#pragma omp for schedule(dynamic, 4)
        for (int64_t c = 0; c < nc; ++c) {
            Context ctx = {0, 0, {0xFFFFFFFFu}};
            int64_t a = c * CHUNK, b = a + CHUNK < n ? a + CHUNK : n;
            int m = 0;
            for (int64_t i = a; i < b; ++i) {
                blocked[i] = 0;
                if (!live[i])
                    continue;
                Ray x = {o[i], o[PS + i], o[2 * PS + i], 0.f, d[i], d[PS + i], d[2 * PS + i], 0.f, FLT_MAX, 0, 0, 0};
                idx[m] = (int32_t) (i - a);
                r[m++] = x;
            }
            if (m)
                occ(scene, &ctx, r, (unsigned) m, sizeof(Ray));
            for (int j = 0; j < m; ++j)
                blocked[a + idx[j]] = r[j].tfar != FLT_MAX;
        }
        free(r);
        free(idx);
    }
}
"""
_P, _I = ctypes.c_void_p, ctypes.c_int64
_SIGNATURES = {"occluded": [_P, _P, _P, _P, _P, _I, _I, _P, ctypes.c_int32]}

# Embree's entry points: (name, result, arguments); looked up as C names or, in Mitsuba's build (Embree in
# the C++ namespace ``mitsuba``), by their mangled names.
_API = {
    "rtcNewDevice": (_P, [ctypes.c_char_p], "PKc"),
    "rtcGetDeviceError": (ctypes.c_int, [_P], "PNS_11RTCDeviceTyE"),
    "rtcNewScene": (_P, [_P], "PNS_11RTCDeviceTyE"),
    "rtcSetSceneFlags": (None, [_P, ctypes.c_int], "PNS_10RTCSceneTyENS_13RTCSceneFlagsE"),
    "rtcSetSceneBuildQuality": (None, [_P, ctypes.c_int], "PNS_10RTCSceneTyENS_15RTCBuildQualityE"),
    "rtcNewGeometry": (_P, [_P, ctypes.c_int], "PNS_11RTCDeviceTyENS_15RTCGeometryTypeE"),
    "rtcSetGeometryBuildQuality": (None, [_P, ctypes.c_int], "PNS_13RTCGeometryTyENS_15RTCBuildQualityE"),
    "rtcSetSharedGeometryBuffer": (None, [_P, ctypes.c_int, ctypes.c_uint, ctypes.c_int, _P, ctypes.c_size_t,
                                          ctypes.c_size_t, ctypes.c_size_t],
                                   "PNS_13RTCGeometryTyENS_13RTCBufferTypeEjNS_9RTCFormatEPKvmmm"),
    "rtcUpdateGeometryBuffer": (None, [_P, ctypes.c_int, ctypes.c_uint], "PNS_13RTCGeometryTyENS_13RTCBufferTypeEj"),
    "rtcCommitGeometry": (None, [_P], "PNS_13RTCGeometryTyE"),
    "rtcAttachGeometry": (ctypes.c_uint, [_P, _P], "PNS_10RTCSceneTyEPNS_13RTCGeometryTyE"),
    "rtcReleaseGeometry": (None, [_P], "PNS_13RTCGeometryTyE"),
    "rtcCommitScene": (None, [_P], "PNS_10RTCSceneTyE"),
    "rtcReleaseScene": (None, [_P], "PNS_10RTCSceneTyE"),
}
_STATE: dict = {}  # "api": {name: function} or None, "device": the Embree device, "occluded1m": its address


def _lib():
    # not cached here (`native.load` caches the build; a None under PRTBENCH_COMPILE=0 must not stick)
    return native.load("oracle_embree", _SOURCE, _SIGNATURES,
                       extra_flags=("-fopenmp", *native.isa_flags()))


def _api():
    """Embree's entry points in Mitsuba's ``libembree3.so`` (``{name: ctypes function}``, with the device and
    ``rtcOccluded1M``'s address in `_STATE`), or None: not found."""
    if "api" in _STATE:
        return _STATE["api"]
    _STATE["api"] = None
    try:
        import mitsuba

        lib = ctypes.CDLL(os.path.join(os.path.dirname(mitsuba.__file__), "libembree3.so"))
        api = {}
        for name, (res, args, sig) in {**_API, "rtcOccluded1M": (None, [], "PNS_10RTCSceneTyEPNS_19RTCIntersectContextEPNS_6RTCRayEjm")}.items():
            mangled = f"_ZN7mitsuba{len(name)}{name}E{sig}"
            fn = getattr(lib, name) if hasattr(lib, name) else getattr(lib, mangled)
            fn.restype, fn.argtypes = res, args
            api[name] = fn
    except (OSError, AttributeError, ImportError):
        return None
    dev = api["rtcNewDevice"](b"threads=1")
    if not dev or api["rtcGetDeviceError"](dev):
        return None
    _STATE.update(api=api, device=dev, occluded1m=ctypes.cast(api["rtcOccluded1M"], ctypes.c_void_p).value)
    return api


class EmbreeTracer:
    """An Embree scene over one triangle mesh (V (N, 3), F (M, 3)) whose vertices a new pose rewrites
    (`repose`: the same faces), and `trace` of component-plane rays (module docstring)."""

    backend = "embree-own"

    def __init__(self, api, lib, V: np.ndarray, F: np.ndarray) -> None:
        self._api, self._lib = api, lib
        self.F = np.ascontiguousarray(F, dtype=np.uint32)
        # one spare vertex: Embree reads a vertex buffer's last element with a 16-byte load
        self._V = np.zeros((V.shape[0] + 1, 3), np.float32)
        self._V[:-1] = V
        dev = _STATE["device"]
        self._scene = api["rtcNewScene"](dev)
        api["rtcSetSceneFlags"](self._scene, _SCENE_FLAGS)
        api["rtcSetSceneBuildQuality"](self._scene, _SCENE_QUALITY)
        g = self._geom = api["rtcNewGeometry"](dev, _TRIANGLE)
        api["rtcSetGeometryBuildQuality"](g, QUALITY)
        api["rtcSetSharedGeometryBuffer"](g, _VERTEX, 0, _FLOAT3, self._V.ctypes.data, 0, 12, V.shape[0])
        api["rtcSetSharedGeometryBuffer"](g, _INDEX, 0, _UINT3, self.F.ctypes.data, 0, 12, self.F.shape[0])
        api["rtcCommitGeometry"](g)
        api["rtcAttachGeometry"](self._scene, g)
        api["rtcCommitScene"](self._scene)
        self.ok = not api["rtcGetDeviceError"](dev)

    @classmethod
    def create(cls, V: Tensor, F: Tensor) -> "EmbreeTracer | None":
        """A tracer of the mesh, or None (module docstring: the caller takes Mitsuba's)."""
        lib, api = _lib(), _api()
        if lib is None or api is None or V.dim() != 2 or F.dim() != 2 or V.shape[1] != 3 or F.shape[1] != 3:
            return None
        Vn = V.detach().cpu().numpy()
        if not np.isfinite(Vn).all() or F.shape[0] == 0:
            return None
        t = cls(api, lib, Vn, F.detach().cpu().numpy())
        return t if t.ok else None

    def repose(self, V: Tensor, F: Tensor) -> bool:
        """The vertex positions V of a new pose of the same faces F written into the scene and its BVH
        refitted / rebuilt (`QUALITY`); False, nothing changed, for another mesh or non-finite V."""
        if tuple(V.shape) != (self._V.shape[0] - 1, 3) or tuple(F.shape) != self.F.shape:
            return False
        Vn = V.detach().cpu().numpy()
        if not np.isfinite(Vn).all():
            return False
        if not np.array_equal(F.detach().cpu().numpy(), self.F):
            return False
        self._V[:-1] = Vn
        api = self._api
        api["rtcUpdateGeometryBuffer"](self._geom, _VERTEX, 0)
        api["rtcCommitGeometry"](self._geom)
        api["rtcCommitScene"](self._scene)
        return not api["rtcGetDeviceError"](_STATE["device"])

    def trace(self, live: Tensor, o: Tensor, d: Tensor, blocked: Tensor, threads: int) -> int:
        """``methods.oracle.native_rays.trace``'s contract: live (K, Q) bool contiguous, origins and directions
        (3, K, Q) component planes (each contiguous, ``stride(0)`` apart) → blocked (K, Q) (False where not
        live), the number of live rays."""
        n = live.numel()
        m = int(torch.count_nonzero(live))
        if not m:
            blocked.zero_()
            return 0
        assert o.stride(0) == d.stride(0) and live.is_contiguous() and blocked.is_contiguous()
        self._lib.occluded(_STATE["occluded1m"], self._scene, live.data_ptr(), o.data_ptr(), d.data_ptr(),
                           int(o.stride(0)), n, blocked.data_ptr(), int(threads))
        return m

    def __del__(self) -> None:
        try:
            self._api["rtcReleaseGeometry"](self._geom)
            self._api["rtcReleaseScene"](self._scene)
        except Exception:
            pass
