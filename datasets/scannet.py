"""ScanNet reader (``scannet``), for the exported frame folders (``SensReader`` output, as used by NICE-SLAM).

Layout: ``color/<n>.jpg`` (1296x968), ``depth/<n>.png`` (uint16 millimetres, 640x480, 0 = invalid),
``pose/<n>.txt`` (4x4 camera-to-world, OpenCV camera axes; used as is, see
:mod:`lrslam.datasets.replica` for how this was checked), ``intrinsic/intrinsic_depth.txt`` (4x4; its
top-left 3x3 is the depth camera's K). Frames are ordered by the number ``n``.

* The colour image is resized to the depth image's size (as NICE-SLAM/ESLAM do; the colour camera's field of
  view differs slightly, which is why their configs crop a border) and K is the depth camera's.
* Poses with inf/NaN entries (tracking lost) mean "no ground truth" for that frame (NaN row in
  ``gt_poses()``, ``Frame.T_w_c_gt`` None). Without ``pose/`` the sequence has no ground truth.
* Timestamps: frame ``n`` gets ``n / 30`` s (ScanNet records at 30 Hz). Mesh: ``*_vh_clean_2.ply`` in the
  folder or its parent (ScanNet's scan layout), when present.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from lrslam.errors import DatasetError
from lrslam.datasets.base import Sequence, SourceIndex
from lrslam.datasets.parsing import numbered_files, paired_frame_numbers, read_matrix, read_pose_files
from lrslam.datasets.registry import register
from lrslam.datasets.replica import NOMINAL_FPS

__all__ = ["ScanNetReader", "SCANNET_DEPTH_SCALE"]

log = logging.getLogger(__name__)

SCANNET_DEPTH_SCALE = 1000.0  # millimetres


@register("scannet")
class ScanNetReader(Sequence):
    """ScanNet exported scene folder (see the module docstring for conventions)."""

    layout_hint = "color/*.jpg + depth/*.png (+ pose/*.txt, intrinsic/intrinsic_depth.txt)"
    color_to_depth_size = True

    @classmethod
    def detect(cls, root: Path) -> bool:
        return (root / "color").is_dir() and (root / "depth").is_dir()

    def _scan(self) -> SourceIndex:
        root = self.root
        colors = numbered_files(root / "color", r"(\d+)\.(?:jpg|jpeg|png)")
        depths = numbered_files(root / "depth", r"(\d+)\.png")
        idx = paired_frame_numbers(colors, depths, lambda n: root / "depth" / f"{n}.png", root / "depth", log)
        poses = None
        if (root / "pose").is_dir() and idx:
            poses = read_pose_files([root / "pose" / f"{i}.txt" for i in idx])
            if poses is not None and not np.all(np.isfinite(poses)):
                n_bad = int(np.count_nonzero(~np.all(np.isfinite(poses), axis=(1, 2))))
                log.info("%s: %d of %d frames have no valid pose (inf/NaN): no ground truth for them",
                         root / "pose", n_bad, len(idx))
        return SourceIndex(timestamps=np.asarray(idx, dtype=np.float64) / NOMINAL_FPS,
                           rgb_paths=[colors[i] for i in idx], depth_paths=[depths[i] for i in idx],
                           K=self._intrinsics(), depth_scale=SCANNET_DEPTH_SCALE, poses=poses,
                           gt_mesh_path=self._mesh())

    def _intrinsics(self) -> np.ndarray:
        path = self.root / "intrinsic" / "intrinsic_depth.txt"
        if not path.is_file():
            if self.options.fx is not None:
                return self.options.intrinsics_override()
            raise DatasetError(f"{path}: file not found (or give fx, fy, cx, cy in the reader options)")
        return read_matrix(path, 4, 4)[:3, :3].copy()

    def _mesh(self) -> Path | None:
        root = self.root.resolve()
        for folder in (root, root.parent):
            found = sorted(folder.glob("*_vh_clean_2.ply"))
            if found:
                return found[0]
        return None
