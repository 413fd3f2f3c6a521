"""Triangle meshes: the container, validation, vertex normals and file loading.

A `Mesh` holds torch tensors: V (N, 3) float32 positions, F (M, 3) int64 vertex indices
(counter-clockwise seen from the front), N (N, 3) float32 unit vertex normals (or None before
`validate()`), uv (N, 2) float32 texture coordinates or None.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

# A face whose area is below AREA_EPS (relative to the squared bounding-box diagonal) counts as
# zero-area: float32 cross products of well-shaped triangles are far above this.
AREA_EPS = 1e-12
# Normals shorter than this cannot be normalised reliably.
NORMAL_EPS = 1e-8
# A mesh whose bounding-box diagonal is below MIN_EXTENT_REL·(1 + max|p|) is degenerate for float32
# ray tracing: Mitsuba offsets secondary rays by 1500·2⁻²⁴·(1 + max|p|) ≈ 8.9e-5·(1 + max|p|)
# (math::RayEpsilon), so such a mesh is at most ~11 ray offsets across and shadows itself at random.
MIN_EXTENT_REL = 1e-3


def _as_tensor(x, dtype) -> Tensor | None:
    if x is None:
        return None
    if isinstance(x, Tensor):
        return x.to(dtype)
    return torch.as_tensor(np.asarray(x), dtype=dtype)


@dataclass
class Mesh:
    """Triangle mesh. V (N, 3) f32, F (M, 3) i64, N (N, 3) f32 | None, uv (N, 2) f32 | None."""

    V: Tensor
    F: Tensor
    N: Tensor | None = None
    uv: Tensor | None = None

    def __post_init__(self) -> None:
        self.V = _as_tensor(self.V, torch.float32)
        self.F = _as_tensor(self.F, torch.int64)
        self.N = _as_tensor(self.N, torch.float32)
        self.uv = _as_tensor(self.uv, torch.float32)
        if self.V.dim() != 2 or self.V.shape[1] != 3:
            raise ValueError(f"mesh positions V must be (N, 3), got {tuple(self.V.shape)}")
        if self.F.dim() != 2 or self.F.shape[1] != 3:
            raise ValueError(f"mesh faces F must be (M, 3), got {tuple(self.F.shape)}")
        if self.N is not None and self.N.shape != self.V.shape:
            raise ValueError(f"mesh normals N must be {tuple(self.V.shape)} like V, got {tuple(self.N.shape)}")
        if self.uv is not None and self.uv.shape != (self.V.shape[0], 2):
            raise ValueError(f"mesh uv must be ({self.V.shape[0]}, 2), got {tuple(self.uv.shape)}")

    @property
    def num_vertices(self) -> int:
        return int(self.V.shape[0])

    @property
    def num_faces(self) -> int:
        return int(self.F.shape[0])

    def face_normals(self) -> tuple[Tensor, Tensor]:
        """Unit face normals (M, 3) and face areas (M,)."""
        return face_normals(self.V, self.F)

    def validate(self) -> "Mesh":
        """Checked copy: raises ValueError on bad data; computes/normalises normals."""
        return validate(self)

    def transformed(self, M: Tensor) -> "Mesh":
        """Copy under an affine 4×4 transform M (normals by the inverse transpose)."""
        M = _as_tensor(M, torch.float64)
        V = (self.V.double() @ M[:3, :3].T + M[:3, 3]).float()
        N = None
        if self.N is not None:
            Nt = self.N.double() @ torch.linalg.inv(M[:3, :3])
            N = (Nt / Nt.norm(dim=1, keepdim=True).clamp_min(1e-30)).float()
        return replace(self, V=V, N=N)


def face_normals(V: Tensor, F: Tensor) -> tuple[Tensor, Tensor]:
    """Unit face normals (M, 3) and areas (M,) of faces F (M, 3) over positions V (N, 3)."""
    p0, p1, p2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    c = torch.cross(p1 - p0, p2 - p0, dim=1)
    l = c.norm(dim=1)
    return c / l.clamp_min(1e-30)[:, None], 0.5 * l


def compute_vertex_normals(V: Tensor, F: Tensor) -> Tensor:
    """Area-weighted vertex normals (N, 3) (unit; zero for unreferenced vertices).

    Each face adds its un-normalised cross product (= 2·area·n_f) to its three vertices.
    """
    Vd = V.double()
    p0, p1, p2 = Vd[F[:, 0]], Vd[F[:, 1]], Vd[F[:, 2]]
    c = torch.cross(p1 - p0, p2 - p0, dim=1)
    acc = torch.zeros_like(Vd)
    for k in range(3):
        acc.index_add_(0, F[:, k], c)
    l = acc.norm(dim=1, keepdim=True)
    n = torch.where(l > 0, acc / l.clamp_min(1e-300), torch.zeros_like(acc))
    return n.to(V.dtype)


def validate(mesh: Mesh) -> Mesh:
    """Check a mesh and return a copy with unit normals.

    Raises ValueError for: NaN/Inf positions, negative or out-of-range indices, degenerate faces
    (a repeated vertex index), zero-area faces, NaN/zero normals. Missing normals are computed
    (area-weighted); non-unit normals are normalised.
    """
    V, F = mesh.V, mesh.F
    n_v = V.shape[0]
    if n_v == 0 or F.shape[0] == 0:
        raise ValueError(f"mesh is empty ({n_v} vertices, {F.shape[0]} faces)")
    bad = ~torch.isfinite(V).all(dim=1)
    if bad.any():
        i = int(bad.nonzero()[0, 0])
        raise ValueError(f"mesh has {int(bad.sum())} vertices with NaN/Inf positions (first: vertex {i})")
    bad = ((F < 0) | (F >= n_v)).any(dim=1)
    if bad.any():
        i = int(bad.nonzero()[0, 0])
        raise ValueError(f"mesh has {int(bad.sum())} faces with indices outside [0, {n_v}) "
                         f"(first: face {i} = {F[i].tolist()})")
    bad = (F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 0] == F[:, 2])
    if bad.any():
        i = int(bad.nonzero()[0, 0])
        raise ValueError(f"mesh has {int(bad.sum())} degenerate faces with a repeated vertex index "
                         f"(first: face {i} = {F[i].tolist()})")
    _, area = face_normals(V.double(), F)
    diag2 = float(((V.max(0).values - V.min(0).values).double() ** 2).sum())
    bad = area <= AREA_EPS * max(diag2, 1e-30)
    if bad.any():
        i = int(bad.nonzero()[0, 0])
        raise ValueError(f"mesh has {int(bad.sum())} zero-area faces (first: face {i} = {F[i].tolist()})")
    if mesh.N is None:
        N = compute_vertex_normals(V, F)
        l = N.norm(dim=1)
        used = torch.zeros(n_v, dtype=torch.bool)
        used[F.reshape(-1)] = True
        bad = used & (l < 0.5)
        if bad.any():
            i = int(bad.nonzero()[0, 0])
            raise ValueError(f"computed normals vanish at {int(bad.sum())} vertices (faces cancel; first: vertex {i})")
        N = torch.where(used[:, None], N, torch.tensor([0.0, 1.0, 0.0]))  # unreferenced vertices
    else:
        N = mesh.N
        bad = ~torch.isfinite(N).all(dim=1)
        if bad.any():
            i = int(bad.nonzero()[0, 0])
            raise ValueError(f"mesh has {int(bad.sum())} NaN/Inf normals (first: vertex {i})")
        l = N.double().norm(dim=1)
        bad = l < NORMAL_EPS
        if bad.any():
            i = int(bad.nonzero()[0, 0])
            raise ValueError(f"mesh has {int(bad.sum())} zero-length normals (first: vertex {i})")
        N = (N.double() / l[:, None]).float()
    uv = mesh.uv
    if uv is not None and not torch.isfinite(uv).all():
        raise ValueError("mesh uv has NaN/Inf values")
    return Mesh(V.clone(), F.clone(), N.contiguous(), None if uv is None else uv.clone())


def check_extent(mesh: Mesh, what: str = "mesh") -> Mesh:
    """``mesh`` if its extent is resolvable in float32 ray tracing; ValueError naming ``what`` if its
    bounding-box diagonal is below `MIN_EXTENT_REL`·(1 + max|p|) (e.g. collapsed by a tiny scale)."""
    V = mesh.V.double()
    if V.shape[0] == 0 or not torch.isfinite(V).all():
        return mesh  # validate() reports these
    diag = float((V.max(0).values - V.min(0).values).norm())
    far = float(V.abs().max())
    if not diag >= MIN_EXTENT_REL * (1.0 + far):
        raise ValueError(f"{what} is degenerate: its bounding-box diagonal {diag:.3g} is below "
                         f"{MIN_EXTENT_REL:g}·(1 + max|p|) = {MIN_EXTENT_REL * (1.0 + far):.3g}, too small for float32 "
                         f"ray tracing at that distance (a collapsed scale?)")
    return mesh


def merge(meshes: list[Mesh]) -> Mesh:
    """Concatenate meshes (normals/uv kept only when every mesh has them)."""
    if not meshes:
        raise ValueError("merge() needs at least one mesh")
    off = 0
    Fs = []
    for m in meshes:
        Fs.append(m.F + off)
        off += m.num_vertices
    N = torch.cat([m.N for m in meshes]) if all(m.N is not None for m in meshes) else None
    uv = torch.cat([m.uv for m in meshes]) if all(m.uv is not None for m in meshes) else None
    return Mesh(torch.cat([m.V for m in meshes]), torch.cat(Fs), N, uv)


def subdivide(mesh: Mesh, levels: int) -> Mesh:
    """``levels`` rounds of midpoint 1-to-4 subdivision: every edge gets its midpoint (shared by the
    two faces of an edge), every face becomes 4. Positions, uv linearly; normals interpolated and
    renormalised. Flat faces keep their exact shape (curved surfaces do not get smoother: this is
    not Loop subdivision); vertices the input keeps apart (a box's per-face corners) stay apart.
    What it is for: per-vertex transport (every PRT method here) cannot show a shadow or highlight
    inside one face, so a scene file's coarse mesh is refined to the tessellation PRT needs."""
    if isinstance(levels, bool) or not isinstance(levels, int) or levels < 0:
        raise ValueError(f"subdivision levels must be an int >= 0, got {levels!r}")
    V, F, N, uv = mesh.V, mesh.F, mesh.N, mesh.uv
    for _ in range(levels):
        M = F.shape[0]
        e = torch.cat([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]).sort(1).values   # (3M, 2)
        uniq, inv = torch.unique(e, dim=0, return_inverse=True)
        mid = V.shape[0] + inv.view(3, M).T                                         # (M, 3): 01, 12, 20
        V = torch.cat([V, 0.5 * (V[uniq[:, 0]] + V[uniq[:, 1]])])
        if N is not None:
            n = N[uniq[:, 0]] + N[uniq[:, 1]]
            N = torch.cat([N, n / n.norm(dim=1, keepdim=True).clamp_min(1e-30)])
        if uv is not None:
            uv = torch.cat([uv, 0.5 * (uv[uniq[:, 0]] + uv[uniq[:, 1]])])
        a, b, c = F.T
        ab, bc, ca = mid.T
        F = torch.cat([torch.stack([a, ab, ca], 1), torch.stack([ab, b, bc], 1),
                       torch.stack([ca, bc, c], 1), torch.stack([ab, bc, ca], 1)])
    return Mesh(V, F, N, uv)


def load_mesh(path: str | Path) -> Mesh:
    """Load an OBJ/PLY/GLB file as one triangle mesh (validated; area-weighted vertex normals).

    Raises ValueError if the file is missing, unreadable, or holds no triangles.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise ValueError(f"mesh file not found: {path}")
    ext = path.suffix.lower()
    if ext not in (".obj", ".ply", ".glb", ".gltf"):
        raise ValueError(f"unsupported mesh format {ext!r} for {path} (OBJ, PLY, GLB)")
    try:
        # process=False keeps the file's vertex order (no merging/reordering).
        tm = trimesh.load(path, force="mesh", process=False, maintain_order=True)
    except Exception as e:  # trimesh raises many types on corrupt input
        raise ValueError(f"cannot read mesh file {path}: {type(e).__name__}: {e}") from e
    if not isinstance(tm, trimesh.Trimesh) or len(tm.faces) == 0 or len(tm.vertices) == 0:
        raise ValueError(f"mesh file {path} contains no triangles")
    V = np.asarray(tm.vertices, dtype=np.float32)
    F = np.asarray(tm.faces, dtype=np.int64)
    # Normals are always recomputed (area-weighted): trimesh 5.2 with process=False does not
    # reliably keep the file's normals, and recomputing keeps every loader consistent.
    N = None
    uv = None
    vis = getattr(tm, "visual", None)
    if vis is not None and getattr(vis, "kind", None) == "texture" and getattr(vis, "uv", None) is not None:
        if len(vis.uv) == len(V):
            uv = np.asarray(vis.uv, dtype=np.float32)
    return Mesh(V, F, N, uv).validate()
