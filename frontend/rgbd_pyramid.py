"""Open3D's multi-scale hybrid RGB-D odometry, run level by level on an image pyramid built here.

Why not ``o3d.t.pipelines.odometry.rgbd_odometry_multi_scale`` itself: it smooths the intensity pyramid with
Intel IPP's Gaussian filter, whose output depends on where ``malloc`` put the image (measured with Open3D 0.20
on an AMD EPYC: the same image filtered at different addresses differs by up to 6e-8, periodically with the
allocation pattern, on one thread), so the same two frames registered twice in one process differ by 3e-9 to
2e-6 m and a run is not reproducible bit for bit. Here the two down-sampling steps are numpy element-wise
arithmetic in a fixed order (the same at every address), and every other step is the Open3D kernel the
multi-scale function calls (depth clipping, grey conversion, Sobel gradients, vertex maps, and the per-iteration
Gauss-Newton step ``compute_odometry_result_hybrid``), with its level schedule and stopping rule.

The pyramid of a view depends only on its images and the parameters, so it is cached on the view
(:meth:`~lrslam.frontend.rgbd_view.RGBDView.cached`): a frame registered as target and then as source is
preprocessed once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from lrslam.frontend.rgbd_view import RGBDView

__all__ = ["PyramidLevel", "rgbd_pyramid", "hybrid_odometry", "pyr_down_intensity", "pyr_down_depth"]

# Open3D's PyrDown: Gaussian filter, kernel 5, sigma 1 (replicated border), then every second pixel.
_GAUSS = np.exp(-0.5 * np.arange(-2, 3, dtype=np.float64) ** 2)
_GAUSS = (_GAUSS / _GAUSS.sum()).astype(np.float32)
# Open3D's PyrDownDepth: weights 0.375, 0.25, 0.0625 by pixel offset, neighbours within a depth difference only.
_DEPTH_WEIGHTS = np.array([0.375, 0.25, 0.0625], dtype=np.float32)


def pyr_down_intensity(img: np.ndarray) -> np.ndarray:
    """(H, W) float32 -> (H // 2, W // 2) float32: separable 5-tap Gaussian (sigma 1 px, replicated border),
    then the even rows and columns. Element-wise sums in a fixed order, so the result does not depend on the
    array's address."""
    h, w = img.shape
    p = np.pad(img, 2, mode="edge")
    rows = _GAUSS[0] * p[:, 0:w]
    for k in range(1, 5):
        rows = rows + _GAUSS[k] * p[:, k:k + w]
    out = _GAUSS[0] * rows[0:h]
    for k in range(1, 5):
        out = out + _GAUSS[k] * rows[k:k + h]
    return np.ascontiguousarray(out[0:2 * (h // 2):2, 0:2 * (w // 2):2])


def pyr_down_depth(depth: np.ndarray, max_diff: float) -> np.ndarray:
    """(H, W) float32 depth (NaN = invalid) -> (H // 2, W // 2): at each even pixel, the weighted mean of its
    5x5 neighbours whose depth is within ``max_diff`` (m) of the centre's (weights 0.375 / 0.25 / 0.0625 by
    offset per axis, as Open3D's ``PyrDownDepth``); NaN where the centre is NaN."""
    h, w = depth.shape[0] // 2, depth.shape[1] // 2
    p = np.pad(depth, 2, mode="constant", constant_values=np.nan)
    centre = depth[0:2 * h:2, 0:2 * w:2]
    v_sum = np.zeros((h, w), np.float32)
    w_sum = np.zeros((h, w), np.float32)
    use = np.empty((h, w), bool)
    term = np.empty((h, w), np.float32)
    with np.errstate(invalid="ignore"):
        for dy in range(-2, 3):
            for dx in range(-2, 3):
                v = p[2 + dy:2 + dy + 2 * h:2, 2 + dx:2 + dx + 2 * w:2]
                np.less(np.abs(v - centre), np.float32(max_diff), out=use)       # False for NaN
                wt = _DEPTH_WEIGHTS[abs(dx)] * _DEPTH_WEIGHTS[abs(dy)]
                # Skipped neighbours add exactly 0 (x + 0 == x), so the sums are those of the skipping loop.
                np.multiply(np.where(use, v, np.float32(0)), wt, out=term)
                v_sum += term
                w_sum += np.where(use, wt, np.float32(0))
        out = v_sum / np.where(w_sum == 0, np.float32(1), w_sum)
    out[w_sum == 0] = np.nan
    return out


@dataclass(frozen=True)
class PyramidLevel:
    """One level of a view's pyramid as Open3D tensors (rows, cols, 1) float32 unless said: ``depth`` (m,
    NaN beyond ``depth_max``; 0 where the input had no depth), ``intensity`` (0..1), their Sobel gradients,
    ``vertex`` (rows, cols, 3) camera-frame points (m), and ``K`` (3, 3) float64 intrinsics of the level."""

    depth: Any
    intensity: Any
    depth_dx: Any
    depth_dy: Any
    intensity_dx: Any
    intensity_dy: Any
    vertex: Any
    K: Any


def rgbd_pyramid(view: RGBDView, n_levels: int, depth_max: float, depth_outlier_trunc: float) -> list[PyramidLevel]:
    """The view's pyramid, finest level first (cached on the view). Depth beyond ``depth_max`` (m) is invalid;
    depth is down-sampled with neighbours within ``2 * depth_outlier_trunc`` (m), as Open3D does."""
    import open3d as o3d

    def build() -> list[PyramidLevel]:
        Image = o3d.t.geometry.Image
        depth = Image(np.ascontiguousarray(view.depth[..., None])).clip_transform(1.0, 0.0, depth_max, np.nan)
        grey = Image(view.rgb).rgb_to_gray().to(o3d.core.Dtype.Float32)
        d, g = depth.as_tensor().numpy()[..., 0].copy(), grey.as_tensor().numpy()[..., 0].copy()
        K = np.asarray(view.K, dtype=np.float64).copy()
        levels = []
        for i in range(n_levels):
            if i > 0:
                d, g = pyr_down_depth(d, 2.0 * depth_outlier_trunc), pyr_down_intensity(g)
                K = K / 2.0
                K[2, 2] = 1.0
            # o3d.core.Tensor copies (the Open3D image owns its memory).
            d_img, g_img = Image(o3d.core.Tensor(d[..., None])), Image(o3d.core.Tensor(g[..., None]))
            K_t = o3d.core.Tensor(K)
            d_dx, d_dy = d_img.filter_sobel()
            g_dx, g_dy = g_img.filter_sobel()
            levels.append(PyramidLevel(d_img.as_tensor(), g_img.as_tensor(), d_dx.as_tensor(), d_dy.as_tensor(),
                                       g_dx.as_tensor(), g_dy.as_tensor(),
                                       d_img.create_vertex_map(K_t, np.nan).as_tensor(), K_t))
        return levels

    return view.cached(("pyramid", n_levels, depth_max, depth_outlier_trunc), build)


def hybrid_odometry(source: RGBDView, target: RGBDView, init_T_tgt_src: np.ndarray, iterations: tuple[int, ...],
                    relative_fitness: float, relative_rmse: float, depth_max: float, depth_outlier_trunc: float,
                    depth_huber_delta: float, intensity_huber_delta: float) -> np.ndarray:
    """``T_tgt_src`` (4x4 float64) by Open3D's hybrid (photometric + geometric) Gauss-Newton steps, coarse to
    fine: ``iterations[k]`` steps at level ``k`` (the first the coarsest, as ``OdometryConvergenceCriteria``),
    stopping a level early when both the fitness and the inlier RMSE change by less than their relative
    tolerances. Raises what Open3D raises (no inliers)."""
    import open3d as o3d

    od = o3d.t.pipelines.odometry
    n = len(iterations)
    src = rgbd_pyramid(source, n, depth_max, depth_outlier_trunc)
    tgt = rgbd_pyramid(target, n, depth_max, depth_outlier_trunc)
    T = np.asarray(init_T_tgt_src, dtype=np.float64).copy()
    rmse, fitness = 0.0, 1.0
    for level, max_iter in zip(reversed(range(n)), iterations):
        s, t = src[level], tgt[level]
        for _ in range(max_iter):
            step = od.compute_odometry_result_hybrid(
                s.depth, t.depth, s.intensity, t.intensity, t.depth_dx, t.depth_dy, t.intensity_dx, t.intensity_dy,
                s.vertex, s.K, o3d.core.Tensor(T), depth_outlier_trunc, depth_huber_delta, intensity_huber_delta)
            T = step.transformation.numpy().astype(np.float64) @ T
            if (_relative_change(fitness, step.fitness) < relative_fitness
                    and _relative_change(rmse, step.inlier_rmse) < relative_rmse):
                break
            rmse, fitness = step.inlier_rmse, step.fitness
    return T


def _relative_change(before: float, after: float) -> float:
    """``|before - after| / before`` as Open3D computes it; inf for ``before`` 0, so the first step (from the
    initial RMSE 0) never counts as converged."""
    return abs(before - after) / before if before != 0 else float("inf")
