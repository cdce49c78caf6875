"""Linear interpolation on feature lines and bilinear interpolation on feature planes (torch).

Coordinates are unit coordinates in ``[0, 1]`` along each axis of the scene bound; a line or plane axis with
``n`` nodes puts node ``i`` at ``i / (n - 1)`` (``align_corners=True``) and clamps outside (``border``
padding), exactly like ESLAM's ``F.grid_sample(..., align_corners=True, padding_mode='border')``.

Layout: lines are ``(n, D)`` and planes ``(n_a, n_b, C)`` with the feature axis last, so a lookup gathers
contiguous rows. Two samplers with identical values:

- ``"gather"``: ``F.embedding_bag`` over the 2 (line) or 4 (plane) neighbouring rows with the interpolation
  weights as per-sample weights — one fused kernel forward and backward; fastest on CPU in our measurements
  (benchmarks/field_speed.py).
- ``"grid_sample"``: ``F.grid_sample`` on the plane viewed as ``(1, C, n_a, n_b)``.

Gradients flow to the features and to the coordinates (through the interpolation weights), never through the
integer cell indices: pose gradients reach the field this way.
"""

from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F

__all__ = ["Sampler", "resolve_sampler", "cell_and_fraction", "sample_lines", "sample_plane"]

Sampler = Literal["auto", "gather", "grid_sample"]


def resolve_sampler(sampler: Sampler, device: torch.device | str) -> str:
    """``"auto"`` -> ``"gather"`` (measured fastest on CPU; also used on CUDA unless set explicitly)."""
    return "gather" if sampler == "auto" else sampler


def cell_and_fraction(x01: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit coordinates ``x01`` (N,) on an axis with ``n`` nodes -> lower node index (N,) int64 in
    ``[0, n-2]`` and fraction (N,) in ``[0, 1]`` (differentiable in ``x01`` inside the bound)."""
    u = (x01 * (n - 1)).clamp(0.0, float(n - 1))
    i0 = u.detach().floor().clamp(max=n - 2).long()
    return i0, u - i0


def sample_lines(lines: torch.Tensor, x01: torch.Tensor) -> torch.Tensor:
    """Linear interpolation of feature lines.

    Args:
        lines: (n, D) features at the n nodes of one axis (D = rank * channels, say).
        x01: (N,) unit coordinates along that axis.
    Returns:
        (N, D) interpolated features.
    """
    n = lines.shape[0]
    i0, t = cell_and_fraction(x01, n)
    idx = torch.stack([i0, i0 + 1], dim=-1)
    w = torch.stack([1.0 - t, t], dim=-1)
    return F.embedding_bag(idx, lines, per_sample_weights=w, mode="sum")


def sample_plane(plane: torch.Tensor, xa01: torch.Tensor, xb01: torch.Tensor, sampler: str = "gather") -> torch.Tensor:
    """Bilinear interpolation of a feature plane.

    Args:
        plane: (n_a, n_b, C) features on the a-b grid.
        xa01, xb01: (N,) unit coordinates along a and b.
        sampler: ``"gather"`` or ``"grid_sample"`` (same values).
    Returns:
        (N, C) interpolated features.
    """
    na, nb, c = plane.shape
    if sampler == "grid_sample":
        grid = torch.stack([xb01, xa01], dim=-1) * 2.0 - 1.0  # grid x indexes the last (b) axis
        out = F.grid_sample(plane.permute(2, 0, 1).unsqueeze(0), grid.view(1, -1, 1, 2), mode="bilinear",
                            padding_mode="border", align_corners=True)
        return out.view(c, -1).t()
    if sampler != "gather":
        raise ValueError(f"unknown sampler {sampler!r} (use 'gather' or 'grid_sample')")
    ia, ta = cell_and_fraction(xa01, na)
    ib, tb = cell_and_fraction(xb01, nb)
    base = ia * nb + ib
    idx = torch.stack([base, base + 1, base + nb, base + nb + 1], dim=-1)
    sa, sb = 1.0 - ta, 1.0 - tb
    w = torch.stack([sa * sb, sa * tb, ta * sb, ta * tb], dim=-1)
    return F.embedding_bag(idx, plane.reshape(na * nb, c), per_sample_weights=w, mode="sum")
