"""``lrslam eval ate|mesh``: trajectory and reconstruction metrics from files.

Bad inputs raise :class:`~lrslam.errors.InputError`; ``lrslam.cli.main`` prints them as one ``error: ...`` line.
A mesh without faces (as given, or after culling) is such an error: its metrics would be infinite. ``--json``
output is strict JSON (:func:`lrslam.jsonio.dumps`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import numpy as np
import typer

from lrslam.errors import InputError
from lrslam.jsonio import dumps

eval_app = typer.Typer(add_completion=False, no_args_is_help=True,
                       help="Evaluate a run: ATE of a TUM trajectory, reconstruction metrics of a mesh.")


@eval_app.command("ate")
def ate(
    est: Annotated[Path, typer.Argument(help="estimated trajectory (TUM: t tx ty tz qx qy qz qw)")],
    gt: Annotated[Path, typer.Argument(help="ground-truth trajectory (TUM)")],
    max_dt: Annotated[float, typer.Option("--max-dt", help="timestamp association tolerance [s]")] = 0.02,
    align: Annotated[bool, typer.Option("--align/--no-align", help="SE(3) Umeyama alignment first")] = True,
    as_json: Annotated[bool, typer.Option("--json", help="print a JSON object instead of text")] = False,
) -> None:
    """Absolute trajectory error (cm) after timestamp association and SE(3) alignment (no scale)."""
    from lrslam.pipeline.evaluation.ate import ate_from_files

    res = ate_from_files(est, gt, max_dt=max_dt, align=align)
    if as_json:
        typer.echo(dumps(res.to_dict()))
    else:
        typer.echo(f"ATE RMSE: {res.rmse_cm:.3f} cm  mean: {res.mean_cm:.3f}  median: {res.median_cm:.3f}  "
                   f"max: {res.max_cm:.3f}  ({res.n_matched} matched)")


@eval_app.command("mesh")
def mesh(
    est: Annotated[Path, typer.Argument(help="estimated mesh (PLY/OBJ/...), metres")],
    gt: Annotated[Path, typer.Argument(help="ground-truth mesh, metres")],
    traj: Annotated[Optional[Path], typer.Option(
        "--traj", help="camera trajectory T_w_c (TUM, GT world) to cull both meshes against")] = None,
    intrinsics: Annotated[Optional[str], typer.Option("--intrinsics", help="fx,fy,cx,cy [px] for culling")] = None,
    size: Annotated[Optional[str], typer.Option("--size", help="W,H image size [px] for culling")] = None,
    est_traj: Annotated[Optional[Path], typer.Option(
        "--est-traj", help="estimated trajectory (TUM): move the estimated mesh into the GT world with its ATE "
        "alignment to --traj")] = None,
    threshold: Annotated[float, typer.Option("--threshold", min=0.0, help="completion-ratio threshold [m]")] = 0.05,
    n_points: Annotated[int, typer.Option("--n-points", min=1, help="points sampled on each mesh")] = 200_000,
    occlusion: Annotated[bool, typer.Option("--occlusion/--no-occlusion", help="cull occluded faces")] = True,
    max_depth: Annotated[Optional[float], typer.Option("--max-depth", help="culling range [m]")] = None,
    stride: Annotated[int, typer.Option("--stride", min=1, help="use every n-th pose for culling")] = 1,
    depth_views: Annotated[int, typer.Option(
        "--depth-views", min=0, help="random views near --traj for depth L1 (0: skip)")] = 0,
    seed: Annotated[int, typer.Option("--seed", help="sampling seed")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="print a JSON object instead of text")] = False,
) -> None:
    """Accuracy / completion (cm), completion ratio (%) and optional depth L1 (cm), as NICE-SLAM / ESLAM.

    With --traj, --intrinsics and --size both meshes are culled against the camera frustums before sampling;
    the depth L1 compares the culled GT with the un-culled estimate from views near the trajectory.
    """
    from lrslam.camera import intrinsics_matrix
    from lrslam.pipeline.evaluation.ate import compute_ate, read_trajectory
    from lrslam.pipeline.evaluation.mesh_metrics import (cull_mesh, depth_l1, load_mesh, random_views,
                                                         reconstruction_metrics)

    # 1. Inputs.
    camera_opts = {"--traj": traj, "--intrinsics": intrinsics, "--size": size}
    given = [k for k, v in camera_opts.items() if v is not None]
    if given and len(given) < 3:
        missing = ", ".join(k for k in camera_opts if k not in given)
        raise InputError(f"culling needs --traj, --intrinsics and --size together (missing {missing})")
    if est_traj is not None and traj is None:
        raise InputError("--est-traj needs --traj (the ground-truth trajectory to align it to)")
    if depth_views > 0 and traj is None:
        raise InputError("--depth-views needs --traj, --intrinsics and --size")
    if max_depth is not None and not max_depth > 0:
        raise InputError(f"--max-depth must be > 0 metres, got {max_depth}")
    est_mesh = _non_empty(load_mesh(est, "estimated mesh"), est, "estimated mesh")
    gt_mesh = _non_empty(load_mesh(gt, "ground-truth mesh"), gt, "ground-truth mesh")

    # 2. Estimated mesh into the ground-truth world.
    if est_traj is not None:
        gt_ts, gt_poses = read_trajectory(traj)
        res = compute_ate(*read_trajectory(est_traj), gt_ts, gt_poses)
        est_mesh = est_mesh.copy().apply_transform(res.T_align)

    # 3. Culling against the trajectory, then metrics.
    out: dict[str, float] = {}
    if traj is not None:
        _, poses = read_trajectory(traj)
        fx, fy, cx, cy = _floats(intrinsics, 4, "--intrinsics", "fx,fy,cx,cy")
        width, height = _floats(size, 2, "--size", "W,H")
        if not (width.is_integer() and height.is_integer() and width > 0 and height > 0):
            raise InputError(f"--size expects two positive integers W,H, got {size!r}")
        width, height = int(width), int(height)
        K = intrinsics_matrix(fx, fy, cx, cy)
        cull = dict(K=K, width=width, height=height, max_depth=max_depth, occlusion=occlusion, stride=stride)
        gt_mesh = cull_mesh(gt_mesh, poses, **cull)
        if depth_views > 0:
            # The estimate is not culled here: a view slightly off the trajectory may see observed GT surface
            # whose estimated counterpart culling would drop (it lies outside every original frustum).
            views = random_views(poses, depth_views, seed=seed)
            out["depth_l1_cm"] = depth_l1(est_mesh, gt_mesh, K, width, height, views)
        est_mesh = cull_mesh(est_mesh, poses, **cull)
        _non_empty(gt_mesh, gt, "ground-truth mesh", f" inside the camera frusta of --traj {traj}")
        _non_empty(est_mesh, est, "estimated mesh", f" inside the camera frusta of --traj {traj}")
    out = {**reconstruction_metrics(est_mesh, gt_mesh, n_points=n_points, threshold=threshold, seed=seed), **out}

    if as_json:
        typer.echo(dumps(out))
        return
    typer.echo(f"Accuracy: {out['accuracy_cm']:.3f} cm  Completion: {out['completion_cm']:.3f} cm  "
               f"Completion ratio: {out['completion_ratio']:.2f} % (< {100 * threshold:g} cm)  "
               f"({out['n_est']} / {out['n_gt']} faces)")
    if "depth_l1_cm" in out:
        typer.echo(f"Depth L1: {out['depth_l1_cm']:.3f} cm ({depth_views} views)")


def _non_empty(mesh, path: Path, name: str, where: str = ""):
    """The mesh, or InputError naming its file when it has no faces (its metrics would be infinite)."""
    if len(mesh.faces) == 0:
        raise InputError(f"{path}: the {name} has no faces{where}; its metrics would be infinite")
    return mesh


def _floats(text: str, n: int, option: str, form: str) -> list[float]:
    try:
        vals = [float(x) for x in text.replace(" ", "").split(",")]
    except ValueError:
        vals = []
    if len(vals) != n or not np.all(np.isfinite(vals)):
        raise InputError(f"{option} expects {n} comma-separated numbers {form}, got {text!r}")
    return vals
