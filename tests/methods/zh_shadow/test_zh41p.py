"""Session 41 (zh41p): the paper configuration's serial Python around its C calls — the skinning and every
vertex's `native.pose_sh` by calls bound once (`native.SkinBound`, `native.PoseSHBound`, `ZHShadow.bound_calls`),
the libraries remembered (`native.load`), the materials' tensors and values kept while they are equal
(`_region_materials`, `_mat_values`), the plane's T¹(n0) kept with its table (`_plane_T`) — against the oracles:
the unbound calls and every cache rebuilt each frame, bit for bit."""
from __future__ import annotations

import pytest
import torch

from methods.zh_shadow import native as zn
from methods.zh_shadow import runtime as rt
from methods.zh_shadow.precompute import CHART_RMAX
from tests.methods.zh_shadow.conftest import assert_frames_equal


def _bits(x: torch.Tensor) -> torch.Tensor:
    return x.contiguous().view(torch.int32)


def _skip_without_pose_sh() -> None:
    if not zn.pose_sh_available():
        pytest.skip("no C compiler or the native passes switched off")


@pytest.mark.parametrize("N", (17, 37, 160))
@pytest.mark.parametrize("zyz,dim", ((False, 1), (False, 0), (True, 0)))
def test_pose_sh_bound_equals_pose_sh(N, zyz, dim):
    """`PoseSHBound`(pose, normals (N, 3) as rows) = `pose_sh`(X, [pose, 1], None, normals.T, …) bit for bit — a
    tail of fewer than 16 vertices, poses one after another (the kept [pose, 1] rewritten), 1 and 2 threads — and
    None for a pose or normals of the wrong shape or dtype. A normal read with the wrong stride, a pose not
    written, or the 1 dropped breaks it."""
    from methods.core.threads import torch_threads

    _skip_without_pose_sh()
    n, lobes, J1 = 4, 2, 6
    g = torch.Generator().manual_seed(N * 7 + dim)
    Xv = zn.vertex_major(torch.randn(J1, N, lobes * (2 + n), generator=g) * 0.6)
    nrm = torch.nn.functional.normalize(torch.randn(N, 3, generator=g), dim=1).contiguous()
    lam = rt._band_norms(n)
    perm = tuple(int(i) for i in rt.zyz_rows(n).tolist()) if zyz else tuple(range(n * n))
    b = zn.pose_sh_bind(Xv, lam, perm, lobes, n, CHART_RMAX, zyz, dim)
    assert b is not None
    for k in range(3):
        pose = torch.randn(J1 - 1, generator=g)
        a = torch.cat([pose, torch.ones(1)])
        want = zn.pose_sh(Xv, a, None, nrm.T.contiguous(), lam, perm, lobes, n, CHART_RMAX, None, zyz, dim)
        for threads in (1, 2):
            with torch_threads(threads):
                got = b(pose, nrm)
            assert got is not None and got.shape == want.shape and torch.equal(_bits(got), _bits(want)), (k, threads)
    assert b(torch.zeros(J1), nrm) is None and b(torch.zeros(J1 - 1, dtype=torch.float64), nrm) is None
    assert b(torch.zeros(J1 - 1), nrm.T.contiguous() if N != 3 else nrm[:1]) is None
    assert zn.pose_sh_bind(Xv, lam, (0,) * (n * n), lobes, n, CHART_RMAX, zyz, dim) is None   # (not a permutation)


def test_skin_bound_equals_skin_vector():
    """`SkinBound`(pose) = `skin_vector`(setup, vsetup, pose) bit for bit, pose after pose (the kept scratch T12
    rewritten), 1 and 2 threads; None for a pose of the wrong length."""
    from methods.core.threads import torch_threads
    from scenes.library import get_scene

    if zn._vskin_lib() is None:
        pytest.skip("no AVX-512 host or no C compiler")
    scene = get_scene("creature", "test")
    st = zn.skin_setup(scene)
    vs = zn.skin_vector_setup(st)
    b = zn.skin_bind(st, vs)
    J = scene.skeleton.num_joints
    g = torch.Generator().manual_seed(41)
    for k in range(3):
        pose = ((torch.rand(J, generator=g) * 2 - 1) * (0.5 + k)).float()
        V, N = zn.skin_vector(st, vs, pose)
        for threads in (1, 2):
            with torch_threads(threads):
                Vb, Nb = b(pose)
            assert torch.equal(V, Vb) and torch.equal(N, Nb), (k, threads)
    assert b(torch.zeros(J + 1)) is None


