"""The ``rosbag`` reader: a tiny synthetic sequence written into a ROS 1 bag and a ROS 2 bag (with ``rosbags``'
own writers) reads back as the same frames as a TUM-layout copy, runs through ``lrslam run`` to the same
trajectory, and every bad bag is a one-line exit-2 error naming the topic or the file."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from test_bad_input import run_cli  # the real command line in-process: (exit code, stdout, stderr)

from lrslam.datasets import READERS, open_sequence
from lrslam.errors import DatasetError
from lrslam.trajectory_io import read_tum

EPOCH = 1_700_000_000  # seconds: stamps of a real recording's size (float64 keeps ~0.2 us there)
W, H = 160, 120


@dataclass
class Topic:
    """One topic of a test bag: ``kind`` rgb | depth | info; ``encoding`` of its images."""

    name: str
    kind: str
    encoding: str = ""


STANDARD = (Topic("/camera/rgb/image_color", "rgb", "rgb8"), Topic("/camera/depth/image", "depth", "16UC1"),
            Topic("/camera/rgb/camera_info", "info"))


@dataclass
class Source:
    """The frames a bag is written from: stamps (s, float64 after EPOCH), colour uint8, depth uint16 mm, K."""

    stamps: list[tuple[int, int]]
    rgb: list[np.ndarray]
    depth_mm: list[np.ndarray]
    K: np.ndarray
    bags: dict[str, Path] = field(default_factory=dict)

    def seconds(self) -> np.ndarray:
        return np.array([s + ns * 1e-9 for s, ns in self.stamps])


def _colour_as(rgb: np.ndarray, encoding: str) -> np.ndarray:
    """An RGB image in the channel layout of a colour encoding (alpha 7; mono8: the green channel)."""
    alpha = np.full(rgb.shape[:2] + (1,), 7, np.uint8)
    return {"rgb8": rgb, "bgr8": rgb[..., ::-1], "rgba8": np.concatenate([rgb, alpha], axis=2),
            "bgra8": np.concatenate([rgb[..., ::-1], alpha], axis=2), "mono8": rgb[..., 1]}.get(encoding, rgb)


def _msg(ts, ros1: bool, topic: Topic, src: Source, i: int):
    """A sensor_msgs Image or CameraInfo message of frame ``i`` for ``topic``."""
    sec, nsec = src.stamps[i]
    T = ts.types
    hdr = dict(stamp=T["builtin_interfaces/msg/Time"](sec=sec, nanosec=nsec), frame_id="camera")
    header = T["std_msgs/msg/Header"](**(dict(seq=i) if ros1 else {}), **hdr)
    if topic.kind == "info":
        K = src.K.ravel().astype(np.float64)
        P = np.hstack([src.K, np.zeros((3, 1))]).ravel()
        cams = dict(D=np.zeros(5), K=K, R=np.eye(3).ravel(), P=P) if ros1 else \
            dict(d=np.zeros(5), k=K, r=np.eye(3).ravel(), p=P)
        roi = T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
        return T["sensor_msgs/msg/CameraInfo"](header=header, height=H, width=W, distortion_model="plumb_bob",
                                               binning_x=0, binning_y=0, roi=roi, **cams)
    img = _colour_as(src.rgb[i], topic.encoding) if topic.kind == "rgb" else src.depth_mm[i]
    if topic.encoding == "32FC1":  # metres; no measurement as NaN
        img = np.where(img > 0, img.astype(np.float32) / np.float32(1000.0), np.float32(np.nan))
    img = np.ascontiguousarray(img)
    return T["sensor_msgs/msg/Image"](header=header, height=H, width=W, encoding=topic.encoding, is_bigendian=0,
                                      step=img.nbytes // H, data=img.view(np.uint8).reshape(-1))


def write_bag(path: Path, src: Source, topics=STANDARD, mcap: bool = False) -> Path:
    """Write ``src`` into a ROS 1 bag (``path`` ends in ``.bag``) or a ROS 2 bag folder (sqlite3, or mcap)."""
    from rosbags.typesys import Stores, get_typestore

    ros1 = path.suffix == ".bag"
    if ros1:
        from rosbags.rosbag1 import Writer

        ts, writer = get_typestore(Stores.ROS1_NOETIC), Writer(path)
    else:
        from rosbags.rosbag2 import StoragePlugin, Writer

        storage = StoragePlugin.MCAP if mcap else StoragePlugin.SQLITE3
        ts = get_typestore(Stores.ROS2_HUMBLE)
        writer = Writer(path, version=Writer.VERSION_LATEST, storage_plugin=storage)
    serialize = ts.serialize_ros1 if ros1 else ts.serialize_cdr
    with writer:
        conns = {}
        for t in topics:
            msgtype = "sensor_msgs/msg/CameraInfo" if t.kind == "info" else "sensor_msgs/msg/Image"
            conns[t.name] = (writer.add_connection(t.name, msgtype, typestore=ts), msgtype)
        for i, (sec, nsec) in enumerate(src.stamps):
            for t in topics:
                conn, msgtype = conns[t.name]
                writer.write(conn, sec * 10**9 + nsec, serialize(_msg(ts, ros1, t, src, i), msgtype))
    return path


def write_tum_copy(root: Path, src: Source) -> Path:
    """The same frames in TUM layout: PNGs (depth in mm), rgb.txt / depth.txt, intrinsics.yaml (depth_scale 1000)."""
    import cv2
    import yaml

    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    lines = {"rgb": [], "depth": []}
    for i, (sec, nsec) in enumerate(src.stamps):
        stamp = f"{sec}.{nsec:09d}"
        cv2.imwrite(str(root / "rgb" / f"{i:04d}.png"), src.rgb[i][..., ::-1])
        cv2.imwrite(str(root / "depth" / f"{i:04d}.png"), src.depth_mm[i])
        for kind in lines:
            lines[kind].append(f"{stamp} {kind}/{i:04d}.png")
    for kind, rows in lines.items():
        (root / f"{kind}.txt").write_text("# timestamp filename\n" + "\n".join(rows) + "\n")
    fx, fy, cx, cy = (float(src.K[0, 0]), float(src.K[1, 1]), float(src.K[0, 2]), float(src.K[1, 2]))
    (root / "intrinsics.yaml").write_text(yaml.safe_dump(dict(fx=fx, fy=fy, cx=cx, cy=cy, depth_scale=1000.0)))
    return root


@pytest.fixture(scope="module")
def source(tmp_path_factory) -> Source:
    """16 synthetic frames at 160x120 (depth quantised to mm), a ROS 1 bag, ROS 2 bags (sqlite3, mcap) and a TUM
    copy."""
    from lrslam.datasets.synth.writer import generate

    root = tmp_path_factory.mktemp("rosbag")
    seq = open_sequence(generate(root / "synth", scene="room", trajectory="loop", n_frames=16, seed=1, width=W,
                                 height=H, show_progress=False))
    frames = list(seq)
    stamps = []
    for t in seq.timestamps:
        ns = int(round(float(t) * 1e9))
        stamps.append((EPOCH + ns // 10**9, ns % 10**9))
    src = Source(stamps, [f.rgb for f in frames],
                 [np.round(f.depth * 1000.0).astype(np.uint16) for f in frames], seq.K.copy())
    src.bags["ros1"] = write_bag(root / "seq.bag", src)
    src.bags["ros2"] = write_bag(root / "seq_ros2", src)
    src.bags["ros2_mcap"] = write_bag(root / "seq_mcap", src, mcap=True)
    src.bags["tum"] = write_tum_copy(root / "tum", src)
    return src


# ------------------------------------------------------------------------------------------------ reading
@pytest.mark.parametrize("kind", ["ros1", "ros2", "ros2_mcap"])
def test_bag_frames_equal_the_tum_copy(source, kind):
    bag = open_sequence(source.bags[kind])
    tum = open_sequence(source.bags["tum"])
    assert bag.name == "rosbag" and tum.name == "tum" and len(bag) == len(tum) == 16
    np.testing.assert_allclose(bag.timestamps, source.seconds(), rtol=0, atol=1e-6)
    np.testing.assert_allclose(bag.timestamps, tum.timestamps, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(bag.K, tum.K)
    assert bag.gt_poses() is None and bag.depth_scale == 1000.0
    for fb, ft in zip(bag, tum):
        np.testing.assert_array_equal(fb.rgb, ft.rgb)
        np.testing.assert_array_equal(fb.depth, ft.depth)          # same mm values, same float32 arithmetic
        assert fb.depth.dtype == np.float32 and fb.rgb.dtype == np.uint8 and fb.T_w_c_gt is None
    # depth in metres: the generator's depth to the mm quantisation
    np.testing.assert_allclose(bag[3].depth, source.depth_mm[3] / 1000.0, rtol=0, atol=1e-6)


def test_reader_options_apply_to_bags(source):
    from lrslam.datasets import ReaderOptions

    opts = ReaderOptions(stride=2, max_frames=5, resize=(80, 60), crop_border=2)
    bag = open_sequence(source.bags["ros1"], options=opts)
    tum = open_sequence(source.bags["tum"], options=opts)
    assert len(bag) == 5 and (bag.width, bag.height) == (76, 56)
    np.testing.assert_array_equal(bag.K, tum.K)
    np.testing.assert_allclose(bag.timestamps, tum.timestamps, rtol=0, atol=1e-6)
    for i in (0, 4):
        np.testing.assert_array_equal(bag[i].rgb, tum[i].rgb)
        np.testing.assert_array_equal(bag[i].depth, tum[i].depth)


@pytest.mark.parametrize("colour", ["bgr8", "rgba8", "bgra8", "mono8"])
def test_other_encodings_decode_to_the_same_frames(source, tmp_path, colour):
    """Other colour encodings and 32FC1 depth (metres, NaN = no measurement) give the rgb8 / 16UC1 frames; the
    topics are told apart by their encoding, not their names."""
    holes = [d.copy() for d in source.depth_mm]
    holes[2][:20, :30] = 0                                     # written as NaN in 32FC1
    src = Source(source.stamps, source.rgb, holes, source.K)
    topics = (Topic("/cam/a", "rgb", colour), Topic("/cam/b", "depth", "32FC1"), Topic("/cam/info", "info"))
    bag = open_sequence(write_bag(tmp_path / "enc.bag", src, topics))
    assert bag.depth_scale == 1.0
    expect = np.repeat(source.rgb[2][..., 1:2], 3, axis=2) if colour == "mono8" else source.rgb[2]
    np.testing.assert_array_equal(bag[2].rgb, expect)
    np.testing.assert_allclose(bag[2].depth, holes[2] / 1000.0, rtol=0, atol=1e-6)
    assert np.all(bag[2].depth[:20, :30] == 0) and np.all(np.isfinite(bag[2].depth))


def test_layout_detection_and_default_preset(source, tmp_path):
    from lrslam.datasets import detect_layout
    from lrslam.pipeline.config_source import default_preset

    assert "rosbag" in READERS
    assert detect_layout(source.bags["ros1"]) == detect_layout(source.bags["ros2"]) == "rosbag"
    assert default_preset(source.bags["ros1"], cuda=False)[0] == "rosbag-cpu"
    assert default_preset(source.bags["ros2"], cuda=True)[0] == "rosbag"
    (tmp_path / "notes.txt").write_text("x")
    with pytest.raises(DatasetError, match="not a folder"):
        open_sequence(tmp_path / "notes.txt")
    with pytest.raises(DatasetError, match="not a folder"):
        open_sequence(source.bags["ros1"], reader="tum")
    with pytest.raises(DatasetError, match="dataset folder not found"):
        open_sequence(tmp_path / "missing.bag")


def test_rosbag_presets_are_the_tum_presets_at_the_cameras_size():
    from lrslam.pipeline.config import build_config

    for mine, base in (("rosbag", "tum"), ("rosbag-cpu", "tum-cpu")):
        for mode in ("field", "fused", "frontend"):
            c, r = build_config(mine, mode=mode), build_config(base, mode=mode)
            assert c.dataset.reader == "rosbag"
            assert c.reader_options() == r.reader_options().model_copy(update={"resize": None, "crop_border": 8})
            cfg, ref = c.model_dump(), r.model_dump()
            assert cfg["bound"] is None and cfg["initial_pose"] == "identity"      # the bound comes from the data
            for key in ("dataset", "bound", "initial_pose"):
                cfg.pop(key), ref.pop(key)
            assert cfg == ref, (mine, mode)


# ------------------------------------------------------------------------------------------ command line
RUN = ["--mode", "frontend", "--set", "deterministic=true", "--config", "rosbag-cpu", "--set", "output.mesh=false",
       "--set", "output.plots=false", "-q"]


@pytest.mark.parametrize("kind", ["ros1", "ros2"])
def test_cli_run_on_a_bag_matches_the_tum_copy(source, tmp_path, capfd, kind):
    code, out, err = run_cli(["run", str(source.bags[kind]), "--out", str(tmp_path / "bag"), *RUN], capfd)
    assert code == 0, err
    code, _, err = run_cli(["run", str(source.bags["tum"]), "--out", str(tmp_path / "tum"), *RUN, "--set",
                            "dataset.reader=tum"], capfd)
    assert code == 0, err
    t_bag, P_bag = read_tum(tmp_path / "bag" / "trajectory.txt")
    t_tum, P_tum = read_tum(tmp_path / "tum" / "trajectory.txt")
    assert len(P_bag) == 16 and np.ptp(P_bag[:, :3, 3], axis=0).max() > 0.03   # the camera moved (truth: 4.4 cm)
    np.testing.assert_allclose(t_bag, t_tum, rtol=0, atol=1e-6)
    np.testing.assert_allclose(P_bag, P_tum, rtol=0, atol=1e-6)
    assert "no ground truth" in out


def test_cli_run_picks_the_rosbag_preset(source, tmp_path, capfd):
    code, out, err = run_cli(["run", str(source.bags["ros1"]), "--out", str(tmp_path / "o"), "--mode", "frontend",
                              "--max-frames", "4", "--set", "output.mesh=false", "--set", "output.plots=false", "-q"],
                             capfd)
    assert code == 0, err
    assert "preset rosbag" in out


# ------------------------------------------------------------------------------------------------ bad bags
def _bad_bags(src: Source, root: Path) -> list[tuple[str, Path, list[str], tuple[str, ...]]]:
    """(id, bag, extra --set options, strings the one-line message must contain)."""
    rgb, depth, info = STANDARD
    cases = []

    def bag(name: str, topics, extra=(), *needles: str) -> None:
        cases.append((name, write_bag(root / f"{name}.bag", src, topics), list(extra), needles))

    bag("no_depth", (rgb, info), (), "no depth image topic (16UC1/mono16/32FC1)", rgb.name)
    bag("no_colour", (depth, info), (), "no colour image topic", depth.name)
    bag("no_camera", (rgb, depth), (), "no sensor_msgs/CameraInfo topic", "intrinsics.yaml")
    bag("bad_encoding", (rgb, Topic(depth.name, "depth", "8UC3"), info), (), "no depth image topic", depth.name,
        "8UC3")
    bag("bad_encoding_given", (rgb, Topic(depth.name, "depth", "8UC3"), info), [f"depth_topic={depth.name}"],
        depth.name, "unsupported image encoding '8UC3'")
    bag("depth_as_colour", STANDARD, [f"rgb_topic={depth.name}"], depth.name, "depth image encoding '16UC1'")
    bag("missing_topic", STANDARD, ["depth_topic=/nope"], "depth_topic /nope is not in the bag", depth.name)
    bag("two_colour", (rgb, Topic("/camera/ir/image", "rgb", "mono8"), depth, info), (), rgb.name,
        "/camera/ir/image", "dataset.options.rgb_topic")
    bag("two_info", (rgb, depth, info, Topic("/other/camera_info", "info")), (), "several CameraInfo topics",
        info.name, "dataset.options.camera_info_topic")
    corrupt = root / "corrupt.bag"
    corrupt.write_bytes(b"#ROSBAG V2.0\n" + b"\x00garbage" * 50)
    cases.append(("corrupt", corrupt, [], ("corrupt.bag", "unreadable or corrupt ROS bag")))
    half = root / "truncated.bag"
    half.write_bytes(src.bags["ros1"].read_bytes()[:5000])
    cases.append(("truncated", half, [], ("truncated.bag", "ROS bag")))
    ros2 = root / "broken_ros2"
    ros2.mkdir()
    (ros2 / "metadata.yaml").write_text("rosbag2_bagfile_information:\n  version: 9\n  storage_identifier: sqlite3\n")
    cases.append(("corrupt_ros2", ros2, [], ("broken_ros2", "unreadable or corrupt ROS bag")))
    return cases


@pytest.fixture(scope="module")
def bad_bags(source, tmp_path_factory):
    return {c[0]: c for c in _bad_bags(source, tmp_path_factory.mktemp("bad_bags"))}


BAD = ["no_depth", "no_colour", "no_camera", "bad_encoding", "bad_encoding_given", "depth_as_colour", "missing_topic",
       "two_colour", "two_info", "corrupt", "truncated", "corrupt_ros2"]


@pytest.mark.parametrize("case", BAD)
def test_bad_bag_is_a_one_line_exit_2(bad_bags, tmp_path, capfd, case):
    _, bag, extra, needles = bad_bags[case]
    sets = [a for opt in extra for a in ("--set", f"dataset.options.{opt}")]
    code, _, err = run_cli(["run", str(bag), "--out", str(tmp_path / "o"), *RUN, *sets], capfd)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("error: ") and "Traceback" not in err, err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def test_camera_from_intrinsics_yaml_or_override(source, tmp_path):
    import yaml

    from lrslam.datasets import ReaderOptions

    rgb, depth, _ = STANDARD
    bag = write_bag(tmp_path / "nocam.bag", source, (rgb, depth))
    fx, fy, cx, cy = 200.0, 201.0, 79.5, 59.5
    seq = open_sequence(bag, options=ReaderOptions(fx=fx, fy=fy, cx=cx, cy=cy))
    np.testing.assert_array_equal(seq.K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    (tmp_path / "intrinsics.yaml").write_text(yaml.safe_dump(dict(fx=fx, fy=fy, cx=cx, cy=cy)))
    seq = open_sequence(bag)
    np.testing.assert_array_equal(seq.K, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    assert seq.depth_scale == 1000.0 and len(seq) == 16
