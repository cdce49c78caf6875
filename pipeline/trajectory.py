"""The one owner of every camera pose of a run: keyframe poses, and non-keyframes stored relative to their
keyframe (so a correction of a keyframe moves the frames that hang off it).

Poses are stored re-orthonormalised (:func:`lrslam.geometry.orthonormalise`): the seeds chain through this
trajectory (last pose times the frontend's increment), and a rotation slightly off SO(3) compounds frame after
frame through the keyframe-relative storage.

Every other component -- the field's keyframe views, the loop closer, the keyframe policy, the pose graph --
receives the poses it needs from here as arguments and hands back what it changed; nothing else keeps a pose
copy that could silently diverge.
"""

from __future__ import annotations

import numpy as np

from lrslam.geometry import inv, orthonormalise, pose_error

__all__ = ["Trajectory"]


class Trajectory:
    """``T_w_c`` poses (4x4 float64) of frames added in order (frame index = order of addition); keyframes are
    stored absolutely, other frames as ``T_kf_c`` relative to the last keyframe before them (frames before any
    keyframe absolutely)."""

    def __init__(self) -> None:
        self._kf: dict[int, np.ndarray] = {}       # keyframe frame index -> T_w_kf
        self._anchor: list[int | None] = []        # per frame: anchoring keyframe (None = absolute)
        self._rel: list[np.ndarray] = []           # per frame: T_kf_c (or T_w_c when unanchored)
        self._last_kf: int | None = None

    def __len__(self) -> int:
        return len(self._rel)

    def add(self, T_w_c: np.ndarray, is_keyframe: bool = False) -> int:
        """Append the next frame's pose; returns its frame index (0-based, in order of addition)."""
        idx = len(self._rel)
        T_w_c = orthonormalise(T_w_c)
        if is_keyframe:
            self._kf[idx] = T_w_c.copy()
            self._last_kf = idx
            self._anchor.append(idx)
            self._rel.append(np.eye(4))
        elif self._last_kf is None:
            self._anchor.append(None)
            self._rel.append(T_w_c.copy())
        else:
            self._anchor.append(self._last_kf)
            self._rel.append(inv(self._kf[self._last_kf]) @ T_w_c)
        return idx

    def set_pose(self, idx: int, T_w_c: np.ndarray) -> None:
        """Overwrite frame ``idx``'s pose (e.g. after mapping refined it); a keyframe moves its dependants."""
        T_w_c = orthonormalise(T_w_c)
        if idx in self._kf:
            self._kf[idx] = T_w_c.copy()
        else:
            a = self._anchor[idx]
            self._rel[idx] = T_w_c.copy() if a is None else inv(self._kf[a]) @ T_w_c

    def apply_corrections(self, poses: dict[int, np.ndarray], min_shift_m: float = 0.0,
                          min_shift_deg: float = 0.0) -> dict[int, tuple[float, float]]:
        """Move keyframes to corrected poses (frame index -> ``T_w_kf``); their non-keyframes follow rigidly.
        Only keyframes that moved by more than ``min_shift_m`` or ``min_shift_deg`` are written.

        Returns ``{keyframe: (shift m, shift deg)}`` of the keyframes written.
        """
        moved = {}
        for k, T in poses.items():
            if k not in self._kf:
                continue
            d_t, d_r = pose_error(self._kf[k], T)
            if d_t > min_shift_m or d_r > min_shift_deg:
                self._kf[k] = orthonormalise(T)
                moved[k] = (d_t, d_r)
        return moved

    def pose(self, idx: int) -> np.ndarray:
        """Current ``T_w_c`` of frame ``idx`` (4x4 float64; negative indices count from the end)."""
        idx = idx % len(self._rel) if idx < 0 else idx
        a = self._anchor[idx]
        return self._rel[idx].copy() if a is None else self._kf[a] @ self._rel[idx]

    def last_motion(self) -> tuple[float, float]:
        """Motion between the last two frames: (metres, degrees); (0, 0) with fewer than two frames."""
        if len(self._rel) < 2:
            return 0.0, 0.0
        d_t, d_r = pose_error(self.pose(-2), self.pose(-1))
        return float(d_t), float(d_r)

    def poses(self) -> np.ndarray:
        """All frames' ``T_w_c`` as (N, 4, 4)."""
        return np.stack([self.pose(i) for i in range(len(self))]) if len(self) else np.zeros((0, 4, 4))

    def keyframe_ids(self) -> list[int]:
        return sorted(self._kf)

    @property
    def last_keyframe(self) -> int | None:
        return self._last_kf

    def state_dict(self) -> dict:
        """Keyframe poses, per-frame anchors and relative poses, for checkpoints (:meth:`load_state_dict`)."""
        return {"kf": {k: v.copy() for k, v in self._kf.items()}, "anchor": list(self._anchor),
                "rel": np.stack(self._rel) if self._rel else np.zeros((0, 4, 4)), "last_kf": self._last_kf}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output (replaces every pose)."""
        self._kf = {int(k): np.asarray(v, dtype=np.float64) for k, v in state["kf"].items()}
        self._anchor = [None if a is None else int(a) for a in state["anchor"]]
        self._rel = [np.asarray(T, dtype=np.float64) for T in state["rel"]]
        self._last_kf = state["last_kf"]

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """``{keyframe index: T_w_kf}`` (copies), in index order."""
        return {k: v.copy() for k, v in sorted(self._kf.items())}
