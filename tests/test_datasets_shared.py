"""Dataset readers on the real excerpts in ../shared/data (skipped when absent). Only a few frames are loaded."""

from __future__ import annotations

import numpy as np
import pytest

from lrslam.datasets import ReaderOptions, detect_layout, open_sequence
from lrslam.datasets.association import associate
from lrslam.datasets.parsing import read_file_list
from lrslam.datasets.tum import FREIBURG_CAMERAS
from lrslam.geometry import is_valid_pose, pose_error
from lrslam.trajectory_io import read_tum

pytestmark = pytest.mark.shared_data


def test_tum_fr1_rpy(shared_data):
    root = shared_data / "tum-fr1-rpy"
    assert detect_layout(root) == "tum"
    seq = open_sequence(root)
    t_rgb, _ = read_file_list(root / "rgb.txt")
    t_depth, _ = read_file_list(root / "depth.txt")
    assert len(seq) == len(associate(t_rgb, t_depth)) == 120  # every colour image has its depth image
    np.testing.assert_array_equal(seq.timestamps, t_rgb)
    (fx, fy, cx, cy), _ = FREIBURG_CAMERAS[1]
    np.testing.assert_array_equal(seq.K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    assert (seq.width, seq.height) == (640, 480)

    gt = seq.gt_poses()
    assert gt.shape == (120, 4, 4) and all(is_valid_pose(T) for T in gt)
    # Interpolated ground truth stays within a few mm / tenths of a degree of the nearest 100 Hz sample.
    t_gt, T_gt = read_tum(root / "groundtruth.txt")
    nearest = T_gt[np.abs(t_gt[None, :] - seq.timestamps[:, None]).argmin(axis=1)]
    errs = np.array([pose_error(a, b) for a, b in zip(gt, nearest)])
    assert errs[:, 0].max() < 0.005 and errs[:, 1].max() < 1.0

    for i in (0, 119):
        f = seq[i]
        assert f.T_w_c_gt is not None and f.rgb.shape == (480, 640, 3) and f.rgb.dtype == np.uint8
        valid = f.depth[f.depth > 0]
        assert f.valid_depth_fraction() > 0.5 and 0.3 < valid.min() and valid.max() < 10.0
        assert 0.5 < np.median(valid) < 5.0 and f.rgb.std() > 10


def test_tum_fr1_rpy_resized_like_eslam(shared_data):
    seq = open_sequence(shared_data / "tum-fr1-rpy", options=ReaderOptions(resize=(512, 384), crop_border=8,
                                                                             stride=40))
    assert len(seq) == 3 and (seq.width, seq.height) == (496, 368)
    f = seq[1]
    assert f.rgb.shape == (368, 496, 3) and f.depth.shape == (368, 496)
    np.testing.assert_allclose(seq.K[0, 0], 517.3 * 0.8)


def test_7scenes_redkitchen(shared_data):
    root = shared_data / "7scenes-redkitchen"
    assert detect_layout(root) == "7scenes"
    seq = open_sequence(root)
    assert len(seq) == 500 and (seq.width, seq.height) == (640, 480)
    np.testing.assert_allclose(seq.timestamps, np.arange(500) / 30.0)
    np.testing.assert_array_equal(seq.K, [[585.0, 0, 320.0], [0, 585.0, 240.0], [0, 0, 1]])
    gt = seq.gt_poses()
    assert gt.shape == (500, 4, 4) and all(is_valid_pose(T) for T in gt)
    steps = np.array([pose_error(a, b) for a, b in zip(gt[:-1], gt[1:])])
    assert steps[:, 0].max() < 0.05 and steps[:, 1].max() < 5.0  # continuous: cm and degrees per frame
    for i in (0, 499):
        f = seq[i]
        valid = f.depth[f.depth > 0]
        assert f.valid_depth_fraction() > 0.5 and 0.3 < valid.min() and valid.max() < 10.0
        assert f.T_w_c_gt is not None and f.rgb.std() > 10
