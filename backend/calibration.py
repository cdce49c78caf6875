"""Calibrated information for the pose graph's factors, from the noise the run measured itself.

The factors arrive with informations their sources state: the frontend's registration gives its point-to-plane
Hessian (scaled by an assumed point noise), the field its tracker's. Measured against ground truth those are off by
one to three orders of magnitude (docs/BENCHMARKS.md, ``benchmarks/calibrate.py``), so a graph built on them cannot
weigh its sources. :class:`lrslam.backend.frame_fusion.NoiseEstimate` measures, without ground truth, the error
variance of the frontend's and of the field's motion over a keyframe gap (:class:`GapNoise`). From it:

- ``odometry`` and ``loop`` factors (both registrations of two views by the same frontend) keep the *shape* of their
  Hessian (which directions the geometry constrains) and get its *scale* from the data: per block (rotation,
  translation) a factor ``alpha`` such that the registrations' mean per-axis variance equals the measured one
  (:func:`registration_scale`; a chain of per-frame steps standing in for a failed registration does not count);
  the loops and those chains get the same ``alpha``;
- ``field`` factors get the measured field variance per axis (the tracker's Hessian is not a registration's, and
  its scale is the one measured least well); ``field_pose`` records (the field's own pose of a keyframe, an
  absolute measurement against the map) get half of it (:meth:`GapNoise.field_pose_information`).

Informations are 6x6 for a right perturbation ``[rotation (rad), translation (m)]``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field as dc_field, replace
import numpy as np

__all__ = ["GapNoise", "registration_scale", "scaled_information", "calibrated"]

_EPS = 1e-12


@dataclass(frozen=True)
class GapNoise:
    """Per-axis error variances over one keyframe gap, ``(2,)`` each: rotation (rad^2), translation (m^2), of the
    frontend's keyframe-to-keyframe motion (``odometry``) and of the field's (``field``); ``measured``: False while
    they are still the configured prior; ``field_gated`` (2,) bool: per block, whether the field is judged too
    imprecise to take part (its variance far above the odometry's, :class:`lrslam.backend.frame_fusion.FusionConfig`);
    ``chain`` (2,): the variance of the frontend's chain of per-frame poses over a gap (the odometry factor's when
    that is the chain, ``BackendConfig.odometry_factor``), None where not measured."""

    odometry: np.ndarray
    field: np.ndarray
    measured: bool
    field_gated: np.ndarray = dc_field(default_factory=lambda: np.zeros(2, dtype=bool))
    chain: np.ndarray | None = None

    def field_pose_information(self) -> np.ndarray:
        """(6, 6) information of the field's own pose of a keyframe against the map (an absolute measurement:
        a gap's field motion is the difference of two such poses, so its per-axis variance is ``field / 2``);
        a gated block gets a negligible weight (1e-6 of its value)."""
        v = np.maximum(self.field, _EPS) / 2 * np.where(self.field_gated, 1e6, 1.0)
        return np.diag(1.0 / np.repeat(v, 3))


def _block_variances(information: np.ndarray) -> np.ndarray:
    """Mean per-axis variance (2,) of the rotation and translation blocks of the covariance ``information^-1``."""
    info = 0.5 * (np.asarray(information, dtype=np.float64) + np.asarray(information, dtype=np.float64).T)
    cov = np.linalg.inv(info + _EPS * np.eye(6))
    d = np.diag(cov)
    return np.array([d[:3].mean(), d[3:].mean()])


def registration_scale(informations: Sequence[np.ndarray], variance: np.ndarray) -> np.ndarray:
    """Scale ``alpha`` (2,: rotation, translation) of registration informations ``informations`` (each (6, 6))
    such that, scaled by it (:func:`scaled_information`), their mean per-axis variance is ``variance`` (2,).
    Ones when there is no information to scale."""
    if not informations:
        return np.ones(2)
    stated = np.mean([_block_variances(H) for H in informations], axis=0)
    return stated / np.maximum(np.asarray(variance, dtype=np.float64), _EPS)


def scaled_information(information: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """``S H S`` with ``S = diag(sqrt(alpha[0]) I3, sqrt(alpha[1]) I3)``: the rotation block of the covariance
    divided by ``alpha[0]``, the translation block by ``alpha[1]``, correlations kept."""
    s = np.sqrt(np.repeat(np.asarray(alpha, dtype=np.float64), 3))
    return np.asarray(information, dtype=np.float64) * np.outer(s, s)


def _scale_setters(factors: Sequence) -> list[np.ndarray]:
    """The informations the registrations' scale is measured on: the odometry factors that are registrations. A
    keyframe whose registration failed its gates gets its chain of per-frame steps instead (``source="chain"``),
    stated n steps loose; in the mean it would outweigh the registrations and make them (and the loops, which
    share the scale) too precise. Where every odometry factor is a chain (``BackendConfig.odometry_factor="chain"``,
    the noise then being the chain's) the chains set it."""
    odometry = [f for f in factors if f.kind == "odometry"]
    registrations = [f.information for f in odometry if f.source != "chain"]
    return registrations or [f.information for f in odometry]


def calibrated(factors: Sequence, noise: GapNoise, registrations: bool = True) -> list:
    """``factors`` (frozen dataclasses with ``kind``, ``information`` and ``source``, e.g.
    :class:`lrslam.backend.policy.FactorRecord`) with their informations calibrated by ``noise`` (module
    docstring); other kinds (a prior) unchanged. ``registrations=False``: ``odometry`` and ``loop`` factors keep
    their stated informations, only the field's are calibrated (data whose colour is registered to its depth only
    approximately: the odometry variance is measured from the disagreement of two RGB-D registrations, the
    frame-to-frame chain and the keyframe registration, which share the colour's error and so agree; on the
    7-Scenes excerpt the calibrated odometry factors came out 40x too precise against ground truth, chi2 / dof
    38-49, the stated ones near 1, docs/BENCHMARKS.md section 15)."""
    alpha = registration_scale(_scale_setters(factors), noise.odometry)
    field_info = np.diag(1.0 / np.repeat(np.maximum(noise.field, _EPS), 3))
    out = []
    for f in factors:
        if f.kind in ("odometry", "loop") and registrations:
            f = replace(f, information=scaled_information(f.information, alpha))
        elif f.kind == "field":
            f = replace(f, information=field_info.copy())
        elif f.kind == "field_pose":
            f = replace(f, information=noise.field_pose_information())
        out.append(f)
    return out
