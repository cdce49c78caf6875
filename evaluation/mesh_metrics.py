"""Reconstruction metrics as NICE-SLAM / ESLAM: accuracy, completion, completion ratio, depth L1; mesh culling.

Building blocks (the protocols that combine them are :mod:`~lrslam.evaluation.mesh_protocol`, the
evaluation itself :mod:`~lrslam.evaluation.mesh_eval`): :func:`cull_mesh` drops faces outside every
camera frustum (or hidden in every view), :func:`icp_align` refines the estimate onto the ground truth,
:func:`reconstruction_metrics` samples points on both surfaces and measures nearest-neighbour distances, and
:func:`depth_l1` compares depth maps rendered from given views (:func:`random_views`: near a trajectory;
:mod:`~lrslam.evaluation.depth_views`: NICE-SLAM's views in the GT bounding box).
Depth rendering uses Open3D's ``RaycastingScene``; see DESIGN.md for its half-pixel principal-point offset.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from lrslam.camera import check_intrinsics
from lrslam.errors import InputError
from lrslam.geometry import inv, random_pose

__all__ = ["load_mesh", "reconstruction_metrics", "cull_mesh", "seen_vertices", "keep_seen_faces", "icp_align",
           "render_depth", "depth_l1", "random_views"]

log = logging.getLogger(__name__)


def load_mesh(mesh: trimesh.Trimesh | str | Path, name: str = "mesh") -> trimesh.Trimesh:
    """A :class:`trimesh.Trimesh` as is, or read from a file (PLY, OBJ, ...; scenes are concatenated).
    Missing or unreadable files raise :class:`InputError`. A file without faces gives an empty mesh."""
    if isinstance(mesh, trimesh.Trimesh):
        return mesh
    path = Path(mesh)
    if not path.is_file():
        raise InputError(f"{path}: {name} file not found")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # trimesh raises many types on garbled files
        raise InputError(f"{path}: cannot read {name} ({type(e).__name__}: {e})".splitlines()[0]) from None
    if not isinstance(loaded, trimesh.Trimesh):
        raise InputError(f"{path}: {name} is not a triangle mesh (got {type(loaded).__name__})")
    return loaded


def reconstruction_metrics(est_mesh: trimesh.Trimesh | str | Path, gt_mesh: trimesh.Trimesh | str | Path,
                           n_points: int = 200_000, threshold: float = 0.05, seed: int = 0) -> dict[str, float]:
    """Accuracy, completion and completion ratio (NICE-SLAM / ESLAM definitions). Meshes in metres, one world.

    ``n_points`` points are sampled uniformly (by area) on each surface, independently (seeds ``seed`` and
    ``seed + 1``). accuracy = mean distance from estimated samples to the nearest ground-truth sample, completion
    = mean distance from ground-truth samples to the nearest estimated sample (both in cm), completion_ratio =
    percentage of ground-truth samples within ``threshold`` metres of an estimated sample. Sampling alone gives a
    small positive floor (about half the sample spacing: ~1 mm for 200k points on 4 m^2).

    Returns ``{accuracy_cm, completion_cm, completion_ratio, n_est, n_gt}`` (``n_*``: face counts). An empty
    estimated mesh gives infinite distances and ratio 0 with a logged warning; an empty GT mesh is an error.
    """
    est = load_mesh(est_mesh, "estimated mesh")
    gt = load_mesh(gt_mesh, "ground-truth mesh")
    if n_points < 1 or not threshold > 0:
        raise InputError(f"need n_points >= 1 and threshold > 0, got {n_points} and {threshold}")
    if _is_empty(gt):
        raise InputError("ground-truth mesh has no surface (after culling?): check the mesh and the trajectory")
    out = {"n_est": int(len(est.faces)), "n_gt": int(len(gt.faces))}
    if _is_empty(est):
        log.warning("estimated mesh has no surface: reconstruction metrics are infinite")
        return {"accuracy_cm": float("inf"), "completion_cm": float("inf"), "completion_ratio": 0.0, **out}
    est_pts, _ = trimesh.sample.sample_surface(est, n_points, seed=seed)
    gt_pts, _ = trimesh.sample.sample_surface(gt, n_points, seed=seed + 1)
    d_est_to_gt, _ = cKDTree(gt_pts).query(est_pts)
    d_gt_to_est, _ = cKDTree(est_pts).query(gt_pts)
    return {"accuracy_cm": 100.0 * float(np.mean(d_est_to_gt)),
            "completion_cm": 100.0 * float(np.mean(d_gt_to_est)),
            "completion_ratio": 100.0 * float(np.mean(d_gt_to_est < threshold)), **out}


def cull_mesh(mesh: trimesh.Trimesh | str | Path, poses: np.ndarray, K: np.ndarray, width: int, height: int,
              max_depth: float | None = None, occlusion: bool = True, stride: int = 1,
              occlusion_tol: float = 0.03, face_rule: str = "any") -> trimesh.Trimesh:
    """Drop the faces no camera saw (ESLAM / NICE-SLAM culling). Returns a new mesh; the input is not modified.

    Vertices are tested by :func:`seen_vertices` (same arguments). ``face_rule="any"`` keeps a face when any of
    its vertices was seen by any camera (ESLAM / NICE-SLAM ``cull_mesh``: a face goes only when all its vertices
    are unseen); ``"all"`` keeps it only when all three were seen (stricter; trims the rim of the observed
    region). Unreferenced vertices are removed.
    """
    if face_rule not in ("any", "all"):
        raise InputError(f"face_rule must be 'any' or 'all', got {face_rule!r}")
    mesh = load_mesh(mesh)
    if _is_empty(mesh):
        _intrinsics(K, width, height)
        return mesh.copy()
    seen = seen_vertices(mesh, poses, K, width, height, max_depth=max_depth, occlusion=occlusion, stride=stride,
                         occlusion_tol=occlusion_tol)
    return keep_seen_faces(mesh, seen, face_rule)


def keep_seen_faces(mesh: trimesh.Trimesh, seen: np.ndarray, face_rule: str = "any") -> trimesh.Trimesh:
    """A copy of ``mesh`` with the faces kept by ``face_rule`` given the per-vertex ``seen (V,)`` mask."""
    if face_rule not in ("any", "all"):
        raise InputError(f"face_rule must be 'any' or 'all', got {face_rule!r}")
    keep = seen[mesh.faces].any(axis=1) if face_rule == "any" else seen[mesh.faces].all(axis=1)
    out = mesh.copy()
    out.update_faces(keep)
    out.remove_unreferenced_vertices()
    log.debug("cull_mesh: kept %d of %d faces", int(keep.sum()), len(keep))
    return out


def seen_vertices(mesh: trimesh.Trimesh | str | Path, poses: np.ndarray, K: np.ndarray, width: int, height: int,
                  max_depth: float | None = None, occlusion: bool = True, stride: int = 1,
                  occlusion_tol: float = 0.03) -> np.ndarray:
    """Which vertices some camera saw: ``(V,)`` bool.

    A vertex is seen by a camera ``T_w_c`` (OpenCV axes, ``poses (N, 4, 4)``, every ``stride``-th used) when it
    projects inside the ``width x height`` image with intrinsics ``K (3, 3)``, lies in front of the camera
    (``0 < z``, and ``z <= max_depth`` metres when given) and, with ``occlusion``, when the first surface hit by
    the ray from the camera centre through it lies no more than ``occlusion_tol`` metres (along z) in front of it.
    Non-finite poses are ignored.
    """
    mesh = load_mesh(mesh)
    poses = _poses(poses)[::max(1, int(stride))]
    poses = poses[np.all(np.isfinite(poses), axis=(1, 2))]  # lost-tracking rows see nothing
    K = _intrinsics(K, width, height)
    verts = np.asarray(mesh.vertices, dtype=np.float64)
    seen = np.zeros(len(verts), dtype=bool)
    if _is_empty(mesh):
        return seen
    scene = _raycasting_scene(mesh) if occlusion else None
    for T_w_c in poses:
        # 1. Frustum test for the vertices no camera has seen yet.
        cand = np.flatnonzero(~seen)
        if len(cand) == 0:
            break
        T_c_w = inv(T_w_c)
        p_c = verts[cand] @ T_c_w[:3, :3].T + T_c_w[:3, 3]
        z = p_c[:, 2]
        in_front = z > 1e-9
        with np.errstate(divide="ignore", invalid="ignore"):
            u = K[0, 0] * p_c[:, 0] / z + K[0, 2]
            v = K[1, 1] * p_c[:, 1] / z + K[1, 2]
        ok = in_front & (u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)
        if max_depth is not None:
            ok &= z <= max_depth
        cand, z, p_c = cand[ok], z[ok], p_c[ok]
        # 2. Occlusion: cast a ray from the camera centre through each candidate vertex (direction with unit
        #    camera z, so the hit parameter is the z-depth of the first surface along it).
        if scene is not None and len(cand):
            dirs_w = (p_c / z[:, None]) @ T_w_c[:3, :3].T
            origins = np.broadcast_to(T_w_c[:3, 3], dirs_w.shape)
            z_hit = _cast(scene, origins, dirs_w)
            cand = cand[z <= z_hit + occlusion_tol]
        seen[cand] = True
    return seen


def icp_align(est_mesh: trimesh.Trimesh | str | Path, gt_mesh: trimesh.Trimesh | str | Path,
              threshold: float = 0.1) -> np.ndarray:
    """Rigid 4x4 ``T`` refining the estimated mesh onto the ground truth (apply as ``est.apply_transform(T)``).

    As NICE-SLAM / ESLAM ``get_align_transformation``: Open3D point-to-point ICP between the two meshes'
    vertices, correspondence distance ``threshold`` metres (0.1), identity start. Empty meshes give identity.
    """
    import open3d as o3d

    est, gt = load_mesh(est_mesh, "estimated mesh"), load_mesh(gt_mesh, "ground-truth mesh")
    if len(est.vertices) == 0 or len(gt.vertices) == 0:
        return np.eye(4)
    src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(est.vertices, dtype=np.float64)))
    dst = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.asarray(gt.vertices, dtype=np.float64)))
    reg = o3d.pipelines.registration.registration_icp(
        src, dst, float(threshold), np.eye(4), o3d.pipelines.registration.TransformationEstimationPointToPoint())
    return np.asarray(reg.transformation, dtype=np.float64)


def render_depth(mesh: trimesh.Trimesh | str | Path, poses: np.ndarray, K: np.ndarray, width: int,
                 height: int) -> np.ndarray:
    """Z-depth maps (metres) of a mesh seen from cameras ``T_w_c (N, 4, 4)`` (OpenCV axes) with intrinsics
    ``K (3, 3)``: ``(N, height, width)`` float64, ``inf`` where no surface is hit. Pixel ``(u, v)`` samples
    the ray through ``((u - cx) / fx, (v - cy) / fy, 1)`` as :mod:`lrslam.camera` (cx + 0.5 given to Open3D)."""
    import open3d as o3d

    mesh = load_mesh(mesh)
    poses = _poses(poses)
    K = _intrinsics(K, width, height)
    out = np.full((len(poses), height, width), np.inf)
    if _is_empty(mesh):
        return out
    scene = _raycasting_scene(mesh)
    K_o3d = K.copy()
    K_o3d[0, 2] += 0.5
    K_o3d[1, 2] += 0.5
    for i, T_w_c in enumerate(poses):
        rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
            o3d.core.Tensor(K_o3d), o3d.core.Tensor(inv(T_w_c)), int(width), int(height))
        out[i] = scene.cast_rays(rays)["t_hit"].numpy()  # directions have unit camera z: t_hit is z-depth
    return out


def depth_l1(est_mesh: trimesh.Trimesh | str | Path, gt_mesh: trimesh.Trimesh | str | Path, K: np.ndarray,
             width: int, height: int, poses: np.ndarray) -> float:
    """Depth L1 (cm) between depth maps rendered from both meshes at views ``T_w_c (N, 4, 4)``.

    As NICE-SLAM, every pixel where the ground-truth render hits a surface counts; an estimated render that
    misses there counts as depth 0 (error = GT depth). The mean is taken over all such pixels of all views.
    An empty estimated mesh gives ``inf`` with a logged warning; views that see no GT surface are an error.
    """
    est = load_mesh(est_mesh, "estimated mesh")
    gt = load_mesh(gt_mesh, "ground-truth mesh")
    gt_depth = render_depth(gt, poses, K, width, height)
    valid = np.isfinite(gt_depth)
    if not valid.any():
        raise InputError(f"depth L1: none of the {len(gt_depth)} views sees the ground-truth mesh")
    if _is_empty(est):
        log.warning("estimated mesh has no surface: depth L1 is infinite")
        return float("inf")
    est_depth = render_depth(est, poses, K, width, height)
    est_depth = np.where(np.isfinite(est_depth), est_depth, 0.0)
    return 100.0 * float(np.mean(np.abs(est_depth[valid] - gt_depth[valid])))


def random_views(poses: np.ndarray, n: int, seed: int = 0, max_trans_m: float = 0.1,
                 max_rot_deg: float = 10.0) -> np.ndarray:
    """``n`` random camera poses ``T_w_c (n, 4, 4)`` near a trajectory ``(N, 4, 4)``.

    Each picks a random trajectory pose (uniform, with replacement; non-finite poses skipped) and perturbs it in
    its own camera frame by a random rigid motion of at most ``max_trans_m`` metres and ``max_rot_deg`` degrees.
    NICE-SLAM instead draws positions anywhere in the GT bounding box; views near the trajectory look at the part
    of the scene that was scanned (and survives culling), so the depth L1 measures the map, not unseen space.
    """
    poses = _poses(poses)
    finite = poses[np.all(np.isfinite(poses), axis=(1, 2))]
    if len(finite) == 0 or n < 1:
        raise InputError(f"random_views: need n >= 1 and finite poses, got n={n} and {len(finite)} finite poses")
    rng = np.random.default_rng(seed)
    picks = rng.integers(0, len(finite), size=n)
    return np.stack([finite[i] @ random_pose(rng, max_trans_m, max_rot_deg) for i in picks])


def _is_empty(mesh: trimesh.Trimesh) -> bool:
    return len(mesh.faces) == 0 or not float(mesh.area) > 0.0


def _poses(poses: np.ndarray) -> np.ndarray:
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim == 2:
        P = P[None]
    if P.ndim != 3 or P.shape[1:] != (4, 4):
        raise InputError(f"expected camera poses (N, 4, 4), got shape {P.shape}")
    return P


def _intrinsics(K: np.ndarray, width: int, height: int) -> np.ndarray:
    if int(width) < 1 or int(height) < 1:
        raise InputError(f"image size must be positive, got {width}x{height}")
    try:
        return check_intrinsics(K, int(width), int(height))
    except ValueError as e:
        raise InputError(str(e)) from None


def _raycasting_scene(mesh: trimesh.Trimesh):
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.core.Tensor(np.asarray(mesh.vertices, dtype=np.float32)),
                        o3d.core.Tensor(np.asarray(mesh.faces, dtype=np.uint32)))
    return scene


def _cast(scene, origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Ray parameter of the first hit (inf on a miss) for rays ``origins + t dirs`` (both (N, 3), world)."""
    import open3d as o3d

    rays = np.concatenate([origins, dirs], axis=1).astype(np.float32)
    return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy().astype(np.float64)
