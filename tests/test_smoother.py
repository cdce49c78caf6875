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


def test_whittaker_solves_its_normal_equations_and_keeps_a_constant_velocity_path():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.02, 0.05, 60))                     # uneven frame times, as TUM drops frames
    line = np.stack([0.3 * t - 1.0, -0.2 * t, 0.05 * t + 2.0], 1)   # constant velocity: no second difference
    assert np.allclose(whittaker(line, 50.0, t), line, atol=1e-12)
    x = rng.normal(size=(60, 3))
    y = whittaker(x, 7.0)                                            # evenly spaced: D is (1, -2, 1)
    D = np.zeros((58, 60))
    for i in range(58):
        D[i, i:i + 3] = (1.0, -2.0, 1.0)
    assert np.allclose((np.eye(60) + 7.0 * D.T @ D) @ y, x, atol=1e-10)
    assert np.array_equal(whittaker(x, 0.0), x)
    # the first row kept: the same normal equations on the other rows, with y_0 = x_0
    z = whittaker(x, 7.0, keep_first=True)
    assert np.array_equal(z[0], x[0])
    assert np.allclose(((np.eye(60) + 7.0 * D.T @ D) @ z - x)[1:], 0.0, atol=1e-10)


def test_the_noise_estimate_recovers_the_per_frame_noise_of_a_smooth_path():
    rng = np.random.default_rng(1)
    n = 2000
    i = np.arange(n)
    truth = np.stack([0.3 * np.sin(2 * np.pi * i / 300), 0.2 * np.cos(2 * np.pi * i / 450), 0.001 * i], 1)
    for sigma in (0.001, 0.003):
        lam, est = estimate_lambda(truth + rng.normal(scale=sigma, size=truth.shape), spacing=3)
        assert est == pytest.approx(sigma, rel=0.15)
        assert lam > 1.0
    # a noise-free path: nothing to smooth
    lam, est = estimate_lambda(truth, spacing=3)
    assert lam < 1e-3 and est < 1e-5


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
    assert out.applied and out.moved_m < 5e-4
    assert np.allclose(out.poses[:, :3, :3], orbit[:, :3, :3], atol=1e-3)


def test_smoothing_leaves_what_it_cannot_measure_as_it_was():
    rng = np.random.default_rng(3)
    P = _poses(rng.normal(size=(8, 3)))
    for poses, cfg, ts in ((P, SmoothingConfig(), None),                           # too short for spacing 3
                           (_poses(rng.normal(size=(40, 3))), SmoothingConfig(enabled=False), None),
                           (_poses(rng.normal(size=(40, 3))), SmoothingConfig(), np.zeros(40))):   # times stand
        out = smooth_trajectory(poses, ts, cfg)
        assert not out.applied and np.array_equal(out.poses, poses)
    bad = _poses(rng.normal(size=(40, 3)))
    bad[5, 0, 3] = np.nan
    out = smooth_trajectory(bad)
    assert not out.applied and np.array_equal(out.poses, bad, equal_nan=True)
