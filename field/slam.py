"""The field SLAM facade the pipeline uses: one scene model, the tracker, the mapper and the mesher behind a
numpy API (poses (4, 4) float64 ``T_w_c``, OpenCV camera; rgb (H, W, 3) uint8; depth (H, W) float32 metres,
0 = invalid). Torch stays inside :mod:`lrslam.field`.

The facade keeps no camera pose: the pipeline's trajectory owns them and passes the ones a step needs
(``map``, ``remap``, ``extract_mesh`` take the keyframe poses as an argument); optimised poses are returned.
The LRSLAM/ESLAM loop itself (constant-velocity seed, field tracking, mapping every N frames) is the pipeline's
``field`` preset (:mod:`lrslam.pipeline.parts`).
"""

from __future__ import annotations

import logging
import numpy as np
import torch

from lrslam.field.background import BackgroundMapping
from lrslam.field.config import FieldSLAMConfig
from lrslam.camera import check_intrinsics, strided_intrinsics
from lrslam.errors import InputError
from lrslam.geometry import checked_pose
from lrslam.field.grid import check_bound
from lrslam.field.inputs import has_valid_depth, image_tensors, resolve_device
from lrslam.field.keyframes import KeyframeStore
from lrslam.field.mapper import Mapper
from lrslam.field.mesh import extract_mesh
from lrslam.field.model import SceneModel
from lrslam.field.tracker import TrackResult, pose_losses, track

__all__ = ["FieldSLAMConfig", "FieldSLAM"]

