"""Run plots (PNG, matplotlib Agg; no pyplot global state): trajectories seen from above, ATE over time."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from lrslam.errors import InputError

__all__ = ["plot_trajectories"]

log = logging.getLogger(__name__)

Trajectory = tuple[np.ndarray, np.ndarray]  # (timestamps (N,) s, poses T_w_c (N, 4, 4))


def plot_trajectories(path_png: str | Path, trajectories: dict[str, Trajectory], gt: Trajectory | None = None,
                      title: str = "") -> Path:
    """Plot camera positions of each named trajectory from above and write ``path_png``; returns the path.

    The top view shows the two world axes with the largest extent (of the GT when given). With ``gt``, every
    trajectory is first aligned to it (SE(3) Umeyama, as the ATE) and a second panel plots its per-frame ATE (cm)
    over time; a trajectory that cannot be aligned is drawn as given, with a logged warning.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from lrslam.evaluation.ate import compute_ate

    # 1. Positions (aligned to the GT when possible) and per-frame errors.
    curves: dict[str, np.ndarray] = {}
    errors: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    for name, (ts, poses) in trajectories.items():
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        pos = poses[:, :3, 3]
        if gt is not None:
            try:
                res = compute_ate(ts, poses, gt[0], gt[1])
                pos = pos @ res.T_align[:3, :3].T + res.T_align[:3, 3]
                errors[name] = (res.timestamps, res.errors_cm)
            except InputError as e:
                log.warning("plot: trajectory %r not aligned to ground truth: %s", name, e)
        curves[name] = pos
    gt_pos = None
    if gt is not None:
        gt_poses = np.asarray(gt[1], dtype=np.float64).reshape(-1, 4, 4)
        gt_pos = gt_poses[np.all(np.isfinite(gt_poses), axis=(1, 2)), :3, 3]

    # 2. The two axes with the largest extent.
    if gt_pos is not None and len(gt_pos):
        ref = gt_pos
    else:
        ref = np.concatenate([np.zeros((0, 3)), *curves.values()])
    if len(ref) == 0:
        ref = np.zeros((1, 3))
    extent = np.nanmax(ref, axis=0) - np.nanmin(ref, axis=0)
    ax0, ax1 = sorted(np.argsort(-extent, kind="stable")[:2])
    labels = "xyz"

    # 3. Figure: top view (+ ATE over time).
    fig = Figure(figsize=(12 if errors else 6.5, 5.5), dpi=100)
    FigureCanvasAgg(fig)
    top = fig.add_subplot(1, 2 if errors else 1, 1)
    if gt_pos is not None:
        top.plot(gt_pos[:, ax0], gt_pos[:, ax1], "k--", lw=1.2, label="ground truth")
    for name, pos in curves.items():
        top.plot(pos[:, ax0], pos[:, ax1], lw=1.2, label=name)
        top.plot(pos[:1, ax0], pos[:1, ax1], "o", ms=4, color=top.lines[-1].get_color())
    top.set_xlabel(f"{labels[ax0]} [m]")
    top.set_ylabel(f"{labels[ax1]} [m]")
    top.set_aspect("equal", adjustable="datalim")
    top.grid(alpha=0.3)
    top.legend(fontsize=8)
    top.set_title("top view" + (" (aligned to ground truth)" if errors else ""))
    if errors:
        err_ax = fig.add_subplot(1, 2, 2)
        t0 = min(float(t[0]) for t, _ in errors.values())
        for name, (t, e) in errors.items():
            rmse = float(np.sqrt(np.mean(e**2)))
            err_ax.plot(t - t0, e, lw=1.0, label=f"{name} (RMSE {rmse:.2f} cm)")
        err_ax.set_xlabel("time [s]")
        err_ax.set_ylabel("ATE [cm]")
        err_ax.grid(alpha=0.3)
        err_ax.legend(fontsize=8)
        err_ax.set_title("per-frame absolute trajectory error")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    path = Path(path_png)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path)
    return path
