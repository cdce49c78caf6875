"""Resumable runs and determinism: checkpoint round trips of every part, ``--resume`` refusing what does not
belong to the run, and runs that repeat bit for bit (same seed, same run after a crash or a SIGKILL + resume).

Determinism on the CPU needs ``deterministic: true`` (``--deterministic``): Open3D 0.20 runs its registrations
on its own thread pool whatever ``OMP_NUM_THREADS`` says, and its multi-threaded reductions differ from run to
run by ~1e-6 m, which a registration gate decided on the edge turns into centimetres (measured: 1.0 cm on the
frontend-only trajectory of a 24-frame run). The field (torch, numba), GTSAM and every generator repeat exactly.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from lrslam.errors import InputError
from lrslam.pipeline.config import build_config
from lrslam.trajectory_io import read_tum

from run_fixtures import TINY as _TINY, assert_same, fail_at_frame, synthetic_room

TINY = _TINY + ["output.mesh=false", "output.plots=false"]


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    return synthetic_room(tmp_path_factory.mktemp("resume") / "room", n_frames=16, seed=1)


def _through_file(state: dict, tmp_path: Path) -> dict:
    """``state`` written by the checkpointer and read back (what a resume gets)."""
    from lrslam.pipeline.checkpoint import Checkpointer, load_checkpoint

    return load_checkpoint(Checkpointer(tmp_path, 1).save(state))


def _frames(seq_dir, n):
    from lrslam.datasets import open_sequence

    seq = open_sequence(seq_dir)
    return seq, [seq[i] for i in range(n)]


# ------------------------------------------------------------------------------------------ part round trips
def test_frontend_parts_round_trip(seq_dir, tmp_path):
    """Odometry, keyframe policy, keyframe link and loop closer: the restored part has the same state and gives
    the same answer for the next frame."""
    from lrslam.backend.keyframe_link import KeyframeLink
    from lrslam.frontend.keyframes import KeyframeConfig, KeyframePolicy
    from lrslam.backend.loop_closure import LoopCloser, LoopClosureConfig
    from lrslam.frontend.odometry import Odometry, OdometryConfig
    from lrslam.pipeline.determinism import open3d_threads

    _, frames = _frames(seq_dir, 8)
    f0, cfg = frames[0], OdometryConfig()
    with open3d_threads(True):
        odo, link = Odometry(cfg, f0.K, f0.height, f0.width), KeyframeLink(cfg.registration, cfg.gates)
        policy, loops = KeyframePolicy(KeyframeConfig()), LoopCloser(LoopClosureConfig(exclude_last=1))
        odo.reset(f0.T_w_c_gt, f0)
        link.start(0, f0)
        policy.add_keyframe(0, f0.depth, f0.K)
        poses = {0: f0.T_w_c_gt}
        for f in frames[1:6]:
            link.accumulate(odo.track(f))
            if f.index % 2 == 0:
                loops.add_keyframe(f.index, f)
                poses[f.index] = f.T_w_c_gt
        parts = {"odometry": (odo, Odometry(cfg, f0.K, f0.height, f0.width)),
                 "link": (link, KeyframeLink(cfg.registration, cfg.gates)),
                 "policy": (policy, KeyframePolicy(KeyframeConfig())),
                 "loops": (loops, LoopCloser(LoopClosureConfig(exclude_last=1)))}
        for name, (part, fresh) in parts.items():
            fresh.load_state_dict(_through_file(part.state_dict(), tmp_path))
            assert_same(part.state_dict(), fresh.state_dict(), name)
        nxt = frames[6]
        a, b = odo.track(nxt), parts["odometry"][1].track(nxt)
        assert np.array_equal(a.T_w_c, b.T_w_c) and a.ok == b.ok
        m_a, m_b = link.measure(6, nxt), parts["link"][1].measure(6, nxt)
        assert np.array_equal(m_a.T_i_j, m_b.T_i_j) and np.array_equal(m_a.information, m_b.information)
        T = nxt.T_w_c_gt
        assert policy.is_keyframe(6, T, f0.T_w_c_gt, nxt.depth, nxt.K) == parts["policy"][1].is_keyframe(
            6, T, f0.T_w_c_gt, nxt.depth, nxt.K)
        found, rejected = [], []
        for closer in (loops, parts["loops"][1]):
            found.append(closer.detect(7, frames[7], poses | {7: frames[7].T_w_c_gt}))
            rejected.append(closer.rejections)
        assert len(found[0]) + len(rejected[0]) >= 1, "no loop candidate: the test checks nothing"
        assert len(found[0]) == len(found[1]) and rejected[0] == rejected[1]
        assert all(np.array_equal(x.T_i_j, y.T_i_j) for x, y in zip(*found))


def test_trajectory_and_timer_round_trip(tmp_path):
    from lrslam.geometry import random_pose
    from lrslam.pipeline.timing import StageTimer
    from lrslam.pipeline.trajectory import Trajectory

    rng = np.random.default_rng(0)
    traj = Trajectory()
    for i in range(7):
        traj.add(random_pose(rng, 1.0, 30.0), is_keyframe=i in (0, 3))
    copy = Trajectory()
    copy.load_state_dict(_through_file(traj.state_dict(), tmp_path))
    assert_same(traj.state_dict(), copy.state_dict())
    T = random_pose(rng, 0.1, 5.0)
    traj.apply_corrections({3: T}), copy.apply_corrections({3: T})   # a correction moves the same frames
    assert np.array_equal(traj.poses(), copy.poses()) and copy.keyframe_ids() == [0, 3]
    timer = StageTimer()
    with timer("map"):
        pass
    t2 = StageTimer()
    t2.load_state_dict(_through_file(timer.state_dict(), tmp_path))
    assert t2.summary(1) == timer.summary(1)


@pytest.mark.parametrize("mode,background", [("field", False), ("fused", False), ("field", True), ("fused", True)])
def test_runner_continues_from_a_checkpoint_file_exactly(seq_dir, tmp_path, mode, background):
    """The whole runner (field tensors, keyframe pixels, generators, graph factors, loop closer, odometry,
    trajectory, records) through a checkpoint file: same state, then the same poses frame after frame. With
    background mapping the checkpoint is taken while a round runs (its result and the tracking copy go along)."""
    from lrslam.pipeline.determinism import open3d_threads
    from lrslam.pipeline.runner import SlamRunner

    cfg = build_config("synthetic", overrides=TINY + [f"schedule.background_mapping={str(background).lower()}"],
                       mode=mode, deterministic=True)
    seq, frames = _frames(seq_dir, 13)
    f0 = frames[0]

    def runner():
        return SlamRunner(cfg, f0.K, f0.height, f0.width, seq.bound)

    with open3d_threads(True):
        a = runner()
        a.start(f0, f0.T_w_c_gt)
        for f in frames[1:8]:
            a.step(f)
        if background and mode == "field":   # a round's result is still to be taken: the checkpoint carries it
            assert a.parts.mapper.field.background.busy
        b = runner()
        b.restore(_through_file(a.checkpoint(), tmp_path))
        assert_same(a.checkpoint(), b.checkpoint())
        for f in frames[8:]:
            ra, rb = a.step(f), b.step(f)
            assert ra == rb
    assert len(a.traj.keyframe_ids()) >= 3
    assert np.array_equal(a.poses(), b.poses())
    untimed = [{k: v for k, v in r.checkpoint().items() if k != "timer"} for r in (a, b)]   # wall times differ
    assert_same(*untimed)


def test_restoring_into_a_runner_of_other_parts_is_refused(seq_dir):
    from lrslam.pipeline.runner import SlamRunner

    seq, (f0,) = _frames(seq_dir, 1)
    field = SlamRunner(build_config("synthetic", overrides=TINY, mode="field"), f0.K, f0.height, f0.width, seq.bound)
    field.start(f0, f0.T_w_c_gt)
    frontend = SlamRunner(build_config("synthetic", mode="frontend"), f0.K, f0.height, f0.width, seq.bound)
    with pytest.raises(InputError, match="other parts"):
        frontend.restore(field.checkpoint())


def test_a_checkpoint_interrupted_while_written_leaves_the_previous_one(tmp_path, monkeypatch):
    import torch

    from lrslam.pipeline.checkpoint import Checkpointer, load_checkpoint

    ck = Checkpointer(tmp_path, 1)
    ck.save({"frame": 6, "poses": np.eye(4)})

    def killed_mid_write(obj, f):
        f.write(b"PK\x03\x04 half a zip")
        raise KeyboardInterrupt

    monkeypatch.setattr(torch, "save", killed_mid_write)
    with pytest.raises(KeyboardInterrupt):
        ck.save({"frame": 12, "poses": np.zeros((4, 4))})
    state = load_checkpoint(ck.path)
    assert state["frame"] == 6 and np.array_equal(state["poses"], np.eye(4))


def test_global_rng_states_round_trip(tmp_path):
    import random

    import torch

    from lrslam.pipeline.determinism import global_rng_state, seed_everything, set_global_rng_state

    seed_everything(4)
    state = _through_file(global_rng_state(), tmp_path)
    first = (random.random(), np.random.rand(), torch.rand(1).item())
    set_global_rng_state(state)
    assert (random.random(), np.random.rand(), torch.rand(1).item()) == first
    seed_everything(5)
    assert (random.random(), np.random.rand(), torch.rand(1).item()) != first


# ------------------------------------------------------------------------------------------ seeds
def test_seed_is_one_setting_with_field_seed():
    assert build_config("synthetic", overrides=["seed=3"]).field.seed == 3
    assert build_config("synthetic", overrides=["field.seed=4"]).seed == 4   # benchmarks set field.seed
    assert build_config(seed=5).field.seed == 5
    with pytest.raises(InputError, match="seed 3 and field.seed 4 disagree"):
        build_config("synthetic", overrides=["seed=3", "field.seed=4"])


def test_seed_on_the_command_line_wins_over_a_fed_back_config(tmp_path):
    from lrslam.config import save_yaml

    save_yaml(tmp_path / "config.yaml", build_config("synthetic", overrides=["seed=2"]).resolved())
    cfg = build_config(str(tmp_path / "config.yaml"), overrides=["seed=7"])
    assert cfg.seed == cfg.field.seed == 7


@pytest.mark.parametrize("mode", ["field", "fused"])
def test_same_seed_same_trajectory_other_seed_other_trajectory(seq_dir, tmp_path, mode):
    from lrslam.pipeline.run import run_sequence

    def poses(seed, name):
        cfg = build_config("synthetic", overrides=TINY + ["dataset.options.max_frames=6"], mode=mode, seed=seed,
                           deterministic=True)
        return run_sequence(seq_dir, cfg, tmp_path / name, progress=False).poses

    a, b = poses(3, "a"), poses(3, "b")
    assert np.array_equal(a, b)
    if mode == "field":   # the seed reaches the poses (fused runs only repeat the check, at twice the cost)
        assert not np.array_equal(a, poses(4, "c"))


# ------------------------------------------------------------------------------------------ --resume on the CLI
def _cli(argv, capfd) -> tuple[int, str]:
    from lrslam.cli import main

    capfd.readouterr()
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in argv])
    return int(e.value.code or 0), capfd.readouterr().err


# frame to frame: a resume with the frame-to-model refinement (frontend mode's default on the CPU presets) is not
# bit for bit (Open3D's voxel grid after its own save / load; tests/test_frontend_model_tracking.py)
FRONTEND = ["--config", "synthetic", "--mode", "frontend", "--seed", "2", "--deterministic", "--checkpoint-every",
            "1", "-q", *[x for o in TINY + ["odometry.model.enabled=false"] for x in ("--set", o)]]


@pytest.fixture
def crashed_run(seq_dir, tmp_path, monkeypatch):
    """A frontend run (checkpoint at every keyframe) that crashed at frame 11: its folder and its checkpoint."""
    from lrslam.cli import main

    out = tmp_path / "run"
    with monkeypatch.context() as m:
        fail_at_frame(m, 11, "simulated crash")
        with pytest.raises(RuntimeError, match="simulated"):
            main(["--debug", "run", str(seq_dir), "--out", str(out), *FRONTEND])
    assert (out / "checkpoint.pt").is_file() and not (out / "metrics.json").exists()
    return out


def _one_error_line(code: int, err: str, *names: str) -> None:
    lines = [ln for ln in err.strip().splitlines() if ln.startswith("error:")]
    assert code == 2 and len(lines) == 1 and "Traceback" not in err, err
    for name in names:
        assert name in lines[0], lines[0]


def test_resume_after_a_crash_gives_the_uninterrupted_run(seq_dir, crashed_run, tmp_path, capfd):
    code, err = _cli(["run", seq_dir, "--out", crashed_run, *FRONTEND, "--resume"], capfd)
    assert code == 0, err
    code, err = _cli(["run", seq_dir, "--out", tmp_path / "straight", *FRONTEND], capfd)
    assert code == 0, err
    for name in ("trajectory.txt", "keyframes.txt", "trajectory_seed.txt"):
        (_, resumed), (_, straight) = read_tum(crashed_run / name), read_tum(tmp_path / "straight" / name)
        assert np.array_equal(resumed, straight), name
    log = (crashed_run / "run.log").read_text()
    assert "simulated crash" in log or "run stopped" in log      # one log: the crash, then the resume
    assert log.index("run stopped") < log.index("resumed from the checkpoint")
    assert not (crashed_run / "checkpoint.pt").exists()          # a finished run removes it
    import json

    assert json.loads((crashed_run / "metrics.json").read_text())["resumed_at_frames"]
    code, err = _cli(["run", seq_dir, "--out", crashed_run, *FRONTEND, "--resume"], capfd)
    _one_error_line(code, err, "finished")


def test_resume_with_another_config_names_the_key(seq_dir, crashed_run, capfd):
    code, err = _cli(["run", seq_dir, "--out", crashed_run, *FRONTEND, "--set", "keyframes.every_n=3", "--resume"],
                     capfd)
    _one_error_line(code, err, "checkpoint.pt", "keyframes.every_n")
    other_seed = [("9" if a == "2" else a) for a in FRONTEND]
    code, err = _cli(["run", seq_dir, "--out", crashed_run, *other_seed, "--resume"], capfd)
    _one_error_line(code, err, "checkpoint.pt", "seed (run: 2, now: 9)")
    assert (crashed_run / "checkpoint.pt").is_file()             # refused resumes change nothing


def test_resume_of_another_sequence_is_refused(seq_dir, crashed_run, tmp_path):
    from lrslam.pipeline.checkpoint import check_resumable, load_checkpoint

    state = load_checkpoint(crashed_run / "checkpoint.pt")
    ts = np.asarray(state["timestamps"])
    check_resumable(crashed_run / "checkpoint.pt", state, state["config"], ts)
    with pytest.raises(InputError, match="sequence differs"):
        check_resumable(crashed_run / "checkpoint.pt", state, state["config"], ts + 1.0)


@pytest.mark.parametrize("damage", ["truncated", "garbage", "empty", "version"])
def test_a_corrupt_checkpoint_is_one_line_exit_2(seq_dir, crashed_run, capfd, damage):
    path = crashed_run / "checkpoint.pt"
    data = path.read_bytes()
    if damage == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif damage == "garbage":
        path.write_bytes(b"not a checkpoint\n" * 10)
    elif damage == "empty":
        path.write_bytes(b"")
    else:
        import torch

        raw = torch.load(path, weights_only=True)
        torch.save({**raw, "version": 99}, path)
    code, err = _cli(["run", seq_dir, "--out", crashed_run, *FRONTEND, "--resume"], capfd)
    _one_error_line(code, err, str(path), "version" if damage == "version" else "checkpoint")


def test_resume_without_a_checkpoint_is_one_line_exit_2(seq_dir, tmp_path, capfd):
    code, err = _cli(["run", seq_dir, "--out", tmp_path / "never", *FRONTEND, "--resume"], capfd)
    _one_error_line(code, err, "no checkpoint")
    code, err = _cli(["run", seq_dir, "--out", tmp_path / "never", *FRONTEND, "--resume", "--overwrite"], capfd)
    _one_error_line(code, err, "--overwrite")


# ------------------------------------------------------------------------------------------ SIGKILL + resume
@pytest.mark.slow
def test_sigkilled_run_resumed_gives_the_uninterrupted_trajectory_bit_for_bit(seq_dir, tmp_path):
    """A fused run (field + frontend + graph) killed with SIGKILL right after its first checkpoint, resumed with
    ``--resume``, ends with exactly the trajectory of an uninterrupted run of the same seed. Bit-identical needs
    ``--deterministic`` (Open3D on one thread, see the module docstring); everything else repeats as it is."""
    args = [sys.executable, "-m", "lrslam", "run", str(seq_dir), "--config", "synthetic", "--seed", "5",
            "--deterministic", "--checkpoint-every", "2", "-q", *[x for o in TINY for x in ("--set", o)]]
    out = tmp_path / "killed"
    proc = subprocess.Popen([*args, "--out", str(out)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    t0 = time.time()
    while not (out / "checkpoint.pt").exists():
        assert proc.poll() is None, proc.communicate()
        assert time.time() - t0 < 120, "no checkpoint appeared"
        time.sleep(0.02)
    proc.kill()
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    assert not (out / "metrics.json").exists(), "the run finished before the kill"
    killed_after = (out / "run.log").read_text().count(" done: ")
    for extra in (["--out", str(out), "--resume"], ["--out", str(tmp_path / "straight")]):
        r = subprocess.run([*args, *extra], check=False, capture_output=True, text=True, timeout=300)
        assert r.returncode == 0, r.stderr
    for name in ("trajectory.txt", "keyframes.txt", "trajectory_frontend.txt"):
        (t_r, resumed), (t_s, straight) = read_tum(out / name), read_tum(tmp_path / "straight" / name)
        assert np.array_equal(t_r, t_s) and np.array_equal(resumed, straight), name
    assert killed_after < 15 and len(read_tum(out / "trajectory.txt")[0]) == 16
