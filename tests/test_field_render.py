"""Rays, samples, volume rendering and losses against closed forms; pose gradients through the renderer."""

import numpy as np
import pytest
import torch

from lrslam import camera, geometry as g
from lrslam.field.losses import LossWeights, rendering_loss, sdf_losses
from lrslam.field.model import SceneModel
from lrslam.field.poses import PoseParams, quat_to_matrix, se3_exp
from lrslam.field.rays import camera_directions, ray_exit_depth, world_rays
from lrslam.field.render import RenderConfig, compositing_weights, render_rays, sdf_to_density
from lrslam.field.sampling import depth_guided_depths, sample_pdf

T_TRUNC = 0.06
BOUND = np.array([[-2.0, 2.0], [-2.0, 2.0], [-1.0, 4.0]])


class AnalyticField:
    """Model-like field with an analytic SDF: ``dist(p)`` metres -> truncated SDF in truncation units."""

    def __init__(self, dist, beta: float):
        self.dist = dist
        self.beta = torch.tensor(beta)
        self.bound = torch.tensor(BOUND, dtype=torch.float32)

    def sdf(self, p):
        return (self.dist(p) / T_TRUNC).clamp(-1.0, 1.0)

    def colour(self, p):
        return 0.5 + 0.25 * torch.sin(3 * p)


def _plane(p):
    return 2.0 - p[:, 2]  # wall z = 2, free space towards the camera at the origin


def _sphere(p):
    return (p - torch.tensor([0.0, 0.0, 3.0])).norm(dim=-1) - 1.0


def _pixels(n=64, seed=0):
    K = camera.intrinsics_matrix(100.0, 100.0, 50.0, 40.0)
    rng = np.random.default_rng(seed)
    u, v = rng.uniform(35, 65, n), rng.uniform(25, 55, n)
    return K, torch.tensor(u, dtype=torch.float32), torch.tensor(v, dtype=torch.float32)


def _sphere_depth(dirs):
    c, r = np.array([0.0, 0.0, 3.0]), 1.0
    a = (dirs**2).sum(1)
    b = dirs @ c
    return (b - np.sqrt(b**2 - a * (c @ c - r * r))) / a  # dirs have unit z: the ray parameter is the depth


def test_rays_reproduce_camera_backprojection(rng):
    K = camera.intrinsics_matrix(120.0, 110.0, 40.0, 30.0)
    T = g.random_pose(rng, 1.0, 40.0)
    depth = rng.uniform(0.5, 3.0, size=(6, 8))
    v, u = np.mgrid[0:6, 0:8]
    o, d = world_rays(camera_directions(torch.tensor(u.ravel(), dtype=torch.float32),
                                        torch.tensor(v.ravel(), dtype=torch.float32),
                                        torch.tensor(K, dtype=torch.float32)),
                      torch.tensor(T, dtype=torch.float32)[None])
    pts = (o + d * torch.tensor(depth.ravel(), dtype=torch.float32)[:, None]).numpy()
    expected = camera.transform_points(T, camera.backproject_depth(depth, K).reshape(-1, 3))
    np.testing.assert_allclose(pts, expected, atol=1e-5)
    exit_z = ray_exit_depth(torch.zeros(1, 3), torch.tensor([[0.0, 0.0, 1.0]]),
                            torch.tensor(BOUND, dtype=torch.float32))
    assert float(exit_z) == pytest.approx(4.0)


def test_pose_parameterisations_match_numpy_geometry(rng):
    xi = np.concatenate([rng.normal(size=3) * 0.5, rng.normal(size=3)])
    torch.testing.assert_close(se3_exp(torch.tensor(xi)[None])[0], torch.tensor(g.exp_se3(xi)), atol=1e-9, rtol=0)
    torch.testing.assert_close(se3_exp(torch.zeros(1, 6, dtype=torch.float64))[0], torch.eye(4, dtype=torch.float64))
    q = g.rot_to_quat(g.random_pose(rng, 0.0, 170.0)[:3, :3])
    torch.testing.assert_close(quat_to_matrix(torch.tensor(q[[3, 0, 1, 2]])[None] * 3.0)[0],
                               torch.tensor(g.quat_to_rot(q)), atol=1e-9, rtol=0)
    T0 = np.stack([g.random_pose(rng, 2.0, 90.0) for _ in range(3)])
    for kind in ("quat", "lie"):
        pp = PoseParams(T0, kind)
        np.testing.assert_allclose(pp.matrices().detach().numpy(), T0, atol=1e-6)
        np.testing.assert_allclose(pp.numpy(), T0, atol=1e-6)
        with torch.no_grad():
            pp.translation.add_(0.1)
            pp.rotation.add_(0.05)
        np.testing.assert_allclose(pp.numpy(), pp.matrices().detach().double().numpy(), atol=1e-6)


