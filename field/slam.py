"""The field SLAM facade the pipeline uses: one scene model, the tracker, the mapper and the mesher behind a
numpy API (poses (4, 4) float64 ``T_w_c``, OpenCV camera; rgb (H, W, 3) uint8; depth (H, W) float32 metres,
0 = invalid). Torch stays inside :mod:`lrslam.field`.

``run_field_slam`` is the LRSLAM/ESLAM-faithful loop (constant-velocity seed, field tracking, mapping every
``map_every`` frames, a keyframe every ``keyframe_every`` frames), used by tests and mirrored by
``lrslam run --mode field``.
"""

from __future__ import annotations

import logging
from typing import Iterable

import numpy as np
import torch

from lrslam.config import StrictModel
from lrslam.camera import check_intrinsics
from lrslam.errors import InputError
from lrslam.geometry import inv, is_valid_pose
from lrslam.field.grid import check_bound
from lrslam.field.inputs import image_tensors, resolve_device
from lrslam.field.keyframes import KeyframeStore
from lrslam.field.mapper import Mapper, MapperConfig
from lrslam.field.mesh import MeshConfig, extract_mesh
from lrslam.field.model import SceneModel, SceneModelConfig
from lrslam.field.render import RenderConfig
from lrslam.field.tracker import TrackerConfig, TrackResult, track

__all__ = ["FieldSLAMConfig", "FieldSLAM", "run_field_slam"]

log = logging.getLogger(__name__)


class FieldSLAMConfig(StrictModel):
    """Everything the field needs. Defaults: the paper's LRSLAM on Replica (ESLAM settings).
    device: ``"auto"`` (CUDA when available), ``"cpu"``, ``"cuda:0"`` ... seed: RNG seed (pixels, jitter,
    window selection, initial features)."""

    model: SceneModelConfig = SceneModelConfig()
    render: RenderConfig = RenderConfig()
    tracking: TrackerConfig = TrackerConfig()
    mapping: MapperConfig = MapperConfig()
    mesh: MeshConfig = MeshConfig()
    device: str = "auto"
    seed: int = 0

    @classmethod
    def cpu_small(cls, **overrides) -> "FieldSLAMConfig":
        """A CPU-sized variant (same model, fewer rays and iterations, coarser mesh) for tests and laptops.
        ``overrides`` replace top-level sections."""
        base = dict(
            render=RenderConfig(n_stratified=24, n_importance=8),
            tracking=TrackerConfig(iters=12, n_rays=400, ignore_edge_h=4, ignore_edge_w=4),
            mapping=MapperConfig(iters=15, n_rays=800, first_iters=100, window_size=8, remap_iters=20),
            mesh=MeshConfig(resolution=0.03),
            device="cpu",
        )
        return cls(**(base | overrides))


