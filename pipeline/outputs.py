"""Write a run folder's files and metrics from a frozen :class:`~lrslam.pipeline.runner.SlamResult` (evaluation
against ground truth happens here, not in the runner)."""

from __future__ import annotations

import logging
from pathlib import Path

from typing import TYPE_CHECKING

import numpy as np

from lrslam.trajectory_io import write_tum

if TYPE_CHECKING:
    from lrslam.evaluation.ate import AteResult

__all__ = ["write_outputs"]

log = logging.getLogger(__name__)


def _mesh(result, seq, poses, cfg, timer):
    if result.mesh is not None:
        return result.mesh
    with timer("mesh"):
        from lrslam.pipeline.tsdf import tsdf_mesh

        return tsdf_mesh((seq[i] for i in range(len(poses))), poses, voxel=cfg.output.tsdf_voxel)


def _evaluate(metrics, seq, timestamps, poses, extra, mesh, cfg) -> dict[str | None, AteResult]:
    """ATE (nearest ground-truth sample, as ``lrslam eval ate`` and evo) of the trajectory and of ``extra``
    (name -> (N, 4, 4) or None: the seeds, the frontend's own estimate) into ``metrics``; mesh metrics (ESLAM
    protocol) when the sequence has a GT mesh -- evaluated un-moved when the run started in the GT world.
    Returns the evaluations for the plot: ``{None: the trajectory's, name: each of extra's}``, empty without
    ground truth."""
    from lrslam.evaluation.ate import compute_run_ate

    res = compute_run_ate(timestamps, poses, seq)
    if res is None:
        log.info("no ground truth: skipping ATE")
        return {}
    metrics.update(ate_rmse_cm=res.rmse_cm, ate_mean_cm=res.mean_cm, ate_median_cm=res.median_cm,
                   ate_max_cm=res.max_cm, ate_matched=res.n_matched)
    ates: dict[str | None, AteResult] = {None: res}
    for name, other in extra.items():
        if other is not None:
            ates[name] = compute_run_ate(timestamps, other, seq)
            metrics[f"{name}_ate_rmse_cm"] = ates[name].rmse_cm
    gt_mesh = getattr(seq, "gt_mesh_path", None)
    if mesh is not None and gt_mesh is not None and Path(gt_mesh).is_file() and len(mesh.faces):
        from lrslam.evaluation.mesh_eval import evaluate_run_mesh
        from lrslam.evaluation.mesh_protocol import get_protocol

        f0 = seq[0]
        rec = evaluate_run_mesh(mesh, gt_mesh, seq.gt_poses(), f0.K, f0.width, f0.height, T_align=res.T_align,
                                world_is_gt=cfg.initial_pose == "gt" and f0.T_w_c_gt is not None,
                                n_points=cfg.output.eval_mesh_points, protocol=get_protocol("eslam", depth_views=0))
        metrics.update({f"mesh_{k}": v for k, v in rec.items()})
    return ates


def write_outputs(out_dir: Path, cfg, seq, result, timestamps, timer, wall_s, bound, bound_src, progress,
                  frame_seconds: np.ndarray | None = None) -> dict:
    """Write trajectory / keyframes / seed / frontend TUM files, the mesh, the plot; return the metrics dict.
    ``frame_seconds``: (N,) wall time per frame, for the first-third / last-third speed figures.

    The ATE is evaluated once (:func:`_evaluate`): ``metrics.json`` and the plot's legend show the same numbers."""
    # 1. Trajectories: the run's own, its seeds, the frontend's own estimate (when the run has a frontend).
    extra = _write_trajectories(out_dir, cfg, result, timestamps)
    _write_factors(out_dir / "factors.npz", result.factors, timestamps)
    # 2. What the run was and how fast.
    metrics = _run_metrics(cfg, result, wall_s, bound, bound_src, frame_seconds)
    # 3. Mesh.
    mesh = _write_mesh(out_dir, cfg, seq, result, timer, metrics) if cfg.output.mesh else None
    # 4. Evaluation against ground truth (once: the plot shows these numbers).
    ates: dict[str | None, AteResult] = {}
    if cfg.output.evaluate:
        try:
            ates = _evaluate(metrics, seq, timestamps, result.poses, extra, mesh, cfg)
            _factor_calibration(metrics, seq, timestamps, result.factors)
        except Exception as e:
            log.error("evaluation failed: %s", e)
            metrics["evaluation_error"] = str(e)
    metrics["timings"] = timer.summary(len(result.poses))
    # 5. Plot.
    if cfg.output.plots:
        _plot(out_dir / "trajectory.png", cfg, seq, timestamps, result.poses, extra, ates)
    return metrics


