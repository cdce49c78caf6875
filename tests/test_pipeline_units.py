"""Unit tests of the pipeline's own pieces (no SLAM run)."""

import numpy as np
import pytest

from lrslam.camera import intrinsics_matrix
from lrslam.geometry import random_pose
from lrslam.pipeline.trajectory import Trajectory
from lrslam.pipeline.auto_bound import bound_from_frame
from lrslam.pipeline.timing import StageTimer


def test_trajectory_follows_keyframe_corrections(rng):
    poses = [random_pose(rng, 1.0, 30.0) for _ in range(6)]
    traj = Trajectory()
    for i, T in enumerate(poses):
        traj.add(T, is_keyframe=i in (0, 3))
    np.testing.assert_allclose(traj.poses(), np.stack(poses), atol=1e-12)
    # move keyframe 3 by a correction C: frames 3..5 follow rigidly, frames 0..2 stay
    C = random_pose(rng, 0.2, 5.0)
    moved = traj.apply_corrections({3: C @ poses[3], 0: poses[0] @ random_pose(rng, 1e-6, 1e-4)},
                                   min_shift_m=1e-4, min_shift_deg=0.01)
    assert list(moved) == [3]              # keyframe 0 moved less than the write threshold: untouched
    got = traj.poses()
    np.testing.assert_allclose(got[:3], np.stack(poses[:3]), atol=1e-12)
    np.testing.assert_allclose(got[3:], np.stack([C @ T for T in poses[3:]]), atol=1e-12)
    assert traj.keyframe_ids() == [0, 3]


def test_trajectory_set_pose_of_non_keyframe(rng):
    traj = Trajectory()
    traj.add(np.eye(4), is_keyframe=True)
    traj.add(np.eye(4))
    T = random_pose(rng, 0.5, 10.0)
    traj.set_pose(1, T)
    np.testing.assert_allclose(traj.pose(1), T, atol=1e-12)


def test_bound_from_frame_contains_points_and_camera():
    K = intrinsics_matrix(100.0, 100.0, 31.5, 23.5)
    depth = np.full((48, 64), 2.0, dtype=np.float32)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    b = bound_from_frame(depth, K, T, margin=0.5)
    assert b.shape == (3, 2)
    # the wall at z = 2 m in the camera lies at world z = 5; the camera at z = 3
    assert b[2, 0] == pytest.approx(3.0 - 0.5) and b[2, 1] == pytest.approx(5.0 + 0.5)
    with pytest.raises(ValueError, match="no valid depth"):
        bound_from_frame(np.zeros_like(depth), K, T)


def test_stage_timer_accumulates():
    t = StageTimer()
    for _ in range(3):
        with t("a"):
            pass
    s = t.summary(3)
    assert s["a"]["calls"] == 3 and s["a"]["total_s"] >= 0


def test_long_chains_through_the_trajectory_stay_rigid(rng):
    """Seeds chain through the trajectory (last pose x increment); a keyframe every few frames used to
    compound a tiny rotation drift (inverse by transposition of a non-orthonormal keyframe) until frame ~100
    was rejected as not rigid."""
    from lrslam.geometry import is_valid_pose

    traj = Trajectory()
    T = random_pose(rng, 1.0, 30.0)
    T[:3, :3] *= 1.0 + 1e-9  # a keyframe slightly off SO(3), as float32 kernels leave them
    traj.add(T, is_keyframe=True)
    for i in range(1, 2000):
        inc = random_pose(rng, 0.01, 1.0)
        traj.add(traj.pose(-1) @ inc, is_keyframe=i % 5 == 0)
    R = traj.pose(-1)[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12
    assert all(is_valid_pose(P) for P in traj.poses()[::50])


@pytest.mark.parametrize("override", ["field.tracking.iters=-5", "field.mapping.n_rays=0", "field.mapping.iters=-1",
                                      "field.render.n_stratified=0", "schedule.map_every=0", "keyframes.every_n=-1",
                                      "backend.remap_keyframes=0", "odometry.gates.min_fitness=2",
                                      "field.mapping.max_pose_step=0", "output.partial_every=0"])
def test_counts_and_iterations_are_validated(override):
    """A negative iteration count or an empty ray budget is an error naming the key, not a silent no-op."""
    from lrslam.errors import InputError
    from lrslam.pipeline.config import build_config

    with pytest.raises(InputError, match=override.split("=")[0].replace(".", r"\.")):
        build_config("synthetic", overrides=[override])
