"""``lrslam run`` and ``lrslam params`` (registered in :mod:`lrslam.cli`). Heavy imports stay inside."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Optional

import typer

from lrslam.errors import InputError
from lrslam.jsonio import dumps
from lrslam.logs import setup_console_logging
from lrslam.threads import flush_denormals, set_threads

__all__ = ["run", "params", "batch", "report", "DEMO_SYNTH"]

# The built-in demo sequence: a textured room, a loop trajectory, Kinect-like depth noise.
DEMO_SYNTH = dict(scene="room", trajectory="loop", n_frames=80, seed=0, width=320, height=240)


def _num(v, fmt: str) -> str:
    return "n/a" if v is None or not math.isfinite(v) else format(v, fmt)


def _ate_line(m: dict) -> str:
    if m.get("ate_rmse_cm") is not None:
        seed = f"   (seed only: {_num(m['seed_ate_rmse_cm'], '.3f')} cm)" if "seed_ate_rmse_cm" in m else ""
        online = (f"   (before the final refinement: {_num(m['online_ate_rmse_cm'], '.3f')} cm)"
                  if "online_ate_rmse_cm" in m else "")
        raw = (f"   (before smoothing: {_num(m['unsmoothed_ate_rmse_cm'], '.3f')} cm)"
               if "unsmoothed_ate_rmse_cm" in m else "")
        return (f"ATE RMSE: {_num(m['ate_rmse_cm'], '.3f')} cm   mean: {_num(m.get('ate_mean_cm'), '.3f')} cm"
                f"{seed}{online}{raw}")
    if m.get("evaluation_error"):
        return f"ATE: evaluation failed ({m['evaluation_error']})"
    if m.get("has_ground_truth", False):
        return "ATE: not evaluated (output.evaluate is off)"
    return "ATE: no ground truth in this sequence"


def _summary_lines(metrics: dict, out: Path) -> list[str]:
    lines = [f"mode: {metrics['mode']}   frames: {metrics['n_frames']}   keyframes: {metrics['n_keyframes']}"
             f"   loop closures: {metrics['n_loop_closures']}   scene bound: {metrics['bound_source']}",
             _ate_line(metrics)]
    if metrics.get("loops"):
        lp = metrics["loops"]
        shift = metrics.get("final_refine_max_shift_m")
        lines.append(f"loops: {lp['proposed']} proposed, {lp['kept']} kept; rejected: {lp['unverified']} by "
                     f"registration, {lp['disputed']} by the map, {lp['inconsistent']} by the graph"
                     + (f"   final refinement: keyframes moved up to {100 * shift:.2f} cm" if shift is not None else ""))
    if metrics.get("factor_chi2"):
        lines.append("graph factors vs ground truth (chi2/dof, 1 = honest weights): " + ", ".join(
            f"{k} {_num(v['chi2_per_dof_mean'], '.2f')} (n={v['n']})" for k, v in metrics["factor_chi2"].items()))
    if "mesh_accuracy_cm" in metrics:
        lines.append(f"mesh: accuracy {_num(metrics['mesh_accuracy_cm'], '.2f')} cm   completion "
                     f"{_num(metrics['mesh_completion_cm'], '.2f')} cm   completion ratio "
                     f"{_num(metrics['mesh_completion_ratio'], '.1f')} %")
    lines.append(f"frame processing time: {metrics['fpt_s']:.3f} s/frame   (wall {metrics['wall_s']:.1f} s)")
    stages = ", ".join(f"{k} {v['per_frame_s']:.3f}" for k, v in metrics.get("timings", {}).items())
    lines.append(f"per-stage s/frame: {stages}")
    if "parameters" in metrics:
        p = metrics["parameters"]
        lines.append("field parameters: " + ", ".join(f"{k} {v:,}" for k, v in p.items()))
    if metrics.get("frames_outside_bound"):
        lines.append(f"WARNING: {metrics['frames_outside_bound']} frames saw more than "
                     f"{100 * metrics['bound_check_fraction']:.0f}% of their depth outside the scene bound")
    if metrics.get("status") == "degraded":
        lines.append("WARNING: run degraded (exit code 3): " + "; ".join(metrics.get("degraded_reasons", [])))
    for name in ("trajectory.txt", "keyframes.txt", "mesh.ply", "trajectory.png", "metrics.json", "config.yaml"):
        if (out / name).exists():
            lines.append(f"  wrote {out / name}")
    return lines


def run(
    path: Optional[Path] = typer.Argument(None, help="Sequence folder (TUM, Replica, ScanNet, 7-Scenes, "
                                 "synthetic) or ROS bag (a ROS 1 .bag file or a ROS 2 bag folder)."),
    out: Path = typer.Option(Path("runs/latest"), "--out", "-o", help="Run folder to write."),
    mode: Optional[str] = typer.Option(None, help="field | frontend | fused (default from config: fused)."),
    config: Optional[str] = typer.Option(None, "--config", "-c",
                                         help="Dataset preset (tum-cpu, tum, 7scenes-cpu, replica, scannet, "
                                              "synthetic, rosbag-cpu, ...; a scene preset such as tum-fr1-desk adds "
                                              "that scene's bound) or a YAML file."),
    representation: Optional[str] = typer.Option(None, "--repr", help="Representation preset (lrslam: CP "
                                                 "geometry + Six-axis appearance; eslam, cp-cp, sa-sa, sa-cp)."),
    overrides: Optional[list[str]] = typer.Option(None, "--set", help="Override, e.g. --set schedule.map_every=2"),
    max_frames: Optional[int] = typer.Option(None, min=1, help="Process at most this many frames."),
    demo: bool = typer.Option(False, "--demo", help="Generate the built-in synthetic sequence and run on it."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Write into a non-empty folder that is not an lrslam "
                                                              "run folder (other files in it are kept)."),
    partial_every: Optional[int] = typer.Option(None, "--partial-every", min=1, help="Save trajectory_partial.txt "
                                                "every N frames during the run (= --set output.partial_every=N)."),
    seed: Optional[int] = typer.Option(None, "--seed", min=0, help="The run's seed: every RNG (Python, numpy, "
                                       "torch, the field's samplers) (= --set seed=N; default 0)."),
    deterministic: bool = typer.Option(False, "--deterministic", help="Open3D on one thread, so that runs with the "
                                       "same seed repeat bit for bit on the CPU (= --set deterministic=true)."),
    checkpoint_every: Optional[int] = typer.Option(None, "--checkpoint-every", min=0, help="Save checkpoint.pt "
                                                   "every N keyframes (= --set output.checkpoint_every=N; 0: never)."),
    resume: bool = typer.Option(False, "--resume", help="Continue the run in OUT from its last checkpoint (same "
                                "sequence and settings as the run)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bars."),
    threads: Optional[int] = typer.Option(None, "--threads", min=1, help="CPU threads for torch, numba and "
                                          "OpenMP (default: the libraries' own choice, all cores)."),
    viewer: bool = typer.Option(False, "--viewer", help="Draw the run live in a Rerun viewer (spawned; needs "
                                "pip install 'lrslam\\[viewer]')."),
    rrd: Optional[Path] = typer.Option(None, "--rrd", help="Record the live view to this .rrd file (headless "
                                       "machines, CI; open it with `rerun FILE`)."),
) -> None:
    """Run SLAM on a sequence and write trajectory, keyframes, mesh, plots, metrics and config to OUT.

    Exit code 0: ok; 2: bad input; 3: the run finished but is degraded (see metrics.json "degraded_reasons").
    ``--set bound=auto`` estimates the scene bound with a fast odometry pre-pass over the sequence.
    ``--resume`` continues a killed run from OUT/checkpoint.pt: give the same sequence and options as the run.
    ``--viewer`` / ``--rrd FILE`` draw the run in Rerun as it goes (``lrslam view OUT`` replays it afterwards).
    """
    from lrslam.pipeline.config_source import default_preset, load_run_config
    from lrslam.pipeline.run import run_sequence
    from lrslam.pipeline.run_folder import check_run_folder

    setup_console_logging()
    set_threads(threads)
    flush_denormals()   # before any thread pool starts: every thread of the run inherits it
    if demo:
        config = config or "synthetic"
    ov = list(overrides or [])
    if max_frames is not None:
        ov.append(f"dataset.options.max_frames={max_frames}")
    if partial_every is not None:
        ov.append(f"output.partial_every={partial_every}")
    if config is None and path is not None:
        config, why = default_preset(path)
        typer.echo(why)
    if seed is not None:
        ov.append(f"seed={seed}")
    if deterministic:
        ov.append("deterministic=true")
    if checkpoint_every is not None:
        ov.append(f"output.checkpoint_every={checkpoint_every}")
    if resume and overwrite:
        raise InputError("--resume continues the run in --out; it cannot be combined with --overwrite")
    loaded = load_run_config(config, representation, overrides=ov, mode=mode)   # fail fast on a bad config
    check_run_folder(out, overwrite)
    typer.echo(f"config: {config or 'built-in defaults'}; {loaded.cfg.mode_settings()}")
    if demo:
        from lrslam.datasets.synth.writer import generate

        path = out / "sequence"
        if not (path / "scene.yaml").is_file():
            typer.echo(f"generating the demo sequence in {path} ...")
            generate(path, noise=_demo_noise(), show_progress=not quiet, **DEMO_SYNTH)
    if path is None:
        raise InputError("give a sequence folder, or --demo for the built-in synthetic sequence")
    live = _open_viewer(viewer, rrd)
    try:
        res = run_sequence(path, loaded.cfg, out, progress=not quiet, overwrite=overwrite, presets=loaded.presets,
                           resume=resume, viewer=live, announce=typer.echo)
    finally:   # flushed and closed also on an error or Ctrl-C: the recording keeps the frames drawn so far
        if live is not None:
            live.close()
    for line in _summary_lines(res.metrics, Path(out)):
        typer.echo(line)
    if res.metrics.get("status") == "degraded":
        raise typer.Exit(3)


def _open_viewer(spawn: bool, rrd: Path | None):
    """The live viewer of ``lrslam run`` (None without ``--viewer`` / ``--rrd``); InputError without rerun-sdk."""
    if not spawn and rrd is None:
        return None
    from lrslam.pipeline.viewer import RerunViewer

    return RerunViewer(spawn=spawn, rrd=rrd)


def _demo_noise():
    from lrslam.datasets.synth.noise import NoiseConfig

    return NoiseConfig(kinect=True)


def params(
    config: Optional[str] = typer.Option("replica-room0", "--config", "-c", help="A scene preset or YAML that "
                                         "gives a bound (e.g. replica-room0, scannet-scene0000, tum-fr1-desk)."),
    representation: Optional[str] = typer.Option(None, "--repr", help="One representation preset; default: all."),
    bound: Optional[str] = typer.Option(None, help="Override bound: xmin,xmax,ymin,ymax,zmin,zmax (metres)."),
    as_json: bool = typer.Option(False, "--json", help="Machine-readable output."),
) -> None:
    """Print the parameter table (f_g, f_a, f_g + f_a, decoders, total: the paper's Table 1) for a config's bound."""
    import numpy as np

    from lrslam.field.model import SceneModel
    from lrslam.pipeline.config import list_presets
    from lrslam.pipeline.config_source import load_run_config

    cfg = load_run_config(config).cfg
    if bound:
        try:
            vals = [float(x) for x in bound.split(",")]
        except ValueError:
            vals = []
        if len(vals) != 6 or not all(map(math.isfinite, vals)):
            raise InputError(f"--bound needs 6 comma-separated numbers xmin,xmax,ymin,ymax,zmin,zmax, got {bound!r}")
        b = np.asarray(vals).reshape(3, 2)
    elif isinstance(cfg.bound, list):
        b = np.asarray(cfg.bound)
    else:
        raise InputError(f"config {config!r} has no fixed bound (a run takes it from the data): pass --bound or a "
                         "scene preset (e.g. replica-room0)")
    names = [representation] if representation else list_presets("representation")
    rows = {}
    for name in names:
        rcfg = load_run_config(config, name).cfg
        counts = SceneModel(b, rcfg.field.model).parameter_count()
        rows[name] = counts
    if as_json:
        typer.echo(dumps({"bound": b.tolist(), "parameters": rows}, indent=2))
        return
    typer.echo(f"bound {b.tolist()} (metres)")
    typer.echo(f"{'representation':<16}{'f_g':>12}{'f_a':>12}{'f_g+f_a':>12}{'decoders':>10}{'total':>12}")
    for name, c in rows.items():
        typer.echo(f"{name:<16}{c['geometry'] / 1e6:>11.3f}M{c['appearance'] / 1e6:>11.3f}M"
                   f"{c['encodings'] / 1e6:>11.3f}M{c['decoders']:>10,}{c['total'] / 1e6:>11.3f}M")
    typer.echo("total = f_g + f_a + decoders, as the paper's Table 1 'Total'")


def _csv(text: str | None) -> list[str]:
    return [x.strip() for x in (text or "").split(",") if x.strip()]


def batch(
    paths: list[str] = typer.Argument(..., help="Sequence folders; SEQ:PRESET runs that sequence with its own "
                                                "dataset preset or YAML file."),
    out: Path = typer.Option(Path("runs/batch"), "--out", "-o", help="Batch folder: one run folder per job."),
    modes: str = typer.Option("field,frontend,fused", help="Comma-separated modes to compare side by side."),
    seeds: int = typer.Option(1, "--seeds", help="Field seeds per field / fused job (field.seed = 0..N-1)."),
    config: Optional[str] = typer.Option(None, "--config", "--preset", "-c",
                                         help="Dataset preset or YAML for sequences that name none."),
    representation: Optional[str] = typer.Option(None, "--repr", help="Comma-separated representation presets."),
    overrides: Optional[list[str]] = typer.Option(None, "--set", help="Override for every job, key.sub=value."),
    max_frames: Optional[int] = typer.Option(None, min=1),
    cpus_per_job: int = typer.Option(1, "--cpus-per-job", min=1, help="CPUs (and threads) per job."),
    workers: Optional[int] = typer.Option(None, "--workers", min=1, help="Local Ray: jobs at a time (default: "
                                                                         "CPUs // --cpus-per-job)."),
    address: Optional[str] = typer.Option(None, "--address", help="Run on this Ray cluster (e.g. auto, or "
                                                                  "ray://host:10001) instead of a local Ray."),
    gpus_per_job: Optional[float] = typer.Option(None, "--gpus-per-job", min=0, help="GPUs per job (default: "
                                                 "local Ray shares this machine's GPUs, a cluster 0)."),
    sequential: bool = typer.Option(False, "--sequential", help="Run the jobs one after another in this process "
                                                                "even when Ray is installed."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress bar and job lines."),
) -> None:
    """Run the job grid sequences x modes x seeds x representations (Ray tasks when Ray is installed) and print
    the comparison table; OUT gets comparison.md / .csv, report.html and batch.json. A re-run skips complete jobs.

    Exit code 1 when any job failed (each failed job is named on stderr), 2 on a bad path or setting (before any
    job starts), 3 when any run is degraded.
    """
    from lrslam.tools.batch import run_grid
    from lrslam.tools.batch_exec import make_executor
    from lrslam.tools.batch_grid import check_jobs, expand_grid, is_complete

    setup_console_logging()
    ov = list(overrides or []) + ([f"dataset.options.max_frames={max_frames}"] if max_frames else [])
    jobs = expand_grid(paths, _csv(modes), seeds, _csv(representation), config, ov)
    check_jobs(jobs, out)     # before Ray starts: a bad path costs nothing

    def note(text: str) -> None:
        typer.echo(text, err=True)

    all_done = all(is_complete(j, out) for j in jobs)    # nothing to run: no Ray to start
    executor = make_executor(False if sequential or all_done else None, cpus_per_job, workers, address,
                             gpus_per_job, note)
    try:
        outcome = run_grid(jobs, out, executor, progress=not quiet, echo=note)
    finally:
        executor.close()
    typer.echo((out / "comparison.md").read_text().rstrip())
    written = [out / n for n in ("comparison.md", "comparison.csv", "report.html", "batch.json")]
    typer.echo("wrote " + ", ".join(str(p) for p in written if p.exists()))
    for e in outcome.failed():
        typer.echo(f"error: job {e['name']} failed: {e['error']}", err=True)
    if outcome.failed():
        raise typer.Exit(1)
    if outcome.degraded():
        typer.echo("warning: some runs are degraded (see their metrics.json)", err=True)
        raise typer.Exit(3)


def report(
    runs_dir: Path = typer.Argument(..., help="A batch folder (batch.json) or any folder holding run folders."),
) -> None:
    """Write RUNS_DIR/report.html (self-contained: tables, ATE box plots over seeds, trajectories on ground truth,
    time per stage, failed jobs) and comparison.md / comparison.csv; prints the table."""
    from lrslam.tools.report import write_report

    setup_console_logging()
    page = write_report(runs_dir)
    typer.echo((runs_dir / "comparison.md").read_text().rstrip())
    typer.echo(f"wrote {page}, {runs_dir / 'comparison.md'}, {runs_dir / 'comparison.csv'}")
