"""Mesh-evaluation protocols: which culling, alignment, sample count and depth-L1 views a mesh metric uses.

Presets (sources: idiap/ESLAM and cvg/nice-slam ``src/tools/eval_recon.py`` and ``cull_mesh.py``):

======================  ==========  ==========  =========  =========  ==========  ===========================
protocol                face kept   poses       occlusion  ICP        points      depth L1
======================  ==========  ==========  =========  =========  ==========  ===========================
``eslam`` (default)     any vertex  all frames  0.06 m     0.1 m p2p  450,000     1000 views in the GT box
``nice-slam``           any vertex  all frames  none       0.1 m p2p  200,000     1000 views in the GT box
``lrslam-v0`` (ours)    all verts   <= 50       0.03 m     none       200,000     100 views near the trajectory
======================  ==========  ==========  =========  =========  ==========  ===========================

* Face rule: ESLAM / NICE-SLAM drop a face only when none of its vertices is seen (keep on *any*); our first
  protocol kept faces with *all* vertices seen.
* Occlusion: ESLAM's Replica evaluation (``eval_rec``) keeps a vertex only when it is no more than the truncation
  (0.06 m) behind the frame's depth; we ray-cast the mesh itself (its own depth map) with that tolerance.
  NICE-SLAM culls by frustum only.
* ICP: ``registration_icp`` point-to-point between the meshes' vertices, threshold 0.1 m, from identity, applied
  to the estimate before every metric.
* Points: ESLAM's ``calc_3d_metric(num_points=450000)``; NICE-SLAM samples 200,000.
* Depth L1: :mod:`~lrslam.evaluation.depth_views` (NICE-SLAM's views; all pixels count) or, for
  ``lrslam-v0``, views within 10 cm / 10 degrees of the trajectory counting pixels that see GT surface.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Literal

from lrslam.errors import InputError

__all__ = ["MeshProtocol", "PROTOCOLS", "get_protocol"]


@dataclass(frozen=True)
class MeshProtocol:
    """How a mesh is evaluated (see the module table).

    face_rule: ``"any"`` / ``"all"`` vertices seen to keep a face. max_poses: cull against at most this many
    evenly strided poses (None: every frame). occlusion_tol: metres a vertex may lie behind the first surface
    and still count as seen (None: frustum only). icp: refine the estimate onto the GT first (threshold
    ``icp_threshold`` metres). n_points: points sampled per mesh. threshold: completion-ratio distance, metres.
    depth_views: number of depth-L1 views (0: none). depth_l1: ``"bbox"`` (NICE-SLAM) or ``"trajectory"``.
    """

    name: str
    face_rule: Literal["any", "all"] = "any"
    max_poses: int | None = None
    occlusion_tol: float | None = 0.06
    icp: bool = True
    icp_threshold: float = 0.1
    n_points: int = 450_000
    threshold: float = 0.05
    depth_views: int = 1000
    depth_l1: Literal["bbox", "trajectory"] = "bbox"

    def stride(self, n_poses: int) -> int:
        """Pose stride giving at most ``max_poses`` of ``n_poses`` poses (1 = all)."""
        return 1 if self.max_poses is None else max(1, -(-int(n_poses) // int(self.max_poses)))


PROTOCOLS: dict[str, MeshProtocol] = {
    "eslam": MeshProtocol("eslam"),
    "nice-slam": MeshProtocol("nice-slam", occlusion_tol=None, n_points=200_000),
    "lrslam-v0": MeshProtocol("lrslam-v0", face_rule="all", max_poses=50, occlusion_tol=0.03, icp=False,
                              n_points=200_000, depth_views=100, depth_l1="trajectory"),
}


def get_protocol(name: str = "eslam", **overrides) -> MeshProtocol:
    """A preset by name with fields replaced by ``overrides`` whose value is not None (CLI options)."""
    if name not in PROTOCOLS:
        raise InputError(f"unknown mesh protocol {name!r}; known: {', '.join(PROTOCOLS)}")
    p = replace(PROTOCOLS[name], **{k: v for k, v in overrides.items() if v is not None})
    if p.face_rule not in ("any", "all") or p.depth_l1 not in ("bbox", "trajectory"):
        raise InputError(f"mesh protocol: face_rule must be any|all and depth_l1 bbox|trajectory, got "
                         f"{p.face_rule!r} and {p.depth_l1!r}")
    if p.n_points < 1 or p.depth_views < 0 or not p.threshold > 0:
        raise InputError(f"mesh protocol: need n_points >= 1, depth_views >= 0, threshold > 0, got {p.n_points}, "
                         f"{p.depth_views}, {p.threshold}")
    return p
