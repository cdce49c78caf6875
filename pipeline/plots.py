"""Run plots (PNG, matplotlib Agg; no pyplot global state): trajectories seen from above, ATE over time.

The ATE numbers a plot shows come from one evaluation: a run passes the :class:`~lrslam.evaluation.ate.AteResult`
it wrote to ``metrics.json`` (``ates``), so the legend and the metrics cannot disagree. The legend labels of the
ATE panel are also stored in the PNG's text metadata (:func:`read_ate_labels`), for checks and tools.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lrslam.errors import InputError

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from lrslam.evaluation.ate import AteResult

__all__ = ["plot_trajectories", "trajectory_figure", "read_ate_labels", "ate_label", "ATE_LABELS_KEY"]

log = logging.getLogger(__name__)

Trajectory = tuple[np.ndarray, np.ndarray]  # (timestamps (N,) s, poses T_w_c (N, 4, 4))
ATE_LABELS_KEY = "lrslam ATE labels"  # PNG text chunk: JSON {trajectory name: legend label of its ATE curve}


def plot_trajectories(path_png: str | Path, trajectories: dict[str, Trajectory], gt: Trajectory | None = None,
                      title: str = "", ates: Mapping[str, AteResult] | None = None) -> Path:
    """Plot camera positions of each named trajectory from above and write ``path_png``; returns the path.

    See :func:`trajectory_figure` for ``gt`` and ``ates``. The ATE panel's legend labels are written into the
    PNG as the text chunk :data:`ATE_LABELS_KEY` (read them back with :func:`read_ate_labels`).
    """
    fig, labels = trajectory_figure(trajectories, gt, title, ates)
    path = Path(path_png)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, metadata={ATE_LABELS_KEY: json.dumps(labels)})
    return path


def trajectory_figure(trajectories: dict[str, Trajectory], gt: Trajectory | None = None, title: str = "",
                      ates: Mapping[str, AteResult] | None = None) -> tuple[Figure, dict[str, str]]:
    """The figure of :func:`plot_trajectories` and the legend labels of its ATE panel (``{name: label}``).

    The top view shows the two world axes with the largest extent (of the GT when given). ``ates``
    (name -> :class:`~lrslam.evaluation.ate.AteResult`): the evaluation already made of each trajectory (a run's
    metrics); a trajectory with one is drawn aligned by its ``T_align`` and a second panel plots its per-frame ATE
    (cm) over time, labelled with its ``rmse_cm``; one without is drawn as given. Without ``ates``, every trajectory
    is evaluated here against ``gt`` (:func:`~lrslam.evaluation.ate.compute_ate`: SE(3) Umeyama, nearest
    ground-truth sample); one that cannot be is drawn as given, with a logged warning.
    """
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    # 1. Evaluations (given, or made here), aligned positions, the ground truth's positions.
    if ates is None:
        ates = _evaluate(trajectories, gt) if gt is not None else {}
    curves = _aligned_positions(trajectories, ates)
    gt_pos = _finite_positions(gt[1]) if gt is not None else None
    evaluated = {name: ates[name] for name in trajectories if ates.get(name) is not None}

    # 2. Figure: top view (+ ATE over time).
    fig = Figure(figsize=(12 if evaluated else 6.5, 5.5), dpi=100)
    FigureCanvasAgg(fig)
    _draw_top_view(fig.add_subplot(1, 2 if evaluated else 1, 1), curves, gt_pos, aligned=bool(evaluated))
    labels = _draw_errors(fig.add_subplot(1, 2, 2), evaluated) if evaluated else {}
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig, labels


def read_ate_labels(path_png: str | Path) -> dict[str, str]:
    """The ATE legend labels ``{name: label}`` stored in a PNG by :func:`plot_trajectories` (empty without)."""
    from PIL import Image

    with Image.open(path_png) as im:
        text = im.text.get(ATE_LABELS_KEY)
    return json.loads(text) if text else {}


def ate_label(name: str, rmse_cm: float) -> str:
    """Legend label of a trajectory's ATE curve."""
    return f"{name} (RMSE {rmse_cm:.2f} cm)"


