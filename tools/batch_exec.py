"""Where the jobs of a batch run: as Ray tasks (local Ray started for the batch, or a cluster given by
address) or, without Ray, one after another in this process.

Each job gets ``cpus_per_job`` CPUs: Ray reserves them (``num_cpus``) and the job's thread pools are set to
match (``OMP_NUM_THREADS`` / ``MKL_NUM_THREADS`` / ``OPENBLAS_NUM_THREADS`` / ``NUMBA_NUM_THREADS`` in the
worker environment, ``torch.set_num_threads`` inside the task; the numba kernels follow torch's count), so
jobs side by side never oversubscribe the machine. With CUDA, local Ray shares the GPUs between the workers
(``num_gpus`` per job); on a cluster ``gpus_per_job`` says how much GPU each job asks for.

A job never raises: :func:`run_job` returns a result dict with ``status`` (the run's ``ok`` / ``degraded``,
or ``failed`` with ``error``); a Ray worker that dies is reported the same way.
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from lrslam.errors import InputError

__all__ = ["run_job", "thread_env", "ray_available", "SequentialExecutor", "RayExecutor", "make_executor"]

log = logging.getLogger(__name__)

THREAD_VARS = ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS", "NUMBA_NUM_THREADS")


def thread_env(cpus: int) -> dict[str, str]:
    """Environment variables that cap every thread pool of a job at ``cpus`` threads."""
    return {k: str(cpus) for k in THREAD_VARS}


def _worker_info() -> dict[str, Any]:
    import torch

    return {"pid": os.getpid(), "torch_threads": torch.get_num_threads(),
            **{k: os.environ.get(k) for k in THREAD_VARS}}


def run_job(job: dict[str, Any], batch_dir: str, cpus: int | None = None) -> dict[str, Any]:
    """Run one job (a :class:`~lrslam.tools.batch_grid.Job` as a dict) into ``batch_dir/<run_dir>``.

    ``cpus``: torch threads for the job (the numba kernels follow torch; None: leave them), restored after it.
    Returns ``{"name", "status", "wall_s", "worker", "error"?, "metrics"?}`` (``worker``: pid, torch threads and
    the thread variables the job ran with); never raises for a failed run (``error``: ``"<Type>: <message>"``)."""
    import torch

    from lrslam.pipeline.config import RunConfig
    from lrslam.pipeline.run import run_sequence

    t0 = time.perf_counter()
    out: dict[str, Any] = {"name": job["name"]}
    threads = torch.get_num_threads()
    try:
        if cpus:
            torch.set_num_threads(max(1, int(cpus)))
        out["worker"] = _worker_info()
        cfg = RunConfig.model_validate(job["config"])
        res = run_sequence(job["sequence"], cfg, Path(batch_dir) / job["run_dir"], progress=False,
                           presets=job.get("presets"))
        out.update(status=res.metrics.get("status", "ok"), metrics=res.metrics)
    except Exception as e:  # one failing job must not lose the others
        log.error("job %s failed: %s: %s", job["name"], type(e).__name__, e)
        out.update(status="failed", error=f"{type(e).__name__}: {' '.join(str(e).split())}")
        _note_failure(Path(batch_dir) / job["run_dir"], out["error"])
    finally:
        torch.set_num_threads(threads)
    out["wall_s"] = round(time.perf_counter() - t0, 2)
    return out


def _note_failure(run_dir: Path, error: str) -> None:
    """Append the job's error to its run.log (the run's own log stops before the exception reaches the batch),
    so a report of the run folders alone can say why the run failed."""
    if (run_dir / "run.log").is_file():
        stamp = time.strftime("%Y-%m-%d %H:%M:%S")
        with open(run_dir / "run.log", "a") as f:
            f.write(f"{stamp},000 ERROR lrslam.tools.batch: job failed: {error}\n")


def ray_available() -> bool:
    """Whether Ray can be imported (the ``distributed`` extra is installed)."""
    try:
        import ray  # noqa: F401
    except ImportError:
        return False
    return True


Callback = Callable[[dict[str, Any]], None]


@dataclass
class SequentialExecutor:
    """Runs jobs one after another in this process, each with ``cpus_per_job`` threads (None: as they are)."""

    cpus_per_job: int | None = 1
    kind: str = "in-process"

    def describe(self) -> str:
        threads = f"{self.cpus_per_job} thread(s)" if self.cpus_per_job else "default threads"
        return f"sequential in-process, {threads} per job"

    def run(self, jobs: list[dict[str, Any]], batch_dir: str, on_start: Callback) -> Iterator[dict[str, Any]]:
        """Yield each job's result as it finishes; ``on_start(job)`` is called when a job starts."""
        for job in jobs:
            on_start(job)
            yield run_job(job, batch_dir, self.cpus_per_job)

    def close(self) -> None:
        pass


