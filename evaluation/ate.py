"""Trajectory accuracy: absolute trajectory error (ATE) and relative pose error (RPE), in cm / degrees.

Protocol (as ESLAM / NICE-SLAM and TUM's ``evaluate_ate.py``): associate estimated and ground-truth poses by
timestamp (:func:`~lrslam.evaluation.association.associate`), align the estimated camera positions to
the ground-truth ones with a rigid SE(3) Umeyama fit (no scale), then take statistics of the per-frame
translation error ``||p_gt - (R p_est + t)||``. Cross-checked against ``evo_ape`` in the tests.

A run and ``lrslam eval ate`` use the same association (the nearest ground-truth *sample*, see
:mod:`~lrslam.evaluation.association`): a run evaluates with :func:`compute_run_ate`, which reads the
dataset's raw ground truth (:func:`ground_truth_samples`), not the reader's per-frame interpolated poses, so
``lrslam eval ate run/trajectory.txt <dataset>/groundtruth.txt`` reproduces the run's number.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lrslam.errors import InputError
from lrslam.geometry import inv, make_pose
from lrslam.evaluation.alignment import umeyama
from lrslam.evaluation.association import associate
from lrslam.trajectory_io import TrajectoryFormatError, read_tum

__all__ = ["AteResult", "RpeResult", "compute_ate", "compute_rpe", "ate_from_files", "read_trajectory",
           "matched_poses", "ground_truth_samples", "compute_run_ate", "RAW_GROUND_TRUTH_FILES"]

# Readers whose dataset holds a ground-truth trajectory sampled independently of the frames (the reader
# interpolates it at frame times): reader name -> file in the dataset folder. Other readers have one
# ground-truth pose per frame, which is already the raw sample.
RAW_GROUND_TRUTH_FILES = {"tum": "groundtruth.txt"}

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class AteResult:
    """Absolute trajectory error. Statistics in cm over the ``n_matched`` associated frames; ``std_cm`` is the
    population standard deviation (as evo). ``T_align`` (4x4) maps the estimated world into the ground-truth
    world (identity when alignment is off); ``errors_cm (n,)`` and ``timestamps (n,)`` (estimate's stamps,
    seconds) are per matched frame, in time order."""

    rmse_cm: float
    mean_cm: float
    median_cm: float
    max_cm: float
    std_cm: float
    n_matched: int
    T_align: np.ndarray
    errors_cm: np.ndarray
    timestamps: np.ndarray

    def to_dict(self) -> dict[str, float | int]:
        """Scalar fields as a JSON-ready dict (``ate_rmse_cm``, ``ate_mean_cm``, ..., ``n_matched``)."""
        return {"ate_rmse_cm": self.rmse_cm, "ate_mean_cm": self.mean_cm, "ate_median_cm": self.median_cm,
                "ate_max_cm": self.max_cm, "ate_std_cm": self.std_cm, "n_matched": self.n_matched}


@dataclass(frozen=True)
class RpeResult:
    """Relative pose error over pairs of matched frames ``delta`` apart: translation (cm) and rotation (deg)."""

    trans_rmse_cm: float
    trans_mean_cm: float
    rot_rmse_deg: float
    rot_mean_deg: float
    n_pairs: int
    delta: int

    def to_dict(self) -> dict[str, float | int]:
        """JSON-ready dict with ``rpe_`` prefixed keys."""
        return {"rpe_trans_rmse_cm": self.trans_rmse_cm, "rpe_trans_mean_cm": self.trans_mean_cm,
                "rpe_rot_rmse_deg": self.rot_rmse_deg, "rpe_rot_mean_deg": self.rot_mean_deg,
                "rpe_n_pairs": self.n_pairs, "rpe_delta": self.delta}


def matched_poses(est_ts: np.ndarray, est_poses: np.ndarray, gt_ts: np.ndarray, gt_poses: np.ndarray,
                  max_dt: float = 0.02) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Associate an estimate with ground truth. Ground-truth rows with any non-finite entry are skipped (datasets
    mark lost tracking that way); a non-finite estimated pose is an error.

    Inputs: stamps ``(N,)`` / ``(M,)`` seconds, poses ``(N, 4, 4)`` / ``(M, 4, 4)`` ``T_w_c``.
    Returns ``(timestamps (n,), est (n, 4, 4), gt (n, 4, 4))`` in time order (estimate's stamps).
    """
    est_ts, est_poses = _trajectory(est_ts, est_poses, "estimate")
    gt_ts, gt_poses = _trajectory(gt_ts, gt_poses, "ground truth")
    bad_est = ~np.all(np.isfinite(est_poses), axis=(1, 2))
    if bad_est.any():
        raise InputError(f"estimate: {int(bad_est.sum())} of {len(est_poses)} poses are not finite "
                         f"(first at t={est_ts[bad_est][0]:.6f} s)")
    valid_gt = np.all(np.isfinite(gt_poses), axis=(1, 2)) & np.isfinite(gt_ts)
    if not valid_gt.any():
        raise InputError(f"ground truth: all {len(gt_poses)} poses are non-finite")
    if not valid_gt.all():
        log.info("skipping %d non-finite ground-truth poses", int((~valid_gt).sum()))
        gt_ts, gt_poses = gt_ts[valid_gt], gt_poses[valid_gt]
    idx_est, idx_gt = associate(est_ts, gt_ts, max_dt)
    return est_ts[idx_est], est_poses[idx_est], gt_poses[idx_gt]


