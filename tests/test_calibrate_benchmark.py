"""``benchmarks/calibrate.py``'s gap table: each source's real per-axis error over a keyframe gap against ground
truth, beside the run's noise estimate (closed form, fast)."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from calibrate import _Gaps, _gap_table  # noqa: E402

from lrslam.geometry import exp_se3, make_pose  # noqa: E402


def test_gap_table_gives_each_sources_sigma_against_ground_truth():
    """Errors of known size per gap: the field 3 cm along x (sigma per axis 3 / sqrt(3) cm), the chain 0.6 deg
    about z (0.6 / sqrt(3) deg per axis), the registration exact; the estimate's sigmas are printed as given; a
    gap without ground truth is skipped; the chain-registration correlation, undefined with an exact registration,
    is left out."""
    gt = {k: make_pose(np.eye(3), [0.1 * k, 0.0, 0.0]) for k in range(4)}
    field_err = exp_se3(np.array([0, 0, 0, 0.03, 0, 0]))
    chain_err = exp_se3(np.array([0, 0, np.radians(0.6), 0, 0, 0]))
    rows = []
    for i, j in ((0, 2), (2, 3), (3, 9)):
        true = np.linalg.inv(gt[i]) @ gt[j] if j in gt else np.eye(4)
        rows.append((i, j, {"field": true @ field_err, "chain": true @ chain_err, "registration": true.copy()}))
    odometry = np.array([np.radians(0.1) ** 2, 0.004 ** 2])
    estimate = {"field": np.array([np.radians(0.5) ** 2, 0.02 ** 2]), "odometry": odometry,
                "registration": odometry.copy()}
    lines = _gap_table(_Gaps(rows), gt, estimate)
    table = {ln.split()[0]: ln.split() for ln in lines[1:4]}
    assert table["field"][1] == "2"                                   # the gap to frame 9 has no ground truth
    assert np.isclose(float(table["field"][3]), 3 / np.sqrt(3), atol=1e-3)
    assert np.isclose(float(table["field"][2]), 0.0, atol=1e-3)
    assert np.isclose(float(table["chain"][2]), 0.6 / np.sqrt(3), atol=1e-3)
    assert np.isclose(float(table["registration"][2]), 0.0, atol=1e-3)
    assert [float(x) for x in table["field"][4:6]] == [0.5, 2.0]
    assert [float(x) for x in table["registration"][4:6]] == [0.1, 0.4]
    assert not any("correlation" in ln for ln in lines)
