"""Procedural meshes (all `Mesh`, validated, +Y up, faces counter-clockwise seen from outside).

Curved surfaces carry smooth per-vertex normals; flat pieces (planes, walls, boxes) carry face
normals, with vertices duplicated at hard edges.
"""
from __future__ import annotations

import math

import numpy as np
import torch

from scenes.mesh import Mesh, compute_vertex_normals, merge

# Profile corners of a lathe sharper than this (turn angle, degrees) get split normals.
LATHE_CREASE_DEG = 50.0


def _orient(V: np.ndarray, F: np.ndarray, N: np.ndarray) -> np.ndarray:
    """Flip faces whose geometric normal disagrees with the mean of their vertex normals."""
    p0, p1, p2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    c = np.cross(p1 - p0, p2 - p0)
    nm = N[F].sum(1)
    flip = (c * nm).sum(1) < 0
    F = F.copy()
    F[flip] = F[flip][:, [0, 2, 1]]
    return F


def _mesh(V, F, N=None, uv=None, orient: bool = True) -> Mesh:
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    if N is None:
        N = compute_vertex_normals(torch.from_numpy(V), torch.from_numpy(F)).numpy()
    else:
        N = np.asarray(N, np.float64)
        N = N / np.linalg.norm(N, axis=1, keepdims=True)
        if orient:
            F = _orient(V, F, N)
    return Mesh(V.astype(np.float32), F, N.astype(np.float32),
                None if uv is None else np.asarray(uv, np.float32)).validate()


def _affine(mesh: Mesh, *, scale=1.0, translate=(0.0, 0.0, 0.0), R=None) -> Mesh:
    M = np.eye(4)
    S = np.diag(np.broadcast_to(np.asarray(scale, float), (3,)))
    M[:3, :3] = (np.eye(3) if R is None else np.asarray(R, float)) @ S
    M[:3, 3] = translate
    return mesh.transformed(torch.from_numpy(M))


# -- spheres ------------------------------------------------------------------------------------


def icosphere(subdivisions: int = 3, radius: float = 1.0, center=(0.0, 0.0, 0.0)) -> Mesh:
    """Subdivided icosahedron, 10·4^s + 2 vertices, exact sphere normals."""
    import trimesh

    if subdivisions < 0 or radius <= 0:
        raise ValueError(f"icosphere needs subdivisions >= 0 and radius > 0, got {subdivisions}, {radius}")
    tm = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    d = np.asarray(tm.vertices, float)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return _mesh(d * radius + np.asarray(center, float), tm.faces, d)


def uv_sphere(n_lat: int = 16, n_lon: int = 32, radius: float = 1.0, center=(0.0, 0.0, 0.0)) -> Mesh:
    """Latitude–longitude sphere (lathe of a half circle), single pole vertices."""
    th = np.linspace(-math.pi / 2, math.pi / 2, n_lat + 1)
    prof = np.stack([np.cos(th), np.sin(th)], 1) * radius
    prof[0, 0] = prof[-1, 0] = 0.0
    m = lathe(prof, n_lon, crease_deg=180.0)
    return _affine(m, translate=center)


def bumpy_sphere(subdivisions: int = 4, radius: float = 1.0, amplitude: float = 0.15, frequency: int = 6,
                 center=(0.0, 0.0, 0.0)) -> Mesh:
    """Sphere with radial bumps r(d) = R(1 + a·sin(f·x)sin(f·y)sin(f·z)) — fine self-shadowing."""
    import trimesh

    tm = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    d = np.asarray(tm.vertices, float)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    r = radius * (1.0 + amplitude * np.sin(frequency * d[:, 0]) * np.sin(frequency * d[:, 1]) * np.sin(frequency * d[:, 2]))
    return _mesh(d * r[:, None] + np.asarray(center, float), tm.faces)


