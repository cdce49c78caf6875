"""Scene bound for the field when neither the config nor the dataset gives one, and a check that it fits.

* :func:`bound_from_prepass` (``bound: auto``): a fast frontend pre-pass over the whole sequence (RGB-D odometry
  from :class:`lrslam.frontend.odometry.Odometry`, no field) collects camera centres and subsampled depth points
  in the world frame; the bound is their robust extent (0.1 / 99.9 percentiles) grown by a margin. The pass is
  recorded (:class:`lrslam.frontend.odometry.OdometryTrace`): a fused run's frontend, which registers the same
  frames with the same settings, replays it instead of registering every frame a second time.
* :func:`bound_from_frame`: the old default, the first frame's points plus a margin.
* :class:`BoundCoverage`: counts the frames whose view leaves the bound by more than a fraction of their valid
  pixels (warned once per frame at most; the count goes into metrics).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np

from lrslam.camera import backproject_depth, strided_intrinsics, transform_points
from lrslam.errors import InputError

if TYPE_CHECKING:
    from lrslam.frontend.odometry import OdometryTrace

__all__ = ["bound_from_frame", "bound_from_prepass", "fraction_outside", "BoundCoverage", "PREPASS_TAIL_PCT"]

log = logging.getLogger(__name__)

# percent of the pre-pass points left out at either end of each axis (stray depth). At 0.5 % the TUM fr1/rpy and
# 7-Scenes excerpts each had 3 frames with 6-9 % of their depth outside the bound; at 0.1 % none above 2.3 %
PREPASS_TAIL_PCT = 0.1
_MAX_WARNINGS = 5         # per run, further frames are counted and logged at INFO


def _world_points(depth: np.ndarray, K: np.ndarray, T_w_c: np.ndarray, max_depth: float,
                  pixel_stride: int = 1) -> np.ndarray:
    """Valid depth points (M, 3) of one frame in the world frame, metres (every ``pixel_stride``-th pixel)."""
    d = depth[::pixel_stride, ::pixel_stride]
    pts = backproject_depth(d, strided_intrinsics(K, pixel_stride) if pixel_stride > 1 else K).reshape(-1, 3)
    z = pts[:, 2]
    return transform_points(T_w_c, pts[(z > 0) & (z < max_depth)])


def _extent(points: np.ndarray, centres: np.ndarray, margin: float, tail_pct: float) -> np.ndarray:
    """Axis-aligned (3, 2) extent of ``points`` (M, 3) without ``tail_pct`` percent at either end of each axis
    (stray depth), always holding every camera centre (K, 3), grown by ``margin`` metres."""
    lo, hi = np.percentile(points, tail_pct, axis=0), np.percentile(points, 100.0 - tail_pct, axis=0)
    lo = np.minimum(lo, centres.min(axis=0)) - margin
    hi = np.maximum(hi, centres.max(axis=0)) + margin
    return np.stack([lo, hi], axis=1)


def bound_from_frame(depth: np.ndarray, K: np.ndarray, T_w_c: np.ndarray, margin: float = 1.0,
                     max_depth: float = 6.0) -> np.ndarray:
    """Axis-aligned bound (3, 2) metres (world frame) around a frame's valid points and camera centre,
    grown by ``margin`` metres on every side. Depths beyond ``max_depth`` are ignored."""
    pts = _world_points(depth, K, T_w_c, max_depth)
    if len(pts) == 0:
        raise InputError("cannot derive a scene bound: the first frame has no valid depth")
    return _extent(np.vstack([pts, T_w_c[:3, 3]]), T_w_c[None, :3, 3], margin, 0.5)


def bound_from_prepass(seq, odometry_cfg, T_w_c0: np.ndarray, margin: float = 1.0,
                       max_depth: float = 6.0, pixel_stride: int = 8,
                       progress: Callable[[int, int], None] | None = None) -> tuple[np.ndarray, OdometryTrace]:
    """Bound (3, 2) metres (world frame, first camera at ``T_w_c0``) covering every frame of ``seq`` seen from
    its odometry pose: camera centres and depth points (every ``pixel_stride``-th pixel, depth < ``max_depth``
    metres), 0.1-99.9 percentile extent plus ``margin`` metres, and the odometry pass's trace (for a run's
    frontend to replay). ``progress(done, total)`` after each frame.
    Frame to frame only (``odometry_cfg.model`` off): a bound with a metre of margin does not need the
    frame-to-model refinement's centimetres, and the pre-pass would pay it on every frame."""
    from lrslam.frontend.odometry import Odometry

    first = seq[0]
    odometry_cfg = odometry_cfg.model_copy(update={"model": odometry_cfg.model.model_copy(update={"enabled": False})})
    odo = Odometry(odometry_cfg, first.K, first.height, first.width, record=True)
    odo.reset(np.asarray(T_w_c0, dtype=np.float64), first)
    centres, points = [T_w_c0[:3, 3]], [_world_points(first.depth, first.K, T_w_c0, max_depth, pixel_stride)]
    n_lost = 0
    for i in range(1, len(seq)):
        frame = seq[i]
        res = odo.track(frame)
        n_lost += not res.ok
        T = np.asarray(res.T_w_c, dtype=np.float64)
        centres.append(T[:3, 3])
        points.append(_world_points(frame.depth, frame.K, T, max_depth, pixel_stride))
        if progress is not None:
            progress(i + 1, len(seq))
    pts = np.vstack(points)
    if len(pts) == 0:
        raise InputError(f"{seq.root}: cannot estimate a scene bound: no frame has valid depth")
    b = _extent(np.vstack([pts, centres]), np.asarray(centres), margin, PREPASS_TAIL_PCT)
    log.info("bound: auto from a %d-frame odometry pre-pass (%d frames lost): %s", len(seq), n_lost,
             np.round(b, 3).tolist())
    return b, odo.trace()


