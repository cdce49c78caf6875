"""Scene bound and feature-grid geometry, exactly as ESLAM computes them (float32 arithmetic included).

ESLAM (``ESLAM.load_bound`` / ``init_planes``) grows the user bound so that every side is a multiple of the
coarse voxel (0.24 m) and sizes every feature grid ``int(side / resolution)`` in float32. Reproducing the
float32 rounding matters for the parameter counts: Replica room0's y side gives ``int(27.999998) = 27`` coarse
cells, which is how the paper's 1.40 M / 5.38 M (ESLAM) and 0.03 M / 0.83 M (LRSLAM) come out.

Grid nodes span the grown bound end to end (``align_corners=True`` in ``grid_sample`` terms): node ``i`` of an
axis with ``n`` nodes sits at ``lo + i * side / (n - 1)``, and points outside the bound take the border value.
"""

from __future__ import annotations

import numpy as np
import torch

from lrslam.errors import InputError

__all__ = ["COARSE_VOXEL", "check_bound", "grow_bound", "grid_shape", "unit_coordinates", "cell_and_fraction"]

COARSE_VOXEL = 0.24  # metres: ESLAM's ``planes_res.bound_dividable``


def check_bound(bound: np.ndarray) -> np.ndarray:
    """Validate a scene bound ``(3, 2)`` ``[[xmin, xmax], [ymin, ymax], [zmin, zmax]]`` in metres (world frame).

    Returns it as float64; raises :class:`InputError` naming the problem otherwise.
    """
    b = np.asarray(bound, dtype=np.float64)
    if b.shape != (3, 2) or not np.all(np.isfinite(b)):
        raise InputError(f"scene bound must be a finite (3, 2) array [[xmin, xmax], ...] in metres, got {b.shape}")
    if np.any(b[:, 1] <= b[:, 0]):
        raise InputError(f"scene bound needs max > min on every axis, got {b.tolist()}")
    return b


def grow_bound(bound: np.ndarray, multiple: float = COARSE_VOXEL) -> np.ndarray:
    """ESLAM's bound growth: ``max = (int((max - min) / multiple) + 1) * multiple + min`` per axis, in float32.

    Args:
        bound: (3, 2) metres.
        multiple: metres (the coarse voxel).
    Returns:
        (3, 2) float64 array holding the float32 values ESLAM would use (the min side is unchanged).
    """
    b = torch.from_numpy(check_bound(bound)).float()
    b[:, 1] = (((b[:, 1] - b[:, 0]) / multiple).int() + 1) * multiple + b[:, 0]
    return b.double().numpy()


def grid_shape(bound: np.ndarray, resolution: float) -> tuple[int, int, int]:
    """Number of grid nodes per axis ``int(side / resolution)`` (float32, as ESLAM), at least 2.

    Args:
        bound: (3, 2) grown bound in metres. resolution: metres per cell.
    """
    if not resolution > 0:
        raise InputError(f"grid resolution must be > 0 metres, got {resolution}")
    b = torch.from_numpy(np.asarray(bound, dtype=np.float64)).float()
    side = b[:, 1] - b[:, 0]
    n = [int(v) for v in (side / resolution).tolist()]
    return tuple(max(2, v) for v in n)  # type: ignore[return-value]


def unit_coordinates(p: torch.Tensor, bound: torch.Tensor) -> torch.Tensor:
    """World points ``p`` (N, 3) metres -> coordinates in ``[0, 1]`` per axis of ``bound`` (3, 2) (not clamped)."""
    lo = bound[:, 0]
    return (p - lo) / (bound[:, 1] - lo)


def cell_and_fraction(x01: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit coordinates ``x01`` (N,) on an axis with ``n`` nodes -> lower node index (N,) int64 in
    ``[0, n-2]`` and fraction (N,) in ``[0, 1]`` (differentiable in ``x01`` inside the bound).

    A NaN coordinate (a diverged pose) gets index 0 and a NaN fraction: the index stays inside the table (the
    CPU kernels do not bounds-check) and the NaN still reaches the output, where the optimisers detect it."""
    u = (x01 * (n - 1)).clamp(0.0, float(n - 1))
    i0 = torch.nan_to_num(u.detach(), nan=0.0).floor().clamp(max=n - 2).long()
    return i0, u - i0
