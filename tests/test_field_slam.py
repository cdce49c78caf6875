"""Field SLAM: the whole field-mode loop (the runner's ``field`` preset) on a synthetic sequence (ATE, mesh), the
facade's mapping window, divergence guard, state round trip, a re-map that moves the surface, meshing."""

import copy
from contextlib import contextmanager

import numpy as np
import pytest
import torch

from field_fixtures import H_SMALL, K_SMALL, W_SMALL, box_room, scene_bound, trajectory
from lrslam import camera
from lrslam.field.mapper import MapperConfig
from lrslam.field.mesh import MeshConfig, extract_mesh
from lrslam.field.slam import FieldSLAM, FieldSLAMConfig
from lrslam.frame import Frame
from lrslam.geometry import pose_error, random_pose
from lrslam.evaluation.alignment import umeyama


@contextmanager
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def _ate_rmse(est: np.ndarray, gt: np.ndarray) -> float:
    R, t, _ = umeyama(est, gt)
    return float(np.sqrt(np.mean(np.sum((est @ R.T + t - gt) ** 2, axis=1))))


def _distance_to_mesh(points: np.ndarray, mesh) -> np.ndarray:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)))
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def _field_runner(cfg: FieldSLAMConfig, bound, map_every=4, keyframe_every=4):
    from lrslam.pipeline.config import RunConfig, build_config
    from lrslam.pipeline.runner import SlamRunner

    base = build_config(mode="field", overrides=[f"schedule.map_every={map_every}",
                                                 f"keyframes.every_n={keyframe_every}"])
    run_cfg = RunConfig.model_validate(base.model_dump() | {"field": cfg.model_dump()})
    return SlamRunner(run_cfg, K_SMALL, H_SMALL, W_SMALL, bound)


@pytest.mark.slow
def test_field_slam_on_synthetic_sequence_tracks_and_reconstructs():
    scene = box_room()
    gt = trajectory(60)
    frames = [scene.render(K_SMALL, H_SMALL, W_SMALL, T) for T in gt]
    cfg = FieldSLAMConfig.cpu_small()
    with one_thread():
        runner = _field_runner(cfg, scene_bound())
        for i, (rgb, depth) in enumerate(frames):
            f = Frame(i, float(i), rgb, depth, K_SMALL)
            runner.start(f, gt[0]) if i == 0 else runner.step(f)
        res = runner.finish(mesh=True)
    est, mesh = res.poses, res.mesh
    ate = _ate_rmse(est[:, :3, 3], gt[:, :3, 3])
    assert ate < 0.02, ate
    assert list(res.keyframe_ids) == list(range(0, 60, 4))
    assert res.counts["refine_failures"] == 0 and res.counts["mapping_poses_reverted"] == 0
    # reconstruction: accuracy (mesh -> true surface) and completion ratio (observed true surface -> mesh)
    samples = np.asarray(mesh.sample(20_000, seed=0))
    accuracy = float(scene.distance(samples).mean())
    observed = np.concatenate([
        camera.transform_points(T, camera.backproject_depth(d, K_SMALL)[::4, ::4].reshape(-1, 3))
        for T, (_, d) in zip(gt, frames)])
    completion = _distance_to_mesh(observed, mesh)
    ratio = float(np.mean(completion < 0.05))
    print(f"ATE RMSE {ate * 100:.2f} cm, accuracy {accuracy * 100:.2f} cm, "
          f"completion {completion.mean() * 100:.2f} cm, completion ratio {ratio * 100:.1f} %, {len(mesh.faces)} faces")
    assert accuracy < 0.03 and ratio > 0.85
    assert mesh.visual.vertex_colors.shape == (len(mesh.vertices), 4)


