"""Scene + Frame → Mitsuba: shapes, buffers, BSDFs, emitter, sensor, integrator."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from references.mitsuba_setup import ensure_variant
from references import export

# Exported buffers are float32 copies of float32 tensors: exact.
EXACT = 0.0
# Env map: bilinear lookups in float32 (Mitsuba) vs torch float32 — a few ulps of radiance ~ 1–50.
ENV_RTOL = 1e-4


def _small(name="sphere_plane", W=16, H=12):
    from scenes.library import get_scene

    sc = get_scene(name, "test")
    return sc.replace(camera=dataclasses.replace(sc.camera, width=W, height=H))


@pytest.fixture(scope="module")
def mi():
    ensure_variant()
    import mitsuba

    return mitsuba


# Plugin vs torch BSDF in float32 (tested to float32 precision by the plugin's own tests).
BSDF_RTOL = 1e-4
# Fixed local direction pairs (z = normal): wi towards the light, wo towards the viewer.
_WI = torch.nn.functional.normalize(torch.tensor([[0.3, 0.1, 0.9], [-0.5, 0.2, 0.6], [0.1, -0.7, 0.5]]), dim=1)
_WO = torch.nn.functional.normalize(torch.tensor([[-0.3, -0.1, 0.9], [0.4, 0.1, 0.8], [0.0, 0.2, 0.9]]), dim=1)


def _bsdf_eval(mi, bsdf):
    import drjit as dr

    si = dr.zeros(mi.SurfaceInteraction3f, _WI.shape[0])
    si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    si.wi = mi.Vector3f(*(mi.Float(_WO[:, k].numpy()) for k in range(3)))  # Mitsuba wi = our wo
    wo = mi.Vector3f(*(mi.Float(_WI[:, k].numpy()) for k in range(3)))
    return np.array(bsdf.eval(mi.BSDFContext(), si, wo)).reshape(3, -1).T


def _torch_eval(mat):
    return (mat.eval(_WI, _WO) * _WI[:, 2:3]).numpy()


def _buffers(mi, shape):
    p = mi.traverse(shape)
    V = np.array(p["vertex_positions"]).reshape(-1, 3)
    N = np.array(p["vertex_normals"]).reshape(-1, 3)
    F = np.array(p["faces"]).reshape(-1, 3)
    return V, N, F


def test_shapes_round_trip(mi):
    sc = _small()
    fr = sc.default_frame()
    d = export.to_mitsuba(sc, fr, max_depth=2, spp=4, seed=3)
    m = mi.load_dict(d)
    g = sc.geometry()
    assert len(m.shapes()) == len(sc.shapes)
    assert list(export.shape_indices(m)) == list(range(len(sc.shapes)))
    for ms in m.shapes():
        i = export.shape_index_of(ms)
        v0, v1 = int(g.vertex_offset[i]), int(g.vertex_offset[i + 1])
        f0, f1 = int(g.face_offset[i]), int(g.face_offset[i + 1])
        assert ms.vertex_count() == v1 - v0 and ms.face_count() == f1 - f0
        V, N, F = _buffers(mi, ms)
        assert np.array_equal(V, g.V[v0:v1].numpy())
        assert np.array_equal(N, g.N[v0:v1].numpy())  # our normals, not Mitsuba's
        assert np.array_equal(F.astype(np.int64), (g.F[f0:f1] - v0).numpy())
        assert ms.has_vertex_normals()
        # the shape's BSDF is its region's material: Mitsuba eval (f·cos, local frame) = torch f·cos
        mat = fr.materials[sc.shapes[i].region]
        assert np.allclose(_bsdf_eval(mi, ms.bsdf()), _torch_eval(mat), rtol=BSDF_RTOL, atol=1e-6)


def test_posed_geometry_is_exported(mi):
    sc = _small("creature")
    pose = torch.full((sc.skeleton.num_joints,), 0.3)
    fr = sc.default_frame(pose=pose)
    m = mi.load_dict(export.geometry_dict(sc, fr))
    g = sc.geometry(pose)
    V = np.concatenate([_buffers(mi, s)[0] for s in m.shapes()])
    N = np.concatenate([_buffers(mi, s)[1] for s in m.shapes()])
    assert np.array_equal(V, g.V.numpy()) and np.array_equal(N, g.N.numpy())
    assert not np.array_equal(V, sc.geometry().V.numpy())


def test_emitter_equals_our_envmap(mi):
    import drjit as dr

    from scenes.envmap import EnvMap

    sc = _small()
    # rotate the lighting so to_world is not the identity
    a = 0.7
    R = torch.tensor([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]], dtype=torch.float32)
    env = sc.envmap.rotated(R)
    fr = dataclasses.replace(sc.default_frame(), envmap=env)
    m = mi.load_dict(export.to_mitsuba(sc, fr, max_depth=2, spp=1, seed=0))
    emitter = m.environment()
    assert emitter is not None and len(m.emitters()) == 1
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(2000, 3, generator=g), dim=1)
    si = dr.zeros(mi.SurfaceInteraction3f, d.shape[0])
    si.wi = mi.Vector3f(*(mi.Float(-d[:, k].numpy()) for k in range(3)))  # wi points away from the emitter
    got = np.array(emitter.eval(si)).reshape(3, -1).T
    want = env.radiance(d).numpy()
    assert np.allclose(got, want, rtol=ENV_RTOL, atol=ENV_RTOL * float(want.max()))


def test_sensor_integrator_and_validation(mi):
    sc = _small(W=10, H=6)
    fr = sc.default_frame()
    d = export.to_mitsuba(sc, fr, max_depth=-1, spp=8, seed=5)
    assert d["integrator"] == {"type": "path", "max_depth": -1, "hide_emitters": True}
    assert d["sensor"]["sampler"] == {"type": "independent", "sample_count": 8, "seed": 5}
    assert d["sensor"]["film"]["rfilter"] == {"type": "box"}
    m = mi.load_dict(d)
    s = m.sensors()[0]
    assert tuple(s.film().crop_size()) == (10, 6)
    assert s.sampler().sample_count() == 8
    for bad in (dict(max_depth=0), dict(max_depth=-2), dict(spp=0), dict(seed=-1)):
        kw = dict(max_depth=2, spp=1, seed=0) | bad
        with pytest.raises(ValueError):
            export.to_mitsuba(sc, fr, **kw)
    fr2 = dataclasses.replace(fr, materials={})
    with pytest.raises(ValueError, match="material"):
        export.to_mitsuba(sc, fr2, max_depth=2, spp=1, seed=0)


def test_make_mesh_validates():
    V = torch.zeros(3, 3)
    with pytest.raises(ValueError):
        export.make_mesh("x", V, torch.tensor([[0, 1, 3]]), torch.zeros(3, 3))
    with pytest.raises(ValueError):
        export.make_mesh("x", V, torch.tensor([[0, 1, 2]]), torch.zeros(2, 3))