class FieldSLAM:
    """Dense SLAM on one LRSLAM field.

    Args:
        cfg: settings. bound: (3, 2) scene bound in metres (world frame; grown to multiples of 0.24 m).
        K: (3, 3) intrinsics. height, width: image size in pixels.
    Raises:
        InputError: bad bound or intrinsics.
    """

    def __init__(self, cfg: FieldSLAMConfig, bound: np.ndarray, K: np.ndarray, height: int, width: int) -> None:
        self.cfg = cfg
        try:
            self.K = check_intrinsics(K, width, height)
        except ValueError as e:
            raise InputError(str(e)) from None
        self.height, self.width = int(height), int(width)
        self.device = resolve_device(cfg.device)
        self.model = SceneModel(check_bound(bound), cfg.model, self.device, seed=cfg.seed)
        self.gen = torch.Generator().manual_seed(cfg.seed)
        self.mapper = Mapper(self.model, self.K, self.height, self.width, cfg.mapping, cfg.render, self.gen, cfg.seed)
        self.initialised = False

    # ------------------------------------------------------------------------------------------ SLAM steps
    def initialise(self, frame_id: int, rgb: np.ndarray, depth: np.ndarray, T_w_c: np.ndarray) -> dict:
        """First frame: fit the field (``mapping.first_iters`` iterations) with the pose fixed; it becomes
        keyframe ``frame_id`` (never moved by mapping). Returns stats (iterations, loss terms).
        Raises InputError when the frame has no valid depth or the pose is invalid."""
        T = self._pose(T_w_c)
        rgb_t, depth_t = image_tensors(rgb, depth, self.height, self.width, self.device)
        if not bool((depth_t > 0).any()):
            raise InputError(f"frame {frame_id}: the first frame has no valid depth; cannot initialise the field")
        stats = self.mapper.initialise(frame_id, rgb_t, depth_t, T)
        self.initialised = True
        return stats

    def track(self, rgb: np.ndarray, depth: np.ndarray, T_w_c_init: np.ndarray) -> TrackResult:
        """Refine a seed pose against the frozen field (never raises for a bad frame: ``ok`` False, seed kept)."""
        self._require_init()
        return track(self.model, rgb, depth, self.K, T_w_c_init, self.cfg.tracking, self.cfg.render, self.gen)

    def map(self, frame_id: int, rgb: np.ndarray, depth: np.ndarray, T_w_c: np.ndarray,
            add_keyframe: bool) -> dict[int, np.ndarray]:
        """Joint field + window-pose optimisation around the current frame.

        Returns the optimised poses by frame id (window keyframes whose pose moved, the current frame always).
        A frame without valid depth is not mapped (logged; returns ``{frame_id: T_w_c}``) and not added.
        """
        self._require_init()
        T = self._pose(T_w_c)
        rgb_t, depth_t = image_tensors(rgb, depth, self.height, self.width, self.device)
        if not bool((depth_t > 0).any()):
            log.warning("frame %d: no valid depth; not mapped, not added as keyframe", frame_id)
            return {frame_id: T}
        poses, _stats = self.mapper.map(frame_id, rgb_t, depth_t, T, add_keyframe, depth_t.cpu().numpy())
        return poses

    def keyframe_poses(self) -> dict[int, np.ndarray]:
        """Current keyframe poses by frame id ((4, 4) float64 copies)."""
        return self.mapper.keyframes.poses()

    def set_keyframe_poses(self, poses: dict[int, np.ndarray]) -> None:
        """Replace keyframe poses (e.g. after pose-graph optimisation); unknown ids are ignored (logged)."""
        unknown = []
        for k, T in poses.items():
            if k in self.mapper.keyframes:
                self.mapper.keyframes.set_pose(k, self._pose(T))
            else:
                unknown.append(k)
        if unknown:
            log.debug("set_keyframe_poses: ids %s are not field keyframes", unknown)

    def remap(self, keyframe_ids: list[int] | None = None, iters: int | None = None) -> dict:
        """Field-only re-optimisation (poses fixed) over the given keyframes (None = all)."""
        self._require_init()
        return self.mapper.remap(keyframe_ids, iters)

    def extract_mesh(self, resolution: float | None = None):
        """Marching-cubes mesh of the field (world metres, vertex colours), culled to what keyframes saw."""
        views = [self.mapper.keyframes.get(k) for k in self.mapper.keyframes.ids()]
        return extract_mesh(self.model, views, self.K, self.height, self.cfg.mesh, resolution)

    def parameter_count(self) -> dict[str, int]:
        """{"geometry", "appearance", "decoders", "total" (= encodings, as the paper)}."""
        return self.model.parameter_count()

    # ------------------------------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Run state as plain Python/numpy: config, bound, intrinsics, field tensors (decoders, beta included),
        keyframes (ids, poses, pixels) and RNG state. Restore with :meth:`load_state_dict`."""
        return {
            "config": self.cfg.model_dump(mode="json"),
            "bound": self.model.bound_np.copy(),
            "K": self.K.copy(), "height": self.height, "width": self.width,
            "model": {k: v.detach().cpu().numpy() for k, v in self.model.state_dict().items()},
            "keyframes": self.mapper.keyframes.state(),
            "generator": self.gen.get_state().numpy(),
            "rng": self.mapper.rng.bit_generator.state,
            "initialised": self.initialised,
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` output into a FieldSLAM built with the same config, bound and camera."""
        if not np.allclose(state["bound"], self.model.bound_np) or (state["height"], state["width"]) != (
                self.height, self.width):
            raise InputError("state was saved for a different scene bound or image size")
        self.model.load_state_dict({k: torch.as_tensor(v) for k, v in state["model"].items()})
        self.mapper.keyframes = KeyframeStore.from_state(state["keyframes"], self.device)
        self.gen.set_state(torch.as_tensor(state["generator"], dtype=torch.uint8))
        self.mapper.rng.bit_generator.state = state["rng"]
        self.initialised = bool(state["initialised"])

    # ------------------------------------------------------------------------------------------ helpers
    def _require_init(self) -> None:
        if not self.initialised:
            raise RuntimeError("FieldSLAM.initialise() must be called with the first frame first")

    @staticmethod
    def _pose(T: np.ndarray) -> np.ndarray:
        T = np.asarray(T, dtype=np.float64)
        if not is_valid_pose(T, tol=1e-3):
            raise InputError("camera pose must be a finite 4x4 rigid transform")
        return T.copy()


def run_field_slam(frames: Iterable[tuple[np.ndarray, np.ndarray]], cfg: FieldSLAMConfig, bound: np.ndarray,
                   K: np.ndarray, height: int, width: int, T_w_c_first: np.ndarray, map_every: int = 4,
                   keyframe_every: int = 4, slam: FieldSLAM | None = None) -> tuple[np.ndarray, FieldSLAM]:
    """Field-only SLAM over ``(rgb, depth)`` frames (ESLAM's loop, sequential).

    1. frame 0: initialise at ``T_w_c_first``; 2. seed ``T_{i-1} inv(T_{i-2}) T_{i-1}`` (constant velocity);
    3. track; 4. every ``map_every`` frames map (a keyframe every ``keyframe_every`` frames); keyframe poses
    moved by joint mapping are written back into the trajectory (ESLAM keeps them only in its keyframe list).

    Returns:
        (poses (N, 4, 4) float64 T_w_c, the FieldSLAM object).
    """
    slam = slam or FieldSLAM(cfg, bound, K, height, width)
    poses: list[np.ndarray] = []
    for i, (rgb, depth) in enumerate(frames):
        if i == 0:
            slam.initialise(0, rgb, depth, T_w_c_first)
            poses.append(np.asarray(T_w_c_first, dtype=np.float64).copy())
            continue
        seed = poses[-1] if i < 2 else poses[-1] @ inv(poses[-2]) @ poses[-1]
        res = slam.track(rgb, depth, seed)
        poses.append(res.T_w_c)
        if i % map_every == 0:
            out = slam.map(i, rgb, depth, poses[-1], add_keyframe=i % keyframe_every == 0)
            for fid, T in out.items():
                poses[fid] = T
    return np.stack(poses), slam
