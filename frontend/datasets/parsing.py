"""Small text parsers shared by the readers: matrix files, camera-to-world pose files, TUM file lists.

Each raises a one-line :class:`~lrslam.errors.DatasetError` naming the file (and line) on malformed input.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from lrslam.errors import DatasetError
from lrslam.geometry import is_valid_pose

__all__ = ["read_numbers", "read_matrix", "as_pose_or_nan", "read_file_list", "NAN_POSE"]

log = logging.getLogger(__name__)

NAN_POSE = np.full((4, 4), np.nan)


def read_numbers(path: Path) -> np.ndarray:
    """All whitespace/comma separated numbers of a text file (``#`` comment lines skipped) -> (N,) float64.
    ``inf``/``nan`` tokens are kept as such (ScanNet marks lost poses with ``-inf``)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    values: list[float] = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        try:
            values.extend(float(x) for x in line.replace(",", " ").split())
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: non-numeric value in {line!r}") from None
    return np.asarray(values, dtype=np.float64)


def read_matrix(path: Path, rows: int, cols: int) -> np.ndarray:
    """A text file holding exactly one ``rows x cols`` matrix -> float64 array."""
    v = read_numbers(path)
    if v.size != rows * cols:
        raise DatasetError(f"{path}: expected a {rows}x{cols} matrix ({rows * cols} numbers), got {v.size} numbers")
    return v.reshape(rows, cols)


def as_pose_or_nan(T: np.ndarray, source: str) -> np.ndarray:
    """A 4x4 camera-to-world matrix read from ``source`` -> itself when it is a finite rigid transform, else a
    NaN matrix (that frame has no ground truth). Non-finite matrices are normal in ScanNet (tracking lost) and
    pass silently; finite non-rigid ones are logged."""
    T = np.asarray(T, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(T)):
        return NAN_POSE.copy()
    if not is_valid_pose(T, tol=1e-3):
        log.warning("%s: ground-truth pose is not a rigid transform; treating this frame as having no ground "
                    "truth", source)
        return NAN_POSE.copy()
    return T


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """A TUM list file (``timestamp filename`` per line, ``#`` comments) -> ``(timestamps (N,) s, filenames)``.
    Extra columns after the filename are ignored."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    stamps: list[float] = []
    names: list[str] = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
        line = line.strip()
        if not line or line.startswith("#"):
            continue
        parts = line.replace(",", " ").split()
        if len(parts) < 2:
            raise DatasetError(f"{path}:{lineno}: expected 'timestamp filename', got {line!r}")
        try:
            t = float(parts[0])
        except ValueError:
            raise DatasetError(f"{path}:{lineno}: non-numeric timestamp {parts[0]!r}") from None
        if not np.isfinite(t):
            raise DatasetError(f"{path}:{lineno}: non-finite timestamp {parts[0]!r}")
        stamps.append(t)
        names.append(parts[1])
    return np.asarray(stamps, dtype=np.float64), names
