"""Pairwise RGB-D registration: Open3D hybrid RGB-D odometry, Open3D ICP, or KISS-ICP, behind one function.

``register_rgbd(source, target, init_T_tgt_src, registration, gates)`` returns ``T_tgt_src``: the pose of the
source camera in the target camera, i.e. it maps source-camera points into the target camera
(``inv(T_w_tgt) @ T_w_src``). This is what Open3D's ``rgbd_odometry_multi_scale`` and ``registration.icp``
return for (source, target), and what GTSAM's ``BetweenFactorPose3(tgt, src, T_tgt_src)`` expects.
``registration`` (:class:`RegistrationConfig`) says how to register, ``gates`` (:class:`RegistrationGates`)
when to accept.

Methods (``RegistrationConfig.method``):

- ``rgbd``: Open3D's multi-scale hybrid RGB-D odometry (photometric + geometric, image pyramid), run level by
  level on a pyramid built in :mod:`lrslam.frontend.rgbd_pyramid` (the steps of ``rgbd_odometry_multi_scale``
  with ``Method.Hybrid``, but bit-reproducible). Open3D's photometric term associates each source pixel with
  the *nearest* target pixel, which biases the result by a fraction of a pixel: 1-3.4 mm at 320x240 on the
  synthetic room of the tests. An optional full-resolution point-to-plane polish (``refine_iterations`` > 0,
  geometry well conditioned) removes that bias on clean synthetic data (0.1-0.3 mm), but made the
  frame-to-frame ATE worse on real data (TUM fr1/rpy, 120 frames at 320x240: 8.4 vs 4.8 cm; 7-Scenes
  redkitchen, 150 frames: 3.6 vs 2.4 cm, although its median per-frame error there was lower, 2.4 vs 3.7 mm),
  so it is off by default.
- ``icp``: ``o3d.t.pipelines.registration.multi_scale_icp`` on back-projected, voxel-downsampled points,
  point-to-plane or coloured ICP.
- ``kiss``: KISS-ICP's registration (point-to-point, robust kernel, voxel hash map of the target) on
  back-projected points, coarse-to-fine over ``kiss_levels`` voxel sizes (KISS-ICP searches correspondences
  only in neighbouring voxels, so one fine scale cannot recover more than about a voxel of motion).

Whatever the method, fitness, inlier RMSE and the information matrix come from one projective measure
(:func:`lrslam.frontend.rgbd_view.assess_alignment`), and the same gates (:class:`RegistrationGates`)
decide ``ok``.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field, model_validator

from lrslam.camera import backproject_depth
from lrslam.config import StrictModel
from lrslam.errors import InputError
from lrslam.frontend.rgbd_pyramid import hybrid_odometry
from lrslam.frontend.rgbd_view import (FrameLike, RGBDView, as_view, assess_alignment,
                                       normal_spread, valid_mask, view_problem)
from lrslam.geometry import diagonal_information, is_valid_pose, orthonormalise, pose_error

__all__ = ["RegistrationConfig", "RegistrationGates", "RegistrationResult", "register_rgbd", "fallback_information",
           "frame_problem"]

log = logging.getLogger(__name__)

# The point-to-plane polish after hybrid RGB-D odometry only removes a sub-pixel bias: a larger move (m, deg)
# means the geometry pulled somewhere the photometric term disagrees with, and the hybrid result is kept.
_POLISH_MAX_TRANSLATION = 0.02
_POLISH_MAX_ROTATION = 1.0


class RegistrationConfig(StrictModel):
    """How a pairwise registration runs: method, depth range, iterations, method parameters and the
    information normalisation. Distances in metres."""

    method: Literal["rgbd", "icp", "kiss"] = "rgbd"
    depth_min: float = Field(0.1, gt=0)
    depth_max: float = Field(4.0, gt=0)
    # Iterations per scale, coarse to fine: image pyramid levels (rgbd) or voxel scales (icp).
    iterations: tuple[int, ...] = (20, 10, 5)
    relative_rmse: float = Field(1e-6, ge=0)
    relative_fitness: float = Field(1e-6, ge=0)
    # rgbd (Open3D OdometryLossParams) and the point-to-plane polish (0 = off).
    depth_outlier_trunc: float = Field(0.07, gt=0)
    depth_huber_delta: float = Field(0.05, gt=0)
    intensity_huber_delta: float = Field(0.1, gt=0)
    refine_iterations: int = Field(0, ge=0)
    # icp / kiss: finest voxel size; icp scale i of n uses voxel_size * 2**(n-1-i) and a correspondence
    # distance of icp_distance_factor voxels.
    voxel_size: float = Field(0.02, gt=0)
    icp_estimation: Literal["point_to_plane", "colored"] = "point_to_plane"
    icp_distance_factor: float = Field(2.5, gt=0)
    kiss_levels: int = Field(4, gt=0, description="KISS-ICP voxel scales voxel_size * 2**k, k = levels-1 .. 0 "
                             "(its correspondence search only reaches the neighbouring voxels)")
    kiss_max_points_per_voxel: int = Field(20, gt=0)
    kiss_max_iterations: int = Field(100, gt=0)
    # Quality measure (projective association) and information normalisation.
    max_correspondence_distance: float = Field(0.05, gt=0)
    information_sigma: float = Field(0.01, gt=0, description="unit point noise (m) of the normalised "
                                     "information; the inlier RMSE replaces it when larger")

    @model_validator(mode="after")
    def _check(self) -> "RegistrationConfig":
        if self.depth_min >= self.depth_max:
            raise ValueError(f"depth_min ({self.depth_min}) must be < depth_max ({self.depth_max})")
        if not self.iterations or any(i <= 0 for i in self.iterations):
            raise ValueError(f"iterations must be a non-empty list of positive counts, got {self.iterations}")
        return self

    @property
    def uses_colour(self) -> bool:
        """The method's cost uses colour (so a textured frame with degenerate geometry is still usable)."""
        return self.method == "rgbd" or (self.method == "icp" and self.icp_estimation == "colored")


