"""Sensor noise for synthetic RGB-D frames: depth noise (constant or Kinect-like), dropout holes, colour noise.

All noise is drawn from ``numpy.random.default_rng([seed, frame_index])``, so a frame's noise does not depend
on which other frames were generated. Noise-free by default.
"""

from __future__ import annotations

import numpy as np
from pydantic import Field

from lrslam.config import StrictModel

__all__ = ["NoiseConfig", "NOISE_PRESETS", "noise_preset", "kinect_sigma", "apply_noise"]


class NoiseConfig(StrictModel):
    """Synthetic sensor noise (all off by default).

    Attributes:
        depth_sigma: constant Gaussian depth noise, metres (standard deviation).
        kinect: add depth-dependent Gaussian noise with ``sigma(z) = 0.0012 + 0.0019 (z - 0.4)^2`` metres
            (Nguyen, Izadi, Lovell, 3DIMPVT 2012, axial noise of the Kinect v1).
        holes: fraction of pixels dropped (depth 0) in smooth random blobs, in [0, 1).
        hole_size: blob size, pixels (standard deviation of the Gaussian smoothing of the random field).
        edge_dropout: probability of dropping a pixel next to a depth discontinuity (jump > 10 % of the depth).
        colour_sigma: Gaussian noise on the 8-bit colour values (standard deviation, grey levels).
        seed: noise seed.
    """

    depth_sigma: float = Field(0.0, ge=0.0)
    kinect: bool = False
    holes: float = Field(0.0, ge=0.0, lt=1.0)
    hole_size: float = Field(4.0, gt=0.0)
    edge_dropout: float = Field(0.0, ge=0.0, le=1.0)
    colour_sigma: float = Field(0.0, ge=0.0)
    seed: int = 0

    @property
    def enabled(self) -> bool:
        """True when any noise is switched on."""
        return bool(self.depth_sigma or self.kinect or self.holes or self.edge_dropout or self.colour_sigma)


NOISE_PRESETS = ("none", "gaussian", "kinect", "kinect+holes", "all")


def noise_preset(name: str, depth_sigma: float = 0.01, colour_sigma: float = 3.0, holes: float = 0.02,
                 seed: int = 0) -> NoiseConfig:
    """Named noise settings used by the CLI.

    ``none``: noise free; ``gaussian``: constant depth noise ``depth_sigma``; ``kinect``: Kinect-like
    depth-dependent noise; ``kinect+holes``: kinect plus ``holes`` blob dropout and 50 % dropout at depth
    edges; ``all``: kinect+holes plus colour noise ``colour_sigma``. Raises ValueError for other names.
    """
    if name not in NOISE_PRESETS:
        raise ValueError(f"unknown noise preset {name!r}; choose one of {', '.join(NOISE_PRESETS)}")
    cfg: dict = {"seed": seed}
    if name == "gaussian":
        cfg["depth_sigma"] = depth_sigma
    if name in ("kinect", "kinect+holes", "all"):
        cfg["kinect"] = True
    if name in ("kinect+holes", "all"):
        cfg.update(holes=holes, edge_dropout=0.5)
    if name == "all":
        cfg["colour_sigma"] = colour_sigma
    return NoiseConfig(**cfg)


def kinect_sigma(z: np.ndarray) -> np.ndarray:
    """Kinect v1 axial depth noise sigma (metres) at z-depth z (metres), Nguyen et al. 2012."""
    z = np.asarray(z, dtype=np.float64)
    return 0.0012 + 0.0019 * (z - 0.4) ** 2


def _depth_edges(depth: np.ndarray, rel_jump: float = 0.1) -> np.ndarray:
    edge = np.zeros(depth.shape, dtype=bool)
    for ax in (0, 1):
        a = np.moveaxis(depth, ax, 0)
        e = np.moveaxis(edge, ax, 0)  # view
        jump = np.abs(a[1:] - a[:-1]) > rel_jump * np.minimum(a[1:], a[:-1])
        e[1:] |= jump
        e[:-1] |= jump
    return edge


def apply_noise(rgb: np.ndarray, depth: np.ndarray, cfg: NoiseConfig,
                frame_index: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Return noisy copies of ``rgb`` (H, W, 3) uint8 and ``depth`` (H, W) float32 metres (0 = invalid).

    Depth noise is added only where depth > 0; results below 1 mm become 0 (invalid). Inputs are unchanged.
    """
    if not cfg.enabled:
        return rgb.copy(), depth.copy()
    rng = np.random.default_rng([int(cfg.seed), int(frame_index)])
    d = depth.astype(np.float64)
    valid = d > 0
    sigma = np.full(d.shape, cfg.depth_sigma)
    if cfg.kinect:
        sigma = np.sqrt(sigma**2 + kinect_sigma(d) ** 2)
    if np.any(sigma > 0):
        d = np.where(valid, d + rng.standard_normal(d.shape) * sigma, 0.0)
        d[d < 1e-3] = 0.0
    if cfg.holes > 0:
        from scipy.ndimage import gaussian_filter

        field = gaussian_filter(rng.standard_normal(d.shape), cfg.hole_size, mode="wrap")
        d[field > np.quantile(field, 1.0 - cfg.holes)] = 0.0
    if cfg.edge_dropout > 0:
        drop = _depth_edges(depth.astype(np.float64)) & (rng.uniform(size=d.shape) < cfg.edge_dropout)
        d[drop] = 0.0
    out_rgb = rgb.copy()
    if cfg.colour_sigma > 0:
        noisy = rgb.astype(np.float64) + rng.standard_normal(rgb.shape) * cfg.colour_sigma
        out_rgb = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    return out_rgb, d.astype(np.float32)
