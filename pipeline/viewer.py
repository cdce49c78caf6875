"""The live viewer: a :class:`~lrslam.pipeline.observer.SlamObserver` that draws a run in Rerun as it goes.

Usage (``lrslam run ... --viewer`` / ``--rrd FILE`` does this; rerun-sdk comes with ``pip install
'lrslam[viewer]'``)::

    from lrslam.pipeline.viewer import RerunViewer

    with RerunViewer(spawn=True, ground_truth=(gt_ts, gt_poses)) as viewer:   # or rrd="run.rrd" (headless)
        slam = Slam(cfg, K, (w, h), observers=[viewer])
        for rgb, depth, t in camera:
            slam.track(rgb, depth, t)
        slam.finish()

Per frame: the camera's pose and frustum, its RGB and depth images, the per-stage seconds; every
``render_every`` frames the field rendered at the tracked pose; every ``trajectory_every`` frames (and when a
loop closes or the graph moves keyframes) the trajectories, keyframes, loops and the running ATE; every
``mesh_every`` keyframes the field's mesh (and at the end). Entity paths: :mod:`lrslam.pipeline.viewer_stream`.

The viewer's own cost is logged as ``timings/viewer_s`` and summed in :attr:`RerunViewer.seconds`. Ground truth
(``(timestamps (M,) s, T_w_c (M, 4, 4))``, e.g. :func:`lrslam.evaluation.ate.ground_truth_samples`) is used for
the running ATE and drawn aligned to the run's world; it never reaches the SLAM.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from pydantic import Field

from lrslam.config import StrictModel
from lrslam.errors import InputError
from lrslam.camera import strided_intrinsics, transform_points
from lrslam.geometry import inv
from lrslam.pipeline.observer import FieldView, FrameEvent
from lrslam.pipeline.viewer_stream import RerunStream, import_rerun

if TYPE_CHECKING:
    from lrslam.evaluation.ate import AteResult
    from lrslam.pipeline.runner import SlamResult

__all__ = ["ViewerConfig", "RerunViewer", "running_ate", "aligned_ground_truth"]

GroundTruth = tuple[np.ndarray, np.ndarray]


class ViewerConfig(StrictModel):
    """What the viewer draws, and how often (the costly parts are rendered, meshed or re-sent only now and then).

    image_scale: RGB and depth logged as ``image[::image_scale, ::image_scale]``. render_every: frames between
    renders of the field at the tracked pose (0: never); render_pixels: at most this many pixels per render
    (the pixel stride grows to fit: 80 x 60 of 640 x 480 images at 4800; each pixel is a ray through the field,
    as costly as a tracking ray). trajectory_every:
    frames between re-sends of the whole trajectories, keyframes and loops, with the running ATE (each re-send
    is O(frames so far)). mesh_every: keyframes between meshes of the field (0: only at the end);
    mesh_resolution: their marching-cubes voxel, metres."""

    image_scale: int = Field(2, ge=1)
    render_every: int = Field(20, ge=0)
    render_pixels: int = Field(4800, gt=0)
    trajectory_every: int = Field(5, ge=1)
    mesh_every: int = Field(10, ge=0)
    mesh_resolution: float = Field(0.05, gt=0)


def running_ate(timestamps: np.ndarray, poses: np.ndarray, ground_truth: GroundTruth | None) -> AteResult | None:
    """ATE of the trajectory so far (``timestamps (N,)`` s, ``poses (N, 4, 4)``) against ``ground_truth`` with the
    run's protocol (:func:`lrslam.evaluation.ate.compute_ate`); None without ground truth or below 3 matches."""
    from lrslam.evaluation.ate import compute_ate

    if ground_truth is None or len(timestamps) < 3:
        return None
    try:
        return compute_ate(timestamps, poses, *ground_truth)
    except InputError:     # fewer than 3 frames matched so far, or degenerate
        return None


def aligned_ground_truth(ground_truth: GroundTruth, timestamps: np.ndarray, poses: np.ndarray,
                         T_align: np.ndarray) -> np.ndarray:
    """Ground-truth positions (n, 3) metres matched to the run's frames (``timestamps (N,)`` s, ``poses (N, 4,
    4)``) as the ATE matches them (:func:`lrslam.evaluation.ate.matched_poses`), in the run's world:
    ``inv(T_align)`` applied (``T_align`` (4, 4) maps the run's world into the ground truth's, as
    :class:`~lrslam.evaluation.ate.AteResult` gives it)."""
    from lrslam.evaluation.ate import matched_poses

    _, _, gt = matched_poses(timestamps, poses, *ground_truth)
    return transform_points(inv(T_align), gt[:, :3, 3])


