"""ROS bag access for :mod:`lrslam.datasets.rosbag`: open a bag, index an image topic once, fetch one message
again later, and decode ``sensor_msgs/Image`` messages to arrays.

The ``rosbags`` library (pure Python, no ROS install) reads ROS 1 ``.bag`` files and ROS 2 bag folders
(sqlite3 ``.db3`` or ``.mcap`` storage). A message is found again by its bag record time (nanoseconds) and its
rank among the topic's messages with that record time, so no image is held in memory between frames. Every
failure is a one-line :class:`~lrslam.errors.DatasetError` naming the bag and, where there is one, the topic.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from lrslam.errors import DatasetError

__all__ = ["BagFile", "ImageStream", "IMAGE", "CAMERA_INFO", "COLOR_ENCODINGS", "DEPTH_ENCODINGS", "stamp_seconds",
           "decode_color", "decode_depth"]

IMAGE = "sensor_msgs/msg/Image"            # rosbags names ROS 1 types the ROS 2 way (sensor_msgs/Image -> ...)
CAMERA_INFO = "sensor_msgs/msg/CameraInfo"

# encoding -> channels of the colour image (REP 104 / sensor_msgs/image_encodings.h names)
COLOR_ENCODINGS: dict[str, int] = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "mono8": 1}
# encoding -> (numpy type, raw units per metre): 16-bit depth in millimetres, float depth in metres (REP 118)
DEPTH_ENCODINGS: dict[str, tuple[str, float]] = {"16UC1": ("u2", 1000.0), "mono16": ("u2", 1000.0),
                                                 "32FC1": ("f4", 1.0)}


def stamp_seconds(msg: Any) -> float:
    """A message's ``header.stamp`` in seconds (float64)."""
    stamp = msg.header.stamp
    return float(stamp.sec) + float(stamp.nanosec) * 1e-9


def _why(e: BaseException) -> str:
    text = " ".join(str(e).split())
    return f"{type(e).__name__}: {text}" if text else type(e).__name__


@dataclass
class ImageStream:
    """The messages of one image topic, in bag order.

    Attributes:
        topic: topic name. encoding: the first message's encoding.
        stamps: (M,) float64 header stamps, seconds.
        record_ns: (M,) int64 bag record times, nanoseconds (how the message is found again).
        rank: (M,) int64 position among the topic's messages with the same record time.
        size: ``(width, height)`` of the first message.
    """

    topic: str
    encoding: str
    stamps: np.ndarray
    record_ns: np.ndarray
    rank: np.ndarray
    size: tuple[int, int]


