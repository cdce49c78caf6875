"""Keyframe database of the mapper and ESLAM's overlap-based window selection (``keyframe_selection_overlap``).

A keyframe keeps its colour and depth as tensors (all pixels, or a random subset to save memory). It keeps
no pose: the pipeline's trajectory owns every keyframe pose and hands the mapper the ones it needs.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from lrslam.field.rays import PixelBatch

__all__ = ["ViewPixels", "KeyframeStore", "select_overlapping"]


@dataclass
class ViewPixels:
    """Pixels of one view available to the mapper.

    frame_id: the caller's frame index. width: image width (to decode indices).
    index: (P,) int64 flat pixel indices ``row * W + col``, or None when all H*W pixels are kept in order.
    rgb: (P, 3) uint8. depth: (P,) float32 metres (0 = invalid).
    """

    frame_id: int
    width: int
    index: torch.Tensor | None
    rgb: torch.Tensor
    depth: torch.Tensor

    @classmethod
    def from_images(cls, frame_id: int, rgb: torch.Tensor, depth: torch.Tensor, n_pixels: int | None = None, generator: torch.Generator | None = None) -> "ViewPixels":
        """From (H, W, 3) uint8 and (H, W) depth tensors; ``n_pixels`` keeps a random subset (without repeats)."""
        h, w = depth.shape
        rgb_f, depth_f = rgb.reshape(-1, 3), depth.reshape(-1)
        index = None
        if n_pixels is not None and n_pixels < h * w:
            index = torch.randperm(h * w, generator=generator)[:n_pixels].to(depth.device)
            rgb_f, depth_f = rgb_f[index], depth_f[index]
        return cls(frame_id, w, index, rgb_f.clone(), depth_f.clone())

    def sample(self, n: int, view_slot: int, generator: torch.Generator) -> PixelBatch:
        """``n`` random pixels (with replacement, as ESLAM) tagged with ``view_slot`` as their frame index."""
        j = torch.randint(0, len(self.depth), (n,), generator=generator).to(self.depth.device)
        flat = self.index[j] if self.index is not None else j
        rows, cols = flat // self.width, flat % self.width
        return PixelBatch(cols.float(), rows.float(), torch.full_like(j, view_slot), self.rgb[j].float() / 255.0,
                          self.depth[j])


class KeyframeStore:
    """Keyframes by frame id, in insertion order."""

    def __init__(self) -> None:
        self._frames: dict[int, ViewPixels] = {}

    def __len__(self) -> int:
        return len(self._frames)

    def __contains__(self, frame_id: int) -> bool:
        return frame_id in self._frames

    def add(self, view: ViewPixels) -> None:
        self._frames[view.frame_id] = view

    def get(self, frame_id: int) -> ViewPixels:
        return self._frames[frame_id]

    def ids(self) -> list[int]:
        return list(self._frames)

    def state(self) -> dict:
        """Serialisable content (numpy arrays)."""
        return {k: {"width": v.width, "rgb": v.rgb.cpu().numpy(), "depth": v.depth.cpu().numpy(),
                    "index": None if v.index is None else v.index.cpu().numpy()} for k, v in self._frames.items()}

    @classmethod
    def from_state(cls, state: dict, device: torch.device) -> "KeyframeStore":
        store = cls()
        for k, s in state.items():
            idx = None if s["index"] is None else torch.as_tensor(s["index"], device=device)
            store.add(ViewPixels(int(k), int(s["width"]), idx,
                                 torch.as_tensor(s["rgb"], device=device), torch.as_tensor(s["depth"], device=device)))
        return store


def select_overlapping(poses: dict[int, np.ndarray], depth: np.ndarray, T_w_c: np.ndarray, K: np.ndarray,
                       n_select: int, rng: np.random.Generator, n_pixels: int = 50, n_samples: int = 8,
                       edge: int = 20) -> list[int]:
    """ESLAM's overlap window selection.

    Samples ``n_pixels`` pixels with valid depth d in the current frame, ``n_samples`` points per pixel from
    ``0.8 d`` to ``d + 0.5`` m, and keeps the keyframes (``poses``: id -> T_w_c) into whose image (minus an
    ``edge``-pixel border, in front of the camera) at least one point projects; returns at most ``n_select``
    of them, chosen at random, sorted by id.

    Args:
        depth: (H, W) current depth (metres). T_w_c: current pose (4, 4). K: (3, 3) intrinsics.
    """
    if not poses or n_select <= 0:
        return []
    h, w = depth.shape
    rows = rng.integers(0, h, n_pixels)
    cols = rng.integers(0, w, n_pixels)
    d = depth[rows, cols]
    ok = d > 0
    if not ok.any():
        return []
    rows, cols, d = rows[ok], cols[ok], d[ok]
    t = np.linspace(0.0, 1.0, n_samples)
    z = (0.8 * d)[:, None] * (1 - t) + (d + 0.5)[:, None] * t  # (P, S)
    dirs = np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones_like(d)], -1)
    pts_c = (dirs[:, None, :] * z[..., None]).reshape(-1, 3)
    pts_w = pts_c @ T_w_c[:3, :3].T + T_w_c[:3, 3]
    ids = list(poses)
    Ts = np.stack([poses[i] for i in ids])
    R_cw = np.swapaxes(Ts[:, :3, :3], 1, 2)
    t_cw = -np.einsum("kij,kj->ki", R_cw, Ts[:, :3, 3])
    pc = np.einsum("kij,nj->kni", R_cw, pts_w) + t_cw[:, None, :]  # (Kf, N, 3)
    zc = pc[..., 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        u = K[0, 0] * pc[..., 0] / zc + K[0, 2]
        v = K[1, 1] * pc[..., 1] / zc + K[1, 2]
    inside = (zc > 0) & (u > edge) & (u < w - edge) & (v > edge) & (v < h - edge)
    overlapping = [ids[i] for i in np.flatnonzero(inside.any(axis=1))]
    if len(overlapping) > n_select:
        overlapping = list(rng.choice(overlapping, size=n_select, replace=False))
    return sorted(int(i) for i in overlapping)
