"""Dataset readers on tiny synthetic folders written in each dataset's exact layout (32x24 images unless a
reader's default calibration needs its native size)."""

from __future__ import annotations

import logging
from pathlib import Path

import cv2
import numpy as np
import pytest
from pydantic import ValidationError
from scipy.spatial.transform import Rotation

from lrslam.errors import DatasetError, InputError
from lrslam.datasets import READERS, ReaderOptions, detect_layout, open_sequence
from lrslam.datasets.association import associate, interpolate_poses
from lrslam.datasets.tum import FREIBURG_CAMERAS, freiburg_camera_from_name
from lrslam.geometry import make_pose
from lrslam.trajectory_io import write_tum

W, H = 32, 24
SMALL_K = dict(fx=30.0, fy=31.0, cx=15.5, cy=11.5)  # intrinsics override for 32x24 TUM/Replica fixtures
T0, DT = 100.0, 1.0 / 30.0


# ------------------------------------------------------------------------------------------- fixture writers
def frame_rgb(i: int, w: int = W, h: int = H) -> np.ndarray:
    """Flat colour identifying frame i (RGB)."""
    return np.broadcast_to(np.array([10 * i + 20, 100, 200], np.uint8), (h, w, 3)).copy()


def frame_depth_raw(i: int, scale: float, w: int = W, h: int = H) -> np.ndarray:
    """(1 + 0.1 i) metres everywhere except an invalid (0) top-left pixel."""
    d = np.full((h, w), round((1.0 + 0.1 * i) * scale), np.uint16)
    d[0, 0] = 0
    return d


def write_rgb(path: Path, rgb: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))


