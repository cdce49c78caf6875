"""The parts a SLAM run is built from, and the factory that builds the runner from config.

- seeder: where a frame's pose starts -- :class:`ConstantVelocitySeeder` (ESLAM) or :class:`OdometrySeeder`
  (the frontend's frame-to-frame motion applied to the last pose);
- refiner: :class:`FieldRefiner` (LRSLAM tracking by rendering loss) or :class:`NoRefiner`;
- keyframer: :class:`EveryNKeyframer` (ESLAM) or :class:`PolicyKeyframer` (motion / overlap);
- mapper: :class:`FieldMapper` (joint field + window-pose optimisation, re-maps), present with the field;
- backend: :class:`GraphBackend` (GTSAM pose graph with frontend, field and loop factors) or none.

``field``, ``frontend`` and ``fused`` are presets of this factory (:data:`lrslam.pipeline.config.MODE_PRESETS`).
Parts keep no pose copies: they receive the poses they need from the runner's :class:`Trajectory`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field as dc_field

import numpy as np

from lrslam.frame import Frame
from lrslam.geometry import diagonal_information, inv, pose_error, pose_from_tum, pose_to_tum
from lrslam.pipeline.config import BackendConfig, RunConfig
from lrslam.pipeline.trajectory import Trajectory

__all__ = ["Seed", "Refinement", "Correction", "ConstantVelocitySeeder", "OdometrySeeder", "FieldRefiner",
           "NoRefiner", "EveryNKeyframer", "PolicyKeyframer", "FieldMapper", "GraphBackend", "build_parts"]

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Seed:
    """A frame's starting pose ``T_w_c`` (4, 4); ``ok`` False when the seeder fell back to a guess;
    ``odometry``: the frontend's result for the frame (None without one); ``alternatives``: other starting
    poses (4, 4) worth comparing with ``T_w_c`` by the field (a refiner picks the one it fits best)."""

    T_w_c: np.ndarray
    ok: bool = True
    odometry: object | None = None
    note: str = ""
    alternatives: tuple[np.ndarray, ...] = ()


@dataclass(frozen=True)
class Refinement:
    """The refined pose ``T_w_c`` (4, 4) (the starting pose when not ``ok`` or not ``accepted``);
    ``information`` (6, 6) of it given the field (None without one); ``ok`` None when there is no refiner;
    ``iters`` tracking iterations run; ``start``: which candidate the refinement started from (0 = the seed's
    ``T_w_c``, k = its ``alternatives[k - 1]``)."""

    T_w_c: np.ndarray
    ok: bool | None = None
    accepted: bool = False
    information: np.ndarray | None = None
    note: str = ""
    iters: int = 0
    start: int = 0


@dataclass(frozen=True)
class Correction:
    """What the backend did at a keyframe: ``poses`` its solution (``{kf: T_w_c}``, empty when it did not
    solve), ``loops`` verified loop closures added, ``solved``."""

    poses: dict = dc_field(default_factory=dict)
    loops: int = 0
    solved: bool = False


def _constant_velocity(traj: Trajectory) -> np.ndarray:
    """The last motion repeated on SE(3): ``T_{i-1} inv(T_{i-2}) T_{i-1}``."""
    if len(traj) < 2:
        return traj.pose(-1)
    T_prev, T_prev2 = traj.pose(-1), traj.pose(-2)
    return T_prev @ inv(T_prev2) @ T_prev


def _linear_velocity(traj: Trajectory) -> np.ndarray:
    """ESLAM's constant-speed guess: ``2 p_{i-1} - p_{i-2}`` on the 7-vector ``p = (t, q)`` (quaternion
    renormalised), i.e. a linear extrapolation of translation and quaternion, not a motion repeated on SE(3)."""
    if len(traj) < 2:
        return traj.pose(-1)
    p1, p0 = pose_to_tum(traj.pose(-1)), pose_to_tum(traj.pose(-2))
    if np.dot(p1[3:], p0[3:]) < 0:  # same hemisphere, as for an interpolation
        p0[3:] = -p0[3:]
    return pose_from_tum(2.0 * p1 - p0)


class _Stateless:
    """A part whose decisions follow from its config and the trajectory alone: nothing to checkpoint."""

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


# -------------------------------------------------------------------------------------------------- seeders
class ConstantVelocitySeeder(_Stateless):
    """The field-only seed: ``linear`` (ESLAM's linear extrapolation of translation and quaternion) or ``se3``
    (the last relative motion repeated)."""

    def __init__(self, kind: str = "linear") -> None:
        self.guess = _linear_velocity if kind == "linear" else _constant_velocity

    def start(self, frame: Frame, T_w_c0: np.ndarray) -> None:
        pass

    def seed(self, frame: Frame, traj: Trajectory) -> Seed:
        return Seed(self.guess(traj))


class OdometrySeeder:
    """The frontend's frame-to-frame motion (:class:`lrslam.frontend.odometry.Odometry`, its own estimate)
    applied to the trajectory's last pose; constant velocity when the odometry failed.

    ``disagreement``: (metres, degrees), or None. When given and the odometry's seed and the constant-velocity
    guess differ by more than either, the guess goes along as an alternative for the refiner to judge (a
    registration that passed its gates can still be wrong by centimetres at large motion)."""

    def __init__(self, odometry, disagreement: tuple[float, float] | None = None) -> None:
        self.odometry = odometry
        self.disagreement = disagreement

    def start(self, frame: Frame, T_w_c0: np.ndarray) -> None:
        self.odometry.reset(T_w_c0, frame)

    def seed(self, frame: Frame, traj: Trajectory) -> Seed:
        res = self.odometry.track(frame)
        if res.ok:
            T = traj.pose(-1) @ res.T_prev_c
            if self.disagreement is not None and len(traj) >= 2:
                guess = _constant_velocity(traj)
                d_t, d_r = pose_error(T, guess)
                if d_t > self.disagreement[0] or d_r > self.disagreement[1]:
                    return Seed(T, True, res, alternatives=(guess,))
            return Seed(T, True, res)
        log.info("frame %d: odometry failed (%s); constant-velocity seed", frame.index, res.reason)
        return Seed(_constant_velocity(traj), False, res, f"odometry failed: {res.reason}")

    def frontend_pose(self) -> np.ndarray:
        """The frontend's own pose of the last frame (odometry alone)."""
        return self.odometry.last_pose

    def state_dict(self) -> dict:
        return self.odometry.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.odometry.load_state_dict(state)


# -------------------------------------------------------------------------------------------------- refiners
class NoRefiner:
    def refine(self, frame: Frame, seed: Seed) -> Refinement:
        return Refinement(seed.T_w_c)


class FieldRefiner:
    """LRSLAM tracking against the frozen field from the seed (``field.tracking.accept_if_better`` keeps the
    seed unless the refinement lowers the loss on the same rays)."""

    def __init__(self, field) -> None:
        self.field = field

    def refine(self, frame: Frame, seed: Seed) -> Refinement:
        start, note = self._start(frame, seed)
        T0 = seed.T_w_c if start == 0 else seed.alternatives[start - 1]
        res = self.field.track(frame.rgb, frame.depth, T0)
        if not res.ok:
            return Refinement(T0, False, False, None, f"field tracking fell back to its starting pose: {res.reason}",
                              res.iters, start)
        reason = "; ".join(x for x in (note, res.reason) if x)
        return Refinement(res.T_w_c, True, res.accepted, res.information, reason, res.iters, start)

    def _start(self, frame: Frame, seed: Seed) -> tuple[int, str]:
        """Which candidate to refine from: the seed, or the alternative whose tracking loss on the same rays is
        strictly lower (a non-finite loss counts as infinite and never wins; a tie keeps the seed, as argmin
        returns the first minimum)."""
        if not seed.alternatives:
            return 0, ""
        losses = np.asarray(self.field.pose_losses(frame.rgb, frame.depth, [seed.T_w_c, *seed.alternatives]))
        losses = np.where(np.isfinite(losses), losses, np.inf)
        k = int(np.argmin(losses))
        if k == 0:
            return 0, ""
        log.info("frame %d: the field prefers the constant-velocity guess to the odometry's seed (loss %.4g vs "
                 "%.4g)", frame.index, losses[k], losses[0])
        return k, f"started from the constant-velocity guess (loss {losses[k]:.4g} vs {losses[0]:.4g})"


# -------------------------------------------------------------------------------------------------- keyframers
class EveryNKeyframer(_Stateless):
    """ESLAM's rule: every ``n``-th frame is a keyframe."""

    def __init__(self, n: int) -> None:
        self.n = n

    def start(self, frame: Frame) -> None:
        pass

    def is_keyframe(self, frame: Frame, T_w_c: np.ndarray, traj: Trajectory) -> bool:
        return frame.index % self.n == 0


class PolicyKeyframer:
    """Motion / overlap policy (:class:`lrslam.frontend.keyframes.KeyframePolicy`), given the last keyframe's
    current pose from the trajectory."""

    def __init__(self, policy) -> None:
        self.policy = policy

    def start(self, frame: Frame) -> None:
        self.policy.add_keyframe(frame.index, frame.depth, frame.K)

    def is_keyframe(self, frame: Frame, T_w_c: np.ndarray, traj: Trajectory) -> bool:
        last = traj.last_keyframe
        ok, _ = self.policy.is_keyframe(frame.index, T_w_c, None if last is None else traj.pose(last),
                                        frame.depth, frame.K)
        return bool(ok)

    def state_dict(self) -> dict:
        return self.policy.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.policy.load_state_dict(state)


# -------------------------------------------------------------------------------------------------- mapper
class FieldMapper:
    """Field mapping on keyframes and every ``map_every`` frames; re-maps after corrections; the mesh.

    ``background``: each round runs in a worker thread beside the tracking of the next frames
    (:meth:`lrslam.field.slam.FieldSLAM.map_in_background`); :meth:`map` then returns the previous round's poses
    and :meth:`collect` the current one's."""

    def __init__(self, field, map_every: int, background: bool = False,
                 wait_motion: tuple[float, float] = (np.inf, np.inf)) -> None:
        self.field = field
        self.map_every = map_every
        self.background = background
        self.wait_motion = wait_motion

    def must_wait(self, traj: Trajectory) -> bool:
        """Background only: the last frame-to-frame motion exceeded ``wait_motion`` (metres, degrees), so the next
        frame should be tracked on the mapped field (:meth:`collect` first)."""
        if not self.background:
            return False
        d_t, d_r = traj.last_motion()
        return d_t > self.wait_motion[0] or d_r > self.wait_motion[1]

    def start(self, frame: Frame, T_w_c0: np.ndarray, progress=None) -> None:
        self.field.initialise(frame.index, frame.rgb, frame.depth, T_w_c0, progress)
        if self.background:
            self.field.start_background_mapping()

    def due(self, frame: Frame, is_keyframe: bool) -> bool:
        return is_keyframe or frame.index % self.map_every == 0

    def map(self, frame: Frame, T_w_c: np.ndarray, keyframe_poses: dict, add_keyframe: bool) -> dict:
        """One mapping round at ``T_w_c``; returns optimised poses ``{frame id: T_w_c}`` (of this round, or of
        the previous one in the background)."""
        if not self.background:
            return self.field.map(frame.index, frame.rgb, frame.depth, T_w_c, keyframe_poses, add_keyframe)
        done = self.collect()
        self.field.map_in_background(frame.index, frame.rgb, frame.depth, T_w_c, keyframe_poses, add_keyframe)
        return done

    def collect(self) -> dict:
        """The running background round's poses (waits for it; ``{}`` when none or not in the background)."""
        return (self.field.take_mapped() or {}) if self.background else {}

    def stop(self) -> None:
        if self.background:
            self.field.stop_background_mapping()

    def remap(self, keyframe_poses: dict, ids: list[int]) -> dict:
        return self.field.remap(keyframe_poses, ids)

    def mesh(self, keyframe_poses: dict, resolution: float | None):
        return self.field.extract_mesh(keyframe_poses, resolution)


# -------------------------------------------------------------------------------------------------- backend
class GraphBackend:
    """Keyframe pose graph (see :class:`lrslam.pipeline.config.BackendConfig` for the factor sets and the
    solve / write-back rules). Keeps factors, the loop closer's keyframe images and the frontend's chain since
    the last keyframe; every pose comes from the trajectory."""

    def __init__(self, cfg: BackendConfig, graph, loop_closer, link, field_default_information: np.ndarray,
                 pose_losses=None):
        self.cfg = cfg
        self.graph, self.loop_closer, self.link = graph, loop_closer, link
        self._default_info = field_default_information
        self._pose_losses = pose_losses if cfg.loop_field_check else None   # (rgb, depth, [T_w_c]) -> losses
        self._last: int | None = None
        self.n_loops = self.n_solves = self.n_loops_disputed = 0

    def state_dict(self) -> dict:
        """Factors (plain numpy, :meth:`PoseGraph.state`), the loop closer's keyframes, the frontend's chain since
        the last keyframe and the counters, for checkpoints. With ``graph.optimiser: isam2`` GTSAM's own
        linearisation point is not saved: a restored graph re-adds every factor at the next solve."""
        return {"graph": self.graph.state(), "loop_closer": self.loop_closer.state_dict(),
                "link": self.link.state_dict(), "last": self._last, "n_loops": self.n_loops,
                "n_solves": self.n_solves, "n_loops_disputed": self.n_loops_disputed}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output."""
        self.graph = type(self.graph).from_state(self.graph.cfg, state["graph"])
        self.loop_closer.load_state_dict(state["loop_closer"])
        self.link.load_state_dict(state["link"])
        self._last = state["last"]
        self.n_loops, self.n_solves = int(state["n_loops"]), int(state["n_solves"])
        self.n_loops_disputed = int(state["n_loops_disputed"])

    def start(self, frame: Frame, T_w_c0: np.ndarray) -> None:
        self.graph.add_keyframe(frame.index, T_w_c0)
        self.loop_closer.add_keyframe(frame.index, frame)
        self.link.start(frame.index, frame)
        self._last = frame.index

    def on_frame(self, seed: Seed) -> None:
        """Chain the frontend's increment of every frame (the odometry factor's fallback)."""
        if seed.odometry is not None:
            self.link.accumulate(seed.odometry)

    def on_keyframe(self, frame: Frame, poses: dict[int, np.ndarray], information: np.ndarray | None) -> Correction:
        """Add keyframe ``frame.index`` (its pose in ``poses``, every keyframe's current ``T_w_c``) with its
        factors; solve when a loop brings a real correction (or at every keyframe); return the solution."""
        i, j, factors = self._last, frame.index, self.cfg.factors
        self.graph.add_keyframe(j)
        # 1. Field factor: the trajectory's relative pose, with the tracker's information.
        if "field" in factors:
            info = information if information is not None else self._default_info
            self.graph.add_field_relative(i, j, inv(poses[i]) @ poses[j], info)
        # 2. Frontend factor: its own keyframe-to-keyframe estimate.
        link = self.link.measure(j, frame)
        if "odometry" in factors and link is not None:
            self.graph.add_odometry(link.i, link.j, link.T_i_j, link.information)
        # 3. Loops against earlier keyframes.
        loops = []
        if "loop" in factors:
            loops = self._agreed_by_field(self.loop_closer.detect(j, frame, poses), frame, poses)
            for lc in loops:
                self.graph.add_loop(lc.i, lc.j, lc.T_i_j, lc.information)
        self.loop_closer.add_keyframe(j, frame)
        self._last = j
        self.n_loops += len(loops)
        real = [lc for lc in loops if self._is_correction(lc)]
        if len(loops) > len(real):
            log.info("keyframe %d: %d loop(s) consistent with the trajectory (no solve for them)", j,
                     len(loops) - len(real))
        if not (real or self.cfg.optimise == "every_keyframe"):
            return Correction({}, len(loops), False)
        # 4. Solve from the trajectory's poses, field factors re-stated from them (the graph never reverts the
        #    mapper's refinements: only loops and the frontend's measurements move poses).
        for a, b in zip(list(poses)[:-1], list(poses)[1:]):
            self.graph.set_measurement("field", a, b, inv(poses[a]) @ poses[b])
        self.n_solves += 1
        return Correction(self.graph.optimise(poses), len(loops), True)

    def _is_correction(self, lc) -> bool:
        return lc.correction_m > self.cfg.loop_min_correction_m or lc.correction_deg > self.cfg.loop_min_correction_deg

    def _agreed_by_field(self, loops: list, frame: Frame, poses: dict[int, np.ndarray]) -> list:
        """The loops the map does not dispute (see ``BackendConfig.loop_field_check``): consistent
        re-observations always; corrections only where the new keyframe fits the field at the loop's pose at
        least as well as at its current one."""
        if self._pose_losses is None or not any(self._is_correction(lc) for lc in loops):
            return loops
        j = frame.index
        corrections = [lc for lc in loops if self._is_correction(lc)]
        losses = self._pose_losses(frame.rgb, frame.depth, [poses[j]] + [poses[lc.i] @ lc.T_i_j for lc in corrections])
        kept = [lc for lc in loops if not self._is_correction(lc)]
        for lc, loss in zip(corrections, losses[1:]):
            if np.isfinite(loss) and np.isfinite(losses[0]) and loss > losses[0] * (1.0 + self.cfg.loop_field_tolerance):
                self.n_loops_disputed += 1
                log.info("loop %d-%d dropped: the map disputes its correction (%.3f m, %.2f deg; loss %.4g vs %.4g "
                         "at the current pose)", lc.i, j, lc.correction_m, lc.correction_deg, loss, losses[0])
            else:
                kept.append(lc)
        return kept


# -------------------------------------------------------------------------------------------------- factory
@dataclass
class Parts:
    seeder: object
    refiner: object
    keyframer: object
    mapper: FieldMapper | None
    backend: GraphBackend | None
    field: object | None


def build_parts(cfg: RunConfig, K: np.ndarray, height: int, width: int, bound: np.ndarray) -> Parts:
    """Build the configured parts (``cfg.parts``); each gets its own config section only."""
    p = cfg.parts
    field = None
    if p.refiner == "field":
        from lrslam.field.slam import FieldSLAM

        field = FieldSLAM(cfg.field, np.asarray(bound, dtype=np.float64), K, height, width)
    if p.seeder == "odometry":
        from lrslam.frontend.odometry import Odometry

        sc = cfg.schedule
        arbitrate = field is not None and sc.seed_arbitration
        seeder = OdometrySeeder(Odometry(cfg.odometry, K, height, width),
                                (sc.seed_disagreement_m, sc.seed_disagreement_deg) if arbitrate else None)
    else:
        seeder = ConstantVelocitySeeder(cfg.schedule.velocity_model)
    refiner = FieldRefiner(field) if field is not None else NoRefiner()
    if p.keyframer == "policy":
        from lrslam.frontend.keyframes import KeyframePolicy

        keyframer = PolicyKeyframer(KeyframePolicy(cfg.keyframes))
    else:
        keyframer = EveryNKeyframer(cfg.schedule.keyframe_every)
    sc = cfg.schedule
    mapper = None if field is None else FieldMapper(field, sc.map_every, sc.background_mapping,
                                                    (sc.background_wait_m, sc.background_wait_deg))
    backend = None
    if p.backend == "graph":
        from lrslam.backend.graph import PoseGraph
        from lrslam.backend.keyframe_link import KeyframeLink
        from lrslam.backend.loop_closure import LoopCloser

        g = cfg.graph
        backend = GraphBackend(cfg.backend, PoseGraph(g), LoopCloser(cfg.loop_closure),
                               KeyframeLink(cfg.odometry.registration, cfg.odometry.gates),
                               diagonal_information(np.radians(g.field_sigma_rotation), g.field_sigma_translation),
                               field.pose_losses if field is not None else None)
    return Parts(seeder, refiner, keyframer, mapper, backend, field)
