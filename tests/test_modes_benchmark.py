"""``benchmarks/modes.py``: which configs it runs per mode, and what its check lines say (fast, no run)."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

from modes import _jobs, report  # noqa: E402


def test_jobs_run_the_frontend_alone_with_its_own_graph_and_without_its_model():
    """``frontend`` has no backend; ``frontend+graph`` is the same frontend with the pose graph of its
    registrations and loops (no field factor, no field); ``frontend-f2f`` the frontend without the frame-to-model
    refinement that the other modes use (the CPU presets); every variant once per seed (threaded Open3D
    registrations do not repeat exactly, so the frontends have a spread too)."""
    jobs = _jobs("synthetic", [], seeds=2, ablation=0)
    assert sorted(jobs) == sorted(f"{v}/s{s}" for v in ("field", "frontend", "frontend+graph", "frontend-f2f",
                                                        "fused") for s in (0, 1))
    fe, fg, fm = jobs["frontend/s0"], jobs["frontend+graph/s1"], jobs["frontend-f2f/s0"]
    assert fe["mode"] == fg["mode"] == fm["mode"] == "frontend"
    assert fe["parts"]["backend"] == "none" and fe["parts"]["refiner"] == "none"
    assert fg["parts"]["backend"] == "graph" and fg["parts"]["refiner"] == "none"
    assert fg["backend"]["factors"] == ["odometry", "loop"]
    assert fm["parts"] == fe["parts"] and not fm["odometry"]["model"]["enabled"]
    assert fe["odometry"]["model"]["enabled"] and fg["odometry"]["model"]["enabled"]
    assert not jobs["fused/s0"]["odometry"]["model"]["enabled"]     # fused runs frame to frame
    assert jobs["fused/s1"]["field"]["seed"] == 1
    only = _jobs("synthetic", [], seeds=1, ablation=0, only=("field", "frontend", "fused"))
    assert "frontend+graph" not in only and "frontend-f2f" not in only


def _results(ates: dict[str, list[float]]) -> dict[str, dict]:
    out = {}
    for name, values in ates.items():
        for s, a in enumerate(values):
            out[f"{name}/s{s}"] = {"ate_rmse_cm": a, "fpt_s": 0.1}
    return out


def test_report_states_the_classical_comparison_apart_from_the_promise():
    """The promise is fused <= min(field, frontend) on the means; the frontend+graph line says PASS / FAIL on its
    own and does not change the promise's verdict."""
    text, ok = report("seq", _results({"field": [0.4, 0.5], "frontend": [2.0], "frontend+graph": [0.25],
                                       "fused": [0.3, 0.36]}))
    assert ok
    assert "PASS  fused <= min(field, frontend): fused 0.33" in text
    # the verdict is on the means; the line gives the margin and the seeds' noise: std([0.3, 0.36]) / sqrt(2)
    assert "fused - min = -0.12 cm, the standard error of fused's mean 0.03 over 2 seeds" in text
    assert "FAIL  fused <= frontend+graph" in text and "frontend+graph 0.25 cm" in text
    text, ok = report("seq", _results({"field": [0.4], "frontend": [0.3], "frontend+graph": [0.5], "fused": [0.35]}))
    assert not ok
    assert "FAIL  fused <= min(field, frontend)" in text and "PASS  fused <= frontend+graph" in text
    text, ok = report("seq", _results({"field": [0.4], "frontend": [2.0], "fused": [0.3]}))
    assert ok and "frontend+graph" not in text and "frontend-f2f" not in text
    assert "standard error" not in text                       # one seed: no noise to state


def test_report_states_the_frame_to_frame_frontend_comparison_apart_from_the_promise():
    """A better frame-to-frame frontend prints FAIL on its own line and leaves the promise's verdict alone."""
    text, ok = report("seq", _results({"field": [0.4], "frontend": [2.0], "frontend-f2f": [0.25],
                                       "fused": [0.3]}))
    assert ok and "PASS  fused <= min(field, frontend)" in text
    assert "FAIL  fused <= frontend-f2f" in text and "frontend-f2f 0.25 cm" in text
    text, _ = report("seq", _results({"field": [0.4], "frontend": [2.0], "frontend-f2f": [0.5], "fused": [0.3]}))
    assert "PASS  fused <= frontend-f2f" in text