class RegistrationGates(StrictModel):
    """When a frame can be registered and a registration is accepted, and the information of a failed one.
    Distances in metres, angles in degrees."""

    # Result gates.
    min_fitness: float = Field(0.3, ge=0, le=1)
    trusted_fitness: float = Field(
        0.55, ge=0, le=1, description="an accepted registration whose fitness is below this is kept by the frontend "
        "but not trusted as a measurement: the per-frame fusion takes the field's word for the frame and the pose "
        "graph gets no odometry factor from it (the noise estimate still counts its error). Measured (frontend "
        "alone, each frame's step against ground truth): fitness < 0.55 on 13 of 41 steps of 7-Scenes redkitchen "
        "at every 12th frame and 4 of 39 of TUM fr1/rpy at every 3rd, step errors 6-21 cm; never on the excerpts "
        "at their own strides or on the synthetic sequences")
    max_inlier_rmse: float = Field(0.03, gt=0)
    max_translation: float = Field(0.3, gt=0, description="largest correction of the initial guess, and (in "
                                   "Odometry) largest motion per frame (m)")
    max_rotation: float = Field(20.0, gt=0, description="same, rotation (deg)")
    # Frame gates (frame_problem); min_normal_spread also decides whether the rgbd polish runs.
    min_valid_depth_fraction: float = Field(0.05, ge=0, le=1)
    min_intensity_std: float = Field(0.01, ge=0, description="grey-level std (0..1) below which a frame is "
                                     "textureless")
    min_normal_spread: float = Field(0.01, ge=0, description="smallest eigenvalue of mean(n n^T) below which "
                                     "the geometry is degenerate (a single plane gives 0)")
    # Information of a failed registration (the constant-velocity prediction stands in).
    fallback_sigma_translation: float = Field(0.2, gt=0)
    fallback_sigma_rotation: float = Field(10.0, gt=0)


