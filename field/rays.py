"""Pixels -> camera rays in the world frame (torch), in the camera convention of :mod:`lrslam.camera`.

A pixel ``(u, v)`` (column, row) looks along ``d_c = ((u - cx) / fx, (v - cy) / fy, 1)`` in the OpenCV camera
frame; in the world ``d = R_w_c d_c`` and ``o = t_w_c``. Because ``d_c`` has unit z, the ray parameter of a
point ``o + z d`` is its camera depth ``z`` (metres), the quantity a depth image stores. Everything stays
differentiable in the pose so tracking gradients reach it (no ``.detach()`` anywhere).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

__all__ = ["PixelBatch", "sample_pixels", "gather_pixels", "camera_directions", "world_rays", "ray_exit_depth"]


@dataclass
class PixelBatch:
    """Sampled pixels of one or more frames.

    u, v: (N,) float pixel coordinates (column, row). frame: (N,) int64 index into the batch's poses.
    rgb: (N, 3) float in [0, 1]. depth: (N,) metres, 0 = invalid.
    """

    u: torch.Tensor
    v: torch.Tensor
    frame: torch.Tensor
    rgb: torch.Tensor
    depth: torch.Tensor

    def select(self, mask: torch.Tensor) -> "PixelBatch":
        return PixelBatch(self.u[mask], self.v[mask], self.frame[mask], self.rgb[mask], self.depth[mask])

    @staticmethod
    def cat(batches: list["PixelBatch"]) -> "PixelBatch":
        return PixelBatch(*(torch.cat([getattr(b, f) for b in batches]) for f in ("u", "v", "frame", "rgb", "depth")))


def sample_pixels(n: int, height: int, width: int, generator: torch.Generator, edge_h: int = 0, edge_w: int = 0,
                  device: torch.device | str = "cpu") -> tuple[torch.Tensor, torch.Tensor]:
    """``n`` pixels uniformly at random (with replacement, as ESLAM) from rows ``[edge_h, H - edge_h)`` and
    columns ``[edge_w, W - edge_w)`` -> (rows (n,), cols (n,)) int64. Edges larger than the image shrink to 0."""
    if 2 * edge_h >= height:
        edge_h = 0
    if 2 * edge_w >= width:
        edge_w = 0
    rows = torch.randint(edge_h, height - edge_h, (n,), generator=generator, device=generator.device)
    cols = torch.randint(edge_w, width - edge_w, (n,), generator=generator, device=generator.device)
    return rows.to(device), cols.to(device)


def gather_pixels(rgb_u8: torch.Tensor, depth: torch.Tensor, rows: torch.Tensor, cols: torch.Tensor,
                  frame_index: int) -> PixelBatch:
    """Read sampled pixels of one frame: ``rgb_u8`` (H, W, 3) uint8, ``depth`` (H, W) metres."""
    rgb = rgb_u8[rows, cols].float() / 255.0
    frame = torch.full_like(rows, frame_index)
    return PixelBatch(cols.float(), rows.float(), frame, rgb, depth[rows, cols])


def camera_directions(u: torch.Tensor, v: torch.Tensor, K: torch.Tensor) -> torch.Tensor:
    """Pixel coordinates (N,) -> camera-frame directions (N, 3) with unit z (OpenCV)."""
    return torch.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], torch.ones_like(u)], dim=-1)


def world_rays(dirs_c: torch.Tensor, T_w_c: torch.Tensor, frame: torch.Tensor | None = None
               ) -> tuple[torch.Tensor, torch.Tensor]:
    """Camera-frame directions (N, 3) and poses ``T_w_c`` (F, 4, 4) (``frame`` (N,) picks each ray's pose;
    None = pose 0) -> world origins (N, 3) and directions (N, 3) (differentiable in the poses)."""
    T = T_w_c[frame] if frame is not None else T_w_c[:1].expand(len(dirs_c), 4, 4)
    d = (T[:, :3, :3] @ dirs_c.unsqueeze(-1)).squeeze(-1)
    return T[:, :3, 3], d


def ray_exit_depth(origins: torch.Tensor, dirs: torch.Tensor, bound: torch.Tensor) -> torch.Tensor:
    """Depth ``z`` at which each ray leaves the axis-aligned ``bound`` (3, 2) (ESLAM's ``far_bb``) -> (N,),
    computed without gradient. Negative or tiny when the origin is outside the bound and the ray points away."""
    with torch.no_grad():
        d = torch.where(dirs.abs() < 1e-9, torch.full_like(dirs, 1e-9), dirs)
        t = (bound.unsqueeze(0) - origins.unsqueeze(-1)) / d.unsqueeze(-1)  # (N, 3, 2)
        return t.max(dim=2).values.min(dim=1).values
