"""``lrslam view RUN_DIR``: replay a finished run folder into a Rerun viewer or an ``.rrd`` file.

What a run folder holds is drawn with the live viewer's entities (:mod:`lrslam.pipeline.viewer_stream`): the
camera along ``trajectory.txt`` frame by frame (time lines ``frame`` and ``time``), the trajectories
(``trajectory.txt`` as ``fused``, ``trajectory_seed.txt``, ``trajectory_frontend.txt``), the keyframes of
``keyframes.txt``, ``mesh.ply``, ``metrics.json`` as ``run/summary``; with the sequence of ``config.yaml``'s
provenance readable, also its ground truth (aligned as the ATE aligns), the running ATE ``metrics/ate_cm`` of the
trajectory's first frames, the camera's frustum and, with ``images``, every frame's RGB and depth. Loop edges,
graph corrections and field renders exist only while a run goes (``lrslam run --viewer`` / ``--rrd``).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from lrslam.errors import InputError
from lrslam.evaluation.ate import read_trajectory
from lrslam.pipeline.viewer import aligned_ground_truth, running_ate
from lrslam.pipeline.viewer_stream import RerunStream

__all__ = ["RunFolder", "read_run_folder", "replay"]

log = logging.getLogger(__name__)

_ATE_SAMPLES = 200   # running-ATE points drawn over the run (each is O(frames))


@dataclass(frozen=True)
class RunFolder:
    """What a finished run folder holds: ``timestamps`` (N,) s and ``poses`` (N, 4, 4) ``T_w_c`` of every frame;
    ``seed`` / ``frontend`` (N, 4, 4) or None; ``keyframe_ids`` (frame indices); ``mesh`` path or None;
    ``metrics`` (metrics.json) and ``record`` (config.yaml) or empty."""

    path: Path
    timestamps: np.ndarray
    poses: np.ndarray
    seed: np.ndarray | None
    frontend: np.ndarray | None
    keyframe_ids: tuple[int, ...]
    mesh: Path | None
    metrics: dict
    record: dict


def read_run_folder(run_dir: str | Path) -> RunFolder:
    """Read a finished run folder; InputError (one line) when it is not one (no ``trajectory.txt``)."""
    from lrslam.pipeline.run_folder import read_run_record

    d = Path(run_dir)
    if not d.is_dir():
        raise InputError(f"{d}: not a folder (give a run folder written by lrslam run)")
    if not (d / "trajectory.txt").is_file():
        raise InputError(f"{d}: not a finished lrslam run folder (no trajectory.txt)")
    ts, poses = read_trajectory(d / "trajectory.txt")
    extra = {n: read_trajectory(d / f"trajectory_{n}.txt")[1] if (d / f"trajectory_{n}.txt").is_file() else None
             for n in ("seed", "frontend")}
    kf_ids: tuple[int, ...] = ()
    if (d / "keyframes.txt").is_file():
        kf_ts, _ = read_trajectory(d / "keyframes.txt")
        idx = np.clip(np.searchsorted(ts, kf_ts), 0, len(ts) - 1)
        kf_ids = tuple(int(i) for i in idx[np.abs(ts[idx] - kf_ts) < 1e-6])
    try:
        metrics = json.loads((d / "metrics.json").read_text()) if (d / "metrics.json").is_file() else {}
    except (OSError, ValueError) as e:
        log.warning("%s: metrics.json unreadable (%s)", d, e)
        metrics = {}
    return RunFolder(d, ts, poses, extra["seed"], extra["frontend"], kf_ids,
                     d / "mesh.ply" if (d / "mesh.ply").is_file() else None, metrics, read_run_record(d) or {})


def _sequence(run: RunFolder):
    """The run's sequence (config.yaml's provenance and reader settings), or None when it cannot be opened."""
    from lrslam.datasets import ReaderOptions, open_sequence

    path = run.record.get("provenance", {}).get("sequence")
    dataset = run.record.get("dataset", {})
    if not path:
        return None
    try:
        return open_sequence(path, reader=dataset.get("reader"),
                             options=ReaderOptions.model_validate(dataset.get("options", {})))
    except Exception as e:  # noqa: BLE001 - a moved or changed dataset only costs the ground truth
        log.warning("sequence %s not readable (%s): no ground truth, no images", path, e)
        return None


def _ground_truth(seq) -> tuple[np.ndarray, np.ndarray] | None:
    from lrslam.evaluation.ate import ground_truth_samples

    try:
        return None if seq is None else ground_truth_samples(seq)
    except InputError as e:
        log.warning("ground truth not readable: %s", e)
        return None


def replay(run_dir: str | Path, stream: RerunStream, images: bool = False, image_scale: int = 2) -> RunFolder:
    """Draw the run folder ``run_dir`` into ``stream`` (see the module docstring); ``images``: every frame's RGB
    and depth too (``image[::image_scale, ::image_scale]``, read from the sequence). Returns what was read."""
    from lrslam.camera import strided_intrinsics

    # 1. Read the folder and, when it can be found, the sequence.
    run = read_run_folder(run_dir)
    seq = _sequence(run)
    gt = _ground_truth(seq)
    frames = images and seq is not None and len(seq) == len(run.timestamps)
    if images and not frames:
        log.warning("no images: the run's sequence is not readable or has another number of frames")
    if seq is not None:
        stream.pinhole("world/camera/image", strided_intrinsics(seq.K, image_scale), -(-seq.width // image_scale),
                       -(-seq.height // image_scale))
    # 2. What does not change: trajectories, keyframes, mesh, summary.
    _static(stream, run, gt)
    # 3. Frame by frame: the camera, the running ATE, the images.
    n = len(run.timestamps)
    ate_every = max(1, n // _ATE_SAMPLES)
    for i in range(n):
        stream.at(i, float(run.timestamps[i]))
        stream.camera(run.poses[i])
        if gt is not None and (i % ate_every == 0 or i == n - 1):
            ate = running_ate(run.timestamps[: i + 1], run.poses[: i + 1], gt)
            if ate is not None:
                stream.scalar("metrics/ate_cm", ate.rmse_cm)
        if frames:
            f = seq[i]
            stream.images("world/camera/image", f.rgb[::image_scale, ::image_scale],
                          f.depth[::image_scale, ::image_scale])
    return run


def _static(stream: RerunStream, run: RunFolder, gt) -> None:
    stream.trajectory("fused", run.poses[:, :3, 3], static=True)
    for name, poses in (("seed", run.seed), ("frontend", run.frontend)):
        if poses is not None:
            stream.trajectory(name, poses[:, :3, 3], static=True)
    if run.keyframe_ids:
        stream.keyframes(run.poses[list(run.keyframe_ids), :3, 3], run.keyframe_ids, static=True)
    ate = running_ate(run.timestamps, run.poses, gt)
    if ate is not None:
        stream.trajectory("gt", aligned_ground_truth(gt, run.timestamps, run.poses, ate.T_align), static=True)
    if run.mesh is not None:
        import trimesh

        try:
            stream.mesh(trimesh.load(run.mesh, force="mesh"), static=True)
        except Exception as e:  # noqa: BLE001 - a broken mesh file only costs the mesh
            log.warning("%s: not drawn (%s)", run.mesh, e)
    scalars = {k: v for k, v in run.metrics.items() if isinstance(v, (int, float, str)) and not isinstance(v, bool)}
    lines = [f"- {k}: {v}" for k, v in scalars.items()]
    stream.text("run/summary", f"### {run.path.name}: {len(run.poses)} frames, {len(run.keyframe_ids)} keyframes"
                "\n\n" + "\n".join(lines))
