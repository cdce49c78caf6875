"""Mesh extraction: marching cubes on the field's SDF, vertex colours from the colour decoder, culling to what
the keyframes observed (ESLAM ``Mesher.get_mesh`` + ``cull_mesh``).

Region: the grown bound, cropped (``crop_to_observed``) to the bounding box of the keyframes' back-projected
depth plus a margin, which saves most of the queries on CPU. Culling (``cull``):
- ``"frustum"`` (default, the evaluation protocol): keep a face when each of its vertices is seen by at least
  one keyframe: it projects inside the image, in front of the camera, onto a pixel with valid depth d, and is
  not occluded (``z <= d + cull_margin``).
- ``"observed"``: additionally the vertex must lie near the observed surface (``|z - d| <= cull_margin``),
  which also removes surfaces the field hallucinated in free space.
- ``"none"``: keep everything.
With ``MapperConfig.keyframe_pixels`` set, keyframes keep only some pixels and culling sees only those.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from lrslam.field.config import MeshConfig
from lrslam.errors import InputError
from lrslam.field.keyframes import ViewPixels
from lrslam.field.model import SceneModel

__all__ = ["MeshConfig", "extract_mesh", "depth_image", "observed_box", "seen_mask"]

log = logging.getLogger(__name__)




def depth_image(view: ViewPixels, height: int) -> np.ndarray:
    """A keyframe's depth as an (H, W) array (pixels not kept are 0)."""
    d = view.depth.detach().cpu().numpy()
    if view.index is None:
        return d.reshape(height, view.width)
    img = np.zeros(height * view.width, dtype=np.float32)
    img[view.index.cpu().numpy()] = d
    return img.reshape(height, view.width)


def observed_box(views: list[ViewPixels], poses: list[np.ndarray], K: np.ndarray, height: int, margin: float,
                 step: int = 4) -> np.ndarray | None:
    """(3, 2) axis-aligned box (metres) around the back-projected depth of the views (at ``poses``, (4, 4)
    ``T_w_c`` each; every ``step``-th pixel), grown by ``margin``; None when no depth is valid."""
    pts = []
    for v, T in zip(views, poses):
        d = depth_image(v, height)[::step, ::step]
        rows, cols = np.nonzero(d > 0)
        if len(rows) == 0:
            continue
        z = d[rows, cols]
        pc = np.stack([(cols * step - K[0, 2]) / K[0, 0] * z, (rows * step - K[1, 2]) / K[1, 1] * z, z], -1)
        pts.append(pc @ T[:3, :3].T + T[:3, 3])
        pts.append(T[:3, 3][None])
    if not pts:
        return None
    p = np.concatenate(pts)
    return np.stack([p.min(0) - margin, p.max(0) + margin], axis=1)


def seen_mask(points: np.ndarray, views: list[ViewPixels], poses: list[np.ndarray], K: np.ndarray, height: int,
              margin: float, near_surface: bool) -> np.ndarray:
    """(V,) bool: which world points (V, 3) some view (at ``poses``, (4, 4) ``T_w_c``) sees (see the module doc
    for the rule)."""
    seen = np.zeros(len(points), dtype=bool)
    for v, T in zip(views, poses):
        d_img = depth_image(v, height)
        h, w = d_img.shape
        pc = (points - T[:3, 3]) @ T[:3, :3]  # world -> camera: R^T (p - t)
        z = pc[:, 2]
        front = z > 1e-6
        u = np.full(len(points), -1, dtype=np.int64)
        r = np.full(len(points), -1, dtype=np.int64)
        u[front] = np.round(K[0, 0] * pc[front, 0] / z[front] + K[0, 2]).astype(np.int64)
        r[front] = np.round(K[1, 1] * pc[front, 1] / z[front] + K[1, 2]).astype(np.int64)
        inside = front & (u >= 0) & (u < w) & (r >= 0) & (r < h)
        d = np.zeros(len(points), dtype=np.float32)
        d[inside] = d_img[r[inside], u[inside]]
        ok = inside & (d > 0) & (z <= d + margin)
        if near_surface:
            ok &= z >= d - margin
        seen |= ok
    return seen


