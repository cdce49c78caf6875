"""Where the time goes: s/frame per stage, iterations used, first / last third and peak RSS, per mode.

Each (sequence, mode) runs as its own ``lrslam run`` process (so peak RSS is that run's alone, read with
``os.wait4``), with ``--threads`` threads, one after another (never two at once: on 2 cores two runs side by
side each slow down 2-5x). Sequences (``--sequences``):

- ``synthetic``: a generated room loop (``--frames``, default 300, 320x240, Kinect-like depth noise + 1 cm), the
  ``synthetic`` preset;
- ``tum``: the TUM fr1/rpy excerpt in ``../shared/data`` (``tum-cpu``, 120 frames);
- ``7scenes``: the 7-Scenes redkitchen excerpt (``7scenes-cpu``, every 4th of 500 frames).

The table per sequence: s/frame in all and per stage (io, seed, refine, keyframe, map, graph, remap; the mesh
at the end is given in seconds, not per frame; with ``schedule.background_mapping``, as in ``tum-cpu``'s field
mode, ``map`` is the time the tracking thread waited for the mapper), tracking iterations used per frame (mean),
first-third and last-third s/frame and their ratio, peak RSS, ATE RMSE. ``--paired`` adds the CP-SA (LRSLAM) /
tri-plane (ESLAM) ratio of whole-run s/frame measured in one process: two runners on the same frames in lockstep,
frame by frame, so both see the same machine speed (``--paired-frames`` frames, field mode). ``--rrd DIR`` runs each
(sequence, mode) a second time right after the first, with the live viewer recording to ``DIR/<sequence>-<mode>.rrd``
(``lrslam run --rrd``), and prints the viewer's cost: s/frame without and with it, side by side.

Usage::

    python benchmarks/fps.py [--sequences synthetic,tum,7scenes] [--modes field,frontend,fused] [--frames 300]
                             [--threads 2] [--device cpu|cuda] [--set key=value ...] [--paired]
                             [--paired-frames 60] [--rrd DIR] [--out runs/bench_fps]

``--device cuda`` runs the GPU-sized presets (``tum``, ``7scenes``; the synthetic preset with ``field.device=cuda``)
and, with ``--paired``, reports the paper settings' CP-SA vs tri-plane s/frame side by side.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

STAGES = ("io", "seed", "refine", "keyframe", "map", "graph", "remap")
PRESETS = {"cpu": {"synthetic": "synthetic", "tum": "tum-cpu", "7scenes": "7scenes-cpu"},
           "cuda": {"synthetic": "synthetic", "tum": "tum", "7scenes": "7scenes"}}
STRIDES = {"synthetic": 1, "tum": 1, "7scenes": 4}


def _data_root() -> Path:
    return Path(os.environ.get("LRSLAM_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))


def sequence_path(name: str, frames: int, out: Path) -> Path | None:
    """The folder of sequence ``name`` (the synthetic loop is generated once under ``out/data``); None when a
    real excerpt is absent."""
    if name == "synthetic":
        from lrslam.datasets.synth.noise import NoiseConfig
        from lrslam.datasets.synth.writer import generate

        noise = NoiseConfig(depth_sigma=0.01, kinect=True, seed=0)
        return Path(generate(out / "data" / f"room_loop_{frames}", scene="room", trajectory="loop", n_frames=frames,
                             seed=0, width=320, height=240, noise=noise, reuse=True, show_progress=False))
    pattern = {"tum": "tum*rpy*", "7scenes": "7scenes*kitchen*"}[name]
    paths = sorted(_data_root().glob(pattern))
    return paths[0] if paths else None


def run_one(seq: Path, preset: str, mode: str, stride: int, threads: int, overrides: list[str],
            out: Path, rrd: Path | None = None) -> dict:
    """One ``lrslam run`` in its own process -> its metrics.json plus ``peak_rss_mb`` and ``process_s``
    (``rrd``: with the live viewer recording to that file)."""
    cmd = [sys.executable, "-m", "lrslam", "run", str(seq), "-c", preset, "--mode", mode, "--out", str(out),
           "--threads", str(threads), "-q", "--overwrite"] + (["--rrd", str(rrd)] if rrd is not None else [])
    for o in overrides + ([f"dataset.options.stride={stride}"] if stride > 1 else []):
        cmd += ["--set", o]
    t0 = time.perf_counter()
    with open(out.parent / f"{out.name}.log", "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT)
        _, status, usage = os.wait4(proc.pid, 0)
    proc.returncode = os.waitstatus_to_exitcode(status)
    metrics_file = out / "metrics.json"
    if proc.returncode not in (0, 3) or not metrics_file.is_file():
        return {"error": f"exit {proc.returncode}; see {out.parent / (out.name + '.log')}"}
    m = json.loads(metrics_file.read_text())
    m["peak_rss_mb"] = usage.ru_maxrss / 1024.0   # KiB on Linux
    m["process_s"] = time.perf_counter() - t0
    return m


def _f(x, fmt="{:.3f}") -> str:
    return "-" if x is None or (isinstance(x, float) and not np.isfinite(x)) else fmt.format(x)


def table(title: str, rows: dict[str, dict]) -> str:
    """Markdown table of the runs of one sequence (mode -> metrics)."""
    head = ["mode", "s/frame", *STAGES, "mesh s", "track iters", "first / last third", "last/first", "peak RSS MB",
            "ATE cm", "keyframes", "loops", "solves", "re-maps"]
    lines = [f"### {title}", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for mode, m in rows.items():
        if "error" in m:
            lines.append(f"| {mode} | failed: {m['error']} |")
            continue
        t = m.get("timings", {})
        stages = [_f(t.get(s, {}).get("per_frame_s")) for s in STAGES]
        lines.append("| " + " | ".join([
            mode, _f(m.get("fpt_s")), *stages, _f(t.get("mesh", {}).get("total_s"), "{:.1f}"),
            _f(m.get("refine_iters_mean"), "{:.1f}"),
            f"{_f(m.get('fpt_first_third_s'))} / {_f(m.get('fpt_last_third_s'))}", _f(m.get("fpt_last_over_first"),
                                                                                      "{:.2f}"),
            _f(m.get("peak_rss_mb"), "{:.0f}"), _f(m.get("ate_rmse_cm"), "{:.2f}"), str(m.get("n_keyframes", "-")),
            str(m.get("n_loop_closures", "-")), str(m.get("n_graph_solves", "-")), str(m.get("n_remaps", "-"))]) + " |")
    return "\n".join(lines + [""])


def viewer_cost(rows: dict[str, dict]) -> list[str]:
    """One line per mode run with and without the viewer: s/frame side by side and the difference."""
    lines = []
    for mode, m in rows.items():
        v = rows.get(f"{mode}+viewer")
        if mode.endswith("+viewer") or v is None or "fpt_s" not in m or "fpt_s" not in v:
            continue
        a, b = m["fpt_s"], v["fpt_s"]
        size = f", recording {v['rrd_mb']:.1f} MB" if "rrd_mb" in v else ""
        lines.append(f"- {mode}: {a:.3f} s/frame without the viewer, {b:.3f} with it ({100 * (b - a) / a:+.1f} %)"
                     f"{size}")
    return lines


def paired_ratio(seq: Path, preset: str, stride: int, frames: int, overrides: list[str]) -> dict:
    """CP-SA / tri-plane whole-run s/frame in one process: two field-mode runners step through the same frames
    in lockstep (each frame: LRSLAM's step, then ESLAM's), so speed drift of the machine hits both alike."""
    from lrslam.datasets import open_sequence
    from lrslam.pipeline.config import build_config
    from lrslam.pipeline.run import choose_bound
    from lrslam.pipeline.runner import SlamRunner

    ov = overrides + [f"dataset.options.max_frames={frames * stride}"] + (
        [f"dataset.options.stride={stride}"] if stride > 1 else [])
    cfgs = {r: build_config(preset, r, overrides=ov, mode="field") for r in ("lrslam", "eslam")}
    cfg0 = cfgs["lrslam"]
    seq = open_sequence(seq, reader=cfg0.dataset.reader, options=cfg0.reader_options())
    first = seq[0]
    T0 = first.T_w_c_gt if first.T_w_c_gt is not None else np.eye(4)
    bound = choose_bound(cfg0, seq, first, T0).bound
    runners, secs = {}, {r: [] for r in cfgs}
    for r, cfg in cfgs.items():
        t0 = time.perf_counter()
        runners[r] = SlamRunner(cfg, first.K, first.height, first.width, bound)
        runners[r].start(first, T0)
        secs[r].append(time.perf_counter() - t0)
    for i in range(1, len(seq)):
        frame = seq[i]
        for r, runner in runners.items():
            t0 = time.perf_counter()
            runner.step(frame)
            secs[r].append(time.perf_counter() - t0)
    a, b = np.asarray(secs["lrslam"]), np.asarray(secs["eslam"])
    params = {r: runner.parts.field.parameter_count()["total"] for r, runner in runners.items()}
    return {"frames": len(a), "lrslam_s_per_frame": float(a.mean()), "eslam_s_per_frame": float(b.mean()),
            "ratio_whole_run": float(a.sum() / b.sum()), "ratio_median_per_frame": float(np.median(a / b)),
            "params": params}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sequences", default="synthetic,tum,7scenes")
    ap.add_argument("--modes", default="field,frontend,fused")
    ap.add_argument("--frames", type=int, default=300, help="synthetic loop length")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="config override key=value")
    ap.add_argument("--paired", action="store_true", help="add the CP-SA / tri-plane paired whole-run ratio")
    ap.add_argument("--paired-frames", type=int, default=60)
    ap.add_argument("--paired-only", action="store_true", help="only the paired ratio")
    ap.add_argument("--rrd", type=Path, default=None, metavar="DIR",
                    help="run each mode again with the live viewer recording to DIR/<sequence>-<mode>.rrd")
    ap.add_argument("--out", type=Path, default=Path("runs/bench_fps"))
    a = ap.parse_args()
    a.out.mkdir(parents=True, exist_ok=True)
    overrides = list(a.overrides) + (["field.device=cuda"] if a.device == "cuda" else [])
    texts, results = [], {}
    for name in a.sequences.split(","):
        seq = sequence_path(name, a.frames, a.out)
        if seq is None:
            print(f"(no {name} data under {_data_root()}; skipped)", flush=True)
            continue
        preset, stride = PRESETS[a.device][name], STRIDES[name]
        rows = {}
        if not a.paired_only:
            for mode in a.modes.split(","):
                print(f"{name} {mode} ...", flush=True)
                rows[mode] = run_one(seq, preset, mode, stride, a.threads, overrides, a.out / f"{name}-{mode}")
                if a.rrd is not None:
                    print(f"{name} {mode} with the viewer ...", flush=True)
                    rrd = a.rrd / f"{name}-{mode}.rrd"
                    rows[f"{mode}+viewer"] = m = run_one(seq, preset, mode, stride, a.threads, overrides,
                                                         a.out / f"{name}-{mode}-viewer", rrd)
                    if rrd.is_file():
                        m["rrd_mb"] = rrd.stat().st_size / 1e6
            frames = next((m.get("n_frames") for m in rows.values() if "n_frames" in m), "?")
            texts.append(table(f"{name} ({preset}, {frames} frames, {a.threads} threads, {a.device})", rows))
            if a.rrd is not None:
                texts[-1] += "\nViewer cost (lrslam run --rrd, measured right after the run without it):\n\n" + \
                    "\n".join(viewer_cost(rows)) + "\n"
            print(texts[-1], flush=True)
        if a.paired:
            import torch

            torch.set_num_threads(a.threads)
            pr = paired_ratio(seq, preset, stride, a.paired_frames, overrides)
            rows["paired"] = pr
            line = (f"{name}: CP-SA / tri-plane whole-run s/frame, field mode, {pr['frames']} frames in lockstep "
                    f"in one process: {pr['lrslam_s_per_frame']:.3f} / {pr['eslam_s_per_frame']:.3f} = "
                    f"{pr['ratio_whole_run']:.2f} (median per-frame ratio {pr['ratio_median_per_frame']:.2f}); "
                    f"parameters {pr['params']['lrslam']:,} vs {pr['params']['eslam']:,}")
            texts.append(line + "\n")
            print(line, flush=True)
        results[name] = rows
    (a.out / "fps.md").write_text("\n".join(texts))
    (a.out / "fps.json").write_text(json.dumps(results, indent=1, default=str))
    print(f"tables in {a.out / 'fps.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
