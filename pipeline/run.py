"""Run one sequence end to end and write its run folder.

Run folder (every run): ``config.yaml`` (resolved config, the reader actually used, ``provenance``; feed it
back with ``--config``), ``trajectory.txt`` (TUM, every frame, input timestamps), ``keyframes.txt`` (TUM),
``trajectory_seed.txt`` (the per-frame seeds: odometry or constant velocity), ``trajectory_unsmoothed.txt`` (the
poses as tracked, before the final smoothing: :mod:`lrslam.backend.smoother`), ``mesh.ply``, ``metrics.json``
(strict JSON, with ``status: ok | degraded``), ``trajectory.png`` and ``run.log``. While the run is going,
``trajectory_partial.txt`` holds the poses tracked so far (rewritten atomically every ``partial_every`` frames
and on a crash or interrupt; removed on success), and ``checkpoint.pt`` the run's state every
``checkpoint_every`` keyframes (removed on success; ``lrslam run --resume`` continues from it: the resumed run
is the same run, its ``run.log`` continues). See :mod:`lrslam.pipeline.run_folder` and
:mod:`lrslam.pipeline.checkpoint`.
"""

from __future__ import annotations

import logging
import platform
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from lrslam.config import save_yaml
from lrslam.errors import InputError
from lrslam.jsonio import dumps, json_safe
from lrslam.pipeline.auto_bound import BoundCoverage, bound_from_frame, bound_from_prepass
from lrslam.pipeline.checkpoint import CHECKPOINT_NAME, Checkpointer, check_resumable, load_checkpoint
from lrslam.pipeline.config import RunConfig
from lrslam.pipeline.determinism import global_rng_state, open3d_threads, set_global_rng_state
from lrslam.pipeline.provenance import provenance
from lrslam.pipeline.run_folder import PartialTrajectory, prepare_run_folder
from lrslam.pipeline.sanity import run_status
from lrslam.pipeline.slam import FrameResult, Slam
from lrslam.pipeline.timing import StageTimer
from lrslam.threads import flush_denormals

if TYPE_CHECKING:
    from lrslam.frontend.odometry import OdometryTrace
    from lrslam.pipeline.viewer import RerunViewer

__all__ = ["run_sequence", "RunResult", "choose_bound", "BoundChoice"]

log = logging.getLogger(__name__)


@dataclass
class RunResult:
    out_dir: Path
    metrics: dict
    timestamps: np.ndarray
    poses: np.ndarray


def _attach_file_log(out_dir: Path, append: bool = False) -> logging.Handler:
    handler = logging.FileHandler(out_dir / "run.log", mode="a" if append else "w")
    handler.setFormatter(logging.Formatter("%(asctime)s %(levelname)s %(name)s: %(message)s"))
    handler.setLevel(logging.INFO)
    root = logging.getLogger("lrslam")
    root.addHandler(handler)
    if root.level == logging.NOTSET or root.level > logging.INFO:
        root.setLevel(logging.INFO)
    return handler


def _open(path: str | Path, cfg: RunConfig):
    from lrslam.datasets import open_sequence

    seq = open_sequence(path, reader=cfg.dataset.reader, options=cfg.reader_options())
    if len(seq) == 0:
        raise InputError(f"{path}: the sequence has no frames")
    return seq


def _bound_plan(cfg: RunConfig, seq) -> str:
    """Where the run's bound will come from: ``given``, ``dataset``, ``prepass`` or ``first_frame`` (see
    :func:`choose_bound`)."""
    if isinstance(cfg.bound, list):
        return "given"
    if cfg.bound is None and seq.bound is not None:
        return "dataset"
    if cfg.bound == "auto" or (cfg.parts.refiner == "field" and len(seq) > 1):
        return "prepass"
    return "first_frame"


@dataclass(frozen=True)
class BoundChoice:
    """The field's scene ``bound`` (3, 2) metres (world frame), where it came from (``source``) and, when it
    came from the odometry pre-pass, that pass's ``trace`` (the run's frontend replays it)."""

    bound: np.ndarray
    source: str
    trace: OdometryTrace | None = None


