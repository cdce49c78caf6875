"""The scene model: a geometry encoding + SDF decoder and an appearance encoding + colour decoder, plus the
learnable sharpness beta of the SDF-to-density mapping (paper Sec. 3; ESLAM ``Decoders``).

Presets name the paper's variants: ``lrslam`` = ``cp-sa`` (CP geometry, Six-axis appearance; the default),
the ablation ``cp-cp`` [A], ``sa-sa`` [B], ``sa-cp`` [C], and ``eslam`` = ``triplane`` (tri-plane both).
Ranks follow the paper's role split whatever the decomposition: k_g = 2 for geometry, k_a = 16 for
appearance (the paper gives no other ranks for its ablation).
"""

from __future__ import annotations

from contextlib import contextmanager
from typing import Iterator

import numpy as np
import torch
from torch import nn

from lrslam.field.config import _ALIASES, _KINDS, PRESETS, SceneModelConfig  # noqa: F401 (re-export)
from lrslam.field.decoders import ColourDecoder, SDFDecoder
from lrslam.field.encodings import build_encoding
from lrslam.field.grid import grow_bound

__all__ = ["SceneModelConfig", "SceneModel", "PRESETS"]





class SceneModel(nn.Module):
    """TSDF + colour field over a (grown) scene bound.

    Args:
        bound: (3, 2) metres, world frame; grown to multiples of 0.24 m like ESLAM (``self.bound_np``).
        cfg: the model config. device: torch device of the parameters. seed: when given, the initial features and
            decoder weights come from this seed without touching torch's global RNG state.

    Units: points are world metres; ``sdf`` is the truncated SDF in truncation units (tanh output, 1 = T metres
    in front of the surface); colours are RGB in [0, 1].
    """

    def __init__(self, bound: np.ndarray, cfg: SceneModelConfig = SceneModelConfig(),
                 device: torch.device | str = "cpu", seed: int | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        self.bound_np = grow_bound(bound)
        self.register_buffer("bound", torch.tensor(self.bound_np, dtype=torch.float32))
        with torch.random.fork_rng(devices=[], enabled=seed is not None):
            if seed is not None:
                torch.manual_seed(seed)
            self.geometry = build_encoding(self.bound_np, cfg.geometry, device)
            self.appearance = build_encoding(self.bound_np, cfg.appearance, device)
            self.sdf_decoder = SDFDecoder(self.geometry.out_dim, cfg.hidden)
            self.colour_decoder = ColourDecoder(self.appearance.out_dim, cfg.hidden)
        beta = torch.tensor(float(cfg.beta_init))
        if cfg.learnable_beta:
            self.beta = nn.Parameter(beta)
        else:
            self.register_buffer("beta", beta)
        self.to(device)

    @property
    def truncation(self) -> float:
        """TSDF truncation T in metres."""
        return self.cfg.truncation

    @property
    def device(self) -> torch.device:
        return self.bound.device

    def sdf(self, p: torch.Tensor) -> torch.Tensor:
        """World points (N, 3) metres -> truncated SDF (N,) in truncation units (Eq. lr_geo + MLP_g)."""
        return self.sdf_decoder(self.geometry.features(p))

    def colour(self, p: torch.Tensor) -> torch.Tensor:
        """World points (N, 3) metres -> RGB (N, 3) in [0, 1] (Eq. clr + MLP_a)."""
        return self.colour_decoder(self.appearance.features(p))

    def parameter_count(self) -> dict[str, int]:
        """Scalar parameter counts. ``geometry`` / ``appearance``: the encodings f_g / f_a; ``encodings`` = f_g +
        f_a (what grows with the scene: O(L) or O(L^2)); ``decoders``: both MLPs and, when learnable, beta (a few
        thousand, independent of the bound); ``total`` = f_g + f_a + decoders, the paper's Table 1 "Total" (it
        exceeds the rounded f_g + f_a by the decoders: ScanNet LRSLAM 0.046 + 1.327 M reads 1.38 M only with them).
        """
        g, a = self.geometry.parameter_count(), self.appearance.parameter_count()
        dec = sum(p.numel() for m in (self.sdf_decoder, self.colour_decoder) for p in m.parameters())
        dec += 1 if self.cfg.learnable_beta else 0
        return {"geometry": g, "appearance": a, "encodings": g + a, "decoders": dec, "total": g + a + dec}

    def encoding_parameters(self) -> list[nn.Parameter]:
        """Feature lines/planes of both encodings (ESLAM lr 0.005)."""
        return list(self.geometry.parameters()) + list(self.appearance.parameters())

    def decoder_parameters(self) -> list[nn.Parameter]:
        """Both MLPs and, when learnable, beta (ESLAM lr 0.001)."""
        params = list(self.sdf_decoder.parameters()) + list(self.colour_decoder.parameters())
        if self.cfg.learnable_beta:
            params.append(self.beta)
        return params

    @contextmanager
    def frozen(self) -> Iterator["SceneModel"]:
        """Freeze the field for the duration (tracking, meshing): no parameter gradients, and derived tensors
        (materialised Six-axis planes) are computed once and cached. Restores the previous state on exit."""
        flags = [(p, p.requires_grad) for p in self.parameters()]
        for p, _ in flags:
            p.requires_grad_(False)
        self.geometry.set_caching(True)
        self.appearance.set_caching(True)
        try:
            yield self
        finally:
            self.geometry.set_caching(False)
            self.appearance.set_caching(False)
            for p, flag in flags:
                p.requires_grad_(flag)
