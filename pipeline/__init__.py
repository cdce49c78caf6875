"""Pipeline: runs sequences end to end (modes field / frontend / fused) and evaluates them.

The Python API (imported on first use, so ``import lrslam.pipeline`` stays light)::

    from lrslam.pipeline import build_config, open_sequence, run_sequence

    seq = open_sequence("data/room")                    # reader auto-detected; seq.gt_poses(), len(seq), seq[i]
    cfg = build_config("synthetic", "lrslam", overrides=["field.seed=1"], mode="fused")
    res = run_sequence("data/room", cfg, "runs/api")    # writes the run folder, returns a RunResult
    res.metrics["ate_rmse_cm"], res.poses               # poses: (N, 4, 4) T_w_c, metres

Batches: :func:`expand_grid` (the job grid), :func:`run_grid` with an executor from :func:`make_executor`
(Ray or in-process), :func:`write_report` (comparison tables + HTML) of a folder of runs.
"""

from __future__ import annotations

from importlib import import_module

__all__ = ["build_config", "RunConfig", "open_sequence", "run_sequence", "RunResult", "expand_grid", "run_grid",
           "make_executor", "write_report", "compute_ate"]

_WHERE = {"build_config": "lrslam.pipeline.config", "RunConfig": "lrslam.pipeline.config",
          "open_sequence": "lrslam.datasets", "run_sequence": "lrslam.pipeline.run",
          "RunResult": "lrslam.pipeline.run", "expand_grid": "lrslam.tools.batch_grid",
          "run_grid": "lrslam.tools.batch", "make_executor": "lrslam.tools.batch_exec",
          "write_report": "lrslam.tools.report", "compute_ate": "lrslam.evaluation.ate"}


def __getattr__(name: str):
    if name in _WHERE:
        return getattr(import_module(_WHERE[name]), name)
    raise AttributeError(f"module 'lrslam.pipeline' has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted(list(globals()) + __all__)
