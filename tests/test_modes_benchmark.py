"""``benchmarks/modes.py``: which configs it runs per mode, and what its check lines say (fast, no run)."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from modes import _jobs, report  # noqa: E402


def test_jobs_run_the_frontend_alone_and_with_its_own_graph():
    """``frontend`` has no backend; ``frontend+graph`` is the same frontend with the pose graph of its
    registrations and loops (no field factor, no field); field and fused once per seed."""
    jobs = _jobs("synthetic", [], seeds=2, ablation=0)
    assert sorted(jobs) == ["field/s0", "field/s1", "frontend", "frontend+graph", "fused/s0", "fused/s1"]
    fe, fg = jobs["frontend"], jobs["frontend+graph"]
    assert fe["mode"] == fg["mode"] == "frontend"
    assert fe["parts"]["backend"] == "none" and fe["parts"]["refiner"] == "none"
    assert fg["parts"]["backend"] == "graph" and fg["parts"]["refiner"] == "none"
    assert fg["backend"]["factors"] == ["odometry", "loop"]
    assert jobs["fused/s1"]["field"]["seed"] == 1
    assert "frontend+graph" not in _jobs("synthetic", [], seeds=1, ablation=0, only=("field", "frontend", "fused"))


def _results(ates: dict[str, list[float]]) -> dict[str, dict]:
    out = {}
    for name, values in ates.items():
        for s, a in enumerate(values):
            out[name if name.startswith("frontend") else f"{name}/s{s}"] = {"ate_rmse_cm": a, "fpt_s": 0.1}
    return out


def test_report_states_the_classical_comparison_apart_from_the_promise():
    """The promise is fused <= min(field, frontend) on the means; the frontend+graph line says PASS / FAIL on its
    own and does not change the promise's verdict."""
    text, ok = report("seq", _results({"field": [0.4, 0.5], "frontend": [2.0], "frontend+graph": [0.25],
                                       "fused": [0.3, 0.36]}))
    assert ok
    assert "PASS  fused <= min(field, frontend): fused 0.33" in text
    assert "FAIL  fused <= frontend+graph" in text and "frontend+graph 0.25 cm" in text
    text, ok = report("seq", _results({"field": [0.4], "frontend": [0.3], "frontend+graph": [0.5], "fused": [0.35]}))
    assert not ok
    assert "FAIL  fused <= min(field, frontend)" in text and "PASS  fused <= frontend+graph" in text
    text, ok = report("seq", _results({"field": [0.4], "frontend": [2.0], "fused": [0.3]}))
    assert ok and "frontend+graph" not in text
