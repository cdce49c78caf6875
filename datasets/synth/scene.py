"""Procedural textured indoor rooms: the geometry and colours behind the synthetic RGB-D sequences.

World frame: metres, z up. The room is the box ``[-sx/2, sx/2] x [-sy/2, sy/2] x [0, sz]`` (floor at z = 0)
with inward-facing walls, floor and ceiling; furniture boxes (yawed about z), cylinders standing on the floor
and spheres (on top of boxes or on the floor) are placed so that they stay >= 0.5 m from the camera region of
:func:`lrslam.datasets.synth.trajectories.camera_region` (low objects may sit below it).

Every surface is one triangle mesh with edges of at most ``mesh_edge`` metres (default 2.5 cm) -- the same mesh
is ray cast by the renderer and written as ``gt_mesh.ply``, so the ground truth is exact. Each triangle belongs
to one *primitive* (floor, ceiling, 4 walls, then objects). Colour is a deterministic function of the 3D point
and its primitive (:meth:`Scene.colour_at`): a base colour modulated by sums of sinusoids along random 3D
directions with wavelengths 6-60 cm (features of 3-30 cm), so every view sees the same smooth, gradient-rich
texture -- what dense photometric tracking needs.
"""

from __future__ import annotations

import colorsys
import logging
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import trimesh

from lrslam.errors import InputError
from lrslam.datasets.synth import meshes
from lrslam.datasets.synth.trajectories import camera_region

__all__ = ["SCENES", "Primitive", "Scene", "make_scene"]

log = logging.getLogger(__name__)

BOUND_MARGIN = 0.1  # metres added around the room to form ``Scene.bound``
CLEARANCE = 0.5  # metres between the camera region and any object
_N_LUMA, _N_ACCENT = 6, 3  # sinusoid components per primitive: luminance pattern, colour-accent pattern

# name -> (default size (sx, sy, sz), counts: tall boxes, tall cylinders, low objects, spheres on boxes)
SCENES: dict[str, tuple[tuple[float, float, float], tuple[int, int, int, int]]] = {
    "room": ((4.0, 3.0, 2.5), (5, 2, 2, 2)),
    "small_room": ((3.0, 2.5, 2.4), (3, 1, 1, 1)),
    "cluttered": ((5.0, 4.0, 2.7), (10, 4, 5, 5)),
    "empty": ((4.0, 3.0, 2.5), (0, 0, 0, 0)),
}


@dataclass(frozen=True)
class Primitive:
    """One textured surface piece. ``kind``: floor, ceiling, wall, box, cylinder or sphere; ``params``: its
    geometry (metres / radians); ``aabb``: (3, 2) axis-aligned bounds in the world frame."""

    kind: str
    params: dict[str, Any]
    aabb: np.ndarray


