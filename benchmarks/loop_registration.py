"""How good is a loop's registration? Every loop of a fused run, registered again under several settings from the
frontend's own prediction, against the ground truth's relative pose of the two keyframes.

Reads ``RUN_DIR/factors.npz`` (the loops the run kept) and ``RUN_DIR/trajectory_frontend.txt`` (the frontend's
trajectory: the prediction each registration starts from, drift included), opens ``SEQUENCE`` with the preset's
reader options, and registers each pair (new keyframe onto the earlier one, images down-sampled as the loop
closer stores them) with:

- ``preset``: the preset's own loop registration (``loop_closure.registration``);
- ``rgbd``: Open3D's hybrid RGB-D odometry (colour and depth), 30/20/10 iterations (the generic default);
- ``icp``: point-to-plane ICP on depth alone, voxels 8/4/2 cm, 10/10/5 iterations (the 7-Scenes presets');
- ``icp-fine``: the same at voxels 4/2/1 cm, 30/20/10 iterations.

The table: registrations passing the loop's gates, translation error RMS and median (cm), rotation error RMS
(deg), median fitness and inlier RMSE, and milliseconds per registration. Open3D runs on one thread (the same
result run to run). The error includes the ground truth's own: on TUM the rotation errors hardly depend on the
method (its time association on a fast-rotating camera), so compare methods, not absolute figures.

Usage::

    python benchmarks/loop_registration.py RUN_DIR SEQUENCE [-c PRESET] [--set key=value ...] [--max-pairs 60]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np


def _settings(preset_registration):
    fast = dict(method="icp", voxel_size=0.02, iterations=(10, 10, 5))
    return {"preset": preset_registration,
            "rgbd": preset_registration.model_copy(update=dict(method="rgbd", iterations=(30, 20, 10))),
            "icp": preset_registration.model_copy(update=fast),
            "icp-fine": preset_registration.model_copy(update=dict(method="icp", voxel_size=0.01,
                                                                   iterations=(30, 20, 10)))}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path, help="a fused run's output folder (factors.npz, trajectory_frontend.txt)")
    ap.add_argument("sequence", type=Path)
    ap.add_argument("-c", "--config", default=None, help="preset (default: the folder's default preset)")
    ap.add_argument("--set", dest="overrides", action="append", default=[])
    ap.add_argument("--max-pairs", type=int, default=60, help="at most this many loops, evenly spread")
    a = ap.parse_args()
    from lrslam.datasets.registry import open_sequence
    from lrslam.errors import InputError
    from lrslam.evaluation.ate import read_trajectory
    from lrslam.frontend.registration import register_rgbd
    from lrslam.frontend.rgbd_view import as_view
    from lrslam.geometry import inv, pose_error
    from lrslam.pipeline.config import build_config
    from lrslam.pipeline.config_source import default_preset
    from lrslam.pipeline.determinism import open3d_threads

    try:
        for name in ("factors.npz", "trajectory_frontend.txt"):
            if not (a.run / name).is_file():
                raise InputError(f"{a.run / name}: not found (a fused run's output folder is needed)")
        preset = a.config or default_preset(a.sequence)[0]
        cfg = build_config(preset, overrides=a.overrides)
        seq = open_sequence(a.sequence, cfg.dataset.reader, cfg.reader_options())
        gt = seq.gt_poses()
        if gt is None:
            raise InputError(f"{a.sequence}: no ground truth")
        factors = np.load(a.run / "factors.npz")
        _, frontend = read_trajectory(a.run / "trajectory_frontend.txt")
    except (InputError, OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    pairs = [(int(i), int(j)) for k, i, j in zip(factors["kind"], factors["i"], factors["j"]) if k == "loop"]
    if not pairs:
        print(f"{a.run}: the run kept no loop")
        return 0
    if len(pairs) > a.max_pairs:
        pairs = [pairs[k] for k in np.linspace(0, len(pairs) - 1, a.max_pairs).round().astype(int)]
    lc = cfg.loop_closure
    views: dict[int, object] = {}

    def view(i: int):
        if i not in views:
            views[i] = as_view(seq[i]).downsampled(lc.downsample)
        return views[i]

    settings = _settings(lc.registration)
    rows: dict[str, list[tuple]] = {name: [] for name in settings}
    with open3d_threads(True):
        for i, j in pairs:
            predicted, truth = inv(frontend[i]) @ frontend[j], inv(gt[i]) @ gt[j]
            for name, reg in settings.items():
                t0 = time.perf_counter()
                res = register_rgbd(view(j), view(i), predicted, reg, lc.gates)
                ms = 1000 * (time.perf_counter() - t0)
                view(i).cache.clear(), view(j).cache.clear()   # each setting pays for its own clouds / pyramids
                ok = lc.rejection(res) is None
                d_t, d_r = pose_error(truth, res.T_tgt_src)
                rows[name].append((ok, 100 * d_t, d_r, res.fitness, 100 * res.inlier_rmse, ms))
    print(f"{a.run}: {len(pairs)} loops of {a.sequence} ({preset}; preset's loop registration: "
          f"{lc.registration.method})\n")
    print("| setting | passed | error cm RMS | median | rotation deg RMS | fitness | inlier RMSE cm | ms |")
    print("|---|---|---|---|---|---|---|---|")
    for name, r in rows.items():
        v = np.array(r, dtype=float)
        ok = v[v[:, 0] > 0]
        if not len(ok):
            print(f"| {name} | 0 / {len(v)} | | | | | | {v[:, 5].mean():.0f} |")
            continue
        print(f"| {name} | {len(ok)} / {len(v)} | {np.sqrt(np.mean(ok[:, 1] ** 2)):.2f} | {np.median(ok[:, 1]):.2f} | "
              f"{np.sqrt(np.mean(ok[:, 2] ** 2)):.2f} | {np.median(ok[:, 3]):.3f} | {np.median(ok[:, 4]):.2f} | "
              f"{v[:, 5].mean():.0f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
