"""A run folder is never mixed: it holds the outputs of one run only.

:func:`prepare_run_folder` refuses a ``--out`` that is a file, lies below a file, or is a non-empty folder that
is not a previous lrslam run folder (unless ``overwrite``), then deletes the outputs of any earlier run in it, so
a run that fails midway never leaves an older run's trajectory, metrics or mesh beside its own config.
:class:`PartialTrajectory` writes ``trajectory_partial.txt`` atomically (temporary file + ``os.replace``), so
even SIGKILL leaves a complete TUM file of the frames tracked up to the last save.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import numpy as np

from lrslam.errors import InputError
from lrslam.pipeline.checkpoint import CHECKPOINT_NAME, CHECKPOINT_TMP
from lrslam.trajectory_io import write_tum

__all__ = ["RUN_OUTPUTS", "check_output_folder", "check_run_folder", "prepare_run_folder", "PartialTrajectory",
           "PARTIAL_NAME"]

log = logging.getLogger(__name__)

PARTIAL_NAME = "trajectory_partial.txt"
_PARTIAL_TMP = ".trajectory_partial.txt.tmp"
# Every file a run writes (trajectory_*.txt covers the seed, frontend, online, unsmoothed and partial trajectories).
RUN_OUTPUTS = ("config.yaml", "trajectory.txt", "keyframes.txt", "metrics.json", "mesh.ply", "trajectory.png",
               "run.log", _PARTIAL_TMP, CHECKPOINT_NAME, CHECKPOINT_TMP)
_OUTPUT_GLOBS = ("trajectory_*.txt",)
_KEPT = ("sequence",)  # ``lrslam run --demo`` generates its sequence inside the run folder


def check_output_folder(out: Path, flag: str = "--out") -> Path:
    """InputError when ``out`` is a file or lies below a file; returns ``out``."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError(f"{flag} {out}: is a file, not a folder")
    for parent in out.parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(f"{flag} {out}: {parent} is a file, not a folder")
            break
    return out


def _is_output(p: Path) -> bool:
    return p.name in RUN_OUTPUTS or any(p.match(g) for g in _OUTPUT_GLOBS)


def _is_run_folder(out: Path) -> bool:
    """Every entry is a run output (or the demo sequence), or ``config.yaml`` is an lrslam run record."""
    entries = list(out.iterdir())
    if all(_is_output(p) or p.name in _KEPT for p in entries):
        return True
    data = read_run_record(out)
    return data is not None and ("provenance" in data or "sequence" in data)


def read_run_record(run_dir: Path) -> dict | None:
    """A run folder's ``config.yaml`` (settings + provenance) as a mapping; None when it is missing, unreadable
    or not a YAML mapping."""
    from lrslam.config import load_yaml

    try:
        return load_yaml(Path(run_dir) / "config.yaml")
    except InputError:
        return None


def check_run_folder(out: Path, overwrite: bool = False) -> Path:
    """Raise InputError unless ``out`` can take a run (see the module docstring); changes nothing."""
    out = check_output_folder(out)
    if out.is_dir() and any(out.iterdir()) and not overwrite and not _is_run_folder(out):
        names = sorted(p.name for p in out.iterdir())
        shown = ", ".join(names[:4]) + (", ..." if len(names) > 4 else "")
        raise InputError(f"--out {out}: folder is not empty and is not an lrslam run folder (holds {shown}); "
                         "choose another folder or pass --overwrite")
    return out


def prepare_run_folder(out: Path, overwrite: bool = False) -> Path:
    """Check ``out`` (:func:`check_run_folder`), create it, and delete the outputs of an earlier run in it."""
    out = check_run_folder(Path(out), overwrite)
    try:
        out.mkdir(parents=True, exist_ok=True)
        stale = [p for p in out.iterdir() if p.is_file() and _is_output(p)]
        for p in stale:
            p.unlink()
    except OSError as e:
        raise InputError(f"--out {out}: {e.strerror or e}") from None
    if stale:
        log.info("%s: removed %d outputs of an earlier run (%s)", out, len(stale), ", ".join(p.name for p in stale))
    return out


class PartialTrajectory:
    """``trajectory_partial.txt`` (TUM) in a run folder, rewritten atomically every ``every`` frames.

    Args:
        out_dir: the run folder. timestamps: (N,) seconds of the sequence's frames. every: frames between saves.
    """

    def __init__(self, out_dir: Path, timestamps: np.ndarray, every: int = 10) -> None:
        if every < 1:
            raise InputError(f"--partial-every must be >= 1 frame, got {every}")
        self.path = Path(out_dir) / PARTIAL_NAME
        self._tmp = Path(out_dir) / _PARTIAL_TMP
        self.timestamps = np.asarray(timestamps, dtype=np.float64)
        self.every = every

    def due(self, n_done: int) -> bool:
        """True when ``n_done`` frames (1-based count) complete a save interval."""
        return n_done % self.every == 0

    def save(self, poses: np.ndarray) -> Path:
        """Write poses (n, 4, 4) ``T_w_c`` of the first n frames, atomically."""
        poses = np.asarray(poses, dtype=np.float64)
        write_tum(self._tmp, self.timestamps[: len(poses)], poses,
                  header=f"lrslam partial trajectory T_w_c: {len(poses)} of {len(self.timestamps)} frames")
        os.replace(self._tmp, self.path)
        return self.path

    def remove(self) -> None:
        """Delete the partial trajectory (the run finished and wrote ``trajectory.txt``)."""
        for p in (self.path, self._tmp):
            p.unlink(missing_ok=True)
