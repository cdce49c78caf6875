"""The :class:`Sequence` base class every dataset reader derives from.

A reader only has to say *where* things are: :meth:`Sequence.detect` recognises its folder layout and
:meth:`Sequence._scan` lists every frame (timestamps, image paths, ground truth) and the native camera in a
:class:`SourceIndex`. The base class does the rest the same way for every dataset: frame selection
(stride, max_frames), the intrinsics override, checks, lazy image loading, undistortion, resize and crop.

A reader whose frames are not image files (a ROS bag) also overrides the source hooks: how the path is checked
(:meth:`Sequence._check_source`), that the selected frames exist (:meth:`Sequence._check_frames_exist`), the
native image size (:meth:`Sequence._read_native_size`, :meth:`Sequence._size_mismatch`) and how one frame's
native colour and depth are loaded (:meth:`Sequence._load_frame`).
"""

from __future__ import annotations

import abc
import logging
import operator
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np

from lrslam.camera import check_intrinsics
from lrslam.errors import DatasetError
from lrslam.datasets.image_ops import ImageGeometry, Undistorter, read_color, read_depth
from lrslam.datasets.options import ReaderOptions
from lrslam.frame import Frame

__all__ = ["Sequence", "SourceIndex"]

log = logging.getLogger(__name__)


@dataclass
class SourceIndex:
    """Everything a reader found in its folder, for every frame in time order (before stride/max_frames).

    Attributes:
        timestamps: (M,) float64 seconds.
        rgb_paths, depth_paths: M image paths each (not yet checked for existence).
        K: (3, 3) float64 intrinsics of the native depth image.
        depth_scale: raw depth units per metre.
        poses: (M, 4, 4) float64 ground-truth ``T_w_c`` (OpenCV camera axes), NaN rows for frames without
            ground truth; None when the dataset has no ground truth at all.
        distortion: OpenCV ``k1 k2 p1 p2 k3`` of the colour camera, or None.
        invalid_depth_raw: raw depth values that mean "no measurement" besides 0 (7-Scenes: 65535).
        expected_size: native ``(width, height)`` the images must have, when the dataset states it.
        bound: (3, 2) scene bound ``[[xmin, xmax], [ymin, ymax], [zmin, zmax]]`` in metres, or None.
        gt_mesh_path: ground-truth mesh file, or None.
    """

    timestamps: np.ndarray
    rgb_paths: list[Path]
    depth_paths: list[Path]
    K: np.ndarray
    depth_scale: float
    poses: np.ndarray | None = None
    distortion: np.ndarray | None = None
    invalid_depth_raw: tuple[int, ...] = ()
    expected_size: tuple[int, int] | None = None
    bound: np.ndarray | None = None
    gt_mesh_path: Path | None = None


