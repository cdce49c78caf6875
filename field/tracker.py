"""Camera tracking against a frozen field (ESLAM ``Tracker.optimize_tracking``).

Per iteration: sample pixels with valid depth away from the image border, cast rays from the current pose
estimate, keep rays whose measured surface lies inside the scene bound, render (Eq. volume_render), drop rays
whose depth error exceeds ``outlier_factor`` x the median, and take an Adam step on the pose with the ESLAM
loss (tracking weights). The pose with the lowest loss seen is returned (ESLAM keeps the best, too).

Failures never raise: no valid depth, a seed outside the bound, no usable rays, a non-finite loss or a result
that moved implausibly far from the seed give ``ok=False`` with the *seed* pose and a one-line reason (logged).

After the iterations one fixed set of rays (no jitter) renders the seed and the refined pose: the two losses
are compared on the same rays (``accept_if_better`` keeps the seed unless the refinement lowers that loss), and
the chosen pose's information comes from the same rays (:func:`pose_information`): the Gauss-Newton Hessian
``sum_k g_k g_k^T / sigma^2`` of the rendered-depth residuals ``r_k = D_k(T exp(xi)) - d_k``, with the
per-ray gradients ``g_k = d r_k / d xi`` of a right perturbation ``xi = [rotation (rad), translation (m)]``
(camera frame, GTSAM's convention) taken from one backward pass through the renderer, ``sigma^2`` the mean
squared residual, and the ray count saturating at ``information_rays`` (neighbouring rays share errors).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np
import torch

from lrslam.field.config import TrackerConfig
from lrslam.geometry import diagonal_information, is_valid_pose, pose_error
from lrslam.field.inputs import has_valid_depth, image_tensors, inside_bound
from lrslam.field.losses import rendering_loss
from lrslam.field.model import SceneModel
from lrslam.field.poses import PoseParams
from lrslam.field.rays import camera_directions, gather_pixels, ray_exit_depth, sample_pixels, world_rays
from lrslam.field.render import RenderConfig, render_rays

__all__ = ["TrackerConfig", "TrackResult", "track", "pose_information", "keep_refinement", "pose_losses"]

log = logging.getLogger(__name__)




@dataclass
class TrackResult:
    """Outcome of tracking one frame. T_w_c: (4, 4) float64, the chosen pose: the refined one, or the seed when
    ``ok`` is False or the refinement was not ``accepted``. loss_first / loss_best: loss at the seed and the best
    loss during the iterations (NaN when never evaluated). check_seed / check_refined: the losses of the seed and
    the refined pose on the same fixed rays (NaN when not checked). accepted: the refinement was kept.
    information: (6, 6) information of ``T_w_c`` (right perturbation, ``[rotation, translation]``) given the
    field, or None. n_check_rays: rays behind it. iters: iterations run. best_iter: the iteration whose pose was
    the best (0 = the seed). reason: why tracking failed or the refinement was not kept ("" otherwise)."""

    T_w_c: np.ndarray
    ok: bool
    loss_first: float
    loss_best: float
    iters: int
    reason: str = ""
    accepted: bool = False
    check_seed: float = float("nan")
    check_refined: float = float("nan")
    information: np.ndarray | None = None
    n_check_rays: int = 0
    best_iter: int = 0


def _fail(T_seed: np.ndarray, reason: str, loss_first: float = float("nan"), iters: int = 0) -> TrackResult:
    log.warning("field tracking failed, keeping the seed pose: %s", reason)
    return TrackResult(np.array(T_seed, dtype=np.float64), False, loss_first, float("nan"), iters, reason)


@dataclass
class _Search:
    """State of the tracking iterations: the first and best loss, the best pose and the early-stop counters.
    ``failure``: why the iterations ended tracking ("" otherwise)."""

    T_best: np.ndarray
    loss_first: float = float("nan")
    loss_best: float = float("inf")
    done: int = 0
    best_iter: int = 0
    since_gain: int = 0               # early stop: iterations since the best loss dropped
    loss_ref: float = float("inf")
    failure: str = ""

    def record(self, value: float, it: int, pose: PoseParams, cfg: TrackerConfig) -> bool:
        """Book the (finite) loss of iteration ``it``; True when the early stop ends the iterations."""
        if np.isnan(self.loss_first):
            self.loss_first = value
        if value < self.loss_best:  # the loss belongs to the pose before this step
            self.loss_best, self.T_best, self.best_iter = value, pose.numpy()[0], it
        self.since_gain += 1
        if value < self.loss_ref * (1.0 - cfg.stop_min_improvement):
            self.loss_ref, self.since_gain = value, 0
        return bool(cfg.stop_patience and self.since_gain >= cfg.stop_patience and self.done >= cfg.min_iters)


def track(model: SceneModel, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, T_w_c_init: np.ndarray,
          cfg: TrackerConfig = TrackerConfig(), render: RenderConfig = RenderConfig(),
          generator: torch.Generator | None = None, early_stop: bool = True) -> TrackResult:
    """Refine the camera pose of one frame against the frozen field.

    Args:
        model: the scene model (not modified). rgb: (H, W, 3) uint8. depth: (H, W) metres, 0 = invalid.
        K: (3, 3) intrinsics. T_w_c_init: (4, 4) seed pose (OpenCV camera to world).
        cfg, render: tracking and sampling settings. generator: torch RNG (CPU) for pixels and jitter.
        early_stop: False runs all ``cfg.iters`` iterations whatever ``cfg.stop_patience`` says (a poor seed).
    Returns:
        :class:`TrackResult`.
    Raises:
        InputError: images of the wrong shape/dtype (a programming error, not a bad frame).
    """
    gen = generator if generator is not None else torch.Generator().manual_seed(0)
    if not early_stop:
        cfg = cfg.model_copy(update={"stop_patience": 0})
    render = _tracking_render(cfg, render)
    T_seed = np.asarray(T_w_c_init, dtype=np.float64)
    if not is_valid_pose(T_seed):
        return _fail(np.eye(4) if T_seed.shape != (4, 4) else T_seed, "seed pose is not a finite rigid transform")
    dev = model.device
    h, w = np.asarray(depth).shape[:2]
    rgb_t, depth_t = image_tensors(rgb, depth, h, w, dev)
    problem = _seed_problem(model, depth_t, T_seed, cfg)
    if problem:
        return _fail(T_seed, problem)

    # 1. Pose parameters and optimiser (ESLAM: Adam with betas (0.5, 0.999)).
    pose, opt = _pose_optimiser(T_seed, cfg, dev)
    Kt = torch.tensor(K, dtype=torch.float32, device=dev)
    search = _iterate(model, pose, opt, rgb_t, depth_t, Kt, T_seed, cfg, render, gen)
    if search.failure:
        return _fail(T_seed, search.failure, search.loss_first, search.done)

    # 5. Sanity checks on the result.
    problem = _result_problem(model, T_seed, search, cfg)
    if problem:
        return _fail(T_seed, problem, search.loss_first, search.done)

    # 6. Paired check on fixed rays the iterations did not fit (also with ``fixed_rays``: the best loss on the
    #    optimised rays is never above the seed's, so it could not reject): is the refinement better than the
    #    seed? How well is the pose determined?
    return _paired_check(model, rgb_t, depth_t, Kt, T_seed, search, cfg, render, gen)


def _seed_problem(model: SceneModel, depth_t: torch.Tensor, T_seed: np.ndarray, cfg: TrackerConfig) -> str:
    """Why the frame cannot be tracked from the seed: no valid depth or a seed outside the bound ("" if it can)."""
    if not has_valid_depth(depth_t):
        return "no valid depth in the frame"
    if not inside_bound(T_seed[:3, 3], model.bound_np, cfg.bound_margin):
        return f"seed camera centre {np.round(T_seed[:3, 3], 2).tolist()} is outside the scene bound"
    return ""


def _pose_optimiser(T_seed: np.ndarray, cfg: TrackerConfig, dev: torch.device
                    ) -> tuple[PoseParams, torch.optim.Adam]:
    """The pose parameters at the seed and their Adam optimiser (ESLAM betas, rotation and translation lrs)."""
    pose = PoseParams(T_seed, cfg.parameterisation, dev)
    opt = torch.optim.Adam([{"params": [pose.rotation], "lr": cfg.lr_rot},
                            {"params": [pose.translation], "lr": cfg.lr_trans}], betas=cfg.adam_betas)
    return pose, opt


def _iterate(model: SceneModel, pose: PoseParams, opt: torch.optim.Adam, rgb_t: torch.Tensor,
             depth_t: torch.Tensor, Kt: torch.Tensor, T_seed: np.ndarray, cfg: TrackerConfig,
             render: RenderConfig, gen: torch.Generator) -> _Search:
    """Steps 2-4: the Adam iterations on the pose against the frozen field -> their :class:`_Search` state."""
    search = _Search(T_seed)
    fixed = _check_rays(rgb_t, depth_t, Kt, cfg, gen, cfg.n_rays) if cfg.fixed_rays else None

    with model.frozen():
        for it in range(cfg.iters):
            _decay(opt, (cfg.lr_rot, cfg.lr_trans), cfg.lr_final_factor, it, cfg.iters)
            # 2. Pixels with valid depth (new ones each iteration, or the fixed set), rays from the current pose,
            #    surface inside the bound.
            rays = _iteration_rays(model, pose, rgb_t, depth_t, Kt, cfg, gen, fixed)
            if rays is None:
                continue
            # 3. Render, reject outlier rays, loss.
            loss = _iteration_loss(model, *rays, cfg, render, gen, fixed is not None)
            value = float(loss.detach())
            search.done = it + 1
            if not np.isfinite(value):
                search.failure = f"non-finite tracking loss at iteration {it}"
                return search
            if search.record(value, it, pose, cfg):
                break
            # 4. Step.
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
    return search


def _iteration_rays(model: SceneModel, pose: PoseParams, rgb_t: torch.Tensor, depth_t: torch.Tensor,
                    Kt: torch.Tensor, cfg: TrackerConfig, gen: torch.Generator, fixed: tuple | None):
    """One iteration's rays from the current pose -> (origins, directions, PixelBatch) of the rays whose surface
    lies inside the bound (differentiable in the pose), None when fewer than ``min_rays``."""
    batch, dirs_c = _check_rays(rgb_t, depth_t, Kt, cfg, gen, cfg.n_rays) if fixed is None else fixed
    o, d = world_rays(dirs_c, pose.matrices())
    inside = ray_exit_depth(o, d, model.bound) >= batch.depth
    if int(inside.sum()) < cfg.min_rays:
        return None
    return o[inside], d[inside], batch.select(inside)


def _iteration_loss(model: SceneModel, o: torch.Tensor, d: torch.Tensor, batch, cfg: TrackerConfig,
                    render: RenderConfig, gen: torch.Generator, fixed: bool) -> torch.Tensor:
    """Render the rays (jitter unless ``fixed``), reject outlier rays -> the tracking loss (with its graph)."""
    r = render_rays(model, o, d, batch.depth, model.truncation, render, gen, jitter=False if fixed else None)
    err = (batch.depth - r.depth.detach()).abs()
    inlier = err < cfg.outlier_factor * err.median().clamp(min=1e-6)
    loss, _ = rendering_loss(r, batch.depth, batch.rgb, model.truncation, cfg.weights, inlier, inlier)
    return loss


def _result_problem(model: SceneModel, T_seed: np.ndarray, search: _Search, cfg: TrackerConfig) -> str:
    """Why the iterations' best pose is rejected: no usable rays, divergence, outside the bound ("" if kept)."""
    if not np.isfinite(search.loss_best):
        return "no usable rays (valid depth inside the scene bound) in any iteration"
    dt, dr = pose_error(T_seed, search.T_best)
    if dt > cfg.max_translation or dr > cfg.max_rotation_deg or not is_valid_pose(search.T_best, tol=1e-3):
        return f"diverged: {dt:.3f} m / {dr:.1f} deg from the seed"
    if not inside_bound(search.T_best[:3, 3], model.bound_np, cfg.bound_margin):
        return "refined camera centre left the scene bound"
    return ""


