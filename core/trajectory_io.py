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


def read_tum(path: str | Path, invalid: str = "raise") -> tuple[np.ndarray, np.ndarray]:
    """Read a TUM trajectory. Returns ``(timestamps (N,) float64 seconds, poses (N, 4, 4) T_w_c)``.

    A line with a non-finite pose value or a zero quaternion raises TrajectoryFormatError, or with
    ``invalid="nan"`` gives a NaN pose (ground truth missing at that time, as datasets mark lost tracking).
    The timestamp must always be finite."""
    if invalid not in ("raise", "nan"):
        raise ValueError(f"invalid must be 'raise' or 'nan', got {invalid!r}")
    path = Path(path)
    if not path.is_file():
        raise TrajectoryFormatError(f"{path}: trajectory file not found")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise TrajectoryFormatError(f"{path}: not a text (UTF-8) file") from None
    stamps, rows = [], []
    for lineno, line in enumerate(text.splitlines(), start=1):
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
        bad = not np.all(np.isfinite(vals)) or not np.linalg.norm(vals[4:8]) >= 1e-12
        if bad and (invalid == "raise" or not np.isfinite(vals[0])):
            raise TrajectoryFormatError(f"{path}:{lineno}: non-finite value or zero quaternion")
        stamps.append(vals[0])
        rows.append([np.nan] * 7 if bad else vals[1:])
    if not rows:
        raise TrajectoryFormatError(f"{path}: no poses in file")
    rows_a = np.asarray(rows, dtype=np.float64)
    ok = np.all(np.isfinite(rows_a), axis=1)
    poses = np.full((len(rows_a), 4, 4), np.nan)
    if ok.any():
        poses[ok] = pose_from_tum(rows_a[ok])
    return np.asarray(stamps, dtype=np.float64), poses


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
