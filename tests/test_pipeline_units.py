"""Unit tests of the pipeline's own pieces (no SLAM run)."""

import numpy as np
import pytest

from lrslam.camera import intrinsics_matrix
from lrslam.geometry import make_pose, random_pose
from lrslam.pipeline.trajectory import Trajectory
from lrslam.pipeline.auto_bound import bound_from_frame
from lrslam.pipeline.timing import StageTimer


def test_trajectory_follows_keyframe_corrections(rng):
    poses = [random_pose(rng, 1.0, 30.0) for _ in range(6)]
    traj = Trajectory(interpolate=False)
    for i, T in enumerate(poses):
        traj.add(T, is_keyframe=i in (0, 3))
    np.testing.assert_allclose(traj.poses(), np.stack(poses), atol=1e-12)
    # move keyframe 3 by a correction C: frames 3..5 follow rigidly, frames 0..2 stay
    C = random_pose(rng, 0.2, 5.0)
    moved = traj.apply_corrections({3: C @ poses[3], 0: poses[0] @ random_pose(rng, 1e-6, 1e-4)},
                                   min_shift_m=1e-4, min_shift_deg=0.01)
    assert list(moved) == [3]              # keyframe 0 moved less than the write threshold: untouched
    got = traj.poses()
    np.testing.assert_allclose(got[:3], np.stack(poses[:3]), atol=1e-12)
    np.testing.assert_allclose(got[3:], np.stack([C @ T for T in poses[3:]]), atol=1e-12)
    assert traj.keyframe_ids() == [0, 3]


def test_trajectory_spreads_a_keyframe_correction_over_the_gap_before_it(rng):
    # keyframes 0 and 4; the graph moves keyframe 4 by a world translation t: frame c of the gap moves by
    # (c / 4) t exactly (closed form of the blend for a pure translation), frames after 4 by t (rigidly)
    poses = [random_pose(rng, 1.0, 30.0) for _ in range(7)]
    traj = Trajectory()
    for i, T in enumerate(poses):
        traj.add(T, is_keyframe=i in (0, 4))
    np.testing.assert_allclose(traj.poses(), np.stack(poses), atol=1e-12)   # adding a keyframe moves nothing
    t = np.array([0.03, -0.02, 0.05])
    traj.apply_corrections({4: make_pose(np.eye(3), t) @ poses[4]})
    got = traj.poses()
    for c in range(7):
        np.testing.assert_allclose(got[c][:3, :3], poses[c][:3, :3], atol=1e-12)
        np.testing.assert_allclose(got[c][:3, 3], poses[c][:3, 3] + min(c / 4, 1.0) * t, atol=1e-12)
    # rigidly, the old behaviour: the gap stays with keyframe 0
    rigid = Trajectory(interpolate=False)
    for i, T in enumerate(poses):
        rigid.add(T, is_keyframe=i in (0, 4))
    rigid.apply_corrections({4: make_pose(np.eye(3), t) @ poses[4]})
    np.testing.assert_allclose(rigid.poses()[1:4], np.stack(poses[1:4]), atol=1e-12)


def test_trajectory_interpolation_survives_a_checkpoint_and_set_pose(rng):
    poses = [random_pose(rng, 1.0, 30.0) for _ in range(6)]
    traj = Trajectory()
    for i, T in enumerate(poses):
        traj.add(T, is_keyframe=i in (0, 3))
    T1 = random_pose(rng, 1.0, 30.0)
    traj.set_pose(1, T1)                            # a frame of a closed gap: exactly the pose it was given
    np.testing.assert_allclose(traj.pose(1), T1, atol=1e-12)
    other = Trajectory()
    other.load_state_dict(traj.state_dict())
    C = random_pose(rng, 0.1, 5.0)
    for t in (traj, other):
        t.apply_corrections({3: C @ t.pose(3), 0: random_pose(rng, 0.0, 0.0) @ t.pose(0)})
    np.testing.assert_allclose(other.poses(), traj.poses(), atol=1e-12)
    assert not np.allclose(traj.pose(2), poses[2], atol=1e-6)     # the gap moved with keyframe 3


