"""Are the information matrices honest? Normalised residuals (chi2 / 6) of every measurement source against ground
truth, on any sequence with ground truth: 1 means the stated information matches the real error (see
:mod:`lrslam.evaluation.factors`; for a 6-dof Gaussian error the mean of chi2 / 6 is 1, its median 0.89).

Sources, from one fused run in this process (``lrslam run``'s parts, instrumented):

- ``odometry/frame``: the frontend's per-frame increment ``T_prev_c`` with its information, against the ground
  truth's relative pose of the two frames;
- ``field/frame``: the field's refined pose of a frame relative to the previous frame's pose in the trajectory
  (what the field adds to the trajectory's last pose), with the tracker's information;
- the graph's keyframe factors (``odometry``, ``field``, ``loop``), as they were added.

For each: n, mean and median of chi2 / 6, and the RMS error in cm and degrees. A source with mean chi2 / 6 far
above 1 is over-confident (the fusion trusts it too much), far below 1 under-confident.

Usage::

    python benchmarks/calibrate.py SEQUENCE [-c PRESET] [--set key=value ...] [--max-frames N] [--threads N]
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np


@dataclass(frozen=True)
class _Measurement:
    kind: str
    i: int
    j: int
    T_i_j: np.ndarray
    information: np.ndarray


def _instrument(runner, out: list[_Measurement]) -> None:
    """Wrap the runner's seeder and refiner so that each frame's odometry increment and field refinement (as a
    motion from the trajectory's last pose) are recorded into ``out``."""
    from lrslam.geometry import inv

    parts, traj = runner.parts, runner.traj
    seed_fn, refine_fn = parts.seeder.seed, parts.refiner.refine

    def seed(frame, trajectory):
        s = seed_fn(frame, trajectory)
        if s.odometry is not None and s.odometry.ok:
            out.append(_Measurement("odometry/frame", frame.index - 1, frame.index, s.odometry.T_prev_c,
                                    s.odometry.information))
        return s

    def refine(frame, s):
        r = refine_fn(frame, s)
        if r.ok and r.information is not None:
            out.append(_Measurement("field/frame", frame.index - 1, frame.index, inv(traj.pose(-1)) @ r.T_w_c,
                                    r.information))
        return r

    parts.seeder.seed, parts.refiner.refine = seed, refine


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("-c", "--config", default=None, help="preset (default: the folder's default preset)")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--threads", type=int, default=None)
    a = ap.parse_args()
    if a.threads:
        from lrslam.threads import set_threads

        set_threads(a.threads)
    from lrslam.datasets.registry import open_sequence
    from lrslam.evaluation.factors import factor_chi2
    from lrslam.pipeline.config import build_config
    from lrslam.pipeline.config_source import default_preset
    from lrslam.pipeline.run import choose_bound
    from lrslam.pipeline.runner import SlamRunner

    preset = a.config or default_preset(a.sequence, cuda=False)[0]
    cfg = build_config(preset, overrides=a.overrides, mode="fused")
    seq = open_sequence(a.sequence, cfg.dataset.reader, cfg.reader_options())
    n = len(seq) if a.max_frames is None else min(len(seq), a.max_frames)
    gt = seq.gt_poses()
    if gt is None:
        print(f"{a.sequence}: no ground truth; nothing to calibrate against")
        return 2
    first = seq[0]
    T0 = gt[0] if cfg.initial_pose == "gt" else np.eye(4)
    bound = choose_bound(cfg, seq, first, T0)[0]
    runner = SlamRunner(cfg, first.K, first.height, first.width, bound)
    recorded: list[_Measurement] = []
    _instrument(runner, recorded)
    runner.start(first, T0)
    for k in range(1, n):
        runner.step(seq[k])
        if k % 20 == 0:
            print(f"  frame {k}/{n}", file=sys.stderr, flush=True)
    result = runner.finish(mesh=False)
    gt_by_index = {k: gt[k] for k in range(n) if np.all(np.isfinite(gt[k]))}
    rows = factor_chi2(recorded, gt_by_index) | factor_chi2(result.factors, gt_by_index)
    print(f"\n{a.sequence.name} ({preset}{', ' + ' '.join(a.overrides) if a.overrides else ''}), {n} frames")
    print(f"{'source':16s} {'n':>5s} {'chi2/6 mean':>12s} {'median':>8s} {'rms cm':>8s} {'rms deg':>8s}")
    for kind, r in rows.items():
        print(f"{kind:16s} {r.n:5d} {r.mean:12.3f} {r.median:8.3f} {r.trans_rms_cm:8.3f} {r.rot_rms_deg:8.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
