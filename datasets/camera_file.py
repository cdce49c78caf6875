"""``intrinsics.yaml``: the camera of a TUM-layout folder recorded with a camera that is not a Freiburg one.

Format (a YAML mapping beside ``rgb.txt``; pixels refer to the native image size)::

    fx: 525.0            # focal lengths, pixels
    fy: 525.0
    cx: 319.5            # principal point, pixels (OpenCV: pixel centres at integers)
    cy: 239.5
    distortion: [0.0, 0.0, 0.0, 0.0, 0.0]   # optional: OpenCV k1 k2 p1 p2 k3 of the colour camera
    depth_scale: 5000.0                     # optional: raw depth units per metre (TUM: 5000)

Unknown keys are errors (a typo must not fall back to a default).
"""

from __future__ import annotations

import math
from pathlib import Path

from pydantic import ConfigDict, PositiveFloat, field_validator

from lrslam.config import StrictModel
from lrslam.datasets.parsing import read_yaml_model

__all__ = ["CameraFile", "read_camera_file", "CAMERA_FILE"]

CAMERA_FILE = "intrinsics.yaml"


class CameraFile(StrictModel):
    """Pinhole intrinsics (pixels), optional colour distortion and depth scale of a user's camera."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    fx: PositiveFloat
    fy: PositiveFloat
    cx: float
    cy: float
    distortion: tuple[float, float, float, float, float] | None = None
    depth_scale: PositiveFloat | None = None

    @field_validator("fx", "fy", "cx", "cy", "depth_scale")
    @classmethod
    def _finite(cls, v: float | None) -> float | None:
        if v is not None and not math.isfinite(v):
            raise ValueError(f"must be finite, got {v}")
        return v


def read_camera_file(path: Path) -> CameraFile:
    """Parse an ``intrinsics.yaml`` (see the module docstring); DatasetError naming the file and the key."""
    return read_yaml_model(path, CameraFile, "camera", " (expected fx, fy, cx, cy in pixels; optional distortion "
                           "[k1, k2, p1, p2, k3], depth_scale)")
