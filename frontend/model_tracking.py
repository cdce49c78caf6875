"""Frame-to-model refinement of the odometry: the frame registered to a TSDF model of the frames tracked so far
(KinectFusion's tracking, with Open3D's ``t.pipelines.slam.Model``: voxel-block TSDF, raycast, point-to-plane
projective ICP), seeded by the frame-to-frame registration.

Frame-to-frame odometry accumulates every registration's error; a model built from many frames does not forget
the scene, so registering against it bounds that drift while the camera stays over mapped ground (figures
below). A fast camera outruns a model whose new parts were integrated from one view each (a synthetic orbit at
5.5 cm / 2.5 deg per frame: 0.79 -> 6.25 cm in a prototype that refined every frame), so the refinement runs only on frames whose frame-to-frame motion is small
(``max_step_translation`` / ``max_step_rotation``) and is kept only when it moved the pose little
(``max_correction_*``) with enough projective inliers (``min_fitness``); otherwise the frame-to-frame pose stands.
Every tracked frame is integrated at its final pose.

Measured, frontend alone (ATE RMSE cm, 2026-12-06; without -> with): TUM fr1/xyz full 4.00 -> 1.59, TUM fr1/rpy
excerpt 5.74 -> 4.99, 7-Scenes redkitchen every 4th frame 3.91 -> 3.35, synthetic loop 2.08 -> 0.54, fast synthetic
orbit 0.79 -> 0.79 (no frame slow enough); +0.1-0.2 s/frame on 2 cores at 320x240. Off in the code's defaults
(``enabled``); on in the CPU presets' frontend mode. Not in fused mode: there it made TUM fr1/xyz worse (1.003 ->
1.125 cm, deterministic seed 0) and tied on 7-Scenes at +0.37 s/frame (docs/BENCHMARKS.md section 21).

Pixel convention: Open3D's integration reads the depth pixel ``int(u)`` (not the nearest) for a voxel projecting
to ``u``, half a pixel off the pinhole model the rest of the project uses. Its tracking associates the same way, so
the model is used as Open3D builds it: shifting the integration's principal point by +0.5 px (the nearest pixel)
was measured worse on TUM fr1/rpy (4.99 -> 5.90), 7-Scenes (3.35 -> 3.49) and the synthetic loop (0.54 -> 0.77),
better only on fr1/xyz (1.59 -> 1.50).

Checkpoints carry the model (Open3D's own voxel-grid file). A resumed run refines against the same model but is
not bit for bit the uninterrupted one: Open3D's grid does not raycast exactly the same after its save / load
(2 mm on the test sequence).

Poses: ``T_w_c`` (4x4 float64, camera to world, metres); the model lives in the world frame of the odometry.
Depth goes to Open3D as uint16 in units of ``1 / DEPTH_UNITS`` m (0.2 mm).
"""

from __future__ import annotations

import os
import tempfile

import numpy as np
from pydantic import Field

from lrslam.config import StrictModel
from lrslam.geometry import pose_error

__all__ = ["ModelTrackingConfig", "ModelTracker"]


DEPTH_UNITS = 5000.0  # uint16 depth units per metre handed to Open3D


class ModelTrackingConfig(StrictModel):
    """Frame-to-model refinement (module docstring). Distances in metres, angles in degrees."""

    enabled: bool = Field(False, description="refine slow frames against a TSDF model of the tracked frames")
    voxel_size: float = Field(0.006, gt=0, description="TSDF voxel edge (m); blocks of 16^3 voxels")
    block_count: int = Field(2000, gt=0, description="initial voxel blocks (the table grows as the scene does; "
                             "each block holds 16^3 voxels, ~80 kB)")
    trunc_voxels: float = Field(8.0, gt=0, description="TSDF truncation in voxels")
    depth_min: float = Field(0.1, gt=0)
    depth_max: float = Field(3.0, gt=0, description="depth beyond this is neither integrated nor tracked (m)")
    distance_threshold: float = Field(0.07, gt=0, description="largest point-to-model distance of an ICP "
                                      "correspondence (m)")
    max_step_translation: float = Field(0.025, gt=0, description="refine only frames whose frame-to-frame motion "
                                        "is below this (m) ...")
    max_step_rotation: float = Field(1.5, gt=0, description="... and this (deg)")
    max_correction_translation: float = Field(0.03, gt=0, description="keep a refinement that moved the pose less "
                                              "than this (m) ...")
    max_correction_rotation: float = Field(2.0, gt=0, description="... and this (deg)")
    min_fitness: float = Field(0.3, ge=0, le=1, description="smallest inlier fraction of a kept refinement")