def test_load_remembered_follows_the_switch_and_a_spy(monkeypatch):
    """`native.load` (zh_shadow's) gives the library `methods.core.native.load` gives, remembered: None while
    ``PRTBENCH_COMPILE`` is 0 (nothing kept), the same library once it is back on, and a spy put on the core
    `load` sees the call (the tests that count loads)."""
    from methods.core import native as core_native

    if core_native.compiler() is None:
        pytest.skip("no C compiler")
    lib = zn._split_lib()
    assert lib is not None and zn._split_lib() is lib
    monkeypatch.setenv("PRTBENCH_COMPILE", "0")
    assert zn._split_lib() is None and zn._pmask_lib() is None
    monkeypatch.setenv("PRTBENCH_COMPILE", "1")
    assert zn._split_lib() is lib
    names = []
    load = core_native.load
    monkeypatch.setattr(core_native, "load", lambda name, *a, **k: names.append(name) or load(name, *a, **k))
    # the same library (dlopen's handle): after an earlier test's `core_native.cache_clear` the core cache makes a new
    # CDLL object of the same file while zh's remembered one is the old object (CI replica of 5d24570, xdist order)
    again = zn._split_lib()
    assert again is not None and again._handle == lib._handle and names == ["zh_plane_split"]


def _oracle_frame(m) -> None:
    """Forget zh41p's kept objects before a frame: the oracle rebuilds them every frame."""
    m._mats_kept = m._plane_T = m._spec_t = None


@pytest.mark.parametrize("kind", ("P", "V", "VB", "VL", "VBL", "L"))
def test_kept_state_frames_equal_oracle(creature, kind):
    """`bound_calls` with the kept materials, plane factor and flags = the oracle (`bound_calls` off, each of them
    rebuilt every frame) bit for bit, with the same path and counts, at 1 and 2 threads. A materials cache not
    dropped when a material changes (VB, VBL), a T¹(n0) not keyed on the table (VL, VBL, L), a pose not
    written into the bound call (P) breaks it."""
    new, orc = creature.with_render_config(), creature.with_render_config()
    orc.bound_calls = False
    assert_frames_equal(creature.scene, new, orc, kind, 41, before_oracle=_oracle_frame, fused=True)
    if kind == "P" and zn.pose_sh_available():
        assert new._pose_bound is not None and orc._pose_bound is None   # (the bound call ran)


def test_pose_sh_bound_rows_write_those_rows():
    """`PoseSHBound`(pose, normals, rows, out): the rows of those vertices (unsorted, repeated, a tail of fewer
    than 16) equal the full call's bit for bit and every other row of ``out`` is untouched, at 1 and 2 threads;
    None without ``out``, for an id out of range, for rows of another dtype. Reading the normal or writing the
    row of the block position instead of the vertex breaks it."""
    from methods.core.threads import torch_threads

    _skip_without_pose_sh()
    n, lobes, J1, N = 4, 2, 6, 300
    g = torch.Generator().manual_seed(4141)
    Xv = zn.vertex_major(torch.randn(J1, N, lobes * (2 + n), generator=g) * 0.6)
    nrm = torch.nn.functional.normalize(torch.randn(N, 3, generator=g), dim=1).contiguous()
    b = zn.pose_sh_bind(Xv, rt._band_norms(n), tuple(range(n * n)), lobes, n, CHART_RMAX, False, 1)
    assert b is not None
    pose = torch.randn(J1 - 1, generator=g)
    full = b(pose, nrm)
    for rows in (torch.randperm(N, generator=g)[:77], torch.tensor([5, 5, 299, 0, 17]), torch.arange(40, 203),
                 torch.zeros(0, dtype=torch.int64)):
        for threads in (1, 2):
            out = torch.full((N, n * n), float("nan"))
            with torch_threads(threads):
                got = b(pose, nrm, rows, out=out)
            assert got is out
            on = torch.zeros(N, dtype=torch.bool)
            on[rows] = True
            assert torch.equal(_bits(out[on]), _bits(full[on])), (rows[:5], threads)
            assert bool(out[~on].isnan().all())
    out = torch.zeros(N, n * n)
    assert b(pose, nrm, torch.tensor([3])) is None                      # (rows without out)
    assert b(pose, nrm, torch.tensor([3, N]), out=out) is None          # (an id out of range)
    assert b(pose, nrm, torch.tensor([3], dtype=torch.int32), out=out) is None


