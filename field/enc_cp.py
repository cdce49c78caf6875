"""One level of the CP encoding (paper Eq. cp / lr_geo): ``f(p) = sum_i f_x^(i)(x) * f_y^(i)(y) * f_z^(i)(z)``.

CP cannot be materialised into planes like Six-axis: every sample costs O(k C). To keep that cheap on CPU the
evaluation is one autograd function that works through the samples in cache-sized chunks and recomputes the
interpolated lines in the backward pass instead of keeping (N, k C) intermediates (which made the k = 16
appearance of the ablation variants ~10x slower and 1.8 GB heavier at 80k samples). On CUDA it runs unchunked.
"""

from __future__ import annotations

import torch
from torch import nn

from lrslam.field.interp import cell_and_fraction

__all__ = ["CPLevel", "cp_features"]

_CPU_CHUNK_FLOATS = 2**18  # per-chunk (samples x k C) budget on CPU: temporaries of ~1 MB stay in cache


class _CPFeatures(torch.autograd.Function):
    """``out[n] = sum_k prod_a lerp(lines_a, i0[n, a], t[n, a])[k]`` with lines (n_a, k * C), k-major."""

    @staticmethod
    def forward(ctx, lx, ly, lz, i0: torch.Tensor, t: torch.Tensor, rank: int, chunk: int) -> torch.Tensor:
        lines = (lx, ly, lz)
        n, c = len(t), lx.shape[1] // rank
        out = t.new_empty(n, c)
        for s in range(0, n, chunk):
            f = [_lerp(L, i0[s:s + chunk, a], t[s:s + chunk, a:a + 1])[0] for a, L in enumerate(lines)]
            out[s:s + chunk] = (f[0] * f[1] * f[2]).view(-1, rank, c).sum(1)
        ctx.save_for_backward(lx, ly, lz, i0, t)
        ctx.rank, ctx.chunk = rank, chunk
        return out

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        lx, ly, lz, i0, t = ctx.saved_tensors
        lines = (lx, ly, lz)
        need_lines = ctx.needs_input_grad[:3]
        g_lines = [torch.zeros_like(L) if need else None for L, need in zip(lines, need_lines)]
        g_t = torch.zeros_like(t) if ctx.needs_input_grad[4] else None
        for s in range(0, len(t), ctx.chunk):
            e = s + ctx.chunk
            ta = [t[s:e, a:a + 1] for a in range(3)]
            f, diff = zip(*(_lerp(L, i0[s:e, a], ta[a]) for a, L in enumerate(lines)))
            gk = grad[s:e].repeat(1, ctx.rank)  # (n, k C): the output gradient for every rank component
            for a, (b, c) in enumerate(((1, 2), (0, 2), (0, 1))):
                ga = gk * f[b] * f[c]  # d out / d f_a
                if g_lines[a] is not None:
                    g_lines[a].index_add_(0, i0[s:e, a], ga * (1.0 - ta[a]))
                    g_lines[a].index_add_(0, i0[s:e, a] + 1, ga * ta[a])
                if g_t is not None:
                    g_t[s:e, a] = (ga * diff[a]).sum(-1)
        return g_lines[0], g_lines[1], g_lines[2], None, g_t, None, None


def _lerp(lines: torch.Tensor, i0: torch.Tensor, t: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Rows ``i0`` and ``i0 + 1`` of (n, D) lines at fractions t (m, 1) -> (interpolated (m, D), row difference)."""
    r0 = lines.index_select(0, i0)
    d = lines.index_select(0, i0 + 1) - r0
    return r0 + t * d, d


def cp_features(lx: torch.Tensor, ly: torch.Tensor, lz: torch.Tensor, x01: torch.Tensor, rank: int) -> torch.Tensor:
    """CP features of unit coordinates ``x01`` (N, 3) from lines ``l_a`` (n_a, k C) (k-major) -> (N, C).
    Differentiable in the lines and in ``x01``."""
    idx, frac = zip(*(cell_and_fraction(x01[:, a], L.shape[0]) for a, L in enumerate((lx, ly, lz))))
    chunk = max(256, _CPU_CHUNK_FLOATS // lx.shape[1]) if x01.device.type == "cpu" else max(1, len(x01))
    return _CPFeatures.apply(lx, ly, lz, torch.stack(idx, -1), torch.stack(frac, -1), rank, chunk)


class CPLevel(nn.Module):
    """Rank-``k`` CP decomposition of a (nx, ny, nz, C) feature volume: three sets of k feature lines.

    Args:
        shape: nodes per axis ``(nx, ny, nz)``. rank: k. channels: C. init_std: N(0, std) initialisation.
    Parameters: ``x (nx, k, C)``, ``y (ny, k, C)``, ``z (nz, k, C)``; ``k C (nx + ny + nz)`` in total.
    Each line is interpolated linearly, the three are multiplied elementwise over C and summed over the rank.
    """

    def __init__(self, shape: tuple[int, int, int], rank: int, channels: int, init_std: float) -> None:
        super().__init__()
        self.rank, self.channels = rank, channels
        self.x, self.y, self.z = (nn.Parameter(torch.randn(n, rank, channels) * init_std) for n in shape)

    def forward(self, x01: torch.Tensor) -> torch.Tensor:
        """Unit coordinates (N, 3) -> features (N, C)."""
        kc = self.rank * self.channels
        return cp_features(self.x.view(-1, kc), self.y.view(-1, kc), self.z.view(-1, kc), x01, self.rank)
