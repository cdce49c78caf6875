"""Small helpers shared by every component config: strict pydantic models and YAML I/O.

Each component defines its own small config (a :class:`StrictModel`) next to its code; a run's root config
only composes them. Unknown keys are rejected, so a typo in a YAML preset is an error, not a silent default.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict

from lrslam.errors import InputError

__all__ = ["StrictModel", "load_yaml", "save_yaml", "deep_update"]

M = TypeVar("M", bound=BaseModel)


class StrictModel(BaseModel):
    """Frozen pydantic model that rejects unknown keys."""

    model_config = ConfigDict(extra="forbid", frozen=True)


def load_yaml(path: str | Path, label: str | None = None) -> dict[str, Any]:
    """A YAML mapping from a file (an empty file gives ``{}``). InputError, one line starting with ``label``
    (default: the path), when the file is missing, a folder, unreadable, not UTF-8, not valid YAML or not a
    mapping."""
    path = Path(path)
    where = label or str(path)
    if not path.exists():
        raise InputError(f"{where}: config file not found")
    if path.is_dir():
        raise InputError(f"{where}: is a folder, not a YAML file")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise InputError(f"{where}: not a text (UTF-8) file") from None
    except OSError as e:
        raise InputError(f"{where}: cannot read: {e.strerror or e}") from None
    except yaml.YAMLError as e:
        raise InputError(f"{where}: invalid YAML: {' '.join(str(e).split())}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(f"{where}: the top level must be a mapping (key: value), got a {type(data).__name__}")
    return data


def save_yaml(path: str | Path, data: dict[str, Any] | BaseModel) -> Path:
    """Write a mapping (or a pydantic model, as JSON-compatible data) to YAML; returns the path."""
    if isinstance(data, BaseModel):
        data = data.model_dump(mode="json")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def deep_update(base: dict[str, Any], override: dict[str, Any]) -> dict[str, Any]:
    """Recursively merge ``override`` into a copy of ``base`` (mappings merge, everything else replaces)."""
    out = dict(base)
    for k, v in override.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = deep_update(out[k], v)
        else:
            out[k] = v
    return out