def _ray_task(job: dict[str, Any], batch_dir: str, cpus: int) -> dict[str, Any]:
    """The Ray task body (module level, so workers import it from the installed package)."""
    return run_job(job, batch_dir, cpus)


@dataclass
class RayExecutor:
    """Runs jobs as Ray tasks with ``num_cpus=cpus_per_job`` (and ``num_gpus`` with CUDA).

    ``address`` None starts a local Ray for the batch with ``workers * cpus_per_job`` CPUs (no dashboard, worker
    output not forwarded); otherwise connects to that cluster (``"auto"``: the one running on this machine).
    At most as many jobs are in flight as the cluster has CPU slots, so "running" means running."""

    cpus_per_job: int = 1
    workers: int = 1
    address: str | None = None
    gpus_per_job: float | None = None
    kind: str = "ray"

    def __post_init__(self) -> None:
        import ray

        self._ray = ray
        env = {"env_vars": thread_env(self.cpus_per_job)}
        quiet = dict(log_to_driver=False, logging_level=logging.ERROR, runtime_env=env)
        try:
            if self.address:
                ray.init(address=self.address, **quiet)
                if self.gpus_per_job is None:
                    self.gpus_per_job = 0.0
            else:
                n_gpus = _cuda_devices()
                if self.gpus_per_job is None:
                    self.gpus_per_job = n_gpus / self.workers if n_gpus else 0.0
                ray.init(num_cpus=self.workers * self.cpus_per_job, num_gpus=n_gpus, include_dashboard=False,
                         object_store_memory=100 * 1024**2, **quiet)
        except Exception as e:  # Ray raises plain Exception too (e.g. "node timed out during startup")
            where = f"--address {self.address}: cannot reach the Ray cluster" if self.address else \
                "local Ray did not start"
            raise InputError(f"{where} ({' '.join(str(e).split())[:300]}); --sequential runs the batch without "
                             "Ray") from None
        cpus = ray.cluster_resources().get("CPU", 0)
        self.slots = max(1, int(cpus // self.cpus_per_job))
        self._task = ray.remote(_ray_task).options(num_cpus=self.cpus_per_job, num_gpus=self.gpus_per_job or 0,
                                                   max_retries=0)

    def describe(self) -> str:
        where = f"Ray cluster {self.address}" if self.address else "local Ray"
        gpu = f", {self.gpus_per_job:g} GPU" if self.gpus_per_job else ""
        return f"{where}: {self.slots} job(s) at a time, {self.cpus_per_job} CPU{gpu} per job"

    def run(self, jobs: list[dict[str, Any]], batch_dir: str, on_start: Callback) -> Iterator[dict[str, Any]]:
        """Yield each job's result as it finishes (any order); ``on_start(job)`` when a job is submitted."""
        ray = self._ray
        queue = list(jobs)
        pending: dict[Any, dict[str, Any]] = {}
        while queue or pending:
            while queue and len(pending) < self.slots:
                job = queue.pop(0)
                on_start(job)
                pending[self._task.remote(job, batch_dir, self.cpus_per_job)] = job
            done, _ = ray.wait(list(pending), num_returns=1)
            job = pending.pop(done[0])
            try:
                yield ray.get(done[0])
            except ray.exceptions.RayError as e:  # the worker died (killed, out of memory, crashed)
                msg = " ".join(str(e).split())
                yield {"name": job["name"], "status": "failed", "error": f"{type(e).__name__}: {msg[:500]}",
                       "wall_s": None}

    def close(self) -> None:
        self._ray.shutdown()


def _cuda_devices() -> int:
    try:
        import torch

        return torch.cuda.device_count() if torch.cuda.is_available() else 0
    except Exception:  # no usable torch CUDA: CPU jobs
        return 0


def make_executor(use_ray: bool | None, cpus_per_job: int = 1, workers: int | None = None,
                  address: str | None = None, gpus_per_job: float | None = None,
                  note: Callable[[str], None] = print):
    """The executor for a batch. ``use_ray``: True requires Ray, False runs in-process, None uses Ray when it
    is installed (else in-process, with a one-line ``note``). ``workers`` (local Ray): jobs at a time, default
    the machine's CPUs // ``cpus_per_job``."""
    if cpus_per_job < 1:
        raise InputError(f"--cpus-per-job must be >= 1, got {cpus_per_job}")
    if workers is not None and workers < 1:
        raise InputError(f"--workers must be >= 1, got {workers}")
    if use_ray is False:
        return SequentialExecutor(cpus_per_job)
    if not ray_available():
        if use_ray or address:
            raise InputError("Ray is not installed: pip install 'lrslam[distributed]' (or run without --address)")
        note("note: Ray is not installed (pip install 'lrslam[distributed]'); running the jobs one after another "
             "in this process")
        return SequentialExecutor(cpus_per_job)
    workers = workers or max(1, (os.cpu_count() or 1) // cpus_per_job)
    return RayExecutor(cpus_per_job, workers, address, gpus_per_job)
