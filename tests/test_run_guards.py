"""Units behind the bad-input guarantees: strict JSON, run folders, partial trajectories, the sanity status,
the pre-pass bound, feeding a run's config back, and NaN ground-truth samples."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from lrslam.errors import InputError


def test_json_safe_replaces_non_finite_values_and_says_why():
    from lrslam.jsonio import dumps, json_safe

    obj = {"acc": float("inf"), "n": np.float32("nan"), "ok": 1.5, "xs": [1.0, -math.inf], "arr": np.array([1, 2]),
           "nested": {"v": np.float64("-inf")}}
    safe = json_safe(obj)
    assert safe["acc"] is None and safe["acc_reason"] == "+infinite"
    assert safe["n"] is None and "NaN" in safe["n_reason"]
    assert safe["xs"] == [1.0, None] and safe["arr"] == [1, 2] and safe["nested"]["v_reason"] == "-infinite"
    assert safe["ok"] == 1.5 and obj["acc"] == math.inf          # the input is not changed
    text = dumps(obj)
    assert "Infinity" not in text and "NaN" not in text.replace("(NaN)", "")
    json.loads(text, parse_constant=lambda c: pytest.fail(f"non-standard constant {c}"))


def test_partial_trajectory_is_replaced_atomically_and_removed(tmp_path):
    from lrslam.pipeline.run_folder import PartialTrajectory
    from lrslam.trajectory_io import read_tum

    p = PartialTrajectory(tmp_path, np.arange(5) * 0.1, every=2)
    assert [p.due(n) for n in (1, 2, 3, 4)] == [False, True, False, True]
    poses = np.repeat(np.eye(4)[None], 3, axis=0)
    p.save(poses[:2])
    p.save(poses)
    ts, got = read_tum(p.path)
    assert len(ts) == 3 and np.allclose(got, poses)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["trajectory_partial.txt"]  # no temporary left
    p.remove()
    assert not any(tmp_path.iterdir())
    with pytest.raises(InputError, match="partial-every"):
        PartialTrajectory(tmp_path, np.arange(5), every=0)


def test_run_folder_checks_and_clears_only_its_own_outputs(tmp_path):
    from lrslam.pipeline.run_folder import prepare_run_folder

    (tmp_path / "afile").write_text("x")
    for out, msg in ((tmp_path / "afile", "is a file"), (tmp_path / "afile" / "sub", "afile is a file")):
        with pytest.raises(InputError, match=msg):
            prepare_run_folder(out)
    mine = tmp_path / "run"
    mine.mkdir()
    for name in ("trajectory.txt", "metrics.json", "trajectory_partial.txt", "trajectory_seed.txt", "mesh.ply"):
        (mine / name).write_text("old")
    (mine / "sequence").mkdir()                                    # the demo's sequence stays
    prepare_run_folder(mine)
    assert [p.name for p in mine.iterdir()] == ["sequence"]
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    (foreign / "metrics.json").write_text("{}")
    with pytest.raises(InputError, match="not an lrslam run folder.*--overwrite"):
        prepare_run_folder(foreign)
    prepare_run_folder(foreign, overwrite=True)
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"]
    (foreign / "config.yaml").write_text("mode: fused\nprovenance: {lrslam_version: 0.1.0}\n")
    prepare_run_folder(foreign)                                   # a run record marks an earlier run folder


def test_run_status():
    from lrslam.pipeline.sanity import run_status

    bound = np.array([[-1.0, 1.0]] * 3)
    poses = np.repeat(np.eye(4)[None], 4, axis=0)
    assert run_status({"refine_failures": 0, "ate_rmse_cm": 1.0}, poses, bound, True) == ("ok", [])
    status, why = run_status({"refine_failures": 3}, poses, bound, True)
    assert status == "degraded" and "every field refine failed" in why[0]
    assert run_status({"refine_failures": 3}, poses, bound, False) == ("ok", [])
    far = poses.copy()
    far[2, 0, 3] = 5.0
    assert "1 of 4 camera poses left the scene bound" in run_status({}, far, bound, True)[1][0]
    assert "non-finite metrics: mesh_accuracy_cm" in run_status({"mesh_accuracy_cm": math.inf}, poses, bound,
                                                                False)[1][0]


def test_prepass_bound_covers_every_view_of_a_walking_camera(tmp_path):
    from lrslam.datasets import open_sequence
    from lrslam.frontend.odometry import OdometryConfig
    from lrslam.datasets.synth.writer import generate
    from lrslam.pipeline.auto_bound import bound_from_frame, bound_from_prepass, fraction_outside

    seq = open_sequence(generate(tmp_path / "s", scene="room", trajectory="loop", n_frames=12, seed=1, width=160,
                                 height=120, show_progress=False))
    gt = seq.gt_poses()
    b, _ = bound_from_prepass(seq, OdometryConfig(), gt[0])
    frames = [seq[i] for i in range(len(seq))]
    worst = max(fraction_outside(f.depth, f.K, gt[i], b) for i, f in enumerate(frames))
    assert worst < 0.02
    assert np.all((gt[:, :3, 3] >= b[:, 0]) & (gt[:, :3, 3] <= b[:, 1]))
    # the first-frame bound (old default, with no margin) misses part of what later frames see
    b0 = bound_from_frame(frames[0].depth, frames[0].K, gt[0], margin=0.0)
    assert max(fraction_outside(f.depth, f.K, gt[i], b0) for i, f in enumerate(frames)) > worst


def test_run_config_yaml_is_accepted_back(tmp_path):
    from lrslam.config import save_yaml
    from lrslam.pipeline.config import build_config
    from lrslam.pipeline.config_source import load_run_config

    cfg = build_config("synthetic", overrides=["schedule.map_every=2"], mode="field")
    rec = {**cfg.resolved(), "sequence": "/data/x", "provenance": {"command": "lrslam run x"}}
    rec["bound"] = "auto"
    save_yaml(tmp_path / "config.yaml", rec)
    loaded = load_run_config(str(tmp_path / "config.yaml"))
    assert loaded.cfg.bound == "auto" and loaded.cfg.resolved() == {**cfg.resolved(), "bound": "auto"}
    again = load_run_config(str(tmp_path / "config.yaml"), overrides=["bound=[[0,1],[0,1],[0,1]]"])
    assert again.cfg.bound == [[0, 1], [0, 1], [0, 1]]
    assert load_run_config("synthetic", overrides=["bound=auto"]).cfg.bound == "auto"


def test_read_tum_can_keep_invalid_lines_as_missing_poses(tmp_path):
    from lrslam.datasets.association import interpolate_poses
    from lrslam.trajectory_io import TrajectoryFormatError, read_tum

    f = tmp_path / "gt.txt"
    f.write_text("0.00 0 0 0 0 0 0 1\n0.01 nan 0 0 0 0 0 1\n0.02 0 0 0 0 0 0 0\n0.03 1 0 0 0 0 0 1\n")
    with pytest.raises(TrajectoryFormatError, match="gt.txt:2"):
        read_tum(f)
    ts, poses = read_tum(f, invalid="nan")
    assert len(ts) == 4 and np.isnan(poses[1:3]).all() and np.isfinite(poses[[0, 3]]).all()
    out = interpolate_poses(np.array([0.0, 0.005, 0.015, 0.03]), ts, poses, max_difference=0.02)
    assert np.isfinite(out[0]).all() and np.isfinite(out[3]).all()
    assert np.isnan(out[1]).all() and np.isnan(out[2]).all()    # brackets a NaN sample: no ground truth
