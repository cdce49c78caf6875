"""The scene bound comes from the data unless a scene preset or the user gives one: a recording in TUM layout from an
unknown camera, in a room that lies far from any preset's bound, runs ok with the default command; the odometry
pre-pass covers the camera path of every synthetic trajectory; presets carry a bound only when named for a scene."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
import yaml

from lrslam.pipeline.config import build_config, list_presets
from lrslam.trajectory_io import read_tum, write_tum

from run_fixtures import TINY

OFFSET = np.array([7.0, -6.0, 2.0])   # metres: the recording's world frame is far from the old tum-cpu bound
OLD_TUM_CPU_BOUND = [[-3.5, 3.0], [-4.0, 3.0], [-1.0, 3.0]]   # tum-cpu's fixed bound before it came from the data


@pytest.fixture(scope="module")
def user_recording(tmp_path_factory):
    """A generated cluttered room (5 x 4 x 2.7 m) in TUM layout with an intrinsics.yaml (no scene.yaml: nothing
    says where the scene is), its ground truth in a world frame offset by ``OFFSET``."""
    from lrslam.datasets.synth.writer import generate

    root = tmp_path_factory.mktemp("bound")
    src = generate(root / "src", scene="cluttered", trajectory="loop", n_frames=14, seed=2, width=160, height=120,
                   show_progress=False)
    dst = root / "my_camera"
    shutil.copytree(src, dst, ignore=shutil.ignore_patterns("scene.yaml", "gt_mesh.ply"))
    intr = yaml.safe_load((src / "scene.yaml").read_text())["intrinsics"]
    (dst / "intrinsics.yaml").write_text(yaml.safe_dump({k: intr[k] for k in ("fx", "fy", "cx", "cy")}))
    ts, poses = read_tum(src / "groundtruth.txt")
    poses[:, :3, 3] += OFFSET
    write_tum(dst / "groundtruth.txt", ts, poses)
    return dst


def _run(args: list[str], capsys) -> tuple[int, str]:
    from lrslam.cli import main

    with pytest.raises(SystemExit) as e:
        main(args)
    return e.value.code, capsys.readouterr().out


def test_the_default_command_takes_the_bound_from_the_data(user_recording, tmp_path, capsys):
    out = tmp_path / "run"
    fast = sum((["--set", o] for o in TINY + ["output.mesh=false", "output.plots=false"]), [])
    code, printed = _run(["run", str(user_recording), "--out", str(out), "-q", *fast], capsys)
    m = json.loads((out / "metrics.json").read_text())
    assert code == 0 and m["status"] == "ok", m.get("degraded_reasons")
    assert m["preset"] == "tum-cpu" and m["bound_source"] == "auto (pre-pass)" and m["bound_s"] > 0
    assert m["frames_outside_bound"] == 0
    assert m["mode_settings"] == build_config("tum-cpu", mode="fused", overrides=TINY).mode_settings()
    # the first lines say which preset, how hard the mode works and where the bound came from
    lines = printed.splitlines()
    assert lines[0].startswith("preset tum-cpu (no --config")
    assert lines[1] == f"config: tum-cpu; {m['mode_settings']}"
    assert lines[2].startswith("scene bound: auto (pre-pass), ")
    # the bound lies around the offset room, not around the origin
    b = np.asarray(m["bound"])
    assert np.all(b[:, 0] < OFFSET) and np.all(OFFSET < b[:, 1])
    # the fused run's frontend replays the pre-pass's registrations instead of registering every frame again
    log = (out / "run.log").read_text()
    assert f"replaying a recorded {m['n_frames']}-frame pass" in log and "not the recorded pass's next" not in log


def test_the_old_fixed_bound_fails_the_same_recording(user_recording, tmp_path, capsys):
    """What the default did before: tum-cpu's fixed bound, measured for TUM fr1/rpy (the check above can fail)."""
    out = tmp_path / "run"
    fast = sum((["--set", o] for o in TINY + ["output.mesh=false", "output.plots=false"]), [])
    code, _ = _run(["run", str(user_recording), "--out", str(out), "-q", *fast, "--set",
                    f"bound={OLD_TUM_CPU_BOUND}"], capsys)
    m = json.loads((out / "metrics.json").read_text())
    assert code == 3 and m["status"] == "degraded" and m["bound_source"] == "given"
    assert m["frames_outside_bound"] == m["n_frames"] - 1   # every frame after the first (checked from frame 1)


