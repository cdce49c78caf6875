"""Reconstruction metrics, culling and depth L1 on meshes with closed-form answers."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh

from lrslam.camera import backproject_depth, intrinsics_matrix, transform_points
from lrslam.errors import InputError
from lrslam.geometry import is_valid_pose, make_pose, random_pose
from lrslam.evaluation.mesh_metrics import (cull_mesh, depth_l1, load_mesh, random_views,
                                                     reconstruction_metrics, render_depth)

W, H = 64, 48
K = intrinsics_matrix(40.0, 40.0, 31.5, 23.5)


def grid_plane(x0: float, x1: float, y0: float, y1: float, z: float, n: int = 20) -> trimesh.Trimesh:
    """Square grid of (n-1)^2 * 2 triangles at height z (normal +z)."""
    xs, ys = np.meshgrid(np.linspace(x0, x1, n), np.linspace(y0, y1, n), indexing="ij")
    verts = np.stack([xs.ravel(), ys.ravel(), np.full(n * n, z)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    return trimesh.Trimesh(verts, faces, process=False)


def empty_mesh() -> trimesh.Trimesh:
    return trimesh.Trimesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))


# ---------------------------------------------------------------- accuracy / completion

def test_identical_meshes_give_only_sampling_noise():
    plane = grid_plane(0, 1, 0, 1, 0.0)
    m = reconstruction_metrics(plane, plane.copy())
    # Two independent 200k samplings of 1 m^2: mean nearest-neighbour distance ~ 1 / (2 sqrt(density)) ~ 1.1 mm.
    assert 0.0 < m["accuracy_cm"] < 0.15 and 0.0 < m["completion_cm"] < 0.15
    assert m["completion_ratio"] == 100.0
    assert m["n_est"] == m["n_gt"] == len(plane.faces)


def test_plane_shifted_along_its_normal():
    gt = grid_plane(0, 1, 0, 1, 0.0)
    est = grid_plane(0, 1, 0, 1, 0.01)
    m = reconstruction_metrics(est, gt, threshold=0.05)
    assert m["accuracy_cm"] == pytest.approx(1.0, abs=0.02)  # sqrt(1 + r^2) with r ~ 1 mm sample spacing
    assert m["completion_cm"] == pytest.approx(1.0, abs=0.02)
    assert m["completion_ratio"] == 100.0
    assert reconstruction_metrics(est, gt, threshold=0.005)["completion_ratio"] == 0.0


def test_half_reconstructed_plane():
    # Estimate = left half of a 1 m square. GT points on the right half are x - 0.5 from it (uniform in
    # [0, 0.5] m): completion = (0 + 25 cm) / 2, ratio = 50 % + the 5 cm strip = 55 %, accuracy ~ 0.
    gt = grid_plane(0, 1, 0, 1, 0.0)
    est = grid_plane(0, 0.5, 0, 1, 0.0)
    m = reconstruction_metrics(est, gt, threshold=0.05)
    assert m["accuracy_cm"] < 0.15
    assert m["completion_cm"] == pytest.approx(12.5, abs=0.3)
    assert m["completion_ratio"] == pytest.approx(55.0, abs=0.5)


def test_empty_estimate_gives_inf_and_warns(caplog):
    with caplog.at_level(logging.WARNING):
        m = reconstruction_metrics(empty_mesh(), grid_plane(0, 1, 0, 1, 0.0))
    assert m["accuracy_cm"] == m["completion_cm"] == float("inf") and m["completion_ratio"] == 0.0
    assert "no surface" in caplog.text
    with pytest.raises(InputError, match="ground-truth mesh has no surface"):
        reconstruction_metrics(grid_plane(0, 1, 0, 1, 0.0), empty_mesh())


def test_load_mesh_from_files(tmp_path):
    plane = grid_plane(0, 1, 0, 1, 0.0, n=5)
    plane.export(tmp_path / "plane.ply")
    loaded = load_mesh(tmp_path / "plane.ply")
    assert len(loaded.faces) == len(plane.faces)
    np.testing.assert_allclose(loaded.vertices, plane.vertices, atol=1e-6)
    with pytest.raises(InputError, match="not found"):
        load_mesh(tmp_path / "missing.ply")
    (tmp_path / "garbled.ply").write_bytes(b"ply\nformat nonsense\n\x00\x01")
    with pytest.raises(InputError, match="garbled.ply"):
        load_mesh(tmp_path / "garbled.ply")


# ---------------------------------------------------------------- culling

def box_around_origin() -> trimesh.Trimesh:
    box = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    return box.subdivide().subdivide().subdivide()


def test_cull_removes_box_face_behind_camera():
    box = box_around_origin()
    # Camera at the box centre looking along +z with fx = 0.4 W: the whole front face (z = 1, |x|, |y| <= 1)
    # projects inside the image, nothing behind the camera survives.
    K_wide = intrinsics_matrix(0.4 * W, 0.4 * W, (W - 1) / 2, (H - 1) / 2)
    culled = cull_mesh(box, np.eye(4)[None], K_wide, W, W, occlusion=True)
    cz = culled.triangles_center[:, 2]
    n_front = int(np.sum(np.isclose(box.triangles_center[:, 2], 1.0)))
    assert np.sum(cz < -0.99) == 0  # back face gone
    assert np.sum(np.isclose(cz, 1.0)) == n_front  # front face kept whole
    assert np.all(culled.triangles[:, :, 2].max(axis=1) > 0)  # every kept face has a vertex in front
    assert 0 < len(culled.faces) < len(box.faces)
    # A second camera looking backwards keeps the back face, unless the stride skips it.
    turn = make_pose(np.diag([-1.0, 1.0, -1.0]), np.zeros(3))
    both = np.stack([np.eye(4), turn])
    assert np.sum(cull_mesh(box, both, K_wide, W, W).triangles_center[:, 2] < -0.99) == n_front
    assert np.sum(cull_mesh(box, both, K_wide, W, W, stride=2).triangles_center[:, 2] < -0.99) == 0
    # max_depth 0.5 m: the front face at 1 m is out of range.
    near = cull_mesh(box, np.eye(4)[None], K_wide, W, W, max_depth=0.5)
    assert np.sum(np.isclose(near.triangles_center[:, 2], 1.0)) == 0


def test_cull_occlusion_hides_the_shadow_of_a_front_plane():
    # Small square at z = 1 hides the region |x|, |y| < 0.5 of the large plane at z = 2 (camera at the origin).
    front = grid_plane(-0.25, 0.25, -0.25, 0.25, 1.0, n=6)
    back = grid_plane(-1.0, 1.0, -1.0, 1.0, 2.0, n=41)
    scene = trimesh.util.concatenate([front, back])
    K_wide = intrinsics_matrix(0.4 * W, 0.4 * W, (W - 1) / 2, (H - 1) / 2)
    visible = cull_mesh(scene, np.eye(4)[None], K_wide, W, W, occlusion=False)
    assert len(visible.faces) == len(scene.faces)
    culled = cull_mesh(scene, np.eye(4)[None], K_wide, W, W, occlusion=True)
    c = culled.triangles_center
    on_back = np.isclose(c[:, 2], 2.0)
    in_shadow = on_back & (np.abs(c[:, 0]) < 0.45) & (np.abs(c[:, 1]) < 0.45)
    assert not in_shadow.any()
    assert np.sum(np.isclose(c[:, 2], 1.0)) == len(front.faces)
    outside = np.isclose(back.triangles_center[:, 2], 2.0) & ((np.abs(back.triangles_center[:, :2]) > 0.55)
                                                              .any(axis=1))
    assert np.sum(on_back & (np.abs(c[:, :2]) > 0.55).any(axis=1)) == int(outside.sum())


# ---------------------------------------------------------------- depth rendering / depth L1

def test_render_depth_backprojects_onto_the_surface(rng):
    # A tilted plane seen from a random camera: rendered depth back-projected with lrslam.camera lands on the
    # plane to float32 precision (with the half-pixel offset wrong the error would be ~1 mm).
    n = np.array([0.3, -0.2, 1.0])
    n /= np.linalg.norm(n)
    plane = grid_plane(-3, 3, -3, 3, 0.0, n=3)
    T_tilt = make_pose(trimesh.geometry.align_vectors([0, 0, 1], n)[:3, :3], np.zeros(3))
    plane.apply_transform(T_tilt)
    T_w_c = make_pose(np.diag([1.0, -1.0, -1.0]), 1.5 * n) @ random_pose(rng, 0.0, 10.0)
    depth = render_depth(plane, T_w_c, K, W, H)[0]
    assert np.isfinite(depth).all()
    pts = transform_points(T_w_c, backproject_depth(depth, K).reshape(-1, 3))
    assert np.abs(pts @ n).max() < 2e-6


def test_depth_l1_of_shifted_plane_is_exact(rng):
    gt = grid_plane(-3, 3, -3, 3, 1.0, n=3)
    est = grid_plane(-3, 3, -3, 3, 1.02, n=3)
    T = random_pose(rng, 2.0, 180.0)  # the same rigid motion of the world changes nothing
    views = np.stack([T @ make_pose(np.eye(3), [0.1 * i, -0.05 * i, 0.0]) for i in range(3)])
    assert depth_l1(est.apply_transform(T), gt.apply_transform(T), K, W, H, views) == pytest.approx(2.0,
                                                                                                  abs=1e-4)


def test_depth_l1_counts_missing_estimate_as_zero_depth():
    gt = grid_plane(-3, 3, -3, 3, 1.0, n=3)
    est_behind = grid_plane(-0.1, 0.1, -0.1, 0.1, -1.0, n=2)  # never hit from the view
    assert depth_l1(est_behind, gt, K, W, H, np.eye(4)[None]) == pytest.approx(100.0, abs=1e-4)


def test_depth_l1_edge_cases(caplog):
    gt = grid_plane(-3, 3, -3, 3, 1.0, n=3)
    with caplog.at_level(logging.WARNING):
        assert depth_l1(empty_mesh(), gt, K, W, H, np.eye(4)[None]) == float("inf")
    assert "no surface" in caplog.text
    looking_away = make_pose(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
    with pytest.raises(InputError, match="none of the 1 views"):
        depth_l1(gt, gt, K, W, H, looking_away[None])


def test_random_views(rng):
    traj = np.stack([random_pose(rng, 2.0, 180.0) for _ in range(10)])
    views = random_views(traj, 25, seed=3, max_trans_m=0.1, max_rot_deg=10.0)
    assert views.shape == (25, 4, 4) and all(is_valid_pose(v) for v in views)
    np.testing.assert_array_equal(views, random_views(traj, 25, seed=3, max_trans_m=0.1, max_rot_deg=10.0))
    dist = np.linalg.norm(views[:, None, :3, 3] - traj[None, :, :3, 3], axis=-1).min(axis=1)
    assert dist.max() <= 0.1 + 1e-12
    with pytest.raises(InputError):
        random_views(np.full((3, 4, 4), np.nan), 5)
