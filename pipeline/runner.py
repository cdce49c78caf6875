"""One SLAM pipeline, three modes (``field`` / ``frontend`` / ``fused``), read as numbered steps per frame:

1. seed     — constant-velocity prediction (field mode) or frontend odometry (frontend, fused)
2. refine   — LRSLAM field tracking by rendering loss from the seed (field, fused)
3. keyframe — ESLAM every-N rule (field) or the distance/angle/overlap policy (frontend, fused)
4. map      — joint field + window-pose optimisation (field, fused)
5. graph    — keyframe node + frontend, field and loop-closure factors; optimise (fused)
6. re-map   — when the graph moved keyframes, the field is re-optimised with the corrected poses (fused)

Non-keyframes are stored relative to their keyframe, so graph corrections move them too. The runner never
reads ground truth: the initial pose is passed in by the caller.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field as dc_field

import numpy as np

from lrslam.frontend.frame import Frame
from lrslam.geometry import inv, pose_error
from lrslam.pipeline.anchored import AnchoredTrajectory
from lrslam.pipeline.config import RunConfig
from lrslam.pipeline.timing import StageTimer

__all__ = ["SlamRunner", "FrameLog"]

log = logging.getLogger(__name__)


@dataclass
class FrameLog:
    """What happened to one frame (for the run log and metrics)."""

    index: int
    seed_ok: bool = True
    refine_ok: bool | None = None
    keyframe: bool = False
    loops: int = 0
    remapped: bool = False
    notes: list[str] = dc_field(default_factory=list)


class SlamRunner:
    """Runs one sequence frame by frame in the configured mode.

    Args:
        cfg: the run config (components get their own sections only).
        K: (3, 3) intrinsics; height, width: image size in pixels.
        bound: (3, 2) scene bound in metres (world frame) for the field.
        timer: accumulates per-stage wall time.
    """

    def __init__(self, cfg: RunConfig, K: np.ndarray, height: int, width: int, bound: np.ndarray,
                 timer: StageTimer | None = None) -> None:
        self.mode = cfg.mode
        self.schedule = cfg.schedule
        self.timer = timer or StageTimer()
        self.traj = AnchoredTrajectory()
        self.seed_poses: list[np.ndarray] = []
        self.n_loops = 0
        self.n_remaps = 0
        self.field = self.odometry = self.policy = self.graph = self.loop_closer = None
        self._last_kf_frame: Frame | None = None
        if self.mode in ("field", "fused"):
            from lrslam.field.slam import FieldSLAM

            self.field = FieldSLAM(cfg.field_config(), np.asarray(bound, dtype=np.float64), K, height, width)
        if self.mode in ("frontend", "fused"):
            from lrslam.frontend.keyframes import KeyframePolicy
            from lrslam.frontend.odometry import Odometry

            self.odometry = Odometry(cfg.odometry_config(), K, height, width)
            self.policy = KeyframePolicy(cfg.keyframe_config())
        if self.mode == "fused":
            from lrslam.backend.graph import PoseGraph
            from lrslam.frontend.loop_closure import LoopCloser

            self.graph = PoseGraph(cfg.graph_config())
            self.loop_closer = LoopCloser(cfg.loop_closure_config())
            self._odometry_cfg = cfg.odometry_config()

    # ------------------------------------------------------------------------------------------------ frames
    def start(self, frame: Frame, T_w_c0: np.ndarray) -> FrameLog:
        """First frame: fixes the world frame at ``T_w_c0`` and initialises every component."""
        rec = FrameLog(frame.index, keyframe=True)
        if frame.valid_depth_fraction() == 0:
            raise ValueError(f"frame {frame.index}: the first frame has no valid depth; cannot initialise the map")
        if self.odometry is not None:
            self.odometry.reset(T_w_c0, frame)
        if self.field is not None:
            with self.timer("map"):
                self.field.initialise(frame.index, frame.rgb, frame.depth, T_w_c0)
        if self.graph is not None:
            with self.timer("graph"):
                self.graph.add_keyframe(frame.index, T_w_c0)
                self.loop_closer.add_keyframe(frame.index, frame, T_w_c0)
        if self.policy is not None:
            self.policy.is_keyframe(frame.index, T_w_c0, frame.depth, frame.K)  # registers the first keyframe
        self._last_kf_frame = frame
        self.seed_poses.append(np.asarray(T_w_c0, dtype=np.float64))
        self.traj.add(T_w_c0, is_keyframe=True)
        return rec

    def step(self, frame: Frame) -> FrameLog:
        """Process the next frame (indices must follow :meth:`start` in order)."""
        rec = FrameLog(frame.index)
        has_depth = frame.valid_depth_fraction() > 0
        if not has_depth:
            rec.notes.append("no valid depth: pose from the seed, no mapping")
            log.warning("frame %d: no valid depth; keeping the seed pose and skipping mapping", frame.index)

        # 1. seed
        with self.timer("seed"):
            T_seed, rec.seed_ok = self._seed(frame)
        self.seed_poses.append(T_seed)

        # 2. refine
        T = T_seed
        if self.field is not None and has_depth:
            with self.timer("refine"):
                res = self.field.track(frame.rgb, frame.depth, T_seed)
            rec.refine_ok = bool(res.ok)
            if res.ok:
                T = res.T_w_c
            else:
                rec.notes.append(f"field tracking fell back to the seed: {res.reason}")
        if self.odometry is not None:
            self.odometry.correct(frame.index, T)

        # 3. keyframe
        with self.timer("keyframe"):
            rec.keyframe = has_depth and self._is_keyframe(frame, T)
        idx = self.traj.add(T, is_keyframe=rec.keyframe)

        # 4. map
        if self.field is not None and has_depth and (rec.keyframe or frame.index % self.schedule.map_every == 0):
            with self.timer("map"):
                optimised = self.field.map(frame.index, frame.rgb, frame.depth, T, add_keyframe=rec.keyframe)
            for fid, T_opt in optimised.items():
                if fid == frame.index:
                    self.traj.set_pose(idx, T_opt)
                elif fid in self.traj.keyframe_ids():
                    self.traj.update_keyframes({fid: T_opt})
            T = self.traj.pose(idx)
            if self.odometry is not None:
                self.odometry.correct(frame.index, T)

        # 5-6. graph and re-map
        if self.graph is not None and rec.keyframe:
            self._graph_update(frame, T, rec)
        if rec.keyframe:
            self._last_kf_frame = frame
        return rec

    # ------------------------------------------------------------------------------------------------ steps
    def _seed(self, frame: Frame) -> tuple[np.ndarray, bool]:
        if self.odometry is not None:
            res = self.odometry.track(frame)
            if not res.ok:
                log.info("frame %d: odometry fell back to constant velocity (%s)", frame.index, res.reason)
            return np.asarray(res.T_w_c, dtype=np.float64), bool(res.ok)
        n = len(self.traj)
        T_prev = self.traj.pose(n - 1)
        if n < 2:
            return T_prev, True
        T_prev2 = self.traj.pose(n - 2)
        return T_prev @ inv(T_prev2) @ T_prev, True          # constant velocity (ESLAM)

    def _is_keyframe(self, frame: Frame, T_w_c: np.ndarray) -> bool:
        if self.mode == "field":
            return frame.index % self.schedule.keyframe_every == 0
        is_kf, _reason = self.policy.is_keyframe(frame.index, T_w_c, frame.depth, frame.K)
        return bool(is_kf)

    def _graph_update(self, frame: Frame, T_w_c: np.ndarray, rec: FrameLog) -> None:
        from lrslam.frontend.registration import register_rgbd

        prev = self._last_kf_frame
        kf_poses = self.traj.keyframe_poses()
        T_w_prev = kf_poses[prev.index]
        with self.timer("graph"):
            self.graph.add_keyframe(frame.index, T_w_c)
            # field-refined relative pose between consecutive keyframes
            T_prev_cur = inv(T_w_prev) @ T_w_c
            self.graph.add_field_relative(prev.index, frame.index, T_prev_cur)
            # independent frontend constraint: register this keyframe against the previous one
            reg = register_rgbd(frame, prev, T_prev_cur, self._odometry_cfg)
            if reg.ok:
                self.graph.add_odometry(prev.index, frame.index, reg.T_tgt_src, reg.information)
            else:
                rec.notes.append(f"keyframe registration rejected: {reg.reason}")
            # loop closures against earlier keyframes
            loops = self.loop_closer.detect(frame.index, frame, T_w_c)
            for lc in loops:
                self.graph.add_loop(lc.i, lc.j, lc.T_i_j, lc.information)
            self.loop_closer.add_keyframe(frame.index, frame, T_w_c)
            rec.loops = len(loops)
            self.n_loops += len(loops)
            if not (self.schedule.graph_every_keyframe or loops):
                return
            new_poses = self.graph.optimise()
        shifts = {k: pose_error(kf_poses.get(k, T_w_c), T)[0] for k, T in new_poses.items()}
        moved = [k for k, s in sorted(shifts.items(), key=lambda kv: -kv[1]) if s > self.schedule.remap_min_shift_m]
        self.traj.update_keyframes(new_poses)
        self.loop_closer.update_poses(new_poses)          # proximity search uses the corrected poses
        for k, T_k in new_poses.items():
            self.policy.update_pose(k, T_k)
        if moved and self.field is not None:
            with self.timer("remap"):
                self.field.set_keyframe_poses(new_poses)
                self.field.remap(moved[: self.schedule.remap_keyframes], self.schedule.remap_iters)
            rec.remapped = True
            self.n_remaps += 1
        if self.odometry is not None:
            self.odometry.correct(frame.index, self.traj.pose(len(self.traj) - 1))

    # ------------------------------------------------------------------------------------------------ results
    def keyframe_poses(self) -> dict[int, np.ndarray]:
        return self.traj.keyframe_poses()

    def poses(self) -> np.ndarray:
        return self.traj.poses()