def test_trajectory_set_pose_of_non_keyframe(rng):
    traj = Trajectory()
    traj.add(np.eye(4), is_keyframe=True)
    traj.add(np.eye(4))
    T = random_pose(rng, 0.5, 10.0)
    traj.set_pose(1, T)
    np.testing.assert_allclose(traj.pose(1), T, atol=1e-12)


def test_last_motion_is_the_step_between_the_last_two_frames():
    traj = Trajectory()
    assert traj.last_motion() == (0.0, 0.0)
    traj.add(np.eye(4), is_keyframe=True)
    assert traj.last_motion() == (0.0, 0.0)                     # one frame: no motion yet
    step = make_pose(np.eye(3), [0.05, 0.0, 0.0])
    traj.add(step)
    assert traj.last_motion() == pytest.approx((0.05, 0.0), abs=1e-12)
    c, s = np.cos(np.radians(10.0)), np.sin(np.radians(10.0))
    traj.add(step @ make_pose(np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]]), [0.0, 0.03, 0.04]))
    assert traj.last_motion() == pytest.approx((0.05, 10.0), abs=1e-9)   # 3-4-5 cm and 10 deg


def test_bound_from_frame_contains_points_and_camera():
    K = intrinsics_matrix(100.0, 100.0, 31.5, 23.5)
    depth = np.full((48, 64), 2.0, dtype=np.float32)
    T = np.eye(4)
    T[:3, 3] = [1.0, 2.0, 3.0]
    b = bound_from_frame(depth, K, T, margin=0.5)
    assert b.shape == (3, 2)
    # the wall at z = 2 m in the camera lies at world z = 5; the camera at z = 3
    assert b[2, 0] == pytest.approx(3.0 - 0.5) and b[2, 1] == pytest.approx(5.0 + 0.5)
    with pytest.raises(ValueError, match="no valid depth"):
        bound_from_frame(np.zeros_like(depth), K, T)


def test_stage_timer_sums_each_stage_exactly(monkeypatch):
    """A fake clock that advances by known steps: each stage's total, calls and per-frame time are exact, a
    stage that raises is still timed, and a checkpoint round trip resumes the sums."""
    from types import SimpleNamespace

    import lrslam.pipeline.timing as timing

    now = [0.0]
    monkeypatch.setattr(timing, "time", SimpleNamespace(perf_counter=lambda: now[0]))

    def stage(t, name, seconds, fail=False):
        with t(name):
            now[0] += seconds
            if fail:
                raise RuntimeError("stage failed")

    t = StageTimer()
    for seconds in (0.5, 0.25, 1.0):
        stage(t, "track", seconds)
    stage(t, "map", 2.0)
    with pytest.raises(RuntimeError):
        stage(t, "map", 0.125, fail=True)
    now[0] += 10.0                                    # time outside any stage counts nowhere
    assert t.summary(4) == {"track": {"total_s": 1.75, "calls": 3, "per_frame_s": 0.4375},
                            "map": {"total_s": 2.125, "calls": 2, "per_frame_s": 0.53125}}
    resumed = StageTimer()
    resumed.load_state_dict(t.state_dict())
    stage(resumed, "track", 0.25)
    assert resumed.summary(5)["track"] == {"total_s": 2.0, "calls": 4, "per_frame_s": 0.4}
    assert t.summary(4)["track"]["calls"] == 3       # the checkpoint is a copy, not a view


def test_long_chains_through_the_trajectory_stay_rigid(rng):
    """Seeds chain through the trajectory (last pose x increment); a keyframe every few frames used to
    compound a tiny rotation drift (inverse by transposition of a non-orthonormal keyframe) until frame ~100
    was rejected as not rigid."""
    from lrslam.geometry import is_valid_pose

    traj = Trajectory()
    T = random_pose(rng, 1.0, 30.0)
    T[:3, :3] *= 1.0 + 1e-9  # a keyframe slightly off SO(3), as float32 kernels leave them
    traj.add(T, is_keyframe=True)
    for i in range(1, 2000):
        inc = random_pose(rng, 0.01, 1.0)
        traj.add(traj.pose(-1) @ inc, is_keyframe=i % 5 == 0)
    R = traj.pose(-1)[:3, :3]
    assert np.abs(R.T @ R - np.eye(3)).max() < 1e-12
    assert all(is_valid_pose(P) for P in traj.poses()[::50])


