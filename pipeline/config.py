"""The run configuration: composes each component's own small config; nothing below reads it whole.

A run config is built from (later wins): component defaults (the paper's settings) <- the mode's preset
(:data:`MODE_PRESETS`: which parts the runner is built from, and the settings that go with them) <- a dataset
preset (``configs/dataset/<name>.yaml``) <- that preset's settings for the mode (its ``modes: {<mode>: ...}``
section, e.g. fewer tracking iterations where the odometry seeds) <- a representation preset (``configs/representation/<name>.yaml``,
merged into ``field.model``) <- a user YAML file <- ``key.sub=value`` overrides. Every section is typed by its
component's own model (validated once, here); the resolved config is a plain dump, saved with every run
(``config.yaml``), and reproduces it.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path
from typing import Any, Literal

import yaml
from pydantic import BaseModel, Field, model_validator

from lrslam.config import StrictModel, deep_update, load_yaml
from lrslam.errors import InputError

from lrslam.backend.graph import GraphConfig
from lrslam.backend.loop_closure import LoopClosureConfig
from lrslam.backend.policy import BackendConfig
from lrslam.backend.smoother import SmoothingConfig
from lrslam.field.config import FieldSLAMConfig
from lrslam.frontend.keyframes import KeyframeConfig
from lrslam.backend.frame_fusion import FusionConfig
from lrslam.frontend.odometry import OdometryConfig

__all__ = ["RunConfig", "ScheduleConfig", "OutputConfig", "DatasetSection", "PartsConfig",
           "MODE_PRESETS", "RECORD_KEYS", "build_config", "list_presets", "read_user_yaml",
           "is_config_file"]


class DatasetSection(StrictModel):
    """Which reader opens the sequence (None = auto-detect) and its options (stride, crop, resize ...)."""

    reader: str | None = None
    options: dict[str, Any] = {}


class ScheduleConfig(StrictModel):
    """When mapping happens (ESLAM: every 4 frames and at every keyframe; keyframes: ``keyframes.every_n``), how
    the constant-velocity seeder extrapolates, and when the field arbitrates between the odometry's seed and the
    constant-velocity guess."""

    map_every: int = Field(4, gt=0, description="map every N frames (and at every keyframe)")
    velocity_model: Literal["linear", "se3"] = Field(
        "linear", description="constant-velocity seeder: ESLAM's linear extrapolation of (t, q), or the last "
        "relative motion repeated on SE(3)")
    seed_arbitration: bool = Field(
        True, description="odometry seeder with a field refiner: when the odometry's seed and the constant-velocity "
        "guess disagree by more than seed_disagreement_m or _deg, the field starts from the one whose tracking "
        "loss is lower on the same rays (a broken odometry step no longer drags the refinement out of its basin)")
    seed_disagreement_m: float = Field(0.02, ge=0, description="metres, see seed_arbitration")
    seed_disagreement_deg: float = Field(2.0, ge=0, description="degrees, see seed_arbitration")
    background_mapping: bool = Field(
        False, description="map in a worker thread beside tracking (ESLAM runs its mapper beside its tracker): "
        "frames between two mapping rounds are tracked on a frozen copy of the field from before the running round, "
        "each thread gets half the torch threads; keyframes with a pose graph wait for their round (the graph and "
        "re-maps need the mapped poses), and so does a frame after fast motion (background_wait_*). Repeats bit for "
        "bit like the serial schedule")
    background_wait_m: float = Field(
        0.03, ge=0, description="background mapping: when the last frame-to-frame motion exceeded this (metres) or "
        "background_wait_deg, the next frame waits for the running round and tracks on the mapped field (a fast "
        "camera leaves the lagging map behind: TUM fr1/rpy at every 3rd frame, field mode, 3 seeds: 27 cm without "
        "the wait)")
    background_wait_deg: float = Field(4.0, ge=0, description="degrees, see background_wait_m")
    uncertain_seed_effort: bool = Field(
        False, description="odometry seeder with a field: a frame whose seed is uncertain (the odometry registered "
        "it weakly, below odometry.gates.trusted_fitness, or failed, or it disagrees with the constant-velocity "
        "guess beyond seed_disagreement_*: pipeline.contracts.Seed.uncertain) is tracked with every iteration (the "
        "early stop assumes a good seed) and mapped, as a keyframe is. Fused, deterministic seed 0: 7-Scenes every "
        "12th frame, where the frontend loses track, 8.33 -> 5.53 cm; every 4th 2.35 -> 2.27; TUM excerpt 2.03 -> "
        "2.13 (3 seeds 2.08 -> 2.13); synthetic loop and orbit unchanged (docs/BENCHMARKS.md section 23)")
    interpolate_non_keyframes: bool = Field(
        True, description="a frame between two keyframes follows both keyframes' corrections, blended by its "
        "position in the gap (off: the keyframe before it only, rigidly); pipeline/trajectory.py")


class PartsConfig(StrictModel):
    """The parts the runner is built from (:func:`lrslam.pipeline.parts.build_parts`); the modes are presets.

    seeder: ``constant_velocity`` (ESLAM) or ``odometry`` (the frontend). refiner: ``field`` (LRSLAM tracking,
    which also builds the field and its mapper) or ``none``. keyframer: ``every_n`` (ESLAM: every
    ``keyframes.every_n``-th frame) or ``policy`` (motion / overlap, a keyframe at least every
    ``keyframes.every_n`` frames). backend: ``graph`` (GTSAM pose graph + loop closure) or ``none``.
    Combinations that cannot work are rejected when the config is built (:meth:`RunConfig._check_parts`)."""

    seeder: Literal["constant_velocity", "odometry"] = "odometry"
    refiner: Literal["field", "none"] = "field"
    keyframer: Literal["every_n", "policy"] = "policy"
    backend: Literal["graph", "none"] = "graph"


class OutputConfig(StrictModel):
    """What a run writes besides the trajectory and config."""

    mesh: bool = True
    mesh_resolution: float | None = None   # metres; None = the field's mesh config
    plots: bool = True
    evaluate: bool = True                  # ATE / mesh metrics when the sequence has ground truth
    eval_mesh_points: int = 100_000
    tsdf_voxel: float = Field(0.02, gt=0)  # frontend-mode reference mesh (Open3D TSDF), metres
    partial_every: int = Field(10, ge=1)   # frames between atomic saves of trajectory_partial.txt
    # keyframes between atomic checkpoints (checkpoint.pt: everything ``lrslam run --resume`` needs); 0 = none
    checkpoint_every: int = Field(10, ge=0)


class RunConfig(StrictModel):
    """Root config of ``lrslam run``: every section typed by its component's own model.

    ``seed``: the run's seed: Python's, numpy's and torch's global RNGs at the start of the run, and the field's
    own generators (``field.seed``: pixel sampling, jitter, window selection, initial features). The two keys
    are one setting: given one, the other follows; given both, they must agree (InputError otherwise).
    ``deterministic``: run Open3D (the frontend's registrations) on one thread: its multi-threaded reductions sum
    in a schedule-dependent order, and a registration gate decided on the edge turns that into centimetres.
    With it and a fixed seed, runs on the CPU repeat bit for bit (see :mod:`lrslam.pipeline.determinism`)."""

    mode: Literal["field", "frontend", "fused"] = "fused"
    seed: int = Field(0, ge=0)
    deterministic: bool = False
    parts: PartsConfig = PartsConfig()
    dataset: DatasetSection = DatasetSection()
    # The field's scene bound, (3, 2) metres in the world frame. None (the default: the bound comes from the data):
    # the sequence's own bound when it states one (a synthetic scene.yaml), else an odometry pre-pass over the
    # whole sequence (lrslam run with a field), else the first frame's points + auto_bound_margin (a streaming run,
    # or a run without a field, which needs none); "auto": the pre-pass even where the sequence states a bound; a
    # list: given (a scene preset, or the user), checked frame by frame (a warning when the camera's view leaves it)
    bound: list[list[float]] | Literal["auto"] | None = None
    # metres added around the data's extent (the pre-pass's points and camera centres, or the first frame's points)
    auto_bound_margin: float = Field(1.0, ge=0)
    initial_pose: Literal["identity", "gt"] = "identity"  # "gt": first pose from GT (ESLAM protocol) when present
    field: FieldSLAMConfig = FieldSLAMConfig()
    odometry: OdometryConfig = OdometryConfig()
    keyframes: KeyframeConfig = KeyframeConfig()
    loop_closure: LoopClosureConfig = LoopClosureConfig()
    graph: GraphConfig = GraphConfig()
    backend: BackendConfig = BackendConfig()
    fusion: FusionConfig = FusionConfig()
    schedule: ScheduleConfig = ScheduleConfig()
    smoothing: SmoothingConfig = SmoothingConfig()
    output: OutputConfig = OutputConfig()

    @model_validator(mode="before")
    @classmethod
    def _one_seed(cls, data: Any) -> Any:
        """``seed`` and ``field.seed`` are one setting (see the class docstring)."""
        if not isinstance(data, dict):
            return data
        field = data.get("field")
        f_seed = field.get("seed") if isinstance(field, dict) else getattr(field, "seed", None)
        seed = data.get("seed")
        if seed is not None and f_seed is not None and seed != f_seed:
            raise ValueError(f"seed {seed} and field.seed {f_seed} disagree (one setting: give seed only)")
        if seed is None and f_seed is not None:
            return {**data, "seed": f_seed}
        if seed is not None and f_seed is None:
            if isinstance(field, BaseModel):
                return {**data, "field": field.model_copy(update={"seed": seed})}
            return {**data, "field": {**(field or {}), "seed": seed}}
        return data

    @model_validator(mode="after")
    def _check_parts(self) -> "RunConfig":
        """Part / option combinations that cannot work, rejected here (one line naming both keys) instead of
        failing, or silently doing nothing, in the middle of a run."""
        p, factors = self.parts, self.backend.factors
        if p.backend == "graph" and self.graph.optimiser == "isam2":
            raise ValueError("graph.optimiser=isam2 does not work with parts.backend=graph (the backend re-states "
                             "its field factors before every solve): use graph.optimiser=lm or gnc")
        if p.backend == "graph" and p.seeder == "constant_velocity" and "odometry" in factors:
            raise ValueError("backend.factors has 'odometry' but parts.seeder=constant_velocity runs no frontend "
                             "odometry: use parts.seeder=odometry or drop the factor")
        if p.backend == "graph" and p.refiner == "none" and "field" in factors:
            raise ValueError("backend.factors has 'field' but parts.refiner=none builds no field: use "
                             "parts.refiner=field or drop the factor")
        return self

    def mode_settings(self) -> str:
        """One line: the mode, its parts and the settings that say how hard it works (printed when a run starts,
        kept in ``metrics.json``)."""
        p, s = self.parts, self.schedule
        out = [f"mode {self.mode} (seeder {p.seeder}, refiner {p.refiner}, keyframer {p.keyframer}, backend "
               f"{p.backend})"]
        if p.refiner == "field":
            t, m = self.field.tracking, self.field.mapping
            out.append(f"tracking {t.iters} it x {t.n_rays} rays, mapping {m.iters} it x {m.n_rays} rays every "
                       f"{s.map_every} frames{' in the background' if s.background_mapping else ''} "
                       f"(device {self.field.device})")
        if p.backend == "graph":
            out.append(f"graph solved {self.backend.optimise.replace('_', ' ')}")
        if self.fusion.per_frame and p.refiner == "field" and p.seeder == "odometry":
            out.append("odometry and field fused at every frame by their measured noise")
        if self.smoothing.enabled:
            out.append("trajectory smoothed at the end")
        size = self.reader_options().resize
        out.append("images " + (f"resized to {size[0]}x{size[1]}" if size else "at their own size"))
        return "; ".join(out)

    def reader_options(self):
        from lrslam.datasets import ReaderOptions

        return ReaderOptions.model_validate(self.dataset.options)

    def resolved(self) -> dict[str, Any]:
        """Every setting with its effective value, for ``config.yaml`` (a plain dump; reader options filled in)."""
        out = self.model_dump(mode="json")
        out["dataset"]["options"] = self.reader_options().model_dump(mode="json")
        return out


# The modes are presets of the runner factory: which parts, and the settings that belong to them.
MODE_PRESETS: dict[str, dict[str, Any]] = {
    "field": {"parts": {"seeder": "constant_velocity", "refiner": "field", "keyframer": "every_n",
                        "backend": "none"},
              "keyframes": {"every_n": 4}},   # ESLAM: every 4th frame
    "frontend": {"parts": {"seeder": "odometry", "refiner": "none", "keyframer": "policy", "backend": "none"}},
    "fused": {"parts": {"seeder": "odometry", "refiner": "field", "keyframer": "policy", "backend": "graph"},
              # the odometry seed is a measurement, not a guess: keep the field's refinement only where it is better
              # (or at most 5 % worse on the same rays: gains within the loss noise still anchor the pose to the map)
              "field": {"tracking": {"accept_if_better": True, "accept_tolerance": 0.05}},
              # every frame: the odometry's seed and the field's pose weighed by their measured noise
              # (lrslam.backend.frame_fusion); at the end, one graph solve over every keyframe with the factors
              # calibrated by that noise, where the field was gated out (backend.final_refine_when)
              "fusion": {"per_frame": True},
              "backend": {"final_refine": True}},
}


def _preset_dir(kind: str):
    return resources.files("lrslam.configs") / kind


def list_presets(kind: str) -> list[str]:
    """Names of the packaged presets of a kind ("dataset" or "representation")."""
    d = _preset_dir(kind)
    return sorted(p.name[:-5] for p in d.iterdir() if p.name.endswith(".yaml"))


# What a run records in its config.yaml besides the settings (dropped when the file is fed back with --config).
RECORD_KEYS = ("provenance", "sequence")


def read_user_yaml(path: str | Path, flag: str = "--config") -> dict[str, Any]:
    """A YAML mapping from a user's file, its record sections (:data:`RECORD_KEYS`) dropped; InputError naming
    the flag and the file when it is missing, a folder, unreadable, not UTF-8, not valid YAML or not a mapping
    (:func:`lrslam.config.load_yaml`). An empty file gives ``{}``."""
    data = load_yaml(path, f"{flag} {path}")
    return {k: v for k, v in data.items() if k not in RECORD_KEYS}


def is_config_file(name: str) -> bool:
    """Whether a ``--config`` value names a file (rather than a packaged preset)."""
    return Path(name).suffix in (".yaml", ".yml") or "/" in name or Path(name).exists()


def _load_preset(kind: str, name: str, _seen: tuple[str, ...] = ()) -> dict[str, Any]:
    """A preset's settings; a dataset preset's ``base: <preset>`` is loaded first and the preset's own keys merged
    over it (a scene preset states only what differs from its base, as ESLAM's ``inherit_from``)."""
    if kind == "dataset" and is_config_file(name):
        data = read_user_yaml(name)
    else:
        f = _preset_dir(kind) / f"{name}.yaml"
        if not f.is_file():
            raise InputError(f"unknown {kind} preset {name!r}; known: {', '.join(list_presets(kind))} "
                             f"(or give a path to a .yaml file)")
        data = load_yaml(f)
    base = data.pop("base", None) if kind == "dataset" else None
    if base is None:
        return data
    if not isinstance(base, str) or base in _seen + (name,):
        raise InputError(f"dataset preset {name!r}: base must name another preset, got {base!r}"
                         + (" (a cycle)" if isinstance(base, str) else ""))
    return deep_update(_load_preset(kind, base, _seen + (name,)), data)


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
    base: dict[str, Any] = _load_preset("dataset", preset) if preset else {}
    per_mode = base.pop("modes", None) or {}
    later: dict[str, Any] = {}
    if representation:
        later = deep_update(later, {"field": {"model": _load_preset("representation", representation)}})
    if config_file:
        later = deep_update(later, read_user_yaml(config_file))
    for item in overrides or []:
        later = deep_update(later, _parse_override(item))
    later = deep_update(later, {k: v for k, v in top_level.items() if v is not None})
    mode = later.get("mode", base.get("mode", "fused"))
    unknown = sorted(set(per_mode) - set(MODE_PRESETS))
    if unknown:
        raise InputError(f"dataset preset {preset!r}: unknown mode(s) under 'modes': {', '.join(unknown)}")
    data = deep_update(deep_update(base, per_mode.get(mode) or {}), later)
    named = {o.split("=", 1)[0].strip() for o in overrides or []} | {k for k, v in top_level.items() if v is not None}
    if "seed" in named and "field.seed" not in named:
        # a seed given on the command line (--seed, --set seed=N) is the run's seed, whatever field.seed a config
        # file (e.g. a fed-back config.yaml) holds
        data = deep_update(data, {"field": {"seed": data["seed"]}})
    if mode in MODE_PRESETS:  # an unknown mode is reported by the validation below
        data = deep_update(MODE_PRESETS[mode], data)
    from pydantic import ValidationError

    try:
        cfg = RunConfig.model_validate(data)
    except ValidationError as e:
        raise InputError(_describe(e, "")) from None
    try:
        cfg.reader_options()
    except ValidationError as e:
        raise InputError(_describe(e, "dataset.options")) from None
    return cfg


def _describe(e, section: str) -> str:
    first = e.errors()[0]
    loc = ".".join([section] * bool(section) + [str(x) for x in first["loc"]])
    if not loc and first["type"] == "value_error":   # a whole-config check: its message names the keys
        return f"invalid config: {first['msg'].removeprefix('Value error, ')}"
    return f"invalid config at {loc or '<root>'}: {first['msg']} ({e.error_count()} error(s))"
