"""The run's final trajectory smoothed under a motion prior, with the prior's weight measured from the trajectory.

Every frame's pose is estimated from its own images, so each carries an error of its own, independent from frame
to frame, on top of the slowly varying drift the pose graph works on. A hand-held or robot-carried camera does
not jerk at 30 Hz. Per component of the camera centre, the smoothed values ``y`` of the run's ``x`` are the
penalised least-squares solution

    minimise  sum_i (y_i - x_i)^2 / sigma_m^2  +  sum_i (second difference of y at i)^2 / sigma_a^2,

a Whittaker smoother, ``(I + lam D^T D) y = x`` with ``lam = sigma_m^2 / sigma_a^2``: the maximum a posteriori
estimate under a discrete white-noise-on-acceleration prior (the motion priors of continuous-time trajectory
estimation, Barfoot, Tong and Sarkka, RSS 2014, in their simplest discrete form). ``D`` is the second derivative
at the frames' own times (dropped frames allowed), scaled to the median frame interval.

Nothing is tuned per sequence: ``lam`` comes from the trajectory's own second differences at two spacings (a
structure function, as the Allan variance separates white noise from a signal). White per-frame noise adds
``6 sigma_m^2`` to the variance of the second difference at any spacing ``k``; a motion that is smooth over ``2k``
frames (locally constant acceleration, what a camera's motion is at 30 Hz) adds ``k^4 sigma_a^2``, ``sigma_a^2``
being the variance of its second difference per frame. From spacing 1 and ``spacing``:

    sigma_a^2 = (V_k - V_1) / (k^4 - 1),   sigma_m^2 = (V_1 - sigma_a^2) / 6.

(If the motion's second differences were independent, as the prior says, ``V_k`` would grow as ``(2k^3 + k) / 3``
instead and ``lam`` would come out about 4x smaller at ``k = 3``: measured on the real sequences, that smooths
less and helps less; docs/BENCHMARKS.md section 27.) Where the frames hold no measurable noise (a fast smooth
orbit) ``lam`` comes out near 0 and the trajectory stays as it was; where the per-frame noise dominates the
frame-to-frame motion (a slow hand-held camera) it is larger. Positions are smoothed in the world frame;
rotations, when asked, as unit quaternions made sign-continuous, with their own ``lam``, and re-normalised. The
first pose (it defines the world frame) stays. Numpy and scipy only; poses ``T_w_c`` (4, 4) float64 in, the same
out.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np
from pydantic import Field

from lrslam.config import StrictModel

__all__ = ["SmoothingConfig", "Smoothing", "estimate_lambda", "second_difference_matrix", "whittaker",
           "smooth_trajectory"]

log = logging.getLogger(__name__)

_NO_NOISE = 1e-9   # per-frame noise below this (units of the series: metres, quaternion units) is rounding


class SmoothingConfig(StrictModel):
    """The final trajectory's smoothing (:mod:`lrslam.backend.smoother`).

    enabled: smooth the trajectory a run returns (the poses as tracked are kept beside it,
    ``trajectory_unsmoothed.txt``). spacing: the second spacing of the noise estimate, in frames (the motion is
    taken as smooth over ``2 spacing`` frames). min_frames: shorter trajectories are left as they are (too few
    second differences to measure the noise). max_lambda: the prior's largest weight (dimensionless, per median
    frame interval; where no smooth motion is measurable at all; 100 halves a wave with a period of ~20 frames).
    rotations: smooth the rotations too, with their own weight (off: on 7-Scenes every 4th frame it raised the
    frame-to-frame rotation error against the reference, 0.36 -> 0.60 deg; docs/BENCHMARKS.md section 27)."""

    enabled: bool = True
    spacing: int = Field(3, ge=2, le=10)
    min_frames: int = Field(20, ge=5)
    max_lambda: float = Field(100.0, gt=0)
    rotations: bool = False


@dataclass(frozen=True)
class Smoothing:
    """What :func:`smooth_trajectory` did. ``poses``: (N, 4, 4) ``T_w_c``; ``lam_t`` / ``lam_r``: the prior's
    weight for positions / rotations (0: left as they were); ``noise_m``: the per-frame position noise it measured
    (metres, per axis); ``moved_m``: the largest position change (metres); ``applied``: whether any pose changed
    (a weight above 0)."""

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


def _times(t: np.ndarray | None, n: int) -> np.ndarray:
    """Frame times (n,) seconds, checked (finite, increasing); None -> evenly spaced. ValueError otherwise."""
    if t is None:
        return np.arange(n, dtype=np.float64)
    t = np.asarray(t, dtype=np.float64)
    if t.shape != (n,):
        raise ValueError(f"times: expected shape ({n},), got {t.shape}")
    if not np.all(np.isfinite(t)) or np.any(np.diff(t) <= 0):
        raise ValueError("times must be finite and increasing")
    return t


def _second_difference_weights(t: np.ndarray, k: int) -> tuple[np.ndarray, np.ndarray]:
    """Weights ``(c0, c2)`` (N - 2k,) of frames ``i - k`` and ``i + k`` (frame ``i`` takes ``-(c0 + c2)``) in the
    second derivative at every frame ``i`` at times ``t``, times ``(k h)^2`` with ``h`` the median frame interval:
    ``(1, -2, 1)`` at even spacing."""
    h0, h1 = t[k:-k] - t[:-2 * k], t[2 * k:] - t[k:-k]
    s = (k * float(np.median(np.diff(t)))) ** 2
    return 2.0 * s / (h0 * (h0 + h1)), 2.0 * s / (h1 * (h0 + h1))


def _second_differences(x: np.ndarray, t: np.ndarray, k: int) -> np.ndarray:
    """Second derivative of ``x`` (N, d) at every frame from frames ``k`` apart (weights of
    :func:`_second_difference_weights`): ``x_{i+k} - 2 x_i + x_{i-k}`` at even spacing. (N - 2k, d)."""
    c0, c2 = _second_difference_weights(t, k)
    return c0[:, None] * x[:-2 * k] - (c0 + c2)[:, None] * x[k:-k] + c2[:, None] * x[2 * k:]


def second_difference_matrix(t: np.ndarray):
    """The rows of :func:`_second_differences` at spacing 1 for frame times ``t`` (N,) seconds, as a scipy sparse
    (N - 2, N) matrix: ``(1, -2, 1)`` at even spacing."""
    import scipy.sparse as sp

    n = len(t)
    c0, c2 = _second_difference_weights(t, 1)
    rows = np.repeat(np.arange(n - 2), 3)
    cols = (np.arange(n - 2)[:, None] + np.arange(3)[None, :]).ravel()
    return sp.csr_matrix((np.stack([c0, -(c0 + c2), c2], 1).ravel(), (rows, cols)), shape=(n - 2, n))


def estimate_lambda(x: np.ndarray, t: np.ndarray | None = None, spacing: int = 3,
                    max_lambda: float = 100.0) -> tuple[float, float]:
    """The motion prior's weight for the series ``x`` (N, d), one row per frame at times ``t`` (N,) seconds (None:
    evenly spaced): returns ``(lam, sigma_m)``, ``sigma_m`` the per-frame white noise per component (units of
    ``x``), from the second differences at spacing 1 and ``spacing`` (module docstring). ``lam`` is clipped to
    ``[0, max_lambda]``; ``max_lambda`` where the second differences do not grow with the spacing (no smooth
    motion is measurable), 0 for a noise-free series (noise under 1e-9). ValueError: ``spacing < 2``,
    ``N <= 2 spacing``, bad times."""
    x = np.asarray(x, dtype=np.float64)
    x = x.reshape(len(x), -1)
    if spacing < 2:
        raise ValueError(f"spacing must be at least 2, got {spacing}")
    if len(x) <= 2 * spacing:
        raise ValueError(f"{len(x)} frames: the noise estimate at spacing {spacing} needs more than {2 * spacing}")
    t = _times(t, len(x))
    v1 = float(np.mean(_second_differences(x, t, 1) ** 2))
    vk = float(np.mean(_second_differences(x, t, spacing) ** 2))
    var_a = (vk - v1) / (spacing ** 4 - 1)
    var_m = max((v1 - max(var_a, 0.0)) / 6.0, 0.0)
    if var_m <= _NO_NOISE ** 2:          # rounding only (a noise-free series): nothing to smooth
        return 0.0, math.sqrt(var_m)
    if var_a <= 0:
        return max_lambda, math.sqrt(var_m)
    return float(min(var_m / var_a, max_lambda)), math.sqrt(var_m)


def whittaker(x: np.ndarray, lam: float, t: np.ndarray | None = None, keep_first: bool = False) -> np.ndarray:
    """Solve ``(I + lam D^T D) y = x`` for ``y`` (N, d), ``D`` the second derivative at the frames' times ``t``
    (N,) seconds (None: evenly spaced), scaled to the median frame interval squared so ``lam`` means the same per
    frame (at even spacing ``D`` is the second difference ``(1, -2, 1)``). A series linear in ``t`` is returned
    unchanged. ``keep_first``: ``y_0 = x_0`` (the first row's measurement is taken as exact; the others solve the
    same problem with it fixed). ValueError: ``lam`` negative or not finite, bad times."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spl

    if not (math.isfinite(lam) and lam >= 0):
        raise ValueError(f"lam must be finite and >= 0, got {lam}")
    x = np.asarray(x, dtype=np.float64)
    n = len(x)
    t = _times(t, n)
    if lam == 0 or n < 3:
        return x.copy()
    D = second_difference_matrix(t)
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
    smoothing is off, the trajectory is shorter than ``cfg.min_frames`` (or ``2 spacing + 3``), the estimate finds
    no noise, or (logged) a pose is not finite or the timestamps are not finite and increasing."""
    from scipy.spatial.transform import Rotation

    P = np.asarray(poses, dtype=np.float64)
    n = len(P)
    if not cfg.enabled or n < max(cfg.min_frames, 2 * cfg.spacing + 3):
        return Smoothing(P.copy())
    if not np.all(np.isfinite(P)):
        log.warning("trajectory smoothing skipped: a pose is not finite")
        return Smoothing(P.copy())
    try:
        t = _times(timestamps, n)
    except ValueError as e:
        log.warning("trajectory smoothing skipped: the frames' %s", e)
        return Smoothing(P.copy())
    out = P.copy()
    lam_t, noise = estimate_lambda(P[:, :3, 3], t, cfg.spacing, cfg.max_lambda)
    out[:, :3, 3] = whittaker(P[:, :3, 3], lam_t, t, keep_first=True)
    lam_r = 0.0
    if cfg.rotations:
        q = _quaternions(P[:, :3, :3])
        lam_r, _ = estimate_lambda(q, t, cfg.spacing, cfg.max_lambda)
        if lam_r > 0:
            qs = whittaker(q, lam_r, t, keep_first=True)[1:]
            out[1:, :3, :3] = Rotation.from_quat(qs / np.linalg.norm(qs, axis=1, keepdims=True)).as_matrix()
    moved = float(np.max(np.linalg.norm(out[:, :3, 3] - P[:, :3, 3], axis=1)))
    return Smoothing(out, lam_t, lam_r, noise, moved, applied=lam_t > 0 or lam_r > 0)
