"""Timestamp association of an estimated and a ground-truth trajectory (TUM RGB-D ``associate.py`` logic).

**One association everywhere: nearest ground-truth sample, never interpolation.** Each estimated pose is paired
with the ground-truth *sample* closest in time (within ``max_dt``); the ground truth is not resampled at the
estimate's stamps. The run's own ATE (``compute_run_ate``), ``lrslam eval ate`` and ``evo_ape tum gt est -a``
therefore compare the same pose pairs and give the same numbers on the same files. Why nearest and not
interpolated: it is what the reference tools do (TUM's ``associate.py`` + ``evaluate_ate.py``, evo's default
``SyncMethod.nearest_time``, ESLAM / NICE-SLAM's ``eval_ate``), so our numbers compare with published ones; it
needs nothing but the two files; and it is exact for datasets with one ground-truth pose per frame (Replica,
ScanNet, 7-Scenes, synthetic). TUM's 100 Hz motion capture is at most 5 ms from a frame, so nearest and
interpolated ground truth differ by at most a few mm per pose (1.090 vs 1.102 cm RMSE on one fr1 run).
The dataset readers still interpolate the ground truth for ``Frame.T_w_c_gt`` (a pose prior, e.g.
``initial_pose: gt``); evaluation does not use those interpolated poses.

Tolerance: ``max_dt = 0.02`` s (strictly less, as TUM). evo's default is 0.01 s; with TUM's 100 Hz ground truth
every frame has a sample within 0.005 s, so both tolerances keep the same pairs. The pairing is one-to-one
(greedy by time difference); evo pairs each pose of the shorter trajectory with its nearest, which is the same
whenever frames are further apart than ground-truth samples (30 Hz frames, 100 Hz ground truth).

The matching itself is :func:`lrslam.datasets.association.associate` (shared with the dataset readers,
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
    from lrslam.datasets.association import associate as associate_pairs

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
