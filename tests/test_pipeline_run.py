"""End-to-end runs of the pipeline on a tiny synthetic sequence: every mode writes a complete run folder."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lrslam.pipeline.config import build_config
from lrslam.trajectory_io import read_tum

from run_fixtures import TINY as _TINY, fail_at_frame, synthetic_room

TINY = _TINY + ["field.mesh.resolution=0.1", "output.eval_mesh_points=5000"]


@pytest.fixture(scope="module")
def tiny_sequence(tmp_path_factory):
    return synthetic_room(tmp_path_factory.mktemp("seq") / "room", n_frames=12, seed=1)


@pytest.mark.parametrize("mode", ["field", "frontend", "fused"])
def test_every_mode_writes_a_run_folder(tiny_sequence, tmp_path, mode):
    from lrslam.pipeline.run import run_sequence

    cfg = build_config("synthetic", overrides=TINY, mode=mode)
    res = run_sequence(tiny_sequence, cfg, tmp_path / mode, progress=False)
    out = tmp_path / mode
    for name in ("config.yaml", "trajectory.txt", "keyframes.txt", "metrics.json", "mesh.ply", "trajectory.png",
                 "run.log"):
        assert (out / name).is_file(), name
    ts, poses = read_tum(out / "trajectory.txt")
    assert len(ts) == 12 and np.all(np.isfinite(poses))
    m = json.loads((out / "metrics.json").read_text())
    assert m["mode"] == mode and m["n_frames"] == 12 and np.isfinite(m["ate_rmse_cm"]) and m["fpt_s"] > 0
    assert res.metrics["ate_rmse_cm"] == m["ate_rmse_cm"]
    # one evaluation, one number: the plot's legend shows the metrics' ATE of each curve
    from lrslam.pipeline.plots import ate_label, read_ate_labels

    labels = read_ate_labels(out / "trajectory.png")
    assert labels[mode] == ate_label(mode, m["ate_rmse_cm"])
    assert labels["seed"] == ate_label("seed", m["seed_ate_rmse_cm"])
    if mode != "frontend":
        assert m["parameters"]["total"] > 0
    # every mode's mesh is a real surface (regression: the frontend TSDF mesh used to be empty) and evaluated
    import trimesh

    assert len(trimesh.load(out / "mesh.ply", force="mesh").faces) > 100
    assert "mesh_accuracy_cm" in m and np.isfinite(m["mesh_accuracy_cm"])


@pytest.mark.parametrize("args", [["run", "{tmp}/missing"], ["run", "{tmp}"], ["eval", "ate", "{tmp}/a", "{tmp}/b"],
                                  ["run", "--demo", "--config", "nope"]])
def test_cli_bad_input_is_one_line_error(tmp_path, args):
    import subprocess
    import sys

    args = [a.format(tmp=tmp_path) for a in args]
    r = subprocess.run([sys.executable, "-m", "lrslam", *args, "--out", str(tmp_path / "o")] if args[0] == "run"
                       else [sys.executable, "-m", "lrslam", *args], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().startswith("error:") and len(r.stderr.strip().splitlines()) == 1, r.stderr


def test_unknown_config_key_is_rejected():
    from lrslam.errors import InputError

    with pytest.raises(InputError, match="schedule"):
        build_config("synthetic", overrides=["schedule.map_evry=2"])
    with pytest.raises(InputError, match="unknown dataset preset"):
        build_config("no-such-preset")


def test_a_crash_mid_run_keeps_the_poses_tracked_so_far(tiny_sequence, tmp_path, monkeypatch):
    from lrslam.pipeline.run import run_sequence

    fail_at_frame(monkeypatch, 5, "simulated failure")
    cfg = build_config("synthetic", overrides=TINY, mode="frontend")
    with pytest.raises(RuntimeError, match="simulated"):
        run_sequence(tiny_sequence, cfg, tmp_path / "crash", progress=False)
    ts, poses = read_tum(tmp_path / "crash" / "trajectory_partial.txt")
    assert len(ts) == 5 and np.all(np.isfinite(poses))
    assert (tmp_path / "crash" / "config.yaml").is_file()
    assert "run stopped after 5 frames" in (tmp_path / "crash" / "run.log").read_text()


def test_console_shows_warnings_but_not_the_run_log_info(capsys):
    import logging

    from lrslam.logs import setup_console_logging

    h = setup_console_logging()
    try:
        log = logging.getLogger("lrslam.test_console")
        log.setLevel(logging.INFO)
        log.info("info-line")
        log.warning("warning-line")
        err = capsys.readouterr().err
    finally:
        logging.getLogger().removeHandler(h)
    assert "warning-line" in err and "info-line" not in err


def test_online_trajectory_is_the_run_without_the_final_refinement(tiny_sequence, tmp_path):
    """A fused run whose final refinement runs (forced: ``final_refine_when=always``) keeps the trajectory as
    tracked in ``trajectory_online.txt`` and its ATE as ``online_ate_rmse_cm``: the very poses of the same run
    with the final refinement off (deterministic), which writes no such file."""
    from lrslam.pipeline.run import run_sequence

    base = TINY + ["deterministic=true", "fusion.warmup_keyframes=1", "output.mesh=false", "smoothing.enabled=false"]
    on = build_config("synthetic", overrides=base + ["backend.final_refine_when=always"], mode="fused")
    off = build_config("synthetic", overrides=base + ["backend.final_refine=false"], mode="fused")
    run_sequence(tiny_sequence, on, tmp_path / "on", progress=False)
    run_sequence(tiny_sequence, off, tmp_path / "off", progress=False)
    m_on = json.loads((tmp_path / "on" / "metrics.json").read_text())
    m_off = json.loads((tmp_path / "off" / "metrics.json").read_text())
    assert m_on["final_refine_max_shift_m"] is not None and m_off["final_refine_max_shift_m"] is None
    _, online = read_tum(tmp_path / "on" / "trajectory_online.txt")
    _, tracked = read_tum(tmp_path / "off" / "trajectory.txt")
    assert np.allclose(online, tracked, atol=1e-6)
    _, refined = read_tum(tmp_path / "on" / "trajectory.txt")
    assert not np.allclose(refined, tracked, atol=1e-6)   # the refinement did move keyframes
    assert m_on["online_ate_rmse_cm"] == pytest.approx(m_off["ate_rmse_cm"], abs=1e-4)
    assert not (tmp_path / "off" / "trajectory_online.txt").exists() and "online_ate_rmse_cm" not in m_off


def test_the_trajectory_is_smoothed_last_and_the_poses_as_tracked_are_kept(tiny_sequence, tmp_path):
    """A run returns its trajectory smoothed under the motion prior (lrslam.backend.smoother) and keeps the poses
    before it in ``trajectory_unsmoothed.txt`` with their ATE: exactly the trajectory of the same run with the
    smoothing off (deterministic), which writes no such file."""
    from lrslam.backend.smoother import smooth_trajectory
    from lrslam.pipeline.run import run_sequence

    base = TINY + ["deterministic=true", "output.mesh=false", "smoothing.min_frames=8"]   # 12 frames here
    cfg = build_config("synthetic", overrides=base, mode="fused")
    run_sequence(tiny_sequence, cfg, tmp_path / "on", progress=False)
    run_sequence(tiny_sequence, build_config("synthetic", overrides=base + ["smoothing.enabled=false"], mode="fused"),
                 tmp_path / "off", progress=False)
    ts, raw = read_tum(tmp_path / "on" / "trajectory_unsmoothed.txt")
    _, tracked = read_tum(tmp_path / "off" / "trajectory.txt")
    _, smoothed = read_tum(tmp_path / "on" / "trajectory.txt")
    assert np.allclose(raw, tracked, atol=1e-6)
    assert np.allclose(smoothed, smooth_trajectory(raw, ts, cfg.smoothing).poses, atol=1e-5)
    m_on = json.loads((tmp_path / "on" / "metrics.json").read_text())
    m_off = json.loads((tmp_path / "off" / "metrics.json").read_text())
    assert m_on["smoothing"]["applied"] and m_on["smoothing"]["max_shift_cm"] > 0
    assert not np.allclose(smoothed, raw, atol=1e-6)
    # the keyframes file holds the same (smoothed) poses at the keyframes' rows
    kts, kposes = read_tum(tmp_path / "on" / "keyframes.txt")
    rows = [int(np.flatnonzero(ts == k)[0]) for k in kts]
    assert len(rows) >= 2 and np.array_equal(kposes, smoothed[rows])
    assert m_on["unsmoothed_ate_rmse_cm"] == pytest.approx(m_off["ate_rmse_cm"], abs=1e-4)
    assert not (tmp_path / "off" / "trajectory_unsmoothed.txt").exists() and "smoothing" not in m_off


def test_the_frontend_with_its_own_graph_closes_loops(tmp_path):
    """``--mode frontend`` with ``parts.backend=graph`` and the factors of the frontend alone (its keyframe
    registrations and loops; no field is built): the classical pipeline ``benchmarks/modes.py`` compares fused
    with. On a synthetic loop it keeps loops, solves the graph and ends below the frontend alone."""
    from lrslam.pipeline.run import run_sequence

    seq = synthetic_room(tmp_path / "room", n_frames=60, seed=0)
    base = ["deterministic=true", "output.mesh=false", "output.plots=false"]
    run_sequence(seq, build_config("synthetic", overrides=base, mode="frontend"), tmp_path / "fe", progress=False)
    run_sequence(seq, build_config("synthetic", overrides=base + ["parts.backend=graph",
                                                                  'backend.factors=["odometry", "loop"]'],
                                   mode="frontend"), tmp_path / "fg", progress=False)
    m_alone = json.loads((tmp_path / "fe" / "metrics.json").read_text())
    m = json.loads((tmp_path / "fg" / "metrics.json").read_text())
    assert m["loops"]["kept"] > 0 and m["n_graph_solves"] > 0 and m_alone["n_loop_closures"] == 0
    assert m["ate_rmse_cm"] < m_alone["ate_rmse_cm"], (m["ate_rmse_cm"], m_alone["ate_rmse_cm"])
