"""TUM-format trajectory files: ``timestamp tx ty tz qx qy qz qw`` per line, ``#`` comments.

Poses are camera-to-world ``T_w_c`` (4x4 float64). Values are written with 17 significant digits, so a
write -> read round trip reproduces every timestamp bit for bit and every pose to float64 rounding of the
quaternion conversion (< 1e-15).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from lrslam.geometry import pose_from_tum, pose_to_tum

__all__ = ["read_tum", "write_tum", "TrajectoryFormatError"]


class TrajectoryFormatError(ValueError):
    """A trajectory file that cannot be parsed; the message names the file and line."""


def read_tum(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory. Returns ``(timestamps (N,) float64 seconds, poses (N, 4, 4) T_w_c)``."""
    path = Path(path)
    if not path.is_file():
        raise TrajectoryFormatError(f"{path}: trajectory file not found")
    stamps, rows = [], []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 8:
            raise TrajectoryFormatError(f"{path}:{lineno}: expected 8 values "
                                        f"(timestamp tx ty tz qx qy qz qw), got {len(parts)}")
        try:
            vals = [float(x) for x in parts]
        except ValueError:
            raise TrajectoryFormatError(f"{path}:{lineno}: non-numeric value in {line!r}") from None
        if not np.all(np.isfinite(vals)) or np.linalg.norm(vals[4:8]) < 1e-12:
            raise TrajectoryFormatError(f"{path}:{lineno}: non-finite value or zero quaternion")
        stamps.append(vals[0])
        rows.append(vals[1:])
    if not rows:
        raise TrajectoryFormatError(f"{path}: no poses in file")
    return np.asarray(stamps, dtype=np.float64), pose_from_tum(np.asarray(rows))


def write_tum(path: str | Path, timestamps: np.ndarray, poses: np.ndarray, header: str | None = None) -> Path:
    """Write ``timestamps (N,)`` and poses ``(N, 4, 4)`` as a TUM trajectory file; returns the path."""
    timestamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(timestamps) != len(poses):
        raise ValueError(f"{len(timestamps)} timestamps but {len(poses)} poses")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = pose_to_tum(poses) if len(poses) else np.zeros((0, 7))
    with path.open("w") as f:
        f.write(f"# {header}\n" if header else "# timestamp tx ty tz qx qy qz qw\n")
        for t, r in zip(timestamps, rows):
            f.write(" ".join(repr(float(x)) for x in (t, *r)) + "\n")
    return path
