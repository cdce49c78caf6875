"""The one registry of dataset readers (``name -> class``), layout auto-detection and :func:`open_sequence`.

Readers register themselves with ``@register("name")``; importing :mod:`lrslam.datasets` imports
every reader module, so the registry is complete whenever this module is used.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from lrslam.errors import DatasetError
from lrslam.datasets.base import Sequence
from lrslam.datasets.options import ReaderOptions

__all__ = ["READERS", "FILE_READERS", "register", "detect_layout", "open_sequence"]

READERS: dict[str, type[Sequence]] = {}
FILE_READERS: set[str] = set()  # readers whose sequence may be a single file (a ROS 1 .bag) instead of a folder


def register(name: str, *, files: bool = False) -> Callable[[type[Sequence]], type[Sequence]]:
    """Class decorator: add a :class:`Sequence` subclass to :data:`READERS` under ``name``; ``files``: the reader
    also opens a single file (its ``detect`` is then asked about files too)."""

    def deco(cls: type[Sequence]) -> type[Sequence]:
        if name in READERS and READERS[name] is not cls:
            raise ValueError(f"dataset reader {name!r} registered twice ({READERS[name].__name__}, {cls.__name__})")
        cls.name = name
        READERS[name] = cls
        if files:
            FILE_READERS.add(name)
        return cls

    return deco


def _existing(path: str | Path, reader: str | None = None) -> Path:
    """``path`` as a Path: a folder, or a file that a file reader (``reader``, or any when None) may open."""
    root = Path(path).expanduser()
    if not root.exists():
        raise DatasetError(f"{root}: dataset folder not found")
    if not root.is_dir():
        readers = [reader] if reader is not None else sorted(FILE_READERS)
        if not any(name in FILE_READERS for name in readers):
            raise DatasetError(f"{root}: not a folder")
    return root


def detect_layout(path: str | Path) -> str:
    """Name of the reader whose folder layout (or file type) ``path`` has; DatasetError when none or several match."""
    root = _existing(path)
    candidates = READERS if root.is_dir() else {name: READERS[name] for name in sorted(FILE_READERS)}
    matches = [name for name, cls in candidates.items() if cls.detect(root)]
    if not matches:
        hints = "; ".join(f"{name}: {cls.layout_hint}" for name, cls in candidates.items())
        if not root.is_dir():
            raise DatasetError(f"{root}: not a folder, nor a file a reader opens ({hints})")
        raise DatasetError(f"{root}: unknown dataset layout (expected one of {hints})")
    if len(matches) > 1:
        raise DatasetError(f"{root}: ambiguous dataset layout (matches {', '.join(matches)}); pass the reader "
                           f"name explicitly")
    return matches[0]


def open_sequence(path: str | Path, reader: str | None = None, options: ReaderOptions | None = None) -> Sequence:
    """Open the RGB-D sequence in folder ``path`` (or file, for readers registered with ``files=True``: a ROS 1
    ``.bag``) with the named reader (auto-detected when None).

    Raises DatasetError (one line, naming the file or folder) when the path is missing, its layout is
    unknown, the reader name is unknown, or the sequence is empty or malformed.
    """
    root = _existing(path, reader)
    name = reader if reader is not None else detect_layout(root)
    if name not in READERS:
        raise DatasetError(f"unknown dataset reader {name!r} (known: {', '.join(sorted(READERS))})")
    return READERS[name](root, options)
