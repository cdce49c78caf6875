"""Ray-cast RGB-D rendering of a synthetic :class:`~lrslam.datasets.synth.scene.Scene` (Open3D Embree).

Rays are built here from :func:`lrslam.camera.pixel_directions` -- pixel (u, v) looks along
``((u - cx) / fx, (v - cy) / fy, 1)``, exactly the back-projection convention -- instead of
``RaycastingScene.create_rays_pinhole``, which would shoot through ``u + 0.5`` (see DESIGN.md). The
directions have unit camera z, so the hit parameter ``t_hit`` *is* the z-depth (no conversion, no rounding
beyond float32). Colour comes from :meth:`Scene.colour_at` at the hit point; at silhouette pixels it is averaged
over ``antialias x antialias`` sub-pixel rays (box filter over the pixel area, like a real sensor). The depth is
always the single ray through the pixel sample point, so back-projected depth lies on the mesh exactly.
"""

from __future__ import annotations

import numpy as np

from lrslam.camera import check_intrinsics, pixel_directions

__all__ = ["default_intrinsics", "Renderer", "render"]


def default_intrinsics(width: int = 320, height: int = 240) -> np.ndarray:
    """Default pinhole K (3, 3) for a width x height image: fx = fy = 260 * width / 320 (about 63.2 deg
    horizontal field of view, like a Kinect / Realsense), principal point at the image centre
    ``cx = (width - 1) / 2``, ``cy = (height - 1) / 2`` (pixel centres at integer coordinates)."""
    f = 260.0 * width / 320.0
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


class Renderer:
    """Renders one scene with one camera; rays in the camera frame are built once.

    Args:
        scene: the :class:`Scene` (its cached RaycastingScene is used).
        K: (3, 3) pinhole intrinsics (pixels); width, height: image size.
        antialias: sub-pixel rays per axis for the colour (1 = one ray per pixel).
    """

    def __init__(self, scene, K: np.ndarray, width: int, height: int, antialias: int = 2):
        self.scene = scene
        self.K = check_intrinsics(K, width, height)
        self.width, self.height = int(width), int(height)
        self.antialias = int(antialias)
        if self.antialias < 1:
            raise ValueError(f"antialias must be >= 1, got {antialias}")
        self._dirs = pixel_directions(self.K, self.height, self.width).reshape(-1, 3)  # unit z
        n = self.antialias
        if n > 1:
            offs = (np.arange(n) + 0.5) / n - 0.5  # sub-pixel offsets in pixels, centred on the sample point
            du, dv = np.meshgrid(offs / self.K[0, 0], offs / self.K[1, 1])
            sub = np.stack([du.ravel(), dv.ravel(), np.zeros(n * n)], axis=-1)  # (n^2, 3)
            self._sub_dirs = (self._dirs[:, None, :] + sub[None]).reshape(-1, 3)
        else:
            self._sub_dirs = None

    def cast(self, T_w_c: np.ndarray, dirs_c: np.ndarray) -> dict[str, np.ndarray]:
        """Cast camera-frame directions (M, 3) from pose T_w_c (4, 4). Returns ``t`` (M,) float32 in units
        of the direction length (inf = miss), ``points`` (M, 3) float32 world hit points (0 = miss) and
        ``primitive`` (M,) int64 scene primitive ids (-1 = miss)."""
        import open3d as o3d

        T = np.asarray(T_w_c, dtype=np.float64)
        rays = np.empty((len(dirs_c), 6), dtype=np.float32)
        rays[:, :3] = T[:3, 3]
        rays[:, 3:] = dirs_c @ T[:3, :3].T
        hit = self.scene.raycaster().cast_rays(o3d.core.Tensor.from_numpy(rays))
        t = hit["t_hit"].numpy()
        ok = np.isfinite(t)
        prim = np.full(len(t), -1, dtype=np.int64)
        prim[ok] = self.scene.triangle_primitive[hit["primitive_ids"].numpy()[ok]]
        points = rays[:, :3] + np.where(ok, t, 0.0)[:, None] * rays[:, 3:]  # float32: used for colours only
        return {"t": t, "points": points, "primitive": prim}

    def _colour(self, hit: dict[str, np.ndarray]) -> np.ndarray:
        ok = hit["primitive"] >= 0
        col = np.zeros((len(ok), 3))
        col[ok] = self.scene.colour_at(hit["points"][ok], hit["primitive"][ok])
        return col

    def _edges(self, prim: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """(H*W,) bool: pixels whose 4-neighbourhood sees another primitive or a depth jump > 5 %."""
        P, D = prim.reshape(self.height, self.width), depth.reshape(self.height, self.width)
        edge = np.zeros(P.shape, dtype=bool)
        for ax in (0, 1):
            sl_a = (slice(None, -1), slice(None)) if ax == 0 else (slice(None), slice(None, -1))
            sl_b = (slice(1, None), slice(None)) if ax == 0 else (slice(None), slice(1, None))
            jump = (P[sl_a] != P[sl_b]) | (np.abs(D[sl_a] - D[sl_b]) > 0.05 * np.minimum(D[sl_a], D[sl_b]))
            edge[sl_a] |= jump
            edge[sl_b] |= jump
        return edge.reshape(-1)

    def render(self, T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Render pose T_w_c (4, 4, camera-to-world, OpenCV axes) -> (rgb (H, W, 3) uint8, depth (H, W)
        float32 metres z-depth, 0 where no surface is hit).

        Colour is supersampled (antialias^2 sub-pixel rays, box filter) only at silhouette pixels (see
        :meth:`_edges`); elsewhere one sample suffices because the texture is smooth at the pixel scale
        (wavelengths >= 6 cm)."""
        hit = self.cast(T_w_c, self._dirs)
        depth = np.where(np.isfinite(hit["t"]), hit["t"], 0.0).astype(np.float32)  # unit-z rays: t = z
        col = self._colour(hit)
        if self._sub_dirs is not None:
            n2 = self.antialias ** 2
            edge = np.flatnonzero(self._edges(hit["primitive"], depth))
            if len(edge):
                sub = self._sub_dirs.reshape(-1, n2, 3)[edge].reshape(-1, 3)
                col[edge] = self._colour(self.cast(T_w_c, sub)).reshape(-1, n2, 3).mean(axis=1)
        rgb = np.clip(np.rint(col), 0, 255).astype(np.uint8)
        return rgb.reshape(self.height, self.width, 3), depth.reshape(self.height, self.width)


def render(scene, T_w_c: np.ndarray, K: np.ndarray, width: int, height: int,
           antialias: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """One-shot :meth:`Renderer.render` (build a :class:`Renderer` to render many frames)."""
    return Renderer(scene, K, width, height, antialias).render(T_w_c)
