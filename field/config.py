"""Every configuration model of the field, in one torch-free module (so the run config can be typed all the way
down without importing torch). The modules that use them re-export them (``lrslam.field.tracker.TrackerConfig``
is this module's class).
"""

from __future__ import annotations

from typing import Literal


from pydantic import Field

from lrslam.config import StrictModel
from lrslam.errors import InputError

__all__ = ["Sampler", "SAEvaluation", "PoseParameterisation", "EncodingConfig", "SceneModelConfig", "PRESETS",
           "RenderConfig", "LossWeights", "TRACKING_WEIGHTS", "MAPPING_WEIGHTS", "MeshConfig", "TrackerConfig",
           "MapperConfig", "FieldSLAMConfig"]

Sampler = Literal["auto", "gather", "ebag", "grid_sample", "numba"]
SAEvaluation = Literal["materialise", "direct"]
PoseParameterisation = Literal["lie", "quat"]


class EncodingConfig(StrictModel):
    """One feature encoding (geometry or appearance).

    kind: ``"cp"`` (Eq. cp), ``"sa"`` (Six-axis, Eq. sixaxis) or ``"triplane"`` (ESLAM, Eq. triplane).
    rank: k (ignored by ``triplane``). coarse_res / fine_res: metres per grid cell of the two levels.
    channels: C per level. init_std: features start N(0, init_std) (ESLAM: 0.01).
    sampler: plane/line interpolation kernel (``auto`` = the numba kernels on CPU when available, else gather;
    see :mod:`lrslam.field.interp`).
    sa_evaluation: Six-axis only, ``materialise`` (fast) or ``direct`` (point by point; tests/benchmarks).
    """

    kind: Literal["cp", "sa", "triplane"] = "cp"
    rank: int = Field(2, gt=0)
    coarse_res: float = Field(0.24, gt=0)
    fine_res: float = Field(0.06, gt=0)
    channels: int = Field(32, gt=0)
    init_std: float = Field(0.01, ge=0)
    sampler: Sampler = "auto"
    sa_evaluation: SAEvaluation = "materialise"


_GEOMETRY = {"coarse_res": 0.24, "fine_res": 0.06, "rank": 2}
_APPEARANCE = {"coarse_res": 0.24, "fine_res": 0.03, "rank": 16}
_KINDS = {"cp-sa": ("cp", "sa"), "cp-cp": ("cp", "cp"), "sa-sa": ("sa", "sa"), "sa-cp": ("sa", "cp"),
          "triplane": ("triplane", "triplane")}
_ALIASES = {"lrslam": "cp-sa", "eslam": "triplane"}
PRESETS = tuple(_KINDS) + tuple(_ALIASES)


class SceneModelConfig(StrictModel):
    """Scene representation. Defaults: LRSLAM (paper Sec. 4.1 implementation details).

    geometry / appearance: the two encodings. hidden: MLP hidden width (16). truncation: TSDF truncation T in
    metres (ESLAM 0.06). beta_init: initial sharpness of the density ``beta * sigmoid(-beta * sdf)`` (10).
    learnable_beta: ESLAM learns it on Replica/ScanNet, fixes it on TUM.
    """

    geometry: EncodingConfig = EncodingConfig(kind="cp", **_GEOMETRY)
    appearance: EncodingConfig = EncodingConfig(kind="sa", **_APPEARANCE)
    hidden: int = Field(16, gt=0)
    truncation: float = Field(0.06, gt=0)
    beta_init: float = Field(10.0, gt=0)
    learnable_beta: bool = True

    @classmethod
    def preset(cls, name: str, **overrides) -> "SceneModelConfig":
        """A named variant: ``lrslam`` (= ``cp-sa``), ``cp-cp``, ``sa-sa``, ``sa-cp``, ``eslam`` (= ``triplane``).
        ``overrides`` replace top-level fields (e.g. ``truncation=0.1``)."""
        key = _ALIASES.get(name, name)
        if key not in _KINDS:
            raise InputError(f"unknown scene model preset {name!r}; known: {', '.join(PRESETS)}")
        kg, ka = _KINDS[key]
        return cls(geometry=EncodingConfig(kind=kg, **_GEOMETRY), appearance=EncodingConfig(kind=ka, **_APPEARANCE),
                   **overrides)


