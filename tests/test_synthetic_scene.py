"""Synthetic scenes: bound, determinism, texture, mesh export, clearance around the camera region;
trajectories: inside the region, hand-held speeds, loop closure."""

from __future__ import annotations

import numpy as np
import pytest

from lrslam.errors import InputError
from lrslam.datasets.synth.scene import SCENES, make_scene
from lrslam.datasets.synth.trajectories import TRAJECTORIES, camera_region, make_trajectory, motion_per_frame
from lrslam.geometry import is_valid_pose, pose_error


@pytest.fixture(scope="module")
def scenes():
    return {name: make_scene(name, seed=0) for name in SCENES}


def _distance(scene, points):
    import open3d as o3d

    return scene.raycaster().compute_distance(o3d.core.Tensor(np.asarray(points, np.float32))).numpy()


# ---------------------------------------------------------------------------------------------------- scenes
def test_bound_is_room_plus_margin_and_contains_mesh(scenes):
    for name, sc in scenes.items():
        sx, sy, sz = SCENES[name][0]
        np.testing.assert_allclose(sc.bound, [[-sx / 2 - 0.1, sx / 2 + 0.1], [-sy / 2 - 0.1, sy / 2 + 0.1],
                                              [-0.1, sz + 0.1]], atol=1e-12)
        assert np.all(sc.vertices >= sc.bound[:, 0] + 0.1 - 1e-9) and np.all(sc.vertices <= sc.bound[:, 1] - 0.1 + 1e-9)
        assert len(sc.triangle_primitive) == len(sc.triangles)
    sc = make_scene("room", seed=0, size=(5.0, 3.5, 2.8))
    np.testing.assert_allclose(sc.bound[:, 1] - sc.bound[:, 0], [5.2, 3.7, 3.0])


def test_scene_is_deterministic_and_seed_dependent(scenes):
    a, b, c = scenes["room"], make_scene("room", seed=0), make_scene("room", seed=1)
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.vertex_colours(), b.vertex_colours())
    assert a.vertices.shape != c.vertices.shape or not np.allclose(a.vertices, c.vertices)
    # colour of a point does not depend on the batch it is queried with
    rng = np.random.default_rng(0)
    idx = rng.choice(len(a.vertices), 5000, replace=False)
    prim = np.zeros(len(a.vertices), dtype=np.int64)
    prim[a.triangles.reshape(-1)] = np.repeat(a.triangle_primitive, 3)
    col = a.colour_at(a.vertices[idx], prim[idx])
    assert col.dtype == np.uint8 and col.shape == (5000, 3)
    np.testing.assert_array_equal(a.colour_at(a.vertices[idx[::-1]], prim[idx[::-1]]), col[::-1])
    np.testing.assert_array_equal(a.colour_at(a.vertices[idx[:7]], prim[idx[:7]]), col[:7])


def test_room_faces_point_inwards_and_objects_exist(scenes):
    sc = scenes["room"]
    kinds = [p.kind for p in sc.primitives]
    assert kinds[:6] == ["floor", "ceiling", "wall", "wall", "wall", "wall"]
    assert {"box", "cylinder", "sphere"} <= set(kinds)
    assert [p.kind for p in scenes["empty"].primitives] == kinds[:6]
    v = sc.vertices[sc.triangles]
    normals = np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])
    centroid = v.mean(axis=1)
    room_centre = np.array([0.0, 0.0, SCENES["room"][0][2] / 2])
    walls = sc.triangle_primitive < 6
    assert np.all(np.einsum("ij,ij->i", normals[walls], room_centre - centroid[walls]) > 0)


def test_texture_has_gradients_at_centimetre_scales_but_is_smooth(scenes):
    sc = scenes["cluttered"]
    rng = np.random.default_rng(1)
    for pid in range(len(sc.primitives)):
        tri = np.flatnonzero(sc.triangle_primitive == pid)
        t = rng.choice(tri, 2000)
        w = rng.dirichlet(np.ones(3), 2000)
        p = np.einsum("nk,nkc->nc", w, sc.vertices[sc.triangles[t]])
        lum = sc.colour_at(p, np.full(len(p), pid)).astype(float).mean(axis=1)
        assert lum.std() > 8.0, f"primitive {pid} ({sc.primitives[pid].kind}) is nearly flat"
        # 1 mm away the colour changes by at most a few grey levels (smooth, no aliasing-prone edges)
        step = rng.normal(size=p.shape)
        step *= 0.001 / np.linalg.norm(step, axis=1, keepdims=True)
        ids = np.full(len(p), pid)
        assert np.abs(sc.colour_at(p + step, ids).astype(int) - sc.colour_at(p, ids)).max() <= 8


