"""Small parsers shared by the readers: matrix files, camera-to-world pose files, TUM file lists, numbered
image files, YAML files checked by a pydantic model.

Each raises a one-line :class:`~lrslam.errors.DatasetError` naming the file (and line or key) on malformed input.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

import numpy as np
from pydantic import BaseModel, ValidationError

from lrslam.config import load_yaml
from lrslam.errors import DatasetError, InputError
from lrslam.geometry import is_valid_pose

__all__ = ["read_numbers", "read_matrix", "as_pose_or_nan", "read_pose_files", "read_file_list", "numbered_files",
           "paired_frame_numbers", "read_yaml_model", "NAN_POSE"]

log = logging.getLogger(__name__)

M = TypeVar("M", bound=BaseModel)

NAN_POSE = np.full((4, 4), np.nan)


def _read_text(path: Path) -> str:
    try:
        return path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: not a text (UTF-8) file") from None
    except OSError as e:
        raise DatasetError(f"{path}: cannot read: {e.strerror or e}") from None


def read_numbers(path: Path) -> np.ndarray:
    """All whitespace/comma separated numbers of a text file (``#`` comment lines skipped) -> (N,) float64.
    ``inf``/``nan`` tokens are kept as such (ScanNet marks lost poses with ``-inf``)."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    values: list[float] = []
    for lineno, line in enumerate(_read_text(path).splitlines(), start=1):
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
    """A 4x4 camera-to-world matrix read from ``source`` -> a rigid transform, or a NaN matrix (no ground truth
    for that frame).

    Non-finite matrices are normal in ScanNet (tracking lost) and pass silently. Rotations within 1e-3 of
    orthonormal are projected onto SO(3) (SVD; 7-Scenes stores its poses with errors of ~2e-4), so every
    returned pose passes :func:`lrslam.geometry.is_valid_pose`; matrices further off are logged and dropped.
    """
    T = np.asarray(T, dtype=np.float64).reshape(4, 4)
    if not np.all(np.isfinite(T)):
        return NAN_POSE.copy()
    if not is_valid_pose(T, tol=1e-3):
        log.warning("%s: ground-truth pose is not a rigid transform; treating this frame as having no ground "
                    "truth", source)
        return NAN_POSE.copy()
    U, _, Vt = np.linalg.svd(T[:3, :3])
    out = T.copy()
    out[:3, :3] = U @ Vt
    out[3] = (0.0, 0.0, 0.0, 1.0)
    return out


def read_pose_files(paths: list[Path]) -> np.ndarray | None:
    """One 4x4 camera-to-world text file per frame -> (N, 4, 4) float64, NaN rows where a file is missing or
    its pose invalid; None when none of the files exists (the dataset has no ground truth)."""
    exists = [p.is_file() for p in paths]
    if not any(exists):
        return None
    if not all(exists):
        missing = [p for p, e in zip(paths, exists) if not e]
        log.warning("%d of %d pose files are missing (first: %s); those frames have no ground truth",
                    len(missing), len(paths), missing[0])
    poses = np.full((len(paths), 4, 4), np.nan)
    for k, (p, e) in enumerate(zip(paths, exists)):
        if e:
            poses[k] = as_pose_or_nan(read_matrix(p, 4, 4), str(p))
    return poses


def numbered_files(folder: Path, pattern: str) -> dict[int, Path]:
    """Files of ``folder`` whose whole name matches ``pattern`` (a regex whose first group is the frame
    number) -> ``{frame number: path}``. DatasetError when two files share a number."""
    rx = re.compile(pattern)
    out: dict[int, Path] = {}
    for p in Path(folder).iterdir():
        m = rx.fullmatch(p.name)
        if m:
            i = int(m.group(1))
            if i in out:
                raise DatasetError(f"{folder}: two files for frame {i}: {out[i].name} and {p.name}")
            out[i] = p
    return out


def paired_frame_numbers(colors: dict[int, Path], depths: dict[int, Path], depth_file: Callable[[int], Path],
                         depth_folder: Path, logger: logging.Logger) -> list[int]:
    """The frame numbers of ``colors`` (sorted), each of which must have a depth image in ``depths`` (both from
    :func:`numbered_files`): DatasetError naming ``depth_file(n)`` of the first missing one. Depth images without
    colour are ignored (logged on ``logger``, the reader's, naming ``depth_folder``)."""
    idx = sorted(colors)
    missing = [i for i in idx if i not in depths]
    if missing:
        raise DatasetError(f"{depth_file(missing[0])}: image file not found ({len(missing)} of {len(idx)} colour "
                           "frames have no depth image)")
    if len(depths) > len(idx):
        logger.warning("%s: %d depth images have no colour image and are ignored", depth_folder, len(depths) - len(idx))
    return idx


def read_yaml_model(path: Path, model: type[M], what: str, expected: str = "") -> M:
    """A YAML mapping file validated by the pydantic ``model``. DatasetError naming the file and, for a bad value,
    the key (``what`` when the problem is not one key's) and ``expected`` (appended, e.g. `` (expected ...)``)."""
    try:
        data = load_yaml(path)
    except InputError as e:  # load_yaml's messages name the file
        raise DatasetError(str(e)) from None
    try:
        return model.model_validate(data)
    except ValidationError as e:
        err = e.errors()[0]
        where = ".".join(str(x) for x in err["loc"]) or what
        raise DatasetError(f"{path}: {where}: {err['msg']}{expected}") from None


def read_file_list(path: Path) -> tuple[np.ndarray, list[str]]:
    """A TUM list file (``timestamp filename`` per line, ``#`` comments) -> ``(timestamps (N,) s, filenames)``.
    Extra columns after the filename are ignored."""
    path = Path(path)
    if not path.is_file():
        raise DatasetError(f"{path}: file not found")
    stamps: list[float] = []
    names: list[str] = []
    for lineno, line in enumerate(_read_text(path).splitlines(), start=1):
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