def choose_bound(cfg: RunConfig, seq, first, T0: np.ndarray,
                 progress: Callable[[int, int], None] | None = None) -> BoundChoice:
    """The field's scene bound (3, 2) in metres (world frame, first camera at ``T0``) and where it came from:
    ``given`` (a list in the config), ``dataset`` (the sequence states it), ``auto (pre-pass)`` (an odometry pass
    over the whole sequence: ``bound: auto``, or no bound and a field; ``progress(done, total)`` per frame; Open3D
    on the run's threads, :func:`open3d_threads`, so the pass registers as the run's frontend would),
    ``auto (first frame)`` (its points plus ``auto_bound_margin``: a run without a field needs no pre-pass). See
    :class:`RunConfig` ``bound``."""
    plan, trace = _bound_plan(cfg, seq), None
    if plan == "given":
        b, src = np.asarray(cfg.bound, dtype=np.float64), "given"
    elif plan == "dataset":
        b, src = np.asarray(seq.bound, dtype=np.float64), "dataset"
    elif plan == "prepass":
        with open3d_threads(cfg.deterministic):
            b, trace = bound_from_prepass(seq, cfg.odometry, T0, cfg.auto_bound_margin, progress=progress)
        src = "auto (pre-pass)"
    else:
        b, src = bound_from_frame(first.depth, first.K, T0, margin=cfg.auto_bound_margin), "auto (first frame)"
    if b.shape != (3, 2) or not np.all(np.isfinite(b)) or np.any(b[:, 1] <= b[:, 0]):
        raise InputError(f"scene bound must be 3 finite [min, max] pairs with min < max, got {b.tolist()}")
    return BoundChoice(b, src, trace)


def _config_record(cfg: RunConfig, seq, prov: dict) -> dict:
    """config.yaml: the resolved settings (the reader actually used) + ``provenance``."""
    rec = cfg.resolved()
    rec["dataset"]["reader"] = seq.name
    return {**rec, "provenance": prov}


def _save_partial(out_dir: Path, seq, slam: Slam) -> None:
    """Write the poses tracked so far to ``trajectory_partial.txt`` (TUM format) after a failed run."""
    try:
        poses = slam.poses()
        PartialTrajectory(out_dir, seq.timestamps).save(poses)
        log.error("run stopped after %d frames; poses so far in %s", len(poses), out_dir / "trajectory_partial.txt")
    except Exception as e:  # the original error matters more
        log.error("could not save the partial trajectory: %s", e)


def _after_frame(i: int, res: FrameResult, frame, slam: Slam, coverage: BoundCoverage | None,
                 partial: PartialTrajectory) -> None:
    """Per-frame bookkeeping: the periodic partial trajectory (first: a kill right after the frame's log line must
    find it saved), the bound coverage check, one run.log line."""
    if partial.due(i + 1):
        partial.save(slam.poses())
    if coverage is not None and frame.valid_depth_fraction() > 0:
        coverage.check(frame, res.T_w_c)
    rec = res.record
    log.info("frame %d done: keyframe %s, refine %s%s", i, rec.keyframe, rec.refine_ok,
             "; " + "; ".join(rec.notes) if rec.notes else "")


@contextmanager
def _bar(show: bool, total: int, desc: str, unit: str) -> Iterator[Callable[[int, int], None] | None]:
    """A progress bar over a long step before the first frame (the bound's pre-pass, the field's first-frame fit:
    minutes on a CPU at the paper's settings, never silent); yields its ``callback(done, total)``, None when not
    shown."""
    if not show:
        yield None
        return
    from tqdm import tqdm

    with tqdm(total=total, desc=desc, unit=unit, leave=False) as bar:
        yield lambda done, total: bar.update(done - bar.n)


