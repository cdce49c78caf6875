"""Scene bound for the field when neither the config nor the dataset gives one."""

from __future__ import annotations

import numpy as np

from lrslam.camera import backproject_depth, transform_points

__all__ = ["bound_from_frame"]


def bound_from_frame(depth: np.ndarray, K: np.ndarray, T_w_c: np.ndarray, margin: float = 1.0,
                     max_depth: float = 6.0) -> np.ndarray:
    """Axis-aligned bound (3, 2) metres (world frame) around a frame's valid points and camera centre,
    grown by ``margin`` metres on every side. Depths beyond ``max_depth`` are ignored."""
    pts = backproject_depth(depth, K).reshape(-1, 3)
    z = pts[:, 2]
    pts = pts[(z > 0) & (z < max_depth)]
    if len(pts) == 0:
        raise ValueError("cannot derive a scene bound: the first frame has no valid depth")
    pts = np.vstack([transform_points(T_w_c, pts), T_w_c[:3, 3]])
    lo, hi = np.percentile(pts, 0.5, axis=0), np.percentile(pts, 99.5, axis=0)
    lo = np.minimum(lo, T_w_c[:3, 3]) - margin
    hi = np.maximum(hi, T_w_c[:3, 3]) + margin
    return np.stack([lo, hi], axis=1)
