"""The ``lrslam`` command line: ``synth``, ``eval ate|mesh``, ``run``, ``view``, ``batch``, ``report``, ``params``.

Each command's body lives next to the code it drives (``*/cli.py`` modules); heavy libraries (torch, open3d,
gtsam) are imported inside the command functions so ``lrslam --help`` stays fast.

One error path (:func:`main`): every usage, config, input and I/O error is printed as one ``error: ...`` line on
stderr with exit code 2, no traceback (``--debug`` anywhere on the command line, or ``LRSLAM_DEBUG=1``, re-raises
it with its traceback). Exit codes: 0 ok, 1 internal error or a failed batch job, 2 bad usage or input,
3 a run that finished degraded (see :mod:`lrslam.pipeline.sanity`), 130 Ctrl-C, 143 SIGTERM.
"""

from __future__ import annotations

import os
import sys
from typing import Optional

import typer
from typer._click import exceptions as click_exc  # typer bundles its own click: catch its classes, not click's

from lrslam import __version__
from lrslam.errors import InputError
from lrslam.signals import Interrupted, handle_termination

__all__ = ["app", "main", "EXIT_USAGE", "EXIT_DEGRADED"]

EXIT_USAGE = 2
EXIT_DEGRADED = 3

app = typer.Typer(add_completion=False, no_args_is_help=True, context_settings={"help_option_names": ["-h", "--help"]},
                  help="LRSLAM dense RGB-D SLAM: low-rank SDF fields + Open3D frontend + GTSAM backend.")


def _show_version(value: bool) -> None:
    if value:
        typer.echo(f"lrslam {__version__}")
        raise typer.Exit(0)


@app.callback()
def _root(
    version: Optional[bool] = typer.Option(None, "--version", is_eager=True, callback=_show_version,
                                           help="Print the version and exit."),
    debug: bool = typer.Option(False, "--debug", help="Show the Python traceback of an error (anywhere on the "
                                                      "command line)."),
) -> None:
    """LRSLAM dense RGB-D SLAM: low-rank SDF fields + Open3D frontend + GTSAM backend."""


def _register() -> None:
    if getattr(app, "_lrslam_registered", False):
        return
    from lrslam.cli.synth import synth
    from lrslam.cli.commands import batch, params, report, run
    from lrslam.cli.evaluate import eval_app
    from lrslam.cli.view import view

    app.command("synth")(synth)
    app.add_typer(eval_app, name="eval")
    app.command("run")(run)
    app.command("view")(view)
    app.command("params")(params)
    app.command("batch")(batch)
    app.command("report")(report)
    app._lrslam_registered = True  # type: ignore[attr-defined]


def _one_line(text: str) -> str:
    return " ".join(str(text).split())


def _fail(message: str, code: int = EXIT_USAGE) -> int:
    typer.echo(f"error: {_one_line(message)}", err=True)
    return code


def _exit_code(e: BaseException) -> int:
    """Print the one-line message for ``e`` and return the exit code (re-raises what is not ours to handle)."""
    from pydantic import ValidationError

    if isinstance(e, Interrupted):
        typer.echo(f"lrslam: {e} (what was tracked is saved in the run folder)", err=True)
        return e.exit_code
    if isinstance(e, KeyboardInterrupt):
        return 130
    if isinstance(e, click_exc.NoArgsIsHelpError):
        typer.echo(e.format_message())
        return 0
    if isinstance(e, click_exc.UsageError):
        where = f"{e.ctx.command_path}: " if e.ctx is not None else ""
        return _fail(where + e.format_message())
    if isinstance(e, click_exc.ClickException):
        return _fail(e.format_message())
    if isinstance(e, typer.Abort):
        return _fail("aborted", 1)
    if isinstance(e, (InputError, FileNotFoundError)):
        return _fail(str(e))
    if isinstance(e, ValidationError):
        err = e.errors()[0]
        return _fail(f"invalid value at {'.'.join(map(str, err['loc'])) or '<root>'}: {err['msg']}")
    if isinstance(e, OSError):
        name = f"{e.filename}: " if e.filename else ""
        return _fail(f"{name}{e.strerror or e}")
    if isinstance(e, Exception):
        return _fail(f"internal error ({type(e).__name__}: {e}); rerun with --debug for the traceback", 1)
    raise e


def main(argv: list[str] | None = None) -> None:
    """Console entry point: run the command line ``argv`` (default ``sys.argv[1:]``) and exit with its code."""
    args = list(sys.argv[1:] if argv is None else argv)
    head = args[: args.index("--")] if "--" in args else args
    debug = "--debug" in head or os.environ.get("LRSLAM_DEBUG", "") not in ("", "0")
    if "--debug" in head:
        args.remove("--debug")
    _register()
    from lrslam.pipeline.provenance import set_command_line

    set_command_line(["lrslam", *args])
    try:
        with handle_termination():
            rv = app(args=args, prog_name="lrslam", standalone_mode=False)
        code = rv if isinstance(rv, int) else 0
    except SystemExit:
        raise
    except typer.Exit as e:
        code = e.exit_code
    except BaseException as e:  # noqa: BLE001 - the one place errors become exit codes
        if debug and not isinstance(e, click_exc.NoArgsIsHelpError):
            raise
        code = _exit_code(e)
    sys.exit(code)
