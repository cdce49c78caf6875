"""Reader for synthetic scenes written by ``lrslam synth`` (``synthetic``).

Layout: the TUM layout (``rgb.txt``, ``depth.txt``, ``groundtruth.txt``, images; see
:mod:`lrslam.datasets.tum` for association and ground truth) plus

* ``scene.yaml`` with at least ``intrinsics: {fx, fy, cx, cy, width, height}`` (pixels), ``depth_scale``
  (raw units per metre, 5000 like TUM) and ``bound: [[xmin, xmax], [ymin, ymax], [zmin, zmax]]`` (metres,
  world frame); other keys are ignored here;
* ``gt_mesh.ply`` beside it: the exact scene surface in the world frame (``Sequence.gt_mesh_path``).

The camera is an ideal pinhole (no distortion); images must be ``width x height``.
"""

from __future__ import annotations

import logging
from pathlib import Path

from pydantic import BaseModel, ConfigDict, PositiveFloat, PositiveInt, field_validator

from lrslam.camera import intrinsics_matrix
from lrslam.datasets.base import SourceIndex
from lrslam.datasets.parsing import read_yaml_model
from lrslam.datasets.registry import register
from lrslam.datasets.tum import TumReader

__all__ = ["SyntheticReader", "SceneInfo"]

log = logging.getLogger(__name__)


class SceneIntrinsics(BaseModel):
    """Pinhole camera of a synthetic scene (pixels)."""

    model_config = ConfigDict(extra="ignore", frozen=True)
    fx: PositiveFloat
    fy: PositiveFloat
    cx: float
    cy: float
    width: PositiveInt
    height: PositiveInt


class SceneInfo(BaseModel):
    """The part of ``scene.yaml`` the reader needs (other keys are ignored)."""

    model_config = ConfigDict(extra="ignore", frozen=True)
    intrinsics: SceneIntrinsics
    depth_scale: PositiveFloat
    bound: tuple[tuple[float, float], tuple[float, float], tuple[float, float]]

    @field_validator("bound")
    @classmethod
    def _ordered(cls, b: tuple[tuple[float, float], ...]) -> tuple[tuple[float, float], ...]:
        if not all(lo < hi for lo, hi in b):
            raise ValueError(f"each bound row must be [min, max] with min < max, got {b}")
        return b


def load_scene_info(path: Path) -> SceneInfo:
    """Parse ``scene.yaml``; DatasetError naming the file and the first problem."""
    return read_yaml_model(path, SceneInfo, "scene")


@register("synthetic")
class SyntheticReader(TumReader):
    """Synthetic scene in TUM layout plus ``scene.yaml`` (intrinsics, depth scale, bound) and ``gt_mesh.ply``."""

    layout_hint = "rgb.txt + depth.txt + scene.yaml (+ gt_mesh.ply)"

    @classmethod
    def detect(cls, root: Path) -> bool:
        return (root / "rgb.txt").is_file() and (root / "scene.yaml").is_file()

    def _scan(self) -> SourceIndex:
        scene = load_scene_info(self.root / "scene.yaml")
        timestamps, rgb_paths, depth_paths, poses = self._scan_lists()
        cam = scene.intrinsics
        mesh = self.root / "gt_mesh.ply"
        if not mesh.is_file():
            log.warning("%s: no gt_mesh.ply beside scene.yaml; mesh evaluation is unavailable", self.root)
        return SourceIndex(timestamps=timestamps, rgb_paths=rgb_paths, depth_paths=depth_paths,
                           K=intrinsics_matrix(cam.fx, cam.fy, cam.cx, cam.cy), depth_scale=scene.depth_scale,
                           poses=poses, expected_size=(cam.width, cam.height), bound=scene.bound,
                           gt_mesh_path=mesh if mesh.is_file() else None)
