"""The contracts between the SLAM loop and its parts: the messages they pass and what each part offers.

The runner (:class:`lrslam.pipeline.runner.SlamRunner`) talks to its parts through these protocols only; the
implementations live in :mod:`lrslam.pipeline.parts` (seeders, refiner, keyframers, mapper) and
:mod:`lrslam.backend.policy` (the graph backend). Every pose is ``T_w_c``, (4, 4) float64 numpy; the parts keep
no pose copies: they receive what they need from the runner's :class:`~lrslam.pipeline.trajectory.Trajectory`.

One frame (numbered as in the runner):

1. ``Seeder.seed(frame, traj) -> Seed``           the frame's starting pose (+ the frontend's measurement)
2. ``Refiner.refine(frame, seed) -> Refinement``  the field's refinement of it, with its information;
   ``Fusion.fuse(...) -> FusedPose``               the two weighed by their measured noise (fused mode)
3. ``Keyframer.is_keyframe(frame, T, traj)``       keyframe or not
4. ``Mapper.map(...) -> {frame id: T_w_c}``        the field's mapping round (poses it refined)
5. ``Backend.on_keyframe(...) -> Correction``      graph factors, loops, a solve: poses to write, keyframes to re-map
6. ``Mapper.remap(poses, ids)``                    the field re-optimised at the corrected poses
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field as dc_field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from lrslam.frame import Frame
from lrslam.backend.calibration import GapNoise
from lrslam.backend.frame_fusion import FusedPose
from lrslam.backend.policy import Correction, FactorRecord

if TYPE_CHECKING:  # annotations only
    from lrslam.frontend.odometry import OdometryResult
    from lrslam.pipeline.trajectory import Trajectory

__all__ = ["Seed", "Refinement", "Correction", "Stateful", "Seeder", "Refiner", "Keyframer", "Mapper", "Backend"]


# ---------------------------------------------------------------------------------------------------- messages
@dataclass(frozen=True)
class Seed:
    """A frame's starting pose ``T_w_c`` (4, 4); ``ok`` False when the seeder fell back to a guess;
    ``odometry``: the frontend's measurement of the frame (None without a frontend); ``alternatives``: other
    starting poses (4, 4) worth comparing with ``T_w_c`` by the field (a refiner picks the one it fits best)."""

    T_w_c: np.ndarray
    ok: bool = True
    odometry: OdometryResult | None = None
    note: str = ""
    alternatives: tuple[np.ndarray, ...] = ()

    def candidate(self, k: int) -> np.ndarray:
        """Starting pose ``k`` (4, 4): 0 the seed's ``T_w_c``, k > 0 ``alternatives[k - 1]``."""
        return self.T_w_c if k == 0 else self.alternatives[k - 1]

    @property
    def weak(self) -> bool:
        """The odometry registered the frame below ``gates.trusted_fitness``, or failed (no frontend: False)."""
        return self.odometry is not None and not self.odometry.trusted

    @property
    def uncertain(self) -> bool:
        """The odometry registered the frame weakly (or failed), or disagrees with another starting pose (the
        seeder's arbitration offers ``alternatives``): a refinement from it should not stop early."""
        return self.weak or bool(self.alternatives)


@dataclass(frozen=True)
class Refinement:
    """The refined pose ``T_w_c`` (4, 4) (the starting pose when not ``ok`` or not ``accepted``);
    ``information`` (6, 6) of it given the field (right perturbation, ``[rotation, translation]``; None without
    one); ``ok`` False when tracking failed; ``iters`` tracking iterations run; ``start``: which candidate the
    refinement started from (0 = the seed's ``T_w_c``, k = its ``alternatives[k - 1]``)."""

    T_w_c: np.ndarray
    ok: bool
    accepted: bool = False
    information: np.ndarray | None = None
    note: str = ""
    iters: int = 0
    start: int = 0


# ---------------------------------------------------------------------------------------------------- parts
class Stateful(Protocol):
    """Everything a checkpoint needs to continue the part, as plain Python / numpy data."""

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...


class Seeder(Stateful, Protocol):
    """Where a frame's pose starts."""

    def start(self, frame: Frame, T_w_c0: np.ndarray) -> None:
        """First frame at ``T_w_c0``."""

    def seed(self, frame: Frame, traj: Trajectory) -> Seed:
        """The next frame's starting pose, given the trajectory so far."""

    def frontend_pose(self) -> np.ndarray | None:
        """The frontend's own ``T_w_c`` of the last frame (its odometry alone); None without a frontend."""


