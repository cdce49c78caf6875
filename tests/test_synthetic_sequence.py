"""Written synthetic sequences: TUM layout, scene.yaml, reuse, CLI, and the acceptance test -- back-projected
noise-free depth with the written K and T_w_c lies on the written ground-truth mesh."""

from __future__ import annotations

import numpy as np
import pytest

from lrslam.camera import backproject_depth, intrinsics_matrix, transform_points
from lrslam.config import load_yaml
from lrslam.errors import InputError
from lrslam.datasets.synth.noise import NoiseConfig
from lrslam.datasets.synth.render import default_intrinsics
from lrslam.datasets.synth.scene import make_scene
from lrslam.datasets.synth.trajectories import make_trajectory
from lrslam.datasets.synth.writer import generate, write_sequence
from lrslam.trajectory_io import read_tum

N = 8


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth") / "cluttered"
    return generate(out, scene="cluttered", trajectory="random_walk", n_frames=N, seed=2, show_progress=False)


def _mesh_distance(ply, points_w):
    import open3d as o3d

    rc = o3d.t.geometry.RaycastingScene()
    rc.add_triangles(o3d.t.io.read_triangle_mesh(str(ply)))
    return rc.compute_distance(o3d.core.Tensor(np.asarray(points_w, np.float32))).numpy()


def _list(path):
    return [ln.split() for ln in path.read_text().splitlines() if ln.strip() and not ln.startswith("#")]


def test_layout_and_metadata(sequence):
    import cv2

    meta = load_yaml(sequence / "scene.yaml")
    assert list(meta) == ["generator", "scene", "seed", "trajectory", "n_frames", "intrinsics", "depth_scale",
                          "bound", "noise"]
    assert meta["generator"] == "lrslam-synth" and meta["scene"] == "cluttered" and meta["seed"] == 2
    assert meta["trajectory"] == "random_walk" and meta["n_frames"] == N and meta["depth_scale"] == 5000.0
    assert meta["intrinsics"] == {"fx": 260.0, "fy": 260.0, "cx": 159.5, "cy": 119.5, "width": 320, "height": 240}
    sc = make_scene("cluttered", 2)
    np.testing.assert_allclose(meta["bound"], sc.bound)
    assert NoiseConfig(**meta["noise"]) == NoiseConfig()

    rgb_list, depth_list = _list(sequence / "rgb.txt"), _list(sequence / "depth.txt")
    stamps, poses = read_tum(sequence / "groundtruth.txt")
    assert [r[0] for r in rgb_list] == [d[0] for d in depth_list] == [f"{i / 30:.6f}" for i in range(N)]
    np.testing.assert_array_equal(stamps, [float(r[0]) for r in rgb_list])
    np.testing.assert_allclose(poses, make_trajectory("random_walk", N, sc.bound, 2), atol=1e-12)
    assert (sequence / "gt_mesh.ply").stat().st_size < 20e6
    for (t, rgb_name), (_, depth_name) in zip(rgb_list, depth_list):
        assert rgb_name == f"rgb/{t}.png" and depth_name == f"depth/{t}.png"
        rgb = cv2.imread(str(sequence / rgb_name), cv2.IMREAD_UNCHANGED)
        depth = cv2.imread(str(sequence / depth_name), cv2.IMREAD_UNCHANGED)
        assert rgb.shape == (240, 320, 3) and rgb.dtype == np.uint8
        assert depth.shape == (240, 320) and depth.dtype == np.uint16
        assert np.all(depth > 0) and depth.max() < 5000 * 7  # closed room: every pixel sees a surface
    assert sorted(p.name for p in (sequence / "rgb").iterdir()) == [f"{r[0]}.png" for r in rgb_list]


def _check_on_mesh(ply, frames):
    """frames: iterable of (depth (H, W) metres, K, T_w_c). Median and 99th percentile point-to-mesh distance."""
    pts = [transform_points(T, backproject_depth(d, K)[d > 0]) for d, K, T in frames]
    dist = _mesh_distance(ply, np.concatenate(pts))
    return np.median(dist), np.percentile(dist, 99)


def test_acceptance_backprojected_depth_lies_on_the_gt_mesh_own_loading(sequence):
    import cv2

    meta = load_yaml(sequence / "scene.yaml")
    c = meta["intrinsics"]
    K = intrinsics_matrix(c["fx"], c["fy"], c["cx"], c["cy"])
    _, poses = read_tum(sequence / "groundtruth.txt")
    frames = [(cv2.imread(str(sequence / d), cv2.IMREAD_UNCHANGED) / meta["depth_scale"], K, T)
              for (_, d), T in zip(_list(sequence / "depth.txt"), poses)]
    median, p99 = _check_on_mesh(sequence / "gt_mesh.ply", frames)
    assert median < 1e-3 and p99 < 1e-3  # depth quantisation (0.2 mm steps) dominates: median ~0.04 mm


