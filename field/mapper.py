"""Mapping: joint optimisation of the field and the window's camera poses (ESLAM ``Mapper.optimize_mapping``).

Window (ESLAM ``overlap`` rule): up to ``window_size - 1`` keyframes that overlap the current view (chosen at
random among the overlapping ones, the last two keyframes excluded), plus the last two keyframes, plus the
current frame. Each iteration samples ``n_rays / |window|`` pixels per view, renders them and takes one Adam step
on the feature lines/planes (lr 0.005), the decoders and beta (lr 0.001) and, once the map holds enough
keyframes, on the poses of all window views except the oldest (lr 0.001), the current frame included. The
first frame is fitted alone for ``first_iters`` iterations with all learning rates x ``lr_first_factor``.

``remap`` re-fits the field alone (poses fixed) over chosen keyframes, e.g. after a pose graph moved them.
"""

from __future__ import annotations

import logging

import numpy as np
import torch

from lrslam.config import StrictModel
from lrslam.field.keyframes import KeyframeStore, ViewPixels, select_overlapping
from lrslam.field.losses import MAPPING_WEIGHTS, LossWeights, rendering_loss
from lrslam.field.model import SceneModel
from lrslam.field.poses import PoseParameterisation, PoseParams
from lrslam.field.rays import PixelBatch, camera_directions, ray_exit_depth, world_rays
from lrslam.field.render import RenderConfig, render_rays

__all__ = ["MapperConfig", "Mapper"]

log = logging.getLogger(__name__)


class MapperConfig(StrictModel):
    """Mapping settings. Defaults: ESLAM on Replica (15 iterations x 4000 pixels; first frame 1000 iterations
    at 5x learning rates; window 20; joint pose optimisation once more than 4 keyframes exist).

    lr_encoding / lr_decoder: Adam lrs of the feature lines/planes and of the MLPs + beta. lr_pose_rot /
    lr_pose_trans: window-pose lrs (ESLAM ``joint_opt_cam_lr``; rotation in quaternion units, see
    :mod:`.poses`). keyframe_pixels: keep only this many random pixels per keyframe (None = all).
    remap_iters / remap_views: defaults of :meth:`Mapper.remap` (iterations; views sampled per iteration).
    """

    iters: int = 15
    n_rays: int = 4000
    first_iters: int = 1000
    lr_first_factor: float = 5.0
    lr_encoding: float = 0.005
    lr_decoder: float = 0.001
    joint_opt: bool = True
    joint_opt_min_keyframes: int = 5
    lr_pose_rot: float = 0.001
    lr_pose_trans: float = 0.001
    pose_parameterisation: PoseParameterisation = "quat"
    window_size: int = 20
    overlap_pixels: int = 50
    weights: LossWeights = MAPPING_WEIGHTS
    keyframe_pixels: int | None = None
    remap_iters: int = 30
    remap_views: int = 20
    max_bad_steps: int = 3