@dataclass(frozen=True)
class RegistrationResult:
    """Outcome of :func:`register_rgbd`.

    Attributes:
        T_tgt_src: (4, 4) pose of the source camera in the target camera (the initial guess when not ok).
        information: (6, 6) information of ``T_tgt_src`` (right perturbation, ``[rotation, translation]``;
            see :func:`~lrslam.frontend.rgbd_view.assess_alignment`), with unit point noise
            ``max(registration.information_sigma, inlier_rmse)``; :func:`fallback_information` when not ok.
        fitness: inlier fraction of the source's valid pixels (0..1).
        inlier_rmse: metres (inf when unknown).
        ok: all gates passed.
        reason: why not ok ("" when ok).
        trusted: ok and the fitness at least ``gates.trusted_fitness`` (a weak registration is no measurement
            for the fusion or the graph).
    """

    T_tgt_src: np.ndarray
    information: np.ndarray
    fitness: float
    inlier_rmse: float
    ok: bool
    reason: str = ""
    trusted: bool = False


def fallback_information(gates: RegistrationGates) -> np.ndarray:
    """Weak diagonal information used when a registration fails (its pose is a prediction, not a measurement)."""
    return diagonal_information(np.radians(gates.fallback_sigma_rotation), gates.fallback_sigma_translation)


def frame_problem(view: RGBDView, registration: RegistrationConfig, gates: RegistrationGates) -> str | None:
    """Why ``view`` cannot be registered with ``registration``'s method under ``gates`` (no valid depth,
    featureless), or None."""
    return view_problem(view, depth_min=registration.depth_min, depth_max=registration.depth_max,
                        min_valid_fraction=gates.min_valid_depth_fraction, min_intensity_std=gates.min_intensity_std,
                        min_normal_spread=gates.min_normal_spread, uses_colour=registration.uses_colour)


def register_rgbd(source: FrameLike | RGBDView, target: FrameLike | RGBDView, init_T_tgt_src: np.ndarray,
                  registration: RegistrationConfig, gates: RegistrationGates) -> RegistrationResult:
    """Register the source RGB-D frame to the target one with ``registration``, starting from
    ``init_T_tgt_src`` (4x4), and accept or reject the result with ``gates``.

    Frames: anything with ``rgb (H, W, 3) uint8``, ``depth (H, W) float32`` metres and ``K (3, 3)``, or an
    :class:`RGBDView` (keeps preprocessing cached across calls). Never raises on bad image content: a frame
    without depth, a featureless frame, an Open3D error, a non-finite result or a failed gate give
    ``ok=False`` with the initial guess, weak information and the reason (also logged at INFO). Malformed
    arrays (wrong shapes) or a non-rigid ``init_T_tgt_src`` raise :class:`~lrslam.errors.InputError`.
    """
    cfg, method = registration, registration.method  # gates only decide acceptance
    src, tgt = as_view(source), as_view(target)
    init = np.asarray(init_T_tgt_src, dtype=np.float64)
    if not is_valid_pose(init):
        raise InputError("register_rgbd: init_T_tgt_src must be a finite 4x4 rigid transform")

    def fail(reason: str, fitness: float = 0.0, rmse: float = float("inf")) -> RegistrationResult:
        log.info("registration rejected: %s", reason)
        return RegistrationResult(init.copy(), fallback_information(gates), fitness, rmse, False, reason)

    # 1. Can these views be registered at all?
    for name, view in (("source", src), ("target", tgt)):
        problem = frame_problem(view, cfg, gates)
        if problem is not None:
            return fail(f"{name}: {problem}")

    # 2. Register.
    try:
        if method == "rgbd":
            T = _register_o3d_rgbd(src, tgt, init, cfg, polish_min_normal_spread=gates.min_normal_spread)
        else:
            T = {"icp": _register_o3d_icp, "kiss": _register_kiss}[method](src, tgt, init, cfg)
    except Exception as e:  # Open3D / KISS-ICP raise RuntimeError on degenerate systems, empty clouds, ...
        return fail(f"{method} registration raised {type(e).__name__}: {_one_line(e)}")
    if not is_valid_pose(T, tol=1e-3):
        return fail(f"{method} registration returned a non-rigid or non-finite transform")
    T = orthonormalise(T)

    # 3. Measure and gate.
    q = assess_alignment(src, tgt, T, max_distance=cfg.max_correspondence_distance, depth_min=cfg.depth_min,
                         depth_max=cfg.depth_max, sigma_m=cfg.information_sigma)
    d_t, d_r = pose_error(init, T)
    if q.fitness < gates.min_fitness:
        return fail(f"fitness {q.fitness:.3f} < {gates.min_fitness}", q.fitness, q.inlier_rmse)
    if q.inlier_rmse > gates.max_inlier_rmse:
        return fail(f"inlier RMSE {q.inlier_rmse:.4f} m > {gates.max_inlier_rmse}", q.fitness, q.inlier_rmse)
    if d_t > gates.max_translation or d_r > gates.max_rotation:
        return fail(f"correction of the initial guess too large ({d_t:.3f} m, {d_r:.1f} deg)", q.fitness,
                    q.inlier_rmse)
    info = q.information * (cfg.information_sigma / max(cfg.information_sigma, q.inlier_rmse)) ** 2
    return RegistrationResult(T, info, q.fitness, q.inlier_rmse, True, "", q.fitness >= gates.trusted_fitness)


