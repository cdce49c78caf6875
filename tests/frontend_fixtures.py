"""Synthetic RGB-D views for the frontend tests: a textured box room with a few boxes inside, ray cast with
Open3D's RaycastingScene. Colour is a smooth procedural function of the world point, so two views of the same
surface point get exactly the same colour (photometric consistency holds up to pixel sampling).

Kept local to the frontend tests (small and dependency-free); the project's scene generator lives in
``lrslam.datasets.synth``.
"""

from __future__ import annotations

import numpy as np

from lrslam.camera import intrinsics_matrix
from lrslam.frame import Frame
from lrslam.geometry import inv, make_pose

# Room [-2, 2] x [-1.5, 1.5] x [-2, 2] m (OpenCV-like world: y down) with three boxes inside.
_ROOM = ((-2.0, -1.5, -2.0), (2.0, 1.5, 2.0))
_BOXES = (((-1.2, 0.5, 0.6), (-0.4, 1.5, 1.4)),
          ((0.5, 0.9, -0.2), (1.3, 1.5, 0.5)),
          ((-0.3, -0.2, 1.2), (0.4, 0.4, 2.0)))


def make_room():
    """Open3D ``RaycastingScene`` of the room (walls, floor, ceiling) and the boxes inside it."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    for lo, hi in (_ROOM,) + _BOXES:
        lo, hi = np.asarray(lo), np.asarray(hi)
        box = o3d.geometry.TriangleMesh.create_box(*(hi - lo))
        box.translate(lo)
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(box))
    return scene


def texture(points_w: np.ndarray) -> np.ndarray:
    """Procedural colour of world points (N, 3) metres -> (N, 3) float in [0, 1]: sums of sinusoids with
    periods of 9-40 cm, different per channel."""
    p = np.asarray(points_w, dtype=np.float64)
    freqs = 0.5 * np.array([[2.7, 1.9, 3.3], [-3.1, 2.3, 1.7], [1.3, -2.9, 2.1], [6.1, 4.7, -5.3], [-4.4, 7.2, 3.9]])
    phases = np.array([[0.0, 1.0, 2.0], [0.5, 2.5, 1.5], [1.2, 0.3, 2.8], [2.2, 0.7, 1.9], [0.9, 1.6, 0.1]])
    out = np.full((len(p), 3), 0.5)
    for f, ph, amp in zip(freqs, phases, (0.12, 0.12, 0.1, 0.08, 0.06)):
        arg = 2 * np.pi * (p @ f)
        out += amp * np.sin(arg[:, None] + ph[None, :])
    return np.clip(out, 0.0, 1.0)


def render(scene, K: np.ndarray, T_w_c: np.ndarray, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Ray cast a view: returns ``rgb (H, W, 3) uint8`` and ``depth (H, W) float32`` metres (z-depth, 0 = miss).

    ``create_rays_pinhole`` samples pixel (u, v) at (u + 0.5, v + 0.5); shifting cx, cy by +0.5 makes it match
    the OpenCV back-projection ``(u - cx) / fx`` used by the project (see DESIGN.md).
    """
    import open3d as o3d

    K_shift = K.copy()
    K_shift[0, 2] += 0.5
    K_shift[1, 2] += 0.5
    rays = o3d.t.geometry.RaycastingScene.create_rays_pinhole(
        intrinsic_matrix=o3d.core.Tensor(K_shift), extrinsic_matrix=o3d.core.Tensor(inv(T_w_c)),
        width_px=width, height_px=height)
    t_hit = scene.cast_rays(rays)["t_hit"].numpy().astype(np.float64)
    r = rays.numpy().astype(np.float64).reshape(-1, 6)
    hit = np.isfinite(t_hit.reshape(-1))
    pts_w = r[:, :3] + np.where(hit, t_hit.reshape(-1), 0.0)[:, None] * r[:, 3:]
    pts_c = pts_w @ inv(T_w_c)[:3, :3].T + inv(T_w_c)[:3, 3]
    depth = np.where(hit, pts_c[:, 2], 0.0).reshape(height, width).astype(np.float32)
    rgb = (255.0 * texture(pts_w)).round().astype(np.uint8).reshape(height, width, 3)
    rgb[~hit.reshape(height, width)] = 0
    return rgb, depth


def look_at(eye: np.ndarray, target: np.ndarray, down: np.ndarray = np.array([0.0, 1.0, 0.0])) -> np.ndarray:
    """Camera pose ``T_w_c`` (OpenCV axes) at ``eye`` looking at ``target``; ``down`` is the world direction that
    should appear downwards in the image."""
    z = np.asarray(target, float) - np.asarray(eye, float)
    z /= np.linalg.norm(z)
    x = np.cross(down, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return make_pose(np.stack([x, y, z], axis=1), eye)


def default_K(height: int, width: int) -> np.ndarray:
    """Pinhole intrinsics with a ~65 degree horizontal field of view, principal point at the centre."""
    f = 0.78 * width
    return intrinsics_matrix(f, f, (width - 1) / 2.0, (height - 1) / 2.0)


# A reference viewpoint that sees two walls, the floor and two of the boxes.
T_W_C_REF = look_at(np.array([0.4, -0.3, -1.2]), np.array([-0.3, 0.5, 1.2]))


def make_frame(scene, T_w_c: np.ndarray, height: int = 240, width: int = 320, index: int = 0) -> Frame:
    """A :class:`Frame` rendered at ``T_w_c`` (ground truth attached for evaluation)."""
    K = default_K(height, width)
    rgb, depth = render(scene, K, T_w_c, height, width)
    return Frame(index=index, timestamp=float(index) / 30.0, rgb=rgb, depth=depth, K=K, T_w_c_gt=T_w_c.copy())
