"""SE(3)/SO(3) helpers on 4x4 float64 numpy poses.

Convention: ``T_a_b`` maps points expressed in frame ``b`` into frame ``a``: ``p_a = T_a_b @ p_b``.
A camera pose ``T_w_c`` maps camera-frame points (OpenCV, see :mod:`lrslam.camera`) into the world.
Quaternions are ``(qx, qy, qz, qw)`` (TUM order, Hamilton, unit norm). 6-vectors (tangents) are ordered
``[rotation (rad), translation (m)]`` like GTSAM and Open3D.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

__all__ = [
    "make_pose", "constant_velocity", "checked_pose", "inv", "rot_to_quat", "quat_to_rot", "pose_from_tum", "pose_to_tum", "exp_se3", "log_se3",
    "pose_error", "random_pose", "is_valid_pose", "relative", "hat", "adjoint", "diagonal_information",
    "propagate_covariance", "orthonormalise", "between_residual", "blend",
]


def make_pose(R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Build a 4x4 float64 pose from a 3x3 rotation and a 3-vector translation (metres)."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R, dtype=np.float64)
    T[:3, 3] = np.asarray(t, dtype=np.float64).reshape(3)
    return T


def inv(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform (4x4), or of a stack (N,4,4), computed in closed form."""
    T = np.asarray(T, dtype=np.float64)
    R = T[..., :3, :3]
    t = T[..., :3, 3]
    out = np.zeros_like(T)
    Rt = np.swapaxes(R, -1, -2)
    out[..., :3, :3] = Rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", Rt, t)
    out[..., 3, 3] = 1.0
    return out


def constant_velocity(T_w_prev: np.ndarray, T_w_last: np.ndarray) -> np.ndarray:
    """The last motion repeated on SE(3): the next ``T_w_c`` is ``T_w_last inv(T_w_prev) T_w_last`` (4, 4)."""
    return T_w_last @ inv(T_w_prev) @ T_w_last


def relative(T_w_a: np.ndarray, T_w_b: np.ndarray) -> np.ndarray:
    """``T_a_b = inv(T_w_a) @ T_w_b``: pose of b expressed in a."""
    return inv(T_w_a) @ np.asarray(T_w_b, dtype=np.float64)


