"""Image I/O and per-frame image geometry (undistort, resize, crop) shared by every reader.

OpenCV does the work: ``cv2.imread`` (colour converted BGR -> RGB; depth read unchanged), ``cv2.remap`` for
undistortion, ``cv2.resize`` for resizing. Every failure is a one-line :class:`~lrslam.errors.DatasetError`
naming the file.

Pixel convention (:mod:`lrslam.camera`): integer pixel ``u`` samples the image at ``u``, so OpenCV's
resampling (output pixel ``u'`` <- input position ``(u' + 0.5) / s - 0.5``) maps ``cx`` to
``(cx + 0.5) * s - 0.5`` and ``fx`` to ``fx * s``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lrslam.errors import DatasetError, InputError

__all__ = ["read_color", "read_depth", "ImageGeometry", "Undistorter"]


def _imread(path: Path, flags: int) -> np.ndarray:
    import cv2

    if not path.is_file():
        raise DatasetError(f"{path}: image file not found")
    img = cv2.imread(str(path), flags)
    if img is None or img.size == 0:
        raise DatasetError(f"{path}: unreadable or corrupt image")
    return img


def read_color(path: Path) -> np.ndarray:
    """Read a colour image -> (H, W, 3) uint8 RGB (grey images are replicated, 16-bit ones scaled to 8 bit)."""
    import cv2

    return cv2.cvtColor(_imread(Path(path), cv2.IMREAD_COLOR), cv2.COLOR_BGR2RGB)


def read_depth(path: Path, depth_scale: float, invalid_raw: tuple[int, ...] = ()) -> tuple[np.ndarray, int]:
    """Read a single-channel depth image -> ``(depth (H, W) float32 metres, count of non-finite pixels)``.

    ``metres = raw / depth_scale``. Accepted raw types: uint16 (the usual PNG) and float32/float64 (e.g. TIFF).
    Raw values listed in ``invalid_raw`` (e.g. 65535 in 7-Scenes), NaN, inf and negative values become 0
    (invalid); the non-finite count is returned so the caller can log it. Any other dtype (8-bit depth, ...)
    or a multi-channel image raises DatasetError.
    """
    import cv2

    path = Path(path)
    raw = _imread(path, cv2.IMREAD_UNCHANGED)
    if raw.ndim != 2:
        raise DatasetError(f"{path}: depth must be a single-channel image, got shape {raw.shape}")
    if raw.dtype == np.uint16:
        depth = raw.astype(np.float32) / np.float32(depth_scale)
        for v in invalid_raw:
            depth[raw == v] = 0.0
        return depth, 0
    if raw.dtype in (np.float32, np.float64):
        depth = raw.astype(np.float32) / np.float32(depth_scale)
        bad = ~np.isfinite(depth)
        n_bad = int(np.count_nonzero(bad))
        depth[bad | (depth < 0)] = 0.0
        return depth, n_bad
    raise DatasetError(f"{path}: depth has dtype {raw.dtype}; expected 16-bit unsigned (uint16) or float32")


@dataclass(frozen=True)
class ImageGeometry:
    """Native image size ``(width, height)`` -> output: resize to ``resize`` ``(width, height)``, then remove
    ``crop`` pixels on every side."""

    width: int
    height: int
    resize: tuple[int, int] | None = None
    crop: int = 0

    def __post_init__(self) -> None:
        w, h = self.resize or (self.width, self.height)
        if w - 2 * self.crop < 1 or h - 2 * self.crop < 1:
            raise InputError(f"crop_border={self.crop} leaves no pixels of the {w}x{h} image")

    @property
    def out_size(self) -> tuple[int, int]:
        """Output ``(width, height)`` in pixels."""
        w, h = self.resize or (self.width, self.height)
        return w - 2 * self.crop, h - 2 * self.crop

    def adjust_K(self, K: np.ndarray) -> np.ndarray:
        """3x3 intrinsics of the native image -> intrinsics of the output image (float64)."""
        K = np.array(K, dtype=np.float64)
        if self.resize is not None:
            sx, sy = self.resize[0] / self.width, self.resize[1] / self.height
            K[0, 0] *= sx
            K[1, 1] *= sy
            K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
            K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        K[0, 2] -= self.crop
        K[1, 2] -= self.crop
        return K

    def color(self, rgb: np.ndarray) -> np.ndarray:
        """(H, W, 3) uint8 native -> output. Area averaging when shrinking, bilinear when enlarging."""
        import cv2

        if self.resize is not None and self.resize != (rgb.shape[1], rgb.shape[0]):
            shrink = self.resize[0] * self.resize[1] < rgb.shape[0] * rgb.shape[1]
            rgb = cv2.resize(rgb, self.resize, interpolation=cv2.INTER_AREA if shrink else cv2.INTER_LINEAR)
        return self._crop(rgb)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """(H, W) float32 metres native -> output. Nearest neighbour (no blending across depth edges)."""
        import cv2

        if self.resize is not None and self.resize != (depth.shape[1], depth.shape[0]):
            depth = cv2.resize(depth, self.resize, interpolation=cv2.INTER_NEAREST_EXACT)
        return self._crop(depth)

    def _crop(self, img: np.ndarray) -> np.ndarray:
        c = self.crop
        return np.ascontiguousarray(img[c:img.shape[0] - c, c:img.shape[1] - c]) if c else img


class Undistorter:
    """Removes lens distortion (OpenCV model ``k1 k2 p1 p2 k3``) from colour images, keeping the same pinhole K
    (like ``cv2.undistort``, which ESLAM uses); the remap tables are built once per image size."""

    def __init__(self, K: np.ndarray, distortion: np.ndarray) -> None:
        self.K = np.asarray(K, dtype=np.float64)
        self.distortion = np.asarray(distortion, dtype=np.float64).reshape(-1)
        self._maps: dict[tuple[int, int], tuple[np.ndarray, np.ndarray]] = {}

    def __call__(self, img: np.ndarray) -> np.ndarray:
        """(H, W, C) image in the distorted camera -> the same image seen by the ideal pinhole camera K."""
        import cv2

        size = (img.shape[1], img.shape[0])
        if size not in self._maps:
            self._maps[size] = cv2.initUndistortRectifyMap(self.K, self.distortion, None, self.K, size,
                                                           cv2.CV_32FC1)
        mx, my = self._maps[size]
        return cv2.remap(img, mx, my, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