@dataclass
class Scene:
    """A synthetic room.

    Attributes:
        name, seed, size: how it was made (size = room extents (sx, sy, sz) metres).
        bound: (3, 2) metres, room extents plus a 0.1 m margin (the SLAM field bound).
        primitives: list of :class:`Primitive`; index = primitive id.
        vertices: (V, 3) float64 world coordinates; triangles: (T, 3) int64, counter-clockwise seen from the
            front (walls face into the room, objects outwards); triangle_primitive: (T,) int64 primitive ids.
    """

    name: str
    seed: int
    size: tuple[float, float, float]
    bound: np.ndarray
    primitives: list[Primitive]
    vertices: np.ndarray
    triangles: np.ndarray
    triangle_primitive: np.ndarray
    _base: np.ndarray = field(repr=False)  # (P, 2, 3) base and accent RGB in [0, 1]
    _freq: np.ndarray = field(repr=False)  # (P, K, 3) rad/m
    _phase: np.ndarray = field(repr=False)  # (P, K)
    _amp: np.ndarray = field(repr=False)  # (P, K)
    _raycaster: Any = field(default=None, repr=False)

    @property
    def camera_region(self) -> np.ndarray:
        """(3, 2) box where trajectories keep the camera (>= 0.5 m from every surface)."""
        return camera_region(self.bound)

    def colour_at(self, points: np.ndarray, primitive_ids: np.ndarray) -> np.ndarray:
        """Texture colour (N, 3) uint8 RGB of world points (N, 3) metres lying on primitives (N,) int.

        Deterministic and view independent. Per primitive: luminance ``L = 0.7 + 0.3 tanh(1.2 s1)`` and accent
        weight ``w = 0.5 + 0.5 tanh(s2)``, with ``s1, s2`` unit-variance sums of ``a_k sin(f_k . p + phi_k)``;
        colour = ``(1 - 0.35 w) L base + 0.35 w accent``.
        """
        # float32 on purpose: np.sin is ~10x faster, and phase errors stay below 1e-4 rad inside a room
        points = np.asarray(points, dtype=np.float32).reshape(-1, 3)
        ids = np.asarray(primitive_ids).reshape(-1).astype(np.int64)
        if len(ids) != len(points):
            raise ValueError(f"{len(points)} points but {len(ids)} primitive ids")
        if len(ids) and (ids.min() < 0 or ids.max() >= len(self.primitives)):
            raise ValueError(f"primitive ids must lie in [0, {len(self.primitives)})")
        out = np.empty((len(points), 3), dtype=np.float32)
        order = np.argsort(ids, kind="stable")
        uniq, starts = np.unique(ids[order], return_index=True)
        for pid, sel in zip(uniq, np.split(order, starts[1:])):
            waves = np.sin(points[sel] @ self._freq[pid].T + self._phase[pid]) * self._amp[pid]
            lum = 0.7 + 0.3 * np.tanh(1.2 * waves[:, :_N_LUMA].sum(axis=1))
            w = 0.175 + 0.175 * np.tanh(waves[:, _N_LUMA:].sum(axis=1))
            out[sel] = (1.0 - w)[:, None] * lum[:, None] * self._base[pid, 0] + w[:, None] * self._base[pid, 1]
        return np.clip(np.rint(out * 255.0), 0, 255).astype(np.uint8)

    def vertex_colours(self) -> np.ndarray:
        """(V, 3) uint8 texture colour at every mesh vertex (vertices are not shared between primitives)."""
        vprim = np.zeros(len(self.vertices), dtype=np.int64)
        vprim[self.triangles.reshape(-1)] = np.repeat(self.triangle_primitive, 3)
        return self.colour_at(self.vertices, vprim)

    def triangle_mesh(self):
        """The scene as an ``open3d.geometry.TriangleMesh`` with vertex colours and normals."""
        import open3d as o3d

        mesh = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(self.vertices),
                                         o3d.utility.Vector3iVector(self.triangles.astype(np.int32)))
        mesh.vertex_colors = o3d.utility.Vector3dVector(self.vertex_colours() / 255.0)
        mesh.compute_vertex_normals()
        return mesh

    def __getstate__(self) -> dict:  # picklable (e.g. for distributed runs): the Open3D raycaster is rebuilt
        state = dict(self.__dict__)
        state["_raycaster"] = None
        return state

    def to_trimesh(self) -> trimesh.Trimesh:
        """The scene as a ``trimesh.Trimesh`` (vertex colours set, vertices not merged)."""
        return trimesh.Trimesh(self.vertices, self.triangles, vertex_colors=self.vertex_colours(), process=False)

    def raycaster(self):
        """Cached ``open3d.t.geometry.RaycastingScene`` holding the mesh as one geometry (id 0), so cast_rays'
        ``primitive_ids`` index :attr:`triangles`."""
        if self._raycaster is None:
            import open3d as o3d

            rc = o3d.t.geometry.RaycastingScene()
            rc.add_triangles(o3d.core.Tensor(self.vertices.astype(np.float32)),
                             o3d.core.Tensor(self.triangles.astype(np.uint32)))
            self._raycaster = rc
        return self._raycaster

    def export_mesh(self, path: str | Path) -> Path:
        """Write the mesh (binary PLY, vertex colours + normals) to ``path``; returns the path. ~9 MB for
        ``room``, ~15 MB for ``cluttered`` at the default 2.5 cm edges (kept under 20 MB)."""
        import open3d as o3d

        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if not o3d.io.write_triangle_mesh(str(path), self.triangle_mesh(), write_ascii=False):
            raise OSError(f"{path}: could not write the mesh")
        return path


# ---- layout --------------------------------------------------------------------------------------------------

def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _overlap(a: np.ndarray, b: np.ndarray, gap: float = 0.0) -> bool:
    return bool(np.all(a[:, 0] < b[:, 1] + gap) and np.all(b[:, 0] < a[:, 1] + gap))


