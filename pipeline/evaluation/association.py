"""Timestamp association of two trajectories (as TUM RGB-D's ``associate.py``).

Every pair of stamps closer than ``max_dt`` is a candidate; candidates are taken greedily in order of increasing
``|t_a - t_b|`` and each stamp is used at most once, so the matching is one-to-one.
"""

from __future__ import annotations

import numpy as np

from lrslam.errors import InputError

__all__ = ["associate"]


def associate(ts_a: np.ndarray, ts_b: np.ndarray, max_dt: float = 0.02) -> tuple[np.ndarray, np.ndarray]:
    """Match stamps of ``ts_a (N,)`` to stamps of ``ts_b (M,)`` (seconds), one-to-one.

    A pair is a candidate when ``|ts_a[i] - ts_b[j]| <= max_dt``; candidates are accepted greedily by
    increasing time difference (TUM ``associate.py``), each index at most once. Neither input needs to be sorted.

    Returns ``(idx_a, idx_b)``: int64 index arrays of equal length, sorted by ``ts_a[idx_a]``.
    Raises :class:`InputError` when an input is not a finite 1-D array or when no pair associates.
    """
    a = _stamps(ts_a, "ts_a")
    b = _stamps(ts_b, "ts_b")
    if not max_dt >= 0:
        raise InputError(f"max_dt must be >= 0 seconds, got {max_dt}")

    # 1. Candidates: for each a, the b stamps within [a - max_dt, a + max_dt] (b sorted; O((N + M) log M + pairs)).
    order_b = np.argsort(b, kind="stable")
    b_sorted = b[order_b]
    lo = np.searchsorted(b_sorted, a - max_dt, side="left")
    hi = np.searchsorted(b_sorted, a + max_dt, side="right")
    counts = hi - lo
    cand_a = np.repeat(np.arange(len(a)), counts)
    offsets = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    cand_b = order_b[np.repeat(lo, counts) + offsets]
    dt = np.abs(a[cand_a] - b[cand_b])
    keep = dt <= max_dt  # guards against rounding in a +- max_dt
    cand_a, cand_b, dt = cand_a[keep], cand_b[keep], dt[keep]

    # 2. Greedy one-to-one selection by increasing |dt| (ties broken by index for determinism).
    used_a = np.zeros(len(a), dtype=bool)
    used_b = np.zeros(len(b), dtype=bool)
    idx_a, idx_b = [], []
    for k in np.lexsort((cand_b, cand_a, dt)):
        i, j = cand_a[k], cand_b[k]
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            idx_a.append(i)
            idx_b.append(j)
    if not idx_a:
        raise InputError(f"no timestamps associate within max_dt={max_dt} s: ts_a spans "
                         f"[{a.min():.3f}, {a.max():.3f}] s, ts_b spans [{b.min():.3f}, {b.max():.3f}] s")

    # 3. Sort the matches by time of the first sequence.
    idx_a = np.asarray(idx_a, dtype=np.int64)
    idx_b = np.asarray(idx_b, dtype=np.int64)
    order = np.lexsort((idx_a, a[idx_a]))
    return idx_a[order], idx_b[order]


def _stamps(ts: np.ndarray, name: str) -> np.ndarray:
    t = np.asarray(ts, dtype=np.float64)
    if t.ndim != 1 or len(t) == 0:
        raise InputError(f"{name}: expected a non-empty 1-D array of timestamps, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise InputError(f"{name}: {int(np.sum(~np.isfinite(t)))} non-finite timestamps")
    return t
