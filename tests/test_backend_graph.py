"""Pose-graph backend: GTSAM conversions, circle recovery, loop closure on a drifting trajectory, robustness."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from lrslam.backend.conversions import gaussian_from_information, key, pose_from_gtsam, pose_to_gtsam
from lrslam.backend.graph import GraphConfig, PoseGraph
from lrslam.errors import InputError
from lrslam.geometry import adjoint, diagonal_information
from lrslam.geometry import exp_se3, inv, log_se3, make_pose, pose_error, random_pose, relative
from lrslam.evaluation.ate import compute_ate

gtsam = pytest.importorskip("gtsam")


# -- conversions -----------------------------------------------------------------------------------------------
def test_pose_roundtrip_and_adjoint_match_gtsam(rng):
    for _ in range(5):
        T = random_pose(rng, 2.0, 170.0)
        P = pose_to_gtsam(T)
        np.testing.assert_allclose(pose_from_gtsam(P), T, atol=1e-12)
        np.testing.assert_allclose(adjoint(T), P.AdjointMap(), atol=1e-12)
        np.testing.assert_allclose(gtsam.Pose3.Logmap(P), log_se3(T), atol=1e-9)


def test_between_factor_is_a_right_perturbation(rng):
    """BetweenFactor(i, j, Z) error = Logmap(Z^-1 X_i^-1 X_j): a measurement Z = T_i_j exp(-xi) gives error xi,
    so an information matrix for ``T_i_j exp(xi)`` (what the frontend returns) is used as is."""
    Xi, Xj = random_pose(rng, 1.0, 60.0), random_pose(rng, 1.0, 60.0)
    xi = np.array([0.01, -0.02, 0.015, 0.03, -0.01, 0.02])
    Z = relative(Xi, Xj) @ exp_se3(-xi)
    factor = gtsam.BetweenFactorPose3(key(0), key(1), pose_to_gtsam(Z), gtsam.noiseModel.Unit.Create(6))
    values = gtsam.Values()
    values.insert(key(0), pose_to_gtsam(Xi))
    values.insert(key(1), pose_to_gtsam(Xj))
    np.testing.assert_allclose(factor.unwhitenedError(values), xi, atol=1e-9)


def test_information_becomes_gaussian_noise():
    A = np.random.default_rng(3).normal(size=(6, 6))
    info = A @ A.T + 6 * np.eye(6)
    noise = gaussian_from_information(info)
    np.testing.assert_allclose(noise.R().T @ noise.R(), info, rtol=1e-10, atol=1e-9)
    with pytest.raises(InputError, match="positive definite"):
        gaussian_from_information(np.diag([1, 1, 1, 1, 1, 0.0]))
    with pytest.raises(InputError, match="6x6"):
        gaussian_from_information(np.eye(3))


# -- circle (GTSAM's circlePose3 example) -------------------------------------------------------------------------
def _circle_truth(n: int = 8) -> list[np.ndarray]:
    from gtsam.utils.circlePose3 import circlePose3

    values = circlePose3(n, 1.0, "x")
    return [pose_from_gtsam(values.atPose3(key(i))) for i in range(n)]


@pytest.mark.parametrize("optimiser", ["lm", "isam2"])
def test_perturbed_circle_is_recovered(optimiser, rng):
    truth = _circle_truth()
    n = len(truth)
    graph = PoseGraph(GraphConfig(optimiser=optimiser))
    info = diagonal_information(np.radians(1.0), 0.01)
    start = {}
    for i, T in enumerate(truth):
        # 1. Nodes; perturbed starting poses (the first one is held by its prior).
        start[i] = T if i == 0 else T @ random_pose(rng, 0.15, 10.0)
        graph.add_keyframe(i, start[i])
    for i in range(n):
        # 2. Between factors from the true relative poses, closing the circle.
        j = (i + 1) % n
        factor = graph.add_loop if j == 0 else graph.add_odometry
        factor(i, j, relative(truth[i], truth[j]), info)
    # 3. Optimise from the given poses.
    est = graph.optimise(start)
    for i, T in enumerate(truth):
        d_t, d_r = pose_error(est[i], T)
        assert d_t < 1e-4 and np.radians(d_r) < 1e-4, (i, d_t, d_r)
    assert graph.n_loops == 1


# -- drifting trajectory with loops ------------------------------------------------------------------------------
N_KF = 40


def _drifting_problem(sigma_rot_deg: float, sigma_trans: float):
    """Keyframes on a 1.5 m circle (wobbling in height); odometry with a yaw bias of 0.4 deg and 4 mm per step
    plus noise at a third of the stated sigmas. Returns (truth, measured relative poses, chained initial poses,
    odometry information)."""
    rng = np.random.default_rng(0)
    truth = []
    for k in range(N_KF):
        th = 2 * np.pi * k / N_KF
        R = np.array([[np.cos(th), 0, np.sin(th)], [0, 1, 0], [-np.sin(th), 0, np.cos(th)]])
        truth.append(make_pose(R, [1.5 * np.sin(th), 0.1 * np.sin(3 * th), 1.5 * np.cos(th)]))
    s_r, s_t = np.radians(sigma_rot_deg), sigma_trans
    bias = np.array([0.0, np.radians(0.4), 0.0, 0.004, 0.0, 0.0])
    meas = [relative(truth[k], truth[k + 1])
            @ exp_se3(bias + np.concatenate([rng.normal(0, s_r / 3, 3), rng.normal(0, s_t / 3, 3)]))
            for k in range(N_KF - 1)]
    init = [truth[0]]
    for m in meas:
        init.append(init[-1] @ m)
    return truth, meas, init, diagonal_information(s_r, s_t)


def _solve(cfg, problem, loops) -> float:
    """Optimise and return the ATE RMSE (cm, Umeyama-aligned)."""
    truth, meas, init, info = problem
    graph = PoseGraph(cfg)
    for k, T in enumerate(init):
        graph.add_keyframe(k, T)
    for k, m in enumerate(meas):
        graph.add_odometry(k, k + 1, m, info)
    loop_info = diagonal_information(np.radians(0.3), 0.01)
    for i, j, T in loops:
        graph.add_loop(i, j, T, loop_info)
    est = graph.optimise(dict(enumerate(init)))
    ts = np.arange(N_KF, dtype=float)
    return compute_ate(ts, np.stack([est[k] for k in range(N_KF)]), ts, np.stack(truth)).rmse_cm


def _good_loop(truth):
    return [(0, N_KF - 1, relative(truth[0], truth[N_KF - 1]))]


def _wrong_loop(truth):
    return [(5, 25, relative(truth[5], truth[25]) @ exp_se3(np.array([0.3, 0.2, 0.1, 0.5, 0.5, 0.3])))]


@pytest.fixture(scope="module")
def stiff_problem():
    """Odometry information as confident as the frontend's (0.5 deg, 1 cm), drift beyond it."""
    return _drifting_problem(0.5, 0.01)