class BagFile:
    """An open ROS 1 ``.bag`` file or ROS 2 bag folder; DatasetError naming it when it cannot be read.

    Attributes:
        path: the bag. topics: ``{topic: message type}`` (None for a topic recorded with several types).
        counts: ``{topic: number of messages}``.
    """

    def __init__(self, path: Path) -> None:
        from rosbags.highlevel import AnyReader
        from rosbags.typesys import Stores, get_typestore

        self.path = path
        self._lock = threading.Lock()  # one message generator at a time on the shared reader
        try:
            # ROS 1 bags (and newer ROS 2 ones) carry their message definitions; older ROS 2 bags need a store
            reader = AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE))
            reader.open()
            infos = reader.topics
        except Exception as e:  # noqa: BLE001 - any failure to parse the file is a corrupt bag for the user
            raise DatasetError(f"{path}: unreadable or corrupt ROS bag ({_why(e)})") from None
        self._reader = reader
        self.topics: dict[str, str | None] = {name: info.msgtype for name, info in infos.items()}
        self.counts: dict[str, int] = {name: int(info.msgcount) for name, info in infos.items()}
        self._connections = {name: list(info.connections) for name, info in infos.items()}

    def close(self) -> None:
        reader, self._reader = getattr(self, "_reader", None), None
        if reader is not None:
            try:
                reader.close()
            except Exception:  # noqa: BLE001 - closing a half-broken bag must not mask the real error
                pass

    def __del__(self) -> None:
        self.close()

    def listing(self) -> str:
        """``/topic (type, N msgs), ...`` for error messages."""
        if not self.topics:
            return "none"
        return ", ".join(f"{t} ({(typ or 'mixed types').replace('/msg/', '/')}, {self.counts[t]} msgs)"
                         for t, typ in sorted(self.topics.items()))

    def _messages(self, topic: str, start: int | None = None, stop: int | None = None):
        """Generator of ``(record time ns, message)`` of ``topic``; DatasetError naming the topic on a bad one."""
        reader = self._reader
        gen = reader.messages(connections=self._connections[topic], start=start, stop=stop)
        try:
            for conn, t_ns, raw in gen:
                yield int(t_ns), reader.deserialize(raw, conn.msgtype)
        except DatasetError:
            raise
        except Exception as e:  # noqa: BLE001 - a truncated chunk, a bad CDR buffer ...: name the topic
            raise DatasetError(f"{self.path}: topic {topic}: unreadable message ({_why(e)})") from None
        finally:
            gen.close()

    def first(self, topic: str) -> Any | None:
        """The first message of ``topic`` (deserialised), or None when it has none."""
        with self._lock:
            gen = self._messages(topic)
            try:
                return next((msg for _, msg in gen), None)
            finally:
                gen.close()

    def index_images(self, topic: str, encoding: str) -> ImageStream:
        """Read every message of an image topic once: header stamps, record times and ranks."""
        stamps, record_ns, rank = [], [], []
        size = None
        with self._lock:
            for t_ns, msg in self._messages(topic):
                stamps.append(stamp_seconds(msg))
                rank.append(rank[-1] + 1 if record_ns and record_ns[-1] == t_ns else 0)
                record_ns.append(t_ns)
                size = size or (int(msg.width), int(msg.height))
        return ImageStream(topic, encoding, np.asarray(stamps, np.float64), np.asarray(record_ns, np.int64),
                           np.asarray(rank, np.int64), size or (0, 0))

    def fetch(self, topic: str, record_ns: int, rank: int) -> Any:
        """The message of ``topic`` recorded at ``record_ns`` (the ``rank``-th one at that time)."""
        with self._lock:
            gen = self._messages(topic, start=record_ns, stop=record_ns + 1)
            try:
                for k, (_, msg) in enumerate(gen):
                    if k == rank:
                        return msg
            finally:
                gen.close()
        raise DatasetError(f"{self.path}: topic {topic}: message recorded at {record_ns} ns not found again "
                           f"(was the bag modified?)")


def _rows(msg: Any, itemsize: int, channels: int, where: str) -> np.ndarray:
    """The pixel bytes of an Image message as (H, W * channels * itemsize) uint8 (row padding removed)."""
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    row = w * channels * itemsize
    data = np.frombuffer(memoryview(msg.data), dtype=np.uint8)
    if h <= 0 or w <= 0 or step < row or data.size < step * h:
        raise DatasetError(f"{where}: malformed image ({w}x{h}, step {step}, {data.size} bytes of data)")
    return data[: step * h].reshape(h, step)[:, :row]


def decode_color(msg: Any, where: str) -> np.ndarray:
    """A colour ``sensor_msgs/Image`` -> (H, W, 3) uint8 RGB (mono8 replicated, alpha dropped)."""
    enc = msg.encoding
    if enc not in COLOR_ENCODINGS:
        raise DatasetError(f"{where}: image encoding {enc!r} is not a colour encoding "
                           f"({', '.join(COLOR_ENCODINGS)})")
    ch = COLOR_ENCODINGS[enc]
    img = _rows(msg, 1, ch, where).reshape(int(msg.height), int(msg.width), ch)
    if ch == 1:
        img = np.repeat(img, 3, axis=2)
    elif enc.startswith("bgr"):
        img = img[..., 2::-1]
    else:
        img = img[..., :3]
    return np.ascontiguousarray(img)


def decode_depth(msg: Any, where: str) -> np.ndarray:
    """A depth ``sensor_msgs/Image`` -> (H, W) raw values (uint16 or float32, native byte order)."""
    enc = msg.encoding
    if enc not in DEPTH_ENCODINGS:
        raise DatasetError(f"{where}: image encoding {enc!r} is not a depth encoding "
                           f"({', '.join(DEPTH_ENCODINGS)})")
    kind = DEPTH_ENCODINGS[enc][0]
    dtype = np.dtype((">" if msg.is_bigendian else "<") + kind)
    raw = _rows(msg, dtype.itemsize, 1, where).copy().view(dtype).reshape(int(msg.height), int(msg.width))
    return raw.astype(dtype.newbyteorder("="), copy=False)
