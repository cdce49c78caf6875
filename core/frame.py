"""The one frame type every reader returns."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lrslam.errors import InputError

__all__ = ["Frame", "DepthSized"]


class DepthSized:
    """``height`` and ``width`` in pixels of an RGB-D pair, read off its ``depth`` image (H, W)."""

    depth: np.ndarray

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])


@dataclass
class Frame(DepthSized):
    """One RGB-D frame.

    Attributes:
        index: position in the (strided, truncated) sequence, 0-based.
        timestamp: seconds (the input's own clock).
        rgb: (H, W, 3) uint8, RGB order.
        depth: (H, W) float32 metres, z-depth along the optical axis; 0 = invalid (never NaN/inf).
        K: (3, 3) float64 pinhole intrinsics of the (possibly resized/cropped) images.
        T_w_c_gt: (4, 4) float64 ground-truth camera-to-world pose, or None. Evaluation only: algorithm code
            must never read it.
    """

    index: int
    timestamp: float
    rgb: np.ndarray
    depth: np.ndarray
    K: np.ndarray
    T_w_c_gt: np.ndarray | None = None

    def valid_depth_fraction(self) -> float:
        """Fraction of pixels with a positive depth."""
        return float(np.count_nonzero(self.depth > 0)) / self.depth.size

    def require_depth(self, source: str | Path | None = None) -> None:
        """The first frame of a map needs depth: InputError naming ``source`` (e.g. its depth file; default
        ``frame <index>``) when no pixel has any."""
        if self.valid_depth_fraction() == 0:
            raise InputError(f"{source or f'frame {self.index}'}: the first frame has no valid depth (all zero); "
                             "cannot initialise the map")
