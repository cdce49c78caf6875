"""Numpy frames at the field's boundary -> validated torch tensors (the only place input arrays are checked)."""

from __future__ import annotations

import numpy as np
import torch

from lrslam.errors import InputError

__all__ = ["resolve_device", "image_tensors", "has_valid_depth", "inside_bound"]


def resolve_device(device: str) -> torch.device:
    """``"auto"`` -> CUDA when available, else CPU; anything else is passed to :class:`torch.device`."""
    if device == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        return torch.device(device)
    except RuntimeError as e:
        raise InputError(f"unknown torch device {device!r}: {e}") from None


def image_tensors(rgb: np.ndarray, depth: np.ndarray, height: int, width: int, device: torch.device
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """Check one RGB-D frame and move it to ``device``.

    Args:
        rgb: (H, W, 3) uint8 RGB. depth: (H, W) metres (z-depth); NaN, inf and values <= 0 count as invalid.
        height, width: the size the field was set up with.
    Returns:
        (rgb (H, W, 3) uint8 tensor, depth (H, W) float32 tensor with invalid pixels set to 0).
    Raises:
        InputError: wrong shapes or dtype.
    """
    rgb = np.asarray(rgb)
    depth = np.asarray(depth)
    if rgb.shape != (height, width, 3):
        raise InputError(f"rgb image must be ({height}, {width}, 3) uint8, got {rgb.shape} {rgb.dtype}")
    if depth.shape != (height, width):
        raise InputError(f"depth image must be ({height}, {width}) metres, got {depth.shape}")
    if rgb.dtype != np.uint8:
        raise InputError(f"rgb image must be uint8, got {rgb.dtype}")
    d = depth.astype(np.float32, copy=True)
    d[~np.isfinite(d) | (d < 0)] = 0.0
    return torch.from_numpy(np.ascontiguousarray(rgb)).to(device), torch.from_numpy(d).to(device)


def has_valid_depth(depth: torch.Tensor) -> bool:
    """True when the depth tensor from :func:`image_tensors` has at least one valid (positive) pixel."""
    return bool((depth > 0).any())


def inside_bound(point: np.ndarray, bound: np.ndarray, margin: float = 0.0) -> bool:
    """True when the 3-vector ``point`` (metres) lies inside ``bound`` (3, 2) grown by ``margin`` metres."""
    p = np.asarray(point, dtype=np.float64)
    return bool(np.all(np.isfinite(p)) and np.all(p >= bound[:, 0] - margin) and np.all(p <= bound[:, 1] + margin))