def write_depth(path: Path, raw: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    assert cv2.imwrite(str(path), raw)


def gt_pose(t: float) -> np.ndarray:
    """Closed-form trajectory: translation linear in t, rotation about a fixed axis with angle linear in t, so
    linear interpolation + slerp between samples reproduce it exactly."""
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    return make_pose(Rotation.from_rotvec(axis * 0.5 * (t - T0)).as_matrix(), [0.3 * (t - T0), -0.1, 2.0])


def write_tum_folder(root: Path, n: int = 5, depth_dt: float = 0.004, gt: bool = True,
                     size: tuple[int, int] = (W, H)) -> Path:
    """TUM layout: rgb at T0 + i/30, depth ``depth_dt`` later, 100 Hz ground truth covering all frames."""
    rgb_lines, depth_lines = ["# color images", "# timestamp filename"], ["# depth maps"]
    for i in range(n):
        t_rgb, t_d = T0 + i * DT, T0 + i * DT + depth_dt
        write_rgb(root / f"rgb/{t_rgb:.6f}.png", frame_rgb(i, *size))
        write_depth(root / f"depth/{t_d:.6f}.png", frame_depth_raw(i, 5000.0, *size))
        rgb_lines.append(f"{t_rgb:.6f} rgb/{t_rgb:.6f}.png")
        depth_lines.append(f"{t_d:.6f} depth/{t_d:.6f}.png")
    (root / "rgb.txt").write_text("\n".join(rgb_lines) + "\n")
    (root / "depth.txt").write_text("\n".join(depth_lines) + "\n")
    if gt:
        t_gt = T0 - 0.05 + 0.01 * np.arange(int((n * DT + 0.1) / 0.01))
        write_tum(root / "groundtruth.txt", t_gt, np.stack([gt_pose(t) for t in t_gt]))
    return root


def write_replica_folder(root: Path, n: int = 3, size: tuple[int, int] = (W, H)) -> list[np.ndarray]:
    poses = [make_pose(Rotation.from_rotvec([0.0, 0.1 * i, 0.0]).as_matrix(), [i * 0.1, 0.0, 0.0])
             for i in range(n)]
    for i in range(n):
        write_rgb(root / f"results/frame{i:06d}.jpg", frame_rgb(i, *size))
        write_depth(root / f"results/depth{i:06d}.png", frame_depth_raw(i, 6553.5, *size))
    (root / "traj.txt").write_text("".join(" ".join(f"{x:.17g}" for x in T.ravel()) + "\n" for T in poses))
    return poses


def write_7scenes_folder(root: Path, n: int = 4, intrinsics: bool = True) -> None:
    for i in range(n):
        write_rgb(root / f"frame-{i:06d}.color.jpg", frame_rgb(i))
        raw = frame_depth_raw(i, 1000.0)
        raw[1, 1] = 65535
        write_depth(root / f"frame-{i:06d}.depth.png", raw)
        np.savetxt(root / f"frame-{i:06d}.pose.txt", make_pose(np.eye(3), [0.0, 0.0, 0.01 * i]))
    if intrinsics:
        np.savetxt(root / "camera-intrinsics.txt", [[28.0, 0, 16.0], [0, 28.0, 12.0], [0, 0, 1]])


# ------------------------------------------------------------------------------------ options and registry
def test_reader_options_validation():
    assert ReaderOptions().stride == 1 and ReaderOptions().intrinsics_override() is None
    np.testing.assert_array_equal(ReaderOptions(**SMALL_K).intrinsics_override(),
                                  [[30.0, 0, 15.5], [0, 31.0, 11.5], [0, 0, 1]])
    for bad in (dict(stride=0), dict(max_frames=0), dict(crop_border=-1), dict(resize=(0, 10)),
                dict(fx=500.0), dict(SMALL_K, fx=float("nan")), dict(depth_scale=-1.0), dict(unknown=1)):
        with pytest.raises(ValidationError):
            ReaderOptions(**bad)


def test_registry_and_layout_detection(tmp_path):
    assert set(READERS) == {"tum", "synthetic", "replica", "scannet", "7scenes", "rosbag"}
    assert all(cls.name == name for name, cls in READERS.items())
    write_tum_folder(tmp_path / "tum", n=1)
    write_replica_folder(tmp_path / "replica", n=1)
    write_7scenes_folder(tmp_path / "7s", n=1)
    (tmp_path / "scannet" / "color").mkdir(parents=True)
    (tmp_path / "scannet" / "depth").mkdir()
    assert [detect_layout(tmp_path / d) for d in ("tum", "replica", "7s", "scannet")] == \
        ["tum", "replica", "7scenes", "scannet"]
    (tmp_path / "tum" / "scene.yaml").write_text("{}\n")
    assert detect_layout(tmp_path / "tum") == "synthetic"

    (tmp_path / "empty").mkdir()
    with pytest.raises(DatasetError, match="unknown dataset layout"):
        open_sequence(tmp_path / "empty")
    with pytest.raises(DatasetError, match="dataset folder not found"):
        open_sequence(tmp_path / "nope")
    with pytest.raises(DatasetError, match="not a folder"):
        open_sequence(tmp_path / "tum" / "rgb.txt")
    with pytest.raises(DatasetError, match="unknown dataset reader 'kitti'"):
        open_sequence(tmp_path / "7s", reader="kitti")
    (tmp_path / "7s" / "results").mkdir()
    with pytest.raises(DatasetError, match="ambiguous"):
        detect_layout(tmp_path / "7s")


# ----------------------------------------------------------------------------------------------------- TUM
def _associate_py(first, second, max_difference=0.02):
    """TUM's associate.py, verbatim algorithm (O(N M)), as the oracle."""
    first_keys, second_keys = list(first), list(second)
    matches = sorted((abs(a - b), a, b) for a in first_keys for b in second_keys if abs(a - b) < max_difference)
    out = []
    for _, a, b in matches:
        if a in first_keys and b in second_keys:
            first_keys.remove(a)
            second_keys.remove(b)
            out.append((a, b))
    return sorted(out)


def test_associate_matches_tum_associate_py(rng):
    for _ in range(5):
        a = np.sort(rng.uniform(0, 3, 60))
        b = rng.permutation(np.concatenate([a[rng.permutation(60)[:45]] + rng.normal(0, 0.01, 45),
                                            rng.uniform(0, 3, 10)]))
        pairs = associate(a, b)
        assert [(a[i], b[j]) for i, j in pairs] == _associate_py(a, b)
    assert associate(np.array([0.0]), np.array([0.02])).shape == (0, 2)  # strictly less than 0.02 s


def test_interpolate_poses_closed_form():
    t_s = np.array([0.0, 0.01, 0.02, 0.10])
    P = np.stack([make_pose(Rotation.from_rotvec([0, 0, 10 * t]).as_matrix(), [t, 0, 0]) for t in t_s])
    out = interpolate_poses(np.array([0.004, 0.02, 0.05, 0.115, 0.5]), t_s, P)
    np.testing.assert_allclose(out[0][:3, 3], [0.004, 0, 0], atol=1e-15)  # interpolated
    np.testing.assert_allclose(out[0][:3, :3], Rotation.from_rotvec([0, 0, 0.04]).as_matrix(), atol=1e-14)
    np.testing.assert_array_equal(out[1], P[2])  # exact sample
    assert np.isnan(out[2]).all()  # 0.03 s from the nearest sample
    np.testing.assert_array_equal(out[3], P[3])  # only one neighbour within 0.02 s: nearest
    assert np.isnan(out[4]).all()


def test_tum_frames_and_interpolated_ground_truth(tmp_path):
    root = write_tum_folder(tmp_path / "seq", n=5)
    seq = open_sequence(root, options=ReaderOptions(**SMALL_K))
    assert seq.name == "tum" and len(seq) == 5 and (seq.width, seq.height) == (W, H)
    np.testing.assert_allclose(seq.timestamps, np.round(T0 + DT * np.arange(5), 6))
    np.testing.assert_array_equal(seq.K, [[30.0, 0, 15.5], [0, 31.0, 11.5], [0, 0, 1]])
    assert seq.bound is None and seq.gt_mesh_path is None
    frames = list(seq)
    for i, f in enumerate(frames):
        assert f.index == i and f.rgb.dtype == np.uint8 and f.rgb.shape == (H, W, 3)
        np.testing.assert_array_equal(f.rgb[5, 5], [10 * i + 20, 100, 200])  # RGB order, no undistortion
        assert f.depth.dtype == np.float32 and f.depth[0, 0] == 0
        np.testing.assert_allclose(f.depth[1:, 1:], 1.0 + 0.1 * i, rtol=1e-6)
        np.testing.assert_allclose(f.T_w_c_gt, gt_pose(f.timestamp), atol=1e-12)
    np.testing.assert_allclose(seq.gt_poses(), [gt_pose(t) for t in seq.timestamps], atol=1e-12)
    assert seq[-1].index == 4
    with pytest.raises(IndexError):
        seq[5]


def test_tum_association_drops_and_failures(tmp_path, caplog):
    root = write_tum_folder(tmp_path / "seq", n=4)
    lines = (root / "depth.txt").read_text().splitlines()
    t_last = float(lines[-1].split()[0])
    lines[-1] = f"{t_last + 0.025:.6f} {lines[-1].split()[1]}"  # last depth now 29 ms from its colour image
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    with caplog.at_level(logging.WARNING):
        seq = open_sequence(root, options=ReaderOptions(**SMALL_K))
    assert len(seq) == 3 and "1 of 4 colour images have no depth" in caplog.text

    # Mismatched lists whose stamps never come within 0.02 s: nothing associates.
    (root / "depth.txt").write_text("\n".join(f"{T0 + 10 + i:.6f} depth/x{i}.png" for i in range(3)) + "\n")
    with pytest.raises(DatasetError, match=r"no rgb/depth pair within 0.02 s \(rgb.txt: 4 stamps"):
        open_sequence(root, options=ReaderOptions(**SMALL_K))
    (root / "rgb.txt").write_text("# nothing\n")
    with pytest.raises(DatasetError, match="empty sequence"):
        open_sequence(root, options=ReaderOptions(**SMALL_K))


def test_tum_without_or_with_partial_ground_truth(tmp_path):
    root = write_tum_folder(tmp_path / "seq", n=3, gt=False)
    seq = open_sequence(root, options=ReaderOptions(**SMALL_K))
    assert seq.gt_poses() is None and seq[0].T_w_c_gt is None
    # Ground truth with a gap around frame 1 (T0 + 33 ms): that frame gets none.
    t_gt = np.array([T0 - 0.01, T0, T0 + 0.06, T0 + 0.07])
    write_tum(root / "groundtruth.txt", t_gt, np.stack([gt_pose(t) for t in t_gt]))
    seq = open_sequence(root, options=ReaderOptions(**SMALL_K))
    gt = seq.gt_poses()
    assert np.isfinite(gt[0]).all() and np.isnan(gt[1]).all() and np.isfinite(gt[2]).all()
    assert seq[1].T_w_c_gt is None and seq[2].T_w_c_gt is not None


def test_freiburg_camera_choice(tmp_path, caplog):
    assert [freiburg_camera_from_name(s) for s in ("rgbd_dataset_freiburg2_xyz", "tum-fr3-office", "FR1_desk",
                                                   "office", "fr12", "afr1")] == [2, 3, 1, None, None, None]
    root = write_tum_folder(tmp_path / "rgbd_dataset_freiburg2_xyz", n=1, gt=False, size=(640, 480))
    (fx, fy, cx, cy), _ = FREIBURG_CAMERAS[2]
    np.testing.assert_array_equal(open_sequence(root).K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    root = write_tum_folder(tmp_path / "office", n=1, gt=False, size=(640, 480))
    with pytest.raises(DatasetError, match="unknown camera.*intrinsics.yaml"):  # never a silent Freiburg 1
        open_sequence(root)
    (root / "rgb.txt").write_text("# file: 'rgbd_dataset_freiburg3_long_office.bag'\n"
                                  + (root / "rgb.txt").read_text())
    assert open_sequence(root).K[0, 0] == FREIBURG_CAMERAS[3][0][0]  # bag name in the list header
    with pytest.raises(DatasetError, match="image is 32x24 but the dataset states 640x480"):
        open_sequence(write_tum_folder(tmp_path / "fr1_small", n=1, gt=False))


def test_tum_camera_of_another_camera_from_its_file_or_options(tmp_path, caplog):
    root = write_tum_folder(tmp_path / "my_kinect", n=1, gt=False)
    (root / "intrinsics.yaml").write_text("fx: 30.0\nfy: 31.0\ncx: 15.5\ncy: 11.5\ndepth_scale: 2500\n")
    with caplog.at_level(logging.WARNING):
        seq = open_sequence(root)
    np.testing.assert_array_equal(seq.K, [[30, 0, 15.5], [0, 31, 11.5], [0, 0, 1]])
    assert seq.depth_scale == 2500 and "Freiburg" not in caplog.text
    (root / "intrinsics.yaml").write_text("fx: 30.0\nfy: 31.0\ncx: 15.5\nc_y: 11.5\n")
    with pytest.raises(DatasetError, match="intrinsics.yaml: cy"):
        open_sequence(root)
    (root / "intrinsics.yaml").unlink()
    opts = ReaderOptions(fx=40.0, fy=40.0, cx=16.0, cy=12.0, distortion=(0.1, 0, 0, 0, 0))
    seq = open_sequence(root, options=opts)
    assert seq.K[0, 0] == 40.0 and seq._undistort is not None


def test_tum_nan_ground_truth_line_is_missing_ground_truth(tmp_path):
    root = write_tum_folder(tmp_path / "fr1_nan", n=3, size=(640, 480))
    lines = (root / "groundtruth.txt").read_text().splitlines()
    t_frame1 = T0 + DT
    # blank every motion-capture sample within 0.02 s of frame 1: that frame has no ground truth
    out = []
    for ln in lines:
        if not ln.startswith("#") and abs(float(ln.split()[0]) - t_frame1) < 0.02:
            ln = ln.split()[0] + " nan nan nan nan nan nan nan"
        out.append(ln)
    (root / "groundtruth.txt").write_text("\n".join(out) + "\n")
    gt = open_sequence(root).gt_poses()
    assert np.isfinite(gt[0]).all() and np.isnan(gt[1]).all() and np.isfinite(gt[2]).all()


def test_7scenes_nan_pose_is_missing_ground_truth(tmp_path, caplog):
    write_7scenes_folder(tmp_path / "s", n=3)
    (tmp_path / "s" / "frame-000001.pose.txt").write_text("nan " * 16)
    with caplog.at_level(logging.WARNING):
        gt = open_sequence(tmp_path / "s").gt_poses()
    assert np.isnan(gt[1]).all() and np.isfinite(gt[0]).all() and "1 of 3 frames" in caplog.text


def test_binary_list_file_is_a_dataset_error(tmp_path):
    root = write_tum_folder(tmp_path / "fr1_bin", n=1, gt=False, size=(640, 480))
    (root / "depth.txt").write_bytes(b"\xff\xfe\x00\x81")
    with pytest.raises(DatasetError, match="depth.txt: not a text"):
        open_sequence(root)


def test_tum_undistorts_colour_only(tmp_path):
    """A blob drawn where the distorted fr1 camera sees a point must land on the point's pinhole projection."""
    (fx, fy, cx, cy), (k1, k2, p1, p2, k3) = FREIBURG_CAMERAS[1]
    u, v = 560.0, 420.0  # ideal pinhole pixel, near the corner where distortion is ~6 px
    x, y = (u - cx) / fx, (v - cy) / fy
    r2 = x * x + y * y
    radial = 1 + k1 * r2 + k2 * r2**2 + k3 * r2**3
    ud = fx * (x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)) + cx
    vd = fy * (y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y) + cy
    assert np.hypot(ud - u, vd - v) > 4
    root = write_tum_folder(tmp_path / "freiburg1_blob", n=1, gt=False, size=(640, 480))
    vv, uu = np.mgrid[0:480, 0:640]
    blob = 250 * np.exp(-((uu - ud) ** 2 + (vv - vd) ** 2) / (2 * 2.0**2))
    write_rgb(next((root / "rgb").iterdir()), np.repeat(blob[..., None], 3, axis=2).astype(np.uint8))
    raw_depth = cv2.imread(str(next((root / "depth").iterdir())), cv2.IMREAD_UNCHANGED)

    def centroid(img):
        w = img[..., 0].astype(float)
        w = np.where(w > 20, w, 0)
        return (w * uu).sum() / w.sum(), (w * vv).sum() / w.sum()

    f = open_sequence(root)[0]
    assert np.hypot(*(np.subtract(centroid(f.rgb), (u, v)))) < 0.3
    np.testing.assert_array_equal(f.depth, raw_depth.astype(np.float32) / np.float32(5000))  # untouched
    f = open_sequence(root, options=ReaderOptions(undistort=False))[0]
    assert np.hypot(*(np.subtract(centroid(f.rgb), (ud, vd)))) < 0.3


# -------------------------------------------------------------------------- selection, resize and crop
def test_stride_and_max_frames(tmp_path):
    root = write_tum_folder(tmp_path / "seq", n=5)
    seq = open_sequence(root, options=ReaderOptions(stride=2, max_frames=2, **SMALL_K))
    assert len(seq) == 2 and [f.index for f in seq] == [0, 1]
    np.testing.assert_allclose(seq.timestamps, np.round(T0 + DT * np.array([0, 2]), 6))
    np.testing.assert_array_equal(seq[1].rgb[0, 0], frame_rgb(2)[0, 0])
    np.testing.assert_allclose(seq.gt_poses()[1], gt_pose(seq.timestamps[1]), atol=1e-12)
    assert len(open_sequence(root, options=ReaderOptions(stride=2, **SMALL_K))) == 3


def test_resize_and_crop_keep_intrinsics_consistent(tmp_path):
    root = write_tum_folder(tmp_path / "seq", n=1, gt=False)
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 0] = 8 * np.arange(W)[None, :]  # red channel = 8 u: a ramp in the source column
    rgb[..., 1] = 8 * np.arange(H)[:, None]
    write_rgb(next((root / "rgb").iterdir()), rgb)
    opts = ReaderOptions(resize=(16, 12), crop_border=2, **SMALL_K)
    seq = open_sequence(root, options=opts)
    fx, fy = 30.0 * 0.5, 31.0 * 0.5
    cx, cy = (15.5 + 0.5) * 0.5 - 0.5 - 2, (11.5 + 0.5) * 0.5 - 0.5 - 2
    np.testing.assert_allclose(seq.K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], atol=1e-12)
    assert (seq.width, seq.height) == (12, 8)
    f = seq[0]
    assert f.rgb.shape == (8, 12, 3) and f.depth.shape == (8, 12) and np.all(f.depth > 0)
    # Each output pixel's ray must hit the source column/row the image content came from.
    u_src = (np.arange(12) - cx) / fx * 30.0 + 15.5
    v_src = (np.arange(8) - cy) / fy * 31.0 + 11.5
    np.testing.assert_allclose(f.rgb[0, :, 0] / 8.0, u_src, atol=1e-9)
    np.testing.assert_allclose(f.rgb[:, 0, 1] / 8.0, v_src, atol=1e-9)
    with pytest.raises(InputError, match="crop_border=12 leaves no pixels"):
        open_sequence(root, options=ReaderOptions(crop_border=12, **SMALL_K))


