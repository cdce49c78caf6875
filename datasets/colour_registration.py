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

from lrslam.camera import pixel_directions, project_points, transform_points

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
        self._rays: dict[tuple[int, int], np.ndarray] = {}   # (H, W) -> pixel_directions of the depth camera

    def sample_positions(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where each depth pixel is seen in the colour image.

        Args:
            depth: (H, W) float metres, 0 = invalid.
        Returns:
            ``(map_x, map_y)``, each (H, W) float32: colour-image pixel coordinates (``cv2.remap`` maps).
        """
        h, w = depth.shape
        if (h, w) not in self._rays:
            self._rays[(h, w)] = pixel_directions(self.K_depth, h, w)
        rays = self._rays[(h, w)].reshape(-1, 3)
        z = depth.astype(np.float64).reshape(-1, 1)
        # a pixel with depth: its point; without: its direction (the translation vanishes at infinity)
        X_c = np.where(z > 0, transform_points(self.T_colour_depth, rays * z), rays @ self.T_colour_depth[:3, :3].T)
        uv, zc = project_points(X_c, self.K_colour)
        uv = np.where((zc > 1e-9)[:, None], uv, -1.0).astype(np.float32).reshape(h, w, 2)
        return np.ascontiguousarray(uv[..., 0]), np.ascontiguousarray(uv[..., 1])

    def __call__(self, rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """``rgb`` (Hc, Wc, 3) uint8 in the colour camera -> (H, W, 3) uint8 on ``depth``'s (H, W) pixel grid."""
        import cv2

        map_x, map_y = self.sample_positions(depth)
        return cv2.remap(rgb, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