def _finish(out_dir: Path, metrics: dict, seq, poses: np.ndarray, bound: np.ndarray, has_field: bool,
            coverage: BoundCoverage | None) -> dict:
    """Add ground-truth presence, bound coverage and the sanity status to the metrics; write ``metrics.json``
    (strict JSON: non-finite values become null + ``<key>_reason``). Returns the written metrics."""
    gt = seq.gt_poses()
    metrics["has_ground_truth"] = bool(gt is not None and np.isfinite(gt).all(axis=(1, 2)).any())
    if coverage is not None:
        metrics.update(coverage.metrics())
    metrics["status"], reasons = run_status(metrics, poses, bound, has_field)
    if reasons:
        metrics["degraded_reasons"] = reasons
        log.warning("run degraded: %s", "; ".join(reasons))
    safe = json_safe(metrics)
    (out_dir / "metrics.json").write_text(dumps(safe, indent=2))
    return safe


@dataclass
class _Progress:
    """The run's own state besides the Slam's: what a checkpoint also needs to continue the run."""

    slam: Slam
    bound_src: str
    coverage: BoundCoverage | None
    frame_seconds: list[float]
    t_start: float                 # perf_counter origin of the run's wall time (shifted on resume)
    next_frame: int
    resumed_at: list[int]
    bound_s: float = 0.0           # wall time of choosing the bound (the odometry pre-pass), in the wall time

    def state(self, frame: int, settings: dict, timestamps: np.ndarray) -> dict:
        """The checkpoint after ``frame`` (see :mod:`lrslam.pipeline.checkpoint`)."""
        return {"frame": frame, "config": settings, "timestamps": timestamps, "slam": self.slam.checkpoint(),
                "bound_source": self.bound_src, "rng": global_rng_state(),
                "frame_seconds": np.asarray(self.frame_seconds), "elapsed_s": time.perf_counter() - self.t_start,
                "coverage_frames": None if self.coverage is None else list(self.coverage.frames),
                "resumed_at": list(self.resumed_at), "bound_s": self.bound_s}


def _initial_pose(cfg: RunConfig, first) -> np.ndarray:
    """Identity, or the first ground-truth pose with ``initial_pose: gt`` (ESLAM protocol: the map lives in the GT
    world frame, where ESLAM's bounds are given)."""
    if cfg.initial_pose == "gt":
        if first.T_w_c_gt is not None:
            return first.T_w_c_gt.copy()
        log.warning("initial_pose=gt but the sequence has no ground truth: starting at identity")
    return np.eye(4)


def _new_run(path, cfg: RunConfig, seq, first, timer: StageTimer, progress: bool = False,
             viewer: RerunViewer | None = None, announce: Callable[[str], None] | None = None) -> _Progress:
    """A new run: choose the bound (``announce``: told where it came from), start the Slam (it seeds every RNG;
    ``viewer`` watches it) on the first frame. The run's wall time includes the bound's pre-pass."""
    T0 = _initial_pose(cfg, first)
    t_start = time.perf_counter()
    prepass = progress and _bound_plan(cfg, seq) == "prepass"
    with _bar(prepass, len(seq), "scene bound (odometry pre-pass)", "frame") as on_frame:
        choice = choose_bound(cfg, seq, first, T0, on_frame)
    bound, bound_src = choice.bound, choice.source
    bound_s = time.perf_counter() - t_start
    where = f"scene bound: {bound_src}, {np.round(bound, 2).tolist()} m ({bound_s:.1f} s)"
    log.info("sequence %s: %d frames, reader %s, mode %s, seed %d; %s", path, len(seq), seq.name, cfg.mode, cfg.seed,
             where)
    if announce is not None:
        announce(where)
    t_frame = time.perf_counter()
    fit = progress and cfg.parts.refiner == "field"
    with _bar(fit, cfg.field.mapping.first_iters, "first-frame fit", "it") as on_fit:
        slam = Slam(cfg, first.K, (first.width, first.height), bound=bound, T_w_c0=T0, timer=timer, progress=on_fit,
                    observers=[viewer] if viewer is not None else [], odometry_trace=choice.trace)
        slam.track(first.rgb, first.depth, first.timestamp)
    coverage = BoundCoverage(bound) if cfg.parts.refiner == "field" else None
    return _Progress(slam, bound_src, coverage, [time.perf_counter() - t_frame], t_start, 1, [], bound_s)


