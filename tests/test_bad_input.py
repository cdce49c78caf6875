"""Bad input through the real command line (:func:`lrslam.cli.main`, in-process): every case states its exit code
and the file / key / flag the one-line message must name; no case may print a traceback.

Classes: usage errors, config errors, input errors, I/O errors, and runs whose output must be honest (run folders
never mixed, feed-back config, ``bound: auto``, degraded runs, evaluation failures, cameras). Cases marked
``silent`` gave a wrong or misleading result without an error before issue 10. The kill tests (SIGTERM /
SIGINT / SIGKILL mid-run) use a subprocess.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
import pytest

# A run that takes about a second: frontend odometry on 4 tiny frames, no mesh, no plot.
FAST = ["--mode", "frontend", "--max-frames", "4", "--set", "output.mesh=false", "--set", "output.plots=false",
        "-q"]
# A field-mode run of 3 frames with the tiny field settings of tests/test_pipeline_run.py.
FIELD = ["--mode", "field", "--max-frames", "3", "-q", "--set", "field.tracking.iters=3", "--set",
         "field.mapping.iters=3", "--set", "field.mapping.first_iters=10", "--set", "field.tracking.n_rays=128",
         "--set", "field.mapping.n_rays=256", "--set", "output.mesh=false", "--set", "output.plots=false"]


def _strict_json(path: Path) -> dict:
    def bad(token):
        raise ValueError(f"{path}: non-standard JSON constant {token}")

    return json.loads(Path(path).read_text(), parse_constant=bad)


# ---------------------------------------------------------------------------------------------------- inputs
def make_world(root: Path) -> dict[str, str]:
    """Every bad (and good) input the cases refer to, under ``root``; returns ``{placeholder: path}``."""
    from lrslam.datasets.synth.writer import generate

    root.mkdir(parents=True, exist_ok=True)
    w: dict[str, Path] = {"tmp": root}
    seq = w["seq"] = generate(root / "seq", scene="room", trajectory="loop", n_frames=12, seed=1, width=160,
                              height=120, show_progress=False)
    first_depth = sorted((seq / "depth").iterdir())[0].name

    def copy(name: str, drop: tuple[str, ...] = ()) -> Path:
        dst = root / name
        shutil.copytree(seq, dst, ignore=shutil.ignore_patterns(*drop))
        w[name] = dst
        return dst

    import cv2

    cv2.imwrite(str(copy("nodepth") / "depth" / first_depth), np.zeros((120, 160), np.uint16))
    (copy("corrupt") / "depth" / first_depth).write_bytes(b"not a png at all")
    d = copy("badstamp")
    lines = (d / "rgb.txt").read_text().splitlines()
    i = next(k for k, ln in enumerate(lines) if not ln.startswith("#"))
    lines[i] = "abc " + lines[i].split()[1]
    (d / "rgb.txt").write_text("\n".join(lines) + "\n")
    (copy("binlist") / "rgb.txt").write_bytes(b"\xff\xfe\x00\x81 binary")
    d = copy("nangt")
    gt = (d / "groundtruth.txt").read_text().splitlines()
    k = next(k for k, ln in enumerate(gt) if not ln.startswith("#")) + 3
    gt[k] = gt[k].split()[0] + " nan nan nan nan nan nan nan"
    (d / "groundtruth.txt").write_text("\n".join(gt) + "\n")
    import yaml

    intr = yaml.safe_load((seq / "scene.yaml").read_text())["intrinsics"]
    w["fx"], w["fy"], w["cx"], w["cy"] = (str(intr[k]) for k in ("fx", "fy", "cx", "cy"))
    copy("office", drop=("scene.yaml", "gt_mesh.ply"))
    d = copy("office_intr", drop=("scene.yaml", "gt_mesh.ply"))
    (d / "intrinsics.yaml").write_text(yaml.safe_dump({k: intr[k] for k in ("fx", "fy", "cx", "cy")}))
    d = copy("office_badintr", drop=("scene.yaml", "gt_mesh.ply"))
    (d / "intrinsics.yaml").write_text("fx: abc\nfy: 1\n")

    (root / "bad.yaml").write_text("mode: [fused\n  : :\n")
    (root / "list.yaml").write_text("- mode\n- field\n")
    (root / "binary.yaml").write_bytes(b"\xff\xfe\x00\x81")
    (root / "badkey.yaml").write_text("schedule: {map_evry: 1}\n")
    (root / "dir.yaml").mkdir()
    (root / "emptydir").mkdir()
    (root / "afile").write_text("just a file\n")
    for name in ("foreign", "foreign2", "o/bforeign/seq/frontend/s0"):   # the last: a batch job's run folder
        (root / name).mkdir(parents=True)
        (root / name / "notes.txt").write_text("my own notes\n")
    (root / "garbage.txt").write_text("this is not a trajectory\n")
    (root / "nan_traj.txt").write_text("0.0 nan 0 0 0 0 0 1\n")
    from lrslam.trajectory_io import write_tum

    ts = np.arange(5) * 0.1
    poses = np.repeat(np.eye(4)[None], 5, axis=0)
    poses[:, 0, 3] = ts
    write_tum(root / "traj.txt", ts, poses)
    import trimesh

    trimesh.creation.box().export(root / "box.ply")
    (root / "empty.ply").write_text("ply\nformat ascii 1.0\nelement vertex 0\nelement face 0\n"
                                    "property list uchar int vertex_indices\nend_header\n")

    # A previous run folder (config.yaml to feed back) and copies of it with stale outputs of an older run.
    subprocess.run([sys.executable, "-m", "lrslam", "run", str(seq), "--out", str(root / "prev"), *FAST],
                   check=True, capture_output=True, timeout=300)
    for name in ("stale_fail", "stale_ok"):
        shutil.copytree(root / "prev", root / name)
        (root / name / "trajectory_partial.txt").write_text("# from another sequence\n1 0 0 0 0 0 0 1\n")
        (root / name / "mesh.ply").write_text("old mesh\n")
        w[name] = root / name
    w["prev"] = root / "prev"
    return {k: str(v) for k, v in w.items()}


# ----------------------------------------------------------------------------------------------------- cases
@dataclass
class Case:
    id: str
    argv: list[str]
    code: int
    names: list[str]                    # substrings the error output must contain (file / key / flag)
    check: Callable[[dict, str, str], str | None] | None = None  # extra check -> problem or None
    silent: bool = False                # before issue 10 the result was silently wrong / misleading
    kind: str = "usage"
    out: str | None = field(default=None)


def _no_old_outputs(folder: str) -> Callable[[dict, str, str], str | None]:
    def check(w, out, err):
        left = [n for n in ("trajectory.txt", "metrics.json", "mesh.ply", "trajectory_partial.txt", "keyframes.txt")
                if (Path(w[folder]) / n).exists()]
        return f"stale outputs left: {left}" if left else None
    return check


def _fed_back(w, out, err):
    from lrslam.trajectory_io import read_tum

    new = Path(w["tmp"]) / "o" / "feedback"
    cfg = (new / "config.yaml").read_text()
    if "reader: synthetic" not in cfg or "provenance:" not in cfg or "command: lrslam run" not in cfg:
        return "config.yaml lacks the reader or the provenance"
    import yaml

    settings = [{k: v for k, v in yaml.safe_load((d / "config.yaml").read_text()).items() if k != "provenance"}
                for d in (Path(w["prev"]), new)]
    if settings[0] != settings[1]:
        return "the fed-back config does not reproduce the run's settings"
    # Open3D's multi-threaded odometry is not bit-reproducible: a gate decided on the edge can differ by mm
    (t0, p0), (t1, p1) = read_tum(Path(w["prev"]) / "trajectory.txt"), read_tum(new / "trajectory.txt")
    if len(t0) != len(t1) or not np.allclose(p0, p1, atol=1e-2):
        return "the fed-back config does not reproduce the run (beyond run-to-run noise)"
    return None


def _metrics(case_out: str) -> Callable[[dict], dict]:
    return lambda w: _strict_json(Path(w["tmp"]) / "o" / case_out / "metrics.json")


def _eval_failed(w, out, err):
    if "ATE: evaluation failed" not in out:
        return "summary does not say that the evaluation failed"
    m = _metrics("evalfail")(w)
    return None if m.get("evaluation_error") else "metrics.json has no evaluation_error"


def _nan_gt_is_missing_gt(w, out, err):
    m = _metrics("nangt")(w)
    return None if m.get("ate_rmse_cm") is not None else "no ATE although most frames have ground truth"


def _no_freiburg(w, out, err):
    return "the Freiburg warning was printed although intrinsics were given" if "Freiburg" in err else None


def _auto_bound(w, out, err):
    m = _metrics("auto")(w)
    return None if m["bound_source"].startswith("auto (pre-pass") else f"bound source {m['bound_source']}"


def _degraded(w, out, err):
    m = _metrics("degraded")(w)
    if m.get("status") != "degraded" or not m.get("degraded_reasons"):
        return f"status {m.get('status')!r}"
    if not m.get("frames_outside_bound"):
        return "no count of frames whose view left the bound"
    return None if "degraded" in out + err else "the summary does not warn"


def _status_ok(case_out):
    def check(w, out, err):
        m = _metrics(case_out)(w)
        return None if m.get("status") == "ok" else f"status {m.get('status')!r}"
    return check


def _wrote_beside_notes(folder):
    """The run's outputs are in the folder, and the user's own file in it is untouched."""
    def check(w, out, err):
        d = Path(w["tmp"]) / folder
        missing = [n for n in ("trajectory.txt", "metrics.json", "config.yaml") if not (d / n).is_file()]
        if missing:
            return f"the run did not write {missing}"
        notes = d / "notes.txt"
        return None if notes.is_file() and notes.read_text() == "my own notes\n" else "notes.txt was not kept"
    return check


def _batch_says_which(w, out, err):
    return None if "job nodepth/frontend/s0 failed" in err else "the failed job is not named"


CASES = [
    # usage errors
    Case("unknown-option", ["run", "{seq}", "--bogus"], 2, ["--bogus"]),
    Case("int-option-not-int", ["run", "{seq}", "--max-frames", "abc"], 2, ["--max-frames"]),
    Case("max-frames-zero", ["run", "{seq}", "--max-frames", "0"], 2, ["--max-frames"]),
    Case("missing-argument", ["eval", "ate", "{tmp}/traj.txt"], 2, ["gt"]),
    Case("unknown-command", ["frobnicate"], 2, ["frobnicate"]),
    Case("unknown-subcommand", ["eval", "nope"], 2, ["nope"]),
    Case("synth-no-out", ["synth"], 2, ["out"]),
    Case("synth-frames-not-int", ["synth", "{tmp}/s1", "--frames", "abc"], 2, ["--frames"]),
    Case("synth-frames-negative", ["synth", "{tmp}/s2", "--frames", "-3"], 2, ["frames"]),
    Case("unknown-mode", ["run", "{seq}", "--mode", "banana"], 2, ["mode"]),
    Case("batch-no-paths", ["batch"], 2, ["paths"]),
    Case("batch-unknown-mode", ["batch", "{seq}", "--modes", "field,banana"], 2, ["banana"]),
    Case("float-option-not-float", ["eval", "ate", "{tmp}/traj.txt", "{tmp}/traj.txt", "--max-dt", "abc"], 2,
         ["--max-dt"]),
    Case("params-bound-not-numbers", ["params", "--bound", "a,b,c,d,e,f"], 2, ["--bound"]),
    Case("eval-mesh-negative-points", ["eval", "mesh", "{tmp}/box.ply", "{tmp}/box.ply", "--n-points", "-5"], 2,
         ["--n-points"]),
    Case("partial-every-zero", ["run", "{seq}", "--partial-every", "0"], 2, ["--partial-every"]),
    # config errors
    Case("config-missing", ["run", "{seq}", "--config", "{tmp}/missing.yaml"], 2, ["missing.yaml"], kind="config"),
    Case("config-invalid-yaml", ["run", "{seq}", "--config", "{tmp}/bad.yaml"], 2, ["bad.yaml"], kind="config"),
    Case("config-not-mapping", ["run", "{seq}", "--config", "{tmp}/list.yaml"], 2, ["list.yaml"], kind="config"),
    Case("config-undecodable", ["run", "{seq}", "--config", "{tmp}/binary.yaml"], 2, ["binary.yaml"],
         kind="config"),
    Case("config-is-folder", ["run", "{seq}", "--config", "{tmp}/dir.yaml"], 2, ["dir.yaml"], kind="config"),
    Case("config-unknown-preset", ["run", "{seq}", "--config", "nope"], 2, ["nope"], kind="config"),
    Case("config-unknown-key", ["run", "{seq}", "--set", "schedule.map_evry=2"], 2, ["map_evry"], kind="config"),
    Case("config-key-in-file", ["run", "{seq}", "--config", "{tmp}/badkey.yaml"], 2, ["map_evry"], kind="config"),
    Case("override-without-value", ["run", "{seq}", "--set", "foo"], 2, ["foo"], kind="config"),
    Case("unknown-representation", ["run", "{seq}", "--repr", "nope"], 2, ["nope"], kind="config"),
    Case("bound-not-a-list", ["run", "{seq}", "--set", "bound=banana"], 2, ["bound"], kind="config"),
    Case("bound-wrong-shape", ["run", "{seq}", "--set", "bound=[[0,1],[0,1]]", *FAST], 2, ["bound"],
         kind="config"),
    Case("intrinsics-incomplete", ["run", "{seq}", "--set", "dataset.options.fx=500"], 2, ["fx"], kind="config"),
    Case("unknown-reader", ["run", "{seq}", "--set", "dataset.reader=nope", *FAST], 2, ["nope"], kind="config"),
    Case("batch-config-invalid", ["batch", "{seq}", "--config", "{tmp}/bad.yaml"], 2, ["bad.yaml"], kind="config"),
    Case("params-unknown-preset", ["params", "--config", "nope"], 2, ["nope"], kind="config"),
    # input errors
    Case("sequence-missing", ["run", "{tmp}/missing_seq"], 2, ["missing_seq"], kind="input"),
    # every batch path is checked before the first job starts (it used to fail as a job, after the others ran)
    Case("batch-sequence-missing", ["batch", "{seq}", "{tmp}/missing_seq", "--modes", "frontend", "--out",
                                    "{tmp}/o/batch_missing"], 2, ["missing_seq"], silent=True, kind="input"),
    Case("batch-job-folder-foreign", ["batch", "{seq}", "--modes", "frontend", "--out", "{tmp}/o/bforeign"], 2,
         ["frontend", "--overwrite"], silent=True, kind="io"),
    Case("sequence-unknown-layout", ["run", "{tmp}/emptydir"], 2, ["emptydir"], kind="input"),
    Case("first-frame-no-depth", ["run", "{nodepth}", *FAST], 2, ["nodepth", "no valid depth"], kind="input"),
    Case("bad-timestamp", ["run", "{badstamp}", *FAST], 2, ["rgb.txt"], kind="input"),
    Case("binary-list-file", ["run", "{binlist}", *FAST], 2, ["rgb.txt"], kind="input"),
    Case("corrupt-depth", ["run", "{corrupt}", *FAST], 2, [".png"], kind="input"),
    Case("crop-too-large", ["run", "{seq}", "--set", "dataset.options.crop_border=100", *FAST], 2,
         ["crop_border"], kind="input"),
    Case("unknown-camera-no-intrinsics", ["run", "{office}", *FAST], 2, ["office", "intrinsics"], silent=True,
         kind="input"),
    Case("intrinsics-file-invalid", ["run", "{office_badintr}", *FAST], 2, ["intrinsics.yaml"], kind="input"),
    Case("ate-missing-file", ["eval", "ate", "{tmp}/missing.txt", "{tmp}/traj.txt"], 2, ["missing.txt"],
         kind="input"),
    Case("ate-garbage-file", ["eval", "ate", "{tmp}/garbage.txt", "{tmp}/traj.txt"], 2, ["garbage.txt"],
         kind="input"),
    Case("ate-nan-estimate", ["eval", "ate", "{tmp}/nan_traj.txt", "{tmp}/traj.txt"], 2, ["nan_traj.txt"],
         kind="input"),
    Case("mesh-empty", ["eval", "mesh", "{tmp}/empty.ply", "{tmp}/box.ply", "--json"], 2, ["empty.ply"],
         silent=True, kind="input"),
    Case("mesh-missing", ["eval", "mesh", "{tmp}/nomesh.ply", "{tmp}/box.ply"], 2, ["nomesh.ply"], kind="input"),
    Case("mesh-bad-intrinsics", ["eval", "mesh", "{tmp}/box.ply", "{tmp}/box.ply", "--traj", "{tmp}/traj.txt",
                                 "--intrinsics", "abc", "--size", "10,10"], 2, ["--intrinsics"], kind="input"),
    Case("synth-unknown-noise", ["synth", "{tmp}/s3", "--noise", "banana"], 2, ["banana"], kind="input"),
    Case("synth-unknown-scene", ["synth", "{tmp}/s4", "--scene", "banana", "--frames", "2"], 2, ["banana"],
         kind="input"),
    # I/O errors
    Case("out-is-a-file", ["run", "{seq}", "--out", "{tmp}/afile", *FAST], 2, ["afile"], kind="io"),
    Case("out-below-a-file", ["run", "{seq}", "--out", "{tmp}/afile/sub", *FAST], 2, ["afile"], kind="io"),
    Case("out-foreign-folder", ["run", "{seq}", "--out", "{tmp}/foreign", *FAST], 2, ["foreign", "--overwrite"],
         silent=True, kind="io"),
    Case("synth-out-below-a-file", ["synth", "{tmp}/afile/sub", "--frames", "2"], 2, ["afile"], kind="io"),
    Case("batch-out-is-a-file", ["batch", "{seq}", "--modes", "frontend", "--out", "{tmp}/afile"], 2, ["afile"],
         kind="io"),
    # honest outputs: runs that must end right
    Case("overwrite-foreign-folder", ["run", "{seq}", "--out", "{tmp}/foreign2", "--overwrite", *FAST], 0, [],
         check=_wrote_beside_notes("foreign2"), kind="run"),
    Case("failed-run-leaves-no-old-outputs", ["run", "{nodepth}", "--out", "{stale_fail}", *FAST], 2,
         ["no valid depth"], check=_no_old_outputs("stale_fail"), silent=True, kind="run"),
    Case("config-fed-back", ["run", "{seq}", "--config", "{prev}/config.yaml", "--out", "{tmp}/o/feedback", "-q"],
         0, [], check=_fed_back, silent=True, kind="run"),
    Case("stale-partial-removed", ["run", "{seq}", "--out", "{stale_ok}", *FAST], 0, [],
         check=lambda w, o, e: "stale trajectory_partial.txt survived" if
         (Path(w["stale_ok"]) / "trajectory_partial.txt").exists() else None, silent=True, kind="run"),
    Case("evaluation-failed-is-said", ["run", "{seq}", "--out", "{tmp}/o/evalfail", *FAST[:2], "--max-frames", "2",
                                       *FAST[4:]], 0, [], check=_eval_failed, silent=True, kind="run"),
    Case("tum-nan-gt-is-missing-gt", ["run", "{nangt}", "--out", "{tmp}/o/nangt", *FAST], 0, [],
         check=_nan_gt_is_missing_gt, kind="run"),
    Case("unknown-camera-intrinsics-file", ["run", "{office_intr}", "--out", "{tmp}/o/office_intr", *FAST], 0, [],
         check=_no_freiburg, silent=True, kind="run"),
    Case("unknown-camera-intrinsics-options", ["run", "{office}", "--out", "{tmp}/o/office_opts", *FAST, "--set",
                                               "dataset.options.fx={fx}", "--set", "dataset.options.fy={fy}",
                                               "--set", "dataset.options.cx={cx}", "--set",
                                               "dataset.options.cy={cy}"], 0, [], check=_no_freiburg, silent=True,
         kind="run"),
    Case("bound-auto", ["run", "{seq}", "--out", "{tmp}/o/auto", "--set", "bound=auto", *FAST], 0, [],
         check=_auto_bound, kind="run"),
    Case("degraded-run-exits-3", ["run", "{seq}", "--out", "{tmp}/o/degraded", *FIELD, "--set",
                                  "bound=[[5,5.2],[5,5.2],[5,5.2]]"], 3, ["degraded"], check=_degraded, silent=True,
         kind="run"),
    Case("ok-run-status", ["run", "{seq}", "--out", "{tmp}/o/okrun", *FAST], 0, [], check=_status_ok("okrun"),
         kind="run"),
    Case("batch-failed-job", ["batch", "{seq}", "{nodepth}", "--modes", "frontend", "--out", "{tmp}/o/batch",
                              "--max-frames", "4", "-q", "--sequential", "--set", "output.mesh=false", "--set",
                              "output.plots=false"], 1, ["nodepth"], check=_batch_says_which, silent=True,
         kind="run"),
]


def expand(argv: list[str], w: dict[str, str]) -> list[str]:
    argv = [a.format(**w) for a in argv]
    if argv[0] == "run" and "--out" not in argv:
        argv += ["--out", str(Path(w["tmp"]) / "o" / "default")]
    return argv


def judge(case: Case, w: dict, code: int, out: str, err: str) -> str | None:
    """None when the case ended as it must, else what went wrong."""
    if "Traceback" in out + err:
        return "traceback"
    if code != case.code:
        return f"exit {code} (expected {case.code}): {err.strip()[-300:]}"
    if case.code == 2:
        lines = [ln for ln in err.strip().splitlines() if ln.startswith("error:")]
        if len(lines) != 1:
            return f"expected one 'error:' line, got {err.strip()!r}"
    for name in case.names:
        if name not in out + err:
            return f"output does not name {name!r}: {err.strip()!r}"
    return case.check(w, out, err) if case.check else None


# ----------------------------------------------------------------------------------------------------- tests
@pytest.fixture(scope="session")
def world(tmp_path_factory):
    return make_world(tmp_path_factory.mktemp("bad_input"))


def run_cli(argv: list[str], capfd) -> tuple[int, str, str]:
    from lrslam.cli import main

    capfd.readouterr()
    with pytest.raises(SystemExit) as e:
        main(argv)
    out, err = capfd.readouterr()
    return int(e.value.code or 0), out, err


def test_every_case_can_fail():
    """Each case asserts something beyond "exit code, no traceback": one that must fail names what it failed on
    (file / key / flag), one that must succeed checks its outputs (a run that silently did the wrong thing also
    exits 0). Ids are unique, so a failure names one case."""
    assert len({c.id for c in CASES}) == len(CASES)
    assert [c.id for c in CASES if c.code != 0 and not c.names] == []
    assert [c.id for c in CASES if c.code == 0 and c.check is None] == []
    assert {c.kind for c in CASES} <= {"usage", "config", "input", "io", "run"}


@pytest.mark.parametrize("case", CASES, ids=[c.id for c in CASES])
def test_bad_input(case, world, capfd):
    code, out, err = run_cli(expand(case.argv, world), capfd)
    problem = judge(case, world, code, out, err)
    assert problem is None, problem


def test_entry_point_version_and_help():
    for args in (["--version"], ["-h"], ["run", "-h"]):
        r = subprocess.run([sys.executable, "-m", "lrslam", *args], capture_output=True, text=True, timeout=60)
        assert r.returncode == 0 and "Traceback" not in r.stderr, r.stderr
    r = subprocess.run([sys.executable, "-m", "lrslam", "--version"], capture_output=True, text=True, timeout=60)
    from lrslam import __version__

    assert __version__ in r.stdout
    r = subprocess.run([sys.executable, "-m", "lrslam", "run", "x", "--bogus", "--debug"], capture_output=True,
                       text=True, timeout=60)
    assert r.returncode != 0 and "Traceback" in r.stderr  # --debug shows it


# ------------------------------------------------------------------------------------------------ kill tests
KILL_FRAMES = 60


@pytest.fixture(scope="module")
def long_seq(tmp_path_factory) -> Path:
    """A 60-frame sequence: field mode with few iterations takes 0.04-0.3 s per frame, so 0.1-0.5 s after the
    first partial save (frame 2 or 3) the run is still far from its end, however fast the machine (12 frames
    were not: on a fast VM the run finished within the 0.5 s the test waited)."""
    from lrslam.datasets.synth.writer import generate

    return generate(tmp_path_factory.mktemp("kill") / "seq", scene="room", trajectory="loop", n_frames=KILL_FRAMES,
                    seed=1, width=160, height=120, show_progress=False)


def _start_run(seq: Path, out: Path, every: int) -> subprocess.Popen:
    args = [sys.executable, "-m", "lrslam", "run", str(seq), "--out", str(out), "--partial-every", str(every),
            *FIELD[:2], *FIELD[4:]]
    return subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)


def _wait_for(path: Path, proc: subprocess.Popen, timeout: float = 90.0) -> None:
    t0 = time.time()
    while not path.exists():
        assert proc.poll() is None, proc.communicate()
        assert time.time() - t0 < timeout, "no partial trajectory appeared"
        time.sleep(0.05)


def _partial(out: Path) -> tuple[np.ndarray, np.ndarray]:
    from lrslam.trajectory_io import read_tum

    ts, poses = read_tum(out / "trajectory_partial.txt")
    assert np.all(np.isfinite(poses))
    others = {p.name for p in out.iterdir()} - {"trajectory_partial.txt", ".trajectory_partial.txt.tmp",
                                                 "config.yaml", "run.log"}
    assert not others, f"outputs of a finished run in an interrupted folder: {others}"
    return ts, poses


@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_terminated_run_saves_its_partial_trajectory(long_seq, tmp_path, sig, code):
    out = tmp_path / "run"
    proc = _start_run(long_seq, out, every=2)
    _wait_for(out / "trajectory_partial.txt", proc)
    time.sleep(0.1)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=60)
    assert proc.returncode == code and "Traceback" not in err, err
    ts, _ = _partial(out)
    assert 2 <= len(ts) < KILL_FRAMES


def test_killed_run_leaves_a_partial_trajectory_within_the_save_interval(long_seq, tmp_path):
    out = tmp_path / "run"
    proc = _start_run(long_seq, out, every=3)
    _wait_for(out / "trajectory_partial.txt", proc)
    time.sleep(0.2)
    proc.kill()
    proc.communicate(timeout=60)
    assert proc.returncode == -signal.SIGKILL
    ts, _ = _partial(out)
    done = 1 + (out / "run.log").read_text().count(" done: ")  # frame 0 + one line per later frame
    assert done < KILL_FRAMES, "the run finished before the kill"
    # A frame's partial trajectory is written before its " done: " line (268a651), so a kill between the two
    # leaves the file one frame ahead of the log: at most done + 1 poses, never more.
    assert len(ts) % 3 == 0 and done - 3 < len(ts) <= done + 1
