"""One SLAM loop built from parts (:mod:`lrslam.pipeline.parts`), read as numbered steps per frame:

1. seed     — constant velocity (ESLAM) or the frontend's odometry
2. refine   — LRSLAM field tracking by rendering loss from the seed (or from the constant-velocity guess when the
               two disagree and the field fits the guess better), kept only where it is better, when asked
3. keyframe — every N frames (ESLAM) or the motion / overlap policy
4. map      — joint field + window-pose optimisation; the refined poses go back into the trajectory (with
               ``schedule.background_mapping`` the round runs in a worker thread beside the next frames' tracking,
               and its poses come back when the next round is due, at a keyframe with a graph, or at the end)
5. graph    — keyframe node + frontend, field and loop factors; solved when a loop brings a real correction
6. re-map   — when the solve moved keyframes, the field is re-optimised at the corrected poses

The runner's :class:`~lrslam.pipeline.trajectory.Trajectory` is the one owner of every pose: each part gets
the poses it needs as arguments and returns what it changed. The runner never reads ground truth: the initial
pose is passed in by the caller. :meth:`SlamRunner.finish` returns a frozen :class:`SlamResult`.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field as dc_field
from typing import TYPE_CHECKING

import numpy as np

from lrslam.errors import InputError
from lrslam.frame import Frame
from lrslam.pipeline.config import RunConfig
from lrslam.backend.policy import Correction, FactorRecord
from lrslam.pipeline.contracts import Refinement, Seed
from lrslam.pipeline.parts import Parts, build_parts
from lrslam.pipeline.timing import StageTimer
from lrslam.pipeline.trajectory import Trajectory

if TYPE_CHECKING:
    from lrslam.frontend.odometry import OdometryTrace

__all__ = ["SlamRunner", "FrameRecord", "SlamResult"]

log = logging.getLogger(__name__)


@dataclass
class FrameRecord:
    """What happened to one frame (for the run log and metrics)."""

    index: int
    seed_ok: bool = True
    seed_weak: bool = False   # the odometry registered the frame with a fitness below gates.trusted_fitness
    refine_ok: bool | None = None
    refine_accepted: bool = False
    refine_iters: int = 0
    refine_start: int = 0
    has_depth: bool = True
    keyframe: bool = False
    loops: int = 0
    solved: bool = False
    remapped: bool = False
    notes: list[str] = dc_field(default_factory=list)
    loop_edges: list[tuple[int, int]] = dc_field(default_factory=list)   # (i, j) keyframe ids of the loops added
    moved: dict[int, tuple[float, float]] = dc_field(default_factory=dict)  # {kf: (m, deg)} the graph moved
    moved_from: dict[int, tuple[float, float, float]] = dc_field(default_factory=dict)  # {kf: xyz (m) before}
    fusion_gain: tuple[float, float] | None = None   # the field's weight (rotation, translation), fused mode


@dataclass(frozen=True)
class SlamResult:
    """Everything a run produced, for the output writers (they never reach into the runner).

    poses: (N, 4, 4) ``T_w_c`` (after :meth:`lrslam.Slam.finish`: smoothed under the motion prior,
    :mod:`lrslam.backend.smoother`). keyframe_ids: frame indices. seed_poses: (N, 4, 4) per-frame seeds.
    frontend_poses: (N, 4, 4) the frontend's own estimate (odometry alone) or None without one.
    records: per-frame :class:`FrameRecord`. counts: loops, solves, re-maps, reverted mapping poses ...
    mesh: the field's mesh (``trimesh.Trimesh``) or None. parameters: field parameter counts or None.
    device: the field's device or None. timestamps: (N,) seconds of the frames (set by :class:`lrslam.Slam`).
    online_poses: (N, 4, 4) ``T_w_c`` as tracked online, before the final global refinement moved keyframes
    (``backend.final_refine``); None when no final refinement was solved (the poses before smoothing are then the
    online ones).
    unsmoothed_poses: (N, 4, 4) ``T_w_c`` before the final smoothing (``smoothing``, :mod:`lrslam.backend.smoother`;
    set by :meth:`lrslam.Slam.finish`); None when it was not smoothed.
    """

    poses: np.ndarray
    keyframe_ids: tuple[int, ...]
    seed_poses: np.ndarray
    frontend_poses: np.ndarray | None
    records: tuple[FrameRecord, ...]
    counts: dict
    mesh: object | None = None
    parameters: dict | None = None
    device: str | None = None
    timestamps: np.ndarray | None = None
    factors: tuple[FactorRecord, ...] = ()
    online_poses: np.ndarray | None = None
    unsmoothed_poses: np.ndarray | None = None


class SlamRunner:
    """Runs one sequence frame by frame with the parts ``cfg.parts`` asks for.

    Args:
        cfg: the run config (each part gets its own section only).
        K: (3, 3) intrinsics; height, width: image size in pixels.
        bound: (3, 2) scene bound in metres (world frame) for the field.
        timer: accumulates per-stage wall time.
        odometry_trace: an earlier odometry pass over the same frames for the frontend to replay (see
            :func:`build_parts`).
    """

    def __init__(self, cfg: RunConfig, K: np.ndarray, height: int, width: int, bound: np.ndarray,
                 timer: StageTimer | None = None, *, odometry_trace: OdometryTrace | None = None) -> None:
        self.timer = timer or StageTimer()
        self.traj = Trajectory(interpolate=cfg.schedule.interpolate_non_keyframes)
        self.parts: Parts = build_parts(cfg, K, height, width, bound, odometry_trace)
        self._seeds: list[np.ndarray] = []
        self._frontend: list[np.ndarray] = []
        self._records: list[FrameRecord] = []
        self.n_remaps = 0

    @property
    def n_loops(self) -> int:
        return self.parts.backend.n_loops if self.parts.backend is not None else 0

    # ------------------------------------------------------------------------------------------------ frames
    def start(self, frame: Frame, T_w_c0: np.ndarray, progress=None) -> FrameRecord:
        """First frame: fixes the world frame at ``T_w_c0`` and initialises every part. ``progress(done, total)``
        is called per iteration of the field's first-frame fit (the longest step of a run)."""
        p = self.parts
        frame.require_depth()
        T0 = np.asarray(T_w_c0, dtype=np.float64)
        p.seeder.start(frame, T0)
        p.keyframer.start(frame)
        if p.mapper is not None:
            with self.timer("map"):
                p.mapper.start(frame, T0, progress)
        if p.backend is not None:
            with self.timer("graph"):
                p.backend.start(frame, T0)
        if p.fusion is not None:
            p.fusion.start(T0, p.seeder.frontend_pose())
        self.traj.add(T0, is_keyframe=True)
        return self._record(FrameRecord(frame.index, keyframe=True), Seed(T0), T0)

    def step(self, frame: Frame) -> FrameRecord:
        """Process the next frame (indices must follow :meth:`start` in order)."""
        p, rec = self.parts, FrameRecord(frame.index)
        rec.has_depth = frame.valid_depth_fraction() > 0
        if not rec.has_depth:
            rec.notes.append("no valid depth: pose from the seed, no mapping")
            log.warning("frame %d: no valid depth; keeping the seed pose and skipping mapping", frame.index)

        # 1. seed (after fast motion, a background mapping round is waited for first: see ScheduleConfig)
        if p.mapper is not None and p.mapper.must_wait(self.traj):
            self._sync_mapper()
        with self.timer("seed"):
            seed = p.seeder.seed(frame, self.traj)
        rec.seed_ok = seed.ok
        rec.seed_weak = seed.ok and seed.weak   # a failed odometry is counted in seed_failures
        if seed.note:
            rec.notes.append(seed.note)
        if p.backend is not None:
            p.backend.on_frame(seed.odometry)

        # 2. refine
        T, information, ref = seed.T_w_c, None, None
        if p.refiner is not None and rec.has_depth:
            with self.timer("refine"):
                ref = p.refiner.refine(frame, seed)
            T, information = ref.T_w_c, ref.information
            self._note_refinement(rec, ref)
        if p.fusion is not None:
            T = self._fuse(seed, ref, rec)

        # 3. keyframe
        with self.timer("keyframe"):
            rec.keyframe = rec.has_depth and p.keyframer.is_keyframe(frame, T, self.traj)
        idx = self.traj.add(T, is_keyframe=rec.keyframe)

        # 4. map (the window poses the mapper refined go back into the trajectory; in the background, those of
        #    the previous round)
        if p.mapper is not None and rec.has_depth and p.mapper.due(frame, rec.keyframe, seed.uncertain):
            with self.timer("map"):
                self._write_mapped(p.mapper.map(frame, T, self.traj.keyframe_poses(), add_keyframe=rec.keyframe))

        # 5-6. graph and re-map (on the mapped keyframe poses: a background round is waited for)
        if p.backend is not None and rec.keyframe:
            self._sync_mapper()
            self._graph_and_remap(frame, information, rec)
        return self._record(rec, seed, self.traj.pose(idx))

    def _fuse(self, seed: Seed, ref: Refinement | None, rec: FrameRecord) -> np.ndarray:
        """Step 2b: the odometry's seed and the field's pose (``ref``; None for a frame without depth) weighed by
        their measured noise. A refinement that started from the constant-velocity guess (the field judged the
        odometry broken), or a weak registration (fitness below ``gates.trusted_fitness``), fuses as a frame without
        odometry: the field's word."""
        start = ref.start if ref is not None else 0
        if rec.seed_weak:
            rec.notes.append(f"odometry weak (fitness {seed.odometry.fitness:.2f}): the field's word")
        odometry_ok = seed.ok and start == 0
        T_field = ref.T_w_c if ref is not None and ref.ok and ref.accepted else None
        fused = self.parts.fusion.fuse(seed.candidate(start), odometry_ok, T_field,
                                       self.parts.seeder.frontend_pose() if seed.ok else None, not rec.seed_weak)
        rec.fusion_gain = fused.gain
        return fused.T_w_c

    @staticmethod
    def _note_refinement(rec: FrameRecord, ref: Refinement) -> None:
        rec.refine_ok, rec.refine_accepted = ref.ok, ref.accepted
        rec.refine_iters, rec.refine_start = ref.iters, ref.start
        if ref.note:
            rec.notes.append(ref.note)

    def _sync_mapper(self) -> None:
        """The one synchronisation point with a background mapping round: wait for it and write its poses back
        (nothing to wait for in the serial schedule or without a mapper)."""
        if self.parts.mapper is not None:
            with self.timer("map"):
                self._write_mapped(self.parts.mapper.collect())

    def _write_mapped(self, refined: dict) -> None:
        """Mapper-optimised poses (the round's frame and window keyframes) back into the trajectory (in fused mode
        by the field's share only, :meth:`lrslam.backend.frame_fusion.FrameFusion.blend`)."""
        fusion = self.parts.fusion
        for fid, T_opt in refined.items():
            if 0 <= fid < len(self.traj):
                self.traj.set_pose(fid, T_opt if fusion is None else fusion.blend(self.traj.pose(fid), T_opt))

    def _graph_and_remap(self, frame: Frame, information: np.ndarray | None, rec: FrameRecord) -> None:
        """Steps 5-6: the backend's verdict on the new keyframe, its corrections written into the trajectory,
        and the field re-mapped over the keyframes it names."""
        p = self.parts
        noise, T_field = (p.fusion.gap_noise(), p.fusion.field_pose()) if p.fusion is not None else (None, None)
        with self.timer("graph"):
            corr = p.backend.on_keyframe(frame, self.traj.keyframe_poses(), information, noise, T_field)
        if p.fusion is not None:
            p.fusion.on_keyframe(corr.link)
        rec.loops, rec.solved = corr.loops, corr.solved
        rec.loop_edges = [(int(i), int(j)) for i, j in corr.edges]
        if not corr.solved:
            return
        rec.moved = {int(k): (float(m), float(d)) for k, (m, d) in corr.shifts.items()}
        rec.moved_from = {int(k): tuple(float(x) for x in self.traj.pose(k)[:3, 3]) for k in corr.poses}
        rec.remapped = self._apply(corr, f"keyframe {frame.index}")

    def _apply(self, corr: Correction, what: str) -> bool:
        """Write a solve's corrections into the trajectory and re-map the field over the keyframes it names;
        returns whether it re-mapped."""
        self.traj.apply_corrections(corr.poses)
        if not corr.remap or self.parts.mapper is None:
            return False
        with self.timer("remap"):
            self.parts.mapper.remap(self.traj.keyframe_poses(), list(corr.remap))
        self.n_remaps += 1
        log.info("%s: graph moved %d keyframe(s) (max %.3f m); re-mapped %d", what, len(corr.poses),
                 corr.shifts[corr.remap[0]][0], len(corr.remap))
        return True

    def refine_all(self) -> Correction | None:
        """The final global refinement (``backend.final_refine``; :meth:`finish` calls it): one solve over every
        keyframe and factor, its corrections written, the field re-mapped over the most-moved keyframes. Returns
        the backend's correction (not solved when the backend's policy says no), None without a backend."""
        p = self.parts
        if p.backend is None:
            return None
        self._sync_mapper()
        with self.timer("graph"):
            corr = p.backend.refine_all(self.traj.keyframe_poses(),
                                        p.fusion.gap_noise() if p.fusion is not None else None)
        if corr.solved:
            log.info("final refinement: %d keyframe(s) moved (max %.3f m)", len(corr.poses), corr.max_shift_m)
            self._apply(corr, "final refinement")
        return corr

    def _record(self, rec: FrameRecord, seed: Seed, T: np.ndarray) -> FrameRecord:
        self._seeds.append(np.asarray(seed.T_w_c, dtype=np.float64).copy())
        frontend = self.parts.seeder.frontend_pose()
        if frontend is not None:
            self._frontend.append(frontend)
        self._records.append(rec)
        return rec

    def last_seed(self) -> tuple[np.ndarray, np.ndarray | None]:
        """The last frame's seed ``T_w_c`` (4, 4) and the frontend's own pose of it (None without a frontend)."""
        frontend = self._frontend[-1] if self._frontend and len(self._frontend) == len(self._seeds) else None
        return self._seeds[-1].copy(), None if frontend is None else np.array(frontend, dtype=np.float64)

    # ------------------------------------------------------------------------------------------------ state
    def checkpoint(self) -> dict:
        """The run state after the last processed frame, as plain Python / numpy data (torch's tensors stay in
        the field's own arrays): trajectory, every part's state, per-frame records, counters and stage timer.
        :meth:`restore` on a runner built from the same config and camera continues exactly from here."""
        p = self.parts
        return {
            "trajectory": self.traj.state_dict(),
            "seeder": p.seeder.state_dict(), "keyframer": p.keyframer.state_dict(),
            "field": p.mapper.state_dict() if p.mapper is not None else None,
            "backend": p.backend.state_dict() if p.backend is not None else None,
            "fusion": p.fusion.state_dict() if p.fusion is not None else None,
            "seeds": np.stack(self._seeds) if self._seeds else np.zeros((0, 4, 4)),
            "frontend": np.stack(self._frontend) if self._frontend else None,
            "records": [asdict(r) for r in self._records],
            "n_remaps": self.n_remaps, "timer": self.timer.state_dict(),
        }

    def restore(self, state: dict) -> None:
        """Continue from :meth:`checkpoint` output (instead of :meth:`start`)."""
        p = self.parts
        if ((state["field"] is None) != (p.mapper is None) or (state["backend"] is None) != (p.backend is None)
                or (state.get("fusion") is None) != (p.fusion is None)):
            raise InputError("checkpoint: it was saved by a runner built from other parts")
        self.traj.load_state_dict(state["trajectory"])
        p.seeder.load_state_dict(state["seeder"])
        p.keyframer.load_state_dict(state["keyframer"])
        if p.mapper is not None:
            p.mapper.load_state_dict(state["field"])
        if p.backend is not None:
            p.backend.load_state_dict(state["backend"])
        if p.fusion is not None:
            p.fusion.load_state_dict(state["fusion"])
        self._seeds = [np.asarray(T, dtype=np.float64) for T in state["seeds"]]
        self._frontend = [] if state["frontend"] is None else [np.asarray(T, dtype=np.float64)
                                                               for T in state["frontend"]]
        self._records = [FrameRecord(**r) for r in state["records"]]
        self.n_remaps = int(state["n_remaps"])
        self.timer.load_state_dict(state["timer"])

    # ------------------------------------------------------------------------------------------------ results
    def poses(self) -> np.ndarray:
        """(N, 4, 4) current ``T_w_c`` of every frame so far (also for a partial trajectory after a crash)."""
        return self.traj.poses()

    def finish(self, mesh: bool = True, mesh_resolution: float | None = None) -> SlamResult:
        """The run's frozen result (with the field's mesh when there is a field and ``mesh``)."""
        p = self.parts
        field_mesh = None
        online = self.traj.poses()
        final = self.refine_all()
        if p.mapper is not None:
            self._sync_mapper()
            p.mapper.stop()
            if mesh:
                with self.timer("mesh"):
                    field_mesh = p.mapper.mesh(self.traj.keyframe_poses(), mesh_resolution)
        recs = tuple(self._records)
        counts = {
            "n_loop_closures": self.n_loops, "n_remaps": self.n_remaps,
            "n_graph_solves": p.backend.n_solves if p.backend is not None else 0,
            "n_loops_disputed_by_field": p.backend.n_loops_disputed if p.backend is not None else 0,
            "loops": p.backend.loop_counts if p.backend is not None else None,
            "final_refine_max_shift_m": final.max_shift_m if final is not None and final.solved else None,
            "seed_failures": sum(not r.seed_ok for r in recs),
            "refine_failures": sum(r.refine_ok is False for r in recs),
            "refinements_kept": sum(bool(r.refine_accepted) for r in recs),
            "refinements_rejected": sum(r.refine_ok is True and not r.refine_accepted for r in recs),
            "frames_without_depth": sum(not r.has_depth for r in recs),
            "mapping_poses_reverted": p.mapper.reverted_poses if p.mapper is not None else 0,
            "seeds_overruled_by_field": sum(r.refine_start > 0 for r in recs),
            "seeds_weak": sum(r.seed_weak for r in recs),
            "fusion_sigmas": p.fusion.sigmas() if p.fusion is not None else None,
            "refine_iters_mean": float(np.mean([r.refine_iters for r in recs if r.refine_ok is not None] or [0])),
        }
        return SlamResult(
            poses=self.traj.poses(), keyframe_ids=tuple(self.traj.keyframe_ids()), seed_poses=np.stack(self._seeds),
            frontend_poses=np.stack(self._frontend) if self._frontend else None, records=recs, counts=counts,
            mesh=field_mesh, parameters=p.mapper.parameter_count() if p.mapper is not None else None,
            device=p.mapper.device if p.mapper is not None else None,
            factors=tuple(p.backend.calibrated_measurements()) if p.backend is not None else (),
            online_poses=online if final is not None and final.solved else None)