def torus_knot(p: int = 2, q: int = 3, n_u: int = 128, n_v: int = 12, R: float = 1.0, r_tube: float = 0.18,
               center=(0.0, 0.0, 0.0), scale: float = 1.0) -> Mesh:
    """(p, q) torus knot tube: n_u samples along the curve × n_v around the tube (closed both ways).

    Curve: ((R + 0.4 cos qφ) cos pφ, 0.4 sin qφ, (R + 0.4 cos qφ) sin pφ); tube frame by
    parallel transport (rotation-minimising), so the tube does not twist.
    """
    phi = np.linspace(0, 2 * math.pi, n_u, endpoint=False)
    def curve(ph):
        rr = R + 0.4 * np.cos(q * ph)
        return np.stack([rr * np.cos(p * ph), 0.4 * np.sin(q * ph), rr * np.sin(p * ph)], -1)
    C = curve(phi)
    T = curve(phi + 1e-4) - curve(phi - 1e-4)
    T /= np.linalg.norm(T, axis=1, keepdims=True)
    # parallel-transport a normal along the closed curve, then spread the closure twist evenly
    Nrm = np.zeros_like(C)
    a = np.cross(T[0], [0.0, 1.0, 0.0])
    Nrm[0] = a / np.linalg.norm(a)
    for i in range(1, n_u):
        v = Nrm[i - 1] - T[i] * (Nrm[i - 1] @ T[i])
        Nrm[i] = v / np.linalg.norm(v)
    v = Nrm[-1] - T[0] * (Nrm[-1] @ T[0])
    v /= np.linalg.norm(v)
    twist = math.atan2(np.cross(v, Nrm[0]) @ T[0], v @ Nrm[0])
    B = np.cross(T, Nrm)
    ang = twist * np.arange(n_u) / n_u
    Nrm, B = Nrm * np.cos(ang)[:, None] + B * np.sin(ang)[:, None], B * np.cos(ang)[:, None] - Nrm * np.sin(ang)[:, None]
    th = np.linspace(0, 2 * math.pi, n_v, endpoint=False)
    D = np.cos(th)[None, :, None] * Nrm[:, None] + np.sin(th)[None, :, None] * B[:, None]  # (n_u, n_v, 3)
    V = (C[:, None] + r_tube * D).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_u), np.arange(n_v), indexing="ij")
    a0 = i * n_v + j
    a1 = ((i + 1) % n_u) * n_v + j
    a2 = ((i + 1) % n_u) * n_v + (j + 1) % n_v
    a3 = i * n_v + (j + 1) % n_v
    F = np.concatenate([np.stack([a0, a1, a2], -1).reshape(-1, 3), np.stack([a0, a2, a3], -1).reshape(-1, 3)])
    return _mesh(V * scale + np.asarray(center, float), F, D.reshape(-1, 3))


# -- flat pieces --------------------------------------------------------------------------------


def quad(center, u, v, n_u: int = 1, n_v: int = 1) -> Mesh:
    """Flat parallelogram center + a·u + b·v, a, b ∈ [−1, 1], (n_u+1)(n_v+1) vertices.

    Front face (normal) = normalize(u × v).
    """
    center, u, v = (np.asarray(x, float) for x in (center, u, v))
    a = np.linspace(-1, 1, n_u + 1)
    b = np.linspace(-1, 1, n_v + 1)
    A, Bm = np.meshgrid(a, b, indexing="ij")
    V = center + A.reshape(-1, 1) * u + Bm.reshape(-1, 1) * v
    n = np.cross(u, v)
    n /= np.linalg.norm(n)
    i, j = np.meshgrid(np.arange(n_u), np.arange(n_v), indexing="ij")
    v00 = i * (n_v + 1) + j
    v10 = v00 + (n_v + 1)
    F = np.concatenate([np.stack([v00, v10, v10 + 1], -1).reshape(-1, 3), np.stack([v00, v10 + 1, v00 + 1], -1).reshape(-1, 3)])
    uv = np.stack([(A.reshape(-1) + 1) / 2, (Bm.reshape(-1) + 1) / 2], 1)
    return _mesh(V, F, np.broadcast_to(n, V.shape), uv)


def plane(size=(10.0, 10.0), n=(8, 8), center=(0.0, 0.0, 0.0)) -> Mesh:
    """Horizontal subdivided plane facing +Y, extent size=(x, z), n=(cells along x, along z)."""
    sx, sz = size
    return quad(center, (0.0, 0.0, sz / 2), (sx / 2, 0.0, 0.0), n[1], n[0])


def box(size=(1.0, 1.0, 1.0), center=(0.0, 0.0, 0.0), n: int = 1) -> Mesh:
    """Axis-aligned box, outward face normals, 4 vertices per side (hard edges), n cells per edge."""
    hx, hy, hz = (s / 2 for s in size)
    c = np.asarray(center, float)
    sides = [
        quad(c + (hx, 0, 0), (0, hy, 0), (0, 0, hz), n, n),    # +x
        quad(c - (hx, 0, 0), (0, 0, hz), (0, hy, 0), n, n),    # -x
        quad(c + (0, hy, 0), (0, 0, hz), (hx, 0, 0), n, n),    # +y
        quad(c - (0, hy, 0), (hx, 0, 0), (0, 0, hz), n, n),    # -y
        quad(c + (0, 0, hz), (hx, 0, 0), (0, hy, 0), n, n),    # +z
        quad(c - (0, 0, hz), (0, hy, 0), (hx, 0, 0), n, n),    # -z
    ]
    return merge(sides).validate()


