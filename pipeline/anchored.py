"""Per-frame poses stored relative to their keyframe, so graph corrections of keyframes move them too."""

from __future__ import annotations

import numpy as np

from lrslam.geometry import inv

__all__ = ["AnchoredTrajectory"]


class AnchoredTrajectory:
    """Trajectory of ``T_w_c`` poses where non-keyframes hang off a keyframe (``T_w_c = T_w_kf @ T_kf_c``).

    Keyframes are identified by their frame index. Frames added before any keyframe are stored absolutely.
    """

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
        T_w_c = np.asarray(T_w_c, dtype=np.float64)
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
        T_w_c = np.asarray(T_w_c, dtype=np.float64)
        if idx in self._kf:
            self._kf[idx] = T_w_c.copy()
        else:
            a = self._anchor[idx]
            self._rel[idx] = T_w_c.copy() if a is None else inv(self._kf[a]) @ T_w_c

    def update_keyframes(self, poses: dict[int, np.ndarray]) -> None:
        """Move keyframes (frame index -> new ``T_w_kf``); their non-keyframes follow rigidly."""
        for k, T in poses.items():
            if k in self._kf:
                self._kf[k] = np.asarray(T, dtype=np.float64).copy()

    def pose(self, idx: int) -> np.ndarray:
        """Current ``T_w_c`` of frame ``idx`` (4x4 float64)."""
        a = self._anchor[idx]
        return self._rel[idx].copy() if a is None else self._kf[a] @ self._rel[idx]

    def poses(self) -> np.ndarray:
        """All frames' ``T_w_c`` as (N, 4, 4)."""
        return np.stack([self.pose(i) for i in range(len(self))]) if len(self) else np.zeros((0, 4, 4))

    def keyframe_ids(self) -> list[int]:
        return sorted(self._kf)

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        return {k: v.copy() for k, v in sorted(self._kf.items())}
