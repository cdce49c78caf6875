"""The one place where numpy poses / information matrices become GTSAM objects and back.

Conventions: poses are 4x4 float64 ``T_a_b``; GTSAM's ``Pose3`` tangent is ordered ``[rotation (rad),
translation (m)]`` like ours, and its ``BetweenFactorPose3(i, j, T_i_j)`` error is ``Logmap(T_i_j^-1 X_i^-1 X_j)``:
a right perturbation of ``T_i_j``, so an information matrix for ``T_i_j exp(xi)`` (what the frontend returns)
is used as is. Keyframe ``k`` is the GTSAM key ``symbol('x', k)``.
"""

from __future__ import annotations

import numpy as np

from lrslam.errors import InputError
from lrslam.geometry import checked_pose

__all__ = ["key", "pose_to_gtsam", "pose_from_gtsam", "gaussian_from_information", "robust_noise",
           "values_to_dict"]


def key(kf_id: int) -> int:
    """GTSAM key of keyframe ``kf_id`` (``symbol('x', kf_id)``)."""
    import gtsam

    return gtsam.symbol("x", int(kf_id))


def pose_to_gtsam(T: np.ndarray, what: str = "pose"):
    """4x4 rigid transform -> ``gtsam.Pose3``; ``InputError`` naming ``what`` when not a finite rigid transform."""
    import gtsam

    return gtsam.Pose3(checked_pose(T, what))


def pose_from_gtsam(pose) -> np.ndarray:
    """``gtsam.Pose3`` -> 4x4 float64 numpy pose."""
    return np.asarray(pose.matrix(), dtype=np.float64).copy()


def gaussian_from_information(information: np.ndarray, what: str = "information"):
    """6x6 information matrix (``[rotation, translation]``) -> ``noiseModel.Gaussian.Information``. It is
    symmetrised; a non-finite or not positive-definite matrix raises ``InputError``."""
    import gtsam

    info = np.asarray(information, dtype=np.float64)
    if info.shape != (6, 6) or not np.all(np.isfinite(info)):
        raise InputError(f"{what} must be a finite 6x6 matrix, got shape {info.shape}")
    info = 0.5 * (info + info.T)
    eig = np.linalg.eigvalsh(info)
    if eig[0] <= 1e-12 * max(1.0, eig[-1]):
        raise InputError(f"{what} is not positive definite (smallest eigenvalue {eig[0]:.3g})")
    return gtsam.noiseModel.Gaussian.Information(info)


def robust_noise(base, kernel: str, parameter: float):
    """Wrap ``base`` in an M-estimator: ``"huber"``, ``"cauchy"`` or ``"dcs"`` with ``parameter`` in whitened
    (sigma) units; ``"none"`` returns ``base``."""
    import gtsam

    m = gtsam.noiseModel.mEstimator
    makers = {"huber": m.Huber.Create, "cauchy": m.Cauchy.Create, "dcs": m.DCS.Create}
    if kernel == "none":
        return base
    if kernel not in makers:
        raise InputError(f"unknown robust kernel {kernel!r} (expected one of none, {', '.join(makers)})")
    return gtsam.noiseModel.Robust.Create(makers[kernel](float(parameter)), base)


def values_to_dict(values, ids) -> dict[int, np.ndarray]:
    """Poses of keyframes ``ids`` from a ``gtsam.Values`` -> ``{id: 4x4}``."""
    return {int(i): pose_from_gtsam(values.atPose3(key(i))) for i in ids}
