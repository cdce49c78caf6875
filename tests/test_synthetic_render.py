"""Synthetic rendering against closed forms, and sensor-noise statistics."""

from __future__ import annotations

import numpy as np
import pytest

from lrslam.camera import backproject_depth, pixel_directions, transform_points
from lrslam.datasets.synth.noise import NoiseConfig, apply_noise, kinect_sigma, noise_preset
from lrslam.datasets.synth.render import Renderer, default_intrinsics
from lrslam.datasets.synth.scene import make_scene
from lrslam.datasets.synth.trajectories import look_rotation
from lrslam.geometry import make_pose


@pytest.fixture(scope="module")
def empty_room():
    return make_scene("empty", seed=0)


def _analytic_box_depth(T_w_c, K, H, W, room):
    """z-depth of every pixel inside the box room[3, 2] seen from T_w_c: closest exit of the ray."""
    d_c = pixel_directions(K, H, W).reshape(-1, 3)  # unit z, so the ray parameter is the z-depth
    d_w = d_c @ T_w_c[:3, :3].T
    o = T_w_c[:3, 3]
    with np.errstate(divide="ignore"):
        t = np.where(d_w > 0, (room[:, 1] - o) / d_w, (room[:, 0] - o) / d_w)
    return np.min(np.where(np.isfinite(t) & (t > 0), t, np.inf), axis=1).reshape(H, W)


def test_default_intrinsics():
    np.testing.assert_allclose(default_intrinsics(320, 240), [[260, 0, 159.5], [0, 260, 119.5], [0, 0, 1]])
    np.testing.assert_allclose(default_intrinsics(640, 480), [[520, 0, 319.5], [0, 520, 239.5], [0, 0, 1]])


@pytest.mark.parametrize("ypr_deg", [(0.0, 0.0, 0.0), (37.0, -25.0, 8.0), (200.0, 12.0, -5.0)])
def test_depth_of_the_box_room_equals_the_closed_form(empty_room, ypr_deg):
    sc = empty_room
    room = sc.bound + np.array([0.1, -0.1])
    T = make_pose(look_rotation(np.radians([ypr_deg]))[0], [0.3, -0.2, 1.3])
    K = default_intrinsics(160, 120)
    rgb, depth = Renderer(sc, K, 160, 120, antialias=1).render(T)
    expected = _analytic_box_depth(T, K, 120, 160, room)
    assert depth.dtype == np.float32 and rgb.dtype == np.uint8 and rgb.shape == (120, 160, 3)
    assert np.all(depth > 0)
    assert np.abs(depth - expected).max() < 1e-5
    if ypr_deg == (0.0, 0.0, 0.0):  # straight at the wall x = +2: constant depth 1.7 m
        np.testing.assert_allclose(depth, 1.7, atol=1e-5)


def test_backprojected_pixels_carry_the_colour_of_their_surface_point(empty_room):
    sc = empty_room
    T = make_pose(look_rotation(np.radians([[120.0, -20.0, 3.0]]))[0], [-0.2, 0.1, 1.2])
    K = default_intrinsics(160, 120)
    r = Renderer(sc, K, 160, 120, antialias=1)
    rgb, depth = r.render(T)
    p_w = transform_points(T, backproject_depth(depth, K).reshape(-1, 3))
    prim = r.cast(T, pixel_directions(K, 120, 160).reshape(-1, 3))["primitive"]
    diff = np.abs(sc.colour_at(p_w, prim).astype(int) - rgb.reshape(-1, 3))
    assert np.percentile(diff, 99) <= 1 and diff.max() <= 3


def test_antialiasing_changes_only_silhouette_pixels():
    sc = make_scene("room", seed=0)
    T = make_pose(look_rotation(np.radians([[0.0, -15.0, 0.0]]))[0], [0.0, 0.0, 1.3])
    K = default_intrinsics(160, 120)
    rgb1, d1 = Renderer(sc, K, 160, 120, antialias=1).render(T)
    rgb3, d3 = Renderer(sc, K, 160, 120, antialias=3).render(T)
    np.testing.assert_array_equal(d1, d3)
    changed = np.any(rgb1 != rgb3, axis=-1)
    assert 0 < changed.mean() < 0.2


# ------------------------------------------------------------------------------------------------------ noise
def test_no_noise_by_default():
    rgb = np.full((24, 32, 3), 100, np.uint8)
    depth = np.full((24, 32), 2.0, np.float32)
    r, d = apply_noise(rgb, depth, NoiseConfig())
    np.testing.assert_array_equal(r, rgb)
    np.testing.assert_array_equal(d, depth)
    assert not NoiseConfig().enabled


def test_gaussian_and_colour_noise_have_the_set_sigma():
    rgb = np.full((240, 320, 3), 120, np.uint8)
    depth = np.full((240, 320), 2.0, np.float32)
    cfg = NoiseConfig(depth_sigma=0.01, colour_sigma=4.0, seed=3)
    r, d = apply_noise(rgb, depth, cfg, frame_index=7)
    assert abs(np.std(d - depth) / 0.01 - 1) < 0.1 and abs(np.mean(d - depth)) < 0.001
    assert abs(np.std(r.astype(float) - 120) / 4.0 - 1) < 0.1
    r2, d2 = apply_noise(rgb, depth, cfg, frame_index=7)
    np.testing.assert_array_equal(d, d2)
    np.testing.assert_array_equal(r, r2)
    assert not np.array_equal(d, apply_noise(rgb, depth, cfg, frame_index=8)[1])


def test_kinect_noise_grows_with_depth():
    np.testing.assert_allclose(kinect_sigma(np.array([0.4, 2.0])), [0.0012, 0.0012 + 0.0019 * 1.6**2])
    depth = np.full((240, 320), 1.0, np.float32)
    depth[:, 160:] = 3.5
    _, d = apply_noise(np.zeros((240, 320, 3), np.uint8), depth, NoiseConfig(kinect=True))
    for sl, z in ((np.s_[:, :160], 1.0), (np.s_[:, 160:], 3.5)):
        assert abs(np.std(d[sl] - depth[sl]) / kinect_sigma(z) - 1) < 0.1


def test_holes_and_edge_dropout():
    depth = np.full((240, 320), 2.0, np.float32)
    depth[:, 200:] = 3.0
    _, d = apply_noise(np.zeros((240, 320, 3), np.uint8), depth, NoiseConfig(holes=0.05, seed=1))
    assert abs((d == 0).mean() - 0.05) < 0.005
    from scipy.ndimage import label

    n_blobs = label(d == 0)[1]
    assert n_blobs < 0.05 * d.size / 10  # blobs, not salt-and-pepper
    _, d = apply_noise(np.zeros((240, 320, 3), np.uint8), depth, NoiseConfig(edge_dropout=1.0))
    assert set(np.flatnonzero(np.any(d == 0, axis=0))) == {199, 200}


def test_noise_presets():
    assert not noise_preset("none").enabled
    assert noise_preset("gaussian", depth_sigma=0.02).depth_sigma == 0.02
    assert noise_preset("kinect").kinect and not noise_preset("kinect").holes
    cfg = noise_preset("kinect+holes", holes=0.03)
    assert cfg.kinect and cfg.holes == 0.03 and cfg.edge_dropout > 0 and cfg.colour_sigma == 0
    assert noise_preset("all", colour_sigma=2.0).colour_sigma == 2.0
    with pytest.raises(ValueError, match="unknown noise preset"):
        noise_preset("speckle")
