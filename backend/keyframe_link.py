"""The frontend's own relative pose between consecutive keyframes (the graph's odometry factor).

Between keyframes i and j the frontend measures the motion twice over: as the chain of its frame-to-frame
odometry increments (:attr:`OdometryResult.T_prev_c`, each with its information) and, at j, by registering
j directly to i starting from that chain. Both come from the frontend alone -- the field never seeds them -- so
the factor is independent of the field's estimate of the same motion. They are not independent of each other
(same images), so one is the factor (``factor``): by default the direct registration when it passes its gates,
else the chain, whose covariance is propagated increment by increment
(:func:`lrslam.geometry.propagate_covariance`); with ``factor="chain"`` always the chain (with the registration's
information shape when it passed its gates: the calibration rescales it to the chain's measured noise). The chain
can be the better factor where the frontend refines each frame against a model (``odometry.model``) and the direct
registration carries a bias of the data: 7-Scenes, whose colour is registered to its depth only approximately (fused
with the model, excerpt every 4th frame, 3 deterministic seeds: 2.96 cm; seed 0: 2.94 against 3.83 with the
registration as the factor; but threaded 3.70, 3.70, 2.73, 3.92 against 3.46 for the default frame-to-frame fused, so
no preset uses it; docs/BENCHMARKS.md section 21). The direct registration is always measured: the
fusion's noise estimate compares the chain with it (:attr:`KeyframeLinkMeasurement.T_registration`).

A measurement is *trusted* when the registration's fitness reaches ``gates.trusted_fitness`` (for the chain standing
in for a failed registration: when every increment was trusted, :attr:`OdometryResult.trusted`; the chain as the
factor by choice: when both are, the registration saying the two keyframes overlap well; 7-Scenes every 12th
frame, where the frontend loses track, deterministic seed 0: 6.53 cm against 8.62 with the registration's trust
alone). An untrusted one is still reported: the graph gets
no factor from it (:class:`lrslam.backend.policy.GraphBackend`), the fusion's noise estimate still counts its error.
At large motion a registration that passes its gates can be wrong by decimetres, and its fitness says so.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Literal

import numpy as np

from lrslam.frontend.odometry import OdometryResult
from lrslam.frontend.registration import RegistrationConfig, RegistrationGates, register_rgbd
from lrslam.frontend.rgbd_view import FrameLike, RGBDView, as_view
from lrslam.geometry import propagate_covariance

__all__ = ["KeyframeLinkMeasurement", "KeyframeLink"]

log = logging.getLogger(__name__)

_EPS = 1e-9


@dataclass(frozen=True)
class KeyframeLinkMeasurement:
    """``T_i_j`` (4, 4): keyframe j's camera in keyframe i's; ``information`` (6, 6), right perturbation,
    ``[rotation, translation]``; ``source``: ``"registration"`` or ``"chain"``; ``frames``: odometry increments
    chained; ``trusted``: see the module docstring; ``T_registration`` (4, 4): the direct registration of j to i
    when it passed its gates (whichever is the factor), else None."""

    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray
    source: str
    frames: int
    trusted: bool = True
    T_registration: np.ndarray | None = None


def _covariance(information: np.ndarray) -> np.ndarray:
    info = 0.5 * (information + information.T)
    return np.linalg.inv(info + _EPS * np.eye(6))


class KeyframeLink:
    """Accumulates the odometry between keyframes and measures each new keyframe against the previous one.

    Args:
        registration: how the keyframe-to-keyframe registration runs.
        gates: whether it is accepted (else the chain is used).
        factor: ``"registration"`` (the direct registration, the chain where it fails its gates) or ``"chain"``
            (the chain always; module docstring).
    """

    def __init__(self, registration: RegistrationConfig, gates: RegistrationGates,
                 factor: Literal["registration", "chain"] = "registration"):
        self.registration, self.gates, self.factor = registration, gates, factor
        self._kf_id: int | None = None
        self._kf_view: RGBDView | None = None
        self._T = np.eye(4)
        self._cov = np.zeros((6, 6))
        self._frames = 0
        self._trusted = True

    def start(self, kf_id: int, frame: FrameLike) -> None:
        """Make ``kf_id`` (images ``frame``) the keyframe the next measurement starts from."""
        self._kf_id, self._kf_view = int(kf_id), RGBDView(*_images(frame))
        self._T, self._cov, self._frames, self._trusted = np.eye(4), np.zeros((6, 6)), 0, True

    def state_dict(self) -> dict:
        """The previous keyframe (id, images) and the chain since it, for checkpoints."""
        return {"kf_id": self._kf_id, "kf_view": None if self._kf_view is None else self._kf_view.state(),
                "T": self._T.copy(), "cov": self._cov.copy(), "frames": self._frames, "trusted": self._trusted}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output."""
        self._kf_id = state["kf_id"]
        self._kf_view = None if state["kf_view"] is None else RGBDView.from_state(state["kf_view"])
        self._T = np.asarray(state["T"], dtype=np.float64)
        self._cov = np.asarray(state["cov"], dtype=np.float64)
        self._frames = int(state["frames"])
        self._trusted = bool(state.get("trusted", True))

    def accumulate(self, odo: OdometryResult) -> None:
        """Chain one frame's odometry increment (``odo.T_prev_c`` with ``odo.information``)."""
        self._cov = propagate_covariance(self._T, self._cov, odo.T_prev_c, _covariance(odo.information))
        self._T = self._T @ odo.T_prev_c
        self._frames += 1
        self._trusted = self._trusted and odo.trusted

    def measure(self, kf_id: int, frame: FrameLike) -> KeyframeLinkMeasurement | None:
        """The frontend's relative pose from the previous keyframe to ``kf_id`` (images ``frame``); then
        ``kf_id`` becomes the previous keyframe. None before :meth:`start`."""
        if self._kf_id is None:
            self.start(kf_id, frame)
            return None
        view = RGBDView(*_images(frame))
        reg = register_rgbd(view, self._kf_view, self._T, self.registration, self.gates)
        T_reg = reg.T_tgt_src if reg.ok else None
        if reg.ok and self.factor == "chain":
            out = KeyframeLinkMeasurement(self._kf_id, int(kf_id), self._T.copy(), reg.information, "chain",
                                          self._frames, reg.trusted and self._trusted, T_reg)
        elif reg.ok:
            out = KeyframeLinkMeasurement(self._kf_id, int(kf_id), reg.T_tgt_src, reg.information, "registration",
                                          self._frames, reg.trusted, T_reg)
        else:
            log.info("keyframe %d -> %d registration rejected (%s): using the odometry chain of %d frames",
                     self._kf_id, kf_id, reg.reason, self._frames)
            out = KeyframeLinkMeasurement(self._kf_id, int(kf_id), self._T.copy(),
                                          np.linalg.inv(self._cov + _EPS * np.eye(6)), "chain", self._frames,
                                          self._trusted)
        if not out.trusted:
            log.info("keyframe %d -> %d: the frontend's %s is weak (fitness below %.2f): no odometry factor",
                     self._kf_id, kf_id, out.source, self.gates.trusted_fitness)
        self.start(kf_id, frame)
        return out


def _images(frame: FrameLike) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    v = as_view(frame)
    return v.rgb, v.depth, v.K
