"""Fusion of the frontend and the field at every frame, weighted by noise levels measured in the run itself.

At every frame two sources say how the camera moved from the last fused pose: the frontend's odometry increment
(the seed) and the field's tracking against the map (the refinement, which also pulls the pose back toward the
map). The fused pose takes the share ``k`` of the field's correction of the seed (per block, rotation and
translation): ``T = T_seed exp(k * log(T_seed^-1 T_field))`` with ``k = s_o / (s_o + s_f)``, where ``s_o`` and
``s_f`` are the odometry's and the field's error variances over the same motion. ``k`` near 0: the odometry is
the more precise and the field only bounds its drift; near 1: the field's word.

The variances come from the run, without ground truth. Between consecutive keyframes i and j three estimates of the
same motion exist: the field's (its own tracked poses of i and j, before fusion), the frontend's chain of per-frame
increments, and the frontend's direct registration of j to i (the graph's odometry factor). The registration never
sees the field, so its disagreement with the field has the mean square ``D_fr = s_f + s_r``; the chain's with the
registration ``D_cr = s_o + s_r``. How ``D_cr`` splits is a model (``FusionConfig.chain_model``): ``random_walk``
(default) takes the chain of ``n`` frame-to-frame registrations (``n`` the mean keyframe gap) to err as ``n``
independent registrations and the direct one as one: ``s_r = D_cr / (n + 1)``, ``s_o = n D_cr / (n + 1)``; ``equal``
takes the two as equally precise, ``s_o = s_r = D_cr / 2`` (for data where the two share most of their error:
7-Scenes, whose colour was recorded unregistered to its depth and is registered only approximately). Then
``s_f = D_fr - s_r`` (per axis; rotation rad^2 and translation m^2 separately). ``s_o`` weighs the chain in the
per-frame fusion, ``s_r`` the graph's registration factors (:meth:`FrameFusion.gap_noise`). The field-chain
disagreement is not used: the field starts from the odometry's seed, so the two are correlated and their
disagreement understates both (measured: the frontend's variance came out at the floor on TUM fr1/rpy).
:class:`NoiseEstimate` keeps the running sums, started from prior values until ``warmup_keyframes`` gaps are
measured.

A frame whose odometry failed, was overruled by the field's seed arbitration, or registered weakly (fitness below
``gates.trusted_fitness``: at large motion a registration that passes its gates can be decimetres off, and the
noise estimate, which compares the frontend with itself, cannot tell) takes the field's word (``k = 1``).

The same share applies where the field's mapper moves poses (its joint optimisation of the window's keyframes,
:meth:`FrameFusion.blend`): on a fast synthetic orbit whose map stayed poor, those write-backs alone took the
fused ATE from the frontend's 0.8 to 2.2 cm.

Poses are 4x4 float64 ``T_w_c``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from pydantic import Field

from lrslam.backend.calibration import GapNoise
from lrslam.config import StrictModel
from lrslam.geometry import blend, inv, log_se3

__all__ = ["FusionConfig", "NoiseEstimate", "FrameFusion", "FusedPose"]

PAIRS = ("field-registration", "chain-registration")


class FusionConfig(StrictModel):
    """Per-frame fusion of odometry and field (:class:`FrameFusion`). Angles in degrees, distances in metres.

    per_frame: fuse at every frame (the ``fused`` mode); off, the field's refinement is the frame's pose.
    prior_*: the per-keyframe-gap standard deviations used until ``warmup_keyframes`` gaps are measured (the
    field's 3x the odometry's: gated out, the field has to earn its share). min_sigma_*: floor of every estimated sigma.
    outlier_factor: a disagreement above this many times the expected RMS counts as that much (a broken
    registration does not swamp the estimate)."""

    per_frame: bool = False
    warmup_keyframes: int = Field(3, ge=1, description="keyframe gaps measured before the estimate replaces the "
                                  "prior")
    prior_field_sigma_deg: float = Field(1.5, gt=0)
    prior_field_sigma_m: float = Field(0.03, gt=0)
    prior_odometry_sigma_deg: float = Field(0.5, gt=0)
    prior_odometry_sigma_m: float = Field(0.01, gt=0)
    min_sigma_deg: float = Field(0.005, gt=0)
    min_sigma_m: float = Field(0.0001, gt=0)
    outlier_factor: float = Field(5.0, gt=1)
    fallback_sigma_deg: float = Field(5.0, gt=0, description="per-frame sigma of a frame whose odometry failed")
    fallback_sigma_m: float = Field(0.1, gt=0)
    max_variance_ratio: float = Field(8.0, gt=1, description="the field gets no share where its variance is "
                                      "more than this many times the odometry's (per block)")
    chain_model: Literal["equal", "random_walk"] = Field(
        "random_walk", description="how the chain-registration disagreement D_cr splits between its two sources: "
        "equal (each D_cr / 2) or random_walk (the chain of n frame-to-frame steps errs as n registrations, the "
        "keyframe registration as one: D_cr / (n + 1) and n D_cr / (n + 1), n the mean keyframe gap in frames)")


def _ms(xi: np.ndarray) -> np.ndarray:
    """Mean square per axis of the rotation (rad^2) and translation (m^2) parts of a 6-vector -> (2,)."""
    return np.array([np.mean(xi[:3] ** 2), np.mean(xi[3:] ** 2)])


class NoiseEstimate:
    """Running estimate of the error variances of the field and of the frontend over a keyframe gap, from their
    disagreements with the frontend's direct registration (module docstring); each (2,): rotation rad^2,
    translation m^2, per axis."""

    def __init__(self, cfg: FusionConfig):
        self.cfg = cfg
        self.sums = np.zeros((2, 2))   # rows: PAIRS; columns: rotation, translation
        self.counts = np.zeros(2)
        self.frames = self.gaps = 0    # frames and keyframe gaps seen (the mean gap length)

    def variances(self) -> dict[str, np.ndarray]:
        """``{"field", "odometry", "registration"}`` -> variance (2,) over a keyframe gap of the field's motion,
        the frontend's chain of frame-to-frame steps and its direct keyframe registration: the prior's until both
        pairs have ``warmup_keyframes`` gaps, the data's alone after (``chain_model`` splits the chain-registration
        disagreement)."""
        c = self.cfg
        if not self.measured():
            odometry = np.array([np.radians(c.prior_odometry_sigma_deg) ** 2, c.prior_odometry_sigma_m ** 2])
            return {"field": np.array([np.radians(c.prior_field_sigma_deg) ** 2, c.prior_field_sigma_m ** 2]),
                    "odometry": odometry, "registration": odometry.copy()}
        floor = np.array([np.radians(c.min_sigma_deg) ** 2, c.min_sigma_m ** 2])
        d_fr, d_cr = self.sums / self.counts[:, None]
        share = 1.0 / (self.gap_frames() + 1.0) if c.chain_model == "random_walk" else 0.5
        registration = d_cr * share
        return {"field": np.maximum(d_fr - registration, floor), "odometry": np.maximum(d_cr - registration, floor),
                "registration": np.maximum(registration, floor)}

    def measured(self) -> bool:
        """Whether both pairs have ``warmup_keyframes`` gaps (the variances are the data's, not the prior's)."""
        return bool(self.counts.min() >= self.cfg.warmup_keyframes)

    def gap_frames(self) -> float:
        """Mean keyframe gap in frames (1 before the first)."""
        return self.frames / self.gaps if self.gaps else 1.0

    def add(self, field: np.ndarray | None, chain: np.ndarray | None, registration: np.ndarray | None,
            frames: int) -> None:
        """One keyframe gap of ``frames`` frames: its three estimates ``T_i_j`` (4, 4) of the same motion; None
        where a source has none (a pair counts only when both of its sources are there)."""
        v = self.variances()
        est = {"field": field, "chain": chain, "registration": registration}
        expected = {"field-registration": v["field"] + v["registration"],
                    "chain-registration": v["odometry"] + v["registration"]}
        for row, pair in enumerate(PAIRS):
            a, b = pair.split("-")
            if est[a] is None or est[b] is None:
                continue
            cap = self.cfg.outlier_factor ** 2 * expected[pair]
            xi = log_se3(inv(est[a]) @ est[b])
            self.sums[row] += np.minimum(_ms(xi), cap)
            self.counts[row] += 1
        self.frames += frames
        self.gaps += 1

    def state_dict(self) -> dict:
        return {"sums": self.sums.copy(), "counts": self.counts.copy(), "frames": self.frames, "gaps": self.gaps}

    def load_state_dict(self, state: dict) -> None:
        self.sums = np.asarray(state["sums"], dtype=np.float64).copy()
        self.counts = np.asarray(state["counts"], dtype=np.float64).copy()
        self.frames, self.gaps = int(state["frames"]), int(state["gaps"])


@dataclass(frozen=True)
class FusedPose:
    """A frame's fused ``T_w_c`` (4, 4) and the share (rotation, translation) of the field's correction taken
    (0: the odometry's seed, 1: the field's pose)."""

    T_w_c: np.ndarray
    gain: tuple[float, float]


class FrameFusion:
    """Per-frame Kalman fusion of the odometry's seed and the field's pose (module docstring). State: the pose
    variance ``P`` (2,) of the last fused frame relative to the map, the :class:`NoiseEstimate` and, since the last
    keyframe, the field's and the frontend's own poses of it (the frontend's chain is broken by a frame where its
    odometry failed); no trajectory pose (the trajectory owns them)."""

    def __init__(self, cfg: FusionConfig):
        self.cfg = cfg
        self.noise = NoiseEstimate(cfg)
        self.P = np.zeros(2)
        self._gain = np.zeros(2)                   # the last frame's share (what the mapper's moves get)
        self._kf_field: np.ndarray | None = None
        self._kf_frontend: np.ndarray | None = None
        self._field: np.ndarray | None = None      # the last frame's field pose (None: failed)
        self._frontend: np.ndarray | None = None   # the last frame's frontend pose (None: chain broken)
        self._chain_ok = True
        self._frames = 0                           # frames since the last keyframe

    def variances(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(q, r, gated)``, each (2,) rotation / translation: the odometry's variance per frame
        (``s_o / mean gap``), the field's per frame (``s_f / 2``: a gap's field motion is the difference of two
        field poses), and whether the field is gated out (:meth:`_gated`)."""
        v = self.noise.variances()
        return v["odometry"] / self.noise.gap_frames(), v["field"] / 2, self._gated(v)

    def _gated(self, v: dict[str, np.ndarray]) -> np.ndarray:
        """(2,) bool per block: the field's variance is above ``max_variance_ratio`` times the odometry's
        (``v``: :meth:`NoiseEstimate.variances`)."""
        return v["field"] > self.cfg.max_variance_ratio * v["odometry"]

    def start(self, T_w_c0: np.ndarray, T_frontend0: np.ndarray | None) -> None:
        """The first frame (a keyframe, fixed: ``P = 0``)."""
        self._field = self._kf_field = np.asarray(T_w_c0, dtype=np.float64).copy()
        self._frontend = self._kf_frontend = None if T_frontend0 is None else np.asarray(T_frontend0, np.float64)
        self._chain_ok = T_frontend0 is not None
        self.P, self._frames = np.zeros(2), 0

    def fuse(self, T_seed: np.ndarray, odometry_ok: bool, T_field: np.ndarray | None,
             T_frontend: np.ndarray | None, trusted: bool = True) -> FusedPose:
        """Fuse one frame: ``T_seed`` (the last fused pose times the odometry increment; a constant-velocity guess
        when ``odometry_ok`` is False), ``T_field`` the field's pose (None when tracking failed or was not kept),
        ``T_frontend`` the frontend's own pose of the frame (None when its odometry failed: that breaks the
        frontend's chain for the keyframe gap); ``trusted`` False for a weak registration
        (:attr:`lrslam.frontend.odometry.OdometryResult.trusted`): the frame fuses as one without odometry, but the
        frontend's chain goes on (its error belongs in the noise estimate: leaving the weak steps out made the
        odometry look 6-7x more precise, in sigma, on TUM fr1/rpy at every 3rd frame); the same for a seed the
        field's arbitration overruled (``odometry_ok`` False while ``T_frontend`` is given: those are the frontend's
        largest errors, and leaving their gaps out made its noise look smaller). Predict
        ``P + q`` (the fallback variance without odometry), update with the field: share ``k = P / (P + r)`` (0
        where the field is gated out, 1 without odometry), ``P = (1 - k) P``."""
        c = self.cfg
        self._field = None if T_field is None else np.asarray(T_field, dtype=np.float64).copy()
        self._frontend = None if T_frontend is None else np.asarray(T_frontend, dtype=np.float64).copy()
        self._chain_ok = self._chain_ok and T_frontend is not None
        odometry_ok = odometry_ok and trusted
        self._frames += 1
        q, r, gated = self.variances()
        fallback = np.array([np.radians(c.fallback_sigma_deg) ** 2, c.fallback_sigma_m ** 2])
        P = self.P + (q if odometry_ok else fallback)
        T_seed = np.asarray(T_seed, dtype=np.float64)
        if T_field is None:
            self.P, self._gain = P, np.zeros(2)
            return FusedPose(T_seed.copy(), (0.0, 0.0))
        k = np.ones(2) if not odometry_ok else np.where(gated, 0.0, P / (P + r))
        self.P, self._gain = np.where(odometry_ok, (1 - k) * P, r), k
        return FusedPose(blend(T_seed, self._field, k), (float(k[0]), float(k[1])))

    def blend(self, T_current: np.ndarray, T_field: np.ndarray) -> np.ndarray:
        """A pose the field's mapper moved (``T_current`` -> ``T_field``, both (4, 4)) moves by the field's last
        share only."""
        return blend(T_current, T_field, self._gain)

    def on_keyframe(self, T_registration: np.ndarray | None) -> None:
        """The last fused frame is a keyframe: add its gap's estimates to the noise estimate
        (``T_registration``: the frontend's direct registration of it to the previous keyframe, None when
        there was none) and make it the reference of the next gap."""
        field = self.field_motion()
        chain = (inv(self._kf_frontend) @ self._frontend
                 if self._chain_ok and self._kf_frontend is not None and self._frontend is not None else None)
        self.noise.add(field, chain, T_registration, self._frames)
        self._kf_field, self._kf_frontend = self._field, self._frontend
        self._chain_ok, self._frames = self._frontend is not None, 0

    def field_pose(self) -> np.ndarray | None:
        """The field's own tracked pose ``T_w_c`` (4, 4) of the last fused frame (before fusion); None when its
        tracking failed or was not kept."""
        return None if self._field is None else self._field.copy()

    def field_motion(self) -> np.ndarray | None:
        """The field's own motion ``T_i_j`` (4, 4) from the last keyframe i to the last fused frame (its tracked
        poses, before fusion); None when the field failed on either."""
        return None if self._field is None or self._kf_field is None else inv(self._kf_field) @ self._field

    def gap_noise(self) -> GapNoise:
        """The current :class:`~lrslam.backend.calibration.GapNoise` (the factors' calibration)."""
        v = self.noise.variances()
        return GapNoise(v["registration"].copy(), v["field"].copy(), self.noise.measured(), self._gated(v),
                        v["odometry"].copy())

    def sigmas(self) -> dict[str, float]:
        """The current estimate: standard deviations per axis over a keyframe gap (``field_deg``, ``field_m``,
        ``odometry_deg``, ``odometry_m``), the mean gap in frames and the last frame's share of the field
        (``gain_rotation``, ``gain_translation``)."""
        out: dict[str, float] = {}
        for name, v in self.noise.variances().items():
            out[f"{name}_deg"] = float(np.degrees(np.sqrt(v[0])))
            out[f"{name}_m"] = float(np.sqrt(v[1]))
        return out | {"gap_frames": self.noise.gap_frames(), "gain_rotation": float(self._gain[0]),
                      "gain_translation": float(self._gain[1])}

    def state_dict(self) -> dict:
        copy = lambda T: None if T is None else T.copy()   # noqa: E731
        return {"noise": self.noise.state_dict(), "P": self.P.copy(), "gain": self._gain.copy(),
                "kf_field": copy(self._kf_field), "kf_frontend": copy(self._kf_frontend),
                "field": copy(self._field), "frontend": copy(self._frontend), "chain_ok": self._chain_ok,
                "frames": self._frames}

    def load_state_dict(self, state: dict) -> None:
        arr = lambda T: None if T is None else np.asarray(T, dtype=np.float64).copy()   # noqa: E731
        self.noise.load_state_dict(state["noise"])
        self.P, self._gain = arr(state["P"]), arr(state["gain"])
        self._kf_field, self._kf_frontend = arr(state["kf_field"]), arr(state["kf_frontend"])
        self._field, self._frontend = arr(state["field"]), arr(state["frontend"])
        self._chain_ok, self._frames = bool(state["chain_ok"]), int(state["frames"])