def _resumed_run(cfg: RunConfig, first, timer: StageTimer, state: dict) -> _Progress:
    """Continue a run from its checkpoint ``state`` (already checked against the config and sequence)."""
    slam = Slam(cfg, first.K, (first.width, first.height), timer=timer)
    slam.restore(state["slam"])
    set_global_rng_state(state["rng"])
    coverage = None
    if state["coverage_frames"] is not None:
        coverage = BoundCoverage(slam.bound)
        coverage.frames = [int(f) for f in state["coverage_frames"]]
    frame = int(state["frame"])
    log.info("resumed from the checkpoint after frame %d (%d keyframes); frames from %d on are processed again",
             frame, slam.n_keyframes, frame + 1)
    return _Progress(slam, str(state["bound_source"]), coverage, [float(x) for x in state["frame_seconds"]],
                     time.perf_counter() - float(state["elapsed_s"]), frame + 1,
                     [int(x) for x in state["resumed_at"]] + [frame + 1], float(state.get("bound_s", 0.0)))


def _frames(run: _Progress, seq, mode: str, timer: StageTimer, partial: PartialTrajectory,
            checkpoints: Checkpointer, checkpoint_state, out_dir: Path, progress: bool) -> None:
    """Process frames ``run.next_frame ..`` of ``seq`` through the Slam: track, per-frame bookkeeping, a
    checkpoint when due (``checkpoint_state(i)`` gives the state after frame i); the partial trajectory is saved on
    any exception."""
    from tqdm import tqdm

    slam = run.slam
    bar = tqdm(range(run.next_frame, len(seq)), desc=f"lrslam {mode}", unit="frame", disable=not progress,
               initial=run.next_frame, total=len(seq))
    try:
        for i in bar:
            t_frame = time.perf_counter()
            with timer("io"):
                frame = seq[i]
            res = slam.track(frame.rgb, frame.depth, frame.timestamp)
            run.frame_seconds.append(time.perf_counter() - t_frame)
            _after_frame(i, res, frame, slam, run.coverage, partial)
            if checkpoints.due(res.keyframe, slam.n_keyframes):
                with timer("checkpoint"):
                    path = checkpoints.save(checkpoint_state(i))
                log.info("checkpoint after frame %d: %s (%.1f MB)", i, path, path.stat().st_size / 1e6)
            if progress and i % 5 == 0:
                bar.set_postfix(kf=slam.n_keyframes, loops=slam.n_loops)
    except BaseException:
        _save_partial(out_dir, seq, slam)   # never lose what was tracked before a crash or Ctrl-C
        raise
    finally:
        bar.close()


def run_sequence(path: str | Path, cfg: RunConfig, out_dir: str | Path, progress: bool = True, *,
                 overwrite: bool = False, presets: dict[str, str | None] | None = None,
                 resume: bool = False, viewer: RerunViewer | None = None,
                 announce: Callable[[str], None] | None = None) -> RunResult:
    """Run the configured pipeline over the sequence at ``path``; write and return the results.

    ``out_dir`` must be new, empty or an earlier run folder (any non-empty folder with ``overwrite``); its old
    outputs are deleted first (``trajectory_partial.txt`` is saved every ``output.partial_every`` frames,
    ``checkpoint.pt`` every ``output.checkpoint_every`` keyframes; ``bound: auto`` estimates the scene bound
    with an odometry pre-pass). ``resume``: continue the run in ``out_dir`` from its checkpoint instead (same
    config and sequence, else InputError; ``run.log`` is appended to). ``presets``: the preset names the config
    came from, for the provenance record and ``metrics.json``. ``viewer``: draws the run as it goes (it gets the
    sequence's ground truth for its running ATE; the caller closes it). ``announce``: told, in one line, where the
    scene bound came from (given, the dataset's, the odometry pre-pass, the first frame) before the first frame.

    Returns the per-frame timestamps (N,) and poses (N, 4, 4) ``T_w_c`` plus the metrics dict (as written to
    ``metrics.json``, with ``status`` "ok" or "degraded").
    """
    flush_denormals()   # before the pre-pass or the field start a thread pool (lrslam.threads)
    out_dir = Path(out_dir)
    if resume and (out_dir / "metrics.json").is_file() and not (out_dir / CHECKPOINT_NAME).exists():
        raise InputError(f"--resume: {out_dir}: the run there finished (metrics.json); nothing to resume")
    saved = load_checkpoint(out_dir / CHECKPOINT_NAME) if resume else None
    if not resume:
        out_dir = prepare_run_folder(out_dir, overwrite)
    handler = _attach_file_log(out_dir, append=resume)
    try:
        with open3d_threads(cfg.deterministic):   # one thread: Open3D repeats bit for bit
            return _run_in_folder(path, cfg, out_dir, saved, presets, progress, viewer, announce)
    finally:
        logging.getLogger("lrslam").removeHandler(handler)
        handler.close()