class ModelTracker:
    """The TSDF model and the frame-to-model registration, for one camera (``K`` (3, 3), ``height`` x ``width``)."""

    def __init__(self, cfg: ModelTrackingConfig, K: np.ndarray, height: int, width: int):
        import open3d as o3d
        import open3d.core as o3c

        self.cfg = cfg
        self._o3d, self._o3c = o3d, o3c
        device = o3c.Device("CPU:0")
        intrinsics = o3c.Tensor(np.asarray(K, dtype=np.float64))
        slam = o3d.t.pipelines.slam
        self._model = slam.Model(cfg.voxel_size, 16, cfg.block_count, o3c.Tensor(np.eye(4)), device)
        self._input = slam.Frame(int(height), int(width), intrinsics, device)
        self._raycast = slam.Frame(int(height), int(width), intrinsics, device)
        self._frames = 0       # poses handed to this model object (Open3D's frame counter: warns on a gap)
        self.integrated = 0    # frames integrated

    # -- frames ----------------------------------------------------------------------------------------------
    def _set_frame(self, rgb: np.ndarray, depth: np.ndarray) -> None:
        o3d, o3c = self._o3d, self._o3c
        raw = np.clip(np.nan_to_num(depth, nan=0.0) * DEPTH_UNITS, 0, 65535).astype(np.uint16)
        self._input.set_data_from_image("depth", o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(raw))))
        self._input.set_data_from_image("color", o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(rgb))))

    def _set_pose(self, T_w_c: np.ndarray) -> None:
        self._model.update_frame_pose(self._frames, self._o3c.Tensor(np.asarray(T_w_c, dtype=np.float64)))
        self._frames += 1

    def wants(self, T_step: np.ndarray) -> bool:
        """Whether a frame that moved ``T_step`` (4x4, since the last frame) is slow enough to refine (and the
        model has something to register to)."""
        d_t, d_r = pose_error(np.eye(4), T_step)
        return (self.integrated > 0 and d_t <= self.cfg.max_step_translation
                and d_r <= self.cfg.max_step_rotation)

    def _quiet(self):
        """Open3D's warnings about its own buffer sizes ("Could not generate full range map") are not ours."""
        return self._o3d.utility.VerbosityContextManager(self._o3d.utility.VerbosityLevel.Error)

    def refine(self, rgb: np.ndarray, depth: np.ndarray, T_w_pred: np.ndarray) -> tuple[np.ndarray | None, str]:
        """Register the frame (rgb (H, W, 3) uint8, depth (H, W) float32 m) to the model raycast at ``T_w_pred``.

        Returns ``(T_w_c, "")`` for a kept refinement, or ``(None, reason)``."""
        cfg = self.cfg
        self._set_frame(rgb, depth)
        self._set_pose(T_w_pred)
        try:
            with self._quiet():
                # Twice: Open3D's raycast sizes a process-wide range-map buffer from the calls before it, and a
                # call that finds it too small covers part of the image (and grows it). The second call is
                # complete whatever ran before in the process (a batch runs several runs in one process), so
                # a run repeats bit for bit.
                for _ in range(2):
                    self._model.synthesize_model_frame(self._raycast, DEPTH_UNITS, cfg.depth_min, cfg.depth_max,
                                                       cfg.trunc_voxels, False)
                res = self._model.track_frame_to_model(self._input, self._raycast, DEPTH_UNITS, cfg.depth_max,
                                                       cfg.distance_threshold,
                                                       self._o3d.t.pipelines.odometry.Method.PointToPlane)
        except RuntimeError as e:   # Open3D raises on a degenerate system (too few correspondences)
            return None, f"frame-to-model registration failed ({str(e).splitlines()[0][:80]})"
        T_pred_c = res.transformation.numpy().astype(np.float64)
        if not np.all(np.isfinite(T_pred_c)):
            return None, "frame-to-model registration diverged"
        d_t, d_r = pose_error(np.eye(4), T_pred_c)
        if res.fitness < cfg.min_fitness:
            return None, f"frame-to-model fitness {res.fitness:.2f} < {cfg.min_fitness}"
        if d_t > cfg.max_correction_translation or d_r > cfg.max_correction_rotation:
            return None, f"frame-to-model correction too large ({d_t:.3f} m, {d_r:.2f} deg)"
        return np.asarray(T_w_pred, dtype=np.float64) @ T_pred_c, ""

    def integrate(self, rgb: np.ndarray, depth: np.ndarray, T_w_c: np.ndarray) -> None:
        """Fuse the frame into the model at its final pose ``T_w_c``."""
        self._set_frame(rgb, depth)
        self._set_pose(T_w_c)
        with self._quiet():
            self._model.integrate(self._input, DEPTH_UNITS, self.cfg.depth_max, self.cfg.trunc_voxels)
        self.integrated += 1

    # -- checkpoints -----------------------------------------------------------------------------------------
    def state(self) -> dict:
        """The model (Open3D's own voxel-grid file, as bytes) and the counters, for checkpoints."""
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "model.npz")
            self._model.voxel_grid.save(path)
            with open(path, "rb") as f:
                blob = f.read()
        blocks = self._model.frustum_block_coords   # the blocks the next raycast visits (set by integrate)
        return {"voxel_grid": np.frombuffer(blob, dtype=np.uint8).copy(), "integrated": self.integrated,
                "frustum_blocks": None if self.integrated == 0 else blocks.numpy().copy()}

    def load_state(self, state: dict) -> None:
        """Restore :meth:`state` (into a tracker built with the same config and camera)."""
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "model.npz")
            with open(path, "wb") as f:
                f.write(np.asarray(state["voxel_grid"], dtype=np.uint8).tobytes())
            self._model.voxel_grid = self._o3d.t.geometry.VoxelBlockGrid.load(path)
        if state.get("frustum_blocks") is not None:
            self._model.frustum_block_coords = self._o3c.Tensor(np.ascontiguousarray(state["frustum_blocks"]))
        self.integrated = int(state["integrated"])