def niche(width: float = 3.0, height: float = 2.5, depth: float = 2.0, center=(0.0, 0.0, 0.0), n: int = 4,
          floor: bool = True) -> Mesh:
    """Three-walled alcove open towards +Z: back wall, left and right walls (+ floor), normals inward.

    `center` is the middle of the floor's front edge... no: the middle of the floor.
    """
    c = np.asarray(center, float)
    w, h, d = width / 2, height / 2, depth / 2
    parts = [
        quad(c + (0, h, -d), (w, 0, 0), (0, h, 0), n, n),        # back wall, normal +z
        quad(c + (-w, h, 0), (0, 0, d), (0, h, 0), n, n),        # left wall, normal +x
        quad(c + (w, h, 0), (0, h, 0), (0, 0, d), n, n),         # right wall, normal -x
    ]
    if floor:
        parts.append(quad(c, (0, 0, d), (w, 0, 0), n, n))        # floor, normal +y
    return merge(parts).validate()


# -- surfaces of revolution ---------------------------------------------------------------------


def lathe(profile, n_seg: int = 32, crease_deg: float = LATHE_CREASE_DEG) -> Mesh:
    """Revolve a 2-D profile (K, 2) of (radius, y) points about +Y.

    The profile runs from bottom to top; points with radius 0 lie on the axis (one vertex each,
    triangle fans). Normals come from the profile: a segment with direction (dr, dy) has outward
    normal (dy, −dr); at corners turning more than `crease_deg` the ring is duplicated with split
    normals, elsewhere segment normals are length-averaged (smooth).
    """
    P = np.asarray(profile, float)
    if P.ndim != 2 or P.shape[1] != 2 or len(P) < 2:
        raise ValueError(f"lathe profile must be (K>=2, 2), got {P.shape}")
    if (P[:, 0] < 0).any():
        raise ValueError("lathe profile radii must be >= 0")
    if n_seg < 3:
        raise ValueError(f"lathe needs n_seg >= 3, got {n_seg}")
    seg = np.diff(P, axis=0)
    L = np.linalg.norm(seg, axis=1)
    if (L <= 0).any():
        raise ValueError("lathe profile has repeated points")
    sn = np.stack([seg[:, 1], -seg[:, 0]], 1) / L[:, None]  # outward (r, y) normals per segment
    # rings: list of (r, y, n_r, n_y, segments it belongs to)
    rings = []
    K = len(P)
    for k in range(K):
        nb = [s for s in (k - 1, k) if 0 <= s < K - 1]
        if len(nb) == 2:
            cosang = float(seg[nb[0]] @ seg[nb[1]] / (L[nb[0]] * L[nb[1]]))
            turn = math.degrees(math.acos(max(-1.0, min(1.0, cosang))))
            if turn > crease_deg:
                rings.append((k, sn[nb[0]], (nb[0],)))
                rings.append((k, sn[nb[1]], (nb[1],)))
                continue
            nrm = sn[nb[0]] * L[nb[0]] + sn[nb[1]] * L[nb[1]]
        else:
            nrm = sn[nb[0]]
        rings.append((k, nrm / np.linalg.norm(nrm), tuple(nb)))
    phi = np.linspace(0, 2 * math.pi, n_seg, endpoint=False)
    cph, sph = np.cos(phi), np.sin(phi)
    V, N, ring_idx = [], [], []
    off = 0
    for k, nrm, _ in rings:
        r, y = P[k]
        if r == 0.0:
            V.append([[0.0, y, 0.0]])
            N.append([[0.0, 1.0 if nrm[1] >= 0 else -1.0, 0.0]])
            ring_idx.append(np.full(n_seg, off))
            off += 1
        else:
            V.append(np.stack([r * cph, np.full(n_seg, y), r * sph], 1))
            N.append(np.stack([nrm[0] * cph, np.full(n_seg, nrm[1]), nrm[0] * sph], 1))
            ring_idx.append(off + np.arange(n_seg))
            off += n_seg
    F = []
    for s in range(K - 1):
        # the ring of point s used by segment s, and the ring of point s+1 used by segment s
        a = next(i for i, (k, _, nb) in enumerate(rings) if k == s and s in nb)
        b = next(i for i, (k, _, nb) in enumerate(rings) if k == s + 1 and s in nb)
        ra, rb = ring_idx[a], ring_idx[b]
        j = np.arange(n_seg)
        j1 = (j + 1) % n_seg
        za, zb = P[s, 0] == 0.0, P[s + 1, 0] == 0.0
        if za and zb:
            raise ValueError("lathe profile has a segment lying on the axis")
        if not za:
            F.append(np.stack([ra[j], rb[j], ra[j1]], 1))
        if not zb:
            F.append(np.stack([ra[j1], rb[j], rb[j1]], 1))
    return _mesh(np.concatenate(V), np.concatenate(F), np.concatenate(N))