def test_export_mesh_round_trip_and_size(tmp_path, scenes):
    import open3d as o3d

    for name in ("room", "cluttered"):
        sc = scenes[name]
        path = sc.export_mesh(tmp_path / f"{name}.ply")
        assert path.stat().st_size < 20e6
        mesh = o3d.io.read_triangle_mesh(str(path))
        np.testing.assert_allclose(np.asarray(mesh.vertices), sc.vertices, atol=1e-9)
        np.testing.assert_array_equal(np.asarray(mesh.triangles), sc.triangles)
        np.testing.assert_allclose(np.asarray(mesh.vertex_colors) * 255, sc.vertex_colours(), atol=0.51)
        assert mesh.has_vertex_normals()


@pytest.mark.parametrize("name", ["room", "small_room", "cluttered"])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_objects_stay_half_a_metre_from_the_camera_region(name, seed):
    sc = make_scene(name, seed=seed)
    reg = sc.camera_region
    g = [np.linspace(lo, hi, 12) for lo, hi in reg]
    pts = np.stack(np.meshgrid(*g, indexing="ij"), axis=-1).reshape(-1, 3)
    on_surface = np.any(np.isclose(pts, reg[:, 0]) | np.isclose(pts, reg[:, 1]), axis=1)
    assert _distance(sc, pts[on_surface]).min() >= 0.5


def test_bad_scene_arguments_raise_input_error():
    with pytest.raises(InputError, match="unknown scene"):
        make_scene("castle")
    with pytest.raises(InputError, match="size"):
        make_scene("room", size=(1.0, 3.0, 2.5))


# ---------------------------------------------------------------------------------------------- trajectories
@pytest.mark.parametrize("kind", TRAJECTORIES)
@pytest.mark.parametrize("name", ["room", "small_room", "cluttered"])
def test_trajectories_stay_inside_at_hand_held_speeds(scenes, kind, name):
    sc = scenes[name]
    for n in (60, 400):
        T = make_trajectory(kind, n, sc.bound, seed=3)
        assert T.shape == (n, 4, 4) and all(is_valid_pose(x, tol=1e-9) for x in T)
        pos = T[:, :3, 3]
        reg = camera_region(sc.bound)
        assert np.all(pos >= reg[:, 0] - 1e-9) and np.all(pos <= reg[:, 1] + 1e-9)
        assert _distance(sc, pos).min() >= 0.5
        dt, dr = motion_per_frame(T)
        assert 0.004 <= dt.mean() <= 0.015 and dt.max() <= 0.02, (dt.mean(), dt.max())
        # the orbit turns its heading at 0.4x its position angle: it travels far per degree turned
        assert (0.3 if kind == "orbit" else 0.4) <= dr.mean() <= 1.5 and dr.max() <= 2.0, (dr.mean(), dr.max())
        # OpenCV axes: the optical axis looks at the room (not at the ceiling), image "down" points down
        assert np.all(T[:, 2, 2] < np.sin(np.radians(15.0)))
        assert np.all(T[:, 2, 1] < 0)


@pytest.mark.parametrize("n", [30, 90, 500])
def test_loop_ends_next_to_its_start(scenes, n):
    T = make_trajectory("loop", n, scenes["room"].bound, seed=0)
    trans, rot = pose_error(T[0], T[-1])
    assert trans < 0.03 and rot < 3.0
    # ... and it is a real loop: it goes away from the start in between
    away = np.array([pose_error(T[0], x) for x in T])
    assert away[:, 0].max() > 0.04 and away[:, 1].max() > 4.0


def test_trajectories_are_deterministic(scenes):
    b = scenes["room"].bound
    for kind in TRAJECTORIES:
        np.testing.assert_array_equal(make_trajectory(kind, 50, b, 4), make_trajectory(kind, 50, b, 4))
        assert not np.allclose(make_trajectory(kind, 50, b, 4), make_trajectory(kind, 50, b, 5))
    with pytest.raises(InputError, match="unknown trajectory"):
        make_trajectory("zigzag", 10, b)
    with pytest.raises(InputError):
        make_trajectory("circle", 1, b)
