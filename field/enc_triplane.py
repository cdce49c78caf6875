"""One level of ESLAM's tri-plane encoding (paper Eq. triplane / eslam_feature): ``f = F_xy + F_xz + F_yz``."""

from __future__ import annotations

import torch
from torch import nn

from lrslam.field.interp import sample_plane_sum

__all__ = ["TriPlaneLevel"]


class TriPlaneLevel(nn.Module):
    """Three axis-aligned feature planes of one resolution, summed after bilinear sampling.

    Args:
        shape: nodes per axis ``(nx, ny, nz)``. channels: C. init_std: std of the N(0, std) initialisation.
        sampler: ``"numba"``, ``"gather"``, ``"ebag"`` or ``"grid_sample"`` (see :mod:`lrslam.field.interp`).
    Parameters: ``xy (nx, ny, C)``, ``xz (nx, nz, C)``, ``yz (ny, nz, C)`` (ESLAM stores the same planes as
    ``(1, C, n_b, n_a)``; the count ``C (nx ny + nx nz + ny nz)`` is identical).
    """

    def __init__(self, shape: tuple[int, int, int], channels: int, init_std: float, sampler: str) -> None:
        super().__init__()
        nx, ny, nz = shape
        self.sampler = sampler
        self.xy = nn.Parameter(torch.randn(nx, ny, channels) * init_std)
        self.xz = nn.Parameter(torch.randn(nx, nz, channels) * init_std)
        self.yz = nn.Parameter(torch.randn(ny, nz, channels) * init_std)

    def forward(self, x01: torch.Tensor) -> torch.Tensor:
        """Unit coordinates (N, 3) -> features (N, C)."""
        x, y, z = x01.unbind(-1)
        return sample_plane_sum((self.xy, self.xz, self.yz), ((x, y), (x, z), (y, z)), self.sampler)
