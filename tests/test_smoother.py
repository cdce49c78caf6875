"""The final trajectory smoothing (lrslam.backend.smoother): the closed forms exactly, the noise estimate and the
smoothing against known truth with thresholds."""

from __future__ import annotations

import numpy as np
import pytest

from lrslam.backend.smoother import SmoothingConfig, estimate_lambda, smooth_trajectory, whittaker


def _poses(positions: np.ndarray, yaw: np.ndarray | None = None) -> np.ndarray:
    """(N, 3) camera centres (and yaw angles, rad) -> (N, 4, 4) ``T_w_c``."""
    n = len(positions)
    P = np.tile(np.eye(4), (n, 1, 1))
    P[:, :3, 3] = positions
    if yaw is not None:
        c, s = np.cos(yaw), np.sin(yaw)
        P[:, 0, 0], P[:, 0, 1], P[:, 1, 0], P[:, 1, 1] = c, -s, s, c
    return P


def _divided_differences(t: np.ndarray) -> np.ndarray:
    """The second-derivative matrix at uneven times, built row by row from the textbook divided differences,
    times the median interval squared: (N - 2, N)."""
    n, h = len(t), np.median(np.diff(t))
    D = np.zeros((n - 2, n))
    for i in range(1, n - 1):
        a, b = t[i] - t[i - 1], t[i + 1] - t[i]
        D[i - 1, i - 1:i + 2] = (2 / (a * (a + b)), -2 / (a * b), 2 / (b * (a + b)))
    return D * h * h


def test_whittaker_solves_its_normal_equations_and_keeps_a_constant_velocity_path():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.02, 0.05, 60))                     # uneven frame times, as TUM drops frames
    line = np.stack([0.3 * t - 1.0, -0.2 * t, 0.05 * t + 2.0], 1)   # constant velocity: no second difference
    assert np.allclose(whittaker(line, 50.0, t), line, atol=1e-12)
    x = rng.normal(size=(60, 3))
    D = _divided_differences(t)
    y = whittaker(x, 7.0, t)
    assert np.allclose((np.eye(60) + 7.0 * D.T @ D) @ y, x, atol=1e-10)
    # the same times in another unit give the same result; evenly spaced times are the (1, -2, 1) default
    assert np.allclose(whittaker(x, 7.0, 1000.0 * t), y, atol=1e-10)
    assert np.allclose(whittaker(x, 7.0, 0.033 * np.arange(60)), whittaker(x, 7.0), atol=1e-12)
    assert np.array_equal(whittaker(x, 0.0, t), x)
    # the first row kept: the same normal equations on the other rows, with y_0 = x_0
    z = whittaker(x, 7.0, t, keep_first=True)
    assert np.array_equal(z[0], x[0])
    assert np.allclose(((np.eye(60) + 7.0 * D.T @ D) @ z - x)[1:], 0.0, atol=1e-10)
    for bad in (np.nan, -1.0, np.inf):
        with pytest.raises(ValueError, match="lam"):
            whittaker(x, bad)
    with pytest.raises(ValueError, match="increasing"):
        whittaker(x, 1.0, np.r_[t[:-1], np.nan])


def test_the_noise_estimate_recovers_the_per_frame_noise_and_the_weight_of_a_smooth_path():
    rng = np.random.default_rng(1)
    n = 2000
    i = np.arange(n)
    truth = np.stack([0.3 * np.sin(2 * np.pi * i / 60), 0.2 * np.cos(2 * np.pi * i / 90), 0.001 * i], 1)
    # the motion's own second difference per frame, per component, over the path
    var_a = float(np.mean(np.diff(truth, 2, axis=0) ** 2))
    for sigma in (0.0005, 0.002):
        lam, est = estimate_lambda(truth + rng.normal(scale=sigma, size=truth.shape), max_lambda=1e9)
        assert est == pytest.approx(sigma, rel=0.15)
        assert lam == pytest.approx(sigma ** 2 / var_a, rel=0.3)
    # a noise-free path: nothing to smooth; dropped frames (every 7th) are not mistaken for noise
    assert estimate_lambda(truth)[0] < 0.01
    keep = i % 7 != 3
    assert estimate_lambda(truth[keep], t=i[keep] / 30.0)[0] < 0.01
    assert estimate_lambda(truth[keep])[0] > 1.0                     # it would be without the frames' times
    with pytest.raises(ValueError, match="needs more than"):
        estimate_lambda(truth[:6], spacing=3)
    with pytest.raises(ValueError, match="spacing"):
        estimate_lambda(truth, spacing=1)


