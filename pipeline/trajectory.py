"""The one owner of every camera pose of a run: keyframe poses, and non-keyframes stored relative to their
keyframe (so a correction of a keyframe moves the frames that hang off it).

A non-keyframe between two keyframes ``a < c < b`` also keeps its pose relative to ``b`` (taken when ``b`` is
added, where both agree). With ``interpolate`` (the default) it then follows both: its pose is the blend
``A exp(alpha log(A^-1 B))`` of ``A = T_w_a T_a_c`` and ``B = T_w_b T_b_c`` at ``alpha = (c - a) / (b - a)``, so a
correction of ``a`` and ``b`` by the graph or the mapper spreads over the gap the way drift builds up in it,
instead of every frame of the gap taking ``a``'s correction rigidly (measured: on the synthetic loop the
keyframes came out at 0.21 cm ATE and the frames between them at 0.46, docs/BENCHMARKS.md section 17).

Poses are stored re-orthonormalised (:func:`lrslam.geometry.orthonormalise`): the seeds chain through this
trajectory (last pose times the frontend's increment), and a rotation slightly off SO(3) compounds frame after
frame through the keyframe-relative storage.

Every other component -- the field's keyframe views, the loop closer, the keyframe policy, the pose graph --
receives the poses it needs from here as arguments and hands back what it changed; nothing else keeps a pose
copy that could silently diverge.
"""

from __future__ import annotations

import numpy as np

from lrslam.geometry import blend, inv, orthonormalise, pose_error

__all__ = ["Trajectory"]


class Trajectory:
    """``T_w_c`` poses (4x4 float64) of frames added in order (frame index = order of addition); keyframes are
    stored absolutely, other frames as ``T_kf_c`` relative to the last keyframe before them (frames before any
    keyframe absolutely) and, once the next keyframe exists, relative to it too (``interpolate``: the module
    docstring; off, they follow the keyframe before them rigidly)."""

    def __init__(self, interpolate: bool = True) -> None:
        self.interpolate = bool(interpolate)
        self._kf: dict[int, np.ndarray] = {}       # keyframe frame index -> T_w_kf
        self._anchor: list[int | None] = []        # per frame: anchoring keyframe (None = absolute)
        self._rel: list[np.ndarray] = []           # per frame: T_kf_c (or T_w_c when unanchored)
        self._next: list[int | None] = []          # per frame: the keyframe after it (None: none yet / keyframe)
        self._rel_next: list[np.ndarray] = []      # per frame: T_next_c (identity while there is none)
        self._last_kf: int | None = None

    def __len__(self) -> int:
        return len(self._rel)

    def add(self, T_w_c: np.ndarray, is_keyframe: bool = False) -> int:
        """Append the next frame's pose; returns its frame index (0-based, in order of addition)."""
        idx = len(self._rel)
        T_w_c = orthonormalise(T_w_c)
        self._next.append(None)
        self._rel_next.append(np.eye(4))
        if is_keyframe:
            if self._last_kf is not None:          # the gap it closes: its frames get their next keyframe
                T_c_w = inv(T_w_c)
                for j in range(self._last_kf + 1, idx):
                    self._next[j], self._rel_next[j] = idx, T_c_w @ self.pose(j)
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
        """Overwrite frame ``idx``'s pose (e.g. after mapping refined it); a keyframe moves its dependants (the
        frames after it and, with ``interpolate``, its share of the gap before it); a non-keyframe gets exactly
        ``T_w_c``."""
        T_w_c = orthonormalise(T_w_c)
        if idx in self._kf:
            self._kf[idx] = T_w_c.copy()
        else:
            a, b = self._anchor[idx], self._next[idx]
            self._rel[idx] = T_w_c.copy() if a is None else inv(self._kf[a]) @ T_w_c
            if b is not None:
                self._rel_next[idx] = inv(self._kf[b]) @ T_w_c

    def apply_corrections(self, poses: dict[int, np.ndarray], min_shift_m: float = 0.0,
                          min_shift_deg: float = 0.0) -> dict[int, tuple[float, float]]:
        """Move keyframes to corrected poses (frame index -> ``T_w_kf``); their non-keyframes follow (rigidly,
        or blended with the next keyframe's correction: the module docstring).
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
        a, b = self._anchor[idx], self._next[idx]
        if a is None:
            return self._rel[idx].copy()
        A = self._kf[a] @ self._rel[idx]
        if b is None or not self.interpolate:
            return A
        B = self._kf[b] @ self._rel_next[idx]
        return orthonormalise(blend(A, B, (idx - a) / (b - a)))

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
        stack = lambda Ts: np.stack(Ts) if Ts else np.zeros((0, 4, 4))  # noqa: E731
        return {"kf": {k: v.copy() for k, v in self._kf.items()}, "anchor": list(self._anchor),
                "rel": stack(self._rel), "last_kf": self._last_kf, "next": list(self._next),
                "rel_next": stack(self._rel_next)}

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output (replaces every pose)."""
        self._kf = {int(k): np.asarray(v, dtype=np.float64) for k, v in state["kf"].items()}
        self._anchor = [None if a is None else int(a) for a in state["anchor"]]
        self._rel = [np.asarray(T, dtype=np.float64) for T in state["rel"]]
        self._last_kf = state["last_kf"]
        n = len(self._rel)                         # checkpoints from before the interpolation: no next keyframe
        self._next = [None if b is None else int(b) for b in state.get("next", [None] * n)]
        self._rel_next = [np.asarray(T, dtype=np.float64) for T in state.get("rel_next", np.tile(np.eye(4), (n, 1, 1)))]

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """``{keyframe index: T_w_kf}`` (copies), in index order."""
        return {k: v.copy() for k, v in sorted(self._kf.items())}