class Sequence(abc.ABC):
    """An RGB-D sequence on disk, read lazily frame by frame.

    Attributes:
        name: the reader's registry name (``"tum"``, ``"replica"``, ...).
        root: the dataset folder.
        options: the :class:`ReaderOptions` in use.
        K: (3, 3) float64 intrinsics of the output images (after resize and crop).
        width, height: output image size in pixels.
        depth_scale: raw depth units per metre in use.
        timestamps: (N,) float64 seconds of the selected frames (after stride/max_frames).
        bound: (3, 2) float64 scene bound in metres from the dataset folder, or None.
        gt_mesh_path: ground-truth mesh file from the dataset folder, or None.

    ``seq[i]`` loads frame ``i`` of the selection (``0 <= i < len(seq)``) as a :class:`Frame`.
    """

    name: ClassVar[str] = ""  # set by @register
    layout_hint: ClassVar[str] = ""  # one phrase describing the folder layout, for "unknown layout" errors
    color_to_depth_size: ClassVar[bool] = False  # resize colour to the depth size instead of requiring equality

    def __init__(self, root: str | Path, options: ReaderOptions | None = None) -> None:
        root = Path(root).expanduser()
        if not root.exists():
            raise DatasetError(f"{root}: dataset folder not found")
        self._check_source(root)
        self.root = root
        self.options = options if options is not None else ReaderOptions()
        self._warned: set[str] = set()

        # 1. List the frames and select stride / max_frames.
        src = self._scan()
        if len(src.timestamps) == 0:
            raise DatasetError(f"{root}: empty sequence (0 frames) for reader '{self.name}'")
        sel = np.arange(0, len(src.timestamps), self.options.stride)[: self.options.max_frames]
        self._selection = sel  # frame i of the selection is frame sel[i] of the SourceIndex
        self.timestamps = np.asarray(src.timestamps, dtype=np.float64)[sel]
        self._rgb_paths = [src.rgb_paths[i] for i in sel]
        self._depth_paths = [src.depth_paths[i] for i in sel]
        self._check_frames_exist()
        self._poses = None if src.poses is None else np.asarray(src.poses, dtype=np.float64)[sel]
        self._invalid_raw = src.invalid_depth_raw
        self.bound = None if src.bound is None else np.asarray(src.bound, dtype=np.float64).reshape(3, 2)
        self.gt_mesh_path = src.gt_mesh_path

        # 2. Native camera (the override wins) and the image size (the first selected depth image's).
        K_native = self.options.intrinsics_override()
        K_native = np.asarray(src.K, dtype=np.float64) if K_native is None else K_native
        self._K_native = K_native
        self.depth_scale = float(self.options.depth_scale or src.depth_scale)
        w, h = self._read_native_size()
        if src.expected_size is not None and src.expected_size != (w, h):
            raise DatasetError(self._size_mismatch((w, h), src.expected_size))
        try:
            check_intrinsics(K_native, w, h)
        except ValueError as e:
            raise DatasetError(f"{root}: {e}") from None

        # 3. Output geometry: undistort colour (native K), resize, crop.
        self._native_size = (w, h)
        self._geometry = ImageGeometry(w, h, self.options.resize, self.options.crop_border)
        self.K = self._geometry.adjust_K(K_native)
        self.width, self.height = self._geometry.out_size
        # an intrinsics override is an ideal pinhole camera unless it gives its own distortion
        dist = src.distortion if self.options.intrinsics_override() is None else self.options.distortion
        self._undistort = (Undistorter(K_native, dist) if self.options.undistort and dist is not None
                           and np.any(np.asarray(dist) != 0) else None)

    # ----------------------------------------------------------------------------------------- reader hooks
    @classmethod
    @abc.abstractmethod
    def detect(cls, root: Path) -> bool:
        """True when ``root`` (an existing folder) has this reader's layout. Cheap: looks at names only."""

    @abc.abstractmethod
    def _scan(self) -> SourceIndex:
        """List every frame of ``self.root`` and the native camera; raise DatasetError on malformed input."""

    # ----------------------------------------------------------------------------- source hooks (image files)
    def _check_source(self, root: Path) -> None:
        """DatasetError unless ``root`` (an existing path) is a source this reader opens: here, a folder."""
        if not root.is_dir():
            raise DatasetError(f"{root}: not a folder")

    def _check_frames_exist(self) -> None:
        """DatasetError naming the first selected frame whose colour or depth image is missing."""
        for p in (*self._rgb_paths, *self._depth_paths):
            if not p.is_file():
                raise DatasetError(f"{p}: image file not found")

    def _read_native_size(self) -> tuple[int, int]:
        """Native ``(width, height)`` of the sequence's images: the first selected depth image's."""
        h, w = read_depth(self._depth_paths[0], self.depth_scale)[0].shape
        return w, h

    def _size_mismatch(self, size: tuple[int, int], expected: tuple[int, int]) -> str:
        """The message when the native ``size`` is not the ``expected`` one the dataset states."""
        return (f"{self._depth_paths[0]}: image is {size[0]}x{size[1]} but the dataset states "
                f"{expected[0]}x{expected[1]}")

    def _load_frame(self, i: int) -> tuple[np.ndarray, np.ndarray, int]:
        """Frame ``i`` of the selection at native size: ``(rgb (H, W, 3) uint8, depth (H, W) float32 metres with
        invalid values 0, count of non-finite depth pixels)``."""
        rgb = read_color(self._rgb_paths[i])
        depth, n_nonfinite = read_depth(self._depth_paths[i], self.depth_scale, self._invalid_raw)
        return rgb, depth, n_nonfinite

    # ------------------------------------------------------------------------------------------ public API
    def __len__(self) -> int:
        return len(self.timestamps)

    def __iter__(self) -> Iterator[Frame]:
        for i in range(len(self)):
            yield self[i]

    def __getitem__(self, i: int) -> Frame:
        """Load frame ``i`` of the selection: rgb (H, W, 3) uint8, depth (H, W) float32 metres (0 = invalid),
        K (3, 3) and the ground-truth ``T_w_c`` (4, 4) or None."""
        n = len(self)
        i = operator.index(i)
        if i < 0:
            i += n
        if not 0 <= i < n:
            raise IndexError(f"frame index {i} out of range for a sequence of {n} frames")
        rgb, depth, n_nonfinite = self._load_frame(i)
        rgb = self._check_sizes(i, rgb, depth)
        if self._undistort is not None:
            rgb = self._undistort(rgb)
        rgb, depth = self._geometry.color(rgb), self._geometry.depth(depth)
        if n_nonfinite:
            self._warn_once("nonfinite", "%s: %d NaN/inf depth pixels set to 0 (invalid); further such frames "
                            "are not reported", self._depth_paths[i], n_nonfinite)
        if not np.any(depth > 0):
            self._warn_once("zero", "%s: depth has no valid pixel (all zero); further such frames are not "
                            "reported", self._depth_paths[i])
        T = None
        if self._poses is not None and np.all(np.isfinite(self._poses[i])):
            T = self._poses[i].copy()
        return Frame(index=i, timestamp=float(self.timestamps[i]), rgb=rgb, depth=depth, K=self.K.copy(),
                     T_w_c_gt=T)

    def depth_path(self, i: int) -> Path:
        """The depth image file of frame ``i`` of the selection (for messages)."""
        return self._depth_paths[i]

    def gt_poses(self) -> np.ndarray | None:
        """Ground-truth ``T_w_c`` of the selected frames, (N, 4, 4) float64, NaN-filled where a frame has none;
        None when the dataset has no ground truth. For evaluation only."""
        return None if self._poses is None else self._poses.copy()

    def __repr__(self) -> str:
        return (f"{type(self).__name__}(name={self.name!r}, root='{self.root}', frames={len(self)}, "
                f"size={self.width}x{self.height})")

    # ------------------------------------------------------------------------------------------- internals
    def _check_sizes(self, i: int, rgb: np.ndarray, depth: np.ndarray) -> np.ndarray:
        """Depth must have the sequence's native size, colour the depth's size (or is resized to it)."""
        w, h = self._native_size
        if depth.shape != (h, w):
            raise DatasetError(f"{self._depth_paths[i]}: depth is {depth.shape[1]}x{depth.shape[0]} but the "
                               f"sequence's images are {w}x{h}")
        if rgb.shape[:2] != depth.shape:
            if not self.color_to_depth_size:
                raise DatasetError(f"{self._rgb_paths[i]}: colour is {rgb.shape[1]}x{rgb.shape[0]} but its depth "
                                   f"image is {w}x{h}")
            import cv2

            rgb = cv2.resize(rgb, (w, h), interpolation=cv2.INTER_AREA)
        return rgb

    def _warn_once(self, key: str, msg: str, *args: object) -> None:
        if key not in self._warned:
            self._warned.add(key)
            log.warning(msg, *args)
