"""NICE-SLAM's depth L1: random virtual cameras inside the ground-truth mesh's bounding box.

As NICE-SLAM / ESLAM ``eval_recon.calc_2d_metric`` (numbers from cvg/nice-slam and idiap/ESLAM
``src/tools/eval_recon.py``): 1000 views of 500 x 500 pixels, focal 300 px; each camera centre is drawn uniformly
in the GT mesh's oriented bounding box shrunk to 0.3 / 0.7 / 0.7 of its extents along the box axes and raised
0.4 m along world z; the viewing direction points at a target drawn uniformly in a cube around the centre
(their ``[-10000, 10000]^3``); camera y (down, OpenCV) is world +z projected (their ``up = [0, 0, -1]`` in an
OpenGL camera). A view is re-drawn while any *unseen* ground-truth point (vertices no input camera observed,
NICE-SLAM's ``*_pc_unseen.npy``) projects into it. The error of a view is the mean over **all** its pixels of
``|d_gt - d_est|`` with depth 0 where a render hits nothing (Open3D's visualiser depth buffer, far plane 20 m);
the depth L1 is the mean over views, in cm.

Differences (documented, deliberate): depth is ray-cast with Open3D's ``RaycastingScene`` rather than the
OpenGL visualiser; a view must also see ground-truth surface in at least ``min_gt_fraction`` of its pixels
(inside a closed room every view does; around an open object a view of empty space would score 0); and after
``max_tries`` re-draws a view is accepted with the fewest unseen points in sight (counted in the result).
"""

from __future__ import annotations

import logging

import numpy as np
import trimesh

from lrslam.camera import intrinsics_matrix
from lrslam.errors import InputError
from lrslam.evaluation.mesh_metrics import load_mesh, render_depth

__all__ = ["NICE_WIDTH", "NICE_HEIGHT", "NICE_FOCAL", "FAR_M", "nice_intrinsics", "bbox_views", "depth_l1_all_pixels"]

log = logging.getLogger(__name__)

NICE_WIDTH = NICE_HEIGHT = 500   # pixels
NICE_FOCAL = 300.0               # pixels
FAR_M = 20.0                     # the visualiser's far plane (``set_constant_z_far(20)``), metres


def nice_intrinsics(width: int = NICE_WIDTH, height: int = NICE_HEIGHT, focal: float = NICE_FOCAL) -> np.ndarray:
    """NICE-SLAM's virtual camera ``K (3, 3)``: focal ``focal`` px, principal point at the image centre."""
    return intrinsics_matrix(focal, focal, width / 2.0 - 0.5, height / 2.0 - 0.5)


def bbox_views(gt_mesh: trimesh.Trimesh, n: int, seed: int = 0, unseen_points: np.ndarray | None = None,
               K: np.ndarray | None = None, width: int = NICE_WIDTH, height: int = NICE_HEIGHT,
               min_gt_fraction: float = 0.1, max_tries: int = 100,
               max_unseen: int = 20_000) -> tuple[np.ndarray, int]:
    """``n`` NICE-SLAM virtual cameras ``T_w_c (n, 4, 4)`` (OpenCV axes) in ``gt_mesh``'s bounding box.

    ``unseen_points (P, 3)`` world metres: GT points no input camera saw; views that project any of them are
    re-drawn (tested on at most ``max_unseen`` of them, drawn at random). Returns ``(poses, n_fallback)``:
    ``n_fallback`` views were accepted after ``max_tries`` draws
    (the draw with the fewest unseen points in sight, among those seeing GT surface when any did).
    """
    gt = load_mesh(gt_mesh, "ground-truth mesh")
    if n < 1 or len(gt.faces) == 0:
        raise InputError(f"bbox_views: need n >= 1 and a non-empty GT mesh, got n={n}, {len(gt.faces)} faces")
    K = nice_intrinsics(width, height) if K is None else np.asarray(K, dtype=np.float64)
    to_origin, extents = trimesh.bounds.oriented_bounds(gt)
    box = np.linalg.inv(to_origin)
    box[2, 3] += 0.4
    half = 0.5 * np.asarray(extents, dtype=np.float64) * np.array([0.3, 0.7, 0.7])
    rng = np.random.default_rng(seed)
    unseen = None if unseen_points is None or len(unseen_points) == 0 else np.asarray(unseen_points, np.float64)
    if unseen is not None and len(unseen) > max_unseen:   # a point sample, like NICE-SLAM's *_pc_unseen.npy
        unseen = unseen[rng.choice(len(unseen), max_unseen, replace=False)]
    out, n_fallback = [], 0
    for _ in range(n):
        best, best_key = None, None
        for _ in range(max_tries):
            origin = box[:3, :3] @ rng.uniform(-half, half) + box[:3, 3]
            T = _look(origin, rng.uniform(-1.0, 1.0, 3))
            if T is None:
                continue
            n_unseen = 0 if unseen is None else _count_in_view(unseen, T, K, width, height)
            hit = _hit_fraction(gt, T, K, width, height)
            key = (hit < min_gt_fraction, n_unseen)
            if best_key is None or key < best_key:
                best, best_key = T, key
            if key == (False, 0):
                break
        if best_key != (False, 0):
            n_fallback += 1
        out.append(best)
    if n_fallback:
        log.warning("bbox_views: %d of %d views still see unseen GT points or little GT surface after %d draws",
                    n_fallback, n, max_tries)
    return np.stack(out), n_fallback


