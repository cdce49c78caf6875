"""Run checkpoints: ``checkpoint.pt`` in the run folder, everything ``lrslam run --resume`` needs to continue a run
after its last checkpointed frame as if it had never stopped.

Written every ``output.checkpoint_every`` keyframes, atomically (temporary file, fsync, ``os.replace``), so a
kill at any moment leaves either the previous checkpoint or the new one, never half of one. The file is a
``torch.save`` of plain data (numpy arrays stored as tensors, read back with ``weights_only=True``: loading a
checkpoint runs no pickled code), with a format name and version. A run that finishes removes it.

What is in it (see :meth:`lrslam.pipeline.runner.SlamRunner.checkpoint`): the field's tensors, keyframe pixels
and generators, the trajectory, the frontend's odometry, the keyframe policy, the pose graph's factors, the loop
closer's keyframes, per-frame records, counters and stage timers, plus the run's own state (frame index, scene
bound, global RNG states, per-frame times, bound coverage) and the resolved config and sequence it belongs to.
There is no optimiser state to save: every mapping round and tracking call starts its own Adam.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

import numpy as np

from lrslam.errors import InputError

__all__ = ["CHECKPOINT_NAME", "CHECKPOINT_TMP", "FORMAT_VERSION", "Checkpointer", "check_resumable",
           "config_difference", "load_checkpoint"]

log = logging.getLogger(__name__)

CHECKPOINT_NAME = "checkpoint.pt"
CHECKPOINT_TMP = ".checkpoint.pt.tmp"
_FORMAT = "lrslam-checkpoint"
FORMAT_VERSION = 1


def _map_leaves(obj: Any, fn) -> Any:
    """``fn`` applied to every leaf of nested dicts / lists / tuples (the containers are rebuilt)."""
    if isinstance(obj, dict):
        return {k: _map_leaves(v, fn) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(_map_leaves(v, fn) for v in obj)
    return fn(obj)


def _to_torch(obj: Any) -> Any:
    """numpy arrays -> CPU tensors (what ``weights_only`` loading accepts), numpy scalars -> Python numbers."""
    import torch

    def leaf(x):
        if isinstance(x, np.ndarray):
            return torch.from_numpy(np.ascontiguousarray(x))
        return x.item() if isinstance(x, np.generic) else x

    return _map_leaves(obj, leaf)


def _to_numpy(obj: Any) -> Any:
    """CPU tensors -> numpy arrays (the inverse of :func:`_to_torch`)."""
    import torch

    return _map_leaves(obj, lambda x: x.numpy() if isinstance(x, torch.Tensor) else x)


class Checkpointer:
    """``checkpoint.pt`` in a run folder, rewritten atomically every ``every`` keyframes (0: never).

    Args:
        out_dir: the run folder. every: keyframes between checkpoints.
    """

    def __init__(self, out_dir: Path, every: int) -> None:
        self.path = Path(out_dir) / CHECKPOINT_NAME
        self._tmp = Path(out_dir) / CHECKPOINT_TMP
        self.every = int(every)

    def due(self, is_keyframe: bool, n_keyframes: int) -> bool:
        """True after a keyframe that completes an interval of ``every`` keyframes (the first frame counts)."""
        return self.every > 0 and is_keyframe and n_keyframes % self.every == 0

    def save(self, state: dict) -> Path:
        """Write ``state`` (plain Python / numpy data) atomically; returns the path."""
        import torch

        with open(self._tmp, "wb") as f:
            torch.save({"format": _FORMAT, "version": FORMAT_VERSION, "state": _to_torch(state)}, f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(self._tmp, self.path)
        return self.path

    def remove(self) -> None:
        """Delete the checkpoint (the run finished)."""
        for p in (self.path, self._tmp):
            p.unlink(missing_ok=True)


def load_checkpoint(path: Path) -> dict:
    """The state saved by :meth:`Checkpointer.save`. InputError (one line naming the file) when it is missing,
    unreadable, corrupt, not an lrslam checkpoint or of another format version."""
    import torch

    path = Path(path)
    if not path.is_file():
        raise InputError(f"--resume: {path}: no checkpoint (a run saves one every output.checkpoint_every "
                         "keyframes); start the run again without --resume")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - a truncated zip, a pickle error, an OS error: all mean "unusable"
        raise InputError(f"--resume: {path}: corrupt or unreadable checkpoint ({type(e).__name__}); start the run "
                         "again without --resume") from None
    if not isinstance(data, dict) or data.get("format") != _FORMAT or not isinstance(data.get("state"), dict):
        raise InputError(f"--resume: {path}: not an lrslam checkpoint")
    if data.get("version") != FORMAT_VERSION:
        raise InputError(f"--resume: {path}: checkpoint format version {data.get('version')!r}, this lrslam reads "
                         f"version {FORMAT_VERSION}; start the run again without --resume")
    return _to_numpy(data["state"])


_MISSING = object()


def config_difference(saved: dict, now: dict, prefix: str = "") -> str | None:
    """The first dotted key (with both values) where two resolved configs differ, or None when equal."""
    for k in list(saved) + [k for k in now if k not in saved]:
        a, b = saved.get(k, _MISSING), now.get(k, _MISSING)
        if isinstance(a, dict) and isinstance(b, dict):
            found = config_difference(a, b, f"{prefix}{k}.")
            if found:
                return found
        elif a != b:
            show = ["(missing)" if v is _MISSING else repr(v) for v in (a, b)]
            return f"{prefix}{k} (run: {show[0]}, now: {show[1]})"
    return None


def check_resumable(path: Path, state: dict, settings: dict, timestamps: np.ndarray) -> None:
    """InputError naming ``path`` unless the checkpoint ``state`` belongs to a run with these resolved
    ``settings`` (config without provenance) over a sequence with these frame ``timestamps`` (N,) seconds."""
    diff = config_difference(state["config"], settings)
    if diff:
        raise InputError(f"--resume: {path}: the run was made with another config: {diff}; resume with the run's "
                         "own settings (e.g. --config <run>/config.yaml) or start a new run")
    saved = np.asarray(state["timestamps"], dtype=np.float64)
    if saved.shape != timestamps.shape or not np.array_equal(saved, timestamps):
        raise InputError(f"--resume: {path}: the sequence differs from the run's ({len(saved)} frames then, "
                         f"{len(timestamps)} now, or other timestamps)")
