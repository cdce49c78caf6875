"""Frame-to-frame (or frame-to-keyframe) RGB-D odometry with a constant-velocity prior and graceful failure.

Per frame (:meth:`Odometry.track`):

1. predict ``T_w_pred = T_w_last @ inv(T_w_prev) @ T_w_last`` (constant velocity);
2. register the frame to the reference frame from ``inv(T_w_ref) @ T_w_pred`` (:func:`register_rgbd`);
3. gate: registration gates (``gates``: fitness, inlier RMSE, correction) and the per-frame motion
   (bounded by the same ``gates.max_translation`` / ``gates.max_rotation``);
4. retry a failed registration (``retry``): from zero motion instead of the constant-velocity guess, then with
   the other registration method (``retry_method``) -- fast or jerky motion breaks the velocity guess first;
5. with ``model.enabled``, refine a slow frame against a TSDF model of the frames tracked so far
   (:mod:`lrslam.frontend.model_tracking`: bounds the drift of frame-to-frame registration) and integrate
   every registered frame into it;
6. on failure of every attempt (frame without depth, featureless frame, Open3D error, failed gate) keep the
   prediction, with weak information and the reason logged;
7. update the velocity and the reference (the previous frame in ``mode="frame"``; in ``mode="keyframe"`` the
   reference changes when the camera has moved far from it or the fitness drops).

A pass can be recorded (``record=True``: :meth:`Odometry.trace`) and replayed by another odometry with the same
config, camera and first pose (``replay=``): steps 1-6 are skipped for every frame whose images are the
recorded ones (in the recorded order), step 7 runs as usual, so the replaying odometry ends in the state it would
have reached by registering (the run's bound pre-pass and the fused run's frontend register the same frames).

The poses here are the **frontend's own estimate** (odometry alone, never corrected by the field or the graph):
the pipeline uses the per-frame motion ``T_prev_c`` as a seed and the chained estimate as an independent
measurement; it never writes poses back. Only the reference frame's images (and their cached preprocessing)
are kept.
"""

from __future__ import annotations

import logging
import zlib
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Literal

import numpy as np
from pydantic import Field

from lrslam.camera import check_intrinsics
from lrslam.config import StrictModel
from lrslam.errors import InputError
from lrslam.frontend.model_tracking import ModelTracker, ModelTrackingConfig
from lrslam.frontend.registration import (RegistrationConfig, RegistrationGates, fallback_information,
                                          frame_problem, register_rgbd)
from lrslam.frontend.rgbd_view import FrameLike, RGBDView, as_view
from lrslam.geometry import constant_velocity, inv, is_valid_pose, pose_error

__all__ = ["OdometryConfig", "OdometryResult", "OdometryStep", "OdometryTrace", "Odometry"]

log = logging.getLogger(__name__)


class OdometryConfig(StrictModel):
    """Frame-to-frame odometry: how each frame is registered (``registration``), when a registration is
    accepted (``gates``; its ``max_translation`` / ``max_rotation`` also bound the motion per frame), and how
    the reference and failures are handled. Distances in metres, angles in degrees."""

    mode: Literal["frame", "keyframe"] = Field(
        "frame", description="register each frame to the previous frame, or to the current reference keyframe")
    registration: RegistrationConfig = RegistrationConfig()
    gates: RegistrationGates = RegistrationGates()
    # Keyframe-mode reference switching, recovery after repeated failures.
    reference_max_translation: float = Field(0.3, gt=0)
    reference_max_rotation: float = Field(15.0, gt=0)
    reference_min_fitness: float = Field(0.6, ge=0, le=1)
    max_consecutive_failures: int = Field(3, ge=0)
    # Retries of a failed registration (zero-motion guess, then the other method).
    retry: bool = True
    retry_method: Literal["rgbd", "icp", "kiss", "none"] = "icp"
    # Frame-to-model refinement of slow frames (off: frame-to-frame / frame-to-keyframe only).
    model: ModelTrackingConfig = ModelTrackingConfig()


