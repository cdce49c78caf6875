"""Mapping: joint optimisation of the field and the window's camera poses (ESLAM ``Mapper.optimize_mapping``).

Window (ESLAM ``overlap`` rule): up to ``window_size - 1`` keyframes that overlap the current view (chosen at
random among the overlapping ones, the last two keyframes excluded), plus the last two keyframes, plus the
current frame. Each iteration samples ``n_rays / |window|`` pixels per view, renders them and takes one Adam step
on the feature lines/planes (lr 0.005), the decoders and beta (lr 0.001) and, once the map holds enough
keyframes, on the poses of all window views except the oldest (lr 0.001), the current frame included. The
first frame is fitted alone for ``first_iters`` iterations with all learning rates x ``lr_first_factor``.

``remap`` re-fits the field alone (poses fixed) over chosen keyframes, e.g. after a pose graph moved them.

The mapper keeps keyframe *pixels* only: every pose comes in as an argument (the pipeline's trajectory owns
them) and the optimised ones go back out as return values. A window pose that joint mapping moves further than
``max_pose_step`` / ``max_pose_step_deg`` in one round, or out of the bound, is reverted (divergence guard,
counted in :attr:`Mapper.reverted_poses`).
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import numpy as np
import torch

from lrslam.field.config import MapperConfig
from lrslam.field.inputs import inside_bound
from lrslam.field.keyframes import KeyframeStore, ViewPixels, select_overlapping
from lrslam.field.losses import rendering_loss
from lrslam.field.model import SceneModel
from lrslam.field.poses import PoseParams
from lrslam.field.rays import PixelBatch, camera_directions, ray_exit_depth, world_rays
from lrslam.field.render import RenderConfig, render_rays
from lrslam.geometry import is_valid_pose, pose_error

__all__ = ["MapperConfig", "Mapper", "depth_error"]

log = logging.getLogger(__name__)




class Mapper:
    """Owns the keyframe pixel database and optimises the field (and window poses) of a :class:`SceneModel`.

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
        self.reverted_poses = 0
        self._Kt = torch.tensor(self.K, dtype=torch.float32, device=model.device)

    # ------------------------------------------------------------------------------------------ public steps
    def initialise(self, frame_id: int, rgb: torch.Tensor, depth: torch.Tensor, T_w_c: np.ndarray,
                   progress: Callable[[int, int], None] | None = None) -> dict:
        """Fit the field to the first frame (pose ``T_w_c`` fixed) and store it as keyframe. rgb (H, W, 3) uint8
        and depth (H, W) metres tensors on the model's device. ``progress(done, total)`` is called after each
        iteration. Returns stats (iterations, final loss terms)."""
        view = ViewPixels.from_images(frame_id, rgb, depth)
        _, stats = self._optimise([view], [np.asarray(T_w_c, dtype=np.float64)], [False], self.cfg.first_iters,
                                  self.cfg.lr_first_factor, progress=progress)
        self.keyframes.add(self._keyframe(frame_id, rgb, depth))
        return stats

    def map(self, frame_id: int, rgb: torch.Tensor, depth: torch.Tensor, T_w_c: np.ndarray,
            keyframe_poses: dict[int, np.ndarray], add_keyframe: bool,
            depth_np: np.ndarray) -> tuple[dict[int, np.ndarray], dict]:
        """One mapping round for the current frame at ``T_w_c`` (tensors as in :meth:`initialise`; ``depth_np``
        the same depth as numpy, for the window selection). ``keyframe_poses``: the current ``T_w_c`` of every
        stored keyframe, by frame id (from the trajectory's owner).

        Returns:
            (poses by frame id of every view whose pose was optimised, the current frame always included;
            stats dict with ``window``, ``reverted``). Adds the frame as keyframe when ``add_keyframe``.
        """
        # 1. Window: overlapping keyframes + the last two + the current frame.
        ids = [k for k in self.keyframes.ids() if k in keyframe_poses]
        last_two = ids[-2:]
        older = {k: keyframe_poses[k] for k in ids if k not in last_two}
        chosen = select_overlapping(older, depth_np, T_w_c, self.K, self.cfg.window_size - 1, self.rng,
                                    n_pixels=self.cfg.overlap_pixels)
        window = sorted(set(chosen) | set(last_two))
        views = [self.keyframes.get(k) for k in window] + [ViewPixels.from_images(frame_id, rgb, depth)]
        poses = [np.asarray(keyframe_poses[k], dtype=np.float64) for k in window] + [
            np.asarray(T_w_c, dtype=np.float64)]
        # 2. Joint pose optimisation (ESLAM: once more than 4 keyframes exist); the oldest view stays fixed.
        joint = self.cfg.joint_opt and len(self.keyframes) >= self.cfg.joint_opt_min_keyframes and len(views) > 1
        first_id = ids[0] if ids else None
        optimise = [joint and i > 0 and v.frame_id != first_id for i, v in enumerate(views)]
        new_poses, stats = self._optimise(views, poses, optimise, self.cfg.iters, 1.0)
        # 3. Divergence guard, then hand back the optimised poses.
        out, reverted = {}, 0
        for v, T_old, T_new, o in zip(views, poses, new_poses, optimise):
            if not o:
                continue
            if self._plausible(T_old, T_new):
                out[v.frame_id] = T_new
            else:
                reverted += 1
        if reverted:
            self.reverted_poses += reverted
            log.warning("mapping: %d window pose(s) moved implausibly far in one round; reverted", reverted)
        out.setdefault(frame_id, poses[-1].copy())
        if add_keyframe:
            self.keyframes.add(self._keyframe(frame_id, rgb, depth))
        stats["window"] = window + [frame_id]
        stats["reverted"] = reverted
        return out, stats

    def remap(self, keyframe_poses: dict[int, np.ndarray], keyframe_ids: list[int] | None = None,
              iters: int | None = None) -> dict:
        """Re-optimise the field only (poses fixed at ``keyframe_poses``) over the given keyframes (None = all
        with a pose). Each iteration samples ``n_rays`` over at most ``remap_views`` of them, chosen at random,
        with the learning rates times ``remap_lr_factor``."""
        known = [k for k in self.keyframes.ids() if k in keyframe_poses]
        ids = known if keyframe_ids is None else [k for k in keyframe_ids if k in known]
        missing = [] if keyframe_ids is None else [k for k in keyframe_ids if k not in known]
        if missing:
            log.warning("remap: ignoring keyframe ids without pixels or pose %s", missing)
        if not ids:
            return {"iters": 0, "loss": float("nan")}
        views = [self.keyframes.get(k) for k in ids]
        poses = [np.asarray(keyframe_poses[k], dtype=np.float64) for k in ids]
        n_iters = self.cfg.remap_iters if iters is None else iters
        _, stats = self._optimise(views, poses, [False] * len(views), n_iters, self.cfg.remap_lr_factor,
                                  views_per_iter=self.cfg.remap_views)
        return stats

    # ------------------------------------------------------------------------------------------ internals
    def _keyframe(self, frame_id: int, rgb: torch.Tensor, depth: torch.Tensor) -> ViewPixels:
        return ViewPixels.from_images(frame_id, rgb, depth, self.cfg.keyframe_pixels, self.gen)

    def _plausible(self, T_old: np.ndarray, T_new: np.ndarray) -> bool:
        if not is_valid_pose(T_new, tol=1e-3):
            return False
        d_t, d_r = pose_error(T_old, T_new)
        return (d_t <= self.cfg.max_pose_step and d_r <= self.cfg.max_pose_step_deg
                and inside_bound(T_new[:3, 3], self.model.bound_np, self.cfg.bound_margin))

    def _optimise(self, views: list[ViewPixels], poses_in: list[np.ndarray], optimise_pose: list[bool], iters: int,
                  lr_factor: float, views_per_iter: int | None = None,
                  progress: Callable[[int, int], None] | None = None) -> tuple[list[np.ndarray], dict]:
        """Adam on the field (and the flagged views' poses). ``poses_in``: (4, 4) ``T_w_c`` per view. Returns
        (the poses after optimisation, copies, unflagged ones unchanged; stats)."""
        dev = self.model.device
        poses_out = [np.array(T, dtype=np.float64) for T in poses_in]
        opt_idx = [i for i, o in enumerate(optimise_pose) if o]
        opt, pose = self._optimiser(poses_out, opt_idx, lr_factor)
        fixed = torch.tensor(np.stack(poses_out), dtype=torch.float32, device=dev)
        slot = torch.tensor(opt_idx, dtype=torch.long, device=dev)
        bad, done, last_loss, last_terms = 0, 0, None, {}
        for it in range(iters):
            step = self._iteration_loss(views, views_per_iter, fixed, slot, pose)
            if step is None:
                continue
            loss, terms = step
            opt.zero_grad(set_to_none=True)
            if not bool(torch.isfinite(loss)):
                bad += 1
                if self._too_many_bad_steps(it, bad):
                    return [np.array(T, dtype=np.float64) for T in poses_in], {
                        "iters": done, "loss": float("nan"), "aborted": True}
                continue
            loss.backward()
            opt.step()
            done, last_loss, last_terms = it + 1, loss.detach(), terms
            if progress is not None:
                progress(it + 1, iters)
        if done == 0 and iters > 0:
            log.warning("mapping: no usable rays (valid depth inside the scene bound) in %d iterations", iters)
        self._take_poses(pose, opt_idx, poses_out)
        stats = {"iters": done, "loss": float("nan") if last_loss is None else float(last_loss)}
        return poses_out, stats | {k: float(v) for k, v in last_terms.items()}

    def _optimiser(self, poses: list[np.ndarray], opt_idx: list[int], lr_factor: float
                   ) -> tuple[torch.optim.Adam, PoseParams | None]:
        """Adam over the field (lrs x ``lr_factor``) and the poses of the views ``opt_idx`` (None: none)."""
        model, cfg = self.model, self.cfg
        groups = [{"params": model.encoding_parameters(), "lr": cfg.lr_encoding * lr_factor},
                  {"params": model.decoder_parameters(), "lr": cfg.lr_decoder * lr_factor}]
        pose = None
        if opt_idx:
            pose = PoseParams(np.stack([poses[i] for i in opt_idx]), cfg.pose_parameterisation, model.device)
            groups += [{"params": [pose.rotation], "lr": cfg.lr_pose_rot},
                       {"params": [pose.translation], "lr": cfg.lr_pose_trans}]
        return torch.optim.Adam(groups), pose

    def _iteration_loss(self, views: list[ViewPixels], views_per_iter: int | None, fixed: torch.Tensor,
                        slot: torch.Tensor, pose: PoseParams | None) -> tuple[torch.Tensor, dict] | None:
        """Steps 1-3 of one mapping iteration -> (loss, loss terms), None when no ray is usable."""
        model, cfg = self.model, self.cfg
        # 1. Pixels from the views (a random subset of views for remapping).
        batch = self._sample_views(views, views_per_iter)
        # 2. Rays from the current poses (optimised ones differentiable); surface inside the bound.
        poses = fixed if pose is None else fixed.index_copy(0, slot, pose.matrices())
        o, d = world_rays(camera_directions(batch.u, batch.v, self._Kt), poses, batch.frame)
        inside = ray_exit_depth(o, d, model.bound) >= batch.depth
        o, d, batch = o[inside], d[inside], batch.select(inside)
        if len(batch.depth) == 0:
            return None
        # 3. Render and loss (SDF/depth terms on rays with depth, colour on all).
        r = render_rays(model, o, d, batch.depth, model.truncation, self.render, self.gen)
        has_depth = batch.depth > 0
        return rendering_loss(r, batch.depth, batch.rgb, model.truncation, cfg.weights, has_depth,
                              torch.ones_like(has_depth))

    def _sample_views(self, views: list[ViewPixels], views_per_iter: int | None) -> PixelBatch:
        """One iteration's pixels: ``n_rays`` spread over the views (at most ``views_per_iter``, chosen at random)."""
        use = list(range(len(views)))
        if views_per_iter is not None and len(use) > views_per_iter:
            use = sorted(self.rng.choice(len(views), size=views_per_iter, replace=False).tolist())
        per_view = max(1, self.cfg.n_rays // len(use))
        return PixelBatch.cat([views[i].sample(per_view, i, self.gen) for i in use])

    def _too_many_bad_steps(self, it: int, bad: int) -> bool:
        """Log a skipped non-finite step (the ``bad``-th); True when mapping must abort."""
        log.warning("mapping: non-finite loss at iteration %d (%d/%d), step skipped", it, bad, self.cfg.max_bad_steps)
        if bad >= self.cfg.max_bad_steps:
            log.warning("mapping: aborted after %d non-finite losses; poses unchanged", bad)
            return True
        return False

    @staticmethod
    def _take_poses(pose: PoseParams | None, opt_idx: list[int], poses_out: list[np.ndarray]) -> None:
        """Write the optimised poses into ``poses_out`` (slots ``opt_idx``) unless they became non-finite."""
        if pose is None:
            return
        if pose.finite():
            for i, T in zip(opt_idx, pose.numpy()):
                poses_out[i] = T
        else:
            log.warning("mapping: window poses became non-finite; keeping the previous poses")


@torch.no_grad()
def depth_error(model: SceneModel, views: list[ViewPixels], poses: list[np.ndarray], K: np.ndarray,
                render: RenderConfig, n_rays: int, generator: torch.Generator) -> float:
    """Mean |rendered - sensor| depth (metres) over ``n_rays`` random valid pixels spread over ``views`` seen from
    ``poses`` ((4, 4) ``T_w_c`` each), rendered without jitter; NaN without usable rays."""
    if not views:
        return float("nan")
    dev = model.device
    per_view = max(1, n_rays // len(views))
    batch = PixelBatch.cat([v.sample(per_view, i, generator) for i, v in enumerate(views)])
    batch = batch.select(batch.depth > 0)
    Kt = torch.tensor(np.asarray(K), dtype=torch.float32, device=dev)
    T = torch.tensor(np.stack(poses), dtype=torch.float32, device=dev)
    o, d = world_rays(camera_directions(batch.u, batch.v, Kt), T, batch.frame)
    inside = ray_exit_depth(o, d, model.bound) >= batch.depth
    if not bool(inside.any()):
        return float("nan")
    with model.frozen():
        r = render_rays(model, o[inside], d[inside], batch.depth[inside], model.truncation, render, generator,
                        jitter=False)
    return float((r.depth - batch.depth[inside]).abs().mean())
