"""Colour registered to depth (lrslam.datasets.colour_registration) and the 7-Scenes reader that uses it."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lrslam.camera import intrinsics_matrix
from lrslam.datasets import ReaderOptions, open_sequence
from lrslam.datasets.colour_registration import ColourToDepth
from lrslam.datasets.sevenscenes import SEVEN_SCENES_COLOUR_INTRINSICS, SEVEN_SCENES_T_COLOUR_DEPTH

K_D = intrinsics_matrix(10.0, 10.0, 4.0, 3.0)
K_C = intrinsics_matrix(9.0, 8.5, 4.5, 3.5)


def _rig() -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("xyz", [1.0, 2.0, -0.5], degrees=True).as_matrix()
    T[:3, 3] = [0.05, -0.02, 0.01]
    return T


def _expected(u: int, v: int, z: float, T: np.ndarray) -> tuple[float, float]:
    """Colour pixel of depth pixel (u, v) at depth z (0: its direction), written out step by step."""
    x = np.array([(u - K_D[0, 2]) / K_D[0, 0], (v - K_D[1, 2]) / K_D[1, 1], 1.0])
    X = T[:3, :3] @ (z * x) + T[:3, 3] if z > 0 else T[:3, :3] @ x
    return K_C[0, 0] * X[0] / X[2] + K_C[0, 2], K_C[1, 1] * X[1] / X[2] + K_C[1, 2]


def test_identity_rig_leaves_the_image_as_is():
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (6, 8, 3), dtype=np.uint8)
    depth = rng.uniform(0.5, 3.0, (6, 8)).astype(np.float32)
    reg = ColourToDepth(K_D, K_D, np.eye(4))
    mx, my = reg.sample_positions(depth)
    u, v = np.meshgrid(np.arange(8), np.arange(6))
    np.testing.assert_allclose(mx, u, atol=1e-5)
    np.testing.assert_allclose(my, v, atol=1e-5)
    np.testing.assert_array_equal(reg(rgb, depth), rgb)


def test_sample_positions_are_the_rig_projection():
    T = _rig()
    depth = np.full((6, 8), 2.0, dtype=np.float32)
    depth[1, 2] = 0.0  # no depth: the pixel's direction
    depth[4, 6] = 0.7
    mx, my = ColourToDepth(K_D, K_C, T).sample_positions(depth)
    for v in range(6):
        for u in range(8):
            eu, ev = _expected(u, v, float(depth[v, u]), T)
            assert mx[v, u] == pytest.approx(eu, abs=1e-4) and my[v, u] == pytest.approx(ev, abs=1e-4)
    # the parallax of the 5 cm baseline: the near pixel moves further than the far one
    assert abs(mx[4, 6] - _expected(6, 4, 0.0, T)[0]) > abs(mx[3, 6] - _expected(6, 3, 0.0, T)[0])


def test_registered_colour_is_the_colour_seen_at_the_projection():
    # a colour image that is a linear ramp in the colour camera's u: bilinear sampling recovers it exactly
    uc = np.arange(12, dtype=np.float64)
    ramp = np.repeat((10.0 * uc + 20.0)[None, :, None], 10, axis=0).repeat(3, axis=2).astype(np.uint8)
    depth = np.full((6, 8), 1.5, dtype=np.float32)
    reg = ColourToDepth(K_D, K_C, _rig())
    out = reg(ramp, depth)
    mx, _ = reg.sample_positions(depth)
    np.testing.assert_allclose(out[..., 0], 10.0 * mx + 20.0, atol=1.0)


def _write_kinect_frame(root: Path, rgb: np.ndarray, depth_mm: np.ndarray) -> None:
    root.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(root / "frame-000000.color.png"), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    cv2.imwrite(str(root / "frame-000000.depth.png"), depth_mm)


def test_7scenes_reader_registers_the_kinect_colour(tmp_path):
    rng = np.random.default_rng(1)
    rgb = cv2.resize(rng.integers(0, 256, (48, 64, 3), dtype=np.uint8), (640, 480), interpolation=cv2.INTER_LINEAR)
    depth_mm = np.full((480, 640), 1500, dtype=np.uint16)
    depth_mm[:40] = 0
    _write_kinect_frame(tmp_path / "k", rgb, depth_mm)

    registered = open_sequence(tmp_path / "k")[0].rgb
    raw = open_sequence(tmp_path / "k", options=ReaderOptions(register_colour=False))[0].rgb
    np.testing.assert_array_equal(raw, rgb)
    reg = ColourToDepth(intrinsics_matrix(585.0, 585.0, 320.0, 240.0),
                        intrinsics_matrix(*SEVEN_SCENES_COLOUR_INTRINSICS), SEVEN_SCENES_T_COLOUR_DEPTH)
    np.testing.assert_array_equal(registered, reg(rgb, depth_mm.astype(np.float32) / 1000.0))
    assert np.abs(registered.astype(int) - raw.astype(int)).mean() > 5

    # the Kinect's depth intrinsics in a camera-intrinsics.txt (as the shared excerpt has): registered; a folder
    # naming another camera: its colour is left as recorded
    _write_kinect_frame(tmp_path / "file", rgb, depth_mm)
    np.savetxt(tmp_path / "file" / "camera-intrinsics.txt", [[585.0, 0, 320.0], [0, 585.0, 240.0], [0, 0, 1]])
    np.testing.assert_array_equal(open_sequence(tmp_path / "file")[0].rgb, registered)
    _write_kinect_frame(tmp_path / "own", rgb, depth_mm)
    np.savetxt(tmp_path / "own" / "camera-intrinsics.txt", [[570.0, 0, 321.0], [0, 570.0, 239.0], [0, 0, 1]])
    np.testing.assert_array_equal(open_sequence(tmp_path / "own")[0].rgb, rgb)


def _edge_agreement(rgb: np.ndarray, depth: np.ndarray) -> float:
    """Mean colour gradient at depth edges over the mean colour gradient (higher: colour edges sit on depth edges)."""
    g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY).astype(np.float32)
    gm = np.hypot(cv2.Sobel(g, cv2.CV_32F, 1, 0), cv2.Sobel(g, cv2.CV_32F, 0, 1))
    d = cv2.medianBlur(depth.astype(np.float32), 5)
    dm = np.hypot(cv2.Sobel(d, cv2.CV_32F, 1, 0), cv2.Sobel(d, cv2.CV_32F, 0, 1))
    edge = (dm > 0.3) & (d > 0)
    inner = np.zeros_like(edge)
    inner[20:-20, 20:-20] = True
    return float(gm[edge & inner].mean() / gm[inner].mean())


@pytest.mark.shared_data
def test_7scenes_registered_colour_edges_meet_depth_edges(shared_data):
    root = shared_data / "7scenes-redkitchen"
    reg = open_sequence(root, options=ReaderOptions(stride=100))
    raw = open_sequence(root, options=ReaderOptions(stride=100, register_colour=False))
    before = np.mean([_edge_agreement(raw[i].rgb, raw[i].depth) for i in range(len(raw))])
    after = np.mean([_edge_agreement(reg[i].rgb, reg[i].depth) for i in range(len(reg))])
    assert after > 1.3 * before  # measured: 1.26 -> 2.13 over every 25th frame
