"""The RGB-D odometry pyramid built in numpy (lrslam.frontend.rgbd_pyramid): closed forms of the two
down-sampling steps, agreement with Open3D's own multi-scale odometry, and results that repeat bit for bit
wherever the images sit in memory (Open3D's IPP Gaussian filter does not)."""

from __future__ import annotations

import numpy as np
import pytest

from frontend_fixtures import T_W_C_REF, make_frame, make_room
from lrslam.frontend.registration import RegistrationConfig, RegistrationGates, register_rgbd
from lrslam.frontend.rgbd_pyramid import hybrid_odometry, pyr_down_depth, pyr_down_intensity
from lrslam.frontend.rgbd_view import RGBDView
from lrslam.geometry import pose_error, random_pose


@pytest.fixture(scope="module")
def pair():
    """(source, target) frames at 320x240 and the true T_tgt_src (4 cm / 2.5 deg)."""
    room = make_room()
    T_rel = random_pose(np.random.default_rng(3), 0.04, 2.5)
    return make_frame(room, T_W_C_REF @ T_rel, index=1), make_frame(room, T_W_C_REF, index=0), T_rel


@pytest.fixture
def one_open3d_thread():
    """Open3D on one thread (its multi-threaded reductions differ from run to run)."""
    from lrslam.pipeline.determinism import open3d_threads

    with open3d_threads(True):
        yield


def _views(pair):
    source, target, _ = pair
    return (RGBDView(source.rgb.copy(), source.depth.copy(), source.K.copy()),
            RGBDView(target.rgb.copy(), target.depth.copy(), target.K.copy()))


def test_pyr_down_intensity_matches_open3d(pair):
    import open3d as o3d

    grey = o3d.t.geometry.Image(pair[1].rgb).rgb_to_gray().to(o3d.core.Dtype.Float32)
    ref = grey.pyrdown().as_tensor().numpy()[..., 0]
    ours = pyr_down_intensity(grey.as_tensor().numpy()[..., 0].copy())
    assert ours.shape == ref.shape == (120, 160) and ours.dtype == np.float32
    np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-6)


def test_pyr_down_intensity_closed_forms():
    assert np.array_equal(pyr_down_intensity(np.full((8, 10), 0.25, np.float32)), np.full((4, 5), 0.25, np.float32))
    # A ramp along x stays a ramp (symmetric kernel) away from the replicated border: value at even column 2k.
    ramp = np.tile(np.arange(12, dtype=np.float32), (6, 1))
    np.testing.assert_allclose(pyr_down_intensity(ramp)[:, 1:5], np.tile([2.0, 4.0, 6.0, 8.0], (3, 1)), atol=1e-5)


def test_pyr_down_depth_closed_forms():
    plane = np.full((6, 8), 2.0, np.float32)
    assert np.array_equal(pyr_down_depth(plane, 0.14), np.full((3, 4), 2.0, np.float32))
    d = plane.copy()
    d[2, 2] = np.nan                                  # centre of output (1, 1)
    d[2, 4] = 3.0                                     # centre of output (1, 2): 1 m off the plane
    d[3, 4] = 2.05
    out = pyr_down_depth(d, 0.14)
    assert np.isnan(out[1, 1])                        # invalid centre -> invalid
    assert out[1, 2] == np.float32(3.0)               # every neighbour > 0.14 m away: the centre alone
    assert out[0, 2] == np.float32(2.0)               # 3.0 and the NaN left out, 2.05 out of reach (dy = 3)
    # Output (2, 2), centred on d[4, 4] = 2.0 (window rows 2..5, clipped, columns 2..6): the weighted mean of
    # the neighbours within 0.14 m, weights 0.375 / 0.25 / 0.0625 by offset per axis.
    g = {0: 0.375, 1: 0.25, 2: 0.0625}
    num = den = 0.0
    for r in range(2, 6):
        for c in range(2, 7):
            if np.isfinite(d[r, c]) and abs(d[r, c] - 2.0) < 0.14:
                num, den = num + g[abs(r - 4)] * g[abs(c - 4)] * d[r, c], den + g[abs(r - 4)] * g[abs(c - 4)]
    assert out[2, 2] == pytest.approx(num / den, abs=1e-6) and out[2, 2] > 2.0


def _both(source: RGBDView, target: RGBDView, iterations: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray]:
    """T_tgt_src from identity by Open3D's ``rgbd_odometry_multi_scale`` (hybrid) and by ours, same parameters
    (depth_max 4 m, truncation 0.07, Huber deltas 0.05 / 0.1, relative tolerances 1e-6)."""
    import open3d as o3d

    od = o3d.t.pipelines.odometry
    rgbd = [o3d.t.geometry.RGBDImage(o3d.t.geometry.Image(v.rgb), o3d.t.geometry.Image(v.depth[..., None].copy()))
            for v in (source, target)]
    ref = od.rgbd_odometry_multi_scale(
        rgbd[0], rgbd[1], o3d.core.Tensor(target.K), o3d.core.Tensor(np.eye(4)), 1.0, 4.0,
        [od.OdometryConvergenceCriteria(n, 1e-6, 1e-6) for n in iterations], od.Method.Hybrid,
        od.OdometryLossParams(0.07, 0.05, 0.1)).transformation.numpy()
    ours = hybrid_odometry(source, target, np.eye(4), iterations, 1e-6, 1e-6, 4.0, 0.07, 0.05, 0.1)
    return ref, ours


def test_one_level_is_open3d(pair, one_open3d_thread):
    """With a single level there is no pyramid: the loop is Open3D's, step for step."""
    source, target = _views(pair)
    for iters in (1, 3, 20):
        ref, ours = _both(source, target, (iters,))
        np.testing.assert_allclose(ours, ref, rtol=0, atol=1e-12)


def test_three_levels_agree_with_open3d_and_the_truth(pair, one_open3d_thread):
    ref, ours = _both(*_views(pair), (20, 10, 5))
    d_t, d_r = pose_error(ours, ref)
    assert d_t < 2e-4 and d_r < 0.02, (d_t, d_r)
    d_t, d_r = pose_error(ours, pair[2])           # Open3D's own: 4.14 mm, 0.058 deg on this pair
    assert d_t < 0.005 and d_r < 0.1, (d_t, d_r)


def test_registration_repeats_bit_for_bit_wherever_the_images_sit(pair, one_open3d_thread):
    """The same two frames registered 16 times on one Open3D thread, with fresh image copies and a different
    heap layout each time: one result. (With Open3D's own multi-scale function the IPP-filtered intensity
    pyramid changed with the addresses: 8-13 distinct results in 20 on an AMD EPYC.)"""
    rng = np.random.default_rng(0)
    cfg, gates = RegistrationConfig(method="rgbd"), RegistrationGates()
    results = set()
    for k in range(16):
        junk = [np.empty(int(rng.integers(1, 50_000)), np.uint8) for _ in range(k)]
        source, target = _views(pair)
        res = register_rgbd(source, target, np.eye(4), cfg, gates)
        assert res.ok, res.reason
        results.add(res.T_tgt_src.tobytes())
        del junk
    assert len(results) == 1