def test_loop_cuts_ate(stiff_problem):
    truth = stiff_problem[0]
    ate_none = _solve(GraphConfig(), stiff_problem, [])
    ate_loop = _solve(GraphConfig(), stiff_problem, _good_loop(truth))
    assert ate_none > 5.0  # the drift is real
    assert ate_loop < 0.5 * ate_none, (ate_none, ate_loop)


def test_wrong_loop_is_downweighted(stiff_problem):
    truth = stiff_problem[0]
    ate_none = _solve(GraphConfig(), stiff_problem, [])
    ate_wrong = _solve(GraphConfig(robust_kernel="huber"), stiff_problem, _wrong_loop(truth))
    ate_wrong_plain = _solve(GraphConfig(robust_kernel="none"), stiff_problem, _wrong_loop(truth))
    assert ate_wrong < 1.5 * ate_none, (ate_none, ate_wrong)
    assert ate_wrong_plain > 1.5 * ate_none  # without the kernel the same loop does blow up
    # A correct loop next to the wrong one still helps.
    ate_both = _solve(GraphConfig(), stiff_problem, _good_loop(truth) + _wrong_loop(truth))
    assert ate_both < 0.5 * ate_none


def test_gnc_rejects_wrong_loop_with_soft_odometry():
    """With realistic (soft) odometry information a Huber kernel cannot hold a wrong loop off; GNC can."""
    problem = _drifting_problem(2.0, 0.03)
    truth = problem[0]
    ate_none = _solve(GraphConfig(), problem, [])
    gnc = GraphConfig(optimiser="gnc")
    assert _solve(gnc, problem, _good_loop(truth)) < 0.5 * ate_none
    assert _solve(gnc, problem, _wrong_loop(truth)) < 1.05 * ate_none
    assert _solve(gnc, problem, _good_loop(truth) + _wrong_loop(truth)) < 0.5 * ate_none


