"""The job grid of a batch: sequences x modes x seeds x representations, one run folder per job.

A sequence argument is ``PATH`` or ``PATH:PRESET`` (the dataset preset or YAML file for that sequence only; a
path that exists as given is never split at a colon). Job names are ``<sequence>/<variant>/s<seed>`` where
``<variant>`` is the mode, or ``<mode>-<representation>`` when representations are named; sequences that share a
folder name are told apart by their parent folders (``a-room``, ``b-room``). A mode whose parts build no field
(``parts.refiner: none``, e.g. ``frontend``) uses neither the field's seed nor a representation: it runs once per
sequence (``<sequence>/<mode>/s0``).

Everything that can be checked before the first job starts is checked by :func:`check_jobs` (sequence folders
and their layout, run folders), so a bad path is a one-line error, not a failure halfway through a batch.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from lrslam.errors import InputError

__all__ = ["Job", "SequenceSpec", "parse_sequence", "name_sequences", "expand_grid", "check_jobs", "is_complete",
           "job_status"]

MODES = ("field", "frontend", "fused")
COMPLETE_STATUSES = ("ok", "degraded")


@dataclass(frozen=True)
class SequenceSpec:
    """A sequence folder, the dataset preset (name or YAML path) it runs with, and its name in the batch."""

    path: str
    preset: str | None = None
    name: str = ""


@dataclass(frozen=True)
class Job:
    """One run of a batch; plain values only, so it travels to a Ray worker as is.

    ``config``: the resolved run config (``RunConfig.model_dump(mode="json")``); ``run_dir``: the job's run
    folder relative to the batch folder; ``presets``: the preset names, for the run's provenance record."""

    name: str
    sequence: str
    sequence_name: str
    variant: str
    mode: str
    representation: str | None
    seed: int
    run_dir: str
    config: dict[str, Any] = field(repr=False)
    presets: dict[str, str | None] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def parse_sequence(arg: str, default_preset: str | None = None) -> SequenceSpec:
    """``PATH`` or ``PATH:PRESET`` -> :class:`SequenceSpec` (name filled in by :func:`expand_grid`)."""
    text = str(arg)
    if not Path(text).exists() and ":" in text:
        head, _, tail = text.rpartition(":")
        if head and tail:
            return SequenceSpec(head, tail)
    return SequenceSpec(text, default_preset)


