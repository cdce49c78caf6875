"""``lrslam view RUN_DIR``: replay a finished run folder into a Rerun viewer (or an ``.rrd`` file)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

__all__ = ["view"]


def view(
    run_dir: Annotated[Path, typer.Argument(help="A run folder written by lrslam run.")],
    rrd: Annotated[Optional[Path], typer.Option("--rrd", help="Record to this .rrd file instead of spawning a "
                                                "viewer (headless machines; open it later with `rerun FILE`).")]
    = None,
    images: Annotated[bool, typer.Option("--images", help="Also every frame's RGB and depth, read from the run's "
                                         "sequence (when it is still where config.yaml says).")] = False,
) -> None:
    """Draw a finished run in Rerun: camera path, trajectories (run, seeds, frontend, ground truth when the
    sequence is readable), keyframes, mesh, running ATE and metrics. Needs ``pip install 'lrslam\\[viewer]'``.

    Exit code 2: not a run folder, or rerun-sdk missing."""
    from lrslam.logs import setup_console_logging
    from lrslam.pipeline.viewer_replay import read_run_folder, replay
    from lrslam.pipeline.viewer_stream import RerunStream

    setup_console_logging()
    read_run_folder(run_dir)            # a wrong folder fails before a viewer starts
    with RerunStream(spawn=rrd is None, rrd=rrd, name=f"lrslam {run_dir.resolve().name}") as stream:
        run = replay(run_dir, stream, images=images)
    where = f"wrote {rrd}" if rrd is not None else "sent to the Rerun viewer"
    typer.echo(f"{run_dir}: {len(run.poses)} frames, {len(run.keyframe_ids)} keyframes; {where}")
