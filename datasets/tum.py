"""TUM RGB-D benchmark reader (``tum``).

Layout: ``rgb.txt`` and ``depth.txt`` (``timestamp filename`` per line, ``#`` comments), the images they list
(colour 8-bit, depth uint16 with 5000 units per metre, 0 = invalid) and optionally ``groundtruth.txt``
(``timestamp tx ty tz qx qy qz qw``, camera-to-world with OpenCV camera axes, 100 Hz motion capture).

* Frames: colour and depth are paired with TUM's ``associate.py`` rule (greedy best matches, strictly less
  than 0.02 s apart); a frame's timestamp is its colour image's. Unpaired images are dropped (logged).
* Ground truth: **interpolated** at each frame's timestamp between the two bracketing motion-capture samples
  (linear translation, slerp rotation) when both lie within 0.02 s, else the nearest sample within 0.02 s,
  else none for that frame (NaN row in ``gt_poses()``, ``Frame.T_w_c_gt`` None). A ``groundtruth.txt`` line with
  NaN/inf values or a zero quaternion is a missing sample: frames that would use it have no ground truth
  (logged), the same as a non-finite 7-Scenes pose file. Without ``groundtruth.txt``
  the sequence still runs (``gt_poses()`` is None).
* Camera, first that applies: (1) the intrinsics override of ``ReaderOptions`` (``--set
  dataset.options.fx=... fy= cx= cy=``, optional ``distortion=[k1,k2,p1,p2,k3]``; without it an ideal pinhole);
  (2) ``intrinsics.yaml`` beside ``rgb.txt`` (format in :mod:`lrslam.datasets.camera_file`: ``fx, fy,
  cx, cy`` pixels, optional ``distortion`` and ``depth_scale``); (3) the published Freiburg 1/2/3 calibration
  (with its distortion model, 640x480 images) when ``freiburg1``/``fr1`` ... appears in the folder name or in
  ``rgb.txt``'s comment header (the source bag name). With none of them the reader stops with an error: a
  recording of another camera must not silently get a Freiburg calibration. With ``ReaderOptions.undistort``
  the colour image is undistorted (same pinhole K, like ESLAM); depth is left as is.

A folder that also holds ``scene.yaml`` is a synthetic scene (:mod:`lrslam.datasets.synthetic`).
"""

from __future__ import annotations

import logging
import re
from pathlib import Path

import numpy as np

from lrslam.camera import intrinsics_matrix
from lrslam.errors import DatasetError
from lrslam.datasets.association import MAX_DIFFERENCE, interpolate_poses, pair_colour_depth
from lrslam.datasets.base import Sequence, SourceIndex
from lrslam.datasets.camera_file import CAMERA_FILE, read_camera_file
from lrslam.datasets.parsing import read_file_list
from lrslam.datasets.registry import register
from lrslam.trajectory_io import TrajectoryFormatError, read_tum

__all__ = ["TumReader", "FREIBURG_CAMERAS", "freiburg_camera_from_name", "TUM_DEPTH_SCALE"]

log = logging.getLogger(__name__)

TUM_DEPTH_SCALE = 5000.0  # raw units per metre

# Published calibrations (https://cvg.cit.tum.de/data/datasets/rgbd-dataset/file_formats):
# (fx, fy, cx, cy) in pixels for 640x480 images, distortion (k1, k2, p1, p2, k3) of the colour camera.
FREIBURG_CAMERAS: dict[int, tuple[tuple[float, float, float, float], tuple[float, ...]]] = {
    1: ((517.3, 516.5, 318.6, 255.3), (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)),
    2: ((520.9, 521.0, 325.1, 249.7), (0.2312, -0.7849, -0.0033, -0.0001, 0.9172)),
    3: ((535.4, 539.2, 320.1, 247.6), (0.0, 0.0, 0.0, 0.0, 0.0)),
}

_FREIBURG_RE = re.compile(r"(?<![a-z])(?:freiburg|fr)_?([123])(?!\d)")


def freiburg_camera_from_name(text: str) -> int | None:
    """1, 2 or 3 when ``text`` names a Freiburg camera (``freiburg2``, ``fr2``, ``rgbd_dataset_freiburg3_x``
    ...; case-insensitive), else None."""
    m = _FREIBURG_RE.search(text.lower())
    return int(m.group(1)) if m else None


