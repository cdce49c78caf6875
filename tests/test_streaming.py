"""The streaming API (:class:`lrslam.Slam`): frames fed one at a time give the run ``lrslam run`` gives (one code
path), checkpoints continue it exactly, and bad frames are one-line errors."""

from __future__ import annotations

import copy

import numpy as np
import pytest

from lrslam.errors import InputError
from lrslam.pipeline.config import build_config
from lrslam.trajectory_io import read_tum, write_tum
from run_fixtures import TINY as _TINY, synthetic_room

TINY = _TINY + ["output.mesh=false", "output.plots=false"]


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    return synthetic_room(tmp_path_factory.mktemp("stream") / "room", n_frames=12, seed=3)


def _slam(cfg, seq, first):
    from lrslam import Slam

    T0 = first.T_w_c_gt if cfg.initial_pose == "gt" else np.eye(4)
    return Slam(cfg, first.K, (first.width, first.height), bound=seq.bound, T_w_c0=T0)


@pytest.mark.parametrize("mode", ["fused", "field"])
def test_frame_by_frame_equals_lrslam_run_bit_for_bit(seq_dir, tmp_path, mode):
    from lrslam.cli import main
    from lrslam.datasets import open_sequence

    with pytest.raises(SystemExit) as e:
        main(["run", str(seq_dir), "--out", str(tmp_path / "run"), "--config", "synthetic", "--mode", mode,
              "--seed", "4", "--deterministic", *sum((["--set", o] for o in TINY), [])])
    assert e.value.code == 0
    ts_run, poses_run = read_tum(tmp_path / "run" / "trajectory.txt")

    cfg = build_config("synthetic", mode=mode, overrides=TINY + ["seed=4", "deterministic=true"])
    seq = open_sequence(seq_dir)
    first = seq[0]
    slam = _slam(cfg, seq, first)
    results = [slam.track(f.rgb, f.depth, f.timestamp) for f in (seq[i] for i in range(len(seq)))]
    out = slam.finish()
    assert [r.index for r in results] == list(range(len(seq)))
    assert results[0].keyframe and all(r.status == "ok" for r in results)
    np.testing.assert_array_equal(out.timestamps, ts_run)
    # the streamed poses, written as the run writes them (repr of every float), give the same file line for line
    write_tum(tmp_path / "stream.txt", out.timestamps, out.poses)
    lines = lambda p: [x for x in p.read_text().splitlines() if not x.startswith("#")]  # noqa: E731
    assert lines(tmp_path / "stream.txt") == lines(tmp_path / "run" / "trajectory.txt")
    # the run's trajectory is the tracked one smoothed at the end (lrslam.backend.smoother)
    tracked = out.unsmoothed_poses if out.unsmoothed_poses is not None else out.poses
    assert len(poses_run) == len(seq) and np.array_equal(tracked[-1], slam.poses()[-1])
    # a different seed is a different run in field mode (the test can tell runs apart; fused mode takes the
    # odometry alone over its first keyframe gaps, FusionConfig.warmup_keyframes)
    if mode != "field":
        return
    other = build_config("synthetic", mode=mode, overrides=TINY + ["seed=5", "deterministic=true"])
    s2 = _slam(other, seq, first)
    for i in range(4):
        s2.track(seq[i].rgb, seq[i].depth, seq[i].timestamp)
    assert not np.array_equal(s2.poses()[3], tracked[3])


def test_a_checkpoint_continues_the_stream_exactly(seq_dir):
    from lrslam.datasets import open_sequence
    from lrslam.pipeline.determinism import global_rng_state, set_global_rng_state

    cfg = build_config("synthetic", mode="fused", overrides=TINY + ["seed=1", "deterministic=true"])
    seq = open_sequence(seq_dir)
    frames = [seq[i] for i in range(len(seq))]
    a = _slam(cfg, seq, frames[0])
    for f in frames[:6]:
        a.track(f.rgb, f.depth, f.timestamp)
    state, rng = copy.deepcopy(a.checkpoint()), copy.deepcopy(global_rng_state())   # a snapshot, as a file is
    for f in frames[6:]:
        a.track(f.rgb, f.depth, f.timestamp)
    b = _slam(cfg, seq, frames[0])
    b.restore(state)
    set_global_rng_state(rng)
    assert b.n_frames == 6
    for f in frames[6:]:
        b.track(f.rgb, f.depth, f.timestamp)
    assert np.array_equal(a.finish().poses, b.finish().poses)


def test_bad_frames_are_one_line_errors(seq_dir):
    from lrslam import Slam
    from lrslam.datasets import open_sequence

    cfg = build_config("synthetic", mode="frontend")
    first = open_sequence(seq_dir)[0]
    slam = Slam(cfg, first.K, (first.width, first.height))
    with pytest.raises(InputError, match=r"rgb must be \(120, 160, 3\) uint8"):
        slam.track(first.rgb[:, :-1], first.depth, 0.0)
    with pytest.raises(InputError, match="depth must be"):
        slam.track(first.rgb, first.depth[:-1], 0.0)
    with pytest.raises(InputError, match="first frame has no valid depth"):
        slam.track(first.rgb, np.zeros_like(first.depth), 0.0)
    with pytest.raises(InputError, match="no frame"):
        slam.finish()
    with pytest.raises(InputError, match="K must be"):
        Slam(cfg, np.eye(2), (160, 120))
    # NaN / negative depth counts as no measurement, never as a distance
    depth = first.depth.copy()
    depth[:10] = np.nan
    depth[10:20] = -1.0
    res = slam.track(first.rgb, depth, 0.0)
    assert res.keyframe and np.all(np.isfinite(res.T_w_c))


def test_without_a_bound_the_first_frame_gives_one(seq_dir):
    from lrslam import Slam
    from lrslam.datasets import open_sequence

    cfg = build_config("synthetic", mode="field", overrides=TINY)
    assert cfg.bound is None
    first = open_sequence(seq_dir)[0]
    slam = Slam(cfg, first.K, (first.width, first.height))
    slam.track(first.rgb, first.depth, first.timestamp)
    b = slam.bound
    assert b.shape == (3, 2) and np.all(b[:, 0] < 0) and np.all(b[:, 1] > 0)   # the camera at the origin inside
