"""Batch runs: several sequences × modes, run one after another into ``OUT/<sequence>/<mode>/``, with a
side-by-side table (``comparison.md`` + ``comparison.json``) and a trajectory plot per sequence comparing
pure-field, frontend-only and graph-fused results.

Each (sequence, mode) job is independent and serialisable (path + config dict), so a distributed engine
can later map :func:`run_job` over the jobs unchanged.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np

from lrslam.jsonio import dumps

__all__ = ["run_job", "run_batch", "comparison_table", "failed_jobs"]

log = logging.getLogger(__name__)

COLUMNS = [("ate_rmse_cm", "ATE RMSE cm", "{:.2f}"), ("ate_mean_cm", "ATE mean cm", "{:.2f}"),
           ("fpt_s", "s/frame", "{:.3f}"), ("n_keyframes", "keyframes", "{}"), ("n_loop_closures", "loops", "{}"),
           ("mesh_accuracy_cm", "acc cm", "{:.2f}"), ("mesh_completion_ratio", "comp %", "{:.1f}")]


def run_job(sequence: str, config: dict[str, Any], out_dir: str, progress: bool = False) -> dict[str, Any]:
    """Run one (sequence, config) job; returns its metrics (with ``error`` set if it failed).

    ``config`` is a run config as a dict."""
    from lrslam.pipeline.config import RunConfig
    from lrslam.pipeline.run import run_sequence

    try:
        cfg = RunConfig.model_validate(config)
        return run_sequence(sequence, cfg, out_dir, progress=progress).metrics
    except Exception as e:  # one failing job must not lose the others
        log.error("job %s (%s) failed: %s", sequence, config.get("mode"), e)
        return {"mode": config.get("mode"), "error": f"{type(e).__name__}: {e}"}


def failed_jobs(results: dict[str, dict[str, dict[str, Any]]]) -> list[tuple[str, str]]:
    """``[("<sequence> (<mode>)", error), ...]`` for every job of a batch that failed."""
    return [(f"{seq} ({mode})", m["error"]) for seq, by_mode in results.items() for mode, m in by_mode.items()
            if "error" in m]


def comparison_table(results: dict[str, dict[str, dict[str, Any]]]) -> str:
    """Markdown table: one row per (sequence, mode)."""
    head = "| sequence | mode | " + " | ".join(c[1] for c in COLUMNS) + " |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 2)]
    for seq, by_mode in results.items():
        for mode, m in by_mode.items():
            cells = [fmt.format(m[key]) if key in m and m[key] is not None else ("error" if "error" in m else "-")
                     for key, _, fmt in COLUMNS]
            lines.append(f"| {seq} | {mode} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def run_batch(sequences: list[str | Path], configs: dict[str, dict[str, Any]], out: str | Path,
              progress: bool = True) -> dict[str, dict[str, dict[str, Any]]]:
    """Run every sequence under every named config (e.g. ``{"field": {...}, "fused": {...}}``)."""
    from lrslam.trajectory_io import read_tum

    out = Path(out)
    results: dict[str, dict[str, dict[str, Any]]] = {}
    for seq in sequences:
        name = Path(seq).resolve().name
        results[name] = {}
        trajs = {}
        for label, cfg in configs.items():
            job_dir = out / name / label
            results[name][label] = run_job(str(seq), cfg, str(job_dir), progress=progress)
            if (job_dir / "trajectory.txt").is_file():
                trajs[label] = read_tum(job_dir / "trajectory.txt")
        _plot_sequence(out / name / "comparison.png", seq, trajs, configs)
    (out / "comparison.json").write_text(dumps(results, indent=2, default=float))
    (out / "comparison.md").write_text(comparison_table(results) + "\n")
    return results


def _plot_sequence(path: Path, seq, trajs, configs) -> None:
    if not trajs:
        return
    try:
        from lrslam.frontend.datasets import open_sequence
        from lrslam.pipeline.plots import plot_trajectories

        first = next(iter(configs.values()))
        s = open_sequence(seq, reader=(first.get("dataset") or {}).get("reader"))
        gt = s.gt_poses()
        plot_trajectories(path, trajs, (np.asarray(s.timestamps), gt) if gt is not None else None,
                          title=f"{Path(seq).name}: " + " vs ".join(trajs))
    except Exception as e:
        log.warning("comparison plot failed: %s", e)
