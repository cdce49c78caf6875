"""Microsoft 7-Scenes reader (``7scenes``), native layout of one sequence folder (e.g. ``redkitchen/seq-01``).

Layout: ``frame-NNNNNN.color.jpg`` (or ``.png``; 640x480), ``frame-NNNNNN.depth.png`` (uint16 millimetres;
0 and 65535 = invalid), ``frame-NNNNNN.pose.txt`` (4x4 camera-to-world from KinectFusion, OpenCV camera axes,
optional), ``camera-intrinsics.txt`` (3x3, optional; default fx = fy = 585, cx = 320, cy = 240).

* Colour and depth are not registered to each other and the poses belong to the depth camera: expect
  colour misalignment of a few pixels. K is the depth camera's.
* Timestamps: frame ``NNNNNN`` gets ``NNNNNN / 30`` s (30 Hz).
* A pose file with NaN/inf values (or not a rigid transform) means no ground truth for that frame (logged),
  the same as a NaN line in a TUM ``groundtruth.txt``.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from lrslam.camera import intrinsics_matrix
from lrslam.datasets.base import Sequence, SourceIndex
from lrslam.datasets.parsing import numbered_files, read_matrix, read_pose_files
from lrslam.datasets.registry import register
from lrslam.datasets.replica import NOMINAL_FPS

__all__ = ["SevenScenesReader", "SEVEN_SCENES_INTRINSICS", "SEVEN_SCENES_DEPTH_SCALE"]

SEVEN_SCENES_INTRINSICS = (585.0, 585.0, 320.0, 240.0)  # fx, fy, cx, cy (pixels, 640x480)
SEVEN_SCENES_DEPTH_SCALE = 1000.0  # millimetres
_INVALID_RAW = (65535,)

log = logging.getLogger(__name__)


@register("7scenes")
class SevenScenesReader(Sequence):
    """7-Scenes sequence folder (see the module docstring for conventions)."""

    layout_hint = "frame-NNNNNN.color.jpg + frame-NNNNNN.depth.png (+ .pose.txt)"

    @classmethod
    def detect(cls, root: Path) -> bool:
        return any(True for _ in root.glob("frame-*.color.*"))

    def _scan(self) -> SourceIndex:
        colors = numbered_files(self.root, r"frame-(\d+)\.color\.(?:jpg|jpeg|png)")
        idx = sorted(colors)
        stems = [colors[i].name.split(".color.")[0] for i in idx]
        poses = read_pose_files([self.root / f"{s}.pose.txt" for s in stems]) if idx else None
        if poses is not None:
            missing = int(np.count_nonzero(~np.all(np.isfinite(poses), axis=(1, 2))))
            if missing:
                log.warning("%s: %d of %d frames have no valid ground-truth pose (missing, NaN/inf or not rigid)",
                            self.root, missing, len(poses))
        return SourceIndex(timestamps=np.asarray(idx, dtype=np.float64) / NOMINAL_FPS,
                           rgb_paths=[colors[i] for i in idx],
                           depth_paths=[self.root / f"{s}.depth.png" for s in stems],
                           K=self._intrinsics(), depth_scale=SEVEN_SCENES_DEPTH_SCALE,
                           poses=poses,
                           invalid_depth_raw=_INVALID_RAW)

    def _intrinsics(self) -> np.ndarray:
        path = self.root / "camera-intrinsics.txt"
        if path.is_file():
            return read_matrix(path, 3, 3)
        return intrinsics_matrix(*SEVEN_SCENES_INTRINSICS)
