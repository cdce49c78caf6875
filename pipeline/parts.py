"""The parts a SLAM run is built from, and the factory that builds them from config.

- seeder: where a frame's pose starts -- :class:`ConstantVelocitySeeder` (ESLAM) or :class:`OdometrySeeder`
  (the frontend's frame-to-frame motion applied to the last pose);
- refiner: :class:`FieldRefiner` (LRSLAM tracking by rendering loss) or none;
- keyframer: :class:`EveryNKeyframer` (ESLAM) or :class:`PolicyKeyframer` (motion / overlap);
- mapper: :class:`FieldMapper` (the field's owner: joint field + window-pose optimisation, re-maps), with the field;
- backend: :class:`lrslam.backend.policy.GraphBackend` (pose graph with frontend, field and loop factors) or none.

Each part implements its protocol in :mod:`lrslam.pipeline.contracts`. ``field``, ``frontend`` and ``fused`` are
presets of this factory (:data:`lrslam.pipeline.config.MODE_PRESETS`). Parts keep no pose copies: they receive
the poses they need from the runner's :class:`Trajectory`.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from lrslam.frame import Frame
from lrslam.geometry import constant_velocity, diagonal_information, pose_error, pose_from_tum, pose_to_tum
from lrslam.pipeline.config import RunConfig
from lrslam.pipeline.contracts import Backend, Fusion, Keyframer, Mapper, Refinement, Refiner, Seed, Seeder
from lrslam.pipeline.trajectory import Trajectory

if TYPE_CHECKING:  # annotations only: torch, GTSAM and Open3D load when a part that needs them is built
    from lrslam.backend.policy import GraphBackend
    from lrslam.field.slam import FieldSLAM
    from lrslam.frontend.keyframes import KeyframePolicy
    from lrslam.frontend.odometry import Odometry, OdometryTrace

__all__ = ["ConstantVelocitySeeder", "OdometrySeeder", "FieldRefiner", "EveryNKeyframer", "PolicyKeyframer",
           "FieldMapper", "Parts", "build_parts"]

log = logging.getLogger(__name__)


def _constant_velocity(traj: Trajectory) -> np.ndarray:
    """The last motion repeated on SE(3): ``T_{i-1} inv(T_{i-2}) T_{i-1}``."""
    if len(traj) < 2:
        return traj.pose(-1)
    return constant_velocity(traj.pose(-2), traj.pose(-1))


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

    def frontend_pose(self) -> None:
        """No frontend."""
        return None


class OdometrySeeder:
    """The frontend's frame-to-frame motion (:class:`lrslam.frontend.odometry.Odometry`, its own estimate)
    applied to the trajectory's last pose; constant velocity when the odometry failed.

    ``disagreement``: (metres, degrees), or None. When given and the odometry's seed and the constant-velocity
    guess differ by more than either, the guess goes along as an alternative for the refiner to judge (a
    registration that passed its gates can still be wrong by centimetres at large motion)."""

    def __init__(self, odometry: Odometry, disagreement: tuple[float, float] | None = None) -> None:
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
class FieldRefiner:
    """LRSLAM tracking against the frozen field from the seed (``field.tracking.accept_if_better`` keeps the
    seed unless the refinement lowers the loss on the same rays). ``uncertain_seed_effort``: an uncertain seed
    (:attr:`Seed.uncertain`) is tracked with every iteration (``schedule.uncertain_seed_effort``)."""

    def __init__(self, field: FieldSLAM, uncertain_seed_effort: bool = False) -> None:
        self.field = field   # owned by the FieldMapper; the refiner only tracks against it
        self.uncertain_seed_effort = uncertain_seed_effort

    def refine(self, frame: Frame, seed: Seed) -> Refinement:
        start, note = self._start(frame, seed)
        T0 = seed.candidate(start)
        full = self.uncertain_seed_effort and seed.uncertain
        res = self.field.track(frame.rgb, frame.depth, T0, early_stop=not full)
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

    def __init__(self, policy: KeyframePolicy) -> None:
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
    """The field's owner: builds it from the first frame, maps keyframes and every ``map_every`` frames, re-maps
    after corrections, meshes it, and holds its state for checkpoints.

    ``background``: each round runs in a worker thread beside the tracking of the next frames
    (:meth:`lrslam.field.slam.FieldSLAM.map_in_background`); :meth:`map` then returns the previous round's poses
    and :meth:`collect` the current one's."""

    def __init__(self, field: FieldSLAM, map_every: int, background: bool = False,
                 wait_motion: tuple[float, float] = (np.inf, np.inf), map_uncertain_seeds: bool = False) -> None:
        self.field = field
        self.map_every = map_every
        self.map_uncertain_seeds = map_uncertain_seeds
        self.background = background
        self.wait_motion = wait_motion

    @property
    def reverted_poses(self) -> int:
        """Mapping poses reverted to their starting value (the round made them worse)."""
        return self.field.reverted_poses

    @property
    def device(self) -> str:
        return str(self.field.device)

    def parameter_count(self) -> dict[str, int]:
        return self.field.parameter_count()

    def state_dict(self) -> dict:
        return self.field.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.field.load_state_dict(state)

    def must_wait(self, traj: Trajectory) -> bool:
        """Background only: the last frame-to-frame motion exceeded ``wait_motion`` (metres, degrees), so the next
        frame should be tracked on the mapped field (:meth:`collect` first)."""
        if not self.background:
            return False
        d_t, d_r = traj.last_motion()
        return d_t > self.wait_motion[0] or d_r > self.wait_motion[1]

    def start(self, frame: Frame, T_w_c0: np.ndarray, progress: Callable[[int, int], None] | None = None) -> None:
        self.field.initialise(frame.index, frame.rgb, frame.depth, T_w_c0, progress)
        if self.background:
            self.field.start_background_mapping()

    def due(self, frame: Frame, is_keyframe: bool, seed_uncertain: bool = False) -> bool:
        return is_keyframe or frame.index % self.map_every == 0 or (self.map_uncertain_seeds and seed_uncertain)

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

    def remap(self, keyframe_poses: dict, ids: list[int]) -> None:
        self.field.remap(keyframe_poses, ids)

    def mesh(self, keyframe_poses: dict, resolution: float | None):
        return self.field.extract_mesh(keyframe_poses, resolution)

    def render(self, T_w_c: np.ndarray, scale: int = 4,
               depth: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Depth (h, w) metres and colour (h, w, 3) in [0, 1] of the field at ``T_w_c``, at the pixels of
        ``image[::scale, ::scale]`` (:meth:`lrslam.field.slam.FieldSLAM.render`)."""
        return self.field.render(T_w_c, scale, depth)


# -------------------------------------------------------------------------------------------------- factory
@dataclass
class Parts:
    """The parts of one run; ``refiner``, ``mapper`` and ``backend`` are None when the run has none (a refiner
    and a mapper come together: both work on the one field, which the mapper owns)."""

    seeder: Seeder
    keyframer: Keyframer
    refiner: Refiner | None = None
    mapper: Mapper | None = None
    backend: Backend | None = None
    fusion: Fusion | None = None


def build_parts(cfg: RunConfig, K: np.ndarray, height: int, width: int, bound: np.ndarray,
                odometry_trace: OdometryTrace | None = None) -> Parts:
    """Build the configured parts (``cfg.parts``); each gets its own config section only. The combinations
    were checked when ``cfg`` was built (:meth:`lrslam.pipeline.config.RunConfig._check_parts`).
    ``odometry_trace``: an earlier pass over the same frames that the odometry seeder replays where it matches."""
    p, sc = cfg.parts, cfg.schedule
    field = None
    if p.refiner == "field":
        from lrslam.field.slam import FieldSLAM

        field = FieldSLAM(cfg.field, np.asarray(bound, dtype=np.float64), K, height, width)
    return Parts(_seeder(cfg, K, height, width, field is not None, odometry_trace), _keyframer(cfg),
                 FieldRefiner(field, sc.uncertain_seed_effort) if field is not None else None,
                 None if field is None else FieldMapper(field, sc.map_every, sc.background_mapping,
                                                        (sc.background_wait_m, sc.background_wait_deg),
                                                        sc.uncertain_seed_effort),
                 _backend(cfg, field) if p.backend == "graph" else None,
                 _fusion(cfg) if field is not None and p.seeder == "odometry" and cfg.fusion.per_frame else None)


def _fusion(cfg: RunConfig) -> Fusion:
    from lrslam.backend.frame_fusion import FrameFusion

    return FrameFusion(cfg.fusion)


def _seeder(cfg: RunConfig, K: np.ndarray, height: int, width: int, with_field: bool,
            odometry_trace: OdometryTrace | None) -> Seeder:
    sc = cfg.schedule
    if cfg.parts.seeder == "constant_velocity":
        return ConstantVelocitySeeder(sc.velocity_model)
    from lrslam.frontend.odometry import Odometry, OdometryTrace

    arbitrate = with_field and sc.seed_arbitration
    return OdometrySeeder(Odometry(cfg.odometry, K, height, width, replay=odometry_trace),
                          (sc.seed_disagreement_m, sc.seed_disagreement_deg) if arbitrate else None)


def _keyframer(cfg: RunConfig) -> Keyframer:
    if cfg.parts.keyframer == "policy":
        from lrslam.frontend.keyframes import KeyframePolicy

        return PolicyKeyframer(KeyframePolicy(cfg.keyframes))
    return EveryNKeyframer(cfg.keyframes.every_n)


def _backend(cfg: RunConfig, field: FieldSLAM | None) -> GraphBackend:
    from lrslam.backend.graph import PoseGraph
    from lrslam.backend.keyframe_link import KeyframeLink
    from lrslam.backend.loop_closure import LoopCloser
    from lrslam.backend.policy import GraphBackend

    g = cfg.graph
    return GraphBackend(cfg.backend, PoseGraph(g), LoopCloser(cfg.loop_closure),
                        KeyframeLink(cfg.odometry.registration, cfg.odometry.gates, cfg.backend.odometry_factor),
                        diagonal_information(np.radians(g.field_sigma_rotation), g.field_sigma_translation),
                        field.pose_losses if field is not None else None)
