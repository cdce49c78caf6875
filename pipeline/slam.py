"""The streaming API: feed RGB-D frames as they arrive, get each frame's pose back.

Usage (any loop that produces frames: a camera callback, a ROS node, a notebook)::

    from lrslam import Slam
    from lrslam.pipeline.config import build_config

    slam = Slam(build_config("tum-cpu"), K, (640, 480))          # K (3, 3) pixels; image (width, height)
    for rgb, depth, t in camera:                                  # (H, W, 3) uint8 RGB, (H, W) float32 metres, s
        res = slam.track(rgb, depth, t)                           # res.T_w_c (4, 4), res.keyframe, res.status
    result = slam.finish()                                        # poses (N, 4, 4) smoothed, keyframes, mesh

``lrslam run`` drives the same object over the frames of a folder or bag (one code path); it adds the run folder
around it (outputs, partial trajectory, checkpoints: :mod:`lrslam.pipeline.run`).

Observers (:class:`lrslam.pipeline.observer.SlamObserver`, e.g. the live viewer
:class:`lrslam.pipeline.viewer.RerunViewer`) watch the run: ``Slam(..., observers=[viewer])`` or
``slam.add_observer(viewer)``; each gets a :class:`~lrslam.pipeline.observer.FrameEvent` per frame and the result
at :meth:`Slam.finish`. Without observers no event is built.

The scene bound: ``bound`` (3, 2) metres in the world frame when given, else the config's ``bound`` when it is a
list, else the first frame's points grown by ``auto_bound_margin`` (a streaming run cannot look ahead; ``bound:
auto`` needs the whole sequence and is for ``lrslam run``).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from lrslam.backend.smoother import smooth_trajectory
from lrslam.errors import InputError
from lrslam.frame import Frame
from lrslam.pipeline.auto_bound import bound_from_frame
from lrslam.pipeline.config import RunConfig
from lrslam.pipeline.determinism import open3d_threads, seed_everything
from lrslam.pipeline.observer import FrameEvent, SlamObserver
from lrslam.pipeline.runner import FrameRecord, SlamResult, SlamRunner
from lrslam.pipeline.timing import StageTimer
from lrslam.threads import flush_denormals

if TYPE_CHECKING:
    from lrslam.frontend.odometry import OdometryTrace

__all__ = ["Slam", "FrameResult"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class FrameResult:
    """One tracked frame: ``index`` (0-based, in arrival order), ``timestamp`` (s, as given), ``T_w_c`` (4, 4) its
    pose now (a later graph solve or mapping round may still move it: :meth:`Slam.poses`), ``keyframe``, ``status``
    (``ok``; ``no_depth``: the seed was kept; ``seed_fallback``: the frontend failed, constant velocity used;
    ``refine_failed``: the field's tracking failed, the seed was kept) and the full :class:`FrameRecord`."""

    index: int
    timestamp: float
    T_w_c: np.ndarray
    keyframe: bool
    status: str
    record: FrameRecord


def _status(rec: FrameRecord) -> str:
    if not rec.has_depth:
        return "no_depth"
    if not rec.seed_ok:
        return "seed_fallback"
    if rec.refine_ok is False:
        return "refine_failed"
    return "ok"


class Slam:
    """One SLAM run over frames that arrive one at a time.

    Args:
        config: the run config (:func:`lrslam.pipeline.config.build_config`); its parts decide the mode.
        K: (3, 3) intrinsics of the images passed to :meth:`track`, pixels.
        image_size: (width, height) of those images, pixels.
        bound: (3, 2) scene bound in metres (world frame); see the module docstring when None.
        T_w_c0: (4, 4) pose of the first frame (the world frame); identity when None.
        timer: accumulates per-stage wall time (a new one when None).
        progress: ``progress(done, total)`` per iteration of the field's first-frame fit (the longest step).
        observers: watch every frame and the end of the run (:meth:`add_observer`).
        odometry_trace: an odometry pass over the frames to come (``lrslam run``'s bound pre-pass), replayed by
            the frontend where its config, camera, first pose and images match (:class:`Odometry`'s ``replay``).

    A new Slam seeds Python's, numpy's and torch's RNGs with ``config.seed``: two runs with the same config and
    frames repeat (bit for bit with ``config.deterministic`` on the CPU). It also flushes subnormal float results
    to zero in the calling thread and the threads started from it afterwards (:func:`lrslam.threads.flush_denormals`:
    the field's backward passes produce many, each ~100x slower on x86).
    """

    def __init__(self, config: RunConfig, K: np.ndarray, image_size: tuple[int, int], *,
                 bound: np.ndarray | None = None, T_w_c0: np.ndarray | None = None, timer: StageTimer | None = None,
                 progress: Callable[[int, int], None] | None = None,
                 observers: Iterable[SlamObserver] = (), odometry_trace: OdometryTrace | None = None) -> None:
        self.cfg = config
        self.K = np.asarray(K, dtype=np.float64)
        self.width, self.height = (int(x) for x in image_size)
        if self.K.shape != (3, 3) or not np.all(np.isfinite(self.K)):
            raise InputError(f"Slam: K must be a finite 3x3 intrinsics matrix, got shape {self.K.shape}")
        self.T_w_c0 = np.eye(4) if T_w_c0 is None else np.asarray(T_w_c0, dtype=np.float64)
        self.timer = timer or StageTimer()
        self.progress = progress
        self.bound = None if bound is None else np.asarray(bound, dtype=np.float64)
        if self.bound is None and isinstance(config.bound, list):
            self.bound = np.asarray(config.bound, dtype=np.float64)
        self.timestamps: list[float] = []
        self.runner: SlamRunner | None = None
        self.observers: list[SlamObserver] = list(observers)
        self.odometry_trace = odometry_trace
        seed_everything(config.seed)
        flush_denormals()   # the field's threads start later and inherit it (lrslam.threads)

    def add_observer(self, observer: SlamObserver) -> None:
        """Watch the run from the next frame on: ``observer.on_frame(event)`` after every :meth:`track`,
        ``observer.on_finish(result)`` after :meth:`finish`. An observer that raises is detached (logged); the run
        goes on."""
        self.observers.append(observer)

    # ------------------------------------------------------------------------------------------------ frames
    def track(self, rgb: np.ndarray, depth: np.ndarray, timestamp: float) -> FrameResult:
        """Process the next frame: ``rgb`` (H, W, 3) uint8 RGB, ``depth`` (H, W) metres (0 = invalid), both
        ``image_size``; ``timestamp`` seconds. The first frame must have depth (InputError otherwise)."""
        frame = self._frame(rgb, depth, timestamp)
        watched = bool(self.observers)
        if watched:
            t0, spent = time.perf_counter(), dict(self.timer.seconds)
        with open3d_threads(self.cfg.deterministic):
            if self.runner is None:
                rec = self._start(frame)
            else:
                rec = self.runner.step(frame)
        self.timestamps.append(float(timestamp))
        res = FrameResult(frame.index, float(timestamp), self.runner.traj.pose(-1), rec.keyframe, _status(rec), rec)
        if watched:
            event = self._event(frame, res, spent, time.perf_counter() - t0)
            self._notify(lambda obs: obs.on_frame(event))
        return res

    def _event(self, frame: Frame, res: FrameResult, spent: dict[str, float], seconds: float) -> FrameEvent:
        """The observers' view of the frame just tracked (``spent``: the stage timer's totals before it)."""
        seed, frontend = self.runner.last_seed()
        stages = {k: v - spent.get(k, 0.0) for k, v in self.timer.seconds.items() if v > spent.get(k, 0.0)}
        return FrameEvent(frame, res, seed, frontend, tuple(self.runner.traj.keyframe_ids()), stages, seconds,
                          self._trajectory, self.runner.parts.mapper)

    def _trajectory(self) -> tuple[np.ndarray, np.ndarray]:
        """``(timestamps (N,) s, T_w_c (N, 4, 4))`` of every frame so far."""
        return np.asarray(self.timestamps, dtype=np.float64), self.poses()

    def _notify(self, call: Callable[[SlamObserver], None]) -> None:
        """``call(observer)`` for every observer; one that raises is detached (logged with its traceback)."""
        for obs in list(self.observers):
            try:
                call(obs)
            except Exception:  # noqa: BLE001 - a broken observer must not stop the run
                log.exception("observer %s failed; detached", type(obs).__name__)
                self.observers.remove(obs)

    def _frame(self, rgb: np.ndarray, depth: np.ndarray, timestamp: float) -> Frame:
        rgb, depth = np.asarray(rgb), np.asarray(depth, dtype=np.float32)
        if rgb.shape != (self.height, self.width, 3) or rgb.dtype != np.uint8:
            raise InputError(f"Slam.track: rgb must be ({self.height}, {self.width}, 3) uint8, got {rgb.shape} "
                             f"{rgb.dtype}")
        if depth.shape != (self.height, self.width):
            raise InputError(f"Slam.track: depth must be ({self.height}, {self.width}) metres, got {depth.shape}")
        depth = np.where(np.isfinite(depth) & (depth > 0), depth, np.float32(0.0)).astype(np.float32)
        return Frame(len(self.timestamps), float(timestamp), rgb, depth, self.K)

    def _start(self, frame: Frame) -> FrameRecord:
        frame.require_depth()
        if self.bound is None:
            self.bound = bound_from_frame(frame.depth, frame.K, self.T_w_c0, margin=self.cfg.auto_bound_margin)
        self.runner = SlamRunner(self.cfg, self.K, self.height, self.width, self.bound, self.timer,
                                 odometry_trace=self.odometry_trace)
        self.odometry_trace = None   # the runner's frontend holds it now
        return self.runner.start(frame, self.T_w_c0, self.progress)

    # ------------------------------------------------------------------------------------------------ state
    @property
    def n_frames(self) -> int:
        return len(self.timestamps)

    @property
    def n_keyframes(self) -> int:
        return 0 if self.runner is None else len(self.runner.traj.keyframe_ids())

    @property
    def n_loops(self) -> int:
        return 0 if self.runner is None else self.runner.n_loops

    def poses(self) -> np.ndarray:
        """(N, 4, 4) current ``T_w_c`` of every frame so far."""
        return np.zeros((0, 4, 4)) if self.runner is None else self.runner.poses()

    def checkpoint(self) -> dict:
        """Everything needed to continue this run (plain data; see :meth:`SlamRunner.checkpoint`). It shares
        arrays with the live run: save it (:class:`lrslam.pipeline.checkpoint.Checkpointer`) or ``copy.deepcopy``
        it before the next :meth:`track`. The global RNG states go with it for an exact continuation
        (:func:`lrslam.pipeline.determinism.global_rng_state`)."""
        if self.runner is None:
            raise InputError("Slam.checkpoint: no frame tracked yet")
        return {"runner": self.runner.checkpoint(), "timestamps": np.asarray(self.timestamps), "bound": self.bound,
                "T_w_c0": self.T_w_c0}

    def restore(self, state: dict) -> None:
        """Continue from :meth:`checkpoint` output (on a Slam built with the same config and camera)."""
        self.bound = np.asarray(state["bound"], dtype=np.float64)
        self.T_w_c0 = np.asarray(state["T_w_c0"], dtype=np.float64)
        self.runner = SlamRunner(self.cfg, self.K, self.height, self.width, self.bound, self.timer)
        self.runner.restore(state["runner"])
        self.timestamps = [float(t) for t in state["timestamps"]]

    def finish(self, mesh: bool | None = None, mesh_resolution: float | None = None) -> SlamResult:
        """End the run: the last mapping round is collected and the field meshed (``mesh``: default
        ``config.output.mesh``). Returns the frozen result with the frames' ``timestamps``; its ``poses`` are the
        trajectory smoothed under the motion prior (``config.smoothing``, :mod:`lrslam.backend.smoother`; the field's
        mesh is built at the keyframe poses as tracked), ``unsmoothed_poses`` the poses as tracked, which
        :meth:`poses` keeps returning."""
        if self.runner is None:
            raise InputError("Slam.finish: no frame was tracked")
        result = self.runner.finish(mesh=self.cfg.output.mesh if mesh is None else mesh,
                                    mesh_resolution=mesh_resolution or self.cfg.output.mesh_resolution)
        ts = np.asarray(self.timestamps, dtype=np.float64)
        result = replace(result, timestamps=ts)
        smoothed = smooth_trajectory(result.poses, ts, self.cfg.smoothing)
        if smoothed.applied:
            log.info("trajectory smoothed (motion prior weight %.3g, per-frame noise %.2f mm, largest shift %.2f mm)",
                     smoothed.lam_t, 1000 * smoothed.noise_m, 1000 * smoothed.moved_m)
            result = replace(result, poses=smoothed.poses, unsmoothed_poses=result.poses,
                             counts={**result.counts, "smoothing": smoothed.summary()})
        self._notify(lambda obs: obs.on_finish(result))
        return result
