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

A second table checks the run's own noise estimate (:class:`lrslam.backend.frame_fusion.NoiseEstimate`): per
keyframe gap it compares three estimates of the same motion (the field's, the frontend's chain of frame-to-frame
steps, the frontend's direct keyframe registration) without ground truth, taking the chain and the registration
as equally precise. The table gives each one's real error per axis over a gap (sigma, against ground truth), the
run's final estimate beside it, and the correlation of the chain's and the registration's errors (the estimate
cannot see what they share).

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


@dataclass
class _Gaps:
    """The noise estimate's inputs per keyframe gap: ``rows`` of (i, j, {source: T_i_j or None}); ``frame``: the
    index of the frame being processed (set by the caller)."""

    rows: list
    frame: int = 0
    last_keyframe: int = 0


def _record_gaps(runner, gaps: _Gaps) -> None:
    """Wrap the fusion's noise estimate so each keyframe gap's three motion estimates land in ``gaps``."""
    noise = runner.parts.fusion.noise
    add = noise.add

    def recorded(field, chain, registration, frames):
        gaps.rows.append((gaps.last_keyframe, gaps.frame,
                          {"field": field, "chain": chain, "registration": registration}))
        gaps.last_keyframe = gaps.frame
        return add(field, chain, registration, frames)

    noise.add = recorded


def _gap_table(gaps: _Gaps, gt: dict[int, np.ndarray], estimate: dict[str, np.ndarray]) -> list[str]:
    """Lines of the gap table: per source its real per-axis sigma over a gap (deg, cm) against ``gt``, the
    run's estimate (``estimate``: NoiseEstimate.variances()) and the chain-registration error correlation."""
    from lrslam.geometry import inv, log_se3

    errors: dict[str, list[np.ndarray]] = {"field": [], "chain": [], "registration": []}
    paired = []
    for i, j, est in gaps.rows:
        if i not in gt or j not in gt:
            continue
        true = inv(gt[i]) @ gt[j]
        e = {k: None if T is None else log_se3(inv(true) @ T) for k, T in est.items()}
        for k, x in e.items():
            if x is not None:
                errors[k].append(x)
        if e["chain"] is not None and e["registration"] is not None:
            paired.append((e["chain"][3:], e["registration"][3:]))
    sigma = lambda x: (np.degrees(np.sqrt(np.mean(x[:, :3] ** 2))), 100 * np.sqrt(np.mean(x[:, 3:] ** 2)))  # noqa: E731
    est = {"field": estimate["field"], "chain": estimate["odometry"], "registration": estimate["registration"]}
    lines = [f"{'gap source':16s} {'n':>5s} {'deg':>8s} {'cm':>8s}   {'run estimate deg':>16s} {'cm':>8s}"]
    for k, rows in errors.items():
        if not rows:
            continue
        d, c = sigma(np.stack(rows))
        lines.append(f"{k:16s} {len(rows):5d} {d:8.3f} {c:8.3f}   {np.degrees(np.sqrt(est[k][0])):16.3f} "
                     f"{100 * np.sqrt(est[k][1]):8.3f}")
    a, b = (np.concatenate(x) for x in zip(*paired)) if paired else (np.zeros(1), np.zeros(1))
    if a.std() > 0 and b.std() > 0:
        lines.append(f"chain-registration translation error correlation: {np.corrcoef(a, b)[0, 1]:.2f}")
    return lines


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sequence", type=Path)
    ap.add_argument("-c", "--config", default=None, help="preset (default: the folder's default preset)")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--threads", type=int, default=None)
    a = ap.parse_args()
    from lrslam.threads import flush_denormals, set_threads

    if a.threads:
        set_threads(a.threads)
    flush_denormals()   # as `lrslam run`: before any pool starts
    from lrslam.datasets.registry import open_sequence
    from lrslam.evaluation.factors import factor_chi2
    from lrslam.pipeline.config import build_config
    from lrslam.pipeline.config_source import default_preset
    from lrslam.pipeline.determinism import open3d_threads
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
    bound = choose_bound(cfg, seq, first, T0).bound
    runner = SlamRunner(cfg, first.K, first.height, first.width, bound)
    recorded: list[_Measurement] = []
    _instrument(runner, recorded)
    gaps = _Gaps([])
    if runner.parts.fusion is not None:
        _record_gaps(runner, gaps)
    with open3d_threads(cfg.deterministic):
        runner.start(first, T0)
        for k in range(1, n):
            gaps.frame = k
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
    if runner.parts.fusion is not None:
        print("\nper keyframe gap: real error per axis (sigma) against ground truth, and the run's noise estimate")
        print("\n".join(_gap_table(gaps, gt_by_index, runner.parts.fusion.noise.variances())))
    return 0


if __name__ == "__main__":
    sys.exit(main())