@pytest.fixture(scope="module")
def _fitted_small_slam():
    """A field fitted on frames 0, 2, 4, 6 at their true poses (fitted once per module; tests get copies)."""
    scene = box_room()
    gt = trajectory(60)
    frames = {i: scene.render(K_SMALL, H_SMALL, W_SMALL, gt[i]) for i in (0, 2, 4, 6, 8, 10)}
    cfg = FieldSLAMConfig.cpu_small(mapping=MapperConfig(first_iters=60, iters=10, n_rays=600,
                                                         joint_opt_min_keyframes=100))
    kf = {0: gt[0]}
    with one_thread():
        slam = FieldSLAM(cfg, scene_bound(), K_SMALL, H_SMALL, W_SMALL)
        slam.initialise(0, *frames[0], gt[0])
        for i in (2, 4, 6):
            slam.map(i, *frames[i], gt[i], kf, add_keyframe=True)
            kf[i] = gt[i]
    return slam, frames, gt, kf


@pytest.fixture
def small_slam(_fitted_small_slam):
    """(slam, frames, gt, keyframe poses): a fresh copy of the fitted field and of its inputs for each test, so no
    test sees what an earlier one changed."""
    slam, frames, gt, kf = _fitted_small_slam
    return _copy(slam), copy.deepcopy(frames), copy.deepcopy(gt), copy.deepcopy(kf)


def _copy(slam: FieldSLAM, **mapping) -> FieldSLAM:
    cfg = slam.cfg.model_copy(update={"mapping": slam.cfg.mapping.model_copy(update=mapping)})
    other = FieldSLAM(cfg, scene_bound(), K_SMALL, H_SMALL, W_SMALL)
    other.load_state_dict(slam.state_dict())
    return other


def test_joint_mapping_moves_window_poses_toward_the_truth_and_fixes_the_oldest(small_slam):
    slam, frames, gt, kf = small_slam
    other = _copy(slam, joint_opt_min_keyframes=2, iters=40, lr_pose_trans=0.002, lr_pose_rot=0.001)
    rng = np.random.default_rng(3)
    drifted = {k: T @ random_pose(rng, 0.02, 1.0) if k in (4, 6) else T for k, T in kf.items()}
    seed8 = gt[8] @ random_pose(rng, 0.02, 1.0)
    with one_thread():
        out = other.map(8, *frames[8], seed8, drifted, add_keyframe=True)
    # the first keyframe never moves; the window's perturbed poses and the current frame come closer to the truth
    assert 0 not in out and 8 in out
    for k, T_in in list(drifted.items())[2:] + [(8, seed8)]:
        if k in out:
            before, after = pose_error(T_in, gt[k])[0], pose_error(out[k], gt[k])[0]
            assert after < before, (k, before, after)
    assert sorted(other.keyframe_ids()) == [0, 2, 4, 6, 8]


def test_mapping_divergence_guard_reverts_runaway_poses(small_slam):
    slam, frames, gt, kf = small_slam
    other = _copy(slam, joint_opt_min_keyframes=2, iters=5, lr_pose_trans=100.0, lr_pose_rot=100.0)
    with one_thread():
        out = other.map(8, *frames[8], gt[8], kf, add_keyframe=False)
    assert other.reverted_poses > 0
    for k, T in out.items():  # what comes back is either the input pose or a plausible step from it
        T_in = gt[8] if k == 8 else kf[k]
        d_t, d_r = pose_error(T_in, T)
        assert d_t <= other.cfg.mapping.max_pose_step and d_r <= other.cfg.mapping.max_pose_step_deg


def test_state_dict_round_trip(small_slam):
    slam, frames, gt, kf = small_slam
    other = _copy(slam)
    p = torch.rand(200, 3) * 2 - 1
    torch.testing.assert_close(other.model.sdf(p), slam.model.sdf(p))
    torch.testing.assert_close(other.model.colour(p), slam.model.colour(p))
    assert other.keyframe_ids() == slam.keyframe_ids()
    assert other.parameter_count() == slam.parameter_count()