@pytest.mark.parametrize("override", ["field.tracking.iters=-5", "field.mapping.n_rays=0", "field.mapping.iters=-1",
                                      "field.render.n_stratified=0", "schedule.map_every=0", "keyframes.every_n=-1",
                                      "backend.remap_keyframes=0", "odometry.gates.min_fitness=2",
                                      "field.mapping.max_pose_step=0", "output.partial_every=0"])
def test_counts_and_iterations_are_validated(override):
    """A negative iteration count or an empty ray budget is an error naming the key, not a silent no-op."""
    from lrslam.errors import InputError
    from lrslam.pipeline.config import build_config

    with pytest.raises(InputError, match=override.split("=")[0].replace(".", r"\.")):
        build_config("synthetic", overrides=[override])


def test_tsdf_grows_past_its_initial_block_count(tmp_path):
    """The TSDF starts small (memory follows the surface) and its hash map grows: a start of 20 blocks gives the
    same mesh as a start big enough for everything."""
    from lrslam.datasets import open_sequence
    from lrslam.datasets.synth.writer import generate
    from lrslam.pipeline.tsdf import tsdf_mesh

    seq = open_sequence(generate(tmp_path / "s", scene="room", trajectory="circle", n_frames=4, width=160, height=120,
                                 show_progress=False))
    poses = seq.gt_poses()
    small = tsdf_mesh(iter(seq), poses, voxel=0.04, block_count=20)
    big = tsdf_mesh(iter(seq), poses, voxel=0.04, block_count=20000)
    assert len(big.faces) > 1000
    assert len(small.faces) == len(big.faces)


def test_set_threads_sets_torch_and_the_environment(monkeypatch):
    import torch

    from lrslam.errors import InputError
    from lrslam.threads import set_threads

    old = torch.get_num_threads()
    monkeypatch.delenv("OMP_NUM_THREADS", raising=False)
    try:
        assert set_threads(None) is None and "OMP_NUM_THREADS" not in __import__("os").environ
        assert set_threads(1) == 1 and torch.get_num_threads() == 1
        assert __import__("os").environ["OMP_NUM_THREADS"] == "1"
        with pytest.raises(InputError, match="--threads"):
            set_threads(0)
    finally:
        torch.set_num_threads(old)


_SUBNORMAL_PROBE = """
import sys, threading
import numpy as np
if sys.argv[1] == "slam":
    from lrslam import Slam
    from lrslam.pipeline.config import build_config
    Slam(build_config("synthetic"), np.array([[50.0, 0, 40], [0, 50.0, 30], [0, 0, 1]]), (80, 60))
from lrslam.field import cpu_kernels
tiny = np.float32(1e-20)   # tiny * tiny = 1e-40: subnormal in float32
out = {}
t = threading.Thread(target=lambda: out.update(numpy=float(np.float32(tiny) * np.float32(tiny))))
t.start(); t.join()
lines = [np.full((2, 1), v, np.float32) for v in (tiny, tiny, 1.0)]
res = np.empty((64, 1), np.float32)   # 64 samples: numba splits them over its pool's threads
cpu_kernels.cp_forward(*lines, np.zeros((64, 3), np.int64), np.zeros((64, 3), np.float32), 1, res)
from scipy.spatial import cKDTree
pts = np.random.default_rng(0).random((2000, 3))
pts[:1000, 2] = 0.0   # half on the plane z = 0: with DAZ too (torch's set_flush_denormal) cKDTree segfaults here
cKDTree(pts)
print(out["numpy"], int(np.count_nonzero(res)))
"""


def test_a_run_flushes_subnormal_floats_in_every_thread_it_starts():
    """A new Slam sets flush-to-zero before any pool starts, so a thread started later and numba's pool compute
    1e-20 * 1e-20 as 0 (a subnormal costs ~100x on x86: the CP backward ran 2.7x slower on a run's gradients);
    without it the same products are 1e-40. Subnormal inputs keep their value (FTZ without DAZ): scipy's
    cKDTree still builds on points lying on a plane through 0 (it crashed the mesh evaluation with DAZ)."""
    import subprocess
    import sys

    def probe(arg):
        out = subprocess.run([sys.executable, "-c", _SUBNORMAL_PROBE, arg], capture_output=True, text=True,
                             timeout=300)
        assert out.returncode == 0, out.stderr
        value, nonzero = out.stdout.split()
        return float(value), int(nonzero)

    assert probe("plain") == (pytest.approx(1e-40, rel=0.01), 64)
    assert probe("slam") == (0.0, 0)