def _run_in_folder(path, cfg: RunConfig, out_dir: Path, saved: dict | None, presets, progress: bool,
                   viewer: RerunViewer | None = None, announce: Callable[[str], None] | None = None) -> RunResult:
    """1. open the sequence and record the config; 2. start (or resume) the run; 3. every frame; 4. outputs."""
    seq = _open(path, cfg)
    record = _config_record(cfg, seq, provenance(path, seq.name, presets))
    settings = {k: v for k, v in record.items() if k != "provenance"}
    timestamps = np.asarray(seq.timestamps, dtype=np.float64)
    if saved is not None:
        check_resumable(out_dir / CHECKPOINT_NAME, saved, settings, timestamps)
    else:
        save_yaml(out_dir / "config.yaml", record)
    first = seq[0]
    first.require_depth(seq.depth_path(0))
    timer = StageTimer()
    if viewer is not None:
        viewer.set_ground_truth(_viewer_ground_truth(seq))
    if saved is not None:
        run = _resumed_run(cfg, first, timer, saved)
        if viewer is not None:
            run.slam.add_observer(viewer)
    else:
        run = _new_run(path, cfg, seq, first, timer, progress, viewer, announce)
    partial = PartialTrajectory(out_dir, seq.timestamps, cfg.output.partial_every)
    checkpoints = Checkpointer(out_dir, cfg.output.checkpoint_every)
    _frames(run, seq, cfg.mode, timer, partial, checkpoints, lambda i: run.state(i, settings, timestamps), out_dir,
            progress)
    wall = time.perf_counter() - run.t_start   # tracking and mapping; the mesh is timed as its own stage
    result = run.slam.finish()
    metrics = _write_results(out_dir, cfg, seq, result, timer, wall, run, progress, record["provenance"]["presets"])
    partial.remove()
    checkpoints.remove()
    return RunResult(out_dir, metrics, result.timestamps, result.poses)


def _viewer_ground_truth(seq) -> tuple[np.ndarray, np.ndarray] | None:
    """The ground truth the run is evaluated against, for the viewer's running ATE (None without, or unreadable:
    the evaluation at the end reports why)."""
    from lrslam.evaluation.ate import ground_truth_samples

    try:
        return ground_truth_samples(seq)
    except InputError as e:
        log.warning("viewer: no ground truth (%s)", e)
        return None


def _write_results(out_dir: Path, cfg: RunConfig, seq, result, timer: StageTimer, wall: float, run: _Progress,
                   progress: bool, presets: dict) -> dict:
    """The run folder's outputs and ``metrics.json`` (status included; the preset, the mode's settings and the
    bound's source and time with them); returns the written metrics."""
    from lrslam.pipeline.outputs import write_outputs

    metrics = write_outputs(out_dir, cfg, seq, result, result.timestamps, timer, wall, run.slam.bound,
                            run.bound_src, progress, np.asarray(run.frame_seconds))
    metrics.update(preset=presets.get("config"), mode_settings=cfg.mode_settings(), bound_s=round(run.bound_s, 3))
    metrics["host"] = {"python": platform.python_version(), "machine": platform.machine()}
    if run.resumed_at:
        metrics["resumed_at_frames"] = run.resumed_at
    return _finish(out_dir, metrics, seq, result.poses, run.slam.bound, cfg.parts.refiner == "field", run.coverage)