def test_acceptance_backprojected_depth_lies_on_the_gt_mesh_reader(sequence):
    from lrslam.datasets import open_sequence

    seq = open_sequence(sequence)
    frames = list(seq)
    assert len(frames) == N
    assert all(f.valid_depth_fraction() == 1.0 for f in frames)
    np.testing.assert_allclose(frames[0].K, default_intrinsics(320, 240))
    median, p99 = _check_on_mesh(sequence / "gt_mesh.ply", [(f.depth, f.K, f.T_w_c_gt) for f in frames])
    assert median < 1e-3 and p99 < 1e-3


def test_noisy_sequence_is_off_the_mesh_by_the_noise(tmp_path):
    out = generate(tmp_path / "noisy", scene="room", trajectory="circle", n_frames=2, seed=0, width=160,
                   height=120, noise=NoiseConfig(depth_sigma=0.01), show_progress=False)
    from lrslam.datasets import open_sequence

    median, _ = _check_on_mesh(out / "gt_mesh.ply", [(f.depth, f.K, f.T_w_c_gt) for f in open_sequence(out)])
    assert 0.004 < median < 0.009  # |N(0, 1 cm)| along rays at grazing-to-frontal angles: median <= 6.7 mm


def test_generate_reuses_identical_and_rewrites_changed(tmp_path):
    out = tmp_path / "seq"
    generate(out, scene="small_room", trajectory="loop", n_frames=4, width=64, height=48, show_progress=False)
    stamp = (out / "scene.yaml").stat().st_mtime_ns
    generate(out, scene="small_room", trajectory="loop", n_frames=4, width=64, height=48, show_progress=False)
    assert (out / "scene.yaml").stat().st_mtime_ns == stamp
    generate(out, scene="small_room", trajectory="loop", n_frames=3, width=64, height=48, show_progress=False)
    assert len(list((out / "rgb").iterdir())) == 3 == load_yaml(out / "scene.yaml")["n_frames"]
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="not empty"):
        generate(tmp_path / "other", n_frames=2, width=64, height=48, show_progress=False)
    assert (tmp_path / "other" / "notes.txt").read_text() == "keep me"


def test_write_sequence_rejects_bad_input(tmp_path):
    sc = make_scene("empty")
    K = default_intrinsics(64, 48)
    with pytest.raises(InputError, match="shape"):
        write_sequence(tmp_path / "a", sc, np.eye(4), K, 64, 48, show_progress=False)
    with pytest.raises(InputError, match="principal point"):
        write_sequence(tmp_path / "a", sc, np.eye(4)[None], K, 16, 12, show_progress=False)
    bad = np.eye(4)[None].copy()
    bad[0, 0, 0] = 2.0
    with pytest.raises(InputError, match="rigid"):
        write_sequence(tmp_path / "a", sc, bad, K, 64, 48, show_progress=False)


def test_cli(tmp_path):
    import typer
    from typer.testing import CliRunner

    from lrslam.cli.synth import synth

    app = typer.Typer()
    app.command()(synth)
    runner = CliRunner()
    out = tmp_path / "cli"
    res = runner.invoke(app, [str(out), "--frames", "3", "--width", "64", "--height", "48", "--noise", "kinect",
                              "--trajectory", "helix", "--scene", "small_room", "--seed", "5"])
    assert res.exit_code == 0, res.output
    meta = load_yaml(out / "scene.yaml")
    assert meta["noise"]["kinect"] and meta["seed"] == 5 and meta["trajectory"] == "helix"
    assert meta["intrinsics"]["width"] == 64 and len(list((out / "depth").iterdir())) == 3
    for args, msg in ((["--noise", "speckle"], "unknown noise preset"), (["--scene", "castle"], "unknown scene"),
                      (["--trajectory", "zigzag"], "unknown trajectory"),
                      (["--noise", "gaussian", "--depth-sigma", "-1"], "--depth-sigma")):
        res = runner.invoke(app, [str(tmp_path / "bad"), "--frames", "2", *args])
        assert isinstance(res.exception, InputError) and msg in str(res.exception)
        assert "\n" not in str(res.exception)
