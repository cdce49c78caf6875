"""Synthetic RGB-D data for the field tests: a textured box room with a few objects, ray-cast with Open3D.

Rays are built here in the OpenCV convention of :mod:`lrslam.camera` (pixel (u, v) along ((u-cx)/fx,
(v-cy)/fy, 1)), so the ray parameter of a hit is the z-depth and no half-pixel shift is involved. Colour is a
smooth procedural albedo of the world point (no lighting), identical from every view.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lrslam.camera import intrinsics_matrix

ROOM = np.array([[-2.0, 2.0], [-1.75, 1.75], [0.0, 2.6]])  # metres, world z up
K_SMALL = intrinsics_matrix(120.0, 120.0, 79.5, 59.5)
H_SMALL, W_SMALL = 120, 160


@dataclass
class SyntheticScene:
    """A ray-castable scene. ``legacy``: the open3d TriangleMesh (ground truth surface)."""

    raycaster: object
    legacy: object

    def render(self, K: np.ndarray, height: int, width: int, T_w_c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """-> rgb (H, W, 3) uint8, depth (H, W) float32 metres (0 where nothing is hit)."""
        import open3d as o3d

        v, u = np.mgrid[0:height, 0:width].astype(np.float64)
        d_c = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1).reshape(-1, 3)
        d_w = d_c @ T_w_c[:3, :3].T
        o_w = np.broadcast_to(T_w_c[:3, 3], d_w.shape)
        rays = o3d.core.Tensor(np.concatenate([o_w, d_w], 1).astype(np.float32))
        t = self.raycaster.cast_rays(rays)["t_hit"].numpy().astype(np.float64)
        hit = np.isfinite(t)
        depth = np.where(hit, t, 0.0)
        pts = o_w + d_w * depth[:, None]
        rgb = np.where(hit[:, None], albedo(pts), 0.0)
        return ((rgb * 255 + 0.5).astype(np.uint8).reshape(height, width, 3),
                depth.astype(np.float32).reshape(height, width))

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (metres) from world points (N, 3) to the ground-truth surface."""
        import open3d as o3d

        return self.raycaster.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def albedo(p: np.ndarray) -> np.ndarray:
    """Smooth procedural colour in [0.1, 0.9] of world points (N, 3)."""
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    r = 0.5 + 0.25 * np.sin(2 * np.pi * (0.9 * x + 0.4 * z)) + 0.15 * np.sin(2 * np.pi * 2.3 * (y - 0.5 * z))
    g = 0.5 + 0.25 * np.sin(2 * np.pi * (0.7 * y + 0.5 * x + 0.3)) + 0.15 * np.sin(2 * np.pi * 2.1 * (z + 0.3 * x))
    b = 0.5 + 0.25 * np.sin(2 * np.pi * (0.8 * z - 0.6 * y + 0.6)) + 0.15 * np.sin(2 * np.pi * 1.9 * (x - y))
    return np.clip(np.stack([r, g, b], -1), 0.1, 0.9)


def box_room() -> SyntheticScene:
    """A 4 x 3.5 x 2.6 m room (the camera sees the inside of its walls) with two boxes and a sphere."""
    import open3d as o3d

    def box(lo, hi):
        m = o3d.geometry.TriangleMesh.create_box(*(np.subtract(hi, lo)))
        m.translate(lo)
        return m

    room = box(ROOM[:, 0], ROOM[:, 1])
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.4, resolution=40)
    sphere.translate([-0.9, -0.6, 0.5])
    mesh = room + box([1.0, 0.5, 0.0], [1.6, 1.1, 0.8]) + box([0.4, -1.3, 0.0], [0.8, -0.9, 1.2]) + sphere
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    return SyntheticScene(scene, mesh)


def look_at(eye: np.ndarray, target: np.ndarray, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV camera pose T_w_c at ``eye`` looking at ``target`` (world z up)."""
    f = np.asarray(target, float) - eye
    f /= np.linalg.norm(f)
    right = np.cross(f, up)
    right /= np.linalg.norm(right)
    down = np.cross(f, right)
    T = np.eye(4)
    T[:3, :3] = np.stack([right, down, f], 1)
    T[:3, 3] = eye
    return T


def trajectory(n: int = 60) -> np.ndarray:
    """(n, 4, 4) smooth camera path in the room (~1 cm and ~0.7 deg per frame for n = 60)."""
    poses = []
    for s in np.linspace(0.0, 1.0, n):
        eye = np.array([-0.6 + 0.6 * s, 0.4 - 0.3 * s, 1.3 + 0.1 * np.sin(np.pi * s)])
        yaw = np.radians(-20 + 60 * s)
        target = eye + np.array([np.cos(yaw), np.sin(yaw), -0.35])
        poses.append(look_at(eye, target))
    return np.stack(poses)


def scene_bound(margin: float = 0.1) -> np.ndarray:
    """Room bound plus a margin (metres)."""
    return ROOM + np.array([-margin, margin])


def umeyama_ate(est: np.ndarray, gt: np.ndarray) -> float:
    """ATE RMSE (metres) of estimated vs ground-truth positions (N, 3) after rigid (no scale) alignment."""
    mu_e, mu_g = est.mean(0), gt.mean(0)
    U, _, Vt = np.linalg.svd((gt - mu_g).T @ (est - mu_e))
    S = np.eye(3)
    S[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ S @ Vt
    aligned = (est - mu_e) @ R.T + mu_g
    return float(np.sqrt(np.mean(np.sum((aligned - gt) ** 2, axis=1))))


def run_and_backprop(fn, module, x):
    """Evaluate ``fn`` at unit coordinates ``x`` (N, 3) and backpropagate a fixed weighting of its (N, C)
    output -> (output, [gradient of the coordinates] + gradients of ``module``'s parameters)."""
    import torch

    xi = x.clone().requires_grad_()
    out = fn(xi)
    (out * torch.linspace(-1, 1, out.shape[1])).sum().backward()
    grads = [xi.grad] + [p.grad.clone() for p in module.parameters()]
    module.zero_grad()
    return out.detach(), grads


def assert_same_values_and_gradients(a, b):
    """Two :func:`run_and_backprop` results agree: values to 1e-5, gradients to 1e-5 of their largest entry."""
    import torch

    torch.testing.assert_close(a[0], b[0], atol=1e-5, rtol=1e-5)
    for ga, gb in zip(a[1], b[1]):
        scale = max(1.0, float(gb.abs().max()))
        torch.testing.assert_close(ga / scale, gb / scale, atol=1e-5, rtol=1e-5)
