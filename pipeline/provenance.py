"""Where a run came from: package version, git commit, command line, presets and sequence.

Stored under ``provenance:`` in a run's ``config.yaml``; :mod:`lrslam.pipeline.config_source` drops that
section when the file is fed back with ``--config``.
"""

from __future__ import annotations

import platform
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

__all__ = ["provenance", "git_commit", "set_command_line"]

_COMMAND_LINE: list[str] | None = None


def set_command_line(argv: list[str]) -> None:
    """Record the command line of this process (called by :func:`lrslam.cli.main`)."""
    global _COMMAND_LINE
    _COMMAND_LINE = list(argv)


def git_commit() -> str | None:
    """The commit of the source tree lrslam is imported from (``+dirty`` when it has changes), or None."""
    here = Path(__file__).resolve().parent
    try:
        rev = subprocess.run(["git", "-C", str(here), "rev-parse", "HEAD"], capture_output=True, text=True,
                             timeout=5)
        if rev.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", str(here), "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, timeout=5)
    except (OSError, subprocess.SubprocessError):
        return None
    return rev.stdout.strip() + ("+dirty" if dirty.stdout.strip() else "")


def provenance(sequence: str | Path, reader: str, presets: dict[str, str | None] | None = None) -> dict[str, Any]:
    """The ``provenance`` record of a run over ``sequence`` read by ``reader``."""
    from lrslam import __version__

    argv = _COMMAND_LINE if _COMMAND_LINE is not None else ["lrslam", *sys.argv[1:]]
    return {
        "lrslam_version": __version__,
        "git_commit": git_commit(),
        "command": shlex.join(argv),
        "presets": dict(presets or {}),
        "sequence": str(Path(sequence).resolve()),
        "reader": reader,
        "python": platform.python_version(),
        "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
    }
