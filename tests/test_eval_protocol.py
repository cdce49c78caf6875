"""ESLAM / NICE-SLAM mesh protocol: face rule, ICP, NICE-SLAM depth views, and the run's mesh world."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from lrslam.camera import intrinsics_matrix
from lrslam.errors import InputError
from lrslam.geometry import is_valid_pose, make_pose
from lrslam.evaluation.ate import compute_ate
from lrslam.evaluation.depth_views import bbox_views, depth_l1_all_pixels
from lrslam.evaluation.mesh_eval import evaluate_mesh, evaluate_run_mesh
from lrslam.evaluation.mesh_metrics import icp_align, keep_seen_faces
from lrslam.evaluation.mesh_protocol import PROTOCOLS, get_protocol

W, H = 64, 48
K = intrinsics_matrix(40.0, 40.0, 31.5, 23.5)


def room(extents=(4.0, 3.0, 2.5)) -> trimesh.Trimesh:
    """A closed box seen from inside (normals inward), subdivided so culling has vertices to test."""
    box = trimesh.creation.box(extents=extents)
    box.invert()
    return box.subdivide().subdivide().subdivide()


def test_presets_follow_the_sources():
    assert PROTOCOLS["eslam"].n_points == 450_000 and PROTOCOLS["nice-slam"].n_points == 200_000
    for name in ("eslam", "nice-slam"):
        p = PROTOCOLS[name]
        assert p.face_rule == "any" and p.icp and p.icp_threshold == 0.1 and p.stride(5000) == 1
        assert p.depth_views == 1000 and p.depth_l1 == "bbox"
    assert PROTOCOLS["nice-slam"].occlusion_tol is None and PROTOCOLS["eslam"].occlusion_tol == 0.06
    ours = PROTOCOLS["lrslam-v0"]
    assert ours.face_rule == "all" and not ours.icp and ours.stride(120) == 3 and ours.stride(50) == 1
    assert get_protocol("eslam", n_points=10, icp=None).n_points == 10
    with pytest.raises(InputError, match="unknown mesh protocol"):
        get_protocol("nope")
    with pytest.raises(InputError, match="face_rule"):
        get_protocol("eslam", face_rule="some")


def test_face_rule_any_vs_all():
    verts = np.random.default_rng(0).normal(size=(6, 3))
    mesh = trimesh.Trimesh(verts, [[0, 1, 2], [1, 2, 3], [3, 4, 5]], process=False)
    one = np.array([True, False, False, False, False, False])
    assert len(keep_seen_faces(mesh, one, "any").faces) == 1
    assert len(keep_seen_faces(mesh, one, "all").faces) == 0
    four = np.array([True, True, True, True, False, False])
    assert len(keep_seen_faces(mesh, four, "any").faces) == 3
    assert len(keep_seen_faces(mesh, four, "all").faces) == 2


def test_icp_removes_a_small_rigid_offset():
    gt = room((1.2, 1.0, 0.8))
    T = make_pose(Rotation.from_rotvec([0.0, 0.0, np.radians(1.0)]).as_matrix(), [0.03, -0.02, 0.01])
    est = gt.copy().apply_transform(T)
    T_icp = icp_align(est, gt)
    assert np.allclose(T_icp @ T, np.eye(4), atol=1e-4)
    p = get_protocol("eslam", n_points=50_000, depth_views=0)
    with_icp = evaluate_mesh(est, gt, protocol=p)
    without = evaluate_mesh(est, gt, protocol=get_protocol("eslam", n_points=50_000, depth_views=0, icp=False))
    floor = evaluate_mesh(gt.copy(), gt, protocol=p)["accuracy_cm"]   # sampling alone (50k points on 5 m^2)
    assert with_icp["accuracy_cm"] < floor + 0.05 and without["accuracy_cm"] > floor + 1.0
    assert with_icp["icp_translation_cm"] > 2.0 and without["icp_translation_cm"] == 0.0


def test_depth_l1_all_pixels_closed_form():
    # A fronto-parallel wall 2 m ahead covering the whole view, the estimate 1 cm further: every pixel's depth
    # differs by exactly 1 cm. An empty estimate renders as 0 depth: the error is the GT depth, 200 cm.
    def wall(z):
        return trimesh.Trimesh([[-50, -50, z], [50, -50, z], [50, 50, z], [-50, 50, z]], [[0, 1, 2], [0, 2, 3]])

    view = np.eye(4)[None]
    assert depth_l1_all_pixels(wall(2.01), wall(2.0), view, K, W, H) == pytest.approx(1.0, abs=1e-4)
    empty = trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    assert depth_l1_all_pixels(empty, wall(2.0), view, K, W, H) == pytest.approx(200.0, abs=1e-3)
    assert depth_l1_all_pixels(wall(25.0), wall(2.0), view, K, W, H) == pytest.approx(200.0, abs=1e-3)  # > 20 m


def test_bbox_views_inside_the_box_and_avoid_unseen_points():
    gt = room()
    unseen = np.array([[1.9, 0.0, 0.0]])   # a point on the +x wall nobody saw
    views, n_fallback = bbox_views(gt, 30, seed=1, unseen_points=unseen, K=K, width=W, height=H)
    assert n_fallback == 0 and all(is_valid_pose(T) for T in views)
    c = views[:, :3, 3]
    # The room is centred at 0 with sides 4 / 3 / 2.5: the shrunk box (0.3 / 0.7 / 0.7 of the extents along the
    # oriented box's axes, +0.4 m in z) keeps every centre strictly inside it.
    assert np.all(np.abs(c[:, :2]) < [2.0, 1.5]) and np.all(np.abs(c[:, 2]) < 1.25)
    for T in views:
        p = T[:3, :3].T @ (unseen[0] - T[:3, 3])
        if p[2] > 0:
            u, v = K[0, 0] * p[0] / p[2] + K[0, 2], K[1, 1] * p[1] / p[2] + K[1, 2]
            assert not (-0.5 <= u < W - 0.5 and -0.5 <= v < H - 0.5)


def ill_conditioned_run():
    """Six cameras on a straight line, looking +z in a room. The estimate differs from the ground truth by
    1 mm offsets turned by 90 degrees about the line, so the Umeyama alignment (free about the line) turns by
    ~90 degrees although every estimated position is within 1.5 mm of the ground truth."""
    s = np.array([1, -1, 1, -1, 1, -1]) * 0.001
    gt = np.stack([make_pose(np.eye(3), [0.05 * i - 0.125, s[i], 0.0]) for i in range(6)])
    est = np.stack([make_pose(np.eye(3), [0.05 * i - 0.125, 0.0, s[i]]) for i in range(6)])
    return np.arange(6) * 0.1, est, gt


def test_run_mesh_in_gt_world_is_not_moved_by_an_ill_conditioned_alignment(tmp_path):
    ts, est, gt = ill_conditioned_run()
    ate = compute_ate(ts, est, ts, gt)
    angle = np.degrees(Rotation.from_matrix(ate.T_align[:3, :3]).magnitude())
    assert ate.rmse_cm < 0.2 and angle > 45.0   # a tiny ATE, a huge rotation
    gt_path = tmp_path / "gt.ply"
    room().export(gt_path)
    mesh = room()   # the run's mesh: built in the GT world (initial_pose: gt), perfect here
    p = get_protocol("eslam", n_points=20_000, depth_views=0)
    kept = evaluate_run_mesh(mesh, gt_path, gt, K, W, H, ate.T_align, world_is_gt=True, protocol=p)
    moved = evaluate_run_mesh(mesh, gt_path, gt, K, W, H, ate.T_align, world_is_gt=False, protocol=p)
    assert kept["mesh_world"] == "gt" and moved["mesh_world"] == "ate_aligned"
    unmoved = evaluate_mesh(mesh, gt_path, gt, K, W, H, protocol=p)
    assert {k: kept[k] for k in unmoved} == unmoved and kept["completion_ratio"] == 100.0
    assert moved["accuracy_cm"] > kept["accuracy_cm"] + 5.0
    assert evaluate_run_mesh(mesh, gt_path, gt, K, W, H, None, world_is_gt=True, n_points=5_000,
                             protocol=p)["n_gt"] == kept["n_gt"]
    with pytest.raises(InputError, match="T_align"):
        evaluate_run_mesh(mesh, gt_path, gt, K, W, H, None, world_is_gt=False, protocol=p)
