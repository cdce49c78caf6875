"""Ctrl-C and SIGTERM as one exception, so that a run saves what it tracked before the process exits.

:func:`handle_termination` turns SIGINT and SIGTERM into :class:`Interrupted` (a ``BaseException``, so neither
library ``except Exception`` blocks nor typer's own Ctrl-C handling swallow it). The run loop saves its partial
trajectory on any ``BaseException``; :func:`lrslam.cli.main` then exits with ``128 + signal number`` (130 for
Ctrl-C, 143 for SIGTERM), as a shell does.
"""

from __future__ import annotations

import signal
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["Interrupted", "handle_termination"]


class Interrupted(BaseException):
    """The process got SIGINT or SIGTERM; ``exit_code`` is ``128 + signum``."""

    def __init__(self, signum: int) -> None:
        super().__init__(f"interrupted by {signal.Signals(signum).name}")
        self.signum = signum
        self.exit_code = 128 + signum


def _raise(signum: int, _frame) -> None:
    raise Interrupted(signum)


@contextmanager
def handle_termination() -> Iterator[None]:
    """While inside, SIGINT and SIGTERM raise :class:`Interrupted`; the previous handlers come back after."""
    old = {s: signal.signal(s, _raise) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        yield
    finally:
        for s, h in old.items():
            signal.signal(s, h)
