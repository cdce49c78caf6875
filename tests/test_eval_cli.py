"""``lrslam eval ate|mesh`` (typer CliRunner on eval_app) and the trajectory plot."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from typer.testing import CliRunner

from lrslam.errors import InputError
from lrslam.geometry import make_pose, random_pose
from lrslam.evaluation.ate import compute_ate
from lrslam.cli.evaluate import eval_app
from lrslam.pipeline.plots import plot_trajectories, read_ate_labels, trajectory_figure
from lrslam.trajectory_io import write_tum

runner = CliRunner()


@pytest.fixture
def trajectories(tmp_path, rng):
    ts = np.arange(60) / 30.0
    gt = np.stack([make_pose(np.eye(3), [np.cos(t), np.sin(t), 0.1 * t]) for t in ts])
    est = random_pose(rng, 1.0, 90.0) @ np.stack([T @ random_pose(rng, 0.02, 1.0) for T in gt])
    return ts, est, gt, write_tum(tmp_path / "est.txt", ts, est), write_tum(tmp_path / "gt.txt", ts, gt)


def grid_plane_file(path, z: float, half: float) -> str:
    """A (2 half) x (2 half) m square at height z, 10 x 10 cells (200 faces), written as PLY."""
    xs, ys = np.meshgrid(np.linspace(-half, half, 11), np.linspace(-half, half, 11), indexing="ij")
    verts = np.stack([xs.ravel(), ys.ravel(), np.full(xs.size, z)], axis=1)
    idx = np.arange(121).reshape(11, 11)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    trimesh.Trimesh(verts, faces, process=False).export(path)
    return str(path)


def test_eval_ate_text_and_json(trajectories):
    ts, est, gt, est_path, gt_path = trajectories
    ref = compute_ate(ts, est, ts, gt)
    res = runner.invoke(eval_app, ["ate", str(est_path), str(gt_path)])
    assert res.exit_code == 0, res.output
    assert res.output.startswith(f"ATE RMSE: {ref.rmse_cm:.3f} cm  mean: {ref.mean_cm:.3f}  ")
    assert "(60 matched)" in res.output
    res = runner.invoke(eval_app, ["ate", str(est_path), str(gt_path), "--json", "--max-dt", "0.001"])
    out = json.loads(res.output)
    assert out["ate_rmse_cm"] == pytest.approx(ref.rmse_cm, abs=1e-9) and out["n_matched"] == 60
    assert set(out) == {"ate_rmse_cm", "ate_mean_cm", "ate_median_cm", "ate_max_cm", "ate_std_cm", "n_matched"}


def test_eval_ate_no_align(tmp_path):
    ts = np.arange(10) * 0.1
    est = np.stack([make_pose(np.eye(3), [t, 0, 0]) for t in ts])
    gt = make_pose(np.eye(3), [0.0, 0.0, 0.07]) @ est
    args = ["ate", str(write_tum(tmp_path / "e.txt", ts, est)), str(write_tum(tmp_path / "g.txt", ts, gt)), "--json"]
    assert json.loads(runner.invoke(eval_app, args + ["--no-align"]).output)["ate_rmse_cm"] == pytest.approx(7.0)


def test_eval_ate_bad_files_raise_input_error(tmp_path, trajectories):
    *_, est_path, gt_path = trajectories
    res = runner.invoke(eval_app, ["ate", str(tmp_path / "nope.txt"), str(gt_path)])
    assert isinstance(res.exception, InputError) and "nope.txt" in str(res.exception)
    (tmp_path / "garbled.txt").write_text("# header\n0.0 1 2 3 0 0 0\n")
    res = runner.invoke(eval_app, ["ate", str(est_path), str(tmp_path / "garbled.txt")])
    assert isinstance(res.exception, InputError) and "garbled.txt:2" in str(res.exception)
    assert len(str(res.exception).splitlines()) == 1
    far = tmp_path / "far.txt"
    write_tum(far, np.arange(5) + 100.0, np.repeat(np.eye(4)[None], 5, axis=0))
    res = runner.invoke(eval_app, ["ate", str(est_path), str(far)])
    assert isinstance(res.exception, InputError) and "associate" in str(res.exception)


def test_eval_mesh(tmp_path):
    # 50k samples on 0.36 m^2: sample spacing ~1.3 mm, so the 1 cm offset reads as ~1.01 cm.
    gt = grid_plane_file(tmp_path / "gt.ply", 1.0, half=0.3)
    est = grid_plane_file(tmp_path / "est.ply", 1.01, half=0.3)
    no_icp = ["--no-icp", "--depth-views", "0"]   # a rigid 1 cm offset is what ICP removes
    res = runner.invoke(eval_app, ["mesh", est, gt, "--n-points", "50000", *no_icp, "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    assert out["accuracy_cm"] == pytest.approx(1.0, abs=0.03) and out["completion_ratio"] == 100.0
    res = runner.invoke(eval_app, ["mesh", est, gt, "--n-points", "2000", *no_icp])
    assert res.output.startswith("Accuracy: ") and "Completion ratio: 100.00 % (< 5 cm)" in res.output


def test_eval_mesh_with_culling_and_depth(tmp_path):
    gt = grid_plane_file(tmp_path / "gt.ply", 1.0, half=2.0)
    est = grid_plane_file(tmp_path / "est.ply", 1.01, half=2.0)
    traj = write_tum(tmp_path / "traj.txt", np.arange(3) * 0.1,
                     np.stack([make_pose(np.eye(3), [0.05 * i, 0, 0]) for i in range(3)]))
    cam = ["--traj", str(traj), "--intrinsics", "40,40,31.5,23.5", "--size", "64,48"]
    res = runner.invoke(eval_app, ["mesh", est, gt, *cam, "--n-points", "20000", "--depth-views", "4",
                                   "--depth-l1", "trajectory", "--no-icp", "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    # Culling to the frustums keeps |x| <~ 0.9 m, |y| <~ 0.6 m of the 4 m planes: ~1/6 of their 200 faces.
    assert 20 < out["n_gt"] < 60 and 20 < out["n_est"] < 60
    # Views tilted by <= 10 deg: the 1 cm normal offset reads as 1 / cos(tilt) <= 1.016 cm of depth.
    assert 1.0 - 1e-4 <= out["depth_l1_cm"] <= 1.016
    res = runner.invoke(eval_app, ["mesh", est, gt, "--traj", str(traj)])
    assert isinstance(res.exception, InputError) and "--intrinsics" in str(res.exception)
    res = runner.invoke(eval_app, ["mesh", est, gt, *cam[:2], "--intrinsics", "40,40", "--size", "64,48"])
    assert isinstance(res.exception, InputError) and "fx,fy,cx,cy" in str(res.exception)
    res = runner.invoke(eval_app, ["mesh", str(tmp_path / "missing.ply"), gt])
    assert isinstance(res.exception, InputError) and "missing.ply" in str(res.exception)


def test_eval_mesh_moves_estimate_into_gt_world(tmp_path, rng):
    # The estimated world is the GT world moved by T: with --est-traj the mesh is moved back before comparing.
    T = random_pose(rng, 1.0, 60.0)
    gt = grid_plane_file(tmp_path / "gt.ply", 1.0, half=0.3)
    est_mesh = trimesh.load(gt, process=False)
    est_mesh.apply_transform(T)
    est_mesh.export(tmp_path / "est.ply")
    ts = np.arange(20) * 0.1
    gt_poses = np.stack([make_pose(np.eye(3), [0.05 * np.cos(i), 0.05 * np.sin(i), 0.02 * i]) for i in range(20)])
    traj = write_tum(tmp_path / "traj.txt", ts, gt_poses)
    est_traj = write_tum(tmp_path / "est_traj.txt", ts, T @ gt_poses)
    base = ["mesh", str(tmp_path / "est.ply"), gt, "--n-points", "50000", "--no-icp", "--depth-views", "0", "--json"]
    cam = ["--traj", str(traj), "--intrinsics", "40,40,31.5,23.5", "--size", "64,48"]
    moved = json.loads(runner.invoke(eval_app, base).output)
    aligned = json.loads(runner.invoke(eval_app, base + cam + ["--est-traj", str(est_traj)]).output)
    assert moved["accuracy_cm"] > 5.0
    assert aligned["accuracy_cm"] < 0.3 and aligned["completion_ratio"] == 100.0


def test_plot_trajectories_writes_png(tmp_path, trajectories):
    ts, est, gt, *_ = trajectories
    for name, gt_arg in (("with_gt.png", (ts, gt)), ("no_gt.png", None)):
        path = plot_trajectories(tmp_path / "plots" / name, {"fused": (ts, est), "frontend": (ts, gt)}, gt_arg,
                                 title="test")
        data = path.read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000
    assert read_ate_labels(tmp_path / "plots" / "no_gt.png") == {}


def test_plot_labels_are_the_legend_of_the_given_evaluations(tmp_path, trajectories):
    """With ``ates`` the plot shows those evaluations (the run's metrics), aligned by their ``T_align``, and
    evaluates nothing itself; without, it evaluates each trajectory against ``gt`` (compute_ate)."""
    from dataclasses import replace

    ts, est, gt, *_ = trajectories
    res = compute_ate(ts, est, ts, gt)
    given = replace(res, rmse_cm=12.345)          # a number the plot could not have computed itself
    fig, labels = trajectory_figure({"fused": (ts, est), "seed": (ts, est)}, (ts, gt), ates={"fused": given})
    assert labels == {"fused": "fused (RMSE 12.35 cm)"}          # "seed" has no evaluation: drawn as given
    top, err_ax = fig.axes
    assert [t.get_text() for t in err_ax.get_legend().get_texts()] == list(labels.values())
    fused_xy = top.lines[1].get_xydata()          # after the ground truth's line
    aligned = est[:, :3, 3] @ res.T_align[:3, :3].T + res.T_align[:3, 3]
    np.testing.assert_allclose(fused_xy, aligned[:, :2], atol=1e-9)   # the GT's widest axes: x and y
    own = plot_trajectories(tmp_path / "own.png", {"fused": (ts, est)}, (ts, gt))
    assert read_ate_labels(own) == {"fused": f"fused (RMSE {res.rmse_cm:.2f} cm)"}
