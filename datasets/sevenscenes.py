"""Microsoft 7-Scenes reader (``7scenes``), native layout of one sequence folder (e.g. ``redkitchen/seq-01``).

Layout: ``frame-NNNNNN.color.jpg`` (or ``.png``; 640x480), ``frame-NNNNNN.depth.png`` (uint16 millimetres;
0 and 65535 = invalid), ``frame-NNNNNN.pose.txt`` (4x4 camera-to-world from KinectFusion, OpenCV camera axes,
optional), ``camera-intrinsics.txt`` (3x3, optional; default fx = fy = 585, cx = 320, cy = 240).

* Colour and depth were recorded unregistered (a Kinect v1: colour focal length 525 pixels, depth 585, the
  cameras about 2.5 cm apart) and the poses belong to the depth camera. K is the depth camera's, and the colour
  image is resampled into it (``ReaderOptions.register_colour``, on by default, for the Kinect's own 640x480
  images with its depth intrinsics, not where a ``camera-intrinsics.txt`` or an override names another camera:
  :mod:`lrslam.datasets.colour_registration`); off, colour features sit up to ~30 pixels (at the image edge, full
  size) from where the depth puts them.
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
from lrslam.datasets.colour_registration import ColourToDepth
from lrslam.datasets.options import ReaderOptions
from lrslam.datasets.parsing import numbered_files, read_matrix, read_pose_files
from lrslam.datasets.registry import register
from lrslam.datasets.replica import NOMINAL_FPS

__all__ = ["SevenScenesReader", "SEVEN_SCENES_INTRINSICS", "SEVEN_SCENES_DEPTH_SCALE"]

SEVEN_SCENES_INTRINSICS = (585.0, 585.0, 320.0, 240.0)  # fx, fy, cx, cy (pixels, 640x480)
SEVEN_SCENES_DEPTH_SCALE = 1000.0  # millimetres
# The colour camera (pixels, 640x480) and the depth-to-colour transform of a Kinect v1, as the 7-Scenes pose
# re-estimation work registers the dataset (Brachmann et al., ICCV 2021; the transform is the LIRIS activities
# dataset's Kinect calibration). On the redkitchen excerpt they align colour edges with depth edges better than
# any other focal length from 505 to 585 or the transform's mirror (docs/BENCHMARKS.md section 23).
SEVEN_SCENES_COLOUR_INTRINSICS = (525.0, 525.0, 320.0, 240.0)
SEVEN_SCENES_T_COLOUR_DEPTH = np.array([
    [0.99996518012567637, 0.0026765126468950343, -0.0079041012313000904, -0.025558943178152542],
    [-0.0027409311281316700, 0.99996302803027592, -0.0081504520778013286, 0.00010109636268061706],
    [0.0078819942130445332, 0.0081718328771890631, 0.99993554558014031, 0.0020318321729487039],
    [0.0, 0.0, 0.0, 1.0]])
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

    def __init__(self, root: str | Path, options: ReaderOptions | None = None) -> None:
        super().__init__(root, options)
        # the Kinect's calibration applies to its own depth camera's 640x480 images, not to another camera named by
        # a camera-intrinsics.txt or an intrinsics override
        kinect = (self._native_size == (640, 480)
                  and np.allclose(self._K_native, intrinsics_matrix(*SEVEN_SCENES_INTRINSICS)))
        self._registration = (ColourToDepth(self._K_native, intrinsics_matrix(*SEVEN_SCENES_COLOUR_INTRINSICS),
                                            SEVEN_SCENES_T_COLOUR_DEPTH)
                              if self.options.register_colour and kinect else None)

    def _load_frame(self, i: int) -> tuple[np.ndarray, np.ndarray, int]:
        """The native frame, its colour resampled into the depth camera when ``register_colour`` is on."""
        rgb, depth, n_nonfinite = super()._load_frame(i)
        if self._registration is not None:
            rgb = self._registration(rgb, depth)
        return rgb, depth, n_nonfinite

    def _intrinsics(self) -> np.ndarray:
        path = self.root / "camera-intrinsics.txt"
        if path.is_file():
            return read_matrix(path, 3, 3)
        return intrinsics_matrix(*SEVEN_SCENES_INTRINSICS)
