"""The run configuration: composes each component's own small config; nothing below reads it whole.

A run config is built from (later wins): component defaults (the paper's settings) <- a dataset preset
(``configs/dataset/<name>.yaml``) <- a representation preset (``configs/representation/<name>.yaml``, merged
into ``field.model``) <- a user YAML file <- ``key.sub=value`` overrides. The resolved config is saved with
every run (``config.yaml``) and reproduces it.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any, Literal

import yaml

from lrslam.config import StrictModel, deep_update, load_yaml
from lrslam.errors import InputError

__all__ = ["RunConfig", "ScheduleConfig", "OutputConfig", "DatasetSection", "build_config", "list_presets"]


class DatasetSection(StrictModel):
    """Which reader opens the sequence (None = auto-detect) and its options (stride, crop, resize ...)."""

    reader: str | None = None
    options: dict[str, Any] = {}


class ScheduleConfig(StrictModel):
    """When mapping, keyframing and re-mapping happen (ESLAM: map every 4 frames, keyframe every 5)."""

    map_every: int = 4                 # field mode: map every N frames (fused mode maps on keyframes)
    keyframe_every: int = 4            # field mode: every N-th frame becomes a keyframe (ESLAM rule)
    remap_iters: int = 30              # fused: field re-optimisation iterations after the graph moved keyframes
    remap_min_shift_m: float = 0.005   # fused: re-map only when some keyframe moved more than this
    remap_keyframes: int = 20          # fused: at most this many (most-moved) keyframes take part in re-mapping
    graph_every_keyframe: bool = True  # fused: optimise the graph at every keyframe (else only at loops / the end)


class OutputConfig(StrictModel):
    """What a run writes besides the trajectory and config."""

    mesh: bool = True
    mesh_resolution: float | None = None   # metres; None = the field's mesh config
    plots: bool = True
    evaluate: bool = True                  # ATE / mesh metrics when the sequence has ground truth
    eval_mesh_points: int = 100_000
    tsdf_voxel: float = 0.02               # frontend-mode reference mesh (Open3D TSDF), metres


class RunConfig(StrictModel):
    """Root config of ``lrslam run``. Component sections are validated by the components' own models."""

    mode: Literal["field", "frontend", "fused"] = "fused"
    dataset: DatasetSection = DatasetSection()
    bound: list[list[float]] | None = None              # (3,2) metres, world frame; None = from data / auto
    auto_bound_margin: float = 1.0                      # metres added around the first frame's points
    initial_pose: Literal["identity", "gt"] = "identity"  # "gt": first pose from GT (ESLAM protocol) when present
    field: dict[str, Any] = {}
    odometry: dict[str, Any] = {}
    keyframes: dict[str, Any] = {}
    loop_closure: dict[str, Any] = {}
    graph: dict[str, Any] = {}
    schedule: ScheduleConfig = ScheduleConfig()
    output: OutputConfig = OutputConfig()

    # -- component configs (each validated strictly by its own model) ---------------------------------------
    def field_config(self):
        from lrslam.field.slam import FieldSLAMConfig

        return FieldSLAMConfig.model_validate(self.field)

    def odometry_config(self):
        from lrslam.frontend.odometry import OdometryConfig

        return OdometryConfig.model_validate(self.odometry)

    def keyframe_config(self):
        from lrslam.frontend.keyframes import KeyframeConfig

        return KeyframeConfig.model_validate(self.keyframes)

    def loop_closure_config(self):
        from lrslam.frontend.loop_closure import LoopClosureConfig

        return LoopClosureConfig.model_validate(self.loop_closure)

    def graph_config(self):
        from lrslam.backend.graph import GraphConfig

        return GraphConfig.model_validate(self.graph)

    def reader_options(self):
        from lrslam.frontend.datasets import ReaderOptions

        return ReaderOptions.model_validate(self.dataset.options)

    def validate_components(self) -> "RunConfig":
        """Validate every component section now (so a typo fails before a long run starts)."""
        from pydantic import ValidationError

        for section, build in (("dataset.options", self.reader_options), ("odometry", self.odometry_config),
                               ("keyframes", self.keyframe_config), ("loop_closure", self.loop_closure_config),
                               ("graph", self.graph_config), ("field", self.field_config)):
            try:
                build()
            except ValidationError as e:
                raise InputError(_describe(e, section)) from None
        return self

    def resolved(self) -> dict[str, Any]:
        """Every setting with its effective value (component defaults filled in), for ``config.yaml``."""
        out = self.model_dump(mode="json")
        out["dataset"]["options"] = self.reader_options().model_dump(mode="json")
        out["field"] = self.field_config().model_dump(mode="json")
        out["odometry"] = self.odometry_config().model_dump(mode="json")
        out["keyframes"] = self.keyframe_config().model_dump(mode="json")
        out["loop_closure"] = self.loop_closure_config().model_dump(mode="json")
        out["graph"] = self.graph_config().model_dump(mode="json")
        return out


def _preset_dir(kind: str):
    return resources.files("lrslam.configs") / kind


def list_presets(kind: str) -> list[str]:
    """Names of the packaged presets of a kind ("dataset" or "representation")."""
    d = _preset_dir(kind)
    return sorted(p.name[:-5] for p in d.iterdir() if p.name.endswith(".yaml"))


def _load_preset(kind: str, name: str) -> dict[str, Any]:
    path = Path(name)
    if path.suffix in (".yaml", ".yml") and path.is_file():
        return load_yaml(path)
    f = _preset_dir(kind) / f"{name}.yaml"
    if not f.is_file():
        raise InputError(f"unknown {kind} preset {name!r}; known: {', '.join(list_presets(kind))} "
                         f"(or give a path to a .yaml file)")
    return yaml.safe_load(f.read_text()) or {}


def _parse_override(item: str) -> dict[str, Any]:
    if "=" not in item:
        raise InputError(f"override {item!r} must look like key.sub=value")
    key, value = item.split("=", 1)
    node: Any = yaml.safe_load(value)
    for part in reversed(key.strip().split(".")):
        node = {part: node}
    return node


def build_config(preset: str | None = None, representation: str | None = None, config_file: str | Path | None = None,
                 overrides: list[str] | None = None, **top_level: Any) -> RunConfig:
    """Compose a :class:`RunConfig` (see module docstring for the order) and validate every section.

    ``top_level`` sets root keys directly (e.g. ``mode="field"``); None values are ignored.
    Raises InputError with a one-line message on an unknown preset, key or bad value.
    """
    data: dict[str, Any] = {}
    if preset:
        data = deep_update(data, _load_preset("dataset", preset))
    if representation:
        data = deep_update(data, {"field": {"model": _load_preset("representation", representation)}})
    if config_file:
        try:
            data = deep_update(data, load_yaml(config_file))
        except (FileNotFoundError, ValueError) as e:
            raise InputError(str(e)) from None
    for item in overrides or []:
        data = deep_update(data, _parse_override(item))
    data = deep_update(data, {k: v for k, v in top_level.items() if v is not None})
    from pydantic import ValidationError

    try:
        cfg = RunConfig.model_validate(data)
    except ValidationError as e:
        raise InputError(_describe(e, "")) from None
    return cfg.validate_components()


def _describe(e, section: str) -> str:
    first = e.errors()[0]
    loc = ".".join([section] * bool(section) + [str(x) for x in first["loc"]])
    return f"invalid config at {loc or '<root>'}: {first['msg']} ({e.error_count()} error(s))"
