"""The run's final trajectory smoothed under a motion prior, with the prior's weight measured from the trajectory.

Every frame's pose is estimated from its own images, so each carries its own small error, independent from frame to
frame, on top of the slowly varying drift the pose graph works on. A hand-held or robot-carried camera does not
jerk at 30 Hz, so the smoothed trajectory is the maximum a posteriori estimate under the white-noise-on-acceleration
motion prior (continuous-time trajectory estimation, Barfoot, Tong and Sarkka, RSS 2014): per component,

    minimise  sum_i |y_i - x_i|^2 / sigma_m^2  +  sum_i |x_{i-1} - 2 x_i + x_{i+1}|^2 / sigma_a^2

over the smoothed values ``y`` given the run's ``x`` (a Whittaker smoother: ``(I + lam D^T D) y = x`` with ``D`` the
second difference and ``lam = sigma_m^2 / sigma_a^2``). Nothing is tuned per sequence: ``lam`` comes from the
trajectory's own second differences at two spacings (a structure function, as the Allan variance separates white
noise from a smooth signal). White per-frame noise adds ``6 sigma_m^2`` to the variance of the second difference at
any spacing ``k``; a smooth motion adds ``k^4 sigma_a^2``. From spacing 1 and ``spacing``:

    sigma_a^2 = (V_k - V_1) / (k^4 - 1),   sigma_m^2 = (V_1 - sigma_a^2) / 6.

Where the frames hold no measurable noise (a fast smooth orbit) ``lam`` comes out near 0 and the trajectory stays
as it was; where the per-frame noise dominates the frame-to-frame motion (a slow hand-held camera) it is larger.
Positions are smoothed in the world frame; rotations, when asked, as unit quaternions made sign-continuous, with
their own ``lam``, and re-normalised. Numpy and scipy only; poses ``T_w_c`` (4, 4) float64 in, the same out.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from pydantic import Field

from lrslam.config import StrictModel

__all__ = ["SmoothingConfig", "Smoothing", "estimate_lambda", "whittaker", "smooth_trajectory"]

log = logging.getLogger(__name__)


class SmoothingConfig(StrictModel):
    """The final trajectory's smoothing (:mod:`lrslam.backend.smoother`).

    enabled: smooth the trajectory a run returns (the poses as tracked are kept beside it,
    ``trajectory_unsmoothed.txt``). spacing: the second spacing of the noise estimate, in frames (the motion is
    taken as smooth over ``2 spacing`` frames). max_lambda: the prior's largest weight (where no smooth motion is
    measurable at all). rotations: smooth the rotations too (their own weight)."""

    enabled: bool = True
    spacing: int = Field(3, ge=2, le=10)
    max_lambda: float = Field(100.0, gt=0)
    rotations: bool = False


@dataclass(frozen=True)
class Smoothing:
    """What :func:`smooth_trajectory` did. ``poses``: (N, 4, 4) ``T_w_c``; ``lam_t`` / ``lam_r``: the prior's
    weight for positions / rotations (0: left as they were); ``noise_m``: the per-frame position noise it measured
    (metres, per axis); ``moved_m``: the largest position change; ``applied``: whether anything was smoothed."""

    poses: np.ndarray
    lam_t: float = 0.0
    lam_r: float = 0.0
    noise_m: float = 0.0
    moved_m: float = 0.0
    applied: bool = False

    def summary(self) -> dict:
        """Plain numbers for ``metrics.json``."""
        return {"applied": self.applied, "lambda_position": round(self.lam_t, 4),
                "lambda_rotation": round(self.lam_r, 4), "noise_cm": round(100 * self.noise_m, 4),
                "max_shift_cm": round(100 * self.moved_m, 4)}


def _second_difference_variance(x: np.ndarray, k: int) -> float:
    """Mean over frames and components of ``(x_{i+k} - 2 x_i + x_{i-k})^2``; x (N, d)."""
    d = x[2 * k:] - 2 * x[k:-k] + x[:-2 * k]
    return float(np.mean(d ** 2))


def estimate_lambda(x: np.ndarray, spacing: int = 3, max_lambda: float = 100.0) -> tuple[float, float]:
    """The motion prior's weight for the series ``x`` (N, d) sampled once per frame (module docstring): returns
    ``(lam, sigma_m)``, ``sigma_m`` the per-frame white noise per component (units of ``x``). ``lam`` is clipped to
    ``[0, max_lambda]``; ``max_lambda`` where the second differences do not grow with the spacing (no smooth motion
    is measurable). Needs ``N > 2 spacing``."""
    x = np.asarray(x, dtype=np.float64).reshape(len(x), -1)
    v1, vk = _second_difference_variance(x, 1), _second_difference_variance(x, spacing)
    var_a = (vk - v1) / (spacing ** 4 - 1)
    var_m = max((v1 - max(var_a, 0.0)) / 6.0, 0.0)
    if var_a <= 0:
        return (max_lambda if var_m > 0 else 0.0), float(np.sqrt(var_m))
    return float(min(var_m / var_a, max_lambda)), float(np.sqrt(var_m))


def whittaker(x: np.ndarray, lam: float, t: np.ndarray | None = None, keep_first: bool = False) -> np.ndarray:
    """Solve ``(I + lam D^T D) y = x`` for ``y`` (N, d), ``D`` the second difference at the frames' times ``t``
    (N,) seconds (None: evenly spaced), scaled to the median frame interval so ``lam`` means the same per frame.
    A series linear in ``t`` is returned unchanged (``D`` removes it). ``keep_first``: ``y_0 = x_0`` (the first
    row's measurement is taken as exact; the others solve the same problem with it fixed)."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl

    x = np.asarray(x, dtype=np.float64)
    n = len(x)
    if lam <= 0 or n < 3:
        return x.copy()
    t = np.arange(n, dtype=np.float64) if t is None else np.asarray(t, dtype=np.float64)
    h = np.diff(t)
    if np.any(h <= 0):
        raise ValueError("whittaker: times must increase")
    h0, h1 = h[:-1], h[1:]
    scale = float(np.median(h)) ** 2
    # second derivative at the interior frames, non-uniform spacing, times the median interval squared
    c0 = 2.0 / (h0 * (h0 + h1)) * scale
    c2 = 2.0 / (h1 * (h0 + h1)) * scale
    rows = np.repeat(np.arange(n - 2), 3)
    cols = (np.arange(n - 2)[:, None] + np.arange(3)[None, :]).ravel()
    vals = np.stack([c0, -(c0 + c2), c2], 1).ravel()
    D = sp.csr_matrix((vals, (rows, cols)), shape=(n - 2, n))
    A = (sp.identity(n, format="csc") + lam * (D.T @ D)).tocsc()
    X = x.reshape(n, -1)
    if not keep_first:
        return np.asarray(spl.splu(A).solve(X)).reshape(x.shape)
    # y_0 fixed: the remaining rows' system with y_0's column moved to the right-hand side
    Y = np.empty_like(X)
    Y[0] = X[0]
    Y[1:] = spl.splu(A[1:, 1:].tocsc()).solve(X[1:] - A[1:, [0]].toarray() * X[0][None, :])
    return Y.reshape(x.shape)


def _quaternions(R: np.ndarray) -> np.ndarray:
    """(N, 3, 3) rotations -> (N, 4) unit quaternions, signs chosen so consecutive ones agree."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R).as_quat()
    for i in range(1, len(q)):
        if np.dot(q[i], q[i - 1]) < 0:
            q[i] = -q[i]
    return q


def smooth_trajectory(poses: np.ndarray, timestamps: np.ndarray | None = None,
                      cfg: SmoothingConfig = SmoothingConfig()) -> Smoothing:
    """The trajectory ``poses`` (N, 4, 4) ``T_w_c`` (world frame, metres) at ``timestamps`` (N,) seconds (None:
    evenly spaced) smoothed under the motion prior (module docstring); the first pose, which defines the world
    frame (identity or the given start pose), stays as it is. Returns it unchanged (``applied`` False) when
    smoothing is off, the trajectory is too short to measure its noise (``N <= 2 spacing + 2``), a pose is not
    finite, or the times do not increase."""
    from scipy.spatial.transform import Rotation

    P = np.asarray(poses, dtype=np.float64)
    n = len(P)
    if not cfg.enabled or n <= 2 * cfg.spacing + 2:
        return Smoothing(P.copy())
    if not np.all(np.isfinite(P)):
        log.warning("trajectory smoothing skipped: a pose is not finite")
        return Smoothing(P.copy())
    t = None if timestamps is None else np.asarray(timestamps, dtype=np.float64)
    if t is not None and np.any(np.diff(t) <= 0):
        log.warning("trajectory smoothing skipped: the frames' timestamps do not increase")
        return Smoothing(P.copy())
    out = P.copy()
    lam_t, noise = estimate_lambda(P[:, :3, 3], cfg.spacing, cfg.max_lambda)
    out[:, :3, 3] = whittaker(P[:, :3, 3], lam_t, t, keep_first=True)
    lam_r = 0.0
    if cfg.rotations:
        q = _quaternions(P[:, :3, :3])
        lam_r, _ = estimate_lambda(q, cfg.spacing, cfg.max_lambda)
        qs = whittaker(q, lam_r, t, keep_first=True)
        out[1:, :3, :3] = Rotation.from_quat(qs[1:] / np.linalg.norm(qs[1:], axis=1, keepdims=True)).as_matrix()
    moved = float(np.max(np.linalg.norm(out[:, :3, 3] - P[:, :3, 3], axis=1)))
    return Smoothing(out, lam_t, lam_r, noise, moved, applied=True)
