"""Timestamp association of an estimated and a ground-truth trajectory (TUM RGB-D ``associate.py`` logic).

The matching itself is :func:`lrslam.frontend.datasets.association.associate` (shared with the dataset readers,
which pair colour and depth images the same way); this wrapper validates the stamps, returns two index arrays and
turns "nothing matched" into a one-line :class:`InputError`.
"""

from __future__ import annotations

import numpy as np

from lrslam.errors import InputError

__all__ = ["associate"]


def associate(ts_a: np.ndarray, ts_b: np.ndarray, max_dt: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Match stamps of ``ts_a (N,)`` to stamps of ``ts_b (M,)`` (seconds), one-to-one.

    A pair is a candidate when ``|ts_a[i] - ts_b[j]| < max_dt`` (strict, as TUM); candidates are accepted
    greedily by increasing time difference, each index at most once. Neither input needs to be sorted.

    Returns ``(idx_a, idx_b)``: int64 index arrays of equal length, sorted by ``ts_a[idx_a]``.
    Raises :class:`InputError` when an input is not a finite non-empty 1-D array or when no pair associates.
    """
    from lrslam.frontend.datasets.association import associate as associate_pairs

    a = _stamps(ts_a, "ts_a")
    b = _stamps(ts_b, "ts_b")
    if not max_dt > 0:
        raise InputError(f"max_dt must be > 0 seconds, got {max_dt}")
    pairs = associate_pairs(a, b, max_dt)
    if len(pairs) == 0:
        raise InputError(f"no timestamps associate within max_dt={max_dt} s: ts_a spans "
                         f"[{a.min():.3f}, {a.max():.3f}] s, ts_b spans [{b.min():.3f}, {b.max():.3f}] s")
    return pairs[:, 0].astype(np.int64), pairs[:, 1].astype(np.int64)


def _stamps(ts: np.ndarray, name: str) -> np.ndarray:
    t = np.asarray(ts, dtype=np.float64)
    if t.ndim != 1 or len(t) == 0:
        raise InputError(f"{name}: expected a non-empty 1-D array of timestamps, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise InputError(f"{name}: {int(np.sum(~np.isfinite(t)))} non-finite timestamps")
    return t
