"""Write synthetic sequences in the TUM RGB-D layout (read back by the ``synthetic`` dataset reader).

Layout of ``out_dir``::

    rgb.txt, depth.txt      "# ..." header lines, then "<timestamp> rgb/<timestamp>.png" (resp. depth/...)
    groundtruth.txt         TUM trajectory "timestamp tx ty tz qx qy qz qw", T_w_c (OpenCV camera axes)
    rgb/<timestamp>.png     8-bit RGB
    depth/<timestamp>.png   16-bit, metres * 5000 (0 = invalid), clipped at 65535 / 5000 = 13.107 m
    scene.yaml              generator, scene, seed, trajectory, n_frames, intrinsics {fx, fy, cx, cy, width,
                            height}, depth_scale, bound [[xmin, xmax], [ymin, ymax], [zmin, zmax]], noise {...}
    gt_mesh.ply             the exact scene mesh with vertex colours (world frame, metres)

Timestamps are ``round(i / fps, 6)`` seconds, written with 6 decimals, identical in all three text files.
"""

from __future__ import annotations

import logging
import shutil
import time
from pathlib import Path

import numpy as np

from lrslam.camera import check_intrinsics
from lrslam.config import load_yaml, save_yaml
from lrslam.errors import InputError
from lrslam.datasets.synth.noise import NoiseConfig, apply_noise
from lrslam.datasets.synth.render import Renderer, default_intrinsics
from lrslam.datasets.synth.scene import Scene, make_scene
from lrslam.datasets.synth.trajectories import make_trajectory
from lrslam.geometry import is_valid_pose
from lrslam.trajectory_io import write_tum

__all__ = ["GENERATOR", "DEPTH_SCALE", "write_sequence", "generate", "sequence_metadata"]

log = logging.getLogger(__name__)

GENERATOR = "lrslam-synth"
DEPTH_SCALE = 5000.0
_OUTPUTS = ("rgb", "depth", "rgb.txt", "depth.txt", "groundtruth.txt", "scene.yaml", "gt_mesh.ply")


def sequence_metadata(scene: Scene, trajectory: str, n_frames: int, K: np.ndarray, width: int, height: int,
                      noise: NoiseConfig, steps: tuple[float, float] = (0.01, 1.0)) -> dict:
    """The ``scene.yaml`` mapping (plain Python types); ``steps``: nominal motion per frame (m, deg), written
    only when it is not the default (older sequences stay identical)."""
    speed = {} if tuple(steps) == (0.01, 1.0) else {"step": {"m": float(steps[0]), "deg": float(steps[1])}}
    return speed | {
        "generator": GENERATOR,
        "scene": scene.name,
        "seed": int(scene.seed),
        "trajectory": trajectory,
        "n_frames": int(n_frames),
        "intrinsics": {"fx": float(K[0, 0]), "fy": float(K[1, 1]), "cx": float(K[0, 2]), "cy": float(K[1, 2]),
                       "width": int(width), "height": int(height)},
        "depth_scale": DEPTH_SCALE,
        "bound": [[float(a), float(b)] for a, b in np.asarray(scene.bound)],
        "noise": noise.model_dump(mode="json"),
    }


def _stamps(n_frames: int, fps: float) -> list[str]:
    return [f"{t:.6f}" for t in np.round(np.arange(n_frames) / fps, 6)]


def _prepare_dir(out_dir: Path) -> None:
    """Create out_dir, or clear a previous synthetic sequence in it; refuse other non-empty folders."""
    if out_dir.exists() and not out_dir.is_dir():
        raise InputError(f"{out_dir}: exists and is not a folder")
    if out_dir.is_dir() and any(out_dir.iterdir()):
        meta = out_dir / "scene.yaml"
        try:
            is_synth = meta.is_file() and load_yaml(meta).get("generator") == GENERATOR
        except ValueError:
            is_synth = False
        if not is_synth:
            raise InputError(f"{out_dir}: folder is not empty and holds no {GENERATOR} sequence; "
                             "choose an empty or new folder")
        for name in _OUTPUTS:
            p = out_dir / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    out_dir.mkdir(parents=True, exist_ok=True)


def _write_list(path: Path, kind: str, stamps: list[str]) -> None:
    lines = [f"# {'color' if kind == 'rgb' else 'depth'} images", f"# synthetic sequence ({GENERATOR})",
             "# timestamp filename"] + [f"{s} {kind}/{s}.png" for s in stamps]
    path.write_text("\n".join(lines) + "\n")


