"""The pose path's C calls of session 35 (zh35o) against their oracles: the pose product for the needed
vertices alone (`native.pose_columns`, X laid out vertex-major) = the columns of `runtime._pose_product`
bit for bit; the skinning (`native.skin`) = `Scene.geometry` to float32 round-off; and P frames rendered
with both (the defaults) = with neither (``pose_columns`` / ``native_skinning`` off: `runtime.world_visibility`
and `Scene.geometry`) to float32 round-off, with the same counts, the same bits at 1 and 2 threads, and
= the reference."""
from __future__ import annotations

import pytest
import torch

from methods.zh_shadow import ZHShadow
from methods.zh_shadow import native as zn
from methods.zh_shadow import runtime as rt

RENDER_TOL = 1e-5   # (test_fast.py's: fast vs reference render)
SMALL = dict(train_poses=4, n_dirs=64, fit_iters=0)


def _skip_without_c_compiler() -> None:
    from methods.core import native as core_native

    if core_native.compiler() is None:   # pragma: no cover - no C compiler here
        pytest.skip("no C compiler")


@pytest.mark.parametrize("J1,N,d", [(11, 13415, 20), (5, 3001, 7), (1, 100, 33), (4, 2500, 256)])
def test_pose_columns_equal_product_columns(J1, N, d):
    """`native.pose_columns` of X laid out vertex-major (`native.vertex_major`) = `runtime._pose_product`'s
    columns (the product over every vertex in `world_visibility`'s point-minor layout) bit for bit: every
    vertex (idx None), a sorted subset, an unsorted one with repeats, an empty one; the same bits at 1 and 2
    threads; None for an id out of range, X not vertex-major, a of the wrong length."""
    from methods.core.threads import torch_threads

    _skip_without_c_compiler()
    g = torch.Generator().manual_seed(J1 * 1000 + d)
    X = torch.randn(J1, N, d, generator=g)
    a = torch.randn(J1, generator=g)
    Xv = zn.vertex_major(X)
    assert zn.is_vertex_major(Xv) and (J1 == 1 or not zn.is_vertex_major(X)) and torch.equal(Xv, X) and zn.vertex_major(Xv) is Xv
    full = rt._pose_product(a, rt.point_minor_model(X).transpose(1, 2).reshape(J1, d * N)).view(d, N)
    sub = torch.sort(torch.randperm(N, generator=g)[: N // 3]).values
    mixed = torch.randint(0, N, (N // 5 + 3,), generator=g)
    for idx in (None, sub, mixed, torch.zeros(0, dtype=torch.int64)):
        want = full if idx is None else full[:, idx]
        got = zn.pose_columns(Xv, a, idx)
        assert got is not None and got.shape == want.shape and torch.equal(got, want)
        with torch_threads(2):
            assert torch.equal(zn.pose_columns(Xv, a, idx), want)
    assert zn.pose_columns(Xv, a, torch.tensor([0, N])) is None
    assert zn.pose_columns(Xv, a, torch.tensor([-1])) is None
    if J1 > 1:
        assert zn.pose_columns(X, a) is None
    assert zn.pose_columns(Xv, a[:-1] if J1 > 1 else torch.ones(2)) is None


@pytest.mark.parametrize("name,size", [("creature", "test"), ("character", "test"), ("creature", "bench")])
def test_native_skin_equals_scene_geometry(name, size):
    """`native.skin` (forward kinematics and blend in one C call) = `Scene.geometry(pose)` to float32
    round-off at the rest pose, random poses and the extreme angles (±π), the unskinned shapes' rows
    bit for bit; the same bits at 1 and 2 threads; `ZHShadow._posed_geometry` = it too."""
    from methods.core.threads import torch_threads
    from scenes.library import get_scene

    _skip_without_c_compiler()
    scene = get_scene(name, size)
    st = zn.skin_setup(scene)
    assert st is not None
    J = scene.skeleton.num_joints
    g = torch.Generator().manual_seed(7)
    rest = scene.rest_geometry()
    skinned = torch.zeros(rest.num_vertices, dtype=torch.bool)
    for i, s in enumerate(scene.shapes):
        if s.name in scene.skin_weights:
            skinned[int(rest.vertex_offset[i]):int(rest.vertex_offset[i + 1])] = True
    assert skinned.any()
    scale = float(rest.V.abs().max())
    # (every joint at ±π folds some blended maps flat: their normals are ill-conditioned in any float32 path —
    # 0.49 apart on the character — so they are checked below for the path taken, not against the reference)
    poses = [torch.zeros(J), (torch.rand(J, generator=g) * 2 - 1) * 1.2, (torch.rand(J, generator=g) * 2 - 1) * 0.5]
    for pose in poses:
        pose = pose.float()
        want = scene.geometry(pose)
        V, N = zn.skin(st, pose)
        assert (V - want.V).abs().max() <= 4e-7 * scale, pose
        assert (N - want.N).abs().max() <= 1e-6, pose
        assert torch.equal(V[~skinned], want.V[~skinned]) and torch.equal(N[~skinned], want.N[~skinned])
        with torch_threads(2):
            V2, N2 = zn.skin(st, pose)
        assert torch.equal(V, V2) and torch.equal(N, N2)
    m = ZHShadow(order=8, shading="vertex", specular="cosine")
    m.scene = scene
    for pose in (poses[1], torch.full((J,), torch.pi), torch.full((J,), -torch.pi)):   # (±π: a valid pose)
        pose = pose.float()
        geom = m._posed_geometry(pose, tuple(pose.tolist()))
        V, N = zn.skin(st, pose)
        assert torch.equal(geom.V, V) and torch.equal(geom.N, N) and geom.F is rest.F
        assert (V - scene.geometry(pose).V).abs().max() <= 4e-7 * scale
    assert zn.skin(st, torch.zeros(J + 1)) is None
    with pytest.raises(ValueError):   # (an invalid pose: `Scene.geometry`'s check raises)
        m._posed_geometry(torch.full((J,), 4.0), (4.0,) * J)


@pytest.mark.parametrize("planes", [True, False])
def test_pose_frames_native_pose_path_equal_torch_path(zh_scene, monkeypatch, planes):
    """Vertex-shaded cosine P frames (the order-8 configuration) with the pose product for the front-facing,
    referenced vertices alone (``pose_columns``), the C skinning (``native_skinning``) and those vertices found
    by one C loop (``front_pass``) = with none (`runtime.world_visibility` over every vertex, `Scene.geometry`,
    the torch passes) to float32 round-off, the same counts,
    the same bits at 1 and 2 threads, = the reference; then a view frame of the last pose (every vertex's
    visibility: `_pose_state`'s full product, by `pose_columns` with every column) likewise."""
    import dataclasses

    from methods.core.threads import torch_threads
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _skip_without_c_compiler()
    if planes:
        monkeypatch.setattr(rt, "PLANAR_MIN_POINTS", 64)
    calls = {"cols": 0, "skin": 0, "front": 0}
    pc_, sk_, fc_ = zn.pose_columns, zn.skin, zn.front_columns
    monkeypatch.setattr(zn, "front_columns", lambda *a: calls.__setitem__("front", calls["front"] + 1) or fc_(*a))
    fr_ = zn.front_regions   # (zh43o: the same loop with the regions' bounds, `ZHShadow.lean_pose`; counted as it)
    monkeypatch.setattr(zn, "front_regions", lambda *a: calls.__setitem__("front", calls["front"] + 1) or fr_(*a))
    monkeypatch.setattr(zn, "pose_columns", lambda *a: calls.__setitem__("cols", calls["cols"] + 1) or pc_(*a))
    monkeypatch.setattr(zn, "skin", lambda *a: calls.__setitem__("skin", calls["skin"] + 1) or sk_(*a))
    sv_ = zn.skin_vector   # (session 38: the skinning by its vector loop first, `skin`'s bits; counted as it)
    monkeypatch.setattr(zn, "skin_vector", lambda *a: (calls.__setitem__("skin", calls["skin"] + 1) or sv_(*a))
                        if zn.VECTOR_SKIN and zn._vskin_lib() is not None else sv_(*a))
    sb_ = zn.SkinBound.__call__   # (session 41: the bound vector skinning, `native.SkinBound`; counted as it)
    monkeypatch.setattr(zn.SkinBound, "__call__", lambda self, *a: calls.__setitem__("skin", calls["skin"] + 1)
                        or sb_(self, *a))
    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    fast, fast2, slow = m.with_render_config(), m.with_render_config(), m.with_render_config()
    slow.pose_columns = slow.native_skinning = slow.front_pass = False
    for x in (fast, fast2, slow):
        x.plane_operators = planes
        x.native_eq1 = False   # (session 36's one call for the product and eq. 1: test_zh36o_pose.py)
    frames = list(make_sequence(m.scene, "P", 4, seed=5))
    view = list(make_sequence(m.scene, "V", 2, seed=5))[1]
    frames.append(dataclasses.replace(view, pose=frames[-1].pose, changed=frozenset({"view"})))
    for i, f in enumerate(frames):
        gb = make_gbuffer(m.scene, f, 2)
        c0 = dict(calls)
        a = fast.render(f, gb)
        assert zn.is_vertex_major(fast.model.X)   # (laid out for `pose_columns`; the slow object lays it back)
        if i > 0:
            p = 1 if i < len(frames) - 1 else 0   # (a P frame: a new pose, its front-facing vertices)
            assert calls["cols"] > c0["cols"] and calls["skin"] >= c0["skin"] + p and calls["front"] >= c0["front"] + p, i
        with torch_threads(2):
            a2 = fast2.render(f, gb)
        b = slow.render(f, gb)
        assert torch.equal(a, a2), i
        assert (a - b).abs().max() <= 2e-6 * b.abs().max(), i
        kind = "P" if i < len(frames) - 1 else "V"
        assert fast.frame_cost(kind, gb.num_samples) == slow.frame_cost(kind, gb.num_samples), i
        want = fast._render_reference(f, gb)
        assert (a - want).abs().max() <= RENDER_TOL, i


def test_vertex_frames_table_resolve_equal_own_resolve(zh_scene):
    """Vertex-shaded order-8 frames (P, V, VB, L) resolved by the face table (``table_resolve``) = by
    `native.resolve` (``table_resolve`` off) bit for bit, the table's path taken."""
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _skip_without_c_compiler()
    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    calls = []
    rt_ = zn.resolve_table
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(zn, "resolve_table", lambda *a: calls.append(1) or rt_(*a))
        mp.setattr(zn, "VECTOR_RESOLVE", False)   # (session 38's vector loop before it: `test_zh38p.py`)
        for kind in ("P", "V", "VB", "L"):
            fast, slow = m.with_render_config(), m.with_render_config()
            slow.table_resolve = False
            for f in make_sequence(m.scene, kind, 3, seed=2):
                gb = make_gbuffer(m.scene, f, 2)
                c0 = len(calls)
                a, b = fast.render(f, gb), slow.render(f, gb)
                assert torch.equal(a, b), (kind, f.index)
                if kind != "L" or f.index == 0:   # (a lighting-only frame resolves by the kept matrix)
                    assert len(calls) == c0 + 1, (kind, f.index)


def test_zh35o_libraries_follow_the_off_switch(zh_scene, monkeypatch):
    """The session-35 libraries follow PRTBENCH_COMPILE at each call (none lru-cached: b541a75): None while
    it is 0 — then a P frame renders by the fallbacks (`Scene.geometry`, the torch front test,
    `runtime.world_visibility` from X laid out point-minor again, `gouraud.resolve`), equal to the native
    frame to float32 round-off — and loaded once it is back on."""
    from methods.core import native as core_native
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _skip_without_c_compiler()
    getters = ("_pose_cols_lib", "_skin_lib", "_front_lib", "_tresolve_lib")
    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    frames = list(make_sequence(m.scene, "P", 3, seed=4))
    gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
    on = m.with_render_config()
    want = [on.render(f, g) for f, g in zip(frames, gbs)]
    assert zn.is_vertex_major(m.model.X)
    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    assert all(getattr(zn, g)() is None for g in getters) and not zn.pose_cols_available()
    off = m.with_render_config()
    for f, g, w in zip(frames, gbs, want):
        got = off.render(f, g)
        assert (got - w).abs().max() <= 2e-6 * w.abs().max()
    assert not zn.is_vertex_major(m.model.X) and m.model.X.transpose(1, 2).is_contiguous()
    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    assert all(getattr(zn, g)() is not None for g in getters) and core_native.compile_enabled()


def test_full_change_frame_loads_the_p_frame_libraries(zh_scene, monkeypatch):
    """A vertex-shaded cosine object's first frame (a full change: the harness's untimed frame 0) loads every
    C library a following P frame calls (`native.warm_pose_libraries`), so the first timed P frame loads none
    for the first time."""
    from methods.core import native as core_native
    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    _skip_without_c_compiler()
    m = ZHShadow(**SMALL, order=8, specular="cosine", shading="vertex")
    m.precompute(zh_scene("creature"))
    frames = list(make_sequence(m.scene, "P", 2, seed=6))
    gbs = [make_gbuffer(m.scene, f, 2) for f in frames]
    names: list[list[str]] = [[], []]
    load = core_native.load
    for i, (f, g) in enumerate(zip(frames, gbs)):
        monkeypatch.setattr(core_native, "load", lambda name, *a, _i=i, **k: names[_i].append(name) or load(name, *a, **k))
        m.render(f, g)
    # (the P frame's; session 38: its skinning and resolve by the vector loops where they build)
    vec = {"zh38p_skin", "zh38p_resolve"} if zn._vskin_lib() is not None else {"zh35o_skin", "zh35o_resolve"}
    # (zh43o, ``lean_pose``: the P frame's visibility by a call bound by frame 0, `ZHShadow._cols_bound` — no
    # library looked up in the P frame for it)
    assert {"zh35o_front", *vec, *(() if m.lean_pose else ("zh35o_pose_cols",))} <= set(names[1])
    assert not m.lean_pose or (m._pose_cols_bound is not None and m._pose_cols_bound[1] is not None)
    assert set(names[1]) <= set(names[0]), set(names[1]) - set(names[0])