@dataclass(frozen=True)
class OdometryResult:
    """Odometry output for one frame.

    Attributes:
        frame_index: the frame's index.
        T_w_c: (4, 4) camera pose in the world (the constant-velocity prediction when not ok).
        T_ref_c: (4, 4) pose of the camera in the reference frame it was registered to (``inv(T_w_ref) @ T_w_c``).
        T_prev_c: (4, 4) motion since the previous tracked frame (``inv(T_w_prev) @ T_w_c``, this odometry's own
            estimates; identity for the first frame).
        ref_index: index of that reference frame (the frame itself for the first frame).
        information: (6, 6) information of ``T_ref_c`` (right perturbation ``T_ref_c exp(xi)``,
            ``xi = [rotation (rad), translation (m)]``, ready for ``BetweenFactor(ref, c)``); the weak
            :func:`~lrslam.frontend.registration.fallback_information` when not ok and for the first frame
            (nothing measured).
        ok: the registration succeeded and passed every gate.
        fitness: inlier fraction (0..1).
        inlier_rmse: metres (inf when unknown).
        reason: why not ok, or a note ("first frame"); "" otherwise.
        attempt: which attempt succeeded ("velocity", "zero-motion", "<method>"; "+model" appended when the
            frame-to-model refinement was kept) or "" when none did.
        trusted: ok and the registration trusted (:attr:`RegistrationResult.trusted`: a weak registration is
            the frontend's own estimate but no measurement for the fusion or the graph).
    """

    frame_index: int
    T_w_c: np.ndarray
    T_ref_c: np.ndarray
    ref_index: int
    information: np.ndarray
    ok: bool
    fitness: float
    inlier_rmse: float
    reason: str = ""
    T_prev_c: np.ndarray = dc_field(default_factory=lambda: np.eye(4))
    attempt: str = ""
    trusted: bool = True


@dataclass(frozen=True)
class OdometryStep:
    """One frame of a recorded pass: its ``result``, why it could not be registered (``problem``; None when it
    could, see :func:`~lrslam.frontend.registration.frame_problem`) and ``fingerprint`` (CRC-32 of its depth
    and colour bytes: a replay only uses the step for the same images)."""

    result: OdometryResult
    problem: str | None
    fingerprint: int


@dataclass(frozen=True)
class OdometryTrace:
    """A recorded pass (:meth:`Odometry.trace`): the ``config``, intrinsics ``K`` (3, 3) and first pose
    ``T_w_c0`` (4, 4) it ran with, and one step per tracked frame in order. Replayed only by an odometry with the
    same config, intrinsics and first pose."""

    config: OdometryConfig
    K: np.ndarray
    T_w_c0: np.ndarray
    steps: tuple[OdometryStep, ...]


def _fingerprint(view: RGBDView) -> int:
    return zlib.crc32(view.rgb, zlib.crc32(view.depth))


