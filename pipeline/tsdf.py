"""Reference mesh for the frontend-only mode: Open3D scalable TSDF fusion of the frames at given poses."""

from __future__ import annotations

import numpy as np

__all__ = ["tsdf_mesh"]


def tsdf_mesh(frames, poses: np.ndarray, voxel: float = 0.02, depth_max: float = 5.0, every: int = 1):
    """Fuse ``frames`` (iterable of Frame) at ``poses`` (N, 4, 4) ``T_w_c`` into a TSDF and extract a
    triangle mesh (trimesh.Trimesh with vertex colours). ``voxel`` metres; truncation = 4 voxels."""
    import open3d as o3d
    import trimesh

    vol = o3d.pipelines.integration.ScalableTSDFVolume(
        voxel_length=voxel, sdf_trunc=4 * voxel, color_type=o3d.pipelines.integration.TSDFVolumeColorType.RGB8)
    for i, frame in enumerate(frames):
        if i % every or i >= len(poses) or frame.valid_depth_fraction() == 0:
            continue
        K = frame.K
        intr = o3d.camera.PinholeCameraIntrinsic(frame.width, frame.height, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        rgbd = o3d.geometry.RGBDImage.create_from_color_and_depth(
            o3d.geometry.Image(np.ascontiguousarray(frame.rgb)), o3d.geometry.Image(frame.depth.astype(np.float32)),
            depth_scale=1.0, depth_trunc=depth_max, convert_rgb_to_intensity=False)
        vol.integrate(rgbd, intr, np.linalg.inv(poses[i]))
    m = vol.extract_triangle_mesh()
    return trimesh.Trimesh(np.asarray(m.vertices), np.asarray(m.triangles),
                           vertex_colors=(np.asarray(m.vertex_colors) * 255).astype(np.uint8), process=False)
