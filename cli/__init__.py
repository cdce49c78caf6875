"""The ``lrslam`` command line (the top of the stack: nothing below imports it).

:mod:`lrslam.cli.app` holds the typer app and the one error path; the commands' bodies live in
:mod:`lrslam.cli.commands` (run, params, batch, report), :mod:`lrslam.cli.synth` and :mod:`lrslam.cli.evaluate`.
"""

from lrslam.cli.app import EXIT_DEGRADED, EXIT_USAGE, app, main

__all__ = ["app", "main", "EXIT_USAGE", "EXIT_DEGRADED"]