def depth_l1_all_pixels(est_mesh: trimesh.Trimesh, gt_mesh: trimesh.Trimesh, poses: np.ndarray,
                        K: np.ndarray | None = None, width: int = NICE_WIDTH, height: int = NICE_HEIGHT,
                        far: float = FAR_M) -> float:
    """NICE-SLAM depth L1 (cm): per view the mean over all pixels of ``|d_gt - d_est|`` (z-depth, metres; 0 where
    a render hits nothing or beyond ``far``), averaged over views ``T_w_c (N, 4, 4)``. An empty estimate
    renders as all zeros (the error is then the GT depth)."""
    K = nice_intrinsics(width, height) if K is None else np.asarray(K, dtype=np.float64)
    gt_d = _visualiser_depth(render_depth(gt_mesh, poses, K, width, height), far)
    est_d = _visualiser_depth(render_depth(est_mesh, poses, K, width, height), far)
    return 100.0 * float(np.mean(np.abs(gt_d - est_d).mean(axis=(1, 2))))


def _hit_fraction(mesh: trimesh.Trimesh, T_w_c: np.ndarray, K: np.ndarray, width: int, height: int,
                  scale: float = 0.1) -> float:
    """Fraction of the view's pixels that see ``mesh``, estimated on a ``scale``-times smaller image."""
    w, h = max(1, round(width * scale)), max(1, round(height * scale))
    Ks = np.asarray(K, dtype=np.float64).copy()
    Ks[0, 0], Ks[1, 1] = K[0, 0] * w / width, K[1, 1] * h / height
    Ks[0, 2], Ks[1, 2] = (K[0, 2] + 0.5) * w / width - 0.5, (K[1, 2] + 0.5) * h / height - 0.5
    return float(np.isfinite(render_depth(mesh, T_w_c, Ks, w, h)[0]).mean())


def _visualiser_depth(d: np.ndarray, far: float) -> np.ndarray:
    return np.where(np.isfinite(d) & (d <= far), d, 0.0)


def _look(origin: np.ndarray, direction: np.ndarray) -> np.ndarray | None:
    """Camera-to-world pose at ``origin`` looking along ``direction`` with camera y (down) towards world +z."""
    f = direction / (np.linalg.norm(direction) + 1e-300)
    x = np.cross([0.0, 0.0, 1.0], f)
    if np.linalg.norm(x) < 1e-6:
        return None
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, np.cross(f, x), f, origin
    return T


def _count_in_view(points: np.ndarray, T_w_c: np.ndarray, K: np.ndarray, width: int, height: int) -> int:
    """How many world points project inside the image, in front of the camera (no occlusion test, as NICE-SLAM)."""
    R, t = T_w_c[:3, :3], T_w_c[:3, 3]
    p = (points - t) @ R
    z = p[:, 2]
    front = z > 1e-9
    u = K[0, 0] * p[front, 0] / z[front] + K[0, 2]
    v = K[1, 1] * p[front, 1] / z[front] + K[1, 2]
    return int(np.count_nonzero((u >= -0.5) & (u < width - 0.5) & (v >= -0.5) & (v < height - 0.5)))