def _one_line(e: Exception) -> str:
    """First line of an exception message without ANSI colours or Open3D's C++ location prefix."""
    text = re.sub(r"\x1b\[[0-9;]*m", "", str(e)).strip()
    text = text.splitlines()[0] if text else ""
    return re.split(r"\.(?:cpp|h):\d+: ", text)[-1]


# ---------------------------------------------------------------------------------------------------------------
# Open3D RGB-D odometry


def _o3d_rgbd(view: RGBDView):
    import open3d as o3d

    def build():
        return o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(view.rgb),
                                        o3d.t.geometry.Image(np.ascontiguousarray(view.depth[..., None])))

    return view.cached("o3d_rgbd", build)


def _register_o3d_rgbd(src: RGBDView, tgt: RGBDView, init: np.ndarray, cfg: RegistrationConfig,
                       polish_min_normal_spread: float) -> np.ndarray:
    """Hybrid RGB-D odometry, then the point-to-plane polish when ``cfg.refine_iterations`` > 0 and the
    source's normal spread is at least ``polish_min_normal_spread`` (geometry well conditioned)."""
    import open3d as o3d

    if src.depth.shape != tgt.depth.shape or not np.allclose(src.K, tgt.K):
        raise ValueError("rgbd odometry needs both frames from the same camera (same size and intrinsics)")
    T = hybrid_odometry(src, tgt, init, cfg.iterations, cfg.relative_fitness, cfg.relative_rmse, cfg.depth_max,
                        cfg.depth_outlier_trunc, cfg.depth_huber_delta, cfg.intensity_huber_delta)
    if (cfg.refine_iterations > 0 and is_valid_pose(T, tol=1e-3)
            and normal_spread(src, cfg.depth_min, cfg.depth_max) >= polish_min_normal_spread):
        # Full-resolution point-to-plane polish (removes the nearest-pixel bias of the photometric term). One
        # level: no intensity pyramid, so Open3D's own function repeats bit for bit.
        od = o3d.t.pipelines.odometry
        params = od.OdometryLossParams(cfg.depth_outlier_trunc, cfg.depth_huber_delta, cfg.intensity_huber_delta)
        K = o3d.core.Tensor(tgt.K)
        polish = od.rgbd_odometry_multi_scale(
            _o3d_rgbd(src), _o3d_rgbd(tgt), K, o3d.core.Tensor(T), 1.0, cfg.depth_max,
            [od.OdometryConvergenceCriteria(cfg.refine_iterations, cfg.relative_rmse, cfg.relative_fitness)],
            od.Method.PointToPlane, params)
        T_p = polish.transformation.numpy().astype(np.float64)
        d_t, d_r = pose_error(T, T_p)
        if is_valid_pose(T_p, tol=1e-3) and d_t < _POLISH_MAX_TRANSLATION and d_r < _POLISH_MAX_ROTATION:
            T = T_p
        else:
            log.debug("point-to-plane polish moved the hybrid result too far (%.3f m, %.2f deg): ignored", d_t, d_r)
    return T


# ---------------------------------------------------------------------------------------------------------------
# Back-projected points (ICP, KISS-ICP)


