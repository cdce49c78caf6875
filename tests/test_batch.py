"""``lrslam batch``: the job grid, path checks before any job, skip-complete re-runs, failed jobs, the in-process
fallback without Ray, and (slow) a real batch on local Ray with 2 workers of 1 CPU."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from lrslam.errors import InputError
from lrslam.tools.batch import run_grid
from lrslam.tools.batch_exec import SequentialExecutor, make_executor, ray_available
from lrslam.tools.batch_grid import check_jobs, expand_grid, job_status, parse_sequence

from batch_fixtures import TINY, Recording


# ------------------------------------------------------------------------------------------ grid (no runs)
def test_grid_expansion_and_unique_names(tmp_path):
    for p in ("x/room", "y/room"):
        (tmp_path / p).mkdir(parents=True)
    seqs = [str(tmp_path / "x/room"), str(tmp_path / "y/room"), f"{tmp_path / 'x/room'}:tum"]
    jobs = expand_grid(seqs, ["field", "frontend", "fused"], seeds=3, representations=["lrslam", "eslam"],
                       preset="synthetic")
    # per sequence: field and fused 2 representations x 3 seeds each, frontend once
    assert len(jobs) == 3 * (2 * 2 * 3 + 1)
    names = [j.name for j in jobs]
    assert len(set(names)) == len(names) and len({j.run_dir for j in jobs}) == len(jobs)
    assert {j.sequence_name for j in jobs} == {"x-room-synthetic", "y-room", "x-room-tum"}  # twins: + preset
    assert "x-room-tum/fused-eslam/s2" in names and "y-room/frontend/s0" in names
    fused = [j for j in jobs if j.sequence_name == "y-room" and j.mode == "fused"]
    assert sorted({j.config["field"]["seed"] for j in fused}) == [0, 1, 2]
    kinds = {j.representation: j.config["field"]["model"]["geometry"]["kind"] for j in fused}
    assert kinds["eslam"] == "triplane" and kinds["lrslam"] != "triplane"
    # each sequence runs with its own preset: x/room:tum has the TUM reader, the others the synthetic one
    readers = {j.sequence_name: j.config["dataset"]["reader"] for j in jobs}
    assert readers == {"x-room-synthetic": "synthetic", "y-room": "synthetic", "x-room-tum": "tum"}
    assert {j.presets["config"] for j in jobs if j.sequence_name == "x-room-tum"} == {"tum"}


def test_sequence_argument_parsing(tmp_path):
    assert parse_sequence("data/seq:tum") == parse_sequence("data/seq:tum", "replica")
    assert parse_sequence("data/seq:tum").preset == "tum" and parse_sequence("data/seq:tum").path == "data/seq"
    odd = tmp_path / "a:b"       # an existing path is never split at its colon
    odd.mkdir()
    assert parse_sequence(str(odd), "synthetic").path == str(odd)
    assert parse_sequence(str(odd), "synthetic").preset == "synthetic"
    with pytest.raises(InputError, match="given twice"):
        expand_grid([str(odd), str(odd)], ["frontend"])
    with pytest.raises(InputError, match="banana"):
        expand_grid([str(odd)], ["field", "banana"])
    with pytest.raises(InputError, match="nope"):
        expand_grid([f"{tmp_path}/x:nope"], ["field"])


def test_every_path_is_checked_before_the_first_job(tmp_path):
    from lrslam.datasets.synth.writer import generate

    ok = generate(tmp_path / "ok", n_frames=3, width=32, height=24, show_progress=False)
    jobs = expand_grid([str(ok), str(tmp_path / "missing_seq")], ["frontend"], preset="synthetic")
    ex = Recording()
    with pytest.raises(InputError, match="missing_seq"):
        run_grid(jobs, tmp_path / "out", ex, progress=False)
    assert ex.ran == [] and not (tmp_path / "out").exists()
    # a job's run folder that holds someone else's files
    jobs = expand_grid([str(ok)], ["frontend"], preset="synthetic")
    (tmp_path / "out2" / jobs[0].run_dir).mkdir(parents=True)
    (tmp_path / "out2" / jobs[0].run_dir / "notes.txt").write_text("mine\n")
    with pytest.raises(InputError, match="not an lrslam run folder"):
        check_jobs(jobs, tmp_path / "out2")
    (tmp_path / "afile").write_text("x")
    with pytest.raises(InputError, match="afile"):
        check_jobs(jobs, tmp_path / "afile")


def test_without_ray_the_batch_runs_in_process_with_a_note(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)     # `import ray` raises ImportError
    assert not ray_available()
    notes: list[str] = []
    ex = make_executor(None, cpus_per_job=1, note=notes.append)
    assert isinstance(ex, SequentialExecutor) and len(notes) == 1 and "Ray is not installed" in notes[0]
    with pytest.raises(InputError, match="Ray is not installed"):
        make_executor(True)
    with pytest.raises(InputError, match="Ray is not installed"):
        make_executor(None, address="auto")
    assert isinstance(make_executor(False), SequentialExecutor)


# ------------------------------------------------------------------------------------------ a real batch
def test_batch_writes_one_run_folder_per_job(tiny_batch):
    out, outcome = tiny_batch["out"], tiny_batch["outcome"]
    ok = [e for e in outcome.entries if e["status"] == "ok"]
    assert len(outcome.entries) == 9 and len(ok) == 6
    for e in ok:
        d = out / e["run_dir"]
        assert (d / "trajectory.txt").is_file() and (d / "metrics.json").is_file() and (d / "config.yaml").is_file()
        assert e["worker"]["torch_threads"] == 1
    assert {e["sequence_name"] for e in ok} == {"a-room", "b-room"}
    manifest = json.loads((out / "batch.json").read_text())
    assert [j["name"] for j in manifest["jobs"]] == [j.name for j in tiny_batch["jobs"]]
    # the field seed reached the runs (and the two seeds gave different trajectories)
    t0 = (out / "a-room/field/s0/trajectory.txt").read_text()
    t1 = (out / "a-room/field/s1/trajectory.txt").read_text()
    assert t0 != t1


def test_a_failed_job_is_reported_with_its_error(tiny_batch):
    failed = tiny_batch["outcome"].failed()
    assert sorted(e["name"] for e in failed) == ["bad-room/field/s0", "bad-room/field/s1", "bad-room/frontend/s0"]
    assert all("depth" in e["error"] and ".png" in e["error"] for e in failed), failed
    md = (tiny_batch["out"] / "comparison.md").read_text()
    assert "Failed jobs:" in md and "bad-room/field/s1" in md
    assert "| bad-room | field | 0/2 (2 failed) |" in md
    page = (tiny_batch["out"] / "report.html").read_text()
    assert "failed jobs" in page and "bad-room/frontend/s0" in page


def test_rerun_skips_complete_jobs_and_reruns_changed_or_failed(tiny_batch, tmp_path):
    out = tmp_path / "out"
    shutil.copytree(tiny_batch["out"], out)
    ex = Recording()
    outcome = run_grid(tiny_batch["jobs"], out, ex, progress=False, report=False)
    assert sorted(ex.ran) == ["bad-room/field/s0", "bad-room/field/s1", "bad-room/frontend/s0"]
    assert sum(bool(e.get("skipped")) for e in outcome.entries) == 6
    assert len(outcome.failed()) == 3
    # another setting: the complete run no longer counts as this job's
    from dataclasses import replace

    same = next(j for j in tiny_batch["jobs"] if j.name == "a-room/frontend/s0")
    other = expand_grid([str(tiny_batch["seqs"]["a"])], ["frontend"], preset="synthetic", overrides=TINY + [
        "odometry.reference_max_translation=0.25"])[0]
    changed = replace(same, config=other.config)
    assert job_status(same, out) == "complete" and job_status(changed, out) == "changed"
    (out / same.run_dir / "metrics.json").unlink()       # an interrupted run is not complete either
    assert job_status(same, out) == "todo"


def test_cli_batch_failed_job_exits_1_and_names_it(tiny_batch, tmp_path, capfd):
    from lrslam.cli import main

    out = tmp_path / "cli"
    args = ["batch", str(tiny_batch["seqs"]["a"]), f"{tiny_batch['seqs']['bad']}:synthetic", "--modes", "frontend",
            "--out", str(out), "--sequential", "-q"] + [x for kv in TINY for x in ("--set", kv)]
    with pytest.raises(SystemExit) as e:
        main(args)
    _, err = capfd.readouterr()
    assert e.value.code == 1 and "error: job bad-room/frontend/s0 failed" in err, err
    assert (out / "report.html").is_file() and (out / "comparison.csv").is_file()


@pytest.mark.slow
@pytest.mark.skipif(not ray_available(), reason="Ray is not installed (pip install 'lrslam[distributed]')")
def test_batch_on_local_ray_with_two_workers(tiny_batch, tmp_path):
    out = tmp_path / "ray"
    env = {**os.environ, "OMP_NUM_THREADS": "2", "NUMBA_NUM_THREADS": "2"}   # the job must not inherit these
    args = [sys.executable, "-m", "lrslam", "batch", str(tiny_batch["seqs"]["a"]), "--preset", "synthetic", "--modes",
            "field,frontend", "--seeds", "2", "--workers", "2", "--cpus-per-job", "1", "--out", str(out), "-q"]
    r = subprocess.run(args + [x for kv in TINY for x in ("--set", kv)], capture_output=True, text=True,
                       timeout=300, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    manifest = json.loads((out / "batch.json").read_text())
    assert manifest["executor"].startswith("local Ray: 2 job(s) at a time, 1 CPU")
    jobs = manifest["jobs"]
    assert len(jobs) == 3 and all(j["status"] == "ok" for j in jobs)
    for j in jobs:
        assert j["worker"]["torch_threads"] == 1 and j["worker"]["OMP_NUM_THREADS"] == "1", j["worker"]
        assert (out / j["run_dir"] / "trajectory.txt").is_file()
    # the same seed gives the same field trajectory on Ray as in-process
    from lrslam.trajectory_io import read_tum

    _, ray_poses = read_tum(out / "room/field/s0/trajectory.txt")
    _, local_poses = read_tum(tiny_batch["out"] / "a-room/field/s0/trajectory.txt")
    assert np.abs(ray_poses - local_poses).max() < 1e-6