def _paired_check(model: SceneModel, rgb_t: torch.Tensor, depth_t: torch.Tensor, Kt: torch.Tensor,
                  T_seed: np.ndarray, search: _Search, cfg: TrackerConfig, render: RenderConfig,
                  gen: torch.Generator) -> TrackResult:
    """Seed and best pose on the same fresh fixed rays: keep the refinement? Information of the chosen pose."""
    T_best = search.T_best
    with model.frozen():
        batch, dirs_c = _check_rays(rgb_t, depth_t, Kt, cfg, gen)
        l_seed, m_seed = _fixed_ray_loss(model, batch, dirs_c, T_seed, cfg, render)
        l_ref, m_ref = _fixed_ray_loss(model, batch, dirs_c, T_best, cfg, render)
        accepted = keep_refinement(l_seed, l_ref, cfg)
        T_out = T_best if accepted else T_seed
        reason = "" if accepted else f"refinement worse than the seed ({l_ref:.4g} vs {l_seed:.4g})"
        info, n_info = None, 0
        if cfg.information:
            info, n_info = pose_information(model, batch, dirs_c, T_out, m_ref if accepted else m_seed, cfg, render)
    return TrackResult(T_out, True, search.loss_first, search.loss_best, search.done, reason, accepted, l_seed,
                       l_ref, info, n_info, search.best_iter)