def test_compositing_weights_closed_form():
    sigma = torch.tensor([[0.1, 0.5, 2.0, 0.0, 3.0]])
    w = compositing_weights(sigma)[0].numpy()
    s = sigma[0].numpy()
    expected = [np.exp(-s[:i].sum()) * (1 - np.exp(-s[i])) for i in range(5)]
    np.testing.assert_allclose(w, expected, rtol=1e-6)
    alpha = 1 - np.exp(-s)  # ESLAM's alpha-compositing form is the same thing
    np.testing.assert_allclose(w, alpha * np.cumprod(np.concatenate([[1.0], 1 - alpha[:-1]])), rtol=1e-6)
    assert float(sdf_to_density(torch.tensor(0.0), 10.0)) == pytest.approx(5.0)


@pytest.mark.parametrize("shape", ["plane", "sphere"])
def test_render_analytic_sdf_depth(shape):
    K, u, v = _pixels()
    field = AnalyticField(_plane if shape == "plane" else _sphere, beta=200.0)
    o, d = world_rays(camera_directions(u, v, torch.tensor(K, dtype=torch.float32)), torch.eye(4)[None])
    truth = np.full(len(u), 2.0) if shape == "plane" else _sphere_depth(d.numpy().astype(np.float64))
    gen = torch.Generator().manual_seed(0)
    # measured depth guides the samples (32 free-space + 64 in the surface band): < 1 cm
    cfg = RenderConfig(n_stratified=32, n_importance=64, perturb=False)
    r = render_rays(field, o, d, torch.tensor(truth, dtype=torch.float32), T_TRUNC, cfg, gen)
    assert np.abs(r.depth.numpy() - truth).max() < 0.01
    w_sum = r.weights.sum(-1)
    assert torch.all(w_sum <= 1 + 1e-5) and torch.all(w_sum > 0.99), w_sum.max()
    assert torch.all(r.weights >= 0) and torch.all(r.z[:, 1:] >= r.z[:, :-1])
    # no measured depth: hierarchical sampling (ESLAM/NeRF) refines the coarse interval around the first sample
    # past the surface, so the error is bounded by one coarse spacing (bound exit ~4 m / 128 samples)
    cfg = RenderConfig(n_stratified=128, n_importance=64, perturb=True)
    r = render_rays(field, o, d, torch.zeros(len(u)), T_TRUNC, cfg, gen)
    assert np.abs(r.depth.numpy() - truth).max() < 4.0 / 128 + 0.005
    assert torch.all(r.weights.sum(-1) <= 1 + 1e-5), r.weights.sum(-1).max()


def test_depth_guided_samples_and_pdf_sampling():
    gen = torch.Generator().manual_seed(0)
    d = torch.tensor([1.0, 3.0])
    z = depth_guided_depths(d, 32, 8, T_TRUNC, True, gen)
    assert z.shape == (2, 40) and torch.all(z[:, 1:] >= z[:, :-1])
    assert torch.all(z >= 0) and torch.all(z <= 1.2 * d[:, None] + 1e-6)
    band = ((z - d[:, None]).abs() <= 1.5 * T_TRUNC + 1e-6).sum(1)
    assert torch.all(band >= 8)
    bins = torch.linspace(0, 1, 11).expand(4000, 11).contiguous()
    w = torch.zeros(4000, 10)
    w[:, 3] = 1.0  # all mass in [0.3, 0.4]
    s = sample_pdf(bins, w, 16, gen)
    assert float(((s >= 0.3) & (s <= 0.4)).float().mean()) > 0.99


def test_sdf_losses_masks_closed_form():
    T = 0.1
    z = torch.tensor([[0.5, 1.9, 1.98, 2.03, 2.5]])
    s = torch.tensor([[0.8, 0.6, 0.1, -0.2, -1.0]])
    terms = sdf_losses(s, z, torch.tensor([2.0]), T)
    # front: z < d - T -> 0.5; centre: |z - d| < 0.4 T -> 1.98, 2.03; tail: 1.9; behind: 2.5 (ignored)
    assert float(terms["free_space"]) == pytest.approx((0.8 - 1.0) ** 2)
    c = [(1.98 + 0.1 * 0.1 - 2.0) ** 2, (2.03 - 0.2 * 0.1 - 2.0) ** 2]
    assert float(terms["center"]) == pytest.approx(np.mean(c), rel=1e-5)
    assert float(terms["tail"]) == pytest.approx((1.9 + 0.06 - 2.0) ** 2, rel=1e-5)
    empty = sdf_losses(s[:, 4:], z[:, 4:], torch.tensor([2.0]), T)  # only a sample behind: all terms 0, no NaN
    assert all(float(v) == 0.0 for v in empty.values())