class RenderConfig(StrictModel):
    """Samples per ray (paper: N_s = 32 on Replica, 48 on real data; N_t = 8) and jitter.

    n_stratified: samples over ``[0, 1.2 d]`` (or up to the bound when d is missing). n_importance: samples in
    ``d +- 1.5 T`` (or drawn from coarse weights when d is missing). perturb: jitter samples within their
    intervals during optimisation. chunk: rays per batch when rendering whole images. colour_min_weight: query
    the appearance only at samples whose compositing weight exceeds this (0: at every sample, the paper's
    rendering; see :func:`lrslam.field.render.render_rays`).
    """

    n_stratified: int = Field(32, gt=0)
    n_importance: int = Field(8, ge=0)
    perturb: bool = True
    colour_min_weight: float = Field(0.0, ge=0.0, lt=1.0)
    chunk: int = Field(20_000, gt=0)


class LossWeights(StrictModel):
    """Loss weights (ESLAM configs). Defaults: tracking 10 / 200 / 50 / 1 / 5."""

    free_space: float = 10.0
    center: float = 200.0
    tail: float = 50.0
    depth: float = 1.0
    colour: float = 5.0


TRACKING_WEIGHTS = LossWeights()
MAPPING_WEIGHTS = LossWeights(free_space=5.0, center=200.0, tail=10.0, depth=0.1, colour=5.0)


class MeshConfig(StrictModel):
    """resolution: marching-cubes voxel in metres (ESLAM 0.01). chunk: points per field query.
    cull / cull_margin (metres): see the module doc. crop_to_observed: evaluate only around observations."""

    resolution: float = Field(0.01, gt=0)
    chunk: int = Field(262_144, gt=0)
    cull: Literal["none", "frustum", "observed"] = "frustum"
    cull_margin: float = Field(0.05, ge=0)
    crop_to_observed: bool = True


class TrackerConfig(StrictModel):
    """Tracking settings. Defaults: ESLAM on Replica (8 iterations, 2000 pixels, lr 0.001 rotation / 0.002
    translation, Adam betas (0.5, 0.999), 75-pixel border ignored, outliers > 10 x median depth error).

    lr_rot: Adam lr of the rotation parameters (quaternion units, ~ half radians; see :mod:`.poses`).
    lr_trans: Adam lr of the translation (metres). lr_final_factor: linear decay of both lrs to this fraction at
    the last iteration (1 = constant, ESLAM). max_translation / max_rotation_deg: a refined pose further than
    this from the seed counts as divergence. bound_margin: metres the camera centre may lie outside the scene
    bound (seed and result). min_rays: fewer usable rays in an iteration skip it.

    Acceptance and confidence (after the iterations, on one fixed set of ``check_rays`` rays): the loss at the
    seed and at the refined pose are compared on the same rays and jitter; with ``accept_if_better`` the
    refinement is kept only when its loss there is at most ``(1 + accept_tolerance)`` times the seed's (0: it
    must not be worse; a small tolerance keeps the refinements whose gain is within the loss noise, which
    anchor the pose to the map over many frames, and still rejects a refinement that went wrong). The refined
    pose's information (:func:`lrslam.field.tracker.pose_information`) comes from the same rays:
    ``information_rays`` is the number of rays that count as independent at saturation (neighbouring rays
    share errors) and ``information_floor_*`` a weak prior that keeps it positive definite.

    Early stop (``stop_patience`` > 0): the iterations end once the best loss (the pose tracking returns) has
    not dropped by more than ``stop_min_improvement`` (relative) for ``stop_patience`` iterations, after at
    least ``min_iters``; the later iterations could only change the answer by finding a better pose, which
    they rarely do from a good seed. 0 runs all ``iters`` (ESLAM).

    ``fixed_rays``: every iteration renders the same ``n_rays`` pixels without jitter (ESLAM draws new ones each
    iteration), so the loss is a function of the pose alone: the best pose is the best on one objective and the
    early stop sees convergence rather than sampling noise (the acceptance check keeps its own rays).

    ``n_stratified``: free-space samples per ray while tracking (None: the render settings'); once the map is
    fitted, samples in front of the surface carry ~zero rendering weight, so a pose refinement needs few of them
    (the ``d +- 1.5 T`` surface band keeps ``render.n_importance``).
    """

    iters: int = Field(8, ge=0)
    n_rays: int = Field(2000, gt=0)
    lr_rot: float = Field(0.001, ge=0)
    lr_trans: float = Field(0.002, ge=0)
    lr_final_factor: float = Field(1.0, ge=0)
    adam_betas: tuple[float, float] = (0.5, 0.999)
    parameterisation: PoseParameterisation = "quat"
    outlier_factor: float = Field(10.0, gt=0)
    ignore_edge_h: int = Field(75, ge=0)
    ignore_edge_w: int = Field(75, ge=0)
    weights: LossWeights = TRACKING_WEIGHTS
    max_translation: float = Field(0.5, gt=0)
    max_rotation_deg: float = Field(30.0, gt=0)
    bound_margin: float = Field(1.0, ge=0)
    min_rays: int = Field(16, gt=0)
    accept_if_better: bool = False
    accept_tolerance: float = Field(0.0, ge=0)
    check_weights: LossWeights | None = Field(None, description="loss weights of the acceptance check (None = "
                                              "weights; e.g. colour 0 to judge by geometry alone)")
    check_rays: int | None = Field(None, gt=0, description="rays of the acceptance / information check "
                                  "(None = n_rays)")
    information: bool = True
    information_rays: float = Field(100.0, gt=0)
    information_floor_rotation_deg: float = Field(10.0, gt=0)
    information_floor_translation: float = Field(0.2, gt=0)
    fixed_rays: bool = False
    stop_patience: int = Field(0, ge=0)
    n_stratified: int | None = Field(None, gt=0)
    stop_min_improvement: float = Field(0.01, ge=0)
    min_iters: int = Field(0, ge=0)


