"""Pairwise registration (Open3D hybrid RGB-D odometry, Open3D ICP, KISS-ICP) on a ray-cast synthetic room."""

from __future__ import annotations

import re

import numpy as np
import pytest

from frontend_fixtures import T_W_C_REF, look_at, make_frame, make_room
from lrslam.frame import Frame
from lrslam.frontend.registration import (RegistrationConfig, RegistrationGates, fallback_information,
                                          register_rgbd)
from lrslam.frontend.rgbd_view import as_view, assess_alignment
from lrslam.geometry import adjoint
from lrslam.geometry import pose_error, random_pose

# Acceptance: 2 mm / 0.2 deg. Open3D's hybrid RGB-D odometry alone is biased by its nearest-pixel photometric
# association (1-3.4 mm at 320x240); with the point-to-plane polish it meets 2 mm. KISS-ICP is point-to-point on
# voxelised points (no normals, no colour): looser.
CASES = {
    "rgbd": ({"method": "rgbd"}, (0.004, 0.2)),
    "rgbd+polish": ({"method": "rgbd", "refine_iterations": 10}, (0.002, 0.2)),
    "icp": ({"method": "icp"}, (0.002, 0.2)),
    "icp-colored": ({"method": "icp", "icp_estimation": "colored"}, (0.002, 0.2)),
    "kiss": ({"method": "kiss"}, (0.005, 0.5)),
}
GATES = RegistrationGates()


@pytest.fixture(scope="module")
def room():
    return make_room()


@pytest.fixture(scope="module")
def pairs(room):
    """Three (source, target, true T_tgt_src) pairs at 320x240, relative motion up to 5 cm / 3 deg."""
    rng = np.random.default_rng(1)
    out = []
    for _ in range(3):
        T_rel = random_pose(rng, 0.05, 3.0)
        target = make_frame(room, T_W_C_REF, index=0)
        source = make_frame(room, T_W_C_REF @ T_rel, index=1)
        out.append((source, target, T_rel))
    return out


@pytest.mark.parametrize("case", list(CASES))
def test_recovers_known_motion(case, pairs):
    kwargs, (max_t, max_r) = CASES[case]
    cfg = RegistrationConfig(**kwargs)
    for source, target, T_true in pairs:
        res = register_rgbd(source, target, np.eye(4), cfg, GATES)
        assert res.ok, res.reason
        d_t, d_r = pose_error(res.T_tgt_src, T_true)
        assert d_t < max_t and d_r < max_r, (case, d_t, d_r)
        assert res.fitness > 0.8 and res.inlier_rmse < 0.01
        info = res.information
        np.testing.assert_allclose(info, info.T)
        assert np.linalg.eigvalsh(info)[0] > 0


def test_information_matches_open3d(pairs):
    """Our information (right perturbation, source points) is Open3D's (left perturbation, target points)
    moved by the adjoint: ``H = Ad_T^T H_o3d Ad_T`` (both un-normalised, same projective association)."""
    import open3d as o3d

    source, target, T = pairs[0]
    src, tgt = as_view(source), as_view(target)
    sigma = 0.01
    q = assess_alignment(src, tgt, T, max_distance=0.03, depth_min=0.1, depth_max=4.0, sigma_m=sigma, stride=1)
    H_ours = q.information * q.n_inliers * sigma**2
    depth = [o3d.t.geometry.Image(np.ascontiguousarray(v.depth[..., None])) for v in (src, tgt)]
    H_o3d = o3d.t.pipelines.odometry.compute_odometry_information_matrix(
        depth[0], depth[1], o3d.core.Tensor(tgt.K), o3d.core.Tensor(T), 0.03, 1.0, 4.0).numpy().astype(float)
    n_o3d = np.trace(H_o3d[3:, 3:]) / 3  # the translation block is N * I
    assert abs(n_o3d - q.n_inliers) < 0.01 * q.n_inliers
    H_right = adjoint(T).T @ H_o3d @ adjoint(T)
    np.testing.assert_allclose(H_ours / q.n_inliers, H_right / n_o3d, rtol=0.02,
                               atol=0.02 * np.abs(H_right).max() / n_o3d)


def _blank(frame: Frame, depth_value: float | None) -> Frame:
    """Same camera, uniform grey image; depth a flat wall at ``depth_value`` m (None: no depth at all)."""
    depth = np.zeros_like(frame.depth) if depth_value is None else np.full_like(frame.depth, depth_value)
    return Frame(index=frame.index, timestamp=frame.timestamp, rgb=np.full_like(frame.rgb, 128), depth=depth,
                 K=frame.K)


