"""Console logging for command-line entry points: warnings and errors on stderr, in one format.

Run folders get their own INFO-level ``run.log`` (see :mod:`lrslam.pipeline.run`); the console handler keeps
its own WARNING threshold so that those INFO records do not reach the terminal (``verbose`` shows them).
Lines go through ``tqdm.write`` so they print above a running progress bar instead of breaking it.
"""

from __future__ import annotations

import logging
import sys

__all__ = ["setup_console_logging"]

_FORMAT = "%(levelname)s %(name)s: %(message)s"


class _TqdmHandler(logging.StreamHandler):
    """A stderr handler that writes through ``tqdm.write`` (safe next to progress bars)."""

    def emit(self, record: logging.LogRecord) -> None:
        try:
            from tqdm import tqdm

            tqdm.write(self.format(record), file=sys.stderr)  # the current stderr (tests swap it)
        except Exception:
            self.handleError(record)


def setup_console_logging(verbose: bool = False) -> logging.Handler:
    """Install (once) a stderr handler on the root logger at WARNING (INFO with ``verbose``); returns it."""
    root = logging.getLogger()
    level = logging.INFO if verbose else logging.WARNING
    for h in root.handlers:
        if getattr(h, "_lrslam_console", False):
            h.setLevel(level)
            return h
    h = _TqdmHandler()
    h.setFormatter(logging.Formatter(_FORMAT))
    h.setLevel(level)
    h._lrslam_console = True  # type: ignore[attr-defined]
    root.addHandler(h)
    if root.level == logging.NOTSET or root.level > level:
        root.setLevel(level)
    return h
