"""Association, Umeyama alignment, ATE / RPE: closed forms and a cross-check against evo."""

from __future__ import annotations

import numpy as np
import pytest

from lrslam.errors import InputError
from lrslam.geometry import make_pose, random_pose
from lrslam.evaluation.alignment import umeyama
from lrslam.evaluation.association import associate
from lrslam.evaluation.ate import ate_from_files, compute_ate, compute_rpe
from lrslam.trajectory_io import write_tum


def random_trajectory(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    """A smooth-ish random camera path: random walk of small rigid steps, 30 Hz stamps."""
    poses = [random_pose(rng, 1.0, 180.0)]
    for _ in range(n - 1):
        poses.append(poses[-1] @ random_pose(rng, 0.05, 5.0))
    return 1000.0 + np.arange(n) / 30.0, np.stack(poses)


def perturb(rng: np.random.Generator, poses: np.ndarray, trans_m: float, rot_deg: float) -> np.ndarray:
    return np.stack([T @ random_pose(rng, trans_m, rot_deg) for T in poses])


# ---------------------------------------------------------------- association

def tum_associate_reference(a: np.ndarray, b: np.ndarray, max_dt: float) -> list[tuple[int, int]]:
    """TUM RGB-D associate.py logic (all pairs with |dt| < max_dt, greedy by |dt|), on indices."""
    cands = sorted((abs(x - y), i, j) for i, x in enumerate(a) for j, y in enumerate(b) if abs(x - y) < max_dt)
    used_a, used_b, out = set(), set(), []
    for _, i, j in cands:
        if i not in used_a and j not in used_b:
            used_a.add(i)
            used_b.add(j)
            out.append((i, j))
    return sorted(out, key=lambda ij: a[ij[0]])


def test_associate_closed_form():
    ia, ib = associate(np.array([0.0, 1.0, 2.0]), np.array([2.01, 0.005, 1.5, 2.015]), max_dt=0.02)
    assert ia.tolist() == [0, 2] and ib.tolist() == [1, 0]


def test_associate_is_one_to_one_and_greedy():
    # b's single stamp is closer to a[1] (0.001 s) than to a[0] (0.009 s): only a[1] gets it.
    ia, ib = associate(np.array([0.0, 0.01]), np.array([0.009]), max_dt=0.02)
    assert ia.tolist() == [1] and ib.tolist() == [0]


def test_associate_matches_tum_reference(rng):
    a = rng.permutation(np.cumsum(rng.uniform(0.0, 0.05, 200)))
    b = np.cumsum(rng.uniform(0.0, 0.02, 400))
    ia, ib = associate(a, b, max_dt=0.02)
    assert list(zip(ia.tolist(), ib.tolist())) == tum_associate_reference(a, b, 0.02)
    assert len(set(ia.tolist())) == len(ia) and len(set(ib.tolist())) == len(ib)
    assert np.all(np.diff(a[ia]) >= 0)


def test_associate_nothing_raises():
    with pytest.raises(InputError, match="no timestamps associate"):
        associate(np.array([0.0, 1.0]), np.array([5.0, 6.0]))
    with pytest.raises(InputError, match="non-finite"):
        associate(np.array([0.0, np.nan]), np.array([0.0]))


# ---------------------------------------------------------------- Umeyama

@pytest.mark.parametrize("with_scale", [False, True])
def test_umeyama_recovers_transform(rng, with_scale):
    src = rng.normal(size=(50, 3))
    T = random_pose(rng, 3.0, 180.0)
    s0 = 1.7 if with_scale else 1.0
    dst = s0 * src @ T[:3, :3].T + T[:3, 3]
    R, t, s = umeyama(src, dst, with_scale=with_scale)
    np.testing.assert_allclose(R, T[:3, :3], atol=1e-12)
    np.testing.assert_allclose(t, T[:3, 3], atol=1e-12)
    assert s == pytest.approx(s0, abs=1e-12)
    if not with_scale:
        assert s == 1.0


def test_umeyama_never_returns_a_reflection(rng):
    src = rng.normal(size=(20, 3))
    dst = src * np.array([1.0, 1.0, -1.0])  # a mirror image: best proper rotation, not the reflection
    R, _, _ = umeyama(src, dst)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)


