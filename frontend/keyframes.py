"""Keyframe policy: a frame becomes a keyframe when the camera has moved or turned enough since the last keyframe,
when it sees too little of the last keyframe's view, or every ``every_n`` frames (ESLAM-style fallback), but
never sooner than ``min_frames`` after the last one.

The policy keeps the last keyframe's (sub-sampled) depth image only; its pose is handed in by the caller (the
pipeline's trajectory owns every pose), so a pose-graph correction can never leave a stale copy here.

:func:`view_overlap` is a pure function shared by the mapper (keyframe window selection) and the pose graph
(loop candidates).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
from pydantic import Field

from lrslam.camera import backproject_depth, project_points, strided_intrinsics, transform_points
from lrslam.config import StrictModel
from lrslam.geometry import checked_pose, inv, pose_error

__all__ = ["KeyframeConfig", "KeyframePolicy", "view_overlap"]

log = logging.getLogger(__name__)


class KeyframeConfig(StrictModel):
    """When a frame becomes a keyframe (any criterion suffices). 0 disables a criterion."""

    min_translation: float = Field(0.15, ge=0, description="m moved since the last keyframe")
    min_rotation: float = Field(15.0, ge=0, description="deg turned since the last keyframe")
    max_overlap: float = Field(0.70, ge=0, le=1, description="a frame whose view overlap with the last keyframe "
                               "is below this fraction is a keyframe (needs depth and K)")
    min_frames: int = Field(1, ge=1, description="frames at least between two keyframes")
    every_n: int = Field(6, ge=0, description="a keyframe at least every n frames (ESLAM: every 4-5); the field's "
                         "mapper remembers keyframes only, and fewer than this measurably weakened the fused map")
    overlap_stride: int = Field(8, gt=0, description="pixel sub-sampling of the overlap estimate")
    occlusion_tolerance: float = Field(0.05, gt=0, description="m; with the keyframe depth, points farther "
                                       "behind the keyframe surface than this count as not visible")


def view_overlap(depth_a: np.ndarray, K_a: np.ndarray, T_w_a: np.ndarray, K_b: np.ndarray, T_w_b: np.ndarray,
                 shape_b: tuple[int, int], depth_b: np.ndarray | None = None, stride: int = 8,
                 depth_min: float = 1e-3, occlusion_tolerance: float = 0.05) -> float:
    """Fraction of view a's back-projected points (valid depth, every ``stride``-th pixel) that land inside
    view b's image ``shape_b = (H, W)`` in front of camera b.

    ``depth_a (H_a, W_a)`` metres, ``K_a``/``K_b`` (3, 3), poses ``T_w_a``/``T_w_b`` (4, 4) camera-to-world.
    With ``depth_b`` (same size as ``shape_b``), points hidden behind b's surface by more than
    ``occlusion_tolerance`` (m) do not count. Returns 0.0 when a has no valid depth. Not symmetric.
    """
    d = np.asarray(depth_a, dtype=np.float64)[::stride, ::stride]
    ok = d > depth_min
    n = int(ok.sum())
    if n == 0:
        return 0.0
    p_a = backproject_depth(d, strided_intrinsics(K_a, stride))[ok]
    p_b = transform_points(inv(T_w_b) @ np.asarray(T_w_a, dtype=np.float64), p_a)
    uv, z = project_points(p_b, np.asarray(K_b, dtype=np.float64))
    h, w = shape_b
    with np.errstate(invalid="ignore"):
        u, v = np.rint(uv[:, 0]), np.rint(uv[:, 1])
    inside = (z > depth_min) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    if depth_b is not None and inside.any():
        db = np.asarray(depth_b)[v[inside].astype(int), u[inside].astype(int)]
        visible = (db <= depth_min) | (z[inside] <= db + occlusion_tolerance)
        inside[np.flatnonzero(inside)[~visible]] = False
    return float(inside.sum()) / n


@dataclass
class _LastKeyframe:
    index: int
    depth: np.ndarray | None  # sub-sampled by the overlap stride (with K to match), for the overlap test
    K: np.ndarray | None


class KeyframePolicy:
    """Decides keyframes. State: the last keyframe's index and sub-sampled depth (no pose)."""

    def __init__(self, cfg: KeyframeConfig):
        self.cfg = cfg
        self._last: _LastKeyframe | None = None

    @property
    def last_keyframe_index(self) -> int | None:
        return None if self._last is None else self._last.index

    def is_keyframe(self, frame_index: int, T_w_c: np.ndarray, T_w_last: np.ndarray | None,
                    depth: np.ndarray | None = None, K: np.ndarray | None = None,
                    commit: bool = True) -> tuple[bool, str]:
        """Whether frame ``frame_index`` at ``T_w_c`` (4x4) is a keyframe, and why (or why not).

        ``T_w_last``: the current pose of the last keyframe (None before the first). ``depth (H, W)`` metres and
        ``K (3, 3)`` enable the overlap criterion. With ``commit`` (default) a positive decision records the
        frame as the last keyframe (as :meth:`add_keyframe`).
        """
        T = self._pose(T_w_c, frame_index)
        decision, reason = self._decide(frame_index, T, T_w_last, depth, K)
        log.debug("frame %d: keyframe=%s (%s)", frame_index, decision, reason)
        if decision and commit:
            self.add_keyframe(frame_index, depth, K)
        return decision, reason

    def _decide(self, frame_index: int, T: np.ndarray, T_w_last: np.ndarray | None, depth: np.ndarray | None,
                K: np.ndarray | None) -> tuple[bool, str]:
        c, last = self.cfg, self._last
        if last is None or T_w_last is None:
            return True, "first keyframe"
        T_last = self._pose(T_w_last, last.index)
        gap = frame_index - last.index
        if gap < c.min_frames:
            return False, f"{gap} frame(s) since keyframe {last.index} < {c.min_frames}"
        d_t, d_r = pose_error(T_last, T)
        if c.min_translation > 0 and d_t >= c.min_translation:
            return True, f"moved {d_t:.3f} m >= {c.min_translation} m"
        if c.min_rotation > 0 and d_r >= c.min_rotation:
            return True, f"turned {d_r:.1f} deg >= {c.min_rotation} deg"
        if c.every_n > 0 and gap >= c.every_n:
            return True, f"{gap} frames since keyframe {last.index}"
        if c.max_overlap > 0 and depth is not None and K is not None and last.K is not None:
            ov = view_overlap(depth, K, T, last.K, T_last, last.depth.shape, last.depth, stride=c.overlap_stride,
                              occlusion_tolerance=c.occlusion_tolerance)
            if ov < c.max_overlap:
                return True, f"overlap {ov:.2f} < {c.max_overlap}"
            return False, f"moved {d_t:.3f} m, turned {d_r:.1f} deg, overlap {ov:.2f}"
        return False, f"moved {d_t:.3f} m, turned {d_r:.1f} deg"

    def state_dict(self) -> dict:
        """The last keyframe's index, sub-sampled depth and intrinsics (None before the first), for checkpoints."""
        last = self._last
        return {"last": None if last is None else {"index": last.index, "depth": last.depth, "K": last.K}}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output."""
        last = state["last"]
        self._last = None if last is None else _LastKeyframe(int(last["index"]), last["depth"], last["K"])

    def add_keyframe(self, frame_index: int, depth: np.ndarray | None = None, K: np.ndarray | None = None) -> None:
        """Record frame ``frame_index`` as the last keyframe (forced keyframes, or after ``commit=False``)."""
        if depth is not None and K is not None:
            s = self.cfg.overlap_stride
            d = np.ascontiguousarray(np.asarray(depth, dtype=np.float32)[::s, ::s])
            self._last = _LastKeyframe(frame_index, d, strided_intrinsics(K, s))
        else:
            self._last = _LastKeyframe(frame_index, None, None)

    @staticmethod
    def _pose(T_w_c: np.ndarray, frame_index: int) -> np.ndarray:
        return checked_pose(T_w_c, f"keyframe policy: pose of frame {frame_index}")
