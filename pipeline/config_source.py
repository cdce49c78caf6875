"""Read the config a user names on the command line: a preset name, or a YAML file (e.g. a run's own
``config.yaml``), plus ``--set key=value`` overrides, and build the :class:`RunConfig`.

A run's ``config.yaml`` can be fed back as is: its record sections (``provenance``, and ``sequence`` from older
runs) are dropped. ``bound: auto`` (in the file or as ``--set bound=auto``) asks for the pre-pass bound of
:mod:`lrslam.pipeline.auto_bound`; it is returned as a flag beside the config.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from lrslam.errors import InputError
from lrslam.pipeline.config import RunConfig, build_config

__all__ = ["LoadedConfig", "load_run_config", "read_user_yaml", "RECORD_KEYS", "AUTO_BOUND"]

RECORD_KEYS = ("provenance", "sequence")  # what a run records in config.yaml besides the settings
AUTO_BOUND = "auto"


@dataclass(frozen=True)
class LoadedConfig:
    """A validated run config, whether the bound is estimated by the pre-pass, and the presets it came from."""

    cfg: RunConfig
    auto_bound: bool = False
    presets: dict[str, str | None] = field(default_factory=dict)


def read_user_yaml(path: str | Path, flag: str = "--config") -> dict[str, Any]:
    """A YAML mapping from a user's file; InputError naming the file when it is missing, a folder, unreadable,
    not UTF-8, not valid YAML or not a mapping. An empty file gives ``{}``."""
    path = Path(path)
    if not path.exists():
        raise InputError(f"{flag} {path}: config file not found")
    if path.is_dir():
        raise InputError(f"{flag} {path}: is a folder, not a YAML file")
    try:
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{flag} {path}: not a text (UTF-8) file") from None
    except OSError as e:
        raise InputError(f"{flag} {path}: cannot read: {e.strerror or e}") from None
    try:
        data = yaml.safe_load(text)
    except yaml.YAMLError as e:
        raise InputError(f"{flag} {path}: invalid YAML: {' '.join(str(e).split())}") from None
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise InputError(f"{flag} {path}: the top level must be a mapping (key: value), got a "
                         f"{type(data).__name__}")
    return data


def _is_file_name(config: str) -> bool:
    return Path(config).suffix in (".yaml", ".yml") or "/" in config or Path(config).exists()


def _split_bound_auto(overrides: list[str]) -> tuple[list[str], bool | None]:
    """Remove ``bound=auto`` overrides; returns the rest and the last say on auto (None: no bound override)."""
    rest, auto = [], None
    for item in overrides:
        key, _, value = item.partition("=")
        if key.strip() == "bound":
            auto = value.strip() == AUTO_BOUND
            if auto:
                continue
        rest.append(item)
    return rest, auto


def load_run_config(config: str | None = None, representation: str | None = None,
                    overrides: list[str] | None = None, mode: str | None = None) -> LoadedConfig:
    """Build the run config from ``config`` (preset name or YAML file), ``representation`` (preset name),
    ``overrides`` (``key.sub=value``) and ``mode``; InputError (one line) on any bad part."""
    overrides, auto_override = _split_bound_auto(list(overrides or []))
    presets = {"config": config, "representation": representation}
    if config is None or not _is_file_name(config):
        cfg = build_config(config, representation, overrides=overrides, mode=mode)
        return LoadedConfig(cfg, bool(auto_override), presets)
    data = read_user_yaml(config)
    for key in RECORD_KEYS:
        data.pop(key, None)
    auto = data.get("bound") == AUTO_BOUND
    if auto:
        data.pop("bound")
    if auto_override is not None:
        auto = auto_override
    with tempfile.TemporaryDirectory(prefix="lrslam-config-") as tmp:
        clean = Path(tmp) / "config.yaml"
        clean.write_text(yaml.safe_dump(data, sort_keys=False))
        try:
            cfg = build_config(str(clean), representation, overrides=overrides, mode=mode)
        except InputError as e:
            raise InputError(f"--config {config}: {e}") from None
    return LoadedConfig(cfg, auto, presets)