def test_default_preset_follows_the_dataset_and_the_device(tmp_path):
    from lrslam.datasets.synth.writer import generate
    from lrslam.pipeline.config_source import default_preset

    seq = generate(tmp_path / "s", scene="room", trajectory="circle", n_frames=2, width=80, height=60,
                   show_progress=False)
    assert default_preset(seq, cuda=False)[0] == "synthetic"    # no synthetic-cpu: the preset is CPU-sized already
    tum = tmp_path / "tum"
    (tum / "rgb").mkdir(parents=True)
    (tum / "depth").mkdir()
    for name in ("rgb.txt", "depth.txt"):
        (tum / name).write_text("# empty\n")
    preset, why = default_preset(tum, cuda=False)
    assert preset == "tum-cpu" and "CPU" in why
    assert default_preset(tum, cuda=True)[0] == "tum"
    assert default_preset(tmp_path / "nothing-here", cuda=False)[0] is None


def test_every_rgbd_dataset_gets_the_one_set_of_cpu_settings(tmp_path):
    """On a CPU a Replica or ScanNet folder gets its ``-cpu`` preset, and every ``-cpu`` dataset preset runs each
    mode with the same field, fusion, schedule and backend settings as ``tum-cpu`` (rgbd-cpu's): a dataset preset
    says what the data is, not how hard to work."""
    from lrslam.pipeline.config import build_config
    from lrslam.pipeline.config_source import default_preset

    (tmp_path / "replica" / "results").mkdir(parents=True)
    (tmp_path / "scannet" / "color").mkdir(parents=True)
    (tmp_path / "scannet" / "depth").mkdir()
    assert default_preset(tmp_path / "replica", cuda=False)[0] == "replica-cpu"
    assert default_preset(tmp_path / "scannet", cuda=False)[0] == "scannet-cpu"
    assert default_preset(tmp_path / "replica", cuda=True)[0] == "replica"
    work = ("field", "fusion", "schedule", "backend", "keyframes", "graph")
    for mode in ("field", "fused"):
        ref = build_config("tum-cpu", mode=mode).model_dump(mode="json")
        for preset in ("7scenes-cpu", "rosbag-cpu", "replica-cpu", "scannet-cpu"):
            cfg = build_config(preset, mode=mode).model_dump(mode="json")
            for key in work:
                want = dict(ref[key])
                # what is true of 7-Scenes (colour not registered to its depth; configs/dataset/7scenes-cpu.yaml)
                special = {"backend": ("calibrate_registrations", False), "fusion": ("chain_model", "equal")}
                if preset == "7scenes-cpu" and key in special:
                    name, value = special[key]
                    assert cfg[key].pop(name) == value and want.pop(name) != value
                assert cfg[key] == want, (preset, mode, key)


def test_dataset_preset_settings_per_mode(tmp_path):
    """A dataset preset's ``modes: {<mode>: ...}`` applies to that mode only, over the preset's own settings
    and under user overrides; an unknown mode name there is a one-line error naming the preset."""
    from lrslam.errors import InputError
    from lrslam.pipeline.config import build_config

    f = tmp_path / "p.yaml"
    f.write_text("field: {tracking: {iters: 30}}\nmodes:\n  fused: {field: {tracking: {iters: 7, fixed_rays: true}}}\n")
    assert build_config(str(f), mode="fused").field.tracking.iters == 7
    assert build_config(str(f), mode="fused").field.tracking.fixed_rays
    assert build_config(str(f), mode="field").field.tracking.iters == 30
    assert not build_config(str(f), mode="field").field.tracking.fixed_rays
    assert build_config(str(f), mode="fused", overrides=["field.tracking.iters=3"]).field.tracking.iters == 3
    assert "modes" not in build_config(str(f), mode="fused").resolved()
    f.write_text("modes:\n  fast: {field: {tracking: {iters: 7}}}\n")
    with pytest.raises(InputError, match="unknown mode"):
        build_config(str(f), mode="fused")
