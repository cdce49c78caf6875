"""Closed-form least-squares similarity / rigid alignment of two point sets (Umeyama 1991)."""

from __future__ import annotations

import numpy as np

from lrslam.errors import InputError

__all__ = ["umeyama"]


def umeyama(src: np.ndarray, dst: np.ndarray, with_scale: bool = False) -> tuple[np.ndarray, np.ndarray, float]:
    """Find ``R (3, 3)``, ``t (3,)``, ``s`` minimising ``sum_i ||dst_i - (s R src_i + t)||^2``.

    S. Umeyama, "Least-squares estimation of transformation parameters between two point patterns",
    TPAMI 1991 (eq. 39-42). ``src``, ``dst``: corresponding points ``(N, 3)`` (any unit; ``t`` is in the same
    unit). Without ``with_scale``, ``s`` is exactly 1. ``R`` is a proper rotation (det +1).

    Collinear points (covariance of rank 1) still give a minimiser, but the rotation about the line is then not
    unique. Raises :class:`InputError` for mismatched shapes, fewer than 3 points, non-finite values, or points
    that all coincide (nothing to align).
    """
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    if src.ndim != 2 or src.shape[1] != 3 or src.shape != dst.shape:
        raise InputError(f"umeyama: expected two (N, 3) arrays of corresponding points, got {src.shape} and "
                         f"{dst.shape}")
    n = len(src)
    if n < 3:
        raise InputError(f"umeyama: need at least 3 corresponding points, got {n}")
    if not (np.all(np.isfinite(src)) and np.all(np.isfinite(dst))):
        raise InputError("umeyama: non-finite point coordinates")

    # 1. Centre both sets (eq. 34-35) and check that there is a spread to align.
    mu_src, mu_dst = src.mean(axis=0), dst.mean(axis=0)
    src_c, dst_c = src - mu_src, dst - mu_dst
    var_src = float(np.mean(np.sum(src_c**2, axis=1)))  # sigma_x^2 (eq. 36)
    var_dst = float(np.mean(np.sum(dst_c**2, axis=1)))
    for name, var, mu in (("source", var_src, mu_src), ("target", var_dst, mu_dst)):
        if var <= (1e-12 * max(1.0, float(np.abs(mu).max()))) ** 2:
            raise InputError(f"umeyama: all {name} points coincide (spread {np.sqrt(var):.3g}); "
                             "the rotation is undetermined")

    # 2. Cross-covariance and its SVD (eq. 38); S fixes a reflection so that det(R) = +1 (eq. 39, 43).
    cov = dst_c.T @ src_c / n
    U, D, Vt = np.linalg.svd(cov)
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt

    # 3. Scale (eq. 42) and translation (eq. 41).
    s = float(np.trace(np.diag(D) @ S) / var_src) if with_scale else 1.0
    t = mu_dst - s * R @ mu_src
    return R, t, s
