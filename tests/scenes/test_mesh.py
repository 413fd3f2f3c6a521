"""scenes/mesh.py and scenes/procedural.py: validation errors, normals (computed, normalised),
file loading (OBJ/PLY round trip, corrupt/missing files), procedural builders' orientation/sizes."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from scenes import procedural as P
from scenes.mesh import Mesh, compute_vertex_normals, load_mesh

# float32 positions / normals: a few ulp of values of order 1.
F32_ATOL = 1e-5
# OBJ files store positions as decimal text (trimesh writes ~8 significant digits).
OBJ_ATOL = 1e-6


def _tetra() -> tuple[np.ndarray, np.ndarray]:
    V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])  # outward, counter-clockwise
    return V, F


# -- validation --------------------------------------------------------------------------------


def test_valid_mesh_passes():
    V, F = _tetra()
    m = Mesh(V, F).validate()
    assert m.num_vertices == 4 and m.num_faces == 4
    torch.testing.assert_close(m.N.norm(dim=1), torch.ones(4), atol=F32_ATOL, rtol=0)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -float("inf")])
def test_nonfinite_positions_raise(bad):
    V, F = _tetra()
    V[2, 1] = bad
    with pytest.raises(ValueError, match="NaN/Inf"):
        Mesh(V, F).validate()


@pytest.mark.parametrize("idx", [4, 100, -1])
def test_out_of_range_indices_raise(idx):
    V, F = _tetra()
    F[1, 2] = idx
    with pytest.raises(ValueError, match="outside"):
        Mesh(V, F).validate()


def test_degenerate_face_raises():
    V, F = _tetra()
    F[3] = [1, 2, 1]
    with pytest.raises(ValueError, match="degenerate"):
        Mesh(V, F).validate()


def test_zero_area_face_raises():
    V, F = _tetra()
    V = np.vstack([V, [0.5, 0.0, 0.0]])  # collinear with vertices 0 and 1
    F = np.vstack([F, [0, 1, 4]])
    with pytest.raises(ValueError, match="zero-area"):
        Mesh(V, F).validate()


def test_zero_normal_raises():
    V, F = _tetra()
    N = compute_vertex_normals(torch.as_tensor(V), torch.as_tensor(F)).numpy()
    N[1] = 0.0
    with pytest.raises(ValueError, match="zero-length"):
        Mesh(V, F, N).validate()


def test_nan_normal_raises():
    V, F = _tetra()
    N = np.ones((4, 3))
    N[0, 0] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        Mesh(V, F, N).validate()


def test_bad_shapes_raise():
    V, F = _tetra()
    with pytest.raises(ValueError):
        Mesh(V[:, :2], F)
    with pytest.raises(ValueError):
        Mesh(V, F[:, :2])
    with pytest.raises(ValueError):
        Mesh(V, F, np.ones((3, 3)))


# -- normals -----------------------------------------------------------------------------------


def test_flat_plane_normals_are_up():
    """A flat grid in y = 0 with counter-clockwise faces seen from +y: every normal is +y."""
    n = 4
    xs = np.linspace(-1, 1, n + 1)
    X, Z = np.meshgrid(xs, xs, indexing="ij")
    V = np.stack([X.ravel(), np.zeros(X.size), Z.ravel()], 1)
    F = []
    for i in range(n):
        for j in range(n):
            a, b, c, d = i * (n + 1) + j, (i + 1) * (n + 1) + j, (i + 1) * (n + 1) + j + 1, i * (n + 1) + j + 1
            # (b − a) = +x, (d − a) = +z; +z × +x = +y, so (a, d, b) is counter-clockwise from +y
            F += [[a, d, b], [b, d, c]]
    m = Mesh(V, np.array(F)).validate()
    torch.testing.assert_close(m.N, torch.tensor([0.0, 1.0, 0.0]).expand_as(m.N), atol=F32_ATOL, rtol=0)
    # reversed winding flips them to −y
    m2 = Mesh(V, np.array(F)[:, [0, 2, 1]]).validate()
    torch.testing.assert_close(m2.N, torch.tensor([0.0, -1.0, 0.0]).expand_as(m2.N), atol=F32_ATOL, rtol=0)


def test_normals_are_area_weighted():
    """Vertex 0 shared by a big face (normal +z) and a small face (normal +x): the normal is
    ∝ 2·area_big·z + 2·area_small·x, not the plain average."""
    V = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0],     # big triangle in z = 0, area 8
                  [0, 1, 0], [0, 0, 1.0]])             # small triangle in x = 0, area 0.5
    F = np.array([[0, 1, 2], [0, 3, 4]])
    m = Mesh(V, F).validate()
    expect = np.array([0.5, 0.0, 8.0])
    expect /= np.linalg.norm(expect)
    np.testing.assert_allclose(m.N[0].numpy(), expect, atol=F32_ATOL)
    np.testing.assert_allclose(m.N[1].numpy(), [0, 0, 1], atol=F32_ATOL)
    np.testing.assert_allclose(m.N[4].numpy(), [1, 0, 0], atol=F32_ATOL)


def test_nonunit_normals_are_normalised():
    V, F = _tetra()
    rng = np.random.default_rng(0)
    N = rng.normal(size=(4, 3)) * np.array([[0.01], [3.0], [100.0], [1.0]])
    m = Mesh(V, F, N).validate()
    torch.testing.assert_close(m.N.norm(dim=1), torch.ones(4), atol=F32_ATOL, rtol=0)
    np.testing.assert_allclose(m.N.numpy(), N / np.linalg.norm(N, axis=1, keepdims=True), atol=F32_ATOL)


# -- file loading ------------------------------------------------------------------------------


@pytest.mark.parametrize("ext", ["obj", "ply"])
def test_load_mesh_round_trip(tmp_path, ext):
    import trimesh

    src = P.icosphere(2, radius=0.7, center=(0.1, 0.2, -0.3))
    tm = trimesh.Trimesh(src.V.numpy(), src.F.numpy(), process=False)
    path = tmp_path / f"ico.{ext}"
    tm.export(path)
    m = load_mesh(path)
    assert m.num_vertices == src.num_vertices and m.num_faces == src.num_faces
    np.testing.assert_allclose(m.V.numpy(), src.V.numpy(), atol=OBJ_ATOL)
    np.testing.assert_array_equal(m.F.numpy(), src.F.numpy())
    # recomputed normals of an icosphere point away from its centre
    assert (((m.V - torch.tensor([0.1, 0.2, -0.3])) * m.N).sum(1) > 0).all()


def test_load_mesh_missing_file(tmp_path):
    with pytest.raises(ValueError, match="not found"):
        load_mesh(tmp_path / "nope.obj")


@pytest.mark.parametrize("ext,content", [
    ("ply", b"ply\nformat binary_little_endian 1.0\nelement vertex 100\nproperty float x\nend_header\n\x00\x01"),
    ("obj", b"this is not an obj file\n\x00\xff garbage\n"),
])
def test_load_mesh_corrupt_file(tmp_path, ext, content):
    path = tmp_path / f"bad.{ext}"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=str(path.name)):
        load_mesh(path)


def test_load_mesh_unsupported_extension(tmp_path):
    path = tmp_path / "mesh.stl"
    path.write_text("solid x\nendsolid x\n")
    with pytest.raises(ValueError, match="unsupported"):
        load_mesh(path)


# -- procedural builders -----------------------------------------------------------------------


def _closed(m: Mesh, decimals: int = 5) -> bool:
    """Every edge of the position-welded mesh is shared by exactly two faces."""
    V = np.round(m.V.double().numpy(), decimals)
    _, inv = np.unique(V, axis=0, return_inverse=True)
    F = inv.reshape(-1)[m.F.numpy()]
    e = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    _, counts = np.unique(e, axis=0, return_counts=True)
    return bool((counts == 2).all())


def _signed_volume(m: Mesh) -> float:
    V = m.V.double()
    p0, p1, p2 = V[m.F[:, 0]], V[m.F[:, 1]], V[m.F[:, 2]]
    return float((p0 * torch.cross(p1, p2, dim=1)).sum() / 6)


@pytest.mark.parametrize("builder", [lambda: P.icosphere(2, 1.5, (0.3, -1.0, 2.0)),
                                     lambda: P.uv_sphere(12, 24, 1.5, (0.3, -1.0, 2.0))])
def test_sphere_closed_outward_and_sized(builder):
    m = builder()
    c = torch.tensor([0.3, -1.0, 2.0])
    p = m.V - c
    assert _closed(m)
    assert ((p * m.N).sum(1) > 0).all(), "sphere normals must point outward (n·p > 0)"
    torch.testing.assert_close(p.norm(dim=1), torch.full((m.num_vertices,), 1.5), atol=F32_ATOL, rtol=0)
    # counter-clockwise faces seen from outside ⇔ positive signed volume ≈ (inscribed) 4/3 π r³
    vol = _signed_volume(m)
    assert 0.8 * 4 / 3 * math.pi * 1.5**3 < vol < 4 / 3 * math.pi * 1.5**3


def test_icosphere_vertex_count():
    for s in range(3):
        assert P.icosphere(s).num_vertices == 10 * 4**s + 2


def test_plane_normals_up_and_size():
    m = P.plane((4.0, 2.0), (3, 5), center=(1.0, 0.5, -1.0))
    torch.testing.assert_close(m.N, torch.tensor([0.0, 1.0, 0.0]).expand_as(m.N), atol=F32_ATOL, rtol=0)
    fn, area = m.face_normals()
    assert (fn[:, 1] > 1 - F32_ATOL).all(), "faces must wind counter-clockwise seen from +y"
    lo, hi = m.V.min(0).values, m.V.max(0).values
    torch.testing.assert_close(lo, torch.tensor([-1.0, 0.5, -2.0]), atol=F32_ATOL, rtol=0)
    torch.testing.assert_close(hi, torch.tensor([3.0, 0.5, 0.0]), atol=F32_ATOL, rtol=0)
    assert m.num_faces == 2 * 3 * 5
    assert float(area.double().sum()) == pytest.approx(8.0, rel=1e-6)


def test_box_closed_outward():
    m = P.box((1.0, 2.0, 3.0), center=(0.5, 0.0, 0.0), n=2)
    assert _closed(m)
    assert _signed_volume(m) == pytest.approx(6.0, rel=1e-6)
    fn, _ = m.face_normals()
    cen = m.V[m.F].mean(1) - torch.tensor([0.5, 0.0, 0.0])
    assert ((fn * cen).sum(1) > 0).all()


@pytest.mark.parametrize("kind", ["pawn", "rook", "bishop", "king"])
def test_chess_pieces_closed_valid(kind):
    m = P.chess_piece(kind, n_seg=12, detail=4, center=(0.5, 0.0, -0.5))
    m.validate()  # raises on any defect
    assert _closed(m)
    assert _signed_volume(m) > 0, "faces must wind counter-clockwise seen from outside"
    # vertex normals agree with the face normals of their faces (no inward normals)
    fn, _ = m.face_normals()
    assert ((m.N[m.F] * fn[:, None, :]).sum(-1) > 0).all()
    assert float(m.V[:, 1].min()) == pytest.approx(0.0, abs=F32_ATOL)


def test_capsule_closed_outward_and_sized():
    p0, p1, r = np.array([0.0, 0.2, 0.0]), np.array([0.6, 1.0, 0.3]), 0.15
    m = P.capsule(p0, p1, r, n_seg=12, n_len=6, n_cap=4)
    assert _closed(m)
    V = m.V.double().numpy()
    d = (p1 - p0) / np.linalg.norm(p1 - p0)
    t = np.clip((V - p0) @ d, 0, np.linalg.norm(p1 - p0))
    closest = p0 + t[:, None] * d
    np.testing.assert_allclose(np.linalg.norm(V - closest, axis=1), r, atol=F32_ATOL)
    assert (((V - closest) * m.N.numpy()).sum(1) > 0).all()


def test_torus_knot_closed_valid():
    m = P.torus_knot(2, 3, n_u=48, n_v=8)
    assert _closed(m)
    assert _signed_volume(m) > 0


def test_lathe_cylinder_closed_and_sized():
    """A closed cylinder profile (radius 0.5, height 1.2) with creases at the rims."""
    prof = [(0.0, 0.0), (0.5, 0.0), (0.5, 0.6), (0.5, 1.2), (0.0, 1.2)]
    m = P.lathe(prof, n_seg=16)
    assert _closed(m)
    V = m.V.double()
    r = V[:, [0, 2]].norm(dim=1)
    assert float(r.max()) == pytest.approx(0.5, abs=F32_ATOL)
    assert float(V[:, 1].min()) == pytest.approx(0.0, abs=F32_ATOL)
    assert float(V[:, 1].max()) == pytest.approx(1.2, abs=F32_ATOL)
    # volume of the inscribed 16-gon prism: ½·16·sin(2π/16)·r²·h
    assert _signed_volume(m) == pytest.approx(0.5 * 16 * math.sin(2 * math.pi / 16) * 0.25 * 1.2, rel=1e-5)
    # crease at the rims: the side vertices have horizontal normals, the caps vertical ones
    side = (r > 0.5 - F32_ATOL) & (V[:, 1] > 0.3) & (V[:, 1] < 0.9)
    assert side.any() and (m.N[side][:, 1].abs() < F32_ATOL).all()
    cap = r < 0.25
    assert (m.N[cap][:, 1].abs() > 1 - F32_ATOL).all()


def test_chess_piece_scale():
    a = P.chess_piece("rook", n_seg=8, detail=2)
    b = P.chess_piece("rook", n_seg=8, detail=2, scale=2.0, center=(1.0, 0.5, 0.0))
    torch.testing.assert_close(b.V, a.V * 2 + torch.tensor([1.0, 0.5, 0.0]), atol=F32_ATOL, rtol=0)
    torch.testing.assert_close(b.N, a.N, atol=F32_ATOL, rtol=0)


def test_closed_check_detects_holes():
    """The helper used above must be able to fail: an open plane and a box with a face removed."""
    assert not _closed(P.plane((1.0, 1.0), (2, 2)))
    b = P.box()
    assert not _closed(Mesh(b.V, b.F[1:], b.N))


def test_empty_mesh_raises():
    with pytest.raises(ValueError, match="empty"):
        Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64)).validate()


def test_transformed_normals_use_inverse_transpose():
    """Under a non-uniform scale, transformed normals stay perpendicular to the transformed faces."""
    m = P.icosphere(1)
    M = torch.tensor([[3.0, 0.5, 0, 1], [0, 1.0, 0, 2], [0, 0, 0.2, 3], [0, 0, 0, 1]])
    t = m.transformed(M)
    torch.testing.assert_close(t.V, m.V @ M[:3, :3].T + M[:3, 3], atol=F32_ATOL, rtol=0)
    # a flat mesh: its vertex normals equal its face normal, before and after
    q = P.quad((0, 0, 0), (1.0, 0.2, 0.0), (0.0, 0.3, 1.0), 2, 2)
    tq = q.transformed(M)
    fn, _ = tq.face_normals()
    torch.testing.assert_close(tq.N, fn[:1].expand_as(tq.N), atol=F32_ATOL, rtol=0)
    torch.testing.assert_close(t.N.norm(dim=1), torch.ones(t.num_vertices), atol=F32_ATOL, rtol=0)


def test_merge_offsets_faces():
    from scenes.mesh import merge

    a, b = P.icosphere(0), P.box()
    m = merge([a, b])
    assert m.num_vertices == a.num_vertices + b.num_vertices
    assert torch.equal(m.F[a.num_faces:], b.F + a.num_vertices)
    assert torch.equal(m.N, torch.cat([a.N, b.N]))
    with pytest.raises(ValueError):
        merge([])