def pose_losses(model: SceneModel, rgb: np.ndarray, depth: np.ndarray, K: np.ndarray, poses: list[np.ndarray],
                cfg: TrackerConfig = TrackerConfig(), render: RenderConfig = RenderConfig(),
                generator: torch.Generator | None = None) -> list[float]:
    """The tracking loss of one frame (rgb (H, W, 3) uint8, depth (H, W) metres) at each candidate pose
    ``poses`` ((4, 4) ``T_w_c`` each), on the same fixed rays without jitter (``check_rays`` of them): which
    pose does the frozen field support? NaN for a pose with too few usable rays."""
    gen = generator if generator is not None else torch.Generator().manual_seed(0)
    render = _tracking_render(cfg, render)
    h, w = np.asarray(depth).shape[:2]
    rgb_t, depth_t = image_tensors(rgb, depth, h, w, model.device)
    Kt = torch.tensor(K, dtype=torch.float32, device=model.device)
    with model.frozen():
        batch, dirs_c = _check_rays(rgb_t, depth_t, Kt, cfg, gen)
        if len(dirs_c) < cfg.min_rays:
            return [float("nan")] * len(poses)
        return [_fixed_ray_loss(model, batch, dirs_c, np.asarray(T, dtype=np.float64), cfg, render)[0]
                for T in poses]


