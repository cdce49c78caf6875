"""Where to evaluate the field along each ray (ESLAM ``Renderer.render_batch_ray``).

Rays with a measured depth d get ``n_stratified`` samples uniform in ``[0, 1.2 d]`` plus ``n_importance``
samples uniform in ``[d - 1.5 T, d + 1.5 T]`` (T: truncation), sorted and jittered within their intervals.
Rays without depth get ``n_stratified`` samples uniform up to where the ray leaves the scene bound and
``n_importance`` more drawn from the weights of a first, gradient-free pass (hierarchical sampling).

Sample depths carry no gradient; the sample *points* ``o + z d`` do (through the ray), see :mod:`.render`.
"""

from __future__ import annotations

from typing import Callable

import torch

__all__ = ["perturb", "depth_guided_depths", "uniform_depths", "sample_pdf", "hierarchical_depths"]


def perturb(z: torch.Tensor, generator: torch.Generator) -> torch.Tensor:
    """Stratified jitter: each sorted depth moves uniformly within its interval between neighbour midpoints."""
    mids = 0.5 * (z[..., 1:] + z[..., :-1])
    upper = torch.cat([mids, z[..., -1:]], -1)
    lower = torch.cat([z[..., :1], mids], -1)
    t = torch.rand(z.shape, generator=generator, device=generator.device).to(z.device)
    return lower + (upper - lower) * t


def depth_guided_depths(depth: torch.Tensor, n_stratified: int, n_importance: int, truncation: float,
                        jitter: bool, generator: torch.Generator) -> torch.Tensor:
    """Sample depths for rays with measured depth ``depth`` (R,) metres -> (R, n_stratified + n_importance),
    sorted: uniform over ``[0, 1.2 d]`` plus a band ``d +- 1.5 T`` around the surface."""
    dev = depth.device
    t_free = torch.linspace(0.0, 1.0, n_stratified, device=dev)
    t_surf = torch.linspace(0.0, 1.0, n_importance, device=dev)
    d = depth.unsqueeze(-1)
    z = torch.cat([1.2 * d * t_free, d - 1.5 * truncation + 3.0 * truncation * t_surf], dim=-1)
    z = torch.sort(z, dim=-1).values
    return perturb(z, generator) if jitter else z


def uniform_depths(far: torch.Tensor, n: int, jitter: bool, generator: torch.Generator) -> torch.Tensor:
    """``n`` depths uniform in ``[0, far]`` per ray (far (R,) metres) -> (R, n)."""
    z = far.unsqueeze(-1) * torch.linspace(0.0, 1.0, n, device=far.device)
    return perturb(z, generator) if jitter else z


def sample_pdf(bins: torch.Tensor, weights: torch.Tensor, n: int, generator: torch.Generator) -> torch.Tensor:
    """Inverse-CDF sampling of ``n`` depths per ray from piecewise-constant ``weights`` (R, B-1) on ``bins``
    (R, B) (NeRF hierarchical sampling; weights are normalised, unlike ESLAM's variant) -> (R, n)."""
    w = weights + 1e-5
    pdf = w / w.sum(-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, -1)], -1)
    u = torch.rand((len(bins), n), generator=generator, device=generator.device).to(bins.device).contiguous()
    idx = torch.searchsorted(cdf.contiguous(), u, right=True)
    below = (idx - 1).clamp(min=0)
    above = idx.clamp(max=cdf.shape[-1] - 1)
    cdf_b, cdf_a = cdf.gather(1, below), cdf.gather(1, above)
    bin_b, bin_a = bins.gather(1, below), bins.gather(1, above)
    denom = torch.where(cdf_a - cdf_b < 1e-5, torch.ones_like(cdf_a), cdf_a - cdf_b)
    return bin_b + (u - cdf_b) / denom * (bin_a - bin_b)


def hierarchical_depths(sdf_fn: Callable[[torch.Tensor], torch.Tensor],
                        weights_fn: Callable[[torch.Tensor], torch.Tensor], origins: torch.Tensor,
                        dirs: torch.Tensor, far: torch.Tensor, n_stratified: int, n_importance: int, jitter: bool,
                        generator: torch.Generator) -> torch.Tensor:
    """Depths for rays without measured depth: a gradient-free uniform pass up to ``far`` (R,), then
    ``n_importance`` extra depths from its compositing weights -> (R, n_stratified + n_importance), sorted.

    ``sdf_fn`` maps points (M, 3) to SDF (M,); ``weights_fn`` maps SDF (R, S) to compositing weights (R, S).
    """
    with torch.no_grad():
        z = uniform_depths(far.clamp(min=1e-3), n_stratified, jitter, generator)
        pts = origins.unsqueeze(1) + dirs.unsqueeze(1) * z.unsqueeze(-1)
        w = weights_fn(sdf_fn(pts.reshape(-1, 3)).reshape(z.shape))
        mids = 0.5 * (z[:, 1:] + z[:, :-1])
        extra = sample_pdf(mids, w[:, 1:-1], n_importance, generator)
        return torch.sort(torch.cat([z, extra], -1), -1).values