class _Layout:
    """Rejection sampling of object placements: inside the room, clear of the camera region, not overlapping."""

    def __init__(self, size: np.ndarray, keep_out: np.ndarray, rng: np.random.Generator):
        self.size, self.keep_out, self.rng = size, keep_out, rng
        self.room = np.array([[-size[0] / 2, size[0] / 2], [-size[1] / 2, size[1] / 2], [0.0, size[2]]])
        self.placed: list[Primitive] = []

    def fits(self, aabb: np.ndarray, ignore: Primitive | None = None) -> bool:
        inside = np.all(aabb[:, 0] >= self.room[:, 0] + [0.02, 0.02, -1e-9]) and \
            np.all(aabb[:, 1] <= self.room[:, 1] - 0.02)
        return bool(inside and not _overlap(aabb, self.keep_out)
                    and not any(_overlap(aabb, p.aabb, 0.03) for p in self.placed if p is not ignore))

    def _xy(self) -> np.ndarray:
        return self.rng.uniform(self.room[:2, 0], self.room[:2, 1])

    def _place(self, kind: str, draw: Callable[[], tuple[dict[str, Any], np.ndarray, Primitive | None]]
               ) -> Primitive | None:
        """Up to 300 draws ``(params, aabb, the placed primitive it may touch or None)``; the first that fits is
        placed and returned; None when none fits."""
        for _ in range(300):
            params, aabb, support = draw()
            if self.fits(aabb, ignore=support):
                p = Primitive(kind, params, aabb)
                self.placed.append(p)
                return p
        return None

    def box(self, low: bool) -> Primitive | None:
        def draw() -> tuple[dict[str, Any], np.ndarray, None]:
            h = self.rng.uniform(0.2, 0.45) if low else self.rng.uniform(0.4, min(1.9, self.size[2] - 0.3))
            half = np.array([self.rng.uniform(0.15, 0.6), self.rng.uniform(0.12, 0.35), h / 2])
            yaw = self.rng.uniform(-0.3, 0.3) + self.rng.integers(0, 4) * np.pi / 2
            R = _rot_z(yaw)
            centre = np.append(self._xy(), h / 2)
            ext = np.abs(R) @ half
            return {"centre": centre, "half": half, "yaw": yaw}, np.stack([centre - ext, centre + ext], axis=1), None

        return self._place("box", draw)

    def cylinder(self, low: bool) -> Primitive | None:
        def draw() -> tuple[dict[str, Any], np.ndarray, None]:
            r = self.rng.uniform(0.08, 0.25)
            h = self.rng.uniform(0.25, 0.45) if low else self.rng.uniform(0.5, min(1.8, self.size[2] - 0.3))
            base = np.append(self._xy(), 0.0)
            aabb = np.stack([base - [r, r, 0], base + [r, r, h]], axis=1)
            return {"base": base, "radius": r, "height": h}, aabb, None

        return self._place("cylinder", draw)

    def sphere(self, on_box: bool) -> Primitive | None:
        boxes = [p for p in self.placed if p.kind == "box"]

        def draw() -> tuple[dict[str, Any], np.ndarray, Primitive | None]:
            r = self.rng.uniform(0.08, 0.2)
            support = boxes[self.rng.integers(len(boxes))] if on_box and boxes else None
            if support is not None:
                centre = np.append(support.params["centre"][:2], 2 * support.params["half"][2] + r)
            else:
                centre = np.append(self._xy(), r)
            return {"centre": centre, "radius": r}, np.stack([centre - r, centre + r], axis=1), support

        return self._place("sphere", draw)