# --------------------------------------------------------------------------------------------- bad input
def test_bad_images(tmp_path, caplog):
    root = write_tum_folder(tmp_path / "seq", n=4, gt=False)
    opts = ReaderOptions(**SMALL_K)
    rgb_files = sorted((root / "rgb").iterdir())
    depth_files = sorted((root / "depth").iterdir())
    rgb_files[1].write_bytes(b"definitely not a png")
    write_depth(depth_files[2], np.full((H, W), 7, np.uint8))  # 8-bit depth
    write_depth(depth_files[3], np.zeros((H, W), np.uint16))  # all-zero depth: valid but empty
    seq = open_sequence(root, options=opts)
    with pytest.raises(DatasetError, match=rf"{rgb_files[1].name}: unreadable or corrupt image"):
        seq[1]
    with pytest.raises(DatasetError, match=r"depth has dtype uint8; expected 16-bit"):
        seq[2]
    with caplog.at_level(logging.WARNING):
        assert seq[3].valid_depth_fraction() == 0.0
        seq[3]
    assert caplog.text.count("depth has no valid pixel") == 1  # warned once

    write_depth(depth_files[2], np.ones((H // 2, W // 2), np.uint16))
    with pytest.raises(DatasetError, match="depth is 16x12 but the sequence's images are 32x24"):
        seq[2]
    write_rgb(rgb_files[3], frame_rgb(3, W * 2, H * 2))
    with pytest.raises(DatasetError, match="colour is 64x48 but its depth image is 32x24"):
        seq[3]
    with pytest.raises(DatasetError, match="principal point"):
        open_sequence(root, options=ReaderOptions(fx=30.0, fy=30.0, cx=100.0, cy=11.5))
    rgb_files[0].unlink()
    with pytest.raises(DatasetError, match=rf"{rgb_files[0].name}: image file not found"):
        open_sequence(root, options=opts)


def test_float_depth_nan_and_inf_become_zero(tmp_path, caplog):
    root = write_tum_folder(tmp_path / "seq", n=1, gt=False)
    depth = np.full((H, W), 2.0 * 5000, np.float32)
    depth[3, 4], depth[5, 6], depth[7, 8] = np.nan, np.inf, -5.0
    write_depth(root / "depth" / "d.tiff", depth)
    (root / "depth.txt").write_text(f"{T0:.6f} depth/d.tiff\n")
    with caplog.at_level(logging.WARNING):
        f = open_sequence(root, options=ReaderOptions(**SMALL_K))[0]
    assert np.all(np.isfinite(f.depth)) and f.depth[3, 4] == f.depth[5, 6] == f.depth[7, 8] == 0
    assert np.count_nonzero(f.depth == 2.0) == H * W - 3 and "2 NaN/inf depth pixels" in caplog.text


# ----------------------------------------------------------------------------------------------- synthetic
def test_synthetic_reader(tmp_path):
    root = write_tum_folder(tmp_path / "scene", n=2)
    (root / "scene.yaml").write_text("intrinsics: {fx: 20.0, fy: 21.0, cx: 16.0, cy: 12.0, width: 32, height: 24}\n"
                                     "depth_scale: 5000.0\nbound: [[-1, 1], [-2, 2], [0, 3]]\nseed: 3\n")
    (root / "gt_mesh.ply").write_text("ply\n")
    seq = open_sequence(root)
    assert seq.name == "synthetic"
    np.testing.assert_array_equal(seq.K, [[20.0, 0, 16.0], [0, 21.0, 12.0], [0, 0, 1]])
    np.testing.assert_array_equal(seq.bound, [[-1, 1], [-2, 2], [0, 3]])
    assert seq.gt_mesh_path == root / "gt_mesh.ply"
    np.testing.assert_allclose(seq[1].T_w_c_gt, gt_pose(seq.timestamps[1]), atol=1e-12)
    np.testing.assert_allclose(seq[1].depth[1:, 1:], 1.1, rtol=1e-6)
    (root / "scene.yaml").write_text("intrinsics: {fx: 20.0, fy: 21.0, cx: 16.0, cy: 12.0, width: 64, height: 48}\n"
                                     "depth_scale: 5000.0\nbound: [[-1, 1], [-2, 2], [0, 3]]\n")
    with pytest.raises(DatasetError, match="image is 32x24 but the dataset states 64x48"):
        open_sequence(root)
    (root / "scene.yaml").write_text("intrinsics: {fx: 20.0, fy: 21.0, cx: 16.0, cy: 12.0, width: 32, height: 24}\n"
                                     "depth_scale: 5000.0\n")
    with pytest.raises(DatasetError, match=r"scene.yaml: bound: Field required"):
        open_sequence(root)


# ---------------------------------------------------------------------------------- replica, scannet, 7scenes
def test_replica_reader(tmp_path):
    root = tmp_path / "room0"
    poses = write_replica_folder(root, n=3)
    seq = open_sequence(root, options=ReaderOptions(**SMALL_K))
    assert seq.name == "replica" and len(seq) == 3 and seq.depth_scale == 6553.5
    np.testing.assert_allclose(seq.timestamps, np.arange(3) / 30.0)
    f = seq[2]
    np.testing.assert_allclose(f.depth[1:, 1:], 1.2, atol=1e-4)
    np.testing.assert_allclose(f.rgb[5, 5], frame_rgb(2)[5, 5], atol=3)  # JPEG, RGB order
    np.testing.assert_allclose(f.T_w_c_gt, poses[2], atol=1e-15)  # OpenCV c2w, used as is
    with pytest.raises(DatasetError, match="image is 32x24 but the dataset states 1200x680"):
        open_sequence(root)  # default Replica intrinsics need 1200x680 images
    (root / "traj.txt").write_text("\n".join((root / "traj.txt").read_text().splitlines()[:2]) + "\n")
    with pytest.raises(DatasetError, match="traj.txt: 2 poses but the images go up to frame 2"):
        open_sequence(root, options=ReaderOptions(**SMALL_K))
    (root / "results" / "depth000001.png").unlink()
    with pytest.raises(DatasetError, match="depth000001.png: image file not found"):
        open_sequence(root, options=ReaderOptions(**SMALL_K))

    big = tmp_path / "office0"
    write_replica_folder(big, n=1, size=(1200, 680))
    seq = open_sequence(big)
    np.testing.assert_array_equal(seq.K, [[600.0, 0, 599.5], [0, 600.0, 339.5], [0, 0, 1]])


def test_scannet_reader(tmp_path):
    root = tmp_path / "scene0000_00"
    ids = [0, 1, 2, 10]  # numeric, not lexicographic, order
    for k, i in enumerate(ids):
        write_rgb(root / f"color/{i}.jpg", frame_rgb(k, 2 * W, 2 * H))
        write_depth(root / f"depth/{i}.png", frame_depth_raw(k, 1000.0))
        T = make_pose(np.eye(3), [k, 0, 0]) if i != 2 else np.full((4, 4), -np.inf)
        (root / "pose").mkdir(exist_ok=True)
        np.savetxt(root / f"pose/{i}.txt", T)
    (root / "intrinsic").mkdir()
    np.savetxt(root / "intrinsic/intrinsic_depth.txt", [[29, 0, 15.5, 0], [0, 29, 11.5, 0], [0, 0, 1, 0],
                                                        [0, 0, 0, 1]])
    seq = open_sequence(root)
    assert seq.name == "scannet" and len(seq) == 4
    np.testing.assert_allclose(seq.timestamps, np.array(ids) / 30.0)
    np.testing.assert_array_equal(seq.K, [[29, 0, 15.5], [0, 29, 11.5], [0, 0, 1]])
    f = seq[3]
    assert f.rgb.shape == (H, W, 3)  # colour resized to the depth size
    np.testing.assert_allclose(f.rgb[5, 5], frame_rgb(3)[5, 5], atol=3)
    np.testing.assert_allclose(f.depth[1:, 1:], 1.3, atol=1e-6)
    gt = seq.gt_poses()
    assert np.isnan(gt[2]).all() and seq[2].T_w_c_gt is None and f.T_w_c_gt[0, 3] == 3
    (root / "intrinsic/intrinsic_depth.txt").unlink()
    with pytest.raises(DatasetError, match="intrinsic_depth.txt: file not found"):
        open_sequence(root)
    (root / "depth/10.png").unlink()
    with pytest.raises(DatasetError, match=r"10.png: image file not found \(1 of 4 colour frames"):
        open_sequence(root)


def test_7scenes_reader(tmp_path):
    root = tmp_path / "seq-01"
    write_7scenes_folder(root, n=4)
    (root / "frame-000002.pose.txt").unlink()
    seq = open_sequence(root, options=ReaderOptions(stride=2))
    assert seq.name == "7scenes" and len(seq) == 2
    np.testing.assert_allclose(seq.timestamps, [0.0, 2 / 30.0])
    np.testing.assert_array_equal(seq.K, [[28.0, 0, 16.0], [0, 28.0, 12.0], [0, 0, 1]])
    f = seq[0]
    assert f.depth[1, 1] == 0 and f.depth[0, 0] == 0  # 65535 and 0 are invalid
    np.testing.assert_allclose(f.depth[2:, 2:], 1.0)
    np.testing.assert_allclose(f.T_w_c_gt, make_pose(np.eye(3), [0, 0, 0]))
    assert seq[1].T_w_c_gt is None and np.isnan(seq.gt_poses()[1]).all()
    for p in root.glob("*.pose.txt"):
        p.unlink()
    assert open_sequence(root).gt_poses() is None
    (root / "frame-000001.pose.txt").write_text("1 0 0\n")
    with pytest.raises(DatasetError, match=r"frame-000001.pose.txt: expected a 4x4 matrix \(16 numbers\), got 3"):
        open_sequence(root)

    native = tmp_path / "native"  # no camera-intrinsics.txt: the published 7-Scenes calibration
    write_rgb(native / "frame-000000.color.png", frame_rgb(0, 640, 480))
    write_depth(native / "frame-000000.depth.png", frame_depth_raw(0, 1000.0, 640, 480))
    np.testing.assert_array_equal(open_sequence(native).K, [[585.0, 0, 320.0], [0, 585.0, 240.0], [0, 0, 1]])