class MapperConfig(StrictModel):
    """Mapping settings. Defaults: ESLAM on Replica (15 iterations x 4000 pixels; first frame 1000 iterations
    at 5x learning rates; window 20; joint pose optimisation once more than 4 keyframes exist).

    lr_encoding / lr_decoder: Adam lrs of the feature lines/planes and of the MLPs + beta. lr_pose_rot /
    lr_pose_trans: window-pose lrs (ESLAM ``joint_opt_cam_lr``; rotation in quaternion units, see
    :mod:`.poses`). keyframe_pixels: keep only this many random pixels per keyframe (None = all).
    remap_iters / remap_views / remap_lr_factor: :meth:`Mapper.remap` (iterations; views sampled per
    iteration; learning-rate factor, so that a corrected surface moves within the budget).
    max_pose_step / max_pose_step_deg: divergence guard of joint mapping: a window pose that moved further than
    this in one mapping round (or left the bound by more than ``bound_margin`` m) is reverted (and counted).
    """

    iters: int = Field(15, ge=0)
    n_rays: int = Field(4000, gt=0)
    first_iters: int = Field(1000, ge=0)
    lr_first_factor: float = Field(5.0, gt=0)
    lr_encoding: float = Field(0.005, ge=0)
    lr_decoder: float = Field(0.001, ge=0)
    joint_opt: bool = True
    joint_opt_min_keyframes: int = Field(5, ge=0)
    lr_pose_rot: float = Field(0.001, ge=0)
    lr_pose_trans: float = Field(0.001, ge=0)
    pose_parameterisation: PoseParameterisation = "quat"
    window_size: int = Field(20, gt=0)
    overlap_pixels: int = Field(50, gt=0)
    weights: LossWeights = MAPPING_WEIGHTS
    keyframe_pixels: int | None = Field(None, gt=0)
    remap_iters: int = Field(30, ge=0)
    remap_views: int = Field(20, gt=0)
    remap_lr_factor: float = Field(2.0, gt=0)
    max_bad_steps: int = Field(3, gt=0)
    max_pose_step: float = Field(0.1, gt=0)
    max_pose_step_deg: float = Field(5.0, gt=0)
    bound_margin: float = Field(1.0, ge=0)


class FieldSLAMConfig(StrictModel):
    """Everything the field needs. Defaults: the paper's LRSLAM on Replica (ESLAM settings).
    device: ``"auto"`` (CUDA when available), ``"cpu"``, ``"cuda:0"`` ... seed: RNG seed (pixels, jitter,
    window selection, initial features)."""

    model: SceneModelConfig = SceneModelConfig()
    render: RenderConfig = RenderConfig()
    tracking: TrackerConfig = TrackerConfig()
    mapping: MapperConfig = MapperConfig()
    mesh: MeshConfig = MeshConfig()
    device: str = "auto"
    seed: int = Field(0, ge=0)

    @classmethod
    def cpu_small(cls, **overrides) -> "FieldSLAMConfig":
        """A CPU-sized variant (same model, fewer rays and iterations, coarser mesh) for tests and laptops.
        ``overrides`` replace top-level sections."""
        base = dict(
            render=RenderConfig(n_stratified=24, n_importance=8),
            tracking=TrackerConfig(iters=12, n_rays=400, ignore_edge_h=4, ignore_edge_w=4),
            mapping=MapperConfig(iters=15, n_rays=800, first_iters=100, window_size=8, remap_iters=20),
            mesh=MeshConfig(resolution=0.03),
            device="cpu",
        )
        return cls(**(base | overrides))