def _safe(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "seq"


def name_sequences(specs: list[SequenceSpec]) -> list[SequenceSpec]:
    """Give every sequence a unique folder-safe name: its folder name, with as many parent folders as it takes
    to tell apart sequences that share it, and the preset for one folder given with two presets."""
    resolved = [Path(s.path).expanduser().resolve() for s in specs]
    seen: dict[tuple[Path, str | None], str] = {}
    for s, r in zip(specs, resolved, strict=True):
        key = (r, s.preset)
        if key in seen:
            raise InputError(f"sequence {s.path} is given twice" + (f" with preset {s.preset}" if s.preset else ""))
        seen[key] = s.path
    names = []
    for r in resolved:
        depth = 1
        while True:
            parts = r.parts[-depth:]
            clash = [o for o in resolved if o != r and o.parts[-depth:] == parts]
            if not clash or depth >= len(r.parts):
                break
            depth += 1
        names.append(_safe("-".join(r.parts[-depth:])))
    out = []
    for s, r, n in zip(specs, resolved, names, strict=True):
        twins = [t for t, rr in zip(specs, resolved, strict=True) if rr == r]
        out.append(SequenceSpec(s.path, s.preset, _safe(f"{n}-{s.preset}") if len(twins) > 1 else n))
    return out


def expand_grid(sequences: list[str], modes: list[str], seeds: int = 1, representations: list[str] | None = None,
                preset: str | None = None, overrides: list[str] | None = None) -> list[Job]:
    """The jobs of a batch, in order sequence, mode, representation, seed.

    ``sequences``: ``PATH`` or ``PATH:PRESET`` strings; ``preset``: the dataset preset of sequences that name
    none; ``seeds``: the field seeds ``0 .. seeds-1`` (config key ``field.seed``); ``representations``:
    representation preset names (None: the preset's own); ``overrides``: ``key=value`` for every job.
    Raises InputError (one line) on an unknown mode, preset, representation or key.
    """
    from lrslam.pipeline.config_source import load_run_config

    if not sequences:
        raise InputError("give at least one sequence folder")
    bad = [m for m in modes if m not in MODES]
    if bad or not modes:
        raise InputError(f"--modes: unknown mode {bad[0]!r}: use field, frontend or fused" if bad else
                         "--modes: give at least one mode")
    if seeds < 1:
        raise InputError(f"--seeds must be >= 1, got {seeds}")
    reprs: list[str | None] = list(dict.fromkeys(representations)) if representations else [None]
    specs = name_sequences([parse_sequence(s, preset) for s in sequences])
    jobs: list[Job] = []
    for spec in specs:
        for mode in dict.fromkeys(modes):
            # a run without a field neither uses a representation nor a seed (its odometry is deterministic)
            with_field = load_run_config(spec.preset, None, overrides=overrides, mode=mode).cfg.parts.refiner == "field"
            grid = [(r, s) for r in reprs for s in range(seeds)] if with_field else [(None, 0)]
            for rep, seed in grid:
                ov = list(overrides or []) + ([f"field.seed={seed}"] if with_field else [])
                loaded = load_run_config(spec.preset, rep, overrides=ov, mode=mode)
                variant = mode if rep is None else f"{mode}-{rep}"
                name = f"{spec.name}/{variant}/s{seed}"
                jobs.append(Job(name=name, sequence=spec.path, sequence_name=spec.name, variant=variant, mode=mode,
                                representation=rep, seed=seed, run_dir=name,
                                config=loaded.cfg.model_dump(mode="json"), presets=loaded.presets))
    return jobs


def check_jobs(jobs: list[Job], out: Path) -> None:
    """Every path of the batch, before the first job starts: the batch folder, each sequence folder (it exists
    and its layout is known to the reader its config names) and each job's run folder. InputError (one line,
    naming the path) on the first problem."""
    import json

    from lrslam.datasets import open_sequence
    from lrslam.pipeline.config import RunConfig
    from lrslam.pipeline.run_folder import check_output_folder, check_run_folder

    check_output_folder(out)
    opened: set[str] = set()
    for job in jobs:
        cfg = RunConfig.model_validate(job.config)
        key = json.dumps([job.sequence, cfg.dataset.model_dump(mode="json")], sort_keys=True)
        if key not in opened:
            try:
                open_sequence(job.sequence, reader=cfg.dataset.reader, options=cfg.reader_options())
            except InputError as e:
                msg = str(e)
                raise InputError(msg if job.sequence in msg else f"sequence {job.sequence}: {msg}") from None
            opened.add(key)
        check_run_folder(out / job.run_dir)


def _settings(record: dict[str, Any]) -> dict[str, Any]:
    """A config record without what differs between equal runs (provenance, the reader actually used)."""
    from lrslam.pipeline.config import RECORD_KEYS

    rec = {k: v for k, v in record.items() if k not in RECORD_KEYS}
    rec["dataset"] = {k: v for k, v in (rec.get("dataset") or {}).items() if k != "reader"}
    return rec


def job_status(job: Job, out: Path) -> str:
    """``complete`` (metrics.json with status ok / degraded, trajectory.txt, config.yaml with the job's
    settings), ``changed`` (a complete run with other settings), or ``todo``."""
    import json

    from lrslam.pipeline.config import RunConfig
    from lrslam.pipeline.run_folder import read_run_record

    d = out / job.run_dir
    try:
        metrics = json.loads((d / "metrics.json").read_text())
    except (OSError, ValueError):
        return "todo"
    record = read_run_record(d)
    if not (isinstance(metrics, dict) and metrics.get("status") in COMPLETE_STATUSES
            and (d / "trajectory.txt").is_file() and record is not None):
        return "todo"
    want = _settings(RunConfig.model_validate(job.config).resolved())
    return "complete" if _settings(record) == want else "changed"


def is_complete(job: Job, out: Path) -> bool:
    """Whether the job's run folder holds a complete run of the job's settings (a re-run skips it)."""
    return job_status(job, out) == "complete"