@torch.no_grad()
def _sdf_volume(model: SceneModel, axes: list[np.ndarray], chunk: int) -> np.ndarray:
    """SDF on the grid ``axes`` (x, y, z node coordinates, metres) -> (nx, ny, nz) float64 volume, evaluated
    slab by slab so the grid coordinates are never all in memory."""
    nx, ny, nz = (len(a) for a in axes)
    volume = np.empty((nx, ny, nz), dtype=np.float32)
    yz = np.stack(np.meshgrid(axes[1], axes[2], indexing="ij"), -1).reshape(-1, 2)
    step = max(1, chunk // len(yz))
    dev = model.device
    with model.frozen():
        for i in range(0, nx, step):
            xs = axes[0][i:i + step]
            pts = np.concatenate([np.repeat(xs, len(yz))[:, None], np.tile(yz, (len(xs), 1))], 1)
            vals = [model.sdf(torch.tensor(pts[s:s + chunk], dtype=torch.float32, device=dev)).cpu().numpy()
                    for s in range(0, len(pts), chunk)]
            volume[i:i + step] = np.concatenate(vals).reshape(len(xs), ny, nz)
    return volume.astype(np.float64)


@torch.no_grad()
def extract_mesh(model: SceneModel, views: list[ViewPixels], poses: list[np.ndarray], K: np.ndarray, height: int,
                 cfg: MeshConfig = MeshConfig(), resolution: float | None = None):
    """Marching cubes on the zero level set of the SDF.

    Args:
        model: the scene model. views: keyframes (depth) for cropping and culling, seen from ``poses``
        ((4, 4) ``T_w_c`` each, same order). K: (3, 3).
        height: image height (pixels). cfg: settings. resolution: overrides ``cfg.resolution`` (metres).
    Returns:
        ``trimesh.Trimesh`` in world metres with uint8 RGBA vertex colours (empty when no surface is found).
    """
    import mcubes
    import trimesh

    res = cfg.resolution if resolution is None else float(resolution)
    if not res > 0:
        raise InputError(f"mesh resolution must be > 0 metres, got {res}")
    # 1. Region and grid.
    box = model.bound_np.copy()
    if cfg.crop_to_observed and views:
        obs = observed_box(views, poses, K, height, model.truncation + 2 * res)
        if obs is not None:
            box = np.stack([np.maximum(box[:, 0], obs[:, 0]), np.minimum(box[:, 1], obs[:, 1])], axis=1)
    axes = [np.arange(lo, hi + 0.5 * res, res) for lo, hi in box]
    if min(len(a) for a in axes) < 2:
        log.warning("mesh: empty region %s", box.tolist())
        return trimesh.Trimesh()
    # 2. SDF on the grid (frozen field, chunked).
    volume = _sdf_volume(model, axes, cfg.chunk)
    if not (volume.min() < 0 < volume.max()):
        log.warning("mesh: the SDF has no zero crossing in the region; empty mesh")
        return trimesh.Trimesh()
    # 3. Marching cubes (PyMCubes: vertices in index coordinates; faces wound for positive-outside volumes after
    #    the flip below, so normals point into free space).
    verts, faces = mcubes.marching_cubes(-volume, 0.0)
    verts = box[:, 0] + verts * res
    # 4. Cull faces not observed by any keyframe.
    if cfg.cull != "none" and views:
        keep_v = seen_mask(verts, views, poses, K, height, cfg.cull_margin, near_surface=cfg.cull == "observed")
        faces = faces[keep_v[faces].all(axis=1)]
    mesh = trimesh.Trimesh(verts, faces, process=False)
    mesh.remove_unreferenced_vertices()
    # 5. Vertex colours from the colour decoder.
    dev = model.device
    if len(mesh.vertices):
        with model.frozen():
            v = np.asarray(mesh.vertices)
            rgb = torch.cat([model.colour(torch.tensor(v[s:s + cfg.chunk], dtype=torch.float32, device=dev)).cpu()
                             for s in range(0, len(v), cfg.chunk)]).numpy()
        rgba = np.concatenate([np.clip(rgb * 255.0 + 0.5, 0, 255), np.full((len(v), 1), 255.0)], -1).astype(np.uint8)
        mesh.visual.vertex_colors = rgba
    return mesh