class Odometry:
    """Tracks a sequence of RGB-D frames from one camera (intrinsics ``K`` (3, 3), images ``height`` x ``width``).

    ``record``: keep every frame's result for :meth:`trace`. ``replay``: a trace of an earlier pass; from the
    next :meth:`reset` on, each frame that matches the trace's next step (same index and images, same config,
    intrinsics and first pose) takes the recorded result instead of being registered again; from the first
    frame that does not, every frame is registered (logged once)."""

    def __init__(self, cfg: OdometryConfig, K: np.ndarray, height: int, width: int, *, record: bool = False,
                 replay: OdometryTrace | None = None):
        try:
            self.K = check_intrinsics(K, width, height)
        except ValueError as e:
            raise InputError(f"odometry: {e}") from None
        self.cfg = cfg
        self.height, self.width = int(height), int(width)
        self._record = record
        self._replay: OdometryTrace | None = None
        self.reset()
        self._replay = replay   # applies from the next reset (the one that gives the first pose)

    # -- state -----------------------------------------------------------------------------------------------
    def reset(self, T_w_c0: np.ndarray | None = None, frame: FrameLike | None = None) -> OdometryResult | None:
        """Forget every frame; the next tracked frame gets pose ``T_w_c0`` (4x4, default identity). With
        ``frame``, that first frame is tracked now (it becomes the reference when usable) and its result is
        returned."""
        T0 = np.eye(4) if T_w_c0 is None else np.asarray(T_w_c0, dtype=np.float64)
        if not is_valid_pose(T0):
            raise InputError("odometry: initial pose must be a finite 4x4 rigid transform")
        self._T_w_c0 = T0
        self._ref: RGBDView | None = None
        self._ref_index: int | None = None
        self._T_w_ref = T0.copy()
        self._last_index: int | None = None
        self._last_view: RGBDView | None = None  # the last frame's images when usable (use_last_as_reference)
        self._T_w_last = T0.copy()
        self._T_w_prev = T0.copy()  # pose before the last one: velocity = inv(prev) @ last
        self._failures = 0
        self._model = (ModelTracker(self.cfg.model, self.K, self.height, self.width) if self.cfg.model.enabled
                       else None)
        self._steps: list[OdometryStep] = []
        r = self._replay
        self._replay_at = 0 if (r is not None and r.config == self.cfg and np.array_equal(r.K, self.K)
                                and np.array_equal(r.T_w_c0, T0)) else None
        if r is not None:
            log.info("odometry: %s", f"replaying a recorded {len(r.steps)}-frame pass where the frames match"
                     if self._replay_at is not None else "the recorded pass ran with another config, camera or "
                     "first pose; every frame is registered")
        self.replayed = 0
        return self.track(frame) if frame is not None else None

    def trace(self) -> OdometryTrace:
        """The frames tracked since the last :meth:`reset`, for another odometry to replay (needs ``record``)."""
        if not self._record:
            raise RuntimeError("Odometry.trace: built without record=True")
        return OdometryTrace(self.cfg, self.K.copy(), self._T_w_c0.copy(), tuple(self._steps))

    def _recorded(self, index: int, view: RGBDView) -> OdometryStep | None:
        """The replayed trace's step for this frame, or None (then no later frame is replayed either)."""
        if self._replay_at is None:
            return None
        steps = self._replay.steps
        at = self._replay_at
        if at < len(steps) and steps[at].result.frame_index == index and steps[at].fingerprint == _fingerprint(view):
            self._replay_at += 1
            self.replayed += 1
            return steps[at]
        log.info("odometry: frame %d is not the recorded pass's next frame; registering from here on", index)
        self._replay_at = None
        return None

    @property
    def reference_index(self) -> int | None:
        """Index of the current reference frame (None before the first valid frame)."""
        return self._ref_index

    @property
    def last_pose(self) -> np.ndarray:
        """``T_w_c`` of the last tracked frame (or the initial pose)."""
        return self._T_w_last.copy()

    def predict(self) -> np.ndarray:
        """Constant-velocity prediction of the next frame's ``T_w_c``."""
        return constant_velocity(self._T_w_prev, self._T_w_last)

    def use_last_as_reference(self) -> bool:
        """Make the last tracked frame the reference (e.g. when the keyframe policy picks it in
        ``mode="keyframe"``). False (and a log line) when that frame was unusable (no depth, featureless)."""
        if self._last_view is None or self._last_index is None:
            log.info("odometry: last frame %s cannot be a reference", self._last_index)
            return False
        self._set_reference(self._last_index, self._last_view, self._T_w_last)
        return True

    def state_dict(self) -> dict:
        """Everything :meth:`track` depends on (reference and last frame images, poses, failure count) as plain
        numpy / Python data, for checkpoints; restore with :meth:`load_state_dict`."""
        last = None if self._last_view is None else ("ref" if self._last_view is self._ref else self._last_view.state())
        return {"T_w_c0": self._T_w_c0.copy(), "ref": None if self._ref is None else self._ref.state(),
                "ref_index": self._ref_index, "T_w_ref": self._T_w_ref.copy(), "last_index": self._last_index,
                "last_view": last, "T_w_last": self._T_w_last.copy(), "T_w_prev": self._T_w_prev.copy(),
                "failures": self._failures, "model": None if self._model is None else self._model.state()}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output (into an odometry built with the same config and camera)."""
        self._T_w_c0 = np.asarray(state["T_w_c0"], dtype=np.float64)
        self._ref = None if state["ref"] is None else RGBDView.from_state(state["ref"])
        self._ref_index = state["ref_index"]
        self._T_w_ref = np.asarray(state["T_w_ref"], dtype=np.float64)
        self._last_index = state["last_index"]
        last = state["last_view"]
        self._last_view = self._ref if isinstance(last, str) else None if last is None else RGBDView.from_state(last)
        self._T_w_last = np.asarray(state["T_w_last"], dtype=np.float64)
        self._T_w_prev = np.asarray(state["T_w_prev"], dtype=np.float64)
        self._failures = int(state["failures"])
        if self._model is not None and state.get("model") is not None:
            self._model.load_state(state["model"])

    # -- tracking --------------------------------------------------------------------------------------------
    def track(self, frame: FrameLike) -> OdometryResult:
        """Estimate the pose of ``frame`` (needs ``index``, ``rgb``, ``depth``, ``K``; see module docstring)."""
        index = int(frame.index)
        view = self._view(frame)
        step = self._recorded(index, view)
        if step is not None:
            result, problem = step.result, step.problem
        else:
            problem = frame_problem(view, self.cfg.registration, self.cfg.gates)
            result = self._first(index, view, problem) if self._last_index is None else \
                self._register(index, view, problem)
        if self._record:
            self._steps.append(OdometryStep(result, problem, _fingerprint(view)))
        # 7. Update velocity and reference.
        if self._last_index is None:
            self._start(index, view, problem)
            return result
        if self._model is not None and result.ok and problem is None:
            self._model.integrate(view.rgb, view.depth, result.T_w_c)
        self._T_w_prev, self._T_w_last, self._last_index = self._T_w_last, result.T_w_c, index
        self._last_view = view if problem is None else None
        self._update_reference(index, view, problem, result)
        return result

    def _register(self, index: int, view: RGBDView, problem: str | None) -> OdometryResult:
        """Steps 1-6 for a frame after the first: its result (the state is not changed)."""
        gates = self.cfg.gates

        # 1. Constant-velocity prediction.
        T_w_pred = self.predict()
        reg, reason, attempt, T_w_c = None, problem or "no reference frame yet", "", T_w_pred
        if self._ref is not None:
            # 2-4. Register to the reference (and retry), gate the per-frame motion.
            for name, T_w_init, registration in self._attempts(T_w_pred):
                reg = register_rgbd(view, self._ref, inv(self._T_w_ref) @ T_w_init, registration, gates)
                reason = reg.reason
                if reg.ok:
                    T_cand = self._T_w_ref @ reg.T_tgt_src
                    d_t, d_r = pose_error(self._T_w_last, T_cand)
                    if d_t > gates.max_translation or d_r > gates.max_rotation:
                        reason = f"motion since the last frame too large ({d_t:.3f} m, {d_r:.1f} deg)"
                    else:
                        T_w_c, attempt = T_cand, name
                        break
                log.debug("frame %d: odometry attempt %s failed (%s)", index, name, reason)
        ok = attempt != ""
        if ok:
            reason = ""
            T_w_c, attempt = self._refine_with_model(index, view, T_w_c, attempt)
        ref_index = self._ref_index if self._ref_index is not None else index
        T_ref_c = inv(self._T_w_ref) @ T_w_c if self._ref is not None else np.eye(4)
        if ok:
            info = reg.information
        else:
            # 6. Fallback to the prediction.
            info = fallback_information(gates)
            log.info("frame %d: odometry failed (%s); using the constant-velocity prediction", index, reason)
        return OdometryResult(index, T_w_c, T_ref_c, ref_index, info, ok,
                              reg.fitness if reg is not None else 0.0,
                              reg.inlier_rmse if reg is not None else float("inf"), reason,
                              inv(self._T_w_last) @ T_w_c, attempt, ok and reg.trusted)

    def _refine_with_model(self, index: int, view: RGBDView, T_w_c: np.ndarray, attempt: str) -> tuple[np.ndarray, str]:
        """5. Frame-to-model refinement of a registered slow frame (kept only when small and well supported):
        ``(T_w_c, attempt)``, with "+model" appended when kept."""
        if self._model is None or not self._model.wants(inv(self._T_w_last) @ T_w_c):
            return T_w_c, attempt
        T_refined, why = self._model.refine(view.rgb, view.depth, T_w_c)
        if T_refined is None:
            log.debug("frame %d: %s; the frame-to-frame pose stands", index, why)
            return T_w_c, attempt
        return T_refined, attempt + "+model"

    def _attempts(self, T_w_pred: np.ndarray):
        """(name, initial world pose, registration config) to try in order (all under the same gates)."""
        registration, retry_method = self.cfg.registration, self.cfg.retry_method
        yield "velocity", T_w_pred, registration
        if not self.cfg.retry:
            return
        yield "zero-motion", self._T_w_last, registration
        if retry_method not in ("none", registration.method):
            yield retry_method, T_w_pred, registration.model_copy(update={"method": retry_method})

    def _first(self, index: int, view: RGBDView, problem: str | None) -> OdometryResult:
        """The first frame's result: the first pose, ok when the frame is usable."""
        if problem is None:
            reason, ok = "first frame", True
        else:
            reason, ok = f"first frame: {problem}", False
            log.info("frame %d: %s", index, reason)
        return OdometryResult(index, self._T_w_c0.copy(), np.eye(4), index, fallback_information(self.cfg.gates), ok,
                              1.0 if ok else 0.0, 0.0 if ok else float("inf"), reason)

    def _start(self, index: int, view: RGBDView, problem: str | None) -> None:
        """Step 7 for the first frame: it becomes the reference (and enters the model) when usable."""
        self._last_index = index
        self._last_view = view if problem is None else None
        if problem is None:
            self._set_reference(index, view, self._T_w_c0)
            if self._model is not None:
                self._model.integrate(view.rgb, view.depth, self._T_w_c0)

    def _update_reference(self, index: int, view: RGBDView, problem: str | None, res: OdometryResult) -> None:
        if problem is not None:
            return  # never keep an unusable frame as reference
        if self._ref is None:
            self._set_reference(index, view, res.T_w_c)
            return
        if not res.ok:
            self._failures += 1
            if self._failures > self.cfg.max_consecutive_failures:
                log.warning("frame %d: %d consecutive odometry failures; re-anchoring the reference at the "
                            "predicted pose", index, self._failures)
                self._set_reference(index, view, res.T_w_c)
            return
        self._failures = 0
        if self.cfg.mode == "frame":
            self._set_reference(index, view, res.T_w_c)
            return
        d_t, d_r = pose_error(self._T_w_ref, res.T_w_c)
        if (d_t > self.cfg.reference_max_translation or d_r > self.cfg.reference_max_rotation
                or res.fitness < self.cfg.reference_min_fitness):
            self._set_reference(index, view, res.T_w_c)

    def _set_reference(self, index: int, view: RGBDView, T_w_c: np.ndarray) -> None:
        self._ref, self._ref_index, self._T_w_ref = view, index, np.asarray(T_w_c, dtype=np.float64).copy()
        self._failures = 0

    def _view(self, frame: FrameLike) -> RGBDView:
        try:
            view = as_view(frame)
        except ValueError as e:
            raise InputError(f"odometry: frame {getattr(frame, 'index', '?')}: {e}") from None
        if view.depth.shape != (self.height, self.width):
            raise InputError(f"odometry: frame {getattr(frame, 'index', '?')} is {view.width}x{view.height}, "
                             f"expected {self.width}x{self.height}")
        if not np.allclose(view.K, self.K):
            raise InputError(f"odometry: frame {getattr(frame, 'index', '?')} has different intrinsics")
        # Keep only the images (a Frame also carries ground truth and other data the odometry must not hold).
        return RGBDView(view.rgb, view.depth, view.K)