@register("tum")
class TumReader(Sequence):
    """TUM RGB-D sequence folder (see the module docstring for association, ground truth and camera)."""

    layout_hint = "rgb.txt + depth.txt (+ groundtruth.txt)"

    @classmethod
    def detect(cls, root: Path) -> bool:
        return (root / "rgb.txt").is_file() and not (root / "scene.yaml").is_file()

    def _scan(self) -> SourceIndex:
        timestamps, rgb_paths, depth_paths, poses = self._scan_lists()
        K, dist, depth_scale, size = self._camera()
        return SourceIndex(timestamps=timestamps, rgb_paths=rgb_paths, depth_paths=depth_paths, K=K,
                           depth_scale=depth_scale, poses=poses, distortion=dist, expected_size=size)

    def _camera(self) -> tuple[np.ndarray, np.ndarray | None, float, tuple[int, int] | None]:
        """``(K (3, 3), distortion (5,) or None, depth scale, expected native (width, height) or None)``."""
        if self.options.fx is not None:  # the base class applies the override (and its distortion)
            return self.options.intrinsics_override(), None, TUM_DEPTH_SCALE, None
        path = self.root / CAMERA_FILE
        if path.is_file():
            cam = read_camera_file(path)
            dist = None if cam.distortion is None else np.asarray(cam.distortion)
            return (intrinsics_matrix(cam.fx, cam.fy, cam.cx, cam.cy), dist, cam.depth_scale or TUM_DEPTH_SCALE,
                    None)
        n = self._freiburg_camera()
        (fx, fy, cx, cy), dist = FREIBURG_CAMERAS[n]
        # Freiburg calibrations are for 640x480 images.
        return intrinsics_matrix(fx, fy, cx, cy), np.asarray(dist), TUM_DEPTH_SCALE, (640, 480)

    def _scan_lists(self) -> tuple[np.ndarray, list[Path], list[Path], np.ndarray | None]:
        """Associated frames: ``(timestamps (N,), rgb paths, depth paths, ground truth (N, 4, 4) or None)``."""
        root = self.root
        t_rgb, rgb_names = read_file_list(root / "rgb.txt")
        t_depth, depth_names = read_file_list(root / "depth.txt")
        if len(t_rgb) == 0 or len(t_depth) == 0:
            raise DatasetError(f"{root}: empty sequence (rgb.txt lists {len(t_rgb)} images, depth.txt "
                               f"{len(t_depth)})")
        pairs = pair_colour_depth(t_rgb, t_depth, root, "rgb.txt", "depth.txt", log)
        timestamps = t_rgb[pairs[:, 0]]
        rgb_paths = [root / rgb_names[i] for i in pairs[:, 0]]
        depth_paths = [root / depth_names[j] for j in pairs[:, 1]]
        return timestamps, rgb_paths, depth_paths, self._ground_truth(timestamps)

    def _ground_truth(self, timestamps: np.ndarray) -> np.ndarray | None:
        path = self.root / "groundtruth.txt"
        if not path.is_file():
            log.info("%s: no groundtruth.txt; the sequence has no ground truth", self.root)
            return None
        try:
            t_gt, T_gt = read_tum(path, invalid="nan")  # NaN lines: no ground truth there (as 7-Scenes)
        except TrajectoryFormatError as e:
            raise DatasetError(str(e)) from None
        poses = interpolate_poses(timestamps, t_gt, T_gt, MAX_DIFFERENCE)
        missing = int(np.count_nonzero(~np.isfinite(poses[:, 0, 0])))
        if missing:
            log.warning("%s: %d of %d frames have no ground-truth sample within %.2f s", path, missing,
                        len(timestamps), MAX_DIFFERENCE)
        return poses

    def _freiburg_camera(self) -> int:
        cam = freiburg_camera_from_name(self.root.resolve().name)
        if cam is None:
            header = [ln for ln in (self.root / "rgb.txt").read_text(errors="replace").splitlines()[:5]
                      if ln.startswith("#")]
            cam = freiburg_camera_from_name(" ".join(header))
        if cam is None:
            raise DatasetError(f"{self.root}: unknown camera: the folder name names no Freiburg camera (freiburg1/2/3, "
                               f"fr1/2/3) and there is no {CAMERA_FILE}; write {self.root / CAMERA_FILE} (fx, fy, cx, "
                               "cy in pixels) or pass --set dataset.options.fx=... (and fy, cx, cy) intrinsics")
        return cam
