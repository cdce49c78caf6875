"""ROS bag reader (``rosbag``): a ROS 1 ``.bag`` file or a ROS 2 bag folder, read with ``rosbags`` (no ROS install).

Layout: a file ending in ``.bag`` (ROS 1), or a folder holding ``metadata.yaml`` (with
``rosbag2_bagfile_information``) and its ``.db3`` / ``.mcap`` storage files (ROS 2).

* Topics: a colour and a depth ``sensor_msgs/Image`` topic and a ``sensor_msgs/CameraInfo`` topic. Colour vs
  depth is decided by the encoding of a topic's first message (colour: rgb8, bgr8, rgba8, bgra8, mono8; depth:
  16UC1 / mono16 in millimetres, 32FC1 in metres). With exactly one topic of a kind it is taken; otherwise name
  it: ``--set dataset.options.rgb_topic=/x``, ``depth_topic=/y``, ``camera_info_topic=/z``. Of several
  CameraInfo topics the one in the depth topic's namespace (``/cam/depth/image`` -> ``/cam/depth/camera_info``)
  is taken when there is exactly one such.
* Frames: colour and depth messages are paired by their ``header.stamp`` (seconds) with TUM's rule
  (:func:`lrslam.datasets.association.associate`, strictly less than 0.02 s apart); a frame's timestamp is its
  colour message's stamp. A topic whose stamps are all zero uses the bag's record times (logged). The messages
  are indexed once when the bag is opened; each frame's two images are read and decoded when the frame is.
* Units: depth in metres = raw / depth_scale, with depth_scale 1000 for 16-bit depth (the ROS millimetre
  convention) and 1 for 32FC1; ``ReaderOptions.depth_scale`` overrides it. 0, NaN and inf are invalid (0).
* Camera, first that applies: (1) the intrinsics override of ``ReaderOptions`` (``--set dataset.options.fx=...
  fy= cx= cy=``, optional ``distortion``); (2) the CameraInfo's ``K`` (its first message; width and height,
  when set, must be the depth image's size); (3) ``intrinsics.yaml`` (:mod:`lrslam.datasets.camera_file`)
  beside a ROS 1 bag or inside a ROS 2 bag folder; else an error. The images are taken as rectified
  (``image_rect``): CameraInfo's ``D`` is not applied. Colour must be registered to depth (same size).
* No ground truth (``Frame.T_w_c_gt`` None, ``gt_poses()`` None), no scene bound. Stride, max_frames, resize and
  crop apply as for every reader.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from lrslam.camera import intrinsics_matrix
from lrslam.errors import DatasetError
from lrslam.datasets.association import pair_colour_depth
from lrslam.datasets.base import Sequence, SourceIndex
from lrslam.datasets.camera_file import CAMERA_FILE, read_camera_file
from lrslam.datasets.registry import register
from lrslam.datasets.rosbag_io import (CAMERA_INFO, COLOR_ENCODINGS, DEPTH_ENCODINGS, IMAGE, BagFile, ImageStream,
                                       decode_color, decode_depth)

__all__ = ["RosbagReader", "is_rosbag"]

log = logging.getLogger(__name__)

_DEPTH_NAMES = "/".join(DEPTH_ENCODINGS)
_COLOR_NAMES = "/".join(COLOR_ENCODINGS)


def is_rosbag(path: Path) -> bool:
    """A ``.bag`` file, or a folder whose ``metadata.yaml`` is a ROS 2 bag's. Looks at names and one small file."""
    if path.is_file():
        return path.suffix == ".bag"
    meta = path / "metadata.yaml"
    try:
        return meta.is_file() and "rosbag2_bagfile_information" in meta.read_text(errors="replace")
    except OSError:
        return False


