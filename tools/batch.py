"""Batch runs: a job grid (:mod:`lrslam.tools.batch_grid`) run by an executor (:mod:`lrslam.tools.batch_exec`:
Ray tasks or in-process), each job into its own run folder ``OUT/<sequence>/<variant>/s<seed>/``.

:func:`run_grid` checks every path before the first job starts, skips jobs whose run folders are complete
(so a re-run of a batch resumes it), shows one overall progress bar (done / failed / running) and a status line
per job, rewrites ``OUT/batch.json`` (every job: settings, status, error) and the comparison tables
(``comparison.md`` / ``comparison.csv``) as jobs finish, and writes the HTML report (:mod:`lrslam.tools.report`)
at the end.
"""

from __future__ import annotations

import logging
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lrslam.jsonio import dumps
from lrslam.tools.batch_grid import Job, check_jobs, job_status

__all__ = ["run_grid", "run_batch", "BatchOutcome", "MANIFEST"]

log = logging.getLogger(__name__)

MANIFEST = "batch.json"


@dataclass
class BatchOutcome:
    """What a batch did: one entry per job (``batch.json``'s ``jobs``) and the report it wrote."""

    entries: list[dict[str, Any]]
    report: Path | None

    def failed(self) -> list[dict[str, Any]]:
        return [e for e in self.entries if e["status"] == "failed"]

    def degraded(self) -> list[dict[str, Any]]:
        return [e for e in self.entries if e["status"] == "degraded"]


class _Progress:
    """One overall bar (jobs done / failed / running) and one status line per job, on stderr."""

    def __init__(self, total: int, enabled: bool) -> None:
        from tqdm import tqdm

        self.enabled = enabled
        self.done = self.failed = self.running = 0
        self.bar = tqdm(total=total, desc="batch", unit="job", file=sys.stderr, disable=not enabled,
                        dynamic_ncols=True)
        self._show()

    def _show(self) -> None:
        self.bar.set_postfix_str(f"done {self.done}, failed {self.failed}, running {self.running}")

    def line(self, text: str) -> None:
        if self.enabled:
            self.bar.write(text, file=sys.stderr)

    def start(self, job: dict[str, Any]) -> None:
        self.running += 1
        self.line(f"  start   {job['name']}")
        self._show()

    def finish(self, entry: dict[str, Any]) -> None:
        self.running -= 1
        if entry["status"] == "failed":
            self.failed += 1
            self.line(f"  FAILED  {entry['name']}: {entry['error']}")
        else:
            self.done += 1
            ate = entry.get("ate_rmse_cm")
            ate_text = f"ATE RMSE {ate:.2f} cm" if isinstance(ate, (int, float)) else "no ATE"
            self.line(f"  {entry['status']:<7} {entry['name']}: {ate_text}, {entry.get('wall_s') or 0:.1f} s")
        self.bar.update(1)
        self._show()

    def close(self) -> None:
        self.bar.close()


def _entry(job: Job, status: str, error: str | None = None, wall_s: float | None = None,
           metrics: dict[str, Any] | None = None, worker: dict[str, Any] | None = None) -> dict[str, Any]:
    d = {k: v for k, v in job.to_dict().items() if k != "config"}
    d.update(status=status, error=error, wall_s=wall_s, ate_rmse_cm=(metrics or {}).get("ate_rmse_cm"),
             worker=worker)
    return d


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def _save(out: Path, entries: list[dict[str, Any]], executor: str) -> None:
    """Rewrite ``batch.json`` and the comparison tables (called after every job)."""
    from lrslam.tools.report import write_tables

    _write_atomic(out / MANIFEST, dumps({"executor": executor, "jobs": entries}, indent=2))
    try:
        write_tables(out)
    except Exception as e:  # a table problem must not stop the batch
        log.warning("comparison table not updated: %s", e)


def _read_metrics(out: Path, job: Job) -> dict[str, Any] | None:
    import json

    try:
        return json.loads((out / job.run_dir / "metrics.json").read_text())
    except (OSError, ValueError):
        return None


