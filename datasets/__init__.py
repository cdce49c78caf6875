"""RGB-D dataset readers: one explicit registry ``name -> Sequence class`` and layout auto-detection.

Usage::

    from lrslam.datasets import ReaderOptions, open_sequence

    seq = open_sequence("data/tum-fr1-rpy", options=ReaderOptions(stride=2))  # reader auto-detected: "tum"
    for frame in seq:  # lrslam.frame.Frame, images loaded lazily
        ...
    gt = seq.gt_poses()  # (N, 4, 4) T_w_c or None; evaluation only

Readers (see each module's docstring for layout, units and conventions): ``tum``, ``synthetic`` (TUM layout
+ ``scene.yaml``, written by ``lrslam synth``), ``replica`` (NICE-SLAM layout), ``scannet``, ``7scenes``,
``rosbag`` (a ROS 1 ``.bag`` file or a ROS 2 bag folder: Image + CameraInfo topics, no ground truth).
Every reader returns depth in metres (float32, 0 = invalid), colour as uint8 RGB, K for the output images and
ground-truth poses ``T_w_c`` with OpenCV camera axes.
"""

from lrslam.datasets.base import Sequence, SourceIndex
from lrslam.datasets.options import ReaderOptions
from lrslam.datasets.registry import READERS, detect_layout, open_sequence, register

# Importing the reader modules registers them (order = order of READERS).
from lrslam.datasets import tum, synthetic, replica, scannet, sevenscenes, rosbag  # noqa: E402,F401  isort: skip

__all__ = ["open_sequence", "detect_layout", "READERS", "register", "ReaderOptions", "Sequence", "SourceIndex"]
