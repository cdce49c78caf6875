"""The ``lrslam`` command line: ``synth``, ``eval ate|mesh``, ``run``, ``batch``, ``params``.

Each command's body lives next to the code it drives (``*/cli.py`` modules); heavy libraries (torch, open3d,
gtsam) are imported inside the command functions so ``lrslam --help`` stays fast. Known input errors are
printed as one ``error: ...`` line with exit code 2 instead of a traceback.
"""

from __future__ import annotations

import sys

import typer

from lrslam.errors import InputError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="LRSLAM dense RGB-D SLAM: low-rank SDF fields + Open3D frontend + GTSAM backend.")


def _register() -> None:
    from lrslam.frontend.synthetic.cli import synth
    from lrslam.pipeline.cli import batch, params, run
    from lrslam.pipeline.evaluation.cli import eval_app

    app.command("synth")(synth)
    app.add_typer(eval_app, name="eval")
    app.command("run")(run)
    app.command("params")(params)
    app.command("batch")(batch)


def main() -> None:
    """Console entry point."""
    _register()
    try:
        app(standalone_mode=False)
    except (InputError, FileNotFoundError) as e:
        typer.echo(f"error: {e}", err=True)
        sys.exit(2)
    except SystemExit:
        raise
    except typer.Exit as e:
        sys.exit(e.exit_code)
    except Exception as e:  # click exceptions (bad usage) keep their own formatting
        import click

        if isinstance(e, click.ClickException):
            e.show()
            sys.exit(e.exit_code)
        if isinstance(e, click.exceptions.Abort):
            sys.exit(1)
        raise