@pytest.mark.parametrize("method", ["rgbd", "icp", "kiss"])
@pytest.mark.parametrize("depth_value, expected", [(None, "no valid depth"), (2.0, "featureless|degenerate")])
def test_unusable_frames_fail_gracefully(method, depth_value, expected, pairs):
    """No depth at all, or a blank frame (uniform grey flat wall): ok False with the reason, no exception."""
    source, target, _ = pairs[0]
    init = random_pose(np.random.default_rng(2), 0.05, 3.0)
    res = register_rgbd(_blank(source, depth_value), target, init, RegistrationConfig(method=method), GATES)
    assert not res.ok
    assert re.search(expected, res.reason), res.reason
    np.testing.assert_array_equal(res.T_tgt_src, init)  # falls back to the initial guess
    np.testing.assert_array_equal(res.information, fallback_information(GATES))


def test_unrelated_views_are_rejected(room, pairs):
    """A view of the opposite side of the room does not register: the gates say so."""
    _, target, _ = pairs[0]
    other = make_frame(room, look_at(np.array([0.4, -0.3, 1.0]), np.array([0.5, 0.3, -2.0])), index=5)
    for method in ("rgbd", "icp"):
        res = register_rgbd(other, target, np.eye(4), RegistrationConfig(method=method), GATES)
        assert not res.ok and res.reason, method


def test_mismatched_cameras_are_reported_not_raised(pairs):
    source, target, _ = pairs[0]
    K = source.K.copy()
    K[0, 0] *= 1.1
    odd = Frame(index=1, timestamp=0.0, rgb=source.rgb, depth=source.depth, K=K)
    res = register_rgbd(odd, target, np.eye(4), RegistrationConfig(method="rgbd"), GATES)
    assert not res.ok and "same camera" in res.reason


def test_bad_arrays_are_one_line_errors(pairs):
    source, target, _ = pairs[0]
    with pytest.raises(ValueError, match="rgb must be"):
        register_rgbd(Frame(0, 0.0, source.rgb[:, :10], source.depth, source.K), target, np.eye(4),
                      RegistrationConfig(), GATES)
    with pytest.raises(ValueError, match="rigid"):
        register_rgbd(source, target, np.zeros((4, 4)), RegistrationConfig(), GATES)


def test_config_is_validated():
    with pytest.raises(ValueError, match="depth_min"):
        RegistrationConfig(depth_min=5.0, depth_max=4.0)
    with pytest.raises(ValueError, match="iterations"):
        RegistrationConfig(iterations=())
    with pytest.raises(ValueError):
        RegistrationConfig(metod="icp")  # typo -> rejected
    with pytest.raises(ValueError):
        RegistrationConfig(min_fitness=0.5)  # a gate, not a registration setting
    with pytest.raises(ValueError):
        RegistrationGates(method="icp")  # a registration setting, not a gate


def test_loop_registration_from_a_drifted_guess(pairs):
    """Registration starts from a wrong initial guess (drift) and still converges."""
    source, target, T_true = pairs[1]
    guess = T_true @ random_pose(np.random.default_rng(4), 0.04, 2.0)
    res = register_rgbd(source, target, guess, RegistrationConfig(**CASES["rgbd+polish"][0]), GATES)
    assert res.ok
    d_t, d_r = pose_error(res.T_tgt_src, T_true)
    assert d_t < 0.002 and d_r < 0.2


def test_downsampled_view_keeps_geometry():
    """Half-resolution copy of a slanted plane: back-projected points stay on the plane (intrinsics rescaled
    about pixel centres, depth averaged per block)."""
    from lrslam.camera import backproject_depth, intrinsics_matrix
    from lrslam.frontend.rgbd_view import RGBDView

    K = intrinsics_matrix(200.0, 200.0, 79.5, 59.5)
    n, d0 = np.array([0.3, -0.2, 1.0]), 2.0  # plane n . p = d0
    rays = backproject_depth(np.ones((120, 160)), K)
    depth = (d0 / (rays @ n)).astype(np.float32)
    half = RGBDView(np.zeros((120, 160, 3), np.uint8), depth, K).downsampled(2)
    assert half.depth.shape == (60, 80)
    p = backproject_depth(half.depth, half.K).reshape(-1, 3)
    assert np.abs(p @ n - d0).max() < 2e-4 * d0
