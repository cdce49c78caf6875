"""Run one sequence end to end and write its run folder.

Run folder (every run): ``config.yaml`` (resolved config), ``trajectory.txt`` (TUM, every frame, input
timestamps), ``keyframes.txt`` (TUM), ``trajectory_seed.txt`` (the per-frame seeds: odometry or constant
velocity), ``mesh.ply``, ``metrics.json``, ``trajectory.png`` and ``run.log``.
"""

from __future__ import annotations

import json
import logging
import platform
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lrslam.config import save_yaml
from lrslam.errors import InputError
from lrslam.pipeline.auto_bound import bound_from_frame
from lrslam.pipeline.config import RunConfig
from lrslam.pipeline.runner import SlamRunner
from lrslam.pipeline.timing import StageTimer
from lrslam.trajectory_io import write_tum

__all__ = ["run_sequence", "RunResult"]

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    out_dir: Path
    metrics: dict
    timestamps: np.ndarray
    poses: np.ndarray


def _attach_file_log(out_dir: Path) -> logging.Handler:
    handler = logging.FileHandler(out_dir / "run.log", mode="w")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    handler.setLevel(logging.INFO)
    root = logging.getLogger("lrslam")
    root.addHandler(handler)
    if root.level == logging.NOTSET or root.level > logging.INFO:
        root.setLevel(logging.INFO)
    return handler


def _open(path: str | Path, cfg: RunConfig):
    from lrslam.frontend.datasets import open_sequence

    seq = open_sequence(path, reader=cfg.dataset.reader, options=cfg.reader_options())
    if len(seq) == 0:
        raise InputError(f"{path}: the sequence has no frames")
    return seq


def _choose_bound(cfg: RunConfig, seq, first, T0) -> tuple[np.ndarray, str]:
    if cfg.bound is not None:
        b = np.asarray(cfg.bound, dtype=np.float64)
        src = "config"
    elif getattr(seq, "bound", None) is not None:
        b, src = np.asarray(seq.bound, dtype=np.float64), "dataset"
    else:
        b, src = bound_from_frame(first.depth, first.K, T0, margin=cfg.auto_bound_margin), "auto (first frame)"
    if b.shape != (3, 2) or not np.all(np.isfinite(b)) or np.any(b[:, 1] <= b[:, 0]):
        raise InputError(f"scene bound must be 3 finite [min, max] pairs with min < max, got {b.tolist()}")
    return b, src


def _save_partial(out_dir: Path, seq, runner: SlamRunner) -> None:
    """Write the poses tracked so far to ``trajectory_partial.txt`` (TUM format) after a failed run."""
    try:
        poses = runner.poses()
        write_tum(out_dir / "trajectory_partial.txt", np.asarray(seq.timestamps, dtype=np.float64)[: len(poses)],
                  poses)
        log.error("run stopped after %d frames; poses so far in %s", len(poses), out_dir / "trajectory_partial.txt")
    except Exception as e:  # the original error matters more
        log.error("could not save the partial trajectory: %s", e)


def run_sequence(path: str | Path, cfg: RunConfig, out_dir: str | Path, progress: bool = True) -> RunResult:
    """Run the configured pipeline over the sequence at ``path``; write and return the results.

    Returns the per-frame timestamps (N,) and poses (N, 4, 4) ``T_w_c`` plus the metrics dict.
    """
    from tqdm import tqdm

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    handler = _attach_file_log(out_dir)
    try:
        seq = _open(path, cfg)
        save_yaml(out_dir / "config.yaml", {"sequence": str(Path(path).resolve()), **cfg.resolved()})
        first = seq[0]
        T0 = np.eye(4)
        if cfg.initial_pose == "gt":
            if first.T_w_c_gt is not None:
                T0 = first.T_w_c_gt.copy()      # ESLAM protocol: the map lives in the GT world frame
            else:
                log.warning("initial_pose=gt but the sequence has no ground truth: starting at identity")
        bound, bound_src = _choose_bound(cfg, seq, first, T0)
        log.info("sequence %s: %d frames, reader %s, bound %s (%s), mode %s", path, len(seq), seq.name,
                 np.round(bound, 3).tolist(), bound_src, cfg.mode)

        timer = StageTimer()
        t_start = time.perf_counter()
        runner = SlamRunner(cfg, first.K, first.height, first.width, bound, timer)
        runner.start(first, T0)
        frame_seconds = [time.perf_counter() - t_start]
        bar = tqdm(range(1, len(seq)), desc=f"lrslam {cfg.mode}", unit="frame", disable=not progress,
                   initial=1, total=len(seq))
        try:
            for i in bar:
                t_frame = time.perf_counter()
                with timer("io"):
                    frame = seq[i]
                runner.step(frame)
                frame_seconds.append(time.perf_counter() - t_frame)
                if progress and i % 5 == 0:
                    bar.set_postfix(kf=len(runner.traj.keyframe_ids()), loops=runner.n_loops)
        except BaseException:
            _save_partial(out_dir, seq, runner)   # never lose what was tracked before a crash or Ctrl-C
            raise
        finally:
            bar.close()
        wall = time.perf_counter() - t_start   # tracking and mapping; the mesh is timed as its own stage
        result = runner.finish(mesh=cfg.output.mesh, mesh_resolution=cfg.output.mesh_resolution)
        poses = result.poses
        timestamps = np.asarray(seq.timestamps, dtype=np.float64)[: len(poses)]

        # outputs
        from lrslam.pipeline.outputs import write_outputs

        metrics = write_outputs(out_dir, cfg, seq, result, timestamps, timer, wall, bound, bound_src, progress,
                                np.asarray(frame_seconds))
        metrics["host"] = {"python": platform.python_version(), "machine": platform.machine()}
        (out_dir / "metrics.json").write_text(json.dumps(metrics, indent=2))
        return RunResult(out_dir, metrics, timestamps, poses)
    finally:
        logging.getLogger("lrslam").removeHandler(handler)
        handler.close()
