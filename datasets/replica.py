"""Replica reader (``replica``), for the sequences as preprocessed and distributed by NICE-SLAM.

Layout: ``results/frame%06d.jpg`` (colour, 1200x680), ``results/depth%06d.png`` (uint16, 6553.5 units per
metre, 0 = invalid) and ``traj.txt`` with one row-major 4x4 camera-to-world matrix (16 numbers) per line, line
``i`` for frame ``i``. Frames are ordered by their number.

* Pose convention: the ``traj.txt`` matrices are ``T_w_c`` with **OpenCV camera axes** (x right, y down,
  z forward), i.e. our convention, and are used as they are. Checked against the public code: NICE-SLAM's
  and ESLAM's ``Replica.load_poses`` (``src/utils/datasets.py`` in cvg/nice-slam and idiap/ESLAM) read each
  line as ``c2w`` and then flip its y and z axes (``c2w[:3, 1] *= -1; c2w[:3, 2] *= -1``) to get the OpenGL
  camera their renderer uses; the raw file is therefore OpenCV. (They treat ScanNet poses the same way.)
* Intrinsics: Replica has no calibration file. Defaults are NICE-SLAM's Replica config (1200x680,
  fx = fy = 600, cx = 599.5, cy = 339.5, depth scale 6553.5); ``ReaderOptions`` fx/fy/cx/cy/depth_scale
  override them (then any image size is accepted).
* Timestamps: the sequences have no clock; frame ``n`` gets ``n / 30`` s (nominal 30 Hz), so trajectories
  written in TUM format associate one-to-one with the ground truth.
* Bound: none in the folder (NICE-SLAM/ESLAM keep it in their configs). Mesh: ``<scene>_mesh.ply`` beside the
  scene folder (NICE-SLAM's download layout), when present.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from lrslam.camera import intrinsics_matrix
from lrslam.errors import DatasetError
from lrslam.datasets.base import Sequence, SourceIndex
from lrslam.datasets.parsing import as_pose_or_nan, numbered_files, paired_frame_numbers, read_numbers
from lrslam.datasets.registry import register

__all__ = ["ReplicaReader", "REPLICA_INTRINSICS", "REPLICA_SIZE", "REPLICA_DEPTH_SCALE", "NOMINAL_FPS"]

log = logging.getLogger(__name__)

REPLICA_INTRINSICS = (600.0, 600.0, 599.5, 339.5)  # fx, fy, cx, cy (pixels)
REPLICA_SIZE = (1200, 680)  # width, height
REPLICA_DEPTH_SCALE = 6553.5  # raw units per metre
NOMINAL_FPS = 30.0  # timestamps = frame number / NOMINAL_FPS for datasets without a clock


@register("replica")
class ReplicaReader(Sequence):
    """NICE-SLAM Replica scene folder (see the module docstring for conventions)."""

    layout_hint = "results/frame*.jpg + results/depth*.png + traj.txt"

    @classmethod
    def detect(cls, root: Path) -> bool:
        return (root / "results").is_dir()

    def _scan(self) -> SourceIndex:
        res = self.root / "results"
        colors = numbered_files(res, r"frame(\d+)\.(?:jpg|jpeg|png)")
        depths = numbered_files(res, r"depth(\d+)\.png")
        idx = paired_frame_numbers(colors, depths, lambda n: res / f"depth{n:06d}.png", res, log)
        override = self.options.fx is not None
        return SourceIndex(timestamps=np.asarray(idx, dtype=np.float64) / NOMINAL_FPS,
                           rgb_paths=[colors[i] for i in idx], depth_paths=[depths[i] for i in idx],
                           K=intrinsics_matrix(*REPLICA_INTRINSICS), depth_scale=REPLICA_DEPTH_SCALE,
                           poses=self._poses(idx), expected_size=None if override else REPLICA_SIZE,
                           gt_mesh_path=self._mesh())

    def _poses(self, idx: list[int]) -> np.ndarray | None:
        path = self.root / "traj.txt"
        if not idx:
            return None
        if not path.is_file():
            log.warning("%s: no traj.txt; the sequence has no ground truth", self.root)
            return None
        v = read_numbers(path)
        if v.size % 16:
            raise DatasetError(f"{path}: {v.size} numbers is not a whole number of 4x4 matrices (16 per line)")
        traj = v.reshape(-1, 4, 4)
        if idx[-1] >= len(traj):
            raise DatasetError(f"{path}: {len(traj)} poses but the images go up to frame {idx[-1]}")
        return np.stack([as_pose_or_nan(traj[i], f"{path} (pose {i})") for i in idx])

    def _mesh(self) -> Path | None:
        mesh = self.root.resolve().parent / f"{self.root.resolve().name}_mesh.ply"
        return mesh if mesh.is_file() else None
