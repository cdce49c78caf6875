"""One ATE association everywhere: the run's ATE, ``lrslam eval ate`` and evo agree on the same files."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

from lrslam.datasets import ReaderOptions, open_sequence
from lrslam.geometry import make_pose
from lrslam.evaluation.ate import compute_ate, compute_run_ate, ground_truth_samples
from lrslam.cli.evaluate import eval_app
from lrslam.trajectory_io import read_tum, write_tum

T0 = 1305031102.175304
SMALL = ReaderOptions(fx=20.0, fy=20.0, cx=15.5, cy=11.5)   # 32x24 images (Freiburg calibrations are 640x480)


def gt_pose(t: float) -> np.ndarray:
    """A fast curved motion (1 m radius circle at 3 rad/s, spinning): interpolating between 100 Hz samples and
    taking the nearest sample give visibly different poses at the frame times."""
    a = 3.0 * (t - T0)
    return make_pose(Rotation.from_rotvec([0.0, a, 0.0]).as_matrix(), [np.cos(a), 0.1 * a, np.sin(a)])


def write_tum_sequence(root, n: int = 12):
    rgb, depth = ["# color"], ["# depth"]
    for i in range(n):
        t = T0 + i / 30.0 + 0.0043   # frames fall between motion-capture samples
        img = np.full((24, 32, 3), 20 * i % 255, np.uint8)
        (root / "rgb").mkdir(parents=True, exist_ok=True)
        (root / "depth").mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(root / f"rgb/{t:.6f}.png"), img)
        assert cv2.imwrite(str(root / f"depth/{t:.6f}.png"), np.full((24, 32), 5000, np.uint16))
        rgb.append(f"{t:.6f} rgb/{t:.6f}.png")
        depth.append(f"{t:.6f} depth/{t:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb) + "\n")
    (root / "depth.txt").write_text("\n".join(depth) + "\n")
    t_gt = T0 - 0.05 + 0.01 * np.arange(int((n / 30.0 + 0.1) / 0.01))
    write_tum(root / "groundtruth.txt", t_gt, np.stack([gt_pose(t) for t in t_gt]))
    return root


@pytest.fixture
def run_files(tmp_path, rng):
    seq = open_sequence(write_tum_sequence(tmp_path / "rgbd_dataset_freiburg1_desk"), reader="tum", options=SMALL)
    ts = seq.timestamps
    # An estimate: the interpolated ground truth with centimetre noise, in another world frame.
    W = make_pose(Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), [1.0, 2.0, -0.5])
    est = np.stack([W @ gt_pose(t) for t in ts])
    est[:, :3, 3] += rng.normal(0.0, 0.01, size=(len(ts), 3))
    traj = write_tum(tmp_path / "trajectory.txt", ts, est)
    return seq, ts, est, traj


def test_run_ate_equals_cli_ate_on_the_same_files(run_files):
    seq, ts, est, traj = run_files
    run = compute_run_ate(ts, est, seq)
    res = CliRunner().invoke(eval_app, ["ate", str(traj), str(seq.root / "groundtruth.txt"), "--json"])
    assert res.exit_code == 0, res.output
    cli = json.loads(res.output)
    assert cli["n_matched"] == run.n_matched == len(ts)
    for key in ("ate_rmse_cm", "ate_mean_cm", "ate_median_cm", "ate_max_cm"):
        assert run.to_dict()[key] == pytest.approx(cli[key], abs=1e-9), key
    # The old run path (ground truth interpolated at the frame stamps) gave another number on these files.
    interpolated = compute_ate(ts, est, seq.timestamps, seq.gt_poses())
    assert abs(interpolated.rmse_cm - run.rmse_cm) > 0.05


def test_run_ate_matches_evo_nearest_association(run_files):
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    seq, ts, est, traj = run_files
    t_gt, T_gt = read_tum(seq.root / "groundtruth.txt")
    t_est, T_est = read_tum(traj)
    ref, mine = sync.associate_trajectories(PoseTrajectory3D(poses_se3=list(T_gt), timestamps=t_gt),
                                            PoseTrajectory3D(poses_se3=list(T_est), timestamps=t_est))
    mine.align(ref, correct_scale=False)   # evo_ape tum gt est -a
    ape = metrics.APE(metrics.PoseRelation.translation_part)
    ape.process_data((ref, mine))
    assert compute_run_ate(ts, est, seq).rmse_cm == pytest.approx(100.0 * ape.get_statistic(
        metrics.StatisticsType.rmse), abs=1e-6)


def test_ground_truth_samples(run_files, tmp_path):
    seq, ts, _, _ = run_files
    t_gt, T_gt = ground_truth_samples(seq)
    assert len(t_gt) > 3 * len(ts)   # the raw 100 Hz samples, not one per frame
    assert np.allclose(T_gt[0], gt_pose(t_gt[0]), atol=1e-9)
    (seq.root / "groundtruth.txt").unlink()
    assert ground_truth_samples(open_sequence(seq.root, reader="tum", options=SMALL)) is None


def _write_run_outputs(seq, ts, est, out, mode: str, rng, overrides: tuple[str, ...] = ()):
    """``write_outputs`` of a run folder for the estimate ``est`` (its seeds and frontend poses: ``est`` with more
    noise), no mesh; returns the metrics."""
    from lrslam.pipeline.config import build_config
    from lrslam.pipeline.outputs import write_outputs
    from lrslam.pipeline.runner import SlamResult
    from lrslam.pipeline.timing import StageTimer

    def noisy(sigma):
        poses = est.copy()
        poses[:, :3, 3] += rng.normal(0.0, sigma, size=(len(est), 3))
        return poses

    result = SlamResult(poses=est, keyframe_ids=(0, 6), seed_poses=noisy(0.02), frontend_poses=noisy(0.03),
                        records=(), counts={})
    cfg = build_config("synthetic", overrides=["output.mesh=false", *overrides], mode=mode)
    out.mkdir()
    return write_outputs(out, cfg, seq, result, ts, StageTimer(), 1.0, np.zeros((3, 2)), "test", False)


def test_the_plot_shows_the_ate_of_the_metrics(run_files, tmp_path, rng):
    """One evaluation, one number: the trajectory plot's legend shows metrics.json's ATE of each curve. On TUM
    ground truth (100 Hz samples, frames between them) the plot used to evaluate again against the reader's
    per-frame *interpolated* ground truth and showed another number than metrics.json (1.28 vs 1.30 cm)."""
    from lrslam.pipeline.plots import ate_label, read_ate_labels

    seq, ts, est, _ = run_files
    m = _write_run_outputs(seq, ts, est, tmp_path / "run", "fused", rng)
    labels = read_ate_labels(tmp_path / "run" / "trajectory.png")
    assert labels == {"fused": ate_label("fused", m["ate_rmse_cm"]),
                      "seed": ate_label("seed", m["seed_ate_rmse_cm"]),
                      "frontend": ate_label("frontend", m["frontend_ate_rmse_cm"])}
    # on these files the plot's former evaluation (interpolated ground truth) gives another legend
    interpolated = compute_ate(ts, est, seq.timestamps, seq.gt_poses())
    assert ate_label("fused", interpolated.rmse_cm) != labels["fused"]


FRONTEND_ONLY = ("parts.refiner=none", "parts.backend=none")


@pytest.mark.parametrize("mode, overrides, curves", [
    ("fused", (), ["fused", "seed", "frontend"]),
    ("field", (), ["field", "seed", "frontend"]),
    ("frontend", (), ["frontend", "seed"]),
    ("fused", FRONTEND_ONLY, ["fused", "seed"]),   # the parts decide, not the mode's name
])
def test_the_frontend_curve_is_drawn_when_parts_move_the_poses_after_it(run_files, tmp_path, rng, mode, overrides,
                                                                        curves):
    """The frontend's own estimate is a curve of its own when a refiner or a backend moves the poses after it;
    without them it is the run's trajectory (drawn once, under the mode's name, with the run's ATE)."""
    from lrslam.pipeline.plots import ate_label, read_ate_labels

    seq, ts, est, _ = run_files
    m = _write_run_outputs(seq, ts, est, tmp_path / "run", mode, rng, overrides)
    labels = read_ate_labels(tmp_path / "run" / "trajectory.png")
    assert list(labels) == curves
    assert labels[mode] == ate_label(mode, m["ate_rmse_cm"])