def _write_trajectories(out_dir: Path, cfg, result, timestamps) -> dict[str, np.ndarray | None]:
    """Write ``trajectory.txt``, ``keyframes.txt``, ``trajectory_seed.txt``, (with a frontend)
    ``trajectory_frontend.txt``, (after a final global refinement) ``trajectory_online.txt``, the trajectory as
    tracked before it, and (when smoothed) ``trajectory_unsmoothed.txt``; returns the others than the run's own:
    ``{"seed": (N, 4, 4), "frontend": (N, 4, 4) or None, "online": ..., "unsmoothed": ...}``."""
    poses = result.poses
    n = len(poses)
    write_tum(out_dir / "trajectory.txt", timestamps, poses, header=f"lrslam {cfg.mode} T_w_c")
    kf_ids = list(result.keyframe_ids)
    write_tum(out_dir / "keyframes.txt", timestamps[kf_ids], poses[kf_ids], header="lrslam keyframes T_w_c")
    seed = result.seed_poses[:n]
    write_tum(out_dir / "trajectory_seed.txt", timestamps, seed, header="per-frame seed poses")
    frontend = result.frontend_poses[:n] if result.frontend_poses is not None else None
    if frontend is not None:
        write_tum(out_dir / "trajectory_frontend.txt", timestamps, frontend, header="frontend-only poses T_w_c")
    online = result.online_poses[:n] if result.online_poses is not None else None
    if online is not None:
        write_tum(out_dir / "trajectory_online.txt", timestamps, online,
                  header="T_w_c as tracked, before the final global refinement")
    unsmoothed = result.unsmoothed_poses[:n] if result.unsmoothed_poses is not None else None
    if unsmoothed is not None:
        write_tum(out_dir / "trajectory_unsmoothed.txt", timestamps, unsmoothed,
                  header="T_w_c before the final smoothing (smoothing.enabled)")
    return {"seed": seed, "frontend": frontend, "online": online, "unsmoothed": unsmoothed}


def _write_factors(path: Path, factors, timestamps) -> None:
    """``factors.npz``: every pose-graph measurement as it was added, with the information the graph weighs it by
    (calibrated by the run's measured noise with ``backend.calibrate``): ``kind`` (``field_pose``: the field's own pose of
    keyframe ``i == j``, ``T_i_j`` then ``T_w_i``), frame indices ``i``, ``j``, their timestamps ``t_i``, ``t_j``
    (s), ``T_i_j`` (n, 4, 4), ``information`` (n, 6, 6), ``source`` (an odometry factor's: ``registration``, or
    ``chain`` where the keyframe registration failed its gates; empty for other kinds); nothing without a graph."""
    if not factors:
        return
    ts = np.asarray(timestamps, dtype=np.float64)
    i = np.array([f.i for f in factors], dtype=np.int64)
    j = np.array([f.j for f in factors], dtype=np.int64)
    np.savez_compressed(path, kind=np.array([f.kind for f in factors]), i=i, j=j, t_i=ts[i], t_j=ts[j],
                        T_i_j=np.stack([f.T_i_j for f in factors]),
                        information=np.stack([f.information for f in factors]),
                        source=np.array([f.source for f in factors]))