def _tracking_render(cfg: TrackerConfig, render: RenderConfig) -> RenderConfig:
    """The render settings tracking uses: ``render`` with ``cfg.n_stratified`` free-space samples when set."""
    if cfg.n_stratified is None:
        return render
    return render.model_copy(update={"n_stratified": cfg.n_stratified})


def keep_refinement(loss_seed: float, loss_refined: float, cfg: TrackerConfig) -> bool:
    """Whether the refined pose is kept, from the two losses on the same fixed rays: never when its loss is not
    finite; with ``accept_if_better``, only when it is at most ``(1 + accept_tolerance)`` times the seed's (a
    seed whose loss is not finite loses to any finite refinement)."""
    if not np.isfinite(loss_refined):
        return False
    if not cfg.accept_if_better or not np.isfinite(loss_seed):
        return True
    return bool(loss_refined <= loss_seed * (1.0 + cfg.accept_tolerance))


def _check_rays(rgb_t: torch.Tensor, depth_t: torch.Tensor, Kt: torch.Tensor, cfg: TrackerConfig,
                gen: torch.Generator, n: int | None = None):
    """One fixed set of ``n`` (default ``check_rays or n_rays``) pixels with valid depth -> (PixelBatch, camera
    directions (N, 3))."""
    h, w = depth_t.shape
    rows, cols = sample_pixels(n or cfg.check_rays or cfg.n_rays, h, w, gen, cfg.ignore_edge_h, cfg.ignore_edge_w,
                               depth_t.device)
    batch = gather_pixels(rgb_t, depth_t, rows, cols, 0)
    batch = batch.select(batch.depth > 0)
    return batch, camera_directions(batch.u, batch.v, Kt)


