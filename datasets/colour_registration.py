"""Colour registered to depth: the colour image resampled into the depth camera, for sensors whose two cameras
were recorded unregistered (Microsoft 7-Scenes: a Kinect v1 with a 525-pixel colour focal length, 585 for depth,
about 2.5 cm apart).

Every depth pixel ``(u, v)`` with depth ``z`` is the point ``X_d = z K_d^-1 [u, v, 1]`` of the depth camera; it is
seen by the colour camera at ``K_c (R X_d + t)``, where ``T_c_d = [R | t]`` maps depth-camera points into the
colour camera. The registered image takes the colour there (bilinear, ``cv2.remap``). A pixel without depth takes
the colour of its direction (the point at infinity: ``K_c R K_d^-1 [u, v, 1]``), the same homography the parallax
goes to far away. Occlusion between the two views (2.5 cm apart) is ignored.

Without it a tracker that compares the colour image with a map built in the depth camera's geometry reads colour
features 525 / 585 = 0.90 times as far from the image centre as the depth puts them, so a lateral motion looks
10 % shorter in colour than in depth (docs/BENCHMARKS.md section 23).
"""

from __future__ import annotations

import numpy as np

__all__ = ["ColourToDepth"]


class ColourToDepth:
    """Resamples colour images into a depth camera's pixel grid.

    Args:
        K_depth: (3, 3) depth camera intrinsics, pixels of the depth image.
        K_colour: (3, 3) colour camera intrinsics, pixels of the colour image.
        T_colour_depth: (4, 4) maps points in the depth camera's frame into the colour camera's (metres).
    """

    def __init__(self, K_depth: np.ndarray, K_colour: np.ndarray, T_colour_depth: np.ndarray) -> None:
        self.K_depth = np.asarray(K_depth, dtype=np.float64)
        self.K_colour = np.asarray(K_colour, dtype=np.float64)
        self.T_colour_depth = np.asarray(T_colour_depth, dtype=np.float64)
        self._rays: dict[tuple[int, int], np.ndarray] = {}

    def _unit_rays(self, width: int, height: int) -> np.ndarray:
        """(H, W, 3) float64 ``K_d^-1 [u, v, 1]`` of every depth pixel (cached per size)."""
        key = (width, height)
        if key not in self._rays:
            u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
            pix = np.stack([u, v, np.ones_like(u)], axis=-1)
            self._rays[key] = pix @ np.linalg.inv(self.K_depth).T
        return self._rays[key]

    def sample_positions(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where each depth pixel is seen in the colour image.

        Args:
            depth: (H, W) float metres, 0 = invalid.
        Returns:
            ``(map_x, map_y)``, each (H, W) float32: colour-image pixel coordinates (``cv2.remap`` maps).
        """
        h, w = depth.shape
        rays = self._unit_rays(w, h)
        R, t = self.T_colour_depth[:3, :3], self.T_colour_depth[:3, 3]
        z = depth.astype(np.float64)[..., None]
        valid = z > 0
        # a pixel with depth: its point; without: its direction (t vanishes at infinity)
        X_c = np.where(valid, (rays * z) @ R.T + t, rays @ R.T)
        p = X_c @ self.K_colour.T
        zc = p[..., 2]
        ok = zc > 1e-9
        safe = np.where(ok, zc, 1.0)
        map_x = np.where(ok, p[..., 0] / safe, -1.0).astype(np.float32)
        map_y = np.where(ok, p[..., 1] / safe, -1.0).astype(np.float32)
        return map_x, map_y

    def __call__(self, rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """``rgb`` (Hc, Wc, 3) uint8 in the colour camera -> (H, W, 3) uint8 on ``depth``'s (H, W) pixel grid."""
        import cv2

        map_x, map_y = self.sample_positions(depth)
        return cv2.remap(rgb, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
