"""Torch autograd functions around the fused numba CPU kernels (:mod:`lrslam.field.cpu_kernels`).

The samplers (:mod:`lrslam.field.interp`) and encodings use these when their sampler is ``"numba"`` (the CPU
default when numba imports) and the tensors allow it (CPU, float32/float64); otherwise they use the torch
implementations, which stay the reference (tests compare values and gradients). numba is imported lazily, on
first use, so importing the field does not compile anything.

- :func:`planes_sum`: sum of P bilinear plane lookups (a tri-plane level, or cached Six-axis planes).
- :func:`cp_product`: one CP level, ``sum_k prod_a lerp(line_a)``.
- :func:`outer_sum`: materialise a Six-axis plane from its two line sets.
- :func:`sixaxis_sum`: a whole Six-axis level in one function: mark the cells the samples touch, materialise
  only those, look them up; backward scatters into the touched cells and contracts them with the lines. The
  dense plane gradient never leaves the function, so its untouched cells need no zeroing.

All functions take plane/line parameters as torch tensors and return torch tensors; gradients reach the
parameters and the fractional coordinates (hence the poses), never the integer cells.
"""

from __future__ import annotations

import functools
import logging
import os
import threading
from typing import Sequence

import numpy as np
import torch

from lrslam.field.grid import cell_and_fraction

__all__ = ["numba_available", "use_numba", "numba_threads", "planes_sum", "cp_product", "outer_sum",
           "sixaxis_sum", "warm_up"]

_log = logging.getLogger(__name__)


@functools.cache
def numba_available() -> bool:
    """Whether the numba kernels import (they compile on first use and are cached on disk).
    ``LRSLAM_NO_NUMBA=1`` turns them off (the torch kernels are used)."""
    if os.environ.get("LRSLAM_NO_NUMBA", "") not in ("", "0"):
        return False
    try:
        import numba

        if "NUMBA_THREADING_LAYER" not in os.environ and "NUMBA_THREADING_LAYER_PRIORITY" not in os.environ:
            # OpenMP first (as torch): the TBB that some wheels bundle is too old for numba and only warns
            numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
        import lrslam.field.cpu_kernels  # noqa: F401
    except Exception as exc:  # noqa: BLE001 - any import problem means: use the torch kernels
        _log.warning("numba kernels unavailable (%s); using the torch samplers", exc)
        return False
    return True


def use_numba(sampler: str, *tensors: torch.Tensor) -> bool:
    """Whether a ``"numba"`` sampler can run on these tensors (CPU, float32/float64, numba importable)."""
    return (sampler == "numba" and numba_available()
            and all(t.device.type == "cpu" and t.dtype in (torch.float32, torch.float64) for t in tensors))