class Mapper:
    """Owns the keyframe database and optimises the field (and window poses) of a :class:`SceneModel`.

    Args:
        model: the scene model (optimised in place). K: (3, 3) intrinsics; height, width: image size (pixels).
        cfg: mapping settings. render: sampling settings. generator: torch RNG (CPU). seed: numpy RNG seed for
        the window selection.
    """

    def __init__(self, model: SceneModel, K: np.ndarray, height: int, width: int, cfg: MapperConfig = MapperConfig(),
                 render: RenderConfig = RenderConfig(), generator: torch.Generator | None = None, seed: int = 0):
        self.model, self.cfg, self.render = model, cfg, render
        self.K = np.asarray(K, dtype=np.float64)
        self.height, self.width = height, width
        self.keyframes = KeyframeStore()
        self.gen = generator if generator is not None else torch.Generator().manual_seed(seed)
        self.rng = np.random.default_rng(seed)
        self._Kt = torch.tensor(self.K, dtype=torch.float32, device=model.device)

    # ------------------------------------------------------------------------------------------ public steps
    def initialise(self, frame_id: int, rgb: torch.Tensor, depth: torch.Tensor, T_w_c: np.ndarray) -> dict:
        """Fit the field to the first frame (pose fixed) and store it as keyframe. rgb (H, W, 3) uint8 and depth
        (H, W) metres tensors on the model's device. Returns stats (iterations, final loss terms)."""
        view = ViewPixels.from_images(frame_id, rgb, depth, T_w_c)
        stats = self._optimise([view], [False], self.cfg.first_iters, self.cfg.lr_first_factor)
        self.keyframes.add(self._keyframe(frame_id, rgb, depth, T_w_c))
        return stats

    def map(self, frame_id: int, rgb: torch.Tensor, depth: torch.Tensor, T_w_c: np.ndarray, add_keyframe: bool,
            depth_np: np.ndarray) -> tuple[dict[int, np.ndarray], dict]:
        """One mapping round for the current frame (tensors as in :meth:`initialise`; ``depth_np`` the same
        depth as numpy, for the window selection).

        Returns:
            (poses by frame id of every view whose pose was optimised, the current frame always included;
            stats dict). Adds the frame as keyframe (with its optimised pose) when ``add_keyframe``.
        """
        # 1. Window: overlapping keyframes + the last two + the current frame.
        ids = self.keyframes.ids()
        last_two = ids[-2:]
        older = {k: T for k, T in self.keyframes.poses().items() if k not in last_two}
        chosen = select_overlapping(older, depth_np, T_w_c, self.K, self.cfg.window_size - 1, self.rng,
                                    n_pixels=self.cfg.overlap_pixels)
        window = sorted(set(chosen) | set(last_two))
        views = [self.keyframes.get(k) for k in window] + [ViewPixels.from_images(frame_id, rgb, depth, T_w_c)]
        # 2. Joint pose optimisation (ESLAM: once more than 4 keyframes exist); the oldest view stays fixed.
        joint = self.cfg.joint_opt and len(self.keyframes) >= self.cfg.joint_opt_min_keyframes and len(views) > 1
        optimise = [joint and i > 0 for i in range(len(views))]
        first_id = ids[0] if ids else None
        optimise = [o and v.frame_id != first_id for o, v in zip(optimise, views)]
        stats = self._optimise(views, optimise, self.cfg.iters, 1.0)
        # 3. Write back.
        out = {v.frame_id: v.T_w_c.copy() for v, o in zip(views, optimise) if o}
        for k in window:
            if k in out:
                self.keyframes.set_pose(k, out[k])
        T_cur = out.get(frame_id, np.asarray(T_w_c, dtype=np.float64).copy())
        out[frame_id] = T_cur
        if add_keyframe:
            self.keyframes.add(self._keyframe(frame_id, rgb, depth, T_cur))
        stats["window"] = window + [frame_id]
        return out, stats

    def remap(self, keyframe_ids: list[int] | None = None, iters: int | None = None) -> dict:
        """Re-optimise the field only (poses fixed) over the given keyframes (None = all). Each iteration
        samples ``n_rays`` over at most ``remap_views`` of them, chosen at random."""
        ids = self.keyframes.ids() if keyframe_ids is None else [k for k in keyframe_ids if k in self.keyframes]
        missing = [] if keyframe_ids is None else [k for k in keyframe_ids if k not in self.keyframes]
        if missing:
            log.warning("remap: ignoring unknown keyframe ids %s", missing)
        if not ids:
            return {"iters": 0, "loss": float("nan")}
        views = [self.keyframes.get(k) for k in ids]
        n_iters = self.cfg.remap_iters if iters is None else iters
        return self._optimise(views, [False] * len(views), n_iters, 1.0, views_per_iter=self.cfg.remap_views)

    # ------------------------------------------------------------------------------------------ internals
    def _keyframe(self, frame_id: int, rgb: torch.Tensor, depth: torch.Tensor, T_w_c: np.ndarray) -> ViewPixels:
        return ViewPixels.from_images(frame_id, rgb, depth, T_w_c, self.cfg.keyframe_pixels, self.gen)

    def _optimise(self, views: list[ViewPixels], optimise_pose: list[bool], iters: int, lr_factor: float,
                  views_per_iter: int | None = None) -> dict:
        """Adam on the field (and the flagged views' poses, written back into ``views[i].T_w_c``)."""
        model, cfg, dev = self.model, self.cfg, self.model.device
        groups = [{"params": model.encoding_parameters(), "lr": cfg.lr_encoding * lr_factor},
                  {"params": model.decoder_parameters(), "lr": cfg.lr_decoder * lr_factor}]
        opt_idx = [i for i, o in enumerate(optimise_pose) if o]
        pose = None
        if opt_idx:
            pose = PoseParams(np.stack([views[i].T_w_c for i in opt_idx]), cfg.pose_parameterisation, dev)
            groups += [{"params": [pose.rotation], "lr": cfg.lr_pose_rot},
                       {"params": [pose.translation], "lr": cfg.lr_pose_trans}]
        opt = torch.optim.Adam(groups)
        fixed = torch.tensor(np.stack([v.T_w_c for v in views]), dtype=torch.float32, device=dev)
        slot = torch.tensor(opt_idx, dtype=torch.long, device=dev)
        bad, done, last_loss, last_terms = 0, 0, None, {}
        for it in range(iters):
            # 1. Pixels from the views (a random subset of views for remapping).
            use = list(range(len(views)))
            if views_per_iter is not None and len(use) > views_per_iter:
                use = sorted(self.rng.choice(len(views), size=views_per_iter, replace=False).tolist())
            per_view = max(1, cfg.n_rays // len(use))
            batch = PixelBatch.cat([views[i].sample(per_view, i, self.gen) for i in use])
            # 2. Rays from the current poses (optimised ones differentiable); surface inside the bound.
            poses = fixed if pose is None else fixed.index_copy(0, slot, pose.matrices())
            o, d = world_rays(camera_directions(batch.u, batch.v, self._Kt), poses, batch.frame)
            inside = ray_exit_depth(o, d, model.bound) >= batch.depth
            o, d, batch = o[inside], d[inside], batch.select(inside)
            if len(batch.depth) == 0:
                continue
            # 3. Render and loss (SDF/depth terms on rays with depth, colour on all).
            r = render_rays(model, o, d, batch.depth, model.truncation, self.render, self.gen)
            has_depth = batch.depth > 0
            loss, terms = rendering_loss(r, batch.depth, batch.rgb, model.truncation, cfg.weights, has_depth,
                                         torch.ones_like(has_depth))
            opt.zero_grad(set_to_none=True)
            if not bool(torch.isfinite(loss)):
                bad += 1
                log.warning("mapping: non-finite loss at iteration %d (%d/%d), step skipped", it, bad,
                            cfg.max_bad_steps)
                if bad >= cfg.max_bad_steps:
                    log.warning("mapping: aborted after %d non-finite losses; poses unchanged", bad)
                    return {"iters": done, "loss": float("nan"), "aborted": True}
                continue
            loss.backward()
            opt.step()
            done, last_loss, last_terms = it + 1, loss.detach(), terms
        if done == 0 and iters > 0:
            log.warning("mapping: no usable rays (valid depth inside the scene bound) in %d iterations", iters)
        if pose is not None:
            if pose.finite():
                for i, T in zip(opt_idx, pose.numpy()):
                    views[i].T_w_c = T
            else:
                log.warning("mapping: window poses became non-finite; keeping the previous poses")
        stats = {"iters": done, "loss": float("nan") if last_loss is None else float(last_loss)}
        return stats | {k: float(v) for k, v in last_terms.items()}
