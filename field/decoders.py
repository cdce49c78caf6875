"""The two small MLP decoders of ESLAM/LRSLAM (paper Eq. eslam_decoder; ESLAM ``networks/decoders.py``).

``2C -> hidden -> hidden -> out`` with ReLU between layers ("two-layer MLPs with 64 input channels and 16
hidden channels"). The SDF head ends in ``tanh`` (SDF in truncation units, in (-1, 1)), the colour head in a
sigmoid (RGB in [0, 1]). PyTorch's default ``nn.Linear`` initialisation, as ESLAM.
"""

from __future__ import annotations

import torch
from torch import nn

__all__ = ["MLPDecoder", "SDFDecoder", "ColourDecoder"]


class MLPDecoder(nn.Module):
    """``in_dim -> hidden -> hidden -> out_dim`` MLP with ReLU hidden activations and no output activation."""

    def __init__(self, in_dim: int, hidden: int, out_dim: int) -> None:
        super().__init__()
        self.net = nn.Sequential(nn.Linear(in_dim, hidden), nn.ReLU(), nn.Linear(hidden, hidden), nn.ReLU(),
                                 nn.Linear(hidden, out_dim))

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        return self.net(f)


class SDFDecoder(MLPDecoder):
    """Geometry features (N, 2C) -> truncated SDF (N,) in truncation units, ``tanh`` output."""

    def __init__(self, in_dim: int, hidden: int) -> None:
        super().__init__(in_dim, hidden, 1)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        return torch.tanh(self.net(f)).squeeze(-1)


class ColourDecoder(MLPDecoder):
    """Appearance features (N, 2C) -> RGB (N, 3) in [0, 1], sigmoid output."""

    def __init__(self, in_dim: int, hidden: int) -> None:
        super().__init__(in_dim, hidden, 3)

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        return torch.sigmoid(self.net(f))