class Refiner(Protocol):
    """Refines a seed against the map."""

    def refine(self, frame: Frame, seed: Seed) -> Refinement: ...


class Keyframer(Stateful, Protocol):
    """Decides which frames become keyframes."""

    def start(self, frame: Frame) -> None: ...

    def is_keyframe(self, frame: Frame, T_w_c: np.ndarray, traj: Trajectory) -> bool: ...


class Mapper(Stateful, Protocol):
    """Owns the field: builds it from the first frame, maps keyframes, re-maps after corrections, meshes it.

    With background mapping a round runs beside the tracking of the next frames; :meth:`collect` is the one
    synchronisation point (it waits for the running round and returns its poses)."""

    reverted_poses: int
    device: str

    def start(self, frame: Frame, T_w_c0: np.ndarray, progress: Callable[[int, int], None] | None = None) -> None: ...

    def must_wait(self, traj: Trajectory) -> bool:
        """The next frame should be tracked on the mapped field (call :meth:`collect` first)."""

    def due(self, frame: Frame, is_keyframe: bool, seed_uncertain: bool = False) -> bool:
        """A mapping round is due at this frame (``seed_uncertain``: its seed was :attr:`Seed.uncertain`)."""

    def map(self, frame: Frame, T_w_c: np.ndarray, keyframe_poses: dict[int, np.ndarray],
            add_keyframe: bool) -> dict[int, np.ndarray]: ...

    def collect(self) -> dict[int, np.ndarray]: ...

    def stop(self) -> None: ...

    def remap(self, keyframe_poses: dict[int, np.ndarray], ids: list[int]) -> None: ...

    def mesh(self, keyframe_poses: dict[int, np.ndarray], resolution: float | None): ...

    def parameter_count(self) -> dict[str, int]: ...


class Fusion(Stateful, Protocol):
    """Per-frame fusion of the odometry's seed and the field's pose (:class:`lrslam.backend.frame_fusion.FrameFusion`)."""

    def fuse(self, T_seed: np.ndarray, odometry_ok: bool, T_field: np.ndarray | None,
             T_frontend: np.ndarray | None, trusted: bool = True) -> FusedPose: ...

    def start(self, T_w_c0: np.ndarray, T_frontend0: np.ndarray | None) -> None: ...

    def blend(self, T_current: np.ndarray, T_field: np.ndarray) -> np.ndarray:
        """A pose the field's mapper moved, moved by the field's share only."""

    def on_keyframe(self, T_registration: np.ndarray | None) -> None:
        """The last fused frame became a keyframe (``T_registration``: the frontend's direct registration of it to
        the previous keyframe, :attr:`Correction.link`)."""

    def sigmas(self) -> dict[str, float]: ...

    def gap_noise(self) -> GapNoise:
        """The measured noise over a keyframe gap (the graph factors' calibration)."""

    def field_pose(self) -> np.ndarray | None:
        """The field's own tracked pose of the last fused frame (None when it failed)."""


class Backend(Stateful, Protocol):
    """The keyframe pose graph and its policy (:class:`lrslam.backend.policy.GraphBackend`)."""

    n_loops: int
    n_solves: int
    n_loops_disputed: int
    measurements: list[FactorRecord]   # every between factor as it was added (calibration checks)

    def start(self, frame: Frame, T_w_c0: np.ndarray) -> None: ...

    def on_frame(self, odometry: OdometryResult | None) -> None:
        """Every frame's frontend measurement (None without one)."""

    def on_keyframe(self, frame: Frame, poses: dict[int, np.ndarray], information: np.ndarray | None,
                    noise: GapNoise | None = None, T_field: np.ndarray | None = None) -> Correction:
        """A new keyframe ``frame.index`` (every keyframe's current pose in ``poses``), the field's information of
        its pose (None without one), the run's measured noise and the field's own pose of it (None without a
        fusion)."""

    def refine_all(self, poses: dict[int, np.ndarray], noise: GapNoise | None = None) -> Correction:
        """The final global refinement over every keyframe ``poses``."""

    def calibrated_measurements(self) -> list[FactorRecord]:
        """Every measurement with the information the graph weighs it by."""

    @property
    def loop_counts(self) -> dict[str, int]:
        """Loops proposed / unverified / disputed / inconsistent / kept."""