@pytest.mark.parametrize("kind", ["quat", "lie"])
def test_pose_gradient_reaches_the_pose_and_matches_finite_differences(kind):
    K, u, v = _pixels(48, seed=3)
    field = AnalyticField(_sphere, beta=10.0)
    Kt = torch.tensor(K, dtype=torch.float32)
    T_true = np.eye(4)
    o, d = world_rays(camera_directions(u, v, Kt), torch.eye(4)[None])
    depth = torch.tensor(_sphere_depth(d.numpy().astype(np.float64)), dtype=torch.float32)
    rgb = torch.full((len(u), 3), 0.5)
    T0 = T_true @ g.exp_se3(np.array([0.02, -0.01, 0.015, 0.03, -0.02, 0.01]))
    cfg = RenderConfig(n_stratified=16, n_importance=16, perturb=False)
    mask = torch.ones(len(u), dtype=torch.bool)

    def loss_of(pose):
        oo, dd = world_rays(camera_directions(u, v, Kt), pose.matrices())
        r = render_rays(field, oo, dd, depth, T_TRUNC, cfg, torch.Generator().manual_seed(0))
        return rendering_loss(r, depth, rgb, T_TRUNC, LossWeights(), mask, mask)[0]

    pose = PoseParams(T0, kind)
    loss = loss_of(pose)
    loss.backward()
    grads = torch.cat([pose.rotation.grad.ravel(), pose.translation.grad.ravel()])
    assert torch.all(torch.isfinite(grads)) and float(grads.norm()) > 1e-3
    # central differences on two parameters
    for param, i in ((pose.translation, 0), (pose.rotation, 1)):
        eps = 1e-3
        with torch.no_grad():
            param[0, i] += eps
            up = float(loss_of(pose))
            param[0, i] -= 2 * eps
            down = float(loss_of(pose))
            param[0, i] += eps
        fd = (up - down) / (2 * eps)
        assert float(param.grad[0, i]) == pytest.approx(fd, rel=0.1, abs=1e-3)


def test_scene_model_gradients_flow_to_pose_and_field():
    model = SceneModel(BOUND)
    K, u, v = _pixels(32, seed=4)
    pose = PoseParams(np.eye(4), "lie")
    o, d = world_rays(camera_directions(u, v, torch.tensor(K, dtype=torch.float32)), pose.matrices())
    depth = torch.full((32,), 2.0)
    r = render_rays(model, o, d, depth, T_TRUNC, RenderConfig(), torch.Generator().manual_seed(0))
    mask = torch.ones(32, dtype=torch.bool)
    loss, _ = rendering_loss(r, depth, torch.rand(32, 3), T_TRUNC, LossWeights(), mask, mask)
    loss.backward()
    for grad in (pose.rotation.grad, pose.translation.grad):
        assert torch.all(torch.isfinite(grad)) and float(grad.abs().sum()) > 0
    assert all(p.grad is not None and torch.all(torch.isfinite(p.grad)) for p in model.parameters())


def test_colour_only_where_the_weight_counts():
    """``colour_min_weight``: the appearance is queried only at samples above the weight; depth, SDF and weights
    are unchanged, the colour moves by at most the weight left out, and colour gradients still reach the rays."""
    K, u, v = _pixels(40, seed=5)
    queried = []

    class Counting(AnalyticField):
        def colour(self, p):
            queried.append(len(p))
            return super().colour(p)

    field = Counting(_sphere, beta=10.0)
    o, d = world_rays(camera_directions(u, v, torch.tensor(K, dtype=torch.float32)), torch.eye(4)[None])
    depth = torch.tensor(_sphere_depth(d.numpy().astype(np.float64)), dtype=torch.float32)
    out = {}
    for w_min in (0.0, 1e-30, 1e-3):
        oo, dd = o.clone().requires_grad_(True), d.clone().requires_grad_(True)
        cfg = RenderConfig(n_stratified=32, n_importance=8, perturb=False, colour_min_weight=w_min)
        r = render_rays(field, oo, dd, depth, T_TRUNC, cfg, torch.Generator().manual_seed(0))
        r.rgb.sum().backward()
        out[w_min] = (r, oo.grad, queried[-1])
    full, _, n_full = out[0.0]
    assert n_full == 40 * 40
    # a threshold below every weight selects all samples: the same numbers bit for bit
    same, _, n_same = out[1e-30]
    assert n_same == int((full.weights > 1e-30).sum()) and torch.equal(same.rgb, full.rgb)
    cut, grad_o, n_cut = out[1e-3]
    dropped = (full.weights * (full.weights <= 1e-3)).sum(-1)
    assert n_cut == int((full.weights > 1e-3).sum()) and n_cut < 0.5 * n_full
    assert torch.equal(cut.depth, full.depth) and torch.equal(cut.weights, full.weights)
    diff = (cut.rgb - full.rgb).abs().max(-1).values
    assert torch.all(diff <= dropped + 1e-6) and float(diff.max()) > 0  # colours lie in [0.25, 0.75]
    assert torch.all(torch.isfinite(grad_o)) and float(grad_o.abs().sum()) > 0
