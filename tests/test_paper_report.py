"""``benchmarks/paper_report.py``: the verdicts next to the paper's numbers follow the measured numbers (fast)."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))

import paper
from paper_report import write_report


def _results(cp_sa_fpt: float, scannet_total: int, depth_l1: tuple[float, float]) -> dict:
    counts = {(ds, r): tuple(int(x * 1e6) for x in v[:3]) for ds, d in paper.PAPER_T1.items() for r, v in d.items()}
    counts[("scannet", "lrslam")] = (46_080, 1_327_104, scannet_total)
    runs = [{"ate": 1.0, "fpt": 0.5, "cpu_fpt": 0.4, "params": 800_000},
            {"ate": 1.2, "fpt": 0.6, "cpu_fpt": 0.4, "params": 800_000}]
    noise = {r: {"depth_l1_cm": d, "accuracy_cm": 1.0, "completion_cm": 1.0, "completion_ratio": 95.0,
                 "ate_mean_cm": 1.0, "ate_rmse_cm": 1.0} for r, d in zip(("lrslam", "eslam"), depth_l1)}
    curve = [{"iters": 5, "loss": 1.0, "depth_l1_cm": 10.0}]
    t1 = {"counts": counts, "fpt": {"lrslam": [0.5], "eslam": [1.0]}, "ratios": [0.5],   # wall: CP-SA faster
          "cpu_fpt": {"lrslam": [cp_sa_fpt], "eslam": [1.0]}, "cpu_ratios": [cp_sa_fpt]}
    return {"table1": t1,
            "memory": {"sides": [1.0, 2.0], "rows": {"tri-plane": [1, 4], "CP (CP-CP)": [1, 2],
                                                     "SA (SA-SA)": [1, 2], "CP-SA": [1, 2]},
                       "slopes": {"tri-plane": 2.0, "CP (CP-CP)": 1.0, "SA (SA-SA)": 1.0, "CP-SA": 1.0}},
            "ablation": {"synthetic": {v: runs for v in paper.VARIANTS}},
            "noise": noise, "convergence": {v: curve for v in paper.VARIANTS},
            "load": {"cpus": 2, "torch_threads": 1, "start": 3.0, "end": 4.0}}


def _report(tmp_path, **kw) -> str:
    path = write_report(tmp_path / "RESULTS.md", paper.SIZES["quick"], _results(**kw), {"total": 600.0},
                        paper.PAPER_T1, paper.PAPER_T4)
    return path.read_text()


def test_report_says_agree_when_the_numbers_agree(tmp_path):
    text = _report(tmp_path, cp_sa_fpt=0.8, scannet_total=1_375_877, depth_l1=(1.0, 2.0))
    assert "All parameter counts agree with the paper to its rounding." in text
    assert "CP-SA is faster per frame here (CPU time), as in the paper." in text
    assert "CP-SA beats tri-plane here on: depth_l1_cm" in text
    assert "schedule.velocity_model: linear" in text and "load average 3.0" in text


def test_report_flags_what_disagrees(tmp_path):
    text = _report(tmp_path, cp_sa_fpt=1.3, scannet_total=1_373_184, depth_l1=(2.0, 1.0))
    assert "| scannet | LRSLAM | 0.046 M | 1.327 M | 1.373 M | 0.05 / 1.33 / 1.38 M (**differs**) |" in text
    assert "CP-SA is **not** faster per frame here (CPU time)" in text   # the verdict follows CPU time
    assert "CP-SA beats tri-plane here on: none" in text
