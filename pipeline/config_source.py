"""Read the config a user names on the command line: a preset name, or a YAML file (e.g. a run's own
``config.yaml``, whose record sections are dropped), plus ``--set key=value`` overrides, and build the
:class:`RunConfig`; keeps the preset names for the run's provenance record.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from lrslam.errors import InputError
from lrslam.pipeline.config import RunConfig, build_config, is_config_file

__all__ = ["LoadedConfig", "load_run_config", "default_preset"]

# Reader name -> packaged dataset preset (paper / GPU-sized); ``<name>-cpu`` is its CPU-sized variant.
_READER_PRESET = {"tum": "tum", "7scenes": "7scenes", "replica": "replica", "scannet": "scannet",
                  "synthetic": "synthetic", "rosbag": "rosbag"}


def default_preset(path, cuda: bool | None = None) -> tuple[str | None, str]:
    """The dataset preset for a sequence folder when no ``--config`` is given: the CPU-sized ``<dataset>-cpu``
    preset on a machine without CUDA (when one exists), the paper's settings with CUDA. Returns (preset or None,
    a one-line reason). Never raises for an unreadable folder (the run reports that itself)."""
    from lrslam.datasets import detect_layout
    from lrslam.pipeline.config import list_presets

    try:
        reader = detect_layout(path)
    except (InputError, OSError):
        return None, "no --config and the dataset layout is not recognised: built-in defaults"
    base = _READER_PRESET.get(reader)
    if base is None:
        return None, f"no --config and no preset for a {reader} sequence: built-in defaults"
    if cuda is None:
        import torch

        cuda = torch.cuda.is_available()
    cpu = f"{base}-cpu"
    if not cuda and cpu in list_presets("dataset"):
        return cpu, f"preset {cpu} (no --config; {reader} sequence on a CPU: the CPU-sized settings)"
    where = "CUDA" if cuda else "a CPU (no CPU-sized variant exists)"
    return base, f"preset {base} (no --config; {reader} sequence on {where}: the paper's settings)"


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
