"""Loop closure over keyframes: propose earlier keyframes near the current one, verify by registration.

:meth:`LoopCloser.detect` runs, for a new keyframe j:

1. candidates: earlier keyframes i (not among the last ``exclude_last`` added) whose camera centre lies within
   ``max_distance`` and optical axis within ``max_angle`` of j's, and whose view overlap with j
   (:func:`~lrslam.frontend.keyframes.view_overlap`, current estimates) is at least ``min_overlap``;
2. optional appearance check (OpenCV ORB matches);
3. verification: :func:`~lrslam.frontend.registration.register_rgbd` of j to i from the predicted relative pose,
   then strict fitness / RMSE / correction gates.

Every rejection is logged with its reason (and kept in :attr:`LoopCloser.rejections` for the last call).
Keyframes are stored as down-sampled copies (images only); their poses are handed in at each call (the
pipeline's trajectory owns them). Each verified loop carries its *correction*: how far the registration moved
the relative pose the current estimates predicted, so a caller can tell a real correction from a consistent
re-observation (a rotating camera re-observes earlier keyframes all the time).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any

import numpy as np
from pydantic import Field, ValidationInfo, field_validator

from lrslam.config import StrictModel
from lrslam.errors import InputError
from lrslam.frontend.keyframes import view_overlap
from lrslam.frontend.registration import RegistrationConfig, RegistrationGates, RegistrationResult, register_rgbd
from lrslam.frontend.rgbd_view import FrameLike, RGBDView, as_view
from lrslam.geometry import checked_pose, inv, pose_error

__all__ = ["LoopClosureConfig", "LoopConstraint", "LoopCloser"]

log = logging.getLogger(__name__)


class LoopClosureConfig(StrictModel):
    """Loop candidate selection and verification. Distances in metres, angles in degrees."""

    exclude_last: int = Field(5, ge=1, description="the most recent keyframes are never loop candidates")
    max_distance: float = Field(1.0, gt=0, description="camera centre distance of a candidate")
    max_angle: float = Field(45.0, gt=0, description="angle between optical axes of a candidate")
    min_overlap: float = Field(0.3, ge=0, le=1, description="view overlap of the new keyframe into the candidate")
    max_candidates: int = Field(3, ge=1, description="candidates verified per call, best overlap first")
    downsample: int = Field(2, ge=1, description="keyframes are stored this many times smaller per side")
    use_orb: bool = False
    min_orb_matches: int = Field(30, ge=1)
    # Strict gates applied after the registration's own (``gates``).
    min_fitness: float = Field(0.5, ge=0, le=1)
    max_inlier_rmse: float = Field(0.015, gt=0)
    registration: RegistrationConfig = Field(RegistrationConfig(method="rgbd", iterations=(30, 20, 10)),
                                             description="registration used for verification")
    gates: RegistrationGates = Field(RegistrationGates(max_translation=0.5, max_rotation=30.0),
                                     description="the verification registration's own gates; max_translation / "
                                     "max_rotation bound the drift a loop may correct")

    @field_validator("registration", "gates", mode="before")
    @classmethod
    def _over_loop_defaults(cls, value: Any, info: ValidationInfo) -> Any:
        """A partial section (a YAML file, ``--set loop_closure.gates.max_rotation=25``) overrides the loop's
        own defaults above, not the generic ones."""
        if isinstance(value, dict):
            return cls.model_fields[info.field_name].default.model_dump() | value
        return value

    def rejection(self, res: RegistrationResult) -> str | None:
        """Why the verification registration ``res`` does not make a loop (its own gates, then the strict
        ``min_fitness`` / ``max_inlier_rmse``); None when it does."""
        if not res.ok:
            return res.reason
        if res.fitness < self.min_fitness:
            return f"fitness {res.fitness:.3f} < {self.min_fitness}"
        if res.inlier_rmse > self.max_inlier_rmse:
            return f"inlier RMSE {res.inlier_rmse:.4f} m > {self.max_inlier_rmse}"
        return None


@dataclass(frozen=True)
class LoopConstraint:
    """A verified loop: ``T_i_j`` (4x4) is keyframe j's camera pose in keyframe i's camera (i earlier), with
    ``information`` (6x6, right perturbation of ``T_i_j``, ``[rotation, translation]``), projective
    ``fitness`` (0..1) and ``rmse`` (m)."""

    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray
    fitness: float
    rmse: float
    correction_m: float = 0.0
    correction_deg: float = 0.0


@dataclass
class _StoredKeyframe:
    view: RGBDView
    orb: np.ndarray | None


class LoopCloser:
    """Keeps down-sampled keyframes and finds verified loops between a new keyframe and earlier ones."""

    def __init__(self, cfg: LoopClosureConfig):
        self.cfg = cfg
        self._kfs: dict[int, _StoredKeyframe] = {}
        self._order: list[int] = []
        self.rejections: list[tuple[int, str]] = []

    def __len__(self) -> int:
        return len(self._kfs)

    def add_keyframe(self, kf_id: int, frame: FrameLike | RGBDView) -> None:
        """Store keyframe ``kf_id``'s images (down-sampled by ``cfg.downsample``)."""
        if kf_id in self._kfs:
            raise InputError(f"loop closure: keyframe {kf_id} added twice")
        view = self._view(frame)
        self._kfs[kf_id] = _StoredKeyframe(view, self._orb(view))
        self._order.append(kf_id)

    def state_dict(self) -> dict:
        """The stored (down-sampled) keyframes with their ORB descriptors, in order, for checkpoints."""
        return {"keyframes": [{"id": k, "view": self._kfs[k].view.state(), "orb": self._kfs[k].orb}
                              for k in self._order]}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output."""
        self._kfs = {int(s["id"]): _StoredKeyframe(RGBDView.from_state(s["view"]), s["orb"])
                     for s in state["keyframes"]}
        self._order = [int(s["id"]) for s in state["keyframes"]]
        self.rejections = []

    def candidates(self, kf_id: int, frame: FrameLike | RGBDView,
                   keyframe_poses: dict[int, np.ndarray]) -> list[tuple[int, float]]:
        """Earlier keyframes passing the pose-proximity and overlap tests: ``[(id, overlap)]``, best first.
        ``keyframe_poses``: current ``T_w_c`` by keyframe id, ``kf_id`` included."""
        return self._candidates(kf_id, self._view(frame), self._poses(keyframe_poses, kf_id))

    def _poses(self, keyframe_poses: dict[int, np.ndarray], kf_id: int) -> dict[int, np.ndarray]:
        if kf_id not in keyframe_poses:
            raise InputError(f"loop closure: no pose given for keyframe {kf_id}")
        return {k: self._pose(T, k) for k, T in keyframe_poses.items() if k in self._kfs or k == kf_id}

    def _candidates(self, kf_id: int, view: RGBDView, poses: dict[int, np.ndarray]) -> list[tuple[int, float]]:
        c = self.cfg
        T = poses[kf_id]
        recent = set(self._order[-c.exclude_last:]) | {kf_id}
        found = []
        for i in self._order:
            if i in recent or i not in poses:
                continue
            kf, T_i = self._kfs[i], poses[i]
            d_t, _ = pose_error(T_i, T)
            cos = float(np.clip(T_i[:3, 2] @ T[:3, 2], -1.0, 1.0))
            if d_t > c.max_distance or np.degrees(np.arccos(cos)) > c.max_angle:
                continue
            ov = view_overlap(view.depth, view.K, T, kf.view.K, T_i, kf.view.depth.shape, kf.view.depth,
                              stride=2)
            if ov >= c.min_overlap:
                found.append((i, ov))
            else:
                log.debug("loop %d-%d: overlap %.2f < %.2f", i, kf_id, ov, c.min_overlap)
        return sorted(found, key=lambda x: -x[1])

    def detect(self, kf_id: int, frame: FrameLike | RGBDView,
               keyframe_poses: dict[int, np.ndarray]) -> list[LoopConstraint]:
        """Verified loops between keyframe ``kf_id`` (images ``frame``) and earlier stored keyframes, from the
        current pose estimates ``keyframe_poses`` (``T_w_c`` by keyframe id, ``kf_id`` included). Does not store
        ``kf_id`` itself (call :meth:`add_keyframe`)."""
        c = self.cfg
        view = self._view(frame)
        poses = self._poses(keyframe_poses, kf_id)
        T = poses[kf_id]
        self.rejections = []
        out: list[LoopConstraint] = []
        orb = self._orb(view)
        for i, ov in self._candidates(kf_id, view, poses)[:c.max_candidates]:
            reason = self._verify_appearance(orb, self._kfs[i].orb)
            if reason is None:
                T_i_j_pred = inv(poses[i]) @ T
                stored = self._kfs[i].view
                res = register_rgbd(view, stored, T_i_j_pred, c.registration, c.gates)
                stored.cache.clear()  # a stored keyframe keeps its images only (its pyramid is ~1 MB at 160x120)
                reason = c.rejection(res)
                if reason is None:
                    d_t, d_r = pose_error(T_i_j_pred, res.T_tgt_src)
                    log.info("loop %d-%d accepted: overlap %.2f, fitness %.3f, rmse %.4f m, correction %.3f m "
                             "%.2f deg", i, kf_id, ov, res.fitness, res.inlier_rmse, d_t, d_r)
                    out.append(LoopConstraint(i, kf_id, res.T_tgt_src, res.information, res.fitness,
                                              res.inlier_rmse, d_t, d_r))
                    continue
            log.info("loop %d-%d rejected: %s", i, kf_id, reason)
            self.rejections.append((i, reason))
        return out

    # -- helpers ---------------------------------------------------------------------------------------------
    def _view(self, frame: FrameLike | RGBDView) -> RGBDView:
        try:
            view = as_view(frame)
        except ValueError as e:
            raise InputError(f"loop closure: {e}") from None
        return view.downsampled(self.cfg.downsample)

    def _orb(self, view: RGBDView) -> np.ndarray | None:
        if not self.cfg.use_orb:
            return None
        import cv2

        grey = cv2.cvtColor(view.rgb, cv2.COLOR_RGB2GRAY)
        _, desc = cv2.ORB_create(nfeatures=500).detectAndCompute(grey, None)
        return desc

    def _verify_appearance(self, a: np.ndarray | None, b: np.ndarray | None) -> str | None:
        if not self.cfg.use_orb:
            return None
        if a is None or b is None:
            return "no ORB features"
        import cv2

        matches = cv2.BFMatcher(cv2.NORM_HAMMING, crossCheck=True).match(a, b)
        good = sum(1 for m in matches if m.distance < 50)
        if good < self.cfg.min_orb_matches:
            return f"{good} ORB matches < {self.cfg.min_orb_matches}"
        return None

    @staticmethod
    def _pose(T_w_c: np.ndarray, kf_id: int) -> np.ndarray:
        return checked_pose(T_w_c, f"loop closure: pose of keyframe {kf_id}")
