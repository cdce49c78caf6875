"""The one module that owns the camera convention.

Camera frame: OpenCV — x right, y down, z forward (optical axis), metres. A pixel ``(u, v)`` (column, row,
integer at the pixel's top-left corner sample, as numpy indexing) back-projects along
``((u - cx) / fx, (v - cy) / fy, 1)``. Depth is the metric z coordinate (not the ray length), 0 = invalid.

ESLAM (and NeRF code) uses OpenGL camera axes (x right, y up, z backward). Convert poses only through
:func:`opengl_to_opencv_pose` / :func:`opencv_to_opengl_pose`.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "OPENGL_FROM_OPENCV", "intrinsics_matrix", "backproject_depth", "pixel_directions", "project_points",
    "opengl_to_opencv_pose", "opencv_to_opengl_pose", "transform_points", "check_intrinsics",
    "strided_intrinsics", "block_intrinsics",
]

# Flips y and z: maps OpenCV camera coordinates to OpenGL camera coordinates (its own inverse).
OPENGL_FROM_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])


def intrinsics_matrix(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """3x3 float64 pinhole matrix from focal lengths and principal point (pixels)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def check_intrinsics(K: np.ndarray, width: int | None = None, height: int | None = None) -> np.ndarray:
    """Validate a 3x3 pinhole matrix (positive finite focal lengths, principal point inside the image when the
    image size is given). Returns it as float64; raises ValueError with a one-line reason otherwise."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise ValueError(f"intrinsics must be a finite 3x3 matrix, got shape {K.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise ValueError(f"intrinsics focal lengths must be positive, got fx={K[0, 0]} fy={K[1, 1]}")
    if not np.allclose(K[2], [0, 0, 1]):
        raise ValueError("intrinsics last row must be [0, 0, 1]")
    if width is not None and height is not None:
        if not (0 < K[0, 2] < width and 0 < K[1, 2] < height):
            raise ValueError(f"principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) lies outside the "
                             f"{width}x{height} image: wrong intrinsics for this image size?")
    return K


def pixel_directions(K: np.ndarray, height: int, width: int) -> np.ndarray:
    """Per-pixel ray directions with unit z in the camera frame: (H, W, 3) float64."""
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    return np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], axis=-1)


def backproject_depth(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Depth (H, W) metres (z-depth) -> camera-frame points (H, W, 3); invalid pixels give z = 0 points."""
    depth = np.asarray(depth, dtype=np.float64)
    return pixel_directions(K, *depth.shape) * depth[..., None]


def project_points(points_c: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) -> pixel coordinates (N, 2) as (u, v) and depth z (N,)."""
    p = np.asarray(points_c, dtype=np.float64)
    z = p[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = np.stack([K[0, 0] * p[:, 0] / z + K[0, 2], K[1, 1] * p[:, 1] / z + K[1, 2]], axis=-1)
    return uv, z


def transform_points(T_a_b: np.ndarray, points_b: np.ndarray) -> np.ndarray:
    """Apply a 4x4 pose to points (N, 3) in frame b -> (N, 3) in frame a."""
    p = np.asarray(points_b, dtype=np.float64)
    return p @ T_a_b[:3, :3].T + T_a_b[:3, 3]


def opengl_to_opencv_pose(T_w_c_gl: np.ndarray) -> np.ndarray:
    """Camera-to-world pose with OpenGL camera axes -> the same camera with OpenCV axes."""
    return np.asarray(T_w_c_gl, dtype=np.float64) @ OPENGL_FROM_OPENCV


def opencv_to_opengl_pose(T_w_c_cv: np.ndarray) -> np.ndarray:
    """Camera-to-world pose with OpenCV camera axes -> the same camera with OpenGL axes."""
    return np.asarray(T_w_c_cv, dtype=np.float64) @ OPENGL_FROM_OPENCV


def strided_intrinsics(K: np.ndarray, stride: int) -> np.ndarray:
    """Intrinsics of ``image[::stride, ::stride]``: new pixel u' is old pixel ``stride * u'``, so
    ``f' = f / stride`` and ``c' = c / stride``."""
    K = np.asarray(K, dtype=np.float64).copy()
    K[:2] /= stride
    return K


def block_intrinsics(K: np.ndarray, factor: int) -> np.ndarray:
    """Intrinsics of an image averaged over ``factor`` x ``factor`` blocks: new pixel u' is centred on old
    ``factor * u' + (factor - 1) / 2``, so ``f' = f / factor`` and ``c' = (c + 0.5) / factor - 0.5``."""
    K = np.asarray(K, dtype=np.float64).copy()
    K[:2, :2] /= factor
    K[:2, 2] = (K[:2, 2] + 0.5) / factor - 0.5
    return K