def write_sequence(out_dir: str | Path, scene: Scene, poses: np.ndarray, K: np.ndarray, width: int,
                   height: int, noise: NoiseConfig | None = None, fps: float = 30.0, trajectory: str = "custom",
                   antialias: int = 2, show_progress: bool = True, steps: tuple[float, float] = (0.01, 1.0)) -> Path:
    """Render ``poses`` (N, 4, 4) camera-to-world (OpenCV axes) of ``scene`` with intrinsics K (3, 3) at
    width x height and write the sequence (layout in the module docstring) to ``out_dir``; returns it.

    A folder that already holds a synthetic sequence is overwritten; any other non-empty folder is refused
    (InputError). ``noise`` defaults to noise free; ``trajectory`` and ``steps`` (nominal motion per frame, m and
    deg) are only recorded in scene.yaml.
    """
    import cv2
    from tqdm import tqdm

    out_dir = Path(out_dir)
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 3 or poses.shape[1:] != (4, 4) or len(poses) == 0:
        raise InputError(f"poses must have shape (N, 4, 4) with N >= 1, got {poses.shape}")
    if not all(is_valid_pose(T) for T in poses):
        raise InputError("poses must be finite rigid transforms")
    if not 0 < fps <= 1000:
        raise InputError(f"fps must lie in (0, 1000] (timestamps have 6 decimals), got {fps}")
    try:
        K = check_intrinsics(K, width, height)
    except ValueError as e:
        raise InputError(str(e)) from None
    noise = noise or NoiseConfig()
    _prepare_dir(out_dir)
    (out_dir / "rgb").mkdir()
    (out_dir / "depth").mkdir()

    # 1. ground truth: trajectory, mesh, metadata
    names = _stamps(len(poses), fps)
    stamps = np.array([float(t) for t in names])
    write_tum(out_dir / "groundtruth.txt", stamps, poses, header="timestamp tx ty tz qx qy qz qw (T_w_c)")
    scene.export_mesh(out_dir / "gt_mesh.ply")
    save_yaml(out_dir / "scene.yaml", sequence_metadata(scene, trajectory, len(poses), K, width, height, noise,
                                                            steps))

    # 2. frames: render, add noise, write 8-bit RGB and 16-bit depth PNGs
    renderer = Renderer(scene, K, width, height, antialias)
    render_s = 0.0
    for i, (T, name) in enumerate(tqdm(list(zip(poses, names)), desc=f"synth {out_dir.name}", unit="frame",
                                       disable=not show_progress)):
        t0 = time.perf_counter()
        rgb, depth = renderer.render(T)
        render_s += time.perf_counter() - t0
        rgb, depth = apply_noise(rgb, depth, noise, frame_index=i)
        depth_png = np.clip(np.rint(depth.astype(np.float64) * DEPTH_SCALE), 0, 65535).astype(np.uint16)
        if not (cv2.imwrite(str(out_dir / "rgb" / f"{name}.png"), rgb[..., ::-1])
                and cv2.imwrite(str(out_dir / "depth" / f"{name}.png"), depth_png)):
            raise OSError(f"{out_dir}: could not write frame {name}")
    _write_list(out_dir / "rgb.txt", "rgb", names)
    _write_list(out_dir / "depth.txt", "depth", names)
    log.info("wrote %d frames to %s (rendering %.1f ms/frame at %dx%d)", len(poses), out_dir,
             1000 * render_s / len(poses), width, height)
    return out_dir


def _complete(out_dir: Path, meta: dict, fps: float) -> bool:
    """True when out_dir holds a finished sequence whose scene.yaml equals ``meta``, at this fps."""
    try:
        if load_yaml(out_dir / "scene.yaml") != meta or not (out_dir / "gt_mesh.ply").is_file():
            return False
        lists = {k: [ln.split() for ln in (out_dir / f"{k}.txt").read_text().splitlines()
                     if ln.strip() and not ln.startswith("#")] for k in ("rgb", "depth")}
    except (OSError, ValueError):
        return False
    names = _stamps(meta["n_frames"], fps)
    return all([row[0] for row in rows] == names and all((out_dir / row[1]).is_file() for row in rows)
               for rows in lists.values())


def generate(out_dir: str | Path, scene: str = "room", trajectory: str = "circle", n_frames: int = 60,
             seed: int = 0, width: int = 320, height: int = 240, noise: NoiseConfig | None = None,
             show_progress: bool = True, fps: float = 30.0, reuse: bool = True, trans_step: float = 0.01,
             rot_step_deg: float = 1.0) -> Path:
    """Make scene + trajectory (same seed) and write the sequence to ``out_dir``; returns the path.
    ``trans_step`` (m), ``rot_step_deg``: the camera's nominal motion per frame
    (:func:`~lrslam.datasets.synth.trajectories.make_trajectory`; 0.06 and 2.4 make a fast camera).

    Intrinsics: :func:`~lrslam.datasets.synth.render.default_intrinsics` (fx = fy = 260 at 320 x 240).
    With ``reuse`` a folder that already holds the identical, complete sequence (same scene.yaml) is returned
    as is (demo re-runs, cached test fixtures).
    """
    out_dir = Path(out_dir)
    noise = noise or NoiseConfig()
    if n_frames < 2:
        raise InputError(f"a sequence needs at least 2 frames, got {n_frames}")
    if width < 16 or height < 16:
        raise InputError(f"image size must be at least 16 x 16, got {width} x {height}")
    sc = make_scene(scene, seed)
    poses = make_trajectory(trajectory, n_frames, sc.bound, seed, trans_step, rot_step_deg)
    K = default_intrinsics(width, height)
    meta = sequence_metadata(sc, trajectory, n_frames, K, width, height, noise, (trans_step, rot_step_deg))
    if reuse and _complete(out_dir, meta, fps):
        log.info("%s already holds this sequence; reusing it", out_dir)
        return out_dir
    return write_sequence(out_dir, sc, poses, K, width, height, noise, fps=fps, trajectory=trajectory, steps=(trans_step, rot_step_deg),
                          show_progress=show_progress)