def _factor_calibration(metrics: dict, seq, timestamps, factors) -> None:
    """Normalised residuals (chi2 / 6) of each factor kind against ground truth into ``metrics["factor_chi2"]``
    (:mod:`lrslam.evaluation.factors`)."""
    from lrslam.evaluation.factors import run_factor_chi2

    res = run_factor_chi2(factors, timestamps, seq)
    if res:
        metrics["factor_chi2"] = {k: v.to_dict() for k, v in res.items()}


def _run_metrics(cfg, result, wall_s, bound, bound_src, frame_seconds: np.ndarray | None) -> dict:
    """What the run was and how fast: parts, counts, wall time per frame (and per third), bound, parameters."""
    n = len(result.poses)
    metrics: dict = {
        "mode": cfg.mode, "parts": cfg.parts.model_dump(), "n_frames": n, "n_keyframes": len(result.keyframe_ids),
        **result.counts, "wall_s": round(wall_s, 3), "fpt_s": round(wall_s / max(n, 1), 4),
        "bound": np.round(bound, 4).tolist(), "bound_source": bound_src,
    }
    if frame_seconds is not None and len(frame_seconds) >= 3:
        k = len(frame_seconds) // 3
        first, last = float(np.mean(frame_seconds[:k])), float(np.mean(frame_seconds[-k:]))
        metrics.update(fpt_first_third_s=round(first, 4), fpt_last_third_s=round(last, 4),
                       fpt_last_over_first=round(last / first, 3) if first > 0 else None)
    if result.parameters is not None:
        metrics["parameters"] = result.parameters
        metrics["device"] = result.device
    return metrics


def _write_mesh(out_dir: Path, cfg, seq, result, timer, metrics: dict):
    """The run's mesh, written to ``mesh.ply``; a failure is noted in ``metrics["mesh_error"]`` (the mesh is then
    None, or the extracted mesh when only writing it failed)."""
    mesh = None
    try:
        # the poses as tracked, as the field's mesh (the smoothing moves positions only, not the rotations with them)
        tracked = result.unsmoothed_poses if result.unsmoothed_poses is not None else result.poses
        mesh = _mesh(result, seq, tracked, cfg, timer)
        if len(mesh.faces) == 0:
            log.warning("the mesh is empty (nothing observed inside the bound?)")
            metrics["mesh_error"] = "empty mesh"
        mesh.export(out_dir / "mesh.ply")
    except Exception as e:  # a failed mesh must not lose the trajectory and metrics
        log.error("mesh extraction failed: %s", e)
        metrics["mesh_error"] = str(e)
    return mesh


def _frontend_is_apart(cfg) -> bool:
    """Whether the frontend's estimate differs from the run's trajectory: a refiner or a backend moves the poses
    after the frontend (without them, the frontend's estimate is the trajectory and is not drawn twice)."""
    return cfg.parts.refiner != "none" or cfg.parts.backend != "none"


def _plot(path_png: Path, cfg, seq, timestamps, poses, extra: dict[str, np.ndarray | None],
          ates: dict[str | None, AteResult]) -> None:
    """``trajectory.png``: the run's trajectory (named by its mode), its seeds and, when it differs from the
    trajectory, the frontend's own estimate, on the per-frame ground truth; aligned and labelled with the
    evaluations ``ates`` of :func:`_evaluate` (the numbers in the metrics)."""
    try:
        from lrslam.pipeline.plots import plot_trajectories

        gt = seq.gt_poses()
        gt_pair = (np.asarray(seq.timestamps), gt) if gt is not None else None
        shown, shown_ates = {cfg.mode: (timestamps, poses)}, {cfg.mode: ates.get(None)}
        for name, other in extra.items():
            if (other is not None and name not in shown and name != "unsmoothed"
                    and (name != "frontend" or _frontend_is_apart(cfg))):
                shown[name], shown_ates[name] = (timestamps, other), ates.get(name)
        plot_trajectories(path_png, shown, gt_pair, title=f"lrslam {cfg.mode}", ates=shown_ates)
    except Exception as e:
        log.error("plotting failed: %s", e)