def compute_ate(est_ts: np.ndarray, est_poses: np.ndarray, gt_ts: np.ndarray, gt_poses: np.ndarray,
                max_dt: float = 0.02, align: bool = True) -> AteResult:
    """Absolute trajectory error of ``est`` against ``gt`` (see module docstring for the protocol).

    ``est_ts (N,)``, ``gt_ts (M,)``: seconds; ``est_poses (N, 4, 4)``, ``gt_poses (M, 4, 4)``: ``T_w_c`` in metres,
    each in its own world frame. ``max_dt``: association tolerance (s). ``align=False`` compares positions as
    given (both trajectories already in one world frame). Needs >= 3 matched frames when aligning.
    """
    ts, est, gt = matched_poses(est_ts, est_poses, gt_ts, gt_poses, max_dt)
    p_est, p_gt = est[:, :3, 3], gt[:, :3, 3]
    if align:
        R, t, _ = umeyama(p_est, p_gt, with_scale=False)
        T_align = make_pose(R, t)
    else:
        T_align = np.eye(4)
    p_aligned = p_est @ T_align[:3, :3].T + T_align[:3, 3]
    err_cm = 100.0 * np.linalg.norm(p_gt - p_aligned, axis=1)
    return AteResult(
        rmse_cm=float(np.sqrt(np.mean(err_cm**2))), mean_cm=float(np.mean(err_cm)),
        median_cm=float(np.median(err_cm)), max_cm=float(np.max(err_cm)), std_cm=float(np.std(err_cm)),
        n_matched=len(err_cm), T_align=T_align, errors_cm=err_cm, timestamps=ts)