def run_grid(jobs: list[Job], out: str | Path, executor, progress: bool = True, report: bool = True,
             echo=None) -> BatchOutcome:
    """Run ``jobs`` with ``executor`` into the batch folder ``out``; returns every job's entry.

    Raises InputError (one line) before any job starts when a path is bad; a failing job is an entry with
    ``status: failed`` and its ``error``. ``echo(text)`` prints the skip notes (default: stderr)."""
    echo = echo or (lambda text: print(text, file=sys.stderr))
    out = Path(out)
    # 1. Every path checked before the first job starts; jobs whose run folders are complete are skipped.
    check_jobs(jobs, out)
    out.mkdir(parents=True, exist_ok=True)
    entries, todo = _plan(jobs, out, echo)
    desc = executor.describe()
    if todo:
        echo(f"running {len(todo)} job(s): {desc}")
    _save(out, list(entries.values()), desc)
    # 2. The jobs, batch.json and the tables rewritten as each starts and ends.
    _run_jobs(executor, todo, out, entries, desc, _Progress(len(todo), progress))
    # 3. The HTML report.
    path = _write_report(out) if report else None
    return BatchOutcome(list(entries.values()), path)


def _plan(jobs: list[Job], out: Path, echo) -> tuple[dict[str, dict[str, Any]], list[Job]]:
    """Every job's entry (``skipped`` when its run folder is complete, else ``pending``) and the jobs to run."""
    entries: dict[str, dict[str, Any]] = {}
    todo: list[Job] = []
    for job in jobs:
        state = job_status(job, out)
        if state == "complete":
            m = _read_metrics(out, job) or {}
            entries[job.name] = _entry(job, m.get("status", "ok"), metrics=m) | {"skipped": True}
        else:
            if state == "changed":
                echo(f"note: {job.name}: its run folder holds a run with other settings; running it again")
            entries[job.name] = _entry(job, "pending")
            todo.append(job)
    if len(todo) < len(jobs):
        echo(f"skipping {len(jobs) - len(todo)} job(s) whose run folders are complete")
    return entries, todo


def _run_jobs(executor, todo: list[Job], out: Path, entries: dict[str, dict[str, Any]], desc: str,
              bar: _Progress) -> None:
    """Run ``todo`` with ``executor``, updating ``entries`` in place; jobs an interruption left unfinished are
    marked failed."""
    by_name = {j.name: j for j in todo}

    def on_start(job_dict: dict[str, Any]) -> None:
        entries[job_dict["name"]]["status"] = "running"
        bar.start(job_dict)
        _save(out, list(entries.values()), desc)

    try:
        for res in executor.run([j.to_dict() for j in todo], str(out), on_start):
            job = by_name[res["name"]]
            entries[job.name] = _entry(job, res["status"], res.get("error"), res.get("wall_s"), res.get("metrics"),
                                       res.get("worker"))
            bar.finish(entries[job.name])
            _save(out, list(entries.values()), desc)
    finally:
        bar.close()
        for e in entries.values():
            if e["status"] in ("pending", "running"):
                e["status"], e["error"] = "failed", "not finished (the batch was interrupted)"
        _save(out, list(entries.values()), desc)


def _write_report(out: Path) -> Path | None:
    """``report.html`` (None when it failed: the runs are kept either way)."""
    from lrslam.tools.report import write_report

    try:
        return write_report(out)
    except Exception as e:  # the runs are kept either way
        log.error("report failed: %s", e)
        return None


def run_batch(sequences: list[str | Path], configs: dict[str, dict[str, Any]], out: str | Path,
              progress: bool = True) -> dict[str, dict[str, dict[str, Any]]]:
    """Every sequence under every named config (e.g. ``{"field/s0": {...}, "fused/s0": {...}}``), one after
    another in this process with the threads as they are, into ``OUT/<sequence>/<label>/``; complete runs of
    the same settings are reused. Returns ``{sequence: {label: metrics or {"mode", "error"}}}``."""
    from lrslam.tools.batch_exec import SequentialExecutor

    jobs = []
    for seq in sequences:
        name = Path(seq).resolve().name
        for label, cfg in configs.items():
            jobs.append(Job(name=f"{name}/{label}", sequence=str(seq), sequence_name=name,
                            variant=label.split("/")[0], mode=cfg.get("mode", "fused"), representation=None,
                            seed=int((cfg.get("field") or {}).get("seed", 0)), run_dir=f"{name}/{label}",
                            config=cfg))
    outcome = run_grid(jobs, out, SequentialExecutor(None), progress=progress)
    results: dict[str, dict[str, dict[str, Any]]] = {}
    for job, e in zip(jobs, outcome.entries, strict=True):
        label = job.name.split("/", 1)[1]
        m = _read_metrics(Path(out), job) if e["status"] != "failed" else None
        results.setdefault(job.sequence_name, {})[label] = m or {"mode": job.mode, "error": e["error"]}
    return results