def _points(view: RGBDView, cfg: RegistrationConfig) -> tuple[np.ndarray, np.ndarray]:
    """Camera-frame points (N, 3) float64 and colours (N, 3) float in [0, 1] of the valid pixels."""
    key = ("points", cfg.depth_min, cfg.depth_max)

    def build():
        mask = valid_mask(view, cfg.depth_min, cfg.depth_max)
        return backproject_depth(view.depth, view.K)[mask], view.rgb[mask].astype(np.float64) / 255.0

    return view.cached(key, build)


def _o3d_cloud(view: RGBDView, cfg: RegistrationConfig):
    """Open3D tensor point cloud downsampled at the finest voxel size, with normals and colours."""
    import open3d as o3d

    key = ("o3d_cloud", cfg.depth_min, cfg.depth_max, cfg.voxel_size)

    def build():
        pts, cols = _points(view, cfg)
        pcd = o3d.t.geometry.PointCloud(o3d.core.Tensor(pts.astype(np.float32)))
        pcd.point.colors = o3d.core.Tensor(cols.astype(np.float32))
        pcd = pcd.voxel_down_sample(cfg.voxel_size)
        pcd.estimate_normals(max_nn=30, radius=2.0 * cfg.voxel_size)
        return pcd

    return view.cached(key, build)


def _register_o3d_icp(src: RGBDView, tgt: RGBDView, init: np.ndarray, cfg: RegistrationConfig) -> np.ndarray:
    import open3d as o3d

    reg = o3d.t.pipelines.registration
    n = len(cfg.iterations)
    voxels = [cfg.voxel_size * 2 ** (n - 1 - i) for i in range(n)]
    criteria = [reg.ICPConvergenceCriteria(cfg.relative_fitness, cfg.relative_rmse, it) for it in cfg.iterations]
    if cfg.icp_estimation == "colored":
        estimation = reg.TransformationEstimationForColoredICP()
    else:
        estimation = reg.TransformationEstimationPointToPlane()
    res = reg.multi_scale_icp(_o3d_cloud(src, cfg), _o3d_cloud(tgt, cfg), o3d.utility.DoubleVector(voxels),
                              criteria, o3d.utility.DoubleVector([cfg.icp_distance_factor * v for v in voxels]),
                              o3d.core.Tensor(init), estimation)
    return res.transformation.numpy().astype(np.float64)


def _register_kiss(src: RGBDView, tgt: RGBDView, init: np.ndarray, cfg: RegistrationConfig) -> np.ndarray:
    """KISS-ICP's point-to-map registration, coarse to fine. At each scale with voxel size ``v`` the target map
    keeps the points at ``v / 2`` and the source is registered at ``1.5 v`` (as ``KissICP.voxelize``), with
    kernel ``v`` and correspondences up to ``3 v`` (its search only reaches neighbouring voxels, so a single
    fine scale cannot recover motions of more than about one voxel)."""
    from kiss_icp.mapping import VoxelHashMap
    from kiss_icp.registration import Registration
    from kiss_icp.voxelization import voxel_down_sample

    def build_map(v: float) -> VoxelHashMap:
        voxel_map = VoxelHashMap(voxel_size=v, max_distance=2.0 * cfg.depth_max,
                                 max_points_per_voxel=cfg.kiss_max_points_per_voxel)
        voxel_map.add_points(voxel_down_sample(_points(tgt, cfg)[0], 0.5 * v))
        return voxel_map

    registration = Registration(max_num_iterations=cfg.kiss_max_iterations, convergence_criterion=1e-4)
    T = init
    for k in reversed(range(cfg.kiss_levels)):
        v = cfg.voxel_size * 2 ** k
        key = (cfg.depth_min, cfg.depth_max, v)
        voxel_map = tgt.cached(("kiss_map", cfg.kiss_max_points_per_voxel) + key, lambda: build_map(v))
        source = src.cached(("kiss_source",) + key, lambda: voxel_down_sample(_points(src, cfg)[0], 1.5 * v))
        T = registration.align_points_to_map(points=source, voxel_map=voxel_map, initial_guess=T,
                                             max_correspondance_distance=3.0 * v, kernel=v)
    return np.asarray(T, dtype=np.float64)
