"""End-of-run sanity check: a run that "finished" but whose result cannot be trusted says so.

``status: degraded`` (with ``degraded_reasons``) when every field refine failed, camera poses left the scene
bound (runs with a field), or a pose or metric is not finite; ``status: ok`` otherwise. ``lrslam run``
prints the reasons and exits with code 3 on a degraded run.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["run_status", "nonfinite_keys"]

def nonfinite_keys(obj: Any, prefix: str = "") -> list[str]:
    """Dotted keys of every non-finite float in a nested dict / list (``"timings.map.total_s"``, ...)."""
    out: list[str] = []
    if isinstance(obj, dict):
        for k, v in obj.items():
            out += nonfinite_keys(v, f"{prefix}{k}.")
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            out += nonfinite_keys(v, f"{prefix}{i}.")
    elif isinstance(obj, (float, np.floating)) and not math.isfinite(float(obj)):
        out.append(prefix.rstrip("."))
    return out


def run_status(metrics: dict, poses: np.ndarray, bound: np.ndarray, has_field: bool) -> tuple[str, list[str]]:
    """``("ok" | "degraded", reasons)`` from a run's metrics, its poses (N, 4, 4) ``T_w_c`` and bound (3, 2) m;
    ``has_field``: the run refined poses with a field (its refinements and bound then count)."""
    reasons: list[str] = []
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    n = len(poses)
    if has_field and n > 1 and metrics.get("refine_failures", 0) >= n - 1:
        reasons.append(f"every field refine failed ({metrics['refine_failures']} of {n - 1} frames)")
    finite = np.all(np.isfinite(poses), axis=(1, 2))
    if not finite.all():
        reasons.append(f"{int((~finite).sum())} of {n} poses are not finite")
    if has_field and finite.any():
        b = np.asarray(bound, dtype=np.float64)
        c = poses[finite, :3, 3]
        out = ~np.all((c >= b[:, 0]) & (c <= b[:, 1]), axis=1)
        if out.any():
            reasons.append(f"{int(out.sum())} of {n} camera poses left the scene bound")
    bad = nonfinite_keys(metrics)
    if bad:
        reasons.append("non-finite metrics: " + ", ".join(bad[:5]) + (" ..." if len(bad) > 5 else ""))
    return ("degraded" if reasons else "ok"), reasons
