"""Linear interpolation on feature lines and bilinear interpolation on feature planes (torch).

Coordinates are unit coordinates in ``[0, 1]`` along each axis of the scene bound; a line or plane axis with
``n`` nodes puts node ``i`` at ``i / (n - 1)`` (``align_corners=True``) and clamps outside (``border``
padding), exactly like ESLAM's ``F.grid_sample(..., align_corners=True, padding_mode='border')``.

Layout: lines are ``(n, D)`` and planes ``(n_a, n_b, C)`` with the feature axis last, so a lookup gathers
contiguous rows. Two samplers with identical values:

- ``"gather"``: a weighted sum of the 2 (line) or 4 (plane) neighbouring rows, forward with one fused
  ``F.embedding_bag`` (interpolation weights as per-sample weights), backward hand-written: ``index_add_`` per
  corner for the features and, for the coordinates, two more fused ``embedding_bag`` calls with the weights'
  derivatives. No (N, corners, C) temporaries, unlike PyTorch's own sort-based ``embedding_bag`` backward.
- ``"ebag"``: ``F.embedding_bag`` with PyTorch's autograd (reference; planes only, lines always use gather).
- ``"grid_sample"``: ``F.grid_sample`` on the plane viewed as ``(1, C, n_a, n_b)``.
- ``"numba"``: the fused CPU kernels (:mod:`lrslam.field.cpu_ops`: all planes of a level summed in one pass,
  backward in one more); CPU float tensors only, anything else falls back to ``"gather"``. ``"auto"`` picks it
  on CPU when numba imports.

Gradients flow to the features and to the coordinates (through the interpolation weights), never through the
integer cell indices: pose gradients reach the field this way.
"""

from __future__ import annotations

from typing import Sequence

import torch
import torch.nn.functional as F

from lrslam.field.config import Sampler
from lrslam.field.cpu_ops import numba_available, planes_sum, use_numba
from lrslam.field.grid import cell_and_fraction

__all__ = ["Sampler", "resolve_sampler", "cell_and_fraction", "sample_lines", "sample_plane", "sample_plane_sum",
           "weighted_rows", "lerp_row_diff", "scatter_weighted_"]



def resolve_sampler(sampler: Sampler, device: torch.device | str) -> str:
    """``"auto"`` -> ``"numba"`` on CPU when numba imports (measured fastest there), else ``"gather"``."""
    if sampler != "auto":
        return sampler
    return "numba" if torch.device(device).type == "cpu" and numba_available() else "gather"