def compute_rpe(est_ts: np.ndarray, est_poses: np.ndarray, gt_ts: np.ndarray, gt_poses: np.ndarray,
                max_dt: float = 0.02, delta: int = 1) -> RpeResult:
    """Relative pose error between matched frames ``i`` and ``i + delta`` (``delta`` counted in matched frames):
    ``E_i = inv(inv(G_i) G_{i+delta}) inv(P_i) P_{i+delta}`` (as evo's RPE); translation RMSE/mean of
    ``||t(E_i)||`` in cm, rotation RMSE/mean of ``angle(R(E_i))`` in degrees. Independent of any world alignment.
    Shapes and units as :func:`compute_ate`."""
    if int(delta) != delta or delta < 1:
        raise InputError(f"RPE delta must be a positive integer number of frames, got {delta}")
    delta = int(delta)
    _, est, gt = matched_poses(est_ts, est_poses, gt_ts, gt_poses, max_dt)
    if len(est) <= delta:
        raise InputError(f"RPE with delta={delta} needs more than {delta} matched frames, got {len(est)}")
    rel_est = inv(est[:-delta]) @ est[delta:]
    rel_gt = inv(gt[:-delta]) @ gt[delta:]
    E = inv(rel_gt) @ rel_est
    trans_cm = 100.0 * np.linalg.norm(E[:, :3, 3], axis=1)
    rot_deg = np.degrees(Rotation.from_matrix(E[:, :3, :3]).magnitude())
    return RpeResult(
        trans_rmse_cm=float(np.sqrt(np.mean(trans_cm**2))), trans_mean_cm=float(np.mean(trans_cm)),
        rot_rmse_deg=float(np.sqrt(np.mean(rot_deg**2))), rot_mean_deg=float(np.mean(rot_deg)),
        n_pairs=len(E), delta=delta)


def ate_from_files(est_path: str | Path, gt_path: str | Path, max_dt: float = 0.02, align: bool = True) -> AteResult:
    """:func:`compute_ate` on two TUM trajectory files. Unreadable files raise :class:`InputError`."""
    est_ts, est_poses = read_trajectory(est_path)
    gt_ts, gt_poses = read_trajectory(gt_path)
    return compute_ate(est_ts, est_poses, gt_ts, gt_poses, max_dt=max_dt, align=align)


def ground_truth_samples(seq) -> tuple[np.ndarray, np.ndarray] | None:
    """The ground truth a run is evaluated against, as raw samples: ``(timestamps (M,) s, T_w_c (M, 4, 4))``.

    ``seq`` is a dataset :class:`~lrslam.datasets.Sequence`. For readers listed in
    :data:`RAW_GROUND_TRUTH_FILES` (TUM) this is the dataset's own trajectory file as written (100 Hz motion
    capture, all of it: association picks the samples); otherwise the per-frame ground truth of the selected
    frames, rows without ground truth dropped. None when the sequence has no ground truth.
    """
    name = RAW_GROUND_TRUTH_FILES.get(getattr(seq, "name", ""))
    if name is not None and (Path(seq.root) / name).is_file():
        return read_trajectory(Path(seq.root) / name)
    gt = seq.gt_poses()
    if gt is None:
        return None
    ok = np.all(np.isfinite(gt), axis=(1, 2))
    if not ok.any():
        return None
    return np.asarray(seq.timestamps, dtype=np.float64)[ok], gt[ok]


def compute_run_ate(timestamps: np.ndarray, poses: np.ndarray, seq, max_dt: float = 0.02,
                    align: bool = True) -> AteResult | None:
    """ATE of a run's trajectory (``timestamps (N,)`` s, ``poses (N, 4, 4)`` ``T_w_c``) on sequence ``seq``,
    with the association of ``lrslam eval ate`` (nearest ground-truth sample). None without ground truth."""
    gt = ground_truth_samples(seq)
    if gt is None:
        return None
    return compute_ate(timestamps, poses, *gt, max_dt=max_dt, align=align)


def read_trajectory(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """:func:`lrslam.trajectory_io.read_tum`, with format errors raised as :class:`InputError`."""
    try:
        return read_tum(path)
    except (TrajectoryFormatError, OSError, UnicodeDecodeError) as e:
        raise InputError(str(e) if isinstance(e, TrajectoryFormatError) else f"{path}: {e}") from None


def _trajectory(ts: np.ndarray, poses: np.ndarray, name: str) -> tuple[np.ndarray, np.ndarray]:
    ts = np.asarray(ts, dtype=np.float64)
    poses = np.asarray(poses, dtype=np.float64)
    if ts.ndim != 1 or poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(ts) != len(poses) or len(ts) == 0:
        raise InputError(f"{name}: expected timestamps (N,) and poses (N, 4, 4) with N > 0, got "
                         f"{ts.shape} and {poses.shape}")
    return ts, poses
