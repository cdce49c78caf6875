"""The live viewer (``lrslam run --rrd``), its replay (``lrslam view``) and the Slam's observer hook: recordings
are read back with Rerun's own reader (``rerun.chunk.RrdReader``) and checked entity by entity."""

from __future__ import annotations

import sys
from collections import defaultdict

import numpy as np
import pytest

from lrslam.pipeline.config import build_config
from lrslam.trajectory_io import read_tum

from run_fixtures import TINY as _TINY, synthetic_room

# a first fit long enough for a surface to mesh (the last setting wins)
TINY = _TINY + ["field.mapping.first_iters=60", "output.mesh=false", "output.plots=false"]
N_FRAMES = 12
MISSING = "error: the viewer needs rerun-sdk: pip install 'lrslam[viewer]'\n"


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    return synthetic_room(tmp_path_factory.mktemp("viewer") / "room", n_frames=N_FRAMES, seed=3)


def _main(args: list[str]) -> int:
    from lrslam.cli import main

    with pytest.raises(SystemExit) as e:
        main(args)
    return e.value.code


@pytest.fixture(scope="module")
def recorded(seq_dir, tmp_path_factory):
    """A fused run through the real CLI with ``--rrd``: (run folder, recording)."""
    pytest.importorskip("rerun")
    tmp = tmp_path_factory.mktemp("viewer_run")
    out, rrd = tmp / "run", tmp / "run" / "live.rrd"     # the recording may live in the run folder
    code = _main(["run", str(seq_dir), "--out", str(out), "--config", "synthetic", "--mode", "fused", "--rrd",
                  str(rrd), "-q", *sum((["--set", o] for o in TINY), [])])
    assert code == 0
    return out, rrd


def _read(rrd) -> dict[str, list]:
    """``{entity path: [record batch, ...]}`` of the recording, read with Rerun's reader."""
    from rerun.chunk import RrdReader

    chunks = defaultdict(list)
    for c in RrdReader(rrd).stream():
        chunks[c.entity_path].append(c.to_record_batch())
    return dict(chunks)


def _rows(batches: list, column: str) -> list:
    return [v for b in batches if column in b.schema.names for v in b.column(column).to_pylist()]


def _frames(batches: list) -> list[int]:
    return sorted(_rows(batches, "frame"))


def test_a_run_recorded_with_rrd_holds_every_entity(recorded):
    out, rrd = recorded
    e = _read(rrd)
    for path in ["/world/camera", "/world/camera/image", "/world/camera/image/rgb", "/world/camera/image/depth",
                 "/world/camera/render", "/world/camera/render/depth", "/world/camera/render/rgb",
                 "/world/trajectory/fused", "/world/trajectory/seed", "/world/trajectory/frontend",
                 "/world/trajectory/gt", "/world/keyframes", "/world/mesh", "/metrics/ate_cm",
                 "/timings/refine_s", "/timings/map_s", "/timings/frame_s", "/timings/viewer_s", "/run/summary"]:
        assert path in e, f"{path} missing from the recording (has {sorted(e)})"
    # one camera pose per frame, on both time lines; the first one is the world's origin
    assert _frames(e["/world/camera"]) == list(range(N_FRAMES))
    ts, poses = read_tum(out / "trajectory.txt")
    assert len(_rows(e["/world/camera"], "time")) == N_FRAMES
    np.testing.assert_allclose(_rows(e["/world/camera"], "Transform3D:translation")[0][0], poses[0][:3, 3],
                               atol=1e-6)
    assert _frames(e["/world/camera/image/depth"]) == list(range(N_FRAMES))
    # the last fused trajectory is the run's trajectory.txt
    last = _rows(e["/world/trajectory/fused"], "LineStrips3D:strips")[-1][0]
    np.testing.assert_allclose(np.asarray(last), poses[:, :3, 3], atol=1e-5)
    # a mesh with faces, a running ATE in cm, the stage times per frame
    mesh = _rows(e["/world/mesh"], "Mesh3D:triangle_indices")[-1]
    assert len(mesh) > 0
    ate = [v[0] for v in _rows(e["/metrics/ate_cm"], "Scalars:scalars")]
    assert ate and all(np.isfinite(ate)) and all(0 <= a < 50 for a in ate)
    assert len(_frames(e["/timings/frame_s"])) == N_FRAMES