def test_isam2_incremental_agrees_with_lm(stiff_problem):
    truth, meas, init, info = stiff_problem
    n = 12
    loop_info = diagonal_information(np.radians(0.3), 0.01)
    graphs = {opt: PoseGraph(GraphConfig(optimiser=opt)) for opt in ("lm", "isam2")}
    est = {}
    for opt, graph in graphs.items():
        for k in range(n):
            graph.add_keyframe(k, init[k])
            if k > 0:
                graph.add_odometry(k - 1, k, meas[k - 1], info)
            if k == n - 1:
                graph.add_loop(0, k, relative(truth[0], truth[k]), loop_info)
            if opt == "isam2" or k == n - 1:
                est[opt] = graph.optimise({i: init[i] for i in range(k + 1)})  # iSAM2 updates every keyframe
    lm, isam = est["lm"], est["isam2"]
    for k in range(n):
        d_t, d_r = pose_error(lm[k], isam[k])
        assert d_t < 1e-5 and d_r < 1e-3, (k, d_t, d_r)
    cov_lm = graphs["lm"].marginal_covariance(n // 2, lm)
    cov_isam = graphs["isam2"].marginal_covariance(n // 2, isam)
    # iSAM2 keeps variables that moved less than its relinearisation threshold at older linearisation points.
    np.testing.assert_allclose(cov_isam, cov_lm, rtol=1e-2, atol=1e-3 * np.abs(cov_lm).max())
    assert len(lm) == len(isam) == n  # the last optimise returned every keyframe


# -- closed forms, degenerate graphs, bad input ------------------------------------------------------------------
def test_field_factor_fuses_with_odometry_as_weighted_mean():
    """Two measurements of a pure x translation fuse to their information-weighted mean (closed form)."""
    graph = PoseGraph(GraphConfig())
    graph.add_keyframe(0, np.eye(4))
    graph.add_keyframe(1, make_pose(np.eye(3), [0.9, 0, 0]))
    graph.add_odometry(0, 1, make_pose(np.eye(3), [1.0, 0, 0]), diagonal_information(0.01, 0.1))
    graph.add_field_relative(0, 1, make_pose(np.eye(3), [1.2, 0, 0]), sigmas=(np.degrees(0.01), 0.05))
    start = {0: np.eye(4), 1: make_pose(np.eye(3), [0.9, 0, 0])}
    est = graph.optimise(start)
    x = est[1][0, 3]
    assert x == pytest.approx((1.0 / 0.1**2 + 1.2 / 0.05**2) / (1 / 0.1**2 + 1 / 0.05**2), abs=1e-6)
    # Marginal covariance of keyframe 1: translation variance 1 / (1/0.1^2 + 1/0.05^2), plus the tiny prior.
    cov = graph.marginal_covariance(1, est)
    assert cov[3, 3] == pytest.approx(1 / (1 / 0.1**2 + 1 / 0.05**2), rel=1e-3)
    # Re-stating the field measurement moves the optimum accordingly (the factor is not frozen at insertion).
    assert graph.set_measurement("field", 0, 1, make_pose(np.eye(3), [1.0, 0, 0]))
    assert graph.optimise(start)[1][0, 3] == pytest.approx(1.0, abs=1e-6)
    assert not graph.set_measurement("loop", 0, 1, np.eye(4))


def test_degenerate_graphs_do_not_crash(caplog):
    caplog.set_level(logging.INFO, logger="lrslam.backend.graph")
    graph = PoseGraph(GraphConfig())
    assert graph.optimise({}) == {}
    T0 = make_pose(np.eye(3), [1.0, 2.0, 3.0])
    graph.add_keyframe(7, T0)
    np.testing.assert_array_equal(graph.optimise({7: T0})[7], T0)
    assert graph.n_loops == 0
    assert "nothing to optimise" in caplog.text
    # Covariance of a lone keyframe is its prior's.
    np.testing.assert_allclose(np.sqrt(np.diag(graph.marginal_covariance(7, {7: T0})))[3:], 1e-5, rtol=1e-6)
    # A keyframe without any factor keeps the given pose through an optimisation.
    graph.add_keyframe(8)
    graph.add_keyframe(9)
    graph.add_odometry(7, 8, np.eye(4), np.eye(6) * 100)
    T9 = T0 @ make_pose(np.eye(3), [0.1, 0, 0])
    est = graph.optimise({7: T0, 8: T0 @ make_pose(np.eye(3), [0.05, 0, 0]), 9: T9})
    np.testing.assert_allclose(est[8], T0, atol=1e-6)
    np.testing.assert_array_equal(est[9], T9)


@pytest.mark.parametrize("optimiser", ["lm", "isam2", "gnc"])
def test_cluster_without_path_to_the_prior_recovers_once_connected(optimiser):
    """Keyframes 1-2 linked to each other but not to keyframe 0 (the prior): no crash (iSAM2 logs the
    indeterminate system and rebuilds); once linked, the optimum is exact."""
    graph = PoseGraph(GraphConfig(optimiser=optimiser))
    step = make_pose(np.eye(3), [0.5, 0.0, 0.0])
    for k in range(3):
        graph.add_keyframe(k, np.eye(4))
    start = {k: np.eye(4) for k in range(3)}
    graph.add_odometry(1, 2, step, np.eye(6) * 1e4)
    assert len(graph.optimise(start)) == 3
    graph.add_odometry(0, 1, step, np.eye(6) * 1e4)
    est = graph.optimise(start)
    np.testing.assert_allclose(est[2], step @ step, atol=1e-6)


def test_bad_input_is_a_clear_error():
    graph = PoseGraph(GraphConfig())
    graph.add_keyframe(0, np.eye(4))
    with pytest.raises(InputError, match="added twice"):
        graph.add_keyframe(0, np.eye(4))
    with pytest.raises(InputError, match="keyframe 3 was never added"):
        graph.add_odometry(0, 3, np.eye(4), np.eye(6))
    graph.add_keyframe(1, np.eye(4))
    with pytest.raises(InputError, match="positive definite"):
        graph.add_loop(0, 1, np.eye(4), np.zeros((6, 6)))
    with pytest.raises(InputError, match="rigid"):
        graph.add_odometry(0, 1, np.full((4, 4), np.nan), np.eye(6))
    with pytest.raises(InputError, match="unknown keyframe"):
        graph.marginal_covariance(5, {0: np.eye(4), 1: np.eye(4)})
    with pytest.raises(InputError, match="no pose given"):
        graph.optimise({0: np.eye(4)})
    with pytest.raises(InputError, match="needs a prior"):
        PoseGraph(GraphConfig()).add_keyframe(0)


def test_state_roundtrip_reproduces_the_optimum(stiff_problem):
    truth, meas, init, info = stiff_problem
    graph = PoseGraph(GraphConfig())
    for k in range(6):
        graph.add_keyframe(k, init[k])
    for k in range(5):
        graph.add_odometry(k, k + 1, meas[k], info)
    graph.add_loop(0, 5, relative(truth[0], truth[5]), info)
    start = {k: init[k] for k in range(6)}
    est = graph.optimise(start)
    copy = PoseGraph.from_state(GraphConfig(), graph.state())
    assert copy.n_factors == graph.n_factors and copy.n_loops == 1 and copy.keyframe_ids == graph.keyframe_ids
    for k, T in copy.optimise(start).items():
        np.testing.assert_allclose(T, est[k], atol=1e-9)
    np.testing.assert_allclose(inv(init[0]) @ est[0], np.eye(4), atol=1e-9)
