"""Evaluate an estimated mesh against a ground-truth mesh under a :class:`MeshProtocol` (default: ESLAM's).

Steps (:func:`evaluate_mesh`): (1) cull both meshes against the ground-truth cameras, (2) ICP-refine the
estimate onto the ground truth, (3) accuracy / completion / completion ratio from sampled points, (4) depth L1
from virtual views. :func:`evaluate_run_mesh` is the run's entry point: it first decides which world the run's
mesh is in (see its docstring), so the metrics never depend on an ill-conditioned trajectory alignment.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from lrslam.errors import InputError
from lrslam.evaluation.depth_views import bbox_views, depth_l1_all_pixels
from lrslam.evaluation.mesh_metrics import (depth_l1, icp_align, keep_seen_faces, load_mesh, random_views,
                                                     reconstruction_metrics, seen_vertices)
from lrslam.evaluation.mesh_protocol import MeshProtocol, get_protocol

__all__ = ["evaluate_mesh", "evaluate_run_mesh"]

log = logging.getLogger(__name__)


def evaluate_mesh(est_mesh: trimesh.Trimesh | str | Path, gt_mesh: trimesh.Trimesh | str | Path,
                  poses: np.ndarray | None = None, K: np.ndarray | None = None, width: int | None = None,
                  height: int | None = None, protocol: MeshProtocol | None = None, max_depth: float | None = None,
                  stride: int | None = None, seed: int = 0) -> dict:
    """Reconstruction metrics of ``est_mesh`` (already in the GT world, metres) against ``gt_mesh``.

    ``poses (N, 4, 4)``: ground-truth ``T_w_c`` (OpenCV axes) of the input frames, with their camera ``K (3, 3)``
    and ``width x height`` pixels: both meshes are culled against them (None: no culling, and no unseen-point
    test for the depth views; a ``"trajectory"`` depth L1 then needs poses). ``max_depth``: culling range, metres;
    ``stride``: cull with every ``stride``-th pose (None: the protocol's ``max_poses`` rule).
    ``protocol``: :data:`~lrslam.evaluation.mesh_protocol.PROTOCOLS` entry (default ``eslam``).

    Returns ``accuracy_cm``, ``completion_cm``, ``completion_ratio`` (%), ``n_est`` / ``n_gt`` (faces after
    culling), ``depth_l1_cm`` (when ``depth_views > 0``), ``icp_rotation_deg`` / ``icp_translation_cm`` (the ICP
    correction; 0 without ICP) and ``protocol`` (its name).
    """
    p = protocol or get_protocol()
    est, gt = load_mesh(est_mesh, "estimated mesh"), load_mesh(gt_mesh, "ground-truth mesh")
    est_full = est
    unseen = None
    # 1. Culling against the ground-truth cameras.
    if poses is not None:
        if K is None or width is None or height is None:
            raise InputError("culling needs the camera: K, width and height with the poses")
        poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
        cull = dict(K=K, width=width, height=height, max_depth=max_depth, stride=stride or p.stride(len(poses)),
                    occlusion=p.occlusion_tol is not None, occlusion_tol=p.occlusion_tol or 0.0)
        gt_seen = seen_vertices(gt, poses, **cull)
        unseen = np.asarray(gt.vertices)[~gt_seen]
        gt = keep_seen_faces(gt, gt_seen, p.face_rule)
        est = keep_seen_faces(est, seen_vertices(est, poses, **cull), p.face_rule)
        for mesh, name in ((gt, "ground-truth mesh"), (est, "estimated mesh")):
            if len(mesh.faces) == 0:
                raise InputError(f"the {name} has no faces inside the camera frusta; its metrics would be infinite")
    # 2. ICP refinement of the estimate onto the ground truth (NICE-SLAM / ESLAM get_align_transformation).
    T_icp = icp_align(est, gt, p.icp_threshold) if p.icp else np.eye(4)
    if p.icp:
        est = est.copy().apply_transform(T_icp)
        est_full = est_full.copy().apply_transform(T_icp)
    # 3. Points on both surfaces.
    out = {**reconstruction_metrics(est, gt, n_points=p.n_points, threshold=p.threshold, seed=seed),
           "icp_rotation_deg": float(np.degrees(Rotation.from_matrix(T_icp[:3, :3]).magnitude())),
           "icp_translation_cm": 100.0 * float(np.linalg.norm(T_icp[:3, 3])), "protocol": p.name}
    # 4. Depth L1 from virtual views.
    if p.depth_views > 0:
        if p.depth_l1 == "bbox":
            views, n_fallback = bbox_views(gt, p.depth_views, seed=seed, unseen_points=unseen)
            out["depth_l1_cm"] = depth_l1_all_pixels(est, gt, views)
            out["depth_views_fallback"] = n_fallback
        else:
            if poses is None:
                raise InputError("a trajectory depth L1 needs the camera poses")
            # Un-culled estimate: a view slightly off the trajectory may see observed GT surface whose estimated
            # counterpart culling would drop (it lies outside every original frustum).
            views = random_views(poses, p.depth_views, seed=seed)
            out["depth_l1_cm"] = depth_l1(est_full, gt, K, width, height, views)
    return out


def evaluate_run_mesh(est_mesh: trimesh.Trimesh, gt_mesh_path: str | Path, gt_poses: np.ndarray, K: np.ndarray,
                      width: int, height: int, T_align: np.ndarray | None, world_is_gt: bool,
                      n_points: int | None = None, protocol: MeshProtocol | None = None, seed: int = 0) -> dict:
    """Mesh metrics of a run: put the run's mesh into the GT world, then :func:`evaluate_mesh`.

    The decision: when ``world_is_gt`` (the run started at the ground-truth first pose, ``initial_pose: gt``, so
    its map is built in the GT world) the mesh is evaluated **as it is** and ``T_align`` is ignored: an ATE
    alignment of a short or nearly straight trajectory is ill-conditioned (a 6-frame run's rotated the mesh by
    ~54 degrees) and would only add its error. Otherwise the mesh is moved by ``T_align`` (4x4, estimated world
    -> GT world, the ATE's Umeyama alignment; required then).

    ``gt_poses (N, 4, 4)``: ground-truth ``T_w_c`` of the frames (non-finite rows dropped), camera ``K``,
    ``width x height`` px: the culling cameras. ``n_points`` overrides the protocol's sample count.
    Returns :func:`evaluate_mesh`'s dict plus ``mesh_world``: ``"gt"`` or ``"ate_aligned"``.
    """
    p = protocol or get_protocol()
    if n_points is not None:
        p = replace(p, n_points=int(n_points))
    est = load_mesh(est_mesh, "estimated mesh")
    if world_is_gt:
        world = "gt"
    else:
        if T_align is None:
            raise InputError("the run's mesh is not in the GT world (world_is_gt=False): T_align is required")
        est = est.copy().apply_transform(np.asarray(T_align, dtype=np.float64))
        world = "ate_aligned"
    poses = np.asarray(gt_poses, dtype=np.float64).reshape(-1, 4, 4)
    poses = poses[np.all(np.isfinite(poses), axis=(1, 2))]
    if len(poses) == 0:
        raise InputError("no finite ground-truth pose to cull the meshes against")
    out = evaluate_mesh(est, gt_mesh_path, poses, K, width, height, protocol=p, seed=seed)
    return {**out, "mesh_world": world}