def test_lazy_visibility_frames(creature, monkeypatch):
    """P frames with a new pose's visibility made for the rows the frame reads (`lazy_visibility`) = the oracle
    (every row, `lazy_visibility` off) bit for bit; those rows alone were made (fewer than every vertex); a frame
    whose fused pass then declines (its other paths read every row), a frame without the fused pass, and a view
    frame at the last pose (the pose's visibility made whole then) likewise. Rows not made for the plane term
    or the table, or a fallback not completing them, break it."""
    import dataclasses

    from references.gbuffer import make_gbuffer
    from scenes.sequences import make_sequence

    new, orc = creature.with_render_config(), creature.with_render_config()
    orc.lazy_visibility = False
    seen = []
    fill = type(new)._fill_visibility

    def spy(self, v0, rows=None):
        if self is new and self._v_pending is not None and self._v_pending[0] is v0:
            seen.append(None if rows is None else int(rows.shape[0]))
        return fill(self, v0, rows)

    monkeypatch.setattr(type(new), "_fill_visibility", spy)
    frames = list(make_sequence(creature.scene, "P", 6, seed=44))
    view = list(make_sequence(creature.scene, "V", 2, seed=44))[1]
    light = list(make_sequence(creature.scene, "L", 3, seed=44))
    # (two lighting-only frames at the last pose: the pose's visibility made whole and kept by the first, so the
    # second takes the transfer cache as the oracle does; then a view frame at that pose)
    frames += [dataclasses.replace(light[i], pose=frames[-1].pose, changed=frozenset({"light"})) for i in (1, 2)]
    frames.append(dataclasses.replace(view, pose=frames[-1].pose, changed=frozenset({"view"})))
    fused_pixels, fused_run = zn.fused_pixels, zn._fused_run
    N = int(creature.scene.geometry().num_vertices)
    for i, fr in enumerate(frames):
        gb = make_gbuffer(creature.scene, fr, 2)
        del seen[:]
        if i == 3:   # the fused pass declines after the rows were made: the split path reads every row
            monkeypatch.setattr(zn, "fused_pixels", lambda *a, **k: None)
            monkeypatch.setattr(zn, "_fused_run", lambda *a, **k: None)   # (and its bound call's, zh46)
        if i == 4:
            new.fused_planes = orc.fused_planes = False
        a = new.render(fr, gb)
        b = orc.render(fr, gb)
        monkeypatch.setattr(zn, "fused_pixels", fused_pixels)
        monkeypatch.setattr(zn, "_fused_run", fused_run)
        new.fused_planes = orc.fused_planes = True
        assert new.last_path == orc.last_path and new.last_fused == orc.last_fused, i
        assert torch.equal(_bits(a), _bits(b)), i
        if i in (1, 2, 5):   # (frame 0 binds the call; a frame of the fused pass: its rows alone)
            assert seen and seen[0] is not None and 0 < seen[0] < N, (i, seen)
        if i == 3:
            assert seen[:1] != [] and seen[-1] is None, seen   # (the rows, then every row)
    assert new._v_pending is None and new._posed[2] is not None
