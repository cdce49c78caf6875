"""Multi-resolution feature encodings of the scene: tri-plane (ESLAM), CP and Six-axis (LRSLAM).

Every encoding has the same interface: ``features(p)`` maps world points (N, 3) in metres to (N, 2C) features,
the coarse level's C channels followed by the fine level's (paper Eq. eslam_feature / lr_geo / clr). Grids are
sized from the grown bound exactly like ESLAM (:mod:`lrslam.field.grid`).
"""

from __future__ import annotations


import numpy as np
import torch
from torch import nn

from lrslam.field.config import EncodingConfig
from lrslam.field.enc_cp import CPLevel
from lrslam.field.enc_sixaxis import SixAxisLevel
from lrslam.field.enc_triplane import TriPlaneLevel
from lrslam.field.grid import grid_shape, unit_coordinates
from lrslam.field.interp import resolve_sampler

__all__ = ["EncodingConfig", "Encoding", "build_encoding"]




class Encoding(nn.Module):
    """Coarse + fine levels of one decomposition over a fixed (grown) bound.

    Args:
        bound: (3, 2) grown bound in metres (see :func:`lrslam.field.grid.grow_bound`).
        cfg: the encoding's config. device: where the parameters live.
    """

    def __init__(self, bound: np.ndarray, cfg: EncodingConfig, device: torch.device | str = "cpu") -> None:
        super().__init__()
        self.cfg = cfg
        self.register_buffer("bound", torch.tensor(np.asarray(bound), dtype=torch.float32))
        sampler = resolve_sampler(cfg.sampler, device)
        levels: list[nn.Module] = []
        for res in (cfg.coarse_res, cfg.fine_res):
            shape = grid_shape(bound, res)
            if cfg.kind == "triplane":
                levels.append(TriPlaneLevel(shape, cfg.channels, cfg.init_std, sampler))
            elif cfg.kind == "cp":
                levels.append(CPLevel(shape, cfg.rank, cfg.channels, cfg.init_std, sampler))
            else:
                levels.append(SixAxisLevel(shape, cfg.rank, cfg.channels, cfg.init_std, sampler, cfg.sa_evaluation))
        self.levels = nn.ModuleList(levels)
        self.shapes = [grid_shape(bound, r) for r in (cfg.coarse_res, cfg.fine_res)]
        self.to(device)

    @property
    def out_dim(self) -> int:
        """2C: coarse and fine features concatenated."""
        return 2 * self.cfg.channels

    def features(self, p: torch.Tensor) -> torch.Tensor:
        """World points (N, 3) metres -> features (N, 2C) ``[coarse; fine]``; outside the bound the border
        value is used (as ESLAM's ``padding_mode='border'``)."""
        x01 = unit_coordinates(p, self.bound)
        return torch.cat([level(x01) for level in self.levels], dim=-1)

    forward = features

    def parameter_count(self) -> int:
        """Number of scalar feature parameters (lines or planes) of both levels."""
        return sum(p.numel() for p in self.parameters())

    def set_caching(self, on: bool) -> None:
        """Let levels cache derived tensors (materialised Six-axis planes) while the parameters are frozen."""
        for level in self.levels:
            if isinstance(level, SixAxisLevel):
                level.set_caching(on)


def build_encoding(bound: np.ndarray, cfg: EncodingConfig, device: torch.device | str = "cpu") -> Encoding:
    """Factory: the encoding described by ``cfg`` over ``bound`` (already grown)."""
    return Encoding(bound, cfg, device)