def test_umeyama_collinear_points_still_minimise(rng):
    src = np.outer(np.linspace(-1, 1, 10), [0.3, -0.5, 0.8])
    T = random_pose(rng, 2.0, 180.0)
    dst = src @ T[:3, :3].T + T[:3, 3]
    R, t, _ = umeyama(src, dst)
    assert np.abs(src @ R.T + t - dst).max() < 1e-12


def test_umeyama_rejects_bad_input(rng):
    with pytest.raises(InputError, match="at least 3"):
        umeyama(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(InputError, match="coincide"):
        umeyama(np.ones((5, 3)), rng.normal(size=(5, 3)))
    with pytest.raises(InputError, match=r"\(N, 3\)"):
        umeyama(np.zeros((5, 3)), np.zeros((4, 3)))
    with pytest.raises(InputError, match="non-finite"):
        umeyama(np.full((5, 3), np.nan), np.zeros((5, 3)))


# ---------------------------------------------------------------- ATE / RPE

def test_ate_of_rigidly_moved_trajectory_is_zero(rng):
    ts, est = random_trajectory(rng, 200)
    T = random_pose(rng, 10.0, 180.0)
    res = compute_ate(ts, est, ts, T @ est)
    assert res.rmse_cm < 1e-9 and res.max_cm < 1e-9
    assert res.n_matched == 200
    np.testing.assert_allclose(res.T_align, T, atol=1e-12)
    assert compute_rpe(ts, est, ts, T @ est).trans_rmse_cm < 1e-9


def test_ate_closed_form_pairwise_offsets(rng):
    # Each position is visited twice; GT = estimate -/+ d_k along z for the two visits of position k. Then the
    # errors sum to zero and are uncorrelated with the positions, so the optimal alignment is the identity and
    # every error is exactly d_k, whatever rigid motion the ground truth is expressed in.
    _, est_k = random_trajectory(rng, 30)
    d = rng.uniform(0.01, 0.2, size=30)
    est = np.repeat(est_k, 2, axis=0)
    gt = est.copy()
    gt[:, 2, 3] += np.repeat(d, 2) * np.tile([-1.0, 1.0], 30)
    T = random_pose(rng, 5.0, 180.0)
    ts = np.arange(60) * 0.1
    res = compute_ate(ts, est, ts, T @ gt)
    expected_cm = 100.0 * np.repeat(d, 2)
    np.testing.assert_allclose(res.errors_cm, expected_cm, atol=1e-9)
    assert res.rmse_cm == pytest.approx(np.sqrt(np.mean(expected_cm**2)), abs=1e-9)
    assert res.mean_cm == pytest.approx(np.mean(expected_cm), abs=1e-9)
    assert res.median_cm == pytest.approx(np.median(expected_cm), abs=1e-9)
    assert res.max_cm == pytest.approx(np.max(expected_cm), abs=1e-9)
    assert res.std_cm == pytest.approx(np.std(expected_cm), abs=1e-9)
    np.testing.assert_allclose(res.T_align, T, atol=1e-12)


def test_ate_without_alignment_sees_a_constant_offset(rng):
    ts, est = random_trajectory(rng, 50)
    offset = make_pose(np.eye(3), [0.03, -0.04, 0.0])  # 5 cm
    assert compute_ate(ts, est, ts, offset @ est, align=False).rmse_cm == pytest.approx(5.0, abs=1e-12)
    assert compute_ate(ts, est, ts, offset @ est, align=True).rmse_cm < 1e-9


def test_ate_skips_nan_ground_truth(rng):
    ts, est = random_trajectory(rng, 80)
    gt = perturb(rng, est, 0.02, 1.0)
    gt_nan = gt.copy()
    gt_nan[[3, 10, 11, 40]] = np.nan
    keep = np.setdiff1d(np.arange(80), [3, 10, 11, 40])
    res = compute_ate(ts, est, ts, gt_nan)
    ref = compute_ate(ts, est, ts[keep], gt[keep])
    assert res.n_matched == 76
    assert res.rmse_cm == ref.rmse_cm
    with pytest.raises(InputError, match="not finite"):
        compute_ate(ts, gt_nan, ts, est)  # a non-finite estimate is an error, not skipped


def test_ate_and_rpe_match_evo(rng):
    from evo.core import metrics, sync
    from evo.core.trajectory import PoseTrajectory3D

    for trial in range(3):
        gt_ts, gt = random_trajectory(rng, 150)
        keep = np.sort(rng.choice(150, size=120, replace=False))  # the estimate misses some frames
        est_ts = gt_ts[keep] + rng.uniform(-0.003, 0.003, size=120)
        est = random_pose(rng, 5.0, 180.0) @ perturb(rng, gt[keep], 0.03, 2.0)

        ours = compute_ate(est_ts, est, gt_ts, gt)
        ours_rpe = compute_rpe(est_ts, est, gt_ts, gt, delta=1)
        traj_ref = PoseTrajectory3D(poses_se3=list(gt), timestamps=gt_ts)
        traj_est = PoseTrajectory3D(poses_se3=list(est), timestamps=est_ts)
        traj_ref, traj_est = sync.associate_trajectories(traj_ref, traj_est, max_diff=0.02)
        traj_est.align(traj_ref, correct_scale=False)
        ape = metrics.APE(metrics.PoseRelation.translation_part)
        ape.process_data((traj_ref, traj_est))
        stats = ape.get_all_statistics()
        assert ours.n_matched == 120 == traj_est.num_poses
        for key, value in (("rmse", ours.rmse_cm), ("mean", ours.mean_cm), ("median", ours.median_cm),
                           ("max", ours.max_cm), ("std", ours.std_cm)):
            assert value == pytest.approx(100.0 * stats[key], abs=1e-6), key
        for relation, value, scale in ((metrics.PoseRelation.translation_part, ours_rpe.trans_rmse_cm, 100.0),
                                       (metrics.PoseRelation.rotation_angle_deg, ours_rpe.rot_rmse_deg, 1.0)):
            rpe = metrics.RPE(relation, delta=1, delta_unit=metrics.Unit.frames, all_pairs=False)
            rpe.process_data((traj_ref, traj_est))
            assert value == pytest.approx(scale * rpe.get_statistic(metrics.StatisticsType.rmse), abs=1e-6)


def test_rpe_closed_form(rng):
    # The estimate moves 12 cm per frame along x where the ground truth moves 10 cm: every relative motion over
    # delta frames is off by exactly 2 * delta cm, with no rotation error.
    ts = np.arange(20) * 0.1
    gt = np.stack([make_pose(np.eye(3), [0.1 * i, 0.0, 0.0]) for i in range(20)])
    est = np.stack([make_pose(np.eye(3), [0.12 * i, 0.0, 0.0]) for i in range(20)])
    res = compute_rpe(ts, est, ts, gt, delta=1)
    assert res.trans_rmse_cm == pytest.approx(2.0, abs=1e-12) and res.rot_rmse_deg == 0.0
    assert compute_rpe(ts, est, ts, gt, delta=5).trans_rmse_cm == pytest.approx(10.0, abs=1e-12)
    with pytest.raises(InputError, match="delta"):
        compute_rpe(ts, est, ts, gt, delta=0)


def test_ate_from_files(tmp_path, rng):
    ts, est = random_trajectory(rng, 40)
    gt = random_pose(rng, 1.0, 90.0) @ perturb(rng, est, 0.01, 0.5)
    res = ate_from_files(write_tum(tmp_path / "est.txt", ts, est), write_tum(tmp_path / "gt.txt", ts, gt))
    assert res.rmse_cm == pytest.approx(compute_ate(ts, est, ts, gt).rmse_cm, abs=1e-9)
    (tmp_path / "bad.txt").write_text("1.0 2.0 three\n")
    with pytest.raises(InputError, match="bad.txt"):
        ate_from_files(tmp_path / "bad.txt", tmp_path / "gt.txt")
    with pytest.raises(InputError, match="not found"):
        ate_from_files(tmp_path / "missing.txt", tmp_path / "gt.txt")
