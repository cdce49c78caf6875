"""``lrslam synth OUT``: write a synthetic RGB-D sequence (TUM layout + scene.yaml + gt_mesh.ply)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from lrslam.errors import InputError

__all__ = ["synth"]


def synth(
    out: Annotated[Path, typer.Argument(help="Output folder (new, empty, or a previous synthetic sequence).")],
    scene: Annotated[str, typer.Option(help="Scene: room | small_room | cluttered | empty.")] = "room",
    trajectory: Annotated[str, typer.Option(help="Camera path: circle | helix | random_walk | loop | orbit (with --step-cm 6 --step-deg 2.4: a fast camera).")] = "circle",
    frames: Annotated[int, typer.Option(help="Number of frames (30 Hz, ~1 cm and ~1 deg per frame).")] = 60,
    seed: Annotated[int, typer.Option(help="Seed of scene layout, textures, trajectory and noise.")] = 0,
    width: Annotated[int, typer.Option(help="Image width, pixels (fx = fy = 260 * width / 320).")] = 320,
    height: Annotated[int, typer.Option(help="Image height, pixels (e.g. 240 or 480).")] = 240,
    noise: Annotated[str, typer.Option(
        help="Sensor noise: none | gaussian (depth N(0, depth-sigma)) | kinect (sigma(z) = 0.0012 + "
             "0.0019 (z - 0.4)^2 m) | kinect+holes (plus blob holes and edge dropout) | all (plus colour "
             "noise).")] = "none",
    depth_sigma: Annotated[float, typer.Option(help="Depth noise sigma for --noise gaussian, metres.")] = 0.01,
    colour_sigma: Annotated[float, typer.Option(help="Colour noise sigma for --noise all, grey levels.")] = 3.0,
    holes: Annotated[float, typer.Option(help="Fraction of depth pixels dropped in blobs (kinect+holes, all).")]
    = 0.02,
    fps: Annotated[float, typer.Option(help="Frame rate for the timestamps, Hz.")] = 30.0,
    step_cm: Annotated[float, typer.Option(help="Nominal camera motion per frame, cm (6 with --step-deg 2.4: a "
                                                "fast camera).")] = 1.0,
    step_deg: Annotated[float, typer.Option(help="Nominal camera rotation per frame, degrees.")] = 1.0,
) -> None:
    """Render a synthetic RGB-D sequence of a textured procedural room with exact ground truth."""
    from lrslam.datasets.synth.noise import noise_preset
    from lrslam.datasets.synth.writer import generate

    from pydantic import ValidationError

    try:
        cfg = noise_preset(noise, depth_sigma=depth_sigma, colour_sigma=colour_sigma, holes=holes, seed=seed)
    except ValidationError as e:  # a value out of range
        err = e.errors()[0]
        raise InputError(f"--{'-'.join(map(str, err['loc'])).replace('_', '-')}: {err['msg']}") from None
    except ValueError as e:  # unknown preset
        raise InputError(str(e)) from None
    path = generate(out, scene=scene, trajectory=trajectory, n_frames=frames, seed=seed, width=width,
                    height=height, noise=cfg, fps=fps, show_progress=True, trans_step=step_cm / 100,
                    rot_step_deg=step_deg)
    typer.echo(f"wrote {frames} frames ({scene}, {trajectory}, noise {noise}) to {path}")
