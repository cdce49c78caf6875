"""One level of the CP encoding (paper Eq. cp / lr_geo): ``f(p) = sum_i f_x^(i)(x) * f_y^(i)(y) * f_z^(i)(z)``."""

from __future__ import annotations

import torch
from torch import nn

from lrslam.field.interp import sample_lines

__all__ = ["CPLevel"]


class CPLevel(nn.Module):
    """Rank-``k`` CP decomposition of a (nx, ny, nz, C) feature volume: three sets of k feature lines.

    Args:
        shape: nodes per axis ``(nx, ny, nz)``. rank: k. channels: C. init_std: N(0, std) initialisation.
    Parameters: ``x (nx, k, C)``, ``y (ny, k, C)``, ``z (nz, k, C)``; ``k C (nx + ny + nz)`` in total.
    Each line is interpolated linearly, the three are multiplied elementwise over C and summed over the rank.
    With k = 2 the point-wise evaluation is cheap, so nothing is materialised.
    """

    def __init__(self, shape: tuple[int, int, int], rank: int, channels: int, init_std: float) -> None:
        super().__init__()
        self.rank, self.channels = rank, channels
        self.x, self.y, self.z = (nn.Parameter(torch.randn(n, rank, channels) * init_std) for n in shape)

    def forward(self, x01: torch.Tensor) -> torch.Tensor:
        """Unit coordinates (N, 3) -> features (N, C)."""
        k, c = self.rank, self.channels
        fx, fy, fz = (sample_lines(line.view(line.shape[0], k * c), x01[:, a])
                      for a, line in enumerate((self.x, self.y, self.z)))
        return (fx * fy * fz).view(-1, k, c).sum(1)
