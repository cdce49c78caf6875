"""Camera tracking against a frozen field (ESLAM ``Tracker.optimize_tracking``).

Per iteration: sample pixels with valid depth away from the image border, cast rays from the current pose
estimate, keep rays whose measured surface lies inside the scene bound, render (Eq. volume_render), drop rays
whose depth error exceeds ``outlier_factor`` x the median, and take an Adam step on the pose with the ESLAM
loss (tracking weights). The pose with the lowest loss seen is returned (ESLAM keeps the best, too).

Failures never raise: no valid depth, a seed outside the bound, no usable rays, a non-finite loss or a result
that moved implausibly far from the seed give ``ok=False`` with the *seed* pose and a one-line reason (logged).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from lrslam.config import StrictModel
from lrslam.geometry import is_valid_pose, pose_error
from lrslam.field.inputs import image_tensors, inside_bound
from lrslam.field.losses import TRACKING_WEIGHTS, LossWeights, rendering_loss
from lrslam.field.model import SceneModel
from lrslam.field.poses import PoseParameterisation, PoseParams
from lrslam.field.rays import camera_directions, gather_pixels, ray_exit_depth, sample_pixels, world_rays
from lrslam.field.render import RenderConfig, render_rays

__all__ = ["TrackerConfig", "TrackResult", "track"]

log = logging.getLogger(__name__)


class TrackerConfig(StrictModel):
    """Tracking settings. Defaults: ESLAM on Replica (8 iterations, 2000 pixels, lr 0.001 rotation / 0.002
    translation, Adam betas (0.5, 0.999), 75-pixel border ignored, outliers > 10 x median depth error).

    lr_rot: Adam lr of the rotation parameters (quaternion units, ~ half radians; see :mod:`.poses`).
    lr_trans: Adam lr of the translation (metres). lr_final_factor: linear decay of both lrs to this fraction at
    the last iteration (1 = constant, ESLAM). max_translation / max_rotation_deg: a refined pose further than
    this from the seed counts as divergence. bound_margin: metres the camera centre may lie outside the scene
    bound (seed and result). min_rays: fewer usable rays in an iteration skip it.
    """

    iters: int = 8
    n_rays: int = 2000
    lr_rot: float = 0.001
    lr_trans: float = 0.002
    lr_final_factor: float = 1.0
    adam_betas: tuple[float, float] = (0.5, 0.999)
    parameterisation: PoseParameterisation = "quat"
    outlier_factor: float = 10.0
    ignore_edge_h: int = 75
    ignore_edge_w: int = 75
    weights: LossWeights = TRACKING_WEIGHTS
    max_translation: float = 0.5
    max_rotation_deg: float = 30.0
    bound_margin: float = 1.0
    min_rays: int = 16


@dataclass
class TrackResult:
    """Outcome of tracking one frame. T_w_c: (4, 4) float64, the refined pose, or the seed when ``ok`` is
    False. loss_first / loss_best: loss at the seed and the best loss (NaN when never evaluated).
    iters: iterations run. reason: why tracking failed ("" when ok)."""

    T_w_c: np.ndarray
    ok: bool
    loss_first: float
    loss_best: float
    iters: int
    reason: str = ""


def _fail(T_seed: np.ndarray, reason: str, loss_first: float = float("nan"), iters: int = 0) -> TrackResult:
    log.warning("field tracking failed, keeping the seed pose: %s", reason)
    return TrackResult(np.array(T_seed, dtype=np.float64), False, loss_first, float("nan"), iters, reason)


def track(model: SceneModel, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, T_w_c_init: np.ndarray,
          cfg: TrackerConfig = TrackerConfig(), render: RenderConfig = RenderConfig(),
          generator: torch.Generator | None = None) -> TrackResult:
    """Refine the camera pose of one frame against the frozen field.

    Args:
        model: the scene model (not modified). rgb: (H, W, 3) uint8. depth: (H, W) metres, 0 = invalid.
        K: (3, 3) intrinsics. T_w_c_init: (4, 4) seed pose (OpenCV camera to world).
        cfg, render: tracking and sampling settings. generator: torch RNG (CPU) for pixels and jitter.
    Returns:
        :class:`TrackResult`.
    Raises:
        InputError: images of the wrong shape/dtype (a programming error, not a bad frame).
    """
    gen = generator if generator is not None else torch.Generator().manual_seed(0)
    T_seed = np.asarray(T_w_c_init, dtype=np.float64)
    if not is_valid_pose(T_seed):
        return _fail(np.eye(4) if T_seed.shape != (4, 4) else T_seed, "seed pose is not a finite rigid transform")
    dev = model.device
    h, w = np.asarray(depth).shape[:2]
    rgb_t, depth_t = image_tensors(rgb, depth, h, w, dev)
    if not bool((depth_t > 0).any()):
        return _fail(T_seed, "no valid depth in the frame")
    if not inside_bound(T_seed[:3, 3], model.bound_np, cfg.bound_margin):
        return _fail(T_seed, f"seed camera centre {np.round(T_seed[:3, 3], 2).tolist()} is outside the scene bound")

    # 1. Pose parameters and optimiser (ESLAM: Adam with betas (0.5, 0.999)).
    pose = PoseParams(T_seed, cfg.parameterisation, dev)
    opt = torch.optim.Adam([{"params": [pose.rotation], "lr": cfg.lr_rot},
                            {"params": [pose.translation], "lr": cfg.lr_trans}], betas=cfg.adam_betas)
    Kt = torch.tensor(K, dtype=torch.float32, device=dev)
    loss_first, loss_best, T_best, done = float("nan"), float("inf"), T_seed, 0

    with model.frozen():
        for it in range(cfg.iters):
            _decay(opt, (cfg.lr_rot, cfg.lr_trans), cfg.lr_final_factor, it, cfg.iters)
            # 2. Pixels with valid depth, rays from the current pose, surface inside the bound.
            rows, cols = sample_pixels(cfg.n_rays, h, w, gen, cfg.ignore_edge_h, cfg.ignore_edge_w, dev)
            batch = gather_pixels(rgb_t, depth_t, rows, cols, 0)
            batch = batch.select(batch.depth > 0)
            o, d = world_rays(camera_directions(batch.u, batch.v, Kt), pose.matrices())
            inside = ray_exit_depth(o, d, model.bound) >= batch.depth
            if int(inside.sum()) < cfg.min_rays:
                continue
            o, d, batch = o[inside], d[inside], batch.select(inside)
            # 3. Render, reject outlier rays, loss.
            r = render_rays(model, o, d, batch.depth, model.truncation, render, gen)
            err = (batch.depth - r.depth.detach()).abs()
            inlier = err < cfg.outlier_factor * err.median().clamp(min=1e-6)
            loss, _ = rendering_loss(r, batch.depth, batch.rgb, model.truncation, cfg.weights, inlier, inlier)
            value = float(loss.detach())
            done = it + 1
            if not np.isfinite(value):
                return _fail(T_seed, f"non-finite tracking loss at iteration {it}", loss_first, done)
            if np.isnan(loss_first):
                loss_first = value
            if value < loss_best:  # the loss belongs to the pose before this step
                loss_best, T_best = value, pose.numpy()[0]
            # 4. Step.
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()

    # 5. Sanity checks on the result.
    if not np.isfinite(loss_best):
        return _fail(T_seed, "no usable rays (valid depth inside the scene bound) in any iteration", loss_first, done)
    dt, dr = pose_error(T_seed, T_best)
    if dt > cfg.max_translation or dr > cfg.max_rotation_deg or not is_valid_pose(T_best, tol=1e-3):
        return _fail(T_seed, f"diverged: {dt:.3f} m / {dr:.1f} deg from the seed", loss_first, done)
    if not inside_bound(T_best[:3, 3], model.bound_np, cfg.bound_margin):
        return _fail(T_seed, "refined camera centre left the scene bound", loss_first, done)
    return TrackResult(T_best, True, loss_first, loss_best, done, "")


def _decay(opt: torch.optim.Optimizer, base: tuple[float, ...], final: float, it: int, iters: int) -> None:
    """Linear learning-rate decay from ``base`` to ``final * base`` over the iterations."""
    if final == 1.0:
        return
    f = 1.0 + (final - 1.0) * (it / max(1, iters - 1))
    for group, lr in zip(opt.param_groups, base):
        group["lr"] = lr * f