def _evaluate(trajectories: dict[str, Trajectory], gt: Trajectory) -> dict[str, AteResult]:
    from lrslam.evaluation.ate import compute_ate

    out = {}
    for name, (ts, poses) in trajectories.items():
        try:
            out[name] = compute_ate(ts, _poses(poses), gt[0], gt[1])
        except InputError as e:
            log.warning("plot: trajectory %r not aligned to ground truth: %s", name, e)
    return out


def _aligned_positions(trajectories: dict[str, Trajectory], ates: Mapping[str, AteResult]) -> dict[str, np.ndarray]:
    """Camera positions ``(N, 3)`` of each trajectory, moved by its evaluation's ``T_align`` when it has one."""
    curves = {}
    for name, (_, poses) in trajectories.items():
        pos = _poses(poses)[:, :3, 3]
        res = ates.get(name)
        if res is not None:
            pos = pos @ res.T_align[:3, :3].T + res.T_align[:3, 3]
        curves[name] = pos
    return curves


def _draw_top_view(top, curves: dict[str, np.ndarray], gt_pos: np.ndarray | None, aligned: bool) -> None:
    """Positions on the two world axes with the largest extent, the ground truth dashed, starts marked."""
    ax0, ax1 = _widest_axes(gt_pos, curves)
    names = "xyz"
    if gt_pos is not None:
        top.plot(gt_pos[:, ax0], gt_pos[:, ax1], "k--", lw=1.2, label="ground truth")
    for name, pos in curves.items():
        top.plot(pos[:, ax0], pos[:, ax1], lw=1.2, label=name)
        top.plot(pos[:1, ax0], pos[:1, ax1], "o", ms=4, color=top.lines[-1].get_color())
    top.set_xlabel(f"{names[ax0]} [m]")
    top.set_ylabel(f"{names[ax1]} [m]")
    top.set_aspect("equal", adjustable="datalim")
    top.grid(alpha=0.3)
    top.legend(fontsize=8)
    top.set_title("top view" + (" (aligned to ground truth)" if aligned else ""))


def _draw_errors(err_ax, evaluated: Mapping[str, AteResult]) -> dict[str, str]:
    """Per-frame ATE (cm) over time, one curve per evaluation; returns the legend labels."""
    t0 = min(float(res.timestamps[0]) for res in evaluated.values())
    labels = {}
    for name, res in evaluated.items():
        labels[name] = ate_label(name, res.rmse_cm)
        err_ax.plot(res.timestamps - t0, res.errors_cm, lw=1.0, label=labels[name])
    err_ax.set_xlabel("time [s]")
    err_ax.set_ylabel("ATE [cm]")
    err_ax.grid(alpha=0.3)
    err_ax.legend(fontsize=8)
    err_ax.set_title("per-frame absolute trajectory error")
    return labels


def _widest_axes(gt_pos: np.ndarray | None, curves: dict[str, np.ndarray]) -> tuple[int, int]:
    """The two world axes (indices, ascending) along which the GT (else every curve) extends most."""
    if gt_pos is not None and len(gt_pos):
        ref = gt_pos
    else:
        ref = np.concatenate([np.zeros((0, 3)), *curves.values()])
    if len(ref) == 0:
        ref = np.zeros((1, 3))
    extent = np.nanmax(ref, axis=0) - np.nanmin(ref, axis=0)
    ax0, ax1 = sorted(np.argsort(-extent, kind="stable")[:2])
    return int(ax0), int(ax1)


def _finite_positions(poses: np.ndarray) -> np.ndarray:
    poses = _poses(poses)
    return poses[np.all(np.isfinite(poses), axis=(1, 2)), :3, 3]


def _poses(poses: np.ndarray) -> np.ndarray:
    return np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