def test_lrslam_view_replays_a_run_folder(recorded, tmp_path, capsys):
    out, _ = recorded
    rrd = tmp_path / "replay.rrd"
    assert _main(["view", str(out), "--rrd", str(rrd), "--images"]) == 0
    assert "12 frames" in capsys.readouterr().out
    e = _read(rrd)
    ts, poses = read_tum(out / "trajectory.txt")
    fused = np.asarray(_rows(e["/world/trajectory/fused"], "LineStrips3D:strips")[0][0])
    np.testing.assert_allclose(fused, poses[:, :3, 3], atol=1e-5)
    for name in ("seed", "frontend", "gt"):         # gt: the sequence of config.yaml's provenance is readable
        assert len(_rows(e[f"/world/trajectory/{name}"], "LineStrips3D:strips")[0][0]) == N_FRAMES
    assert _frames(e["/world/camera"]) == list(range(N_FRAMES))
    assert _frames(e["/world/camera/image/rgb"]) == list(range(N_FRAMES))
    assert len(_rows(e["/world/keyframes"], "Points3D:positions")[0]) >= 2
    assert _rows(e["/metrics/ate_cm"], "Scalars:scalars")
    assert "/run/summary" in e


def test_view_refuses_what_is_not_a_run_folder(tmp_path, capsys):
    assert _main(["view", str(tmp_path), "--rrd", str(tmp_path / "x.rrd")]) == 2
    assert capsys.readouterr().err == f"error: {tmp_path}: not a finished lrslam run folder (no trajectory.txt)\n"
    assert not (tmp_path / "x.rrd").exists()


def test_without_rerun_the_viewer_is_one_line_and_exit_2(seq_dir, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "rerun", None)      # `import rerun` raises ImportError
    out = tmp_path / "run"
    assert _main(["run", str(seq_dir), "--out", str(out), "--config", "synthetic", "--mode", "frontend",
                  "--rrd", str(tmp_path / "x.rrd"), "-q"]) == 2
    assert capsys.readouterr().err == MISSING
    assert not (out / "trajectory.txt").exists()         # it failed before the run started
    (tmp_path / "fake").mkdir()
    (tmp_path / "fake" / "trajectory.txt").write_text("0 0 0 0 0 0 0 1\n1 0 0 0 0 0 0 1\n")
    assert _main(["view", str(tmp_path / "fake")]) == 2
    assert capsys.readouterr().err == MISSING


class _Probe:
    def __init__(self) -> None:
        self.events, self.results = [], []

    def on_frame(self, event) -> None:
        self.events.append(event)

    def on_finish(self, result) -> None:
        self.results.append(result)


def test_observers_see_every_frame_and_cost_nothing_when_absent(seq_dir, monkeypatch):
    from lrslam import Slam
    from lrslam.datasets import open_sequence

    cfg = build_config("synthetic", mode="frontend")
    seq = open_sequence(seq_dir)
    frames = [seq[i] for i in range(6)]
    probe, broken = _Probe(), _Probe()
    broken.on_frame = lambda event: 1 / 0                # a failing observer is detached, the run goes on
    slam = Slam(cfg, frames[0].K, (frames[0].width, frames[0].height), observers=[probe, broken])
    for f in frames:
        slam.track(f.rgb, f.depth, f.timestamp)
    result = slam.finish()
    assert slam.observers == [probe] and probe.results == [result]
    assert [ev.index for ev in probe.events] == list(range(6))
    last = probe.events[-1]
    ts, poses = last.trajectory()
    np.testing.assert_array_equal(ts, [f.timestamp for f in frames])
    np.testing.assert_array_equal(poses, result.poses)
    np.testing.assert_array_equal(last.T_w_seed, result.seed_poses[-1])
    np.testing.assert_array_equal(last.T_w_frontend, result.frontend_poses[-1])
    assert last.keyframe_ids == result.keyframe_ids and last.field is None
    assert set(last.stage_seconds) <= {"seed", "keyframe", "graph"} and last.seconds > 0
    assert all(ev.loop_edges == () and ev.moved == {} for ev in probe.events)
    # no observer: no event is ever built
    monkeypatch.setattr(Slam, "_event", lambda *a: pytest.fail("an event was built without observers"))
    quiet = Slam(cfg, frames[0].K, (frames[0].width, frames[0].height))
    for f in frames[:3]:
        quiet.track(f.rgb, f.depth, f.timestamp)
    quiet.finish()
