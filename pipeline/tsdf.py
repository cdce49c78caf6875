"""Reference mesh for the frontend-only mode: TSDF fusion of the frames at given poses (Open3D tensor API,
``VoxelBlockGrid``: hashed 16^3 voxel blocks, so memory follows the observed surface, not the bound).

Open3D's legacy ``ScalableTSDFVolume`` returned empty meshes with open3d 0.20 pip wheels here (even for one
frame of valid depth), which is why this uses the tensor API (test: the frontend run's mesh has faces).
"""

from __future__ import annotations

import logging

import numpy as np

__all__ = ["tsdf_mesh"]

log = logging.getLogger(__name__)


def tsdf_mesh(frames, poses: np.ndarray, voxel: float = 0.02, depth_max: float = 5.0, every: int = 1,
              weight_threshold: float = 1.0, block_count: int = 1000):
    """Fuse ``frames`` (iterable of Frame) at ``poses`` (N, 4, 4) ``T_w_c`` into a TSDF and extract a triangle
    mesh (``trimesh.Trimesh`` with vertex colours, world frame, metres). ``voxel`` metres (truncation 4 voxels);
    ``weight_threshold``: voxels seen fewer times are left out of the surface. ``block_count``: the hash map's
    initial capacity in blocks (16^3 voxels x 20 bytes = 80 kB each); it grows as needed, so a small start
    keeps memory to the observed surface (TUM excerpt, 120 frames: the same 254 438 faces with 500 as with
    40 000 blocks, peak RSS 0.43 vs 3.5 GB)."""
    import open3d as o3d
    import open3d.core as o3c
    import trimesh

    vbg = o3d.t.geometry.VoxelBlockGrid(attr_names=("tsdf", "weight", "color"),
                                        attr_dtypes=(o3c.float32, o3c.float32, o3c.float32),
                                        attr_channels=((1), (1), (3)), voxel_size=voxel, block_resolution=16,
                                        block_count=block_count)
    n_fused = 0
    for i, frame in enumerate(frames):
        if i % every or i >= len(poses) or frame.valid_depth_fraction() == 0 or not np.all(np.isfinite(poses[i])):
            continue
        depth = o3d.t.geometry.Image(np.ascontiguousarray(frame.depth, dtype=np.float32))
        colour = o3d.t.geometry.Image(np.ascontiguousarray(frame.rgb, dtype=np.float32) / 255.0)
        K = o3c.Tensor(np.asarray(frame.K, dtype=np.float64))
        T_c_w = o3c.Tensor(np.linalg.inv(poses[i]))
        blocks = vbg.compute_unique_block_coordinates(depth, K, T_c_w, 1.0, depth_max, trunc_voxel_multiplier=4.0)
        vbg.integrate(blocks, depth, colour, K, T_c_w, 1.0, depth_max, trunc_voxel_multiplier=4.0)
        n_fused += 1
    if n_fused == 0:
        log.warning("TSDF fusion: no frame with valid depth; empty mesh")
        return trimesh.Trimesh()
    m = vbg.extract_triangle_mesh(weight_threshold=weight_threshold).to_legacy()
    colours = (np.clip(np.asarray(m.vertex_colors), 0.0, 1.0) * 255).astype(np.uint8)
    return trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.triangles),
                           vertex_colors=colours if len(colours) else None, process=False)
