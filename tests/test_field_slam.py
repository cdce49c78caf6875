"""Field SLAM facade: the whole loop on a synthetic sequence (ATE, mesh), state round trip, pose updates, meshing."""

from contextlib import contextmanager

import numpy as np
import pytest
import torch

from field_fixtures import H_SMALL, K_SMALL, W_SMALL, box_room, scene_bound, trajectory
from lrslam import camera
from lrslam.field.mapper import MapperConfig
from lrslam.field.mesh import MeshConfig, extract_mesh
from lrslam.field.slam import FieldSLAM, FieldSLAMConfig, run_field_slam
from lrslam.pipeline.evaluation.alignment import umeyama


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


@pytest.mark.slow
def test_field_slam_on_synthetic_sequence_tracks_and_reconstructs():
    scene = box_room()
    gt = trajectory(60)
    frames = [scene.render(K_SMALL, H_SMALL, W_SMALL, T) for T in gt]
    cfg = FieldSLAMConfig.cpu_small()
    with one_thread():
        est, slam = run_field_slam(frames, cfg, scene_bound(), K_SMALL, H_SMALL, W_SMALL, gt[0], map_every=4,
                                   keyframe_every=4)
        mesh = slam.extract_mesh()
    ate = _ate_rmse(est[:, :3, 3], gt[:, :3, 3])
    assert ate < 0.02, ate
    assert sorted(slam.keyframe_poses()) == list(range(0, 60, 4))
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
def small_slam():
    scene = box_room()
    gt = trajectory(60)
    frames = {i: scene.render(K_SMALL, H_SMALL, W_SMALL, gt[i]) for i in (0, 2, 4)}
    cfg = FieldSLAMConfig.cpu_small(mapping=MapperConfig(first_iters=10, iters=3, n_rays=300,
                                                         joint_opt_min_keyframes=2))
    with one_thread():
        slam = FieldSLAM(cfg, scene_bound(), K_SMALL, H_SMALL, W_SMALL)
        slam.initialise(0, *frames[0], gt[0])
        slam.map(2, *frames[2], gt[2], add_keyframe=True)
    return slam, frames, gt


def test_map_returns_window_poses_and_registers_keyframes(small_slam):
    slam, frames, gt = small_slam
    with one_thread():
        out = slam.map(4, *frames[4], gt[4], add_keyframe=True)
    # joint optimisation (>= 2 keyframes here): the oldest view (keyframe 0) stays fixed, the others move
    assert set(out) == {2, 4}
    assert sorted(slam.keyframe_poses()) == [0, 2, 4]
    np.testing.assert_array_equal(slam.keyframe_poses()[0], gt[0])
    for k, T in out.items():
        np.testing.assert_allclose(slam.keyframe_poses()[k], T)
        assert np.linalg.norm(T[:3, 3] - gt[k][:3, 3]) < 0.02


def test_state_dict_round_trip_and_pose_updates(small_slam):
    slam, frames, gt = small_slam
    state = slam.state_dict()
    other = FieldSLAM(slam.cfg, scene_bound(), K_SMALL, H_SMALL, W_SMALL)
    other.load_state_dict(state)
    p = torch.rand(200, 3) * 2 - 1
    torch.testing.assert_close(other.model.sdf(p), slam.model.sdf(p))
    torch.testing.assert_close(other.model.colour(p), slam.model.colour(p))
    assert other.keyframe_poses().keys() == slam.keyframe_poses().keys()
    for k, T in slam.keyframe_poses().items():
        np.testing.assert_array_equal(other.keyframe_poses()[k], T)
    assert other.parameter_count() == slam.parameter_count()
    # pose-graph style correction: move keyframe 2 (unknown ids are ignored), then re-fit the field only
    moved = slam.keyframe_poses()[2].copy()
    moved[:3, 3] += [0.01, 0.0, 0.0]
    other.set_keyframe_poses({2: moved, 999: np.eye(4)})
    np.testing.assert_array_equal(other.keyframe_poses()[2], moved)
    before = {k: v.copy() for k, v in other.keyframe_poses().items()}
    with one_thread():
        stats = other.remap([2, 999], iters=3)
    assert stats["iters"] == 3 and np.isfinite(stats["loss"])
    for k, T in other.keyframe_poses().items():
        np.testing.assert_array_equal(T, before[k])  # remap never moves poses
    assert not torch.equal(other.model.sdf(p), slam.model.sdf(p))


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
    mesh = extract_mesh(_SphereField(), [], K_SMALL, H_SMALL, MeshConfig(resolution=0.04, cull="none"))
    r = np.linalg.norm(mesh.vertices, axis=1)
    assert np.abs(r - 0.5).max() < 0.01
    centres = mesh.triangles_center
    assert np.mean(np.sum(mesh.face_normals * centres, axis=1) > 0) > 0.99  # normals point into free space
    np.testing.assert_array_equal(mesh.visual.vertex_colors[:, 3], 255)


def test_keyframes_can_keep_a_pixel_subset(small_slam):
    _, frames, gt = small_slam
    cfg = FieldSLAMConfig.cpu_small(mapping=MapperConfig(first_iters=3, iters=2, n_rays=200, keyframe_pixels=500),
                                    mesh=MeshConfig(resolution=0.08))
    with one_thread():
        slam = FieldSLAM(cfg, scene_bound(), K_SMALL, H_SMALL, W_SMALL)
        slam.initialise(0, *frames[0], gt[0])
        slam.map(2, *frames[2], gt[2], add_keyframe=True)
        slam.remap(None, 2)
        mesh = slam.extract_mesh()
    kf = slam.mapper.keyframes.get(2)
    assert len(kf.depth) == 500 and kf.index is not None and len(torch.unique(kf.index)) == 500
    flat = frames[2][1].reshape(-1)
    np.testing.assert_array_equal(kf.depth.numpy(), flat[kf.index.numpy()])
    # a barely fitted field; meshing with sparse keyframe depth must still work and stay inside the bound
    bound = slam.model.bound_np
    assert np.all((mesh.vertices >= bound[:, 0] - 1e-6) & (mesh.vertices <= bound[:, 1] + 1e-6))