def test_smoothing_removes_per_frame_noise_and_leaves_a_fast_clean_orbit_alone():
    rng = np.random.default_rng(2)
    n = 300
    a = np.linspace(0, 2 * np.pi, n)
    slow = np.stack([0.5 * np.cos(a), 0.5 * np.sin(a), 0.1 * np.sin(3 * a)], 1)   # 1 cm per frame
    noisy = _poses(slow + rng.normal(scale=0.003, size=slow.shape))
    out = smooth_trajectory(noisy)
    err_before = np.sqrt(np.mean(np.sum((noisy[:, :3, 3] - slow) ** 2, 1)))
    err_after = np.sqrt(np.mean(np.sum((out.poses[:, :3, 3] - slow) ** 2, 1)))
    assert out.applied and err_after < 0.6 * err_before
    assert np.array_equal(out.poses[0], noisy[0])                    # the world frame stays the first camera's
    assert np.allclose(out.poses[:, :3, :3], noisy[:, :3, :3])      # rotations kept unless asked
    # 6 cm and 2.4 deg per frame on a circle, no noise: moves under half a millimetre
    b = np.arange(72) * np.deg2rad(2.4)
    orbit = _poses(np.stack([1.4 * np.cos(b), 1.4 * np.sin(b), np.zeros_like(b)], 1), yaw=b)
    out = smooth_trajectory(orbit, cfg=SmoothingConfig(rotations=True))
    assert out.moved_m < 5e-4
    assert np.allclose(out.poses[:, :3, :3], orbit[:, :3, :3], atol=1e-3)


def test_rotations_are_smoothed_through_full_turns_when_asked():
    rng = np.random.default_rng(4)
    n = 400
    yaw = np.linspace(0, 4 * np.pi, n)                               # two full turns: quaternion signs flip
    truth = _poses(np.zeros((n, 3)), yaw=yaw)
    noisy = _poses(rng.normal(scale=0.002, size=(n, 3)), yaw=yaw + rng.normal(scale=np.deg2rad(0.5), size=n))
    out = smooth_trajectory(noisy, cfg=SmoothingConfig(rotations=True))

    def angle_rms(P):
        c = np.clip((np.einsum("nij,nij->n", P[:, :3, :3], truth[:, :3, :3]) - 1) / 2, -1, 1)
        return np.degrees(np.sqrt(np.mean(np.arccos(c) ** 2)))

    assert out.lam_r > 0 and angle_rms(out.poses) < 0.6 * angle_rms(noisy)
    assert np.array_equal(out.poses[0], noisy[0])
    R = out.poses[:, :3, :3]
    assert np.allclose(np.einsum("nji,njk->nik", R, R), np.eye(3), atol=1e-9)


def test_smoothing_leaves_what_it_cannot_measure_as_it_was():
    rng = np.random.default_rng(3)
    cfg = SmoothingConfig(min_frames=9)                               # spacing 3: 2 * 3 + 3 = 9 frames at least
    P8 = _poses(rng.normal(size=(8, 3)))
    assert not smooth_trajectory(P8, cfg=cfg).applied
    assert smooth_trajectory(_poses(rng.normal(size=(9, 3))), cfg=cfg).applied
    long = _poses(rng.normal(size=(40, 3)))
    for ts, c in ((None, SmoothingConfig(enabled=False)), (np.zeros(40), cfg), (np.arange(39.0), cfg),
                  (np.r_[np.arange(39.0), np.nan], cfg)):
        out = smooth_trajectory(long, ts, c)
        assert not out.applied and np.array_equal(out.poses, long)
    # a clean constant-velocity path: no noise measured, nothing applied
    line = _poses(np.outer(np.arange(40.0), [0.01, 0.0, 0.002]))
    assert not smooth_trajectory(line).applied
    bad = long.copy()
    bad[5, 0, 3] = np.nan
    out = smooth_trajectory(bad)
    assert not out.applied and np.array_equal(out.poses, bad, equal_nan=True)
