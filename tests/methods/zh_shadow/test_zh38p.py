"""Session 38 (zh38p): the vertex-shaded frames' resolve with a pixel's 2×2 samples as one AVX-512 vector
(`native.resolve_vector`, ``VECTOR_RESOLVE``) against `native.resolve_table` (its oracle, the same bits).
The kernel alone against `gouraud.resolve`: `test_fast.test_resolve_native_equals_gouraud_resolve`."""
from __future__ import annotations


import pytest
import torch

from methods.zh_shadow import ZHShadow
from methods.zh_shadow import native as zn
from testing.gbuffers import knock_out

def test_vector_resolve_frames_equal_table_resolve(order8, monkeypatch):
    """Order-8 vertex-shaded frames (P, V, VB, VL, VBL, L; with misses; at 1 and 2 threads) with the vector
    resolve = with `resolve_table` (``VECTOR_RESOLVE`` off) bit for bit, the vector loop taken once per frame
    that resolves per sample (a lighting-only frame after the first reads the kept matrix). A sum in another
    order, a miss sample's garbage added, a wrong corner or channel breaks the image."""
    from methods.core.threads import torch_threads
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    if zn._vresolve_lib() is None:
        pytest.skip("no AVX-512 host or no C compiler")
    monkeypatch.setattr(zn, "MIN_RESOLVE_PIXELS_PER_THREAD", 1)   # (test size: split over 2 threads too)
    calls = []
    rv = zn.resolve_vector
    monkeypatch.setattr(zn, "resolve_vector", lambda *a: calls.append(1) or rv(*a))
    for kind in ("P", "V", "VB", "VL", "VBL", "L"):
        fast, fast2, slow = order8.with_render_config(), order8.with_render_config(), order8.with_render_config()
        for i, f in enumerate(make_sequence(order8.scene, kind, 3, seed=5)):
            gb = make_gbuffer(order8.scene, f, 2)
            if i == 2:
                gb = knock_out(gb, 7, 3)
            c0 = len(calls)
            a = fast.render(f, gb)
            with torch_threads(2):
                a2 = fast2.render(f, gb)
            monkeypatch.setattr(zn, "VECTOR_RESOLVE", False)
            b = slow.render(f, gb)
            monkeypatch.setattr(zn, "VECTOR_RESOLVE", True)
            assert torch.equal(a, b), (kind, i, float((a - b).abs().max()))
            assert torch.equal(a2, b), (kind, i)
            if kind != "L" or i == 0:
                assert len(calls) == c0 + 3, (kind, i)   # (three renders, each the vector loop; off: None)


@pytest.mark.parametrize("name,size", [("creature", "test"), ("character", "test"), ("creature", "bench")])
def test_vector_skin_equals_skin(name, size, monkeypatch):
    """`native.skin_vector` (16 vertices a vector, the weights joint-major) = `native.skin` bit for bit — the
    rest pose, random poses, ±π on every joint (flat blended maps), the ranges' tails of fewer than 16 vertices
    — at 1 and 2 threads (bench: the range split over the team), and `ZHShadow._posed_geometry` takes it (off:
    `skin`, the same geometry). A lost tail, a wrong cofactor, weight or order breaks it."""
    from methods.core.threads import torch_threads
    from scenes.library import get_scene

    if zn._vskin_lib() is None:
        pytest.skip("no AVX-512 host or no C compiler")
    scene = get_scene(name, size)
    st = zn.skin_setup(scene)
    vs = zn.skin_vector_setup(st)
    J = scene.skeleton.num_joints
    g = torch.Generator().manual_seed(11)
    poses = [torch.zeros(J), torch.full((J,), torch.pi), torch.full((J,), -torch.pi),
             *((torch.rand(J, generator=g) * 2 - 1) * s for s in (0.3, 1.0, 2.5))]
    for pose in poses:
        pose = pose.float()
        V, N = zn.skin(st, pose)
        Vv, Nv = zn.skin_vector(st, vs, pose)
        assert torch.equal(V, Vv) and torch.equal(N, Nv), pose
        with torch_threads(2):
            V2, N2 = zn.skin_vector(st, vs, pose)
        assert torch.equal(V, V2) and torch.equal(N, N2), pose
    calls = []
    sv = zn.skin_vector
    monkeypatch.setattr(zn, "skin_vector", lambda *a: calls.append(1) or sv(*a))
    m = ZHShadow(order=8, shading="vertex", specular="cosine")
    m.scene = scene
    m.bound_calls = False   # (the bound call, `native.SkinBound`: below)
    pose = poses[4].float()
    geom = m._posed_geometry(pose, tuple(pose.tolist()))
    assert len(calls) == 1 and torch.equal(geom.V, zn.skin(st, pose)[0]) and torch.equal(geom.N, zn.skin(st, pose)[1])
    mb = ZHShadow(order=8, shading="vertex", specular="cosine")
    mb.scene = scene
    gb = mb._posed_geometry(pose, tuple(pose.tolist()))
    assert len(calls) == 1 and mb._skin[3] is not None   # (zh41p: the bound call, not `skin_vector`)
    assert torch.equal(gb.V, geom.V) and torch.equal(gb.N, geom.N)
    monkeypatch.setattr(zn, "VECTOR_SKIN", False)
    assert zn.skin_vector(st, vs, pose) is None
    geom2 = ZHShadow(order=8, shading="vertex", specular="cosine")
    geom2.scene = scene
    g2 = geom2._posed_geometry(pose, tuple(pose.tolist()))
    assert torch.equal(g2.V, geom.V) and torch.equal(g2.N, geom.N)


def test_zh38p_libraries_follow_the_off_switch(monkeypatch):
    """The session-38 libraries follow PRTBENCH_COMPILE at each call (not lru-cached: b541a75): None while it is
    0 (then `skin_vector` / `resolve_vector` return None: the callers' `skin` / `resolve_table` path), loaded
    once it is back on; and a full-change frame loads them for the P frames after it (`warm_pose_libraries`)."""
    from methods.core import native as core_native
    from scenes.library import get_scene

    if zn._vskin_lib() is None or zn._vresolve_lib() is None:
        pytest.skip("no AVX-512 host or no C compiler")
    scene = get_scene("creature", "test")
    st = zn.skin_setup(scene)
    vs = zn.skin_vector_setup(st)
    pose = torch.zeros(scene.skeleton.num_joints)
    N, M, H, W = 30, 40, 4, 6
    F = torch.randint(0, N, (M, 3))
    face, hit = torch.randint(0, M, (H * W * 4,)), torch.ones(H * W * 4, dtype=torch.bool)
    args = (torch.randn(N, 3), F, face, torch.rand(2, H * W * 4).T * 0.5, hit, H, W, 2)
    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    assert zn._vskin_lib() is None and zn._vresolve_lib() is None
    assert zn.skin_vector(st, vs, pose) is None and zn.resolve_vector(*args) is None
    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    assert zn.skin_vector(st, vs, pose) is not None and zn.resolve_vector(*args) is not None
    names = []
    load = core_native.load
    monkeypatch.setattr(core_native, "load", lambda name, *a, **k: names.append(name) or load(name, *a, **k))
    zn.warm_pose_libraries()
    assert {"zh38p_skin", "zh38p_resolve"} <= set(names)
