"""One level of the Six-axis encoding (paper Eq. sixaxis / clr):
``f(p) = sum_i f_{x_y}^(i)(x) f_{y_x}^(i)(y) + sum_i f_{y_z}^(i)(y) f_{z_y}^(i)(z)
       + sum_i f_{z_x}^(i)(z) f_{x_z}^(i)(x)``.

Speed (DESIGN.md): evaluating the k lines point by point costs O(k C) per sample and is ~40x slower on CPU than
materialising each rank-k plane ``P_ab = sum_i f_{a_b}^(i) (outer) f_{b_a}^(i)`` (O(n^2 C), independent of the
number of samples) and sampling it bilinearly. Bilinear interpolation of a sum of outer products equals the sum
of products of the linearly interpolated lines, so both modes give the same values (test: 1e-5). Only the lines
are parameters; the planes are transients rebuilt every forward pass (differentiable), or cached while the
model is frozen (tracking, meshing). On CPU with the numba kernels a forward pass materialises only the cells
its samples touch (:func:`lrslam.field.cpu_ops.sixaxis_sum`; same values).
"""

from __future__ import annotations


import torch
from torch import nn

from lrslam.field.config import SAEvaluation
from lrslam.field.cpu_ops import outer_sum, sixaxis_sum, use_numba
from lrslam.field.interp import sample_lines, sample_plane_sum

__all__ = ["SixAxisLevel", "SAEvaluation"]


# (first axis, second axis) of the three planes, and the parameter names of their two line sets.
_PLANES = ((0, 1, "x_y", "y_x"), (1, 2, "y_z", "z_y"), (2, 0, "z_x", "x_z"))


def _outer_sum(la: torch.Tensor, lb: torch.Tensor, sampler: str = "gather") -> torch.Tensor:
    """``P[a, b, c] = sum_k la[a, k, c] * lb[b, k, c]`` -> (n_a, n_b, C), row-major so that bilinear lookups
    gather contiguous C-vectors: the numba kernel when ``sampler == "numba"`` allows it, else one batched matmul
    over channels."""
    if use_numba(sampler, la, lb):
        return outer_sum(la, lb)
    P = torch.bmm(la.permute(2, 0, 1), lb.permute(2, 1, 0))  # (C, n_a, n_b)
    return P.permute(1, 2, 0).contiguous()


class SixAxisLevel(nn.Module):
    """Rank-``k`` Six-axis decomposition of one resolution level.

    Args:
        shape: nodes per axis ``(nx, ny, nz)``. rank: k. channels: C. init_std: N(0, std) initialisation.
        sampler: plane sampler (see :mod:`lrslam.field.interp`). evaluation: ``"materialise"`` (default, fast)
            or ``"direct"`` (point by point, reference for tests and benchmarks).
    Parameters: six line sets ``x_y (nx, k, C)``, ``y_x (ny, k, C)``, ``y_z (ny, k, C)``, ``z_y (nz, k, C)``,
    ``z_x (nz, k, C)``, ``x_z (nx, k, C)``: ``2 k C (nx + ny + nz)`` in total.
    """

    def __init__(self, shape: tuple[int, int, int], rank: int, channels: int, init_std: float, sampler: str,
                 evaluation: SAEvaluation = "materialise") -> None:
        super().__init__()
        self.rank, self.channels, self.sampler, self.evaluation = rank, channels, sampler, evaluation
        for a, b, name_ab, name_ba in _PLANES:
            setattr(self, name_ab, nn.Parameter(torch.randn(shape[a], rank, channels) * init_std))
            setattr(self, name_ba, nn.Parameter(torch.randn(shape[b], rank, channels) * init_std))
        self._cache: list[torch.Tensor] | None = None
        self.caching = False

    def planes(self) -> list[torch.Tensor]:
        """The three materialised planes ``P_xy (nx, ny, C)``, ``P_yz (ny, nz, C)``, ``P_zx (nz, nx, C)``
        (``einsum('akc,bkc->abc')``, contiguous)."""
        if self.caching and self._cache is not None:
            return self._cache
        out = [_outer_sum(getattr(self, n_ab), getattr(self, n_ba), self.sampler) for _, _, n_ab, n_ba in _PLANES]
        if self.caching:
            self._cache = out
        return out

    def set_caching(self, on: bool) -> None:
        """Cache the materialised planes (only valid while the lines do not change); off clears the cache."""
        self.caching = on
        self._cache = None

    def forward(self, x01: torch.Tensor) -> torch.Tensor:
        """Unit coordinates (N, 3) -> features (N, C)."""
        if self.evaluation == "direct":
            return self._direct(x01)
        coords = [(x01[:, a], x01[:, b]) for a, b, _, _ in _PLANES]
        pairs = [(getattr(self, n_ab), getattr(self, n_ba)) for _, _, n_ab, n_ba in _PLANES]
        if not self.caching and use_numba(self.sampler, x01, *(L for pair in pairs for L in pair)):
            return sixaxis_sum(pairs, coords)  # fused: only the touched cells are materialised
        return sample_plane_sum(self.planes(), coords, self.sampler)

    def _direct(self, x01: torch.Tensor) -> torch.Tensor:
        k, c = self.rank, self.channels
        out = None
        for a, b, n_ab, n_ba in _PLANES:
            la, lb = getattr(self, n_ab), getattr(self, n_ba)
            fa = sample_lines(la.view(la.shape[0], k * c), x01[:, a])
            fb = sample_lines(lb.view(lb.shape[0], k * c), x01[:, b])
            f = (fa * fb).view(-1, k, c).sum(1)
            out = f if out is None else out + f
        return out