def _as_ground_truth(ground_truth: GroundTruth | None) -> GroundTruth | None:
    """float64 arrays (non-finite rows are skipped by the ATE's own association, as in the run's evaluation)."""
    return None if ground_truth is None else tuple(np.asarray(x, dtype=np.float64) for x in ground_truth)


class RerunViewer:
    """Draws a run in Rerun, frame by frame (see the module docstring).

    Args:
        spawn: start a Rerun viewer and stream to it. rrd: record to this ``.rrd`` file (headless machines, CI).
        cfg: what to draw how often. ground_truth: ``(timestamps (M,) s, T_w_c (M, 4, 4))`` or None.
    Raises:
        InputError: rerun-sdk is not installed, or neither ``spawn`` nor ``rrd``.

    The viewer is spawned / the file created at the first frame (``lrslam run`` prepares its run folder, which
    may hold the file, in between).
    """

    def __init__(self, spawn: bool = False, rrd: str | Path | None = None, cfg: ViewerConfig | None = None,
                 ground_truth: GroundTruth | None = None, name: str = "lrslam") -> None:
        self.cfg = cfg or ViewerConfig()
        if not spawn and rrd is None:
            raise InputError("the viewer needs somewhere to go: spawn a viewer or give an .rrd file")
        import_rerun()     # fail now, not at the first frame
        self._sink = (spawn, rrd, name)
        self._stream: RerunStream | None = None
        self.ground_truth = _as_ground_truth(ground_truth)
        self.seconds = 0.0          # the viewer's own wall time so far
        self.frames = 0
        self._seeds: list[np.ndarray] = []
        self._frontend: list[np.ndarray] = []
        self._edges: list[tuple[int, int]] = []
        self._field: FieldView | None = None
        self._last = (0, 0.0)               # index and timestamp of the last frame drawn
        self._keyframes_since_mesh = 0
        self._render_stride = 0            # pixel stride of the renders, set by the first frame

    def set_ground_truth(self, ground_truth: GroundTruth | None) -> None:
        """``(timestamps (M,) s, T_w_c (M, 4, 4))`` for the running ATE and the ``gt`` trajectory (None: none)."""
        self.ground_truth = _as_ground_truth(ground_truth)

    @property
    def stream(self) -> RerunStream:
        """The recording (opened on first use)."""
        if self._stream is None:
            self._stream = RerunStream(*self._sink)
        return self._stream

    # ------------------------------------------------------------------------------------------------ observer
    def on_frame(self, event: FrameEvent) -> None:
        """Draw one tracked frame (see :class:`ViewerConfig` for what is drawn when)."""
        t0 = time.perf_counter()
        c, s, i = self.cfg, self.stream, event.index
        self._field, self._last = event.field, (i, event.timestamp)
        s.at(i, event.timestamp)
        # 1. The camera: pose, frustum, images.
        self._cameras(event)
        s.camera(event.result.T_w_c)
        f, k = event.frame, c.image_scale
        s.images("world/camera/image", f.rgb[::k, ::k], f.depth[::k, ::k])
        # 2. The field seen from the tracked pose.
        if event.field is not None and c.render_every and i % c.render_every == 0:
            depth, rgb = event.field.render(event.result.T_w_c, self._render_stride, f.depth)
            s.images("world/camera/render", rgb, depth)
        # 3. Time per stage.
        for stage, sec in event.stage_seconds.items():
            s.scalar(f"timings/{stage}_s", sec)
        s.scalar("timings/frame_s", event.seconds)
        # 4. Trajectories, keyframes, loops, graph corrections, running ATE.
        self._seeds.append(event.T_w_seed[:3, 3].copy())
        if event.T_w_frontend is not None:
            self._frontend.append(event.T_w_frontend[:3, 3].copy())
        self._edges.extend(event.loop_edges)
        if i % c.trajectory_every == 0 or event.moved or event.loop_edges:
            ts, poses = event.trajectory()
            self._trajectories(ts, poses, event.keyframe_ids)
            if event.moved:
                self._corrections(event, poses)
        # 5. The mesh, every few keyframes.
        self._keyframes_since_mesh += bool(event.result.keyframe)
        if event.field is not None and c.mesh_every and self._keyframes_since_mesh >= c.mesh_every:
            ts, poses = event.trajectory()
            s.mesh(event.field.mesh({kf: poses[kf] for kf in event.keyframe_ids}, c.mesh_resolution))
            self._keyframes_since_mesh = 0
        self._spent(t0)

    def on_finish(self, result: SlamResult) -> None:
        """Draw the final trajectories, keyframes, ATE and mesh (the result's, else the field's at
        ``mesh_resolution``) at the last frame, and the run's counts as ``run/summary``; then flush."""
        t0 = time.perf_counter()
        n = len(result.poses)
        ts = result.timestamps if result.timestamps is not None else np.arange(n, dtype=np.float64)
        self.stream.at(n - 1, float(ts[-1]) if n else self._last[1])
        self._seeds = list(result.seed_poses[:n, :3, 3])
        if result.frontend_poses is not None:
            self._frontend = list(result.frontend_poses[:n, :3, 3])
        self._trajectories(ts, result.poses, result.keyframe_ids)
        mesh = result.mesh
        if mesh is None and self._field is not None:
            mesh = self._field.mesh({kf: result.poses[kf] for kf in result.keyframe_ids}, self.cfg.mesh_resolution)
        self.stream.mesh(mesh)
        lines = [f"- {k}: {v}" for k, v in result.counts.items()]
        self.stream.text("run/summary", f"### lrslam run: {n} frames, {len(result.keyframe_ids)} keyframes\n\n"
                         + "\n".join(lines))
        self.seconds += time.perf_counter() - t0
        self.stream.rec.flush()

    def close(self) -> None:
        """Flush and close the recording (idempotent; also on Ctrl-C when used as a context manager)."""
        if self._stream is not None:
            self._stream.close()

    def __enter__(self) -> RerunViewer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------------------------------------ parts
    def _cameras(self, event: FrameEvent) -> None:
        """The Pinholes of the images and of the renders (once: the intrinsics are fixed)."""
        if self._render_stride:
            return
        f, k = event.frame, self.cfg.image_scale
        r = self._render_stride = max(1, int(np.ceil(np.sqrt(f.width * f.height / self.cfg.render_pixels))))
        self.stream.pinhole("world/camera/image", strided_intrinsics(f.K, k), -(-f.width // k), -(-f.height // k))
        self.stream.pinhole("world/camera/render", strided_intrinsics(f.K, r), -(-f.width // r), -(-f.height // r),
                            plane_m=0.1)

    def _trajectories(self, ts: np.ndarray, poses: np.ndarray, keyframe_ids) -> None:
        """Every trajectory, the keyframes and loops at the current poses, and the running ATE."""
        s = self.stream
        positions = poses[:, :3, 3]
        s.trajectory("fused", positions)
        s.trajectory("seed", np.asarray(self._seeds))
        if self._frontend:
            s.trajectory("frontend", np.asarray(self._frontend))
        ids = [k for k in keyframe_ids if k < len(poses)]
        s.keyframes(positions[ids], ids)
        edges = [(a, b) for a, b in self._edges if max(a, b) < len(poses)]
        if edges:
            s.loops(np.stack([[positions[a], positions[b]] for a, b in edges]))
        ate = running_ate(ts, poses, self.ground_truth)
        if ate is not None:
            s.scalar("metrics/ate_cm", ate.rmse_cm)
            s.trajectory("gt", aligned_ground_truth(self.ground_truth, ts, poses, ate.T_align))

    def _corrections(self, event: FrameEvent, poses: np.ndarray) -> None:
        moved_from = event.moved_from
        ids = sorted(moved_from)
        if ids:
            self.stream.corrections(np.stack([moved_from[k] for k in ids]), poses[ids, :3, 3],
                                    100.0 * max(m for m, _ in event.moved.values()))

    def _spent(self, t0: float) -> None:
        """Count a frame's drawing time (``t0``: when it began) and log it as ``timings/viewer_s``."""
        dt = time.perf_counter() - t0
        self.seconds += dt
        self.frames += 1
        self.stream.scalar("timings/viewer_s", dt)
