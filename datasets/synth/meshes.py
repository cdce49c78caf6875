"""Triangle meshes of the synthetic scene's primitives, at a given maximum edge length.

Each builder returns ``(vertices (V, 3) float64 metres, triangles (T, 3) int64)``, counter-clockwise seen from
the front (the side the normal points to). Flat faces are regular grids, so their geometry does not depend on
the edge length; curved ones (cylinder side, sphere) are polyhedra that *are* the scene's exact geometry.
"""

from __future__ import annotations

import numpy as np
import trimesh

__all__ = ["grid_rect", "concat", "box_faces", "cylinder", "sphere"]


def grid_rect(origin: np.ndarray, U: np.ndarray, V: np.ndarray, edge: float) -> tuple[np.ndarray, np.ndarray]:
    """Rectangle origin + a U + b V, a, b in [0, 1], as a regular grid; front normal along U x V."""
    nu = max(1, int(np.ceil(np.linalg.norm(U) / edge)))
    nv = max(1, int(np.ceil(np.linalg.norm(V) / edge)))
    a, b = np.meshgrid(np.linspace(0, 1, nu + 1), np.linspace(0, 1, nv + 1), indexing="ij")
    verts = origin + a.reshape(-1, 1) * U + b.reshape(-1, 1) * V
    i, j = np.meshgrid(np.arange(nu), np.arange(nv), indexing="ij")
    v00 = (i * (nv + 1) + j).reshape(-1)
    v10, v01, v11 = v00 + nv + 1, v00 + 1, v00 + nv + 2
    tris = np.concatenate([np.stack([v00, v10, v11], -1), np.stack([v00, v11, v01], -1)])
    return verts, tris


def concat(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    """Merge meshes into one (vertices are not shared between parts)."""
    verts, tris, off = [], [], 0
    for v, t in parts:
        verts.append(v)
        tris.append(t + off)
        off += len(v)
    return np.concatenate(verts), np.concatenate(tris)


def box_faces(centre: np.ndarray, half: np.ndarray, R: np.ndarray, edge: float, inward: bool = False,
              skip_bottom: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
    """The 6 faces (or 5 without the -z face) of the box ``centre + R @ [-half, half]^3`` as separate grids;
    normals outward (or inward, for a room)."""
    faces = []
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        for s in (1.0, -1.0):
            if skip_bottom and a == 2 and s < 0:
                continue
            eb, ec, ea = np.eye(3)[b] * 2 * half[b], np.eye(3)[c] * 2 * half[c], np.eye(3)[a] * half[a]
            corner = s * ea - 0.5 * eb - 0.5 * ec
            U, V = (eb, ec) if (s > 0) != inward else (ec, eb)
            v, t = grid_rect(corner, U, V, edge)
            faces.append((centre + v @ R.T, t))
    return faces


def cylinder(base: np.ndarray, radius: float, height: float, edge: float) -> tuple[np.ndarray, np.ndarray]:
    """Vertical cylinder standing on ``base`` (side + top cap, no bottom), outward normals."""
    ns = int(np.clip(np.ceil(2 * np.pi * radius / edge), 24, 256))
    nh = max(1, int(np.ceil(height / edge)))
    th = np.linspace(0, 2 * np.pi, ns + 1)
    z = np.linspace(0, height, nh + 1)
    T, Z = np.meshgrid(th, z, indexing="ij")
    side_v = np.stack([radius * np.cos(T), radius * np.sin(T), Z], -1).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(ns), np.arange(nh), indexing="ij")
    v00 = (i * (nh + 1) + j).reshape(-1)
    v10, v01, v11 = v00 + nh + 1, v00 + 1, v00 + nh + 2
    side_t = np.concatenate([np.stack([v00, v10, v11], -1), np.stack([v00, v11, v01], -1)])
    nr = max(1, int(np.ceil(radius / edge)))
    rr = np.linspace(0, radius, nr + 1)[1:]
    R_, T_ = np.meshgrid(rr, th[:-1], indexing="ij")  # ring k, angle m
    cap_v = np.concatenate([[[0.0, 0.0, height]],
                            np.stack([R_ * np.cos(T_), R_ * np.sin(T_), np.full_like(R_, height)], -1).reshape(-1, 3)])
    m = np.arange(ns)
    ring = lambda k, mm: 1 + k * ns + (mm % ns)  # noqa: E731
    cap_t = [np.stack([np.zeros(ns, dtype=np.int64), ring(0, m), ring(0, m + 1)], -1)]
    for k in range(nr - 1):
        cap_t += [np.stack([ring(k, m), ring(k + 1, m), ring(k + 1, m + 1)], -1),
                  np.stack([ring(k, m), ring(k + 1, m + 1), ring(k, m + 1)], -1)]
    v, t = concat([(side_v, side_t), (cap_v, np.concatenate(cap_t))])
    return v + base, t


def sphere(centre: np.ndarray, radius: float, edge: float) -> tuple[np.ndarray, np.ndarray]:
    level = int(np.clip(np.ceil(np.log2(1.05 * radius / edge)), 2, 6))  # icosphere edge ~ 1.05 r / 2^level
    m = trimesh.creation.icosphere(subdivisions=level, radius=radius)
    return np.asarray(m.vertices) + centre, np.asarray(m.faces, dtype=np.int64)
