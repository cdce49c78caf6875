"""Timestamp association (TUM ``associate.py`` logic) and ground-truth pose interpolation.

Both use the TUM benchmark's tolerance: two stamps match when they differ by strictly less than
``max_difference`` seconds (0.02 s by default).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from lrslam.errors import DatasetError

__all__ = ["associate", "pair_colour_depth", "interpolate_poses", "MAX_DIFFERENCE"]

MAX_DIFFERENCE = 0.02  # seconds, as TUM's associate.py


def associate(first: np.ndarray, second: np.ndarray, max_difference: float = MAX_DIFFERENCE) -> np.ndarray:
    """Greedy one-to-one association of two timestamp lists, as TUM's ``associate.py``.

    All pairs with ``|t1 - t2| < max_difference`` are candidates; they are taken in order of increasing
    difference, skipping pairs whose stamps are already used. Returns (K, 2) int indices ``(i_first,
    i_second)`` sorted by ``first[i_first]``. Vectorised: only pairs inside the window are formed.
    """
    a = np.asarray(first, dtype=np.float64).reshape(-1)
    b = np.asarray(second, dtype=np.float64).reshape(-1)
    order_b = np.argsort(b, kind="stable")
    bs = b[order_b]
    lo = np.searchsorted(bs, a - max_difference, side="left")
    hi = np.searchsorted(bs, a + max_difference, side="right")
    counts = hi - lo
    ia = np.repeat(np.arange(len(a)), counts)
    jb_sorted = np.concatenate([np.arange(s, e) for s, e in zip(lo, hi)]) if counts.sum() else np.zeros(0, int)
    jb = order_b[jb_sorted]
    diff = np.abs(a[ia] - b[jb])
    keep = diff < max_difference
    ia, jb, diff = ia[keep], jb[keep], diff[keep]
    # associate.py sorts (diff, a, b) tuples: ties broken by the stamps themselves.
    order = np.lexsort((b[jb], a[ia], diff))
    used_a = np.zeros(len(a), bool)
    used_b = np.zeros(len(b), bool)
    pairs = []
    for k in order:
        i, j = ia[k], jb[k]
        if not used_a[i] and not used_b[j]:
            used_a[i] = used_b[j] = True
            pairs.append((i, j))
    out = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    return out[np.argsort(a[out[:, 0]], kind="stable")]


def pair_colour_depth(t_rgb: np.ndarray, t_depth: np.ndarray, where: Path, rgb_source: str, depth_source: str,
                      logger: logging.Logger, *, pair: str = "rgb/depth", images: str = "colour images") -> np.ndarray:
    """A reader's colour and depth stamps associated with :func:`associate` (``MAX_DIFFERENCE``) -> (K, 2) pairs.

    DatasetError naming ``where`` and both sources' stamp ranges when nothing pairs; the colour images left
    without depth are logged on ``logger`` (the reader's), as a warning when more than 5 % of them.

    Args:
        t_rgb, t_depth: (N,), (M,) float64 seconds, neither empty.
        where: the dataset (folder or bag) for messages. rgb_source, depth_source: where the stamps come from
            (``rgb.txt``, a topic). pair: what is paired, in the error. images: what is dropped, in the log.
    """
    pairs = associate(t_rgb, t_depth, MAX_DIFFERENCE)
    if len(pairs) == 0:
        raise DatasetError(f"{where}: no {pair} pair within {MAX_DIFFERENCE} s ({rgb_source}: {len(t_rgb)} stamps "
                           f"{t_rgb.min():.3f}..{t_rgb.max():.3f}, {depth_source}: {len(t_depth)} stamps "
                           f"{t_depth.min():.3f}..{t_depth.max():.3f})")
    dropped = len(t_rgb) - len(pairs)
    if dropped:
        (logger.warning if dropped > 0.05 * len(t_rgb) else logger.info)(
            "%s: %d of %d %s have no depth image within %.2f s and are skipped", where, dropped, len(t_rgb), images,
            MAX_DIFFERENCE)
    return pairs


def interpolate_poses(t_query: np.ndarray, t_samples: np.ndarray, poses: np.ndarray,
                      max_difference: float = MAX_DIFFERENCE) -> np.ndarray:
    """Poses at query times from timed samples (e.g. 100 Hz motion capture) -> (N, 4, 4), NaN where none.

    For each query time: when the samples just before and just after both lie within ``max_difference``,
    the pose is interpolated between them (translation linearly, rotation by slerp); otherwise the nearest
    sample within ``max_difference`` is used; otherwise the row is NaN (no ground truth for that time). A NaN
    sample (lost tracking) gives NaN to every query it would be used for.

    Args:
        t_query: (N,) seconds. t_samples: (M,) seconds (any order). poses: (M, 4, 4) rigid transforms.
    """
    tq = np.asarray(t_query, dtype=np.float64).reshape(-1)
    order = np.argsort(np.asarray(t_samples, dtype=np.float64).reshape(-1), kind="stable")
    ts = np.asarray(t_samples, dtype=np.float64)[order]
    P = np.asarray(poses, dtype=np.float64)[order]
    out = np.full((len(tq), 4, 4), np.nan)
    if len(ts) == 0 or len(tq) == 0:
        return out
    nxt = np.searchsorted(ts, tq, side="left")  # first sample at or after the query
    prv = nxt - 1  # last sample strictly before the query
    has_n = nxt < len(ts)
    has_p = prv >= 0
    n_c, p_c = np.clip(nxt, 0, len(ts) - 1), np.clip(prv, 0, len(ts) - 1)
    dn = np.where(has_n, ts[n_c] - tq, np.inf)
    dp = np.where(has_p, tq - ts[p_c], np.inf)
    exact = has_n & (dn == 0)
    interp = has_n & has_p & (dn < max_difference) & (dp < max_difference) & ~exact
    # a NaN sample (lost tracking) leaves every query that would use it without a pose
    valid = np.all(np.isfinite(P), axis=(1, 2))
    broken = interp & ~(valid[p_c] & valid[n_c])
    interp &= ~broken
    nearest = ~interp & ~broken & (np.minimum(dn, dp) < max_difference)
    near_idx = np.where(dn <= dp, n_c, p_c)
    out[nearest] = P[near_idx[nearest]]
    if np.any(interp):
        i0, i1 = p_c[interp], n_c[interp]
        w = (tq[interp] - ts[i0]) / (ts[i1] - ts[i0])
        r0, r1 = Rotation.from_matrix(P[i0, :3, :3]), Rotation.from_matrix(P[i1, :3, :3])
        R = (r0 * Rotation.from_rotvec((r0.inv() * r1).as_rotvec() * w[:, None])).as_matrix()
        t = (1 - w)[:, None] * P[i0, :3, 3] + w[:, None] * P[i1, :3, 3]
        block = np.zeros((len(w), 4, 4))
        block[:, :3, :3], block[:, :3, 3], block[:, 3, 3] = R, t, 1.0
        out[interp] = block
    return out