def numba_threads() -> int:
    """Give numba torch's CPU thread count (capped by numba's pool) and return it."""
    import numba

    n = max(1, min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    numba.set_num_threads(n)
    return n


def _np(t: torch.Tensor) -> np.ndarray:
    """A contiguous numpy view (or copy) of a CPU tensor, outside autograd."""
    return t.detach().contiguous().numpy()


def _kernels():
    from lrslam.field import cpu_kernels

    return cpu_kernels


def _plane_cells(shapes: Sequence[tuple[int, int]], coords: Sequence[tuple[torch.Tensor, torch.Tensor]],
                 dtype: torch.dtype):
    """Cells of P planes: lower-left rows ``base`` (N, P) int64, row strides ``nb`` (P,), fractions ``ta, tb``
    (N, P) (differentiable in the coordinates)."""
    bases, tas, tbs = [], [], []
    for (na, nb), (xa, xb) in zip(shapes, coords):
        ia, ta = cell_and_fraction(xa, na)
        ib, tb = cell_and_fraction(xb, nb)
        bases.append(ia * nb + ib)
        tas.append(ta)
        tbs.append(tb)
    ta = torch.stack(tas, -1).to(dtype).contiguous()
    tb = torch.stack(tbs, -1).to(dtype).contiguous()
    return torch.stack(bases, -1).contiguous(), np.array([nb for _, nb in shapes], np.int64), ta, tb


def _scratch(shapes: Sequence[tuple[int, ...]], dtype: np.dtype) -> tuple[np.ndarray, ...]:
    """Per-thread gradient tables, kept between calls (per Python thread) so that a backward pass only zeroes
    the rows it touches instead of allocating and faulting in fresh pages (~20 MB per fine level)."""
    cache = _SCRATCH.__dict__.setdefault("tables", {})
    out = []
    for shape in shapes:
        key = (tuple(shape), np.dtype(dtype).str)
        if key not in cache:
            if len(cache) >= _SCRATCH_MAX:
                cache.clear()
            cache[key] = np.empty(shape, dtype)
        out.append(cache[key])
    return tuple(out)


_SCRATCH = threading.local()
_SCRATCH_MAX = 12  # table shapes kept (a model has at most 2 encodings x 2 levels x 3 planes)


def _planes_backward(tables: tuple[np.ndarray, ...], base: np.ndarray, nb: np.ndarray, ta: np.ndarray,
                     tb: np.ndarray, grad: np.ndarray, need_tables: bool, need_coords: bool,
                     masks: Sequence[np.ndarray] | None = None, dense: bool = True):
    """Gradients of :func:`cpu_kernels.planes_forward`: (list of table gradients or None, g_ta, g_tb or None).

    Samples are split between threads, each accumulating into its own copy of the tables (only the touched rows
    are zeroed and summed). ``dense=True`` returns new zero-filled gradient tables; ``dense=False`` returns
    views of the scratch copies with only the touched rows (``masks``) valid, valid until the next call, for a
    caller that reads just those rows right away."""
    K = _kernels()
    threads = numba_threads()
    if need_tables:
        if masks is None:
            masks = tuple(np.zeros(len(T), np.bool_) for T in tables)
            K.mark_cells(base, nb, masks)
        per_thread = _scratch([(threads, *T.shape) for T in tables], tables[0].dtype)
        for S, m in zip(per_thread, masks):
            K.zero_rows(S, m)
    else:
        per_thread = tuple(np.empty((threads, 1, 1), T.dtype) for T in tables)  # unused placeholders
    g_ta = np.empty(base.shape if need_coords else (1, 1), grad.dtype)
    g_tb = np.empty_like(g_ta)
    K.planes_backward(tables, per_thread, base, nb, ta, tb, grad, g_ta, g_tb, need_tables, need_coords)
    g_tables = None
    if need_tables:
        g_tables = []
        for S, m in zip(per_thread, masks):
            out = np.zeros(S.shape[1:], S.dtype) if dense else S[0]
            K.reduce_rows(S, m, out)
            g_tables.append(out)
    return g_tables, (g_ta if need_coords else None), (g_tb if need_coords else None)


class _Planes(torch.autograd.Function):
    """``sum_p bilerp(tables[p])`` over P row-major tables (n_a * n_b, C)."""

    @staticmethod
    def forward(ctx, base: torch.Tensor, nb: np.ndarray, ta: torch.Tensor, tb: torch.Tensor, *tables):
        numba_threads()
        arrays = tuple(_np(T) for T in tables)
        out = np.empty((len(base), arrays[0].shape[1]), dtype=arrays[0].dtype)
        _kernels().planes_forward(arrays, base.numpy(), nb, _np(ta), _np(tb), out)
        ctx.save_for_backward(base, ta, tb, *tables)
        ctx.nb = nb
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        base, ta, tb, *tables = ctx.saved_tensors
        arrays = tuple(_np(T) for T in tables)
        need_tables = any(ctx.needs_input_grad[4:])
        need_coords = ctx.needs_input_grad[2] or ctx.needs_input_grad[3]
        g_tables, g_ta, g_tb = _planes_backward(arrays, base.numpy(), ctx.nb, _np(ta), _np(tb),
                                                _np(grad.to(tables[0].dtype)), need_tables, need_coords)
        gt = [torch.from_numpy(G) for G in g_tables] if need_tables else [None] * len(tables)
        g_ta = torch.from_numpy(g_ta) if need_coords else None
        g_tb = torch.from_numpy(g_tb) if need_coords else None
        return (None, None, g_ta, g_tb, *gt)


def planes_sum(planes: Sequence[torch.Tensor], coords: Sequence[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """Sum of P bilinear lookups (``align_corners``/border as :mod:`lrslam.field.interp`).

    Args:
        planes: P planes (n_a, n_b, C) (channels equal, sizes may differ).
        coords: P pairs (xa01, xb01) of (N,) unit coordinates along each plane's two axes.
    Returns:
        (N, C), differentiable in the planes and the coordinates.
    """
    base, nb, ta, tb = _plane_cells([p.shape[:2] for p in planes], coords, planes[0].dtype)
    tables = [p.reshape(p.shape[0] * p.shape[1], p.shape[2]) for p in planes]
    return _Planes.apply(base, nb, ta, tb, *tables)


class _CPProduct(torch.autograd.Function):
    """``out[n] = sum_k prod_a lerp(l_a, i0[n, a], t[n, a])[k]`` with lines (n_a, k C), k-major."""

    @staticmethod
    def forward(ctx, lx, ly, lz, i0: torch.Tensor, t: torch.Tensor, rank: int) -> torch.Tensor:
        numba_threads()
        lines = [_np(L) for L in (lx, ly, lz)]
        out = np.empty((len(t), lines[0].shape[1] // rank), dtype=lines[0].dtype)
        _kernels().cp_forward(*lines, i0.numpy(), _np(t), rank, out)
        ctx.save_for_backward(lx, ly, lz, i0, t)
        ctx.rank = rank
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        lx, ly, lz, i0, t = ctx.saved_tensors
        lines = [_np(L) for L in (lx, ly, lz)]
        need_lines, need_t = any(ctx.needs_input_grad[:3]), ctx.needs_input_grad[4]
        threads = numba_threads()  # samples split into this many ranges, each with its own line gradients
        dtype = lines[0].dtype
        g_lines = [np.zeros((threads, *L.shape), dtype) for L in lines] if need_lines else \
            [np.empty((threads, 1, 1), dtype)] * 3
        g_t = np.empty((len(t), 3) if need_t else (1, 3), dtype)
        _kernels().cp_backward(*lines, i0.numpy(), _np(t), ctx.rank, _np(grad.to(lx.dtype)), *g_lines, g_t,
                               need_lines, need_t)
        out = [torch.from_numpy(G[0] if threads == 1 else G.sum(0)) if need else None
               for G, need in zip(g_lines, ctx.needs_input_grad[:3])]
        return out[0], out[1], out[2], None, torch.from_numpy(g_t) if need_t else None, None


def cp_product(lx: torch.Tensor, ly: torch.Tensor, lz: torch.Tensor, x01: torch.Tensor, rank: int) -> torch.Tensor:
    """One CP level: lines ``l_a`` (n_a, k C) (k-major), unit coordinates ``x01`` (N, 3) -> (N, C)."""
    idx, frac = zip(*(cell_and_fraction(x01[:, a], L.shape[0]) for a, L in enumerate((lx, ly, lz))))
    t = torch.stack(frac, -1).to(lx.dtype).contiguous()
    return _CPProduct.apply(lx, ly, lz, torch.stack(idx, -1).contiguous(), t, rank)


_NO_MASK = np.zeros((1, 1), np.bool_)


class _OuterSum(torch.autograd.Function):
    """``P[a, b, c] = sum_k la[a, k, c] lb[b, k, c]``, all cells."""

    @staticmethod
    def forward(ctx, la: torch.Tensor, lb: torch.Tensor) -> torch.Tensor:
        numba_threads()
        a, b = _np(la), _np(lb)
        out = np.empty((a.shape[0], b.shape[0], a.shape[2]), a.dtype)
        _kernels().outer_sum_forward(a, b, out, _NO_MASK, False)
        ctx.save_for_backward(la, lb)
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        la, lb = ctx.saved_tensors
        numba_threads()
        a, b = _np(la), _np(lb)
        g_a, g_b = np.empty_like(a), np.empty_like(b)
        need_a, need_b = ctx.needs_input_grad[:2]
        _kernels().outer_sum_backward(_np(grad.to(la.dtype)), a, b, g_a, g_b, need_a, need_b, _NO_MASK, False)
        return torch.from_numpy(g_a) if need_a else None, torch.from_numpy(g_b) if need_b else None


def outer_sum(la: torch.Tensor, lb: torch.Tensor) -> torch.Tensor:
    """Materialised Six-axis plane of lines la (n_a, k, C), lb (n_b, k, C) -> (n_a, n_b, C), every cell."""
    return _OuterSum.apply(la, lb)


class _SixAxis(torch.autograd.Function):
    """A Six-axis level: for each of the P planes, line sets (la_p, lb_p); cells touched by the samples are
    materialised and looked up, the dense planes and their gradients stay inside."""

    @staticmethod
    def forward(ctx, base: torch.Tensor, nb: np.ndarray, ta: torch.Tensor, tb: torch.Tensor, *lines):
        K = _kernels()
        numba_threads()
        b = base.numpy()
        arrays = [_np(L) for L in lines]
        shapes = [(arrays[2 * p].shape[0], arrays[2 * p + 1].shape[0]) for p in range(len(arrays) // 2)]
        masks = tuple(np.zeros(na * nbp, np.bool_) for na, nbp in shapes)
        K.mark_cells(b, nb, masks)
        planes = []
        for p, (na, nbp) in enumerate(shapes):
            la, lb = arrays[2 * p], arrays[2 * p + 1]
            P = np.empty((na, nbp, la.shape[2]), la.dtype)
            K.outer_sum_forward(la, lb, P, masks[p].reshape(na, nbp), True)
            planes.append(P.reshape(na * nbp, la.shape[2]))
        out = np.empty((len(b), arrays[0].shape[2]), arrays[0].dtype)
        K.planes_forward(tuple(planes), b, nb, _np(ta), _np(tb), out)
        ctx.save_for_backward(base, ta, tb, *lines)
        ctx.nb, ctx.planes, ctx.masks, ctx.shapes = nb, tuple(planes), masks, shapes
        return torch.from_numpy(out)

    @staticmethod
    def backward(ctx, grad: torch.Tensor):
        K = _kernels()
        base, ta, tb, *lines = ctx.saved_tensors
        arrays = [_np(L) for L in lines]
        need_lines = any(ctx.needs_input_grad[4:])
        need_coords = ctx.needs_input_grad[2] or ctx.needs_input_grad[3]
        g_planes, g_ta, g_tb = _planes_backward(ctx.planes, base.numpy(), ctx.nb, _np(ta), _np(tb),
                                                _np(grad.to(lines[0].dtype)), need_lines, need_coords, ctx.masks,
                                                dense=False)  # only the touched cells are read below
        g_lines: list[torch.Tensor | None] = [None] * len(lines)
        if need_lines:  # numba's thread count was set by _planes_backward
            for p, (na, nbp) in enumerate(ctx.shapes):
                la, lb = arrays[2 * p], arrays[2 * p + 1]
                g_a, g_b = np.empty_like(la), np.empty_like(lb)
                G = g_planes[p].reshape(na, nbp, la.shape[2])
                K.outer_sum_backward(G, la, lb, g_a, g_b, True, True, ctx.masks[p].reshape(na, nbp), True)
                g_lines[2 * p], g_lines[2 * p + 1] = torch.from_numpy(g_a), torch.from_numpy(g_b)
        g_ta = torch.from_numpy(g_ta) if need_coords else None
        g_tb = torch.from_numpy(g_tb) if need_coords else None
        return (None, None, g_ta, g_tb, *g_lines)


def sixaxis_sum(line_pairs: Sequence[tuple[torch.Tensor, torch.Tensor]],
                coords: Sequence[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """``sum_p bilerp(outer_sum(la_p, lb_p), xa_p, xb_p)`` with only the touched cells materialised.

    Args:
        line_pairs: P pairs of line sets (la (n_a, k, C), lb (n_b, k, C)).
        coords: P pairs (xa01, xb01) of (N,) unit coordinates along each plane's two axes.
    Returns:
        (N, C), differentiable in the lines and the coordinates (same values as materialising every cell).
    """
    shapes = [(la.shape[0], lb.shape[0]) for la, lb in line_pairs]
    base, nb, ta, tb = _plane_cells(shapes, coords, line_pairs[0][0].dtype)
    return _SixAxis.apply(base, nb, ta, tb, *(L for pair in line_pairs for L in pair))


def warm_up() -> bool:
    """Compile (or load from numba's on-disk cache) every kernel for float32, forward and backward, on tiny
    inputs, so the first SLAM frame is not timed with the compilation (~20 s once per install). Returns whether
    the kernels are available."""
    if not numba_available():
        return False
    x = torch.rand(64, 3, requires_grad=True)
    lines = [torch.randn(n, 2, 4, requires_grad=True) for n in (5, 4, 6)]
    coords = [(x[:, 0], x[:, 1]), (x[:, 1], x[:, 2]), (x[:, 2], x[:, 0])]  # 3 planes, as every level uses
    pairs = [(lines[0], lines[1]), (lines[1], lines[2]), (lines[2], lines[0])]
    planes = [outer_sum(a, b) for a, b in pairs]
    outs = [cp_product(*(L.view(L.shape[0], -1) for L in lines), x, rank=2), planes_sum(planes, coords),
            sixaxis_sum(pairs, coords)]
    sum(o.square().sum() for o in outs).backward()
    return True