def fraction_outside(depth: np.ndarray, K: np.ndarray, T_w_c: np.ndarray, bound: np.ndarray,
                     max_depth: float = 6.0, pixel_stride: int = 4) -> float:
    """Fraction in [0, 1] of a frame's valid depth points (world frame via ``T_w_c``) outside ``bound`` (3, 2)."""
    pts = _world_points(depth, K, T_w_c, max_depth, pixel_stride)
    if len(pts) == 0:
        return 0.0
    b = np.asarray(bound, dtype=np.float64)
    inside = np.all((pts >= b[:, 0]) & (pts <= b[:, 1]), axis=1)
    return float(1.0 - inside.mean())


class BoundCoverage:
    """Counts frames whose view leaves ``bound`` (3, 2) metres by more than ``max_fraction`` of valid pixels."""

    def __init__(self, bound: np.ndarray, max_fraction: float = 0.05) -> None:
        self.bound = np.asarray(bound, dtype=np.float64)
        self.max_fraction = max_fraction
        self.frames: list[int] = []

    def check(self, frame, T_w_c: np.ndarray) -> float:
        """Check one frame (depth, K) at pose ``T_w_c``; returns its fraction of points outside the bound."""
        f = fraction_outside(frame.depth, frame.K, T_w_c, self.bound)
        if f > self.max_fraction:
            self.frames.append(frame.index)
            (log.warning if len(self.frames) <= _MAX_WARNINGS else log.info)(
                "frame %d: %.0f%% of its depth points lie outside the scene bound %s (the field cannot map them: "
                "give a larger `bound`)%s", frame.index, 100 * f, np.round(self.bound, 2).tolist(),
                "; further frames are logged in run.log" if len(self.frames) == _MAX_WARNINGS else "")
        return f

    def metrics(self) -> dict:
        """``frames_outside_bound`` (count) and the first such frame indices, for metrics.json."""
        return {"frames_outside_bound": len(self.frames), "frames_outside_bound_first": self.frames[:10],
                "bound_check_fraction": self.max_fraction}
