"""Training losses of ESLAM/LRSLAM (paper Sec. 3.1 "Simultaneous Localization and Mapping"; ESLAM
``Tracker.sdf_losses`` / ``Mapper.sdf_losses``).

With measured depth D and truncation T, the samples z of a ray split into
- free space ``z < D - T``: the SDF should be 1 (truncation units): ``(s - 1)^2``;
- centre band ``|z - D| < 0.4 T`` and tail band (the rest of ``D - T <= z <= D + T``): the SDF should be the
  signed distance along the ray, ``(z + s T - D)^2`` in metres^2;
- behind ``z > D + T``: no constraint.
Each term is the mean over its samples; colour and depth are mean squared errors of the rendered values.
Total = w_fs fs + w_center center + w_tail tail + w_depth depth + w_colour colour.
"""

from __future__ import annotations

import torch

from lrslam.field.config import MAPPING_WEIGHTS, TRACKING_WEIGHTS, LossWeights
from lrslam.field.render import RenderResult

__all__ = ["LossWeights", "TRACKING_WEIGHTS", "MAPPING_WEIGHTS", "masked_mean", "sdf_losses", "rendering_loss"]






def masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean of ``x[mask]``; 0 (keeping the graph) when the mask is empty (ESLAM would give NaN)."""
    sel = x[mask]
    return sel.mean() if sel.numel() else x.sum() * 0.0


def sdf_losses(sdf: torch.Tensor, z: torch.Tensor, depth: torch.Tensor, truncation: float
               ) -> dict[str, torch.Tensor]:
    """Free-space, centre and tail SDF losses for rays with valid depth.

    Args:
        sdf: (R, S) truncation units. z: (R, S) sample depths (m). depth: (R,) measured depth (m), all > 0.
        truncation: T (m).
    Returns:
        {"free_space", "center", "tail"} scalar tensors.
    """
    d = depth.unsqueeze(-1)
    front = z < d - truncation
    back = z > d + truncation
    center = (z > d - 0.4 * truncation) & (z < d + 0.4 * truncation)
    tail = ~front & ~back & ~center
    signed = (z + sdf * truncation - d) ** 2
    return {"free_space": masked_mean((sdf - 1.0) ** 2, front), "center": masked_mean(signed, center),
            "tail": masked_mean(signed, tail)}


def rendering_loss(r: RenderResult, depth: torch.Tensor, rgb: torch.Tensor, truncation: float, w: LossWeights,
                   geometry_mask: torch.Tensor, colour_mask: torch.Tensor
                   ) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """Weighted ESLAM loss of rendered rays.

    Args:
        r: rendered rays (R rays). depth: (R,) measured depth (m). rgb: (R, 3) measured colour in [0, 1].
        truncation: T (m). w: loss weights.
        geometry_mask: (R,) bool, rays used by the SDF and depth terms (need depth > 0).
        colour_mask: (R,) bool, rays used by the colour term.
    Returns:
        (total loss scalar tensor, {term: detached scalar tensor}).
    """
    terms = sdf_losses(r.sdf[geometry_mask], r.z[geometry_mask], depth[geometry_mask], truncation)
    terms["depth"] = masked_mean((r.depth - depth) ** 2, geometry_mask)
    terms["colour"] = masked_mean(((r.rgb - rgb) ** 2).mean(-1), colour_mask)
    total = (w.free_space * terms["free_space"] + w.center * terms["center"] + w.tail * terms["tail"]
             + w.depth * terms["depth"] + w.colour * terms["colour"])
    return total, {k: v.detach() for k, v in terms.items()}
