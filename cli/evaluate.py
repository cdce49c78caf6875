"""``lrslam eval ate|mesh``: trajectory and reconstruction metrics from files.

Bad inputs raise :class:`~lrslam.errors.InputError`; ``lrslam.cli.main`` prints them as one ``error: ...`` line.
A mesh without faces (as given, or after culling) is such an error: its metrics would be infinite. ``--json``
output is strict JSON (:func:`lrslam.jsonio.dumps`).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Optional

import numpy as np
import typer

from lrslam.errors import InputError
from lrslam.jsonio import dumps

if TYPE_CHECKING:
    from lrslam.evaluation.mesh_protocol import MeshProtocol

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
    from lrslam.evaluation.ate import ate_from_files

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
    protocol: Annotated[str, typer.Option("--protocol", help="eslam | nice-slam | lrslam-v0 (ours before issue "
                                          "11); the options below override its fields")] = "eslam",
    n_points: Annotated[Optional[int], typer.Option(
        "--n-points", min=1, help="points sampled on each mesh [eslam 450000, nice-slam 200000]")] = None,
    face_rule: Annotated[Optional[str], typer.Option(
        "--face-rule", help="keep a face when any|all of its vertices were seen [any]")] = None,
    icp: Annotated[Optional[bool], typer.Option(
        "--icp/--no-icp", help="ICP-refine the estimate onto the GT (0.1 m, point-to-point) [on]")] = None,
    occlusion: Annotated[Optional[bool], typer.Option(
        "--occlusion/--no-occlusion", help="cull occluded faces [eslam: on, 0.06 m; nice-slam: off]")] = None,
    max_depth: Annotated[Optional[float], typer.Option("--max-depth", help="culling range [m]")] = None,
    stride: Annotated[Optional[int], typer.Option("--stride", min=1, help="use every n-th pose for culling [1]")] = None,
    depth_views: Annotated[Optional[int], typer.Option("--depth-views", min=0, help="depth-L1 views (0: skip) [1000]")] = None,
    depth_l1: Annotated[Optional[str], typer.Option(
        "--depth-l1", help="bbox (NICE-SLAM: random views in the GT box) | trajectory (views near --traj)")] = None,
    seed: Annotated[int, typer.Option("--seed", help="sampling seed")] = 0,
    as_json: Annotated[bool, typer.Option("--json", help="print a JSON object instead of text")] = False,
) -> None:
    """Accuracy / completion (cm), completion ratio (%) and depth L1 (cm), by default with ESLAM's protocol.

    Default ``--protocol eslam`` (idiap/ESLAM ``eval_recon.py`` / ``cull_mesh.py``): with --traj, --intrinsics
    and --size both meshes are culled against every camera (a face is kept when any vertex is seen; occlusion
    tolerance 0.06 m), the estimate is ICP-refined onto the GT (0.1 m), 450,000 points are sampled per mesh and
    the depth L1 averages 1000 NICE-SLAM views in the GT bounding box (all pixels). ``nice-slam``: no occlusion
    test, 200,000 points. ``lrslam-v0`` (ours before issue 11): faces with all vertices seen, at most 50 poses,
    no ICP, 200,000 points, depth L1 from 100 views near the trajectory. See ``mesh_protocol``.
    """
    from lrslam.evaluation.mesh_eval import evaluate_mesh
    from lrslam.evaluation.mesh_metrics import load_mesh

    # 1. Inputs.
    proto = _mesh_protocol(protocol, n_points, face_rule, icp, depth_views, depth_l1, threshold, occlusion)
    _check_mesh_options(proto, traj, intrinsics, size, est_traj, max_depth)
    est_mesh = _non_empty(load_mesh(est, "estimated mesh"), est, "estimated mesh")
    gt_mesh = _non_empty(load_mesh(gt, "ground-truth mesh"), gt, "ground-truth mesh")

    # 2. Estimated mesh into the ground-truth world.
    if est_traj is not None:
        est_mesh = _into_gt_world(est_mesh, est_traj, traj)

    # 3. Culling against the trajectory, ICP, metrics (mesh_eval.evaluate_mesh).
    poses, K, width, height = _culling_camera(traj, intrinsics, size) if traj is not None else (None,) * 4
    out = evaluate_mesh(est_mesh, gt_mesh, poses, K, width, height, protocol=proto, max_depth=max_depth,
                        stride=stride, seed=seed)

    # 4. Report.
    _echo_mesh_metrics(out, proto, threshold, as_json)


def _mesh_protocol(name: str, n_points: int | None, face_rule: str | None, icp: bool | None,
                   depth_views: int | None, depth_l1: str | None, threshold: float,
                   occlusion: bool | None) -> MeshProtocol:
    """The named protocol with the given options overriding its fields (``occlusion``: on keeps its tolerance,
    or 0.03 m when it has none; off drops the occlusion test)."""
    from dataclasses import replace

    from lrslam.evaluation.mesh_protocol import get_protocol

    proto = get_protocol(name, n_points=n_points, face_rule=face_rule, icp=icp, depth_views=depth_views,
                         depth_l1=depth_l1, threshold=threshold)
    if occlusion is not None:
        proto = replace(proto, occlusion_tol=(proto.occlusion_tol or 0.03) if occlusion else None)
    return proto


def _check_mesh_options(proto: MeshProtocol, traj: Path | None, intrinsics: str | None, size: str | None,
                        est_traj: Path | None, max_depth: float | None) -> None:
    """InputError for options that need others (culling needs all three camera options) or bad values."""
    camera_opts = {"--traj": traj, "--intrinsics": intrinsics, "--size": size}
    given = [k for k, v in camera_opts.items() if v is not None]
    if given and len(given) < 3:
        missing = ", ".join(k for k in camera_opts if k not in given)
        raise InputError(f"culling needs --traj, --intrinsics and --size together (missing {missing})")
    if est_traj is not None and traj is None:
        raise InputError("--est-traj needs --traj (the ground-truth trajectory to align it to)")
    if proto.depth_views > 0 and proto.depth_l1 == "trajectory" and traj is None:
        raise InputError("--depth-l1 trajectory needs --traj, --intrinsics and --size")
    if max_depth is not None and not max_depth > 0:
        raise InputError(f"--max-depth must be > 0 metres, got {max_depth}")


def _into_gt_world(est_mesh, est_traj: Path, traj: Path):
    """A copy of ``est_mesh`` moved by the ATE alignment (SE(3)) of ``est_traj`` to the GT trajectory ``traj``."""
    from lrslam.evaluation.ate import compute_ate, read_trajectory

    gt_ts, gt_poses = read_trajectory(traj)
    res = compute_ate(*read_trajectory(est_traj), gt_ts, gt_poses)
    return est_mesh.copy().apply_transform(res.T_align)


def _culling_camera(traj: Path, intrinsics: str, size: str) -> tuple[np.ndarray, np.ndarray, int, int]:
    """``(poses (N, 4, 4) T_w_c, K (3, 3), width, height)`` from --traj, --intrinsics fx,fy,cx,cy and --size W,H."""
    from lrslam.camera import intrinsics_matrix
    from lrslam.evaluation.ate import read_trajectory

    _, poses = read_trajectory(traj)
    fx, fy, cx, cy = _floats(intrinsics, 4, "--intrinsics", "fx,fy,cx,cy")
    width, height = _floats(size, 2, "--size", "W,H")
    if not (width.is_integer() and height.is_integer() and width > 0 and height > 0):
        raise InputError(f"--size expects two positive integers W,H, got {size!r}")
    return poses, intrinsics_matrix(fx, fy, cx, cy), int(width), int(height)


def _echo_mesh_metrics(out: dict, proto: MeshProtocol, threshold: float, as_json: bool) -> None:
    if as_json:
        typer.echo(dumps(out))
        return
    typer.echo(f"Accuracy: {out['accuracy_cm']:.3f} cm  Completion: {out['completion_cm']:.3f} cm  "
               f"Completion ratio: {out['completion_ratio']:.2f} % (< {100 * threshold:g} cm)  "
               f"({out['n_est']} / {out['n_gt']} faces)")
    if "depth_l1_cm" in out:
        typer.echo(f"Depth L1: {out['depth_l1_cm']:.3f} cm ({proto.depth_views} views, {proto.depth_l1})")


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
