"""Are the pose graph's factors honest about their errors? Normalised residuals against ground truth.

For a between factor ``(i, j, T_i_j, Lambda)`` the error against ground truth is
``e = log(T_i_j^-1 T_gt_i^-1 T_gt_j)`` (6-vector ``[rotation rad, translation m]``, right perturbation, the
graph's convention) and its normalised square ``chi2 = e^T Lambda e``. For a factor whose information is the
inverse of its true error covariance, ``chi2`` follows a chi-square law with 6 degrees of freedom: mean 6,
median 5.35. ``chi2 / 6`` far above 1 means the factor is over-confident (the graph trusts it too much), far
below 1 under-confident. Relative poses do not depend on the world frame, so no alignment is needed.

Ground truth is looked up by frame timestamp (nearest sample within 0.02 s, the ATE's association).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lrslam.evaluation.association import associate
from lrslam.evaluation.ate import ground_truth_samples
from lrslam.geometry import between_residual, inv

__all__ = ["FactorChi2", "factor_chi2", "run_factor_chi2"]

DOF = 6


@dataclass(frozen=True)
class FactorChi2:
    """Normalised residuals of one factor kind: ``n`` factors, ``mean`` and ``median`` of ``chi2 / 6`` (1 and
    0.89 when calibrated), and the RMS translation (cm) and rotation (deg) error of the measurements."""

    kind: str
    n: int
    mean: float
    median: float
    trans_rms_cm: float
    rot_rms_deg: float

    def to_dict(self) -> dict[str, float | int]:
        return {"n": self.n, "chi2_per_dof_mean": round(self.mean, 4), "chi2_per_dof_median": round(self.median, 4),
                "trans_rms_cm": round(self.trans_rms_cm, 4), "rot_rms_deg": round(self.rot_rms_deg, 4)}


def factor_chi2(factors: Sequence, gt_poses: dict[int, np.ndarray]) -> dict[str, FactorChi2]:
    """Per factor kind, :class:`FactorChi2` of ``factors`` (records with ``kind, i, j, T_i_j, information``,
    e.g. :class:`lrslam.backend.policy.FactorRecord`) against ``gt_poses`` (frame index -> ground-truth
    ``T_w_c``); factors whose frames have no ground truth are skipped."""
    by_kind: dict[str, list[tuple[np.ndarray, float]]] = {}
    for f in factors:
        if f.i == f.j or f.i not in gt_poses or f.j not in gt_poses:   # unary (a field pose): world-frame bound
            continue
        true = inv(gt_poses[f.i]) @ gt_poses[f.j]
        by_kind.setdefault(f.kind, []).append(between_residual(f.T_i_j, f.information, true))
    out = {}
    for kind, rows in sorted(by_kind.items()):
        e = np.stack([r[0] for r in rows])
        c = np.array([r[1] for r in rows]) / DOF
        out[kind] = FactorChi2(kind, len(rows), float(np.mean(c)), float(np.median(c)),
                               float(np.sqrt(np.mean(np.sum(e[:, 3:] ** 2, axis=1)))) * 100,
                               float(np.degrees(np.sqrt(np.mean(np.sum(e[:, :3] ** 2, axis=1))))))
    return out


def run_factor_chi2(factors: Sequence, timestamps: np.ndarray, seq) -> dict[str, FactorChi2] | None:
    """:func:`factor_chi2` of a run's factors (frame indices into ``timestamps`` (N,) s) against the ground truth
    of sequence ``seq``; None without ground truth or factors."""
    if not factors:
        return None
    gt = ground_truth_samples(seq)
    if gt is None:
        return None
    gt_ts, gt_T = gt
    ok = np.all(np.isfinite(gt_T), axis=(1, 2)) & np.isfinite(gt_ts)
    i_est, i_gt = associate(np.asarray(timestamps, dtype=np.float64), gt_ts[ok])
    return factor_chi2(factors, {int(a): gt_T[ok][b] for a, b in zip(i_est, i_gt)})