def weighted_rows(table: torch.Tensor, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """``out[n] = sum_j w[n, j] table[idx[n, j]]`` for idx, w (N, m) -> (N, D): one fused ``embedding_bag``."""
    return F.embedding_bag(idx, table, per_sample_weights=w, mode="sum")


def lerp_row_diff(table: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """``table[idx[:, 1]] - table[idx[:, 0]]`` (N, D): the derivative of a lerp along its fraction."""
    return weighted_rows(table, idx, _LERP_DT.to(table).expand(len(idx), 2).contiguous())


def scatter_weighted_(g_table: torch.Tensor, idx: torch.Tensor, values: torch.Tensor, w: torch.Tensor) -> None:
    """Adjoint of :func:`weighted_rows`: ``g_table[idx[n, j]] += w[n, j] values[n]`` in place, for idx, w (N, m)
    and values (N, D). One ``index_add_`` per corner, with a contiguous weight column (~3x faster to broadcast
    than a strided one)."""
    wt = w.t().contiguous()
    for j in range(idx.shape[1]):
        g_table.index_add_(0, idx[:, j], values * wt[j].unsqueeze(1))


class _GatherLerp(torch.autograd.Function):
    """Linear interpolation of table rows: ``out = (1 - t) table[i0] + t table[i0 + 1]``."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, i0: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        idx = torch.stack([i0, i0 + 1], dim=-1)
        w = torch.stack([1.0 - t, t], dim=-1)
        ctx.save_for_backward(table, idx, w)
        return weighted_rows(table, idx, w)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        table, idx, w = ctx.saved_tensors
        g_table = g_t = None
        if ctx.needs_input_grad[0]:
            g_table = torch.zeros_like(table)
            scatter_weighted_(g_table, idx, grad, w)
        if ctx.needs_input_grad[2]:
            g_t = (lerp_row_diff(table, idx) * grad).sum(-1)
        return g_table, None, g_t


class _GatherBilerp(torch.autograd.Function):
    """Bilinear interpolation of a row-major plane table (n_a * n_b, C) at cells ``base = a0 * n_b + b0``."""

    @staticmethod
    def forward(ctx, table: torch.Tensor, base: torch.Tensor, nb: int, ta: torch.Tensor, tb: torch.Tensor):
        idx = torch.stack([base, base + 1, base + nb, base + nb + 1], dim=-1)
        sa, sb = 1.0 - ta, 1.0 - tb
        w = torch.stack([sa * sb, sa * tb, ta * sb, ta * tb], dim=-1)
        ctx.save_for_backward(table, idx, ta, tb, w)
        return weighted_rows(table, idx, w)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        table, idx, ta, tb, w = ctx.saved_tensors
        g_table = g_ta = g_tb = None
        if ctx.needs_input_grad[0]:
            g_table = torch.zeros_like(table)
            scatter_weighted_(g_table, idx, grad, w)
        sa, sb = 1.0 - ta, 1.0 - tb
        if ctx.needs_input_grad[3]:  # d out / d ta = (1-tb)(P10 - P00) + tb (P11 - P01)
            d = weighted_rows(table, idx, torch.stack([-sb, -tb, sb, tb], -1))
            g_ta = (d * grad).sum(-1)
        if ctx.needs_input_grad[4]:  # d out / d tb = (1-ta)(P01 - P00) + ta (P11 - P10)
            d = weighted_rows(table, idx, torch.stack([-sa, sa, -ta, ta], -1))
            g_tb = (d * grad).sum(-1)
        return g_table, None, None, g_ta, g_tb


_LERP_DT = torch.tensor([-1.0, 1.0])


def sample_lines(lines: torch.Tensor, x01: torch.Tensor) -> torch.Tensor:
    """Linear interpolation of feature lines.

    Args:
        lines: (n, D) features at the n nodes of one axis (D = rank * channels, say).
        x01: (N,) unit coordinates along that axis.
    Returns:
        (N, D) interpolated features.
    """
    i0, t = cell_and_fraction(x01, lines.shape[0])
    return _GatherLerp.apply(lines, i0, t)


def sample_plane(plane: torch.Tensor, xa01: torch.Tensor, xb01: torch.Tensor, sampler: str = "gather") -> torch.Tensor:
    """Bilinear interpolation of a feature plane.

    Args:
        plane: (n_a, n_b, C) features on the a-b grid.
        xa01, xb01: (N,) unit coordinates along a and b.
        sampler: ``"gather"``, ``"ebag"``, ``"grid_sample"`` or ``"numba"`` (same values).
    Returns:
        (N, C) interpolated features.
    """
    na, nb, c = plane.shape
    if sampler == "numba":
        return sample_plane_sum([plane], [(xa01, xb01)], sampler)
    if sampler == "grid_sample":
        grid = torch.stack([xb01, xa01], dim=-1) * 2.0 - 1.0  # grid x indexes the last (b) axis
        out = F.grid_sample(plane.permute(2, 0, 1).unsqueeze(0), grid.view(1, -1, 1, 2), mode="bilinear",
                            padding_mode="border", align_corners=True)
        return out.view(c, -1).t()
    if sampler not in ("gather", "ebag"):
        raise ValueError(f"unknown sampler {sampler!r} (use 'gather', 'ebag' or 'grid_sample')")
    ia, ta = cell_and_fraction(xa01, na)
    ib, tb = cell_and_fraction(xb01, nb)
    table = plane.reshape(na * nb, c)
    if sampler == "ebag":  # reference: PyTorch's own embedding_bag autograd
        base = ia * nb + ib
        idx = torch.stack([base, base + 1, base + nb, base + nb + 1], dim=-1)
        w = torch.stack([(1 - ta) * (1 - tb), (1 - ta) * tb, ta * (1 - tb), ta * tb], dim=-1)
        return F.embedding_bag(idx, table, per_sample_weights=w, mode="sum")
    return _GatherBilerp.apply(table, ia * nb + ib, nb, ta, tb)


def sample_plane_sum(planes: Sequence[torch.Tensor], coords: Sequence[tuple[torch.Tensor, torch.Tensor]],
                     sampler: str = "gather") -> torch.Tensor:
    """``sum_p sample_plane(planes[p], *coords[p])``: the features of one tri-plane / Six-axis level.

    Args:
        planes: P planes (n_a, n_b, C) (channels equal, sizes may differ).
        coords: P pairs (xa01, xb01) of (N,) unit coordinates along each plane's two axes.
        sampler: as :func:`sample_plane`; ``"numba"`` evaluates all P planes in one fused kernel.
    Returns:
        (N, C) summed features, differentiable in the planes and the coordinates.
    """
    if not use_numba(sampler, *planes, *(x for pair in coords for x in pair)):
        sampler = "gather" if sampler == "numba" else sampler
        out = None
        for plane, (xa, xb) in zip(planes, coords):
            f = sample_plane(plane, xa, xb, sampler)
            out = f if out is None else out + f
        return out
    return planes_sum(planes, coords)