def test_remap_after_a_pose_correction_moves_the_surface(small_slam):
    """A field mapped at drifted keyframe poses, then told the corrected (true) ones: the re-map must make the
    rendered depth at the corrected poses agree with the sensor measurably better (and never move a pose)."""
    _, frames, gt, _ = small_slam
    cfg = FieldSLAMConfig.cpu_small(mapping=MapperConfig(first_iters=60, iters=10, n_rays=600,
                                                         joint_opt_min_keyframes=100, remap_iters=30))
    drift = {i: gt[i] @ g for i, g in zip((0, 2, 4, 6, 8, 10), [np.eye(4)] + [
        _shift(0.012 * n) for n in range(1, 6)])}
    with one_thread():
        slam = FieldSLAM(cfg, scene_bound(), K_SMALL, H_SMALL, W_SMALL)
        slam.initialise(0, *frames[0], drift[0])
        kf = {0: drift[0]}
        for i in (2, 4, 6, 8, 10):
            slam.map(i, *frames[i], drift[i], kf, add_keyframe=True)
            kf[i] = drift[i]
        corrected = {i: gt[i] for i in kf}
        before = slam.depth_error(corrected, [6, 8, 10])
        stats = slam.remap(corrected, None)
        after = slam.depth_error(corrected, [6, 8, 10])
    print(f"depth error at the corrected poses: {before * 100:.2f} -> {after * 100:.2f} cm")
    assert stats["iters"] == 30 and np.isfinite(stats["loss"])
    assert after < 0.7 * before, (before, after)


def _shift(x: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = [x, 0.5 * x, 0.0]
    return T


class _SphereField:
    """Model-like object with an analytic sphere SDF for the mesher."""

    def __init__(self):
        self.bound_np = np.array([[-1.0, 1.0], [-1.0, 1.0], [-1.0, 1.0]])
        self.truncation = 0.06
        self.device = torch.device("cpu")

    @contextmanager
    def frozen(self):
        yield self

    def sdf(self, p):
        return ((p.norm(dim=-1) - 0.5) / self.truncation).clamp(-1, 1)

    def colour(self, p):
        return (p + 1) / 2


def test_mesh_of_analytic_sphere_is_accurate_and_outward_facing():
    mesh = extract_mesh(_SphereField(), [], [], K_SMALL, H_SMALL, MeshConfig(resolution=0.04, cull="none"))
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(r - 0.5).max() < 0.01
    centres = mesh.triangles_center
    assert np.mean(np.sum(mesh.face_normals * centres, axis=1) > 0) > 0.99  # normals point into free space
    np.testing.assert_array_equal(mesh.visual.vertex_colors[:, 3], 255)


def test_keyframes_can_keep_a_pixel_subset(small_slam):
    _, frames, gt, _ = small_slam
    cfg = FieldSLAMConfig.cpu_small(mapping=MapperConfig(first_iters=3, iters=2, n_rays=200, keyframe_pixels=500),
                                    mesh=MeshConfig(resolution=0.08))
    with one_thread():
        slam = FieldSLAM(cfg, scene_bound(), K_SMALL, H_SMALL, W_SMALL)
        slam.initialise(0, *frames[0], gt[0])
        slam.map(2, *frames[2], gt[2], {0: gt[0]}, add_keyframe=True)
        slam.remap({0: gt[0], 2: gt[2]}, None, 2)
        mesh = slam.extract_mesh({0: gt[0], 2: gt[2]})
    kf = slam.mapper.keyframes.get(2)
    assert len(kf.depth) == 500 and kf.index is not None and len(torch.unique(kf.index)) == 500
    flat = frames[2][1].reshape(-1)
    np.testing.assert_array_equal(kf.depth.numpy(), flat[kf.index.numpy()])
    # a barely fitted field; meshing with sparse keyframe depth must still work and stay inside the bound
    bound = slam.model.bound_np
    assert np.all((mesh.vertices >= bound[:, 0] - 1e-6) & (mesh.vertices <= bound[:, 1] + 1e-6))
