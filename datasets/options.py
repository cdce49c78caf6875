"""Options shared by every dataset reader: frame selection, image geometry, intrinsics override."""

from __future__ import annotations

import math

import numpy as np
from pydantic import Field, PositiveFloat, PositiveInt, model_validator

from lrslam.camera import intrinsics_matrix
from lrslam.config import StrictModel

__all__ = ["ReaderOptions"]


class ReaderOptions(StrictModel):
    """How a reader turns a dataset folder into frames.

    Order of operations on each frame: (1) colour undistortion (TUM only, native intrinsics; depth untouched)
    or registration to the depth camera (7-Scenes only), (2) ``resize`` of both images to ``(width, height)``,
    (3) ``crop_border`` pixels removed on every side.
    ``Sequence.K`` / ``Frame.K`` describe the images after all three steps.

    Attributes:
        stride: keep every ``stride``-th frame of the dataset (1 = all).
        max_frames: keep at most this many frames (after the stride); None = all.
        crop_border: pixels removed on every side after resizing (ESLAM ``crop_edge``); ``cx, cy -= crop_border``.
        resize: output size ``(width, height)`` in pixels before cropping (ESLAM ``crop_size``, which is a resize);
            K is scaled so pixel centres stay consistent with OpenCV's resampling.
        undistort: undistort the colour image with the camera's distortion model (TUM Freiburg 1/2 only; the
            depth image is left as is, like ESLAM).
        fx, fy, cx, cy: pinhole intrinsics (pixels, native image size) overriding the reader's own, for readers
            whose intrinsics come from a config (Replica), for a TUM-layout folder of a non-Freiburg camera, or to
            correct a dataset. All four or none. The override describes an ideal pinhole camera (the reader's own
            distortion model is not applied) unless ``distortion`` is given.
        distortion: OpenCV ``k1 k2 p1 p2 k3`` of the colour camera that goes with an intrinsics override.
        register_colour: resample the colour image into the depth camera (7-Scenes only, whose Kinect recorded
            colour and depth unregistered: :mod:`lrslam.datasets.colour_registration`; not for a folder whose
            ``camera-intrinsics.txt`` or intrinsics override names another camera); other readers ignore it.
        depth_scale: raw depth units per metre (metres = raw / depth_scale), overriding the reader's own.
        rgb_topic, depth_topic, camera_info_topic: ROS bags only (:mod:`lrslam.datasets.rosbag`): the
            ``sensor_msgs/Image`` colour and depth topics and the ``sensor_msgs/CameraInfo`` topic to read; None =
            the bag's only topic of that kind. Other readers ignore them.
    """

    stride: PositiveInt = 1
    max_frames: PositiveInt | None = None
    crop_border: int = Field(0, ge=0)
    resize: tuple[PositiveInt, PositiveInt] | None = None
    undistort: bool = True
    fx: PositiveFloat | None = None
    fy: PositiveFloat | None = None
    cx: float | None = None
    cy: float | None = None
    distortion: tuple[float, float, float, float, float] | None = None
    depth_scale: PositiveFloat | None = None
    register_colour: bool = True
    rgb_topic: str | None = Field(None, description="ROS bags: the sensor_msgs/Image colour topic (None: the only "
                                  "one with a colour encoding)")
    depth_topic: str | None = Field(None, description="ROS bags: the sensor_msgs/Image depth topic (None: the only "
                                    "one with a depth encoding)")
    camera_info_topic: str | None = Field(None, description="ROS bags: the sensor_msgs/CameraInfo topic giving K "
                                          "(None: the only one, or the one beside the depth topic)")

    @model_validator(mode="after")
    def _intrinsics_all_or_none(self) -> ReaderOptions:
        given = [v is not None for v in (self.fx, self.fy, self.cx, self.cy)]
        if any(given) and not all(given):
            raise ValueError("intrinsics override needs all of fx, fy, cx, cy (or none of them)")
        if self.distortion is not None and not any(given):
            raise ValueError("distortion needs the intrinsics override fx, fy, cx, cy")
        if self.distortion is not None and not all(math.isfinite(v) for v in self.distortion):
            raise ValueError(f"distortion must be finite, got {self.distortion}")
        for name in ("fx", "fy", "cx", "cy", "depth_scale"):
            v = getattr(self, name)
            if v is not None and not math.isfinite(v):
                raise ValueError(f"{name} must be finite, got {v}")
        return self

    def intrinsics_override(self) -> np.ndarray | None:
        """The 3x3 float64 override matrix (native image size), or None when no override is given."""
        if self.fx is None:
            return None
        return intrinsics_matrix(self.fx, self.fy, self.cx, self.cy)