@pytest.mark.parametrize("trajectory", ["loop", "circle", "helix", "random_walk"])
def test_the_prepass_bound_holds_every_camera_centre_with_a_margin(trajectory, tmp_path):
    from lrslam.datasets import open_sequence
    from lrslam.datasets.synth.writer import generate
    from lrslam.pipeline.auto_bound import bound_from_prepass

    seq = open_sequence(generate(tmp_path / trajectory, scene="room", trajectory=trajectory, n_frames=20, seed=1,
                                 width=160, height=120, show_progress=False))
    gt = seq.gt_poses()
    b, _ = bound_from_prepass(seq, build_config("synthetic").odometry, gt[0])
    centres = gt[:, :3, 3]
    margin = build_config("synthetic").auto_bound_margin / 2
    assert np.all(centres - margin > b[:, 0]) and np.all(centres + margin < b[:, 1]), (b.tolist(), trajectory)


def test_only_scene_presets_carry_a_bound():
    """A dataset preset (tum-cpu, replica, ...) fits any sequence of its layout: its bound comes from the data.
    A fixed bound belongs to a preset named for its scene (``<base>-<scene>``, inheriting ``<base>``)."""
    d = Path(__file__).resolve().parents[1] / "configs" / "dataset"
    for name in list_presets("dataset"):
        raw = yaml.safe_load((d / f"{name}.yaml").read_text()) or {}
        if build_config(name).bound is None:
            continue
        assert "bound" in raw and raw.get("base") and name.startswith(f"{raw['base']}-"), name


def test_a_view_of_a_far_wall_stays_inside_the_prepass_bound():
    """A few frames look at a wall 3 m beyond the rest: their points (0.4 % of the sequence's) must not be cut off
    as stray depth (at 0.5 % tails they were, and the real excerpts each had 3 frames with 6-9 % of their depth
    outside the bound)."""
    from lrslam.pipeline.auto_bound import PREPASS_TAIL_PCT, _extent

    rng = np.random.default_rng(0)
    near = rng.uniform(-1.0, 1.0, size=(99_600, 3))
    wall = np.column_stack([rng.uniform(3.8, 4.0, 400), rng.uniform(-1.0, 1.0, (400, 2))])
    b = _extent(np.vstack([near, wall]), np.zeros((1, 3)), 0.3, PREPASS_TAIL_PCT)
    inside = np.all((wall >= b[:, 0]) & (wall <= b[:, 1]), axis=1)
    assert inside.mean() > 0.95, b.tolist()


@pytest.mark.parametrize("name,preset,stride", [("tum-fr1-rpy", "tum-cpu", 1),
                                               ("7scenes-redkitchen", "7scenes-cpu", 4)])
def test_the_prepass_bound_holds_every_view_of_the_real_excerpts(name, preset, stride):
    from lrslam.datasets import open_sequence
    from lrslam.pipeline.auto_bound import bound_from_prepass, fraction_outside

    path = Path(__file__).resolve().parents[2] / "shared" / "data" / name
    if not path.is_dir():
        pytest.skip(f"{path} absent")
    cfg = build_config(preset, overrides=[f"dataset.options.stride={stride}"])
    seq = open_sequence(path, options=cfg.reader_options())
    gt = seq.gt_poses()
    b, _ = bound_from_prepass(seq, cfg.odometry, gt[0])
    worst = max(fraction_outside(seq[i].depth, seq[i].K, gt[i], b) for i in range(0, len(seq), 2))
    assert worst < 0.05, (worst, b.tolist())