def _rays_at(T: np.ndarray, dirs_c: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    Tt = torch.tensor(T, dtype=torch.float32, device=dirs_c.device)
    return Tt[:3, 3].expand(len(dirs_c), 3), dirs_c @ Tt[:3, :3].T


@torch.no_grad()
def _fixed_ray_loss(model: SceneModel, batch, dirs_c: torch.Tensor, T: np.ndarray, cfg: TrackerConfig,
                    render: RenderConfig) -> tuple[float, torch.Tensor]:
    """Tracking loss of pose ``T`` on the fixed rays without jitter -> (loss, geometry mask (N,) of the rays
    inside the bound and not outliers). NaN when too few rays are usable."""
    o, d = _rays_at(T, dirs_c)
    inside = ray_exit_depth(o, d, model.bound) >= batch.depth
    if int(inside.sum()) < cfg.min_rays:
        return float("nan"), inside
    r = render_rays(model, o, d, batch.depth, model.truncation, render, torch.Generator(), jitter=False)
    err = (batch.depth - r.depth).abs()
    mask = inside & (err < cfg.outlier_factor * err[inside].median().clamp(min=1e-6))
    loss, _ = rendering_loss(r, batch.depth, batch.rgb, model.truncation, cfg.check_weights or cfg.weights, mask,
                             mask)
    return float(loss), mask


def pose_information(model: SceneModel, batch, dirs_c: torch.Tensor, T_w_c: np.ndarray, mask: torch.Tensor,
                     cfg: TrackerConfig, render: RenderConfig) -> tuple[np.ndarray, int]:
    """Information (6, 6) of the camera pose ``T_w_c`` (4, 4) given the frozen field, from the rays ``batch``
    (camera directions ``dirs_c`` (N, 3), ``mask`` (N,) the rays to use); see the module docstring.

    Right perturbation ``T exp(xi)``, ``xi = [omega, v]``: ray origins move by ``R v`` and directions by
    ``-R [d_c]x omega``, so with ``a_k = R^T dD_k/dd_k`` and ``b_k = R^T dD_k/do_k`` the per-ray gradient is
    ``g_k = [d_c,k x a_k, b_k]``. Returns (information, rays used); a weak diagonal prior
    (``information_floor_*``) keeps it positive definite when the geometry leaves a direction unconstrained.
    """
    floor = diagonal_information(np.radians(cfg.information_floor_rotation_deg), cfg.information_floor_translation)
    n = int(mask.sum())
    if n < cfg.min_rays:
        return floor, n
    o, d = _rays_at(T_w_c, dirs_c[mask])
    o = o.detach().clone().requires_grad_(True)
    d = d.detach().clone().requires_grad_(True)
    depth = batch.depth[mask]
    r = render_rays(model, o, d, depth, model.truncation, render, torch.Generator(), jitter=False)
    go, gd = torch.autograd.grad(r.depth.sum(), (o, d))
    R = torch.tensor(T_w_c[:3, :3], dtype=torch.float32, device=dirs_c.device)
    a, b = gd @ R, go @ R                                       # rows: R^T dD/dd, R^T dD/do
    g = torch.cat([torch.cross(dirs_c[mask], a, dim=-1), b], dim=-1).double().cpu().numpy()  # (n, 6)
    res = (r.depth.detach() - depth).double().cpu().numpy()
    sigma2 = max(float(np.mean(res ** 2)), 1e-6)
    n_eff = n * cfg.information_rays / (n + cfg.information_rays)
    H = g.T @ g / n * n_eff / sigma2
    return 0.5 * (H + H.T) + floor, n


def _decay(opt: torch.optim.Optimizer, base: tuple[float, ...], final: float, it: int, iters: int) -> None:
    """Linear learning-rate decay from ``base`` to ``final * base`` over the iterations."""
    if final == 1.0:
        return
    f = 1.0 + (final - 1.0) * (it / max(1, iters - 1))
    for group, lr in zip(opt.param_groups, base):
        group["lr"] = lr * f