def _texture(rng: np.random.Generator, kind: str) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-primitive colours and sinusoid parameters (see :meth:`Scene.colour_at`)."""
    if kind in ("wall", "ceiling"):
        hsv = (rng.uniform(0, 1), rng.uniform(0.1, 0.35), rng.uniform(0.65, 0.9))
    elif kind == "floor":
        hsv = (rng.uniform(0.05, 0.12), rng.uniform(0.3, 0.6), rng.uniform(0.45, 0.7))
    else:
        hsv = (rng.uniform(0, 1), rng.uniform(0.35, 0.8), rng.uniform(0.5, 0.95))
    base = np.array(colorsys.hsv_to_rgb(*hsv))
    accent = np.array(colorsys.hsv_to_rgb((hsv[0] + rng.uniform(0.25, 0.75)) % 1.0, 0.7, 0.8))
    n = _N_LUMA + _N_ACCENT
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lam = np.exp(rng.uniform(np.log(0.06), np.log(0.6), n))  # wavelength, metres
    amp = (lam / 0.6) ** 0.7  # fine scales weaker: colour gradients stay moderate at the pixel scale
    for sl in (slice(0, _N_LUMA), slice(_N_LUMA, n)):  # unit variance per pattern: sum(a^2)/2 = 1
        amp[sl] /= np.sqrt(0.5 * np.sum(amp[sl] ** 2))
    return np.stack([base, accent]), d * (2 * np.pi / lam)[:, None], rng.uniform(0, 2 * np.pi, n), amp


def make_scene(name: str = "room", seed: int = 0, size: tuple[float, float, float] | None = None,
               mesh_edge: float = 0.025) -> Scene:
    """Build a procedural room.

    Args:
        name: ``room`` (4 x 3 x 2.5 m, 5 cabinets/tables, 2 columns, 2 low objects, 2 spheres on top),
            ``small_room`` (3 x 2.5 x 2.4 m, fewer objects), ``cluttered`` (5 x 4 x 2.7 m, many objects),
            ``empty`` (bare 4 x 3 x 2.5 m box, for closed-form tests).
        seed: layout and texture seed; the same (name, seed, size, mesh_edge) gives the same scene.
        size: room extents (sx, sy, sz) metres, default per name; sx, sy >= 2.0 m and sz >= 2.2 m.
        mesh_edge: longest triangle edge in metres (mesh resolution for vertex colours; the geometry of
            planar faces does not depend on it).
    """
    if name not in SCENES:
        raise InputError(f"unknown scene {name!r}; choose one of {', '.join(SCENES)}")
    default_size, (n_box, n_cyl, n_low, n_sph) = SCENES[name]
    size_a = np.asarray(default_size if size is None else size, dtype=np.float64).reshape(-1)
    if size_a.shape != (3,) or not np.all(np.isfinite(size_a)) or min(size_a[:2]) < 2.0 or size_a[2] < 2.2:
        raise InputError(f"scene size must be (sx, sy, sz) with sx, sy >= 2.0 m and sz >= 2.2 m, got {size}")
    if not 0.005 <= mesh_edge <= 0.5:
        raise InputError(f"mesh_edge must lie in [0.005, 0.5] m, got {mesh_edge}")
    rng = np.random.default_rng([int(seed), zlib.crc32(name.encode())])
    sx, sy, sz = size_a
    room = np.array([[-sx / 2, sx / 2], [-sy / 2, sy / 2], [0.0, sz]])
    bound = room + np.array([-BOUND_MARGIN, BOUND_MARGIN])
    keep_out = camera_region(bound) + np.array([-CLEARANCE - 0.05, CLEARANCE + 0.05])

    # 1. the room: one primitive per face (floor, ceiling, 4 walls), normals pointing inwards
    faces = meshes.box_faces(room.mean(axis=1), size_a / 2, np.eye(3), mesh_edge, inward=True)
    order = [5, 4, 0, 1, 2, 3]  # box_faces order: +x, -x, +y, -y, +z, -z -> floor, ceiling, walls
    kinds = ["floor", "ceiling", "wall", "wall", "wall", "wall"]
    prims = [Primitive(k, {"face": i}, room.copy()) for k, i in zip(kinds, order)]
    parts = [faces[i] for i in order]

    # 2. furniture: tall objects along the walls, low ones anywhere below the camera region, spheres on top
    layout = _Layout(size_a, keep_out, rng)
    placed = [layout.box(low=False) for _ in range(n_box)] + [layout.cylinder(low=False) for _ in range(n_cyl)]
    placed += [layout.box(True) if rng.uniform() < 0.5 else layout.cylinder(True) for _ in range(n_low)]
    placed += [layout.sphere(on_box=i % 2 == 0) for i in range(n_sph)]
    if any(p is None for p in placed):
        log.info("scene %s seed %d: %d of %d objects did not fit", name, seed,
                 sum(p is None for p in placed), len(placed))
    for p in (p for p in placed if p is not None):
        if p.kind == "box":
            geom = meshes.concat(meshes.box_faces(p.params["centre"], p.params["half"], _rot_z(p.params["yaw"]),
                                                  mesh_edge, skip_bottom=True))
        elif p.kind == "cylinder":
            geom = meshes.cylinder(p.params["base"], p.params["radius"], p.params["height"], mesh_edge)
        else:
            geom = meshes.sphere(p.params["centre"], p.params["radius"], mesh_edge)
        prims.append(p)
        parts.append(geom)

    # 3. one mesh, triangle -> primitive map, textures
    verts, tris = meshes.concat(parts)
    tri_prim = np.repeat(np.arange(len(parts)), [len(t) for _, t in parts])
    tex = [_texture(rng, p.kind) for p in prims]
    f32 = lambda i: np.stack([t[i] for t in tex]).astype(np.float32)  # noqa: E731
    return Scene(name=name, seed=int(seed), size=tuple(float(x) for x in size_a), bound=bound, primitives=prims,
                 vertices=verts, triangles=tris.astype(np.int64), triangle_primitive=tri_prim,
                 _base=f32(0), _freq=f32(1), _phase=f32(2), _amp=f32(3))