@register("rosbag", files=True)
class RosbagReader(Sequence):
    """ROS 1 ``.bag`` file or ROS 2 bag folder (see the module docstring for topics, units and camera).

    Reads through a :class:`~lrslam.datasets.rosbag_io.BagFile` kept open while the sequence lives; the frame
    selection, camera checks, image geometry and frame assembly are the base class's: this class overrides only
    its source hooks (a bag file or folder, the depth topic's image size, frames decoded from messages).
    """

    layout_hint = "a ROS 1 .bag file or a ROS 2 bag folder (metadata.yaml + .db3/.mcap)"

    @classmethod
    def detect(cls, root: Path) -> bool:
        return is_rosbag(root)

    # ----------------------------------------------------------------------------------------- source
    def _check_source(self, root: Path) -> None:
        if not is_rosbag(root):
            raise DatasetError(f"{root}: not a ROS bag (expected {self.layout_hint})")

    def _check_frames_exist(self) -> None:
        """Nothing to check: every frame's messages were indexed when the bag was opened."""

    def _read_native_size(self) -> tuple[int, int]:
        return self._depth.size

    def _size_mismatch(self, size: tuple[int, int], expected: tuple[int, int]) -> str:
        return (f"{self.root}: depth topic {self._depth.topic} has {size[0]}x{size[1]} images but CameraInfo topic "
                f"{self._info_topic} states {expected[0]}x{expected[1]}")

    # ------------------------------------------------------------------------------------------ index
    def _scan(self) -> SourceIndex:
        """Open the bag, choose the topics, index their messages once and pair colour with depth by header stamp."""
        root = self.root
        self._bag = BagFile(root)
        rgb_topic, depth_topic = self._image_topics()
        self._rgb = self._stream(rgb_topic, "rgb_topic")
        self._depth = self._stream(depth_topic, "depth_topic")
        t_rgb = self._rgb.stamps
        pairs = pair_colour_depth(t_rgb, self._depth.stamps, root, rgb_topic, depth_topic, log, pair="colour/depth",
                                  images=f"colour images of {rgb_topic}")
        self._pairs = pairs  # (rgb message, depth message) of every frame of the SourceIndex
        K, depth_scale, size = self._camera()
        return SourceIndex(timestamps=t_rgb[pairs[:, 0]],
                           rgb_paths=[Path(f"{root}:{rgb_topic}[{i}]") for i in pairs[:, 0]],
                           depth_paths=[Path(f"{root}:{depth_topic}[{j}]") for j in pairs[:, 1]],
                           K=K, depth_scale=depth_scale, expected_size=size)

    def _stream(self, topic: str, option: str) -> ImageStream:
        """Index one image topic (its first message's encoding must suit the role ``option`` names)."""
        kinds = COLOR_ENCODINGS if option == "rgb_topic" else DEPTH_ENCODINGS
        enc = self._encodings[topic]
        if enc is None:
            raise DatasetError(f"{self.root}: {option} {topic} has no messages")
        if enc not in kinds:
            other = "a depth" if enc in DEPTH_ENCODINGS else "a colour" if enc in COLOR_ENCODINGS else "an unsupported"
            raise DatasetError(f"{self.root}: {option} {topic} has {other} image encoding {enc!r} (expected "
                               f"{'/'.join(kinds)})")
        stream = self._bag.index_images(topic, enc)
        if len(stream.stamps) and not np.any(stream.stamps):
            log.warning("%s: topic %s has no header stamps (all zero); using the bag's record times", self.root,
                        topic)
            stream.stamps = stream.record_ns * 1e-9
        return stream

    def _image_topics(self) -> tuple[str, str]:
        """The colour and depth topics: the options' when given, else the bag's only one of each kind."""
        bag, opts = self._bag, self.options
        given = {"rgb_topic": opts.rgb_topic, "depth_topic": opts.depth_topic}
        for option, topic in given.items():
            self._check_topic(option, topic, IMAGE)
        images = [t for t, typ in bag.topics.items() if typ == IMAGE]
        ask = [t for t in given.values() if t is not None] if all(given.values()) else images
        self._encodings: dict[str, str | None] = {}
        for t in ask:
            first = bag.first(t)
            self._encodings[t] = None if first is None else str(first.encoding)
        colour = [t for t, e in self._encodings.items() if e in COLOR_ENCODINGS]
        depth = [t for t, e in self._encodings.items() if e in DEPTH_ENCODINGS]
        return (opts.rgb_topic or self._only(colour, "colour image topic", "rgb_topic", f" ({_COLOR_NAMES})"),
                opts.depth_topic or self._only(depth, "depth image topic", "depth_topic", f" ({_DEPTH_NAMES})"))

    def _check_topic(self, option: str, topic: str | None, msgtype: str) -> None:
        bag = self._bag
        if topic is None:
            return
        if topic not in bag.topics:
            raise DatasetError(f"{self.root}: {option} {topic} is not in the bag; topics: {bag.listing()}")
        if bag.topics[topic] != msgtype:
            raise DatasetError(f"{self.root}: {option} {topic} carries {bag.topics[topic]}, not {msgtype}")

    def _only(self, candidates: list[str], what: str, option: str, encodings: str = "") -> str:
        """The one candidate topic; DatasetError listing the bag's topics (none) or the candidates (several)."""
        if len(candidates) == 1:
            return candidates[0]
        if not candidates:
            encs = ", ".join(f"{t}: {e or 'no messages'}" for t, e in sorted(self._encodings.items()))
            raise DatasetError(f"{self.root}: no {what}{encodings} in the bag; topics: {self._bag.listing()}"
                               + (f"; image encodings: {encs}" if encs else ""))
        raise DatasetError(f"{self.root}: several {what}s{encodings}: {', '.join(sorted(candidates))}; choose one "
                           f"with --set dataset.options.{option}=<topic>")

    # ----------------------------------------------------------------------------------------- camera
    def _camera(self) -> tuple[np.ndarray, float, tuple[int, int] | None]:
        """``(K (3, 3) native, depth scale, (width, height) the camera states or None)``."""
        scale = DEPTH_ENCODINGS[self._depth.encoding][1]
        self._info_topic = None
        if self.options.fx is not None:  # the base class applies the override
            return self.options.intrinsics_override(), scale, None
        topic = self._info_topic = self._camera_info_topic()
        if topic is not None:
            msg = self._bag.first(topic)
            if msg is None:
                raise DatasetError(f"{self.root}: CameraInfo topic {topic} has no messages")
            K = np.asarray(msg.k if hasattr(msg, "k") else msg.K, dtype=np.float64).reshape(3, 3)  # ROS 2 / ROS 1
            if K[0, 0] > 0:
                size = (int(msg.width), int(msg.height))
                return K, scale, size if all(size) else None
            log.warning("%s: CameraInfo topic %s has an all-zero K (uncalibrated camera)", self.root, topic)
        path = (self.root if self.root.is_dir() else self.root.parent) / CAMERA_FILE
        if path.is_file():
            cam = read_camera_file(path)
            return intrinsics_matrix(cam.fx, cam.fy, cam.cx, cam.cy), cam.depth_scale or scale, None
        why = f"CameraInfo topic {topic} has no calibration (K = 0)" if topic else "no sensor_msgs/CameraInfo topic"
        raise DatasetError(f"{self.root}: unknown camera: {why} and no {path}; write it (fx, fy, cx, cy in pixels) "
                           "or pass --set dataset.options.fx=... (and fy, cx, cy)")

    def _camera_info_topic(self) -> str | None:
        """The CameraInfo topic: the option's, the only one, or the only one beside the depth topic; None: none."""
        opts, bag = self.options, self._bag
        self._check_topic("camera_info_topic", opts.camera_info_topic, CAMERA_INFO)
        if opts.camera_info_topic is not None:
            return opts.camera_info_topic
        infos = sorted(t for t, typ in bag.topics.items() if typ == CAMERA_INFO)
        if len(infos) <= 1:
            return infos[0] if infos else None
        depth_ns = self._depth.topic.rsplit("/", 1)[0]
        beside = [t for t in infos if t.rsplit("/", 1)[0] == depth_ns]
        if len(beside) == 1:
            log.info("%s: CameraInfo from %s (beside the depth topic %s)", self.root, beside[0], self._depth.topic)
            return beside[0]
        return self._only(infos, "CameraInfo topic", "camera_info_topic")

    # --------------------------------------------------------------------------------------- frames
    def _load_frame(self, i: int) -> tuple[np.ndarray, np.ndarray, int]:
        """Read and decode the two messages of frame ``i`` of the selection."""
        k_rgb, k_depth = self._pairs[self._selection[i]]
        rgb_msg = self._message(self._rgb, int(k_rgb))
        depth_msg = self._message(self._depth, int(k_depth))
        rgb = decode_color(rgb_msg, str(self._rgb_paths[i]))
        depth, n_nonfinite = self._metres(decode_depth(depth_msg, str(self._depth_paths[i])), i, depth_msg.encoding)
        return rgb, depth, n_nonfinite

    def _message(self, stream: ImageStream, k: int):
        return self._bag.fetch(stream.topic, int(stream.record_ns[k]), int(stream.rank[k]))

    def _metres(self, raw: np.ndarray, i: int, encoding: str) -> tuple[np.ndarray, int]:
        """Raw depth -> float32 metres, invalid (NaN, inf, negative) set to 0; and the count of non-finite."""
        if encoding != self._depth.encoding:
            raise DatasetError(f"{self._depth_paths[i]}: depth encoding changed from {self._depth.encoding!r} to "
                               f"{encoding!r} within the topic")
        depth = raw.astype(np.float32) / np.float32(self.depth_scale)
        if raw.dtype.kind != "f":
            return depth, 0
        bad = ~np.isfinite(depth)
        depth[bad | (depth < 0)] = 0.0
        return depth, int(np.count_nonzero(bad))