def _arc(cy: float, rad: float, a0: float, a1: float, n: int, cx: float = 0.0) -> list[tuple[float, float]]:
    """Points (r, y) on a circle of radius `rad` centred (cx, cy), angles a0→a1 (deg, 0 = +r)."""
    t = np.radians(np.linspace(a0, a1, n))
    return [(max(0.0, cx + rad * math.cos(a)), cy + rad * math.sin(a)) for a in t]


def _clean(pts) -> np.ndarray:
    P = np.asarray(pts, float)
    P[np.abs(P[:, 0]) < 1e-9, 0] = 0.0
    keep = np.r_[True, np.linalg.norm(np.diff(P, axis=0), axis=1) > 1e-9]
    return P[keep]


def chess_profile(kind: str, detail: int = 8) -> np.ndarray:
    """(K, 2) lathe profiles (radius, y) of chess pieces, height ~1 (king ~1.25); `detail` = arc points."""
    base = [(0.0, 0.0), (0.36, 0.0), (0.36, 0.07), (0.31, 0.1), (0.3, 0.14), (0.24, 0.17)]
    d = max(3, detail)
    if kind == "pawn":
        pts = base + [(0.14, 0.24), (0.11, 0.42), (0.2, 0.46), (0.2, 0.49), (0.1, 0.52)]
        pts += _arc(0.66, 0.16, -62, 90, 2 * d)
    elif kind == "rook":
        pts = base + [(0.22, 0.3), (0.2, 0.62), (0.28, 0.68), (0.28, 0.9), (0.2, 0.9), (0.2, 0.82), (0.0, 0.82)]
    elif kind == "bishop":
        pts = base + [(0.15, 0.26), (0.11, 0.55), (0.21, 0.59), (0.21, 0.62), (0.12, 0.65)]
        pts += [(0.12 + 0.06 * math.sin(math.pi * t), 0.65 + 0.3 * t) for t in np.linspace(0.0, 1.0, d)[1:]]
        pts = [(r if y < 0.95 else 0.0, y) for r, y in pts[:-1]] + [(0.05, 0.95)]
        pts += _arc(1.0, 0.05, -90, 90, d)[1:]
    elif kind == "king":
        pts = base + [(0.16, 0.28), (0.12, 0.7), (0.23, 0.75), (0.23, 0.78), (0.14, 0.8), (0.2, 1.0),
                      (0.2, 1.04), (0.0, 1.04)]
    else:
        raise ValueError(f"unknown chess piece {kind!r} (pawn, rook, bishop, king)")
    return _clean(pts)


def chess_piece(kind: str, *, n_seg: int = 24, detail: int = 8, scale: float = 1.0, center=(0.0, 0.0, 0.0)) -> Mesh:
    """A lathe chess piece standing on y = center.y (`king` gets a cross of two boxes on top)."""
    m = lathe(chess_profile(kind, detail), n_seg)
    if kind == "king":
        m = merge([m, box((0.06, 0.22, 0.06), (0.0, 1.15, 0.0)), box((0.18, 0.06, 0.06), (0.0, 1.17, 0.0))]).validate()
    return _affine(m, scale=scale, translate=center)


def capsule(p0, p1, radius: float, *, n_seg: int = 16, n_len: int = 12, n_cap: int = 5) -> Mesh:
    """Capsule from point p0 to p1 (hemispherical caps), `n_len` rings along the cylinder part."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    L = np.linalg.norm(p1 - p0)
    if L <= 0 or radius <= 0:
        raise ValueError("capsule needs distinct end points and radius > 0")
    prof = _arc(0.0, radius, -90, 0, n_cap + 1)
    prof += [(radius, t) for t in np.linspace(0, L, n_len + 1)[1:-1]]
    prof += _arc(L, radius, 0, 90, n_cap + 1)
    m = lathe(_clean(prof), n_seg, crease_deg=180.0)
    # rotate +Y onto (p1 − p0)
    y = (p1 - p0) / L
    a = np.cross([0.0, 1.0, 0.0], y)
    s, c = np.linalg.norm(a), y[1]
    if s < 1e-12:
        R = np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    else:
        k = a / s
        Kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
        R = np.eye(3) + s * Kx + (1 - c) * Kx @ Kx
    return _affine(m, R=R, translate=p0)
