"""Read the config a user names on the command line: a preset name, or a YAML file (e.g. a run's own
``config.yaml``, whose record sections are dropped), plus ``--set key=value`` overrides, and build the
:class:`RunConfig`; keeps the preset names for the run's provenance record.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lrslam.errors import InputError
from lrslam.pipeline.config import RunConfig, build_config, is_config_file

__all__ = ["LoadedConfig", "load_run_config"]


@dataclass(frozen=True)
class LoadedConfig:
    """A validated run config and the presets it came from."""

    cfg: RunConfig
    presets: dict[str, str | None] = field(default_factory=dict)


def load_run_config(config: str | None = None, representation: str | None = None,
                    overrides: list[str] | None = None, mode: str | None = None) -> LoadedConfig:
    """Build the run config from ``config`` (preset name or YAML file), ``representation`` (preset name),
    ``overrides`` (``key.sub=value``) and ``mode``; InputError (one line, naming the file) on any bad part."""
    presets = {"config": config, "representation": representation}
    try:
        cfg = build_config(config, representation, overrides=list(overrides or []), mode=mode)
    except InputError as e:
        if config is not None and is_config_file(config) and not str(e).startswith("--config"):
            raise InputError(f"--config {config}: {e}") from None
        raise
    return LoadedConfig(cfg, presets)