def rot_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix (...,3,3) -> unit quaternion (...,4) as (qx, qy, qz, qw), qw >= 0."""
    q = Rotation.from_matrix(np.asarray(R, dtype=np.float64)).as_quat()
    q = np.where(q[..., 3:4] < 0, -q, q)
    return q


def quat_to_rot(q: np.ndarray) -> np.ndarray:
    """Quaternion(s) (...,4) as (qx, qy, qz, qw) (normalised here) -> rotation matrix (...,3,3)."""
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q, axis=-1, keepdims=True)
    if np.any(~np.isfinite(q)) or np.any(norm < 1e-12):
        raise ValueError("quaternion is not finite or has zero norm")
    return Rotation.from_quat(q / norm).as_matrix()


def pose_from_tum(values: np.ndarray) -> np.ndarray:
    """``(..., 7)`` rows ``tx ty tz qx qy qz qw`` -> poses ``(..., 4, 4)``."""
    v = np.asarray(values, dtype=np.float64)
    T = np.zeros(v.shape[:-1] + (4, 4))
    T[..., :3, :3] = quat_to_rot(v[..., 3:7])
    T[..., :3, 3] = v[..., :3]
    T[..., 3, 3] = 1.0
    return T


def pose_to_tum(T: np.ndarray) -> np.ndarray:
    """Poses ``(..., 4, 4)`` -> ``(..., 7)`` rows ``tx ty tz qx qy qz qw``."""
    T = np.asarray(T, dtype=np.float64)
    return np.concatenate([T[..., :3, 3], rot_to_quat(T[..., :3, :3])], axis=-1)


def orthonormalise(T: np.ndarray) -> np.ndarray:
    """The nearest rigid transform: the rotation block projected onto SO(3) (SVD), translation kept. Chains of
    products drift away from orthonormal (float32 kernels, ``inv`` by transposition), and a drift compounds."""
    T = np.asarray(T, dtype=np.float64)
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ np.diag([1.0, 1.0, np.linalg.det(U @ Vt)]) @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def hat(w: np.ndarray) -> np.ndarray:
    """Skew-symmetric 3x3 matrix of a 3-vector: ``hat(w) @ x == np.cross(w, x)``."""
    w = np.asarray(w, dtype=np.float64).reshape(3)
    return np.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


def adjoint(T: np.ndarray) -> np.ndarray:
    """6x6 adjoint of a 4x4 pose for tangents ordered ``[rotation, translation]`` (as GTSAM's
    ``Pose3.AdjointMap``): ``T exp(xi) T^-1 = exp(Ad_T xi)``."""
    T = np.asarray(T, dtype=np.float64)
    R, t = T[:3, :3], T[:3, 3]
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = hat(t) @ R
    return Ad


def diagonal_information(sigma_rotation_rad: float, sigma_translation_m: float) -> np.ndarray:
    """6x6 diagonal information ``diag(1/sigma_r^2 (x3), 1/sigma_t^2 (x3))`` for a ``[rotation, translation]``
    tangent (radians, metres)."""
    return np.diag([sigma_rotation_rad ** -2] * 3 + [sigma_translation_m ** -2] * 3)


def propagate_covariance(T_a_b: np.ndarray, cov_a_b: np.ndarray, T_b_c: np.ndarray,
                         cov_b_c: np.ndarray) -> np.ndarray:
    """Covariance (6x6, right perturbation, ``[rotation, translation]``) of the composition ``T_a_c = T_a_b T_b_c``
    of two independent relative poses: ``T_a_b exp(x1) T_b_c exp(x2) = T_a_c exp(Ad(T_b_c^-1) x1 + x2)``
    (first order), so ``cov = A cov_a_b A^T + cov_b_c`` with ``A = Ad(inv(T_b_c))``. ``T_a_b`` only names the
    factor; it does not enter the first-order result."""
    del T_a_b
    A = adjoint(inv(T_b_c))
    return A @ np.asarray(cov_a_b, dtype=np.float64) @ A.T + np.asarray(cov_b_c, dtype=np.float64)


def exp_se3(xi: np.ndarray) -> np.ndarray:
    """Exponential map of a 6-vector ``[omega (rad), v (m)]`` -> 4x4 pose (exact, Rodrigues + V matrix)."""
    xi = np.asarray(xi, dtype=np.float64).reshape(6)
    w, v = xi[:3], xi[3:]
    theta = np.linalg.norm(w)
    W = hat(w)
    if theta < 1e-10:
        R = np.eye(3) + W
        V = np.eye(3) + 0.5 * W
    else:
        a = np.sin(theta) / theta
        b = (1 - np.cos(theta)) / theta**2
        c = (theta - np.sin(theta)) / theta**3
        R = np.eye(3) + a * W + b * W @ W
        V = np.eye(3) + b * W + c * W @ W
    return make_pose(R, V @ v)


def log_se3(T: np.ndarray) -> np.ndarray:
    """Logarithm of a 4x4 pose -> 6-vector ``[omega (rad), v (m)]`` (inverse of :func:`exp_se3`)."""
    T = np.asarray(T, dtype=np.float64)
    w = Rotation.from_matrix(T[:3, :3]).as_rotvec()
    theta = np.linalg.norm(w)
    W = hat(w)
    if theta < 1e-10:
        V_inv = np.eye(3) - 0.5 * W
    else:
        half = 0.5 * theta
        k = (1 - half * np.cos(half) / np.sin(half)) / theta**2
        V_inv = np.eye(3) - 0.5 * W + k * W @ W
    return np.concatenate([w, V_inv @ T[:3, 3]])


def blend(T_a: np.ndarray, T_b: np.ndarray, k) -> np.ndarray:
    """The pose a share ``k`` of the way from ``T_a`` to ``T_b`` (both (4, 4)) along the SE(3) geodesic:
    ``T_a exp(k log(T_a^-1 T_b))``; ``k`` a scalar, or ``(rotation share, translation share)`` scaling the two
    blocks of the log separately. ``k = 0`` gives ``T_a``, ``k = 1`` gives ``T_b``."""
    k = np.broadcast_to(np.asarray(k, dtype=np.float64), (2,))
    T_a = np.asarray(T_a, dtype=np.float64)
    xi = log_se3(inv(T_a) @ T_b)
    return T_a @ exp_se3(np.concatenate([k[0] * xi[:3], k[1] * xi[3:]]))


def between_residual(T_meas: np.ndarray, information: np.ndarray, T_other: np.ndarray) -> tuple[np.ndarray, float]:
    """Residual of a between measurement ``T_meas`` (4, 4, a relative pose ``T_i_j``) against another estimate
    ``T_other`` of the same relative pose: the error 6-vector ``e = log(T_meas^-1 T_other)`` (``[rotation rad,
    translation m]``, right perturbation) and its normalised square ``chi2 = e^T information e`` (``information``
    (6, 6)). Chi-square with 6 degrees of freedom when ``information`` is the inverse of the error covariance."""
    e = log_se3(inv(np.asarray(T_meas, dtype=np.float64)) @ np.asarray(T_other, dtype=np.float64))
    return e, float(e @ np.asarray(information, dtype=np.float64) @ e)


def pose_error(T_a: np.ndarray, T_b: np.ndarray) -> tuple[float, float]:
    """Difference between two poses: (translation error in metres, rotation error in degrees)."""
    D = relative(T_a, T_b)
    trans = float(np.linalg.norm(np.asarray(T_a)[:3, 3] - np.asarray(T_b)[:3, 3]))
    cos = np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return trans, float(np.degrees(np.arccos(cos)))


def random_pose(rng: np.random.Generator, max_trans_m: float, max_rot_deg: float) -> np.ndarray:
    """Random rigid transform: translation uniform in a ball of radius ``max_trans_m``, rotation of angle
    uniform in ``[0, max_rot_deg]`` about a random axis."""
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(0.0, max_rot_deg))
    d = rng.normal(size=3)
    d /= np.linalg.norm(d)
    t = d * max_trans_m * rng.uniform(0.0, 1.0) ** (1.0 / 3.0)
    return make_pose(Rotation.from_rotvec(axis * angle).as_matrix(), t)


def checked_pose(T: np.ndarray, what: str = "pose", tol: float = 1e-4) -> np.ndarray:
    """``T`` as a new (4, 4) float64 array; InputError "<what> is not a finite 4x4 rigid transform" when it is not
    one (:func:`is_valid_pose` with ``tol``)."""
    from lrslam.errors import InputError

    T = np.array(T, dtype=np.float64)
    if not is_valid_pose(T, tol=tol):
        raise InputError(f"{what} is not a finite 4x4 rigid transform")
    return T


def is_valid_pose(T: np.ndarray, tol: float = 1e-4) -> bool:
    """True when T is a finite 4x4 rigid transform (orthonormal rotation, det +1, last row 0 0 0 1)."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return (np.allclose(R.T @ R, np.eye(3), atol=tol) and abs(np.linalg.det(R) - 1) < tol
            and np.allclose(T[3], [0, 0, 0, 1], atol=tol))