log = logging.getLogger(__name__)




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
        self.background: BackgroundMapping | None = None

    def start_background_mapping(self) -> None:
        """From now on :meth:`map_in_background` runs mapping rounds in a worker thread while :meth:`track` and
        :meth:`pose_losses` read a frozen copy of the field, refreshed when a round's result is taken
        (:meth:`take_mapped`); see :mod:`lrslam.field.background`. Call after :meth:`initialise`."""
        self._require_init()
        if self.background is None:
            self.background = BackgroundMapping(self.model, self.cfg.seed)

    # ------------------------------------------------------------------------------------------ SLAM steps
    def initialise(self, frame_id: int, rgb: np.ndarray, depth: np.ndarray, T_w_c: np.ndarray,
                   progress=None) -> dict:
        """First frame: fit the field (``mapping.first_iters`` iterations) with the pose fixed; it becomes
        keyframe ``frame_id`` (never moved by mapping). ``progress(done, total)``: called per iteration.
        Returns stats (iterations, loss terms).
        Raises InputError when the frame has no valid depth or the pose is invalid."""
        T = self._pose(T_w_c)
        rgb_t, depth_t = image_tensors(rgb, depth, self.height, self.width, self.device)
        if not has_valid_depth(depth_t):
            raise InputError(f"frame {frame_id}: the first frame has no valid depth; cannot initialise the field")
        stats = self.mapper.initialise(frame_id, rgb_t, depth_t, T, progress)
        self.initialised = True
        return stats

    def track(self, rgb: np.ndarray, depth: np.ndarray, T_w_c_init: np.ndarray, early_stop: bool = True) -> TrackResult:
        """Refine a seed pose against the frozen field (never raises for a bad frame: ``ok`` False, seed kept);
        ``early_stop`` False: every iteration (:func:`lrslam.field.tracker.track`)."""
        self._require_init()
        model, gen = self._tracking_model()
        return track(model, rgb, depth, self.K, T_w_c_init, self.cfg.tracking, self.cfg.render, gen, early_stop)

    def pose_losses(self, rgb: np.ndarray, depth: np.ndarray, poses: list[np.ndarray]) -> list[float]:
        """The frame's tracking loss at each candidate pose ``T_w_c`` on the same rays (lower: the map agrees
        better); see :func:`lrslam.field.tracker.pose_losses`."""
        self._require_init()
        model, gen = self._tracking_model()
        return pose_losses(model, rgb, depth, self.K, poses, self.cfg.tracking, self.cfg.render, gen)

    def _tracking_model(self):
        if self.background is not None:
            return self.background.tracking_model, self.background.tracking_gen
        return self.model, self.gen

    def map(self, frame_id: int, rgb: np.ndarray, depth: np.ndarray, T_w_c: np.ndarray,
            keyframe_poses: dict[int, np.ndarray], add_keyframe: bool) -> dict[int, np.ndarray]:
        """Joint field + window-pose optimisation around the current frame at ``T_w_c``; ``keyframe_poses``
        are the current ``T_w_c`` of the keyframes (by frame id, from the trajectory's owner).

        Returns the optimised poses by frame id (window keyframes whose pose moved, the current frame always).
        A frame without valid depth is not mapped (logged; returns ``{frame_id: T_w_c}``) and not added.
        """
        self._require_init()
        T = self._pose(T_w_c)
        rgb_t, depth_t = image_tensors(rgb, depth, self.height, self.width, self.device)
        if not has_valid_depth(depth_t):
            log.warning("frame %d: no valid depth; not mapped, not added as keyframe", frame_id)
            return {frame_id: T}
        poses, _stats = self.mapper.map(frame_id, rgb_t, depth_t, T, keyframe_poses, add_keyframe,
                                        depth_t.cpu().numpy())
        return poses

    def map_in_background(self, frame_id: int, rgb: np.ndarray, depth: np.ndarray, T_w_c: np.ndarray,
                          keyframe_poses: dict[int, np.ndarray], add_keyframe: bool) -> None:
        """:meth:`map` in the worker thread (after :meth:`start_background_mapping`); its result comes from
        :meth:`take_mapped`, which must be called before the next round."""
        if self.background is None:
            raise RuntimeError("FieldSLAM.start_background_mapping() was not called")
        kf = {k: np.array(T, dtype=np.float64) for k, T in keyframe_poses.items()}
        T, rgb, depth = np.array(T_w_c, dtype=np.float64), np.array(rgb), np.array(depth)
        self.background.submit(lambda: self.map(frame_id, rgb, depth, T, kf, add_keyframe))

    def take_mapped(self) -> dict[int, np.ndarray] | None:
        """Wait for the background round and return its optimised poses (as :meth:`map`; None when no round
        was submitted); the tracker sees the mapped field from now on."""
        return None if self.background is None else self.background.take()

    def stop_background_mapping(self) -> None:
        """Stop the worker thread (a round's result not yet taken is dropped): tracking reads the field again."""
        if self.background is not None:
            self.background.close()
            self.background = None

    def _idle(self) -> None:
        """Wait for a running background round (its result stays to be taken)."""
        if self.background is not None:
            self.background.wait()

    def keyframe_ids(self) -> list[int]:
        """Frame ids of the stored keyframes (pixels), in insertion order."""
        self._idle()
        return self.mapper.keyframes.ids()

    @property
    def reverted_poses(self) -> int:
        """Window poses the mapping divergence guard reverted so far."""
        return self.mapper.reverted_poses

    def remap(self, keyframe_poses: dict[int, np.ndarray], keyframe_ids: list[int] | None = None,
              iters: int | None = None) -> dict:
        """Field-only re-optimisation with the keyframes fixed at ``keyframe_poses`` (e.g. after a pose-graph
        correction), over ``keyframe_ids`` (None = all). A background round's result must have been taken."""
        self._require_init()
        if self.background is not None and self.background.busy:
            raise RuntimeError("FieldSLAM.remap: take_mapped() the background round first")
        return self.mapper.remap({k: self._pose(T) for k, T in keyframe_poses.items()}, keyframe_ids, iters)

    def extract_mesh(self, keyframe_poses: dict[int, np.ndarray], resolution: float | None = None):
        """Marching-cubes mesh of the field (world metres, vertex colours), culled to what the keyframes (at
        ``keyframe_poses``) saw."""
        self._idle()
        ids = [k for k in self.mapper.keyframes.ids() if k in keyframe_poses]
        views = [self.mapper.keyframes.get(k) for k in ids]
        poses = [np.asarray(keyframe_poses[k], dtype=np.float64) for k in ids]
        return extract_mesh(self.model, views, poses, self.K, self.height, self.cfg.mesh, resolution)

    def render(self, T_w_c: np.ndarray, scale: int = 4,
               depth: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The field seen from ``T_w_c`` (4, 4) at the pixels of ``image[::scale, ::scale]`` ((h, w) = ceil of
        (H, W) / scale; :func:`lrslam.camera.strided_intrinsics`): depth (h, w) float32 metres (0 where the rays
        hit nothing) and colour (h, w, 3) float32 in [0, 1] (Eq. volume_render, no jitter). ``depth``: the
        frame's (H, W) metres, 0 = invalid; strided alike, it guides the samples as in tracking (hierarchical
        sampling where it is 0 or None). Reads the field only (with background mapping, the tracking copy: never
        waits for a mapping round)."""
        from lrslam.field.render import render_image

        self._require_init()
        s = max(int(scale), 1)
        h, w = -(-self.height // s), -(-self.width // s)
        guide = None if depth is None else np.asarray(depth, dtype=np.float32)[::s, ::s]
        model, _ = self._tracking_model()
        with model.frozen():
            return render_image(model, strided_intrinsics(self.K, s), self._pose(T_w_c), h, w, model.truncation,
                                self.cfg.render, guide)

    def depth_error(self, keyframe_poses: dict[int, np.ndarray], keyframe_ids: list[int] | None = None,
                    n_rays: int = 2000) -> float:
        """Mean absolute difference (metres) between rendered and sensor depth over random pixels of the given
        keyframes (None = all) at ``keyframe_poses``: how well the surface agrees with those poses."""
        from lrslam.field.mapper import depth_error

        self._idle()
        ids = [k for k in (keyframe_ids or self.mapper.keyframes.ids()) if k in keyframe_poses]
        return depth_error(self.model, [self.mapper.keyframes.get(k) for k in ids],
                           [np.asarray(keyframe_poses[k], dtype=np.float64) for k in ids], self.K, self.cfg.render,
                           n_rays, torch.Generator().manual_seed(0))

    def parameter_count(self) -> dict[str, int]:
        """Counts by part: see :meth:`SceneModel.parameter_count` (``total`` includes the decoders, as the
        paper's Table 1 Total)."""
        return self.model.parameter_count()

    # ------------------------------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Run state as plain Python/numpy: config, bound, intrinsics, field tensors (decoders, beta included),
        keyframe pixels (poses belong to the trajectory), RNG states and the mapper's counter. No optimiser state:
        every mapping round and tracking call starts its own Adam (as ESLAM). With background mapping, the running
        round is waited for and the tracking copy, its generator and the round's result not yet taken are saved
        too. Restore with :meth:`load_state_dict`."""
        self._idle()
        return {
            "background": self.background.state_dict() if self.background is not None else None,
            "config": self.cfg.model_dump(mode="json"),
            "bound": self.model.bound_np.copy(),
            "K": self.K.copy(), "height": self.height, "width": self.width,
            "model": {k: v.detach().cpu().numpy() for k, v in self.model.state_dict().items()},
            "keyframes": self.mapper.keyframes.state(),
            "generator": self.gen.get_state().numpy(),
            "rng": self.mapper.rng.bit_generator.state,
            "initialised": self.initialised,
            "reverted_poses": self.mapper.reverted_poses,
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
        self.mapper.reverted_poses = int(state.get("reverted_poses", 0))
        if state.get("background") is not None:
            self.start_background_mapping()
            self.background.load_state_dict(state["background"])

    # ------------------------------------------------------------------------------------------ helpers
    def _require_init(self) -> None:
        if not self.initialised:
            raise RuntimeError("FieldSLAM.initialise() must be called with the first frame first")

    @staticmethod
    def _pose(T: np.ndarray) -> np.ndarray:
        return checked_pose(T, "camera pose", tol=1e-3)
