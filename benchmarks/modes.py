"""Field-only vs frontend-only vs graph-fused SLAM, side by side: ATE (cm), frames per second, keyframes, loops.

Two suites (run both by default):

- ``synthetic``: a generated loop sequence (>= 150 frames by default) with Kinect-like depth noise plus a
  constant Gaussian term (sigma = 1 cm), the acceptance setting of the fused-SLAM issue. The script checks
  fused < frontend, fused <= field and fused < 1.5 cm and prints PASS/FAIL for each (it does not hide a FAIL).
- ``real``: the real excerpts in ``../shared/data`` (TUM fr1/rpy, 7-Scenes redkitchen), when present.

Usage::

    python benchmarks/modes.py [--suite synthetic|real|all] [--frames 150] [--out runs/bench_modes]
                               [--max-frames N] [--set key=value ...] [--threads N]

Every run writes its own run folder (trajectory, mesh, metrics, plots) under ``--out``; the table is printed
and saved as ``--out/<suite>/comparison.md``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

MODES = ("field", "frontend", "fused")


def _configs(preset: str, overrides: list[str]) -> dict[str, dict]:
    from lrslam.pipeline.config import build_config

    return {m: build_config(preset, overrides=overrides, mode=m).model_dump(mode="json") for m in MODES}


def _print(title: str, results: dict) -> None:
    from lrslam.pipeline.batch import comparison_table

    print(f"\n## {title}\n")
    print(comparison_table(results))
    print("\n| sequence | mode | fps | " + " | ".join(["seed ATE cm", "remaps", "stage s/frame"]) + " |")
    print("|---|---|---|---|---|---|")
    for seq, by_mode in results.items():
        for mode, m in by_mode.items():
            if "error" in m:
                print(f"| {seq} | {mode} | error: {m['error']} | | | |")
                continue
            stages = ", ".join(f"{k} {v['per_frame_s']:.3f}" for k, v in m.get("timings", {}).items())
            seed = f"{m['seed_ate_rmse_cm']:.2f}" if "seed_ate_rmse_cm" in m else "-"
            print(f"| {seq} | {mode} | {1.0 / m['fpt_s']:.2f} | {seed} | {m.get('n_remaps', '-')} | {stages} |")


def synthetic_suite(out: Path, frames: int, overrides: list[str], seed: int) -> bool:
    """Generate the noisy loop, run the three modes, print the table and the acceptance checks."""
    from lrslam.frontend.synthetic.noise import NoiseConfig
    from lrslam.frontend.synthetic.writer import generate
    from lrslam.pipeline.batch import run_batch

    noise = NoiseConfig(depth_sigma=0.01, kinect=True, seed=seed)
    seq = generate(out / "data" / f"room_loop_{frames}", scene="room", trajectory="loop", n_frames=frames,
                   seed=seed, width=320, height=240, noise=noise)
    results = run_batch([seq], _configs("synthetic", overrides), out / "synthetic", progress=True)
    _print(f"synthetic loop, {frames} frames, depth noise: constant 1 cm + Kinect-like", results)
    m = next(iter(results.values()))
    ate = {k: v.get("ate_rmse_cm", float("inf")) for k, v in m.items()}
    checks = [("fused < frontend", ate["fused"] < ate["frontend"]),
              ("fused <= field", ate["fused"] <= ate["field"]),
              ("fused < 1.5 cm", ate["fused"] < 1.5)]
    print()
    for name, ok in checks:
        print(f"{'PASS' if ok else 'FAIL'}  {name}   (field {ate['field']:.2f}, frontend {ate['frontend']:.2f}, "
              f"fused {ate['fused']:.2f} cm)")
    return all(ok for _, ok in checks)


def real_suite(out: Path, overrides: list[str], max_frames: int | None, stride: int, only: str | None) -> None:
    """TUM fr1/rpy and 7-Scenes redkitchen from ../shared/data (skipped when absent)."""
    from lrslam.pipeline.batch import run_batch

    root = Path(os.environ.get("LRSLAM_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data"))
    jobs = [("tum-cpu", sorted(root.glob("tum*rpy*"))), ("7scenes-cpu", sorted(root.glob("7scenes*kitchen*")))]
    ov = list(overrides) + ([f"dataset.options.max_frames={max_frames}"] if max_frames else [])
    ov += [f"dataset.options.stride={stride}"] if stride > 1 else []
    for preset, paths in jobs:
        if only and not preset.startswith(only):
            continue
        if not paths:
            print(f"\n(no {preset} data under {root}; skipped)")
            continue
        results = run_batch(paths[:1], _configs(preset, ov), out / preset, progress=True)
        _print(f"{preset}: {paths[0].name}", results)


def main() -> int:
    from lrslam.logs import setup_console_logging

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--suite", choices=("synthetic", "real", "all"), default="all")
    ap.add_argument("--frames", type=int, default=150, help="synthetic loop length (>= 150 for the acceptance)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-frames", type=int, default=None, help="truncate the real sequences")
    ap.add_argument("--stride", type=int, default=1, help="use every n-th frame of the real sequences")
    ap.add_argument("--only", choices=("tum", "7scenes"), default=None, help="one real sequence only")
    ap.add_argument("--set", dest="overrides", action="append", default=[], help="config override key=value")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    ap.add_argument("--out", type=Path, default=Path("runs/bench_modes"))
    a = ap.parse_args()
    setup_console_logging()
    if a.threads:
        import torch

        torch.set_num_threads(a.threads)
    ok = True
    if a.suite in ("synthetic", "all"):
        ok = synthetic_suite(a.out, a.frames, a.overrides, a.seed)
    if a.suite in ("real", "all"):
        real_suite(a.out, a.overrides, a.max_frames, a.stride, a.only)
    (a.out / "args.json").write_text(json.dumps({k: str(v) for k, v in vars(a).items()}, indent=2))
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
